"""Wavelet basis of latent-grid maps: lifting vs filter bank, perfect reconstruction, exact
start, bitstream round trip, rate estimate, bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.export import load_map
from neuralmap.terrain.latent import (
    LatentGrid,
    LatentTerrainMap,
    RateDistortion,
    export_map,
    write_latent_map,
)
from neuralmap.terrain.latent.bitstream import encode_latent_map
from neuralmap.terrain.latent.bspline import interpolating_coefficients, node_values
from neuralmap.terrain.latent.entropy import encode_levels, ideal_bits
from neuralmap.terrain.latent.wavelet import (
    analysis_1d,
    forward_2d,
    inverse_2d,
    subband_shapes,
)

# JPEG 2000 analysis taps (ISO/IEC 15444-1 Annex F), centre first; scaled below to the
# module's sqrt(2) normalisation.
_LOW97 = (0.6029490182363579, 0.2668641184428723, -0.07822326652898785,
          -0.01686411844287495, 0.02674875741080976)
_HIGH97 = (1.115087052456994, -0.5912717631142470, -0.05754352622849957,
           0.09127176311424948)
_LOW53 = (0.75, 0.25, -0.125)
_HIGH53 = (1.0, -0.5)


def _symmetric_filter(x: np.ndarray, half: tuple[float, ...]) -> np.ndarray:
    """Symmetric FIR filter with whole-sample symmetric extension (NumPy, float64)."""
    n, p = len(x), len(half) - 1
    idx = np.arange(-p, n + p) % (2 * (n - 1))
    idx = np.where(idx > n - 1, 2 * (n - 1) - idx, idx)
    ext = x[idx]
    taps = np.concatenate([half[:0:-1], half])
    return np.array([ext[i : i + 2 * p + 1] @ taps for i in range(n)])


@pytest.mark.parametrize("wavelet", ["cdf97", "cdf53"])
@pytest.mark.parametrize("n", [2, 3, 4, 7, 8, 13, 20])
def test_lifting_equals_jpeg2000_filter_bank(wavelet: str, n: int):
    """Lifting with mirrored neighbours == the JPEG 2000 filter bank with symmetric
    extension (float64, 1e-12), odd and even lengths."""
    low, high = (_LOW97, _HIGH97) if wavelet == "cdf97" else (_LOW53, _HIGH53)
    x = np.random.default_rng(n).normal(size=n)
    ref_low = _symmetric_filter(x, tuple(np.sqrt(2) * np.asarray(low)))[0::2]
    ref_high = _symmetric_filter(x, tuple(np.asarray(high) / np.sqrt(2)))[1::2]
    s, d = analysis_1d(torch.from_numpy(x), wavelet)
    np.testing.assert_allclose(s.numpy(), ref_low, atol=1e-12, rtol=0)
    np.testing.assert_allclose(d.numpy(), ref_high, atol=1e-12, rtol=0)


@pytest.mark.parametrize("wavelet", ["cdf97", "cdf53"])
@pytest.mark.parametrize(("shape", "levels"), [((2, 3), 1), ((7, 9), 2), ((33, 42), 4),
                                                ((46, 36), 5)])
def test_perfect_reconstruction_any_size(wavelet: str, shape: tuple[int, int], levels: int):
    x = torch.from_numpy(np.random.default_rng(1).normal(size=shape) * 100.0)
    bands = forward_2d(x, levels, wavelet)
    assert [tuple(b.shape) for b in bands] == subband_shapes(shape, levels)
    assert sum(b.numel() for b in bands) == x.numel()  # critically sampled
    torch.testing.assert_close(inverse_2d(bands, wavelet), x, atol=1e-10, rtol=0)


def test_near_orthonormal_energy():
    """The sqrt(2) normalisation keeps the energy of white noise within 10 % per level."""
    x = torch.from_numpy(np.random.default_rng(2).normal(size=(256, 256)))
    bands = forward_2d(x, 3)
    ratio = sum(float((b**2).sum()) for b in bands) / float((x**2).sum())
    assert ratio == pytest.approx(1.0, abs=0.1)


def test_interpolating_coefficients_are_the_natural_cubic_spline():
    """The exact start's B-spline == scipy's natural cubic interpolating spline, at and
    between the nodes (1-D slice of a separable start, float64)."""
    from scipy.interpolate import CubicSpline

    h = np.random.default_rng(4).normal(size=(1, 17)) * 10.0
    c = interpolating_coefficients(torch.from_numpy(np.repeat(h, 3, axis=0)))[2].numpy()
    u = np.linspace(0.0, 16.0, 161)
    j = np.minimum(np.floor(u), 15).astype(int)
    t = u - j
    w = np.stack([(1 - t) ** 3, 3 * t**3 - 6 * t**2 + 4, -3 * t**3 + 3 * t**2 + 3 * t + 1,
                  t**3]) / 6
    ours = sum(w[a] * c[j + a] for a in range(4))
    ref = CubicSpline(np.arange(17.0), h[0], bc_type="natural")(u)
    np.testing.assert_allclose(ours, ref, atol=1e-9, rtol=0)


def _tile(seed: int = 0, shape: tuple[int, int] = (29, 35)) -> DemTile:
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0 : shape[0], 0 : shape[1]] * 25.0
    h = 300 + 40 * np.sin(x / 200) * np.cos(y / 150) + rng.normal(0, 0.5, x.shape)
    return DemTile(h, spacing=(25.0, 25.0), name=f"wave{seed}")


def test_wavelet_exact_start_reproduces_every_node():
    """Odd tile (29 x 35 nodes): the unquantised start gives the DEM at every node."""
    rng = np.random.default_rng(3)
    heights = np.cumsum(rng.normal(0.0, 80.0, (23, 31)), axis=1)
    tile = DemTile(heights, spacing=(2000.0, 2000.0), name="rough")
    grid = LatentGrid(tile, levels=3, basis="wavelet")
    latents = [z.detach().double() for z in grid.latents]
    nodes = node_values(grid.basis.lattice(latents, tile.shape))[0].numpy() + heights.mean()
    assert np.abs(nodes - heights).max() < 2e-3  # float32 latents of ~1 km values


@pytest.fixture(scope="module")
def trained() -> tuple[DemTile, LatentGrid, LatentTerrainMap]:
    tile = _tile()
    torch.manual_seed(0)
    grid = LatentGrid(tile, levels=3, hidden=0, init_step=0.2, basis="wavelet")
    objective = RateDistortion(tile, rate_weight=0.05, between_points=256)
    opt = torch.optim.Adam(grid.parameters(), lr=0.02)
    for _ in range(30):
        loss = objective(grid, "noise").loss
        opt.zero_grad()
        loss.backward()
        opt.step()
    return tile, grid, export_map(grid, metrics={"rmse_m": 0.5})


def test_wavelet_round_trip_is_exact(trained, tmp_path: Path):
    tile, grid, m = trained
    loaded = load_map(write_latent_map(m, tmp_path / "w.nlat"))
    assert isinstance(loaded, LatentTerrainMap) and loaded.basis == grid.basis
    for a, b in zip(grid.symbols(), loaded.symbols, strict=True):
        np.testing.assert_array_equal(a, b)
    torch.testing.assert_close(loaded.coeffs, m.coeffs, rtol=0, atol=0)
    xy = torch.from_numpy(tile.node_xy().reshape(-1, 2)).float()
    torch.testing.assert_close(loaded(xy), m(xy), rtol=0, atol=0)
    # queries == the float64 node decode of the stored latents
    torch.testing.assert_close(loaded(xy).double().view(tile.shape), loaded.node_heights(),
                               atol=2e-3, rtol=0)


def test_wavelet_rate_estimate_within_5_percent_of_file(trained):
    _, grid, m = trained
    with torch.no_grad():
        _, bits = grid.relaxed("round")
    assert float(bits) == pytest.approx(ideal_bits(m.symbols, list(m.scales)), rel=1e-4)
    words = encode_levels(m.symbols, [float(b) for b in m.scales])
    assert abs(4 * words.size - float(bits) / 8) <= 0.05 * float(bits) / 8
    # the file = the coded latents + the layout's fixed parts (bitstream module docstring)
    data = encode_latent_map(m)
    json_len = int.from_bytes(data[10:14], "little")
    count, channels = len(m.symbols), 1
    fixed = 14 + json_len + 8 * count + 4 * channels + 4 * (channels + 1) + 4 + 4
    assert len(data) == fixed + 4 * words.size


def test_unknown_basis_wavelet_or_too_many_levels_is_a_clear_error():
    tile = _tile(shape=(9, 11))
    with pytest.raises(NeuralMapError, match=r"unknown basis 'dct'.*model.basis"):
        LatentGrid(tile, basis="dct")
    with pytest.raises(NeuralMapError, match=r"unknown wavelet 'haar'.*cdf53"):
        LatentGrid(tile, basis="wavelet", wavelet="haar")
    with pytest.raises(NeuralMapError, match=r"6 levels does not fit a 11 x 13.*fewer"):
        LatentGrid(tile, basis="wavelet", levels=6)
