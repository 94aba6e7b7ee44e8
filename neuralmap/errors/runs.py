"""The Wald–Wolfowitz runs test about the median (non-parametric randomness test)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from neuralmap.errors.sequence import as_sequence
from neuralmap.exceptions import NeuralMapError


@dataclass(frozen=True)
class RunsResult:
    """Runs-test verdict.

    Attributes:
        runs: Observed number of runs ``R`` of values above / below the median.
        expected: ``E[R] = 2 n₁ n₂ / n + 1`` under randomness.
        z: ``(R − E[R]) / √Var[R]`` (normal approximation, no continuity correction).
        p_value: Two-sided p-value.
        n_above: ``n₁``, values above the median.
        n_below: ``n₂``, values below it (values equal to the median are dropped).
        random: True when ``p_value ≥ alpha`` (randomness not rejected).
        alpha: Significance level.
    """

    runs: int
    expected: float
    z: float
    p_value: float
    n_above: int
    n_below: int
    random: bool
    alpha: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable summary."""
        return dict(self.__dict__)


def runs_test(values: Any, *, alpha: float = 0.05, where: str = "runs_test") -> RunsResult:
    """Wald–Wolfowitz runs test of randomness about the median.

    ``Var[R] = 2 n₁ n₂ (2 n₁ n₂ − n) / (n² (n − 1))``, ``n = n₁ + n₂``. Too few runs means
    positive correlation (or a trend), too many means alternation. The normal approximation
    needs about 10 values on each side of the median.

    Args:
        values: ``(n,)`` values in order.
        alpha: Significance level.
        where: Caller, for messages.

    Returns:
        The `RunsResult`.
    """
    from scipy.stats import norm

    x = as_sequence(values, where=where, min_length=4, why="a runs test")
    signs = x[x != np.median(x)] > np.median(x)
    n1 = int(signs.sum())
    n2 = int(signs.size - n1)
    if n1 < 2 or n2 < 2:
        raise NeuralMapError(
            f"{where}: the runs test needs at least 2 values above and 2 below the median, "
            f"got {n1} above and {n2} below. Pass more (or less tied) values."
        )
    n = n1 + n2
    runs = int(1 + np.count_nonzero(signs[1:] != signs[:-1]))
    expected = 2.0 * n1 * n2 / n + 1.0
    variance = 2.0 * n1 * n2 * (2.0 * n1 * n2 - n) / (n * n * (n - 1.0))
    z = (runs - expected) / math.sqrt(variance)
    p_value = float(2.0 * norm.sf(abs(z)))
    return RunsResult(runs, expected, float(z), p_value, n1, n2, bool(p_value >= alpha), alpha)
