"""The TAN step: Φ, H, residual sign, update direction, linearisation error, off-map masking."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.ekf import BatchedEKF
from neuralmap.linearize.autograd import AutogradLinearizer
from neuralmap.linearize.base import Linearization, Linearizer
from neuralmap.linearize.factory import make_linearizer
from neuralmap.tan.ekf_step import tan_filter_step
from neuralmap.tan.model import measurement_jacobian, transition_matrix
from neuralmap.terrain.base import TerrainModel

F64 = torch.float64


class WavyTerrain(TerrainModel):
    """Analytic smooth terrain ``300 + 50 sin(x/400) cos(y/300)`` (independent of grids)."""

    extent = (0.0, 5000.0, 0.0, 5000.0)

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        return 300.0 + 50.0 * torch.sin(xy[..., 0] / 400.0) * torch.cos(xy[..., 1] / 300.0)


def plane_tile(a: float, b: float, c: float = 400.0) -> DemTile:
    x = np.arange(64) * 50.0
    y = np.arange(64) * 50.0
    xx, yy = np.meshgrid(x, y)
    return DemTile(heights=a * xx + b * yy + c, spacing=(50.0, 50.0), name="plane")


def test_transition_matrix_and_jacobian() -> None:
    phi = transition_matrix(2.0)
    expected = torch.eye(5, dtype=F64)
    expected[0, 3] = expected[1, 4] = 2.0
    assert torch.equal(phi, expected)
    H = measurement_jacobian(torch.tensor([[0.1, -0.3]], dtype=F64))
    assert torch.equal(H, torch.tensor([[-0.1, 0.3, 1.0, 0.0, 0.0]], dtype=F64))
    with pytest.raises(NeuralMapError, match="dt"):
        transition_matrix(0.0)
    with pytest.raises(NeuralMapError, match=r"\(N, 2\)"):
        measurement_jacobian(torch.zeros(3, 3))


def test_plane_update_matches_closed_form_and_moves_toward_truth() -> None:
    """On a plane the EKF is linear: compare with a hand-written float64 Kalman update."""
    a, b = 0.2, 0.1
    tile = plane_tile(a, b)
    lin = make_linearizer("bilinear", tile=tile)
    truth_err = np.array([50.0, -30.0, 4.0, 0.0, 0.0])  # δX = INS − truth
    p_true = np.array([1500.0, 1600.0])
    h_true = 2000.0
    terrain = a * p_true[0] + b * p_true[1] + 400.0
    radar = h_true - terrain  # noise-free
    ins = np.array([p_true[0] + truth_err[0], p_true[1] + truth_err[1], h_true + truth_err[2]])
    P0 = np.diag([1e4, 1e4, 100.0, 1.0, 1.0])
    Q = np.diag([1.0, 1.0, 1.0, 0.01, 0.01])
    R = 25.0
    F = transition_matrix(1.0).numpy()

    ekf = BatchedEKF(torch.zeros(1, 5, dtype=F64), torch.tensor(P0))
    diag = tan_filter_step(
        ekf, torch.tensor(ins)[None], torch.tensor([radar]), lin, F=torch.tensor(F),
        Q=torch.tensor(Q), R=R,
    )
    # closed form: r = H (δX − 0), H = [−a, −b, 1, 0, 0]
    H = np.array([-a, -b, 1.0, 0.0, 0.0])
    P_pred = F @ P0 @ F.T + Q
    r = float(H @ truth_err)
    assert float(diag.residual[0]) == pytest.approx(r, abs=1e-9)
    S = float(H @ P_pred @ H) + R
    K = P_pred @ H / S
    x_ref = K * r
    A = np.eye(5) - np.outer(K, H)
    P_ref = A @ P_pred @ A.T + R * np.outer(K, K)  # Joseph form
    assert np.allclose(ekf.x[0].numpy(), x_ref, rtol=1e-10, atol=1e-12)
    assert np.allclose(ekf.P[0].numpy(), P_ref, rtol=1e-10, atol=1e-10)
    assert float(diag.nis[0]) == pytest.approx(r * r / S, rel=1e-10)
    # the estimate moved toward the truth error along the observable direction
    g = np.array([a, b])
    along_true = float(g @ truth_err[:2]) - truth_err[2]
    along_est = float(g @ ekf.x[0, :2].numpy()) - float(ekf.x[0, 2])
    assert 0.0 < along_est < along_true
    # corrected estimate error |δX − δX̂| shrinks in the measured direction
    assert abs(H @ (truth_err - ekf.x[0].numpy())) < abs(H @ truth_err)


def test_linearised_residual_matches_exact_for_small_errors() -> None:
    """r = (ĥ − t(p̂)) − radar equals H (δX − δX̂⁻) up to second order in the error."""
    terrain = WavyTerrain()
    lin = AutogradLinearizer(terrain)
    p_true = torch.tensor([[1200.0, 2100.0], [3000.0, 800.0], [2500.0, 2500.0]], dtype=F64)
    h_true = torch.full((3,), 1500.0, dtype=F64)
    radar = h_true - terrain(p_true)
    x_prior = torch.tensor([[20.0, -10.0, 5.0, 0.0, 0.0]] * 3, dtype=F64)
    F = torch.eye(5, dtype=F64)  # keep the prior: x⁻ = x
    Q = torch.diag(torch.full((5,), 1e-6, dtype=F64))
    gaps = []
    for scale in (1.0, 0.5):
        d = scale * torch.tensor([1.0, -0.5, 0.3, 0.0, 0.0], dtype=F64)
        delta = x_prior + d  # true INS error
        ins = torch.cat([p_true + delta[:, :2], (h_true + delta[:, 2])[:, None]], dim=1)
        ekf = BatchedEKF(x_prior.clone(), torch.eye(5, dtype=F64) * 100.0)
        diag = tan_filter_step(ekf, ins, radar, lin, F=F, Q=Q, R=1.0)
        p_hat = ins[:, :2] - x_prior[:, :2]
        exact = (ins[:, 2] - x_prior[:, 2]) - terrain(p_hat) - radar
        assert torch.allclose(diag.residual, exact, atol=1e-10)
        slope = lin(p_hat).slope
        linear = (measurement_jacobian(slope) * d).sum(1)
        gaps.append((diag.residual - linear).abs().max().item())
        assert torch.allclose(diag.residual, linear, atol=2e-3)  # curvature ~3e-4 m⁻¹
        assert not torch.allclose(diag.residual, -linear, atol=1e-2)  # the sign matters
    assert gaps[1] < 0.35 * gaps[0]  # second order: halving the error quarters the gap


class NanOffMap(Linearizer):
    """Linearizer that returns NaN off the map, to check the masking."""

    extent = (0.0, 1000.0, 0.0, 1000.0)

    def forward(self, xy: torch.Tensor, pos_cov: torch.Tensor | None = None) -> Linearization:
        inside = (xy >= 0.0).all(1) & (xy <= 1000.0).all(1)
        nan = torch.full_like(xy[:, 0], float("nan"))
        height = torch.where(inside, 100.0 + 0.1 * xy[:, 0], nan)
        slope = torch.stack([torch.where(inside, 0.1, nan), torch.where(inside, 0.0, nan)], 1)
        return Linearization(height, slope, torch.zeros_like(height))


def test_off_map_estimates_are_masked_and_flagged() -> None:
    ins = torch.tensor([[500.0, 500.0, 1000.0], [1500.0, 500.0, 1000.0]], dtype=F64)
    radar = torch.tensor([840.0, 840.0], dtype=F64)
    ekf = BatchedEKF(torch.zeros(2, 5, dtype=F64), torch.eye(5, dtype=F64) * 100.0)
    F = transition_matrix(1.0)
    Q = torch.eye(5, dtype=F64) * 0.1
    diag = tan_filter_step(ekf, ins, radar, NanOffMap(), F=F, Q=Q, R=4.0)
    assert diag.on_map.tolist() == [True, False]
    assert diag.updated.tolist() == [True, False]
    assert torch.isfinite(ekf.x).all() and torch.isfinite(ekf.P).all()
    assert ekf.healthy.all()
    # the off-map sample only predicted: x stays 0, P = F P0 Fᵀ + Q
    assert torch.equal(ekf.x[1], torch.zeros(5, dtype=F64))
    assert torch.allclose(ekf.P[1], F @ (torch.eye(5, dtype=F64) * 100.0) @ F.T + Q)
    assert float(ekf.x[0].abs().sum()) > 0.0
    # an explicit mask skips on-map samples too
    diag = tan_filter_step(ekf, ins, radar, NanOffMap(), F=F, Q=Q, R=4.0,
                           mask=torch.tensor([False, True]))
    assert diag.updated.tolist() == [False, False]


def test_bad_shapes() -> None:
    ekf = BatchedEKF(torch.zeros(2, 5, dtype=F64), torch.eye(5, dtype=F64))
    with pytest.raises(NeuralMapError, match="ins_pos"):
        tan_filter_step(ekf, torch.zeros(3, 3, dtype=F64), torch.zeros(3, dtype=F64),
                        NanOffMap(), F=transition_matrix(1.0), Q=torch.eye(5), R=1.0)
