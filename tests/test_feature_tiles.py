"""Planar features in ground tiles (georefine.lidar.feature_tiles): the same objects as the whole flight's matching.

The synthetic scene of tests/test_correspondences.py (a 100 m road of overlapping patches that
chains into long components, roofs, gables, facades, parallel plates) laid out three times,
shifted and turned, and matched in ground tiles of one balancing cell: every object and every
frame must be the whole flight's, to the bit, whatever order the features come in.
"""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest

from georefine.lidar.correspondences import MatchingConfig, group_features, match_features
from georefine.lidar.feature_tiles import FeatureStore, SearchSample, match_store, read_rect, tile_size
from georefine.lidar.planes import PlanarFeatures
from georefine.tasks import TaskRunner
from georefine.workflows.strips import sort_features
from test_correspondences import PLANES, _features_on


def _scene(seed: int) -> PlanarFeatures:
    rng = np.random.default_rng(seed)
    parts = []
    for k, (dx, dy, turn) in enumerate([(0.0, 0.0, 0.0), (130.0, 10.0, 0.6), (40.0, 95.0, -1.1)]):
        f, _ = _features_on(PLANES, rng)
        c, s = np.cos(turn), np.sin(turn)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        parts.append(PlanarFeatures(**{
            **{fld.name: getattr(f, fld.name) for fld in fields(PlanarFeatures)},
            "centre_w": f.centre_w @ R.T + [dx, dy, 0.0], "normal_w": f.normal_w @ R.T,
            "time": f.time + 1e4 * k,
        }))
    return PlanarFeatures.concatenate(parts)


def _same(a: PlanarFeatures, b: PlanarFeatures) -> None:
    for fld in fields(PlanarFeatures):
        np.testing.assert_array_equal(getattr(a, fld.name), getattr(b, fld.name), err_msg=fld.name)


def _stored(features: PlanarFeatures, tile_m: float, rng, chunks: int = 7) -> FeatureStore:
    store = FeatureStore(tile_m)
    cuts = np.sort(rng.choice(np.arange(1, len(features)), chunks - 1, replace=False))
    for part in np.split(rng.permutation(len(features)), cuts):  # any order, any chunks
        store.add(features.select(np.sort(part)))
    return store


@pytest.mark.parametrize(("cfg", "margin_m"), [(MatchingConfig(), None), (MatchingConfig(max_objects_per_cell=10_000), None),
                                              (MatchingConfig(), 0.5)],
                         ids=["balanced", "unbalanced", "narrow-margin"])
def test_tiles_give_the_whole_flights_objects(cfg, margin_m):
    """Also from a first margin far narrower than an object (0.5 m): the tiles whose features near
    them are not settled are matched again with a wider one."""
    rng = np.random.default_rng(7)
    features = sort_features(_scene(11))
    whole = match_features(features, cfg)
    matched = whole.feature_object >= 0
    assert len(whole) > 60
    with _stored(features, tile_size(25.0, cfg), rng) as store:
        assert store.count == len(features) and len(store.tiles) > 20
        tiled = match_store(store, cfg, margin_m=margin_m)
    assert tiled.extracted == len(features)
    if margin_m:  # the anti-chaining split reaches past the first margin in every tile
        assert tiled.grown >= len(store.tiles)
    _same(tiled.features, features.select(matched))
    for name in ("c0", "k1", "k2", "n0", "n_features", "n_views", "is_vertical"):
        np.testing.assert_array_equal(getattr(tiled.objects, name), getattr(whole, name), err_msg=name)
    np.testing.assert_array_equal(tiled.objects.feature_object, whole.feature_object[matched])


def test_tiles_do_not_depend_on_the_scheduler_or_the_tile_size():
    cfg = MatchingConfig()
    features = sort_features(_scene(12))
    with _stored(features, 50.0, np.random.default_rng(1)) as store:
        sync = match_store(store, cfg)
        with TaskRunner("threads", workers=2) as runner:
            threads = match_store(store, cfg, runner)
    with _stored(features, 200.0, np.random.default_rng(2)) as store:
        big = match_store(store, cfg)
    for other in (threads, big):
        _same(other.features, sync.features)
        np.testing.assert_array_equal(other.objects.c0, sync.objects.c0)


def test_store_reads_a_rectangle_in_the_flights_order_and_cleans_up():
    features = sort_features(_scene(13))
    store = _stored(features, 30.0, np.random.default_rng(3))
    folder = store.folder
    assert sum(len(store.read_tile(ij)[0]) for ij in store.tiles) == len(features)
    everything, arrival = store.read_all()
    _same(everything, features)
    assert np.unique(arrival).size == len(features)
    rect = (10.0, -5.0, 70.0, 25.0)
    part, _ = read_rect(folder, store.tile_m, rect)
    xy = features.centre_w[:, :2]
    inside = (xy[:, 0] >= 10) & (xy[:, 0] < 70) & (xy[:, 1] >= -5) & (xy[:, 1] < 25)
    _same(part, features.select(inside))
    store.close()
    assert not folder.exists()


def test_search_sample_is_bounded_and_independent_of_the_order():
    features = sort_features(_scene(14))
    samples = []  # a sample with a small bound, fed in two different orders
    for rng in (np.random.default_rng(6), np.random.default_rng(8)):
        s = SearchSample(500)
        for part in np.array_split(rng.permutation(len(features)), 9):
            part = np.sort(part)
            s.add(features.select(part), part)
        samples.append(s.features())
    assert len(samples[0]) == 500
    _same(samples[0], samples[1])
    n = features.normal_w / np.linalg.norm(features.normal_w, axis=1, keepdims=True)
    assert np.all(np.abs(samples[0].normal_w[:, 2] / np.linalg.norm(samples[0].normal_w, axis=1))
                  < np.cos(np.radians(10.0)))
    assert (np.abs(n[:, 2]) < np.cos(np.radians(10.0))).sum() > 500


def _member_sets(group: np.ndarray, ids: np.ndarray) -> dict[int, frozenset]:
    """Feature id -> the ids of its group's members (features in a group only)."""
    sets = {}
    for g in np.unique(group[group >= 0]):
        members = frozenset(ids[group == g].tolist())
        sets.update(dict.fromkeys(members, members))
    return sets


def test_settled_features_are_grouped_as_in_the_whole_flight():
    """Cut rectangles out of the scene: every feature ``group_features`` calls settled is in the
    group (as a set of features) that it is in when the whole scene is matched, and features near
    the cut that it does not call settled are, some of them, grouped otherwise."""
    cfg = MatchingConfig()
    features = sort_features(_scene(15))
    ids = np.arange(len(features))
    whole = _member_sets(group_features(features, cfg).group, ids)
    rng = np.random.default_rng(4)
    xy = features.centre_w[:, :2]
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    settled_total = differ_unsettled = 0
    for _ in range(12):
        a = rng.uniform(lo, hi - 20.0)
        b = a + rng.uniform(15.0, 60.0, 2)
        inside = np.all((xy >= a) & (xy < b), axis=1)
        cut = features.select(inside)
        cxy = cut.centre_w[:, :2]
        inner = cfg.max_centre_distance_m + 1e-6
        open_ = np.any((cxy <= a + inner) | (cxy >= b - inner), axis=1)
        grouping = group_features(cut, cfg, open_)
        part = _member_sets(grouping.group, ids[inside])
        for k, i in enumerate(ids[inside]):
            same = part.get(int(i)) == whole.get(int(i))
            if grouping.settled[k]:
                assert same, f"feature {i} settled but grouped otherwise"
                settled_total += 1
            elif not same:
                differ_unsettled += 1
    assert settled_total > 500 and differ_unsettled > 0


def test_a_transformed_store_keeps_the_arrival_order_and_closes_the_old_one():
    """What the time offset does to a store: every tile through a function (here: later times,
    the first feature of each tile dropped) into a new store, in the flight's order."""
    features = sort_features(_scene(16))
    store = _stored(features, 40.0, np.random.default_rng(9))
    old_folder = store.folder
    everything, arrival = store.read_all()

    def later(f, a):
        keep = np.arange(1, len(f))
        moved = f.select(keep)
        return PlanarFeatures(**{**{fld.name: getattr(moved, fld.name) for fld in fields(PlanarFeatures)},
                                 "time": moved.time + 0.5}), a[keep]

    new = store.transformed(later)
    assert not old_folder.exists() and new.folder.exists()
    got, got_arrival = new.read_all()
    assert len(got) == len(features) - len(store.tiles)
    dropped = set(arrival.tolist()) - set(got_arrival.tolist())
    assert len(dropped) == len(store.tiles)
    kept = np.isin(arrival, got_arrival)
    np.testing.assert_array_equal(got.time, everything.time[kept] + 0.5)  # the same order, shifted
    np.testing.assert_array_equal(got_arrival, arrival[kept])
    new.close()
    broken = _stored(features, 40.0, np.random.default_rng(10))
    before = set(broken.folder.parent.glob("georefine-features-*"))

    def fail(f, a):
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError):  # a failing function leaves neither store's folder behind
        broken.transformed(fail)
    assert set(broken.folder.parent.glob("georefine-features-*")) == before - {broken.folder}
