"""The whole TAN filter is differentiable: gradients reach the neural map's parameters."""

from __future__ import annotations

import torch

from neuralmap.dem import synthetic_tile
from neuralmap.filters import BatchedEKF
from neuralmap.linearize import AutogradLinearizer
from neuralmap.tan.ekf_step import tan_filter_step
from neuralmap.tan.model import transition_matrix
from neuralmap.terrain.blockwise import BlockwiseTerrainNet

F64 = torch.float64


def _filter_loss(net: BlockwiseTerrainNet, scale: torch.Tensor) -> torch.Tensor:
    """Three TAN steps on fixed inputs; loss = squared final position estimate."""
    lin = AutogradLinearizer(net, create_graph=True)
    n = 6
    generator = torch.Generator().manual_seed(0)
    x0 = torch.zeros(n, 5, dtype=F64)
    ekf = BatchedEKF(x0, torch.diag(torch.tensor([900.0, 900.0, 100.0, 1.0, 1.0], dtype=F64)))
    F = transition_matrix(1.0, dtype=F64, device="cpu")
    Q = torch.diag(torch.tensor([1.0, 1.0, 1.0, 0.01, 0.01], dtype=F64))
    start = torch.tensor([900.0, 1100.0], dtype=F64) + 200.0 * torch.rand(
        n, 2, generator=generator, dtype=F64)
    for k in range(3):
        xy = start + torch.tensor([60.0 * k, 20.0 * k], dtype=F64)
        ins_pos = torch.cat([xy + 30.0, torch.full((n, 1), 2000.0, dtype=F64)], dim=1)
        radar = 2000.0 - 520.0 * scale + torch.randn(n, generator=generator, dtype=F64)
        tan_filter_step(ekf, ins_pos, radar, lin, F=F, Q=Q, R=25.0)
    return ekf.x[:, :2].square().sum()


def test_gradient_flows_from_filter_output_to_map_parameters() -> None:
    tile = synthetic_tile((48, 48), 40.0, seed=2)
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=16, hidden=8, n_frequencies=4).double()
    loss = _filter_loss(net, torch.tensor(1.0, dtype=F64))
    loss.backward()
    grads = [p.grad for p in net.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert sum(float(g.abs().sum()) for g in grads) > 0.0


def test_filter_gradient_matches_finite_difference() -> None:
    """d loss / d (one map bias) by autograd equals a central difference (float64)."""
    tile = synthetic_tile((48, 48), 40.0, seed=2)
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=16, hidden=8, n_frequencies=4).double()
    scale = torch.tensor(1.0, dtype=F64, requires_grad=True)
    loss = _filter_loss(net, scale)
    (grad_scale,) = torch.autograd.grad(loss, scale)
    with torch.no_grad():
        h = 1e-6
        up = _filter_loss(net, torch.tensor(1.0 + h, dtype=F64))
        down = _filter_loss(net, torch.tensor(1.0 - h, dtype=F64))
    torch.testing.assert_close(grad_scale, (up - down) / (2 * h), rtol=1e-5, atol=1e-8)
    bias = net.out_bias
    (grad_bias,) = torch.autograd.grad(_filter_loss(net, torch.tensor(1.0, dtype=F64)), bias)
    block = int(grad_bias.abs().argmax())
    with torch.no_grad():
        step = 1e-6
        bias[block] += step
        up = _filter_loss(net, torch.tensor(1.0, dtype=F64))
        bias[block] -= 2 * step
        down = _filter_loss(net, torch.tensor(1.0, dtype=F64))
        bias[block] += step
    torch.testing.assert_close(grad_bias[block], (up - down) / (2 * step), rtol=1e-4, atol=1e-8)
