"""Point density and strip overlap: what a surveyor checks of a delivery before its accuracy.

The strip-difference scan (:class:`~georefine.evaluation.strip_differences.StripDifferenceStream`)
sees every point once, in chunks; on the same raster it counts the points per cell
(:class:`CellCounts`, merged as chunks arrive: memory grows with the cells, not the points) and
knows which strips have points in each cell. :func:`coverage_map` turns both into a
:class:`CoverageMap`: points per square metre and strips per cell, the two maps a project's
specification is written against (e.g. "at least 8 points/m², every place seen from two strips").
:func:`write_coverage_png` draws them tiled along the corridor at equal aspect, as the
strip-difference map is drawn (:mod:`georefine.evaluation.strip_difference_maps`).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["COVERAGE_MAPS", "CellCounts", "CoverageMap", "coverage_map", "write_coverage_png"]


@dataclass(frozen=True)
class CellCounts:
    """Points per cell: sorted cell keys (:func:`~georefine.evaluation.cell_moments.cell_keys`) and counts."""

    keys: np.ndarray  # (C,) int64, sorted, unique once merged
    n: np.ndarray  # (C,) int64

    def __len__(self) -> int:
        return int(self.keys.size)

    @classmethod
    def empty(cls) -> CellCounts:
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64))

    @classmethod
    def merge(cls, parts: Iterable[CellCounts | None]) -> CellCounts:
        """One row per cell, the counts of its rows added."""
        parts = [p for p in parts if p is not None and len(p)]
        if not parts:
            return cls.empty()
        keys = np.concatenate([p.keys for p in parts])
        n = np.concatenate([p.n for p in parts])
        order = np.argsort(keys, kind="stable")
        keys, n = keys[order], n[order]
        new = np.ones(keys.size, dtype=bool)
        new[1:] = keys[1:] != keys[:-1]
        starts = np.flatnonzero(new)
        return cls(keys[starts], np.add.reduceat(n, starts))


def _ij(keys: np.ndarray) -> np.ndarray:
    """Cell indices of :func:`~georefine.evaluation.cell_moments.cell_keys` keys."""
    return np.column_stack([keys >> 32, (keys & 0xFFFFFFFF) - (1 << 31)])


@dataclass(frozen=True)
class CoverageMap:
    """Points per cell and strips per cell on one raster; row 0 is the northern edge."""

    points: np.ndarray  # (rows, cols) int32, 0 where no point (4 bytes a cell beside the map's 25)
    strips: np.ndarray  # (rows, cols) uint8 strips with points in the cell
    x0: float
    y1: float
    cell_size_m: float
    covered_m2: np.ndarray | None = None  # (rows, cols) area of a cell with points (None: the whole cell)

    def density(self) -> np.ndarray:
        """Points per square metre of the covered area, NaN outside the covered cells."""
        area = self.cell_size_m ** 2 if self.covered_m2 is None else np.maximum(self.covered_m2, 1e-300)
        return np.where(self.points > 0, self.points / area, np.nan)

    def coarse(self, factor: int) -> CoverageMap:
        """The map on cells ``factor`` times larger: points added, strips the most of the small cells,
        the covered area that of the small cells with points (so that the corridor's edge does not
        thin out); the edges of the raster padded with empty cells."""
        k = int(factor)
        if k <= 1:
            return self
        rows, cols = self.points.shape
        pr, pc = -rows % k, -cols % k

        def blocks(a, op):
            a = np.pad(a, ((0, pr), (0, pc)))
            return op(a.reshape((rows + pr) // k, k, (cols + pc) // k, k), axis=(1, 3))

        area = np.where(self.points > 0, self.cell_size_m ** 2, 0.0) if self.covered_m2 is None else self.covered_m2
        return CoverageMap(blocks(self.points, np.sum), blocks(self.strips, np.max).astype(np.uint8), self.x0,
                           self.y1, self.cell_size_m * k, blocks(area, np.sum))

    def summary(self) -> dict[str, float]:
        """Covered area (km²), density (points/m²: median, 5th and 95th percentile over the covered
        cells), share of the covered area seen from at least two strips, most strips on a cell."""
        covered = self.points > 0
        if not np.any(covered):
            return {"area_km2": 0.0, "density_median_per_m2": float("nan"), "density_p5_per_m2": float("nan"),
                    "density_p95_per_m2": float("nan"), "overlap_share": float("nan"), "max_strips": 0}
        d = self.points[covered] / self.cell_size_m ** 2
        p5, p50, p95 = np.percentile(d, [5.0, 50.0, 95.0])
        return {"area_km2": float(np.count_nonzero(covered) * self.cell_size_m ** 2 / 1e6),
                "density_median_per_m2": float(p50), "density_p5_per_m2": float(p5),
                "density_p95_per_m2": float(p95),
                "overlap_share": float(np.count_nonzero(self.strips >= 2) / np.count_nonzero(covered)),
                "max_strips": int(self.strips.max())}


def coverage_map(counts: CellCounts, strips: dict[int, np.ndarray], cell_size_m: float) -> CoverageMap:
    """The rasters of ``counts`` (all layers) and of ``strips`` (per strip, the sorted keys of its
    cells with points), over the bounding box of the counted cells."""
    if len(counts) == 0:
        return CoverageMap(np.zeros((1, 1), np.int32), np.zeros((1, 1), np.uint8), 0.0, cell_size_m, cell_size_m)
    ij = _ij(counts.keys)
    i0, j0 = ij.min(axis=0)
    i1, j1 = ij.max(axis=0)
    rows, cols = int(j1 - j0 + 1), int(i1 - i0 + 1)
    points = np.zeros((rows, cols), np.int32)
    points[j1 - ij[:, 1], ij[:, 0] - i0] = counts.n
    seen = np.zeros((rows, cols), np.uint8)
    for keys in strips.values():
        s = _ij(np.asarray(keys, dtype=np.int64))
        inside = (s[:, 0] >= i0) & (s[:, 0] <= i1) & (s[:, 1] >= j0) & (s[:, 1] <= j1)
        seen[j1 - s[inside, 1], s[inside, 0] - i0] += 1
    return CoverageMap(points, seen, float(i0 * cell_size_m), float((j1 + 1) * cell_size_m), float(cell_size_m))


COVERAGE_MAPS = ("density", "overlap")
"""What :func:`write_coverage_png` draws."""


DRAWN_CELL_M = 5.0
"""Cell size of the drawn density map: on 1 m cells the scan lines beat with the raster (a moiré
of +-30 %) and a facade's points fall on one cell; 5 m cells show the density a specification
asks for and keep the picture a tenth the size."""


def write_coverage_png(path: str | Path, m: CoverageMap, what: str, *, title: str = "", epsg: int | None = None,
                       sites: list[tuple[str, float, float]] | None = None) -> Path:
    """One of the two maps (``what`` in :data:`COVERAGE_MAPS`), tiled along the corridor at equal
    aspect: ``"density"``, points per m² (colour scale to the 99th percentile, denser cells in the
    top colour and the colour bar so marked); ``"overlap"``, strips per cell (one colour per count,
    cells of a single strip, which nothing checks, in orange). ``sites`` ``(label, x, y)`` marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import BoundaryNorm, ListedColormap

    from georefine.evaluation.figures import save_png
    from georefine.evaluation.map_panels import label_axes, mark_sites, tiled_axes

    if what not in COVERAGE_MAPS:
        raise ValueError(f"coverage map {what!r}: expected one of {COVERAGE_MAPS}")
    s, cell = m.summary(), m.cell_size_m  # the figures on the raster's cells
    if what == "density":
        m = m.coarse(max(1, int(round(DRAWN_CELL_M / m.cell_size_m))))
        rows, cols = m.points.shape
        fig, axes, panels = tiled_axes(rows, cols, m.x0, m.y1, m.cell_size_m)
        grid = m.density()
        finite = grid[np.isfinite(grid)]
        top = max(float(np.percentile(finite, 99.0)), 1e-9) if finite.size else 1.0
        kw = {"cmap": plt.get_cmap("viridis").with_extremes(bad=(1.0, 1.0, 1.0, 0.0), over="magenta"),
              "vmin": 0.0, "vmax": top}
        head = (f"point density on {m.cell_size_m:g} m cells (on {cell:g} m cells: median "
                f"{s['density_median_per_m2']:.1f} points/m², 5 % of the area below {s['density_p5_per_m2']:.1f})")
    else:
        fig, axes, panels = tiled_axes(*m.strips.shape, m.x0, m.y1, m.cell_size_m)
        n_strips = max(int(m.strips.max()), 1)
        colours = plt.get_cmap("tab10")(np.arange(1, n_strips + 1) % 10)
        colours[0] = (0.95, 0.55, 0.1, 1.0)
        kw = {"cmap": ListedColormap(colours).with_extremes(bad=(1.0, 1.0, 1.0, 0.0)),
              "norm": BoundaryNorm(np.arange(0.5, n_strips + 1.0), n_strips)}
        grid = np.where(m.strips > 0, m.strips.astype(float), np.nan)
        head = f"strip overlap ({100.0 * s['overlap_share']:.0f} % of the area seen from two strips or more)"
    im = None
    for ax, (r, q, extent) in zip(axes, panels):
        im = ax.imshow(grid[r, q], extent=extent, interpolation="nearest", origin="upper", **kw)
        mark_sites(ax, extent, sites)
    label_axes(fig, epsg)
    fig.suptitle(f"{title}: {head}" if title else head, fontsize=10)
    if what == "density":
        fig.colorbar(im, ax=axes, label="points per m²", shrink=0.8,
                     extend="max" if finite.size and finite.max() > top else "neither")
    else:
        fig.colorbar(im, ax=axes, label="strips", shrink=0.8, ticks=np.arange(1, n_strips + 1))
    save_png(fig, path)
    plt.close(fig)
    return Path(path)
