"""The lean step of the following lattice (`neuralmap.filters.lattice.follow_step`).

* The static driver (one pass of static-shape kernels per prediction and update, rare runs
  redone eagerly; the compiled and CUDA path) equals the eager driver (host branches) step
  by step from identical states: a few runs (every run regridded, masked) and a batch that
  resamples only its moved runs, through regrids, a lost-track widening and re-acquisition,
  cells off the map, masks, a missing measurement and the likelihood flattening.
* The same under ``torch.compile`` (slow: compiles the step functions on the CPU).
* The closed forms the step uses against LAPACK: the moment-correction map, the eigenvalue
  floor of the linear part, the thin-posterior test, the blur with a static band.
* `LatticeFilter.predictive_nis` against a brute-force sum over the cells.
* The whole tracking epoch as one step (`PointMassTracker.track`: prediction, map at the
  cells, spike gate, update, moments, radial mass profile) against the eager driver's
  prediction, predictive NIS, gate and update, uncompiled and (slow) compiled; its mass
  profile's protection radius against `lattice_protection_radius`.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from neuralmap.filters.lattice import follow_rule
from neuralmap.filters.lattice import follow_step as fs
from neuralmap.filters.lattice.algebra2 import sqrtm2
from neuralmap.filters.lattice.kernels import blur, mass_radius
from neuralmap.filters.point_mass import PointMassConfig, PointMassFilter
from neuralmap.filters.point_mass_tracker import PointMassTracker, TrackerConfig
from neuralmap.tan.cells import lattice_protection_radius

D = torch.float64
T = 1.0
E = torch.tensor([[0.0, T, 0.0], [0.0, 0.0, T]], dtype=D)
P0 = torch.diag(torch.tensor([60.0**2, 45.0**2, 20.0**2, 0.5**2, 0.5**2], dtype=D))
QS = torch.eye(2, dtype=D)
QZ = torch.diag(torch.tensor([1.0, 0.0025, 0.0025], dtype=D))


def _relief(p: torch.Tensor) -> torch.Tensor:
    x, y = p[..., 0], p[..., 1]
    return 40.0 * torch.sin(x / 310.0) * torch.cos(y / 270.0) + 25.0 * torch.sin((x + y) / 130.0)


def _tracker(n: int, config: TrackerConfig, dtype: torch.dtype = D) -> PointMassTracker:
    return PointMassTracker(torch.zeros(n, 5, dtype=dtype), P0.to(dtype), E=E.to(dtype),
                            F=torch.eye(3, dtype=dtype), c=torch.tensor([1.0, 0.0, 0.0],
                                                                        dtype=dtype),
                            config=config, dtype=dtype)


def _step(f: PointMassTracker, k: int, y: torch.Tensor, ins: torch.Tensor) -> tuple:
    n = f.n_runs
    f.predict(Q_s=QS.to(f.dtype), Q_z=QZ.to(f.dtype))
    pts = f.points()
    g = _relief(ins[:, None, None, :].to(f.dtype) - pts)
    g = torch.where(pts[..., 0] > 60.0 + 10.0 * k, math.nan, g)  # east of it: off the map
    gy, gx = torch.gradient(torch.nan_to_num(g), dim=(1, 2))
    mask = torch.tensor([(k + i) % 4 != 0 for i in range(n)])
    y = y.clone()
    if k == 5:
        y[0] = math.nan
    upd = f.update(y.to(f.dtype), g, R=9.0, mask=mask, cell_variance=(gx**2 + gy**2) / 12.0)
    mean, cov = f.moments()
    w, mu, P, _, _ = f.state()  # the lattice (centre near 0 at first) through its cells
    return (w, mu, P, f.points(), mean, cov, upd.nis, upd.log_likelihood, upd.applied,
            upd.recovered, f.regrids, f.widenings, f.lost)


def _compare(n: int, steps: int, *, compile_: bool, rtol: float, config: TrackerConfig,
             dtype: torch.dtype = D) -> dict[str, int]:
    """The eager driver flies; at every step a static copy (compiled or not) takes the same
    step from the same state; returns the events seen."""
    gen = torch.Generator().manual_seed(7)
    truth = torch.randn(n, 5, generator=gen, dtype=D) * P0.diagonal().sqrt()
    phi = torch.eye(5, dtype=D)
    phi[0, 3] = phi[1, 4] = T
    eager = _tracker(n, config, dtype)
    ins = torch.zeros(n, 2, dtype=D)
    ins[:, 0] = torch.arange(n, dtype=D) * 3000.0
    events = {"regrids": 0, "widenings": 0}
    for k in range(steps):
        ins = ins + torch.tensor([60.0, 20.0], dtype=D)
        truth = truth @ phi.T + torch.randn(n, 5, generator=gen, dtype=D) * torch.cat(
            [QS.diagonal(), QZ.diagonal()]).sqrt()
        y = _relief(ins - truth[:, :2]) + truth[:, 2] + 3.0 * torch.randn(n, generator=gen,
                                                                        dtype=D)
        if k >= steps // 2:
            y = y + 300.0  # a lost track: widened, then re-acquired
        static = eager.take(torch.arange(n))
        static.rule.static, static.rule._compile = True, compile_
        want = _step(eager, k, y, ins)
        got = _step(static, k, y, ins)
        for a, b in zip(want, got, strict=True):
            if a.dtype in (torch.bool, torch.int64):
                assert torch.equal(a, b), k
            else:  # relative to each run's largest entry; non-finite entries equal
                a2, b2 = a.reshape(n, -1), b.reshape(n, -1)
                fin = torch.isfinite(a2)
                assert torch.equal(fin, torch.isfinite(b2)), k
                assert torch.equal(a2[~fin], b2[~fin]) or bool(a2[~fin].isnan().all()), k
                a2, b2 = torch.where(fin, a2, 0.0), torch.where(fin, b2, 0.0)
                scale = a2.abs().amax(1).clamp_min(1e-6 * float(a2.abs().max()) + 1e-300)
                err = float(((a2 - b2).abs().amax(1) / scale).max())
                assert err <= rtol, (k, err)
    events["regrids"] = int(eager.regrids.sum())
    events["widenings"] = int(eager.widenings.sum())
    return events


@pytest.mark.parametrize(("n", "compact", "min_half_width"),
                         [(3, False, 26.0), (6, True, 26.0), (3, False, 0.0)])
def test_static_step_equals_the_eager_driver(n: int, compact: bool, min_half_width: float,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """Every run regridded and masked (``compact`` False), or only the moved runs resampled
    (True: the threshold lowered to test it on a few runs); with the lattice floor of the
    navigator (26 m: three-tap kernels) and without it (longer kernels, other bands)."""
    if compact:
        monkeypatch.setattr(follow_rule, "COMPACT_MIN_RUNS", 2)
    cfg = TrackerConfig(lost_window=4, local_widenings=1, min_half_width=min_half_width)
    events = _compare(n, 14, compile_=False, rtol=1e-9, config=cfg)
    assert events["regrids"] >= n and events["widenings"] >= n


@pytest.mark.slow
def test_compiled_step_equals_the_eager_step() -> None:
    """``torch.compile`` of the step functions (C++ on the CPU) against the eager driver,
    float64 (round-off of a different evaluation order: 1e-8) and float32."""
    cfg = TrackerConfig(lost_window=4, local_widenings=1, min_half_width=26.0)
    events = _compare(3, 12, compile_=True, rtol=1e-8, config=cfg)
    assert events["regrids"] >= 3 and events["widenings"] >= 3


def _cells_relief(ins: torch.Tensor, east_limit: float, points: torch.Tensor) -> torch.Tensor:
    """The test relief at the cells ``points (N, G, G, 2)`` seen from ``ins (N, 2)``; cells
    east of ``east_limit`` off the map (a module-level map for the whole-epoch step)."""
    g = _relief(ins[:, None, None, :].to(points.dtype) - points)
    return torch.where(points[..., 0] > east_limit, math.nan, g)


@pytest.mark.parametrize("compile_", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_whole_epoch_step_equals_prediction_then_gated_update(compile_: bool) -> None:
    """`PointMassTracker.track` from the eager driver's state at every epoch equals its
    prediction, `predictive_nis`, the spike gate (a 300 m spike on one run) and the masked
    update (float64: 1e-9 eager, 1e-8 compiled); its mass profile gives
    `lattice_protection_radius` at three risks."""
    n, steps, gate, r = 3, 12, 10.83, 9.0
    cfg = TrackerConfig(lost_window=4, local_widenings=1, min_half_width=26.0)
    gen = torch.Generator().manual_seed(3)
    truth = torch.randn(n, 5, generator=gen, dtype=D) * P0.diagonal().sqrt()
    eager = _tracker(n, cfg)
    ins = torch.zeros(n, 2, dtype=D)
    ins[:, 0] = torch.arange(n, dtype=D) * 3000.0
    fused_steps = gated_runs = profiles = 0
    for k in range(steps):
        ins = ins + torch.tensor([60.0, 20.0], dtype=D)
        truth[:, :2] += truth[:, 3:] * T
        y = _relief(ins - truth[:, :2]) + truth[:, 2] + 3.0 * torch.randn(n, generator=gen,
                                                                        dtype=D)
        if k == 6:
            y[1] += 300.0  # a spike
        mask = torch.tensor([(k + i) % 5 != 0 for i in range(n)])
        limit = 60.0 + 10.0 * k
        static = eager.take(torch.arange(n))
        static.rule.static, static.rule._compile = True, compile_
        eager.predict(Q_s=QS, Q_z=QZ)
        g = _cells_relief(ins, limit, eager.points())
        nis_pred = eager.predictive_nis(y, g, r)
        gated = mask & torch.isfinite(nis_pred) & (nis_pred > gate)
        want = eager.update(y, g, R=r, mask=mask & ~gated)
        out = static.track(Q_s=QS, Q_z=QZ, measurement=y, heights=_cells_relief,
                           heights_args=(ins, limit), R=torch.full((n,), r, dtype=D),
                           mask=mask, gate=gate)
        if out is None:  # a rare event of the prediction: the epoch runs in two steps
            continue
        fused_steps += 1
        got, nis_got, gated_got, mass = out
        assert torch.equal(gated_got, gated), k
        gated_runs += int(gated.sum())
        assert torch.equal(got.applied, want.applied), k
        tol = 1e-8 if compile_ else 1e-9
        for a, b in zip((*static.state(), *static.moments(), got.nis, nis_got),
                        (*eager.state(), *eager.moments(), want.nis, nis_pred), strict=True):
            torch.testing.assert_close(a, b, rtol=tol, atol=tol, equal_nan=True)
        if mass is not None:
            profiles += 1
            mean = static.moments()[0][:, :2]
            for risk in (1e-1, 1e-2, 1e-4):
                gauss = torch.full((n,), 5.0, dtype=D)  # below the lattice's own radius
                torch.testing.assert_close(
                    torch.maximum(gauss, mass_radius(mass[0], mass[1], risk)),
                    lattice_protection_radius(static.points(), static.weights, static.axes,
                                              mean, risk, gauss), rtol=1e-9, atol=1e-9)
    assert fused_steps >= steps - 2 and gated_runs >= 1 and profiles >= steps - 2


# ---------------------------------------------------------------------------- closed forms
def test_moment_correction_map_is_the_lapack_formula() -> None:
    gen = torch.Generator().manual_seed(1)
    a = torch.randn(200, 2, 2, generator=gen, dtype=D)
    b = torch.randn(200, 2, 2, generator=gen, dtype=D)
    c = a @ a.mT + 1e-3 * torch.eye(2, dtype=D)
    ct = b @ b.mT + 1e-3 * torch.eye(2, dtype=D)
    c[0] = torch.tensor([[81.0, 0.0], [0.0, 720.0**2]], dtype=D)  # elongated: condition 6e3
    root = sqrtm2(c)
    iroot = torch.linalg.inv(root)
    want = iroot @ sqrtm2(root @ ct @ root) @ iroot
    got = fs.transport2(c, ct)
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(got @ c @ got, ct, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(fs.transport2(c, c), torch.eye(2, dtype=D).expand(200, 2, 2),
                               rtol=0.0, atol=1e-12)


def test_eigenvalue_floor_of_the_linear_part_is_the_lapack_floor() -> None:
    gen = torch.Generator().manual_seed(2)
    n = 500
    q = torch.linalg.qr(torch.randn(n, 3, 3, generator=gen, dtype=D))[0]
    small = torch.where(torch.rand(n, generator=gen) < 0.5,
                        -1e-9 * torch.rand(n, generator=gen, dtype=D),
                        1e-11 * torch.rand(n, generator=gen, dtype=D))
    lam = torch.stack([small, 0.05 + torch.rand(n, generator=gen, dtype=D),
                       2.5 + torch.rand(n, generator=gen, dtype=D)], -1)
    P = q @ torch.diag_embed(lam) @ q.mT
    P = 0.5 * (P + P.mT)
    got, hard = fs.p_floor(P)
    assert not bool(hard.any())
    want = fs.floor_p_rows(P)
    assert float(((got - want).abs().amax((1, 2)) / want.abs().amax((1, 2))).max()) < 1e-13
    lo = torch.linalg.eigvalsh(got)
    assert bool((lo[:, 0] >= 0.99e-12 * lo[:, -1]).all())  # at the floor (round-off)
    # two eigenvalues at the floor: no cross product defines the vector, LAPACK's turn
    lam2 = torch.tensor([0.0, 1e-14, 3.0], dtype=D).expand(20, 3)
    assert bool(fs.p_floor(q[:20] @ torch.diag_embed(lam2) @ q[:20].mT)[1].all())
    # a few runs outside torch.compile: LAPACK directly, the same floor
    torch.testing.assert_close(fs.p_floor(P[:5])[0], want[:5], rtol=1e-13, atol=0.0)


def test_thin_posterior_test_is_the_smallest_eigenvalue() -> None:
    gen = torch.Generator().manual_seed(3)
    a = torch.randn(400, 2, 2, generator=gen, dtype=D) * 0.6
    cu = a @ a.mT
    want = torch.linalg.eigvalsh(cu)[:, 0] < fs.MIN_CELL_VARIANCE
    assert torch.equal(fs.thin_flag(cu), want)
    assert not bool(fs.thin_flag(torch.full((1, 2, 2), math.nan, dtype=D)).any())


@pytest.mark.parametrize("sigma", [0.05, 0.4, 0.69, 0.8, 1.7])
def test_blur_with_a_static_band_equals_the_kernel_of_the_batch(sigma: float) -> None:
    """`follow_step.blur_band` (kernel in a band of static length, zero beyond the
    batch's ``⌈4 σ_max⌉``) equals `kernels.blur` (kernel of that length)."""
    gen = torch.Generator().manual_seed(4)
    chans = torch.rand(3, 2, 16, 16, generator=gen, dtype=D)
    sig = torch.tensor([[sigma, 0.5 * sigma], [0.3, sigma], [0.1, 0.2]], dtype=D)
    half_len = min(max(1, math.ceil(4.0 * float(sig.max()))), 15)
    band = 1 if float(sig.max()) < fs.GAUSS_MIN_CELLS else half_len
    for b in {band, fs.FAST_BAND if band <= fs.FAST_BAND else band, 15}:
        got = fs.blur_band(chans, sig, torch.tensor(float(half_len), dtype=D), b)
        torch.testing.assert_close(got, blur(chans, sig), rtol=1e-13, atol=1e-15)


# ---------------------------------------------------------------------------- predictive NIS
def _brute_nis(w: np.ndarray, g: np.ndarray, mu: np.ndarray, P: np.ndarray, c: np.ndarray,
               y: float, R: float) -> float:
    """``(y − ŷ)² / S_y`` by a loop over the cells where ``g`` is finite."""
    num = den = 0.0
    cells = []
    for i in range(w.shape[0]):
        for j in range(w.shape[1]):
            if math.isfinite(g[i, j]):
                yc = g[i, j] + float(c @ mu[:, i, j])
                cells.append((w[i, j], yc))
                num += w[i, j] * yc
                den += w[i, j]
    if not cells or den == 0.0 or not math.isfinite(y):
        return math.nan
    yhat = num / den
    spread = sum(wc * (yc - yhat) ** 2 for wc, yc in cells) / den
    return (y - yhat) ** 2 / (spread + float(c @ P @ c) + R)


def test_predictive_nis_equals_the_sum_over_the_cells() -> None:
    gen = torch.Generator().manual_seed(5)
    trk = _tracker(4, TrackerConfig(cells=12, lost_window=0))
    trk.predict(Q_s=QS, Q_z=QZ)
    trk.lin_mean = trk.lin_mean + torch.randn(trk.lin_mean.shape, generator=gen, dtype=D)
    g = 100.0 * torch.rand(4, 12, 12, generator=gen, dtype=D)
    g[1, :, :5] = math.nan  # partly off the map
    g[2] = math.nan  # all off the map: NaN
    y = torch.tensor([30.0, 55.0, 40.0, math.nan], dtype=D)  # the last: no measurement
    R = torch.tensor([9.0, 16.0, 9.0, 9.0], dtype=D)
    got = trk.predictive_nis(y, g, R)
    for r in range(4):
        want = _brute_nis(trk.weights[r].numpy(), g[r].numpy(), trk.lin_mean[r].numpy(),
                          trk.lin_cov[r].numpy(), trk.c.numpy(), float(y[r]), float(R[r]))
        if math.isnan(want):
            assert math.isnan(float(got[r]))
        else:
            assert float(got[r]) == pytest.approx(want, rel=1e-12)
    # the update reports the same NIS for the runs it applies (all cells on the map)
    y_all, g_all = torch.tensor([30.0, 55.0, 40.0, 20.0], dtype=D), torch.nan_to_num(g, 50.0)
    before = trk.predictive_nis(y_all, g_all, 9.0)
    torch.testing.assert_close(trk.update(y_all, g_all, R=9.0).nis, before, rtol=1e-12,
                               atol=0.0)


def test_predictive_nis_of_the_acquisition_grid() -> None:
    gen = torch.Generator().manual_seed(6)
    pm = PointMassFilter(torch.zeros(2, 2, dtype=D), torch.eye(2, dtype=D) * 200.0**2,
                         scalar_var=25.0, config=PointMassConfig(cells=10), dtype=D)
    pm.predict(Q=4.0, scalar_q=1.0)
    g = 50.0 * torch.rand(2, 10, 10, generator=gen, dtype=D)
    g[0, 0] = math.nan
    y = torch.tensor([20.0, 31.0], dtype=D)
    got = pm.predictive_nis(y, g, 16.0)
    want = [_brute_nis(pm.weights[r].numpy(), g[r].numpy(), pm.lin_mean[r].numpy(),
                       pm.lin_cov[r].numpy(), pm.c.numpy(), float(y[r]), 16.0) for r in range(2)]
    torch.testing.assert_close(got, torch.tensor(want, dtype=D), rtol=1e-12, atol=0.0)
    nis_upd = pm.update(y, torch.nan_to_num(g, nan=25.0), R=16.0).nis
    assert nis_upd is None  # the grid's update does not report it: the filter's method does


@pytest.mark.parametrize("static", [False, True])
def test_a_regrid_that_needs_coarser_cells_than_allowed_raises_in_both_drivers(
        static: bool) -> None:
    """A posterior that outgrows ``max_spacing`` (no measurements, large process noise):
    both drivers raise at the regrid, after the measurement update (the same state)."""
    from neuralmap.exceptions import NeuralMapError

    cfg = TrackerConfig(cells=16, lost_window=0, max_spacing=60.0)
    trk = _tracker(2, cfg)
    trk.rule.static = static
    with pytest.raises(NeuralMapError, match="max_spacing"):
        for _ in range(20):
            trk.predict(Q_s=QS * 400.0, Q_z=QZ)
            trk.update(torch.full((2,), math.nan, dtype=D), torch.zeros(2, 16, 16, dtype=D),
                       R=9.0)
    assert bool(torch.isfinite(trk.moments()[1]).all())
