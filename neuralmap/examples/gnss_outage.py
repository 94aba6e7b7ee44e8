"""Worked example: a GNSS/INS solution loses GNSS and hands over to terrain-aided navigation.

::

    python -m neuralmap.examples.gnss_outage OUT_DIR [--size tiny|full]

Everything goes through files and the two command-line tools, as a user's own data would:

1. **World**: a synthetic fractal terrain written as a geographic ESRI ASCII grid
   (``terrain.asc`` + ``terrain.prj``, WGS-84 degrees). Its heights are taken as
   ellipsoidal, so the geoid undulation of this world is 0 (given explicitly below).
2. **Drive and flight**: a level trajectory at constant ellipsoidal height above the terrain
   (`neuralmap.ins.trajectory.generate`: a take-off-like acceleration, straight legs,
   turns), a tactical-MEMS IMU (`ImuErrorProcess`) and
   1 Hz GNSS with an outage (`simulate_gnss`), written in the
   KF-GINS formats (``imu.txt``, ``gnss.txt``, the reference ``truth.nav``,
   ``kf-gins.yaml``).
3. **GNSS/INS**: ``neuralmap-gins kf-gins.yaml`` runs the 15-state loosely coupled filter
   (SEEDS 003) and writes ``KF_GINS_Navresult.nav`` and its σ file. During the outage the
   solution coasts on the IMU and drifts.
4. **Radar log**: ``radar.csv`` (``time, radar``) at 1 Hz over the outage: the true clearance
   ``h − H(x, y)`` plus altimeter noise, H the DEM's bicubic surface (the map is exact
   here; a real DEM adds its own error, see ``map_error.dem_accuracy_m``).
5. **Hand-over**: ``neuralmap-navigate KF_GINS_Navresult.nav --radar radar.csv --reference
   truth.nav --map terrain.asc --geoid_undulation 0 --config nav.yaml``: the navigator
   starts at the outage with the GNSS/INS σ of that epoch (``nav.yaml``, from the σ file)
   and bounds the drift with the terrain.

`run_example` returns the errors at the end of the outage (GNSS/INS coasting and
TAN) and the output folder.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

__all__ = ["ExampleSize", "SIZES", "run_example"]

#: Lever arm IMU -> GNSS antenna (body frame, m).
LEVER_ARM = (0.5, 0.2, -1.2)


@dataclass(frozen=True)
class ExampleSize:
    """How big the example is.

    Attributes:
        imu_rate_hz: IMU rate.
        legs: ``(duration s, speed change m/s, heading change deg)`` segments of the drive.
        outage: ``(start, end)`` of the GNSS outage, s from the start.
        nodes: Terrain nodes a side.
        cell_deg: Terrain cell size, degrees.
    """

    imu_rate_hz: float
    legs: tuple[tuple[float, float, float], ...]
    outage: tuple[float, float]
    nodes: int
    cell_deg: float


#: ``tiny`` runs in the test suite (seconds); ``full`` is the documented example.
SIZES: dict[str, ExampleSize] = {
    "tiny": ExampleSize(imu_rate_hz=10.0, legs=((10.0, 50.0, 0.0), (30.0, 0.0, 0.0),
                                                (20.0, 0.0, 60.0), (40.0, 0.0, 0.0)),
                        outage=(40.0, 100.0), nodes=96, cell_deg=0.0008),
    "full": ExampleSize(imu_rate_hz=100.0, legs=((15.0, 40.0, 0.0), (60.0, 0.0, 0.0),
                                                 (30.0, 0.0, 90.0), (120.0, 0.0, 0.0),
                                                 (30.0, 0.0, 90.0), (120.0, 0.0, 0.0)),
                        outage=(90.0, 375.0), nodes=320, cell_deg=0.0006),
}


def _write_terrain(out: Path, size: ExampleSize, *, seed: int, lat_c: float,
                   lon_c: float) -> Path:
    """A geographic ESRI ASCII grid (+ .prj) of synthetic terrain centred on (lat_c, lon_c)."""
    from neuralmap.dem.synthetic import synthetic_tile
    from neuralmap.io import atomic_write_text

    n = size.nodes
    heights = synthetic_tile((n, n), 50.0, seed=seed, relief=400.0, hurst=0.75).heights
    half = 0.5 * (n - 1) * size.cell_deg
    lines = [f"ncols {n}", f"nrows {n}", f"xllcenter {lon_c - half:.12f}",
             f"yllcenter {lat_c - half:.12f}", f"cellsize {size.cell_deg:.12f}",
             "NODATA_value -9999"]
    lines += [" ".join(f"{v:.3f}" for v in row) for row in heights[::-1]]  # first row north
    atomic_write_text(out / "terrain.prj", 'GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID['
                      '"WGS 84",6378137,298.257223563]],PRIMEM["Greenwich",0],UNIT["degree",'
                      '0.0174532925199433]]\n')
    return atomic_write_text(out / "terrain.asc", "\n".join(lines) + "\n")


def _kfgins_config(out: Path, traj: Any, imu: Any, ref: Any) -> Path:
    """KF-GINS configuration of the simulated logs (the tactical-MEMS noise)."""
    from neuralmap.io import atomic_write_text

    cfg = {
        "imupath": "imu.txt", "gnsspath": "gnss.txt", "outputpath": "gins",
        "truthpath": "truth.nav", "imudatalen": 7, "imudatarate": 1.0 / traj.dt,
        "starttime": float(imu.time[0]), "endtime": -1,
        "initpos": ref.position[0].tolist(), "initvel": ref.velocity[0].tolist(),
        "initatt": ref.euler[0].tolist(), "initgyrbias": [0, 0, 0], "initaccbias": [0, 0, 0],
        "initposstd": [0.05, 0.05, 0.1], "initvelstd": [0.02, 0.02, 0.02],
        "initattstd": [0.1, 0.1, 0.5],
        "imunoise": {"arw": [0.15] * 3, "vrw": [0.06] * 3, "gbstd": [3.0] * 3,
                     "abstd": [49.0] * 3, "gsstd": [300.0] * 3, "asstd": [300.0] * 3,
                     "corrtime": 1.0},
        "initbgstd": [10.44] * 3, "initbastd": [1100.0] * 3, "antlever": list(LEVER_ARM),
    }
    return atomic_write_text(out / "kf-gins.yaml", yaml.safe_dump(cfg, sort_keys=False))


def run_example(out_dir: str | Path, *, size: str = "tiny", seed: int = 0,
                altimeter_sigma_m: float = 3.0) -> dict[str, Any]:
    """Builds the logs, runs ``neuralmap-gins`` and ``neuralmap-navigate`` (module docstring).

    Args:
        out_dir: Folder for the logs and both tools' outputs (created).
        size: ``"tiny"`` or ``"full"`` (`SIZES`).
        seed: Seed of the terrain, the IMU, the GNSS and the altimeter noise.
        altimeter_sigma_m: Radar-altimeter noise σ, m.

    Returns:
        ``{"navigation": <neuralmap-navigate folder>, "gins_error_m": horizontal error of
        the coasting GNSS/INS at the outage end, "tan_error_m": TAN's there,
        "tan_sigma_m": TAN's reported 1σ major axis there, "ins_rmse_m", "tan_rmse_m":
        RMS over the outage, "results": results.json}``.

    Raises:
        RuntimeError: A tool failed (its exit code).
    """
    import json

    from neuralmap.dem.load import load_tile
    from neuralmap.flights.cli import main as navigate_main
    from neuralmap.ins.gins_cli import NAV_FILE, STD_FILE
    from neuralmap.ins.gins_cli import main as gins_main
    from neuralmap.ins.gnss import UrbanEffects, simulate_gnss
    from neuralmap.ins.imu_model import ImuErrorProcess
    from neuralmap.ins.kfgins import simulated_logs, write_gnss, write_imu, write_nav
    from neuralmap.ins.trajectory import Segment, generate
    from neuralmap.io import atomic_write_text
    from neuralmap.nav.georef import MapFrame
    from neuralmap.terrain.grid import GridTerrain

    spec = SIZES[size]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    lat_c, lon_c = 36.55, -84.10
    tile = load_tile(_write_terrain(out, spec, seed=seed, lat_c=lat_c, lon_c=lon_c))
    frame = MapFrame.from_tile(tile)
    terrain = GridTerrain(tile, method="bicubic")
    # start a quarter in from the west edge, heading north-east, 300 m above the highest
    # terrain (ellipsoidal height; the terrain's heights are ellipsoidal in this world)
    xmin, xmax, ymin, ymax = tile.extent
    lat0, lon0 = frame.to_geo(xmin + 0.25 * (xmax - xmin), ymin + 0.45 * (ymax - ymin))
    h0 = float(np.nanmax(tile.heights)) + 300.0
    segments = [Segment(d, dspeed=v, dheading=math.radians(a)) for d, v, a in spec.legs]
    traj = generate(segments, dt=1.0 / spec.imu_rate_hz, lat0_deg=lat0, lon0_deg=lon0, h0=h0,
                    heading0_deg=45.0)
    gen = torch.Generator().manual_seed(seed)
    gnss = simulate_gnss(traj, n_runs=1, lever_arm=LEVER_ARM, generator=gen,
                         effects=UrbanEffects(outages=(spec.outage,)))
    imu_process = ImuErrorProcess("tactical_mems", n_runs=1, dt=traj.dt, generator=gen,
                                  scale_factor=False)
    imu, gnss_log, ref = simulated_logs(traj, gnss, imu=imu_process)
    write_imu(out / "imu.txt", imu)
    write_gnss(out / "gnss.txt", gnss_log)
    write_nav(out / "truth.nav", ref)
    config = _kfgins_config(out, traj, imu, ref)
    if gins_main([str(config), "--outputpath", str(out / "gins")]) not in (None, 0):
        raise RuntimeError("neuralmap-gins failed on the simulated logs")
    # radar log over the outage at 1 Hz: true clearance + altimeter noise
    t0, t1 = spec.outage
    t_radar = np.arange(math.ceil(t0), math.ceil(t1) - 1.0 + 1e-9, 1.0)  # GNSS-free epochs
    lat = np.interp(t_radar, ref.time, ref.position[:, 0])
    lon = np.interp(t_radar, ref.time, ref.position[:, 1])
    h = np.interp(t_radar, ref.time, ref.position[:, 2])
    x, y = frame.to_map(lat, lon)
    with torch.no_grad():
        ground = terrain(torch.as_tensor(np.stack([x, y], -1))).numpy()
    noise = np.random.default_rng(seed).normal(0.0, altimeter_sigma_m, t_radar.size)
    clearance = h - ground + noise
    lines = ["time,radar"] + [f"{t!r},{c!r}" for t, c in zip(t_radar.tolist(),
                                                             clearance.tolist(), strict=True)]
    atomic_write_text(out / "radar.csv", "\n".join(lines) + "\n")
    # hand-over: the navigator starts from the GNSS/INS solution's own σ at the outage start
    std = np.loadtxt(out / "gins" / STD_FILE)
    k = int(np.argmin(np.abs(std[:, 0] - t_radar[0])))
    sigma_p = float(max(std[k, 1], std[k, 2], 0.5))
    nav_cfg = {"sensor": {"dt_s": 1.0, "altimeter_sigma_m": altimeter_sigma_m},
               "initial": {"position_sigma_m": sigma_p,
                           "altitude_sigma_m": float(max(std[k, 3], 0.5)),
                           "velocity_sigma_mps": float(max(std[k, 4:6].max(), 0.02))},
               "process_noise": {"position_sigma_m": 0.5, "altitude_sigma_m": 0.5,
                                 "velocity_sigma_mps": 0.05},
               "integrity": {"acquired_sigma_m": 40.0}}
    atomic_write_text(out / "nav.yaml", yaml.safe_dump(nav_cfg, sort_keys=False))
    code = navigate_main([str(out / "gins" / NAV_FILE), "--radar", str(out / "radar.csv"),
                          "--reference", str(out / "truth.nav"), "--map",
                          str(out / "terrain.asc"), "--geoid_undulation", "0", "--config",
                          str(out / "nav.yaml"), "--out", str(out / "navigate"),
                          "--tensorboard", "false"])
    if code != 0:
        raise RuntimeError(f"neuralmap-navigate failed (exit {code})")
    folder = max((out / "navigate").glob("version_*"), key=lambda p: int(p.name.split("_")[1]))
    results = json.loads((folder / "results.json").read_text())
    with open(folder / "navigation.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    last = rows[-1]
    ins_err = results["errors"]
    # the coasting GNSS/INS error at the outage end (INS input interpolated to that epoch)
    nav = np.loadtxt(out / "gins" / NAV_FILE)
    g_lat = np.interp(t_radar[-1], nav[:, 1], nav[:, 2])
    g_lon = np.interp(t_radar[-1], nav[:, 1], nav[:, 3])
    gx, gy = frame.to_map(g_lat, g_lon)
    return {"navigation": folder, "results": results,
            "gins_error_m": float(math.hypot(gx - x[-1], gy - y[-1])),
            "tan_error_m": float(last["horizontal_error_m"]),
            "tan_sigma_m": float(last["sigma_major_m"]),
            "ins_rmse_m": float(ins_err["ins_rmse_horizontal_m"]),
            "tan_rmse_m": float(ins_err["rmse_horizontal_m"])}


def main(argv: list[str] | None = None) -> int:
    """``python -m neuralmap.examples.gnss_outage OUT_DIR [--size tiny|full]``."""
    parser = argparse.ArgumentParser(prog="python -m neuralmap.examples.gnss_outage",
                                     description="GNSS/INS hand-over to TAN in a GNSS outage.")
    parser.add_argument("out_dir")
    parser.add_argument("--size", default="full", choices=sorted(SIZES))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    summary = run_example(args.out_dir, size=args.size, seed=args.seed)
    print(f"end of the GNSS outage: GNSS/INS coasting {summary['gins_error_m']:.1f} m off, "
          f"TAN {summary['tan_error_m']:.1f} m off (reported 1σ {summary['tan_sigma_m']:.1f} m);"
          f" RMS over the outage: INS {summary['ins_rmse_m']:.1f} m, TAN "
          f"{summary['tan_rmse_m']:.1f} m. Outputs: {summary['navigation']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
