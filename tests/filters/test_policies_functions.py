"""The pure weight/factor functions of the update policies against the papers' formulas.

Values at and between the breakpoints are computed by hand from SEEDS 002 (IGG-III,
Yang's adaptive factor, Sage-Husa's fading weight) and SEEDS 003 (innovation inflation,
quality memberships), and Huber's weight ``min(1, k/ṽ)``.
"""

from __future__ import annotations

import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.policies import (
    IGG3,
    ChiSquareGate,
    Huber,
    InnovationInflation,
    QualityIndicator,
    QualityR,
    RobustAdaptive,
    SageHusa,
    VariationalAdaptive,
    YangAdaptive,
    chi_square_threshold,
    huber_weights,
    igg3_weights,
    innovation_inflation_factor,
    quality_factor,
    quality_membership,
    sage_husa_weight,
    yang_factor,
)

D = torch.float64


def test_igg3_weights_at_and_between_breakpoints() -> None:
    v = torch.tensor([0.0, 1.0, 1.5, 2.0, 3.0, 4.5, 5.0, -3.0], dtype=D)
    w = igg3_weights(v, 1.5, 4.5)
    expected = [
        1.0, 1.0, 1.0,                      # ṽ ≤ k0
        (1.5 / 2.0) * (2.5 / 3.0) ** 2,     # (k0/ṽ)((k1−ṽ)/(k1−k0))²
        (1.5 / 3.0) * (1.5 / 3.0) ** 2,
        0.0,                                # ṽ = k1: the taper reaches 0
        0.0,                                # ṽ > k1
        (1.5 / 3.0) * (1.5 / 3.0) ** 2,     # |ṽ|
    ]
    torch.testing.assert_close(w, torch.tensor(expected, dtype=D), rtol=1e-15, atol=0)
    # continuous at k0 (from above)
    assert float(igg3_weights(torch.tensor(1.5 + 1e-9, dtype=D), 1.5, 4.5)) == pytest.approx(
        1.0, abs=1e-8)


def test_yang_factor_three_and_two_segments() -> None:
    d = torch.tensor([0.0, 0.5, 1.0, 2.0, 2.5, 3.0, 4.0], dtype=D)
    a = yang_factor(d, 1.0, 3.0, floor=1e-3)
    expected = [1.0, 1.0, 1.0, 0.5 * 0.5**2, 0.4 * 0.25**2, 1e-3, 1e-3]
    torch.testing.assert_close(a, torch.tensor(expected, dtype=D), rtol=1e-15, atol=0)
    a2 = yang_factor(d, 1.0, segments=2)
    torch.testing.assert_close(
        a2, torch.tensor([1.0, 1.0, 1.0, 0.5, 0.4, 1 / 3, 0.25], dtype=D), rtol=1e-15, atol=0
    )


def test_huber_and_inflation_and_sage_husa_weights() -> None:
    v = torch.tensor([0.0, 1.0, 1.345, 2.69], dtype=D)
    torch.testing.assert_close(huber_weights(v, 1.345),
                               torch.tensor([1.0, 1.0, 1.0, 0.5], dtype=D))
    lam = torch.tensor([0.5, 1.2, 2.4, 6.0], dtype=D)
    torch.testing.assert_close(innovation_inflation_factor(lam, 1.2),
                               torch.tensor([1.0, 1.0, 2.0, 5.0], dtype=D))
    k = torch.tensor([0, 1, 2, 1000])
    d = sage_husa_weight(0.9, k)
    expected = [1.0, 0.1 / (1 - 0.81), 0.1 / (1 - 0.729), 0.1]
    torch.testing.assert_close(d, torch.tensor(expected, dtype=D), rtol=1e-14, atol=0)


def test_quality_membership_and_factor() -> None:
    pdop = torch.tensor([1.0, 2.0, 4.0, 6.0, 30.0], dtype=D)
    mu = quality_membership(pdop, 2.0, 6.0, cap=4.0)
    torch.testing.assert_close(mu, torch.tensor([0.0, 0.0, 0.5, 1.0, 4.0], dtype=D))
    sats = torch.tensor([12.0, 10.0, 7.0, 4.0], dtype=D)  # decreasing quality indicator
    torch.testing.assert_close(quality_membership(sats, 10.0, 4.0),
                               torch.tensor([0.0, 0.0, 0.5, 1.0], dtype=D))
    mus = torch.tensor([[0.0, 0.0], [1.0, 0.5]], dtype=D)
    rho = quality_factor(mus, torch.tensor([0.3, 0.4], dtype=D))
    torch.testing.assert_close(rho, torch.tensor([1.0, 1.0 + 0.3 + 0.2], dtype=D))


def test_chi_square_threshold_is_scipy_quantile() -> None:
    assert chi_square_threshold(0.99, 1) == pytest.approx(6.634896601021214, rel=1e-12)
    assert chi_square_threshold(0.95, 2) == pytest.approx(5.991464547107979, rel=1e-12)


@pytest.mark.parametrize(
    "make",
    [
        lambda: IGG3(3.0, 2.0),
        lambda: IGG3(2.0, 2.0),
        lambda: IGG3(-1.0, 2.0),
        lambda: YangAdaptive(3.0, 1.0),
        lambda: YangAdaptive(1.0, 3.0, segments=4),
        lambda: YangAdaptive(1.0, 3.0, floor=0.0),
        lambda: RobustAdaptive(k0=2.0, k1=1.0),
        lambda: RobustAdaptive(c0=3.0, c1=3.0),
        lambda: SageHusa(b=1.0),
        lambda: SageHusa(b=0.0),
        lambda: SageHusa(b=0.9, R_min=0.0),
        lambda: SageHusa(b=0.9, R_min=-1.0),
        lambda: SageHusa(b=0.9, R_max=0.0),
        lambda: SageHusa(b=0.9, R_min=10.0, R_max=1.0),
        lambda: InnovationInflation(0.0),
        lambda: ChiSquareGate(1.0),
        lambda: Huber(0.0),
        lambda: VariationalAdaptive(iterations=0),
        lambda: VariationalAdaptive(rho=1.5),
        lambda: VariationalAdaptive(tau=-1.0),
        lambda: QualityR([]),
        lambda: QualityR([QualityIndicator("pdop", 2.0, 2.0)]),
        lambda: QualityR([QualityIndicator("pdop", 2.0, 6.0, weight=-0.1)]),
        lambda: igg3_weights(torch.zeros(1), 2.0, 1.0),
        lambda: yang_factor(torch.zeros(1), 2.0, 1.0),
    ],
)
def test_bad_parameters_raise(make) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(NeuralMapError):
        make()


def test_quality_indicator_lengths_are_checked() -> None:
    q = QualityR.gnss()
    with pytest.raises(NeuralMapError, match="columns"):
        q.set_quality(torch.ones(5, 3))
    with pytest.raises(NeuralMapError, match="missing"):
        q.set_quality({"pdop": torch.ones(5)})
    with pytest.raises(NeuralMapError, match="same length"):
        q.set_quality({"pdop": torch.ones(5), "fix_ratio": torch.ones(4),
                       "satellites": torch.ones(5), "sigma_m": torch.ones(5)})
