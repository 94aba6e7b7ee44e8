"""Grid → tracker hand-off: the point-mass grid's 5-state estimate against a NumPy
computation on its masses (velocity conditioned on the position posterior, the
altitude-position cross-covariance included), the tracker and the EKF loaded from it
conserving mean and covariance, and the whole acquisition path (grid, hand-off, tracker)
against the Kalman filter on a linear-Gaussian (tilted-plane) flight."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

from neuralmap.tan.method import MethodContext
from neuralmap.tan.methods.ekf import EkfOptions, PointMassEkf
from neuralmap.tan.methods.point_mass import PointMassGrid, PointMassOptions
from neuralmap.tan.methods.tracker import PointMassTrackerMethod, TrackerOptions
from neuralmap.tan.model import TanModel

D = torch.float64
N = 5
#: The vehicles on the grid (and handed off); the others are not loaded.
ON = torch.tensor([False, True, False, True, True])


class _Sine(torch.nn.Module):
    """A nonlinear map (not a grid): ``500 + 40 sin(x / 35) + 0.3 y``."""

    extent = (0.0, 4000.0, 0.0, 4000.0)

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        return 500.0 + 40.0 * torch.sin(xy[..., 0] / 35.0) + 0.3 * xy[..., 1]


MODEL = TanModel(dt=1.0, P0=(900.0, 1600.0, 400.0, 0.25, 0.25),
                 Q=(4.0, 9.0, 1.0, 0.0025, 0.0025), R_altimeter=25.0)


def _context() -> MethodContext:
    return MethodContext(terrain=_Sine(), extent=_Sine.extent, model=MODEL, R=25.0,
                         R_altimeter=25.0, n_vehicles=N, device=torch.device("cpu"))


def _prior() -> tuple[torch.Tensor, torch.Tensor]:
    """Per-vehicle priors with position-velocity correlation (so ``B ≠ 0``)."""
    gen = torch.Generator().manual_seed(0)
    mean = torch.zeros(N, 5, dtype=D)
    mean[:, :2] = torch.randn(N, 2, generator=gen, dtype=D) * 20.0
    mean[:, 2] = torch.tensor([1.0, -2.0, 0.5, 3.0, -1.0], dtype=D)
    mean[:, 3:] = torch.randn(N, 2, generator=gen, dtype=D) * 0.1
    cov = torch.diag(torch.tensor([1e4, 1.44e4, 400.0, 0.25, 0.36], dtype=D)).repeat(N, 1, 1)
    cov[:, 0, 1] = cov[:, 1, 0] = 2000.0
    cov[:, 2, 2] = torch.tensor([400.0, 900.0, 100.0, 250.0, 600.0], dtype=D)
    cov[:, 0, 3] = cov[:, 3, 0] = 5.0 + torch.rand(N, generator=gen, dtype=D)
    cov[:, 1, 4] = cov[:, 4, 1] = 3.0 + torch.rand(N, generator=gen, dtype=D)
    return mean, cov


def _skewed_grid(dtype: str) -> PointMassGrid:
    """Vehicles ``ON`` on a 40² grid (~20 m cells), predicted once (process noise below
    0.3 cells: left pending on the grid) and updated with a measurement of the sine map: a
    non-Gaussian posterior whose per-cell altitude means depend on the cell."""
    grid = PointMassGrid(_context(), PointMassOptions(cells=40, dtype=dtype,
                                                      flatten_likelihood=False))
    mean, cov = _prior()
    grid.load(ON, mean, cov)
    grid.predict(1.0)
    ins = torch.zeros(N, 3, dtype=D)
    ins[:, 0] = 1000.0 + 150.0 * torch.arange(N, dtype=D)
    ins[:, 1] = 1200.0
    ins[:, 2] = 1500.0
    s_true = torch.tensor([12.0, -9.0], dtype=D)
    terrain = _Sine()(ins[:, :2] - s_true)
    clearance = ins[:, 2] - (terrain + torch.tensor([4.0, -6.0, 2.0, 0.0, 8.0], dtype=D))
    grid.update(ins, clearance, torch.ones(N, dtype=torch.bool))
    return grid


def _numpy_estimate(grid: PointMassGrid) -> tuple[np.ndarray, np.ndarray]:
    """Independent NumPy moments of ``[s, a, v]`` of the grid's members from its masses:
    the velocity prior propagated over the one prediction (per axis ``P_pp ← P_pp + 2Δt
    P_pv + Δt² P_vv + q_p``, ``P_pv ← P_pv + Δt P_vv``, ``P_vv ← P_vv + q_v``, ``m_p ← m_p
    + Δt v₀``) and ``v = v₀ + B (s − m_p) + ε``, ``B = P_pv / P_pp``."""
    pm = grid.pm
    mean0, cov0 = (t.numpy() for t in _prior())
    q = np.array(MODEL.Q)
    w = pm.weights.double().numpy()
    a = pm.scalar_mean.double().numpy()
    va = pm.scalar_var.double().numpy()
    pts = pm.points().double().numpy()
    pending = pm._pending.double().numpy()
    xs, Ps = [], []
    for r, vehicle in enumerate(grid.members.tolist()):
        c0 = cov0[vehicle]
        ppp0, ppv0 = np.diag(c0[:2, :2]), np.array([c0[0, 3], c0[1, 4]])
        pvv0, v0 = np.diag(c0[3:, 3:]), mean0[vehicle, 3:]
        ppp = ppp0 + 2.0 * ppv0 + pvv0 + q[:2]
        ppv = ppv0 + pvv0
        pvv = pvv0 + q[3:]
        mp = mean0[vehicle, :2] + v0
        wr = w[r].ravel()
        s = pts[r].reshape(-1, 2)
        ar = a[r].ravel()
        ms = wr @ s
        ds = s - ms
        css = (wr[:, None] * ds).T @ ds + np.diag(pending[r])
        ma = wr @ ar
        var_a = va[r] + wr @ (ar - ma) ** 2
        cas = (wr * (ar - ma)) @ ds  # Σ_ps = Σ w (a − ā)(s − s̄)
        b = ppv / ppp
        B = np.diag(b)
        x = np.concatenate([ms, [ma], v0 + b * (ms - mp)])
        P = np.zeros((5, 5))
        P[:2, :2] = css
        P[2, 2] = var_a
        P[2, :2] = P[:2, 2] = cas
        P[3:, :2] = B @ css
        P[:2, 3:] = (B @ css).T
        P[3:, 2] = P[2, 3:] = B @ cas  # cov(δv, δh) = B Σ_ps
        P[3:, 3:] = np.diag(pvv - b * b * ppp) + B @ css @ B
        xs.append(x)
        Ps.append(P)
    return np.array(xs), np.array(Ps)


@pytest.mark.parametrize("dtype,tol", [("float64", 1e-9), ("float32", 2e-5)])
def test_grid_estimate_equals_a_numpy_computation(dtype: str, tol: float) -> None:
    """`PointMassGrid.estimate` of every member against NumPy on its masses (mean to ``tol``
    σ, covariance to ``tol`` relative to σσ: float64 round-off, or a float32 grid's)."""
    grid = _skewed_grid(dtype)
    assert grid.members.tolist() == ON.nonzero().reshape(-1).tolist()
    assert float(grid.pm._pending.abs().max()) > 0.0  # deferred process noise exercised
    x, P = grid.estimate()
    xr, Pr = _numpy_estimate(grid)
    xg, Pg = x[ON].numpy(), P[ON].numpy()
    sd = np.sqrt(np.diagonal(Pr, axis1=1, axis2=2))
    assert np.abs((xg - xr) / sd).max() <= tol
    assert np.abs((Pg - Pr) / (sd[:, :, None] * sd[:, None, :])).max() <= tol
    assert np.abs(Pr[:, 2, :2]).max() > 1.0  # the altitude-position term is exercised
    assert np.abs(Pr[:, 3:, 2]).max() > 1e-3  # ... and cov(δv, δh) = B Σ_ps
    # vehicles not on the grid keep the model's prior
    torch.testing.assert_close(P[~ON], MODEL.filter_prior().expand(2, 5, 5))


@pytest.mark.parametrize("dtype,tol", [("float64", 1e-9), ("float32", 2e-5)])
def test_handoff_conserves_mean_and_covariance(dtype: str, tol: float) -> None:
    """The tracker loaded from the grid's estimate has that estimate (mean to ``tol`` σ,
    covariance to ``tol`` relative), for the vehicles handed off; the others, dropped (held
    on the grid), hold the dormant Gaussian (zero mean, ``dormant_sigma`` horizontally)."""
    grid = _skewed_grid("float64")
    x, P = grid.estimate()
    options = TrackerOptions(cells=32, dtype=dtype)
    tracker = PointMassTrackerMethod(_context(), options)
    tracker.drop(torch.ones(N, dtype=torch.bool))  # every vehicle starts on the grid ...
    tracker.load(ON, x, P)  # ... and these are handed off
    mean, cov = tracker.estimate()
    sd = P[ON].diagonal(dim1=1, dim2=2).sqrt()
    err_mean = ((mean[ON] - x[ON]) / sd).abs().max()
    err_cov = ((cov[ON] - P[ON]) / (sd[:, :, None] * sd[:, None, :])).abs().max()
    assert float(err_mean) <= tol and float(err_cov) <= tol
    assert float(mean[~ON].abs().max()) < 1e-3
    dormant = torch.diag(torch.tensor([options.dormant_sigma**2] * 2, dtype=D))
    torch.testing.assert_close(cov[~ON][:, :2, :2], dormant.expand(2, 2, 2), rtol=1e-3,
                               atol=1e-3)
    assert bool(tracker.healthy().all())


def test_the_ekf_takes_the_grid_moments_whole() -> None:
    """``point_mass_ekf`` starts from the grid's full moments: the EKF loaded from the grid's
    estimate holds it exactly (altitude-position and velocity-altitude correlations
    included); the vehicles not loaded keep the model's prior."""
    grid = _skewed_grid("float64")
    x, P = grid.estimate()
    ekf = PointMassEkf(_context(), EkfOptions(linearizer="neural"))
    ekf.load(ON, x, P)
    mean, cov = ekf.estimate()
    torch.testing.assert_close(mean[ON], x[ON], rtol=0, atol=1e-12)
    torch.testing.assert_close(cov[ON], P[ON], rtol=1e-12, atol=1e-12)
    assert float(cov[ON][:, 2, :2].abs().max()) > 1.0
    torch.testing.assert_close(cov[~ON], MODEL.filter_prior().expand(2, 5, 5))


@pytest.fixture(scope="module")
def plane(tiny_scenario: Any, plane_flight: Any) -> Any:  # noqa: ANN401
    """Tilted plane, DEM as truth: linear-Gaussian, the bilinear EKF is the Kalman filter."""
    return plane_flight(tiny_scenario, duration_s=30.0)


def test_grid_then_tracker_equals_the_kalman_filter_across_the_handoff(
        plane: Any) -> None:  # noqa: ANN401
    """Linear-Gaussian flight: grid acquisition, hand-off, tracker to the end (the tracker
    starts on the grid: σ0 = 60 m above ``acquisition.above_sigma_m``; a plane observes one
    direction only, so the hand-off σ is above the prior σ). Every run hands off and none
    loses lock (the product's lost-lock test on); at every step the estimate is within
    0.5 % of σ of the Kalman filter's and the horizontal covariance within 1 % (the grid's
    own error at the hand-off, carried unchanged); after the hand-off the difference grows
    by at most 0.2 % σ (tracker ≡ Kalman from its start; the grid posterior at hand-off is
    Gaussian only to grid accuracy), and altitude and velocity errors follow the Kalman
    filter's (the Kalman part per cell)."""
    res = plane.fly(
        {"method": "point_mass_tracker", "point_mass_tracker": {"dtype": "float64"}},
        {"acquisition": {"above_sigma_m": 50.0, "handoff_sigma_m": 65.0, "handoff_hold": 2,
                         "min_acquire_steps": 3},
         "point_mass": {"cells": 96, "dtype": "float64"},
         "integrity": {"lost_window": 20, "lost_prob": 0.99999}})
    handoff = res.vehicle_counts["first_handoff"]
    assert bool((handoff > 0).all()) and res.counts["handoffs"] == plane.truth.n_runs
    assert res.counts["lost"] == 0
    kalman = plane.kalman
    err, ref = res.err[..., :2], kalman.err[..., :2]
    Pk = kalman.P[..., :2, :2]
    sd = Pk.diagonal(dim1=-2, dim2=-1).amax(-1).sqrt()
    rel = (err - ref).norm(dim=-1) / sd  # (N, K+1), in units of the Kalman σ
    assert float(rel.max()) < 5e-3
    P = res.P[..., :2, :2]
    assert float(((P - Pk).abs() / Pk.abs().amax((2, 3), keepdim=True)).max()) < 1e-2
    steps = torch.arange(err.shape[1])[None, :]
    at = torch.where(steps <= handoff[:, None], rel, 0.0).amax(1)
    after = torch.where(steps > handoff[:, None], rel, 0.0).amax(1)
    assert bool((after <= at + 2e-3).all())
    torch.testing.assert_close(res.err[..., 2], kalman.err[..., 2], atol=0.05, rtol=0)
    torch.testing.assert_close(res.err[..., 3:], kalman.err[..., 3:], atol=0.01, rtol=0)
