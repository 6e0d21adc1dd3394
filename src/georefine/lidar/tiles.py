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

The task functions (:func:`tile_features`, :func:`tile_georeference`,
:func:`tile_georeference_encoded`) are module-level and take only picklable arguments, so any
scheduler of :class:`georefine.tasks.TaskRunner` runs them. Tiles of at least
:data:`~georefine.io.las_encode.LAZ_CHUNK_POINTS` records are planned in multiples of it, so the
georeferencing tasks' LAZ chunks fall on the output file's chunk grid.
"""

from __future__ import annotations

import contextlib
import logging
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from georefine.config import PlaneExtractionConfig, ScaleConfig
from georefine.errors import InputError
from georefine.geometry.frames import GeoidHeights, LocalFrame, OutputCRS
from georefine.io.las import PointCloud, TimeIndex, read_las_range, time_index
from georefine.io.las_encode import LAZ_CHUNK_POINTS, EncodedPoints, LasLayout, encode_points
from georefine.io.las_writer import LasWriter, offset_near
from georefine.io.point_manifest import record_point_files
from georefine.lidar.georeference import PoseInterpolator, ScannerCalibration, georeference, scan_angles_deg
from georefine.lidar.planes import PlanarFeatures, extract_features
from georefine.progress import Progress, no_progress
from georefine.tasks import TaskRunner

log = logging.getLogger(__name__)

__all__ = [
    "BYTES_PER_POINT", "GEOREFERENCE_CHUNK", "Tile", "StripPlan", "TileFeatures", "plan_strip", "tile_points",
    "tile_features", "tile_georeference", "tile_georeference_encoded", "read_tile_points", "georeference_strip",
    "georeference_strips", "StripGeoreferenceResult",
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
    # A multiple of the sampling step and, where the tile is large enough, of the LAZ chunk, so
    # that the georeferencing tasks' LAZ chunks start on the output file's chunk grid.
    unit = math.lcm(step, LAZ_CHUNK_POINTS) if step > 0 else 1
    if tile_size < unit:
        unit = max(1, step)
    size = max(unit, (max(1, int(tile_size)) // unit) * unit)
    # Tiles of about equal size (never larger): a 15 M-point strip becomes two tiles of 7.5 M for
    # a budget of 11.5 M, not 11.5 M and 3.5 M, which would leave a worker idle.
    size = max(unit, -(-n // (-(-n // size)) // unit) * unit) if n else size
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


def shift_plan(plan: StripPlan, delta_s: float) -> StripPlan:
    """``plan`` with every time (span, tiles' own intervals) ``delta_s`` later: the same records
    seen through a changed time offset of the scanner (the tiles' record ranges stay)."""
    if delta_s == 0.0:
        return plan
    tiles = tuple(replace(t, own_t0=t.own_t0 + delta_s, own_t1=t.own_t1 + delta_s) for t in plan.tiles)
    return replace(plan, t_first=plan.t_first + delta_s, t_last=plan.t_last + delta_s, tiles=tiles)


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

    ``t0_gps`` is the epoch in the strip's time scale: the navigation's epoch minus the
    scanner's time offset, so that ``gps_time - t0_gps`` is navigation time.

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
    frame: LocalFrame, crs: OutputCRS, time_offset_s: float = 0.0, heights: GeoidHeights | None = None,
    calibration: ScannerCalibration | None = None,
) -> tuple[PointCloud | None, int]:
    """Step 6 on one tile's own records: the points in the output CRS with their LAS scan angles
    (:func:`~georefine.lidar.georeference.scan_angles_deg`; ``None`` if all are outside the
    trajectory), and the number left out because they are outside it.

    ``t0_gps``: the navigation's epoch; the points are georeferenced, and written, at their
    ``gps_time + time_offset_s``. Heights are ellipsoidal, or with ``heights`` gravity-related
    (``H = h - N``, converted here, sub-chunk by sub-chunk; a point the geoid grid does not
    cover is an :class:`~georefine.errors.InputError` naming the grid). ``calibration``: the
    scanner's range offset and scale error and its channels' angle errors, taken out of every point first
    (:class:`~georefine.lidar.georeference.ScannerCalibration`)."""
    parts, outside = [], 0
    for a in range(tile.start, tile.stop, GEOREFERENCE_CHUNK):
        pc = read_las_range(tile.path, a, min(a + GEOREFERENCE_CHUNK, tile.stop), ())
        time_gps = pc.time_gps + time_offset_s if time_offset_s else pc.time_gps
        t = time_gps - t0_gps
        keep = poses.inside(t)
        outside += int(np.count_nonzero(~keep))
        if not np.any(keep):
            continue
        x_s = pc.xyz[keep] if calibration is None else calibration.apply(pc.xyz[keep], pc.scanner_channel[keep])
        x_w = georeference(t[keep], x_s, poses, p_b_s, R_b_s)
        lat, lon, h = frame.to_geodetic(x_w)
        angle = scan_angles_deg(t[keep], x_s, poses, R_b_s, frame.up_w(lat, lon))
        xyz = crs.from_geodetic(lat, lon, h)
        if heights is not None:
            xyz[:, 2] = heights.orthometric(lat, lon, h, what=f"points of {tile.path.name}")
        parts.append(PointCloud(time_gps[keep], xyz, pc.intensity[keep],
                                pc.scanner_channel[keep], pc.point_source_id[keep], pc.return_number[keep],
                                pc.number_of_returns[keep], scan_angle_deg=angle))
    if not parts:
        return None, outside
    return (parts[0] if len(parts) == 1 else PointCloud.concatenate(parts)), outside


def tile_georeference_encoded(
    tile: Tile, poses: PoseInterpolator, t0_gps: float, p_b_s: np.ndarray, R_b_s: np.ndarray,
    frame: LocalFrame, crs: OutputCRS, layout: LasLayout, time_offset_s: float = 0.0,
    heights: GeoidHeights | None = None, calibration: ScannerCalibration | None = None,
) -> tuple[EncodedPoints, int]:
    """:func:`tile_georeference`, the points encoded for the output file of ``layout`` (LAZ
    chunks compressed here, :mod:`georefine.io.las_encode`)."""
    cloud, outside = tile_georeference(tile, poses, t0_gps, p_b_s, R_b_s, frame, crs, time_offset_s, heights,
                                       calibration)
    return encode_points(PointCloud.empty() if cloud is None else cloud, layout), outside


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
    heights: GeoidHeights | None = None,
) -> StripGeoreferenceResult:
    """Georeference one scanner-frame strip into an output-CRS LAZ (:func:`georeference_strips`)."""
    return georeference_strips([plan], [out_path], poses, t0_gps, p_b_s, R_b_s, frame, crs, runner=runner,
                               scale_m=scale_m, progress=progress, protect=protect, heights=heights)[0]


def refuse_strips_outside(plans: list[StripPlan], span: tuple[float, float], t0_gps: float,
                          time_offset_s: float = 0.0) -> None:
    """InputError for the first strip with no point inside the trajectory's time ``span`` (s from the epoch).

    Georeferencing it would write an empty file and call that success. The plans' times include
    the scanner's time offset; the message states the file's own time stamps.
    """
    shift = t0_gps - time_offset_s  # plan times to the file's own time stamps
    for plan in plans:
        if plan.point_count and (plan.t_last < span[0] or plan.t_first > span[1]):
            raise strip_outside_error(plan.path, (span[0] + shift, span[1] + shift),
                                      (plan.t_first + shift, plan.t_last + shift), time_offset_s)


def strip_outside_error(path, span_gps: tuple[float, float], found_gps: tuple[float, float],
                        time_offset_s: float = 0.0) -> InputError:
    """The error for a strip whose time stamps ``found_gps`` miss the navigation's ``span_gps``
    (both GPS s in the file's time scale); ``georefine check`` raises the same."""
    return InputError(
        "no point of the strip lies inside the trajectory's time span", path=path, field="gps_time",
        expected=f"times within {span_gps[0]:.3f} .. {span_gps[1]:.3f} GPS s"
        + (f" (scanner.time_offset_s {time_offset_s:g} s applied)" if time_offset_s else ""),
        found=f"{found_gps[0]:.3f} .. {found_gps[1]:.3f} GPS s",
    )


def georeference_strips(
    plans: list[StripPlan], out_paths: list[str | Path], poses: PoseInterpolator, t0_gps: float,
    p_b_s: np.ndarray, R_b_s: np.ndarray, frame: LocalFrame, crs: OutputCRS, *, runner: TaskRunner | None = None,
    scale_m: float = 0.001, progress: Progress = no_progress, protect: tuple = (), time_offset_s: float = 0.0,
    heights: GeoidHeights | None = None, calibration: ScannerCalibration | None = None,
) -> list[StripGeoreferenceResult]:
    """Georeference scanner-frame strips into output-CRS LAZ files (LAS 1.4, PF 6), tile by tile.

    ``t0_gps`` is the navigation's epoch; ``time_offset_s`` the scanner's time offset
    (``scanner.time_offset_s``, or its estimate): points are georeferenced at, and written with,
    ``gps_time + time_offset_s``, and the plans' times must include it (:func:`shift_plan`).

    The tiles of all strips run as one stream of tasks on ``runner`` (default: this process), so
    a worker that finishes a strip's last tile goes on with the next strip's first. Each task
    also encodes its points (LAZ chunks, :mod:`georefine.io.las_encode`); they are written in
    the order of the input records as they arrive, one file open at a time, so memory holds a
    few tiles whatever the strips' sizes. The files' offset is fixed before the tasks start:
    the local frame's origin in the output CRS, rounded to 1000 units. Keeps gps_time,
    intensity, ``scanner_channel``, ``point_source_id`` and return numbers, sets the scan angle
    from the beam and the body's heading, and the header's file source ID to the strip id; the
    CRS is written as WKT (:func:`georefine.io.las_writer.las_crs_wkt`); heights are
    ellipsoidal, or with ``heights`` (``crs.geoid_grid``) gravity-related, each task converting
    its own points, and the files state the compound CRS (:meth:`GeoidHeights.compound_crs`); a
    point outside the geoid grid stops the run with an error naming the grid, and no file is
    left half-written. Points outside the trajectory's time span are left out and counted (a warning
    is logged). ``poses`` may be a value that ``runner.share`` returned. ``calibration``: the
    scanner's estimated range offset and scale error and channel angles, taken out of every point.
    """
    if len(plans) != len(out_paths):
        raise ValueError(f"{len(plans)} strips but {len(out_paths)} output paths")
    runner = runner or TaskRunner("sync")
    offset = tuple(offset_near(crs.from_w(frame, np.zeros((1, 3)))[0]))
    file_crs = crs.crs if heights is None else heights.compound_crs(crs)
    writers = [LasWriter(Path(o), scale=scale_m, offset=offset, crs=file_crs, protect=protect) for o in out_paths]
    tasks = [(tile, poses, t0_gps, p_b_s, R_b_s, frame, crs, w.layout_for(), time_offset_s, heights, calibration)
             for plan, w in zip(plans, writers) for tile in plan.tiles]
    owner = [k for k, plan in enumerate(plans) for _ in plan.tiles]
    last = {k: i for i, k in enumerate(owner)}  # a file is complete after its strip's last tile
    written, outside = [0] * len(plans), [0] * len(plans)
    label = f"georeference {plans[0].path.name}" if len(plans) == 1 else f"georeference {len(plans)} strips"
    with contextlib.ExitStack() as stack:
        for w in writers:
            stack.enter_context(w)  # on an error the files not yet complete are discarded: none half-written
        results = runner.map(tile_georeference_encoded, tasks, label=label, window=runner.workers + 1,
                             progress=progress)
        for i, (k, (points, left_out)) in enumerate(zip(owner, results)):
            outside[k] += left_out
            writers[k].write_encoded(points)
            written[k] += len(points)
            if i == last[k]:
                if not written[k] and outside[k]:  # every point outside the trajectory: not a result
                    raise InputError("no point of the strip lies inside the trajectory's time span",
                                     path=plans[k].path, field="gps_time",
                                     found=f"all {outside[k]:,} points outside it")
                writers[k].close()
        for k in range(len(plans)):
            writers[k].close()  # a strip without tiles: an empty file
    record_point_files([w.path for w in writers], written)  # evaluations read these, not stale neighbours
    out = []
    for plan, w, n, left in zip(plans, writers, written, outside):
        if w.recompressed_points:
            log.debug("%s: %d points compressed again (tiles off the LAZ chunk grid)", w.path, w.recompressed_points)
        if left:
            log.warning("%s: %d points outside the trajectory span were left out", plan.path, left)
        out.append(StripGeoreferenceResult(plan.path, w.path, n, left))
    return out
