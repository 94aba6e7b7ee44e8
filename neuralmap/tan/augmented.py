"""TAN error models augmented with an AR map-error state (SEEDS 000, section 4).

The DEM-making error (and the linearisation error of a fixed fitting region) identified as
AR(1) or AR(2) is appended to the 5-state TAN error state
``δX = [δx, δy, δh, δv_x, δv_y]``:

* 6 states (AR(1)): ``δX = [δx, δy, δh, δv_x, δv_y, e_r]``, ``Φ_66 = a_1``;
* 7 states (AR(2)): ``δX = [… , e_r, e_c]`` with rows ``[… a_1 a_2]`` and ``[… 1 0]``
  (``e_c`` is ``e_r`` one step earlier);

and ``H = [−h_x, −h_y, 1, 0, 0, −1(, 0)]``: the map reads ``h_d = h_t + e_r``, so the
residual ``(ĥ − h_map(p̂)) − h_radar`` carries ``−e_r``. Only ``e_r`` is driven by noise
(``Q_66 = σ_e²``, the identified fit residual). General AR(p) uses the same companion form.

The PCRB of the augmented model follows from the 5-state information
(`augment_information`).

"Switching the map-error state off" (``observed=False``) zeroes its column of H: the state is
then decoupled and the first five states follow the 5-state filter exactly.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch

from neuralmap.errors.arma import check_stationary
from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.stats import symmetrize
from neuralmap.tan.model import N_STATES, TanModel, transition_matrix

#: Paper tuning (SEEDS 000): initial standard deviations of the 5 navigation states
#: (m, m, m, m/s, m/s) and of each map-error state (m).
PAPER_P0_STD = (400.0, 400.0, 400.0, 40.0, 40.0)
PAPER_P0_MAP_STD = 40.0
#: Paper tuning: process-noise standard deviations of the navigation states.
PAPER_Q_STD = (5.0, 5.0, 5.0, 0.5, 0.5)
#: Paper tuning: altimeter measurement standard deviation, m.
PAPER_R_STD = 20.0


def _ar(ar: Sequence[float], where: str) -> list[float]:
    coef = [float(v) for v in check_stationary(ar, where=where)]
    if not coef:
        raise NeuralMapError(
            f"{where}: give at least one AR coefficient (a_1 for the 6-state model, a_1, a_2 "
            "for the 7-state model); the 5-state model has no map-error state."
        )
    return coef


def augmented_transition_matrix(
    dt: float,
    ar: Sequence[float],
    *,
    dtype: torch.dtype = torch.float64,
    device: str | torch.device = "cpu",
) -> torch.Tensor:
    """Φ of the augmented model: the 5-state Φ and the AR companion block (SEEDS 000).

    Args:
        dt: Filter period T, s.
        ar: Stationary AR coefficients ``(a_1, …, a_p)`` of the map error.
        dtype: Tensor dtype.
        device: Tensor device.

    Returns:
        ``(5 + p, 5 + p)`` tensor.
    """
    coef = _ar(ar, "augmented_transition_matrix")
    p = len(coef)
    phi = torch.zeros(N_STATES + p, N_STATES + p, dtype=dtype, device=device)
    phi[:N_STATES, :N_STATES] = transition_matrix(dt, dtype=dtype, device=device)
    phi[N_STATES, N_STATES:] = torch.tensor(coef, dtype=dtype, device=device)
    for k in range(1, p):
        phi[N_STATES + k, N_STATES + k - 1] = 1.0
    return phi


def augmented_process_noise(
    q_nav: torch.Tensor | Sequence[float],
    sigma_e: float,
    p: int,
    *,
    dtype: torch.dtype = torch.float64,
    device: str | torch.device = "cpu",
) -> torch.Tensor:
    """Q of the augmented model: ``blockdiag(Q_nav, σ_e², 0, …)``.

    Args:
        q_nav: ``(5, 5)`` navigation process noise, or 5 standard deviations (paper:
            ``Q½ = diag(5, 5, 5, 0.5, 0.5)``).
        sigma_e: Standard deviation of the AR innovation ``w_{e_r}``, m (the square root of
            the identified fit residual).
        p: AR order (number of map-error states).
        dtype: Tensor dtype.
        device: Tensor device.

    Returns:
        ``(5 + p, 5 + p)`` tensor.
    """
    q = torch.as_tensor(q_nav, dtype=dtype, device=device)
    if q.shape == (N_STATES,):
        q = torch.diag(q**2)
    if q.shape != (N_STATES, N_STATES) or p < 1:
        raise NeuralMapError(
            f"augmented_process_noise: q_nav must be (5, 5) or 5 standard deviations and p ≥ 1, "
            f"got shape {tuple(q.shape)} and p={p}."
        )
    if not (sigma_e >= 0.0 and torch.isfinite(torch.tensor(sigma_e))):
        raise NeuralMapError(
            f"augmented_process_noise: sigma_e must be finite and ≥ 0 m, got {sigma_e!r}."
        )
    out = torch.zeros(N_STATES + p, N_STATES + p, dtype=dtype, device=device)
    out[:N_STATES, :N_STATES] = q
    out[N_STATES, N_STATES] = float(sigma_e) ** 2
    return out


def augmented_measurement_jacobian(
    slope: torch.Tensor, p: int, *, observed: bool = True
) -> torch.Tensor:
    """``H = [−h_x, −h_y, 1, 0, 0, −1, 0, …]`` of the augmented model (SEEDS 000).

    Args:
        slope: ``(N, 2)`` terrain slope at the estimate.
        p: AR order (number of map-error states).
        observed: False zeroes the map-error column (the state switched off).

    Returns:
        ``(N, 5 + p)`` rows of H, dtype and device of ``slope``.
    """
    if slope.ndim != 2 or slope.shape[1] != 2 or p < 1:
        raise NeuralMapError(
            f"augmented_measurement_jacobian: slope must be (N, 2) and p ≥ 1, got "
            f"{tuple(slope.shape)} and p={p}."
        )
    n = slope.shape[0]
    ones = torch.ones(n, 1, dtype=slope.dtype, device=slope.device)
    zeros = torch.zeros(n, 2, dtype=slope.dtype, device=slope.device)
    map_cols = torch.zeros(n, p, dtype=slope.dtype, device=slope.device)
    if observed:
        map_cols[:, 0] = -1.0
    return torch.cat([-slope, ones, zeros, map_cols], dim=1)


def stationary_map_covariance(
    ar: Sequence[float], sigma_e: float, *, dtype: torch.dtype = torch.float64
) -> torch.Tensor:
    """Stationary covariance of the map-error states (the consistent initial covariance).

    Solves ``P = A P Aᵀ + Q_e`` for the companion block ``A`` and ``Q_e = diag(σ_e², 0, …)``;
    for AR(1) ``σ_e² / (1 − a_1²)``, for AR(2) the Toeplitz matrix of ``γ_0, γ_1``.

    Args:
        ar: Stationary AR coefficients.
        sigma_e: AR innovation standard deviation, m.
        dtype: Tensor dtype.

    Returns:
        ``(p, p)`` tensor.
    """
    coef = _ar(ar, "stationary_map_covariance")
    p = len(coef)
    a = torch.zeros(p, p, dtype=torch.float64)
    a[0] = torch.tensor(coef, dtype=torch.float64)
    for k in range(1, p):
        a[k, k - 1] = 1.0
    q = torch.zeros(p, p, dtype=torch.float64)
    q[0, 0] = float(sigma_e) ** 2
    lhs = torch.eye(p * p, dtype=torch.float64) - torch.kron(a, a)
    vec = torch.linalg.solve(lhs, q.reshape(-1))
    out = vec.reshape(p, p)
    return (symmetrize(out)).to(dtype)


def augmented_initial_covariance(
    p0_nav: torch.Tensor | Sequence[float],
    p0_map: torch.Tensor | Sequence[float] | float,
    p: int,
    *,
    dtype: torch.dtype = torch.float64,
    device: str | torch.device = "cpu",
) -> torch.Tensor:
    """``P_0 = blockdiag(P0_nav, P0_map)`` of the augmented model.

    Args:
        p0_nav: ``(5, 5)`` covariance, or 5 standard deviations (paper:
            ``diag(400, 400, 400, 40, 40)``).
        p0_map: ``(p, p)`` covariance (e.g. `stationary_map_covariance`), ``p``
            standard deviations, or one standard deviation for every map state (paper: 40 m).
        p: AR order.
        dtype: Tensor dtype.
        device: Tensor device.

    Returns:
        ``(5 + p, 5 + p)`` tensor.
    """
    nav = torch.as_tensor(p0_nav, dtype=dtype, device=device)
    if nav.shape == (N_STATES,):
        nav = torch.diag(nav**2)
    block = torch.as_tensor(p0_map, dtype=dtype, device=device)
    if block.ndim == 0:
        block = block.expand(p)
    if block.shape == (p,):
        block = torch.diag(block**2)
    if nav.shape != (N_STATES, N_STATES) or block.shape != (p, p):
        raise NeuralMapError(
            "augmented_initial_covariance: p0_nav must be (5, 5) or 5 standard deviations and "
            f"p0_map (p, p), p standard deviations or one number; got {tuple(nav.shape)} and "
            f"{tuple(block.shape)} for p={p}."
        )
    out = torch.zeros(N_STATES + p, N_STATES + p, dtype=dtype, device=device)
    out[:N_STATES, :N_STATES] = nav
    out[N_STATES:, N_STATES:] = block
    return out


def paper_augmented_tuning(
    ar: Sequence[float], sigma_e: float, *, dt: float = 1.0, dtype: torch.dtype = torch.float64
) -> dict[str, torch.Tensor | float]:
    """The paper's tuning of the augmented filter (SEEDS 000, section 4).

    ``P0½ = diag(400, 400, 400, 40, 40, 40(, 40))``, ``Q½ = diag(5, 5, 5, 0.5, 0.5, σ_e(, 0))``,
    ``R½ = 20 m``, ``T = 1 s``.

    Returns:
        ``{"F", "Q", "P0"}`` tensors and ``"R"`` (variance, m²).
    """
    coef = _ar(ar, "paper_augmented_tuning")
    p = len(coef)
    return {
        "F": augmented_transition_matrix(dt, coef, dtype=dtype),
        "Q": augmented_process_noise(PAPER_Q_STD, sigma_e, p, dtype=dtype),
        "P0": augmented_initial_covariance(PAPER_P0_STD, PAPER_P0_MAP_STD, p, dtype=dtype),
        "R": PAPER_R_STD**2,
    }


def augment_information(info: torch.Tensor, p: int) -> torch.Tensor:
    """Measurement information ``E[Hᵀ R⁻¹ H]`` of the augmented model from the 5-state one.

    With ``H = [−h_x, −h_y, 1, 0, 0, −1, 0, …]`` every new entry is already in the 5-state
    information, because its δh entry is 1: ``E[H_i · (−1)] / R = −info[i, 2]`` and
    ``E[(−1)²] / R = info[2, 2]``. So the augmented PCRB is
    ``pcrb_recursion(P0_aug, Φ_aug, Q_aug, augment_information(info, p)[1:])`` with ``info``
    from `neuralmap.lab.pcrb.terrain_information`.

    Args:
        info: ``(..., 5, 5)`` 5-state information (per step).
        p: AR order (number of map-error states).

    Returns:
        ``(..., 5 + p, 5 + p)`` float64 information.
    """
    if info.shape[-2:] != (N_STATES, N_STATES) or p < 1:
        raise NeuralMapError(
            f"augment_information: info must be (..., 5, 5) and p ≥ 1, got "
            f"{tuple(info.shape)} and p={p}."
        )
    n = N_STATES + p
    out = torch.zeros(*info.shape[:-2], n, n, dtype=info.dtype, device=info.device)
    out[..., :N_STATES, :N_STATES] = info
    out[..., :N_STATES, N_STATES] = -info[..., :, 2]
    out[..., N_STATES, :N_STATES] = -info[..., 2, :]
    out[..., N_STATES, N_STATES] = info[..., 2, 2]
    return out


def paper_tan_model(base: TanModel) -> TanModel:
    """The 5-state model with the paper's tuning (SEEDS 000): ``P0½ = diag(400, 400, 400,
    40, 40)``, ``Q½ = diag(5, 5, 5, 0.5, 0.5)``, ``R½ = 20 m``, no extra fit variance;
    ``base`` keeps ``dt`` and the truth description."""
    return dataclasses.replace(
        base,
        P0=tuple(s * s for s in PAPER_P0_STD),
        Q=tuple(s * s for s in PAPER_Q_STD),
        R_altimeter=PAPER_R_STD**2,
        fit_variance=0.0,
    )


@dataclass(frozen=True)
class AugmentedTanModel:
    """A 5-state `TanModel` augmented with AR map-error states.

    Provides what the EKF navigation method (`neuralmap.tan.methods.ekf`) reads from a
    model (``n_states``, ``transition``, ``process_noise``, ``filter_prior``, ``base_R``,
    ``jacobian``), so ``run_filter(truth, linearizer, scenario, model=augmented)``
    (`neuralmap.lab.monte_carlo`) flies the 6- or 7-state filter of SEEDS 000 through the
    `Navigator` on the same truth as the 5-state one.

    Attributes:
        base: The 5-state model (its ``dt``, ``P0`` and ``Q`` tune the navigation block).
        ar: Stationary AR coefficients ``(a_1,)`` (6 states) or ``(a_1, a_2)`` (7 states).
        sigma_e: AR innovation standard deviation, m (the identified fit residual's root).
        p0_map: Initial standard deviations of the map-error states, m (paper: 40 m each);
            None = the stationary covariance of the AR model (the consistent choice).
        R: Measurement variance of the augmented filter, m²; None = ``base.base_R``.
        observed: False switches the map-error state off (zero column of H).
    """

    base: TanModel
    ar: tuple[float, ...]
    sigma_e: float
    p0_map: tuple[float, ...] | None = None
    R: float | None = None
    observed: bool = True

    def __post_init__(self) -> None:
        where = "AugmentedTanModel"
        object.__setattr__(self, "ar", tuple(_ar(self.ar, where)))
        if not (math.isfinite(self.sigma_e) and self.sigma_e >= 0.0):
            raise NeuralMapError(
                f"{where}: sigma_e must be finite and ≥ 0 m, got {self.sigma_e!r}."
            )
        if self.p0_map is not None:
            p0 = tuple(float(v) for v in self.p0_map)
            if len(p0) != len(self.ar) or not all(math.isfinite(v) and v > 0 for v in p0):
                raise NeuralMapError(
                    f"{where}: p0_map must hold {len(self.ar)} standard deviations > 0 m (one "
                    f"per map-error state), got {self.p0_map!r}."
                )
            object.__setattr__(self, "p0_map", p0)
        elif self.sigma_e == 0.0:
            raise NeuralMapError(
                f"{where}: with sigma_e = 0 the stationary map-error covariance is 0; give "
                "p0_map (initial standard deviations) or a sigma_e > 0."
            )
        if self.R is not None and not (math.isfinite(self.R) and self.R > 0.0):
            raise NeuralMapError(f"{where}: R must be finite and > 0 m², got {self.R!r}.")

    @classmethod
    def paper(cls, base: TanModel, ar: Sequence[float], sigma_e: float) -> AugmentedTanModel:
        """The paper's tuning (SEEDS 000): ``P0½ = diag(400, 400, 400, 40, 40, 40…)``,
        ``Q½ = diag(5, 5, 5, 0.5, 0.5, σ_e…)``, ``R½ = 20 m``; ``base`` keeps ``dt`` and the
        truth description."""
        return cls(paper_tan_model(base), tuple(ar), sigma_e, p0_map=(PAPER_P0_MAP_STD,) * len(ar),
                   R=PAPER_R_STD**2)

    @property
    def p(self) -> int:
        """Number of map-error states (the AR order)."""
        return len(self.ar)

    @property
    def n_states(self) -> int:
        """``5 + p``."""
        return N_STATES + self.p

    @property
    def dt(self) -> float:
        """Filter period T, s."""
        return self.base.dt

    @property
    def R_altimeter(self) -> float:
        """The altimeter's variance of the base model, m²."""
        return self.base.R_altimeter

    def altitude_decay(self, dt: float | None = None) -> float:
        """The base model's altitude decay over ``dt``."""
        return self.base.altitude_decay(dt)

    @property
    def base_R(self) -> float:
        """Measurement variance before the linearisation variance, m²."""
        return self.base.base_R if self.R is None else float(self.R)

    def _nominal(self, dt: float | None) -> None:
        """The AR map-error states advance one step per period: other intervals are refused."""
        if dt is not None and abs(float(dt) - self.dt) > 1e-9 * self.dt:
            raise NeuralMapError(
                f"AugmentedTanModel: the AR map-error states advance per period T = {self.dt:g} "
                f"s; an interval of {float(dt):g} s cannot be predicted (a log with gaps needs "
                "the 5-state model).")

    def transition(self, dt: float | None = None, *, dtype: torch.dtype = torch.float64,
                   device: str | torch.device = "cpu") -> torch.Tensor:
        """``(5+p, 5+p)`` Φ (`augmented_transition_matrix`) over the period T."""
        self._nominal(dt)
        return augmented_transition_matrix(self.dt, self.ar, dtype=dtype, device=device)

    def process_noise(self, dt: float | None = None, *, dtype: torch.dtype = torch.float64,
                      device: str | torch.device = "cpu") -> torch.Tensor:
        """``(5+p, 5+p)`` Q over the period T: the base model's, then ``σ_e²`` for ``e_r``."""
        self._nominal(dt)
        q_nav = self.base.filter_process_noise(dtype=dtype, device=device)
        return augmented_process_noise(q_nav, self.sigma_e, self.p, dtype=dtype, device=device)

    def filter_process_noise(self, *, dtype: torch.dtype = torch.float64,
                             device: str | torch.device = "cpu") -> torch.Tensor:
        """``(5+p, 5+p)`` Q per period (`process_noise`)."""
        return self.process_noise(dtype=dtype, device=device)

    def map_prior(self, *, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """``(p, p)`` initial covariance of the map-error states."""
        if self.p0_map is None:
            return stationary_map_covariance(self.ar, self.sigma_e, dtype=dtype)
        return torch.diag(torch.tensor(self.p0_map, dtype=dtype) ** 2)

    def filter_prior(self, *, dtype: torch.dtype = torch.float64,
                     device: str | torch.device = "cpu") -> torch.Tensor:
        """``(5+p, 5+p)`` P0: the base model's, then the map-error block."""
        return augmented_initial_covariance(
            self.base.filter_prior(dtype=dtype, device=device),
            self.map_prior(dtype=dtype).to(device), self.p, dtype=dtype, device=device,
        )

    def jacobian(self, slope: torch.Tensor) -> torch.Tensor:
        """``(N, 5+p)`` rows ``H = [−h_x, −h_y, 1, 0, 0, −1, 0…]``."""
        return augmented_measurement_jacobian(slope, self.p, observed=self.observed)

    def measurement_noise(self, linearisation_variance: torch.Tensor | float = 0.0
                          ) -> torch.Tensor | float:
        """``R = base_R + linearisation variance``."""
        return linearisation_variance + self.base_R

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable summary for reports."""
        return {
            "n_states": self.n_states,
            "ar": list(self.ar),
            "sigma_e": self.sigma_e,
            "p0_map": None if self.p0_map is None else list(self.p0_map),
            "R": self.base_R,
            "observed": self.observed,
        }
