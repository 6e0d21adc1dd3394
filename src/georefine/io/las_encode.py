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
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

from georefine.io.las import GPS_TIME_OFFSET_S

__all__ = ["LAZ_CHUNK_POINTS", "EncodedPoints", "LasLayout", "compress_chunks",
           "decompress_chunks", "encode_points"]

LAZ_CHUNK_POINTS = 50_000
"""Points per LAZ chunk (LASzip's default); a tile's last chunk holds the rest."""



@dataclass(frozen=True)
class LasLayout:
    """What fixes a file's point records: scale and offset (m or CRS units), extra dimensions, compression."""

    scale: tuple[float, float, float]
    offset: tuple[float, float, float]
    extra: tuple[tuple[str, str], ...] = ()
    compress: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "scale", tuple(float(v) for v in np.broadcast_to(self.scale, (3,))))
        object.__setattr__(self, "offset", tuple(float(v) for v in np.broadcast_to(self.offset, (3,))))
        object.__setattr__(self, "extra", tuple((str(k), np.dtype(t).str) for k, t in self.extra))
        if not all(s > 0 for s in self.scale):
            raise ValueError(f"scale must be > 0, found {self.scale}")

    def point_header(self):
        """A bare LAS 1.4 point-format-6 ``laspy.LasHeader`` with this layout (no CRS, no counts)."""
        import laspy

        header = laspy.LasHeader(version="1.4", point_format=6)
        if self.extra:
            header.add_extra_dims([laspy.ExtraBytesParams(name=k, type=np.dtype(t)) for k, t in self.extra])
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
    smallest and the largest value of every extra dimension (for the extra-bytes VLR).
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

    def __len__(self) -> int:
        return self.count


def _records(cloud, layout: LasLayout):
    """The point records of ``cloud`` (a ``laspy.ScaleAwarePointRecord``) in ``layout``."""
    import laspy

    missing = [k for k, _ in layout.extra if k not in cloud.extra]
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
    for k, _ in layout.extra:
        rec[k] = cloud.extra[k]
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
        for k, _ in layout.extra:
            values = rec.array[k]
            ext[k][0], ext[k][1] = values.min(axis=0), values.max(axis=0)
        extremes = ext.tobytes()
    raw = memoryview(np.frombuffer(rec.array, np.uint8))
    data, sizes, cut = b"", (), 0
    if layout.compress and compress and n >= LAZ_CHUNK_POINTS:
        cut = (n // LAZ_CHUNK_POINTS) * LAZ_CHUNK_POINTS * rec.point_format.size
        data, sizes = compress_chunks(raw[:cut], layout.laz_vlr(), parallel=False)
    ixyz = np.stack([rec.X, rec.Y, rec.Z], axis=1)
    scale, offset = np.asarray(layout.scale), np.asarray(layout.offset)
    returns = np.bincount(np.asarray(rec.return_number, dtype=np.int64), minlength=16)[1:16].astype(np.uint64)
    return EncodedPoints(layout, data, sizes, bytes(raw[cut:]), n, ixyz.min(axis=0) * scale + offset,
                         ixyz.max(axis=0) * scale + offset, returns, extremes)
