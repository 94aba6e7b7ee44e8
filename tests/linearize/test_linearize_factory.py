"""make_linearizer: every name builds the right method; bad names and options are clear."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.linearize import (
    LINEARIZER_NAMES,
    AutogradLinearizer,
    Linearizer,
    MeanPointLinearizer,
    NinePointLinearizer,
    PlaneFitLinearizer,
    TaylorLinearizer,
    describe_linearizer,
    make_linearizer,
)
from neuralmap.terrain.grid import GridTerrain


def tile(seed: int = 0) -> DemTile:
    heights = 200 + 25 * np.random.default_rng(seed).standard_normal((40, 50))
    return DemTile(heights, spacing=(60.0, 50.0), origin=(0.0, 0.0), name=f"t{seed}")


def test_every_name_builds_and_runs() -> None:
    t = tile()
    net = GridTerrain(t, method="bicubic")
    xy = torch.tensor([[1200.0, 900.0], [1500.5, 1010.25]], dtype=torch.float64)
    cov = (torch.eye(2, dtype=torch.float64) * 150.0**2).expand(2, 2, 2)
    expected = {
        "neural": AutogradLinearizer,
        "neural_region": AutogradLinearizer,
        "bilinear": TaylorLinearizer,
        "bicubic": AutogradLinearizer,
        "nine_point": NinePointLinearizer,
        "mean_point": MeanPointLinearizer,
        "lsq_max": PlaneFitLinearizer,
        "lsq_mean": PlaneFitLinearizer,
        "lsq_min": PlaneFitLinearizer,
        "lsq_adaptive": PlaneFitLinearizer,
    }
    assert set(LINEARIZER_NAMES) == set(expected)
    for name in LINEARIZER_NAMES:
        lin = make_linearizer(name, tile=t, terrain=net, fit_variance=6.0)
        assert isinstance(lin, expected[name]) and isinstance(lin, Linearizer)
        out = lin(xy, cov)
        assert out.slope.shape == (2, 2) and torch.isfinite(out.slope).all()
        # A real description, not the fallback that echoes the name back.
        assert describe_linearizer(name) != name and len(describe_linearizer(name)) > 20
    assert make_linearizer("lsq_max", tile=t).sigma == (400.0, 400.0)
    assert make_linearizer("lsq_mean", tile=t).sigma == (240.0, 240.0)
    assert make_linearizer("lsq_min", tile=t).sigma == (80.0, 80.0)
    assert make_linearizer("lsq_adaptive", tile=t).adaptive
    assert make_linearizer("mean_point", tile=t).adaptive


def test_neural_uses_fit_variance_and_grid_methods_do_not() -> None:
    t = tile()
    xy = torch.tensor([[1200.0, 900.0]], dtype=torch.float64)
    neural = make_linearizer("neural", tile=t, terrain=GridTerrain(t), fit_variance=6.0)
    assert float(neural(xy).variance[0]) == 6.0
    bicubic = make_linearizer("bicubic", tile=t, fit_variance=6.0)
    assert float(bicubic(xy).variance[0]) == 0.0


def test_bicubic_name_matches_bicubic_grid() -> None:
    t = tile(1)
    xy = torch.rand(100, 2, dtype=torch.float64) * torch.tensor([2900.0, 1900.0])
    lin = make_linearizer("bicubic", tile=t)(xy)
    h, slope = GridTerrain(t, method="bicubic").height_and_slope(xy)
    torch.testing.assert_close(lin.slope, slope, rtol=0, atol=1e-10)
    torch.testing.assert_close(lin.height, h, rtol=0, atol=1e-10)


def test_options_are_passed_through() -> None:
    t = tile()
    assert make_linearizer("lsq_min", tile=t, n_samples=5).n_samples == 5
    assert make_linearizer("bilinear", tile=t, variance="zero").variance_mode == "zero"
    lin = make_linearizer("bicubic", tile=t, dtype=torch.float32, create_graph=True)
    assert lin.create_graph and lin.terrain.heights.dtype == torch.float32
    assert make_linearizer("lsq_adaptive", tile=t, max_sigma=500.0).sigma_bounds[1] == (500.0,) * 2


def test_errors() -> None:
    t = tile()
    with pytest.raises(NeuralMapError) as info:
        make_linearizer("sitan", tile=t)
    for name in LINEARIZER_NAMES:
        assert name in str(info.value)
    with pytest.raises(NeuralMapError, match="terrain="):
        make_linearizer("neural", tile=t)
    with pytest.raises(NeuralMapError, match="fitted to tile"):
        make_linearizer("neural", tile=t, terrain=GridTerrain(tile(seed=5)))
    with pytest.raises(NeuralMapError, match="unknown option.*n_sample"):
        make_linearizer("lsq_min", tile=t, n_sample=5)
    with pytest.raises(NeuralMapError, match="unknown option.*max_sigma"):
        make_linearizer("lsq_min", tile=t, max_sigma=5.0)
    with pytest.raises(NeuralMapError, match="DemTile"):
        make_linearizer("bilinear", tile=None)
