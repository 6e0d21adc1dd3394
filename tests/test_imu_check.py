"""Units, axes and signs of the IMU record against the GNSS trajectory (``georefine check``, every workflow)."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import messages
from cli_helpers import run_georefine as _georefine
from georefine.config import load_project
from georefine.geometry.earth import normal_gravity
from georefine.geometry.frames import LocalFrame
from georefine.io.gnss import gnss_in_w
from georefine.sim.scenarios import simulate_project
from georefine.trajectory.imu_check import check_imu_frame, signed_permutations
from georefine.workflows.project import read_project_gnss, read_project_imu

FAST_SCAN = ["scanner.pulse_rate_hz=2000", "scanner.line_rate_hz=100"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("imucheck") / "tiny"
    simulate_project("corridor-tiny", out, seed=31, overrides=FAST_SCAN)
    return out


@pytest.fixture(scope="module")
def record(tiny):
    cfg = load_project(tiny)
    gnss, imu = read_project_gnss(tiny, cfg), read_project_imu(tiny, cfg)
    lat, lon, h = (a[0] for a in gnss.geodetic())
    frame = LocalFrame(float(lat), float(lon), float(h))
    t0 = float(np.floor(imu.time_gps[0]))
    gt, gp, _ = gnss_in_w(frame, t0, gnss)
    return imu.time_gps - t0, imu.gyro, imu.acc, gt, gp, float(normal_gravity(frame.lat0_rad, frame.h0_m))


def _check(record, gyro=None, acc=None):
    t, g, a, gt, gp, grav = record
    return check_imu_frame(t, g if gyro is None else gyro, a if acc is None else acc, gt, gp, grav)


def test_signed_permutations():
    P = signed_permutations()
    assert P.shape == (48, 3, 3) and np.array_equal(P[0], np.eye(3))
    assert len({p.tobytes() for p in P}) == 48
    assert np.allclose(np.abs(np.linalg.det(P)), 1.0)


def test_a_clean_record_passes(record):
    assert _check(record) is None


@pytest.mark.parametrize("name, transform, field, words", [
    ("deg/s", lambda g: np.degrees(g), "gyro_x, gyro_y, gyro_z", "look like deg/s"),
    ("x<->y", lambda g: g[:, [1, 0, 2]], "gyro_x, gyro_y", "gyro_x and gyro_y look swapped"),
    ("y<->z", lambda g: g[:, [0, 2, 1]], "gyro_y, gyro_z", "gyro_y and gyro_z look swapped"),
    ("-x", lambda g: g * [-1, 1, 1], "gyro_x", "gyro_x looks like it has the wrong sign"),
    ("-z", lambda g: g * [1, 1, -1], "gyro_z", "gyro_z looks like it has the wrong sign"),
])
def test_gyro_faults_are_named(record, name, transform, field, words):
    f = _check(record, gyro=transform(record[1]))
    assert f is not None, name
    assert f.field == field and words in f.message, f
    residual_read, residual_best = (float(x) for x in f.found.split("residual ")[1].replace(" m/s as read,", "")
                                    .replace(" m/s so read)", "").split())
    assert residual_read > 10 * residual_best, f.found  # metres per second against a tenth


@pytest.mark.parametrize("name, transform, field, words", [
    ("acc in g", lambda a: a / 9.80665, "acc_x, acc_y, acc_z", "look like g"),
    ("-acc_z", lambda a: a * [1, 1, -1], "acc_z", "not along the body's down axis"),
    ("acc z<->x", lambda a: a[:, [2, 1, 0]], "acc_x, acc_z", "not along the body's down axis"),
    ("-acc_x", lambda a: a * [-1, 1, 1], "acc_x, acc_y, acc_z", "do not agree"),
])
def test_accelerometer_faults_are_named(record, name, transform, field, words):
    f = _check(record, acc=transform(record[2]))
    assert f is not None, name
    assert field in f.field and words in f.message, f




def test_check_and_trajectory_refuse_a_gyro_in_deg_per_s_in_seconds(tiny, tmp_path):
    p = tmp_path / "p"
    shutil.copytree(tiny, p, ignore=shutil.ignore_patterns("truth"))
    csv = p / "imu" / "imu.csv"
    lines = csv.read_text().splitlines()
    rows = []
    for line in lines[1:]:
        f = line.split(",")
        rows.append(",".join([f[0], *(f"{np.degrees(float(x)):.10e}" for x in f[1:4]), *f[4:]]))
    csv.write_text("\n".join([lines[0], *rows]) + "\n")
    t = time.perf_counter()
    check = _georefine("check", str(p))
    elapsed = time.perf_counter() - t
    run = _georefine("trajectory", str(p), "--out", str(tmp_path / "o"))
    for r in (check, run):
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        assert messages(r.stderr).strip().count("\n") == 0
        assert "imu.csv" in r.stderr and "field 'gyro_x, gyro_y, gyro_z'" in r.stderr and "deg/s" in r.stderr
        assert "expected rad/s" in r.stderr
    assert messages(check.stderr) == messages(run.stderr)  # one rule, one message
    assert elapsed < 10.0
    assert not (tmp_path / "o").exists()
