"""Strip differences on a raster, as paper 000's Fig. 7 shows them (docs/ARCHITECTURE.md §5).

A horizontal raster (default 1 m) in the output CRS. Every *layer* -- the points of one strip x
scanner channel -- gets a least-squares plane ``z = a + b dx + c dy`` in every cell where it has
enough points (``min_points``) spanning the cell; ``a`` is its height at the cell centre. A
layer is *planar* in the cell when its plane fits (RMS residual at most ``max_roughness_m``)
and is not steeper than ``max_slope_deg``. The map is the spread ``max - min`` of the planar
layers' heights, measured along their mean normal (``n_z (max - min)``: the distance between
parallel planes, where the vertical spread on a slope would count a horizontal shift too).
Because each layer's plane is evaluated at the same point (the cell centre), slopes do not
bias the difference, and a cell's value is the largest disagreement between any two views or
passes there.

Gating. A cell shows a difference only where it is a planar surface in every view of it: a
wire over the ground, a tree crown, a roof edge or the border of a strip give planes through
unrelated points, which in the corridor simulation made metre-size "differences" (up to 31 m
on the wires). A cell where at least two layers fit within ``max_roughness_m`` (the map before
gating, :attr:`StripDifferenceMap.ungated_m`) is gated, for the first reason that applies
(:data:`GATES`; counts in :meth:`StripDifferenceMap.gating`), when

* ``rough``: another layer has enough points there but its plane does not fit (its points lie
  on two objects: the wires seen with the ground, a crown, a roof edge);
* ``steep``: a layer's smooth plane is steeper than ``max_slope_deg`` (:data:`MAX_SLOPE_DEG`: a
  plane through a wire and the ground, or the top and foot of a facade);
* ``edge``: a strip with a planar layer there does not cover all eight neighbouring cells with
  points (the end or the side of its swath, the shadow of a building or a tree), so the cell may
  be covered only in part;
* ``normals``: the planar layers' normals differ by more than ``max_normal_angle_deg``
  (:data:`MAX_NORMAL_ANGLE_DEG`; checked on the bounding box of their components, which bounds
  every pair's angle from above).

The thresholds and their reasons: :data:`MIN_POINTS`, :data:`MAX_ROUGHNESS_M`,
:data:`MAX_SLOPE_DEG`, :data:`MAX_NORMAL_ANGLE_DEG`.

Streaming. The planes come from per-cell moment sums that merge chunk by chunk
(:mod:`georefine.evaluation.cell_moments`), and the map needs of a layer's planes only a few
numbers per cell and strip -- highest and lowest height, normals, how many layers are planar,
rough or steep there (:class:`CellSpread`) -- so :class:`StripDifferenceStream` takes the points
as a stream of chunks and keeps only the cells still *open*: once a layer x cell has had no
points for ``close_after`` records (a strip read in time order has passed it) or its layer is
declared complete (the end of the strip's file), its plane is folded into the spread and its
sums are dropped. The spread is kept per strip because the edge test needs every strip's
coverage, complete only at the end. Memory is then the cells of the last few chunks and the
map -- plus 8 bytes per cell a still open layer has left, to check that it stays closed, and 8
bytes per cell a strip covers -- not the points. Closing is checked, not assumed: points that
arrive for a closed layer x cell raise :class:`Reopened` (the caller then reads again without
closing, in memory that grows with the cells of all layers). Closing changes nothing in the
results but the order of floating-point sums.

Outputs: the raster (NaN where undefined or gated), its summary (median, P95, RMS over the
defined cells), the gating counts, a PNG map (:mod:`georefine.evaluation.strip_difference_maps`:
0-100 mm green to red, gated cells grey, equal-aspect panels along a long corridor) and a GeoTIFF (float32 metres, Deflate; NaN as no-data; model tie
point and pixel scale, the EPSG code as ``ProjectedCSTypeGeoKey``; band description and unit
``metre`` in the GDAL_METADATA tag), written with tifffile.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from georefine.evaluation.cell_moments import (
    CellMoments,
    CellPlanes,
    cell_keys,
    cell_moments,
    cell_planes,
)
from georefine.evaluation.coverage import CellCounts, CoverageMap, coverage_map
from georefine.io.files import atomic_path

__all__ = [
    "CellMoments", "cell_moments", "CellPlanes", "cell_planes", "CellSpread", "Reopened", "StripDifferenceStream",
    "StripDifferenceMap", "strip_differences", "crop", "write_geotiff", "LAYER_CODE", "GATES",
    "MIN_POINTS", "MAX_ROUGHNESS_M", "MAX_SLOPE_DEG", "MAX_NORMAL_ANGLE_DEG", "BAND_DESCRIPTION",
]

LAYER_CODE = 256
"""A layer's code is ``strip * LAYER_CODE + channel``: its strip is ``layer // LAYER_CODE``."""

GATES = ("none", "kept", "rough", "steep", "edge", "normals")
"""What became of a cell (:attr:`StripDifferenceMap.gate`): no difference (fewer than two layers
fit a plane within the roughness limit), kept, or gated for the first reason that applies
(module docstring, "Gating")."""

MIN_POINTS = 6
"""Points of a layer in a cell for a plane: three parameters and three degrees of freedom left
for the roughness."""

MAX_ROUGHNESS_M = 0.03
"""RMS residual of a planar layer's plane: six times the 5 mm range noise of a VUX-160-class
scanner, so that a plane of six noisy points passes, while a plane through two objects (roof
and ground, crown and ground) does not."""

MAX_SLOPE_DEG = 60.0
"""Steepest plane that counts. Roofs (25-45 degrees in the simulated scenes, rarely above 60
in the field) and terrain pass; a steeper ``z = f(x, y)`` plane in a 1 m cell turns every
centimetre of horizontal error into more than 1.7 cm of height, and the smooth ones seen on
the corridor (75-89 degrees) run through two lines of points: a wire and the ground, or the
top and foot of a facade."""

MAX_NORMAL_ANGLE_DEG = 5.0
"""Largest angle between the normals of a cell's planar layers. The normal of a plane through
six points with 5 mm noise spread over a 1 m cell scatters by 0.4 degrees (1 sigma), and
boresight or attitude errors tilt it by tenths of a degree; the planes of two different surfaces meeting in a cell (a roof and the
ground, a wire's plane and the ground) differ by tens of degrees."""

_MERGE_ROWS = 500_000
"""Rows held aside before they are merged into a total (sums of a layer, the spread)."""


@dataclass(frozen=True)
class StripDifferenceMap:
    """Raster of strip differences: row 0 is the northern edge (image order)."""

    spread_m: np.ndarray  # (rows, cols) float64: along the common normal, NaN where undefined or gated
    layers_m: np.ndarray  # (rows, cols) int: layers whose plane fits within max_roughness_m, per cell
    x0: float  # easting of the western edge
    y1: float  # northing of the northern edge
    cell_size_m: float
    ungated_m: np.ndarray  # (rows, cols) float64: max - min of those layers' heights, no gate (the old map)
    gate: np.ndarray  # (rows, cols) uint8: index in GATES of what became of the cell

    def summary(self) -> dict[str, float]:
        """``cells``, ``median_m``, ``p95_m``, ``mean_m``, ``rms_m``, ``max_m``, ``cells_above_1m`` of the map."""
        return _figures(self.spread_m)

    def ungated_summary(self) -> dict[str, float]:
        """:meth:`summary` of the map without gating (``ungated_m``)."""
        return _figures(self.ungated_m)

    def gating(self) -> dict[str, int]:
        """Cells that had a difference before gating (``candidates``) and what became of them:
        ``kept`` or gated as ``rough``, ``steep``, ``edge``, ``normals`` (module docstring, "Gating")."""
        counts = np.bincount(self.gate.ravel(), minlength=len(GATES))
        return {"candidates": int(counts[1:].sum()), **{g: int(counts[k]) for k, g in enumerate(GATES) if k}}


def _figures(a: np.ndarray) -> dict[str, float]:
    v = a[np.isfinite(a)]
    if v.size == 0:
        nan = float("nan")
        return {"cells": 0, "median_m": nan, "p95_m": nan, "mean_m": nan, "rms_m": nan, "max_m": nan,
                "cells_above_1m": 0}
    return {"cells": int(v.size), "median_m": float(np.median(v)), "p95_m": float(np.percentile(v, 95)),
            "mean_m": float(np.mean(v)), "rms_m": float(np.sqrt(np.mean(v * v))), "max_m": float(v.max()),
            "cells_above_1m": int(np.count_nonzero(v > 1.0))}


def _union(parts: Iterable[np.ndarray | None]) -> np.ndarray:
    """Sorted unique cell keys of ``parts`` (a sort and a comparison: ``np.unique`` hashes, slower here)."""
    parts = [p for p in parts if p is not None]
    if not parts:
        return np.zeros(0, dtype=np.int64)
    keys = np.sort(np.concatenate(parts))
    new = np.ones(keys.size, dtype=bool)
    new[1:] = keys[1:] != keys[:-1]
    return keys[new]


_NEIGHBOURS = np.array([di * (1 << 32) + dj for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj], dtype=np.int64)
"""Key offsets (:func:`cell_keys`) of a cell's eight neighbours."""


def _interior(keys: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """Which cells (sorted keys ``covered`` of a strip's cells with points) have all eight neighbours covered."""
    if covered.size == 0:
        return np.zeros(keys.size, dtype=bool)
    nk = keys[:, None] + _NEIGHBOURS[None, :]
    at = np.minimum(np.searchsorted(covered, nk), covered.size - 1)
    return np.all(covered[at] == nk, axis=1)


_DTYPES = {"high_m": float, "low_m": float, "ungated_high_m": float, "ungated_low_m": float,
           "normal_sum": float, "normal_min": np.float32, "normal_max": np.float32}
"""Data types of :class:`CellSpread`'s fields: heights and the normals' sum (whose rounding would
depend on the order of the rows) in float64, the normals' bounds in float32 (1e-7, ample for a
5 degree test), counts (the others) in int32."""

_FIELDS = {  # CellSpread's per-row fields and how rows of one key merge
    "high_m": np.maximum, "low_m": np.minimum, "layers": np.add,
    "normal_sum": np.add, "normal_min": np.minimum, "normal_max": np.maximum,
    "ungated_high_m": np.maximum, "ungated_low_m": np.minimum, "ungated_layers": np.add,
    "rough": np.add, "steep": np.add,
}


@dataclass(frozen=True)
class CellSpread:
    """Per raster cell and strip, what the map needs of the layers' planes there (the map before
    it is gated and rasterised). Rows sorted by ``(i, j, strip)`` once merged.

    *Planar* layers (roughness and slope within the limits) give the highest and lowest height
    at the cell centre, their count and their unit normals (sum, and the per-component minimum
    and maximum); layers that fit within the roughness limit whatever their slope give the same
    for the ungated map; ``rough`` and ``steep`` count the layers whose plane fails one limit.
    """

    cell_ij: np.ndarray  # (K, 2) int64
    strip: np.ndarray  # (K,) int32
    high_m: np.ndarray  # (K,) -inf where no layer is planar
    low_m: np.ndarray  # (K,) +inf where no layer is planar
    layers: np.ndarray  # (K,) int32 planar layers
    normal_sum: np.ndarray  # (K, 3)
    normal_min: np.ndarray  # (K, 3) float32
    normal_max: np.ndarray  # (K, 3) float32
    ungated_high_m: np.ndarray  # (K,)
    ungated_low_m: np.ndarray  # (K,)
    ungated_layers: np.ndarray  # (K,) int32 layers within max_roughness_m (any slope)
    rough: np.ndarray  # (K,) int32 layers whose plane is rougher than max_roughness_m
    steep: np.ndarray  # (K,) int32 layers within max_roughness_m but steeper than max_slope_deg

    def __len__(self) -> int:
        return int(self.cell_ij.shape[0])

    @classmethod
    def empty(cls) -> CellSpread:
        return cls(np.zeros((0, 2), np.int64), np.zeros(0, np.int32),
                   **{f: np.zeros((0, 3) if f.startswith("normal") else 0, _DTYPES.get(f, np.int32))
                      for f in _FIELDS})

    @classmethod
    def of_planes(cls, planes: CellPlanes, max_roughness_m: float = MAX_ROUGHNESS_M,
                  max_slope_deg: float = MAX_SLOPE_DEG) -> CellSpread:
        """The rows of the planes of any layers (a layer's strip: ``layer // LAYER_CODE``)."""
        k = planes.height_m.size
        smooth = planes.roughness_m <= max_roughness_m
        flat = np.hypot(planes.gradient[:, 0], planes.gradient[:, 1]) <= np.tan(np.radians(max_slope_deg))
        planar = smooth & flat
        h = planes.height_m
        normals = planes.normals()
        bounds = normals.astype(np.float32)
        inf = np.full(k, np.inf)
        strip = (np.zeros(k, np.int32) if planes.layer is None else planes.layer // LAYER_CODE).astype(np.int32)
        part = cls(planes.cell_ij, strip, np.where(planar, h, -inf), np.where(planar, h, inf), planar.astype(np.int32),
                   np.where(planar[:, None], normals, 0.0),
                   np.where(planar[:, None], bounds, np.float32(np.inf)),
                   np.where(planar[:, None], bounds, np.float32(-np.inf)),
                   np.where(smooth, h, -inf), np.where(smooth, h, inf), smooth.astype(np.int32),
                   (~smooth).astype(np.int32), (smooth & ~flat).astype(np.int32))
        return cls.merge([part])

    @classmethod
    def merge(cls, parts: Iterable[CellSpread | None]) -> CellSpread:
        """One row per cell and strip: the fields of its rows merged (maxima, minima, sums)."""
        parts = [p for p in parts if p is not None]
        if not parts:
            return cls.empty()
        ij = np.concatenate([p.cell_ij for p in parts])
        strip = np.concatenate([p.strip for p in parts])
        if ij.shape[0] == 0:
            return cls.empty()
        order = np.lexsort((strip, cell_keys(ij)))
        ij, strip = ij[order], strip[order]
        new = np.ones(ij.shape[0], dtype=bool)
        new[1:] = np.any(ij[1:] != ij[:-1], axis=1) | (strip[1:] != strip[:-1])
        starts = np.flatnonzero(new)
        return cls(ij[starts], strip[starts], **{
            f: op.reduceat(np.concatenate([getattr(p, f) for p in parts])[order], starts, axis=0)
            for f, op in _FIELDS.items()})

    def to_map(self, cell_size_m: float, coverage: dict[int, np.ndarray] | None = None,
               max_normal_angle_deg: float = 5.0) -> StripDifferenceMap:
        """The gated raster over the bounding box of the cells with a layer within the roughness limit.

        ``coverage``: per strip, the sorted keys (:func:`cell_keys`) of its cells with points
        (``None``: every cell is interior). A cell where at least two layers fit within the
        roughness limit is a candidate; it is gated (module docstring, "Gating") when a layer's
        plane there is rough, or steep, when a strip with a planar layer there does not cover all
        eight neighbours, or when the planar layers' normals disagree; else its value is
        ``high - low`` along the layers' mean normal.
        """
        smooth_rows = self.ungated_layers > 0
        if not np.any(smooth_rows):
            one = np.full((1, 1), np.nan)
            return StripDifferenceMap(one, np.zeros((1, 1), dtype=int), 0.0, cell_size_m, cell_size_m, one.copy(),
                                      np.zeros((1, 1), np.uint8))
        keys = cell_keys(self.cell_ij)
        interior = np.ones(len(self), dtype=bool)
        if coverage is not None:
            for s in np.unique(self.strip):
                rows = np.flatnonzero(self.strip == s)
                interior[rows] = _interior(keys[rows], coverage.get(int(s), np.zeros(0, np.int64)))
        new = np.ones(len(self), dtype=bool)
        new[1:] = keys[1:] != keys[:-1]
        starts = np.flatnonzero(new)
        c = {f: op.reduceat(getattr(self, f), starts, axis=0) for f, op in _FIELDS.items()}
        edge = np.logical_or.reduceat(~interior & (self.layers > 0), starts)
        cells = self.cell_ij[starts]

        candidate = c["ungated_layers"] >= 2
        with np.errstate(invalid="ignore"):
            chord = np.linalg.norm(c["normal_max"] - c["normal_min"], axis=1)  # >= every pair's chord
            disagree = ~(chord <= 2.0 * np.sin(np.radians(max_normal_angle_deg) / 2.0))
        gate = np.select([~candidate, c["rough"] > 0, c["steep"] > 0, edge, disagree],
                         [GATES.index(g) for g in ("none", "rough", "steep", "edge", "normals")],
                         GATES.index("kept")).astype(np.uint8)
        kept = gate == GATES.index("kept")
        normal_z = c["normal_sum"][:, 2] / np.maximum(np.linalg.norm(c["normal_sum"], axis=1), 1e-300)

        ext = cells[c["ungated_layers"] > 0]
        i0, j0 = ext.min(axis=0)
        i1, j1 = ext.max(axis=0)
        inside = c["ungated_layers"] > 0
        cells, gate, kept, candidate = cells[inside], gate[inside], kept[inside], candidate[inside]
        rows, cols = int(j1 - j0 + 1), int(i1 - i0 + 1)
        r = (j1 - cells[:, 1]).astype(np.int64)
        col = (cells[:, 0] - i0).astype(np.int64)
        spread = np.full((rows, cols), np.nan)
        ungated = np.full((rows, cols), np.nan)
        nlay = np.zeros((rows, cols), dtype=int)
        codes = np.zeros((rows, cols), dtype=np.uint8)
        nlay[r, col] = c["ungated_layers"][inside]
        codes[r, col] = gate
        ungated[r[candidate], col[candidate]] = (c["ungated_high_m"] - c["ungated_low_m"])[inside][candidate]
        on = np.flatnonzero(inside)[kept]
        spread[r[kept], col[kept]] = normal_z[on] * (c["high_m"][on] - c["low_m"][on])
        return StripDifferenceMap(spread, nlay, float(i0 * cell_size_m), float((j1 + 1) * cell_size_m), cell_size_m,
                                  ungated, codes)


class Reopened(RuntimeError):
    """Points of a layer x cell arrived after :class:`StripDifferenceStream` had closed it."""


class _Pile:
    """Parts merged into a total once they hold as many rows as it (at least ``_MERGE_ROWS``): every
    row is merged a few times on average and memory stays within a few times the total."""

    def __init__(self, merge) -> None:
        self._merge = merge
        self.total = None
        self.parts: list = []
        self.rows = 0

    def add(self, part) -> None:
        self.parts.append(part)
        self.rows += len(part)
        if self.rows >= max(_MERGE_ROWS, len(self.total) if self.total is not None else 0):
            self.merged()

    def merged(self):
        self.total = self._merge([self.total, *self.parts])
        self.parts, self.rows = [], 0
        return self.total


class StripDifferenceStream:
    """The strip-difference map of points that arrive in chunks (module docstring, "Streaming").

    :meth:`add` takes a chunk's cell sums, one :class:`CellMoments` per layer (any layer codes),
    and its number of records; :meth:`close_layer` declares a layer complete; :meth:`result`
    gives the map. ``close_after``: records after which a layer x cell that got no points is
    closed (``None``: cells are closed only with their layer).
    """

    def __init__(self, cell_size_m: float = 1.0, min_points: int = MIN_POINTS, max_roughness_m: float = MAX_ROUGHNESS_M,
                 *, max_slope_deg: float = MAX_SLOPE_DEG, max_normal_angle_deg: float = MAX_NORMAL_ANGLE_DEG,
                 close_after: int | None = None) -> None:
        self.cell_size_m = float(cell_size_m)
        self.min_points = int(min_points)
        self.max_roughness_m = float(max_roughness_m)
        self.max_slope_deg = float(max_slope_deg)
        self.max_normal_angle_deg = float(max_normal_angle_deg)
        self.close_after = None if close_after is None else max(1, int(close_after))
        self._coverage: dict[int, _Pile] = {}  # per strip: keys of its cells with points
        self._counts = _Pile(CellCounts.merge)  # points per cell, all layers (the density map)
        self._sums: dict[int, _Pile] = {}  # open layers
        self._touched: dict[int, list[np.ndarray]] = {}  # their cells with points since the last closing
        self._closed_cells: dict[int, list[np.ndarray]] = {}  # sorted keys of closed cells of open layers
        self._closed_layers: set[int] = set()
        self._spread = _Pile(CellSpread.merge)
        self._since = 0

    def open_rows(self) -> int:
        """Layer x cell rows held open (sums merged or not)."""
        return sum(p.rows + (len(p.total) if p.total is not None else 0) for p in self._sums.values())

    def add(self, chunk: Sequence[CellMoments], records: int) -> None:
        """The cell sums of the next chunk (one :class:`CellMoments` per layer, rows of one layer)."""
        for m in chunk:
            if len(m) == 0:
                continue
            if m.cell_size_m != self.cell_size_m:
                raise ValueError(f"cell sums of {m.cell_size_m} m added to a stream of {self.cell_size_m} m")
            layer = int(m.layer[0])
            if layer in self._closed_layers:
                raise Reopened(f"layer {layer} has points after it was declared complete")
            keys = cell_keys(m.cell_ij)
            for closed in self._closed_cells.get(layer, ()):
                at = np.minimum(np.searchsorted(closed, keys), closed.size - 1)
                if np.any(closed[at] == keys):
                    raise Reopened(f"layer {layer} has points in a cell it left more than {self.close_after} "
                                   "records before")
            self._sums.setdefault(layer, _Pile(CellMoments.merge)).add(m)
            self._coverage.setdefault(layer // LAYER_CODE, _Pile(_union)).add(keys)
            self._counts.add(CellCounts(keys, np.rint(m.sums[:, 0]).astype(np.int64)))
            if self.close_after is not None:
                self._touched.setdefault(layer, []).append(keys)
        self._since += int(records)
        if self.close_after is not None and self._since >= self.close_after:
            self._close_untouched()
            self._since = 0

    def _fold(self, m: CellMoments) -> None:
        """Fold closed rows' planes into the spread."""
        if len(m):
            self._spread.add(CellSpread.of_planes(m.planes(self.min_points), self.max_roughness_m, self.max_slope_deg))

    def _close_untouched(self) -> None:
        """Close the rows of open layers that got no points since the last closing."""
        for layer, pile in self._sums.items():
            total = pile.merged()
            keys = cell_keys(total.cell_ij)  # sorted: merged rows are
            idle = np.ones(len(total), dtype=bool)
            for t in self._touched.pop(layer, []):  # keys are in the total: mark them
                idle[np.searchsorted(keys, t)] = False
            if not np.any(idle):
                continue
            self._fold(total.take(idle))
            closed = self._closed_cells.setdefault(layer, [])
            closed.append(keys[idle])
            if len(closed) > 8:  # one sorted array now and then keeps the checks cheap
                closed[:] = [np.sort(np.concatenate(closed))]
            pile.total = total.take(~idle)

    def close_layer(self, layer: int) -> None:
        """Declare ``layer`` complete: its planes go into the spread, its sums are dropped."""
        layer = int(layer)
        pile = self._sums.pop(layer, None)
        if pile is not None:
            self._fold(pile.merged())
        self._touched.pop(layer, None)
        self._closed_cells.pop(layer, None)
        self._closed_layers.add(layer)

    def coverage(self) -> CoverageMap:
        """Points and strips per cell of everything added so far (:mod:`georefine.evaluation.coverage`)."""
        return coverage_map(self._counts.merged(), {strip: pile.merged() for strip, pile in self._coverage.items()},
                            self.cell_size_m)

    def result(self) -> StripDifferenceMap:
        """The gated map of everything added (every layer is closed)."""
        for layer in list(self._sums):
            self.close_layer(layer)
        coverage = {strip: pile.merged() for strip, pile in self._coverage.items()}
        return self._spread.merged().to_map(self.cell_size_m, coverage, self.max_normal_angle_deg)


def strip_differences(
    layers: list[np.ndarray], cell_size_m: float = 1.0, min_points: int = MIN_POINTS,
    max_roughness_m: float = MAX_ROUGHNESS_M, *, max_slope_deg: float = MAX_SLOPE_DEG,
    max_normal_angle_deg: float = MAX_NORMAL_ANGLE_DEG,
) -> StripDifferenceMap:
    """The strip-difference raster of point layers in memory (each ``(N, 3)`` in a projected CRS,
    each its own strip)."""
    stream = StripDifferenceStream(cell_size_m, min_points, max_roughness_m, max_slope_deg=max_slope_deg,
                                   max_normal_angle_deg=max_normal_angle_deg)
    stream.add([cell_moments(x, cell_size_m, k * LAYER_CODE) for k, x in enumerate(layers)], sum(map(len, layers)))
    return stream.result()


def crop(m: StripDifferenceMap, window: tuple[float, float, float, float]) -> StripDifferenceMap:
    """The part of ``m`` inside ``(xmin, xmax, ymin, ymax)`` (whole cells)."""
    xmin, xmax, ymin, ymax = window
    rows, cols = m.spread_m.shape
    c0 = int(np.clip(np.floor((xmin - m.x0) / m.cell_size_m), 0, cols))
    c1 = int(np.clip(np.ceil((xmax - m.x0) / m.cell_size_m), c0, cols))
    r0 = int(np.clip(np.floor((m.y1 - ymax) / m.cell_size_m), 0, rows))
    r1 = int(np.clip(np.ceil((m.y1 - ymin) / m.cell_size_m), r0, rows))
    if c1 <= c0 or r1 <= r0:
        raise ValueError(f"crop window {window} does not overlap the map")
    return StripDifferenceMap(m.spread_m[r0:r1, c0:c1], m.layers_m[r0:r1, c0:c1], m.x0 + c0 * m.cell_size_m,
                              m.y1 - r0 * m.cell_size_m, m.cell_size_m, m.ungated_m[r0:r1, c0:c1], m.gate[r0:r1, c0:c1])


BAND_DESCRIPTION = "strip difference along the surface normal (max - min over planar strip x channel planes)"
"""The GeoTIFF band's description (GDAL's band description)."""


def _gdal_metadata(description: str, unit: str) -> str:
    """The GDAL_METADATA TIFF tag (42112): band 1's description and unit type, as GDAL writes them."""
    from xml.sax.saxutils import escape

    return ("<GDALMetadata>\n"
            f'  <Item name="DESCRIPTION" sample="0" role="description">{escape(description)}</Item>\n'
            f'  <Item name="UNITTYPE" sample="0" role="unittype">{escape(unit)}</Item>\n'
            "</GDALMetadata>\n")


def write_geotiff(path: str | Path, m: StripDifferenceMap, epsg: int) -> Path:
    """GeoTIFF of the map (float32 metres) in the projected CRS ``epsg``, Deflate-compressed.

    GeoKeys: projected model, pixel is area, ``ProjectedCSTypeGeoKey = epsg`` (GDAL and PROJ
    identify the EPSG code from it); model tie point at the north-west corner and pixel scale.
    Band description and unit type (``metre``) in the GDAL_METADATA tag (42112), no-data NaN in
    GDAL_NODATA (42113): the tags GDAL itself writes for them.
    """
    import tifffile

    from georefine import __version__

    geokeys = [
        1, 1, 0, 3,  # GeoKeyDirectory version 1.1.0, 3 keys
        1024, 0, 1, 1,  # GTModelTypeGeoKey = ModelTypeProjected
        1025, 0, 1, 1,  # GTRasterTypeGeoKey = RasterPixelIsArea
        3072, 0, 1, int(epsg),  # ProjectedCSTypeGeoKey
    ]
    extratags = [
        (33550, "d", 3, (m.cell_size_m, m.cell_size_m, 0.0), False),  # ModelPixelScaleTag
        (33922, "d", 6, (0.0, 0.0, 0.0, m.x0, m.y1, 0.0), False),  # ModelTiepointTag: pixel (0,0) corner
        (34735, "H", len(geokeys), tuple(geokeys), False),  # GeoKeyDirectoryTag
        (42112, "s", 0, _gdal_metadata(BAND_DESCRIPTION, "metre"), False),  # GDAL_METADATA
        (42113, "s", 0, "nan", False),  # GDAL_NODATA
    ]
    path = Path(path)
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, m.spread_m.astype(np.float32), extratags=extratags, photometric="minisblack",
                         compression="zlib", metadata=None, software=f"georefine {__version__}")
    return path
