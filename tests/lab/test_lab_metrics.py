"""Navigation metrics on hand-built runs with known answers (closed forms and NumPy/SciPy
references): RMSE, NEES bands, divergence rules, acquisition time, χ² quantiles."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from scipy.stats import chi2

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.stats import chi2_mean_threshold, chi2_quantile
from neuralmap.lab.metrics import (
    DIVERGENCE_RULE,
    acquisition_time,
    divergence_rule,
    navigation_metrics,
    nees,
)
from neuralmap.lab.monte_carlo import FilterRun

F64 = torch.float64


def build_run() -> tuple[FilterRun, torch.Tensor]:
    """6 runs, 4 samples (last half = samples 2, 3), PCRB [20, 10, 10, 10].

    run 0: converged, err (3, 4 | 0.3, 0.4), P = diag(25, 25, 1, 1, 1)
    run 1: converged, err (-6, 8 | 0, 0), same P
    run 2: diverged by the PCRB rule (e = 100 > 5 x 10; 3σ bound large)
    run 3: diverged by the 9σ rule (e = 20 < 50; P = I: 9 sqrt(2) = 12.7 < 20)
    run 4: off-map (excluded), run 5: unhealthy (a numerical failure, not a divergence), err 0
    """
    n, k1 = 6, 4
    err = torch.zeros(n, k1, 5, dtype=F64)
    err[0, :, :] = torch.tensor([3.0, 4.0, 0.0, 0.3, 0.4], dtype=F64)
    err[1, :, :2] = torch.tensor([-6.0, 8.0], dtype=F64)
    err[2, :, :2] = torch.tensor([60.0, 80.0], dtype=F64)
    err[3, :, :2] = torch.tensor([12.0, 16.0], dtype=F64)
    err[4, :, :2] = torch.tensor([1000.0, 0.0], dtype=F64)
    err[0:2, 0] *= 10.0  # NEES of sample 0 far above the band
    P = torch.diag(torch.tensor([25.0, 25.0, 1.0, 1.0, 1.0], dtype=F64)).expand(n, k1, 5, 5).clone()
    P[2] = torch.eye(5, dtype=F64) * 1e4
    P[3] = torch.eye(5, dtype=F64)
    off_map = torch.tensor([False, False, False, False, True, False])
    healthy = torch.tensor([True, True, True, True, True, False])
    run = FilterRun(
        method="hand", t=torch.arange(k1, dtype=F64), err=err, P=P,
        nis=torch.zeros(n, k1, dtype=F64), residual=torch.zeros(n, k1, dtype=F64),
        updated=torch.ones(n, k1, dtype=torch.bool), est_on_map=~off_map[:, None].expand(n, k1),
        off_map=off_map, healthy=healthy,
    )
    return run, torch.tensor([20.0, 10.0, 10.0, 10.0], dtype=F64)


def test_known_answers() -> None:
    run, pcrb = build_run()
    m = navigation_metrics(run, pcrb)
    assert m["n_runs"] == 6 and m["n_off_map"] == 1 and m["n_included"] == 5
    assert m["diverged"] == [False, False, True, True, False, False]
    assert m["n_diverged"] == 2 and m["n_converged"] == 2 and m["n_unhealthy"] == 1
    assert m["divergence_rate"] == pytest.approx(2 / 5)
    assert m["numerical_failure_rate"] == pytest.approx(1 / 5)
    assert m["rmse_pos_converged_m"] == pytest.approx(math.sqrt((25 + 100) / 2))
    assert m["rmse_pos_m"] == pytest.approx(math.sqrt((25 + 100 + 1e4 + 400 + 0) / 5))
    assert m["final_pos_m"] == pytest.approx(m["rmse_pos_m"])
    assert m["rmse_vel_mps"] == pytest.approx(math.sqrt(0.25 / 5))
    assert m["rmse_vel_converged_mps"] == pytest.approx(math.sqrt(0.25 / 2))
    # 1σ about the mean, ddof = 1, over runs 0, 1 and samples 2, 3
    ex, ey = np.array([3.0, 3.0, -6.0, -6.0]), np.array([4.0, 4.0, 8.0, 8.0])
    assert m["sigma_pos_m"] == pytest.approx(math.sqrt(ex.var(ddof=1) + ey.var(ddof=1)))
    vx, vy = np.array([0.3, 0.3, 0.0, 0.0]), np.array([0.4, 0.4, 0.0, 0.0])
    assert m["sigma_vel_mps"] == pytest.approx(math.sqrt(vx.var(ddof=1) + vy.var(ddof=1)))
    assert m["pcrb_pos_m"] == pytest.approx(10.0) and m["pcrb_pos_final_m"] == 10.0
    assert m["pcrb_ratio_converged"] == pytest.approx(math.sqrt(62.5) / 10.0)
    assert m["pcrb_ratio_all"] == pytest.approx(m["rmse_pos_m"] / 10.0)
    # time-averaged NEES over the converged runs 0, 1 and steps 1..3: (1.25 + 4) / 2
    assert m["nees_time_avg"] == pytest.approx(2.625)
    lo6, hi6 = chi2.ppf(0.025, 30) / 6, chi2.ppf(0.975, 30) / 6
    assert m["nees_time_band"] == pytest.approx([lo6, hi6])
    # runs band: per-run averages 1.25 and 4 -> s = 1.9445, 5 ± 1.96 s / √2
    half = 1.959963984540054 * float(np.std([1.25, 4.0], ddof=1)) / math.sqrt(2)
    assert m["nees_time_band_runs"] == pytest.approx([5 - half, 5 + half])
    assert m["nees_time_in_band"] is bool(5 - half <= 2.625 <= 5 + half)
    # curves over the K+1 samples
    assert m["rmse_pos_converged_curve"][1] == pytest.approx(math.sqrt(62.5))
    assert m["rmse_pos_converged_curve"][0] == pytest.approx(math.sqrt(6250.0))
    assert len(m["rmse_pos_curve"]) == len(m["rmse_vel_curve"]) == 4
    # NEES: run 0 → 1 + 0.25, run 1 → 4; mean 2.625 inside the χ²(10)/2 band, sample 0 ×100
    lo, hi = chi2.ppf(0.025, 10) / 2, chi2.ppf(0.975, 10) / 2
    assert m["nees_band"] == pytest.approx([lo, hi])
    assert m["nees_curve"][1:] == pytest.approx([2.625] * 3)
    assert m["nees_curve"][0] == pytest.approx(262.5)
    assert m["nees_in_band"] == pytest.approx(3 / 4)
    json.dumps(m, allow_nan=False)  # strict JSON, no NaN anywhere


def test_divergence_factors_change_the_verdict() -> None:
    run, pcrb = build_run()
    loose = navigation_metrics(run, pcrb, pcrb_factor=20.0, divergence_sigma=15.0)
    assert loose["diverged"] == [False, False, False, False, False, False]
    assert "20x the final PCRB" in loose["divergence_rule"]
    assert "15x the filter's own final 1-sigma" in loose["divergence_rule"]
    tight = navigation_metrics(run, pcrb, pcrb_factor=0.1, divergence_sigma=15.0)
    assert tight["diverged"] == [True, True, True, True, False, False]
    assert tight["n_unhealthy"] == 1
    assert divergence_rule() == DIVERGENCE_RULE.format(pcrb="5", sigma="9")


def test_empty_subsets_give_none_not_nan() -> None:
    run, pcrb = build_run()
    run.off_map[:] = True
    m = navigation_metrics(run, pcrb)
    assert m["n_included"] == 0 and m["n_off_map"] == 6
    for key in ("rmse_pos_m", "rmse_pos_converged_m", "rmse_vel_mps", "sigma_pos_m",
                "divergence_rate", "nees_in_band", "pcrb_ratio_all", "pcrb_ratio_converged",
                "nees_time_avg", "final_pos_m"):
        assert m[key] is None, key
    assert m["rmse_pos_curve"] == [None] * 4
    json.dumps(m, allow_nan=False)


def test_nonfinite_runs_are_excluded_and_counted() -> None:
    run, pcrb = build_run()
    run.err[1, 2, 0] = float("nan")
    m = navigation_metrics(run, pcrb)
    assert m["n_nonfinite"] == 1 and m["n_included"] == 4
    assert m["rmse_pos_converged_m"] == pytest.approx(5.0)
    json.dumps(m, allow_nan=False)


def test_nees_function_against_explicit_inverse() -> None:
    gen = torch.Generator().manual_seed(0)
    A = torch.randn(7, 5, 5, generator=gen, dtype=F64)
    P = A @ A.transpose(1, 2) + torch.eye(5, dtype=F64)
    e = torch.randn(7, 5, generator=gen, dtype=F64)
    ref = torch.einsum("bi,bij,bj->b", e, torch.linalg.inv(P), e)
    assert torch.allclose(nees(e, P), ref, rtol=1e-10)
    P[3] = -torch.eye(5, dtype=F64)
    assert torch.isnan(nees(e, P)[3]) and torch.isfinite(nees(e, P)[[0, 1, 2, 4]]).all()


@pytest.mark.parametrize("dof", [10, 50, 500, 5000])
def test_chi2_quantiles(dof: int) -> None:
    for p in (0.025, 0.975, 0.99999):
        assert chi2_quantile(p, dof) == pytest.approx(chi2.ppf(p, dof), rel=1e-12)
        assert chi2_mean_threshold(p, dof) == pytest.approx(chi2.ppf(p, dof) / dof, rel=1e-12)


def test_acquisition_time() -> None:
    """First time from which the error stays within ``factor`` × the bound (by hand)."""
    bound = torch.ones(5)
    err = torch.tensor([[9.0, 9.0, 1.0, 1.0, 1.0], [9.0, 1.0, 9.0, 1.0, 1.0],
                        [1.0, 1.0, 1.0, 1.0, 9.0]])
    t = acquisition_time(err, bound, factor=3.0, dt=2.0)
    assert t.tolist() == [4.0, 6.0, float("inf")]


def test_bad_pcrb_shape() -> None:
    run, _ = build_run()
    with pytest.raises(NeuralMapError, match=r"\(K\+1,\)"):
        navigation_metrics(run, torch.ones(3))
    with pytest.raises(NeuralMapError, match="pcrb_factor"):
        navigation_metrics(run, torch.ones(4), pcrb_factor=0.0)


def test_estimate_leaving_the_map_counts_as_diverged_not_excluded() -> None:
    run, pcrb = build_run()
    run.est_on_map[0, 2] = False  # run 0's estimate wandered off the tile at one step
    m = navigation_metrics(run, pcrb)
    assert m["diverged"] == [True, False, True, True, False, False]
    assert m["n_included"] == 5 and m["n_estimate_left_map"] == 1
    assert m["divergence_rate"] == pytest.approx(3 / 5)
    assert "estimate left the map" in m["divergence_rule"]


def test_nees_over_all_runs_is_reported_beside_converged() -> None:
    run, pcrb = build_run()
    m = navigation_metrics(run, pcrb)
    # by hand: NEES per run (samples 1..3) — run 0: 1.25, run 1: 4, run 2: 1e4/1e4 = 1,
    # run 3: 400, run 5: 0 -> mean 81.25 at samples 1..3 (sample 0 larger still), far above
    # the χ²(25)/5 band [2.6, 8.1]: no sample is in the band
    assert chi2.ppf(0.975, 25) / 5 < 81.25
    assert m["nees_in_band_all"] == 0.0
    run.err[3] = 0.0  # without the 9σ outlier: mean (1.25 + 4 + 1 + 0 + 0) / 5 = 1.25 < 2.6
    assert navigation_metrics(run, pcrb)["nees_in_band_all"] == 0.0
    run.err[3, :, :2] = torch.tensor([3.0, 4.0], dtype=F64)  # NEES 25: mean 6.25 in band
    assert chi2.ppf(0.025, 25) / 5 < 6.25 < chi2.ppf(0.975, 25) / 5
    assert navigation_metrics(run, pcrb)["nees_in_band_all"] == pytest.approx(3 / 4)
