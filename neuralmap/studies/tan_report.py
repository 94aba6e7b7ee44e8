"""The TAN study's results: ``results.json``, ``report.md``, console table, claims check.

The evaluation front end (``evaluate.py``) collects one metrics dict per linearisation
method (`neuralmap.lab.metrics.navigation_metrics`), the posterior Cramér-Rao bound
and the run configuration; this module turns them into the files a user reads. It knows
nothing about filters or maps: every input is plain numbers, lists and dicts.

The claims check compares the measured numbers with paper 004's statements (SEEDS 004,
"Claims"): position error < 50 m (1σ), velocity error < 5 m/s (1σ), the neural map about
25 m (1σ) better than the classical linearisations; and with the toolkit's accuracy targets
(neural RMSE over all runs within 1.5× the PCRB, divergence ≤ 2 %). A verdict needs a
minimum number of converged runs per method (the shared rule of
`neuralmap.outputs.verdict`); below it the claim reads "not enough converged
runs (n of N)". Numerical failures count against every claim (as not converged, and as
failed runs in the divergence target).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from neuralmap.exceptions import NeuralMapError
from neuralmap.linearize.factory import METHODS as LINEARIZER_METHODS
from neuralmap.linearize.factory import method_label
from neuralmap.outputs import (
    MIN_CONVERGED,
    NOT_MEASURED,
    RunCounts,
    verdict,
)

#: Per-method keys that every results.json carries.
METHOD_KEYS: tuple[str, ...] = (
    "rmse_pos_m",
    "rmse_pos_converged_m",
    "rmse_vel_mps",
    "sigma_pos_m",
    "divergence_rate",
    "numerical_failure_rate",
    "nees_in_band",
    "nees_time_avg",
    "pcrb_ratio_all",
    "pcrb_ratio_converged",
)

#: Per-method count keys (integers).
COUNT_KEYS: tuple[str, ...] = ("n_runs", "n_off_map", "n_diverged")

#: Per-method curve keys (lists over the time steps), kept under ``curves`` in results.json.
CURVE_KEYS: tuple[str, ...] = (
    "rmse_pos_curve",
    "rmse_pos_converged_curve",
    "rmse_vel_curve",
    "nees_curve",
)

#: Per-method keys of the metrics dict that are not copied into results.json (per-run
#: lists; the rule is stored once at the top level).
_SKIPPED_KEYS: tuple[str, ...] = ("diverged", "divergence_rule")

#: The method that carries the neural map (the subject of paper 004's claims).
NEURAL_METHOD = "neural"

#: Sources of the claims (the report's "paper" column).
SEEDS_004 = "SEEDS 004"
TOOLKIT_TARGET = "toolkit target"

# Columns of the console and markdown tables: (key, header, format).
_TABLE_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("rmse_pos_m", "RMSE pos all [m]", "{:.1f}"),
    ("rmse_pos_converged_m", "RMSE pos conv [m]", "{:.1f}"),
    ("sigma_pos_m", "1σ pos conv [m]", "{:.1f}"),
    ("rmse_vel_mps", "RMSE vel [m/s]", "{:.2f}"),
    ("sigma_vel_mps", "1σ vel conv [m/s]", "{:.2f}"),
    ("final_pos_m", "final pos [m]", "{:.1f}"),
    ("pcrb_ratio_all", "RMSE/PCRB all", "{:.2f}"),
    ("pcrb_ratio_converged", "RMSE/PCRB conv", "{:.2f}"),
    ("pcrb_map_ratio_all", "RMSE/map PCRB", "{:.2f}"),
    ("divergence_rate", "diverged", "{:.1%}"),
    ("numerical_failure_rate", "num. failed", "{:.1%}"),
    ("nees_time_avg", "NEES time-avg", "{:.2f}"),
    ("nees_in_band", "NEES in band (conv)", "{:.1%}"),
    ("n_off_map", "off-map", "{:d}"),
)


@dataclass(frozen=True)
class ClaimCheck:
    """One claim or target compared with the measured numbers.

    Attributes:
        claim: The statement being checked (with its source).
        measured: The measured value(s), as text with units.
        verdict: A verdict of `neuralmap.outputs.VERDICTS`.
        detail: How the verdict was reached (the rule), and caveats.
        paper: The claim's source, the report's "paper" column (``"SEEDS 004"`` or
            ``"toolkit target"``); the claim text does not repeat it.
    """

    claim: str
    measured: str
    verdict: str
    detail: str
    paper: str = TOOLKIT_TARGET


def _last_half_rms(curve: Sequence[float]) -> float:
    """Root mean square of the finite values of the last half of a curve (NaN when none).

    The same time average as `neuralmap.lab.metrics.navigation_metrics` uses for the
    PCRB (samples ``(K+1)//2 … K``).
    """
    values = np.asarray(curve, dtype=np.float64)
    values = values[len(values) // 2 :]
    values = values[np.isfinite(values)]
    return float(np.sqrt((values**2).mean())) if values.size else float("nan")


def build_results(
    *,
    method_metrics: Mapping[str, Mapping[str, Any]],
    t: Sequence[float],
    pcrb_pos: Sequence[float],
    divergence_rule: str,
    config: Mapping[str, Any],
    scenario: Mapping[str, Any] | None = None,
    map_info: Mapping[str, Any] | None = None,
    off_map: Mapping[str, Any] | None = None,
    timing_s: Mapping[str, float] | None = None,
    truth_model: Mapping[str, Any] | None = None,
    pcrb_kind: str = "bound",
) -> dict[str, Any]:
    """Assembles the ``results.json`` structure.

    Args:
        method_metrics: Method name -> metrics dict from
            `neuralmap.lab.metrics.navigation_metrics` (must hold `METHOD_KEYS`;
            curves and counts are kept when present).
        t: ``(K+1,)`` time stamps in seconds.
        pcrb_pos: ``(K+1,)`` horizontal position PCRB in metres
            (`neuralmap.lab.pcrb.pcrb_position`).
        divergence_rule: The divergence rule text (``neuralmap.lab.metrics.DIVERGENCE_RULE``).
        config: The evaluation configuration (JSON-serialisable).
        scenario: The scenario's fields.
        map_info: Map file, tile name and fingerprint, parameter count, ...
        off_map: Off-map counts (e.g. ``{"truth": n, "per_method": {...}}``).
        timing_s: Wall-clock seconds per stage.
        truth_model: How the truth terrain was made (``TrueTerrain.summary()``).
        pcrb_kind: ``"bound"``, or ``"reference"`` for a fixed initial error (the Bayesian
            PCRB then bounds nothing and is shown as a reference curve).

    Returns:
        A dict with ``methods`` (name -> the `METHOD_KEYS` plus counts and
        ``final_pos_m``), ``curves`` (``t``, ``pcrb_pos_m`` and per-method curves),
        ``pcrb_pos_m`` (RMS over the last half), ``pcrb_pos_final_m``,
        ``divergence_rule``, ``config``, ``scenario``, ``map``, ``off_map``, ``timing_s``.

    Raises:
        NeuralMapError: When a method lacks one of `METHOD_KEYS` or the curves do
            not match ``t``.
    """
    if not method_metrics:
        raise NeuralMapError("build_results: no methods were evaluated; pass at least one.")
    n_steps = len(t)
    if len(pcrb_pos) != n_steps:
        raise NeuralMapError(
            f"build_results: pcrb_pos has {len(pcrb_pos)} values but t has {n_steps}; "
            "both must cover the same time steps."
        )
    methods: dict[str, dict[str, Any]] = {}
    curves: dict[str, Any] = {
        "t": [float(v) for v in t],
        "pcrb_pos_m": [float(v) for v in pcrb_pos],
    }
    for name, metrics in method_metrics.items():
        missing = [key for key in METHOD_KEYS if key not in metrics]
        if missing:
            raise NeuralMapError(
                f"build_results: metrics of method '{name}' lack {missing}; "
                "compute them with neuralmap.lab.metrics.navigation_metrics."
            )
        entry: dict[str, Any] = {"label": method_label(name)}
        for key, value in metrics.items():
            if key in _SKIPPED_KEYS:
                continue
            if key in CURVE_KEYS:
                if len(value) != n_steps:
                    raise NeuralMapError(
                        f"build_results: curve '{key}' of method '{name}' has {len(value)} "
                        f"values, expected {n_steps} (one per time step)."
                    )
                curves.setdefault(name, {})[key] = [None if v is None else float(v) for v in value]
            elif isinstance(value, (bool, int, float, str, np.integer, np.floating)) or (
                value is None
            ):
                entry[key] = value
            elif hasattr(value, "numel") and value.numel() == 1:
                entry[key] = value.item()
            elif isinstance(value, (list, tuple)) and len(value) <= 8:
                entry[key] = list(value)  # small vectors such as the NEES band
        methods[name] = entry
    return {
        "methods": methods,
        "pcrb_pos_m": _last_half_rms(pcrb_pos),
        "pcrb_pos_final_m": float(pcrb_pos[-1]),
        "divergence_rule": divergence_rule,
        "config": dict(config),
        "scenario": dict(scenario or {}),
        "map": dict(map_info or {}),
        "off_map": dict(off_map or {}),
        "timing_s": dict(timing_s or {}),
        "truth_model": dict(truth_model or {}),
        "pcrb_kind": pcrb_kind,
        "curves": curves,
    }


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and math.isfinite(value)


def _fmt(value: Any, spec: str) -> str:
    """Formats a metric; non-finite or missing values print as ``n/a``."""
    if not _finite(value):
        return "n/a"
    if spec == "{:d}":
        return f"{int(value):d}"
    return spec.format(float(value))


def check_claims(
    results: Mapping[str, Any],
    *,
    neural_method: str = NEURAL_METHOD,
    pos_limit_m: float = 50.0,
    vel_limit_mps: float = 5.0,
    improvement_m: float = 25.0,
    pcrb_ratio_target: float = 1.5,
    divergence_target: float = 0.02,
    min_converged: int = MIN_CONVERGED,
) -> list[ClaimCheck]:
    """Compares the measured numbers with paper 004's claims and the issue's targets.

    Rules (all on the neural method unless stated):

    * position < ``pos_limit_m`` (1σ): the 1σ of the converged horizontal error
      (``sigma_pos_m``, SEEDS 004 "Claims") is below the limit;
    * velocity < ``vel_limit_mps`` (1σ): ``sigma_vel_mps`` when the metrics provide it,
      else ``rmse_vel_mps`` (an upper bound of the 1σ);
    * ≈ ``improvement_m`` better than classical: Δ = σ_classical − σ_neural per classical
      method (every registered linearisation method whose name does not start with ``neural``); "holds" when the neural map beats every classical method and the mean Δ is
      at least half the claimed improvement, "partly" when the mean Δ is at least a fifth
      of it, "does not hold" otherwise;
    * RMSE over all runs / PCRB ≤ ``pcrb_ratio_target`` and divergence ≤
      ``divergence_target`` (the toolkit's accuracy targets).

    A claim that compares 1σ figures needs, for every method it uses, at least
    ``min_converged`` converged runs and half of its on-map runs converged; otherwise its
    verdict is "not enough converged runs (n of N)" and methods without enough converged
    runs are named, never silently dropped.

    Args:
        results: The structure from `build_results`.
        neural_method: Name of the neural-map method.
        pos_limit_m: Claimed 1σ position bound, metres.
        vel_limit_mps: Claimed 1σ velocity bound, m/s.
        improvement_m: Claimed improvement over the classical linearisations, metres.
        pcrb_ratio_target: Target all-run RMSE / PCRB ratio.
        divergence_target: Target divergence rate (fraction).
        min_converged: Minimum converged runs for a 1σ-based verdict.

    Returns:
        One `ClaimCheck` per claim/target, in the order above.
    """
    methods: Mapping[str, Mapping[str, Any]] = results["methods"]
    neural = methods.get(neural_method)
    pos_claim = f"{neural_method}: position error < {pos_limit_m:g} m (1σ)"
    vel_claim = f"{neural_method}: velocity error < {vel_limit_mps:g} m/s (1σ)"
    better_claim = (f"{neural_method} ≈ {improvement_m:g} m (1σ) better than the classical "
                    "linearisations")
    if neural is None:
        reason = f"method '{neural_method}' was not evaluated (add it to --methods)"
        claims = [(pos_claim, SEEDS_004), (vel_claim, SEEDS_004), (better_claim, SEEDS_004),
                  (_ratio_claim(neural_method, pcrb_ratio_target), TOOLKIT_TARGET),
                  (_divergence_claim(neural_method, divergence_target), TOOLKIT_TARGET)]
        return [ClaimCheck(c, "n/a", NOT_MEASURED, reason, paper) for c, paper in claims]

    checks: list[ClaimCheck] = []

    def enough(entry: Mapping[str, Any]) -> bool:
        return RunCounts.from_metrics(entry).enough(min_converged)

    def too_few(name: str, entry: Mapping[str, Any]) -> str:
        text = RunCounts.from_metrics(entry).too_few(min_converged)
        return text.replace("(", f"({name}: ", 1)

    sigma = neural.get("sigma_pos_m")
    if not enough(neural):
        sigma = None
        few = too_few(neural_method, neural)
        for claim in (pos_claim, vel_claim, better_claim):
            checks.append(ClaimCheck(claim, "n/a", few, "1σ over the converged runs only",
                                     SEEDS_004))
        return checks + _target_checks(neural, pcrb_ratio_target, divergence_target,
                                       min_converged, neural_method)
    checks.append(
        ClaimCheck(
            claim=pos_claim,
            measured=f"1σ = {_fmt(sigma, '{:.1f}')} m",
            verdict=verdict(sigma < pos_limit_m if _finite(sigma) else None),
            detail="1σ of the horizontal error of the non-diverged runs "
            f"({neural.get('n_converged', 'n/a')} of {neural.get('n_included', 'n/a')} on-map "
            "runs), last half of the flight"
            + ("" if _finite(sigma) else "; no converged run to measure"),
            paper=SEEDS_004,
        )
    )

    if _finite(neural.get("sigma_vel_mps")):
        vel, vel_what = (neural["sigma_vel_mps"], "1σ of the velocity error of the converged "
                         "runs (table column \"1σ vel conv\")")
    else:
        vel, vel_what = (neural.get("rmse_vel_mps"), "velocity RMSE, an upper bound of the 1σ "
                         "(table column \"RMSE vel\")")
    checks.append(
        ClaimCheck(
            claim=vel_claim,
            measured=f"{_fmt(vel, '{:.2f}')} m/s",
            verdict=verdict(vel < vel_limit_mps if _finite(vel) else None),
            detail=vel_what,
            paper=SEEDS_004,
        )
    )

    # the classical linearisations: registered linearisation methods that do not carry the
    # neural map (the point-mass tracker and the point-mass-started EKF are not linearisations)
    classical_names = [name for name in methods
                       if name in LINEARIZER_METHODS and not name.startswith("neural")]
    short = [name for name in classical_names if not enough(methods[name])]
    classical = {
        name: methods[name]["sigma_pos_m"]
        for name in classical_names
        if name not in short and _finite(methods[name].get("sigma_pos_m"))
    }
    claim = better_claim + (f" ({', '.join(classical_names)})" if classical_names else "")
    if short:
        checks.append(ClaimCheck(
            claim, "n/a", "; ".join(too_few(n, methods[n]) for n in short),
            "every classical method needs enough converged runs for the comparison", SEEDS_004))
    elif not classical or not _finite(sigma):
        checks.append(
            ClaimCheck(
                claim,
                "n/a",
                NOT_MEASURED,
                "needs the neural method and at least one classical method with a finite 1σ",
                SEEDS_004,
            )
        )
    else:
        deltas = {name: value - sigma for name, value in classical.items()}
        mean_delta = float(np.mean(list(deltas.values())))
        improved = verdict(min(deltas.values()) > 0 and mean_delta >= 0.5 * improvement_m,
                           partly=mean_delta >= 0.2 * improvement_m)
        per_method = ", ".join(f"{name} {delta:+.1f} m" for name, delta in deltas.items())
        checks.append(
            ClaimCheck(
                claim,
                f"mean Δ = {mean_delta:+.1f} m ({per_method})",
                improved,
                "Δ = 1σ(classical) − 1σ(neural); holds when the neural map beats every "
                f"classical method and mean Δ ≥ {0.5 * improvement_m:g} m, partly when "
                f"mean Δ ≥ {0.2 * improvement_m:g} m",
                SEEDS_004,
            )
        )

    return checks + _target_checks(neural, pcrb_ratio_target, divergence_target,
                                   min_converged, neural_method)


def _ratio_claim(method: str, target: float) -> str:
    return f"{method}: RMSE (all runs) ≤ {target:g}× PCRB"


def _divergence_claim(method: str, target: float) -> str:
    return f"{method}: divergence ≤ {target:.0%}"


def _target_checks(neural: Mapping[str, Any], pcrb_ratio_target: float,
                   divergence_target: float, min_converged: int,
                   neural_method: str = NEURAL_METHOD) -> list[ClaimCheck]:
    """The toolkit's accuracy targets on the neural method (all runs count; a numerical
    failure counts as a failed run, and the RMSE of a method with numerical failures or
    too few converged runs gets no verdict)."""
    ratio = neural.get("pcrb_ratio_all")
    runs = RunCounts.from_metrics(neural)
    rate = runs.bad_rate
    if runs.failed:  # a numerically failed run has no error to average: it fails the target
        ratio_verdict = verdict(False, runs=runs.all_runs(), min_converged=min_converged,
                                detail=f"{runs.failed} of {runs.total} runs failed numerically")
    else:
        ratio_verdict = verdict(ratio <= pcrb_ratio_target if _finite(ratio) else None,
                                runs=runs.all_runs(), min_converged=min_converged)
    return [
        ClaimCheck(
            claim=_ratio_claim(neural_method, pcrb_ratio_target),
            measured=f"all runs {_fmt(ratio, '{:.2f}')}, converged "
            f"{_fmt(neural.get('pcrb_ratio_converged'), '{:.2f}')}",
            verdict=ratio_verdict,
            detail="horizontal RMSE over every on-map run / PCRB, both time-averaged over "
            "the last half (the converged-run ratio beside it)",
        ),
        ClaimCheck(
            claim=_divergence_claim(neural_method, divergence_target),
            measured=f"{_fmt(rate, '{:.1%}')} ({neural.get('n_diverged', 'n/a')} diverged + "
            f"{runs.failed} numerical failures of {runs.total} on-map runs)",
            verdict=verdict(rate <= divergence_target if _finite(rate) else None,
                            runs=runs.all_runs(), min_converged=min_converged),
            detail="fraction of on-map runs that diverged or failed numerically (rule below)",
        ),
    ]


def format_table(results: Mapping[str, Any], *, markdown: bool = False) -> str:
    """The per-method metrics table.

    Args:
        results: The structure from `build_results`.
        markdown: Pipe table for markdown instead of aligned plain text.

    Returns:
        The table as text (no trailing newline). Missing or non-finite values show ``n/a``.
    """
    headers = ["method"] + [header for _, header, _ in _TABLE_COLUMNS]
    rows = []
    for name, entry in results["methods"].items():
        rows.append([name] + [_fmt(entry.get(key), spec) for key, _, spec in _TABLE_COLUMNS])
    label = "PCRB (reference)" if results.get("pcrb_kind") == "reference" else "PCRB"
    pcrb_row = [label, _fmt(results.get("pcrb_pos_m"), "{:.1f}")] + ["" for _ in headers[2:]]
    pcrb_row[headers.index("final pos [m]")] = _fmt(results.get("pcrb_pos_final_m"), "{:.1f}")
    rows.append(pcrb_row)
    if markdown:
        lines = ["| " + " | ".join(headers) + " |"]
        lines.append("|" + "|".join(["---"] + ["---:"] * (len(headers) - 1)) + "|")
        lines += ["| " + " | ".join(row) + " |" for row in rows]
        return "\n".join(lines)
    widths = [max(len(row[i]) for row in [headers, *rows]) for i in range(len(headers))]
    out = [
        "  ".join(
            h.ljust(w) if i == 0 else h.rjust(w)
            for i, (h, w) in enumerate(zip(headers, widths, strict=True))
        )
    ]
    out.append("  ".join("-" * w for w in widths))
    for row in rows:
        out.append(
            "  ".join(
                v.ljust(w) if i == 0 else v.rjust(w)
                for i, (v, w) in enumerate(zip(row, widths, strict=True))
            )
        )
    return "\n".join(out)


def diverged_section(results: Mapping[str, Any]) -> list[str]:
    """Markdown lines: which runs diverged, per method, with their initial horizontal error
    (``diverged_runs`` of the results; nothing when no run diverged)."""
    listed = {name: entry["diverged_runs"] for name, entry in results["methods"].items()
              if entry.get("diverged_runs")}
    if not listed:
        return []
    lines = ["## Diverged runs", ""]
    for name, items in listed.items():
        n = results["methods"][name].get("n_diverged", len(items))
        cells = ", ".join(f"run {d['run']} (initial error {d['initial_error_m']:.0f} m = "
                          f"{d['initial_error_sigma']:.1f}σ of the prior)" for d in items)
        more = f" and {n - len(items)} more" if n > len(items) else ""
        lines.append(f"- **{name}**: {cells}{more}.")
    lines += ["", "A cold-started EKF linearises the terrain at its prior estimate and can "
              "settle on a wrong terrain match and stay there, the more likely the farther "
              "out in the prior it starts (a radial error beyond c σ has probability "
              "exp(−c²/2)); which runs are lost changes with small differences between "
              "methods (their R tables, their slopes), not with the map alone. "
              "`point_mass_ekf` acquires on the grid first and hands over to the EKF only once "
              "the posterior is unimodal and small.", ""]
    return lines


#: Position σ (m) at which the report prints the derived R.
_NOISE_REPORT_SIGMAS = (0.0, 10.0, 20.0, 40.0, 100.0, 300.0)


def noise_section(noise: Mapping[str, Any]) -> list[str]:
    """Markdown lines: how the EKF methods' R was built and, when measured, its value at a
    few position σ per method (the full tables are in results.json, ``noise``)."""
    if not noise:
        return []
    lines = ["## Measurement noise R of the EKF methods", "", str(noise.get("rule", "")), ""]
    methods = noise.get("methods") or {}
    if not methods:
        return lines
    if noise.get("pilot_runs"):
        lines.append(f"Pilot flights: {noise['pilot_runs']} runs (seed {noise['pilot_seed']}, "
                     f"independent of the study's), {noise['iterations']} iterations; "
                     "altimeter variance "
                     f"{noise['altimeter_R_m2']:g} m². R [m²] at the position σ (per axis):")
    lines.append("")
    header = "| method | " + " | ".join(f"σ = {s:g} m" for s in _NOISE_REPORT_SIGMAS) + " |"
    lines += [header, "|---|" + "---:|" * len(_NOISE_REPORT_SIGMAS)]
    for name, table in methods.items():
        sig = table["sigmas_m"]
        cells = [f"{float(np.interp(s, sig, table['R_m2'])):.1f}" for s in _NOISE_REPORT_SIGMAS]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines.append("")
    return lines


def report_text(results: Mapping[str, Any]) -> str:
    """The TAN study's own report sections: setup, metrics table, off-map runs, divergence
    rule and timing (the title, figures and claims table come from
    `StudyOutputs`).

    Args:
        results: The structure from `build_results`.

    Returns:
        Markdown text.
    """
    config = results.get("config", {})
    scenario = results.get("scenario", {})
    map_info = results.get("map", {})
    off_map = results.get("off_map", {})
    lines = ["## Setup"]
    lines.append("")
    setup = [
        ("map", map_info.get("path", config.get("map", "n/a"))),
        (
            "tile",
            f"{map_info.get('tile_name', 'n/a')} (fingerprint "
            f"{map_info.get('tile_fingerprint', 'n/a')})",
        ),
        ("scenario", scenario.get("name", config.get("scenario", "n/a"))),
        ("Monte Carlo runs", config.get("n_runs", "n/a")),
        ("time steps", max(len(results.get("curves", {}).get("t", [])) - 1, 0)),
        ("methods", ", ".join(results["methods"])),
        ("seed", config.get("seed", "n/a")),
        ("dtype / device", f"{config.get('dtype', 'n/a')} / {config.get('device', 'n/a')}"),
    ]
    truth_model = results.get("truth_model") or {}
    if truth_model:
        setup.append(("truth terrain", truth_model.get("description", truth_model.get("kind"))))
        voids = truth_model.get("void_exposure") or {}
        if voids.get("samples"):
            setup.append(("truth samples over DEM voids (nearest-node fill, not terrain)",
                          f"{voids['samples']} in {voids['runs']} runs"))
    fit = map_info.get("fit_metrics", {}) or {}
    if _finite(fit.get("rmse_m")):
        setup.append(("map fit RMSE at the training nodes (in-sample)", f"{fit['rmse_m']:.2f} m"))
    measured = map_info.get("error_vs_truth") or {}
    if _finite(measured.get("rmse_m")):
        setup.append((
            "neural map error against the truth terrain between nodes (measured)",
            f"RMSE {measured['rmse_m']:.2f} m, max {measured['max_abs_m']:.2f} m, "
            f"mean {measured['mean_m']:+.2f} m over {measured['n_points']} seeded random points",
        ))
    if _finite(map_info.get("neural_extra_variance_m2")):
        setup.append(
            (
                "extra variance added to R for the neural map (measured map MSE less "
                "scenario.fit_variance_m2)",
                f"{map_info['neural_extra_variance_m2']:.2f} m²",
            )
        )
    if results.get("pcrb_kind") == "reference":
        setup.append(("PCRB", "reference curve only: this scenario starts from a fixed initial "
                      "error, which the Bayesian bound (drawn from P0) does not bound"))
    for key in (
        "dt",
        "speed_mps",
        "altimeter_sigma_m",
        "init_pos_sigma_m",
        "R_m2",
        "fit_variance_m2",
    ):
        if key in scenario:
            setup.append((f"scenario.{key}", scenario[key]))
    lines += [f"- **{key}**: {value}" for key, value in setup]
    lines.append("")

    lines.append("## Results")
    lines.append("")
    lines.append(format_table(results, markdown=True))
    lines.append("")
    lines.append(
        "RMSE pos all: horizontal RMSE over **all** on-map runs, time-averaged over the last "
        "half of the flight. RMSE pos conv: the same over the runs that neither diverged nor "
        "failed numerically. 1σ pos conv: standard deviation of the converged horizontal "
        "error (the papers' figure). **RMSE/PCRB all** (the headline ratio): all-run RMSE over "
        "the PCRB, both time-averaged over the last half; RMSE/PCRB conv: the same for the "
        "converged runs only (it cannot see diverged runs). num. failed: runs whose filter "
        "covariance became non-finite or indefinite (counted apart from divergence). NEES "
        "time-avg: NEES of the converged runs averaged over runs and steps (5 states: 5 for a "
        "consistent filter; its 95 % χ² band is in results.json as nees_time_band). NEES in "
        "band (conv): fraction of the time steps whose run-averaged NEES lies inside the "
        "two-sided 95 % χ² band. The PCRB row gives the horizontal bound (time-averaged, and "
        "final)."
    )
    lines.append("")
    n_truth = off_map.get("truth")
    per_method = off_map.get("per_method", {})
    off_text = ", ".join(f"{k}: {v}" for k, v in per_method.items()) or "none"
    lines.append(
        "**Off-map runs** (excluded from every metric): "
        + (f"{n_truth} truth trajectories left the tile; " if n_truth is not None else "")
        + f"per method (truth left the map; an estimate that left it counts as diverged): {off_text}."
    )
    lines.append("")

    lines += diverged_section(results)
    lines += noise_section(results.get("noise") or {})

    lines.append("## Divergence rule")
    lines.append("")
    lines.append(str(results.get("divergence_rule", "n/a")))
    lines.append("")

    timing = results.get("timing_s", {})
    if timing:
        lines.append("## Timing")
        lines.append("")
        lines += [f"- {key}: {value:.2f} s" for key, value in timing.items() if _finite(value)]
        lines.append("")
    lines.append(
        "Full numbers (per-step curves, configuration, scenario) are in `results.json`; the "
        "configuration used is in `config.yaml`; TensorBoard logs are in this folder "
        "(`tensorboard --logdir .`)."
    )
    lines.append("")
    return "\n".join(lines)
