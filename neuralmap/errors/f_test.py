"""Order selection by the F-test (SEEDS 000, identification step 5).

A model with ``k₀`` coefficients and fit residual ``Q₀`` is compared with a larger model
(``k₁ = k₀ + s`` coefficients, residual ``Q₁``) fitted to the same ``n`` samples:

    F = ((Q₀ − Q₁) / s) / (Q₁ / (n − k₁)),

which is ``F(s, n − k₁)``-distributed when the extra coefficients are not needed. The
smaller model passes when ``F ≤ F_0.95(s, n − k₁)``. The paper's Table 1 follows this with
residual variances and large-n quantiles (3.00 for s = 2, 3.84 for s = 1); its F of −29.3 for
AR(1) is this statistic against ARMA(2,1) (n = 610). F is negative when the larger model
fits worse, which the method of moments allows.
"""

from __future__ import annotations

from neuralmap.exceptions import NeuralMapError


def f_statistic(
    residual_small: float,
    residual_large: float,
    *,
    n: int,
    n_params_small: int,
    n_params_large: int,
) -> float:
    """The F statistic of the larger model's extra coefficients.

    Args:
        residual_small: Fit residual (variance or sum of squares) of the smaller model.
        residual_large: The same for the larger model (same samples, same normalisation).
        n: Number of samples.
        n_params_small: Coefficients of the smaller model ``k₀``.
        n_params_large: Coefficients of the larger model ``k₁ > k₀``, ``k₁ < n``.

    Returns:
        ``F``.
    """
    s = n_params_large - n_params_small
    if s < 1 or n_params_large >= n:
        raise NeuralMapError(
            f"f_statistic: need n_params_small < n_params_large < n, got {n_params_small}, "
            f"{n_params_large}, n={n}."
        )
    if not residual_large > 0.0:
        raise NeuralMapError(
            f"f_statistic: the larger model's residual must be > 0, got {residual_large!r}."
        )
    return float(((residual_small - residual_large) / s) / (residual_large / (n - n_params_large)))


def f_quantile(s: int, dof: int, *, level: float = 0.95) -> float:
    """Quantile ``F_level(s, dof)`` (``scipy.stats.f.ppf``)."""
    if s < 1 or dof < 1 or not 0.0 < level < 1.0:
        raise NeuralMapError(
            f"f_quantile: need s ≥ 1, dof ≥ 1 and 0 < level < 1, got {s}, {dof}, {level}."
        )
    from scipy.stats import f as f_distribution

    return float(f_distribution.ppf(level, s, dof))
