"""The lane-vectorised covariance propagation against the per-run compiled loop it replaces:
the same numbers (bit-identical), including exact zeros in F, Φ and P, unhealthy runs and
a run count that is not a multiple of the lane width."""

from __future__ import annotations

import numpy as np
import pytest

import neuralmap.ins.kernels as kernels
from neuralmap.ins import covariance_kernels as ck
from neuralmap.ins.error_model import process_noise_density
from neuralmap.ins.imu_model import imu_grade

needs_numba = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba not installed (extra: fast)")


def _inputs(n: int, points: int, seed: int = 0):  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(seed)
    states = np.zeros((n, points, 10))
    states[..., 0] = 0.6 + 0.01 * rng.standard_normal((n, points))
    states[..., 1] = 0.2
    states[..., 2] = 100.0 + rng.standard_normal((n, points))
    states[..., 3:6] = 5.0 * rng.standard_normal((n, points, 3))
    q = rng.standard_normal((n, points, 4))
    states[..., 6:10] = q / np.linalg.norm(q, axis=-1, keepdims=True)
    states[:2, :, 3:6] = 0.0  # standing still: transport rate zero, exact zeros in F and Φ
    states[2:4, :, 6:10] = [1.0, 0.0, 0.0, 0.0]  # level, north: zeros in C
    accel = rng.standard_normal((n, points, 3))
    accel[..., 2] -= 9.8
    accel[:1] = 0.0
    a = rng.standard_normal((n, 15, 15))
    P = a @ a.transpose(0, 2, 1) * 1e-3 + np.eye(15) * 1e-4
    P[4:6] = np.diag(rng.random(15))  # diagonal P (the filter's start): exact zeros
    healthy = np.ones(n, dtype=bool)
    healthy[[1, n - 1]] = False
    intervals = np.full(points, 0.05)
    intervals[-1] = 0.02
    return P, healthy, states, accel, intervals


@needs_numba
@pytest.mark.parametrize("n", [2, 8, 13])
def test_lanes_equal_the_per_run_loop(n: int) -> None:
    P, healthy, states, accel, intervals = _inputs(n, 6)
    grade = imu_grade("tactical_mems")
    qc = process_noise_density(grade).numpy()
    ref = P.copy()
    phi_ref, qd_ref = np.empty((n, 15, 15)), np.empty((n, 15, 15))
    kernels._propagate_nb(ref, healthy, states, accel, intervals, qc, grade.gyro_corr_time,
                          grade.accel_corr_time, phi_ref, qd_ref)
    got = P.copy()
    phi, qd = ck.propagate_lanes(got, healthy, states, accel, intervals, qc,
                                 grade.gyro_corr_time, grade.accel_corr_time)
    assert np.array_equal(got, ref) and np.array_equal(phi, phi_ref)
    assert np.array_equal(qd, qd_ref)
    assert np.array_equal(got[~healthy], P[~healthy])
    assert not np.array_equal(got[healthy], P[healthy])


def test_patterns_cover_the_error_model() -> None:
    # the numerical nonzeros of F and Φ at generic states lie inside the structural patterns
    P, healthy, states, accel, intervals = _inputs(6, 3, seed=2)
    grade = imu_grade("tactical_mems")
    qc = process_noise_density(grade).numpy()
    model = getattr(kernels.error_model_nb, "py_func", kernels.error_model_nb)
    F, G, C, fn = np.empty((15, 15)), np.empty((15, 15)), np.empty((3, 3)), np.empty(3)
    for r in range(6):
        model(states[r, 0], accel[r, 0], qc, grade.gyro_corr_time, grade.accel_corr_time, F,
              G, C, fn)
        assert not np.any((F != 0) & ~ck.F_PATTERN)
        ft = F * 0.05
        phi = np.eye(15) + ft + 0.5 * ft @ ft
        assert not np.any((phi != 0) & ~ck.PHI_PATTERN)
    assert ck.F_PATTERN.sum() == 54 and ck.PHI_PATTERN.sum() > ck.F_PATTERN.sum()
