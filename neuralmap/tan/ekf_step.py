"""The 5-state terrain-aided navigation (TAN) error-state EKF step (SEEDS 004).

The step every EKF navigation method takes (`neuralmap.tan.methods.ekf`), and the
differentiable filter of the learning code.

State ``δX = [δx, δy, δh, δv_x, δv_y]`` = INS minus truth; output correction: the corrected
estimate is ``INS − δX̂``. One step (`tan_filter_step`):

1. predict ``δX̂⁻ = Φ δX̂``, ``P⁻ = Φ P Φᵀ + Q`` (SEEDS 004, Φ);
2. linearise the map at the best horizontal estimate ``p̂ = p_ins − δX̂⁻[:2]`` with the
   horizontal covariance ``P⁻[:2, :2]`` (adaptive methods use it);
3. residual (the innovation) ``r = (ĥ − h_map(p̂)) − h_radar``, ``ĥ = h_ins − δĥ⁻``:
   predicted clearance minus radar clearance (SEEDS 004, measurement ``z``); since
   ``h_radar = h − t(p) + v`` this is ``r ≈ H (δX − δX̂⁻) − v`` with
   ``H = [−h_x, −h_y, 1, 0, 0]`` (SEEDS 004, H);
4. update with ``R = R_base + lin.variance`` (``R_base`` = altimeter variance + map fit
   variance), skipping samples whose estimate ``p̂`` is off the map.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.linearize.base import Linearizer
from neuralmap.tan.model import N_STATES
from neuralmap.terrain.base import inside_extent

__all__ = ["StepDiagnostics", "linearizer_extent", "linearizer_map", "tan_filter_step"]

@dataclass
class StepDiagnostics:
    """Per-sample diagnostics of one TAN filter step.

    Attributes:
        residual: ``(N,)`` innovation ``(ĥ − h_map(p̂)) − h_radar`` (0 where not updated).
        S: ``(N,)`` innovation variance ``H P⁻ Hᵀ + R``.
        nis: ``(N,)`` normalised innovation squared ``r² / S``.
        on_map: ``(N,)`` bool, the estimate ``p̂`` was inside the map extent.
        updated: ``(N,)`` bool, the measurement update was applied (on map, not masked,
            filter healthy).
        lin_variance: ``(N,)`` linearisation variance the linearizer returned, m².
        p_hat: ``(N, 2)`` horizontal estimate where the map was linearised.
    """

    residual: torch.Tensor
    S: torch.Tensor
    nis: torch.Tensor
    on_map: torch.Tensor
    updated: torch.Tensor
    lin_variance: torch.Tensor
    p_hat: torch.Tensor


def _jacobian_batch_last(slope: torch.Tensor) -> torch.Tensor:
    """``Hᵀ`` as a contiguous ``(5, N)`` tensor (the EKF works on batch-last rows).

    Passing ``ht.t()`` to the EKF avoids a strided copy in its hot path. Uses in-place
    writes into one allocation unless ``slope`` carries a graph.
    """
    n = slope.shape[0]
    if slope.requires_grad:
        ones = torch.ones(1, n, dtype=slope.dtype, device=slope.device)
        zeros = torch.zeros(2, n, dtype=slope.dtype, device=slope.device)
        return torch.cat([-slope.t(), ones, zeros], dim=0)
    ht = torch.empty(N_STATES, n, dtype=slope.dtype, device=slope.device)
    torch.neg(slope.t(), out=ht[:2])
    ht[2].fill_(1.0)
    ht[3:].zero_()
    return ht


def linearizer_map(linearizer: Any) -> Any:
    """The map a linearizer reads (its ``.terrain``, ``.grid`` or ``.model``, through
    wrappers' ``.inner``): the first with an ``extent``; None when there is none."""
    seen = linearizer
    while seen is not None:
        for owner in (getattr(seen, "terrain", None), getattr(seen, "grid", None),
                      getattr(seen, "model", None)):
            if getattr(owner, "extent", None) is not None:
                return owner
        seen = getattr(seen, "inner", None)
    return None


def linearizer_extent(linearizer: Any) -> tuple[float, float, float, float] | None:
    """The map extent of a linearizer (its own, or of the map it reads, `linearizer_map`)."""
    extent = getattr(linearizer, "extent", None)
    if extent is None:
        extent = getattr(linearizer_map(linearizer), "extent", None)
    return None if extent is None else tuple(float(e) for e in extent)  # type: ignore[return-value]


def tan_filter_step(
    ekf: Any,
    ins_pos: torch.Tensor,
    radar: torch.Tensor,
    linearizer: Linearizer,
    *,
    F: torch.Tensor,
    Q: torch.Tensor,
    R: float | torch.Tensor,
    extent: tuple[float, float, float, float] | None = None,
    mask: torch.Tensor | None = None,
    policy: Any = None,
    jacobian: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> StepDiagnostics:
    """One TAN step: predict, linearise at the estimate, altimeter update (SEEDS 004).

    Samples whose horizontal estimate ``p̂`` lies outside ``extent`` (or with
    ``mask == False``) are predicted but not updated, and their residual is set to 0 so a
    map that returns NaN off its extent cannot leak into the filter.

    Args:
        ekf: A `neuralmap.filters.ekf.BatchedEKF` with ``n = 5`` states; updated in
            place.
        ins_pos: ``(N, 3)`` INS position ``x, y, h`` at this step, m.
        radar: ``(N,)`` radar-altimeter clearance, m.
        linearizer: The map linearisation method (``forward(xy, pos_cov) ->
            Linearization``).
        F: ``(5, 5)`` transition matrix (`neuralmap.tan.model.TanModel.transition`).
        Q: ``(5, 5)`` or ``(N, 5, 5)`` process noise.
        R: Base measurement variance (altimeter + map fit), float or ``(N,)`` m²; the
            linearisation variance is added per sample.
        extent: Map ``(xmin, xmax, ymin, ymax)``; None = the linearizer's (or no check).
        mask: ``(N,)`` bool, optional; False skips the update of that sample.
        policy: Optional robust/adaptive filter policy
            (`neuralmap.filters.policies`), passed to the predict and the update.
        jacobian: For a state augmented beyond the 5 navigation states (e.g. the AR
            map-error states of `neuralmap.tan.augmented`): builds the ``(N, n)``
            rows of H from the ``(N, 2)`` slopes. The extra states enter the measurement
            linearly, so their prediction ``H[:, 5:] · x̂⁻[5:]`` is taken off the residual.
            None = the 5-state ``H = [−h_x, −h_y, 1, 0, 0]``.

    Returns:
        `StepDiagnostics`.
    """
    n = ekf.x.shape[0]
    if ins_pos.shape != (n, 3) or radar.shape != (n,):
        raise NeuralMapError(
            f"tan_filter_step: ins_pos must be ({n}, 3) and radar ({n},) for {n} filters, got "
            f"{tuple(ins_pos.shape)} and {tuple(radar.shape)}."
        )
    if policy is None:
        ekf.predict(F, Q)
    else:
        ekf.predict(F, Q, policy=policy)
    x = ekf.x
    p_hat = ins_pos[:, :2] - x[:, :2]
    lin = linearizer(p_hat, ekf.P[:, :2, :2])
    dtype = x.dtype
    height = lin.height.to(dtype)
    slope = lin.slope.to(dtype)
    lin_var = lin.variance.to(dtype)
    if extent is None:
        extent = linearizer_extent(linearizer)
    if extent is None:
        use = torch.ones(n, dtype=torch.bool, device=x.device) if mask is None else mask
        on_map = use if mask is None else torch.ones_like(mask)
    else:
        on_map = inside_extent(p_hat, extent)
        use = on_map if mask is None else on_map & mask
    residual = (ins_pos[:, 2] - x[:, 2]) - height - radar
    r_total = lin_var + R
    all_used = bool(use.all())
    if not all_used:  # skipped samples: no NaN from an off-map linearisation
        residual = torch.where(use, residual, 0.0)
        slope = torch.where(use.unsqueeze(1), slope, 0.0)
        r_total = torch.where(use, r_total, 1.0)
    if jacobian is None:
        rows = _jacobian_batch_last(slope).t()
    else:
        rows = jacobian(slope)
        predicted = (rows[:, N_STATES:] * x[:, N_STATES:]).sum(dim=1)
        residual = residual - (predicted if all_used else torch.where(use, predicted, 0.0))
    kwargs = {} if policy is None else {"policy": policy}
    diag = ekf.update(residual, rows, r_total, mask=None if all_used else use, **kwargs)
    S = diag.S.reshape(n)
    applied = getattr(diag, "applied", None)
    return StepDiagnostics(
        residual=residual,
        S=S,
        nis=diag.nis.reshape(n),
        on_map=on_map,
        updated=use & diag.healthy if applied is None else applied & use,
        lin_variance=lin_var,
        p_hat=p_hat,
    )
