"""The stochastic-linearisation error ``m2`` and a Table 2-style summary of error sequences.

SEEDS 000, eq. 11: ``h_t(x̂, ŷ) = f(x̂, ŷ) + m2``: ``m2`` is the true terrain minus the fitted
plane, both at the filter's estimate ``(x̂, ŷ)`` (the method-related error; ``m1``, at the true
position, has the same nature). Sampled once per filter period along Monte Carlo flights it
forms the sequences whose standard deviation the paper tabulates (Table 2) and whose models
it identifies (fixed regions: stationary AR(1)/AR(2); adaptive region: non-stationary,
shrinking).
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np
import torch

from neuralmap.errors.identification import identify_error_model, minimum_length
from neuralmap.exceptions import NeuralMapError

#: Points per linearizer call (bounds memory for region fits and neural maps).
CHUNK = 65536


def linearization_error(
    linearizer: Any,
    true_terrain: Any,
    xy: torch.Tensor,
    *,
    pos_cov: torch.Tensor | None = None,
) -> torch.Tensor:
    """``m2 = h_t(x̂, ŷ) − f(x̂, ŷ)`` at a batch of estimates (SEEDS 000, eq. 11).

    Args:
        linearizer: A linearisation method (``forward(xy (M, 2), pos_cov (M, 2, 2)) ->
            Linearization``; its ``height`` is the fitted plane at ``xy``).
        true_terrain: The true terrain (``forward(xy (..., 2)) -> heights (...)``), e.g. a
            bicubic :class:`~neuralmap.terrain.GridTerrain` of the true tile.
        xy: ``(..., 2)`` horizontal estimates ``(x̂, ŷ)``, m (e.g. the filter's ``p_hat``
            per step, ``(N, K, 2)``).
        pos_cov: ``(..., 2, 2)`` horizontal covariance at each estimate (the adaptive
            region Ω_adp uses it), or None.

    Returns:
        ``(...)`` tensor of ``m2`` in metres (dtype of ``xy``); NaN where a map returns NaN.
    """
    if not isinstance(xy, torch.Tensor) or xy.ndim < 1 or xy.shape[-1] != 2:
        raise NeuralMapError(
            f"linearization_error: xy must be a (..., 2) tensor of estimates, got "
            f"{tuple(getattr(xy, 'shape', ()))}."
        )
    lead = xy.shape[:-1]
    flat = xy.reshape(-1, 2)
    cov = None
    if pos_cov is not None:
        if tuple(pos_cov.shape) != (*lead, 2, 2):
            raise NeuralMapError(
                f"linearization_error: pos_cov must have shape {(*lead, 2, 2)} to match xy, "
                f"got {tuple(pos_cov.shape)}."
            )
        cov = pos_cov.reshape(-1, 2, 2)
    out = []
    with torch.no_grad():
        for start in range(0, flat.shape[0], CHUNK):
            part = flat[start : start + CHUNK]
            lin = linearizer(part, None if cov is None else cov[start : start + CHUNK])
            truth = true_terrain(part)
            out.append(truth.to(xy.dtype) - lin.height.to(xy.dtype))
    return torch.cat(out).reshape(lead)


def summarise_error_sequences(
    sequences: Any,
    *,
    max_order: int = 2,
    n_identify: int = 20,
    skip: int = 0,
) -> dict[str, Any]:
    """One Table 2 cell: the spread of error sequences, their stationarity and model.

    Args:
        sequences: ``(N, K)`` error sequences (e.g. ``m2`` along N flights of K steps);
            non-finite samples (off-map steps) are dropped from each sequence.
        max_order: Largest ARMA order identified.
        n_identify: Identify at most this many sequences (the first ones long enough).
        skip: Leading samples dropped from each sequence before identification (e.g. the
            convergence transient); the std is over all finite samples.

    Returns:
        Plain dict: ``std`` and ``mean`` over all finite samples (m), ``n_sequences``,
        ``n_identified``, ``stationary_fraction`` (run test and ADF both accept),
        ``chosen_counts`` (model name → count), ``ar1_phi_median``, ``sigma_a_median``
        (square root of the chosen models' innovation variance), and ``first`` (the
        identification of the first identified sequence, as a dict, or None).
    """
    arr = np.asarray(
        sequences.detach().cpu().numpy() if hasattr(sequences, "detach") else sequences,
        dtype=np.float64,
    )
    if arr.ndim == 1:
        arr = arr[None]
    if arr.ndim != 2:
        raise NeuralMapError(
            f"summarise_error_sequences: sequences must be (N, K), got shape {arr.shape}."
        )
    finite = arr[np.isfinite(arr)]
    if finite.size == 0:
        raise NeuralMapError(
            "summarise_error_sequences: no finite samples (every step off the map?)."
        )
    need = minimum_length(max_order, max_order)
    chosen: Counter[str] = Counter()
    stationary, phis, sigmas = [], [], []
    first = None
    for row in arr:  # one identification per sequence (not a hot path)
        seq = row[skip:][np.isfinite(row[skip:])]
        if len(stationary) >= n_identify or seq.size < need or np.ptp(seq) == 0.0:
            continue
        result = identify_error_model(seq, max_order=max_order)
        if first is None:
            first = result.to_dict()
        assert result.stationarity is not None
        stationary.append(result.stationarity.stationary)
        chosen[result.chosen.name] += 1
        ar1 = result.row(1, 0).model
        if ar1 is not None:
            phis.append(ar1.phi[0])
        sigmas.append(float(np.sqrt(result.chosen.sigma2)))
    return {
        "std": float(finite.std()),
        "mean": float(finite.mean()),
        "n_sequences": int(arr.shape[0]),
        "n_identified": len(stationary),
        "stationary_fraction": float(np.mean(stationary)) if stationary else None,
        "chosen_counts": dict(chosen),
        "ar1_phi_median": float(np.median(phis)) if phis else None,
        "sigma_a_median": float(np.median(sigmas)) if sigmas else None,
        "first": first,
    }
