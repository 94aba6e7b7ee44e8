"""GNSS simulation: error statistics vs the quality record, urban effects, bad records."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.ins.earth import position_offset_ned
from neuralmap.ins.gnss import UrbanEffects, check_epochs, sanitize_quality, simulate_gnss
from neuralmap.ins.measurement import antenna_position
from neuralmap.ins.trajectory import short_drive

ARM = [0.5, 0.2, -1.2]


@pytest.fixture(scope="module")
def record():
    traj = short_drive(duration=60.0, dt=0.1)
    effects = UrbanEffects(outages=((10.0, 15.0),), degraded=((20.0, 40.0),),
                           multipath=((30.0, 35.0, 6.0),))
    gen = torch.Generator().manual_seed(0)
    return traj, simulate_gnss(traj, n_runs=2000, lever_arm=ARM, generator=gen,
                               effects=effects)


def test_errors_match_reported_sigma(record) -> None:
    traj, rec = record
    q = rec.quality
    assert q.n_epochs == 61 and torch.equal(q.time, torch.arange(61, dtype=torch.float64))
    true_ant = antenna_position(traj.states[q.imu_index], rec.lever_arm)
    err = position_offset_ned(rec.position[..., 0], rec.position[..., 1], rec.position[..., 2],
                              true_ant[:, 0], true_ant[:, 1], true_ant[:, 2])
    good = q.valid & ~q.degraded
    ratio = err[:, good].std(0) / q.sigma_pos[good]
    assert ratio.mean().item() == pytest.approx(1.0, abs=0.02)
    clean_degraded = q.degraded & ~q.multipath
    ratio = err[:, clean_degraded].std(0) / q.sigma_pos[clean_degraded]
    assert ratio.mean().item() == pytest.approx(2.5, rel=0.03)  # receiver σ optimistic
    assert (q.pdop[q.degraded] > 3.5).all() and (q.pdop[good] < 2.0).all()
    assert not q.fixed[q.degraded].any() and q.fixed[good].all()
    assert (q.fix_ratio[q.degraded] < 0.71).all() and (q.n_sats[q.degraded] <= 10).all()


def test_urban_effects(record) -> None:
    traj, rec = record
    q = rec.quality
    out = (q.time >= 10) & (q.time < 15)
    assert not q.valid[out].any() and torch.isnan(rec.position[:, out]).all()
    mp = q.multipath
    assert int(mp.sum()) == 5
    jump = rec.position_error[:, mp, :2].mean(1).norm(dim=-1)  # horizontal jump per run
    # magnitudes uniform in [0.7, 1.3] x 6 m, plus the degraded noise averaged over 5 epochs
    assert jump.mean().item() == pytest.approx(6.0, abs=0.15)
    assert jump.min() > 2.0


def test_antenna_offset_is_lever_arm(record) -> None:
    traj, rec = record
    ant = antenna_position(traj.states, rec.lever_arm)
    s = traj.states
    off = position_offset_ned(ant[:, 0], ant[:, 1], ant[:, 2], s[:, 0], s[:, 1], s[:, 2])
    assert torch.allclose(off.norm(dim=-1), torch.tensor(ARM).norm().double(), atol=1e-6)


def test_bad_records(record) -> None:
    traj, rec = record
    q = rec.quality
    time = q.time.clone()
    time[[20, 21]] = time[[21, 20]]
    with pytest.raises(NeuralMapError, match="out of order: epoch 21"):
        check_epochs(time)
    with pytest.raises(NeuralMapError, match="out of order"):
        sanitize_quality(dataclasses.replace(q, time=torch.cat([q.time[:5], q.time[4:-1]])))
    pdop, sig = q.pdop.clone(), q.sigma_pos.clone()
    pdop[[3, 7]] = float("nan")
    sig[5, 1] = float("nan")
    fixed, counts = sanitize_quality(dataclasses.replace(q, pdop=pdop, sigma_pos=sig))
    assert counts["nan_pdop"] == 2 and counts["invalid_sigma"] == 1
    assert fixed.pdop[3].item() == 99.0 and not fixed.valid[5]
    assert torch.isfinite(fixed.sigma_pos).all()
    with pytest.raises(NeuralMapError, match="lever_arm"):
        simulate_gnss(traj, n_runs=2, lever_arm=[1.0, 2.0], generator=torch.Generator())
    with pytest.raises(NeuralMapError, match="multiple of the IMU"):
        simulate_gnss(traj, n_runs=2, lever_arm=ARM, generator=torch.Generator(),
                      interval=0.25)
