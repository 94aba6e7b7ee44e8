"""``python -m neuralmap.docs update RUN_DIR...``: stamped results pages from study,
training and benchmark runs; ``python -m neuralmap.docs check``: every stamp and every
quoted number.

Exit codes: 0 done (``check``: stale benchmark pages are printed as ``warning:`` lines and
fail only with ``--strict``), 1 ``check`` found problems, 2 bad input (one ``error:`` line
on stderr).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from neuralmap.docs.stamp import check_page
from neuralmap.docs.trace import TRACED_PAGES, check_linked_page, check_study_page
from neuralmap.docs.update import update_page
from neuralmap.exceptions import NeuralMapError


def build_parser() -> argparse.ArgumentParser:
    """The ``python -m neuralmap.docs`` parser (``update`` and ``check``)."""
    parser = argparse.ArgumentParser(prog="python -m neuralmap.docs", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    update = sub.add_parser("update", help="copy runs' summary.md into docs/results/, stamped")
    update.add_argument("run_dirs", nargs="+", metavar="RUN_DIR",
                        help="published run folders (runs/<experiment>/version_N) of a "
                             "study, a training run or a benchmark")
    update.add_argument("--docs_dir", default="docs", help="documentation sources (docs)")
    update.add_argument("--configs_dir", default="configs", help="shipped configs (configs)")
    update.add_argument("--no_figures", action="store_true", help="do not copy the PNGs")
    update.add_argument("--page", default=None, metavar="NAME",
                        help="page name for one training or benchmark run (bench_gins_log_cli: "
                             "a second run of a benchmark with other options)")
    check = sub.add_parser(
        "check", help="check every docs/results/*.md stamp and the numbers of docs/studies/*.md"
                      f" and of {', '.join(TRACED_PAGES)}")
    check.add_argument("--docs_dir", default="docs")
    check.add_argument("--repo_root", default=".")
    check.add_argument("--strict", action="store_true",
                       help="a stale benchmark page (its script changed) fails too")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    args = build_parser().parse_args(argv)
    try:
        if args.command == "update":
            if args.page is not None and len(args.run_dirs) != 1:
                raise NeuralMapError(f"--page {args.page}: names the page of one run; got "
                                     f"{len(args.run_dirs)} run folders")
            for run_dir in args.run_dirs:
                page = update_page(run_dir, docs_dir=args.docs_dir,
                                   configs_dir=args.configs_dir,
                                   figures=not args.no_figures, page_name=args.page)
                print(f"{run_dir} -> {page}", flush=True)
            return 0
        warnings: list[str] = []
        problems = [p for page in sorted(Path(args.docs_dir, "results").glob("*.md"))
                    if page.name != "index.md"
                    for p in check_page(page, args.repo_root, warnings=warnings)]
        problems += [p for page in sorted(Path(args.docs_dir, "studies").glob("*.md"))
                     if page.name != "index.md"
                     for p in check_study_page(page, args.repo_root)]
        problems += [p for pattern in TRACED_PAGES
                     for page in sorted(Path(args.docs_dir).glob(pattern))
                     for p in check_linked_page(page, args.repo_root)]
        for problem in problems:
            print(problem)
        for warning in warnings:
            print(f"warning: {warning}")
        return 1 if problems or (args.strict and warnings) else 0
    except NeuralMapError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
