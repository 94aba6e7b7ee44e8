"""The Navigator's ``device`` option: the CPU request is the default bit for bit, a CUDA
request without CUDA is refused by name, and on CUDA (when present) the fixes match the
CPU's within float64 round-off. The tracker's static driver (what CUDA and ``compile: true``
run: one step per epoch, `PointMassTracker.track`) gives the eager driver's fixes."""

from __future__ import annotations

import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.lattice import follow_step
from neuralmap.lab.scenario import load_scenario, scenario_tile
from neuralmap.lab.simulator import simulate
from neuralmap.nav.fix import FixTrack
from neuralmap.nav.navigator import Navigator
from neuralmap.terrain.grid import GridTerrain

TINY = {"sensor": {"dt_s": 1.0, "altimeter_sigma_m": 3.0},
        "initial": {"position_sigma_m": 20.0, "altitude_sigma_m": 10.0, "velocity_sigma_mps": 0.2},
        "process_noise": {"position_sigma_m": 1.0, "altitude_sigma_m": 1.0,
                          "velocity_sigma_mps": 0.05}}
# a wide prior: the acquisition grid first, then the hand-off to the tracker
WIDE = dict(TINY, initial={"position_sigma_m": 150.0, "altitude_sigma_m": 10.0,
                           "velocity_sigma_mps": 0.2}, acquisition={"above_sigma_m": 100.0})
EKF = dict(TINY, method="neural", ekf={"policy": "raf"})
# a biased altimeter (+50 m below) with a short lost-lock window: lost locks, re-acquired on
# the grid from the open-loop prior
REACQUIRE = dict(WIDE, integrity={"lost_window": 3, "lost_prob": 0.5},
                 acquisition={"above_sigma_m": 15.0})
CONFIGS = {"tracker": TINY, "grid_then_tracker": WIDE, "ekf": EKF, "reacquire": REACQUIRE}
RADAR_BIAS_M = {"reacquire": 50.0}
FIELDS = ("xy", "altitude", "velocity", "cov", "status", "nis", "mean_nis", "innovation",
          "correction", "hpl", "vpl", "updated", "healthy")


@pytest.fixture(scope="module")
def tiny_flight():
    scenario = load_scenario("tiny")
    tile = scenario_tile(scenario)
    truth = simulate(scenario, tile, n_runs=3, seed=0)
    k = min(25, truth.t.shape[0])
    radar = truth.radar[:, :k].clone()
    radar[1, 5] = float("nan")  # a missing clearance on one vehicle
    return truth, k, radar, GridTerrain(tile, method="bilinear"), tile


def _replay(nav: Navigator, truth, k: int, radar: torch.Tensor, name: str) -> FixTrack:
    radar = radar + RADAR_BIAS_M.get(name, 0.0)
    return nav.replay(truth.t[:k], truth.ins_pos[:, :k, :2], truth.ins_pos[:, :k, 2], radar)


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_device_cpu_is_the_default_bit_for_bit(tiny_flight, name: str) -> None:
    truth, k, radar, grid, _ = tiny_flight
    cfg = CONFIGS[name]
    default = Navigator(grid, cfg, n_vehicles=3)
    on_cpu = Navigator(grid, cfg, n_vehicles=3, device="cpu")
    by_object = Navigator(grid, cfg, n_vehicles=3, device=torch.device("cpu"))
    assert default.device == on_cpu.device == by_object.device == torch.device("cpu")
    ref = _replay(default, truth, k, radar, name)
    for nav in (on_cpu, by_object):
        got = _replay(nav, truth, k, radar, name)
        for f in FIELDS:  # NaN (no velocity at the prior, no NIS yet) at the same places
            a, b = getattr(got, f), getattr(ref, f)
            if not a.is_floating_point():
                assert torch.equal(a, b), (name, f)
                continue
            assert torch.equal(a.isnan(), b.isnan()), (name, f)
            assert torch.equal(a.nan_to_num(0.0), b.nan_to_num(0.0)), (name, f)
        assert got.counts == ref.counts
    if name == "grid_then_tracker":
        assert ref.counts["handoffs"] > 0  # the grid ran and handed off
    if name == "reacquire":
        assert ref.counts["reacquisitions"] > 0


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_a_cuda_request_without_cuda_names_the_option(tiny_flight) -> None:
    grid = tiny_flight[3]
    with pytest.raises(NeuralMapError, match=r"device='cuda'.*CUDA is not available"):
        Navigator(grid, TINY, device="cuda")


def test_an_unknown_device_is_refused_by_name(tiny_flight) -> None:
    grid = tiny_flight[3]
    with pytest.raises(NeuralMapError, match=r"device='gpu0' is not a torch device"):
        Navigator(grid, TINY, device="gpu0")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_a_map_elsewhere_than_the_device_is_refused(tiny_flight) -> None:
    grid = tiny_flight[3]  # on the CPU
    with pytest.raises(NeuralMapError, match=r"device='cuda'.*move the map first"):
        Navigator(grid, TINY, device="cuda")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_cuda_matches_the_cpu(tiny_flight, name: str) -> None:
    truth, k, radar, grid, tile = tiny_flight
    cfg = CONFIGS[name]
    ref = _replay(Navigator(grid, cfg, n_vehicles=3), truth, k, radar, name)
    grid_gpu = GridTerrain(tile, method="bilinear").to("cuda")
    nav = Navigator(grid_gpu, cfg, n_vehicles=3)  # the map's device
    assert nav.device.type == "cuda"
    got = _replay(nav, truth, k, radar, name)  # CPU inputs are moved
    assert got.xy.device.type == "cpu"  # replay returns on the CPU
    assert torch.equal(got.status, ref.status), name
    assert got.counts == ref.counts
    # float64 on both; reductions in another order: round-off, amplified over 25 epochs
    for f in ("xy", "altitude", "cov", "nis", "mean_nis"):
        torch.testing.assert_close(getattr(got, f), getattr(ref, f), rtol=1e-6, atol=1e-6,
                                   equal_nan=True, msg=f"{name}: {f}")
    fix = nav.step(truth.t[k], truth.ins_pos[:, k, :2].cuda(), truth.ins_pos[:, k, 2].cuda(),
                   truth.radar[:, k].cuda())
    assert fix.xy.device.type == "cuda"  # step stays on the device


@pytest.mark.parametrize("name", ["tracker", "grid_then_tracker", "reacquire"])
def test_one_step_per_epoch_gives_the_eager_drivers_fixes(tiny_flight, name: str,
                                                          monkeypatch: pytest.MonkeyPatch,
                                                          ) -> None:
    """The tracker on its static driver (uncompiled here: the compiled form is tested
    against it in tests/filters/test_lattice_step.py) runs each epoch as one step — the
    prediction, the map at the cells, the spike gate, the update, the moments and the mass
    profile its protection level reads — and flies the eager driver's flight: fixes,
    protection levels and status equal to float64 round-off (1e-9 relative), the same
    counts, through a hand-off and a re-acquisition."""
    truth, k, radar, grid, _ = tiny_flight
    steps = []
    whole_epoch = follow_step.track_step
    monkeypatch.setattr(follow_step, "track_step",
                        lambda *args: steps.append(1) or whole_epoch(*args))
    cfg = dict(CONFIGS[name], point_mass_tracker={"dtype": "float64"})
    ref = _replay(Navigator(grid, cfg, n_vehicles=3), truth, k, radar, name)
    assert not steps  # the eager driver: a prediction, then an update
    nav = Navigator(grid, cfg, n_vehicles=3)
    nav._track.tracker.rule.static = True  # the driver CUDA and compile: true run
    got = nav.replay(truth.t[:k], truth.ins_pos[:, :k, :2], truth.ins_pos[:, :k, 2],
                     radar + RADAR_BIAS_M.get(name, 0.0), reset=False)
    assert len(steps) >= k // 2  # one step per tracking epoch
    for f in FIELDS:
        a, b = getattr(got, f), getattr(ref, f)
        if not a.is_floating_point():
            assert torch.equal(a, b), (name, f)
            continue
        assert torch.equal(a.isnan(), b.isnan()), (name, f)
        torch.testing.assert_close(a.nan_to_num(0.0), b.nan_to_num(0.0), rtol=1e-9,
                                   atol=1e-9, msg=f"{name}: {f}")
    assert got.counts == ref.counts


def test_a_map_the_compiler_cannot_trace_falls_back_to_two_steps(
        tiny_flight, monkeypatch: pytest.MonkeyPatch) -> None:
    """``compile: true`` with a whole-epoch step that fails to compile (as for a map
    ``torch.compile`` cannot trace): one warning, then the prediction and the update as
    separate steps (compiled; here their uncompiled functions stand in), with the eager
    driver's fixes."""

    def compiled(name: str, fn):  # noqa: ANN001, ANN202 - the step functions, uncompiled
        if name == "track":
            def fails(*args):  # noqa: ANN002, ANN202
                raise RuntimeError("cannot trace this map")
            return fails
        return fn

    truth, k, radar, grid, _ = tiny_flight
    cfg = dict(TINY, point_mass_tracker={"dtype": "float64"})
    ref = _replay(Navigator(grid, cfg, n_vehicles=3), truth, k, radar, "tracker")
    monkeypatch.setattr(follow_step, "compiled", compiled)
    nav = Navigator(grid, dict(TINY, point_mass_tracker={"dtype": "float64", "compile": True}),
                    n_vehicles=3)
    with pytest.warns(RuntimeWarning, match="whole tracking epoch failed"):
        got = _replay(nav, truth, k, radar, "tracker")
    for f in ("xy", "cov", "hpl", "nis"):
        a, b = getattr(got, f), getattr(ref, f)
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9, equal_nan=True, msg=f)
    assert torch.equal(got.status, ref.status)
