"""LatentFitModule: Lightning training of a latent-grid neural map on one DEM tile."""

from __future__ import annotations

import math
from typing import Any

import lightning.pytorch as pl
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.latent.basis import check_basis
from neuralmap.terrain.latent.encode import (
    RELAXATIONS,
    make_optimizer,
    quantizer_at,
    rdoq_rate_weight,
    soft_alpha,
    zones_due,
)
from neuralmap.terrain.latent.latent_grid import LatentGrid, check_entropy, export_map
from neuralmap.terrain.latent.map import LatentTerrainMap
from neuralmap.terrain.latent.objective import RateDistortion, check_rate_weight
from neuralmap.terrain.latent.quality import map_quality
from neuralmap.terrain.latent.zones import check_zones

#: Hyperparameters that fix the latent grid's shape (must match on resume).
ARCHITECTURE_KEYS = ("levels", "hidden", "seed", "basis", "wavelet", "entropy",
                     "context_hidden", "zones")
#: Hyperparameters of checkpoints written before the zones got their name -> the names now.
OLD_HPARAMS = {"regions": "zones"}


class LatentFitModule(pl.LightningModule):
    """Fits a `LatentGrid` with ``D + lambda R``.

    Each step evaluates `RateDistortion` on the whole tile:
    node MSE, between-node MSE against bicubic of the DEM, and ``lambda`` times the rate in
    bits per node; the rounding is relaxed by noise, then straight-through for the last
    ``ste_fraction`` of the steps (`quantizer_at`).

    Logged: ``train/loss``, ``train/rate_bits``, ``train/rate_bytes``,
    ``train/bits_per_node``, ``train/node_rmse_m``, ``train/between_rmse_m``,
    ``train/lambda``, ``train/lr``; per validation (the map as stored, hard rounding):
    ``val/file_bytes``, ``val/bits_per_node``, ``val/rmse_m``, ``val/max_abs_m``,
    ``val/between_rmse_m``.

    Args:
        levels: Latent levels (knots ``2^l`` nodes apart).
        hidden: MLP hidden units (0 = linear synthesis, the default: queries at grid speed;
            8 = the tanh residual MLP, about 7x slower queries, see ``bench_filter.py`` (f)).
        rate_weight: ``lambda``, m² per bit per node (> 0); larger = smaller map.
        between_weight: Weight of the between-node MSE (0 = nodes only).
        between_points: Random between-node points per step.
        lr: Peak Adam learning rate (cosine decay to a tenth).
        init_step: Initial quantisation step of every level, metres.
        ste_fraction: Final fraction of steps with straight-through rounding.
        seed: Seed of the MLP weights and between-node points.
        exact_start: Start from latents that reproduce every node exactly
            (`exact_finest`); false keeps the
            Laplacian-pyramid sweeps alone (pyramid basis).
        basis: ``"wavelet"`` (critically sampled subbands of a CDF wavelet transform of
            the B-spline coefficient grid) or ``"pyramid"`` (overcomplete B-spline levels).
        wavelet: ``"cdf97"`` or ``"cdf53"`` (wavelet basis).
        entropy: ``"factorized"`` (one Laplace per subband) or ``"context"`` (the context
            MLP of `neuralmap.terrain.latent.context_model`, stored in the file; wavelet
            basis).
        context_hidden: Hidden units of the context MLP.
        relaxation: First-phase relaxation of the rounding: ``"noise"`` or ``"soft"``
            (soft rounding annealed, `soft_alpha`).
        rdoq: Choose the stored symbols by rate-distortion-optimised quantisation
            (`neuralmap.terrain.latent.rdoq`) instead of rounding.
        zones: Side ``R`` of the grid of zones with their own quantisation steps and
            entropy scales (`neuralmap.terrain.latent.zones`; 0 = one step per subband,
            the default). The codes are chosen by RDO when straight-through rounding starts;
            files with zones are format 4.

    Raises:
        NeuralMapError: ``rate_weight`` <= 0, or other out-of-range settings.
    """

    def __init__(self, levels: int = 6, hidden: int = 0, rate_weight: float = 3.0,
                 between_weight: float = 0.5, between_points: int = 8192, lr: float = 0.01,
                 init_step: float = 1.0, ste_fraction: float = 0.2, seed: int = 0,
                 exact_start: bool = True, basis: str = "wavelet",
                 wavelet: str = "cdf97", entropy: str = "factorized",
                 context_hidden: int = 12, relaxation: str = "noise",
                 rdoq: bool = False, zones: int = 0) -> None:
        super().__init__()
        check_rate_weight(rate_weight)
        check_zones(zones)
        if not (math.isfinite(lr) and lr > 0):
            raise NeuralMapError(f"--model.lr must be finite and > 0, got {lr}.")
        if not 0.0 <= ste_fraction <= 1.0:
            raise NeuralMapError(f"--model.ste_fraction must be in [0, 1], got {ste_fraction}.")
        check_basis(basis, wavelet)
        check_entropy(entropy, basis)
        if relaxation not in RELAXATIONS:
            raise NeuralMapError(f"--model.relaxation must be one of {list(RELAXATIONS)}, got "
                                 f"{relaxation!r}.")
        self.save_hyperparameters()
        self.grid: LatentGrid | None = None
        self.objective: RateDistortion | None = None
        self.tile: DemTile | None = None
        self.last_quality: dict[str, Any] = {}

    def build(self, tile: DemTile) -> LatentGrid:
        """Builds the latent grid and objective for ``tile`` (once)."""
        if self.grid is None:
            hp = self.hparams
            torch.manual_seed(int(hp.seed))
            self.tile = tile
            self.grid = LatentGrid(tile, levels=hp.levels, hidden=hp.hidden,
                                   init_step=hp.init_step, seed=hp.seed,
                                   exact_start=bool(hp.get("exact_start", True)),
                                   basis=str(hp.get("basis", "wavelet")),
                                   wavelet=str(hp.get("wavelet", "cdf97")),
                                   entropy=str(hp.get("entropy", "factorized")),
                                   context_hidden=int(hp.get("context_hidden", 12)),
                                   zones=int(hp.get("zones", 0)))
            self.objective = RateDistortion(tile, rate_weight=hp.rate_weight,
                                            between_weight=hp.between_weight,
                                            between_points=hp.between_points)
            self._generator = torch.Generator().manual_seed(int(hp.seed))
        return self.grid

    def configure_model(self) -> None:
        if self.grid is not None:
            return
        tile = getattr(getattr(self.trainer, "datamodule", None), "tile", None)
        if not isinstance(tile, DemTile):
            raise NeuralMapError(
                "LatentFitModule needs a LatentDataModule (trainer.fit(model, datamodule=...)) "
                "or a grid built beforehand with module.build(tile).")
        self.build(tile)

    def total_steps(self) -> int:
        total = self.trainer.estimated_stepping_batches
        return int(total) if math.isfinite(total) and total >= 1 else 1

    def training_step(self, batch: torch.Tensor, batch_idx: int) -> torch.Tensor:
        assert self.grid is not None and self.objective is not None
        step, total = int(self.global_step), self.total_steps()
        fraction = float(self.hparams.ste_fraction)
        if self.grid.zones and zones_due(step, total, fraction):
            self.grid.choose_zones(self._node_lambda())
        quantizer = quantizer_at(step, total, fraction,
                                 str(self.hparams.get("relaxation", "noise")))
        terms = self.objective(self.grid, quantizer, self._generator,
                               soft_alpha(step, total, fraction))
        bits = terms.bits.detach()
        self.log_dict({
            "train/loss": terms.loss.detach(),
            "train/rate_bits": bits,
            "train/rate_bytes": bits / 8.0,
            "train/bits_per_node": terms.bits_per_node.detach(),
            "train/node_rmse_m": terms.node_mse.detach().sqrt(),
            "train/between_rmse_m": terms.between_mse.detach().sqrt(),
            "train/lambda": float(self.hparams.rate_weight),
            "train/ste": float(quantizer == "ste"),
        }, on_step=True, on_epoch=False, batch_size=1)
        return terms.loss

    def _node_lambda(self) -> float:
        """``lambda'`` of RDOQ and of the zone codes (m² per bit, node error only)."""
        return rdoq_rate_weight(float(self.hparams.rate_weight),
                                float(self.hparams.between_weight))

    def stored_map(self, metrics: dict[str, Any] | None = None) -> LatentTerrainMap:
        """The map exactly as its file stores it (before the fit chooses the zone codes,
        with codes chosen for this export only)."""
        assert self.grid is not None
        lam = self._node_lambda() if self.hparams.get("rdoq", False) else None
        assert self.objective is not None
        return export_map(self.grid, metrics=metrics, rdoq_rate_weight=lam,
                          rdoq_target=(self.objective.heights, self.objective.valid),
                          zone_rate_weight=self._node_lambda())

    def validation_step(self, batch: torch.Tensor, batch_idx: int) -> None:
        assert self.tile is not None
        quality = map_quality(self.stored_map(), self.tile, n_between=8192)
        self.last_quality = quality
        self.log("val/rmse_m", quality["rmse_m"], prog_bar=True, batch_size=1)
        self.log("val/file_bytes", float(quality["file_bytes"]), prog_bar=True, batch_size=1)
        for key in ("bits_per_node", "max_abs_m", "between_rmse_m"):
            self.log(f"val/{key}", float(quality[key]), batch_size=1)

    def configure_optimizers(self) -> Any:
        assert self.grid is not None
        optimizer, scheduler = make_optimizer(self.grid, float(self.hparams.lr), self.total_steps())
        self.log_lr = scheduler
        return {"optimizer": optimizer,
                "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    def on_train_batch_end(self, outputs: Any, batch: Any, batch_idx: int) -> None:
        optimizer = self.optimizers(use_pl_optimizer=False)
        self.log("train/lr", float(optimizer.param_groups[0]["lr"]), on_step=True,  # type: ignore[union-attr]
                 on_epoch=False, batch_size=1)

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["neuralmap"] = {
            "tile_fingerprint": self.tile.fingerprint() if self.tile is not None else "",
            "tile_name": self.tile.name if self.tile is not None else "",
        }

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Refuses a checkpoint of another tile or latent-grid shape.

        Raises:
            NeuralMapError: When the checkpoint's levels / hidden / seed or tile differ.
        """
        saved = {OLD_HPARAMS.get(key, key): value
                 for key, value in checkpoint.get("hyper_parameters", {}).items()}
        differ = [f"{key}: checkpoint {saved[key]!r} vs config {self.hparams[key]!r}"
                  for key in ARCHITECTURE_KEYS if key in saved and saved[key] != self.hparams[key]]
        if differ:
            raise NeuralMapError("--ckpt_path: the checkpoint was trained with other latent-grid "
                                 "settings (" + "; ".join(differ) + "). Resume with that run's "
                                 "config.yaml.")
        fingerprint = checkpoint.get("neuralmap", {}).get("tile_fingerprint", "")
        if self.tile is not None and fingerprint and fingerprint != self.tile.fingerprint():
            raise NeuralMapError(
                f"--ckpt_path: the checkpoint was trained on tile "
                f"'{checkpoint['neuralmap'].get('tile_name')}', not on '{self.tile.name}'. "
                "Pass the same --data.path as that run.")
