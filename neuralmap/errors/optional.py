"""The optional statsmodels dependency of the error-model toolkit (SciPy is a core
dependency)."""

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

