"""The index file of a latent tileset: the region, its tile grid, and one bitstream per tile.

``latent_tileset.json`` (written atomically, last, so a folder without it is no tileset)::

    {"format": "neuralmap-latent-tileset", "format_version": 1,
     "region": DemTile.describe() of the whole region (name, shape, spacing, origin,
               extent, fingerprint, geo / projected georeference, units),
     "layout": TilesetLayout.describe() (core rows / columns, overlap, seams, blend widths),
     "tiles": [{"row": i, "col": j, "file": "tiles/r000_c000.nlat", "sha256": "...",
                "bytes": n, "core": [r0, r1, c0, c1], "window": [r0, r1, c0, c1],
                "extent": [xmin, xmax, ymin, ymax] of the window, "fingerprint": window
                DemTile.fingerprint, "source": DEM file, "metrics": {...}}, ...],
     "info": {"metrics": region metrics, "training": settings}}

Tile files are ordinary latent-map bitstreams (`neuralmap.terrain.latent.bitstream`), named
relative to the index; the ``sha256`` of each is checked when the tile is decoded.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from neuralmap.exceptions import NeuralMapError
from neuralmap.io import atomic_write_json
from neuralmap.terrain.latent.tileset_layout import TilesetLayout

__all__ = ["INDEX_FILENAME", "TILESET_FORMAT", "TileEntry", "TilesetIndex", "file_sha256",
           "is_tileset_index", "read_tileset_index", "tile_file_name", "write_tileset_index"]

TILESET_FORMAT = "neuralmap-latent-tileset"
TILESET_VERSION = 1
#: File name of the index inside a tileset folder.
INDEX_FILENAME = "latent_tileset.json"


def tile_file_name(row: int, col: int) -> str:
    """Relative file name of tile ``(row, col)``: ``tiles/r000_c000.nlat``."""
    return f"tiles/r{row:03d}_c{col:03d}.nlat"


def file_sha256(path: str | os.PathLike[str]) -> str:
    """Hex SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


@dataclass(frozen=True)
class TileEntry:
    """One tile of the index (module docstring for the fields)."""

    row: int
    col: int
    file: str
    sha256: str
    bytes: int
    core: tuple[int, int, int, int]
    window: tuple[int, int, int, int]
    extent: tuple[float, float, float, float]
    fingerprint: str = ""
    source: str = ""
    metrics: dict[str, Any] = field(default_factory=dict)

    def describe(self) -> dict[str, Any]:
        """The entry as the index stores it."""
        return {"row": self.row, "col": self.col, "file": self.file, "sha256": self.sha256,
                "bytes": self.bytes, "core": list(self.core), "window": list(self.window),
                "extent": list(self.extent), "fingerprint": self.fingerprint,
                "source": self.source, "metrics": dict(self.metrics)}


@dataclass
class TilesetIndex:
    """A parsed index: region description, layout, tiles (row-major), extra info."""

    region: dict[str, Any]
    layout: TilesetLayout
    tiles: list[TileEntry]
    info: dict[str, Any] = field(default_factory=dict)

    def describe(self) -> dict[str, Any]:
        """The JSON document (``format`` first)."""
        return {"format": TILESET_FORMAT, "format_version": TILESET_VERSION,
                "region": self.region, "layout": self.layout.describe(),
                "tiles": [t.describe() for t in self.tiles], "info": self.info}


def write_tileset_index(path: str | os.PathLike[str], index: TilesetIndex) -> Path:
    """Writes the index atomically (temporary file, then rename).

    Raises:
        NeuralMapError: Tiles not one per grid cell in row-major order.
    """
    rows, cols = index.layout.grid
    cells = [(t.row, t.col) for t in index.tiles]
    if cells != [(i, j) for i in range(rows) for j in range(cols)]:
        raise NeuralMapError(f"write_tileset_index: tiles {cells} are not the {rows} x {cols} "
                             "grid in row-major order.")
    return atomic_write_json(Path(path), index.describe())


def _index_file(path: str | os.PathLike[str]) -> Path:
    path = Path(path)
    return path / INDEX_FILENAME if path.is_dir() else path


def is_tileset_index(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a tileset index (or a folder holding ``latent_tileset.json``)."""
    file = _index_file(path)
    if file.suffix.lower() != ".json" or not file.is_file():
        return False
    try:
        with open(file, "rb") as fh:
            head = fh.read(256).decode("utf-8", "replace")
    except OSError:
        return False
    return TILESET_FORMAT in head


def read_tileset_index(path: str | os.PathLike[str]) -> tuple[Path, TilesetIndex]:
    """Reads and checks an index.

    Args:
        path: ``latent_tileset.json`` or the folder holding it.

    Returns:
        ``(index file, parsed index)``.

    Raises:
        NeuralMapError: Missing, unreadable, not a tileset index, newer format, or missing /
            malformed keys (naming the key).
    """
    file = _index_file(path)
    try:
        data = json.loads(file.read_text())
    except (OSError, ValueError) as exc:
        raise NeuralMapError(
            f"latent tileset index '{file}' could not be read ({exc}); give the "
            f"{INDEX_FILENAME} that `train.py latent --data.path 'tiles/*.hgt'` wrote."
        ) from None
    if not isinstance(data, dict) or data.get("format") != TILESET_FORMAT:
        raise NeuralMapError(f"'{file}' is not a latent tileset index (no '{TILESET_FORMAT}' "
                             "format key).")
    if int(data.get("format_version", 0)) > TILESET_VERSION:
        raise NeuralMapError(f"'{file}': tileset format version {data['format_version']} is "
                             f"newer than this neuralmap reads ({TILESET_VERSION}); upgrade.")
    try:
        layout = TilesetLayout.from_description(data["layout"])
        tiles = [TileEntry(row=int(t["row"]), col=int(t["col"]), file=str(t["file"]),
                           sha256=str(t["sha256"]), bytes=int(t["bytes"]),
                           core=tuple(int(v) for v in t["core"]),  # type: ignore[arg-type]
                           window=tuple(int(v) for v in t["window"]),  # type: ignore[arg-type]
                           extent=tuple(float(v) for v in t["extent"]),  # type: ignore[arg-type]
                           fingerprint=str(t.get("fingerprint", "")),
                           source=str(t.get("source", "")), metrics=dict(t.get("metrics", {})))
                 for t in data["tiles"]]
        region = dict(data["region"])
    except (KeyError, TypeError, ValueError) as exc:
        raise NeuralMapError(f"'{file}': malformed tileset index ({type(exc).__name__}: {exc}); "
                             "the file is damaged or was edited. Train the tileset again.") from None
    rows, cols = layout.grid
    if [(t.row, t.col) for t in tiles] != [(i, j) for i in range(rows) for j in range(cols)]:
        raise NeuralMapError(f"'{file}': the index lists {len(tiles)} tiles, not the {rows} x "
                             f"{cols} grid of its layout; the file is damaged or was edited.")
    return file, TilesetIndex(region=region, layout=layout, tiles=tiles,
                              info=dict(data.get("info", {})))
