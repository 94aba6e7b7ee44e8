"""Activation functions of the terrain networks, with their derivatives.

The derivatives serve the analytic input gradient of SEEDS 004, eq. (8); autograd gives
the same numbers (tested to 1e-9 in float64).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from neuralmap.exceptions import NeuralMapError


def bipolar_sigmoid(a: torch.Tensor) -> torch.Tensor:
    """SEEDS 004 activation ``f(a) = (1 - e^-a) / (1 + e^-a)``, which equals ``tanh(a / 2)``."""
    return torch.tanh(0.5 * a)


def _bipolar_sigmoid_derivative(a: torch.Tensor) -> torch.Tensor:
    # f' = (1 + f)(1 - f) / 2. The paper prints (1 + f)(1 - f); the exact derivative of
    # tanh(a/2) carries the factor 1/2 (SEEDS 004 note).
    f = torch.tanh(0.5 * a)
    return 0.5 * (1.0 + f) * (1.0 - f)


def _tanh_derivative(a: torch.Tensor) -> torch.Tensor:
    t = torch.tanh(a)
    return 1.0 - t * t


def _silu_derivative(a: torch.Tensor) -> torch.Tensor:
    s = torch.sigmoid(a)
    return s * (1.0 + a * (1.0 - s))


ACTIVATIONS: dict[str, tuple[Callable[[torch.Tensor], torch.Tensor], Callable[[torch.Tensor], torch.Tensor]]] = {
    "sine": (torch.sin, torch.cos),
    "tanh": (torch.tanh, _tanh_derivative),
    "silu": (torch.nn.functional.silu, _silu_derivative),
    "bipolar_sigmoid": (bipolar_sigmoid, _bipolar_sigmoid_derivative),
}


def get_activation(
    name: str,
) -> tuple[Callable[[torch.Tensor], torch.Tensor], Callable[[torch.Tensor], torch.Tensor]]:
    """Returns ``(f, f')`` for an activation name.

    Args:
        name: One of ``sine``, ``tanh``, ``silu``, ``bipolar_sigmoid``.

    Raises:
        NeuralMapError: For an unknown name.
    """
    try:
        return ACTIVATIONS[name]
    except KeyError:
        raise NeuralMapError(
            f"unknown activation '{name}' (model.activation); choose one of "
            f"{', '.join(sorted(ACTIVATIONS))}."
        ) from None
