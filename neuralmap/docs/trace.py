"""Numbers traced to runs: a study page may quote a measured number only from its stamped
results page.

A study page ``docs/studies/<study>.md`` describes the study and quotes its results; the
numbers come from ``docs/results/<study>.md``, the stamped run. Every decimal number of the
study page's prose and tables (``20.4``, ``1.16``, ``0.025``) must occur in that page or in
the study's config file ``configs/<study>.yaml``; integers (run counts, seeds, σ0 values)
and code spans (parameters, commands) are not checked.
"""

from __future__ import annotations

import re
from pathlib import Path

__all__ = ["check_study_page", "untraced_numbers"]

#: A decimal number standing on its own (not part of a word, version or path).
_DECIMAL = re.compile(r"(?<![\w.])\d+\.\d+(?![\d.])")
#: Inline code spans and fenced code blocks.
_CODE = re.compile(r"```.*?```|`[^`\n]*`", re.DOTALL)


def untraced_numbers(page_text: str, sources: list[str]) -> list[str]:
    """The decimal numbers of ``page_text`` (outside code) found in none of ``sources``.

    Args:
        page_text: The study page's Markdown.
        sources: The texts the numbers may come from (stamped page, config).

    Returns:
        The untraced numbers, in page order (repeats kept once).
    """
    prose = _CODE.sub(" ", page_text)
    traced = set()
    for source in sources:
        traced.update(_DECIMAL.findall(source))
    missing: list[str] = []
    for number in _DECIMAL.findall(prose):
        if number not in traced and number not in missing:
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
    missing = untraced_numbers(page.read_text(encoding="utf-8"), sources)
    if not missing:
        return []
    return [f"{page}: {', '.join(missing)} not on the stamped page {results.relative_to(root)}"
            " nor in its config; quote numbers from the stamped run only (or stamp a run "
            "that measures them)"]
