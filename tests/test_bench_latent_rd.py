"""Bjøntegaard delta rate of the latent-map benchmarks against closed forms."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def _bench():
    spec = importlib.util.spec_from_file_location(
        "bench_latent_rd", REPO_ROOT / "benchmarks" / "bench_latent_rd.py")
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    sys.modules["bench_latent_rd"] = bench  # dataclasses look their module up
    spec.loader.exec_module(bench)
    return bench


REF = [(80_000.0, 0.4), (40_000.0, 0.9), (21_000.0, 1.8), (12_000.0, 3.1), (7_000.0, 6.0)]


@pytest.mark.parametrize("factor", [0.7, 1.0, 1.25])
def test_constant_rate_factor_gives_exactly_that_bd_rate(factor: float):
    bench = _bench()
    test = [(b * factor, r) for b, r in REF]
    result = bench.bd_rate_span(test, REF)
    assert result.percent == pytest.approx((factor - 1.0) * 100.0, abs=1e-9)
    assert (result.lo_m, result.hi_m) == pytest.approx((0.5, 5.0))
    assert result.note == ""


def test_flat_tile_curves_under_the_window_use_their_overlap():
    # every point under 0.5 m (a flat tile): computed over the curves' own overlap, said so
    bench = _bench()
    ref = [(b, r / 20.0) for b, r in REF]  # 0.02-0.3 m
    test = [(0.8 * b, r * 1.1) for b, r in ref]  # 0.022-0.33 m, 20 % fewer bytes
    result = bench.bd_rate_span(test, ref)
    assert math.isfinite(result.percent)
    assert result.lo_m == pytest.approx(0.022) and result.hi_m == pytest.approx(0.3)
    assert "whole overlap" in result.note
    # closed form with a constant factor over that range
    same = bench.bd_rate_span([(0.8 * b, r) for b, r in ref], ref)
    assert same.percent == pytest.approx(-20.0, abs=1e-9)


def test_lossless_points_are_dropped_not_nan():
    bench = _bench()
    test = [(b * 1.1, r) for b, r in REF] + [(200_000.0, 0.0)]
    result = bench.bd_rate_span(test, REF)
    assert result.percent == pytest.approx(10.0, abs=1e-9)
    assert "RMSE 0" in result.note


def test_no_overlap_is_nan_with_a_reason_and_a_warning():
    bench = _bench()
    far = [(b, r * 100.0) for b, r in REF]
    result = bench.bd_rate_span(far, REF)
    assert np.isnan(result.percent) and "do not overlap" in result.note
    with pytest.warns(RuntimeWarning, match="do not overlap"):
        assert np.isnan(bench.bd_rate(far, REF))
    with pytest.warns(RuntimeWarning, match=">= 2 points"):
        assert np.isnan(bench.bd_rate(REF[:1], REF))
