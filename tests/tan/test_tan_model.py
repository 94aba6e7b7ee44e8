"""The TAN model (`TanModel`): Φ(Δt), Q(Δt) and the lattice form against closed forms for a
random-walk and a Gauss-Markov altitude error, the navigator config's Gauss-Markov numbers,
and every built-in method predicting the altitude error with the model (flown through the
Navigator without measurements, gaps included) against the closed-form recursion."""

from __future__ import annotations

import math
from typing import Any

import pytest
import torch

from neuralmap.nav.config import load_navigator_config
from neuralmap.nav.navigator import Navigator
from neuralmap.tan.model import TanModel, transition_matrix

D = torch.float64
Q = (1.0, 2.0, 0.5, 0.0025, 0.0036)
P0 = (400.0, 400.0, 100.0, 0.04, 0.04)


def _phi(dt: float, a: float) -> torch.Tensor:
    phi = torch.eye(5, dtype=D)
    phi[0, 3] = phi[1, 4] = dt
    phi[2, 2] = a
    return phi


@pytest.mark.parametrize("dt", [1.0, 3.0, 0.5])
def test_random_walk_transition_and_process_noise(dt: float) -> None:
    model = TanModel(dt=1.0, P0=P0, Q=Q, R_altimeter=9.0)
    assert model.altitude_decay(dt) == 1.0
    assert torch.equal(model.transition(dt), _phi(dt, 1.0))
    assert torch.equal(model.transition(dt), transition_matrix(dt))
    torch.testing.assert_close(model.process_noise(dt), torch.diag(torch.tensor(Q, dtype=D))
                               * dt, rtol=1e-15, atol=0.0)


@pytest.mark.parametrize("dt", [1.0, 3.0, 0.5])
def test_gauss_markov_transition_and_process_noise(dt: float) -> None:
    """``a = exp(−Δt/τ)``, ``q_h(Δt) = σ² (1 − a²)`` with ``σ² = q_h / (1 − exp(−2T/τ))``;
    the other states scale with ``Δt / T``."""
    tau, T = 32.0, 2.0
    model = TanModel(dt=T, P0=P0, Q=Q, R_altimeter=9.0, altitude_time_constant_s=tau)
    a = math.exp(-dt / tau)
    assert model.altitude_decay(dt) == pytest.approx(a, rel=1e-15)
    torch.testing.assert_close(model.transition(dt), _phi(dt, a), rtol=1e-15, atol=0.0)
    sigma2 = Q[2] / (1.0 - math.exp(-2.0 * T / tau))
    ref = torch.diag(torch.tensor(Q, dtype=D)) * (dt / T)
    ref[2, 2] = sigma2 * (1.0 - a * a)
    torch.testing.assert_close(model.process_noise(dt), ref, rtol=1e-12, atol=0.0)
    # the stationary variance is that σ²: P ← a² P + q over many steps
    p = 0.0
    for _ in range(2000):
        p = model.altitude_decay() ** 2 * p + float(model.process_noise()[2, 2])
    assert p == pytest.approx(sigma2, rel=1e-12)


@pytest.mark.parametrize("tau", [None, 20.0])
def test_lattice_form_is_the_model_split(tau: float | None) -> None:
    model = TanModel(dt=1.0, P0=P0, Q=Q, R_altimeter=9.0, altitude_time_constant_s=tau)
    for dt in (1.0, 2.5):
        form, phi, q = model.lattice_form(dt), model.transition(dt), model.process_noise(dt)
        assert torch.equal(form.E, phi[:2, 2:]) and torch.equal(form.F, phi[2:, 2:])
        assert torch.equal(phi[:2, :2], torch.eye(2, dtype=D))  # s⁺ = s + E z
        assert torch.equal(form.c, torch.tensor([1.0, 0.0, 0.0], dtype=D))
        assert torch.equal(form.Q_s, q[:2, :2]) and torch.equal(form.Q_z, q[2:, 2:])


def test_config_gauss_markov_numbers() -> None:
    cfg = load_navigator_config({"sensor": {"dt_s": 2.0},
                                 "altitude_error": {"model": "gauss_markov",
                                                    "time_constant_s": 32.0, "sigma_m": 15.0}})
    model = cfg.model()
    assert model.altitude_time_constant_s == 32.0 and model.dt == 2.0
    assert model.Q[2] == pytest.approx(225.0 * (1.0 - math.exp(-4.0 / 32.0)), rel=1e-15)
    assert load_navigator_config().model().altitude_time_constant_s is None
    from neuralmap.exceptions import NeuralMapError

    with pytest.raises(NeuralMapError, match="gauss_markov"):
        load_navigator_config({"altitude_error": {"model": "gauss_markov"}})


@pytest.mark.parametrize("method", ["bilinear", "point_mass", "point_mass_tracker",
                                    "ekf_bank"])
def test_every_method_predicts_the_altitude_error_with_the_model(
        tiny_flight_3: Any, method: str) -> None:  # noqa: ANN401
    """No clearance at all: every epoch is a prediction, so the altitude variance follows
    ``P ← a(Δt)² P + q_h(Δt)`` exactly (Gauss-Markov, τ = 8 s; a 3 s gap included)."""
    truth, grid = tiny_flight_3
    k = 20
    t = truth.t[:k].clone()
    t[10:] += 2.0
    cfg = {"method": method, "sensor": {"altimeter_sigma_m": 3.0},
           "initial": {"position_sigma_m": 20.0, "altitude_sigma_m": 30.0,
                       "velocity_sigma_mps": 0.2},
           "altitude_error": {"model": "gauss_markov", "time_constant_s": 8.0, "sigma_m": 12.0},
           "integrity": {"lost_window": 0},
           "point_mass": {"cells": 32, "dtype": "float64"},
           "point_mass_tracker": {"dtype": "float64"}, "ekf_bank": {"per_axis": 3}}
    nav = Navigator(grid, cfg, n_vehicles=3)
    radar = torch.full((3, k), float("nan"), dtype=D)
    track = nav.replay(t, truth.ins_pos[:, :k, :2], truth.ins_pos[:, :k, 2], radar)
    assert not bool(track.updated.any())
    p = 900.0
    expected = [p]
    for j in range(1, k):
        dt = float(t[j] - t[j - 1])
        a = math.exp(-dt / 8.0)
        p = a * a * p + 144.0 * (1.0 - a * a)
        expected.append(p)
    ref = torch.tensor(expected, dtype=D).expand(3, k)
    torch.testing.assert_close(track.cov[..., 2, 2], ref, rtol=1e-9, atol=0.0)
    assert track.counts["gaps"] == 3


@pytest.fixture(scope="module")
def tiny_flight_3() -> tuple[Any, Any]:
    from neuralmap.lab.scenario import load_scenario, scenario_tile
    from neuralmap.lab.simulator import simulate
    from neuralmap.terrain.grid import GridTerrain

    scenario = load_scenario("tiny")
    tile = scenario_tile(scenario)
    return simulate(scenario, tile, n_runs=3, seed=4), GridTerrain(tile, method="bilinear")
