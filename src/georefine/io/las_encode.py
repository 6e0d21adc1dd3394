"""Point records encoded where they are made: LAS records and LAZ chunks built by tasks (docs/ARCHITECTURE.md §4.7).

A LAZ file of point format 6 or higher is a header, its VLRs, an 8-byte offset to the chunk
table, chunks of :data:`LAZ_CHUNK_POINTS` points compressed independently of each other (the
last one holds the rest), and the chunk table (LASzip specification, "LAZ File Layout"). So a
task that georeferenced a tile can also compress it: :func:`encode_points` turns a
:class:`~georefine.io.las.PointCloud` into whole LAZ chunks (lazrs) and the raw records of the
points after the last whole chunk, with the figures the header needs (count, bounds, points by
return). The process that writes the file (:class:`georefine.io.las_writer.LasWriter`) appends the
chunks as they are when the tile starts at a chunk boundary of the file -- tiles are planned in
multiples of :data:`LAZ_CHUNK_POINTS` records (:func:`georefine.lidar.tiles.plan_strip`) -- and
otherwise decodes them and compresses the points again itself, so the file is the same either
way.

The chunks keep LASzip's fixed chunk size. Variable-size chunks would free the tiles from the
chunk grid, but lazrs 0.8's parallel decoder (laspy's default) reads wrong points after a
``seek`` in such files, and LASzip crashes on a truncated one.

The records hold the point's ``scan_angle`` (LAS 1.4: int16 in steps of
:data:`SCAN_ANGLE_UNIT_DEG`, from :attr:`~georefine.io.las.PointCloud.scan_angle_deg`) and each
extra dimension as its :class:`ExtraDim` says: type, description and no-data value go into the
extra-bytes VLR, and the range the header states leaves the no-data values out (LAS 1.4 R15,
"Extra Bytes"). :class:`EncodedPoints` also carries the smallest and largest
``point_source_id``, from which the writer sets the header's file source ID.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

from georefine.io.las import GPS_TIME_OFFSET_S, SCAN_ANGLE_UNIT_DEG

__all__ = ["LAZ_CHUNK_POINTS", "SCAN_ANGLE_UNIT_DEG", "EncodedPoints", "ExtraDim", "LasLayout",
           "compress_chunks", "decompress_chunks", "encode_points", "scan_angle_counts"]

LAZ_CHUNK_POINTS = 50_000
"""Points per LAZ chunk (LASzip's default); a tile's last chunk holds the rest."""

_SCAN_ANGLE_MAX = 30_000
"""LAS 1.4 scan angle limit in steps (+-180 degrees, both straight up)."""


@dataclass(frozen=True)
class ExtraDim:
    """One extra dimension of a LAS 1.4 file (an extra-bytes descriptor).

    ``name`` and ``description`` (ASCII, at most 32 characters each) are what LAS readers show;
    ``dtype`` a numpy scalar type of 1 to 8 bytes; ``no_data`` the value that means "no value
    for this point" (options bit 0 set), or ``None`` for a dimension every point has. A name
    alone (``ExtraDim("x")``) is a float32 without description or no-data value.
    """

    name: str
    dtype: str = "<f4"
    description: str = ""
    no_data: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "dtype", np.dtype(self.dtype).str)
        for field, text in (("name", self.name), ("description", self.description)):
            if len(text) > 32 or not text.isascii():
                raise ValueError(f"extra dimension {field} must be ASCII of at most 32 characters, found {text!r}")
        if np.dtype(self.dtype).kind not in "iuf":
            raise ValueError(f"extra dimension {self.name!r}: numeric type expected, found {self.dtype}")
        if self.no_data is not None:
            value = float(self.no_data)
            if not np.isfinite(value) or np.dtype(self.dtype).type(value) != value:
                raise ValueError(f"extra dimension {self.name!r}: no-data value {self.no_data!r} is not a finite "
                                 f"{np.dtype(self.dtype).name}")
            object.__setattr__(self, "no_data", value)

    @classmethod
    def of(cls, spec) -> ExtraDim:
        """An :class:`ExtraDim` from itself, a name, or a ``(name, dtype)`` pair."""
        if isinstance(spec, ExtraDim):
            return spec
        if isinstance(spec, str):
            return cls(spec)
        name, dtype = spec
        return cls(str(name), np.dtype(dtype).str)

    def params(self):
        """The ``laspy.ExtraBytesParams`` of this dimension."""
        import laspy

        return laspy.ExtraBytesParams(name=self.name, type=np.dtype(self.dtype), description=self.description,
                                      no_data=None if self.no_data is None else [self.no_data])


@dataclass(frozen=True)
class LasLayout:
    """What fixes a file's point records: scale and offset (m or CRS units), extra dimensions
    (:class:`ExtraDim`; names or ``(name, dtype)`` pairs are accepted), compression."""

    scale: tuple[float, float, float]
    offset: tuple[float, float, float]
    extra: tuple[ExtraDim, ...] = ()
    compress: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "scale", tuple(float(v) for v in np.broadcast_to(self.scale, (3,))))
        object.__setattr__(self, "offset", tuple(float(v) for v in np.broadcast_to(self.offset, (3,))))
        object.__setattr__(self, "extra", tuple(ExtraDim.of(e) for e in self.extra))
        if not all(s > 0 for s in self.scale):
            raise ValueError(f"scale must be > 0, found {self.scale}")

    def point_header(self):
        """A bare LAS 1.4 point-format-6 ``laspy.LasHeader`` with this layout (no CRS, no counts)."""
        import laspy

        header = laspy.LasHeader(version="1.4", point_format=6)
        if self.extra:
            header.add_extra_dims([e.params() for e in self.extra])
        header.scales = np.asarray(self.scale)
        header.offsets = np.asarray(self.offset)
        return header

    def laz_vlr(self):
        """The lazrs LASzip VLR of the file: layered chunks of :data:`LAZ_CHUNK_POINTS` points."""
        import lazrs

        vlr = lazrs.LazVlr.new_for_compression(6, self.point_header().point_format.num_extra_bytes)
        if vlr.chunk_size() != LAZ_CHUNK_POINTS:
            raise RuntimeError(f"lazrs chunks of {vlr.chunk_size()} points, expected {LAZ_CHUNK_POINTS}")
        return vlr


@dataclass(frozen=True)
class EncodedPoints:
    """Points as the bytes of a file with ``layout`` and what its header needs of them.

    ``chunk_data``: whole LAZ chunks of :data:`LAZ_CHUNK_POINTS` points, ``chunk_bytes`` the
    size of each; ``records``: the raw point records that follow them (all points for LAS, or
    when not compressed here). ``mins``/``maxs``: bounds of the quantised coordinates;
    ``returns``: points by return number 1-15; ``extremes``: two raw records holding the
    smallest and the largest value of every extra dimension, no-data values left out (for the
    extra-bytes VLR; a dimension with only no-data values holds its type's largest value in the
    first and its smallest in the second); ``source_ids``: the smallest and the largest
    ``point_source_id`` (``(65535, 0)`` without points).
    """

    layout: LasLayout
    chunk_data: bytes
    chunk_bytes: tuple[int, ...]
    records: bytes
    count: int
    mins: np.ndarray
    maxs: np.ndarray
    returns: np.ndarray
    extremes: bytes = b""
    source_ids: tuple[int, int] = (65535, 0)

    def __len__(self) -> int:
        return self.count


def scan_angle_counts(scan_angle_deg: np.ndarray) -> np.ndarray:
    """LAS 1.4 scan angles (int16, steps of :data:`SCAN_ANGLE_UNIT_DEG`) of angles in degrees
    (wrapped to -180..180, rounded to the nearest step)."""
    a = np.remainder(np.asarray(scan_angle_deg, dtype=np.float64) + 180.0, 360.0) - 180.0
    return np.clip(np.rint(a / SCAN_ANGLE_UNIT_DEG), -_SCAN_ANGLE_MAX, _SCAN_ANGLE_MAX).astype(np.int16)


def _records(cloud, layout: LasLayout):
    """The point records of ``cloud`` (a ``laspy.ScaleAwarePointRecord``) in ``layout``."""
    import laspy

    missing = [e.name for e in layout.extra if e.name not in cloud.extra]
    if missing:
        raise ValueError(f"chunk lacks extra dimensions {missing}")
    counts = (cloud.xyz - np.asarray(layout.offset)) / np.asarray(layout.scale)
    if np.any(np.abs(counts) > np.iinfo(np.int32).max - 1):
        raise ValueError("coordinates out of the int32 range of the chosen scale/offset; pass offset=")
    rec = laspy.ScaleAwarePointRecord.zeros(len(cloud), header=layout.point_header())
    rec.x, rec.y, rec.z = cloud.xyz[:, 0], cloud.xyz[:, 1], cloud.xyz[:, 2]
    rec.gps_time = cloud.time_gps - GPS_TIME_OFFSET_S
    rec.intensity = cloud.intensity
    rec.scanner_channel = cloud.scanner_channel
    rec.point_source_id = cloud.point_source_id
    rec.return_number = cloud.return_number
    rec.number_of_returns = cloud.number_of_returns
    rec.scan_angle = scan_angle_counts(cloud.scan_angle_deg)
    for e in layout.extra:
        values = cloud.extra[e.name]
        rec[e.name] = np.rint(values) if np.dtype(e.dtype).kind in "iu" else values
    return rec


def compress_chunks(records, vlr, parallel: bool) -> tuple[bytes, tuple[int, ...]]:
    """LAZ chunks of the raw ``records`` (uint8 buffer) and each chunk's size in bytes."""
    import lazrs

    raw = np.frombuffer(records, np.uint8)
    if raw.size == 0:
        return b"", ()
    blob = bytes(lazrs.compress_points(vlr, raw, parallel))
    table_at = int.from_bytes(blob[:8], "little")
    sizes = tuple(int(b) for _, b in lazrs.read_chunk_table(io.BytesIO(blob), vlr))
    n = raw.size // vlr.item_size()
    if len(sizes) != -(-n // vlr.chunk_size()) or 8 + sum(sizes) != table_at:
        raise RuntimeError(f"unexpected lazrs chunk table: {len(sizes)} chunks of {sum(sizes)} bytes for {n} "
                           f"points, table at {table_at}")
    return blob[8:table_at], sizes


def decompress_chunks(data: bytes, sizes: tuple[int, ...], vlr) -> bytearray:
    """The raw records of whole chunks made by :func:`compress_chunks`."""
    import lazrs

    out = np.zeros(len(sizes) * vlr.chunk_size() * vlr.item_size(), np.uint8)
    lazrs.decompress_points_with_chunk_table(data, vlr.record_data(), out, [(vlr.chunk_size(), b) for b in sizes])
    return bytearray(out)


def encode_points(cloud, layout: LasLayout, *, compress: bool = True) -> EncodedPoints:
    """Encode ``cloud`` (a :class:`georefine.io.las.PointCloud`) for a file of ``layout``.

    With a compressed layout and ``compress``, the whole chunks are compressed here, on one
    thread (a task's worker has its other slots busy); the rest stays raw records.
    """
    rec = _records(cloud, layout)
    n = len(rec)
    if not n:
        return EncodedPoints(layout, b"", (), b"", 0, np.full(3, np.inf), np.full(3, -np.inf), np.zeros(15, np.uint64))
    extremes = b""
    if layout.extra:
        ext = np.zeros(2, dtype=rec.array.dtype)
        for e in layout.extra:
            values = rec.array[e.name]
            if e.no_data is not None:
                values = values[values != values.dtype.type(e.no_data)]
            if values.size:
                ext[e.name][0], ext[e.name][1] = values.min(axis=0), values.max(axis=0)
            else:  # only no-data values: extremes that widen nothing
                info = np.finfo(values.dtype) if values.dtype.kind == "f" else np.iinfo(values.dtype)
                ext[e.name][0], ext[e.name][1] = info.max, info.min
        extremes = ext.tobytes()
    raw = memoryview(np.frombuffer(rec.array, np.uint8))
    data, sizes, cut = b"", (), 0
    if layout.compress and compress and n >= LAZ_CHUNK_POINTS:
        cut = (n // LAZ_CHUNK_POINTS) * LAZ_CHUNK_POINTS * rec.point_format.size
        data, sizes = compress_chunks(raw[:cut], layout.laz_vlr(), parallel=False)
    ixyz = np.stack([rec.X, rec.Y, rec.Z], axis=1)
    scale, offset = np.asarray(layout.scale), np.asarray(layout.offset)
    returns = np.bincount(np.asarray(rec.return_number, dtype=np.int64), minlength=16)[1:16].astype(np.uint64)
    ids = rec.point_source_id
    return EncodedPoints(layout, data, sizes, bytes(raw[cut:]), n, ixyz.min(axis=0) * scale + offset,
                         ixyz.max(axis=0) * scale + offset, returns, extremes, (int(ids.min()), int(ids.max())))
