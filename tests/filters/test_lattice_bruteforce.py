"""Point-mass filters against the exact Bayes recursion on a fine fixed lattice (brute force).

The reference (`_FineLattice`, NumPy float64) carries the joint density of the *whole* state
on a fine regular lattice — no Rao-Blackwellisation, no moment matching, no regrid:

* acquisition grid (`PointMassFilter`, scalar altitude): ``(x, y, δh)``, model
  ``s_{k+1} = s_k + u + w_s``, ``δh_{k+1} = δh_k + w_h``, ``y = g(s) + δh + e``;
* tracker (`PointMassTracker`, velocity coupling): ``(x, y, v_x, v_y)``, model
  ``s_{k+1} = s_k + T v_k + u + w_s``, ``v_{k+1} = v_k + w_v``, ``y = g(s) + e``;

with a nonlinear synthetic terrain ``g`` (a hill the flight climbs over, with ripples) and
a truth that flies over it (known displacement ``u`` per step, plus the random walk and,
for the tracker, the velocity drift ``T v``: posteriors elongated along the contour lines,
2.4–9 m, and velocity σ 0.18–0.26 m/s, with strong position–velocity correlation).

Why the reference is exact to far below the tolerances:

* the velocity coupling is an integer shear: the lattice steps satisfy ``T · dv = r · ds``
  (``r`` integer), so the slice of velocity ``v_j`` moves by exactly ``r · j`` cells in s —
  no interpolation;
* process noise is a sampled, normalised Gaussian of at least one lattice cell (1σ): by
  Poisson summation its mean and variance equal the continuous kernel's to ~e^{-2π²}
  ≈ 3e-9 relative; the prior is a sampled Gaussian (same argument);
* the likelihood is evaluated at every lattice point; every posterior σ stays above 1.5
  reference cells (asserted), where moment sums of a smooth density are exact to ~1e-9;
* the lattice re-centres by whole cells only (an index shift, exact), and every
  operation asserts that the mass it drops at the border is below 1e-4 (mass beyond ~5σ:
  its effect on the moments is < 1e-3 σ in the mean and < 2e-3 in σ, a tenth of the
  tolerances).

The reference itself is checked against the exact Kalman filter on a plane terrain
(Gaussian posterior; same shear, noise and re-centring): ≤ 2e-3 σ per axis.

Errors are reported per axis in units of that axis's posterior σ (of the reference), at
the **worst step of the worst run** (not averaged, not scaled by the largest eigenvalue):
``|m_f − m_ref| / σ_ref`` for the mean, ``|σ_f / σ_ref − 1|`` for the standard deviation
and ``|ρ_f − ρ_ref|`` for each correlation coefficient. The tolerances (module constants)
are what the lattice methods achieve here plus a margin; the fault-injection tests show
that a wrong process noise, a wrong velocity coupling or a wrong measurement variance
fails them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter1d

from neuralmap.filters.point_mass import PointMassConfig, PointMassFilter
from neuralmap.filters.point_mass_tracker import PointMassTracker, TrackerConfig

D = torch.float64

#: Largest mass a reference operation may drop at the lattice border.
_EDGE_MASS = 1e-4
#: Smallest posterior σ of the reference in its own cells (moment sums exact above it).
_MIN_REF_CELLS = 1.5


def terrain(x, y, lib=np):
    """Nonlinear synthetic terrain ``g(x, y)``, m (NumPy or torch): a 150 m hill of 110 m
    radius (1σ) that the flight climbs over, with 5 m ripples of 140–200 m wavelength."""
    return (150.0 * lib.exp(-((x - 150.0) ** 2 + (y - 20.0) ** 2) / (2.0 * 110.0**2))
            + 5.0 * lib.sin(x / 23.0) * lib.cos(y / 31.0))


def terrain_t(points: torch.Tensor) -> torch.Tensor:
    """`terrain` on ``(..., 2)`` torch points."""
    return terrain(points[..., 0], points[..., 1], torch)


# --------------------------------------------------------------------------- reference
class _FineLattice:
    """Exact Bayes recursion on a fixed fine lattice over ``[s_x, s_y, z_1, …]``.

    ``p[i_x, i_y, j_1, …]`` is the mass at ``s = origin + ds · (i − c_s)``,
    ``z = dz · (j − c_z)`` (every axis symmetric about its centre index).

    Args:
        mean: ``(D,)`` prior mean (the s part sets the lattice origin; the z part must be 0).
        sd: ``(D,)`` prior standard deviations (diagonal prior).
        steps: ``(D,)`` lattice steps.
        half: ``(D,)`` half-widths (multiples of the steps).
    """

    def __init__(self, mean, sd, steps, half) -> None:
        self.steps = np.asarray(steps, float)
        n = [2 * int(round(h / d)) + 1 for h, d in zip(half, steps, strict=True)]
        self.offsets = [np.arange(k) - (k - 1) / 2 for k in n]
        self.origin = np.asarray(mean, float).copy()
        self._dim = len(n)
        logp = sum(-0.5 * (self.coords(a) - mean[a]) ** 2 / sd[a] ** 2
                   for a in range(len(n)))
        p = np.exp(logp - logp.max())
        self.p = p / p.sum()

    @property
    def dim(self) -> int:
        return self._dim

    def axis(self, a: int) -> np.ndarray:
        """``(n_a,)`` coordinates of axis ``a``."""
        return self.origin[a] + self.steps[a] * self.offsets[a]

    def coords(self, a: int) -> np.ndarray:
        """Axis ``a``'s coordinates shaped to broadcast against ``p``."""
        shape = [1] * self.dim
        shape[a] = -1
        return self.axis(a).reshape(shape)

    def _border_mass(self, a: int, width: int) -> float:
        """Mass in the first and last ``width`` cells of axis ``a``."""
        if width <= 0:
            return 0.0
        p = np.moveaxis(self.p, a, 0)
        return float(p[:width].sum() + p[-width:].sum())

    def shear(self, ratio: int, pairs: tuple[tuple[int, int], ...]) -> None:
        """``s_a += T · z_b`` for each pair ``(a, b)``, exactly: ``T dz_b = ratio · ds_a``,
        so the slice ``j`` of ``z_b`` moves ``ratio · (j − c)`` cells along ``a``."""
        for a, b in pairs:
            out = np.empty_like(self.p)
            dropped = 0.0
            axis = a if a < b else a - 1  # axis a inside a slice of z_b
            for j in range(self.p.shape[b]):
                sl = [slice(None)] * self.dim
                sl[b] = j
                part = self.p[tuple(sl)]
                k = ratio * int(self.offsets[b][j])
                if k:
                    edge = [slice(None)] * part.ndim
                    edge[axis] = slice(-k, None) if k > 0 else slice(None, -k)
                    dropped += float(part[tuple(edge)].sum())
                out[tuple(sl)] = np.roll(part, k, axis=axis)
            assert dropped < _EDGE_MASS, f"reference: shear drops mass {dropped:.2e}"
            self.p = out

    def blur(self, variances) -> None:
        """Adds independent Gaussian noise of the given variance along each axis: a
        sampled, normalised Gaussian kernel of at least one cell (1σ), whose mean and
        variance equal the continuous kernel's to ~e^{-2π²} ≈ 3e-9 (Poisson summation)."""
        for a, q in enumerate(variances):
            if q == 0.0:
                continue
            sigma = math.sqrt(q) / self.steps[a]
            assert sigma >= 1.0 - 1e-9, f"reference: noise of axis {a} below one cell"
            self.p = gaussian_filter1d(self.p, sigma, axis=a, mode="constant", truncate=8.0)
        dropped = 1.0 - float(self.p.sum())
        assert dropped < _EDGE_MASS, f"reference: noise drops mass {dropped:.2e}"
        self.p /= self.p.sum()

    def update(self, loglik: np.ndarray) -> None:
        """``p ∝ p · exp(loglik)`` (``loglik`` broadcasts against ``p``)."""
        p = self.p * np.exp(loglik - loglik.max())
        self.p = p / p.sum()

    def recentre(self) -> None:
        """Moves the s part of the lattice by whole cells towards the mean (exact)."""
        for a in (0, 1):
            mean_a = self.p.sum(tuple(b for b in range(self.dim) if b != a)) @ self.axis(a)
            k = int(round((mean_a - self.origin[a]) / self.steps[a]))
            if k == 0:
                continue
            p = np.moveaxis(self.p, a, 0)
            dropped = float((p[:k] if k > 0 else p[k:]).sum())  # the cells that wrap round
            assert dropped < _EDGE_MASS, f"reference: re-centring drops mass {dropped:.2e}"
            p = np.roll(p, -k, axis=0)
            (p[-k:] if k > 0 else p[:-k]).fill(0.0)
            self.p = np.moveaxis(p, 0, a)
            self.origin[a] += k * self.steps[a]

    def moments(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean ``(D,)`` and covariance ``(D, D)``."""
        d = self.dim
        mean = np.empty(d)
        for a in range(d):
            mean[a] = self.p.sum(tuple(b for b in range(d) if b != a)) @ self.axis(a)
        cov = np.empty((d, d))
        for a in range(d):
            for b in range(a, d):
                keep = (a,) if a == b else (a, b)
                marg = self.p.sum(tuple(c for c in range(d) if c not in keep))
                da, db = self.axis(a) - mean[a], self.axis(b) - mean[b]
                cov[a, b] = cov[b, a] = marg @ (da * da) if a == b else da @ marg @ db
        return mean, cov


# --------------------------------------------------------------------------- scenarios
@dataclass
class Scenario:
    """One brute-force scenario (units m, m/s, s)."""

    steps: int = 6
    sd_s: float = 6.0  # prior σ of x, y
    sd_z: float = 0.15  # prior σ of the linear part (velocity, or altitude)
    q_s: float = 1.0  # position noise per step, m²
    q_z: float = 0.01  # linear-part noise per step
    R: float = 9.0  # measurement variance, m²
    u: tuple[float, float] = (15.0, 10.0)  # known displacement per step, m
    T: float = 7.5  # period (velocity coupling), s
    ds: float = 0.75  # reference step in s, m
    dz: float = 0.1  # reference step of the linear part
    half_s: float = 45.0
    half_z: float = 1.4


@dataclass
class Errors:
    """Worst per-axis errors over steps and runs (units: the reference's σ)."""

    mean: np.ndarray  # (D,)
    sd: np.ndarray  # (D,)
    corr: float  # largest |ρ_f − ρ_ref| over the pairs
    ref_cells: float  # smallest reference posterior σ in reference cells
    mean_avg: np.ndarray  # (D,) averages over steps and runs (reported only)
    sd_avg: np.ndarray


def _errors(pairs: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
            steps: np.ndarray) -> Errors:
    """Worst per-axis errors of ``(m_f, C_f, m_ref, C_ref)`` over every step and run."""
    e_mean, e_sd, e_corr, cells = [], [], [], []
    for mf, cf, mr, cr in pairs:
        sr, sf = np.sqrt(np.diag(cr)), np.sqrt(np.diag(cf))
        e_mean.append(np.abs(mf - mr) / sr)
        e_sd.append(np.abs(sf / sr - 1.0))
        iu = np.triu_indices(len(mr), 1)
        e_corr.append(float(np.abs(cf / np.outer(sf, sf) - cr / np.outer(sr, sr))[iu].max()))
        cells.append(float((sr / steps).min()))
    return Errors(np.max(e_mean, 0), np.max(e_sd, 0), max(e_corr), min(cells),
                  np.mean(e_mean, 0), np.mean(e_sd, 0))


def _truth(sc: Scenario, seed: int, coupled: bool, g: Callable = terrain):
    """Truth states ``(K, 4)`` and measurements ``(K,)`` of one run (steps 1…K)."""
    rng = np.random.default_rng(seed)
    s = sc.sd_s * rng.standard_normal(2)
    z = sc.sd_z * rng.standard_normal(2 if coupled else 1)
    states, ys = [], []
    for _ in range(sc.steps):
        s = s + (sc.T * z if coupled else 0.0) + np.asarray(sc.u) + math.sqrt(sc.q_s) * \
            rng.standard_normal(2)
        z = z + math.sqrt(sc.q_z) * rng.standard_normal(z.shape)
        y = g(*s) + (0.0 if coupled else z[0]) + math.sqrt(sc.R) * rng.standard_normal()
        states.append(np.concatenate([s, z]))
        ys.append(float(y))
    return np.array(states), np.array(ys)


def velocity_reference(sc: Scenario, ys: np.ndarray, g: Callable = terrain):
    """Reference moments per step over ``(x, y, v_x, v_y)`` (list of ``(mean, cov)``)."""
    ratio = sc.T * sc.dz / sc.ds
    assert abs(ratio - round(ratio)) < 1e-9, "reference: T·dv must be a whole number of ds"
    ref = _FineLattice(np.zeros(4), [sc.sd_s, sc.sd_s, sc.sd_z, sc.sd_z],
                       [sc.ds, sc.ds, sc.dz, sc.dz],
                       [sc.half_s, sc.half_s, sc.half_z, sc.half_z])
    out = []
    for k, y in enumerate(ys, start=1):
        ref.shear(int(round(ratio)), ((0, 2), (1, 3)))
        ref.origin[:2] += np.asarray(sc.u)
        ref.blur([sc.q_s, sc.q_s, sc.q_z, sc.q_z])
        ref.update(-0.5 * (y - g(ref.coords(0), ref.coords(1))) ** 2 / sc.R)
        ref.recentre()
        out.append(ref.moments())
        del k
    return out


def altitude_reference(sc: Scenario, ys: np.ndarray):
    """Reference moments per step over ``(x, y, δh)``."""
    ref = _FineLattice(np.zeros(3), [sc.sd_s, sc.sd_s, sc.sd_z], [sc.ds, sc.ds, sc.dz],
                       [sc.half_s, sc.half_s, sc.half_z])
    out = []
    for y in ys:
        ref.origin[:2] += np.asarray(sc.u)
        ref.blur([sc.q_s, sc.q_s, sc.q_z])
        g = terrain(ref.coords(0), ref.coords(1))
        ref.update(-0.5 * (y - g - ref.coords(2)) ** 2 / sc.R)
        ref.recentre()
        out.append(ref.moments())
    return out


# --------------------------------------------------------------------------- filters
def run_tracker(sc: Scenario, ys: np.ndarray, config: TrackerConfig, *,
                model_T: float | None = None, model_q_s: float | None = None,
                model_R: float | None = None, dtype: torch.dtype = D):
    """The tracker's moments per step for the runs ``ys (N, K)`` (list over steps of
    ``(mean (N, 4), cov (N, 4, 4))``); ``model_*`` override the model (fault injection)."""
    n = ys.shape[0]
    T = sc.T if model_T is None else model_T
    q_s = sc.q_s if model_q_s is None else model_q_s
    R = sc.R if model_R is None else model_R
    cov0 = torch.diag(torch.tensor([sc.sd_s**2] * 2 + [sc.sd_z**2] * 2, dtype=D)).to(dtype)
    tracker = PointMassTracker(torch.zeros(n, 4, dtype=dtype), cov0,
                               E=T * torch.eye(2, dtype=dtype), F=torch.eye(2, dtype=dtype),
                               c=torch.zeros(2, dtype=dtype), config=config, dtype=dtype)
    shift = torch.tensor(sc.u, dtype=dtype).expand(n, 2)
    out = []
    for k in range(ys.shape[1]):
        tracker.predict(Q_s=q_s * torch.eye(2, dtype=dtype),
                        Q_z=sc.q_z * torch.eye(2, dtype=dtype), shift=shift)
        tracker.update(torch.as_tensor(ys[:, k], dtype=dtype), terrain_t, R=R)
        mean, cov = tracker.moments()
        out.append((mean.double().numpy(), cov.double().numpy()))
    return out, tracker


def run_grid(sc: Scenario, ys: np.ndarray, config: PointMassConfig, *,
             model_q_s: float | None = None, model_R: float | None = None,
             dtype: torch.dtype = D):
    """The acquisition grid's moments per step over ``(x, y, δh)`` (cross-covariance of
    δh with s is not part of its moments API: set to the reference's by the caller)."""
    n = ys.shape[0]
    q_s = sc.q_s if model_q_s is None else model_q_s
    R = sc.R if model_R is None else model_R
    pm = PointMassFilter(torch.zeros(n, 2, dtype=dtype), sc.sd_s**2 * torch.eye(2, dtype=dtype),
                         scalar_mean=0.0, scalar_var=sc.sd_z**2, config=config, dtype=dtype)
    shift = torch.tensor(sc.u, dtype=dtype).expand(n, 2)
    out = []
    for k in range(ys.shape[1]):
        pm.predict(Q=q_s, shift=shift, scalar_q=sc.q_z)
        pm.update(torch.as_tensor(ys[:, k], dtype=dtype), terrain_t, R=R)
        m_s, c_s = pm.mean().double().numpy(), pm.cov().double().numpy()
        m_h, v_h = (t.double().numpy() for t in pm.scalar_moments())
        out.append((m_s, c_s, m_h, v_h))
    return out, pm


# --------------------------------------------------------------------------- comparisons
@dataclass
class Case:
    """Scenario, seeds and the cached references."""

    sc: Scenario
    seeds: tuple[int, ...]
    coupled: bool

    def __post_init__(self) -> None:
        self.truths, self.ys, self.refs = [], [], []
        for seed in self.seeds:
            states, ys = _truth(self.sc, seed, self.coupled)
            self.truths.append(states)
            self.ys.append(ys)
            self.refs.append((velocity_reference if self.coupled else altitude_reference)(
                self.sc, ys))
        self.ys = np.stack(self.ys)

    @property
    def ref_steps(self) -> np.ndarray:
        sc = self.sc
        return np.array([sc.ds, sc.ds] + [sc.dz] * (2 if self.coupled else 1))


def tracker_errors(case: Case, config: TrackerConfig, **model) -> tuple[Errors, PointMassTracker]:
    """Worst per-axis errors of the tracker against the reference over ``case``."""
    moments, tracker = run_tracker(case.sc, case.ys, config, **model)
    pairs = [(mean[i], cov[i], *case.refs[i][k])
             for k, (mean, cov) in enumerate(moments) for i in range(len(case.seeds))]
    return _errors(pairs, case.ref_steps), tracker


def grid_errors(case: Case, config: PointMassConfig, **model) -> tuple[Errors, PointMassFilter]:
    """Worst per-axis errors of the acquisition grid against the reference over ``case``
    (its s–δh cross-covariance is taken from the reference: the grid reports none)."""
    moments, pm = run_grid(case.sc, case.ys, config, **model)
    pairs = []
    for k, (m_s, c_s, m_h, v_h) in enumerate(moments):
        for i in range(len(case.seeds)):
            mr, cr = case.refs[i][k]
            mf = np.array([*m_s[i], m_h[i]])
            cf = cr.copy()
            cf[:2, :2] = c_s[i]
            cf[2, 2] = v_h[i]
            pairs.append((mf, cf, mr, cr))
    return _errors(pairs, case.ref_steps), pm


def _describe(e: Errors, names: tuple[str, ...]) -> str:
    return ("worst mean/σ " + ", ".join(f"{n} {v:.4f}" for n, v in zip(names, e.mean, strict=True))
            + " | worst |σ/σ_ref − 1| " + ", ".join(
                f"{n} {v:.4f}" for n, v in zip(names, e.sd, strict=True))
            + f" | worst |Δρ| {e.corr:.4f} | ref σ ≥ {e.ref_cells:.2f} cells")


def _kalman_velocity(sc: Scenario, ys: np.ndarray, slope: tuple[float, float]):
    """Textbook Kalman filter (Joseph form) of the velocity model on a plane terrain."""
    F = np.eye(4)
    F[0, 2] = F[1, 3] = sc.T
    Q = np.diag([sc.q_s, sc.q_s, sc.q_z, sc.q_z])
    H = np.array([slope[0], slope[1], 0.0, 0.0])
    x, P = np.zeros(4), np.diag([sc.sd_s**2] * 2 + [sc.sd_z**2] * 2)
    out = []
    for y in ys:
        x = F @ x + np.array([*sc.u, 0.0, 0.0])
        P = F @ P @ F.T + Q
        S = H @ P @ H + sc.R
        K = P @ H / S
        x = x + K * (y - H @ x)
        ikh = np.eye(4) - np.outer(K, H)
        P = ikh @ P @ ikh.T + sc.R * np.outer(K, K)
        out.append((x.copy(), P.copy()))
    return out


# --------------------------------------------------------------------------- tests
#: Tracker tolerances (worst step, worst run; units of the reference's σ). Measured (one
#: run, 32 cells at σ/3.1): 0.032 σ in the mean (y), 2.7 % in σ (y, v_y), 0.035 in ρ; with
#: 64 cells the same to 1e-3, so this is the Rao-Blackwellised velocity part (one
#: conditional covariance per run), not the lattice resolution. Four runs (the slow test):
#: 0.032 σ, 2.7 %, 0.037. About 1.5× margin.
TRACKER_MEAN_TOL = 0.05
TRACKER_SD_TOL = 0.04
TRACKER_CORR_TOL = 0.05

#: Acquisition grid tolerances (same units). Measured (two runs, 20 steps, default 64-cell
#: adaptive grid and a fixed 64-cell grid): 0.0047 σ in the mean, 1.0 % in σ (δh); 2× margin.
GRID_MEAN_TOL = 0.01
GRID_SD_TOL = 0.02

VELOCITY = Scenario()
ALTITUDE = Scenario(steps=20, sd_z=3.0, q_z=1.0, dz=0.5, half_z=18.0, T=0.0)
_NAMES_V = ("x", "y", "vx", "vy")
_NAMES_H = ("x", "y", "dh")


@pytest.fixture(scope="module")
def velocity_case() -> Case:
    return Case(VELOCITY, seeds=(0,), coupled=True)


@pytest.fixture(scope="module")
def altitude_case() -> Case:
    return Case(ALTITUDE, seeds=(0, 1), coupled=False)


def _assert_within(e: Errors, names: tuple[str, ...], mean_tol: float, sd_tol: float,
                   corr_tol: float | None) -> None:
    text = _describe(e, names)
    assert e.ref_cells >= _MIN_REF_CELLS, "reference too coarse: " + text
    assert float(e.mean.max()) <= mean_tol, text
    assert float(e.sd.max()) <= sd_tol, text
    if corr_tol is not None:
        assert e.corr <= corr_tol, text


def test_reference_equals_the_kalman_filter_on_a_plane() -> None:
    """The brute-force recursion itself (shear, noise, re-centring) against the exact
    Kalman filter where the posterior is Gaussian (plane terrain): ≤ 2e-3 σ per axis."""
    slope = (0.6, -0.4)

    def plane(x, y):
        return slope[0] * x + slope[1] * y

    sc = VELOCITY
    _, ys = _truth(sc, 7, True, g=plane)
    ref = velocity_reference(sc, ys, g=plane)
    kf = _kalman_velocity(sc, ys, slope)
    e = _errors([(mk, ck, mr, cr) for (mk, ck), (mr, cr) in zip(kf, ref, strict=True)],
                np.array([sc.ds, sc.ds, sc.dz, sc.dz]))
    assert float(e.mean.max()) <= 2e-3 and float(e.sd.max()) <= 2e-3 and e.corr <= 2e-3, (
        _describe(e, _NAMES_V))


def test_tracker_matches_the_fine_lattice_per_axis_at_the_worst_step(
        velocity_case: Case) -> None:
    """(x, y, vx, vy), moving truth, velocity coupling T = 7.5 s: worst step of the run."""
    e, tracker = tracker_errors(velocity_case, TrackerConfig(lost_window=0))
    assert int(tracker.regrids.min()) >= 3  # the lattice followed the posterior
    _assert_within(e, _NAMES_V, TRACKER_MEAN_TOL, TRACKER_SD_TOL, TRACKER_CORR_TOL)


@pytest.mark.parametrize(("fault", "model"), [
    ("no velocity coupling", {"model_T": 0.0}),
    ("process noise x4", {"model_q_s": 4.0 * VELOCITY.q_s}),
    ("measurement variance x2", {"model_R": 2.0 * VELOCITY.R}),
])
def test_tracker_comparison_fails_for_a_wrong_model(velocity_case: Case, fault: str,
                                                     model: dict) -> None:
    """The same comparison with one model term wrong exceeds the tolerances."""
    e, _ = tracker_errors(velocity_case, TrackerConfig(lost_window=0), **model)
    assert (float(e.mean.max()) > TRACKER_MEAN_TOL or float(e.sd.max()) > TRACKER_SD_TOL
            or e.corr > TRACKER_CORR_TOL), f"{fault} not detected: " + _describe(e, _NAMES_V)


@pytest.mark.slow
def test_tracker_matches_the_fine_lattice_over_four_runs() -> None:
    """Four runs (seeds 0–3), worst step of the worst run."""
    case = Case(VELOCITY, seeds=(0, 1, 2, 3), coupled=True)
    e, _ = tracker_errors(case, TrackerConfig(lost_window=0))
    _assert_within(e, _NAMES_V, TRACKER_MEAN_TOL, TRACKER_SD_TOL, TRACKER_CORR_TOL)


@pytest.mark.parametrize("config", [
    PointMassConfig(),
    PointMassConfig(cells=64, adaptive=False),
], ids=["adaptive", "fixed"])
def test_grid_matches_the_fine_lattice_per_axis_at_the_worst_step(
        altitude_case: Case, config: PointMassConfig) -> None:
    """(x, y, δh), moving truth, altitude in the measurement: worst step of two runs."""
    e, _ = grid_errors(altitude_case, config)
    _assert_within(e, _NAMES_H, GRID_MEAN_TOL, GRID_SD_TOL, None)


@pytest.mark.parametrize(("fault", "model"), [
    ("process noise x4", {"model_q_s": 4.0 * ALTITUDE.q_s}),
    ("measurement variance x2", {"model_R": 2.0 * ALTITUDE.R}),
])
def test_grid_comparison_fails_for_a_wrong_model(altitude_case: Case, fault: str,
                                                 model: dict) -> None:
    e, _ = grid_errors(altitude_case, PointMassConfig(), **model)
    assert float(e.mean.max()) > GRID_MEAN_TOL or float(e.sd.max()) > GRID_SD_TOL, (
        f"{fault} not detected: " + _describe(e, _NAMES_H))
