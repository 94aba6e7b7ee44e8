"""Run outputs of a fit: the exported neural map, its metrics JSON and the figure PNGs."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from matplotlib.figure import Figure
from torch import nn

from neuralmap.io import atomic_write_figure, atomic_write_json, to_jsonable

#: File names written into the run folder ``runs/<experiment>/version_N/``.
MAP_FILENAME = "neural_map.pt"
METRICS_FILENAME = "metrics.json"


def write_json(path: Path, payload: dict[str, Any]) -> Path:
    """Writes strict JSON atomically (`neuralmap.io.atomic_write_json`)."""
    return atomic_write_json(path, payload)


def save_figure(figure: Figure, path: Path, *, dpi: int = 110) -> Path:
    """Saves a figure as PNG atomically (`neuralmap.io.atomic_write_figure`)."""
    return atomic_write_figure(path, figure, dpi=dpi)


def export_map(
    net: nn.Module,
    run_dir: Path,
    metrics: dict[str, Any],
    *,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Exports the fitted map and its metrics into ``run_dir``.

    Writes ``neural_map.pt`` with `neuralmap.terrain.export.save_map` (metrics
    embedded; loadable with ``load_map`` without Lightning) and ``metrics.json`` beside it.

    Args:
        net: The fitted `BlockwiseTerrainNet`.
        run_dir: Run folder (created if needed).
        metrics: Final metrics (JSON-serialisable scalars).
        extra: Extra JSON-serialisable data stored in the export (hparams, data settings).

    Returns:
        Path of ``neural_map.pt``.
    """
    from neuralmap.terrain.export import save_map

    run_dir.mkdir(parents=True, exist_ok=True)
    map_path = run_dir / MAP_FILENAME
    save_map(net, map_path, metrics=to_jsonable(metrics), extra=to_jsonable(extra or {}))
    payload = dict(metrics)
    payload["file_bytes"] = map_path.stat().st_size
    write_json(run_dir / METRICS_FILENAME, payload)
    return map_path
