"""The co-adjustment on a synthetic block: the three cases recover the true poses, and the
estimated sigmas agree with the actual errors."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from georefine.geometry.camera import Camera, R_w_c_from_opk, project_points
from georefine.lidargrammetry.bundle import BlockImages, ControlData, coadjust

PHOTO = Camera(3000, 2000, 4000.0, 4000.0, 1503.0, 997.0, k1=-0.05, k2=0.01, name="photo")
LG = PHOTO.scaled(0.5)


def _block(seed: int):
    """2 strips x 3 photos at 320 m, a lidargram per photo (same station, half resolution) whose
    pose is off by decimetres and 0.05 deg in heading (a jammed LiDAR trajectory); 600 tie
    points, 6 control and 6 check points measured in the photos."""
    rng = np.random.default_rng(seed)
    n = 6
    R = np.array([R_w_c_from_opk(*rng.normal(0, 0.005, 3)) for _ in range(n)])
    p = np.column_stack([np.tile([-64.0, 0.0, 64.0], 2), np.repeat([-50.0, 50.0], 3), np.full(n, 320.0)])
    p += rng.normal(0, 0.02, p.shape)
    X = np.column_stack([rng.uniform(-150, 150, 600), rng.uniform(-120, 120, 600), rng.uniform(0, 20, 600)])
    G = np.column_stack([rng.uniform(-110, 110, 12), rng.uniform(-80, 80, 12), rng.uniform(0, 10, 12)])
    # The lidargrams' true poses: where their (jammed) cloud must go.
    R_lg = np.array([r @ Rotation.from_rotvec([0, 0, np.radians(0.05)]).as_matrix() for r in R])
    p_lg = p + rng.normal(0, 0.2, p.shape)
    cams = [PHOTO] * n + [LG] * n
    R_all, p_all = np.concatenate([R, R_lg]), np.concatenate([p, p_lg])
    img, pt, uv, depth = [], [], [], []
    for i in range(2 * n):
        u, front = project_points(cams[i], X, R_all[i], p_all[i])
        ok = np.flatnonzero(front & cams[i].inside(u, 5))
        img += [i] * ok.size
        pt += ok.tolist()
        uv.append(u[ok] + rng.normal(0, 0.5 if i < n else 1.0, (ok.size, 2)))
        z = ((X[ok] - p_all[i]) @ R_all[i])[:, 2]
        depth.append(z + rng.normal(0, 0.03, ok.size) if i >= n else np.full(ok.size, np.nan))
    mi, mp, muv = [], [], []
    for i in range(n):
        u, front = project_points(PHOTO, G, R[i], p[i])
        ok = np.flatnonzero(front & PHOTO.inside(u, 20))
        mi += [i] * ok.size
        mp += ok.tolist()
        muv.append(u[ok] + rng.normal(0, 0.3, (ok.size, 2)))
    sigma_g = np.tile([0.01, 0.01, 0.02], (12, 1))
    control = ControlData(tuple(f"P{k}" for k in range(12)), G + rng.normal(0, 1.0, G.shape) * sigma_g, sigma_g,
                          np.arange(12) < 6, np.array(mi), np.array(mp), np.concatenate(muv))
    # Approximate poses: photos off by 10 cm and 0.02 deg; lidargrams rendered at the photos' approximate poses.
    R0 = np.array([r @ Rotation.from_rotvec(rng.normal(0, np.radians(0.02), 3)).as_matrix() for r in R])
    p0 = p + rng.normal(0, 0.1, p.shape)
    images = BlockImages(tuple(f"I{i}" for i in range(2 * n)), tuple(cams), np.arange(2 * n) >= n,
                         np.concatenate([R0, R0]), np.concatenate([p0, p0]),
                         np.concatenate([np.full((n, 3), 0.1), np.full((n, 3), 1.0)]),
                         np.radians(np.concatenate([np.full((n, 3), 0.02), np.tile([0.01, 0.01, 0.1], (n, 1))])),
                         np.r_[np.arange(n), np.arange(n)])
    xyz0 = X + rng.normal(0, 0.3, X.shape)
    return images, np.array(img), np.array(pt), np.concatenate(uv), xyz0, np.concatenate(depth), control, \
        (R_all, p_all)


def _angle_deg(Ra, Rb):
    return np.degrees(np.linalg.norm(Rotation.from_matrix(np.swapaxes(Ra, 1, 2) @ Rb).as_rotvec(), axis=1))


def test_case_1_recovers_the_lidargram_poses_and_its_sigmas_are_honest():
    images, img, pt, uv, xyz0, depth, control, (R_true, p_true) = _block(21)
    r = coadjust(images, img, pt, uv, xyz0, control, 1, tie_depth_m=depth)
    lg = images.is_lidargram
    assert np.max(np.linalg.norm(r.p_w_c[lg] - p_true[lg], axis=1)) < 0.1
    # The 0.05 deg heading error (plus 0.02 deg of the approximate photo attitude) is removed down
    # to the noise: errors within 3 estimated sigmas.
    assert np.min(_angle_deg(images.R_w_c[lg], R_true[lg])) > 0.03  # where they started
    ang = _angle_deg(r.R_w_c[lg], R_true[lg])
    sig_rot = np.linalg.norm(r.extra["precision"]["lidargrams"]["sigma_rotation_deg_median"])
    assert np.max(ang) < 0.03 and np.max(ang) < 3 * sig_rot, (ang, sig_rot)
    assert np.max(np.linalg.norm(r.p_w_c[~lg] - p_true[~lg], axis=1)) < 0.2  # the photo block with its GCPs
    assert r.check.reprojection_px < 0.5 and r.check.n == 6 and r.control.n == 6
    assert np.all(r.check.rmse_xyz_m[:2] < 0.05) and r.check.rmse_xyz_m[2] < 0.2
    cp = r.extra["photo_block_precision"]["check_points"]
    assert 0.4 <= cp["normalised_rms"] <= 2.5, cp
    # Estimated sigma of the lidargram positions against their actual errors (6 images x 3 axes).
    sig = r.extra["precision"]["lidargrams"]["sigma_position_m_median"]
    err = r.p_w_c[lg] - p_true[lg]
    assert 0.2 <= np.sqrt(np.mean(err**2)) / np.sqrt(np.mean(np.square(sig))) <= 5.0


@pytest.mark.parametrize("case", [2, 3])
def test_cases_2_and_3(case):
    images, img, pt, uv, xyz0, depth, control, (R_true, p_true) = _block(22)
    r = coadjust(images, img, pt, uv, xyz0, control, case, tie_depth_m=depth)
    photo = ~images.is_lidargram
    assert r.check.reprojection_px < 0.5
    if case == 3:  # lidargrams fixed: the photos land on them, their 0.05 deg heading included
        assert r.control is None and r.check.n == 12
        np.testing.assert_array_equal(r.p_w_c[~photo], images.p_w_c[~photo])
        assert "photos" in r.extra["precision"] and "lidargrams" not in r.extra["precision"]
    else:
        assert np.max(np.linalg.norm(r.p_w_c[photo] - p_true[photo], axis=1)) < 0.2
        assert np.all(r.check.rmse_xyz_m[:2] < 0.05)


def test_tracks_seen_from_one_station_are_left_out_without_depth():
    images, img, pt, uv, xyz0, depth, control, _ = _block(23)
    # Point k, seen by photo 0 and by the lidargram of the same station (image 6), kept in those two only.
    k = np.intersect1d(pt[img == 0], pt[img == 6])[0]
    keep = (pt != k) | np.isin(img, [0, 6])
    r = coadjust(images, img[keep], pt[keep], uv[keep], xyz0, control, 2)
    assert np.isnan(r.tie_points_w[k]).all()
    stations = images.station[img[keep]]
    seen = {k: set(stations[pt[keep] == k]) for k in np.unique(pt[keep])}
    two = np.array([k for k, v in seen.items() if len(v) >= 2])
    one = np.array([k for k, v in seen.items() if len(v) == 1])
    assert one.size > 1 and np.isnan(r.tie_points_w[one]).all() and np.isfinite(r.tie_points_w[two]).all()
    # With the lidargram's depth the point is determined and kept.
    r = coadjust(images, img[keep], pt[keep], uv[keep], xyz0, control, 2, tie_depth_m=depth[keep])
    assert np.isfinite(r.tie_points_w[k]).all()
