"""What ``--map`` names: a trained map file, a DEM file or an embedded tile, as one source.

``resolve_map(text)`` accepts, in this order:

1. an existing file or folder that is a DEM (`neuralmap.dem.readers.
   SUPPORTED_EXTENSIONS`: GeoTIFF via rasterio, ``.asc``, ``.hgt``, ``.npy``/``.npz``):
   the DEM is navigated on its bicubic grid (`GridTerrain`);
2. an existing trained map: the ``neural_map.pt`` of ``train.py``, a latent-grid map
   bitstream, a sharded region map index or a latent tileset index
   (``latent_tileset.json`` or its folder; `neuralmap.terrain.export.load_map`);
3. an embedded tile name (``jacksboro``, ``topobathy``, ``synthetic[:N]``), on its bicubic
   grid.

The map's own error model (no truth terrain exists for a real flight): the variance the
navigator adds to the altimeter's is ``σ_DEM² + σ_fit²`` — the DEM's stated vertical
accuracy (``dem_accuracy_m``, from the navigator config or the caller; 0 when unknown) and,
for a trained map, the fit error it records (`neuralmap.nav.map_noise.map_fit_rmse`).
The navigator builds its ``R`` from the same parts (`neuralmap.nav.map_noise`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neuralmap.dem.tile import DemTile, GeoReference, ProjectedReference
from neuralmap.exceptions import NeuralMapError
from neuralmap.nav.georef import MapFrame
from neuralmap.nav.map_noise import map_fit_rmse

__all__ = ["MapSource", "resolve_map"]

#: Largest side of the height grid sampled from a trained map for the background figure.
_PREVIEW_NODES = 256


@dataclass
class MapSource:
    """A resolved ``--map``.

    Attributes:
        terrain: The terrain model the navigator flies over (``forward(xy) -> height``).
        kind: ``"dem"``, ``"sample"`` or ``"trained_map"``.
        name: Tile name.
        source: The ``--map`` text.
        extent: ``(xmin, xmax, ymin, ymax)`` map frame, m.
        tile: The DEM tile (DEM and sample maps), else None.
        reference: The tile's georeference (None when the map has none).
        fit_rmse_m: The trained map's recorded fit error, m (0 for a DEM grid).
        dem_accuracy_m: The DEM's stated vertical accuracy, m (0 when unknown).
        info: The tile description (``DemTile.describe()`` or the map's ``tile_info``).
    """

    terrain: torch.nn.Module
    kind: str
    name: str
    source: str
    extent: tuple[float, float, float, float]
    tile: DemTile | None = None
    reference: GeoReference | ProjectedReference | None = None
    fit_rmse_m: float = 0.0
    dem_accuracy_m: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)
    _frame: MapFrame | None = field(default=None, repr=False)

    @property
    def map_error_variance(self) -> float:
        """The map's own error variance ``σ_DEM² + σ_fit²``, m²."""
        return float(self.dem_accuracy_m**2 + self.fit_rmse_m**2)

    @property
    def has_frame(self) -> bool:
        """Whether the map is georeferenced (lat/lon can be converted)."""
        return self.reference is not None and not (
            isinstance(self.reference, ProjectedReference) and not self.reference.crs)

    @property
    def frame(self) -> MapFrame:
        """The `MapFrame` (built on first use; pyproj only for projected maps).

        Raises:
            NeuralMapError: The map has no usable georeference or pyproj is missing.
        """
        if self._frame is None:
            self._frame = MapFrame(self.reference, name=self.name)
        return self._frame

    def preview_tile(self) -> DemTile:
        """Heights to draw under the track: the tile, or the trained map sampled on a grid
        of at most 256 nodes a side over its extent."""
        if self.tile is not None:
            return self.tile
        xmin, xmax, ymin, ymax = self.extent
        shape = self.info.get("shape") or [_PREVIEW_NODES, _PREVIEW_NODES]
        ny, nx = (max(2, min(int(s), _PREVIEW_NODES)) for s in shape)
        xs = np.linspace(xmin, xmax, nx)
        ys = np.linspace(ymin, ymax, ny)
        grid = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
        with torch.no_grad():
            dtype = next((b.dtype for b in self.terrain.buffers() if b.is_floating_point()),
                         torch.float32)
            heights = self.terrain(torch.as_tensor(grid, dtype=dtype)).double().numpy()
        return DemTile(heights=heights.reshape(ny, nx),
                       spacing=((xmax - xmin) / (nx - 1), (ymax - ymin) / (ny - 1)),
                       origin=(xmin, ymin), name=self.name, source=self.source)

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable summary for reports."""
        return {"kind": self.kind, "name": self.name, "source": self.source,
                "extent": list(self.extent), "fit_rmse_m": self.fit_rmse_m,
                "dem_accuracy_m": self.dem_accuracy_m,
                "map_error_variance_m2": self.map_error_variance,
                "georeference": None if self.reference is None else {
                    "kind": type(self.reference).__name__, **self.reference.describe()}}


def _reference_from_info(info: dict[str, Any]) -> GeoReference | ProjectedReference | None:
    geo, projected = info.get("geo"), info.get("projected")
    if isinstance(geo, dict):
        return GeoReference(**geo)
    if isinstance(projected, dict):
        return ProjectedReference(**projected)
    return None


def _grid_source(tile: DemTile, *, kind: str, source: str, dem_accuracy_m: float,
                 dtype: torch.dtype) -> MapSource:
    from neuralmap.terrain.grid import GridTerrain

    terrain = GridTerrain(tile, method="bicubic", dtype=dtype)
    return MapSource(terrain=terrain, kind=kind, name=tile.name, source=source,
                     extent=tuple(float(e) for e in tile.extent), tile=tile,  # type: ignore[arg-type]
                     reference=tile.georeference, dem_accuracy_m=dem_accuracy_m,
                     info=tile.describe())


def resolve_map(text: str, *, dem_accuracy_m: float | None = None,
                dtype: torch.dtype = torch.float64, **tile_options: Any) -> MapSource:
    """Resolves ``--map`` (see the module docstring).

    Args:
        text: A DEM file, a trained map file (or sharded index), or a sample tile name.
        dem_accuracy_m: The DEM's stated vertical accuracy (1σ), m; None = 0 (unknown).
        dtype: Height dtype of a DEM grid.
        **tile_options: Reader options of `neuralmap.dem.load_tile` (``units``,
            ``nodata``, ``spacing`` for bare ``.npy`` grids, ...).

    Raises:
        NeuralMapError: Nothing of that name, or a file that is neither a DEM nor a map.
    """
    from neuralmap.dem.load import load_tile
    from neuralmap.dem.readers import SAMPLE_NAMES, SUPPORTED_EXTENSIONS
    from neuralmap.dem.samples import is_sample_name

    accuracy = 0.0 if dem_accuracy_m is None else float(dem_accuracy_m)
    if not (np.isfinite(accuracy) and accuracy >= 0):
        raise NeuralMapError(f"dem_accuracy_m must be a finite number >= 0, got "
                             f"{dem_accuracy_m!r}.")
    raw = str(text).strip()
    path = Path(raw).expanduser()
    if path.exists() and path.suffix.lower() in SUPPORTED_EXTENSIONS and path.is_file():
        tile = load_tile(path, **tile_options)
        return _grid_source(tile, kind="dem", source=raw, dem_accuracy_m=accuracy, dtype=dtype)
    if path.exists():
        from neuralmap.terrain.export import load_map

        if tile_options:
            raise NeuralMapError(f"--map {raw}: DEM reader options {sorted(tile_options)} do "
                                 "not apply to a trained map file.")
        try:
            terrain = load_map(path)
        except NeuralMapError as exc:
            raise NeuralMapError(
                f"--map {raw}: not a DEM ({', '.join(SUPPORTED_EXTENSIONS)}) nor a trained "
                f"map: {exc}") from None
        info = dict(getattr(terrain, "tile_info", None) or {})
        extent = getattr(terrain, "extent", None) or info.get("extent")
        if extent is None:
            raise NeuralMapError(f"--map {raw}: the map records no extent; export it again "
                                 "with `python train.py`.")
        return MapSource(terrain=terrain, kind="trained_map",
                         name=str(getattr(terrain, "tile_name", "") or info.get("name") or
                                  path.stem), source=raw,
                         extent=tuple(float(e) for e in extent),  # type: ignore[arg-type]
                         reference=_reference_from_info(info), fit_rmse_m=map_fit_rmse(terrain)[0],
                         dem_accuracy_m=accuracy, info=info)
    if is_sample_name(raw):
        tile = load_tile(raw, **tile_options)
        return _grid_source(tile, kind="sample", source=raw, dem_accuracy_m=accuracy,
                            dtype=dtype)
    raise NeuralMapError(
        f"--map {raw}: no such file and not an embedded tile. Give a DEM file "
        f"({', '.join(SUPPORTED_EXTENSIONS)}), a trained map (neural_map.pt from "
        f"`python train.py`) or a tile name ({', '.join(SAMPLE_NAMES)}).")
