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
        # scan angles with the roll, as the simulator's true beams give them, to a 0.006 deg step
        assert np.abs(est.scan_angle.astype(int) - truth.scan_angle).max() <= 1
        assert est.scan_angle.min() * 0.006 < -45 and est.scan_angle.max() * 0.006 > 45
        # one strip per file: its id is the file source ID, in the scan file as well
        sid = int(s.output.stem.split("_")[1])
        assert est.header.file_source_id == truth.header.file_source_id == sid
        with laspy.open(project / "scans" / s.output.name) as scan:
            assert scan.header.file_source_id == sid


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
    # Points and directions in one pass (the time offset search's features): the same blend.
    d_b = rng.normal(size=(t.size, 3))
    x_w, d_w = interp.transform_with_directions(t, x_s, d_b)
    np.testing.assert_allclose(x_w, p + np.einsum("nij,nj->ni", R_w_b, x_s), rtol=0, atol=1e-9)
    np.testing.assert_allclose(d_w, np.einsum("nij,nj->ni", R_w_b, d_b), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(x_w, interp.transform(t, x_s))


def test_scan_angle_left_negative_right_positive_with_the_roll():
    """LAS scan angle on a constructed flight: heading 30 deg, roll and pitch, beams of a nadir and
    a forward-tilted view; the angle from the local vertical across the track, positive right."""
    from georefine.geometry.frames import LocalFrame
    from georefine.lidar.georeference import PoseInterpolator, georeference, scan_angles_deg
    from georefine.trajectory.sampled import Trajectory

    frame = LocalFrame.from_degrees(48.2, 11.3, 500.0)
    heading = np.radians(30.0)
    tt = np.linspace(0.0, 1.0, 201)
    for roll_deg, pitch_deg in ((0.0, 0.0), (4.0, 0.0), (-6.0, 0.0), (5.0, 3.0)):
        roll, pitch = np.radians(roll_deg), np.radians(pitch_deg)
        p = np.column_stack([np.sin(heading) * 50 * tt, np.cos(heading) * 50 * tt, np.full(tt.size, 300.0)])
        R = frame.R_w_b_from_rph(p, np.tile([roll, pitch, heading], (tt.size, 1)))
        traj = Trajectory(tt, p, R)
        alpha = np.radians(np.linspace(-50.0, 50.0, 41))
        t = np.full(alpha.size, 0.5)
        for tau in (0.0, np.radians(10.0)):
            x_s = 300.0 * np.column_stack([np.full(alpha.size, np.sin(tau)), np.cos(tau) * np.sin(alpha),
                                           np.cos(tau) * np.cos(alpha)])
            x_w = georeference(t, x_s, traj, np.zeros(3), np.eye(3))
            lat, lon, _ = frame.to_geodetic(x_w)
            up = frame.up_w(lat, lon)
            got = scan_angles_deg(t, x_s, PoseInterpolator(traj), np.eye(3), up)
            np.testing.assert_allclose(got, scan_angles_deg(t, x_s, traj, np.eye(3), up), atol=1e-6)
            # body frame -> level frame along the heading: right = cos(tau) sin(alpha - roll),
            # down = -sin(pitch) sin(tau) + cos(pitch) cos(tau) cos(alpha - roll)
            want = np.degrees(np.arctan2(np.cos(tau) * np.sin(alpha - roll),
                                         -np.sin(pitch) * np.sin(tau) + np.cos(pitch) * np.cos(tau) * np.cos(alpha - roll)))
            # the local vertical at the point, 300 m off the body, tilts by < 0.003 deg
            np.testing.assert_allclose(got, want, atol=0.004, err_msg=f"roll {roll_deg}, pitch {pitch_deg}, tau {tau}")
            if pitch == 0.0:  # the level case: alpha - roll exactly
                np.testing.assert_allclose(got, np.degrees(alpha - roll), atol=0.004)
                # a right-wing-down roll turns the nadir beam to the left: negative
                assert got[alpha.size // 2] == pytest.approx(-roll_deg, abs=0.004)
            # the sign is the side of the track the point lies on (right of a 30 deg heading: east-south-east)
            p_w = traj.interpolate(t)[0]
            right_w = np.array([np.cos(heading), -np.sin(heading), 0.0])
            side = (x_w - p_w) @ right_w
            off = np.abs(side) > 1.0
            np.testing.assert_array_equal(np.sign(got[off]), np.sign(side[off]))
