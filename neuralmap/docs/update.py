"""Copies a run's ``summary.md`` into ``docs/results/``, stamped.

- A study run (``evaluate.py``) goes to ``<study>.md``. The stamp names the config file of
  ``configs/`` the run was made with. It is found, not trusted: every shipped config of
  the run's study is resolved as ``evaluate.py`` resolves it, and the one the run's saved
  ``config.yaml`` differs from least is the run's (the options it set on top are listed in
  the stamp as overrides).
- A training run (``train.py``, `neuralmap.training.run_summary`) goes to
  ``train_<config>.md``, stamped with its last config file, which must be a file of
  ``configs/`` with the SHA-256 the run recorded; its other command-line words are the
  overrides.
- A benchmark run (`neuralmap.docs.bench_run`) goes to ``bench_<name>.md``, stamped with
  its script and the script's SHA-256 at the run; its parsed options are the stamp's
  overrides.
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
from dataclasses import asdict
from pathlib import Path
from typing import Any

import yaml

from neuralmap.docs.stamp import TINY_NOTE, RunStamp, config_sha256
from neuralmap.exceptions import NeuralMapError
from neuralmap.io import atomic_write_text, load_yaml, to_jsonable
from neuralmap.outputs import SUMMARY_MARK

__all__ = ["IGNORED_OPTIONS", "IGNORED_TRAIN_OPTIONS", "find_config", "update_page"]

#: Options that say where and how a run reports, not what it computes.
IGNORED_OPTIONS = frozenset({"runs_dir", "experiment", "tensorboard", "progress"})

#: The same for ``train.py`` (each takes one value).
IGNORED_TRAIN_OPTIONS = frozenset({"--runs_dir", "--experiment",
                                   "--trainer.enable_progress_bar"})


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
    """Headings one level down (the page's own title is the only ``#``); the lines of
    fenced code blocks (a benchmark's ``# comment`` lines) are left as they are."""
    parts = re.split(r"(^```.*?^```[ \t]*$)", markdown, flags=re.MULTILINE | re.DOTALL)
    return "".join(part if part.startswith("```")
                   else re.sub(r"^(#+) ", r"#\1 ", part, flags=re.MULTILINE)
                   for part in parts)


def _shell_value(value: Any) -> str:
    """An override as the studies' CLI reads it, quoted for a shell (``'[a,b]'``)."""
    if isinstance(value, str):
        return shlex.quote(value)
    if isinstance(value, list) and all(isinstance(v, str) for v in value):
        return shlex.quote(f"[{','.join(value)}]")
    return shlex.quote(json.dumps(value))


def _stamp_table(stamp: RunStamp, run_dir: Path) -> str:
    commit = f"`{stamp.commit[:12]}`" if stamp.commit else "unknown (not run from a checkout)"
    if stamp.dirty:
        commit += " with uncommitted changes in the working tree"
    rerun = f"python evaluate.py --config {stamp.config}" + "".join(
        f" --{k} {_shell_value(v)}" for k, v in stamp.overrides.items())
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
    if stamp.machine:  # runs from before studies recorded their machine have none
        rows.insert(4, ("machine", _machine_row(stamp.machine)))
    return "| run stamp | |\n|---|---|\n" + "\n".join(f"| {k} | {v} |" for k, v in rows)


def _train_stamp(provenance: dict[str, Any], configs_dir: Path,
                 summary: Path) -> tuple[RunStamp, str]:
    """The stamp and page name of a training run."""
    configs = provenance.get("configs") or []
    if not configs:
        raise NeuralMapError(f"{summary}: line 1: the training run names no config file; "
                             "stamp only runs of a shipped config (python train.py --config "
                             "configs/<file>.yaml)")
    last = configs[-1]
    shipped = configs_dir / last["name"]
    if not shipped.is_file():
        raise NeuralMapError(f"{summary}: the run's config {last['path']} is not a file of "
                             f"{configs_dir}/; stamp only runs of a shipped config")
    if config_sha256(shipped) != last.get("sha256"):
        raise NeuralMapError(f"{summary}: {configs_dir.name}/{shipped.name} changed since the "
                             "run (its SHA-256 differs from the one the run recorded); rerun "
                             "the training with the current config")
    argv = list(provenance.get("argv") or [])
    overrides: dict[str, Any] = {}
    i = 0
    while i < len(argv):
        word = argv[i]
        key, _, value = word.partition("=")
        if key in ("--config", "-c") or key in IGNORED_TRAIN_OPTIONS:
            i += 1 if value else 2
            continue
        if value:
            overrides[key.lstrip("-")] = value
            i += 1
        elif i + 1 < len(argv) and not argv[i + 1].startswith("--"):
            overrides[key.lstrip("-")] = argv[i + 1]
            i += 2
        else:
            overrides[key.lstrip("-")] = True
            i += 1
    stamp = RunStamp(
        study=f"train_{provenance.get('mode', 'map')}",
        config=f"{configs_dir.name}/{shipped.name}", config_sha256=last["sha256"],
        seed=provenance.get("seed"), commit=provenance.get("commit"),
        dirty=provenance.get("dirty"), date=provenance.get("date", ""), overrides=overrides,
        kind="train", argv=argv, machine=provenance.get("machine"))
    return stamp, f"train_{shipped.stem}"


def _bench_stamp(provenance: dict[str, Any], summary: Path) -> tuple[RunStamp, str]:
    """The stamp and page name of a benchmark run."""
    for key in ("bench", "script", "script_sha256"):
        if not provenance.get(key):
            raise NeuralMapError(f"{summary}: line 1: the benchmark provenance lacks {key!r}; "
                                 "rerun the benchmark")
    stamp = RunStamp(
        study=provenance["bench"], config=provenance["script"],
        config_sha256=provenance["script_sha256"], seed=provenance.get("seed"),
        commit=provenance.get("commit"), dirty=provenance.get("dirty"),
        date=provenance.get("date", ""), overrides=dict(provenance.get("options") or {}),
        kind="bench", argv=list(provenance.get("argv") or []),
        machine=provenance.get("machine"))
    return stamp, f"bench_{provenance['bench'].removeprefix('bench_')}"


def _without_out(argv: list[str]) -> list[str]:
    words, skip = [], False
    for word in argv:
        if skip:
            skip = False
        elif word == "--out":
            skip = True
        elif not word.startswith("--out="):
            words.append(word)
    return words


def _machine_row(machine: dict[str, Any] | None) -> str:
    if not machine:
        return "not recorded"
    load = machine.get("load_1min")
    end = machine.get("load_1min_end")
    loads = f"load {load}" + (f" → {end}" if end is not None else "")
    return (f"{machine.get('cpu')}, {machine.get('cores')} cores, torch threads "
            f"{machine.get('torch_threads')} (`OMP_NUM_THREADS={machine.get('omp_num_threads')}`)"
            f", {loads}")


def _run_table(stamp: RunStamp, run_dir: Path) -> str:
    """The stamp table of a training or benchmark page."""
    commit = f"`{stamp.commit[:12]}`" if stamp.commit else "unknown (not run from a checkout)"
    if stamp.dirty:
        commit += " with uncommitted changes in the working tree"
    if stamp.kind == "bench":
        what = ("benchmark", f"`{stamp.config}` (sha256 `{stamp.config_sha256[:12]}`)")
        rerun = " ".join(["python", stamp.config, *_without_out(stamp.argv or [])])
    else:
        what = ("config", f"`{stamp.config}` (sha256 `{stamp.config_sha256[:12]}`)"
                + (f" — **{TINY_NOTE}**" if stamp.tiny else ""))
        mode = stamp.study.removeprefix("train_")
        rerun = " ".join(["python train.py", *([mode] if mode != "map" else []),
                          "--config", stamp.config]
                         + [f"--{k}" + ("" if v is True else f" {v}")
                            for k, v in stamp.overrides.items()])
    rows = [what,
            ("seed", "the script's own" if stamp.seed is None else str(stamp.seed)),
            ("commit", commit), ("date", stamp.date),
            ("machine", _machine_row(stamp.machine)),
            ("rerun", f"`{rerun}`"),
            ("run folder", f"`{run_dir.parent.name}/{run_dir.name}`")]
    if stamp.kind == "train":
        rows.insert(4, ("overrides", ", ".join(f"`{k}`" for k in stamp.overrides) or "none"))
    else:
        rows.insert(4, ("options", ", ".join(f"`{k}={json.dumps(v)}`"
                                             for k, v in stamp.overrides.items()) or "none"))
    return "| run stamp | |\n|---|---|\n" + "\n".join(f"| {k} | {v} |" for k, v in rows)


def update_page(run_dir: str | Path, *, docs_dir: str | Path = "docs",
                configs_dir: str | Path = "configs", figures: bool = True,
                page_name: str | None = None) -> Path:
    """Writes a stamped ``<docs_dir>/results/`` page from one run: ``<config>.md`` for a
    study (the stem of the shipped config found, ``_tiny`` dropped: ``tan.md``,
    ``tan_synthetic.md``), ``train_<config>.md`` for a training run, ``bench_<name>.md``
    for a benchmark.

    Args:
        run_dir: A published run folder (``runs/<experiment>/version_N``).
        docs_dir: The documentation sources.
        configs_dir: The repository's ``configs/`` (stamp paths are relative to its parent).
        figures: Also copy the run's PNG figures beside the page.
        page_name: The page's name instead of the run's (``bench_gins_log_cli``: two runs
            of one benchmark with different options); a training or benchmark run only.

    Returns:
        The page written.

    Raises:
        NeuralMapError: Not a run folder, no summary or config, or no config of the study;
            a training run whose config is not shipped or changed since; a bad
            ``page_name``.
    """
    run_dir, docs_dir, configs_dir = Path(run_dir), Path(docs_dir), Path(configs_dir)
    if not run_dir.is_dir():
        raise NeuralMapError(f"{run_dir}: not a folder; pass runs/<experiment>/version_N")
    if not configs_dir.is_dir():
        raise NeuralMapError(f"--configs_dir {configs_dir}: not a folder; run from the "
                             "repository root or pass the configs/ folder")
    provenance, body = _read_summary(run_dir)
    kind = provenance.get("kind", "study")
    if kind == "study":
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
            date=provenance.get("date", ""), overrides=overrides,
            machine=provenance.get("machine"))
        # One page per shipped config of the study (tan.yaml -> tan, tan_synthetic.yaml ->
        # tan_synthetic); the smoke config writes the study's page, marked as tiny.
        name = config.stem.removesuffix("_tiny")
        title, table = f"# Results: `{name}` (stamped run)\n", None
    elif kind in ("train", "bench"):
        stamp, name = (_train_stamp(provenance, configs_dir, run_dir / "summary.md")
                       if kind == "train" else _bench_stamp(provenance, run_dir / "summary.md"))
        title = (f"# Training: `{stamp.config}` (stamped run)\n" if kind == "train"
                 else f"# Benchmark: `{stamp.config}` (stamped run)\n")
        table = _run_table(stamp, run_dir)
        body = re.sub(r"\A\s*# [^\n]*\n", "", body)  # the page has its own title
    else:
        raise NeuralMapError(f"{run_dir / 'summary.md'}: line 1: unknown run kind {kind!r}")
    if page_name is not None:
        prefix = f"{kind}_"
        if kind == "study" or not re.fullmatch(rf"{prefix}[a-z0-9_]+", page_name):
            raise NeuralMapError(
                f"--page {page_name!r}: a page name is for a training or benchmark run and "
                f"reads {prefix}<letters, digits, _> (this run is a {kind} run)")
        name = page_name
    out_dir = docs_dir / "results"
    out_dir.mkdir(parents=True, exist_ok=True)
    parts = [stamp.line(), title]
    if stamp.tiny:
        parts.append(f'!!! warning "{TINY_NOTE}"\n    These numbers come from '
                     f"`{stamp.config}`, the study's smoke config: they show what the study "
                     "reports, not what it measures at its stated size. The study's page "
                     "gives the numbers at the stated size.\n")
    parts += [(table or _stamp_table(stamp, run_dir)) + "\n", _demote(body.strip()) + "\n"]
    if figures:
        pngs = sorted(run_dir.glob("*.png"))
        fig_dir = out_dir / name
        if pngs:
            fig_dir.mkdir(exist_ok=True)
            for old in fig_dir.glob("*.png"):
                old.unlink()
            parts.append("## Figures\n")
            for png in pngs:
                shutil.copyfile(png, fig_dir / png.name)
                parts.append(f"![{png.stem}]({name}/{png.name})\n")
    page = out_dir / f"{name}.md"
    atomic_write_text(page, "\n".join(parts))
    return page
