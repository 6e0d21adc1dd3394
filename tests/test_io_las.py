"""Tests of georefine.io.las (LAS 1.4 / LAZ strips and clouds)."""

from __future__ import annotations

import laspy
import numpy as np
import pyproj
import pytest

from georefine.errors import InputError
from georefine.io.las import (
    GPS_TIME_OFFSET_S,
    PointCloud,
    iter_las_chunks,
    read_las,
    read_las_info,
)
from georefine.io.las_writer import LasWriter, write_las

T0 = 1_400_000_000.0


def _cloud(seed: int, n: int = 5000, t0: float = T0, centre=(0.0, 0.0, 0.0), extent=300.0) -> PointCloud:
    rng = np.random.default_rng(seed)
    return PointCloud(
        time_gps=t0 + np.sort(rng.uniform(0, 10, n)),
        xyz=np.asarray(centre) + rng.uniform(-extent, extent, (n, 3)),
        intensity=rng.integers(0, 65536, n),
        scanner_channel=rng.integers(0, 3, n),
        point_source_id=np.full(n, 7),
        return_number=np.ones(n, int),
        number_of_returns=rng.integers(1, 4, n),
        extra={"range_error_m": rng.normal(scale=0.01, size=n)},
        scan_angle_deg=rng.uniform(-75.0, 75.0, n),
    )


def _assert_same_points(a: PointCloud, b: PointCloud, xyz_atol: float) -> None:
    assert len(a) == len(b)
    np.testing.assert_allclose(a.xyz, b.xyz, rtol=0, atol=xyz_atol)
    # LAS stores adjusted time (t - 1e9) exactly; the 1e9 shift costs < 0.25 us of float64 resolution
    np.testing.assert_allclose(a.time_gps, b.time_gps, rtol=0, atol=5e-7)
    for name in ("intensity", "scanner_channel", "point_source_id", "return_number", "number_of_returns"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert set(a.extra) == set(b.extra)
    for k in a.extra:
        np.testing.assert_allclose(a.extra[k], b.extra[k], rtol=1e-7, atol=1e-9)  # float32 storage
    np.testing.assert_allclose(a.scan_angle_deg, b.scan_angle_deg, rtol=0, atol=0.003 + 1e-9)  # half a 0.006 deg step


@pytest.mark.parametrize("suffix", [".las", ".laz"])
@pytest.mark.parametrize("seed", [0, 1])
def test_round_trip(tmp_path, suffix, seed):
    cloud = _cloud(seed)
    path = write_las(tmp_path / f"strip{suffix}", cloud)
    back = read_las(path)
    _assert_same_points(cloud, back, xyz_atol=0.5e-4 + 1e-9)  # half of the 0.1 mm scale
    info = read_las_info(path)
    assert info.point_count == len(cloud) and info.point_format == 6 and info.version == "1.4"
    assert info.compressed is (suffix == ".laz")
    assert info.extra_dims == ("range_error_m",)
    np.testing.assert_allclose(info.mins, cloud.xyz.min(axis=0), atol=1e-4)
    np.testing.assert_allclose(info.maxs, cloud.xyz.max(axis=0), atol=1e-4)
    with laspy.open(path) as reader:
        h = reader.header
        assert h.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD
        assert h.system_identifier == "Georefine" and h.generating_software.startswith("Georefine")
        np.testing.assert_allclose(reader.read().gps_time[:3], cloud.time_gps[:3] - GPS_TIME_OFFSET_S, atol=1e-9)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_chunked_write_equals_one_shot(tmp_path, suffix):
    cloud = _cloud(3, n=10_000)
    one = write_las(tmp_path / f"one{suffix}", cloud)
    with LasWriter(tmp_path / f"chunked{suffix}", extra_dims=["range_error_m"]) as writer:
        for lo in range(0, len(cloud), 3000):
            sl = slice(lo, lo + 3000)
            writer.write(PointCloud(cloud.time_gps[sl], cloud.xyz[sl], cloud.intensity[sl], cloud.scanner_channel[sl],
                                    cloud.point_source_id[sl], cloud.return_number[sl], cloud.number_of_returns[sl],
                                    {"range_error_m": cloud.extra["range_error_m"][sl]}, cloud.scan_angle_deg[sl]))
    a, b = read_las(one), read_las(writer.path)
    _assert_same_points(a, b, xyz_atol=0.0)
    chunks = list(iter_las_chunks(writer.path, chunk_size=2500))
    assert [len(c) for c in chunks] == [2500] * 4
    _assert_same_points(PointCloud.concatenate(chunks), a, xyz_atol=0.0)


def test_crs_offsets_and_quantisation_in_utm(tmp_path):
    cloud = _cloud(4, n=2000, centre=(691_234.0, 5_334_567.0, 600.0), extent=2000.0)
    path = write_las(tmp_path / "utm.laz", cloud, scale=0.001, crs="EPSG:25832")
    info = read_las_info(path)
    assert pyproj.CRS.from_wkt(info.crs_wkt).to_epsg() == 25832
    midrange = 0.5 * (cloud.xyz.min(axis=0) + cloud.xyz.max(axis=0))
    np.testing.assert_array_equal(info.offsets % 1000.0, 0.0)  # offsets from the first chunk, 1 km steps
    assert np.all(np.abs(info.offsets - midrange) <= 500.0)
    err = np.abs(read_las(path).xyz - cloud.xyz)
    assert err.max() <= 0.0005 + 1e-9


def test_writer_abort_leaves_nothing(tmp_path):
    path = tmp_path / "x.laz"
    with pytest.raises(RuntimeError):
        with LasWriter(path) as writer:
            writer.write(_cloud(0, n=100))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_writer_refuses_protected_input(tmp_path):
    src = write_las(tmp_path / "in.laz", _cloud(0, n=10))
    with pytest.raises(InputError, match="refusing to write into an input"):
        LasWriter(src, protect=[src])


def test_empty_file_round_trip(tmp_path):
    with LasWriter(tmp_path / "empty.las", extra_dims=["range_error_m"]) as _:
        pass
    back = read_las(tmp_path / "empty.las")
    assert len(back) == 0 and set(back.extra) == {"range_error_m"}


# --- errors -----------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".laz", ".las"])
def test_truncated_file_gives_input_error(tmp_path, suffix):
    path = write_las(tmp_path / f"cut{suffix}", _cloud(5, n=50_000))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError) as info:
        for _ in iter_las_chunks(path, chunk_size=10_000):
            pass
    msg = str(info.value)
    assert f"cut{suffix}" in msg and ("truncated" in msg or "corrupt" in msg)
    assert "50000 points" in msg


def test_garbage_file_gives_input_error(tmp_path):
    path = tmp_path / "garbage.laz"
    path.write_bytes(np.random.default_rng(0).integers(0, 256, 4000, dtype=np.uint8).tobytes())
    with pytest.raises(InputError, match=r"garbage\.laz: cannot open as LAS/LAZ"):
        read_las(path)


def _laspy_file(path, version, point_format, gps_standard):
    header = laspy.LasHeader(version=version, point_format=point_format)
    if gps_standard:
        header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    las = laspy.LasData(header)
    las.x = np.array([1.0, 2.0])
    las.y = np.array([1.0, 2.0])
    las.z = np.array([1.0, 2.0])
    las.write(path)
    return path


def test_gps_week_time_is_rejected(tmp_path):
    path = _laspy_file(tmp_path / "week.las", "1.4", 6, gps_standard=False)
    with pytest.raises(InputError) as info:
        read_las(path)
    assert "week.las" in str(info.value) and "adjusted standard GPS time" in str(info.value)
    assert info.value.field == "global_encoding"


def test_old_point_format_is_rejected(tmp_path):
    path = _laspy_file(tmp_path / "pf1.las", "1.2", 1, gps_standard=True)
    with pytest.raises(InputError, match=r"pf1\.las, field 'point_format'.*expected 6 or higher.*found 1"):
        read_las(path)


def test_missing_extra_dimension(tmp_path):
    path = write_las(tmp_path / "a.las", _cloud(0, n=10))
    with pytest.raises(InputError, match=r"field 'sigma_m': extra dimension missing"):
        read_las(path, extra_dims=["sigma_m"])


# --- points encoded elsewhere (georefine.io.las_encode) -----------------------


def _part(c: PointCloud, a: int, b: int) -> PointCloud:
    s = slice(a, b)
    return PointCloud(c.time_gps[s], c.xyz[s], c.intensity[s], c.scanner_channel[s], c.point_source_id[s],
                      c.return_number[s], c.number_of_returns[s], {k: v[s] for k, v in c.extra.items()},
                      c.scan_angle_deg[s])


@pytest.mark.parametrize("suffix", [".laz", ".las"])
def test_points_encoded_by_tasks_give_the_file_the_writer_makes(tmp_path, suffix):
    """Parts on the chunk grid keep their LAZ chunks, parts off it are compressed again; either
    way the file is the one the writer makes from the points itself, byte for byte."""
    from georefine.io.las_encode import LAZ_CHUNK_POINTS, encode_points

    c = _cloud(11, n=237_000)
    kw = dict(scale=0.001, offset=(0.0, 0.0, 0.0), crs="EPSG:25832", extra_dims=("range_error_m",))
    with LasWriter(tmp_path / f"own{suffix}", **kw) as w:
        for a in range(0, len(c), 64_000):
            w.write(_part(c, a, a + 64_000))
    own = (tmp_path / f"own{suffix}").read_bytes()
    for name, cuts in (("grid", (0, 100_000, 200_000)), ("off", (0, 70_000, 120_000, 200_000))):
        path = tmp_path / f"{name}{suffix}"
        with LasWriter(path, **kw) as w:
            for a, b in zip(cuts, (*cuts[1:], len(c))):
                enc = encode_points(_part(c, a, b), w.layout_for())
                assert enc.count == b - a
                if suffix == ".laz":
                    assert len(enc.chunk_bytes) == (b - a) // LAZ_CHUNK_POINTS
                w.write_encoded(enc)
        assert (w.recompressed_points > 0) == (name == "off" and suffix == ".laz")
        assert path.read_bytes() == own, name
    _assert_same_points(read_las(tmp_path / f"off{suffix}"), _part(c, 0, len(c)), 6e-4)
    # the extra-bytes VLR holds the true range of the dimension
    struct = laspy.read(tmp_path / f"own{suffix}").header.vlrs.get("ExtraBytesVlr")[0].extra_bytes_structs[0]
    values = c.extra["range_error_m"].astype(np.float32)
    assert struct._raw_min()[0] == values.min() and struct._raw_max()[0] == values.max()


def test_encoded_laz_reads_and_seeks_with_every_decoder(tmp_path):
    from georefine.io.las_encode import encode_points

    c = _cloud(12, n=123_457)
    path = tmp_path / "parts.laz"
    with LasWriter(path, scale=0.001, offset=(0.0, 0.0, 0.0), extra_dims=("range_error_m",)) as w:
        for a, b in ((0, 50_000), (50_000, 61_000), (61_000, 123_457)):
            w.write_encoded(encode_points(_part(c, a, b), w.layout_for()))
    backends = [b for b in laspy.LazBackend.detect_available()]  # lazrs (both), LASzip where installed
    assert laspy.LazBackend.LazrsParallel in backends
    for backend in backends:
        d = laspy.read(path, laz_backend=backend)
        np.testing.assert_allclose(d.x, c.xyz[:, 0], atol=6e-4, err_msg=str(backend))
        with laspy.open(path, laz_backend=backend) as r:
            r.seek(100_001)
            np.testing.assert_allclose(r.read_points(5).x, c.xyz[100_001:100_006, 0], atol=6e-4)


def test_encoded_points_of_another_layout_are_refused(tmp_path):
    from georefine.io.las_encode import LasLayout, encode_points

    c = _cloud(13, n=1000)
    with LasWriter(tmp_path / "a.laz", scale=0.001, offset=(0.0, 0.0, 0.0)) as w:
        with pytest.raises(ValueError, match="encoded for"):
            w.write_encoded(encode_points(c, LasLayout((0.01,) * 3, (0.0, 0.0, 0.0))))
        w.write_encoded(encode_points(c, w.layout_for()))
    assert len(read_las(tmp_path / "a.laz")) == 1000
    with pytest.raises(ValueError, match="offset"):  # no offset: the first chunk fixes it
        LasWriter(tmp_path / "b.laz").layout_for()
