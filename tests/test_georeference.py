"""Georeferencing strips with a trajectory file: accuracy against the truth, no extrapolation."""

import shutil
from pathlib import Path

import laspy
import numpy as np
import pytest
import yaml

from georefine.errors import InputError
from georefine.io.trajectory import read_sbet, write_sbet
from georefine.sim.scenarios import simulate_project
from georefine.workflows import run_georeference


@pytest.fixture(scope="module")
def project(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("geo") / "p"
    simulate_project("corridor-tiny", out, seed=4, overrides=["scanner.pulse_rate_hz=5000"])
    return out


def test_georeferencing_with_the_true_trajectory_reproduces_the_truth(project, tmp_path):
    res = run_georeference(project, project / "truth" / "trajectory.sbet", tmp_path / "pts")
    assert [s.points_outside for s in res.strips] == [0, 0]
    for s in res.strips:
        est = laspy.read(s.output)
        truth = laspy.read(project / "truth" / s.output.name)
        assert est.header.point_format.id == 6 and est.header.global_encoding.gps_time_type
        assert est.header.parse_crs() is not None
        np.testing.assert_array_equal(est.gps_time, truth.gps_time)
        np.testing.assert_array_equal(est.scanner_channel, truth.scanner_channel)
        d = np.column_stack([est.x - truth.x, est.y - truth.y, est.z - truth.z])
        assert np.abs(d).max() < 1.5e-3  # 1 mm output resolution


def test_points_outside_the_trajectory_are_left_out_and_counted(project, tmp_path):
    first = laspy.read(project / "scans" / "strip_1.laz").gps_time[0] + 1e9
    week = int(first // 604800)
    sbet = read_sbet(project / "truth" / "trajectory.sbet", gps_week=week)
    # Cut the trajectory in the middle of the first pass.
    t_cut = np.median(laspy.read(project / "scans" / "strip_1.laz").gps_time) + 1e9
    keep = sbet.time_gps <= t_cut
    from dataclasses import replace

    short = replace(
        sbet, **{f: getattr(sbet, f)[keep] for f in (
            "time_gps", "lat_rad", "lon_rad", "h_m", "velocity_wander", "roll_rad", "pitch_rad", "heading_rad",
            "wander_rad", "accel_b", "angular_rate_b")}
    )
    write_sbet(tmp_path / "short.sbet", short, time_scale="gps")
    # The whole second pass is outside: an error naming it, not an empty file called success.
    with pytest.raises(InputError, match=r"strip_2.laz, field 'gps_time': no point of the strip lies inside"):
        run_georeference(project, tmp_path / "short.sbet", tmp_path / "pts", gps_week=week)
    assert not (tmp_path / "pts").exists()
    # The first pass alone: the points after the cut are left out and counted.
    one = tmp_path / "one"
    shutil.copytree(project, one, ignore=shutil.ignore_patterns("truth"))
    cfg = yaml.safe_load((one / "project.yaml").read_text())
    cfg["scanner"]["files"] = ["scans/strip_1.laz"]
    (one / "project.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    res = run_georeference(one, tmp_path / "short.sbet", tmp_path / "pts", gps_week=week)
    (s1,) = res.strips
    n1 = laspy.open(project / "scans" / "strip_1.laz").header.point_count
    assert 0.3 * n1 < s1.points_outside < 0.7 * n1 and s1.points_written + s1.points_outside == n1
    assert "outside the trajectory" in res.summary()


def test_fused_kernel_matches_exact_slerp_and_the_numpy_blend():
    """The numba loop equals the numpy nlerp (to rounding) and exact SLERP (to 1e-9 m at 300 m)."""
    from georefine.geometry.rotation import R_n_b_from_rph
    from georefine.lidar.georeference import PoseInterpolator, georeference
    from georefine.trajectory.sampled import Trajectory

    rng = np.random.default_rng(3)
    tt = np.arange(0.0, 20.0, 0.005)  # 200 Hz, aircraft-like rates (several deg/s)
    R = R_n_b_from_rph(0.2 * np.sin(tt), 0.05 * np.cos(2 * tt), 0.3 * tt)
    traj = Trajectory(tt, np.column_stack([60.0 * tt, np.sin(tt), 500.0 + 0.1 * tt]), R)
    t = np.sort(rng.uniform(0.0, tt[-1], 20_000))
    x_s = rng.normal(size=(t.size, 3)) * 300.0
    R_b_s, p_b_s = R_n_b_from_rph(0.01, -0.02, 0.03), np.array([0.1, -0.2, 0.3])
    interp = PoseInterpolator(traj)
    fast = georeference(t, x_s, interp, p_b_s, R_b_s)
    p, R_w_b = interp(t)
    blend = p + np.einsum("nij,nj->ni", R_w_b, x_s @ R_b_s.T + p_b_s)
    np.testing.assert_allclose(fast, blend, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fast, georeference(t, x_s, traj, p_b_s, R_b_s), rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="outside the trajectory span"):
        georeference(np.array([tt[-1] + 1.0]), x_s[:1], interp, p_b_s, R_b_s)
