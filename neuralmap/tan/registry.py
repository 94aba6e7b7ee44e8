"""The registry of navigation methods: the one place a method's name is spelled.

Every `NavigationMethod` registers under its name with `register_method`; the `Navigator`,
its config (one options section per registered name), ``neuralmap-navigate`` and the
studies look methods up here. The built-in methods (`neuralmap.tan.methods`) register when
the package is imported. Besides the registered names, every EKF linearisation name of
`neuralmap.linearize.factory.LINEARIZER_NAMES` (``bilinear``, ``neural``, ...) names the
EKF with that linearisation (`resolve_method`).

Adding a method::

    @register_method("my_method")
    class MyMethod(NavigationMethod):
        Options = MyOptions
        ...
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from neuralmap.exceptions import NeuralMapError
from neuralmap.tan.method import ACQUISITION_RULES, NavigationMethod

__all__ = ["all_method_names", "method_class", "method_names", "register_method",
           "resolve_method", "unregister_method"]

_METHODS: dict[str, type[NavigationMethod]] = {}

#: The registered method an EKF linearisation name stands for, and its option.
_LINEARIZER_METHOD, _LINEARIZER_OPTION = "ekf", "linearizer"


def register_method(name: str) -> Callable[[type[NavigationMethod]], type[NavigationMethod]]:
    """Class decorator: registers a `NavigationMethod` subclass under ``name``.

    Raises:
        NeuralMapError: A name already taken, or a class that is not a complete
            `NavigationMethod` with a dataclass ``Options`` and a known ``acquisition``.
    """

    def add(cls: type[NavigationMethod]) -> type[NavigationMethod]:
        import dataclasses

        if not (isinstance(cls, type) and issubclass(cls, NavigationMethod)):
            raise NeuralMapError(f"register_method({name!r}): {cls!r} is not a "
                                 "NavigationMethod subclass.")
        if getattr(cls, "__abstractmethods__", None):
            raise NeuralMapError(f"register_method({name!r}): {cls.__name__} does not implement "
                                 f"{', '.join(sorted(cls.__abstractmethods__))}.")
        if not dataclasses.is_dataclass(cls.Options):
            raise NeuralMapError(f"register_method({name!r}): {cls.__name__}.Options must be a "
                                 "dataclass of the method's options.")
        if cls.acquisition not in ACQUISITION_RULES:
            raise NeuralMapError(f"register_method({name!r}): {cls.__name__}.acquisition must "
                                 f"be one of {', '.join(ACQUISITION_RULES)}.")
        if name in _METHODS and _METHODS[name] is not cls:
            raise NeuralMapError(f"register_method: the name {name!r} is taken by "
                                 f"{_METHODS[name].__name__}.")
        cls.name = name
        _METHODS[name] = cls
        return cls

    return add


def unregister_method(name: str) -> None:
    """Removes the method registered under ``name`` (a no-op for an unknown name)."""
    _METHODS.pop(name, None)


def _builtin() -> dict[str, type[NavigationMethod]]:
    """The registry (the built-in methods registered themselves when `neuralmap.tan`, the
    package around this module, imported `neuralmap.tan.methods`)."""
    return _METHODS


def method_names() -> tuple[str, ...]:
    """The registered method names, in registration order."""
    return tuple(_builtin())


def _linearizer_names() -> tuple[str, ...]:
    from neuralmap.linearize.factory import LINEARIZER_NAMES

    return tuple(LINEARIZER_NAMES)


def resolve_method(name: str, *, where: str = "method") -> tuple[str, dict[str, Any]]:
    """A method name as given by a user: ``(registered name, option overrides)``.

    A registered name resolves to itself; an EKF linearisation name to the EKF with that
    linearisation (``("ekf", {"linearizer": name})``).

    Raises:
        NeuralMapError: An unknown name (lists the valid ones).
    """
    methods = _builtin()
    if name in methods:
        return name, {}
    if isinstance(name, str) and name in _linearizer_names():
        return _LINEARIZER_METHOD, {_LINEARIZER_OPTION: name}
    raise NeuralMapError(f"{where}: unknown navigation method {name!r}; valid: "
                         f"{', '.join(method_names() + _linearizer_names())}.")


def method_class(name: str) -> type[NavigationMethod]:
    """The class registered under ``name`` (or the EKF for a linearisation name)."""
    return _builtin()[resolve_method(name)[0]]


def all_method_names() -> tuple[str, ...]:
    """Every name a user may give: the registered methods and the EKF linearisations."""
    return method_names() + _linearizer_names()
