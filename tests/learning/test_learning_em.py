"""The gradient learner against EM (Shumway & Stoffer) on a linear-Gaussian model.

The reference EM here is written from Shumway & Stoffer (1982; 2017, sections 6.2-6.3)
in plain NumPy, one flight at a time, with their lag-one covariance smoother recursion
(eq. 6.56) rather than the package's de Jong identity, so it also checks
`neuralmap.learning.em`.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuralmap.learning.em import em_noise
from neuralmap.learning.likelihood import linear_log_likelihood
from neuralmap.learning.noise_model import NoiseModel

F = np.array([[1.0, 1.0], [0.0, 1.0]])
Q_TRUE = np.diag([0.5, 0.02])
R_TRUE = 4.0
P0 = np.diag([10.0, 1.0])
X0 = np.zeros(2)


def _data(n_flights: int, n_steps: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = rng.multivariate_normal(X0, P0, size=n_flights)
    z = np.full((n_flights, n_steps + 1), np.nan)
    H = np.zeros((n_flights, n_steps + 1, 2))
    H[..., 0] = 1.0
    H[..., 1] = 0.3 * np.sin(np.arange(n_steps + 1) / 7.0)
    for k in range(1, n_steps + 1):
        x = x @ F.T + rng.multivariate_normal(np.zeros(2), Q_TRUE, size=n_flights)
        z[:, k] = np.einsum("ni,ni->n", H[:, k], x) + np.sqrt(R_TRUE) * rng.standard_normal(n_flights)
    z[0, 5] = np.nan  # a missing sample: skipped by both
    return z, H


def _em_step_reference(z: np.ndarray, H: np.ndarray, Q: np.ndarray, R: float
                       ) -> tuple[np.ndarray, float]:
    """One EM iteration, flight by flight, Shumway-Stoffer lag-one recursion."""
    n = 2
    A = np.zeros((n, n))
    r_sum, m_count, steps = 0.0, 0, 0
    for f in range(z.shape[0]):
        K1 = z.shape[1]
        xp, Pp, xf, Pf, gains = [None] * K1, [None] * K1, [None] * K1, [None] * K1, [None] * K1
        xf[0], Pf[0] = X0.copy(), P0.copy()
        for k in range(1, K1):
            xp[k] = F @ xf[k - 1]
            Pp[k] = F @ Pf[k - 1] @ F.T + Q
            h = H[f, k]
            if np.isfinite(z[f, k]):
                S = h @ Pp[k] @ h + R
                gain = Pp[k] @ h / S
                xf[k] = xp[k] + gain * (z[f, k] - h @ xp[k])
                Pf[k] = (np.eye(n) - np.outer(gain, h)) @ Pp[k]
            else:
                gain = np.zeros(n)
                xf[k], Pf[k] = xp[k], Pp[k]
            gains[k] = gain
        xs, Ps = list(xf), list(Pf)
        J = [None] * K1
        for k in range(K1 - 1, 0, -1):
            J[k - 1] = Pf[k - 1] @ F.T @ np.linalg.inv(Pp[k])
            xs[k - 1] = xf[k - 1] + J[k - 1] @ (xs[k] - xp[k])
            Ps[k - 1] = Pf[k - 1] + J[k - 1] @ (Ps[k] - Pp[k]) @ J[k - 1].T
        lag = [None] * K1  # lag[k] = P_{k,k-1|K}
        last = K1 - 1
        lag[last] = (np.eye(n) - np.outer(gains[last], H[f, last])) @ F @ Pf[last - 1]
        for k in range(last, 1, -1):  # eq. 6.56
            lag[k - 1] = Pf[k - 1] @ J[k - 2].T + J[k - 1] @ (lag[k] - F @ Pf[k - 1]) @ J[k - 2].T
        for k in range(1, K1):
            e = xs[k] - F @ xs[k - 1]
            A += (np.outer(e, e) + Ps[k] - F @ lag[k].T - lag[k] @ F.T
                  + F @ Ps[k - 1] @ F.T)
            steps += 1
            if np.isfinite(z[f, k]):
                h = H[f, k]
                r_sum += (z[f, k] - h @ xs[k]) ** 2 + h @ Ps[k] @ h
                m_count += 1
    return np.diag(np.diag(A / steps)), r_sum / m_count


def _gradient_answer(z: np.ndarray, H: np.ndarray) -> tuple[np.ndarray, float]:
    noise = NoiseModel(torch.tensor([5.0, 0.2]), 40.0)  # mis-specified: Q x 10, R x 10
    zt, Ht = torch.tensor(z), torch.tensor(H)
    Ft, P0t = torch.tensor(F), torch.tensor(P0)
    opt = torch.optim.LBFGS(noise.parameters(), lr=1, max_iter=60, tolerance_grad=1e-8,
                            tolerance_change=1e-14, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = -linear_log_likelihood(zt, Ht, F=Ft, Q=noise.Q(), R=noise.R(),
                                      P0=P0t).log_likelihood.sum()
        loss.backward()
        return loss

    opt.step(closure)
    values = noise.values()
    return np.diag(values["Q_diag"]), values["R"]


@pytest.fixture(scope="module")
def problem() -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    z, H = _data(8, 50, seed=0)
    Q, R = _gradient_answer(z, H)
    return z, H, Q, R


def test_gradient_answer_is_the_em_fixed_point(problem) -> None:  # noqa: ANN001
    """One reference EM iteration from the gradient answer returns it (1e-3 relative)."""
    z, H, Q, R = problem
    Q_em, R_em = _em_step_reference(z, H, Q, R)
    np.testing.assert_allclose(np.diag(Q_em), np.diag(Q), rtol=1e-3)
    assert R_em == pytest.approx(R, rel=1e-3)
    # and the point is not trivial: an EM step from elsewhere moves
    Q_off, R_off = _em_step_reference(z, H, 2.0 * Q, 2.0 * R)
    assert abs(R_off - 2.0 * R) > 0.1 * R


def test_package_em_matches_reference_step(problem) -> None:  # noqa: ANN001
    z, H, Q, R = problem
    start_Q, start_R = np.diag([1.0, 0.05]), 10.0
    ref_Q, ref_R = _em_step_reference(z, H, start_Q, start_R)
    pkg = em_noise(z, H, F=F, Q0=start_Q, R0=start_R, x0=X0, P0=P0, max_iter=1)
    np.testing.assert_allclose(np.diag(pkg.Q), np.diag(ref_Q), rtol=1e-9)
    assert pkg.R == pytest.approx(ref_R, rel=1e-9)


@pytest.mark.slow
def test_em_from_misspecified_start_converges_to_gradient_answer(problem) -> None:  # noqa: ANN001
    """Full EM from Q x 10, R x 10 reaches the gradient answer to 1e-3 relative."""
    z, H, Q, R = problem
    em = em_noise(z, H, F=F, Q0=np.diag([5.0, 0.2]), R0=40.0, x0=X0, P0=P0,
                  max_iter=20000, tol=1e-9)
    assert em.converged
    np.testing.assert_allclose(np.diag(em.Q), np.diag(Q), rtol=1e-3)
    assert em.R == pytest.approx(R, rel=1e-3)
    assert np.all(np.diff(em.log_likelihood) > -1e-6)  # EM never decreases the likelihood
