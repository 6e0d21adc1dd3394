"""The LAS/LAZ header as the field's readers expect it (georefine.io.las_writer, io/las_encode):
the CRS WKT (identified by GDAL/PROJ at 100 %, ellipsoidal heights stated), the file source ID,
described extra dimensions with no-data values, and the scan angle's encoding."""

from __future__ import annotations

import json
import shutil
import subprocess

import laspy
import numpy as np
import pyproj
import pytest

from georefine.geometry.frames import OutputCRS
from georefine.io.las import SCAN_ANGLE_UNIT_DEG, PointCloud, epsg_of, read_las, read_las_info
from georefine.io.las_encode import ExtraDim, scan_angle_counts
from georefine.io.las_writer import ELLIPSOIDAL_VERT_CS, LasWriter, las_crs_wkt, write_las

# laspy must read what Georefine writes without a single warning.
pytestmark = pytest.mark.filterwarnings("error")

T0 = 1_400_000_000.0
UTM = OutputCRS(25832)  # the 3-D CRS the workflows hand the writer (ellipsoidal heights)


def _cloud(seed: int, n: int = 3000, strips=(4,), extra: dict | None = None) -> PointCloud:
    rng = np.random.default_rng(seed)
    centre = np.array([691_000.0, 5_334_000.0, 550.0])
    return PointCloud(T0 + np.sort(rng.uniform(0, 10, n)), centre + rng.uniform(-400, 400, (n, 3)),
                      rng.integers(0, 65536, n), rng.integers(0, 3, n), rng.choice(strips, n), np.ones(n), np.ones(n),
                      extra or {}, scan_angle_deg=rng.uniform(-60.0, 60.0, n))


def _vlr(path, user_id: str, record_id: int):
    with laspy.open(path) as f:
        found = [v for v in f.header.vlrs if v.user_id == user_id and v.record_id == record_id]
    assert len(found) == 1, f"{user_id} {record_id}: {len(found)} records"
    return found[0]


def _source_id(path) -> int:
    with laspy.open(path) as f:
        return f.header.file_source_id


def _wkt_of(path) -> str:
    return _vlr(path, "LASF_Projection", 2112).string


@pytest.fixture(scope="module")
def utm_laz(tmp_path_factory):
    path = tmp_path_factory.mktemp("las") / "strip_4.laz"
    return write_las(path, _cloud(0), scale=0.001, crs=UTM.crs)


# --- CRS ----------------------------------------------------------------------


def test_wkt_is_wkt1_of_the_horizontal_epsg_crs_identified_at_100_percent(utm_laz):
    wkt = _wkt_of(utm_laz)
    assert wkt.startswith('PROJCS["ETRS89 / UTM zone 32N"') and wkt.endswith('AUTHORITY["EPSG","25832"]]')
    crs = pyproj.CRS.from_wkt(wkt)
    assert crs.to_epsg(min_confidence=100) == 25832
    assert [(m.auth_name, m.code, m.confidence) for m in crs.list_authority()] == [("EPSG", "25832", 100)]
    with laspy.open(utm_laz) as f:
        assert f.header.global_encoding.wkt and f.header.parse_crs().to_epsg(min_confidence=100) == 25832
    # the WKT record is null-terminated (LAS 1.4 R15)
    assert _vlr(utm_laz, "LASF_Projection", 2112).record_data_bytes().endswith(b"\0")


def test_ellipsoidal_heights_are_stated_in_a_text_area_description(utm_laz):
    text = _vlr(utm_laz, "LASF_Spec", 3).record_data
    assert text.endswith(b"\0") and text.isascii()
    text = text.rstrip(b"\0").decode("ascii")
    assert "ellipsoidal heights" in text and "GRS 1980" in text and "ETRS89" in text and "EPSG:25832" in text
    assert text.endswith(ELLIPSOIDAL_VERT_CS)
    # what the text says is true: the WKT record with the VERT_CS in a COMPD_CS is the 3-D CRS of
    # ellipsoidal heights that the points are in
    compound = pyproj.CRS.from_wkt(f'COMPD_CS["3-D",{_wkt_of(utm_laz)},{ELLIPSOIDAL_VERT_CS}]')
    assert len(compound.axis_info) == 3 and "ellipsoidal" in compound.axis_info[2].name.lower()
    assert compound.equals(UTM.crs, ignore_axis_order=False)


def test_las_crs_wkt_of_other_crs_kinds():
    # a 2-D CRS: as it is, nothing said of heights
    wkt, text = las_crs_wkt("EPSG:25832")
    assert text is None and pyproj.CRS.from_wkt(wkt).to_epsg(min_confidence=100) == 25832
    # a compound CRS states its vertical part itself
    wkt, text = las_crs_wkt(5555)
    assert text is None and wkt.startswith("COMPD_CS") and pyproj.CRS.from_wkt(wkt).to_epsg() == 5555
    # a 3-D geographic CRS: its 2-D EPSG CRS and the ellipsoidal heights
    wkt, text = las_crs_wkt(4979)
    assert wkt.startswith('GEOGCS["WGS 84"') and pyproj.CRS.from_wkt(wkt).to_epsg(min_confidence=100) == 4326
    assert "WGS 84 ellipsoid" in text
    # a 3-D projected CRS from another datum
    wkt, text = las_crs_wkt(pyproj.CRS.from_epsg(2056).to_3d())
    assert pyproj.CRS.from_wkt(wkt).to_epsg(min_confidence=100) == 2056 and "Bessel 1841" in text


def test_files_of_the_former_writer_still_read(tmp_path):
    """Strips written before, with the 3-D CRS as WKT2:2019 through laspy's add_crs."""
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    header.add_crs(UTM.crs)
    header.offsets, header.scales = np.array([691_000.0, 5_334_000.0, 0.0]), np.full(3, 0.001)
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.array([691_000.5]), np.array([5_334_000.5]), np.array([550.0])
    las.gps_time = np.array([T0 - 1e9])
    path = tmp_path / "old.laz"
    las.write(path)
    assert "Promoted to 3D" in _wkt_of(path)
    assert pyproj.CRS.from_wkt(read_las_info(path).crs_wkt).to_2d().to_epsg() == 25832
    assert epsg_of(path) == 25832 and len(read_las(path)) == 1
    assert epsg_of(write_las(tmp_path / "new.laz", _cloud(1, n=10), crs=UTM.crs)) == 25832


@pytest.mark.skipif(shutil.which("gdalsrsinfo") is None, reason="GDAL's gdalsrsinfo not installed")
def test_gdal_identifies_epsg_25832_at_100_percent(utm_laz, tmp_path):
    # GDAL has no LAS driver of its own (PDAL's plug-in reads LAS): the WKT record goes to a file.
    wkt_file = tmp_path / "crs.wkt"
    wkt_file.write_text(_wkt_of(utm_laz))
    out = subprocess.run(["gdalsrsinfo", "-e", str(wkt_file)], capture_output=True, text=True, check=True).stdout
    # gdalsrsinfo names the match and adds "Confidence in this match: N %" only below 100 %
    assert "EPSG:25832" in out.split() and "Confidence" not in out, out


@pytest.mark.skipif(shutil.which("projinfo") is None, reason="PROJ's projinfo not installed")
def test_proj_identifies_epsg_25832_at_100_percent_and_exports_wkt1(utm_laz):
    wkt = _wkt_of(utm_laz)
    out = subprocess.run(["projinfo", "--identify", "-q", "-o", "PROJJSON", wkt], capture_output=True, text=True,
                         check=True).stdout
    assert "EPSG:25832: 100 %" in out.splitlines(), out
    res = subprocess.run(["projinfo", "-q", "-o", "WKT1_GDAL", wkt], capture_output=True, text=True)
    assert res.returncode == 0 and res.stdout.startswith('PROJCS["ETRS89 / UTM zone 32N"'), res.stdout + res.stderr
    # the statement of the heights, read by PROJ: a 3-D CRS with an ellipsoidal height axis
    compound = f'COMPD_CS["3-D",{wkt},{ELLIPSOIDAL_VERT_CS}]'
    res = subprocess.run(["projinfo", "-q", "-o", "PROJJSON", compound], capture_output=True, text=True, check=True)
    described = json.loads(res.stdout)
    assert described["type"] == "ProjectedCRS"
    assert [(a["name"], a["direction"]) for a in described["coordinate_system"]["axis"]] == [
        ("Easting", "east"), ("Northing", "north"), ("Ellipsoidal height", "up")]


# --- file source ID -----------------------------------------------------------


def test_file_source_id_is_the_strip_id_of_a_single_strip_file(tmp_path):
    assert _source_id(write_las(tmp_path / "one.laz", _cloud(2, strips=(7,)))) == 7
    assert _source_id(write_las(tmp_path / "two.laz", _cloud(2, strips=(7, 8)))) == 0
    # chunks of different strips: 0 as well, whichever comes first
    with LasWriter(tmp_path / "chunks.las") as w:
        w.write(_cloud(3, n=100, strips=(2,)))
        w.write(_cloud(4, n=100, strips=(3,)))
    assert w.file_source_id == 0 and _source_id(w.path) == 0
    with LasWriter(tmp_path / "empty.las") as w:
        pass
    assert _source_id(w.path) == 0
    given = write_las(tmp_path / "given.las", _cloud(5, strips=(7, 8)), file_source_id=12)
    assert _source_id(given) == 12
    with pytest.raises(ValueError, match="file_source_id"):
        LasWriter(tmp_path / "bad.las", file_source_id=70_000)


# --- extra dimensions ---------------------------------------------------------


def test_extra_dimensions_have_description_and_no_data_that_laspy_reads_back(tmp_path):
    n = 2000
    rng = np.random.default_rng(6)
    counts = rng.integers(-1, 4, n)
    err = rng.normal(0, 0.01, n)
    err[:5] = -9999.0  # no data
    dims = [ExtraDim("lidargrams", "i2", "lidargrams that showed the point", no_data=-1),
            ExtraDim("range_error_m", "f4", "range noise (m)", no_data=-9999.0),
            ExtraDim("empty", "f4", "never a value", no_data=-9999.0)]
    cloud = _cloud(6, n=n, extra={"lidargrams": counts, "range_error_m": err, "empty": np.full(n, -9999.0)})
    path = write_las(tmp_path / "x.laz", cloud, extra_dims=dims)
    las = laspy.read(path)
    structs = {s.format_name(): s for s in las.header.vlrs.get("ExtraBytesVlr")[0].extra_bytes_structs}
    assert list(structs) == ["lidargrams", "range_error_m", "empty"]
    for d in dims:
        s = structs[d.name]
        assert s.description.decode() == d.description and s.options & s.NO_DATA_BIT_MASK
        assert s.no_data.tolist() == [d.no_data] and s.dtype() == np.dtype(d.dtype)
    # the stated range leaves the no-data values out (LAS 1.4 R15, "Extra Bytes")
    assert structs["lidargrams"].min.tolist() == [counts[counts >= 0].min()]
    assert structs["lidargrams"].max.tolist() == [counts.max()]
    valid = err[5:].astype(np.float32)
    assert structs["range_error_m"].min.tolist() == [valid.min()] and structs["range_error_m"].max.tolist() == [valid.max()]
    # only no-data values: no range claimed (options bits off, fields zero)
    assert structs["empty"].min is None and structs["empty"].max is None and not any(bytes(structs["empty"]._min))
    np.testing.assert_array_equal(las.lidargrams, counts)
    back = read_las(path)
    np.testing.assert_array_equal(back.extra["lidargrams"], counts)
    assert back.extra["range_error_m"][0] == -9999.0


@pytest.mark.parametrize("bad", [dict(name="x" * 33), dict(name="x", description="é"), dict(name="x", no_data=np.nan),
                                 dict(name="x", dtype="i2", no_data=0.5), dict(name="x", dtype="U4")])
def test_extra_dim_refuses_what_las_cannot_hold(bad):
    with pytest.raises(ValueError):
        ExtraDim(**bad)


# --- scan angle ---------------------------------------------------------------


def test_scan_angle_is_written_in_steps_of_0_006_degrees(tmp_path):
    angles = np.array([0.0, 0.003, 0.0091, -0.0091, 45.0, -45.0, 179.999, 180.0, -180.0, 200.0])
    np.testing.assert_array_equal(scan_angle_counts(angles),
                                  [0, 0, 2, -2, 7500, -7500, 30000, -30000, -30000, -26667])
    cloud = _cloud(8, n=len(angles))
    cloud = PointCloud(cloud.time_gps, cloud.xyz, cloud.intensity, cloud.scanner_channel, cloud.point_source_id,
                       cloud.return_number, cloud.number_of_returns, scan_angle_deg=angles)
    path = write_las(tmp_path / "a.laz", cloud)
    np.testing.assert_array_equal(laspy.read(path).scan_angle, scan_angle_counts(angles))
    np.testing.assert_allclose(read_las(path).scan_angle_deg, scan_angle_counts(angles) * SCAN_ANGLE_UNIT_DEG)


def test_laszip_reads_the_header_and_the_points(tmp_path):
    """LASzip's own reader (the library LAStools builds on), where its Python binding is installed."""
    laszip = pytest.importorskip("laszip")
    cloud = _cloud(9, n=60_000, strips=(5,), extra={"range_error_m": np.zeros(60_000)})
    path = write_las(tmp_path / "s.laz", cloud, scale=0.001, crs=UTM.crs,
                     extra_dims=[ExtraDim("range_error_m", "f4", "range noise (m)", no_data=-9999.0)])
    with open(path, "rb") as f:
        reader = laszip.LasUnZipper(f)
        h = reader.header
        assert (h.version_major, h.version_minor, h.point_data_format) == (1, 4, 6)
        assert h.file_source_ID == 5 and h.global_encoding == 0b10001  # GPS standard time, WKT
        assert h.extended_number_of_point_records == len(cloud)
        assert h.number_of_variable_length_records == 3  # extra bytes, WKT, text area (LASzip's own not counted)
        raw = np.zeros(len(cloud) * h.point_data_record_length, np.uint8)
        reader.decompress_into(raw)
        reader.close()
    with laspy.open(path) as f:
        records = raw.view(f.header.point_format.dtype())
    np.testing.assert_array_equal(records["scan_angle"], scan_angle_counts(cloud.scan_angle_deg))
    np.testing.assert_array_equal(records["point_source_id"], 5)
