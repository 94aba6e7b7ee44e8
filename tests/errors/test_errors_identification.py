"""F-test and the one-call identification: paper Table 1 arithmetic and order choice."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.signal import lfilter
from scipy.stats import chi2

from neuralmap.errors import f_quantile, f_statistic, identify_error_model, simulate_ar

# (row, residual, compared row, residual, extra coefficients s, coefficients k₁, printed F)
PAPER_F = [
    ("AR(1)", 0.23903, "ARMA(2,1)", 0.26454, 2, 3, -29.268),
    ("ARMA(1,1)", 0.26845, "ARMA(2,2)", 0.26453, 2, 4, 4.490),
    ("ARMA(1,2)", 0.26451, "ARMA(2,2)", 0.26453, 1, 4, -0.046),
    ("ARMA(2,1)", 0.26454, "ARMA(2,2)", 0.26453, 1, 4, 0.023),
]


@pytest.mark.parametrize("row", PAPER_F, ids=[r[0] for r in PAPER_F])
def test_f_statistic_reproduces_paper_table1(row: tuple) -> None:
    _, q0, _, q1, s, k1, printed = row
    f = f_statistic(q0, q1, n=610, n_params_small=k1 - s, n_params_large=k1)
    # the residuals are printed to 5 digits; that rounding moves F by up to ~0.03
    assert f == pytest.approx(printed, abs=0.03)


def test_f_quantile_tends_to_papers_large_n_values() -> None:
    assert f_quantile(2, 10**7) == pytest.approx(chi2.ppf(0.95, 2) / 2, rel=1e-4)
    assert round(f_quantile(2, 10**7), 2) == 3.00
    assert round(f_quantile(1, 10**7), 2) == 3.84
    assert f_quantile(2, 606) == pytest.approx(3.0108, abs=1e-3)


def test_ar1_series_chooses_ar1_with_paper_parameters() -> None:
    x = simulate_ar(610, seed=11)
    result = identify_error_model(x)
    assert result.chosen.name == "AR(1)"
    assert result.chosen.phi[0] == pytest.approx(0.5315, abs=0.07)  # ~2 standard errors
    # innovation variance of the AR(1) = σ²(1 − φ²) for σ = 1.0435 (sampling ±12 %)
    assert result.chosen.sigma2 == pytest.approx(1.0435**2 * (1 - 0.5315**2), rel=0.12)
    assert result.stationarity is not None and result.stationarity.stationary
    assert result.whiteness is not None and not result.whiteness.white
    assert result.innovation_whiteness is not None and result.innovation_whiteness.white


def test_ar1_is_chosen_most_of_the_time() -> None:
    x = simulate_ar(1000, batch=40, seed=12)
    names = [identify_error_model(s, diagnostics=False).chosen.name for s in x]
    assert names.count("AR(1)") >= 32, names


def test_ar2_and_arma11_series() -> None:
    x = simulate_ar(4000, phi=(0.5, 0.3), seed=13)
    result = identify_error_model(x)
    assert result.chosen.name == "AR(2)"
    np.testing.assert_allclose(result.chosen.phi, (0.5, 0.3), atol=0.05)
    rng = np.random.default_rng(14)
    y = lfilter([1.0, 0.6], [1.0, -0.5], rng.standard_normal(4500))[500:]  # θ = −0.6
    result = identify_error_model(y, diagnostics=False)
    assert result.chosen.name == "ARMA(1,1)"
    assert result.chosen.phi[0] == pytest.approx(0.5, abs=0.06)
    assert result.chosen.theta[0] == pytest.approx(-0.6, abs=0.06)


def test_white_series_chooses_white_noise() -> None:
    rng = np.random.default_rng(15)
    result = identify_error_model(rng.standard_normal(800))
    assert result.chosen.name == "white noise"
    assert result.whiteness is not None and result.whiteness.white


def test_report_formats() -> None:
    result = identify_error_model(simulate_ar(610, seed=16))
    md = result.to_markdown()
    assert "| order | parameters (φ; θ) | σ_a² (residual) | vs | F | F_0.95 | passes |" in md
    assert "| AR(1) |" in md and "Chosen: AR(1)" in md
    headers, rows = result.table()
    assert len(rows) == 9 and all(len(r) == len(headers) for r in rows)
    data = json.loads(json.dumps(result.to_dict()))
    assert data["chosen"]["name"] == "AR(1)"
    assert {row["order"] for row in data["table"]} >= {"AR(1)", "AR(2)", "ARMA(1,1)"}
    assert str(result) == md


def test_tensor_input_gives_the_same_table() -> None:
    import torch

    x = simulate_ar(300, seed=17)
    a = identify_error_model(x, diagnostics=False)
    b = identify_error_model(torch.from_numpy(x), diagnostics=False)
    assert a.table() == b.table()
