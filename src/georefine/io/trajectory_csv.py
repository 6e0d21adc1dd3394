"""The trajectory CSV: a documented text table of the adjusted trajectory (with its sigmas).

Columns ``time,x,y,z,roll_deg,pitch_deg,heading_deg`` then optionally
``sigma_x_m,sigma_y_m,sigma_z_m`` and/or
``sigma_roll_mdeg,sigma_pitch_mdeg,sigma_heading_mdeg``.
``time``: GPS seconds; ``x,y,z``: position of the IMU (body origin) in the
output CRS (metres; easting, northing, ellipsoidal height for a projected
CRS); roll/pitch/heading: NED Euler angles (Z-Y-X) in degrees, heading from
true north (not grid north), in [0, 360). Comment lines start with ``#``;
the writer records the CRS as ``# crs: <text>`` and the GPS week of the
first row as ``# gps_week: <week>`` (the week the SBET beside it counts
its seconds from).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from georefine.errors import InputError
from georefine.io.files import (
    PathLike,
    atomic_output,
    data_lines,
    finite_array,
    parse_float_rows,
    raise_if_not_increasing,
    read_text_lines,
    week_from_gps_seconds,
)

__all__ = ["TrajectoryTable", "read_trajectory_csv", "write_trajectory_csv"]

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
        object.__setattr__(self, "time_gps", finite_array(t, (n,), "time_gps"))
        for name in ("xyz", "rpy_rad", "sigma_xyz_m", "sigma_rpy_rad"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, finite_array(value, (n, 3), name))
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
        if len(table):
            fh.write(f"# gps_week: {int(week_from_gps_seconds(table.time_gps[0])[0])}\n")
        fh.write(",".join(columns) + "\n")
        fh.writelines(fmt % tuple(r) for r in values.tolist())
    return Path(path)
