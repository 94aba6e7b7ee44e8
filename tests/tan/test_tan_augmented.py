"""Augmented 6- and 7-state TAN models: the paper's matrices, the stationary map-error
covariance, reduction to the 5-state filter, and a FilterPy reference run."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuralmap.errors import ArmaModel
from neuralmap.exceptions import NeuralMapError
from neuralmap.filters import BatchedEKF
from neuralmap.tan.augmented import (
    augmented_initial_covariance,
    augmented_measurement_jacobian,
    augmented_process_noise,
    augmented_transition_matrix,
    paper_augmented_tuning,
    stationary_map_covariance,
)
from neuralmap.tan.model import measurement_jacobian, transition_matrix


def test_paper_matrices() -> None:
    T = 1.0
    f6 = augmented_transition_matrix(T, (0.5315,))
    ref6 = np.eye(6)
    ref6[0, 3] = ref6[1, 4] = T
    ref6[5, 5] = 0.5315
    np.testing.assert_array_equal(f6.numpy(), ref6)
    f7 = augmented_transition_matrix(T, (0.44417, 0.16430))
    ref7 = np.eye(7)
    ref7[0, 3] = ref7[1, 4] = T
    ref7[5, 5:] = [0.44417, 0.16430]
    ref7[6, 5:] = [1.0, 0.0]
    np.testing.assert_array_equal(f7.numpy(), ref7)
    slope = torch.tensor([[0.1, -0.2]], dtype=torch.float64)
    np.testing.assert_array_equal(
        augmented_measurement_jacobian(slope, 2).numpy(), [[-0.1, 0.2, 1, 0, 0, -1, 0]]
    )
    tuning = paper_augmented_tuning((0.5315,), 0.5)
    np.testing.assert_array_equal(
        torch.diagonal(tuning["P0"]).sqrt().numpy(), [400, 400, 400, 40, 40, 40]
    )
    np.testing.assert_allclose(
        torch.diagonal(tuning["Q"]).sqrt().numpy(), [5, 5, 5, 0.5, 0.5, 0.5]
    )
    assert tuning["R"] == 400.0


@pytest.mark.parametrize("ar", [(0.5315,), (0.44417, 0.16430), (1.2, -0.5, 0.1)], ids=str)
def test_stationary_covariance_is_the_ar_autocovariance(ar: tuple[float, ...]) -> None:
    sigma_e = 0.7
    gamma = ArmaModel(phi=ar, sigma2=sigma_e**2).autocovariance(len(ar))
    p = len(ar)
    toeplitz = gamma[np.abs(np.subtract.outer(np.arange(p), np.arange(p)))]
    np.testing.assert_allclose(stationary_map_covariance(ar, sigma_e).numpy(), toeplitz,
                               rtol=1e-10)
    if p == 1:  # closed form σ_e² / (1 − a²)
        assert gamma[0] == pytest.approx(sigma_e**2 / (1 - ar[0] ** 2), rel=1e-12)


def _run(ekf: BatchedEKF, F: torch.Tensor, Q: torch.Tensor, slopes: torch.Tensor,
         residuals: torch.Tensor, R: float, p: int, observed: bool) -> None:
    for k in range(slopes.shape[0]):
        ekf.predict(F, Q)
        if p:
            H = augmented_measurement_jacobian(slopes[k], p, observed=observed)
        else:
            H = measurement_jacobian(slopes[k])
        ekf.update(residuals[k], H, R)


@pytest.mark.parametrize("ar", [(0.5315,), (0.44417, 0.16430)], ids=["6-state", "7-state"])
def test_reduces_to_five_state_filter(ar: tuple[float, ...]) -> None:
    gen = torch.Generator().manual_seed(0)
    n, steps, p = 32, 25, len(ar)
    slopes = 0.3 * torch.randn(steps, n, 2, generator=gen, dtype=torch.float64)
    residuals = 20.0 * torch.randn(steps, n, generator=gen, dtype=torch.float64)
    x0 = torch.randn(n, 5, generator=gen, dtype=torch.float64)
    p0 = torch.diag(torch.tensor([400.0, 400, 400, 40, 40], dtype=torch.float64) ** 2)
    q = torch.tensor([5.0, 5, 5, 0.5, 0.5], dtype=torch.float64)
    R = 400.0
    five = BatchedEKF(x0, p0)
    _run(five, transition_matrix(1.0), torch.diag(q**2), slopes, residuals, R, 0, True)
    F = augmented_transition_matrix(1.0, ar)
    Q = augmented_process_noise(q, 0.5, p)
    x0a = torch.cat([x0, torch.zeros(n, p, dtype=torch.float64)], dim=1)

    # switched off: the map-error column of H is zero -> identical navigation states
    off = BatchedEKF(x0a, augmented_initial_covariance(p0, 40.0, p))
    _run(off, F, Q, slopes, residuals, R, p, observed=False)
    torch.testing.assert_close(off.x[:, :5], five.x, rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(off.P[:, :5, :5], five.P, rtol=1e-12, atol=1e-9)
    assert torch.count_nonzero(off.P[:, :5, 5:]) == 0

    # observed but vanishing (map-error σ = 1 mm, stationary P0): the same in the limit;
    # the difference scales with σ² (measured 1e-9 relative at 1 mm)
    small = 1e-3
    tiny = BatchedEKF(x0a, augmented_initial_covariance(
        p0, stationary_map_covariance(ar, small), p))
    _run(tiny, F, augmented_process_noise(q, small, p), slopes, residuals, R, p, observed=True)
    assert bool(tiny.healthy.all())
    rel = (tiny.x[:, :5] - five.x).abs().max() / five.x.abs().max()
    assert rel < 1e-8

    # and with a real map-error state the estimate differs (the test can fail)
    on = BatchedEKF(x0a, augmented_initial_covariance(p0, 40.0, p))
    _run(on, F, Q, slopes, residuals, R, p, observed=True)
    assert (on.x[:, :5] - five.x).abs().max() > 1.0


def test_six_state_matches_filterpy() -> None:
    from filterpy.kalman import KalmanFilter

    tuning = paper_augmented_tuning((0.5315,), 0.49)
    rng = np.random.default_rng(1)
    kf = KalmanFilter(dim_x=6, dim_z=1)
    kf.x = np.zeros((6, 1))
    kf.P = tuning["P0"].numpy().copy()
    kf.F = tuning["F"].numpy()
    kf.Q = tuning["Q"].numpy()
    kf.R = np.array([[tuning["R"]]])
    ekf = BatchedEKF(torch.zeros(1, 6, dtype=torch.float64), tuning["P0"])
    for _ in range(30):
        slope = rng.normal(scale=0.3, size=(1, 2))
        z = rng.normal(scale=20.0)
        H = augmented_measurement_jacobian(torch.tensor(slope), 1)
        kf.predict()
        kf.update(np.array([[z]]), H=H.numpy())
        ekf.predict(tuning["F"], tuning["Q"])
        # the EKF's residual is the innovation about the prior, z − H x⁻
        residual = torch.tensor([z], dtype=torch.float64) - (H * ekf.x).sum(1)
        ekf.update(residual, H, tuning["R"])
    np.testing.assert_allclose(ekf.x.numpy()[0], kf.x[:, 0], rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(ekf.P.numpy()[0], kf.P, rtol=1e-10, atol=1e-9)


@pytest.mark.parametrize("ar", [(1.0,), (0.7, 0.4), ()], ids=str)
def test_bad_ar_parameters(ar: tuple[float, ...]) -> None:
    with pytest.raises(NeuralMapError, match="not stationary|at least one AR coefficient"):
        augmented_transition_matrix(1.0, ar)
    with pytest.raises(NeuralMapError, match="not stationary|at least one AR coefficient"):
        paper_augmented_tuning(ar, 0.5)


def test_augmented_information_equals_direct_expectation() -> None:
    from neuralmap.tan.augmented import augment_information

    gen = torch.Generator().manual_seed(3)
    slopes = 0.4 * torch.randn(50, 2, generator=gen, dtype=torch.float64) + 0.1
    R = 25.0
    rows5 = torch.cat([-slopes, torch.ones(50, 1, dtype=torch.float64),
                       torch.zeros(50, 2, dtype=torch.float64)], dim=1)
    info5 = torch.einsum("ni,nj->ij", rows5, rows5) / (50 * R)
    for p in (1, 2):
        rows = augmented_measurement_jacobian(slopes, p)
        direct = torch.einsum("ni,nj->ij", rows, rows) / (50 * R)
        torch.testing.assert_close(augment_information(info5, p), direct, rtol=1e-14,
                                   atol=1e-16)


@pytest.fixture(scope="module")
def tiny():
    from neuralmap.lab.scenario import load_scenario, scenario_tile
    from neuralmap.lab.simulator import simulate

    scenario = load_scenario("tiny")
    tile = scenario_tile(scenario)
    return scenario, tile, simulate(scenario, tile, n_runs=6, seed=3)


@pytest.mark.parametrize("ar", [(0.5315,), (0.44417, 0.16430)], ids=["6-state", "7-state"])
def test_run_filter_switched_off_equals_five_state(tiny, ar: tuple[float, ...]) -> None:
    from neuralmap.lab.monte_carlo import run_filter
    from neuralmap.linearize.factory import make_linearizer
    from neuralmap.tan.augmented import AugmentedTanModel
    from neuralmap.tan.model import TanModel

    scenario, tile, truth = tiny
    lin = make_linearizer("nine_point", tile=tile)
    five = run_filter(truth, lin, scenario)
    base = TanModel.from_scenario(scenario)
    off = run_filter(truth, lin, scenario,
                     model=AugmentedTanModel(base, ar, 0.5, observed=False))
    torch.testing.assert_close(off.err, five.err, rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(off.P, five.P, rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(off.nis[:, 1:], five.nis[:, 1:], rtol=1e-10, atol=1e-12)
    on = run_filter(truth, lin, scenario, model=AugmentedTanModel(base, ar, 0.5))
    assert on.err.shape == five.err.shape and bool(on.healthy.all())
    assert float((on.err - five.err).abs().max()) > 1e-3


def test_augmented_run_matches_filterpy_ekf(tiny) -> None:
    """FilterPy EKF on 6 states; predicted clearance ĥ − (h_map(p̂) − ê_r)."""
    from filterpy.kalman import ExtendedKalmanFilter

    from neuralmap.lab.monte_carlo import run_filter
    from neuralmap.linearize.factory import make_linearizer
    from neuralmap.tan.augmented import AugmentedTanModel
    from neuralmap.tan.model import TanModel

    scenario, tile, truth = tiny
    lin = make_linearizer("bilinear", tile=tile)
    model = AugmentedTanModel.paper(TanModel.from_scenario(scenario), (0.5315,), 0.9)
    run = run_filter(truth, lin, scenario, model=model)
    for i in (0, 4):
        ekf = ExtendedKalmanFilter(dim_x=6, dim_z=1)
        ekf.x = np.zeros((6, 1))
        ekf.P = model.filter_prior().numpy().copy()
        ekf.F = model.transition().numpy()
        ekf.Q = model.filter_process_noise().numpy()
        for k in range(1, truth.n_steps + 1):
            ins = truth.ins_pos[i, k].numpy()
            ekf.predict()

            def linearise(x: np.ndarray, ins: np.ndarray = ins):
                return lin(torch.tensor((ins[:2] - x[:2, 0])[None]))

            def hx(x: np.ndarray, ins: np.ndarray = ins) -> np.ndarray:
                return np.array([[ins[2] - x[2, 0] - float(linearise(x).height[0]) + x[5, 0]]])

            def jacobian(x: np.ndarray) -> np.ndarray:
                sx, sy = linearise(x).slope[0].tolist()
                return np.array([[sx, sy, -1.0, 0.0, 0.0, 1.0]])  # ∂h(x)/∂x = −H

            R = model.base_R + float(linearise(ekf.x).variance[0])
            ekf.update(np.array([[float(truth.radar[i, k])]]), jacobian, hx, R=np.array([[R]]))
            err_ref = truth.ins_error[i, k].numpy() - ekf.x[:5, 0]
            assert np.allclose(run.err[i, k].numpy(), err_ref, rtol=1e-9, atol=1e-7), (i, k)
            assert np.allclose(run.P[i, k].numpy(), ekf.P[:5, :5], rtol=1e-9, atol=1e-7), (i, k)


def test_augmented_model_tuning_and_bad_input() -> None:
    from neuralmap.tan.augmented import AugmentedTanModel
    from neuralmap.tan.model import TanModel

    base = TanModel(dt=1.0, P0=(1.0,) * 5, Q=(0.1,) * 5, R_altimeter=9.0, fit_variance=1.0,
                    truth_P0=(1.0,) * 5, truth_mean=(0.0,) * 5, truth_Q=(0.1,) * 5, truth_R=9.0)
    paper = AugmentedTanModel.paper(base, (0.44417, 0.16430), 0.51)
    assert paper.n_states == 7 and paper.base_R == 400.0
    np.testing.assert_allclose(torch.diagonal(paper.filter_prior()).sqrt().numpy(),
                               [400, 400, 400, 40, 40, 40, 40])
    np.testing.assert_allclose(torch.diagonal(paper.filter_process_noise()).sqrt().numpy(),
                               [5, 5, 5, 0.5, 0.5, 0.51, 0])
    consistent = AugmentedTanModel(base, (0.5315,), 0.8)
    assert float(consistent.filter_prior()[5, 5]) == pytest.approx(0.64 / (1 - 0.5315**2))
    assert consistent.base_R == 10.0
    with pytest.raises(NeuralMapError, match="not stationary"):
        AugmentedTanModel(base, (1.1,), 0.5)
    with pytest.raises(NeuralMapError, match="p0_map must hold 2"):
        AugmentedTanModel(base, (0.4, 0.1), 0.5, p0_map=(40.0,))
    with pytest.raises(NeuralMapError, match="give p0_map"):
        AugmentedTanModel(base, (0.5,), 0.0)
