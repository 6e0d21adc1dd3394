"""Tests of georefine.io.imu (IMU CSV and Inertial Explorer IMR)."""

from __future__ import annotations

import numpy as np
import pytest

from georefine.errors import InputError
from georefine.io.imu import (
    ImuData,
    _imr_header_dtype,
    _imr_record_dtype,
    read_imr,
    read_imr_header,
    read_imu_csv,
    sample_intervals,
    write_imr,
    write_imu_csv,
)

T0 = 1_400_000_000.0  # GPS week 2314, 492800 s
WEEK = 2314
RATE = 200.0


def _imu(seed: int, n: int = 400, kind: str = "rates") -> ImuData:
    rng = np.random.default_rng(seed)
    t = T0 + np.arange(n) / RATE + rng.normal(scale=1e-6, size=n)
    gyro = rng.normal(scale=0.2, size=(n, 3))
    acc = rng.normal(scale=1.0, size=(n, 3)) + [0.0, 0.0, -9.81]
    return ImuData(t, gyro, acc, RATE, kind)


# --- CSV ----------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("kind", ["rates", "increments"])
def test_csv_round_trip(tmp_path, seed, kind):
    data = _imu(seed, kind=kind)
    path = write_imu_csv(tmp_path / "imu.csv", data)
    header = path.read_text().splitlines()[0]
    assert header.startswith("time,gyro_x" if kind == "rates" else "time,dtheta_x")
    back = read_imu_csv(path, rate_hz=RATE)
    assert back.kind == kind and back.rate_hz == RATE
    np.testing.assert_array_equal(back.time_gps, data.time_gps)  # %.9f round-trips float64 exactly
    np.testing.assert_allclose(back.gyro, data.gyro, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(back.acc, data.acc, rtol=1e-9, atol=1e-12)


def test_csv_nominal_rate_from_median_interval(tmp_path):
    path = write_imu_csv(tmp_path / "imu.csv", _imu(0))
    assert read_imu_csv(path).rate_hz == pytest.approx(RATE, rel=1e-5)


def test_intervals_nominal_first_after_gaps_and_for_tag_rounding():
    # 0.24 us float64 rounding of absolute GPS seconds must not leak into the rates.
    t = T0 + np.array([0.0, 0.005, 0.010, 0.050, 0.055, 0.0575])
    assert np.diff(t)[0] != 0.005  # the raw difference is off by the float64 resolution
    dt = sample_intervals(t, RATE)
    np.testing.assert_array_equal(dt[:5], 1.0 / RATE)  # first, regular, after the gap
    np.testing.assert_allclose(dt[5], 0.0025, atol=3e-7)  # genuinely irregular: actual interval
    dth = np.tile([[1e-3, 0.0, 0.0]], (6, 1))
    data = ImuData.from_increments(t, dth, dth, RATE)
    np.testing.assert_allclose(data.gyro[:5, 0], 0.2, rtol=1e-15)
    back, _ = data.increments()
    np.testing.assert_allclose(back, dth, rtol=1e-12)


def test_find_imu_gaps():
    from georefine.io.imu_gaps import find_imu_gaps

    data = _imu(0, n=100)
    t = np.delete(data.time_gps, np.arange(40, 45))
    gapped = ImuData(t, np.delete(data.gyro, np.arange(40, 45), 0), np.delete(data.acc, np.arange(40, 45), 0), RATE)
    (gap,) = find_imu_gaps(gapped)
    np.testing.assert_allclose([gap.t_before, gap.t_after], [data.time_gps[39], data.time_gps[45]])
    assert gap.index == 39 and gap.missing == 5
    assert find_imu_gaps(data) == []


def _write_csv(tmp_path, body: str, name="imu.csv"):
    path = tmp_path / name
    path.write_text("time,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z\n" + body)
    return path


def test_csv_bad_value_names_line_and_field(tmp_path):
    path = _write_csv(tmp_path, "1.0,0,0,0,0,0,-9.8\n1.005,0,0.1,0,0,abc,-9.8\n")
    with pytest.raises(InputError) as info:
        read_imu_csv(path)
    msg = str(info.value)
    assert "imu.csv" in msg and "line 3" in msg and "field 'acc_y'" in msg and "'abc'" in msg


def test_csv_time_repeats_names_line_and_both_values(tmp_path):
    path = _write_csv(tmp_path, "1.0,0,0,0,0,0,-9.8\n1.005,0,0,0,0,0,-9.8\n1.005,0,0,0,0,0,-9.8\n")
    with pytest.raises(InputError) as info:
        read_imu_csv(path)
    msg = str(info.value)
    assert info.value.line == 4 and "time repeats" in msg and "1.005000000" in msg and "line 3" in msg


def test_csv_time_backwards(tmp_path):
    path = _write_csv(tmp_path, "1.0,0,0,0,0,0,-9.8\n0.995,0,0,0,0,0,-9.8\n")
    with pytest.raises(InputError, match=r"line 3, field 'time': time goes backwards"):
        read_imu_csv(path)


def test_csv_unknown_header(tmp_path):
    path = tmp_path / "imu.csv"
    path.write_text("t,wx,wy,wz,ax,ay,az\n1,0,0,0,0,0,0\n")
    with pytest.raises(InputError, match=r"line 1: unknown IMU CSV header"):
        read_imu_csv(path)


def test_csv_implausible_magnitude(tmp_path):
    path = _write_csv(tmp_path, "1.0,0,0,0,0,0,-9.8\n1.005,0,0,900,0,0,-9.8\n")
    with pytest.raises(InputError, match=r"line 3, field 'gyro_z': implausible"):
        read_imu_csv(path)


def test_csv_wrong_field_count(tmp_path):
    path = _write_csv(tmp_path, "1.0,0,0,0,0,0,-9.8\n1.005,0,0,0,0,-9.8\n")
    with pytest.raises(InputError, match=r"line 3: wrong number of fields"):
        read_imu_csv(path)


@pytest.mark.parametrize("kind", ["rates", "increments"])
def test_csv_temperature_column_round_trips_and_is_optional(tmp_path, kind):
    """A last ``temperature_c`` column (deg C) is read where it is; files without it read as before (None)."""
    from dataclasses import replace

    data = _imu(3, kind=kind)
    temperature = 20.0 + np.linspace(0.0, 7.5, len(data))
    path = write_imu_csv(tmp_path / "imu.csv", replace(data, temperature_c=temperature))
    assert path.read_text().splitlines()[0].endswith(",temperature_c")
    back = read_imu_csv(path, rate_hz=RATE)
    np.testing.assert_allclose(back.temperature_c, temperature, atol=5e-5)  # written with 4 decimals
    np.testing.assert_allclose(back.gyro, data.gyro, rtol=1e-9, atol=1e-12)
    assert read_imu_csv(write_imu_csv(tmp_path / "plain.csv", data), rate_hz=RATE).temperature_c is None


def test_csv_implausible_temperature_names_line_and_field(tmp_path):
    path = tmp_path / "imu.csv"
    path.write_text("time,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z,temperature_c\n"
                    "1.0,0,0,0,0,0,-9.8,21.5\n1.005,0,0,0,0,0,-9.8,2150\n")
    with pytest.raises(InputError, match=r"line 3, field 'temperature_c': implausible IMU temperature.*2150"):
        read_imu_csv(path)
    path.write_text("time,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z,temperature_c,extra\n1.0,0,0,0,0,0,-9.8,21.5,0\n")
    with pytest.raises(InputError, match=r"line 1: unknown IMU CSV header.*optionally followed by ',temperature_c'"):
        read_imu_csv(path)


def test_bridged_samples_get_the_interpolated_temperature():
    from dataclasses import replace

    from georefine.io.imu_gaps import bridge_imu_gaps

    data = _imu(4)
    keep = np.ones(len(data), dtype=bool)
    keep[100:104] = False
    temperature = 20.0 + 0.01 * np.arange(len(data))
    gappy = ImuData(data.time_gps[keep], data.gyro[keep], data.acc[keep], RATE, temperature_c=temperature[keep])
    bridged, too_long = bridge_imu_gaps(gappy, max_gap_s=1.0)
    assert too_long is None and len(bridged.data) == len(data)
    np.testing.assert_allclose(bridged.data.temperature_c, np.interp(bridged.data.time_gps, gappy.time_gps,
                                                                     gappy.temperature_c))
    assert replace(gappy, temperature_c=None).temperature_c is None


# --- IMR ----------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("delta", [True, False])
def test_imr_round_trip_quantisation_bounded(tmp_path, seed, delta):
    data = _imu(seed, kind="increments" if delta else "rates")
    path = write_imr(tmp_path / "raw.imr", data, WEEK, delta=delta)
    header = read_imr_header(path)
    assert header.delta_theta is delta and header.rate_hz == RATE and header.imu_name == "Georefine"
    back = read_imr(path, gps_week=WEEK)
    assert back.kind == ("increments" if delta else "rates")
    np.testing.assert_allclose(back.time_gps, data.time_gps, rtol=0, atol=1e-6)
    dt = data.intervals()[:, None] if delta else 1.0
    # half a count of the scale factor, converted back to rates
    g_bound = np.radians(header.gyro_scale) / 2 / dt * 1.001
    a_bound = header.accel_scale / 2 / dt * 1.001
    assert np.all(np.abs(back.gyro - data.gyro) <= g_bound)
    assert np.all(np.abs(back.acc - data.acc) <= a_bound)
    assert np.max(np.abs(back.gyro - data.gyro)) < 1e-6


def test_imr_axes_are_right_forward_up(tmp_path):
    # FRD forward specific force and a yaw rate about down.
    t = T0 + np.arange(3) / RATE
    data = ImuData(t, np.tile([0.0, 0.0, 0.1], (3, 1)), np.tile([1.0, 0.0, 0.0], (3, 1)), RATE)
    path = write_imr(tmp_path / "axes.imr", data, WEEK, delta=False)
    rec = np.fromfile(path, dtype=_imr_record_dtype("<"), offset=512)
    assert np.all(rec["ay"] > 0) and np.all(rec["ax"] == 0) and np.all(rec["az"] == 0)  # forward = +y
    assert np.all(rec["gz"] < 0) and np.all(rec["gx"] == 0)  # down = -z
    np.testing.assert_allclose(rec["time"], t - WEEK * 604800.0)


def _write_raw_imr(path, times, counts, endian="<", delta=0, rate=100.0, magic=b"$IMURAW\0"):
    h = np.zeros(1, dtype=_imr_header_dtype(endian))
    h["szHeader"] = magic
    h["bIsIntelOrMotorola"] = 1 if endian == ">" else 0
    h["bDeltaTheta"] = h["bDeltaVelocity"] = delta
    h["dDataRateHz"] = rate
    h["dGyroScaleFactor"], h["dAccelScaleFactor"] = 0.01, 0.001
    h["iUtcOrGpsTime"] = 2
    rec = np.zeros(len(times), dtype=_imr_record_dtype(endian))
    rec["time"] = times
    for k, f in enumerate(("gx", "gy", "gz", "ax", "ay", "az")):
        rec[f] = counts[:, k]
    path.write_bytes(h.tobytes() + rec.tobytes())
    return path


def test_imr_big_endian_and_week_rollover(tmp_path):
    times = np.array([604799.98, 604799.99, 0.0, 0.01])
    counts = np.tile([100, 0, 0, 0, 0, -9810], (4, 1))
    path = _write_raw_imr(tmp_path / "be.imr", times, counts, endian=">")
    data = read_imr(path, gps_week=WEEK)
    np.testing.assert_allclose(data.time_gps - WEEK * 604800.0, [604799.98, 604799.99, 604800.0, 604800.01])
    # gx (right) = 1 deg/s -> FRD y; az (up) = -9.81 -> FRD z = +9.81
    np.testing.assert_allclose(data.gyro[0], [0.0, np.radians(1.0), 0.0])
    np.testing.assert_allclose(data.acc[0], [0.0, 0.0, 9.81])


def test_imr_short_header(tmp_path):
    path = tmp_path / "short.imr"
    path.write_bytes(b"$IMURAW\0" + bytes(100))
    with pytest.raises(InputError, match=r"short\.imr: short IMR header \(expected 512 bytes, found 108 bytes\)"):
        read_imr(path, WEEK)


def test_imr_wrong_magic(tmp_path):
    path = _write_raw_imr(tmp_path / "magic.imr", [1.0], np.zeros((1, 6)), magic=b"$IMUXYZ\0")
    with pytest.raises(InputError, match=r"magic\.imr, field 'szHeader': not an IMR file"):
        read_imr(path, WEEK)


def test_imr_truncated_record(tmp_path):
    path = _write_raw_imr(tmp_path / "trunc.imr", np.arange(5) * 0.01 + 10, np.zeros((5, 6)))
    path.write_bytes(path.read_bytes()[:-7])
    with pytest.raises(InputError) as info:
        read_imr(path, WEEK)
    assert "record 5" in str(info.value) and "truncated record" in str(info.value) and "25 bytes" in str(info.value)


def test_imr_time_not_increasing_names_record(tmp_path):
    path = _write_raw_imr(tmp_path / "t.imr", [10.0, 10.01, 10.01, 10.03], np.zeros((4, 6)))
    with pytest.raises(InputError) as info:
        read_imr(path, WEEK)
    assert "record 3" in str(info.value) and "time repeats" in str(info.value) and "record 2" in str(info.value)


def test_imr_seconds_of_week_need_the_week(tmp_path):
    path = _write_raw_imr(tmp_path / "sow.imr", [10.0, 10.01], np.zeros((2, 6)))
    with pytest.raises(InputError, match="GPS week is needed"):
        read_imr(path)
