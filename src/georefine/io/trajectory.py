"""Trajectory files: Applanix SBET (binary), its companion file and POSPac accuracy file.

The trajectory CSV is in :mod:`georefine.io.trajectory_csv`.

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
    times are absolute GPS seconds; otherwise they are seconds of the week
    (week rollovers inside the file are undone) and the week comes from the
    ``gps_week`` argument or from the SBET's companion file; without either the
    reader refuses. Georefine writes the body rows as specific force ``f_ib_b``
    and angular rate ``omega_ib_b`` and always wander angle 0.

SBET companion file (``<name>.json`` beside the SBET, e.g. ``trajectory.sbet.json``)
    Georefine writes SBETs in seconds of the GPS week, as POSPac and Inertial
    Explorer do, and states the week beside them in a small JSON file:
    ``{"format": ..., "time": "GPS seconds of week", "gps_week": 2314,
    "output_crs": "EPSG:25832", "accuracy_file": "smrmsg_trajectory.out"}``.
    ``gps_week`` is the week the times count from (the week of the first
    record; times continue past 604800 s instead of rolling over);
    ``output_crs`` (optional) the project's output CRS, which
    ``georefine export trajectory`` takes by default; ``accuracy_file``
    (optional) the name of the accuracy file written beside it. The readers
    take the week from it (:func:`read_sbet_companion`); other tools ignore it.

Accuracy file (POSPac ``smrmsg``; :func:`read_smrmsg`, :func:`write_smrmsg`)
    Headerless 80-byte records of 10 little-endian float64: time (GPS seconds
    of week), north, east, down position RMS (m), north, east, down velocity
    RMS (m/s), roll, pitch, heading RMS (arc minutes). The layout and units
    are those of the open-source readers of POSPac's ``smrmsg_<name>.out``
    (PDAL's ``readers.smrmsg``, 10 doubles per point; the ``AccuracyEvent``
    record of public SBET tools: "seconds of week", metres, metres/second,
    arc minutes). Georefine names it after the SBET the POSPac way
    (:func:`smrmsg_path`): ``sbet_<name>.out`` -> ``smrmsg_<name>.out``, any
    other SBET name -> ``smrmsg_<stem>.out`` (``trajectory.sbet`` ->
    ``smrmsg_trajectory.out``).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from georefine.errors import InputError
from georefine.io.files import (
    SECONDS_PER_WEEK,
    PathLike,
    atomic_output,
    finite_array,
    raise_if_not_increasing,
    unwrap_seconds_of_week,
    week_from_gps_seconds,
)

__all__ = ["SbetData", "read_sbet", "write_sbet", "SBET_FIELDS", "SBET_RECORD_SIZE", "SbetCompanion", "sbet_companion_path",
           "read_sbet_companion", "write_sbet_companion", "SmrmsgData", "read_smrmsg", "write_smrmsg",
           "smrmsg_path", "SMRMSG_FIELDS", "SMRMSG_RECORD_SIZE"]

_log = logging.getLogger(__name__)

SBET_FIELDS = ("time", "latitude", "longitude", "altitude", "x_velocity", "y_velocity", "z_velocity",
               "roll", "pitch", "platform_heading", "wander_angle", "x_acceleration", "y_acceleration",
               "z_acceleration", "x_angular_rate", "y_angular_rate", "z_angular_rate")
SBET_RECORD_SIZE = 8 * len(SBET_FIELDS)  # 136 bytes: little-endian float64 (_read_float64_records)


def _read_float64_records(path: Path, fields: tuple[str, ...], what: str, unit: str) -> np.ndarray:
    """``(n, len(fields))`` little-endian float64 records of a binary file (SBET, smrmsg).

    Raises :class:`InputError` for a missing file, a size that is not whole records (naming the
    incomplete one), no records (``what``), and the first non-finite value (record and field).
    """
    size_record = 8 * len(fields)
    try:
        size = path.stat().st_size
    except FileNotFoundError as exc:
        raise InputError("file not found", path=path) from exc
    n, rest = divmod(size, size_record)
    if rest:
        raise InputError("incomplete record", path=path, line=n + 1, record_kind="record",
                         expected=f"{size_record} {unit}", found=f"{rest} bytes")
    if n == 0:
        raise InputError(f"no {what}", path=path, expected="at least one record", found="empty file")
    values = np.fromfile(path, dtype="<f8", count=n * len(fields)).reshape(n, len(fields))
    bad = ~np.isfinite(values)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise InputError("non-finite value", path=path, line=int(i) + 1, field=fields[j],
                         record_kind="record", expected="a finite number", found=f"{values[i, j]}")
    return values


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
            object.__setattr__(self, name, finite_array(getattr(self, name), (n,), name))
        for name in ("velocity_wander", "accel_b", "angular_rate_b"):
            object.__setattr__(self, name, finite_array(getattr(self, name), (n, 3), name))
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
        GPS week for files whose time is seconds of the week. Without it the
        week of the SBET's companion file (:func:`read_sbet_companion`) is used.

    Raises
    ------
    InputError
        File size not a multiple of 136 bytes (names the incomplete record), no
        records, non-finite values (record and field), seconds of week without
        ``gps_week`` or companion file, a ``gps_week`` that contradicts the
        companion file, a bad companion file, non-increasing time (record and
        both times).
    """
    path = Path(path)
    values = _read_float64_records(path, SBET_FIELDS, "SBET records", "bytes per record")
    n = values.shape[0]
    tag = values[:, 0]
    if tag[0] >= SECONDS_PER_WEEK:
        t = tag.copy()
    else:
        week = _week_of_sbet(path, gps_week, float(tag[0]))
        t = week * SECONDS_PER_WEEK + unwrap_seconds_of_week(tag)
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
# SBET companion file (the GPS week of an SBET in seconds of week)
# ---------------------------------------------------------------------------

_COMPANION_FORMAT = "Applanix SBET: 136-byte records of 17 little-endian float64 (time, latitude, longitude, ...)"
_COMPANION_TIME = "GPS seconds of week"


@dataclass(frozen=True)
class SbetCompanion:
    """What the companion file ``<sbet>.json`` states about an SBET (module docstring).

    Attributes
    ----------
    gps_week
        GPS week the SBET's seconds of week count from.
    output_epsg
        EPSG code of the project's output CRS, or None.
    accuracy_file
        File name of the accuracy file (``smrmsg``) beside the SBET, or None.
    """

    gps_week: int
    output_epsg: int | None = None
    accuracy_file: str | None = None


def sbet_companion_path(sbet_path: PathLike) -> Path:
    """The companion file of an SBET: its name plus ``.json`` (``trajectory.sbet.json``)."""
    p = Path(sbet_path)
    return p.with_name(p.name + ".json")


def write_sbet_companion(
    sbet_path: PathLike, companion: SbetCompanion, *, protect: tuple[PathLike, ...] = ()
) -> Path:
    """Write the companion file of ``sbet_path``, atomically; returns its path."""
    path = sbet_companion_path(sbet_path)
    data: dict = {"format": _COMPANION_FORMAT, "time": _COMPANION_TIME, "gps_week": int(companion.gps_week)}
    if companion.output_epsg is not None:
        data["output_crs"] = f"EPSG:{int(companion.output_epsg)}"
    if companion.accuracy_file is not None:
        data["accuracy_file"] = companion.accuracy_file
    with atomic_output(path, "w", protect=protect) as fh:
        json.dump(data, fh, indent=2)
        fh.write("\n")
    return path


def read_sbet_companion(sbet_path: PathLike) -> SbetCompanion | None:
    """The companion file of ``sbet_path``, or None if there is none.

    Raises
    ------
    InputError
        The file is not a JSON object, its ``time`` is not seconds of week, its ``gps_week``
        is not a whole number >= 0, ``output_crs`` is not ``EPSG:<code>`` or ``accuracy_file``
        is not a file name.
    """
    path = sbet_companion_path(sbet_path)
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError("unreadable SBET companion file", path=path, expected="a JSON object",
                         found=str(exc).splitlines()[0]) from None
    if not isinstance(data, dict):
        raise InputError("unreadable SBET companion file", path=path, expected="a JSON object",
                         found=type(data).__name__)
    if data.get("time", _COMPANION_TIME) != _COMPANION_TIME:
        raise InputError("unexpected time scale in the SBET companion file", path=path, field="time",
                         expected=repr(_COMPANION_TIME), found=repr(data.get("time")))
    week = data.get("gps_week")
    if isinstance(week, bool) or not isinstance(week, int) or week < 0:
        raise InputError("bad GPS week in the SBET companion file", path=path, field="gps_week",
                         expected="a whole number >= 0", found=repr(week))
    epsg = None
    crs = data.get("output_crs")
    if crs is not None:
        code = str(crs).upper().removeprefix("EPSG:")
        if not isinstance(crs, str) or not code.isdigit():
            raise InputError("bad output CRS in the SBET companion file", path=path, field="output_crs",
                             expected="'EPSG:<code>'", found=repr(crs))
        epsg = int(code)
    accuracy = data.get("accuracy_file")
    if accuracy is not None and (not isinstance(accuracy, str) or Path(accuracy).name != accuracy or not accuracy):
        raise InputError("bad accuracy file name in the SBET companion file", path=path, field="accuracy_file",
                         expected="a file name beside the SBET", found=repr(accuracy))
    return SbetCompanion(week, epsg, accuracy)


def _week_of_sbet(path: Path, gps_week: int | None, first: float) -> int:
    """The GPS week of an SBET in seconds of week: ``gps_week`` or its companion file's, which must agree."""
    companion = read_sbet_companion(path)
    if companion is not None and gps_week is not None and int(gps_week) != companion.gps_week:
        raise InputError("the GPS week given contradicts the SBET's companion file", path=sbet_companion_path(path),
                         field="gps_week", expected=f"{int(gps_week)} (given)", found=str(companion.gps_week))
    if gps_week is not None:
        return int(gps_week)
    if companion is not None:
        return companion.gps_week
    raise InputError("time is seconds of week; the GPS week is needed", path=path, field="time",
                     record_kind="record", line=1,
                     expected=f"a GPS week (gps_week argument, --gps-week, or {sbet_companion_path(path).name})",
                     found=f"{first:.3f} s of week")


# ---------------------------------------------------------------------------
# Accuracy file (POSPac smrmsg)
# ---------------------------------------------------------------------------

SMRMSG_FIELDS = ("time", "north_position_rms", "east_position_rms", "down_position_rms", "north_velocity_rms",
                 "east_velocity_rms", "down_velocity_rms", "roll_rms", "pitch_rms", "heading_rms")
SMRMSG_RECORD_SIZE = 8 * len(SMRMSG_FIELDS)  # 80 bytes
ARCMIN_PER_RAD = 180.0 * 60.0 / np.pi


@dataclass(frozen=True)
class SmrmsgData:
    """Accuracy records of an SBET (1-sigma; module docstring).

    Attributes
    ----------
    time_gps
        (N,) GPS seconds, strictly increasing.
    sigma_ned_m
        (N,3) north, east, down position RMS, m.
    sigma_velocity_ned_m_s
        (N,3) north, east, down velocity RMS, m/s.
    sigma_rph_rad
        (N,3) roll, pitch, heading RMS, rad.
    """

    time_gps: np.ndarray
    sigma_ned_m: np.ndarray
    sigma_velocity_ned_m_s: np.ndarray
    sigma_rph_rad: np.ndarray

    def __post_init__(self) -> None:
        t = np.asarray(self.time_gps)
        if t.ndim != 1:
            raise ValueError(f"time_gps must be 1-D, got shape {t.shape}")
        n = t.shape[0]
        object.__setattr__(self, "time_gps", finite_array(t, (n,), "time_gps"))
        for name in ("sigma_ned_m", "sigma_velocity_ned_m_s", "sigma_rph_rad"):
            value = finite_array(getattr(self, name), (n, 3), name)
            if np.any(value < 0):
                raise ValueError(f"{name} must not be negative")
            object.__setattr__(self, name, value)
        if n > 1 and np.any(np.diff(self.time_gps) <= 0):
            raise ValueError("time_gps must be strictly increasing")

    def __len__(self) -> int:
        return self.time_gps.shape[0]


def smrmsg_path(sbet_path: PathLike) -> Path:
    """The accuracy file beside an SBET, named the POSPac way (module docstring)."""
    p = Path(sbet_path)
    stem = p.stem[len("sbet_"):] if p.name.lower().startswith("sbet_") else p.stem
    return p.with_name(f"smrmsg_{stem}.out")


def write_smrmsg(
    path: PathLike, data: SmrmsgData, gps_week: int | None = None, *, protect: tuple[PathLike, ...] = ()
) -> Path:
    """Write ``data`` as an ``smrmsg`` accuracy file, atomically.

    Times are written as seconds of ``gps_week`` (default: the week of the first record),
    continuing past 604800 s instead of rolling over, like :func:`write_sbet`; angles in arc
    minutes.
    """
    week = (int(week_from_gps_seconds(data.time_gps[0])[0]) if len(data) else 0) if gps_week is None else gps_week
    values = np.column_stack([
        data.time_gps - week * SECONDS_PER_WEEK, data.sigma_ned_m, data.sigma_velocity_ned_m_s,
        data.sigma_rph_rad * ARCMIN_PER_RAD,
    ]).astype("<f8")
    with atomic_output(path, "wb", protect=protect) as fh:
        fh.write(np.ascontiguousarray(values).tobytes())
    return Path(path)


def read_smrmsg(path: PathLike, gps_week: int | None = None) -> SmrmsgData:
    """Read an ``smrmsg`` accuracy file (little-endian, 10 float64 per record).

    Parameters
    ----------
    gps_week
        GPS week of the times (seconds of week, as POSPac writes them); a file whose first
        time is >= 604800 s holds absolute GPS seconds and needs none.

    Raises
    ------
    InputError
        File size not a multiple of 80 bytes (names the incomplete record), no records,
        non-finite values (record and field), seconds of week without ``gps_week``, negative
        RMS (record and field), non-increasing time (record and both times).
    """
    path = Path(path)
    values = _read_float64_records(path, SMRMSG_FIELDS, "accuracy records", "bytes per record (10 float64)")
    n = values.shape[0]
    negative = values[:, 1:] < 0
    if negative.any():
        i, j = np.argwhere(negative)[0]
        raise InputError("negative RMS", path=path, line=int(i) + 1, field=SMRMSG_FIELDS[j + 1],
                         record_kind="record", expected=">= 0", found=f"{values[i, j + 1]:g}")
    tag = values[:, 0]
    if tag[0] >= SECONDS_PER_WEEK:
        t = tag.copy()
    elif gps_week is not None:
        t = int(gps_week) * SECONDS_PER_WEEK + unwrap_seconds_of_week(tag)
    else:
        raise InputError("time is seconds of week; the GPS week is needed", path=path, field="time",
                         record_kind="record", line=1, expected="a GPS week (that of the SBET it belongs to)",
                         found=f"{tag[0]:.3f} s of week")
    raise_if_not_increasing(path, t, np.arange(1, n + 1), "time", "record", formatter=lambda x: f"{x:.6f}")
    _log.info("read %d accuracy records from %s", n, path)
    return SmrmsgData(t, values[:, 1:4], values[:, 4:7], values[:, 7:10] / ARCMIN_PER_RAD)
