"""The co-adjustment's tie problem solved by COLMAP's bundle adjuster and by Georefine's engine.

A COLMAP model written by ``georefine coadjust`` (``OUT/colmap``) holds the photos and
lidargrams, the tie points and their inlier observations. :func:`solve_both` takes it (as a
:class:`georefine.io.colmap.ColmapBlock`) and solves the same least-squares problem twice --
tie reprojections only, unit weights, no robust loss, intrinsics fixed, the chosen images held
fixed -- with pycolmap (Ceres) and with :mod:`georefine.adjustment`, from the same start. Both
should reach the same minimum; the reprojection errors are reported by COLMAP's statistic
(:func:`georefine.io.colmap.mean_reprojection_error`) and per observation.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from georefine.adjustment.observations.reprojection import ReprojectionObservation
from georefine.adjustment.problem import Problem
from georefine.adjustment.solver import SolverOptions
from georefine.io.colmap import (
    ColmapBlock,
    block_from_reconstruction,
    colmap_bundle_adjustment,
    mean_reprojection_error,
    to_reconstruction,
)

__all__ = ["SolverRun", "reprojection_errors", "solve_both"]


@dataclass(frozen=True)
class SolverRun:
    """One solver's result on the block."""

    solver: str
    R_w_c: np.ndarray
    p_w_c: np.ndarray
    points_w: np.ndarray
    errors_px: np.ndarray  # (k,) per observation (NaN where the point does not project: behind the camera)
    re_px: float  # COLMAP's statistic, over the observations that project
    seconds: float
    iterations: int

    @property
    def invalid(self) -> int:
        """Observations whose point no longer projects into its image."""
        return int(np.count_nonzero(~np.isfinite(self.errors_px)))

    @property
    def sum_of_squares(self) -> float:
        return float(np.nansum(self.errors_px**2))


def reprojection_errors(b: ColmapBlock, R: np.ndarray, p: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Image distance (px) between each observation and its point projected with Georefine's camera model."""
    grp = ReprojectionObservation("t", b.cameras, b.obs_image, b.obs_point, b.obs_uv)
    uv, _ = grp.predict({"image_rotation": R, "image_position": p, "points": X})
    return np.linalg.norm(uv - b.obs_uv, axis=1)


def _run(name, b, R, p, X, seconds, iterations) -> SolverRun:
    e = reprojection_errors(b, R, p, X)
    ok = np.isfinite(e)
    return SolverRun(name, R, p, X, e, mean_reprojection_error(e[ok], b.obs_point[ok]), seconds, iterations)


def solve_both(b: ColmapBlock, fixed: np.ndarray, R0: np.ndarray | None = None, p0: np.ndarray | None = None,
               X0: np.ndarray | None = None, max_iterations: int = 100) -> tuple[SolverRun, SolverRun]:
    """``(georefine, colmap)`` from the start ``(R0, p0, X0)`` (default: the block's own state)."""
    R0 = b.R_w_c if R0 is None else R0
    p0 = b.p_w_c if p0 is None else p0
    X0 = b.points_w if X0 is None else X0
    fixed = np.asarray(fixed, dtype=bool)
    t = time.perf_counter()
    P = Problem()
    P.add_block("image_rotation", R0, manifold="so3", constant=fixed)
    P.add_block("image_position", p0, constant=fixed)
    P.add_block("points", X0)
    P.add_group(ReprojectionObservation("ties", b.cameras, b.obs_image, b.obs_point, b.obs_uv))
    res = P.solve(SolverOptions(max_iterations=max_iterations, function_tolerance=1e-8))
    ours = _run("Georefine", b, P.values("image_rotation"), P.values("image_position"), P.values("points"),
                time.perf_counter() - t, res.iterations)
    t = time.perf_counter()
    rec = to_reconstruction(b.names, b.cameras, R0, p0, b.obs_image, b.obs_point, b.obs_uv, X0)
    colmap_bundle_adjustment(rec, fixed_images=np.flatnonzero(fixed), max_iterations=max_iterations)
    seconds = time.perf_counter() - t
    c = block_from_reconstruction(rec)
    X = X0.copy()  # to_reconstruction adds the points with two observations or more, by index
    X[np.flatnonzero(np.bincount(b.obs_point, minlength=len(X0)) >= 2)] = c.points_w
    theirs = _run("COLMAP", b, c.R_w_c, c.p_w_c, X, seconds, -1)
    return ours, theirs
