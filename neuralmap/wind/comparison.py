"""Wind filters compared on common draws: filter specifications and their runs.

A :class:`WindFilterSpec` names one estimator: the wind model (``"tvar"``, the paper's
time-varying AR model with differenced measurements and the correlated-noise EKF, or
``"lti"``, the first-order Markov model on raw measurements) and an optional
robust/adaptive policy from :mod:`neuralmap.filters.policies`, looked up by class name
(``"SageHusa"``, ``"RobustAdaptive"``, ``"VariationalAdaptive"``) and built with
``policy_args``. :func:`run_filters` runs every spec on the same measurements.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters import FilterPolicy
from neuralmap.wind.filtering import WindEstimate, estimate_wind
from neuralmap.wind.lti_model import LTIWindModel
from neuralmap.wind.tvar_model import TVARWindModel

__all__ = ["WindFilterSpec", "make_policy", "run_filters"]

_MODELS = ("tvar", "lti")
_POLICY_MODULE = "neuralmap.filters.policies"


@dataclass
class WindFilterSpec:
    """One estimator of the comparison.

    Attributes:
        name: Label in tables and plots ("KF", "Sage-Husa", "RAF", "VB", "LTI").
        model: ``"tvar"`` or ``"lti"``.
        policy: Class name of a policy in :mod:`neuralmap.filters.policies`; None = the
            classic Kalman filter.
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
    """Builds the policy of ``spec`` (None for the classic Kalman filter).

    Raises:
        NeuralMapError: The policy module or class is missing, or its arguments are bad.
    """
    if spec.policy is None:
        return None
    try:
        module = importlib.import_module(_POLICY_MODULE)
    except ImportError as exc:
        raise NeuralMapError(
            f"WindFilterSpec '{spec.name}': policy {spec.policy!r} needs "
            f"{_POLICY_MODULE}, which this installation lacks; drop the policy or update "
            "the toolkit."
        ) from exc
    cls = getattr(module, spec.policy, None)
    if cls is None or not (isinstance(cls, type) and issubclass(cls, FilterPolicy)):
        names = sorted(n for n, v in vars(module).items()
                       if isinstance(v, type) and issubclass(v, FilterPolicy)
                       and v is not FilterPolicy)
        raise NeuralMapError(
            f"WindFilterSpec '{spec.name}': no policy {spec.policy!r} in {_POLICY_MODULE}; "
            f"available: {names}."
        )
    try:
        return cls(**spec.policy_args)
    except TypeError as exc:
        raise NeuralMapError(
            f"WindFilterSpec '{spec.name}': bad 'policy_args' for {spec.policy}: {exc}."
        ) from exc


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
