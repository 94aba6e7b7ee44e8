"""Point-mass filter against closed forms: the Kalman filter on a plane, a bimodal terrain,
float32 weight health, the adaptive grid and bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters import BatchedEKF
from neuralmap.filters.point_mass import PointMassConfig, PointMassFilter

M0 = np.array([10.0, -20.0, 2.0])
P0 = np.array([[400.0, 100.0, 0.0], [100.0, 900.0, 0.0], [0.0, 0.0, 25.0]])
Q = np.array([30.0, 50.0, 1.0])
R = 16.0
# plane terrain g(s) = c + gx sx + gy sy whose slope turns from step to step
PLANES = [(0.3 * math.cos(k), 0.3 * math.sin(k), 5.0) for k in range(6)]
MEAS = [float(v) for v in np.random.default_rng(0).normal(0.0, 30.0, len(PLANES))]


def kalman_reference() -> tuple[np.ndarray, np.ndarray]:
    """Plain NumPy Kalman filter of the 3-state linear model (float64)."""
    x, P = M0.copy(), P0.copy()
    for k, ((gx, gy, c), y) in enumerate(zip(PLANES, MEAS, strict=True)):
        if k > 0:
            P = P + np.diag(Q)
        H = np.array([gx, gy, 1.0])
        S = H @ P @ H + R
        K = P @ H / S
        x = x + K * (y - c - H @ x)
        A = np.eye(3) - np.outer(K, H)
        P = A @ P @ A.T + R * np.outer(K, K)
    return x, P


def run_grid(dtype: torch.dtype, adaptive: bool, n: int = 3) -> PointMassFilter:
    cfg = PointMassConfig(cells=96, span_sigma=5.0, adaptive=adaptive)
    f = PointMassFilter(torch.tensor(M0[:2]).expand(n, 2), torch.tensor(P0[:2, :2]),
                        scalar_mean=M0[2], scalar_var=P0[2, 2], config=cfg, dtype=dtype)
    for k, ((gx, gy, c), y) in enumerate(zip(PLANES, MEAS, strict=True)):
        if k > 0:
            f.predict(Q=torch.tensor(Q[:2]), scalar_q=Q[2])
        f.update(torch.full((n,), y),
                 lambda pts, gx=gx, gy=gy, c=c: c + gx * pts[..., 0] + gy * pts[..., 1], R=R)
    return f


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_plane_terrain_equals_kalman_filter(dtype: torch.dtype) -> None:
    """Linear-Gaussian case: grid posterior = Kalman posterior to grid accuracy.

    96 cells over ±5σ (spacing σ/9.5), fixed grid: the mean agrees to 2e-3 posterior σ,
    the covariance to 2e-3 of its largest entry, the altitude mean and variance to 2e-3.
    """
    x, P = kalman_reference()
    f = run_grid(dtype, adaptive=False)
    mean, cov = f.mean().double(), f.cov().double()
    a_mean, a_var = (t.double() for t in f.scalar_moments())
    sig = np.sqrt(np.diag(P[:2, :2]))
    for i in range(3):
        assert np.all(np.abs(mean[i].numpy() - x[:2]) / sig < 2e-3)
        assert np.abs(cov[i].numpy() - P[:2, :2]).max() / np.abs(P[:2, :2]).max() < 2e-3
        assert abs(float(a_mean[i]) - x[2]) / math.sqrt(P[2, 2]) < 2e-3
        assert abs(float(a_var[i]) / P[2, 2] - 1.0) < 2e-3


def test_adaptive_grid_tracks_kalman_filter() -> None:
    """The re-centred / re-sized grid stays within 2 % of the Kalman posterior."""
    x, P = kalman_reference()
    f = run_grid(torch.float32, adaptive=True)
    assert int(f.regrids[0]) >= 2  # the grid did move
    mean, cov = f.mean()[0].double().numpy(), f.cov()[0].double().numpy()
    sig = np.sqrt(np.diag(P[:2, :2]))
    assert np.all(np.abs(mean - x[:2]) / sig < 2e-2)
    assert np.abs(cov - P[:2, :2]).max() / np.abs(P[:2, :2]).max() < 2e-2


@pytest.mark.parametrize("q", [0.05, 3.0, 400.0])
def test_prediction_adds_process_noise_exactly(q: float) -> None:
    """Three-tap, sampled-Gaussian and FFT kernels all add exactly diag(Q) (to 1e-3)."""
    cov0 = torch.tensor([[100.0, 20.0], [20.0, 60.0]], dtype=torch.float64)
    cfg = PointMassConfig(cells=128, span_sigma=6.0, min_spacing=0.01)
    f = PointMassFilter(torch.zeros(1, 2), cov0, config=cfg, dtype=torch.float64)
    c1 = f.cov()[0]
    f.predict(Q=torch.tensor([q, 2 * q]))
    expected = c1 + torch.diag(torch.tensor([q, 2 * q], dtype=torch.float64))
    torch.testing.assert_close(f.cov()[0], expected, rtol=1e-3, atol=1e-3 * float(cov0.max()))


def test_regrid_keeps_moments() -> None:
    """Moving a narrowed, off-centre posterior to a new grid keeps mean and covariance."""
    cfg = PointMassConfig(cells=64)
    f = PointMassFilter(torch.zeros(2, 2), torch.eye(2) * 1e4, config=cfg, dtype=torch.float64)
    target_mean = torch.tensor([[60.0, -40.0], [-30.0, 10.0]], dtype=torch.float64)
    target_cov = torch.tensor([[1600.0, 480.0], [480.0, 1200.0]],
                              dtype=torch.float64).expand(2, 2, 2)
    f.weights.copy_(f._gaussian_weights(target_mean, target_cov, f.centre, f.spacing))
    m1, c1 = f.mean().clone(), f.cov().clone()
    moved = f.regrid()
    assert bool(moved.all())
    assert bool((f.spacing < 10.0).all())  # finer than the prior's 400 / 31.5 m
    torch.testing.assert_close(f.mean(), m1, atol=0.05, rtol=0)
    torch.testing.assert_close(f.cov(), c1, rtol=2e-3, atol=1.0)


def test_bimodal_terrain_point_mass_keeps_both_modes_ekf_locks_on_one() -> None:
    """Symmetric terrain g = 0.002 s_x²: truth at s_x = +100; the EKF, linearised from a
    prior mean at −30, converges to the mirror mode −100; the grid keeps both."""
    steps, truth_sx, r = 4, 100.0, 25.0
    rng = np.random.default_rng(1)
    ys = [0.002 * truth_sx**2 + float(rng.normal(0.0, 5.0)) for _ in range(steps)]
    prior_mean = torch.tensor([[-30.0, 0.0]], dtype=torch.float64)
    prior_cov = torch.diag(torch.tensor([100.0**2, 100.0**2], dtype=torch.float64))
    pm = PointMassFilter(prior_mean, prior_cov, scalar_mean=0.0, scalar_var=1.0,
                         config=PointMassConfig(cells=256), dtype=torch.float64)
    ekf = BatchedEKF(torch.tensor([[-30.0, 0.0, 0.0]], dtype=torch.float64),
                     torch.diag(torch.tensor([1e4, 1e4, 1.0], dtype=torch.float64)))
    for y in ys:
        pm.update(torch.tensor([y]), lambda pts: 0.002 * pts[..., 0] ** 2, R=r)
        sx = ekf.x[0, 0]
        residual = y - (0.002 * sx**2 + ekf.x[0, 2])
        ekf.update(residual.reshape(1), torch.tensor([[0.004 * float(sx), 0.0, 1.0]]), r)
    assert abs(float(ekf.x[0, 0]) + truth_sx) < 10.0  # locked onto the wrong mode
    w = pm.weights[0]
    sx_cells = pm.points()[0, ..., 0]
    mass_pos = float(w[sx_cells > 0].sum())
    assert 0.2 < mass_pos < 0.8  # both modes carry weight
    near = (sx_cells.abs() - truth_sx).abs() < 30.0
    assert float(w[near].sum()) > 0.95  # and nothing else does
    assert float(pm.gaussian_affinity()[0]) < 0.8  # the Gaussian fit does not explain it


def test_float32_weights_stay_normalised_and_finite() -> None:
    """Extreme residuals (likelihood underflows in linear scale), rough terrain, 30 steps."""
    torch.manual_seed(0)
    n = 16
    f = PointMassFilter(torch.zeros(n, 2), torch.eye(2) * 300.0**2,
                        config=PointMassConfig(cells=48), dtype=torch.float32)
    for k in range(30):
        f.predict(Q=torch.tensor([4.0, 4.0]), scalar_q=1.0)
        y = torch.randn(n) * (1e4 if k % 7 == 3 else 30.0)
        out = f.update(y, lambda p: 50.0 * torch.sin(p[..., 0] / 40.0)
                       * torch.cos(p[..., 1] / 55.0),
                       R=1.0)
        total = f.weights.sum((1, 2))
        assert torch.isfinite(f.weights).all()
        torch.testing.assert_close(total, torch.ones(n), atol=1e-5, rtol=0)
        assert torch.isfinite(out.log_likelihood[out.applied]).all()
        assert torch.isfinite(f.scalar_mean).all() and torch.isfinite(f.scalar_var).all()


def test_all_zero_likelihood_is_a_counted_recovery() -> None:
    """Every cell non-finite (or zero): prior weights kept, recovery counted, no NaN."""
    f = PointMassFilter(torch.zeros(3, 2), torch.eye(2) * 100.0,
                        config=PointMassConfig(cells=16), dtype=torch.float32)
    before = f.weights.clone()
    pred = torch.zeros(3, 16, 16)
    pred[1] = float("nan")
    out = f.update(torch.zeros(3), pred, R=1.0)
    assert out.recovered.tolist() == [False, True, False]
    assert f.recoveries.tolist() == [0, 1, 0]
    torch.testing.assert_close(f.weights[1], before[1])
    assert torch.isfinite(f.weights).all() and torch.isfinite(f.scalar_mean).all()
    assert out.log_likelihood[1] == -math.inf


def test_outlier_likelihood_resists_a_wild_measurement() -> None:
    """Gaussian + uniform likelihood: a 500 m altimeter outlier barely moves the posterior."""
    def posterior_shift(p_out: float) -> float:
        cfg = PointMassConfig(cells=64, outlier_prob=p_out, outlier_width=2000.0)
        f = PointMassFilter(torch.zeros(1, 2), torch.eye(2) * 100.0**2, scalar_var=1.0,
                            config=cfg, dtype=torch.float64)
        f.update(torch.tensor([500.0]), lambda p: 0.5 * p[..., 0], R=4.0)
        return float(f.mean()[0, 0])

    assert abs(posterior_shift(0.0)) > 150.0
    assert abs(posterior_shift(0.05)) < 5.0


def test_bad_input_raises() -> None:
    with pytest.raises(NeuralMapError, match="not symmetric positive definite"):
        PointMassFilter(torch.zeros(2, 2), torch.tensor([[1.0, 2.0], [2.0, 1.0]]))
    with pytest.raises(NeuralMapError, match="cannot|covers"):
        PointMassFilter(torch.zeros(1, 2), torch.eye(2) * 1e6,
                        config=PointMassConfig(cells=32, spacing=10.0))
    with pytest.raises(NeuralMapError, match="cells"):
        PointMassConfig(cells=4).validate()
    f = PointMassFilter(torch.zeros(2, 2), torch.eye(2), config=PointMassConfig(cells=16))
    with pytest.raises(NeuralMapError, match="predicted must have shape"):
        f.update(torch.zeros(2), torch.zeros(2, 8, 8), R=1.0)
    with pytest.raises(NeuralMapError, match="R must be > 0"):
        f.update(torch.zeros(2), torch.zeros(2, 16, 16), R=0.0)


@pytest.mark.parametrize("half_len", [1, 3, 5, 12, 31])
@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_separable_convolution_equals_scipy(half_len: int, dim: int, dtype: torch.dtype) -> None:
    """Both paths of the prediction's convolution (shifted slices for short kernels, the
    banded Toeplitz product for long ones) against scipy.ndimage.convolve1d per run; the
    far tails are compared relative to each output (a direct sum, no FFT round-off)."""
    from scipy.ndimage import convolve1d

    from neuralmap.filters.point_mass import convolve_axis, gaussian_kernels

    gen = torch.Generator().manual_seed(half_len)
    n, c, g = 3, 2, 32
    o = torch.arange(g, dtype=torch.float64) - 15.5
    # a narrow peak: its tails span 100+ decades, which FFT round-off would bury
    x = torch.exp(-0.5 * (o[:, None] ** 2 + o[None, :] ** 2) / 2.0).expand(n, c, g, g).clone()
    x *= torch.rand(n, c, 1, 1, generator=gen, dtype=torch.float64) + 0.5
    sigma = torch.tensor([0.5, 1.3, half_len / 4.0], dtype=torch.float64)
    k = gaussian_kernels(sigma, half_len)
    got = convolve_axis(x.to(dtype), k.to(dtype), half_len, dim).double()
    for r in range(n):
        want = convolve1d(x[r].numpy(), k[r].numpy()[::-1], axis=dim - 1, mode="constant")
        want = torch.from_numpy(want)
        big = want > 1e-30
        rel = ((got[r] - want).abs()[big] / want[big]).max()
        assert rel <= (1e-12 if dtype == torch.float64 else 1e-5), (r, float(rel))


@pytest.mark.parametrize("moved", [[0, 1, 2, 3], [2]])
def test_regrid_of_every_run_equals_regrid_of_a_subset(moved: list[int]) -> None:
    """Same-run property: the in-place regrid (every run moves) and the subset one give the
    moved runs the same grid, masses, scalar part and deferred process noise (1e-12
    relative); runs that do not move are untouched bit for bit."""
    n = 4
    gen = torch.Generator().manual_seed(7)
    mean = torch.randn(n, 2, generator=gen, dtype=torch.float64) * 50.0
    cfg = PointMassConfig(cells=16)
    a = PointMassFilter(mean, torch.eye(2, dtype=torch.float64) * 300.0**2, config=cfg)
    b = PointMassFilter(mean, torch.eye(2, dtype=torch.float64) * 300.0**2, config=cfg)
    for f in (a, b):
        f.predict(Q=1.0, scalar_q=1.0)
        f.update(torch.full((n,), 3.0, dtype=torch.float64),
                 lambda p: 40.0 * torch.sin(p[..., 0] / 90.0) + 0.1 * p[..., 1], R=25.0)
        f._pending.fill_(0.5)
    names = ("weights", "scalar_mean", "scalar_var", "centre", "spacing", "_pending")
    before = {k: getattr(b, k).clone() for k in names}
    a.regrid(torch.ones(n, dtype=torch.bool), extra_cov=torch.full((n, 2), 1e6))
    cand = torch.zeros(n, dtype=torch.bool)
    cand[moved] = True
    moved_b = b.regrid(cand, extra_cov=torch.full((n, 2), 1e6))
    assert bool((moved_b == cand).all())
    for k in names:
        ga, gb = getattr(a, k), getattr(b, k)
        for r in range(n):
            if bool(cand[r]):
                scale = ga[r].abs().max().clamp_min(1e-300)
                assert float((ga[r] - gb[r]).abs().max() / scale) <= 1e-12, k
            else:
                assert torch.equal(gb[r], before[k][r]), k
