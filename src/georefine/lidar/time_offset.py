"""The LiDAR's time offset against the navigation: found from the strips' agreement (docs/ARCHITECTURE.md §4.5).

A scanner whose time stamps run ``tau`` behind the navigation's GPS time (a synchronisation
error of milliseconds, or whole seconds: time stamps in UTC, a missed leap second) georeferences
every point with the pose ``tau`` too early. On a straight line at speed ``v`` that moves the
strip by ``v tau`` along the flight; two passes flown in opposite directions then disagree by
``2 v tau`` -- 120 m for 1 s at 60 m/s -- far beyond what feature matching and the G/I/L
adjustment (:class:`~georefine.adjustment.observations.plane.PlaneObservation` estimates the
remaining ``tau``) can bridge. :func:`search_time_offset` finds it first.

**Score.** The planar features (extracted once, in the scanner frame with their times) are
georeferenced with the trajectory at ``t_f + delta`` for a candidate ``delta``. Each feature
looks for features of *other* strips (other views of the same strip move with it) whose centre
lies within ``radius`` and whose normal agrees within ``max_normal_angle_deg``; it scores
``1 - (d / d_max)²`` for the smallest distance ``d < d_max`` of such a centre to its plane, else
0. The score of ``delta`` is the mean over the features that stay inside the trajectory's span.
Only features on tilted planes (roofs, slopes, facades) take part when there are enough of them:
flat ground agrees with itself at any along-track shift.

**Search.** A shift of ``delta`` moves a feature against its counterpart in another pass by up
to ``2 v_max delta``, so the score of a candidate reaches ``delta`` within ``d_max / (2 v_max)``.
A coarse scan over ``[-range_s, range_s]`` (around the configured offset) with ``d_max`` = 8 m
and that step finds the region; a fine scan over 1.5 coarse steps around the best candidate,
with ``d_max`` = 0.4 m and half the step that gives, places it to a millisecond or two (a
parabola through the peak), which the adjustment then refines. The fine scan looks for
counterparts within two seed spacings of the features' grid (``feature_spacing_m``, 4 m at the
default 2 m, :mod:`georefine.lidar.planes`), not within ``4 d_max``: a feature whose node the
other strip did not seed has its counterparts at the next nodes, 2 m away, and with a radius of
1.6 m a shift of about 1 m brought them in. On a simulated corridor flown at 30 m/s (300 m,
truth 0) that made the score lowest near the truth (0.720 at +2 ms, with the true trajectory)
and highest at ±14-18 ms (0.805), and the search adopted ±16 ms in all four such projects of the scenario matrix;
with the wider radius the score peaks at the truth (0.995 against 0.942 at -30 ms). A candidate moves every
counterpart into ``w`` (one compiled pass, :meth:`PoseInterpolator.transform_with_directions`),
builds a k-d tree over them and queries it; on ``corridor-tiny`` (3000 features scored against
30,000 in the coarse scan, 80,000 in the fine one, 353 candidates) the search takes a third of
the time it took with numpy's per-feature matrices: 11-16 s against 39 s on two busy cores.
The candidate is adopted when its fine score clearly beats the configured offset's (by
``min_gain``): otherwise the configured offset stays. Nothing is searched where the strips
cannot show a shift (:func:`offset_unobservable`: one strip, or strips all flown one way, whose
scan found nothing in 10-20 s), the same test by which the adjustment holds the offset.

Written by hand: no library scores a rigid time shift of a continuous-time pose against
plane-to-plane agreement; the neighbour search is scipy's cKDTree.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from georefine.lidar.georeference import PoseInterpolator
from georefine.lidar.planes import PlanarFeatures

log = logging.getLogger(__name__)

__all__ = ["MAX_POOL", "MIN_TILTED", "MIN_TRACK_ANGLE_DEG", "MOVING_M_S", "TimeOffsetSearch", "georeference_features", "offset_unobservable",
           "search_time_offset", "tilted", "time_offset_score"]

MIN_TRACK_ANGLE_DEG = 30.0
"""Strips whose tracks differ by less than this cannot show a time offset (:func:`offset_unobservable`)."""
MOVING_M_S = 5.0
"""Slower than this a strip has no track (hover, turn on the spot): its features show no offset."""

_MIN_TILT_DEG = 10.0  # features on planes tilted more than this take part ...
MIN_TILTED = 200
"""... when there are at least this many of them (:func:`tilted`)."""
MAX_POOL = 30_000
"""Default possible counterparts of the coarse scan; the fine scan's are five times as many (:func:`search_time_offset`)."""
_COARSE_D_MAX_M = 8.0
_FINE_D_MAX_M = 0.4
_MIN_INSIDE = 0.5  # a candidate must keep this fraction of the features inside the span


@dataclass(frozen=True)
class TimeOffsetSearch:
    """Result of :func:`search_time_offset` (offsets in s, to add to the strips' time stamps).

    ``configured_s`` the offset the features were extracted at; ``best_s`` the best candidate;
    ``score_best``/``score_configured`` their fine scores (mean agreement of the features, 0-1);
    ``adopted`` whether ``best_s`` replaces ``configured_s``; ``features`` the features scored;
    ``candidates`` the offsets tried; ``step_s`` the fine step; ``reason`` why nothing was
    searched or adopted (empty when adopted).
    """

    configured_s: float
    best_s: float
    score_best: float
    score_configured: float
    adopted: bool
    features: int
    candidates: int
    step_s: float
    reason: str = ""

    @property
    def offset_s(self) -> float:
        """The offset to use: the best one if adopted, else the configured one."""
        return self.best_s if self.adopted else self.configured_s

    def describe(self) -> str:
        """One line for the log and the metrics."""
        if self.adopted:
            return (
                f"the strips agree best with their time stamps shifted by {self.best_s:+.4f} s, not the configured "
                f"{self.configured_s:+.4f} s (scanner.time_offset_s): {self.score_best:.3f} against "
                f"{self.score_configured:.3f} agreement over {self.features} features, {self.candidates} offsets "
                f"tried; the adjustment goes on from {self.best_s:+.4f} s"
            )
        return f"the configured time offset {self.configured_s:+.4f} s stays: {self.reason}"

    def to_dict(self) -> dict:
        """Plain JSON values (a score that could not be computed is None, not NaN)."""
        def number(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None

        return {"configured_s": float(self.configured_s), "best_s": float(self.best_s),
                "score_best": number(self.score_best), "score_configured": number(self.score_configured),
                "adopted": bool(self.adopted), "features": int(self.features), "candidates": int(self.candidates),
                "step_s": float(self.step_s), "reason": self.reason}


def georeference_features(
    features: PlanarFeatures, poses, p_b_s: np.ndarray, R_b_s: np.ndarray, time: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Feature centres and unit normals in ``w`` (F, 3) each, from the scanner frame with the poses at ``time``.

    ``poses``: ``t -> (p_w_b (N,3), R_w_b (N,3,3))``; ``time`` defaults to the features' times.
    """
    t = features.time if time is None else np.asarray(time, dtype=float)
    return _centres_normals_w(poses, t, features.centre_s, features.normal_s, p_b_s, R_b_s)


def _centres_normals_w(poses, t, centre_s, normal_s, p_b_s, R_b_s) -> tuple[np.ndarray, np.ndarray]:
    """Scanner-frame centres and normals (N, 3) in ``w`` with the poses at ``t`` (N,)."""
    return _body_to_w(poses, t, *_in_body(centre_s, normal_s, p_b_s, R_b_s))


def _in_body(centre_s, normal_s, p_b_s, R_b_s) -> tuple[np.ndarray, np.ndarray]:
    """Scanner-frame centres and normals (N, 3) in the body frame (lever arm and boresight applied)."""
    return p_b_s + centre_s @ R_b_s.T, normal_s @ R_b_s.T


def _body_to_w(poses, t, x_b, n_b) -> tuple[np.ndarray, np.ndarray]:
    """Body-frame centres and normals (N, 3) in ``w`` with the poses at ``t`` (N,).

    A :class:`~georefine.lidar.georeference.PoseInterpolator` does it in one compiled pass (the
    search calls this for every candidate: with numpy's (N, 3, 3) temporaries it was two thirds
    of a candidate's time); any other ``t -> (p_w_b, R_w_b)`` through its matrices.
    """
    if isinstance(poses, PoseInterpolator):
        return poses.transform_with_directions(t, x_b, n_b)
    p, R = poses(t)
    return p + np.einsum("nij,nj->ni", R, x_b), np.einsum("nij,nj->ni", R, n_b)


def _groups(features: PlanarFeatures) -> np.ndarray:
    """What counts as 'another' feature: one of another strip (the views of one strip move alike)."""
    return features.strip.astype(np.int64)


def time_offset_score(
    features: PlanarFeatures, poses, span: tuple[float, float], p_b_s: np.ndarray, R_b_s: np.ndarray,
    delta_s: float, *, d_max_m: float, radius_m: float, queries: np.ndarray | None = None,
    max_normal_angle_deg: float = 5.0, k: int = 8,
) -> float:
    """Mean agreement (0-1) of ``features[queries]`` with all ``features`` of other strips when shifted by ``delta_s``.

    Every feature is a possible counterpart (a random subset would lose most of them); ``queries``
    (default all) are the features scored. NaN when fewer than half of them stay inside ``span``.
    """
    return _Scorer(features, p_b_s, R_b_s, queries).score(poses, span, delta_s, d_max_m=d_max_m, radius_m=radius_m,
                                                          max_normal_angle_deg=max_normal_angle_deg, k=k)


class _Scorer:
    """:func:`time_offset_score` for one feature set and many candidates: what does not depend on
    the candidate (body-frame geometry, groups, queries) is prepared once."""

    def __init__(self, features: PlanarFeatures, p_b_s: np.ndarray, R_b_s: np.ndarray,
                 queries: np.ndarray | None) -> None:
        self.time = features.time
        self.x_b, self.n_b = _in_body(features.centre_s, features.normal_s, p_b_s, R_b_s)
        self.group = _groups(features)
        self.queries = np.arange(len(features)) if queries is None else np.asarray(queries)
        self.total = len(features) if queries is None else np.size(queries)

    def score(self, poses, span, delta_s: float, *, d_max_m: float, radius_m: float,
              max_normal_angle_deg: float = 5.0, k: int = 8) -> float:
        t = self.time + delta_s
        inside = (t >= span[0]) & (t <= span[1])
        q = self.queries[inside[self.queries]]
        if q.size < max(10, _MIN_INSIDE * self.total):
            return float("nan")
        keep = np.flatnonzero(inside)
        # The two arrays it needs, not a copy of every field (a third of the time of a candidate).
        c, n = _body_to_w(poses, t[keep], self.x_b[keep], self.n_b[keep])
        group = self.group[keep]
        row = np.searchsorted(keep, q)  # the queries' rows among the kept features
        # An unbalanced tree builds about twice as fast and answers the same (exact) queries.
        tree = cKDTree(c, balanced_tree=False, compact_nodes=False)
        dist, idx = tree.query(c[row], k=min(k + 1, keep.size), distance_upper_bound=radius_m)
        idx = np.where(np.isfinite(dist), idx, keep.size)
        c_ext = np.vstack([c, np.full((1, 3), np.inf)])
        n_ext = np.vstack([n, np.zeros((1, 3))])
        g_ext = np.append(group, -1)
        cq, nq = c[row], n[row]
        other = (g_ext[idx] != group[row][:, None]) & (g_ext[idx] >= 0)
        cos_ok = np.abs(np.einsum("nkj,nj->nk", n_ext[idx], nq)) > np.cos(np.radians(max_normal_angle_deg))
        with np.errstate(invalid="ignore"):
            d = np.abs(np.einsum("nkj,nj->nk", c_ext[idx] - cq[:, None, :], nq))
        d = np.where(other & cos_ok & np.isfinite(d), d, np.inf)
        best = d.min(axis=1)
        return float(np.mean(np.clip(1.0 - (best / d_max_m) ** 2, 0.0, 1.0)))


def _scan(features, queries, poses, span, p_b_s, R_b_s, deltas, d_max_m, radius_m) -> np.ndarray:
    scorer = _Scorer(features, p_b_s, R_b_s, queries)
    return np.array([scorer.score(poses, span, float(d), d_max_m=d_max_m, radius_m=radius_m) for d in deltas])


def tilted(features: PlanarFeatures) -> np.ndarray:
    """(F,) bool: the features on planes tilted more than 10 degrees, the ones the search scores when there
    are :data:`MIN_TILTED` of them (flat ground agrees with itself at any along-track shift)."""
    normal_w = features.normal_w / np.linalg.norm(features.normal_w, axis=1, keepdims=True)
    return np.abs(normal_w[:, 2]) < np.cos(np.radians(_MIN_TILT_DEG))


def _pool(features: PlanarFeatures, max_pool: int, rng: np.random.Generator) -> PlanarFeatures:
    """The features on tilted planes (all if too few), at most ``max_pool`` of them."""
    on_tilted = np.flatnonzero(tilted(features))
    pool = on_tilted if on_tilted.size >= MIN_TILTED else np.arange(len(features))
    if pool.size > max_pool:
        pool = np.sort(rng.choice(pool, max_pool, replace=False))
    return features.select(pool)


def offset_unobservable(times: np.ndarray, strips: np.ndarray, velocity, samples: int = 2000) -> str | None:
    """Why features at ``times`` of ``strips`` cannot show the LiDAR time offset, or None when they can.

    An offset ``delta`` moves every point of a strip along its track by ``v delta``; the strips
    disagree by ``delta (v_1 - v_2)``, so only strips whose tracks differ see it (opposite passes
    twice the shift, crossing ones 1.4 times; the module docstring).
    With one strip, or strips whose mean horizontal directions all lie within
    :data:`MIN_TRACK_ANGLE_DEG`, what the planes say about the offset comes from the attitude
    changing during it, a second-order effect that modelling errors of the planes outweigh: on a
    simulated single pass (tactical IMU, 30 m/s at 300 m) the robust adjustment took an offset
    whose truth was 0 past 45 ms, nine of its prior's sigmas, and the pitch with it from 1.0 to 2.2
    mdeg, where the bound was 0.7 (BENCHMARKS.md). ``velocity``: ``t -> v_w`` (m/s, ``w``
    horizontal in its first two axes); at most ``samples`` times per strip are used.
    """
    times, strips = np.asarray(times, dtype=float), np.asarray(strips)
    directions = []
    for strip in np.unique(strips):
        t = times[strips == strip]
        t = t[np.linspace(0, t.size - 1, min(samples, t.size)).astype(int)]
        v = np.asarray(velocity(t), dtype=float)[:, :2]
        speed = np.linalg.norm(v, axis=1)
        moving = speed > MOVING_M_S
        if np.any(moving):
            mean = np.mean(v[moving] / speed[moving, None], axis=0)
            directions.append(mean / max(float(np.linalg.norm(mean)), 1e-12))
    if len(directions) < 2:
        if np.unique(strips).size < 2:
            return "one strip only: a time offset moves all its views alike"
        return (f"one strip flown faster than {MOVING_M_S:g} m/s only: a time offset moves all its views alike, "
                "and a strip without a track none")
    d = np.asarray(directions)
    spread = float(np.degrees(np.arccos(np.clip(np.min(d @ d.T), -1.0, 1.0))))
    if spread < MIN_TRACK_ANGLE_DEG:
        return (f"the strips were flown one way (their tracks within {spread:.0f} degrees): "
                "a time offset moves all their views alike")
    return None


def _velocity(poses, span: tuple[float, float], h: float = 0.5):
    """``t -> v_w`` from ``poses`` by central differences over ``2 h`` seconds, times clamped to ``span``.

    Enough to tell the strips' tracks apart (:func:`offset_unobservable`) at times the configured
    offset may still leave seconds off, or outside the trajectory.
    """
    lo, hi = span[0] + h, span[1] - h

    def velocity(t: np.ndarray) -> np.ndarray:
        t = np.clip(np.asarray(t, dtype=float), lo, max(lo, hi))
        return (poses(t + h)[0] - poses(t - h)[0]) / (2.0 * h)

    return velocity


def search_time_offset(
    features: PlanarFeatures, poses, span: tuple[float, float], p_b_s: np.ndarray, R_b_s: np.ndarray,
    *, speed_max_m_s: float, configured_s: float = 0.0, range_s: float = 20.0, max_features: int = 3000,
    max_pool: int = MAX_POOL, min_gain: float = 0.05, seed: int = 0, feature_spacing_m: float = 2.0,
) -> TimeOffsetSearch:
    """Search the LiDAR time offset that makes the strips agree best (module docstring).

    Parameters
    ----------
    features
        Planar features of all views; their ``time`` is relative to the epoch with ``configured_s``
        already applied, their ``normal_w`` picks the tilted ones.
    poses, span
        The trajectory (``t -> (p_w_b, R_w_b)``, e.g. a
        :class:`~georefine.lidar.georeference.PoseInterpolator`) and its time span (s).
    p_b_s, R_b_s
        Scanner lever arm (m) and boresight.
    speed_max_m_s
        The highest speed of the flight (sets the steps).
    configured_s
        The offset the features' times include.
    range_s
        Candidates lie within ``configured_s ± range_s``.
    max_features, max_pool
        At most ``max_features`` (tilted) features are scored (a seeded random subset), against
        at most ``max_pool`` possible counterparts in the coarse scan and five times as many in
        the fine one (a thinned pool flattens the fine peak: it loses most counterparts).
    feature_spacing_m
        The seed spacing of the features' grid (``processing.planes.seed_spacing_m``): the fine
        scan's counterparts lie within twice it (module docstring).
    min_gain
        The best candidate is adopted when its fine score exceeds the configured offset's by
        this fraction of it and by 0.02 in absolute terms, and lies more than a fine step from
        it. On ``corridor`` (18 m/s) the configured offset scores as well as the best candidate
        when it is right (0.981 against 0.981), 0.882 against 0.979 when it is 50 ms off and 0.929
        against 0.976 when 20 ms (adopted by a hair); a smaller offset is left to the adjustment,
        which estimates it from a prior 5 ms wide around the configured one.
    """
    rng = np.random.default_rng(seed)
    if len(features) == 0:
        return TimeOffsetSearch(configured_s, configured_s, float("nan"), float("nan"), False, 0, 0, 0.0,
                                "no planar features")
    unobservable = offset_unobservable(features.time, features.strip, _velocity(poses, span))
    if unobservable is not None:  # one strip, or strips flown one way: the views move alike
        return TimeOffsetSearch(configured_s, configured_s, float("nan"), float("nan"), False, len(features), 0,
                                0.0, unobservable)
    full = _pool(features, 5 * max_pool, rng)  # the fine scan's counterparts
    in_coarse = np.sort(rng.permutation(len(full))[:max_pool])
    sub = full.select(in_coarse)  # the coarse scan's
    queries = np.sort(rng.choice(len(sub), min(max_features, len(sub)), replace=False))
    fine_queries = in_coarse[queries]
    speed = max(float(speed_max_m_s), 1.0)
    coarse_step = _COARSE_D_MAX_M / (2.0 * speed)
    fine_step = _FINE_D_MAX_M / (2.0 * speed) / 2.0
    n = int(np.ceil(range_s / coarse_step))
    coarse = coarse_step * np.arange(-n, n + 1)
    scores = _scan(sub, queries, poses, span, p_b_s, R_b_s, coarse, _COARSE_D_MAX_M, 2.0 * _COARSE_D_MAX_M)
    if not np.any(np.isfinite(scores)):
        return TimeOffsetSearch(configured_s, configured_s, float("nan"), float("nan"), False, queries.size, coarse.size,
                                fine_step, "no candidate keeps the features inside the trajectory")
    centre = coarse[int(np.nanargmax(scores))]
    half = int(np.ceil(1.5 * coarse_step / fine_step))
    fine = centre + fine_step * np.arange(-half, half + 1)
    fine_radius = max(4.0 * _FINE_D_MAX_M, 2.0 * feature_spacing_m)  # past the next seed node (module docstring)
    fine_scores = _scan(full, fine_queries, poses, span, p_b_s, R_b_s, fine, _FINE_D_MAX_M, fine_radius)
    j = int(np.nanargmax(fine_scores))
    best, score_best = float(fine[j]), float(fine_scores[j])
    if 0 < j < fine.size - 1 and np.all(np.isfinite(fine_scores[j - 1:j + 2])):  # parabola through the peak
        a, b, c = fine_scores[j - 1:j + 2]
        curv = a - 2 * b + c
        if curv < 0:
            best += 0.5 * (a - c) / curv * fine_step
    score_cfg = time_offset_score(full, poses, span, p_b_s, R_b_s, 0.0, d_max_m=_FINE_D_MAX_M,
                                  radius_m=fine_radius, queries=fine_queries)
    tried = coarse.size + fine.size + 1
    adopted = bool(np.isfinite(score_best) and abs(best) > fine_step
                   and (not np.isfinite(score_cfg)
                        or score_best > score_cfg * (1.0 + min_gain) and score_best > score_cfg + 0.02))
    reason = "" if adopted else (
        f"no shift within ±{range_s:g} s agrees clearly better ({score_best:.3f} at {configured_s + best:+.4f} s, "
        f"{score_cfg:.3f} at the configured offset, {queries.size} features)"
    )
    return TimeOffsetSearch(configured_s, configured_s + best, score_best, score_cfg, adopted, queries.size, tried,
                            fine_step, reason)
