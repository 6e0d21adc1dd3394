"""Reprojection observations: Jacobians against finite differences, behind-camera handling."""

from __future__ import annotations

import numpy as np

from georefine.adjustment.observations.reprojection import (
    BEHIND_RESIDUAL,
    ReprojectionObservation,
)
from georefine.adjustment.testing import check_jacobians
from georefine.geometry.camera import Camera, R_w_c_from_opk, project_points


def _setup(seed=31):
    rng = np.random.default_rng(seed)
    cams = [Camera(3000, 2000, 4000.0, 4000.0, 1503.0, 997.0, k1=-0.05, k2=0.01, p1=1e-4, p2=-2e-4, name="a"),
            Camera(1500, 1000, 2000.0, 2000.0, 751.0, 499.0, k1=-0.05, name="b")]
    n_img, n_pts = 4, 30
    R = R_w_c_from_opk(*(rng.normal(0, 0.02, (n_img, 3)) + [0, 0, 0.3]).T)
    p = np.column_stack([rng.uniform(-50, 50, n_img), rng.uniform(-50, 50, n_img), np.full(n_img, 320.0)])
    X = np.column_stack([rng.uniform(-60, 60, n_pts), rng.uniform(-60, 60, n_pts), rng.uniform(0, 20, n_pts)])
    image = np.repeat(np.arange(n_img), n_pts)
    point = np.tile(np.arange(n_pts), n_img)
    cameras = [cams[0], cams[0], cams[1], cams[1]]
    uv = np.concatenate([project_points(cameras[i], X, R[i], p[i])[0] for i in range(n_img)])
    uv += rng.normal(0, 0.5, uv.shape)
    return cameras, R, p, X, image, point, uv


def test_jacobians_match_finite_differences():
    cameras, R, p, X, image, point, uv = _setup()
    grp = ReprojectionObservation("r", cameras, image, point, uv, sigma_px=0.7)
    chk = check_jacobians(grp, {"image_rotation": R, "image_position": p, "points": X},
                          {"image_rotation": "so3", "image_position": "euclidean", "points": "euclidean"}, eps=1e-6)
    assert chk.max_rel_error < 1e-5 and chk.residual_mismatch == 0.0, chk
    lin = grp.linearize({"image_rotation": R, "image_position": p, "points": X})
    np.testing.assert_allclose(lin.residuals.reshape(-1, 2),
                               (grp.predict({"image_rotation": R, "image_position": p, "points": X})[0] - uv) / 0.7)


def test_points_behind_an_image_get_a_large_residual_and_no_jacobian():
    cameras, R, p, X, image, point, uv = _setup()
    X = X.copy()
    X[0, 2] = 400.0  # above the cameras (320 m): behind every image
    grp = ReprojectionObservation("r", cameras, image, point, uv)
    lin = grp.linearize({"image_rotation": R, "image_position": p, "points": X})
    bad = np.flatnonzero(point == 0)
    assert np.all(lin.residuals.reshape(-1, 2)[bad] == BEHIND_RESIDUAL)
    for jb in lin.jacobians:
        assert np.all(jb.values[bad] == 0.0)
    _, front = grp.predict({"image_rotation": R, "image_position": p, "points": X})
    assert not front[bad].any() and front[point != 0].all()


def test_depth_jacobians_match_finite_differences():
    from georefine.adjustment.observations.reprojection import DepthObservation

    cameras, R, p, X, image, point, uv = _setup(33)
    z = np.einsum("nji,nj->ni", R[image], X[point] - p[image])[:, 2]
    grp = DepthObservation("d", image, point, z + 0.03, sigma_m=0.05)
    values = {"image_rotation": R, "image_position": p, "points": X}
    chk = check_jacobians(grp, values, {"image_rotation": "so3", "image_position": "euclidean", "points": "euclidean"})
    assert chk.max_rel_error < 1e-6, chk
    np.testing.assert_allclose(grp.linearize(values).residuals, -0.6)
