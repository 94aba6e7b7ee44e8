"""Built-in sample tiles: ``"jacksboro"`` (matplotlib's shipped DEM) and ``"synthetic"``."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from neuralmap.dem.readers import SAMPLE_NAMES, as_pair, read_matplotlib_arrays, reject_spacing
from neuralmap.dem.synthetic import synthetic_tile
from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError

#: ``synthetic``, ``synthetic:N`` (N × N) or ``synthetic:NYxNX``.
_SYNTHETIC_RE = re.compile(r"^synthetic(?::(\d+)(?:x(\d+))?)?$", re.IGNORECASE)
#: matplotlib sample file behind ``"jacksboro"``.
JACKSBORO_FILE = "jacksboro_fault_dem.npz"


def is_sample_name(text: str) -> bool:
    """True for ``"jacksboro"`` and the ``"synthetic[:NY[xNX]]"`` forms (case-insensitive)."""
    text = text.strip()
    return text.lower() == "jacksboro" or _SYNTHETIC_RE.match(text) is not None


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
    row 0 is south. ``"synthetic"``: :func:`neuralmap.dem.synthetic_tile` with its defaults
    (seed 0); ``"synthetic:N"`` / ``"synthetic:NYxNX"`` set the shape.

    Args:
        sample: Sample name (see :data:`neuralmap.dem.readers.SAMPLE_NAMES`).
        spacing: Only for ``synthetic``: grid spacing in metres.
        origin: Metric coordinates of node ``[0, 0]`` (default ``(0, 0)``).
        name: Tile name (default: ``"jacksboro"`` / ``"synthetic"``).
        **options: For ``synthetic`` only: ``shape``, ``seed``, ``relief``, ``hurst``.

    Returns:
        The tile.

    Raises:
        NeuralMapError: Unknown sample name, spacing or options given for ``jacksboro``,
            unknown options, a shape given twice.
    """
    text = sample.strip()
    if text.lower() == "jacksboro":
        reject_spacing(spacing, "sample 'jacksboro'")
        if options:
            raise NeuralMapError(
                f"sample 'jacksboro' takes no options, got {sorted(options)}; they apply to "
                "'synthetic' only."
            )
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
    try:
        from matplotlib import cbook
    except ImportError as exc:  # pragma: no cover - matplotlib is a runtime dependency
        raise NeuralMapError("sample 'jacksboro' needs matplotlib: pip install matplotlib.") from exc
    try:
        data = cbook.get_sample_data(JACKSBORO_FILE)
    except (OSError, ValueError) as exc:  # pragma: no cover - broken matplotlib install
        raise NeuralMapError(
            f"sample 'jacksboro': matplotlib's sample file {JACKSBORO_FILE} was not found "
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


__all__ = ["JACKSBORO_FILE", "is_sample_name", "jacksboro_arrays", "load_sample"]
