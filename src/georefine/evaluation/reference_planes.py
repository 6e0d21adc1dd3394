"""Point clouds against surveyed reference planes, as paper 000 reports them (its Table 1).

Each reference surface is a flat patch surveyed at three or more points (``reference/surfaces.csv``,
:mod:`georefine.io.reference`). Its plane is the least-squares plane through the surveyed
points (normal pointing up), its outline the convex hull of the points in the plane, shrunk by
an inset margin so that edge effects (the slab's rim, mixed footprints) stay out.

An *observation* is one view of one surface: the points of one strip x scanner channel that lie
inside the inset outline and within ``max_distance_m`` of the plane; its value is the mean signed
distance of those points along the plane normal (positive: the cloud lies above the surface).
With two passes and three views, six surfaces give the paper's 36 observations. Over all
observations:

* **Mean**: the mean of the observation values (a common offset, e.g. from GNSS);
* **RMSE**: the root mean square of the observation values (accuracy);
* **AVG-SD**: the mean over surfaces of the standard deviation (``ddof=1``) of that surface's
  observation values -- how well the strips and views agree with each other where they see the
  same surface (inter-strip precision; paper 000: 10.1 mm for G/I, 3.3 mm for G/I/L).

The points' individual scatter about the plane (ranging noise) is reported per observation
(``sd_points_m``) but does not enter the three figures.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull

from georefine.adjustment.accuracy_standards import PositionalAccuracy
from georefine.io.reference import ReferenceSurfaces

__all__ = [
    "ReferencePlane",
    "reference_planes",
    "PlaneObservation",
    "observe_reference_planes",
    "ReferencePlaneSummary",
    "summarise_observations",
]


@dataclass(frozen=True)
class ReferencePlane:
    """A surveyed plane: centre, unit normal (up), in-plane axes and the outline (plane coordinates)."""

    surface_id: str
    centre: np.ndarray  # (3,)
    normal: np.ndarray  # (3,), normal[2] > 0
    axis_u: np.ndarray  # (3,)
    axis_v: np.ndarray  # (3,)
    outline_uv: np.ndarray  # (K, 2) convex hull, counter-clockwise
    rms_survey_m: float  # RMS distance of the surveyed points from the plane
    n_survey_points: int = 0  # how many surveyed points the plane was fitted to

    def inside(self, xyz: np.ndarray, inset_m: float) -> np.ndarray:
        """Which points project into the outline shrunk by ``inset_m``."""
        d = np.asarray(xyz, dtype=float) - self.centre
        uv = np.column_stack([d @ self.axis_u, d @ self.axis_v])
        ok = np.ones(uv.shape[0], dtype=bool)
        poly = self.outline_uv
        for a, b in zip(poly, np.roll(poly, -1, axis=0)):
            edge = b - a
            inward = np.array([-edge[1], edge[0]]) / np.linalg.norm(edge)  # left of a CCW edge
            ok &= (uv - a) @ inward >= inset_m
        return ok


def reference_planes(surfaces: ReferenceSurfaces) -> list[ReferencePlane]:
    """Least-squares planes and outlines of all surfaces, in order of first appearance."""
    out = []
    for sid in surfaces.surface_ids():
        pts = surfaces.points_of(sid)
        c = pts.mean(axis=0)
        _, _, Vt = np.linalg.svd(pts - c)
        n = Vt[2] if Vt[2, 2] >= 0 else -Vt[2]
        u = Vt[0] - (Vt[0] @ n) * n
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        uv = np.column_stack([(pts - c) @ u, (pts - c) @ v])
        hull = ConvexHull(uv) if len(uv) > 3 else None
        ring = uv[hull.vertices] if hull is not None else uv
        # counter-clockwise (positive shoelace area)
        area = 0.5 * np.sum(ring[:, 0] * np.roll(ring[:, 1], -1) - np.roll(ring[:, 0], -1) * ring[:, 1])
        if area < 0:
            ring = ring[::-1]
        rms = float(np.sqrt(np.mean(((pts - c) @ n) ** 2)))
        out.append(ReferencePlane(sid, c, n, u, v, ring, rms, int(len(pts))))
    return out


@dataclass(frozen=True)
class PlaneObservation:
    """One view (strip x channel) of one reference surface."""

    surface_id: str
    strip: int
    channel: int
    n_points: int
    mean_m: float  # mean signed distance along the normal: the observation value
    sd_points_m: float  # scatter of the points about their mean


def observe_reference_planes(
    xyz: np.ndarray,
    strip: np.ndarray | int,
    channel: np.ndarray | int,
    planes: Iterable[ReferencePlane],
    *,
    inset_m: float = 0.25,
    max_distance_m: float = 0.3,
    min_points: int = 10,
) -> list[PlaneObservation]:
    """Observations of ``planes`` by the points ``xyz`` (output CRS), per strip x channel.

    Parameters
    ----------
    xyz : (N, 3)
        Georeferenced points in the CRS of the reference surfaces.
    strip, channel : (N,) int or int
        Strip id (``point_source_id``) and ``scanner_channel`` of every point.
    inset_m
        Margin inside the surveyed outline.
    max_distance_m
        Points farther from the plane are not on the surface (wires, vegetation, people).
    min_points
        Views with fewer points on a surface give no observation.
    """
    xyz = np.asarray(xyz, dtype=float)
    strip = np.broadcast_to(np.asarray(strip), (xyz.shape[0],))
    channel = np.broadcast_to(np.asarray(channel), (xyz.shape[0],))
    out = []
    for pl in planes:
        reach = np.max(np.linalg.norm(pl.outline_uv, axis=1)) + max_distance_m
        near = np.flatnonzero(np.all(np.abs(xyz - pl.centre) <= reach, axis=1))
        if near.size == 0:
            continue
        d = (xyz[near] - pl.centre) @ pl.normal
        on = (np.abs(d) <= max_distance_m) & pl.inside(xyz[near], inset_m)
        idx, d = near[on], d[on]
        keys = np.column_stack([strip[idx], channel[idx]])
        for s, c in np.unique(keys, axis=0) if idx.size else []:
            m = (keys[:, 0] == s) & (keys[:, 1] == c)
            if np.count_nonzero(m) < min_points:
                continue
            out.append(PlaneObservation(pl.surface_id, int(s), int(c), int(np.count_nonzero(m)),
                                        float(np.mean(d[m])), float(np.std(d[m], ddof=1))))
    return out


@dataclass(frozen=True)
class ReferencePlaneSummary:
    """Paper 000's Table 1 figures and the per-surface table."""

    mean_m: float
    rmse_m: float
    avg_sd_m: float
    n_observations: int
    per_surface: list[dict]  # surface_id, observations, mean_m, sd_m, rmse_m
    vertical: PositionalAccuracy | None = None  # ASPRS 2023 / NSSDA on the level surfaces (adjustment.accuracy_standards)

    def to_dict(self) -> dict:
        out = {"mean_m": self.mean_m, "rmse_m": self.rmse_m, "avg_sd_m": self.avg_sd_m,
               "n_observations": self.n_observations, "surfaces": self.per_surface}
        if self.vertical is not None:
            out["asprs_vertical"] = self.vertical.to_dict()
        return out


def summarise_observations(observations: list[PlaneObservation]) -> ReferencePlaneSummary:
    """Mean, RMSE and AVG-SD over the observations (module docstring), and per surface."""
    vals = np.array([o.mean_m for o in observations], dtype=float)
    if vals.size == 0:
        nan = float("nan")
        return ReferencePlaneSummary(nan, nan, nan, 0, [])
    per = []
    sds = []
    for sid in dict.fromkeys(o.surface_id for o in observations):
        v = np.array([o.mean_m for o in observations if o.surface_id == sid])
        sd = float(np.std(v, ddof=1)) if v.size > 1 else float("nan")
        if v.size > 1:
            sds.append(sd)
        per.append({"surface_id": sid, "observations": int(v.size), "mean_m": float(v.mean()), "sd_m": sd,
                    "rmse_m": float(np.sqrt(np.mean(v**2)))})
    avg_sd = float(np.mean(sds)) if sds else float("nan")
    return ReferencePlaneSummary(float(vals.mean()), float(np.sqrt(np.mean(vals**2))), avg_sd, int(vals.size), per)
