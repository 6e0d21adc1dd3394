"""COLMAP interchange: a block round-trips through a COLMAP text model, and COLMAP's bundle
adjustment on it reaches the reprojection error of ours (the reference peer); the exported
model folder (images, errors, colours, georeference) is used as is by COLMAP's own tools."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from colmap_helpers import colmap_checks
from georefine.geometry.camera import Camera, R_w_c_from_opk, project_points
from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.io.colmap import (
    block_from_reconstruction,
    mean_reprojection_error,
    poses_from_reconstruction,
    read_model,
    to_reconstruction,
    write_model,
)
from georefine.lidargrammetry.crosscheck import reprojection_errors, solve_both


def _block(seed=51, scale=1.0):
    """Three photos (y = -30 m) and three lidargram-like images (y = +30 m) 320 m above 300 points;
    ``scale``: the cameras' resolution relative to 3000 x 2000 and 1500 x 1000 px."""
    rng = np.random.default_rng(seed)
    cams = [Camera(3000, 2000, 4000.0, 4000.0, 1503.0, 997.0, k1=-0.05, k2=0.01, p1=1e-4, p2=-2e-4,
                   name="photo").scaled(scale),
            Camera(1500, 1000, 2000.0, 2000.0, 751.5, 498.5, k1=-0.05, k2=0.01, p1=1e-4, p2=-2e-4,
                   name="lg").scaled(scale)]
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


def test_block_round_trip_and_colmap_statistic(tmp_path):
    cameras, R, p, X, *_, img, pt, uv = _block()
    names = [f"img{i}.jpg" for i in range(len(cameras))]
    write_model(to_reconstruction(names, cameras, R, p, img, pt, uv, X), tmp_path / "m")
    rec = read_model(tmp_path / "m")
    b = block_from_reconstruction(rec)
    assert b.names == tuple(names) and b.cameras[0].fx_px == 4000.0 and b.cameras[3].width_px == 1500
    assert b.cameras[0].k1 == pytest.approx(-0.05) and b.cameras[0].p2 == pytest.approx(-2e-4)
    assert len(b.obs_image) == len(img) and len(b.points_w) == len(np.unique(pt))
    np.testing.assert_allclose(b.p_w_c, p, atol=1e-6)
    e = reprojection_errors(b, b.R_w_c, b.p_w_c, b.points_w)
    rec.update_point_3d_errors()
    # COLMAP's mean reprojection error is the mean over points of each point's mean error.
    assert mean_reprojection_error(e, b.obs_point) == pytest.approx(rec.compute_mean_reprojection_error(), rel=1e-4)
    assert mean_reprojection_error(e, b.obs_point) != pytest.approx(e.mean(), rel=1e-3)


def test_colmap_camera_models_read_back():
    from georefine.io.colmap import _camera_from_colmap

    c = _camera_from_colmap(pycolmap.Camera(model="SIMPLE_RADIAL", width=100, height=80, params=[90.0, 50.0, 40.0, 0.1],
                                            camera_id=3))
    assert (c.fx_px, c.fy_px, c.cx_px, c.cy_px, c.k1) == (90.0, 90.0, 50.0, 40.0, 0.1)
    with pytest.raises(ValueError, match="model .* is not supported"):
        _camera_from_colmap(pycolmap.Camera(model="FOV", width=100, height=80, params=[90.0, 90.0, 50.0, 40.0, 0.1],
                                            camera_id=4))


def test_colmap_bundle_adjustment_agrees_with_ours():
    cameras, R, p, X, R0, p0, X0, img, pt, uv = _block()
    fixed = np.array([True, True, True, False, False, False])  # photos fixed, lidargram-like images free
    rec = to_reconstruction([f"i{i}" for i in range(6)], cameras, R0, p0, img, pt, uv, X0)
    b = block_from_reconstruction(rec)
    ours, theirs = solve_both(b, fixed)
    # The same minimum: equal sums of squares (COLMAP's solution evaluated with our camera model),
    # equal reprojection error by either statistic, equal poses.
    assert theirs.sum_of_squares == pytest.approx(ours.sum_of_squares, rel=1e-6)
    assert theirs.re_px == pytest.approx(ours.re_px, rel=0.05) and theirs.re_px == pytest.approx(ours.re_px, rel=1e-4)
    assert ours.errors_px.mean() < 0.6 and ours.re_px < 0.6  # 0.5 px noise
    np.testing.assert_allclose(theirs.p_w_c, ours.p_w_c, atol=1e-4)
    assert reprojection_errors(b, R0, p0, X0).mean() > 4 * ours.errors_px.mean()  # both started well off


FRAME = LocalFrame.from_degrees(48.137, 11.575, 520.0)  # Munich, in EPSG:25832's zone
CRS = OutputCRS(25832)
PHOTO_BGR = [(40, 90, 200), (10, 160, 30), (250, 20, 120)]  # each photo one colour (BGR, as OpenCV writes)
LG_GREY = [60, 120, 180]


def _export(tmp_path, scale=1.0, outlier_every=0, station=None):
    """The block of :func:`_block` exported: photos as one-colour JPEG files (PNG-exact colours
    are not needed: the JPEG of a flat colour decodes to it within 1-2 levels), lidargrams as
    one-grey arrays; every ``outlier_every``-th observation an outlier of the adjustment; returns
    the block, the inlier flags, the ColmapModel and the model folder."""
    from georefine.lidargrammetry.bundle import BundleResult
    from georefine.workflows.lidargrammetry import export_colmap

    cameras, R, p, X, *_, img, pt, uv = _block(scale=scale)
    (tmp_path / "photos").mkdir()
    images, names = [], []
    for i in range(3):
        c = cameras[i]
        names.append(f"IMG_0{i + 1}.jpg")
        cv2.imwrite(str(tmp_path / "photos" / names[-1]), np.full((c.height_px, c.width_px, 3), PHOTO_BGR[i], np.uint8))
        images.append(tmp_path / "photos" / names[-1])
    for i in range(3, 6):
        c = cameras[i]
        names.append(f"LG_strip_1_IMG_0{i - 2}.png")
        images.append(np.full((c.height_px, c.width_px), LG_GREY[i - 3], np.uint8))
    inlier = np.ones(len(img), bool)
    if outlier_every:
        inlier[::outlier_every] = False
    result = BundleResult(1, R, p, X, None, None, {}, None, np.zeros((0, 3)), tie_inlier=inlier)
    model = export_colmap(tmp_path / "colmap", names, cameras, result, img, pt, uv, station, images=images,
                          frame=FRAME, crs=CRS)
    return (cameras, R, p, X, img, pt, uv, names, images), inlier, model, tmp_path / "colmap"


def test_export_colmap_writes_the_inlier_observations_seen_from_two_stations(tmp_path):
    station = np.array([0, 1, 2, 0, 1, 2])  # a lidargram rendered at each photo: one station
    (_, _, _, X, img, pt, *_), inlier, model, folder = _export(tmp_path, scale=0.1, outlier_every=7, station=station)
    assert model.folder == "colmap" and folder.is_dir() and not (tmp_path / "colmap.partial").exists()
    back = read_model(folder)
    keep = inlier.copy()
    n_st = np.array([len(np.unique(station[img[keep & (pt == k)]])) for k in range(len(X))])
    keep &= n_st[pt] >= 2
    assert back.num_points3D() == len(np.unique(pt[keep])) == model.points and back.num_images() == 6 == model.images
    assert sum(len(back.point3D(k).track.elements) for k in back.point3D_ids()) == int(keep.sum()) == model.observations


def test_exported_model_has_its_images_errors_colours_and_georeference(tmp_path):
    (cameras, R, p, X, img, pt, uv, names, images), _, model, folder = _export(tmp_path, scale=0.2)
    rec = read_model(folder)
    # Every image the model names is in images/ under that name: photos the same bytes, lidargrams lossless PNG.
    assert sorted(rec.image(i).name for i in rec.reg_image_ids()) == sorted(names)
    assert sorted(f.name for f in (folder / "images").iterdir()) == sorted(names)
    for name, im in zip(names, images):
        if isinstance(im, Path):
            assert (folder / "images" / name).read_bytes() == im.read_bytes()
        else:
            np.testing.assert_array_equal(cv2.imread(str(folder / "images" / name), cv2.IMREAD_UNCHANGED), im)
    # Errors: each point's mean over its track, as COLMAP itself computes them from the model.
    ids = sorted(rec.point3D_ids())
    stored = np.array([rec.point3D(k).error for k in ids])
    assert np.all(stored > 0) and model.mean_reprojection_error_px == pytest.approx(stored.mean(), rel=1e-9)
    rec.update_point_3d_errors()
    np.testing.assert_allclose(stored, [rec.point3D(k).error for k in ids], rtol=1e-6)
    assert model.mean_reprojection_error_px == pytest.approx(rec.compute_mean_reprojection_error(), rel=1e-6)
    assert 0.3 < model.mean_reprojection_error_px < 1.0  # 0.5 px noise per coordinate
    # Colours: the mean photo colour (RGB) of a point's photos, the lidargrams' grey without a photo.
    photo_rgb = np.array(PHOTO_BGR, dtype=float)[:, ::-1]
    seen_lg_only = 0
    for k in ids:
        el = [e.image_id - 1 for e in rec.point3D(k).track.elements]
        ph = [i for i in el if i < 3]
        want = photo_rgb[ph].mean(axis=0) if ph else np.full(3, np.mean([LG_GREY[i - 3] for i in el]))
        seen_lg_only += not ph
        np.testing.assert_allclose(rec.point3D(k).color, want, atol=2.5, err_msg=str(el))
    assert seen_lg_only > 10
    # Georeference: the camera centres in the output CRS, and the frame they came from.
    ref = [line.split() for line in (folder / "reference_images.txt").read_text().splitlines()]
    assert [r[0] for r in ref] == list(names)
    np.testing.assert_allclose(np.array([r[1:] for r in ref], float), CRS.from_w(FRAME, p), atol=1e-4)
    geo = json.loads((folder / "georeference.json").read_text())
    back = LocalFrame.from_degrees(geo["origin_lat_deg"], geo["origin_lon_deg"], geo["origin_h_m"])
    np.testing.assert_allclose(OutputCRS(int(geo["crs"].split(":")[1])).to_w(back, np.array([r[1:] for r in ref],
                                                                                         float)), p, atol=1e-4)
    assert geo["frame"] == model.frame == "local east-north-up" and model.crs == geo["crs"] == "EPSG:25832"


@pytest.mark.skipif(shutil.which("colmap") is None, reason="COLMAP is not installed")
def test_colmap_uses_the_exported_model_as_is(tmp_path):
    _, _, model, folder = _export(tmp_path, scale=0.2)
    colmap_checks(folder, tmp_path, model.mean_reprojection_error_px)
