"""Latent-grid neural maps: multiresolution latents, a smooth kernel, a tiny decoder.

The stored latents are the subbands of a CDF 9/7 wavelet transform of one cubic B-spline
coefficient grid (critically sampled, the default) or a few latent grids at decreasing
resolution (the Cool-chic / C3 / Instant-NGP line; `.basis`, `.wavelet`),
upsampled with the cubic B-spline kernel (`.bspline`), mixed by a linear synthesis
plus a tiny tanh MLP (`.synthesis`), and stored as range-coded integer latents under a
factorized Laplace entropy model (`.entropy`, `.bitstream`) or under the context model
(`.context_model`: a small stored MLP predicts each wavelet coefficient's Laplace location
and scale from causal neighbours, parent and siblings; decoded wavefront by wavefront),
the final symbols optionally chosen by RDOQ (`.rdoq`), with their own quantisation step
and entropy scale per zone of an ``R x R`` grid of zones if asked (`.zones`). Training state:
`LatentGrid` with the rate-distortion objective `RateDistortion`; the decoded
map is `LatentTerrainMap`, a `TerrainModel`. A region of many tiles is a
`LatentTileset` (`.tileset`: an index plus one bitstream per tile, decoded lazily into a
bounded cache, blended C² across seams).
"""

from neuralmap.terrain.latent.bitstream import (
    is_latent_file,
    read_latent_map,
    write_latent_map,
)
from neuralmap.terrain.latent.latent_grid import LatentGrid, export_map
from neuralmap.terrain.latent.map import LatentTerrainMap
from neuralmap.terrain.latent.objective import RateDistortion, check_rate_weight
from neuralmap.terrain.latent.tileset import LatentTileset

__all__ = [
    "LatentGrid",
    "LatentTerrainMap",
    "LatentTileset",
    "RateDistortion",
    "check_rate_weight",
    "export_map",
    "is_latent_file",
    "read_latent_map",
    "write_latent_map",
]
