"""Per-zone steps and entropy scales of the latent map: closed forms, the RDO choice,
bit-exact decode, code length against the ideal, old formats, and a flat-and-rough tile."""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.latent import LatentGrid, RateDistortion
from neuralmap.terrain.latent.bitstream import (
    coding_model,
    decode_latent_map,
    encode_latent_map,
    read_latent_map,
    symbol_models,
    write_latent_map,
)
from neuralmap.terrain.latent.context_model import encode_context, symbol_bits
from neuralmap.terrain.latent.encode import fit_latent_map
from neuralmap.terrain.latent.entropy import encode_located, laplace_bits, symbol_range
from neuralmap.terrain.latent.latent_grid import exact_objective, zones_pay
from neuralmap.terrain.latent.zones import (
    CODE_BITS,
    STEP_CANDIDATES,
    ZoneCodes,
    _laplace_zone_bits,
    active_groups,
    choose_step_codes,
    code_scales,
    decode_codes,
    encode_codes,
    multiplier,
    zone_index,
)


def _half_tile() -> DemTile:
    """64 x 64 nodes: the west half flat (1 cm noise), the east half rough (about 10 m)."""
    rng = np.random.default_rng(0)
    h = 100.0 + 0.01 * rng.normal(size=(64, 64))
    rough = gaussian_filter(rng.normal(size=(64, 64)), 1.5) * 30.0
    h[:, 32:] += rough[:, 32:]
    return DemTile(h, spacing=(10.0, 10.0), name="half")


FIT = {"steps": 150, "levels": 4, "between_points": 512, "rdoq": True, "zones_always": True}


@pytest.fixture(scope="module")
def fits() -> dict:
    torch.set_num_threads(1)
    tile = _half_tile()
    out = {"tile": tile}
    for zones in (0, 4):
        for lam in (0.3, 3.0):
            out[zones, lam] = fit_latent_map(tile, rate_weight=lam, zones=zones, **FIT)[0]
    out["context"] = fit_latent_map(tile, rate_weight=0.3, zones=4, entropy="context",
                                    context_hidden=4, relaxation="soft", **FIT)[0]
    return out


def test_zone_index_and_multipliers_closed_form():
    idx = zone_index((5, 8), 2)
    rows = np.array([0, 0, 0, 1, 1])  # (i * 2) // 5
    cols = np.array([0, 0, 0, 0, 1, 1, 1, 1])  # (j * 2) // 8
    np.testing.assert_array_equal(idx, rows[:, None] * 2 + cols[None, :])
    np.testing.assert_allclose(multiplier(np.array([-4, 0, 4, 8])), [0.5, 1.0, 2.0, 4.0],
                               rtol=0, atol=1e-15)
    codes = ZoneCodes(2, np.array([[4, 0, 0, -4]]), np.array([[0, 0, 0, 0]]), (0,), (True,))
    (m,) = codes.step_maps([(5, 8)])
    np.testing.assert_allclose(m, multiplier(np.array([4, 0, 0, -4]))[idx])


def test_zone_statistics_give_the_exact_laplace_code_length():
    rng = np.random.default_rng(1)
    q = np.round(rng.laplace(0, 1.7, 500))
    for b in (0.6, 0.8, 3.0):  # scales where laplace_bits' 1e-9 probability floor is not hit
        m = np.abs(q)
        got = _laplace_zone_bits(np.float64((m == 0).sum()), np.float64((m > 0).sum()),
                                   m[m > 0].sum(), np.float64(b))
        want = float(laplace_bits(torch.as_tensor(q), torch.tensor(b, dtype=torch.float64)).sum())
        assert got == pytest.approx(want, rel=1e-10)


def test_step_codes_minimise_the_zoned_objective_by_brute_force():
    # two arrays of one group: the west half near zero, the east half Laplace(0, 4 m)
    rng = np.random.default_rng(2)
    z = [rng.laplace(0, 4.0, (16, 16)) for _ in range(2)]
    for a in z:
        a[:, :8] *= 0.01
    steps, scales, gains = np.array([1.0, 1.3]), np.array([3.0, 2.5]), np.array([1.0, 0.7])
    lam = 2.0
    codes = choose_step_codes(z, steps, scales, gains, 1.0, lam, 2, [0, 0])
    idx = zone_index((16, 16), 2)
    for r in range(4):
        def cost(k: int, r: int = r) -> float:
            total_d, bits = 0.0, np.zeros(len(range(-32, 17)))
            for a, d, s, g in zip(z, steps, scales, gains, strict=True):
                x = a[idx == r]
                q = np.round(x / (d * 2 ** (k / 4)))
                total_d += g * np.sum((x - q * d * 2 ** (k / 4)) ** 2)
                for ci, c in enumerate(range(-32, 17)):
                    bits[ci] += float(laplace_bits(torch.as_tensor(q),
                                                   torch.tensor(s * 2 ** (c / 4))).sum())
            bits += CODE_BITS * np.abs(np.arange(-32, 17))
            return total_d + lam * (bits.min() + CODE_BITS * abs(k))

        best = min(cost(k) for k in STEP_CANDIDATES)
        assert cost(int(codes.step_codes[0, r])) == pytest.approx(best, rel=1e-6)
    west, east = codes.scale_codes[0, [0, 2]], codes.scale_codes[0, [1, 3]]
    assert west.max() < east.min() - 8  # the flat half's zeros get a much narrower Laplace


def test_zone_codes_round_trip_and_small_groups_carry_none():
    shapes = [(40, 40)] * 3 + [(6, 6)]
    groups = [0, 0, 0, 1]
    active = active_groups(shapes, groups, 4)
    assert active == (True, False)  # 36 coefficients < 16 per zone of a 4 x 4 grid
    rng = np.random.default_rng(3)
    steps = rng.integers(-4, 9, (2, 16)) * np.array([[1], [0]])
    scales = rng.integers(-20, 10, (2, 16)) * np.array([[1], [0]])
    codes = ZoneCodes(4, steps, scales, tuple(groups), active)
    sc = code_scales(codes)
    back = decode_codes(encode_codes(codes, sc), 4, groups, sc, shapes)
    np.testing.assert_array_equal(back.step_codes, steps)
    np.testing.assert_array_equal(back.scale_codes, scales)


@pytest.mark.parametrize("key", [(4, 0.3), (4, 3.0), "context"])
def test_zoned_decode_equals_the_encoders_reconstruction(fits, key, tmp_path: Path):
    latent_map = fits[key]
    assert latent_map.zones is not None
    data = encode_latent_map(latent_map)
    assert struct.unpack("<H", data[8:10])[0] == 4
    path = write_latent_map(latent_map, tmp_path / "m.nlat")
    back = read_latent_map(path)
    for a, b in zip(latent_map.symbols, back.symbols, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(back.zones.step_codes, latent_map.zones.step_codes)
    np.testing.assert_array_equal(back.zones.scale_codes, latent_map.zones.scale_codes)
    assert torch.equal(back.node_heights(), latent_map.node_heights())
    xy = torch.tensor([[100.0, 200.0], [555.5, 321.0]])
    with torch.no_grad():
        assert torch.equal(back(xy), latent_map(xy))


@pytest.mark.parametrize("key", [(4, 0.3), "context"])
def test_zoned_rate_matches_the_ideal_code_length(fits, key):
    """Range-coded latent words against ``sum -log2 p`` of the zoned model: within
    1 % + 64 bits (the coder's fixed-point probabilities and its final word)."""
    latent_map = fits[key]
    ranges = [symbol_range(s) for s in latent_map.symbols]
    ideal = 0.0
    for sym, (mu, b), (lo, hi) in zip(latent_map.symbols, symbol_models(latent_map), ranges,
                                      strict=True):
        ideal += float(symbol_bits(sym, mu, b, lo, hi).sum())
    if latent_map.context is None:
        words = encode_located(latent_map.symbols, symbol_models(latent_map), ranges)
    else:
        words = encode_context(coding_model(latent_map), latent_map.symbols, ranges)
    coded = 32.0 * words.size
    assert ideal <= coded + 1e-6
    assert coded <= 1.01 * ideal + 64
    # the uniform-model ideal is larger: the zones' scales are what the rate gains
    flat = [(np.zeros(s.size), np.full(s.size, float(b)))
            for s, b in zip(latent_map.symbols, latent_map.scales, strict=True)]
    if latent_map.context is None:
        uniform = sum(float(symbol_bits(s, mu, b, *r).sum())
                      for s, (mu, b), r in zip(latent_map.symbols, flat, ranges, strict=True))
        assert uniform > ideal


def test_maps_without_zones_keep_formats_2_and_3_and_load(fits):
    for latent_map, version in ((fits[0, 0.3], 2),):
        data = encode_latent_map(latent_map)
        assert struct.unpack("<H", data[8:10])[0] == version
        back = decode_latent_map(data, where="<test>")
        assert back.zones is None
        assert torch.equal(back.node_heights(), latent_map.node_heights())
    # a context map without zones: format 3, as written before zones existed
    ctx = fits["context"]
    plain = type(ctx)(ctx.symbols, ctx.steps, ctx.scales, ctx.synthesis_vector,
                      ctx.feature_scale, hidden=ctx.hidden, tile_info=ctx.tile_info,
                      basis=ctx.basis, context=ctx.context, context_hidden=ctx.context_hidden)
    data = encode_latent_map(plain)
    assert struct.unpack("<H", data[8:10])[0] == 3
    back = decode_latent_map(data, where="<test>")
    for a, b in zip(plain.symbols, back.symbols, strict=True):
        np.testing.assert_array_equal(a, b)


def test_format_4_keeps_its_header_keys(fits):
    """The file format did not change with the zones' name: the header still carries the
    zone grid side and the code scales under ``"regions"`` and ``"region_scales"``, so files
    written before read as they did."""
    data = encode_latent_map(fits[4, 0.3])
    (length,) = struct.unpack("<I", data[10:14])
    header = json.loads(zlib.decompress(data[14:14 + length]))
    assert header["regions"] == 4 and len(header["region_scales"]) == 2
    assert "zones" not in header


def test_a_checkpoint_with_the_old_buffer_names_loads():
    """Checkpoints written before the zones got their name keep the codes in buffers
    ``region_step_codes``, ``region_scale_codes``, ``regions_chosen``: they load."""
    tile = _half_tile()
    grid = LatentGrid(tile, levels=4, zones=4)
    grid.choose_zones(0.2)
    assert grid.zone_scale_codes.abs().sum() > 0  # codes to carry over
    old = {("region_step_codes" if k == "zone_step_codes" else
            "region_scale_codes" if k == "zone_scale_codes" else
            "regions_chosen" if k == "zones_chosen" else k): v
           for k, v in grid.state_dict().items()}
    assert "zone_step_codes" not in old and "region_step_codes" in old
    back = LatentGrid(tile, levels=4, zones=4)
    back.load_state_dict(old)  # strict: no missing or unexpected keys
    assert bool(back.zones_chosen)
    assert torch.equal(back.zone_step_codes, grid.zone_step_codes)
    assert torch.equal(back.zone_scale_codes, grid.zone_scale_codes)


def test_a_newer_format_is_refused(fits):
    data = bytearray(encode_latent_map(fits[4, 0.3]))
    data[8:10] = struct.pack("<H", 5)
    body = bytes(data[:-4])
    with pytest.raises(NeuralMapError, match="newer"):
        decode_latent_map(body + struct.pack("<I", zlib.crc32(body)), where="<test>")


def _rate_at(curve: list[tuple[int, float]], rmse: float) -> float:
    """Bytes of a two-point curve at ``rmse``, log-log interpolated (or extrapolated)."""
    (b0, r0), (b1, r1) = sorted(curve, key=lambda p: p[1])
    slope = np.log(b1 / b0) / np.log(r1 / r0)
    return float(b0 * (rmse / r0) ** slope)


def test_flat_and_rough_halves_get_different_steps_and_a_lower_rate(fits):
    """Measured on the 64 x 64 half-flat tile (150 steps, lambda 0.3 and 3; one run): the
    zoned maps take about 3 % fewer file bytes than the single-step curve (log-log
    through its two points) at their node RMSE: 858 B against 883 B at 0.341 m, 717 B
    against 741 B at 0.537 m. The flat half's scale codes average -12 / -9.6 (a Laplace
    2-3 octaves narrower), the rough half's -0.8 / -3.1; step codes 0 on the flat half
    (every symbol 0 whatever the step: the tie goes to 0), 2.2 / 3.1 on the rough half.
    Asserted: fewer bytes, a scale-code gap > 2, different step codes."""
    tile = fits["tile"]
    rmse = {k: float(np.sqrt(np.mean((fits[k].node_heights().numpy() - tile.heights) ** 2)))
            for k in [(0, 0.3), (0, 3.0), (4, 0.3), (4, 3.0)]}
    single = [(len(encode_latent_map(fits[0, lam])), rmse[0, lam]) for lam in (0.3, 3.0)]
    for lam in (0.3, 3.0):
        zoned = fits[4, lam]
        codes = zoned.zones
        cols = np.arange(16) % 4  # zone column: 0 west (flat), 2, 3 east (rough)
        on = np.asarray(codes.active)
        west = codes.scale_codes[on][:, cols == 0].mean()
        east = codes.scale_codes[on][:, cols >= 2].mean()
        assert west < east - 2.0  # flat ground: a narrower entropy scale (> 1/2 octave)
        steps_west = codes.step_codes[on][:, cols == 0]
        steps_east = codes.step_codes[on][:, cols >= 2]
        assert steps_west.mean() != steps_east.mean()
        print(f"lambda {lam}: zoned {len(encode_latent_map(zoned))} B at "
              f"{rmse[4, lam]:.3f} m; single-step curve there "
              f"{_rate_at(single, rmse[4, lam]):.0f} B; scale codes west {west:.1f} east "
              f"{east:.1f}; step codes west {steps_west.mean():.2f} east {steps_east.mean():.2f}")
        assert len(encode_latent_map(zoned)) < _rate_at(single, rmse[4, lam])


def test_zones_are_stored_only_where_they_pay():
    tile = _half_tile()
    grid = LatentGrid(tile, levels=4, zones=4)
    objective = RateDistortion(tile, rate_weight=0.3, between_points=0)
    target = (objective.heights, objective.valid)
    codes = grid.choose_zones(0.2)
    zero = ZoneCodes(4, np.zeros_like(codes.step_codes), np.zeros_like(codes.scale_codes),
                       codes.groups, codes.active)
    plain = grid.symbols(zero)
    # all-zero codes decode exactly as no zones (the same SSE + lambda' bits as the
    # uniform model's, computed independently), so they only add their own bits
    with torch.no_grad():
        sse = float(((grid.node_heights([torch.from_numpy(q.astype(np.float32)) * d for q, d
                                         in zip(plain, grid.steps, strict=True)])
                      - objective.heights) ** 2).sum())
    bits = sum(float(laplace_bits(torch.as_tensor(q, dtype=torch.float64),
                                  torch.tensor(float(b), dtype=torch.float64)).sum())
               for q, b in zip(plain, grid.scales.detach().numpy().astype(np.float32),
                               strict=True) if q.min() < q.max() or q.any())
    # within 2 %: the coder's model keeps the tails beyond the symbol range in the end
    # symbols, laplace_bits has infinite support
    assert exact_objective(grid, plain, zero, 0.2, *target) == pytest.approx(
        sse + 0.2 * bits, rel=2e-2)
    assert not zones_pay(grid, plain, zero, plain, 0.2, *target)
    # the chosen codes on the half-flat tile lower SSE + lambda' bits by more than they cost
    assert zones_pay(grid, grid.symbols(codes), codes, plain, 0.2, *target)
