"""The sample of planar features the G/I/L adjustment takes (docs/ARCHITECTURE.md §4.5 step 5).

With more matched features in a window of flight time than the budget
(``max_features_per_minute`` over ``selection_window_s``, lowered evenly where the whole flight
has more than ``max_features``), each outer iteration adjusts a sample of whole planar objects
(:func:`windowed_object_subset`): every minute of flight keeps its share of the features. A
fresh random draw would change the sample, and with it the trajectory, from one outer
iteration to the next; here every feature has a pseudo-random key fixed by what it is (strip,
channel, seed voxel), every object is ranked by what it constrains and then by the smallest key
among its members (a min-hash), so an object matched again keeps its place.
"""

from __future__ import annotations

import numba
import numpy as np

from georefine.lidar.planes import PlanarFeatures

__all__ = ["feature_keys", "shared_budget", "time_windows", "windowed_object_subset"]


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
    (:func:`windowed_object_subset`).
    """
    h = np.full(len(features), 0x9E3779B97F4A7C15, dtype=np.uint64)
    for column in (features.strip, features.channel, *features.seed_cell.T):
        h = _mix64(h ^ np.asarray(column, dtype=np.int64).astype(np.uint64))
    return h


def time_windows(time: np.ndarray, window_s: float, flight: np.ndarray | None = None) -> np.ndarray:
    """(F,) int64 window of each feature: ``floor(time / window_s)`` (fixed to the clock, not to the
    first feature, so that a window keeps its features from one outer iteration to the next),
    apart per ``flight`` (whose clocks may overlap) when given."""
    w = np.floor(np.asarray(time, np.float64) / float(window_s)).astype(np.int64)
    if flight is None:
        return w
    w -= w.min(initial=0)
    return np.asarray(flight, np.int64) * (int(w.max(initial=0)) + 1) + w


@numba.njit(cache=True)
def _greedy_windows(obj_start: np.ndarray, pair_window: np.ndarray, pair_count: np.ndarray,
                    n_windows: int, budget: int) -> np.ndarray:  # pragma: no cover - compiled
    used = np.zeros(n_windows, np.int64)
    take = np.zeros(obj_start.size - 1, np.bool_)
    for o in range(obj_start.size - 1):
        fits = True
        for k in range(obj_start[o], obj_start[o + 1]):
            if used[pair_window[k]] + pair_count[k] > budget:
                fits = False
                break
        if fits:
            take[o] = True
            for k in range(obj_start[o], obj_start[o + 1]):
                used[pair_window[k]] += pair_count[k]
    return take


def shared_budget(per_window: np.ndarray, budget: int, total: int | None) -> int:
    """The budget of every window when the windows share ``total`` evenly: the largest ``B <= budget``
    with ``sum(min(per_window, B)) <= total`` (water-filling: a window with fewer features than ``B``
    leaves its room to the others)."""
    counts = np.sort(np.asarray(per_window, np.int64))
    if total is None or np.minimum(counts, budget).sum() <= total:
        return int(budget)
    # With the k smallest windows whole, the others share what is left.
    below = np.r_[0, np.cumsum(counts)[:-1]]
    rest = counts.size - np.arange(counts.size)
    level = (total - below) // rest
    ok = level >= np.r_[0, counts[:-1]]  # the windows taken whole are all below the level
    return int(min(budget, level[np.flatnonzero(ok)[-1]]))


def windowed_object_subset(index: np.ndarray, keys: np.ndarray, feature_object: np.ndarray, window: np.ndarray,
                           strip: np.ndarray, object_vertical: np.ndarray, budget: int,
                           total: int | None = None) -> np.ndarray:
    """Whole objects, at most ``budget`` features of ``index`` in every ``window`` (:func:`time_windows`),
    and at most ``total`` in all (the windows' budget lowered evenly, :func:`shared_budget`), in
    increasing order.

    The objects are offered by what they constrain: first those seen from more strips (an object
    two passes share ties them together and fixes what one pass alone cannot), then facades
    (``object_vertical``: the horizontal position) before roofs and roads, then by min-hash (each
    object ranked by the smallest key among its members, so that an object that keeps that
    member, and gains none with a smaller key, keeps its place however its other members change).
    Each is taken while every window its members lie in has room for them (a greedy pass, written
    by hand in numba: an object that does not fit leaves the room to the next). Where the matched
    features of every window are under the budget all are taken. Unlike a sample of single
    features, every object taken keeps all its views: an object with one member adds three
    unknowns and no redundancy.
    """
    index = np.asarray(index)
    obj = np.asarray(feature_object)[index]
    if np.any(obj < 0):
        raise ValueError("windowed_object_subset: every feature of index must belong to an object")
    win = np.asarray(window, np.int64)[index]
    w_ids, win = np.unique(win, return_inverse=True)
    win = win.ravel()
    per_window = np.bincount(win, minlength=w_ids.size)
    budget = shared_budget(per_window, budget, total)
    if per_window.max(initial=0) <= budget:
        return np.sort(index)
    objs, obj_local = np.unique(obj, return_inverse=True)
    obj_local = obj_local.ravel()
    n_obj = objs.size
    k = keys[index]
    min_key = np.full(n_obj, np.iinfo(np.uint64).max, np.uint64)
    np.minimum.at(min_key, obj_local, k)
    span = int(np.max(strip, initial=0)) + 1  # distinct (object, strip) pairs per object
    n_strips = np.bincount(np.unique(obj_local.astype(np.int64) * span + np.asarray(strip, np.int64)[index]) // span,
                           minlength=n_obj)
    not_vertical = ~np.asarray(object_vertical, bool)[objs]
    rank = np.lexsort((min_key, not_vertical, -n_strips))  # objects in the order they are offered
    position = np.empty(n_obj, np.int64)
    position[rank] = np.arange(n_obj)
    # (object, window) pairs with their member counts, objects in rank order.
    pair = np.unique(position[obj_local] * w_ids.size + win, return_counts=True)
    pair_obj, pair_window = pair[0] // w_ids.size, pair[0] % w_ids.size
    obj_start = np.searchsorted(pair_obj, np.arange(n_obj + 1))
    take = _greedy_windows(obj_start, pair_window, pair[1].astype(np.int64), w_ids.size, int(budget))
    chosen = np.zeros(n_obj, bool)
    chosen[rank[take]] = True
    return np.sort(index[chosen[obj_local]])
