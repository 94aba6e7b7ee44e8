"""Batched TAN truth simulator: trajectories, INS errors, radar altimeter, DEM error, outliers.

Everything is batched over the N Monte Carlo runs (no Python loop over runs; the nominal
path is built by a loop over time steps). Random numbers come from a seeded CPU generator
in float64 and are then cast, so a seed gives the same truth on every device and dtype.

Models (see `neuralmap.lab.scenario` for the parameters):

- Flight: a nominal path from the start at ``speed_mps``, rate-limited turns
  (``turn_rate_dps``) toward the waypoints in order, straight flight otherwise; each run is
  the nominal path translated by a random start offset ``N(0, start_spread_m² I)``.
  Altitude ``max(tile) + altitude_agl_m + climb_rate_mps · t``.
- INS errors (SEEDS 004 5-state error model): ``δX_0 ~ N(init_error_mean,
  diag(init_error_sigma²))``, ``δX_{k+1} = Φ δX_k + w_k``, ``w_k ~ N(0, Q_truth)``
  (`Scenario.truth_process_noise`); INS output = truth + δX.
- Radar altimeter: ``h_radar = h_true − terrain_true(p_true) + v``,
  ``v ~ N(0, altimeter_sigma_m²)``; with probability ``outlier_prob`` a sample also gets
  ``N(0, outlier_sigma_m²)`` (flagged in ``outlier``).
- True terrain: bicubic `GridTerrain` of the tile plus, when
  ``dem_error_sigma_m > 0``, a DEM-making error field (`dem_error_field`), one
  realisation per seed shared by all runs (the world is fixed, the map is wrong).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.altimeter import altimeter_faults, footprint_roughness
from neuralmap.lab.scenario import Scenario
from neuralmap.lab.truth_terrain import TrueTerrain, dem_error_field, true_terrain
from neuralmap.tan.model import TanModel
from neuralmap.terrain.grid import GridTerrain

__all__ = ["Truth", "dem_error_field", "nominal_path", "simulate"]


@dataclass
class Truth:
    """Simulated truth, INS outputs and altimeter measurements of N runs over K steps.

    Attributes:
        t: ``(K+1,)`` sample times, s (``t[k] = k · dt``).
        pos: ``(N, K+1, 3)`` true ``x, y, h`` (m, tile frame).
        vel: ``(N, K+1, 2)`` true horizontal velocity, m/s.
        ins_pos: ``(N, K+1, 3)`` INS position = ``pos + ins_error[..., :3]``.
        ins_vel: ``(N, K+1, 2)`` INS velocity = ``vel + ins_error[..., 3:]``.
        radar: ``(N, K+1)`` measured clearance (radar altimeter), m.
        terrain_true: ``(N, K+1)`` true terrain height under the aircraft, m.
        outlier: ``(N, K+1)`` bool, the altimeter sample is an outlier.
        on_map: ``(N, K+1)`` bool, the true position is inside the tile.
        ins_error: ``(N, K+1, 5)`` true INS error ``δX`` (INS − truth).
        extent: The tile's ``(xmin, xmax, ymin, ymax)``.
        tile_name: The tile's name.
        tile_fingerprint: The tile's `DemTile.fingerprint` (the DEM, not the truth
            terrain with DEM error), checked against the map's.
        scenario: The scenario simulated.
        seed: The seed used.
        dem_error: ``(ny, nx)`` DEM-making error field added to the tile (m), or None.
        terrain: The truth terrain flown over (`true_terrain`).
        fault: ``(N, K+1)`` int8 altimeter fault code per epoch
            (`FAULT_CODES`: 0 clean, 1 spike, 2 patch, 3
            loss of lock; ``radar`` is NaN at a loss of lock).
        quality: ``(N, K+1, 3)`` the altimeter's quality record
            (`QUALITY_COLUMNS`: footprint roughness of the
            map at the INS position, height above ground read by the altimeter, lock flag).
    """

    t: torch.Tensor
    pos: torch.Tensor
    vel: torch.Tensor
    ins_pos: torch.Tensor
    ins_vel: torch.Tensor
    radar: torch.Tensor
    terrain_true: torch.Tensor
    outlier: torch.Tensor
    on_map: torch.Tensor
    ins_error: torch.Tensor
    extent: tuple[float, float, float, float]
    tile_name: str
    tile_fingerprint: str
    scenario: Scenario
    seed: int
    dem_error: np.ndarray | None = field(default=None, repr=False)
    terrain: TrueTerrain | None = field(default=None, repr=False)
    fault: torch.Tensor | None = field(default=None, repr=False)
    quality: torch.Tensor | None = field(default=None, repr=False)

    @property
    def n_runs(self) -> int:
        """Number of runs N."""
        return int(self.pos.shape[0])

    @property
    def n_steps(self) -> int:
        """Number of filter steps K (``K + 1`` samples)."""
        return int(self.pos.shape[1]) - 1

    def take(self, index: torch.Tensor) -> Truth:
        """The runs ``index`` (a ``(M,)`` index or an ``(N,)`` bool mask) as a new `Truth`."""
        index = torch.as_tensor(index, device=self.pos.device)
        if index.dtype == torch.bool:
            index = index.nonzero().reshape(-1)
        per_run = {f.name: getattr(self, f.name).index_select(0, index)
                   for f in dataclasses.fields(self)
                   if f.name != "t" and isinstance(getattr(self, f.name), torch.Tensor)}
        return dataclasses.replace(self, **per_run)


def _heading_vector(psi: float) -> np.ndarray:
    """Unit east/north vector of a heading in radians clockwise from north."""
    return np.array([math.sin(psi), math.cos(psi)])


def nominal_path(scenario: Scenario, tile: DemTile) -> tuple[np.ndarray, np.ndarray]:
    """The nominal horizontal path (before the per-run offset) in the tile frame.

    Pure pursuit of the waypoints with the heading change per step limited to
    ``turn_rate_dps · dt``; a waypoint is taken when it is closer than the turn radius
    ``speed / turn_rate`` (or one step). Positions are integrated with the mean of the
    heading vectors at both ends of the step.

    Args:
        scenario: The scenario (validated).
        tile: The tile (for the origin and the automatic start).

    Returns:
        ``(xy (K+1, 2), vel (K+1, 2))`` float64 arrays: absolute metric positions and
        velocities.
    """
    k_steps = scenario.n_steps
    dt = scenario.dt
    speed = scenario.speed_mps
    psi = math.radians(scenario.heading_deg)
    origin = np.asarray(tile.origin, dtype=np.float64)
    if scenario.start_xy is None:
        xmin, xmax, ymin, ymax = tile.extent
        centre = np.array([0.5 * (xmin + xmax), 0.5 * (ymin + ymax)])
        start = centre - 0.5 * speed * scenario.duration_s * _heading_vector(psi)
    else:
        start = origin + np.asarray(scenario.start_xy, dtype=np.float64)
    waypoints = [origin + np.asarray(w, dtype=np.float64) for w in (scenario.waypoints or [])]
    rate = math.radians(scenario.turn_rate_dps)
    capture = max(speed / rate, speed * dt)
    max_turn = rate * dt
    xy = np.empty((k_steps + 1, 2))
    heading = np.empty(k_steps + 1)
    xy[0], heading[0] = start, psi
    index = 0
    for k in range(k_steps):
        while index < len(waypoints) and np.hypot(*(waypoints[index] - xy[k])) <= capture:
            index += 1
        new_psi = psi
        if index < len(waypoints):
            d = waypoints[index] - xy[k]
            desired = math.atan2(d[0], d[1])
            turn = (desired - psi + math.pi) % (2.0 * math.pi) - math.pi
            new_psi = psi + min(max(turn, -max_turn), max_turn)
        step = 0.5 * speed * dt * (_heading_vector(psi) + _heading_vector(new_psi))
        xy[k + 1] = xy[k] + step
        psi = new_psi
        heading[k + 1] = psi
    vel = speed * np.stack([np.sin(heading), np.cos(heading)], axis=-1)
    return xy, vel


def simulate(
    scenario: Scenario,
    tile: DemTile,
    *,
    n_runs: int,
    seed: int | None = None,
    dtype: torch.dtype = torch.float64,
    device: str | torch.device = "cpu",
    truth_terrain: TrueTerrain | None = None,
    quality: bool = True,
) -> Truth:
    """Simulates N truth trajectories, their INS outputs and radar-altimeter measurements.

    Args:
        scenario: The scenario (validated here).
        tile: The DEM tile the flight is over (the map's tile).
        n_runs: Number of Monte Carlo runs N (≥ 1).
        seed: Random seed; ``None`` uses ``scenario.seed``. Equal seeds, scenarios, tiles
            and ``n_runs`` give identical truth.
        dtype: Floating dtype of the returned tensors.
        device: Device of the returned tensors.
        truth_terrain: The truth terrain (built from the scenario and ``seed`` when None;
            pass it to share one world between several simulations or the PCRB).
        quality: Also compute the altimeter's quality record (``Truth.quality``; False
            leaves it None, the draws unchanged: only quality-aware policies read it).

    Returns:
        `Truth` with ``K = scenario.n_steps``.

    Raises:
        NeuralMapError: ``n_runs < 1``, a bad scenario, or a tile that is not a DemTile.
    """
    scenario.validate()
    if isinstance(n_runs, bool) or not isinstance(n_runs, int) or n_runs < 1:
        raise NeuralMapError(f"simulate: n_runs must be an integer >= 1, got {n_runs!r}.")
    if not isinstance(tile, DemTile):
        raise NeuralMapError(
            f"simulate: tile must be a DemTile, got {type(tile).__name__}. Load it with "
            "neuralmap.lab.scenario.scenario_tile(scenario) or neuralmap.dem.load_tile()."
        )
    seed = scenario.seed if seed is None else int(seed)
    f64 = torch.float64
    n, k_steps, dt = n_runs, scenario.n_steps, scenario.dt
    gen = torch.Generator().manual_seed(seed)

    # truth trajectories: nominal path translated per run, constant climb
    xy_nom, vel_nom = nominal_path(scenario, tile)
    offset = scenario.start_spread_m * torch.randn(n, 1, 2, generator=gen, dtype=f64)
    t = torch.arange(k_steps + 1, dtype=f64) * dt
    xy = torch.from_numpy(xy_nom).unsqueeze(0) + offset
    h0 = float(np.nanmax(tile.heights)) + scenario.altitude_agl_m
    h = (h0 + scenario.climb_rate_mps * t).expand(n, k_steps + 1)
    pos = torch.cat([xy, h.unsqueeze(-1)], dim=-1)
    vel = torch.from_numpy(vel_nom).unsqueeze(0).expand(n, k_steps + 1, 2).clone()

    # INS errors: δX_{k+1} = Φ δX_k + w_k in closed form (cumulative sums over time)
    model = TanModel.from_scenario(scenario)
    mean = torch.tensor(model.truth_mean, dtype=f64)
    sigma0 = torch.tensor(model.truth_P0, dtype=f64).sqrt()
    err0 = mean + sigma0 * torch.randn(n, 5, generator=gen, dtype=f64)
    q_std = torch.tensor(model.truth_Q, dtype=f64).sqrt()
    w = q_std * torch.randn(n, k_steps, 5, generator=gen, dtype=f64)
    ins_error = model.propagate_truth(err0, w)

    # true terrain (DEM + DEM-making error [+ sub-grid detail]) and the radar altimeter
    if truth_terrain is None:
        truth_terrain = true_terrain(scenario, tile, seed=seed)
    terrain = truth_terrain.model
    dem_error = truth_terrain.dem_error
    with torch.no_grad():
        terrain_true = terrain(xy)
    on_map = terrain.contains(xy)
    noise = scenario.altimeter_sigma_m * torch.randn(n, k_steps + 1, generator=gen, dtype=f64)
    outlier = torch.rand(n, k_steps + 1, generator=gen, dtype=f64) < scenario.outlier_prob
    extra = scenario.outlier_sigma_m * torch.randn(n, k_steps + 1, generator=gen, dtype=f64)
    radar = h - terrain_true + noise + torch.where(outlier, extra, torch.zeros_like(extra))
    fault_error, fault = altimeter_faults(scenario, (n, k_steps + 1), generator=gen)
    radar = radar + fault_error
    lock = torch.isfinite(radar)
    ins_pos_f64 = pos + ins_error[..., :3]
    record = None
    if quality:
        roughness = footprint_roughness(
            GridTerrain(tile, method="bilinear", dtype=f64), ins_pos_f64[..., :2],
            torch.where(lock, radar, h - terrain_true), scenario.beam_half_angle_deg)
        record = torch.stack([roughness, torch.where(lock, radar, 0.0), lock.to(f64)], dim=-1)

    def cast(x: torch.Tensor) -> torch.Tensor:
        return x.to(device=device, dtype=dtype)

    return Truth(
        t=cast(t), pos=cast(pos), vel=cast(vel), ins_pos=cast(pos + ins_error[..., :3]),
        ins_vel=cast(vel + ins_error[..., 3:]), radar=cast(radar),
        terrain_true=cast(terrain_true), outlier=outlier.to(device),
        on_map=on_map.to(device), ins_error=cast(ins_error),
        extent=tuple(float(e) for e in tile.extent),  # type: ignore[arg-type]
        tile_name=tile.name, tile_fingerprint=tile.fingerprint(), scenario=scenario,
        seed=seed, dem_error=dem_error, terrain=truth_terrain, fault=fault.to(device),
        quality=None if record is None else cast(record),
    )
