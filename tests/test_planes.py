"""Tests of planar feature extraction (georefine.lidar.planes)."""

from __future__ import annotations

import numpy as np
import pydantic
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from georefine.errors import InputError
from georefine.lidar.feature_sample import feature_keys, shared_budget, time_windows, windowed_object_subset
from georefine.lidar.planes import (
    CSV_COLUMNS,
    PlanarFeatures,
    PlaneExtractionConfig,
    extract_features,
    extract_features_chunked,
    read_features,
    write_features,
)

SPEED = 18.0  # m/s, along-track coordinate -> point time
# Dense patches (radius 1.5 m, 60 points/m^2: ~420 points) so that 2 mm noise gives slope
# errors of ~0.01 deg (0.08 deg at the rectangles' edges); the ranging-noise floor is below the
# noise and the sigma floors are off, so that the sigmas can be checked against the errors.
DENSE = PlaneExtractionConfig(radius_m=1.5, max_roughness_m=0.01, range_sigma_m=0.001, min_sigma_d_m=0.0,
                              min_sigma_slope_mdeg=0.0)


def random_pose_fn(rng, centre):
    """A 'scanner' platform ~150 m above ``centre``, moving and rotating smoothly at random."""
    p0 = np.asarray(centre) + np.r_[rng.uniform(-30, 30, 2), 150.0]
    v = rng.uniform(-20, 20, 3) * [1, 1, 0.1]
    R0 = Rotation.from_rotvec(rng.normal(0, 0.5, 3)).as_matrix()
    w = rng.normal(0, 0.05, 3)

    def pose_fn(t):
        t = np.asarray(t, float)
        return p0 + t[:, None] * v, R0 @ Rotation.from_rotvec(t[:, None] * w).as_matrix()

    return pose_fn


def sample_rectangle(rng, origin, e1, e2, size1, size2, density, noise):
    """Points on a rectangle ``origin + u e1 + v e2`` with Gaussian noise along its normal."""
    e1, e2 = np.asarray(e1, float), np.asarray(e2, float)
    n = int(density * size1 * size2)
    u, v = rng.uniform(0, size1, n), rng.uniform(0, size2, n)
    normal = np.cross(e1, e2)
    pts = origin + u[:, None] * e1 + v[:, None] * e2 + rng.normal(0, noise, n)[:, None] * normal
    return pts, u / SPEED


def known_planes(rng, density=60.0, noise=0.002):
    """Horizontal roof, tilted roof (30 deg, random azimuth), vertical facade, well apart."""
    az = rng.uniform(0, 2 * np.pi)
    c, s = np.cos(az), np.sin(az)
    tilt = np.radians(30.0)
    planes = [  # origin, e1, e2, size1, size2
        (np.array([0.0, 0.0, 10.0]), [1, 0, 0], [0, 1, 0], 16.0, 12.0),
        (np.array([40.0, 0.0, 10.0]), [c, s, 0], [-s * np.cos(tilt), c * np.cos(tilt), np.sin(tilt)], 14.0, 10.0),
        (np.array([80.0, 0.0, 0.0]), [0, 1, 0], [0, 0, 1], 16.0, 12.0),
    ]
    pts, t, label = [], [], []
    for k, (o, e1, e2, a, b) in enumerate(planes):
        p, tk = sample_rectangle(rng, o, e1, e2, a, b, density, noise)
        pts.append(p)
        t.append(tk + 5.0 * k)  # time = 5 k + u / SPEED, linear along e1
        label.append(np.full(len(p), k))
    geometry = {name: np.array([pl[i] for pl in planes], float) for i, name in enumerate(("origin", "e1", "e2"))}
    geometry["normal"] = np.cross(geometry["e1"], geometry["e2"])
    return np.concatenate(pts), np.concatenate(t), np.concatenate(label), geometry


def angle_deg(a, b):
    """Angle between unit vectors up to sign (deg)."""
    return np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", a, b)), 0.0, 1.0)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_known_planes(seed):
    rng = np.random.default_rng(seed)
    noise = 0.002
    pts, t, label, geometry = known_planes(rng, noise=noise)
    normals = geometry["normal"]
    pose_fn = random_pose_fn(rng, [40.0, 6.0, 10.0])
    p_b_s = rng.normal(0, 0.3, 3)
    R_b_s = Rotation.from_rotvec(rng.normal(0, 0.02, 3)).as_matrix()
    f = extract_features(pts, t, 7, 2, pose_fn, p_b_s, R_b_s, DENSE)
    assert len(f) > 60
    np.testing.assert_array_equal(f.strip, 7)
    np.testing.assert_array_equal(f.channel, 2)
    # every plane, the facade included, gives features; each is assigned by its nearest point
    k = label[cKDTree(pts).query(f.centre_w)[1]]
    assert np.all(np.bincount(k, minlength=3) >= 15)
    err = angle_deg(f.normal_w, normals[k])
    assert err.max() < 0.1, err.max()
    # the slope sigma describes the normal error (two slopes per feature), as does sigma_d the offset
    rms_slope = np.sqrt(np.mean(np.radians(err) ** 2 / (2 * f.sigma_slope_rad**2)))
    assert 0.4 < rms_slope < 1.3, rms_slope
    rel = f.centre_w - geometry["origin"][k]
    dist = np.einsum("ij,ij->i", rel, normals[k])
    assert 0.6 < np.sqrt(np.mean((dist / f.sigma_d_m) ** 2)) < 1.4
    # roughness: the orthogonal noise, up to the three fitted parameters
    corrected = f.roughness_m * np.sqrt(f.n_points / (f.n_points - 3.0))
    assert abs(np.median(corrected) / noise - 1) < 0.05
    # time is linear along e1, so the mean point time is the time at the centroid
    t_centre = 5.0 * k + np.einsum("ij,ij->i", rel, geometry["e1"][k]) / SPEED
    np.testing.assert_allclose(f.time, t_centre, atol=1e-9)
    # normals face the scanner
    p_w_b, R_w_b = pose_fn(f.time)
    p_w_s = p_w_b + R_w_b @ p_b_s
    assert np.all(np.einsum("ij,ij->i", f.normal_w, p_w_s - f.centre_w) > 0)


@pytest.mark.parametrize("seed", [3, 4])
def test_frame_transform_and_axes(seed):
    rng = np.random.default_rng(seed)
    pts, t, _, _ = known_planes(rng, density=15.0, noise=0.005)
    pose_fn = random_pose_fn(rng, [40.0, 6.0, 10.0])
    p_b_s = rng.normal(0, 0.3, 3)
    R_b_s = Rotation.from_rotvec(rng.normal(0, 0.02, 3)).as_matrix()
    f = extract_features(pts, t, 1, 0, pose_fn, p_b_s, R_b_s)
    assert len(f) > 20
    p_w_b, R_w_b = pose_fn(f.time)
    R_w_s = R_w_b @ R_b_s
    p_w_s = p_w_b + R_w_b @ p_b_s
    np.testing.assert_allclose(p_w_s + np.einsum("nij,nj->ni", R_w_s, f.centre_s), f.centre_w, atol=1e-9)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", R_w_s, f.normal_s), f.normal_w, atol=1e-12)
    for frame in ("s", "w"):
        k1 = f.axis1_s if frame == "s" else np.einsum("nij,nj->ni", R_w_s, f.axis1_s)
        k2 = f.axis2_s if frame == "s" else np.einsum("nij,nj->ni", R_w_s, f.axis2_s)
        n = f.normal_s if frame == "s" else f.normal_w
        basis = np.stack([k1, k2, n], axis=-1)
        eye = np.broadcast_to(np.eye(3), basis.shape)
        np.testing.assert_allclose(basis.transpose(0, 2, 1) @ basis, eye, atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(basis), 1.0, atol=1e-12)
    # extent 2 sqrt(l1): at most the diameter, ~ the radius (1 m) for full discs
    assert np.all(f.extent_m >= 0.5) and np.all(f.extent_m <= 2.0) and 0.85 < np.median(f.extent_m) < 1.1


def test_wire_and_clutter_give_no_features():
    rng = np.random.default_rng(11)
    # a sagging wire: 40 m span, 1.5 cm radius tube, dense points
    s = rng.uniform(0, 40, 4000)
    phi = rng.uniform(0, 2 * np.pi, s.size)
    wire = np.column_stack([s, 0.015 * np.cos(phi), 20 - 0.01 * s * (40 - s) + 0.015 * np.sin(phi)])
    # a single scan line on flat ground (a line of points on a plane)
    u = np.linspace(0, 30, 300)
    line = np.column_stack([u, np.full_like(u, 50.0), rng.normal(0, 0.005, u.size)])
    # volumetric clutter (vegetation), ~8 points/m^3
    clutter = rng.uniform([100, 0, 0], [120, 20, 10], (32_000, 3))
    # rough ground: 10 cm noise
    rough = np.column_stack([rng.uniform(200, 220, 4000), rng.uniform(0, 20, 4000), rng.normal(0, 0.1, 4000)])
    pose_fn = random_pose_fn(rng, [100.0, 10.0, 0.0])
    for pts in (wire, line, clutter, rough):
        t = pts[:, 0] / SPEED
        f = extract_features(pts, t, 0, 0, pose_fn, np.zeros(3), np.eye(3))
        assert len(f) == 0
    # all together as one view: still nothing
    pts = np.concatenate([wire, line, clutter, rough])
    assert len(extract_features(pts, pts[:, 0] / SPEED, 0, 0, pose_fn, np.zeros(3), np.eye(3))) == 0


def test_facades_survive_next_to_ground_and_roof():
    """A flat-roofed box on the ground: seeds on a horizontal grid must still give wall features."""
    rng = np.random.default_rng(5)
    parts = [sample_rectangle(rng, np.array([-30.0, -30.0, 0.0]), [1, 0, 0], [0, 1, 0], 60, 60, 8, 0.005)[0]]
    ground = parts[0]
    parts[0] = ground[~((np.abs(ground[:, 0] - 1) < 10) & (np.abs(ground[:, 1] - 3) < 6))]
    x0, x1, y0, y1, h = -9.0, 11.0, -3.0, 9.0, 8.0
    walls = [  # origin, e1, e2, length; normals outwards
        (np.array([x0, y0, 0.0]), [1, 0, 0], [0, 0, 1], x1 - x0),
        (np.array([x1, y0, 0.0]), [0, 1, 0], [0, 0, 1], y1 - y0),
        (np.array([x1, y1, 0.0]), [-1, 0, 0], [0, 0, 1], x1 - x0),
        (np.array([x0, y1, 0.0]), [0, -1, 0], [0, 0, 1], y1 - y0),
    ]
    for o, e1, e2, length in walls:
        parts.append(sample_rectangle(rng, o, e1, e2, length, h, 6, 0.005)[0])
    parts.append(sample_rectangle(rng, np.array([x0, y0, h]), [1, 0, 0], [0, 1, 0], x1 - x0, y1 - y0, 8, 0.005)[0])
    pts = np.concatenate(parts)
    t = 100.0 + pts[:, 1] / SPEED

    def pose_fn(tq):  # hovering above the building, level
        tq = np.asarray(tq, float)
        return np.tile([1.0, 3.0, 160.0], (tq.size, 1)), np.tile(np.diag([1.0, -1.0, -1.0]), (tq.size, 1, 1))

    f = extract_features(pts, t, 0, 0, pose_fn, np.zeros(3), np.eye(3))
    vertical = np.abs(f.normal_w[:, 2]) < 0.01
    n_wall = [np.count_nonzero(vertical & (angle_deg(f.normal_w, np.tile(np.cross(e1, e2), (len(f), 1))) < 0.5))
              for _, e1, e2, _ in walls]
    assert min(n_wall) >= 5, n_wall
    assert np.count_nonzero(np.abs(f.normal_w[:, 2]) > 0.9999) > 500  # ground and roof
    # walls face the scanner above: outwards and up is not possible, the sign follows the sensor
    assert np.all(np.einsum("ij,ij->i", f.normal_w, [1.0, 3.0, 160.0] - f.centre_w) > 0)


def test_sigmas_positive_and_shrink_with_more_points():
    rng = np.random.default_rng(8)
    pose_fn = random_pose_fn(rng, [10.0, 10.0, 0.0])
    cfg = PlaneExtractionConfig(min_sigma_d_m=0.0, min_sigma_slope_mdeg=0.0)
    med = []
    for density in (10.0, 40.0, 160.0):
        pts, t = sample_rectangle(rng, np.zeros(3), [1, 0, 0], [0, 1, 0], 20, 20, density, 0.01)
        f = extract_features(pts, t, 0, 0, pose_fn, np.zeros(3), np.eye(3), cfg)
        assert len(f) > 50 and np.all(f.sigma_d_m > 0) and np.all(f.sigma_slope_rad > 0)
        med.append((np.median(f.sigma_d_m), np.median(f.sigma_slope_rad), np.median(f.n_points)))
    med = np.array(med)
    assert np.all(np.diff(med[:, 0]) < 0) and np.all(np.diff(med[:, 1]) < 0)
    # ~1/sqrt(n): four times the points halve the sigmas
    np.testing.assert_allclose(med[1:, :2] / med[:-1, :2], 0.5, rtol=0.15)
    # the floors bound the sigmas from below
    floors = PlaneExtractionConfig(min_sigma_d_m=0.004, min_sigma_slope_mdeg=500.0)
    f = extract_features(pts, t, 0, 0, pose_fn, np.zeros(3), np.eye(3), floors)
    assert f.sigma_d_m.min() == pytest.approx(0.004) and f.sigma_slope_rad.min() == pytest.approx(np.radians(0.5))


def test_empty_and_small_inputs():
    pose_fn = random_pose_fn(np.random.default_rng(0), [0.0, 0.0, 0.0])
    f = extract_features(np.zeros((0, 3)), np.zeros(0), 0, 0, pose_fn, np.zeros(3), np.eye(3))
    assert len(f) == 0 and f.centre_s.shape == (0, 3) and f.strip.dtype == np.int32
    f = extract_features(np.zeros((5, 3)), np.zeros(5), 0, 0, pose_fn, np.zeros(3), np.eye(3))
    assert len(f) == 0
    with pytest.raises(ValueError):
        extract_features(np.zeros((5, 2)), np.zeros(5), 0, 0, pose_fn, np.zeros(3), np.eye(3))
    with pytest.raises(ValueError):
        extract_features(np.full((5, 3), np.nan), np.zeros(5), 0, 0, pose_fn, np.zeros(3), np.eye(3))
    with pytest.raises(pydantic.ValidationError):
        PlaneExtractionConfig(radius=1.0)


# --------------------------------------------------------------------------- simulated scan

H_AGL = 160.0
R_SOUTH = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # body x south, y west, z down
T0 = 1000.0


@pytest.fixture(scope="module")
def simulated():
    from georefine.sim.scanner import ScannerConfig, scan
    from georefine.sim.scene import SceneConfig, build_scene

    scene = build_scene(SceneConfig(length_m=300.0, width_m=300.0, end_margin_m=100.0, settlement_count=1,
                                    buildings_per_settlement=10, scattered_building_count=2),
                        np.random.default_rng(3))
    z = np.mean(scene.axis_w[:, 2]) + H_AGL

    def pose_fn(t):
        t = np.asarray(t, float)
        p = np.column_stack([np.zeros_like(t), 350.0 - SPEED * (t - T0), np.full_like(t, z)])
        return p, np.broadcast_to(R_SOUTH, (t.size, 3, 3)).copy()

    p_b_s = np.array([0.3, -0.1, 0.5])
    R_b_s = Rotation.from_rotvec([0.004, -0.006, 0.01]).as_matrix()
    cfg = ScannerConfig()  # 200 kHz: ~11 points/m^2 per view at nadir
    chunks = list(scan(pose_fn, T0, T0 + 18.0, scene, cfg, p_b_s, R_b_s, np.random.default_rng(4)))
    pts = {k: np.concatenate([getattr(c, k) for c in chunks]) for k in ("time", "xyz_s", "channel", "face_id")}
    p_w_b, R_w_b = pose_fn(pts["time"])
    pts["xyz_w"] = p_w_b + np.einsum("nij,nj->ni", R_w_b, pts["xyz_s"] @ R_b_s.T + p_b_s)
    feats = {}
    for c in range(3):
        m = pts["channel"] == c
        feats[c] = extract_features(pts["xyz_w"][m], pts["time"][m], 4, c, pose_fn, p_b_s, R_b_s)
    return scene, pts, feats, pose_fn, p_b_s, R_b_s


def test_simulated_scan_all_views_facades_and_reference_surfaces(simulated):
    from georefine.sim.scene import Material

    scene, pts, feats, *_ = simulated
    for c, f in feats.items():
        m = pts["channel"] == c
        assert len(f) > 5000
        np.testing.assert_array_equal(f.channel, c)
        # what each feature lies on: the face of the view's point nearest to its centre
        face = pts["face_id"][m][cKDTree(pts["xyz_w"][m]).query(f.centre_w)[1]]
        material = scene.face_material[face]
        assert not np.any(material == Material.WIRE)
        facade = material == Material.FACADE
        assert np.count_nonzero(facade & (np.abs(f.normal_w[:, 2]) < 0.02)) >= 50
        # building faces and reference slabs are exact planes: normals and offsets agree with them
        exact = np.isin(material, [Material.ROOF_TILE, Material.ROOF_FLAT, Material.FACADE, Material.REFERENCE])
        err = angle_deg(f.normal_w[exact], scene.surface_normal(face[exact]))
        assert np.median(err) < 0.15 and np.percentile(err, 95) < 0.5
        assert np.sqrt(np.mean(np.radians(err) ** 2 / (2 * f.sigma_slope_rad[exact] ** 2))) < 1.5
        # every reference slab (5 m square) the view covers carries features, on its plane
        covered = [ref for ref in scene.reference_surfaces
                   if np.count_nonzero(np.isin(pts["face_id"][m], ref.face_ids)) > 100]
        assert len(covered) >= 4
        for ref in covered:
            centre = ref.corners_w.mean(axis=0)
            rel = f.centre_w - centre
            on = np.all(np.abs(rel[:, :2]) < 1.5, axis=1) & (np.abs(rel[:, 2]) < 0.1)
            assert np.count_nonzero(on) >= 1, (c, ref.surface_id)
            assert np.all(angle_deg(f.normal_w[on], np.tile(ref.normal_w, (on.sum(), 1))) < 0.5)
            assert np.all(np.abs((f.centre_w[on] - centre) @ ref.normal_w) < 0.01)


def test_chunked_equals_whole_view(simulated):
    _, pts, feats, pose_fn, p_b_s, R_b_s = simulated
    m = pts["channel"] == 1
    t, xyz = pts["time"][m], pts["xyz_w"][m]
    chunks = ((t[i:i + 50_000], xyz[i:i + 50_000]) for i in range(0, t.size, 50_000))
    g = extract_features_chunked(chunks, 4, 1, pose_fn, p_b_s, R_b_s, window_s=3.0)
    f = feats[1]
    assert len(g) == len(f)
    a, b = np.lexsort(f.centre_w.T), np.lexsort(g.centre_w.T)
    np.testing.assert_allclose(g.centre_w[b], f.centre_w[a], atol=1e-9)
    np.testing.assert_allclose(g.sigma_d_m[b], f.sigma_d_m[a], rtol=1e-9)
    with pytest.raises(ValueError):
        extract_features_chunked([(t[10:20], xyz[10:20]), (t[:10], xyz[:10])], 4, 1, pose_fn, p_b_s, R_b_s)


def test_features_keep_their_keys_when_the_trajectory_changes_a_little(simulated):
    """A re-extraction after an outer iteration names the same features; the bottom-k sample of
    their keys stays the same, where two random draws would share only the sample's fraction."""
    _, pts, feats, pose_fn, p_b_s, R_b_s = simulated
    dR = Rotation.from_rotvec(np.radians([2e-3, -3e-3, 2.5e-3])).as_matrix()  # ~2-3 mdeg

    def moved(t):
        p, R = pose_fn(t)
        return p + [0.004, -0.003, 0.005], R @ dR

    m = pts["channel"] == 1
    p_w_b, R_w_b = moved(pts["time"][m])
    xyz_w = p_w_b + np.einsum("nij,nj->ni", R_w_b, pts["xyz_s"][m] @ R_b_s.T + p_b_s)
    f = feats[1]
    g = extract_features(xyz_w, pts["time"][m], 4, 1, moved, p_b_s, R_b_s)
    kf, kg = feature_keys(f), feature_keys(g)
    assert kf.dtype == np.uint64 and np.unique(kf).size == len(f)  # one feature per seed voxel
    shared = np.intersect1d(kf, kg).size
    assert shared >= 0.97 * min(len(f), len(g))
    size = len(f) // 10
    # each feature its own object: the sample is the features of smallest key (bottom-k)
    a = _one_window_subset(np.arange(len(f)), kf, np.arange(len(f)), size)
    b = _one_window_subset(np.arange(len(g)), kg, np.arange(len(g)), size)
    assert a.size == b.size == size and np.all(np.diff(a) > 0)
    assert np.intersect1d(kf[a], kg[b]).size >= 0.95 * size
    # keys do not depend on the feature order, and differ between views of the same places
    perm = np.random.default_rng(5).permutation(len(f))
    np.testing.assert_array_equal(feature_keys(f.select(perm)), kf[perm])
    assert np.intersect1d(kf, feature_keys(feats[0])).size < 0.01 * len(f)
    # the sample is spread like a random one: over time, and not tied to the seed grid's rows
    tq = np.quantile(f.time, [0.25, 0.5, 0.75])
    counts = np.bincount(np.searchsorted(tq, f.time[a]), minlength=4)
    assert np.all(np.abs(counts - size / 4) < 4 * np.sqrt(size / 4))


def _one_window_subset(index, keys, obj, size):
    """One window, one strip, no facades: the objects of smallest min-hash that fit ``size``."""
    n = keys.size
    return windowed_object_subset(index, keys, obj, np.zeros(n, np.int64), np.ones(n, np.int64),
                                  np.zeros(int(obj.max()) + 1, bool), size)


def test_windowed_object_subset_small_and_exact():
    keys = np.array([9, 3, 7, 1, 5, 2, 8], dtype=np.uint64)
    obj = np.array([0, 1, 0, 2, 1, 0, 2])  # min-hashes: object 2 -> 1, object 0 -> 2, object 1 -> 3
    np.testing.assert_array_equal(_one_window_subset(np.arange(7), keys, obj, 7), np.arange(7))
    np.testing.assert_array_equal(_one_window_subset(np.array([6, 3, 0]), keys, obj, 5), [0, 3, 6])
    np.testing.assert_array_equal(_one_window_subset(np.arange(7), keys, obj, 5), [0, 2, 3, 5, 6])
    # greedy: object 0 (3 members) does not fit after object 2, object 1 (2 members) does
    np.testing.assert_array_equal(_one_window_subset(np.arange(7), keys, obj, 4), [1, 3, 4, 6])
    # object 0 without its smallest-keyed member ranks by its next one (7), after object 1 (3)
    np.testing.assert_array_equal(_one_window_subset(np.array([0, 1, 2, 3, 4, 6]), keys, obj, 4), [1, 3, 4, 6])
    with pytest.raises(ValueError, match="object"):
        _one_window_subset(np.arange(7), keys, np.array([0, 1, 0, -1, 1, 0, 2]), 3)


def test_windowed_object_subset_keeps_each_windows_budget_and_prefers_what_constrains_more():
    """Two windows of flight time: each keeps its own budget (a long flight keeps a short one's
    density), an object counts in every window its members lie in, objects seen from two strips
    come first, then facades, then the min-hash."""
    keys = np.arange(10, dtype=np.uint64)[::-1].copy()  # later features have smaller keys
    obj = np.array([0, 0, 1, 1, 2, 2, 3, 3, 4, 4])
    window = np.array([0, 0, 0, 0, 0, 1, 1, 1, 1, 1])
    strip = np.array([1, 1, 1, 1, 1, 2, 1, 1, 2, 2])  # object 2 is seen from strips 1 and 2
    vertical = np.array([False, True, False, False, False])
    pick = windowed_object_subset(np.arange(10), keys, obj, window, strip, vertical, 3)
    # object 2 (two strips, one member in each window) first, then the facade 1 in window 0
    # (room for 2 more there), then 4 (smallest min-hash) in window 1; 0 and 3 find no room.
    np.testing.assert_array_equal(pick, [2, 3, 4, 5, 8, 9])
    per_window = np.bincount(window[pick])
    assert per_window.max() <= 3
    # under the budget in every window: all
    np.testing.assert_array_equal(windowed_object_subset(np.arange(10), keys, obj, window, strip, vertical, 6),
                                  np.arange(10))
    # a ceiling of 5 in all: the windows share it evenly (2 each); object 2 takes one in each, and
    # no object of two members in one window fits beside it
    capped = windowed_object_subset(np.arange(10), keys, obj, window, strip, vertical, 6, total=5)
    np.testing.assert_array_equal(capped, [4, 5])
    capped = windowed_object_subset(np.arange(10), keys, obj, window, strip, vertical, 6, total=6)
    np.testing.assert_array_equal(capped, [2, 3, 4, 5, 8, 9])  # 3 each: the facade 1 and object 4 fit
    # the windows follow the clock, apart per flight
    t = np.array([0.0, 59.9, 60.0, 125.0])
    np.testing.assert_array_equal(time_windows(t, 60.0), [0, 0, 1, 2])
    w = time_windows(t, 60.0, flight=np.array([0, 0, 1, 1]))
    assert w[0] == w[1] and len(set(w[1:].tolist())) == 3


def test_shared_budget_fills_the_windows_evenly():
    """Water-filling: the windows below the level are taken whole, the others share what is left."""
    assert shared_budget([10, 100, 100], 1000, 150) == 70
    assert shared_budget([10, 20, 30], 1000, 60) == 1000  # all fit
    assert shared_budget([10, 20, 30], 1000, 59) == 29
    assert shared_budget([10, 100, 100], 50, 1000) == 50  # the per-window budget binds first
    assert shared_budget([5, 5], 1000, 3) == 1
    rng = np.random.default_rng(3)
    for _ in range(50):
        counts = rng.integers(0, 500, rng.integers(1, 30))
        total = int(rng.integers(0, counts.sum() + 1))
        b = shared_budget(counts, 10_000, total)
        assert np.minimum(counts, b).sum() <= total < np.minimum(counts, b + 1).sum() or b >= counts.max()


def test_windowed_object_subset_keeps_whole_objects_and_its_sample_through_a_rematching():
    """The sample is whole objects; after a re-matching that moves a few members between
    objects and drops others, most sampled objects are sampled again (two random draws of a
    fifth of the objects would share a fifth)."""
    rng = np.random.default_rng(11)
    n_obj = 4000
    size_of = rng.integers(2, 13, n_obj)
    obj = np.repeat(np.arange(n_obj), size_of)
    keys = rng.integers(0, 2**63, obj.size, dtype=np.uint64)
    cap = obj.size // 5
    a = _one_window_subset(np.arange(obj.size), keys, obj, cap)
    assert a.size <= cap and a.size > cap - 12 and np.all(np.diff(a) > 0)
    taken = np.unique(obj[a])
    np.testing.assert_array_equal(np.bincount(obj[a], minlength=n_obj)[taken], size_of[taken])  # whole
    # the re-matching: 3 % of the features change object, 3 % are no longer matched
    obj2 = obj.copy()
    moved = rng.random(obj.size) < 0.03
    obj2[moved] = rng.integers(0, n_obj, int(moved.sum()))
    kept = np.flatnonzero(rng.random(obj.size) >= 0.03)
    b = _one_window_subset(kept, keys, obj2, cap)
    shared = np.intersect1d(taken, np.unique(obj2[b])).size
    assert shared >= 0.8 * taken.size


# --------------------------------------------------------------------------- container and files


def test_select_and_concatenate(simulated):
    _, _, feats, *_ = simulated
    f = feats[0]
    both = PlanarFeatures.concatenate([f.select(np.arange(10)), f.select(f.n_points > 20)])
    assert len(both) == 10 + np.count_nonzero(f.n_points > 20)
    np.testing.assert_array_equal(both.centre_s[:10], f.centre_s[:10])
    assert len(PlanarFeatures.concatenate([])) == 0
    with pytest.raises(ValueError):
        f.select(np.ones(3, bool))
    with pytest.raises(ValueError):
        PlanarFeatures(**{**{k: getattr(f, k) for k in f.__dataclass_fields__}, "normal_w": f.normal_w[:, :2]})


def test_write_read_round_trip(tmp_path, simulated):
    _, _, feats, *_ = simulated
    f = PlanarFeatures.concatenate(list(feats.values()))
    path = tmp_path / "features.csv"
    write_features(path, f)
    assert path.read_text().splitlines()[0] == ",".join(CSV_COLUMNS)
    g = read_features(path)
    assert len(g) == len(f)
    for name in ("strip", "channel", "n_points", "seed_cell"):
        np.testing.assert_array_equal(getattr(g, name), getattr(f, name))
        assert getattr(g, name).dtype == getattr(f, name).dtype
    np.testing.assert_allclose(g.time, f.time, atol=1e-6)
    for name in ("centre_s", "centre_w"):
        np.testing.assert_allclose(getattr(g, name), getattr(f, name), atol=1e-6)
    for name in ("axis1_s", "axis2_s", "normal_s", "normal_w"):
        np.testing.assert_allclose(getattr(g, name), getattr(f, name), atol=1e-11)
    for name in ("roughness_m", "extent_m", "sigma_d_m", "sigma_slope_rad"):
        np.testing.assert_allclose(getattr(g, name), getattr(f, name), rtol=1e-3, atol=1e-6)
    # no features: a header only
    write_features(tmp_path / "none.csv", PlanarFeatures.empty())
    assert len(read_features(tmp_path / "none.csv")) == 0


def test_read_errors_name_line_and_field(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text("strip,channel,time\n1,2,3\n")
    with pytest.raises(InputError, match="wrong header"):
        read_features(path)
    row = ",".join(["1"] * len(CSV_COLUMNS))
    path.write_text(",".join(CSV_COLUMNS) + "\n" + row + "\n" + row.replace("1", "x", 1) + "\n")
    with pytest.raises(InputError) as info:
        read_features(path)
    assert info.value.line == 3 and info.value.field == "strip"
    path.write_text(",".join(CSV_COLUMNS) + "\n" + "1.5" + row[1:] + "\n")
    with pytest.raises(InputError, match="not an integer"):
        read_features(path)
