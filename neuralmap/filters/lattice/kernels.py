"""The one set of point-mass kernels: prediction by separable convolution, the measurement
update, bilinear regrid and lattice moments.

Both lattice rules of the point-mass filter (the fixed / adaptive acquisition grid,
`neuralmap.filters.point_mass.PointMassFilter`, and the lattice that follows the
posterior, `neuralmap.filters.point_mass_tracker.PointMassTracker`) run on these
functions; nothing here knows which lattice it works on. Conventions (N runs, ``G × G``
cells, ``nz`` conditionally linear states per cell):

* masses ``w (N, G, G)``, rows ``i`` along the lattice's second axis, columns ``j`` along
  its first; cell ``(i, j)`` has lattice coordinates ``o = (j − h, i − h)``,
  ``h = (G − 1)/2`` (``off (G,)`` holds ``j − h``);
* the Rao-Blackwellised part: per-cell means ``μ (N, nz, G, G)`` and one conditional
  covariance ``P (N, nz, nz)`` per run (exact for the linear-Gaussian model);
* the measurement ``y = g(s) + c·z + e``, ``e ~ N(0, R)`` (optionally a Gaussian + uniform
  mixture).

Prediction (the efficient point-mass filter of Matoušek, Duník et al.): the masses and
``w μ`` are convolved with the transition density, one 1-D kernel per lattice axis and run
(`blur`: `convolve_axis` along x then y), and the per-cell means recovered as the ratio
``(K * wμ) / (K * w)`` (`conditional_mean`). Update (log domain, `cell_log_likelihood`,
`weight_update`, `kalman_cells`): ``ν = y − g − c·μ``, ``S = cᵀPc + R`` (the same in
every cell), ``log w += −½ ν²/S``, ``μ += K ν``, ``P ← P − K S Kᵀ``, ``K = P c / S``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as nnf

from neuralmap.filters.lattice.algebra2 import eigh2, mm, mv
from neuralmap.filters.underflow import exp_or_zero, log_or_neg_inf

__all__ = ["BANDED_MIN_HALF_LEN", "LatticeMoments", "WeightUpdate", "affine_field", "blur",
           "cell_log_likelihood", "conditional_mean", "convolve_axis", "gaussian_kernels",
           "gaussian_log_density", "kalman_cells", "lattice_moment_tensors", "mass_moments",
           "normalised", "resample_bilinear", "toeplitz_kernels", "weight_update"]

_LOG_2PI = math.log(2.0 * math.pi)

#: Kernels with more than ``2 · BANDED_MIN_HALF_LEN + 1`` taps are applied as one banded
#: Toeplitz product instead of shifted slices.
BANDED_MIN_HALF_LEN = 4

#: Relative mass under which a cell's conditional mean is pulled to the run's (round-off).
RATIO_EPS = 1e-13


# ---------------------------------------------------------------------------- prediction
def toeplitz_kernels(kernels: torch.Tensor, half_len: int, cells: int) -> torch.Tensor:
    """``(N, G, G)`` banded Toeplitz matrices ``T[n, j, i] = k[n, j − i + half_len]`` (zero
    outside the band): ``out = T x`` is the zero-padded convolution of ``x`` with ``k``.

    Args:
        kernels: ``(N, 2·half_len + 1)`` 1-D kernels.
        half_len: Kernel half-length.
        cells: Lattice cells ``G`` along the axis.
    """
    n = kernels.shape[0]
    i = torch.arange(cells, device=kernels.device)
    tap = i[:, None] - i[None, :] + half_len  # (G, G) tap index of out j, in i
    tap = tap.masked_fill((tap < 0) | (tap > 2 * half_len), 2 * half_len + 1)
    padded = torch.cat([kernels, kernels.new_zeros(n, 1)], 1)
    return padded[:, tap]


def convolve_axis(x: torch.Tensor, kernels: torch.Tensor, half_len: int,
                  dim: int) -> torch.Tensor:
    """Zero-padded 1-D convolution of ``x (N, C, G, G)`` along ``dim`` with per-run kernels.

    ``kernels (N, 2·half_len + 1)``. Short kernels (``≤ 2·BANDED_MIN_HALF_LEN + 1`` taps): a
    sum of shifted, scaled slices; longer ones: one batched product with the banded
    Toeplitz matrix of the kernel (`toeplitz_kernels`; ``G`` multiply-adds per output,
    one pass over ``x``) — the separable form of the convolution prediction of the
    efficient point-mass filter (Matoušek, Duník et al.). On a lattice of ``G ≤ 128``
    cells this beats an FFT (which needs a padded, complex float64 copy) several times
    over and its round-off is that of a direct sum (relative to each output, not to the
    peak: far tails stay exact).
    """
    g = x.shape[dim]
    n = x.shape[0]
    if half_len > BANDED_MIN_HALF_LEN:
        t = toeplitz_kernels(kernels.to(x.dtype), half_len, g)
        if dim == 3:  # out[..., j] = Σ_i T[j, i] x[..., i]
            return torch.bmm(x.reshape(n, -1, g), t.transpose(1, 2)).reshape(x.shape)
        return torch.matmul(t[:, None], x)  # rows: out[:, :, j] = Σ_i T[j, i] x[:, :, i]
    out = torch.mul(x, kernels[:, half_len, None, None, None])
    for t in range(2 * half_len + 1):
        o = t - half_len  # out[j] += k[t] · x[j − o]
        if o == 0 or abs(o) >= g:
            continue
        length = g - abs(o)
        dst = out.narrow(dim, max(o, 0), length)
        dst.addcmul_(x.narrow(dim, max(-o, 0), length), kernels[:, t, None, None, None])
    return out


def gaussian_kernels(sigma_cells: torch.Tensor, half_len: int) -> torch.Tensor:
    """``(M, 2·half_len + 1)`` 1-D process-noise kernels of variance ``sigma_cells²`` (cells).

    A sampled, normalised Gaussian for ``σ ≥ 0.7`` cells; the three-tap kernel
    ``[σ²/2, 1 − σ², σ²/2]`` below (its variance is exactly ``σ²``, which a sampled
    Gaussian narrower than a cell would not have).

    Args:
        sigma_cells: ``(M,)`` standard deviations in cells.
        half_len: Kernel half-length (taps ``−half_len … half_len``, ``≥ 1``).
    """
    dtype, device = sigma_cells.dtype, sigma_cells.device
    k = torch.arange(-half_len, half_len + 1, dtype=dtype, device=device)
    s = sigma_cells.clamp_min(1e-6)[:, None]
    gauss = torch.exp(-0.5 * (k / s) ** 2)
    gauss = gauss / gauss.sum(1, keepdim=True)
    var = s.squeeze(1) ** 2
    tap = torch.zeros_like(gauss)
    tap[:, half_len] = 1.0 - var.clamp_max(0.5)
    if half_len >= 1:
        tap[:, half_len - 1] = 0.5 * var.clamp_max(0.5)
        tap[:, half_len + 1] = 0.5 * var.clamp_max(0.5)
    return torch.where((sigma_cells >= 0.7)[:, None], gauss, tap)


def blur(chans: torch.Tensor, sigma_cells: torch.Tensor) -> torch.Tensor:
    """Channels ``(N, C, G, G)`` convolved with separable Gaussians of ``sigma_cells (N, 2)``
    cells (x: along columns, y: along rows; `gaussian_kernels`, `convolve_axis`).

    The prediction ``p(s') = Σ_s p(s' | s) w(s)`` of the point-mass filter for a transition
    density that is Gaussian along the lattice axes (Matoušek, Duník et al.); the kernel
    half-length is ``⌈4 σ_max⌉`` cells (at most ``G − 1``), common to the batch.
    """
    g = chans.shape[-1]
    half_len = min(max(1, int(math.ceil(4.0 * float(sigma_cells.max())))), g - 1)
    out = convolve_axis(chans, gaussian_kernels(sigma_cells[:, 0], half_len), half_len, dim=3)
    return convolve_axis(out, gaussian_kernels(sigma_cells[:, 1], half_len), half_len, dim=2)


def conditional_mean(mass: torch.Tensor, weighted: torch.Tensor,
                     fallback: torch.Tensor | None = None) -> torch.Tensor:
    """Per-cell means ``(N, nz, G, G)`` from blurred ``mass (N, G, G)`` (clamped ≥ 0) and
    blurred ``w μ`` ``weighted (N, nz, G, G)``: ``(wμ + ε μ̄) / (w + ε)``.

    ``ε = RATIO_EPS · max w`` (at least the dtype's tiny): cells whose mass is at the
    round-off level get ``fallback (N, nz)`` (the run's mean; None = 0) instead of a ratio of
    two round-off errors.
    """
    eps = (RATIO_EPS * mass.amax((1, 2), keepdim=True)).clamp_min(
        torch.finfo(mass.dtype).tiny)[:, None]
    if fallback is None:
        return weighted / (mass[:, None] + eps)
    return (weighted + eps * fallback[:, :, None, None]) / (mass[:, None] + eps)


# ---------------------------------------------------------------------------- update
def cell_log_likelihood(nu: torch.Tensor, s_run: torch.Tensor,
                        cell_variance: torch.Tensor | None = None, *,
                        outlier_prob: float = 0.0, outlier_width: float = 1000.0,
                        ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Per-cell log-likelihood of the innovations ``nu (N, G, G)``, up to the run constant
    ``−½ log 2πS`` (the marginalised likelihood of the Rao-Blackwellised point-mass filter).

    Args:
        nu: ``(N, G, G)`` innovations ``y − g − c·μ`` (finite).
        s_run: ``(N,)`` innovation variance ``S = cᵀPc + R``, the same in every cell.
        cell_variance: ``(N, G, G)`` spread of ``g`` over each cell, added to ``S`` in the
            likelihood only ("likelihood flattening": a coarse lattice cannot step over a
            peak narrower than a cell), or None.
        outlier_prob: Probability of a uniform outlier over ``outlier_width`` (0 = Gaussian).
        outlier_width: Width of the uniform outlier density (measurement units).

    Returns:
        ``loglik (N, G, G)`` and the inlier responsibility ``(N, G, G)`` (None when
        ``outlier_prob`` is 0).
    """
    if cell_variance is None:
        loglik = nu * nu * (-0.5 / s_run)[:, None, None]
    else:
        cv = torch.as_tensor(cell_variance).to(nu.dtype).clamp_min(0.0)
        s_cell = cv + s_run[:, None, None]
        loglik = -0.5 * (nu * nu / s_cell + torch.log1p(cv / s_run[:, None, None]))
    if outlier_prob <= 0.0:
        return loglik, None
    const = -0.5 * (_LOG_2PI + s_run.log())
    log_out = math.log(outlier_prob / outlier_width) - const[:, None, None]
    log_in = loglik + math.log1p(-outlier_prob)
    mix = torch.logaddexp(log_in, log_out.expand_as(log_in))
    return mix, (log_in - mix).exp()


class WeightUpdate:
    """Result of `weight_update`.

    Attributes:
        weights: ``(N, G, G)`` posterior masses, normalised where ``use`` (else unnormalised:
            the caller keeps the prior masses of those runs).
        log_likelihood: ``(N,)`` ``log Σ w p(y | cell)`` (−inf where it vanished).
        use: ``(N,)`` bool, the likelihood was finite and positive somewhere.
    """

    __slots__ = ("log_likelihood", "use", "weights")

    def __init__(self, weights: torch.Tensor, log_likelihood: torch.Tensor,
                 use: torch.Tensor) -> None:
        self.weights, self.log_likelihood, self.use = weights, log_likelihood, use


def weight_update(w: torch.Tensor, loglik: torch.Tensor, s_run: torch.Tensor) -> WeightUpdate:
    """Bayes' rule on the masses in the log domain: ``log w += loglik``, renormalised by the
    peak (no underflow), never NaN.

    Args:
        w: ``(N, G, G)`` prior masses.
        loglik: ``(N, G, G)`` per-cell log-likelihood (−inf: zero likelihood; no NaN).
        s_run: ``(N,)`` innovation variance (the run constant ``−½ log 2πS``).
    """
    n = w.shape[0]
    logw = log_or_neg_inf(w).add_(loglik)
    peak = logw.amax((1, 2), keepdim=True)
    finite_peak = torch.isfinite(peak)
    wn = exp_or_zero(logw.sub_(torch.where(finite_peak, peak, 0.0)), out_of_place=False)
    total = wn.sum((1, 2))
    fin = finite_peak.reshape(n)
    log_lik = torch.where(fin, -0.5 * (_LOG_2PI + s_run.log()) + peak.reshape(n) + total.log(),
                          -math.inf)
    use = fin & (total > 0) & torch.isfinite(total)
    wn.div_(torch.where(use, total, 1.0)[:, None, None])
    return WeightUpdate(wn, log_lik, use)


def kalman_cells(mu: torch.Tensor, P: torch.Tensor, c: torch.Tensor, nu: torch.Tensor,
                 s_run: torch.Tensor, resp: torch.Tensor | None = None,
                 weights: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The Kalman update of the linear part in every cell (the same gain in every cell).

    Args:
        mu: ``(N, nz, G, G)`` per-cell means; ``P``: ``(N, nz, nz)``; ``c``: ``(nz,)``.
        nu: ``(N, G, G)`` innovations (finite); ``s_run``: ``(N,)`` ``S = cᵀPc + R``.
        resp: ``(N, G, G)`` inlier responsibility of a Gaussian + uniform likelihood, or
            None: the gain is weighted by it and ``P`` shrinks by its posterior mean
            (needs the posterior ``weights (N, G, G)``).

    Returns:
        ``μ + K ν`` ``(N, nz, G, G)`` and ``P − K S Kᵀ`` ``(N, nz, nz)``, ``K = P c / S``.
    """
    gain = mv(P, c) / s_run[:, None]  # (N, nz)
    kks = gain[:, :, None] * gain[:, None, :] * s_run[:, None, None]
    if resp is None:
        mu_new = mu + gain[:, :, None, None] * nu[:, None]
        P_new = P - kks
    else:
        mu_new = mu + gain[:, :, None, None] * (resp * nu)[:, None]
        rbar = (weights * resp).sum((1, 2))
        P_new = P - rbar[:, None, None] * kks
    return mu_new, 0.5 * (P_new + P_new.transpose(1, 2))


# ---------------------------------------------------------------------------- moments
def mass_moments(w: torch.Tensor, off: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean ``(N, 2)`` and covariance ``(N, 2, 2)`` of masses ``w (N, G, G)`` in lattice
    coordinates (cells; separable sums, two passes over ``w``)."""
    wx, wy = w.sum(1), w.sum(2)  # along columns (x) and rows (y)
    ux, uy = mv(wx, off), mv(wy, off)
    cxx = mv(wx, off * off) - ux * ux
    cyy = mv(wy, off * off) - uy * uy
    cxy = mv(mv(w, off), off) - ux * uy
    u = torch.stack([ux, uy], 1)
    cu = torch.stack([torch.stack([cxx, cxy], 1), torch.stack([cxy, cyy], 1)], 1)
    return u, cu


def lattice_moment_tensors(w: torch.Tensor, mu: torch.Tensor, off: torch.Tensor,
                           ) -> tuple[torch.Tensor, ...]:
    """Moments of a lattice state in lattice coordinates, as a tuple of tensors (the
    functional form of `LatticeMoments`, for compiled steps).

    Args:
        w: ``(N, G, G)`` masses; ``mu``: ``(N, nz, G, G)`` per-cell means; ``off``: ``(G,)``.

    Returns:
        ``u (N, 2)``, ``cu (N, 2, 2)``, ``mz (N, nz)``, ``czu (N, nz, 2)``,
        ``czz_b (N, nz, nz)`` (`LatticeMoments`).
    """
    n, nz = mu.shape[0], mu.shape[1]
    u, cu = mass_moments(w, off)
    ux, uy = u[:, 0], u[:, 1]
    wmu = mu * w[:, None]
    mz = wmu.sum((2, 3))  # z̄ = Σ w μ
    czx = mv(wmu.sum(2), off) - mz * ux[:, None]  # Cov_w(μ, o_x)
    czy = mv(wmu.sum(3), off) - mz * uy[:, None]
    czu = torch.stack([czx, czy], 2)
    second = mm(wmu.reshape(n, nz, -1), mu.reshape(n, nz, -1).transpose(1, 2))
    czz = second - mz[:, :, None] * mz[:, None, :]  # Cov_w(μ) = Σ w μ μᵀ − z̄ z̄ᵀ
    return u, cu, mz, czu, 0.5 * (czz + czz.transpose(1, 2))


class LatticeMoments:
    """Moments of a lattice state in lattice coordinates (cheap separable sums).

    Attributes: ``u (N, 2)`` mean cell coordinate, ``cu (N, 2, 2)`` its covariance (cells²),
    ``mz (N, nz)``, ``czu (N, nz, 2)`` ``Cov_w(μ, o)``, ``czz_b (N, nz, nz)`` ``Cov_w(μ)``.
    """

    __slots__ = ("cu", "czu", "czz_b", "mz", "u")

    def __init__(self, w: torch.Tensor, mu: torch.Tensor, off: torch.Tensor) -> None:
        self.u, self.cu, self.mz, self.czu, self.czz_b = lattice_moment_tensors(w, mu, off)

    def tensors(self) -> tuple[torch.Tensor, ...]:
        """``(u, cu, mz, czu, czz_b)``."""
        return self.u, self.cu, self.mz, self.czu, self.czz_b


def gaussian_log_density(off: torch.Tensor, u: torch.Tensor, cu: torch.Tensor) -> torch.Tensor:
    """``(N, G, G)`` ``log N(o; u, cu)`` at the cells (lattice coordinates) up to a per-run
    constant.

    ``cu``'s eigenvalues are floored at 1/12 cell² (the variance of one uniform cell: a
    lattice cannot hold a narrower posterior), so a posterior collapsed onto one cell or one
    line of cells stays invertible; wider posteriors are unchanged.
    """
    vals, vecs = eigh2(0.5 * (cu + cu.transpose(1, 2)))
    floored = vals.clamp_min(1.0 / 12.0)
    inv = mm(vecs / floored[:, None, :], vecs.transpose(1, 2))
    dx = (off[None, :] - u[:, 0:1])[:, None, :]  # (N, 1, G) along columns
    dy = (off[None, :] - u[:, 1:2])[:, :, None]  # (N, G, 1) along rows
    a, b, c = (inv[:, i, j, None, None] for i, j in ((0, 0), (0, 1), (1, 1)))
    return -0.5 * (a * dx * dx + 2.0 * b * dx * dy + c * dy * dy)


def normalised(logw: torch.Tensor) -> torch.Tensor:
    """Masses ``(N, G, G)`` from log masses, normalised by the peak then the sum."""
    w = exp_or_zero(logw - logw.amax((1, 2), keepdim=True), out_of_place=False)
    return w / w.sum((1, 2), keepdim=True)


def affine_field(off: torch.Tensor, g: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """``(N, nz, G, G)`` ``g · (o − u)`` for ``g (N, nz, 2)`` (lattice coordinates)."""
    dx = (off[None, :] - u[:, 0:1])[:, None, None, :]
    dy = (off[None, :] - u[:, 1:2])[:, None, :, None]
    return g[:, :, 0, None, None] * dx + g[:, :, 1, None, None] * dy


# ---------------------------------------------------------------------------- regrid
def resample_bilinear(chans: torch.Tensor, coords: torch.Tensor, *,
                      padding: str = "zeros", opaque: bool = False) -> torch.Tensor:
    """Bilinear samples of lattice channels ``(N, C, G, G)`` at ``coords (N, G', G', 2)``
    given in the old lattice's normalised coordinates (−1 … 1 from the first to the last
    cell, x first); ``padding``: ``zeros`` (density outside is zero) or ``border``.

    ``opaque``: under ``torch.compile``, call the library's kernel as one operation
    (`grid_sample_op`) rather than let the code generator expand it into index arithmetic
    and gathers fused with its neighbours. The expansion is several times slower for many
    runs on the CPU (62 ms against 15 ms for 1000 runs × 4 channels × 32²) and faster for a
    few (the opaque call costs ~30 µs of dispatch).
    """
    coords = coords.to(chans.dtype)
    if opaque and torch.compiler.is_compiling():
        return grid_sample_op(chans, coords, padding)
    return nnf.grid_sample(chans, coords, mode="bilinear", padding_mode=padding,
                           align_corners=True)


@torch.library.custom_op("neuralmap::lattice_grid_sample", mutates_args=())
def grid_sample_op(chans: torch.Tensor, coords: torch.Tensor, padding: str) -> torch.Tensor:
    """``grid_sample`` (bilinear, ``align_corners``) as an opaque operator for compiled
    steps (`resample_bilinear`)."""
    return nnf.grid_sample(chans, coords, mode="bilinear", padding_mode=padding,
                           align_corners=True)


@grid_sample_op.register_fake
def _grid_sample_shape(chans: torch.Tensor, coords: torch.Tensor,
                       padding: str) -> torch.Tensor:
    return chans.new_empty(chans.shape[0], chans.shape[1], coords.shape[1], coords.shape[2])


def cell_reach(points: torch.Tensor, axes: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
    """``(N, G²)`` float64: how far each cell's area reaches from ``centre (N, 2)``, ``d +
    h`` with ``d`` the distance of the cell ``points (N, G, G, 2)`` and ``h`` the half
    diagonal of a cell of steps ``axes (N, 2, 2)`` (columns)."""
    half = 0.5 * torch.maximum((axes[:, :, 0] + axes[:, :, 1]).norm(dim=-1),
                               (axes[:, :, 0] - axes[:, :, 1]).norm(dim=-1))
    return ((points - centre[:, None, None, :].to(points.dtype)).norm(dim=-1)
            + half[:, None, None].to(points.dtype)).flatten(1).double()


def sorted_mass(reach: torch.Tensor, weights: torch.Tensor,
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """``reach (N, M)`` sorted ascending and the cumulative mass ``(N, M)`` of ``weights
    (N, M)`` taken in that order (float64): the mass within each radius."""
    reach, order = torch.sort(reach, dim=1)
    return reach, torch.gather(weights.double(), 1, order).cumsum(1)


def radial_mass_profile(points: torch.Tensor, weights: torch.Tensor, axes: torch.Tensor,
                        centre: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The lattice's mass against the radius around ``centre (N, 2)``: `sorted_mass` of the
    cells' reach (`cell_reach`) and masses ``w (N, G, G)``, ``(N, G²)`` each. The radius
    holding ``1 − risk`` of the mass is `mass_radius`."""
    return sorted_mass(cell_reach(points, axes, centre), weights.flatten(1))


def mass_radius(reach: torch.Tensor, cum: torch.Tensor, risk: float) -> torch.Tensor:
    """``(N,)`` the smallest radius of a `sorted_mass` profile holding at least ``1 − risk``
    of the mass: the reach where the cumulative mass first reaches ``(1 − risk)`` × total."""
    first = (cum >= (1.0 - risk) * cum[:, -1:]).long().argmax(1)
    return reach.gather(1, first[:, None]).squeeze(1)
