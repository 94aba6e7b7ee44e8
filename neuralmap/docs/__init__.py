"""Documentation helpers: results pages generated from study runs and stamped.

A study run writes ``summary.md`` (its headline table and claims) beside its report;
``python -m neuralmap.docs update RUN_DIR...`` copies it into ``docs/results/<study>.md``
with a run stamp (the config file and its hash, seed, commit, date), and
`check_page` tells whether a page's stamp still matches the
repository's config file; `check_study_page` that a study page quotes only numbers
of its stamped page.
"""

from neuralmap.docs.stamp import RunStamp, check_page, config_sha256, read_stamp
from neuralmap.docs.trace import check_study_page, untraced_numbers
from neuralmap.docs.update import update_page

__all__ = ["RunStamp", "check_page", "check_study_page", "config_sha256", "read_stamp",
           "untraced_numbers", "update_page"]
