"""Batched wind filters: the differenced TVAR-model EKF and the LTI-model Kalman filter.

:func:`run_tvar_filter` (SEEDS 002, the paper's estimator): the first-order time-varying
AR model of :mod:`.tvar_model` with the differenced measurement ``L_k = Z_{k+1} − Z_k``,
filtered by the correlated-noise EKF of :mod:`.correlated`: for ``k = 0 … T−2``

    update with L_k at x⁻_k   (residual L_k − h(x⁻_k), A_k = H F_k − H),
    decorrelated predict      (x⁻_{k+1} = f(x⁺_k) + J (L_k − h(x⁺_k)), J = C R_e⁻¹),

so ``x⁻_{k+1}`` is the estimate of the wind at ``k+1`` given ``Z_0 … Z_{k+1}`` (the
differenced measurement is one sample late by construction). The start is
``x_0 = [Z_0, a0, 0]``.

:func:`run_lti_filter`: the usual choice, a scalar Kalman filter of the first-order
Markov model on the raw measurement (white-noise assumption).

Both take scalar series ``(N, T)`` (one wind axis per row; :func:`estimate_wind` folds
the two axes into the batch) and an optional :class:`UpdateAdapter` that may reweight
``R`` and inflate ``P⁻`` at each update (robust / adaptive filtering).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.wind.correlated import correlated_predict, correlated_update
from neuralmap.wind.lti_model import LTIWindModel
from neuralmap.wind.tvar_model import TVARWindModel

__all__ = ["UpdateAdapter", "WindEstimate", "run_tvar_filter", "run_lti_filter",
           "estimate_wind"]


class UpdateAdapter(Protocol):
    """Hook of a robust or adaptive filter into the update of a wind filter.

    ``adjust`` returns the prior covariance and measurement-noise covariance to use for
    this update (``P⁻/α`` for an adaptive factor, ``R/weight`` for robust weights, an
    estimated ``R̂`` for Sage-Husa) and ``(Q, R)`` overrides for the next predict.
    """

    def adjust(
        self, step: int, residual: torch.Tensor, A: torch.Tensor, P: torch.Tensor,
        R: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Returns ``(P_eff (N, n, n), R_eff (N, m, m))`` for the update at ``step``."""
        ...

    def observe(
        self, step: int, residual: torch.Tensor, A: torch.Tensor, P_prior: torch.Tensor,
        P_post: torch.Tensor, gain: torch.Tensor, P_prev_post: torch.Tensor,
        F: torch.Tensor,
    ) -> None:
        """Sees the update's result (for noise-statistics estimation)."""
        ...


@dataclass
class WindEstimate:
    """Filter output aligned with the measurement samples, batch first.

    Attributes:
        wind: ``(N, T)`` or ``(N, T, 2)`` wind estimate at every sample.
        variance: Same shape, estimated variance of the wind component.
        nis: Same shape, NIS of the update that produced the estimate (NaN where none).
        coefficient: Same shape, AR coefficient estimate (TVAR) or the fixed φ (LTI).
    """

    wind: torch.Tensor
    variance: torch.Tensor
    nis: torch.Tensor
    coefficient: torch.Tensor


def _check_series(z: torch.Tensor, where: str) -> torch.Tensor:
    if not isinstance(z, torch.Tensor) or z.ndim != 2 or z.shape[1] < 2:
        shape = tuple(z.shape) if isinstance(z, torch.Tensor) else type(z).__name__
        raise NeuralMapError(f"{where}: 'z' must be a (N, T) tensor with T >= 2, got {shape}.")
    if not z.is_floating_point():
        z = z.double()
    return z


def run_tvar_filter(
    z: torch.Tensor,
    model: TVARWindModel,
    *,
    adapter: UpdateAdapter | None = None,
    correlated: bool = True,
) -> WindEstimate:
    """The paper's estimator on ``(N, T)`` measured-wind series (see module docstring).

    Args:
        z: ``(N, T)`` measured wind of one axis per row.
        model: TVAR model parameters (validated here).
        adapter: Optional robust/adaptive hook.
        correlated: Handle the cross-covariance of the differenced measurement noise and
            the process noise (default). False drops it (a plain EKF predict; for
            comparison only: the filter is then inconsistent when ``direct_noise``).

    Returns:
        :class:`WindEstimate` with ``(N, T)`` tensors.
    """
    where = "run_tvar_filter"
    model.validate()
    z = _check_series(z, where)
    batch, steps = z.shape
    dtype = z.dtype
    Q, R, C = model.noise_covariances(dtype=dtype)
    x, P = model.initial(z[:, 0])
    wind = [x[:, 0]]
    var = [P[:, 0, 0]]
    coef = [x[:, 1]]
    nis = [torch.full((batch,), float("nan"), dtype=dtype)]
    P_prev_post = P
    for k in range(steps - 1):
        L = (z[:, k + 1] - z[:, k]).unsqueeze(-1)
        hx, A = model.measurement(x)
        residual = L - hx
        R_k = R.expand(batch, 1, 1)
        P_eff = P
        if adapter is not None:
            P_eff, R_k = adapter.adjust(k, residual, A, P, R_k)
        x_post, P_post, diag = correlated_update(x, P_eff, residual=residual, A=A, R=R_k)
        fx, F = model.transition(x_post)
        if adapter is not None:
            adapter.observe(k, residual, A, P_eff, P_post, diag.gain, P_prev_post, F)
        hx_post, A_post = model.measurement(x_post)  # linearised at x⁺ for F* = F − J A
        if correlated:
            x, P = correlated_predict(x_post, P_post, fx=fx, F=F, Q=Q, C=C, R=R,
                                      A=A_post, residual=L - hx_post)
        else:
            x, P = correlated_predict(x_post, P_post, fx=fx, F=F, Q=Q)
        P_prev_post = P_post
        wind.append(x[:, 0])
        var.append(P[:, 0, 0])
        coef.append(x[:, 1])
        nis.append(diag.nis)
    return WindEstimate(torch.stack(wind, 1), torch.stack(var, 1), torch.stack(nis, 1),
                        torch.stack(coef, 1))


def run_lti_filter(
    z: torch.Tensor, model: LTIWindModel, *, adapter: UpdateAdapter | None = None
) -> WindEstimate:
    """Kalman filter of the LTI first-order Markov model on the raw measurement.

    Args:
        z: ``(N, T)`` measured wind of one axis per row.
        model: LTI model parameters (validated here).
        adapter: Optional robust/adaptive hook.

    Returns:
        :class:`WindEstimate` with ``(N, T)`` tensors (the filtered ``x⁺_k``).
    """
    where = "run_lti_filter"
    model.validate()
    z = _check_series(z, where)
    batch, steps = z.shape
    dtype = z.dtype
    F = torch.full((1, 1), model.phi, dtype=dtype)
    Q = torch.full((1, 1), model.process_var, dtype=dtype)
    R = torch.full((batch, 1, 1), model.meas_var, dtype=dtype)
    A = torch.ones(batch, 1, 1, dtype=dtype)
    x, P = model.initial(z[:, 0])
    P_prev_post = P
    wind, var, nis = [], [], []
    for k in range(steps):
        if k > 0:
            x, P = correlated_predict(x, P, fx=x * model.phi, F=F, Q=Q)
        residual = z[:, k : k + 1] - x
        P_eff, R_k = P, R
        if adapter is not None:
            P_eff, R_k = adapter.adjust(k, residual, A, P, R)
        x, P_post, diag = correlated_update(x, P_eff, residual=residual, A=A, R=R_k)
        if adapter is not None:
            adapter.observe(k, residual, A, P_eff, P_post, diag.gain, P_prev_post,
                            F.expand(batch, 1, 1))
        P = P_post
        P_prev_post = P_post
        wind.append(x[:, 0])
        var.append(P[:, 0, 0])
        nis.append(diag.nis)
    coef = torch.full((batch, steps), model.phi, dtype=dtype)
    return WindEstimate(torch.stack(wind, 1), torch.stack(var, 1), torch.stack(nis, 1), coef)


def estimate_wind(
    z: torch.Tensor,
    model: TVARWindModel | LTIWindModel,
    *,
    adapter: UpdateAdapter | None = None,
) -> WindEstimate:
    """Runs the filter of ``model`` on both axes of ``(N, T, 2)`` measured wind.

    The axes are filtered independently (folded into the batch as ``2N`` rows).

    Args:
        z: ``(N, T, 2)`` measured wind (east, north).
        model: :class:`TVARWindModel` (the paper's estimator) or :class:`LTIWindModel`.
        adapter: Optional robust/adaptive hook (sees the ``2N`` folded rows).

    Returns:
        :class:`WindEstimate` with ``(N, T, 2)`` tensors.
    """
    if not isinstance(z, torch.Tensor) or z.ndim != 3 or z.shape[-1] != 2:
        shape = tuple(z.shape) if isinstance(z, torch.Tensor) else type(z).__name__
        raise NeuralMapError(f"estimate_wind: 'z' must be (N, T, 2), got {shape}.")
    n, t, _ = z.shape
    rows = z.permute(0, 2, 1).reshape(2 * n, t)
    if isinstance(model, TVARWindModel):
        est = run_tvar_filter(rows, model, adapter=adapter)
    elif isinstance(model, LTIWindModel):
        est = run_lti_filter(rows, model, adapter=adapter)
    else:
        raise NeuralMapError(
            f"estimate_wind: 'model' must be a TVARWindModel or LTIWindModel, got "
            f"{type(model).__name__}."
        )

    def unfold(v: torch.Tensor) -> torch.Tensor:
        return v.reshape(n, 2, t).permute(0, 2, 1)

    return WindEstimate(unfold(est.wind), unfold(est.variance), unfold(est.nis),
                        unfold(est.coefficient))
