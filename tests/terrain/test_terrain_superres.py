"""Residual super-resolution prior: bicubic upsampler anchors, shapes, the zero-residual case."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from neuralmap.dem import synthetic_tile
from neuralmap.terrain.grid import GridTerrain
from neuralmap.terrain.superres import ResidualSuperRes, bicubic_upsample, upsample_tile
from neuralmap.training.superres_prior import fit_superres_prior, prior_loss


def test_bicubic_upsample_equals_grid_terrain_at_the_fine_nodes() -> None:
    tile = synthetic_tile((20, 17), spacing=30.0, seed=1)
    up = bicubic_upsample(torch.as_tensor(tile.heights), 3)
    ny, nx = up.shape
    assert (ny, nx) == (3 * 19 + 1, 3 * 16 + 1)
    yy, xx = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    xy = torch.as_tensor(np.stack([xx * 10.0, yy * 10.0], -1).reshape(-1, 2))
    with torch.no_grad():
        ref = GridTerrain(tile, method="bicubic", dtype=torch.float64)(xy).reshape(ny, nx)
    torch.testing.assert_close(up, ref, atol=1e-9, rtol=0)


def test_bicubic_upsample_is_exact_on_quadratics_and_near_scipy_cubic() -> None:
    from scipy.interpolate import RectBivariateSpline

    y, x = np.arange(12.0), np.arange(15.0)
    quad = 0.3 * x[None] ** 2 - 0.2 * x[None] * y[:, None] + 0.1 * y[:, None] ** 2 + x[None]
    fy, fx = np.arange(0, 11.01, 0.5), np.arange(0, 14.01, 0.5)
    exact = 0.3 * fx[None] ** 2 - 0.2 * fx[None] * fy[:, None] + 0.1 * fy[:, None] ** 2 + fx[None]
    np.testing.assert_allclose(bicubic_upsample(torch.as_tensor(quad), 2).numpy(), exact,
                               atol=1e-9)
    smooth = np.sin(0.4 * x[None]) * np.cos(0.3 * y[:, None])
    spline = RectBivariateSpline(y, x, smooth, kx=3, ky=3)(fy, fx)
    ours = bicubic_upsample(torch.as_tensor(smooth), 2).numpy()
    assert np.abs(ours - spline)[2:-2, 2:-2].max() < 0.01  # both O(h^3) of a unit field


def test_prior_with_zero_last_layer_is_bicubic_and_keeps_coarse_nodes() -> None:
    prior = ResidualSuperRes(factor=2, channels=4, depth=2).double()
    coarse = torch.as_tensor(synthetic_tile((9, 11), seed=3).heights)[None]
    out = prior(coarse)
    assert out.shape == (1, 17, 21)
    torch.testing.assert_close(out[:, ::2, ::2], coarse, atol=1e-9, rtol=0)  # residual 0 there
    with torch.no_grad():
        prior.last_layer.weight.zero_()
        prior.last_layer.bias.zero_()
    torch.testing.assert_close(prior(coarse), bicubic_upsample(coarse, 2), atol=0, rtol=0)


def test_short_fit_lowers_the_loss_on_its_training_terrain() -> None:
    grids = [synthetic_tile((64, 64), seed=s).heights for s in (0, 1)]
    torch.manual_seed(0)
    fine = torch.as_tensor(grids[0][:31, :31])[None].float()
    untrained = ResidualSuperRes(factor=2, channels=8, depth=3).float()
    with torch.no_grad():
        untrained.last_layer.weight.zero_()
        untrained.last_layer.bias.zero_()
        bicubic_loss = float(prior_loss(untrained, fine))
    prior = fit_superres_prior(grids, steps=60, batch=8, patch=16, channels=8, depth=3)
    with torch.no_grad():
        assert float(prior_loss(prior, fine)) < bicubic_loss


def test_upsample_tile_halves_the_spacing() -> None:
    tile = synthetic_tile((10, 12), spacing=30.0, seed=0)
    fine = upsample_tile(tile, None, factor=2)
    assert fine.shape == (19, 23) and fine.spacing == (15.0, 15.0)
    holed = dataclasses.replace(tile, heights=np.where(tile.heights > 1e9, 0, tile.heights))
    holed.heights[0, 0] = np.nan
    with pytest.raises(Exception, match="void"):
        upsample_tile(holed, None)
