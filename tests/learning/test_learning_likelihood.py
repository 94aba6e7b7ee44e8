"""The innovation log-likelihood through the TAN filter: gradients, masks, NaN samples."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.scenario import Scenario
from neuralmap.lab.simulator import simulate
from neuralmap.learning.covariance import (
    LogCholeskyCovariance,
    LogDiagonalCovariance,
    make_covariance,
)
from neuralmap.learning.flights import FlightBatch
from neuralmap.learning.likelihood import linear_log_likelihood, tan_log_likelihood
from neuralmap.learning.noise_model import NoiseModel
from neuralmap.linearize.factory import make_linearizer
from neuralmap.tan.model import TanModel

F64 = torch.float64
SPACING = 100.0


@pytest.fixture(scope="module")
def plane() -> tuple[Scenario, DemTile, FlightBatch]:
    """A plane terrain: the TAN measurement is linear, the likelihood exactly Gaussian."""
    yy, xx = np.mgrid[0:80, 0:80]
    tile = DemTile(heights=0.08 * xx * SPACING - 0.05 * yy * SPACING + 500.0,
                   spacing=(SPACING, SPACING), name="plane")
    scenario = Scenario(
        name="plane", tile="plane", dt=1.0, duration_s=15.0, start_xy=[3000.0, 3000.0],
        start_spread_m=200.0, speed_mps=80.0, heading_deg=60.0, altitude_agl_m=500.0,
        init_pos_sigma_m=50.0, init_alt_sigma_m=10.0, init_vel_sigma_mps=0.5,
        altimeter_sigma_m=5.0, truth_model="dem",
        P0_diag=[2500.0, 2500.0, 100.0, 0.25, 0.25], Q_diag=[1.0, 1.0, 1.0, 0.0025, 0.0025],
        R_m2=25.0,
    ).validate()
    truth = simulate(scenario, tile, n_runs=6, seed=3)
    return scenario, tile, FlightBatch.from_truth(truth)


def _loss(flights: FlightBatch, tile: DemTile, scenario: Scenario, noise: NoiseModel) -> torch.Tensor:
    model = TanModel.from_scenario(scenario)
    lin = make_linearizer("bilinear", tile=tile, variance="zero")
    return tan_log_likelihood(flights, lin, F=model.transition(), Q=noise.Q(), R=noise.R(),
                              P0=model.filter_prior()).log_likelihood.sum()


@pytest.mark.parametrize("kind", ["log_diagonal", "log_cholesky"])
def test_tan_likelihood_gradient_matches_finite_differences(plane, kind: str) -> None:  # noqa: ANN001
    scenario, tile, flights = plane
    q0 = torch.diag(torch.tensor([2.0, 1.5, 0.7, 0.004, 0.003], dtype=F64))
    if kind == "log_cholesky":
        q0[0, 1] = q0[1, 0] = 0.3
    noise = NoiseModel(q0, 40.0, q_kind=kind)
    loss = _loss(flights, tile, scenario, noise)
    params = [noise.q.theta, noise.log_r]
    grads = torch.autograd.grad(loss, params)
    step = 1e-6
    with torch.no_grad():
        for p, g in zip(params, grads, strict=True):
            # every log-diagonal entry; for log-Cholesky the diagonal, one correlation and R
            picks = range(p.numel()) if p.numel() <= 5 else (0, 1, 5, 9, 14)
            for i in picks:
                flat = p.view(-1)
                flat[i] += step
                up = _loss(flights, tile, scenario, noise)
                flat[i] -= 2 * step
                down = _loss(flights, tile, scenario, noise)
                flat[i] += step
                fd = (up - down) / (2 * step)
                assert float(g.view(-1)[i]) == pytest.approx(float(fd), rel=1e-5, abs=1e-6)


def test_likelihood_equals_brute_force_gaussian_density() -> None:
    """Prediction-error decomposition = the joint Gaussian density of all measurements."""
    gen = torch.Generator().manual_seed(0)
    F = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=F64)
    Q = torch.diag(torch.tensor([0.5, 0.02], dtype=F64))
    P0 = torch.diag(torch.tensor([3.0, 1.0], dtype=F64))
    K = 6
    H = torch.randn(1, K + 1, 2, generator=gen, dtype=F64)
    z = torch.randn(1, K + 1, generator=gen, dtype=F64)
    run = linear_log_likelihood(z, H, F=F, Q=Q, R=torch.tensor(2.0, dtype=F64), P0=P0)
    # joint covariance of z_1..z_K: Cov(x_j, x_k) = F^(k-j) Cov(x_j) for j <= k
    covs = [P0]
    for _ in range(K):
        covs.append(F @ covs[-1] @ F.T + Q)
    C = torch.zeros(K, K, dtype=F64)
    for j in range(1, K + 1):
        for k in range(j, K + 1):
            cross = torch.linalg.matrix_power(F, k - j) @ covs[j]
            C[j - 1, k - 1] = C[k - 1, j - 1] = H[0, k] @ cross @ H[0, j]
    C += 2.0 * torch.eye(K, dtype=F64)
    dist = torch.distributions.MultivariateNormal(torch.zeros(K, dtype=F64), C)
    assert float(run.log_likelihood[0]) == pytest.approx(float(dist.log_prob(z[0, 1:])), rel=1e-10)


def test_padded_flights_equal_separate_runs(plane) -> None:  # noqa: ANN001
    """Different lengths: a padded batch gives each flight's own likelihood; padding adds 0."""
    scenario, tile, flights = plane
    noise = NoiseModel(torch.tensor(scenario.Q_diag, dtype=F64), 25.0)
    lengths = [16, 13, 8]
    batch = FlightBatch.from_sequences(
        1.0, [flights.ins_pos[i, :n] for i, n in enumerate(lengths)],
        [flights.radar[i, :n] for i, n in enumerate(lengths)])
    assert batch.n_padded == (16 - 13) + (16 - 8)
    together = tan_log_likelihood(batch, make_linearizer("bilinear", tile=tile, variance="zero"),
                                  F=TanModel.from_scenario(scenario).transition(), Q=noise.Q(),
                                  R=noise.R(), P0=TanModel.from_scenario(scenario).filter_prior())
    for i, n in enumerate(lengths):
        alone = FlightBatch(1.0, flights.ins_pos[i:i + 1, :n], flights.radar[i:i + 1, :n],
                            torch.ones(1, n, dtype=torch.bool))
        ll = _loss(alone, tile, scenario, noise)
        assert float(together.log_likelihood[i].detach()) == pytest.approx(float(ll.detach()), rel=1e-12)
        assert int(together.n_updates[i]) == n - 1


def test_nan_altimeter_samples_are_skipped_counted_and_keep_gradients_finite(plane) -> None:  # noqa: ANN001
    scenario, tile, flights = plane
    radar = flights.radar.clone()
    radar[0, 3] = float("nan")
    radar[2, 7:10] = float("nan")
    holed = FlightBatch(flights.dt, flights.ins_pos, radar, flights.valid)
    assert holed.n_missing == 4
    noise = NoiseModel(torch.tensor(scenario.Q_diag, dtype=F64), 25.0)
    loss = _loss(holed, tile, scenario, noise)
    loss.backward()
    assert torch.isfinite(loss)
    assert all(torch.isfinite(p.grad).all() for p in noise.parameters())
    # skipping = predict only: equal to the flight with the sample removed from the update
    model = TanModel.from_scenario(scenario)
    run = tan_log_likelihood(holed, make_linearizer("bilinear", tile=tile, variance="zero"),
                             F=model.transition(), Q=noise.Q(), R=noise.R(),
                             P0=model.filter_prior())
    assert run.n_updates.tolist() == [14, 15, 12, 15, 15, 15]
    assert bool(torch.isnan(run.nis[0, 2])) and bool(torch.isnan(run.nis[2, 6:9]).all())


def test_covariance_parametrisations_stay_positive_definite_and_refuse_indefinite_starts() -> None:
    full = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=F64)
    chol = LogCholeskyCovariance(full)
    torch.testing.assert_close(chol(), full)
    with torch.no_grad():
        chol.theta.copy_(torch.tensor([-30.0, 50.0, 3.0], dtype=F64))  # any theta
    assert float(torch.linalg.eigvalsh(chol()).min()) > 0.0
    diag = LogDiagonalCovariance([1.0, 0.01])
    torch.testing.assert_close(torch.diagonal(diag()), torch.tensor([1.0, 0.01], dtype=F64))
    for bad in ([[1.0, 2.0], [2.0, 1.0]], [1.0, 0.0], [1.0, -1.0], [[1.0, 0.0], [0.5, 1.0]],
                [float("nan"), 1.0]):
        with pytest.raises(NeuralMapError, match="LogCholeskyCovariance|LogDiagonal"):
            make_covariance("log_cholesky", torch.tensor(bad, dtype=F64))
    with pytest.raises(NeuralMapError, match="off-diagonal"):
        LogDiagonalCovariance(full)
    with pytest.raises(NeuralMapError, match="unknown"):
        make_covariance("cholesky", full)
    with pytest.raises(NeuralMapError, match="R0"):
        NoiseModel([1.0, 1.0], 0.0)
    assert math.isfinite(NoiseModel([1.0, 1.0], 2.0).values()["R"])
