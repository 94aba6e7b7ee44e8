"""The 15-state loosely coupled filter on a recorded GNSS/INS log (KF-GINS formats).

The simulator-driven filter (`neuralmap.ins.loosely_coupled.run_loosely_coupled`)
corrupts a true IMU record; a log carries measured increments and no truth. This driver
runs the same filter — the same mechanisation (`
strapdown_step`), error model (`error_dynamics`,
`discretize`), lever-arm measurement model
(`gnss_measurement_model`), closed-loop feedback
(`correct`) and `BatchedEKF` —
on an `ImuLog` and a `GnssLog`
(SEEDS 003), and records the solution itself.

An increment ``Δθ_k`` over ``(t_{k−1}, t_k]`` enters the mechanisation as the constant rate
``Δθ_k / Δt_k`` over that interval (the increment is kept exactly). A logging gap
(`read_imu`'s ``max_gap``) is propagated across as one interval of its true length with
the increments that bridge it (`bridge_gaps`): the rate of the record after the gap held
over the whole gap when that record holds one nominal interval's increments (the KF-GINS
format), its increments as they are when they were accumulated over the gap; gaps are
counted in `LogSolution.counts`. A GNSS epoch updates at its own time: the IMU
interval that holds it is split there, each part with its share of the increment, as
KF-GINS does (`neuralmap.ins.epoch_alignment`); the solution is recorded at the IMU
records only. Run 0 processes the log as recorded from the configured
initial state; with ``n_runs > 1`` the other runs draw an initial error from ``P0``, white
IMU noise at the configured ARW/VRW and GNSS noise at the reported σ (a Monte Carlo of the
spread the noise model implies), all batched.

The log is processed in blocks between GNSS epochs: the mechanisation of all the block's
increments and the covariance propagation over its propagation points (every
``propagate_every`` records from the block start and at the epoch) run in compiled loops
(`neuralmap.ins.increment_kernels`), giving the numbers of a record-by-record loop
(the tests check them against stored ones to 1e-9 relative).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters import BatchedEKF
from neuralmap.ins.covariance_kernels import propagate_block
from neuralmap.ins.earth import position_offset_ned, radii
from neuralmap.ins.epoch_alignment import split_at_epochs
from neuralmap.ins.error_model import (
    process_noise_density,
)
from neuralmap.ins.error_state import correct, inject, total_attitude_error
from neuralmap.ins.imu_model import ImuGrade
from neuralmap.ins.increment_kernels import mechanize_increments, propagate_with_sigma
from neuralmap.ins.kfgins import GAP_FACTOR, GnssLog, ImuLog, NavLog, bridge_gaps
from neuralmap.ins.loosely_coupled import LooselyCoupledConfig, initial_covariance
from neuralmap.ins.measurement import antenna_velocity, check_lever_arm, gnss_measurement_model
from neuralmap.ins.rotation import dcm_from_quat, euler_from_dcm, quat_from_euler

__all__ = ["LogSolution", "compare_with_reference", "run_on_log"]

_DEG = 180.0 / math.pi


@dataclass
class LogSolution:
    """Filter output on a log at the recorded IMU epochs.

    Attributes:
        time: ``(K,)`` s.
        states: ``(N, K, 10)`` packed solutions ``[lat, lon, h, v_NED, q(C_b^n)]``.
        std: ``(N, K, 15)`` filter σ.
        gyro_bias: ``(N, K, 3)`` estimated gyro biases (rad/s).
        accel_bias: ``(N, K, 3)`` estimated accelerometer biases (m/s²).
        counts: Updates applied (``updates``), of them between two IMU records
            (``gnss_between_records``), GNSS epochs outside the processed interval
            (``gnss_outside``), IMU records, logging gaps propagated over (``imu_gaps``, an
            interval > 1.5 nominal ones), of them bridged by holding the rate of the record
            after the gap (``imu_gaps_rate_held``; the others held accumulated
            increments), and the longest (``imu_longest_gap_s``), ….
    """

    time: torch.Tensor
    states: torch.Tensor
    std: torch.Tensor
    gyro_bias: torch.Tensor
    accel_bias: torch.Tensor
    counts: dict[str, int] = field(default_factory=dict)

    def nav_log(self, run: int = 0) -> NavLog:
        """One run as a `NavLog` (week 0)."""
        s = self.states[run].detach().cpu().double()
        euler = euler_from_dcm(dcm_from_quat(s[:, 6:10]))
        return NavLog(week=np.zeros(s.shape[0]), time=self.time.cpu().double().numpy(),
                      position=np.column_stack([np.degrees(s[:, 0:2].numpy()), s[:, 2].numpy()]),
                      velocity=s[:, 3:6].numpy(), euler=np.degrees(euler.numpy()))


def run_on_log(
    imu: ImuLog,
    gnss: GnssLog,
    *,
    grade: ImuGrade,
    initial_position: tuple[float, float, float],
    initial_velocity: tuple[float, float, float],
    initial_euler: tuple[float, float, float],
    lever_arm: tuple[float, float, float],
    filter_config: LooselyCoupledConfig,
    initial_gyro_bias: tuple[float, float, float] = (0.0, 0.0, 0.0),
    initial_accel_bias: tuple[float, float, float] = (0.0, 0.0, 0.0),
    start: float | None = None,
    end: float | None = None,
    n_runs: int = 1,
    output_every: int = 1,
    seed: int = 0,
    use_velocity: bool | None = None,
) -> LogSolution:
    """Runs the closed-loop 15-state error-state EKF over a recorded log.

    Args:
        imu: Increments (forward-right-down body axes).
        gnss: Antenna positions (and velocities) with σ.
        grade: The IMU noise model (Q and the initial bias σ).
        initial_position: lat, lon (rad), h (m) of the IMU at the first processed record.
        initial_velocity: NED (m/s).
        initial_euler: roll, pitch, yaw (rad).
        lever_arm: IMU-to-antenna vector (m, body frame).
        filter_config: Initial navigation σ, ``propagate_every``, ``r_scale`` (its
            ``grade``, ``lever_arm`` and ``use_velocity`` are not used here).
        initial_gyro_bias, initial_accel_bias: Starting bias estimates (rad/s, m/s²).
        start: First processed IMU time (s); None = the first record.
        end: Last processed IMU time (s); None = the last record.
        n_runs: Runs N (run 0 = the log as recorded; the others with noise draws).
        output_every: Record every this many IMU epochs (1 = all, as KF-GINS writes).
        seed: Seed of the noise draws.
        use_velocity: Update with the GNSS velocity too; None = when the log has one.

    Returns:
        `LogSolution`.

    Raises:
        NeuralMapError: Fewer than two IMU records in [start, end], a bad run count or
            output interval, two GNSS epochs on one IMU record, velocity asked but absent.
    """
    if not (isinstance(n_runs, int) and n_runs >= 1):
        raise NeuralMapError(f"run_on_log: n_runs = {n_runs!r} must be an integer >= 1.")
    if not (isinstance(output_every, int) and output_every >= 1):
        raise NeuralMapError(f"run_on_log: output_every = {output_every!r} must be an "
                             "integer >= 1.")
    if use_velocity is None:
        use_velocity = gnss.velocity is not None
    if use_velocity and gnss.velocity is None:
        raise NeuralMapError("run_on_log: use_velocity is set but the GNSS log has no velocity "
                             "(a 7-column file); use a 13-column file or use_velocity: false.")
    filter_config.validate()
    t_all = imu.time
    lo = 0 if start is None else int(np.searchsorted(t_all, start, side="left"))
    hi = t_all.shape[0] if end is None else int(np.searchsorted(t_all, end, side="right"))
    if hi - lo < 2:
        raise NeuralMapError(
            f"run_on_log: only {max(hi - lo, 0)} IMU record(s) between starttime {start} and "
            f"endtime {end} (the log covers {t_all[0]:.3f}–{t_all[-1]:.3f} s)."
        )
    kw = {"dtype": torch.float64}
    t_imu = t_all[lo:hi]
    real_steps = np.diff(t_imu)
    gaps = real_steps > GAP_FACTOR * imu.dt
    # a gap's missing increments: the rate of the record after it held over the gap
    bridged_dtheta, bridged_dvel, held = bridge_gaps(t_imu, imu.dtheta[lo:hi],
                                                     imu.dvel[lo:hi], imu.dt)
    # GNSS epochs at their own time: the IMU interval holding one is split there (KF-GINS)
    line = split_at_epochs(t_imu, bridged_dtheta, bridged_dvel, gnss.time)
    time = torch.as_tensor(line.time, **kw)
    steps = torch.diff(time)
    dtheta = torch.as_tensor(line.dtheta, **kw)
    dvel = torch.as_tensor(line.dvel, **kw)
    n_imu = time.shape[0]  # records of the time line (IMU records + inserted epochs)
    g_index = line.epoch_index
    epoch_of = {int(k): int(j) for k, j in zip(line.epoch_record, g_index, strict=True)}
    arm = check_lever_arm(lever_arm, where="run_on_log").to(**kw)
    gnss_position = np.column_stack([np.radians(gnss.position[:, :2]), gnss.position[:, 2]])
    qc = process_noise_density(grade)
    tau_g, tau_a = grade.gyro_corr_time, grade.accel_corr_time
    p0 = initial_covariance(LooselyCoupledConfig(
        grade=grade, init_pos_sigma=filter_config.init_pos_sigma,
        init_vel_sigma=filter_config.init_vel_sigma,
        init_att_sigma_deg=filter_config.init_att_sigma_deg), dtype=torch.float64)
    gen = torch.Generator().manual_seed(int(seed))
    n = n_runs
    draw = torch.ones(n, 1, **kw)
    draw[0] = 0.0  # run 0: the log as recorded
    quat0 = quat_from_euler(torch.tensor([initial_euler], **kw))
    start_state = torch.cat([torch.tensor([initial_position], **kw),
                             torch.tensor([initial_velocity], **kw), quat0], dim=1)
    e0 = torch.randn(n, 9, generator=gen, **kw) @ torch.linalg.cholesky(p0[:9, :9]).T
    y = inject(start_state.expand(n, 10), e0 * draw)
    ekf = BatchedEKF(torch.zeros(n, 15, **kw), p0)
    zeros = torch.zeros(n, 15, **kw)
    bg_hat = torch.tensor(initial_gyro_bias, **kw).expand(n, 3).clone()
    ba_hat = torch.tensor(initial_accel_bias, **kw).expand(n, 3).clone()
    white_g, white_a = grade.gyro_arw_si, grade.accel_vrw_si  # per √s
    m = 6 if use_velocity else 3
    real_index = np.nonzero(line.real)[0]  # time-line records of the IMU records
    rec_real = list(range(0, real_index.size, output_every))
    if rec_real[-1] != real_index.size - 1:
        rec_real.append(real_index.size - 1)
    rec = real_index[rec_real].tolist()
    slot = {k: i for i, k in enumerate(rec)}
    out_states = torch.empty(n, len(rec), 10, **kw)
    out_std = torch.empty(n, len(rec), 15, **kw)
    out_bg = torch.empty(n, len(rec), 3, **kw)
    out_ba = torch.empty(n, len(rec), 3, **kw)
    counts = {"gnss_epochs": int(g_index.size), "gnss_outside": int(gnss.n_epochs - g_index.size),
              "updates": 0, "imu_records": int(real_index.size),
              "gnss_between_records": line.n_split, "imu_gaps": int(gaps.sum()),
              "imu_gaps_rate_held": int(held.sum()),
              "imu_longest_gap_s": float(real_steps[gaps].max()) if gaps.any() else 0.0}

    def record(k: int) -> None:
        i = slot[k]
        out_states[:, i] = y
        out_std[:, i] = ekf.P.diagonal(dim1=-2, dim2=-1).sqrt()
        out_bg[:, i] = bg_hat
        out_ba[:, i] = ba_hat

    def update(j: int, gyro: torch.Tensor) -> None:
        nonlocal y, bg_hat, ba_hat
        sig_p = torch.as_tensor(gnss.sigma_pos[j], **kw)
        pos = torch.as_tensor(gnss_position[j], **kw).expand(n, 3)
        noise = torch.randn(n, 6, generator=gen, **kw) * draw
        rm, rn = radii(pos[:, 0])
        d_ned = noise[:, :3] * sig_p
        pos = torch.stack([pos[:, 0] + d_ned[:, 0] / (rm + pos[:, 2]),
                           pos[:, 1] + d_ned[:, 1] / ((rn + pos[:, 2]) * torch.cos(pos[:, 0])),
                           pos[:, 2] - d_ned[:, 2]], dim=1)
        if use_velocity:
            sig_v = torch.as_tensor(gnss.sigma_vel[j], **kw)
            vel = torch.as_tensor(gnss.velocity[j], **kw) + noise[:, 3:] * sig_v
            sig = torch.cat([sig_p, sig_v])
        else:
            vel = antenna_velocity(y, gyro, arm)  # unused rows
            sig = sig_p
        resid, H = gnss_measurement_model(y, gyro, arm, pos, vel)
        R = torch.diag((sig * filter_config.r_scale).square())
        ekf.update(resid[:, :m], H[:, :m], R)
        x = ekf.x
        y = correct(y, x[:, :9])
        bg_hat = bg_hat - x[:, 9:12]
        ba_hat = ba_hat - x[:, 12:15]
        ekf.x = zeros
        counts["updates"] += 1

    rate_g = dtheta / torch.cat([steps[:1], steps])[:, None]
    rate_a = dvel / torch.cat([steps[:1], steps])[:, None]
    if 0 in epoch_of:
        update(epoch_of[0], rate_g[0] - bg_hat)
    if 0 in slot:
        record(0)
    rec_index = np.asarray(rec)
    every = filter_config.propagate_every
    noisy = n > 1
    with torch.no_grad():
        # One block per stretch between GNSS epochs: mechanisation of all its IMU
        # intervals, then the covariance over its propagation points (every
        # ``propagate_every`` intervals from the block start and at the epoch), in compiled
        # loops (neuralmap.ins.increment_kernels); the same numbers as one record at a time.
        ends = sorted(k for k in epoch_of if k > 0)
        if not ends or ends[-1] != n_imu - 1:
            ends.append(n_imu - 1)
        begin = 0
        for end in ends:
            length = end - begin
            dts = steps[begin:end]
            gyro = rate_g[begin + 1:end + 1].expand(n, length, 3)
            accel = rate_a[begin + 1:end + 1].expand(n, length, 3)
            if noisy:
                noise = torch.randn(n, length, 6, generator=gen, **kw) * draw[:, :, None]
                root = dts.sqrt()[None, :, None]
                gyro = gyro + noise[..., :3] * (white_g / root)
                accel = accel + noise[..., 3:] * (white_a / root)
            j = epoch_of.get(end)
            points = list(range(every, length + 1, every))
            if j is not None and (not points or points[-1] != length):
                points.append(length)
            lo_r, hi_r = np.searchsorted(rec_index, [begin + 1, end + 1])
            rec_steps = (rec_index[lo_r:hi_r] - begin).tolist()
            stops = sorted(set(points) | set(rec_steps))
            states, y = mechanize_increments(y, gyro, accel, bg_hat, ba_hat, dts, stops)
            var = ekf.P.diagonal(dim1=-2, dim2=-1)[:, None]  # (N, 1, 15) at the block start
            if points:
                at = [stops.index(s) for s in points]
                f_points = accel[:, [s - 1 for s in points]] - ba_hat[:, None]
                cum = torch.cat([dts.new_zeros(1), torch.cumsum(dts, 0)])
                intervals = [float(cum[b] - cum[a]) for a, b in zip([0, *points], points,
                                                                   strict=False)]
                P, var_mid = propagate_with_sigma(ekf.P, ekf.healthy, states[:, at[:-1]],
                                                  f_points[:, :-1], intervals[:-1], qc,
                                                  tau_g, tau_a)
                _, phi, qd = propagate_block(P, ekf.healthy, states[:, at[-1:]],
                                             f_points[:, -1:], intervals[-1:], qc, tau_g,
                                             tau_a)
                ekf.P = P
                ekf.predict(phi, qd, trusted_noise=True)  # Q_d: the error model's, symmetric
                var = torch.cat([var, var_mid, ekf.P.diagonal(dim1=-2, dim2=-1)[:, None]], 1)
            if rec_steps:
                slots = torch.as_tensor([slot[begin + s] for s in rec_steps])
                pos = torch.as_tensor([stops.index(s) for s in rec_steps])
                which = torch.as_tensor(np.searchsorted(points, rec_steps, side="right"))
                out_states[:, slots] = states[:, pos]
                out_std[:, slots] = var[:, which].sqrt()
                out_bg[:, slots] = bg_hat[:, None]
                out_ba[:, slots] = ba_hat[:, None]
            if j is not None:
                update(j, gyro[:, -1] - bg_hat)
                if end in slot:
                    record(end)
            begin = end
    if not bool(torch.isfinite(out_states).all()):
        raise NeuralMapError(
            "run_on_log: the solution became non-finite; check the initial state (initpos, "
            "initatt), the IMU axes (forward-right-down) and units (rad, m/s increments)."
        )
    counts["unhealthy_runs"] = int((~ekf.healthy).sum())
    return LogSolution(time=time[rec], states=out_states, std=out_std, gyro_bias=out_bg,
                       accel_bias=out_ba, counts=counts)


def compare_with_reference(solution: LogSolution, reference: NavLog) -> dict[str, object]:
    """Position, velocity and attitude errors of every run against a reference trajectory.

    The reference is interpolated linearly in time to the solution epochs (yaw unwrapped);
    epochs outside the reference are left out and counted. Errors are solution − reference:
    NED position (m, about the reference point), NED velocity (m/s) and the total attitude
    error φ (rad, NED axes; ≈ roll, pitch, heading errors for a level vehicle), as the
    ``gnss_ins`` study reports them.

    Returns:
        JSON-ready dict: RMSE horizontal / vertical / 3-D, 95th percentile and maximum
        horizontal, velocity RMSE, roll / pitch / heading RMSE in degrees (all runs), the
        same for run 0 alone, and the number of compared epochs.
    """
    t = solution.time.cpu().numpy()
    ok = (t >= reference.time[0]) & (t <= reference.time[-1])
    if not ok.any():
        raise NeuralMapError(
            f"compare_with_reference: the reference covers {reference.time[0]:.3f}–"
            f"{reference.time[-1]:.3f} s, the solution {t[0]:.3f}–{t[-1]:.3f} s: no overlap."
        )
    tt = t[ok]

    def interp(values: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.column_stack([np.interp(tt, reference.time, values[:, i])
                                                for i in range(values.shape[1])]))

    euler = np.radians(reference.euler)
    euler[:, 2] = np.unwrap(euler[:, 2])
    position = np.column_stack([np.radians(reference.position[:, :2]), reference.position[:, 2]])
    ref_pos, ref_vel, ref_eul = interp(position), interp(reference.velocity), interp(euler)
    ref = torch.cat([ref_pos, ref_vel, quat_from_euler(ref_eul)], dim=1)
    s = solution.states[:, torch.as_tensor(ok)].cpu().double()  # (N, K', 10)
    n, k = s.shape[:2]
    flat = s.reshape(n * k, 10)
    ref_n = ref.expand(n, k, 10).reshape(n * k, 10)
    dpos = position_offset_ned(flat[:, 0], flat[:, 1], flat[:, 2],
                               ref_n[:, 0], ref_n[:, 1], ref_n[:, 2]).reshape(n, k, 3)
    dvel = (flat[:, 3:6] - ref_n[:, 3:6]).reshape(n, k, 3)
    datt = total_attitude_error(ref_n, flat).reshape(n, k, 3) * _DEG

    def rms(x: torch.Tensor) -> float:
        return float(x.square().mean().sqrt())

    def summary(p: torch.Tensor, v: torch.Tensor, a: torch.Tensor) -> dict[str, float]:
        horiz = p[..., :2].norm(dim=-1)
        return {
            "rmse_horizontal_m": rms(horiz), "rmse_vertical_m": rms(p[..., 2]),
            "rmse_3d_m": rms(p.norm(dim=-1)),
            "p95_horizontal_m": float(torch.quantile(horiz.flatten(), 0.95)),
            "max_horizontal_m": float(horiz.max()),
            "rmse_velocity_mps": rms(v.norm(dim=-1)),
            "rmse_roll_deg": rms(a[..., 0]), "rmse_pitch_deg": rms(a[..., 1]),
            "rmse_heading_deg": rms(a[..., 2]),
        }

    return {"n_runs": n, "epochs_compared": k, "epochs_outside_reference": int((~ok).sum()),
            "all_runs": summary(dpos, dvel, datt),
            "run_0": summary(dpos[:1], dvel[:1], datt[:1])}
