"""EKF bank (Gaussian sum) against a NumPy Gaussian-sum reference on a linear model."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.ekf_bank import GaussianSumEKF, lattice_prior


def numpy_gaussian_sum(means, covs, weights, H, y, R):
    """Exact Bayes update of a Gaussian mixture with a linear scalar measurement."""
    new_m, new_c, new_w = [], [], []
    for m, c, w in zip(means, covs, weights, strict=True):
        s = H @ c @ H + R
        k = c @ H / s
        nu = y - H @ m
        new_m.append(m + k * nu)
        a = np.eye(len(m)) - np.outer(k, H)
        new_c.append(a @ c @ a.T + R * np.outer(k, k))
        new_w.append(w * np.exp(-0.5 * nu * nu / s) / np.sqrt(2 * np.pi * s))
    new_w = np.array(new_w) / np.sum(new_w)
    mean = sum(w * m for w, m in zip(new_w, new_m, strict=True))
    cov = sum(w * (c + np.outer(m - mean, m - mean))
              for w, c, m in zip(new_w, new_c, new_m, strict=True))
    return new_w, mean, cov


def test_linear_update_matches_numpy_gaussian_sum() -> None:
    """Weights, mixture mean and covariance after two updates agree to 1e-9."""
    x0 = torch.tensor([[5.0, -3.0, 1.0]], dtype=torch.float64)
    P0 = torch.diag(torch.tensor([400.0, 400.0, 4.0], dtype=torch.float64))
    means, covs, logw = lattice_prior(x0, P0, per_axis=3)
    bank = GaussianSumEKF(means, covs, log_weights=logw, prune_threshold=0.0,
                          merge_distance=0.0)
    ref_m = [m.numpy() for m in means[0]]
    ref_c = [c.numpy() for c in covs]
    ref_w = logw[0].exp().numpy()
    for H, y in ((np.array([0.4, -0.2, 1.0]), 12.0), (np.array([-0.1, 0.5, 1.0]), -7.0)):
        k = bank.n_components
        xs = bank.ekf.x
        residual = torch.tensor(y) - xs @ torch.tensor(H)
        diag = bank.ekf.update(residual, torch.tensor(H).expand(k, 3), 9.0)
        bank.reweight(diag.innovation.reshape(-1), diag.S.reshape(-1), diag.applied)
        ref_w, mean, cov = numpy_gaussian_sum(ref_m, ref_c, ref_w, H, y, 9.0)
        ref_m = [bank.ekf.x[i].numpy() for i in range(k)]
        ref_c = [bank.ekf.P[i].numpy() for i in range(k)]
    np.testing.assert_allclose(bank.log_weights[0].exp().numpy(), ref_w, atol=1e-9)
    m, c = bank.mixture()
    np.testing.assert_allclose(m[0].numpy(), mean, atol=1e-9)
    np.testing.assert_allclose(c[0].numpy(), cov, atol=1e-7)


@pytest.mark.parametrize("per_axis", [3, 7, 11])
def test_lattice_prior_keeps_the_prior_moments(per_axis: int) -> None:
    """The mixture's mean and covariance are x0 and P0 (law of total variance)."""
    x0 = torch.tensor([[5.0, -3.0, 1.0], [0.0, 2.0, -1.0]], dtype=torch.float64)
    P0 = torch.diag(torch.tensor([400.0, 900.0, 4.0], dtype=torch.float64))
    means, covs, logw = lattice_prior(x0, P0, per_axis=per_axis)
    bank = GaussianSumEKF(means, covs, log_weights=logw, prune_threshold=0.0,
                          merge_distance=0.0)
    mean, cov = bank.mixture()
    torch.testing.assert_close(mean, x0, atol=1e-9, rtol=0)
    torch.testing.assert_close(cov, P0.expand(2, 3, 3), atol=1e-9, rtol=0)


def test_merge_and_prune_keep_mixture_moments() -> None:
    """Merging close components keeps the mixture mean/cov; pruning drops tiny weights."""
    means = torch.tensor([[[0.0, 0.0], [0.1, 0.0], [50.0, 0.0]]], dtype=torch.float64)
    covs = torch.eye(2, dtype=torch.float64) * 4.0
    logw = torch.log(torch.tensor([[0.5, 0.4999999, 1e-7]], dtype=torch.float64))
    bank = GaussianSumEKF(means, covs, log_weights=logw, prune_threshold=0.0,
                          merge_distance=1.0)
    m0, c0 = bank.mixture()
    bank.merge()
    alive = torch.isfinite(bank.log_weights[0])
    assert alive.tolist() == [True, False, True]
    m1, c1 = bank.mixture()
    torch.testing.assert_close(m1, m0)
    torch.testing.assert_close(c1, c0)
    bank.prune_threshold = 1e-4
    bank.prune()
    assert torch.isfinite(bank.log_weights[0]).tolist() == [True, False, False]
    torch.testing.assert_close(bank.log_weights[0].exp().sum(), torch.tensor(1.0,
                               dtype=torch.float64))


def test_zero_likelihood_everywhere_is_a_counted_recovery() -> None:
    means, covs, logw = lattice_prior(torch.zeros(2, 2, dtype=torch.float64),
                                      torch.eye(2, dtype=torch.float64), per_axis=2)
    bank = GaussianSumEKF(means, covs, log_weights=logw)
    before = bank.log_weights.clone()
    residual = torch.tensor([0.0, 0.0, 0.0, 0.0, 1e200, 1e200, 1e200, 1e200],
                            dtype=torch.float64)[:8]
    residual = residual[: 2 * bank.n_components]
    bank.reweight(residual, torch.ones_like(residual), torch.ones_like(residual).bool())
    assert bank.recoveries.tolist() == [0, 1]
    torch.testing.assert_close(bank.log_weights[1], before[1])


def test_bad_input() -> None:
    with pytest.raises(NeuralMapError):
        GaussianSumEKF(torch.zeros(3, 2), torch.eye(2))
    with pytest.raises(NeuralMapError):
        lattice_prior(torch.zeros(1, 2), torch.eye(2), per_axis=0)
