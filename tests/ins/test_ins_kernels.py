"""The GNSS/INS block filter: compiled loops against the torch operations they replace.

References: the torch strapdown step and error model (sample by sample, float64), the
per-sample IMU draws, and the recorded output of the per-sample filter this block form
replaced (the same drive, seeds and policy; values printed by that implementation).
"""

from __future__ import annotations

import pytest
import torch

import neuralmap.ins.kernels as kernels
from neuralmap.filters import InnovationInflation
from neuralmap.ins.covariance_kernels import propagate_block
from neuralmap.ins.error_model import (
    continuous_noise,
    discretize,
    error_dynamics,
    process_noise_density,
)
from neuralmap.ins.gnss import UrbanEffects, simulate_gnss
from neuralmap.ins.imu_model import ImuErrorProcess, imu_grade
from neuralmap.ins.loosely_coupled import LooselyCoupledConfig, run_loosely_coupled
from neuralmap.ins.mechanization import strapdown_step
from neuralmap.ins.trajectory import short_drive

D = torch.float64
needs_numba = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba not installed (extra: fast)")

# Output of the per-sample filter (one torch operation set per IMU sample) on the case of
# _recorded_case: final position and attitude errors and σ of [δr, δv, ψ], and the NIS sum.
_POS = [
    [0.0071799347854790046, 0.0011994567773677702, -0.007323494066280745],
    [-0.007992362599186939, 0.0157584499508193, 0.014494173172067804],
    [0.011114684293867187, -0.008698290541953087, -0.05375089596613236],
]
_ATT = [
    [-0.0004777948554831392, -0.00043313957152499094, -0.0005851165854036003],
    [0.001655380948605711, -0.0018724991691021534, -0.001087994420979663],
    [-0.0009757689611400734, -0.0009982322115683242, 9.097059834914798e-05],
]
_STD = [
    [0.016578566817864796, 0.01641066049007469, 0.03871610251868877, 0.017293771108336176,
     0.01668212937267726, 0.0189295835651444, 0.0013591829855602385, 0.0015123536083759103,
     0.002708101016834213],
    [0.016656475847001886, 0.016306136081933542, 0.03839580036823873, 0.01989516570562997,
     0.019257472950708787, 0.024893217640588054, 0.0022631969111071297, 0.002432758812760071,
     0.0048916387302345675],
    [0.01625916855111544, 0.016050523825559906, 0.03782530226485847, 0.016301556094077428,
     0.016345863116659986, 0.01881125023469878, 0.0012715080298391634, 0.001360965451390972,
     0.0023487835280210584],
]
_NIS = 311.4366352755225


def _recorded_case(monkeypatch: pytest.MonkeyPatch, compiled: bool):  # type: ignore[no-untyped-def]
    monkeypatch.setattr(kernels, "HAVE_NUMBA", compiled and kernels.HAVE_NUMBA)
    traj = short_drive(duration=12.0, dt=0.02)
    gen = torch.Generator().manual_seed(5)
    imu = ImuErrorProcess("tactical_mems", n_runs=3, dt=0.02, generator=gen)
    rec = simulate_gnss(traj, n_runs=3, lever_arm=[0.5, 0.2, -1.2], generator=gen,
                        effects=UrbanEffects.urban(traj.duration))
    return run_loosely_coupled(traj, imu, rec, LooselyCoupledConfig(propagate_every=3),
                               generator=gen, policy=InnovationInflation(1.0))


def _outputs(res) -> list[torch.Tensor]:  # type: ignore[no-untyped-def]
    return [res.position_error[:, -1], res.attitude_error[:, -1], res.std[:, -1, :9],
            torch.nan_to_num(res.nis).sum()]


def _recorded() -> list[torch.Tensor]:
    return [torch.tensor(v, dtype=D) for v in (_POS, _ATT, _STD, _NIS)]


def test_block_filter_without_compiled_loops_matches_the_recorded_output(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # the recorded values come from another machine: another CPU rounds differently
    # (measured: 1e-16 in attitude and σ, 3e-13 in the NIS sum), so a stated tolerance
    res = _recorded_case(monkeypatch, compiled=False)
    for got, want in zip(_outputs(res), _recorded(), strict=True):
        torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-13)
    assert bool(res.healthy.all())


@needs_numba
def test_block_filter_with_compiled_loops_matches_to_rounding(
        monkeypatch: pytest.MonkeyPatch) -> None:
    res = _recorded_case(monkeypatch, compiled=True)
    for got, want in zip(_outputs(res), _recorded(), strict=True):
        torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-13)
    assert bool(res.healthy.all())


def _imu_block(n: int, steps: int) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(n)
    traj = short_drive(duration=steps * 0.01, dt=0.01)
    imu = ImuErrorProcess("tactical_mems", n_runs=n, dt=0.01, generator=g)
    gyro, accel = imu.measure_block(traj.gyro[: steps + 1], traj.accel[: steps + 1])
    return traj, gyro, accel


@needs_numba
def test_compiled_strapdown_matches_the_torch_step() -> None:
    traj, gyro, accel = _imu_block(5, 400)
    y0 = traj.states[0].expand(5, 10).clone()
    bg = 1e-4 * torch.randn(5, 3, generator=torch.Generator().manual_seed(1), dtype=D)
    ba = 1e-2 * torch.randn(5, 3, generator=torch.Generator().manual_seed(2), dtype=D)
    failed = torch.zeros(5, dtype=torch.bool)
    stops = [100, 250, 400]
    states, y, _ = kernels.mechanize_block(y0, y0.clone(), failed, gyro, accel, bg, ba, 0.01,
                                           stops)
    ref, kept = y0, []
    for k in range(1, 401):
        ref = strapdown_step(ref, gyro[:, k - 1] - bg, accel[:, k - 1] - ba, gyro[:, k] - bg,
                             accel[:, k] - ba, 0.01)
        if k in stops:
            kept.append(ref)
    torch.testing.assert_close(states, torch.stack(kept, 1), rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(y, ref, rtol=1e-12, atol=1e-13)
    assert not bool(failed.any())


def test_block_guard_restores_the_last_good_solution() -> None:
    traj, gyro, accel = _imu_block(2, 20)
    y0 = traj.states[0].expand(2, 10).clone()
    accel = accel.clone()
    accel[1, 12] = float("nan")
    failed = torch.zeros(2, dtype=torch.bool)
    zero = torch.zeros(2, 3, dtype=D)
    states, y, good = kernels.mechanize_block(y0, y0.clone(), failed, gyro, accel, zero, zero,
                                              0.01, [10, 20])
    assert failed.tolist() == [False, True]
    assert torch.equal(y[1], states[1, 0]) and torch.isfinite(y).all()


@needs_numba
def test_compiled_propagation_matches_the_torch_error_model() -> None:
    traj, gyro, accel = _imu_block(4, 50)
    states = traj.states[torch.tensor([10, 20, 30, 40, 50])].expand(4, 5, 10).clone()
    states[:, :, 3:6] += torch.randn(4, 5, 3, generator=torch.Generator().manual_seed(3),
                                     dtype=D)
    f = accel[:, [10, 20, 30, 40, 50]]
    grade = imu_grade("tactical_mems")
    qc = process_noise_density(grade)
    A = torch.randn(4, 15, 15, generator=torch.Generator().manual_seed(4), dtype=D)
    P0 = A @ A.transpose(1, 2) * 1e-3 + torch.eye(15, dtype=D) * 1e-4
    # A @ A.T is not exactly symmetric on every CPU: symmetric by construction (one triangle)
    P0 = torch.tril(P0) + torch.tril(P0, -1).transpose(1, 2)
    healthy = torch.tensor([True, True, False, True])
    intervals = [0.1, 0.1, 0.05, 0.1, 0.1]
    P, phi, qd = propagate_block(P0, healthy, states, f, intervals, qc,
                                         grade.gyro_corr_time, grade.accel_corr_time)
    ref = P0
    for s in range(5):
        F = error_dynamics(states[:, s], f[:, s], gyro_corr_time=grade.gyro_corr_time,
                           accel_corr_time=grade.accel_corr_time)
        phi_r, qd_r = discretize(F, continuous_noise(states[:, s], qc), intervals[s])
        if s < 4:
            fpf = phi_r @ ref @ phi_r.transpose(1, 2)
            ref = torch.where(healthy.reshape(-1, 1, 1), 0.5 * (fpf + fpf.transpose(1, 2))
                              + qd_r, ref)
    torch.testing.assert_close(P, ref, rtol=1e-12, atol=1e-18)
    torch.testing.assert_close(phi, phi_r, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(qd, qd_r, rtol=1e-12, atol=1e-24)
    assert torch.equal(P[2], P0[2]) and torch.equal(P, P.transpose(1, 2))


@pytest.mark.parametrize("n", [1, 3, 8])
def test_imu_block_draws_the_same_numbers_as_sample_by_sample(n: int) -> None:
    traj = short_drive(duration=0.3, dt=0.01)
    a = ImuErrorProcess("tactical_mems", n_runs=n, dt=0.01,
                        generator=torch.Generator().manual_seed(9))
    b = ImuErrorProcess("tactical_mems", n_runs=n, dt=0.01,
                        generator=torch.Generator().manual_seed(9))
    steps = [a.measure(traj.gyro[k], traj.accel[k]) for k in range(traj.n_samples)]
    w1, f1 = b.measure_block(traj.gyro[:11], traj.accel[:11])
    w2, f2 = b.measure_block(traj.gyro[11:], traj.accel[11:])
    assert torch.equal(torch.cat([w1, w2], 1), torch.stack([s[0] for s in steps], 1))
    assert torch.equal(torch.cat([f1, f2], 1), torch.stack([s[1] for s in steps], 1))
    assert torch.equal(a.gyro_gm, b.gyro_gm) and torch.equal(a.accel_gm, b.accel_gm)


def test_a_run_whose_error_model_overflows_is_frozen_and_counted() -> None:
    # a run with an absurd accelerometer reading: its bias estimate and error model blow up;
    # it is counted as failed and the other runs go on
    traj = short_drive(duration=6.0, dt=0.02)
    gen = torch.Generator().manual_seed(1)
    imu = ImuErrorProcess("tactical_mems", n_runs=2, dt=0.02, generator=gen)
    imu.accel_turn_on = imu.accel_turn_on.clone()
    imu.accel_turn_on[1] = 1e300
    rec = simulate_gnss(traj, n_runs=2, lever_arm=[0.5, 0.2, -1.2], generator=gen)
    res = run_loosely_coupled(traj, imu, rec, LooselyCoupledConfig(propagate_every=5),
                              generator=gen)
    assert res.counts["failed_runs"] >= 1
    assert res.healthy.tolist() == [True, False]
    assert torch.isfinite(res.position_error[0]).all()
