"""Point-cloud accuracy: distance to the true surface (simulation) and strip-to-strip discrepancy.

Paper 000 judges the trajectory by its point cloud: how far the points lie from the surface
they were measured on, and how well overlapping strips agree on planar surfaces (its Fig. 7).

* :func:`surface_distances` needs the simulated truth (``truth/strip_N.laz``: the true position
  of every return, same point order as the scan file). For a sample of points the true surface
  is approximated by the plane through the true neighbours (PCA); only points whose
  neighbourhood is planar (roughness below a threshold: roofs, roads, terrain, facades; not
  vegetation, edges or wires) count. The distance is ``|(x_est - x_true) . n|``.
* :func:`strip_discrepancy` works without truth: a horizontal raster (default 1 m); in every cell
  each strip's points get a least-squares plane ``z = a + b dx + c dy`` about the cell centre;
  cells where at least two strips are planar (RMS residual below a threshold) give the spread
  ``max - min`` of the strips' plane heights at the centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["SurfaceDistances", "surface_distances", "CellPlanes", "cell_planes", "strip_discrepancy"]


@dataclass(frozen=True)
class SurfaceDistances:
    """Distances of sampled points to the true surface (m)."""

    distance_m: np.ndarray  # (K,) |(x_est - x_true) . n_true| of the planar samples
    error_3d_m: np.ndarray  # (K,) |x_est - x_true| of the same samples

    def summary(self) -> dict[str, float]:
        d, e = self.distance_m, self.error_3d_m
        return {
            "points": int(d.size),
            "mean_abs_distance_m": float(np.mean(d)) if d.size else float("nan"),
            "rms_distance_m": float(np.sqrt(np.mean(d**2))) if d.size else float("nan"),
            "p95_distance_m": float(np.percentile(d, 95)) if d.size else float("nan"),
            "mean_3d_error_m": float(np.mean(e)) if e.size else float("nan"),
        }


def surface_distances(
    estimate_xyz: np.ndarray,
    truth_xyz: np.ndarray,
    *,
    sample_step: int = 20,
    neighbours: int = 12,
    max_roughness_m: float = 0.01,
) -> SurfaceDistances:
    """Distances of every ``sample_step``-th point to the plane of its true neighbourhood.

    Parameters
    ----------
    estimate_xyz, truth_xyz : (N, 3)
        The same points (same order): georeferenced with the estimate, and their true positions.
    sample_step
        Evaluate every ``sample_step``-th point (the neighbourhoods use all true points).
    neighbours
        True points in a neighbourhood (including the point itself).
    max_roughness_m
        Keep samples whose neighbourhood's smallest PCA standard deviation is below this.
    """
    est = np.asarray(estimate_xyz, dtype=float)
    tru = np.asarray(truth_xyz, dtype=float)
    if est.shape != tru.shape or est.ndim != 2 or est.shape[1] != 3:
        raise ValueError(f"estimate and truth must both be (N, 3), found {est.shape} and {tru.shape}")
    origin = tru.mean(axis=0) if len(tru) else np.zeros(3)
    tree = cKDTree(tru - origin)
    idx = np.arange(0, len(tru), max(1, int(sample_step)))
    _, nb = tree.query(tru[idx] - origin, k=neighbours, workers=-1)
    P = tru[nb] - tru[nb].mean(axis=1, keepdims=True)
    C = np.einsum("kni,knj->kij", P, P) / neighbours
    w, V = np.linalg.eigh(C)
    planar = np.sqrt(np.clip(w[:, 0], 0.0, None)) < max_roughness_m
    n = V[planar, :, 0]
    e = est[idx[planar]] - tru[idx[planar]]
    return SurfaceDistances(np.abs(np.einsum("ki,ki->k", e, n)), np.linalg.norm(e, axis=1))


@dataclass(frozen=True)
class CellPlanes:
    """Least-squares planes of one point layer on a raster: ``z = height + slope . (x - centre)``."""

    cell_ij: np.ndarray  # (C, 2) int64 cell indices (floor(x / size), floor(y / size))
    height_m: np.ndarray  # (C,) plane height at the cell centre
    roughness_m: np.ndarray  # (C,) RMS residual of the plane
    n_points: np.ndarray  # (C,) int64


def cell_planes(xyz: np.ndarray, cell_size_m: float = 1.0, min_points: int = 6) -> CellPlanes:
    """Fit a plane to the points of every raster cell (vectorised with ``bincount`` sums)."""
    xyz = np.asarray(xyz, dtype=float)
    ij = np.floor(xyz[:, :2] / cell_size_m).astype(np.int64)
    cells, inv, counts = np.unique(ij, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    centre = (cells + 0.5) * cell_size_m
    dx = xyz[:, 0] - centre[inv, 0]
    dy = xyz[:, 1] - centre[inv, 1]
    z = xyz[:, 2]
    z_ref = np.bincount(inv, z, cells.shape[0]) / counts  # numerically safer: fit about the mean
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
    ok &= np.abs(np.linalg.det(A)) > 1e-9 * np.maximum(n, 1.0) ** 3 * cell_size_m**4
    coef = np.full((cells.shape[0], 3), np.nan)
    coef[ok] = np.linalg.solve(A[ok], b[ok][:, :, None])[:, :, 0]
    res = dz - (coef[inv, 0] + coef[inv, 1] * dx + coef[inv, 2] * dy)
    rough = np.sqrt(s(res * res) / n)
    keep = ok & np.isfinite(rough)
    return CellPlanes(cells[keep], (z_ref + coef[:, 0])[keep], rough[keep], counts[keep])


def strip_discrepancy(
    layers: list[np.ndarray], cell_size_m: float = 1.0, min_points: int = 6, max_roughness_m: float = 0.03
) -> dict[str, float]:
    """Spread (max - min) of the layers' plane heights in cells where at least two are planar.

    Returns ``cells``, ``median_m``, ``p95_m`` and ``mean_m`` of the spread.
    """
    planes = [cell_planes(x, cell_size_m, min_points) for x in layers]
    keys, heights = [], []
    for p in planes:
        good = p.roughness_m < max_roughness_m
        keys.append(p.cell_ij[good])
        heights.append(p.height_m[good])
    if not keys:
        return {"cells": 0, "median_m": float("nan"), "p95_m": float("nan"), "mean_m": float("nan")}
    allk = np.concatenate(keys)
    allh = np.concatenate(heights)
    cells, inv, counts = np.unique(allk, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    hi = np.full(cells.shape[0], -np.inf)
    lo = np.full(cells.shape[0], np.inf)
    np.maximum.at(hi, inv, allh)
    np.minimum.at(lo, inv, allh)
    spread = (hi - lo)[counts >= 2]
    if spread.size == 0:
        return {"cells": 0, "median_m": float("nan"), "p95_m": float("nan"), "mean_m": float("nan")}
    return {"cells": int(spread.size), "median_m": float(np.median(spread)), "p95_m": float(np.percentile(spread, 95)),
            "mean_m": float(np.mean(spread))}
