"""Fit a neural terrain map to a DEM tile: ``python train.py [--config configs/train.yaml]``."""

from neuralmap.training.cli import main

if __name__ == "__main__":
    main()
