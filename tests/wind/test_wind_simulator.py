"""Wind simulator statistics against the analytic values of the exact discretisation."""

from __future__ import annotations

import math

import pytest
import torch

from neuralmap.wind import WindSimConfig, simulate_wind, turbulence_coefficients


def test_paper_defaults_and_coefficients():
    cfg = WindSimConfig()
    row = [cfg.mean_walk_var, cfg.driver_var, cfg.intensity, cfg.scale, cfg.step, cfg.mean0,
           cfg.turb0]
    assert row == [0.01, 1.0, 1.75, 100.0, 20.0, 10.0, 0.0]
    coef = cfg.turbulence()
    assert coef.phi == pytest.approx(math.exp(-0.2), rel=1e-15)
    assert coef.gain == pytest.approx(1.75 * math.sqrt(1.0 - math.exp(-0.4)), rel=1e-15)
    assert coef.variance == pytest.approx(1.75**2)
    assert coef.correlation_steps == pytest.approx(5.0)
    assert cfg.dt == pytest.approx(1.0)


def test_stationary_turbulence_variance_and_autocorrelation():
    # 2 axes x 20000 runs = 40000 independent series; cross-run estimates per time.
    cfg = WindSimConfig(turb0=None)
    truth = simulate_wind(cfg, n_runs=20000, n_steps=16, seed=3)
    turb = truth.turbulence.permute(1, 0, 2).reshape(16, -1)  # (T, 40000)
    coef = cfg.turbulence()
    # variance at every time: std. error sqrt(2/40000) = 0.7 %; tolerance 3 % (> 4 s.e.)
    var_t = turb.var(dim=1)
    assert torch.allclose(var_t, torch.full_like(var_t, coef.variance), rtol=0.03)
    # autocorrelation at lags 0..10 from the first sample: std. error <= 1/sqrt(40000)
    x0 = turb[0]
    for lag in range(11):
        rho = torch.corrcoef(torch.stack([x0, turb[lag]]))[0, 1].item()
        assert rho == pytest.approx(coef.autocorrelation(lag), abs=0.02), lag
    # correlation time: the autocorrelation falls to 1/e after L/h = 5 samples
    rho5 = torch.corrcoef(torch.stack([x0, turb[5]]))[0, 1].item()
    assert rho5 == pytest.approx(math.exp(-1.0), abs=0.02)


def test_transient_variance_from_zero_start():
    # v_t(0) = 0 (the paper's row): Var v_t(k) = σ² Σ (1 − φ^{2k}).
    cfg = WindSimConfig()
    truth = simulate_wind(cfg, n_runs=20000, n_steps=6, seed=4)
    coef = cfg.turbulence()
    turb = truth.turbulence.permute(1, 0, 2).reshape(6, -1)
    assert torch.all(turb[0] == 0)
    for k in range(1, 6):
        expected = coef.variance * (1.0 - coef.phi ** (2 * k))
        assert turb[k].var().item() == pytest.approx(expected, rel=0.04), k


def test_mean_wind_random_walk_increments_and_start():
    cfg = WindSimConfig()
    truth = simulate_wind(cfg, n_runs=5000, n_steps=20, seed=5)
    assert torch.allclose(truth.mean[:, 0], torch.tensor([10.0, 0.0], dtype=torch.float64),
                          atol=1e-12)
    inc = truth.mean.diff(dim=1).reshape(-1)  # 190000 increments
    assert inc.var().item() == pytest.approx(0.01, rel=0.02)
    # increments are uncorrelated (random walk)
    a, b = truth.mean.diff(dim=1)[:, :-1].reshape(-1), truth.mean.diff(dim=1)[:, 1:].reshape(-1)
    assert abs(torch.corrcoef(torch.stack([a, b]))[0, 1].item()) < 0.01


def test_turbulence_coefficients_other_values():
    coef = turbulence_coefficients(intensity=2.0, scale=50.0, step=10.0, driver_var=0.5)
    assert coef.phi == pytest.approx(math.exp(-0.2))
    assert coef.variance == pytest.approx(2.0)


def test_shear_step_and_gust():
    cfg = WindSimConfig(shear_step=5.0, shear_time=10, shear_direction_deg=0.0,
                        gust_amplitude=4.0, gust_time=20, gust_length=10,
                        gust_direction_deg=90.0)
    truth = simulate_wind(cfg, n_runs=3, n_steps=40, seed=6)
    jump = truth.mean[:, 10] - truth.mean[:, 9]
    inc = truth.mean[:, 11] - truth.mean[:, 10]  # an ordinary random-walk increment
    assert torch.all((jump[:, 1] - 5.0).abs() < 0.5)
    assert torch.all(inc.abs() < 0.5)
    assert truth.gust[25, 0].item() == pytest.approx(4.0)  # peak mid-gust
    assert truth.gust[19].abs().max().item() == 0.0 and truth.gust[30].abs().max().item() == 0.0
    assert torch.allclose(truth.wind, truth.mean + truth.turbulence + truth.gust)


def test_seeded_reproducible():
    a = simulate_wind(WindSimConfig(), n_runs=4, n_steps=10, seed=11).wind
    b = simulate_wind(WindSimConfig(), n_runs=4, n_steps=10, seed=11).wind
    c = simulate_wind(WindSimConfig(), n_runs=4, n_steps=10, seed=12).wind
    assert torch.equal(a, b) and not torch.equal(a, c)
