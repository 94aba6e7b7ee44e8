"""Integrity of a Monte Carlo flight: misleading fixes, hazards and availability.

Aviation's integrity statistics (the SBAS vocabulary of `neuralmap.nav.integrity`), counted
over every scored epoch of every included run (epoch 0, the prior, excluded), per integrity
risk the flight's protection levels were computed at:

* **misleading information** (MI): the navigator says ``tracking`` and the horizontal error
  exceeds the HPL — rate over the tracking epochs, with its Clopper-Pearson 95 % interval
  (`scipy.stats.binomtest`); a consistent navigator has a rate at most the risk;
* **hazardously misleading** (HMI): the error exceeds the alert limit while the HPL is
  within it — rate over all epochs;
* **availability**: the share of epochs whose HPL is within the alert limit;
* **error beyond HPL** at any status: the rate over all epochs (a filter that never says
  ``tracking`` — gentle relief keeps it ``acquiring`` — still has an HPL that must hold);
* **diverged runs flagged first**: of the runs the study's divergence rule counts as
  diverged, those that said so before their error left their HPL — at the first epoch whose
  error exceeds the HPL the status is not ``tracking`` (``acquiring`` or ``lost``), or the
  error never exceeds it. A silent divergence is a run still ``tracking`` at that epoch.

The Stanford diagram (`neuralmap.viz.integrity.plot_stanford`) draws the same epochs as a
2-D histogram of error against HPL.
"""

from __future__ import annotations

from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError

__all__ = ["integrity_metrics", "scored_epochs"]


def scored_epochs(run: Any) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(error, status, included)``: the horizontal error norm ``(N, K)``, the status codes
    ``(N, K)`` of epochs 1…K, and the runs the metrics keep ``(N,)`` (the truth stayed on
    the map, the filter finite)."""
    err = run.err[:, 1:, :2].detach().to("cpu", torch.float64).norm(dim=-1)
    status = run.status[:, 1:].detach().cpu()
    included = (~run.off_map.detach().cpu()) & torch.isfinite(err).all(1)
    return err, status, included


def _rate(k: int, n: int) -> dict[str, Any]:
    """A rate with its Clopper-Pearson 95 % interval (None without epochs)."""
    if n == 0:
        return {"count": k, "epochs": n, "rate": None, "ci95": None}
    from scipy.stats import binomtest

    ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="exact")
    return {"count": k, "epochs": n, "rate": k / n, "ci95": [float(ci.low), float(ci.high)]}


def _flagged_first(err: torch.Tensor, hpl: torch.Tensor, tracking: torch.Tensor
                   ) -> torch.Tensor:
    """``(N,)`` bool: at the first epoch whose error exceeds the HPL the status is not
    tracking, or no epoch exceeds it (``err``, ``hpl``, ``tracking`` ``(N, K)``)."""
    over = err > hpl
    k = over.shape[1]
    steps = torch.arange(k).expand_as(over)
    first = torch.where(over, steps, k).amin(1)  # K: never exceeded
    tracking_then = tracking.gather(1, first.clamp_max(k - 1)[:, None])[:, 0]
    return (first == k) | ~tracking_then


def integrity_metrics(run: Any, *, alert_limit_m: float,
                      diverged: Any = None) -> dict[str, Any]:
    """Misleading, hazardous and available epochs of a flight, per integrity risk.

    Args:
        run: A `neuralmap.lab.monte_carlo.FilterRun` with ``status`` and ``protection``
            (risk → ``(N, K+1)`` HPL, m).
        alert_limit_m: Horizontal alert limit, m.
        diverged: ``(N,)`` bool, the runs the study's divergence rule counts as diverged
            (`neuralmap.lab.metrics.navigation_metrics`' ``diverged``), or None.

    Returns:
        ``{"alert_limit_m", "risks": {risk: {"misleading", "exceeded", "hazardous",
        "available", "hpl_median_m", "within_risk", "diverged_flagged"}}}`` where each of
        the four is ``{"count", "epochs", "rate", "ci95"}``, ``within_risk`` says whether the
        MI rate is at most the risk (None without tracking epochs) and
        ``diverged_flagged`` is ``{"runs", "flagged"}`` over the included diverged runs
        (None without ``diverged``).

    Raises:
        NeuralMapError: The run has no status or protection levels, or a bad alert limit.
    """
    if run.status is None or not getattr(run, "protection", None):
        raise NeuralMapError("integrity_metrics: the run carries no status or protection "
                             "levels; fly it through the Navigator (neuralmap.lab.fly).")
    if not alert_limit_m > 0:
        raise NeuralMapError(f"integrity_metrics: alert_limit_m must be > 0 m, got "
                             f"{alert_limit_m!r}.")
    from neuralmap.nav.fix import STATUS_CODE

    err, status, included = scored_epochs(run)
    div = None
    if diverged is not None:
        div = torch.as_tensor(diverged, dtype=torch.bool).reshape(-1).cpu()
        if div.numel() != included.numel():
            raise NeuralMapError(f"integrity_metrics: diverged has {div.numel()} runs, the "
                                 f"flight {included.numel()}.")
        div = div[included]
    err, status = err[included], status[included]
    tracking = status == STATUS_CODE["tracking"]
    out: dict[str, Any] = {"alert_limit_m": float(alert_limit_m), "risks": {}}
    for risk, hpl_all in run.protection.items():
        hpl = hpl_all[:, 1:].detach().to("cpu", torch.float64)[included]
        within = hpl <= alert_limit_m
        mi = _rate(int((tracking & (err > hpl)).sum()), int(tracking.sum()))
        entry = {
            "misleading": mi,
            "exceeded": _rate(int((err > hpl).sum()), err.numel()),
            "hazardous": _rate(int(((err > alert_limit_m) & within).sum()), err.numel()),
            "available": _rate(int(within.sum()), err.numel()),
            "hpl_median_m": float(hpl.median()) if hpl.numel() else None,
            "within_risk": None if mi["rate"] is None else bool(mi["rate"] <= risk),
            "diverged_flagged": None if div is None else {
                "runs": int(div.sum()),
                "flagged": int(_flagged_first(err[div], hpl[div], tracking[div]).sum())},
        }
        out["risks"][f"{risk:g}"] = entry
    return out
