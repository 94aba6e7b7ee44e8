"""Stationarity tests of an error sequence (SEEDS 000, identification step 1).

* Non-parametric (the run test of Bendat & Piersol): cut the sequence into equal segments,
  compute each segment's mean and mean square, and apply the runs test about the median
  to both lists. A stationary sequence gives segment statistics that scatter randomly; a
  trend in level or in variance (the paper's adaptive-region linearisation error, whose
  variance shrinks) gives too few runs.
* Parametric: the augmented Dickey–Fuller unit-root test (statsmodels ``adfuller``);
  stationarity is accepted when the unit root is rejected.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from neuralmap.errors.optional import require_statsmodels
from neuralmap.errors.runs import RunsResult, runs_test
from neuralmap.errors.sequence import as_sequence
from neuralmap.exceptions import NeuralMapError


@dataclass(frozen=True)
class AdfResult:
    """Augmented Dickey–Fuller verdict.

    Attributes:
        statistic: ADF t-statistic.
        p_value: MacKinnon p-value of the unit-root null.
        used_lags: Lagged differences in the regression (chosen by AIC).
        stationary: True when ``p_value < alpha`` (unit root rejected).
        alpha: Significance level.
    """

    statistic: float
    p_value: float
    used_lags: int
    stationary: bool
    alpha: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable summary."""
        return dict(self.__dict__)


@dataclass(frozen=True)
class StationarityResult:
    """Both stationarity tests.

    Attributes:
        mean_runs: Runs test on the segment means.
        mean_square_runs: Runs test on the segment mean squares.
        adf: Augmented Dickey–Fuller test (None when not run).
        n_segments: Number of segments of the run test.
        stationary: True when every test that ran accepts stationarity.
    """

    mean_runs: RunsResult
    mean_square_runs: RunsResult
    adf: AdfResult | None
    n_segments: int
    stationary: bool = field(init=False)

    def __post_init__(self) -> None:
        ok = self.mean_runs.random and self.mean_square_runs.random
        if self.adf is not None:
            ok = ok and self.adf.stationary
        object.__setattr__(self, "stationary", bool(ok))

    @property
    def run_test_stationary(self) -> bool:
        """Verdict of the non-parametric run test alone."""
        return self.mean_runs.random and self.mean_square_runs.random

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable summary."""
        return {
            "stationary": self.stationary,
            "n_segments": self.n_segments,
            "mean_runs": self.mean_runs.to_dict(),
            "mean_square_runs": self.mean_square_runs.to_dict(),
            "adf": None if self.adf is None else self.adf.to_dict(),
        }


def segment_statistics(sequence: Any, *, n_segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Means and mean squares of ``n_segments`` equal consecutive segments.

    The sequence is demeaned first; a remainder of ``n mod n_segments`` samples at the end is
    dropped.

    Returns:
        ``(means, mean_squares)``, each ``(n_segments,)``.
    """
    x = as_sequence(
        sequence, where="segment_statistics", min_length=2 * n_segments, why="the segments"
    )
    length = x.size // n_segments
    seg = (x - x.mean())[: length * n_segments].reshape(n_segments, length)
    return seg.mean(axis=1), (seg**2).mean(axis=1)


def run_stationarity_test(
    sequence: Any, *, n_segments: int = 20, alpha: float = 0.05
) -> tuple[RunsResult, RunsResult]:
    """Non-parametric run test of stationarity on segment means and mean squares.

    Args:
        sequence: ``(n,)`` samples, ``n ≥ 2 n_segments``; segments should be long compared
            with the correlation time.
        n_segments: Number of segments (≥ 10; 20 is usual).
        alpha: Significance level of each runs test.

    Returns:
        ``(runs test on the means, runs test on the mean squares)``.
    """
    if n_segments < 10:
        raise NeuralMapError(
            f"run_stationarity_test: n_segments must be ≥ 10 for the runs test's normal "
            f"approximation, got {n_segments}."
        )
    means, squares = segment_statistics(sequence, n_segments=n_segments)
    where = "run_stationarity_test"
    return (
        runs_test(means, alpha=alpha, where=f"{where} (segment means)"),
        runs_test(squares, alpha=alpha, where=f"{where} (segment mean squares)"),
    )


def adf_test(sequence: Any, *, alpha: float = 0.05) -> AdfResult:
    """Augmented Dickey–Fuller test (``statsmodels.tsa.stattools.adfuller``, constant, AIC).

    Args:
        sequence: ``(n,)`` samples (n ≥ 20).
        alpha: Significance level.

    Returns:
        The `AdfResult`.
    """
    x = as_sequence(sequence, where="adf_test", min_length=20, why="the ADF regression")
    require_statsmodels("adf_test")
    from statsmodels.tsa.stattools import adfuller

    with warnings.catch_warnings():  # statsmodels ≥ 0.15 announces a new return type
        warnings.simplefilter("ignore", FutureWarning)
        statistic, p_value, used_lags, *_ = adfuller(x, regression="c", autolag="AIC")
    return AdfResult(
        float(statistic), float(p_value), int(used_lags), bool(p_value < alpha), alpha
    )


def check_stationarity(
    sequence: Any, *, n_segments: int = 20, alpha: float = 0.05, parametric: bool = True
) -> StationarityResult:
    """Runs the non-parametric run test and (optionally) the parametric ADF test.

    Args:
        sequence: ``(n,)`` samples.
        n_segments: Segments of the run test.
        alpha: Significance level of every test.
        parametric: Also run the ADF test (needs statsmodels).

    Returns:
        The `StationarityResult`.
    """
    mean_runs, square_runs = run_stationarity_test(sequence, n_segments=n_segments, alpha=alpha)
    adf = adf_test(sequence, alpha=alpha) if parametric else None
    return StationarityResult(mean_runs, square_runs, adf, n_segments)
