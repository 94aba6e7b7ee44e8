"""One outputs writer for every study: report.md, summary.md, results.json, PNGs, TensorBoard,
config.yaml.

A study writes through `StudyOutputs` while it runs; everything lands in a hidden
staging folder under ``<runs_dir>/<experiment>/`` and is published as the next free
``version_<N>`` only by `StudyOutputs.finalize`, so an interrupted or failed study
leaves nothing that looks complete (and no staging folder either).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import yaml

from neuralmap.io import (
    atomic_write_figure,
    atomic_write_json,
    atomic_write_text,
    make_staging_dir,
    publish_dir,
    to_jsonable,
)
from neuralmap.machine import machine

__all__ = [
    "DOES_NOT_HOLD",
    "HOLDS",
    "MIN_CONVERGED",
    "MIN_CONVERGED_FRACTION",
    "NOT_ENOUGH",
    "NOT_MEASURED",
    "PARTLY",
    "VERDICTS",
    "Claim",
    "RunCounts",
    "StudyOutputs",
    "SUMMARY_MARK",
    "markdown_table",
    "run_provenance",
    "verdict",
]

# ---------------------------------------------------------------------------- verdicts
#: The verdict vocabulary of every study's claims table. A verdict is one of these words,
#: optionally followed by a parenthesised detail ("does not hold (by 12 %)",
#: "not enough converged runs (6 of 8; a verdict needs ≥ 30 and half)",
#: "not measured (no neural map)").
HOLDS = "holds"
PARTLY = "partly"
DOES_NOT_HOLD = "does not hold"
NOT_ENOUGH = "not enough converged runs"
NOT_MEASURED = "not measured"
VERDICTS: tuple[str, ...] = (HOLDS, PARTLY, DOES_NOT_HOLD, NOT_ENOUGH, NOT_MEASURED)

#: Converged runs a claim needs before it gets a verdict: at least this many, and at
#: least this fraction of the runs the claim is about.
MIN_CONVERGED = 30
MIN_CONVERGED_FRACTION = 0.5


@dataclass(frozen=True)
class RunCounts:
    """How many Monte Carlo runs a claim rests on.

    Attributes:
        good: Runs that count for the claim: finished, finite, numerically healthy and
            not diverged ("converged").
        total: Runs the claim is about (e.g. the on-map runs), numerical failures
            included.
        failed: Numerical failures among ``total`` (non-finite or unhealthy filter):
            they count against every accuracy claim, never silently dropped.
    """

    good: int
    total: int
    failed: int = 0

    @classmethod
    def from_metrics(cls, m: Any) -> RunCounts:
        """From a `navigation_metrics` dict: total = runs
        not excluded as off the map (non-finite runs included), failed = non-finite +
        unhealthy, good = converged."""
        failed = int(m.get("n_nonfinite") or 0) + int(m.get("n_unhealthy") or 0)
        total = int(m.get("n_included") or 0) + int(m.get("n_nonfinite") or 0)
        return cls(good=int(m.get("n_converged") or 0), total=total, failed=failed)

    def enough(self, min_converged: int = MIN_CONVERGED) -> bool:
        """At least ``min_converged`` good runs and at least half of ``total``."""
        return self.good >= min_converged and self.good >= MIN_CONVERGED_FRACTION * self.total

    @staticmethod
    def weakest(*counts: RunCounts) -> RunCounts:
        """Of the counts a comparison rests on, the one with the fewest good runs (most
        numerical failures on ties): the comparison is only as sound as that one."""
        return min(counts, key=lambda c: (c.good, -c.failed))

    def all_runs(self) -> RunCounts:
        """The counts of a claim over all runs (divergence rate, all-run RMSE): every run
        of ``total`` is part of the measurement, so the verdict needs ``total`` runs."""
        return RunCounts(good=self.total, total=self.total, failed=self.failed)

    @property
    def bad_rate(self) -> float | None:
        """Share of ``total`` that diverged or failed numerically (None when empty)."""
        return (self.total - self.good) / self.total if self.total else None

    def too_few(self, min_converged: int = MIN_CONVERGED) -> str:
        """The verdict when `enough` is False: "not enough converged runs (n of N)"."""
        failed = f", {self.failed} failed numerically" if self.failed else ""
        return (f"{NOT_ENOUGH} ({self.good} of {self.total}{failed}; a verdict needs "
                f"≥ {min_converged} and half)")


def verdict(holds: bool | None, *, partly: bool = False, runs: RunCounts | None = None,
            min_converged: int = MIN_CONVERGED, detail: str | None = None) -> str:
    """The one verdict rule of every study.

    Args:
        holds: The measured comparison (None or NaN-based: nothing measured).
        partly: When ``holds`` is False, whether the weaker bound is met.
        runs: The runs the claim rests on; too few converged runs give "not enough
            converged runs (n of N)" whatever ``holds`` says.
        min_converged: Converged runs a verdict needs.
        detail: Text appended in parentheses (e.g. "by 12 %", or why nothing was measured).

    Returns:
        A verdict of the `VERDICTS` vocabulary.
    """
    if runs is not None and not runs.enough(min_converged):
        return runs.too_few(min_converged)
    if holds is None:
        word = NOT_MEASURED
    else:
        word = HOLDS if holds else (PARTLY if partly else DOES_NOT_HOLD)
    return f"{word} ({detail})" if detail else word


def check_verdict(text: str) -> str:
    """Returns ``text`` if it is a verdict of the vocabulary; raises ValueError otherwise
    (a study bug, not a user error)."""
    if not any(text == v or text.startswith(v + " (") for v in VERDICTS):
        raise ValueError(f"verdict {text!r} is not in the vocabulary {VERDICTS}")
    return text


@dataclass
class Claim:
    """A paper's claim beside the measured number.

    Attributes:
        paper: Which paper (e.g. ``"SEEDS 004"``) or ``"toolkit target"``.
        claim: The claim in words.
        measured: What this run measured, in words and numbers.
        verdict: A verdict of `VERDICTS` (see `verdict`).
        detail: How the verdict was reached (the rule), optional.
    """

    paper: str
    claim: str
    measured: str
    verdict: str
    detail: str = ""


def _cell(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}" if abs(value) < 1e4 else f"{value:.3e}"
    return "n/a" if value is None else str(value)


def markdown_table(headers: list[str], rows: list[list[Any]]) -> str:
    """A GitHub-flavoured markdown table (floats to 4 significant digits, None as n/a)."""
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(_cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


#: First line of every ``summary.md``: this mark, then the run's provenance as JSON (read by
#: ``python -m neuralmap.docs update``).
SUMMARY_MARK = "<!-- neuralmap-run:"


def run_provenance(config: Any) -> dict[str, Any]:
    """Where a run's numbers come from: study, experiment, seed, source commit, date.

    The commit is that of the git checkout the package runs from (``None`` outside one);
    ``dirty`` says whether tracked files differed from it.
    """
    here = Path(__file__).resolve().parent

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", str(here), *args], capture_output=True,
                                  text=True, timeout=10, check=False)
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no") if commit else None
    return {
        "study": getattr(config, "study", ""),
        "experiment": getattr(config, "experiment", ""),
        "seed": getattr(config, "seed", None),
        "commit": commit,
        "dirty": bool(status) if status is not None else None,
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }


def _first_table(markdown: str) -> str | None:
    """The first markdown table of ``markdown`` with the heading above it (if any)."""
    lines = markdown.splitlines()
    for i, line in enumerate(lines):
        if line.startswith("|") and i + 1 < len(lines) and lines[i + 1].startswith("|---"):
            end = i
            while end < len(lines) and lines[end].startswith("|"):
                end += 1
            head = next((lines[k] for k in range(i - 1, -1, -1) if lines[k].startswith("#")),
                        None)
            table = "\n".join(lines[i:end])
            return (f"## {head.lstrip('#').strip()}\n\n" if head else "") + table
    return None


class StudyOutputs:
    """Collects a study's outputs and publishes them as one complete run folder.

    Use as a context manager (the CLI does this)::

        with StudyOutputs(root, config=config, title="...") as outputs:
            run(config, outputs)
            out_dir = outputs.finalize()

    Attributes:
        dir: The staging folder to write extra files into (published by finalize).
        results: The dict that becomes ``results.json`` (the study fills it).
        claims: The claims added with `add_claim`.
    """

    def __init__(self, root: str | Path, *, config: Any, title: str, echo: bool = True,
                 tensorboard: bool = True) -> None:
        self.root = Path(root)
        self.config = config
        self.title = title
        self.echo = echo
        self.tensorboard = tensorboard
        self.results: dict[str, Any] = {}
        self.claims: list[Claim] = []
        self._sections: list[str] = []
        self._writer: Any = None
        self._staging: Path | None = None
        self.published: Path | None = None
        self._report: str | None = None
        self._headline: str | None = None
        self._started = time.monotonic()  # the study's wall time runs from here
        self._machine = machine()

    def __enter__(self) -> StudyOutputs:
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        if self._staging is not None and self._staging.exists():
            shutil.rmtree(self._staging, ignore_errors=True)

    @property
    def dir(self) -> Path:
        """The staging folder (created on first use, so a study that fails early writes
        nothing at all)."""
        if self._staging is None:
            self._staging = make_staging_dir(self.root)
        return self._staging

    # ------------------------------------------------------------------ content
    def add_text(self, markdown: str) -> None:
        """Appends a markdown paragraph (or section) to the report."""
        self._sections.append(markdown.rstrip() + "\n")

    def add_table(self, title: str, headers: list[str], rows: list[list[Any]],
                  *, note: str | None = None, headline: bool = False) -> str:
        """Appends a table to the report (and prints it); returns its markdown.

        ``headline=True`` makes it the table of ``summary.md`` (default: the report's first).
        """
        table = markdown_table(headers, rows)
        text = f"### {title}\n\n{table}\n" + (f"\n{note}\n" if note else "")
        self._sections.append(text)
        if headline:
            self._headline = f"## {title}\n\n{table}"
        if self.echo:
            print(f"\n{title}\n{table}" + (f"\n{note}" if note else ""), flush=True)
        return table

    def add_figure(self, name: str, fig: Any, caption: str) -> Path:
        """Saves ``fig`` as ``<name>.png``, shows it in the report and in TensorBoard."""
        path = atomic_write_figure(self.dir / f"{name}.png", fig)
        self._sections.append(f"![{caption}]({name}.png)\n\n*{caption}*\n")
        writer = self.writer()
        if writer is not None:
            writer.add_figure(f"figures/{name}", fig)
        return path

    def add_claim(self, paper: str, claim: str, measured: str, verdict: str, *,
                  runs: RunCounts | None = None, min_converged: int = MIN_CONVERGED,
                  detail: str = "") -> Claim:
        """Records a paper's claim beside the measured number (report and results.json).

        Args:
            paper: Source (``"SEEDS 002"``, ``"toolkit target"``).
            claim: The claim in words.
            measured: What was measured.
            verdict: A verdict of `VERDICTS` (build it with `verdict`).
            runs: The Monte Carlo runs the claim rests on: too few converged runs replace
                the verdict by "not enough converged runs (n of N)", and numerical
                failures are named in ``measured``.
            min_converged: Converged runs a verdict needs.
            detail: How the verdict was reached (a "how" column in the report).

        Raises:
            ValueError: ``verdict`` is not of the vocabulary.
        """
        check_verdict(verdict)
        if runs is not None:
            if not runs.enough(min_converged):
                verdict = runs.too_few(min_converged)
            if runs.failed:
                measured = f"{measured}; {runs.failed} of {runs.total} runs failed numerically"
        item = Claim(paper, claim, measured, verdict, detail)
        self.claims.append(item)
        if self.echo:
            print(f"claim ({paper}): {claim}: {measured} -> {verdict}", flush=True)
        return item

    def writer(self) -> Any:
        """The TensorBoard ``SummaryWriter`` of this run (None when disabled)."""
        if not self.tensorboard:
            return None
        if self._writer is None:
            # here, not at the top: torch's TensorBoard writer takes ~0.7 s to import and a
            # run with --tensorboard false never needs it
            from torch.utils.tensorboard import SummaryWriter

            self._writer = SummaryWriter(log_dir=str(self.dir))
        return self._writer

    def log_scalar(self, tag: str, value: float, step: int = 0) -> None:
        """Logs one scalar to TensorBoard (ignored when disabled or not finite)."""
        writer = self.writer()
        if writer is not None and value is not None and value == value:
            writer.add_scalar(tag, float(value), step)

    def log_curve(self, tag: str, values: Any, *, step_scale: float = 1.0) -> None:
        """Logs a curve (sequence of values) as TensorBoard scalars, step = index·scale."""
        for k, value in enumerate(list(values)):
            if value is not None:
                self.log_scalar(tag, float(value), int(round(k * step_scale)))

    # ------------------------------------------------------------------ publish
    def set_report(self, markdown: str) -> None:
        """Uses ``markdown`` as the whole report (a study that renders its own layout)."""
        self._report = markdown

    def render(self) -> str:
        """The report markdown: title, sections in order, then the claims table."""
        if self._report is not None:
            return self._report
        parts = [f"# {self.title}\n"] + self._sections
        if self.claims:
            headers = ["paper", "claim", "measured", "verdict"]
            rows = [[c.paper, c.claim, c.measured, f"**{c.verdict}**"] for c in self.claims]
            if any(c.detail for c in self.claims):
                headers.append("how")
                rows = [[*row, c.detail] for row, c in zip(rows, self.claims, strict=True)]
            parts.append("## Papers' claims beside the measurements\n\n"
                         + markdown_table(headers, rows) + "\n")
        return "\n".join(parts)

    def summary(self) -> str:
        """The run's ``summary.md``: its provenance line, the headline table (the one added
        with ``headline=True``, else the report's first) and the claims table; ``python -m neuralmap.docs update`` copies it
        into the documentation."""
        wall_s = round(time.monotonic() - self._started, 1)
        host = {**self._machine, "load_1min_end": machine()["load_1min"]}
        provenance = json.dumps({**run_provenance(self.config), "wall_s": wall_s,
                                 "machine": host}, sort_keys=True)
        body = self._report if self._report is not None else "\n".join(self._sections)
        parts = [f"{SUMMARY_MARK} {provenance} -->", f"# {self.title}\n"]
        table = self._headline or _first_table(body)
        if table:
            parts.append(table + "\n")
        parts.append(f"Study time: {wall_s} s wall on {host['cpu']}, {host['cores']} cores, "
                     f"torch threads {host['torch_threads']}, load {host['load_1min']} → "
                     f"{host['load_1min_end']}.\n")
        claims = self.render().split("## Papers' claims beside the measurements", 1)
        if len(claims) == 2:
            parts.append("## Papers' claims beside the measurements" + claims[1].rstrip() + "\n")
        return "\n".join(parts)

    def finalize(self) -> Path:
        """Writes report.md, summary.md, results.json and config.yaml and publishes the run
        folder.

        Returns:
            The published ``<runs_dir>/<experiment>/version_<N>`` folder.
        """
        config_dump = to_jsonable(asdict(self.config)) if hasattr(
            self.config, "__dataclass_fields__") else to_jsonable(self.config)
        results = {"study": getattr(self.config, "study", ""), **self.results,
                   "claims": [asdict(c) for c in self.claims], "config": config_dump}
        atomic_write_json(self.dir / "results.json", results)
        atomic_write_text(self.dir / "report.md", self.render())
        atomic_write_text(self.dir / "summary.md", self.summary())
        atomic_write_text(
            self.dir / "config.yaml",
            "# configuration used for this run (python evaluate.py --config <this file>)\n"
            + yaml.safe_dump(config_dump, sort_keys=False),
        )
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        self.published = publish_dir(self.dir, self.root)
        return self.published
