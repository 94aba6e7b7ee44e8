"""Context entropy model of the wavelet latents: closed forms, causality, code length vs
ideal, bit-exact decode, soft rounding and RDOQ."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from scipy import stats

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.latent import LatentGrid, LatentTerrainMap, RateDistortion, export_map
from neuralmap.terrain.latent.bitstream import encode_latent_map, read_latent_map, write_latent_map
from neuralmap.terrain.latent.context_model import (
    CAUSAL,
    CodingModel,
    ContextModel,
    decode_context,
    encode_context,
    ideal_context_bits,
    parameter_count,
    plog2,
    subband_links,
    symbol_bits,
    wavefront_order,
)
from neuralmap.terrain.latent.encode import fit_latent_map, soft_alpha
from neuralmap.terrain.latent.entropy import laplace_bits
from neuralmap.terrain.latent.latent_grid import rdoq_symbols, soft_round
from neuralmap.terrain.latent.wavelet import subband_shapes


def _tile() -> DemTile:
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:30, 0:34] * 25.0
    h = 300 + 40 * np.sin(x / 200) * np.cos(y / 150) + rng.normal(0, 0.5, x.shape)
    h[:, 20:] += 3 * rng.normal(0, 1, (30, 14))  # a rough part beside a smooth one
    return DemTile(h, spacing=(25.0, 25.0), name="ctx")


@pytest.fixture(scope="module")
def trained() -> tuple[DemTile, LatentGrid, LatentTerrainMap]:
    tile = _tile()
    torch.manual_seed(0)
    grid = LatentGrid(tile, levels=3, init_step=0.3, entropy="context", context_hidden=6)
    objective = RateDistortion(tile, rate_weight=0.05, between_points=256)
    opt = torch.optim.Adam(grid.parameters(), lr=0.02)
    for step in range(40):
        loss = objective(grid, "soft" if step < 30 else "ste", alpha=soft_alpha(step, 40, 0.25)).loss
        opt.zero_grad()
        loss.backward()
        opt.step()
    return tile, grid, export_map(grid, rdoq_rate_weight=0.05,
                                  rdoq_target=(objective.heights, objective.valid))


def _random_coder(seed: int, shape: tuple[int, int], levels: int, hidden: int = 5):
    rng = np.random.default_rng(seed)
    shapes = subband_shapes(shape, levels)
    symbols = [rng.laplace(0, 3, s).round().astype(np.int32) for s in shapes]
    vector = rng.normal(0, 0.05, parameter_count(hidden)).astype(np.float16).astype(np.float32)
    steps = rng.uniform(0.5, 2, len(shapes)).astype(np.float32)
    scales = np.full(len(shapes), 2.0, np.float32)
    ranges = [(min(0, int(s.min())), max(0, int(s.max()))) for s in symbols]
    return CodingModel(vector, hidden, shapes, levels, steps, scales), symbols, ranges


def test_located_laplace_bits_match_scipy_closed_form():
    q = np.arange(-6, 7, dtype=np.float64)
    mu, b = 0.37, 1.7
    ref = -np.log2(stats.laplace.cdf(q + 0.5, mu, b) - stats.laplace.cdf(q - 0.5, mu, b))
    got = laplace_bits(torch.from_numpy(q - mu), torch.tensor(b, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-10)
    # the coder's form: the end symbols take the tails
    lo, hi = -6, 6
    tails = ref.copy()
    tails[0] = -np.log2(stats.laplace.cdf(lo + 0.5, mu, b))
    tails[-1] = -np.log2(stats.laplace.sf(hi - 0.5, mu, b))
    coded = symbol_bits(q, np.full(q.size, mu), np.full(q.size, b), lo, hi)
    np.testing.assert_allclose(coded, tails, rtol=1e-10, atol=1e-10)


def test_piecewise_linear_log_is_exact_at_powers_of_two_and_close_between():
    v = np.array([1.0, 2.0, 4.0, 1024.0])
    np.testing.assert_array_equal(plog2(v), np.log2(v))
    u = np.geomspace(1, 1e4, 1001)
    assert np.abs(plog2(u) - np.log2(u)).max() < 0.087  # max of x - log2(1+x)... on [0, 1]
    torch.testing.assert_close(plog2(torch.from_numpy(u)), torch.from_numpy(plog2(u)),
                               rtol=0, atol=0)


@pytest.mark.parametrize("shape", [(1, 1), (2, 5), (7, 3), (9, 12)])
def test_wavefront_order_is_a_causal_permutation(shape: tuple[int, int]):
    order = wavefront_order(shape)
    np.testing.assert_array_equal(np.sort(order), np.arange(shape[0] * shape[1]))
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    h, w = shape
    for i in range(h):
        for j in range(w):
            for di, dj in CAUSAL:
                a, b = i + di, j + dj
                if 0 <= a < h and 0 <= b < w:
                    assert rank[a * w + b] < rank[i * w + j], ((i, j), (a, b))


def test_subband_links_decode_parents_first():
    links = subband_links(2)  # storage [HL1, LH1, HH1, HL2, LH2, HH2, LL2]
    assert links.order == (6, 3, 4, 5, 0, 1, 2)
    assert links.parent == (3, 4, 5, 6, 6, 6, -1)
    assert links.siblings[2] == (0, 1) and links.siblings[3] == ()
    seen = set()
    for band in links.order:
        assert links.parent[band] < 0 or links.parent[band] in seen
        assert all(s in seen for s in links.siblings[band])
        seen.add(band)


@pytest.mark.parametrize("seed,shape,levels", [(0, (43, 37), 4), (1, (10, 11), 2)])
def test_random_context_coder_round_trips_and_meets_its_ideal_length(seed, shape, levels):
    model, symbols, ranges = _random_coder(seed, shape, levels)
    words = encode_context(model, symbols, ranges)
    back = decode_context(model, words, ranges)
    for a, b in zip(symbols, back, strict=True):
        np.testing.assert_array_equal(a, b)
    ideal = ideal_context_bits(model, symbols, ranges)
    assert abs(32 * words.size - ideal) <= 0.01 * ideal + 64


def test_training_model_matches_the_coding_model(trained):
    _, grid, m = trained
    coder = CodingModel(m.context, m.context_hidden, [s.shape for s in m.symbols], m.levels,
                        m.steps, m.scales)
    net = ContextModel(grid.basis.shapes(grid.shape), grid.levels, hidden=m.context_hidden)
    net.load_parameter_vector(torch.from_numpy(m.context))
    with torch.no_grad():
        ref = net.parameters_of([torch.from_numpy(s).float() for s in m.symbols],
                                torch.from_numpy(m.steps), torch.from_numpy(np.log(m.scales)))
    for (mu, b), (mu_t, b_t) in zip(coder.all_parameters(m.symbols), ref, strict=True):
        np.testing.assert_allclose(mu, mu_t.numpy(), atol=1 / 128 + 1e-4)
        np.testing.assert_allclose(np.log(b), np.log(b_t.numpy()), atol=1 / 32 + 1e-4)


def test_file_size_matches_the_ideal_code_length(trained):
    _, _, m = trained
    data = encode_latent_map(m)
    coder = CodingModel(m.context, m.context_hidden, [s.shape for s in m.symbols], m.levels,
                        m.steps, m.scales)
    ranges = [(min(0, int(s.min())), max(0, int(s.max()))) for s in m.symbols]
    ideal_bytes = ideal_context_bits(coder, m.symbols, ranges) / 8
    words = encode_context(coder, m.symbols, ranges)
    assert abs(4 * words.size - ideal_bytes) <= 0.01 * ideal_bytes + 8
    # the context weights are in the file (float16) and counted in its size
    assert len(data) >= 4 * words.size + 2 * parameter_count(m.context_hidden)


def test_context_map_round_trip_is_bit_exact(trained, tmp_path: Path):
    _, _, m = trained
    loaded = read_latent_map(write_latent_map(m, tmp_path / "ctx.nlat"))
    assert loaded.entropy == "context"
    for a, b in zip(m.symbols, loaded.symbols, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(loaded.context, m.context)
    xy = torch.rand(200, 2) * 700
    torch.testing.assert_close(loaded(xy), m(xy), rtol=0, atol=0)


def test_damaged_context_file_is_refused(trained, tmp_path: Path):
    data = bytearray(encode_latent_map(trained[2]))
    data[len(data) // 2] ^= 0x40
    path = tmp_path / "bad.nlat"
    path.write_bytes(bytes(data))
    with pytest.raises(NeuralMapError, match="checksum"):
        read_latent_map(path)


def test_soft_round_limits_and_continuity():
    y = torch.linspace(-3, 3, 601, dtype=torch.float64)
    torch.testing.assert_close(soft_round(y, 1e-4), y, atol=1e-6, rtol=0)
    off_half = (y - y.round()).abs() < 0.35  # tanh(60 * 0.15) = 1 - 3e-8
    torch.testing.assert_close(soft_round(y, 60.0)[off_half], y.round()[off_half], atol=1e-7,
                               rtol=0)
    k = torch.tensor([0.5, 1.5, -0.5], dtype=torch.float64)  # continuous at half-integers
    torch.testing.assert_close(soft_round(k - 1e-9, 5.0), soft_round(k + 1e-9, 5.0), atol=1e-7,
                               rtol=0)


def test_rdoq_lowers_the_exact_objective(trained):
    tile, grid, _ = trained
    heights = torch.as_tensor(tile.heights, dtype=torch.float32)
    symbols, info = rdoq_symbols(grid, 0.05, heights)
    assert info["j_rdoq"] < info["j_round"] and info["passes"] >= 1
    # J recomputed independently: node SSE of the stored map + lambda x its ideal code length
    m = LatentTerrainMap(symbols, grid.steps.detach().numpy(), grid.scales.detach().numpy(),
                         grid.synthesis.parameter_vector().detach().numpy(),
                         grid.synthesis.feature_scale.numpy(), hidden=0,
                         tile_info=grid.tile_info, basis=grid.basis)
    sse = float(((m.node_heights().numpy() - tile.heights) ** 2).sum())
    coder = CodingModel(export_map(grid).context, grid.context.hidden,
                        [s.shape for s in symbols], grid.levels,
                        grid.steps.detach().numpy().astype(np.float32),
                        grid.scales.detach().numpy().astype(np.float32))
    ranges = [(min(0, int(s.min())), max(0, int(s.max()))) for s in symbols]
    j = sse + 0.05 * ideal_context_bits(coder, symbols, ranges)
    assert j == pytest.approx(info["j_rdoq"], rel=1e-3)


def test_context_model_needs_the_wavelet_basis():
    with pytest.raises(NeuralMapError, match="basis: wavelet"):
        LatentGrid(_tile(), levels=3, basis="pyramid", entropy="context")
    with pytest.raises(NeuralMapError, match="entropy model"):
        LatentGrid(_tile(), levels=3, entropy="arithmetic")


def test_fit_with_context_soft_rounding_and_rdoq_runs_end_to_end():
    m, history = fit_latent_map(_tile(), rate_weight=0.1, steps=12, levels=3,
                                between_points=64, entropy="context", relaxation="soft",
                                rdoq=True, context_hidden=4)
    assert m.entropy == "context" and np.isfinite(history["loss"])
    with pytest.raises(NeuralMapError, match="relaxation"):
        fit_latent_map(_tile(), rate_weight=0.1, steps=1, levels=3, relaxation="gumbel")


def test_tiny_config_trains_a_context_map_through_train_py(tmp_path: Path, capsys):
    from neuralmap.training.cli import main

    configs = Path(__file__).resolve().parents[2] / "configs"
    path = main(["latent", "--config", str(configs / "latent_map.yaml"), "--config",
                 str(configs / "latent_map_tiny.yaml"), "--model.entropy", "context",
                 "--model.relaxation", "soft", "--model.rdoq", "true",
                 "--runs_dir", str(tmp_path)])
    capsys.readouterr()
    assert path is not None
    latent_map = read_latent_map(path)
    assert latent_map.entropy == "context" and latent_map.metrics["rmse_m"] > 0
