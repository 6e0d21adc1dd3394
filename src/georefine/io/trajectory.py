"""Trajectory files: Applanix SBET (binary) and a documented trajectory CSV.

SBET (smoothed best estimate of trajectory)
    Headerless sequence of 136-byte records, 17 little-endian float64 each, in
    this order (verified against public SBET readers found by code search, e.g.
    the field list of G. Rice's ``sbet.py``: time, latitude, longitude,
    altitude, x_vel, y_vel, z_vel, roll, pitch, platform_heading, wander_angle,
    x_acceleration, y_acceleration, z_acceleration, x_angular_rate,
    y_angular_rate, z_angular_rate):

    ====  ==================  ===============================================
    0     time                GPS seconds of week (or absolute GPS seconds)
    1-3   lat, lon, alt       WGS84, rad, rad, m (ellipsoidal height)
    4-6   x/y/z velocity      m/s in the wander frame; with wander angle 0:
                              north, east, down
    7-9   roll, pitch,        rad; NED Euler angles (Z-Y-X), heading from
          platform heading    true north
    10    wander angle        rad
    11-13 x/y/z acceleration  m/s², body frame (x forward, y right, z down)
    14-16 x/y/z angular rate  rad/s, body frame
    ====  ==================  ===============================================

    Time handling (:func:`read_sbet`): if the first time is >= 604800 s the
    times are absolute GPS seconds; otherwise they are seconds of the week and
    ``gps_week`` must be given (week rollovers inside the file are undone).
    Georefine writes the body rows as specific force ``f_ib_b`` and angular
    rate ``omega_ib_b`` and always wander angle 0.

Trajectory CSV
    Columns ``time,x,y,z,roll_deg,pitch_deg,heading_deg`` then optionally
    ``sigma_x_m,sigma_y_m,sigma_z_m`` and/or
    ``sigma_roll_mdeg,sigma_pitch_mdeg,sigma_heading_mdeg``.
    ``time``: GPS seconds; ``x,y,z``: position of the IMU (body origin) in the
    output CRS (metres; easting, northing, ellipsoidal height for a projected
    CRS); roll/pitch/heading: NED Euler angles (Z-Y-X) in degrees, heading from
    true north (not grid north), in [0, 360). Comment lines start with ``#``;
    the writer records the CRS as ``# crs: <text>``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

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

__all__ = ["SbetData", "read_sbet", "write_sbet", "TrajectoryTable", "read_trajectory_csv",
           "write_trajectory_csv", "SBET_FIELDS", "SBET_RECORD_SIZE"]

_log = logging.getLogger(__name__)

SBET_FIELDS = ("time", "latitude", "longitude", "altitude", "x_velocity", "y_velocity", "z_velocity",
               "roll", "pitch", "platform_heading", "wander_angle", "x_acceleration", "y_acceleration",
               "z_acceleration", "x_angular_rate", "y_angular_rate", "z_angular_rate")
_SBET_DTYPE = np.dtype([(name, "<f8") for name in SBET_FIELDS])
SBET_RECORD_SIZE = _SBET_DTYPE.itemsize  # 136 bytes


def _as(arr, shape: tuple[int, ...], name: str) -> np.ndarray:
    a = np.ascontiguousarray(arr, dtype=np.float64)
    if a.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains non-finite values")
    return a


@dataclass(frozen=True)
class SbetData:
    """SBET records as arrays (see the module docstring for frames and units).

    Attributes
    ----------
    time_gps
        (N,) GPS seconds, strictly increasing.
    lat_rad, lon_rad, h_m
        (N,) WGS84 latitude, longitude (rad) and ellipsoidal height (m).
    velocity_wander
        (N,3) velocity in the wander frame, m/s (north, east, down if the wander angle is 0).
    roll_rad, pitch_rad, heading_rad
        (N,) NED Euler angles, rad.
    wander_rad
        (N,) wander angle, rad.
    accel_b
        (N,3) body-frame acceleration row of the file, m/s² (Georefine writes ``f_ib_b``).
    angular_rate_b
        (N,3) body-frame angular rate, rad/s (Georefine writes ``omega_ib_b``).
    """

    time_gps: np.ndarray
    lat_rad: np.ndarray
    lon_rad: np.ndarray
    h_m: np.ndarray
    velocity_wander: np.ndarray
    roll_rad: np.ndarray
    pitch_rad: np.ndarray
    heading_rad: np.ndarray
    wander_rad: np.ndarray
    accel_b: np.ndarray
    angular_rate_b: np.ndarray

    def __post_init__(self) -> None:
        t = np.asarray(self.time_gps)
        if t.ndim != 1:
            raise ValueError(f"time_gps must be 1-D, got shape {t.shape}")
        n = t.shape[0]
        for name in ("time_gps", "lat_rad", "lon_rad", "h_m", "roll_rad", "pitch_rad", "heading_rad", "wander_rad"):
            object.__setattr__(self, name, _as(getattr(self, name), (n,), name))
        for name in ("velocity_wander", "accel_b", "angular_rate_b"):
            object.__setattr__(self, name, _as(getattr(self, name), (n, 3), name))
        if n > 1 and np.any(np.diff(self.time_gps) <= 0):
            raise ValueError("time_gps must be strictly increasing")
        if np.any(np.abs(self.lat_rad) > np.pi / 2):
            raise ValueError("lat_rad must be within [-pi/2, pi/2]")

    def __len__(self) -> int:
        return self.time_gps.shape[0]

    def velocity_ned(self) -> np.ndarray:
        """(N,3) north-east-down velocity, m/s; only for wander angle 0.

        Raises
        ------
        ValueError
            If any wander angle is non-zero (its sign convention is not verified).
        """
        if np.any(self.wander_rad != 0.0):
            raise ValueError("velocity_ned needs wander angle 0; this SBET uses a wander-azimuth frame")
        return self.velocity_wander.copy()


def read_sbet(path: PathLike, gps_week: int | None = None) -> SbetData:
    """Read an SBET file (little-endian, 17 float64 per record).

    Parameters
    ----------
    gps_week
        GPS week for files whose time is seconds of the week.

    Raises
    ------
    InputError
        File size not a multiple of 136 bytes (names the incomplete record), no
        records, non-finite values (record and field), seconds of week without
        ``gps_week``, non-increasing time (record and both times).
    """
    path = Path(path)
    try:
        size = path.stat().st_size
    except FileNotFoundError as exc:
        raise InputError("file not found", path=path) from exc
    n, rest = divmod(size, SBET_RECORD_SIZE)
    if rest:
        raise InputError("incomplete record", path=path, line=n + 1, record_kind="record",
                         expected=f"{SBET_RECORD_SIZE} bytes per record", found=f"{rest} bytes")
    if n == 0:
        raise InputError("no SBET records", path=path, expected="at least one record", found="empty file")
    rec = np.fromfile(path, dtype=_SBET_DTYPE, count=n)
    values = rec.view("<f8").reshape(n, 17)
    bad = ~np.isfinite(values)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise InputError("non-finite value", path=path, line=int(i) + 1, field=SBET_FIELDS[j],
                         record_kind="record", expected="a finite number", found=f"{values[i, j]}")
    tag = values[:, 0]
    if tag[0] >= SECONDS_PER_WEEK:
        t = tag.copy()
    elif gps_week is not None:
        t = gps_week * SECONDS_PER_WEEK + unwrap_seconds_of_week(tag)
    else:
        raise InputError("time is seconds of week; the GPS week is needed", path=path, field="time",
                         record_kind="record", line=1, expected="gps_week argument", found=f"{tag[0]:.3f} s of week")
    raise_if_not_increasing(path, t, np.arange(1, n + 1), "time", "record", formatter=lambda x: f"{x:.6f}")
    lat = values[:, 1]
    if np.any(np.abs(lat) > np.pi / 2):
        i = int(np.flatnonzero(np.abs(lat) > np.pi / 2)[0])
        raise InputError("latitude out of range", path=path, line=i + 1, field="latitude", record_kind="record",
                         expected="|latitude| <= pi/2 rad", found=f"{lat[i]:.6g} rad")
    _log.info("read %d SBET records from %s", n, path)
    return SbetData(
        time_gps=t, lat_rad=lat, lon_rad=values[:, 2], h_m=values[:, 3], velocity_wander=values[:, 4:7],
        roll_rad=values[:, 7], pitch_rad=values[:, 8], heading_rad=values[:, 9], wander_rad=values[:, 10],
        accel_b=values[:, 11:14], angular_rate_b=values[:, 14:17],
    )


def write_sbet(
    path: PathLike, data: SbetData, time_scale: str = "week", *, protect: tuple[PathLike, ...] = ()
) -> Path:
    """Write ``data`` as an SBET file, atomically.

    Parameters
    ----------
    time_scale
        ``"week"``: seconds of the week of the first record (continuing past
        604800 s instead of rolling over); ``"gps"``: absolute GPS seconds.
    """
    if time_scale == "week":
        week = int(week_from_gps_seconds(data.time_gps[0])[0]) if len(data) else 0
        t = data.time_gps - week * SECONDS_PER_WEEK
    elif time_scale == "gps":
        t = data.time_gps
    else:
        raise ValueError(f"time_scale must be 'week' or 'gps', got {time_scale!r}")
    values = np.column_stack([
        t, data.lat_rad, data.lon_rad, data.h_m, data.velocity_wander, data.roll_rad, data.pitch_rad,
        data.heading_rad, data.wander_rad, data.accel_b, data.angular_rate_b,
    ]).astype("<f8")
    with atomic_output(path, "wb", protect=protect) as fh:
        fh.write(np.ascontiguousarray(values).tobytes())
    return Path(path)


# ---------------------------------------------------------------------------
# Trajectory CSV
# ---------------------------------------------------------------------------

_CSV_REQUIRED = ("time", "x", "y", "z", "roll_deg", "pitch_deg", "heading_deg")
_CSV_SIGMA_POS = ("sigma_x_m", "sigma_y_m", "sigma_z_m")
_CSV_SIGMA_ATT = ("sigma_roll_mdeg", "sigma_pitch_mdeg", "sigma_heading_mdeg")


@dataclass(frozen=True)
class TrajectoryTable:
    """Trajectory in an output CRS with NED attitude (see the module docstring).

    Attributes
    ----------
    time_gps
        (N,) GPS seconds, strictly increasing.
    xyz
        (N,3) position in the output CRS, m.
    rpy_rad
        (N,3) roll, pitch, heading (NED, Z-Y-X), rad.
    sigma_xyz_m
        (N,3) position standard deviations, m, or None.
    sigma_rpy_rad
        (N,3) attitude standard deviations, rad, or None.
    crs
        The output CRS as text (e.g. "EPSG:25832"), or None.
    """

    time_gps: np.ndarray
    xyz: np.ndarray
    rpy_rad: np.ndarray
    sigma_xyz_m: np.ndarray | None = None
    sigma_rpy_rad: np.ndarray | None = None
    crs: str | None = None

    def __post_init__(self) -> None:
        t = np.asarray(self.time_gps)
        if t.ndim != 1:
            raise ValueError(f"time_gps must be 1-D, got shape {t.shape}")
        n = t.shape[0]
        object.__setattr__(self, "time_gps", _as(t, (n,), "time_gps"))
        for name in ("xyz", "rpy_rad", "sigma_xyz_m", "sigma_rpy_rad"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, _as(value, (n, 3), name))
        if n > 1 and np.any(np.diff(self.time_gps) <= 0):
            raise ValueError("time_gps must be strictly increasing")

    def __len__(self) -> int:
        return self.time_gps.shape[0]


def read_trajectory_csv(path: PathLike) -> TrajectoryTable:
    """Read a trajectory CSV (columns in the module docstring).

    Raises
    ------
    InputError
        Missing/unknown/incomplete columns (header line), bad value (line and
        field), non-increasing time, negative sigma, no rows.
    """
    path = Path(path)
    lines = read_text_lines(path)
    crs = None
    for s in lines:
        if s.startswith("#") and s[1:].strip().lower().startswith("crs:"):
            crs = s[1:].strip()[4:].strip() or None
            break
    rows, numbers = data_lines(lines, 0)
    if not rows:
        raise InputError("no trajectory rows", path=path, expected="a header and data lines", found="none")
    header_line = int(numbers[0])
    header = tuple(t.strip() for t in rows[0].split(","))
    groups = [g for g in (_CSV_SIGMA_POS, _CSV_SIGMA_ATT) if g[0] in header or any(c in header for c in g)]
    expected = _CSV_REQUIRED + tuple(c for g in groups for c in g)
    if header != expected:
        raise InputError(
            "unexpected trajectory CSV header", path=path, line=header_line,
            expected=repr(",".join(expected)) + f" (required {','.join(_CSV_REQUIRED)}; optional groups "
            f"{','.join(_CSV_SIGMA_POS)} and {','.join(_CSV_SIGMA_ATT)})",
            found=repr(rows[0]),
        )
    rows, numbers = rows[1:], numbers[1:]
    if not rows:
        raise InputError("no trajectory rows", path=path, expected="data lines after the header", found="none")
    v = parse_float_rows(path, rows, numbers, header, delimiter=",")
    raise_if_not_increasing(path, v[:, 0], numbers, "time")
    if v.shape[1] > 7:
        neg = v[:, 7:] < 0
        if neg.any():
            i, j = np.argwhere(neg)[0]
            raise InputError("negative standard deviation", path=path, line=int(numbers[i]), field=header[7 + j],
                             expected=">= 0", found=f"{v[i, 7 + j]:g}")
    sig_pos = sig_att = None
    col = 7
    for g in groups:
        block = v[:, col:col + 3]
        if g is _CSV_SIGMA_POS:
            sig_pos = block
        else:
            sig_att = np.radians(block / 1000.0)
        col += 3
    return TrajectoryTable(v[:, 0], v[:, 1:4], np.radians(v[:, 4:7]), sig_pos, sig_att, crs)


def write_trajectory_csv(
    path: PathLike, table: TrajectoryTable, *, protect: tuple[PathLike, ...] = ()
) -> Path:
    """Write a trajectory CSV, atomically.

    Formats: time ``%.6f``, x/y/z ``%.4f``, angles ``%.8f`` deg (heading wrapped
    to [0, 360)), sigmas ``%.5f`` m / ``%.4f`` mdeg.
    """
    rpy = np.degrees(table.rpy_rad)
    rpy[:, 2] = np.mod(rpy[:, 2], 360.0)
    rpy[:, 2][rpy[:, 2] >= 360.0] = 0.0  # mod can round up to exactly 360
    columns, blocks = list(_CSV_REQUIRED), [table.time_gps, table.xyz, rpy]
    fmts = ["%.6f"] + ["%.4f"] * 3 + ["%.8f"] * 3
    if table.sigma_xyz_m is not None:
        columns += _CSV_SIGMA_POS
        blocks.append(table.sigma_xyz_m)
        fmts += ["%.5f"] * 3
    if table.sigma_rpy_rad is not None:
        columns += _CSV_SIGMA_ATT
        blocks.append(np.degrees(table.sigma_rpy_rad) * 1000.0)
        fmts += ["%.4f"] * 3
    fmt = ",".join(fmts) + "\n"
    values = np.column_stack(blocks)
    with atomic_output(path, "w", protect=protect) as fh:
        fh.write("# Georefine trajectory: time = GPS s; x,y,z = IMU position in the output CRS (m); "
                 "roll/pitch/heading = NED Z-Y-X Euler angles (deg, heading from true north)\n")
        if table.crs:
            fh.write(f"# crs: {table.crs}\n")
        fh.write(",".join(columns) + "\n")
        fh.writelines(fmt % tuple(r) for r in values.tolist())
    return Path(path)
