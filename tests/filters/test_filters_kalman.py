"""The functional Kalman core and the policy extension point against independent references.

References: FilterPy's ``KalmanFilter`` (float64, one sample at a time), scipy's Gaussian
log-density, and the plain update with the adapted inputs written out by hand.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from filterpy.kalman import KalmanFilter
from scipy.stats import multivariate_normal

from neuralmap.filters import (
    Adaptation,
    BatchedEKF,
    FilterPolicy,
    UpdateContext,
    kalman_predict,
    kalman_update,
)

TOL = 1e-10  # relative, float64 against FilterPy


def _random_problem(n: int, m: int, batch: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(batch, n, n, generator=g, dtype=torch.float64)
    P = A @ A.transpose(1, 2) + n * torch.eye(n, dtype=torch.float64)
    B = torch.randn(batch, m, m, generator=g, dtype=torch.float64)
    R = B @ B.transpose(1, 2) + torch.eye(m, dtype=torch.float64)
    return {
        "x": torch.randn(batch, n, generator=g, dtype=torch.float64),
        "P": P,
        "F": torch.eye(n, dtype=torch.float64) + 0.1 * torch.randn(n, n, generator=g,
                                                                     dtype=torch.float64),
        "Q": torch.diag(torch.rand(n, generator=g, dtype=torch.float64) + 0.1),
        "H": torch.randn(batch, m, n, generator=g, dtype=torch.float64),
        "R": R,
        "z": torch.randn(batch, m, generator=g, dtype=torch.float64),
    }


def _filterpy_step(prob: dict[str, torch.Tensor], i: int) -> tuple[np.ndarray, np.ndarray, float]:
    n, m = prob["x"].shape[1], prob["z"].shape[1]
    kf = KalmanFilter(dim_x=n, dim_z=m)
    kf.x = prob["x"][i].numpy().reshape(n, 1).copy()
    kf.P = prob["P"][i].numpy().copy()
    kf.F = prob["F"].numpy()
    kf.Q = prob["Q"].numpy()
    kf.predict()
    kf.H = prob["H"][i].numpy()
    kf.R = prob["R"][i].numpy()
    kf.update(prob["z"][i].numpy().reshape(m, 1))
    return kf.x.ravel(), kf.P, float(kf.log_likelihood)


@pytest.mark.parametrize(("n", "m"), [(5, 1), (5, 3), (10, 1), (10, 4)])
def test_functional_core_matches_filterpy(n: int, m: int) -> None:
    prob = _random_problem(n, m, batch=6, seed=n * 10 + m)
    xt, pt = kalman_predict(prob["x"].t(), prob["P"].permute(1, 2, 0), prob["F"], prob["Q"])
    residual = prob["z"].t() - torch.einsum("bmn,nb->mb", prob["H"], xt)
    out = kalman_update(xt, pt, residual, prob["H"].permute(1, 2, 0), prob["R"].permute(1, 2, 0))
    for i in range(6):
        x_ref, p_ref, ll_ref = _filterpy_step(prob, i)
        np.testing.assert_allclose(out.x[:, i].numpy(), x_ref, rtol=TOL, atol=TOL)
        np.testing.assert_allclose(out.P[:, :, i].numpy(), p_ref, rtol=TOL, atol=TOL)
        assert out.log_likelihood[i].item() == pytest.approx(ll_ref, rel=1e-10)
        assert torch.equal(out.P[:, :, i], out.P[:, :, i].t())  # exactly symmetric


def test_stateful_filter_matches_functional_core_and_loglik() -> None:
    prob = _random_problem(5, 2, batch=4, seed=3)
    ekf = BatchedEKF(prob["x"], prob["P"])
    ekf.predict(prob["F"], prob["Q"])
    x_prior, p_prior = ekf.x, ekf.P
    residual = prob["z"] - torch.einsum("bmn,bn->bm", prob["H"], x_prior)
    diag = ekf.update(residual, prob["H"], prob["R"])
    assert torch.equal(diag.x_prior, x_prior) and torch.equal(diag.P_prior, p_prior)
    S = diag.S.numpy()
    for i in range(4):
        ref = multivariate_normal(mean=np.zeros(2), cov=S[i]).logpdf(residual[i].numpy())
        assert diag.log_likelihood[i].item() == pytest.approx(ref, rel=1e-12)
        x_ref, p_ref, _ = _filterpy_step(prob, i)
        np.testing.assert_allclose(ekf.x[i].numpy(), x_ref, rtol=TOL, atol=TOL)
        np.testing.assert_allclose(ekf.P[i].numpy(), p_ref, rtol=TOL, atol=TOL)


class _Fixed(FilterPolicy):
    """A policy returning a fixed adaptation (the core's contract, not a robust method)."""

    def __init__(self, adaptation: Adaptation, iterations: int = 1) -> None:
        self.adaptation = adaptation
        self.iterations = iterations
        self.calls: list[str] = []

    def adapt(self, context: UpdateContext) -> Adaptation:
        self.calls.append("adapt")
        return self.adaptation

    def refine(self, context, adaptation, posterior):  # type: ignore[no-untyped-def]
        self.calls.append("refine")
        return adaptation if self.calls.count("refine") < self.iterations else None

    def commit(self, context, adaptation, posterior, applied):  # type: ignore[no-untyped-def]
        self.calls.append("commit")


def test_policy_rescaling_equals_plain_update_with_rescaled_inputs() -> None:
    prob = _random_problem(5, 3, batch=5, seed=7)
    scale = torch.tensor([1.0, 2.0, 0.5, 3.0, 1.5], dtype=torch.float64)
    R_new = prob["R"] * torch.tensor([1.0, 4.0, 9.0, 1.0, 2.0], dtype=torch.float64).reshape(5, 1, 1)
    policy = _Fixed(Adaptation(p_scale=scale, R=R_new, info={"w": scale}), iterations=3)
    ekf = BatchedEKF(prob["x"], prob["P"])
    diag = ekf.update(prob["z"], prob["H"], prob["R"], policy=policy)
    ref = BatchedEKF(prob["x"], prob["P"] * scale.reshape(5, 1, 1))
    ref.update(prob["z"], prob["H"], R_new)
    torch.testing.assert_close(ekf.x, ref.x, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(ekf.P, ref.P, rtol=1e-12, atol=1e-12)
    assert policy.calls == ["adapt", "refine", "refine", "refine", "commit"]
    assert torch.equal(diag.policy_info["w"], scale)


def test_policy_rejecting_a_component_equals_update_without_it() -> None:
    prob = _random_problem(5, 3, batch=3, seed=11)
    R = torch.diag_embed(torch.rand(3, 3, dtype=torch.float64) + 0.5)  # diagonal R
    keep = torch.tensor([[True, False, True], [True, True, True], [False, False, False]])
    ekf = BatchedEKF(prob["x"], prob["P"])
    diag = ekf.update(prob["z"], prob["H"], R, policy=_Fixed(Adaptation(keep=keep)))
    # sample 0 without component 1
    ref = BatchedEKF(prob["x"][:1], prob["P"][:1])
    idx = torch.tensor([0, 2])
    ref.update(prob["z"][:1, idx], prob["H"][:1, idx], R[:1][:, idx][:, :, idx])
    torch.testing.assert_close(ekf.x[0], ref.x[0], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(ekf.P[0], ref.P[0], rtol=1e-12, atol=1e-12)
    # sample 2: everything rejected -> not updated
    assert not bool(diag.applied[2]) and torch.equal(ekf.x[2], prob["x"][2])
    assert bool(diag.applied[0]) and bool(diag.applied[1])


def test_masked_nan_sample_keeps_gradients_finite() -> None:
    """A skipped sample with NaN inputs must not put NaN into any gradient."""
    theta = torch.tensor(2.0, dtype=torch.float64, requires_grad=True)
    x0 = torch.zeros(3, 5, dtype=torch.float64)
    ekf = BatchedEKF(x0, theta * torch.eye(5, dtype=torch.float64))
    residual = torch.tensor([1.0, float("nan"), -0.5], dtype=torch.float64)
    H = torch.tensor([[1.0, 0.5, 1.0, 0.0, 0.0]] * 3, dtype=torch.float64)
    H[1] = float("nan")
    R = torch.tensor([4.0, float("nan"), 4.0], dtype=torch.float64)
    mask = torch.tensor([True, False, True])
    diag = ekf.update(residual, H, R, mask=mask)
    loss = ekf.P.sum() + ekf.x.sum() + diag.log_likelihood[mask].sum()
    (grad,) = torch.autograd.grad(loss, theta, create_graph=True)
    (grad2,) = torch.autograd.grad(grad, theta)
    assert torch.isfinite(grad) and torch.isfinite(grad2)
    assert torch.equal(ekf.x[1], x0[1]) and bool(ekf.healthy.all())
    # the gradient equals the finite difference of the same loss (float64)
    def loss_at(t: float) -> float:
        f = BatchedEKF(x0, t * torch.eye(5, dtype=torch.float64))
        d = f.update(residual, H, R, mask=mask)
        return float(f.P.sum() + f.x.sum() + d.log_likelihood[mask].sum())
    eps = 1e-6
    assert float(grad.detach()) == pytest.approx((loss_at(2 + eps) - loss_at(2 - eps)) / (2 * eps),
                                        rel=1e-6)


def test_scalar_policy_path_matches_fast_path_float32() -> None:
    prob = _random_problem(5, 1, batch=64, seed=5)
    x = prob["x"].float()
    P = prob["P"].float()
    a = BatchedEKF(x, P)
    b = BatchedEKF(x, P)
    a.update(prob["z"].float()[:, 0], prob["H"].float()[:, 0], prob["R"].float()[:, 0, 0])
    b.update(prob["z"].float()[:, 0], prob["H"].float()[:, 0], prob["R"].float()[:, 0, 0],
             policy=FilterPolicy())
    torch.testing.assert_close(a.x, b.x, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(a.P, b.P, rtol=1e-4, atol=1e-4)
    assert torch.equal(b.P, b.P.transpose(1, 2))
