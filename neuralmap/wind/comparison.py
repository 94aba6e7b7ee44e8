"""Wind filters compared on common draws: filter specifications and their runs.

A `WindFilterSpec` names one estimator: the wind model (``"tvar"``, the paper's
time-varying AR model with differenced measurements and the correlated-noise EKF, or
``"lti"``, the first-order Markov model on raw measurements) and an optional
robust/adaptive policy of the registry in `neuralmap.filters.policies`, looked up by
name (``"sage_husa"``, ``"raf"``, ``"variational"``) and built with ``policy_args`` over
the registry's defaults. `run_filters` runs every spec on the same measurements.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.policies.registry import make_policy as registry_make_policy
from neuralmap.filters.policy import FilterPolicy
from neuralmap.wind.filtering import WindEstimate, estimate_wind
from neuralmap.wind.lti_model import LTIWindModel
from neuralmap.wind.tvar_model import TVARWindModel

__all__ = ["WindFilterSpec", "make_policy", "run_filters"]

_MODELS = ("tvar", "lti")


@dataclass
class WindFilterSpec:
    """One estimator of the comparison.

    Attributes:
        name: Label in tables and plots ("KF", "Sage-Husa", "RAF", "VB", "LTI").
        model: ``"tvar"`` or ``"lti"``.
        policy: Registry name of a policy (`neuralmap.filters.policies.POLICIES`);
            None = the classic Kalman filter.
        policy_args: Keyword arguments of the policy.
        correlated: TVAR only: handle the differencing cross-covariance (default).
    """

    name: str
    model: str = "tvar"
    policy: str | None = None
    policy_args: dict[str, Any] = field(default_factory=dict)
    correlated: bool = True

    def validate(self) -> WindFilterSpec:
        """Checks the fields; returns ``self``.

        Raises:
            NeuralMapError: Unknown model, empty name, non-dict ``policy_args``.
        """
        if not self.name:
            raise NeuralMapError("WindFilterSpec: 'name' must be a non-empty label.")
        if self.model not in _MODELS:
            raise NeuralMapError(
                f"WindFilterSpec '{self.name}': 'model' = {self.model!r} is unknown; use one "
                f"of {list(_MODELS)}."
            )
        if not isinstance(self.policy_args, dict):
            raise NeuralMapError(f"WindFilterSpec '{self.name}': 'policy_args' must be a "
                                 "mapping of keyword arguments.")
        return self


def make_policy(spec: WindFilterSpec) -> FilterPolicy | None:
    """Builds the policy of ``spec`` from the policy registry (None for the classic Kalman
    filter).

    Raises:
        NeuralMapError: Unknown policy name, or bad arguments.
    """
    if spec.policy is None:
        return None
    return registry_make_policy(spec.policy, spec.policy_args,
                                where=f"filters '{spec.name}'")


def run_filters(
    z: torch.Tensor,
    specs: list[WindFilterSpec],
    *,
    tvar: TVARWindModel,
    lti: LTIWindModel,
) -> dict[str, WindEstimate]:
    """Runs every filter on the same ``(N, T, 2)`` measurements.

    Args:
        z: Measured wind ``(N, T, 2)``.
        specs: The estimators (names must be unique).
        tvar: Parameters of the TVAR model (shared by the ``"tvar"`` filters).
        lti: Parameters of the LTI model.

    Returns:
        ``{name: WindEstimate}`` in the order of ``specs``.

    Raises:
        NeuralMapError: Duplicate names or a bad spec.
    """
    names = [s.name for s in specs]
    if len(set(names)) != len(names):
        raise NeuralMapError(f"run_filters: filter names must be unique, got {names}.")
    out: dict[str, WindEstimate] = {}
    for spec in specs:
        spec.validate()
        policy = make_policy(spec)
        if spec.model == "tvar":
            out[spec.name] = estimate_wind(z, tvar, policy=policy, correlated=spec.correlated)
        else:
            out[spec.name] = estimate_wind(z, lti, policy=policy)
    return out
