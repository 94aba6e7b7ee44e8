"""Third-party notices a training run does not print: Lightning's product tips and a
deprecation warning that Lightning's own code triggers inside torch.

Neither says anything about the user's run or asks anything of the user:

* Lightning logs "💡 Tip: For seamless cloud logging ... litlogger" and "💡 Tip: For
  seamless cloud uploads ... litmodels" through its rank-zero INFO logger whenever a
  Trainer starts. A filter on those loggers drops records that start with the tip marker;
  every other Lightning line ("GPU available: ...") stays.
* ``lightning/pytorch/utilities/_pytree.py`` uses ``torch.utils._pytree.LeafSpec``, which
  torch ≥ 2.9 marks deprecated (a ``FutureWarning`` naming ``isinstance(treespec, LeafSpec)``).
  The call is Lightning's, not ours; only that message is ignored.
"""

from __future__ import annotations

import contextlib
import logging
import warnings
from collections.abc import Iterator

__all__ = ["TIP_MARKER", "quiet_lightning", "silence_lightning_notices"]

#: How Lightning's advertisement lines begin.
TIP_MARKER = "💡 Tip:"

#: The loggers Lightning's ``rank_zero_info`` writes to (the package and its fabric twin).
_TIP_LOGGERS = (
    "lightning.pytorch.utilities.rank_zero",
    "lightning.fabric.utilities.rank_zero",
    "lightning_fabric.utilities.rank_zero",
    "pytorch_lightning.utilities.rank_zero",
)

#: The torch deprecation message that Lightning's pytree helper triggers (a regex).
_PYTREE_MESSAGE = r"`isinstance\(treespec, LeafSpec\)` is deprecated"


class _DropTips(logging.Filter):
    """Drops the log records that are Lightning's product tips."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.getMessage()).lstrip().startswith(TIP_MARKER)


_FILTER = _DropTips()


def silence_lightning_notices() -> None:
    """Installs the tip filter on Lightning's loggers and the warning filter in the
    current warning context (idempotent; call before a Trainer is built)."""
    for name in _TIP_LOGGERS:
        logger = logging.getLogger(name)
        if _FILTER not in logger.filters:
            logger.addFilter(_FILTER)
    warnings.filterwarnings("ignore", message=_PYTREE_MESSAGE, category=FutureWarning)


@contextlib.contextmanager
def quiet_lightning() -> Iterator[None]:
    """A block (building the CLI, ``trainer.fit``) without the notices; the warning filter
    is undone on exit, the tip filter (which drops nothing else) stays."""
    with warnings.catch_warnings():
        silence_lightning_notices()
        yield
