"""Loosely coupled GNSS/INS: the 15-state ψ-angle error-state EKF, batched over N runs.

The system of paper 003 (SEEDS 003): the strapdown mechanisation runs at the IMU rate on
bias-corrected measurements; the error covariance is propagated with
``Φ = I + FT + (FT)²/2`` and ``Q_d`` every ``propagate_every`` IMU samples and at each GNSS
epoch; a GNSS epoch updates the 15-state error with the 6 lever-arm position and velocity
differences (predicted − measured); the estimated errors are fed back into the solution
and the bias estimates (closed loop) and the error state is reset to zero.

All N runs advance together on `BatchedEKF` (per-sample
``(N, 15, 15)`` Φ, ``Q_d`` and ``(N, 6, 15)`` H). Runs do not interact: an epoch without
a solution (outage, NaN quality σ, a NaN measurement of one run) is skipped for the runs
concerned through the update mask and counted.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters import BatchedEKF
from neuralmap.filters.policies.compose import quality_members
from neuralmap.filters.policy import FilterPolicy
from neuralmap.ins.covariance_kernels import propagate_block
from neuralmap.ins.error_model import (
    process_noise_density,
)
from neuralmap.ins.error_state import correct, inject, navigation_error, total_attitude_error
from neuralmap.ins.gnss import GnssRecord, sanitize_quality
from neuralmap.ins.imu_model import ImuErrorProcess, ImuGrade, imu_grade
from neuralmap.ins.kernels import mechanize_block
from neuralmap.ins.measurement import check_lever_arm, gnss_measurement_model
from neuralmap.ins.trajectory import Trajectory, check_continuity

__all__ = ["LooselyCoupledConfig", "LooselyCoupledResult", "LooselyCoupledVariant",
           "initial_covariance", "run_loosely_coupled", "run_loosely_coupled_variants"]

_DEG = math.pi / 180.0


@dataclass(frozen=True)
class LooselyCoupledConfig:
    """Filter settings.

    Attributes:
        grade: IMU grade assumed by the filter (Q and initial bias variances).
        propagate_every: IMU samples per covariance propagation (≥ 1).
        init_pos_sigma: Initial NED position σ (m).
        init_vel_sigma: Initial NED velocity σ (m/s).
        init_att_sigma_deg: Initial roll, pitch, heading σ (deg).
        use_velocity: Use the GNSS velocity (m = 6) or position only (m = 3).
        r_scale: Factor on the reported σ (R = diag((r_scale σ)²)).
        lever_arm: Lever arm the filter assumes (None = the record's true one).
    """

    grade: str | ImuGrade = "tactical_mems"
    propagate_every: int = 10
    init_pos_sigma: tuple[float, float, float] = (0.05, 0.05, 0.1)
    init_vel_sigma: tuple[float, float, float] = (0.02, 0.02, 0.02)
    init_att_sigma_deg: tuple[float, float, float] = (0.1, 0.1, 0.5)
    use_velocity: bool = True
    r_scale: float = 1.0
    lever_arm: tuple[float, float, float] | None = None

    def validate(self) -> LooselyCoupledConfig:
        """Checks the settings; returns self.

        Raises:
            NeuralMapError: Non-positive σ, interval or scale, or a bad lever arm.
        """
        imu_grade(self.grade)
        if not (isinstance(self.propagate_every, int) and self.propagate_every >= 1):
            raise NeuralMapError(
                f"LooselyCoupledConfig: 'propagate_every' = {self.propagate_every!r} must be an "
                "integer >= 1 (IMU samples per covariance propagation)."
            )
        for name in ("init_pos_sigma", "init_vel_sigma", "init_att_sigma_deg"):
            value = getattr(self, name)
            if len(value) != 3 or not all(math.isfinite(v) and v > 0 for v in value):
                raise NeuralMapError(
                    f"LooselyCoupledConfig: '{name}' = {value!r} must be three finite "
                    "values > 0."
                )
        if not (math.isfinite(self.r_scale) and self.r_scale > 0):
            raise NeuralMapError(
                f"LooselyCoupledConfig: 'r_scale' = {self.r_scale!r} must be finite and > 0."
            )
        if self.lever_arm is not None:
            check_lever_arm(self.lever_arm, where="LooselyCoupledConfig")
        return self


@dataclass
class LooselyCoupledResult:
    """Errors and covariances at the GNSS epochs (after the update where one applied).

    Attributes:
        time: ``(K,)`` epochs (s).
        position_error: ``(N, K, 3)`` NED position error of the IMU (m), computed − true.
        velocity_error: ``(N, K, 3)`` NED velocity error (m/s).
        attitude_error: ``(N, K, 3)`` total attitude error φ (rad, NED axes; ≈ roll,
            pitch, heading errors for a level vehicle).
        std: ``(N, K, 15)`` filter standard deviations.
        nees_position: ``(N, K)`` position NEES (3 degrees of freedom).
        nees_navigation: ``(N, K)`` NEES of ``[δr, δv, ψ]`` (9 degrees of freedom).
        nis: ``(N, K)`` NIS of the update (NaN where none applied).
        applied: ``(N, K)`` update applied.
        healthy: ``(N,)`` filter health at the end.
        counts: Counted treatments (skipped epochs, sanitised quality indicators, runs
            frozen after their solution became non-finite: ``failed_runs``, samples the
            filter froze when their covariance lost positive definiteness:
            ``frozen_samples``).
        elapsed_s: Wall time of this filter (s), without the IMU simulation.
    """

    time: torch.Tensor
    position_error: torch.Tensor
    velocity_error: torch.Tensor
    attitude_error: torch.Tensor
    std: torch.Tensor
    nees_position: torch.Tensor
    nees_navigation: torch.Tensor
    nis: torch.Tensor
    applied: torch.Tensor
    healthy: torch.Tensor
    counts: dict[str, int] = field(default_factory=dict)
    elapsed_s: float = 0.0




def _guard(
    y: torch.Tensor, y_good: torch.Tensor, failed: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Freezes runs whose solution left the valid domain (non-finite, |lat| ≥ 89°).

    A run that diverged that far (e.g. after a huge correction) is marked in ``failed``
    (in place; reported as unhealthy and counted) and keeps its last valid solution, so
    that it cannot stop the batch with NaN in the shared tensors.

    Returns:
        ``(y, new last-good y)``.
    """
    bad = ~torch.isfinite(y).all(1) | (y[:, 0].abs() >= math.radians(89.0))
    if bool(bad.any()):
        failed |= bad
        y = torch.where(bad[:, None], y_good, y)
    return y, y


def _freeze_overflow(
    P: torch.Tensor, phi: torch.Tensor, qd: torch.Tensor, P_old: torch.Tensor,
    failed: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Runs whose error model overflowed (a diverged run's huge bias estimate or solution)
    are marked in ``failed`` (in place) and keep their covariance (Φ = I, Q = 0)."""
    ok = (torch.isfinite(phi).flatten(1).all(1) & torch.isfinite(qd).flatten(1).all(1)
          & torch.isfinite(P).flatten(1).all(1))
    if bool(ok.all()):
        return P, phi, qd
    failed |= ~ok
    keep = ok.reshape(-1, 1, 1)
    eye = torch.eye(phi.shape[-1], dtype=phi.dtype, device=phi.device)
    return (torch.where(keep, P, P_old), torch.where(keep, phi, eye),
            torch.where(keep, qd, 0.0))


def initial_covariance(config: LooselyCoupledConfig, *, dtype: torch.dtype) -> torch.Tensor:
    """``P0`` ``(15, 15)``: configured navigation σ, bias σ² = turn-on² + instability²."""
    g = imu_grade(config.grade)
    sig_bg = math.hypot(g.gyro_turn_on_si, g.gyro_bias_sigma_si)
    sig_ba = math.hypot(g.accel_turn_on_si, g.accel_bias_sigma_si)
    diag = (list(config.init_pos_sigma) + list(config.init_vel_sigma)
            + [a * _DEG for a in config.init_att_sigma_deg] + [sig_bg] * 3 + [sig_ba] * 3)
    return torch.diag(torch.tensor(diag, dtype=dtype) ** 2)


@dataclass
class LooselyCoupledVariant:
    """One filter of a lockstep run (`run_loosely_coupled_variants`).

    Attributes:
        config: Filter settings.
        policy: Optional update policy (see `run_loosely_coupled`).
        measurement_noise: Optional ``(epoch index, base R) -> R`` hook.
    """

    config: LooselyCoupledConfig
    policy: FilterPolicy | None = None
    measurement_noise: Callable[[int, torch.Tensor], torch.Tensor] | None = None


class _ClosedLoop:
    """The closed-loop error-state EKF of one variant over the N runs (state between
    blocks); the IMU samples come from outside, shared by every variant."""

    def __init__(self, traj: Trajectory, gnss: GnssRecord, quality: Any, counts: dict[str, int],
                 variant: LooselyCoupledVariant, draw0: torch.Tensor,
                 epoch_of: dict[int, int]) -> None:
        config = variant.config.validate()
        self.config, self.policy = config, variant.policy
        self.measurement_noise = variant.measurement_noise
        self.traj, self.gnss, self.quality = traj, gnss, quality
        self.epoch_of = epoch_of
        self.elapsed_s = 0.0
        n = draw0.shape[0]
        self.n = n
        dtype = traj.states.dtype
        device = traj.states.device
        kw = {"dtype": dtype, "device": device}
        self.counts = dict(counts)
        grade = imu_grade(config.grade)
        self.arm = (gnss.lever_arm if config.lever_arm is None
                    else check_lever_arm(config.lever_arm, where="run_loosely_coupled")).to(**kw)
        self.qc = process_noise_density(grade).to(dtype=dtype, device=device)
        self.tau_g, self.tau_a = grade.gyro_corr_time, grade.accel_corr_time
        p0 = initial_covariance(config, dtype=dtype).to(device)
        chol = torch.linalg.cholesky(p0[:9, :9])
        e0 = draw0.to(device) @ chol.T
        self.y = inject(traj.states[0].expand(n, 10), e0)
        self.ekf = BatchedEKF(torch.zeros(n, 15, **kw), p0)
        self.zeros = torch.zeros(n, 15, **kw)
        self.bg_hat = torch.zeros(n, 3, **kw)
        self.ba_hat = torch.zeros(n, 3, **kw)
        self.m = 6 if config.use_velocity else 3
        k_epochs = quality.n_epochs
        self.out = {name: torch.full((n, k_epochs, 3), math.nan, **kw)
                    for name in ("pos", "vel", "att")}
        self.std = torch.full((n, k_epochs, 15), math.nan, **kw)
        self.nees_p = torch.full((n, k_epochs), math.nan, **kw)
        self.nees_n = torch.full((n, k_epochs), math.nan, **kw)
        self.nis = torch.full((n, k_epochs), math.nan, **kw)
        self.applied = torch.zeros(n, k_epochs, dtype=torch.bool, device=device)
        self.counts["skipped_epochs"] = 0
        self.quality_takers = quality_members(self.policy)
        if self.policy is not None:
            self.policy.reset()
        self.counts["nan_measurements"] = 0
        self.failed = torch.zeros(n, dtype=torch.bool, device=device)
        self.y_good = self.y

    def record(self, j: int, k: int) -> None:
        n, y = self.n, self.y
        truth = self.traj.states[k].expand(n, 10)
        err = navigation_error(truth, y)
        self.out["pos"][:, j] = err[:, :3]
        self.out["vel"][:, j] = y[:, 3:6] - truth[:, 3:6]
        self.out["att"][:, j] = total_attitude_error(truth, y)
        P = self.ekf.P
        self.std[:, j] = P.diagonal(dim1=-2, dim2=-1).sqrt()
        pr = torch.linalg.cholesky_ex(P[:, :3, :3])[0]
        w = torch.linalg.solve_triangular(pr, err[:, :3, None], upper=False)
        self.nees_p[:, j] = w.square().sum((-2, -1))
        pn = torch.linalg.cholesky_ex(P[:, :9, :9])[0]
        w = torch.linalg.solve_triangular(pn, err[:, :, None], upper=False)
        self.nees_n[:, j] = w.square().sum((-2, -1))

    def update(self, j: int, gyro: torch.Tensor) -> None:
        quality, gnss, config, n, m = self.quality, self.gnss, self.config, self.n, self.m
        y = self.y
        valid = bool(quality.valid[j])
        if not valid:
            self.counts["skipped_epochs"] += 1
            return
        pos, vel = gnss.position[:, j], gnss.velocity[:, j]
        finite = torch.isfinite(pos).all(-1) & torch.isfinite(vel).all(-1)
        self.counts["nan_measurements"] += int((~finite).sum())
        pos = torch.where(finite[:, None], pos, y[:, :3])
        vel = torch.where(finite[:, None], vel, y[:, 3:6])
        resid, H = gnss_measurement_model(y, gyro, self.arm, pos, vel)
        sig = torch.cat([quality.sigma_pos[j], quality.sigma_vel[j]]) * config.r_scale
        R = torch.diag(sig[:m].square())
        if self.measurement_noise is not None:
            R = self.measurement_noise(j, R)
        if self.quality_takers:
            sig_h = quality.sigma_pos[j, :2].square().mean().sqrt()
            indicators = {name: value.expand(n) for name, value in (
                ("pdop", quality.pdop[j]), ("fix_ratio", quality.fix_ratio[j]),
                ("satellites", quality.n_sats[j]), ("sigma_m", sig_h))}
            for taker in self.quality_takers:
                taker.set_quality(indicators)
        ekf = self.ekf
        diag = ekf.update(resid[:, :m], H[:, :m], R, mask=finite, policy=self.policy)
        self.nis[:, j] = torch.where(diag.applied, diag.nis, math.nan)
        self.applied[:, j] = diag.applied
        x = ekf.x
        y = correct(y, x[:, :9])
        self.y, self.y_good = _guard(y, self.y_good, self.failed)
        self.bg_hat = self.bg_hat - x[:, 9:12]
        self.ba_hat = self.ba_hat - x[:, 12:15]
        ekf.x = self.zeros

    def first(self, raw_g: torch.Tensor) -> None:
        """The epoch at sample 0 (if any), on the first measured sample."""
        tick = time.perf_counter()
        if 0 in self.epoch_of:
            self.update(self.epoch_of[0], raw_g - self.bg_hat)
            self.record(self.epoch_of[0], 0)
        self.elapsed_s += time.perf_counter() - tick

    def block(self, gyro: torch.Tensor, accel: torch.Tensor, start: int, end: int) -> None:
        """Advances over samples ``start … end`` (``gyro``/``accel``: ``(N, L + 1, 3)``
        measured samples, the first one that of ``start``); updates at ``end`` if an
        epoch falls there."""
        tick = time.perf_counter()
        dt = self.traj.dt
        device = self.traj.states.device
        ekf = self.ekf
        every = self.config.propagate_every
        stops = list(range(every, end - start, every))
        j = self.epoch_of.get(end)
        if j is not None:  # every epoch is a propagation point
            stops.append(end - start)
        states, y, y_good = mechanize_block(self.y, self.y_good, self.failed, gyro, accel,
                                            self.bg_hat, self.ba_hat, dt, stops)
        states, self.y, self.y_good = states.to(device), y.to(device), y_good.to(device)
        if stops:
            f_stops = accel[:, stops] - self.ba_hat[:, None]
            intervals = [(b - a) * dt for a, b in zip([0, *stops], stops, strict=False)]
            # all but the last point here; the last one is the filter's predict (health
            # check, and the process noise that policies read)
            P, phi, qd = propagate_block(ekf.P, ekf.healthy, states, f_stops, intervals,
                                         self.qc, self.tau_g, self.tau_a)
            P, phi, qd = _freeze_overflow(P, phi, qd, ekf.P, self.failed)
            if len(stops) > 1:
                ekf.P = P
            ekf.predict(phi, qd, trusted_noise=True)  # Q_d: finite (frozen runs: 0), symmetric
        if j is not None:
            self.update(j, gyro[:, -1] - self.bg_hat)
            self.record(j, end)
        self.elapsed_s += time.perf_counter() - tick

    def result(self) -> LooselyCoupledResult:
        counts = self.counts
        counts["failed_runs"] = int(self.failed.sum())
        # samples the filter froze (P or S lost positive definiteness, non-finite values)
        counts["frozen_samples"] = int((~self.ekf.healthy).sum())
        return LooselyCoupledResult(
            time=self.quality.time, position_error=self.out["pos"],
            velocity_error=self.out["vel"], attitude_error=self.out["att"], std=self.std,
            nees_position=self.nees_p, nees_navigation=self.nees_n, nis=self.nis,
            applied=self.applied, healthy=self.ekf.healthy & ~self.failed, counts=counts,
            elapsed_s=self.elapsed_s,
        )


def run_loosely_coupled(
    traj: Trajectory,
    imu: ImuErrorProcess,
    gnss: GnssRecord,
    config: LooselyCoupledConfig,
    *,
    generator: torch.Generator,
    measurement_noise: Callable[[int, torch.Tensor], torch.Tensor] | None = None,
    policy: FilterPolicy | None = None,
    progress: Callable[[int], None] | None = None,
) -> LooselyCoupledResult:
    """Runs the closed-loop error-state EKF over a drive for the N runs of ``imu``.

    Args:
        traj: Reference trajectory (truth and true IMU record).
        imu: IMU error process of the N runs (advanced in place).
        gnss: GNSS record of the same N runs (epochs on IMU samples).
        config: Filter settings.
        generator: Draws the initial navigation errors from ``P0``.
        measurement_noise: Optional ``(epoch index, base R (m, m)) -> R`` hook (shared
            ``(m, m)`` or per-run ``(N, m, m)``), e.g. a quality-based R; default: the
            reported σ times ``r_scale``.
        policy: Optional update policy of the batched Kalman core (adaptive factor on
            ``P⁻``, robust R...), passed to every GNSS update. A policy with
            ``set_quality`` (a quality-based R, or a composition holding one) receives the
            epoch's indicators before each update as a mapping of ``(N,)`` tensors:
            ``pdop``, ``fix_ratio``, ``satellites`` and ``sigma_m`` (the reported horizontal
            position σ, RMS of north and east), after NaN treatment
            (`sanitize_quality`).
        progress: Optional callback, called with the number of IMU samples advanced after
            each stretch between GNSS epochs (e.g. a progress bar's ``update``).

    Returns:
        `LooselyCoupledResult`.

    Raises:
        NeuralMapError: Bad config, run counts that differ, GNSS epochs out of order, a
            trajectory with a discontinuity.

    Device: everything runs on the trajectory's device (``traj.to(device)``); the IMU
    process and the GNSS record must live there too.
    """
    variant = LooselyCoupledVariant(config, policy=policy, measurement_noise=measurement_noise)
    return run_loosely_coupled_variants(traj, imu, gnss, {"filter": variant},
                                        generator=generator, progress=progress)["filter"]


def run_loosely_coupled_variants(
    traj: Trajectory,
    imu: ImuErrorProcess,
    gnss: GnssRecord,
    variants: dict[str, LooselyCoupledVariant],
    *,
    generator: torch.Generator,
    progress: Callable[[int], None] | None = None,
) -> dict[str, LooselyCoupledResult]:
    """Several filters over the same runs in lockstep: the IMU samples of each stretch
    between GNSS epochs are drawn once and fed to every filter.

    Each filter gets exactly the numbers `run_loosely_coupled` would give it on a
    generator in the same state (the initial-error draw, then the IMU samples, are the same
    for every variant), at the cost of one IMU simulation for all of them.

    Args:
        traj, imu, gnss, generator: As in `run_loosely_coupled`.
        variants: Name to filter (settings and policy); policies must be distinct objects.
        progress: Optional callback, called with (IMU samples advanced) × (filters) after
            each stretch.

    Returns:
        Name to `LooselyCoupledResult` (``elapsed_s``: that filter's own time,
        without the shared IMU simulation).

    Raises:
        NeuralMapError: As `run_loosely_coupled`; no variants; a policy shared by two.
    """
    if not variants:
        raise NeuralMapError("run_loosely_coupled_variants: pass at least one variant.")
    policies = [id(v.policy) for v in variants.values() if v.policy is not None]
    if len(set(policies)) != len(policies):
        raise NeuralMapError(
            "run_loosely_coupled_variants: two variants share one policy object; a policy "
            "keeps state (windows, factors), so build one per variant."
        )
    for v in variants.values():
        v.config.validate()
    n = imu.n_runs
    if gnss.position.shape[0] != n:
        raise NeuralMapError(
            f"run_loosely_coupled: the GNSS record has {gnss.position.shape[0]} runs but the "
            f"IMU process has {n}; simulate both with the same n_runs."
        )
    dtype = traj.states.dtype
    check_continuity(traj)
    quality, counts = sanitize_quality(gnss.quality)
    index = quality.imu_index.tolist()
    if any(b <= a for a, b in zip(index, index[1:], strict=False)) or (
            index and (index[0] < 0 or index[-1] >= traj.n_samples)):
        raise NeuralMapError(
            "run_loosely_coupled: the GNSS epochs' IMU sample indices must increase strictly "
            f"and lie in [0, {traj.n_samples - 1}]; got {index[:5]}... Rebuild the record "
            "against this trajectory (simulate_gnss) or sort it by time."
        )
    epoch_of = {int(i): j for j, i in enumerate(index)}
    draw0 = torch.randn(n, 9, generator=generator, dtype=dtype)
    filters = {name: _ClosedLoop(traj, gnss, quality, counts, v, draw0, epoch_of)
               for name, v in variants.items()}
    raw_g, raw_a = imu.measure(traj.gyro[0], traj.accel[0])
    for f in filters.values():
        f.first(raw_g)
    with torch.no_grad():
        # One block per stretch between GNSS epochs: IMU samples, mechanisation and the
        # covariance propagation of the whole stretch at once (the same numbers as one
        # IMU sample at a time; see propagate_block).
        ends = [k for k in index if k > 0]
        if not ends or ends[-1] != traj.n_samples - 1:
            ends.append(traj.n_samples - 1)
        start = 0
        for end in ends:
            new_g, new_a = imu.measure_block(traj.gyro[start + 1:end + 1],
                                             traj.accel[start + 1:end + 1])
            gyro = torch.cat([raw_g[:, None], new_g], 1)
            accel = torch.cat([raw_a[:, None], new_a], 1)
            for f in filters.values():
                f.block(gyro, accel, start, end)
            raw_g, raw_a = gyro[:, -1], accel[:, -1]
            if progress is not None:
                progress((end - start) * len(filters))
            start = end
    return {name: f.result() for name, f in filters.items()}
