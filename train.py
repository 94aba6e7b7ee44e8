"""Every trainer: ``python train.py [map|noise|region] [--config FILE] [options]``.

``map`` (default) fits a neural map to a DEM tile or a mosaic of tiles, ``noise`` learns
the TAN filter's Q and R from flights, ``region`` fits a region-scale sharded map; see
`neuralmap.training.cli`.
"""

from neuralmap.training.cli import main

if __name__ == "__main__":
    main()
