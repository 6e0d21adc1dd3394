"""The matrix of strip-pair differences: every two overlapping strips compared (docs/ARCHITECTURE.md §5).

The strip-difference raster (:mod:`georefine.evaluation.strip_differences`) gives one spread per
cell over all layers (strip x scanner channel). A block of many strips (parallel strips with
sidelap, cross strips, several flights) is judged pair by pair instead, as TerraMatch's "Measure
Match" does: for every two strips ``a < b`` that both have a planar fit in a cell, the
difference of their planes at the cell centre, and per pair the number of such cells and the
median, P95 and RMS of the absolute difference and the median of the signed one (strip ``b``
above strip ``a`` is positive), in mm (:class:`StripPairDifferences`).

The planes are those of the raster, from the same streamed per-cell moment sums
(:class:`StripPairStream` is a :class:`~georefine.evaluation.strip_differences.StripDifferenceStream`;
its closing of the cells the scanner has left, its checks and its per-cell-and-strip records
:class:`~georefine.evaluation.strip_differences.CellSpread` are the raster's). Per layer, then
combined per strip: every channel of a strip gets its own plane, is gated on its own (rough,
steep) as in the raster, and a strip's height in a cell is the centre ``(high + low) / 2`` of its
planar layers' heights (their mean for one or two channels). Fitting a strip's channels together
would mix views from different directions into one plane: a disagreement between the channels
(their own boresight, the forward and backward looks of a facet mirror) would then show as
roughness -- failing the roughness gate or hiding in the fit -- instead of as the spread between
layers the raster shows; per layer, each plane is a single view, as in the raster, and the pair
figures compare the strips' centres. The difference of strips ``a`` and ``b`` in a cell is
``n_z (h_b - h_a)`` with ``n`` the mean normal of their planar layers: the distance between
(nearly) parallel planes, so a shift along a slope is not counted as a height difference.

Gating, with the raster's constants (:data:`~georefine.evaluation.strip_differences.MAX_ROUGHNESS_M`,
:data:`~georefine.evaluation.strip_differences.MAX_SLOPE_DEG`,
:data:`~georefine.evaluation.strip_differences.MAX_NORMAL_ANGLE_DEG`, ``MIN_POINTS``). A cell counts
for a pair only where it is a planar surface in every view of it and both strips see the whole
cell:

* ``rough`` and ``steep`` apply to the cell, over every layer of every strip there: they say the
  surface is not one plane (a wire over the ground, a crown, a facade), whichever strip saw it;
* ``edge`` applies to the pair: strip ``a`` or ``b`` does not cover all eight neighbouring cells
  with points (the side or end of its swath, a shadow), so its plane may fit part of the cell; a
  third strip's swath border there does not touch the planes of ``a`` and ``b``;
* ``normals`` applies to the pair: the normals of the planar layers of ``a`` and ``b`` differ by
  more than ``max_normal_angle_deg`` (the bounding box of their components, as in the raster).

Where the raster keeps a cell, every pair planar there is kept, and with one channel per strip
the largest pair difference is the raster's value (up to the mean normal: the pair's, not the
cell's). A pair with fewer than :data:`MIN_PAIR_CELLS` common kept cells is listed without
figures ("not overlapping / too few cells"; ``cells`` says which).

One read. :func:`scan_clouds_with_pairs` runs :func:`~georefine.evaluation.clouds.scan_clouds`
unchanged and hands every chunk's cell sums, as the scan takes them, to a
:class:`StripPairStream` as well (through the task runner the scan is given), so the files are
read once for the raster, the coverage, the reference planes and the pairs; when the scan reads
again with every cell open (a strip split over files), the pairs' stream does too. The price is
a second stream in this process: its open cells and its per-cell-and-strip records, about as
much as the raster's (both bounded by the cells, not the points), and its merging (three strips
of 3 M points each, read in one process: 24 s for the scan alone, 28.5 s with the pairs). Memory
then: the open cells of the last few chunks, one record per cell and strip
(:class:`~georefine.evaluation.strip_differences.CellSpread`), at the end one per kept cell and
pair (:class:`PairCells`, 40 bytes), never the points.

Outputs: ``strip_pairs.csv`` (:func:`write_pairs_csv`) and the matrix of the medians
(:func:`write_pairs_png`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from georefine.errors import GeorefineError, InputError
from georefine.evaluation.cell_moments import cell_keys, cell_moments
from georefine.evaluation.clouds import CLOSE_AFTER_POINTS, CloudScan, scan_chunk, scan_clouds
from georefine.evaluation.figures import save_png
from georefine.evaluation.strip_differences import (
    LAYER_CODE,
    MAX_NORMAL_ANGLE_DEG,
    MAX_ROUGHNESS_M,
    MAX_SLOPE_DEG,
    MIN_POINTS,
    CellSpread,
    StripDifferenceStream,
)
from georefine.io.files import write_csv
from georefine.tasks import TaskRunner

__all__ = [
    "MIN_PAIR_CELLS", "CSV_HEADER", "PairCells", "pair_cells", "StripPair", "StripPairDifferences",
    "StripPairStream", "strip_pair_differences", "scan_clouds_with_pairs", "write_pairs_csv", "pairs_figure",
    "write_pairs_png",
]

MIN_PAIR_CELLS = 50
"""Common kept cells (1 m: m²) a pair needs for figures. The P95 of 50 cells still has two or
three cells above it, and their median scatters by about 1.25 / sqrt(50) = 0.18 of the per-cell
scatter (about 1 mm at 5 mm range noise), well below the centimetres a misalignment makes.
Fewer come from strips that meet only at a corner or at a swath's end, or from an overlap that
is all trees or water, where a handful of cells would give a median of noise and a P95 that is
just the largest value."""

CSV_HEADER = ("strip_a", "strip_b", "cells", "median_mm", "p95_mm", "rms_mm", "signed_median_mm")
"""Columns of ``strip_pairs.csv`` (:func:`write_pairs_csv`)."""

_NEIGHBOURS = np.array([di * (1 << 32) + dj for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj], dtype=np.int64)
"""Key offsets (:func:`~georefine.evaluation.cell_moments.cell_keys`) of a cell's eight neighbours."""


def _interior(keys: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """Which cells (``keys``) have all eight neighbours among ``covered`` (a strip's sorted cell
    keys with points): the raster's edge rule."""
    if covered.size == 0:
        return np.zeros(keys.size, dtype=bool)
    nk = keys[:, None] + _NEIGHBOURS[None, :]
    at = np.minimum(np.searchsorted(covered, nk), covered.size - 1)
    return np.all(covered[at] == nk, axis=1)


@dataclass(frozen=True)
class PairCells:
    """Per kept cell and pair of strips planar there, the difference of their planes (module
    docstring): ``strip_a < strip_b``, ``difference_m`` signed, strip ``b`` above ``a`` positive,
    along the pair's mean normal."""

    cell_ij: np.ndarray  # (K, 2) int64
    strip_a: np.ndarray  # (K,) int64
    strip_b: np.ndarray  # (K,) int64
    difference_m: np.ndarray  # (K,) float64

    def __len__(self) -> int:
        return int(self.difference_m.size)


def pair_cells(spread: CellSpread, coverage: Mapping[int, np.ndarray] | None = None,
               max_normal_angle_deg: float = MAX_NORMAL_ANGLE_DEG) -> PairCells:
    """The kept cells of every pair of strips from the raster's per-cell-and-strip records.

    ``spread``: merged (rows sorted by cell and strip, :meth:`CellSpread.merge`); ``coverage``:
    per strip the sorted keys of its cells with points (``None``: every cell is interior).
    Gating as the module docstring says: ``rough``/``steep`` over the cell, ``edge``/``normals``
    over the pair.
    """
    empty = PairCells(np.zeros((0, 2), np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    if len(spread) == 0:
        return empty
    keys = cell_keys(spread.cell_ij)
    new = np.ones(keys.size, dtype=bool)
    new[1:] = keys[1:] != keys[:-1]
    starts = np.flatnonzero(new)
    cell = np.cumsum(new) - 1
    surface = (np.add.reduceat(spread.rough, starts) == 0) & (np.add.reduceat(spread.steep, starts) == 0)
    rows = np.flatnonzero((spread.layers > 0) & surface[cell])
    if rows.size < 2:
        return empty
    key, strip = keys[rows], spread.strip[rows].astype(np.int64)
    height = 0.5 * (spread.high_m[rows] + spread.low_m[rows])
    nsum, nmin, nmax = spread.normal_sum[rows], spread.normal_min[rows], spread.normal_max[rows]
    interior = np.ones(rows.size, dtype=bool)
    if coverage is not None:
        for s in np.unique(strip):
            on = np.flatnonzero(strip == s)
            interior[on] = _interior(key[on], coverage.get(int(s), np.zeros(0, np.int64)))
    limit = 2.0 * np.sin(np.radians(max_normal_angle_deg) / 2.0)
    out_a, out_b, out_d = [], [], []
    for d in range(1, rows.size):  # rows of a cell are consecutive, by strip: row r and r + d of one cell
        a = np.arange(rows.size - d)
        b = a + d
        same = key[a] == key[b]
        if not np.any(same):  # no cell has more than d planar strips
            break
        a, b = a[same], b[same]
        chord = np.linalg.norm(np.maximum(nmax[a], nmax[b]) - np.minimum(nmin[a], nmin[b]), axis=1)
        keep = interior[a] & interior[b] & (chord <= limit)
        a, b = a[keep], b[keep]
        n = nsum[a] + nsum[b]
        normal_z = n[:, 2] / np.linalg.norm(n, axis=1)
        out_a.append(a)
        out_b.append(b)
        out_d.append(normal_z * (height[b] - height[a]))
    if not out_a:
        return empty
    a, b = np.concatenate(out_a), np.concatenate(out_b)
    order = np.lexsort((strip[b], strip[a], key[a]))
    a, b = a[order], b[order]
    return PairCells(spread.cell_ij[rows[a]], strip[a], strip[b], np.concatenate(out_d)[order])


def _mm(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


@dataclass(frozen=True)
class StripPair:
    """The figures of one pair of strips (``strip_a < strip_b``), in mm; ``None`` (all four) when
    the pair has fewer than the minimum of common kept cells (``cells``; 0: not overlapping)."""

    strip_a: int
    strip_b: int
    cells: int
    median_mm: float | None = None  # of |difference|
    p95_mm: float | None = None  # of |difference|
    rms_mm: float | None = None  # of the difference
    signed_median_mm: float | None = None  # strip b above strip a positive

    @property
    def measured(self) -> bool:
        """Whether the pair has figures (enough common kept cells)."""
        return self.median_mm is not None

    def to_dict(self) -> dict[str, Any]:
        return {"strip_a": self.strip_a, "strip_b": self.strip_b, "cells": self.cells, "median_mm": self.median_mm,
                "p95_mm": self.p95_mm, "rms_mm": self.rms_mm, "signed_median_mm": self.signed_median_mm}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StripPair:
        return cls(int(d["strip_a"]), int(d["strip_b"]), int(d["cells"]), _mm(d.get("median_mm")),
                   _mm(d.get("p95_mm")), _mm(d.get("rms_mm")), _mm(d.get("signed_median_mm")))


@dataclass(frozen=True)
class StripPairDifferences:
    """Every pair of the strips with points, sorted by ``(strip_a, strip_b)``; figures for the
    pairs with at least ``min_cells`` common kept cells (module docstring)."""

    strips: tuple[int, ...]
    pairs: tuple[StripPair, ...]
    min_cells: int = MIN_PAIR_CELLS
    cell_size_m: float = 1.0

    def pair(self, a: int, b: int) -> StripPair:
        """The pair of strips ``a`` and ``b`` (either order)."""
        lo, hi = sorted((int(a), int(b)))
        for p in self.pairs:
            if (p.strip_a, p.strip_b) == (lo, hi):
                return p
        raise KeyError(f"no pair of strips {lo} and {hi} (strips {list(self.strips)})")

    def measured(self) -> tuple[StripPair, ...]:
        """The pairs with figures."""
        return tuple(p for p in self.pairs if p.measured)

    def unmeasured(self) -> tuple[StripPair, ...]:
        """The pairs not overlapping or with too few common kept cells."""
        return tuple(p for p in self.pairs if not p.measured)

    @classmethod
    def from_cells(cls, cells: PairCells, strips: Sequence[int], min_cells: int = MIN_PAIR_CELLS,
                   cell_size_m: float = 1.0) -> StripPairDifferences:
        """The figures of ``cells`` (:func:`pair_cells`) for every pair of ``strips``."""
        strips = tuple(sorted({int(s) for s in strips}))
        code = cells.strip_a * (1 << 32) + cells.strip_b
        order = np.argsort(code, kind="stable")
        code, diff_mm = code[order], cells.difference_m[order] * 1e3
        found, first, count = np.unique(code, return_index=True, return_counts=True)
        where = {int(c): (int(f), int(n)) for c, f, n in zip(found, first, count)}
        pairs = []
        for i, a in enumerate(strips):
            for b in strips[i + 1:]:
                f, n = where.get(a * (1 << 32) + b, (0, 0))
                if n < min_cells:
                    pairs.append(StripPair(a, b, n))
                    continue
                d = diff_mm[f:f + n]
                ad = np.abs(d)
                pairs.append(StripPair(a, b, n, float(np.median(ad)), float(np.percentile(ad, 95)),
                                       float(np.sqrt(np.mean(d * d))), float(np.median(d))))
        return cls(strips, tuple(pairs), int(min_cells), float(cell_size_m))

    def to_dict(self) -> dict[str, Any]:
        return {"cell_size_m": self.cell_size_m, "min_cells": self.min_cells, "strips": list(self.strips),
                "pairs": [p.to_dict() for p in self.pairs]}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StripPairDifferences:
        return cls(tuple(int(s) for s in d["strips"]), tuple(StripPair.from_dict(p) for p in d["pairs"]),
                   int(d["min_cells"]), float(d["cell_size_m"]))


class StripPairStream(StripDifferenceStream):
    """The strip-difference stream (same arguments, same :meth:`add`, :meth:`close_layer`,
    :meth:`result`) that also gives the strip-pair differences of everything added (:meth:`pairs`)."""

    def _close_all(self) -> None:
        for layer in list(self._sums):
            self.close_layer(layer)

    def _strip_coverage(self) -> dict[int, np.ndarray]:
        return {strip: pile.merged() for strip, pile in self._coverage.items()}

    def pair_cells(self) -> PairCells:
        """The kept cells of every pair (:func:`pair_cells`); every layer is closed."""
        self._close_all()
        return pair_cells(self._spread.merged(), self._strip_coverage(), self.max_normal_angle_deg)

    def pairs(self, min_cells: int = MIN_PAIR_CELLS) -> StripPairDifferences:
        """The figures of every pair of the strips added (every layer is closed).

        Raises :class:`~georefine.errors.InputError` when no points were added: there is no
        strip to compare, and an empty matrix of NaN would read as a result.
        """
        strips = sorted(self._strip_coverage())
        if not strips:
            raise InputError("no points to compare: the strip-pair differences need the points of at least two "
                             "strips", found="no points")
        return StripPairDifferences.from_cells(self.pair_cells(), strips, min_cells, self.cell_size_m)


def strip_pair_differences(
    layers: Mapping[tuple[int, int], np.ndarray], cell_size_m: float = 1.0, min_points: int = MIN_POINTS,
    max_roughness_m: float = MAX_ROUGHNESS_M, *, max_slope_deg: float = MAX_SLOPE_DEG,
    max_normal_angle_deg: float = MAX_NORMAL_ANGLE_DEG, min_cells: int = MIN_PAIR_CELLS,
) -> StripPairDifferences:
    """The strip-pair differences of point layers in memory: ``{(strip, channel): (N, 3) points}``
    in a projected CRS. Raises :class:`~georefine.errors.InputError` without points."""
    stream = StripPairStream(cell_size_m, min_points, max_roughness_m, max_slope_deg=max_slope_deg,
                             max_normal_angle_deg=max_normal_angle_deg)
    chunk = [cell_moments(xyz, cell_size_m, int(s) * LAYER_CODE + int(c)) for (s, c), xyz in layers.items()
             if len(xyz)]
    stream.add(chunk, sum(len(x) for x in layers.values()))
    return stream.pairs(min_cells)


class _ChunkTee:
    """A task runner that hands every chunk :func:`scan_clouds` scans to a :class:`StripPairStream`
    too, in the order the scan takes them, closing cells as the scan does: by idle records and at
    the end of each file on the first read, not at all on a read again (after
    :class:`~georefine.evaluation.strip_differences.Reopened`)."""

    def __init__(self, runner: TaskRunner, make_stream, close_after: int | None) -> None:
        self._runner = runner
        self._make_stream = make_stream
        self._close_after = close_after
        self._reads = 0
        self._complete = False
        self.stream: StripPairStream | None = None

    def __getattr__(self, name: str):
        return getattr(self._runner, name)

    def map(self, fn, args, **kwargs):
        if fn is not scan_chunk:
            yield from self._runner.map(fn, args, **kwargs)
            return
        tasks = list(args)
        closing = self._reads == 0
        self._reads += 1
        self._complete = False
        stream = self.stream = self._make_stream(self._close_after if closing else None)
        last = {f: k for k, (f, *_) in enumerate(tasks)}
        in_file: set[int] = set()
        inner = self._runner.map(fn, tasks, **kwargs)
        try:
            for k, part in enumerate(inner):
                path, start, stop = tasks[k][:3]
                stream.add(part.moments, stop - start)
                in_file.update(part.layers.tolist())
                if last[path] == k:
                    if closing:
                        for code in in_file:
                            stream.close_layer(code)
                    in_file = set()
                yield part
            self._complete = True
        finally:
            inner.close()

    def pairs(self, min_cells: int) -> StripPairDifferences:
        if self.stream is None or not self._complete:
            raise GeorefineError("the point-cloud scan did not hand its chunks to the strip-pair differences")
        return self.stream.pairs(min_cells)


def scan_clouds_with_pairs(
    files: list[Path], *, cell_size_m: float = 1.0, min_points: int = MIN_POINTS,
    max_roughness_m: float = MAX_ROUGHNESS_M, max_slope_deg: float = MAX_SLOPE_DEG,
    max_normal_angle_deg: float = MAX_NORMAL_ANGLE_DEG, min_cells: int = MIN_PAIR_CELLS,
    runner: TaskRunner | None = None, close_after: int | None = CLOSE_AFTER_POINTS, **scan: Any,
) -> tuple[CloudScan, StripPairDifferences]:
    """:func:`~georefine.evaluation.clouds.scan_clouds` of ``files`` (``scan``: its other
    arguments) and the strip-pair differences of the same chunks: the files are read once
    (module docstring, "One read"). Raises :class:`~georefine.errors.InputError` when the files
    hold no points."""
    runner = runner or TaskRunner("sync")

    def make_stream(close: int | None) -> StripPairStream:
        return StripPairStream(cell_size_m, min_points, max_roughness_m, max_slope_deg=max_slope_deg,
                               max_normal_angle_deg=max_normal_angle_deg, close_after=close)

    tee = _ChunkTee(runner, make_stream, close_after)
    result = scan_clouds(files, cell_size_m=cell_size_m, min_points=min_points, max_roughness_m=max_roughness_m,
                         max_slope_deg=max_slope_deg, max_normal_angle_deg=max_normal_angle_deg, runner=tee,
                         close_after=close_after, **scan)
    return result, tee.pairs(min_cells)


def _fmt(x: float | None) -> str:
    return "" if x is None else f"{x:.2f}"


def write_pairs_csv(path: str | Path, result: StripPairDifferences) -> Path:
    """``strip_pairs.csv``: one row per pair (:data:`CSV_HEADER`), mm with two decimals; the
    figures of a pair without enough common cells are empty (``cells`` then says how many)."""
    path = Path(path)
    write_csv(path, CSV_HEADER, [[p.strip_a, p.strip_b, p.cells, _fmt(p.median_mm), _fmt(p.p95_mm), _fmt(p.rms_mm),
                                  _fmt(p.signed_median_mm)] for p in result.pairs])
    return path


FONT_PT = 9.0
"""Smallest text on the matrix (the numbers in its cells)."""


def pairs_figure(result: StripPairDifferences, *, title: str = "", vmax_mm: float = 50.0):
    """The matrix of the pairs' medians of |difference| (mm): strips on both axes (symmetric),
    a number in every cell with figures, 0-``vmax_mm`` green to red (beyond in purple), "–" where
    the pair does not overlap or has too few common cells. Returns the matplotlib figure."""
    import matplotlib
    from matplotlib import patheffects
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import ListedColormap
    from matplotlib.figure import Figure

    strips = result.strips
    n = len(strips)
    side = max(4.5, 0.55 * n + 2.5)
    fig = Figure(figsize=(side + 1.2, side), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    at = {s: k for k, s in enumerate(strips)}
    values = np.full((n, n), np.nan)
    for p in result.measured():
        values[at[p.strip_a], at[p.strip_b]] = values[at[p.strip_b], at[p.strip_a]] = p.median_mm
    cmap = matplotlib.colormaps["RdYlGn_r"].with_extremes(bad=(0.88, 0.88, 0.88), over=(0.45, 0.05, 0.55))
    im = ax.imshow(values, cmap=cmap, vmin=0.0, vmax=vmax_mm, interpolation="nearest", origin="upper")
    diagonal = np.where(np.eye(n, dtype=bool), 1.0, np.nan)  # a strip with itself: white
    ax.imshow(diagonal, cmap=ListedColormap(["white"]).with_extremes(bad=(0, 0, 0, 0)), interpolation="nearest",
              origin="upper")
    outline = [patheffects.withStroke(linewidth=2.0, foreground="white")]
    for i in range(n):
        for j in range(n):
            if i == j:
                continue
            v = values[i, j]
            text = "–" if not np.isfinite(v) else (f"{v:.1f}" if v < 100 else f"{v:.0f}")
            ax.text(j, i, text, ha="center", va="center", fontsize=FONT_PT, path_effects=outline)
    ax.set_xticks(range(n), [str(s) for s in strips], fontsize=FONT_PT + 1)
    ax.set_yticks(range(n), [str(s) for s in strips], fontsize=FONT_PT + 1)
    ax.set_xlabel("strip", fontsize=FONT_PT + 1)
    ax.set_ylabel("strip", fontsize=FONT_PT + 1)
    measured = len(result.measured())
    ax.set_title((title or "strip-pair differences") + "\nmedian |difference| per pair [mm]\n"
                 f"{measured} of {len(result.pairs)} pairs with ≥ {result.min_cells} common planar cells (–: fewer)",
                 fontsize=FONT_PT + 1)
    bar = fig.colorbar(im, ax=ax, shrink=0.8, extend="max")
    bar.set_label("median |difference| [mm]", fontsize=FONT_PT + 1)
    bar.ax.tick_params(labelsize=FONT_PT + 1)
    return fig


def write_pairs_png(path: str | Path, result: StripPairDifferences, *, title: str = "", vmax_mm: float = 50.0) -> Path:
    """The matrix of :func:`pairs_figure` as PNG, written atomically (:func:`~georefine.evaluation.figures.save_png`)."""
    return save_png(pairs_figure(result, title=title, vmax_mm=vmax_mm), path, 110)
