"""A benchmark run's stamped fragment: what a script under ``benchmarks/`` printed, with
its provenance, as ``summary.md`` + ``results.json`` in a run folder.

Every benchmark script does three things (nothing else changes in it)::

    add_out_option(parser, "bench_filter")          # --out DIR
    run = start_bench(__file__, args)               # after parsing: records stdout from here
    ...                                              # the benchmark prints its tables
    run.finish()                                     # DIR/version_N/summary.md + results.json

``summary.md`` starts with `SUMMARY_MARK` and the provenance (``kind: bench``, the
benchmark's name, its argv and options, the SHA-256 of the script file, seed, commit, date
and the machine: CPU model, cores, torch threads, load) and holds the printed output: its
markdown tables as tables, every other line in text blocks. ``python -m neuralmap.docs
update DIR/version_N`` turns it into ``docs/results/bench_<name>.md``; the script hash is
the benchmark's config (a changed script makes the page stale, which ``check`` reports).
The run folder is staged under a hidden name and published whole (`neuralmap.io`), so an
interrupted benchmark leaves no half-written run.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import sys
from pathlib import Path
from typing import Any

from neuralmap.io import (
    atomic_write_json,
    atomic_write_text,
    make_staging_dir,
    publish_dir,
    to_jsonable,
)
from neuralmap.machine import machine
from neuralmap.outputs import SUMMARY_MARK, run_provenance

__all__ = ["BenchRun", "add_out_option", "machine", "markdown_of_output", "script_sha256",
           "start_bench"]

#: The ``kind`` of a benchmark run's provenance.
BENCH_KIND = "bench"


def script_sha256(path: str | Path) -> str:
    """SHA-256 of a benchmark script's bytes (hex): the benchmark's config in its stamp."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def add_out_option(parser: argparse.ArgumentParser, name: str) -> None:
    """Adds ``--out DIR`` (default ``runs/bench/<name>``): where the stamped run goes.

    A ``--quick`` smoke run is stamped only when ``--out`` is given.
    """
    parser.add_argument(
        "--out", default=None, metavar="DIR",
        help=f"run folder root (default runs/bench/{name}; a --quick run only when given): "
             "summary.md and results.json go to DIR/version_N for "
             "`python -m neuralmap.docs update`")


class _Tee(io.TextIOBase):
    """Writes to the real stdout and keeps a copy (stdout's other attributes pass through)."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream
        self.copy = io.StringIO()

    def write(self, text: str) -> int:
        self.copy.write(text)
        return self._stream.write(text)

    def flush(self) -> None:
        self._stream.flush()

    def isatty(self) -> bool:
        return self._stream.isatty()

    def fileno(self) -> int:
        return self._stream.fileno()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def markdown_of_output(text: str) -> str:
    """A benchmark's printed output as markdown: runs of ``|`` lines that form a table stay
    tables, every other run of lines goes into a ``text`` block (blank runs dropped)."""
    lines = text.rstrip("\n").splitlines()
    parts: list[str] = []
    block: list[str] = []

    def flush_block() -> None:
        while block and not block[-1].strip():
            block.pop()
        if any(line.strip() for line in block):
            parts.append("```text\n" + "\n".join(block) + "\n```")
        block.clear()

    i = 0
    while i < len(lines):
        line = lines[i]
        if (line.startswith("|") and i + 1 < len(lines)
                and lines[i + 1].replace(" ", "").startswith("|---")):
            flush_block()
            end = i
            while end < len(lines) and lines[end].startswith("|"):
                end += 1
            parts.append("\n".join(lines[i:end]))
            i = end
            continue
        if block or line.strip():
            block.append(line)
        i += 1
    flush_block()
    return "\n\n".join(parts) + "\n"


class BenchRun:
    """One benchmark run: records stdout from `start_bench` on, `finish` publishes it.

    Attributes:
        name: The benchmark (the script's stem, ``bench_filter``).
        script: The script file.
        argv: The command-line words the script was given.
        options: The parsed options.
        out: The run folder root (``--out``).
        active: Whether the run is recorded (not a ``--quick`` run without ``--out``).
    """

    def __init__(self, script: str | Path, args: argparse.Namespace,
                 argv: list[str] | None = None) -> None:
        self.script = Path(script).resolve()
        self.name = self.script.stem
        self.argv = list(sys.argv[1:] if argv is None else argv)
        self.options = to_jsonable({k: v for k, v in vars(args).items() if k != "out"})
        out = getattr(args, "out", None)
        self.active = out is not None or not getattr(args, "quick", False)
        self.out = Path(out or Path("runs") / "bench" / self.name)
        self.sha256 = script_sha256(self.script)
        self.machine_start = machine()
        self._origin = run_provenance(argparse.Namespace(study=self.name, experiment="bench",
                                                         seed=self.options.get("seed")))
        self._tee = _Tee(sys.stdout)
        self._stdout = sys.stdout
        if self.active:
            sys.stdout = self._tee

    def provenance(self) -> dict[str, Any]:
        """The ``summary.md`` first-line JSON of this run (the commit and working-tree
        state when it started, the date when it ended)."""
        base = run_provenance(argparse.Namespace(study=self.name, experiment="bench",
                                                 seed=self.options.get("seed")))
        end = machine()
        return {**base, "commit": self._origin["commit"], "dirty": self._origin["dirty"],
                "kind": BENCH_KIND, "bench": self.name,
                "script": f"benchmarks/{self.script.name}", "script_sha256": self.sha256,
                "argv": self.argv, "options": self.options,
                "machine": {**self.machine_start, "load_1min_end": end["load_1min"]}}

    def finish(self, results: dict[str, Any] | None = None, *,
               markdown: str | None = None) -> Path | None:
        """Stops recording and publishes ``<out>/version_N`` with ``summary.md`` and
        ``results.json`` (the provenance, the printed output, ``results``).

        Args:
            results: Numbers the script wants kept machine-readable (optional).
            markdown: The page's body instead of the whole printed output (a script whose
                output is mostly progress lines passes its tables); the output is still
                kept in ``results.json``.

        Returns:
            The published run folder (also printed as the last stdout line); ``None`` for a
            run that is not recorded.
        """
        sys.stdout.flush()
        if sys.stdout is self._tee:
            sys.stdout = self._stdout
        if not self.active:
            return None
        output = self._tee.copy.getvalue()
        provenance = self.provenance()
        body = (f"# Benchmark `{self.name}`\n\n"
                f"`python benchmarks/{self.script.name}"
                + "".join(f" {a}" for a in self.argv) + "`\n\n"
                + markdown_of_output(output if markdown is None else markdown))
        staging = make_staging_dir(self.out)
        try:
            atomic_write_text(staging / "summary.md",
                              f"{SUMMARY_MARK} {json.dumps(provenance, sort_keys=True)} -->\n"
                              + body)
            atomic_write_json(staging / "results.json",
                              {**provenance, "output": output, "results": results or {}})
            published = publish_dir(staging, self.out)
        finally:
            if staging.exists():
                import shutil

                shutil.rmtree(staging, ignore_errors=True)
        print(f"stamped run: {published}", flush=True)
        return published


def start_bench(script: str | Path, args: argparse.Namespace,
                argv: list[str] | None = None) -> BenchRun:
    """Starts recording a benchmark's output (call right after parsing its options).

    Args:
        script: The benchmark script (``__file__``).
        args: Its parsed options (``--out`` among them, see `add_out_option`).
        argv: Its command-line words (default ``sys.argv[1:]``).
    """
    return BenchRun(script, args, argv)
