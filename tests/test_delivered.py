"""Delivered data: strips georeferenced by a vendor and their SBET, imported and adjusted (docs/ARCHITECTURE.md §4.9).

* ``import-strips`` brings georeferenced strips back to the scanner frame: georeferencing the
  simulated scans with the truth SBET and importing them gives the scans back to the output
  files' resolution.
* The delivered-trajectory adjustment: scans with an SBET whose heading is off by a slowly
  varying error (as an INS/GNSS solution's is) are adjusted with the LiDAR planes; the heading
  error comes down to a fraction, within the posterior sigma's reach.
* Bad delivered data: an SBET not covering the strips, a strip without a CRS, a strip without
  GPS time: one-line errors, exit code 2, nothing written.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest
import yaml

from georefine.adjustment.gnss_imu import GnssImuResult
from georefine.adjustment.observations.prior import RotationPrior
from georefine.adjustment.trajectory_prior import (
    TrajectoryPriorData,
    build_trajectory_prior_problem,
    reference_from_sbet,
    solve_trajectory_prior,
)
from georefine.config import TrajectoryAdjustmentConfig, TrajectoryPriorConfig
from georefine.errors import InputError
from georefine.evaluation.trajectory_files import truth_pass_rmse
from georefine.geometry.frames import LocalFrame
from georefine.geometry.rotation import exp_so3, log_so3
from georefine.io.trajectory import read_sbet, write_sbet
from georefine.sim.scenarios import simulate_project
from georefine.trajectory.spline import KnotGrid
from georefine.workflows import run_georeference
from georefine.workflows.check import inspect_project
from georefine.workflows.import_strips import import_strips
from georefine.workflows.lidar import run_workflow

MDEG = np.radians(1e-3)


# ------------------------------------------------------------------ the problem alone


def _synthetic(seed: int, n_s: float = 60.0, rate: float = 50.0) -> TrajectoryPriorData:
    """A straight, level flight at 50 m/s heading 30°, sampled at ``rate``, with given sigmas."""
    rng = np.random.default_rng(seed)
    frame = LocalFrame.from_degrees(48.0, 11.0, 500.0)
    t = np.arange(0.0, n_s, 1.0 / rate)
    heading = np.radians(30.0)
    v = 50.0 * np.array([np.sin(heading), np.cos(heading), 0.0])
    p = t[:, None] * v + [0.0, 0.0, 300.0] + rng.normal(0, 1e-4, (t.size, 3))
    # body FRD in w (ENU): forward along the track, down = -up
    fwd = v / np.linalg.norm(v)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    R = np.tile(np.column_stack([fwd, right, [0.0, 0.0, -1.0]]), (t.size, 1, 1))
    sp = np.tile([0.03, 0.03, 0.05], (t.size, 1))
    st = np.tile([3 * MDEG, 3 * MDEG, 20 * MDEG], (t.size, 1))
    return TrajectoryPriorData(frame, 0.0, t, p, R, np.tile(v, (t.size, 1)), None, sp, st, rate)


def test_without_other_observations_the_prior_keeps_the_sbet_and_states_its_sigma():
    data = _synthetic(0)
    tcfg = TrajectoryAdjustmentConfig(knot_interval_s=0.2)
    pcfg = TrajectoryPriorConfig(sbet="x", gps_week=0)
    grid = KnotGrid(0.0, 0.2, 300)  # 0 .. 59.8 s, the last sample at 59.98 s is outside: tested as such
    reference, high = reference_from_sbet(data, grid)
    assert high.rms()[0] < 1e-6 and high.rms()[1] < 3e-4  # smooth: only the samples' 0.1 mm noise is faster than the knots
    res = solve_trajectory_prior(build_trajectory_prior_problem(data, pcfg, tcfg, reference))
    p, R = res.spline.pose(data.time[10:-10])
    assert np.abs(p - data.p_w_b[10:-10]).max() < 1e-3
    assert np.abs(np.degrees(log_so3(np.swapaxes(R, 1, 2) @ data.R_w_b[10:-10]))).max() * 1e3 < 0.05
    # The posterior is the prior: the stated sigma (heading 20 mdeg, position 3 cm), to a few per cent.
    mid = res.sigma_time.size // 2
    assert res.sigma_rph_rad[mid, 2] / MDEG == pytest.approx(20.0, rel=0.05)
    assert res.sigma_position_m[mid, 0] == pytest.approx(0.03, rel=0.05)
    assert res.solve.iterations <= 2


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_heading_fix_moves_the_error_process_and_its_sigma_is_consistent(seed):
    """Attitude fixes (as the planes give) every second, 2 mdeg each, against an SBET 25 mdeg off
    in heading: the estimate recovers the offset within 3 sigma, and the sigma is what 60 fixes
    of 2 mdeg and the prior's correlation allow."""
    rng = np.random.default_rng(seed)
    data = _synthetic(seed)
    err = np.radians(25e-3)
    truth_R = data.R_w_b.copy()
    off = dataclasses.replace(data, R_w_b=exp_so3(np.array([0.0, 0.0, err]))[None] @ truth_R)
    tcfg = TrajectoryAdjustmentConfig(knot_interval_s=0.2)
    pcfg = TrajectoryPriorConfig(sbet="x", gps_week=0, correlation_time_s=300.0)
    grid = KnotGrid(0.0, 0.2, 300)  # 0 .. 59.8 s, the last sample at 59.98 s is outside: tested as such
    reference, _ = reference_from_sbet(off, grid)
    built = build_trajectory_prior_problem(off, pcfg, tcfg, reference)
    knots = np.arange(2, grid.n_knots - 2, 5)
    fixes = exp_so3(rng.normal(0, 2 * MDEG, (knots.size, 3))) @ truth_R[np.searchsorted(data.time, grid.knot_times[knots])]
    # RotationPrior is body-frame: Log(R0^T R) ~ N(0, sigma^2)
    built.problem.add_group(RotationPrior("fixes", built.blocks.attitude, knots, fixes, 2 * MDEG))
    res: GnssImuResult = solve_trajectory_prior(built)
    e = res.sbet_errors
    mid = e.grid.n_knots // 2
    assert -e.attitude_rad[mid, 2] / MDEG == pytest.approx(25.0, abs=3.0)  # the error process took the offset
    # The adjusted heading against the truth, in the middle 40 s, and its posterior sigma there.
    _, R = res.spline.pose(data.time[500:2500])
    d = np.degrees(log_so3(np.swapaxes(truth_R[500:2500], 1, 2) @ R)) * 1e3
    sig = float(np.median(res.sigma_rph_rad[(res.sigma_time > 10) & (res.sigma_time < 50), 2])) / MDEG
    assert 0.2 < sig < 2.0, sig  # far below the prior's 20 mdeg, not below what 60 fixes of 2 mdeg give
    assert abs(np.mean(d[:, 2])) < 3 * sig, (np.mean(d[:, 2]), sig)
    assert np.sqrt(np.mean(d[:, 2] ** 2)) < 3 * sig + 1.0, (np.sqrt(np.mean(d[:, 2] ** 2)), sig)


# ------------------------------------------------------------------ import and adjust, end to end


@pytest.fixture(scope="module")
def project(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("delivered") / "p"
    simulate_project("corridor-tiny", out, seed=11)
    return out


@pytest.fixture(scope="module")
def delivered_files(project, tmp_path_factory) -> Path:
    """The scans georeferenced with the truth SBET, as a vendor delivers them (``pts/strip_*.laz``): read only."""
    d = tmp_path_factory.mktemp("vendor")
    run_georeference(project, project / "truth" / "trajectory.sbet", d / "pts")
    return d


def _scanner(project: Path) -> dict:
    return yaml.safe_load((project / "project.yaml").read_text())["scanner"]


def test_imported_strips_are_the_scans_to_the_files_resolution(project, delivered_files, tmp_path):
    sc = _scanner(project)
    files = sorted((delivered_files / "pts").glob("strip_*.laz"))
    assert [f.name for f in files] == ["strip_1.laz", "strip_2.laz"]
    res = import_strips(files, project / "truth" / "trajectory.sbet", tmp_path / "imp",
                        lever_arm_m=tuple(sc["lever_arm_m"]), boresight_deg=tuple(sc["boresight_deg"]))
    assert res.epsg == 25832 and res.strip_ids == (1, 2)
    for f in ("strip_1.laz", "strip_2.laz"):
        a, b = laspy.read(project / "scans" / f), laspy.read(tmp_path / "imp" / "scans" / f)
        assert len(a) == len(b)
        d = np.column_stack([a.x - b.x, a.y - b.y, a.z - b.z])
        assert np.abs(d).max() < 0.0011  # the georeferenced files hold millimetres
        assert np.array_equal(a.gps_time, b.gps_time) and np.array_equal(a.scanner_channel, b.scanner_channel)
        assert np.array_equal(a.point_source_id, b.point_source_id)
    cfg = yaml.safe_load((tmp_path / "imp" / "project.yaml").read_text())
    assert cfg["trajectory"]["sbet"] == "nav/trajectory.sbet" and "gnss" not in cfg and "imu" not in cfg
    # `georefine check` reads the delivered project with the workflow's readers.
    summary = inspect_project(tmp_path / "imp")
    assert summary.delivered[0] > 1000 and not summary.warnings
    assert "delivered trajectory" in summary.summary() and "GNSS:" not in summary.summary()


def _sbet_with_heading_error(project: Path, dest: Path) -> None:
    """The truth SBET with the heading 30 mdeg off plus a 10 mdeg-per-minute drift, roll 3 mdeg off."""
    truth = read_sbet(project / "truth" / "trajectory.sbet", gps_week=_week(project))
    t = truth.time_gps - truth.time_gps[0]
    bad = dataclasses.replace(truth, heading_rad=truth.heading_rad + (30 + 10 * t / 60) * MDEG,
                              roll_rad=truth.roll_rad + 3 * MDEG)
    write_sbet(dest, bad, time_scale="week")


def _week(project: Path) -> int:
    from georefine.io.las import gps_week_of_strip

    return gps_week_of_strip(project / "scans" / "strip_1.laz")


@pytest.mark.slow
def test_the_planes_correct_a_delivered_heading_error(project, tmp_path):
    delivered = tmp_path / "d"
    (delivered / "nav").mkdir(parents=True)
    (delivered / "scans").symlink_to(project / "scans")
    _sbet_with_heading_error(project, delivered / "nav" / "sbet.out")
    sc = _scanner(project)
    (delivered / "project.yaml").write_text(yaml.safe_dump({
        "crs": {"output_epsg": 25832},
        "trajectory": {"sbet": "nav/sbet.out", "gps_week": _week(project), "default_sigma_heading_deg": 0.05},
        "scanner": {k: sc[k] for k in ("files", "lever_arm_m", "boresight_deg")},
        # One outer iteration, no time offset search: the heading is what this test is about (the
        # raw workflow's tests cover the iterations and the search).
        "processing": {"lidar": {"outer_iterations": 1, "time_offset": {"search": False}}},
    }))
    result = run_workflow(delivered, tmp_path / "run", strips=[1], points=False)  # one pass: its three views suffice
    for strip in (1,):
        before = truth_pass_rmse(tmp_path / "run" / "gi" / "trajectory.sbet", project, strip)
        after = truth_pass_rmse(tmp_path / "run" / "gil" / "trajectory.sbet", project, strip)
        assert before[2] > 25.0, before
        assert after[2] < 0.25 * before[2], (strip, before, after)
        assert after[0] < before[0], (strip, before, after)
    gil = result.gil.result
    assert gil.imu_errors is None and gil.sbet_errors is not None
    # Consistency: the heading error left is within three posterior sigmas plus 2 mdeg of GNSS-free
    # modelling (the planes see features, not the trajectory's every wiggle).
    sigma_h = float(np.median(np.degrees(gil.sigma_rph_rad[:, 2]) * 1e3))
    assert after[2] < 3 * sigma_h + 2.0, (after, sigma_h)


# ------------------------------------------------------------------ bad delivered data


def _georefine(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "georefine", *args], cwd=cwd, capture_output=True, text=True,
                          env=dict(os.environ, COLUMNS="300"), timeout=600)


def _refused(proc, *words):
    assert proc.returncode == 2, proc.stdout + proc.stderr
    line = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else proc.stderr
    for w in words:
        assert w in line, line


def test_an_sbet_not_covering_the_strips_is_refused(delivered_files, project, tmp_path):
    truth = read_sbet(project / "truth" / "trajectory.sbet", gps_week=_week(project))
    keep = truth.time_gps < truth.time_gps[0] + 0.5 * (truth.time_gps[-1] - truth.time_gps[0])
    short = tmp_path / "short.out"
    write_sbet(short, type(truth)(*(getattr(truth, f.name)[keep] for f in dataclasses.fields(truth))))
    proc = _georefine(tmp_path, "import-strips", str(delivered_files / "pts" / "strip_1.laz"),
                      str(delivered_files / "pts" / "strip_2.laz"), "--sbet", str(short), "--lever-arm", "0,0,0",
                      "--out", "imp")
    _refused(proc, "strip_2.laz", "the SBET does not cover the strip", "gps_time")
    assert not (tmp_path / "imp").exists()


def test_a_strip_without_crs_or_gps_time_is_refused(delivered_files, project, tmp_path):
    las = laspy.read(delivered_files / "pts" / "strip_1.laz")
    no_crs = laspy.LasData(laspy.LasHeader(point_format=6, version="1.4"))
    no_crs.header.scales, no_crs.header.offsets = las.header.scales, las.header.offsets
    no_crs.x, no_crs.y, no_crs.z, no_crs.gps_time = las.x[:100], las.y[:100], las.z[:100], las.gps_time[:100]
    no_crs.header.global_encoding.gps_time_type = las.header.global_encoding.gps_time_type
    no_crs.write(tmp_path / "no_crs.laz")
    no_time = laspy.LasData(laspy.LasHeader(point_format=2, version="1.2"))
    no_time.header.scales, no_time.header.offsets = las.header.scales, las.header.offsets
    no_time.x, no_time.y, no_time.z = las.x[:100], las.y[:100], las.z[:100]
    no_time.write(tmp_path / "no_time.las")
    sbet = str(project / "truth" / "trajectory.sbet")
    for name, words in (("no_crs.laz", ("no_crs.laz", "states no CRS")),
                        ("no_time.las", ("no_time.las", "no GPS time", "point_format"))):
        proc = _georefine(tmp_path, "import-strips", name, "--sbet", sbet, "--lever-arm", "0,0,0",
                          "--gps-week", str(_week(project)), "--out", "imp")
        _refused(proc, *words)
        assert not (tmp_path / "imp").exists()
    with pytest.raises(InputError, match="comma-separated"):
        from georefine.cli import _vector3

        _vector3("1,2", "--lever-arm")


def test_with_the_raw_imu_the_sbet_positions_and_the_imu_observe_the_trajectory(project, delivered_files, tmp_path):
    """`import-strips --imu`: the SBET's positions stand in for the GNSS (gnss.format: sbet), the raw
    IMU rebuilds the attitude; with the truth SBET's positions the G/I heading is as good as the raw
    GNSS gives it, and the SBET's attitude is not used (a heading error in it changes nothing)."""
    cfg = yaml.safe_load((project / "project.yaml").read_text())
    (tmp_path / "imu.yaml").write_text(yaml.safe_dump(dict(cfg["imu"], file=str(project / cfg["imu"]["file"]))))
    sbet = tmp_path / "sbet.out"
    _sbet_with_heading_error(project, sbet)  # the attitude is not used: a wrong heading must not matter
    sc = _scanner(project)
    files = sorted((delivered_files / "pts").glob("strip_*.laz"))
    # The strips were georeferenced with the truth SBET: import them with it, then swap in the wrong one.
    import_strips(files, project / "truth" / "trajectory.sbet", tmp_path / "imp", lever_arm_m=tuple(sc["lever_arm_m"]),
                  boresight_deg=tuple(sc["boresight_deg"]), imu=tmp_path / "imu.yaml")
    (tmp_path / "imp" / "nav" / "trajectory.sbet").write_bytes(sbet.read_bytes())
    written = yaml.safe_load((tmp_path / "imp" / "project.yaml").read_text())
    assert written["gnss"]["format"] == "sbet" and written["imu"]["file"] == "imu/" + Path(cfg["imu"]["file"]).name
    assert "trajectory" not in written
    summary = inspect_project(tmp_path / "imp")
    assert summary.gnss_epochs > 1000 and summary.imu_samples > 10_000
    result = run_workflow(tmp_path / "imp", tmp_path / "run", lidar=False, points=False)
    assert result.gi.imu_errors is not None  # a raw G/I adjustment
    for strip in (1, 2):
        rmse = truth_pass_rmse(tmp_path / "run" / "gi" / "trajectory.sbet", project, strip)
        assert rmse[2] < 20.0 and np.all(rmse[:2] < 5.0), (strip, rmse)  # the SBET's 30+ mdeg heading error is gone
