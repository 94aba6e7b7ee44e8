"""The one set of point-mass kernels (`neuralmap.filters.lattice.kernels`) against
independent references: scipy's 1-D convolution, a per-cell NumPy Kalman filter, Bayes'
rule summed directly, the Gaussian + uniform mixture density, moments summed over every
cell, and bilinear interpolation by hand. float64 throughout."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.ndimage import convolve1d

from neuralmap.filters.lattice import kernels as K

D = torch.float64
G = 16


def _rand_masses(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    w = torch.rand(n, G, G, generator=g, dtype=D) ** 4
    return w / w.sum((1, 2), keepdim=True)


@pytest.mark.parametrize("sigma", [0.4, 0.9, 3.0])  # three-tap, slices (≤ 4 taps), Toeplitz
def test_blur_equals_scipy_convolution_along_each_axis(sigma: float) -> None:
    x = torch.rand(3, 2, G, G, dtype=D, generator=torch.Generator().manual_seed(0))
    sig = torch.tensor([[sigma, 0.5 * sigma], [sigma, sigma], [0.3, sigma]], dtype=D)
    got = K.blur(x, sig)
    half_len = min(max(1, math.ceil(4.0 * float(sig.max()))), G - 1)
    for n in range(3):
        kx = K.gaussian_kernels(sig[n:n + 1, 0], half_len)[0].numpy()
        ky = K.gaussian_kernels(sig[n:n + 1, 1], half_len)[0].numpy()
        ref = convolve1d(x[n].numpy(), kx[::-1], axis=2, mode="constant")
        ref = convolve1d(ref, ky[::-1], axis=1, mode="constant")
        np.testing.assert_allclose(got[n].numpy(), ref, rtol=1e-12, atol=1e-15)


def test_kernel_variance_is_the_process_noise() -> None:
    sig = torch.tensor([0.2, 0.5, 0.69, 0.7, 1.3, 2.5], dtype=D)
    k = K.gaussian_kernels(sig, 25)  # ±10 σ: no truncation
    taps = torch.arange(-25, 26, dtype=D)
    torch.testing.assert_close(k.sum(1), torch.ones(6, dtype=D), rtol=0, atol=1e-14)
    var = (k * taps**2).sum(1)
    # exact below 0.7 cells (three taps); a sampled Gaussian's variance is off by its
    # aliasing, ~4π²σ⁴ exp(−2π²σ²) relative: 0.25 % at 0.7 cells, < 1e-12 from 1.3 cells
    torch.testing.assert_close(var[:3], sig[:3] ** 2, rtol=1e-14, atol=0.0)
    torch.testing.assert_close(var[3], sig[3] ** 2, rtol=3e-3, atol=0.0)
    torch.testing.assert_close(var[4:], sig[4:] ** 2, rtol=1e-12, atol=0.0)


def test_kalman_cells_equals_a_kalman_filter_in_every_cell() -> None:
    g = torch.Generator().manual_seed(1)
    n, nz = 2, 3
    mu = torch.randn(n, nz, G, G, generator=g, dtype=D)
    a = torch.randn(n, nz, nz, generator=g, dtype=D)
    P = a @ a.transpose(1, 2) + torch.eye(nz, dtype=D)
    c = torch.tensor([1.0, 0.3, -0.2], dtype=D)
    nu = torch.randn(n, G, G, generator=g, dtype=D)
    r = torch.tensor([2.0, 0.5], dtype=D)
    s = (P @ c) @ c + r
    mu_new, P_new = K.kalman_cells(mu, P, c, nu, s)
    for i in range(n):
        p, cc = P[i].numpy(), c.numpy()
        S = cc @ p @ cc + r[i].item()
        gain = p @ cc / S
        ref_P = (np.eye(nz) - np.outer(gain, cc)) @ p @ (np.eye(nz) - np.outer(gain, cc)).T \
            + np.outer(gain, gain) * r[i].item()  # Joseph form
        np.testing.assert_allclose(P_new[i].numpy(), ref_P, rtol=1e-12, atol=1e-12)
        for (row, col) in ((0, 0), (5, 9), (15, 15)):
            ref_m = mu[i, :, row, col].numpy() + gain * nu[i, row, col].item()
            np.testing.assert_allclose(mu_new[i, :, row, col].numpy(), ref_m, rtol=1e-12)


def test_weight_update_is_bayes_rule_with_the_predictive_likelihood() -> None:
    w = _rand_masses(2, 2)
    nu = torch.randn(2, G, G, generator=torch.Generator().manual_seed(3), dtype=D) * 3.0
    s = torch.tensor([4.0, 9.0], dtype=D)
    loglik, resp = K.cell_log_likelihood(nu, s)
    assert resp is None
    upd = K.weight_update(w.clone(), loglik, s)
    dens = torch.exp(-0.5 * nu**2 / s[:, None, None]) / torch.sqrt(2 * math.pi * s)[:, None, None]
    post = w * dens
    torch.testing.assert_close(upd.weights, post / post.sum((1, 2), keepdim=True), rtol=1e-12,
                               atol=1e-300)
    torch.testing.assert_close(upd.log_likelihood, post.sum((1, 2)).log(), rtol=1e-12, atol=0.0)
    assert bool(upd.use.all())
    # zero likelihood in every cell: flagged, never NaN
    gone = K.weight_update(w.clone(), torch.full_like(w, -math.inf), s)
    assert not bool(gone.use.any()) and bool(torch.isfinite(gone.weights).all())
    assert bool((gone.log_likelihood == -math.inf).all())


def test_mixture_likelihood_and_flattening_are_the_stated_densities() -> None:
    nu = torch.linspace(-80.0, 80.0, G * G, dtype=D).reshape(1, G, G)
    s = torch.tensor([25.0], dtype=D)
    p, width = 0.05, 1000.0
    mix, resp = K.cell_log_likelihood(nu, s, outlier_prob=p, outlier_width=width)
    gauss = torch.exp(-0.5 * nu**2 / s) / torch.sqrt(2 * math.pi * s)
    const = -0.5 * math.log(2 * math.pi * 25.0)
    torch.testing.assert_close(mix, ((1 - p) * gauss + p / width).log() - const, rtol=1e-12,
                               atol=1e-12)
    torch.testing.assert_close(resp, (1 - p) * gauss / ((1 - p) * gauss + p / width),
                               rtol=1e-12, atol=1e-15)
    cv = torch.full_like(nu, 11.0)
    flat, _ = K.cell_log_likelihood(nu, s, cv)
    dens = torch.exp(-0.5 * nu**2 / 36.0) / math.sqrt(2 * math.pi * 36.0)
    torch.testing.assert_close(flat, dens.log() - const, rtol=1e-12, atol=1e-12)


def test_lattice_moments_equal_sums_over_every_cell() -> None:
    w = _rand_masses(2, 4)
    mu = torch.randn(2, 2, G, G, generator=torch.Generator().manual_seed(5), dtype=D)
    off = torch.arange(G, dtype=D) - 0.5 * (G - 1)
    lm = K.LatticeMoments(w, mu, off)
    oy, ox = torch.meshgrid(off, off, indexing="ij")
    o = torch.stack([ox, oy], -1)  # (G, G, 2) x = column, y = row
    for n in range(2):
        wn = w[n].numpy().reshape(-1)
        on = o.numpy().reshape(-1, 2)
        zn = mu[n].numpy().reshape(2, -1).T
        u = wn @ on
        np.testing.assert_allclose(lm.u[n].numpy(), u, rtol=1e-12)
        np.testing.assert_allclose(lm.cu[n].numpy(), (wn[:, None] * (on - u)).T @ (on - u),
                                   rtol=1e-10, atol=1e-12)
        mz = wn @ zn
        np.testing.assert_allclose(lm.mz[n].numpy(), mz, rtol=1e-12)
        np.testing.assert_allclose(lm.czu[n].numpy(), (wn[:, None] * (zn - mz)).T @ (on - u),
                                   rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(lm.czz_b[n].numpy(), (wn[:, None] * (zn - mz)).T @ (zn - mz),
                                   rtol=1e-10, atol=1e-12)


def test_gaussian_density_on_the_lattice_has_the_asked_moments() -> None:
    off = torch.arange(64, dtype=D) - 31.5  # ±10 σ: no truncation
    u = torch.tensor([[1.3, -2.1]], dtype=D)
    cu = torch.tensor([[[9.0, 2.0], [2.0, 4.0]]], dtype=D)
    w = K.normalised(K.gaussian_log_density(off, u, cu))
    got_u, got_cu = K.mass_moments(w, off)
    torch.testing.assert_close(got_u, u, rtol=0, atol=1e-9)
    torch.testing.assert_close(got_cu, cu, rtol=1e-9, atol=1e-9)  # σ ≥ 2 cells: no aliasing


def test_bilinear_resampling_at_the_cells_and_between_them() -> None:
    x = torch.rand(1, 1, G, G, dtype=D, generator=torch.Generator().manual_seed(6))
    lin = torch.linspace(-1.0, 1.0, G, dtype=D)
    gy, gx = torch.meshgrid(lin, lin, indexing="ij")
    same = K.resample_bilinear(x, torch.stack([gx, gy], -1)[None])
    torch.testing.assert_close(same, x, rtol=1e-12, atol=1e-14)
    mid = (lin[:-1] + lin[1:]) / 2
    my, mx = torch.meshgrid(mid, mid, indexing="ij")
    half = K.resample_bilinear(x, torch.stack([mx, my], -1)[None])[0, 0]
    ref = 0.25 * (x[0, 0, :-1, :-1] + x[0, 0, 1:, :-1] + x[0, 0, :-1, 1:] + x[0, 0, 1:, 1:])
    torch.testing.assert_close(half, ref, rtol=1e-12, atol=1e-14)
    outside = K.resample_bilinear(x, torch.full((1, 2, 2, 2), 3.0, dtype=D))
    assert bool((outside == 0).all())  # zero density outside the old lattice


def test_conditional_mean_is_the_ratio_and_falls_back_where_mass_vanishes() -> None:
    mass = _rand_masses(1, 7)
    mass[0, :4] = 0.0
    mu = torch.randn(1, 2, G, G, generator=torch.Generator().manual_seed(8), dtype=D)
    fallback = torch.tensor([[5.0, -3.0]], dtype=D)
    got = K.conditional_mean(mass, mass[:, None] * mu, fallback)
    live = mass[0] > 1e-6 * mass.max()
    torch.testing.assert_close(got[0][:, live], mu[0][:, live], rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(got[0, :, :4], fallback[0, :, None, None].expand(2, 4, G))
