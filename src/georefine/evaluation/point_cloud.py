"""Point-cloud accuracy: distance to the true surface (simulation) and strip-to-strip discrepancy.

Paper 000 judges the trajectory by its point cloud: how far the points lie from the surface
they were measured on, and how well overlapping strips agree on planar surfaces (its Fig. 7).

* :func:`surface_distances` needs the simulated truth (``truth/strip_N.laz``: the true position
  of every return, same point order as the scan file). For a sample of points the true surface
  is approximated by the plane through the true neighbours (PCA); only points whose
  neighbourhood is planar (roughness below a threshold: roofs, roads, terrain, facades; not
  vegetation, edges or wires) count. The distance is ``|(x_est - x_true) . n|``.
* :func:`strip_discrepancy` works without truth: the summary of the strip-difference raster
  (:mod:`georefine.evaluation.strip_differences`) of the given layers.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np
from scipy.spatial import cKDTree

from georefine.evaluation.strip_differences import strip_differences

__all__ = ["SurfaceDistances", "surface_distances", "strip_discrepancy", "compare_with_truth"]


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


def strip_discrepancy(
    layers: list[np.ndarray], cell_size_m: float = 1.0, min_points: int = 6, max_roughness_m: float = 0.03
) -> dict[str, float]:
    """Spread (max - min) of the layers' plane heights in cells where at least two are planar.

    The summary of :func:`georefine.evaluation.strip_differences.strip_differences`:
    ``cells``, ``median_m``, ``p95_m`` and ``mean_m``.
    """
    return strip_differences(layers, cell_size_m, min_points, max_roughness_m).summary()


def compare_with_truth(
    points_dir: Path, truth_dir: Path, names: set[str] | None = None, *, sample_step: int = 20
) -> dict[str, float]:
    """Georeferenced strips ``points_dir/strip_N.laz`` against the simulated ``truth_dir/strip_N.laz``.

    The files hold the same points in the same order. Returns the distance to the true surface
    (:func:`surface_distances` over all strips: ``mean_abs_distance_m``, ``rms_distance_m``,
    ``p95_distance_m``, ``samples``) and, with two or more strips, their discrepancy
    (:func:`strip_discrepancy`, one layer per strip: ``strip_median_m``, ``strip_p95_m``,
    ``strip_cells``). ``names`` restricts the strips (file names).
    """
    dist, layers = [], []
    for f in sorted(Path(points_dir).glob("strip_*.laz")):
        if names is not None and f.name not in names:
            continue
        est = laspy.read(f)
        tru = laspy.read(Path(truth_dir) / f.name)
        e = np.column_stack([est.x, est.y, est.z])
        dist.append(surface_distances(e, np.column_stack([tru.x, tru.y, tru.z]), sample_step=sample_step).distance_m)
        layers.append(e)
    if not dist:
        raise ValueError(f"no strip_*.laz to compare in {points_dir}")
    d = np.concatenate(dist)
    out = {"mean_abs_distance_m": float(d.mean()), "rms_distance_m": float(np.sqrt(np.mean(d**2))),
           "p95_distance_m": float(np.percentile(d, 95)), "samples": int(d.size)}
    if len(layers) > 1:
        sd = strip_discrepancy(layers)
        out.update(strip_median_m=sd["median_m"], strip_p95_m=sd["p95_m"], strip_cells=sd["cells"])
    return out
