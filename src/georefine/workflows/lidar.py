"""Workflow steps 3-6 of paper 000: tightly-coupled GNSS/IMU/LiDAR trajectory estimation.

3. Preliminary georeferencing of every strip with the current trajectory (IMU rate, per-point
   interpolation).
4. Planar features per view (strip x scanner channel) and their matching across views into
   planar objects.
5. GNSS/IMU/LiDAR adjustment: the GNSS/IMU problem plus the plane observations (robust loss),
   optionally the boresight. Steps 3-5 repeat (outer iterations) until the trajectory changes
   less than the configured thresholds.
6. Final georeferencing into the output CRS.

Steps 3-4 are in :mod:`georefine.workflows.strips`, step 5 in :mod:`georefine.workflows.gil`; the
outer iterations and the run are here.
:func:`run_workflow` runs the workflow as explicit stages -- read inputs, G/I, G/I products,
outer iterations, posterior, G/I/L products, final point clouds, metrics -- each cached stage
through one helper (:class:`~georefine.workflows.cache.StepRunner`). It writes ``gi/`` and
``gil/`` (trajectory products), ``points/*.laz``, ``features/`` (features and objects as CSV),
``metrics.json`` (:class:`~georefine.io.run_metrics.WorkflowMetrics`) and the resolved
configuration.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np

from georefine.adjustment.gnss_imu import (
    GnssImuResult,
)
from georefine.config import boresight_matrix, write_yaml
from georefine.errors import ConfigError
from georefine.geometry.frames import GeoidHeights, OutputCRS
from georefine.io.files import make_output_folder, write_json
from georefine.io.run_metrics import (
    OuterIteration,
    PointsWritten,
    WorkflowMetrics,
    write_adjustment_report,
)
from georefine.lidar.correspondences import PlanarObjects, match_features
from georefine.lidar.feature_tiles import FeatureStore, match_store, tile_size
from georefine.lidar.georeference import PoseInterpolator
from georefine.lidar.object_files import write_objects
from georefine.lidar.planes import FEATURES_VERSION, PlanarFeatures, write_features
from georefine.lidar.tiles import georeference_strips, refuse_strips_outside
from georefine.progress import Progress, no_progress
from georefine.tasks import DEFAULT_SCHEDULER, TaskRunner
from georefine.workflows.cache import StepCache, StepRunner, file_stamp
from georefine.workflows.calibration_check import CalibrationCheck, check_scanner_calibration, warn_calibration
from georefine.workflows.flights import FlightsResult, run_flights
from georefine.workflows.gil import LidarAdjustment, add_posterior, step_adjust_gil
from georefine.workflows.navigation import (
    NavigationData,
    imu_rate_trajectory,
    write_trajectory_products,
)
from georefine.workflows.opened import Project, ProjectLike, Workspace, as_project, open_workspace
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
from georefine.workflows.run_parts import (
    adjustment_report,
    frame_crs,
    navigation_key,
    outer_knot_interval,
    stage_gnss_imu,
    vibrating,
)
from georefine.workflows.strip_baseline import stage_strip_baseline
from georefine.workflows.strips import FeatureCounts, StripFile, read_strips, step_features
from georefine.workflows.time_offset import (
    TimeOffsetStart,
    gnss_offset_sigma,
    search_and_shift,
    search_and_shift_store,
    warn_time_offset,
)

log = logging.getLogger(__name__)

__all__ = [  # steps 3-5 live in georefine.workflows.strips and .gil; named here as the workflow's steps
    "FeatureCounts", "LidarAdjustment", "StripFile", "WorkflowResult", "add_posterior", "precompute_gnss_imu",
    "read_strips", "run_workflow", "step_adjust_gil", "step_features", "trajectory_change",
]


@dataclass(frozen=True)
class WorkflowResult:
    """What :func:`run_workflow` computed and wrote (``metrics``: what ``metrics.json`` holds)."""

    out: Path
    gi: GnssImuResult
    gil: LidarAdjustment | None
    metrics: WorkflowMetrics

    def summary(self) -> str:
        m = self.metrics
        lines = [f"Results written to {self.out}"]
        for it in m.outer_iterations:
            lines.append(
                f"  iteration {it.iteration}: {it.features:,} features, {it.objects:,} objects, "
                f"{it.features_used:,} used; RMS change {it.attitude_change_mdeg:.2f} mdeg, "
                f"{it.position_change_m * 1e3:.1f} mm"
            )
        if self.gil is not None and self.gil.boresight_deg is not None:
            b = self.gil.boresight_deg
            lines.append(f"  boresight roll/pitch/yaw: {b[0]:.4f} {b[1]:.4f} {b[2]:.4f} deg")
        if self.gil is not None and self.gil.time_offset_sigma_s is not None:
            gnss = self.gil.time_offset_gnss_sigma_s
            lines.append(f"  LiDAR time offset: {self.gil.time_offset_s:+.5f} s ± {self.gil.time_offset_sigma_s * 1e3:.3f} ms"
                         + (f" (± {gnss * 1e3:.2f} ms from GNSS errors that last a pass)" if gnss else ""))
        if self.gil is not None:
            lines += self.gil.calibration_lines()
        if self.gil is not None and self.gil.time_offset_held is not None:
            lines.append(f"  LiDAR time offset: held at {self.gil.time_offset_s:+.5f} s, not estimated: "
                         f"{self.gil.time_offset_held}")
        lines += precision_lines(m.pass_precision)
        if m.resumed:
            lines.append("  resumed from the cache: " + ", ".join(m.resumed))
        lines.append("  timings: " + ", ".join(f"{k} {v:.1f} s" for k, v in m.timings_s.items()))
        return "\n".join(lines)


# --- The stages of run_workflow -------------------------------------------------------------
#
# read inputs -> G/I (steps 1-2) -> G/I products -> outer iterations (steps 3-5) -> posterior
# -> G/I/L products -> final point clouds (step 6) -> metrics. Every stage that is cached runs
# through StepRunner.cached with a key that chains the key of the stage before it.


@dataclass(frozen=True)
class WorkflowInputs:
    """The read inputs of a run: navigation data, strips (indexed), output folder, CRS and task
    runner; ``heights``: the final point clouds' gravity-related heights (``crs.geoid_grid``), or
    ``None`` for ellipsoidal ones."""

    nav: NavigationData
    strips: list[StripFile]
    out: Path
    crs: OutputCRS
    runner: TaskRunner
    heights: GeoidHeights | None = None


@dataclass(frozen=True)
class IterationOutcome:
    """One outer iteration: the adjustment (no posterior) and its record.

    ``features`` and ``objects`` are there only when the iteration was computed, not loaded
    (the cache keeps them apart: only the last iteration's are needed, by the posterior).
    """

    gil: LidarAdjustment
    record: OuterIteration
    features: PlanarFeatures | None = None
    objects: PlanarObjects | None = None

    def cached_form(self) -> tuple[LidarAdjustment, dict]:
        """What the cache stores: the adjustment without its problem, the record as a plain dict."""
        return replace(self.gil, built=None), self.record.to_dict()

    @classmethod
    def from_cached(cls, stored: tuple[LidarAdjustment, dict]) -> IterationOutcome:
        gil, record = stored
        return cls(gil, OuterIteration.from_dict(record))


@dataclass(frozen=True)
class OuterIterations:
    """The outer iterations until convergence: the last one, where it started, its cache key."""

    last: IterationOutcome
    start: GnssImuResult
    key: str
    records: tuple[OuterIteration, ...]


@dataclass(frozen=True)
class Posterior:
    """The G/I/L adjustment with posterior sigma, the last iteration's features and objects, its key."""

    gil: LidarAdjustment
    features: PlanarFeatures
    objects: PlanarObjects
    key: str


@contextmanager
def untimed(name: str) -> Iterator[None]:
    """A ``timed`` that records nothing: a recomputation inside another step's time."""
    yield


def features_and_objects(nav, current: GnssImuResult, strip_files, it: int, timed, progress, runner,
                         search: bool = False, scratch: Path | None = None):
    """Steps 3-4 from ``current``: planar features per view and their matching into objects.

    The matched features only (the members of objects, in the order of strip, channel and time)
    and their objects; with ``processing.scale.feature_tile_m`` the features go to ground tiles
    on disk (in a folder in ``scratch``, default the system's temporary folder) and each tile is
    matched on its own (:mod:`georefine.lidar.feature_tiles`: the same objects as matching the
    whole flight's features held at once, which ``null`` does). With ``search`` the LiDAR time
    offset is searched between extraction and matching
    (:func:`~georefine.workflows.time_offset.search_and_shift`); the search's result (or None)
    is returned last, and the features are at its offset.
    """
    cfg = nav.config
    tile_m = cfg.processing.scale.feature_tile_m
    store = None if tile_m is None else FeatureStore(tile_size(tile_m, cfg.processing.matching), scratch)
    found = None
    try:
        with timed(f"features_{it}"):
            traj = imu_rate_trajectory(nav, current)
            features, counts = step_features(nav, traj, strip_files, progress, runner,
                                             frame_poses=current.spline.pose, store=store)
        if search:
            progress("LiDAR time offset search", 0, 1)
            with timed("time_offset_search"):
                if store is None:
                    found, features = search_and_shift(nav, traj, current.spline.pose, features,
                                                       strip_files[0].time_offset_s)
                else:
                    found, store = search_and_shift_store(nav, traj, current.spline.pose, store,
                                                          strip_files[0].time_offset_s)
            progress("LiDAR time offset search", 1, 1)
        with timed(f"matching_{it}"):
            if store is not None:  # the tasks show their progress
                tiled = match_store(store, cfg.processing.matching, runner, progress)
                return tiled.features, tiled.objects, counts, found
            progress("matching planar features", 0, 1)
            objects = match_features(features, cfg.processing.matching)
            progress("matching planar features", 1, 1)
    finally:
        if store is not None:
            store.close()
    used = objects.feature_object >= 0
    return features.select(used), replace(objects, feature_object=objects.feature_object[used]), counts, found


def _searches(nav, it: int) -> bool:
    """Whether outer iteration ``it`` searches the time offset (the first, when configured)."""
    return it == 1 and nav.config.processing.lidar.time_offset.search


def _outer_iteration(nav, current: GnssImuResult, strip_files, it: int, timed, progress, runner,
                     knot_interval_s: float | None = None, prior_s: float | None = None,
                     scratch: Path | None = None) -> IterationOutcome:
    """Steps 3-5 once from ``current``: features, objects, G/I/L adjustment (no posterior) and record.

    ``strip_files`` are at the offset the features are extracted at; ``prior_s`` centres the
    offset's prior (default: the search's result in the first iteration, else that offset);
    ``scratch`` holds the ground tiles' features while they are matched.
    """
    features, objects, counts, found = features_and_objects(nav, current, strip_files, it, timed, progress, runner,
                                                            search=_searches(nav, it), scratch=scratch)
    start_s = found.offset_s if found is not None else strip_files[0].time_offset_s
    start = TimeOffsetStart(start_s, start_s if prior_s is None else prior_s)
    with timed(f"gil_adjustment_{it}"):
        gil = step_adjust_gil(nav, current, features, objects, progress, covariance=False,
                              knot_interval_s=knot_interval_s, time_offset=start)
    d_att, d_pos = trajectory_change(current.spline, gil.result.spline)
    record = OuterIteration(it, counts.extracted, len(objects), gil.features_used, gil.objects_used, d_att, d_pos,
                            counts.points_outside_trajectory, counts.views, gil.result.spline.grid.dt,
                            start.features_s, start.prior_s, gil.time_offset_s,
                            None if found is None else found.to_dict())
    return IterationOutcome(gil, record, features, objects)


def _lidar_key(nav: NavigationData, strips: list[StripFile], upstream: str, iteration: int) -> str:
    """Key of outer iteration ``iteration``: the strips, the LiDAR configuration and the key before it."""
    cfg = nav.config
    return StepCache.key(
        "gil", iteration, upstream, FEATURES_VERSION, [file_stamp(s.path, nav.root) for s in strips],
        cfg.scanner.model_dump(),
        # The baseline beside the G/I/L changes nothing in it.
        cfg.processing.planes.model_dump(), cfg.processing.matching.model_dump(),
        cfg.processing.lidar.model_dump(exclude={"strip_baseline"}),
    )


def _points_key(nav: NavigationData, strips: list[StripFile], upstream: str) -> str:
    """Key of step 6: the trajectory's key, the CRS, the scanner and the strips (named relative
    to the project, as in the other steps' keys: a project moved, or named by another path,
    keeps its points). With a geoid grid, its vertical CRS and the grid file's stamp too."""
    crs = nav.config.crs
    geoid = ([] if crs.geoid_grid is None
             else [[crs.vertical_epsg, file_stamp(nav.root / crs.geoid_grid, nav.root)]])
    return StepCache.key("points", upstream, frame_crs(nav.config), nav.config.scanner.model_dump(),
                         [file_stamp(s.path, nav.root) for s in strips], *geoid)


def stage_read_inputs(steps: StepRunner, project: Project, out: Path,
                      strips: list[int] | None, runner: TaskRunner) -> WorkflowInputs:
    """Read and check the navigation data (once per project: :attr:`Project.navigation
    <georefine.workflows.opened.Project.navigation>`), index the strips (time tiles); create the
    output folder ``out``, a workspace's (:func:`~georefine.workflows.opened.open_workspace`
    checked it). Its sub-folders are made by the stages that write into them."""
    with steps.timed("read"):
        nav = project.navigation
        strip_files = read_strips(nav, strips, slots=runner.workers)
        # A strip entirely outside the navigation is refused now, as `georefine check` does, not
        # after the adjustments (the time offset search looks ±20 s around scanner.time_offset_s).
        refuse_strips_outside([s.plan for s in strip_files], nav.span, nav.t0_gps, nav.config.scanner.time_offset_s)
    make_output_folder(out)
    return WorkflowInputs(nav, strip_files, out, project.crs, runner, project.heights)


def stage_outer_iterations(steps: StepRunner, inputs: WorkflowInputs, gi: GnssImuResult, key: str,
                           progress: Progress = no_progress) -> OuterIterations:
    """Steps 3-5 repeated from ``gi`` until the trajectory changes less than the thresholds.

    Each iteration is cached under a key that chains the one before it; a computed
    iteration's features and objects are kept too (the last only), for the posterior.
    """
    nav, lcfg = inputs.nav, inputs.nav.config.processing.lidar
    current, records, strips, prior = gi, [], inputs.strips, None
    shaking = vibrating(nav, gi)
    for it in range(1, lcfg.outer_iterations + 1):
        key = _lidar_key(nav, inputs.strips, key, it)
        start = current
        coarse = outer_knot_interval(lcfg, nav.config.processing.trajectory.knot_interval_s, it, shaking)
        # The previous iteration's problem and factorisation go before this one is built: held
        # through the next extraction and adjustment they doubled the G/I/L's share of the peak.
        outcome = None
        outcome = steps.cached(
            f"gil_{it}", key, partial(_outer_iteration, nav, start, strips, it, steps.timed, progress,
                                      inputs.runner, coarse, prior, inputs.out),
            encode=IterationOutcome.cached_form, decode=IterationOutcome.from_cached,
        )
        if outcome.features is not None:
            steps.keep("gil_features", key, (outcome.features, outcome.objects))
        if it == 1 and lcfg.strip_baseline:  # the classical strip adjustment from the same planes
            stage_strip_baseline(
                steps, nav, gi, inputs.strips, key, (outcome.features, outcome.objects),
                outcome.record.time_offset_start_s, inputs.out / "baseline", inputs.crs,
                lambda strips: features_and_objects(nav, gi, strips, 1, untimed, progress, inputs.runner,
                                                    scratch=inputs.out)[:2], progress)
        records.append(outcome.record)
        current = outcome.gil.result
        # The next iteration extracts its features at this one's estimate of the time offset.
        prior = outcome.record.time_offset_prior_s
        strips = [s.shifted(outcome.gil.time_offset_s) for s in inputs.strips]
        if coarse is None and outer_converged(outcome.record, lcfg):  # a coarse start is never the result
            break
    else:
        warn_unconverged(records, lcfg)
    return OuterIterations(outcome, start, key, tuple(records))


def stage_posterior(steps: StepRunner, inputs: WorkflowInputs, outer: OuterIterations,
                    progress: Progress = no_progress) -> Posterior:
    """The posterior sigma of the last outer iteration (cached), and that iteration's features and objects.

    When the last iteration came from the cache, its features come from the cache too, or are
    recomputed from the trajectory it started at (deterministic); and its problem is solved
    once more (from the same start, a short solve) for the covariance.
    """
    nav, last = inputs.nav, outer.records[-1]
    it = last.iteration
    with steps.timed("gil_covariance"):
        features, objects = outer.last.features, outer.last.objects
        if features is None:  # extracted as the iteration did: at its start offset, or searched from the configured
            strips = inputs.strips if _searches(nav, it) else [s.shifted(last.time_offset_start_s) for s in inputs.strips]
            features, objects, _, _ = steps.cached(
                "gil_features", outer.key,
                lambda: features_and_objects(nav, outer.start, strips, it, untimed, progress, inputs.runner,
                                             search=_searches(nav, it), scratch=inputs.out),
                decode=lambda fo: (*fo, None, None), store=False,
            )

        def compute() -> LidarAdjustment:
            gil = outer.last.gil
            if gil.built is None:  # the last iteration came from the cache: one more (short) solve
                gil = step_adjust_gil(nav, outer.start, features, objects, progress, covariance=False,
                                      time_offset=TimeOffsetStart(last.time_offset_start_s, last.time_offset_prior_s))
            return replace(add_posterior(gil), built=None)

        key = StepCache.key("gil_posterior", outer.key)
        progress("G/I/L posterior sigma", 0, 1)
        gil = steps.cached("gil_posterior", key, compute)
        progress("G/I/L posterior sigma", 1, 1)
    return Posterior(gil, features, objects, key)


def stage_calibration_check(steps: StepRunner, inputs: WorkflowInputs, outer: OuterIterations, posterior: Posterior,
                            progress: Progress = no_progress) -> CalibrationCheck | None:
    """The scanner calibration the configuration leaves out, estimated once more from the last outer iteration's
    problem, started at its solution (cached; :mod:`georefine.workflows.calibration_check`), or None where the
    check is switched off."""
    last = outer.records[-1]

    def compute() -> CalibrationCheck | None:
        progress("scanner calibration check", 0, 1)
        out = check_scanner_calibration(inputs.nav, posterior.gil.result, posterior.features, posterior.objects,
                                        TimeOffsetStart(last.time_offset_start_s, last.time_offset_prior_s), progress)
        progress("scanner calibration check", 1, 1)
        return out

    if not inputs.nav.config.processing.lidar.check_scanner_calibration:
        return None
    return steps.cached("calibration_check", StepCache.key("calibration_check", "encoder-boresight", outer.key), compute,
                        timing="calibration_check")


def lidar_stages(steps: StepRunner, inputs: WorkflowInputs, gi: GnssImuResult, key: str,
                 progress: Progress) -> tuple[LidarAdjustment, str, tuple[OuterIteration, ...]]:
    """Steps 3-5 and the G/I/L products: the adjustment with its posterior, its key, the outer iterations.

    Its own function so that what only steps 3-5 need -- the last problem (with its
    factorisation), the features and objects -- is freed before step 6 starts: held through the
    final georeferencing it raised the peak of a 400 kHz run from 4.46 to 5.37 GB.
    """
    outer = stage_outer_iterations(steps, inputs, gi, key, progress)
    posterior = stage_posterior(steps, inputs, outer, progress)
    if posterior.gil.time_offset_sigma_s is not None:
        posterior = replace(posterior, gil=replace(posterior.gil, time_offset_gnss_sigma_s=gnss_offset_sigma(inputs.nav, gi)))
    warn_time_offset(inputs.nav.config, posterior.gil.time_offset_s, posterior.gil.time_offset_sigma_s,
                     posterior.gil.time_offset_gnss_sigma_s or 0.0)
    warn_plane_misfit(gi, posterior.gil, outer.records, inputs.nav)
    warn_gi_tilt(gi, posterior.gil, inputs.nav.frame)
    warn_boresight_separation(gi, posterior.gil)
    warn_gnss_error_misfit(posterior.gil)
    warn_calibration(stage_calibration_check(steps, inputs, outer, posterior, progress))
    stage_gil_products(inputs, posterior)
    return posterior.gil, posterior.key, outer.records


def stage_gi_products(inputs: WorkflowInputs, gi: GnssImuResult) -> None:
    """``gi/``: trajectory products and ``adjustment.json`` of the G/I adjustment."""
    (inputs.out / "gi").mkdir(exist_ok=True)
    write_trajectory_products(inputs.out / "gi", inputs.nav, gi, inputs.crs)
    write_adjustment_report(inputs.out / "gi" / "adjustment.json", adjustment_report(inputs.nav, gi, "G/I"))


def stage_gil_products(inputs: WorkflowInputs, posterior: Posterior) -> None:
    """``features/`` (the matched features and objects) and ``gil/`` (trajectory products, ``adjustment.json``)."""
    for sub in ("features", "gil"):
        (inputs.out / sub).mkdir(exist_ok=True)
    _write_matched_features(inputs.out / "features", posterior.features, posterior.objects)
    write_trajectory_products(inputs.out / "gil", inputs.nav, posterior.gil.result, inputs.crs)
    write_adjustment_report(inputs.out / "gil" / "adjustment.json",
                            adjustment_report(inputs.nav, posterior.gil.result, "G/I/L", posterior.gil))


def stage_points(steps: StepRunner, inputs: WorkflowInputs, final: GnssImuResult, gil: LidarAdjustment | None,
                 key: str, progress: Progress = no_progress) -> tuple[PointsWritten, ...]:
    """Step 6: the strips in the output CRS into ``points/`` (cached: skipped while the files are those it wrote)."""
    nav, folder = inputs.nav, inputs.out / "points"
    folder.mkdir(parents=True, exist_ok=True)
    p_b_s = np.asarray(nav.config.scanner.lever_arm_m, dtype=float)
    R_b_s = boresight_matrix(nav.config.scanner.boresight_deg)
    if gil is not None and gil.boresight_deg is not None:
        R_b_s = boresight_matrix(tuple(gil.boresight_deg))

    def written(records: list[dict]) -> bool:  # the LAZ files are still those this step wrote
        return all(
            (folder / r["file"]).is_file() and file_stamp(folder / r["file"])[1:] == r["stamp"] for r in records
        )

    offset = nav.config.scanner.time_offset_s if gil is None else gil.time_offset_s
    strips = [s.shifted(offset) for s in inputs.strips]

    def compute() -> list[dict]:  # stored with each file's stamp, for ``written``
        runner = inputs.runner
        interpolator = PoseInterpolator(imu_rate_trajectory(nav, final))
        refuse_strips_outside([s.plan for s in strips], interpolator.span, nav.t0_gps, offset)
        poses = runner.share(interpolator)
        paths = [folder / (s.path.stem + ".laz") for s in strips]
        results = georeference_strips([s.plan for s in strips], paths, poses, nav.t0_gps, p_b_s, R_b_s,
                                      nav.frame, inputs.crs, runner=runner, progress=progress, protect=(nav.root,),
                                      time_offset_s=offset, heights=inputs.heights,
                                      calibration=None if gil is None else gil.scanner_calibration())
        return [{"strip": s.strip_id, "file": path.name, "points": r.points_written,
                 "outside_trajectory": r.points_outside, "stamp": file_stamp(path)[1:]}
                for s, path, r in zip(inputs.strips, paths, results)]

    records = steps.cached("points", _points_key(nav, inputs.strips, key), compute, valid=written)
    return tuple(PointsWritten.from_dict(r) for r in records)


def stage_metrics(steps: StepRunner, inputs: WorkflowInputs, outer: tuple[OuterIteration, ...],
                  points: tuple[PointsWritten, ...], gi: GnssImuResult, gil: LidarAdjustment | None) -> WorkflowMetrics:
    """``metrics.json`` and ``config.resolved.yaml``: what was run, resumed and how long it took,
    and with a G/I/L ``gil`` the attitude sigma per pass of it and ``gi`` (:mod:`georefine.workflows.precision`)."""
    nav = inputs.nav
    passes = () if gil is None else pass_precision(
        gi, gil.result, {s.strip_id: (float(s.t_first), float(s.t_last)) for s in inputs.strips})
    metrics = WorkflowMetrics(
        t0_gps=nav.t0_gps, strips=tuple(s.strip_id for s in inputs.strips),
        strip_time_gps={s.strip_id: (float(s.t_first + nav.t0_gps), float(s.t_last + nav.t0_gps))
                        for s in inputs.strips},
        outer_iterations=outer, points=points, resumed=steps.resumed, timings_s=dict(steps.timings_s),
        pass_precision=passes,
    )
    write_json(inputs.out / "metrics.json", metrics.to_dict())
    write_yaml(inputs.out / "config.resolved.yaml", nav.config)
    return metrics


def precompute_gnss_imu(project: ProjectLike, cache_dir: str | Path) -> dict[str, float]:
    """Steps 1-2 of ``project`` into the step cache ``cache_dir``; their timings.

    They need the GNSS and IMU files only, so they can run while the scans are still being
    written (``georefine demo`` runs them in a second process during the simulation); a
    :func:`run_workflow` with the same ``cache_dir`` then resumes them. Nothing is read or
    computed when the cache already holds them.
    """
    project, steps = as_project(project), StepRunner(StepCache(Path(cache_dir)))
    if not steps.cache.exists("gi", navigation_key(project.config, project.root)):
        stage_gnss_imu(steps, project.navigation)
    return steps.timings_s


def _write_matched_features(folder: Path, features: PlanarFeatures, objects: PlanarObjects) -> None:
    """``features.csv`` and ``objects.csv`` of the matched features (members of objects), which
    :func:`features_and_objects` returns.

    Only the features the adjustment can observe are written (about 4 % of the extracted features on ``corridor``:
    all 1.75 M of them made a 0.5 GB table that took 17 s to write); the objects' member
    indices refer to rows of this ``features.csv``. The extracted count per view is in
    ``metrics.json``.
    """
    write_features(folder / "features.csv", features)
    write_objects(folder / "objects.csv", objects)


def run_workflow(
    project: ProjectLike,
    out: str | Path,
    *,
    strips: list[int] | None = None,
    lidar: bool = True,
    resume: bool = True,
    points: bool = True,
    cache_dir: str | Path | None = None,
    progress: Progress = no_progress,
    scheduler: str | TaskRunner = DEFAULT_SCHEDULER,
) -> WorkflowResult | FlightsResult:
    """Steps 1-6 on a project (an opened :class:`~georefine.workflows.opened.Project` or its
    folder; see the module docstring for the outputs). A project of several flights adjusts them
    together (:func:`~georefine.workflows.flights.run_flights`, a :class:`~georefine.workflows.flights.FlightsResult`).

    Every step's result is cached in ``out/.cache`` (:mod:`georefine.workflows.cache`); with
    ``resume`` a rerun loads what its inputs and configuration have not changed, e.g. after an
    interruption or when only the final georeferencing is repeated. ``metrics.json`` lists the
    resumed steps under ``resumed``. ``points=False`` skips the final point clouds (step 6), e.g.
    when only the trajectory is wanted. ``cache_dir`` puts the cache elsewhere, e.g. one folder shared
    by a full and a single-pass run (they share the GNSS/IMU adjustment). ``scheduler`` runs
    the per-tile work (:mod:`georefine.tasks`: a name, an address or a running
    :class:`~georefine.tasks.TaskRunner`); the results do not depend on it.

    Raises
    ------
    InputError
        Bad navigation data or strips (``strips``: an id no strip has), or no planar features.
    """
    # The cache touches no file before the first step stores; the output folder is made on reading.
    project = as_project(project)
    if project.multi_flight:  # every flight's trajectory in one G/I/L (docs/ARCHITECTURE.md §4.5)
        if strips is not None or not lidar:
            raise ConfigError("a project of several flights is run whole", field="--strips" if strips else "--no-lidar",
                              expected="all strips of all flights with the LiDAR (run one flight as a project of its "
                              "own for less)", found=f"{len(project.flights)} flights")
        return run_flights(project, out, resume=resume, points=points, cache_dir=cache_dir, progress=progress,
                           scheduler=scheduler)
    with open_workspace(project, out, resume=resume, cache_dir=cache_dir, scheduler=scheduler) as ws:
        return _run_stages(ws, project, strips, lidar, points, progress)


def _run_stages(ws: Workspace, project: Project, strips, lidar: bool, points: bool,
                progress: Progress) -> WorkflowResult:
    """The stages of :func:`run_workflow` in the workspace ``ws`` (output folder, cache, runner)."""
    steps = ws.steps
    progress("reading the input", 0, 1)
    inputs = stage_read_inputs(steps, project, ws.out, strips, ws.runner)
    progress("reading the input", 1, 1)
    gi, key = stage_gnss_imu(steps, inputs.nav, progress)
    stage_gi_products(inputs, gi)
    final, gil, records = gi, None, ()
    if lidar:
        gil, key, records = lidar_stages(steps, inputs, gi, key, progress)
        final = gil.result
    with steps.timed("final_georeferencing"):
        written = stage_points(steps, inputs, final, gil, key, progress) if points else ()
    metrics = stage_metrics(steps, inputs, records, written, gi, gil)
    return WorkflowResult(inputs.out, gi, gil, metrics)
