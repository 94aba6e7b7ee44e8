"""End of a latent-grid fit: write the bitstream file and its metrics into the run folder."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lightning.pytorch as pl
from lightning.pytorch.utilities.rank_zero import rank_zero_info

from neuralmap.io import atomic_write_json, to_jsonable
from neuralmap.terrain.latent.bitstream import write_latent_map
from neuralmap.terrain.latent.quality import map_quality
from neuralmap.training.callbacks.fit_report import FitReport

#: File names written into ``runs/<experiment>/version_N/``.
LATENT_MAP_FILENAME = "latent_map.nlat"
LATENT_METRICS_FILENAME = "metrics.json"


class LatentMapReport(pl.Callback):
    """Exports ``latent_map.nlat`` (the file whose size is the map's size) and
    ``metrics.json`` at the end of training; logs ``final/*`` scalars (rank 0 writes).

    Attributes:
        map_path: Path of the exported bitstream on rank 0 after the fit (None elsewhere).
        metrics: Final metrics on rank 0.
    """

    def __init__(self) -> None:
        self.map_path: Path | None = None
        self.metrics: dict[str, Any] = {}

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        run_dir = FitReport.run_dir(trainer)
        if trainer.is_global_zero:
            self._export(trainer, pl_module, run_dir)
        trainer.strategy.barrier("neuralmap_latent_report")

    def _export(self, trainer: pl.Trainer, pl_module: Any, run_dir: Path) -> None:
        tile = pl_module.tile
        quality = map_quality(pl_module.stored_map(), tile)
        header_metrics = {key: quality[key] for key in ("rmse_m", "max_abs_m", "between_rmse_m")}
        header_metrics["rate_weight"] = float(pl_module.hparams.rate_weight)
        latent_map = pl_module.stored_map(metrics=header_metrics)
        run_dir.mkdir(parents=True, exist_ok=True)
        path = write_latent_map(latent_map, run_dir / LATENT_MAP_FILENAME)
        metrics = dict(quality)
        metrics.update({"tile": tile.name, "tile_shape": list(tile.shape),
                        "file_bytes": path.stat().st_size,
                        "raw_grid_bytes": int(tile.shape[0] * tile.shape[1] * 4),
                        "rate_weight": float(pl_module.hparams.rate_weight),
                        "basis": str(pl_module.hparams.get("basis", "wavelet")),
                        "levels": int(pl_module.hparams.levels),
                        "hidden": int(pl_module.hparams.hidden),
                        "global_step": int(trainer.global_step)})
        atomic_write_json(run_dir / LATENT_METRICS_FILENAME, to_jsonable(metrics))
        for logger in trainer.loggers:
            logger.log_metrics({f"final/{k}": float(metrics[k]) for k in
                                ("file_bytes", "bits_per_node", "rmse_m", "max_abs_m",
                                 "between_rmse_m")}, step=int(trainer.global_step))
        rank_zero_info(
            f"latent map: {metrics['file_bytes']} bytes ({metrics['bits_per_node']:.3f} bits/node), "
            f"node RMSE {metrics['rmse_m']:.3f} m, max {metrics['max_abs_m']:.2f} m, "
            f"between-node RMSE vs bicubic {metrics['between_rmse_m']:.3f} m")
        self.map_path = path
        self.metrics = metrics
