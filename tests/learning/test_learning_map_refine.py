"""Map refinement from flights: the biased region is corrected, unflown areas stay put."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.scenario import load_scenario, scenario_tile
from neuralmap.lab.simulator import simulate
from neuralmap.lab.truth_terrain import true_terrain
from neuralmap.learning.flights import FlightBatch
from neuralmap.learning.map_correction import (
    BiasedTerrain,
    CorrectedLinearizer,
    CorrectedTerrain,
    MapCorrection,
)
from neuralmap.learning.map_refine import refine_map
from neuralmap.linearize.factory import make_linearizer
from neuralmap.tan.model import TanModel
from neuralmap.terrain.grid import GridTerrain

F64 = torch.float64


def test_correction_slope_is_the_gradient_of_its_height() -> None:
    corr = MapCorrection((0.0, 1000.0, 0.0, 800.0), spacing_m=200.0)
    with torch.no_grad():
        corr.offsets.copy_(torch.randn(corr.offsets.shape, generator=torch.Generator().manual_seed(0),
                                       dtype=F64))
    xy = torch.tensor([[123.0, 456.0], [710.0, 90.0], [999.0, 799.0]], dtype=F64,
                      requires_grad=True)
    value, slope = corr(xy)
    (grad,) = torch.autograd.grad(value.sum(), xy)
    torch.testing.assert_close(slope, grad)
    nodes = corr.nodes()
    torch.testing.assert_close(corr(nodes[2, 3])[0], corr.offsets[2, 3])
    with pytest.raises(NeuralMapError, match="spacing_m"):
        MapCorrection((0.0, 1.0, 0.0, 1.0), spacing_m=0.0)
    with pytest.raises(NeuralMapError, match="box"):
        BiasedTerrain(GridTerrain(DemTile(heights=np.zeros((5, 5)), spacing=(10.0, 10.0))),
                      (5.0, 1.0, 0.0, 1.0), bias_m=1.0)


@pytest.fixture(scope="module")
def refined() -> dict:
    scenario = load_scenario("tiny")
    tile = scenario_tile(scenario)
    world = true_terrain(scenario, tile, seed=0)
    ox, oy = tile.extent[0], tile.extent[2]
    base = GridTerrain(tile, method="bicubic", dtype=F64)
    biased = BiasedTerrain(base, (ox + 1000, ox + 1600, oy + 1000, oy + 1600), bias_m=20.0)
    lin = make_linearizer("neural", tile=None, terrain=biased)
    train = FlightBatch.from_truth(simulate(scenario, tile, n_runs=24, seed=1, truth_terrain=world))
    model = TanModel.from_scenario(scenario)
    result = refine_map(train, lin, extent=tuple(tile.extent), F=model.transition(),
                        Q=model.filter_process_noise(), R=model.base_R, P0=model.filter_prior(),
                        spacing_m=150.0, prior_sigma_m=10.0, epochs=6, lr=2.0, tbptt_steps=None)
    return {"biased": biased, "base": base, "world": world, "train": train, "result": result,
            "tile": tile}


@pytest.mark.slow
def test_refinement_reduces_the_map_error_in_the_flown_biased_region(refined) -> None:  # noqa: ANN001
    biased, world, result = refined["biased"], refined["world"], refined["result"]
    new_map = CorrectedTerrain(biased, result.correction)
    with torch.no_grad():
        p = refined["train"].pos[..., :2].reshape(-1, 2)
        inside = biased.error(p) > 19.99
        assert int(inside.sum()) > 50
        before = (biased(p[inside]) - world.model(p[inside])).square().mean().sqrt()
        after = (new_map(p[inside]) - world.model(p[inside])).square().mean().sqrt()
    assert float(before) == pytest.approx(20.0, abs=0.5)
    assert float(after) < 0.7 * float(before), (float(before), float(after))


@pytest.mark.slow
def test_unflown_areas_stay_within_tolerance_of_the_original_map(refined) -> None:  # noqa: ANN001
    biased, result, tile = refined["biased"], refined["result"], refined["tile"]
    new_map = CorrectedTerrain(biased, result.correction)
    gen = torch.Generator().manual_seed(1)
    xmin, xmax, ymin, ymax = tile.extent
    pts = torch.stack([xmin + (xmax - xmin) * torch.rand(4000, generator=gen, dtype=F64),
                       ymin + (ymax - ymin) * torch.rand(4000, generator=gen, dtype=F64)], 1)
    flown = refined["train"].pos[..., :2].reshape(-1, 2)
    far = torch.cdist(pts, flown).min(dim=1).values > 2 * 150.0 * 1.5
    assert int(far.sum()) > 500
    with torch.no_grad():
        drift = (new_map(pts[far]) - biased(pts[far])).abs().max()
    assert float(drift) <= 0.01
    # the corrected linearizer equals the corrected map's own height there
    lin = result.linearizer
    with torch.no_grad():
        out = lin(pts[:5], None)
        torch.testing.assert_close(out.height, new_map(pts[:5]))
    assert isinstance(lin, CorrectedLinearizer)
