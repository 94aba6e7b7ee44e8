"""Monte Carlo evaluation of terrain-aided navigation: ``python evaluate.py``.

Loads the neural map of the latest ``python train.py`` run (or ``--map PATH``), flies the
scenario's Monte Carlo trajectories once, runs the batched TAN EKF with every linearisation
method on the same truth, computes the posterior Cramér-Rao bound and the metrics, prints a
table and writes ``<runs_dir>/<experiment>/version_<N>/`` with ``report.md``,
``results.json``, PNG plots, TensorBoard event files and the ``config.yaml`` used. The folder
is written under a temporary name and renamed when complete.

Examples:
    python evaluate.py
    python evaluate.py --n_runs 200 --methods [neural,bilinear,lsq_adaptive]
    python evaluate.py --map runs/default/version_3/neural_map.pt --scenario paper
    python evaluate.py --config configs/evaluate_tiny.yaml
"""

from __future__ import annotations

import os
import re
import shutil
import sys
import tempfile
import time
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from jsonargparse import ActionConfigFile, ArgumentParser

from neuralmap.exceptions import NeuralMapError
from neuralmap.nav.evaluate_config import KNOWN_METHODS, EvaluateConfig
from neuralmap.nav.report import atomic_write_json, atomic_write_text, default_mode

REPO_ROOT = Path(__file__).resolve().parent
DEFAULT_CONFIG = REPO_ROOT / "configs" / "evaluate.yaml"
MAP_FILENAME = "neural_map.pt"
NO_MAP_MESSAGE = (
    "no trained map found under {runs}/: run `python train.py` first (or pass --map PATH)"
)
_FIGURES = {
    "error_vs_time": "Horizontal position RMSE vs time, with the PCRB",
    "trajectories": "Trajectories over the tile (truth and estimates)",
    "final_error_hist": "Final horizontal error",
}


def build_parser() -> ArgumentParser:
    """The command-line parser (``--config`` YAML + the :class:`EvaluateConfig` options)."""
    parser = ArgumentParser(
        prog="evaluate.py",
        description="Monte Carlo evaluation of terrain-aided navigation with a neural map "
        f"and the classical linearisations ({', '.join(KNOWN_METHODS)}).",
        default_config_files=[str(DEFAULT_CONFIG)] if DEFAULT_CONFIG.is_file() else None,
    )
    parser.add_argument("--config", action=ActionConfigFile, help="YAML configuration file.")
    parser.add_class_arguments(EvaluateConfig, nested_key=None, as_group=False)
    return parser


def parse_config(args: list[str] | None = None) -> EvaluateConfig:
    """Parses and validates the options.

    Args:
        args: Command-line arguments (``None`` = ``sys.argv[1:]``).

    Returns:
        The validated :class:`EvaluateConfig`.

    Raises:
        NeuralMapError: Invalid values.
        SystemExit: ``--help``, ``--print_config`` or a parse error (jsonargparse).
    """
    namespace = build_parser().parse_args(args)
    values = {f.name: namespace[f.name] for f in fields(EvaluateConfig) if f.name in namespace}
    config = EvaluateConfig(**values)
    config.validate()
    return config


def _version_number(path: Path) -> int:
    match = re.fullmatch(r"version_(\d+)", path.name)
    return int(match.group(1)) if match else -1


def find_latest_map(runs_dir: str | os.PathLike[str]) -> Path | None:
    """The newest ``<runs_dir>/*/version_*/neural_map.pt`` (by modification time).

    Args:
        runs_dir: Root of the run folders.

    Returns:
        The path, or ``None`` when there is none.
    """
    candidates = [p for p in Path(runs_dir).glob(f"*/version_*/{MAP_FILENAME}") if p.is_file()]
    if not candidates:
        return None
    return max(candidates, key=lambda p: (p.stat().st_mtime, _version_number(p.parent)))


def resolve_map_path(config: EvaluateConfig) -> Path:
    """The map file to evaluate.

    Raises:
        NeuralMapError: ``--map`` does not exist, or no map was given nor found.
    """
    if config.map is not None:
        path = Path(config.map)
        if not path.is_file():
            raise NeuralMapError(
                f"--map {config.map}: file not found. Pass the neural_map.pt written by "
                "`python train.py` (runs/<experiment>/version_N/neural_map.pt)."
            )
        return path
    path = find_latest_map(config.runs_dir)
    if path is None:
        raise NeuralMapError(NO_MAP_MESSAGE.format(runs=config.runs_dir.rstrip("/")))
    return path


def _torch_dtype(name: str) -> torch.dtype:
    return {"float64": torch.float64, "float32": torch.float32}[name]


def _check_device(device: str) -> torch.device:
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise NeuralMapError(
            f"--device {device!r} is not a torch device; use cpu, cuda or cuda:<i>."
        ) from exc
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise NeuralMapError(
            f"--device {device}: CUDA is not available on this machine; use --device cpu."
        )
    return dev


def check_map_tile(terrain_map: Any, tile: Any, *, map_path: Path, scenario_name: str) -> None:
    """Checks that the map was exported from the scenario's tile (fingerprints equal).

    Args:
        terrain_map: The loaded map (``tile_fingerprint``, ``tile_name``).
        tile: The scenario's :class:`~neuralmap.dem.tile.DemTile`.
        map_path: Map file, for the message.
        scenario_name: Scenario name, for the message.

    Raises:
        NeuralMapError: The fingerprints differ or the map has none.
    """
    expected = tile.fingerprint()
    found = str(getattr(terrain_map, "tile_fingerprint", "") or "")
    if found == expected:
        return
    map_tile = getattr(terrain_map, "tile_name", "") or "unknown"
    info = getattr(terrain_map, "tile_info", None) or {}
    differences = [
        f"{key} {info[key]} vs {now}"
        for key, now in (
            ("shape", list(tile.shape)),
            ("spacing", list(tile.spacing)),
            ("origin", list(tile.origin)),
        )
        if key in info and list(info[key]) != now
    ]
    hint = ""
    if map_tile == tile.name:
        hint = (
            " Same tile name, different content: the DEM file or its reader changed since "
            "the map was trained"
            + (f" ({'; '.join(differences)})" if differences else "")
            + ", so retrain it (python train.py)."
        )
    raise NeuralMapError(
        f"--map {map_path}: the map was exported from tile '{map_tile}' (fingerprint "
        f"{found or 'none'}), but scenario '{scenario_name}' flies over tile '{tile.name}' "
        f"(fingerprint {expected})."
        + (
            hint
            or " Train a map on the scenario's tile (python train.py with that tile), "
            "pass the matching --map, or pick the scenario of the map's tile (--scenario)."
        )
    )


def map_fit_variance(terrain_map: Any) -> float:
    """Square of the fit RMSE recorded in the map file (``metrics["rmse_m"]``), else 0."""
    metrics = getattr(terrain_map, "metrics", None) or {}
    rmse = metrics.get("rmse_m") if isinstance(metrics, dict) else None
    try:
        rmse = float(rmse)
    except (TypeError, ValueError):
        return 0.0
    return rmse * rmse if np.isfinite(rmse) else 0.0


def build_methods(
    names: list[str],
    *,
    tile: Any,
    terrain_map: Any,
    device: torch.device,
    fit_variance: float = 0.0,
) -> dict[str, Any]:
    """One linearizer per method name (``neural`` = the map with autograd).

    Args:
        names: Method names (:data:`KNOWN_METHODS`).
        tile: The scenario's DEM tile (grid and plane-fit methods).
        terrain_map: The loaded neural map.
        device: Device the filters run on.
        fit_variance: The neural map's fit-error variance (m²), its linearisation variance.

    Returns:
        Method name -> :class:`~neuralmap.linearize.base.Linearizer`, in ``names`` order.
    """
    from neuralmap.linearize.factory import make_linearizer

    methods: dict[str, Any] = {}
    for name in names:
        if name in ("neural", "neural_region"):
            linearizer = make_linearizer(
                name, tile=tile, terrain=terrain_map, fit_variance=fit_variance
            )
        else:
            linearizer = make_linearizer(name, tile=tile)
        methods[name] = linearizer.to(device)
    return methods


def true_terrain_model(tile: Any, truth: Any) -> Any:
    """The simulator's true terrain: bicubic DEM plus the DEM-making error field, if any.

    Args:
        tile: The scenario's DEM tile.
        truth: The simulated truth (its ``dem_error`` field, ``(ny, nx)`` metres, or None).

    Returns:
        A float64 bicubic :class:`~neuralmap.terrain.grid.GridTerrain`.
    """
    from neuralmap.dem.tile import DemTile
    from neuralmap.terrain.grid import GridTerrain

    dem_error = getattr(truth, "dem_error", None)
    if dem_error is not None:
        tile = DemTile(
            tile.heights + np.asarray(dem_error),
            spacing=tile.spacing,
            origin=tile.origin,
            name=tile.name,
            source=tile.source,
        )
    return GridTerrain(tile, method="bicubic", dtype=torch.float64)


def _make_output_dir(root: Path) -> Path:
    """A fresh temporary folder inside ``root`` (renamed into place by :func:`_publish`)."""
    root.mkdir(parents=True, exist_ok=True)
    path = Path(tempfile.mkdtemp(prefix=".tmp-version_", dir=root))
    os.chmod(path, default_mode(directory=True))
    return path


def _publish(tmp_dir: Path, root: Path) -> Path:
    """Renames the complete ``tmp_dir`` to the next free ``root/version_<N>``."""
    for _ in range(100):
        existing = [_version_number(p) for p in root.glob("version_*")]
        target = root / f"version_{max(existing, default=-1) + 1}"
        try:
            target.mkdir()  # reserve the name: fails if another run took it
        except FileExistsError:
            continue
        os.replace(tmp_dir, target)  # replaces the empty reserved folder atomically
        return target
    raise NeuralMapError(f"could not find a free version folder under {root}.")


def _final_horizontal_errors(run: Any) -> np.ndarray:
    """``(M,)`` final horizontal errors (m) of the runs that stayed on the map."""
    err = run.err[:, -1, :2].detach().to("cpu", torch.float64)
    keep = ~run.off_map.detach().cpu()
    return err[keep].norm(dim=-1).numpy()


def _plot_indices(truth: Any, runs: dict[str, Any], count: int) -> list[int]:
    """The first ``count`` runs that stayed on the map for every method."""
    bad = ~truth.on_map.all(dim=1).cpu()
    for run in runs.values():
        bad |= run.off_map.cpu()
    return torch.nonzero(~bad).flatten()[:count].tolist()


def write_outputs(
    out_dir: Path,
    *,
    config: EvaluateConfig,
    config_dump: dict[str, Any],
    results: dict[str, Any],
    claims: list[Any],
    truth: Any,
    runs: dict[str, Any],
    tile: Any,
    pcrb_pos: np.ndarray,
) -> None:
    """Writes plots, TensorBoard logs, results.json, report.md and config.yaml into ``out_dir``."""
    from neuralmap.nav.report import render_report
    from neuralmap.viz.navigation import (
        plot_error_vs_time,
        plot_final_error_histogram,
        plot_trajectories,
        save_figure,
    )

    curves = results["curves"]
    t = np.asarray(curves["t"])
    figures = {
        "error_vs_time": plot_error_vs_time(
            t,
            {m: curves[m]["rmse_pos_curve"] for m in runs},
            pcrb_pos,
            converged_curves={m: curves[m]["rmse_pos_converged_curve"] for m in runs},
        ),
    }
    idx = _plot_indices(truth, runs, config.n_plot_trajectories)
    truth_xy = truth.pos[idx, :, :2].detach().cpu().double().numpy()
    figures["trajectories"] = plot_trajectories(
        tile,
        truth_xy,
        {m: run.estimate_xy(truth)[idx].detach().cpu().double().numpy() for m, run in runs.items()},
    )
    final_errors = {m: _final_horizontal_errors(run) for m, run in runs.items()}
    figures["final_error_hist"] = plot_final_error_histogram(
        final_errors, pcrb_final=float(pcrb_pos[-1])
    )
    for name, fig in figures.items():
        save_figure(fig, out_dir / f"{name}.png")

    if config.tensorboard:
        from neuralmap.viz.tensorboard_nav import log_navigation

        log_navigation(
            out_dir,
            curves={m: curves[m] for m in runs},
            pcrb_pos=pcrb_pos,
            final_errors=final_errors,
            summary={m: results["methods"][m] for m in runs},
            figures=figures,
        )

    atomic_write_json(out_dir / "results.json", results)
    report = render_report(
        results,
        claims=claims,
        figures={_FIGURES[name]: f"{name}.png" for name in figures},
    )
    atomic_write_text(out_dir / "report.md", report)
    atomic_write_text(
        out_dir / "config.yaml",
        "# evaluate.py configuration used for this run (python evaluate.py --config <this>)\n"
        + yaml.safe_dump(config_dump, sort_keys=False),
    )


def run_evaluation(config: EvaluateConfig) -> Path:
    """Runs the whole evaluation and writes the output folder.

    Args:
        config: Validated options.

    Returns:
        The output folder ``<runs_dir>/<experiment>/version_<N>``.

    Raises:
        NeuralMapError: Bad input (no map, tile mismatch, bad scenario, device...).
    """
    from neuralmap.nav.metrics import divergence_rule, navigation_metrics
    from neuralmap.nav.monte_carlo import run_monte_carlo
    from neuralmap.nav.pcrb import pcrb, pcrb_position
    from neuralmap.nav.report import build_results, check_claims, format_table
    from neuralmap.nav.scenario import load_scenario, scenario_tile
    from neuralmap.terrain.export import load_map

    started = time.perf_counter()
    timing: dict[str, float] = {}
    device = _check_device(config.device)
    dtype = _torch_dtype(config.dtype)
    map_path = resolve_map_path(config)
    scenario = load_scenario(config.scenario)
    tile = scenario_tile(scenario)
    terrain_map = load_map(map_path)
    check_map_tile(terrain_map, tile, map_path=map_path, scenario_name=scenario.name)
    if config.neural_fit_variance is None:
        fit_variance = max(map_fit_variance(terrain_map) - scenario.fit_variance_m2, 0.0)
    else:
        fit_variance = float(config.neural_fit_variance)
    methods = build_methods(
        config.methods,
        tile=tile,
        terrain_map=terrain_map,
        device=device,
        fit_variance=fit_variance,
    )
    print(
        f"evaluate: map {map_path} | scenario {scenario.name} (tile {tile.name}, "
        f"{scenario.n_steps} steps of {scenario.dt:g} s) | {config.n_runs} runs | "
        f"methods {', '.join(config.methods)} | {config.dtype} on {device}",
        flush=True,
    )
    timing["setup"] = time.perf_counter() - started

    truth, runs = run_monte_carlo(
        scenario,
        methods,
        n_runs=config.n_runs,
        seed=config.seed,
        progress=config.progress,
        device=device,
        dtype=dtype,
        tile=tile,
    )
    for name, run in runs.items():
        timing[f"filter_{name}"] = float(run.elapsed_s)

    tick = time.perf_counter()
    kept = truth.on_map.all(dim=1)  # the metrics drop runs whose truth left the map
    bound = pcrb(
        truth, scenario, true_terrain_model(tile, truth), runs=kept if bool(kept.any()) else None
    )
    pcrb_pos = pcrb_position(bound).detach().to("cpu", torch.float64).numpy()
    timing["pcrb"] = time.perf_counter() - tick

    method_metrics = {
        name: navigation_metrics(
            run,
            torch.as_tensor(pcrb_pos),
            pcrb_factor=config.pcrb_factor,
            sigma_factor=config.sigma_factor,
        )
        for name, run in runs.items()
    }
    n_truth_off = int((~truth.on_map.all(dim=1)).sum())
    off_map = {
        "truth": n_truth_off,
        "per_method": {name: int(run.off_map.sum()) for name, run in runs.items()},
    }
    config_dump = {**asdict(config), "map": str(map_path), "seed": truth.seed}
    results = build_results(
        method_metrics=method_metrics,
        t=truth.t.detach().cpu().tolist(),
        pcrb_pos=pcrb_pos.tolist(),
        divergence_rule=divergence_rule(config.pcrb_factor, config.sigma_factor),
        config=config_dump,
        scenario=scenario.to_dict(),
        map_info={
            "path": str(map_path),
            "tile_name": getattr(terrain_map, "tile_name", ""),
            "tile_fingerprint": getattr(terrain_map, "tile_fingerprint", ""),
            "model": type(terrain_map).__name__,
            "num_parameters": int(sum(p.numel() for p in terrain_map.parameters())),
            "fit_metrics": dict(getattr(terrain_map, "metrics", None) or {}),
            "neural_extra_variance_m2": fit_variance,
        },
        off_map=off_map,
        timing_s=timing,
    )
    claims = check_claims(results)

    print()
    print(format_table(results))
    print()
    print(
        f"off-map runs (excluded from the metrics): truth left the tile in {n_truth_off} of "
        f"{config.n_runs}; per method: "
        + ", ".join(f"{k} {v}" for k, v in off_map["per_method"].items())
    )
    for check in claims:
        print(f"claim: {check.claim}: {check.measured} -> {check.verdict}")

    root = Path(config.runs_dir) / config.experiment
    tmp_dir = _make_output_dir(root)
    try:
        results["timing_s"]["total"] = time.perf_counter() - started
        write_outputs(
            tmp_dir,
            config=config,
            config_dump=config_dump,
            results=results,
            claims=claims,
            truth=truth,
            runs=runs,
            tile=tile,
            pcrb_pos=pcrb_pos,
        )
        out_dir = _publish(tmp_dir, root)
    except BaseException:
        shutil.rmtree(tmp_dir, ignore_errors=True)
        raise
    return out_dir


def main(args: list[str] | None = None) -> int:
    """Command-line entry point.

    Args:
        args: Arguments (``None`` = ``sys.argv[1:]``).

    Returns:
        0 on success, 2 on bad input (the message goes to stderr), or the exit code of
        ``--help`` / a parse error.
    """
    previous_threads = torch.get_num_threads()
    try:
        config = parse_config(args)
        if config.threads is not None:
            torch.set_num_threads(config.threads)
        out_dir = run_evaluation(config)
    except NeuralMapError as exc:
        print(f"evaluate.py: error: {exc}", file=sys.stderr)
        return 2
    except SystemExit as exc:  # --help, --print_config, jsonargparse parse errors
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    finally:
        torch.set_num_threads(previous_threads)
    print(f"results written to {out_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
