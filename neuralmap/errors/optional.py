"""The optional SciPy / statsmodels dependencies of the error-model toolkit."""

from __future__ import annotations

from types import ModuleType

from neuralmap.exceptions import NeuralMapError

#: The ``pyproject.toml`` extra that installs statsmodels.
STATSMODELS_EXTRA = "errors"


def require_statsmodels(what: str) -> ModuleType:
    """Imports statsmodels or raises NeuralMapError naming the extra that installs it.

    Args:
        what: The function that needs statsmodels (for the message).

    Returns:
        The ``statsmodels`` module.
    """
    try:
        import statsmodels
    except ImportError as exc:
        raise NeuralMapError(
            f"{what} needs statsmodels (>= 0.14), which is not installed. Install the optional "
            f"extra: pip install 'neuralmap[{STATSMODELS_EXTRA}]'."
        ) from exc
    return statsmodels


def require_scipy(what: str) -> ModuleType:
    """Imports SciPy or raises NeuralMapError naming the extra that installs it.

    Args:
        what: The function that needs SciPy (for the message).

    Returns:
        The ``scipy`` module.
    """
    try:
        import scipy
    except ImportError as exc:
        raise NeuralMapError(
            f"{what} needs SciPy, which is not installed. Install the optional extra: "
            f"pip install 'neuralmap[{STATSMODELS_EXTRA}]'."
        ) from exc
    return scipy
