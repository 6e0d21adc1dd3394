"""Raw IMU data: CSV (rates or increments) and NovAtel Inertial Explorer ``.imr``.

In memory (:class:`ImuData`) the samples are always rates in the IMU body frame
``b`` (forward-right-down): ``gyro`` = angular rate ``omega_ib_b`` in rad/s and
``acc`` = specific force ``f_ib_b`` in m/s². ``kind`` says what a sample means:

* ``"rates"``: the sensor's value at the time tag;
* ``"increments"``: the average rate over the interval ``(t_{k-1}, t_k]`` that
  ends at the time tag, i.e. increment / interval length.

Sample intervals (:func:`sample_intervals`): ``dt_k = t_k - t_{k-1}``, except
that the nominal interval ``1 / rate_hz`` is used for the first sample, after a
gap (``dt_k > max_gap_factor / rate_hz``: an increment after a gap covers one
nominal interval, the samples lost in the gap are lost), and whenever ``dt_k``
is within ``jitter_tolerance`` (relative, default 1e-3) of the nominal interval.
The last rule matters: absolute GPS seconds (~1.4e9 s) in float64 resolve only
0.24 µs, so a raw time difference at 200 Hz is off by up to 5e-5 relative,
which would turn into up to 50 µg of noise on 1 g; like Inertial Explorer (which
multiplies increments by ``dDataRateHz``), regular samples use the nominal
interval. The same intervals convert rates back to increments, so the
conversions are exact inverses.

CSV
    Header ``time,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z`` (GPS seconds, rad/s,
    m/s², FRD) or ``time,dtheta_x,dtheta_y,dtheta_z,dv_x,dv_y,dv_z`` (rad and m/s
    over the interval ending at ``time``), either optionally followed by
    ``temperature_c``: the unit's temperature (deg C), as IMUs log it beside their readings,
    against which the adjustment can estimate the biases' temperature coefficients. Lines
    starting with ``#`` are comments.

IMR (Inertial Explorer raw IMU)
    512-byte header then 32-byte records ``double time; int32 gx, gy, gz, ax, ay, az``
    (NovAtel Waypoint documentation, "IMR File" and "Inertial Explorer Data
    Formats", docs.novatel.com/Waypoint/Content/Data_Formats/IMR_File.htm). Times
    are GPS seconds of the week. ``bDeltaTheta``/``bDeltaVelocity`` = 1: the
    scaled values are increments in degrees and m/s (times ``dDataRateHz`` gives
    deg/s and m/s²); = 0: rates in deg/s and m/s². Axes: Inertial Explorer's IMU
    frame is X right, Y forward, Z up (RFU); NovAtel application note APN-065
    "Determining Rotations for Inertial Explorer and SPAN" (gnss.ca/support/papers/apn065):
    "mount the IMU without rotations (Y forward, X right, Z up)". So
    ``x_FRD = y_RFU, y_FRD = x_RFU, z_FRD = -z_RFU`` (a proper rotation, applied to
    both sensors). Files with UTC time tags or a non-zero ``dTimeTagBias`` are
    rejected (the bias sign convention is not documented in the sources found).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np

from georefine.errors import InputError
from georefine.io.files import (
    SECONDS_PER_WEEK,
    PathLike,
    atomic_output,
    data_lines,
    parse_float_rows,
    raise_if_not_increasing,
    read_text_lines,
    unwrap_seconds_of_week,
    week_from_gps_seconds,
)

__all__ = [
    "ImuData", "ImrHeader", "sample_intervals", "read_imu_csv", "write_imu_csv",
    "read_imr_header", "read_imr", "write_imr", "RATE_COLUMNS", "INCREMENT_COLUMNS",
]

_log = logging.getLogger(__name__)

RATE_COLUMNS = ("time", "gyro_x", "gyro_y", "gyro_z", "acc_x", "acc_y", "acc_z")
INCREMENT_COLUMNS = ("time", "dtheta_x", "dtheta_y", "dtheta_z", "dv_x", "dv_y", "dv_z")
TEMPERATURE_COLUMN = "temperature_c"
"""The optional last CSV column: the unit's temperature (deg C)."""

# R_FRD_RFU: x_FRD = y_RFU, y_FRD = x_RFU, z_FRD = -z_RFU (det = +1).
R_FRD_RFU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def sample_intervals(
    time_gps: np.ndarray, rate_hz: float, max_gap_factor: float = 1.5, jitter_tolerance: float = 1e-3
) -> np.ndarray:
    """Interval (s) that each sample's increment covers, (N,); see the module docstring."""
    nominal = 1.0 / rate_hz
    dt = np.empty_like(np.asarray(time_gps, dtype=np.float64))
    if dt.size:
        dt[0] = nominal
        dt[1:] = np.diff(time_gps)
        use_nominal = (dt[1:] > max_gap_factor * nominal) | (np.abs(dt[1:] - nominal) <= jitter_tolerance * nominal)
        dt[1:][use_nominal] = nominal
    return dt


@dataclass(frozen=True)
class ImuData:
    """IMU samples in the body frame ``b`` (FRD).

    Attributes
    ----------
    time_gps
        (N,) GPS seconds, strictly increasing.
    gyro
        (N,3) angular rate ``omega_ib_b``, rad/s.
    acc
        (N,3) specific force ``f_ib_b``, m/s².
    rate_hz
        Nominal sample rate, Hz.
    kind
        ``"rates"`` (values at the time tag) or ``"increments"`` (averages over
        the interval ending at the time tag).
    temperature_c
        (N,) the unit's temperature at each sample (deg C), or None where the file has none.
    """

    time_gps: np.ndarray
    gyro: np.ndarray
    acc: np.ndarray
    rate_hz: float
    kind: Literal["rates", "increments"] = "rates"
    temperature_c: np.ndarray | None = None

    def __post_init__(self) -> None:
        t = np.ascontiguousarray(self.time_gps, dtype=np.float64)
        if t.ndim != 1:
            raise ValueError(f"time_gps must be 1-D, got shape {t.shape}")
        for name in ("gyro", "acc"):
            a = np.ascontiguousarray(getattr(self, name), dtype=np.float64)
            if a.shape != (t.shape[0], 3):
                raise ValueError(f"{name} must have shape {(t.shape[0], 3)}, got {a.shape}")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"{name} contains non-finite values")
            object.__setattr__(self, name, a)
        if not np.all(np.isfinite(t)) or (t.size > 1 and np.any(np.diff(t) <= 0)):
            raise ValueError("time_gps must be finite and strictly increasing")
        if not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise ValueError(f"rate_hz must be positive, got {self.rate_hz}")
        if self.kind not in ("rates", "increments"):
            raise ValueError(f"kind must be 'rates' or 'increments', got {self.kind!r}")
        if self.temperature_c is not None:
            temp = np.ascontiguousarray(self.temperature_c, dtype=np.float64)
            if temp.shape != t.shape or not np.all(np.isfinite(temp)):
                raise ValueError(f"temperature_c must be finite with shape {t.shape}, got {temp.shape}")
            object.__setattr__(self, "temperature_c", temp)
        object.__setattr__(self, "time_gps", t)
        object.__setattr__(self, "rate_hz", float(self.rate_hz))

    def __len__(self) -> int:
        return self.time_gps.shape[0]

    def intervals(self, max_gap_factor: float = 1.5) -> np.ndarray:
        """(N,) interval each sample covers, s (:func:`sample_intervals`)."""
        return sample_intervals(self.time_gps, self.rate_hz, max_gap_factor)

    def increments(self, max_gap_factor: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
        """(dtheta (N,3) rad, dv (N,3) m/s) = rates times :meth:`intervals`."""
        dt = self.intervals(max_gap_factor)[:, None]
        return self.gyro * dt, self.acc * dt

    @classmethod
    def from_increments(
        cls, time_gps: np.ndarray, dtheta: np.ndarray, dv: np.ndarray, rate_hz: float,
        max_gap_factor: float = 1.5,
    ) -> ImuData:
        """Average rates = increment / interval; ``kind="increments"``."""
        dt = sample_intervals(np.asarray(time_gps, float), rate_hz, max_gap_factor)[:, None]
        return cls(time_gps, np.asarray(dtheta) / dt, np.asarray(dv) / dt, rate_hz, "increments")


def _check_magnitudes(
    path: Path, gyro: np.ndarray, acc: np.ndarray, numbers: np.ndarray, names: tuple[str, ...],
    max_gyro: float, max_acc: float, record_kind: str,
) -> None:
    for arr, limit, off, unit in ((gyro, max_gyro, 0, "rad/s"), (acc, max_acc, 3, "m/s²")):
        bad = np.abs(arr) > limit
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise InputError(
                "implausible IMU value", path=path, line=int(numbers[i]), field=names[off + j],
                expected=f"|rate| <= {limit:g} {unit}", found=f"{arr[i, j]:.6g} {unit}", record_kind=record_kind,
            )


def _nominal_rate(time_gps: np.ndarray) -> float:
    """1 / median interval, snapped to a whole Hz within 1e-4 (float64 GPS seconds resolve 0.24 µs)."""
    if time_gps.size < 2:
        return 1.0
    rate = 1.0 / float(np.median(np.diff(time_gps)))
    return float(round(rate)) if abs(rate - round(rate)) <= 1e-4 * rate else rate


# ---------------------------------------------------------------------------
# CSV
# ---------------------------------------------------------------------------


def read_imu_csv(
    path: PathLike,
    *,
    rate_hz: float | None = None,
    max_gyro_rad_s: float = 50.0,
    max_acc_m_s2: float = 500.0,
    max_gap_factor: float = 1.5,
) -> ImuData:
    """Read an IMU CSV file (rates or increments, detected from the header).

    Parameters
    ----------
    rate_hz
        Nominal sample rate; default ``1 / median(dt)``.
    max_gyro_rad_s, max_acc_m_s2
        Plausibility limits on the (average) rates.

    Raises
    ------
    InputError
        Unknown header, bad value (line and field), non-increasing time (line
        and both times), implausible magnitude, no samples.
    """
    path = Path(path)
    lines = read_text_lines(path)
    rows, numbers = data_lines(lines, 0)
    if not rows:
        raise InputError("no IMU samples", path=path, expected="a header and data lines", found="none")
    header_line = int(numbers[0])
    header = tuple(t.strip().lower() for t in rows[0].split(","))
    temperature = header[-1:] == (TEMPERATURE_COLUMN,)
    if header[:7] not in (RATE_COLUMNS, INCREMENT_COLUMNS) or len(header) != 7 + temperature:
        raise InputError(
            "unknown IMU CSV header", path=path, line=header_line,
            expected=f"'{','.join(RATE_COLUMNS)}' or '{','.join(INCREMENT_COLUMNS)}', either optionally followed by "
            f"',{TEMPERATURE_COLUMN}'", found=repr(rows[0]),
        )
    rows, numbers = rows[1:], numbers[1:]
    if not rows:
        raise InputError("no IMU samples", path=path, expected="data lines after the header", found="none")
    v = parse_float_rows(path, rows, numbers, header, delimiter=",")
    t = v[:, 0]
    raise_if_not_increasing(path, t, numbers, "time", formatter=lambda x: f"{x:.9f}")
    rate = rate_hz or _nominal_rate(t)
    if header[:7] == RATE_COLUMNS:
        data = ImuData(t, v[:, 1:4], v[:, 4:7], rate, "rates")
    else:
        data = ImuData.from_increments(t, v[:, 1:4], v[:, 4:7], rate, max_gap_factor)
    _check_magnitudes(path, data.gyro, data.acc, numbers, header[1:7], max_gyro_rad_s, max_acc_m_s2, "line")
    if temperature:
        temp = v[:, 7]
        bad = np.flatnonzero((temp < -60.0) | (temp > 125.0))  # beyond any IMU's operating range
        if bad.size:
            raise InputError("implausible IMU temperature", path=path, line=int(numbers[bad[0]]),
                             field=TEMPERATURE_COLUMN, expected="deg C within -60 .. 125",
                             found=f"{temp[bad[0]]:g}")
        data = replace(data, temperature_c=temp)
    _log.info("read %d IMU samples (%s, %.1f Hz) from %s", len(data), data.kind, rate, path)
    return data


def write_imu_csv(
    path: PathLike,
    data: ImuData,
    kind: Literal["rates", "increments"] | None = None,
    *,
    max_gap_factor: float = 1.5,
    protect: tuple[PathLike, ...] = (),
) -> Path:
    """Write ``data`` as IMU CSV (time ``%.9f``, values ``%.10e``), atomically.

    ``kind`` defaults to ``data.kind``; ``"increments"`` writes rates times
    :func:`sample_intervals`.
    """
    kind = kind or data.kind
    if kind == "rates":
        columns, a, b = RATE_COLUMNS, data.gyro, data.acc
    elif kind == "increments":
        columns = INCREMENT_COLUMNS
        a, b = data.increments(max_gap_factor)
    else:
        raise ValueError(f"kind must be 'rates' or 'increments', got {kind!r}")
    fmt = "%.9f" + ",%.10e" * 6 + "\n"
    table = np.column_stack([data.time_gps, a, b])
    if data.temperature_c is not None:
        columns, fmt = (*columns, TEMPERATURE_COLUMN), fmt[:-1] + ",%.4f\n"
        table = np.column_stack([table, data.temperature_c])
    with atomic_output(path, "w", protect=protect) as fh:
        fh.write(",".join(columns) + "\n")
        fh.writelines(fmt % tuple(r) for r in table.tolist())
    return Path(path)


# ---------------------------------------------------------------------------
# IMR
# ---------------------------------------------------------------------------

_IMR_MAGIC = b"$IMURAW\0"
_IMR_HEADER_SIZE = 512
_IMR_FIELDS = ("gx", "gy", "gz", "ax", "ay", "az")


def _imr_header_dtype(endian: str) -> np.dtype:
    e = endian
    return np.dtype([
        ("szHeader", "S8"), ("bIsIntelOrMotorola", "i1"), ("dVersionNumber", e + "f8"),
        ("bDeltaTheta", e + "i4"), ("bDeltaVelocity", e + "i4"), ("dDataRateHz", e + "f8"),
        ("dGyroScaleFactor", e + "f8"), ("dAccelScaleFactor", e + "f8"), ("iUtcOrGpsTime", e + "i4"),
        ("iRcvTimeOrCorrTime", e + "i4"), ("dTimeTagBias", e + "f8"), ("szImuName", "S32"),
        ("reserved1", "V4"), ("szProgramName", "S32"), ("tCreate", "V12"), ("bLeverArmValid", "u1"),
        ("lXoffset", e + "i4"), ("lYoffset", e + "i4"), ("lZoffset", e + "i4"), ("Reserved", "V354"),
    ])


def _imr_record_dtype(endian: str) -> np.dtype:
    return np.dtype([("time", endian + "f8")] + [(f, endian + "i4") for f in _IMR_FIELDS])


assert _imr_header_dtype("<").itemsize == _IMR_HEADER_SIZE and _imr_record_dtype("<").itemsize == 32


@dataclass(frozen=True)
class ImrHeader:
    """The fields of an IMR header (units as in the file: Hz, deg or deg/s per count, m/s or m/s² per count).

    ``lever_arm_raw`` holds ``lXoffset, lYoffset, lZoffset`` as stored; their unit
    is not documented in the sources consulted and Georefine does not use them
    (lever arms come from ``project.yaml``).
    """

    version: float
    delta_theta: bool
    delta_velocity: bool
    rate_hz: float
    gyro_scale: float
    accel_scale: float
    utc_or_gps_time: int
    rcv_or_corr_time: int
    time_tag_bias_s: float
    imu_name: str
    program_name: str
    lever_arm_valid: bool
    lever_arm_raw: tuple[int, int, int]
    big_endian: bool = False


def read_imr_header(path: PathLike) -> ImrHeader:
    """Read and validate the 512-byte IMR header.

    Raises
    ------
    InputError
        Short header, wrong magic, unknown byte order, bad rate or scale factors,
        UTC time tags, non-zero time tag bias.
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            raw = fh.read(_IMR_HEADER_SIZE)
    except FileNotFoundError as exc:
        raise InputError("file not found", path=path) from exc
    if len(raw) < _IMR_HEADER_SIZE:
        raise InputError("short IMR header", path=path, expected=f"{_IMR_HEADER_SIZE} bytes",
                         found=f"{len(raw)} bytes", record_kind="record")
    if raw[:8] != _IMR_MAGIC:
        raise InputError("not an IMR file", path=path, field="szHeader", expected=repr(_IMR_MAGIC),
                         found=repr(raw[:8]))
    order = raw[8]
    if order not in (0, 1):
        raise InputError("unknown byte order flag", path=path, field="bIsIntelOrMotorola",
                         expected="0 (Intel) or 1 (Motorola)", found=str(order))
    h = np.frombuffer(raw, dtype=_imr_header_dtype(">" if order else "<"), count=1)[0]
    rate, gs, acs = float(h["dDataRateHz"]), float(h["dGyroScaleFactor"]), float(h["dAccelScaleFactor"])
    for name, value in (("dDataRateHz", rate), ("dGyroScaleFactor", gs), ("dAccelScaleFactor", acs)):
        if not (np.isfinite(value) and value > 0):
            raise InputError("invalid header value", path=path, field=name, expected="a positive number",
                             found=f"{value:g}")
    if int(h["iUtcOrGpsTime"]) == 1:
        raise InputError("UTC time tags are not supported", path=path, field="iUtcOrGpsTime",
                         expected="0 or 2 (GPS time)", found="1 (UTC)")
    if float(h["dTimeTagBias"]) != 0.0:
        raise InputError("non-zero time tag bias is not supported", path=path, field="dTimeTagBias",
                         expected="0.0", found=f"{float(h['dTimeTagBias']):g}")
    return ImrHeader(
        version=float(h["dVersionNumber"]), delta_theta=bool(h["bDeltaTheta"]),
        delta_velocity=bool(h["bDeltaVelocity"]), rate_hz=rate, gyro_scale=gs, accel_scale=acs,
        utc_or_gps_time=int(h["iUtcOrGpsTime"]), rcv_or_corr_time=int(h["iRcvTimeOrCorrTime"]),
        time_tag_bias_s=float(h["dTimeTagBias"]),
        imu_name=bytes(h["szImuName"]).split(b"\0")[0].decode("latin-1"),
        program_name=bytes(h["szProgramName"]).split(b"\0")[0].decode("latin-1"),
        lever_arm_valid=bool(h["bLeverArmValid"]),
        lever_arm_raw=(int(h["lXoffset"]), int(h["lYoffset"]), int(h["lZoffset"])),
        big_endian=bool(order),
    )


def read_imr(
    path: PathLike,
    gps_week: int | None = None,
    *,
    max_gyro_rad_s: float = 50.0,
    max_acc_m_s2: float = 500.0,
    max_gap_factor: float = 1.5,
) -> ImuData:
    """Read an Inertial Explorer ``.imr`` file into FRD rates (see the module docstring).

    Parameters
    ----------
    gps_week
        GPS week of the first record; times become ``week * 604800 + seconds of
        week`` (week rollovers inside the file are undone). Without it the
        times must already be absolute GPS seconds (>= 604800).

    Raises
    ------
    InputError
        Header problems (:func:`read_imr_header`), a truncated record (its
        1-based number), no records, seconds of week without ``gps_week``,
        non-increasing time, implausible values.
    """
    path = Path(path)
    header = read_imr_header(path)
    rec_dtype = _imr_record_dtype(">" if header.big_endian else "<")
    size = path.stat().st_size - _IMR_HEADER_SIZE
    n, rest = divmod(size, rec_dtype.itemsize)
    if rest:
        raise InputError("truncated record", path=path, line=n + 1, record_kind="record",
                         expected=f"{rec_dtype.itemsize} bytes", found=f"{rest} bytes")
    if n == 0:
        raise InputError("no IMU records", path=path, expected="at least one record", found="none")
    rec = np.fromfile(path, dtype=rec_dtype, offset=_IMR_HEADER_SIZE, count=n)
    numbers = np.arange(1, n + 1)
    tag = rec["time"].astype(np.float64)
    if not np.all(np.isfinite(tag)):
        i = int(np.flatnonzero(~np.isfinite(tag))[0])
        raise InputError("non-finite time", path=path, line=i + 1, field="time", record_kind="record",
                         expected="a finite time", found=f"{tag[i]}")
    if gps_week is not None:
        t = gps_week * SECONDS_PER_WEEK + unwrap_seconds_of_week(tag)
    elif tag[0] >= SECONDS_PER_WEEK:
        t = tag
    else:
        raise InputError("time tags are seconds of week; the GPS week is needed", path=path, field="time",
                         expected="gps_week argument", found=f"{tag[0]:.3f} s of week")
    raise_if_not_increasing(path, t, numbers, "time", "record", formatter=lambda x: f"{x:.6f}")

    ints = np.stack([rec[f] for f in _IMR_FIELDS], axis=1).astype(np.float64)
    g_deg = ints[:, :3] * header.gyro_scale  # deg or deg/s, RFU
    a_raw = ints[:, 3:] * header.accel_scale  # m/s or m/s², RFU
    g = np.radians(g_deg) @ R_FRD_RFU.T
    a = a_raw @ R_FRD_RFU.T
    dt = sample_intervals(t, header.rate_hz, max_gap_factor)[:, None]
    if header.delta_theta:
        g = g / dt
    if header.delta_velocity:
        a = a / dt
    kind = "increments" if (header.delta_theta or header.delta_velocity) else "rates"
    _check_magnitudes(path, g, a, numbers, _IMR_FIELDS, max_gyro_rad_s, max_acc_m_s2, "record")
    _log.info("read %d IMR records (%s, %.1f Hz, IMU %r) from %s", n, kind, header.rate_hz, header.imu_name, path)
    return ImuData(t, g, a, header.rate_hz, kind)


def _auto_scale(values: np.ndarray) -> float:
    """Smallest power of ten with ``max|values| / scale`` inside int32 (with margin)."""
    peak = float(np.max(np.abs(values))) if values.size else 0.0
    return 10.0 ** np.ceil(np.log10(max(peak / 2.0e9, 1e-15)))


def write_imr(
    path: PathLike,
    data: ImuData,
    gps_week: int | None = None,
    *,
    delta: bool = True,
    gyro_scale: float | None = None,
    accel_scale: float | None = None,
    imu_name: str = "Georefine",
    max_gap_factor: float = 1.5,
    protect: tuple[PathLike, ...] = (),
) -> Path:
    """Write ``data`` as a little-endian IMR file (RFU axes, GPS seconds of week), atomically.

    Parameters
    ----------
    gps_week
        Week the time tags refer to; default: the week of the first sample.
        Tags are ``time_gps - week * 604800`` (they exceed 604800 after a week
        boundary rather than rolling over).
    delta
        Write increments (deg, m/s; ``bDeltaTheta = bDeltaVelocity = 1``) or rates.
    gyro_scale, accel_scale
        Header scale factors (deg or deg/s per count; m/s or m/s² per count);
        default: the finest power of ten that fits the data into int32.
        The quantisation error is at most half a count.
    """
    week = int(week_from_gps_seconds(data.time_gps[0])[0]) if gps_week is None else int(gps_week)
    if delta:
        dth, dv = data.increments(max_gap_factor)
        g, a = np.degrees(dth), dv
    else:
        g, a = np.degrees(data.gyro), data.acc
    g, a = g @ R_FRD_RFU, a @ R_FRD_RFU  # FRD -> RFU (R is symmetric and orthogonal)
    gs = gyro_scale or _auto_scale(g)
    acs = accel_scale or _auto_scale(a)
    counts = np.round(np.column_stack([g / gs, a / acs]))
    if np.any(np.abs(counts) > np.iinfo(np.int32).max):
        raise ValueError("IMR scale factor too small: values overflow int32")
    header = np.zeros(1, dtype=_imr_header_dtype("<"))
    header["szHeader"] = _IMR_MAGIC
    header["dVersionNumber"] = 8.80
    header["bDeltaTheta"] = header["bDeltaVelocity"] = int(delta)
    header["dDataRateHz"] = data.rate_hz
    header["dGyroScaleFactor"], header["dAccelScaleFactor"] = gs, acs
    header["iUtcOrGpsTime"], header["iRcvTimeOrCorrTime"] = 2, 2
    header["szImuName"] = imu_name.encode("latin-1")[:31]
    header["szProgramName"] = b"Georefine"
    rec = np.empty(len(data), dtype=_imr_record_dtype("<"))
    rec["time"] = data.time_gps - week * SECONDS_PER_WEEK
    for k, f in enumerate(_IMR_FIELDS):
        rec[f] = counts[:, k].astype(np.int32)
    with atomic_output(path, "wb", protect=protect) as fh:
        fh.write(header.tobytes())
        fh.write(rec.tobytes())
    return Path(path)
