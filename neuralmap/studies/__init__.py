"""Studies behind one entry point: ``python evaluate.py --config configs/<study>.yaml``.

Each study is one module with a config dataclass and ``run(config, outputs)``; they share
one outputs writer (`StudyOutputs`).
"""

from neuralmap.outputs import StudyOutputs
from neuralmap.studies.base import StudyConfig
from neuralmap.studies.registry import STUDIES, get_study

__all__ = ["STUDIES", "StudyConfig", "StudyOutputs", "get_study"]
