"""Trajectory exchange files for evaluation tools: TUM (evo) and trajectopy's ASCII format.

Both hold one pose per line: a time, a position and a unit quaternion ``qx qy qz qw`` (the
``xyzw`` order of docs/ARCHITECTURE.md §2, SciPy's, evo's and trajectopy's). Georefine writes
them from its SBETs and trajectory CSVs (:func:`poses_from_geodetic`,
``georefine export trajectory``) so that evo and trajectopy evaluate its trajectories as they
are, without an alignment.

Frame of the poses
    Position ``x, y, z`` of the IMU (body origin) in a stated CRS: a projected CRS (easting,
    northing, ellipsoidal height, m; the project's output CRS by default) or a geocentric one
    (ECEF X, Y, Z, m; e.g. EPSG:4978). The quaternion is the body attitude in the axes of
    those coordinates, ``R_c_b``: for a projected CRS ``c`` is the grid's east-north-up
    (x easting, y northing, z up), so ``R_c_b = R_grid_enu R_enu_ned R_n_b`` with the
    meridian convergence in ``R_grid_enu`` (the grid is conformal: true north lies at the
    convergence angle from grid north); for a geocentric CRS ``R_c_b = R_e_n R_n_b``. The body
    is Georefine's, x forward, y right, z down; ``R_n_b`` the NED roll, pitch and heading of
    the SBET. A pose is thus ``x_c = R_c_b x_b + p_c``, the form evo and trajectopy assume, and
    the angle of ``R_ref^T R_est`` they report is the angle of Georefine's ``Log(R_ref^T R_est)``
    (the frames of estimate and reference differ by the convergence change over their
    distance, ~1e-9 rad per cm). Position differences in grid coordinates differ from
    Georefine's north/east/down metres by the grid scale (UTM: 0.9996-1.0004).
TUM (``.tum``, evo's ``read_tum_trajectory_file``)
    ``timestamp tx ty tz qx qy qz qw``, separated by single spaces, one pose per line;
    lines starting with ``#`` are comments. Georefine's timestamp is absolute GPS seconds
    (since 1980-01-06 GPST); its comments state the CRS as ``# crs: EPSG:<code>`` (read back
    by :func:`read_tum`) and the conventions.
trajectopy (``.traj``; ``trajectopy.Trajectory.from_file``)
    Header lines ``#name``, ``#epsg <code>``, ``#nframe enu``, ``#sorting time``,
    ``#time_format gps_sow``, ``#gps_week <week>``, ``#fields t,px,py,pz,qx,qy,qz,qw``, then
    comma-separated rows. ``t`` is seconds of the GPS week ``#gps_week`` (continuing past
    604800 s rather than rolling over). ``#nframe enu`` tells trajectopy that the quaternion
    refers to east-north-up axes, which are the grid's for a projected ``#epsg``. Lines
    starting with ``#`` and a space are comments to trajectopy and Georefine alike.

Numbers are written with the shortest text that reads back to the same float64
(``repr``), so a file read back equals what was written.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from georefine.errors import InputError
from georefine.geometry import earth
from georefine.geometry.frames import OutputCRS
from georefine.geometry.rotation import R_n_b_from_rph, matrix_from_quat, quat_from_matrix, rph_from_R_n_b
from georefine.io.files import (
    SECONDS_PER_WEEK,
    PathLike,
    atomic_output,
    data_lines,
    parse_float_rows,
    raise_if_not_increasing,
    read_text_lines,
    week_from_gps_seconds,
)

__all__ = ["PoseTable", "poses_from_geodetic", "geodetic_from_poses", "write_tum", "read_tum",
           "write_trajectopy", "read_trajectopy", "write_poses", "POSE_FORMATS", "pose_crs"]

_log = logging.getLogger(__name__)

POSE_FORMATS = ("tum", "trajectopy")
"""The formats of :func:`write_poses`: evo's TUM and trajectopy's ASCII format."""

R_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
"""Maps north-east-down components to east-north-up (its own inverse)."""

_QUAT_NORM_TOLERANCE = 1e-6
_TUM_FIELDS = ("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
_TRAJECTOPY_FIELDS = ("t", "px", "py", "pz", "qx", "qy", "qz", "qw")


@dataclass(frozen=True)
class PoseTable:
    """Poses in a CRS with the body attitude as a quaternion (see the module docstring).

    Attributes
    ----------
    time_gps
        (N,) GPS seconds, strictly increasing.
    xyz
        (N,3) IMU position in the CRS ``epsg``, m.
    quat_xyzw
        (N,4) unit quaternions of ``R_c_b`` (body FRD in the CRS's axes), ``w >= 0``.
    epsg
        EPSG code of the CRS of ``xyz`` (projected or geocentric), or None if unknown.
    name
        Name of the trajectory (trajectopy's ``#name``).
    """

    time_gps: np.ndarray
    xyz: np.ndarray
    quat_xyzw: np.ndarray
    epsg: int | None = None
    name: str = "trajectory"

    def __post_init__(self) -> None:
        t = np.ascontiguousarray(self.time_gps, dtype=np.float64)
        if t.ndim != 1:
            raise ValueError(f"time_gps must be 1-D, got shape {t.shape}")
        n = t.shape[0]
        for name, value, width in (("time_gps", t, None), ("xyz", self.xyz, 3), ("quat_xyzw", self.quat_xyzw, 4)):
            a = np.ascontiguousarray(value, dtype=np.float64)
            if a.shape != ((n,) if width is None else (n, width)):
                raise ValueError(f"{name} must have shape ({n}{'' if width is None else f', {width}'}), got {a.shape}")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"{name} contains non-finite values")
            object.__setattr__(self, name, a)
        if n > 1 and np.any(np.diff(t) <= 0):
            raise ValueError("time_gps must be strictly increasing")
        if n and np.abs(np.linalg.norm(self.quat_xyzw, axis=1) - 1.0).max() > _QUAT_NORM_TOLERANCE:
            raise ValueError("quat_xyzw must be unit quaternions")
        if any(c in self.name for c in "\r\n"):
            raise ValueError("name must be one line")

    def __len__(self) -> int:
        return self.time_gps.shape[0]


# ---------------------------------------------------------------------------
# Frames
# ---------------------------------------------------------------------------


def pose_crs(epsg: int) -> OutputCRS:
    """The CRS of exported poses; projected or geocentric (a pose needs Cartesian axes).

    Raises
    ------
    InputError
        Unknown EPSG code, or a CRS that is neither projected nor geocentric (e.g. latitude
        and longitude in degrees, whose axes are not Cartesian).
    """
    crs = OutputCRS(int(epsg))
    try:
        c = crs.crs
    except Exception as exc:  # pyproj.exceptions.CRSError
        raise InputError("unknown CRS", field="epsg", expected="an EPSG code PROJ knows",
                         found=f"EPSG:{epsg} ({str(exc).splitlines()[0]})") from None
    if not (c.is_projected or c.is_geocentric):
        raise InputError("the poses need a projected or geocentric CRS", field="epsg",
                         expected="a projected CRS (e.g. EPSG:25832) or a geocentric one (EPSG:4978)",
                         found=f"EPSG:{epsg} ({c.name}, {c.type_name})")
    return crs


def _R_c_n(crs: OutputCRS, lat: np.ndarray, lon: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Rotations ``(n, 3, 3)`` from the local NED frame to the CRS's axes (module docstring)."""
    if crs.crs.is_geocentric:
        return earth.R_e_n(lat, lon)
    return crs.R_grid_enu(lat, lon, h) @ R_ENU_NED


def poses_from_geodetic(
    time_gps: np.ndarray, lat_rad: np.ndarray, lon_rad: np.ndarray, h_m: np.ndarray, rph_rad: np.ndarray,
    epsg: int, name: str = "trajectory",
) -> PoseTable:
    """Poses in ``epsg`` of geodetic WGS84 positions and NED roll, pitch, heading (rad).

    Raises
    ------
    InputError
        From :func:`pose_crs`.
    """
    crs = pose_crs(epsg)
    lat, lon, h = (np.asarray(a, dtype=float) for a in (lat_rad, lon_rad, h_m))
    rph = np.asarray(rph_rad, dtype=float).reshape(-1, 3)
    xyz = crs.from_geodetic(lat, lon, h).reshape(-1, 3)
    R_c_b = _R_c_n(crs, lat, lon, h) @ R_n_b_from_rph(rph[:, 0], rph[:, 1], rph[:, 2])
    return PoseTable(time_gps, xyz, quat_from_matrix(R_c_b), int(epsg), name)


def geodetic_from_poses(poses: PoseTable) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Latitude, longitude (rad), ellipsoidal height (m) and NED roll, pitch, heading (rad, ``(N, 3)``).

    The inverse of :func:`poses_from_geodetic`.

    Raises
    ------
    InputError
        The poses state no CRS, or one that :func:`pose_crs` refuses.
    """
    if poses.epsg is None:
        raise InputError("the poses state no CRS", field="epsg", expected="a CRS (# crs: EPSG:<code>, #epsg <code>)",
                         found="none")
    crs = pose_crs(poses.epsg)
    lat, lon, h = crs.to_geodetic(poses.xyz)
    R_n_b = np.swapaxes(_R_c_n(crs, lat, lon, h), 1, 2) @ matrix_from_quat(poses.quat_xyzw)
    return lat, lon, h, rph_from_R_n_b(R_n_b)


# ---------------------------------------------------------------------------
# Writing and reading
# ---------------------------------------------------------------------------


def _rows(columns: list[np.ndarray], delimiter: str) -> list[str]:
    """Rows of the shortest round-trip text of each float64."""
    values = np.column_stack(columns).tolist()
    return [delimiter.join(map(repr, row)) + "\n" for row in values]


def _conventions(poses: PoseTable) -> list[str]:
    if poses.epsg is None:
        frame = "x, y, z and the quaternion's axes: a Cartesian frame not stated"
    elif pose_crs(poses.epsg).crs.is_geocentric:
        frame = f"x, y, z: ECEF (EPSG:{poses.epsg}), m; quaternion R_e_b"
    else:
        frame = (f"x, y, z: easting, northing, ellipsoidal height (EPSG:{poses.epsg}), m; quaternion R_grid_b "
                 "in the grid's east-north-up axes (meridian convergence included)")
    return [f"# Georefine trajectory: IMU poses; {frame}; body x forward, y right, z down; "
            "quaternion order qx qy qz qw\n"]


def write_tum(path: PathLike, poses: PoseTable, *, protect: tuple[PathLike, ...] = ()) -> Path:
    """Write ``poses`` as a TUM file (evo), atomically; time in absolute GPS seconds."""
    with atomic_output(path, "w", protect=protect) as fh:
        fh.writelines(_conventions(poses))
        fh.write("# timestamp: GPS seconds since 1980-01-06 00:00:00 GPST\n")
        if poses.epsg is not None:
            fh.write(f"# crs: EPSG:{poses.epsg}\n")
        fh.write("# " + " ".join(_TUM_FIELDS) + "\n")
        fh.writelines(_rows([poses.time_gps, poses.xyz, poses.quat_xyzw], " "))
    return Path(path)


def _quaternions(path: Path, q: np.ndarray, numbers: np.ndarray) -> np.ndarray:
    """Unit quaternions with ``w >= 0``; InputError at the first one that is not of unit length."""
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > _QUAT_NORM_TOLERANCE)
    if bad.size:
        i = int(bad[0])
        raise InputError("not a unit quaternion", path=path, line=int(numbers[i]), field="qx qy qz qw",
                         expected=f"|q| = 1 within {_QUAT_NORM_TOLERANCE:g}", found=f"|q| = {norm[i]:.9g}")
    q = q / norm[:, None]
    return q * np.where(q[:, 3:4] < 0.0, -1.0, 1.0)


def _epsg_of(text: str, path: Path, line: int, field: str) -> int:
    code = text.strip().upper().removeprefix("EPSG:")
    if not code.isdigit():
        raise InputError("bad CRS", path=path, line=line, field=field, expected="an EPSG code", found=repr(text.strip()))
    return int(code)


def read_tum(path: PathLike) -> PoseTable:
    """Read a TUM file: ``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments.

    The CRS comes from a ``# crs: EPSG:<code>`` comment when there is one; the timestamps are
    taken as GPS seconds.

    Raises
    ------
    InputError
        No poses, a line without exactly 8 numbers (line and field), non-finite values,
        non-increasing time, a quaternion not of unit length (line), a bad ``# crs:`` line.
    """
    path = Path(path)
    lines = read_text_lines(path)
    epsg = None
    for i, s in enumerate(lines):
        text = s.strip()
        if text.startswith("#") and text[1:].strip().lower().startswith("crs:"):
            epsg = _epsg_of(text[1:].strip()[4:], path, i + 1, "crs")
            break
    rows, numbers = data_lines(lines, 0)
    if not rows:
        raise InputError("no poses", path=path, expected="lines 'timestamp tx ty tz qx qy qz qw'", found="none")
    v = parse_float_rows(path, rows, numbers, _TUM_FIELDS, delimiter=None)
    raise_if_not_increasing(path, v[:, 0], numbers, "timestamp")
    return PoseTable(v[:, 0], v[:, 1:4], _quaternions(path, v[:, 4:8], numbers), epsg, path.stem)


def write_trajectopy(path: PathLike, poses: PoseTable, *, protect: tuple[PathLike, ...] = ()) -> Path:
    """Write ``poses`` in trajectopy's ASCII format, atomically; time in seconds of the GPS week."""
    week = int(week_from_gps_seconds(poses.time_gps[0])[0]) if len(poses) else 0
    with atomic_output(path, "w", protect=protect) as fh:
        fh.writelines(_conventions(poses))
        fh.write(f"#name {poses.name}\n")
        if poses.epsg is not None:
            fh.write(f"#epsg {poses.epsg}\n")
        fh.write("#nframe enu\n#sorting time\n#time_format gps_sow\n")
        fh.write(f"#gps_week {week}\n")
        fh.write("#fields " + ",".join(_TRAJECTOPY_FIELDS) + "\n")
        fh.writelines(_rows([poses.time_gps - week * SECONDS_PER_WEEK, poses.xyz, poses.quat_xyzw], ","))
    return Path(path)


def read_trajectopy(path: PathLike) -> PoseTable:
    """Read a trajectopy ASCII file with the header :func:`write_trajectopy` writes.

    Reads ``#fields`` (``t``, ``px``, ``py``, ``pz``, ``qx``, ``qy``, ``qz``, ``qw`` in any order;
    other columns are skipped), ``#epsg``, ``#name``, ``#time_format`` (``gps_sow`` with
    ``#gps_week``, or ``unix``, whose seconds are taken as GPS seconds), ``#nframe`` (only
    ``enu``) and ``#delimiter``.

    Raises
    ------
    InputError
        A field missing from ``#fields``, an unsupported ``#time_format`` or ``#nframe``,
        ``gps_sow`` without ``#gps_week``, a bad ``#epsg``, no rows, a row without the
        listed number of values (line and field), non-finite values, non-increasing time, a
        quaternion not of unit length.
    """
    path = Path(path)
    lines = read_text_lines(path)
    header: dict[str, tuple[str, int]] = {}
    for i, s in enumerate(lines):
        text = s.strip()
        if text.startswith("#") and len(text) > 1 and not text[1].isspace():
            key, _, value = text[1:].partition(" ")
            header.setdefault(key.strip(), (value.strip(), i + 1))
    fields_text, fields_line = header.get("fields", (",".join(_TRAJECTOPY_FIELDS), 0))
    fields = [f.strip() for f in fields_text.split(",")]
    missing = [f for f in _TRAJECTOPY_FIELDS if f not in fields]
    if missing:
        raise InputError("missing trajectopy fields", path=path, line=fields_line or None, field="#fields",
                         expected=",".join(_TRAJECTOPY_FIELDS), found=fields_text)
    nframe, nframe_line = header.get("nframe", ("enu", 0))
    if nframe.lower() != "enu":
        raise InputError("unsupported navigation frame", path=path, line=nframe_line, field="#nframe",
                         expected="enu", found=nframe)
    time_format, tf_line = header.get("time_format", ("unix", 0))
    week = None
    if time_format.lower() == "gps_sow":
        if "gps_week" not in header:
            raise InputError("seconds of week without a GPS week", path=path, line=tf_line, field="#gps_week",
                             expected="#gps_week <week>", found="none")
        text, line = header["gps_week"]
        if not text.isdigit():
            raise InputError("bad GPS week", path=path, line=line, field="#gps_week", expected="a whole number >= 0",
                             found=repr(text))
        week = int(text)
    elif time_format.lower() != "unix":
        raise InputError("unsupported time format", path=path, line=tf_line, field="#time_format",
                         expected="gps_sow or unix", found=time_format)
    epsg = None
    if "epsg" in header:
        text, line = header["epsg"]
        epsg = _epsg_of(text, path, line, "#epsg") or None  # trajectopy's 0: a local, unknown system
    delimiter = ","
    if "delimiter" in header:
        text = header["delimiter"][0]
        delimiter = text[1] if len(text) == 3 and text[0] == text[2] and text[0] in "'\"" else delimiter
    rows, numbers = data_lines(lines, 0)
    if not rows:
        raise InputError("no poses", path=path, expected=f"rows of {fields_text}", found="none")
    v = parse_float_rows(path, rows, numbers, fields, delimiter=delimiter)
    col = {f: fields.index(f) for f in _TRAJECTOPY_FIELDS}
    t = v[:, col["t"]] + (0.0 if week is None else week * SECONDS_PER_WEEK)
    raise_if_not_increasing(path, t, numbers, "t")
    xyz = v[:, [col["px"], col["py"], col["pz"]]]
    q = _quaternions(path, v[:, [col["qx"], col["qy"], col["qz"], col["qw"]]], numbers)
    name = header.get("name", (path.stem, 0))[0] or path.stem
    return PoseTable(t, xyz, q, epsg, name)


def write_poses(path: PathLike, poses: PoseTable, fmt: str, *, protect: tuple[PathLike, ...] = ()) -> Path:
    """Write ``poses`` as ``fmt`` (one of :data:`POSE_FORMATS`)."""
    if fmt == "tum":
        return write_tum(path, poses, protect=protect)
    if fmt == "trajectopy":
        return write_trajectopy(path, poses, protect=protect)
    raise InputError("unknown trajectory format", field="format", expected=" or ".join(POSE_FORMATS), found=repr(fmt))
