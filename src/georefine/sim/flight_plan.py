"""Flight plans: the lines a survey flies and the turns between them (docs/ARCHITECTURE.md §6 "Flight plans").

A plan is a sequence of *lines* in the mapping frame ``w`` (x east, y north, metres), each a
polyline flown from its first vertex to its last with the scanner on; between lines the
aircraft turns with the scanner off, as an operator cuts the strips. Three kinds:

* ``area``: a block of ``lines`` parallel lines along ``direction_deg`` (grid azimuth,
  clockwise from ``w`` north) across the scene, ``spacing_m`` apart (or at ``sidelap`` of the
  swath), plus ``cross_lines`` perpendicular lines over the whole block, evenly spread along it.
  The parallel lines are flown back and forth; ``order: racetrack`` flies them in the skip-line
  pattern ``1, 1+k, 2, 2+k, ...`` (``k = ceil(lines / 2)``) that keeps consecutive lines at least
  two turn radii apart when the spacing is smaller, as crews do with a helicopter or aircraft
  that cannot turn onto the next line; ``serpentine`` flies them in order.
* ``corridor``: a polyline axis (``polyline_m``, default the scene's axis ``scene.axis_m``)
  with bends flown as turns of ``bend_radius_m`` inside the strip, and ``parallel_lines``
  offset copies of it ``line_spacing_m`` apart (a wide corridor), flown back and forth.
* ``file``: a CSV of line end points in the output CRS (``line,x0,y0,x1,y1``; one row per line,
  flown in the file's order from ``(x0, y0)`` to ``(x1, y1)``; comment lines start with ``#``).

:func:`plan_lines` turns a plan into :class:`PlannedLine` records; :func:`dubins_path` is the
shortest path of bounded curvature between two poses (Dubins 1957: the six words ``LSL``,
``RSR``, ``LSR``, ``RSL``, ``RLR``, ``LRL``), which :mod:`georefine.sim.flight` flies between
lines with its smooth roll-in. Written by hand: the ``dubins`` package on PyPI is a C extension
last released in 2018 without wheels for current Pythons, and the flight needs the words as
primitives it can time, not sampled points.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from georefine.config import StrictModel
from georefine.errors import ConfigError, InputError

__all__ = ["FlightPlanConfig", "PlannedLine", "Primitive", "dubins_path", "plan_lines", "read_line_file",
           "swath_width_m"]


class FlightPlanConfig(StrictModel):
    """A flight plan of several lines (see the module docstring); ``None`` in a scenario flies the corridor passes."""

    kind: Literal["area", "corridor", "file"] = "area"
    lines: int = Field(8, ge=1, le=200, description="area: parallel lines")
    sidelap: float = Field(0.3, ge=0.0, lt=0.95, description="area: overlap of neighbouring swaths (share of the swath)")
    spacing_m: float | None = Field(None, gt=0, description="area: line spacing; overrides sidelap")
    direction_deg: float = Field(0.0, ge=-360.0, le=360.0, description="area: grid azimuth of the parallel lines")
    cross_lines: int = Field(2, ge=0, le=50, description="area: perpendicular lines over the block")
    order: Literal["racetrack", "serpentine"] = "racetrack"
    polyline_m: tuple[tuple[float, float], ...] | None = Field(
        None, description="corridor: axis vertices in w (x east, y north); default x = 0 along the scene")
    parallel_lines: int = Field(1, ge=1, le=9, description="corridor: lines side by side")
    line_spacing_m: float = Field(250.0, gt=0, description="corridor: spacing of the parallel lines")
    bend_radius_m: float = Field(600.0, gt=0, description="corridor: turn radius of the bends inside a strip")
    file: str | None = Field(None, description="file: CSV of line end points in the output CRS")
    transit_m: float = Field(0.0, ge=0.0, description="straight flight from the take-off to the first line")

    @model_validator(mode="after")
    def _check(self) -> FlightPlanConfig:
        if self.kind == "file" and not self.file:
            raise ValueError("plan.kind file needs plan.file, a CSV of line,x0,y0,x1,y1 in the output CRS")
        if self.polyline_m is not None and len(self.polyline_m) < 2:
            raise ValueError("plan.polyline_m needs at least two vertices")
        return self


@dataclass(frozen=True)
class PlannedLine:
    """One line of a plan: its strip id and the vertices (K, 2) in ``w`` it covers, in flying order."""

    line_id: int
    vertices: np.ndarray

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, float)
        if v.ndim != 2 or v.shape[1] != 2 or len(v) < 2 or not np.all(np.isfinite(v)):
            raise ValueError(f"line {self.line_id}: vertices must be a finite (K>=2, 2) array, got {v.shape}")
        if np.any(np.linalg.norm(np.diff(v, axis=0), axis=1) < 1.0):
            raise ValueError(f"line {self.line_id}: consecutive vertices closer than 1 m")
        object.__setattr__(self, "vertices", v)

    @property
    def start_heading(self) -> float:
        """Grid azimuth (rad, clockwise from north) of the first segment."""
        d = self.vertices[1] - self.vertices[0]
        return float(np.arctan2(d[0], d[1]))

    @property
    def end_heading(self) -> float:
        d = self.vertices[-1] - self.vertices[-2]
        return float(np.arctan2(d[0], d[1]))

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.vertices, axis=0), axis=1).sum())


@dataclass(frozen=True)
class Primitive:
    """A piece of a horizontal path: a straight of ``length_m`` (``turn_rad`` 0) or an arc of radius
    ``radius_m`` turning by ``turn_rad`` (grid azimuth: positive clockwise, i.e. to the right)."""

    length_m: float = 0.0
    turn_rad: float = 0.0
    radius_m: float = 0.0

    @property
    def path_length_m(self) -> float:
        return self.length_m if self.turn_rad == 0.0 else abs(self.turn_rad) * self.radius_m


def swath_width_m(altitude_agl_m: float, field_of_view_deg: float) -> float:
    """Across-track width of a scan at ``altitude_agl_m`` over flat ground."""
    return 2.0 * altitude_agl_m * float(np.tan(np.radians(field_of_view_deg) / 2.0))


def _unit(az: float) -> np.ndarray:
    return np.array([np.sin(az), np.cos(az)])


def plan_lines(plan: FlightPlanConfig, *, length_m: float, width_m: float, swath_m: float,
               to_w=None, base: Path | None = None, axis_m=None) -> tuple[PlannedLine, ...]:
    """The plan's lines in flying order (see the module docstring).

    ``length_m`` and ``width_m`` are the scene's extent (``y`` from 0 to ``length_m``, ``x``
    within ``±width_m / 2``), ``swath_m`` the scan's width, ``axis_m`` the scene's corridor axis
    (a corridor plan without ``polyline_m`` follows it); ``to_w`` maps (N, 2) output-CRS
    coordinates to ``w`` (for ``file`` plans, read relative to ``base``).

    Raises
    ------
    ConfigError
        A block whose swaths leave the scene, or lines too short for their bends.
    """
    if plan.kind == "area":
        lines = _area_lines(plan, length_m, width_m, swath_m)
    elif plan.kind == "corridor":
        lines = _corridor_lines(plan, length_m, axis_m)
    else:
        path = Path(plan.file) if base is None or Path(plan.file).is_absolute() else base / plan.file
        if to_w is None:
            raise ConfigError("a file plan needs the output CRS", field="plan.file")
        lines = read_line_file(path, to_w)
    half = width_m / 2.0
    for ln in lines:
        inside = (np.abs(ln.vertices[:, 0]) <= half + 1e-6) & (ln.vertices[:, 1] >= -1e-6) & (
            ln.vertices[:, 1] <= length_m + 1e-6)
        if not inside.all():
            raise ConfigError("a line of the flight plan leaves the scene", field="plan",
                              expected=f"vertices within x ±{half:.0f} m, y 0-{length_m:.0f} m (scene.width_m, "
                              "scene.length_m)", found=f"line {ln.line_id}: {np.round(ln.vertices, 1).tolist()}")
    return lines


def _clip(point: np.ndarray, direction: np.ndarray, length_m: float, width_m: float,
          limit: float = np.inf) -> tuple[float, float] | None:
    """Parameters ``(t0, t1)`` of the part of the line ``point + t direction`` inside the scene
    (``|x| <= width_m / 2``, ``0 <= y <= length_m``) and within ``|t| <= limit``; None if none."""
    lo, hi = -limit, limit
    for k, (a, b) in enumerate(((-width_m / 2.0, width_m / 2.0), (0.0, length_m))):
        if abs(direction[k]) < 1e-12:
            if not a - 1e-9 <= point[k] <= b + 1e-9:
                return None
            continue
        t = sorted(((a - point[k]) / direction[k], (b - point[k]) / direction[k]))
        lo, hi = max(lo, t[0]), min(hi, t[1])
    return (lo, hi) if hi - lo > 1.0 else None


def _area_lines(plan: FlightPlanConfig, length_m: float, width_m: float, swath_m: float) -> tuple[PlannedLine, ...]:
    n = plan.lines
    spacing = plan.spacing_m if plan.spacing_m is not None else (1.0 - plan.sidelap) * swath_m
    az = np.radians(plan.direction_deg)
    u, v = _unit(az), _unit(az + np.pi / 2.0)  # along the lines, across them (to the right)
    centre = np.array([0.0, length_m / 2.0])
    # Each line spans the scene along its direction (a north-south block its whole length; a
    # rotated one is clipped to the scene's rectangle); the cross lines span the block's width.
    across = (np.arange(n) - (n - 1) / 2.0) * spacing
    if plan.order == "racetrack" and n > 2:
        k = (n + 1) // 2
        order = [i for pair in zip(range(k), range(k, n)) for i in pair] + ([k - 1] if n % 2 else [])
        order = list(dict.fromkeys(order))
    else:
        order = list(range(n))
    def line(point, direction, line_id, limit=np.inf):
        span = _clip(point, direction, length_m, width_m, limit)
        if span is None:
            raise ConfigError("a line of the flight plan misses the scene", field="plan",
                              expected="lines that cross the scene (scene.width_m, scene.length_m, plan.spacing_m, "
                              "plan.direction_deg)", found=f"line {line_id} through {np.round(point, 1).tolist()}")
        return point + span[0] * direction, point + span[1] * direction

    out = []
    for j, i in enumerate(order):
        a, b = line(centre + across[i] * v, u, i + 1)
        out.append(PlannedLine(i + 1, np.array([a, b] if j % 2 == 0 else [b, a])))
    m = plan.cross_lines
    half_across = (n - 1) / 2.0 * spacing + swath_m / 2.0
    # Cross lines spread evenly along the parallel lines' common extent.
    extents = [_clip(centre + a * v, u, length_m, width_m) for a in across]
    t_lo, t_hi = max(e[0] for e in extents), min(e[1] for e in extents)
    for j in range(m):
        s = t_lo + (j + 1) / (m + 1) * (t_hi - t_lo) if m else 0.0
        a, b = line(centre + s * u, v, n + j + 1, limit=half_across)
        out.append(PlannedLine(n + j + 1, np.array([a, b] if j % 2 == 0 else [b, a])))
    return tuple(out)


def _offset_polyline(vertices: np.ndarray, offset: float) -> np.ndarray:
    """The polyline shifted ``offset`` to the right of its direction (mitred at the bends)."""
    d = np.diff(vertices, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    right = np.column_stack([d[:, 1], -d[:, 0]])
    normals = np.vstack([right[:1], right[:-1] + right[1:], right[-1:]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    cos_half = np.ones(len(vertices))
    cos_half[1:-1] = np.einsum("ij,ij->i", normals[1:-1], right[:-1])
    return vertices + offset * normals / cos_half[:, None]


def _corridor_lines(plan: FlightPlanConfig, length_m: float, axis_m=None) -> tuple[PlannedLine, ...]:
    axis = np.array(plan.polyline_m if plan.polyline_m is not None else
                    axis_m if axis_m is not None else [(0.0, 0.0), (0.0, length_m)], float)
    n = plan.parallel_lines
    out = []
    for i in range(n):
        line = _offset_polyline(axis, (i - (n - 1) / 2.0) * plan.line_spacing_m)
        out.append(PlannedLine(i + 1, line if i % 2 == 0 else line[::-1]))
    return tuple(out)


def read_line_file(path: Path, to_w) -> tuple[PlannedLine, ...]:
    """Lines from a CSV ``line,x0,y0,x1,y1`` (output CRS, metres), flown in the file's order.

    Raises
    ------
    InputError
        A missing file, a bad header or number (line, field), a repeated line id.
    """
    from georefine.io.files import read_text_lines

    lines = read_text_lines(path)
    rows = [(i + 1, s.strip()) for i, s in enumerate(lines) if s.strip() and not s.lstrip().startswith("#")]
    header = ("line", "x0", "y0", "x1", "y1")
    if not rows or tuple(c.strip() for c in rows[0][1].split(",")) != header:
        raise InputError("unexpected header", path=path, line=rows[0][0] if rows else 1, expected=",".join(header),
                         found=repr(rows[0][1] if rows else ""))
    ids, ends = [], []
    for number, text in rows[1:]:
        parts = [p.strip() for p in text.split(",")]
        if len(parts) != 5:
            raise InputError("wrong number of fields", path=path, line=number, expected="5 (line,x0,y0,x1,y1)",
                             found=str(len(parts)))
        try:
            ids.append(int(parts[0]))
        except ValueError:
            raise InputError("not a line id", path=path, line=number, field="line", expected="an integer",
                             found=repr(parts[0])) from None
        try:
            ends.append([float(p) for p in parts[1:]])
        except ValueError:
            raise InputError("not a number", path=path, line=number, field="x0,y0,x1,y1",
                             expected="coordinates in metres", found=repr(text)) from None
        if ids[-1] in ids[:-1]:
            raise InputError("line listed twice", path=path, line=number, field="line", found=str(ids[-1]))
    if not ids:
        raise InputError("no lines", path=path, expected="at least one row line,x0,y0,x1,y1")
    e = np.asarray(ends)
    xy = np.asarray(to_w(np.column_stack([e[:, [0, 2]].reshape(-1), e[:, [1, 3]].reshape(-1)])), float)[:, :2]
    return tuple(PlannedLine(i, xy[2 * k:2 * k + 2]) for k, i in enumerate(ids))


# ---------------------------------------------------------------------------- Dubins paths
def _mod2pi(a):
    return np.mod(a, 2.0 * np.pi)


def dubins_path(start_xy, start_az: float, goal_xy, goal_az: float, radius_m: float) -> list[Primitive]:
    """Shortest path of curvature at most ``1 / radius_m`` from a pose to another.

    Poses are horizontal positions in ``w`` and grid azimuths (rad, clockwise from north). The
    result is three primitives (arc, straight, arc or arc, arc, arc; zero-length ones dropped)
    in the convention of :class:`Primitive`.
    """
    R = float(radius_m)
    p0, p1 = np.asarray(start_xy, float), np.asarray(goal_xy, float)
    # Normalised frame: math angles (counter-clockwise from east), unit radius.
    th0, th1 = np.pi / 2.0 - start_az, np.pi / 2.0 - goal_az
    dx, dy = (p1 - p0) / R
    d = np.hypot(dx, dy)
    phi = np.arctan2(dy, dx)
    a, b = _mod2pi(th0 - phi), _mod2pi(th1 - phi)
    sa, sb, ca, cb = np.sin(a), np.sin(b), np.cos(a), np.cos(b)
    cab = np.cos(a - b)
    best = None

    def consider(word, t, p, q):
        nonlocal best
        if best is None or t + p + q < sum(best[1]) - 1e-12:
            best = (word, (t, p, q))

    # LSL
    sq = 2 + d * d - 2 * cab + 2 * d * (sa - sb)
    if sq >= 0:
        tmp = np.arctan2(cb - ca, d + sa - sb)
        consider("LSL", _mod2pi(-a + tmp), np.sqrt(sq), _mod2pi(b - tmp))
    # RSR
    sq = 2 + d * d - 2 * cab + 2 * d * (sb - sa)
    if sq >= 0:
        tmp = np.arctan2(ca - cb, d - sa + sb)
        consider("RSR", _mod2pi(a - tmp), np.sqrt(sq), _mod2pi(-b + tmp))
    # LSR
    sq = -2 + d * d + 2 * cab + 2 * d * (sa + sb)
    if sq >= 0:
        p = np.sqrt(sq)
        tmp = np.arctan2(-ca - cb, d + sa + sb) - np.arctan2(-2.0, p)
        consider("LSR", _mod2pi(-a + tmp), p, _mod2pi(-_mod2pi(b) + tmp))
    # RSL
    sq = -2 + d * d + 2 * cab - 2 * d * (sa + sb)
    if sq >= 0:
        p = np.sqrt(sq)
        tmp = np.arctan2(ca + cb, d - sa - sb) - np.arctan2(2.0, p)
        consider("RSL", _mod2pi(a - tmp), p, _mod2pi(b - tmp))
    # RLR
    tmp = (6.0 - d * d + 2 * cab + 2 * d * (sa - sb)) / 8.0
    if abs(tmp) <= 1.0:
        p = _mod2pi(2 * np.pi - np.arccos(tmp))
        t = _mod2pi(a - np.arctan2(ca - cb, d - sa + sb) + p / 2.0)
        consider("RLR", t, p, _mod2pi(a - b - t + p))
    # LRL
    tmp = (6.0 - d * d + 2 * cab + 2 * d * (sb - sa)) / 8.0
    if abs(tmp) <= 1.0:
        p = _mod2pi(2 * np.pi - np.arccos(tmp))
        t = _mod2pi(-a + np.arctan2(-ca + cb, d + sa - sb) + p / 2.0)
        consider("LRL", t, p, _mod2pi(b - a - t + p))
    if best is None:  # cannot happen for finite poses: RSR and LSL always exist
        raise ValueError("no Dubins path")
    word, lengths = best
    out = []
    for letter, s in zip(word, lengths):
        if s <= 1e-12:
            continue
        if letter == "S":
            out.append(Primitive(length_m=float(s * R)))
        else:  # L turns counter-clockwise: the azimuth decreases
            out.append(Primitive(turn_rad=float(-s if letter == "L" else s), radius_m=R))
    return out


def follow(primitives: list[Primitive], start_xy, start_az: float) -> tuple[np.ndarray, float]:
    """End pose of ideal ``primitives`` flown from a pose (for tests and the planner's checks)."""
    p, az = np.asarray(start_xy, float).copy(), float(start_az)
    for q in primitives:
        if q.turn_rad == 0.0:
            p = p + q.length_m * _unit(az)
        else:
            side = np.sign(q.turn_rad)  # +1 right
            centre = p + q.radius_m * _unit(az + side * np.pi / 2.0)
            az_end = az + q.turn_rad
            p = centre - q.radius_m * _unit(az_end + side * np.pi / 2.0)
            az = az_end
    return p, float(np.mod(az, 2.0 * np.pi))
