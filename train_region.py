"""Fit a region-scale neural map: ``python train_region.py SOURCE... --out DIR``.

Mosaics of DEM files, memory-mapped ``.npy`` regions or the paper-size synthetic region,
fitted shard by shard over Lightning's launcher. Logic: :mod:`neuralmap.training.region_cli`.
"""

import sys

from neuralmap.training.region_cli import main

if __name__ == "__main__":
    sys.exit(main())
