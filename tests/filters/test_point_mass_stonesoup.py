"""Anchor: the batched point-mass filter against Stone Soup's point-mass predictor plus a
plain NumPy Bayes update (one run, 2-D grid). ``stonesoup`` is in the test extra."""

from __future__ import annotations

from datetime import datetime, timedelta

import numpy as np
import torch

from neuralmap.filters.point_mass import PointMassConfig, PointMassFilter


def test_predict_and_update_agree_with_stone_soup() -> None:
    """Prior N(m, P) → predict (random walk, Q) → altimeter-like update on a plane.

    Stone Soup's predictor re-grids (eigen-aligned, ±4σ, 101² points) and convolves by FFT;
    the Bayes update is NumPy on its grid. The toolkit's grid is axis-aligned (96² cells,
    ±5σ). Posterior means agree to 1e-3 of the posterior σ, covariances to 2e-3 of the
    largest entry (measured: 2e-5 and 4e-4).
    """
    from stonesoup.functions import grid_creation
    from stonesoup.models.transition.linear import (
        CombinedLinearGaussianTransitionModel,
        RandomWalk,
    )
    from stonesoup.predictor.pointmass import PointMassPredictor
    from stonesoup.types.array import StateVectors
    from stonesoup.types.state import PointMassState

    m0 = np.array([30.0, -10.0])
    P0 = np.array([[900.0, 300.0], [300.0, 1600.0]])
    q = np.array([100.0, 60.0])
    g = np.array([0.4, -0.25])  # plane slope
    y, r = 12.0, 25.0
    npa = np.array([101, 101])
    t0 = datetime(2026, 1, 1)
    grid, delta, dims, centre, eig = grid_creation(m0.reshape(-1, 1), P0, 4.0, 2, npa)
    diff = grid - m0[:, None]
    pdf = np.exp(-0.5 * np.sum(diff * np.linalg.solve(P0, diff), axis=0))
    pdf = pdf / (pdf.sum() * np.prod(delta))
    prior = PointMassState(state_vector=StateVectors(grid), weight=pdf.reshape(-1, 1),
                           grid_delta=delta, grid_dim=dims, center=centre, eigVec=eig,
                           Npa=npa, timestamp=t0)
    model = CombinedLinearGaussianTransitionModel([RandomWalk(q[0]), RandomWalk(q[1])])
    pred = PointMassPredictor(model).predict(prior, timestamp=t0 + timedelta(seconds=1))
    pts = np.asarray(pred.state_vector, dtype=float)
    w = np.asarray(pred.weight, dtype=float).reshape(-1)
    lik = np.exp(-0.5 * (y - g @ pts) ** 2 / r)
    w = w * lik
    w = w / w.sum()
    ref_mean = pts @ w
    d = pts - ref_mean[:, None]
    ref_cov = (d * w) @ d.T

    f = PointMassFilter(torch.tensor(m0)[None], torch.tensor(P0), scalar_mean=0.0,
                        scalar_var=1e-9, config=PointMassConfig(cells=96, span_sigma=5.0,
                                                                min_spacing=0.01),
                        dtype=torch.float64)
    f.predict(Q=torch.tensor(q))
    f.update(torch.tensor([y]), lambda p: g[0] * p[..., 0] + g[1] * p[..., 1], R=r)
    mean, cov = f.mean()[0].numpy(), f.cov()[0].numpy()
    sig = np.sqrt(np.diag(ref_cov))
    assert np.all(np.abs(mean - ref_mean) / sig < 1e-3)
    assert np.abs(cov - ref_cov).max() / np.abs(ref_cov).max() < 2e-3
