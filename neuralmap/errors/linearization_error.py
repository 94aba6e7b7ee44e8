"""The stochastic-linearisation error and a Table 2-style summary of error sequences.

SEEDS 000, eqs. 9–12: with the estimate ``p̂ = (x̂, ŷ)``, the truth ``p`` and the method's
height ``f(p̂)`` and slope ``∇f``, the altimeter measurement is
``z = H δX + (linearisation error) − m_d − m_r`` where the linearisation error is

    e_lin = h(p) − f(p̂) − ∇f · (p − p̂)         (the part of z that H δX does not explain).

The paper splits it into ``m2 = h(p̂) − f(p̂)`` (eq. 11, at the estimate) and the error at the
true position ``m1``. The toolkit's linearisation methods return the map look-up at the
estimate as ``f(p̂)`` (SEEDS 000 eq. 5) and the plane only for the slope, so ``m2`` here is the
look-up's interpolation error and the region's size acts through the slope term;
`linearization_error` gives ``m2`` or, with the true positions, ``e_lin``. Sampled once
per filter period along Monte Carlo flights they form the sequences whose standard deviation
the paper tabulates (Table 2) and whose models it identifies (fixed regions: stationary
AR(1)/AR(2); adaptive region: non-stationary, shrinking).
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
    true_xy: torch.Tensor | None = None,
) -> torch.Tensor:
    """Linearisation error at a batch of estimates (SEEDS 000, eqs. 11–12).

    Without ``true_xy``: ``m2 = h(p̂) − f(p̂)`` (eq. 11). With it: the whole linearisation
    error of the measurement ``e_lin = h(p) − f(p̂) − ∇f · (p − p̂)`` (module docstring).

    Args:
        linearizer: A linearisation method (``forward(xy (M, 2), pos_cov (M, 2, 2)) ->
            Linearization``: ``height`` = ``f(p̂)``, ``slope`` = ``∇f``).
        true_terrain: The reference surface ``h`` (``forward(xy (..., 2)) -> heights``),
            e.g. a bicubic `GridTerrain` of the DEM (to isolate
            the linearisation from the DEM-making error) or of the truth.
        xy: ``(..., 2)`` horizontal estimates ``p̂``, m (e.g. ``(N, K, 2)`` per run and step).
        pos_cov: ``(..., 2, 2)`` horizontal covariance at each estimate (the adaptive
            region Ω_adp uses it), or None.
        true_xy: ``(..., 2)`` true positions ``p``, or None for ``m2``.

    Returns:
        ``(...)`` tensor in metres (dtype of ``xy``); NaN where a map returns NaN.
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
    truth_flat = None
    if true_xy is not None:
        if tuple(true_xy.shape) != tuple(xy.shape):
            raise NeuralMapError(
                f"linearization_error: true_xy must have the shape of xy {tuple(xy.shape)}, "
                f"got {tuple(true_xy.shape)}."
            )
        truth_flat = true_xy.reshape(-1, 2).to(xy.dtype)
    out = []
    with torch.no_grad():
        for start in range(0, flat.shape[0], CHUNK):
            part = flat[start : start + CHUNK]
            lin = linearizer(part, None if cov is None else cov[start : start + CHUNK])
            if truth_flat is None:
                out.append(true_terrain(part).to(xy.dtype) - lin.height.to(xy.dtype))
                continue
            true_part = truth_flat[start : start + CHUNK]
            step = ((true_part - part) * lin.slope.to(xy.dtype)).sum(dim=-1)
            out.append(true_terrain(true_part).to(xy.dtype) - lin.height.to(xy.dtype) - step)
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
