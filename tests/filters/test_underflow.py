"""exp/log helpers of the point-mass grids: bit-identical to torch where the result is a
normal number, exactly 0 / -inf below."""

from __future__ import annotations

import math

import pytest
import torch

from neuralmap.filters.underflow import EXP_FLOOR, exp_or_zero, log_or_neg_inf


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_exp_or_zero_equals_exp_above_the_floor_and_zero_below(dtype) -> None:
    gen = torch.Generator().manual_seed(0)
    x = torch.cat([-torch.rand(20000, generator=gen, dtype=dtype) * 2000.0,
                   torch.tensor([-math.inf, 0.0, 3.0, EXP_FLOOR[dtype]], dtype=dtype)])
    got = exp_or_zero(x)
    ref = x.exp()
    keep = x >= EXP_FLOOR[dtype]
    assert torch.equal(got[keep], ref[keep])
    assert bool((got[~keep] == 0).all())
    assert bool((ref[~keep] <= math.exp(EXP_FLOOR[dtype])).all())  # only such masses dropped
    y = x.clone()
    out = exp_or_zero(y, out_of_place=False)
    assert out.data_ptr() == y.data_ptr() and torch.equal(out, got)
    assert bool(exp_or_zero(torch.tensor([math.nan], dtype=dtype)).isnan().all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_log_or_neg_inf_equals_log(dtype) -> None:
    w = torch.cat([torch.rand(1000, dtype=dtype), torch.zeros(7, dtype=dtype),
                   torch.tensor([1e-40 if dtype == torch.float32 else 1e-310], dtype=dtype)])
    assert torch.equal(log_or_neg_inf(w), w.log())
