"""Batched wind filters: the differenced TVAR-model EKF and the LTI-model Kalman filter.

`run_tvar_filter` (SEEDS 002, the paper's estimator): the first-order time-varying
AR model of `.tvar_model` with the differenced measurement ``L_k = Z_{k+1} − Z_k``,
filtered by the correlated-noise EKF of `.correlated`: for ``k = 0 … T−2``

    update with L_k at x⁻_k   (residual L_k − h(x⁻_k), A_k = H F_k − H),
    decorrelated predict      (x⁻_{k+1} = f(x⁺_k) + J (L_k − h(x⁺_k)), J = C R_e⁻¹),

so ``x⁻_{k+1}`` is the estimate of the wind at ``k+1`` given ``Z_0 … Z_{k+1}`` (the
differenced measurement is one sample late by construction). The start is
``x_0 = [Z_0, a0, 0]``.

`run_lti_filter`: the usual choice, a scalar Kalman filter of the first-order
Markov model on the raw measurement (white-noise assumption).

Both take scalar series ``(N, T)`` (one wind axis per row; `estimate_wind` folds
the two axes into the batch) and an optional
`FilterPolicy` (robust / adaptive filtering: it may
reweight ``R``, scale ``P⁻`` and adapt ``Q`` at each step; for the TVAR filter it sees the
decorrelated system ``F*``, ``Q*``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters import Adaptation, BatchedEKF, FilterPolicy, Posterior, UpdateContext
from neuralmap.wind.correlated import CorrelatedNoiseEKF
from neuralmap.wind.lti_model import LTIWindModel
from neuralmap.wind.tvar_model import TVARWindModel

__all__ = ["WindEstimate", "run_tvar_filter", "run_lti_filter", "estimate_wind"]


class _NoiseRecorder(FilterPolicy):
    """Delegates to a policy and records the ``R`` and kept components its update used."""

    def __init__(self, inner: FilterPolicy) -> None:
        self.inner = inner
        self.iterations = inner.iterations
        self.name = inner.name
        self.R: torch.Tensor | None = None
        self.keep: torch.Tensor | None = None

    def reset(self) -> None:
        self.inner.reset()

    def adapt(self, context: UpdateContext) -> Adaptation:
        return self.inner.adapt(context)

    def refine(self, context: UpdateContext, adaptation: Adaptation,
               posterior: Posterior) -> Adaptation | None:
        return self.inner.refine(context, adaptation, posterior)

    def commit(self, context: UpdateContext, adaptation: Adaptation, posterior: Posterior,
               applied: torch.Tensor) -> None:
        self.R = posterior.R
        self.keep = None if adaptation.keep is None else adaptation.keep.to(torch.bool).any(-1)
        self.inner.commit(context, adaptation, posterior, applied)

    def process_noise(self, *, F: torch.Tensor, Q: torch.Tensor,
                      P: torch.Tensor) -> torch.Tensor | None:
        return self.inner.process_noise(F=F, Q=Q, P=P)


@dataclass
class WindEstimate:
    """Filter output aligned with the measurement samples, batch first.

    Attributes:
        wind: ``(N, T)`` or ``(N, T, 2)`` wind estimate at every sample.
        variance: Same shape, estimated variance of the wind component.
        nis: Same shape, NIS of the update that produced the estimate (NaN where none).
        coefficient: Same shape, AR coefficient estimate (TVAR) or the fixed φ (LTI).
        healthy: ``(N,)`` bool, False where the filter flagged the run (both axes for
            ``(N, T, 2)``) as numerically broken and froze it.
    """

    wind: torch.Tensor
    variance: torch.Tensor
    nis: torch.Tensor
    coefficient: torch.Tensor
    healthy: torch.Tensor


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
    policy: FilterPolicy | None = None,
    correlated: bool = True,
) -> WindEstimate:
    """The paper's estimator on ``(N, T)`` measured-wind series (see module docstring).

    Args:
        z: ``(N, T)`` measured wind of one axis per row.
        model: TVAR model parameters (validated here).
        policy: Optional robust/adaptive filter policy (reset here).
        correlated: Handle the cross-covariance of the differenced measurement noise and
            the process noise (default). False drops it (a plain EKF predict; for
            comparison only: the filter is then inconsistent when ``direct_noise``).

    Returns:
        `WindEstimate` with ``(N, T)`` tensors.
    """
    where = "run_tvar_filter"
    model.validate()
    z = _check_series(z, where)
    batch, steps = z.shape
    dtype = z.dtype
    Q, R, C = (m.to(z.device) for m in model.noise_covariances(dtype=dtype))
    # the rewrite needs Q − C R⁻¹ Cᵀ ≥ 0, i.e. R ≥ g² Σ_w (the correlated part of R_e):
    # an adaptive R̂ below it is floored for the decorrelation only
    r_floor = (1.0 + 1e-9) * (R - model.meas_var)
    recorder = None if policy is None else _NoiseRecorder(policy)
    if recorder is not None:
        recorder.reset()
    x0, P0 = model.initial(z[:, 0])
    filt = CorrelatedNoiseEKF(x0, P0)
    wind = [x0[:, 0]]
    var = [P0[:, 0, 0]]
    coef = [x0[:, 1]]
    nis = [torch.full((batch,), float("nan"), dtype=dtype, device=z.device)]
    for k in range(steps - 1):
        L = (z[:, k + 1] - z[:, k]).unsqueeze(-1)
        hx, A = model.measurement(filt.x)
        diag = filt.update(L - hx, A, R, policy=recorder)
        x_post = filt.x
        fx, F = model.transition(x_post)
        if correlated:
            R_used, keep = R, None
            if recorder is not None and recorder.R is not None:
                R_used, keep = torch.maximum(recorder.R, r_floor), recorder.keep
            hx_post, A_post = model.measurement(x_post)  # linearised at x⁺: F* = F − J A
            filt.predict(fx=fx, F=F, Q=Q, C=C, R=R_used, A=A_post, residual=L - hx_post,
                         keep=keep, policy=recorder)
        else:
            filt.predict(fx=fx, F=F, Q=Q, policy=recorder)
        wind.append(filt.x[:, 0])
        var.append(filt.P[:, 0, 0])
        coef.append(filt.x[:, 1])
        nis.append(diag.nis)
    return WindEstimate(torch.stack(wind, 1), torch.stack(var, 1), torch.stack(nis, 1),
                        torch.stack(coef, 1), filt.healthy.clone())


def run_lti_filter(
    z: torch.Tensor, model: LTIWindModel, *, policy: FilterPolicy | None = None
) -> WindEstimate:
    """Kalman filter of the LTI first-order Markov model on the raw measurement.

    Args:
        z: ``(N, T)`` measured wind of one axis per row.
        model: LTI model parameters (validated here).
        policy: Optional robust/adaptive filter policy (reset here).

    Returns:
        `WindEstimate` with ``(N, T)`` tensors (the filtered ``x⁺_k``).
    """
    where = "run_lti_filter"
    model.validate()
    z = _check_series(z, where)
    batch, steps = z.shape
    dtype = z.dtype
    F = torch.full((1, 1), model.phi, dtype=dtype, device=z.device)
    Q = torch.full((1, 1), model.process_var, dtype=dtype, device=z.device)
    H = torch.ones(1, 1, dtype=dtype, device=z.device)
    if policy is not None:
        policy.reset()
    x0, P0 = model.initial(z[:, 0])
    ekf = BatchedEKF(x0, P0)
    wind, var, nis = [], [], []
    for k in range(steps):
        if k > 0:
            ekf.predict(F, Q, policy=policy)
        diag = ekf.update(z[:, k : k + 1] - ekf.x, H, model.meas_var, policy=policy)
        wind.append(ekf.x[:, 0])
        var.append(ekf.P[:, 0, 0])
        nis.append(diag.nis)
    coef = torch.full((batch, steps), model.phi, dtype=dtype, device=z.device)
    return WindEstimate(torch.stack(wind, 1), torch.stack(var, 1), torch.stack(nis, 1), coef,
                        ekf.healthy.clone())


def estimate_wind(
    z: torch.Tensor,
    model: TVARWindModel | LTIWindModel,
    *,
    policy: FilterPolicy | None = None,
    correlated: bool = True,
) -> WindEstimate:
    """Runs the filter of ``model`` on both axes of ``(N, T, 2)`` measured wind.

    The axes are filtered independently (folded into the batch as ``2N`` rows).

    Args:
        z: ``(N, T, 2)`` measured wind (east, north).
        model: `TVARWindModel` (the paper's estimator) or `LTIWindModel`.
        policy: Optional robust/adaptive policy (sees the ``2N`` folded rows).
        correlated: TVAR only; see `run_tvar_filter`.

    Returns:
        `WindEstimate` with ``(N, T, 2)`` tensors.
    """
    if not isinstance(z, torch.Tensor) or z.ndim != 3 or z.shape[-1] != 2:
        shape = tuple(z.shape) if isinstance(z, torch.Tensor) else type(z).__name__
        raise NeuralMapError(f"estimate_wind: 'z' must be (N, T, 2), got {shape}.")
    n, t, _ = z.shape
    rows = z.permute(0, 2, 1).reshape(2 * n, t)
    if isinstance(model, TVARWindModel):
        est = run_tvar_filter(rows, model, policy=policy, correlated=correlated)
    elif isinstance(model, LTIWindModel):
        est = run_lti_filter(rows, model, policy=policy)
    else:
        raise NeuralMapError(
            f"estimate_wind: 'model' must be a TVARWindModel or LTIWindModel, got "
            f"{type(model).__name__}."
        )

    def unfold(v: torch.Tensor) -> torch.Tensor:
        return v.reshape(n, 2, t).permute(0, 2, 1)

    return WindEstimate(unfold(est.wind), unfold(est.variance), unfold(est.nis),
                        unfold(est.coefficient), est.healthy.reshape(n, 2).all(-1))
