"""Lidargrams: z-buffer with splats, ULPI consistency, occlusion, chunking, hole filling, files."""

from __future__ import annotations

import numpy as np
import pytest

from georefine.errors import InputError
from georefine.geometry.camera import Camera, R_w_c_from_opk, project_points
from georefine.lidargrammetry.render import (
    Lidargram,
    LidargramCanvas,
    estimate_point_spacing,
    load_lidargram,
    render_lidargram,
    save_lidargram,
)

CAM = Camera(640, 480, 560.0, 561.0, 321.7, 238.4, k1=-0.12, k2=0.04, k3=-0.005, p1=3e-4, p2=-2e-4)


def _scene(rng):
    """~50 k points: a 1 m grid on a tilted plane (220 m x 220 m) and three boxes on it (m)."""
    g = np.arange(-110.0, 110.0, 1.0)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    parts = [np.stack([x, y, 0.08 * x - 0.05 * y], axis=1)]
    for cx, cy, size, height in ((-30.0, 20.0, 24.0, 15.0), (25.0, -15.0, 18.0, 25.0), (40.0, 40.0, 12.0, 8.0)):
        s = np.arange(-size / 2, size / 2, 0.7)
        tx, ty = (a.ravel() for a in np.meshgrid(s, s))
        base = 0.08 * cx - 0.05 * cy
        parts.append(np.stack([cx + tx, cy + ty, np.full_like(tx, base + height)], axis=1))
        hz = np.arange(base, base + height, 0.7)
        for sx, sy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            a, b = (c.ravel() for c in np.meshgrid(s, hz))
            px = cx + (np.full_like(a, sx * size / 2) if sx else a)
            py = cy + (np.full_like(a, sy * size / 2) if sy else a)
            parts.append(np.stack([px, py, b], axis=1))
    pts = np.concatenate(parts) + rng.normal(0.0, 0.02, (sum(len(q) for q in parts), 3))
    return pts, rng.gamma(4.0, 20.0, len(pts))


def _pose():
    """An oblique photo from 260 m above the scene."""
    return R_w_c_from_opk(np.deg2rad(8.0), np.deg2rad(-5.0), np.deg2rad(20.0)), np.array([10.0, -5.0, 260.0])


def _z_c(points, R, p):
    return ((points - p) @ R)[:, 2]


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(1)
    pts, inten = _scene(rng)
    R, p = _pose()
    return pts, inten, R, p, render_lidargram(pts, inten, CAM, R, p)


def test_every_shown_pixel_lies_in_the_splat_of_its_point_and_uv_depth_are_exact(scene):
    pts, _, R, p, lg = scene
    assert 0.5 < lg.point_spacing_m < 1.0 and len(pts) > 40_000
    shown = lg.shown_mask
    assert shown.mean() > 0.5
    rows, cols = np.nonzero(shown)
    idx = lg.ulpi[rows, cols]
    uv, in_front = project_points(CAM, pts[idx], R, p)
    z = _z_c(pts[idx], R, p)
    assert in_front.all()
    r = np.clip(0.5 * lg.point_spacing_m * CAM.fx_px / z, 0.5, 7)
    assert np.all(np.abs(cols + 0.5 - uv[:, 0]) <= r + 1e-9)
    assert np.all(np.abs(rows + 0.5 - uv[:, 1]) <= r + 1e-9)
    np.testing.assert_allclose(lg.depth[rows, cols], z, rtol=1e-6)
    assert np.all(np.isnan(lg.depth[~shown])) and np.all(lg.image[~shown] == 0)
    np.testing.assert_array_equal(lg.point_index, np.unique(idx))
    np.testing.assert_allclose(lg.point_uv, project_points(CAM, pts[lg.point_index], R, p)[0], atol=1e-9)
    np.testing.assert_array_equal(lg.uv_of(lg.point_index[::7]), lg.point_uv[::7])
    assert np.isnan(lg.uv_of([-5])).all()
    np.testing.assert_array_equal(lg.ulpi_at(np.stack([cols, rows], 1) + 0.3), idx)


def test_the_pixel_of_a_points_projection_shows_it_or_a_nearer_point(scene):
    pts, _, R, p, lg = scene
    uv, _ = project_points(CAM, pts, R, p)
    z = _z_c(pts, R, p)
    own = CAM.inside(uv) & (uv[:, 0] < CAM.width_px) & (uv[:, 1] < CAM.height_px)
    winner = lg.ulpi[np.floor(uv[own, 1]).astype(int), np.floor(uv[own, 0]).astype(int)]
    assert np.all(winner >= 0)
    me = np.flatnonzero(own)
    zw, zm = z[winner], z[me]
    assert np.all((winner == me) | (zw < zm) | ((zw == zm) & (winner < me)))
    # and on this sampling many points win their own pixel
    assert np.mean(winner == me) > 0.3


def test_a_near_square_occludes_the_far_plane():
    cam = Camera(300, 200, 250.0, 250.0, 150.2, 99.7, k1=-0.1, k2=0.02, p1=1e-4)
    rng = np.random.default_rng(2)
    g = np.arange(-80.0, 80.0, 0.5)
    fx, fy = (a.ravel() for a in np.meshgrid(g, g))
    far = np.stack([fx, fy, np.full_like(fx, 100.0)], 1)
    s = np.arange(-5.0, 5.0, 0.25)
    nx, ny = (a.ravel() for a in np.meshgrid(s, s))
    near = np.stack([nx + 3.0, ny - 2.0, np.full_like(nx, 50.0)], 1)
    pts = np.concatenate([far, near])
    order = rng.permutation(len(pts))  # near points anywhere in the arrays
    pts = pts[order]
    is_near = order >= len(far)
    lg = render_lidargram(pts, rng.uniform(0, 100, len(pts)), cam, np.eye(3), np.zeros(3))
    cols, rows = np.meshgrid(np.arange(cam.width_px) + 0.5, np.arange(cam.height_px) + 0.5)
    rays = cam.rays(np.stack([cols.ravel(), rows.ravel()], 1))
    hit = rays[:, :2] * (50.0 / rays[:, 2:3]) - [3.0, -2.0]
    covered = (np.abs(hit) < 5.0 - 0.5).all(axis=1).reshape(cols.shape)
    assert covered.sum() > 400
    assert np.all(lg.ulpi[covered] >= 0) and np.all(is_near[lg.ulpi[covered]])
    np.testing.assert_allclose(lg.depth[covered], 50.0, rtol=1e-6)
    elsewhere = lg.ulpi[~covered & lg.shown_mask]
    assert (~is_near[elsewhere]).sum() > 0.9 * elsewhere.size


def test_points_behind_the_camera_too_near_or_outside_the_view_never_appear():
    cam = Camera(400, 300, 400.0, 400.0, 200.0, 150.0, k1=-0.3)
    rng = np.random.default_rng(3)
    uv = rng.uniform([0, 0], [400, 300], (3000, 2))
    front = cam.rays(uv) * (60.0 / cam.rays(uv)[:, 2:3])
    behind = -front[:500] * 0.5          # projects to the same pixels, nearer in |z|
    too_near = front[500:800] * (0.05 / 60.0)
    fold = np.array([[1.5, 0.0, 1.0], [-1.5, 0.1, 1.0], [0.2, 1.6, 1.0]]) * 20.0  # folds back into the image
    assert cam.inside(cam.project(fold)).all()
    outside = np.array([[1.0, 0.0, 1.0], [0.0, -0.9, 1.0]]) * 30.0  # beyond the image border (and the splats)
    assert not cam.inside(cam.project(outside), margin_px=-10).any()
    pts = np.concatenate([behind, too_near, fold, outside, front])
    bad = np.arange(len(pts) - len(front))
    lg = render_lidargram(pts, np.ones(len(pts)), cam, np.eye(3), np.zeros(3), point_spacing_m=0.5)
    assert not np.isin(bad, lg.point_index).any() and not np.isin(bad, lg.ulpi).any()
    assert lg.point_index.size > 1000
    assert np.all(lg.image[lg.shown_mask] == 128)  # constant intensity


def test_chunking_does_not_change_the_result_and_ties_go_to_the_lower_index(scene):
    pts, inten, R, p, lg = scene
    dup = np.concatenate([pts, pts[:5000]])  # exact duplicates, higher indices, other intensities
    dup_int = np.concatenate([inten, inten[:5000] + 50.0])
    spacing = lg.point_spacing_m
    a = render_lidargram(dup, dup_int, CAM, R, p, point_spacing_m=spacing)
    b = render_lidargram(dup, dup_int, CAM, R, p, point_spacing_m=spacing, chunk_size=1000)
    for f in ("image", "depth", "ulpi", "point_index", "point_uv"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    assert a.point_index.max() < len(pts)
    np.testing.assert_array_equal(a.ulpi, lg.ulpi)


def test_a_canvas_fed_in_parts_with_identifiers_renders_the_whole_cloud(scene):
    """Parts of uneven size, identifiers with gaps (a subset of a larger cloud): the lidargram of
    the points held whole, its ULPI and point indices mapped to the identifiers."""
    pts, inten, R, p, lg = scene
    rng = np.random.default_rng(12)
    ids = np.cumsum(rng.integers(1, 4, len(pts)))
    canvas = LidargramCanvas(CAM, R, p, point_spacing_m=lg.point_spacing_m, chunk_size=3000)
    cuts = np.sort(rng.choice(np.arange(1, len(pts)), 6, replace=False))
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(pts)]):
        canvas.add(pts[a:b], inten[a:b], ids[a:b])
    got = canvas.finish()
    np.testing.assert_array_equal(got.ulpi, np.where(lg.ulpi >= 0, ids[np.maximum(lg.ulpi, 0)], -1))
    np.testing.assert_array_equal(got.point_index, ids[lg.point_index])
    for f in ("image", "depth", "point_uv"):
        np.testing.assert_array_equal(getattr(got, f), getattr(lg, f))


def test_hole_filling_fills_image_and_depth_only():
    cam = Camera(200, 150, 200.0, 200.0, 100.0, 75.0, k1=-0.05)
    rng = np.random.default_rng(4)
    n = int(1.5 * 200 * 150 * 0.64)  # ~1.5 points per pixel over the central 80 % x 80 %
    uv = rng.uniform([20, 15], [180, 135], (n, 2))
    pts = cam.rays(uv) * (40.0 / cam.rays(uv)[:, 2:3])
    inten = rng.uniform(0, 1000, n)
    kw = dict(point_spacing_m=1e-3)  # splat radius 0.5 px: holes
    plain = render_lidargram(pts, inten, cam, np.eye(3), np.zeros(3), **kw)
    filled = render_lidargram(pts, inten, cam, np.eye(3), np.zeros(3), fill_holes=True, **kw)
    np.testing.assert_array_equal(filled.ulpi, plain.ulpi)
    np.testing.assert_array_equal(filled.point_index, plain.point_index)
    shown = plain.shown_mask
    np.testing.assert_array_equal(filled.image[shown], plain.image[shown])
    np.testing.assert_array_equal(filled.depth[shown], plain.depth[shown])
    new = filled.filled_mask
    assert new.sum() > 0.3 * (~shown[20:130, 25:175]).sum() and not new[:10].any()
    pad = np.pad(shown, 1)
    nbrs = sum(pad[1 + dr:1 + dr + 150, 1 + dc:1 + dc + 200]
               for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc)
    np.testing.assert_array_equal(new, ~shown & (nbrs >= 5))
    # a filled pixel copies one of its shown neighbours (depth and grey together)
    for r, c in np.argwhere(new)[:200]:
        nb = [(r + dr, c + dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if shown[r + dr, c + dc]]
        assert (filled.depth[r, c], filled.image[r, c]) in [(plain.depth[q], plain.image[q]) for q in nb]


def test_save_load_round_trip_and_bad_files(scene, tmp_path):
    lg = scene[4]
    png, npz = save_lidargram(lg, tmp_path, "lg_0001")
    assert png.is_file() and npz.is_file() and not list(tmp_path.glob(".*part"))
    back = load_lidargram(tmp_path, "lg_0001", CAM)
    for f in ("R_w_c", "p_w_c", "image", "depth", "ulpi", "point_index", "point_uv"):
        a, b = getattr(lg, f), getattr(back, f)
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    assert back.point_spacing_m == lg.point_spacing_m

    with pytest.raises(InputError, match="different camera"):
        load_lidargram(tmp_path, "lg_0001", Camera(640, 480, 561.0, 561.0, 321.7, 238.4))
    with pytest.raises(InputError, match="file not found"):
        load_lidargram(tmp_path, "missing", CAM)

    data = npz.read_bytes()
    (tmp_path / "cut.png").write_bytes(png.read_bytes())
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="not a readable lidargram"):
        load_lidargram(tmp_path, "cut", CAM)

    with np.load(npz) as z:
        arrays = dict(z)
    arrays["depth"] = arrays["depth"][:-1]
    (tmp_path / "bad.png").write_bytes(png.read_bytes())
    np.savez_compressed(tmp_path / "bad.npz", **arrays)
    with pytest.raises(InputError, match="depth") as err:
        load_lidargram(tmp_path, "bad", CAM)
    assert err.value.field == "depth" and "(480, 640)" in err.value.expected

    del arrays["ulpi"]
    np.savez_compressed(tmp_path / "bad.npz", **arrays)
    with pytest.raises(InputError, match="ulpi"):
        load_lidargram(tmp_path, "bad", CAM)


def test_empty_cloud_and_spacing_estimate():
    lg = render_lidargram(np.zeros((0, 3)), np.zeros(0), CAM, np.eye(3), np.zeros(3), point_spacing_m=1.0)
    assert isinstance(lg, Lidargram) and lg.point_index.size == 0 and not lg.shown_mask.any()
    assert lg.uv_of([0, 1]).shape == (2, 2)
    g = np.arange(0.0, 50.0, 0.4)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    assert estimate_point_spacing(np.stack([x, y, 0 * x], 1)) == pytest.approx(0.4)
