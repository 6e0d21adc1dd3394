"""Strip differences on a raster, as paper 000's Fig. 7 shows them (docs/ARCHITECTURE.md §5).

A horizontal raster (default 1 m) in the output CRS. Every *layer* -- the points of one strip x
scanner channel -- gets a least-squares plane ``z = a + b dx + c dy`` in every cell where it has
enough points (``min_points``) and the plane fits (RMS residual at most ``max_roughness_m``:
roofs, roads and terrain; not vegetation, edges or wires); ``a`` is its height at the cell
centre. The map is the spread ``max - min`` of those heights over the layers planar in the cell,
where at least two are. Because each layer's plane is evaluated at the same point (the cell
centre), slopes do not bias the difference, and a cell's value is the largest disagreement
between any two views or passes there.

Streaming. The planes come from per-cell moment sums that merge chunk by chunk
(:mod:`georefine.evaluation.cell_moments`), and the map needs of a layer's planes only the
highest and lowest height per cell and how many layers are planar there (:class:`CellSpread`),
so :class:`StripDifferenceStream` takes the points as a stream of chunks and keeps only the
cells still *open*: once a layer x cell has had no points for ``close_after`` records (a strip
read in time order has passed it) or its layer is declared complete (the end of the strip's
file), its plane is folded into the spread and its sums are dropped. Memory is then the
cells of the last few chunks and the map -- plus 8 bytes per cell a still open layer has left,
to check that it stays closed -- not the points. Closing is checked, not assumed: points that
arrive for a closed layer x cell raise :class:`Reopened` (the caller then reads again without
closing, in memory that grows with the cells of all layers). Closing changes nothing in the
results but the order of floating-point sums.

Outputs: the raster (NaN where undefined), its summary (median, P95 over the defined cells), a
PNG map (0-0.1 m, green to red, colour bar, easting/northing axes) and a GeoTIFF (float32
metres, Deflate; NaN as no-data; model tie point and pixel scale, the EPSG code as
``ProjectedCSTypeGeoKey``; band description and unit ``metre`` in the GDAL_METADATA tag),
written with tifffile.
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
from georefine.io.files import atomic_path

__all__ = [
    "CellMoments", "cell_moments", "CellPlanes", "cell_planes", "CellSpread", "Reopened", "StripDifferenceStream",
    "StripDifferenceMap", "strip_difference_map", "strip_differences", "crop", "write_png", "write_geotiff",
    "BAND_DESCRIPTION",
]

_MERGE_ROWS = 500_000
"""Rows held aside before they are merged into a total (sums of a layer, the spread)."""


@dataclass(frozen=True)
class StripDifferenceMap:
    """Raster of strip differences: row 0 is the northern edge (image order)."""

    spread_m: np.ndarray  # (rows, cols) float64, NaN where fewer than two layers are planar
    layers_m: np.ndarray  # (rows, cols) int: planar layers per cell
    x0: float  # easting of the western edge
    y1: float  # northing of the northern edge
    cell_size_m: float

    def summary(self) -> dict[str, float]:
        v = self.spread_m[np.isfinite(self.spread_m)]
        if v.size == 0:
            return {"cells": 0, "median_m": float("nan"), "p95_m": float("nan"), "mean_m": float("nan")}
        return {"cells": int(v.size), "median_m": float(np.median(v)), "p95_m": float(np.percentile(v, 95)),
                "mean_m": float(np.mean(v))}


@dataclass(frozen=True)
class CellSpread:
    """Per raster cell: the highest and lowest plane height over the layers planar there, and how
    many they are (the map before it is rasterised). Rows sorted by ``(i, j)`` once merged."""

    cell_ij: np.ndarray  # (K, 2) int64
    high_m: np.ndarray  # (K,)
    low_m: np.ndarray  # (K,)
    layers: np.ndarray  # (K,) int64

    def __len__(self) -> int:
        return int(self.cell_ij.shape[0])

    @classmethod
    def of_planes(cls, planes: CellPlanes, max_roughness_m: float = 0.03) -> CellSpread:
        """The spread of the planes (any layers) that fit within ``max_roughness_m``."""
        good = planes.roughness_m <= max_roughness_m
        h = planes.height_m[good]
        return cls.merge([cls(planes.cell_ij[good], h, h, np.ones(h.size, dtype=np.int64))])

    @classmethod
    def merge(cls, parts: Iterable[CellSpread | None]) -> CellSpread:
        """One row per cell: max of the highs, min of the lows, sum of the layers."""
        parts = [p for p in parts if p is not None]
        if not parts:
            return cls(np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0), np.zeros(0, np.int64))
        ij = np.concatenate([p.cell_ij for p in parts])
        if ij.shape[0] == 0:
            return cls(ij, np.zeros(0), np.zeros(0), np.zeros(0, np.int64))
        order = np.argsort(cell_keys(ij), kind="stable")
        ij = ij[order]
        new = np.ones(ij.shape[0], dtype=bool)
        new[1:] = np.any(ij[1:] != ij[:-1], axis=1)
        starts = np.flatnonzero(new)
        return cls(ij[starts],
                   np.maximum.reduceat(np.concatenate([p.high_m for p in parts])[order], starts),
                   np.minimum.reduceat(np.concatenate([p.low_m for p in parts])[order], starts),
                   np.add.reduceat(np.concatenate([p.layers for p in parts])[order], starts))

    def to_map(self, cell_size_m: float) -> StripDifferenceMap:
        """The raster over the cells' bounding box: ``high - low`` where two or more layers are planar."""
        if len(self) == 0:
            return StripDifferenceMap(np.full((1, 1), np.nan), np.zeros((1, 1), dtype=int), 0.0, cell_size_m,
                                      cell_size_m)
        cells, counts = self.cell_ij, self.layers
        i0, j0 = cells.min(axis=0)
        i1, j1 = cells.max(axis=0)
        rows, cols = int(j1 - j0 + 1), int(i1 - i0 + 1)
        spread = np.full((rows, cols), np.nan)
        nlay = np.zeros((rows, cols), dtype=int)
        r = (j1 - cells[:, 1]).astype(np.int64)
        c = (cells[:, 0] - i0).astype(np.int64)
        nlay[r, c] = counts
        two = counts >= 2
        spread[r[two], c[two]] = (self.high_m - self.low_m)[two]
        return StripDifferenceMap(spread, nlay, float(i0 * cell_size_m), float((j1 + 1) * cell_size_m), cell_size_m)


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

    def __init__(self, cell_size_m: float = 1.0, min_points: int = 6, max_roughness_m: float = 0.03, *,
                 close_after: int | None = None) -> None:
        self.cell_size_m = float(cell_size_m)
        self.min_points = int(min_points)
        self.max_roughness_m = float(max_roughness_m)
        self.close_after = None if close_after is None else max(1, int(close_after))
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
            if self.close_after is not None:
                self._touched.setdefault(layer, []).append(keys)
        self._since += int(records)
        if self.close_after is not None and self._since >= self.close_after:
            self._close_untouched()
            self._since = 0

    def _fold(self, m: CellMoments) -> None:
        """Fold closed rows' planes into the spread."""
        if len(m):
            self._spread.add(CellSpread.of_planes(m.planes(self.min_points), self.max_roughness_m))

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

    def result(self) -> StripDifferenceMap:
        """The map of everything added (every layer is closed)."""
        for layer in list(self._sums):
            self.close_layer(layer)
        return self._spread.merged().to_map(self.cell_size_m)


def strip_difference_map(planes: CellPlanes, cell_size_m: float, max_roughness_m: float = 0.03) -> StripDifferenceMap:
    """The raster of the planes of all layers (one plane per layer x cell): max - min per cell."""
    return CellSpread.of_planes(planes, max_roughness_m).to_map(cell_size_m)


def strip_differences(
    layers: list[np.ndarray], cell_size_m: float = 1.0, min_points: int = 6, max_roughness_m: float = 0.03
) -> StripDifferenceMap:
    """The strip-difference raster of point layers in memory (each ``(N, 3)`` in a projected CRS)."""
    moments = CellMoments.concatenate([cell_moments(x, cell_size_m, k) for k, x in enumerate(layers)], cell_size_m)
    return strip_difference_map(moments.planes(min_points), cell_size_m, max_roughness_m)


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
                              m.y1 - r0 * m.cell_size_m, m.cell_size_m)


def write_png(path: str | Path, m: StripDifferenceMap, *, title: str = "", vmax_m: float = 0.1, epsg: int | None = None) -> Path:
    """PNG map of the spread: 0-``vmax_m`` green to red, colour bar in cm, axes in the output CRS."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, cols = m.spread_m.shape
    extent = (m.x0, m.x0 + cols * m.cell_size_m, m.y1 - rows * m.cell_size_m, m.y1)
    aspect = (extent[3] - extent[2]) / max(extent[1] - extent[0], 1e-9)
    fig, ax = plt.subplots(figsize=(8.0, float(np.clip(8.0 * aspect, 3.0, 12.0)) + 1.0), dpi=150)
    cmap = plt.get_cmap("RdYlGn_r").with_extremes(bad="white")
    im = ax.imshow(m.spread_m * 100.0, extent=extent, cmap=cmap, vmin=0.0, vmax=vmax_m * 100.0,
                   interpolation="nearest", origin="upper")
    crs = f" (EPSG:{epsg})" if epsg else ""
    ax.set_xlabel(f"easting [m]{crs}")
    ax.set_ylabel(f"northing [m]{crs}")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.set_title(title or "strip differences (max - min of plane heights per cell)")
    fig.colorbar(im, ax=ax, label="difference [cm]", shrink=0.8)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path


BAND_DESCRIPTION = "strip difference: max - min of the planar strip x channel planes' heights at the cell centre"
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
