"""Numbers traced to runs: a page may quote a measured number only from a stamped page.

A study page ``docs/studies/<study>.md`` describes the study and quotes its results; the
numbers come from ``docs/results/<study>.md``, the stamped run. Every decimal number of the
study page's prose and tables (``20.4``, ``1.16``, ``0.025``) must occur in that page or in
the study's config file ``configs/<study>.yaml``; integers (run counts, seeds, σ0 values)
and code spans (parameters, commands) are not checked.

A study page may also quote the stamped pages it links (another tile's run of the
study, ``results/tan_synthetic.md``).

Every other page of the site (`TRACED_PAGES`: getting started, guides, benchmarks,
training, data, known gaps, architecture, ...) takes its numbers from the stamped pages it
links (``results/bench_filter.md``, ``results/train_train.md``, ...) and the config files
it names (``configs/train.yaml``). There a number may be quoted rounded: ``0.71`` is traced
by a stamped ``0.7122`` (a study page quotes its page's digits exactly).

A bound is not a result: a number written right after ``target``, ``≤``, ``≥``, ``<`` or
``>`` (``target 1.10×``, ``≤ 1.05×``) is a requirement and is not traced.
"""

from __future__ import annotations

import re
from pathlib import Path

__all__ = ["TRACED_PAGES", "check_linked_page", "check_study_page", "linked_results",
           "untraced_numbers"]

#: The pages besides the study pages whose numbers are traced (globs under ``docs/``):
#: every page of the site but the stamped pages themselves, the study pages (traced by
#: `check_study_page`) and the API reference (docstrings).
TRACED_PAGES = ("*.md", "guides/*.md", "training/*.md")

#: A decimal number standing on its own (not part of a word, version or path).
_DECIMAL = re.compile(r"(?<![\w.])\d+\.\d+(?![\d.])")
#: A bound (a requirement, not a result): a decimal right after "target", ≤, ≥, < or >.
_BOUND = re.compile(r"(?:\btargets?:?|[≤≥<>])\s*\d+\.\d+(?![\d.])", re.IGNORECASE)
#: Inline code spans and fenced code blocks.
_CODE = re.compile(r"```.*?```|`[^`\n]*`", re.DOTALL)
#: A markdown link target ending in ``.md`` (an anchor allowed).
_LINK = re.compile(r"\]\(([^)\s#]+\.md)(?:#[^)]*)?\)")
#: A config file named in a page.
_CONFIG = re.compile(r"configs/[\w./-]+\.yaml")


def _rounded(number: str, traced: set[str]) -> bool:
    """Whether ``number`` is a traced number with more decimals, rounded (``0.71`` from
    ``0.7122``); numbers of one significant digit must match exactly."""
    decimals = len(number.split(".")[1])
    if len(number.replace(".", "").lstrip("0")) < 2:
        return False
    return any(len(t.split(".")[1]) > decimals and f"{float(t):.{decimals}f}" == number
               for t in traced)


def untraced_numbers(page_text: str, sources: list[str], *, rounded: bool = False) -> list[str]:
    """The decimal numbers of ``page_text`` (outside code) found in none of ``sources``.

    Args:
        page_text: The study page's Markdown.
        sources: The texts the numbers may come from (stamped page, config).
        rounded: Also accept a source number with more decimals rounded to the quoted ones
            (``0.71`` from ``0.7122``; two significant digits at least).

    Returns:
        The untraced numbers, in page order (repeats kept once).
    """
    prose = _BOUND.sub(" ", _CODE.sub(" ", page_text))
    traced = set()
    for source in sources:
        traced.update(_DECIMAL.findall(source))
    missing: list[str] = []
    for number in _DECIMAL.findall(prose):
        if number in traced or number in missing or (rounded and _rounded(number, traced)):
            continue
        missing.append(number)
    return missing


def check_study_page(page: str | Path, repo_root: str | Path) -> list[str]:
    """What is wrong with a study page's numbers (empty when every one is traced).

    Args:
        page: A ``docs/studies/<study>.md`` page.
        repo_root: The repository root (holding ``docs/results/`` and ``configs/``).
    """
    page, root = Path(page), Path(repo_root)
    study = page.stem
    results = root / "docs" / "results" / f"{study}.md"
    if not results.is_file():
        return [f"{page}: no stamped results page docs/results/{study}.md to quote from; "
                "stamp a run with `python -m neuralmap.docs update RUN_DIR`"]
    sources = [results.read_text(encoding="utf-8")]
    config = root / "configs" / f"{study}.yaml"
    if config.is_file():
        sources.append(config.read_text(encoding="utf-8"))
    problems, linked = _stamped_sources(page, root)
    missing = untraced_numbers(page.read_text(encoding="utf-8"), sources + linked)
    if missing:
        problems.append(
            f"{page}: {', '.join(missing)} not on the stamped page "
            f"{results.relative_to(root)}, a stamped page it links, nor in its config; quote "
            "numbers from the stamped run only (or stamp a run that measures them)")
    return problems


def _stamped_sources(page: Path, root: Path) -> tuple[list[str], list[str]]:
    """The problems of the results pages ``page`` links and the texts of the stamped ones."""
    from neuralmap.docs.stamp import read_stamp

    sources, problems = [], []
    for linked in linked_results(page, root / "docs"):
        if not linked.is_file():
            continue  # a broken link: the strict site build names it
        try:
            stamped = read_stamp(linked) is not None
        except ValueError:
            stamped = False
        if not stamped:
            problems.append(f"{page}: links {linked.name}, which carries no run stamp")
            continue
        sources.append(linked.read_text(encoding="utf-8"))
    return problems, sources


def linked_results(page: str | Path, docs_dir: str | Path) -> list[Path]:
    """The pages of ``<docs_dir>/results/`` that ``page`` links to (in page order)."""
    page, results = Path(page), (Path(docs_dir) / "results").resolve()
    found: list[Path] = []
    for target in _LINK.findall(_CODE.sub(" ", page.read_text(encoding="utf-8"))):
        path = (page.parent / target).resolve()
        if path.parent == results and path.name != "index.md" and path not in found:
            found.append(path)
    return found


def check_linked_page(page: str | Path, repo_root: str | Path) -> list[str]:
    """What is wrong with the numbers of a page of `TRACED_PAGES` (empty when each one is
    on a stamped page it links or in a config file it names).

    Args:
        page: A page under ``docs/`` (``docs/benchmarks.md``).
        repo_root: The repository root (holding ``docs/`` and ``configs/``).
    """
    page, root = Path(page), Path(repo_root)
    text = page.read_text(encoding="utf-8")
    problems, sources = _stamped_sources(page, root)
    for name in sorted(set(_CONFIG.findall(text))):
        if (root / name).is_file():
            sources.append((root / name).read_text(encoding="utf-8"))
    missing = untraced_numbers(text, sources, rounded=True)
    if missing:
        problems.append(f"{page}: {', '.join(missing)} on no stamped page it links nor in a "
                        "config it names; quote numbers from a stamped run only and link its "
                        "page (docs/results/bench_*.md, train_*.md, <study>.md)")
    return problems
