"""The differenced measurement noise: whiteness (Ljung-Box) and the derived covariances."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from statsmodels.stats.diagnostic import acorr_ljungbox

from neuralmap.wind import (
    FaultConfig,
    MeasurementConfig,
    TVARWindModel,
    WindSimConfig,
    measure_wind,
    simulate_wind,
)


def test_differenced_measurement_noise_is_white_on_simulated_data():
    gen = torch.Generator().manual_seed(21)
    truth = simulate_wind(WindSimConfig(), n_runs=3, n_steps=3000, generator=gen)
    meas = measure_wind(truth, MeasurementConfig(walk_var=0.05), generator=gen)
    error = (meas.z - truth.wind).numpy()  # γ: the random walk
    for run in range(3):
        for axis in range(2):
            diff = np.diff(error[run, :, axis])  # L_k − (v_{k+1} − v_k) = ν_{k+1}
            p_white = acorr_ljungbox(diff, lags=[10, 20])["lb_pvalue"].to_numpy()
            assert np.all(p_white > 0.001), (run, axis, p_white)
            assert diff.var() == pytest.approx(0.05, rel=0.1)
            # the undifferenced error is strongly autocorrelated (the test can fail)
            p_raw = acorr_ljungbox(error[run, :, axis], lags=[10])["lb_pvalue"].to_numpy()
            assert np.all(p_raw < 1e-10)


def test_outlier_patches_mark_consecutive_samples():
    gen = torch.Generator().manual_seed(22)
    truth = simulate_wind(WindSimConfig(), n_runs=50, n_steps=200, generator=gen)
    meas = measure_wind(truth, MeasurementConfig(),
                        FaultConfig(patch_count=1, patch_length=20, patch_std=10.0),
                        generator=gen)
    assert torch.all(meas.outlier.sum(1) == 20)
    idx = meas.outlier.float().argmax(1)
    for run in range(50):
        start = int(idx[run])
        assert bool(meas.outlier[run, start:start + 20].all())
        assert 0.3 * 199 - 1 <= start <= 0.7 * 199
    assert torch.allclose(meas.z, truth.wind + meas.noise + meas.fault)
    assert meas.fault[meas.outlier].std().item() == pytest.approx(10.0, rel=0.1)
    assert torch.all(meas.fault[~meas.outlier] == 0)


def _simulate_tvar(model: TVARWindModel, runs: int, steps: int, a: float, seed: int):
    """Plain NumPy simulation of the model of the derivation; returns x, ω-noise, ν."""
    rng = np.random.default_rng(seed)
    g = 1.0 if model.direct_noise else 0.0
    x = np.zeros((runs, steps, 3))
    x[:, 0] = np.stack([rng.normal(5.0, 1.0, runs), np.full(runs, a),
                        rng.normal(0.0, 0.3, runs)], -1)
    w = rng.normal(0.0, np.sqrt(model.process_var), (runs, steps))
    xi = rng.normal(0.0, np.sqrt(model.coeff_var), (runs, steps))
    nu = rng.normal(0.0, np.sqrt(model.meas_var), (runs, steps))
    for k in range(steps - 1):
        v, aa, eta = x[:, k].T
        x[:, k + 1, 0] = aa * v + eta + g * w[:, k + 1]
        x[:, k + 1, 1] = aa + xi[:, k + 1]
        x[:, k + 1, 2] = eta + w[:, k + 1]
    gamma = np.cumsum(nu, axis=1)
    z = x[:, :, 0] + gamma
    return x, z


@pytest.mark.parametrize("direct_noise", [True, False])
def test_differenced_noise_covariance_and_cross_covariance_match_derivation(direct_noise):
    model = TVARWindModel(process_var=0.5, coeff_var=1e-4, meas_var=1.0,
                          direct_noise=direct_noise)
    x, z = _simulate_tvar(model, runs=20000, steps=12, a=0.9, seed=5)
    v, a, eta = x[:, :-1, 0], x[:, :-1, 1], x[:, :-1, 2]
    L = z[:, 1:] - z[:, :-1]
    e = L - ((a - 1.0) * v + eta)  # e_k = L_k − h(x_k), exact
    fx = np.stack([a * v + eta, a, eta], -1)
    u = x[:, 1:] - fx  # process noise of x_k → x_{k+1}
    Q, R, C = model.noise_covariances()
    n = e.size
    # cov e: std. error ~ R sqrt(2/n) = 0.3 %
    assert (e**2).mean() == pytest.approx(R.item(), rel=0.02)
    assert abs(e.mean()) < 5 * np.sqrt(R.item() / n)
    # E[u eᵀ] = Γ Σ_ω Γᵀ Hᵀ; std. error ~ sqrt(Q_ii R / n) < 0.002
    cross = (u * e[..., None]).reshape(-1, 3).mean(0)
    assert np.allclose(cross, C[:, 0].numpy(), atol=0.01), cross
    # cov u = Q
    flat = u.reshape(-1, 3)
    cov_u = flat.T @ flat / n
    assert np.allclose(cov_u, Q.numpy(), atol=0.01)
    # whiteness: no correlation of e across steps, nor with other steps' process noise
    assert abs((e[:, 1:] * e[:, :-1]).mean()) < 0.01
    assert np.all(np.abs((u[:, 1:] * e[:, :-1, None]).reshape(-1, 3).mean(0)) < 0.01)
    assert np.all(np.abs((u[:, :-1] * e[:, 1:, None]).reshape(-1, 3).mean(0)) < 0.01)
    if direct_noise:  # the correlation is real: far from zero at this sample size
        assert cross[0] > 0.4 and cross[2] > 0.4


def test_isolated_spikes_rate_and_size():
    gen = torch.Generator().manual_seed(23)
    truth = simulate_wind(WindSimConfig(), n_runs=200, n_steps=200, generator=gen)
    meas = measure_wind(truth, MeasurementConfig(),
                        FaultConfig(spike_rate=0.02, spike_magnitude=15.0), generator=gen)
    rate = meas.outlier.double().mean().item()
    assert rate == pytest.approx(0.02, abs=0.003)  # 40000 samples: std. error 0.0007
    assert torch.all(meas.fault[meas.outlier].abs() == 15.0)
    assert torch.all(meas.fault[~meas.outlier] == 0.0)
    # isolated: mostly single samples, not patches
    both = (meas.outlier[:, 1:] & meas.outlier[:, :-1]).double().mean().item()
    assert both < 0.002
