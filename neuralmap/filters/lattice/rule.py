"""Lattice rules of the point-mass filter: how the lattice moves, by registry name.

Every rule is an object held by the one `neuralmap.filters.lattice.filter.LatticeFilter`
(one state, one measurement update, one set of kernels) as its ``rule`` attribute; what
differs is how the lattice moves (a *lattice rule*; "policy" in this package names a
filter's update policy, `neuralmap.filters.policy`):

* ``fixed`` — a regular axis-aligned grid sized once from the prior (acquisition of a wide
  prior: every mode stays on the grid); deferred diffusion, scalar Rao-Blackwellised part
  (`neuralmap.filters.lattice.grid_rule.GridLattice`; the configuration
  `neuralmap.filters.point_mass.PointMassFilter` with ``adaptive=False``);
* ``adaptive`` — the same grid, re-centred and re-sized as the posterior moves and
  shrinks (``adaptive=True``);
* ``follow`` — an affine lattice that follows the posterior (principal axes, moment-exact
  prediction and regrid, an ``nz``-D Kalman part per cell, lost-track test and open-loop
  re-acquisition; `neuralmap.filters.lattice.follow_rule.FollowLattice`, the
  configuration `neuralmap.filters.point_mass_tracker.PointMassTracker`).

``make_lattice_filter(name, mean, cov, ...)`` builds one from a Gaussian prior over
``[s, z]`` (``s``: the 2-D lattice state, ``z``: the conditionally linear part; the grid
rules hold ``nz = 1`` with ``E = 0``, ``F = 1``, ``c = 1``: the altitude error).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError

__all__ = ["LATTICE_RULES", "LatticeRule", "make_lattice_filter"]


@dataclass(frozen=True)
class LatticeRule:
    """A registered lattice rule.

    Attributes:
        name: Registry name.
        description: One line for listings and errors.
        build: ``(mean (N, 2+nz), cov (N, 2+nz, 2+nz), dtype, options) -> filter``.
    """

    name: str
    description: str
    build: Callable[..., Any]


def _grid(adaptive: bool) -> Callable[..., Any]:
    def build(mean: torch.Tensor, cov: torch.Tensor, dtype: torch.dtype,
              options: dict[str, Any], model: dict[str, torch.Tensor] | None) -> Any:
        from neuralmap.filters.point_mass import PointMassConfig, PointMassFilter

        if mean.shape[1] != 3 or model is not None:
            raise NeuralMapError(
                "make_lattice_filter: the fixed and adaptive grids hold one scalar linear "
                f"state (mean (N, 3), no E/F/c model); got mean {tuple(mean.shape)}"
                f"{' and a model' if model is not None else ''}. Use the rule 'follow' for an "
                "nz-D linear part.")
        try:
            config = PointMassConfig(adaptive=adaptive, **options)
        except TypeError as exc:
            raise NeuralMapError(f"make_lattice_filter: {exc} (options of PointMassConfig).") \
                from exc
        return PointMassFilter(mean[:, :2], cov[:, :2, :2], scalar_mean=mean[:, 2],
                               scalar_var=cov[:, 2, 2], config=config, dtype=dtype)
    return build


def _follow(mean: torch.Tensor, cov: torch.Tensor, dtype: torch.dtype,
            options: dict[str, Any], model: dict[str, torch.Tensor] | None) -> Any:
    from neuralmap.filters.point_mass_tracker import PointMassTracker, TrackerConfig

    nz = mean.shape[1] - 2
    model = dict(model or {})
    model.setdefault("E", torch.zeros(2, nz, dtype=dtype))
    model.setdefault("F", torch.eye(nz, dtype=dtype))
    model.setdefault("c", torch.nn.functional.one_hot(torch.tensor(0), nz).to(dtype))
    try:
        config = TrackerConfig(**options)
    except TypeError as exc:
        raise NeuralMapError(f"make_lattice_filter: {exc} (options of TrackerConfig).") from exc
    return PointMassTracker(mean, cov, E=model["E"], F=model["F"], c=model["c"], config=config,
                            dtype=dtype)


LATTICE_RULES: dict[str, LatticeRule] = {
    p.name: p for p in (
        LatticeRule("fixed", "regular grid sized once from the prior (acquisition)",
                      _grid(False)),
        LatticeRule("adaptive", "regular grid re-centred and re-sized as the posterior "
                      "shrinks", _grid(True)),
        LatticeRule("follow", "affine lattice following the posterior, moment-exact "
                      "(tracking)", _follow),
    )
}


def make_lattice_filter(rule: str, mean: torch.Tensor, cov: torch.Tensor, *,
                        dtype: torch.dtype = torch.float64,
                        model: dict[str, torch.Tensor] | None = None, **options: Any) -> Any:
    """A point-mass filter with the lattice rule ``rule`` (module docstring).

    Args:
        rule: ``fixed``, ``adaptive`` or ``follow``.
        mean: ``(N, 2 + nz)`` prior mean ``[s, z]``.
        cov: ``(N, 2+nz, 2+nz)`` or ``(2+nz, 2+nz)`` prior covariance (positive definite;
            the grid rules use its ``s`` block and the variance of ``z``).
        dtype: float32 or float64.
        model: ``follow`` only: ``{"E": (2, nz), "F": (nz, nz), "c": (nz,)}`` (defaults:
            ``E = 0``, ``F = I``, ``c = e₁``).
        **options: The rule's lattice options (`PointMassConfig` for the grids,
            `TrackerConfig` for ``follow``).

    Raises:
        NeuralMapError: An unknown rule (names the registered ones), bad shapes or options.
    """
    if rule not in LATTICE_RULES:
        known = ", ".join(f"{k} ({v.description})" for k, v in LATTICE_RULES.items())
        raise NeuralMapError(f"make_lattice_filter: unknown lattice rule {rule!r}; "
                             f"registered: {known}.")
    mean = torch.as_tensor(mean, dtype=dtype)
    if mean.ndim != 2 or mean.shape[1] < 3:
        raise NeuralMapError(f"make_lattice_filter: mean must have shape (N, 2 + nz) with "
                             f"nz >= 1, got {tuple(mean.shape)}.")
    d = mean.shape[1]
    cov = torch.as_tensor(cov, dtype=dtype)
    if tuple(cov.shape) not in ((d, d), (mean.shape[0], d, d)):
        raise NeuralMapError(f"make_lattice_filter: cov must have shape ({d}, {d}) or "
                             f"({mean.shape[0]}, {d}, {d}), got {tuple(cov.shape)}.")
    cov = cov.expand(mean.shape[0], d, d)
    return LATTICE_RULES[rule].build(mean, cov, dtype, options, model)
