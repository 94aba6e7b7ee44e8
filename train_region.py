"""Replaced by ``python train.py region`` (same option style as every trainer).

``python train_region.py SOURCE... --out DIR --steps N`` is now
``python train.py region --data.path SOURCE --out DIR --model.steps N``; this stub only
says so.
"""

import sys

if __name__ == "__main__":
    print("error: train_region.py is replaced by `python train.py region`: e.g. "
          "`python train.py region --data.path \"srtm/*.hgt\" --out runs/two_tiles "
          "--trainer.devices 2` (options: python train.py region --help).", file=sys.stderr)
    sys.exit(2)
