"""The LiDAR's time offset in the workflow: search before the first G/I/L adjustment, estimate in each.

``scanner.time_offset_s`` is added to the strips' time stamps to give navigation time. With
``processing.lidar.time_offset.search`` the first outer iteration scores the planar features
it extracted at that offset against shifted ones (:mod:`georefine.lidar.time_offset`) and,
when another offset makes the strips agree clearly better, goes on from it with a warning that
states the figures. With ``estimate`` every G/I/L adjustment carries the offset as a parameter of the plane
observations, with a prior around the configured or searched value; the next outer iteration
extracts its features at the estimate, and the final georeferencing uses the last one. Only
strips flown in different directions show an offset
(:func:`~georefine.lidar.time_offset.offset_unobservable`): with one
strip, or strips all flown one way, the offset stays where it started, and the run says so.
docs/ARCHITECTURE.md §4.5.

A clock drift is modelled by the plane observations (``time_drift``) but not offered here: the
tiles, the feature extraction and the final georeferencing shift times by a constant, and an
estimated drift they did not apply would make the products disagree with the adjustment.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from georefine.adjustment.observations.prior import EuclideanPrior
from georefine.adjustment.problem import Problem
from georefine.config import boresight_matrix
from georefine.lidar.feature_tiles import FeatureStore
from georefine.lidar.georeference import PoseInterpolator
from georefine.lidar.planes import PlanarFeatures
from georefine.lidar.time_offset import TimeOffsetSearch, georeference_features, search_time_offset
from georefine.trajectory.sampled import Trajectory

log = logging.getLogger(__name__)

__all__ = ["OFFSET_BLOCK", "TimeOffsetStart", "add_time_offset", "gnss_offset_sigma", "search_and_shift",
           "search_and_shift_store", "shifted_features", "warn_time_offset"]

OFFSET_BLOCK = "lidar_time_offset"
EDGE_MARGIN_S = 0.5
"""Features closer than this to the trajectory's ends stay out of an adjustment that moves their times."""


@dataclass(frozen=True)
class TimeOffsetStart:
    """Where an adjustment starts: the offset its features' times include, and the prior's centre (s)."""

    features_s: float
    prior_s: float


def search_and_shift(nav, trajectory: Trajectory, frame_poses, features: PlanarFeatures, configured_s: float
                     ) -> tuple[TimeOffsetSearch, PlanarFeatures]:
    """Search the offset (module docstring); the features at the adopted one (times and ``w`` geometry).

    ``trajectory``: the IMU-rate trajectory the features were extracted with; ``frame_poses``
    the poses their scanner-frame geometry refers to.
    """
    result, poses = _search(nav, trajectory, features, configured_s)
    if not result.adopted:
        return result, features
    return result, shifted_features(nav, frame_poses, poses.span, features, result.best_s - configured_s)[0]


def search_and_shift_store(nav, trajectory: Trajectory, frame_poses, store: FeatureStore, configured_s: float
                           ) -> tuple[TimeOffsetSearch, FeatureStore]:
    """:func:`search_and_shift` on the features of a ground-tiled ``store``: the search scores its sample
    (:class:`~georefine.lidar.feature_tiles.SearchSample`, the pool the search draws anyway); at an adopted
    offset the features move, tile by tile, into a new store (``store`` is closed), else ``store`` is returned."""
    result, poses = _search(nav, trajectory, store.sample.features(), configured_s)
    if not result.adopted:
        return result, store
    def shift(features: PlanarFeatures, arrival: np.ndarray) -> tuple[PlanarFeatures, np.ndarray]:
        shifted, inside = shifted_features(nav, frame_poses, poses.span, features, result.best_s - configured_s)
        return shifted, arrival[inside]

    return result, store.transformed(shift)


def _search(nav, trajectory: Trajectory, features: PlanarFeatures, configured_s: float
            ) -> tuple[TimeOffsetSearch, PoseInterpolator]:
    """The search (logged) and the trajectory's interpolator."""
    cfg = nav.config
    tcfg = cfg.processing.lidar.time_offset
    poses = PoseInterpolator(trajectory)
    p_b_s = np.asarray(cfg.scanner.lever_arm_m, dtype=float)
    R_b_s = boresight_matrix(cfg.scanner.boresight_deg)
    speed = np.linalg.norm(np.diff(trajectory.p_w_b, axis=0), axis=1) / np.diff(trajectory.time)
    result = search_time_offset(features, poses, poses.span, p_b_s, R_b_s,
                                speed_max_m_s=float(np.percentile(speed, 99.5)), configured_s=configured_s,
                                range_s=tcfg.search_range_s, feature_spacing_m=cfg.processing.planes.seed_spacing_m)
    if result.adopted:
        log.warning("LiDAR time offset: %s", result.describe())
    else:
        log.info("LiDAR time offset search: %s", result.describe())
    return result, poses


def shifted_features(nav, frame_poses, span: tuple[float, float], features: PlanarFeatures, delta: float
             ) -> tuple[PlanarFeatures, np.ndarray]:
    """``features`` with their times moved by ``delta`` (s), those that stay inside ``span``, in ``w`` again;
    the index of those kept."""
    cfg = nav.config
    p_b_s = np.asarray(cfg.scanner.lever_arm_m, dtype=float)
    R_b_s = boresight_matrix(cfg.scanner.boresight_deg)
    t = features.time + delta
    inside = np.flatnonzero((t >= span[0]) & (t <= span[1]))
    shifted = features.select(inside)
    t = t[inside]
    centre_w, normal_w = georeference_features(shifted, frame_poses, p_b_s, R_b_s, t)
    return replace(shifted, time=t, centre_w=centre_w, normal_w=normal_w), inside


def add_time_offset(problem: Problem, cfg, start: TimeOffsetStart, unobservable: str | None = None
                    ) -> dict[str, str | None]:
    """The offset's block and prior in ``problem``; the PlaneObservation's block names.

    The offset block holds the correction to ``start.features_s`` (0 to begin with); its prior
    centres the total on ``start.prior_s``. None of it when the configuration does not estimate
    the offset, or with ``unobservable`` (:func:`~georefine.lidar.time_offset.offset_unobservable`'s reason, logged).
    """
    tcfg = cfg.processing.lidar.time_offset
    if not tcfg.estimate:
        return {"time_offset": None}
    if unobservable is not None:
        log.info("LiDAR time offset held at %.4f s, not estimated: %s", start.features_s, unobservable)
        return {"time_offset": None}
    problem.add_block(OFFSET_BLOCK, np.zeros((1, 1)))
    problem.add_group(EuclideanPrior("lidar_time_offset_prior", OFFSET_BLOCK, [0],
                                     [[start.prior_s - start.features_s]], [[tcfg.prior_sigma_s]]))
    return {"time_offset": OFFSET_BLOCK}


def gnss_offset_sigma(nav, gi) -> float:
    """The sigma (s) that GNSS errors lasting a whole pass put on the offset, which the adjustment's does not hold.

    The adjustment treats GNSS errors as white, but PPK errors are correlated over minutes: each
    pass's trajectory sits off along its track by about the epochs' horizontal sigma
    ``sigma_h``, and opposite passes at speed ``v`` then disagree as an offset of
    ``(e_1 + e_2) / (2 v)``, sigma ``sigma_h / (sqrt(2) v)``. On ``corridor`` the simulated GNSS
    errors made -0.62 ms of it (``evaluation.trajectory_files.truth_gnss_time_offset``), against
    a sigma of 0.02 ms from the adjustment and 0.71 ms from this (18 m/s, 1.8 cm). ``nav``: the navigation data
    (GNSS covariances in ``w``); ``gi``: a trajectory result (the speed at its knots).

    0 when the adjustment estimates the correlated GNSS error (``gnss.correlated_error``): its
    own sigma holds this then.
    """
    if nav.prior is None and nav.gnss.gnss_correlated is not None:
        return 0.0
    if nav.prior is not None:  # a delivered trajectory: its stated horizontal position sigma (§4.9)
        sp = nav.prior.sigma_p_w
        sigma_h = float(np.median(np.sqrt(0.5 * (sp[:, 0] ** 2 + sp[:, 1] ** 2))))
    else:
        cov = nav.gnss.gnss_cov_w
        if cov.size == 0:
            return float("nan")
        sigma_h = float(np.median(np.sqrt(0.5 * (cov[:, 0, 0] + cov[:, 1, 1]))))
    speed = np.linalg.norm(gi.spline.v_w_b[:, :2], axis=1)
    moving = speed[speed > 5.0]
    return sigma_h / (np.sqrt(2.0) * float(np.median(moving))) if moving.size else float("nan")


def warn_time_offset(cfg, offset_s: float, sigma_s: float | None, gnss_sigma_s: float = 0.0) -> None:
    """Warn when the estimated offset differs clearly from ``scanner.time_offset_s`` (figures included).

    Clearly: by more than ``warn_ms`` and three sigmas, the adjustment's and the GNSS's
    (:func:`gnss_offset_sigma`) together. On ``corridor`` (18 m/s, 1.8 cm GNSS sigma) that sigma
    is 0.71 ms: the clean run's -0.64 ms stays quiet, a 50 ms offset does not.
    """
    tcfg = cfg.processing.lidar.time_offset
    configured = cfg.scanner.time_offset_s
    diff = offset_s - configured
    if sigma_s is None:
        return
    gnss = gnss_sigma_s if np.isfinite(gnss_sigma_s) else 0.0
    sigma = float(np.hypot(sigma_s, gnss))
    if abs(diff) * 1e3 <= tcfg.warn_ms or abs(diff) <= 3.0 * sigma:
        return
    split = f": {sigma_s * 1e3:.2f} from the adjustment, {gnss * 1e3:.2f} from GNSS errors that last a pass" if gnss else ""
    log.warning(
        "the LiDAR time stamps are %+.2f ms (± %.2f ms%s) off the navigation: the adjustment estimated a time offset "
        "of %.4f s against scanner.time_offset_s = %.4f s; state it in project.yaml (scanner.time_offset_s: %.4f) or "
        "fix the synchronisation",
        diff * 1e3, sigma * 1e3, split, offset_s, configured, offset_s,
    )
