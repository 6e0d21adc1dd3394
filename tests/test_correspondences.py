"""Matching of planar features into planar objects (georefine.lidar.correspondences).

Synthetic features from six views (2 strips x nadir/forward/backward) on known planes: a
long road made of many patches, flat and gabled roofs, facades, two parallel plates 0.5 m
apart, and a small surface seen once per view. Centres carry noise along the normal and a
systematic offset per view (a trajectory error), normals a small tilt and a random sign.
"""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from georefine.errors import InputError
from georefine.lidar.correspondences import (
    MatchingConfig,
    PlanarObjects,
    candidate_pairs,
    initial_object_parameters,
    inject_wrong_matches,
    match_features,
    object_planes,
    view_ids,
)
from georefine.lidar.object_files import read_objects, write_objects
from georefine.lidar.planes import PlanarFeatures

VIEWS = [(s, c) for s in (0, 1) for c in (0, 1, 2)]
E_X, E_Y, E_Z = np.eye(3)


def _plane(name, centre, normal, u, half_u, half_v):
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    u = np.asarray(u, float) - np.dot(u, n) * n
    u /= np.linalg.norm(u)
    return {"name": name, "centre": np.asarray(centre, float), "normal": n, "u": u, "v": np.cross(n, u),
            "half": (half_u, half_v)}


def _tilted(angle_deg, toward):
    a = np.radians(angle_deg)
    return np.cos(a) * E_Z + np.sin(a) * np.asarray(toward, float)


PLANES = [
    _plane("road", (50.0, 0.0, 0.5), (-0.01, 0.0, 1.0), E_X, 50.0, 3.0),
    _plane("roof_flat_a", (15.0, 20.0, 8.0), E_Z, E_X, 5.0, 4.0),
    _plane("roof_flat_b", (45.0, 22.0, 12.0), E_Z, E_X, 4.0, 4.0),
    _plane("roof_flat_c", (75.0, -20.0, 6.0), E_Z, E_X, 5.0, 3.0),
    _plane("gable_south", (30.0, -22.0, 8.85), _tilted(30.0, -E_Y), E_X, 5.0, 2.3),
    _plane("gable_north", (30.0, -18.0, 8.85), _tilted(30.0, E_Y), E_X, 5.0, 2.3),
    _plane("facade_y", (15.0, 14.0, 4.0), -E_Y, E_X, 5.0, 3.0),
    _plane("facade_x", (60.0, 15.0, 5.0), E_X, E_Y, 5.0, 4.0),
    _plane("facade_road", (47.5, 8.0, 4.0), -E_Y, E_X, 7.5, 3.0),
    _plane("plate_low", (90.0, 15.0, 3.0), E_Z, E_X, 3.0, 3.0),
    _plane("plate_high", (90.0, 15.0, 3.5), E_Z, E_X, 3.0, 3.0),
]


def _features_on(planes, rng, spacing_m=2.0, views=VIEWS, sigma_n_m=0.01, view_offset_m=0.04, tilt_deg=0.2):
    """Features on ``planes`` from every view; returns (features, plane index per feature)."""
    parts, truth = [], []
    offsets = rng.normal(0.0, view_offset_m, (len(views), 3))
    for k, pl in enumerate(planes):
        hu, hv = pl["half"]
        for iv, (strip, channel) in enumerate(views):
            o = rng.uniform(0.0, spacing_m, 2)
            gu = np.arange(-hu + 0.3 + o[0] % spacing_m, hu - 0.3, spacing_m)
            gv = np.arange(-hv + 0.3 + o[1] % spacing_m, hv - 0.3, spacing_m)
            gu, gv = (g if g.size else np.zeros(1) for g in (gu, gv))  # small surfaces: one patch
            uu, vv = (a.ravel() for a in np.meshgrid(gu, gv))
            uu = np.clip(uu + rng.normal(0, 0.2, uu.size), -hu, hu)
            vv = np.clip(vv + rng.normal(0, 0.2, vv.size), -hv, hv)
            m = uu.size
            c = pl["centre"] + uu[:, None] * pl["u"] + vv[:, None] * pl["v"]
            c = c + rng.normal(0, sigma_n_m, (m, 1)) * pl["normal"] + offsets[iv]
            n = pl["normal"] + np.radians(tilt_deg) * rng.normal(0, 1, (m, 3))
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            n *= np.where(rng.random(m) < 0.3, -1.0, 1.0)[:, None]
            parts.append(dict(strip=np.full(m, strip), channel=np.full(m, channel), centre=c, normal=n))
            truth.append(np.full(m, k))
    return _make_features(parts, rng), np.concatenate(truth)


def _make_features(parts, rng):
    cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    f = cat["strip"].size
    zeros3 = np.zeros((f, 3))
    return PlanarFeatures(
        strip=cat["strip"], channel=cat["channel"], time=np.arange(f, dtype=float),
        centre_s=zeros3, axis1_s=np.tile(E_X, (f, 1)), axis2_s=np.tile(E_Y, (f, 1)), normal_s=np.tile(E_Z, (f, 1)),
        centre_w=cat["centre"], normal_w=cat["normal"], n_points=np.full(f, 60),
        roughness_m=np.full(f, 0.01), extent_m=np.full(f, 1.0),
        sigma_d_m=rng.uniform(0.005, 0.02, f), sigma_slope_rad=rng.uniform(0.002, 0.01, f),
        seed_cell=np.floor(cat["centre"]).astype(np.int64),
    )


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(20250616)
    features, truth = _features_on(PLANES, rng)
    return features, truth


UNBALANCED = MatchingConfig(max_objects_per_cell=10_000)


def _members(objects):
    fo = objects.feature_object
    order = np.argsort(fo, kind="stable")
    order = order[fo[order] >= 0]
    return np.split(order, np.cumsum(objects.n_features)[:-1]) if len(objects) else []


def _cells(objects, cell_m):
    return np.unique(np.floor(objects.c0[:, :2] / cell_m).astype(int), axis=0, return_inverse=True)[1].ravel()


def test_objects_recover_the_true_planes(scene):
    features, truth = scene
    cfg = UNBALANCED
    objects = match_features(features, cfg)
    members = _members(objects)
    assert len(objects) > 50
    # Precision 100 %: every object lies on one true plane.
    obj_plane = np.array([np.unique(truth[m]).size for m in members])
    assert np.all(obj_plane == 1)
    plane_of = np.array([truth[m[0]] for m in members])
    # Recall: every plane has objects; most features are used.
    assert set(plane_of.tolist()) == set(range(len(PLANES)))
    assert (objects.feature_object >= 0).mean() > 0.85
    # Frames: orthonormal right-handed, on the true plane.
    assert np.allclose(np.cross(objects.k1, objects.k2), objects.n0, atol=1e-12)
    true_n = np.array([PLANES[k]["normal"] for k in plane_of])
    true_c = np.array([PLANES[k]["centre"] for k in plane_of])
    assert np.degrees(np.arccos(np.minimum(np.abs(np.einsum("ij,ij->i", true_n, objects.n0)), 1.0))).max() < 0.5
    assert np.abs(np.einsum("ij,ij->i", objects.c0 - true_c, true_n)).max() < 0.15
    assert np.all(objects.n0[~objects.is_vertical, 2] > 0)
    is_facade = np.array([PLANES[k]["name"].startswith("facade") for k in plane_of])
    assert np.array_equal(objects.is_vertical, is_facade)
    # Rule 4 and the cap hold for every member against the final frame.
    view = view_ids(features)
    for o, m in enumerate(members):
        d = features.centre_w[m] - objects.c0[o]
        assert np.abs(d @ objects.n0[o]).max() <= cfg.max_plane_distance_m
        assert np.linalg.norm(d, axis=1).max() <= cfg.max_object_radius_m
        assert np.abs(features.normal_w[m] @ objects.n0[o]).min() >= np.cos(np.radians(cfg.max_normal_angle_deg))
        assert 2 <= m.size <= cfg.max_features_per_object
        assert np.unique(view[m]).size == objects.n_views[o] >= cfg.min_views_per_object
    summary = objects.summary()
    assert summary["n_objects"] == len(objects) and summary["n_features_used"] == objects.n_features.sum()


def test_long_road_is_split_not_chained(scene):
    features, truth = scene
    cfg = UNBALANCED
    pairs = candidate_pairs(features, cfg)
    road = truth == 0
    # The road's pair graph is one chain over its whole length ...
    rp = pairs[road[pairs[:, 0]] & road[pairs[:, 1]]]
    g = coo_matrix((np.ones(len(rp)), (rp[:, 0], rp[:, 1])), shape=(road.size, road.size))
    labels = connected_components(g, directed=False)[1]
    sizes = np.bincount(labels[road])
    assert sizes.max() > 0.8 * road.sum()
    # ... but becomes many small objects.
    objects = match_features(features, cfg)
    on_road = np.unique(objects.feature_object[road & (objects.feature_object >= 0)])
    assert on_road.size >= 40
    assert objects.n_features[on_road].max() <= cfg.max_features_per_object
    extent = [np.ptp(features.centre_w[m, 0]) for m in _members(objects) if truth[m[0]] == 0]
    assert max(extent) <= 2 * cfg.max_object_radius_m


def test_small_surface_seen_once_per_view_is_one_object():
    rng = np.random.default_rng(3)
    small = [_plane("chimney", (5.0, 5.0, 12.0), _tilted(10.0, E_X), E_Y, 0.5, 0.5)]
    features, _ = _features_on(small, rng, spacing_m=3.0)
    assert len(features) == len(VIEWS)
    objects = match_features(features, MatchingConfig())
    assert len(objects) == 1
    assert objects.n_features[0] == objects.n_views[0] == len(VIEWS)
    assert not objects.is_vertical[0]


def test_same_view_features_are_not_matched(scene):
    features, _ = scene
    view = view_ids(features)
    pairs = candidate_pairs(features, MatchingConfig())
    assert len(pairs) > 0 and np.all(view[pairs[:, 0]] != view[pairs[:, 1]])
    one_view = features.select(view == view[0])
    assert len(match_features(one_view, MatchingConfig())) == 0
    loose = MatchingConfig(cross_view_only=False, min_views_per_object=1)
    assert len(match_features(one_view, loose)) > 0


def test_parallel_planes_half_a_metre_apart_stay_apart():
    rng = np.random.default_rng(11)
    plates = [p for p in PLANES if p["name"].startswith("plate")]
    features, truth = _features_on(plates, rng, spacing_m=1.0)
    objects = match_features(features, UNBALANCED)
    members = _members(objects)
    assert len(members) > 10
    assert all(np.unique(truth[m]).size == 1 for m in members)
    assert {int(truth[m[0]]) for m in members} == {0, 1}
    # Parallel planes inside the distance bound would be merged: the bound is what separates them.
    merged = match_features(features, UNBALANCED.model_copy(update={"max_plane_distance_m": 0.6}))
    assert any(np.unique(truth[m]).size == 2 for m in _members(merged))


def test_curved_surface_objects_keep_consistent_normals():
    # A cylinder of 30 m radius: neighbouring patches differ by ~2 deg, the whole arc by 40 deg.
    rng = np.random.default_rng(5)
    phi = np.radians(np.linspace(-20.0, 20.0, 21))
    parts = []
    for strip, channel in VIEWS:
        p = phi + rng.normal(0, 0.005, phi.size)
        n = np.stack([np.sin(p), np.zeros_like(p), np.cos(p)], axis=1)
        parts.append(dict(strip=np.full(p.size, strip), channel=np.full(p.size, channel), centre=30.0 * n, normal=n))
    features = _make_features(parts, rng)
    cfg = MatchingConfig()
    objects = match_features(features, cfg)
    assert len(objects) >= 5
    for o, m in enumerate(_members(objects)):
        cos = np.abs(features.normal_w[m] @ objects.n0[o])
        assert cos.min() >= np.cos(np.radians(cfg.max_normal_angle_deg))


def test_balancing_caps_cells_and_keeps_facades(scene):
    features, truth = scene
    cfg = MatchingConfig()
    full = match_features(features, UNBALANCED)
    kept = match_features(features, cfg)
    assert len(kept) < len(full)
    counts = np.bincount(_cells(kept, cfg.balance_cell_m))
    assert counts.max() <= cfg.max_objects_per_cell
    # Per cell: vertical and other objects are picked alternately, facades first, so a
    # cell keeps min(V, max(ceil(cap/2), cap - H)) of its V facade and H other objects.
    cap = cfg.max_objects_per_cell
    cell_full = {tuple(c) for c in np.floor(full.c0[:, :2] / cfg.balance_cell_m).astype(int)}

    def count(objects, cell, vertical):
        in_cell = np.all(np.floor(objects.c0[:, :2] / cfg.balance_cell_m).astype(int) == cell, axis=1)
        return int((in_cell & (objects.is_vertical == vertical)).sum())

    for cell in cell_full:
        v, h = count(full, cell, True), count(full, cell, False)
        assert count(kept, cell, True) == min(v, max(-(-cap // 2), cap - h))
        assert count(kept, cell, True) + count(kept, cell, False) == min(v + h, cap)
    # Within a cell and class the kept objects are the best (most views) ones.
    key_full = {tuple(c): i for i, c in enumerate(np.round(full.c0, 9))}
    kept_in_full = np.array([key_full[tuple(c)] for c in np.round(kept.c0, 9)])
    dropped = np.setdiff1d(np.arange(len(full)), kept_in_full)
    cell_of = np.floor(full.c0[:, :2] / cfg.balance_cell_m).astype(int)
    for i in dropped:
        same = kept_in_full[np.all(cell_of[kept_in_full] == cell_of[i], axis=1)
                            & (full.is_vertical[kept_in_full] == full.is_vertical[i])]
        assert same.size and full.n_views[same].min() >= full.n_views[i]
    # Each facade plane keeps objects, and so does the road.
    planes_kept = {int(truth[m[0]]) for m in _members(kept)}
    names = {PLANES[k]["name"] for k in planes_kept}
    assert {"facade_y", "facade_x", "facade_road", "road"} <= names


def test_balancing_along_a_track_axis(scene):
    features, _ = scene
    cfg = MatchingConfig(balance_cell_m=10.0, max_objects_per_cell=3)
    objects = match_features(features, cfg, track_axis=lambda p_w: p_w[:, 0])
    bins = np.floor(objects.c0[:, 0] / cfg.balance_cell_m).astype(int)
    assert np.bincount(bins - bins.min()).max() <= 3
    assert len(objects) >= 3 * 8
    with pytest.raises(ValueError, match="track_axis"):
        match_features(features, cfg, track_axis=lambda p_w: p_w[:, :2])


def test_initial_parameters_are_zero_and_give_the_frame(scene):
    features, _ = scene
    objects = match_features(features, MatchingConfig())
    params = initial_object_parameters(objects, features)
    assert params.shape == (len(objects), 3) and not params.any()
    c, n = object_planes(objects, params)
    assert np.array_equal(c, objects.c0) and np.allclose(n, objects.n0, atol=1e-15)
    c, n = object_planes(objects, np.tile([0.1, 0.01, 0.0], (len(objects), 1)))
    assert np.allclose(c - objects.c0, 0.1 * objects.n0)
    assert np.allclose(np.einsum("ij,ij->i", n, objects.k1), 0.01 / np.sqrt(1.0001))


def test_write_read_round_trip(scene, tmp_path):
    features, _ = scene
    objects = match_features(features, MatchingConfig())
    path = write_objects(tmp_path / "objects.csv", objects)
    back = read_objects(path)
    assert np.array_equal(back.feature_object, objects.feature_object)
    for name in ("n_features", "n_views", "is_vertical"):
        assert np.array_equal(getattr(back, name), getattr(objects, name))
    for name in ("c0", "k1", "k2", "n0"):
        assert np.allclose(getattr(back, name), getattr(objects, name), atol=1e-6, rtol=0)
    text = path.read_text().splitlines()
    assert text[2].startswith("object,c0_x_m") and len(text) == 3 + len(objects)
    # Empty object sets round-trip too.
    empty = match_features(features.select(np.zeros(len(features), bool)), MatchingConfig())
    assert len(read_objects(write_objects(tmp_path / "empty.csv", empty))) == 0
    # A damaged member list is reported with its line.
    bad = text[:3] + [text[3].rsplit(",", 1)[0] + ",999999999"] + text[4:]
    (tmp_path / "bad.csv").write_text("\n".join(bad) + "\n")
    with pytest.raises(InputError, match="line 4"):
        read_objects(tmp_path / "bad.csv")


@pytest.mark.parametrize("n_nearest", [5, None])
def test_inject_wrong_matches_changes_the_requested_fraction(scene, n_nearest):
    features, _ = scene
    objects = match_features(features, MatchingConfig())
    rng = np.random.default_rng(7)
    wrong, changed = inject_wrong_matches(objects, features, 0.1, rng, n_nearest=n_nearest)
    before, after = objects.feature_object, wrong.feature_object
    matched = before >= 0
    assert changed.size == round(0.1 * matched.sum())
    diff = np.flatnonzero(before != after)
    assert np.array_equal(diff, changed)
    assert np.all(after[changed] >= 0) and np.all(matched[changed])
    assert wrong.n_features.sum() == objects.n_features.sum()
    assert np.array_equal(wrong.n_features, np.bincount(after[after >= 0], minlength=len(objects)))
    assert np.array_equal(wrong.c0, objects.c0)
    same, none = inject_wrong_matches(objects, features, 0.0, rng)
    assert none.size == 0 and np.array_equal(same.feature_object, before)


def test_config_and_container_validation():
    with pytest.raises(ValidationError):
        MatchingConfig(max_centre_distance=1.0)
    with pytest.raises(ValidationError):
        MatchingConfig(max_normal_angle_deg=-1.0)
    with pytest.raises(ValueError, match="n_features"):
        PlanarObjects(c0=np.zeros((1, 3)), k1=[E_X], k2=[E_Y], n0=[E_Z], feature_object=[0, -1],
                      n_features=[2], n_views=[1], is_vertical=[False])
    with pytest.raises(ValueError, match="orthonormal"):
        PlanarObjects(c0=np.zeros((1, 3)), k1=[E_X], k2=[E_X], n0=[E_Z], feature_object=[0, 0],
                      n_features=[2], n_views=[1], is_vertical=[False])
