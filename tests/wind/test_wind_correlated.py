"""The correlated-noise Kalman filter against a plain NumPy one-step predictor."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.wind import correlated_predict, correlated_update


def _random_system(rng, batch, n, m, steps):
    F = rng.normal(size=(steps, batch, n, n)) * 0.4 + np.eye(n) * 0.6
    A = rng.normal(size=(steps, batch, m, n))
    B = rng.normal(size=(batch, n + m, n + m))
    joint = B @ B.transpose(0, 2, 1) + 0.5 * np.eye(n + m)
    Q, C, R = joint[:, :n, :n], joint[:, :n, n:], joint[:, n:, n:]
    y = rng.normal(size=(steps, batch, m)) * 3.0
    x0 = rng.normal(size=(batch, n))
    G = rng.normal(size=(batch, n, n))
    P0 = G @ G.transpose(0, 2, 1) + np.eye(n)
    return F, A, Q, C, R, y, x0, P0


def _numpy_one_step_predictor(F, A, Q, C, R, y, x0, P0):
    """Simon (2006) §7.1: K̄ = (F P Aᵀ + C) S⁻¹, x⁻' = F x⁻ + K̄ r, P⁻' = F P Fᵀ + Q − K̄ S K̄ᵀ."""
    steps, batch = y.shape[:2]
    xs, Ps = [], []
    for b in range(batch):
        x, P = x0[b].copy(), P0[b].copy()
        xb, Pb = [], []
        for k in range(steps):
            Fk, Ak = F[k, b], A[k, b]
            S = Ak @ P @ Ak.T + R[b]
            K = (Fk @ P @ Ak.T + C[b]) @ np.linalg.inv(S)
            x = Fk @ x + K @ (y[k, b] - Ak @ x)
            P = Fk @ P @ Fk.T + Q[b] - K @ S @ K.T
            xb.append(x.copy())
            Pb.append(P.copy())
        xs.append(xb)
        Ps.append(Pb)
    return np.array(xs), np.array(Ps)  # (batch, steps, n), (batch, steps, n, n)


def _torch_filter(F, A, Q, C, R, y, x0, P0, with_c=True):
    t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    x, P = t(x0), t(P0)
    Qt, Ct, Rt = t(Q), t(C), t(R)
    xs, Ps = [], []
    for k in range(y.shape[0]):
        Fk, Ak, yk = t(F[k]), t(A[k]), t(y[k])
        r = yk - (Ak @ x.unsqueeze(-1)).squeeze(-1)
        x_post, P_post, _ = correlated_update(x, P, residual=r, A=Ak, R=Rt)
        fx = (Fk @ x_post.unsqueeze(-1)).squeeze(-1)
        r_post = yk - (Ak @ x_post.unsqueeze(-1)).squeeze(-1)
        if with_c:
            x, P = correlated_predict(x_post, P_post, fx=fx, F=Fk, Q=Qt, C=Ct, R=Rt, A=Ak,
                                      residual=r_post)
        else:
            x, P = correlated_predict(x_post, P_post, fx=fx, F=Fk, Q=Qt)
        xs.append(x)
        Ps.append(P)
    return torch.stack(xs, 1).numpy(), torch.stack(Ps, 1).numpy()


@pytest.mark.parametrize("m", [1, 2])
def test_matches_numpy_one_step_predictor(m):
    rng = np.random.default_rng(7 + m)
    system = _random_system(rng, batch=4, n=3, m=m, steps=25)
    x_ref, P_ref = _numpy_one_step_predictor(*system)
    x, P = _torch_filter(*system)
    assert np.allclose(x, x_ref, rtol=0, atol=1e-10 * max(1.0, np.abs(x_ref).max()))
    assert np.allclose(P, P_ref, rtol=0, atol=1e-10 * max(1.0, np.abs(P_ref).max()))
    assert np.allclose(P, P.transpose(0, 1, 3, 2), atol=0)


def test_ignoring_the_cross_covariance_differs():
    rng = np.random.default_rng(9)
    system = _random_system(rng, batch=2, n=3, m=1, steps=10)
    x_ref, _ = _numpy_one_step_predictor(*system)
    x, _ = _torch_filter(*system, with_c=False)
    assert np.abs(x - x_ref).max() > 1e-3


def test_zero_cross_covariance_is_plain_kalman_filter():
    rng = np.random.default_rng(10)
    F, A, Q, C, R, y, x0, P0 = _random_system(rng, batch=3, n=2, m=1, steps=15)
    C = np.zeros_like(C)
    x_ref, P_ref = _numpy_one_step_predictor(F, A, Q, C, R, y, x0, P0)
    x, P = _torch_filter(F, A, Q, C, R, y, x0, P0, with_c=False)
    assert np.allclose(x, x_ref, atol=1e-10) and np.allclose(P, P_ref, atol=1e-10)


def test_mask_keeps_prior_and_shapes_are_checked():
    x = torch.zeros(3, 2, dtype=torch.float64)
    P = torch.eye(2, dtype=torch.float64).expand(3, 2, 2)
    r = torch.ones(3, 1, dtype=torch.float64)
    A = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    R = torch.eye(1, dtype=torch.float64)
    mask = torch.tensor([True, False, True])
    x1, P1, diag = correlated_update(x, P, residual=r, A=A, R=R, mask=mask)
    assert torch.equal(x1[1], x[1]) and torch.equal(P1[1], P[1])
    assert x1[0, 0].item() == pytest.approx(0.5) and P1[0, 0, 0].item() == pytest.approx(0.5)
    assert diag.applied.tolist() == [True, False, True]
    with pytest.raises(NeuralMapError, match="'A' has shape"):
        correlated_update(x, P, residual=r, A=torch.ones(3, 1, 3, dtype=torch.float64), R=R)
    with pytest.raises(NeuralMapError, match="pass 'R', 'A' and 'residual'"):
        correlated_predict(x, P, fx=x, F=torch.eye(2, dtype=torch.float64),
                           Q=torch.eye(2, dtype=torch.float64),
                           C=torch.ones(2, 1, dtype=torch.float64))
