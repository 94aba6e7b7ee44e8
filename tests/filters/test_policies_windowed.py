"""The windowed, block-restricted adaptive factor against a NumPy reference.

Reference: a plain float64 NumPy Kalman filter, one sample at a time, with the window of
innovations kept in a Python list (covariance matching, Mohamed & Schwarz 1999; Yang & Xu
2003) and the factor applied as ``D (P⁻ − Q) D + Q`` on the block (SEEDS 003's
``α Φ P Φᵀ + Q`` restricted to the block).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters import BatchedEKF, Compose, InnovationInflation, QualityR, WindowedInflation
from neuralmap.filters.policies import windowed_inflation_factor

D = torch.float64


def _system() -> tuple[np.ndarray, ...]:
    F = np.array([[1, 0, 1, 0], [0, 1, 0, 1], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=float)
    Q = np.diag([0.01, 0.01, 0.04, 0.04])
    H = np.array([[1.0, 0, 0, 0], [0, 1.0, 0.2, 0]])
    R = np.diag([0.5, 0.8])
    return F, Q, H, R


def _data(batch: int, steps: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    F, Q, H, _ = _system()
    x = rng.normal(size=(batch, 4))
    zs = np.zeros((steps, batch, 2))
    for k in range(steps):
        x = x @ F.T + rng.normal(size=(batch, 4)) * np.sqrt(np.diag(Q))
        # model error: a manoeuvre the filter's Q does not know between steps 5 and 9
        if 5 <= k < 9:
            x[:, 2:] += 1.5
        zs[k] = x @ H.T + rng.normal(size=(batch, 2)) * np.sqrt([0.5, 0.8])
    mask = np.ones((steps, batch), dtype=bool)
    mask[min(3, steps - 1), 1 % batch] = False
    mask[min(7, steps - 1), 2 % batch] = False
    return zs, mask


def _reference(zs, mask, c0, window, block, cap):  # type: ignore[no-untyped-def]
    F, Q, H, R = _system()
    steps, batch, _ = zs.shape
    xs, Ps, alphas = [], [], []
    for i in range(batch):
        x, P = np.zeros(4), 4.0 * np.eye(4)
        stored: list[float] = []
        a_run = []
        for s in range(steps):
            x, P = F @ x, F @ P @ F.T + Q
            if not mask[s, i]:
                a_run.append(1.0)
                continue
            r = zs[s, i] - H @ x
            S = H @ P @ H.T + R
            window_sq = stored[-(window - 1):] if window > 1 else []
            lam = (sum(window_sq) + r @ r) / (len(window_sq) + 1) / np.trace(S)
            alpha = min(cap, lam / c0) if lam > c0 else 1.0
            d = np.ones(4)
            d[list(block)] = math.sqrt(alpha)
            P = np.diag(d) @ (P - Q) @ np.diag(d) + Q
            S = H @ P @ H.T + R
            K = P @ H.T @ np.linalg.inv(S)
            x = x + K @ r
            ikh = np.eye(4) - K @ H
            P = ikh @ P @ ikh.T + K @ R @ K.T
            stored.append(float(r @ r))
            a_run.append(alpha)
        xs.append(x)
        Ps.append(P)
        alphas.append(a_run)
    return np.array(xs), np.array(Ps), np.array(alphas).T


def _run(policy, zs, mask):  # type: ignore[no-untyped-def]
    F, Q, H, R = (torch.tensor(a, dtype=D) for a in _system())
    steps, batch, _ = zs.shape
    ekf = BatchedEKF(torch.zeros(batch, 4, dtype=D), 4.0 * torch.eye(4, dtype=D))
    alphas = []
    for s in range(steps):
        ekf.predict(F, Q)
        z = torch.tensor(zs[s], dtype=D)
        diag = ekf.update(z - ekf.x @ H.t(), H, R, mask=torch.tensor(mask[s]), policy=policy)
        alphas.append(diag.policy_info["alpha"])
    return ekf, torch.stack(alphas).numpy()


@pytest.mark.parametrize(("window", "block", "cap"), [
    (2, (0, 1), 10.0), (5, (0, 1, 2, 3), 3.0), (4, (2, 3), math.inf)])
def test_windowed_inflation_matches_numpy_reference(window, block, cap) -> None:  # type: ignore[no-untyped-def]
    zs, mask = _data(batch=4, steps=14, seed=3)
    policy = WindowedInflation(1.2, window=window, block=block, cap=cap)
    ekf, alphas = _run(policy, zs, mask)
    x_ref, P_ref, a_ref = _reference(zs, mask, 1.2, window, block, cap)
    np.testing.assert_allclose(alphas, a_ref, rtol=1e-12)
    np.testing.assert_allclose(ekf.x.numpy(), x_ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(ekf.P.numpy(), P_ref, rtol=1e-10, atol=1e-10)
    assert (a_ref > 1).any() and (a_ref == 1).any()  # the test exercises both branches
    if math.isfinite(cap):
        assert alphas.max() <= cap


def _run_scalar(policy, zs, mask):  # type: ignore[no-untyped-def]
    F, Q = (torch.tensor(a, dtype=D) for a in _system()[:2])
    H = torch.tensor([[1.0, 0, 0, 0]], dtype=D)
    ekf = BatchedEKF(torch.zeros(zs.shape[1], 4, dtype=D), 4.0 * torch.eye(4, dtype=D))
    alphas = []
    for s in range(zs.shape[0]):
        ekf.predict(F, Q)
        z = torch.tensor(zs[s, :, :1], dtype=D)
        diag = ekf.update(z - ekf.x @ H.t(), H, 0.5, mask=torch.tensor(mask[s]), policy=policy)
        alphas.append(diag.policy_info["alpha"])
    return ekf, torch.stack(alphas).numpy()


def test_window_one_whole_state_uncapped_is_the_literal_form() -> None:
    # m = 1 (the filter's scalar fast path): window 1, every state, no cap = InnovationInflation
    zs, mask = _data(batch=3, steps=10, seed=5)
    a, alpha_w = _run_scalar(WindowedInflation(1.2, window=1, block=None, cap=math.inf), zs,
                             mask)
    b, alpha_l = _run_scalar(InnovationInflation(1.2), zs, mask)
    assert (alpha_l > 1).any()
    np.testing.assert_allclose(alpha_w, alpha_l, rtol=1e-12)
    np.testing.assert_allclose(a.P.numpy(), b.P.numpy(), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(a.x.numpy(), b.x.numpy(), rtol=1e-10, atol=1e-12)


def test_inside_compose_after_quality_r_sees_the_tuned_R() -> None:
    zs, mask = _data(batch=2, steps=8, seed=6)
    quality = QualityR.gnss(0.3, 0.3, 0.3, 0.3)
    policy = Compose(quality, WindowedInflation(1.2, window=2, block=(0, 1)))
    F, Q, H, R = (torch.tensor(a, dtype=D) for a in _system())
    ekf = BatchedEKF(torch.zeros(2, 4, dtype=D), 4.0 * torch.eye(4, dtype=D))
    for s in range(8):
        ekf.predict(F, Q)
        quality.set_quality({"pdop": torch.full((2,), 4.0), "fix_ratio": torch.full((2,), 0.5),
                             "satellites": torch.full((2,), 6.0),
                             "sigma_m": torch.full((2,), 2.0)})
        diag = ekf.update(torch.tensor(zs[s], dtype=D) - ekf.x @ H.t(), H, R, policy=policy)
        assert "windowed_inflation.alpha" in diag.policy_info
    assert bool(ekf.healthy.all())


def test_reset_and_batch_change() -> None:
    policy = WindowedInflation(1.2, window=2, block=(0,))
    zs, mask = _data(batch=3, steps=2, seed=7)
    _run(policy, zs, mask)
    with pytest.raises(NeuralMapError, match="reset"):
        _run(policy, zs[:, :2], mask[:, :2])
    policy.reset()
    _run(policy, zs[:, :2], mask[:, :2])


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"window": 0}, "window"), ({"window": 2.5}, "window"), ({"cap": 0.5}, "cap"),
    ({"cap": float("nan")}, "cap"), ({"block": (0, 0)}, "distinct"), ({"block": (-1,)}, "block"),
    ({"block": ()}, "block"), ({"c0": 0.0}, "c0"),
])
def test_bad_settings_are_clear_errors(kwargs, match) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(NeuralMapError, match=match):
        WindowedInflation(**kwargs)


def test_window_shorter_than_measurement_and_block_outside_state() -> None:
    zs, mask = _data(batch=2, steps=1, seed=8)
    with pytest.raises(NeuralMapError, match="shorter than the measurement dimension m = 2"):
        _run(WindowedInflation(1.2, window=1, block=(0,)), zs, mask)
    with pytest.raises(NeuralMapError, match="outside the state"):
        _run(WindowedInflation(1.2, window=3, block=(0, 4)), zs, mask)
    with pytest.raises(NeuralMapError, match="cap"):
        windowed_inflation_factor(torch.ones(2), 1.2, 0.9)
