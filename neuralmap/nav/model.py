"""The 5-state TAN model (SEEDS 004): one source for the simulator, filter, PCRB and reports.

State ``δX = [δx, δy, δh, δv_x, δv_y]`` = INS minus truth.

* Dynamics: ``δX_{k+1} = Φ δX_k + w_k`` with
  ``Φ = [[1,0,0,T,0],[0,1,0,0,T],[0,0,1,0,0],[0,0,0,1,0],[0,0,0,0,1]]`` (SEEDS 004, Φ).
  The *truth* drives it with ``w ~ N(0, Q_truth)`` (the simulated INS:
  ``diag(q_p², q_p², q_h², vrw²·T, vrw²·T)``) from ``δX_0 ~ N(mean, P0_truth)``; the
  *filter* assumes ``Q`` and ``P0`` (the scenario's tuning, consistent or not).
* Measurement: radar-altimeter clearance; the innovation is ``r = (ĥ − h_map(p̂)) − h_radar``
  with ``H = [−h_x, −h_y, 1, 0, 0]`` (SEEDS 004, H) and
  ``R = R_altimeter + fit_variance + linearisation variance`` (SEEDS 004: the fit error is
  white noise added to R). The PCRB uses the truth's altimeter variance alone.

`TanModel` holds these numbers once; `neuralmap.nav.simulator.simulate`,
`neuralmap.nav.monte_carlo.run_filter`, `neuralmap.nav.pcrb.pcrb` and the
reports all read them from here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.nav.tan import N_STATES, measurement_jacobian, transition_matrix

__all__ = ["N_STATES", "TanModel"]


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
    """

    dt: float
    P0: tuple[float, ...]
    Q: tuple[float, ...]
    R_altimeter: float
    fit_variance: float
    truth_P0: tuple[float, ...]
    truth_mean: tuple[float, ...]
    truth_Q: tuple[float, ...]
    truth_R: float

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
        return cls(
            dt=float(dt), P0=P0, Q=Q, R_altimeter=R, fit_variance=fit, truth_P0=truth_P0,
            truth_mean=(0.0,) * N_STATES if mean is None else _five(mean, "init_error_mean",
                                                                    signed=True),
            truth_Q=truth_Q,
            truth_R=R + fit if altimeter is None else float(altimeter) ** 2,
        )

    # ------------------------------------------------------------------ dynamics
    def transition(self, *, dtype: torch.dtype = torch.float64,
                   device: str | torch.device = "cpu") -> torch.Tensor:
        """``(5, 5)`` Φ (SEEDS 004)."""
        return transition_matrix(self.dt, dtype=dtype, device=device)

    def filter_prior(self, *, dtype: torch.dtype = torch.float64,
                     device: str | torch.device = "cpu") -> torch.Tensor:
        """``(5, 5)`` the filter's ``P0``."""
        return torch.diag(torch.tensor(self.P0, dtype=dtype, device=device))

    def filter_process_noise(self, *, dtype: torch.dtype = torch.float64,
                             device: str | torch.device = "cpu") -> torch.Tensor:
        """``(5, 5)`` the filter's ``Q``."""
        return torch.diag(torch.tensor(self.Q, dtype=dtype, device=device))

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
        """True error sequences ``δX_{k+1} = Φ δX_k + w_k`` in closed form (no time loop).

        With Φ above: ``δv_k = δv_0 + Σ_{j<k} w_v,j``, ``δp_k = δp_0 + T Σ_{j<k} δv_j +
        Σ_{j<k} w_p,j``, ``δh_k = δh_0 + Σ_{j<k} w_h,j`` (cumulative sums).

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
        dh = err0[:, None, 2:3] + w_sum[..., 2:3]
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
