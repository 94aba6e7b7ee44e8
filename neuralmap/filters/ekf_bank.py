"""EKF bank (Gaussian-sum filter): K weighted EKF hypotheses per run, N runs at once.

The classical answer to a multimodal prior that one EKF cannot linearise (SITAN-style
parallel EKFs; Alspach and Sorenson's Gaussian sum): the prior of each run is split into
K Gaussian components, each run by its own EKF, and each component's weight is multiplied
by the likelihood of its innovation,

    log w_k ← log w_k − ½ (log 2π S_k + ν_k² / S_k),      then normalised per run,

(scalar measurements; ``ν_k`` the innovation, ``S_k`` its variance). All ``N · K``
components live in one `BatchedEKF` (component ``k`` of run
``n`` is sample ``n · K + k``), so any linearisation a caller uses with the EKF works with
the bank. Components whose weight falls below ``prune_threshold × max`` are pruned (weight
0, no further updates); components closer than ``merge_distance`` (squared Mahalanobis
distance of the means under the heavier one's covariance) are merged by moment matching
into the heavier one. The mixture's mean and covariance are the run's estimate. A run
whose components all get zero likelihood keeps its weights (a counted recovery).
"""

from __future__ import annotations

import math

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.ekf import BatchedEKF
from neuralmap.filters.stats import symmetrize

__all__ = ["GaussianSumEKF", "lattice_prior"]

_LOG_2PI = math.log(2.0 * math.pi)


def lattice_prior(
    x0: torch.Tensor,
    P0: torch.Tensor,
    *,
    per_axis: int,
    span_sigma: float = 2.5,
    axes: tuple[int, int] = (0, 1),
    shrink: float = 0.6,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Splits a Gaussian prior into a moment-matched ``per_axis × per_axis`` lattice of components.

    The component means sit on a regular lattice over ``± span_sigma · σ`` of two state
    ``axes`` (the horizontal error). Each component keeps ``P0`` but with those two
    variances replaced by ``c²``, ``c`` aimed at ``shrink · spacing`` (at most ``0.8 σ``);
    the weights are a Gaussian of variance ``σ² − c²`` at the lattice points, and ``c²`` is
    then set to ``σ² − Σ_k w_k g_k²`` (``g_k`` the lattice offsets), so that the mixture has
    exactly the prior's mean and covariance (law of total variance,
    ``Cov = E[Cov_k] + Cov[mean_k]``). A coarse lattice over a wide span therefore puts
    almost all weight on its centre: covering ``± span_sigma · σ`` and keeping the prior's
    moments cannot both be had with few components.

    Args:
        x0: ``(N, n)`` prior means.
        P0: ``(n, n)`` prior covariance, or ``(N, n, n)`` one per run (positive definite;
            diagonal on ``axes`` assumed).
        per_axis: Components per axis (K = per_axis²).
        span_sigma: Lattice half-width in prior standard deviations.
        axes: The two state indices spread over.
        shrink: Aimed component standard deviation as a fraction of the lattice spacing.

    Returns:
        ``(means (N, K, n), covs (K, n, n) or (N, K, n, n), log_weights (N, K))``; the
        mixture's mean is ``x0`` and its covariance ``P0``.
    """
    if per_axis < 1:
        raise NeuralMapError(f"lattice_prior: per_axis must be >= 1, got {per_axis}.")
    dtype = x0.dtype
    P0 = torch.as_tensor(P0, dtype=dtype, device=x0.device)
    i, j = axes
    si = P0[..., i, i].sqrt()[..., None]  # (1,) or (N, 1): σ per run
    sj = P0[..., j, j].sqrt()[..., None]
    if per_axis == 1:
        unit = torch.zeros(1, dtype=dtype, device=x0.device)
    else:
        unit = torch.linspace(-span_sigma, span_sigma, per_axis, dtype=dtype, device=x0.device)
    # component σ / prior σ, aimed at shrink · spacing and at most 0.8
    aim = 1.0 if per_axis == 1 else min(shrink * 2.0 * span_sigma / (per_axis - 1), 0.8)
    spread = max(1.0 - aim**2, 1e-12)  # lattice weights' variance, in prior σ²
    axis_logw = -0.5 * unit**2 / spread
    axis_w = torch.softmax(axis_logw, 0)
    component = max(1.0 - float((axis_w * unit**2).sum()), 1e-6)  # c² / σ², moments exact
    gi, gj = torch.meshgrid(unit, unit, indexing="ij")
    gi, gj = gi.reshape(-1), gj.reshape(-1)
    k = gi.numel()
    means = x0[:, None, :].expand(-1, k, -1).clone()
    means[..., i] += gi * si
    means[..., j] += gj * sj
    covs = P0.unsqueeze(-3).expand(*P0.shape[:-2], k, *P0.shape[-2:]).clone()
    covs[..., i, i] = component * si**2
    covs[..., j, j] = component * sj**2
    covs[..., i, j] = covs[..., j, i] = 0.0
    logw = -0.5 * (gi**2 + gj**2) / spread
    logw = logw - torch.logsumexp(logw, 0)
    return means, covs, logw.expand(x0.shape[0], k).clone()


class GaussianSumEKF:
    """A bank of K EKFs per run with innovation-likelihood weights, pruning and merging.

    Args:
        means: ``(N, K, n)`` component means.
        covs: ``(n, n)``, ``(K, n, n)`` or ``(N, K, n, n)`` component covariances.
        log_weights: ``(N, K)`` log prior weights (normalised here); None = uniform.
        prune_threshold: Relative weight below which a component is pruned.
        merge_distance: Squared Mahalanobis distance under which components merge
            (0 disables merging).
        dtype: Filter dtype (default: that of ``means``).

    Attributes:
        ekf: The underlying `BatchedEKF` over ``N · K`` samples.
        log_weights: ``(N, K)`` normalised log weights (−inf = pruned).
        recoveries: ``(N,)`` count of updates where every component's likelihood vanished.
    """

    def __init__(
        self,
        means: torch.Tensor,
        covs: torch.Tensor,
        *,
        log_weights: torch.Tensor | None = None,
        prune_threshold: float = 1e-4,
        merge_distance: float = 1.0,
        dtype: torch.dtype | None = None,
    ) -> None:
        if means.ndim != 3:
            raise NeuralMapError(
                f"GaussianSumEKF: means must have shape (N, K, n), got {tuple(means.shape)}."
            )
        if not 0.0 <= prune_threshold < 1.0 or merge_distance < 0.0:
            raise NeuralMapError(
                "GaussianSumEKF: prune_threshold must be in [0, 1) and merge_distance >= 0, "
                f"got {prune_threshold} and {merge_distance}."
            )
        dtype = dtype or (means.dtype if means.is_floating_point() else torch.float64)
        n, k, d = means.shape
        self.n_runs, self.n_components, self.n_states = n, k, d
        covs = torch.as_tensor(covs, dtype=dtype, device=means.device)
        covs = covs.expand(n, k, d, d).reshape(n * k, d, d)
        self.ekf = BatchedEKF(means.reshape(n * k, d).to(dtype), covs, dtype=dtype)
        if log_weights is None:
            log_weights = torch.zeros(n, k, dtype=dtype, device=means.device)
        log_weights = torch.as_tensor(log_weights, dtype=dtype, device=means.device)
        if tuple(log_weights.shape) != (n, k):
            raise NeuralMapError(
                f"GaussianSumEKF: log_weights must have shape (N, K) = ({n}, {k}), got "
                f"{tuple(log_weights.shape)}."
            )
        self.log_weights = log_weights - torch.logsumexp(log_weights, 1, keepdim=True)
        self.prune_threshold = prune_threshold
        self.merge_distance = merge_distance
        self.recoveries = torch.zeros(n, dtype=torch.int64, device=means.device)

    @property
    def alive(self) -> torch.Tensor:
        """``(N · K,)`` bool, components still in the mixture (flattened like the EKF)."""
        return (torch.isfinite(self.log_weights).reshape(-1) & self.ekf.healthy)

    def reweight(self, residual: torch.Tensor, S: torch.Tensor,
                 applied: torch.Tensor) -> torch.Tensor:
        """Multiplies weights by the innovation likelihoods, normalises, prunes and merges.

        Args:
            residual: ``(N · K,)`` innovations of the last scalar update.
            S: ``(N · K,)`` innovation variances.
            applied: ``(N · K,)`` bool, components whose update was applied (others keep
                their weight factor 1, i.e. no information).

        Returns:
            ``(N,)`` log predictive likelihood of the measurement per run.
        """
        n, k = self.n_runs, self.n_components
        r = residual.reshape(n, k).to(self.log_weights.dtype)
        s = S.reshape(n, k).to(self.log_weights.dtype)
        use = applied.reshape(n, k)
        loglik = -0.5 * (_LOG_2PI + s.log() + r * r / s)
        loglik = torch.where(use & torch.isfinite(loglik), loglik,
                             torch.where(use, -math.inf, 0.0))
        alive = self.alive.reshape(n, k)
        logw = torch.where(alive, self.log_weights + loglik, -math.inf)
        total = torch.logsumexp(logw, 1)
        ok = torch.isfinite(total)
        self.recoveries.add_((~ok).long())
        self.log_weights = torch.where(ok[:, None], logw - total[:, None], self.log_weights)
        self.log_weights = torch.where(alive, self.log_weights, -math.inf)
        self.prune()
        if self.merge_distance > 0.0:
            self.merge()
        return torch.where(ok, total, -math.inf)

    def prune(self) -> None:
        """Sets components below ``prune_threshold × max`` weight to weight 0."""
        if self.prune_threshold <= 0.0:
            return
        peak = self.log_weights.amax(1, keepdim=True)
        dead = self.log_weights < peak + math.log(self.prune_threshold)
        logw = torch.where(dead, -math.inf, self.log_weights)
        self.log_weights = logw - torch.logsumexp(logw, 1, keepdim=True)

    def merge(self) -> None:
        """Moment-matched merge of components within ``merge_distance`` of a heavier one.

        Loops over the component index (not over runs): component ``i`` absorbs every
        lighter live component ``j`` with ``(x_j − x_i)ᵀ P_i⁻¹ (x_j − x_i) < merge_distance``.
        Each pass works on the runs where component ``i`` is alive only (after acquisition
        most runs keep a few of their K components), and merges on the runs that grab one.
        """
        n, k, d = self.n_runs, self.n_components, self.n_states
        x = self.ekf.x.reshape(n, k, d)
        P = self.ekf.P.reshape(n, k, d, d)
        w = self.log_weights.exp()
        changed = False
        for i in range(k):
            rows = (w[:, i] > 0).nonzero().reshape(-1)
            if rows.numel() == 0:
                continue
            xr, wr = x.index_select(0, rows), w.index_select(0, rows)
            wi = wr[:, i]
            diff = xr - xr[:, i : i + 1]  # (m, k, d)
            chol = torch.linalg.cholesky_ex(P[rows, i])
            sol = torch.cholesky_solve(diff.transpose(1, 2), chol.L)  # (m, d, k)
            dist = (diff.transpose(1, 2) * sol).sum(1)  # (m, k)
            grab = ((dist < self.merge_distance) & (wr > 0) & (wr <= wi[:, None])
                    & (chol.info == 0)[:, None])
            grab[:, i] = False
            took = grab.any(1)
            if not bool(took.any()):
                continue
            if not changed:
                x, P = x.clone(), P.clone()
                changed = True
            sel = took.nonzero().reshape(-1)
            rr = rows.index_select(0, sel)
            g, xs, ws = grab.index_select(0, sel), xr.index_select(0, sel), wr.index_select(0, sel)
            Ps = P.index_select(0, rr)
            gw = torch.where(g, ws, 0.0)
            gw[:, i] = ws[:, i]
            tot = gw.sum(1)
            mean = (gw[..., None] * xs).sum(1) / tot[:, None]
            dx = xs - mean[:, None]
            cov = (gw[..., None, None] * (Ps + dx[..., :, None] * dx[..., None, :])).sum(1)
            cov = cov / tot[:, None, None]
            cov = symmetrize(cov)
            x[rr, i] = mean
            P[rr, i] = cov
            wn = torch.where(g, 0.0, ws)
            wn[:, i] = tot
            w = w.index_copy(0, rr, wn)
        if changed:
            self.ekf.x = x.reshape(n * k, d)
            self.ekf.P = P.reshape(n * k, d, d)
            self.log_weights = w.log()

    def mixture(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Mixture mean ``(N, n)`` and covariance ``(N, n, n)`` of every run."""
        n, k, d = self.n_runs, self.n_components, self.n_states
        w = self.log_weights.exp()
        x = self.ekf.x.reshape(n, k, d)
        P = self.ekf.P.reshape(n, k, d, d)
        mean = (w[..., None] * x).sum(1)
        dx = x - mean[:, None]
        cov = (w[..., None, None] * (P + dx[..., :, None] * dx[..., None, :])).sum(1)
        return mean, symmetrize(cov)

    def best(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean ``(N, n)`` and covariance ``(N, n, n)`` of each run's heaviest component."""
        n, k, d = self.n_runs, self.n_components, self.n_states
        idx = self.log_weights.argmax(1)
        x = self.ekf.x.reshape(n, k, d)[torch.arange(n), idx]
        P = self.ekf.P.reshape(n, k, d, d)[torch.arange(n), idx]
        return x, P
