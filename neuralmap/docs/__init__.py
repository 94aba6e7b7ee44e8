"""Documentation helpers: results pages generated from runs and stamped.

A study run writes ``summary.md`` (its headline table and claims) beside its report, a
training run (``train.py``) one with its fit metrics, a benchmark (`bench_run`) one with
its printed tables; ``python -m neuralmap.docs update RUN_DIR...`` copies it into
``docs/results/`` (``<study>.md``, ``train_<config>.md``, ``bench_<name>.md``) with a run
stamp (the config file or benchmark script and its hash, seed, commit, date, machine), and
`check_page` tells whether a page's stamp still matches the repository's file;
`check_study_page` that a study page quotes only numbers of its stamped page and
`check_linked_page` that a page of `TRACED_PAGES` quotes only numbers of the stamped pages
it links.
"""

from neuralmap.docs.stamp import RunStamp, check_page, config_sha256, read_stamp
from neuralmap.docs.trace import (
    TRACED_PAGES,
    check_linked_page,
    check_study_page,
    linked_results,
    untraced_numbers,
)
from neuralmap.docs.update import update_page

__all__ = ["TRACED_PAGES", "RunStamp", "check_linked_page", "check_page", "check_study_page",
           "config_sha256", "linked_results", "read_stamp", "untraced_numbers", "update_page"]
