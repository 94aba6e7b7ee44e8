"""Run a study: ``python evaluate.py [--config configs/<study>.yaml] [--key value ...]``.

The default study is the terrain-aided navigation Monte Carlo (``configs/tan.yaml``); the
config's ``study:`` key picks another. Logic lives in :mod:`neuralmap.studies`.
"""

import sys

try:  # importing torch takes seconds: Ctrl-C then is an interrupt too, not a traceback
    from neuralmap.studies.cli import main
except KeyboardInterrupt:
    print("evaluate.py: interrupted; nothing was written.", file=sys.stderr)
    sys.exit(130)

if __name__ == "__main__":
    sys.exit(main())
