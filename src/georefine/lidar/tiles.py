"""Time tiles of a strip: the unit of per-point work in bounded memory (docs/ARCHITECTURE.md §4.7).

A strip file is read once in a light pass (:func:`georefine.io.las.time_index`: only the GPS-time
layer of a LAZ file is decoded) that samples the point times and checks that they never
decrease. The strip is then cut into tiles of consecutive records:

* a tile *owns* the records ``[start, stop)`` and the times ``[own_t0, own_t1)`` (the first
  tile from -inf, the last to +inf); georeferencing reads exactly its own records, so the
  output keeps the input's point order, and every point is written once;
* planar features need every point of a neighbourhood: a tile's feature task also reads the
  points up to ``margin_s = 2 max_time_span_s`` before and after its own times
  (``read_start``/``read_stop``) and keeps only the features whose seed it owns. A patch that
  is accepted spans at most ``max_time_span_s``, so it lies inside the margin whole; a patch
  that spans more is seen over at least ``2 max_time_span_s`` of it and is still rejected. The
  features are therefore those of the whole view, whatever the tile size.

A file whose times are not in order cannot be cut by time: it becomes one tile (its memory
then grows with its points; a warning says so). The tile size follows
``processing.scale.memory_budget_gb``: the tiles in work at once -- one per task slot -- fit the
budget together (:func:`tile_points`).

The task functions (:func:`tile_features`, :func:`tile_georeference`) are module-level and take
only picklable arguments, so any scheduler of :class:`georefine.tasks.TaskRunner` runs them.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from georefine.config import PlaneExtractionConfig, ScaleConfig
from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.io.las import LasWriter, PointCloud, TimeIndex, read_las_range, time_index
from georefine.lidar.georeference import PoseInterpolator, georeference
from georefine.lidar.planes import PlanarFeatures, extract_features
from georefine.progress import Progress, no_progress
from georefine.tasks import TaskRunner

log = logging.getLogger(__name__)

__all__ = [
    "BYTES_PER_POINT", "GEOREFERENCE_CHUNK", "Tile", "StripPlan", "TileFeatures", "plan_strip", "tile_points", "tile_features",
    "tile_georeference", "read_tile_points", "georeference_strip", "StripGeoreferenceResult",
]

BYTES_PER_POINT = 130
"""Peak memory of a feature task per point it reads (decoded records, times, georeferenced
points, one view's voxel keys and sort orders): 96 bytes measured with ``tracemalloc`` on a
3.2 M-point tile of ``corridor``, plus a margin for what it does not see (the LAZ decoder's
buffers). The georeferencing task works through its tile in sub-chunks of
:data:`GEOREFERENCE_CHUNK` points (184 bytes a point at peak, the CRS transform's temporaries)
and keeps 39 bytes a point of result."""

GEOREFERENCE_CHUNK = 1_000_000
"""Points a georeferencing task transforms at once."""


@dataclass(frozen=True)
class Tile:
    """Consecutive records of one strip file (module docstring): owned, and read with margins."""

    path: Path
    strip_id: int
    number: int
    start: int
    stop: int
    own_t0: float
    own_t1: float
    read_start: int
    read_stop: int
    margin_s: float

    @property
    def points(self) -> int:
        return self.stop - self.start


@dataclass(frozen=True)
class StripPlan:
    """The tiles of one strip file, its point count, time span (s from the epoch) and order."""

    path: Path
    strip_id: int
    point_count: int
    t_first: float
    t_last: float
    ordered: bool
    tiles: tuple[Tile, ...]


def tile_points(scale: ScaleConfig, slots: int, margin_points: int = 0) -> int:
    """Records a tile owns so that ``slots`` tiles read with their margins fit the memory budget."""
    per_task = scale.memory_budget_gb * 1e9 / max(1, slots) / BYTES_PER_POINT
    return max(int(scale.min_tile_points), int(per_task) - 2 * int(margin_points))


def plan_strip(
    path: str | Path, strip_id: int, t0_gps: float, tile_size: int, margin_s: float,
    index: TimeIndex | None = None,
) -> StripPlan:
    """Cut a strip file into tiles of about ``tile_size`` records (module docstring).

    ``t0_gps``: the dataset epoch (tiles hold times relative to it); ``margin_s``: the time the
    feature tasks read beyond both ends of a tile; ``index``: a :func:`time_index` already made.
    """
    path = Path(path)
    ti = index or time_index(path)
    n = ti.point_count
    t_first, t_last = float(ti.time_gps[0] - t0_gps), float(ti.time_gps[-1] - t0_gps)
    if not ti.ordered:
        log.warning(
            "%s: point times decrease at record %d, so the strip cannot be cut into time tiles: it is "
            "processed whole, in memory that grows with its %d points (sort it by gps_time to stream it)",
            path, ti.first_unordered + 1, n,
        )
        tile = Tile(path, strip_id, 0, 0, n, -math.inf, math.inf, 0, n, margin_s)
        return StripPlan(path, strip_id, n, float(np.min(ti.time_gps) - t0_gps),
                         float(np.max(ti.time_gps) - t0_gps), False, (tile,))
    step = int(ti.index[1] - ti.index[0]) if ti.index.size > 1 else n
    size = max(step, (max(1, int(tile_size)) // step) * step)  # a multiple of the sampling step
    bounds = list(range(0, n, size)) + [n]
    if len(bounds) > 2 and n - bounds[-2] < size // 4:  # no sliver at the end
        bounds.pop(-2)
    tiles = []
    for k in range(len(bounds) - 1):
        a, b = bounds[k], bounds[k + 1]
        own_t0 = -math.inf if k == 0 else float(ti.time_gps[a // step] - t0_gps)
        own_t1 = math.inf if b == n else float(ti.time_gps[b // step] - t0_gps)
        r0 = 0 if k == 0 else ti.first_at_or_after(own_t0 + t0_gps - margin_s)
        r1 = n if b == n else ti.last_before(own_t1 + t0_gps + margin_s)
        tiles.append(Tile(path, strip_id, k, a, b, own_t0, own_t1, min(r0, a), max(r1, b), margin_s))
    return StripPlan(path, strip_id, n, t_first, t_last, True, tuple(tiles))


def read_tile_points(tile: Tile, *, margins: bool, extra_dims=()) -> PointCloud:
    """The tile's records: its own, or with the margins of the feature tasks."""
    if margins:
        return read_las_range(tile.path, tile.read_start, tile.read_stop, extra_dims)
    return read_las_range(tile.path, tile.start, tile.stop, extra_dims)


@dataclass(frozen=True)
class TileFeatures:
    """Planar features of one tile's own seeds, per view, and its own points outside the trajectory."""

    features: PlanarFeatures
    views: dict[int, int]  # channel id -> features
    points_outside: int
    channels_seen: tuple[int, ...]


def tile_features(
    tile: Tile, poses: PoseInterpolator, t0_gps: float, p_b_s: np.ndarray, R_b_s: np.ndarray,
    channels: tuple[int, ...], cfg: PlaneExtractionConfig, frame_poses=None,
) -> TileFeatures:
    """Steps 3-4a on one tile: georeference with ``poses`` and extract each view's features.

    Only the features whose seed time lies in the tile's own times are returned; the points
    outside the trajectory are counted over the own records only (each point once).
    ``frame_poses`` (default ``poses``) gives the pose at a feature's mean time that its
    scanner-frame geometry refers to: the adjustment's spline, which lacks the up-sampled
    high-frequency motion of ``poses`` (docs/ARCHITECTURE.md §4.6).
    """
    pc = read_tile_points(tile, margins=True)
    t = pc.time_gps - t0_gps
    window = (t >= tile.own_t0 - tile.margin_s) & (t < tile.own_t1 + tile.margin_s)
    inside = poses.inside(t)
    own = (t >= tile.own_t0) & (t < tile.own_t1)
    outside = int(np.count_nonzero(own & ~inside))
    keep = window & inside
    t, xs, ch = t[keep], pc.xyz[keep], pc.scanner_channel[keep]
    del pc
    x_w = georeference(t, xs, poses, p_b_s, R_b_s)
    del xs
    parts, views = [], {}
    seen = tuple(int(c) for c in np.unique(ch[(t >= tile.own_t0) & (t < tile.own_t1)]))
    for c in channels:
        m = ch == c
        if not np.any(m):
            views[c] = 0
            continue
        f = extract_features(x_w[m], t[m], tile.strip_id, c, frame_poses or poses, p_b_s, R_b_s, cfg,
                             own_time=(tile.own_t0, tile.own_t1))
        views[c] = len(f)
        parts.append(f)
    features = PlanarFeatures.concatenate(parts) if parts else PlanarFeatures.empty()
    return TileFeatures(features, views, outside, seen)


def tile_georeference(
    tile: Tile, poses: PoseInterpolator, t0_gps: float, p_b_s: np.ndarray, R_b_s: np.ndarray,
    frame: LocalFrame, crs: OutputCRS,
) -> tuple[PointCloud | None, int]:
    """Step 6 on one tile's own records: the points in the output CRS (``None`` if all are
    outside the trajectory), and the number left out because they are outside it."""
    parts, outside = [], 0
    for a in range(tile.start, tile.stop, GEOREFERENCE_CHUNK):
        pc = read_las_range(tile.path, a, min(a + GEOREFERENCE_CHUNK, tile.stop), ())
        t = pc.time_gps - t0_gps
        keep = poses.inside(t)
        outside += int(np.count_nonzero(~keep))
        if not np.any(keep):
            continue
        x_w = georeference(t[keep], pc.xyz[keep], poses, p_b_s, R_b_s)
        parts.append(PointCloud(pc.time_gps[keep], crs.from_w(frame, x_w), pc.intensity[keep],
                                pc.scanner_channel[keep], pc.point_source_id[keep], pc.return_number[keep],
                                pc.number_of_returns[keep]))
    if not parts:
        return None, outside
    return (parts[0] if len(parts) == 1 else PointCloud.concatenate(parts)), outside


@dataclass(frozen=True)
class StripGeoreferenceResult:
    """One georeferenced strip: points written and points left out (outside the trajectory)."""

    source: Path
    output: Path
    points_written: int
    points_outside: int


def georeference_strip(
    plan: StripPlan, out_path: str | Path, poses: PoseInterpolator, t0_gps: float, p_b_s: np.ndarray,
    R_b_s: np.ndarray, frame: LocalFrame, crs: OutputCRS, *, runner: TaskRunner | None = None,
    scale_m: float = 0.001, progress: Progress = no_progress, protect: tuple = (),
) -> StripGeoreferenceResult:
    """Georeference a scanner-frame strip into an output-CRS LAZ (LAS 1.4, PF 6), tile by tile.

    The tiles run as tasks on ``runner`` (default: this process); their points are written in
    the order of the input records as they arrive, so memory holds a few tiles whatever the
    strip's size. Keeps gps_time, intensity, ``scanner_channel``, ``point_source_id`` and return
    numbers; the CRS is written as WKT; heights are ellipsoidal. Points outside the trajectory's
    time span are left out and counted (a warning is logged). ``poses`` may be a value that
    ``runner.share`` returned.
    """
    runner = runner or TaskRunner("sync")
    out_path = Path(out_path)
    written = outside = 0
    tasks = [(tile, poses, t0_gps, p_b_s, R_b_s, frame, crs) for tile in plan.tiles]
    with LasWriter(out_path, scale=scale_m, crs=crs.crs, protect=protect) as writer:
        for cloud, left_out in runner.map(tile_georeference, tasks, label=f"georeference {plan.path.name}",
                                          window=runner.workers + 1, progress=progress):
            outside += left_out
            if cloud is not None:
                writer.write(cloud)
                written += len(cloud)
    if outside:
        log.warning("%s: %d points outside the trajectory span were left out", plan.path, outside)
    return StripGeoreferenceResult(plan.path, out_path, written, outside)
