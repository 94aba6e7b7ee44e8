"""One-call identification of a DEM-related error model (SEEDS 000, section 3, Table 1).

The procedure of the paper, in order: (1) stationarity (run test and ADF), (2)
autocorrelation and partial autocorrelation, (3) ARMA(p, q) by the method of moments for every
order up to ``max_order``, (4) the fit residual of each by the inverse-function method, (5)
the F-test of each order against the next larger one (both orders raised by one, capped at
the maximum: AR(1) against ARMA(2,1), ARMA(1,1) against ARMA(2,2), as in Table 1). The chosen
model is the lowest order (fewest coefficients, then smallest residual) whose F does not
exceed ``F_0.95``; if none passes, the largest fitted order. The Ljung–Box test reports the
whiteness of the sequence and of the chosen model's innovations.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from neuralmap.errors.arma import ArmaModel, order_name
from neuralmap.errors.correlation import autocorrelation, partial_autocorrelation
from neuralmap.errors.f_test import f_quantile, f_statistic
from neuralmap.errors.inverse_function import fit_residual, innovations
from neuralmap.errors.moments import MomentSolutionError, arma_moments, sample_autocovariance
from neuralmap.errors.sequence import as_sequence
from neuralmap.errors.stationarity import StationarityResult, check_stationarity
from neuralmap.errors.whiteness import WhitenessResult, ljung_box
from neuralmap.exceptions import NeuralMapError

#: Table headers (the paper's Table 1 plus the compared order).
TABLE_HEADERS = ("order", "parameters (φ; θ)", "σ_a² (residual)", "vs", "F", "F_0.95", "passes")


@dataclass(frozen=True)
class OrderRow:
    """One order of the identification table.

    Attributes:
        p: AR order.
        q: MA order.
        model: Moment estimate, or None when the moment equations have no stationary,
            invertible solution.
        residual: Inverse-function fit residual (innovation variance), or None.
        reference: Order ``(p₁, q₁)`` the F-test compares against, or None.
        f: F statistic against ``reference``, or None.
        f_critical: ``F_level(s, n − k₁)``, or None.
        passed: True when ``f ≤ f_critical``.
        note: Why a value is missing.
    """

    p: int
    q: int
    model: ArmaModel | None
    residual: float | None
    reference: tuple[int, int] | None
    f: float | None
    f_critical: float | None
    passed: bool
    note: str = ""

    @property
    def name(self) -> str:
        """Display name of the order."""
        return order_name(self.p, self.q)

    @property
    def short_note(self) -> str:
        """Table cell for rows without an F value."""
        if self.model is None:
            return "no moment solution"
        return self.note or "—"

    def cells(self) -> list[str]:
        """Formatted table cells (see ``TABLE_HEADERS``)."""
        if self.model is None:
            params = "—"
        else:
            phi = ", ".join(f"{v:.5f}" for v in self.model.phi)
            theta = ", ".join(f"{v:.5f}" for v in self.model.theta)
            params = "; ".join(part for part in (phi, theta) if part) or "—"
        return [
            self.name,
            params,
            "—" if self.residual is None else f"{self.residual:.5f}",
            "—" if self.reference is None else order_name(*self.reference),
            "—" if self.f is None else f"{self.f:.3f}",
            "—" if self.f_critical is None else f"{self.f_critical:.2f}",
            ("yes" if self.passed else "no") if self.f is not None else self.short_note,
        ]

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable summary."""
        return {
            "order": self.name,
            "p": self.p,
            "q": self.q,
            "model": None if self.model is None else self.model.to_dict(),
            "residual": self.residual,
            "reference": None if self.reference is None else order_name(*self.reference),
            "f": self.f,
            "f_critical": self.f_critical,
            "passed": self.passed,
            "note": self.note,
        }


@dataclass(frozen=True)
class ErrorModelIdentification:
    """Result of `identify_error_model`.

    Attributes:
        n: Sequence length.
        mean: Sample mean.
        std: Sample standard deviation (divide by n).
        rows: The table, one `OrderRow` per order.
        chosen: The selected model.
        chosen_reason: How it was selected.
        acf: ``(nlags + 1,)`` sample autocorrelation.
        pacf: ``(nlags + 1,)`` sample partial autocorrelation.
        stationarity: Stationarity tests (None when skipped).
        whiteness: Ljung–Box on the sequence (None when skipped).
        innovation_whiteness: Ljung–Box on the chosen model's innovations (None when skipped).
        level: Confidence level of the F-test.
    """

    n: int
    mean: float
    std: float
    rows: tuple[OrderRow, ...]
    chosen: ArmaModel
    chosen_reason: str
    acf: np.ndarray
    pacf: np.ndarray
    stationarity: StationarityResult | None
    whiteness: WhitenessResult | None
    innovation_whiteness: WhitenessResult | None
    level: float

    def row(self, p: int, q: int) -> OrderRow:
        """The table row of order ``(p, q)``."""
        for row in self.rows:
            if (row.p, row.q) == (p, q):
                return row
        raise NeuralMapError(f"ErrorModelIdentification.row: order ({p}, {q}) was not fitted.")

    def table(self) -> tuple[tuple[str, ...], list[list[str]]]:
        """``(headers, rows)`` of formatted cells, e.g. for ``StudyOutputs.add_table``."""
        return TABLE_HEADERS, [row.cells() for row in self.rows]

    def to_markdown(self) -> str:
        """Markdown: summary lines and the Table 1 analogue."""
        headers, rows = self.table()
        lines = [
            f"Error sequence: n = {self.n}, mean = {self.mean:.4g}, σ = {self.std:.4f}.",
            "",
        ]
        if self.stationarity is not None:
            st = self.stationarity
            adf = "" if st.adf is None else f", ADF p = {st.adf.p_value:.3g}"
            lines.append(
                f"- Stationary: {'yes' if st.stationary else 'no'} (run test on "
                f"{st.n_segments} segment means p = {st.mean_runs.p_value:.3g}, mean squares "
                f"p = {st.mean_square_runs.p_value:.3g}{adf})."
            )
        if self.whiteness is not None:
            lines.append(
                f"- White: {'yes' if self.whiteness.white else 'no'} (Ljung–Box, "
                f"{self.whiteness.lags} lags, p = {self.whiteness.p_value:.3g})."
            )
        lines.append(
            "- ρ̂_1…ρ̂_5 = " + ", ".join(f"{v:.3f}" for v in self.acf[1:6])
            + "; partial: " + ", ".join(f"{v:.3f}" for v in self.pacf[1:6]) + "."
        )
        lines.append(f"- Chosen: {self.chosen.name} ({self.chosen_reason}).")
        if self.innovation_whiteness is not None:
            iw = self.innovation_whiteness
            lines.append(
                f"- Innovations of the chosen model white: {'yes' if iw.white else 'no'} "
                f"(Ljung–Box p = {iw.p_value:.3g})."
            )
        lines += ["", "| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
        lines += ["| " + " | ".join(cells) + " |" for cells in rows]
        return "\n".join(lines) + "\n"

    def __str__(self) -> str:
        return self.to_markdown()

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable summary (for results.json and logs)."""
        return {
            "n": self.n,
            "mean": self.mean,
            "std": self.std,
            "level": self.level,
            "chosen": self.chosen.to_dict(),
            "chosen_reason": self.chosen_reason,
            "acf": self.acf.tolist(),
            "pacf": self.pacf.tolist(),
            "stationarity": None if self.stationarity is None else self.stationarity.to_dict(),
            "whiteness": None if self.whiteness is None else self.whiteness.to_dict(),
            "innovation_whiteness": (
                None if self.innovation_whiteness is None else self.innovation_whiteness.to_dict()
            ),
            "table": [row.to_dict() for row in self.rows],
        }


def minimum_length(max_ar_order: int, max_ma_order: int) -> int:
    """Shortest sequence `identify_error_model` accepts.

    Ten samples per coefficient of the largest model plus one, and at least 50 (Box and
    Jenkins' rule of thumb; also 20 run-test segments of ≥ 2 samples).
    """
    return max(50, 10 * (max_ar_order + max_ma_order + 1))


def identify_error_model(
    sequence: Any,
    *,
    max_order: int = 2,
    max_ma_order: int | None = None,
    level: float = 0.95,
    include_white: bool = True,
    nlags: int = 20,
    alpha: float = 0.05,
    n_segments: int = 20,
    diagnostics: bool = True,
) -> ErrorModelIdentification:
    """Identifies an ARMA error model for a 1-D error sequence (SEEDS 000, Table 1).

    Args:
        sequence: ``(n,)`` error samples in time / grid order (NumPy array, list or tensor).
        max_order: Largest AR order ``P`` (≥ 1).
        max_ma_order: Largest MA order ``Q`` (default ``max_order``; 0 for AR models only).
        level: Confidence level of the F-test (the paper: 0.95).
        include_white: Also fit order (0, 0), white noise, tested against ARMA(1,1).
        nlags: Lags of the autocorrelation / partial autocorrelation reported.
        alpha: Significance level of the stationarity and whiteness tests.
        n_segments: Segments of the non-parametric run test.
        diagnostics: Run the stationarity and Ljung–Box tests (need statsmodels); the
            table itself needs only NumPy / SciPy.

    Returns:
        The `ErrorModelIdentification` (table, chosen model, tests).
    """
    max_ma = max_order if max_ma_order is None else int(max_ma_order)
    if max_order < 1 or max_ma < 0:
        raise NeuralMapError(
            f"identify_error_model: need max_order ≥ 1 and max_ma_order ≥ 0, got {max_order} "
            f"and {max_ma}."
        )
    if not 0.0 < level < 1.0:
        raise NeuralMapError(f"identify_error_model: level must be in (0, 1), got {level}.")
    need = minimum_length(max_order, max_ma)
    x = as_sequence(
        sequence,
        where="identify_error_model",
        min_length=need,
        why=f"orders up to ARMA({max_order},{max_ma}) (10 samples per coefficient, ≥ 50)",
    )
    n = x.size
    nlags = int(min(nlags, n // 2 - 1))
    gamma = sample_autocovariance(x, max_order + max_ma)
    start = max_order  # common first innovation: every order is scored on the same samples
    n_eff = n - start

    orders = [(p, q) for p in range(max_order + 1) for q in range(max_ma + 1)]
    if not include_white:
        orders.remove((0, 0))
    orders.sort(key=lambda pq: (max(pq), pq[0] + pq[1], -pq[0]))
    fitted: dict[tuple[int, int], tuple[ArmaModel | None, float | None, str]] = {}
    for p, q in orders:
        try:
            model = arma_moments(gamma, p, q)
        except MomentSolutionError as exc:
            fitted[(p, q)] = (None, None, str(exc).split(": ", 1)[-1])
            continue
        residual = fit_residual(x, model, start=start)
        model = ArmaModel(phi=model.phi, theta=model.theta, sigma2=residual)
        fitted[(p, q)] = (model, residual, "")

    rows = []
    for p, q in orders:
        model, residual, note = fitted[(p, q)]
        reference = f_value = f_crit = None
        passed = False
        if model is not None:
            up_p, up_q = min(p + 1, max_order), min(q + 1, max_ma)
            for cand in ((up_p, up_q), (up_p, q), (p, up_q)):
                if cand != (p, q) and cand in fitted and fitted[cand][0] is not None:
                    reference = cand
                    break
            if reference is None:
                note = "largest order"
            else:
                ref_model, ref_residual, _ = fitted[reference]
                assert ref_model is not None and ref_residual is not None
                f_value = f_statistic(
                    residual,
                    ref_residual,
                    n=n_eff,
                    n_params_small=p + q,
                    n_params_large=ref_model.n_params,
                )
                f_crit = f_quantile(ref_model.n_params - p - q, n_eff - ref_model.n_params,
                                    level=level)
                passed = f_value <= f_crit
        rows.append(OrderRow(p, q, model, residual, reference, f_value, f_crit, passed, note))

    passing = [r for r in rows if r.passed]
    if passing:
        best = min(passing, key=lambda r: (r.p + r.q, r.residual))
        reason = f"lowest order with F ≤ F_{level:g}"
    else:
        candidates = [r for r in rows if r.model is not None]
        if not candidates:
            raise NeuralMapError(
                "identify_error_model: no order up to "
                f"ARMA({max_order},{max_ma}) has a moment solution. Check the sequence."
            )
        best = max(candidates, key=lambda r: (r.p + r.q, -(r.residual or 0.0)))
        reason = f"no lower order passed the F-test at {level:g}; largest fitted order"
    assert best.model is not None

    stationarity = whiteness = innovation_whiteness = None
    lb_lags = int(min(10, n // 5))
    if diagnostics:
        stationarity = check_stationarity(x, n_segments=n_segments, alpha=alpha)
        whiteness = ljung_box(x, lags=lb_lags, alpha=alpha)
        if best.model.n_params < lb_lags:
            innovation_whiteness = ljung_box(
                innovations(x, best.model)[start:],
                lags=lb_lags,
                model_df=best.model.n_params,
                alpha=alpha,
            )
        acf_values = autocorrelation(x, nlags=nlags)
        pacf_values = partial_autocorrelation(x, nlags=min(nlags, n // 2 - 1))
    else:
        full = sample_autocovariance(x, nlags)
        acf_values = full / full[0]
        pacf_values = np.full(nlags + 1, np.nan)
        pacf_values[0] = 1.0
    return ErrorModelIdentification(
        n=n,
        mean=float(x.mean()),
        std=float(x.std()),
        rows=tuple(rows),
        chosen=best.model,
        chosen_reason=reason,
        acf=acf_values,
        pacf=pacf_values,
        stationarity=stationarity,
        whiteness=whiteness,
        innovation_whiteness=innovation_whiteness,
        level=level,
    )
