"""The georeferencing workflow of paper 000 (Fig. 1), one function per step (docs/ARCHITECTURE.md §4.5).

Implemented so far: loading and validating the navigation data, step 1 (initialisation
filter and spline fit) and step 2 (GNSS/IMU adjustment), with their products:
``trajectory.sbet`` (IMU rate, seconds of the GPS week; the week in ``trajectory.sbet.json``,
the posterior sigma in ``smrmsg_trajectory.out``), ``trajectory.csv`` (output CRS,
roll/pitch/heading and posterior sigma) and ``adjustment.json`` (:class:`~georefine.io.run_metrics.AdjustmentReport`:
per-group statistics, iterations, cost, estimated IMU errors, the filter, timings). Each step is a plain function
returning a frozen result.
"""

from __future__ import annotations

import logging
import time as _time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from georefine.adjustment.gnss_imu import (
    GnssImuResult,
    build_gnss_imu_problem,
    solve_gnss_imu,
    start_imu_errors,
    with_posterior,
)
from georefine.adjustment.upsampling import adjust_upsampled
from georefine.config import write_yaml
from georefine.errors import ConfigError, InputError
from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.io.files import make_output_folder
from georefine.io.run_metrics import AdjustmentReport, FilterSummary, FrameOrigin, write_adjustment_report
from georefine.progress import Progress, no_progress
from georefine.tasks import DEFAULT_SCHEDULER, TaskRunner, runner_for
from georefine.trajectory.ekf import FilterResult, run_filter
from georefine.trajectory.sampled import Trajectory, interp_columns
from georefine.trajectory.spline import KnotGrid
from georefine.trajectory.spline_fit import fit_spline
from georefine.workflows.opened import NavigationData, ProjectLike, as_project, output_folder
from georefine.workflows.products import (
    accuracy_from_sigmas,
    body_kinematics,
    write_csv_product,
    write_sbet_product,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrajectoryRunResult:
    """What :func:`run_trajectory` computed and wrote."""

    out: Path
    filter: FilterResult
    adjustment: GnssImuResult | None
    timings_s: dict = field(default_factory=dict)

    def summary(self) -> str:
        lines = [f"Trajectory written to {self.out}"]
        f = self.filter
        lines.append(f"  filter: {f.n_gnss_updates} GNSS updates, {f.n_gnss_rejected} rejected")
        if self.adjustment is not None:
            s = self.adjustment.solve
            lines.append(
                f"  G/I adjustment: {s.iterations} iterations ({s.termination}), sigma0 {s.sigma0:.3f}, "
                f"{s.n_unknowns:,} unknowns"
            )
            for g in s.groups:
                lines.append(f"    {g.name:<24} n={g.n_observations:>8,}  RMS {g.rms:.3f}")
        lines.append("  timings: " + ", ".join(f"{k} {v:.1f} s" for k, v in self.timings_s.items()))
        return "\n".join(lines)


def step_initialise(nav: NavigationData) -> FilterResult:
    """Step 1: error-state EKF with in-motion alignment and RTS smoother."""
    d = nav.gnss
    return run_filter(
        nav.frame, nav.t0_gps, nav.imu, d.gnss_time, d.gnss_p_w, d.gnss_cov_w, d.p_b_a,
        nav.config.imu.errors, nav.config.processing.filter,
    )


def knot_grid(t_first: float, t_last: float, knot_interval_s: float) -> KnotGrid:
    """The knots of step 2: from ``t_first`` every ``knot_interval_s``, the last at or before ``t_last``."""
    return KnotGrid(t_first, knot_interval_s, int(np.floor((t_last - t_first) / knot_interval_s + 1e-9)) + 1)


FIT_EPOCHS_PER_INTERVAL = 4
"""Filter epochs per knot interval the spline that starts the G/I adjustment is fitted to (at least)."""


def step_adjust_gnss_imu(nav: NavigationData, filt: FilterResult, progress: Progress = no_progress) -> GnssImuResult:
    """Step 2: fit the spline to the smoothed filter and adjust GNSS + IMU (on the knots and IMU
    windows of ``processing.trajectory.gnss_imu_knot_interval_s`` and ``gnss_imu_window_s``)."""
    tcfg = nav.config.processing.trajectory.gnss_imu()
    t_start = _time.perf_counter()
    t_first = max(float(filt.time[0]), float(nav.gnss.gnss_time[0]))
    t_last = min(float(filt.time[-1]), float(nav.gnss.gnss_time[-1]))
    grid = knot_grid(t_first, t_last, tcfg.knot_interval_s)
    sel = np.flatnonzero((filt.time >= grid.t_start) & (filt.time <= grid.t_end))
    # The fit only starts the adjustment: FIT_EPOCHS_PER_INTERVAL of the filter's epochs per knot
    # interval, evenly spread, start it as well as all of them (at 200 Hz and 0.4 s knots every
    # 20th epoch; the fit took 0.72 s of a 2.7 s G/I adjustment of the corridor with all 124,000,
    # 0.06 s with these, and the adjustment ends at the same solution after as many steps).
    stride = max(1, int(sel.size / max(1, grid.n_intervals) / FIT_EPOCHS_PER_INTERVAL))
    sel = np.unique(np.concatenate([sel[::stride], sel[-1:]]))
    s_g = getattr(filt, "scale_gyro", np.zeros(3))
    imu_sel = np.isin(nav.gnss.imu_time, filt.time[sel])
    gyro = nav.gnss.imu_gyro[imu_sel]
    R = filt.R_w_b[sel]
    omega_wb = (gyro - filt.bias_gyro[sel]) / (1.0 + s_g) - np.swapaxes(R, 1, 2) @ nav.frame.omega_ie_w
    spline0 = fit_spline(
        grid, filt.time[sel], filt.p_w_b[sel], R, filt.v_w_b[sel], omega_wb if omega_wb.shape[0] == R.shape[0] else None,
        t0_gps=nav.t0_gps,
    )
    t_fit = _time.perf_counter()
    built = build_gnss_imu_problem(nav.gnss, nav.config.imu.errors, tcfg, spline0)
    # Start the IMU errors from the filter's estimates.
    tb = built.bias_grid.times
    for name, series in (("acc_bias", filt.bias_acc), ("gyro_bias", filt.bias_gyro)):
        built.problem.set_values(name, interp_columns(tb, filt.time, series))
    if tcfg.estimate_scale_factors:
        built.problem.set_values("acc_scale", np.asarray(filt.scale_acc, dtype=float).reshape(1, 3))
        built.problem.set_values("gyro_scale", np.asarray(filt.scale_gyro, dtype=float).reshape(1, 3))

    start = {"start": t_fit - t_start, "build": _time.perf_counter() - t_fit}  # the fit, the problem

    def report(it) -> None:
        progress("G/I adjustment", min(getattr(it, "iteration", 0), tcfg.max_iterations), tcfg.max_iterations)

    if not tcfg.upsampling:
        result = solve_gnss_imu(built, progress=report)
        _warn_on_imu_misfit(result)
        return replace(result, timings_s={**start, **result.timings_s})
    last = {}

    # Where the up-sampling finds motion faster than the knots standing out of the IMU noise
    # (vibration, or a navigation-grade unit's smooth motion between coarse knots), the G/I starts
    # again on the G/I/L's knots and windows and re-solves there. On 0.4 s knots the cleaning takes
    # the motion above the knots' cubic B-splines (1.25 Hz), a band the adjustment's quintic and
    # cubic Hermite splines follow too, so the redundancy it spends is counted twice: a vibrating
    # navigation-grade corridor's G/I had a variance factor of 9.3 with every group at 1.0-1.05,
    # against 1.8 on 0.1 s knots.
    fine = nav.config.processing.trajectory

    def on_fine_knots(spline):
        if abs(spline.grid.dt - fine.knot_interval_s) <= 1e-6 * fine.knot_interval_s:
            return spline
        return spline.resampled(KnotGrid.spanning(spline.grid.t_start, spline.grid.t_end, fine.knot_interval_s))

    def rebuild(data, previous):
        last["built"] = start_imu_errors(build_gnss_imu_problem(data, nav.config.imu.errors, fine,
                                                                on_fine_knots(previous.spline)),
                                         previous.imu_errors, previous.gnss_error)
        return last["built"]

    def restart(coarse):
        log.info("G/I: motion faster than the %.3g s knots stands out of the IMU noise; adjusting again on "
                 "%.3g s knots", tcfg.knot_interval_s, fine.knot_interval_s)
        return solve(rebuild(nav.gnss, coarse))

    def solve(b):
        return solve_gnss_imu(b, progress=report, covariance=False)

    first = solve(built)
    last["built"] = built
    result = adjust_upsampled(nav.gnss, first, rebuild, solve, tcfg.upsampling_iterations,
                              restart=restart if fine.knot_interval_s < tcfg.knot_interval_s - 1e-9 else None)
    result = with_posterior(last["built"], result)
    return replace(result, timings_s={**start, **result.timings_s})


IMU_MISFIT_FACTOR = 10.0
"""IMU windows whose variance factor exceeds this do not fit the spline (see :func:`_warn_on_imu_misfit`)."""


def _warn_on_imu_misfit(result: GnssImuResult) -> None:
    """Warn when the raw IMU windows fit the spline far worse than their noise model allows.

    The usual cause is motion faster than the knots (vibration): the windows then carry it as
    noise and the posterior sigma, scaled by the variance factor, grow with it.
    """
    imu = next((g for g in result.solve.groups if g.name == "imu"), None)
    if imu is not None and imu.variance_factor > IMU_MISFIT_FACTOR:
        log.warning(
            "the IMU windows fit the trajectory %.0f times worse than the IMU noise model (RMS %.1f sigma): "
            "motion faster than the %.3g s knots? processing.trajectory.upsampling rebuilds it from the raw IMU",
            imu.variance_factor, imu.rms, result.spline.grid.dt,
        )


def _filter_sigma_rph(nav: NavigationData, filt: FilterResult) -> np.ndarray:
    """Filter attitude sigma (body-frame tangent) mapped to roll/pitch/heading sigma."""
    from georefine.adjustment.gnss_imu import euler_rate_inverse

    rph = nav.frame.rph_from_R_w_b(filt.p_w_b, filt.R_w_b)
    Einv = euler_rate_inverse(rph)
    cov = np.zeros((rph.shape[0], 3, 3))
    cov[:, np.arange(3), np.arange(3)] = filt.sigma[:, 6:9] ** 2
    return np.sqrt(np.diagonal(Einv @ cov @ np.swapaxes(Einv, 1, 2), axis1=1, axis2=2))


def write_trajectory_products(out: Path, nav: NavigationData, adj: GnssImuResult, crs: OutputCRS) -> None:
    """``trajectory.sbet`` at the IMU samples inside the spline (with its companion ``trajectory.sbet.json``
    and, at the posterior's times, the accuracy file ``smrmsg_trajectory.out``), ``trajectory.csv`` at the knots."""
    spline = adj.spline
    t_imu = nav.sample_time
    t_imu = t_imu[(t_imu >= spline.grid.t_start) & (t_imu <= spline.grid.t_end)]
    p, v, R, f, w = body_kinematics(nav.frame, spline, t_imu)
    if adj.high_rate is not None:  # up-sampled: the spline plus the rebuilt high-frequency motion (§4.6)
        traj = adj.high_rate.trajectory(spline)
        d_omega, d_f = adj.high_rate.reading_corrections(nav.frame, spline)
        p, v, R, f, w = traj.p_w_b, traj.v_w_b, traj.R_w_b, f + d_f, w + d_omega
    accuracy = None
    if adj.sigma_velocity_m_s is not None:
        p_s = spline.position(adj.sigma_time, 0)
        accuracy = accuracy_from_sigmas(nav.frame, nav.t0_gps, adj.sigma_time, p_s, adj.sigma_position_m,
                                        adj.sigma_velocity_m_s, adj.sigma_rph_rad)
    else:  # a result cached before the velocity sigma was computed
        log.warning("no posterior velocity sigma in this result (cached by an older version): no accuracy file "
                    "beside %s; --fresh recomputes it", out / "trajectory.sbet")
    write_sbet_product(out / "trajectory.sbet", nav.frame, nav.t0_gps, t_imu, p, v, R, f, w,
                       output_epsg=crs.epsg, accuracy=accuracy)
    tk = spline.grid.knot_times
    pk, Rk = spline.pose(tk)
    sig_rph = interp_columns(tk, adj.sigma_time, adj.sigma_rph_rad)
    sig_p = interp_columns(tk, adj.sigma_time, adj.sigma_position_m)
    write_csv_product(out / "trajectory.csv", nav.frame, crs, nav.t0_gps, tk, pk, Rk, sig_rph, sig_p)


def imu_rate_trajectory(nav: NavigationData, adj: GnssImuResult) -> Trajectory:
    """The adjusted trajectory at the IMU samples inside its span (for georeferencing).

    The spline plus the rebuilt high-frequency motion when the adjustment up-sampled
    (``adj.high_rate``, docs/ARCHITECTURE.md §4.6), else the spline alone.
    """
    if adj.high_rate is not None:
        return adj.high_rate.trajectory(adj.spline)
    spline = adj.spline
    t_imu = nav.sample_time
    t_imu = t_imu[(t_imu >= spline.grid.t_start) & (t_imu <= spline.grid.t_end)]
    return spline.to_sampled(t_imu)


def run_trajectory(
    project: ProjectLike,
    out: str | Path,
    *,
    filter_only: bool = False,
    progress: Progress = no_progress,
) -> TrajectoryRunResult:
    """Steps 1-2 on a project folder; write the trajectory products into ``out``."""
    timings: dict[str, float] = {}
    t = _time.perf_counter()
    progress("reading the input", 0, 1)
    nav = as_project(project).navigation
    progress("reading the input", 1, 1)
    timings["read"] = _time.perf_counter() - t
    if nav.prior is not None:
        raise InputError("steps 1-2 need raw GNSS and IMU; this project has a delivered trajectory "
                         "(section trajectory), which `georefine run` adjusts with the LiDAR",
                         path=nav.root / "project.yaml", field="gnss, imu")
    out = make_output_folder(output_folder(out, nav.root))
    crs = OutputCRS(nav.config.crs.output_epsg)

    progress("initialisation filter", 0, 1)
    t = _time.perf_counter()
    filt = step_initialise(nav)
    timings["filter"] = _time.perf_counter() - t
    progress("initialisation filter", 1, 1)

    adj = None
    if filter_only:
        # Body specific force and angular rate: the IMU readings corrected with the filter's
        # biases and scale factors (f~ = (I + S) f + b), where the filter's epochs are samples.
        at = np.isin(nav.gnss.imu_time, filt.time)
        f_b = w_b = None
        if np.count_nonzero(at) == filt.time.size:
            f_b = (nav.imu.acc[at] - filt.bias_acc) / (1.0 + filt.scale_acc)
            w_b = (nav.imu.gyro[at] - filt.bias_gyro) / (1.0 + filt.scale_gyro)
        dec = slice(None, None, max(1, int(round(nav.imu.rate_hz / 10))))
        sig_rph = _filter_sigma_rph(nav, filt)[dec]
        accuracy = accuracy_from_sigmas(nav.frame, nav.t0_gps, filt.time[dec], filt.p_w_b[dec], filt.sigma[dec, 0:3],
                                        filt.sigma[dec, 3:6], sig_rph)
        write_sbet_product(out / "trajectory.sbet", nav.frame, nav.t0_gps, filt.time, filt.p_w_b, filt.v_w_b, filt.R_w_b,
                           f_b, w_b, output_epsg=crs.epsg, accuracy=accuracy)
        write_csv_product(out / "trajectory.csv", nav.frame, crs, nav.t0_gps, filt.time[dec], filt.p_w_b[dec],
                          filt.R_w_b[dec], sig_rph, filt.sigma[dec, 0:3])
    else:
        t = _time.perf_counter()
        adj = step_adjust_gnss_imu(nav, filt, progress)
        progress("G/I adjustment", 1, 1)  # it reports iterations of its limit; it ended here
        timings["adjustment"] = _time.perf_counter() - t
        t = _time.perf_counter()
        write_trajectory_products(out, nav, adj, crs)
        timings["products"] = _time.perf_counter() - t

    alignment = getattr(filt, "alignment_time", None)
    report = AdjustmentReport(
        "filter", nav.t0_gps, dict(timings), project=str(Path(nav.root).resolve()), frame=FrameOrigin.of(nav.frame),
        filter=FilterSummary(int(filt.n_gnss_updates), int(filt.n_gnss_rejected),
                             None if alignment is None else float(alignment)))
    if adj is not None:
        report = replace(
            report, solution="G/I", adjustment=adj.solve.to_dict(), imu_errors=adj.imu_errors.to_dict(),
            gnss_error=None if adj.gnss_error is None else adj.gnss_error.to_dict(),
            timings_s=dict(timings, **{f"adjustment_{k}": v for k, v in adj.timings_s.items()}))
    write_adjustment_report(out / "adjustment.json", report)
    write_yaml(out / "config.resolved.yaml", nav.config)
    return TrajectoryRunResult(out, filt, adj, timings)


@dataclass(frozen=True)
class GeoreferenceRunResult:
    """Strips georeferenced by :func:`run_georeference`."""

    out: Path
    strips: tuple

    def summary(self) -> str:
        lines = [f"Point clouds written to {self.out}"]
        for s in self.strips:
            extra = f", {s.points_outside:,} outside the trajectory (left out)" if s.points_outside else ""
            lines.append(f"  {s.output.name}: {s.points_written:,} points{extra}")
        return "\n".join(lines)


def run_georeference(
    project: ProjectLike,
    trajectory_path: str | Path,
    out: str | Path,
    *,
    gps_week: int | None = None,
    progress: Progress = no_progress,
    scheduler: str | TaskRunner = DEFAULT_SCHEDULER,
) -> GeoreferenceRunResult:
    """Georeference every strip of a project with a trajectory SBET into ``out/*.laz``.

    The strips are cut into time tiles (:mod:`georefine.lidar.tiles`) that run on ``scheduler``
    (:mod:`georefine.tasks`); memory holds a few tiles whatever the number of points. The points
    are georeferenced at, and written with, ``gps_time + scanner.time_offset_s``. Heights
    are ellipsoidal, or gravity-related with ``crs.geoid_grid`` (:class:`~georefine.geometry.frames.GeoidHeights`).
    """
    from georefine.config import boresight_matrix
    from georefine.io.las import gps_week_of_strip, time_index
    from georefine.io.trajectory import read_sbet, read_sbet_companion
    from georefine.lidar.georeference import PoseInterpolator
    from georefine.lidar.tiles import georeference_strips, plan_strip, refuse_strips_outside, tile_points
    from georefine.trajectory.sampled import trajectory_from_sbet

    project = as_project(project)
    if project.multi_flight:  # one trajectory georeferences one flight's strips
        raise ConfigError("georeferencing with one trajectory takes a project of one flight", field="flights",
                          expected="a project of one flight (a flight's strips with its own trajectory); `georefine "
                          "run` writes every strip of several flights", found=f"{len(project.flights)} flights")
    root, cfg = project.root, project.config
    out = project.output_folder(out)
    if gps_week is None and read_sbet_companion(trajectory_path) is None:  # else the SBET's companion states it
        gps_week = gps_week_of_strip(root / cfg.scanner.files[0])
    sbet = read_sbet(trajectory_path, gps_week=gps_week)
    frame = LocalFrame(float(sbet.lat_rad[0]), float(sbet.lon_rad[0]), float(sbet.h_m[0]))
    t0 = float(np.floor(sbet.time_gps[0]))
    traj = trajectory_from_sbet(sbet, frame, t0)
    crs = project.crs
    with runner_for(scheduler) as runner:
        size = tile_points(cfg.processing.scale, runner.workers)
        offset = cfg.scanner.time_offset_s
        plans = [plan_strip(root / rel, 0, t0 - offset, size, 0.0, index=time_index(root / rel))
                 for rel in cfg.scanner.files]
        refuse_strips_outside(plans, (float(traj.time[0]), float(traj.time[-1])), t0, offset)
        make_output_folder(out)
        poses = runner.share(PoseInterpolator(traj))
        results = georeference_strips(
            plans, [out / (Path(rel).stem + ".laz") for rel in cfg.scanner.files], poses, t0,
            np.asarray(cfg.scanner.lever_arm_m), boresight_matrix(cfg.scanner.boresight_deg), frame, crs,
            runner=runner, progress=progress, protect=(root,), time_offset_s=offset, heights=project.heights,
        )
    return GeoreferenceRunResult(out, tuple(results))
