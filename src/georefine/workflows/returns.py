"""The LiDAR returns behind a georeferenced cloud's points (docs/ARCHITECTURE.md §4.8).

A lidargram's ULPI raster names a point of the cloud it was rendered from: its record number in
the point files taken in order (:class:`~georefine.workflows.cloud_index.CloudIndex`). The
hybrid adjustment of GNSS, IMU, LiDAR and photos observes the trajectory through that point, so
it needs the return itself: its time and its vector in the scanner frame, which the project's
scan files hold (``scans/strip_N.laz``, scanner frame).

``georefine run`` and ``georefine georeference`` write each strip's points in the scan file's
record order, every record (``points_outside`` 0), with the GPS time at which each was
georeferenced: the scan's time plus the LiDAR time offset the run applied (configured and
estimated, one constant per run). :func:`returns_of_points` relies on that and checks it: the
point file and the scan file of a strip (the same ``point_source_id``) must hold the same number
of records, and the looked-up records together with the strip's first and last must differ in
time by one constant; a cloud that does not (points dropped, resorted, or from another scan) is
refused, naming the files.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from georefine.errors import InputError
from georefine.io.las import read_las_info, read_las_range
from georefine.io.las_encode import LAZ_CHUNK_POINTS
from georefine.workflows.strips import strip_id_of

__all__ = ["LidarReturns", "returns_of_points"]

_TIME_TOL_S = 1e-6  # spread of (point time - scan time) within a strip: the applied offset is one constant


@dataclass(frozen=True)
class LidarReturns:
    """Returns of looked-up points, in the order asked for (N each).

    ``strip_id`` (``point_source_id``), ``record`` (its number in the scan file), ``time_gps``
    (GPS seconds at which the cloud georeferenced it: the point file's time), ``x_s`` (N, 3) the
    return in the scanner frame (m), ``channel`` (``scanner_channel``); ``offset_s`` per strip id,
    the point files' time minus the scan's (the time offset the run applied).
    """

    strip_id: np.ndarray
    record: np.ndarray
    time_gps: np.ndarray
    x_s: np.ndarray
    channel: np.ndarray
    offset_s: dict[int, float]

    def __len__(self) -> int:
        return int(self.record.size)


def _read_records(path: Path, records: np.ndarray):
    """``(time_gps, xyz, channel)`` of sorted unique ``records`` of one file, one LAZ chunk at a time."""
    times, xyz, channel = (np.empty(records.size), np.empty((records.size, 3)), np.empty(records.size, np.uint8))
    chunk = records // LAZ_CHUNK_POINTS
    starts = np.flatnonzero(np.r_[True, chunk[1:] != chunk[:-1]])
    for a, b in zip(starts, np.r_[starts[1:], records.size]):
        lo = int(records[a])
        pc = read_las_range(path, lo, int(records[b - 1]) + 1)
        at = records[a:b] - lo
        times[a:b], xyz[a:b], channel[a:b] = pc.time_gps[at], pc.xyz[at], pc.scanner_channel[at]
    return times, xyz, channel


def returns_of_points(point_files: list[Path], scan_files: list[Path], ids: np.ndarray) -> LidarReturns:
    """The scan records behind points ``ids`` of the cloud ``point_files`` (module docstring).

    Parameters
    ----------
    point_files
        The georeferenced strips, in the order the point identifiers count them.
    scan_files
        The project's scan files (scanner frame); matched to the point files by ``point_source_id``.
    ids : (N,) int
        Point identifiers (record numbers across ``point_files``), e.g. ULPI values.

    Raises
    ------
    InputError
        An identifier outside the cloud, a strip without its scan file, a strip whose record
        count differs from its scan's, or a record whose GPS time differs between the two files.
    """
    ids = np.asarray(ids, dtype=np.int64).reshape(-1)
    point_files, scan_files = [Path(p) for p in point_files], [Path(p) for p in scan_files]
    counts = np.array([read_las_info(p).point_count for p in point_files], dtype=np.int64)
    start = np.r_[0, np.cumsum(counts)]
    if ids.size and (ids.min() < 0 or ids.max() >= start[-1]):
        bad = ids[(ids < 0) | (ids >= start[-1])][0]
        raise InputError("point identifier outside the cloud", field="ulpi",
                         expected=f"0 .. {start[-1] - 1} ({len(point_files)} files)", found=str(int(bad)))
    scans = {strip_id_of(p): p for p in scan_files}
    out_strip = np.empty(ids.size, np.int64)
    out_record = np.empty(ids.size, np.int64)
    out_time, out_x, out_ch = np.empty(ids.size), np.empty((ids.size, 3)), np.empty(ids.size, np.uint8)
    file_of = np.searchsorted(start, ids, side="right") - 1
    offsets: dict[int, float] = {}
    for f, path in enumerate(point_files):
        mine = np.flatnonzero(file_of == f)
        if mine.size == 0:
            continue
        sid = strip_id_of(path)
        scan = scans.get(sid)
        if scan is None:
            raise InputError("no scan file for this strip", path=path, field="point_source_id",
                             expected="one of " + ", ".join(map(str, sorted(scans))), found=str(sid))
        n_scan = read_las_info(scan).point_count
        if n_scan != counts[f]:
            raise InputError("the strip does not hold every record of its scan, in order", path=path,
                             expected=f"{n_scan} records as {scan.name}", found=f"{counts[f]} records")
        wanted = ids[mine] - start[f]
        records = np.unique(np.r_[wanted, 0, counts[f] - 1])  # the ends pin the offset down
        t_pts, _, _ = _read_records(path, records)
        t_scan, x_s, channel = _read_records(scan, records)
        diff = t_pts - t_scan
        offset = float(diff[0])
        off = np.abs(diff - offset) > _TIME_TOL_S
        if np.any(off):
            k = int(np.flatnonzero(off)[0])
            raise InputError("the strip's record is not its scan's", path=path, record_kind="record",
                             line=int(records[k]) + 1, field="gps_time",
                             expected=f"{t_scan[k] + offset:.6f} ({scan.name}'s time + the strip's offset "
                                      f"{offset * 1e3:.3f} ms)", found=f"{t_pts[k]:.6f}")
        at = np.searchsorted(records, wanted)
        out_strip[mine], out_record[mine], offsets[sid] = sid, wanted, offset
        out_time[mine], out_x[mine], out_ch[mine] = t_pts[at], x_s[at], channel[at]
    return LidarReturns(out_strip, out_record, out_time, out_x, out_ch, offsets)
