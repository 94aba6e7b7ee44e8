"""``neuralmap-export``: a fitted map's height, residual and slope as GeoTIFF on its DEM's grid.

::

    neuralmap-export runs/jacksboro/version_0/neural_map.pt            # DEM from the map file
    neuralmap-export neural_map.pt --dem N36W085.hgt --out qgis/ --layers [height,residual]
    neuralmap-export runs/latent_tileset_N36W085_4/version_0      # a latent tileset, per tile

Writes ``<out>/neural_map_<layer>.tif`` (default ``out``: a ``geotiff`` folder next to the
map; a latent tileset: ``<out>/latent_tileset_r000_c000_<layer>.tif`` per tile) in the
source DEM's CRS, grid and no-data (`neuralmap.terrain.geotiff`). The output folder is
checked before any work; all files are written to hidden temporary names and renamed into
place together at the end, so a failed run (a full disk, Ctrl-C) leaves the folder's
earlier files as they were and no new one. Bad input, a bad option value and a full disk
print one ``error:`` line and exit 2; Ctrl-C prints one line and exits 130.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from jsonargparse import ArgumentParser

from neuralmap.exceptions import NeuralMapError

__all__ = ["main"]

PROG = "neuralmap-export"
EXIT_BAD_INPUT = 2


def _parser() -> ArgumentParser:
    from neuralmap.terrain.geotiff import LAYERS

    parser = ArgumentParser(prog=PROG, description="Write a fitted map's height, residual and "
                            "slope as GeoTIFF on the source DEM's grid.",
                            exit_on_error=False)  # parse errors: one line (main)
    parser.add_argument("map", type=str, help="The exported map (neural_map.pt).")
    parser.add_argument("--dem", type=str | None, default=None,
                        help="The DEM the map was fitted to; default: the source the map records.")
    parser.add_argument("--spacing", type=float | None, default=None,
                        help="Grid spacing (m) of a plain .npy DEM; default: the map's record.")
    parser.add_argument("--units", type=str | None, default=None,
                        help="Units of an .asc/GeoTIFF without CRS (metres or degrees).")
    parser.add_argument("--nodata", type=float | None, default=None,
                        help="Extra no-data value of the DEM (as given to train.py).")
    parser.add_argument("--out", type=str | None, default=None,
                        help="Output folder; default: <map folder>/geotiff.")
    parser.add_argument("--layers", type=list[str], default=list(LAYERS),
                        help=f"Layers to write, of {list(LAYERS)}.")
    parser.add_argument("--cog", type=bool, default=False,
                        help="Write Cloud Optimized GeoTIFFs (tiled, internal overviews).")
    return parser


#: What each option accepts, for the one-line refusal of a value the parser rejects.
EXPECTED = {
    "spacing": "a grid spacing > 0 in metres, e.g. --spacing 30",
    "nodata": "a number, e.g. --nodata -32768",
    "layers": "a list of height, residual, slope, e.g. --layers [height,slope]",
    "cog": "true or false",
}

#: Units a DEM without a CRS can be read in (``--units``).
UNITS = ("metres", "degrees")

#: train.py's DEM options as the loader names them -> this CLI's.
_OPTION_NAMES = {"--data.spacing": "--spacing", "--data.units": "--units",
                 "--data.nodata": "--nodata"}


def _cli_option_names(text: str) -> str:
    for theirs, ours in _OPTION_NAMES.items():
        text = text.replace(theirs, ours)
    return text


def export(args: object) -> dict[str, Path]:
    """Loads the map and its DEM and writes the layers; returns layer -> path."""
    from neuralmap.dem import load_tile
    from neuralmap.terrain.export import load_map
    from neuralmap.terrain.geotiff import LAYERS, write_map_geotiffs

    out = _output_folder(args)  # before any work: a folder that cannot be made is refused
    if args.spacing is not None and not (math.isfinite(args.spacing) and args.spacing > 0):
        raise NeuralMapError(f"--spacing must be a grid spacing > 0 in metres, got "
                             f"{args.spacing}; leave it out for a DEM that carries its own.")
    if args.units is not None and args.units not in UNITS:
        raise NeuralMapError(f"--units must be one of {', '.join(UNITS)}, got {args.units!r}.")
    unknown = [name for name in args.layers if name not in LAYERS]
    if unknown or not args.layers:
        raise NeuralMapError(f"--layers: unknown or empty {unknown or args.layers}; choose "
                             f"from {list(LAYERS)}, e.g. --layers [height,slope].")
    terrain = load_map(args.map)
    from neuralmap.terrain.latent.tileset import LatentTileset

    if isinstance(terrain, LatentTileset):
        return _export_tileset(terrain, args, out)
    info = getattr(terrain, "tile_info", {}) or {}
    dem = args.dem or info.get("source") or info.get("name")
    if isinstance(dem, str) and dem.startswith("sample:"):  # "sample:jacksboro (...)"
        dem = dem.split(":", 1)[1].split()[0]
    if not dem:
        raise NeuralMapError(f"map '{args.map}' records no source DEM; give it with --dem.")
    spacing = args.spacing
    if spacing is None and str(dem).lower().endswith(".npy") and info.get("spacing"):
        spacing = tuple(info["spacing"])
    origin = tuple(info["origin"]) if info.get("origin") else None
    try:
        tile = load_tile(dem, spacing=spacing, units=args.units, nodata=args.nodata,
                         origin=origin)
    except NeuralMapError as exc:  # the loader names train.py's options; name this CLI's
        raise NeuralMapError(f"--dem {dem}: {_cli_option_names(str(exc))}") from None
    paths = write_map_geotiffs(terrain, tile, out, layers=tuple(args.layers), cog=args.cog)
    for name, path in paths.items():
        print(f"{PROG}: {name} -> {path}", flush=True)
    return paths


def _output_folder(args: object) -> Path:
    """``--out`` (default: ``geotiff`` beside the map, or inside a tileset's folder), checked
    before any work: it must be, or be able to become, a writable folder.

    Raises:
        NeuralMapError: A file in the way (``--out`` or one of its parents), a parent that
            is not writable.
    """
    from neuralmap.io import check_writable_dir

    if args.out:
        out = Path(args.out)
    else:
        folder = Path(args.map) if Path(args.map).is_dir() else Path(args.map).parent
        out = folder / "geotiff"
    return check_writable_dir(out, option="--out")


def _export_tileset(tileset: object, args: object, out: Path) -> dict[str, Path]:
    """A latent tileset: every tile's core grid, ``<out>/latent_tileset_r000_c000_<layer>.tif``
    (`neuralmap.terrain.latent.tileset_geotiff`); the region's DEM (``--dem``, default the
    files the index records) only for the residual layer."""
    from neuralmap.dem import load_mosaic, load_tile
    from neuralmap.terrain.latent.tileset_geotiff import export_tileset_geotiffs

    region = None
    if "residual" in args.layers or args.dem:
        info = tileset.tile_info  # type: ignore[attr-defined]
        dem = args.dem or info.get("source")
        if not dem:
            raise NeuralMapError(f"tileset '{args.map}' records no source DEM; give it with "
                                 "--dem, or --layers [height,slope] for the map alone.")
        files = dem.split(";") if ";" in dem else dem
        try:
            if isinstance(files, list) or any(c in files for c in "*?["):
                region = load_mosaic(files, units=args.units, nodata=args.nodata)
            else:
                region = load_tile(files, spacing=args.spacing or tuple(info.get("spacing") or ())
                                   or None, units=args.units, nodata=args.nodata)
        except NeuralMapError as exc:
            raise NeuralMapError(f"--dem {dem}: {_cli_option_names(str(exc))} (or pass "
                                 "--layers [height,slope] to export the map alone)") from None
    written = export_tileset_geotiffs(tileset, out, region=region,  # type: ignore[arg-type]
                                      layers=tuple(args.layers), cog=args.cog)
    paths: dict[str, Path] = {}
    for (row, col), layers in written.items():
        for name, path in layers.items():
            paths[f"r{row:03d}_c{col:03d}_{name}"] = path
            print(f"{PROG}: tile r{row} c{col} {name} -> {path}", flush=True)
    return paths


def main(argv: list[str] | None = None) -> None:
    """Console entry point: exit code 2 with one ``error:`` line on bad input (an option
    value the parser rejects included) or a full disk, 130 with one line on Ctrl-C."""
    from jsonargparse import ArgumentError

    from neuralmap.entry import EXIT_INTERRUPTED, interrupted_line, parse_error_message

    try:
        try:
            args = _parser().parse_args(argv)
        except ArgumentError as exc:
            raise NeuralMapError(parse_error_message(exc, PROG, EXPECTED)) from None
        export(args)
    except NeuralMapError as exc:
        sys.stdout.flush()
        print(f"{PROG}: error: {' '.join(str(exc).split())}", file=sys.stderr, flush=True)
        raise SystemExit(EXIT_BAD_INPUT) from None
    except KeyboardInterrupt:
        sys.stdout.flush()
        print(interrupted_line(PROG), file=sys.stderr, flush=True)
        raise SystemExit(EXIT_INTERRUPTED) from None


if __name__ == "__main__":  # pragma: no cover
    main()
