"""The sample of planar features the G/I/L adjustment takes (docs/ARCHITECTURE.md §4.5 step 5).

With more matched features than ``max_features``, each outer iteration adjusts a sample. A
fresh random draw would change the sample, and with it the trajectory, from one outer iteration
to the next; here every feature has a pseudo-random key fixed by what it is (strip, channel,
seed voxel), and the sample is the features with the smallest keys (a bottom-k sample), so a
feature extracted again keeps its place in it.
"""

from __future__ import annotations

import numpy as np

from georefine.lidar.planes import PlanarFeatures

__all__ = ["feature_keys", "stable_subset"]


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
    its key. The features with the smallest keys are a random-like sample that stays the same
    from one outer iteration to the next (:func:`stable_subset`).
    """
    h = np.full(len(features), 0x9E3779B97F4A7C15, dtype=np.uint64)
    for column in (features.strip, features.channel, *features.seed_cell.T):
        h = _mix64(h ^ np.asarray(column, dtype=np.int64).astype(np.uint64))
    return h


def stable_subset(index: np.ndarray, keys: np.ndarray, size: int) -> np.ndarray:
    """The ``size`` entries of ``index`` with the smallest ``keys[index]``, in increasing order.

    A bottom-k sample: where two sets of candidates share most of their keys, their samples share
    most of their members, unlike two independent random draws.
    """
    index = np.asarray(index)
    if index.size <= size:
        return np.sort(index)
    k = keys[index]
    return np.sort(index[np.argpartition(k, size - 1)[:size]])
