"""Loosely coupled GNSS/INS EKF: statistical consistency (NEES/NIS) and bad input."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from scipy.stats import chi2

from neuralmap.exceptions import NeuralMapError
from neuralmap.ins.gnss import UrbanEffects, simulate_gnss
from neuralmap.ins.imu_model import ImuErrorProcess
from neuralmap.ins.loosely_coupled import LooselyCoupledConfig, run_loosely_coupled
from neuralmap.ins.trajectory import short_drive

ARM = [0.5, 0.2, -1.2]
N_RUNS = 40


def _run(config: LooselyCoupledConfig, *, seed: int = 0, effects: UrbanEffects | None = None,
         duration: float = 40.0, n_runs: int = N_RUNS, gnss_hook=None, traj_hook=None):
    gen = torch.Generator().manual_seed(seed)
    traj = short_drive(duration=duration, dt=0.05)
    imu = ImuErrorProcess("tactical_mems", n_runs=n_runs, dt=traj.dt, generator=gen,
                          scale_factor=False)
    rec = simulate_gnss(traj, n_runs=n_runs, lever_arm=ARM, generator=gen, effects=effects)
    if gnss_hook is not None:
        rec = gnss_hook(rec)
    if traj_hook is not None:
        traj = traj_hook(traj)
    return run_loosely_coupled(traj, imu, rec, config, generator=gen)


@pytest.fixture(scope="module")
def consistent():
    return _run(LooselyCoupledConfig(propagate_every=4))


def test_filter_is_consistent(consistent) -> None:
    """Matched models: run-averaged NEES in its χ² band, errors inside 3σ.

    With N runs the run-averaged position NEES at one epoch is χ²(3N)/N; the 99 % band
    for N = 40 is [2.20, 3.95]. Measured: mean position NEES 2.88, 9-state NEES 8.91,
    NIS 6.08 (m = 6); 99.7 % of the position errors inside 3σ; max error 0.10 m.
    """
    res = consistent
    assert res.healthy.all() and res.applied[:, 1:].all()
    nees = res.nees_position[:, 5:]  # skip the first seconds (initial transient)
    lo, hi = chi2.ppf([0.005, 0.995], 3 * N_RUNS) / N_RUNS
    per_epoch = nees.mean(0)
    assert ((per_epoch > lo) & (per_epoch < hi)).float().mean() > 0.9
    assert 2.6 < nees.mean().item() < 3.4
    assert 8.0 < res.nees_navigation[:, 5:].mean().item() < 10.0
    assert 5.4 < res.nis[:, 5:].nanmean().item() < 6.6
    ratio = res.position_error.abs() / res.std[..., :3]
    assert (ratio[:, 5:] < 3.0).float().mean() > 0.99
    # and the solution is good: centimetre position, sub-0.1° attitude
    assert res.position_error[:, 5:].abs().max() < 0.3


def test_overconfident_filter_fails_the_check() -> None:
    """Reported σ scaled by 0.3 (R 11× too small): the same checks reject it (measured
    position NEES 34, NIS 64)."""
    res = _run(LooselyCoupledConfig(propagate_every=4, r_scale=0.3), n_runs=20,
               duration=20.0)
    assert res.nees_position[:, 5:].mean().item() > 5.0
    assert res.nis[:, 5:].nanmean().item() > 20.0


def test_outage_is_skipped_and_counted_and_errors_grow_inside_sigma() -> None:
    effects = UrbanEffects(outages=((20.0, 30.0),))
    res = _run(LooselyCoupledConfig(propagate_every=4), effects=effects, n_runs=20)
    assert res.counts["skipped_epochs"] == 10
    inside = (res.time >= 20) & (res.time < 30)
    assert not res.applied[:, inside].any()
    std = res.std[..., :2].norm(dim=-1)
    assert (std[:, inside][:, -1] > 3 * std[:, inside.nonzero()[0, 0] - 1]).all()
    assert (res.position_error[:, inside].abs() < 3.5 * res.std[:, inside, :3]).float().mean() > 0.98


def test_bad_input() -> None:
    with pytest.raises(NeuralMapError, match="lever_arm"):
        LooselyCoupledConfig(lever_arm=(1.0, 2.0)).validate()
    with pytest.raises(NeuralMapError, match="propagate_every"):
        LooselyCoupledConfig(propagate_every=0).validate()
    with pytest.raises(NeuralMapError, match="init_att_sigma_deg"):
        LooselyCoupledConfig(init_att_sigma_deg=(0.1, 0.0, 0.5)).validate()

    def shuffle(rec):
        q = rec.quality
        time = q.time.clone()
        time[[3, 4]] = time[[4, 3]]
        return dataclasses.replace(rec, quality=dataclasses.replace(q, time=time))

    with pytest.raises(NeuralMapError, match="out of order"):
        _run(LooselyCoupledConfig(), gnss_hook=shuffle, n_runs=2, duration=10.0)

    def jump(traj):
        states = traj.states.clone()
        states[100:, 1] += 1e-5  # a 55 m east jump at sample 100
        return dataclasses.replace(traj, states=states)

    with pytest.raises(NeuralMapError, match="jumps between samples 99 and 100"):
        _run(LooselyCoupledConfig(), traj_hook=jump, n_runs=2, duration=10.0)


def test_nan_quality_and_measurements_are_counted() -> None:
    def spoil(rec):
        q = rec.quality
        sig = q.sigma_pos.clone()
        sig[4] = float("nan")
        fix = q.fix_ratio.clone()
        fix[6] = float("nan")
        pos = rec.position.clone()
        pos[1, 8] = float("nan")
        return dataclasses.replace(rec, position=pos, quality=dataclasses.replace(
            q, sigma_pos=sig, fix_ratio=fix))

    res = _run(LooselyCoupledConfig(), gnss_hook=spoil, n_runs=3, duration=10.0)
    assert res.counts["invalid_sigma"] == 1 and res.counts["skipped_epochs"] == 1
    assert res.counts["nan_fix_ratio"] == 1 and res.counts["nan_measurements"] == 1
    assert not res.applied[:, 4].any() and not res.applied[1, 8] and res.applied[0, 8]
    assert res.healthy.all() and torch.isfinite(res.position_error).all()


def test_quality_policy_receives_the_epoch_indicators() -> None:
    """A quality-based R policy sees this epoch's PDOP, fix ratio, satellites and σ."""
    from neuralmap.filters.policies import Compose, InnovationInflation, QualityR

    seen: list[dict] = []

    class Recording(QualityR):
        def set_quality(self, values):  # noqa: ANN001, ANN202
            seen.append({k: v.clone() for k, v in values.items()})
            super().set_quality(values)

    policy = Compose(Recording.gnss(), InnovationInflation(1.2))
    gen = torch.Generator().manual_seed(0)
    traj = short_drive(duration=10.0, dt=0.05)
    imu = ImuErrorProcess("tactical_mems", n_runs=3, dt=traj.dt, generator=gen)
    effects = UrbanEffects(degraded=((4.0, 7.0),))
    rec = simulate_gnss(traj, n_runs=3, lever_arm=ARM, generator=gen, effects=effects)
    res = run_loosely_coupled(traj, imu, rec, LooselyCoupledConfig(), generator=gen,
                              policy=policy)
    q = rec.quality
    assert len(seen) == q.n_epochs
    for j, values in enumerate(seen):
        assert values["pdop"].shape == (3,) and values["pdop"][0] == q.pdop[j]
        assert values["satellites"][0] == q.n_sats[j]
        assert values["fix_ratio"][0] == q.fix_ratio[j]
        assert values["sigma_m"][0] == pytest.approx(
            float(q.sigma_pos[j, :2].square().mean().sqrt()))
    assert res.healthy.all()


def test_run_driven_off_the_globe_is_frozen_and_counted() -> None:
    """An absurd GNSS fix (a latitude 60° off, huge R-blind correction) must not stop the
    batch: the run is frozen, reported unhealthy and counted; the others are untouched."""

    def absurd(rec):
        pos = rec.position.clone()
        pos[1, 5:, 0] += 1.05  # rad
        return dataclasses.replace(rec, position=pos)

    res = _run(LooselyCoupledConfig(), gnss_hook=absurd, n_runs=3, duration=10.0)
    assert res.counts["failed_runs"] == 1
    assert res.healthy.tolist() == [True, False, True]
    assert torch.isfinite(res.position_error).all()
    assert res.position_error[[0, 2]].abs().max() < 0.5
