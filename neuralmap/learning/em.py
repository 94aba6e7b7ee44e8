"""EM for Q and R of a linear-Gaussian model (Shumway & Stoffer 1982), in NumPy.

The reference the gradient learner is checked against: for ``x_k = F x_{k−1} + w``,
``w ~ N(0, Q)``, ``z_k = H_k x_k + v``, ``v ~ N(0, R)`` (scalar ``z``), ``x_0 ~ N(x0, P0)``
with F, H, x0, P0 known, one EM iteration is

* E-step: Kalman filter, Rauch–Tung–Striebel smoother ``x̂_k|K``, ``P_k|K`` and the lag-one
  smoothed covariance ``P_{k,k−1|K} = P_k|K J_{k−1}ᵀ``, ``J_{k−1} = P_{k−1|k−1} Fᵀ
  P_{k|k−1}⁻¹`` (de Jong 1989; equal to Shumway–Stoffer's recursion, eq. 6.56);
* M-step: ``Q = (1/NK) Σ [e_k e_kᵀ + P_k|K − F P_{k,k−1}ᵀ − P_{k,k−1} Fᵀ + F P_{k−1|K} Fᵀ]``
  with ``e_k = x̂_k|K − F x̂_{k−1|K}`` (its diagonal when Q is constrained diagonal), and
  ``R = (1/M) Σ_measured [(z_k − H_k x̂_k|K)² + H_k P_k|K H_kᵀ]``.

Each iteration does not decrease the likelihood; its fixed point is a stationary point of
the likelihood — the maximum-likelihood answer the gradient method must also find.
Flights are vectorised (NaN measurements are skipped, as in the filter).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["EmResult", "em_noise", "kalman_smoother"]


@dataclass
class EmResult:
    """EM iterations.

    Attributes:
        Q: ``(n, n)`` final Q.
        R: Final R.
        log_likelihood: Per iteration, the log-likelihood at the iteration's start values.
        iterations: Iterations run.
        converged: The relative parameter change fell below the tolerance.
        Q_path: Diagonal of Q per iteration.
        R_path: R per iteration.
    """

    Q: np.ndarray
    R: float
    log_likelihood: list[float] = field(default_factory=list)
    iterations: int = 0
    converged: bool = False
    Q_path: list[list[float]] = field(default_factory=list)
    R_path: list[float] = field(default_factory=list)


def kalman_smoother(z: np.ndarray, H: np.ndarray, F: np.ndarray, Q: np.ndarray, R: float,
                    x0: np.ndarray, P0: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Filter + RTS smoother of N flights.

    Args:
        z: ``(N, K+1)`` measurements (``z[:, 0]`` unused, NaN = missing).
        H: ``(N, K+1, n)`` rows. F, Q: ``(n, n)``. R: variance. x0: ``(n,)``. P0: ``(n, n)``.

    Returns:
        ``xs (N, K+1, n)``, ``Ps (N, K+1, n, n)``, lag-one ``Pl (N, K+1, n, n)``
        (``Pl[:, k] = Cov(x_k, x_{k−1} | all)``, ``Pl[:, 0]`` unused) and the
        log-likelihood.
    """
    nf, k1 = z.shape
    n = F.shape[0]
    xf = np.zeros((nf, k1, n))
    Pf = np.zeros((nf, k1, n, n))
    Pp = np.zeros((nf, k1, n, n))
    xf[:, 0] = x0
    Pf[:, 0] = P0
    loglik = 0.0
    for k in range(1, k1):
        xp = xf[:, k - 1] @ F.T
        P = F @ Pf[:, k - 1] @ F.T + Q
        Pp[:, k] = P
        h = H[:, k]
        ok = np.isfinite(z[:, k])
        ph = np.einsum("nij,nj->ni", P, h)
        S = np.einsum("ni,ni->n", h, ph) + R
        r = np.where(ok, z[:, k] - np.einsum("ni,ni->n", h, xp), 0.0)
        K = ph / S[:, None]
        xf[:, k] = xp + np.where(ok[:, None], K * r[:, None], 0.0)
        Pu = P - np.einsum("ni,nj->nij", K, ph)
        Pf[:, k] = np.where(ok[:, None, None], 0.5 * (Pu + Pu.transpose(0, 2, 1)), P)
        loglik += float(np.sum(np.where(ok, -0.5 * (np.log(2 * np.pi * S) + r * r / S), 0.0)))
    xs = xf.copy()
    Ps = Pf.copy()
    Pl = np.zeros_like(Pf)
    for k in range(k1 - 2, -1, -1):
        J = Pf[:, k] @ F.T @ np.linalg.inv(Pp[:, k + 1])
        xs[:, k] = xf[:, k] + np.einsum("nij,nj->ni", J, xs[:, k + 1] - xf[:, k] @ F.T)
        Ps[:, k] = Pf[:, k] + J @ (Ps[:, k + 1] - Pp[:, k + 1]) @ J.transpose(0, 2, 1)
        Pl[:, k + 1] = Ps[:, k + 1] @ J.transpose(0, 2, 1)
    return xs, Ps, Pl, loglik


def em_noise(z: np.ndarray, H: np.ndarray, *, F: np.ndarray, Q0: np.ndarray, R0: float,
             x0: np.ndarray, P0: np.ndarray, diagonal_q: bool = True,
             max_iter: int = 20000, tol: float = 1e-10) -> EmResult:
    """EM estimate of Q and R (see the module docstring).

    Args:
        z, H, F, x0, P0: As in `kalman_smoother`.
        Q0, R0: Start values.
        diagonal_q: Constrain Q to be diagonal.
        max_iter: Iteration limit.
        tol: Stop when the largest relative change of a Q entry or R is below this.

    Returns:
        `EmResult`.
    """
    Q = np.array(Q0, dtype=np.float64)
    R = float(R0)
    result = EmResult(Q, R)
    measured = np.isfinite(z[:, 1:])
    n_meas = int(measured.sum())
    nf, k1 = z.shape
    for it in range(1, max_iter + 1):
        xs, Ps, Pl, ll = kalman_smoother(z, H, F, Q, R, x0, P0)
        result.log_likelihood.append(ll)
        result.Q_path.append(np.diag(Q).tolist())
        result.R_path.append(R)
        e = xs[:, 1:] - xs[:, :-1] @ F.T
        FPl = F @ Pl[:, 1:].transpose(0, 1, 3, 2)
        A = (np.einsum("nki,nkj->ij", e, e) + Ps[:, 1:].sum((0, 1))
             - FPl.sum((0, 1)) - FPl.sum((0, 1)).T
             + (F @ Ps[:, :-1] @ F.T).sum((0, 1)))
        Q_new = A / (nf * (k1 - 1))
        Q_new = np.diag(np.diag(Q_new)) if diagonal_q else 0.5 * (Q_new + Q_new.T)
        h = H[:, 1:]
        resid = np.where(measured, z[:, 1:] - np.einsum("nki,nki->nk", h, xs[:, 1:]), 0.0)
        hph = np.einsum("nki,nkij,nkj->nk", h, Ps[:, 1:], h)
        R_new = float(np.sum(np.where(measured, resid**2 + hph, 0.0)) / n_meas)
        change = max(float(np.max(np.abs(np.diag(Q_new) - np.diag(Q)) / np.abs(np.diag(Q)))),
                     abs(R_new - R) / R)
        Q, R = Q_new, R_new
        result.iterations = it
        if change < tol:
            result.converged = True
            break
    result.Q, result.R = Q, R
    return result
