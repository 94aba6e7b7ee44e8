"""Update policies by name: the one list that configs, studies and benchmarks use.

A config names a policy as ``{policy: <name>, policy_args: {<option>: <value>}}``;
`make_policy` merges ``policy_args`` over the entry's defaults and builds a fresh
object (policies keep per-sample state, so every filter gets its own). The defaults are
the papers' tunings (SEEDS 002 for IGG-III / RAF / Sage-Husa, SEEDS 003 for the quality
R and the innovation inflation); "raf" is ``RobustAdaptive(k0=1.5, k1=4.5, c0=1.5,
c1=8.5)`` everywhere.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.policies.compose import Compose
from neuralmap.filters.policies.gate import ChiSquareGate
from neuralmap.filters.policies.huber import Huber
from neuralmap.filters.policies.igg3 import IGG3
from neuralmap.filters.policies.inflation import InnovationInflation
from neuralmap.filters.policies.quality import QualityR
from neuralmap.filters.policies.robust_adaptive import RobustAdaptive
from neuralmap.filters.policies.sage_husa import SageHusa
from neuralmap.filters.policies.variational import VariationalAdaptive
from neuralmap.filters.policies.windowed_inflation import POSITION_VELOCITY, WindowedInflation
from neuralmap.filters.policies.yang import YangAdaptive
from neuralmap.filters.policy import FilterPolicy

__all__ = ["POLICIES", "POLICY_NAMES", "PolicyInfo", "make_policy", "policy_label"]

#: RAF breakpoints of SEEDS 002 (IGG-III k0, k1; adaptive factor c0, c1).
RAF_ARGS: dict[str, float] = {"k0": 1.5, "k1": 4.5, "c0": 1.5, "c1": 8.5}


@dataclass(frozen=True)
class PolicyInfo:
    """One registered policy: report label, builder and the builder's defaults.

    Attributes:
        label: Label in tables and figures.
        build: Called with the merged options (keyword arguments); returns the policy
            (None for the plain filter).
        defaults: Every option the builder takes, with its default value.
    """

    label: str
    build: Callable[..., FilterPolicy | None]
    defaults: dict[str, Any] = field(default_factory=dict)


def _raf(k0: float, k1: float, c0: float, c1: float) -> RobustAdaptive:
    return RobustAdaptive(k0, k1, c0, c1)


def _quality_altimeter(kappa: float, eta: float) -> QualityR:
    return QualityR.altimeter(kappa, eta)


def _quality_gnss(weight: float) -> QualityR:
    return QualityR.gnss(weight, weight, weight, weight)


#: Every policy by name, in the order reports show them.
POLICIES: dict[str, PolicyInfo] = {
    "ekf": PolicyInfo("plain EKF", lambda: None),
    "chi2": PolicyInfo("χ² gate (p = 0.99)", ChiSquareGate,
                       {"p": 0.99, "per_component": False}),
    "huber": PolicyInfo("Huber (k = 1.345)", Huber, {"k": 1.345}),
    "igg3": PolicyInfo("IGG-III (k0 = 1.5, k1 = 4.5)", IGG3, {"k0": 1.5, "k1": 4.5}),
    "yang": PolicyInfo("Yang adaptive factor (c0 = 1, c1 = 3)", YangAdaptive,
                       {"c0": 1.0, "c1": 3.0, "segments": 3}),
    "raf": PolicyInfo("RAF: IGG-III + Yang (c0 = 1.5, c1 = 8.5)", _raf, dict(RAF_ARGS)),
    "inflation": PolicyInfo("innovation inflation (c0 = 1.2)", InnovationInflation,
                            {"c0": 1.2}),
    "windowed_inflation": PolicyInfo(
        "windowed adaptive factor (c0 = 1.2, 10 epochs, position + velocity, cap 10)",
        lambda c0, window, block, cap: WindowedInflation(c0, window=window, block=block,
                                                         cap=cap),
        {"c0": 1.2, "window": 10, "block": list(POSITION_VELOCITY), "cap": 10.0}),
    "quality": PolicyInfo("quality R (altimeter)", _quality_altimeter,
                          {"kappa": 0.5, "eta": 0.2}),
    "quality_gnss": PolicyInfo("quality R (GNSS)", _quality_gnss, {"weight": 0.3}),
    "raf_quality": PolicyInfo(
        "quality R, then RAF",
        lambda kappa, eta, k0, k1, c0, c1: Compose(_quality_altimeter(kappa, eta),
                                                   _raf(k0, k1, c0, c1)),
        {"kappa": 0.5, "eta": 0.2, **RAF_ARGS}),
    "quality_inflation": PolicyInfo(
        "quality R, then innovation inflation (paper 003's tuning)",
        lambda kappa, eta, c0: Compose(_quality_altimeter(kappa, eta), InnovationInflation(c0)),
        {"kappa": 0.5, "eta": 0.2, "c0": 1.2}),
    "quality_gnss_inflation": PolicyInfo(
        "quality R (GNSS), then innovation inflation",
        lambda weight, c0: Compose(_quality_gnss(weight), InnovationInflation(c0)),
        {"weight": 0.3, "c0": 1.2}),
    "quality_gnss_windowed": PolicyInfo(
        "quality R (GNSS), then the windowed adaptive factor",
        lambda weight, c0, window, block, cap: Compose(
            _quality_gnss(weight), WindowedInflation(c0, window=window, block=block, cap=cap)),
        {"weight": 0.3, "c0": 1.2, "window": 10, "block": list(POSITION_VELOCITY),
         "cap": 10.0}),
    "sage_husa": PolicyInfo("Sage-Husa (b = 0.97)", SageHusa,
                            {"b": 0.97, "R_min": 1e-6, "R_max": 1e6, "adapt_Q": False,
                             "diagonal": True}),
    "variational": PolicyInfo("variational Bayes (3 iterations)", VariationalAdaptive,
                              {"iterations": 3, "tau": 3.0, "rho": 1.0 - math.exp(-4.0),
                               "prior_dof": 3.0}),
}

#: Every name `make_policy` accepts.
POLICY_NAMES: tuple[str, ...] = tuple(POLICIES)


def policy_label(name: str) -> str:
    """Report label of a policy name (the name itself when unknown)."""
    info = POLICIES.get(name)
    return info.label if info else name


def make_policy(name: str, policy_args: Mapping[str, Any] | None = None, *,
                where: str = "policy") -> FilterPolicy | None:
    """A fresh policy by registry name, its defaults overridden by ``policy_args``.

    Args:
        name: One of `POLICY_NAMES`.
        policy_args: Options to override (a mapping; keys among the entry's defaults).
        where: What to name in error messages (a config key such as ``"--policies"`` or
            ``"filters[2]"``).

    Returns:
        The policy, or None for ``"ekf"`` (the plain filter).

    Raises:
        NeuralMapError: Unknown name (the message lists the valid ones), ``policy_args``
            not a mapping, an option the policy does not take, or a value it refuses.
    """
    if not isinstance(name, str) or name not in POLICIES:
        raise NeuralMapError(
            f"{where}: unknown policy {name!r}; choose one of {', '.join(POLICY_NAMES)}."
        )
    info = POLICIES[name]
    if policy_args is None:
        policy_args = {}
    if not isinstance(policy_args, Mapping):
        raise NeuralMapError(
            f"{where}: 'policy_args' of {name!r} must be a mapping of option: value (e.g. "
            f"{{{', '.join(f'{k}: {v!r}' for k, v in info.defaults.items()) or ''}}}), got "
            f"{type(policy_args).__name__} {policy_args!r}."
        )
    unknown = sorted(set(policy_args) - set(info.defaults))
    if unknown:
        raise NeuralMapError(
            f"{where}: policy {name!r} has no option(s) {', '.join(map(str, unknown))}; it "
            f"accepts: {', '.join(info.defaults) or 'none'}."
        )
    try:
        return info.build(**{**info.defaults, **policy_args})
    except (TypeError, ValueError) as exc:
        raise NeuralMapError(f"{where}: bad 'policy_args' for {name!r}: {exc}.") from exc
