"""Which neural map a study uses: discovery in the run folders, tile check, fit variance."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from neuralmap.exceptions import NeuralMapError
from neuralmap.io import version_number
from neuralmap.terrain.export import load_map, load_map_payload

__all__ = [
    "MAP_FILENAME",
    "check_map_tile",
    "find_latest_map",
    "find_tile_maps",
    "map_fit_variance",
    "resolve_map_path",
]

#: File name of an exported neural map inside a training run folder.
MAP_FILENAME = "neural_map.pt"
#: Every map file a training run folder may hold: the blockwise export and the latent-grid
#: bitstream (`neuralmap.terrain.latent`).
MAP_FILENAMES = (MAP_FILENAME, "latent_map.nlat")

NO_MAP_MESSAGE = (
    "no trained map found under {runs}/: run `python train.py` first (or pass --map PATH)"
)


def _map_tile_fingerprint(path: Path) -> str:
    """The tile fingerprint recorded in a map file ("" when unreadable)."""
    try:
        if path.suffix != ".pt":  # a latent-grid bitstream: its header names the tile
            return str(getattr(load_map(path), "tile_fingerprint", "") or "")
        payload = load_map_payload(path)
    except Exception:  # noqa: BLE001 - a broken candidate is simply not preferred
        return ""
    config = payload.get("config") or {}
    info = config.get("tile_info") or {}
    return str(config.get("tile_fingerprint") or info.get("fingerprint") or "")


def find_latest_map(runs_dir: str | os.PathLike[str], *, tile_fingerprint: str = ""
                    ) -> Path | None:
    """The newest ``<runs_dir>/*/version_*/neural_map.pt`` (by modification time).

    Args:
        runs_dir: Root of the run folders.
        tile_fingerprint: When given, the newest map *of that tile* is preferred; the
            newest map of any tile is returned only when no map matches.

    Returns:
        The path, or ``None`` when there is none.
    """
    candidates = [p for p in Path(runs_dir).glob(f"*/version_*/{MAP_FILENAME}") if p.is_file()]
    if not candidates:
        return None
    ordered = sorted(candidates, key=lambda p: (p.stat().st_mtime, version_number(p.parent)),
                     reverse=True)
    if tile_fingerprint:
        for path in ordered:
            if _map_tile_fingerprint(path) == tile_fingerprint:
                return path
    return ordered[0]


def find_tile_maps(runs_dir: str | os.PathLike[str], tile_fingerprint: str) -> list[Path]:
    """The newest map of the tile in every experiment folder of ``runs_dir`` (experiments
    in name order), the tile read from the map file as `find_latest_map` reads it.

    Args:
        runs_dir: Root of the run folders.
        tile_fingerprint: The tile's `fingerprint`.

    Returns:
        One path per experiment that holds a map of the tile (may be empty).
    """
    root = Path(runs_dir)
    if not root.is_dir():
        return []
    found: list[Path] = []
    for experiment in sorted(p for p in root.iterdir() if p.is_dir()):
        candidates = sorted((p for name in MAP_FILENAMES
                             for p in experiment.glob(f"version_*/{name}") if p.is_file()),
                            key=lambda p: (p.stat().st_mtime, version_number(p.parent)),
                            reverse=True)
        for path in candidates:
            if _map_tile_fingerprint(path) == tile_fingerprint:
                found.append(path)
                break
    return found


def resolve_map_path(map_path: str | None, runs_dir: str, *, tile_fingerprint: str = "") -> Path:
    """The map file to use: ``map_path`` when given, else the newest in ``runs_dir``.

    Raises:
        NeuralMapError: ``map_path`` does not exist, or no map was given nor found.
    """
    if map_path is not None:
        path = Path(map_path)
        if not path.is_file():
            raise NeuralMapError(
                f"--map {map_path}: file not found. Pass the neural_map.pt written by "
                "`python train.py` (runs/<experiment>/version_N/neural_map.pt)."
            )
        return path
    path = find_latest_map(runs_dir, tile_fingerprint=tile_fingerprint)
    if path is None:
        raise NeuralMapError(NO_MAP_MESSAGE.format(runs=str(runs_dir).rstrip("/")))
    return path


def check_map_tile(terrain_map: Any, tile: Any, *, map_path: Path, scenario_name: str) -> None:
    """Checks that the map was exported from the scenario's tile (fingerprints equal).

    Raises:
        NeuralMapError: The fingerprints differ or the map has none.
    """
    expected = tile.fingerprint()
    found = str(getattr(terrain_map, "tile_fingerprint", "") or "")
    if found == expected:
        return
    map_tile = getattr(terrain_map, "tile_name", "") or "unknown"
    info = getattr(terrain_map, "tile_info", None) or {}
    differences = [
        f"{key} {info[key]} vs {now}"
        for key, now in (
            ("shape", list(tile.shape)),
            ("spacing", list(tile.spacing)),
            ("origin", list(tile.origin)),
        )
        if key in info and list(info[key]) != now
    ]
    hint = ""
    if map_tile == tile.name:
        hint = (
            " Same tile name, different content: the DEM file or its reader changed since "
            "the map was trained"
            + (f" ({'; '.join(differences)})" if differences else "")
            + ", so retrain it (python train.py)."
        )
    raise NeuralMapError(
        f"--map {map_path}: the map was exported from tile '{map_tile}' (fingerprint "
        f"{found or 'none'}), but scenario '{scenario_name}' flies over tile '{tile.name}' "
        f"(fingerprint {expected})."
        + (
            hint
            or " Train a map on the scenario's tile (python train.py with that tile), "
            "pass the matching --map, or pick the scenario of the map's tile (--scenario)."
        )
    )


def map_fit_variance(terrain_map: Any) -> float:
    """Square of the fit RMSE recorded in the map file (``metrics["rmse_m"]``), else 0."""
    metrics = getattr(terrain_map, "metrics", None) or {}
    rmse = metrics.get("rmse_m") if isinstance(metrics, dict) else None
    try:
        rmse = float(rmse)
    except (TypeError, ValueError):
        return 0.0
    return rmse * rmse if np.isfinite(rmse) else 0.0
