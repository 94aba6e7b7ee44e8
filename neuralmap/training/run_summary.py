"""A training run's stamped fragment: ``summary.md`` in its run folder (the fit metrics).

``python train.py`` (map and latent modes) writes it beside ``metrics.json``; its first line
is `neuralmap.outputs.SUMMARY_MARK` with the provenance (``kind: train``, the mode,
the command-line words, the config files with their SHA-256, seed, commit, date, machine,
wall time), then a table of every scalar of ``metrics.json``. ``python -m neuralmap.docs
update RUN_DIR`` copies it into ``docs/results/train_<config>.md``, stamped with the config.
"""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path
from typing import Any

from neuralmap.io import atomic_write_text
from neuralmap.outputs import SUMMARY_MARK, markdown_table, run_provenance

__all__ = ["TRAIN_KIND", "train_summary", "write_train_summary"]

#: The ``kind`` of a training run's provenance.
TRAIN_KIND = "train"


def _config_entry(path: str | Path) -> dict[str, Any]:
    path = Path(path).resolve()
    digest = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None
    return {"path": str(path), "name": path.name, "sha256": digest}


def train_summary(*, mode: str, argv: list[str], configs: list[str | Path],
                  metrics: dict[str, Any], seed: int | None, wall_s: float,
                  experiment: str = "") -> str:
    """The ``summary.md`` text of a finished training run.

    Args:
        mode: The ``train.py`` mode (``map``, ``latent``).
        argv: The words after the mode.
        configs: The config files the run read, in order (the default config first when
            no ``--config`` was given); the last one names the run's page.
        metrics: The run's ``metrics.json``.
        seed: ``seed_everything`` of the run.
        wall_s: Wall time of the command from parsing to export (s).
        experiment: The run's experiment name.
    """
    from neuralmap.machine import machine

    base = run_provenance(argparse.Namespace(study=f"train_{mode}", experiment=experiment,
                                             seed=seed))
    provenance = {**base, "kind": TRAIN_KIND, "mode": mode, "argv": list(argv),
                  "configs": [_config_entry(c) for c in configs], "machine": machine(),
                  "wall_s": round(float(wall_s), 1)}
    rows = [[key, value] for key, value in metrics.items()
            if isinstance(value, (int, float, str)) and not isinstance(value, bool)
            and key not in ("tile_units_reason", "run_dir")]
    rows.append(["wall_s (command, parse to export)", round(float(wall_s), 1)])
    config = Path(configs[-1]).name if configs else "the defaults"
    return "\n".join([
        f"{SUMMARY_MARK} {json.dumps(provenance, sort_keys=True)} -->",
        f"# Training run: `train.py {mode}` with `{config}`\n",
        "## Fit metrics\n",
        "Every valid node unless the key starts with `val_` (held-out nodes, the last "
        "epoch before the refit) or `offnode_` / `between_` (random points between the "
        "nodes).\n",
        markdown_table(["metric", "value"], rows) + "\n",
    ])


def write_train_summary(run_dir: str | Path, **kwargs: Any) -> Path:
    """Writes `train_summary` (same arguments) to ``run_dir/summary.md`` atomically."""
    path = Path(run_dir) / "summary.md"
    atomic_write_text(path, train_summary(**kwargs))
    return path
