"""The 5-state TAN model (SEEDS 004): one source for the simulator, every method, the PCRB.

State ``δX = [δx, δy, δh, δv_x, δv_y]`` = INS minus truth.

* Dynamics: ``δX_{k+1} = Φ(Δt) δX_k + w_k`` with
  ``Φ = [[1,0,0,Δt,0],[0,1,0,0,Δt],[0,0,a,0,0],[0,0,0,1,0],[0,0,0,0,1]]`` (SEEDS 004, Φ)
  and ``w ~ N(0, Q(Δt))``. The altitude error is a random walk (``a = 1``, its variance
  growing as ``q_h Δt / T``) or a first-order Gauss-Markov process of time constant ``τ``
  (``a = exp(−Δt/τ)``, ``q_h(Δt) = σ_h² (1 − a²)`` with the stationary ``σ_h² = q_h /
  (1 − exp(−2T/τ))`` from the per-period ``q_h``: a barometric altitude bias); the position
  and velocity random walks scale as ``Δt / T`` (`TanModel.transition`,
  `TanModel.process_noise`).
  The *truth* drives it with ``w ~ N(0, Q_truth)`` (the simulated INS:
  ``diag(q_p², q_p², q_h², vrw²·T, vrw²·T)``) from ``δX_0 ~ N(mean, P0_truth)``; the
  *filter* assumes ``Q`` and ``P0`` (the scenario's tuning, consistent or not).
* Measurement: radar-altimeter clearance; the innovation is ``r = (ĥ − h_map(p̂)) − h_radar``
  with ``H = [−h_x, −h_y, 1, 0, 0]`` (SEEDS 004, H) and
  ``R = R_altimeter + fit_variance + linearisation variance`` (SEEDS 004: the fit error is
  white noise added to R). The PCRB uses the truth's altimeter variance alone.

`TanModel` holds these numbers once; the simulator (`neuralmap.lab.simulator`), every
navigation method (`neuralmap.tan.methods`), the PCRB (`neuralmap.lab.pcrb`) and the
reports read them from here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError

__all__ = ["N_STATES", "LatticeForm", "TanModel", "measurement_jacobian", "transition_matrix"]

#: Number of states of the TAN error model ``[δx, δy, δh, δv_x, δv_y]``.
N_STATES = 5


def transition_matrix(dt: float, *, altitude_decay: float = 1.0,
                      dtype: torch.dtype = torch.float64,
                      device: str | torch.device = "cpu") -> torch.Tensor:
    """The error-state transition matrix Φ over ``Δt`` (SEEDS 004).

    ``Φ = [[1,0,0,Δt,0],[0,1,0,0,Δt],[0,0,a,0,0],[0,0,0,1,0],[0,0,0,0,1]]`` with ``a`` the
    altitude error's decay over ``Δt`` (1 = random walk).

    Args:
        dt: Interval Δt, s (> 0).
        altitude_decay: ``a``, in ``(0, 1]``.
        dtype: Tensor dtype.
        device: Tensor device.

    Returns:
        ``(5, 5)`` tensor.
    """
    if not dt > 0.0:
        raise NeuralMapError(f"transition_matrix: dt must be > 0 seconds, got {dt!r}.")
    phi = torch.eye(N_STATES, dtype=dtype, device=device)
    phi[0, 3] = dt
    phi[1, 4] = dt
    phi[2, 2] = altitude_decay
    return phi


def measurement_jacobian(slope: torch.Tensor) -> torch.Tensor:
    """Altimeter measurement Jacobian ``H = [−h_x, −h_y, 1, 0, 0]`` (SEEDS 004).

    Args:
        slope: ``(N, 2)`` terrain slope ``(∂h/∂x, ∂h/∂y)`` at the estimate.

    Returns:
        ``(N, 5)`` rows of H, dtype and device of ``slope``.
    """
    if slope.ndim != 2 or slope.shape[1] != 2:
        raise NeuralMapError(
            f"measurement_jacobian: slope must have shape (N, 2), got {tuple(slope.shape)}."
        )
    n = slope.shape[0]
    ones = torch.ones(n, 1, dtype=slope.dtype, device=slope.device)
    zeros = torch.zeros(n, 2, dtype=slope.dtype, device=slope.device)
    return torch.cat([-slope, ones, zeros], dim=1)


@dataclass(frozen=True)
class LatticeForm:
    """The TAN model split for a point-mass lattice (Rao-Blackwellised form).

    ``s = δp`` on the lattice, ``z = [δh, δv_x, δv_y]`` a Kalman part per cell::

        s⁺ = s + E z + w_s,   z⁺ = F z + w_z,   y = g(s) + c·z + e

    Attributes:
        E: ``(2, 3)`` ``Δt [[0, 1, 0], [0, 0, 1]]``.
        F: ``(3, 3)`` ``diag(a, 1, 1)``.
        c: ``(3,)`` ``[1, 0, 0]``.
        Q_s: ``(2, 2)`` position block of ``Q(Δt)``.
        Q_z: ``(3, 3)`` altitude / velocity block of ``Q(Δt)``.
    """

    E: torch.Tensor
    F: torch.Tensor
    c: torch.Tensor
    Q_s: torch.Tensor
    Q_z: torch.Tensor


def _five(values: Any, name: str, *, signed: bool = False) -> tuple[float, ...]:
    """Five finite numbers (variances ≥ 0 unless ``signed``), or a clear error."""
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError) as exc:
        raise NeuralMapError(
            f"TAN model: scenario field '{name}' must hold 5 numbers (x, y, h, v_x, v_y), "
            f"got {values!r}."
        ) from exc
    if len(out) != N_STATES or not all(math.isfinite(v) for v in out) or (
        not signed and any(v < 0 for v in out)
    ):
        what = "finite numbers" if signed else "finite variances >= 0"
        raise NeuralMapError(
            f"TAN model: scenario field '{name}' must hold 5 {what} (x, y, h, v_x, v_y), "
            f"got {list(out)}."
        )
    return out


@dataclass(frozen=True)
class TanModel:
    """The TAN dynamics and measurement model of one scenario.

    Attributes:
        dt: Period T, s.
        P0: Filter's initial covariance diagonal ``(5,)``.
        Q: Filter's process-noise diagonal per step ``(5,)``.
        R_altimeter: Altimeter variance the filter assumes, m².
        fit_variance: Map error variance every method adds to R, m².
        truth_P0: Variances of the true initial error ``(5,)`` (0 = a fixed error).
        truth_mean: Mean of the true initial error ``(5,)``.
        truth_Q: Per-step variances of the truth's driving noise ``(5,)``.
        truth_R: The true altimeter noise variance, m² (outliers excluded).
        altitude_time_constant_s: Time constant τ of the altitude error, s: None = a
            random walk (module docstring); a number = first-order Gauss-Markov, the
            truth's and the filter's.

    A model for a filter only (the `Navigator`'s) leaves the truth fields at their
    defaults: the filter's own numbers.
    """

    dt: float
    P0: tuple[float, ...]
    Q: tuple[float, ...]
    R_altimeter: float
    fit_variance: float = 0.0
    truth_P0: tuple[float, ...] = field(default=())
    truth_mean: tuple[float, ...] = field(default=(0.0,) * N_STATES)
    truth_Q: tuple[float, ...] = field(default=())
    truth_R: float = math.nan
    altitude_time_constant_s: float | None = None

    def __post_init__(self) -> None:
        if not self.truth_P0:
            object.__setattr__(self, "truth_P0", tuple(self.P0))
        if not self.truth_Q:
            object.__setattr__(self, "truth_Q", tuple(self.Q))
        if math.isnan(self.truth_R):
            object.__setattr__(self, "truth_R", self.R_altimeter + self.fit_variance)
        tau = self.altitude_time_constant_s
        if tau is not None and not (isinstance(tau, (int, float)) and math.isfinite(tau)
                                    and tau > 0):
            raise NeuralMapError(f"TAN model: altitude_time_constant_s must be a number > 0 "
                                 f"(s) or null for a random walk, got {tau!r}.")

    @classmethod
    def from_scenario(cls, scenario: Any) -> TanModel:
        """The model of a `Scenario` (validated first).

        Duck-typed objects work too: a missing truth description falls back to the
        filter's (``init_error_sigma()`` to ``sqrt(P0_diag)``, ``truth_process_noise()``
        to ``Q_diag``, ``altimeter_sigma_m²`` to ``R_m2 + fit_variance_m2``).

        Raises:
            NeuralMapError: A missing or invalid field (name, expected, got).
        """
        if callable(getattr(scenario, "validate", None)):
            scenario.validate()
        dt = getattr(scenario, "dt", None)
        if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not dt > 0:
            raise NeuralMapError(f"TAN model: scenario.dt must be a number > 0, got {dt!r}.")
        P0 = _five(getattr(scenario, "P0_diag", None), "P0_diag")
        Q = _five(getattr(scenario, "Q_diag", None), "Q_diag")
        R = float(getattr(scenario, "R_m2", float("nan")))
        fit = float(getattr(scenario, "fit_variance_m2", 0.0) or 0.0)
        sigma = getattr(scenario, "init_error_sigma", None)
        truth_P0 = (_five([float(v) ** 2 for v in sigma()], "init_error_sigma()")
                    if callable(sigma) else P0)
        noise = getattr(scenario, "truth_process_noise", None)
        truth_Q = _five(noise(), "truth_process_noise()") if callable(noise) else Q
        mean = getattr(scenario, "init_error_mean", None)
        altimeter = getattr(scenario, "altimeter_sigma_m", None)
        tau = getattr(scenario, "altitude_time_constant_s", None)
        return cls(
            dt=float(dt), P0=P0, Q=Q, R_altimeter=R, fit_variance=fit, truth_P0=truth_P0,
            truth_mean=(0.0,) * N_STATES if mean is None else _five(mean, "init_error_mean",
                                                                    signed=True),
            truth_Q=truth_Q,
            truth_R=R + fit if altimeter is None else float(altimeter) ** 2,
            altitude_time_constant_s=None if tau is None else float(tau),
        )

    # ------------------------------------------------------------------ dynamics
    def altitude_decay(self, dt: float | None = None) -> float:
        """``a = exp(−Δt/τ)`` of the altitude error over ``dt`` (default T); 1 for a random
        walk."""
        tau = self.altitude_time_constant_s
        return 1.0 if tau is None else math.exp(-float(self.dt if dt is None else dt) / tau)

    def transition(self, dt: float | None = None, *, dtype: torch.dtype = torch.float64,
                   device: str | torch.device = "cpu") -> torch.Tensor:
        """``(5, 5)`` Φ over ``dt`` (default the period T; SEEDS 004)."""
        dt = self.dt if dt is None else float(dt)
        return transition_matrix(dt, altitude_decay=self.altitude_decay(dt), dtype=dtype,
                                 device=device)

    def process_noise(self, dt: float | None = None, *, dtype: torch.dtype = torch.float64,
                      device: str | torch.device = "cpu") -> torch.Tensor:
        """``(5, 5)`` the filter's ``Q(Δt)`` (module docstring): ``Q Δt / T`` for the random
        walks, ``σ_h² (1 − a²)`` for a Gauss-Markov altitude error."""
        scale = 1.0 if dt is None else float(dt) / self.dt
        q = [v * scale for v in self.Q] if scale != 1.0 else list(self.Q)
        tau = self.altitude_time_constant_s
        if tau is not None and scale != 1.0:
            stationary = self.Q[2] / (1.0 - self.altitude_decay() ** 2)
            q[2] = stationary * (1.0 - self.altitude_decay(dt) ** 2)  # σ_h² (1 − a²)
        return torch.diag(torch.tensor(q, dtype=dtype, device=device))

    def lattice_form(self, dt: float | None = None, *, dtype: torch.dtype = torch.float64,
                     device: str | torch.device = "cpu") -> LatticeForm:
        """The model over ``dt`` split for a point-mass lattice (`LatticeForm`)."""
        dt = self.dt if dt is None else float(dt)
        kw = {"dtype": dtype, "device": device}
        Q = self.process_noise(dt, **kw)
        return LatticeForm(
            E=torch.tensor([[0.0, dt, 0.0], [0.0, 0.0, dt]], **kw),
            F=torch.diag(torch.tensor([self.altitude_decay(dt), 1.0, 1.0], **kw)),
            c=torch.tensor([1.0, 0.0, 0.0], **kw), Q_s=Q[:2, :2], Q_z=Q[2:, 2:])

    def filter_prior(self, *, dtype: torch.dtype = torch.float64,
                     device: str | torch.device = "cpu") -> torch.Tensor:
        """``(5, 5)`` the filter's ``P0``."""
        return torch.diag(torch.tensor(self.P0, dtype=dtype, device=device))

    def filter_process_noise(self, *, dtype: torch.dtype = torch.float64,
                             device: str | torch.device = "cpu") -> torch.Tensor:
        """``(5, 5)`` the filter's ``Q`` per period T."""
        return self.process_noise(dtype=dtype, device=device)

    def truth_process_noise(self, *, dtype: torch.dtype = torch.float64,
                            device: str | torch.device = "cpu") -> torch.Tensor:
        """``(5, 5)`` the truth's ``Q`` (driving noise of the simulated INS error)."""
        return torch.diag(torch.tensor(self.truth_Q, dtype=dtype, device=device))

    def bound_prior(self, *, dtype: torch.dtype = torch.float64,
                    device: str | torch.device = "cpu") -> torch.Tensor:
        """``(5, 5)`` prior of the PCRB: the truth's spread; the filter's ``P0`` where the
        truth's initial error is fixed (a zero spread would make the bound 0 at t = 0 while
        the filter does not know that error)."""
        values = [t if t > 0 else f for t, f in zip(self.truth_P0, self.P0, strict=True)]
        return torch.diag(torch.tensor(values, dtype=dtype, device=device))

    def propagate_truth(self, err0: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """True error sequences ``δX_{k+1} = Φ δX_k + w_k``.

        With Φ above: ``δv_k = δv_0 + Σ_{j<k} w_v,j``, ``δp_k = δp_0 + T Σ_{j<k} δv_j +
        Σ_{j<k} w_p,j`` (cumulative sums); ``δh_k = δh_0 + Σ_{j<k} w_h,j`` for a random walk,
        ``δh_{k+1} = a δh_k + w_h,k`` (a recursion over K, batched over N) for a
        Gauss-Markov altitude error.

        Args:
            err0: ``(N, 5)`` initial errors.
            noise: ``(N, K, 5)`` driving noise ``w_0 … w_{K−1}``.

        Returns:
            ``(N, K + 1, 5)`` errors ``δX_0 … δX_K``.
        """
        n = err0.shape[0]
        zeros = torch.zeros(n, 1, N_STATES, dtype=err0.dtype, device=err0.device)
        w_sum = torch.cat([zeros, torch.cumsum(noise, dim=1)], dim=1)  # Σ_{j<k} w_j
        dv = err0[:, None, 3:] + w_sum[..., 3:]
        dv_sum = torch.cat([zeros[..., 3:], torch.cumsum(dv[:, :-1], dim=1)], dim=1)
        dp = err0[:, None, :2] + self.dt * dv_sum + w_sum[..., :2]
        if self.altitude_time_constant_s is None:
            dh = err0[:, None, 2:3] + w_sum[..., 2:3]
        else:
            a = self.altitude_decay()
            h = [err0[:, 2]]
            for j in range(noise.shape[1]):
                h.append(a * h[-1] + noise[:, j, 2])  # δh_{k+1} = a δh_k + w_h,k
            dh = torch.stack(h, 1)[..., None]
        return torch.cat([dp, dh, dv], dim=-1)

    # ------------------------------------------------------------------ measurement
    @staticmethod
    def jacobian(slope: torch.Tensor) -> torch.Tensor:
        """``(N, 5)`` rows ``H = [−h_x, −h_y, 1, 0, 0]`` from ``(N, 2)`` slopes (SEEDS 004)."""
        return measurement_jacobian(slope)

    @property
    def base_R(self) -> float:
        """The measurement variance every method uses before its linearisation variance."""
        return self.R_altimeter + self.fit_variance

    def measurement_noise(self, linearisation_variance: torch.Tensor | float = 0.0
                          ) -> torch.Tensor | float:
        """``R = R_altimeter + fit_variance + linearisation variance`` (SEEDS 004)."""
        return linearisation_variance + self.base_R
