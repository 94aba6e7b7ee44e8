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
* `spd2_ok` (finite, symmetric, positive definite: ``a > 0`` and ``det > 0``).
"""

from __future__ import annotations

import torch

__all__ = ["eigh2", "eigvalsh2", "inv2", "solve2", "spd2_ok", "sqrtm2"]


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
    return (v * r[..., None, :]) @ v.transpose(-1, -2)


def inv2(a: torch.Tensor) -> torch.Tensor:
    """``(..., 2, 2)`` inverse by the adjugate: ``[[d, −b], [−c, a]] / (ad − bc)``."""
    p, q, r, s = a[..., 0, 0], a[..., 0, 1], a[..., 1, 0], a[..., 1, 1]
    det = p * s - q * r
    adj = torch.stack([torch.stack([s, -q], -1), torch.stack([-r, p], -1)], -2)
    return adj / det[..., None, None]


def solve2(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a⁻¹ b`` for ``a (..., 2, 2)`` and ``b (..., 2, k)`` (`inv2`)."""
    return inv2(a) @ b


def spd2_ok(c: torch.Tensor) -> torch.Tensor:
    """``(...,)`` bool: ``c (..., 2, 2)`` finite, symmetric (1e-9 relative) and positive
    definite (``c₀₀ > 0`` and ``det > 0``, in float64 as the Cholesky test it replaces)."""
    c = c.double()
    finite = torch.isfinite(c).flatten(-2).all(-1)
    a, b, b2, d = c[..., 0, 0], c[..., 0, 1], c[..., 1, 0], c[..., 1, 1]
    scale = c.abs().flatten(-2).amax(-1)
    sym = (b - b2).abs() <= 1e-9 * scale + 1e-300
    return finite & sym & (a > 0) & (a * d - b * b2 > 0)
