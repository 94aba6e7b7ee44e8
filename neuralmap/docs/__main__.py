"""``python -m neuralmap.docs update RUN_DIR...``: stamped results pages from study runs.

Exit codes: 0 done, 2 bad input (one ``error:`` line on stderr).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from neuralmap.docs.stamp import check_page
from neuralmap.docs.trace import check_study_page
from neuralmap.docs.update import update_page
from neuralmap.exceptions import NeuralMapError


def build_parser() -> argparse.ArgumentParser:
    """The ``python -m neuralmap.docs`` parser (``update`` and ``check``)."""
    parser = argparse.ArgumentParser(prog="python -m neuralmap.docs", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    update = sub.add_parser("update", help="copy runs' summary.md into docs/results/, stamped")
    update.add_argument("run_dirs", nargs="+", metavar="RUN_DIR",
                        help="published study run folders (runs/<experiment>/version_N)")
    update.add_argument("--docs_dir", default="docs", help="documentation sources (docs)")
    update.add_argument("--configs_dir", default="configs", help="shipped configs (configs)")
    update.add_argument("--no_figures", action="store_true", help="do not copy the PNGs")
    check = sub.add_parser(
        "check", help="check every docs/results/*.md stamp and the numbers of docs/studies/*.md")
    check.add_argument("--docs_dir", default="docs")
    check.add_argument("--repo_root", default=".")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    args = build_parser().parse_args(argv)
    try:
        if args.command == "update":
            for run_dir in args.run_dirs:
                page = update_page(run_dir, docs_dir=args.docs_dir,
                                   configs_dir=args.configs_dir,
                                   figures=not args.no_figures)
                print(f"{run_dir} -> {page}", flush=True)
            return 0
        problems = [p for page in sorted(Path(args.docs_dir, "results").glob("*.md"))
                    if page.name != "index.md" for p in check_page(page, args.repo_root)]
        problems += [p for page in sorted(Path(args.docs_dir, "studies").glob("*.md"))
                     if page.name != "index.md"
                     for p in check_study_page(page, args.repo_root)]
        for problem in problems:
            print(problem)
        return 1 if problems else 0
    except NeuralMapError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
