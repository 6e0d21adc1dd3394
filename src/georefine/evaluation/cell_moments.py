"""Per-cell plane fits from moment sums that merge chunk by chunk (docs/ARCHITECTURE.md §5).

The strip differences (:mod:`georefine.evaluation.strip_differences`) fit a least-squares plane
``z = a + b dx + c dy`` to the points of every layer (strip x channel) in every raster cell. A
cell's plane needs only sums over its points, so the points can be read chunk by chunk: each
chunk becomes per-cell *moment sums* (:class:`CellMoments`, :func:`cell_moments`), the sums of
the chunks are merged (:meth:`CellMoments.merge`) and the planes come from the merged sums
(:meth:`CellMoments.planes`). Memory: the cells, not the points.

A cell keeps, per layer, ten sums equivalent to
``n, Σdx, Σdy, Σdz, Σdx², Σdxdy, Σdy², Σdxdz, Σdydz, Σdz²`` (``dx, dy`` from the cell centre),
arranged so that nothing cancels:

    n, Σdx, Σdy;  Σu², Σuv, Σv²;  Σr, Σu·r, Σv·r, Σr²

with ``u, v`` the offsets from the centroid of the cell's points (co-moments, merged with the
parallel-variance formula) and ``r`` the height above a per-cell *reference plane*. The fit
``r = p0 + s·(u, v)`` gives the slopes ``s`` from the 2x2 co-moments, the height at the cell
centre and the residual sum of squares ``Σr² - (Σr)²/n - s·(Σu·r, Σv·r)``. That last
difference cancels: its rounding error is about ``1e-16 Σr²``, and the square root of the RMS
magnifies it -- about ``1e-8 |dz|`` on a perfect plane. A fixed reference (a height from the
file header, or a horizontal plane through the cell's first point or mean) keeps ``dz`` to the
cell's own relief, which on a 45° roof is still ±0.5 m in a 1 m cell, i.e. ~1e-8 m of
spurious roughness. The reference is therefore the cell's own plane: a chunk, which has its
points in memory, fits it in two passes (mean height, then the least-squares plane about it,
minimum-norm where the points lie on one line or are fewer than three) and sums the
residuals about it, so ``Σr²`` *is* that chunk's residual sum of squares and ``Σr, Σu·r,
Σv·r`` are ~0. Merging moves each part onto one reference by the exact change
``r' = r - (q0 + q1 dx + q2 dy)``, whose extra terms ``n q̄² + q·M·q`` are sums of
non-negative terms, and adds the sums -- first onto the reference of the part that spans the
cell best, which yields the merged plane, then onto the merged plane itself, which becomes the
cell's reference. The streaming planes thus equal the in-memory two-pass fit to rounding,
whatever the chunks, their order or the scheduler: ~1e-13 m in height and roughness where the
points span the cell, perfect planes included, and below 1e-10 m where they barely do (both
fits are then ill-conditioned alike).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["MOMENTS", "CellMoments", "cell_moments", "CellPlanes", "cell_planes", "cell_index", "cell_keys"]

MOMENTS = ("n", "dx", "dy", "uu", "uv", "vv", "r", "ur", "vr", "rr")
"""The sums of :class:`CellMoments` in column order (module docstring)."""

_SPANS = 0.05
"""A part of a cell *spans* it when its points' standard deviation is at least this fraction of
the cell size in every horizontal direction; merging prefers the reference planes of such parts."""


@dataclass(frozen=True)
class CellPlanes:
    """Least-squares planes of point layers on a raster: ``z = height + gradient . (x - centre)``."""

    cell_ij: np.ndarray  # (C, 2) int64 cell indices (floor(x / size), floor(y / size))
    height_m: np.ndarray  # (C,) plane height at the cell centre
    roughness_m: np.ndarray  # (C,) RMS residual of the plane
    n_points: np.ndarray  # (C,) int64
    gradient: np.ndarray  # (C, 2) dz/dx, dz/dy
    layer: np.ndarray | None = None  # (C,) int64 layer of each plane (None: one layer)

    def normals(self) -> np.ndarray:
        """``(C, 3)`` unit normals of the planes, pointing up."""
        n = np.column_stack([-self.gradient, np.ones(self.gradient.shape[0])])
        return n / np.linalg.norm(n, axis=1, keepdims=True)


def cell_keys(ij: np.ndarray) -> np.ndarray:
    """One int64 per cell index pair, in the order of ``(i, j)`` (for ``|i|, |j| < 2**31``)."""
    return ij[:, 0].astype(np.int64) * (1 << 32) + (ij[:, 1].astype(np.int64) + (1 << 31))


def cell_index(ij: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(cells (C, 2), inverse (N,), counts (C,))`` of integer cell indices, without a 2-D sort.

    A dense index over the bounding box with ``bincount`` when the box has at most 4 cells per
    point (a strip), else a 1-D ``unique`` of the linear index (a diagonal corridor). The cells
    come sorted by ``(i, j)``.
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


_RANK_TOL = 1e-12
"""Co-moments whose smaller eigenvalue is at most this fraction of the larger one are of points
on one line (exactly, up to rounding): that direction has no spread."""


def _eig2(uu, uv, vv) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(c, s, lam1, lam2)``: eigen-decomposition of the 2x2 co-moments ``[[uu, uv], [uv, vv]]``
    (vectorised): ``lam1 >= lam2`` along ``(c, s)`` and ``(-s, c)``; a ``lam2`` at rounding level
    (:data:`_RANK_TOL`) is 0."""
    theta = 0.5 * np.arctan2(2.0 * uv, uu - vv)
    c, s = np.cos(theta), np.sin(theta)
    lam1 = np.maximum(uu * c * c + 2.0 * uv * c * s + vv * s * s, 0.0)
    lam2 = uu * s * s - 2.0 * uv * c * s + vv * c * c
    lam2 = np.where(lam2 > _RANK_TOL * lam1, lam2, 0.0)
    return c, s, lam1, lam2


def _min_norm_slopes(uu, uv, vv, gu, gv) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Minimum-norm solutions ``s`` of ``[[uu, uv], [uv, vv]] s = (gu, gv)`` (vectorised 2x2
    pseudo-inverse: a direction with no spread gets no slope), and the smaller eigenvalue."""
    c, s, lam1, lam2 = _eig2(uu, uv, vv)
    with np.errstate(divide="ignore", invalid="ignore"):
        w1 = np.where(lam1 > 0.0, (c * gu + s * gv) / lam1, 0.0)
        w2 = np.where(lam2 > 0.0, (-s * gu + c * gv) / lam2, 0.0)
    return w1 * c - w2 * s, w1 * s + w2 * c, lam2


@dataclass(frozen=True)
class CellMoments:
    """Per-cell moment sums of point layers about per-cell reference planes (module docstring).

    One row per layer x cell of a chunk; :meth:`merge` adds the rows of the same layer x cell and
    sorts them by ``(layer, i, j)``. Memory: 16 numbers per layer x cell, whatever the points.
    """

    cell_size_m: float
    layer: np.ndarray  # (C,) int64 layer (the caller's code, e.g. strip * 256 + channel)
    cell_ij: np.ndarray  # (C, 2) int64 cell indices (floor(x / size), floor(y / size))
    reference: np.ndarray  # (C, 3) reference plane: height at the cell centre, dz/dx, dz/dy
    spans: np.ndarray  # (C,) bool: the reference was fitted to points that span the cell
    sums: np.ndarray  # (C, 10) float64: the sums named by MOMENTS

    def __len__(self) -> int:
        return int(self.layer.shape[0])

    def take(self, rows: np.ndarray) -> CellMoments:
        """The rows ``rows`` (a mask or indices), in that order."""
        return CellMoments(self.cell_size_m, self.layer[rows], self.cell_ij[rows], self.reference[rows],
                           self.spans[rows], self.sums[rows])

    @classmethod
    def empty(cls, cell_size_m: float) -> CellMoments:
        return cls(float(cell_size_m), np.zeros(0, np.int64), np.zeros((0, 2), np.int64), np.zeros((0, 3)),
                   np.zeros(0, bool), np.zeros((0, len(MOMENTS))))

    @classmethod
    def concatenate(cls, parts: Sequence[CellMoments | None], cell_size_m: float | None = None) -> CellMoments:
        """The rows of ``parts`` one after the other (not merged)."""
        parts = [p for p in parts if p is not None]
        size = float(cell_size_m) if cell_size_m is not None else parts[0].cell_size_m if parts else None
        if size is None:
            raise ValueError("no moments to concatenate and no cell size")
        if any(p.cell_size_m != size for p in parts):
            raise ValueError(f"moments of cell sizes {sorted({p.cell_size_m for p in parts})}, expected {size}")
        if not parts:
            return cls.empty(size)
        if len(parts) == 1:
            return parts[0]
        return cls(size, *(np.concatenate([getattr(p, f) for p in parts])
                           for f in ("layer", "cell_ij", "reference", "spans", "sums")))

    @classmethod
    def merge(cls, parts: Sequence[CellMoments | None], cell_size_m: float | None = None) -> CellMoments:
        """One row per layer x cell, sorted by ``(layer, i, j)``: the sums of all ``parts``.

        Vectorised: the rows are sorted into groups of one layer x cell (a stable sort of one
        key per row when all are of one layer: the parts' sorted runs merge), and the rows of a
        group of several are moved onto one reference plane and the group's centroid
        (:func:`_onto`), then added with ``np.add.reduceat``. Twice: first onto the reference of
        the group's best part (one that spans the cell, with the most points), which gives the
        group's plane, then -- from the rows as they came -- onto that plane, which becomes the
        group's reference. Every part's points lie close to the group's plane, so no term of
        the second pass is large.
        """
        m = cls.concatenate(parts, cell_size_m)
        if len(m) == 0:
            return m
        if np.all(m.layer == m.layer[0]):  # one layer: one key; a stable sort merges the sorted parts' runs
            order = np.argsort(cell_keys(m.cell_ij), kind="stable")
        else:
            order = np.lexsort((m.cell_ij[:, 1], m.cell_ij[:, 0], m.layer))
        layer, ij, ref, spans, sums = m.layer[order], m.cell_ij[order], m.reference[order], m.spans[order], m.sums[order]
        new = np.ones(len(layer), dtype=bool)
        new[1:] = (layer[1:] != layer[:-1]) | (ij[1:, 0] != ij[:-1, 0]) | (ij[1:, 1] != ij[:-1, 1])
        starts = np.flatnonzero(new)
        if starts.size == len(layer):  # one row per layer x cell already
            return cls(m.cell_size_m, layer, ij, ref, spans, sums)
        # Only the groups of several rows change (few: the cells that chunks share).
        size = np.diff(np.append(starts, len(layer)))
        several = size > 1
        rows = np.repeat(several, size)
        s, r = sums[rows], ref[rows]
        first = np.flatnonzero(new[rows])  # the first rows of those groups, among their rows
        group = np.repeat(np.arange(first.size), size[several])
        # Each group's first reference: that of a part spanning the cell, with the most points.
        score = s[:, 0] + np.where(spans[rows], 2.0**60, 0.0)
        top = score == np.maximum.reduceat(score, first)[group]
        best = np.minimum.reduceat(np.where(top, np.arange(len(s)), len(s)), first)
        total = np.add.reduceat(s[:, :3], first, axis=0)
        centroid = total[:, 1:3] / total[:, :1]  # the groups' centroids (dx, dy)
        merged = np.add.reduceat(_onto(s, r, r[best][group], centroid[group]), first, axis=0)
        n, _, _, uu, uv, vv, sr, ur, vr, _ = merged.T
        s1, s2, lam2 = _min_norm_slopes(uu, uv, vv, ur, vr)
        plane = r[best] + np.column_stack([sr / n - s1 * centroid[:, 0] - s2 * centroid[:, 1], s1, s2])
        out_ref, out_spans, out_sums = ref[starts], spans[starts], sums[starts]
        out_ref[several] = plane
        out_sums[several] = np.add.reduceat(_onto(s, r, plane[group], centroid[group]), first, axis=0)
        out_spans[several] = (n >= 3) & (lam2 >= n * (_SPANS * m.cell_size_m) ** 2)
        return cls(m.cell_size_m, layer[starts], ij[starts], out_ref, out_spans, out_sums)

    def planes(self, min_points: int = 6) -> CellPlanes:
        """The least-squares plane of every layer x cell with ``min_points`` that span the cell.

        Rows must be merged (one per layer x cell: :meth:`merge`, or one chunk's :func:`cell_moments`).
        """
        n, sx, sy, uu, uv, vv, sr, ur, vr, rr = self.sums.T
        det = uu * vv - uv * uv  # det of the 3x3 normal matrix = n * det
        ok = (n >= min_points) & (n * np.abs(det) > 1e-9 * np.maximum(n, 1.0) ** 3 * self.cell_size_m**4)
        with np.errstate(divide="ignore", invalid="ignore"):
            s1 = np.where(ok, (vv * ur - uv * vr) / det, np.nan)
            s2 = np.where(ok, (uu * vr - uv * ur) / det, np.nan)
            mean_r = sr / n
            rss = np.maximum(rr - sr * mean_r - (s1 * ur + s2 * vr), 0.0)
            rough = np.sqrt(rss / n)
            height = self.reference[:, 0] + mean_r - s1 * (sx / n) - s2 * (sy / n)
        keep = ok & np.isfinite(rough) & np.isfinite(height)
        return CellPlanes(self.cell_ij[keep], height[keep], rough[keep], n[keep].astype(np.int64),
                          self.reference[keep, 1:] + np.column_stack([s1[keep], s2[keep]]), self.layer[keep])


def _onto(sums: np.ndarray, ref: np.ndarray, target: np.ndarray, centroid: np.ndarray) -> np.ndarray:
    """Rows of moment sums about their reference planes ``ref``, moved onto the planes ``target``
    and onto the centroids ``centroid`` (``dx, dy``; per row).

    With ``q = target - ref``: ``r' = r - (qc + q1 u + q2 v)``, ``qc`` the value of ``q`` at the
    row's centroid, so ``Σr'² = Σr² - 2 (qc Σr + q1 Σu·r + q2 Σv·r) + n qc² + q·M·q``; the
    co-moments ``M`` and the sums ``Σu·r, Σv·r`` move to the new centroid (parallel-variance
    formula). ``q·M·q`` is summed on the eigenvectors of ``M``, as non-negative terms: expanded,
    it would cancel where the points lie on one line along which both planes agree.
    """
    n, sx, sy, uu, uv, vv, sr, ur, vr, rr = sums.T
    mx, my = sx / n, sy / n
    ex, ey = mx - centroid[:, 0], my - centroid[:, 1]
    q = target - ref
    q1, q2 = q[:, 1], q[:, 2]
    qc = q[:, 0] + q1 * mx + q2 * my
    c, si, lam1, lam2 = _eig2(uu, uv, vv)
    quad = lam1 * (c * q1 + si * q2) ** 2 + lam2 * (c * q2 - si * q1) ** 2
    sr2 = sr - n * qc
    ur2 = ur - (q1 * uu + q2 * uv)
    vr2 = vr - (q1 * uv + q2 * vv)
    rr2 = rr - 2.0 * (qc * sr + q1 * ur + q2 * vr) + n * qc * qc + quad
    return np.column_stack([n, sx, sy, uu + n * ex * ex, uv + n * ex * ey, vv + n * ey * ey,
                            sr2, ur2 + ex * sr2, vr2 + ey * sr2, rr2])


def cell_moments(xyz: np.ndarray, cell_size_m: float = 1.0, layer: int = 0) -> CellMoments:
    """Moment sums of one layer's points per raster cell (one chunk in memory; module docstring).

    Vectorised with ``bincount``: the cells' centroids and mean heights, then the co-moments
    about them and the least-squares plane (the cell's reference), then the residuals about it.
    Rows come sorted by cell, one per cell.
    """
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    ij = np.floor(xyz[:, :2] / cell_size_m).astype(np.int64)
    cells, inv, counts = cell_index(ij)
    C = cells.shape[0]

    def s(w):
        return np.bincount(inv, w, C)

    centre = (cells + 0.5) * cell_size_m
    dx = xyz[:, 0] - centre[inv, 0]
    dy = xyz[:, 1] - centre[inv, 1]
    n = counts.astype(float)
    sx, sy = s(dx), s(dy)
    mx, my, z_mean = sx / n, sy / n, s(xyz[:, 2]) / n
    u, v, dz = dx - mx[inv], dy - my[inv], xyz[:, 2] - z_mean[inv]
    uu, uv, vv = s(u * u), s(u * v), s(v * v)
    s1, s2, lam2 = _min_norm_slopes(uu, uv, vv, s(u * dz), s(v * dz))
    r = dz - (s1[inv] * u + s2[inv] * v)
    sums = np.column_stack([n, sx, sy, uu, uv, vv, s(r), s(u * r), s(v * r), s(r * r)])
    reference = np.column_stack([z_mean - s1 * mx - s2 * my, s1, s2])
    spans = (counts >= 3) & (lam2 >= n * (_SPANS * cell_size_m) ** 2)
    return CellMoments(float(cell_size_m), np.full(C, int(layer), dtype=np.int64), cells, reference, spans, sums)


def cell_planes(xyz: np.ndarray, cell_size_m: float = 1.0, min_points: int = 6) -> CellPlanes:
    """Fit a plane to the points of every raster cell (points in memory; :func:`cell_moments`)."""
    return cell_moments(xyz, cell_size_m).planes(min_points)
