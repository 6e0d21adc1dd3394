"""End-to-end checks of a simulated project folder: physics, real file formats, truth, bad input.

One ``corridor-tiny`` project with an ideal IMU and ideal GNSS is simulated per test session, with a
sparse scanner (20 kHz at 60 lines/s instead of the scenario's 100 kHz at 120): these checks do not
depend on the point density, and a fifth of the points keeps the session quick.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import laspy
import numpy as np
import pytest
import yaml

from cli_helpers import run_georefine as _georefine
from georefine.geometry import earth
from georefine.geometry.frames import LocalFrame
from georefine.geometry.rotation import log_so3
from georefine.io.imu import read_imr, read_imu_csv
from georefine.io.trajectory import read_sbet, read_sbet_companion
from georefine.sim.scenarios import simulate_project
from georefine.sim.verify import verify_project
from georefine.trajectory.sampled import trajectory_from_sbet
from georefine.trajectory.strapdown import integrate

SPARSE_SCAN = ["scanner.pulse_rate_hz=20000", "scanner.line_rate_hz=60"]


@pytest.fixture(scope="session")
def ideal_project(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "tiny"
    simulate_project("corridor-tiny", out, seed=11, imu_grade="ideal", gnss_grade="ideal", overrides=SPARSE_SCAN)
    return out


def _truth(project: Path):
    truth = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())
    t0 = truth["t0_gps"]
    week = int(t0 // 604800)
    sbet = read_sbet(project / "truth" / "trajectory.sbet", gps_week=week)
    frame = LocalFrame(float(sbet.lat_rad[0]), float(sbet.lon_rad[0]), float(sbet.h_m[0]))
    return truth, t0, sbet, frame


def test_strapdown_of_ideal_imu_reproduces_the_true_trajectory(ideal_project):
    """60 s of free inertial navigation from the true initial state: < 5 cm and < 1 mdeg."""
    truth, t0, sbet, frame = _truth(ideal_project)
    traj = trajectory_from_sbet(sbet, frame, t0)
    imu = read_imu_csv(ideal_project / "imu" / "imu.csv")
    t_imu = imu.time_gps - t0
    np.testing.assert_allclose(t_imu, traj.time, atol=1e-6)  # same sample times
    manoeuvre = next(p for p in truth["phases"] if p["name"] == "manoeuvre")
    k0 = int(np.searchsorted(t_imu, manoeuvre["t_start_s"] + 10.0))
    k1 = int(np.searchsorted(t_imu, t_imu[k0] + 60.0)) + 1
    sl = slice(k0, k1)
    res = integrate(frame, t_imu[sl], imu.gyro[sl], imu.acc[sl], traj.p_w_b[k0], traj.v_w_b[k0], traj.R_w_b[k0])
    pos_err = np.linalg.norm(res.p_w_b - traj.p_w_b[sl], axis=1)
    att_err = np.degrees(np.linalg.norm(log_so3(np.swapaxes(res.R_w_b, 1, 2) @ traj.R_w_b[sl]), axis=1)) * 1e3
    assert t_imu[k1 - 1] - t_imu[k0] >= 60.0
    assert pos_err.max() < 0.05, f"position error {pos_err.max():.4f} m"
    assert att_err.max() < 1.0, f"attitude error {att_err.max():.4f} mdeg"


def test_stationary_ideal_imu_reads_normal_gravity_and_earth_rate(ideal_project):
    truth, t0, sbet, frame = _truth(ideal_project)
    static = next(p for p in truth["phases"] if p["name"] == "static")
    imu = read_imu_csv(ideal_project / "imu" / "imu.csv")
    at_rest = (imu.time_gps - t0) < static["t_end_s"] - 0.5
    assert at_rest.sum() > 100
    g = earth.normal_gravity(sbet.lat_rad[0], sbet.h_m[0])
    np.testing.assert_allclose(np.linalg.norm(imu.acc[at_rest], axis=1), g, rtol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(imu.gyro[at_rest], axis=1), earth.OMEGA_IE, rtol=1e-6)
    # Direction: the specific force at rest points up, i.e. -g in the body frame.
    traj = trajectory_from_sbet(sbet, frame, t0)
    g_b = np.einsum("nji,nj->ni", traj.R_w_b[at_rest], frame.gravity_w(traj.p_w_b[at_rest]))
    np.testing.assert_allclose(imu.acc[at_rest], -g_b, atol=1e-8)


def test_scan_files_are_real_las14(ideal_project):
    for name in ("strip_1.laz", "strip_2.laz"):
        las = laspy.read(ideal_project / "scans" / name)
        h = las.header
        assert (h.version.major, h.version.minor) == (1, 4)
        assert h.point_format.id >= 6
        assert h.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD
        np.testing.assert_allclose(h.scales, 1e-4)
        assert set(np.unique(las.scanner_channel)) == {0, 1, 2}
        assert set(np.unique(las.point_source_id)) == {int(name[6])}
        # Adjusted standard GPS time: GPS seconds - 1e9, a few hundred million in 2024.
        assert 3e8 < las.gps_time.min() < 5e8
        r = np.linalg.norm(np.column_stack([las.x, las.y, las.z]), axis=1)
        assert 100 < np.median(r) < 400  # scanner frame: ranges, not map coordinates
        truth = laspy.read(ideal_project / "truth" / name)
        assert truth.header.parse_crs().to_epsg() in (25832, None)
        assert "range_error_m" in truth.point_format.extra_dimension_names
        np.testing.assert_array_equal(truth.gps_time, las.gps_time)
        assert 6e5 < np.median(truth.x) < 8e5 and 5.1e6 < np.median(truth.y) < 5.2e6


def test_pos_file_follows_rtklib_layout(ideal_project):
    lines = (ideal_project / "gnss" / "rover.pos").read_text().splitlines()
    header = [l for l in lines if l.startswith("%")]
    data = [l for l in lines if not l.startswith("%")]
    assert any("GPST" in l and "latitude(deg)" in l and "sdun(m)" in l and "ratio" in l for l in header)
    fields = data[0].split()
    # date time lat lon h Q ns sdn sde sdu sdne sdeu sdun age ratio
    assert len(fields) == 15
    assert fields[0].count("/") == 2 and fields[1].count(":") == 2
    assert fields[5] == "1"


def test_sbet_is_17_doubles_per_record(ideal_project):
    path = ideal_project / "truth" / "trajectory.sbet"
    raw = np.fromfile(path, dtype="<f8")
    assert path.stat().st_size % 136 == 0
    rec = raw.reshape(-1, 17)
    assert np.all(rec[:, 0] < 604800)  # seconds of week
    assert np.all(np.abs(rec[:, 1]) < np.pi / 2) and np.all(rec[:, 10] == 0.0)  # lat rad, wander 0
    imu = read_imu_csv(ideal_project / "imu" / "imu.csv")
    assert rec.shape[0] == imu.time_gps.size  # at IMU rate
    np.testing.assert_allclose(rec[:, 11:14], imu.acc, atol=1e-9)  # body specific force
    np.testing.assert_allclose(rec[:, 14:17], imu.gyro, atol=1e-12)  # body angular rate
    companion = read_sbet_companion(path)  # truth/trajectory.sbet.json: the week, as beside a run's SBETs
    assert companion.gps_week == int(imu.time_gps[0] // 604800) and companion.output_epsg == 25832
    np.testing.assert_allclose(read_sbet(path).time_gps, imu.time_gps, rtol=0, atol=1e-6)


def test_scans_georeferenced_with_true_trajectory_reproduce_truth(ideal_project):
    result = verify_project(ideal_project)
    assert set(result.strips) == {"strip_1.laz", "strip_2.laz"}
    assert result.max_error_m < 1e-3


def test_same_seed_same_files_on_any_scheduler_and_imr_matches_csv(tmp_path):
    """The scan chunks simulated one after the other here and as tasks on two worker processes
    give the same files, byte for byte."""
    args = dict(seed=5, overrides=["flight.passes=1", "scanner.pulse_rate_hz=5000"], write_imr=True)
    simulate_project("corridor-tiny", tmp_path / "a", **args)
    simulate_project("corridor-tiny", tmp_path / "b", scheduler="processes", **args)
    for rel in ("gnss/rover.pos", "imu/imu.csv", "imu/imu.imr", "scans/strip_1.laz", "truth/strip_1.laz",
                "reference/surfaces.csv"):
        assert (tmp_path / "a" / rel).read_bytes() == (tmp_path / "b" / rel).read_bytes(), rel
    assert not (tmp_path / "a" / "scans" / "strip_2.laz").exists()
    cfg = yaml.safe_load((tmp_path / "a" / "truth" / "scenario.yaml").read_text())["scenario"]
    assert cfg["flight"]["passes"] == 1 and cfg["scanner"]["pulse_rate_hz"] == 5000
    csv = read_imu_csv(tmp_path / "a" / "imu" / "imu.csv")
    imr = read_imr(tmp_path / "a" / "imu" / "imu.imr", gps_week=int(csv.time_gps[0] // 604800))
    np.testing.assert_allclose(imr.time_gps, csv.time_gps, atol=1e-6)
    np.testing.assert_allclose(imr.gyro, csv.gyro, atol=1e-7)  # int32 quantisation
    np.testing.assert_allclose(imr.acc, csv.acc, atol=1e-6)


# ------------------------------------------------------------------------------ bad input




def _copy_project(src: Path, dst: Path, modify: str) -> Path:
    """Copy a project by symlinks, except the one file ``modify`` which is copied for editing."""
    for path in src.rglob("*"):
        rel = path.relative_to(src)
        target = dst / rel
        if path.is_dir():
            target.mkdir(parents=True, exist_ok=True)
        elif str(rel) == modify:
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(path, target)
        else:
            target.parent.mkdir(parents=True, exist_ok=True)
            target.symlink_to(path)
    return dst / modify


def test_check_accepts_the_simulated_project(ideal_project):
    run = _georefine("check", str(ideal_project))
    assert run.returncode == 0, run.stderr
    assert "strip_1.laz" in run.stdout and "GNSS" in run.stdout


def test_truncated_laz_is_reported_with_exit_code_2(ideal_project, tmp_path):
    f = _copy_project(ideal_project, tmp_path / "p", "scans/strip_2.laz")
    data = f.read_bytes()
    f.write_bytes(data[: len(data) // 2])
    run = _georefine("check", str(tmp_path / "p"))
    assert run.returncode == 2
    assert "strip_2.laz" in run.stderr and "Traceback" not in run.stderr


def test_malformed_pos_line_is_reported_with_line_and_field(ideal_project, tmp_path):
    f = _copy_project(ideal_project, tmp_path / "p", "gnss/rover.pos")
    lines = f.read_text().splitlines()
    k = next(i for i, l in enumerate(lines) if not l.startswith("%")) + 10
    fields = lines[k].split()
    fields[3] = "11.65x"  # longitude
    lines[k] = "  ".join(fields)
    f.write_text("\n".join(lines) + "\n")
    run = _georefine("check", str(tmp_path / "p"))
    assert run.returncode == 2
    assert "rover.pos" in run.stderr and f"line {k + 1}" in run.stderr and "longitude" in run.stderr


def test_non_monotonic_imu_time_is_reported_with_line(ideal_project, tmp_path):
    f = _copy_project(ideal_project, tmp_path / "p", "imu/imu.csv")
    lines = f.read_text().splitlines()
    lines[501], lines[502] = lines[502], lines[501]
    f.write_text("\n".join(lines) + "\n")
    run = _georefine("check", str(tmp_path / "p"))
    assert run.returncode == 2
    assert "imu.csv" in run.stderr and "line 503" in run.stderr and "time" in run.stderr


def test_unknown_key_in_project_yaml_is_reported(ideal_project, tmp_path):
    f = _copy_project(ideal_project, tmp_path / "p", "project.yaml")
    data = yaml.safe_load(f.read_text())
    data["scanner"]["lever_arm"] = [0, 0, 0]
    f.write_text(yaml.safe_dump(data, sort_keys=False))
    run = _georefine("check", str(tmp_path / "p"))
    assert run.returncode == 2
    assert "project.yaml" in run.stderr and "scanner.lever_arm" in run.stderr and "unknown key" in run.stderr


def test_simulate_refuses_non_empty_output_and_bad_override(tmp_path):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("keep")
    run = _georefine("simulate", "corridor-tiny", "--out", str(tmp_path / "full"))
    assert run.returncode == 2 and "not empty" in run.stderr
    assert (tmp_path / "full" / "x").read_text() == "keep"
    run = _georefine("simulate", "corridor-tiny", "--out", str(tmp_path / "new"), "--set", "flight.speed=20")
    assert run.returncode == 2 and "flight.speed" in run.stderr and "unknown key" in run.stderr
    assert not (tmp_path / "new").exists()
    assert not any(p.name.startswith(".new") for p in tmp_path.iterdir())  # nothing half-written
