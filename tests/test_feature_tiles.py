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

from georefine.lidar.correspondences import MatchingConfig, match_features
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
    """Also from a first margin far narrower than an object (0.5 m): the tiles whose components reach
    past it are matched again with a wider one (without that, objects on the tiles' edges differ)."""
    rng = np.random.default_rng(7)
    features = sort_features(_scene(11))
    whole = match_features(features, cfg)
    matched = whole.feature_object >= 0
    assert len(whole) > 60
    with _stored(features, tile_size(25.0, cfg), rng) as store:
        assert store.count == len(features) and len(store.tiles) > 20
        tiled = match_store(store, cfg, margin_m=margin_m)
    assert tiled.extracted == len(features)
    assert tiled.grown > (len(store.tiles) if margin_m else 0)  # the road's chains reach past the first margin
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
