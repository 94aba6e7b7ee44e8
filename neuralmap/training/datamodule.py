"""DemDataModule: the valid nodes of a DEM tile as in-memory training and validation sets.

Every valid (non-void) node of the tile is one training point ``(x, y) -> h``. A seeded
random fraction is held out for validation; the final evaluation uses every valid node.
Batches are cut from in-memory tensors (no per-item DataLoader overhead): the training
dataset's item ``i`` *is* the ``i``-th batch of this epoch's permutation of the training
nodes, served with ``batch_size=None``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import numpy as np
import torch
from lightning.pytorch.utilities.rank_zero import rank_zero_info, rank_zero_warn
from torch.utils.data import DataLoader, Dataset

from neuralmap.dem import load_mosaic, load_tile
from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.grid import GridTerrain
from neuralmap.training.offnode import OffNodeSampler

#: Seed offset so that the split and the per-epoch shuffles use different streams.
_SHUFFLE_STREAM = 1_000_003
#: Seed offset of the off-node draws (another stream than the shuffles and the split).
_OFFNODE_STREAM = 7_919


class ShuffledBatches(Dataset):
    """Map-style dataset whose item ``i`` is the ``i``-th training batch of the epoch.

    The node order is a fresh permutation per epoch, drawn from ``seed`` and the epoch
    number (so a resumed run and every DDP rank see the same permutation). Lightning's
    distributed sampler then hands disjoint batch ids to the ranks.

    Args:
        xy: ``(N, 2)`` float32 node coordinates, metres.
        heights: ``(N,)`` float32 node heights, metres.
        batch_size: Points per batch (the last batch of an epoch may be smaller).
        seed: Base seed of the shuffles.
        epoch_fn: Returns the current epoch number.
        full: Optional ``(xy, heights)`` of every valid node, used instead of the training
            nodes in the epochs where ``full_fn(epoch)`` is true (the refit phase). The
            number of batches per epoch stays the same; batches grow slightly instead.
        full_fn: Whether an epoch trains on ``full``.
        offnode: Optional `OffNodeSampler`; each batch then also carries
            ``round(offnode_ratio * B)`` points between the nodes with their bicubic
            targets, drawn from a generator seeded by ``(seed, epoch, index)``.
        offnode_ratio: Off-node points per node point of a batch.
    """

    def __init__(
        self,
        xy: torch.Tensor,
        heights: torch.Tensor,
        *,
        batch_size: int,
        seed: int,
        epoch_fn: Callable[[], int],
        full: tuple[torch.Tensor, torch.Tensor] | None = None,
        full_fn: Callable[[int], bool] | None = None,
        offnode: OffNodeSampler | None = None,
        offnode_ratio: float = 0.0,
    ) -> None:
        if xy.ndim != 2 or xy.shape[1] != 2 or heights.shape != xy.shape[:1]:
            raise ValueError(
                f"xy (N, 2) and heights (N,) expected, got {xy.shape}, {heights.shape}"
            )
        self.xy = xy
        self.heights = heights
        self.batch_size = int(batch_size)
        self.seed = int(seed)
        self.epoch_fn = epoch_fn
        self.full = full
        self.full_fn = full_fn
        self.offnode = offnode
        self.offnode_ratio = float(offnode_ratio)
        self._cached: tuple[int, torch.Tensor] | None = None

    def __len__(self) -> int:
        return math.ceil(self.xy.shape[0] / self.batch_size)

    def _source(self, epoch: int) -> tuple[torch.Tensor, torch.Tensor]:
        if self.full is not None and self.full_fn is not None and self.full_fn(epoch):
            return self.full
        return self.xy, self.heights

    def permutation(self, epoch: int) -> torch.Tensor:
        """Node order of ``epoch`` over that epoch's node set (cached for the epoch)."""
        if self._cached is None or self._cached[0] != epoch:
            generator = torch.Generator().manual_seed(self.seed * _SHUFFLE_STREAM + epoch)
            n = self._source(epoch)[0].shape[0]
            self._cached = (epoch, torch.randperm(n, generator=generator))
        return self._cached[1]

    def __getitem__(self, index: int) -> tuple[torch.Tensor, ...]:
        """``(xy (B, 2), h (B,))``, plus ``(xy_off (M, 2), h_off (M,), slope_off (M, 2))``
        with an off-node sampler."""
        if not 0 <= index < len(self):
            raise IndexError(index)
        epoch = int(self.epoch_fn())
        order = self.permutation(epoch)
        size = self.batch_size
        if order.shape[0] != self.xy.shape[0]:  # refit phase: same batch count, all nodes
            size = math.ceil(order.shape[0] / len(self))
        take = order[index * size : (index + 1) * size]
        xy, heights = self._source(epoch)
        if self.offnode is None or self.offnode_ratio <= 0.0:
            return xy[take], heights[take]
        generator = torch.Generator().manual_seed(
            (self.seed * _SHUFFLE_STREAM + epoch) * _OFFNODE_STREAM + index)
        n_off = max(1, round(self.offnode_ratio * int(take.shape[0])))
        xy_off, h_off, slope_off = self.offnode.sample(n_off, generator, dtype=xy.dtype)
        return xy[take], heights[take], xy_off, h_off, slope_off


class Chunks(Dataset):
    """Map-style dataset of ``n_chunks`` contiguous slices of aligned tensors.

    Item ``r`` is the ``r``-th slice of every tensor (slices may be empty when there are
    fewer rows than chunks).

    Args:
        tensors: Tensors with the same first dimension.
        n_chunks: Number of slices (≥ 1).
    """

    def __init__(self, *tensors: torch.Tensor, n_chunks: int) -> None:
        self.tensors = tensors
        self.n_chunks = max(1, int(n_chunks))

    def __len__(self) -> int:
        return self.n_chunks

    def __getitem__(self, index: int) -> tuple[torch.Tensor, ...]:
        if not 0 <= index < self.n_chunks:
            raise IndexError(index)
        return tuple(torch.tensor_split(t, self.n_chunks)[index] for t in self.tensors)


def _is_mosaic(path: str | list[str]) -> bool:
    """A list of sources, or one glob pattern that is not an existing file."""
    if not isinstance(path, str):
        return True
    return any(c in path for c in "*?[") and not Path(path).exists()


def spacing_argument(spacing: float | list[float] | None
                     ) -> float | tuple[float, ...] | None:
    """``--data.spacing`` as `neuralmap.dem.load_tile` takes it: one number (square
    cells) or ``[dx, dy]`` metres, the same in every ``train.py`` mode.

    Raises:
        NeuralMapError: Neither a number nor two numbers.
    """
    if spacing is None:
        return None
    if np.ndim(spacing) == 0:
        return float(spacing)  # type: ignore[arg-type]
    values = tuple(spacing)  # type: ignore[arg-type]
    if len(values) != 2:
        raise NeuralMapError(
            f"--data.spacing {list(values)}: give one number (square cells) or two, "
            "[dx, dy] metres, e.g. --data.spacing [30,30].")
    return tuple(float(v) for v in values)


class DemDataModule(pl.LightningDataModule):
    """The valid nodes of one DEM tile, split into training and validation nodes.

    **Validation rule.** ``n_val = max(1, round(val_fraction * n_valid))`` nodes are drawn
    uniformly at random without replacement from the valid (non-void) nodes with a
    ``torch.Generator`` seeded by ``seed``; they are never used for training. Because the
    held-out nodes sit between training nodes, the validation RMSE measures how well the
    map interpolates the DEM at nodes it did not see. The **final evaluation** (see
    `neuralmap.training.evaluation.evaluate_fit`) uses every valid node, training and
    validation alike. Void nodes are excluded from everything and counted
    (`n_void`).

    Training batches are cut from in-memory tensors: item ``i`` of the training dataset is
    the ``i``-th batch of this epoch's seeded permutation (``batch_size=None`` loader,
    ``num_workers=0``). Under DDP, Lightning's distributed sampler shards the batch ids over
    the ranks, so each rank trains on disjoint batches of the same permutation; validation
    is split into one chunk per rank.

    Args:
        path: Sample name (``"jacksboro"``, ``"synthetic"``) or DEM file path, as for
            `neuralmap.dem.load_tile`; a glob (``"srtm/*.hgt"``) or a list of files /
            globs: the tiles stitched by `neuralmap.dem.load_mosaic`; from Python
            also an already loaded `DemTile` (see `from_tile`).
        spacing: Grid spacing in metres for files that do not carry it (``.npy``, generic
            ``.npz``): one number or ``[dx, dy]``.
        origin: ``[x0, y0]`` metres of node ``[0, 0]`` for such files.
        name: Tile name (default: from the file or sample); names the run folder.
        batch_size: Training points per optimisation step.
        val_fraction: Fraction of valid nodes held out for validation, in ``(0, 0.5]``.
        seed: Seed of the validation split and of the per-epoch shuffles.
        eval_batch_size: Points per chunk for validation, testing and the final evaluation.
        refit_epochs: The last R epochs train on every valid node (held-out ones included).
            Must be below ``trainer.max_epochs`` to leave a held-out phase; a refit as long
            as the run (or longer, or a run without ``max_epochs``) is disabled with a
            printed warning, so held-out figures are always held out.
        units: ``"metres"`` / ``"degrees"`` for ``.asc``/GeoTIFF files whose units the
            reader cannot tell (see `neuralmap.dem.load_tile`).
        nodata: Extra no-data value(s) of the file (e.g. ``-32768`` for int16 SRTM voids).
        height_check: ``"refuse"`` (default), ``"void"`` or ``"off"`` for heights outside
            −12 000 … +9 000 m.
        offnode_ratio: Points between the nodes per node point in every training batch,
            with the bicubic DEM as target (`OffNodeSampler`), so that the map fits
            the continuous surface and not only the nodes; ``0`` trains on the nodes
            alone. How much they weigh is the module's ``offnode_weight``.
        offnode_val_points: Fixed seeded off-node points of the per-epoch validation
            (``val/offnode_rmse_m``: the map against the bicubic DEM between the nodes).
        min_batches: At least this many optimisation steps per epoch: the training batch is
            ``min(batch_size, ceil(n_train / min_batches))`` points (`train_batch_size`).
            With a fixed ``batch_size`` a small tile would get one step per epoch (a 7 000-
            node tile 400 steps in 400 epochs, a 140 000-node one 6 800) and end under-fitted;
            ``1`` keeps ``batch_size`` whatever the tile.
        offnode_surface: Target surface of the off-node training points: ``"bicubic"``
            (Keys, the grid's answer) or ``"spline"`` (the interpolating cubic spline of the
            nodes, see `neuralmap.training.offnode`). The logged ``val/offnode_*`` error is
            against the bicubic DEM either way.
        offnode_voids: ``"skip"`` (no off-node point in a cell touching a void) or
            ``"fill"`` (also the cells next to voids, the target surface built on the voids
            filled by the Clough-Tocher cubic of the valid nodes; `OffNodeSampler`).

    Raises:
        NeuralMapError: Bad path/file (from ``load_tile``), bad batch size or fraction, or
            a tile with fewer than 2 valid nodes.
    """

    def __init__(
        self,
        path: str | list[str] = "jacksboro",
        spacing: float | list[float] | None = None,
        origin: list[float] | None = None,
        name: str | None = None,
        batch_size: int = 8192,
        val_fraction: float = 0.02,
        seed: int = 0,
        eval_batch_size: int = 65536,
        refit_epochs: int = 0,
        units: str | None = None,
        nodata: float | list[float] | None = None,
        height_check: str = "refuse",
        offnode_ratio: float = 0.5,
        offnode_val_points: int = 4096,
        min_batches: int = 1,
        offnode_surface: str = "bicubic",
        offnode_voids: str = "skip",
    ) -> None:
        super().__init__()
        tile_given = isinstance(path, DemTile)
        # logger=False: the module and the data module both have a `seed`; Lightning's
        # hparams merge would refuse different values. The fit report logs both, prefixed.
        self.save_hyperparameters(ignore=["path"] if tile_given else None, logger=False)
        if int(batch_size) < 1:
            raise NeuralMapError(f"--data.batch_size must be >= 1, got {batch_size}.")
        if int(eval_batch_size) < 1:
            raise NeuralMapError(f"--data.eval_batch_size must be >= 1, got {eval_batch_size}.")
        if int(min_batches) < 1:
            raise NeuralMapError(
                f"--data.min_batches must be >= 1 (optimisation steps per epoch at least), got "
                f"{min_batches}. Try 16, or 1 to keep --data.batch_size on every tile.")
        self.min_batches = int(min_batches)
        if not (math.isfinite(val_fraction) and 0.0 < val_fraction <= 0.5):
            raise NeuralMapError(
                f"--data.val_fraction must be in (0, 0.5] (fraction of valid nodes held out for "
                f"validation), got {val_fraction}. Try 0.02."
            )
        # A DemTile passed from Python is recorded by its source (or name).
        mosaic = not tile_given and _is_mosaic(path)
        if tile_given:
            self.path = path.source or path.name  # type: ignore[union-attr]
        else:
            self.path = str(path) if isinstance(path, str) else ", ".join(map(str, path))
        self.batch_size = int(batch_size)
        self.val_fraction = float(val_fraction)
        self.seed = int(seed)
        self.eval_batch_size = int(eval_batch_size)
        if int(refit_epochs) < 0:
            raise NeuralMapError(f"--data.refit_epochs must be >= 0, got {refit_epochs}.")
        if not (math.isfinite(offnode_ratio) and offnode_ratio >= 0.0):
            raise NeuralMapError(
                f"--data.offnode_ratio must be a finite number >= 0 (off-node points per node "
                f"point of a batch; 0 = nodes only), got {offnode_ratio}. Try 0.5."
            )
        if int(offnode_val_points) < 1:
            raise NeuralMapError(
                f"--data.offnode_val_points must be >= 1, got {offnode_val_points}."
            )
        self.offnode_ratio = float(offnode_ratio)
        self.offnode_val_points = int(offnode_val_points)
        self.refit_epochs = int(refit_epochs)
        self.refit_epochs_requested = int(refit_epochs)
        self.refit_note: str | None = None
        spacing_arg = spacing_argument(spacing)
        if tile_given:
            self.tile: DemTile = path  # type: ignore[assignment]
        elif mosaic:
            if spacing is not None or origin is not None:
                raise NeuralMapError(
                    f"--data.path {path!r} is a mosaic: each tile's spacing and place come from "
                    "its own georeference, so remove --data.spacing / --data.origin.")
            self.tile = load_mosaic(path, name=name, units=units, nodata=nodata,
                                    height_check=height_check)
        else:
            self.tile = load_tile(
                self.path,
                spacing=spacing_arg,  # type: ignore[arg-type]
                origin=tuple(origin) if origin is not None else None,  # type: ignore[arg-type]
                name=name,
                units=units,
                nodata=nodata,
                height_check=height_check,
            )
        self._split()
        self.offnode = (OffNodeSampler(self.tile, offnode_surface, offnode_voids)
                        if self.offnode_ratio > 0 else None)
        self._offnode_val: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
        self._val_slopes: torch.Tensor | None = None
        self._all_slopes: torch.Tensor | None = None
        rank_zero_info(
            f"tile '{self.tile.name}': {self.tile.shape[0]} x {self.tile.shape[1]} nodes, "
            f"{self.n_void} void node(s) excluded; training on {self.n_train} nodes, "
            f"validating on {self.n_val} held-out nodes"
        )
        meta = self.tile.meta
        if meta.get("units_reason"):
            rank_zero_info(
                f"tile '{self.tile.name}': coordinates in {meta.get('units')}, because "
                f"{meta['units_reason']}"
            )
        if meta.get("implausible_note"):
            rank_zero_info(f"tile '{self.tile.name}': {meta['implausible_note']}")

    @classmethod
    def from_tile(cls, tile: DemTile, **kwargs: Any) -> DemDataModule:
        """Builds the data module around an already loaded tile (no file access).

        Args:
            tile: The DEM tile.
            **kwargs: Other constructor arguments (``batch_size``, ``val_fraction``, ...).
        """
        return cls(tile, **kwargs)  # type: ignore[arg-type]

    # ------------------------------------------------------------------ split
    def _split(self) -> None:
        tile = self.tile
        valid = tile.valid_mask.reshape(-1)
        n_valid = int(valid.sum())
        where = f"tile '{tile.name}' ({self.path})"
        if n_valid < 2:
            raise NeuralMapError(
                f"{where} has only {n_valid} valid node(s); at least 2 are needed to train "
                "and validate. Check the file's no-data value."
            )
        self.node_index = torch.as_tensor(np.flatnonzero(valid), dtype=torch.int64)
        xy = tile.node_xy().reshape(-1, 2)[valid]
        self.xy = torch.as_tensor(xy, dtype=torch.float32)
        self.heights = torch.as_tensor(tile.heights.reshape(-1)[valid], dtype=torch.float32)
        n_val = min(max(1, round(self.val_fraction * n_valid)), n_valid - 1)
        generator = torch.Generator().manual_seed(self.seed)
        order = torch.randperm(n_valid, generator=generator)
        self.val_index = order[:n_val].sort().values
        self.train_index = order[n_val:].sort().values
        self.n_void = tile.n_void

    @property
    def n_valid(self) -> int:
        """Number of valid (non-void) nodes."""
        return int(self.xy.shape[0])

    @property
    def n_train(self) -> int:
        """Number of training nodes."""
        return int(self.train_index.shape[0])

    @property
    def train_batch_size(self) -> int:
        """Points per training step: ``min(batch_size, ceil(n_train / min_batches))``."""
        return max(1, min(self.batch_size, math.ceil(self.n_train / self.min_batches)))

    @property
    def n_val(self) -> int:
        """Number of held-out validation nodes."""
        return int(self.val_index.shape[0])

    @property
    def experiment_name(self) -> str:
        """Default experiment (run folder) name: the tile name, made path-safe."""
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in self.tile.name)
        return safe.strip("._") or Path(self.path).stem or "tile"

    # ------------------------------------------------------------------ reference slopes
    def _reference_slopes(self, xy: torch.Tensor) -> torch.Tensor:
        """Bicubic DEM slopes ``(N, 2)`` float32 at ``xy`` (float64 evaluation, chunked).

        Uses `GridTerrain.height_and_slope`, the closed form of the autograd slope of
        the Keys bicubic interpolant.
        """
        grid = GridTerrain(self.tile, method="bicubic", dtype=torch.float64)
        parts = [
            grid.height_and_slope(chunk.to(torch.float64))[1]
            for chunk in torch.split(xy, self.eval_batch_size)
        ]
        return torch.cat(parts).to(torch.float32)

    @property
    def val_slopes(self) -> torch.Tensor:
        """``(n_val, 2)`` bicubic DEM slopes at the validation nodes (m/m)."""
        if self._val_slopes is None:
            self._val_slopes = self._reference_slopes(self.xy[self.val_index])
        return self._val_slopes

    @property
    def offnode_val(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """Fixed ``(xy (M, 2), h (M,), slope (M, 2))`` float32 off-node validation points
        with the bicubic DEM as target (seeded by ``seed``); None when the tile has no
        valid cell."""
        if self._offnode_val is None:
            try:
                bicubic = (self.offnode is not None and self.offnode.surface == "bicubic"
                           and self.offnode.voids == "skip")
                sampler = self.offnode if bicubic else OffNodeSampler(self.tile)
            except NeuralMapError:
                return None
            generator = torch.Generator().manual_seed(self.seed * _OFFNODE_STREAM + 1)
            self._offnode_val = sampler.sample(self.offnode_val_points, generator)
        return self._offnode_val

    @property
    def all_slopes(self) -> torch.Tensor:
        """``(n_valid, 2)`` bicubic DEM slopes at every valid node (m/m)."""
        if self._all_slopes is None:
            self._all_slopes = self._reference_slopes(self.xy)
        return self._all_slopes

    # ------------------------------------------------------------------ loaders
    def _epoch(self) -> int:
        trainer = self.trainer
        return int(trainer.current_epoch) if trainer is not None else 0

    def _world_size(self) -> int:
        trainer = getattr(self, "trainer", None)
        return int(trainer.world_size) if trainer is not None else 1

    def _chunks(self, *tensors: torch.Tensor) -> Chunks:
        world = self._world_size()
        n_chunks = max(1, math.ceil(tensors[0].shape[0] / self.eval_batch_size))
        n_chunks = math.ceil(n_chunks / world) * world  # same number of chunks on every rank
        return Chunks(*tensors, n_chunks=n_chunks)

    def setup(self, stage: str) -> None:
        """Plans the refit phase against the trainer's run length (before training)."""
        if stage == "fit":
            self.plan_refit()

    def plan_refit(self) -> None:
        """Disables a refit that would leave no held-out epoch, saying so.

        With ``refit_epochs >= max_epochs`` the refit would start at epoch 0: the
        "validation" nodes would be trained on from the first step and no held-out figure
        would exist. Such a refit (and one in a run bounded only by ``max_steps``/time)
        is switched off with a printed warning; ``refit_note`` records it for the metrics.
        """
        self.refit_epochs = self.refit_epochs_requested
        self.refit_note = None
        if self.refit_epochs <= 0:
            return
        trainer = getattr(self, "trainer", None)
        max_epochs = getattr(trainer, "max_epochs", None) if trainer is not None else None
        if max_epochs is None or max_epochs < 0:
            self.refit_note = (
                f"--data.refit_epochs {self.refit_epochs} needs a run length in epochs "
                "(trainer.max_epochs); refit disabled, validation stays held out"
            )
        elif self.refit_epochs >= max_epochs:
            self.refit_note = (
                f"--data.refit_epochs {self.refit_epochs} >= --trainer.max_epochs {max_epochs} "
                "would train on the validation nodes from epoch 0 (no held-out figures); "
                "refit disabled for this run, validation stays held out. Set "
                f"--data.refit_epochs below {max_epochs} to keep a refit"
            )
        else:
            return
        self.refit_epochs = 0
        rank_zero_warn(self.refit_note)

    @property
    def refit_start_epoch(self) -> int | None:
        """First epoch of the refit phase (training on every valid node), or None."""
        trainer = getattr(self, "trainer", None)
        max_epochs = getattr(trainer, "max_epochs", None) if trainer is not None else None
        if self.refit_epochs <= 0 or max_epochs is None or max_epochs < 0:
            return None
        return max(0, int(max_epochs) - self.refit_epochs)

    def in_refit(self, epoch: int) -> bool:
        """Whether ``epoch`` trains on every valid node (held-out ones included)."""
        start = self.refit_start_epoch
        return start is not None and epoch >= start

    def train_dataloader(self) -> DataLoader:
        """Whole shuffled batches ``(xy (B, 2), h (B,))`` of the training nodes (with
        ``offnode_ratio > 0`` also ``(xy_off, h_off, slope_off)`` between the nodes).

        With ``refit_epochs = R > 0`` the last R epochs draw their batches from every valid
        node, the held-out ones included: validation numbers logged before that phase are
        the held-out generalisation error; the exported map has then seen every node
        (train, monitor, then refit on all data).
        """
        dataset = ShuffledBatches(
            self.xy[self.train_index],
            self.heights[self.train_index],
            batch_size=self.train_batch_size,
            seed=self.seed,
            epoch_fn=self._epoch,
            full=(self.xy, self.heights) if self.refit_epochs > 0 else None,
            full_fn=self.in_refit,
            offnode=self.offnode,
            offnode_ratio=self.offnode_ratio,
        )
        return DataLoader(dataset, batch_size=None, shuffle=False, num_workers=0)

    def val_dataloader(self) -> DataLoader:
        """Chunks ``(xy, h, slope_ref)`` of the held-out validation nodes."""
        dataset = self._chunks(
            self.xy[self.val_index], self.heights[self.val_index], self.val_slopes
        )
        return DataLoader(dataset, batch_size=None, shuffle=False, num_workers=0)

    def test_dataloader(self) -> DataLoader:
        """Chunks ``(xy, h, slope_ref)`` of every valid node (the final evaluation set)."""
        dataset = self._chunks(self.xy, self.heights, self.all_slopes)
        return DataLoader(dataset, batch_size=None, shuffle=False, num_workers=0)
