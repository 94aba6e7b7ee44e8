"""Closed-form 2 × 2 linear algebra for batches of lattice matrices ``(N, 2, 2)``.

The lattice filter does a dozen small matrix operations per step on the 2-D lattice state
(its covariance, cell steps, moment-correction map). Batched LAPACK calls
(``torch.linalg.eigh`` / ``solve`` / ``lstsq``) on ``(N, 2, 2)`` cost one call per matrix
inside; these closed forms are a few element-wise operations on ``(N,)`` tensors,
deterministic (no driver-dependent last bits) and accurate to round-off (tested against
``torch.linalg`` in float64):

* `eigh2`: eigenvalues (ascending) and orthonormal eigenvectors of a symmetric matrix
  (the stable formulas of LAPACK's ``dlaev2``: the larger eigenvalue from the trace and the
  discriminant, the smaller one from the determinant over it; the rotation angle
  ``θ = ½ atan2(2b, a − c)``);
* `inv2` (adjugate over determinant), `solve2`;
* `sqrtm2` (symmetric square root or inverse root from `eigh2`);
* `spd2_ok` (finite, symmetric, positive definite: ``a > 0`` and ``det > 0``);

and for the filter's small linear part (``nz ≤ 3`` states per cell: altitude and velocity
errors):

* `spd_ok` (the Cholesky test of a ``d × d`` matrix; closed-form pivots for ``d ≤ 3``,
  LAPACK above);
* `eigvalsh3` (eigenvalues of a symmetric 3 × 3 matrix by the trigonometric method, in
  float64: absolute error about ``1e-15 · ‖c‖``).
"""

from __future__ import annotations

import torch

__all__ = ["eigh2", "eigvalsh2", "eigvalsh3", "few_for_lapack", "inv2", "mm", "mv", "solve2",
           "spd2_ok", "spd_ok", "sqrtm2"]

import math


def mm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` for small matrices (any broadcast batch dimensions).

    Under ``torch.compile`` a broadcast product and a sum, which the code generator fuses
    into the surrounding kernel (a library call per 2 × 2 product costs more than the
    product); eagerly one ``matmul``.
    """
    if torch.compiler.is_compiling():
        return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)
    return a @ b


def mv(a: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``a @ v`` for a small matrix ``a (..., m, k)`` and vector ``v (..., k)`` (as `mm`)."""
    if torch.compiler.is_compiling():
        return (a * v.unsqueeze(-2)).sum(-1)
    return a @ v if v.ndim == 1 else (a @ v.unsqueeze(-1)).squeeze(-1)


def eigvalsh2(c: torch.Tensor) -> torch.Tensor:
    """``(..., 2)`` ascending eigenvalues of symmetric ``c (..., 2, 2)`` (upper triangle used
    as LAPACK does: ``c[..., 0, 1]``)."""
    a, b, d = c[..., 0, 0], c[..., 0, 1], c[..., 1, 1]
    sm = a + d
    rt = torch.hypot(a - d, 2.0 * b)  # sqrt((a − d)² + 4 b²)
    big_pos = 0.5 * (sm + rt)  # the eigenvalue of the larger magnitude
    big_neg = 0.5 * (sm - rt)
    big = torch.where(sm >= 0, big_pos, big_neg)
    safe = torch.where(big == 0, 1.0, big)
    small = torch.where(big == 0, 0.0, (a * d - b * b) / safe)  # det / λ_big (dlaev2)
    lo = torch.minimum(big, small)
    hi = torch.maximum(big, small)
    return torch.stack([lo, hi], -1)


def eigh2(c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Eigenvalues ``(..., 2)`` (ascending) and eigenvectors ``(..., 2, 2)`` (columns) of
    symmetric ``c (..., 2, 2)``: ``c = V diag(λ) Vᵀ``.

    ``θ = ½ atan2(2b, a − c₂₂)`` is the direction of the larger eigenvalue; the smaller one's
    is ``θ + π/2``.
    """
    lam = eigvalsh2(c)
    a, b, d = c[..., 0, 0], c[..., 0, 1], c[..., 1, 1]
    theta = 0.5 * torch.atan2(2.0 * b, a - d)
    cs, sn = torch.cos(theta), torch.sin(theta)
    # columns: v_small = (−sin θ, cos θ), v_big = (cos θ, sin θ)
    vec = torch.stack([torch.stack([-sn, cs], -1), torch.stack([cs, sn], -1)], -1)
    return lam, vec


def sqrtm2(c: torch.Tensor, inverse: bool = False) -> torch.Tensor:
    """Symmetric square root (or inverse root) of SPD ``c (..., 2, 2)`` (eigenvalues floored
    at the dtype's tiny)."""
    lam, v = eigh2(c)
    lam = lam.clamp_min(torch.finfo(c.dtype).tiny)
    r = lam.rsqrt() if inverse else lam.sqrt()
    return mm(v * r[..., None, :], v.transpose(-1, -2))


def inv2(a: torch.Tensor) -> torch.Tensor:
    """``(..., 2, 2)`` inverse by the adjugate: ``[[d, −b], [−c, a]] / (ad − bc)``."""
    p, q, r, s = a[..., 0, 0], a[..., 0, 1], a[..., 1, 0], a[..., 1, 1]
    det = p * s - q * r
    adj = torch.stack([torch.stack([s, -q], -1), torch.stack([-r, p], -1)], -2)
    return adj / det[..., None, None]


def solve2(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a⁻¹ b`` for ``a (..., 2, 2)`` and ``b (..., 2, k)`` (`inv2`)."""
    return mm(inv2(a), b)


def spd2_ok(c: torch.Tensor) -> torch.Tensor:
    """``(...,)`` bool: ``c (..., 2, 2)`` finite, symmetric (1e-9 relative) and positive
    definite (``c₀₀ > 0`` and ``det > 0``, in float64 as the Cholesky test it replaces)."""
    c = c.double()
    finite = torch.isfinite(c).flatten(-2).all(-1)
    a, b, b2, d = c[..., 0, 0], c[..., 0, 1], c[..., 1, 0], c[..., 1, 1]
    scale = c.abs().flatten(-2).amax(-1)
    sym = (b - b2).abs() <= 1e-9 * scale + 1e-300
    return finite & sym & (a > 0) & (a * d - b * b2 > 0)


def spd_ok(c: torch.Tensor) -> torch.Tensor:
    """``(N,)`` bool: ``c (N, d, d)`` finite, symmetric (1e-9 relative) and positive definite
    (the test of a Cholesky factorisation in float64).

    ``d = 2``: `spd2_ok`; ``d = 1`` and ``d = 3``: the pivots of ``c = L D Lᵀ`` in closed
    form (``D > 0``: the pivots LAPACK's Cholesky checks; one LAPACK call for a few matrices
    outside ``torch.compile``, where it is the cheaper of the two); larger ``d``: LAPACK.
    """
    d = c.shape[-1]
    if d == 2:
        return spd2_ok(c)
    finite = torch.isfinite(c).flatten(1).all(1)
    if d == 1:
        return finite & (c[:, 0, 0] > 0)
    eye = torch.eye(d, dtype=c.dtype, device=c.device)
    safe = torch.where(finite[:, None, None], c, eye)
    sym = (safe - safe.transpose(1, 2)).abs().flatten(1).amax(1) <= (
        1e-9 * safe.abs().flatten(1).amax(1) + 1e-300)
    if d != 3 or few_for_lapack(c):
        return finite & sym & (torch.linalg.cholesky_ex(safe.double()).info == 0)
    a = safe.double()
    d0 = a[:, 0, 0]
    l10, l20 = a[:, 1, 0] / d0, a[:, 2, 0] / d0
    d1 = a[:, 1, 1] - l10 * a[:, 1, 0]  # pivots of the lower triangle, as LAPACK reads it
    e21 = a[:, 2, 1] - l20 * a[:, 1, 0]
    d2 = a[:, 2, 2] - l20 * a[:, 2, 0] - e21 * e21 / d1
    return finite & sym & (d0 > 0) & (d1 > 0) & (d2 > 0)


def few_for_lapack(c: torch.Tensor) -> bool:
    """A batch small enough (≤ 16 matrices, on the CPU) that one LAPACK call costs less than
    a closed form's few dozen operations, outside ``torch.compile`` (where the closed form
    fuses; on a GPU the library call would also wait for the device)."""
    return (c.shape[0] <= 16 and c.device.type == "cpu"
            and not torch.compiler.is_compiling())


def eigvalsh3(c: torch.Tensor) -> torch.Tensor:
    """``(N, 3)`` ascending eigenvalues (float64) of symmetric ``c (N, 3, 3)``.

    The trigonometric method (Smith 1961): ``q = tr c / 3``, ``p² = ‖c − q I‖²_F / 6``,
    ``r = det((c − q I)/p) / 2``, ``λ = q + 2p cos(acos(r)/3 + 2πk/3)``; an absolute error
    of about ``1e-15 · ‖c‖`` (enough to decide whether an eigenvalue is below ``1e-12`` of
    the largest; the eigenvectors are not needed there).
    """
    a = c.double()
    a00, a11, a22 = a[:, 0, 0], a[:, 1, 1], a[:, 2, 2]
    a01, a02, a12 = a[:, 0, 1], a[:, 0, 2], a[:, 1, 2]
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    p = ((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1) / 6.0).sqrt()
    det = (b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02)
           + a02 * (a01 * a12 - b11 * a02))
    safe_p = torch.where(p > 0, p, 1.0)
    r = torch.where(p > 0, det / (2.0 * safe_p**3), 0.0).clamp(-1.0, 1.0)
    phi = torch.acos(r) / 3.0
    hi = q + 2.0 * p * torch.cos(phi)
    lo = q + 2.0 * p * torch.cos(phi + 2.0 * math.pi / 3.0)
    mid = 3.0 * q - hi - lo
    return torch.stack([lo, mid, hi], -1)
