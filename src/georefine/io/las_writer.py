"""Writing LAS 1.4 / LAZ files chunk by chunk, atomically (docs/ARCHITECTURE.md §3, §4.7).

:class:`LasWriter` takes point chunks (:class:`~georefine.io.las.PointCloud`) or points encoded
elsewhere (:mod:`georefine.io.las_encode`), writes them under a temporary name and renames the
file when it is complete; :func:`write_las` writes one cloud in one go. Conventions as
:mod:`georefine.io.las`. The header as LAS readers expect it:

* **CRS** (:func:`las_crs_wkt`). LAS 1.4 asks for OGC WKT (OGC 01-009, "WKT1", as GDAL, PDAL
  and LAStools read it) in the ``LASF_Projection`` 2112 VLR, with the global-encoding WKT bit
  set. Georefine's coordinates are a projected CRS with *ellipsoidal* heights, a 3-D CRS that
  has no EPSG code (EPSG gives codes to 2-D projected CRSs and to compounds with
  gravity-related heights only). WKT1 cannot state it in a way that keeps the EPSG code: tried
  with GDAL 3.6 / PROJ 9.1 (``gdalsrsinfo -e``, ``projinfo --identify``) and PROJ 9.5
  (pyproj), for EPSG:25832,

  - the 3-D CRS in WKT2:2019 (the former writer): identified as EPSG:25832 at 50 %, and
    ``projinfo -o WKT1_GDAL`` refuses it;
  - ``COMPD_CS[PROJCS[... AUTHORITY["EPSG","25832"]], VERT_CS["ellipsoidal height",
    VERT_DATUM["Ellipsoid",2002], ...]]`` (what GDAL writes for LAS with the option
    ``ALLOW_ELLIPSOIDAL_HEIGHT_AS_VERTICAL_CRS``): PROJ turns it back into the 3-D CRS,
    50 % again;
  - a ``VERT_CS`` of another datum type (2000, 2005): kept as a compound, and identified only
    as compounds with gravity-related heights (EPSG:5555 "+ DHHN92 height", ...) at 25 %.

  So the WKT is the horizontal CRS alone in WKT1 (``PROJCS[... AUTHORITY["EPSG","25832"]]``),
  identified at 100 % by GDAL, PROJ and pyproj (``CRS.to_epsg()``), and the heights are stated
  where LAS 1.4 puts free text, a Text Area Description VLR (``LASF_Spec`` 3): they are
  ellipsoidal heights above the CRS's ellipsoid, with the ``VERT_CS`` above that, appended to
  the ``PROJCS`` in a ``COMPD_CS``, gives the 3-D CRS. A 2-D CRS or a compound one (which
  states its vertical part) is written as WKT1 as it is.
* **File source ID** = the strip id (``point_source_id``) when every point of the file has the
  same one, else 0 (LAS 1.4: 0 = no id assigned); ``file_source_id=`` sets it.
* **Extra dimensions** (:class:`~georefine.io.las_encode.ExtraDim`) with description and no-data
  value; their minimum and maximum leave the no-data values out.
* ``scan_angle`` from :attr:`~georefine.io.las.PointCloud.scan_angle_deg`.
"""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from georefine.io.files import PathLike, check_output_path
from georefine.io.las import PointCloud
from georefine.io.las_encode import (
    LAZ_CHUNK_POINTS,
    EncodedPoints,
    ExtraDim,
    LasLayout,
    compress_chunks,
    decompress_chunks,
    encode_points,
)

__all__ = ["LasWriter", "ELLIPSOIDAL_VERT_CS", "las_crs_wkt", "offset_near", "write_las"]

_log = logging.getLogger(__name__)

ELLIPSOIDAL_VERT_CS = ('VERT_CS["ellipsoidal height",VERT_DATUM["Ellipsoid",2002],'
                       'UNIT["metre",1,AUTHORITY["EPSG","9001"]],AXIS["Ellipsoidal height",UP]]')
"""OGC 01-009 vertical CRS of ellipsoidal heights (datum type 2002), as GDAL writes it for LAS."""


def las_crs_wkt(crs) -> tuple[str, str | None]:
    """The OGC WKT of ``crs`` for a LAS 1.4 file, and what to say of its heights (module docstring).

    ``crs``: a ``pyproj.CRS`` or anything ``pyproj.CRS.from_user_input`` takes. A 3-D projected
    or geographic CRS (ellipsoidal heights) gives the WKT1 of its horizontal CRS -- the EPSG
    definition when PROJ identifies it at 100 % -- and a sentence stating the ellipsoidal heights
    (ASCII, for a Text Area Description VLR); any other CRS its WKT1 and ``None``. A CRS that WKT1
    cannot express is written as WKT2:2019 (with a warning in the log).
    """
    import pyproj
    from pyproj.exceptions import CRSError

    crs = pyproj.CRS.from_user_input(crs)
    heights = None
    if not crs.is_compound and len(crs.axis_info) == 3 and (crs.is_projected or crs.is_geographic):
        horizontal = crs.to_2d()
        code = horizontal.to_epsg(min_confidence=100)
        if code is not None:
            horizontal = pyproj.CRS.from_epsg(code)
        datum = crs.geodetic_crs.name if crs.geodetic_crs is not None else crs.name
        ellipsoid = crs.ellipsoid.name if crs.ellipsoid is not None else "the datum's"
        text = (f"Heights (z) are ellipsoidal heights in metres above the {ellipsoid} ellipsoid of {datum}, not "
                f"gravity-related heights. The CRS record holds the horizontal CRS "
                f"({horizontal.name}{f', EPSG:{code}' if code else ''}); with this vertical CRS appended in a "
                f"COMPD_CS it gives the 3-D CRS: {ELLIPSOIDAL_VERT_CS}")
        heights = text.encode("ascii", "replace").decode("ascii")
        crs = horizontal
    try:
        return crs.to_wkt("WKT1_GDAL"), heights
    except CRSError:
        _log.warning("%s cannot be written as WKT1; the LAS file gets WKT2:2019, which not every reader takes",
                     crs.name)
        return crs.to_wkt("WKT2_2019"), heights


def offset_near(centre) -> np.ndarray:
    """The record offset of a file whose points lie about ``centre`` (CRS units): the centre
    rounded to a multiple of 1000, so that the offset reads as a round coordinate."""
    return np.round(np.asarray(centre, dtype=np.float64) / 1000.0) * 1000.0


class LasWriter:
    """Chunked LAS 1.4 / LAZ writer (point format 6) with an atomic rename on close.

    Parameters
    ----------
    path
        Destination; ``.laz`` is compressed (lazrs) unless ``compress`` says otherwise.
    scale
        Coordinate resolution in metres (scalar or (3,)); default 0.0001 m.
    offset
        Header offsets (3,); default from the first chunk: its centre rounded to
        a multiple of 1000 m (0 for scanner-frame data near the origin).
    crs
        Optional coordinate reference system (``pyproj.CRS``, WKT, EPSG code or
        "EPSG:xxxx"); written as a WKT VLR (:func:`las_crs_wkt`).
    extra_dims
        Extra dimensions to write: :class:`~georefine.io.las_encode.ExtraDim` (type,
        description, no-data value), names (float32) or ``{name: dtype}``.
    file_source_id
        The header's file source ID; default the ``point_source_id`` of the points when they all
        have the same one, else 0.
    system_identifier, generating_software
        Header texts; both default to Georefine.
    protect
        Input files/folders that must not be written into.

    Notes
    -----
    Use as a context manager: on an exception the temporary file is removed and
    ``path`` is left untouched. Points are encoded by :mod:`georefine.io.las_encode` (laspy's
    records; LAZ chunks of at most ``LAZ_CHUNK_POINTS`` points, compressed by lazrs), here or in
    the task that made them (:meth:`write_encoded`); this object appends them, and on close writes
    the LAZ chunk table and the header's counts and bounds.
    """

    def __init__(
        self,
        path: PathLike,
        *,
        scale: float | Sequence[float] = 1e-4,
        offset: Sequence[float] | None = None,
        crs=None,
        extra_dims: Sequence[str | ExtraDim] | Mapping[str, type] = (),
        compress: bool | None = None,
        file_source_id: int | None = None,
        system_identifier: str = "Georefine",
        generating_software: str | None = None,
        protect: Sequence[PathLike] = (),
    ) -> None:
        self.path = check_output_path(path, protect)
        self._compress = self.path.suffix.lower() == ".laz" if compress is None else bool(compress)
        self._scale = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,)).copy()
        self._offset = None if offset is None else np.asarray(offset, dtype=np.float64).reshape(3)
        self._crs = crs
        specs = extra_dims.items() if isinstance(extra_dims, Mapping) else extra_dims
        self._extra = tuple(ExtraDim.of(e) for e in specs)
        if file_source_id is not None and not 0 <= int(file_source_id) <= 65535:
            raise ValueError(f"file_source_id must be in 0..65535, found {file_source_id}")
        self._file_source_id = None if file_source_id is None else int(file_source_id)
        self._source_ids = (65535, 0)  # smallest and largest point_source_id written
        self._system_identifier = system_identifier
        if generating_software is None:
            from georefine import __version__

            generating_software = f"Georefine {__version__}"
        self._software = generating_software
        self._layout: LasLayout | None = None
        self._header = None
        self._vlr = None
        self._chunks: list[int] = []  # bytes of every LAZ chunk so far
        self._carry = bytearray()  # raw records after the last whole chunk
        self.recompressed_points = 0  # points of chunks made elsewhere but compressed again here
        self._points_at = 0
        self._fh = None
        self._tmp: Path | None = None
        self._closed = False
        self._aborted = False
        self.point_count = 0

    def __enter__(self) -> LasWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        elif not self._closed:
            self.abort()

    def layout_for(self, first: PointCloud | None = None) -> LasLayout:
        """The file's record layout; without an ``offset`` given, the first chunk fixes it (its
        centre rounded to a multiple of 1000 m), so it is known once ``first`` is."""
        if self._layout is None:
            if self._offset is None:
                if first is None:
                    raise ValueError("the offset is fixed by the first chunk: pass offset= to encode points elsewhere")
                centre = 0.5 * (first.xyz.min(axis=0) + first.xyz.max(axis=0)) if len(first) else np.zeros(3)
                self._offset = offset_near(centre)
            self._layout = LasLayout(tuple(self._scale), tuple(self._offset), self._extra, self._compress)
        return self._layout

    def _open(self) -> None:
        """Write the header and VLRs (counts and bounds follow on close) to the temporary file."""
        import laspy
        from laspy.header import GpsTimeType
        from laspy.vlrs.known import LasZipVlr, WktCoordinateSystemVlr

        layout = self.layout_for()
        header = layout.point_header()
        header.global_encoding.gps_time_type = GpsTimeType.STANDARD
        if self._crs is not None:
            wkt, heights = las_crs_wkt(self._crs)
            header.vlrs.append(WktCoordinateSystemVlr(wkt))
            if heights is not None:
                header.vlrs.append(laspy.VLR("LASF_Spec", 3, "Text Area Description",
                                             heights.encode("ascii") + b"\0"))
            header.global_encoding.wkt = True
        header.system_identifier = self._system_identifier[:32]
        header.generating_software = self._software[:32]
        if self._compress:
            self._vlr = layout.laz_vlr()
            header.vlrs.append(LasZipVlr(self._vlr.record_data()))
            header.are_points_compressed = True
        header.partial_reset()
        fd, name = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".part", dir=self.path.parent)
        os.close(fd)
        self._tmp = Path(name)
        self._fh = open(self._tmp, "wb")
        header.write_to(self._fh)
        self._points_at = self._fh.tell()
        if self._compress:
            self._fh.write(bytes(8))  # the offset to the chunk table, set on close
        self._header = header

    def write(self, chunk: PointCloud) -> None:
        """Append a chunk of points (its extra dimensions must include the writer's)."""
        if self._closed:
            raise ValueError("LasWriter is closed")
        # Raw records: the whole chunks are compressed below on all cores.
        self.write_encoded(encode_points(chunk, self.layout_for(chunk), compress=False))

    def write_encoded(self, points: EncodedPoints) -> None:
        """Append points encoded elsewhere (:func:`georefine.io.las_encode.encode_points` with
        :meth:`layout_for`), e.g. by the task that computed them. Their LAZ chunks are used as
        they are when they start at a chunk boundary of the file, else compressed again."""
        if self._closed:
            raise ValueError("LasWriter is closed")
        if points.layout != self.layout_for():
            raise ValueError(f"points encoded for {points.layout}, this file is {self.layout_for()}")
        if self._fh is None:
            self._open()
        h = self._header
        if h.point_count + points.count > h.max_point_count():
            raise ValueError(f"{h.point_count + points.count} points exceed what a LAS {h.version} file holds")
        if not self._compress:
            self._fh.write(points.chunk_data)  # empty: a LAS layout is never compressed
            self._fh.write(points.records)
        else:
            if points.chunk_bytes and not self._carry:
                self._fh.write(points.chunk_data)
                self._chunks.extend(points.chunk_bytes)
            elif points.chunk_bytes:
                self.recompressed_points += len(points.chunk_bytes) * LAZ_CHUNK_POINTS
                self._carry += decompress_chunks(points.chunk_data, points.chunk_bytes, self._vlr)
            self._carry += points.records
            self._flush(final=False)
        if points.count:
            h.mins = np.minimum(h.mins, points.mins)
            h.maxs = np.maximum(h.maxs, points.maxs)
            h.number_of_points_by_return = h.number_of_points_by_return + points.returns
            h.point_count += points.count
            if points.extremes:
                _grow_extra_ranges(h, points.extremes)
            self._source_ids = (min(self._source_ids[0], points.source_ids[0]),
                                max(self._source_ids[1], points.source_ids[1]))
        self.point_count += points.count

    def _flush(self, final: bool) -> None:
        """Compress the whole chunks of the raw records held back (all of them if ``final``)."""
        per_chunk = LAZ_CHUNK_POINTS * self._vlr.item_size()
        cut = len(self._carry) if final else (len(self._carry) // per_chunk) * per_chunk
        if cut:
            data, sizes = compress_chunks(memoryview(self._carry)[:cut], self._vlr, parallel=True)
            self._fh.write(data)
            self._chunks.extend(sizes)
            del self._carry[:cut]

    def close(self) -> Path:
        """Finish the file and rename it to ``path``. Returns ``path``."""
        if self._aborted:
            raise ValueError("LasWriter was aborted; nothing was written")
        if self._closed:
            return self.path
        try:
            if self._fh is None:  # nothing written: still a valid, empty file
                self.layout_for(PointCloud.empty())
                self._open()
            fh, h = self._fh, self._header
            if self._compress:
                import lazrs

                self._flush(final=True)
                table_at = fh.tell()
                counts = [LAZ_CHUNK_POINTS] * len(self._chunks)
                if self._chunks:
                    counts[-1] = h.point_count - LAZ_CHUNK_POINTS * (len(self._chunks) - 1)
                lazrs.write_chunk_table(fh, list(zip(counts, self._chunks)), self._vlr)
                fh.seek(self._points_at)
                fh.write(table_at.to_bytes(8, "little", signed=True))
            if h.point_count == 0:
                h.mins, h.maxs = np.zeros(3), np.zeros(3)
            h.file_source_id = self.file_source_id
            _close_extra_ranges(h)
            fh.seek(0)
            h.write_to(fh, ensure_same_size=True)
            fh.flush()
            os.fsync(fh.fileno())
            fh.close()
            os.chmod(self._tmp, 0o644)  # mkstemp made it private
            os.replace(self._tmp, self.path)
        except BaseException:
            self.abort()
            raise
        self._closed = True
        _log.info("wrote %d points to %s", self.point_count, self.path)
        return self.path

    @property
    def file_source_id(self) -> int:
        """The header's file source ID: as given, else the one strip id of the points so far, or 0."""
        if self._file_source_id is not None:
            return self._file_source_id
        lo, hi = self._source_ids
        return lo if lo == hi else 0

    def abort(self) -> None:
        """Discard the temporary file; ``path`` is left untouched."""
        try:
            if self._fh is not None:
                self._fh.close()
        except Exception:  # already failing; the temp file is removed below
            pass
        if self._tmp is not None and self._tmp.exists():
            self._tmp.unlink()
        self._fh = None
        self._closed = self._aborted = True


# Where the LAS 1.4 (R15) extra-bytes descriptor, 192 bytes, keeps its "min" and "max": three
# 8-byte values each, after reserved (2), data_type (1), options (1), name (32), unused (4) and
# no_data (24). laspy's ExtraBytesStruct is this record as a ctypes structure.
_EXTRA_BYTES_MIN_AT, _EXTRA_BYTES_MAX_AT = 64, 88
_ANYTYPE = {"u": np.dtype("<u8"), "i": np.dtype("<i8"), "f": np.dtype("<f8")}
"""The 8-byte type LAS 1.4 stores an extra dimension's no-data, min and max in, by the kind of
the dimension's own type (unsigned, signed, floating point)."""


def _stored_range(struct) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Writable views of the minimum and the maximum an extra-bytes descriptor states, as
    stored (before scale and offset), one value per element; ``None`` where its options bit
    is off, and for undocumented bytes (``data_type`` 0, no range).

    laspy reads them (``min``/``max``, scaled) but sets them only in ``grow``: they are viewed
    here in the descriptor's bytes, which a ctypes structure hands out writable (buffer protocol).
    """
    if struct.data_type == 0:
        return None, None
    record = np.frombuffer(struct, dtype=np.uint8)
    anytype, n = _ANYTYPE[struct.dtype().base.kind], struct.num_elements()

    def values(at: int) -> np.ndarray:
        return record[at: at + 24].view(anytype)[:n]

    return (values(_EXTRA_BYTES_MIN_AT) if struct.min_is_relevant() else None,
            values(_EXTRA_BYTES_MAX_AT) if struct.max_is_relevant() else None)


def _grow_extra_ranges(header, extremes: bytes) -> None:
    """Widen the minimum and maximum of each extra dimension in the extra-bytes VLR.

    ``extremes``: two raw records, the smallest and the largest stored values
    (:class:`~georefine.io.las_encode.EncodedPoints`). laspy's own update reads only the first
    point of every batch of a one-element dimension (``pts[..., i]``), so the file would claim a
    narrower range than its points have; the struct's stored values are set here instead
    (:func:`_stored_range`: views of the struct's bytes).
    """
    ext = np.frombuffer(extremes, dtype=header.point_format.dtype())
    for struct in header.vlrs.get("ExtraBytesVlr")[0].extra_bytes_structs:
        name = struct.format_name()
        if name not in ext.dtype.names:
            continue
        lo, hi = np.atleast_1d(ext[name][0]), np.atleast_1d(ext[name][1])
        raw_min, raw_max = _stored_range(struct)
        if raw_min is not None:
            raw_min[:] = np.minimum(raw_min, lo)
        if raw_max is not None:
            raw_max[:] = np.maximum(raw_max, hi)


def _close_extra_ranges(header) -> None:
    """Clear the minimum and maximum of extra dimensions that got no value (no points, or only
    no-data values): LAS 1.4 wants the options bits off and the fields zero then."""
    vlrs = header.vlrs.get("ExtraBytesVlr")
    for struct in vlrs[0].extra_bytes_structs if vlrs else ():
        raw_min, raw_max = _stored_range(struct)
        if raw_min is not None and raw_max is not None and np.any(raw_min > raw_max):
            raw_min[:] = 0
            raw_max[:] = 0
            struct.options &= ~(struct.MIN_BIT_MASK | struct.MAX_BIT_MASK)


def write_las(path: PathLike, cloud: PointCloud, **kwargs) -> Path:
    """Write one cloud in one go (keyword arguments as :class:`LasWriter`)."""
    with LasWriter(path, extra_dims=kwargs.pop("extra_dims", tuple(cloud.extra)), **kwargs) as writer:
        writer.write(cloud)
    return Path(path)

