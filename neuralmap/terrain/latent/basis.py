"""Latent bases of a latent-grid map: what the stored latents are, and how they become
the map's cubic B-spline coefficient grid.

* ``pyramid``: an overcomplete stack of ``L`` B-spline levels, knots ``2^l`` nodes apart
  (`.pyramid`); each level is one feature channel of the synthesis.
* ``wavelet``: critically sampled: the ``3 J + 1`` subbands of a ``J``-level biorthogonal
  wavelet transform (`.wavelet`, CDF 9/7 or 5/3) of the node-lattice B-spline
  coefficient grid ``(ny + 2, nx + 2)``; the inverse transform gives that grid, one
  feature channel. As many latents as coefficients, against about 4/3 of them for the
  pyramid, and a transform that decorrelates smooth relief as JPEG 2000's does.

Both give ``(C, ny + 2, nx + 2)`` node-lattice coefficients (`LatentBasis.lattice`),
so the continuous surface, its analytic slope and the query path of
`LatentTerrainMap` are the same for both.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.latent.pyramid import level_shapes, node_lattice
from neuralmap.terrain.latent.wavelet import (
    check_levels,
    check_wavelet,
    forward_2d,
    inverse_2d,
    subband_shapes,
)

#: Known latent bases (``model.basis``).
BASES = ("pyramid", "wavelet")


@dataclass(frozen=True)
class LatentBasis:
    """A latent basis with its level count.

    Attributes:
        name: ``"pyramid"`` or ``"wavelet"``.
        levels: Pyramid levels ``L`` or wavelet levels ``J``.
        wavelet: Wavelet of the ``wavelet`` basis (``"cdf97"`` or ``"cdf53"``).
    """

    name: str
    levels: int
    wavelet: str = "cdf97"

    @property
    def channels(self) -> int:
        """Feature channels of the synthesis: ``L`` (pyramid) or 1 (wavelet)."""
        return self.levels if self.name == "pyramid" else 1

    def shapes(self, shape: tuple[int, int]) -> list[tuple[int, int]]:
        """Shapes of the stored latent arrays for a ``(ny, nx)`` tile, in storage order."""
        if self.name == "pyramid":
            return level_shapes(shape, self.levels)
        return subband_shapes((shape[0] + 2, shape[1] + 2), self.levels)

    def names(self) -> list[str]:
        """One label per latent array (``level 0`` .. or ``HL1``, .., ``LL5``)."""
        if self.name == "pyramid":
            return [f"level {k}" for k in range(self.levels)]
        return [f"{o}{j + 1}" for j in range(self.levels) for o in ("HL", "LH", "HH")] + [
            f"LL{self.levels}"]

    def lattice(self, latents: list[torch.Tensor], shape: tuple[int, int]) -> torch.Tensor:
        """``(C, ny + 2, nx + 2)`` node-lattice coefficients of the latents (differentiable)."""
        if self.name == "pyramid":
            return node_lattice(latents, shape)
        return inverse_2d(latents, self.wavelet).unsqueeze(0)

    def analyse(self, coeffs: torch.Tensor) -> list[torch.Tensor]:
        """Wavelet basis only: the subbands of a ``(ny + 2, nx + 2)`` coefficient grid."""
        if self.name != "wavelet":
            raise NeuralMapError("latent map: analyse() needs the wavelet basis.")
        return forward_2d(coeffs, self.levels, self.wavelet)

    def describe(self) -> dict[str, Any]:
        """Header entry of the bitstream."""
        out: dict[str, Any] = {"basis": self.name}
        if self.name == "wavelet":
            out["wavelet"] = self.wavelet
        return out


def check_basis(name: str, wavelet: str = "cdf97") -> str:
    """The basis name if known (and its wavelet, for the wavelet basis), else a clear error.

    Raises:
        NeuralMapError: Unknown basis or wavelet name.
    """
    if name not in BASES:
        raise NeuralMapError(
            f"latent map: unknown basis {name!r} (model.basis); use one of {list(BASES)}: "
            "'wavelet' (critically sampled CDF 9/7 subbands) or 'pyramid' (overcomplete "
            "B-spline levels)."
        )
    if name == "wavelet":
        check_wavelet(wavelet)
    return name


def make_basis(name: str, levels: int, shape: tuple[int, int], *, wavelet: str = "cdf97"
               ) -> LatentBasis:
    """A checked `LatentBasis` for a ``(ny, nx)`` tile.

    Raises:
        NeuralMapError: Unknown basis or wavelet name, or too many levels for the tile.
    """
    check_basis(name, wavelet)
    ny, nx = shape
    if name == "pyramid":
        if not 1 <= int(levels) <= 12 or 2 ** (levels - 1) > max(ny, nx):
            raise NeuralMapError(
                f"latent map: levels must be in 1..12 with 2^(levels-1) <= the tile's larger "
                f"side ({max(ny, nx)} nodes), got {levels}."
            )
    else:
        check_levels((ny + 2, nx + 2), int(levels))
    return LatentBasis(name, int(levels), wavelet)


def basis_from_header(header: dict[str, Any], shape: tuple[int, int]) -> LatentBasis:
    """The basis a bitstream header names (no ``basis`` key: the pyramid, format 1)."""
    return make_basis(str(header.get("basis", "pyramid")), int(header["levels"]), shape,
                      wavelet=str(header.get("wavelet", "cdf97")))
