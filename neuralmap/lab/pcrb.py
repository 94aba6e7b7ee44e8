"""Posterior Cramér-Rao bound (PCRB) of terrain-aided navigation.

The PCRB (Van Trees' Bayesian Cramér-Rao bound) is a lower bound on the mean-square-error
matrix of *any* estimator of the TAN error state (no unbiasedness assumption): the
physical limit every linearisation method is compared against.

For linear dynamics with additive Gaussian noise, ``x_{k+1} = F x_k + w_k``,
``w_k ~ N(0, Q)``, and a measurement ``z_k = h(x_k) + v_k``, ``v_k ~ N(0, R)``, the
Bayesian information matrix obeys the recursion of Tichavský, Muravchik & Nehorai (1998)
as used for TAN by Bergman (1999):

    J_0     = P0⁻¹
    J_{k+1} = (Q + F J_k⁻¹ Fᵀ)⁻¹ + E[H_{k+1}ᵀ R⁻¹ H_{k+1}],

where ``H_k = ∂h/∂x`` at the *true* state. For the 5-state TAN model of SEEDS 004
(``δX = [δx, δy, δh, δv_x, δv_y]``, ``Φ`` with period T) the measurement Jacobian is
``H = [−h_x, −h_y, 1, 0, 0]`` with the true terrain's slopes at the true position, and the
expectation is the Monte Carlo mean over the simulated truth trajectories.

The recursion is run in covariance form, ``B = J⁻¹``:
``P⁻ = F B_k Fᵀ + Q``, ``B_{k+1} = (I + P⁻ I_{k+1})⁻¹ P⁻`` (a linear solve; no matrix is
inverted explicitly, and a singular ``P0`` or ``Q`` — a perfectly known component — is
fine). It equals the Kalman filter covariance when the model is linear-Gaussian.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.kalman import add_information
from neuralmap.filters.stats import symmetrize
from neuralmap.filters.validation import check_covariance, check_finite, shape_error
from neuralmap.tan.model import TanModel
from neuralmap.terrain.base import model_device

__all__ = ["map_aware_pcrb", "pcrb", "pcrb_position", "pcrb_recursion", "terrain_information"]

#: Points per terrain query when computing slopes (bounds memory for neural maps).
SLOPE_CHUNK = 65536


def _as_f64(value: Any, name: str, where: str, device: torch.device | None = None) -> torch.Tensor:
    try:
        out = torch.as_tensor(value, dtype=torch.float64, device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise NeuralMapError(f"{where}: '{name}' must be numeric ({exc}).") from exc
    return out


def _per_step(
    m: torch.Tensor, name: str, where: str, n: int, steps: int, *, covariance: bool
) -> torch.Tensor:
    """``(n, n)`` or ``(steps, n, n)`` → ``(steps, n, n)`` (validated)."""
    if m.ndim == 2 and tuple(m.shape) == (n, n):
        if covariance:
            m = check_covariance(m, name=name, where=where, definite=False)
        else:
            check_finite(m, name=name, where=where)
        return m.expand(steps, n, n)
    if m.ndim == 3 and tuple(m.shape) == (steps, n, n):
        if covariance:
            return check_covariance(m, name=name, where=where, definite=False)
        check_finite(m, name=name, where=where)
        return m
    raise shape_error(where, name, f"({n}, {n}) or (K, {n}, {n}) = ({steps}, {n}, {n})", m.shape)


def pcrb_recursion(
    P0: torch.Tensor,
    F: torch.Tensor,
    Q: torch.Tensor,
    info_increments: torch.Tensor,
    *,
    initial_info: torch.Tensor | None = None,
) -> torch.Tensor:
    """Bound covariances ``J_k⁻¹`` of the Tichavský/Bergman PCRB recursion.

    ``J_0 = P0⁻¹ (+ initial_info)``; for ``k = 0 … K−1``:
    ``J_{k+1} = (Q_k + F_k J_k⁻¹ F_kᵀ)⁻¹ + I_{k+1}`` with ``I_{k+1} = info_increments[k]``
    (e.g. ``E[Hᵀ R⁻¹ H]`` of the measurement taken at step ``k+1``, after the predict —
    the order in which `BatchedEKF` runs). Computed in
    covariance form ``B = J⁻¹``: ``P⁻ = F B Fᵀ + Q``, ``B⁺ = solve(I + P⁻ I, P⁻)``,
    symmetrised. Everything in float64.

    Args:
        P0: ``(n, n)`` prior covariance (positive semi-definite; a zero variance means a
            known component).
        F: ``(n, n)`` or per-step ``(K, n, n)`` transition matrices (step k → k+1).
        Q: ``(n, n)`` or per-step ``(K, n, n)`` process-noise covariances.
        info_increments: ``(K, n, n)`` measurement information added at steps 1 … K
            (positive semi-definite; zero where there is no measurement).
        initial_info: ``(n, n)`` information of a measurement at step 0, if the filter
            updates before its first predict (default: none).

    Returns:
        ``(K + 1, n, n)`` bound covariances ``B_k = J_k⁻¹`` (float64); ``B_0`` is the prior.

    Raises:
        NeuralMapError: Shapes that do not agree (expected vs received), non-finite or
            non-symmetric inputs, negative variances, matrices that are not positive
            semi-definite.
    """
    where = "pcrb_recursion"
    increments = _as_f64(info_increments, "info_increments", where)
    if increments.ndim != 3 or increments.shape[1] != increments.shape[2]:
        raise shape_error(where, "info_increments", "(K, n, n)", increments.shape)
    steps, n = increments.shape[0], increments.shape[1]
    device = increments.device
    check_finite(increments, name="info_increments", where=where)
    increments = symmetrize(increments)
    P0 = _as_f64(P0, "P0", where, device)
    if tuple(P0.shape) != (n, n):
        raise shape_error(where, "P0", f"({n}, {n}) (n from info_increments)", P0.shape)
    P0 = check_covariance(P0, name="P0", where=where, definite=False)
    Fs = _per_step(_as_f64(F, "F", where, device), "F", where, n, steps, covariance=False)
    Qs = _per_step(_as_f64(Q, "Q", where, device), "Q", where, n, steps, covariance=True)

    bound = P0
    if initial_info is not None:
        info0 = _as_f64(initial_info, "initial_info", where, device)
        if tuple(info0.shape) != (n, n):
            raise shape_error(where, "initial_info", f"({n}, {n})", info0.shape)
        check_finite(info0, name="initial_info", where=where)
        bound = add_information(P0, symmetrize(info0))
    out = [bound]
    for k in range(steps):
        prior = Fs[k] @ bound @ Fs[k].T + Qs[k]
        bound = add_information(symmetrize(prior), increments[k])
        out.append(bound)
    return torch.stack(out)


def pcrb_position(bound: torch.Tensor) -> torch.Tensor:
    """Horizontal position bound ``sqrt(B[0, 0] + B[1, 1])`` per step (metres).

    Args:
        bound: ``(K + 1, n, n)`` bound covariances from `pcrb` (states 0, 1 = x, y).

    Returns:
        ``(K + 1,)`` root of the summed horizontal variances (the RMSE floor).

    Raises:
        NeuralMapError: ``bound`` is not ``(K + 1, n, n)`` with ``n >= 2``.
    """
    if not isinstance(bound, torch.Tensor) or bound.ndim != 3 or bound.shape[1] < 2 or (
        bound.shape[1] != bound.shape[2]
    ):
        shape = tuple(bound.shape) if isinstance(bound, torch.Tensor) else type(bound).__name__
        raise NeuralMapError(
            f"pcrb_position: 'bound' must be a (K+1, n, n) tensor with n >= 2 (from pcrb()), "
            f"got {shape}."
        )
    return (bound[:, 0, 0] + bound[:, 1, 1]).clamp_min(0.0).sqrt()


def _terrain_slopes(terrain: Any, xy: torch.Tensor,
                    progress: Callable[[float], None] | None = None) -> torch.Tensor:
    """``(M, 2)`` terrain slopes at ``(M, 2)`` points (float64, on ``xy``'s device), chunked.

    Uses ``terrain.height_and_slope`` when the model has it (analytic, e.g. GridTerrain),
    else autograd of ``terrain(xy)``, on the terrain's device. ``progress`` is called with
    each chunk's share.
    """
    parts = []
    analytic = getattr(terrain, "height_and_slope", None)
    device = model_device(terrain) or xy.device
    for start in range(0, xy.shape[0], SLOPE_CHUNK):
        chunk = xy[start:start + SLOPE_CHUNK].to(device)
        if callable(analytic):
            with torch.no_grad():
                slope = analytic(chunk)[1]
        else:
            with torch.enable_grad():
                pts = chunk.detach().clone().requires_grad_(True)
                height = terrain(pts)
                (slope,) = torch.autograd.grad(height.sum(), pts)
        parts.append(slope.detach().to(device=xy.device, dtype=torch.float64))
        if progress is not None:
            progress(chunk.shape[0] / xy.shape[0])
    if not parts:
        return torch.zeros(0, 2, dtype=torch.float64, device=xy.device)
    return torch.cat(parts)


def terrain_information(
    pos: torch.Tensor,
    terrain: Any,
    R_m2: float,
    *,
    on_map: torch.Tensor | None = None,
    progress: Callable[[float], None] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Expected measurement information ``E[Hᵀ R⁻¹ H]`` per step over true trajectories.

    ``H = [−h_x, −h_y, 1, 0, 0]`` (SEEDS 004) with the terrain slopes at the true
    positions; the expectation is the mean over the trajectories that are on the map at
    that step (a step with none gets zero information). Points whose slope is not finite
    count as off the map.

    Args:
        pos: ``(N, K + 1, ≥2)`` true positions (x, y first), metres.
        terrain: The *true* terrain model (``forward(xy) -> heights``, optionally
            ``height_and_slope``), e.g. the simulator's bicubic DEM.
        R_m2: Measurement-noise variance, m².
        on_map: ``(N, K + 1)`` bool, where the measurement exists (default: the terrain's
            ``contains``, or everywhere if it has none).
        progress: Called with the share of the slope evaluations each chunk does
            (`neuralmap.progress.stage_progress`); None = silent.

    Returns:
        ``(K + 1, 5, 5)`` information per step (float64) and ``(K + 1,)`` the number of
        trajectories averaged at each step.
    """
    where = "terrain_information"
    if not isinstance(pos, torch.Tensor) or pos.ndim != 3 or pos.shape[-1] < 2:
        shape = tuple(pos.shape) if isinstance(pos, torch.Tensor) else type(pos).__name__
        raise shape_error(where, "truth.pos", "(N, K+1, 3)", shape)  # type: ignore[arg-type]
    if not (R_m2 > 0.0 and R_m2 < float("inf")):
        raise NeuralMapError(
            f"{where}: the measurement variance must be finite and > 0, got {R_m2!r} m². "
            "Check the scenario's altimeter_sigma_m / R_m2."
        )
    N, steps = pos.shape[0], pos.shape[1]
    xy = pos[..., :2].detach()
    if on_map is None:
        contains = getattr(terrain, "contains", None)
        on_map = (contains(xy.to(model_device(terrain) or xy.device)) if callable(contains)
                  else torch.ones(N, steps, dtype=torch.bool, device=pos.device))
    on_map = torch.as_tensor(on_map, device=pos.device).to(torch.bool)
    if tuple(on_map.shape) != (N, steps):
        raise shape_error(where, "on_map", f"(N, K+1) = ({N}, {steps})", on_map.shape)
    flat = xy.reshape(-1, 2).to(torch.float64)
    slope = _terrain_slopes(terrain, flat, progress).reshape(N, steps, 2)
    valid = on_map & torch.isfinite(slope).all(-1)
    slope = torch.where(valid.unsqueeze(-1), slope, 0.0)
    w = valid.to(torch.float64)
    count = w.sum(0)  # (K+1,)
    rows = TanModel.jacobian(slope.reshape(-1, 2)).reshape(N, steps, 5)
    info = torch.einsum("nk,nki,nkj->kij", w, rows, rows)
    info = info / (count.clamp_min(1.0)[:, None, None] * R_m2)
    return info, count


def pcrb(
    truth: Any,
    scenario: Any,
    terrain: Any,
    *,
    model: str = "truth",
    R_m2: float | None = None,
    runs: torch.Tensor | None = None,
    update_at_step0: bool = False,
    progress: Callable[[float], None] | None = None,
) -> torch.Tensor:
    """PCRB of the 5-state TAN error state over the simulated truth trajectories.

    ``H = [−h_x, −h_y, 1, 0, 0]`` uses the slopes of ``terrain`` at the *true* positions
    ``truth.pos``; ``E[Hᵀ R⁻¹ H]`` is the mean over the trajectories on the map at each
    step (``truth.on_map``); see `pcrb_recursion` for the recursion. The first
    measurement enters at step 1: the filter starts from ``P0`` at step 0 and runs
    predict-then-update at steps 1 … K (set ``update_at_step0`` for a filter that also
    updates at step 0).

    Noise model (``model``):

    * ``"truth"`` (default, the physical limit): the simulator's own statistics —
      ``P0 = diag(scenario.init_error_sigma())²``, ``Q = diag(scenario.truth_process_noise())``
      and ``R = altimeter_sigma_m²`` (the radar-altimeter noise variance alone: the DEM
      error and outliers are left out, which keeps it a lower bound). Scenarios without
      those methods/fields fall back to the filter's values.
    * ``"filter"``: the filter's assumed model — ``diag(P0_diag)``, ``diag(Q_diag)``,
      ``R = R_m2 + fit_variance_m2``.

    ``R_m2`` overrides R in either case.

    Args:
        truth: Simulation result with ``pos (N, K+1, 3)`` true x, y, h and optionally
            ``on_map (N, K+1)`` bool (duck-typed; see ``neuralmap.lab.simulator.Truth``).
        scenario: Object with ``dt`` and the fields named above (duck-typed).
        terrain: The true terrain model (e.g. the simulator's bicubic
            `GridTerrain`), not the map under test.
        model: ``"truth"`` or ``"filter"``.
        R_m2: Measurement variance override, m².
        runs: ``(N,)`` bool, trajectories to include (e.g. those the metrics keep).
        update_at_step0: Add the step-0 measurement information to ``J_0``.
        progress: Called with the share of the work done (the terrain slopes at the true
            positions, the costly part); None = silent.

    Returns:
        ``(K + 1, 5, 5)`` bound covariances (float64, inverse information), step 0 = prior.

    Raises:
        NeuralMapError: Unknown ``model``, missing/invalid scenario fields, bad shapes.
    """
    where = "pcrb"
    if model not in ("truth", "filter"):
        raise NeuralMapError(f"{where}: model must be 'truth' or 'filter', got {model!r}.")
    pos = getattr(truth, "pos", None)
    if not isinstance(pos, torch.Tensor):
        raise NeuralMapError(
            f"{where}: 'truth' must have a tensor attribute 'pos' (N, K+1, 3) of true "
            "positions (the result of neuralmap.lab.simulator.simulate)."
        )
    dt = getattr(scenario, "dt", None)
    if not isinstance(dt, (int, float)) or not dt > 0:
        raise NeuralMapError(f"{where}: scenario.dt must be a number > 0, got {dt!r}.")
    tan = TanModel.from_scenario(scenario)
    if model == "truth":
        P0, Q = tan.bound_prior(), tan.truth_process_noise()
    else:
        P0, Q = tan.filter_prior(), tan.filter_process_noise()
    if R_m2 is None:
        R_m2 = tan.truth_R if model == "truth" else tan.base_R
    on_map = getattr(truth, "on_map", None)
    if on_map is not None:
        on_map = torch.as_tensor(on_map, device=pos.device).to(torch.bool)
    if runs is not None:
        runs = torch.as_tensor(runs, device=pos.device).to(torch.bool)
        if tuple(runs.shape) != (pos.shape[0],):
            raise shape_error(where, "runs", f"(N,) = ({pos.shape[0]},)", runs.shape)
        base = on_map if on_map is not None else torch.ones(pos.shape[:2], dtype=torch.bool,
                                                           device=pos.device)
        on_map = base & runs[:, None]
    info, _ = terrain_information(pos, terrain, float(R_m2), on_map=on_map, progress=progress)
    device = info.device
    return pcrb_recursion(
        P0.to(device),
        tan.transition(dtype=torch.float64, device=device),
        Q.to(device),
        info[1:],
        initial_info=info[0] if update_at_step0 else None,
    )


def map_aware_pcrb(
    truth: Any,
    scenario: Any,
    map_terrain: Any,
    *,
    map_error_var: float,
    map_error_corr: float = 0.0,
    runs: torch.Tensor | None = None,
    R_m2: float | None = None,
    progress: Callable[[float], None] | None = None,
) -> torch.Tensor:
    """PCRB of a filter that knows the map (the DEM), not the true terrain.

    The measurement is ``y = t_map(p) + e_map(p) + δh − v``: the information comes from the
    slopes of ``map_terrain`` (what such a filter can linearise) at the true positions, and
    the map's error ``e_map`` is noise of variance ``map_error_var`` (measured against the
    truth terrain, e.g. `neuralmap.lab.map_error.measure_map_error`). With
    ``map_error_corr = ρ > 0`` (the correlation of the map error between successive
    samples, e.g. `neuralmap.lab.map_error.map_error_correlation` at the distance
    flown per step) the map error is a first-order Gauss-Markov state appended to the
    5-state model: ``e_{k+1} = ρ e_k + w``, ``Var w = (1 − ρ²) σ²``, ``e_0 ~ N(0, σ²)``,
    ``H = [−t_x, −t_y, 1, 0, 0, 1]``, ``R = R_altimeter`` (state augmentation for
    coloured measurement noise); with ``ρ = 0``, ``R = R_altimeter + σ²`` on the 5 states.
    Same recursion, prior and process noise as `pcrb` (``model="truth"``).

    Args:
        truth: Simulation result (``pos (N, K+1, 3)``, optionally ``on_map``).
        scenario: The scenario (as for `pcrb`).
        map_terrain: The map the filter knows (grid or neural; ``forward(xy)``).
        map_error_var: Map error variance σ², m² (≥ 0).
        map_error_corr: Correlation ρ of the map error between successive samples, [0, 1).
        runs: ``(N,)`` bool, trajectories to include.
        R_m2: Altimeter variance override (default: the truth's, ``altimeter_sigma_m²``).
        progress: As for `pcrb`.

    Returns:
        ``(K + 1, 5, 5)`` bound covariances of the navigation states (float64).

    Raises:
        NeuralMapError: A negative or non-finite variance, ρ outside [0, 1), bad shapes.
    """
    where = "map_aware_pcrb"
    if not (map_error_var >= 0.0 and map_error_var < float("inf")):
        raise NeuralMapError(f"{where}: map_error_var must be finite and >= 0 m², got "
                             f"{map_error_var!r}.")
    if not 0.0 <= map_error_corr < 1.0:
        raise NeuralMapError(f"{where}: map_error_corr must be in [0, 1), got {map_error_corr!r}.")
    tan = TanModel.from_scenario(scenario)
    r_alt = tan.truth_R if R_m2 is None else float(R_m2)
    if map_error_corr == 0.0 or map_error_var == 0.0:
        return pcrb(truth, scenario, map_terrain, R_m2=r_alt + map_error_var, runs=runs,
                    progress=progress)
    pos = truth.pos
    n, steps = pos.shape[0], pos.shape[1]
    on_map = getattr(truth, "on_map", None)
    on_map = (torch.ones(n, steps, dtype=torch.bool, device=pos.device) if on_map is None
              else torch.as_tensor(on_map, device=pos.device).to(torch.bool))
    if runs is not None:
        on_map = on_map & torch.as_tensor(runs, device=pos.device).to(torch.bool)[:, None]
    slope = _terrain_slopes(map_terrain, pos[..., :2].detach().reshape(-1, 2).double(),
                            progress)
    slope = slope.reshape(n, steps, 2)
    valid = on_map & torch.isfinite(slope).all(-1)
    slope = torch.where(valid.unsqueeze(-1), slope, 0.0)
    rows = torch.cat([TanModel.jacobian(slope.reshape(-1, 2)).reshape(n, steps, 5),
                      torch.ones(n, steps, 1, dtype=torch.float64, device=pos.device)], -1)
    w = valid.to(torch.float64)
    count = w.sum(0).clamp_min(1.0)
    info = torch.einsum("nk,nki,nkj->kij", w, rows, rows) / (count[:, None, None] * r_alt)
    rho, var = float(map_error_corr), float(map_error_var)
    P0 = torch.block_diag(tan.bound_prior(), torch.tensor([[var]], dtype=torch.float64))
    Q = torch.block_diag(tan.truth_process_noise(),
                         torch.tensor([[(1.0 - rho * rho) * var]], dtype=torch.float64))
    F = torch.block_diag(tan.transition(), torch.tensor([[rho]], dtype=torch.float64))
    device = info.device
    bound = pcrb_recursion(P0.to(device), F.to(device), Q.to(device), info[1:])
    return bound[:, :5, :5]
