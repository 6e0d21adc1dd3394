"""The project's strips as time tiles, and their planar features: workflow steps 3-4 of paper 000.

3. Preliminary georeferencing of every strip with the current trajectory (IMU rate, per-point
   interpolation).
4. Planar features per view (strip x scanner channel); :mod:`georefine.workflows.lidar`
   matches them across views and adjusts.

No strip is held in memory: :func:`read_strips` indexes each file's point times and cuts it
into time tiles (:mod:`georefine.lidar.tiles`), and :func:`step_features` runs one task per
tile on the run's :class:`~georefine.tasks.TaskRunner`, each reading its tile with margins,
georeferencing it and extracting the features it owns. Memory is bounded by
``processing.scale.memory_budget_gb`` whatever the number of points; the features are those of
the whole views, in an order that depends on neither the tiles nor the scheduler.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from georefine.config import boresight_matrix
from georefine.errors import InputError
from georefine.io.las import read_las_info, read_las_range, time_index
from georefine.lidar.feature_tiles import FeatureStore
from georefine.lidar.georeference import PoseInterpolator
from georefine.lidar.planes import PlanarFeatures
from georefine.lidar.tiles import StripPlan, Tile, plan_strip, shift_plan, tile_features, tile_points
from georefine.progress import Progress, no_progress
from georefine.tasks import TaskRunner
from georefine.trajectory.sampled import Trajectory
from georefine.workflows.navigation import NavigationData

log = logging.getLogger(__name__)

__all__ = ["FeatureCounts", "StripFile", "read_strips", "step_features", "sort_features", "strip_id_of"]


@dataclass(frozen=True)
class StripFile:
    """One strip of the project: its file, id, time span (s from the epoch) and time tiles.

    ``time_offset_s`` is the scanner's time offset the plan's times include: they are the
    points' ``gps_time + time_offset_s`` relative to the navigation's epoch.
    """

    path: Path
    strip_id: int
    plan: StripPlan
    time_offset_s: float = 0.0

    def shifted(self, time_offset_s: float) -> StripFile:
        """The strip seen through another time offset (the same records and tiles)."""
        return replace(self, plan=shift_plan(self.plan, time_offset_s - self.time_offset_s),
                       time_offset_s=float(time_offset_s))

    def epoch(self, t0_gps: float) -> float:
        """The navigation's epoch ``t0_gps`` in the strip's time scale: ``gps_time - epoch`` is navigation time."""
        return t0_gps - self.time_offset_s

    @property
    def t_first(self) -> float:
        return self.plan.t_first

    @property
    def t_last(self) -> float:
        return self.plan.t_last

    @property
    def tiles(self) -> tuple[Tile, ...]:
        return self.plan.tiles

    @property
    def point_count(self) -> int:
        return self.plan.point_count


def strip_id_of(path: Path) -> int:
    """A strip file's id: the ``point_source_id`` of its first record."""
    return int(read_las_range(path, 0, 1).point_source_id[0])


def read_strips(nav: NavigationData, strips: list[int] | None = None, *, slots: int = 1) -> list[StripFile]:
    """Index the project's strips (optionally only those with the given ``point_source_id``).

    One light pass per file (point times and channels only) checks it and cuts it into time
    tiles sized for ``slots`` tasks at once within ``processing.scale.memory_budget_gb``.

    Raises
    ------
    InputError
        A strip without points, without configured ``scanner_channel`` values, or a requested
        strip id that no file holds.
    """
    cfg = nav.config
    channels = {c.id for c in cfg.scanner.channels}
    margin_s = 2.0 * cfg.processing.planes.max_time_span_s
    out = []
    for rel in cfg.scanner.files:
        path = nav.root / rel
        if read_las_info(path).point_count == 0:
            raise InputError("strip has no points", path=path)
        sid = strip_id_of(path)
        if strips is not None and sid not in strips:
            continue
        ti = time_index(path)
        present = [c for c, n in enumerate(ti.channel_counts) if n]
        if not channels & set(present):
            raise InputError(
                "no point has a configured scanner_channel", path=path, field="scanner_channel",
                expected="one of " + ", ".join(map(str, sorted(channels))), found=", ".join(map(str, present[:5])),
            )
        rate = ti.point_count / max(float(ti.time_gps[-1] - ti.time_gps[0]), 1e-3)
        size = tile_points(cfg.processing.scale, slots, int(rate * margin_s))
        offset = cfg.scanner.time_offset_s
        out.append(StripFile(path, sid, plan_strip(path, sid, nav.t0_gps - offset, size, margin_s, index=ti), offset))
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

    @property
    def extracted(self) -> int:
        """Features extracted in all views."""
        return int(sum(self.views.values()))


def sort_features(features: PlanarFeatures) -> PlanarFeatures:
    """Features by strip, channel and time (stable): one order whatever the tiles."""
    order = np.lexsort((features.time, features.channel, features.strip))
    return features.select(order)


def step_features(
    nav: NavigationData, trajectory: Trajectory, strips: list[StripFile], progress: Progress = no_progress,
    runner: TaskRunner | None = None, frame_poses=None, store: FeatureStore | None = None,
) -> tuple[PlanarFeatures, FeatureCounts]:
    """Steps 3-4a: georeference each tile of each strip with ``trajectory`` and extract its planar features.

    ``frame_poses`` (``t -> (p_w_b, R_w_b)``, default the trajectory) is the pose each feature's
    scanner-frame geometry refers to: the adjustment's spline (see :func:`~georefine.lidar.tiles.tile_features`).
    With a ``store`` each task's features go into its ground tiles as they come
    (:mod:`georefine.lidar.feature_tiles`) and none are returned: memory holds a few tasks' features.
    """
    cfg = nav.config
    runner = runner or TaskRunner("sync")
    p_b_s = np.asarray(cfg.scanner.lever_arm_m, dtype=float)
    R_b_s = boresight_matrix(cfg.scanner.boresight_deg)
    poses = runner.share(PoseInterpolator(trajectory))
    channels = tuple(c.id for c in cfg.scanner.channels)
    if frame_poses is not None:
        frame_poses = runner.share(frame_poses)
    tasks = [(tile, poses, s.epoch(nav.t0_gps), p_b_s, R_b_s, channels, cfg.processing.planes, frame_poses)
             for s in strips for tile in s.tiles]
    parts, outside, stored = [], 0, 0
    per_view: dict[tuple[int, int], int] = {}
    seen: dict[int, set[int]] = {s.strip_id: set() for s in strips}
    for (tile, *_), r in zip(tasks, runner.map(tile_features, tasks, label="planar features", progress=progress)):
        if store is None:
            parts.append(r.features)
        else:
            store.add(r.features)
            stored += len(r.features)
        outside += r.points_outside
        seen[tile.strip_id].update(r.channels_seen)
        for c, n in r.views.items():
            per_view[(tile.strip_id, c)] = per_view.get((tile.strip_id, c), 0) + n
    views = {}
    for s in strips:
        for c in cfg.scanner.channels:
            if c.id not in seen[s.strip_id]:
                log.warning("%s: no points of channel %d (%s)", s.path.name, c.id, c.name)
                continue
            n = per_view.get((s.strip_id, c.id), 0)
            views[f"strip{s.strip_id}_{c.name}"] = n
            if n == 0:
                log.warning("%s: channel %d (%s) gave no planar features", s.path.name, c.id, c.name)
    features = sort_features(PlanarFeatures.concatenate(parts)) if parts else PlanarFeatures.empty()
    if (len(features) if store is None else stored) == 0:  # these strips' features (a store may hold others')
        raise InputError("no planar features in any view", field="processing.planes",
                         expected="planar surfaces (roofs, roads, facades) in the scans")
    return features, FeatureCounts(outside, views)
