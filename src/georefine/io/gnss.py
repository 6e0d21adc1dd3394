"""RTKLIB ``.pos`` GNSS solution files (RTKPOST / rnx2rtkp output).

Layout (RTKLIB ``src/solution.c``: ``outsolheads``, ``outpos``, ``outecef``,
``decode_solllh``, ``decode_solxyz``)::

    % program   : RTKPOST ver.2.4.3
    % pos mode  : kinematic
    % (lat/lon/height=WGS84/ellipsoidal,Q=1:fix,2:float,3:sbas,4:dgps,5:single,6:ppp,ns=# of satellites)
    %  GPST          latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)  sdne(m)  sdeu(m)  sdun(m) age(s)  ratio
    2024/05/01 10:00:00.000   47.123456789   11.123456789   612.3456   1  12   0.0123 ...

* Time: ``YYYY/MM/DD HH:MM:SS.SSS`` (GPST calendar) or ``WEEK SECONDS_OF_WEEK``.
  Files in UTC or JST are rejected (converting them needs a leap-second table).
* Position: ``latitude(deg) longitude(deg) height(m)`` (WGS84, ellipsoidal
  height) or ``x-ecef(m) y-ecef(m) z-ecef(m)``. The ``d'"`` (dms) form and ENU
  baselines are rejected with a clear message.
* Then ``Q ns`` and standard deviations: ``sdn sde sdu sdne sdeu sdun`` (llh) or
  ``sdx sdy sdz sdxy sdyz sdzx`` (ecef), ``age(s) ratio``; velocity columns after
  them are ignored. Files that stop after ``sdu``/``sdz`` are accepted (the
  covariances, age and ratio are then 0).
* The off-diagonal columns are *signed square roots* of the covariances:
  RTKLIB writes ``sqvar(c) = sign(c) sqrt(|c|)`` and reads ``c = sign(s) s²``;
  so do :func:`read_pos` and :func:`write_pos`.

Covariance convention: the llh form gives the covariance in the local
east-north-up frame at the solution's own latitude/longitude; it is rotated into
ECEF as ``C_e = R_e_enu C_enu R_e_enuᵀ``, where the columns of ``R_e_enu`` are the
east, north and up unit vectors in ECEF (as RTKLIB's ``covecef``). Writing the
llh form applies the inverse rotation.

The in-memory solution is always held in ECEF (:class:`GnssSolution`); the
geodetic coordinates are derived with :mod:`georefine.geometry.earth` (WGS84, tested against pyproj).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from georefine.errors import InputError
from georefine.geometry import earth
from georefine.geometry.frames import LocalFrame
from georefine.io.files import (
    PathLike,
    atomic_output,
    calendar_from_gps_seconds,
    data_lines,
    days_in_month,
    gps_seconds_from_calendar,
    gps_seconds_from_week,
    parse_float_rows,
    raise_if_not_increasing,
    read_text_lines,
    rounded_time_units,
)

__all__ = ["GnssSolution", "read_pos", "write_pos", "enu_rotation", "gnss_in_w"]

_log = logging.getLogger(__name__)

_LLH_FIELDS = ("latitude(deg)", "longitude(deg)", "height(m)", "Q", "ns", "sdn(m)", "sde(m)", "sdu(m)",
               "sdne(m)", "sdeu(m)", "sdun(m)", "age(s)", "ratio")
_ECEF_FIELDS = ("x-ecef(m)", "y-ecef(m)", "z-ecef(m)", "Q", "ns", "sdx(m)", "sdy(m)", "sdz(m)",
                "sdxy(m)", "sdyz(m)", "sdzx(m)", "age(s)", "ratio")
_CAL_FIELDS = ("GPST year", "GPST month", "GPST day", "GPST hour", "GPST minute", "GPST second")
_WEEK_FIELDS = ("GPS week", "GPST seconds of week")
_MIN_FIELDS = 8  # position, Q, ns and the three standard deviations
_LEGEND = "Q=1:fix,2:float,3:sbas,4:dgps,5:single,6:ppp,ns=# of satellites"


# One implementation of the WGS84 conversions for the whole package (geometry.earth).
_geodetic_to_ecef = earth.geodetic_to_ecef
_ecef_to_geodetic = earth.ecef_to_geodetic
enu_rotation = earth.R_e_enu
"""``R_e_enu`` (N,3,3): columns are the east, north, up unit vectors in ECEF."""


def _sqvar(c: np.ndarray) -> np.ndarray:
    """RTKLIB's signed square root of a covariance: sign(c) sqrt(|c|)."""
    return np.sign(c) * np.sqrt(np.abs(c))


def _unsqvar(s: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_sqvar`: sign(s) s²."""
    return np.sign(s) * s * s


def _cov_from_columns(sd: np.ndarray, cross: np.ndarray, order: str) -> np.ndarray:
    """(N,3,3) covariance from standard deviations and signed-root cross terms.

    ``order="neu"``: sd = (sdn, sde, sdu), cross = (sdne, sdeu, sdun) -> ENU matrix.
    ``order="xyz"``: sd = (sdx, sdy, sdz), cross = (sdxy, sdyz, sdzx) -> XYZ matrix.
    """
    c = _unsqvar(cross)
    cov = np.zeros((sd.shape[0], 3, 3))
    if order == "neu":
        var = sd[:, [1, 0, 2]] ** 2  # e, n, u
        pairs = ((1, 0), (0, 2), (2, 1))  # ne, eu, un in ENU indices
    else:
        var = sd**2
        pairs = ((0, 1), (1, 2), (2, 0))
    cov[:, [0, 1, 2], [0, 1, 2]] = var
    for k, (i, j) in enumerate(pairs):
        cov[:, i, j] = cov[:, j, i] = c[:, k]
    return cov


@dataclass(frozen=True)
class GnssSolution:
    """GNSS antenna positions with covariances, one row per epoch.

    Attributes
    ----------
    time_gps
        (N,) GPS seconds since 1980-01-06 GPST, strictly increasing.
    position_ecef
        (N,3) antenna phase centre in ECEF WGS84, metres (``p_e_a``).
    covariance_ecef
        (N,3,3) position covariance in ECEF, m², symmetric.
    quality
        (N,) int, RTKLIB Q flag (1 fix, 2 float, 3 sbas, 4 dgps, 5 single, 6 ppp).
    num_sats
        (N,) int, number of satellites.
    age_s
        (N,) differential age in seconds.
    ratio
        (N,) ambiguity ratio test value.
    """

    time_gps: np.ndarray
    position_ecef: np.ndarray
    covariance_ecef: np.ndarray
    quality: np.ndarray
    num_sats: np.ndarray
    age_s: np.ndarray
    ratio: np.ndarray

    def __post_init__(self) -> None:
        t = np.ascontiguousarray(self.time_gps, dtype=np.float64)
        n = t.shape[0] if t.ndim == 1 else -1
        if n < 0:
            raise ValueError(f"time_gps must be 1-D, got shape {t.shape}")
        arrays = {
            "time_gps": (t, (n,)),
            "position_ecef": (np.ascontiguousarray(self.position_ecef, dtype=np.float64), (n, 3)),
            "covariance_ecef": (np.ascontiguousarray(self.covariance_ecef, dtype=np.float64), (n, 3, 3)),
            "quality": (np.ascontiguousarray(self.quality, dtype=np.int64), (n,)),
            "num_sats": (np.ascontiguousarray(self.num_sats, dtype=np.int64), (n,)),
            "age_s": (np.ascontiguousarray(self.age_s, dtype=np.float64), (n,)),
            "ratio": (np.ascontiguousarray(self.ratio, dtype=np.float64), (n,)),
        }
        for name, (arr, shape) in arrays.items():
            if arr.shape != shape:
                raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} contains non-finite values")
            object.__setattr__(self, name, arr)
        if n > 1 and np.any(np.diff(t) <= 0):
            raise ValueError("time_gps must be strictly increasing")
        cov = arrays["covariance_ecef"][0]
        if not np.allclose(cov, np.swapaxes(cov, 1, 2), rtol=1e-9, atol=1e-12):
            raise ValueError("covariance_ecef must be symmetric")

    def __len__(self) -> int:
        return self.time_gps.shape[0]

    @classmethod
    def from_geodetic(
        cls, time_gps: np.ndarray, lat_rad: np.ndarray, lon_rad: np.ndarray, h_m: np.ndarray,
        covariance_enu: np.ndarray, quality: np.ndarray, num_sats: np.ndarray,
        age_s: np.ndarray | None = None, ratio: np.ndarray | None = None,
    ) -> GnssSolution:
        """Build from WGS84 latitude/longitude (rad), ellipsoidal height (m) and an ENU covariance (N,3,3)."""
        lat, lon = np.asarray(lat_rad, float), np.asarray(lon_rad, float)
        R = enu_rotation(lat, lon)
        cov = R @ np.asarray(covariance_enu, float) @ np.swapaxes(R, 1, 2)
        zeros = np.zeros(lat.shape[0])
        return cls(
            time_gps=time_gps, position_ecef=_geodetic_to_ecef(lat, lon, np.asarray(h_m, float)),
            covariance_ecef=0.5 * (cov + np.swapaxes(cov, 1, 2)), quality=quality, num_sats=num_sats,
            age_s=zeros if age_s is None else age_s, ratio=zeros if ratio is None else ratio,
        )

    def geodetic(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """WGS84 (latitude rad, longitude rad, ellipsoidal height m), each (N,)."""
        return _ecef_to_geodetic(self.position_ecef)

    def covariance_enu(self) -> np.ndarray:
        """(N,3,3) covariance in the local east-north-up frame at each position, m²."""
        lat, lon, _ = self.geodetic()
        R = enu_rotation(lat, lon)
        return np.swapaxes(R, 1, 2) @ self.covariance_ecef @ R


# ---------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------


def _header_info(path: Path, comments: list[tuple[int, str]]) -> tuple[str | None, str | None]:
    """Position format ("llh"|"ecef"|None) and time system from the '%' header lines."""
    pos_format = time_system = None
    for line_no, text in comments:
        if "latitude(d'\")" in text:
            raise InputError(
                "degree-minute-second latitude/longitude is not supported", path=path, line=line_no,
                field="latitude", expected="latitude(deg) or x-ecef(m)", found="latitude(d'\")",
            )
        if "e-baseline(m)" in text:
            raise InputError(
                "ENU baseline solutions are not supported", path=path, line=line_no,
                field="position", expected="latitude(deg) or x-ecef(m)", found="e-baseline(m)",
            )
        if "latitude(deg)" in text or "x-ecef(m)" in text:
            pos_format = "llh" if "latitude(deg)" in text else "ecef"
            tokens = text.lstrip("%").split()
            time_system = tokens[0] if tokens else None
            if time_system in ("UTC", "JST"):
                raise InputError(
                    "time system not supported (GPS time without leap seconds is required)",
                    path=path, line=line_no, field="time system", expected="GPST", found=time_system,
                )
    return pos_format, time_system


def read_pos(path: PathLike) -> GnssSolution:
    """Read an RTKLIB ``.pos`` solution file.

    The position and time formats are detected from the ``%`` column header line
    (``latitude(deg)`` or ``x-ecef(m)``; ``GPST``) and from the first data line
    (a ``/`` in the first token means a calendar date, otherwise GPS week and
    seconds of week). Without a column header the position form is guessed from
    the magnitude of the first position value (> 1000 means ECEF).

    Returns
    -------
    GnssSolution
        Positions and covariances in ECEF (see the module docstring for the
        covariance rotation).

    Raises
    ------
    InputError
        For a malformed line (line number, field name, expected, found), a file
        without epochs, a time that does not increase, or an unsupported
        time system or position form.
    """
    path = Path(path)
    lines = read_text_lines(path)
    comments = [(i + 1, s) for i, s in enumerate(lines[:200]) if s.startswith("%")]
    pos_format, _ = _header_info(path, comments)
    rows, line_numbers = data_lines(lines, 0, comment="%")
    if not rows:
        raise InputError("no solution epochs", path=path, expected="at least one data line", found="none")

    first = rows[0].split()
    calendar = "/" in first[0]
    original_rows = rows
    if calendar:  # "YYYY/MM/DD HH:MM:SS.SSS" -> six numeric tokens
        rows = "\n".join(rows).translate(str.maketrans("/:", "  ")).split("\n")
        first = rows[0].split()
    time_fields = _CAL_FIELDS if calendar else _WEEK_FIELDS
    nt = len(time_fields)
    if pos_format is None:
        try:
            pos_format = "ecef" if abs(float(first[nt])) > 1000.0 else "llh"
        except (IndexError, ValueError):
            pos_format = "llh"
        _log.warning("%s: no RTKLIB column header; assuming %s positions", path, pos_format)
    names = _LLH_FIELDS if pos_format == "llh" else _ECEF_FIELDS
    n_fields = min(len(first) - nt, len(names))
    if n_fields < _MIN_FIELDS:
        raise InputError(
            "too few fields", path=path, line=int(line_numbers[0]),
            expected=f"at least {nt + _MIN_FIELDS} fields ({', '.join(time_fields + names[:_MIN_FIELDS])})",
            found=f"{len(first)} fields",
        )
    if n_fields in (9, 10):
        raise InputError(
            "incomplete covariance columns", path=path, line=int(line_numbers[0]),
            expected=f"{nt + 8} or at least {nt + 11} fields", found=f"{len(first)} fields",
        )
    if len(first) - nt > len(names):
        _log.debug("%s: ignoring %d extra columns (velocity)", path, len(first) - nt - len(names))
    extra = tuple(f"column {k + 1}" for k in range(nt + n_fields, len(first)))
    field_names = time_fields + names[:n_fields] + extra
    # exact=True: every line must have the shape of the first one, so that a
    # missing field is reported instead of shifting the columns.
    try:
        values = parse_float_rows(path, rows, line_numbers, field_names, exact=True)[:, : nt + n_fields]
    except InputError as exc:
        if not (calendar and exc.field is None and exc.line is not None):
            raise
        # Report the field count as the user sees it: date and time are one field each.
        names_seen = ("GPST date", "GPST time") + field_names[nt:]
        i = int(np.searchsorted(line_numbers, exc.line))
        tokens = original_rows[i].split()
        for k, (name, sep, form) in enumerate((("GPST date", "/", "YYYY/MM/DD"), ("GPST time", ":", "HH:MM:SS.SSS"))):
            if len(tokens) > k and len(tokens[k].split(sep)) != 3:
                raise InputError(f"malformed {name}", path=path, line=exc.line, field=name,
                                 expected=form, found=repr(tokens[k])) from exc
        raise InputError(
            "wrong number of fields", path=path, line=exc.line,
            expected=f"{len(names_seen)} fields ({', '.join(names_seen)})",
            found=f"{len(original_rows[i].split())} fields",
        ) from exc

    time_gps = _parse_time(path, values[:, :nt], line_numbers, calendar)
    v = np.zeros((values.shape[0], len(names)))
    v[:, :n_fields] = values[:, nt:]
    _check_columns(path, v, line_numbers, names, pos_format, n_fields)
    raise_if_not_increasing(path, time_gps, line_numbers, time_fields[-1] if not calendar else "GPST",
                            formatter=lambda t: f"{t:.3f} s GPS")

    sd, cross = v[:, 5:8], v[:, 8:11]
    if pos_format == "llh":
        lat, lon = np.radians(v[:, 0]), np.radians(v[:, 1])
        return GnssSolution.from_geodetic(
            time_gps, lat, lon, v[:, 2], _cov_from_columns(sd, cross, "neu"),
            quality=v[:, 3].astype(np.int64), num_sats=v[:, 4].astype(np.int64), age_s=v[:, 11], ratio=v[:, 12],
        )
    return GnssSolution(
        time_gps=time_gps, position_ecef=v[:, 0:3], covariance_ecef=_cov_from_columns(sd, cross, "xyz"),
        quality=v[:, 3].astype(np.int64), num_sats=v[:, 4].astype(np.int64), age_s=v[:, 11], ratio=v[:, 12],
    )


def _first_bad(path: Path, mask: np.ndarray, line_numbers: np.ndarray, field: str, expected: str,
               found: np.ndarray) -> None:
    if mask.any():
        i = int(np.flatnonzero(mask)[0])
        raise InputError(f"invalid {field}", path=path, line=int(line_numbers[i]), field=field,
                         expected=expected, found=f"{found[i]:g}")


def _parse_time(path: Path, t: np.ndarray, line_numbers: np.ndarray, calendar: bool) -> np.ndarray:
    """GPS seconds from the parsed time columns, with range checks naming the line."""
    if not calendar:
        week, sow = t[:, 0], t[:, 1]
        _first_bad(path, (week != np.round(week)) | (week < 0) | (week > 9999), line_numbers,
                   "GPS week", "an integer week 0..9999", week)
        _first_bad(path, (sow < 0) | (sow >= 604800.0), line_numbers,
                   "GPST seconds of week", "0 <= seconds < 604800", sow)
        return gps_seconds_from_week(week, sow)
    checks = (
        ("GPST year", 1980, 2200), ("GPST month", 1, 12), ("GPST day", 1, 31),
        ("GPST hour", 0, 23), ("GPST minute", 0, 59),
    )
    for j, (name, lo, hi) in enumerate(checks):
        col = t[:, j]
        _first_bad(path, (col != np.round(col)) | (col < lo) | (col > hi), line_numbers, name,
                   f"an integer {lo}..{hi}", col)
    _first_bad(path, t[:, 2] > days_in_month(t[:, 0], t[:, 1]), line_numbers, "GPST day",
               "a day within the month", t[:, 2])
    _first_bad(path, (t[:, 5] < 0) | (t[:, 5] >= 60), line_numbers, "GPST second", "0 <= second < 60", t[:, 5])
    return gps_seconds_from_calendar(*(t[:, j] for j in range(6)))


def _check_columns(path: Path, v: np.ndarray, line_numbers: np.ndarray, names: tuple[str, ...],
                   pos_format: str, n_fields: int) -> None:
    if pos_format == "llh":
        _first_bad(path, np.abs(v[:, 0]) > 90, line_numbers, names[0], "-90..90", v[:, 0])
        _first_bad(path, (v[:, 1] < -180) | (v[:, 1] > 360), line_numbers, names[1], "-180..360", v[:, 1])
    else:
        r = np.linalg.norm(v[:, :3], axis=1)
        _first_bad(path, (r < 6.0e6) | (r > 1.0e8), line_numbers, names[0],
                   "an ECEF position with |p| between 6000 km and 100000 km", v[:, 0])
    for j in (3, 4):
        _first_bad(path, (v[:, j] != np.round(v[:, j])) | (v[:, j] < 0), line_numbers, names[j],
                   "a non-negative integer", v[:, j])
    for j in (5, 6, 7):
        _first_bad(path, v[:, j] < 0, line_numbers, names[j], "a standard deviation >= 0", v[:, j])
    if n_fields < 11:
        _log.warning("%s: no covariance columns; using diagonal covariances", path)


# ---------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------


def write_pos(
    path: PathLike,
    solution: GnssSolution,
    time_format: Literal["calendar", "week"] = "calendar",
    position_format: Literal["llh", "ecef"] = "llh",
    *,
    program: str | None = None,
    pos_mode: str = "kinematic",
    time_decimals: int = 3,
    protect: tuple[PathLike, ...] = (),
) -> Path:
    """Write ``solution`` as an RTKLIB-like ``.pos`` file (atomically).

    Parameters
    ----------
    time_format
        ``"calendar"`` (``YYYY/MM/DD HH:MM:SS.SSS`` GPST) or ``"week"`` (week, seconds of week).
    position_format
        ``"llh"`` (latitude/longitude 9 decimals in degrees, height 4 decimals in m,
        NEU standard deviations) or ``"ecef"`` (x/y/z 4 decimals, XYZ standard deviations).
    program, pos_mode
        Text of the ``% program`` and ``% pos mode`` header lines.
    time_decimals
        Decimals of the seconds (RTKLIB's ``timeu``).
    protect
        Input files/folders that must not be written into.

    Returns
    -------
    Path
        The written file.
    """
    if time_format not in ("calendar", "week"):
        raise ValueError(f"time_format must be 'calendar' or 'week', got {time_format!r}")
    if position_format not in ("llh", "ecef"):
        raise ValueError(f"position_format must be 'llh' or 'ecef', got {position_format!r}")
    if program is None:
        from georefine import __version__

        program = f"Georefine {__version__}"
    d = time_decimals
    n = len(solution)
    if time_format == "calendar":
        cols = list(calendar_from_gps_seconds(solution.time_gps, d))
        time_fmt = "%04d/%02d/%02d %02d:%02d:%02d" + (f".%0{d}d" if d else "")
        time_head, width = "GPST", 16 + d + (1 if d else 0)
        if not d:
            cols = cols[:6]
    else:
        units = rounded_time_units(solution.time_gps, d)
        week, sow_units = np.divmod(units, 604800 * 10**d)
        whole, frac = np.divmod(sow_units, 10**d)
        cols = [week, whole, frac] if d else [week, whole]
        time_fmt = "%4d %6d" + (f".%0{d}d" if d else "")
        time_head, width = "GPST", 8 + d + (1 if d else 0)

    if position_format == "llh":
        lat, lon, h = solution.geodetic()
        cov = solution.covariance_enu()
        pos = [np.degrees(lat), np.degrees(lon), h]
        sd = np.sqrt(np.maximum(cov[:, [1, 0, 2], [1, 0, 2]], 0.0))  # n, e, u
        cross = _sqvar(np.stack([cov[:, 1, 0], cov[:, 0, 2], cov[:, 2, 1]], axis=1))  # ne, eu, un
        pos_fmt = "%14.9f %14.9f %10.4f"
        names, legend = _LLH_FIELDS, f"lat/lon/height=WGS84/ellipsoidal,{_LEGEND}"
        head = "%14s %14s %10s" % names[:3]
    else:
        cov = solution.covariance_ecef
        pos = [solution.position_ecef[:, k] for k in range(3)]
        sd = np.sqrt(np.maximum(cov[:, [0, 1, 2], [0, 1, 2]], 0.0))
        cross = _sqvar(np.stack([cov[:, 0, 1], cov[:, 1, 2], cov[:, 2, 0]], axis=1))
        pos_fmt = "%14.4f %14.4f %14.4f"
        names, legend = _ECEF_FIELDS, f"x/y/z-ecef=WGS84,{_LEGEND}"
        head = "%14s %14s %14s" % names[:3]
    head += " %3s %3s %8s %8s %8s %8s %8s %8s %6s %6s" % names[3:]
    row_fmt = f"{time_fmt} {pos_fmt} %3d %3d" + " %8.4f" * 6 + " %6.2f %6.1f\n"
    # Integer columns stay exact in float64 (< 2**53); '%d' formats them.
    table = np.column_stack(cols + pos + [solution.quality, solution.num_sats, sd, cross,
                                          solution.age_s, solution.ratio])

    header = (
        f"% program   : {program}\n% pos mode  : {pos_mode}\n%\n% ({legend})\n"
        f"%  {time_head:<{width}} {head}\n"
    )
    with atomic_output(path, "w", protect=protect) as fh:
        fh.write(header)
        fh.writelines(row_fmt % tuple(r) for r in table.tolist())
    _log.info("wrote %d GNSS epochs to %s", n, path)
    return Path(path)


def gnss_in_w(frame: LocalFrame, t0_gps: float, solution: GnssSolution,
              min_quality: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """GNSS antenna positions and covariances in ``w``.

    Parameters
    ----------
    frame : LocalFrame
    t0_gps : float
        Dataset epoch (GPS seconds).
    solution : GnssSolution
    min_quality : int
        Worst RTKLIB quality flag kept (1 fix, 2 float, ...).

    Returns
    -------
    time : (G,) s rel. ``t0_gps``; p_w : (G, 3) m; cov_w : (G, 3, 3) m^2 (``R_e_w^T C_e R_e_w``).
    """
    keep = solution.quality <= min_quality
    R_e_w = frame.R_e_w
    cov_w = R_e_w.T @ solution.covariance_ecef[keep] @ R_e_w
    return solution.time_gps[keep] - t0_gps, frame.from_ecef(solution.position_ecef[keep]), cov_w
