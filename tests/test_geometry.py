"""SO(3), WGS84 and frame conversions: identities, round trips, Jacobians against finite differences."""

import numpy as np
import pytest
from pyproj import Transformer
from scipy.spatial.transform import Rotation

from georefine.geometry import earth, rotation
from georefine.geometry.frames import LocalFrame, OutputCRS

SEEDS = [0, 1, 2]


def random_rotvecs(rng, n, max_angle=3.0):
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return axis * rng.uniform(0, max_angle, size=(n, 1))


@pytest.mark.parametrize("seed", SEEDS)
def test_exp_log_round_trip_and_scipy_agreement(seed):
    rng = np.random.default_rng(seed)
    phi = np.concatenate([random_rotvecs(rng, 200), random_rotvecs(rng, 50, 1e-7)])
    R = rotation.exp_so3(phi)
    np.testing.assert_allclose(R, Rotation.from_rotvec(phi).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(rotation.log_so3(R), phi, atol=1e-12)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)


def test_log_near_pi():
    phi = np.array([[np.pi - 1e-9, 0.0, 0.0], [0.0, 0.0, -(np.pi - 1e-6)]])
    back = rotation.log_so3(rotation.exp_so3(phi))
    # Near pi the sign of the axis is ambiguous; the rotation must be the same.
    np.testing.assert_allclose(rotation.exp_so3(back), rotation.exp_so3(phi), atol=1e-12)


@pytest.mark.parametrize("seed", SEEDS)
def test_quaternion_conversions(seed):
    rng = np.random.default_rng(seed)
    R = Rotation.random(100, random_state=seed).as_matrix()
    q = rotation.quat_from_matrix(R)
    ref = Rotation.from_matrix(R).as_quat()
    ref *= np.sign(ref[:, 3:4])
    np.testing.assert_allclose(q, ref, atol=1e-14)
    np.testing.assert_allclose(rotation.matrix_from_quat(q), R, atol=1e-14)
    phi = random_rotvecs(rng, 100)
    np.testing.assert_allclose(rotation.rotvec_from_quat(rotation.quat_from_rotvec(phi)), phi, atol=1e-13)


@pytest.mark.parametrize("seed", SEEDS)
def test_right_jacobian_finite_differences(seed):
    """Exp(phi + d) ~= Exp(phi) Exp(Jr d) and Log(Exp(phi) Exp(d)) ~= phi + Jr^-1 d."""
    rng = np.random.default_rng(seed)
    phi = np.concatenate([random_rotvecs(rng, 20), random_rotvecs(rng, 3, 1e-6)])
    h = 1e-6
    for p in phi:
        Jr = rotation.right_jacobian(p)
        Jr_inv = rotation.right_jacobian_inv(p)
        np.testing.assert_allclose(Jr @ Jr_inv, np.eye(3), atol=1e-12)
        num = np.empty((3, 3))
        num_inv = np.empty((3, 3))
        for k in range(3):
            e = np.zeros(3)
            e[k] = h
            num[:, k] = rotation.log_so3(
                rotation.exp_so3(p).T @ rotation.exp_so3(p + e)
            ) / 2 - rotation.log_so3(rotation.exp_so3(p).T @ rotation.exp_so3(p - e)) / 2
            num_inv[:, k] = (
                rotation.log_so3(rotation.exp_so3(p) @ rotation.exp_so3(e))
                - rotation.log_so3(rotation.exp_so3(p) @ rotation.exp_so3(-e))
            ) / 2
        np.testing.assert_allclose(num / h, Jr, atol=1e-7)
        np.testing.assert_allclose(num_inv / h, Jr_inv, atol=1e-7)
        np.testing.assert_allclose(rotation.left_jacobian(p), rotation.exp_so3(p) @ Jr, atol=1e-12)


def test_skew_is_cross_product():
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(2, 10, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", rotation.skew(a), b), np.cross(a, b), atol=1e-14)


@pytest.mark.parametrize("seed", SEEDS)
def test_roll_pitch_heading(seed):
    rng = np.random.default_rng(seed)
    rph = np.column_stack(
        [rng.uniform(-1.5, 1.5, 50), rng.uniform(-1.5, 1.5, 50), rng.uniform(0, 2 * np.pi, 50)]
    )
    R = rotation.R_n_b_from_rph(rph[:, 0], rph[:, 1], rph[:, 2])
    np.testing.assert_allclose(rotation.rph_from_R_n_b(R), rph, atol=1e-12)
    # Same as SciPy's intrinsic z-y'-x'' sequence (yaw, pitch, roll).
    ref = Rotation.from_euler("ZYX", rph[:, ::-1]).as_matrix()
    np.testing.assert_allclose(R, ref, atol=1e-14)


def test_wrap_angle_radians_and_degrees_at_both_ends():
    w = rotation.wrap_angle
    # Radians, (-pi, pi] by default: -pi becomes +pi.
    np.testing.assert_allclose(w([np.pi, -np.pi, 2 * np.pi - 1e-3, -2 * np.pi + 1e-3, 0.0, 3 * np.pi]),
                               [np.pi, np.pi, -1e-3, 1e-3, 0.0, np.pi], atol=1e-15)
    # [-pi, pi): +pi becomes -pi.
    np.testing.assert_allclose(w([np.pi, -np.pi, 2 * np.pi - 1e-3, 0.0], closed="lower"),
                               [-np.pi, -np.pi, -1e-3, 0.0], atol=1e-15)
    # Degrees through the period.
    assert list(w(np.array([180.0, -180.0, 540.0, 359.0, -181.0]), 360.0)) == [180.0, 180.0, 180.0, -1.0, 179.0]
    assert list(w(np.array([180.0, -180.0, 540.0, 359.0, -181.0]), 360.0, closed="lower")) == [
        -180.0, -180.0, -180.0, -1.0, 179.0]
    # The expressions it replaced, bit for bit, on both ends and inside.
    a = np.concatenate([np.random.default_rng(0).uniform(-1000.0, 1000.0, 1000),
                        [180.0, -180.0, np.nextafter(180.0, 0.0), np.nextafter(-180.0, 0.0), -0.0, 720.0]])
    assert np.array_equal(w(a, 360.0, closed="lower"), (a + 180.0) % 360.0 - 180.0)
    r = np.radians(a)
    assert np.array_equal(w(r, closed="lower"), (r + np.pi) % (2.0 * np.pi) - np.pi)
    assert np.array_equal(w(r), np.pi - np.mod(np.pi - r, 2.0 * np.pi))
    assert isinstance(w(np.float64(190.0), 360.0), np.float64)  # a scalar stays a scalar
    with pytest.raises(ValueError):
        w(0.0, closed="both")


@pytest.mark.parametrize("seed", SEEDS)
def test_euler_rates_give_body_rate(seed):
    rng = np.random.default_rng(seed)
    rph0 = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(0, 6)])
    rate = rng.normal(size=3) * 0.3
    h = 1e-6
    R = lambda t: rotation.R_n_b_from_rph(*(rph0 + rate * t))  # noqa: E731
    numeric = rotation.log_so3(R(-h).T @ R(h)) / (2 * h)
    np.testing.assert_allclose(rotation.omega_nb_b_from_rph_rates(rph0, rate), numeric, atol=1e-8)


@pytest.mark.parametrize("seed", SEEDS)
def test_geodetic_ecef_against_pyproj(seed):
    rng = np.random.default_rng(seed)
    lat = rng.uniform(-89.9, 89.9, 500)
    lon = rng.uniform(-180, 180, 500)
    h = rng.uniform(-100, 10000, 500)
    t = Transformer.from_crs(4979, 4978, always_xy=True)
    ref = np.column_stack(t.transform(lon, lat, h))
    p = earth.geodetic_to_ecef(np.radians(lat), np.radians(lon), h)
    np.testing.assert_allclose(p, ref, atol=1e-6)
    lat2, lon2, h2 = earth.ecef_to_geodetic(p)
    np.testing.assert_allclose(lat2, np.radians(lat), atol=1e-13)
    np.testing.assert_allclose(lon2, np.radians(lon), atol=1e-13)
    np.testing.assert_allclose(h2, h, atol=1e-7)


def test_normal_gravity_reference_values():
    # TR8350.2: gamma_e = 9.7803253359, gamma_p = 9.8321849378 on the ellipsoid.
    np.testing.assert_allclose(earth.normal_gravity(0.0, 0.0), 9.7803253359, rtol=1e-12)
    np.testing.assert_allclose(earth.normal_gravity(np.pi / 2, 0.0), 9.8321849378, rtol=1e-10)
    # Free-air gradient ~ -0.3086 mGal/m.
    grad = (earth.normal_gravity(0.8, 100.0) - earth.normal_gravity(0.8, 0.0)) / 100.0
    assert -3.09e-6 < grad < -3.08e-6


def test_gravity_points_along_the_ellipsoidal_normal():
    frame = LocalFrame.from_degrees(46.7, 11.65, 600.0)
    g = frame.gravity_w(np.zeros(3))
    np.testing.assert_allclose(g[:2], 0.0, atol=1e-12)
    np.testing.assert_allclose(-g[2], earth.normal_gravity(frame.lat0_rad, 600.0), rtol=1e-14)


def test_local_frame_round_trips_and_earth_rate():
    frame = LocalFrame.from_degrees(46.7, 11.65, 600.0)
    rng = np.random.default_rng(4)
    p_w = rng.uniform(-5000, 5000, size=(100, 3))
    np.testing.assert_allclose(frame.from_ecef(frame.to_ecef(p_w)), p_w, atol=1e-8)
    np.testing.assert_allclose(frame.from_geodetic(*frame.to_geodetic(p_w)), p_w, atol=1e-7)
    w = frame.omega_ie_w
    np.testing.assert_allclose(np.linalg.norm(w), earth.OMEGA_IE)
    # ENU at latitude phi: omega = Omega (0, cos phi, sin phi).
    np.testing.assert_allclose(w, earth.OMEGA_IE * np.array([0, np.cos(frame.lat0_rad), np.sin(frame.lat0_rad)]), atol=1e-18)


def test_rph_in_w_round_trip():
    frame = LocalFrame.from_degrees(46.7, 11.65, 600.0)
    rng = np.random.default_rng(5)
    p_w = rng.uniform(-3000, 3000, size=(20, 3))
    rph = np.column_stack([rng.uniform(-0.3, 0.3, 20), rng.uniform(-0.3, 0.3, 20), rng.uniform(0, 6.2, 20)])
    R_w_b = frame.R_w_b_from_rph(p_w, rph)
    np.testing.assert_allclose(frame.rph_from_R_w_b(p_w, R_w_b), rph, atol=1e-12)
    # The per-point kernel is the product R_w_n R_n_b written out.
    R_n_b = rotation.R_n_b_from_rph(rph[:, 0], rph[:, 1], rph[:, 2])
    np.testing.assert_allclose(R_w_b, frame.R_w_n_at(p_w) @ R_n_b, atol=1e-15)
    assert frame.R_w_b_from_rph(p_w[:4].reshape(2, 2, 3), rph[:4].reshape(2, 2, 3)).shape == (2, 2, 3, 3)
    # At the origin, heading 0 points the body x axis north (w y axis) and z down.
    R0 = frame.R_w_b_from_rph(np.zeros(3), np.zeros(3))
    np.testing.assert_allclose(R0, [[0, 1, 0], [1, 0, 0], [0, 0, -1]], atol=1e-12)


def test_transport_rate_matches_rotation_of_ned_frame():
    frame = LocalFrame.from_degrees(46.7, 11.65, 600.0)
    v_w = np.array([12.0, -13.0, 1.5])
    p = lambda t: np.array([100.0, 2000.0, 160.0]) + v_w * t  # noqa: E731
    h = 1e-3
    R_e_n = lambda t: earth.R_e_n(*frame.to_geodetic(p(t))[:2])  # noqa: E731
    numeric = rotation.log_so3(R_e_n(-h).T @ R_e_n(h)) / (2 * h)
    lat, lon, height = frame.to_geodetic(p(0.0))
    v_n = frame.R_w_n(lat, lon).T @ v_w
    np.testing.assert_allclose(earth.transport_rate_n(lat, height, v_n), numeric, atol=1e-11)


def test_output_crs_round_trip_keeps_ellipsoidal_height():
    frame = LocalFrame.from_degrees(46.7, 11.65, 600.0)
    crs = OutputCRS(25832)
    p_w = np.array([[0.0, 0.0, 0.0], [1000.0, -2000.0, 150.0]])
    xyz = crs.from_w(frame, p_w)
    assert 600000 < xyz[0, 0] < 800000 and 5.1e6 < xyz[0, 1] < 5.2e6
    np.testing.assert_allclose(xyz[0, 2], 600.0, atol=1e-9)
    np.testing.assert_allclose(crs.to_w(frame, xyz), p_w, atol=1e-6)
