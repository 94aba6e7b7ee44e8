"""Differentiable innovation log-likelihood of flights through the Kalman filter.

The prediction-error decomposition: for a (linearised) Gaussian state-space model the
log-likelihood of the measurements is the sum over updates of the innovation log-density
``ℓ_k = −½ (ln 2π + ln S_k + r_k² / S_k)`` (Schweppe 1965; Shumway & Stoffer 2017, eq.
6.62), which the functional Kalman core (`neuralmap.filters.kalman`) returns with
every update. Everything here is pure torch on batch-last storage, so gradients reach Q,
R (and, through the linearizer, the map) with ``loss.backward()``.

Masking: an update is applied only where the sample exists (flight not over), the altimeter
reading is finite, and (TAN) the estimate lies on the map. Elsewhere the filter only
predicts, the step adds 0 to the likelihood, and the inputs of the skipped update are
replaced by harmless values before it is computed, so a NaN reading or an off-map
linearisation never reaches a gradient.

Truncated back-propagation through time: each pass runs steps ``start … stop − 1`` from a
`FilterState` and returns the state after them; `FilterState.detach` cuts the
graph between windows.

TAN linearisation: the map height enters the residual as
``h(p̂) ≈ h(p̂₀) + s·(p̂ − p̂₀)`` with ``p̂₀ = p̂`` detached (a straight-through first-order
term), so the gradient of the residual with respect to the estimate uses the slope ``s`` —
exact for the value and its first derivative whatever the linearizer is (a grid method
need not be differentiable). The slope's own dependence on the estimate (the terrain
curvature) is not differentiated unless the linearizer returns slopes with a graph
(``AutogradLinearizer(create_graph=True)``); on a plane terrain the gradient is exact.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from neuralmap.filters.kalman import kalman_predict, kalman_update
from neuralmap.learning.flights import FlightBatch
from neuralmap.terrain.base import inside_extent

__all__ = [
    "FilterState",
    "LikelihoodPass",
    "initial_state",
    "linear_log_likelihood",
    "masked_update",
    "tan_log_likelihood",
]


@dataclass
class FilterState:
    """Batch-last filter state of N flights.

    Attributes:
        x: ``(n, N)`` state estimates.
        P: ``(n, n, N)`` covariances.
    """

    x: torch.Tensor
    P: torch.Tensor

    def detach(self) -> FilterState:
        """The same state without its graph (the truncation of TBPTT)."""
        return FilterState(self.x.detach(), self.P.detach())


@dataclass
class LikelihoodPass:
    """What one pass over steps ``start … stop − 1`` returns.

    Attributes:
        log_likelihood: ``(N,)`` summed innovation log-likelihood per flight.
        n_updates: ``(N,)`` updates applied per flight.
        state: The filter state after the last step.
        nis: ``(N, steps)`` normalised innovation squared (NaN where not updated).
        nees: ``(N, steps)`` position-velocity NEES ``eᵀ P⁻¹ e`` over the 5 navigation
            states when the true error is known (else None).
        skipped_off_map: Updates skipped because the estimate left the map.
    """

    log_likelihood: torch.Tensor
    n_updates: torch.Tensor
    state: FilterState
    nis: torch.Tensor
    nees: torch.Tensor | None
    skipped_off_map: int = 0


def initial_state(n_flights: int, P0: torch.Tensor, *, x0: torch.Tensor | None = None
                  ) -> FilterState:
    """``x = x0`` (default 0), ``P = P0`` for every flight (batch last).

    Args:
        n_flights: N.
        P0: ``(n, n)`` prior covariance.
        x0: ``(n,)`` prior mean (default zeros).
    """
    n = P0.shape[0]
    x = torch.zeros(n, n_flights, dtype=P0.dtype, device=P0.device)
    if x0 is not None:
        x = x + x0.reshape(n, 1).to(P0)
    return FilterState(x, P0.unsqueeze(-1).expand(n, n, n_flights).clone())


def masked_update(state: FilterState, residual: torch.Tensor, h: torch.Tensor,
                  R: torch.Tensor, use: torch.Tensor
                  ) -> tuple[FilterState, torch.Tensor, torch.Tensor]:
    """Scalar-measurement Kalman update applied where ``use`` (Joseph form, SEEDS 004).

    Args:
        state: Predicted state.
        residual: ``(N,)`` innovation ``z − h(x⁻)`` (may be NaN where not used).
        h: ``(n, N)`` measurement rows (batch last).
        R: ``(N,)`` measurement variances.
        use: ``(N,)`` bool.

    Returns:
        ``(state⁺, log_likelihood (N,) with 0 where not used, nis (N,) NaN where not used)``.
    """
    n, batch = state.x.shape
    residual = torch.where(use, residual, torch.zeros_like(residual))
    h = torch.where(use, h, torch.zeros_like(h))
    R = torch.where(use, R, torch.ones_like(R))
    out = kalman_update(state.x, state.P, residual.reshape(1, batch), h.reshape(1, n, batch),
                        R.reshape(1, 1, batch))
    x = torch.where(use, out.x, state.x)
    P = torch.where(use, out.P, state.P)
    loglik = torch.where(use, out.log_likelihood, torch.zeros_like(out.log_likelihood))
    nis = torch.where(use, out.nis, torch.full_like(out.nis, float("nan")))
    return FilterState(x, P), loglik, nis


def linear_log_likelihood(z: torch.Tensor, H: torch.Tensor, *, F: torch.Tensor,
                          Q: torch.Tensor, R: torch.Tensor, P0: torch.Tensor,
                          x0: torch.Tensor | None = None, valid: torch.Tensor | None = None
                          ) -> LikelihoodPass:
    """Log-likelihood of a linear-Gaussian model with scalar measurements.

    ``x_k = F x_{k−1} + w``, ``w ~ N(0, Q)``; ``z_k = H_k x_k + v``, ``v ~ N(0, R)``,
    ``k = 1 … K``; ``x_0 ~ N(x0, P0)`` (sample 0 carries no measurement).

    Args:
        z: ``(N, K+1)`` measurements (NaN = missing; ``z[:, 0]`` unused).
        H: ``(N, K+1, n)`` measurement rows.
        F: ``(n, n)``; Q: ``(n, n)``; R: ``()`` variance; P0: ``(n, n)``.
        x0: ``(n,)`` prior mean (default 0).
        valid: ``(N, K+1)`` bool (default all True).

    Returns:
        `LikelihoodPass` (``nees`` None).
    """
    n_flights, k1 = z.shape
    valid = torch.ones_like(z, dtype=torch.bool) if valid is None else valid
    measured = valid & torch.isfinite(z)
    state = initial_state(n_flights, P0, x0=x0)
    total = torch.zeros(n_flights, dtype=P0.dtype, device=P0.device)
    nis_all = []
    for k in range(1, k1):
        x, P = kalman_predict(state.x, state.P, F, Q)
        hk = H[:, k].t()
        residual = z[:, k] - (hk * x).sum(0)
        state, ll, nis = masked_update(FilterState(x, P), residual, hk,
                                       R.reshape(()).expand(n_flights), measured[:, k])
        total = total + ll
        nis_all.append(nis)
    nis_t = torch.stack(nis_all, 1) if nis_all else z.new_zeros(n_flights, 0)
    return LikelihoodPass(total, measured[:, 1:].sum(1), state, nis_t, None)


def _tan_rows(slope: torch.Tensor, n: int) -> torch.Tensor:
    """``(n, N)`` rows ``H = [−h_x, −h_y, 1, 0, …]`` (SEEDS 004), batch last."""
    batch = slope.shape[0]
    ones = torch.ones(1, batch, dtype=slope.dtype, device=slope.device)
    zeros = torch.zeros(n - 3, batch, dtype=slope.dtype, device=slope.device)
    return torch.cat([-slope.t(), ones, zeros], dim=0)


def tan_log_likelihood(
    flights: FlightBatch,
    linearizer: Any,
    *,
    F: torch.Tensor,
    Q: torch.Tensor,
    R: torch.Tensor,
    P0: torch.Tensor | None = None,
    state: FilterState | None = None,
    start: int = 1,
    stop: int | None = None,
    extent: tuple[float, float, float, float] | None = None,
) -> LikelihoodPass:
    """Innovation log-likelihood of TAN flights through the 5-state EKF (SEEDS 004).

    The step is `neuralmap.tan.ekf_step.tan_filter_step`'s (predict, linearise at
    ``p̂ = p_ins − δX̂⁻[:2]``, residual ``(h_ins − δĥ⁻) − h_map(p̂) − h_radar``, update
    with ``R + lin.variance``), written on the pure functional core so that it is
    differentiable in Q, R and the map.

    Args:
        flights: The flights.
        linearizer: Map linearisation (``forward(xy, pos_cov) -> Linearization``).
        F: ``(5, 5)`` Φ.
        Q: ``(5, 5)`` process noise (may require grad).
        R: ``()`` base measurement variance (may require grad).
        P0: ``(5, 5)`` prior covariance (needed when ``state`` is None).
        state: State before step ``start`` (None = the prior at sample 0).
        start: First step (1 = the first update after the prior).
        stop: One past the last step (default K + 1).
        extent: Map extent; None = the linearizer's (no check when it has none).

    Returns:
        `LikelihoodPass`.
    """
    from neuralmap.tan.ekf_step import linearizer_extent

    stop = flights.n_steps + 1 if stop is None else stop
    n_flights = flights.n_flights
    if state is None:
        assert P0 is not None, "tan_log_likelihood: pass P0 or a state"
        state = initial_state(n_flights, P0)
    n = state.x.shape[0]
    extent = linearizer_extent(linearizer) if extent is None else extent
    measured = flights.measured
    radar = torch.where(measured, flights.radar, torch.zeros_like(flights.radar))
    total = torch.zeros(n_flights, dtype=state.x.dtype, device=state.x.device)
    count = torch.zeros(n_flights, dtype=torch.long, device=state.x.device)
    nis_all, nees_all = [], []
    skipped = 0
    for k in range(start, stop):
        x, P = kalman_predict(state.x, state.P, F, Q)
        ins = flights.ins_pos[:, k]
        p_hat = ins[:, :2] - x[:2].t()
        if extent is None:
            on_map = torch.ones(n_flights, dtype=torch.bool, device=x.device)
            p_lin = p_hat
        else:
            on_map = inside_extent(p_hat.detach(), extent)
            centre = p_hat.new_tensor([0.5 * (extent[0] + extent[1]),
                                       0.5 * (extent[2] + extent[3])])
            p_lin = torch.where(on_map.unsqueeze(1), p_hat, centre)
        pos_cov = P[:2, :2].permute(2, 0, 1).detach()
        lin = linearizer(p_lin.detach(), pos_cov)
        slope = lin.slope.to(x.dtype)
        height = lin.height.to(x.dtype) + (slope.detach() * (p_lin - p_lin.detach())).sum(1)
        residual = (ins[:, 2] - x[2]) - height - radar[:, k]
        use = measured[:, k] & on_map
        skipped += int((measured[:, k] & ~on_map).sum())
        r_k = R + lin.variance.to(x.dtype)
        state, ll, nis = masked_update(FilterState(x, P), residual, _tan_rows(slope, n), r_k,
                                       use)
        total = total + ll
        count = count + use.long()
        nis_all.append(nis.detach())
        if flights.ins_error is not None:
            err = (flights.ins_error[:, k] - state.x[:5].t()).detach()
            cov = state.P[:5, :5].permute(2, 0, 1).detach()
            nees = (err.unsqueeze(1) @ torch.linalg.solve(cov, err.unsqueeze(-1))).reshape(-1)
            nees_all.append(torch.where(flights.valid[:, k], nees, float("nan")))
    empty = total.new_zeros(n_flights, 0)
    return LikelihoodPass(
        total, count, state, torch.stack(nis_all, 1) if nis_all else empty,
        (torch.stack(nees_all, 1) if nees_all else empty) if flights.ins_error is not None
        else None,
        skipped,
    )
