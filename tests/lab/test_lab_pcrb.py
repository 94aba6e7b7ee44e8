"""Posterior Cramér-Rao bound: equals the Kalman covariance in linear-Gaussian cases.

References: an independent float64 NumPy Riccati recursion (predict, then Joseph update)
and FilterPy's KalmanFilter; closed form on a plane terrain (constant slope → time-
invariant H). Tolerance 1e-10 relative.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from filterpy.kalman import KalmanFilter

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.filters import BatchedEKF
from neuralmap.lab.pcrb import (
    pcrb,
    pcrb_position,
    pcrb_recursion,
    terrain_information,
)
from neuralmap.tan.model import transition_matrix
from neuralmap.terrain.base import TerrainModel
from neuralmap.terrain.grid import GridTerrain

F64 = torch.float64


def _riccati(P0: np.ndarray, F: np.ndarray, Q: np.ndarray, H: np.ndarray, R: np.ndarray,
             steps: int, skip: set[int] = frozenset()) -> np.ndarray:
    """Kalman covariances P_0 … P_K: predict then (Joseph) update at steps 1 … K."""
    out = [P0]
    P = P0
    eye = np.eye(P0.shape[0])
    for k in range(1, steps + 1):
        P = F @ P @ F.T + Q
        if k not in skip:
            S = H @ P @ H.T + R
            K = np.linalg.solve(S, H @ P).T
            A = eye - K @ H
            P = A @ P @ A.T + K @ R @ K.T
        out.append(P)
    return np.stack(out)


def _rel_err(a: torch.Tensor, b: np.ndarray) -> float:
    b_t = torch.as_tensor(b, dtype=F64)
    return float((a - b_t).abs().max() / b_t.abs().max())


def test_recursion_equals_kalman_covariance_linear_gaussian() -> None:
    rng = np.random.default_rng(0)
    n, m, steps = 5, 2, 60
    F = np.eye(n) + 0.2 * rng.standard_normal((n, n))
    F /= max(1.0, np.abs(np.linalg.eigvals(F)).max())
    A = rng.standard_normal((n, n))
    Q = 0.3 * A @ A.T / n
    B = rng.standard_normal((n, n))
    P0 = 40.0 * B @ B.T / n + np.eye(n)
    H = rng.standard_normal((m, n))
    R = np.array([[2.0, 0.3], [0.3, 1.0]])
    info = H.T @ np.linalg.solve(R, H)
    bound = pcrb_recursion(torch.tensor(P0), torch.tensor(F), torch.tensor(Q),
                           torch.tensor(info).expand(steps, n, n))
    assert bound.shape == (steps + 1, n, n) and bound.dtype == F64
    assert _rel_err(bound, _riccati(P0, F, Q, H, R, steps)) < 1e-10
    # and FilterPy's Kalman filter covariance (Joseph form) as a second reference
    kf = KalmanFilter(dim_x=n, dim_z=m)
    kf.F, kf.Q, kf.H, kf.R, kf.P = F, Q, H, R, P0.copy()
    ref = [P0]
    for _ in range(steps):
        kf.predict()
        kf.update(np.zeros((m, 1)))
        ref.append(kf.P.copy())
    assert _rel_err(bound, np.stack(ref)) < 1e-10


def test_recursion_matches_batched_ekf_and_options() -> None:
    n, steps = 5, 40
    F = transition_matrix(1.0).numpy()
    Q = np.diag([1.0, 1.0, 1.0, 0.01, 0.01])
    P0 = np.diag([1e4, 1e4, 100.0, 1.0, 1.0])
    H = np.array([[-0.1, 0.05, 1.0, 0.0, 0.0]])
    R = np.array([[100.0]])
    info = torch.tensor(H.T @ H / 100.0).expand(steps, n, n)
    bound = pcrb_recursion(torch.tensor(P0), torch.tensor(F), torch.tensor(Q), info)
    ekf = BatchedEKF(torch.zeros(1, n, dtype=F64), torch.tensor(P0))
    for k in range(1, steps + 1):
        ekf.predict(torch.tensor(F), torch.tensor(Q))
        ekf.update(torch.zeros(1), torch.tensor(H[0]), 100.0)
        assert float((ekf.P[0] - bound[k]).abs().max() / bound[k].abs().max()) < 1e-10
    # a measurement at step 0 too (initial_info), and per-step F/Q
    b0 = pcrb_recursion(torch.tensor(P0), torch.tensor(F).expand(steps, n, n),
                        torch.tensor(Q).expand(steps, n, n), info,
                        initial_info=torch.tensor(H.T @ H / 100.0))
    P_upd = _riccati(P0, np.eye(n), np.zeros((n, n)), H, R, 1)[1]  # update only
    assert _rel_err(b0[0], P_upd) < 1e-12
    # singular prior (a perfectly known velocity) is fine in covariance form
    P0s = P0.copy()
    P0s[3, 3] = 0.0
    bs = pcrb_recursion(torch.tensor(P0s), torch.tensor(F), torch.tensor(Q), info)
    assert _rel_err(bs, _riccati(P0s, F, Q, H, R, steps)) < 1e-10


def _plane_tile(a: float, b: float) -> DemTile:
    ny, nx, d = 40, 60, 50.0
    x = np.arange(nx) * d
    y = np.arange(ny) * d
    heights = 300.0 + a * x[None, :] + b * y[:, None]
    return DemTile(heights=heights, spacing=(d, d), origin=(0.0, 0.0), name="plane")


def _straight_truth(N: int, steps: int, dt: float, *, seed: int = 0) -> SimpleNamespace:
    gen = torch.Generator().manual_seed(seed)
    start = torch.stack([200.0 + 300.0 * torch.rand(N, generator=gen, dtype=F64),
                         300.0 + 1000.0 * torch.rand(N, generator=gen, dtype=F64)], -1)
    t = torch.arange(steps + 1, dtype=F64) * dt
    pos = torch.zeros(N, steps + 1, 3, dtype=F64)
    pos[..., 0] = start[:, None, 0] + 40.0 * t
    pos[..., 1] = start[:, None, 1] + 5.0 * t
    pos[..., 2] = 2000.0
    return SimpleNamespace(t=t, pos=pos, on_map=torch.ones(N, steps + 1, dtype=torch.bool))


def _filter_scenario(dt: float) -> SimpleNamespace:
    return SimpleNamespace(dt=dt, P0_diag=[1e4, 1e4, 100.0, 4.0, 4.0],
                           Q_diag=[1.0, 1.0, 1.0, 0.01, 0.01], R_m2=90.0, fit_variance_m2=10.0)


@pytest.mark.parametrize("method", ["bilinear", "bicubic"])
def test_plane_terrain_equals_closed_form(method: str) -> None:
    a, b, dt, steps = 0.12, -0.07, 1.0, 50
    terrain = GridTerrain(_plane_tile(a, b), method=method)
    truth = _straight_truth(30, steps, dt)
    scen = _filter_scenario(dt)
    bound = pcrb(truth, scen, terrain, model="filter")
    H = np.array([[-a, -b, 1.0, 0.0, 0.0]])
    ref = _riccati(np.diag(scen.P0_diag), transition_matrix(dt).numpy(), np.diag(scen.Q_diag),
                   H, np.array([[100.0]]), steps)  # R = R_m2 + fit_variance_m2
    assert bound.shape == (steps + 1, 5, 5)
    assert _rel_err(bound, ref) < 1e-10
    pos = pcrb_position(bound)
    np.testing.assert_allclose(pos.numpy(), np.sqrt(ref[:, 0, 0] + ref[:, 1, 1]), rtol=1e-10)
    # a plane observes only the slope direction: the across-slope variance is never reduced
    g = torch.tensor([a, b], dtype=F64) / (a * a + b * b) ** 0.5
    along = torch.einsum("i,kij,j->k", g, bound[:, :2, :2], g)
    across = bound[:, 0, 0] + bound[:, 1, 1] - along
    assert float(along[-1]) < 0.7 * float(along[0]) and float(across[-1]) > float(across[0])


def test_truth_model_fields_and_off_map_steps() -> None:
    a, b, dt, steps = 0.1, 0.2, 2.0, 20
    terrain = GridTerrain(_plane_tile(a, b), method="bilinear")
    truth = _straight_truth(12, steps, dt)
    truth.on_map[:, 7] = False  # nobody measures at step 7
    truth.on_map[:6, 3] = False  # half of them at step 3: the mean over the rest is the same
    sig = [30.0, 30.0, 5.0, 0.5, 0.5]
    qt = [0.5, 0.5, 0.2, 0.003, 0.003]
    scen = SimpleNamespace(dt=dt, P0_diag=[1.0] * 5, Q_diag=[1.0] * 5, R_m2=1.0,
                           altimeter_sigma_m=8.0, init_error_sigma=lambda: sig,
                           truth_process_noise=lambda: qt)
    bound = pcrb(truth, scen, terrain)  # model="truth"
    H = np.array([[-a, -b, 1.0, 0.0, 0.0]])
    ref = _riccati(np.diag(np.square(sig)), transition_matrix(dt).numpy(), np.diag(qt), H,
                   np.array([[64.0]]), steps, skip={7})
    assert _rel_err(bound, ref) < 1e-10
    # R override, and a run selection that removes everybody at some step
    runs = torch.ones(12, dtype=torch.bool)
    bound2 = pcrb(truth, scen, terrain, R_m2=64.0, runs=runs)
    assert torch.equal(bound, bound2)


class _PlaneNet(TerrainModel):
    """A plane as a generic TerrainModel (no height_and_slope: the autograd path)."""

    def __init__(self, a: float, b: float) -> None:
        super().__init__()
        self.a, self.b = a, b
        self.extent = (0.0, 3000.0, 0.0, 2000.0)
        self.w = torch.nn.Parameter(torch.tensor(1.0, dtype=torch.float32))

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        xy = xy.to(torch.float32)
        return self.w * (self.a * xy[..., 0] + self.b * xy[..., 1])


def test_autograd_slopes_and_random_slope_information() -> None:
    truth = _straight_truth(10, 8, 1.0)
    info_grid, count = terrain_information(
        truth.pos, GridTerrain(_plane_tile(0.3, -0.2)), 25.0, on_map=truth.on_map)
    info_net, _ = terrain_information(truth.pos, _PlaneNet(0.3, -0.2), 25.0,
                                      on_map=truth.on_map)
    torch.testing.assert_close(info_net, info_grid, rtol=1e-6, atol=1e-9)
    assert torch.equal(count, torch.full((9,), 10.0, dtype=F64))

    # non-constant slopes: the expectation is the mean of the per-trajectory outer products
    class Bowl(TerrainModel):
        extent = (0.0, 3000.0, 0.0, 2000.0)

        def forward(self, xy: torch.Tensor) -> torch.Tensor:
            return 1e-4 * (xy[..., 0] ** 2) + 3e-4 * xy[..., 0] * xy[..., 1]

    on_map = truth.on_map.clone()
    on_map[:3, 2] = False
    info, count = terrain_information(truth.pos, Bowl(), 25.0, on_map=on_map)
    x, y = truth.pos[..., 0].numpy(), truth.pos[..., 1].numpy()
    hx, hy = 2e-4 * x + 3e-4 * y, 3e-4 * x
    rows = np.stack([-hx, -hy, np.ones_like(hx), 0 * hx, 0 * hx], -1)
    w = on_map.numpy().astype(float)
    ref = np.einsum("nk,nki,nkj->kij", w, rows, rows) / (w.sum(0)[:, None, None] * 25.0)
    np.testing.assert_allclose(info.numpy(), ref, rtol=1e-10, atol=1e-14)
    assert float(count[2]) == 7.0


def test_bad_inputs() -> None:
    terrain = GridTerrain(_plane_tile(0.1, 0.1))
    truth = _straight_truth(3, 4, 1.0)
    scen = _filter_scenario(1.0)
    with pytest.raises(NeuralMapError, match="model must be"):
        pcrb(truth, scen, terrain, model="exact")
    with pytest.raises(NeuralMapError, match="'pos'"):
        pcrb(SimpleNamespace(), scen, terrain)
    with pytest.raises(NeuralMapError, match="dt"):
        pcrb(truth, SimpleNamespace(dt=0.0), terrain)
    with pytest.raises(NeuralMapError, match="P0_diag"):
        pcrb(truth, SimpleNamespace(dt=1.0, P0_diag=[1.0, 2.0]), terrain, model="filter")
    with pytest.raises(NeuralMapError, match=r"'runs' has shape \(2,\)"):
        pcrb(truth, scen, terrain, model="filter", runs=torch.ones(2, dtype=torch.bool))
    with pytest.raises(NeuralMapError, match="finite and > 0"):
        pcrb(truth, scen, terrain, model="filter", R_m2=-1.0)
    with pytest.raises(NeuralMapError, match=r"'P0' has shape \(4, 4\)"):
        pcrb_recursion(torch.eye(4), torch.eye(5), torch.eye(5), torch.zeros(3, 5, 5))
    with pytest.raises(NeuralMapError, match="'Q' is not positive semi-definite"):
        pcrb_recursion(torch.eye(2), torch.eye(2), torch.tensor([[1.0, 2.0], [2.0, 1.0]]),
                       torch.zeros(3, 2, 2))
    with pytest.raises(NeuralMapError, match=r"\(K\+1, n, n\)"):
        pcrb_position(torch.zeros(3, 5))


def test_fixed_initial_error_takes_the_filter_prior() -> None:
    """Zero initial spread (paper scenario) must not give a zero bound at t = 0."""
    import dataclasses

    from neuralmap.lab.scenario import load_scenario, scenario_tile
    from neuralmap.lab.simulator import simulate
    from neuralmap.terrain.grid import GridTerrain

    scenario = load_scenario("tiny")
    fixed = dataclasses.replace(
        scenario, init_pos_sigma_m=0.0, init_alt_sigma_m=0.0, init_vel_sigma_mps=0.0
    )
    tile = scenario_tile(fixed)
    truth = simulate(fixed, tile, n_runs=4, seed=0)
    bound = pcrb(truth, fixed, GridTerrain(tile, method="bicubic"))
    torch.testing.assert_close(
        torch.diagonal(bound[0]), torch.tensor(fixed.P0_diag, dtype=bound.dtype)
    )
    assert pcrb_position(bound)[-1] > 0


def test_map_aware_pcrb_on_a_plane_equals_closed_form() -> None:
    """White map error σ²: the bound is the Kalman covariance with R = R_alt + σ² (and a
    Gauss-Markov map error gives the 6-state Riccati of the augmented model)."""
    from neuralmap.lab.pcrb import map_aware_pcrb

    a, b, dt, steps, var = 0.12, -0.07, 1.0, 50, 25.0
    terrain = GridTerrain(_plane_tile(a, b), method="bilinear")
    truth = _straight_truth(30, steps, dt)
    scen = SimpleNamespace(dt=dt, P0_diag=[1e4, 1e4, 100.0, 4.0, 4.0],
                           Q_diag=[1.0, 1.0, 1.0, 0.01, 0.01], R_m2=81.0, fit_variance_m2=0.0,
                           altimeter_sigma_m=9.0)
    F, P0, Q = transition_matrix(dt).numpy(), np.diag(scen.P0_diag), np.diag(scen.Q_diag)
    H = np.array([[-a, -b, 1.0, 0.0, 0.0]])
    white = map_aware_pcrb(truth, scen, terrain, map_error_var=var)
    ref = _riccati(P0, F, Q, H, np.array([[81.0 + var]]), steps)
    assert _rel_err(white, ref) < 1e-10
    rho = 0.6
    corr = map_aware_pcrb(truth, scen, terrain, map_error_var=var, map_error_corr=rho)
    F6 = np.block([[F, np.zeros((5, 1))], [np.zeros((1, 5)), np.array([[rho]])]])
    ref6 = _riccati(np.diag([*scen.P0_diag, var]), F6, np.diag([*scen.Q_diag, (1 - rho**2) * var]),
                    np.array([[-a, -b, 1.0, 0.0, 0.0, 1.0]]), np.array([[81.0]]), steps)
    assert _rel_err(corr, ref6[:, :5, :5]) < 1e-10
    # the map's error only ever removes information: both bounds lie above the map-only one
    exact = pcrb(truth, scen, terrain)
    assert bool((pcrb_position(white) >= pcrb_position(exact) - 1e-9).all())
    with pytest.raises(NeuralMapError, match="map_error_corr"):
        map_aware_pcrb(truth, scen, terrain, map_error_var=var, map_error_corr=1.0)
