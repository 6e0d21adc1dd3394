"""Tests of georefine.io.trajectory (SBET with its companion file, smrmsg accuracy file, trajectory CSV)."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from georefine.errors import InputError
from georefine.io.trajectory import (
    SBET_RECORD_SIZE,
    SMRMSG_RECORD_SIZE,
    SbetCompanion,
    SbetData,
    SmrmsgData,
    read_sbet,
    read_sbet_companion,
    read_smrmsg,
    sbet_companion_path,
    smrmsg_path,
    write_sbet,
    write_sbet_companion,
    write_smrmsg,
)
from georefine.io.trajectory_csv import TrajectoryTable, read_trajectory_csv, write_trajectory_csv

T0 = 1_400_000_000.0
WEEK = 2314


def _sbet(seed: int, n: int = 300, t0: float = T0) -> SbetData:
    rng = np.random.default_rng(seed)
    return SbetData(
        time_gps=t0 + np.arange(n) / 200.0,
        lat_rad=np.radians(47.0 + 1e-3 * rng.random(n)), lon_rad=np.radians(11.0 + 1e-3 * rng.random(n)),
        h_m=700.0 + rng.random(n), velocity_wander=rng.normal(size=(n, 3)),
        roll_rad=rng.normal(scale=0.05, size=n), pitch_rad=rng.normal(scale=0.05, size=n),
        heading_rad=rng.uniform(-np.pi, np.pi, n), wander_rad=np.zeros(n),
        accel_b=rng.normal(size=(n, 3)) + [0, 0, -9.81], angular_rate_b=rng.normal(scale=0.1, size=(n, 3)),
    )


def _assert_sbet_equal(a: SbetData, b: SbetData) -> None:
    for name in SbetData.__dataclass_fields__:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("time_scale", ["week", "gps"])
def test_sbet_round_trip(tmp_path, seed, time_scale):
    data = _sbet(seed)
    path = write_sbet(tmp_path / "sbet.out", data, time_scale)
    assert path.stat().st_size == len(data) * SBET_RECORD_SIZE == len(data) * 136
    back = read_sbet(path, gps_week=WEEK if time_scale == "week" else None)
    _assert_sbet_equal(data, back)  # binary float64: exact
    assert np.fromfile(path, "<f8", count=1)[0] == (T0 - WEEK * 604800.0 if time_scale == "week" else T0)


def test_sbet_field_order(tmp_path):
    # One record written field by field: time, lat, lon, alt, vx, vy, vz, roll, pitch, heading,
    # wander, ax, ay, az, wx, wy, wz.
    values = [492800.5, 0.8, 0.2, 650.0, 1.0, 2.0, 3.0, 0.01, 0.02, 1.5, 0.0, 0.1, 0.2, -9.8, 0.3, 0.4, 0.5]
    path = tmp_path / "one.out"
    path.write_bytes(struct.pack("<17d", *values))
    s = read_sbet(path, gps_week=WEEK)
    assert s.time_gps[0] == WEEK * 604800.0 + 492800.5
    assert (s.lat_rad[0], s.lon_rad[0], s.h_m[0]) == (0.8, 0.2, 650.0)
    np.testing.assert_array_equal(s.velocity_wander[0], [1.0, 2.0, 3.0])
    assert (s.roll_rad[0], s.pitch_rad[0], s.heading_rad[0], s.wander_rad[0]) == (0.01, 0.02, 1.5, 0.0)
    np.testing.assert_array_equal(s.accel_b[0], [0.1, 0.2, -9.8])
    np.testing.assert_array_equal(s.angular_rate_b[0], [0.3, 0.4, 0.5])
    np.testing.assert_array_equal(s.velocity_ned(), [[1.0, 2.0, 3.0]])


def test_sbet_week_rollover(tmp_path):
    data = _sbet(0, n=10, t0=(WEEK + 1) * 604800.0 - 0.02)
    raw = np.column_stack([data.time_gps - (WEEK * 604800.0), np.zeros((10, 16))])
    raw[:, 0] = np.where(raw[:, 0] >= 604800.0, raw[:, 0] - 604800.0, raw[:, 0])  # rolled-over tags
    path = tmp_path / "roll.out"
    path.write_bytes(raw.astype("<f8").tobytes())
    back = read_sbet(path, gps_week=WEEK)
    np.testing.assert_allclose(back.time_gps, data.time_gps, atol=1e-9)


def test_sbet_incomplete_record(tmp_path):
    path = write_sbet(tmp_path / "cut.out", _sbet(0, n=10))
    path.write_bytes(path.read_bytes()[:-40])
    with pytest.raises(InputError) as info:
        read_sbet(path, WEEK)
    msg = str(info.value)
    assert "cut.out" in msg and "record 10" in msg and "incomplete record" in msg and "96 bytes" in msg


def test_sbet_seconds_of_week_need_week(tmp_path):
    path = write_sbet(tmp_path / "w.out", _sbet(0, n=3), "week")
    with pytest.raises(InputError, match="GPS week is needed"):
        read_sbet(path)


def test_sbet_time_not_increasing(tmp_path):
    data = _sbet(0, n=5)
    raw = np.fromfile(write_sbet(tmp_path / "t.out", data, "gps"), "<f8").reshape(5, 17)
    raw[3, 0] = raw[1, 0]
    (tmp_path / "t.out").write_bytes(raw.tobytes())
    with pytest.raises(InputError, match=r"t\.out, record 4, field 'time': time goes backwards.*record 3"):
        read_sbet(tmp_path / "t.out")


def test_sbet_non_finite(tmp_path):
    raw = np.fromfile(write_sbet(tmp_path / "n.out", _sbet(0, n=5), "gps"), "<f8").reshape(5, 17)
    raw[2, 8] = np.nan
    (tmp_path / "n.out").write_bytes(raw.tobytes())
    with pytest.raises(InputError, match=r"record 3, field 'pitch': non-finite value"):
        read_sbet(tmp_path / "n.out")


# --- SBET companion file (GPS week) ------------------------------------------------


def test_sbet_week_from_companion_file(tmp_path):
    data = _sbet(2, n=20)
    path = write_sbet(tmp_path / "trajectory.sbet", data, "week")
    assert np.fromfile(path, "<f8", count=1)[0] < 604800.0  # seconds of week, as POSPac writes them
    companion = write_sbet_companion(path, SbetCompanion(WEEK, 25832, "smrmsg_trajectory.out"))
    assert companion == sbet_companion_path(path) == tmp_path / "trajectory.sbet.json"
    stated = json.loads(companion.read_text())
    assert stated["gps_week"] == WEEK and stated["time"] == "GPS seconds of week"
    assert stated["output_crs"] == "EPSG:25832" and stated["accuracy_file"] == "smrmsg_trajectory.out"
    assert read_sbet_companion(path) == SbetCompanion(WEEK, 25832, "smrmsg_trajectory.out")
    _assert_sbet_equal(data, read_sbet(path))  # the week found without being given
    _assert_sbet_equal(data, read_sbet(path, gps_week=WEEK))  # given and agreeing
    with pytest.raises(InputError) as info:
        read_sbet(path, gps_week=WEEK - 1)
    msg = str(info.value)
    assert "trajectory.sbet.json" in msg and "contradicts" in msg and str(WEEK - 1) in msg and str(WEEK) in msg
    # A week file with only the week is enough; no companion at all keeps the clear error.
    companion.write_text(json.dumps({"gps_week": WEEK + 1}))
    assert read_sbet(path).time_gps[0] == pytest.approx(data.time_gps[0] + 604800.0, abs=1e-6)
    companion.unlink()
    assert read_sbet_companion(path) is None
    with pytest.raises(InputError, match=r"trajectory\.sbet, record 1, field 'time'.*GPS week is needed.*trajectory\.sbet\.json"):
        read_sbet(path)


@pytest.mark.parametrize("content, field, found", [
    ('{"gps_week": "2314"}', "gps_week", "'2314'"),
    ('{"gps_week": -1}', "gps_week", "-1"),
    ('{"gps_week": 2314.5}', "gps_week", "2314.5"),
    ('{"time": "GPS seconds", "gps_week": 2314}', "time", "'GPS seconds'"),
    ('{"gps_week": 2314, "output_crs": "UTM32"}', "output_crs", "'UTM32'"),
    ('{"gps_week": 2314, "accuracy_file": "../x.out"}', "accuracy_file", "'../x.out'"),
    ('[2314]', None, "list"),
    ('{"gps_week": 2314', None, "Expecting"),
])
def test_sbet_bad_companion_file(tmp_path, content, field, found):
    path = write_sbet(tmp_path / "t.sbet", _sbet(0, n=3), "week")
    sbet_companion_path(path).write_text(content)
    with pytest.raises(InputError) as info:
        read_sbet(path)
    msg = str(info.value)
    assert "t.sbet.json" in msg and found in msg and (field is None or f"field '{field}'" in msg), msg


# --- smrmsg accuracy file ------------------------------------------------------------


def _smrmsg(seed: int, n: int = 50, t0: float = T0) -> SmrmsgData:
    rng = np.random.default_rng(seed)
    return SmrmsgData(t0 + np.arange(n) * 1.0, rng.uniform(0.01, 0.05, (n, 3)), rng.uniform(0.001, 0.01, (n, 3)),
                      np.radians(rng.uniform(1, 30, (n, 3)) / 1000.0))


@pytest.mark.parametrize("seed", [0, 1])
def test_smrmsg_round_trip(tmp_path, seed):
    data = _smrmsg(seed)
    path = write_smrmsg(tmp_path / "smrmsg_t.out", data, gps_week=WEEK)
    assert path.stat().st_size == len(data) * SMRMSG_RECORD_SIZE == len(data) * 80
    raw = np.fromfile(path, "<f8").reshape(-1, 10)
    assert raw[0, 0] == T0 - WEEK * 604800.0  # seconds of week
    np.testing.assert_allclose(raw[:, 7:10], np.degrees(data.sigma_rph_rad) * 60.0, rtol=1e-14)  # arc minutes
    back = read_smrmsg(path, gps_week=WEEK)
    np.testing.assert_array_equal(back.time_gps, data.time_gps)
    np.testing.assert_array_equal(back.sigma_ned_m, data.sigma_ned_m)
    np.testing.assert_array_equal(back.sigma_velocity_ned_m_s, data.sigma_velocity_ned_m_s)
    np.testing.assert_allclose(back.sigma_rph_rad, data.sigma_rph_rad, rtol=1e-14, atol=0)


def test_smrmsg_field_order(tmp_path):
    # POSPac's record: time (s of week), N/E/D position RMS (m), N/E/D velocity RMS (m/s),
    # roll/pitch/heading RMS (arc minutes).
    path = tmp_path / "smrmsg_one.out"
    path.write_bytes(struct.pack("<10d", 492800.5, 0.01, 0.02, 0.03, 0.004, 0.005, 0.006, 0.5, 0.75, 3.0))
    a = read_smrmsg(path, gps_week=WEEK)
    assert a.time_gps[0] == WEEK * 604800.0 + 492800.5
    np.testing.assert_array_equal(a.sigma_ned_m[0], [0.01, 0.02, 0.03])
    np.testing.assert_array_equal(a.sigma_velocity_ned_m_s[0], [0.004, 0.005, 0.006])
    np.testing.assert_allclose(np.degrees(a.sigma_rph_rad[0]) * 60.0, [0.5, 0.75, 3.0], rtol=1e-14)


def test_smrmsg_path_is_named_the_pospac_way(tmp_path):
    assert smrmsg_path(tmp_path / "trajectory.sbet") == tmp_path / "smrmsg_trajectory.out"
    assert smrmsg_path(tmp_path / "sbet_Mission1.out") == tmp_path / "smrmsg_Mission1.out"


def _damaged_smrmsg(tmp_path, edit) -> str:
    path = write_smrmsg(tmp_path / "smrmsg_d.out", _smrmsg(3, n=6), gps_week=WEEK)
    raw = np.fromfile(path, "<f8").reshape(-1, 10)
    data = edit(raw)
    path.write_bytes(data if isinstance(data, bytes) else raw.tobytes())
    with pytest.raises(InputError) as info:
        read_smrmsg(path, gps_week=WEEK)
    return str(info.value)


def test_smrmsg_bad_files(tmp_path):
    msg = _damaged_smrmsg(tmp_path, lambda r: r.tobytes()[:-8])
    assert "smrmsg_d.out" in msg and "record 6" in msg and "incomplete record" in msg and "72 bytes" in msg
    msg = _damaged_smrmsg(tmp_path, lambda r: b"")
    assert "no accuracy records" in msg
    msg = _damaged_smrmsg(tmp_path, lambda r: r.__setitem__((2, 5), np.inf))
    assert "record 3, field 'east_velocity_rms': non-finite value" in msg
    msg = _damaged_smrmsg(tmp_path, lambda r: r.__setitem__((4, 9), -1.0))
    assert "record 5, field 'heading_rms': negative RMS" in msg
    msg = _damaged_smrmsg(tmp_path, lambda r: r.__setitem__((3, 0), r[2, 0]))
    assert "record 4, field 'time': time repeats" in msg
    path = write_smrmsg(tmp_path / "smrmsg_w.out", _smrmsg(3, n=2), gps_week=WEEK)
    with pytest.raises(InputError, match=r"record 1, field 'time'.*GPS week is needed"):
        read_smrmsg(path)


# --- trajectory CSV ---------------------------------------------------------------


def _table(seed: int, n: int = 100, pos_sigma=True, att_sigma=True) -> TrajectoryTable:
    rng = np.random.default_rng(seed)
    rpy = np.column_stack([rng.normal(scale=0.05, size=n), rng.normal(scale=0.05, size=n),
                           rng.uniform(0, 2 * np.pi, n)])
    return TrajectoryTable(
        time_gps=T0 + np.arange(n) * 0.005,
        xyz=np.array([691_000.0, 5_334_000.0, 700.0]) + rng.uniform(-500, 500, (n, 3)),
        rpy_rad=rpy,
        sigma_xyz_m=rng.uniform(0.01, 0.05, (n, 3)) if pos_sigma else None,
        sigma_rpy_rad=np.radians(rng.uniform(1, 20, (n, 3)) / 1000.0) if att_sigma else None,
        crs="EPSG:25832",
    )


@pytest.mark.parametrize("pos_sigma", [False, True])
@pytest.mark.parametrize("att_sigma", [False, True])
def test_trajectory_csv_round_trip(tmp_path, pos_sigma, att_sigma):
    table = _table(0, pos_sigma=pos_sigma, att_sigma=att_sigma)
    path = write_trajectory_csv(tmp_path / "traj.csv", table)
    assert f"# gps_week: {int(T0 // 604800)}" in path.read_text().splitlines()  # the week of the SBET beside it
    back = read_trajectory_csv(path)
    assert back.crs == "EPSG:25832"
    np.testing.assert_allclose(back.time_gps, table.time_gps, atol=1e-6)
    np.testing.assert_allclose(back.xyz, table.xyz, atol=5e-5 + 1e-9)
    np.testing.assert_allclose(back.rpy_rad, table.rpy_rad, atol=np.radians(5e-9) + 1e-15)
    for name, atol in (("sigma_xyz_m", 5e-6 + 1e-12), ("sigma_rpy_rad", np.radians(5e-8) + 1e-15)):
        a, b = getattr(table, name), getattr(back, name)
        assert (a is None) == (b is None)
        if a is not None:
            np.testing.assert_allclose(b, a, atol=atol)


def test_trajectory_csv_heading_wraps_to_0_360(tmp_path):
    table = TrajectoryTable(np.array([T0]), np.zeros((1, 3)), np.array([[0.0, 0.0, -np.pi / 2]]))
    path = write_trajectory_csv(tmp_path / "h.csv", table)
    assert path.read_text().splitlines()[-1].split(",")[6].startswith("270.0")


def test_trajectory_csv_bad_value(tmp_path):
    path = write_trajectory_csv(tmp_path / "bad.csv", _table(1, n=5))
    lines = path.read_text().splitlines()
    fields = lines[5].split(",")
    fields[5] = "1.2.3"
    lines[5] = ",".join(fields)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"bad\.csv, line 6, field 'pitch_deg': not a number.*'1\.2\.3'"):
        read_trajectory_csv(path)


def test_trajectory_csv_incomplete_sigma_group(tmp_path):
    path = tmp_path / "g.csv"
    path.write_text("time,x,y,z,roll_deg,pitch_deg,heading_deg,sigma_x_m\n1,0,0,0,0,0,0,0.1\n")
    with pytest.raises(InputError, match=r"line 1: unexpected trajectory CSV header.*sigma_y_m"):
        read_trajectory_csv(path)


def test_trajectory_csv_time_repeats(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text("time,x,y,z,roll_deg,pitch_deg,heading_deg\n1,0,0,0,0,0,0\n1,0,0,0,0,0,0\n")
    with pytest.raises(InputError, match=r"line 3, field 'time': time repeats"):
        read_trajectory_csv(path)
