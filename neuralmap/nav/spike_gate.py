"""Altimeter spike gate of a point-mass grid: a clearance whose predictive NIS is past
``χ²₁(p)`` is not used.

The predictive density of the measurement ``y = g(s) + a + e`` under the grid's predicted
mixture (masses ``w``, per-cell altitude-error mean ``a`` and common variance ``v_a``) has,
over the cells on the map,

    ŷ = Σ w (g + a),   S_y = Σ w (g + a − ŷ)² + v_a + R,   NIS = (y − ŷ)² / S_y,

the NIS the navigator's tracker gates on (`neuralmap.nav.navigator`,
``integrity.spike_gate_prob``). One consistent NIS exceeds ``χ²₁(p)`` with probability
``1 − p``; a spike of tens of metres exceeds it by far. A gated run is predicted only at
that epoch (its grid keeps the prior masses), so a spike during acquisition cannot move the
mass to a wrong terrain match.
"""

from __future__ import annotations

import functools

import torch

__all__ = ["predictive_nis", "spike_gate_threshold", "spiked"]


@functools.lru_cache(maxsize=16)
def spike_gate_threshold(prob: float) -> float:
    """``χ²₁(prob)`` (``inf`` for ``prob`` 0: the gate off)."""
    if prob <= 0.0:
        return float("inf")
    from neuralmap.nav.metrics import chi2_quantile

    return chi2_quantile(prob, 1)


def predictive_nis(y: torch.Tensor, w: torch.Tensor, g: torch.Tensor, a: torch.Tensor,
                   v_a: torch.Tensor, R: float | torch.Tensor) -> torch.Tensor:
    """``(N,)`` NIS of ``y`` against the predicted grid mixture (module docstring).

    Args:
        y: ``(N,)`` measurements ``h_ins − h_radar`` (NaN: no measurement, NIS NaN).
        w: ``(N, G, G)`` predicted cell masses (sum 1).
        g: ``(N, G, G)`` map heights at the cells (NaN off the map: the sums run over the
            cells on it, masses renormalised).
        a: ``(N, G, G)`` per-cell mean of the altitude error.
        v_a: ``(N,)`` its conditional variance.
        R: Measurement variance, m² (float or ``(N,)``).

    Returns:
        ``(N,)`` NIS (NaN where ``y`` is NaN or no cell is on the map).
    """
    yc = g + a
    ok = torch.isfinite(yc)
    wk = torch.where(ok, w, 0.0)
    mass = wk.sum((1, 2))
    yc = torch.where(ok, yc, 0.0)
    yhat = (wk * yc).sum((1, 2)) / mass  # ŷ = Σ w (g + a)
    spread = (wk * (yc - yhat[:, None, None]) ** 2).sum((1, 2)) / mass
    s_y = spread + v_a + R  # S_y = Σ w (g + a − ŷ)² + v_a + R
    nis = (y - yhat) ** 2 / s_y
    return torch.where(mass > 0, nis, float("nan"))


def spiked(nis: torch.Tensor, prob: float) -> torch.Tensor:
    """``(N,)`` bool: the NIS is past the gate ``χ²₁(prob)`` (False for NaN or the gate off)."""
    return torch.isfinite(nis) & (nis > spike_gate_threshold(prob))
