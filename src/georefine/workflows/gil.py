"""Workflow step 5 of paper 000: the GNSS/IMU/LiDAR adjustment of one outer iteration.

:func:`build_gil_problem` builds it -- the G/I problem started at the previous trajectory plus
the plane observations (robust loss), optionally the boresight and the LiDAR time offset --
and :func:`step_adjust_gil` solves it; :func:`add_posterior` adds the posterior sigma. The
outer iterations and the run are in :mod:`georefine.workflows.lidar`; the Cramér-Rao bound of a
simulated project builds the same problem at the truth (:mod:`georefine.workflows.cramer_rao`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from georefine.adjustment.gnss_imu import (
    GnssImuProblem,
    GnssImuResult,
    block_sigma,
    build_gnss_imu_problem,
    posterior_scale,
    solve_gnss_imu,
    start_imu_errors,
    trajectory_solver_options,
    with_posterior,
)
from georefine.adjustment.observations.plane import ENCODER_TERMS, PlaneObservation
from georefine.adjustment.observations.prior import EuclideanPrior, RotationPrior
from georefine.adjustment.robust import make_loss
from georefine.adjustment.trajectory_prior import TrajectoryPriorProblem, solve_trajectory_prior, with_prior_posterior
from georefine.adjustment.upsampling import on_knots, rebuild_high_rate, without_high_rate
from georefine.config import boresight_matrix
from georefine.errors import InputError
from georefine.geometry.rotation import rph_from_R_n_b, wrap_angle
from georefine.lidar.correspondences import PlanarObjects
from georefine.lidar.feature_sample import feature_keys, time_windows, windowed_object_subset
from georefine.lidar.georeference import ScannerCalibration
from georefine.lidar.planes import PlanarFeatures
from georefine.lidar.time_offset import offset_unobservable
from georefine.progress import Progress, no_progress
from georefine.trajectory.spline import KnotGrid
from georefine.workflows.delivered import build_delivered_problem
from georefine.workflows.navigation import NavigationData
from georefine.workflows.time_offset import (
    EDGE_MARGIN_S,
    OFFSET_BLOCK,
    TimeOffsetStart,
    add_time_offset,
)

__all__ = ["GilProblem", "LidarAdjustment", "PlaneSelection", "add_posterior", "boresight_body_sigma_mdeg",
           "boresight_deg_of", "build_gil_problem",
           "plane_candidates", "scanner_estimates",
           "step_adjust_gil"]


@dataclass(frozen=True)
class LidarAdjustment:
    """Result of one G/I/L adjustment (``built``: the problem, for :func:`add_posterior`).

    ``time_offset_s`` is the LiDAR time offset the adjustment ends with (estimated, or the one its
    features used); ``time_offset_start`` where it started; the sigmas come with the posterior;
    ``time_offset_held``: why an offset the configuration estimates was held (its strips cannot
    show one, :func:`~georefine.lidar.time_offset.offset_unobservable`), or None.
    """

    result: GnssImuResult
    features_used: int
    objects_used: int
    boresight_deg: np.ndarray | None
    boresight_sigma_mdeg: np.ndarray | None
    built: GnssImuProblem | None = None
    time_offset_s: float = 0.0
    time_offset_start: TimeOffsetStart | None = None
    time_offset_sigma_s: float | None = None
    time_offset_gnss_sigma_s: float | None = None  # what GNSS errors lasting a pass add (gnss_offset_sigma)
    time_offset_held: str | None = None
    range_calibration: tuple[float, float] | None = None  # range offset r0 (m) and scale error k, where estimated
    range_calibration_sigma: tuple[float, float] | None = None
    channel_angles: np.ndarray | None = None  # (C, 2) tilt and scan-angle error per channel (rad), where estimated
    channel_angles_sigma: np.ndarray | None = None
    encoder: np.ndarray | None = None  # (4,) the encoder error's Legendre coefficients (rad), where estimated
    encoder_sigma: np.ndarray | None = None
    boresight_body_sigma_mdeg: np.ndarray | None = None  # the boresight's sigma about the body's x, y, z axes

    def calibration_lines(self, scope: str = "") -> list[str]:
        """What ``run`` prints of the scanner calibration it estimated (range, channel angles, encoder error), each
        with its sigma; ``scope`` follows the name (``" (all flights)"``)."""
        lines = []
        if self.range_calibration is not None:
            (r0, k), sig = self.range_calibration, self.range_calibration_sigma or (np.nan, np.nan)
            lines.append(f"  scanner range offset{scope} {r0 * 1e3:+.1f} ± {sig[0] * 1e3:.1f} mm, scale {k * 1e6:+.1f} "
                         f"± {sig[1] * 1e6:.1f} ppm (points corrected)")
        if self.channel_angles is not None:
            a = np.degrees(self.channel_angles) * 1e3
            sig = (np.full_like(a, np.nan) if self.channel_angles_sigma is None
                   else np.degrees(self.channel_angles_sigma) * 1e3)
            lines.append(f"  scanner channel angles{scope} against channel 0 (tilt, scan angle; points corrected): "
                         + "; ".join(f"{c}: {a[c, 0]:+.1f} ± {sig[c, 0]:.1f}, {a[c, 1]:+.1f} ± {sig[c, 1]:.1f} mdeg"
                                     for c in range(1, len(a))))
        if self.encoder is not None:
            e = np.degrees(self.encoder) * 1e3
            sig = np.full_like(e, np.nan) if self.encoder_sigma is None else np.degrees(self.encoder_sigma) * 1e3
            lines.append(f"  scanner encoder error{scope}, Legendre terms P1..P4 (points corrected): "
                         + ", ".join(f"{v:+.1f} ± {s:.1f}" for v, s in zip(e, sig)) + " mdeg")
        return lines

    def scanner_calibration(self) -> ScannerCalibration | None:
        """What the final georeferencing takes out of every point (range, channel angles, encoder error), or None."""
        if self.range_calibration is None and self.channel_angles is None and self.encoder is None:
            return None
        return ScannerCalibration(range=self.range_calibration, channel_angles=self.channel_angles,
                                  encoder=self.encoder)


def add_posterior(adj: LidarAdjustment) -> LidarAdjustment:
    """``adj`` with posterior sigma (trajectory, IMU errors, boresight, time offset) if it has none yet."""
    if adj.result.sigma_time.size or adj.built is None:
        return adj
    if isinstance(adj.built, TrajectoryPriorProblem):
        result = with_prior_posterior(adj.built, adj.result)
    else:
        result = with_posterior(adj.built, adj.result)
    problem = adj.built.problem
    vf = posterior_scale(result.solve)  # as the trajectory's: the variance factor where it exceeds 1
    bs_sig, extra = None, {}
    if adj.boresight_deg is not None:
        cov = problem.covariance("boresight", scale_by_variance_factor=False)[0] * vf
        bs_sig = np.degrees(np.sqrt(np.diag(cov))) * 1e3
        extra["boresight_body_sigma_mdeg"] = boresight_body_sigma_mdeg(problem.values("boresight")[0], cov)
    if OFFSET_BLOCK in problem.blocks:
        cov = problem.covariance(OFFSET_BLOCK, scale_by_variance_factor=False)[0, 0, 0] * vf
        extra["time_offset_sigma_s"] = float(np.sqrt(cov))
    extra |= {k: v for k, v in scanner_estimates(problem, vf).items() if k.endswith("_sigma")}
    return replace(adj, result=result, boresight_sigma_mdeg=bs_sig, **extra)


def boresight_body_sigma_mdeg(R_b_s: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """The boresight's sigma (mdeg) about the body's x, y and z axes from its covariance ``cov`` (3, 3; rad^2) in the
    scanner's tangent (``R_b_s <- R_b_s Exp(eps)``): a turn ``eps`` of the scanner is ``R_b_s eps`` in the body, so
    its covariance there is ``R_b_s cov R_b_s^T``. About the body's axes a scanner mounted turned (a sideways or
    backwards head) is compared with the trajectory's roll, pitch and heading."""
    R = np.asarray(R_b_s, dtype=float)
    return np.degrees(np.sqrt(np.diag(R @ np.asarray(cov, dtype=float) @ R.T))) * 1e3


RANGE_BLOCK = "range_calibration"
"""The scanner's range offset (m) and scale error ((1, 2); ``processing.lidar.estimate_range_calibration``)."""
INCIDENCE_BLOCK = "range_incidence"
"""A range bias ``b`` (m) growing with the incidence as ``b (1 / cos(phi) - 1)`` ((1, 1)): only the scanner
calibration check estimates it (:mod:`georefine.workflows.calibration_check`); the products cannot take it, a
point's incidence being unknown where it is georeferenced."""
INCIDENCE_PRIOR_M = 0.1
"""Prior sigma of ``b`` (m): weak, a tenth of it is a large bias (5 cm at 60 degrees' incidence)."""
CHANNEL_BLOCK = "channel_angles"
"""Each scanner channel's facet-tilt and scan-angle error against channel 0's ((C - 1, 2) for channels 1..C-1, rad;
``processing.lidar.estimate_channel_angles``). Channel 0's are the boresight's: a scan-angle error common to all
channels is a scanner roll, which the planes cannot tell from a roll of the trajectory where both passes share it."""
ENCODER_BLOCK = "encoder_error"
"""The scan-angle encoder's error across the field of view, the same on every channel: Legendre coefficients ((1, 4),
rad; :func:`~georefine.adjustment.observations.plane.encoder_basis`; ``processing.lidar.estimate_encoder_error``).
Their mean over the field of view is zero: a constant scan-angle error is the boresight's roll."""
CALIBRATION_PRIORS = {RANGE_BLOCK: "range_calibration_prior", CHANNEL_BLOCK: "channel_angles_prior",
                      ENCODER_BLOCK: "encoder_error_prior"}
"""The prior group of each scanner calibration block: one scanner's, shared where several flights are adjusted
together (:mod:`georefine.workflows.flights`)."""


def scanner_estimates(problem, scale: float | None = None) -> dict:
    """The scanner calibration a solved G/I/L problem estimated, under :class:`LidarAdjustment`'s names:
    ``range_calibration`` ``(r0, k)``, ``channel_angles`` (C, 2) with channel 0's row of zeros first, ``encoder``
    (4,), each where its block is in ``problem``; with ``scale`` (the posterior's factor, :func:`posterior_scale`)
    also their sigmas (``..._sigma``, channel 0's zero)."""
    out: dict = {}
    blocks = problem.blocks
    if RANGE_BLOCK in blocks:
        out["range_calibration"] = tuple(float(v) for v in problem.values(RANGE_BLOCK)[0])
        if scale is not None:
            out["range_calibration_sigma"] = tuple(float(v) for v in block_sigma(problem, RANGE_BLOCK, scale)[0])
    if CHANNEL_BLOCK in blocks:
        zero = np.zeros((1, 2))
        out["channel_angles"] = np.vstack([zero, problem.values(CHANNEL_BLOCK)])
        if scale is not None:
            out["channel_angles_sigma"] = np.vstack([zero, block_sigma(problem, CHANNEL_BLOCK, scale)])
    if ENCODER_BLOCK in blocks:
        out["encoder"] = problem.values(ENCODER_BLOCK)[0].copy()
        if scale is not None:
            out["encoder_sigma"] = block_sigma(problem, ENCODER_BLOCK, scale)[0]
    return out


@dataclass
class GilProblem:
    """A built G/I/L problem (:func:`build_gil_problem`) and what its solve needs.

    ``built``: the G/I problem with the plane observations in it; ``features_used`` and
    ``objects_used``: the features and objects it observes; ``boresight``: the name of the
    boresight block, or None; ``estimates_offset``: whether it estimates the LiDAR time offset,
    ``offset_held``: why not though the configuration asks for it (its strips cannot show one);
    ``high_rate``: a delivered trajectory's faster motion (§4.9), else None; ``lidar_groups`` and
    ``lidar_blocks``: what the LiDAR adds to the G/I problem (the plane observations, the
    boresight's and time offset's priors; the objects, boresight and time offset blocks), so that
    the G/I problem can be had back from it (:func:`~georefine.workflows.cramer_rao.cramer_rao_bound`).
    """

    built: GnssImuProblem | TrajectoryPriorProblem
    features_used: int
    objects_used: int
    boresight: str | None
    estimates_offset: bool
    time_offset: TimeOffsetStart
    high_rate: object = None
    lidar_groups: tuple[str, ...] = ()
    lidar_blocks: tuple[str, ...] = ()
    offset_held: str | None = None


@dataclass(frozen=True)
class PlaneSelection:
    """The features and objects of one problem, chosen across several (the flights adjusted together,
    :mod:`georefine.workflows.flights`) instead of by :func:`build_gil_problem` itself.

    ``features``: indices (increasing) into the features given to :func:`build_gil_problem`, the ones
    this problem observes (inside its trajectory, away from its ends where the offset is estimated);
    ``objects``: the object ids (increasing) of every problem's selection together, the rows of the one
    ``plane_params`` block they share; ``offset_held``: why the LiDAR time offset is held, decided
    over all problems' features (:func:`~georefine.lidar.time_offset.offset_unobservable`), or None.
    """

    features: np.ndarray
    objects: np.ndarray
    offset_held: str | None = None


def build_gil_problem(
    nav: NavigationData,
    previous: GnssImuResult,
    features: PlanarFeatures,
    objects: PlanarObjects,
    knot_interval_s: float | None = None,
    time_offset: TimeOffsetStart | None = None,
    selection: PlaneSelection | None = None,
    range_incidence: bool = False,
) -> GilProblem:
    """Step 5's problem: the G/I problem started at ``previous`` plus the plane observations.

    Arguments as :func:`step_adjust_gil`; ``previous.high_rate`` (up-sampling, §4.6) is taken
    out of the IMU windows. ``selection`` gives the features, the objects (the rows of
    ``plane_params``) and the time offset's observability where several problems share the
    objects; without it they are chosen here (matched, inside the trajectory, at most
    ``max_features_per_minute`` in each ``selection_window_s`` and ``max_features`` in all).
    ``range_incidence``: estimate the incidence-dependent range bias too (:data:`INCIDENCE_BLOCK`).

    Raises
    ------
    InputError
        No matched planar feature inside the trajectory span (without ``selection``).
    """
    cfg = nav.config
    lcfg = cfg.processing.lidar
    tcfg = cfg.processing.trajectory
    spline = previous.spline
    if knot_interval_s is not None and knot_interval_s != tcfg.knot_interval_s:
        tcfg = tcfg.model_copy(update={"knot_interval_s": float(knot_interval_s),
                                       "imu_window_s": tcfg.imu_window_s * knot_interval_s / tcfg.knot_interval_s})
    high_rate = None
    if nav.prior is not None:  # a delivered trajectory (§4.9): its problem, its faster motion
        if abs(spline.grid.dt - tcfg.knot_interval_s) > 1e-6 * tcfg.knot_interval_s:
            spline = spline.resampled(KnotGrid.spanning(spline.grid.t_start, spline.grid.t_end, tcfg.knot_interval_s))
        built, high_rate = build_delivered_problem(nav, tcfg, spline, previous)
    else:  # windows without the high-frequency motion the new knots do not hold (up-sampling, §4.6)
        previous = on_knots(nav.gnss, previous, tcfg.knot_interval_s)
        spline = previous.spline
        data = without_high_rate(nav.gnss, previous)
        built = start_imu_errors(build_gnss_imu_problem(data, cfg.imu.errors, tcfg, spline), previous.imu_errors,
                                 previous.gnss_error)
    P = built.problem
    gi_groups, gi_blocks = {g.name for g in P.groups}, set(P.blocks)

    grid = built.grid
    if time_offset is None:
        time_offset = TimeOffsetStart(cfg.scanner.time_offset_s, cfg.scanner.time_offset_s)
    if selection is not None:  # chosen across the problems that share the objects
        held = selection.offset_held
        timing = add_time_offset(P, cfg, time_offset, held)
        sel, used_objects = np.asarray(selection.features, dtype=np.int64), np.asarray(selection.objects)
        obj_index = np.searchsorted(used_objects, objects.feature_object[sel])
    else:
        matched = (objects.feature_object >= 0) & (features.time >= grid.t_start) & (features.time <= grid.t_end)
        held = None
        if lcfg.time_offset.estimate:  # only strips with different tracks show an offset
            held = offset_unobservable(features.time[matched], features.strip[matched], spline.velocity)
        timing = add_time_offset(P, cfg, time_offset, held)
        sel = plane_candidates(features, objects, (grid.t_start, grid.t_end), bool(timing["time_offset"]))
        # Whole objects within a budget per window of flight time, the same ones in every outer
        # iteration as far as the re-matching allows (ranked by a min-hash of keys fixed by strip,
        # channel and seed voxel), not a fresh random draw, and not single features, which would
        # leave objects with one view or one member.
        sel = windowed_object_subset(sel, feature_keys(features), objects.feature_object,
                                     time_windows(features.time, lcfg.selection_window_s), features.strip,
                                     objects.is_vertical, lcfg.window_budget, lcfg.max_features)
        if sel.size == 0:
            raise InputError("no matched planar features inside the trajectory span", field="processing.matching")
        used_objects, obj_index = np.unique(objects.feature_object[sel], return_inverse=True)
    f = features.select(sel)
    R_b_s = boresight_matrix(cfg.scanner.boresight_deg)
    P.add_block("plane_params", np.zeros((used_objects.size, 3)))
    boresight = None
    if lcfg.estimate_boresight:
        P.add_block("boresight", R_b_s[None].copy(), manifold="so3")
        P.add_group(RotationPrior("boresight_prior", "boresight", [0], R_b_s[None], np.radians(lcfg.boresight_prior_deg)))
        boresight = "boresight"
    ranges = None
    if lcfg.estimate_range_calibration:
        P.add_block(RANGE_BLOCK, np.zeros((1, 2)))
        P.add_group(EuclideanPrior(CALIBRATION_PRIORS[RANGE_BLOCK], RANGE_BLOCK, [0], np.zeros((1, 2)),
                                   np.array([lcfg.range_offset_prior_m, lcfg.range_scale_prior_ppm * 1e-6])))
        ranges = RANGE_BLOCK
    incidence = None
    if range_incidence:
        P.add_block(INCIDENCE_BLOCK, np.zeros((1, 1)))
        P.add_group(EuclideanPrior("range_incidence_prior", INCIDENCE_BLOCK, [0], np.zeros((1, 1)),
                                   np.array([INCIDENCE_PRIOR_M])))
        incidence = INCIDENCE_BLOCK
    channels = None
    if lcfg.estimate_channel_angles:  # channel 0 is the reference, whose angles are the boresight's
        # Where several problems share the block (the flights), its rows are every problem's channels.
        n_ch = max(int((features.channel if selection is not None else f.channel).max()), 1)
        sigma = np.radians(lcfg.channel_angle_prior_mdeg * 1e-3)
        P.add_block(CHANNEL_BLOCK, np.zeros((n_ch, 2)))
        P.add_group(EuclideanPrior(CALIBRATION_PRIORS[CHANNEL_BLOCK], CHANNEL_BLOCK, np.arange(n_ch), np.zeros((n_ch, 2)),
                                   np.full(2, sigma)))
        channels = CHANNEL_BLOCK
    enc = None
    if lcfg.estimate_encoder_error:
        sigma = np.radians(lcfg.encoder_error_prior_mdeg * 1e-3)
        P.add_block(ENCODER_BLOCK, np.zeros((1, ENCODER_TERMS)))
        P.add_group(EuclideanPrior(CALIBRATION_PRIORS[ENCODER_BLOCK], ENCODER_BLOCK, [0], np.zeros((1, ENCODER_TERMS)),
                                   np.full(ENCODER_TERMS, sigma)))
        enc = ENCODER_BLOCK
    P.add_group(
        PlaneObservation(
            grid, f.time, f.centre_s, f.axis1_s, f.axis2_s, f.sigma_d_m, f.sigma_slope_rad, obj_index,
            objects.c0[used_objects], objects.k1[used_objects], objects.k2[used_objects], objects.n0[used_objects],
            np.asarray(cfg.scanner.lever_arm_m, dtype=float), R_b_s, boresight=boresight, range_calibration=ranges,
            range_incidence=incidence, channel=f.channel.astype(np.int64) - 1 if channels else None, channel_angles=channels,
            encoder=enc, blocks=built.blocks, loss=make_loss(lcfg.plane_loss, lcfg.plane_loss_scale), **timing,
        )
    )
    return GilProblem(built, int(sel.size), int(used_objects.size), boresight, bool(timing["time_offset"]),
                      time_offset, high_rate, tuple(g.name for g in P.groups if g.name not in gi_groups),
                      tuple(n for n in P.blocks if n not in gi_blocks), held)


def plane_candidates(features: PlanarFeatures, objects: PlanarObjects, span: tuple[float, float],
                     offset_estimated: bool, among: np.ndarray | None = None) -> np.ndarray:
    """Indices of the matched features inside the trajectory ``span`` (s), :data:`EDGE_MARGIN_S` inside its ends
    when the adjustment estimates the time offset (it moves the feature times); only those of the mask ``among``."""
    margin = EDGE_MARGIN_S if offset_estimated else 0.0
    t = features.time
    keep = (objects.feature_object >= 0) & (t >= span[0] + margin) & (t <= span[1] - margin)
    if among is not None:
        keep &= among
    return np.flatnonzero(keep)


def boresight_deg_of(R_b_s: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (deg) of a boresight ``R_b_s``, the yaw in [0, 360)."""
    bs_deg = np.degrees(rph_from_R_n_b(R_b_s))
    bs_deg[2] = wrap_angle(bs_deg[2], 360.0, closed="lower")
    return bs_deg


def step_adjust_gil(
    nav: NavigationData,
    previous: GnssImuResult,
    features: PlanarFeatures,
    objects: PlanarObjects,
    progress: Progress = no_progress,
    covariance: bool = True,
    knot_interval_s: float | None = None,
    time_offset: TimeOffsetStart | None = None,
    range_incidence: bool = False,
) -> LidarAdjustment:
    """Step 5: the G/I problem started at ``previous`` plus the plane observations, solved.

    With ``covariance=False`` no posterior sigma is computed (see :func:`add_posterior`).
    ``time_offset``: the LiDAR time offset the features' times include and the centre of its
    prior (default ``scanner.time_offset_s`` for both); with
    ``processing.lidar.time_offset.estimate`` the adjustment estimates it
    (:mod:`georefine.workflows.time_offset`). ``range_incidence``: estimate :data:`INCIDENCE_BLOCK` too
    (the scanner calibration check).
    The trajectory has knots about ``knot_interval_s`` apart (default
    ``processing.trajectory.knot_interval_s``) over ``previous``'s span, IMU windows in the
    configured proportion to them; ``previous`` on another grid is resampled onto it.
    """
    cfg = nav.config
    lcfg = cfg.processing.lidar
    tcfg = cfg.processing.trajectory
    gil = build_gil_problem(nav, previous, features, objects, knot_interval_s, time_offset,
                            range_incidence=range_incidence)
    built, P = gil.built, gil.built.problem

    def report(it) -> None:
        progress("G/I/L adjustment", getattr(it, "iteration", 0), tcfg.max_iterations)

    options = trajectory_solver_options(tcfg, function_tolerance=lcfg.function_tolerance,
                                        initial_lambda=lcfg.initial_lambda)
    if nav.prior is not None:
        result = solve_trajectory_prior(built, options, progress=report, covariance=False, high_rate=gil.high_rate)
    else:
        result = solve_gnss_imu(built, options, progress=report, covariance=False)
        if tcfg.upsampling:
            result = replace(result, high_rate=rebuild_high_rate(nav.gnss, result))
    progress("G/I/L adjustment", 1, 1)  # it reports iterations of its limit; it ended here
    bs_deg = None
    if gil.boresight:
        bs_deg = boresight_deg_of(P.values("boresight")[0])
    offset = gil.time_offset.features_s
    if gil.estimates_offset:
        offset += float(P.values(OFFSET_BLOCK)[0, 0])
    adj = LidarAdjustment(result, gil.features_used, gil.objects_used, bs_deg, None, built,
                          time_offset_s=offset, time_offset_start=gil.time_offset, time_offset_held=gil.offset_held,
                          **scanner_estimates(P))
    return add_posterior(adj) if covariance else adj
