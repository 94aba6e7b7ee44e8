"""Run outputs of a fit: the exported neural map, its metrics JSON and the figure PNGs."""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any

from matplotlib.figure import Figure
from torch import nn

#: File names written into the run folder ``runs/<experiment>/version_N/``.
MAP_FILENAME = "neural_map.pt"
METRICS_FILENAME = "metrics.json"


def _json_safe(value: Any) -> Any:
    """Replaces non-finite floats by None (strict JSON) and tuples by lists, recursively."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def write_json(path: Path, payload: dict[str, Any]) -> Path:
    """Writes JSON atomically (temporary file in the same folder, then ``os.replace``)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as handle:
            json.dump(_json_safe(payload), handle, indent=2, sort_keys=True)
            handle.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def save_figure(figure: Figure, path: Path, *, dpi: int = 110) -> Path:
    """Saves a figure as PNG atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".png")
    os.close(fd)
    try:
        figure.savefig(tmp, dpi=dpi, format="png")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def export_map(
    net: nn.Module,
    run_dir: Path,
    metrics: dict[str, Any],
    *,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Exports the fitted map and its metrics into ``run_dir``.

    Writes ``neural_map.pt`` with :func:`neuralmap.terrain.export.save_map` (metrics
    embedded; loadable with ``load_map`` without Lightning) and ``metrics.json`` beside it.

    Args:
        net: The fitted :class:`BlockwiseTerrainNet`.
        run_dir: Run folder (created if needed).
        metrics: Final metrics (JSON-serialisable scalars).
        extra: Extra JSON-serialisable data stored in the export (hparams, data settings).

    Returns:
        Path of ``neural_map.pt``.
    """
    from neuralmap.terrain.export import save_map

    run_dir.mkdir(parents=True, exist_ok=True)
    map_path = run_dir / MAP_FILENAME
    save_map(net, map_path, metrics=_json_safe(metrics), extra=_json_safe(extra or {}))
    payload = dict(metrics)
    payload["file_bytes"] = map_path.stat().st_size
    write_json(run_dir / METRICS_FILENAME, payload)
    return map_path
