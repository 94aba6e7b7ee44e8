"""TAN under bad radar-altimeter data: robust and adaptive update policies (SEEDS 002, 003).

The scenario is flown twice on the same Monte Carlo draws: once with a clean altimeter (the
plain EKF's reference) and once with faults — isolated spikes, patches of consecutive
biased returns (canopy, roofs) and losses of lock (`neuralmap.lab.altimeter`). The
faulty flight is filtered with every policy: plain EKF, χ² gate, Huber, Sage-Husa, IGG-III,
RAF (IGG-III + Yang's factor, SEEDS 002), RAF + quality R (SEEDS 003's quality factor
before the adaptive factor), paper 003's tuned filter (quality R + innovation inflation)
and the variational-Bayes filter (Huang et al. 2018), each on the neural map
(``neural_region``) and one classical linearisation.

Targets: the best robust policy keeps divergence ≤ 1 % and an all-run RMSE within 1.3× of
the same method on clean data; the report shows what the plain EKF does instead.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from matplotlib.figure import Figure

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.policies.registry import POLICY_NAMES, make_policy, policy_label
from neuralmap.filters.policy import FilterPolicy
from neuralmap.lab.altimeter import FAULT_CODES
from neuralmap.lab.metrics import divergence_rule, navigation_metrics
from neuralmap.lab.monte_carlo import check_map_matches, run_filter
from neuralmap.lab.pcrb import pcrb, pcrb_position
from neuralmap.lab.scenario import load_scenario
from neuralmap.lab.simulator import simulate
from neuralmap.linearize.factory import method_label
from neuralmap.outputs import RunCounts, StudyOutputs, verdict
from neuralmap.progress import progress_bar
from neuralmap.studies.integrity_report import (
    add_integrity_table,
    add_stanford,
    integrity_entry,
)
from neuralmap.studies.setup import TanOptions, prepare_tan
from neuralmap.tan.model import TanModel
from neuralmap.viz.navigation import plot_error_vs_time

__all__ = ["POLICIES", "TanOutliersConfig", "run", "study_policy"]

#: The study's default policies (registry names of `neuralmap.filters.policies`, in
#: report order) with their labels; ``--policies`` takes any registry name.
POLICIES: dict[str, str] = {
    name: policy_label(name)
    for name in ("ekf", "chi2", "huber", "sage_husa", "igg3", "raf", "raf_quality",
                 "quality_inflation", "variational")
}


def study_policy(name: str, *, R: float) -> FilterPolicy | None:
    """A fresh policy of the registry (None for the plain EKF), Sage-Husa clamped to the
    filter's nominal measurement variance: ``R/4 … 100 R``.

    Args:
        name: A registry name (`POLICY_NAMES`).
        R: The filter's nominal measurement variance, m².
    """
    args = {"R_min": R / 4.0, "R_max": 100.0 * R} if name == "sage_husa" else {}
    return make_policy(name, args, where="--policies")


@dataclass
class TanOutliersConfig(TanOptions):
    """Options of the altimeter-fault study (``study: tan_outliers``): the shared TAN
    options (`TanOptions`; the scenario's own fault
    settings are replaced by the ones below) plus the faults, policies and targets.

    Attributes:
        policies: Update policies, registry names (default `POLICIES`); ``ekf`` is the
            plain filter.
        spike_prob: Probability per epoch of an isolated spike.
        spike_min_m: Smallest spike, m.
        spike_max_m: Largest spike, m.
        patch_prob: Probability per epoch that a biased patch starts.
        patch_min_s: Shortest patch, s.
        patch_max_s: Longest patch, s.
        patch_bias_min_m: Most negative patch bias, m.
        patch_bias_max_m: Least negative patch bias, m.
        lock_loss_prob: Probability per epoch of a loss of lock.
        alert_limit_m: Horizontal alert limit of the integrity section (misleading fixes
            per method and policy, a Stanford diagram per method at its best policy), m.
        target_divergence: Target divergence of the best robust policy.
        target_rmse_ratio: Target all-run RMSE of the best policy over the clean run's.
    """

    study: str = "tan_outliers"
    experiment: str = "tan_outliers"
    methods: list[str] = field(default_factory=lambda: ["neural_region", "nine_point"])
    policies: list[str] = field(default_factory=lambda: list(POLICIES))
    spike_prob: float = 0.05
    spike_min_m: float = 50.0
    spike_max_m: float = 300.0
    patch_prob: float = 0.01
    patch_min_s: float = 5.0
    patch_max_s: float = 20.0
    patch_bias_min_m: float = -40.0
    patch_bias_max_m: float = -10.0
    lock_loss_prob: float = 0.02
    target_divergence: float = 0.01
    target_rmse_ratio: float = 1.3
    alert_limit_m: float = 100.0

    def validate(self) -> None:
        """Checks values; raises `NeuralMapError` naming the option and the fix."""
        super().validate()
        bad = [p for p in self.policies if p not in POLICY_NAMES]
        if not self.policies or bad:
            raise NeuralMapError(
                f"--policies: give one or more of {', '.join(POLICY_NAMES)}; unknown {bad}."
            )
        for key in ("spike_prob", "patch_prob", "lock_loss_prob"):
            if not 0.0 <= getattr(self, key) <= 1.0:
                raise NeuralMapError(f"--{key} must be a probability in [0, 1], got "
                                     f"{getattr(self, key)}.")

    def faults(self) -> dict[str, float]:
        """The scenario fields of the fault model."""
        keys = ("spike_prob", "spike_min_m", "spike_max_m", "patch_prob", "patch_min_s",
                "patch_max_s", "patch_bias_min_m", "patch_bias_max_m", "lock_loss_prob")
        return {k: float(getattr(self, k)) for k in keys}


def _max_jump(run: Any) -> float | None:
    """Mean over the included runs of the largest one-step growth of the horizontal error."""
    err = run.err[..., :2].detach().double().norm(dim=-1)  # (N, K+1)
    keep = ~run.off_map.cpu()
    if not bool(keep.any()):
        return None
    jumps = (err[:, 1:] - err[:, :-1]).clamp_min(0.0).amax(dim=1)
    value = float(jumps[keep].mean())
    return value if math.isfinite(value) else None


def _fault_error(run: Any, faulty: torch.Tensor) -> float | None:
    """RMS horizontal error at epochs with a fault and the 10 after it (included runs)."""
    err2 = (run.err[..., :2].detach().double() ** 2).sum(-1)
    keep = ~run.off_map.cpu()
    window = faulty.clone()
    for shift in range(1, 11):
        window[:, shift:] |= faulty[:, :-shift]
    mask = window & keep[:, None]
    if not bool(mask.any()):
        return None
    return math.sqrt(float(err2[mask].mean()))


def run(config: TanOutliersConfig, outputs: StudyOutputs) -> None:
    """Flies the clean and faulty altimeter with every policy and fills ``outputs``."""

    started = time.perf_counter()
    base = load_scenario(config.scenario)
    clean_scenario = dataclasses.replace(base, spike_prob=0.0, patch_prob=0.0,
                                         lock_loss_prob=0.0, outlier_prob=0.0).validate()
    faulty_scenario = dataclasses.replace(clean_scenario, **config.faults()).validate(
        where="tan_outliers", options=True)
    setup = prepare_tan(scenario=clean_scenario, methods=config.methods, map_path=config.map,
                        runs_dir=config.runs_dir, seed=config.seed,
                        neural_fit_variance=config.neural_fit_variance,
                        map_error_points=config.map_error_points, device=config.torch_device)
    setup.pin(config)
    device, dtype = config.torch_device, config.torch_dtype
    sim = {"n_runs": config.n_runs, "seed": setup.seed, "dtype": dtype, "device": device,
           "truth_terrain": setup.truth_terrain}
    clean = simulate(clean_scenario, setup.tile, **sim)
    faulty = simulate(faulty_scenario, setup.tile, **sim)
    assert torch.equal(clean.ins_error, faulty.ins_error)  # the same draws
    codes = faulty.fault.cpu()
    fault_share = {name: float((codes[:, 1:] == code).double().mean())
                   for name, code in FAULT_CODES.items()}
    print(f"tan_outliers: {config.n_runs} runs, {len(config.methods)} methods x "
          f"{len(config.policies)} policies; altimeter epochs: "
          + ", ".join(f"{k} {v:.1%}" for k, v in fault_share.items()), flush=True)
    kept = clean.on_map.all(dim=1)
    if not bool(kept.any()):
        raise NeuralMapError(
            f"no run could be scored: all {config.n_runs} truth trajectories left the tile "
            f"or started off it (--scenario {config.scenario}). Move the scenario's "
            "start_xy/waypoints inside the tile, shorten duration_s, or lower start_spread_m.")
    bound = pcrb(clean, clean_scenario, setup.truth_terrain.model, runs=kept)
    pcrb_pos = pcrb_position(bound).detach().to("cpu", torch.float64)
    R = TanModel.from_scenario(clean_scenario).base_R
    faulty_epochs = (codes != FAULT_CODES["clean"]) & (codes != FAULT_CODES["lock_loss"])

    rows: list[list[Any]] = []
    results: dict[str, Any] = {}
    curves: dict[str, dict[str, list[float | None]]] = {}
    integrity: dict[str, Any] = {}
    best: dict[str, tuple[float, str, Any]] = {}  # method -> the policy of least RMSE
    total = len(config.methods) * (len(config.policies) + 1)
    bar = None
    if config.progress:

        bar = progress_bar(total=total, desc="tan_outliers", unit="filter")
    try:
        for method in config.methods:
            if bar is not None:
                bar.set_description(f"tan_outliers [{method}]")
            linearizer = setup.methods[method]
            check_map_matches(linearizer, clean, method=method)
            reference = run_filter(clean, linearizer, clean_scenario, method=method)
            ref_m = navigation_metrics(reference, pcrb_pos, pcrb_factor=config.pcrb_factor,
                                       divergence_sigma=config.divergence_sigma)
            if bar is not None:
                bar.update(1)
            entry: dict[str, Any] = {"clean": _summary(ref_m, reference, faulty_epochs)}
            curves[method] = {"clean (plain EKF)": ref_m["rmse_pos_curve"]}
            rows.append([method_label(method), "plain EKF, clean altimeter",
                         *_row(entry["clean"], ref_m["rmse_pos_m"])])
            for name in config.policies:
                tick = time.perf_counter()
                filtered = run_filter(faulty, linearizer, faulty_scenario, method=method,
                                      policy=study_policy(name, R=R))
                m = navigation_metrics(filtered, pcrb_pos, pcrb_factor=config.pcrb_factor,
                                       divergence_sigma=config.divergence_sigma)
                summary = _summary(m, filtered, faulty_epochs)
                summary["wall_s"] = time.perf_counter() - tick
                key = f"{method}/{name}"
                entry_i = integrity_entry(filtered, alert_limit_m=config.alert_limit_m)
                if entry_i is not None:
                    integrity[key] = entry_i
                rmse = m["rmse_pos_m"]
                if rmse is not None and (method not in best or rmse < best[method][0]):
                    best[method] = (rmse, key, filtered)
                entry[name] = summary
                curves[method][policy_label(name)] = m["rmse_pos_curve"]
                rows.append([method_label(method), policy_label(name),
                             *_row(summary, ref_m["rmse_pos_m"])])
                for k, value in enumerate(m["rmse_pos_curve"]):
                    if value is not None:
                        outputs.log_scalar(f"rmse_pos/{method}/{name}", value, k)
                if bar is not None:
                    bar.update(1)
            results[method] = entry
    finally:
        if bar is not None:
            bar.close()

    outputs.add_text(
        f"Scenario **{base.name}** (truth: {setup.truth_terrain.description}), "
        f"{config.n_runs} runs, the same draws for every policy. Altimeter faults: spikes "
        f"{config.spike_prob:.0%} of epochs (±{config.spike_min_m:g}–{config.spike_max_m:g} m), "
        f"biased patches starting with probability {config.patch_prob:g} per epoch "
        f"({config.patch_min_s:g}–{config.patch_max_s:g} s at {config.patch_bias_min_m:g} to "
        f"{config.patch_bias_max_m:g} m), loss of lock {config.lock_loss_prob:.0%}. Measured "
        "share of epochs: " + ", ".join(f"{k} {v:.1%}" for k, v in fault_share.items()) + ".\n\n"
        f"Divergence rule: {divergence_rule(config.pcrb_factor, config.divergence_sigma)}"
    )
    outputs.add_table(
        "Navigation under altimeter faults (horizontal position; all-run figures)",
        ["method", "filter", "RMSE all [m]", "× clean", "RMSE/PCRB all", "diverged",
         "num. failed", "RMSE near faults [m]", "mean max jump [m]"],
        rows,
        note="× clean: all-run RMSE over the same method's plain EKF on the clean altimeter. "
        "RMSE near faults: over epochs with a spike or patch and the 10 s after. Mean max "
        "jump: the largest one-step growth of each run's horizontal error, averaged.",
    )
    add_integrity_table(outputs, integrity, alert_limit_m=config.alert_limit_m)
    for _, key, run in best.values():  # a Stanford diagram per method: its best policy
        add_stanford(outputs, key, run, alert_limit_m=config.alert_limit_m)
    targets = _targets(config, results)
    _claims(outputs, config, results)
    _figures(outputs, config, curves, pcrb_pos.numpy(), results)
    outputs.results.update({
        "methods": results, "integrity": integrity, "targets": targets, "fault_share": fault_share,
        "pcrb_pos_m": float(pcrb_pos[len(pcrb_pos) // 2:].square().mean().sqrt()),
        "truth_model": setup.truth_terrain.summary(), "map": setup.map_info(),
        "policies": POLICIES, "timing_s": {"total": time.perf_counter() - started},
        "curves": {"pcrb_pos_m": pcrb_pos.tolist(), "rmse_pos": curves},
    })


def _summary(m: dict[str, Any], run: Any, faulty_epochs: torch.Tensor) -> dict[str, Any]:
    return {
        "rmse_pos_m": m["rmse_pos_m"], "rmse_pos_converged_m": m["rmse_pos_converged_m"],
        "pcrb_ratio_all": m["pcrb_ratio_all"], "divergence_rate": m["divergence_rate"],
        "numerical_failure_rate": m["numerical_failure_rate"], "n_diverged": m["n_diverged"],
        "n_included": m["n_included"], "n_converged": m["n_converged"],
        "n_nonfinite": m["n_nonfinite"], "n_unhealthy": m["n_unhealthy"],
        "nees_time_avg": m["nees_time_avg"],
        "rmse_near_faults_m": _fault_error(run, faulty_epochs), "mean_max_jump_m": _max_jump(run),
    }


def _row(summary: dict[str, Any], clean_rmse: float | None) -> list[Any]:
    ratio = (summary["rmse_pos_m"] / clean_rmse
             if summary["rmse_pos_m"] is not None and clean_rmse else None)
    pct = (lambda v: None if v is None else f"{v:.1%}")  # noqa: E731
    return [summary["rmse_pos_m"], ratio, summary["pcrb_ratio_all"],
            pct(summary["divergence_rate"]), pct(summary["numerical_failure_rate"]),
            summary["rmse_near_faults_m"], summary["mean_max_jump_m"]]


def _best(entry: dict[str, Any], policies: list[str]) -> str | None:
    robust = [p for p in policies if p != "ekf" and entry[p]["rmse_pos_m"] is not None]
    return min(robust, key=lambda p: entry[p]["rmse_pos_m"]) if robust else None


def _targets(config: TanOutliersConfig, results: dict[str, Any]) -> dict[str, Any]:
    out = {}
    for method, entry in results.items():
        best = _best(entry, config.policies)
        clean = entry["clean"]["rmse_pos_m"]
        if best is None or not clean:
            out[method] = {"best_policy": best, "met": None}
            continue
        ratio = entry[best]["rmse_pos_m"] / clean
        div = entry[best]["divergence_rate"] or 0.0
        out[method] = {"best_policy": best, "rmse_ratio_to_clean": ratio,
                       "divergence_rate": div,
                       "met": bool(ratio <= config.target_rmse_ratio
                                   and div <= config.target_divergence)}
    return out


def _claims(outputs: StudyOutputs, config: TanOutliersConfig, results: dict[str, Any]) -> None:
    """Paper 002's / 003's claims and the toolkit target, per method. Every claim is over
    all runs of the policies it compares (`RunCounts.all_runs`); numerical failures
    count as failed runs in the divergence figures."""
    def fmt(v: Any, spec: str = "{:.1f}") -> str:
        return "n/a" if v is None else spec.format(v)

    def runs(*names: str) -> RunCounts:
        return RunCounts.weakest(*(RunCounts.from_metrics(entry[n]) for n in names)).all_runs()

    def bad(name: str) -> float:
        rate = RunCounts.from_metrics(entry[name]).bad_rate
        return 0.0 if rate is None else rate

    for method, entry in results.items():
        label = method_label(method)
        best = _best(entry, config.policies)
        clean = entry["clean"]
        if best is not None and clean["rmse_pos_m"]:
            ratio = entry[best]["rmse_pos_m"] / clean["rmse_pos_m"]
            div = bad(best)
            ok = ratio <= config.target_rmse_ratio and div <= config.target_divergence
            outputs.add_claim(
                "toolkit target",
                f"{label}: best robust policy diverges ≤ {config.target_divergence:.0%} with "
                f"all-run RMSE ≤ {config.target_rmse_ratio:g}× clean",
                f"{policy_label(best)}: {fmt(ratio, '{:.2f}')}× clean, divergence {div:.1%}",
                verdict(ok), runs=runs("clean", best))
        if "ekf" in entry:
            ekf = entry["ekf"]
            outputs.add_claim(
                "SEEDS 002", f"{label}: the plain KF diverges under continuous outliers",
                f"plain EKF divergence {fmt(ekf['divergence_rate'], '{:.1%}')} with faults vs "
                f"{fmt(clean['divergence_rate'], '{:.1%}')} clean; RMSE {fmt(ekf['rmse_pos_m'])} m"
                f" vs {fmt(clean['rmse_pos_m'])} m",
                verdict(bad("ekf") > max(2 * bad("clean"), 0.01)), runs=runs("clean", "ekf"))
        if {"sage_husa", "raf"} <= set(entry):
            sh, raf = entry["sage_husa"], entry["raf"]
            outputs.add_claim(
                "SEEDS 002", f"{label}: Sage-Husa jumps at outliers, RAF stays smooth",
                f"mean max jump Sage-Husa {fmt(sh['mean_max_jump_m'])} m, RAF "
                f"{fmt(raf['mean_max_jump_m'])} m",
                verdict((sh["mean_max_jump_m"] or 0) > (raf["mean_max_jump_m"] or 0)),
                runs=runs("sage_husa", "raf"))
            policies = [p for p in config.policies if p != "ekf" and entry[p]["rmse_pos_m"]]
            best_rmse = min(policies, key=lambda p: entry[p]["rmse_pos_m"]) if policies else None
            outputs.add_claim(
                "SEEDS 002", f"{label}: RAF (alone or after the quality-based R) is the most accurate",
                f"RAF {fmt(raf['rmse_pos_m'])} m; best {policy_label(best_rmse) if best_rmse else 'n/a'} "
                f"{fmt(entry[best_rmse]['rmse_pos_m'] if best_rmse else None)} m",
                verdict(best_rmse in ("raf", "raf_quality")), runs=runs(*policies or ["raf"]))
        if {"ekf", "quality_inflation"} <= set(entry):
            ekf, tuned = entry["ekf"], entry["quality_inflation"]
            if ekf["rmse_near_faults_m"] and tuned["rmse_near_faults_m"]:
                cut = 1.0 - tuned["rmse_near_faults_m"] / ekf["rmse_near_faults_m"]
                outputs.add_claim(
                    "SEEDS 003", f"{label}: the tuned filter cuts error spikes by about two thirds",
                    f"RMSE near faults {fmt(ekf['rmse_near_faults_m'])} → "
                    f"{fmt(tuned['rmse_near_faults_m'])} m ({cut:.0%} lower)",
                    verdict(cut >= 0.5, partly=cut >= 0.25), runs=runs("ekf", "quality_inflation"))


def _figures(outputs: StudyOutputs, config: TanOutliersConfig,
             curves: dict[str, dict[str, list[float | None]]], pcrb_pos: np.ndarray,
             results: dict[str, Any]) -> None:
    for method, by_policy in curves.items():
        fig = plot_error_vs_time(
            np.arange(len(pcrb_pos)), by_policy, pcrb_pos,
            references=[k for k in by_policy if k.startswith("clean")], xlabel="time step",
            ylabel="horizontal RMSE, all runs [m]",
            title=f"{method_label(method)}: faulty altimeter, every policy")
        outputs.add_figure(f"rmse_vs_time_{method}", fig,
                           f"{method_label(method)}: all-run RMSE vs time per policy")
    fig = Figure(figsize=(8, 4))
    ax = fig.add_subplot()
    width = 0.8 / max(len(results), 1)
    for i, (method, entry) in enumerate(results.items()):
        names = ["clean", *config.policies]
        values = [100.0 * (entry[n]["divergence_rate"] or 0.0) for n in names]
        ax.bar(np.arange(len(names)) + i * width, values, width, label=method_label(method))
    ax.set_xticks(np.arange(len(names)) + 0.4 - width / 2)
    ax.set_xticklabels(["clean EKF", *config.policies], rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("diverged runs [%]")
    ax.legend(fontsize=8)
    outputs.add_figure("divergence", fig, "Divergence per policy (faulty altimeter)")
