"""The paper's repeat-survey sample of the DEM-making error, simulated (SEEDS 000, 3.1).

In the paper, 61 grid nodes on a line were measured 10 times over, one pass after the other;
the per-node mean of the 10 measurements is taken as truth and the 610 deviations, in
measurement order, form the error sample (σ = 1.0435 m; AR(1) φ = 0.5315 identified).
Here the measurement error is an AR(p) process running through the measurement sequence
(``continuous=True``, the passes follow each other) or restarting each pass.

Subtracting the per-node mean of P passes scales the error variance by ``1 − 1/P`` and
leaves the lag-k correlation within a pass essentially unchanged, so identification of the
deviations recovers the AR coefficients of the measurement error.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from neuralmap.errors.arma import ArmaModel
from neuralmap.errors.identification import ErrorModelIdentification, identify_error_model
from neuralmap.errors.simulation import DEM_ERROR_AR1, DEM_ERROR_SIGMA, ar_filter
from neuralmap.exceptions import NeuralMapError


@dataclass(frozen=True)
class RepeatSurvey:
    """A simulated repeat survey (leading batch dimension optional).

    Attributes:
        true_heights: ``(n_nodes,)`` true heights along the line, m.
        true_errors: ``(..., n_passes, n_nodes)`` simulated measurement errors, m.
        measurements: ``(..., n_passes, n_nodes)`` measured heights = truth + error.
    """

    true_heights: np.ndarray
    true_errors: np.ndarray
    measurements: np.ndarray

    @property
    def truth_estimate(self) -> np.ndarray:
        """``(..., n_nodes)`` per-node mean of the passes (the paper's truth)."""
        return self.measurements.mean(axis=-2)

    @property
    def errors(self) -> np.ndarray:
        """``(..., n_passes * n_nodes)`` error sample: measurement minus per-node mean,
        in measurement order (pass after pass)."""
        dev = self.measurements - self.truth_estimate[..., None, :]
        return dev.reshape(*dev.shape[:-2], -1)


def repeat_survey(
    *,
    n_nodes: int = 61,
    n_passes: int = 10,
    phi: Sequence[float] = DEM_ERROR_AR1,
    sigma: float | None = None,
    true_heights: np.ndarray | None = None,
    continuous: bool = True,
    batch: int | None = None,
    seed: int = 0,
) -> RepeatSurvey:
    """Simulates the repeat survey of a line of grid nodes.

    Args:
        n_nodes: Nodes on the line (paper: 61).
        n_passes: Passes (paper: 10).
        phi: AR coefficients of the measurement error between consecutive measurements.
        sigma: Standard deviation of one measurement's error, m. Default:
            ``1.0435 / √(1 − 1/n_passes)``, so that the error sample (deviations from the
            per-node mean) has the paper's σ = 1.0435 m.
        true_heights: ``(n_nodes,)`` true heights (default zeros; they cancel in the sample).
        continuous: The AR error runs on through all passes (True) or restarts each pass.
        batch: Independent surveys (None: one, no batch dimension).
        seed: Seed of the NumPy generator.

    Returns:
        The `RepeatSurvey`.
    """
    if n_nodes < 2 or n_passes < 2:
        raise NeuralMapError(
            f"repeat_survey: need ≥ 2 nodes and ≥ 2 passes (the per-node mean of one pass is "
            f"the pass itself), got n_nodes={n_nodes}, n_passes={n_passes}."
        )
    if sigma is None:
        sigma = DEM_ERROR_SIGMA / math.sqrt(1.0 - 1.0 / n_passes)
    if not (math.isfinite(sigma) and sigma > 0.0):
        raise NeuralMapError(f"repeat_survey: sigma must be finite and > 0 m, got {sigma!r}.")
    heights = np.zeros(n_nodes) if true_heights is None else np.asarray(true_heights, float)
    if heights.shape != (n_nodes,) or not np.all(np.isfinite(heights)):
        raise NeuralMapError(
            f"repeat_survey: true_heights must be {n_nodes} finite values, got shape "
            f"{heights.shape}."
        )
    rng = np.random.default_rng(seed)
    n_batch = 1 if batch is None else int(batch)
    white = rng.standard_normal((n_batch, n_passes, n_nodes))
    if continuous:
        err = ar_filter(white.reshape(n_batch, -1), phi, axis=-1).reshape(white.shape)
    else:
        err = ar_filter(white, phi, axis=-1)
    err = sigma * err
    if batch is None:
        err = err[0]
    return RepeatSurvey(true_heights=heights, true_errors=err, measurements=heights + err)


def survey_recovery(
    *,
    n_trials: int = 100,
    phi: Sequence[float] = DEM_ERROR_AR1,
    n_nodes: int = 61,
    n_passes: int = 10,
    max_order: int = 2,
    seed: int = 0,
) -> dict[str, Any]:
    """Shows that identification recovers the DEM-making error model from repeat surveys.

    Simulates ``n_trials`` surveys, identifies each (orders up to ``max_order``), and
    summarises the AR(1) / AR(2) moment estimates, the chosen orders, and the full
    identification of the first survey.

    Args:
        n_trials: Independent surveys.
        phi: True AR coefficients of the measurement error.
        n_nodes: Nodes per line.
        n_passes: Passes.
        max_order: Largest identified order.
        seed: Seed.

    Returns:
        Plain dict: ``true_model``, ``ar1_phi_mean`` / ``ar1_phi_std``, ``ar2_phi_mean`` /
        ``ar2_phi_std``, ``arma11_mean`` / ``arma11_std`` (``[φ, θ]`` of ARMA(1,1)),
        ``sample_std_mean``, ``chosen_counts`` (order name → count),
        ``first`` (the `ErrorModelIdentification` of survey 0, as a dict) and
        ``first_result`` (the object itself).
    """
    survey = repeat_survey(
        n_nodes=n_nodes, n_passes=n_passes, phi=phi, batch=n_trials, seed=seed
    )
    samples = survey.errors
    ar1, ar2, arma11, chosen, stds = [], [], [], Counter(), []
    first: ErrorModelIdentification | None = None
    for i in range(n_trials):  # one identification per survey (not a hot path)
        result = identify_error_model(samples[i], max_order=max_order, diagnostics=i == 0)
        if first is None:
            first = result
        ar1.append(result.row(1, 0).model.phi)  # type: ignore[union-attr]
        if max_order >= 2:
            row = result.row(2, 0)
            if row.model is not None:
                ar2.append(row.model.phi)
        if any((r.p, r.q) == (1, 1) for r in result.rows):
            row = result.row(1, 1)
            if row.model is not None:
                arma11.append((*row.model.phi, *row.model.theta))
        chosen[result.chosen.name] += 1
        stds.append(result.std)
    assert first is not None
    ar1_arr, ar2_arr, arma_arr = np.asarray(ar1), np.asarray(ar2), np.asarray(arma11)
    true = ArmaModel(phi=tuple(phi), sigma2=1.0)
    return {
        "true_model": true.to_dict(),
        "n_trials": n_trials,
        "ar1_phi_mean": ar1_arr.mean(axis=0).tolist(),
        "ar1_phi_std": ar1_arr.std(axis=0).tolist(),
        "ar2_phi_mean": ar2_arr.mean(axis=0).tolist() if ar2_arr.size else None,
        "ar2_phi_std": ar2_arr.std(axis=0).tolist() if ar2_arr.size else None,
        "arma11_mean": arma_arr.mean(axis=0).tolist() if arma_arr.size else None,
        "arma11_std": arma_arr.std(axis=0).tolist() if arma_arr.size else None,
        "sample_std_mean": float(np.mean(stds)),
        "chosen_counts": dict(chosen),
        "first": first.to_dict(),
        "first_result": first,
    }
