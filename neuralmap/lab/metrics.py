"""Navigation metrics of a Monte Carlo TAN run: RMSE, 1σ, divergence, NEES, PCRB ratio.

Definitions (the report quotes them; ``e`` is the error of the corrected estimate):

- Horizontal error of run n at step k: ``e_{n,k} = ||p̂_{n,k} − p_{n,k}||`` (m); velocity
  error ``||v̂ − v||`` (m/s).
- Included runs: off-map runs (the truth left the map at some step) are excluded from
  every metric and counted in ``n_off_map``; runs with non-finite errors likewise
  (``n_nonfinite``). A run whose *estimate* left the map stays included and counts as
  diverged (``n_estimate_left_map``).
- RMSE curve: ``sqrt(mean_n e_{n,k}²)`` per step. Time-averaged RMSE: root of the mean of
  ``e²`` over the runs and the **last half** of the samples (indices ``(K+1)//2 … K``).
  Final: the RMSE at the last sample.
- Divergence: `DIVERGENCE_RULE`. Numerical failures (the filter's covariance became
  non-finite or lost positive definiteness: ``n_unhealthy``) are counted apart from
  estimate divergence; a run the filter declared lost (the point-mass tracker's
  ``lost`` flag, `FilterRun.lost`) counts as diverged. "Converged" runs are the included
  runs that neither diverged nor failed numerically.
- ``sigma_pos_m`` (the papers' 1σ): ``sqrt(var(e_x) + var(e_y))`` with the sample variance
  (about the mean, ddof = 1) pooled over the converged runs and the last-half samples;
  ``sigma_vel_mps`` likewise for the velocity.
- NEES (Bar-Shalom): ``ε_{n,k} = errᵀ P⁻¹ err`` on the 5-state error; per step the average
  ``ε̄_k`` over the M converged runs; ``M·ε̄_k ~ χ²(5M)`` for a consistent filter, so
  ``nees_in_band`` is the fraction of the K+1 samples with ``ε̄_k`` inside the two-sided
  95 % band ``[χ²_{0.025}(5M)/M, χ²_{0.975}(5M)/M]``. ``nees_in_band_all`` is the same
  over every included run, diverged ones too (the stricter figure).
- ``pcrb_ratio_all`` (the headline): time-averaged RMSE over **all** included runs divided
  by the time-averaged (RMS over the last half) PCRB position bound;
  ``pcrb_ratio_converged``: the same over the converged runs (labelled; it cannot see
  the diverged runs).
- Time-averaged NEES (Bar-Shalom): ``ε̄ = mean over the M converged runs and the K
  filter steps`` of ``ε_{n,k}``; for a consistent filter ``M·K·ε̄ ~ χ²(n·M·K)`` if the
  steps were independent (``nees_time_band``, Bar-Shalom); since a filter's errors are
  correlated in time, ``nees_time_in_band`` tests ``ε̄`` against the band built from the
  spread of the M independent per-run averages (``nees_time_band_runs``).

Outputs never contain NaN: an empty subset gives ``None`` (and curves of ``None``).
"""

from __future__ import annotations

import math
from statistics import NormalDist
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.stats import chi2_quantile, nees
from neuralmap.lab.monte_carlo import FilterRun

#: Human-readable divergence rule (default factors), written into reports and results.json.
DIVERGENCE_RULE = (
    "A run diverged when its final horizontal position error exceeds {pcrb}x the final PCRB "
    "position bound sqrt(J^-1_xx + J^-1_yy) (the larger of the true-terrain and the "
    "map-aware bound, when both are given: no filter on the DEM reaches below the map-aware "
    "one), or exceeds {sigma}x the filter's own final 1-sigma "
    "horizontal bound sqrt(P_xx + P_yy), or when its estimate left the map, or when the "
    "navigator lost it (a lost lock not re-acquired by the last epoch). A run whose "
    "filter failed numerically (covariance non-finite or not positive definite) is counted "
    "apart as a numerical failure. Neither counts as converged. Runs whose truth left the "
    "map are excluded from every metric and counted as off-map."
)


def divergence_rule(pcrb_factor: float = 5.0, divergence_sigma: float = 9.0) -> str:
    """`DIVERGENCE_RULE` with the given factors.

    Args:
        pcrb_factor: Multiple of the final PCRB position bound.
        divergence_sigma: Multiple of the filter's final 1σ horizontal bound.

    Returns:
        The rule as one sentence group.
    """
    return DIVERGENCE_RULE.format(pcrb=f"{pcrb_factor:g}", sigma=f"{divergence_sigma:g}")


def _nees_in_band(
    err: torch.Tensor, P: torch.Tensor, n_states: int, confidence: float
) -> tuple[float, torch.Tensor, float, float]:
    """Fraction of samples whose run-averaged NEES lies in the two-sided χ² band.

    Returns:
        ``(fraction, eps_bar (K+1,), lo, hi)``.
    """
    m = err.shape[0]
    eps_bar = nees(err, P).mean(dim=0)
    alpha = 1.0 - confidence
    lo = chi2_quantile(0.5 * alpha, n_states * m) / m
    hi = chi2_quantile(1.0 - 0.5 * alpha, n_states * m) / m
    inside = torch.isfinite(eps_bar) & (eps_bar >= lo) & (eps_bar <= hi)
    return float(inside.sum()) / eps_bar.shape[0], eps_bar, lo, hi


def _none_if_bad(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _rms(sq: torch.Tensor) -> float | None:
    """Root of the mean of a tensor of squared errors (None when empty)."""
    return _none_if_bad(math.sqrt(float(sq.mean()))) if sq.numel() else None


def bound_rms_last_half(bound: Any) -> float | None:
    """RMS of a bound curve ``(K+1,)`` over its last half (indices ``(K+1)//2 … K``), finite
    values only: the time-averaged bound the RMSE ratios divide by (None when empty)."""
    tail = torch.as_tensor(bound, dtype=torch.float64)
    tail = tail[tail.shape[0] // 2:]
    return _rms(tail[torch.isfinite(tail)] ** 2)


def _curve(sq: torch.Tensor, n_steps: int) -> list[float | None]:
    """Per-step RMS over runs of ``sq (M, K+1)`` (None entries when M = 0)."""
    if sq.shape[0] == 0:
        return [None] * n_steps
    return [_none_if_bad(v) for v in sq.mean(dim=0).sqrt().tolist()]


def _pooled_sigma(err_xy: torch.Tensor) -> float | None:
    """``sqrt(var(e_x) + var(e_y))`` (ddof = 1) of ``(..., 2)`` errors; None when < 2."""
    flat = err_xy.reshape(-1, 2)
    if flat.shape[0] < 2:
        return None
    return _none_if_bad(math.sqrt(float(flat.var(dim=0, unbiased=True).sum())))


def diverged_runs(
    final_err: torch.Tensor,
    final_sigma: torch.Tensor,
    *,
    included: torch.Tensor,
    healthy: torch.Tensor,
    est_left: torch.Tensor,
    pcrb_final: float | None,
    pcrb_factor: float = 5.0,
    divergence_sigma: float = 9.0,
    lost: torch.Tensor | None = None,
) -> torch.Tensor:
    """The divergence rule (`divergence_rule`) per run.

    Args:
        final_err: ``(N,)`` final horizontal error, m.
        final_sigma: ``(N,)`` the filter's final 1σ horizontal bound ``sqrt(Pxx + Pyy)``.
        included: ``(N,)`` runs that count (on the map, finite).
        healthy: ``(N,)`` runs whose filter stayed numerically healthy (a failed run is a
            numerical failure, not a divergence).
        est_left: ``(N,)`` runs whose estimate left the map.
        pcrb_final: Final PCRB position bound, m (None: only the 1σ test).
        pcrb_factor: Threshold in final PCRBs.
        divergence_sigma: Threshold in the filter's own 1σ.
        lost: ``(N,)`` runs the filter declared lost (`FilterRun.lost`): diverged whatever
            their final error (a lost run's held estimate may end near the truth by
            chance); None = none.

    Returns:
        ``(N,)`` bool, True where the run diverged.
    """
    too_far = final_err > divergence_sigma * final_sigma
    if pcrb_final is not None:
        too_far = too_far | (final_err > pcrb_factor * pcrb_final)
    diverged = included & healthy & (too_far | est_left)
    return diverged if lost is None else diverged | (included & lost)


def _time_averaged_nees(err: torch.Tensor, P: torch.Tensor, confidence: float
                        ) -> dict[str, Any]:
    """Time-averaged NEES over runs and filter steps 1…K, with two bands.

    ``nees_time_band``: Bar-Shalom's χ² band, ``χ²(n·M·K)/(M·K)`` quantiles, which treats
    every step as independent (too narrow when the errors are correlated in time, as a
    filter's are). ``nees_time_band_runs``: the band from the M independent runs, ``n ±
    z·s/√M`` with ``s`` the spread of the per-run time-averaged NEES (valid whatever the
    time correlation); ``nees_time_in_band`` tests the mean against this one.
    """
    m_runs, n_samples, n_states = err.shape
    empty = {"nees_time_avg": None, "nees_time_band": None, "nees_time_band_runs": None,
             "nees_time_in_band": None}
    if m_runs == 0 or n_samples < 2:
        return empty
    eps = nees(err[:, 1:], P[:, 1:])  # (M, K)
    finite = torch.isfinite(eps)
    count = int(finite.sum())
    if count == 0:
        return empty
    mean = float(eps[finite].mean())
    alpha = 1.0 - confidence
    lo = chi2_quantile(0.5 * alpha, n_states * count) / count
    hi = chi2_quantile(1.0 - 0.5 * alpha, n_states * count) / count
    per_run = torch.where(finite, eps, 0.0).sum(1) / finite.sum(1).clamp_min(1)
    per_run = per_run[finite.any(1)]
    band_runs = None
    inside = None
    if per_run.numel() >= 2:
        z = NormalDist().inv_cdf(1.0 - 0.5 * alpha)
        half = z * float(per_run.std(unbiased=True)) / math.sqrt(per_run.numel())
        band_runs = [n_states - half, n_states + half]
        inside = bool(band_runs[0] <= mean <= band_runs[1])
    return {"nees_time_avg": mean, "nees_time_band": [lo, hi],
            "nees_time_band_runs": band_runs, "nees_time_in_band": inside}


def navigation_metrics(
    run: FilterRun,
    pcrb_pos: torch.Tensor,
    *,
    pcrb_factor: float = 5.0,
    divergence_sigma: float = 9.0,
    nees_confidence: float = 0.95,
    map_aware_pos: torch.Tensor | None = None,
) -> dict[str, Any]:
    """Metrics of one method's Monte Carlo run (definitions in the module docstring).

    Args:
        run: The method's `FilterRun`.
        pcrb_pos: ``(K+1,)`` PCRB position bound ``sqrt(J⁻¹_xx + J⁻¹_yy)``, m
            (`neuralmap.lab.pcrb.pcrb_position`).
        map_aware_pos: ``(K+1,)`` the map-aware bound (`neuralmap.lab.pcrb.map_aware_pcrb`),
            or None: the divergence test's bound is then the larger of the two at the last
            sample (the ratios still use ``pcrb_pos``).
        pcrb_factor: Divergence threshold as a multiple of the final PCRB bound.
        divergence_sigma: Divergence threshold as a multiple of the filter's final 1σ
            horizontal bound ``sqrt(P_xx + P_yy)``.
        nees_confidence: Two-sided probability of the NEES band.

    Returns:
        Dict with floats (or None for empty subsets): ``rmse_pos_m`` (all included runs),
        ``rmse_pos_converged_m``, ``rmse_vel_mps`` (all included runs),
        ``rmse_vel_converged_mps``, ``sigma_pos_m``, ``sigma_vel_mps``,
        ``divergence_rate``, ``nees_in_band``, ``nees_mean``, ``nees_band`` ([lo, hi]),
        ``pcrb_ratio``, ``pcrb_pos_m`` (last-half RMS of the bound),
        ``pcrb_pos_final_m``, ``final_pos_m``, ``final_pos_converged_m``; ints
        ``n_runs``, ``n_off_map``, ``n_nonfinite``, ``n_unhealthy``, ``n_included``,
        ``n_diverged``, ``n_converged``; lists over the K+1 samples ``rmse_pos_curve``,
        ``rmse_pos_converged_curve``, ``rmse_vel_curve``, ``nees_curve``; the per-run
        bool list ``diverged`` (False for excluded runs) and ``divergence_rule``.

    Raises:
        NeuralMapError: ``pcrb_pos`` does not have shape ``(K+1,)``, or bad factors.
    """
    err = run.err.detach().to("cpu", torch.float64)
    P = run.P.detach().to("cpu", torch.float64)
    n_runs, n_samples = err.shape[0], err.shape[1]
    pcrb_pos = torch.as_tensor(pcrb_pos).detach().to("cpu", torch.float64).reshape(-1)
    if pcrb_pos.shape != (n_samples,):
        raise NeuralMapError(
            f"navigation_metrics: pcrb_pos must have shape (K+1,) = ({n_samples},) like the "
            f"run's time axis, got {tuple(pcrb_pos.shape)}."
        )
    if not (pcrb_factor > 0 and divergence_sigma > 0 and 0.0 < nees_confidence < 1.0):
        raise NeuralMapError(
            "navigation_metrics: pcrb_factor and divergence_sigma must be > 0 and "
            f"nees_confidence in (0, 1), got {pcrb_factor!r}, {divergence_sigma!r}, "
            f"{nees_confidence!r}."
        )
    half = n_samples // 2
    off_map = run.off_map.detach().cpu().bool()
    healthy = run.healthy.detach().cpu().bool()
    finite = torch.isfinite(err).all(dim=2).all(dim=1) & torch.isfinite(P).flatten(1).all(1)
    included = ~off_map & finite
    e_pos2 = err[..., 0] ** 2 + err[..., 1] ** 2
    e_vel2 = err[..., 3] ** 2 + err[..., 4] ** 2
    final_e = e_pos2[:, -1].sqrt()
    bound1 = (P[:, -1, 0, 0] + P[:, -1, 1, 1]).clamp(min=0.0).sqrt()
    pcrb_final = float(pcrb_pos[-1])
    if map_aware_pos is not None:
        pcrb_final = max(pcrb_final, float(torch.as_tensor(map_aware_pos).reshape(-1)[-1]))
    est_left = ~run.est_on_map.detach().cpu().bool().all(dim=1)
    lost = None if getattr(run, "lost", None) is None else run.lost.detach().cpu().bool()
    diverged = diverged_runs(final_e, bound1, included=included, healthy=healthy,
                             est_left=est_left, pcrb_final=pcrb_final,
                             pcrb_factor=pcrb_factor, divergence_sigma=divergence_sigma,
                             lost=lost)
    failed = included & ~healthy & ~diverged
    converged = included & ~diverged & ~failed
    n_included, n_conv = int(included.sum()), int(converged.sum())

    out: dict[str, Any] = {
        "n_runs": n_runs,
        "n_off_map": int(off_map.sum()),
        "n_nonfinite": int((~off_map & ~finite).sum()),
        "n_unhealthy": int(failed.sum()),
        "numerical_failure_rate": (int(failed.sum()) / n_included) if n_included else None,
        "n_estimate_left_map": int((included & est_left).sum()),
        "n_included": n_included,
        "n_diverged": int(diverged.sum()),
        "n_converged": n_conv,
        "divergence_rate": (int(diverged.sum()) / n_included) if n_included else None,
        "rmse_pos_m": _rms(e_pos2[included, half:]),
        "rmse_pos_converged_m": _rms(e_pos2[converged, half:]),
        "rmse_vel_mps": _rms(e_vel2[included, half:]),
        "rmse_vel_converged_mps": _rms(e_vel2[converged, half:]),
        "sigma_pos_m": _pooled_sigma(err[converged, half:, 0:2]),
        "sigma_vel_mps": _pooled_sigma(err[converged, half:, 3:5]),
        "final_pos_m": _rms(e_pos2[included, -1]),
        "final_pos_converged_m": _rms(e_pos2[converged, -1]),
        "pcrb_pos_m": _rms(pcrb_pos[half:] ** 2),
        "pcrb_pos_final_m": _none_if_bad(pcrb_final),
    }
    def ratio(rmse: float | None) -> float | None:
        return rmse / out["pcrb_pos_m"] if rmse is not None and out["pcrb_pos_m"] else None

    out["pcrb_ratio_all"] = ratio(out["rmse_pos_m"])
    out["pcrb_ratio_converged"] = ratio(out["rmse_pos_converged_m"])
    out["rmse_pos_curve"] = _curve(e_pos2[included], n_samples)
    out["rmse_pos_converged_curve"] = _curve(e_pos2[converged], n_samples)
    out["rmse_vel_curve"] = _curve(e_vel2[included], n_samples)

    n_states = err.shape[-1]
    out["nees_in_band_all"] = (
        _nees_in_band(err[included], P[included], n_states, nees_confidence)[0]
        if n_included
        else None
    )
    if n_conv:
        fraction, eps_bar, lo, hi = _nees_in_band(
            err[converged], P[converged], n_states, nees_confidence
        )
        good = torch.isfinite(eps_bar)
        out["nees_in_band"] = fraction
        out["nees_mean"] = _none_if_bad(float(eps_bar[good].mean())) if good.any() else None
        out["nees_band"] = [lo, hi]
        out["nees_curve"] = [_none_if_bad(v) for v in eps_bar.tolist()]
    else:
        out["nees_in_band"] = None
        out["nees_mean"] = None
        out["nees_band"] = None
        out["nees_curve"] = [None] * n_samples
    out.update(_time_averaged_nees(err[converged], P[converged], nees_confidence))
    out["diverged"] = diverged.tolist()
    out["divergence_rule"] = divergence_rule(pcrb_factor, divergence_sigma)
    return out


def acquisition_time(err_xy: torch.Tensor, bound: torch.Tensor, factor: float = 3.0,
                     dt: float = 1.0) -> torch.Tensor:
    """Time to acquire per run: the first time after which the error stays below
    ``factor`` times the bound.

    Args:
        err_xy: ``(N, K+1)`` horizontal error norms, m.
        bound: ``(K+1,)`` PCRB position bound, m.
        factor: Multiple of the bound.
        dt: Sample period, s.

    Returns:
        ``(N,)`` seconds; ``inf`` for a run still above the threshold at the last sample.
    """
    above = err_xy > factor * bound[None, :]
    k1 = above.shape[1]
    idx = torch.arange(k1, device=err_xy.device).expand_as(above)
    last_above = torch.where(above, idx, -1).amax(1)
    t = (last_above + 1).to(torch.float64) * dt
    return torch.where(last_above >= k1 - 1, math.inf, t)

