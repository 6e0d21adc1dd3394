"""Point-cloud evaluation of georeferenced strips (LAZ in the output CRS) and its files.

Reads the strips a run wrote (``points/strip_N.laz``, or any LAS/LAZ with ``point_source_id``
and ``scanner_channel``) in memory that does not grow with their points (docs/ARCHITECTURE.md
§5): every file is cut into record ranges of ``chunk_points`` (default
:data:`DEFAULT_CHUNK_POINTS`), and every range is one task on a
:class:`georefine.tasks.TaskRunner` (:func:`scan_chunk`, module-level with picklable
arguments) that reads its records and keeps only what the metrics need:

* per layer strip x channel, the per-cell moment sums of the strip-difference planes
  (:func:`georefine.evaluation.cell_moments.cell_moments`), merged as the tasks finish in
  order (:class:`georefine.evaluation.strip_differences.StripDifferenceStream`). A layer x cell
  is closed -- its plane goes into the map, its sums are dropped -- when its file ends or when
  it got no points for ``CLOSE_AFTER_POINTS`` records (files in time order, as a run writes
  them, have passed it), so memory holds the cells of the last few chunks and the map;
* the points inside a box around each reference surface (:func:`plane_boxes`: 10 m, or more
  for a surface larger than that), which are few, whatever the length of the corridor.

One pass (:func:`scan_clouds`) serves both metrics. The results do not depend on the chunk
size, the closing or the scheduler, beyond the order of floating-point sums (< 1e-10 m). Writes:

* ``reference_planes.json`` and ``reference_planes.csv``: the observations of the reference
  surfaces per strip x channel and paper 000's Table 1 figures
  (:mod:`georefine.evaluation.reference_planes`);
* ``strip_differences.json``, ``strip_differences.png`` and ``strip_differences.tif``: the Fig. 7
  raster over the layers strip x channel (:mod:`georefine.evaluation.strip_differences`);
* ``coverage_density.png`` and ``coverage_overlap.png``: points per m² and strips per cell on the
  same raster, from the same scan (:mod:`georefine.evaluation.coverage`; figures under
  ``coverage`` in ``strip_differences.json``).
"""

from __future__ import annotations

import csv
import io
import logging
from dataclasses import dataclass, replace
from pathlib import Path

import laspy
import numpy as np

from georefine.adjustment.accuracy_standards import (
    positional_accuracy,
    surface_vertical_errors,
)
from georefine.errors import InputError
from georefine.evaluation.coverage import COVERAGE_MAPS, CoverageMap, write_coverage_png
from georefine.evaluation.reference_planes import (
    PlaneObservation,
    ReferencePlane,
    ReferencePlaneSummary,
    observe_reference_planes,
    reference_planes,
    summarise_observations,
)
from georefine.evaluation.strip_difference_maps import write_png
from georefine.evaluation.strip_differences import (
    LAYER_CODE,
    MAX_NORMAL_ANGLE_DEG,
    MAX_ROUGHNESS_M,
    MAX_SLOPE_DEG,
    MIN_POINTS,
    CellMoments,
    Reopened,
    StripDifferenceMap,
    StripDifferenceStream,
    cell_moments,
    crop,
    write_geotiff,
)
from georefine.geometry.frames import GeoidHeights, OutputCRS
from georefine.io.files import atomic_output, make_output_folder, write_json
from georefine.io.las import epsg_of, vertical_epsg_of
from georefine.io.reference import read_reference_surfaces
from georefine.progress import Progress, no_progress
from georefine.tasks import TaskRunner

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_CHUNK_POINTS", "CLOSE_AFTER_POINTS", "NEAR_PLANE_M", "plane_boxes", "reference_boxes",
    "record_ranges", "ScanSettings", "ChunkScan", "scan_chunk", "CloudScan", "scan_clouds", "evaluate_reference_planes",
    "evaluate_strip_differences",
]

DEFAULT_CHUNK_POINTS = 2_000_000
"""Records per task: about 0.3 GB of memory in the task (LAZ record, coordinates, cell sums)."""

NEAR_PLANE_M = 10.0
"""Half-size of the box kept around a reference surface's centre (at least; :func:`plane_boxes`)."""

CLOSE_AFTER_POINTS = 4_000_000
"""Records after which a strip x channel that got no points in a cell is done with it (files in
time order: the scanner has passed it); checked, not assumed (:func:`scan_clouds`)."""

_LAYER = LAYER_CODE  # layer code = point_source_id * 256 + scanner_channel


def plane_boxes(planes: list[ReferencePlane], max_distance_m: float = 0.3, margin_m: float = NEAR_PLANE_M) -> np.ndarray:
    """``(P, 2, 3)`` boxes (low and high corners) around the reference surfaces.

    Each is centred on its surface with a half-size of ``margin_m`` in x, y and z, or the
    surface's radius plus ``max_distance_m`` where that is larger, so that it holds every point
    :func:`~georefine.evaluation.reference_planes.observe_reference_planes` may count.
    """
    if not planes:
        return np.zeros((0, 2, 3))
    centre = np.array([p.centre for p in planes], dtype=float)
    reach = np.array([np.max(np.linalg.norm(p.outline_uv, axis=1)) + max_distance_m for p in planes])
    half = np.maximum(margin_m, reach)[:, None]
    return np.stack([centre - half, centre + half], axis=1)


def reference_boxes(reference_csv: Path, max_distance_m: float = 0.3, margin_m: float = NEAR_PLANE_M) -> np.ndarray:
    """:func:`plane_boxes` of the reference surfaces in ``reference_csv``."""
    return plane_boxes(reference_planes(read_reference_surfaces(reference_csv)), max_distance_m, margin_m)


def _in_boxes(xyz: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Which points lie in at least one box (boxes that miss the points' extent are skipped)."""
    keep = np.zeros(xyz.shape[0], dtype=bool)
    if xyz.shape[0] == 0 or boxes.shape[0] == 0:
        return keep
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    for b in boxes[np.all((boxes[:, 0] <= hi) & (boxes[:, 1] >= lo), axis=1)]:
        keep |= np.all((xyz >= b[0]) & (xyz <= b[1]), axis=1)
    return keep


def _open(path: Path):
    """The file open for reading x, y, z, point_source_id and scanner_channel only."""
    sel = (laspy.DecompressionSelection.XY_RETURNS_CHANNEL | laspy.DecompressionSelection.Z
           | laspy.DecompressionSelection.POINT_SOURCE_ID)
    try:
        return laspy.open(path, decompression_selection=sel)
    except (laspy.errors.LaspyException, OSError, ValueError) as exc:
        raise InputError(f"cannot read the point cloud ({exc})", path=path) from exc


def record_ranges(files: list[Path], chunk_points: int = DEFAULT_CHUNK_POINTS) -> list[tuple[Path, int, int]]:
    """``(file, start, stop)`` record ranges of at most ``chunk_points`` covering every file."""
    step = max(1, int(chunk_points))
    out = []
    for f in map(Path, files):
        with _open(f) as reader:
            n = int(reader.header.point_count)
        out += [(f, a, min(a + step, n)) for a in range(0, n, step)]
    return out


def _read_range(path: Path, start: int, stop: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(xyz, point_source_id, scanner_channel)`` of records ``start`` to ``stop`` (exclusive).

    Only the layers that hold them are decompressed; LAZ seeks through its chunk table, so a
    range costs about its own points.
    """
    try:
        with _open(path) as reader:
            reader.seek(start)
            rec = reader.read_points(stop - start)
            xyz = np.column_stack([rec.x, rec.y, rec.z])
            sid, ch = np.asarray(rec.point_source_id), np.asarray(rec.scanner_channel)
    except InputError:
        raise
    except Exception as exc:  # laspy/lazrs raise many types for corrupt files
        raise InputError(f"cannot read the point cloud ({exc})", path=path, record_kind="record",
                         line=start + 1, expected=f"records {start + 1}..{stop}") from exc
    if xyz.shape[0] != stop - start:
        raise InputError("truncated point data", path=path, record_kind="record", line=start + xyz.shape[0] + 1,
                         expected=f"records {start + 1}..{stop}", found=f"{xyz.shape[0]} records")
    return xyz, sid, ch


@dataclass(frozen=True)
class ScanSettings:
    """What a chunk task keeps: cell sums of this size (``None``: none) and the points in these
    ``(P, 2, 3)`` boxes (``None``: none). ``ellipsoidal``: the output CRS and geoid grid that turn
    the file's gravity-related heights back into ellipsoidal ones (:func:`scan_clouds`)."""

    cell_size_m: float | None = None
    boxes: np.ndarray | None = None
    ellipsoidal: tuple[OutputCRS, GeoidHeights] | None = None


@dataclass(frozen=True)
class ChunkScan:
    """What one chunk task returns: its layers and their points, cell sums and near-surface points."""

    layers: np.ndarray  # (L,) int64 layer codes (point_source_id * 256 + scanner_channel), sorted
    points: np.ndarray  # (L,) int64 points per layer
    moments: tuple[CellMoments, ...] | None  # per layer (same order), one row per cell
    near_xyz: np.ndarray  # (K, 3) points in the boxes
    near_layer: np.ndarray  # (K,) their layer codes


def scan_chunk(path: Path, start: int, stop: int, settings: ScanSettings) -> ChunkScan:
    """The task of one record range: read it and reduce it to what ``settings`` asks for."""
    xyz, sid, ch = _read_range(Path(path), int(start), int(stop))
    if settings.ellipsoidal is not None:
        crs, geoid = settings.ellipsoidal
        xyz = geoid.ellipsoidal_xyz(crs, xyz, what=f"points of {Path(path).name}")
    code = sid.astype(np.int64) * _LAYER + ch
    layers, points = np.unique(code, return_counts=True)
    moments = None
    if settings.cell_size_m is not None:
        order = np.argsort(code, kind="stable")
        bounds = np.append(0, np.cumsum(points))
        sorted_xyz = xyz[order]
        moments = tuple(cell_moments(sorted_xyz[a:b], settings.cell_size_m, int(k))
                        for k, a, b in zip(layers, bounds, bounds[1:]))
        del sorted_xyz, order
    if settings.boxes is not None:
        near = _in_boxes(xyz, settings.boxes)
        near_xyz, near_layer = xyz[near], code[near]
    else:
        near_xyz, near_layer = np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    return ChunkScan(layers, points, moments, near_xyz, near_layer)


@dataclass(frozen=True)
class CloudScan:
    """The point files reduced to what the metrics need (:func:`scan_clouds`)."""

    files: tuple[Path, ...]
    layers: tuple[tuple[int, int, int], ...]  # (strip, channel, points), sorted
    strip_differences: StripDifferenceMap | None
    coverage: CoverageMap | None  # points and strips per cell, on the strip-difference raster
    settings: tuple[float, int, float, float, float] | None  # cell size, min points, roughness, slope, normal angle
    boxes: np.ndarray | None
    near_xyz: np.ndarray  # (K, 3) the points in the boxes, by layer, in file order within a layer
    near_strip: np.ndarray  # (K,)
    near_channel: np.ndarray  # (K,)


def scan_clouds(
    files: list[Path], *, cell_size_m: float | None = None, min_points: int = MIN_POINTS,
    max_roughness_m: float = MAX_ROUGHNESS_M, max_slope_deg: float = MAX_SLOPE_DEG,
    max_normal_angle_deg: float = MAX_NORMAL_ANGLE_DEG, boxes: np.ndarray | None = None, runner: TaskRunner | None = None, chunk_points: int = DEFAULT_CHUNK_POINTS,
    close_after: int | None = CLOSE_AFTER_POINTS, progress: Progress = no_progress,
    label: str = "point cloud evaluation", heights: tuple[OutputCRS, GeoidHeights] | None = None,
) -> CloudScan:
    """Read ``files`` once, a task per record range (:func:`scan_chunk`) on ``runner`` (default:
    this process), the results taken in the order of the ranges.

    ``cell_size_m``: the strip-difference map on that raster (with ``min_points``,
    ``max_roughness_m``, ``max_slope_deg``, ``max_normal_angle_deg``: the gate of
    :mod:`georefine.evaluation.strip_differences`); ``boxes`` (:func:`plane_boxes`): keep the points inside them.
    The layers' cell sums are closed (:class:`~georefine.evaluation.strip_differences.StripDifferenceStream`)
    when a file ends and when a cell got no points for ``close_after`` records; if a file brings
    points to a closed layer x cell (a strip split over files, a file not in time order), the
    files are read again with every cell open to the end, in memory that grows with the cells of
    all layers (a warning says so).

    ``heights``: the output CRS and the geoid grid of the run (``crs.geoid_grid``). A file whose
    header states the grid's vertical CRS (a run's final clouds with gravity-related heights)
    is read back to ellipsoidal heights, ``h = H + N``, chunk by chunk: the reference surfaces
    and the simulated truth the metrics compare with are ellipsoidal, as everything inside
    Georefine is, so the evaluation stays ellipsoidal rather than converting them. Other files,
    and every file without ``heights``, are taken as they are.
    """
    files = [Path(f) for f in files]
    runner = runner or TaskRunner("sync")
    settings = ScanSettings(None if cell_size_m is None else float(cell_size_m),
                            None if boxes is None else np.asarray(boxes, dtype=float).reshape(-1, 2, 3))
    per_file = {f: settings for f in files}
    if heights is not None:
        for f in files:
            if vertical_epsg_of(f) == int(heights[1].vertical_epsg):
                per_file[f] = replace(settings, ellipsoidal=(heights[0], heights[1]))
    tasks = [(f, a, b, per_file[f]) for f, a, b in record_ranges(files, chunk_points)]
    gate = (int(min_points), float(max_roughness_m), float(max_slope_deg), float(max_normal_angle_deg))
    try:
        return _scan(files, tasks, settings, gate, runner, close_after, True, progress, label)
    except Reopened as exc:
        log.warning("%s: reading the point clouds again with every cell kept to the end (memory grows with "
                    "the cells of all layers)", exc)
    return _scan(files, tasks, settings, gate, runner, None, False, progress, label)


def _scan(files, tasks, settings, gate, runner, close_after, close_files, progress, label) -> CloudScan:
    min_points, max_roughness_m, max_slope_deg, max_normal_angle_deg = gate
    stream = None
    if settings.cell_size_m is not None:
        stream = StripDifferenceStream(settings.cell_size_m, min_points, max_roughness_m, max_slope_deg=max_slope_deg,
                                       max_normal_angle_deg=max_normal_angle_deg, close_after=close_after)
    last = {f: k for k, (f, *_) in enumerate(tasks)}  # the last task of every file
    counts: dict[int, int] = {}
    in_file: set[int] = set()
    near_xyz, near_layer = [], []
    for k, part in enumerate(runner.map(scan_chunk, tasks, label=label, progress=progress)):
        for code, n in zip(part.layers.tolist(), part.points.tolist()):
            counts[code] = counts.get(code, 0) + n
        in_file.update(part.layers.tolist())
        if stream is not None:
            stream.add(part.moments, tasks[k][2] - tasks[k][1])
            if close_files and last[tasks[k][0]] == k:
                for code in in_file:
                    stream.close_layer(code)
        if last[tasks[k][0]] == k:
            in_file = set()
        if part.near_xyz.shape[0]:
            near_xyz.append(part.near_xyz)
            near_layer.append(part.near_layer)
    xyz = np.concatenate(near_xyz) if near_xyz else np.zeros((0, 3))
    code = np.concatenate(near_layer) if near_layer else np.zeros(0, dtype=np.int64)
    order = np.argsort(code, kind="stable")  # by layer, as the observations are made
    xyz, code = xyz[order], code[order]
    layers = tuple((c // _LAYER, c % _LAYER, counts[c]) for c in sorted(counts))
    return CloudScan(tuple(files), layers, None if stream is None else stream.result(),
                     None if stream is None else stream.coverage(),
                     None if stream is None else (settings.cell_size_m, *gate),
                     settings.boxes, xyz, code // _LAYER, code % _LAYER)


def evaluate_reference_planes(
    files: list[Path], reference_csv: Path, out: Path | None = None, *, inset_m: float = 0.25,
    max_distance_m: float = 0.3, min_points: int = 10, scan: CloudScan | None = None,
    runner: TaskRunner | None = None, chunk_points: int = DEFAULT_CHUNK_POINTS, progress: Progress = no_progress,
) -> tuple[list[PlaneObservation], ReferencePlaneSummary]:
    """Observations of the reference surfaces and the Table 1 figures (written to ``out``).

    ``files`` are read in chunks on ``runner`` (:func:`scan_clouds`), keeping the points near
    each surface (:func:`plane_boxes`); ``scan``: a scan of ``files`` already made with boxes
    that hold those.
    """
    planes = reference_planes(read_reference_surfaces(reference_csv))
    boxes = plane_boxes(planes, max_distance_m)
    if scan is None:
        scan = scan_clouds(files, boxes=boxes, runner=runner, chunk_points=chunk_points, progress=progress)
    elif scan.boxes is None or scan.boxes.shape != boxes.shape or not (
            np.all(scan.boxes[:, 0] <= boxes[:, 0]) and np.all(scan.boxes[:, 1] >= boxes[:, 1])):
        raise ValueError("the scan did not keep the points near these reference surfaces (scan_clouds(boxes=...))")
    obs = observe_reference_planes(scan.near_xyz, scan.near_strip, scan.near_channel, planes, inset_m=inset_m,
                                   max_distance_m=max_distance_m, min_points=min_points)
    obs.sort(key=lambda o: (o.surface_id, o.strip, o.channel))
    errors, survey, _ = surface_vertical_errors(obs, planes)
    summary = replace(summarise_observations(obs), vertical=positional_accuracy(errors, survey))
    if out is not None:
        make_output_folder(out)
        write_json(out / "reference_planes.json", {
            **summary.to_dict(), "inset_m": inset_m, "max_distance_m": max_distance_m,
            "observations": [o.__dict__ for o in obs], "files": [str(f) for f in files],
        })
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(["surface_id", "strip", "channel", "n_points", "mean_mm", "sd_points_mm"])
        for o in obs:
            w.writerow([o.surface_id, o.strip, o.channel, o.n_points, f"{o.mean_m * 1e3:.2f}", f"{o.sd_points_m * 1e3:.2f}"])
        with atomic_output(out / "reference_planes.csv", "w") as fh:
            fh.write(buf.getvalue())
    return obs, summary


def evaluate_strip_differences(
    files: list[Path], out: Path | None = None, *, cell_size_m: float = 1.0, min_points: int = MIN_POINTS,
    max_roughness_m: float = MAX_ROUGHNESS_M, max_slope_deg: float = MAX_SLOPE_DEG,
    max_normal_angle_deg: float = MAX_NORMAL_ANGLE_DEG, title: str = "", zoom: tuple[float, float, float, float] | None = None,
    scan: CloudScan | None = None, runner: TaskRunner | None = None, chunk_points: int = DEFAULT_CHUNK_POINTS,
    progress: Progress = no_progress, sites: list[tuple[str, float, float]] | None = None,
) -> StripDifferenceMap:
    """The strip-difference raster over all strip x channel layers (files written to ``out``).

    ``files`` are read in chunks on ``runner`` (:func:`scan_clouds`), keeping per-cell sums;
    ``scan``: a scan of ``files`` already made with the same settings. ``min_points``,
    ``max_roughness_m``, ``max_slope_deg``, ``max_normal_angle_deg``: the gate
    (:mod:`georefine.evaluation.strip_differences`, "Gating"); ``strip_differences.json`` holds
    the figures of the gated map, the cells gated per reason (``gated``) and the figures of the
    map without the gate (``ungated``). ``sites``: ``(label, x, y)`` marked on the maps. ``zoom``: ``(xmin, xmax,
    ymin, ymax)`` of an additional detail map, ``strip_differences_zoom.png`` (as paper 000's
    Fig. 7 shows a semi-urban area).
    """
    wanted = (float(cell_size_m), int(min_points), float(max_roughness_m), float(max_slope_deg),
              float(max_normal_angle_deg))
    if scan is None:
        scan = scan_clouds(files, cell_size_m=cell_size_m, min_points=min_points, max_roughness_m=max_roughness_m,
                           max_slope_deg=max_slope_deg, max_normal_angle_deg=max_normal_angle_deg,
                           runner=runner, chunk_points=chunk_points, progress=progress)
    elif scan.settings != wanted:
        raise ValueError(f"the scan made the map with (cell_size_m, min_points, max_roughness_m, max_slope_deg, "
                         f"max_normal_angle_deg) = {scan.settings}, not {wanted}")
    m = scan.strip_differences
    if out is not None:
        make_output_folder(out)
        epsg = epsg_of(files[0])
        write_json(out / "strip_differences.json", {
            **m.summary(), "cell_size_m": cell_size_m, "min_points": min_points, "max_roughness_m": max_roughness_m,
            "max_slope_deg": max_slope_deg, "max_normal_angle_deg": max_normal_angle_deg,
            "gated": m.gating(), "ungated": m.ungated_summary(),
            "layers": [{"strip": s, "channel": c, "points": n} for s, c, n in scan.layers],
            "x0": m.x0, "y1": m.y1, "epsg": epsg,
            **({} if scan.coverage is None else {"coverage": scan.coverage.summary()}),
        })
        write_png(out / "strip_differences.png", m, title=title, epsg=epsg, sites=sites)
        if scan.coverage is not None:  # the same scan's density and overlap
            for what in COVERAGE_MAPS:
                write_coverage_png(out / f"coverage_{what}.png", scan.coverage, what, epsg=epsg, sites=sites,
                                   title=title.replace("strip differences", "coverage") if title else "")
        if zoom is not None:
            write_png(out / "strip_differences_zoom.png", crop(m, zoom), title=title + " (detail)", epsg=epsg,
                      sites=sites)
        if epsg is not None:
            write_geotiff(out / "strip_differences.tif", m, epsg)
    return m
