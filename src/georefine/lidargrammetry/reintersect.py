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

__all__ = ["Reintersection", "reintersect", "feather_weights"]


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


def reintersect(points_w: np.ndarray, groups: np.ndarray, shown: list[np.ndarray], R0: np.ndarray, p0: np.ndarray,
                R1: np.ndarray, p1: np.ndarray, *, weights: list[np.ndarray] | None = None, k: int = 8,
                min_distance_m: float = 0.1, max_distance_m: float = 5.0) -> Reintersection:
    """Refine ``points_w`` (N, 3) from lidargram poses before ``(R0, p0)`` and after ``(R1, p1)``.

    ``shown[j]``: indices of the points lidargram ``j`` shows (its ``point_index``);
    ``groups`` (N,): strip of every point -- interpolation stays within a strip, whose
    trajectory error is one smooth function.
    """
    X = np.asarray(points_w, dtype=float)
    disp = np.zeros_like(X)
    count = np.zeros(len(X), dtype=np.int64)
    wsum = np.zeros(len(X))
    for j, idx in enumerate(shown):
        idx = np.asarray(idx, dtype=np.int64)
        moved = p1[j] + (X[idx] - p0[j]) @ R0[j] @ R1[j].T
        w = np.ones(idx.size) if weights is None else np.asarray(weights[j], dtype=float)
        np.add.at(disp, idx, w[:, None] * (moved - X[idx]))
        np.add.at(wsum, idx, w)
        np.add.at(count, idx, 1)
    seen = count > 0
    disp[seen] /= wsum[seen, None]
    for g in np.unique(groups):
        src = np.flatnonzero(seen & (groups == g))
        dst = np.flatnonzero(~seen & (groups == g))
        if dst.size == 0:
            continue
        if src.size == 0:  # a strip no lidargram shows keeps its coordinates
            continue
        dist, nb = cKDTree(X[src]).query(X[dst], k=min(k, src.size))
        dist, nb = dist.reshape(len(dst), -1), nb.reshape(len(dst), -1)
        near = dist[:, 0] <= max_distance_m
        w = 1.0 / np.maximum(dist[near], min_distance_m)
        disp[dst[near]] = np.einsum("nk,nkd->nd", w, disp[src][nb[near]]) / w.sum(axis=1, keepdims=True)
        count[dst[~near]] = -1
    count[~seen & (count == 0) & ~np.isin(groups, np.unique(groups[seen]))] = -1  # strips no lidargram shows
    return Reintersection(X + disp, count)
