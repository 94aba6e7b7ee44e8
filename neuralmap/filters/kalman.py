"""The functional Kalman core: batch-last pure predict and update (FilterPy's procedural style).

Every function here is pure (no state, no in-place change of its inputs) and works on a
batch of N independent filters stored *batch-last*: the state ``x`` as ``(n, N)`` and the
covariance ``P`` as ``(n, n, N)``, so that each entry ``P[i, j]`` is a contiguous length-N
vector. For small states (n ≤ `SMALL_STATE_MAX`) the kernels are written entry by
entry on those vectors (a loop over *state indices*, never over samples); larger states use
batched matrix kernels. `neuralmap.filters.ekf.BatchedEKF` is a thin stateful layer
over these kernels (validation, health flags, policies).

Equations (FilterPy, Joseph form):

* predict: ``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q`` (exactly symmetric: upper triangle, mirrored);
* update: ``S = H P⁻ Hᵀ + R``, ``K = P⁻ Hᵀ S⁻¹`` (Cholesky solve; a division for m = 1),
  ``x⁺ = x⁻ + K r``, ``P⁺ = (I − KH) P⁻ (I − KH)ᵀ + K R Kᵀ``, ``NIS = rᵀ S⁻¹ r``,
  log-likelihood ``ℓ = −½ (m ln 2π + ln det S + NIS)`` (the Gaussian density of the
  innovation: the natural loss for learning through the filter).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch

from neuralmap.filters.stats import symmetrize

__all__ = [
    "SMALL_STATE_MAX",
    "KalmanUpdate",
    "TransitionPlan",
    "kalman_predict",
    "kalman_update",
    "predict_upper",
    "transition_plan",
    "update_scalar_upper",
    "update_dense",
    "upper_pairs",
]

#: Largest state size handled entry by entry (fast paths); larger ones use batched
#: matrix kernels (``matmul``, ``cholesky_ex``).
SMALL_STATE_MAX = 8

_LOG_2PI = math.log(2.0 * math.pi)


def upper_pairs(n: int) -> list[tuple[int, int]]:
    """Upper-triangle index pairs ``(i, j)``, ``i ≤ j``, in row-major order."""
    return [(i, j) for i in range(n) for j in range(i, n)]


def full_from_upper(p_up: Sequence[torch.Tensor], n: int) -> torch.Tensor:
    """Stacks upper-triangle entries (row-major, ``(N,)`` each) into a ``(n, n, N)`` matrix."""
    index = {ij: t for t, ij in enumerate(upper_pairs(n))}
    order = [index[min(i, j), max(i, j)] for i in range(n) for j in range(n)]
    return torch.stack([p_up[t] for t in order]).reshape(n, n, -1)


@dataclass
class TransitionPlan:
    """A shared transition matrix with its covariance-propagation plan.

    ``(F P Fᵀ)_il = Σ_{j≤k} c_{il,jk} P_jk`` with ``c = F_ij F_lk + F_ik F_lj`` for ``j < k``
    and ``F_ij F_lj`` for ``j = k`` (P symmetric). A sparse ``F`` (as the TAN Φ) has few
    nonzero ``c`` and is applied entry by entry (`terms`); a dense one through one
    matrix product ``vec(F P Fᵀ) = (F ⊗ F) vec(P)`` on the upper-triangle rows
    (`m_tri`, rows of ``(i, l)`` and ``(l, i)`` averaged: the symmetrisation).

    Attributes:
        F: ``(n, n)`` shared, or ``(N, n, n)`` per-sample (batch first) transition matrix.
        coef_sum: ``max_il Σ |c|`` (shared F; 0 for per-sample F).
        n_terms: Largest number of terms of one output entry.
        terms: Sparse plan, per upper output entry a list of ``(input index, coefficient)``.
        m_tri: Dense plan, ``(T, n·n)`` symmetrised Kronecker rows.
    """

    F: torch.Tensor
    coef_sum: float = 0.0
    n_terms: int = 0
    terms: list[list[tuple[int, float]]] | None = None
    m_tri: torch.Tensor | None = None


def transition_plan(F: torch.Tensor) -> TransitionPlan:
    """Builds the propagation plan of a transition matrix (see `TransitionPlan`).

    Args:
        F: ``(n, n)`` shared or ``(N, n, n)`` per-sample transition matrix.
    """
    if F.ndim == 3:
        return TransitionPlan(F)
    n = F.shape[0]
    upper = upper_pairs(n)
    if n <= SMALL_STATE_MAX and not F.requires_grad:
        f = F.tolist()
        index = {ij: t for t, ij in enumerate(upper)}
        terms: list[list[tuple[int, float]]] = []
        for i, m in upper:
            row = []
            for j, k in upper:
                c = f[i][j] * f[m][k] + (f[i][k] * f[m][j] if j != k else 0.0)
                if c != 0.0:
                    row.append((index[j, k], c))
            terms.append(row)
        if sum(len(t) for t in terms) <= 4 * len(upper):
            coef_sum = max(sum(abs(c) for _, c in t) for t in terms)
            return TransitionPlan(F, coef_sum, max(len(t) for t in terms), terms, None)
    kron = torch.kron(F, F)  # kron[i*n+l, j*n+k] = F_ij F_lk
    rows_up = torch.tensor([i * n + j for i, j in upper], device=F.device)
    rows_low = torch.tensor([j * n + i for i, j in upper], device=F.device)
    m_tri = 0.5 * (kron[rows_up] + kron[rows_low])
    coef_sum = float(m_tri.detach().abs().sum(1).max())
    return TransitionPlan(F, coef_sum, n * n, None, m_tri)


def predict_upper(
    xt: torch.Tensor, pt: torch.Tensor, plan: TransitionPlan, Q: torch.Tensor
) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """Time update on batch-last storage; returns ``x⁻`` and the upper triangle of ``P⁻``.

    ``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q`` (SEEDS 004: ``P⁻ = Φ P Φᵀ + Q``).

    Args:
        xt: ``(n, N)`` states.
        pt: ``(n, n, N)`` symmetric covariances.
        plan: `transition_plan` of F.
        Q: ``(n, n)`` shared or ``(N, n, n)`` per-sample (batch first) process noise.

    Returns:
        ``x⁻`` ``(n, N)`` and the upper-triangle entries of ``P⁻`` (row-major, ``(N,)`` each).
    """
    n, batch = xt.shape
    upper = upper_pairs(n)
    F = plan.F
    if F.ndim == 2:
        x_new = F @ xt
        q_up = [Q[i, j] for i, j in upper] if Q.ndim == 2 else [Q[:, i, j] for i, j in upper]
        if plan.terms is not None:
            rows = [pt[i, j] for i, j in upper]
            p_up = []
            for terms, q in zip(plan.terms, q_up, strict=True):
                acc = None
                for s, c in terms:
                    acc = rows[s] * c if acc is None else torch.add(acc, rows[s], alpha=c)
                p_up.append(q.expand(batch) + 0.0 if acc is None else acc + q)
            return x_new, p_up
        assert plan.m_tri is not None
        p_tri = plan.m_tri @ pt.reshape(n * n, batch)
        return x_new, [p_tri[t] + q for t, q in enumerate(q_up)]
    P = pt.permute(2, 0, 1)
    x_new = torch.einsum("bij,jb->ib", F, xt)
    fpf = torch.matmul(torch.matmul(F, P), F.transpose(1, 2))
    full = (symmetrize(fpf) + Q).permute(1, 2, 0)
    return x_new, [full[i, j] for i, j in upper]


def update_scalar_upper(
    xt: torch.Tensor,
    pt: torch.Tensor,
    residual: torch.Tensor,
    h: Sequence[torch.Tensor],
    R: torch.Tensor,
    u: Sequence[torch.Tensor] | None = None,
) -> tuple[torch.Tensor, list[torch.Tensor], torch.Tensor, torch.Tensor]:
    """Scalar-measurement update (m = 1) on batch-last storage, entry by entry.

    Everything is a length-N vector: ``u = P⁻ hᵀ``, ``S = h u + R`` (a division replaces
    ``S⁻¹``), ``K = u / S``. The Joseph form with a scalar measurement, expanded with
    ``h P hᵀ + R = S``::

        P⁺ = (I − K h) P (I − K h)ᵀ + K R Kᵀ = P − u Kᵀ + K wᵀ,   w = S K − u

    i.e. ``P⁺_ij = P_ij − u_i K_j + K_i w_j`` for ``i ≤ j`` (mirrored): exactly symmetric
    and, like the Joseph form, insensitive to first-order errors in ``K``.

    Args:
        xt: ``(n, N)`` predicted states.
        pt: ``(n, n, N)`` predicted covariances.
        residual: ``(N,)`` innovation.
        h: n entries of the measurement row, each ``(N,)`` or a 0-d shared value.
        R: ``()`` or ``(N,)`` measurement variance.
        u: Optional precomputed ``P hᵀ`` (n entries, ``(N,)`` each) when the caller has it.

    Returns:
        ``x⁺`` ``(n, N)``, upper triangle of ``P⁺``, ``S`` ``(N,)``, gain ``(n, N)``.
    """
    n, batch = xt.shape
    if u is None:
        u = []
        for i in range(n):
            acc = pt[i, 0] * h[0]
            for j in range(1, n):
                acc = torch.addcmul(acc, pt[i, j], h[j])
            u.append(acc)
    S = R
    for j in range(n):
        S = torch.addcmul(S, h[j], u[j])  # S = h P hᵀ + R
    if S.ndim == 0:
        S = S.expand(batch)
    ut = torch.stack(u)  # (n, N) = P hᵀ
    kt = ut / S  # K = P hᵀ S⁻¹
    wt = kt * S - ut  # w = S K − u
    x_new = torch.addcmul(xt, kt, residual)  # x⁺ = x⁻ + K r
    p_up = [
        torch.addcmul(torch.addcmul(pt[i, j], kt[i], wt[j]), ut[i], kt[j], value=-1.0)
        for i, j in upper_pairs(n)
    ]  # P⁺_ij = P_ij + K_i w_j − u_i K_j   (Joseph form, expanded)
    return x_new, p_up, S, kt


class DenseUpdate(NamedTuple):
    """Result of `update_dense` (batch first)."""

    x: torch.Tensor  # (N, n)
    P: torch.Tensor  # (N, n, n)
    S: torch.Tensor  # (N, m, m)
    gain: torch.Tensor  # (N, n, m)
    nis: torch.Tensor  # (N,)
    log_det_S: torch.Tensor  # (N,)
    s_ok: torch.Tensor  # (N,) bool: S finite and positive definite


def update_dense(
    x: torch.Tensor, P: torch.Tensor, residual: torch.Tensor, H: torch.Tensor, R: torch.Tensor
) -> DenseUpdate:
    """Vector-measurement update with ``(N, m, m)`` innovation covariances (batch first).

    ``S = H P⁻ Hᵀ + R`` (symmetrised), Cholesky ``S = L Lᵀ``, ``K = P⁻ Hᵀ S⁻¹`` from
    ``S Kᵀ = H P⁻`` (two triangular solves), Joseph form ``P⁺``, ``NIS = |L⁻¹ r|²``,
    ``ln det S = 2 Σ ln L_ii``.

    Args:
        x: ``(N, n)``; P: ``(N, n, n)``; residual: ``(N, m)``; H: ``(N, m, n)``;
        R: ``(N, m, m)``.
    """
    n = x.shape[1]
    batch = x.shape[0]
    pht = torch.matmul(P, H.transpose(1, 2))  # P Hᵀ (N, n, m)
    S = torch.matmul(H, pht) + R
    S = symmetrize(S)
    chol, info = torch.linalg.cholesky_ex(S)
    gain = torch.cholesky_solve(pht.transpose(1, 2), chol).transpose(1, 2)  # (N, n, m)
    x_new = x + torch.matmul(gain, residual.unsqueeze(-1)).squeeze(-1)
    eye = torch.eye(n, dtype=x.dtype, device=x.device)
    ikh = eye - torch.matmul(gain, H)
    p_new = torch.matmul(torch.matmul(ikh, P), ikh.transpose(1, 2))
    p_new = p_new + torch.matmul(torch.matmul(gain, R), gain.transpose(1, 2))
    p_new = symmetrize(p_new)  # Joseph form, symmetrised
    white = torch.linalg.solve_triangular(chol, residual.unsqueeze(-1), upper=False)
    nis = white.squeeze(-1).square().sum(-1)  # rᵀ S⁻¹ r = |L⁻¹ r|²
    log_det = 2.0 * torch.diagonal(chol, dim1=-2, dim2=-1).log().sum(-1)
    s_ok = (info == 0) & torch.isfinite(S.reshape(batch, -1).sum(-1))
    return DenseUpdate(x_new, p_new, S, gain, nis, log_det, s_ok)


def add_information(P: torch.Tensor, info: torch.Tensor) -> torch.Tensor:
    """Covariance after adding information ``I``: ``(P⁻¹ + I)⁻¹ = (E + P I)⁻¹ P``.

    The information form of the Kalman update (``I = Hᵀ R⁻¹ H``), computed with a linear
    solve and no explicit inverse, so a singular ``P`` (a known component) is fine;
    symmetrised. Used by the PCRB recursion.

    Args:
        P: ``(..., n, n)`` prior covariance.
        info: ``(..., n, n)`` information to add (symmetric positive semi-definite).

    Returns:
        ``(..., n, n)`` posterior covariance.
    """
    eye = torch.eye(P.shape[-1], dtype=P.dtype, device=P.device)
    post = torch.linalg.solve(eye + P @ info, P)
    return symmetrize(post)


def gaussian_log_likelihood(nis: torch.Tensor, log_det_S: torch.Tensor, m: int) -> torch.Tensor:
    """Innovation log-density ``−½ (m ln 2π + ln det S + rᵀ S⁻¹ r)``, ``(N,)``."""
    return -0.5 * (m * _LOG_2PI + log_det_S + nis)


class KalmanUpdate(NamedTuple):
    """Result of `kalman_update` (batch last, like its inputs).

    Attributes:
        x: ``(n, N)`` updated states.
        P: ``(n, n, N)`` updated covariances (Joseph form, symmetric).
        S: ``(m, m, N)`` innovation covariances.
        gain: ``(n, m, N)`` Kalman gains.
        nis: ``(N,)`` normalised innovation squared.
        log_likelihood: ``(N,)`` Gaussian log-likelihood of the innovation.
    """

    x: torch.Tensor
    P: torch.Tensor
    S: torch.Tensor
    gain: torch.Tensor
    nis: torch.Tensor
    log_likelihood: torch.Tensor


def kalman_predict(
    x: torch.Tensor, P: torch.Tensor, F: torch.Tensor, Q: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pure time update of N filters, batch last (FilterPy ``predict``).

    ``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q`` (SEEDS 004), exactly symmetric.

    Args:
        x: ``(n, N)`` states.
        P: ``(n, n, N)`` covariances.
        F: ``(n, n)`` shared or ``(n, n, N)`` per-sample transition matrix.
        Q: ``(n, n)`` shared or ``(n, n, N)`` per-sample process noise.

    Returns:
        ``(x⁻ (n, N), P⁻ (n, n, N))``.
    """
    n, batch = x.shape
    assert P.shape == (n, n, batch), f"P must be (n, n, N) = {(n, n, batch)}, got {P.shape}"
    assert F.shape in ((n, n), (n, n, batch)), f"F must be (n, n) or (n, n, N), got {F.shape}"
    assert Q.shape in ((n, n), (n, n, batch)), f"Q must be (n, n) or (n, n, N), got {Q.shape}"
    F_b = F if F.ndim == 2 else F.permute(2, 0, 1)
    Q_b = Q if Q.ndim == 2 else Q.permute(2, 0, 1)
    x_new, p_up = predict_upper(x, P, transition_plan(F_b), Q_b)
    return x_new, full_from_upper(p_up, n)


def kalman_update(
    x: torch.Tensor,
    P: torch.Tensor,
    residual: torch.Tensor,
    H: torch.Tensor,
    R: torch.Tensor,
) -> KalmanUpdate:
    """Pure measurement update of N filters, batch last (FilterPy ``update``, Joseph form).

    Args:
        x: ``(n, N)`` predicted states.
        P: ``(n, n, N)`` predicted covariances.
        residual: ``(m, N)`` innovations ``z − h(x⁻)``.
        H: ``(m, n)`` shared or ``(m, n, N)`` per-sample Jacobians.
        R: ``(m, m)`` shared or ``(m, m, N)`` per-sample noise covariances.

    Returns:
        `KalmanUpdate`.
    """
    n, batch = x.shape
    m = residual.shape[0]
    assert P.shape == (n, n, batch), f"P must be (n, n, N) = {(n, n, batch)}, got {P.shape}"
    assert residual.shape == (m, batch), f"residual must be (m, N), got {residual.shape}"
    assert H.shape in ((m, n), (m, n, batch)), f"H must be (m, n) or (m, n, N), got {H.shape}"
    assert R.shape in ((m, m), (m, m, batch)), f"R must be (m, m) or (m, m, N), got {R.shape}"
    if m == 1 and n <= SMALL_STATE_MAX:
        h = [H[0, j] for j in range(n)]
        r_var = R[0, 0]
        x_new, p_up, S, kt = update_scalar_upper(x, P, residual[0], h, r_var)
        nis = residual[0] * residual[0] / S
        loglik = gaussian_log_likelihood(nis, S.log(), 1)
        return KalmanUpdate(x_new, full_from_upper(p_up, n), S.reshape(1, 1, batch),
                            kt.unsqueeze(1), nis, loglik)
    H_b = H.permute(2, 0, 1) if H.ndim == 3 else H.expand(batch, m, n)
    R_b = R.permute(2, 0, 1) if R.ndim == 3 else R.expand(batch, m, m)
    out = update_dense(x.t(), P.permute(2, 0, 1), residual.t(), H_b, R_b)
    return KalmanUpdate(
        out.x.t(), out.P.permute(1, 2, 0), out.S.permute(1, 2, 0), out.gain.permute(1, 2, 0),
        out.nis, gaussian_log_likelihood(out.nis, out.log_det_S, m),
    )
