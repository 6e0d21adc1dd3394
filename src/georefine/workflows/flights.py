"""Several flights of one project adjusted together: one G/I/L holding every flight's trajectory (docs/ARCHITECTURE.md §3, §4.5).

A project of several flights (``flights:`` in ``project.yaml``) has one navigation per flight
(:meth:`~georefine.workflows.opened.Project.navigation_of`), all in one mapping frame ``w``.
Each flight keeps what is its own -- the initialisation filter and the G/I adjustment (steps 1-2,
cached as a single-flight run caches them), its spline, IMU errors and correlated GNSS error, its
time epoch -- and the flights are tied by what they share:

* the **planar objects**: the features of every flight, each georeferenced with its own flight's
  trajectory, are matched together (:func:`~georefine.lidar.correspondences.match_features`; strip
  ids are unique across the project's flights), so an object seen by strips of several flights is
  one object, one row of the one ``plane_params`` block that each flight's plane observations
  index into (:class:`~georefine.workflows.gil.PlaneSelection`);
* the **scanner calibration**: one boresight (``processing.lidar.estimate_boresight``) and one
  LiDAR time offset (``processing.lidar.time_offset``) for all flights, where the flights state the
  same configured values (a flight with its own boresight or time offset in ``project.yaml`` gets
  its own block). The time offset search runs over all strips of all flights (any two strips
  with different tracks show an offset, whichever flight flew them), and the offset's
  observability is judged over all of them too. The scanner's range calibration, channel angles
  and encoder error (``processing.lidar.estimate_range_calibration``, ``estimate_channel_angles``,
  ``estimate_encoder_error``) are the one unit's: one block each for all flights, their priors
  once, and every flight's points corrected with them.

Each outer iteration builds every flight's G/I/L problem as the single-flight run does
(:func:`~georefine.workflows.gil.build_gil_problem` with the joint selection), merges them into
one problem (:func:`~georefine.adjustment.joint.merge_problems`: every flight's blocks prefixed
``f<id>/``, the objects, boresight and time offset shared, their priors once) and solves it with
the existing solver. The posterior is computed on the joint problem and read out per flight
through its part's view (:meth:`~georefine.adjustment.joint.JointProblem.part`), with the same
read-out as one flight (:func:`~georefine.adjustment.gnss_imu.with_posterior`): the variance
components pool the planes of all flights, and the navigation sensors of all flights.

:func:`run_flights` writes ``gi/flight_<id>/`` and ``gil/flight_<id>/`` (the trajectory products
and ``adjustment.json`` of each flight), ``features/`` (the matched features and objects of all
flights), ``points/strip_<n>.laz`` (each strip georeferenced with its own flight's trajectory),
``metrics.json`` (:class:`~georefine.io.run_metrics.WorkflowMetrics`: the joint outer iterations,
every strip's points and precision) and the resolved configuration. The per-tile work is streamed
as in a single-flight run (:func:`~georefine.workflows.strips.step_features`), one flight after
the other, so memory is bounded as there.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from georefine.adjustment.gnss_imu import (
    GnssImuProblem,
    GnssImuResult,
    gnss_error_of,
    imu_errors_of,
    posterior_columns,
    posterior_scale,
    trajectory_solver_options,
    with_posterior,
)
from georefine.adjustment.joint import JointProblem, merge_problems
from georefine.adjustment.solver import SolveResult
from georefine.adjustment.upsampling import rebuild_high_rate
from georefine.config import boresight_matrix, write_yaml
from georefine.errors import InputError
from georefine.io.files import make_output_folder, write_json
from georefine.io.run_metrics import (
    OuterIteration,
    PointsWritten,
    WorkflowMetrics,
    write_adjustment_report,
)
from georefine.lidar.correspondences import PlanarObjects, match_features
from georefine.lidar.feature_sample import feature_keys, time_windows, windowed_object_subset
from georefine.lidar.feature_tiles import FeatureStore, match_store, tile_size
from georefine.lidar.georeference import PoseInterpolator
from georefine.lidar.object_files import write_objects
from georefine.lidar.planes import FEATURES_VERSION, PlanarFeatures, write_features
from georefine.lidar.tiles import georeference_strips, refuse_strips_outside
from georefine.lidar.time_offset import offset_unobservable, search_time_offset
from georefine.progress import Progress, no_progress
from georefine.tasks import DEFAULT_SCHEDULER, TaskRunner
from georefine.trajectory.sampled import Trajectory
from georefine.workflows.cache import StepCache, StepRunner, file_stamp
from georefine.workflows.gil import (
    CALIBRATION_PRIORS,
    LidarAdjustment,
    PlaneSelection,
    boresight_body_sigma_mdeg,
    boresight_deg_of,
    build_gil_problem,
    plane_candidates,
    scanner_estimates,
)
from georefine.workflows.navigation import (
    NavigationData,
    imu_rate_trajectory,
    write_trajectory_products,
)
from georefine.workflows.opened import Flight, Project, open_workspace
from georefine.workflows.outer_checks import (
    outer_converged,
    trajectory_change,
    warn_boresight_separation,
    warn_gi_tilt,
    warn_gnss_error_misfit,
    warn_plane_misfit,
    warn_unconverged,
)
from georefine.workflows.precision import pass_precision, precision_lines
from georefine.workflows.run_parts import adjustment_report, outer_knot_interval, stage_gnss_imu, vibrating
from georefine.workflows.strips import StripFile, read_strips, sort_features, step_features
from georefine.workflows.time_offset import (
    OFFSET_BLOCK,
    TimeOffsetStart,
    gnss_offset_sigma,
    shifted_features,
    warn_time_offset,
)

log = logging.getLogger(__name__)

__all__ = ["FlightsAdjustment", "FlightsResult", "FlightInputs", "add_flights_posterior", "flight_prefix",
           "joint_features", "run_flights", "step_adjust_flights"]

BORESIGHT_BLOCK = "boresight"
PLANES_BLOCK = "plane_params"
BORESIGHT_PRIOR = "boresight_prior"
OFFSET_PRIOR = "lidar_time_offset_prior"
SEARCH_SHIFT_S = 1.0e7
"""The flights' times apart in the one time base of the joint time offset search and observability test
(every flight's own times plus its index times this): farther than any search range."""


def flight_prefix(flight: Flight) -> str:
    """The prefix of a flight's blocks and groups in the joint problem: ``f<id>/``."""
    return f"f{flight.id}/"


@dataclass(frozen=True)
class FlightInputs:
    """One flight of a run: its record, its project (:meth:`~georefine.workflows.opened.Project.flight_project`),
    its navigation and its strips (indexed, at the configured time offset)."""

    flight: Flight
    project: Project
    nav: NavigationData
    strips: list[StripFile]


@dataclass(frozen=True)
class FlightsAdjustment:
    """One joint G/I/L adjustment of several flights.

    ``flights``: per flight the :class:`~georefine.workflows.gil.LidarAdjustment` as a single-flight
    run has it (its trajectory, IMU errors and statistics of its own groups, its feature and object
    counts, and the shared boresight and time offset); ``solve``: the joint problem's statistics;
    ``joint``: the merged problem (for :func:`add_flights_posterior`), None once it has its posterior.
    """

    flights: tuple[LidarAdjustment, ...]
    solve: SolveResult
    features_used: int
    objects_used: int
    joint: JointProblem | None = None
    shared: tuple[str, ...] = ()


def _same(values) -> bool:
    values = [tuple(np.atleast_1d(np.asarray(v, dtype=float))) for v in values]
    return all(v == values[0] for v in values)


def shared_calibration(flights: list[FlightInputs]) -> tuple[bool, bool]:
    """Whether the flights share one boresight and one LiDAR time offset: they do where ``project.yaml``
    gives them the same configured values (a flight stating its own keeps its own)."""
    return (_same([f.flight.boresight_deg for f in flights]),
            _same([f.flight.scanner_time_offset_s for f in flights]))


def _joint_time(flights: list[FlightInputs], features: PlanarFeatures, flight_of: np.ndarray) -> np.ndarray:
    """The features' times in the one time base of the joint search (:data:`SEARCH_SHIFT_S`)."""
    return features.time + flight_of * SEARCH_SHIFT_S


def _joint_velocity(splines):
    """``t -> v_w`` in the joint time base, from each flight's spline."""
    def velocity(t):
        t = np.asarray(t, dtype=float)
        k = np.clip(np.floor((t + 0.5 * SEARCH_SHIFT_S) / SEARCH_SHIFT_S).astype(int), 0, len(splines) - 1)
        out = np.zeros((t.size, 3))
        for i, s in enumerate(splines):
            m = k == i
            if np.any(m):
                ti = np.clip(t[m] - i * SEARCH_SHIFT_S, s.grid.t_start, s.grid.t_end)
                out[m] = s.velocity(ti)
        return out
    return velocity


def step_adjust_flights(
    flights: list[FlightInputs],
    previous: list[GnssImuResult],
    features: PlanarFeatures,
    objects: PlanarObjects,
    flight_of: np.ndarray,
    progress: Progress = no_progress,
    covariance: bool = True,
    knot_intervals_s: list[float | None] | None = None,
    time_offsets: list[TimeOffsetStart] | None = None,
) -> FlightsAdjustment:
    """Step 5 for several flights at once: every flight's G/I problem started at its ``previous``, the
    plane observations of all flights on one set of objects, one boresight and time offset where the
    flights share them (module docstring); solved as one problem.

    ``features`` and ``objects``: the features of all flights matched together (:func:`joint_features`),
    each feature's times those of its own flight; ``flight_of``: the index (into ``flights``) of
    each feature's flight. ``knot_intervals_s`` and ``time_offsets`` per flight as
    :func:`~georefine.workflows.gil.step_adjust_gil` takes them.

    Raises
    ------
    InputError
        No matched planar feature inside any flight's trajectory span.
    """
    n = len(flights)
    knot_intervals_s = knot_intervals_s or [None] * n
    cfg = flights[0].nav.config
    lcfg, tcfg = cfg.processing.lidar, cfg.processing.trajectory
    if time_offsets is None:
        time_offsets = [TimeOffsetStart(f.flight.scanner_time_offset_s, f.flight.scanner_time_offset_s)
                        for f in flights]
    share_bs, share_offset = shared_calibration(flights)
    flight_of = np.asarray(flight_of)
    spans = [(p.spline.grid.t_start, p.spline.grid.t_end) for p in previous]

    # The offset's observability over the matched features of all flights inside their trajectories.
    held = None
    if lcfg.time_offset.estimate:
        inside = np.zeros(len(features), dtype=bool)
        for k, (t0, t1) in enumerate(spans):
            inside |= (flight_of == k) & (features.time >= t0) & (features.time <= t1)
        matched = inside & (objects.feature_object >= 0)
        if share_offset:
            held = offset_unobservable(_joint_time(flights, features, flight_of)[matched], features.strip[matched],
                                       _joint_velocity([p.spline for p in previous]))
        else:  # each flight its own offset: judged per flight
            reasons = [offset_unobservable(features.time[matched & (flight_of == k)],
                                           features.strip[matched & (flight_of == k)], previous[k].spline.velocity)
                       for k in range(n)]
            held = next((r for r in reasons if r is not None), None)
    estimated = lcfg.time_offset.estimate and held is None
    sel = [plane_candidates(features, objects, spans[k], estimated, among=flight_of == k) for k in range(n)]
    every = np.concatenate(sel)
    # Whole objects across the flights, within the budget of each window of each flight's time.
    chosen = windowed_object_subset(np.sort(every), feature_keys(features), objects.feature_object,
                                    time_windows(features.time, lcfg.selection_window_s, flight_of), features.strip,
                                    objects.is_vertical, lcfg.window_budget, lcfg.max_features)
    if chosen.size < every.size:
        every = chosen
        sel = [np.intersect1d(s, every) for s in sel]
    if every.size == 0:
        raise InputError("no matched planar features inside the trajectory span of any flight",
                         field="processing.matching")
    used = np.unique(objects.feature_object[every])
    gils = [build_gil_problem(f.nav, p, features, objects, knot, start, selection=PlaneSelection(s, used, held))
            for f, p, knot, start, s in zip(flights, previous, knot_intervals_s, time_offsets, sel)]
    # One scanner: its range, channel and encoder calibration are every flight's, as the planes are.
    calibration = [b for b in CALIBRATION_PRIORS if b in gils[0].built.problem.blocks]
    shared = [PLANES_BLOCK] + ([BORESIGHT_BLOCK] if share_bs else []) + ([OFFSET_BLOCK] if share_offset else []) \
        + calibration
    prefixes = [flight_prefix(f.flight) for f in flights]
    joint = merge_problems([g.built.problem for g in gils], prefixes, shared=shared,
                           shared_groups=[g for g, b in ((BORESIGHT_PRIOR, BORESIGHT_BLOCK), (OFFSET_PRIOR, OFFSET_BLOCK))
                                          if b in shared] + [CALIBRATION_PRIORS[b] for b in calibration])

    def report(it) -> None:
        progress("G/I/L adjustment of the flights", getattr(it, "iteration", 0), tcfg.max_iterations)

    options = trajectory_solver_options(tcfg, function_tolerance=lcfg.function_tolerance,
                                        initial_lambda=lcfg.initial_lambda)
    solve = joint.problem.solve(options, progress=report)
    progress("G/I/L adjustment of the flights", 1, 1)
    out = []
    for k, (f, g) in enumerate(zip(flights, gils)):
        view = joint.part(k)
        built = replace(g.built, problem=view)
        result = _read_out(built, joint.part_solve(k, solve))
        if tcfg.upsampling:
            result = replace(result, high_rate=rebuild_high_rate(f.nav.gnss, result))
        bs_deg = boresight_deg_of(view.values(BORESIGHT_BLOCK)[0]) if g.boresight else None
        offset = g.time_offset.features_s
        if g.estimates_offset:
            offset += float(view.values(OFFSET_BLOCK)[0, 0])
        out.append(LidarAdjustment(result, g.features_used, g.objects_used, bs_deg, None, built,
                                   time_offset_s=offset, time_offset_start=g.time_offset,
                                   time_offset_held=g.offset_held, **scanner_estimates(view)))
    adj = FlightsAdjustment(tuple(out), solve, int(every.size), int(used.size), joint, tuple(shared))
    return add_flights_posterior(adj) if covariance else adj


def _read_out(built: GnssImuProblem, solve: SolveResult) -> GnssImuResult:
    """A flight's trajectory, IMU errors and correlated GNSS error from its part of the solved joint problem
    (as :func:`~georefine.adjustment.gnss_imu.solve_gnss_imu` reads them from one problem)."""
    errors = imu_errors_of(built)
    return GnssImuResult(built.spline(), errors, solve, np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), {},
                         gnss_error=gnss_error_of(built))


def add_flights_posterior(adj: FlightsAdjustment) -> FlightsAdjustment:
    """``adj`` with the posterior sigma of every flight (trajectory, IMU errors) and of the shared boresight and
    time offset, from the joint problem's one posterior; the joint problem is let go."""
    joint = adj.joint
    if joint is None:
        return adj
    built = [a.built for a in adj.flights]
    joint.problem.expect_covariance(sum(posterior_columns(b) for b in built) + 3 * len(built) + len(built))
    flights = []
    for a, b in zip(adj.flights, built):
        result = with_posterior(b, a.result)
        vf = posterior_scale(result.solve)
        extra = {}
        if a.boresight_deg is not None:
            cov = b.problem.covariance(BORESIGHT_BLOCK, scale_by_variance_factor=False)[0] * vf
            extra["boresight_sigma_mdeg"] = np.degrees(np.sqrt(np.diag(cov))) * 1e3
            extra["boresight_body_sigma_mdeg"] = boresight_body_sigma_mdeg(b.problem.values(BORESIGHT_BLOCK)[0], cov)
        if OFFSET_BLOCK in b.problem.blocks:
            cov = b.problem.covariance(OFFSET_BLOCK, scale_by_variance_factor=False)[0, 0, 0] * vf
            extra["time_offset_sigma_s"] = float(np.sqrt(cov))
        extra |= {k: v for k, v in scanner_estimates(b.problem, vf).items() if k.endswith("_sigma")}
        flights.append(replace(a, result=result, built=None, **extra))
    solve = flights[0].result.solve
    solve = replace(adj.solve, variance_components=solve.variance_components)
    return replace(adj, flights=tuple(flights), solve=solve, joint=None)


# --- features of all flights ----------------------------------------------------------------


def _strip_flight(flights: list[FlightInputs]) -> dict[int, int]:
    return {s.strip_id: k for k, f in enumerate(flights) for s in f.strips}


def joint_features(flights: list[FlightInputs], currents: list[GnssImuResult], strips: list[list[StripFile]],
                   progress: Progress, runner: TaskRunner, search: bool = False, scratch: Path | None = None):
    """Steps 3-4 for all flights: each flight's features extracted with its own trajectory, then matched together.

    Returns ``(features, objects, flight_of, views, outside, found, extracted)``: the matched
    features of all flights (sorted by strip, channel, time; each with its own flight's times),
    their objects, each feature's flight index, the features per view, the points outside the
    trajectories, the time offset search (or None) and the features extracted in all. With
    ``processing.scale.feature_tile_m`` every flight's features go to one store of ground tiles (in
    a folder in ``scratch``; strip ids are unique across the flights) and each tile is matched on
    its own (:mod:`georefine.lidar.feature_tiles`: the objects of matching them all at once, which
    ``null`` does). With ``search`` the offset is searched over all strips of all flights before
    matching; an adopted offset shifts and re-georeferences every flight's features.
    """
    cfg = flights[0].nav.config
    mcfg = cfg.processing.matching
    tile_m = cfg.processing.scale.feature_tile_m
    store = None if tile_m is None else FeatureStore(tile_size(tile_m, mcfg), scratch)
    by_strip = _strip_flight(flights)
    try:
        parts, views, outside, trajs = [], {}, 0, []
        for f, cur, s in zip(flights, currents, strips):
            traj = imu_rate_trajectory(f.nav, cur)
            trajs.append(traj)
            feats, counts = step_features(f.nav, traj, s, progress, runner, frame_poses=cur.spline.pose, store=store)
            parts.append(feats)
            views.update(counts.views)
            outside += counts.points_outside_trajectory
        found = None
        if search:
            progress("LiDAR time offset search", 0, 1)
            if store is None:
                found, parts = _search_flights(flights, trajs, currents, parts, strips[0][0].time_offset_s)
            else:
                found, store = _search_flights_store(flights, trajs, currents, store, strips[0][0].time_offset_s,
                                                     by_strip)
            progress("LiDAR time offset search", 1, 1)
        if store is None:
            features = sort_features(PlanarFeatures.concatenate(parts))
            progress("matching planar features", 0, 1)
            objects = match_features(features, mcfg)
            progress("matching planar features", 1, 1)
            used = objects.feature_object >= 0
            features, objects = features.select(used), replace(objects, feature_object=objects.feature_object[used])
        else:  # the tiles' tasks show their progress
            tiled = match_store(store, mcfg, runner, progress)
            features, objects = tiled.features, tiled.objects
    finally:
        if store is not None:
            store.close()
    return features, objects, _flight_of(by_strip, features.strip), views, outside, found, int(sum(views.values()))


def _flight_of(by_strip: dict[int, int], strip: np.ndarray) -> np.ndarray:
    """(F,) int64 index of each feature's flight from its strip."""
    return np.array([by_strip[int(s)] for s in strip], dtype=np.int64)


def _joint_search(flights, trajs: list[Trajectory], features: list[PlanarFeatures], configured_s: float):
    """The time offset search over every flight's ``features`` in one time base (:data:`SEARCH_SHIFT_S`), logged."""
    cfg = flights[0].nav.config
    tcfg = cfg.processing.lidar.time_offset
    p_b_s = np.asarray(cfg.scanner.lever_arm_m, dtype=float)
    R_b_s = boresight_matrix(cfg.scanner.boresight_deg)
    joint = Trajectory(np.concatenate([t.time + k * SEARCH_SHIFT_S for k, t in enumerate(trajs)]),
                       np.concatenate([t.p_w_b for t in trajs]), np.concatenate([t.R_w_b for t in trajs]))
    poses = PoseInterpolator(joint)
    shifted = [replace(p, time=p.time + k * SEARCH_SHIFT_S) for k, p in enumerate(features)]
    speed = np.concatenate([np.linalg.norm(np.diff(t.p_w_b, axis=0), axis=1) / np.diff(t.time) for t in trajs])
    result = search_time_offset(PlanarFeatures.concatenate(shifted), poses, poses.span, p_b_s, R_b_s,
                                speed_max_m_s=float(np.percentile(speed, 99.5)), configured_s=configured_s,
                                range_s=tcfg.search_range_s, feature_spacing_m=cfg.processing.planes.seed_spacing_m)
    if result.adopted:
        log.warning("LiDAR time offset (%d flights): %s", len(flights), result.describe())
    else:
        log.info("LiDAR time offset search over %d flights: %s", len(flights), result.describe())
    return result


def _search_flights(flights, trajs: list[Trajectory], currents, parts: list[PlanarFeatures], configured_s: float):
    """The joint time offset search over the features of all flights; the features at the adopted offset."""
    result = _joint_search(flights, trajs, parts, configured_s)
    if not result.adopted:
        return result, parts
    delta = result.best_s - configured_s
    nav = flights[0].nav  # the first flight's scanner calibration, as the search itself
    return result, [shifted_features(nav, cur.spline.pose, (traj.time[0], traj.time[-1]), p, delta)[0]
                    for traj, cur, p in zip(trajs, currents, parts)]


def _search_flights_store(flights, trajs: list[Trajectory], currents, store: FeatureStore, configured_s: float,
                          by_strip: dict[int, int]) -> tuple:
    """:func:`_search_flights` on a ground-tiled ``store``: the search scores its sample; at an adopted
    offset every flight's features move, tile by tile, into a new store (``store`` is closed)."""
    sample = store.sample.features()
    of = _flight_of(by_strip, sample.strip)
    result = _joint_search(flights, trajs, [sample.select(np.flatnonzero(of == k)) for k in range(len(flights))],
                           configured_s)
    if not result.adopted:
        return result, store
    delta = result.best_s - configured_s
    nav = flights[0].nav  # the first flight's scanner calibration, as the search itself

    def shift(features: PlanarFeatures, arrival: np.ndarray) -> tuple[PlanarFeatures, np.ndarray]:
        of = _flight_of(by_strip, features.strip)
        parts, kept = [], []
        for k, (traj, cur) in enumerate(zip(trajs, currents)):
            mine = np.flatnonzero(of == k)
            shifted, inside = shifted_features(nav, cur.spline.pose, (traj.time[0], traj.time[-1]),
                                               features.select(mine), delta)
            parts.append(shifted)
            kept.append(arrival[mine][inside])
        return PlanarFeatures.concatenate(parts), np.concatenate(kept)

    return result, store.transformed(shift)


# --- the run ------------------------------------------------------------------------------


@dataclass(frozen=True)
class FlightsResult:
    """What :func:`run_flights` computed and wrote: per flight the G/I and the G/I/L (with posterior), the
    joint adjustment's statistics, and ``metrics.json``'s record."""

    out: Path
    flights: tuple[Flight, ...]
    gi: tuple[GnssImuResult, ...]
    gil: tuple[LidarAdjustment, ...]
    solve: SolveResult
    metrics: WorkflowMetrics

    def summary(self) -> str:
        m = self.metrics
        lines = [f"Results written to {self.out} ({len(self.flights)} flights adjusted together)"]
        for it in m.outer_iterations:
            lines.append(f"  iteration {it.iteration}: {it.features:,} features, {it.objects:,} objects, "
                         f"{it.features_used:,} used; largest RMS change of a flight {it.attitude_change_mdeg:.2f} "
                         f"mdeg, {it.position_change_m * 1e3:.1f} mm")
        g = self.gil[0]
        if g.boresight_deg is not None:
            b = g.boresight_deg
            lines.append(f"  boresight roll/pitch/yaw (all flights): {b[0]:.4f} {b[1]:.4f} {b[2]:.4f} deg")
        if g.time_offset_sigma_s is not None:
            lines.append(f"  LiDAR time offset (all flights): {g.time_offset_s:+.5f} s ± "
                         f"{g.time_offset_sigma_s * 1e3:.3f} ms")
        if g.time_offset_held is not None:
            lines.append(f"  LiDAR time offset: held at {g.time_offset_s:+.5f} s: {g.time_offset_held}")
        lines += g.calibration_lines(" (all flights)")
        lines += precision_lines(m.pass_precision)
        if m.resumed:
            lines.append("  resumed from the cache: " + ", ".join(m.resumed))
        lines.append("  timings: " + ", ".join(f"{k} {v:.1f} s" for k, v in m.timings_s.items()))
        return "\n".join(lines)


def _gil_key(flights: list[FlightInputs], gi_keys: list[str]) -> str:
    """Key of the joint outer iterations and posterior: every flight's G/I key and strips, the LiDAR configuration."""
    cfg = flights[0].nav.config
    return StepCache.key("flights_gil", gi_keys, FEATURES_VERSION,
                         [[file_stamp(s.path, f.nav.root) for s in f.strips] for f in flights],
                         [f.nav.config.scanner.model_dump() for f in flights], cfg.processing.planes.model_dump(),
                         cfg.processing.matching.model_dump(), cfg.processing.lidar.model_dump())


@dataclass(frozen=True)
class _Outcome:
    """The joint G/I/L with posterior, its outer iterations, and the last iteration's features and objects."""

    gil: tuple[LidarAdjustment, ...]
    solve: SolveResult
    records: tuple[OuterIteration, ...]
    features: PlanarFeatures
    objects: PlanarObjects


def _outer_iterations(flights: list[FlightInputs], gis: list[GnssImuResult], steps: StepRunner, progress: Progress,
                      runner: TaskRunner, scratch: Path | None = None) -> _Outcome:
    cfg = flights[0].nav.config
    lcfg = cfg.processing.lidar
    share_bs, share_offset = shared_calibration(flights)
    search = lcfg.time_offset.search and share_offset
    if lcfg.time_offset.search and not share_offset:
        log.info("the flights state different LiDAR time offsets: each estimates its own, no joint search")
    shaking = [vibrating(f.nav, g) for f, g in zip(flights, gis)]
    current = list(gis)
    starts = [TimeOffsetStart(s[0].time_offset_s, s[0].time_offset_s) for s in (f.strips for f in flights)]
    strips = [f.strips for f in flights]
    records = []
    for it in range(1, lcfg.outer_iterations + 1):
        with steps.timed(f"features_{it}"):
            features, objects, flight_of, views, outside, found, extracted = joint_features(
                flights, current, strips, progress, runner, search=search and it == 1, scratch=scratch)
        if found is not None:
            starts = [TimeOffsetStart(found.offset_s, found.offset_s)] * len(flights)
        knots = [outer_knot_interval(lcfg, f.nav.config.processing.trajectory.knot_interval_s, it, v)
                 for f, v in zip(flights, shaking)]
        with steps.timed(f"gil_adjustment_{it}"):
            adj = step_adjust_flights(flights, current, features, objects, flight_of, progress, covariance=False,
                                      knot_intervals_s=knots, time_offsets=starts)
        changes = [trajectory_change(c.spline, a.result.spline) for c, a in zip(current, adj.flights)]
        d_att, d_pos = max(c[0] for c in changes), max(c[1] for c in changes)
        g0 = adj.flights[0]
        record = OuterIteration(it, extracted, len(objects), adj.features_used, adj.objects_used, d_att, d_pos,
                                outside, views, g0.result.spline.grid.dt, starts[0].features_s, starts[0].prior_s,
                                g0.time_offset_s, None if found is None else found.to_dict())
        records.append(record)
        log.info("flights' outer iteration %d: %s", it, ", ".join(
            f"flight {f.flight.id} {c[0]:.2f} mdeg, {c[1] * 1e3:.1f} mm" for f, c in zip(flights, changes)))
        current = [a.result for a in adj.flights]
        converged = all(k is None for k in knots) and outer_converged(record, lcfg)
        if converged or it == lcfg.outer_iterations:
            break
        # The next iteration extracts its features at this one's estimate of the time offset.
        starts = [TimeOffsetStart(a.time_offset_s, s.prior_s) for a, s in zip(adj.flights, starts)]
        strips = [[s.shifted(a.time_offset_s) for s in f.strips] for f, a in zip(flights, adj.flights)]
    if not converged:
        warn_unconverged(records, lcfg)
    progress("G/I/L posterior sigma", 0, 1)
    with steps.timed("gil_covariance"):
        adj = add_flights_posterior(adj)
    progress("G/I/L posterior sigma", 1, 1)
    return _Outcome(adj.flights, adj.solve, tuple(records), features, objects)


def _write_points(flights: list[FlightInputs], gils: tuple[LidarAdjustment, ...], project: Project, out: Path,
                  runner: TaskRunner, progress: Progress) -> tuple[PointsWritten, ...]:
    """Step 6: every strip in the output CRS with its own flight's trajectory, boresight and time offset, and the
    scanner calibration the flights share."""
    folder = out / "points"
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for f, g in zip(flights, gils):
        nav = f.nav
        p_b_s = np.asarray(nav.config.scanner.lever_arm_m, dtype=float)
        R_b_s = boresight_matrix(tuple(g.boresight_deg) if g.boresight_deg is not None
                                 else nav.config.scanner.boresight_deg)
        offset = g.time_offset_s
        strips = [s.shifted(offset) for s in f.strips]
        interpolator = PoseInterpolator(imu_rate_trajectory(nav, g.result))
        refuse_strips_outside([s.plan for s in strips], interpolator.span, nav.t0_gps, offset)
        paths = [folder / (s.path.stem + ".laz") for s in strips]
        results = georeference_strips([s.plan for s in strips], paths, runner.share(interpolator), nav.t0_gps, p_b_s,
                                      R_b_s, nav.frame, project.crs, runner=runner, progress=progress,
                                      protect=(project.root,), time_offset_s=offset, heights=project.heights,
                                      calibration=g.scanner_calibration())
        written += [PointsWritten.from_dict({"strip": s.strip_id, "file": path.name, "points": r.points_written,
                                             "outside_trajectory": r.points_outside})
                    for s, path, r in zip(f.strips, paths, results)]
    return tuple(written)


def run_flights(
    project: Project,
    out: str | Path,
    *,
    resume: bool = True,
    points: bool = True,
    cache_dir: str | Path | None = None,
    progress: Progress = no_progress,
    scheduler: str | TaskRunner = DEFAULT_SCHEDULER,
) -> FlightsResult:
    """Steps 1-6 on a project of several flights, the G/I/L of all flights adjusted together (module docstring).

    Steps 1-2 of each flight are cached (``out/.cache`` or ``cache_dir``) under the key a run of that
    flight alone gives them; the joint outer iterations with their posterior are cached as one step.
    ``points=False`` skips the final point clouds.

    Raises
    ------
    InputError
        Bad navigation data or strips of a flight, or no planar features.
    """
    flight_records = project.flights
    with open_workspace(project, out, resume=resume, cache_dir=cache_dir, scheduler=scheduler) as ws:
        steps, runner = ws.steps, ws.runner
        progress("reading the input", 0, 1)
        flights = []
        with steps.timed("read"):
            for fl in flight_records:
                fp = project.flight_project(fl.id)
                nav = project.navigation_of(fl.id)
                strips = read_strips(nav, slots=runner.workers)
                refuse_strips_outside([s.plan for s in strips], nav.span, nav.t0_gps, nav.config.scanner.time_offset_s)
                flights.append(FlightInputs(fl, fp, nav, strips))
        ids = [s.strip_id for f in flights for s in f.strips]
        if len(set(ids)) != len(ids):
            raise InputError("two strips of the project have the same point_source_id: the flights' features are "
                             "matched together by strip", path=project.root / "project.yaml", field="flights.strips",
                             expected="a point_source_id per strip unique across the flights",
                             found=", ".join(map(str, ids)))
        make_output_folder(ws.out)
        progress("reading the input", 1, 1)
        staged = [stage_gnss_imu(steps, f.nav, progress) for f in flights]  # each cached as its flight alone
        gis, gi_keys = [g for g, _ in staged], [k for _, k in staged]
        for f, gi in zip(flights, gis):
            folder = ws.out / "gi" / f"flight_{f.flight.id}"
            folder.mkdir(parents=True, exist_ok=True)
            write_trajectory_products(folder, f.nav, gi, project.crs)
            write_adjustment_report(folder / "adjustment.json", adjustment_report(f.nav, gi, "G/I"))
        outcome = steps.cached("flights_gil", _gil_key(flights, gi_keys),
                               lambda: _outer_iterations(flights, gis, steps, progress, runner, ws.out))
        gils = tuple(replace(g, time_offset_gnss_sigma_s=gnss_offset_sigma(f.nav, gi)) if g.time_offset_sigma_s
                     is not None else g for f, g, gi in zip(flights, outcome.gil, gis))
        cfg = flights[0].nav.config
        g0 = gils[0]
        warn_time_offset(cfg, g0.time_offset_s, g0.time_offset_sigma_s, g0.time_offset_gnss_sigma_s or 0.0)
        for f, gi, g in zip(flights, gis, gils):
            warn_plane_misfit(gi, g, outcome.records, f.nav)
            warn_gi_tilt(gi, g, f.nav.frame, who=f"flight {f.flight.id}: ")
            warn_gnss_error_misfit(g, f"flight {f.flight.id}'s G/I/L")
        warn_boresight_separation(gis, gils)
        (ws.out / "features").mkdir(exist_ok=True)
        used = np.flatnonzero(outcome.objects.feature_object >= 0)
        write_features(ws.out / "features" / "features.csv", outcome.features.select(used))
        write_objects(ws.out / "features" / "objects.csv",
                      replace(outcome.objects, feature_object=outcome.objects.feature_object[used]))
        for f, g in zip(flights, gils):
            folder = ws.out / "gil" / f"flight_{f.flight.id}"
            folder.mkdir(parents=True, exist_ok=True)
            write_trajectory_products(folder, f.nav, g.result, project.crs)
            write_adjustment_report(folder / "adjustment.json", adjustment_report(f.nav, g.result, "G/I/L", g))
        written = ()
        if points:
            with steps.timed("final_georeferencing"):
                written = _write_points(flights, gils, project, ws.out, runner, progress)
        passes = tuple(p for f, gi, g in zip(flights, gis, gils) for p in pass_precision(
            gi, g.result, {s.strip_id: (float(s.t_first), float(s.t_last)) for s in f.strips}))
        metrics = WorkflowMetrics(
            t0_gps=flights[0].nav.t0_gps, strips=tuple(ids),
            strip_time_gps={s.strip_id: (float(s.t_first + f.nav.t0_gps), float(s.t_last + f.nav.t0_gps))
                            for f in flights for s in f.strips},
            outer_iterations=outcome.records, points=written, resumed=steps.resumed,
            timings_s=dict(steps.timings_s), pass_precision=passes)
        write_json(ws.out / "metrics.json", metrics.to_dict())
        write_yaml(ws.out / "config.resolved.yaml", project.config)
        return FlightsResult(ws.out, tuple(project.flights), tuple(gis), gils, outcome.solve, metrics)
