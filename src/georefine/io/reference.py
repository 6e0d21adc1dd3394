"""Reference surfaces: surveyed points on flat surfaces (evaluation only).

CSV with header ``surface_id,point_id,x,y,z``: one surveyed point per line,
coordinates in the output CRS (metres). ``surface_id`` and ``point_id`` are
free text without commas. Every surface needs at least 3 points that are not
collinear (they must span a plane); the pair (surface_id, point_id) must be
unique. Lines starting with ``#`` are comments.

Collinearity test: the points of a surface are centred and their singular
values s1 >= s2 >= s3 computed; ``s2 / sqrt(n)`` is the RMS distance of the
points from their best-fit line and must exceed ``min_width_m`` (default 1 mm).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from georefine.errors import InputError
from georefine.io.files import (
    PathLike,
    atomic_output,
    data_lines,
    parse_float_rows,
    read_text_lines,
)

__all__ = ["ReferenceSurfaces", "read_reference_surfaces", "write_reference_surfaces", "REFERENCE_COLUMNS"]

_log = logging.getLogger(__name__)

REFERENCE_COLUMNS = ("surface_id", "point_id", "x", "y", "z")


@dataclass(frozen=True)
class ReferenceSurfaces:
    """Surveyed points of reference surfaces, one row per point.

    Attributes
    ----------
    surface_id, point_id
        (N,) str.
    xyz
        (N,3) coordinates in the output CRS, m.
    """

    surface_id: np.ndarray
    point_id: np.ndarray
    xyz: np.ndarray

    def __post_init__(self) -> None:
        sid = np.asarray(self.surface_id, dtype=str)
        pid = np.asarray(self.point_id, dtype=str)
        xyz = np.ascontiguousarray(self.xyz, dtype=np.float64)
        n = sid.shape[0]
        if sid.shape != (n,) or pid.shape != (n,) or xyz.shape != (n, 3):
            raise ValueError(f"shapes must be (N,), (N,), (N,3); got {sid.shape}, {pid.shape}, {xyz.shape}")
        if not np.all(np.isfinite(xyz)):
            raise ValueError("xyz contains non-finite values")
        for name, ids in (("surface_id", sid), ("point_id", pid)):
            if any("," in s or not s.strip() for s in ids.tolist()):
                raise ValueError(f"{name} values must be non-empty and contain no commas")
        object.__setattr__(self, "surface_id", sid)
        object.__setattr__(self, "point_id", pid)
        object.__setattr__(self, "xyz", xyz)

    def __len__(self) -> int:
        return self.xyz.shape[0]

    def surface_ids(self) -> list[str]:
        """Surface ids in order of first appearance."""
        _, first = np.unique(self.surface_id, return_index=True)
        return [str(self.surface_id[i]) for i in np.sort(first)]

    def points_of(self, surface_id: str) -> np.ndarray:
        """(K,3) points of one surface, in file order."""
        return self.xyz[self.surface_id == surface_id]


def _check_surfaces(
    path: Path | None, surfaces: ReferenceSurfaces, line_numbers: np.ndarray, min_width_m: float
) -> None:
    """Raise :class:`InputError` for duplicate points, small or collinear surfaces."""
    # Ids contain no commas (checked in ReferenceSurfaces), so "surface,point" is a unique key.
    keys = np.char.add(np.char.add(surfaces.surface_id, ","), surfaces.point_id)
    uniq, counts = np.unique(keys, return_counts=True)
    if np.any(counts > 1):
        rows = np.flatnonzero(keys == uniq[np.flatnonzero(counts > 1)[0]])
        s, p = str(surfaces.surface_id[rows[0]]), str(surfaces.point_id[rows[0]])
        raise InputError(
            f"duplicate point {p!r} of surface {s!r}", path=path, line=int(line_numbers[rows[1]]),
            field="point_id", expected="unique (surface_id, point_id)",
            found=f"also on line {int(line_numbers[rows[0]])}",
        )
    for sid in surfaces.surface_ids():  # a handful of surfaces: a loop over surfaces, not points
        rows = np.flatnonzero(surfaces.surface_id == sid)
        lines = ", ".join(str(int(line_numbers[r])) for r in rows)
        if rows.size < 3:
            raise InputError(
                f"surface {sid!r} has too few points (lines {lines})", path=path, line=int(line_numbers[rows[0]]),
                field="surface_id", expected="at least 3 points per surface", found=f"{rows.size} points",
            )
        pts = surfaces.xyz[rows]
        s = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
        width = s[1] / np.sqrt(rows.size)
        if width <= min_width_m:
            raise InputError(
                f"points of surface {sid!r} are collinear (lines {lines})", path=path,
                line=int(line_numbers[rows[0]]), field="surface_id",
                expected=f"points spanning a plane (RMS distance from their line > {min_width_m:g} m)",
                found=f"{width:.3g} m",
            )


def read_reference_surfaces(path: PathLike, *, min_width_m: float = 1e-3) -> ReferenceSurfaces:
    """Read a reference-surface CSV (``surface_id,point_id,x,y,z``).

    Raises
    ------
    InputError
        Wrong header, bad or missing value (line and field), duplicate point,
        a surface with fewer than 3 points or collinear points (naming the
        surface and its lines), no rows.
    """
    path = Path(path)
    lines = read_text_lines(path)
    rows, numbers = data_lines(lines, 0)
    if not rows:
        raise InputError("no reference points", path=path, expected="a header and data lines", found="none")
    header = tuple(t.strip().lower() for t in rows[0].split(","))
    if header != REFERENCE_COLUMNS:
        raise InputError("unexpected header", path=path, line=int(numbers[0]),
                         expected=repr(",".join(REFERENCE_COLUMNS)), found=repr(rows[0]))
    rows, numbers = rows[1:], numbers[1:]
    if not rows:
        raise InputError("no reference points", path=path, expected="data lines after the header", found="none")
    # Few rows: split in Python, then parse the numeric part with the shared fast path.
    fields = [[t.strip() for t in r.split(",")] for r in rows]
    for f, line in zip(fields, numbers.tolist()):
        if len(f) != 5:
            raise InputError("wrong number of fields", path=path, line=line,
                             expected="5 fields (surface_id, point_id, x, y, z)", found=f"{len(f)} fields")
        for name, value in zip(REFERENCE_COLUMNS[:2], f[:2]):
            if not value:
                raise InputError("empty identifier", path=path, line=line, field=name,
                                 expected="a non-empty text", found="''")
    xyz = parse_float_rows(path, [",".join(f[2:]) for f in fields], numbers, REFERENCE_COLUMNS[2:], delimiter=",")
    surfaces = ReferenceSurfaces(np.array([f[0] for f in fields]), np.array([f[1] for f in fields]), xyz)
    _check_surfaces(path, surfaces, numbers, min_width_m)
    _log.info("read %d reference points on %d surfaces from %s", len(surfaces), len(surfaces.surface_ids()), path)
    return surfaces


def write_reference_surfaces(
    path: PathLike, surfaces: ReferenceSurfaces, *, min_width_m: float = 1e-3, protect: tuple[PathLike, ...] = ()
) -> Path:
    """Write a reference-surface CSV (coordinates ``%.4f``), atomically.

    The surfaces are checked as on reading, so a written file always reads back.
    """
    _check_surfaces(None, surfaces, np.arange(2, len(surfaces) + 2), min_width_m)
    with atomic_output(path, "w", protect=protect) as fh:
        fh.write(",".join(REFERENCE_COLUMNS) + "\n")
        fh.writelines(
            f"{s},{p},{x:.4f},{y:.4f},{z:.4f}\n"
            for s, p, (x, y, z) in zip(surfaces.surface_id.tolist(), surfaces.point_id.tolist(), surfaces.xyz.tolist())
        )
    return Path(path)
