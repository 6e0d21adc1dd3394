"""Strip differences on a raster, as paper 000's Fig. 7 shows them.

A horizontal raster (default 1 m) in the output CRS. Every *layer* -- the points of one strip x
scanner channel -- gets a least-squares plane ``z = a + b dx + c dy`` in every cell where it has
enough points (``min_points``) and the plane fits (RMS residual at most ``max_roughness_m``:
roofs, roads and terrain; not vegetation, edges or wires); ``a`` is its height at the cell
centre. The map is the spread ``max - min`` of those heights over the layers planar in the cell,
where at least two are. Because each layer's plane is evaluated at the same point (the cell
centre), slopes do not bias the difference, and a cell's value is the largest disagreement
between any two views or passes there.

Outputs: the raster (NaN where undefined), its summary (median, P95 over the defined cells), a
PNG map (0-0.1 m, green to red, colour bar, easting/northing axes) and a GeoTIFF (float32,
NaN as no-data, model tie point and pixel scale, the EPSG code as ``ProjectedCSTypeGeoKey``),
written with tifffile.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from georefine.io.files import atomic_path

__all__ = ["CellPlanes", "cell_planes", "StripDifferenceMap", "strip_differences", "crop", "write_png", "write_geotiff"]


@dataclass(frozen=True)
class CellPlanes:
    """Least-squares planes of one point layer on a raster: ``z = height + slope . (x - centre)``."""

    cell_ij: np.ndarray  # (C, 2) int64 cell indices (floor(x / size), floor(y / size))
    height_m: np.ndarray  # (C,) plane height at the cell centre
    roughness_m: np.ndarray  # (C,) RMS residual of the plane
    n_points: np.ndarray  # (C,) int64


def _cell_index(ij: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(cells (C, 2), inverse (N,), counts (C,))`` of integer cell indices, without a 2-D sort.

    A dense index over the bounding box with ``bincount`` when the box has at most 4 cells per
    point (a strip), else a 1-D ``unique`` of the linear index (a diagonal corridor).
    """
    if ij.shape[0] == 0:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    lo = ij.min(axis=0)
    size = ij.max(axis=0) - lo + 1
    lin = (ij[:, 0] - lo[0]) * size[1] + (ij[:, 1] - lo[1])
    if size[0] * size[1] <= 4 * ij.shape[0] + 1024:
        counts_all = np.bincount(lin, minlength=int(size[0] * size[1]))
        used = np.flatnonzero(counts_all)
        remap = np.zeros(counts_all.size, dtype=np.int64)
        remap[used] = np.arange(used.size)
        inv, counts, ulin = remap[lin], counts_all[used], used
    else:
        ulin, inv, counts = np.unique(lin, return_inverse=True, return_counts=True)
    cells = np.column_stack([ulin // size[1] + lo[0], ulin % size[1] + lo[1]])
    return cells, inv.reshape(-1), counts


def cell_planes(xyz: np.ndarray, cell_size_m: float = 1.0, min_points: int = 6) -> CellPlanes:
    """Fit a plane to the points of every raster cell (vectorised with ``bincount`` sums)."""
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    ij = np.floor(xyz[:, :2] / cell_size_m).astype(np.int64)
    cells, inv, counts = _cell_index(ij)
    centre = (cells + 0.5) * cell_size_m
    dx = xyz[:, 0] - centre[inv, 0]
    dy = xyz[:, 1] - centre[inv, 1]
    z = xyz[:, 2]
    z_ref = np.bincount(inv, z, cells.shape[0]) / counts  # fit about the cell mean (conditioning)
    dz = z - z_ref[inv]

    def s(w):
        return np.bincount(inv, w, cells.shape[0])

    n = counts.astype(float)
    A = np.empty((cells.shape[0], 3, 3))
    A[:, 0, 0] = n
    A[:, 0, 1] = A[:, 1, 0] = s(dx)
    A[:, 0, 2] = A[:, 2, 0] = s(dy)
    A[:, 1, 1] = s(dx * dx)
    A[:, 1, 2] = A[:, 2, 1] = s(dx * dy)
    A[:, 2, 2] = s(dy * dy)
    b = np.stack([s(dz), s(dx * dz), s(dy * dz)], axis=1)
    ok = counts >= min_points
    # points spread over the cell in both directions (not all on one line)
    ok &= np.abs(np.linalg.det(A)) > 1e-9 * np.maximum(n, 1.0) ** 3 * cell_size_m**4
    coef = np.full((cells.shape[0], 3), np.nan)
    coef[ok] = np.linalg.solve(A[ok], b[ok][:, :, None])[:, :, 0]
    res = dz - (coef[inv, 0] + coef[inv, 1] * dx + coef[inv, 2] * dy)
    rough = np.sqrt(s(res * res) / n)
    keep = ok & np.isfinite(rough)
    return CellPlanes(cells[keep], (z_ref + coef[:, 0])[keep], rough[keep], counts[keep])


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


def strip_differences(
    layers: list[np.ndarray], cell_size_m: float = 1.0, min_points: int = 6, max_roughness_m: float = 0.03
) -> StripDifferenceMap:
    """The strip-difference raster of point layers (each ``(N, 3)`` in a projected CRS)."""
    keys, heights = [], []
    for x in layers:
        p = cell_planes(x, cell_size_m, min_points)
        good = p.roughness_m <= max_roughness_m
        keys.append(p.cell_ij[good])
        heights.append(p.height_m[good])
    allk = np.concatenate(keys) if keys else np.zeros((0, 2), dtype=np.int64)
    allh = np.concatenate(heights) if heights else np.zeros(0)
    if allk.shape[0] == 0:
        return StripDifferenceMap(np.full((1, 1), np.nan), np.zeros((1, 1), dtype=int), 0.0, cell_size_m, cell_size_m)
    cells, inv, counts = _cell_index(allk)
    hi = np.full(cells.shape[0], -np.inf)
    lo = np.full(cells.shape[0], np.inf)
    np.maximum.at(hi, inv, allh)
    np.minimum.at(lo, inv, allh)
    i0, j0 = cells.min(axis=0)
    i1, j1 = cells.max(axis=0)
    rows, cols = int(j1 - j0 + 1), int(i1 - i0 + 1)
    spread = np.full((rows, cols), np.nan)
    nlay = np.zeros((rows, cols), dtype=int)
    r = (j1 - cells[:, 1]).astype(np.int64)
    c = (cells[:, 0] - i0).astype(np.int64)
    nlay[r, c] = counts
    two = counts >= 2
    spread[r[two], c[two]] = (hi - lo)[two]
    return StripDifferenceMap(spread, nlay, float(i0 * cell_size_m), float((j1 + 1) * cell_size_m), cell_size_m)


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


def write_geotiff(path: str | Path, m: StripDifferenceMap, epsg: int) -> Path:
    """GeoTIFF of the spread (metres, float32, NaN no-data) in the projected CRS ``epsg``."""
    import tifffile

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
        (42113, "s", 0, "nan", False),  # GDAL_NODATA
    ]
    path = Path(path)
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, m.spread_m.astype(np.float32), extratags=extratags, photometric="minisblack")
    return path
