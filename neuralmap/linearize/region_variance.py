"""Mean squared miss of the tangent plane over the position uncertainty (Gauss-Hermite).

For an estimate ``p`` with horizontal covariance ``P`` the linearisation error of the
tangent plane is ``e(d) = h(p + d) - h(p) - slope . d`` with ``d ~ N(0, P)``; its second
moment ``E[e^2]`` is the extra measurement variance of the linearised terrain (the
neural-map analogue of the plane-fit residual over Omega_adp, SEEDS 000). It is computed
with the 3 x 3 Gauss-Hermite product rule (probabilists' nodes ``0, +-sqrt(3)``, weights
``2/3, 1/6`` per axis) on ``d = S u`` with ``S S^T = P``. The rule integrates polynomials
of degree <= 5 in ``u`` exactly; ``e^2`` of a quadratic terrain is quartic, so the result
is exact there for any square root ``S``.

Two guards keep the number meaningful (and never NaN):

* **Nodes off the map.** A node outside the terrain's extent, or whose height is not
  finite, is not used. The eight non-centre nodes come in mirror pairs ``+-u`` of equal
  weight, and ``e(d) = e(-d)`` for a quadratic terrain, so a pair with one usable node uses
  that node's miss for both (still exact for a quadratic). A pair with no usable node is
  dropped and the weights of the remaining nodes (the centre included; its miss is zero by
  construction) are renormalised to one. The share of the rule's weight kept is reported.
* **A covariance that is not positive definite.** ``torch.linalg.cholesky_ex`` is checked
  per sample; where it fails (singular or indefinite ``P``) the square root is taken from
  the eigen-decomposition with negative eigenvalues clamped to zero (the nearest positive
  semi-definite matrix in the Frobenius norm). A non-finite ``P`` has no square root: its
  variance is zero. Both cases are reported.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import torch

from neuralmap.filters.stats import symmetrize

#: How the square root of a position covariance was taken (`RegionReport.root`).
ROOT_CHOLESKY = 0
ROOT_EIGEN_CLAMPED = 1
ROOT_NONE = 2

_ROOT3 = math.sqrt(3.0)
#: One node of each mirror pair ``+-u`` (units of the covariance root) and the pair's
#: per-node weight: two diagonal corners, then the two axis nodes.
_HALF_NODES = ((_ROOT3, _ROOT3), (_ROOT3, -_ROOT3), (_ROOT3, 0.0), (0.0, _ROOT3))
_HALF_WEIGHTS = (1.0 / 36.0, 1.0 / 36.0, 1.0 / 9.0, 1.0 / 9.0)
#: Weight of the centre node (its miss is zero).
CENTRE_WEIGHT = 4.0 / 9.0


class RegionReport(NamedTuple):
    """What a region-variance evaluation did, per sample.

    Attributes:
        coverage: ``(N,)`` share of the Gauss-Hermite weight that was used (1 = the full
            rule, possibly with mirrored nodes; ``4/9`` = no node off the centre was usable,
            the variance is then zero).
        nodes_used: ``(N,)`` number of the 8 off-centre nodes on the map with a finite
            height.
        root: ``(N,)`` int8 `ROOT_CHOLESKY`, `ROOT_EIGEN_CLAMPED` (singular or
            indefinite covariance) or `ROOT_NONE` (non-finite covariance, variance 0).
    """

    coverage: torch.Tensor
    nodes_used: torch.Tensor
    root: torch.Tensor


def covariance_root(cov: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A square root ``S`` with ``S S^T = cov`` for each covariance of a batch.

    Cholesky where it succeeds (``cholesky_ex``'s ``info == 0``); otherwise
    ``V diag(sqrt(max(lambda, 0)))`` from the eigen-decomposition of the symmetrised
    matrix; zero for a matrix with a non-finite entry.

    Args:
        cov: ``(N, d, d)`` covariances.

    Returns:
        ``(root (N, d, d), status (N,) int8)``, status one of `ROOT_CHOLESKY`,
        `ROOT_EIGEN_CLAMPED`, `ROOT_NONE`.
    """
    sym = symmetrize(cov)
    finite = torch.isfinite(sym).all(-1).all(-1)
    safe = torch.where(finite[:, None, None], sym, torch.zeros_like(sym))
    chol, info = torch.linalg.cholesky_ex(safe)
    failed = info != 0
    status = torch.full_like(info, ROOT_CHOLESKY, dtype=torch.int8)
    status[failed] = ROOT_EIGEN_CLAMPED
    status[~finite] = ROOT_NONE
    root = torch.where(failed[:, None, None], torch.zeros_like(chol), chol)
    if bool(failed.any()):
        values, vectors = torch.linalg.eigh(safe[failed])
        root[failed] = vectors * values.clamp(min=0.0).sqrt().unsqueeze(-2)
    return root, status


def region_miss_variance(
    terrain: Callable[[torch.Tensor], torch.Tensor],
    *,
    xy: torch.Tensor,
    pos_cov: torch.Tensor,
    height: torch.Tensor,
    slope: torch.Tensor,
    on_map: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> tuple[torch.Tensor, RegionReport]:
    """``E[(h(p + d) - h(p) - slope . d)^2]`` for ``d ~ N(0, pos_cov)``, Gauss-Hermite.

    Args:
        terrain: Maps ``(..., 2)`` metres to ``(...)`` heights.
        xy: ``(N, 2)`` linearisation points ``p``.
        pos_cov: ``(N, 2, 2)`` horizontal position covariance, m^2.
        height: ``(N,)`` ``h(p)``.
        slope: ``(N, 2)`` tangent-plane slope at ``p``.
        on_map: ``(..., 2) -> (...)`` bool, where the terrain is valid (``None``: everywhere).

    Returns:
        ``(variance (N,), report)`` in ``xy``'s dtype; see the module docstring for nodes
        off the map and covariances that are not positive definite.
    """
    dtype, device = xy.dtype, xy.device
    half = torch.tensor(_HALF_NODES, dtype=dtype, device=device)
    u = torch.cat([half, -half])  # (8, 2): node k and its mirror k + 4
    pair_weight = 2.0 * torch.tensor(_HALF_WEIGHTS, dtype=dtype, device=device)  # (4,)
    root, status = covariance_root(pos_cov.to(dtype))
    offsets = torch.einsum("nij,kj->nki", root, u)  # (N, 8, 2)
    nodes = xy.unsqueeze(1) + offsets
    around = terrain(nodes).to(dtype)  # (N, 8)
    miss = around - height.unsqueeze(1) - (offsets * slope.unsqueeze(1)).sum(-1)
    usable = torch.isfinite(miss)
    if on_map is not None:
        usable = usable & on_map(nodes)
    square = torch.where(usable, miss, torch.zeros_like(miss)).square().unflatten(1, (2, 4))
    count = usable.unflatten(1, (2, 4)).sum(1)  # (N, 4) usable nodes per mirror pair
    pair_mean = square.sum(1) / count.clamp(min=1).to(dtype)
    kept = torch.where(count > 0, pair_weight, torch.zeros_like(pair_weight))  # (N, 4)
    coverage = CENTRE_WEIGHT + kept.sum(-1)
    variance = (kept * pair_mean).sum(-1) / coverage
    variance = torch.where(status == ROOT_NONE, torch.zeros_like(variance), variance)
    report = RegionReport(coverage=coverage, nodes_used=usable.sum(-1), root=status)
    return variance, report
