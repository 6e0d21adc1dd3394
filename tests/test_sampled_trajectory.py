"""Sampled trajectory interpolation and direct georeferencing."""

import numpy as np
import pytest

from georefine.errors import InputError
from georefine.geometry.frames import LocalFrame
from georefine.geometry.rotation import exp_so3, log_so3
from georefine.io.trajectory import SbetData
from georefine.lidar.georeference import georeference
from georefine.trajectory.sampled import Trajectory, trajectory_from_sbet


def smooth_motion(t):
    p = np.column_stack([3 * t, 18 * t, 0.5 * np.sin(t)])
    R = exp_so3(np.column_stack([0.05 * np.sin(0.7 * t), 0.03 * np.cos(0.4 * t), 0.2 + 0.01 * t]))
    return p, R


@pytest.mark.parametrize("seed", [0, 1])
def test_interpolation_accuracy_at_imu_rate(seed):
    rng = np.random.default_rng(seed)
    t = np.arange(0, 20, 0.005)
    traj = Trajectory(t, *smooth_motion(t))
    tq = np.sort(rng.uniform(0, 19.99, 1000))
    p, R = traj.interpolate(tq)
    p_true, R_true = smooth_motion(tq)
    assert np.abs(p - p_true).max() < 1e-5
    assert np.linalg.norm(log_so3(np.swapaxes(R, 1, 2) @ R_true), axis=1).max() < 1e-7


def test_no_extrapolation():
    t = np.arange(0, 1, 0.01)
    traj = Trajectory(t, *smooth_motion(t))
    with pytest.raises(InputError, match="outside the trajectory span"):
        traj.interpolate(np.array([0.5, 1.5]))


def test_rejects_non_monotonic_time():
    t = np.array([0.0, 0.1, 0.1, 0.3])
    with pytest.raises(ValueError, match="increase strictly"):
        Trajectory(t, *smooth_motion(t))


def test_georeference_matches_rigid_transform():
    rng = np.random.default_rng(7)
    t = np.arange(0, 5, 0.005)
    traj = Trajectory(t, *smooth_motion(t))
    tq = t[10:20]  # sample times: interpolation is exact there
    xyz_s = rng.normal(size=(10, 3)) * 100
    p_b_s = np.array([0.3, -0.1, 0.2])
    R_b_s = exp_so3(np.array([0.001, -0.002, 0.003]))
    x_w = georeference(tq, xyz_s, traj, p_b_s, R_b_s)
    p, R = smooth_motion(tq)
    expected = p + np.einsum("nij,nj->ni", R, xyz_s @ R_b_s.T + p_b_s)
    np.testing.assert_allclose(x_w, expected, atol=1e-9)


def test_trajectory_from_sbet_round_trip():
    frame = LocalFrame.from_degrees(46.7, 11.65, 600.0)
    t = np.arange(0, 2, 0.01)
    p_w, R_w_b = smooth_motion(t)
    lat, lon, h = frame.to_geodetic(p_w)
    rph = frame.rph_from_R_w_b(p_w, R_w_b)
    n = t.size
    t0 = 1.4e9
    sbet = SbetData(
        time_gps=t0 + t, lat_rad=lat, lon_rad=lon, h_m=h, velocity_wander=np.zeros((n, 3)),
        roll_rad=rph[:, 0], pitch_rad=rph[:, 1], heading_rad=rph[:, 2], wander_rad=np.zeros(n),
        accel_b=np.zeros((n, 3)), angular_rate_b=np.zeros((n, 3)),
    )
    traj = trajectory_from_sbet(sbet, frame, t0)
    np.testing.assert_allclose(traj.time, t, atol=1e-6)
    np.testing.assert_allclose(traj.p_w_b, p_w, atol=1e-7)
    np.testing.assert_allclose(traj.R_w_b, R_w_b, atol=1e-12)
