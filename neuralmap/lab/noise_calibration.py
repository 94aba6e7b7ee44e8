"""R of every EKF method from measured statistics: the map table, then pilot flights.

The TAN EKF's measurement noise is the altimeter's plus the method's miss
``e = t(p) − h(p̂) − slope(p̂) · (p − p̂)`` (map error and linearisation error, SEEDS 000:
``m_d`` and ``m2``). `neuralmap.linearize.measured_noise.measure_linearization_noise`
measures ``E[e²]`` over the map with ``p − p̂ ~ N(0, σ² I)``. While the filter converges its
errors are not Gaussian with its own covariance (some runs lag behind it), so the miss it
meets in flight is larger than the map table says at the same σ. `calibrate_noise`
therefore flies the filter on pilot Monte Carlo runs (an independent seed of trajectories
and sensor noise over the same world), reconstructs at every step the prior estimate
``p̂``, the prior covariance ``P⁻`` and the true position ``p``, evaluates the miss there,
and takes ``v(σ) = E[e² | σ]`` binned on the table's σ nodes (σ = sqrt(tr P⁻_xy / 2);
linear bin weights, a weighted non-decreasing fit), repeated with the new table
(``iterations`` times, a fixed-point iteration). Nodes with too few pilot samples keep the
map value.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.linearize.measured_noise import (
    DEFAULT_NOISE_SIGMAS_M,
    MeasuredNoiseLinearizer,
    NoiseTable,
    fit_offset_scale,
    measure_linearization_noise,
    position_sigma,
)

__all__ = ["binned_mean_square", "calibrate_noise", "derive_method_noise", "flight_miss",
           "isotonic_increasing"]


def flight_miss(run: Any, truth: Any, linearizer: Any, model: Any, truth_model: Any
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The miss met in flight at every updated step of a filter run.

    The prior estimate of step k is ``x̂⁻_k = Φ x̂_{k−1}`` with ``x̂ = δX − err`` (output
    correction), ``P⁻_k = Φ P_{k−1} Φᵀ + Q``, ``p̂_k = p_ins,k − x̂⁻_k[:2]``; the method is
    evaluated at ``(p̂_k, P⁻_k[:2, :2])`` and ``e_k = t(p_k) − h(p̂_k) − slope · (p_k − p̂_k)``.

    Args:
        run: A `FilterRun` (5-state) on ``truth``.
        truth: Its simulated truth.
        linearizer: The method the run used (its height and slope).
        model: The filter's `TanModel`.
        truth_model: The true terrain (float64).

    Returns:
        ``(sigma (M,), miss (M,), own variance (M,))`` over the updated steps of runs whose
        truth stayed on the map, float64 (``own``: the method's own variance there).
    """
    dtype = run.err.dtype
    F = model.transition(dtype=dtype, device=run.err.device)
    Q = model.filter_process_noise(dtype=dtype, device=run.err.device)
    x = truth.ins_error - run.err
    x_prior = x[:, :-1] @ F.T
    P_prior = F @ run.P[:, :-1] @ F.T + Q
    use = run.updated[:, 1:] & truth.on_map.all(dim=1, keepdim=True)
    p_hat = (truth.ins_pos[:, 1:, :2] - x_prior[..., :2])[use]
    p = truth.pos[:, 1:, :2][use]
    cov = P_prior[use][:, :2, :2]
    with torch.no_grad():
        lin = linearizer(p_hat, cov)
        miss = (truth_model(p.double()).double() - lin.height.detach().double()
                - (lin.slope.detach().double() * (p - p_hat).double()).sum(-1))
    sigma = position_sigma(cov.double())
    own = lin.variance.detach().double()
    ok = torch.isfinite(miss) & torch.isfinite(sigma) & torch.isfinite(own)
    return sigma[ok], miss[ok], own[ok]


def tent_weights(sigma: torch.Tensor, nodes: tuple[float, ...]) -> torch.Tensor:
    """``(K, M)`` tent weights of samples at ``sigma`` on the nodes (columns sum to 1)."""
    s = torch.tensor(nodes, dtype=torch.float64)
    sig = sigma.double().clamp(min=float(s[0]), max=float(s[-1]))
    k = len(nodes)
    out = torch.zeros(k, sig.numel(), dtype=torch.float64)
    if k == 1:
        return out + 1.0
    idx = torch.bucketize(sig, s).clamp(1, k - 1)
    w = (sig - s[idx - 1]) / (s[idx] - s[idx - 1])
    cols = torch.arange(sig.numel())
    out[idx - 1, cols] += 1.0 - w
    out[idx, cols] += w
    return out


def binned_mean_square(sigma: torch.Tensor, value: torch.Tensor, nodes: tuple[float, ...]
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``value`` per σ node with linear (tent) bin weights.

    A sample at σ between nodes ``s_i ≤ σ < s_{i+1}`` gives weight ``1 − w`` to node i and
    ``w`` to node i+1 (``w = (σ − s_i)/(s_{i+1} − s_i)``); beyond the ends it goes to the end
    node. The inverse of the piecewise-linear interpolation the filter applies.

    Returns:
        ``(mean (K,), weight (K,))`` (mean NaN where the weight is 0).
    """
    s = torch.tensor(nodes, dtype=torch.float64)
    sig = sigma.double().clamp(min=float(s[0]), max=float(s[-1]))
    k = len(nodes)
    num, den = torch.zeros(k, dtype=torch.float64), torch.zeros(k, dtype=torch.float64)
    if k == 1:
        return np.array([float(value.double().mean())]), np.array([float(value.numel())])
    idx = torch.bucketize(sig, s).clamp(1, k - 1)
    w = (sig - s[idx - 1]) / (s[idx] - s[idx - 1])
    v = value.double()
    num.index_add_(0, idx - 1, (1.0 - w) * v)
    den.index_add_(0, idx - 1, 1.0 - w)
    num.index_add_(0, idx, w * v)
    den.index_add_(0, idx, w)
    mean = torch.where(den > 0, num / den.clamp(min=1e-300), torch.full_like(num, float("nan")))
    return mean.numpy(), den.numpy()


def isotonic_increasing(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted least-squares non-decreasing fit (pool-adjacent-violators).

    Args:
        values: ``(K,)`` values.
        weights: ``(K,)`` positive weights.

    Returns:
        ``(K,)`` the non-decreasing sequence closest to ``values`` in weighted squares.
    """
    blocks: list[list[float]] = []  # [mean, weight, count]
    for v, w in zip(values.tolist(), weights.tolist(), strict=True):
        blocks.append([v, w, 1])
        while len(blocks) > 1 and blocks[-2][0] > blocks[-1][0]:
            m2, w2, c2 = blocks.pop()
            m1, w1, c1 = blocks.pop()
            blocks.append([(m1 * w1 + m2 * w2) / (w1 + w2), w1 + w2, c1 + c2])
    return np.concatenate([np.full(int(c), m) for m, _, c in blocks])


def calibrate_noise(linearizer: Any, table: NoiseTable, *, pilot: Any, scenario: Any,
                    model: Any, truth_model: Any, iterations: int = 2,
                    min_weight: float = 200.0, local: bool = False,
                    progress: Callable[[float], None] | None = None) -> NoiseTable:
    """Replaces a table's ``variance_m2`` by the miss met on pilot flights.

    Each iteration flies the EKF (``run_filter``) on ``pilot`` with the current table,
    measures the miss (`flight_miss`), bins ``e²`` on the table's σ nodes
    (`binned_mean_square`), keeps the map value where the pilot weight is below
    ``min_weight``, and makes the result non-decreasing in σ (`isotonic_increasing`).

    Args:
        linearizer: The method (unwrapped).
        table: Its map table (`measure_linearization_noise`).
        pilot: Pilot truth (`neuralmap.lab.simulator.simulate`, an independent seed).
        scenario: The scenario the filter runs (its R without the map variance).
        model: The filter's `TanModel` for that scenario.
        truth_model: The true terrain.
        iterations: Pilot flights (>= 1).
        min_weight: Pilot weight a node needs to use the flight value.
        local: Fit ``e² ≈ a + b u`` per node on the method's own variance ``u``
            (`fit_offset_scale`, tent weights).
        progress: Called with the share of the work each pilot step does
            (`neuralmap.progress.stage_progress`); None = silent.

    Returns:
        The table with ``variance_m2`` and ``flight_samples`` from the last iteration.
    """
    from neuralmap.lab.monte_carlo import run_filter
    from neuralmap.progress import ScaledUpdates

    if iterations < 1:
        raise NeuralMapError(f"calibrate_noise: iterations must be >= 1, got {iterations}.")
    current = table
    map_mse = np.asarray(table.map_mse_m2)
    for _ in range(iterations):
        bar = (False if progress is None
               else ScaledUpdates(progress, 1.0 / (iterations * pilot.n_steps)))
        run = run_filter(pilot, MeasuredNoiseLinearizer(linearizer, current), scenario,
                         model=model, progress=bar)
        sigma, miss, own = flight_miss(run, pilot, linearizer, model, truth_model)
        mean, weight = binned_mean_square(sigma, miss.square(), current.sigmas_m)
        enough = weight >= min_weight
        values = np.where(enough, mean, map_mse)
        scale = np.asarray(current.scale, dtype=float)
        if local:
            tents = tent_weights(sigma, current.sigmas_m)
            fits = [fit_offset_scale(miss.square(), own, tents[i]) for i in range(len(values))]
            values = np.where(enough, [a for a, _ in fits], np.asarray(table.variance_m2))
            scale = np.where(enough, [b for _, b in fits], np.asarray(table.scale))
            scale = isotonic_increasing(scale, np.maximum(weight, min_weight))
        values = isotonic_increasing(values, np.maximum(weight, min_weight))
        current = dataclasses.replace(current, variance_m2=tuple(float(v) for v in values),
                                      scale=tuple(float(b) for b in scale),
                                      flight_samples=tuple(float(w) if e else 0.0
                                                           for w, e in zip(weight, enough,
                                                                           strict=True)))
    return current


def derive_method_noise(methods: dict[str, Any], *, scenario: Any, tile: Any, truth_terrain: Any,
                        seed: int, n_pilot: int, iterations: int, n_points: int = 4000,
                        draws: int = 8, sigmas: tuple[float, ...] = DEFAULT_NOISE_SIGMAS_M,
                        local: bool = False, pilot_duration_s: float | None = None,
                        progress: Callable[[float], None] | None = None,
                        ) -> tuple[dict[str, Any], Any, dict[str, Any]]:
    """Measured R for every EKF method: map table, then (``n_pilot > 0``) pilot flights.

    The filter's R becomes ``R_m2`` (the altimeter variance) + the method's measured
    ``v(σ)``; the scenario's hand ``fit_variance_m2`` and the methods' own variances are
    dropped (the table holds the map error, measured).

    Args:
        methods: Method name -> linearizer.
        scenario: The study's scenario.
        tile: Its tile (the map extent of the table).
        truth_terrain: The study's `TrueTerrain` (the
            pilot flies over the same world).
        seed: The study's seed; the pilot flies ``seed + 1`` (independent trajectories and
            sensor noise), the map table uses ``seed``.
        n_pilot: Pilot runs (0 = the map table only).
        iterations: Pilot iterations.
        n_points: Map points of the table.
        draws: Draws per point and σ.
        sigmas: σ nodes, m.
        local: ``R = a(σ) + b(σ) u`` on each method's own variance ``u`` (fitted), not
            ``a(σ)`` alone.
        pilot_duration_s: Length of the pilot flights (s); None = the scenario's. The
            filter's σ passes from the prior to the converged level in the first part of
            a flight, so a shorter pilot samples the same σ range for less time.
        progress: Called with the share of the work done (each method an equal share:
            its map table one part, each pilot flight one more); None = silent.

    Returns:
        ``(wrapped methods, scenario without the hand map variance, info)``; ``info`` has
        each method's table (``to_dict``) and the R the filter gets at the nodes.
    """
    from neuralmap.lab.simulator import simulate
    from neuralmap.tan.model import TanModel

    filter_scenario = dataclasses.replace(scenario, fit_variance_m2=0.0)
    model = TanModel.from_scenario(filter_scenario)
    extent = tuple(float(e) for e in tile.extent)
    truth_model = truth_terrain.model
    pilot, pilot_scenario = None, filter_scenario
    if n_pilot > 0:
        pilot_scenario = filter_scenario if pilot_duration_s is None else dataclasses.replace(
            filter_scenario, duration_s=min(float(pilot_duration_s),
                                            float(filter_scenario.duration_s)))
        pilot = simulate(pilot_scenario, tile, n_runs=int(n_pilot), seed=int(seed) + 1,
                         truth_terrain=truth_terrain)
    wrapped, info = {}, {}
    parts = 1 + (iterations if pilot is not None else 0)  # per method: table + pilot flights

    def share(fraction: float) -> Callable[[float], None] | None:
        return None if progress is None else (lambda f: progress(f * fraction))

    for name, linearizer in methods.items():
        table = measure_linearization_noise(linearizer, truth_model, extent=extent,
                                            sigmas=sigmas, n_points=n_points, draws=draws,
                                            seed=seed, local=local,
                                            progress=share(1.0 / (parts * len(methods))))
        if pilot is not None:
            table = calibrate_noise(linearizer, table, pilot=pilot, scenario=pilot_scenario,
                                    model=model, truth_model=truth_model,
                                    iterations=iterations, local=local,
                                    progress=share((parts - 1) / (parts * len(methods))))
        wrapped[name] = MeasuredNoiseLinearizer(linearizer, table)
        info[name] = {**table.to_dict(),
                      "R_m2": [float(filter_scenario.R_m2) + v for v in table.variance_m2]}
    return wrapped, filter_scenario, {
        "rule": "R = altimeter variance (R_m2) + v(sigma), v = E[miss^2] of the method "
                "against the truth terrain at sigma = sqrt(tr P_xy / 2): measured over the map "
                "with d ~ N(0, sigma^2 I), replaced by the pilot flights' value where they "
                "have samples",
        "altimeter_R_m2": float(filter_scenario.R_m2), "pilot_runs": int(n_pilot),
        "pilot_seed": int(seed) + 1, "pilot_duration_s": float(
            filter_scenario.duration_s if pilot_duration_s is None else min(
                float(pilot_duration_s), float(filter_scenario.duration_s))),
        "iterations": int(iterations) if n_pilot > 0 else 0,
        "methods": info}

