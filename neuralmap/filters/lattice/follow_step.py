"""One step of the following lattice as pure, static-shape functions of tensors.

The kernels of `neuralmap.filters.lattice.follow_rule.FollowLattice` (the ``follow`` lattice
rule of `neuralmap.filters.lattice.filter.LatticeFilter`; model, equations and rules in
that module's docstring) — the prediction (`predict_prepare`, `predict_finish`), the
measurement update (`update_core`), the lost-track window (`lost_window_core`), the regrid
(`regrid_rule`, `regrid_move`), the moment correction (`matched_core`, `transport2`,
`p_floor`) and the lattice for a Gaussian (`lattice_for_core`) — and the two **static
steps** composed of them, `predict_step` and `update_step` (with `regrid_rows_step`), for
N runs at once in a fixed sequence of tensor operations:

* **no data-dependent Python branch.** Every run computes every path and keeps its own by
  ``torch.where`` (its moved lattice kept where the regrid rule moves it); a step returns
  what fired as a few flags, which its driver reads in one host read per prediction and
  per update (one more, the number of moved runs, where a large CPU batch resamples only
  those: about a third per step);
* **rare events are flags, not work for every run.** A posterior narrower than the cells
  (its Gaussian refit), a blur kernel longer than the step's band, two eigenvalues of the
  linear part's covariance at its floor, a lost-track widening, a lattice error: the
  driver redoes the prediction, or the update of the runs concerned, with the eager
  branches of the same kernels (results equal to the eager driver, tested);
* **one source for eager, CPU code generation and CUDA.** `compiled` wraps the step
  functions in ``torch.compile`` (inductor: C++ on the CPU, Triton on CUDA); run eagerly
  they are the fallback and the reference the compiled ones are tested against
  (tests/filters/test_lattice_step.py). Small matrix products go through
  `neuralmap.filters.lattice.algebra2.mm` (fused by the code generator), the bilinear
  resampling of many runs through one library call (`kernels.resample_bilinear`).

Precision: the state, the update and the convolutions run in the filter's dtype; float64 in
both dtypes only where float32 is not accurate enough:

* the 2 × 2 moment-correction map ``T`` (`transport2`): its determinants of an elongated
  posterior (condition ~1e4 and above) lose that many digits; in float32 the small
  direction is at round-off and ``T`` collapsed the lattice (a float32 tracker at 32
  cells crashed; tests/filters/test_point_mass_tracker.py::
  test_float32_moment_correction_of_an_elongated_posterior_keeps_its_covariance);
* the positive-definiteness tests (`neuralmap.filters.lattice.algebra2.spd_ok`,
  ``spd2_ok``) and the eigenvalues of the eigenvalue floor (`p_floor`, ``eigvalsh3``):
  decisions against ``1e-12`` of the largest eigenvalue
  (tests/filters/test_lattice_step.py::
  test_eigenvalue_floor_of_the_linear_part_is_the_lapack_floor).

Lattice coordinates: ``o = (j − h, i − h)`` for cell ``(i, j)``; ``off (G,)`` holds
``j − h``.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import torch

import neuralmap.filters.lattice.kernels as _kernels
from neuralmap.filters.lattice.algebra2 import (
    eigh2,
    eigvalsh3,
    few_for_lapack,
    inv2,
    mm,
    mv,
    solve2,
    spd2_ok,
    spd_ok,
)
from neuralmap.filters.lattice.kernels import (
    affine_field,
    cell_log_likelihood,
    conditional_mean,
    gaussian_log_density,
    kalman_cells,
    lattice_moment_tensors,
    normalised,
    resample_bilinear,
    weight_update,
)

__all__ = ["BLUR_MIN_CELLS", "FAST_BAND", "MIN_CELL_VARIANCE", "PREDICT_FLAGS", "UPDATE_FLAGS",
           "FollowParams", "Targets", "blur_band", "compiled", "floor_p_rows", "joint_moments",
           "kernel_length", "lattice_for_core", "lattice_points", "lost_window_core",
           "matched_core", "p_floor", "predict_finish", "predict_prepare", "predict_step",
           "predictive_nis_core", "regrid_move", "regrid_rows_step", "regrid_rule",
           "state_moments", "thin_flag", "update_core", "update_step"]

#: Transition noise below this many cells (1σ, every run and axis) is left to the moment
#: correction alone (an affine stretch of the lattice) instead of a blur.
BLUR_MIN_CELLS = 1e-3

#: Smallest variance (cells², along any direction) of masses the moment correction may
#: stretch; a narrower posterior is replaced by its Gaussian fit on a fresh lattice.
MIN_CELL_VARIANCE = 0.25

#: Half-lengths (taps each side) of the static step's blur bands: 1 (every run's noise below
#: 0.7 cells: the three-tap kernel), `FAST_BAND` (shifted slices) or ``G − 1`` (one banded
#: Toeplitz product per axis). A kernel longer than the step's band sets a flag and the
#: step is redone eagerly; the next step takes the band this one needed.
FAST_BAND = 4

#: Transition noise (cells, 1σ) from which the blur kernel is a sampled Gaussian (below:
#: the three-tap kernel of exact variance; `gaussian_kernels`).
GAUSS_MIN_CELLS = 0.7

#: Floor of the log ratio posterior / Gaussian fit in a regrid (relative to its peak).
LOG_R_FLOOR = -60.0

#: Relative floor of the eigenvalues of the linear part's conditional covariance.
P_FLOOR = 1e-12


class FollowParams(NamedTuple):
    """Static options of one step (Python numbers: constants of a compiled step).

    Attributes: as `neuralmap.filters.lattice.follow_rule.TrackerConfig`, plus ``half``
    (``(G − 1)/2``), ``regrid_box`` (``regrid_sigma / span_sigma``, 1 without hysteresis),
    ``max_spacing`` (``inf`` when unbounded), ``band`` (blur half-length of the step) and
    ``f_identity`` (``F = I``: the per-cell means need no transition).
    """

    cells: int
    half: float
    span_sigma: float
    principal_axes: bool
    recentre_fraction: float
    regrid_box: float
    resize_ratio: float
    min_half_width: float
    max_spacing: float
    weight_floor: float
    f_identity: bool
    band: int


class Targets(NamedTuple):
    """Moments a moment correction imposes: ``ms (N, 2)``, ``css (N, 2, 2)``, ``mz (N, nz)``,
    ``czz (N, nz, nz)``, ``czs (N, nz, 2)``."""

    ms: torch.Tensor
    css: torch.Tensor
    mz: torch.Tensor
    czz: torch.Tensor
    czs: torch.Tensor


def _sym(m: torch.Tensor) -> torch.Tensor:
    return 0.5 * (m + m.transpose(-1, -2))


def _rows(mask: torch.Tensor, k: int) -> torch.Tensor:
    """``mask (N,)`` viewed with ``k`` trailing singleton dimensions."""
    return mask.reshape(-1, *([1] * k))


def lattice_points(centre: torch.Tensor, axes: torch.Tensor, off: torch.Tensor) -> torch.Tensor:
    """``(N, G, G, 2)`` cell coordinates ``centre + A (j − h, i − h)``."""
    col = axes[:, None, None, :, 0] * off[None, None, :, None]
    row = axes[:, None, None, :, 1] * off[None, :, None, None]
    return centre[:, None, None, :] + col + row


def state_moments(lm: tuple[torch.Tensor, ...], P: torch.Tensor, centre: torch.Tensor,
                  axes: torch.Tensor) -> Targets:
    """Moments of the lattice state in state units: ``ms = c + A u``, ``css = A cu Aᵀ``,
    ``mz``, ``czz = P + Cov_w(μ)``, ``czs = Cov_w(μ, o) Aᵀ``."""
    u, cu, mz, czu, czz_b = lm
    ms = centre + mv(axes, u)
    css = _sym(mm(mm(axes, cu), axes.transpose(1, 2)))
    czs = mm(czu, axes.transpose(1, 2))
    czz = P + czz_b
    return Targets(ms, css, mz, _sym(czz), czs)


def joint_moments(t: Targets) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean ``(N, 2+nz)`` and covariance ``(N, 2+nz, 2+nz)`` of ``[s, z]``."""
    mean = torch.cat([t.ms, t.mz], 1)
    cov = torch.cat([torch.cat([t.css, t.czs.transpose(1, 2)], 2),
                     torch.cat([t.czs, t.czz], 2)], 1)
    return mean, _sym(cov)


def thin_flag(cu: torch.Tensor) -> torch.Tensor:
    """``(N,)`` bool: masses narrower than `MIN_CELL_VARIANCE` cells² along some direction
    (the smallest eigenvalue of ``cu`` below it: ``cu − t I`` not positive semi-definite;
    False for non-finite moments)."""
    t = MIN_CELL_VARIANCE
    a, b, d = cu[:, 0, 0] - t, cu[:, 0, 1], cu[:, 1, 1] - t
    return (a < 0) | (d < 0) | (a * d - b * b < 0)


# ---------------------------------------------------------------------------- blur
def blur_band(chans: torch.Tensor, sigma_cells: torch.Tensor, half_len: torch.Tensor,
              band: int) -> torch.Tensor:
    """`neuralmap.filters.lattice.kernels.blur` with a static band.

    The kernels of ``sigma_cells (N, 2)`` are those of `gaussian_kernels` at the half-length
    ``half_len`` (a 0-d tensor, ``≤ band``), stored in ``2·band + 1`` taps (zero beyond
    ``half_len``): the same numbers as the kernel of length ``2·half_len + 1`` without a
    host read of ``half_len``. ``band ≤ BANDED_MIN_HALF_LEN``: shifted slices; above: one
    banded Toeplitz product per axis (`convolve_axis`).
    """
    dtype, device = sigma_cells.dtype, sigma_cells.device
    k = torch.arange(-band, band + 1, dtype=dtype, device=device)
    inside = k.abs() <= half_len

    def kernels(sig: torch.Tensor) -> torch.Tensor:
        s = sig.clamp_min(1e-6)[:, None]
        gauss = torch.where(inside, torch.exp(-0.5 * (k / s) ** 2), 0.0)
        gauss = gauss / gauss.sum(1, keepdim=True)
        var = s.squeeze(1) ** 2
        third = 0.5 * var.clamp_max(0.5)  # the three-tap kernel of variance σ² (< 0.7 cells)
        tap = torch.where(k == 0, 1.0 - var.clamp_max(0.5)[:, None],
                          torch.where(k.abs() == 1, third[:, None], 0.0))
        return torch.where((sig >= GAUSS_MIN_CELLS)[:, None], gauss, tap)

    conv = _kernels.convolve_axis  # looked up per call (tests spy on the kernel lengths)
    out = conv(chans, kernels(sigma_cells[:, 0]), band, dim=3)
    return conv(out, kernels(sigma_cells[:, 1]), band, dim=2)


# ---------------------------------------------------------------------------- lattice for
def lattice_for_core(mean: torch.Tensor, cov: torch.Tensor, q: torch.Tensor,
                     p: FollowParams) -> tuple[torch.Tensor, ...]:
    """Centre ``(N, 2)`` and cell steps ``(N, 2, 2)`` of a lattice for ``N(mean, cov)``
    (principal axes or x/y, half-width ``span_sigma · sqrt(σ² + q)`` per axis, at least
    ``min_half_width``); ``q (N, 2)``: the next step's process noise.

    Returns:
        ``centre, axes, step (N, 2), too_coarse (N,), bad (N,)``: cells above
        ``max_spacing``; zero or non-finite cells (the driver raises for the runs it uses).
    """
    if p.principal_axes:
        lam, vec = eigh2(_sym(cov))
        qa = torch.einsum("nki,nk->ni", vec * vec, q)  # q projected on the axes
    else:
        lam = torch.diagonal(cov, dim1=1, dim2=2)
        vec = torch.eye(2, dtype=cov.dtype, device=cov.device).expand_as(cov)
        qa = q
    halfw = (p.span_sigma * (lam.clamp_min(0.0) + qa).sqrt()).clamp_min(p.min_half_width)
    step = halfw / p.half
    too_coarse = (step > p.max_spacing * (1 + 1e-9)).any(1)
    bad = ~(torch.isfinite(step).all(1) & (step > 0).all(1))
    return mean.clone(), vec * step[:, None, :], step, too_coarse, bad


# ---------------------------------------------------------------------------- moments
def p_floor(P: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The linear part's covariance with its eigenvalues floored at ``P_FLOOR`` of the
    largest (round-off: keeps the Kalman part positive definite), and a flag.

    ``P = V diag(max(λ, f)) Vᵀ``. ``nz ≤ 2``: closed form. ``nz = 3``: for a few runs
    outside ``torch.compile`` LAPACK (`floor_p_rows`); else the eigenvalues in
    closed form (`eigvalsh3`, float64) and, where the smallest is below the floor, the
    rank-one correction ``P + (f − λ_min) v vᵀ`` with ``v`` the cross product of two rows of
    ``P − λ_min I`` (the same matrix: only ``λ_min`` is floored); the flag is set where the
    two smallest eigenvalues are within 1e-6 of the largest of each other (``v``
    ill-defined, the closed form's eigenvalues less accurate there: the driver floors those
    runs with LAPACK, `floor_p_rows`). Larger ``nz``: LAPACK in the step.

    Returns:
        ``P (N, nz, nz)`` and ``(N,)`` bool.
    """
    nz = P.shape[-1]
    none = torch.zeros(P.shape[0], dtype=torch.bool, device=P.device)
    if nz == 3 and few_for_lapack(P):
        return floor_p_rows(P), none
    if nz == 3:
        a = P.double()
        lam = eigvalsh3(a)
        big = lam.abs().amax(-1).clamp_min(1e-300)
        floor = P_FLOOR * big
        low = lam[:, 0] < floor
        # the trigonometric eigenvalues of a near-degenerate pair err by ~sqrt(eps)·|λ|:
        # such a pair at the floor is LAPACK's (`floor_p_rows`)
        hard = low & (lam[:, 1] - lam[:, 0] < 1e-6 * big)
        m = a - lam[:, 0, None, None] * torch.eye(3, dtype=a.dtype, device=a.device)
        r0, r1, r2 = m[:, 0], m[:, 1], m[:, 2]
        crosses = torch.stack([_cross(r0, r1), _cross(r0, r2), _cross(r1, r2)], 1)
        norms = (crosses * crosses).sum(-1)  # (N, 3)
        best = norms.argmax(-1, keepdim=True)
        v = crosses.gather(1, best[:, :, None].expand(-1, 1, 3)).squeeze(1)
        v = v / norms.gather(1, best).clamp_min(1e-300).sqrt()
        fixed = a + (floor - lam[:, 0])[:, None, None] * (v[:, :, None] * v[:, None, :])
        fixed = _sym(fixed).to(P.dtype)
        return torch.where((low & ~hard)[:, None, None], fixed, P), hard
    if nz == 1:
        lam, vec = P[:, :, 0], torch.ones_like(P)
    elif nz == 2:
        lam, vec = eigh2(P)
    else:
        lam, vec = torch.linalg.eigh(P)
    floor = P_FLOOR * lam.abs().amax(-1, keepdim=True).clamp_min(1e-300)
    low = (lam < floor).any(-1)
    fixed = _sym(mm(vec * lam.clamp_min(floor)[:, None, :], vec.transpose(1, 2)))
    return torch.where(low[:, None, None], fixed, P), none


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``(N, 3)`` cross product ``a × b``."""
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    return torch.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], -1)


def floor_p_rows(P: torch.Tensor) -> torch.Tensor:
    """``P (K, nz, nz)`` with eigenvalues below ``P_FLOOR`` of the largest raised to it
    (LAPACK eigh: the runs `p_floor` flags, or a few runs outside ``torch.compile``);
    non-finite matrices are returned unchanged."""
    ok = torch.isfinite(P).flatten(1).all(1)
    eye = torch.eye(P.shape[-1], dtype=P.dtype, device=P.device)
    lam, vec = torch.linalg.eigh(torch.where(ok[:, None, None], P, eye))
    floor = P_FLOOR * lam.abs().amax(-1, keepdim=True).clamp_min(1e-300)
    low = (lam < floor).any(-1) & ok
    fixed = _sym((vec * lam.clamp_min(floor)[:, None, :]) @ vec.transpose(1, 2))
    return torch.where(low[:, None, None], fixed, P)


def transport2(c: torch.Tensor, ct: torch.Tensor) -> torch.Tensor:
    """``(N, 2, 2)`` the symmetric map ``T`` with ``T C T = C_t`` closest to the identity,
    ``T = C^{-1/2} (C^{1/2} C_t C^{1/2})^{1/2} C^{-1/2}``, in closed form for 2 × 2:

    ``T = (C_t + sqrt(det C_t / det C) adj C) / sqrt(tr(C C_t) + 2 sqrt(det C det C_t))``

    (the square root of a 2 × 2 SPD matrix ``M`` is ``(M + sqrt(det M) I) / sqrt(tr M +
    2 sqrt(det M))``; with ``S = C^{1/2}``: ``tr(S C_t S) = tr(C C_t)`` and ``S⁻¹ S⁻¹ =
    adj C / det C``). ``C = C_t`` gives ``I`` (``C + adj C = tr C · I``). Non-finite where
    ``C`` or ``C_t`` is not positive definite (the caller keeps ``I`` there).

    Args:
        c, ct: ``(N, 2, 2)`` symmetric positive definite (float64: the determinants of an
            elongated covariance lose ``log10`` of its condition number in digits).
    """
    a, b, d = c[:, 0, 0], 0.5 * (c[:, 0, 1] + c[:, 1, 0]), c[:, 1, 1]
    at, bt, dt = ct[:, 0, 0], 0.5 * (ct[:, 0, 1] + ct[:, 1, 0]), ct[:, 1, 1]
    det, det_t = a * d - b * b, at * dt - bt * bt
    r = (det_t / det).sqrt()  # sqrt(det C det C_t) C⁻¹ = r adj C
    tau = (a * at + 2.0 * b * bt + d * dt + 2.0 * (det * det_t).sqrt()).sqrt()
    off = (bt - r * b) / tau
    return torch.stack([torch.stack([(at + r * d) / tau, off], -1),
                        torch.stack([off, (dt + r * a) / tau], -1)], -2)


def matched_core(w: torch.Tensor, mu: torch.Tensor, P: torch.Tensor, centre: torch.Tensor,
                 axes: torch.Tensor, t: Targets, off: torch.Tensor,
                 ) -> tuple[tuple[torch.Tensor, ...], torch.Tensor, torch.Tensor]:
    """The moment correction: the lattice state with mean and covariance ``t`` exactly.

    The lattice is moved by the affine map ``s ↦ m_t + T (s − m)``,
    ``T = C^{-1/2} (C^{1/2} C_t C^{1/2})^{1/2} C^{-1/2}`` (float64, `transport2`), the
    per-cell means get ``μ ← μ + Δz̄ + g (o − u)`` with ``g`` such that ``Cov(z, s)`` hits
    its target, and
    ``P ← C_zz,t − Cov_w(μ)`` (module docstring of ``follow_rule``).

    Returns:
        ``(w, mu, P, centre, axes)``, ``thin (N,)`` (the input masses are narrower than
        `MIN_CELL_VARIANCE`: the driver replaces those runs by the Gaussian of ``t``) and
        ``floor (N,)`` (`p_floor`).
    """
    u, cu, mz, czu, czz_b = lattice_moment_tensors(w, mu, off)
    thin = thin_flag(cu)
    css = _sym(mm(mm(axes, cu), axes.transpose(1, 2)))
    # the 2 x 2 map in float64: in float32 the small eigenvalue of an elongated posterior
    # (condition ~1e4) is at round-off level and T would collapse the lattice
    T = transport2(css.double(), t.css.double()).to(w.dtype)
    ok = torch.isfinite(T).flatten(1).all(1) & spd2_ok(css) & spd2_ok(_sym(t.css))
    eye = torch.eye(2, dtype=w.dtype, device=w.device).expand_as(T)
    T = torch.where(ok[:, None, None], T, eye)
    axes = mm(T, axes)
    centre = t.ms - mv(axes, u)
    # z: mean shift and a per-cell-step gain gu so that Cov(z, s) hits its target
    want = solve2(axes, t.czs.transpose(1, 2)).transpose(1, 2)  # czs_t A^-T
    gu = solve2(cu, (want - czu).transpose(1, 2)).transpose(1, 2)
    mu = mu + (t.mz - mz)[:, :, None, None] + affine_field(off, gu, u)
    czz_b = (czz_b + mm(gu, czu.transpose(1, 2)) + mm(czu, gu.transpose(1, 2))
             + mm(mm(gu, cu), gu.transpose(1, 2)))
    P, floor = p_floor(_sym(t.czz - czz_b))
    return (w, mu, P, centre, axes), thin, floor


# ---------------------------------------------------------------------------- predict
def predict_prepare(w: torch.Tensor, mu: torch.Tensor, P: torch.Tensor, centre: torch.Tensor,
                    axes: torch.Tensor, lm: tuple[torch.Tensor, ...], E: torch.Tensor,
                    F: torch.Tensor, qs: torch.Tensor, qz: torch.Tensor, shift: torch.Tensor,
                    open_mean: torch.Tensor, open_cov: torch.Tensor) -> dict[str, Any]:
    """The first half of the time update (``follow_rule`` module docstring): the exact
    predicted moments, the lattice moved by the affine part of the shift ``E μ``, the blur's
    variance in cells, the next step's process noise and the open-loop prior.

    Args:
        w, mu, P, centre, axes: The lattice state; ``lm``: its `lattice_moment_tensors`.
        E: ``(2, nz)``; ``F``: ``(nz, nz)``; ``qs``: ``(N, 2, 2)``; ``qz``: ``(N, nz, nz)``;
            ``shift``: ``(N, 2)`` known displacement.
        open_mean, open_cov: The open-loop prior ``(N, 2+nz)``, ``(N, 2+nz, 2+nz)``.

    Returns:
        ``targets`` (`Targets`), ``gzu (N, nz, 2)``, ``axes``, ``centre`` (the moved lattice),
        ``var_c (N, 2)`` (blur variance in cells along the lattice axes), ``q_next``,
        ``open_mean``, ``open_cov``, ``thin_start`` (the input masses need their Gaussian
        refit first) and ``healthy`` (finite, positive definite predicted moments).
    """
    nz = mu.shape[1]
    u_c, cu, mz, czu, czz_b = lm
    cur = state_moments(lm, P, centre, axes)
    ms, css, czz, czs = cur.ms, cur.css, cur.czz, cur.czs
    # exact predicted moments
    ms_t = ms + mm(mz, E.T) + shift
    csz = czs.transpose(1, 2)
    css_t = _sym(css + mm(E, czs) + mm(csz, E.T) + mm(mm(E, czz), E.T) + qs)
    mz_t = mm(mz, F.T)
    czz_t = _sym(mm(mm(F, czz), F.T) + qz)
    czs_t = mm(F, czs + mm(czz, E.T))
    # the per-cell z mean = its affine fit in the cell coordinates + a residual; the
    # affine part of the shift E μ moves the lattice (exact), the residual's spread is
    # transition noise
    gzu = solve2(cu, czu.transpose(1, 2)).transpose(1, 2)  # (N, nz, 2)
    cz_res = _sym(czz_b - mm(gzu, czu.transpose(1, 2)))
    axes_new = axes + mm(E, gzu)  # shift per cell step B_u = E gzu
    centre_new = ms_t - mv(axes_new, u_c)
    sig_eta = _sym(mm(mm(E, P), E.T) + qs + mm(mm(E, cz_res), E.T))
    # blur by separable kernels of exact variance along the lattice axes; the cross-axis
    # part and any remainder are carried by the moment correction (an affine stretch)
    inv_a = inv2(axes_new)
    k_cells = mm(mm(inv_a, sig_eta), inv_a.transpose(1, 2))
    var_c = torch.diagonal(k_cells, dim1=1, dim2=2).clamp_min(0.0)  # (N, 2) x, y
    healthy = torch.isfinite(ms_t).all(1) & spd2_ok(css_t) & spd_ok(czz_t)
    q_next = torch.diagonal(qs + mm(mm(E, P), E.T), dim1=1, dim2=2)
    # the open-loop prior through one prediction: m ← A m + u, P ← A P Aᵀ + Q
    eye = torch.eye(2 + nz, dtype=w.dtype, device=w.device)
    A = torch.cat([torch.cat([eye[:2, :2], E], 1), torch.cat([eye[2:, :2], F], 1)], 0)
    om = mm(open_mean, A.T) + torch.cat([shift, torch.zeros_like(open_mean[:, 2:])], 1)
    oc = mm(mm(A, open_cov), A.T) + torch.cat([
        torch.cat([qs, torch.zeros_like(open_cov[:, :2, 2:])], 2),
        torch.cat([torch.zeros_like(open_cov[:, 2:, :2]), qz], 2)], 1)
    return {"targets": Targets(ms_t, css_t, mz_t, czz_t, czs_t), "gzu": gzu,
            "axes": axes_new, "centre": centre_new, "var_c": var_c, "q_next": q_next,
            "open_mean": om, "open_cov": _sym(oc), "thin_start": thin_flag(cu),
            "healthy": healthy}


def kernel_length(var_c: torch.Tensor, cells: int,
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The blur decision of a batch (0-d tensors): ``blur_on`` (some run's transition noise
    reaches `BLUR_MIN_CELLS`), the kernel half-length ``⌈4 σ_max⌉`` in ``[1, G − 1]`` (one
    length for the batch, `gaussian_kernels`) and the band it needs (1 while every run's
    kernel is the three-tap one: its taps beyond ±1 are zero)."""
    vmax = var_c.max()
    half_len = torch.ceil(4.0 * vmax.sqrt()).clamp(1.0, cells - 1.0)
    return (vmax >= BLUR_MIN_CELLS**2, half_len,
            torch.where(vmax.sqrt() >= GAUSS_MIN_CELLS, half_len, 1.0))


def predict_finish(w: torch.Tensor, mu: torch.Tensor, P: torch.Tensor,
                   lm: tuple[torch.Tensor, ...], prep: dict[str, Any], F: torch.Tensor,
                   off: torch.Tensor, p: FollowParams, blur_on: torch.Tensor | bool,
                   half_len: torch.Tensor | float,
                   ) -> tuple[tuple[torch.Tensor, ...], torch.Tensor, torch.Tensor]:
    """The second half of the time update: the masses and ``w (μ − affine fit)`` blurred by
    the separable kernels (``p.band`` taps each side, zero beyond ``half_len``), the per-cell
    means recovered as the ratio, ``F`` applied, then the moment correction to the exact
    predicted moments (`matched_core`).

    ``blur_on``: a Python bool (the eager driver: no blur computed when False) or a 0-d
    tensor (the static step: both computed, one kept).

    Returns:
        The predicted state, and ``thin``, ``floor`` of `matched_core`.
    """
    u_c, mz = lm[0], lm[2]
    w_new, mu_new = w, mu
    if blur_on is not False:
        affine = mz[:, :, None, None] + affine_field(off, prep["gzu"], u_c)
        chans = blur_band(torch.cat([w[:, None], w[:, None] * (mu - affine)], 1),
                          prep["var_c"].sqrt(), half_len, p.band)
        mass = chans[:, 0].clamp_min(0.0)
        w_b = mass / mass.sum((1, 2), keepdim=True).clamp_min(torch.finfo(w.dtype).tiny)
        mu_b = conditional_mean(mass, chans[:, 1:]) + affine
        if blur_on is True:
            w_new, mu_new = w_b, mu_b
        else:
            w_new, mu_new = torch.where(blur_on, w_b, w), torch.where(blur_on, mu_b, mu)
    if not p.f_identity:
        mu_new = torch.einsum("yz,nzij->nyij", F, mu_new)
    return matched_core(w_new, mu_new, P, prep["centre"], prep["axes"], prep["targets"], off)


#: The flags of a static prediction, in the order of its host read.
PREDICT_FLAGS = ("thin_start", "wide", "thin", "floor", "unhealthy")


def predict_step(w: torch.Tensor, mu: torch.Tensor, P: torch.Tensor, centre: torch.Tensor,
                 axes: torch.Tensor, lm: tuple[torch.Tensor, ...] | None, E: torch.Tensor,
                 F: torch.Tensor, qs: torch.Tensor, qz: torch.Tensor, shift: torch.Tensor,
                 open_mean: torch.Tensor, open_cov: torch.Tensor, off: torch.Tensor,
                 p: FollowParams) -> tuple[Any, ...]:
    """The static time update of every run (`predict_prepare`, `predict_finish`; ``lm``
    None: computed here, one fused pass when compiled).

    Returns:
        ``state`` (``(w, mu, P, centre, axes)``), ``points`` ``(N, G, G, 2)``, ``q_next``,
        ``open_mean``, ``open_cov``, ``healthy`` ``(N,)`` and ``read`` ``(6,)``: whether any
        run raised each of `PREDICT_FLAGS` (``wide``: the kernel is longer than ``p.band``;
        ``floor``: `p_floor`'s flag), then the band the kernel needs (0 without a blur).
        The driver commits the state when none of the first four is set (``unhealthy``
        runs then get the guard) and redoes the step with its eager branches otherwise.
    """
    if lm is None:
        lm = lattice_moment_tensors(w, mu, off)
    prep = predict_prepare(w, mu, P, centre, axes, lm, E, F, qs, qz, shift, open_mean,
                           open_cov)
    blur_on, half_len, need = kernel_length(prep["var_c"], p.cells)
    state, thin, floor = predict_finish(w, mu, P, lm, prep, F, off, p, blur_on, half_len)
    wide = blur_on & (need > p.band)
    flags = torch.stack([prep["thin_start"].any(), wide, thin.any(), floor.any(),
                         (~prep["healthy"]).any()]).to(w.dtype)
    read = torch.cat([flags, torch.where(blur_on, need, 0.0)[None]])
    return (state, lattice_points(state[3], state[4], off), prep["q_next"],
            prep["open_mean"], prep["open_cov"], prep["healthy"], read)


# ---------------------------------------------------------------------------- regrid
def regrid_rule(lm: tuple[torch.Tensor, ...], axes: torch.Tensor, q_next: torch.Tensor,
                force: torch.Tensor | None, p: FollowParams) -> torch.Tensor:
    """``(N,)`` bool: the runs the regrid rule moves (``follow_rule`` module docstring): mean
    off the central ``recentre_fraction``, the ``± regrid_sigma σ`` box poking out, a
    lattice more than ``resize_ratio`` too wide (unless at ``min_half_width``), principal
    axes turned (``|ρ| > 0.5``) or ``force``; never a run whose masses are degenerate."""
    u, cu = lm[0], lm[1]
    h = p.half
    inv_a = inv2(axes)
    sig = torch.diagonal(cu, dim1=1, dim2=2).clamp_min(0.0).sqrt()
    qc = torch.diagonal(mm(mm(inv_a, torch.diag_embed(q_next)), inv_a.transpose(1, 2)),
                        dim1=1, dim2=2)
    need = p.span_sigma * (sig**2 + qc).sqrt()
    rho = cu[:, 0, 1] / (sig[:, 0] * sig[:, 1]).clamp_min(1e-300)
    off_centre = (u.abs() > p.recentre_fraction * h).any(1)
    pokes_out = (u.abs() + need * p.regrid_box > h * (1 + 1e-6)).any(1)
    too_coarse = (need * p.resize_ratio < h).any(1)
    if p.min_half_width > 0:  # a guarded lattice at its floor is not "too coarse"
        floor_cells = p.min_half_width / torch.linalg.vector_norm(axes, dim=1)
        too_coarse = too_coarse & ~(floor_cells >= h * (1 - 1e-6)).all(1)
    move = off_centre | pokes_out | too_coarse | ~torch.isfinite(need).all(1)
    if p.principal_axes:
        move = move | (rho.abs() > 0.5)
    if force is not None:
        move = move | force
    return move & spd2_ok(cu)


def regrid_move(w: torch.Tensor, mu: torch.Tensor, P: torch.Tensor, centre: torch.Tensor,
                axes: torch.Tensor, lm: tuple[torch.Tensor, ...], q_next: torch.Tensor,
                off: torch.Tensor, p: FollowParams, opaque: bool = False) -> dict[str, Any]:
    """The runs moved to a lattice centred on their mean, sized for ``± span_sigma σ``
    (`lattice_for_core`), with their moments kept exactly.

    Gaussian-factored resampling: ``w = N(o; u, C_u) · r(o)``; the Gaussian factor is
    evaluated exactly at the new cells, only ``log r`` (0 for a Gaussian posterior) and the
    residual of the per-cell means from their affine fit (0 for a linear-Gaussian model)
    are interpolated bilinearly: a Gaussian posterior moves without error.

    Returns:
        ``state``, ``targets`` (the moments kept), ``thin``, ``floor`` (`matched_core`),
        ``too_coarse``, ``bad`` (`lattice_for_core`).
    """
    u, cu, mz, czu, czz_b = lm
    h = p.half
    t = state_moments(lm, P, centre, axes)
    c_n, a_n, _, coarse_err, bad_err = lattice_for_core(t.ms, t.css, q_next, p)
    # old cell coordinates of the new cells: o_old = A_o⁻¹ (c_n − c_o) + A_o⁻¹ A_n o
    inv_a = inv2(axes)
    base = mv(inv_a, c_n - centre)
    lin = mm(inv_a, a_n)
    uv = (base[:, None, None, :] + lin[:, None, None, :, 0] * off[None, None, :, None]
          + lin[:, None, None, :, 1] * off[None, :, None, None]) / h
    tiny = torch.finfo(w.dtype).tiny
    log_r = w.clamp_min(tiny).log() - gaussian_log_density(off, u, cu)
    log_r = (log_r - log_r.amax((1, 2), keepdim=True)).clamp_min(LOG_R_FLOOR)
    gzu = solve2(cu, czu.transpose(1, 2)).transpose(1, 2)
    resid = mu - mz[:, :, None, None] - affine_field(off, gzu, u)
    out = resample_bilinear(torch.cat([log_r[:, None], resid], 1), uv, padding="border",
                            opaque=opaque)
    ia_n = inv2(a_n)
    cu_n = _sym(mm(mm(ia_n, t.css), ia_n.transpose(1, 2)))
    zero = torch.zeros_like(u)
    w_n = normalised(out[:, 0] + gaussian_log_density(off, zero, cu_n))
    g_n = mm(t.czs, solve2(t.css, a_n))  # z-gain per new cell step
    mu_n = out[:, 1:] + mz[:, :, None, None] + affine_field(off, g_n, zero)
    state, thin, floor = matched_core(w_n, mu_n, P, c_n, a_n, t, off)
    return {"state": state, "targets": t, "thin": thin, "floor": floor,
            "too_coarse": coarse_err, "bad": bad_err}


# ---------------------------------------------------------------------------- update
def update_core(w: torch.Tensor, mu: torch.Tensor, P: torch.Tensor, c: torch.Tensor,
                y: torch.Tensor, g: torch.Tensor, r: torch.Tensor, mask: torch.Tensor | None,
                cell_variance: torch.Tensor | None, *, reports_nis: bool,
                outlier_prob: float, outlier_width: float, floor_weights,
                ) -> dict[str, object]:
    """The measurement update of every run (``filter`` module docstring): ``ν = y − g − c·μ``,
    ``S = cᵀPc + R``, ``log w += −½ ν²/S``, ``μ += K ν``, ``P ← P − K S Kᵀ``.

    Args:
        w, mu, P: Masses ``(N, G, G)``, per-cell means ``(N, nz, G, G)``, ``(N, nz, nz)``.
        c: ``(nz,)``; ``y``: ``(N,)`` (NaN: no measurement); ``g``: ``(N, G, G)`` (non-finite:
            zero likelihood); ``r``: ``(N,)`` R; ``mask``: ``(N,)`` bool or None;
            ``cell_variance``: ``(N, G, G)`` or None.
        reports_nis: Compute the mixture's predictive NIS.
        outlier_prob, outlier_width: Gaussian + uniform likelihood (0: Gaussian).
        floor_weights: The rule's weight floor (a function of the posterior masses).

    Returns:
        ``state`` (``(w, mu, P)``, the runs not applied unchanged), ``log_likelihood``,
        ``recovered``, ``applied``, ``nis`` and ``innovation`` (None unless
        ``reports_nis``; NIS not yet masked by ``applied``), ``r_bad`` (``(N,)``: R not
        finite and positive; the driver raises).
    """
    r_bad = ~((r > 0) & torch.isfinite(r))
    s_run = (mv(P, c) * c).sum(-1) + r  # (N,) S = cᵀPc + R, the same in every cell
    yhat_cell = g + torch.einsum("z,nzij->nij", c, mu)
    nu = y[:, None, None] - yhat_cell  # ν = y − g − c·μ
    finite_cell = torch.isfinite(nu)
    nis = innov = None
    if reports_nis:  # the mixture's predictive moments of y (over the cells on the map)
        yhat, s_y, _ = _mixture_moments(w, yhat_cell, torch.isfinite(yhat_cell), s_run)
        innov = y - yhat
        nis = innov * innov / s_y
    nu = torch.where(finite_cell, nu, 0.0)
    loglik, resp = cell_log_likelihood(nu, s_run, cell_variance, outlier_prob=outlier_prob,
                                       outlier_width=outlier_width)
    loglik = torch.where(finite_cell, loglik, -math.inf)
    upd = weight_update(w, torch.nan_to_num(loglik, nan=-math.inf, neginf=-math.inf), s_run)
    has_y = torch.isfinite(y)
    use = upd.use & has_y
    recovered = ~upd.use & has_y
    if mask is not None:
        recovered = recovered & mask
        use = use & mask
    wn = floor_weights(upd.weights)
    mu_new, P_new = kalman_cells(mu, P, c, nu, s_run, resp, wn)
    state = (torch.where(use[:, None, None], wn, w),
             torch.where(use[:, None, None, None], mu_new, mu),
             torch.where(use[:, None, None], P_new, P))
    return {"state": state, "log_likelihood": upd.log_likelihood, "recovered": recovered,
            "applied": use, "nis": nis, "innovation": innov, "r_bad": r_bad}


def _mixture_moments(w: torch.Tensor, yc: torch.Tensor, ok: torch.Tensor, s_run: torch.Tensor,
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``ŷ = Σ w yc / Σ w`` and ``S_y = Σ w (yc − ŷ)² / Σ w + S`` over the cells ``ok``, and
    the mass ``Σ w`` there (``(N,)`` each)."""
    yc = torch.where(ok, yc, 0.0)
    w_ok = torch.where(ok, w, 0.0)
    mass = w_ok.sum((1, 2))
    safe = mass.clamp_min(torch.finfo(w.dtype).tiny)
    yhat = (w_ok * yc).sum((1, 2)) / safe
    s_y = (w_ok * (yc - yhat[:, None, None]) ** 2).sum((1, 2)) / safe + s_run
    return yhat, s_y, mass


def predictive_nis_core(w: torch.Tensor, mu: torch.Tensor, P: torch.Tensor, c: torch.Tensor,
                        y: torch.Tensor, g: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """``(N,)`` NIS ``(y − ŷ)² / S_y`` of ``y`` against the predicted mixture, ``ŷ = Σ w (g +
    c·μ)``, ``S_y = Σ w (g + c·μ − ŷ)² + cᵀPc + R`` over the cells where ``g`` is finite
    (masses renormalised); NaN where no cell is or ``y`` is NaN."""
    s_run = (mv(P, c) * c).sum(-1) + r
    yc = g + torch.einsum("z,nzij->nij", c, mu)
    yhat, s_y, mass = _mixture_moments(w, yc, torch.isfinite(yc), s_run)
    nis = (y - yhat) ** 2 / s_y
    return torch.where(mass > 0, nis, math.nan)


def lost_window_core(nis_win: torch.Tensor, count: torch.Tensor, lost: torch.Tensor,
                     nis: torch.Tensor, applied: torch.Tensor, slot: torch.Tensor,
                     threshold: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The lost-track window: ``nis`` of the applied runs written at the slot ``slot`` (a
    one-hot ``(W,)`` bool: no host index, no recompilation per slot); returns the window,
    the count and ``widen (N,)``: a full window whose mean NIS exceeds ``threshold``
    (``χ²_prob(W)/W``), not yet lost."""
    nis_win = torch.where(slot[None, :] & applied[:, None], nis[:, None], nis_win)
    count = count + applied.long()
    full = count >= nis_win.shape[1]
    return nis_win, count, full & (nis_win.mean(1) > threshold) & ~lost


#: The flags of a static update, in the order of its host read (then the count of runs
#: the static regrid leaves to the driver's compaction).
UPDATE_FLAGS = ("r_bad", "special", "lattice_error")


def _moved(new: dict[str, Any], move: torch.Tensor,
           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The moved lattice of `regrid_move`: which runs keep it (moved and no rare flag),
    which go to the driver (``special``: the moment correction's Gaussian fallback or an
    inseparable eigenvalue floor), and its lattice errors."""
    special = (new["thin"] | new["floor"]) & move
    error = (new["too_coarse"] | new["bad"]) & move
    return move & ~special & ~error, special, error


def regrid_rows_step(w: torch.Tensor, mu: torch.Tensor, P: torch.Tensor, centre: torch.Tensor,
                     axes: torch.Tensor, q_next: torch.Tensor, off: torch.Tensor,
                     p: FollowParams) -> tuple[Any, ...]:
    """`regrid_move` of ``K`` runs the rule moves (the driver's compaction of a large batch
    on the CPU: only the moved runs are resampled), with the moments and cells of the result.

    Returns:
        ``state``, ``mean``, ``cov``, ``points`` of the moved runs, ``keep`` ``(K,)`` (no rare
        flag), ``special`` ``(K,)`` (to the driver's eager path), ``error`` ``(K,)``.
    """
    new = regrid_move(w, mu, P, centre, axes, lattice_moment_tensors(w, mu, off), q_next,
                      off, p, opaque=True)
    keep, special, error = _moved(new, torch.ones_like(q_next[:, 0], dtype=torch.bool))
    st = new["state"]
    mean, cov = joint_moments(state_moments(lattice_moment_tensors(st[0], st[1], off), st[2],
                                            st[3], st[4]))
    return st, mean, cov, lattice_points(st[3], st[4], off), keep, special, error


def update_step(w: torch.Tensor, mu: torch.Tensor, P: torch.Tensor, centre: torch.Tensor,
                axes: torch.Tensor, c: torch.Tensor, y: torch.Tensor, g: torch.Tensor,
                r: torch.Tensor, mask: torch.Tensor, cell_variance: torch.Tensor | None,
                q_next: torch.Tensor, nis_win: torch.Tensor, nis_count: torch.Tensor,
                lost: torch.Tensor, slot: torch.Tensor, recoveries: torch.Tensor,
                regrids: torch.Tensor, off: torch.Tensor, p: FollowParams, threshold: float,
                window: bool, regrid: str) -> tuple[Any, ...]:
    """The static update of every run: the measurement update (`update_core`), the
    lost-track window (``window``), the regrid rule and the moments of the result.

    ``regrid``: ``"all"`` (every run's moved lattice computed, kept where the rule moves
    it: no host read, the choice for few runs and for the GPU), ``"rule"`` (the rule
    only: the driver resamples the moved runs with `regrid_rows_step`, the choice for many
    runs on the CPU, where a third of the runs moves per step) or ``"none"``.

    Runs that need the driver's eager path (``special``: a lost-track widening, masses
    narrower than the cells before the regrid, a rare flag of the moved lattice) keep their
    updated state, unregridded.

    Returns:
        ``state`` (the result; the special runs at their updated state), ``points``,
        ``mean``, ``cov`` (of the result), ``nis`` (NaN where not applied), ``innovation``, ``log_likelihood``, ``recovered``, ``applied``, the
        counters ``recoveries``, ``regrids`` (the moves made here), the window ``nis_win``,
        ``nis_count``, ``widen``, ``special``, ``move`` (``"rule"``: the runs the driver is
        to move) and ``read`` ``(4,)`` float: whether any run raised each of
        `UPDATE_FLAGS`, then the number of runs in ``move`` (one host read).
    """
    up = update_core(w, mu, P, c, y, g, r, mask, cell_variance, reports_nis=True,
                     outlier_prob=0.0, outlier_width=1000.0,
                     floor_weights=lambda x: floor_weights(x, p.weight_floor))
    w1, mu1, P1 = up["state"]
    applied = up["applied"]
    widen = torch.zeros_like(applied)
    if window:
        nis_win, nis_count, widen = lost_window_core(nis_win, nis_count, lost, up["nis"],
                                                     applied, slot, threshold)
    lm1 = lattice_moment_tensors(w1, mu1, off)
    mean, cov = joint_moments(state_moments(lm1, P1, centre, axes))
    final = (w1, mu1, P1, centre, axes)
    special, error, move = widen, torch.zeros_like(applied), torch.zeros_like(applied)
    if regrid != "none":
        special = widen | thin_flag(lm1[1])
        move = regrid_rule(lm1, axes, q_next, None, p) & ~special
    if regrid == "all":
        new = regrid_move(*final, lm1, q_next, off, p)
        keep, special_new, error = _moved(new, move)
        special = special | special_new
        st = new["state"]
        final = tuple(torch.where(_rows(keep, x.ndim - 1), a, x)
                      for a, x in zip(st, final, strict=True))
        mean_n, cov_n = joint_moments(state_moments(
            lattice_moment_tensors(st[0], st[1], off), st[2], st[3], st[4]))
        mean = torch.where(keep[:, None], mean_n, mean)
        cov = torch.where(keep[:, None, None], cov_n, cov)
        regrids = regrids + keep.long()
        move = torch.zeros_like(move)  # nothing left to the driver
    read = torch.stack([up["r_bad"].any(), special.any(), error.any()]).to(w.dtype)
    read = torch.cat([read, move.sum()[None].to(w.dtype)])
    return (final, lattice_points(final[3], final[4], off), mean, cov,
            torch.where(applied, up["nis"], math.nan), up["innovation"],
            up["log_likelihood"], up["recovered"], applied,
            recoveries + up["recovered"].long(), regrids, nis_win, nis_count, widen, special,
            move, read)


def track_step(w: torch.Tensor, mu: torch.Tensor, P: torch.Tensor, centre: torch.Tensor,
               axes: torch.Tensor, E: torch.Tensor, F: torch.Tensor, qs: torch.Tensor,
               qz: torch.Tensor, shift: torch.Tensor, open_mean: torch.Tensor,
               open_cov: torch.Tensor, c: torch.Tensor, y: torch.Tensor,
               heights: Any, heights_args: tuple[Any, ...], r: torch.Tensor,
               mask: torch.Tensor, gate: float, nis_win: torch.Tensor,
               nis_count: torch.Tensor, lost: torch.Tensor, slot: torch.Tensor,
               recoveries: torch.Tensor, regrids: torch.Tensor, off: torch.Tensor,
               p: FollowParams, threshold: float, window: bool, regrid: str,
               profile: bool) -> tuple[Any, ...]:
    """One whole tracking epoch of every run as one static step: `predict_step`, the
    measurement model at the predicted cells, the spike gate, `update_step` and (``profile``)
    the radial mass profile of the result around its mean
    (`neuralmap.filters.lattice.kernels.radial_mass_profile`: the protection radius of any
    risk in a few operations).

    ``g = heights(*heights_args, points)`` ``(N, G, G)`` at the predicted cells ``points
    (N, G, G, 2)`` (a module-level function: under ``torch.compile`` the map lookup is
    fused with the filter). The spike gate leaves out ``y`` of the runs whose NIS against
    the predicted mixture (`predictive_nis_core`) exceeds ``gate`` (``inf``: no gate). The
    result equals `predict_step`, then `predictive_nis_core` and `update_step` with the
    mask ``mask & ~gated``; the driver commits it only when the prediction raised none of
    `PREDICT_FLAGS` and its kernel fitted the band (else it redoes the epoch as a
    prediction and an update).

    Returns:
        ``predicted`` (the outputs of `predict_step`), ``updated`` (those of `update_step`),
        ``nis_predicted`` ``(N,)``, ``gated`` ``(N,)`` bool, the profile (None without
        ``profile``) and ``read``: the prediction's ``read`` followed by the update's (one
        host read).
    """
    predicted = predict_step(w, mu, P, centre, axes, None, E, F, qs, qz, shift, open_mean,
                             open_cov, off, p)
    state, points, q_next = predicted[0], predicted[1], predicted[2]
    g = heights(*heights_args, points)
    nis_pred = predictive_nis_core(state[0], state[1], state[2], c, y, g, r)
    gated = mask & torch.isfinite(nis_pred) & (nis_pred > gate)
    updated = update_step(*state, c, y, g, r, mask & ~gated, None, q_next, nis_win,
                          nis_count, lost, slot, recoveries, regrids, off, p, threshold,
                          window, regrid)
    read = torch.cat([predicted[-1], updated[-1]])
    final = updated[0]
    mass = (_kernels.radial_mass_profile(updated[1], final[0], final[4], updated[2][:, :2])
            if profile else None)
    return predicted, updated, nis_pred, gated, mass, read


def floor_weights(w: torch.Tensor, weight_floor: float) -> torch.Tensor:
    """The following lattice's weight floor: masses below ``weight_floor × max`` raised to
    it, renormalised (0: unchanged)."""
    if weight_floor > 0:
        w = w.clamp_min(weight_floor * w.amax((1, 2), keepdim=True))
        w = w / w.sum((1, 2), keepdim=True)
    return w


# ---------------------------------------------------------------------------- compiled
_COMPILED: dict[str, object] = {}

#: Inductor options of the compiled steps: the C++ wrapper (no Python per kernel launch and
#: buffer) and pointwise concatenation (the 2 × 2 algebra stacks many tiny tensors; as
#: pointwise reads they stay in registers instead of one buffer each).
COMPILE_OPTIONS = {"cpp_wrapper": True, "force_pointwise_cat": True}


def compiled(name: str, fn):
    """``torch.compile`` of one step function (cached per name; ``fullgraph``: a step has no
    host read). Raises what ``torch.compile`` raises when the backend is unavailable."""
    if name not in _COMPILED:
        # a step compiles once per batch size (then for any), blur band, dtype and option
        # set: more variants than dynamo's default of 8 per function in one process
        limit = getattr(torch._dynamo.config, "recompile_limit", None)
        if limit is not None and limit < 32:
            torch._dynamo.config.recompile_limit = 32
        _COMPILED[name] = torch.compile(fn, fullgraph=True, dynamic=None,
                                        options=dict(COMPILE_OPTIONS))
    return _COMPILED[name]
