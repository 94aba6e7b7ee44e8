"""Noise learning through the TAN filter: TBPTT bookkeeping and recovery of known Q and R."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.scenario import Scenario
from neuralmap.lab.simulator import simulate
from neuralmap.learning.flights import FlightBatch
from neuralmap.learning.likelihood import tan_log_likelihood
from neuralmap.learning.noise_fit import fit_noise
from neuralmap.learning.noise_model import NoiseModel
from neuralmap.linearize.factory import make_linearizer
from neuralmap.tan.model import TanModel

F64 = torch.float64
SPACING = 100.0


def _plane(n_runs: int, duration: float, seed: int) -> tuple[Scenario, DemTile, FlightBatch]:
    yy, xx = np.mgrid[0:80, 0:80]
    tile = DemTile(heights=0.08 * xx * SPACING - 0.05 * yy * SPACING + 500.0,
                   spacing=(SPACING, SPACING), name="plane")
    scenario = Scenario(
        name="plane", tile="plane", dt=1.0, duration_s=duration, start_xy=[3000.0, 3000.0],
        start_spread_m=200.0, speed_mps=80.0, heading_deg=60.0, altitude_agl_m=500.0,
        init_pos_sigma_m=50.0, init_alt_sigma_m=10.0, init_vel_sigma_mps=0.5,
        alt_noise_sigma_m=2.0, altimeter_sigma_m=5.0, truth_model="dem",
        P0_diag=[2500.0, 2500.0, 100.0, 0.25, 0.25], Q_diag=[1.0, 1.0, 4.0, 0.0025, 0.0025],
        R_m2=25.0,
    ).validate()
    return scenario, tile, FlightBatch.from_truth(simulate(scenario, tile, n_runs=n_runs,
                                                           seed=seed))


def test_truncated_windows_chain_to_the_whole_flight() -> None:
    """Windows carried state to state give the whole-flight likelihood (values)."""
    scenario, tile, flights = _plane(4, 12.0, seed=0)
    model = TanModel.from_scenario(scenario)
    lin = make_linearizer("bilinear", tile=tile, variance="zero")
    kw = {"F": model.transition(), "Q": model.filter_process_noise(),
          "R": torch.tensor(25.0, dtype=F64)}
    whole = tan_log_likelihood(flights, lin, P0=model.filter_prior(), **kw)
    state, total = None, torch.zeros(4, dtype=F64)
    for start in (1, 6, 11):
        part = tan_log_likelihood(flights, lin, P0=model.filter_prior(), state=state,
                                  start=start, stop=min(start + 5, 13), **kw)
        total = total + part.log_likelihood
        state = part.state.detach()
    torch.testing.assert_close(total, whole.log_likelihood)
    with pytest.raises(NeuralMapError, match="tbptt_steps"):
        fit_noise(flights, lin, NoiseModel([1.0] * 5, 25.0), F=kw["F"],
                  P0=model.filter_prior(), tbptt_steps=0)
    with pytest.raises(NeuralMapError, match="optimizer"):
        fit_noise(flights, lin, NoiseModel([1.0] * 5, 25.0), F=kw["F"],
                  P0=model.filter_prior(), optimizer="lbfgs", epochs=1)


@pytest.mark.slow
def test_learning_recovers_altimeter_and_altitude_noise_on_a_plane() -> None:
    """From R x 10, Q x 0.1: R and Q_h (the observable ones) come back within 15 %."""
    scenario, tile, flights = _plane(96, 30.0, seed=1)
    model = TanModel.from_scenario(scenario)
    noise = NoiseModel([0.1 * q for q in model.Q], 10.0 * model.base_R)
    fit = fit_noise(flights, make_linearizer("bilinear", tile=tile, variance="zero"), noise,
                    F=model.transition(), P0=model.filter_prior(), epochs=40, lr=0.1,
                    tbptt_steps=10)
    values = fit.history[-1]
    assert values["R"] == pytest.approx(25.0, rel=0.15)
    assert values["Q_diag"][2] == pytest.approx(4.0, rel=0.15)
    lls = [h["log_likelihood_per_update"] for h in fit.history]
    assert lls[-1] > lls[0] + 0.5
