"""The correlated-noise Kalman filter against a plain NumPy one-step predictor."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.wind import CorrelatedNoiseEKF, decorrelate


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
    filt = CorrelatedNoiseEKF(t(x0), t(P0))
    Qt, Ct, Rt = t(Q), t(C), t(R)
    xs, Ps = [], []
    for k in range(y.shape[0]):
        Fk, Ak, yk = t(F[k]), t(A[k]), t(y[k])
        filt.update(yk - (Ak @ filt.x.unsqueeze(-1)).squeeze(-1), Ak, Rt)
        x_post = filt.x
        fx = (Fk @ x_post.unsqueeze(-1)).squeeze(-1)
        r_post = yk - (Ak @ x_post.unsqueeze(-1)).squeeze(-1)
        if with_c:
            filt.predict(fx=fx, F=Fk, Q=Qt, C=Ct, R=Rt, A=Ak, residual=r_post)
        else:
            filt.predict(fx=fx, F=Fk, Q=Qt)
        xs.append(filt.x)
        Ps.append(filt.P)
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


def test_decorrelated_noise_is_uncorrelated_and_errors():
    rng = np.random.default_rng(11)
    B = rng.normal(size=(5, 5))
    joint = B @ B.T + np.eye(5)
    Q, C, R = (torch.as_tensor(a) for a in (joint[:3, :3], joint[:3, 3:], joint[3:, 3:]))
    x = torch.zeros(2, 3, dtype=torch.float64)
    dec = decorrelate(fx=x, F=torch.eye(3, dtype=torch.float64), Q=Q, C=C, R=R,
                      A=torch.zeros(2, 3, dtype=torch.float64),
                      residual=torch.zeros(2, 2, dtype=torch.float64))
    # cov(u − J e, e) = C − J R = 0 and Q* = Q − C R⁻¹ Cᵀ (Schur complement), PSD
    assert torch.allclose(C - dec.gain @ R, torch.zeros(3, 2, dtype=torch.float64),
                          atol=1e-12)
    assert torch.allclose(dec.Q, Q - C @ torch.linalg.solve(R, C.T), atol=1e-12)
    assert torch.linalg.eigvalsh(dec.Q).min() > 0
    with pytest.raises(NeuralMapError, match="inconsistent shapes"):
        decorrelate(fx=x, F=torch.eye(3, dtype=torch.float64), Q=Q, C=C.T, R=R,
                    A=torch.zeros(2, 3, dtype=torch.float64),
                    residual=torch.zeros(2, 2, dtype=torch.float64))
    with pytest.raises(NeuralMapError, match="not positive definite"):
        decorrelate(fx=x, F=torch.eye(3, dtype=torch.float64), Q=Q, C=C, R=-R,
                    A=torch.zeros(2, 3, dtype=torch.float64),
                    residual=torch.zeros(2, 2, dtype=torch.float64))
    filt = CorrelatedNoiseEKF(x, torch.eye(3, dtype=torch.float64))
    with pytest.raises(NeuralMapError, match="pass 'R', 'A' and 'residual'"):
        filt.predict(fx=x, F=torch.eye(3, dtype=torch.float64), Q=Q, C=C)
