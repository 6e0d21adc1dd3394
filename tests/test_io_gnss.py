"""Tests of georefine.io.gnss (RTKLIB .pos) and the shared helpers in io.files."""

from __future__ import annotations

import datetime as dt

import numpy as np
import pytest
from pyproj import Transformer

from georefine.errors import InputError
from georefine.io.files import (
    atomic_output,
    calendar_from_gps_seconds,
    gps_seconds_from_calendar,
    unwrap_seconds_of_week,
    week_from_gps_seconds,
)
from georefine.io.gnss import GnssSolution, enu_rotation, read_pos, write_pos

T0 = 1_400_000_000.0  # 2024/05/17 16:53:20 GPST = week 2314, 492800 s


def _random_solution(seed: int, n: int = 50) -> GnssSolution:
    rng = np.random.default_rng(seed)
    t = T0 + np.arange(n) * 0.2 + rng.integers(0, 3, n).cumsum() * 0.1
    lat = np.radians(47.0 + 0.01 * rng.random(n))
    lon = np.radians(11.0 + 0.01 * rng.random(n))
    h = 600.0 + 50.0 * rng.random(n)
    a = rng.normal(scale=0.02, size=(n, 3, 3))
    cov = a @ np.swapaxes(a, 1, 2) + 1e-4 * np.eye(3)
    return GnssSolution.from_geodetic(
        t, lat, lon, h, cov, quality=rng.integers(1, 3, n), num_sats=rng.integers(5, 30, n),
        age_s=np.round(rng.random(n), 2), ratio=np.round(10 * rng.random(n), 1),
    )


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("time_format", ["calendar", "week"])
@pytest.mark.parametrize("position_format", ["llh", "ecef"])
def test_round_trip(tmp_path, seed, time_format, position_format):
    sol = _random_solution(seed)
    path = write_pos(tmp_path / "sol.pos", sol, time_format, position_format)
    back = read_pos(path)
    np.testing.assert_allclose(back.time_gps, sol.time_gps, rtol=0, atol=1e-6)
    # llh: 1e-9 deg ~ 0.1 mm; ecef: 0.1 mm rounding
    np.testing.assert_allclose(back.position_ecef, sol.position_ecef, rtol=0, atol=1.2e-4)
    # standard deviations are written with 0.1 mm resolution
    np.testing.assert_allclose(back.covariance_ecef, sol.covariance_ecef, rtol=0, atol=2e-5)
    np.testing.assert_array_equal(back.quality, sol.quality)
    np.testing.assert_array_equal(back.num_sats, sol.num_sats)
    np.testing.assert_allclose(back.age_s, sol.age_s, atol=0.006)
    np.testing.assert_allclose(back.ratio, sol.ratio, atol=0.06)


def test_header_layout_matches_rtklib(tmp_path):
    path = write_pos(tmp_path / "a.pos", _random_solution(0, 3), "calendar", "llh")
    lines = path.read_text().splitlines()
    assert lines[0].startswith("% program   : Georefine")
    assert lines[1] == "% pos mode  : kinematic"
    assert "(lat/lon/height=WGS84/ellipsoidal,Q=1:fix,2:float" in lines[3]
    assert lines[4].split() == ["%", "GPST", "latitude(deg)", "longitude(deg)", "height(m)", "Q", "ns",
                                "sdn(m)", "sde(m)", "sdu(m)", "sdne(m)", "sdeu(m)", "sdun(m)", "age(s)", "ratio"]
    first = lines[5].split()
    assert len(first[2].split(".")[1]) == 9 and len(first[4].split(".")[1]) == 4


RTKLIB_SAMPLE = """\
% program   : RTKPOST ver.2.4.3 b34
% inp file  : rover.obs
% pos mode  : kinematic
% solution  : combined
%
% (lat/lon/height=WGS84/ellipsoidal,Q=1:fix,2:float,3:sbas,4:dgps,5:single,6:ppp,ns=# of satellites)
%  GPST                  latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)  sdne(m)  sdeu(m)  sdun(m) age(s)  ratio
2024/05/17 16:53:20.000   47.000000000   11.000000000   600.0000   1  12   0.0200   0.0100   0.0300  -0.0050   0.0040   0.0000   1.00    5.2
2024/05/17 16:53:20.200   47.000000100   11.000000200   600.0100   2   9   0.0200   0.0100   0.0300   0.0050   0.0000   0.0000   1.20    2.1
"""


def test_reads_rtklib_sample_and_signed_root_covariance(tmp_path):
    path = tmp_path / "rtk.pos"
    path.write_text(RTKLIB_SAMPLE)
    sol = read_pos(path)
    expected_t0 = (dt.datetime(2024, 5, 17, 16, 53, 20) - dt.datetime(1980, 1, 6)).total_seconds()
    np.testing.assert_allclose(sol.time_gps, [expected_t0, expected_t0 + 0.2], atol=1e-9)
    assert expected_t0 == T0
    lat, lon, h = sol.geodetic()
    np.testing.assert_allclose(np.degrees(lat[0]), 47.0, atol=1e-11)
    np.testing.assert_allclose(h, [600.0, 600.01], atol=1e-6)
    c = sol.covariance_enu()
    # E, N, U variances and the signed square roots: sdne = -0.005 -> c_ne = -2.5e-5
    np.testing.assert_allclose(np.diag(c[0]), [0.01**2, 0.02**2, 0.03**2], atol=1e-12)
    np.testing.assert_allclose(c[0, 0, 1], -0.005**2, atol=1e-12)
    np.testing.assert_allclose(c[1, 0, 1], +0.005**2, atol=1e-12)
    np.testing.assert_allclose(c[0, 0, 2], 0.004**2, atol=1e-12)  # sdeu
    np.testing.assert_array_equal(sol.quality, [1, 2])
    np.testing.assert_array_equal(sol.num_sats, [12, 9])
    np.testing.assert_allclose(sol.ratio, [5.2, 2.1])
    # Writing again reproduces the signed square roots.
    out = write_pos(tmp_path / "again.pos", sol)
    row = out.read_text().splitlines()[5].split()
    assert row[10] == "-0.0050" and row[11] == "0.0040"


def test_covariance_rotation_at_lat0_lon0():
    # At lat = lon = 0: east = +y, north = +z, up = +x in ECEF.
    cov_enu = np.diag([1.0, 4.0, 9.0])[None]
    sol = GnssSolution.from_geodetic(np.array([T0]), np.zeros(1), np.zeros(1), np.zeros(1), cov_enu,
                                     np.ones(1), np.ones(1))
    np.testing.assert_allclose(np.diag(sol.covariance_ecef[0]), [9.0, 1.0, 4.0], atol=1e-12)
    R = enu_rotation(np.radians([47.0]), np.radians([11.0]))
    np.testing.assert_allclose(R[0] @ R[0].T, np.eye(3), atol=1e-15)
    np.testing.assert_allclose(np.linalg.det(R[0]), 1.0)


def test_ecef_matches_pyproj(tmp_path):
    sol = _random_solution(3, 5)
    lat, lon, h = sol.geodetic()
    x, y, z = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True).transform(
        np.degrees(lon), np.degrees(lat), h)
    np.testing.assert_allclose(sol.position_ecef, np.column_stack([x, y, z]), atol=1e-6)


def test_week_format_velocity_columns_and_no_header(tmp_path):
    sol = _random_solution(4, 4)
    path = write_pos(tmp_path / "w.pos", sol, "week", "ecef")
    lines = path.read_text().splitlines()
    # Strip the header and append velocity-like columns: still readable, extras ignored.
    body = [ln + "   1.00000   2.00000   3.00000" for ln in lines[5:]]
    (tmp_path / "bare.pos").write_text("\n".join(body) + "\n")
    back = read_pos(tmp_path / "bare.pos")
    np.testing.assert_allclose(back.position_ecef, sol.position_ecef, atol=1e-4)
    np.testing.assert_allclose(back.time_gps, sol.time_gps, atol=1e-6)


def test_short_rows_without_covariances(tmp_path):
    text = RTKLIB_SAMPLE.replace("  -0.0050   0.0040   0.0000   1.00    5.2", "").replace(
        "   0.0050   0.0000   0.0000   1.20    2.1", "")
    (tmp_path / "s.pos").write_text(text)
    sol = read_pos(tmp_path / "s.pos")
    c = sol.covariance_enu()
    np.testing.assert_allclose(c[0], np.diag([0.01**2, 0.02**2, 0.03**2]), atol=1e-12)
    np.testing.assert_array_equal(sol.age_s, [0.0, 0.0])


# --- errors -----------------------------------------------------------------


def _sample_with(tmp_path, old: str, new: str, name="bad.pos"):
    path = tmp_path / name
    text = RTKLIB_SAMPLE.replace(old, new, 1)
    assert text != RTKLIB_SAMPLE
    path.write_text(text)
    return path


def test_bad_latitude_names_line_and_field(tmp_path):
    path = _sample_with(tmp_path, "47.000000100", "47.0000x0100")
    with pytest.raises(InputError) as info:
        read_pos(path)
    msg = str(info.value)
    assert "bad.pos" in msg and "line 9" in msg and "latitude(deg)" in msg and "47.0000x0100" in msg
    assert info.value.line == 9 and info.value.field == "latitude(deg)"


def test_latitude_out_of_range(tmp_path):
    path = _sample_with(tmp_path, "47.000000100", "97.000000100")
    with pytest.raises(InputError, match=r"line 9.*latitude\(deg\)"):
        read_pos(path)


def test_missing_field_names_line(tmp_path):
    path = _sample_with(tmp_path, "   2   9   0.0200", "   2   0.0200")
    with pytest.raises(InputError) as info:
        read_pos(path)
    assert info.value.line == 9 and "wrong number of fields" in str(info.value)


def test_bad_date_names_field(tmp_path):
    path = _sample_with(tmp_path, "2024/05/17 16:53:20.200", "2024/13/17 16:53:20.200")
    with pytest.raises(InputError) as info:
        read_pos(path)
    assert info.value.line == 9 and info.value.field == "GPST month" and "13" in str(info.value)


def test_no_epochs(tmp_path):
    path = tmp_path / "empty.pos"
    path.write_text("\n".join(RTKLIB_SAMPLE.splitlines()[:7]) + "\n")
    with pytest.raises(InputError, match=r"empty\.pos: no solution epochs"):
        read_pos(path)


def test_time_not_increasing_names_both_values(tmp_path):
    path = _sample_with(tmp_path, "2024/05/17 16:53:20.200", "2024/05/17 16:53:19.900")
    with pytest.raises(InputError) as info:
        read_pos(path)
    msg = str(info.value)
    assert info.value.line == 9 and "goes backwards" in msg
    assert f"{T0:.3f}" in msg and f"{T0 - 0.1:.3f}" in msg and "line 8" in msg


def test_utc_files_are_rejected(tmp_path):
    path = _sample_with(tmp_path, "%  GPST ", "%  UTC  ")
    with pytest.raises(InputError, match=r"line 7.*expected GPST, found UTC"):
        read_pos(path)


def test_writer_refuses_to_write_into_input_folder(tmp_path):
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    with pytest.raises(InputError, match="refusing to write into an input"):
        write_pos(inputs / "out.pos", _random_solution(0, 2), protect=(inputs,))
    assert not (inputs / "out.pos").exists()


# --- shared helpers -----------------------------------------------------------


def test_atomic_output_keeps_old_file_on_failure(tmp_path):
    path = tmp_path / "f.txt"
    path.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_output(path) as fh:
            fh.write("half")
            raise RuntimeError("boom")
    assert path.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.txt"]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_calendar_round_trip_against_datetime(seed):
    rng = np.random.default_rng(seed)
    t = np.round(rng.uniform(0, 2e9, 200), 3)
    y, mo, d, h, mi, s, frac = calendar_from_gps_seconds(t, 3)
    for k in range(0, 200, 37):
        ref = dt.datetime(1980, 1, 6) + dt.timedelta(seconds=float(t[k]))
        assert (y[k], mo[k], d[k], h[k], mi[k], s[k]) == (ref.year, ref.month, ref.day, ref.hour, ref.minute,
                                                          ref.second)
    back = gps_seconds_from_calendar(y, mo, d, h, mi, s + frac / 1000.0)
    np.testing.assert_allclose(back, t, atol=1e-6)


def test_calendar_rounding_carries_into_the_next_minute():
    y, mo, d, h, mi, s, frac = calendar_from_gps_seconds(np.array([T0 + 39.99996]), 3)
    assert (int(mi[0]), int(s[0]), int(frac[0])) == (54, 0, 0)


def test_week_helpers():
    week, sow = week_from_gps_seconds(np.array([T0]))
    assert week[0] == 2314 and sow[0] == 492800.0
    np.testing.assert_allclose(unwrap_seconds_of_week(np.array([604799.0, 0.5, 1.5])), [604799.0, 604800.5, 604801.5])


def test_malformed_time_names_field(tmp_path):
    path = _sample_with(tmp_path, "2024/05/17 16:53:20.200", "2024/05/17 16:53")
    with pytest.raises(InputError, match=r"line 9, field 'GPST time': malformed GPST time.*'16:53'"):
        read_pos(path)
