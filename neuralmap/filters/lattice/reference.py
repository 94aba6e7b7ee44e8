"""The following lattice of the point-mass tracker in NumPy, one run: the algorithm written
out plainly, as a reference.

`FollowLatticeReference` is `neuralmap.filters.point_mass_tracker.PointMassTracker` (the
``follow`` lattice rule, `neuralmap.filters.lattice.follow_rule`) for a single run, in
float64 NumPy with Python control flow and no batching: the same prediction (exact
predicted moments, the lattice moved by the affine part of ``E μ``, the separable blur of
the residual noise, the per-cell means as a ratio), the same measurement update of the
masses and of the Rao-Blackwellised linear part, the same lost-track test and regrid
(Gaussian-factored bilinear resampling) and the same moment correction. It serves the
tests (tests/filters/test_lattice_reference.py: equal to the torch filter on a flight) and
the benchmark's same-algorithm NumPy row (benchmarks/bench_point_mass.py).

Conventions as the torch filter: cell ``(i, j)`` (row ``i``, column ``j``) sits at
``centre + A (j − h, i − h)``, ``h = (G − 1)/2``; the lattice axes of a Gaussian are its
principal axes in the closed-form convention of `neuralmap.filters.lattice.algebra2.eigh2`
(the axes' signs order the cells; every other matrix function here is LAPACK's).

One difference is the batch: the torch filter takes one blur-kernel length for all its
runs (``⌈4 σ_max⌉`` over the batch); here it is the run's own (equal for a batch of one).
"""

from __future__ import annotations

import math

import numpy as np

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.lattice.follow_rule import TrackerConfig
from neuralmap.filters.stats import chi2_mean_threshold

__all__ = ["FollowLatticeReference"]

_LOG_2PI = math.log(2.0 * math.pi)
_TINY = np.finfo(np.float64).tiny
_BLUR_MIN_CELLS = 1e-3  # as follow_step.BLUR_MIN_CELLS
_MIN_CELL_VARIANCE = 0.25  # as follow_step.MIN_CELL_VARIANCE
_GAUSS_MIN_CELLS = 0.7  # as follow_step.GAUSS_MIN_CELLS
_LOG_R_FLOOR = -60.0
_P_FLOOR = 1e-12
_RATIO_EPS = 1e-13  # as kernels.RATIO_EPS
_EXP_FLOOR = -700.0  # as underflow.EXP_FLOOR (float64)


def _sym(m: np.ndarray) -> np.ndarray:
    return 0.5 * (m + m.T)


def _eigh2(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ascending eigenvalues and eigenvectors (columns) of a symmetric 2 × 2 matrix in the
    convention of `neuralmap.filters.lattice.algebra2.eigh2` (``θ = ½ atan2(2b, a − d)``;
    columns ``(−sin θ, cos θ)``, ``(cos θ, sin θ)``)."""
    a, b, d = c[0, 0], c[0, 1], c[1, 1]
    sm, rt = a + d, math.hypot(a - d, 2.0 * b)
    big = 0.5 * (sm + rt) if sm >= 0 else 0.5 * (sm - rt)
    small = 0.0 if big == 0 else (a * d - b * b) / big
    theta = 0.5 * math.atan2(2.0 * b, a - d)
    cs, sn = math.cos(theta), math.sin(theta)
    return (np.array([min(big, small), max(big, small)]),
            np.array([[-sn, cs], [cs, sn]]))


def _spd(c: np.ndarray) -> bool:
    """Finite, symmetric (1e-9 relative) and positive definite."""
    if not np.all(np.isfinite(c)):
        return False
    if np.abs(c - c.T).max() > 1e-9 * np.abs(c).max() + 1e-300:
        return False
    try:
        np.linalg.cholesky(c)
    except np.linalg.LinAlgError:
        return False
    return True


def _sqrtm(m: np.ndarray) -> np.ndarray:
    lam, vec = np.linalg.eigh(_sym(m))
    return (vec * np.sqrt(np.maximum(lam, _TINY))) @ vec.T


def _exp_or_zero(x: np.ndarray) -> np.ndarray:
    with np.errstate(under="ignore"):
        return np.where(x < _EXP_FLOOR, 0.0, np.exp(np.maximum(x, _EXP_FLOOR)))


class FollowLatticeReference:
    """One run of the point-mass tracker (the ``follow`` lattice), NumPy float64.

    Args:
        mean: ``(2 + nz,)`` prior mean ``[s, z]``.
        cov: ``(2+nz, 2+nz)`` prior covariance.
        E, F, c: The model (``(2, nz)``, ``(nz, nz)``, ``(nz,)``; ``follow_rule`` module
            docstring).
        config: `TrackerConfig` (its lattice and lost-track options).

    Attributes:
        w: ``(G, G)`` masses; ``mu``: ``(nz, G, G)`` per-cell means of ``z``; ``P``:
            ``(nz, nz)``; ``centre``: ``(2,)``; ``axes``: ``(2, 2)`` cell steps (columns).
        regrids, widenings: Counters; ``lost``: lost beyond recovery.
    """

    def __init__(self, mean: np.ndarray, cov: np.ndarray, *, E: np.ndarray, F: np.ndarray,
                 c: np.ndarray, config: TrackerConfig | None = None) -> None:
        self.cfg = (config or TrackerConfig()).validate()
        self.E, self.F, self.c = (np.asarray(x, dtype=np.float64) for x in (E, F, c))
        self.nz = self.c.shape[0]
        self.G = self.cfg.cells
        self.h = 0.5 * (self.G - 1)
        self.off = np.arange(self.G) - self.h
        mean, cov = np.asarray(mean, dtype=np.float64), np.asarray(cov, dtype=np.float64)
        self.q_next = np.zeros(2)
        self.open_mean, self.open_cov = mean.copy(), cov.copy()
        self.nis_win = np.zeros(self.cfg.lost_window or 1)
        self.nis_count = self.step = self.widenings = self.regrids = 0
        self.lost = False
        self.w, self.mu, self.P, self.centre, self.axes = self._gaussian(mean, cov, np.zeros(2))

    # ------------------------------------------------------------------ moments
    def _lattice_moments(self, w: np.ndarray, mu: np.ndarray) -> tuple[np.ndarray, ...]:
        """``u (2,)``, ``cu (2, 2)`` (cells), ``mz (nz,)``, ``czu (nz, 2)``, ``czz_b (nz, nz)``:
        the masses' mean and covariance in cell coordinates, the mean of ``z`` and the
        covariances of the per-cell means with the cells and with themselves."""
        o = self.off
        wx, wy = w.sum(0), w.sum(1)  # per column (x), per row (y)
        ux, uy = wx @ o, wy @ o
        cxx, cyy = wx @ (o * o) - ux * ux, wy @ (o * o) - uy * uy
        cxy = o @ w @ o - ux * uy  # Σ_ij w_ij o_i o_j
        wmu = mu * w
        mz = wmu.sum((1, 2))
        czx = wmu.sum(1) @ o - mz * ux
        czy = wmu.sum(2) @ o - mz * uy
        czz = np.einsum("aij,bij->ab", wmu, mu) - np.outer(mz, mz)
        return (np.array([ux, uy]), np.array([[cxx, cxy], [cxy, cyy]]), mz,
                np.stack([czx, czy], 1), _sym(czz))

    def _state_moments(self, lm: tuple[np.ndarray, ...], P: np.ndarray, centre: np.ndarray,
                       axes: np.ndarray) -> tuple[np.ndarray, ...]:
        """``ms, css, mz, czz, czs`` in state units: ``c + A u``, ``A cu Aᵀ``, ``z̄``,
        ``P + Cov_w(μ)``, ``Cov_w(μ, o) Aᵀ``."""
        u, cu, mz, czu, czz_b = lm
        return (centre + axes @ u, _sym(axes @ cu @ axes.T), mz, _sym(P + czz_b), czu @ axes.T)

    def moments(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean ``(2+nz,)`` and covariance ``(2+nz, 2+nz)`` of ``[s, z]``."""
        ms, css, mz, czz, czs = self._state_moments(self._lattice_moments(self.w, self.mu),
                                                    self.P, self.centre, self.axes)
        return _joint(ms, css, mz, czz, czs)

    # ------------------------------------------------------------------ lattices
    def _lattice_for(self, mean: np.ndarray, cov: np.ndarray,
                     q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centre and cell steps of the lattice of ``N(mean, cov)``: ``± span_sigma
        sqrt(σ² + q)`` per (principal) axis, at least ``min_half_width``."""
        cfg = self.cfg
        if cfg.principal_axes:
            lam, vec = _eigh2(_sym(cov))
            qa = (vec * vec).T @ q  # q on the axes
        else:
            lam, vec, qa = np.diag(cov).copy(), np.eye(2), q
        halfw = np.maximum(cfg.span_sigma * np.sqrt(np.maximum(lam, 0.0) + qa),
                           cfg.min_half_width)
        step = halfw / self.h
        if cfg.max_spacing is not None and np.any(step > cfg.max_spacing * (1 + 1e-9)):
            raise NeuralMapError("FollowLatticeReference: cells coarser than max_spacing.")
        if not np.all(np.isfinite(step)) or not np.all(step > 0):
            raise NeuralMapError("FollowLatticeReference: zero or non-finite cells.")
        return mean.copy(), vec * step[None, :]

    def _log_gauss(self, u: np.ndarray, cu: np.ndarray) -> np.ndarray:
        """``log N(o; u, cu)`` at the cells up to a constant, eigenvalues of ``cu`` floored
        at 1/12 cell² (one uniform cell)."""
        lam, vec = np.linalg.eigh(_sym(cu))
        inv = (vec / np.maximum(lam, 1.0 / 12.0)) @ vec.T
        dx, dy = (self.off - u[0])[None, :], (self.off - u[1])[:, None]
        return -0.5 * (inv[0, 0] * dx * dx + 2.0 * inv[0, 1] * dx * dy + inv[1, 1] * dy * dy)

    def _affine(self, g: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``(nz, G, G)`` ``g (o − u)`` for ``g (nz, 2)``."""
        dx, dy = (self.off - u[0])[None, None, :], (self.off - u[1])[None, :, None]
        return g[:, 0, None, None] * dx + g[:, 1, None, None] * dy

    def _gaussian(self, mean: np.ndarray, cov: np.ndarray, q: np.ndarray) -> tuple:
        """Lattice state of ``N(mean, cov)`` with its moments matched exactly."""
        ms, mz = mean[:2], mean[2:]
        css, czs, czz = cov[:2, :2], cov[2:, :2], cov[2:, 2:]
        centre, axes = self._lattice_for(ms, css, q)
        ia = np.linalg.inv(axes)
        w = _normalised(self._log_gauss(np.zeros(2), _sym(ia @ css @ ia.T)))
        mu = mz[:, None, None] + self._affine(czs @ np.linalg.solve(css, axes), np.zeros(2))
        P = _sym(czz - czs @ np.linalg.solve(css, czs.T))
        return self._matched((w, mu, P, centre, axes), (ms, css, mz, czz, czs), fallback=False)

    def _matched(self, state: tuple, target: tuple, fallback: bool = True) -> tuple:
        """The moment correction: the lattice mapped by ``s ↦ m_t + T (s − m)``,
        ``T = C^{-1/2} (C^{1/2} C_t C^{1/2})^{1/2} C^{-1/2}``, the per-cell means shifted by
        ``Δz̄ + g (o − u)`` (``Cov(z, s)`` on target), ``P = C_zz,t − Cov_w(μ)`` (floored
        at ``1e-12`` of its largest eigenvalue). Masses narrower than 0.25 cell² are
        replaced by the Gaussian of the target first."""
        w, mu, P, centre, axes = state
        ms_t, css_t, mz_t, czz_t, czs_t = target
        lm = self._lattice_moments(w, mu)
        if fallback and _thin(lm[1]):
            w, mu, P, centre, axes = self._gaussian(*_joint(*target), np.zeros(2))
            lm = self._lattice_moments(w, mu)
        u, cu, mz, czu, czz_b = lm
        css = _sym(axes @ cu @ axes.T)
        with np.errstate(all="ignore"):
            root = _sqrtm(css)
            iroot = np.linalg.inv(root)
            T = iroot @ _sqrtm(root @ css_t @ root) @ iroot
        if not (np.all(np.isfinite(T)) and _spd(css) and _spd(_sym(css_t))):
            T = np.eye(2)
        axes = T @ axes
        centre = ms_t - axes @ u
        want = np.linalg.solve(axes, czs_t.T).T  # czs_t A^-T
        gu = np.linalg.solve(cu, (want - czu).T).T
        mu = mu + (mz_t - mz)[:, None, None] + self._affine(gu, u)
        czz_b = czz_b + gu @ czu.T + czu @ gu.T + gu @ cu @ gu.T
        P = _sym(czz_t - czz_b)
        lam, vec = np.linalg.eigh(P)
        floor = _P_FLOOR * max(np.abs(lam).max(), 1e-300)
        if np.any(lam < floor):
            P = _sym((vec * np.maximum(lam, floor)) @ vec.T)
        return w, mu, P, centre, axes

    def _refit_thin(self) -> tuple[np.ndarray, ...]:
        """Masses narrower than 0.25 cell²: their Gaussian fit (cell spread ``A Aᵀ/12``
        added) on a fresh lattice (counted as a regrid); the lattice moments."""
        lm = self._lattice_moments(self.w, self.mu)
        if not _thin(lm[1]):
            return lm
        u, cu, mz, czu, czz_b = lm
        a = self.axes
        target = (self.centre + a @ u, _sym(a @ (cu + np.eye(2) / 12.0) @ a.T), mz,
                  _sym(self.P + czz_b), czu @ a.T)
        self.w, self.mu, self.P, self.centre, self.axes = self._gaussian(*_joint(*target),
                                                                          np.zeros(2))
        self.regrids += 1
        return self._lattice_moments(self.w, self.mu)

    # ------------------------------------------------------------------ predict
    def predict(self, Q_s: np.ndarray, Q_z: np.ndarray, shift: np.ndarray | None = None) -> None:
        """Time update ``s' = s + E z + u + w_s``, ``z' = F z + w_z`` (exact in its first two
        moments; ``follow_rule`` module docstring)."""
        E, F = self.E, self.F
        qs, qz = np.asarray(Q_s, dtype=np.float64), np.asarray(Q_z, dtype=np.float64)
        u_shift = np.zeros(2) if shift is None else np.asarray(shift, dtype=np.float64)
        lm = self._refit_thin()
        u, cu, mz, czu, czz_b = lm
        w, mu, P, centre, axes = self.w, self.mu, self.P, self.centre, self.axes
        ms, css, _, czz, czs = self._state_moments(lm, P, centre, axes)
        ms_t = ms + E @ mz + u_shift
        css_t = _sym(css + E @ czs + czs.T @ E.T + E @ czz @ E.T + qs)
        mz_t = F @ mz
        czz_t = _sym(F @ czz @ F.T + qz)
        czs_t = F @ (czs + czz @ E.T)
        # the per-cell means' affine fit moves the lattice; its residual is transition noise
        gzu = np.linalg.solve(cu, czu.T).T
        cz_res = _sym(czz_b - gzu @ czu.T)
        axes_new = axes + E @ gzu
        centre_new = ms_t - axes_new @ u
        sig_eta = _sym(E @ P @ E.T + qs + E @ cz_res @ E.T)
        ia = np.linalg.inv(axes_new)
        var_c = np.maximum(np.diag(ia @ sig_eta @ ia.T), 0.0)
        vmax = var_c.max()
        if vmax >= _BLUR_MIN_CELLS**2:
            half_len = min(max(1, math.ceil(4.0 * math.sqrt(vmax))), self.G - 1)
            affine = mz[:, None, None] + self._affine(gzu, u)
            chans = np.concatenate([w[None], w[None] * (mu - affine)], 0)
            chans = _convolve(chans, _kernel(math.sqrt(var_c[0]), half_len), axis=2)
            chans = _convolve(chans, _kernel(math.sqrt(var_c[1]), half_len), axis=1)
            mass = np.maximum(chans[0], 0.0)
            w = mass / max(mass.sum(), _TINY)
            eps = max(_RATIO_EPS * mass.max(), _TINY)  # a cell at round-off: the fit's mean
            mu = chans[1:] / (mass[None] + eps) + affine
        if not np.array_equal(F, np.eye(self.nz)):
            mu = np.einsum("yz,zij->yij", F, mu)
        target = (ms_t, css_t, mz_t, czz_t, czs_t)
        self.w, self.mu, self.P, self.centre, self.axes = self._matched(
            (w, mu, P, centre_new, axes_new), target)
        if not (np.all(np.isfinite(ms_t)) and _spd(css_t) and _spd(czz_t)) and not self.lost:
            d = 2 + self.nz
            wide = np.eye(d) * max(self.cfg.widen_min_sigma, 1.0) ** 2
            self.w, self.mu, self.P, self.centre, self.axes = self._gaussian(
                np.zeros(d), wide, np.zeros(2))
            self.lost = True
        self.q_next = np.diag(qs + E @ P @ E.T).copy()
        A = np.block([[np.eye(2), E], [np.zeros((self.nz, 2)), F]])
        self.open_mean = A @ self.open_mean + np.concatenate([u_shift, np.zeros(self.nz)])
        self.open_cov = _sym(A @ self.open_cov @ A.T + np.block(
            [[qs, np.zeros((2, self.nz))], [np.zeros((self.nz, 2)), qz]]))

    # ------------------------------------------------------------------ update
    def points(self) -> np.ndarray:
        """``(G, G, 2)`` cell coordinates."""
        o = self.off
        return (self.centre[None, None, :] + self.axes[None, None, :, 0] * o[None, :, None]
                + self.axes[None, None, :, 1] * o[:, None, None])

    def update(self, y: float, g: np.ndarray, R: float,
               cell_variance: np.ndarray | None = None) -> dict[str, float]:
        """Measurement update ``y = g(s) + c·z + e`` (``g (G, G)`` at the cells, NaN: zero
        likelihood), the lost-track test, then the regrid.

        Returns:
            ``nis`` and ``innovation`` of the predicted mixture (NaN when not applied),
            ``log_likelihood``, ``applied``, ``recovered``.
        """
        c, P, w, mu = self.c, self.P, self.w, self.mu
        s = float(c @ P @ c + R)  # S = cᵀPc + R, every cell
        yc = g + np.einsum("z,zij->ij", c, mu)
        nu = y - yc
        ok = np.isfinite(nu)
        w_ok = np.where(np.isfinite(yc), w, 0.0)
        yc0 = np.where(np.isfinite(yc), yc, 0.0)
        mass = max(w_ok.sum(), _TINY)
        yhat = (w_ok * yc0).sum() / mass
        s_y = (w_ok * (yc0 - yhat) ** 2).sum() / mass + s
        innov = y - yhat
        nis = innov * innov / s_y
        nu = np.where(ok, nu, 0.0)
        if cell_variance is None:
            loglik = -0.5 * nu * nu / s
        else:
            cv = np.maximum(cell_variance, 0.0)
            loglik = -0.5 * (nu * nu / (cv + s) + np.log1p(cv / s))
        loglik = np.where(ok, loglik, -np.inf)
        with np.errstate(divide="ignore"):
            logw = np.where(w > 0, np.log(np.where(w > 0, w, 1.0)), -np.inf) + loglik
        peak = logw.max()
        out = {"nis": math.nan, "innovation": math.nan, "log_likelihood": -math.inf,
               "applied": False, "recovered": False}
        if not math.isfinite(y):
            self._lost_test(math.nan, False)
            self.regrid()
            return out
        wn = _exp_or_zero(logw - (peak if math.isfinite(peak) else 0.0))
        total = wn.sum()
        if not (math.isfinite(peak) and total > 0 and math.isfinite(total)):
            out["recovered"] = True  # the likelihood vanished everywhere: keep the prior
            self._lost_test(math.nan, False)
            self.regrid()
            return out
        out.update(log_likelihood=-0.5 * (_LOG_2PI + math.log(s)) + peak + math.log(total),
                   applied=True, nis=nis, innovation=innov)
        wn = wn / total
        if self.cfg.weight_floor > 0:
            wn = np.maximum(wn, self.cfg.weight_floor * wn.max())
            wn = wn / wn.sum()
        gain = P @ c / s  # K = P c / S
        self.w = wn
        self.mu = mu + gain[:, None, None] * nu[None]
        self.P = _sym(P - np.outer(gain, gain) * s)
        self._lost_test(nis, True)
        self.regrid()
        return out

    def _lost_test(self, nis: float, applied: bool) -> None:
        """The mean NIS of the last ``lost_window`` updates above ``χ²_p(W)/W`` widens the
        lattice: around the mean (``local_widenings`` times), then to the open-loop prior."""
        cfg = self.cfg
        if cfg.lost_window <= 0:
            return
        slot = self.step % cfg.lost_window
        self.step += 1
        if applied:
            self.nis_win[slot] = nis
            self.nis_count += 1
        thr = chi2_mean_threshold(cfg.lost_prob, cfg.lost_window)
        if self.nis_count >= cfg.lost_window and self.nis_win.mean() > thr and not self.lost:
            mean, cov = self.moments()
            d = cov.shape[0]
            infl = cov.copy()
            infl[:2, :2] = cov[:2, :2] * cfg.widen_factor**2 + np.eye(2) * cfg.widen_min_sigma**2
            infl = _sym(infl + 1e-9 * np.eye(d))
            if not _spd(infl):
                infl = np.eye(d)
            if self.widenings >= cfg.local_widenings:
                mean, infl = self.open_mean, self.open_cov
            self.w, self.mu, self.P, self.centre, self.axes = self._gaussian(mean, infl,
                                                                              np.zeros(2))
            self.widenings += 1
            self.nis_count = 0
            self.lost = self.widenings > cfg.max_widenings

    # ------------------------------------------------------------------ regrid
    def regrid(self) -> bool:
        """Moves the run to a lattice centred on its mean, sized for ``± span_sigma σ``, when
        its mean left the central ``recentre_fraction``, its ``± regrid_sigma σ`` box pokes
        out, the lattice is ``resize_ratio`` too wide (not at ``min_half_width``) or the
        principal axes turned (``|ρ| > 0.5``); moments kept exactly. Returns whether it
        moved."""
        cfg, h = self.cfg, self.h
        lm = self._refit_thin()
        u, cu, mz, czu, czz_b = lm
        axes, centre = self.axes, self.centre
        ia = np.linalg.inv(axes)
        sig = np.sqrt(np.maximum(np.diag(cu), 0.0))
        qc = np.diag(ia @ np.diag(self.q_next) @ ia.T)
        need = cfg.span_sigma * np.sqrt(sig**2 + qc)
        box = need * (1.0 if cfg.regrid_sigma is None else cfg.regrid_sigma / cfg.span_sigma)
        too_coarse = np.any(need * cfg.resize_ratio < h)
        if cfg.min_half_width > 0:
            floor_cells = cfg.min_half_width / np.linalg.norm(axes, axis=0)
            too_coarse = too_coarse and not np.all(floor_cells >= h * (1 - 1e-6))
        move = (np.any(np.abs(u) > cfg.recentre_fraction * h)
                or np.any(np.abs(u) + box > h * (1 + 1e-6)) or too_coarse
                or not np.all(np.isfinite(need)))
        if cfg.principal_axes:
            move = move or abs(cu[0, 1] / max(sig[0] * sig[1], 1e-300)) > 0.5
        if not (move and _spd(cu)):
            return False
        ms, css, _, czz, czs = self._state_moments(lm, self.P, centre, axes)
        c_n, a_n = self._lattice_for(ms, css, self.q_next)
        # the new cells in the old lattice's coordinates, normalised to −1 … 1
        o = self.off
        base, lin = ia @ (c_n - centre), ia @ a_n
        px = (base[0] + lin[0, 0] * o[None, :] + lin[0, 1] * o[:, None]) / h
        py = (base[1] + lin[1, 0] * o[None, :] + lin[1, 1] * o[:, None]) / h
        log_r = np.log(np.maximum(self.w, _TINY)) - self._log_gauss(u, cu)
        log_r = np.maximum(log_r - log_r.max(), _LOG_R_FLOOR)
        gzu = np.linalg.solve(cu, czu.T).T
        resid = self.mu - mz[:, None, None] - self._affine(gzu, u)
        out = _bilinear_border(np.concatenate([log_r[None], resid], 0), px, py)
        ia_n = np.linalg.inv(a_n)
        w_n = _normalised(out[0] + self._log_gauss(np.zeros(2), _sym(ia_n @ css @ ia_n.T)))
        mu_n = out[1:] + mz[:, None, None] + self._affine(czs @ np.linalg.solve(css, a_n),
                                                          np.zeros(2))
        self.w, self.mu, self.P, self.centre, self.axes = self._matched(
            (w_n, mu_n, self.P, c_n, a_n), (ms, css, mz, czz, czs))
        self.regrids += 1
        return True


def _joint(ms: np.ndarray, css: np.ndarray, mz: np.ndarray, czz: np.ndarray,
           czs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of ``[s, z]`` from the blocks."""
    return np.concatenate([ms, mz]), _sym(np.block([[css, czs.T], [czs, czz]]))


def _thin(cu: np.ndarray) -> bool:
    """The masses' smallest eigenvalue (cells²) below 0.25."""
    return bool(np.linalg.eigvalsh(cu)[0] < _MIN_CELL_VARIANCE)


def _normalised(logw: np.ndarray) -> np.ndarray:
    w = _exp_or_zero(logw - logw.max())
    return w / w.sum()


def _kernel(sigma: float, half_len: int) -> np.ndarray:
    """The 1-D transition kernel of ``sigma`` cells: a sampled, normalised Gaussian for
    ``σ ≥ 0.7``; else ``[σ²/2, 1 − σ², σ²/2]`` (exact variance)."""
    k = np.arange(-half_len, half_len + 1, dtype=np.float64)
    s = max(sigma, 1e-6)
    if sigma >= _GAUSS_MIN_CELLS:
        g = np.exp(-0.5 * (k / s) ** 2)
        return g / g.sum()
    tap = np.zeros_like(k)
    v = min(s * s, 0.5)
    tap[half_len], tap[half_len - 1], tap[half_len + 1] = 1.0 - v, 0.5 * v, 0.5 * v
    return tap


def _convolve(x: np.ndarray, kernel: np.ndarray, axis: int) -> np.ndarray:
    """Zero-padded convolution of ``x`` along ``axis`` (``out[j] = Σ_t k[t] x[j − t + L]``)."""
    half = (kernel.size - 1) // 2
    g = x.shape[axis]
    out = x * kernel[half]
    for t, k in enumerate(kernel):
        o = t - half
        if o == 0 or abs(o) >= g or k == 0.0:
            continue
        dst = [slice(None)] * x.ndim
        src = [slice(None)] * x.ndim
        dst[axis] = slice(max(o, 0), g + min(o, 0))
        src[axis] = slice(max(-o, 0), g - max(o, 0))
        out[tuple(dst)] += k * x[tuple(src)]
    return out


def _bilinear_border(chans: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``chans (C, G, G)`` at normalised coordinates ``px, py``
    (−1 … 1 from the first to the last cell, clamped to the border)."""
    g = chans.shape[-1]
    x = np.clip((px + 1.0) * 0.5 * (g - 1), 0.0, g - 1.0)
    y = np.clip((py + 1.0) * 0.5 * (g - 1), 0.0, g - 1.0)
    x0 = np.minimum(np.floor(x), g - 2).astype(np.int64)
    y0 = np.minimum(np.floor(y), g - 2).astype(np.int64)
    fx, fy = x - x0, y - y0
    v00, v01 = chans[:, y0, x0], chans[:, y0, x0 + 1]
    v10, v11 = chans[:, y0 + 1, x0], chans[:, y0 + 1, x0 + 1]
    return (v00 * (1 - fx) + v01 * fx) * (1 - fy) + (v10 * (1 - fx) + v11 * fx) * fy
