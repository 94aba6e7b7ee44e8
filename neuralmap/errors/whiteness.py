"""Whiteness of an error sequence: the Ljung–Box portmanteau test (statsmodels)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from neuralmap.errors.optional import require_statsmodels
from neuralmap.errors.sequence import as_sequence
from neuralmap.exceptions import NeuralMapError


@dataclass(frozen=True)
class WhitenessResult:
    """Ljung–Box verdict.

    Attributes:
        statistic: ``Q = n (n + 2) Σ_{k≤lags} ρ̂_k² / (n − k)``.
        p_value: ``P(χ²_{lags − model_df} > Q)``.
        lags: Number of autocorrelations summed.
        model_df: Degrees of freedom removed for fitted ARMA coefficients.
        white: True when ``p_value ≥ alpha`` (whiteness not rejected).
        alpha: Significance level.
    """

    statistic: float
    p_value: float
    lags: int
    model_df: int
    white: bool
    alpha: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable summary."""
        return dict(self.__dict__)


def ljung_box(
    sequence: Any, *, lags: int = 10, model_df: int = 0, alpha: float = 0.05
) -> WhitenessResult:
    """Ljung–Box whiteness test (``statsmodels.stats.diagnostic.acorr_ljungbox``).

    Args:
        sequence: ``(n,)`` samples (an error sequence or a model's innovations).
        lags: Number of autocorrelation lags tested (``> model_df``).
        model_df: ARMA coefficients fitted to produce ``sequence`` (``p + q`` for
            innovations), subtracted from the χ² degrees of freedom.
        alpha: Significance level.

    Returns:
        The `WhitenessResult`.
    """
    if lags <= model_df:
        raise NeuralMapError(
            f"ljung_box: lags ({lags}) must exceed model_df ({model_df}); raise lags."
        )
    x = as_sequence(sequence, where="ljung_box", min_length=lags + 2, why=f"{lags} lags")
    require_statsmodels("ljung_box")
    from statsmodels.stats.diagnostic import acorr_ljungbox

    table = acorr_ljungbox(x, lags=[lags], model_df=model_df)
    statistic = float(table["lb_stat"].iloc[-1])
    p_value = float(table["lb_pvalue"].iloc[-1])
    return WhitenessResult(statistic, p_value, lags, model_df, bool(p_value >= alpha), alpha)
