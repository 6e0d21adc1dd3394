"""The planar-objects file (``features/objects.csv``): the objects of a run and their member features.

docs/ARCHITECTURE.md §4.5 step 4: written beside ``features.csv`` (whose rows the member indices
name), read back by the Cramér-Rao check (``workflows/cramer_rao.py``). Format in :func:`write_objects`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from georefine.errors import InputError
from georefine.io.files import PathLike, atomic_output, data_lines, parse_float_rows, read_text_lines
from georefine.lidar.correspondences import PlanarObjects

__all__ = ["read_objects", "write_objects"]

_FORMAT_LINE = "# georefine planar objects, format 1"
_COLUMNS = (
    "object", "c0_x_m", "c0_y_m", "c0_z_m", "k1_x", "k1_y", "k1_z", "k2_x", "k2_y", "k2_z",
    "n0_x", "n0_y", "n0_z", "n_features", "n_views", "is_vertical", "features",
)


def write_objects(path: PathLike, objects: PlanarObjects, protect: tuple[PathLike, ...] = ()) -> Path:
    """Write planar objects as CSV, atomically.

    Two comment lines (format, ``n_input_features=F``), a header, then one row per object:
    ``object``, ``c0`` (m, ``%.6f``), ``k1``, ``k2``, ``n0`` (``%.10f``), ``n_features``,
    ``n_views``, ``is_vertical`` (0/1) and ``features``, the member feature indices
    separated by spaces.
    """
    fo = objects.feature_object
    order = np.argsort(fo, kind="stable")
    order = order[fo[order] >= 0]
    members = np.split(order, np.cumsum(objects.n_features)[:-1]) if len(objects) else []
    frame = np.hstack([objects.c0, objects.k1, objects.k2, objects.n0])
    with atomic_output(path, "w", protect=protect) as fh:
        fh.write(f"{_FORMAT_LINE}\n# n_input_features={fo.size}\n{','.join(_COLUMNS)}\n")
        fh.writelines(
            f"{o},{','.join(f'{v:.6f}' for v in row[:3])},{','.join(f'{v:.10f}' for v in row[3:])},"
            f"{nf},{nv},{int(vert)},{' '.join(map(str, mem.tolist()))}\n"
            for o, (row, nf, nv, vert, mem) in enumerate(
                zip(frame, objects.n_features.tolist(), objects.n_views.tolist(), objects.is_vertical.tolist(), members,
                    strict=True)
            )
        )
    return Path(path)


def read_objects(path: PathLike) -> PlanarObjects:
    """Read planar objects written by :func:`write_objects`.

    Raises
    ------
    InputError
        Unknown format or feature count, wrong header, bad numbers (line and field), an
        object out of order, or a member list that disagrees with ``n_features``, repeats a
        feature or names one out of range (line).
    """
    path = Path(path)
    lines = read_text_lines(path)
    try:
        if lines[0].strip() != _FORMAT_LINE or not lines[1].startswith("# n_input_features="):
            raise ValueError(lines[:2])
        n_input = int(lines[1].split("=", 1)[1])
        if n_input < 0:
            raise ValueError(n_input)
    except (ValueError, IndexError) as exc:
        raise InputError("not a planar-objects file", path=path, line=1, expected=f"{_FORMAT_LINE!r}, then "
                         "'# n_input_features=F'", found=repr(lines[:2])) from exc
    rows, numbers = data_lines(lines, 2)
    if not rows or rows[0].strip() != ",".join(_COLUMNS):
        raise InputError("unexpected header", path=path, line=3, expected=repr(",".join(_COLUMNS)),
                         found=repr(rows[0] if rows else ""))
    rows, numbers = rows[1:], numbers[1:]
    parts = [r.rpartition(",") for r in rows]
    values = parse_float_rows(path, [q[0] for q in parts], numbers, _COLUMNS[:-1], delimiter=",")
    fo = np.full(n_input, -1, np.int64)
    for o, (q, line) in enumerate(zip(parts, numbers.tolist(), strict=True)):
        tokens = q[2].split()
        ok = values[o, 0] == o and len(tokens) == values[o, 13] and all(t.isdigit() for t in tokens)
        mem = np.array(tokens if ok else [], np.int64)
        if not ok or (mem.size and mem.max() >= n_input) or np.unique(mem).size != mem.size or np.any(fo[mem] >= 0):
            raise InputError("inconsistent object row", path=path, line=line, field="object, features",
                             expected=f"object {o} with {values[o, 13]:g} distinct unused indices in [0, {n_input})",
                             found=repr(rows[o][:80]))
        fo[mem] = o
    try:
        return PlanarObjects(
            c0=values[:, 1:4], k1=values[:, 4:7], k2=values[:, 7:10], n0=values[:, 10:13], feature_object=fo,
            n_features=values[:, 13].astype(np.int64), n_views=values[:, 14].astype(np.int64),
            is_vertical=values[:, 15] != 0,
        )
    except ValueError as exc:
        raise InputError(f"invalid planar objects: {exc}", path=path) from exc
