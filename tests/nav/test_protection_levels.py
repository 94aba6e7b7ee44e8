"""Protection levels against closed forms and brute force, and the misleading rate of a
consistent filter against its integrity risk (binomial interval)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import binomtest, chi2, norm

from neuralmap.nav.integrity import protection_levels
from neuralmap.tan.cells import lattice_protection_radius


@pytest.mark.parametrize("risk", [1e-2, 1e-4, 1e-7])
def test_hpl_and_vpl_of_a_gaussian_are_its_quantiles(risk: float) -> None:
    sigma, sigma_h = 7.0, 3.0
    cov = torch.diag(torch.tensor([sigma**2, sigma**2, sigma_h**2, 0.1, 0.1],
                                  dtype=torch.float64))[None]
    hpl, vpl = protection_levels(cov, risk)
    # circular Gaussian: |e|²/σ² ~ χ²₂, so P(|e| > HPL) = risk exactly
    assert float(hpl[0]) == pytest.approx(sigma * math.sqrt(chi2.isf(risk, 2)),
                                          rel=1e-12)
    assert math.exp(-float(hpl[0]) ** 2 / (2 * sigma**2)) == pytest.approx(risk, rel=1e-9)
    assert float(vpl[0]) == pytest.approx(sigma_h * norm.isf(risk / 2), rel=1e-12)


def test_the_hpl_of_an_elongated_gaussian_bounds_its_risk() -> None:
    risk = 1e-2
    cov = torch.zeros(1, 5, 5, dtype=torch.float64)
    c, s = math.cos(0.4), math.sin(0.4)
    rot = torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    cov[0, :2, :2] = rot @ torch.diag(torch.tensor([100.0, 4.0], dtype=torch.float64)) @ rot.T
    cov[0, 2, 2] = 1.0
    hpl = float(protection_levels(cov, risk)[0][0])
    gen = torch.Generator().manual_seed(0)
    e = torch.randn(400_000, 2, generator=gen, dtype=torch.float64) @ torch.linalg.cholesky(
        cov[0, :2, :2]).T
    outside = float((e.norm(dim=1) > hpl).double().mean())
    assert outside <= risk and outside > 0.2 * risk  # conservative, not wildly


def _lattice(masses: np.ndarray, spacing: float) -> tuple[torch.Tensor, ...]:
    g = masses.shape[0]
    off = (np.arange(g) - (g - 1) / 2) * spacing
    x, y = np.meshgrid(off, off)  # rows along y, columns along x
    points = torch.tensor(np.stack([x, y], -1)[None])
    w = torch.tensor(masses / masses.sum())[None]
    axes = torch.tensor(np.diag([spacing, spacing])[None])
    mean = (points * w[..., None]).sum((1, 2))
    return points, w, axes, mean


def test_the_lattice_radius_holds_its_mass_brute_force() -> None:
    spacing, risk = 5.0, 1e-2
    g = np.arange(48) - 23.5
    x, y = np.meshgrid(g * spacing, g * spacing)
    # two modes 150 m apart: the Gaussian fit says nothing of the gap
    masses = 0.7 * np.exp(-((x + 60) ** 2 + y**2) / (2 * 15.0**2)) + 0.3 * np.exp(
        -((x - 90) ** 2 + (y - 10) ** 2) / (2 * 10.0**2))
    points, w, axes, mean = _lattice(masses, spacing)
    small = torch.tensor([5.0], dtype=torch.float64)  # a Gaussian level far too small
    r = float(lattice_protection_radius(points, w, axes, mean, risk, small)[0])
    # brute force: each cell's mass at its far corner
    reach = (points - mean[:, None, None, :]).norm(dim=-1)[0].numpy() + spacing / math.sqrt(2)
    assert masses[reach > r].sum() / masses.sum() <= risk
    assert masses[reach > r - spacing].sum() / masses.sum() > risk  # the smallest such r
    # where the Gaussian level already holds the mass, it is the answer
    big = torch.tensor([1e4], dtype=torch.float64)
    assert float(lattice_protection_radius(points, w, axes, mean, risk, big)[0]) == 1e4


def test_the_misleading_rate_of_a_consistent_filter_is_its_risk() -> None:
    """A consistent filter (errors drawn from its own circular covariance, tracking at
    every epoch): the misleading rate at each risk lies within its binomial interval."""
    from neuralmap.lab.integrity import integrity_metrics
    from neuralmap.lab.monte_carlo import FilterRun
    from neuralmap.nav.fix import STATUS_CODE

    n, k, sigma = 400, 101, 12.0
    gen = torch.Generator().manual_seed(7)
    err = torch.zeros(n, k, 5, dtype=torch.float64)
    err[..., :2] = sigma * torch.randn(n, k, 2, generator=gen, dtype=torch.float64)
    P = torch.diag(torch.tensor([sigma**2, sigma**2, 1.0, 1.0, 1.0],
                                dtype=torch.float64)).expand(n, k, 5, 5)
    protection = {r: protection_levels(P.reshape(-1, 5, 5), r)[0].reshape(n, k)
                  for r in (1e-2, 5e-2)}
    run = FilterRun(method="consistent", t=torch.arange(k, dtype=torch.float64), err=err, P=P,
                    nis=torch.zeros(n, k), residual=torch.zeros(n, k),
                    updated=torch.ones(n, k, dtype=torch.bool),
                    est_on_map=torch.ones(n, k, dtype=torch.bool),
                    off_map=torch.zeros(n, dtype=torch.bool),
                    healthy=torch.ones(n, dtype=torch.bool),
                    status=torch.full((n, k), STATUS_CODE["tracking"]), protection=protection)
    metrics = integrity_metrics(run, alert_limit_m=1e6)
    for risk, entry in metrics["risks"].items():
        mi = entry["misleading"]
        assert mi["epochs"] == n * (k - 1)
        lo, hi = binomtest(mi["count"], mi["epochs"]).proportion_ci(confidence_level=0.999)
        assert lo <= float(risk) <= hi, (risk, mi)
    # a filter twice too sure of itself is caught: its misleading rate is far above the risk
    run.protection = {1e-2: protection[1e-2] / 2.0}
    over = integrity_metrics(run, alert_limit_m=1e6)["risks"]["0.01"]
    assert over["misleading"]["ci95"][0] > 0.1 and over["within_risk"] is False
