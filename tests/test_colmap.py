"""COLMAP interchange: a block round-trips through a COLMAP text model, and COLMAP's bundle
adjustment on it reaches the reprojection error of ours (the reference peer)."""

from __future__ import annotations

import numpy as np
import pytest

from georefine.adjustment.observations.reprojection import ReprojectionObservation
from georefine.adjustment.problem import Problem
from georefine.io.colmap import (
    colmap_bundle_adjustment, poses_from_reconstruction, read_model, to_reconstruction, write_model,
)
from georefine.lidargrammetry.camera import Camera, R_w_c_from_opk, project_points

pycolmap = pytest.importorskip("pycolmap")


def _block(seed=51):
    rng = np.random.default_rng(seed)
    cams = [Camera(3000, 2000, 4000.0, 4000.0, 1503.0, 997.0, k1=-0.05, k2=0.01, p1=1e-4, p2=-2e-4, name="photo"),
            Camera(1500, 1000, 2000.0, 2000.0, 751.5, 498.5, k1=-0.05, k2=0.01, p1=1e-4, p2=-2e-4, name="lg")]
    n, m = 6, 300
    R = R_w_c_from_opk(*rng.normal(0, 0.01, (n, 3)).T)
    p = np.column_stack([np.tile([-40.0, 0.0, 40.0], 2), np.repeat([-30.0, 30.0], 3), np.full(n, 320.0)])
    X = np.column_stack([rng.uniform(-80, 80, m), rng.uniform(-70, 70, m), rng.uniform(0, 15, m)])
    cameras = [cams[0]] * 3 + [cams[1]] * 3
    img, pt, uv = [], [], []
    for i in range(n):
        u, front = project_points(cameras[i], X, R[i], p[i])
        ok = front & cameras[i].inside(u, 5)
        img += [i] * int(ok.sum())
        pt += list(np.flatnonzero(ok))
        uv.append(u[ok] + rng.normal(0, 0.5, (ok.sum(), 2)))
    # Start from perturbed free poses and points.
    R0 = R.copy()
    p0 = p.copy()
    for i in range(3, n):
        R0[i] = R[i] @ R_w_c_from_opk(*rng.normal(0, 2e-4, 3)) @ np.diag([1.0, -1.0, -1.0])
        p0[i] += rng.normal(0, 0.2, 3)
    return cameras, R, p, X, R0, p0, X + rng.normal(0, 0.1, X.shape), np.array(img), np.array(pt), np.concatenate(uv)


def test_model_round_trip(tmp_path):
    cameras, R, p, X, *_ , img, pt, uv = _block()
    names = [f"img{i}.jpg" for i in range(len(cameras))]
    rec = to_reconstruction(names, cameras, R, p, img, pt, uv, X)
    write_model(rec, tmp_path / "model")
    back = read_model(tmp_path / "model")
    assert back.num_images() == 6 and back.num_points3D() == len(np.unique(pt)) and back.num_cameras() == 2
    R2, p2 = poses_from_reconstruction(back, names)
    np.testing.assert_allclose(R2, R, atol=1e-9)
    np.testing.assert_allclose(p2, p, atol=1e-6)
    back.update_point_3d_errors()
    assert back.compute_mean_reprojection_error() == pytest.approx(
        np.mean(np.linalg.norm(np.concatenate([project_points(cameras[i], X[pt[img == i]], R[i], p[i])[0] - uv[img == i]
                                               for i in range(6)]), axis=1)), rel=1e-2)  # text model rounding


def test_colmap_bundle_adjustment_agrees_with_ours():
    cameras, R, p, X, R0, p0, X0, img, pt, uv = _block()
    fixed = np.array([True, True, True, False, False, False])  # photos fixed, lidargram-like images free
    P = Problem()
    P.add_block("image_rotation", R0, manifold="so3", constant=fixed)
    P.add_block("image_position", p0, constant=fixed)
    P.add_block("points", X0)
    P.add_group(ReprojectionObservation("ties", cameras, img, pt, uv))
    P.solve()
    values = {"image_rotation": P.values("image_rotation"), "image_position": P.values("image_position"),
              "points": P.values("points")}
    uv_ours, _ = ReprojectionObservation("t", cameras, img, pt, uv).predict(values)
    ours = np.mean(np.linalg.norm(uv_ours - uv, axis=1))
    rec = to_reconstruction([f"i{i}" for i in range(6)], cameras, R0, p0, img, pt, uv, X0)
    theirs = colmap_bundle_adjustment(rec, fixed_images=np.flatnonzero(fixed))
    assert theirs == pytest.approx(ours, rel=0.05), (ours, theirs)
    R_c, p_c = poses_from_reconstruction(rec, [f"i{i}" for i in range(6)])
    np.testing.assert_allclose(p_c, values["image_position"], atol=0.01)
