"""Simulator statistics against the closed-form truth models, determinism and map flags."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.scenario import load_scenario, scenario_tile
from neuralmap.lab.simulator import dem_error_field, nominal_path, simulate
from neuralmap.tan.model import transition_matrix
from neuralmap.terrain.grid import GridTerrain


@pytest.fixture(scope="module")
def tiny():
    scenario = load_scenario("tiny")
    return scenario, scenario_tile(scenario)


def test_altimeter_noise_sigma_recovered(tiny) -> None:
    scenario, tile = tiny
    truth = simulate(scenario, tile, n_runs=2000, seed=3)
    noise = truth.radar - (truth.pos[..., 2] - truth.terrain_true)
    n = noise.numel()  # 82 000 samples: std error of the sigma estimate ~0.25 %
    assert float(noise.std()) == pytest.approx(scenario.altimeter_sigma_m, rel=0.02)
    assert abs(float(noise.mean())) < 5.0 * scenario.altimeter_sigma_m / math.sqrt(n)
    # the true terrain is the bicubic DEM (no DEM error in this scenario)
    bicubic = GridTerrain(tile, method="bicubic")
    assert torch.allclose(truth.terrain_true, bicubic(truth.pos[..., :2]), atol=1e-9)


def test_ins_error_mean_and_covariance_follow_the_error_model(tiny) -> None:
    """Empirical mean/covariance of δX_k vs Φ^k m_0 and C_{k+1} = Φ C_k Φᵀ + Q_truth."""
    scenario, tile = tiny
    scenario = dataclasses.replace(
        scenario, init_error_mean=[10.0, -5.0, 3.0, 0.5, -0.2], vel_random_walk=0.3,
        init_vel_sigma_mps=0.4,
    )
    n = 6000
    truth = simulate(scenario, tile, n_runs=n, seed=11)
    err = truth.ins_error  # (N, K+1, 5)
    F = transition_matrix(scenario.dt)
    Q = torch.diag(torch.tensor(scenario.truth_process_noise(), dtype=torch.float64))
    mean = torch.tensor(scenario.init_error_mean, dtype=torch.float64)
    cov = torch.diag(torch.tensor(scenario.init_error_sigma(), dtype=torch.float64) ** 2)
    for k in range(truth.n_steps + 1):
        if k in (0, truth.n_steps // 2, truth.n_steps):
            emp_mean = err[:, k].mean(0)
            emp_var = err[:, k].var(0)
            se = (cov.diagonal() / n).sqrt()
            assert torch.all((emp_mean - mean).abs() <= 5.0 * se + 1e-12), k
            # relative std error of a variance is sqrt(2/N) = 1.8 %; allow 10 %
            assert torch.allclose(emp_var, cov.diagonal(), rtol=0.10), (k, emp_var, cov)
        mean, cov = F @ mean, F @ cov @ F.T + Q
    # velocity random walk: variance grows linearly, by vrw² dt per step
    growth = err[:, -1, 3].var() - err[:, 0, 3].var()
    expected = scenario.vel_random_walk**2 * scenario.dt * truth.n_steps
    assert float(growth) == pytest.approx(expected, rel=0.12)
    # the INS outputs are truth + error
    assert torch.allclose(truth.ins_pos, truth.pos + err[..., :3])
    assert torch.allclose(truth.ins_vel, truth.vel + err[..., 3:])


def test_start_spread_and_altitude(tiny) -> None:
    scenario, tile = tiny
    truth = simulate(scenario, tile, n_runs=3000, seed=1)
    xy_nom, _ = nominal_path(scenario, tile)
    offset = truth.pos[:, 0, :2] - torch.from_numpy(xy_nom[0])
    assert offset.std(0).tolist() == pytest.approx([scenario.start_spread_m] * 2, rel=0.06)
    # each run is the nominal path translated by its offset
    shifted = torch.from_numpy(xy_nom)[None] + offset[:, None]
    assert torch.allclose(truth.pos[..., :2], shifted, atol=1e-9)
    h = float(np.nanmax(tile.heights)) + scenario.altitude_agl_m
    assert torch.allclose(truth.pos[..., 2], torch.full_like(truth.pos[..., 2], h))


def test_same_seed_same_truth_other_seed_differs(tiny) -> None:
    scenario, tile = tiny
    a = simulate(scenario, tile, n_runs=5, seed=7)
    b = simulate(scenario, tile, n_runs=5, seed=7)
    c = simulate(scenario, tile, n_runs=5, seed=8)
    for name in ("pos", "ins_pos", "ins_vel", "radar", "outlier", "on_map"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert not torch.equal(a.radar, c.radar)
    f32 = simulate(scenario, tile, n_runs=5, seed=7, dtype=torch.float32)
    assert f32.radar.dtype == torch.float32
    assert torch.allclose(f32.radar.double(), a.radar, rtol=1e-6)
    default_seed = simulate(scenario, tile, n_runs=5)
    assert default_seed.seed == scenario.seed


def test_on_map_flags_when_the_flight_leaves_the_tile(tiny) -> None:
    scenario, tile = tiny
    long = dataclasses.replace(scenario, duration_s=80.0)  # 4 km at 50 m/s: leaves the tile
    truth = simulate(long, tile, n_runs=20, seed=0)
    xmin, xmax, ymin, ymax = tile.extent
    x, y = truth.pos[..., 0], truth.pos[..., 1]
    expected = (x >= xmin) & (x <= xmax) & (y >= ymin) & (y <= ymax)
    assert torch.equal(truth.on_map, expected)
    assert truth.on_map[:, 0].all() and not truth.on_map[:, -1].any()


def test_outliers_probability_and_size(tiny) -> None:
    scenario, tile = tiny
    s = dataclasses.replace(scenario, outlier_prob=0.1, outlier_sigma_m=60.0)
    truth = simulate(s, tile, n_runs=1000, seed=2)
    n = truth.outlier.numel()
    frac = float(truth.outlier.float().mean())
    assert abs(frac - 0.1) < 5.0 * math.sqrt(0.1 * 0.9 / n)
    noise = truth.radar - (truth.pos[..., 2] - truth.terrain_true)
    total = math.hypot(s.altimeter_sigma_m, s.outlier_sigma_m)
    assert float(noise[truth.outlier].std()) == pytest.approx(total, rel=0.05)
    assert float(noise[~truth.outlier].std()) == pytest.approx(s.altimeter_sigma_m, rel=0.03)


def test_waypoints_turn_rate_and_speed(tiny) -> None:
    scenario, tile = tiny
    s = dataclasses.replace(
        scenario, duration_s=120.0, heading_deg=90.0, start_xy=[300.0, 300.0],
        waypoints=[[2400.0, 300.0], [2400.0, 2400.0], [300.0, 2400.0]], turn_rate_dps=10.0,
    )
    xy, vel = nominal_path(s, tile)
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    # a turn step is the chord: speed dt cos(Δψ / 2) with Δψ <= turn rate · dt
    chord = s.speed_mps * s.dt * math.cos(0.5 * math.radians(s.turn_rate_dps) * s.dt)
    assert np.all(step >= chord - 1e-9) and np.all(step <= s.speed_mps * s.dt + 1e-9)
    assert np.allclose(np.linalg.norm(vel, axis=1), s.speed_mps)
    heading = np.unwrap(np.arctan2(vel[:, 0], vel[:, 1]))
    assert np.abs(np.diff(heading)).max() <= math.radians(s.turn_rate_dps) * s.dt + 1e-12
    radius = s.speed_mps / math.radians(s.turn_rate_dps)
    for wp in s.waypoints:
        assert np.linalg.norm(xy - np.asarray(wp), axis=1).min() <= radius + s.speed_mps


def test_dem_error_field_statistics() -> None:
    field = dem_error_field((256, 256), (10.0, 10.0), sigma_m=2.0, corr_m=50.0, seed=4)
    assert field.std() == pytest.approx(2.0, rel=1e-9) and abs(field.mean()) < 1e-9
    lag = 5  # nodes = 50 m = the correlation length: correlation exp(-1)
    rho_x = float((field[:, :-lag] * field[:, lag:]).mean() / field.var())
    rho_y = float((field[:-lag] * field[lag:]).mean() / field.var())
    assert rho_x == pytest.approx(math.exp(-1.0), abs=0.08)
    assert rho_y == pytest.approx(math.exp(-1.0), abs=0.08)
    again = dem_error_field((256, 256), (10.0, 10.0), sigma_m=2.0, corr_m=50.0, seed=4)
    assert np.array_equal(field, again)


def test_dem_error_enters_the_true_terrain(tiny) -> None:
    scenario, tile = tiny
    s = dataclasses.replace(scenario, dem_error_sigma_m=2.0, dem_error_corr_m=150.0)
    truth = simulate(s, tile, n_runs=50, seed=5)
    assert truth.dem_error is not None and truth.dem_error.std() == pytest.approx(2.0)
    diff = truth.terrain_true - GridTerrain(tile, method="bicubic")(truth.pos[..., :2])
    assert 0.5 < float(diff.std()) < 3.0
    assert truth.tile_fingerprint == tile.fingerprint()  # the map's tile, not the truth's


def test_bad_arguments(tiny) -> None:
    scenario, tile = tiny
    with pytest.raises(NeuralMapError, match="n_runs"):
        simulate(scenario, tile, n_runs=0)
    with pytest.raises(NeuralMapError, match="DemTile"):
        simulate(scenario, np.zeros((4, 4)), n_runs=2)  # type: ignore[arg-type]
