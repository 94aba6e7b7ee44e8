"""Run a study: ``python evaluate.py [--config configs/<study>.yaml] [--key value ...]``.

The default study is the terrain-aided navigation Monte Carlo (``configs/tan.yaml``); the
config's ``study:`` key picks another. Logic lives in `neuralmap.studies`.
"""

import sys

from neuralmap.entry import evaluate  # standard library only: Ctrl-C while importing exits 130

if __name__ == "__main__":
    sys.exit(evaluate())
