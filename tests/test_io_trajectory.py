"""Tests of georefine.io.trajectory (SBET and trajectory CSV)."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from georefine.errors import InputError
from georefine.io.trajectory import (
    SBET_RECORD_SIZE,
    SbetData,
    TrajectoryTable,
    read_sbet,
    read_trajectory_csv,
    write_sbet,
    write_trajectory_csv,
)

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
    back = read_trajectory_csv(write_trajectory_csv(tmp_path / "traj.csv", table))
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
