"""The navigation-method registry: the built-in methods and their acquisition rules, EKF
linearisation names as aliases of ``ekf``, and the refusals of `register_method` (each
checked against the message it names)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.linearize.factory import LINEARIZER_NAMES
from neuralmap.tan.method import Innovation, NavigationMethod
from neuralmap.tan.methods import (
    EkfBank,
    EkfMethod,
    PointMassEkf,
    PointMassGrid,
    PointMassTrackerMethod,
)
from neuralmap.tan.registry import (
    all_method_names,
    method_class,
    method_names,
    register_method,
    resolve_method,
    unregister_method,
)

BUILTIN = {"ekf": (EkfMethod, "never"), "point_mass_ekf": (PointMassEkf, "always"),
           "ekf_bank": (EkfBank, "never"), "point_mass": (PointMassGrid, "never"),
           "point_mass_tracker": (PointMassTrackerMethod, "wide")}


def test_builtin_methods_and_their_acquisition_rules() -> None:
    assert set(BUILTIN) <= set(method_names())
    for name, (cls, rule) in BUILTIN.items():
        assert method_class(name) is cls and cls.name == name and cls.acquisition == rule
        assert dataclasses.is_dataclass(cls.Options)
        assert resolve_method(name) == (name, {})
    assert all_method_names() == method_names() + tuple(LINEARIZER_NAMES)


@pytest.mark.parametrize("lin", ["bilinear", "neural", "nine_point"])
def test_a_linearisation_name_is_the_ekf_with_it(lin: str) -> None:
    assert resolve_method(lin) == ("ekf", {"linearizer": lin})
    assert method_class(lin) is EkfMethod


def test_unknown_names_list_the_valid_ones() -> None:
    with pytest.raises(NeuralMapError, match=r"here: unknown navigation method 'kalman'; "
                                             r"valid: .*point_mass_tracker.*bilinear"):
        resolve_method("kalman", where="here")
    with pytest.raises(NeuralMapError, match="unknown navigation method"):
        method_class("kalman")


@dataclasses.dataclass
class _Opts:
    x: float = 1.0


class _Good(NavigationMethod):
    Options = _Opts

    def predict(self, dt: float) -> None:
        pass

    def update(self, ins: torch.Tensor, clearance: torch.Tensor, mask: torch.Tensor, *,
               gate: float = math.inf, quality: Any = None) -> Innovation:  # noqa: ANN401
        return Innovation.none(self.context.n_vehicles, self.context.device)

    def estimate(self) -> tuple[torch.Tensor, torch.Tensor]:
        raise NotImplementedError

    def load(self, mask: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> None:
        pass


def test_register_method_refusals() -> None:
    class Abstract(NavigationMethod):
        Options = _Opts

    class NoOptions(_Good):
        Options = dict  # not a dataclass

    class BadRule(_Good):
        acquisition = "sometimes"

    cases = ((object, "is not a NavigationMethod subclass"),
             (Abstract, "does not implement estimate, load, predict, update"),
             (NoOptions, "Options must be a dataclass"),
             (BadRule, "acquisition must be one of never, wide, always"),
             (_Good, "the name 'ekf' is taken by EkfMethod"))
    for cls, match in cases:
        name = "ekf" if cls is _Good else "test_refused"
        with pytest.raises(NeuralMapError, match=match):
            register_method(name)(cls)  # type: ignore[arg-type]
    assert "test_refused" not in method_names()
    assert method_class("ekf") is EkfMethod  # untouched


def test_register_and_unregister() -> None:
    try:
        assert register_method("test_good")(_Good) is _Good
        assert register_method("test_good")(_Good) is _Good  # the same class again: fine
        assert _Good.name == "test_good" and method_names()[-1] == "test_good"
        assert resolve_method("test_good") == ("test_good", {})
    finally:
        unregister_method("test_good")
    assert "test_good" not in method_names()
    unregister_method("test_good")  # unknown: a no-op
