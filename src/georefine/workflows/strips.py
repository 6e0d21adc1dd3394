"""The project's strips in memory and their planar features: workflow steps 3-4 of paper 000.

3. Preliminary georeferencing of every strip with the current trajectory (IMU rate, per-point
   interpolation).
4. Planar features per view (strip x scanner channel); :mod:`georefine.workflows.lidar`
   matches them across views and adjusts.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from georefine.config import boresight_matrix
from georefine.errors import InputError
from georefine.io.las import iter_las_chunks
from georefine.lidar.georeference import PoseInterpolator, georeference
from georefine.lidar.planes import PlanarFeatures, extract_features
from georefine.progress import Progress, no_progress
from georefine.trajectory.sampled import Trajectory
from georefine.workflows.navigation import NavigationData

log = logging.getLogger(__name__)

__all__ = ["FeatureCounts", "StripPoints", "read_strips", "step_features"]


@dataclass(frozen=True)
class StripPoints:
    """One strip in memory: scanner-frame points, times relative to the epoch, channels."""

    path: Path
    strip_id: int
    time: np.ndarray
    xyz_s: np.ndarray
    channel: np.ndarray


def read_strips(nav: NavigationData, strips: list[int] | None = None) -> list[StripPoints]:
    """Read the project's strips (optionally only those with the given ``point_source_id``).

    Raises
    ------
    InputError
        A strip without points, without configured ``scanner_channel`` values, or a requested
        strip id that no file holds.
    """
    cfg = nav.config
    channels = {c.id for c in cfg.scanner.channels}
    out = []
    for rel in cfg.scanner.files:
        path = nav.root / rel
        parts = list(iter_las_chunks(path, 5_000_000))
        if not parts or sum(len(p) for p in parts) == 0:
            raise InputError("strip has no points", path=path)
        sid = int(parts[0].point_source_id[0])
        if strips is not None and sid not in strips:
            continue
        t = np.concatenate([p.time_gps for p in parts]) - nav.t0_gps
        ch = np.concatenate([p.scanner_channel for p in parts])
        if not np.any(np.isin(ch, list(channels))):
            raise InputError(
                "no point has a configured scanner_channel", path=path, field="scanner_channel",
                expected="one of " + ", ".join(map(str, sorted(channels))), found=", ".join(map(str, np.unique(ch)[:5])),
            )
        out.append(StripPoints(path, sid, t, np.concatenate([p.xyz for p in parts]), ch))
    if strips is not None:
        missing = set(strips) - {s.strip_id for s in out}
        if missing:
            raise InputError("no strip with this id", field="strips", expected="ids of the project's strips",
                             found=", ".join(map(str, sorted(missing))))
    return out


@dataclass(frozen=True)
class FeatureCounts:
    """What :func:`step_features` saw: points outside the trajectory, features per view (``strip{id}_{channel}``)."""

    points_outside_trajectory: int
    views: dict[str, int]


def step_features(
    nav: NavigationData, trajectory: Trajectory, strips: list[StripPoints], progress: Progress = no_progress
) -> tuple[PlanarFeatures, FeatureCounts]:
    """Steps 3-4a: georeference each view with ``trajectory`` and extract its planar features."""
    cfg = nav.config
    p_b_s = np.asarray(cfg.scanner.lever_arm_m, dtype=float)
    R_b_s = boresight_matrix(cfg.scanner.boresight_deg)
    interp = PoseInterpolator(trajectory)
    parts, outside, views = [], 0, {}
    for k, strip in enumerate(strips):
        inside = interp.inside(strip.time)
        outside += int(np.count_nonzero(~inside))
        t, xs, ch = strip.time[inside], strip.xyz_s[inside], strip.channel[inside]
        x_w = georeference(t, xs, interp, p_b_s, R_b_s)
        for c in cfg.scanner.channels:
            m = ch == c.id
            if not np.any(m):
                log.warning("%s: no points of channel %d (%s)", strip.path.name, c.id, c.name)
                continue
            f = extract_features(x_w[m], t[m], strip.strip_id, c.id, interp, p_b_s, R_b_s, cfg.processing.planes)
            views[f"strip{strip.strip_id}_{c.name}"] = len(f)
            if len(f) == 0:
                log.warning("%s: channel %d (%s) gave no planar features", strip.path.name, c.id, c.name)
            parts.append(f)
        progress("planar features", k + 1, len(strips))
    features = PlanarFeatures.concatenate(parts) if parts else PlanarFeatures.empty()
    if len(features) == 0:
        raise InputError("no planar features in any view", field="processing.planes",
                         expected="planar surfaces (roofs, roads, facades) in the scans")
    return features, FeatureCounts(outside, views)
