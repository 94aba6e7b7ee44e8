"""The integrity section every TAN study writes: misleading fixes, hazards, availability,
and one Stanford diagram per method (`neuralmap.lab.integrity`, `neuralmap.viz.integrity`).
"""

from __future__ import annotations

import re
from typing import Any

from neuralmap.lab.integrity import integrity_metrics, scored_epochs
from neuralmap.outputs import RunCounts, StudyOutputs, verdict
from neuralmap.viz.integrity import plot_stanford

__all__ = ["INTEGRITY_NOTE", "add_integrity", "add_integrity_table", "add_stanford",
           "integrity_entry"]

#: How the section's figures are defined (the report's note).
INTEGRITY_NOTE = (
    "Misleading (MI): status tracking and horizontal error > HPL, over the tracking epochs "
    "(95 % Clopper-Pearson interval). Error > HPL, any status: over all epochs (a filter "
    "kept acquiring on gentle relief has no tracking epoch, but its HPL must hold). "
    "Hazardous: error > alert limit while HPL ≤ alert "
    "limit, over all epochs. Available: HPL ≤ alert limit, over all epochs. Diverged runs "
    "flagged first: of the runs counted as diverged, those not tracking at the first epoch "
    "their error exceeded the HPL (or never exceeding it). Every epoch "
    "after the prior of every included run; HPL from the method's own posterior (a "
    "point-mass lattice's mass, an EKF's covariance) at each integrity risk.")


def _fmt_flagged(entry: dict[str, Any] | None) -> str:
    if entry is None:
        return "n/a"
    return f"{entry['flagged']} of {entry['runs']}"


def _fmt_rate(entry: dict[str, Any]) -> str:
    if entry["rate"] is None:
        return "n/a (0 epochs)"
    lo, hi = entry["ci95"]
    return f"{entry['rate']:.2e} [{lo:.1e}, {hi:.1e}] ({entry['count']}/{entry['epochs']})"


def add_stanford(outputs: StudyOutputs, name: str, run: Any, *, alert_limit_m: float,
                 prefix: str = "") -> None:
    """The Stanford diagram of one method's flight (at its largest risk: the smallest HPL,
    the harder diagram), as a PNG in the report and in TensorBoard."""
    err, _, included = scored_epochs(run)
    risk = max(run.protection)
    hpl = run.protection[risk][:, 1:].detach().cpu().double()[included].numpy()
    fig = plot_stanford(err[included].numpy(), hpl, alert_limit_m=alert_limit_m, risk=risk,
                        title=f"{prefix}{name}: error against HPL (risk {risk:g})")
    key = re.sub(r"[^A-Za-z0-9.]+", "_", f"stanford {prefix}{name}").strip("_")
    outputs.add_figure(key, fig, f"Stanford diagram of {prefix}{name}: horizontal error "
                       f"against HPL at risk {risk:g}, alert limit {alert_limit_m:g} m")


def add_integrity_table(outputs: StudyOutputs, table: dict[str, Any], *, alert_limit_m: float,
                        targets: tuple[str, ...] = (), prefix: str = "") -> None:
    """The integrity table of methods' `integrity_metrics` and the toolkit's claim "MI rate
    ≤ the integrity risk" for the methods in ``targets``."""
    rows = [[name, risk, _fmt_rate(e["misleading"]), _fmt_rate(e["exceeded"]),
             _fmt_rate(e["hazardous"]), _fmt_rate(e["available"]),
             f"{e['hpl_median_m']:.1f}" if e["hpl_median_m"] else "n/a",
             _fmt_flagged(e.get("diverged_flagged"))]
            for name, metrics in table.items() for risk, e in metrics["risks"].items()]
    if not rows:
        return
    outputs.add_table(
        f"{prefix}Integrity at alert limit {alert_limit_m:g} m",
        ["method", "risk", "misleading rate [95 % CI] (count/epochs)",
         "error > HPL, any status", "hazardous rate", "availability", "HPL median [m]",
         "diverged runs flagged first"],
        rows, note=INTEGRITY_NOTE)
    for name in targets:
        if name not in table:
            continue
        runs = table[name].get("runs")
        for risk, entry in table[name]["risks"].items():
            mi = entry["misleading"]
            outputs.add_claim(
                "toolkit target", f"{prefix}{name}: misleading-information rate ≤ the "
                f"integrity risk {risk} ({'≥' if mi['epochs'] >= 100_000 else '<'} 100 000 "
                "tracking epochs)", _fmt_rate(mi), verdict(entry["within_risk"]),
                runs=None if runs is None else RunCounts(runs, runs),
                detail="MI over the tracking epochs; Clopper-Pearson 95 % interval")
        flagged = [(risk, e["diverged_flagged"]) for risk, e in table[name]["risks"].items()
                   if e.get("diverged_flagged") is not None]
        if flagged:
            # the largest risk: the smallest HPL, the harder test
            risk, entry = max(flagged, key=lambda item: float(item[0]))
            outputs.add_claim(
                "toolkit target", f"{prefix}{name}: every diverged run says so (status or "
                f"HPL at risk {risk}) before its error leaves its HPL",
                f"{_fmt_flagged(entry)} diverged runs flagged first",
                verdict(entry["flagged"] == entry["runs"]),
                detail="status not tracking at the first epoch with error > HPL, or never "
                       "error > HPL")


def integrity_entry(run: Any, *, alert_limit_m: float,
                    diverged: Any = None) -> dict[str, Any] | None:
    """`integrity_metrics` of a run with the number of runs it rests on (None for a run
    that carries no protection levels); ``diverged`` ``(N,)`` bool or None."""
    if run.status is None or not run.protection:
        return None
    metrics = integrity_metrics(run, alert_limit_m=alert_limit_m, diverged=diverged)
    metrics["runs"] = int(scored_epochs(run)[2].sum())
    return metrics


def add_integrity(outputs: StudyOutputs, runs: dict[str, Any], *, alert_limit_m: float,
                  targets: tuple[str, ...] = (), prefix: str = "",
                  diverged: dict[str, Any] | None = None) -> dict[str, Any]:
    """Every method's integrity (`integrity_entry`), the table, the Stanford diagrams and
    the claims for ``targets`` (`add_integrity_table`).

    Args:
        outputs: The study's writer.
        runs: Method → `neuralmap.lab.monte_carlo.FilterRun` (flown through the Navigator).
        alert_limit_m: Horizontal alert limit, m.
        targets: Methods held to the target "MI rate ≤ the integrity risk at every risk".
        prefix: Figure-name and table-title prefix (e.g. ``"sigma300 "``).
        diverged: Method → ``(N,)`` bool, its runs counted as diverged (for the "flagged
            first" column and claim), or None.

    Returns:
        Method → its metrics (for results.json).
    """
    diverged = diverged or {}
    table = {name: entry for name, run in runs.items()
             if (entry := integrity_entry(run, alert_limit_m=alert_limit_m,
                                          diverged=diverged.get(name))) is not None}
    add_integrity_table(outputs, table, alert_limit_m=alert_limit_m, targets=targets,
                        prefix=prefix)
    for name in table:
        add_stanford(outputs, name, runs[name], alert_limit_m=alert_limit_m, prefix=prefix)
    return table
