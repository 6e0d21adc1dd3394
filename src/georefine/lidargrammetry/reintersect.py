"""The refined point cloud from adjusted lidargram orientations (docs/ARCHITECTURE.md §4.8, paper 004 Case 1/2).

A lidargram rendered from pose ``(R0, p0)`` shows point ``X`` along the ray
``x_c = R0^T (X - p0)``; after the co-adjustment its pose is ``(R1, p1)``. Through the ULPI
raster each shown point knows its lidargrams:

* shown in two or more lidargrams: the mean of its rigidly moved positions ``p1 + R1 x_c``
  over those lidargrams. docs/ARCHITECTURE.md §4.8 asks for the least-squares intersection of the rays; that
  is ill-conditioned here (lidargrams at photo stations 64 m apart seen from 320 m meet at
  about 11 degrees, so 0.5 px of pose noise moves the intersection by decimetres along the
  rays), while each ray also carries the depth the scanner measured: averaging the
  depth-preserving moves keeps it and is the intersection whenever the moved rays agree;
* shown in one lidargram: moved rigidly with it, ``X' = p1 + R1 R0^T (X - p0)`` (depth
  preserved);
* shown in none (hidden by a neighbour's splat): the displacement interpolated from the shown
  points of the same strip nearby (inverse-distance weights over the ``k`` nearest,
  :class:`scipy.spatial.cKDTree`), if the nearest is within ``max_distance_m``; farther away
  (outside every lidargram, e.g. the strip beyond the photo block) nothing is known and the
  point keeps its coordinates.

Points keep their order, so the refined strips can be compared point by point with the input
and, in simulation, with the truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["Reintersection", "Reintersector", "reintersect", "feather_weights"]


@dataclass(frozen=True)
class Reintersection:
    """Refined coordinates and how each point got them."""

    xyz_w: np.ndarray  # (N, 3)
    n_lidargrams: np.ndarray  # (N,) lidargrams that show the point (0: interpolated, -1: unchanged)

    @property
    def covered(self) -> np.ndarray:
        """Points that were moved (shown, or interpolated near shown ones)."""
        return self.n_lidargrams >= 0

    def summary(self) -> dict:
        n = self.n_lidargrams
        return {"points": int(n.size), "multi_ray": int(np.count_nonzero(n >= 2)),
                "single_ray": int(np.count_nonzero(n == 1)), "interpolated": int(np.count_nonzero(n == 0)),
                "unchanged": int(np.count_nonzero(n < 0))}


def feather_weights(uv: np.ndarray, width: int, height: int, floor: float = 0.05) -> np.ndarray:
    """Weights of the points a lidargram shows: 1 at the image centre, falling linearly to ``floor`` at the border."""
    tu = 1.0 - np.abs(2.0 * uv[:, 0] / width - 1.0)
    tv = 1.0 - np.abs(2.0 * uv[:, 1] / height - 1.0)
    return np.maximum(np.clip(tu, 0.0, 1.0) * np.clip(tv, 0.0, 1.0), floor)


def _positions(sorted_ids: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where ``ids`` are in the ascending ``sorted_ids``, and whether each is there."""
    if not len(sorted_ids):
        return np.zeros(len(ids), np.int64), np.zeros(len(ids), bool)
    pos = np.minimum(np.searchsorted(sorted_ids, ids), len(sorted_ids) - 1)
    return pos, sorted_ids[pos] == ids


_QUERY_POINTS = 250_000
"""Points interpolated at a time (their neighbours' displacements: about 50 MB)."""


class Reintersector:
    """The moves of a re-intersection, held for the shown points only, applied to any points.

    Built from the lidargrams' poses before and after the adjustment and the points they show
    (their identifiers ``shown[j]`` and coordinates): the mean displacement of every shown point
    and, per strip, a k-d tree of the shown points for the interpolation. :meth:`refine` then
    moves any set of points of the cloud (module docstring), so the cloud can be refined range by
    range: its memory is that of the shown points, not of the cloud.

    Parameters
    ----------
    index : (M,) int64
        The distinct points shown in any lidargram, sorted.
    xyz_w : (M, 3) float64, m
        Their coordinates.
    groups : (M,) int
        Their strips.
    shown, R0, p0, R1, p1, weights, k, min_distance_m, max_distance_m
        As :func:`reintersect`.
    """

    def __init__(self, index: np.ndarray, xyz_w: np.ndarray, groups: np.ndarray, shown: list[np.ndarray],
                 R0: np.ndarray, p0: np.ndarray, R1: np.ndarray, p1: np.ndarray, *,
                 weights: list[np.ndarray] | None = None, k: int = 8, min_distance_m: float = 0.1,
                 max_distance_m: float = 5.0) -> None:
        self.index = np.asarray(index, dtype=np.int64)
        X = np.asarray(xyz_w, dtype=float)
        disp = np.zeros_like(X)
        count = np.zeros(len(X), dtype=np.int64)
        wsum = np.zeros(len(X))
        for j, idx in enumerate(shown):
            idx = np.asarray(idx, dtype=np.int64)
            pos, held = _positions(self.index, idx)
            if not held.all():
                raise ValueError(f"lidargram {j} shows points that index does not hold")
            moved = p1[j] + (X[pos] - p0[j]) @ R0[j] @ R1[j].T
            w = np.ones(pos.size) if weights is None else np.asarray(weights[j], dtype=float)
            np.add.at(disp, pos, w[:, None] * (moved - X[pos]))
            np.add.at(wsum, pos, w)
            np.add.at(count, pos, 1)
        if np.any(count == 0):
            raise ValueError("index holds points that no lidargram shows")
        disp /= wsum[:, None]
        del wsum
        self.disp, self.count = disp, count
        self.k, self.min_distance_m, self.max_distance_m = int(k), float(min_distance_m), float(max_distance_m)
        groups = np.asarray(groups)
        self._trees = {}
        # Points sorted by strip (identifiers over the files in order are): each strip's points
        # are a slice, and the trees and displacements views of the arrays, not copies.
        grouped = bool(np.all(groups[1:] >= groups[:-1]))
        for g in np.unique(groups):
            if grouped:
                src = slice(int(np.searchsorted(groups, g, "left")), int(np.searchsorted(groups, g, "right")))
            else:
                src = np.flatnonzero(groups == g)
            self._trees[int(g)] = (cKDTree(X[src]), self.disp[src])

    def refine(self, xyz_w: np.ndarray, index: np.ndarray, groups: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Refined coordinates of the points ``index`` at ``xyz_w`` (strips ``groups``) and how many
        lidargrams showed each (0: interpolated, -1: unchanged)."""
        X = np.asarray(xyz_w, dtype=float)
        index, groups = np.asarray(index, dtype=np.int64), np.asarray(groups)
        pos, seen = _positions(self.index, index)
        disp = np.zeros_like(X)
        count = np.zeros(len(X), dtype=np.int64)
        disp[seen] = self.disp[pos[seen]]
        count[seen] = self.count[pos[seen]]
        for g in np.unique(groups[~seen]):
            dst = np.flatnonzero(~seen & (groups == g))
            if int(g) not in self._trees:  # a strip no lidargram shows keeps its coordinates
                count[dst] = -1
                continue
            tree, src_disp = self._trees[int(g)]
            for part in np.array_split(dst, -(-len(dst) // _QUERY_POINTS)):  # bounded temporaries
                dist, nb = tree.query(X[part], k=min(self.k, tree.n))
                dist, nb = dist.reshape(len(part), -1), nb.reshape(len(part), -1)
                near = dist[:, 0] <= self.max_distance_m
                w = 1.0 / np.maximum(dist[near], self.min_distance_m)
                disp[part[near]] = np.einsum("nk,nkd->nd", w, src_disp[nb[near]]) / w.sum(axis=1, keepdims=True)
                count[part[~near]] = -1
        return X + disp, count


def reintersect(points_w: np.ndarray, groups: np.ndarray, shown: list[np.ndarray], R0: np.ndarray, p0: np.ndarray,
                R1: np.ndarray, p1: np.ndarray, *, weights: list[np.ndarray] | None = None, k: int = 8,
                min_distance_m: float = 0.1, max_distance_m: float = 5.0) -> Reintersection:
    """Refine ``points_w`` (N, 3) from lidargram poses before ``(R0, p0)`` and after ``(R1, p1)``.

    ``shown[j]``: indices of the points lidargram ``j`` shows (its ``point_index``);
    ``groups`` (N,): strip of every point -- interpolation stays within a strip, whose
    trajectory error is one smooth function. The cloud held whole: :class:`Reintersector`
    does the same range by range.
    """
    X = np.asarray(points_w, dtype=float)
    groups = np.asarray(groups)
    u = np.unique(np.concatenate([np.asarray(i, dtype=np.int64) for i in shown])) if len(shown) else \
        np.zeros(0, np.int64)
    r = Reintersector(u, X[u], groups[u], shown, R0, p0, R1, p1, weights=weights, k=k,
                      min_distance_m=min_distance_m, max_distance_m=max_distance_m)
    xyz, count = r.refine(X, np.arange(len(X)), groups)
    return Reintersection(xyz, count)
