"""TerrainFitModule: Lightning training of a BlockwiseTerrainNet on a DEM tile."""

from __future__ import annotations

import math
import time
from typing import Any

import lightning.pytorch as pl
import torch
from lightning.pytorch.utilities.rank_zero import rank_zero_warn

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.blockwise import NET_DEFAULTS, BlockwiseTerrainNet
from neuralmap.training.evaluation import FitAccumulator, height_and_slope

OPTIMIZERS = ("adam", "sgd")
#: Hyperparameters that fix the network's shape and initial state (must match on resume).
ARCHITECTURE_KEYS = ("block_nodes", "overlap_nodes", "num_blocks", "encoding", "n_frequencies",
                     "frequency_scale", "hidden", "depth", "activation", "blend", "seed")
LR_SCHEDULES = ("cosine", "onecycle", "none")


class TerrainFitModule(pl.LightningModule):
    """Fits a `BlockwiseTerrainNet` to the nodes of a DEM tile.

    The network is built from the data module's tile in `configure_model` (seeded,
    so every DDP rank and a resumed run build the same one before weights are loaded).

    Loss (SEEDS 004's ``e``, normalised): ``L = mean((N(x_i, y_i) - h_i)^2) / s^2`` with
    ``s = net.height_scale`` the tile's height standard deviation, so the loss is unitless.
    When the data module also serves points between the nodes (``data.offnode_ratio > 0``,
    targets from the bicubic DEM ``B``, `OffNodeSampler`),
    the loss fits the continuous surface too::

        L += offnode_weight * mean((N(p_j) - B(p_j))^2) / s^2
             + offnode_slope_weight * mean(|grad N(p_j) - grad B(p_j)|^2) * d^2 / s^2

    with ``d`` the mean grid spacing (a slope error times one cell = a height error), so
    that the map is no worse a surface than the grid it replaces where the filter samples
    it (between the nodes).
    Optimiser: Adam, or SGD with momentum (the paper's back-propagation with momentum).
    Stopping: optionally when the validation RMSE falls below ``target_rmse`` metres (the
    paper stops at ``e < rho``; see `neuralmap.training.callbacks.TargetRmseStopping`).

    Logged per epoch: ``train/loss``, ``train/lr``, ``val/rmse_m``, ``val/max_abs_m``,
    ``val/mean_m`` (metres) and ``val/slope_rmse`` (m/m, RMS norm of the slope error against
    the bicubic DEM slopes at the validation nodes), under ``refit/`` instead of ``val/``
    in the refit epochs (``data.refit_epochs``: those nodes are then trained on, so the
    error is in-sample); ``train/offnode_loss`` and
    ``val/offnode_rmse_m``, ``val/offnode_max_abs_m`` (the map against the bicubic DEM at
    fixed points between the nodes).

    The network arguments default to `neuralmap.terrain.blockwise.NET_DEFAULTS`
    (the net's own defaults), so the module, the net and ``configs/train.yaml`` cannot drift.

    Args:
        block_nodes: Block core width in node intervals (``None`` with ``num_blocks``).
        overlap_nodes: Blending zone width in node intervals.
        num_blocks: ``[nbx, nby]`` block grid; overrides ``block_nodes``.
        encoding: ``"fourier"`` or ``"none"``.
        n_frequencies: Fourier frequencies per block.
        frequency_scale: Std of the Gaussian frequencies (cycles per block half-width).
        hidden: Hidden width.
        depth: Hidden layers.
        activation: ``sine``, ``tanh``, ``silu`` or ``bipolar_sigmoid``.
        blend: Smooth blending between blocks (False = the paper's hard gate).
        optimizer: ``"adam"`` or ``"sgd"``.
        lr: Learning rate (peak rate for ``onecycle``).
        momentum: SGD momentum.
        weight_decay: L2 weight decay.
        lr_schedule: ``"cosine"`` (to 0 over the run's steps), ``"onecycle"`` or ``"none"``.
        target_rmse: Stop when the validation RMSE (m) is below this; ``None`` = never.
        seed: Seed of the network's initial weights and frequencies.
        offnode_weight: Weight of the off-node height term (batches without off-node
            points, ``data.offnode_ratio: 0``, train on the nodes alone).
        offnode_slope_weight: Weight of the off-node slope term (``0`` skips it; it costs
            a second backward pass).

    Raises:
        NeuralMapError: Unknown optimiser or schedule, non-positive ``lr``, negative
            ``momentum``/``weight_decay``/``target_rmse``/off-node weights.
    """

    def __init__(
        self,
        block_nodes: int | None = NET_DEFAULTS.block_nodes,
        overlap_nodes: float = NET_DEFAULTS.overlap_nodes,
        num_blocks: list[int] | None = None,
        encoding: str = NET_DEFAULTS.encoding,
        n_frequencies: int = NET_DEFAULTS.n_frequencies,
        frequency_scale: float = NET_DEFAULTS.frequency_scale,
        hidden: int = NET_DEFAULTS.hidden,
        depth: int = NET_DEFAULTS.depth,
        activation: str = NET_DEFAULTS.activation,
        blend: bool = NET_DEFAULTS.blend,
        optimizer: str = "adam",
        lr: float = 3e-3,
        momentum: float = 0.9,
        weight_decay: float = 0.0,
        lr_schedule: str = "cosine",
        target_rmse: float | None = None,
        seed: int = NET_DEFAULTS.seed,
        offnode_weight: float = 1.0,
        offnode_slope_weight: float = 0.0,
    ) -> None:
        super().__init__()
        if optimizer not in OPTIMIZERS:
            raise NeuralMapError(
                f"--model.optimizer = {optimizer!r} is not supported; choose one of {OPTIMIZERS}."
            )
        if lr_schedule not in LR_SCHEDULES:
            raise NeuralMapError(
                f"--model.lr_schedule = {lr_schedule!r} is not supported; choose one of "
                f"{LR_SCHEDULES}."
            )
        if not (math.isfinite(lr) and lr > 0):
            raise NeuralMapError(f"--model.lr must be finite and > 0, got {lr}.")
        if momentum < 0 or weight_decay < 0:
            raise NeuralMapError(
                f"--model.momentum and --model.weight_decay must be >= 0, got {momentum}, "
                f"{weight_decay}."
            )
        if target_rmse is not None and not target_rmse > 0:
            raise NeuralMapError(
                f"--model.target_rmse must be > 0 metres (or null to disable), got {target_rmse}."
            )
        for key, weight in (("offnode_weight", offnode_weight),
                            ("offnode_slope_weight", offnode_slope_weight)):
            if not (math.isfinite(weight) and weight >= 0):
                raise NeuralMapError(
                    f"--model.{key} must be a finite number >= 0, got {weight}. Try 1.0 "
                    "(0 ignores the off-node points)."
                )
        if num_blocks is not None and len(num_blocks) != 2:
            raise NeuralMapError(
                f"--model.num_blocks must be [nbx, nby] (blocks along east, north), got {num_blocks}."
            )
        self.save_hyperparameters()
        self.net: BlockwiseTerrainNet | None = None
        self.points_seen = 0
        self.heldout_metrics: dict[str, float] = {}
        self.train_time_s = 0.0
        self._epoch_start: float | None = None
        self._val = FitAccumulator()

    # ------------------------------------------------------------------ model
    def net_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of `BlockwiseTerrainNet.from_tile` from the hparams."""
        hp = self.hparams
        return {
            "block_nodes": hp.block_nodes,
            "overlap_nodes": hp.overlap_nodes,
            "num_blocks": tuple(hp.num_blocks) if hp.num_blocks is not None else None,
            "encoding": hp.encoding,
            "n_frequencies": hp.n_frequencies,
            "frequency_scale": hp.frequency_scale,
            "hidden": hp.hidden,
            "depth": hp.depth,
            "activation": hp.activation,
            "blend": hp.blend,
            "seed": hp.seed,
        }

    def build(self, tile: DemTile) -> BlockwiseTerrainNet:
        """Builds the network for ``tile`` (once; later calls return the same net).

        Raises:
            NeuralMapError: When the tile cannot feed the requested blocks.
        """
        if self.net is None:
            self.net = BlockwiseTerrainNet.from_tile(tile, **self.net_kwargs())
        return self.net

    def configure_model(self) -> None:
        """Builds the net from ``trainer.datamodule.tile`` (before weights are restored)."""
        if self.net is not None:
            return
        datamodule = getattr(self.trainer, "datamodule", None)
        tile = getattr(datamodule, "tile", None)
        if not isinstance(tile, DemTile):
            raise NeuralMapError(
                "TerrainFitModule needs a DemDataModule (trainer.fit(model, datamodule=...)) "
                "or a net built beforehand with module.build(tile)."
            )
        self.build(tile)

    def configure_callbacks(self) -> list[pl.Callback]:
        """Adds the target-RMSE stop when ``target_rmse`` is set."""
        from neuralmap.training.callbacks.target_rmse import TargetRmseStopping

        if self.hparams.target_rmse is None:
            return []
        return [TargetRmseStopping(self.hparams.target_rmse)]

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        """Heights ``(...)`` in metres at ``xy`` ``(..., 2)``."""
        assert self.net is not None, "call configure_model() or build(tile) first"
        return self.net(xy)

    # ------------------------------------------------------------------ training
    def training_step(
        self, batch: tuple[torch.Tensor, ...], batch_idx: int
    ) -> torch.Tensor:
        """One step on a batch ``(xy (B, 2), h (B,))``: normalised MSE (SEEDS 004 ``e``),
        plus the off-node terms when the batch carries ``(xy_off, h_off, slope_off)``."""
        xy, target = batch[0], batch[1]
        assert self.net is not None
        scale2 = self.net.height_scale**2
        pred = self.net(xy)
        loss = torch.nn.functional.mse_loss(pred, target) / scale2
        self.points_seen += int(target.numel())
        if len(batch) == 5 and (self.hparams.offnode_weight > 0
                                or self.hparams.offnode_slope_weight > 0):
            off = self._offnode_loss(*batch[2:]) / scale2
            self.log("train/offnode_loss", off, on_step=False, on_epoch=True,
                     batch_size=int(batch[3].numel()), sync_dist=True)
            loss = loss + off
        self.log("train/loss", loss, on_step=False, on_epoch=True, prog_bar=True,
                 batch_size=int(target.numel()), sync_dist=True)
        return loss

    def _offnode_loss(
        self, xy: torch.Tensor, target: torch.Tensor, slope_ref: torch.Tensor
    ) -> torch.Tensor:
        """Weighted off-node height (and slope) squared error, m^2 (not yet normalised)."""
        assert self.net is not None
        hp = self.hparams
        use_slope = hp.offnode_slope_weight > 0
        points = xy.detach().requires_grad_(True) if use_slope else xy
        pred = self.net(points)
        loss = hp.offnode_weight * torch.nn.functional.mse_loss(pred, target)
        if use_slope:
            (slope,) = torch.autograd.grad(pred.sum(), points, create_graph=True)
            spacing = self.net.tile_info.get("spacing") or (1.0, 1.0)
            cell2 = float(spacing[0]) * float(spacing[1])
            loss = loss + hp.offnode_slope_weight * cell2 * (
                (slope - slope_ref).square().sum(-1).mean())
        return loss

    def on_train_epoch_start(self) -> None:
        self._epoch_start = time.perf_counter()

    def on_train_epoch_end(self) -> None:
        if self._epoch_start is not None:
            self.train_time_s += time.perf_counter() - self._epoch_start
            self._epoch_start = None
        optimizer = self.optimizers(use_pl_optimizer=False)
        lr = optimizer.param_groups[0]["lr"]  # type: ignore[union-attr]
        self.log("train/lr", float(lr), on_step=False, on_epoch=True, sync_dist=True)

    # ------------------------------------------------------------------ validation / test
    def _accumulate(self, batch: tuple[torch.Tensor, ...]) -> None:
        xy, target, slope_ref = batch
        if xy.shape[0] == 0:
            return
        assert self.net is not None
        pred, slope = height_and_slope(self.net, xy)
        self._val.update(pred, target, slope, slope_ref)

    def _reduced_metrics(self) -> dict[str, float]:
        acc = self._val
        self._val = FitAccumulator()
        state = acc.as_tensor().to(self.device)
        if self.trainer is not None and self.trainer.world_size > 1:
            sums = self.trainer.strategy.reduce(state.clone(), reduce_op="sum")
            maxima = self.trainer.strategy.reduce(state.clone(), reduce_op="max")
            acc = FitAccumulator.from_tensors(sums.cpu(), maxima.cpu())
        return acc.metrics()

    def on_validation_epoch_start(self) -> None:
        self._val = FitAccumulator()

    def validation_step(self, batch: tuple[torch.Tensor, ...], batch_idx: int) -> None:
        """Accumulates errors on a chunk ``(xy (N, 2), h (N,), slope_ref (N, 2))``."""
        self._accumulate(batch)

    def on_validation_epoch_end(self) -> None:
        # Already reduced over ranks; sync_dist only keeps Lightning's bookkeeping uniform.
        m = self._reduced_metrics()
        datamodule = getattr(self.trainer, "datamodule", None)
        in_refit = getattr(datamodule, "in_refit", None)
        refit = in_refit is not None and in_refit(int(self.current_epoch))
        if not refit:
            # Last validation on truly held-out nodes (before any refit on all nodes).
            self.heldout_metrics = {"epoch": int(self.current_epoch), **m}
        # In the refit the validation nodes are trained on: the same error is in-sample
        # and goes under refit/ (never val/, which best-*.ckpt is ranked by).
        prefix = "refit" if refit else "val"
        self.log_dict({f"{prefix}/rmse_m": m["rmse_m"], f"{prefix}/max_abs_m": m["max_abs_m"]},
                      prog_bar=True, sync_dist=True)
        self.log_dict({f"{prefix}/mean_m": m["mean_m"], f"{prefix}/slope_rmse": m["slope_rmse"]},
                      sync_dist=True)
        off = getattr(datamodule, "offnode_val", None)
        if off is not None:
            err = self._offnode_errors(off[0], off[1])
            self.log_dict({"val/offnode_rmse_m": err.square().mean().sqrt(),
                           "val/offnode_max_abs_m": err.abs().max()}, sync_dist=True)

    def _offnode_errors(self, xy: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """``(M,)`` float64 map minus bicubic DEM at fixed off-node points, metres."""
        assert self.net is not None
        with torch.no_grad():
            pred = self.net(xy.to(self.device))
        return (pred.double() - target.to(pred.device).double()).cpu()

    def on_test_epoch_start(self) -> None:
        self._val = FitAccumulator()

    def test_step(self, batch: tuple[torch.Tensor, ...], batch_idx: int) -> None:
        """Accumulates errors on a chunk of all valid nodes."""
        self._accumulate(batch)

    def on_test_epoch_end(self) -> None:
        m = self._reduced_metrics()
        keys = ("rmse_m", "max_abs_m", "mean_m", "slope_rmse")
        self.log_dict({f"test/{key}": m[key] for key in keys}, sync_dist=True)

    # ------------------------------------------------------------------ optimisation
    def configure_optimizers(self) -> Any:
        """Adam or SGD with momentum, with a cosine / one-cycle / constant schedule."""
        assert self.net is not None
        hp = self.hparams
        if hp.optimizer == "adam":
            optimizer: torch.optim.Optimizer = torch.optim.Adam(
                self.net.parameters(), lr=hp.lr, weight_decay=hp.weight_decay
            )
        else:
            optimizer = torch.optim.SGD(
                self.net.parameters(), lr=hp.lr, momentum=hp.momentum,
                weight_decay=hp.weight_decay,
            )
        if hp.lr_schedule == "none":
            return optimizer
        total = self.trainer.estimated_stepping_batches
        if not math.isfinite(total) or total < 1:
            rank_zero_warn(
                f"lr_schedule={hp.lr_schedule!r} needs a finite run length (trainer.max_epochs "
                "or trainer.max_steps); using a constant learning rate."
            )
            return optimizer
        total = int(total)
        if hp.lr_schedule == "cosine":
            scheduler: torch.optim.lr_scheduler.LRScheduler = (
                torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=total)
            )
        else:
            # total + 1: the scheduler is stepped after each of the `total` steps, so the
            # last step lands on the end of the annealing phase (not past it).
            scheduler = torch.optim.lr_scheduler.OneCycleLR(
                optimizer, max_lr=hp.lr, total_steps=total + 1
            )
        return {
            "optimizer": optimizer,
            "lr_scheduler": {"scheduler": scheduler, "interval": "step"},
        }

    # ------------------------------------------------------------------ checkpoint state
    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["neuralmap"] = {
            "points_seen": self.points_seen,
            "train_time_s": self.train_time_s,
            "tile_fingerprint": self.net.tile_fingerprint if self.net is not None else "",
            "tile_name": self.net.tile_name if self.net is not None else "",
            "heldout_metrics": dict(self.heldout_metrics),
        }

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Restores the counters; refuses a checkpoint of another tile or architecture.

        Raises:
            NeuralMapError: When the checkpoint's network settings or tile differ.
        """
        saved = checkpoint.get("hyper_parameters", {})
        differ = [
            f"{key}: checkpoint {saved[key]!r} vs config {self.hparams[key]!r}"
            for key in ARCHITECTURE_KEYS
            if key in saved and _canonical(saved[key]) != _canonical(self.hparams[key])
        ]
        if differ:
            raise NeuralMapError(
                "--ckpt_path: the checkpoint was trained with other network settings ("
                + "; ".join(differ) + "). Resume with the run's config.yaml: "
                "python train.py --config runs/<experiment>/version_N/config.yaml --ckpt_path ..."
            )
        state = checkpoint.get("neuralmap", {})
        fingerprint = state.get("tile_fingerprint", "")
        if self.net is not None and fingerprint and fingerprint != self.net.tile_fingerprint:
            raise NeuralMapError(
                f"--ckpt_path: the checkpoint was trained on tile '{state.get('tile_name')}' "
                f"(fingerprint {fingerprint}), not on '{self.net.tile_name}' "
                f"({self.net.tile_fingerprint}). Pass the same --data.path as that run."
            )
        self.points_seen = int(state.get("points_seen", 0))
        self.train_time_s = float(state.get("train_time_s", 0.0))
        self.heldout_metrics = dict(state.get("heldout_metrics", {}))


def _canonical(value: Any) -> Any:
    """Lists and tuples compare equal (YAML gives lists, Python callers may pass tuples)."""
    return list(value) if isinstance(value, (list, tuple)) else value
