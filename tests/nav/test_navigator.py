"""The Navigator API: the lab's `fly` is the Navigator (bit for bit), streaming = replay,
the EKF equal to FilterPy's Kalman filter (estimate, innovation, NIS) and the tracker to
1e-3 σ of it on a tilted plane, config (one section per registered method) and noise from
what a user has."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.monte_carlo import fly, study_navigator_config
from neuralmap.lab.scenario import load_scenario, scenario_tile
from neuralmap.lab.simulator import simulate
from neuralmap.nav.config import NavigatorConfig, load_navigator_config
from neuralmap.nav.fix import FIX_FIELDS, STATUS_CODE
from neuralmap.nav.map_noise import measurement_noise
from neuralmap.nav.navigator import Navigator
from neuralmap.tan.model import TanModel
from neuralmap.terrain.base import TerrainModel
from neuralmap.terrain.grid import GridTerrain

TINY = {"sensor": {"dt_s": 1.0, "altimeter_sigma_m": 3.0},
        "initial": {"position_sigma_m": 20.0, "altitude_sigma_m": 10.0, "velocity_sigma_mps": 0.2},
        "process_noise": {"position_sigma_m": 1.0, "altitude_sigma_m": 1.0,
                          "velocity_sigma_mps": 0.05}}


@pytest.fixture(scope="module")
def tiny_flight():
    scenario = load_scenario("tiny")
    tile = scenario_tile(scenario)
    truth = simulate(scenario, tile, n_runs=4, seed=0)
    return scenario, tile, truth, GridTerrain(tile, method="bilinear")


def _replay(nav: Navigator, truth, radar=None, t=None):
    return nav.replay(truth.t if t is None else t, truth.ins_pos[..., :2], truth.ins_pos[..., 2],
                      truth.radar if radar is None else radar)


def test_fly_is_the_navigator_bit_for_bit(tiny_flight) -> None:
    # the lab is the product: a study flight (`fly`, the study's noise configuration: R =
    # the scenario's altimeter variance + the map error given as an override) equals
    # Navigator.replay with the same config and model, fix for fix
    scenario, _, truth, grid = tiny_flight
    map_var = 0.5
    model = TanModel.from_scenario(scenario)
    cfg = study_navigator_config(
        scenario, {"method": "point_mass_tracker", "point_mass_tracker": {"dtype": "float64"}},
        overrides={"integrity": {"lost_window": 10, "lost_prob": 0.9999}})
    run = fly(truth, grid, cfg, model=model, map_error_variance=map_var, name="tracker")
    nav = Navigator(grid, cfg, n_vehicles=4, model=model, map_error_variance=map_var)
    assert nav.R == scenario.R_m2 + map_var
    torch.testing.assert_close(nav.model.filter_prior(),
                               torch.diag(torch.tensor(scenario.P0_diag, dtype=torch.float64)))
    torch.testing.assert_close(nav.model.process_noise(),
                               torch.diag(torch.tensor(scenario.Q_diag, dtype=torch.float64)))
    track = _replay(nav, truth)
    assert torch.equal(run.err, truth.ins_error - track.correction)
    assert torch.equal(run.P, track.cov)
    assert torch.equal(run.nis.nan_to_num(-1.0), track.nis.nan_to_num(-1.0))
    assert torch.equal(run.residual, torch.where(track.updated, track.innovation, 0.0))
    assert torch.equal(run.updated, track.updated) and torch.equal(run.status, track.status)
    assert run.counts == track.counts and run.counts["updates"] == int(run.updated.sum())
    assert run.counts["updates"] == 4 * truth.n_steps  # every epoch after the prior
    # the fix is the INS corrected by δX̂
    assert torch.equal(track.xy, truth.ins_pos[..., :2] - track.correction[..., :2])
    assert torch.equal(track.altitude, truth.ins_pos[..., 2] - track.correction[..., 2])


@pytest.mark.parametrize("method", ["point_mass_tracker", "point_mass_ekf", "bilinear"])
def test_streaming_equals_replay_bit_for_bit(tiny_flight, method) -> None:
    _, _, truth, grid = tiny_flight
    radar = truth.radar.clone()
    radar[1, 7] = math.nan
    radar[2, 9] = 1e6  # out of the altimeter's range
    t = truth.t.clone()
    t[20:] += 2.0  # a 3 s gap
    cfg = dict(TINY, method=method)
    if method == "bilinear":
        cfg["ekf"] = {"policy": "raf"}
    nav = Navigator(grid, cfg, n_vehicles=4)
    track = _replay(nav, truth, radar=radar, t=t)
    nav.reset()
    for k in range(t.shape[0]):
        fix = nav.step(t[k], truth.ins_pos[:, k, :2], truth.ins_pos[:, k, 2], radar[:, k])
        ref = track.fix(k)
        for name in FIX_FIELDS:
            a, b = getattr(fix, name), getattr(ref, name)
            if a is None or b is None:
                assert a is None and b is None, (k, name)
                continue
            assert torch.equal(a.nan_to_num(-1.0) if a.is_floating_point() else a,
                               b.nan_to_num(-1.0) if b.is_floating_point() else b), (k, name)
    assert track.counts["gaps"] == 4 and track.counts["missing_radar"] == 1
    assert track.counts["out_of_range"] == 1
    assert nav.counts == track.counts


def _kalman_reference(truth, P0, Q, R, slope):
    """FilterPy's linear Kalman filter per vehicle on the tilted plane (float64):
    ``z = y − t(p_ins) = H δX + v``, ``H = [−a, −b, 1, 0, 0]``; the estimate ``(N, K+1, 5)``,
    the innovation and the NIS ``(N, K+1)`` (NaN at the prior)."""
    from filterpy.kalman import KalmanFilter

    a, b, c0 = slope
    F = np.eye(5)
    F[0, 3] = F[1, 4] = 1.0
    out = np.zeros((truth.n_runs, truth.n_steps + 1, 5))
    innovation = np.full((truth.n_runs, truth.n_steps + 1), np.nan)
    nis = np.full((truth.n_runs, truth.n_steps + 1), np.nan)
    for i in range(truth.n_runs):
        kf = KalmanFilter(dim_x=5, dim_z=1)
        kf.x = np.zeros((5, 1))
        kf.P, kf.F, kf.Q = P0.copy(), F, Q.copy()
        kf.H, kf.R = np.array([[-a, -b, 1.0, 0.0, 0.0]]), np.array([[R]])
        ins = truth.ins_pos[i].numpy()
        for k in range(1, truth.n_steps + 1):
            kf.predict()
            terrain = c0 + a * ins[k, 0] + b * ins[k, 1]
            kf.update(np.array([[ins[k, 2] - truth.radar[i, k].item() - terrain]]))
            out[i, k] = kf.x[:, 0]
            innovation[i, k] = kf.y[0, 0]
            nis[i, k] = kf.y[0, 0] ** 2 / kf.S[0, 0]
    return out, innovation, nis


def test_kalman_equality_on_a_tilted_plane(tiny_scenario_plane) -> None:
    # linear-Gaussian case, lost-lock detector off: the EKF method equals FilterPy's Kalman
    # filter to float64 rounding (estimate, innovation, NIS); the point-mass tracker
    # (float64) to 1e-3 σ
    truth, grid, slope = tiny_scenario_plane
    P0 = np.diag([400.0, 400.0, 100.0, 0.04, 0.04])
    Q = np.diag([1.0, 1.0, 1.0, 0.0025, 0.0025])
    ref, ref_innovation, ref_nis = _kalman_reference(truth, P0, Q, 9.0, slope)
    ins_err = truth.ins_pos.numpy()
    for method, tol in (("bilinear", 1e-9), ("point_mass_tracker", 1e-3)):
        cfg = dict(TINY, method=method, integrity={"lost_window": 0, "spike_gate_prob": 0.0},
                   point_mass_tracker={"dtype": "float64"})
        track = _replay(Navigator(grid, cfg, n_vehicles=truth.n_runs), truth)
        est = ins_err[..., :2] - track.xy.numpy()  # δp̂
        sigma = np.sqrt(track.cov[..., 0, 0].numpy())[..., None]
        assert np.abs((est - ref[..., :2]) / sigma).max() < tol, method
        assert bool(track.updated[:, 1:].all()) and not bool(track.updated[:, 0].any())
        if method == "bilinear":
            np.testing.assert_allclose(track.correction.numpy(), ref, rtol=0, atol=1e-9)
            np.testing.assert_allclose(track.innovation.numpy(), ref_innovation, rtol=1e-9,
                                       atol=1e-9)
            np.testing.assert_allclose(track.nis.numpy(), ref_nis, rtol=1e-9, atol=1e-12)


@pytest.fixture(scope="module")
def tiny_scenario_plane():
    scenario = dataclasses.replace(load_scenario("tiny"), truth_model="dem",
                                   start_xy=[900.0, 900.0], start_spread_m=0.0).validate()
    a, b, c0 = 0.15, 0.08, 200.0
    xs = 30.0 * np.arange(96)
    x, y = np.meshgrid(xs, xs)
    tile = DemTile(heights=c0 + a * x + b * y, spacing=(30.0, 30.0), origin=(0.0, 0.0),
                   name="plane")
    truth = simulate(scenario, tile, n_runs=3, seed=1)
    return truth, GridTerrain(tile, method="bilinear"), (a, b, c0)


class _PlaneMap(TerrainModel):
    """An analytic map (not a grid) that carries stored fit metrics like a neural map."""

    def __init__(self) -> None:
        super().__init__()
        self.extent = (0.0, 2850.0, 0.0, 2850.0)
        self.metrics = {"rmse_m": 0.4, "offnode_rmse_m": 0.7}

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        return 200.0 + 0.15 * xy[..., 0] + 0.08 * xy[..., 1]


def test_any_terrain_model_lat_lon_and_noise_from_the_map(tiny_scenario_plane) -> None:
    truth, grid, _ = tiny_scenario_plane

    class Frame:  # duck-typed map frame
        def to_geo(self, x, y):
            return 32.0 + y / 111000.0, -97.0 + x / 94000.0

    neural = _PlaneMap()
    nav = Navigator(neural, TINY, n_vehicles=truth.n_runs, map_frame=Frame())
    assert nav.noise.fit_source == "map metrics: offnode_rmse_m"
    assert nav.R == pytest.approx(9.0 + 0.49)
    track = _replay(nav, truth)
    ref = _replay(Navigator(grid, TINY, n_vehicles=truth.n_runs, map_error_variance=0.49), truth)
    torch.testing.assert_close(track.xy, ref.xy, rtol=0, atol=1e-2)  # same plane (float32 lattice)
    torch.testing.assert_close(track.lat, 32.0 + track.xy[..., 1] / 111000.0)
    torch.testing.assert_close(track.lon, -97.0 + track.xy[..., 0] / 94000.0)
    assert bool((track.status[:, -1] == STATUS_CODE["tracking"]).all())
    assert bool(torch.isnan(track.velocity[:, 0]).all())
    # INS Δp/Δt − δv̂: the INS's white position noise (1 m per step) makes it noisy, unbiased
    dv = track.velocity[:, 1:] - truth.vel[:, 1:]
    assert float(dv.mean((0, 1)).abs().max()) < 0.3 and float(dv.std()) < 2.0


def test_noise_model_parts() -> None:
    cfg = load_navigator_config({"sensor": {"altimeter_sigma_m": 2.0},
                                 "map_error": {"dem_accuracy_m": 1.5}})
    grid_like = type("G", (), {"heights": 0, "method": "bilinear"})()
    noise = measurement_noise(cfg, grid_like)
    assert (noise.altimeter_m2, noise.dem_m2, noise.fit_m2) == (4.0, 2.25, 0.0)
    assert noise.fit_source == "grid map"
    latent_like = type("L", (), {"metrics": {"rmse_m": 0.3, "between_rmse_m": 0.5}})()
    assert measurement_noise(cfg, latent_like).fit_m2 == pytest.approx(0.25)
    cfg.map_error.fit_rmse_m = 2.0
    assert measurement_noise(cfg, latent_like).R == pytest.approx(4.0 + 2.25 + 4.0)
    assert measurement_noise(cfg, latent_like, map_error_variance=1.0).R == 5.0
    with pytest.raises(NeuralMapError, match="map_error_variance"):
        measurement_noise(cfg, None, map_error_variance=-1.0)


def test_config_defaults_and_refusals(tmp_path) -> None:
    cfg = load_navigator_config()
    assert isinstance(cfg, NavigatorConfig) and cfg.method == "point_mass_tracker"
    assert cfg.source.endswith("navigator.yaml")
    assert (cfg.integrity.lost_window, cfg.integrity.lost_prob) == (20, 0.99999)
    bad = tmp_path / "nav.yaml"
    bad.write_text("sensor:\n  altimeter_sigma: 3\n")
    with pytest.raises(NeuralMapError, match=r"nav.yaml.*sensor.altimeter_sigma"):
        load_navigator_config(bad)
    bad.write_text("method: kalman\n")
    with pytest.raises(NeuralMapError, match=r"nav.yaml.*unknown navigation method 'kalman'"):
        load_navigator_config(bad)
    with pytest.raises(NeuralMapError, match="max_gap_s"):
        load_navigator_config({"sensor": {"dt_s": 2.0, "max_gap_s": 1.0}})


def test_config_has_one_section_per_registered_method() -> None:
    from neuralmap.tan.registry import method_class, method_names

    cfg = load_navigator_config()
    assert set(cfg.methods) == set(method_names())
    for name in method_names():
        assert isinstance(cfg.methods[name], method_class(name).Options), name
    assert cfg.methods["point_mass_tracker"].cells == 32
    # an EKF linearisation name is the ekf method with that linearisation
    cfg = load_navigator_config({"method": "bilinear", "ekf": {"policy": "raf"}})
    name, options = cfg.method_options()
    assert (name, options.linearizer, options.policy) == ("ekf", "bilinear", "raf")
    assert cfg.methods["ekf"].linearizer == "neural"  # the section itself is unchanged
    # the old top-level keys are gone; a method's options are checked in its section
    for data, match in (({"policy": "raf"}, "unknown navigator option 'policy'"),
                        ({"tracker": {"cells": 16}}, "unknown navigator option 'tracker'"),
                        ({"acquisition": {"cells": 48}}, "unknown option acquisition.cells"),
                        ({"ekf": {"polcy": "raf"}}, "unknown option ekf.polcy"),
                        ({"ekf": {"policy": "raff"}}, "ekf.policy must be one of"),
                        ({"point_mass_tracker": {"dtype": "float16"}},
                         "point_mass_tracker.dtype"),
                        ({"acquisition": {"handoff_affinity": 0.0}}, "handoff_affinity")):
        with pytest.raises(NeuralMapError, match=match):
            load_navigator_config(data)
    plain = load_navigator_config({"point_mass": {"cells": 40}}).to_dict()
    again = load_navigator_config(plain)
    assert again.to_dict() == plain and again.methods["point_mass"].cells == 40


def test_a_policy_that_reads_the_quality_record_needs_it(tiny_flight) -> None:
    _, _, truth, grid = tiny_flight
    nav = Navigator(grid, dict(TINY, method="bilinear", ekf={"policy": "quality"}),
                    n_vehicles=4)
    p, h, r = truth.ins_pos[:, :2, :2], truth.ins_pos[:, :2, 2], truth.radar[:, :2]
    nav.step(0.0, p[:, 0], h[:, 0], r[:, 0])  # the prior: no update
    with pytest.raises(NeuralMapError, match="quality record"):
        nav.step(1.0, p[:, 1], h[:, 1], r[:, 1])
    nav.reset()
    nav.step(0.0, p[:, 0], h[:, 0], r[:, 0], quality=truth.quality[:, 0])
    fix = nav.step(1.0, p[:, 1], h[:, 1], r[:, 1], quality=truth.quality[:, 1])
    assert bool(fix.updated.all())


def test_step_refusals(tiny_flight) -> None:
    _, _, truth, grid = tiny_flight
    nav = Navigator(grid, TINY, n_vehicles=4)
    p, h, r = truth.ins_pos[:, 0, :2], truth.ins_pos[:, 0, 2], truth.radar[:, 0]
    with pytest.raises(NeuralMapError, match=r"\(4, 2\)"):
        nav.step(0.0, p[:2], h, r)
    nav.step(0.0, p, h, r)
    with pytest.raises(NeuralMapError, match="time must increase"):
        nav.step(0.0, p, h, r)
    with pytest.raises(NeuralMapError, match="finite"):
        nav.step(1.0, p * math.nan, h, r)


def test_linearisation_table_for_ekf_methods(tiny_flight, tmp_path) -> None:
    # a measured table with a constant 4 m² miss: the EKF's R is the altimeter variance plus
    # the table's value (replacing the method's own), i.e. the same filter as a 4 m² map
    # error with a zero-variance linearizer
    import json

    _, tile, truth, grid = tiny_flight
    table = {"sigmas_m": [0.0, 100.0], "map_mse_m2": [4.0, 4.0], "map_mean_m": [0.0, 0.0],
             "variance_m2": [4.0, 4.0], "flight_samples": [0.0, 0.0], "n_points": 10,
             "draws": 1, "seed": 0}
    path = tmp_path / "table.json"
    path.write_text(json.dumps(table))
    cfg = dict(TINY, method="bilinear", map_error={"linearisation_table": str(path)})
    with_table = _replay(Navigator(grid, cfg, n_vehicles=4), truth)
    from neuralmap.linearize.factory import make_linearizer

    # the table replaces the method's own variance: the reference has none
    zero = make_linearizer("bilinear", tile=tile, variance="zero")
    ref = Navigator(grid, dict(TINY, method="ekf", ekf={"linearizer": zero}), n_vehicles=4,
                    map_error_variance=4.0)
    plain = _replay(ref, truth)
    torch.testing.assert_close(with_table.xy, plain.xy, rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(with_table.cov, plain.cov, rtol=1e-12, atol=1e-9)
    own = _replay(Navigator(grid, dict(TINY, method="bilinear"), n_vehicles=4,
                            map_error_variance=4.0), truth)
    assert not torch.equal(own.cov, plain.cov)  # the bilinear method's own variance differs
    path.write_text("{\"sigmas_m\": [0.0]}")
    with pytest.raises(NeuralMapError, match="lacks"):
        Navigator(grid, cfg, n_vehicles=4)
