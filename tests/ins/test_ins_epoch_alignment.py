"""GNSS updates at the GNSS time (the IMU interval split there) and IMU logging gaps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.ins.epoch_alignment import split_at_epochs
from neuralmap.ins.gnss import simulate_gnss
from neuralmap.ins.imu_model import imu_grade
from neuralmap.ins.kfgins import GnssLog, ImuLog, read_imu, simulated_logs, write_imu
from neuralmap.ins.log_run import compare_with_reference, run_on_log
from neuralmap.ins.loosely_coupled import LooselyCoupledConfig
from neuralmap.ins.measurement import antenna_position
from neuralmap.ins.trajectory import short_drive

ARM = (0.5, 0.2, -1.2)


def test_split_shares_the_increment_by_time() -> None:
    time = np.array([0.0, 0.1, 0.2, 0.3])
    dtheta = np.arange(12.0).reshape(4, 3) + 1.0
    dvel = -dtheta
    # 0.13 splits (0.1, 0.2] at 30 %; 0.3 + 1e-9 is on the last record; -1 is outside
    line = split_at_epochs(time, dtheta, dvel, np.array([-1.0, 0.13, 0.3 + 1e-9]))
    np.testing.assert_allclose(line.time, [0.0, 0.1, 0.13, 0.2, 0.3], rtol=0, atol=1e-15)
    assert line.real.tolist() == [True, True, False, True, True] and line.n_split == 1
    np.testing.assert_allclose(line.dtheta[2], 0.3 * dtheta[2], rtol=1e-12)
    np.testing.assert_allclose(line.dtheta[3], 0.7 * dtheta[2], rtol=1e-12)
    np.testing.assert_allclose(line.dtheta[2] + line.dtheta[3], dtheta[2], rtol=1e-15)
    np.testing.assert_allclose(line.dvel[2] + line.dvel[3], dvel[2], rtol=1e-15)
    # untouched intervals keep their increments exactly; the rates stay the same
    np.testing.assert_array_equal(line.dtheta[[0, 1, 4]], dtheta[[0, 1, 3]])
    assert line.epoch_index.tolist() == [1, 2] and line.epoch_record.tolist() == [2, 4]
    with pytest.raises(NeuralMapError, match="two GNSS epochs fall on the IMU record"):
        split_at_epochs(time, dtheta, dvel, np.array([0.1, 0.1 + 1e-7]))


def _filter(imu: ImuLog, gnss: GnssLog, ref, **kwargs) -> dict:  # noqa: ANN001
    lat, lon, h = ref.position[0]
    sol = run_on_log(imu, gnss, grade=imu_grade("tactical_mems"),
                     initial_position=(np.radians(lat), np.radians(lon), h),
                     initial_velocity=tuple(ref.velocity[0]),
                     initial_euler=tuple(np.radians(ref.euler[0])), lever_arm=ARM,
                     filter_config=LooselyCoupledConfig(), **kwargs)
    return {"counts": sol.counts, **compare_with_reference(sol, ref)["run_0"]}


def test_gnss_update_at_the_gnss_time_against_the_exact_trajectory() -> None:
    """The analytic drive (accelerating, turning, up to 12 m/s) with exact 20 Hz increments and
    exact antenna positions (σ 1 cm) at epochs 20 ms after an IMU record. Updating at the GNSS
    time keeps run 0 within 1 cm of the truth; the same fixes applied at the nearest record
    (the former rule) are 20 ms stale and cost decimetres (speed × 20 ms = 0.24 m at 12 m/s)."""
    coarse, fine = short_drive(duration=20.0, dt=0.05), short_drive(duration=20.0, dt=0.01)
    assert float((coarse.states - fine.states[::5]).abs().max()) < 1e-12  # one trajectory
    gnss = simulate_gnss(coarse, n_runs=1, lever_arm=ARM, generator=torch.Generator())
    imu, _, ref = simulated_logs(coarse, gnss)
    at = torch.arange(102, fine.n_samples - 5, 100)  # 1.02 s, 2.02 s, ...
    exact = antenna_position(fine.states[at], torch.tensor(ARM, dtype=torch.float64))
    position = torch.cat([torch.rad2deg(exact[:, :2]), exact[:, 2:]], dim=1).numpy()
    sigma = np.full((at.numel(), 3), 0.01)
    t_gnss = fine.time[at].numpy()
    timed = _filter(imu, GnssLog(time=t_gnss, position=position, sigma_pos=sigma), ref)
    assert timed["counts"]["updates"] == at.numel()
    assert timed["counts"]["gnss_between_records"] == at.numel()
    nearest = _filter(imu, GnssLog(time=np.round(t_gnss / 0.05) * 0.05, position=position,
                                   sigma_pos=sigma), ref)
    assert nearest["counts"]["gnss_between_records"] == 0
    assert timed["max_horizontal_m"] < 0.01
    assert nearest["max_horizontal_m"] > 0.1 > 10 * timed["max_horizontal_m"]


def _gap_log(tmp_path: Path, gap_records: int) -> tuple[Path, ImuLog]:
    """A 100 Hz record at rest with ``gap_records`` records missing after 0.5 s."""
    n = 200
    t = np.arange(1, n + 1) * 0.01
    keep = np.ones(n, bool)
    keep[50:50 + gap_records] = False
    dvel = np.tile([0.0, 0.0, -9.80 * 0.01], (n, 1))
    log = ImuLog(time=t[keep], dtheta=np.zeros((keep.sum(), 3)), dvel=dvel[keep], dt=0.01)
    return write_imu(tmp_path / "imu.txt", log), log


def test_imu_gap_refused_or_propagated_up_to_max_gap(tmp_path: Path) -> None:
    path, log = _gap_log(tmp_path, 52)  # 0.53 s between two records
    with pytest.raises(NeuralMapError, match=r"gap of 0\.53 s .*--max_gap"):
        read_imu(path, rate_hz=100.0)
    with pytest.raises(NeuralMapError, match=r"longer than --max_gap 0\.5 s: raise --max_gap "
                                             r"to at least 0\.53"):
        read_imu(path, rate_hz=100.0, max_gap=0.5)
    with pytest.raises(NeuralMapError, match="--max_gap -1 must be a number of seconds > 0"):
        read_imu(path, rate_hz=100.0, max_gap=-1)
    back = read_imu(path, rate_hz=100.0, max_gap=0.6)
    np.testing.assert_array_equal(back.time, log.time)


def test_filter_propagates_across_a_gap_with_its_true_interval(tmp_path: Path) -> None:
    """At rest with the records of a 0.53 s gap missing, the record after it carrying the
    specific force of the whole gap: the filter integrates the true interval, counts the
    gap, and gives the solution of the log without the gap at the records after it."""
    _, whole = _gap_log(tmp_path, 0)
    _, gapped = _gap_log(tmp_path, 52)
    # the record after the gap carries the specific force over the whole gap
    after = int(np.searchsorted(gapped.time, 1.03 - 1e-9))
    dvel = gapped.dvel.copy()
    dvel[after] *= 53.0
    gapped = ImuLog(time=gapped.time, dtheta=gapped.dtheta, dvel=dvel, dt=0.01)
    ref_pos = (np.radians(30.0), np.radians(114.0), 20.0)
    gnss = GnssLog(time=np.array([0.3, 1.5]), position=np.array([[30.0, 114.0, 20.0]] * 2),
                   sigma_pos=np.full((2, 3), 0.05))
    outs = []
    for log in (whole, gapped):
        sol = run_on_log(log, gnss, grade=imu_grade("tactical_mems"), initial_position=ref_pos,
                         initial_velocity=(0.0, 0.0, 0.0), initial_euler=(0.0, 0.0, 0.0),
                         lever_arm=(0.0, 0.0, 0.0), filter_config=LooselyCoupledConfig())
        outs.append(sol)
    assert outs[0].counts["imu_gaps"] == 0
    assert outs[1].counts["imu_gaps"] == 1
    assert outs[1].counts["imu_longest_gap_s"] == pytest.approx(0.53, abs=1e-9)
    # the same nav solution at the common records after the gap, to the discretisation of
    # one 0.53 s step against 53 steps (Earth rate and Coriolis: ~2e-6 m/s of a 1e-3 m/s
    # east drift)
    common = np.isin(outs[0].time.numpy(), outs[1].time.numpy())
    a, b = outs[0].states[0, common], outs[1].states[0]
    assert float((a[:, 3:6] - b[:, 3:6]).abs().max()) < 1e-5  # m/s
    assert float((a[:, :2] - b[:, :2]).abs().max()) * 6.4e6 < 1e-4  # m
    assert float((a[:, 2] - b[:, 2]).abs().max()) < 1e-4  # m


def test_cli_refuses_a_gap_beyond_max_gap_and_counts_the_accepted_one(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import yaml

    from neuralmap.ins.gins_cli import main
    from neuralmap.ins.kfgins import write_gnss

    path, _ = _gap_log(tmp_path, 52)
    write_gnss(tmp_path / "gnss.txt", GnssLog(
        time=np.array([0.305, 1.505]), position=np.array([[30.0, 114.0, 20.0]] * 2),
        sigma_pos=np.full((2, 3), 0.05)))
    cfg = {"imupath": str(path), "gnsspath": str(tmp_path / "gnss.txt"),
           "outputpath": str(tmp_path / "out"), "imudatalen": 7, "imudatarate": 100.0,
           "starttime": 0.0, "endtime": -1, "initpos": [30.0, 114.0, 20.0],
           "initvel": [0, 0, 0], "initatt": [0, 0, 0],
           "initposstd": [0.05, 0.05, 0.1], "initvelstd": [0.02, 0.02, 0.02],
           "initattstd": [0.1, 0.1, 0.5],
           "imunoise": {"arw": [0.15] * 3, "vrw": [0.06] * 3, "gbstd": [3.0] * 3,
                        "abstd": [49.0] * 3, "corrtime": 1.0}, "antlever": [0, 0, 0]}
    (tmp_path / "kf-gins.yaml").write_text(yaml.safe_dump(cfg))
    config = str(tmp_path / "kf-gins.yaml")
    for extra in ([], ["--max_gap", "0.3"]):
        with pytest.raises(SystemExit) as info:
            main([config, *extra])
        assert info.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("neuralmap-gins: error: KF-GINS IMU file")
        assert "--max_gap" in err[0] and not (tmp_path / "out").exists()
    main([config, "--max_gap", "0.6"])
    out = capsys.readouterr().out
    assert "1 IMU logging gap(s) propagated across (longest 0.530 s)" in out
    assert "2 GNSS updates (2 between two IMU records, at the GNSS time)" in out
