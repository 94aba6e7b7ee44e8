"""Lattice rules by registry name: each builds its filter, and on a linear-Gaussian
measurement (a tilted plane) every rule gives the Kalman posterior (float64 reference,
closed form)."""

from __future__ import annotations

import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.lattice.rule import LATTICE_RULES, make_lattice_filter
from neuralmap.filters.point_mass import PointMassFilter
from neuralmap.filters.point_mass_tracker import PointMassTracker

D = torch.float64
SLOPE = torch.tensor([0.3, -0.2], dtype=D)
R = 25.0


def _kalman(mean: torch.Tensor, cov: torch.Tensor, y: torch.Tensor):
    h = torch.cat([SLOPE, torch.ones(1, dtype=D)])  # y = slope · s + a + e
    s = h @ cov @ h + R
    k = cov @ h / s
    return mean + k * (y - mean @ h)[:, None], cov - torch.outer(k, k) * s


@pytest.mark.parametrize("rule", ["fixed", "adaptive", "follow"])
def test_every_rule_gives_the_kalman_posterior_on_a_plane(rule: str) -> None:
    mean = torch.tensor([[10.0, -20.0, 3.0], [0.0, 0.0, 0.0]], dtype=D)
    cov = torch.diag(torch.tensor([60.0**2, 40.0**2, 10.0**2], dtype=D))
    f = make_lattice_filter(rule, mean, cov, cells=64)
    assert isinstance(f, PointMassTracker if rule == "follow" else PointMassFilter)
    y = torch.tensor([5.0, -12.0], dtype=D)
    plane = lambda pts: pts @ SLOPE  # noqa: E731
    f.update(y, plane, R=R)
    want_m, want_c = _kalman(mean, cov, y)
    if rule == "follow":
        got_m, got_c = f.moments()
        torch.testing.assert_close(got_m[:, 2], want_m[:, 2], rtol=0.0,
                                   atol=1e-5 * float(want_c[2, 2]) ** 0.5)
        tol_m, tol_c = 1e-5, 3e-5  # linear-Gaussian: exact but for the lattice's ±5 σ tails
    else:
        a_m, a_v = f.scalar_moments()
        got_m = torch.cat([f.mean(), a_m[:, None]], 1)
        got_c = f.cov()
        want_c = want_c[:2, :2].expand(2, 2, 2)
        tol_m, tol_c = 1e-3, 1e-3  # sampled prior: a grid's discretisation
        var_a = float(_kalman(mean, cov, y)[1][2, 2])
        torch.testing.assert_close(a_v, torch.full_like(a_v, var_a), rtol=1e-3, atol=0.0)
        torch.testing.assert_close(a_m, want_m[:, 2], rtol=0.0, atol=1e-3 * var_a**0.5)
    sig = want_c.diagonal(dim1=-2, dim2=-1).sqrt().expand(2, -1)
    assert float(((got_m[:, :2] - want_m[:, :2]) / sig[:, :2]).abs().max()) < tol_m
    torch.testing.assert_close(got_c[..., :2, :2], want_c[..., :2, :2].expand(2, 2, 2),
                               rtol=tol_c, atol=0.0)


def test_registry_refusals_name_the_problem() -> None:
    mean, cov = torch.zeros(1, 3, dtype=D), torch.eye(3, dtype=D)
    with pytest.raises(NeuralMapError, match="unknown lattice rule 'grid'.*fixed"):
        make_lattice_filter("grid", mean, cov)
    with pytest.raises(NeuralMapError, match="one scalar linear state"):
        make_lattice_filter("fixed", torch.zeros(1, 5, dtype=D), torch.eye(5, dtype=D))
    with pytest.raises(NeuralMapError, match="options of TrackerConfig"):
        make_lattice_filter("follow", mean, cov, spacing=3.0)
    with pytest.raises(NeuralMapError, match="cov must have shape"):
        make_lattice_filter("follow", mean, torch.eye(2, dtype=D))
    assert set(LATTICE_RULES) == {"fixed", "adaptive", "follow"}

