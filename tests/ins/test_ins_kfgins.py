"""KF-GINS formats: exact round trips of simulator logs, the filter on a log against the
truth, the neuralmap-gins entry point, and bad logs refused with file and line."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from neuralmap.exceptions import NeuralMapError
from neuralmap.ins.gins_cli import IMU_ERROR_FILE, NAV_FILE, STD_FILE, main
from neuralmap.ins.gnss import simulate_gnss
from neuralmap.ins.imu_model import ImuErrorProcess, imu_grade
from neuralmap.ins.kfgins import (
    GnssLog,
    read_config,
    read_gnss,
    read_imu,
    read_nav,
    simulated_logs,
    write_gnss,
    write_imu,
    write_nav,
)
from neuralmap.ins.log_run import compare_with_reference, run_on_log
from neuralmap.ins.loosely_coupled import LooselyCoupledConfig
from neuralmap.ins.measurement import antenna_position
from neuralmap.ins.trajectory import short_drive

ARM = (0.5, 0.2, -1.2)


@pytest.fixture(scope="module")
def drive():  # noqa: ANN201
    """A 20 s drive at 20 Hz, 1 Hz GNSS, one noisy IMU (kept small: the filter loops in time)."""
    traj = short_drive(duration=20.0, dt=0.05)
    gen = torch.Generator().manual_seed(3)
    gnss = simulate_gnss(traj, n_runs=1, lever_arm=ARM, generator=gen)
    imu = ImuErrorProcess("tactical_mems", n_runs=1, dt=traj.dt, generator=gen,
                          scale_factor=False)
    return traj, gnss, simulated_logs(traj, gnss, imu=imu)


def test_round_trip_is_exact(tmp_path: Path, drive) -> None:  # noqa: ANN001
    _, _, (imu, gnss, ref) = drive
    back = read_imu(write_imu(tmp_path / "imu.txt", imu))
    for name in ("time", "dtheta", "dvel"):
        np.testing.assert_array_equal(getattr(back, name), getattr(imu, name))
    assert back.dt == pytest.approx(imu.dt, rel=1e-12)
    g = read_gnss(write_gnss(tmp_path / "gnss.txt", gnss))
    for name in ("time", "position", "sigma_pos", "velocity", "sigma_vel"):
        np.testing.assert_array_equal(getattr(g, name), getattr(gnss, name))
    g7 = GnssLog(time=gnss.time, position=gnss.position, sigma_pos=gnss.sigma_pos)
    back7 = read_gnss(write_gnss(tmp_path / "gnss7.txt", g7))
    assert back7.velocity is None and len((tmp_path / "gnss7.txt").read_text().split("\n")[0]
                                          .split()) == 7
    np.testing.assert_array_equal(back7.position, gnss.position)
    r = read_nav(write_nav(tmp_path / "ref.nav", ref))
    for name in ("week", "time", "position", "velocity", "euler"):
        np.testing.assert_array_equal(getattr(r, name), getattr(ref, name))


def test_filter_on_an_exact_log_follows_the_truth(drive) -> None:  # noqa: ANN001
    """True increments and exact antenna positions (σ 1 cm): run 0 stays within 1 cm and
    0.05° of the truth (the only errors are the filter's and the increment discretisation)."""
    traj, gnss, _ = drive
    imu, _, ref = simulated_logs(traj, gnss)
    q = gnss.quality
    exact = antenna_position(traj.states[q.imu_index], torch.tensor(ARM, dtype=torch.float64))
    exact = torch.cat([torch.rad2deg(exact[:, :2]), exact[:, 2:]], dim=1)
    log = GnssLog(time=q.time.numpy(), position=exact.numpy(),
                  sigma_pos=np.full((q.n_epochs, 3), 0.01))
    lat, lon, h = ref.position[0]
    sol = run_on_log(imu, log, grade=imu_grade("tactical_mems"),
                     initial_position=(np.radians(lat), np.radians(lon), h),
                     initial_velocity=tuple(ref.velocity[0]),
                     initial_euler=tuple(np.radians(ref.euler[0])),
                     lever_arm=ARM, filter_config=LooselyCoupledConfig())
    assert sol.states.shape == (1, imu.n_samples, 10)
    assert sol.counts["updates"] == q.n_epochs
    e = compare_with_reference(sol, ref)["run_0"]
    assert e["max_horizontal_m"] < 0.01 and e["rmse_vertical_m"] < 0.01
    assert e["rmse_velocity_mps"] < 0.005
    assert max(e["rmse_roll_deg"], e["rmse_pitch_deg"], e["rmse_heading_deg"]) < 0.05


def _write_case(tmp_path: Path, drive, **extra) -> Path:  # noqa: ANN001
    traj, _, (imu, gnss, ref) = drive
    write_imu(tmp_path / "imu.txt", imu)
    write_gnss(tmp_path / "gnss.txt", gnss)
    write_nav(tmp_path / "truth.nav", ref)
    cfg = {
        "imupath": "imu.txt", "gnsspath": "gnss.txt", "outputpath": "out",
        "truthpath": "truth.nav", "imudatalen": 7, "imudatarate": 1.0 / traj.dt,
        "starttime": float(imu.time[0]), "endtime": -1,
        "initpos": ref.position[0].tolist(),
        "initvel": ref.velocity[0].tolist(), "initatt": ref.euler[0].tolist(),
        "initgyrbias": [0, 0, 0], "initaccbias": [0, 0, 0],
        "initposstd": [0.05, 0.05, 0.1], "initvelstd": [0.02, 0.02, 0.02],
        "initattstd": [0.1, 0.1, 0.5],
        "imunoise": {"arw": [0.15] * 3, "vrw": [0.06] * 3, "gbstd": [3.0] * 3,
                     "abstd": [49.0] * 3, "gsstd": [300.0] * 3, "asstd": [300.0] * 3,
                     "corrtime": 1.0},
        "initbgstd": [10.44] * 3, "initbastd": [1100.0] * 3,
        "antlever": list(ARM), **extra,
    }
    path = tmp_path / "kf-gins.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_config_units(tmp_path: Path, drive) -> None:  # noqa: ANN001
    cfg = read_config(_write_case(tmp_path, drive))
    grade = cfg.imu_grade()
    assert grade.gyro_arw == 0.15 and grade.accel_vrw == 0.06 and grade.gyro_corr_time == 3600.0
    assert grade.accel_bias_instability == pytest.approx(49.0e-5 / 9.80665e-3, rel=1e-12)
    # initial bias σ² = turn-on² + instability² reproduces initbgstd
    assert np.hypot(grade.gyro_turn_on, grade.gyro_bias_instability) == pytest.approx(10.44)
    assert cfg.imupath == tmp_path / "imu.txt" and cfg.endtime is None


def test_entry_point_writes_kfgins_results(tmp_path: Path, drive, capsys) -> None:  # noqa: ANN001
    _, _, (imu, gnss, _) = drive
    main([str(_write_case(tmp_path, drive)), "--n_runs", "3"])
    out = tmp_path / "out"
    nav = read_nav(out / NAV_FILE)
    np.testing.assert_array_equal(nav.time, imu.time)
    assert np.loadtxt(out / IMU_ERROR_FILE).shape == (imu.n_samples, 13)
    assert np.loadtxt(out / STD_FILE).shape == (imu.n_samples, 22)
    comparison = json.loads((out / "comparison.json").read_text())
    assert comparison["n_runs"] == 3 and comparison["epochs_compared"] == imu.n_samples
    run0 = comparison["run_0"]
    # noisy IMU, simulated GNSS with 2-5 cm σ: decimetre level at most
    assert run0["rmse_horizontal_m"] < 0.2 and run0["rmse_heading_deg"] < 1.0
    assert "RMSE horizontal" in capsys.readouterr().out


def _raises(path: Path, match: str, reader, **kwargs) -> str:  # noqa: ANN001
    with pytest.raises(NeuralMapError, match=match) as info:
        reader(path, **kwargs)
    assert path.name in str(info.value)
    return str(info.value)


def test_bad_imu_files(tmp_path: Path) -> None:
    rows = [f"{0.01 * k:.2f} 0 0 0 0 0 -0.098" for k in range(1, 8)]
    path = tmp_path / "imu.txt"
    path.write_text("\n".join(rows[:3] + [rows[1]] + rows[4:]) + "\n")
    msg = _raises(path, "line 4: time 0.02 s does not increase", read_imu)
    assert "Sort" in msg
    path.write_text("\n".join(rows[:3] + rows[5:]) + "\n")  # 0.03 -> 0.06
    msg = _raises(path, "line 4: a gap of 0.03 s", read_imu, rate_hz=100.0)
    assert "Split the log" in msg
    path.write_text("\n".join(rows[:2] + ["0.03 0 0 0 0 0"] + rows[3:]) + "\n")
    _raises(path, "line 3: 6 columns, expected 7", read_imu)
    path.write_text("\n".join(rows[:2] + ["0.03 0 0 x 0 0 0"] + rows[3:]) + "\n")
    _raises(path, "line 3: 'x' is not a number", read_imu)


def test_bad_gnss_files(tmp_path: Path) -> None:
    rows = [f"{k}.0 30.5 114.3 20.0 0.02 0.02 0.05" for k in range(5)]
    path = tmp_path / "gnss.txt"
    path.write_text("\n".join([rows[0], rows[2], rows[1]] + rows[3:]) + "\n")
    msg = _raises(path, "line 3: time 1.0 s does not increase", read_gnss)
    assert "time order" in msg
    path.write_text("\n".join(rows[:2] + ["2.0 30.5 114.3 20.0 0 0.02 0.05"]) + "\n")
    _raises(path, r"line 3: position σ .* must be > 0", read_gnss)
    path.write_text("\n".join(rows[:2] + ["2.0 30.5 114.3 20.0 0.02"]) + "\n")
    _raises(path, "line 3: 5 columns, expected 7 or 13", read_gnss)


def test_read_only_output_is_refused(tmp_path: Path, drive, capsys,  # noqa: ANN001
                                     monkeypatch: pytest.MonkeyPatch) -> None:
    config = _write_case(tmp_path, drive)
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    real_access = os.access
    # as root a 0o500 folder is still writable: answer for it as for any other user
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p) == locked
                        else real_access(p, mode, **kw))
    try:
        with pytest.raises(SystemExit) as info:
            main([str(config), "--outputpath", str(locked / "out")])
    finally:
        locked.chmod(0o700)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "error:" in err and "not writable" in err
    assert not (locked / "out").exists()


def test_log_driver_reproduces_the_simulator_driven_filter() -> None:
    """Anchor: on the same measured IMU record (two IMU processes with one seed) and the same
    GNSS record, the log driver and `run_loosely_coupled` agree at the GNSS epochs to
    3 mm in position and 2 mm/s in velocity (measured 1.1 mm, 0.6 mm/s; the errors themselves
    are 16 mm RMS). The only difference is the IMU input: increments as a constant rate per
    interval here, linear rates between samples there. P0 is tiny so that neither draws an
    initial error."""
    from neuralmap.ins.earth import position_offset_ned
    from neuralmap.ins.loosely_coupled import run_loosely_coupled

    traj = short_drive(duration=20.0, dt=0.05)
    gnss = simulate_gnss(traj, n_runs=1, lever_arm=ARM, generator=torch.Generator().manual_seed(3))

    def imu_process() -> ImuErrorProcess:
        return ImuErrorProcess("tactical_mems", n_runs=1, dt=traj.dt, scale_factor=False,
                               generator=torch.Generator().manual_seed(5))

    cfg = LooselyCoupledConfig(init_pos_sigma=(1e-6,) * 3, init_vel_sigma=(1e-6,) * 3,
                               init_att_sigma_deg=(1e-6,) * 3)
    reference = run_loosely_coupled(traj, imu_process(), gnss, cfg,
                                    generator=torch.Generator().manual_seed(0))
    imu, log, ref = simulated_logs(traj, gnss, imu=imu_process())
    sol = run_on_log(imu, log, grade=imu_grade("tactical_mems"),
                     initial_position=tuple(traj.states[0, :3].tolist()),
                     initial_velocity=tuple(traj.states[0, 3:6].tolist()),
                     initial_euler=tuple(np.radians(ref.euler[0])), lever_arm=ARM,
                     filter_config=cfg)
    idx = gnss.quality.imu_index
    s, t = sol.states[0, idx], traj.states[idx]
    err = position_offset_ned(s[:, 0], s[:, 1], s[:, 2], t[:, 0], t[:, 1], t[:, 2])
    assert float(reference.position_error[0].square().mean().sqrt()) > 0.005
    assert float((err - reference.position_error[0]).abs().max()) < 3e-3
    vel_err = s[:, 3:6] - t[:, 3:6]
    assert float((vel_err - reference.velocity_error[0]).abs().max()) < 2e-3


def _run_drive(drive, **kwargs):  # noqa: ANN001, ANN202
    _, _, (imu, gnss, ref) = drive
    lat, lon, h = ref.position[0]
    return run_on_log(imu, gnss, grade=imu_grade("tactical_mems"),
                      initial_position=(np.radians(lat), np.radians(lon), h),
                      initial_velocity=tuple(ref.velocity[0]),
                      initial_euler=tuple(np.radians(ref.euler[0])), lever_arm=ARM, **kwargs)


def test_block_driver_reproduces_the_record_by_record_driver(drive) -> None:  # noqa: ANN001
    """The block form (compiled mechanisation and covariance over each stretch between GNSS
    epochs) gives the numbers of the record-by-record implementation it replaced, stored
    once from that code (tests/ins/data/log_run_per_record.json): states to 1e-9 relative,
    σ and bias estimates to 1e-9 relative (measured 6e-13, 3e-15, 1e-12)."""
    expected = json.loads((Path(__file__).parent / "data" / "log_run_per_record.json")
                          .read_text())
    sol = _run_drive(drive, filter_config=LooselyCoupledConfig(
        propagate_every=expected["propagate_every"]))
    idx = expected["index"]
    for name, got in (("states", sol.states), ("std", sol.std), ("gyro_bias", sol.gyro_bias),
                      ("accel_bias", sol.accel_bias)):
        np.testing.assert_allclose(got[0, idx].numpy(), np.array(expected[name]), rtol=1e-9,
                                   atol=1e-15, err_msg=name)


def test_compiled_and_torch_block_paths_agree(drive, monkeypatch: pytest.MonkeyPatch) -> None:  # noqa: ANN001
    """Three runs (two with noise draws), a record every 3rd epoch: the numba kernels and
    their torch fallbacks give the same solutions and σ (1e-10 relative)."""
    from neuralmap.ins import kernels

    if not kernels.HAVE_NUMBA:
        pytest.skip("numba (extra 'fast') is not installed")
    cfg = LooselyCoupledConfig(propagate_every=6)
    kw = {"filter_config": cfg, "n_runs": 3, "output_every": 3, "seed": 4, "end": 6.0}
    fast = _run_drive(drive, **kw)
    monkeypatch.setattr(kernels, "HAVE_NUMBA", False)
    slow = _run_drive(drive, **kw)
    assert fast.states.shape == slow.states.shape and fast.states.shape[0] == 3
    assert float((fast.states[1] - fast.states[0]).abs().max()) > 1e-9  # noise drawn
    torch.testing.assert_close(fast.states, slow.states, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(fast.std, slow.std, rtol=1e-10, atol=1e-15)
    torch.testing.assert_close(fast.gyro_bias, slow.gyro_bias, rtol=1e-8, atol=1e-14)


# --------------------------------------------------------------------------- bad input, CLI

INTERRUPTED = "neuralmap-gins: interrupted; nothing was written (earlier outputs are unchanged)."


def _outputs(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


@pytest.mark.parametrize("value", ["nan", "abc", "inf", "1e400", "-1", "0"])
def test_bad_max_gap_is_one_line(tmp_path: Path, capsys, value: str) -> None:  # noqa: ANN001
    """A value the parser rejects (abc, nan, inf) or one out of range: one error line naming
    the option and its range, no parser dump, nothing written."""
    with pytest.raises(SystemExit) as info:
        main([str(tmp_path / "kf-gins.yaml"), "--max_gap", value, "--outputpath",
              str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert info.value.code == 2 and err.count("\n") == 1, err
    assert err.startswith("neuralmap-gins: error: --max_gap: ") and "usage:" not in err
    assert "is not valid; expected a finite number of seconds > 0" in err
    assert not (tmp_path / "out").exists()


def test_full_disk_keeps_the_previous_results(tmp_path: Path, drive, capsys,  # noqa: ANN001
                                              fail_write) -> None:  # noqa: ANN001
    """A rerun that fills the disk while writing its third file: one error line, exit 2,
    the previous run's four files byte for byte, no temporary file."""
    config = _write_case(tmp_path, drive)
    main([str(config)])
    out = tmp_path / "out"
    before = _outputs(out)
    assert sorted(before) == sorted([NAV_FILE, IMU_ERROR_FILE, STD_FILE, "comparison.json"])
    capsys.readouterr()
    fail_write(3)
    with pytest.raises(SystemExit) as info:
        main([str(config), "--r_scale", "2.0"])
    err = capsys.readouterr().err
    assert info.value.code == 2 and err.count("\n") == 1, err
    assert "error: outputpath: cannot write" in err and "No space left on device" in err
    assert _outputs(out) == before  # byte for byte, and no hidden temporary file


def test_interrupt_keeps_the_previous_results(tmp_path: Path, drive, capsys,  # noqa: ANN001
                                              fail_write, monkeypatch) -> None:  # noqa: ANN001
    config = _write_case(tmp_path, drive)
    main([str(config)])
    out = tmp_path / "out"
    before = _outputs(out)
    capsys.readouterr()
    fail_write(2, KeyboardInterrupt())  # Ctrl-C while writing
    with pytest.raises(SystemExit) as info:
        main([str(config)])
    assert info.value.code == 130
    assert capsys.readouterr().err.strip().splitlines() == [INTERRUPTED]
    assert _outputs(out) == before

    def interrupted(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise KeyboardInterrupt

    # Ctrl-C at start-up: while reading the logs, and while the package still imports
    monkeypatch.setattr("neuralmap.ins.kfgins.read_imu", interrupted)
    with pytest.raises(SystemExit) as info:
        main([str(config), "--outputpath", str(tmp_path / "new")])
    assert info.value.code == 130
    assert capsys.readouterr().err.strip().splitlines() == [INTERRUPTED]
    assert not (tmp_path / "new").exists()
    from neuralmap import entry

    monkeypatch.setattr(entry.importlib, "import_module", interrupted)
    assert entry.gins([str(config)]) == 130
    assert capsys.readouterr().err.strip().splitlines() == [INTERRUPTED]


def test_outputpath_that_cannot_be_made_is_refused_first(
        tmp_path: Path, drive, capsys: pytest.CaptureFixture[str],  # noqa: ANN001
        monkeypatch: pytest.MonkeyPatch) -> None:
    config = _write_case(tmp_path, drive)
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")

    def no_work(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise AssertionError("the IMU log was read before outputpath was checked")

    monkeypatch.setattr("neuralmap.ins.kfgins.read_imu", no_work)
    with pytest.raises(SystemExit) as info:
        main([str(config), "--outputpath", str(blocker / "out")])
    err = capsys.readouterr().err
    assert info.value.code == 2 and err.count("\n") == 1, err
    assert "error: outputpath" in err and "is a file, not a folder" in err


def test_a_run_without_reference_removes_an_older_comparison(tmp_path: Path, drive,  # noqa: ANN001
                                                             capsys) -> None:  # noqa: ANN001
    """The outputs of one run belong together: a comparison.json of an earlier run with a
    reference would sit beside results it is not about."""
    config = _write_case(tmp_path, drive)
    main([str(config)])
    assert (tmp_path / "out" / "comparison.json").is_file()
    (tmp_path / "truth.nav").unlink()
    cfg = yaml.safe_load(config.read_text())
    del cfg["truthpath"]
    config.write_text(yaml.safe_dump(cfg))
    main([str(config)])
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(
        [NAV_FILE, IMU_ERROR_FILE, STD_FILE])
