"""Tests of the evaluation report writer, the claims check, the plots and TensorBoard logging."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.io import atomic_write_json, to_jsonable
from neuralmap.studies.tan_report import (
    METHOD_KEYS,
    build_results,
    check_claims,
    format_table,
    report_text,
)

K1 = 11  # samples (K + 1)


def _metrics(sigma: float, *, vel: float = 1.0, rate: float = 0.0, ratio: float = 1.2) -> dict:
    curve = list(np.linspace(100.0, sigma, K1))
    return {
        "rmse_pos_m": sigma * 1.5,
        "rmse_pos_converged_m": sigma * 1.1,
        "rmse_vel_mps": vel,
        "sigma_pos_m": sigma,
        "sigma_vel_mps": vel * 0.8,
        "divergence_rate": rate,
        "nees_in_band": 0.9,
        "nees_time_avg": 5.1,
        "numerical_failure_rate": 0.0,
        "pcrb_ratio_all": ratio,
        "pcrb_ratio_converged": ratio * 0.9,
        "final_pos_m": sigma,
        "n_runs": 100,
        "n_off_map": 2,
        "n_included": 98,
        "n_diverged": int(rate * 98),
        "n_converged": 98 - int(rate * 98),
        "nees_band": [4.0, 6.0],
        "rmse_pos_curve": curve,
        "rmse_pos_converged_curve": curve,
        "rmse_vel_curve": [vel] * K1,
        "nees_curve": [5.0] * (K1 - 1) + [None],
        "diverged": [False] * 100,
        "divergence_rule": "rule",
    }


#: Registered classical linearisation methods the fake results use.
CLASSIC = ("bilinear", "nine_point", "mean_point", "lsq_min")


def _results(neural: float = 20.0, classical: tuple[float, ...] = (60.0, 70.0),
             extra: dict[str, float] | None = None, **kw) -> dict:
    metrics = {"neural": _metrics(neural, **kw)}
    for i, value in enumerate(classical):
        metrics[CLASSIC[i]] = _metrics(value)
    for name, value in (extra or {}).items():
        metrics[name] = _metrics(value)
    return build_results(
        method_metrics=metrics,
        t=list(range(K1)),
        pcrb_pos=list(np.linspace(50.0, 10.0, K1)),
        divergence_rule="A run diverged when ...",
        config={"n_runs": 100, "seed": 0},
        off_map={"truth": 1, "per_method": {"neural": 2}},
    )


def test_to_jsonable_makes_strict_json() -> None:
    data = {
        "nan": float("nan"),
        "inf": np.float32("inf"),
        "t": torch.tensor([1.0, float("nan")]),
        "a": np.arange(3),
        "n": np.int64(4),
        "b": np.bool_(True),
        "tup": (1, 2.5),
        "p": Path("x/y"),
    }
    out = to_jsonable(data)
    assert out == {
        "nan": None,
        "inf": None,
        "t": [1.0, None],
        "a": [0, 1, 2],
        "n": 4,
        "b": True,
        "tup": [1, 2.5],
        "p": "x/y",
    }
    json.dumps(out, allow_nan=False)  # raises on NaN


def test_atomic_write_json_leaves_no_temporary(tmp_path: Path) -> None:
    path = atomic_write_json(tmp_path / "r.json", {"x": float("nan"), "y": [1, 2]})
    assert json.loads(path.read_text()) == {"x": None, "y": [1, 2]}
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]


def test_build_results_structure() -> None:
    results = _results()
    assert set(results) >= {"methods", "pcrb_pos_m", "divergence_rule", "config", "curves"}
    for entry in results["methods"].values():
        assert set(METHOD_KEYS) <= set(entry)
        assert "diverged" not in entry and "rmse_pos_curve" not in entry
        assert entry["nees_band"] == [4.0, 6.0]
    # RMS of the last half of the bound (samples 5..10), independent computation
    bound = np.linspace(50.0, 10.0, K1)[K1 // 2 :]
    assert results["pcrb_pos_m"] == pytest.approx(math.sqrt(np.mean(bound**2)), rel=1e-12)
    assert results["pcrb_pos_final_m"] == pytest.approx(10.0)
    assert len(results["curves"]["neural"]["rmse_pos_curve"]) == K1
    assert results["curves"]["neural"]["nees_curve"][-1] is None
    json.dumps(to_jsonable(results), allow_nan=False)


def test_build_results_rejects_missing_keys_and_bad_curves() -> None:
    bad = _metrics(10.0)
    del bad["pcrb_ratio_all"]
    with pytest.raises(NeuralMapError, match="pcrb_ratio_all"):
        build_results(
            method_metrics={"x": bad},
            t=[0.0] * K1,
            pcrb_pos=[1.0] * K1,
            divergence_rule="r",
            config={},
        )
    with pytest.raises(NeuralMapError, match="rmse_pos_curve"):
        build_results(
            method_metrics={"x": _metrics(10.0)},
            t=[0.0] * 5,
            pcrb_pos=[1.0] * 5,
            divergence_rule="r",
            config={},
        )
    with pytest.raises(NeuralMapError, match="pcrb_pos"):
        build_results(
            method_metrics={"x": _metrics(10.0)},
            t=[0.0] * K1,
            pcrb_pos=[1.0] * 3,
            divergence_rule="r",
            config={},
        )


@pytest.mark.parametrize(
    ("neural", "classical", "verdict"),
    [
        (20.0, (60.0, 70.0), "holds"),  # better than all, by 45 m on average
        (20.0, (25.0, 30.0), "partly"),  # better, but only by 7.5 m on average
        (20.0, (10.0, 60.0), "partly"),  # mean better, not better than every method
        (20.0, (19.0, 23.0), "does not hold"),  # 1 m better on average: not meaningful
        (60.0, (20.0, 30.0), "does not hold"),
    ],
)
def test_claims_improvement_verdicts(neural: float, classical: tuple, verdict: str) -> None:
    checks = check_claims(_results(neural, classical))
    assert checks[2].verdict == verdict
    mean_delta = np.mean(classical) - neural
    assert f"{mean_delta:+.1f}" in checks[2].measured


def test_claims_compare_with_linearisations_only() -> None:
    """The point-mass tracker and the point-mass-started EKF are not classical
    linearisations: a better tracker must not change the neural-vs-classical verdict."""
    plain = check_claims(_results(20.0, (60.0, 70.0)))
    with_others = check_claims(_results(20.0, (60.0, 70.0), extra={
        "point_mass_tracker": 5.0, "point_mass_ekf": 6.0}))
    assert with_others[2].verdict == plain[2].verdict == "holds"
    assert with_others[2].measured == plain[2].measured


def test_claims_limits_and_targets() -> None:
    checks = check_claims(_results(20.0, vel=3.0, rate=0.01, ratio=1.4))
    assert [c.verdict for c in checks] == ["holds"] * 5
    assert "2.40" in checks[1].measured  # sigma_vel_mps = 0.8 * 3.0 preferred over the RMSE
    checks = check_claims(_results(55.0, (90.0,), vel=7.0, rate=0.05, ratio=2.0))
    assert checks[0].verdict == "does not hold"
    assert checks[1].verdict == "does not hold"  # 5.6 m/s
    assert checks[3].verdict == "does not hold"
    assert checks[4].verdict == "does not hold"


def test_claims_without_neural_or_with_missing_values() -> None:
    results = _results()
    results["methods"].pop("neural")
    assert {c.verdict for c in check_claims(results)} == {"not measured"}
    results = _results()
    results["methods"]["neural"]["sigma_pos_m"] = None
    checks = check_claims(results)
    assert checks[0].verdict == "not measured" and checks[2].verdict == "not measured"


def test_claims_need_enough_converged_runs() -> None:
    """A hopeless tuning: 3 survivors of 100 give no verdict, and no method is dropped."""
    results = _results(20.0, (60.0, 70.0))
    results["methods"]["neural"].update(n_converged=3, n_diverged=95, divergence_rate=0.97)
    checks = check_claims(results)
    assert all("not enough converged runs (neural: 3 of 98" in c.verdict for c in checks[:3])
    assert checks[4].verdict == "does not hold"  # the divergence target still judges
    results = _results(20.0, (60.0, 70.0))
    results["methods"][CLASSIC[1]].update(n_converged=0, n_diverged=98)
    checks = check_claims(results)
    assert checks[0].verdict == "holds"
    assert f"{CLASSIC[1]}: 0 of 98" in checks[2].verdict


def test_tables_and_report_text() -> None:
    results = _results()
    results["methods"][CLASSIC[0]]["pcrb_ratio_all"] = None
    text = format_table(results)
    lines = text.splitlines()
    assert lines[0].split()[0] == "method" and len(lines) == 2 + 3 + 1  # header, rule, 3, PCRB
    assert "n/a" in lines[3] and lines[-1].startswith("PCRB")
    md = format_table(results, markdown=True)
    assert md.splitlines()[1].startswith("|---|")
    report = report_text(results)
    assert "A run diverged when ..." in report
    assert "1 truth trajectories left the tile" in report
    assert "nan" not in report.lower().replace("mean", "")


def test_tan_report_goes_through_the_one_outputs_writer(tmp_path: Path) -> None:
    """The TAN study wrote its PNGs itself, opened a second TensorBoard writer and replaced
    the report; now sections, figures and claims go through StudyOutputs."""
    import matplotlib.figure

    from neuralmap.outputs import StudyOutputs

    results = _results()
    with StudyOutputs(tmp_path, config={"study": "tan"}, title="TAN", echo=False,
                      tensorboard=False) as outputs:
        outputs.add_text(report_text(results))
        for check in check_claims(results):
            outputs.add_claim("SEEDS 004", check.claim, check.measured, check.verdict,
                              detail=check.detail)
        outputs.add_figure("error_vs_time", matplotlib.figure.Figure(), "Error vs time")
        report = outputs.render()
    assert report.startswith("# TAN") and "![Error vs time](error_vs_time.png)" in report
    assert "position error < 50 m (1σ)" in report and "**holds**" in report
    assert "| how |" in report


def test_plots_and_tensorboard(tmp_path: Path) -> None:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from neuralmap.viz.navigation import (
        plot_error_vs_time,
        plot_final_error_histogram,
        plot_trajectories,
        save_figure,
    )
    from neuralmap.viz.tensorboard_nav import log_navigation

    rng = np.random.default_rng(0)
    tile = DemTile(rng.normal(size=(20, 30)).cumsum(0), spacing=(30.0, 30.0), name="t")
    t = np.arange(K1, dtype=float)
    curves = {"neural": np.linspace(50, 5, K1), "bilinear": np.linspace(50, 8, K1)}
    conv = {"neural": [None] + list(np.linspace(40, 5, K1 - 1))}
    fig1 = plot_error_vs_time(t, curves, np.linspace(40, 4, K1), converged_curves=conv)
    truth = np.stack([np.linspace(100, 800, K1), np.linspace(100, 500, K1)], -1)[None]
    fig2 = plot_trajectories(tile, truth, {"neural": truth + 5.0})
    finals = {"neural": rng.gamma(2.0, 5.0, 50), "bilinear": np.append(rng.gamma(2, 9, 49), 1e4)}
    fig3 = plot_final_error_histogram(finals, pcrb_final=4.0)
    for name, fig in {"a": fig1, "b": fig2, "c": fig3}.items():
        path = save_figure(fig, tmp_path / f"{name}.png")
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "b.png", "c.png"]
    with pytest.raises(NeuralMapError, match="expected"):
        plot_error_vs_time(t, {"x": np.ones(K1 - 1)}, np.ones(K1))
    with pytest.raises(NeuralMapError, match="shape"):
        plot_trajectories(tile, truth, {"neural": truth[:, :-1]})

    from torch.utils.tensorboard import SummaryWriter

    log_dir = tmp_path / "tb"
    writer = SummaryWriter(log_dir=str(log_dir))
    log_navigation(
        writer,
        curves={m: {"rmse_pos_curve": v, "nees_curve": v} for m, v in curves.items()},
        pcrb_pos=np.linspace(40, 4, K1),
        final_errors=finals,
        summary={"neural": {"rmse_pos_m": 3.0, "pcrb_ratio": None}},
    )
    writer.add_figure("figures/err", fig1)  # as StudyOutputs.add_figure does
    writer.close()
    acc = EventAccumulator(str(log_dir), size_guidance={"scalars": 0, "images": 0}).Reload()
    tags = acc.Tags()
    assert {"rmse_pos/neural", "rmse_pos/bilinear", "pcrb_pos", "summary/rmse_pos_m/neural"} <= set(
        tags["scalars"]
    )
    assert "summary/pcrb_ratio/neural" not in tags["scalars"]  # None is skipped
    values = [e.value for e in acc.Scalars("rmse_pos/neural")]
    np.testing.assert_allclose(values, curves["neural"], rtol=1e-6)
    assert [e.step for e in acc.Scalars("rmse_pos/neural")] == list(range(K1))
    assert set(tags["histograms"]) == {"final_pos_error/neural", "final_pos_error/bilinear"}
    assert tags["images"] == ["figures/err"]


def test_numerical_failures_count_against_the_claims() -> None:
    """A map with NaN parameters: every run fails numerically. The old rule read the
    divergence rate over the finite runs only (``divergence_rate`` None → "holds" via
    ``or 0``, or 0 of 2 finite runs) and called the divergence target held."""
    results = _results(20.0, (60.0, 70.0))
    results["methods"]["neural"].update(
        n_included=0, n_nonfinite=98, n_converged=0, n_diverged=0, divergence_rate=None,
        pcrb_ratio_all=None, sigma_pos_m=None)
    checks = check_claims(results)
    assert all(c.verdict.startswith("not enough converged runs (neural: 0 of 98, 98 failed")
               for c in checks[:3])
    assert checks[4].verdict == "does not hold" and "98 numerical failures" in checks[4].measured
    # 40 of 98 unhealthy filters: not diverged by the rule, but failed runs
    results = _results(20.0, (60.0, 70.0))
    results["methods"]["neural"].update(n_unhealthy=40, n_converged=58, divergence_rate=0.0)
    checks = check_claims(results)
    assert checks[0].verdict == "holds"  # 58 converged runs still give the 1σ claims
    assert checks[3].verdict.startswith("does not hold (40 of 98 runs failed numerically")
    assert checks[4].verdict == "does not hold" and "40.8%" in checks[4].measured


def test_one_error_vs_time_figure_for_every_study() -> None:
    """tan, tan_outliers and learned draw through viz.navigation.plot_error_vs_time:
    None gaps (results.json curves), no bound, a dash-dot reference."""
    from neuralmap.viz.navigation import plot_error_vs_time

    fig = plot_error_vs_time(np.arange(4), {"clean": [3.0, 2.0, None, 1.0], "raf": [4, 3, 2, 1]},
                             None, references=["clean"], xlabel="time step")
    ax = fig.axes[0]
    assert [line.get_label() for line in ax.lines] == ["clean", "raf"]
    assert ax.lines[0].get_linestyle() == "-." and math.isnan(ax.lines[0].get_ydata()[2])
    assert ax.get_yscale() == "log" and ax.get_xlabel() == "time step"
    import neuralmap.studies.learned as learned
    import neuralmap.studies.tan_outliers as tan_outliers

    assert learned.plot_error_vs_time is tan_outliers.plot_error_vs_time is plot_error_vs_time


def test_claims_name_their_method_once_and_their_source_apart() -> None:
    """Every claim names the method it is about; the source is the paper column, not a tag
    repeated in the text; the velocity claim's number is a column of the table."""
    results = _results(20.0, (60.0, 70.0), vel=2.0)
    checks = check_claims(results)
    assert [c.paper for c in checks] == ["SEEDS 004"] * 3 + ["toolkit target"] * 2
    for check in checks:
        assert check.claim.startswith("neural"), check.claim
        assert "[" not in check.claim and "SEEDS" not in check.claim
        assert "toolkit target" not in check.claim
    assert "RMSE (all runs) ≤ 1.5× PCRB" in checks[3].claim
    assert "(bilinear, nine_point)" in checks[2].claim  # the classical methods compared
    vel = checks[1].measured.split()[0]  # sigma_vel_mps = 0.8 * 2.0
    assert vel == "1.60" and "1σ vel conv" in checks[1].detail
    table = format_table(results)
    header, _, neural_row = table.splitlines()[:3]
    assert "1σ vel conv [m/s]" in header and vel in neural_row.split()


def test_tan_study_claims_use_the_one_verdict_rule() -> None:
    """The tracker's and the recommended EKF's targets on a handful of runs get "not enough
    converged runs", never holds/does not hold (the old rule judged NEES on 1 run)."""
    from neuralmap.studies.tan import _consistency_claims, _default_method_claims

    few = _metrics(20.0)
    few.update(n_runs=1, n_off_map=0, n_included=1, n_converged=1, n_diverged=0,
               pcrb_map_ratio_all=1.0)
    results = {"methods": {"point_mass_ekf": dict(few), "point_mass_tracker": dict(few)},
               "noise": {"mode": "measured"}}
    claims = _consistency_claims(results) + _default_method_claims(results)
    assert len(claims) == 5
    for claim in claims:
        assert claim.verdict.startswith("not enough converged runs (1 of 1"), claim
        assert claim.paper == "toolkit target" and "toolkit target" not in claim.claim
    assert claims[0].claim.startswith("point_mass_ekf (recommended EKF method): NEES")
    many = _metrics(20.0)
    many.update(pcrb_map_ratio_all=1.0, pcrb_ratio_all=1.2)
    results["methods"] = {"point_mass_ekf": dict(many), "point_mass_tracker": dict(many)}
    verdicts = [c.verdict for c in _consistency_claims(results) + _default_method_claims(results)]
    # NEES 0.9 >= 0.9; map ratio 1.0 <= 1.05; true ratio 1.2 > 1.10; 0 diverged
    assert verdicts == ["holds", "holds", "does not hold", "holds", "holds"]


def test_identical_error_curves_stay_visible() -> None:
    """Two methods with the same curve: different markers at staggered samples, and the
    legend says that the second coincides with the first."""
    from neuralmap.viz.navigation import coinciding_curves, plot_error_vs_time

    t = np.arange(40.0)
    same = np.linspace(100.0, 10.0, 40)
    fig = plot_error_vs_time(t, {"neural": same, "neural_region": same.copy(),
                                 "bilinear": same * 1.5}, None)
    ax = fig.axes[0]
    labels = [line.get_label() for line in ax.lines]
    assert labels == ["neural", "neural_region (= neural)", "bilinear"]
    markers = [line.get_marker() for line in ax.lines]
    assert len(set(markers)) == 3
    first, second = (np.asarray(ax.lines[i].get_markevery()) for i in (0, 1))
    assert first[0] != second[0]  # markers of the coinciding curves do not overlap
    assert coinciding_curves({"a": same, "b": same + 1e-3}) == {}


def test_trajectory_figure_zooms_on_the_error() -> None:
    """The second panel draws estimate − truth (metres), which the tile-wide panel cannot."""
    from neuralmap.viz.navigation import plot_trajectories

    rng = np.random.default_rng(1)
    tile = DemTile(rng.normal(size=(20, 30)).cumsum(0), spacing=(30.0, 30.0), name="t")
    truth = np.stack([np.linspace(100, 800, K1), np.linspace(100, 500, K1)], -1)[None]
    offset = np.stack([np.linspace(40.0, 3.0, K1), np.linspace(-20.0, 1.0, K1)], -1)[None]
    fig = plot_trajectories(tile, truth, {"neural": truth + offset})
    assert len(fig.axes) >= 2
    zoom = fig.axes[1]
    paths = [line for line in zoom.lines if line.get_label() == "neural"]
    assert len(paths) == 1
    np.testing.assert_allclose(paths[0].get_xdata(), offset[0, :, 0], atol=1e-9)
    np.testing.assert_allclose(paths[0].get_ydata(), offset[0, :, 1], atol=1e-9)


def test_report_lists_the_diverged_runs_with_their_start() -> None:
    results = _results(20.0, (60.0, 70.0), rate=0.02)
    assert "## Diverged runs" not in report_text(results)
    results["methods"]["neural"]["diverged_runs"] = [
        {"run": 283, "initial_error_m": 300.4, "initial_error_sigma": 3.004}]
    text = report_text(results)
    assert "## Diverged runs" in text
    assert "- **neural**: run 283 (initial error 300 m = 3.0σ of the prior)." in text
    results["methods"]["neural"]["n_diverged"] = 3  # more diverged than listed
    assert "3.0σ of the prior) and 2 more." in report_text(results)
