"""LAS 1.4 / LAZ point clouds: scanner-frame strips and georeferenced clouds.

Conventions (docs/ARCHITECTURE.md §3):

* ``gps_time`` in the file is *adjusted standard GPS time* (GPS seconds − 1e9)
  and the LAS 1.4 global-encoding GPS-time-type bit must be set; in memory
  ``time_gps`` is GPS seconds (``gps_time + 1e9``).
* ``x, y, z``: scanner frame ``s`` coordinates (metres) for raw strips, output
  CRS coordinates for georeferenced clouds.
* ``scanner_channel`` = view direction (0 nadir, 1 forward, 2 backward),
  ``point_source_id`` = strip id; the header's file source ID is the strip id too when the
  file holds one strip (0 when it mixes strips).
* ``scan_angle`` (int16, steps of 0.006 degrees; in memory ``scan_angle_deg``): as LAS 1.4
  defines it, the angle of the beam from "down" in the coordinate system of the data, in the
  plane across the flight direction, positive to the right of the flight direction (counter-
  clockwise seen from behind). In georeferenced clouds "down" is the local vertical, so the
  angle includes the aircraft's roll (:func:`georefine.lidar.georeference.scan_angles_deg`); in
  scanner-frame strips it is the scanner's +z axis, so the angle is the mirror's angle in the
  scan line, without the roll.
* Point format 6 or higher (LAS 1.4). Extra dimensions (LAS extra bytes) are read by name, as
  float64, e.g. ``range_error_m``; they are written with a type, a description and a no-data
  value (:class:`georefine.io.las_encode.ExtraDim`).
* The CRS is a WKT VLR in the form GDAL, PDAL and LAStools read
  (:func:`georefine.io.las_writer.las_crs_wkt`); files written by earlier versions, with the
  3-D CRS in WKT2, read as well.

Files can be larger than memory: :func:`iter_las_chunks` streams them with
``laspy.open(...).chunk_iterator(n)``; :class:`georefine.io.las_writer.LasWriter`
writes chunk by chunk to a temporary name that is renamed on close, the records
and LAZ chunks possibly encoded by the tasks that compute them
(:mod:`georefine.io.las_encode`). LAZ uses the lazrs backend.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from georefine.errors import InputError
from georefine.io.files import PathLike
from georefine.io.point_manifest import manifest_files

__all__ = ["PointCloud", "ScanChunk", "LasInfo", "TimeIndex", "read_las_info", "iter_las_chunks",
           "read_las", "read_las_range", "time_index", "point_files", "epsg_of", "vertical_epsg_of",
           "GPS_TIME_OFFSET_S", "SCAN_ANGLE_UNIT_DEG"]

_log = logging.getLogger(__name__)

GPS_TIME_OFFSET_S = 1.0e9
"""Adjusted standard GPS time = GPS seconds − this offset."""

SCAN_ANGLE_UNIT_DEG = 0.006
"""One step of the LAS 1.4 ``scan_angle`` (point formats 6-10), degrees."""

_MIN_POINT_FORMAT = 6


@dataclass(frozen=True)
class PointCloud:
    """A chunk of points (struct of arrays, leading axis N).

    Attributes
    ----------
    time_gps
        (N,) float64 GPS seconds (not necessarily increasing).
    xyz
        (N,3) float64 coordinates, metres (scanner frame or output CRS).
    intensity
        (N,) uint16.
    scanner_channel
        (N,) uint8, 0..3 (view direction).
    point_source_id
        (N,) uint16 (strip id).
    return_number, number_of_returns
        (N,) uint8, 0..15.
    extra
        Extra float dimensions by name, each (N,) float64.
    scan_angle_deg
        (N,) float64 LAS scan angle in degrees (module docstring); default 0 for every point.
    """

    time_gps: np.ndarray
    xyz: np.ndarray
    intensity: np.ndarray
    scanner_channel: np.ndarray
    point_source_id: np.ndarray
    return_number: np.ndarray
    number_of_returns: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    scan_angle_deg: np.ndarray | None = None

    def __post_init__(self) -> None:
        t = np.ascontiguousarray(self.time_gps, dtype=np.float64)
        if t.ndim != 1:
            raise ValueError(f"time_gps must be 1-D, got shape {t.shape}")
        n = t.shape[0]
        xyz = np.ascontiguousarray(self.xyz, dtype=np.float64)
        if xyz.shape != (n, 3):
            raise ValueError(f"xyz must have shape {(n, 3)}, got {xyz.shape}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(xyz))):
            raise ValueError("time_gps and xyz must be finite")
        object.__setattr__(self, "time_gps", t)
        object.__setattr__(self, "xyz", xyz)
        for name, dtype, hi in (("intensity", np.uint16, 65535), ("scanner_channel", np.uint8, 3),
                                ("point_source_id", np.uint16, 65535), ("return_number", np.uint8, 15),
                                ("number_of_returns", np.uint8, 15)):
            a = np.asarray(getattr(self, name))
            if a.shape != (n,):
                raise ValueError(f"{name} must have shape {(n,)}, got {a.shape}")
            if a.size and (np.min(a) < 0 or np.max(a) > hi):
                raise ValueError(f"{name} must be in 0..{hi}")
            object.__setattr__(self, name, np.ascontiguousarray(a, dtype=dtype))
        extra = {}
        for name, a in self.extra.items():
            a = np.ascontiguousarray(a, dtype=np.float64)
            if a.shape != (n,):
                raise ValueError(f"extra dimension {name!r} must have shape {(n,)}, got {a.shape}")
            extra[name] = a
        object.__setattr__(self, "extra", extra)
        angle = np.zeros(n) if self.scan_angle_deg is None else np.ascontiguousarray(self.scan_angle_deg, np.float64)
        if angle.shape != (n,):
            raise ValueError(f"scan_angle_deg must have shape {(n,)}, got {angle.shape}")
        object.__setattr__(self, "scan_angle_deg", angle)

    def __len__(self) -> int:
        return self.time_gps.shape[0]

    @classmethod
    def empty(cls, extra_dims: Sequence[str] = ()) -> PointCloud:
        """No points (with the given extra dimensions)."""
        e = np.empty(0)
        return cls(e, np.empty((0, 3)), e, e, e, e, e, {k: e for k in extra_dims})

    @classmethod
    def concatenate(cls, chunks: Sequence[PointCloud]) -> PointCloud:
        """One cloud from several chunks with the same extra dimensions."""
        if not chunks:
            raise ValueError("no chunks to concatenate")
        names = list(chunks[0].extra)
        return cls(
            time_gps=np.concatenate([c.time_gps for c in chunks]),
            xyz=np.concatenate([c.xyz for c in chunks]),
            intensity=np.concatenate([c.intensity for c in chunks]),
            scanner_channel=np.concatenate([c.scanner_channel for c in chunks]),
            point_source_id=np.concatenate([c.point_source_id for c in chunks]),
            return_number=np.concatenate([c.return_number for c in chunks]),
            number_of_returns=np.concatenate([c.number_of_returns for c in chunks]),
            extra={k: np.concatenate([c.extra[k] for c in chunks]) for k in names},
            scan_angle_deg=np.concatenate([c.scan_angle_deg for c in chunks]),
        )


ScanChunk = PointCloud
"""A chunk of a scanner-frame strip: the same structure as :class:`PointCloud`."""


@dataclass(frozen=True)
class LasInfo:
    """Header facts of a LAS/LAZ file."""

    path: Path
    point_count: int
    point_format: int
    version: str
    scales: np.ndarray
    offsets: np.ndarray
    mins: np.ndarray
    maxs: np.ndarray
    extra_dims: tuple[str, ...]
    crs_wkt: str | None
    compressed: bool


def _open_reader(path: Path):
    import laspy  # deferred: heavy import

    if not path.is_file():
        raise InputError("file not found", path=path)
    try:
        return laspy.open(path)
    except Exception as exc:  # laspy/lazrs raise many types for corrupt files
        raise InputError(f"cannot open as LAS/LAZ: {exc}", path=path, expected="a LAS 1.4 or LAZ file") from exc


def _validate_header(path: Path, header) -> None:
    from laspy.header import GpsTimeType

    pf = header.point_format.id
    if pf < _MIN_POINT_FORMAT:
        raise InputError("point format not supported", path=path, field="point_format",
                         expected=f"{_MIN_POINT_FORMAT} or higher (LAS 1.4)", found=str(pf))
    if header.global_encoding.gps_time_type != GpsTimeType.STANDARD:
        raise InputError("GPS time type bit not set", path=path, field="global_encoding",
                         expected="adjusted standard GPS time (bit 0 set)", found="GPS week time (bit 0 clear)")
    names = set(header.point_format.dimension_names)
    for required in ("X", "Y", "Z", "gps_time", "intensity", "scanner_channel", "point_source_id",
                     "return_number", "number_of_returns"):
        if required not in names:
            raise InputError("required dimension missing", path=path, field=required, expected="present",
                             found="absent")


def gps_week_of_strip(path: PathLike) -> int:
    """GPS week of a strip's first point (to read trajectories stored in seconds of week)."""
    first = next(iter_las_chunks(path, 1), None)
    if first is None or len(first) == 0:
        raise InputError("strip has no points", path=Path(path))
    return int(first.time_gps[0] // 604800)


def read_las_info(path: PathLike) -> LasInfo:
    """Open, validate and describe a LAS/LAZ file without reading its points."""
    path = Path(path)
    with _open_reader(path) as reader:
        h = reader.header
        _validate_header(path, h)
        try:
            crs = h.parse_crs()
        except Exception:  # an unreadable CRS VLR is not fatal for reading points
            _log.warning("%s: CRS VLR could not be parsed", path)
            crs = None
        return LasInfo(
            path=path, point_count=int(h.point_count), point_format=h.point_format.id, version=str(h.version),
            scales=np.array(h.scales, float), offsets=np.array(h.offsets, float),
            mins=np.array(h.mins, float), maxs=np.array(h.maxs, float),
            extra_dims=tuple(h.point_format.extra_dimension_names),
            crs_wkt=None if crs is None else crs.to_wkt(), compressed=h.are_points_compressed,
        )


def _extra_names(path: Path, header, extra_dims: Sequence[str] | None) -> tuple[str, ...]:
    """The extra dimensions to read (``None``: all of the file's); a requested one that is absent is an error."""
    available = tuple(header.point_format.extra_dimension_names)
    names = available if extra_dims is None else tuple(extra_dims)
    for name in names:
        if name not in available:
            raise InputError("extra dimension missing", path=path, field=name,
                             expected="present", found=f"extra dimensions {list(available)}")
    return names


def _chunk_from_record(rec, extra_names: Sequence[str]) -> PointCloud:
    return PointCloud(
        time_gps=np.asarray(rec.gps_time, dtype=np.float64) + GPS_TIME_OFFSET_S,
        xyz=np.column_stack([np.asarray(rec.x), np.asarray(rec.y), np.asarray(rec.z)]),
        intensity=np.asarray(rec.intensity), scanner_channel=np.asarray(rec.scanner_channel),
        point_source_id=np.asarray(rec.point_source_id), return_number=np.asarray(rec.return_number),
        number_of_returns=np.asarray(rec.number_of_returns),
        extra={k: np.asarray(rec[k], dtype=np.float64) for k in extra_names},
        scan_angle_deg=np.asarray(rec.scan_angle, dtype=np.float64) * SCAN_ANGLE_UNIT_DEG,
    )


def iter_las_chunks(
    path: PathLike, chunk_size: int = 1_000_000, extra_dims: Sequence[str] | None = None
) -> Iterator[PointCloud]:
    """Stream a LAS/LAZ file in chunks of at most ``chunk_size`` points.

    Parameters
    ----------
    extra_dims
        Extra dimensions to return; default all extra dimensions of the file.

    Raises
    ------
    InputError
        The file does not open, the point format is below 6, the GPS time type
        bit is not set, a required dimension or a requested extra dimension is
        missing, or the point data are corrupt/truncated (with the point range).
    """
    path = Path(path)
    with _open_reader(path) as reader:
        h = reader.header
        _validate_header(path, h)
        names = _extra_names(path, h, extra_dims)
        total, done = int(h.point_count), 0
        it = reader.chunk_iterator(chunk_size)
        while True:
            try:
                rec = next(it)
            except StopIteration:
                break
            except Exception as exc:
                raise InputError(
                    f"corrupt or truncated point data: {exc}", path=path, record_kind="record",
                    line=done + 1, expected=f"{total} points", found=f"{done} points readable",
                ) from exc
            if len(rec) == 0:
                break
            done += len(rec)
            yield _chunk_from_record(rec, names)
        if done != total:
            raise InputError("truncated point data", path=path, expected=f"{total} points (header)",
                             found=f"{done} points")


@dataclass(frozen=True)
class TimeIndex:
    """Point times of a LAS/LAZ file sampled every ``step`` records, and whether they are ordered.

    ``index`` holds record numbers (0, step, 2 step, ..., and the last record), ``time_gps`` their
    GPS times. ``ordered`` is true when *every* record's time is at least its predecessor's
    (checked on all records, not only the samples); ``first_unordered`` is then -1, else the
    0-based number of the first record earlier than the one before it. ``channel_counts``: records
    per ``scanner_channel`` value 0-3 (read with the times, at no extra cost).
    """

    path: Path
    point_count: int
    index: np.ndarray
    time_gps: np.ndarray
    ordered: bool
    first_unordered: int
    channel_counts: tuple[int, int, int, int] = (0, 0, 0, 0)

    def first_at_or_after(self, t_gps: float) -> int:
        """A record number at or before the first record with time >= ``t_gps`` (ordered files)."""
        k = int(np.searchsorted(self.time_gps, t_gps, side="left")) - 1
        return 0 if k < 0 else int(self.index[k])

    def last_before(self, t_gps: float) -> int:
        """A record number (exclusive end) at or after the last record with time < ``t_gps``."""
        k = int(np.searchsorted(self.time_gps, t_gps, side="left"))
        return self.point_count if k >= self.index.size else int(self.index[k]) + 1


def time_index(path: PathLike, step: int = 5000, chunk_size: int = 4_000_000) -> TimeIndex:
    """Sample the point times of ``path`` every ``step`` records, in one streaming pass.

    Only the GPS-time layer of a LAZ file is decompressed (LAS 1.4 layered compression, about
    1.5x faster than a full read), with lazrs' multi-threaded decoder where available.

    Raises
    ------
    InputError
        As :func:`iter_las_chunks`; also a file without points.
    """
    import laspy

    path = Path(path)
    info = read_las_info(path)
    if info.point_count == 0:
        raise InputError("strip has no points", path=path)
    sel = laspy.DecompressionSelection.base() | laspy.DecompressionSelection.GPS_TIME
    backend = laspy.LazBackend.LazrsParallel if laspy.LazBackend.LazrsParallel.is_available() else None
    idx, times = [], []
    channels = np.zeros(4, dtype=np.int64)
    done, last, first_bad = 0, -np.inf, -1
    try:
        with laspy.open(path, decompression_selection=sel, laz_backend=backend) as reader:
            for rec in reader.chunk_iterator(chunk_size):
                g = np.asarray(rec.gps_time, dtype=np.float64)
                if g.size == 0:
                    break
                if first_bad < 0:
                    bad = np.flatnonzero(np.diff(np.r_[last, g]) < 0)
                    if bad.size:
                        first_bad = done + int(bad[0])
                k = np.arange(-done % step, g.size, step)
                idx.append(done + k)
                times.append(g[k])
                channels += np.bincount(np.asarray(rec.scanner_channel, dtype=np.int64), minlength=4)[:4]
                last = g[-1]
                done += g.size
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"corrupt or truncated point data: {exc}", path=path, record_kind="record",
                         line=done + 1, expected=f"{info.point_count} points") from exc
    if done != info.point_count:
        raise InputError("truncated point data", path=path, expected=f"{info.point_count} points (header)",
                         found=f"{done} points")
    index, t = np.concatenate(idx), np.concatenate(times)
    if index[-1] != done - 1:
        index, t = np.append(index, done - 1), np.append(t, last)
    return TimeIndex(path, done, index, t + GPS_TIME_OFFSET_S, first_bad < 0, first_bad,
                     tuple(int(c) for c in channels))


def read_las_range(path: PathLike, start: int, stop: int, extra_dims: Sequence[str] | None = ()) -> PointCloud:
    """Records ``start`` to ``stop`` (exclusive, 0-based) of a LAS/LAZ file.

    LAZ seeks through the chunk table, so a range costs about its own points, not the records
    before it. ``extra_dims``: extra dimensions to read (default none; ``None`` reads all).
    """
    path = Path(path)
    with _open_reader(path) as reader:
        h = reader.header
        _validate_header(path, h)
        total = int(h.point_count)
        if not 0 <= start <= stop <= total:
            raise ValueError(f"record range {start}..{stop} outside 0..{total} of {path}")
        names = _extra_names(path, h, extra_dims)
        try:
            reader.seek(start)
            rec = reader.read_points(stop - start)
        except Exception as exc:
            raise InputError(f"corrupt or truncated point data: {exc}", path=path, record_kind="record",
                             line=start + 1, expected=f"records {start + 1}..{stop}") from exc
        if len(rec) != stop - start:
            raise InputError("truncated point data", path=path, record_kind="record", line=start + len(rec) + 1,
                             expected=f"records {start + 1}..{stop}", found=f"{len(rec)} records")
        return _chunk_from_record(rec, names)


def read_las(path: PathLike, extra_dims: Sequence[str] | None = None) -> PointCloud:
    """Read a whole LAS/LAZ file (see :func:`iter_las_chunks` for validation)."""
    chunks = list(iter_las_chunks(path, extra_dims=extra_dims))
    if not chunks:
        info = read_las_info(path)
        return PointCloud.empty(extra_dims or info.extra_dims)
    return PointCloud.concatenate(chunks)


def point_files(paths: list[Path]) -> list[Path]:
    """LAS/LAZ files named directly or found in the named folders (sorted).

    A folder Georefine wrote gives the files its manifest lists (:mod:`georefine.io.point_manifest`:
    others are named in a warning and left out); any other folder, all its LAS/LAZ files.
    """
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            listed = manifest_files(p)
            out += listed if listed is not None else sorted(q for q in p.iterdir() if q.suffix.lower() in (".las", ".laz"))
        elif p.is_file():
            out.append(p)
        else:
            raise InputError("no such file or folder", path=p)
    if not out:
        raise InputError("no LAS/LAZ files", path=", ".join(map(str, paths)), expected="georeferenced strips")
    return out


def _header_crs(path: Path):
    """The ``pyproj.CRS`` of a LAS/LAZ file's header (its WKT), or None."""
    import laspy  # deferred: heavy import

    with laspy.open(path) as f:
        return f.header.parse_crs()


def epsg_of(path: Path) -> int | None:
    """EPSG code of a LAS/LAZ file's CRS (WKT in the header), if it has one."""
    crs = _header_crs(path)
    if crs is None:
        return None
    # The strips carry the projected CRS with ellipsoidal heights (3-D), which has no EPSG code
    # of its own: the horizontal CRS has.
    return crs.to_epsg() or crs.to_2d().to_epsg()


def vertical_epsg_of(path: Path) -> int | None:
    """EPSG code of the vertical part of a LAS/LAZ file's compound CRS, if it has one (a run's
    final clouds with gravity-related heights, ``crs.vertical_epsg``)."""
    crs = _header_crs(path)
    if crs is None or not crs.is_compound:
        return None
    vertical = [c for c in crs.sub_crs_list if c.is_vertical]
    return vertical[0].to_epsg() if vertical else None
