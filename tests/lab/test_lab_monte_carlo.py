"""Monte Carlo runner: end to end on the tiny scenario, FilterPy reference, bad input."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch
from filterpy.kalman import ExtendedKalmanFilter

from neuralmap.dem.synthetic import synthetic_tile
from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.metrics import navigation_metrics
from neuralmap.lab.monte_carlo import run_filter, run_monte_carlo
from neuralmap.lab.scenario import load_scenario, scenario_tile
from neuralmap.lab.simulator import simulate
from neuralmap.linearize.factory import make_linearizer
from neuralmap.tan.model import transition_matrix

F64 = torch.float64


def _filterpy_states(truth, scenario, tile, runs: list[int]) -> np.ndarray:  # noqa: ANN001
    """FilterPy's ExtendedKalmanFilter, one run at a time, on the bilinear DEM (scipy).

    Innovation ``(ĥ − h_map(p̂)) − h_radar`` with ``H = [−h_x, −h_y, 1, 0, 0]`` (SEEDS 004);
    slopes by central differences of the bilinear interpolant (exact inside a cell).
    Returns ``(len(runs), K + 1, 5)`` filter states.
    """
    from filterpy.kalman import ExtendedKalmanFilter
    from scipy.interpolate import RegularGridInterpolator

    ny, nx = tile.shape
    ys = tile.origin[1] + np.arange(ny) * tile.spacing[1]
    xs = tile.origin[0] + np.arange(nx) * tile.spacing[0]
    interp = RegularGridInterpolator((ys, xs), tile.heights, method="linear")
    F = np.eye(5)
    F[0, 3] = F[1, 4] = scenario.dt
    out = np.zeros((len(runs), truth.n_steps + 1, 5))
    d = 1e-3
    for row, i in enumerate(runs):
        ekf = ExtendedKalmanFilter(dim_x=5, dim_z=1)
        ekf.x = np.zeros((5, 1))
        ekf.P = np.diag(scenario.P0_diag).astype(float)
        ekf.F, ekf.Q = F, np.diag(scenario.Q_diag)
        ekf.R = np.array([[scenario.R_m2 + scenario.fit_variance_m2]])
        for k in range(1, truth.n_steps + 1):
            ekf.predict()
            px, py, ph = truth.ins_pos[i, k].tolist()
            p = np.array([px - ekf.x[0, 0], py - ekf.x[1, 0]])
            pts = np.array([[p[1], p[0]], [p[1], p[0] + d], [p[1], p[0] - d],
                            [p[1] + d, p[0]], [p[1] - d, p[0]]])
            v = interp(pts)
            H = np.array([[-(v[1] - v[2]) / (2 * d), -(v[3] - v[4]) / (2 * d), 1.0, 0.0, 0.0]])
            ekf.update(np.array([[-float(truth.radar[i, k])]]), lambda x, H=H: H,
                       lambda x, ph=ph, h=v[0]: np.array([[-(ph - x[2, 0]) + h]]))
            out[row, k] = ekf.x[:, 0]
    return out


@pytest.fixture(scope="module")
def tiny():
    scenario = load_scenario("tiny")
    return scenario, scenario_tile(scenario)


def test_run_monte_carlo_converges_on_the_tiny_scenario(tiny, capsys) -> None:
    scenario, tile = tiny
    methods = {
        "bilinear": make_linearizer("bilinear", tile=tile),
        "nine_point": make_linearizer("nine_point", tile=tile),
    }
    truth, runs = run_monte_carlo(scenario, methods, n_runs=64, seed=5, progress=True, tile=tile)
    captured = capsys.readouterr()
    # the progress ran: a bar on stderr on a terminal, plain lines on stdout otherwise
    assert "Monte Carlo" in captured.err + captured.out
    assert list(runs) == ["bilinear", "nine_point"]
    n, k1 = 64, scenario.n_steps + 1
    initial_rms = math.sqrt(2.0) * scenario.init_pos_sigma_m
    for run in runs.values():
        assert run.err.shape == (n, k1, 5) and run.P.shape == (n, k1, 5, 5)
        assert run.nis.shape == (n, k1) and run.off_map.shape == (n,)
        assert torch.equal(run.err[:, 0], truth.ins_error[:, 0])  # prior: δX̂ = 0
        assert torch.allclose(run.P[:, 0], torch.diag(torch.tensor(scenario.P0_diag, dtype=F64)))
        assert not run.updated[:, 0].any() and run.updated[:, 1:].all()
        assert torch.isnan(run.nis[:, 0]).all() and torch.isfinite(run.nis[:, 1:]).all()
        assert run.healthy.all() and not run.off_map.any()
        # estimate = truth + err
        est = run.estimate_xy(truth)
        corrected = truth.ins_pos[..., :2] - (truth.ins_error[..., :2] - run.err[..., :2])
        assert torch.allclose(est, corrected)
        pcrb_pos = torch.full((k1,), 5.0, dtype=F64)
        m = navigation_metrics(run, pcrb_pos)
        json.dumps(m, allow_nan=False)
        assert m["n_off_map"] == 0
        assert m["n_included"] == n
    # the batched filter equals an independent FilterPy EKF, run by run (bilinear map)
    lin = make_linearizer("bilinear", tile=tile, variance="zero")
    exact = run_filter(truth, lin, scenario, method="bilinear0")
    ref = _filterpy_states(truth, scenario, tile, runs=[0, 7, 31])
    est = truth.ins_error[[0, 7, 31]] - exact.err[[0, 7, 31]]
    np.testing.assert_allclose(est.numpy(), ref, rtol=0, atol=1e-6)
    assert initial_rms > 0
    # both methods saw the same truth but differ in their estimates
    assert not torch.equal(runs["bilinear"].err, runs["nine_point"].err)


def test_run_filter_matches_filterpy_ekf(tiny) -> None:
    """Per-run textbook float64 EKF (FilterPy) with z = radar, h(x) = predicted clearance."""
    scenario, tile = tiny
    scenario = dataclasses.replace(scenario, fit_variance_m2=2.0)
    truth = simulate(scenario, tile, n_runs=3, seed=9)
    lin = make_linearizer("bilinear", tile=tile)
    run = run_filter(truth, lin, scenario)
    F = transition_matrix(scenario.dt).numpy()
    for i in range(truth.n_runs):
        ekf = ExtendedKalmanFilter(dim_x=5, dim_z=1)
        ekf.x = np.zeros((5, 1))
        ekf.P = np.diag(scenario.P0_diag)
        ekf.F = F
        ekf.Q = np.diag(scenario.Q_diag)
        for k in range(1, truth.n_steps + 1):
            ins = truth.ins_pos[i, k].numpy()
            ekf.predict()

            def linearise(x: np.ndarray, ins: np.ndarray = ins):
                p_hat = torch.tensor((ins[:2] - x[:2, 0])[None])
                return lin(p_hat)

            def hx(x: np.ndarray, ins: np.ndarray = ins) -> np.ndarray:
                return np.array([[ins[2] - x[2, 0] - float(linearise(x).height[0])]])

            def jacobian(x: np.ndarray) -> np.ndarray:
                sx, sy = linearise(x).slope[0].tolist()
                return np.array([[sx, sy, -1.0, 0.0, 0.0]])  # ∂h(x)/∂x = −H

            R = scenario.R_m2 + scenario.fit_variance_m2 + float(linearise(ekf.x).variance[0])
            ekf.update(np.array([[float(truth.radar[i, k])]]), jacobian, hx, R=np.array([[R]]))
            err_ref = truth.ins_error[i, k].numpy() - ekf.x[:, 0]
            assert np.allclose(run.err[i, k].numpy(), err_ref, rtol=1e-9, atol=1e-8), (i, k)
            assert np.allclose(run.P[i, k].numpy(), ekf.P, rtol=1e-9, atol=1e-9), (i, k)
            nis_ref = float(ekf.y[0, 0] ** 2 / ekf.S[0, 0])
            assert float(run.nis[i, k]) == pytest.approx(nis_ref, rel=1e-8)


def test_map_of_another_tile_is_refused(tiny) -> None:
    scenario, tile = tiny
    other = synthetic_tile((96, 96), 30.0, seed=99)
    truth = simulate(scenario, tile, n_runs=2, seed=0)
    with pytest.raises(NeuralMapError, match="fingerprint"):
        run_filter(truth, make_linearizer("bilinear", tile=other), scenario, method="x")
    with pytest.raises(NeuralMapError, match="fingerprint"):
        run_monte_carlo(scenario, {"x": make_linearizer("bilinear", tile=other)}, n_runs=2,
                        seed=0, progress=False, tile=tile)
    with pytest.raises(NeuralMapError, match="methods"):
        run_monte_carlo(scenario, {}, n_runs=2, seed=0, progress=False, tile=tile)


def test_runs_that_leave_the_map_are_flagged_and_excluded(tiny) -> None:
    scenario, tile = tiny
    s = dataclasses.replace(scenario, duration_s=60.0, start_spread_m=300.0)
    truth, runs = run_monte_carlo(s, {"bilinear": make_linearizer("bilinear", tile=tile)},
                                  n_runs=40, seed=1, progress=False, tile=tile)
    run = runs["bilinear"]
    left = ~truth.on_map.all(dim=1)
    assert left.any() and (~left).any()  # some runs leave, some stay
    assert torch.equal(run.off_map, left)  # only the truth leaving excludes a run
    assert torch.isfinite(run.err).all() and torch.isfinite(run.P).all()
    m = navigation_metrics(run, torch.full((s.n_steps + 1,), 5.0, dtype=F64))
    assert m["n_off_map"] == int(run.off_map.sum()) and m["n_included"] == 40 - m["n_off_map"]
    json.dumps(m, allow_nan=False)


def test_float32_run(tiny) -> None:
    scenario, tile = tiny
    lin = make_linearizer("bilinear", tile=tile, dtype=torch.float32)
    truth, runs = run_monte_carlo(scenario, {"bilinear": lin}, n_runs=8, seed=2,
                                  progress=False, dtype=torch.float32, tile=tile)
    run = runs["bilinear"]
    assert run.err.dtype == torch.float32 and torch.isfinite(run.err).all()
    ref = run_filter(simulate(scenario, tile, n_runs=8, seed=2),
                     make_linearizer("bilinear", tile=tile), scenario)
    assert torch.allclose(run.err[:, :, :2].double(), ref.err[:, :, :2], atol=0.5)
