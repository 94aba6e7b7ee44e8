"""The run stamp of a results page: which config, seed, commit and date its numbers are from.

The stamp is the page's first line, an HTML comment holding JSON (invisible on the site);
the page repeats it as a table for the reader. Three kinds of run are stamped: a study
(``evaluate.py``; its config of ``configs/``), a training run (``train.py``; its config of
``configs/``) and a benchmark (a script of ``benchmarks/``, whose SHA-256 is its config).
A changed config fails the check; a changed benchmark script makes its page *stale*, a
warning: benchmark numbers belong to a machine and a load, and a docstring edit of a
script must not fail CI until someone reruns a benchmark of several minutes.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from neuralmap.io import load_yaml

__all__ = ["KINDS", "STAMP_MARK", "TINY_NOTE", "RunStamp", "check_page", "config_sha256",
           "read_stamp"]

#: First characters of a stamped results page.
STAMP_MARK = "<!-- neuralmap-stamp:"

#: Sentence every page stamped with a tiny config carries.
TINY_NOTE = "tiny config: a smoke run, not the study's result"

#: The kinds of stamped run: a study, a training run, a benchmark.
KINDS = ("study", "train", "bench")


def config_sha256(path: str | Path) -> str:
    """SHA-256 of a config file's bytes (hex)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


@dataclass
class RunStamp:
    """Provenance of a results page.

    Attributes:
        study: The study (``study:`` key).
        config: The config file, relative to the repository root (``configs/tan_tiny.yaml``).
        config_sha256: SHA-256 of that file when the run was stamped.
        seed: The run's seed (``None``: the scenario's).
        commit: The git commit the run's code came from (``None`` if unknown).
        dirty: Whether the run's working tree had uncommitted changes to tracked files.
        date: When the run finished (UTC, ISO 8601).
        overrides: Options the run set on top of the config file (name -> value); for a
            benchmark, every option it parsed.
        kind: ``study``, ``train`` or ``bench`` (`KINDS`); for a benchmark ``study`` is its
            name and ``config`` its script (``benchmarks/bench_filter.py``).
        argv: The command-line words of a training run or benchmark.
        machine: CPU model, cores, torch threads and load of a benchmark or training run.
    """

    study: str
    config: str
    config_sha256: str
    seed: int | None
    commit: str | None
    dirty: bool | None
    date: str
    overrides: dict[str, Any] = field(default_factory=dict)
    kind: str = "study"
    argv: list[str] | None = None
    machine: dict[str, Any] | None = None

    @property
    def tiny(self) -> bool:
        """Whether the stamp's config is a study's tiny smoke config."""
        return Path(self.config).stem.endswith("_tiny")

    def line(self) -> str:
        """The machine-readable first line of the page."""
        return f"{STAMP_MARK} {json.dumps(asdict(self), sort_keys=True)} -->"


def read_stamp(page: str | Path) -> RunStamp | None:
    """The stamp of a results page, or ``None`` when its first line carries none.

    Raises:
        ValueError: The first line is a stamp whose JSON is damaged or incomplete.
    """
    first = Path(page).read_text(encoding="utf-8").split("\n", 1)[0].strip()
    if not first.startswith(STAMP_MARK):
        return None
    body = first[len(STAMP_MARK):].removesuffix("-->").strip()
    try:
        return RunStamp(**json.loads(body))
    except (json.JSONDecodeError, TypeError) as exc:
        raise ValueError(f"{page}: line 1: damaged run stamp ({exc})") from exc


def check_page(page: str | Path, repo_root: str | Path, *,
               warnings: list[str] | None = None) -> list[str]:
    """What is wrong with a results page's stamp (empty when it is sound).

    A page is sound when its first line is a stamp, the stamp's config file exists in the
    repository with the same SHA-256, names the same study (studies), and a page stamped
    with a tiny config says so. A benchmark page whose script changed since the run is
    sound but stale: the message goes to ``warnings``.

    Args:
        page: A ``docs/results/<name>.md`` page.
        repo_root: The repository root the config path is relative to.
        warnings: Where stale benchmark pages are reported (dropped when ``None``).
    """
    page = Path(page)
    try:
        stamp = read_stamp(page)
    except ValueError as exc:
        return [str(exc)]
    if stamp is None:
        return [f"{page}: no run stamp on line 1; generate the page with "
                "`python -m neuralmap.docs update RUN_DIR`"]
    problems = []
    config = Path(repo_root) / stamp.config
    if stamp.kind not in KINDS:
        return [f"{page}: line 1: run stamp of unknown kind {stamp.kind!r} (one of {KINDS})"]
    if not config.is_file():
        return [f"{page}: stamped with {stamp.config}, which is not in the repository"]
    if stamp.kind == "bench":
        if config_sha256(config) != stamp.config_sha256 and warnings is not None:
            warnings.append(f"{page}: stale: {stamp.config} changed since the run (sha256 "
                            f"{stamp.config_sha256[:12]}, now {config_sha256(config)[:12]}); "
                            "rerun the benchmark and update the page")
        return []
    if config_sha256(config) != stamp.config_sha256:
        problems.append(f"{page}: stamped with {stamp.config} at sha256 "
                        f"{stamp.config_sha256[:12]}, but the file now hashes to "
                        f"{config_sha256(config)[:12]}; rerun the "
                        f"{'training' if stamp.kind == 'train' else 'study'} with the current "
                        "config and update the page")
    data = load_yaml(config.read_text(encoding="utf-8"))
    if stamp.kind == "study" and (not isinstance(data, dict) or data.get("study") != stamp.study):
        problems.append(f"{page}: stamp says study {stamp.study!r} but {stamp.config} "
                        "names another")
    if stamp.tiny and TINY_NOTE not in page.read_text(encoding="utf-8"):
        problems.append(f"{page}: stamped with the tiny config {stamp.config} but does not "
                        f"say so ({TINY_NOTE!r})")
    return problems
