"""The one lattice filter: acquisition grid and tracker are configurations of
`LatticeFilter` (one state, one update), the mixture update with off-map cells against a
closed form, and run subsets (take / extend) of both configurations."""

from __future__ import annotations

import math

import torch

from neuralmap.filters.lattice.filter import LatticeFilter
from neuralmap.filters.point_mass import PointMassConfig, PointMassFilter
from neuralmap.filters.point_mass_tracker import PointMassTracker, TrackerConfig

D = torch.float64


def _terrain(p: torch.Tensor) -> torch.Tensor:
    return 40.0 * torch.sin(p[..., 0] / 90.0) + 0.1 * p[..., 1]


def test_grid_and_tracker_share_one_state_and_one_update() -> None:
    """A tracker holding the grid's state (axis-aligned lattice, nz = 1, E = 0, F = c = 1)
    gives the grid's update bit for bit (same run; the policies' weight floors off): the
    update exists once."""
    n = 3
    grid = PointMassFilter(torch.tensor([[0.0, 0.0], [30.0, -10.0], [5.0, 5.0]], dtype=D),
                           torch.diag(torch.tensor([90.0**2, 60.0**2], dtype=D)),
                           scalar_mean=2.0, scalar_var=16.0,
                           config=PointMassConfig(cells=24, adaptive=False, weight_floor=0.0),
                           dtype=D)
    trk = PointMassTracker(torch.zeros(n, 3, dtype=D), torch.eye(3, dtype=D) * 100.0,
                           E=torch.zeros(2, 1, dtype=D), F=torch.ones(1, 1, dtype=D),
                           c=torch.ones(1, dtype=D), config=TrackerConfig(cells=24), dtype=D)
    assert isinstance(grid, LatticeFilter) and isinstance(trk, LatticeFilter)
    trk.set_state(*(t.clone() for t in grid.state()))
    y = torch.tensor([3.0, -7.0, 12.0], dtype=D)
    pred = _terrain(grid.points())
    pred[1, :2] = math.nan  # off-map cells
    ug = grid.update(y, pred, R=9.0)
    ut = trk.update(y, pred.clone(), R=9.0, regrid=False)
    for a, b in zip(grid.state(), trk.state(), strict=True):
        assert torch.equal(a, b)
    assert torch.equal(ug.log_likelihood, ut.log_likelihood)
    assert torch.equal(ug.applied, ut.applied)
    assert ug.nis is None and ut.nis is not None  # only the tracker's policy reports NIS


def test_mixture_update_with_off_map_cells_is_the_closed_form() -> None:
    """Gaussian + uniform likelihood, some cells off the map (NaN): those cells get zero
    mass, every other cell the mixture posterior; the altitude part stays finite and is the
    responsibility-weighted Kalman update (float64 closed form per cell, 1e-12)."""
    eps, width, r = 0.05, 1000.0, 9.0
    f = PointMassFilter(torch.zeros(2, 2, dtype=D), torch.eye(2, dtype=D) * 1e4,
                        scalar_mean=1.0, scalar_var=100.0,
                        config=PointMassConfig(cells=16, outlier_prob=eps, outlier_width=width,
                                               weight_floor=0.0), dtype=D)
    w0, m0, v0 = f.weights.clone(), f.scalar_mean.clone(), f.scalar_var.clone()
    pred = _terrain(f.points())
    pred[0, :3] = math.nan
    y = torch.tensor([3.0, 5.0], dtype=D)
    f.update(y, pred, R=r)
    s = v0 + r
    nu = y[:, None, None] - pred - m0
    gauss = torch.exp(-0.5 * nu**2 / s[:, None, None]) / torch.sqrt(2 * math.pi * s)[:, None, None]
    lik = (1 - eps) * gauss + eps / width
    lik = torch.nan_to_num(lik, nan=0.0)
    post = w0 * lik
    post = post / post.sum((1, 2), keepdim=True)
    resp = torch.nan_to_num((1 - eps) * gauss / ((1 - eps) * gauss + eps / width), nan=0.0)
    k = v0 / s
    m_want = m0 + k[:, None, None] * resp * torch.nan_to_num(nu, nan=0.0)
    v_want = v0 - (post * resp).sum((1, 2)) * k * k * s
    assert bool((f.weights[0, :3] == 0).all())
    torch.testing.assert_close(f.weights, post, rtol=0, atol=1e-12)
    finite = post > 0
    torch.testing.assert_close(f.scalar_mean[finite], m_want[finite], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(f.scalar_var, v_want, rtol=1e-12, atol=0)


def _tracker(n: int) -> PointMassTracker:
    gen = torch.Generator().manual_seed(3)
    mean = torch.cat([torch.randn(n, 2, generator=gen, dtype=D) * 20.0,
                      torch.zeros(n, 3, dtype=D)], 1)
    cov = torch.diag(torch.tensor([40.0**2, 30.0**2, 5.0**2, 0.2**2, 0.2**2], dtype=D))
    E = torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=D)
    return PointMassTracker(mean, cov, E=E, F=torch.eye(3, dtype=D),
                            c=torch.tensor([1.0, 0.0, 0.0], dtype=D),
                            config=TrackerConfig(cells=16, lost_window=3), dtype=D)


def _step(f: LatticeFilter, k: int) -> None:
    y = torch.full((f.n_runs,), 2.0 + k, dtype=D)
    if isinstance(f, PointMassTracker):
        f.predict(Q_s=torch.eye(2, dtype=D), Q_z=torch.eye(3, dtype=D) * 1e-2)
    else:
        f.predict(Q=1.0, shift=torch.ones(f.n_runs, 2, dtype=D), scalar_q=1.0)
    f.update(y, _terrain, R=16.0)


def test_take_and_extend_carry_every_per_run_state() -> None:
    """Same run: runs taken out of a filter (tracker: with the policy's NIS window and
    open-loop prior; grid: with its deferred noise) and put back by extend continue exactly
    as in the whole filter."""
    for make in (lambda: _tracker(4),
                 lambda: PointMassFilter(torch.zeros(4, 2, dtype=D),
                                         torch.eye(2, dtype=D) * 300.0**2,
                                         config=PointMassConfig(cells=16), dtype=D)):
        whole, parts = make(), make()
        for k in range(2):
            _step(whole, k)
            _step(parts, k)
        a = parts.take(torch.tensor([0, 1]))
        b = parts.take(torch.tensor([2, 3]))
        joined = a.extend(b)
        for k in range(2, 5):
            _step(whole, k)
            _step(joined, k)
        for x, y in zip(whole.state(), joined.state(), strict=True):
            torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-12)
        assert torch.equal(whole.regrids, joined.regrids)
        assert torch.equal(whole.recoveries, joined.recoveries)
