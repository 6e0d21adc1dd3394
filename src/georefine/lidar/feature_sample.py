"""The sample of planar features the G/I/L adjustment takes (docs/ARCHITECTURE.md §4.5 step 5).

With more matched features than ``max_features``, each outer iteration adjusts a sample of
whole planar objects. A fresh random draw would change the sample, and with it the trajectory,
from one outer iteration to the next; here every feature has a pseudo-random key fixed by what
it is (strip, channel, seed voxel), every object is ranked by the smallest key among its members
(a min-hash), and the sample is the objects of smallest rank (a bottom-k sample), so an object
matched again keeps its place in it.
"""

from __future__ import annotations

import numpy as np

from georefine.lidar.planes import PlanarFeatures

__all__ = ["feature_keys", "stable_object_subset"]


def _mix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser on uint64 (wrapping arithmetic): a bijection that scatters bits."""
    x = x ^ (x >> np.uint64(30))
    x = x * np.uint64(0xBF58476D1CE4E5B9)
    x = x ^ (x >> np.uint64(27))
    x = x * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def feature_keys(features: PlanarFeatures) -> np.ndarray:
    """(F,) uint64 pseudo-random key of each feature, fixed by its strip, channel and seed voxel.

    A feature extracted again with a slightly changed trajectory keeps its seed voxel, and so
    its key, and an object keeps its rank while it keeps its smallest-keyed member
    (:func:`stable_object_subset`).
    """
    h = np.full(len(features), 0x9E3779B97F4A7C15, dtype=np.uint64)
    for column in (features.strip, features.channel, *features.seed_cell.T):
        h = _mix64(h ^ np.asarray(column, dtype=np.int64).astype(np.uint64))
    return h


def stable_object_subset(index: np.ndarray, keys: np.ndarray, feature_object: np.ndarray, size: int) -> np.ndarray:
    """Whole objects, at most ``size`` features of ``index`` in all, in increasing order.

    Each object is ranked by the smallest key among its members in ``index`` (a min-hash: an
    object that keeps that member, and gains none with a smaller key, keeps its key however its
    other members change), and objects are taken in that order, a prefix of it, while their
    members fit in ``size``. Objects with more members tend to rank first (the smallest of more
    keys is smaller), which favours the well-observed ones. Unlike a sample of single features,
    every object taken keeps all its views: a feature sample of a third of an object's twelve
    members leaves about four, often one per view or none, and an object with one member adds
    three unknowns and no redundancy.
    """
    index = np.asarray(index)
    if index.size <= size:
        return np.sort(index)
    obj = np.asarray(feature_object)[index]
    if np.any(obj < 0):
        raise ValueError("stable_object_subset: every feature of index must belong to an object")
    k = keys[index]
    order = np.lexsort((k, obj))  # by object, then key: each object's first entry holds its min-hash
    obj_sorted = obj[order]
    first = np.flatnonzero(np.r_[True, obj_sorted[1:] != obj_sorted[:-1]])
    count = np.diff(np.r_[first, obj_sorted.size])
    rank = np.argsort(k[order[first]], kind="stable")
    taken = np.cumsum(count[rank]) <= size
    chosen = np.zeros(first.size, bool)
    chosen[rank[taken]] = True
    return np.sort(index[order[np.repeat(chosen, count)]])
