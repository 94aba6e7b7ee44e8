"""GNSS/INS logs in the KF-GINS text formats: IMU increments, GNSS positions, navigation
results, IMU errors and state standard deviations, and the KF-GINS configuration YAML.

The formats are those documented by KF-GINS (i2Nav group, Wuhan University) and its
open datasets (awesome-gins-datasets); every file is whitespace-separated numbers, one
record a line:

=====================  ==========================================================================
IMU file (7 columns)   time [s of week], X-Y-Z angle increments [rad], X-Y-Z velocity increments
                       [m/s] over the interval ending at ``time``; body axes forward-right-down
GNSS file (7 or 13)    time, latitude [deg], longitude [deg], ellipsoidal height [m], position σ
                       north-east-down [m]; 13 columns add the NED velocity [m/s] after the
                       height and its σ [m/s] after the position σ
navigation result /    GNSS week, time [s], latitude [deg], longitude [deg], height [m], NED
reference (11)         velocity [m/s], roll, pitch, yaw [deg] (ZYX Euler angles of body → NED)
IMU error (13)         time, gyro biases [deg/h], accelerometer biases [mGal], gyro and
                       accelerometer scale factors [ppm]
state σ (22)           time, σ of NED position [m], NED velocity [m/s], roll-pitch-yaw [deg],
                       gyro biases [deg/h], accelerometer biases [mGal], scale factors [ppm]
=====================  ==========================================================================

The toolkit's filter has no scale-factor states (15 states, SEEDS 003): the IMU error file
carries zero scale factors and the σ file NaN for their σ. The log classes keep the files'
units (degrees); files are written with 17 significant digits, so writing and reading
back gives the same float64 values; writes are
atomic (`neuralmap.io`). Bad input (a wrong column count, a non-number, time that does
not increase, a gap in the IMU record, a non-positive σ) is refused with the file, line and
fix.
"""

from __future__ import annotations

import io as _io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from neuralmap.exceptions import NeuralMapError
from neuralmap.io import atomic_write_text, load_yaml

if TYPE_CHECKING:
    from neuralmap.ins.gnss import GnssRecord
    from neuralmap.ins.imu_model import ImuErrorProcess, ImuGrade
    from neuralmap.ins.trajectory import Trajectory

__all__ = [
    "GnssLog",
    "ImuLog",
    "KfGinsConfig",
    "NavLog",
    "bridge_gaps",
    "imu_error_text",
    "nav_text",
    "read_config",
    "read_gnss",
    "read_imu",
    "read_nav",
    "simulated_logs",
    "std_text",
    "table_text",
    "write_gnss",
    "write_imu",
    "write_imu_error",
    "write_nav",
    "write_std",
]

_DEG = math.pi / 180.0
_HOUR = 3600.0
_MGAL = 1e-5  # m/s² per mGal
#: An IMU interval longer than this many nominal intervals is a gap.
GAP_FACTOR = 1.5
#: Standard gravity (m/s²): the scale of the specific force `bridge_gaps` tells apart.
STANDARD_GRAVITY = 9.80665


@dataclass(frozen=True)
class ImuLog:
    """An IMU increment record.

    Attributes:
        time: ``(K,)`` end of each increment interval (s), strictly increasing.
        dtheta: ``(K, 3)`` angle increments (rad), body forward-right-down.
        dvel: ``(K, 3)`` velocity increments (m/s).
        dt: Nominal interval (s).
    """

    time: np.ndarray
    dtheta: np.ndarray
    dvel: np.ndarray
    dt: float

    @property
    def n_samples(self) -> int:
        """Number of records K."""
        return int(self.time.shape[0])


@dataclass(frozen=True)
class GnssLog:
    """GNSS position (and optional velocity) solutions at the antenna.

    Attributes:
        time: ``(M,)`` epochs (s), strictly increasing.
        position: ``(M, 3)`` latitude, longitude (degrees, as in the file), ellipsoidal
            height (m).
        sigma_pos: ``(M, 3)`` position σ north-east-down (m), > 0.
        velocity: ``(M, 3)`` NED velocity (m/s) or None.
        sigma_vel: ``(M, 3)`` velocity σ (m/s) or None.
    """

    time: np.ndarray
    position: np.ndarray
    sigma_pos: np.ndarray
    velocity: np.ndarray | None = None
    sigma_vel: np.ndarray | None = None

    @property
    def n_epochs(self) -> int:
        """Number of epochs M."""
        return int(self.time.shape[0])


@dataclass(frozen=True)
class NavLog:
    """Navigation solutions (a result or a reference trajectory).

    Attributes:
        week: ``(K,)`` GNSS week (0 when unknown).
        time: ``(K,)`` seconds of week, strictly increasing.
        position: ``(K, 3)`` latitude, longitude (degrees), height (m).
        velocity: ``(K, 3)`` NED velocity (m/s).
        euler: ``(K, 3)`` roll, pitch, yaw (degrees).
    """

    week: np.ndarray
    time: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    euler: np.ndarray


# --------------------------------------------------------------------------- reading


def _read_table(path: str | Path, columns: tuple[int, ...], what: str) -> tuple[np.ndarray, list[int]]:
    """Numbers of a whitespace-separated text file with the line number of each row.

    Blank lines and lines starting with ``#`` or ``%`` are skipped.

    Raises:
        NeuralMapError: Missing file, a row with a column count not in ``columns`` or a
            value that is not a number (file and line named), no rows at all.
    """
    path = Path(path)
    if not path.is_file():
        raise NeuralMapError(f"{what} '{path}' not found (working directory {Path.cwd()}).")
    rows: list[list[float]] = []
    lines: list[int] = []
    width: int | None = None
    with open(path, encoding="utf-8", errors="replace") as handle:
        for number, line in enumerate(handle, start=1):
            parts = line.replace(",", " ").split()
            if not parts or parts[0][0] in "#%":
                continue
            if len(parts) not in columns or (width is not None and len(parts) != width):
                expected = " or ".join(str(c) for c in columns)
                if width is not None and len(parts) in columns:
                    expected = f"{width} (as the lines above)"
                raise NeuralMapError(
                    f"{what} '{path}', line {number}: {len(parts)} columns, expected {expected} "
                    f"({_COLUMN_HINT[what]}). Fix or remove the line."
                )
            width = len(parts)
            try:
                rows.append([float(p) for p in parts])
            except ValueError:
                bad = next(p for p in parts if not _is_number(p))
                raise NeuralMapError(
                    f"{what} '{path}', line {number}: '{bad}' is not a number."
                ) from None
            lines.append(number)
    if not rows:
        raise NeuralMapError(f"{what} '{path}' holds no records ({_COLUMN_HINT[what]}).")
    table = np.asarray(rows, dtype=np.float64)
    bad = ~np.isfinite(table)
    if bool(bad.any()):
        row = int(np.nonzero(bad.any(1))[0][0])
        raise NeuralMapError(
            f"{what} '{path}', line {lines[row]}: a value is not finite (NaN or inf); "
            "remove the record."
        )
    return table, lines


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


_COLUMN_HINT = {
    "KF-GINS IMU file": "time, 3 angle increments [rad], 3 velocity increments [m/s]",
    "KF-GINS GNSS file": "time, lat [deg], lon [deg], h [m], σ N/E/D [m]; 13 columns add the "
                         "NED velocity and its σ",
    "KF-GINS navigation file": "week, time, lat [deg], lon [deg], h [m], v N/E/D [m/s], roll, "
                               "pitch, yaw [deg]",
}


def _check_increasing(time: np.ndarray, lines: list[int], path: Path, what: str,
                      fix: str) -> None:
    steps = np.diff(time)
    bad = np.nonzero(steps <= 0)[0]
    if bad.size:
        k = int(bad[0]) + 1
        raise NeuralMapError(
            f"{what} '{path}', line {lines[k]}: time {float(time[k])!r} s does not increase "
            f"(the record before, line {lines[k - 1]}, is at {float(time[k - 1])!r} s). {fix}"
        )


def read_imu(path: str | Path, *, rate_hz: float | None = None, columns: int = 7,
             max_gap: float | None = None) -> ImuLog:
    """Reads a KF-GINS IMU increment file.

    A logging gap (an interval longer than `GAP_FACTOR` nominal intervals) is refused
    unless ``max_gap`` accepts it: the filter then propagates across it as one interval of
    its true length (`neuralmap.ins.log_run.run_on_log`), with the rate of the record
    after the gap held over the gap when that record holds one interval's increments (the
    KF-GINS format: a missing record means missing increments), or with its increments as
    they are when they were accumulated over the gap (`bridge_gaps` tells the two apart),
    and counts it. The INS error grows over a gap with no IMU data; ``max_gap`` is the
    longest the user accepts.

    Args:
        path: The file.
        rate_hz: Nominal IMU rate (``imudatarate`` of the KF-GINS config); None = from the
            median interval.
        columns: Columns per line (``imudatalen``, ≥ 7; only the first 7 are used).
        max_gap: Longest accepted interval (s); None = no gap accepted.

    Returns:
        The `ImuLog`.

    Raises:
        NeuralMapError: Wrong column count, a non-number, time that does not increase, a
            gap longer than ``max_gap`` (or any gap without it), naming file and line, or a
            ``max_gap`` that is not a number > 0.
    """
    path = Path(path)
    what = "KF-GINS IMU file"
    if not (isinstance(columns, int) and columns >= 7):
        raise NeuralMapError(f"{what} '{path}': imudatalen {columns!r} must be an integer >= 7.")
    table, lines = _read_table(path, (columns,), what)
    if table.shape[0] < 2:
        raise NeuralMapError(f"{what} '{path}' holds {table.shape[0]} record; at least 2 needed.")
    time = table[:, 0]
    _check_increasing(time, lines, path, what,
                      "Sort the records by time and remove duplicates.")
    steps = np.diff(time)
    if rate_hz is not None:
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise NeuralMapError(f"{what} '{path}': imudatarate {rate_hz!r} must be > 0 Hz.")
        dt = 1.0 / float(rate_hz)
    else:
        dt = float(np.median(steps))
    if max_gap is not None and not (isinstance(max_gap, (int, float)) and math.isfinite(max_gap)
                                    and max_gap > 0):
        raise NeuralMapError(f"{what} '{path}': --max_gap {max_gap!r} must be a number of "
                             "seconds > 0 (the longest logging gap to propagate across).")
    limit = GAP_FACTOR * dt if max_gap is None else max(GAP_FACTOR * dt, float(max_gap))
    gaps = np.nonzero(steps > limit)[0]
    if gaps.size:
        k = int(gaps[0]) + 1
        longest = float(steps[gaps].max())
        how = ("Split the log at the gap (starttime/endtime) or fill it (the increments of "
               "a missing interval cannot be recovered), or pass --max_gap S (read_imu's "
               "max_gap) with S >= the gap to propagate across gaps as one interval of their "
               "true length (counted in the output)." if max_gap is None else
               f"It is longer than --max_gap {float(max_gap):g} s: raise --max_gap to at "
               f"least {longest:.6g} s to propagate across it, or split the log at the gap "
               "(starttime/endtime).")
        raise NeuralMapError(
            f"{what} '{path}', line {lines[k]}: a gap of {steps[k - 1]:.6g} s after time "
            f"{float(time[k - 1])!r} s (line {lines[k - 1]}); the nominal interval is {dt:.6g} s "
            f"({gaps.size} such gap(s), the longest {longest:.6g} s). {how} If every interval "
            "is flagged, imudatarate does not match the file."
        )
    return ImuLog(time=time.copy(), dtheta=table[:, 1:4].copy(), dvel=table[:, 4:7].copy(),
                  dt=dt)


def bridge_gaps(time: np.ndarray, dtheta: np.ndarray, dvel: np.ndarray,
                dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The increments that bridge IMU logging gaps over their true length.

    A KF-GINS IMU record holds the increments of *one* interval, the one since the record
    before it. When records are missing (a gap: an interval longer than `GAP_FACTOR`
    nominal ones), their increments are missing too, and the record after the gap holds
    its own interval's increments only: taking them as the whole gap's would integrate
    gravity over the gap with one period's specific force (a vehicle at rest falls at
    ``g · gap``). So the rate of that record (``Δθ/dt``, ``Δv/dt``) is held over the gap:
    its increments are scaled by ``gap / dt``. Some loggers instead accumulate the
    increments over a gap into the next record; that record's velocity increment is then
    about ``g · gap`` rather than ``g · dt``. The two are told apart by the specific force
    each reading implies, which for any vehicle that is not in free fall is near ``g``: a
    record with ``|Δv| > g · √(dt · gap)`` (its specific force over the gap nearer ``g``
    than over one period) is taken to hold the gap's accumulated increments and is kept as
    it is.

    Args:
        time: ``(K,)`` record times (s), increasing.
        dtheta, dvel: ``(K, 3)`` increments (rad, m/s).
        dt: Nominal interval (s).

    Returns:
        ``(dtheta, dvel, held)``: the increments (copies; records after a gap scaled where
        they hold one period) and ``(K,)`` bool, True where a rate was held over a gap.
    """
    dtheta = np.array(dtheta, dtype=np.float64)
    dvel = np.array(dvel, dtype=np.float64)
    held = np.zeros(time.shape[0], dtype=bool)
    steps = np.diff(time)
    gap = np.nonzero(steps > GAP_FACTOR * dt)[0] + 1
    if gap.size:
        length = steps[gap - 1]
        one_period = np.linalg.norm(dvel[gap], axis=1) <= STANDARD_GRAVITY * np.sqrt(dt * length)
        rows, scale = gap[one_period], (length / dt)[one_period, None]
        dtheta[rows] *= scale
        dvel[rows] *= scale
        held[rows] = True
    return dtheta, dvel, held


def read_gnss(path: str | Path) -> GnssLog:
    """Reads a KF-GINS GNSS position file (7 columns, or 13 with velocity).

    Raises:
        NeuralMapError: Wrong column count, a non-number, epochs out of order, a σ that is
            not > 0, a latitude outside ±90°, naming file and line.
    """
    path = Path(path)
    what = "KF-GINS GNSS file"
    table, lines = _read_table(path, (7, 13), what)
    time = table[:, 0]
    _check_increasing(time, lines, path, what,
                      "GNSS records must be in time order, one per epoch; sort the file.")
    with_vel = table.shape[1] == 13
    sig_cols = slice(7, 10) if with_vel else slice(4, 7)
    sigma = table[:, sig_cols]
    sigma_vel = table[:, 10:13] if with_vel else None
    for name, values in (("position σ", sigma), ("velocity σ", sigma_vel)):
        if values is None:
            continue
        bad = np.nonzero((values <= 0).any(1))[0]
        if bad.size:
            row = int(bad[0])
            raise NeuralMapError(
                f"{what} '{path}', line {lines[row]}: {name} {values[row].tolist()} must be "
                "> 0 (a zero σ would make the update singular)."
            )
    bad = np.nonzero(np.abs(table[:, 1]) > 90.0)[0]
    if bad.size:
        row = int(bad[0])
        raise NeuralMapError(
            f"{what} '{path}', line {lines[row]}: latitude {float(table[row, 1])!r}° is outside ±90°; "
            "columns are time, latitude, longitude (degrees), height."
        )
    return GnssLog(time=time.copy(), position=table[:, 1:4].copy(), sigma_pos=sigma.copy(),
                   velocity=table[:, 4:7].copy() if with_vel else None,
                   sigma_vel=None if sigma_vel is None else sigma_vel.copy())


def read_nav(path: str | Path) -> NavLog:
    """Reads a KF-GINS navigation result or reference trajectory (11 columns).

    Raises:
        NeuralMapError: Wrong column count, a non-number, time that does not increase.
    """
    path = Path(path)
    what = "KF-GINS navigation file"
    table, lines = _read_table(path, (11,), what)
    _check_increasing(table[:, 1], lines, path, what, "Sort the records by time.")
    return NavLog(
        week=table[:, 0].copy(), time=table[:, 1].copy(),
        position=table[:, 2:5].copy(), velocity=table[:, 5:8].copy(),
        euler=table[:, 8:11].copy(),
    )


# --------------------------------------------------------------------------- writing


def table_text(table: np.ndarray) -> str:
    """Rows of numbers as text with 17 significant digits (exact float64 round trip)."""
    buffer = _io.StringIO()
    np.savetxt(buffer, np.asarray(table, dtype=np.float64), fmt="%.17g", delimiter=" ")
    return buffer.getvalue()


def write_imu(path: str | Path, log: ImuLog) -> Path:
    """Writes an `ImuLog` as a KF-GINS IMU file (7 columns)."""
    return atomic_write_text(path, table_text(np.column_stack([log.time, log.dtheta,
                                                               log.dvel])))


def write_gnss(path: str | Path, log: GnssLog) -> Path:
    """Writes a `GnssLog` as a KF-GINS GNSS file (13 columns when it has velocity)."""
    head = [log.time, log.position]
    if log.velocity is None:
        table = np.column_stack([*head, log.sigma_pos])
    else:
        sigma_vel = log.sigma_vel if log.sigma_vel is not None else np.full_like(log.velocity, 0.1)
        table = np.column_stack([*head, log.velocity, log.sigma_pos, sigma_vel])
    return atomic_write_text(path, table_text(table))


def nav_text(log: NavLog) -> str:
    """A `NavLog` as the text of a KF-GINS navigation result (11 columns)."""
    return table_text(np.column_stack([log.week, log.time, log.position, log.velocity,
                                       log.euler]))


def write_nav(path: str | Path, log: NavLog) -> Path:
    """Writes a `NavLog` as a KF-GINS navigation result (`nav_text`)."""
    return atomic_write_text(path, nav_text(log))


def imu_error_text(time: np.ndarray, gyro_bias: np.ndarray, accel_bias: np.ndarray) -> str:
    """Estimated IMU errors as the text of a KF-GINS IMU error file (13 columns).

    Args:
        time: ``(K,)`` s.
        gyro_bias: ``(K, 3)`` rad/s (written in deg/h).
        accel_bias: ``(K, 3)`` m/s² (written in mGal).

    The scale-factor columns are 0: the 15-state filter does not estimate them.
    """
    k = time.shape[0]
    return table_text(np.column_stack([time, gyro_bias / _DEG * _HOUR, accel_bias / _MGAL,
                                       np.zeros((k, 6))]))


def write_imu_error(path: str | Path, time: np.ndarray, gyro_bias: np.ndarray,
                    accel_bias: np.ndarray) -> Path:
    """Writes estimated IMU errors as a KF-GINS IMU error file (`imu_error_text`)."""
    return atomic_write_text(path, imu_error_text(time, gyro_bias, accel_bias))


def std_text(time: np.ndarray, std: np.ndarray) -> str:
    """Filter standard deviations as the text of a KF-GINS state σ file (22 columns).

    Args:
        time: ``(K,)`` s.
        std: ``(K, 15)`` σ of ``[δr (m), δv (m/s), ψ (rad), δb_g (rad/s), δb_a (m/s²)]``.

    The attitude σ is the ψ-angle σ about north, east, down (≈ roll, pitch, yaw for a level
    vehicle); the scale-factor σ columns are NaN (no such states).
    """
    k = time.shape[0]
    return table_text(np.column_stack([time, std[:, :6], std[:, 6:9] / _DEG,
                                       std[:, 9:12] / _DEG * _HOUR, std[:, 12:15] / _MGAL,
                                       np.full((k, 6), np.nan)]))


def write_std(path: str | Path, time: np.ndarray, std: np.ndarray) -> Path:
    """Writes filter standard deviations as a KF-GINS state σ file (`std_text`)."""
    return atomic_write_text(path, std_text(time, std))


# --------------------------------------------------------------------------- config


@dataclass(frozen=True)
class KfGinsConfig:
    """A KF-GINS configuration (``kf-gins.yaml``) in SI units.

    Attributes:
        imupath, gnsspath, outputpath: Files and output folder (a relative path is taken
            from the working directory, as KF-GINS does, when it exists there, else from the
            config file's folder).
        imudatalen: IMU columns; imudatarate: IMU rate (Hz).
        starttime, endtime: Processing interval (s; endtime None = to the end).
        init_position: ``(3,)`` lat, lon (rad), h (m).
        init_velocity: ``(3,)`` NED m/s.
        init_euler: ``(3,)`` roll, pitch, yaw (rad).
        init_gyro_bias, init_accel_bias: ``(3,)`` rad/s, m/s².
        init_pos_sigma, init_vel_sigma: ``(3,)`` m, m/s.
        init_att_sigma_deg: ``(3,)`` deg.
        arw: Gyro angle random walk (deg/√h, mean of the axes); vrw: m/s/√h.
        gyro_bias_std: deg/h; accel_bias_std: mGal; corr_time: s.
        init_gyro_bias_std: deg/h; init_accel_bias_std: mGal (default: the bias std).
        lever_arm: ``(3,)`` IMU-to-antenna vector, forward-right-down (m).
        reference: Optional reference trajectory file (toolkit key ``truthpath``).
        source: The config file.
    """

    imupath: Path
    gnsspath: Path
    outputpath: Path
    imudatalen: int
    imudatarate: float
    starttime: float
    endtime: float | None
    init_position: tuple[float, float, float]
    init_velocity: tuple[float, float, float]
    init_euler: tuple[float, float, float]
    init_gyro_bias: tuple[float, float, float]
    init_accel_bias: tuple[float, float, float]
    init_pos_sigma: tuple[float, float, float]
    init_vel_sigma: tuple[float, float, float]
    init_att_sigma_deg: tuple[float, float, float]
    arw: float
    vrw: float
    gyro_bias_std: float
    accel_bias_std: float
    corr_time: float
    init_gyro_bias_std: float
    init_accel_bias_std: float
    lever_arm: tuple[float, float, float]
    reference: Path | None
    source: Path

    def imu_grade(self) -> ImuGrade:
        """The noise model as an `ImuGrade`.

        The filter's initial bias variance is turn-on² + instability², so the turn-on σ is
        set to ``√(init_bias_std² − bias_std²)`` (0 when the initial σ is not larger).
        """
        from neuralmap.ins.imu_model import ImuGrade

        mg = 9.80665e-3 / _MGAL  # mGal per mg
        return ImuGrade(
            name=f"kf-gins:{self.source.name}", gyro_arw=self.arw, accel_vrw=self.vrw,
            gyro_bias_instability=self.gyro_bias_std,
            accel_bias_instability=self.accel_bias_std / mg,
            gyro_corr_time=self.corr_time, accel_corr_time=self.corr_time,
            gyro_turn_on=math.sqrt(max(self.init_gyro_bias_std**2 - self.gyro_bias_std**2, 0.0)),
            accel_turn_on=math.sqrt(max(self.init_accel_bias_std**2
                                        - self.accel_bias_std**2, 0.0)) / mg,
        ).validate()


def _triple(cfg: dict[str, Any], key: str, where: str, *, positive: bool = False,
            default: Any = None, section: dict[str, Any] | None = None) -> tuple[float, ...]:
    src = cfg if section is None else section
    value = src.get(key, default)
    if value is None:
        raise NeuralMapError(f"{where}: key '{key}' is missing (three numbers).")
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise NeuralMapError(f"{where}: '{key}' = {value!r} must be three numbers.") from None
    if len(out) != 3 or not all(math.isfinite(v) for v in out) or (
            positive and min(out) <= 0):
        need = "three finite numbers > 0" if positive else "three finite numbers"
        raise NeuralMapError(f"{where}: '{key}' = {value!r} must be {need}.")
    return out


def read_config(path: str | Path) -> KfGinsConfig:
    """Reads a KF-GINS configuration YAML (the keys of KF-GINS's ``kf-gins.yaml``).

    Keys: ``imupath``, ``gnsspath``, ``outputpath``, ``imudatalen``, ``imudatarate``,
    ``starttime``, ``endtime`` (−1 = to the end), ``initpos`` [deg, deg, m], ``initvel``
    [m/s], ``initatt`` [deg], ``initgyrbias`` [deg/h], ``initaccbias`` [mGal],
    ``initposstd`` [m], ``initvelstd`` [m/s], ``initattstd`` [deg], optional ``initbgstd``
    [deg/h] and ``initbastd`` [mGal], ``imunoise`` (``arw`` [deg/√h], ``vrw`` [m/s/√h],
    ``gbstd`` [deg/h], ``abstd`` [mGal], ``corrtime`` [h]; scale-factor keys are read and
    ignored), ``antlever`` [m]; the toolkit adds an optional ``truthpath`` (reference).
    Per-axis noise values are averaged (the filter's noise model is per-sensor).

    Raises:
        NeuralMapError: A missing file or key, a value of the wrong kind, non-positive noise.
    """
    path = Path(path)
    where = f"KF-GINS config '{path}'"
    if not path.is_file():
        raise NeuralMapError(f"{where} not found (working directory {Path.cwd()}).")
    try:
        cfg = load_yaml(path.read_text(encoding="utf-8"))
    except Exception as exc:  # yaml.YAMLError and decoding errors
        raise NeuralMapError(f"{where} is not valid YAML ({exc}).") from exc
    if not isinstance(cfg, dict):
        raise NeuralMapError(f"{where}: expected a mapping of KF-GINS keys, got {type(cfg).__name__}.")
    base = path.parent

    def file_key(key: str, *, required: bool = True) -> Path | None:
        value = cfg.get(key)
        if value in (None, ""):
            if required:
                raise NeuralMapError(f"{where}: key '{key}' is missing (a file path).")
            return None
        p = Path(str(value)).expanduser()
        if p.is_absolute() or p.exists():  # KF-GINS: relative to the working directory
            return p
        return base / p  # else next to the config file

    def number(key: str, default: Any = None, section: dict[str, Any] | None = None) -> float:
        src = cfg if section is None else section
        value = src.get(key, default)
        try:
            out = float(value)
        except (TypeError, ValueError):
            raise NeuralMapError(f"{where}: '{key}' = {value!r} must be a number.") from None
        if not math.isfinite(out):
            raise NeuralMapError(f"{where}: '{key}' = {value!r} must be finite.")
        return out

    noise = cfg.get("imunoise")
    if not isinstance(noise, dict):
        raise NeuralMapError(f"{where}: key 'imunoise' (arw, vrw, gbstd, abstd, corrtime) is "
                             "missing.")
    arw = float(np.mean(_triple(cfg, "arw", where, positive=True, section=noise)))
    vrw = float(np.mean(_triple(cfg, "vrw", where, positive=True, section=noise)))
    gbstd = float(np.mean(_triple(cfg, "gbstd", where, section=noise)))
    abstd = float(np.mean(_triple(cfg, "abstd", where, section=noise)))
    corr = number("corrtime", section=noise)
    if corr <= 0 or gbstd < 0 or abstd < 0:
        raise NeuralMapError(f"{where}: imunoise corrtime must be > 0 and gbstd, abstd >= 0.")
    pos = _triple(cfg, "initpos", where)
    if abs(pos[0]) > 90:
        raise NeuralMapError(f"{where}: initpos latitude {pos[0]}° is outside ±90° (initpos is "
                             "latitude, longitude [deg], height [m]).")
    end = number("endtime", -1)
    columns = cfg.get("imudatalen", 7)
    if not isinstance(columns, int) or columns < 7:
        raise NeuralMapError(f"{where}: imudatalen {columns!r} must be an integer >= 7.")
    truth = file_key("truthpath", required=False)
    return KfGinsConfig(
        imupath=file_key("imupath"), gnsspath=file_key("gnsspath"),
        outputpath=file_key("outputpath") or base, imudatalen=columns,
        imudatarate=number("imudatarate"), starttime=number("starttime", 0.0),
        endtime=None if end < 0 else end,
        init_position=(pos[0] * _DEG, pos[1] * _DEG, pos[2]),
        init_velocity=_triple(cfg, "initvel", where),
        init_euler=tuple(a * _DEG for a in _triple(cfg, "initatt", where)),
        init_gyro_bias=tuple(b * _DEG / _HOUR for b in _triple(cfg, "initgyrbias", where,
                                                               default=(0, 0, 0))),
        init_accel_bias=tuple(b * _MGAL for b in _triple(cfg, "initaccbias", where,
                                                         default=(0, 0, 0))),
        init_pos_sigma=_triple(cfg, "initposstd", where, positive=True),
        init_vel_sigma=_triple(cfg, "initvelstd", where, positive=True),
        init_att_sigma_deg=_triple(cfg, "initattstd", where, positive=True),
        arw=arw, vrw=vrw, gyro_bias_std=gbstd, accel_bias_std=abstd, corr_time=corr * _HOUR,
        init_gyro_bias_std=float(np.mean(_triple(cfg, "initbgstd", where,
                                                 default=(gbstd,) * 3))),
        init_accel_bias_std=float(np.mean(_triple(cfg, "initbastd", where,
                                                  default=(abstd,) * 3))),
        lever_arm=_triple(cfg, "antlever", where), reference=truth, source=path,
    )


# --------------------------------------------------------------------------- simulation


def simulated_logs(traj: Trajectory, gnss: GnssRecord, *, imu: ImuErrorProcess | None = None,
                   run: int = 0, week: int = 0) -> tuple[ImuLog, GnssLog, NavLog]:
    """One run of the toolkit's simulator as KF-GINS logs: IMU, GNSS and reference.

    The IMU increments are the trapezoid of the sampled rates over each interval,
    ``Δθ_k = (ω̃_{k−1} + ω̃_k) Δt / 2`` (the mechanisation's linear-in-time inputs), of the
    measured rates when ``imu`` (an `ImuErrorProcess`,
    advanced in place) is given, else of the true ones. The first record repeats the
    first interval's increment. GNSS epochs without a solution (outages) are left out, as
    a receiver log has no line for them.

    Args:
        traj: `Trajectory`.
        gnss: `GnssRecord` of the same drive.
        imu: Optional IMU error process.
        run: The run of ``imu`` and ``gnss`` to export.
        week: GNSS week written in the reference.

    Returns:
        ``(imu_log, gnss_log, reference)``.
    """
    import torch

    from neuralmap.ins.rotation import dcm_from_quat, euler_from_dcm

    if imu is None:
        gyro, accel = traj.gyro.double(), traj.accel.double()
    else:
        pairs = [imu.measure(traj.gyro[k], traj.accel[k]) for k in range(traj.n_samples)]
        gyro = torch.stack([g[run] for g, _ in pairs]).double()
        accel = torch.stack([a[run] for _, a in pairs]).double()
    dt = float(traj.dt)
    dtheta = 0.5 * (gyro[1:] + gyro[:-1]) * dt
    dvel = 0.5 * (accel[1:] + accel[:-1]) * dt
    dtheta = torch.cat([dtheta[:1], dtheta]).numpy()
    dvel = torch.cat([dvel[:1], dvel]).numpy()
    time = traj.time.double().numpy()
    imu_log = ImuLog(time=time.copy(), dtheta=dtheta, dvel=dvel, dt=dt)
    q = gnss.quality
    valid = q.valid.cpu().numpy() & np.isfinite(gnss.position[run].cpu().numpy()).all(1)
    position = gnss.position[run].double().cpu().numpy()[valid]
    gnss_log = GnssLog(
        time=q.time.double().cpu().numpy()[valid],
        position=np.column_stack([np.degrees(position[:, :2]), position[:, 2]]),
        sigma_pos=q.sigma_pos.double().cpu().numpy()[valid],
        velocity=gnss.velocity[run].double().cpu().numpy()[valid],
        sigma_vel=q.sigma_vel.double().cpu().numpy()[valid],
    )
    s = traj.states.double()
    reference = NavLog(week=np.full(time.shape, float(week)), time=time.copy(),
                       position=np.column_stack([np.degrees(s[:, 0:2].numpy()),
                                                 s[:, 2].numpy()]),
                       velocity=s[:, 3:6].numpy(),
                       euler=np.degrees(euler_from_dcm(dcm_from_quat(s[:, 6:10])).numpy()))
    return imu_log, gnss_log, reference
