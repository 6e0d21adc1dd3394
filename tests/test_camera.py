"""Frame camera: projection, distortion and their Jacobians; omega-phi-kappa."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from georefine.geometry.camera import (
    Camera,
    R_w_c_from_opk,
    opk_from_R_w_c,
    project_points,
)
from georefine.geometry.rotation import exp_so3

CAM = Camera(4000, 3000, 3500.0, 3502.0, 2001.3, 1497.8, k1=-0.08, k2=0.03, k3=-0.004, p1=2e-4, p2=-3e-4)


def _points_in_view(rng, n=200):
    uv = rng.uniform([0, 0], [CAM.width_px, CAM.height_px], size=(n, 2))
    depth = rng.uniform(50.0, 500.0, n)
    return CAM.rays(uv) * (depth / CAM.rays(uv)[:, 2])[:, None], uv


def test_projection_reproduces_the_pixel_of_a_ray():
    rng = np.random.default_rng(11)
    x_c, uv = _points_in_view(rng)
    np.testing.assert_allclose(CAM.project(x_c), uv, atol=1e-8)


def test_projection_agrees_with_opencv():
    rng = np.random.default_rng(12)
    x_c, _ = _points_in_view(rng)
    K, dist = CAM.opencv()
    uv_cv, _ = cv2.projectPoints(x_c, np.zeros(3), np.zeros(3), K, dist)
    np.testing.assert_allclose(CAM.project(x_c), uv_cv[:, 0] + 0.5, atol=1e-6)  # OpenCV: pixel centre at 0


def test_distortion_and_projection_jacobians_match_finite_differences():
    rng = np.random.default_rng(13)
    x_c, _ = _points_in_view(rng, 50)
    _, J = CAM.project(x_c, jacobian=True)
    h = 1e-6 * np.abs(x_c).max()
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fd = (CAM.project(x_c + e) - CAM.project(x_c - e)) / (2 * h)
        np.testing.assert_allclose(J[:, :, k], fd, rtol=1e-6, atol=1e-6)
    xn = x_c[:, :2] / x_c[:, 2:]
    _, Jd = CAM.distort(xn, jacobian=True)
    for k in range(2):
        e = np.zeros(2)
        e[k] = 1e-7
        fd = (CAM.distort(xn + e) - CAM.distort(xn - e)) / 2e-7
        np.testing.assert_allclose(Jd[:, :, k], fd, rtol=1e-6, atol=1e-8)


def test_pose_jacobians_match_finite_differences():
    rng = np.random.default_rng(14)
    R = R_w_c_from_opk(0.03, -0.02, 1.1)
    p = np.array([100.0, -50.0, 800.0])
    X = p + (rng.uniform(-300, 300, (40, 3)) * [1, 1, 0]) - [0, 0, 750.0]
    uv, front, jac = project_points(CAM, X, R, p, jacobians=True)
    assert front.all()
    for k in range(3):
        d = np.zeros(3)
        d[k] = 1e-7
        fd = (project_points(CAM, X, R @ exp_so3(d), p)[0] - project_points(CAM, X, R @ exp_so3(-d), p)[0]) / 2e-7
        np.testing.assert_allclose(jac.rotation[:, :, k], fd, rtol=1e-5, atol=1e-3)
        d = np.zeros(3)
        d[k] = 1e-4
        fd = (project_points(CAM, X, R, p + d)[0] - project_points(CAM, X, R, p - d)[0]) / 2e-4
        np.testing.assert_allclose(jac.position[:, :, k], fd, rtol=1e-5, atol=1e-6)
        fd = (project_points(CAM, X + d, R, p)[0] - project_points(CAM, X - d, R, p)[0]) / 2e-4
        np.testing.assert_allclose(jac.point[:, :, k], fd, rtol=1e-5, atol=1e-6)
    # One pose per point gives the same.
    uv2, _ = project_points(CAM, X, np.broadcast_to(R, (40, 3, 3)), np.broadcast_to(p, (40, 3)))
    np.testing.assert_allclose(uv2, uv, atol=1e-9)


def test_undistortion_inverts_distortion_over_the_image():
    u, v = np.meshgrid(np.linspace(0, CAM.width_px, 41), np.linspace(0, CAM.height_px, 31))
    uv = np.column_stack([u.ravel(), v.ravel()])
    rays = CAM.rays(uv)
    np.testing.assert_allclose(CAM.project(rays), uv, atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0)
    # Solved in chunks of a few points (as large inputs are): the same, in the input's shape.
    xd = (uv - [CAM.cx_px, CAM.cy_px]) / [CAM.fx_px, CAM.fy_px]
    whole = CAM.undistort(xd)
    chunked = CAM.undistort(xd.reshape(31, 41, 2), chunk=100)
    assert chunked.shape == (31, 41, 2)
    np.testing.assert_allclose(chunked.reshape(-1, 2), whole, atol=1e-15)
    np.testing.assert_allclose(CAM.distort(chunked), xd.reshape(31, 41, 2), atol=1e-14)


def test_omega_phi_kappa_matches_micmac_oriexport_and_round_trips():
    rng = np.random.default_rng(15)
    w, p, k = rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(-np.pi, np.pi)
    cw, sw, cp, sp, ck, sk = np.cos(w), np.sin(w), np.cos(p), np.sin(p), np.cos(k), np.sin(k)
    # MicMac OriExport's published matrix for its omega-phi-kappa: the same product, written out.
    micmac = np.array([
        [cp * ck, cp * sk, -sp],
        [cw * sk + sw * sp * ck, -cw * ck + sw * sp * sk, sw * cp],
        [sw * sk - cw * sp * ck, -sw * ck - cw * sp * sk, -cw * cp],
    ])
    np.testing.assert_allclose(R_w_c_from_opk(w, p, k), micmac, atol=1e-15)
    angles = rng.uniform([-0.5, -1.2, -3.1], [0.5, 1.2, 3.1], (100, 3))
    R = R_w_c_from_opk(*angles.T)
    np.testing.assert_allclose(opk_from_R_w_c(R), angles, atol=1e-12)
    # A nadir photo, image top to the north: the camera looks down, image x east, image y (down) south.
    np.testing.assert_allclose(R_w_c_from_opk(0.0, 0.0, 0.0), np.diag([1.0, -1.0, -1.0]))


@pytest.mark.parametrize("field, value", [("fx_px", 0.0), ("fy_px", -3.0), ("width_px", 0), ("k1", np.nan)])
def test_invalid_interior_orientation_is_rejected(field, value):
    kw = dict(width_px=100, height_px=80, fx_px=90.0, fy_px=90.0, cx_px=50.0, cy_px=40.0)
    kw[field] = value
    with pytest.raises(ValueError, match=field):
        Camera(**kw)
