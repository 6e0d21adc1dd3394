"""The adjustment on a delivered trajectory: an SBET as the prior, no raw GNSS or IMU (docs/ARCHITECTURE.md §4.9).

A LiDAR vendor delivers georeferenced strips and the trajectory its GNSS/IMU post-processor
computed (an SBET at the IMU rate and its ``smrmsg`` sigmas). This module puts that trajectory
into the same continuous-time adjustment the raw data use, so that the LiDAR planes of
:mod:`georefine.workflows.lidar` can correct it:

1. :func:`reference_from_sbet`: the spline fitted to the SBET (the *reference*, knots
   ``processing.trajectory.knot_interval_s`` apart) and the SBET's motion faster than the knots
   as a :class:`~georefine.trajectory.highrate.HighRateMotion` (the SBET minus the reference).
   Georeferencing adds that motion to the adjusted spline as it adds the motion rebuilt from a
   raw IMU; it is the delivered trajectory's own and stays fixed.
2. :func:`build_trajectory_prior_problem`: the spline knots, the SBET's error process on its own
   knots (``trajectory.error_knot_interval_s``), reference poses observing spline plus error
   (:class:`~georefine.adjustment.observations.trajectory_prior.TrajectoryPoseObservation`,
   ``SAMPLES_PER_KNOT`` per knot interval) and a Gauss-Markov prior on the error with the
   ``smrmsg`` sigma (:class:`~georefine.adjustment.observations.trajectory_prior.GaussMarkovPrior`).
   The plane observations are added by the workflow as to the G/I problem.
3. :func:`solve_trajectory_prior`: solve, read out the spline and the error estimate, and the
   posterior sigma (:func:`~georefine.adjustment.gnss_imu.trajectory_sigma`), scaled by the
   variance factor only where it exceeds 1 (:func:`with_prior_posterior`).

The error is a rotation about the axes of ``w`` (east, north, up) and an offset in ``w``; the
``smrmsg`` sigmas (north, east, down; roll, pitch, heading) map to them as: east/north/up
position sigma from east/north/down; rotation sigma about east and north both
``sqrt((roll^2 + pitch^2) / 2)`` (roll and pitch swap between the two axes with the heading),
about up the heading sigma.
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass, replace

import numpy as np

from georefine.adjustment.gnss_imu import (
    GnssImuResult,
    add_spline_blocks,
    block_sigma,
    posterior_components,
    posterior_scale,
    spline_from_problem,
    trajectory_sigma,
    trajectory_solver_options,
)
from georefine.adjustment.observations.bias import BiasGrid
from georefine.adjustment.observations.trajectory_blocks import TrajectoryBlocks
from georefine.adjustment.observations.trajectory_prior import GaussMarkovPrior, TrajectoryPoseObservation
from georefine.adjustment.problem import Problem
from georefine.adjustment.solver import SolverOptions
from georefine.config import TrajectoryAdjustmentConfig, TrajectoryPriorConfig
from georefine.errors import InputError
from georefine.geometry.frames import LocalFrame
from georefine.geometry.rotation import log_so3
from georefine.trajectory.highrate import HighRateMotion
from georefine.trajectory.sampled import interp_columns
from georefine.trajectory.spline import KnotGrid, SplineTrajectory
from georefine.trajectory.spline_fit import fit_spline

__all__ = [
    "SAMPLES_PER_KNOT", "SbetErrorEstimate", "TrajectoryPriorData", "TrajectoryPriorProblem",
    "build_trajectory_prior_problem", "reference_from_sbet", "solve_trajectory_prior", "with_prior_posterior",
]

SAMPLES_PER_KNOT = 4
"""Reference poses per knot interval: enough to fix the quintic position and cubic orientation
states of each interval (3 and 2 per knot)."""
POSITION_ERROR = "sbet_position_error"
ATTITUDE_ERROR = "sbet_attitude_error"


@dataclass(frozen=True)
class TrajectoryPriorData:
    """A delivered trajectory in the mapping frame, with its sigmas.

    Attributes
    ----------
    frame, t0_gps
        Mapping frame and dataset epoch (times are relative to it).
    time : (N,) s; p_w_b (N, 3) m; R_w_b (N, 3, 3); v_w_b (N, 3) m/s
    omega_wb_b : (N, 3) rad/s or None
        Body rate against ``w`` (from the SBET's angular rates less the Earth rate), if given.
    sigma_p_w : (N, 3) m
        Position sigma along east, north, up.
    sigma_theta_w : (N, 3) rad
        Attitude sigma as rotations about east, north, up (module docstring).
    rate_hz : float
        Nominal sample rate.
    """

    frame: LocalFrame
    t0_gps: float
    time: np.ndarray
    p_w_b: np.ndarray
    R_w_b: np.ndarray
    v_w_b: np.ndarray
    omega_wb_b: np.ndarray | None
    sigma_p_w: np.ndarray
    sigma_theta_w: np.ndarray
    rate_hz: float


@dataclass(frozen=True)
class SbetErrorEstimate:
    """The delivered trajectory's estimated error on its knots (``w`` axes), with 1-sigma."""

    grid: BiasGrid
    position_m: np.ndarray
    attitude_rad: np.ndarray
    position_sigma_m: np.ndarray | None = None
    attitude_sigma_rad: np.ndarray | None = None

    def to_dict(self) -> dict:
        def arr(x, f=1.0):
            return None if x is None else (np.asarray(x) * f).round(9).tolist()

        return {
            "knot_times_s": self.grid.times.tolist(),
            "axes": "east, north, up of w (attitude: rotations about them)",
            "position_m": arr(self.position_m),
            "attitude_mdeg": arr(self.attitude_rad, np.degrees(1.0) * 1e3),
            "position_sigma_m": arr(self.position_sigma_m),
            "attitude_sigma_mdeg": arr(self.attitude_sigma_rad, np.degrees(1.0) * 1e3),
        }


def reference_from_sbet(data: TrajectoryPriorData, grid: KnotGrid) -> tuple[SplineTrajectory, HighRateMotion]:
    """The spline fitted to the delivered trajectory on ``grid`` and the motion it leaves out.

    The motion is the sampled trajectory minus the spline at the samples inside ``grid``:
    ``R = R_s Exp(dtheta)``, ``p = p_s + dp``; its rates are central differences of the samples.
    """
    inside = (data.time >= grid.t_start) & (data.time <= grid.t_end)
    t = data.time[inside]
    if t.size < 4:
        raise InputError("the delivered trajectory has fewer than 4 samples inside the strips' span",
                         field="trajectory.sbet")
    omega = None if data.omega_wb_b is None else data.omega_wb_b[inside]
    spline = fit_spline(grid, t, data.p_w_b[inside], data.R_w_b[inside], data.v_w_b[inside], omega,
                        t0_gps=data.t0_gps)
    p_s, R_s = spline.pose(t)
    v_s = spline.velocity(t)
    dp = data.p_w_b[inside] - p_s
    dtheta = log_so3(np.swapaxes(R_s, 1, 2) @ data.R_w_b[inside])
    dv = data.v_w_b[inside] - v_s
    da = np.gradient(dv, t, axis=0)
    return spline, HighRateMotion(t, dtheta, np.gradient(dtheta, t, axis=0), dp, dv, da, grid.dt)


@dataclass
class TrajectoryPriorProblem:
    """A built delivered-trajectory problem and what is needed to read its solution."""

    problem: Problem
    grid: KnotGrid
    error_grid: BiasGrid
    blocks: TrajectoryBlocks
    data: TrajectoryPriorData
    cfg: TrajectoryAdjustmentConfig
    prior: TrajectoryPriorConfig
    reference: SplineTrajectory

    def spline(self) -> SplineTrajectory:
        return spline_from_problem(self.problem, self.blocks, self.grid, self.data.t0_gps)


def _sigma_at(data: TrajectoryPriorData, t: np.ndarray, which: np.ndarray) -> np.ndarray:
    return interp_columns(t, data.time, which)


def build_trajectory_prior_problem(
    data: TrajectoryPriorData,
    prior: TrajectoryPriorConfig,
    cfg: TrajectoryAdjustmentConfig,
    reference: SplineTrajectory,
    initial: SplineTrajectory | None = None,
    errors: SbetErrorEstimate | None = None,
) -> TrajectoryPriorProblem:
    """Build the problem on ``reference.grid``, started at ``initial`` (default the reference) and ``errors``.

    ``initial`` on another grid is resampled onto the reference's; ``errors`` on another error
    grid are interpolated onto this one.
    """
    grid = reference.grid
    if initial is None:
        initial = reference
    elif initial.grid != grid:
        initial = initial.resampled(grid)
    egrid = BiasGrid.covering(grid.t_start, grid.t_end, prior.error_knot_interval_s)
    blocks = TrajectoryBlocks()
    problem = Problem()
    add_spline_blocks(problem, blocks, initial)
    e_p = np.zeros((egrid.n_knots, 3))
    e_t = np.zeros((egrid.n_knots, 3))
    if errors is not None:
        e_p = errors.grid.evaluate(errors.position_m, egrid.times)
        e_t = errors.grid.evaluate(errors.attitude_rad, egrid.times)
    problem.add_block(POSITION_ERROR, e_p)
    problem.add_block(ATTITUDE_ERROR, e_t)

    n_s = (grid.n_knots - 1) * SAMPLES_PER_KNOT + 1
    t = np.linspace(grid.t_start, grid.t_end, n_s)
    p_ref, R_ref = reference.pose(t)
    problem.add_group(TrajectoryPoseObservation(
        grid, t, p_ref, R_ref, prior.white_sigma_position_m, np.radians(prior.white_sigma_attitude_mdeg * 1e-3),
        egrid, POSITION_ERROR, ATTITUDE_ERROR, blocks,
    ))
    tk = egrid.times
    scale = prior.sigma_scale
    problem.add_group(GaussMarkovPrior("sbet_position_error_prior", POSITION_ERROR, egrid,
                                       scale * _sigma_at(data, tk, data.sigma_p_w), prior.correlation_time_s))
    tau = np.array([prior.tilt_correlation_time_s, prior.tilt_correlation_time_s, prior.correlation_time_s])
    problem.add_group(GaussMarkovPrior("sbet_attitude_error_prior", ATTITUDE_ERROR, egrid,
                                       scale * _sigma_at(data, tk, data.sigma_theta_w), tau))
    return TrajectoryPriorProblem(problem, grid, egrid, blocks, data, cfg, prior, reference)


def solve_trajectory_prior(
    built: TrajectoryPriorProblem, options: SolverOptions | None = None, progress=None, covariance: bool = True,
    high_rate: HighRateMotion | None = None,
) -> GnssImuResult:
    """Solve; the result has ``imu_errors`` None and the SBET error in ``sbet_errors``."""
    cfg = built.cfg
    t = _time.perf_counter()
    options = options or trajectory_solver_options(cfg, narrow=True)
    result = built.problem.solve(options, progress=progress)
    p = built.problem
    errors = SbetErrorEstimate(built.error_grid, p.values(POSITION_ERROR), p.values(ATTITUDE_ERROR))
    out = GnssImuResult(built.spline(), None, result, np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)),
                        {"solve": _time.perf_counter() - t}, high_rate, sbet_errors=errors)
    return with_prior_posterior(built, out) if covariance else out


def with_prior_posterior(built: TrajectoryPriorProblem, result: GnssImuResult) -> GnssImuResult:
    """``result`` with posterior sigma of the trajectory and of the SBET error."""
    t = _time.perf_counter()
    p = built.problem
    # Scaled by the variance factor only where it exceeds 1: the delivered trajectory's samples
    # fit the reference they are fitted to, so without other observations the factor is 0 and
    # says nothing; the stated accuracy is the floor.
    solve = posterior_components(p, built.cfg, result.solve)
    vf = posterior_scale(solve)
    tk, sigma_rph, sigma_p, sigma_v = trajectory_sigma(p, built.blocks, built.grid, built.cfg, built.data.frame,
                                                       result.spline, scale=vf)
    e = result.sbet_errors
    errors = replace(e, position_sigma_m=block_sigma(p, POSITION_ERROR, vf),
                     attitude_sigma_rad=block_sigma(p, ATTITUDE_ERROR, vf))
    timings = dict(result.timings_s, covariance=_time.perf_counter() - t)
    return replace(result, solve=solve, sbet_errors=errors, sigma_time=tk, sigma_rph_rad=sigma_rph, sigma_position_m=sigma_p,
                   sigma_velocity_m_s=sigma_v, timings_s=timings)
