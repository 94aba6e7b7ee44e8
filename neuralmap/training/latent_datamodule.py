"""LatentDataModule: one DEM tile for latent-grid map training (full-tile steps).

A latent-grid map is fitted to the whole tile at every step (every node plus random
between-node points, `RateDistortion`), so an epoch is
just ``steps_per_epoch`` step indices; validation is one item (the whole tile, quantised).

Several DEM files (a glob such as ``'tiles/*.hgt'`` or a list), or ``tile_nodes``, make a
tileset run instead: `tileset_plan` holds the region and its tiles
(`neuralmap.training.latent_tileset.plan_tileset`), which ``train.py latent`` fits tile by
tile into a latent tileset.
"""

from __future__ import annotations

from pathlib import Path

import lightning.pytorch as pl
import torch
from lightning.pytorch.utilities.rank_zero import rank_zero_info
from torch.utils.data import DataLoader, Dataset

from neuralmap.dem import load_tile
from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.training.datamodule import spacing_argument
from neuralmap.training.latent_tileset import TilesetPlan, is_tileset_source, plan_tileset


class _Steps(Dataset):
    """``count`` items, each its own index (the module does the work)."""

    def __init__(self, count: int) -> None:
        self.count = int(count)

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, index: int) -> torch.Tensor:
        if not 0 <= index < self.count:
            raise IndexError(index)
        return torch.tensor(index)


class LatentDataModule(pl.LightningDataModule):
    """A DEM tile served as full-tile training steps.

    Args:
        path: Sample name (``jacksboro``, ``synthetic``, ``synthetic:64x48``) or a DEM file
            (`neuralmap.dem.load_tile`); from Python also a `DemTile`. A glob pattern or a
            list of DEM files: a tileset, one tile per file.
        spacing: Grid spacing in metres for files that do not carry it: one number or
            ``[dx, dy]`` (as ``train.py map``'s ``--data.spacing``).
        steps_per_epoch: Optimisation steps per epoch (each over the whole tile).
        overlap_nodes: Tileset: overlap margin and blend half-width at the seams, node
            intervals (`neuralmap.terrain.latent.tileset_layout`).
        tile_nodes: Tileset: cut the region (or one DEM) into tiles of this many node
            intervals instead of one tile per file.

    Attributes:
        tileset_plan: The region and its tiles for a tileset run, else None.

    Raises:
        NeuralMapError: Bad path / file, or ``steps_per_epoch`` < 1; for a tileset an empty
            glob, tiles that do not form a region, mismatched spacing / CRS.
    """

    def __init__(self, path: str | Path | list[str] = "jacksboro",
                 spacing: float | list[float] | None = None, steps_per_epoch: int = 100,
                 overlap_nodes: int = 4, tile_nodes: int | None = None) -> None:
        super().__init__()
        if int(steps_per_epoch) < 1:
            raise NeuralMapError(
                f"--data.steps_per_epoch must be >= 1, got {steps_per_epoch}.")
        self.steps_per_epoch = int(steps_per_epoch)
        self.tileset_plan: TilesetPlan | None = None
        if not isinstance(path, DemTile) and (is_tileset_source(path) or tile_nodes is not None):
            self.tileset_plan = plan_tileset(path, overlap_nodes=overlap_nodes,
                                             tile_nodes=tile_nodes,
                                             spacing=spacing_argument(spacing))
            self.tile: DemTile = self.tileset_plan.region
            rows, cols = self.tileset_plan.layout.grid
            rank_zero_info(
                f"tileset '{self.tile.name}': {self.tile.shape[0]} x {self.tile.shape[1]} nodes "
                f"in {rows} x {cols} tiles, overlap {overlap_nodes} nodes")
            return
        if isinstance(path, DemTile):
            self.tile = path
        else:
            self.tile = load_tile(str(path), spacing=spacing_argument(spacing))  # type: ignore[arg-type]
        rank_zero_info(
            f"tile '{self.tile.name}': {self.tile.shape[0]} x {self.tile.shape[1]} nodes, "
            f"spacing {self.tile.spacing[0]:.2f} x {self.tile.spacing[1]:.2f} m")

    @property
    def experiment_name(self) -> str:
        """Run folder name: ``latent_<tile name>``."""
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in self.tile.name)
        return f"latent_{safe}"

    def train_dataloader(self) -> DataLoader:
        return DataLoader(_Steps(self.steps_per_epoch), batch_size=None, shuffle=False)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(_Steps(1), batch_size=None, shuffle=False)
