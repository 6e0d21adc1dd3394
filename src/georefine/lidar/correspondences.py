"""Plane correspondences: planar features of different views grouped into planar objects.

docs/ARCHITECTURE.md §4.5 step 4, §4.3; paper 000, §2: features of one view (strip x scanner channel) are
matched to nearby features of *other* views and all corresponding features are aggregated
into a planar object, the model of the physical surface. A nadir/forward/backward scanner
sees every surface from three views within seconds in one pass, so the matches constrain
pitch and heading without cross strips; vertical planes (facades) fix horizontal position.

Matching rules (:func:`match_features`)
---------------------------------------
1. **Candidate pairs** (:func:`candidate_pairs`): feature centres ``c_w`` closer than
   ``max_centre_distance_m`` (:class:`scipy.spatial.cKDTree`), kept when (a) the views
   differ (``cross_view_only``), (b) the normals agree up to sign, ``|n_i . n_j| >=
   cos(max_normal_angle_deg)`` (normals point to the scanner, so a thin surface seen from
   both sides has opposite ones), (c) each centre lies within ``max_plane_distance_m`` of
   the other's plane, both ways: parallel surfaces further apart are never linked.
2. **Union-find**: the connected components of the accepted-pair graph
   (:func:`scipy.sparse.csgraph.connected_components`).
3. **Anti-chaining**: components are transitive, so a long road covered by overlapping
   patches is one component tens of metres long, which is *not* one planar object. A
   component is one object only when every member centre lies within
   ``max_object_radius_m`` (default 2 x ``max_centre_distance_m``) of its weighted
   centroid. Any other component is split into *stars*: in rounds, a free feature whose
   priority (more accepted free neighbours, then smaller ``sigma_d_m``, then index) beats
   all its free neighbours' is a seed, and each free neighbour of a seed joins its best
   adjacent seed. Seeds are never adjacent, so stars are disjoint and every member is within
   ``max_centre_distance_m`` of its seed. Features without a free neighbour stay unused.
4. **Member check** against the object plane (frame below), repeated until stable: a
   member whose normal deviates from ``n0`` by more than ``max_normal_angle_deg``, or
   whose centre lies further than ``max_plane_distance_m`` from the plane or than
   ``max_object_radius_m`` from ``c0``, is dropped (this also stops normals drifting
   slowly along a curved surface).
5. **Cap**: at most ``max_features_per_object`` members, the best (smallest ``sigma_d_m``)
   feature of each view first, then the next best of each view, and so on.
6. **Views**: an object needs at least 2 members from at least ``min_views_per_object``
   distinct views.
7. **Balancing along the track**: per square horizontal cell of ``balance_cell_m`` (or
   per bin of the along-track coordinate when ``track_axis`` is given) at most
   ``max_objects_per_cell`` objects are kept. Vertical and other objects are ranked
   separately (more views, more members, smaller mean ``sigma_d_m``) and picked
   alternately, facades first: a cell keeps its facades (horizontal position) and its
   roofs and roads (height, roll, pitch).

Object frame and parameters
---------------------------
Fixed per object, in ``w``: ``c0`` the weighted mean of the member centres (weights
``1/sigma_d^2``); ``n0`` the normalised weighted mean of the member normals (weights
``1/sigma_slope^2``), each flipped to agree with the best member's, then turned upward
(``n0_z > 0``) unless vertical (facades keep the best member's side, towards the scanner);
``k1 = normalize(h x n0)``, ``h = e_z`` (``e_x`` when ``|n0_z| >= 0.9``), ``k2 = n0 x k1``:
``[k1 k2 n0]`` is right-handed orthonormal, ``k1`` horizontal on facades. The adjustment
estimates ``(d, alpha, beta)``: ``n = normalize(n0 + alpha k1 + beta k2)``, ``c = c0 + d n0``
(docs/ARCHITECTURE.md §4.3).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from georefine.config import MatchingConfig
from georefine.lidar.planes import PlanarFeatures

__all__ = [
    "Grouping", "MatchingConfig", "PlanarObjects", "balanced", "candidate_pairs", "group_features", "match_features",
    "objects_from_groups", "initial_object_parameters",
    "object_planes", "inject_wrong_matches", "view_ids",
]

_log = logging.getLogger(__name__)



@dataclass(frozen=True)
class PlanarObjects:
    """Planar objects and the assignment of features to them.

    Attributes
    ----------
    c0, k1, k2, n0 : (O, 3) float64
        Fixed reference frame of each object in ``w``: point on the plane (m), in-plane unit
        axes and unit normal, ``[k1 k2 n0]`` right-handed orthonormal.
    feature_object : (F,) int64
        Object of each input feature, -1 if unused.
    n_features, n_views : (O,) int64
        Members and distinct views (strip, channel) per object.
    is_vertical : (O,) bool
        ``|n0_z| < sin(vertical_max_tilt_deg)``: facades, which fix the horizontal position.
    """

    c0: np.ndarray
    k1: np.ndarray
    k2: np.ndarray
    n0: np.ndarray
    feature_object: np.ndarray
    n_features: np.ndarray
    n_views: np.ndarray
    is_vertical: np.ndarray

    def __post_init__(self) -> None:
        n_obj = np.asarray(self.c0).shape[0] if np.ndim(self.c0) == 2 else -1
        for name in ("c0", "k1", "k2", "n0"):
            a = np.ascontiguousarray(getattr(self, name), dtype=np.float64)
            if a.shape != (n_obj, 3) or not np.all(np.isfinite(a)):
                raise ValueError(f"{name} must be a finite (O,3) array with O={n_obj}, got shape {a.shape}")
            object.__setattr__(self, name, a)
        for name, dtype in (("n_features", np.int64), ("n_views", np.int64), ("is_vertical", bool)):
            a = np.asarray(getattr(self, name)).astype(dtype)
            if a.shape != (n_obj,):
                raise ValueError(f"{name} must have shape ({n_obj},), got {a.shape}")
            object.__setattr__(self, name, a)
        fo = np.asarray(self.feature_object).astype(np.int64)
        if fo.ndim != 1 or (fo.size and (fo.min() < -1 or fo.max() >= n_obj)):
            raise ValueError(f"feature_object must be (F,) with values in [-1, {n_obj})")
        object.__setattr__(self, "feature_object", fo)
        if not np.array_equal(np.bincount(fo[fo >= 0], minlength=n_obj), self.n_features):
            raise ValueError("n_features does not match the counts in feature_object")
        basis = np.stack([self.k1, self.k2, self.n0], axis=1)
        orthonormal = np.abs(basis @ basis.transpose(0, 2, 1) - np.eye(3)).max(initial=0.0) <= 1e-6
        if not orthonormal or np.any(np.linalg.det(basis) < 0):
            raise ValueError("[k1 k2 n0] must be right-handed orthonormal")

    def __len__(self) -> int:
        return self.c0.shape[0]

    def to_dict(self) -> dict[str, np.ndarray]:
        """All attributes as a dict of arrays (for ``np.savez`` and reports)."""
        return {name: getattr(self, name) for name in self.__dataclass_fields__}

    def summary(self) -> dict[str, float]:
        """Counts for logs and reports: objects, vertical objects, features used, means per object."""
        o = len(self)
        return {
            "n_objects": o, "n_vertical": int(self.is_vertical.sum()),
            "n_features_total": int(self.feature_object.size), "n_features_used": int(self.n_features.sum()),
            "mean_features_per_object": float(self.n_features.mean()) if o else 0.0,
            "mean_views_per_object": float(self.n_views.mean()) if o else 0.0,
        }


# --------------------------------------------------------------------------- helpers on groups (vectorised)


def view_ids(features: PlanarFeatures) -> np.ndarray:
    """(F,) int64 index of each feature's view among the distinct (strip, channel) pairs, sorted."""
    key = np.asarray(features.strip, np.int64) * 65536 + (np.asarray(features.channel, np.int64) + 32768)
    return np.unique(key, return_inverse=True)[1].ravel().astype(np.int64)


def _group_sum(group: np.ndarray, values: np.ndarray, n_groups: int) -> np.ndarray:
    """Column-wise sums of ``values`` (M,k) per group -> (n_groups, k)."""
    return np.stack([np.bincount(group, values[:, k], n_groups) for k in range(values.shape[1])], axis=1)


def _rank_in_group(sorted_group: np.ndarray) -> np.ndarray:
    """0, 1, 2, ... within each run of equal values of an already sorted key."""
    n = sorted_group.size
    if n == 0:
        return np.zeros(0, np.int64)
    start = np.r_[True, sorted_group[1:] != sorted_group[:-1]]
    first = np.flatnonzero(start)
    return np.arange(n) - np.repeat(first, np.diff(np.r_[first, n]))


def _count_views(obj: np.ndarray, view: np.ndarray, n_obj: int) -> np.ndarray:
    """Distinct views per object from members' object ``obj`` and ``view`` (M,)."""
    n_view = int(view.max(initial=-1)) + 1
    return np.bincount(np.unique(_pair_key(obj, view)) // max(n_view, 1), minlength=n_obj).astype(np.int64)


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _feature_arrays(features: PlanarFeatures) -> tuple[np.ndarray, ...]:
    """Centres, unit normals, centre and normal weights; checks the sigmas."""
    centre = np.asarray(features.centre_w, np.float64)
    normal = _normalize(np.asarray(features.normal_w, np.float64))
    sd = np.asarray(features.sigma_d_m, np.float64)
    ss = np.asarray(features.sigma_slope_rad, np.float64)
    if not (np.all(np.isfinite(sd) & (sd > 0)) and np.all(np.isfinite(ss) & (ss > 0))):
        raise ValueError("sigma_d_m and sigma_slope_rad must be finite and positive")
    return centre, normal, 1.0 / sd**2, 1.0 / ss**2


def _frames(
    obj: np.ndarray, idx: np.ndarray, features: PlanarFeatures, n_obj: int, sin_vertical: float
) -> tuple[np.ndarray, ...]:
    """Object frames (c0, k1, k2, n0) and is_vertical from members ``idx`` of objects ``obj``."""
    centre, normal, w_c, w_n = _feature_arrays(features)
    c, n, wc, wn = centre[idx], normal[idx], w_c[idx], w_n[idx]
    best = np.lexsort((-wn, obj))  # best normal weight first within each object
    first = best[np.r_[True, obj[best][1:] != obj[best][:-1]]] if obj.size else best
    ref = np.zeros((n_obj, 3))
    ref[obj[first]] = n[first]
    n = n * np.where(np.einsum("ij,ij->i", n, ref[obj]) < 0.0, -1.0, 1.0)[:, None]
    c0 = _group_sum(obj, wc[:, None] * c, n_obj) / np.bincount(obj, wc, n_obj)[:, None]
    n0 = _normalize(_group_sum(obj, wn[:, None] * n, n_obj))
    vertical = np.abs(n0[:, 2]) < sin_vertical
    n0 = np.where(((n0[:, 2] < 0.0) & ~vertical)[:, None], -n0, n0)
    h = np.where((np.abs(n0[:, 2]) < 0.9)[:, None], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    k1 = _normalize(np.cross(h, n0))
    k2 = np.cross(n0, k1)
    return c0, k1, k2, n0, vertical


# --------------------------------------------------------------------------- matching


PAIR_BLOCK = 2_000_000  # candidate pairs tested at a time in candidate_pairs (bounds its temporaries)


def candidate_pairs(features: PlanarFeatures, cfg: MatchingConfig) -> np.ndarray:
    """Accepted feature pairs (rule 1 of the module docstring).

    Returns
    -------
    (P, 2) int64
        Feature indices ``i < j`` of every accepted pair.
    """
    centre, normal, _, _ = _feature_arrays(features)
    pairs = cKDTree(centre).query_pairs(cfg.max_centre_distance_m, output_type="ndarray")
    if pairs.size == 0:
        return np.zeros((0, 2), np.int64)
    view, cos_max = view_ids(features) if cfg.cross_view_only else None, np.cos(np.radians(cfg.max_normal_angle_deg))
    # In blocks: a long flight has tens of millions of pairs, whose (P, 3) temporaries take GBs.
    ok = np.empty(len(pairs), bool)
    for a in range(0, len(pairs), PAIR_BLOCK):
        i, j = pairs[a:a + PAIR_BLOCK, 0], pairs[a:a + PAIR_BLOCK, 1]
        good = np.ones(i.size, bool) if view is None else view[i] != view[j]
        good &= np.abs(np.einsum("ij,ij->i", normal[i], normal[j])) >= cos_max
        dc = centre[j] - centre[i]
        good &= np.abs(np.einsum("ij,ij->i", normal[i], dc)) <= cfg.max_plane_distance_m
        good &= np.abs(np.einsum("ij,ij->i", normal[j], dc)) <= cfg.max_plane_distance_m
        ok[a:a + PAIR_BLOCK] = good
    return pairs[ok].astype(np.int64)


def _star_split(active: np.ndarray, pairs: np.ndarray, sigma_d: np.ndarray) -> tuple[np.ndarray, int]:
    """Split the features flagged ``active`` into disjoint stars (rule 3); -1 = unassigned.

    Returns the seed feature index of each feature's star (seeds map to themselves), and the
    rounds that assigned features. A round decides a feature from the free features within 3
    hops of the pair graph (its and its neighbours' degrees make the seeds, a seed's neighbours
    join it), so after ``K`` rounds a feature's state depends on the features within ``3 K`` hops.
    """
    n = active.size
    star = np.full(n, -1, np.int64)
    free = active.copy()
    rounds = 0
    while True:
        e = pairs[free[pairs[:, 0]] & free[pairs[:, 1]]]
        if e.size == 0:
            return star, rounds
        rounds += 1
        a, b = e[:, 0], e[:, 1]
        degree = np.bincount(a, minlength=n) + np.bincount(b, minlength=n)
        rank = np.empty(n, np.int64)
        rank[np.lexsort((np.arange(n), sigma_d, -degree))] = np.arange(n)
        nbr_min = np.full(n, n, np.int64)
        np.minimum.at(nbr_min, a, rank[b])
        np.minimum.at(nbr_min, b, rank[a])
        seed = free & (degree > 0) & (rank < nbr_min)
        # Each free neighbour of a seed joins the best-ranked adjacent seed.
        best = np.full(n, n, np.int64)
        for s, m in ((a, b), (b, a)):
            hit = seed[s]
            np.minimum.at(best, m[hit], rank[s[hit]])
        by_rank = np.argsort(rank)
        joined = free & ~seed & (best < n)
        star[joined] = by_rank[best[joined]]
        star[seed] = np.flatnonzero(seed)
        free &= ~(seed | joined)


@dataclass(frozen=True)
class _Initial:
    """Rules 2-3: the group of each feature before the member check, its component, the split's rounds."""

    group: np.ndarray
    comp: np.ndarray
    rounds: int


def _initial_groups(features: PlanarFeatures, pairs: np.ndarray, cfg: MatchingConfig) -> _Initial:
    """Group label per feature (-1 = none) from union-find plus the anti-chaining split."""
    n = len(features)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    size = np.bincount(comp)
    in_pair = size[comp] >= 2
    centre, _, w_c, _ = _feature_arrays(features)
    centroid = _group_sum(comp, w_c[:, None] * centre, size.size) / np.bincount(comp, w_c, size.size)[:, None]
    radius = np.linalg.norm(centre - centroid[comp], axis=1)
    spread = np.zeros(size.size)
    np.maximum.at(spread, comp, radius)
    compact = spread <= cfg.max_object_radius_m
    group = np.where(in_pair & compact[comp], comp, -1)
    stars, rounds = _star_split(in_pair & ~compact[comp], pairs, np.asarray(features.sigma_d_m, np.float64))
    group = np.where(stars >= 0, size.size + stars, group)
    _log.debug("%d components with >= 2 features, %d split against chaining in %d rounds",
               int((size >= 2).sum()), int(((size >= 2) & ~compact).sum()), rounds)
    return _Initial(group, comp, rounds)


def _settled(features: PlanarFeatures, pairs: np.ndarray, init: _Initial, open_: np.ndarray,
             cfg: MatchingConfig) -> np.ndarray:
    """(F,) bool: the features whose group before the member check (rules 2-3) is, as a set of
    features, the one that ``features`` together with any features not given make; ``open_`` flags
    the features that may pair with one not given (rule 1 pairs only within ``max_centre_distance_m``).

    A component without an open member is a whole component. One with an open member is surely not
    compact when two of its members are more than ``2 max_object_radius_m`` apart along an axis;
    otherwise its members may be grouped differently. The star split decides a feature from those
    within ``3 K`` hops (``K`` rounds, :func:`_star_split`): every feature within ``3 K + 1`` hops of
    an unsure one is unsure, and a group is settled when none of its members is within one more hop
    (a member the given features miss would be a neighbour of its seed). Rules 4-6 work on each group
    alone, so a settled group gives the same object whatever else is given.
    """
    n = len(features)
    comp = init.comp
    n_comp = int(comp.max(initial=-1)) + 1
    has_open = np.bincount(comp[open_], minlength=n_comp) > 0
    centre = np.asarray(features.centre_w, np.float64)
    lo = np.full((n_comp, 3), np.inf)
    hi = np.full((n_comp, 3), -np.inf)
    np.minimum.at(lo, comp, centre)
    np.maximum.at(hi, comp, centre)
    spread_out = np.any(hi - lo > 2.0 * cfg.max_object_radius_m, axis=1)
    unsure = open_ | (has_open & ~spread_out)[comp]
    if not unsure.any():
        return np.ones(n, bool)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)).tocsr()
    hops = 3 * init.rounds + 2
    dist = dijkstra(graph, directed=False, indices=np.flatnonzero(unsure), unweighted=True, min_only=True,
                    limit=hops + 0.5)
    state_unsure = dist <= hops - 1
    near_unsure = dist <= hops
    group = init.group
    used = group >= 0
    labels, inverse = np.unique(group[used], return_inverse=True)
    bad = np.bincount(inverse.ravel(), near_unsure[used], labels.size) > 0
    settled = ~state_unsure
    settled[used] = ~bad[inverse.ravel()]
    return settled


def _relabel(group: np.ndarray) -> tuple[np.ndarray, int]:
    """Consecutive labels 0..G-1 for the labels >= 0 (ordered by first member), -1 kept."""
    out = np.full(group.size, -1, np.int64)
    used = group >= 0
    _, first, inverse = np.unique(group[used], return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first))  # label order = order of first appearance
    out[used] = order[inverse.ravel()]
    return out, first.size


def _prune(features: PlanarFeatures, group: np.ndarray, cfg: MatchingConfig, sin_vertical: float) -> np.ndarray:
    """Member check against the object plane (rule 4), repeated until no member is dropped."""
    centre, normal, _, _ = _feature_arrays(features)
    cos_max = np.cos(np.radians(cfg.max_normal_angle_deg))
    for _ in range(10):
        group, n_obj = _relabel(group)
        idx = np.flatnonzero(group >= 0)
        obj = group[idx]
        c0, _, _, n0, _ = _frames(obj, idx, features, n_obj, sin_vertical)
        d = centre[idx] - c0[obj]
        bad = (
            (np.abs(np.einsum("ij,ij->i", normal[idx], n0[obj])) < cos_max)
            | (np.abs(np.einsum("ij,ij->i", d, n0[obj])) > cfg.max_plane_distance_m)
            | (np.linalg.norm(d, axis=1) > cfg.max_object_radius_m)
        )
        # Objects left with a single member dissolve.
        group[idx[bad]] = -1
        lone = np.bincount(group[group >= 0], minlength=n_obj) < 2
        group[np.append(lone, False)[group]] = -1
        if not bad.any() and not lone.any():
            return group
    return group


def _cap_and_views(features: PlanarFeatures, group: np.ndarray, cfg: MatchingConfig) -> np.ndarray:
    """Rules 5 and 6: cap the members per object, then require enough views."""
    view = view_ids(features)
    sigma = np.asarray(features.sigma_d_m, np.float64)
    idx = np.flatnonzero(group >= 0)
    g, v, s = group[idx], view[idx], sigma[idx]
    by_view = np.lexsort((s, v, g))
    rank_in_view = np.empty(idx.size, np.int64)
    rank_in_view[by_view] = _rank_in_group(_pair_key(g, v)[by_view])
    key = np.lexsort((s, rank_in_view, g))
    drop = _rank_in_group(g[key]) >= cfg.max_features_per_object
    group = group.copy()
    group[idx[key][drop]] = -1
    group, n_obj = _relabel(group)
    used = group >= 0
    n_views = _count_views(group[used], view[used], n_obj)
    n_members = np.bincount(group[used], minlength=n_obj)
    bad = (n_views < cfg.min_views_per_object) | (n_members < 2)
    group[np.append(bad, False)[group]] = -1
    return _relabel(group)[0]


def _pair_key(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """int64 key of pairs of non-negative integers, in the lexicographic order of (a, b)."""
    return np.asarray(a, np.int64) * (int(np.max(b, initial=0)) + 1) + np.asarray(b, np.int64)


def _balance(
    c0: np.ndarray, vertical: np.ndarray, n_views: np.ndarray, n_members: np.ndarray, mean_sigma: np.ndarray,
    cfg: MatchingConfig, track_axis: Callable[[np.ndarray], np.ndarray] | None,
) -> np.ndarray:
    """Rule 7: (O,) bool, the objects kept by the balancing along the track."""
    if track_axis is None:
        cells = np.floor(c0[:, :2] / cfg.balance_cell_m).astype(np.int64)
    else:
        along_m = np.asarray(track_axis(c0), np.float64).reshape(-1)
        if along_m.shape != (c0.shape[0],):
            raise ValueError(f"track_axis must map (O,3) positions to (O,), got shape {along_m.shape}")
        cells = np.floor(along_m / cfg.balance_cell_m).astype(np.int64)[:, None]
    cell = np.unique(cells, axis=0, return_inverse=True)[1].ravel()
    cls = (~vertical).astype(np.int64)  # 0 = vertical, preferred on ties
    quality = np.lexsort((mean_sigma, -n_members, -n_views, cls, cell))
    rank_in_class = np.empty(c0.shape[0], np.int64)
    rank_in_class[quality] = _rank_in_group(_pair_key(cell, cls)[quality])
    pick = np.lexsort((cls, rank_in_class, cell))
    keep = np.zeros(c0.shape[0], bool)
    keep[pick[_rank_in_group(cell[pick]) < cfg.max_objects_per_cell]] = True
    return keep


def _objects_from_groups(features: PlanarFeatures, group: np.ndarray, sin_vertical: float) -> PlanarObjects:
    """Objects (frames, counts) from a group label per feature."""
    group, n_obj = _relabel(group)
    idx = np.flatnonzero(group >= 0)
    obj = group[idx]
    c0, k1, k2, n0, vertical = _frames(obj, idx, features, n_obj, sin_vertical)
    return PlanarObjects(
        c0=c0, k1=k1, k2=k2, n0=n0, feature_object=group,
        n_features=np.bincount(obj, minlength=n_obj), n_views=_count_views(obj, view_ids(features)[idx], n_obj),
        is_vertical=vertical,
    )


def match_features(
    features: PlanarFeatures,
    cfg: MatchingConfig,
    track_axis: Callable[[np.ndarray], np.ndarray] | None = None,
) -> PlanarObjects:
    """Match planar features of different views and group them into planar objects.

    Implements rules 1-7 of the module docstring (docs/ARCHITECTURE.md §4.5 step 4; paper 000, §2).

    Parameters
    ----------
    features
        F planar features with centres and normals in ``w`` under the current trajectory.
    cfg
        Matching thresholds.
    track_axis
        Optional map of (O,3) positions in ``w`` to (O,) along-track coordinates (m), e.g.
        the arc length of the nearest trajectory point; balancing then bins along the track
        instead of in horizontal square cells.

    Returns
    -------
    PlanarObjects
        Objects with their fixed frames; ``feature_object`` maps every input feature.
    """
    n = len(features)
    sin_vertical = np.sin(np.radians(cfg.vertical_max_tilt_deg))
    if n == 0:
        return _objects_from_groups(features, np.zeros(0, np.int64), sin_vertical)
    grouping = group_features(features, cfg)
    group, n_pairs = grouping.group, grouping.n_pairs
    objects = _objects_from_groups(features, group, sin_vertical)
    group = objects.feature_object.copy()
    keep = balanced(objects, features, cfg, track_axis)
    group[np.append(~keep, False)[group]] = -1
    objects = _objects_from_groups(features, group, sin_vertical)
    _log.info(
        "matched %d of %d features into %d planar objects (%d vertical) from %d accepted pairs",
        int(objects.n_features.sum()), n, len(objects), int(objects.is_vertical.sum()), n_pairs,
    )
    return objects


@dataclass(frozen=True)
class Grouping:
    """Rules 1-6 on a set of features (:func:`group_features`)."""

    group: np.ndarray
    """(F,) int64 object of each feature (-1 = none), numbered by first member."""
    n_pairs: int
    """Accepted pairs (rule 1)."""
    settled: np.ndarray | None
    """(F,) bool, with ``open_``: the features whose group is the one the features not given would
    not change (``settled`` before the member check, :func:`_settled`); None without ``open_``."""
    rounds: int
    """Rounds of the anti-chaining split (rule 3)."""


def group_features(features: PlanarFeatures, cfg: MatchingConfig, open_: np.ndarray | None = None) -> Grouping:
    """Rules 1-6: the group of each feature (-1 = none).

    Every step works on each component of the pair graph alone (ties broken by the features'
    order); with ``open_`` (the features that may pair with features not given) the result says
    which features' groups those others cannot change (:mod:`georefine.lidar.feature_tiles`
    matches ground tiles on that ground).
    """
    sin_vertical = np.sin(np.radians(cfg.vertical_max_tilt_deg))
    pairs = candidate_pairs(features, cfg)
    init = _initial_groups(features, pairs, cfg)
    settled = None if open_ is None else _settled(features, pairs, init, np.asarray(open_, bool), cfg)
    group = _prune(features, init.group, cfg, sin_vertical)
    return Grouping(_cap_and_views(features, group, cfg), len(pairs), settled, init.rounds)


def balanced(objects: PlanarObjects, features: PlanarFeatures, cfg: MatchingConfig,
             track_axis: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """Rule 7: (O,) bool, the ``objects`` (of ``features``) the balancing keeps; each cell on its own."""
    group = objects.feature_object
    used = group >= 0
    mean_sigma = np.bincount(group[used], np.asarray(features.sigma_d_m)[used], len(objects)) / objects.n_features
    return _balance(objects.c0, objects.is_vertical, objects.n_views, objects.n_features, mean_sigma, cfg, track_axis)


def objects_from_groups(features: PlanarFeatures, group: np.ndarray, cfg: MatchingConfig) -> PlanarObjects:
    """Objects (frames, counts) from a group label per feature (-1 = none), numbered by first member."""
    return _objects_from_groups(features, group, np.sin(np.radians(cfg.vertical_max_tilt_deg)))


def initial_object_parameters(objects: PlanarObjects, features: PlanarFeatures) -> np.ndarray:
    """Initial object parameters ``[d, alpha, beta]`` (O,3), zero by construction.

    The frame ``(c0, k1, k2, n0)`` of each object *is* the weighted estimate of its plane
    from its member features under the trajectory used for matching, so the plane
    ``c = c0 + d n0``, ``n = normalize(n0 + alpha k1 + beta k2)`` starts at ``d = alpha =
    beta = 0``. ``features`` is only checked to be the set the objects index.
    """
    if len(features) != objects.feature_object.size:
        raise ValueError(f"objects index {objects.feature_object.size} features, got {len(features)}")
    return np.zeros((len(objects), 3))


def object_planes(objects: PlanarObjects, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Plane centre and unit normal (both (O,3), in ``w``) from parameters ``[d, alpha, beta]`` (O,3).

    ``c = c0 + d n0``, ``n = normalize(n0 + alpha k1 + beta k2)`` (docs/ARCHITECTURE.md §4.3).
    """
    p = np.asarray(params, np.float64).reshape(len(objects), 3)
    c = objects.c0 + p[:, :1] * objects.n0
    n = _normalize(objects.n0 + p[:, 1:2] * objects.k1 + p[:, 2:3] * objects.k2)
    return c, n


def inject_wrong_matches(
    objects: PlanarObjects,
    features: PlanarFeatures,
    fraction: float,
    rng: np.random.Generator,
    n_nearest: int | None = 5,
) -> tuple[PlanarObjects, np.ndarray]:
    """Testing aid: reassign a fraction of the matched features to wrong objects.

    Exactly ``round(fraction * M)`` of the M matched features, drawn without replacement,
    move to another object: one drawn uniformly from the ``n_nearest`` objects whose
    ``c0`` is nearest to the feature's centre (other than its own), or from all other
    objects when ``n_nearest`` is None. Nearby wrong objects are what a real matcher
    confuses. Object frames are left unchanged; ``n_features`` and ``n_views`` are updated.

    Returns
    -------
    objects
        The perturbed objects.
    changed : (K,) int64
        Indices of the reassigned features, sorted.
    """
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"fraction must be in [0, 1], got {fraction}")
    matched = np.flatnonzero(objects.feature_object >= 0)
    k = int(np.rint(fraction * matched.size))
    n_obj = len(objects)
    if k and n_obj < 2:
        raise ValueError("wrong matches need at least two objects")
    changed = np.sort(rng.choice(matched, size=k, replace=False)) if k else np.zeros(0, np.int64)
    own = objects.feature_object[changed]
    if k == 0:
        new = own
    elif n_nearest is None:
        new = rng.integers(0, n_obj - 1, size=k)
        new = new + (new >= own)  # uniform over the other objects
    else:
        m = min(n_nearest, n_obj - 1)
        centre = np.asarray(features.centre_w, np.float64)[changed]
        _, cand = cKDTree(objects.c0).query(centre, k=m + 1)
        cand = np.asarray(cand).reshape(k, m + 1)
        is_own = cand == own[:, None]
        # Own object last (stable), then draw one of the first m.
        cand = np.take_along_axis(cand, np.argsort(is_own, axis=1, kind="stable"), axis=1)[:, :m]
        new = cand[np.arange(k), rng.integers(0, m, size=k)]
    fo = objects.feature_object.copy()
    fo[changed] = new
    used = fo >= 0
    n_views = _count_views(fo[used], view_ids(features)[used], n_obj)
    out = replace(objects, feature_object=fo, n_features=np.bincount(fo[used], minlength=n_obj), n_views=n_views)
    return out, changed.astype(np.int64)
