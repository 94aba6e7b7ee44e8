"""Linearisation methods by name, for configs and the Monte Carlo comparison.

The names (`LINEARIZER_NAMES`) are the ones configs, stamped results and the papers' tables
use, so they keep SEEDS 000's word: the ``_region`` suffix (``neural_region``) names the
window Omega around the estimate that SEEDS 000 calls the region, i.e. the area the
estimate may be in given its position covariance. ``neural_region`` adds the tangent
plane's mean squared miss over that window to the variance (`.region_variance`). In the
code that window is the *window* (`.window`, `WindowPlaneLinearizer`); a *region* elsewhere
in the toolkit is a large area of many tiles.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from torch import nn

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.linearize.autograd import AutogradLinearizer
from neuralmap.linearize.base import Linearizer
from neuralmap.linearize.mean_point import MeanPointLinearizer
from neuralmap.linearize.nine_point import NinePointLinearizer
from neuralmap.linearize.plane_fit import PlaneFitLinearizer
from neuralmap.linearize.taylor import TaylorLinearizer
from neuralmap.linearize.window import SIGMA_MAX_M, SIGMA_MEAN_M, SIGMA_MIN_M
from neuralmap.terrain.grid import GridTerrain


@dataclass(frozen=True)
class MethodInfo:
    """A linearisation method's report label and one-line description."""

    label: str
    description: str


#: Every linearisation method by name: the one list that configs, the factory and the
#: reports use (in the order reports show them).
METHODS: dict[str, MethodInfo] = {
    "neural": MethodInfo(
        "neural map + autograd",
        "autograd on the given terrain model (neural map), variance = the map's error "
        "variance"),
    "neural_region": MethodInfo(
        "neural map + autograd, region variance",
        "autograd on the neural map, variance = the map's error variance + the tangent "
        "plane's mean squared miss over the position uncertainty (Gauss-Hermite)"),
    "bilinear": MethodInfo("bilinear grid (Taylor)",
                           "first-order Taylor on the bilinear DEM grid"),
    "bicubic": MethodInfo("bicubic grid (Taylor)", "autograd on the bicubic DEM grid"),
    "nine_point": MethodInfo("nine-point fit",
                             "least-squares plane through the 3 x 3 nodes around the estimate"),
    "mean_point": MethodInfo("mean-point selection",
                             "plane through half-region mean points, adaptive region"),
    "lsq_max": MethodInfo(f"least squares Ω_max (σ = {SIGMA_MAX_M:g} m)",
                          f"least-squares plane over Omega_max (sigma = {SIGMA_MAX_M:g} m)"),
    "lsq_mean": MethodInfo(f"least squares Ω_mean (σ = {SIGMA_MEAN_M:g} m)",
                           f"least-squares plane over Omega_mean (sigma = {SIGMA_MEAN_M:g} m)"),
    "lsq_min": MethodInfo(f"least squares Ω_min (σ = {SIGMA_MIN_M:g} m)",
                          f"least-squares plane over Omega_min (sigma = {SIGMA_MIN_M:g} m)"),
    "lsq_adaptive": MethodInfo(
        "least squares Ω_adp",
        "least-squares plane over Omega_adp (sigma from the position covariance)"),
}

#: Every name `make_linearizer` accepts.
LINEARIZER_NAMES: tuple[str, ...] = tuple(METHODS)

#: Methods that need a neural (or any given) terrain model rather than the DEM grid.
TERRAIN_MODEL_METHODS: tuple[str, ...] = ("neural", "neural_region")


def method_label(name: str) -> str:
    """Human-readable label of a method name (the name itself when unknown)."""
    info = METHODS.get(name)
    return info.label if info else name


def describe_linearizer(name: str) -> str:
    """One-line description of a linearizer name, for reports."""
    info = METHODS.get(name)
    return info.description if info else name


def _check_kwargs(name: str, target: Callable[..., Any], kw: dict[str, Any], fixed: set[str]) -> None:
    """Raises NeuralMapError for keyword arguments ``target`` does not take."""
    params = inspect.signature(target).parameters
    allowed = sorted(p for p in params if p not in fixed and p != "self" and p != "tile")
    unknown = sorted(set(kw) - set(allowed))
    if unknown:
        raise NeuralMapError(
            f"make_linearizer('{name}'): unknown option(s) {', '.join(unknown)}; "
            f"this method accepts: {', '.join(allowed) or 'none'}."
        )


def make_linearizer(
    name: str,
    *,
    tile: DemTile | None,
    terrain: nn.Module | None = None,
    fit_variance: float = 0.0,
    **kw: Any,
) -> Linearizer:
    """Builds a linearisation method by name.

    Names (`LINEARIZER_NAMES`): ``"neural"`` (AutogradLinearizer on ``terrain``),
    ``"neural_region"`` (the same with the variance over the window Omega, SEEDS 000's
    region: ``region_variance=True``), ``"bilinear"`` (TaylorLinearizer), ``"bicubic"``
    (AutogradLinearizer on a bicubic GridTerrain), ``"nine_point"``, ``"mean_point"``
    (adaptive window), ``"lsq_max"``, ``"lsq_mean"``, ``"lsq_min"`` (PlaneFitLinearizer
    with sigma 400 / 240 / 80 m), ``"lsq_adaptive"`` (sigma from the position covariance).

    Args:
        name: Method name.
        tile: The DEM tile (required for every method but ``"neural"``).
        terrain: The terrain model for ``"neural"``. When it records a
            ``tile_fingerprint`` and ``tile`` is given, the two must match.
        fit_variance: The map's fit-error variance (m^2) returned as the ``"neural"``
            method's variance (SEEDS 004: 6 m^2). The grid methods read the DEM itself and
            ignore it.
        **kw: Options of the underlying class, e.g. ``dtype``, ``create_graph``,
            ``n_samples``, ``max_sigma``, ``variance`` (Taylor).

    Returns:
        The `Linearizer`.

    Raises:
        NeuralMapError: Unknown name (the message lists the valid ones), a missing tile or
            terrain, a map fitted to another tile, or an option the method does not take.
    """
    if name not in LINEARIZER_NAMES:
        raise NeuralMapError(
            f"make_linearizer: unknown linearisation method {name!r}; choose one of "
            f"{', '.join(LINEARIZER_NAMES)}."
        )
    if name in ("neural", "neural_region"):
        if terrain is None:
            raise NeuralMapError(
                f"make_linearizer('{name}'): pass terrain=<the neural map> (load it with "
                "neuralmap.terrain.load_map(path))."
            )
        fingerprint = getattr(terrain, "tile_fingerprint", "")
        if tile is not None and fingerprint and fingerprint != tile.fingerprint():
            raise NeuralMapError(
                f"make_linearizer('{name}'): the map was fitted to tile "
                f"'{getattr(terrain, 'tile_name', '?')}' (fingerprint {fingerprint}), not to "
                f"tile '{tile.name}' (fingerprint {tile.fingerprint()}). Fit a map to this "
                "tile with `python train.py --data.path ...` or pick the matching tile."
            )
        _check_kwargs(name, AutogradLinearizer, kw, {"terrain", "fit_variance"})
        if name == "neural_region":
            kw.setdefault("region_variance", True)
        return AutogradLinearizer(terrain, fit_variance=fit_variance, **kw)
    if not isinstance(tile, DemTile):
        raise NeuralMapError(
            f"make_linearizer('{name}'): tile must be a DemTile (load one with "
            f"neuralmap.dem.load_tile), got {type(tile).__name__}."
        )
    if name == "bicubic":
        grid_kw = {k: kw.pop(k) for k in ("dtype",) if k in kw}
        _check_kwargs(name, AutogradLinearizer, kw, {"terrain", "fit_variance"})
        return AutogradLinearizer(GridTerrain(tile, method="bicubic", **grid_kw), **kw)
    if name == "bilinear":
        _check_kwargs(name, TaylorLinearizer, kw, set())
        return TaylorLinearizer(tile, **kw)
    if name == "nine_point":
        _check_kwargs(name, NinePointLinearizer, kw, set())
        return NinePointLinearizer(tile, **kw)
    if name == "mean_point":
        _check_kwargs(name, MeanPointLinearizer, kw, set())
        return MeanPointLinearizer(tile, **kw)
    sigma: float | str = {
        "lsq_max": SIGMA_MAX_M,
        "lsq_mean": SIGMA_MEAN_M,
        "lsq_min": SIGMA_MIN_M,
        "lsq_adaptive": "adaptive",
    }[name]
    fixed = {"sigma"} | ({"min_sigma", "max_sigma"} if sigma != "adaptive" else set())
    _check_kwargs(name, PlaneFitLinearizer, kw, fixed)
    return PlaneFitLinearizer(tile, sigma=sigma, **kw)
