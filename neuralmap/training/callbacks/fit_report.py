"""End-of-fit report: evaluate on every valid node, log to TensorBoard, export the map."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import numpy as np
import torch
from lightning.pytorch.loggers import TensorBoardLogger
from lightning.pytorch.utilities.rank_zero import rank_zero_info

from neuralmap.training.callbacks.export import (
    METRICS_FILENAME,
    export_map,
    save_figure,
)
from neuralmap.training.evaluation import FitEvaluation, evaluate_fit
from neuralmap.viz.fit import (
    figure_to_rgb,
    hillshade_comparison_figure,
    residual_autocorrelation_figure,
    residual_histogram_figure,
    residual_map_figure,
)

#: TensorBoard image tags written at the end of the fit (PNG file name in the run folder).
IMAGE_TAGS = {
    "fit/residual_map": "residual_map.png",
    "fit/hillshade": "hillshade.png",
    "fit/residual_histogram": "residual_histogram.png",
    "fit/residual_acf": "residual_acf.png",
}
#: TensorBoard histogram tag of the final residuals.
HISTOGRAM_TAG = "fit/residuals"
#: Final metrics logged as scalars ``final/<key>`` and as hparams metrics.
FINAL_SCALARS = ("rmse_m", "max_abs_m", "mean_m", "std_m", "slope_rmse", "acf_x_lag1",
                 "acf_y_lag1", "offnode_rmse_m", "offnode_max_abs_m", "offnode_slope_rmse",
                 "points_per_s", "train_time_s")


def _tensorboard(trainer: pl.Trainer) -> TensorBoardLogger | None:
    for logger in trainer.loggers:
        if isinstance(logger, TensorBoardLogger):
            return logger
    return None


def _flat_hparams(params: dict[str, Any], prefix: str) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in params.items():
        if key.startswith("_"):  # e.g. LightningCLI's "_instantiator"
            continue
        if isinstance(value, (bool, int, float, str)) or value is None:
            out[f"{prefix}{key}"] = "None" if value is None else value
        else:
            out[f"{prefix}{key}"] = str(value)
    return out


class FitReport(pl.Callback):
    """Final evaluation, dashboards and export at the end of training (rank 0 writes).

    On every valid node of the tile (`evaluate_fit`): RMSE, max |error|, mean and std
    of the error (m), slope RMSE against the bicubic DEM slopes (m/m) and the lag-1
    residual autocorrelations. Then, into the run folder (the TensorBoard logger's
    ``version_N``, or ``<default_root_dir>/fast_dev_run`` when there is no log folder):

    * TensorBoard: scalars ``final/*``, images `IMAGE_TAGS` (residual map in a
      diverging colour map with symmetric limits, DEM vs fitted hillshade, residual
      histogram, residual autocorrelation vs lag in metres), histogram
      `HISTOGRAM_TAG`, and hparams with the final metrics;
    * the same figures as PNG files;
    * ``neural_map.pt`` (`neuralmap.terrain.export.save_map`) and ``metrics.json``.

    Attributes:
        map_path: Path of the exported map on rank 0 after the fit (None elsewhere).
        metrics: Final metrics dict on rank 0.
        evaluation: The `FitEvaluation` on rank 0.
    """

    def __init__(self, *, max_lag: int = 40) -> None:
        self.max_lag = int(max_lag)
        self.map_path: Path | None = None
        self.metrics: dict[str, Any] = {}
        self.evaluation: FitEvaluation | None = None

    @staticmethod
    def run_dir(trainer: pl.Trainer) -> Path:
        """The run folder; must be called on every rank (it broadcasts)."""
        log_dir = trainer.log_dir
        if log_dir is None or trainer.fast_dev_run:
            return Path(trainer.default_root_dir) / "fast_dev_run"
        return Path(log_dir)

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        run_dir = self.run_dir(trainer)
        points = trainer.strategy.reduce(
            torch.tensor(float(getattr(pl_module, "points_seen", 0)), dtype=torch.float64),
            reduce_op="sum",
        )
        if trainer.is_global_zero:
            self._report(trainer, pl_module, run_dir, float(points))
        trainer.strategy.barrier("neuralmap_fit_report")

    # ------------------------------------------------------------------ rank 0
    def _report(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, run_dir: Path, points: float
    ) -> None:
        datamodule = trainer.datamodule  # type: ignore[attr-defined]
        tile = datamodule.tile
        net = pl_module.net  # type: ignore[attr-defined]
        evaluation = evaluate_fit(
            net, tile, slope_ref=datamodule.all_slopes, chunk=datamodule.eval_batch_size,
            max_lag=self.max_lag,
        )
        self.evaluation = evaluation
        train_time = float(getattr(pl_module, "train_time_s", 0.0))
        n_params = int(net.num_parameters)
        raw_bytes = int(tile.shape[0] * tile.shape[1] * 4)
        metrics: dict[str, Any] = dict(evaluation.metrics)
        metrics.update(
            {
                "tile": tile.name,
                "tile_shape": list(tile.shape),
                "n_train": datamodule.n_train,
                "n_val": datamodule.n_val,
                "num_parameters": n_params,
                "param_bytes": 4 * n_params,
                "raw_grid_bytes": raw_bytes,
                "bytes_ratio": 4 * n_params / raw_bytes,
                "epochs": int(trainer.current_epoch),
                "global_step": int(trainer.global_step),
                "train_points": int(points),
                "train_time_s": train_time,
                "points_per_s": points / train_time if train_time > 0 else float("nan"),
                "world_size": int(trainer.world_size),
            }
        )
        heldout = getattr(pl_module, "heldout_metrics", None)
        metrics["heldout_validation"] = bool(heldout)
        if heldout:
            # Held-out nodes, last validation before any refit on every node.
            metrics["val_rmse_m"] = float(heldout["rmse_m"])
            metrics["val_max_abs_m"] = float(heldout["max_abs_m"])
            metrics["val_slope_rmse"] = float(heldout["slope_rmse"])
            metrics["val_epoch"] = int(heldout["epoch"])
        # No fallback to the last logged val/* values: in a refit epoch they are in-sample.
        metrics["refit_epochs"] = int(getattr(datamodule, "refit_epochs", 0))
        metrics["refit_epochs_requested"] = int(
            getattr(datamodule, "refit_epochs_requested", metrics["refit_epochs"])
        )
        start = getattr(datamodule, "refit_start_epoch", None)
        metrics["refit_start_epoch"] = start if metrics["refit_epochs"] > 0 else None
        note = getattr(datamodule, "refit_note", None)
        if note:
            metrics["refit_note"] = note
        target = pl_module.hparams.get("target_rmse")
        if target is not None:
            stop = next((cb for cb in trainer.callbacks
                         if type(cb).__name__ == "TargetRmseStopping"), None)
            metrics["target_rmse"] = float(target)
            metrics["target_reached_epoch"] = getattr(stop, "stopped_epoch", None)
        metrics["tile_units"] = tile.meta.get("units")
        metrics["tile_units_reason"] = tile.meta.get("units_reason")
        metrics["n_implausible_voided"] = int(tile.meta.get("n_implausible", 0))
        self.metrics = metrics

        figures = {
            "fit/residual_map": residual_map_figure(
                evaluation.residual, tile.extent, title=f"{tile.name} fit residual"
            ),
            "fit/hillshade": hillshade_comparison_figure(
                tile.heights, evaluation.fitted, tile.spacing, tile.extent
            ),
            "fit/residual_histogram": residual_histogram_figure(evaluation.residual),
            "fit/residual_acf": residual_autocorrelation_figure(
                evaluation.acf_x, evaluation.acf_y, tile.spacing, int(metrics["n_nodes"])
            ),
        }
        for tag, figure in figures.items():
            save_figure(figure, run_dir / IMAGE_TAGS[tag])

        logger = _tensorboard(trainer)
        if logger is not None:
            self._log_tensorboard(logger, trainer, pl_module, figures, evaluation, metrics)

        extra = {
            "hparams": {k: v for k, v in pl_module.hparams.items() if not k.startswith("_")},
            "data": {k: v for k, v in datamodule.hparams.items() if not k.startswith("_")},
            # units decision, no-data counts and, for metric files, the absolute position
            # of the tile frame (tile.projected): the map's coordinates are tile-local
            "tile": tile.describe(),
            "run_dir": str(run_dir),
        }
        self.map_path = export_map(net, run_dir, metrics, extra=extra)
        pl_module.map_path = self.map_path  # type: ignore[attr-defined]
        rank_zero_info(
            f"final fit on all {metrics['n_nodes']} valid nodes of '{tile.name}': "
            f"RMSE {metrics['rmse_m']:.3f} m, max |e| {metrics['max_abs_m']:.2f} m, "
            f"mean {metrics['mean_m']:+.3f} m, slope RMSE {metrics['slope_rmse']:.4f} m/m; "
            f"between the nodes vs the bicubic DEM: RMSE "
            f"{metrics.get('offnode_rmse_m', float('nan')):.3f} m, max |e| "
            f"{metrics.get('offnode_max_abs_m', float('nan')):.2f} m; "
            f"{n_params} parameters ({metrics['bytes_ratio']:.2f} x raw float32 grid); "
            f"{metrics['points_per_s']:.3g} points/s; outputs in {run_dir} "
            f"({METRICS_FILENAME}, PNGs)"
        )
        if heldout:
            rank_zero_info(
                f"held-out validation ({datamodule.n_val} nodes never trained on, epoch "
                f"{metrics['val_epoch']}): RMSE {metrics['val_rmse_m']:.3f} m"
            )
        else:
            rank_zero_info("no held-out validation figure: every validation ran in the refit "
                           "phase (val_* keys are absent from metrics.json)")

    def _log_tensorboard(
        self,
        logger: TensorBoardLogger,
        trainer: pl.Trainer,
        pl_module: pl.LightningModule,
        figures: dict[str, Any],
        evaluation: FitEvaluation,
        metrics: dict[str, Any],
    ) -> None:
        writer = logger.experiment
        step = int(trainer.global_step)
        for tag, figure in figures.items():
            writer.add_image(tag, figure_to_rgb(figure), step, dataformats="HWC")
        residual = evaluation.residual[np.isfinite(evaluation.residual)]
        writer.add_histogram(HISTOGRAM_TAG, residual, step, bins="auto")
        final = {
            f"final/{key}": float(metrics[key])
            for key in FINAL_SCALARS
            if key in metrics and np.isfinite(float(metrics[key]))
        }
        params = _flat_hparams(dict(pl_module.hparams), "model/")
        datamodule = trainer.datamodule  # type: ignore[attr-defined]
        params.update(_flat_hparams(dict(datamodule.hparams), "data/"))
        params["tile"] = str(metrics["tile"])
        params["num_parameters"] = int(metrics["num_parameters"])
        logger.log_hyperparams(params, metrics=final, step=step)
        writer.flush()
