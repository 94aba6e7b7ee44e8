"""Copies a study run's ``summary.md`` into ``docs/results/<study>.md``, stamped.

The stamp names the config file of ``configs/`` the run was made with. It is found, not
trusted: every shipped config of the run's study is resolved as ``evaluate.py`` resolves
it, and the one the run's saved ``config.yaml`` differs from least is the run's (the
options it set on top are listed in the stamp as overrides).
"""

from __future__ import annotations

import json
import re
import shutil
from dataclasses import asdict
from pathlib import Path
from typing import Any

import yaml

from neuralmap.docs.stamp import TINY_NOTE, RunStamp, config_sha256
from neuralmap.exceptions import NeuralMapError
from neuralmap.io import atomic_write_text, load_yaml, to_jsonable
from neuralmap.studies.outputs import SUMMARY_MARK

__all__ = ["IGNORED_OPTIONS", "find_config", "update_page"]

#: Options that say where and how a run reports, not what it computes.
IGNORED_OPTIONS = frozenset({"runs_dir", "experiment", "tensorboard", "progress"})


def _read_summary(run_dir: Path) -> tuple[dict[str, Any], str]:
    summary = run_dir / "summary.md"
    if not summary.is_file():
        raise NeuralMapError(
            f"{run_dir}: no summary.md; pass a study's run folder "
            "(runs/<experiment>/version_N) made by this version of evaluate.py, or rerun it")
    first, _, body = summary.read_text(encoding="utf-8").partition("\n")
    if not first.startswith(SUMMARY_MARK):
        raise NeuralMapError(f"{summary}: line 1: no run provenance; rerun the study")
    try:
        provenance = json.loads(first[len(SUMMARY_MARK):].removesuffix("-->").strip())
    except json.JSONDecodeError as exc:
        raise NeuralMapError(f"{summary}: line 1: damaged run provenance ({exc})") from exc
    return provenance, body


def _resolved(path: Path) -> dict[str, Any]:
    from neuralmap.studies.cli import parse_config  # the studies' CLI: imports torch

    return to_jsonable(asdict(parse_config(["--config", str(path)])))


def _differences(run: dict[str, Any], config: dict[str, Any]) -> dict[str, Any]:
    keys = (set(run) | set(config)) - IGNORED_OPTIONS
    return {k: run.get(k) for k in sorted(keys) if run.get(k) != config.get(k)}


def find_config(run_config: dict[str, Any], study: str,
                configs_dir: Path) -> tuple[Path, dict[str, Any]]:
    """The shipped config of ``study`` a run was made with, and the run's overrides.

    Args:
        run_config: The run's saved ``config.yaml``.
        study: The run's study.
        configs_dir: The repository's ``configs/``.

    Returns:
        The config file and the options the run set differently (name -> run's value).

    Raises:
        NeuralMapError: No config of the study is shipped.
    """
    best: tuple[int, Path, dict[str, Any]] | None = None
    for path in sorted(configs_dir.glob("*.yaml")):
        data = load_yaml(path.read_text(encoding="utf-8"))
        if not isinstance(data, dict) or data.get("study") != study:
            continue
        diff = _differences(run_config, _resolved(path))
        if best is None or len(diff) < best[0]:
            best = (len(diff), path, diff)
    if best is None:
        raise NeuralMapError(f"{configs_dir}: no config of study {study!r}; pass "
                             "--configs_dir the repository's configs/ folder")
    return best[1], best[2]


def _demote(markdown: str) -> str:
    """Headings one level down (the page's own title is the only ``#``)."""
    return re.sub(r"^(#+) ", r"#\1 ", markdown, flags=re.MULTILINE)


def _stamp_table(stamp: RunStamp, run_dir: Path) -> str:
    commit = f"`{stamp.commit[:12]}`" if stamp.commit else "unknown (not run from a checkout)"
    if stamp.dirty:
        commit += " with uncommitted changes in the working tree"
    rerun = f"python evaluate.py --config {stamp.config}" + "".join(
        f" --{k} {json.dumps(v) if not isinstance(v, str) else v}"
        for k, v in stamp.overrides.items())
    rows = [
        ("config", f"`{stamp.config}` (sha256 `{stamp.config_sha256[:12]}`)"
                   + (f" — **{TINY_NOTE}**" if stamp.tiny else "")),
        ("seed", "the scenario's" if stamp.seed is None else str(stamp.seed)),
        ("commit", commit),
        ("date", stamp.date),
        ("overrides", ", ".join(f"`{k}`" for k in stamp.overrides) or "none"),
        ("rerun", f"`{rerun}`"),
        ("run folder", f"`{run_dir.parent.name}/{run_dir.name}`"),
    ]
    return "| run stamp | |\n|---|---|\n" + "\n".join(f"| {k} | {v} |" for k, v in rows)


def update_page(run_dir: str | Path, *, docs_dir: str | Path = "docs",
                configs_dir: str | Path = "configs", figures: bool = True) -> Path:
    """Writes ``<docs_dir>/results/<study>.md`` from one study run, stamped.

    Args:
        run_dir: A published run folder (``runs/<experiment>/version_N``).
        docs_dir: The documentation sources.
        configs_dir: The repository's ``configs/`` (stamp paths are relative to its parent).
        figures: Also copy the run's PNG figures beside the page.

    Returns:
        The page written.

    Raises:
        NeuralMapError: Not a run folder, no summary or config, or no config of the study.
    """
    run_dir, docs_dir, configs_dir = Path(run_dir), Path(docs_dir), Path(configs_dir)
    if not run_dir.is_dir():
        raise NeuralMapError(f"{run_dir}: not a folder; pass runs/<experiment>/version_N")
    if not configs_dir.is_dir():
        raise NeuralMapError(f"--configs_dir {configs_dir}: not a folder; run from the "
                             "repository root or pass the configs/ folder")
    provenance, body = _read_summary(run_dir)
    saved = run_dir / "config.yaml"
    if not saved.is_file():
        raise NeuralMapError(f"{run_dir}: no config.yaml; not a complete study run")
    run_config = yaml.safe_load(saved.read_text(encoding="utf-8")) or {}
    study = provenance.get("study") or run_config.get("study")
    config, overrides = find_config(run_config, study, configs_dir)
    stamp = RunStamp(
        study=study, config=f"{configs_dir.name}/{config.name}",
        config_sha256=config_sha256(config), seed=provenance.get("seed"),
        commit=provenance.get("commit"), dirty=provenance.get("dirty"),
        date=provenance.get("date", ""), overrides=overrides)
    out_dir = docs_dir / "results"
    out_dir.mkdir(parents=True, exist_ok=True)
    parts = [stamp.line(), f"# Results: `{study}` (stamped run)\n"]
    if stamp.tiny:
        parts.append(f'!!! warning "{TINY_NOTE}"\n    These numbers come from '
                     f"`{stamp.config}`, the study's smoke config: they show what the study "
                     "reports, not what it measures at its stated size. The study's page "
                     "gives the numbers at the stated size.\n")
    parts += [_stamp_table(stamp, run_dir) + "\n", _demote(body.strip()) + "\n"]
    if figures:
        pngs = sorted(run_dir.glob("*.png"))
        fig_dir = out_dir / study
        if pngs:
            fig_dir.mkdir(exist_ok=True)
            for old in fig_dir.glob("*.png"):
                old.unlink()
            parts.append("## Figures\n")
            for png in pngs:
                shutil.copyfile(png, fig_dir / png.name)
                parts.append(f"![{png.stem}]({study}/{png.name})\n")
    page = out_dir / f"{study}.md"
    atomic_write_text(page, "\n".join(parts))
    return page
