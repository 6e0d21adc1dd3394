"""The GNSS/IMU adjustment of a continuous-time trajectory (docs/ARCHITECTURE.md §4.5 step 2).

Parameters: the spline knots (positions, velocities, accelerations, attitudes, body rates),
piecewise-linear accelerometer and gyro biases, constant diagonal scale factors and, where
estimated (:func:`misalignment_prior`), each triad's constant misalignment.
Observations: GNSS antenna positions (robust loss), window-averaged IMU readings, the bias
random walk, and priors on the turn-on biases, the scale factors and the misalignments from the
datasheet.
The same problem later receives the LiDAR plane observations (step 5), so the builder
returns the :class:`~georefine.adjustment.problem.Problem` for further groups.
"""

from __future__ import annotations

import logging
import time as _time
from dataclasses import dataclass, field, fields, replace
from typing import Literal

import numpy as np

from georefine.adjustment.gnss_jumps import GnssJump, find_jumps, jump_warning
from georefine.adjustment.gnss_segments import (
    GNSS_SEGMENT_BLOCK,
    GnssSegments,
    jump_spans,
    non_fix_segments,
    segment_warnings,
)
from georefine.adjustment.linalg import available_backends
from georefine.adjustment.observations.bias import BiasGrid, BiasRandomWalk
from georefine.adjustment.observations.gnss import GnssPositionObservation
from georefine.adjustment.observations.imu import ImuObservation, fewest_nodes, make_imu_windows, sample_support
from georefine.adjustment.observations.prior import EuclideanPrior
from georefine.adjustment.observations.trajectory_blocks import TrajectoryBlocks
from georefine.adjustment.observations.trajectory_prior import GaussMarkovPrior
from georefine.adjustment.problem import Problem
from georefine.adjustment.robust import make_loss
from georefine.adjustment.solver import SolveResult, SolverOptions
from georefine.config import (
    GnssCorrelatedError,
    GnssFloatOffset,
    GnssMultipath,
    ImuErrorSpec,
    TrajectoryAdjustmentConfig,
)
from georefine.errors import InputError
from georefine.geometry.frames import LocalFrame
from georefine.geometry.rotation import rph_from_R_n_b
from georefine.trajectory.highrate import HighRateMotion
from georefine.trajectory.spline import KnotGrid, SplineTrajectory

logger = logging.getLogger(__name__)

DEG_PER_H = np.pi / 180.0 / 3600.0
MICRO_G = 9.80665e-6


@dataclass(frozen=True)
class GnssImuData:
    """Inputs of the adjustment, in the mapping frame and relative times.

    Attributes
    ----------
    frame : LocalFrame
    t0_gps : float
        Dataset epoch (GPS s); all times are relative to it.
    imu_time : (N,) s; imu_gyro (N,3) rad/s; imu_acc (N,3) m/s²; imu_rate_hz : float
    gnss_time : (G,) s; gnss_p_w (G,3) m; gnss_cov_w (G,3,3) m²
    p_b_a : (3,) antenna lever arm (m)
    imu_gyro_sigma, imu_acc_sigma : (N,) or None
        Interpolation sigma of samples bridged over a sampling gap (rad/s, m/s²; 0 for measured
        ones; :mod:`georefine.io.imu_gaps`); None when no sample was bridged.
    gnss_correlated : GnssCorrelatedError or None
        The GNSS error that lasts minutes (``gnss.correlated_error``): estimated on its own
        knots, ``gnss_cov_w`` then holds the total of which the white part is what remains;
        None: ``gnss_cov_w`` is white.
    imu_temperature : (N,) or None
        The unit's temperature at each IMU sample (deg C, ``ImuData.temperature_c``), against which the
        biases' temperature coefficients are estimated (:func:`temperature_prior`); None: not logged.
    gnss_multipath : GnssMultipath or None
        The GNSS error that lasts tens of seconds (``gnss.multipath``), estimated beside
        ``gnss_correlated`` on knots of its own (:func:`multipath_knot_interval`); None: not modelled.

    imu_kind : ``"rates"`` or ``"increments"``
        What an IMU sample is (``ImuData.kind``): the value at its time tag, or the mean over
        the interval that ends there. It decides how the windows are modelled
        (:mod:`georefine.adjustment.observations.imu`).
    imu_cleaning : (N, 6) or None
        Readings cleaned of the rebuilt vibration (up-sampling, docs/ARCHITECTURE.md §4.6): what
        the cleaning took out of unit white noise per sample (gyro, then accelerometer axes;
        :func:`georefine.adjustment.upsampling.without_high_rate`), for the redundancy it
        consumed (:func:`cleaning_redundancy`); None for readings as measured.
    gnss_quality : (G,) int or None
        RTKLIB Q of each epoch; with ``gnss_float`` (``gnss.float_offset``), each segment of epochs
        worse than a fix gets an offset of its own (:mod:`georefine.adjustment.gnss_segments`).
    gnss_jumps : (J, 2) or None
        First and last epoch (s) of runs of fixed epochs found off their neighbours (wrong fixes,
        :mod:`georefine.adjustment.gnss_jumps`), each a segment with an offset of its own too; None:
        not searched (the first G/I searches where ``gnss_float.detect_jumps``).
    """

    frame: LocalFrame
    t0_gps: float
    imu_time: np.ndarray
    imu_gyro: np.ndarray
    imu_acc: np.ndarray
    imu_rate_hz: float
    gnss_time: np.ndarray
    gnss_p_w: np.ndarray
    gnss_cov_w: np.ndarray
    p_b_a: np.ndarray
    imu_gyro_sigma: np.ndarray | None = None
    imu_acc_sigma: np.ndarray | None = None
    gnss_correlated: GnssCorrelatedError | None = None
    imu_kind: Literal["rates", "increments"] = "rates"
    imu_cleaning: np.ndarray | None = None
    gnss_quality: np.ndarray | None = None
    gnss_float: GnssFloatOffset | None = None
    gnss_jumps: np.ndarray | None = None
    gnss_multipath: GnssMultipath | None = None
    imu_temperature: np.ndarray | None = None


GNSS_ERROR_BLOCK = "gnss_error"
"""Block of the correlated GNSS error's knot values ((J, 3), m in ``w``)."""

GNSS_MULTIPATH_BLOCK = "gnss_multipath"
"""Block of the multipath's knot values ((K, 3), m in ``w``; ``gnss.multipath``)."""


def multipath_knot_interval(model: GnssMultipath, cfg: TrajectoryAdjustmentConfig) -> float:
    """Knot spacing of the multipath (s): the correlated error's, or a quarter of the multipath's
    correlation time where that is shorter. Between knots a quarter of the correlation time apart,
    the chords miss about ``sqrt(1/12)`` of its sigma, which :func:`white_gnss_covariance` adds to
    the white part."""
    return min(cfg.gnss_error_knot_interval_s, model.time_constant_s / 4.0)


@dataclass(frozen=True)
class GnssErrorEstimate:
    """The estimated correlated GNSS error ``d(t)`` (m, east/north/up of ``w``) on its knots, with 1-sigma
    (``grid`` None where it is not modelled), and the offsets of the segments without a fix, or None."""

    grid: BiasGrid | None
    value_w: np.ndarray | None
    sigma_w: np.ndarray | None = None
    segments: GnssSegments | None = None
    multipath_grid: BiasGrid | None = None
    """Knots of the multipath (``gnss.multipath``), None where it is not modelled; its values and sigma below."""
    multipath_w: np.ndarray | None = None
    multipath_sigma_w: np.ndarray | None = None

    def to_dict(self) -> dict:
        """``adjustment.json``'s ``gnss_error``: knot times (s from ``t0_gps``), east/north/up values and sigma (m);
        ``multipath``: the same of the multipath, where modelled; ``segments``: one record per segment without a
        fix (:meth:`GnssSegments.to_dict`)."""
        out = {}
        if self.grid is not None:
            out = {"knot_times_s": self.grid.times.tolist(), "enu_m": np.round(self.value_w, 5).tolist()}
            if self.sigma_w is not None:
                out["enu_sigma_m"] = np.round(self.sigma_w, 5).tolist()
        if self.multipath_grid is not None:
            out["multipath"] = {"knot_times_s": self.multipath_grid.times.tolist(),
                                "enu_m": np.round(self.multipath_w, 5).tolist()}
            if self.multipath_sigma_w is not None:
                out["multipath"]["enu_sigma_m"] = np.round(self.multipath_sigma_w, 5).tolist()
        if self.segments is not None:
            out["segments"] = self.segments.to_dict()
        return out


def white_gnss_covariance(cov_w: np.ndarray, model: GnssCorrelatedError, knot_interval_s: float,
                          multipath: GnssMultipath | None = None, multipath_interval_s: float | None = None) -> np.ndarray:
    """The white part of the GNSS covariances ``cov_w`` (G, 3, 3) when ``model`` is estimated apart.

    Per axis of ``w`` the variance of the correlated part is taken off the epoch's (down to
    ``min_white_fraction`` of its sigma), and what a piecewise-linear ``d(t)`` on knots
    ``knot_interval_s`` apart cannot follow is added: a Gauss-Markov process of sigma ``s`` and
    correlation time ``tau`` is locally a random walk of density ``s sqrt(2 / tau)``, whose
    distance from the chord between knots ``dt`` apart has a mean variance of
    ``s² dt / (3 tau)``. The correlations between axes are kept (the axes are rescaled). A stated
    ``multipath`` on knots ``multipath_interval_s`` apart is a second such process: its variance is
    taken off too (down to the same floor) and what its knots cannot follow is added.
    """
    cov_w = np.asarray(cov_w, dtype=float)
    var = np.diagonal(cov_w, axis1=1, axis2=2)
    s2 = np.array([model.sigma_horizontal_m, model.sigma_horizontal_m, model.sigma_up_m]) ** 2
    unfollowed = s2 * knot_interval_s / (3.0 * model.time_constant_s)
    if multipath is not None:
        m2 = np.array([multipath.sigma_horizontal_m, multipath.sigma_horizontal_m, multipath.sigma_up_m]) ** 2
        s2 = s2 + m2
        unfollowed = unfollowed + m2 * multipath_interval_s / (3.0 * multipath.time_constant_s)
    white = np.maximum(var - s2, model.min_white_fraction**2 * var) + unfollowed
    scale = np.sqrt(white / np.maximum(var, 1e-300))
    return cov_w * scale[:, :, None] * scale[:, None, :]


@dataclass(frozen=True)
class ImuErrorEstimate:
    """Estimated IMU errors: biases on their knots, scale factors and, where estimated, each triad's
    misalignment (six off-diagonal elements, :data:`~georefine.adjustment.observations.imu.OFF_DIAGONAL`
    order), with 1-sigma."""

    bias_grid: BiasGrid
    acc_bias: np.ndarray
    gyro_bias: np.ndarray
    acc_scale: np.ndarray
    gyro_scale: np.ndarray
    acc_bias_sigma: np.ndarray | None = None
    gyro_bias_sigma: np.ndarray | None = None
    acc_scale_sigma: np.ndarray | None = None
    gyro_scale_sigma: np.ndarray | None = None
    acc_misalignment: np.ndarray | None = None
    gyro_misalignment: np.ndarray | None = None
    acc_misalignment_sigma: np.ndarray | None = None
    gyro_misalignment_sigma: np.ndarray | None = None
    acc_temperature: np.ndarray | None = None
    """The biases' temperature coefficients (m/s² and rad/s per deg C), where estimated, and their sigma."""
    gyro_temperature: np.ndarray | None = None
    acc_temperature_sigma: np.ndarray | None = None
    gyro_temperature_sigma: np.ndarray | None = None

    def to_dict(self) -> dict:
        def arr(x, f=1.0):
            return None if x is None else (np.asarray(x) * f).tolist()

        return {
            "bias_knot_times_s": self.bias_grid.times.tolist(),
            "acc_bias_ug": arr(self.acc_bias, 1 / MICRO_G),
            "gyro_bias_deg_per_h": arr(self.gyro_bias, 1 / DEG_PER_H),
            "acc_bias_sigma_ug": arr(self.acc_bias_sigma, 1 / MICRO_G),
            "gyro_bias_sigma_deg_per_h": arr(self.gyro_bias_sigma, 1 / DEG_PER_H),
            "acc_scale_ppm": arr(self.acc_scale, 1e6),
            "gyro_scale_ppm": arr(self.gyro_scale, 1e6),
            "acc_scale_sigma_ppm": arr(self.acc_scale_sigma, 1e6),
            "gyro_scale_sigma_ppm": arr(self.gyro_scale_sigma, 1e6),
            "acc_misalignment_mrad": arr(self.acc_misalignment, 1e3),
            "gyro_misalignment_mrad": arr(self.gyro_misalignment, 1e3),
            "acc_misalignment_sigma_mrad": arr(self.acc_misalignment_sigma, 1e3),
            "gyro_misalignment_sigma_mrad": arr(self.gyro_misalignment_sigma, 1e3),
            "acc_temperature_ug_per_c": arr(self.acc_temperature, 1 / MICRO_G),
            "gyro_temperature_deg_per_h_per_c": arr(self.gyro_temperature, 1 / DEG_PER_H),
            "acc_temperature_sigma_ug_per_c": arr(self.acc_temperature_sigma, 1 / MICRO_G),
            "gyro_temperature_sigma_deg_per_h_per_c": arr(self.gyro_temperature_sigma, 1 / DEG_PER_H),
        }


@dataclass(frozen=True)
class GnssImuResult:
    """The adjusted trajectory, IMU errors, statistics and posterior attitude sigma.

    Also the result of an adjustment on a delivered trajectory
    (:mod:`georefine.adjustment.trajectory_prior`): then ``imu_errors`` is None and
    ``sbet_errors`` holds the estimated error of the delivered trajectory.
    """

    spline: SplineTrajectory
    imu_errors: ImuErrorEstimate | None
    solve: SolveResult
    sigma_time: np.ndarray
    sigma_rph_rad: np.ndarray
    sigma_position_m: np.ndarray
    timings_s: dict = field(default_factory=dict)
    high_rate: HighRateMotion | None = None
    """Motion faster than the knots, rebuilt from the IMU (:mod:`georefine.adjustment.upsampling`),
    or the delivered trajectory's (:mod:`georefine.adjustment.trajectory_prior`)."""
    sigma_velocity_m_s: np.ndarray | None = None
    """Posterior velocity sigma in ``w`` at ``sigma_time``, m/s (the knot velocities are the spline's)."""
    sbet_errors: object | None = None
    """Without raw GNSS/IMU (``imu_errors`` None): the delivered trajectory's estimated error,
    a :class:`~georefine.adjustment.trajectory_prior.SbetErrorEstimate`."""
    gnss_error: GnssErrorEstimate | None = None
    """The estimated correlated GNSS error (``gnss.correlated_error``), or None."""


@dataclass
class GnssImuProblem:
    """A built problem and what is needed to read its solution."""

    problem: Problem
    grid: KnotGrid
    bias_grid: BiasGrid
    blocks: TrajectoryBlocks
    data: GnssImuData
    cfg: TrajectoryAdjustmentConfig
    estimate_scale: bool
    gnss_error_grid: BiasGrid | None = None
    estimate_misalignment: bool = False
    gnss_segments: GnssSegments | None = None
    spec: ImuErrorSpec | None = None
    gnss_multipath_grid: BiasGrid | None = None
    estimate_temperature: bool = False
    """The biases' temperature coefficients are estimated (blocks ``acc_temperature``, ``gyro_temperature``)."""
    detect_jumps: bool = False
    """Search the residuals of the first solve for wrong GNSS fixes (:func:`solve_gnss_imu`)."""

    def spline(self) -> SplineTrajectory:
        return spline_from_problem(self.problem, self.blocks, self.grid, self.data.t0_gps)


def add_spline_blocks(problem: Problem, blocks: TrajectoryBlocks, initial: SplineTrajectory) -> None:
    """The five knot blocks of a spline trajectory (§4.2), started at ``initial`` (copied)."""
    problem.add_block(blocks.position, initial.p_w_b.copy())
    problem.add_block(blocks.velocity, initial.v_w_b.copy())
    problem.add_block(blocks.acceleration, initial.a_w_b.copy())
    problem.add_block(blocks.attitude, initial.R_w_b.copy(), manifold="so3")
    problem.add_block(blocks.rate, initial.omega_wb_b.copy())


def spline_from_problem(problem: Problem, blocks: TrajectoryBlocks, grid: KnotGrid, t0_gps: float) -> SplineTrajectory:
    """The spline trajectory the knot blocks of ``problem`` hold now."""
    return SplineTrajectory(
        grid, problem.values(blocks.position), problem.values(blocks.velocity), problem.values(blocks.acceleration),
        problem.values(blocks.attitude), problem.values(blocks.rate), t0_gps=t0_gps,
    )


def _densities(spec: ImuErrorSpec, cfg: TrajectoryAdjustmentConfig, temperature_modelled: bool = False
               ) -> dict[str, float]:
    """White-noise and bias random-walk densities in SI units, with the configured floors."""
    arw = max(spec.gyro_arw_deg_per_sqrt_h, cfg.min_gyro_noise_deg_per_sqrt_h)
    vrw = max(spec.acc_vrw_m_per_s_per_sqrt_h, cfg.min_acc_noise_m_per_s_per_sqrt_h)
    # widened where a temperature change is stated and the coefficients are not estimated
    q_g, q_a = spec.bias_random_walk_si(temperature_modelled=temperature_modelled)
    return {
        "gyro_noise": np.radians(arw) / 60.0,  # rad/s/sqrt(Hz)
        "acc_noise": vrw / 60.0,  # m/s²/sqrt(Hz)
        "gyro_rw": max(q_g, cfg.min_gyro_bias_rw_deg_per_h_per_sqrt_h * DEG_PER_H / 60.0),
        "acc_rw": max(q_a, cfg.min_acc_bias_rw_ug_per_sqrt_h * MICRO_G / 60.0),
        "gyro_turn_on": max(spec.gyro_turn_on_bias_deg_per_h, cfg.min_turn_on_gyro_deg_per_h) * DEG_PER_H,
        "acc_turn_on": max(spec.acc_turn_on_bias_ug, cfg.min_turn_on_acc_ug) * MICRO_G,
        "gyro_scale": max(spec.gyro_scale_factor_ppm, cfg.min_scale_factor_ppm) * 1e-6,
        "acc_scale": max(spec.acc_scale_factor_ppm, cfg.min_scale_factor_ppm) * 1e-6,
    }


def misalignment_prior(spec: ImuErrorSpec, cfg: TrajectoryAdjustmentConfig) -> tuple[float, float] | None:
    """Prior sigma (rad) of the gyro and the accelerometer misalignment elements, or None where they
    are not estimated (``cfg.estimate_misalignment``: ``auto`` where ``spec`` states one)."""
    stated = spec.gyro_misalignment_mrad > 0 or spec.acc_misalignment_mrad > 0
    if cfg.estimate_misalignment is False or (cfg.estimate_misalignment == "auto" and not stated):
        return None
    return tuple((v if v > 0 else cfg.misalignment_prior_mrad) * 1e-3
                 for v in (spec.gyro_misalignment_mrad, spec.acc_misalignment_mrad))


def _temperature_stated(spec: ImuErrorSpec) -> bool:
    """Whether the datasheet states a temperature coefficient (``auto`` then estimates them)."""
    return spec.gyro_temperature_deg_per_h_per_c > 0 or spec.acc_temperature_ug_per_c > 0


def temperature_prior(spec: ImuErrorSpec, cfg: TrajectoryAdjustmentConfig, data: GnssImuData
                      ) -> tuple[float, float] | None:
    """Prior sigma of the gyro (rad/s per deg C) and the accelerometer (m/s² per deg C) temperature
    coefficients, or None where they are not estimated (``cfg.estimate_temperature_coefficients``: ``auto``
    where the IMU file logs a temperature and ``spec`` states a coefficient; ``true`` where it logs one).

    Raises
    ------
    InputError
        ``true`` with an IMU file that logs no temperature.
    """
    stated = _temperature_stated(spec)
    mode = cfg.estimate_temperature_coefficients
    if mode is True and data.imu_temperature is None:
        raise InputError("the IMU file logs no temperature", field="temperature_c",
                         expected="a temperature_c column where processing.trajectory."
                         "estimate_temperature_coefficients is true", found="none")
    if mode is False or data.imu_temperature is None or (mode == "auto" and not stated):
        return None
    g = spec.gyro_temperature_deg_per_h_per_c or cfg.temperature_prior_gyro_deg_per_h_per_c
    a = spec.acc_temperature_ug_per_c or cfg.temperature_prior_acc_ug_per_c
    return g * DEG_PER_H, a * MICRO_G


TEMPERATURE_CHANGE_NOTE_C = 3.0
"""The logged temperature change (deg C) from which :func:`unmodelled_temperature` names coefficients left out: at
the default priors (0.1 deg/h and 10 micro-g per deg C) 3 deg C drift the biases by 0.3 deg/h and 30 micro-g, about
a MEMS unit's bias instability (0.5 deg/h, 50 micro-g)."""


def unmodelled_temperature(temperature_c: np.ndarray | None, spec: ImuErrorSpec,
                           cfg: TrajectoryAdjustmentConfig) -> str | None:
    """What ``check`` and ``run`` say where the IMU file logs a temperature that changes by
    :data:`TEMPERATURE_CHANGE_NOTE_C` or more and the biases' temperature coefficients are not estimated
    (``auto`` with no coefficient in the datasheet): the change, the drift it makes at the default priors, and
    the setting that estimates them; else None. Left out, such a drift is not the bias walk the model holds: on
    ``corridor`` a 20 deg C warm-up cost the G/I/L's roll 1.36 times the clean run's with honest sigmas, 1.24
    estimated (BENCHMARKS.md, "Sensors beyond the model")."""
    if temperature_c is None or not np.size(temperature_c) or cfg.estimate_temperature_coefficients is False:
        return None
    t = np.asarray(temperature_c, dtype=float)
    change = float(t.max() - t.min())
    if change < TEMPERATURE_CHANGE_NOTE_C or cfg.estimate_temperature_coefficients is True or _temperature_stated(spec):
        return None
    g, a = cfg.temperature_prior_gyro_deg_per_h_per_c, cfg.temperature_prior_acc_ug_per_c
    return (f"the IMU file logs its temperature changing by {change:.1f} deg C ({t.min():.1f} .. {t.max():.1f}), and "
            "the biases' temperature coefficients are not estimated (imu.errors states none): at "
            f"{g:g} deg/h and {a:g} micro-g per deg C the biases drift by {g * change:.2f} deg/h and {a * change:.0f} "
            "micro-g over it, smoothly, which the bias walk does not model; processing.trajectory."
            "estimate_temperature_coefficients: true estimates them against the logged temperature "
            "(priors temperature_prior_gyro_deg_per_h_per_c, temperature_prior_acc_ug_per_c), or state the "
            "datasheet's imu.errors.gyro_temperature_deg_per_h_per_c, acc_temperature_ug_per_c")


def cleaning_redundancy(data: GnssImuData, inside: np.ndarray, window_s: float, densities: dict,
                        sigma_gyro: np.ndarray, sigma_acc: np.ndarray) -> float:
    """The redundancy of the IMU windows that the cleaning of the readings consumed.

    The cleaning (up-sampling, docs/ARCHITECTURE.md §4.6) subtracts from the readings what a
    filter fitted to these same readings keeps: the vibration lines' bins of the rebuilt
    high-frequency motion, and near the segments' ends all of it. With the lines goes the sensor
    noise in their bins: the cleaned windows fit better than their weights say, by as many
    degrees of freedom as the filter took. Uncounted, the variance factor of the navigation
    sensors fell below 1 while the attitude error stayed (the G/I/L's IMU windows with a
    navigation-grade unit on a vibrating platform fitted at 0.48 per row; BENCHMARKS.md,
    Operating conditions). The expected loss of ``sum w r^2`` is ``tr(W A S Sigma S^T A^T)``
    (``S`` the filter, ``A`` the window means, ``Sigma`` the sample noise, ``W`` the window
    weights); ``data.imu_cleaning`` is ``S`` applied to unit white noise (one seeded draw), so
    the sum below is an unbiased estimate of it, with a relative standard deviation of about
    ``sqrt(2 / estimate)`` (1 % for 18,000). It slightly overcounts where the filter's bins
    overlap what the spline follows (its 2.5-5 Hz transition for 0.1 s knots), which ``tr(H)``
    counts already. 0 for readings as measured.
    """
    if data.imu_cleaning is None:
        return 0.0
    u = data.imu_cleaning[inside]
    per_sample = np.sqrt(data.imu_rate_hz)  # density -> sample sigma
    w = make_imu_windows(data.imu_time[inside], u[:, :3] * densities["gyro_noise"] * per_sample,
                         u[:, 3:] * densities["acc_noise"] * per_sample, data.imu_rate_hz, window_s, kind=data.imu_kind)
    sg = np.broadcast_to(np.asarray(sigma_gyro, dtype=float), (len(w),))[:, None]
    sa = np.broadcast_to(np.asarray(sigma_acc, dtype=float), (len(w),))[:, None]
    return float(np.sum((w.gyro / sg) ** 2) + np.sum((w.acc / sa) ** 2))


def build_gnss_imu_problem(
    data: GnssImuData,
    spec: ImuErrorSpec,
    cfg: TrajectoryAdjustmentConfig,
    initial: SplineTrajectory,
    acc_bias0: np.ndarray | None = None,
    gyro_bias0: np.ndarray | None = None,
) -> GnssImuProblem:
    """Build the G/I problem on ``initial.grid`` from starting values (e.g. the smoothed filter).

    ``acc_bias0``/``gyro_bias0`` are starting biases, either (3,) or sampled at the bias knots
    ((J, 3)); zero by default.
    """
    grid = initial.grid
    span = (grid.t_start, grid.t_end)
    before, after = sample_support(data.imu_kind, data.imu_rate_hz)
    inside = (data.imu_time - before >= span[0]) & (data.imu_time + after <= span[1])
    if inside.sum() < 2:
        raise InputError("no IMU samples inside the trajectory span", field="time")
    temp = temperature_prior(spec, cfg, data)
    d = _densities(spec, cfg, temperature_modelled=temp is not None)
    windows = make_imu_windows(
        data.imu_time[inside], data.imu_gyro[inside], data.imu_acc[inside], data.imu_rate_hz, cfg.imu_window_s,
        gyro_sigma=None if data.imu_gyro_sigma is None else data.imu_gyro_sigma[inside],
        acc_sigma=None if data.imu_acc_sigma is None else data.imu_acc_sigma[inside], kind=data.imu_kind,
    )
    sigma_g = d["gyro_noise"] * np.sqrt(data.imu_rate_hz / windows.n_samples)
    sigma_a = d["acc_noise"] * np.sqrt(data.imu_rate_hz / windows.n_samples)
    if windows.gyro_bridged_sigma is not None:  # samples bridged over a gap: their interpolation error too
        sigma_g = np.hypot(sigma_g, windows.gyro_bridged_sigma)
    if windows.acc_bridged_sigma is not None:
        sigma_a = np.hypot(sigma_a, windows.acc_bridged_sigma)
    consumed = cleaning_redundancy(data, inside, cfg.imu_window_s, d, sigma_g, sigma_a)
    bias_grid = BiasGrid.covering(span[0], span[1], cfg.bias_knot_interval_s)

    blocks = TrajectoryBlocks()
    problem = Problem()
    add_spline_blocks(problem, blocks, initial)
    J = bias_grid.n_knots
    for name, b0 in (("acc_bias", acc_bias0), ("gyro_bias", gyro_bias0)):
        b = np.zeros((J, 3)) if b0 is None else np.broadcast_to(np.asarray(b0, dtype=float), (J, 3)).copy()
        problem.add_block(name, b)
    problem.add_block("acc_scale", np.zeros((1, 3)), constant=not cfg.estimate_scale_factors)
    problem.add_block("gyro_scale", np.zeros((1, 3)), constant=not cfg.estimate_scale_factors)
    mis = misalignment_prior(spec, cfg)
    if mis is not None:
        problem.add_block("acc_misalignment", np.zeros((1, 6)))
        problem.add_block("gyro_misalignment", np.zeros((1, 6)))
    temperature = {}
    if temp is not None:  # the windows' temperature against the file's first sample
        problem.add_block("acc_temperature", np.zeros((1, 3)))
        problem.add_block("gyro_temperature", np.zeros((1, 3)))
        mid = 0.5 * (windows.t_start + windows.t_end)
        temperature = dict(temperature=np.interp(mid, data.imu_time, data.imu_temperature) - data.imu_temperature[0],
                           acc_temperature="acc_temperature", gyro_temperature="gyro_temperature")

    g_in = (data.gnss_time >= span[0]) & (data.gnss_time <= span[1])
    if not np.any(g_in):
        raise InputError("no GNSS epoch inside the trajectory span", field="time")
    cov, error, egrid, mgrid = data.gnss_cov_w[g_in], {}, None, None
    segments = non_fix_segments(data.gnss_time[g_in], None if data.gnss_quality is None else data.gnss_quality[g_in],
                                cov, data.gnss_float, data.gnss_jumps)
    if segments is not None:  # an offset per segment without a fix, with its prior
        problem.add_block(GNSS_SEGMENT_BLOCK, np.zeros((len(segments), 3)))
        problem.add_group(EuclideanPrior("gnss_segment_prior", GNSS_SEGMENT_BLOCK, np.arange(len(segments)),
                                         np.zeros((len(segments), 3)), segments.prior_sigma_w))
        error = {"segment": segments.index, "segment_block": GNSS_SEGMENT_BLOCK}
    model, mp = data.gnss_correlated, data.gnss_multipath
    if mp is not None and model is None:
        raise ValueError("the multipath is estimated beside the correlated GNSS error: gnss_correlated is None")
    if model is not None:  # d(t) on its own knots with its Gauss-Markov prior; the epochs keep the white part
        egrid = BiasGrid.covering(span[0], span[1], cfg.gnss_error_knot_interval_s)
        mgrid = None if mp is None else BiasGrid.covering(span[0], span[1], multipath_knot_interval(mp, cfg))
        cov = white_gnss_covariance(cov, model, egrid.dt_s, mp, None if mgrid is None else mgrid.dt_s)
        problem.add_block(GNSS_ERROR_BLOCK, np.zeros((egrid.n_knots, 3)))
        sigma = np.array([model.sigma_horizontal_m, model.sigma_horizontal_m, model.sigma_up_m])
        problem.add_group(GaussMarkovPrior("gnss_error_prior", GNSS_ERROR_BLOCK, egrid, sigma, model.time_constant_s))
        error |= {"error_grid": egrid, "error_block": GNSS_ERROR_BLOCK}
        if mgrid is not None:  # the multipath: a second, short-correlated process on its own knots
            problem.add_block(GNSS_MULTIPATH_BLOCK, np.zeros((mgrid.n_knots, 3)))
            sigma = np.array([mp.sigma_horizontal_m, mp.sigma_horizontal_m, mp.sigma_up_m])
            problem.add_group(GaussMarkovPrior("gnss_multipath_prior", GNSS_MULTIPATH_BLOCK, mgrid, sigma,
                                               mp.time_constant_s))
            error |= {"multipath_grid": mgrid, "multipath_block": GNSS_MULTIPATH_BLOCK}
    problem.add_group(
        GnssPositionObservation(
            grid, data.gnss_time[g_in], data.gnss_p_w[g_in], cov, data.p_b_a,
            loss=make_loss(cfg.gnss_loss, cfg.gnss_loss_scale), blocks=blocks, **error,
        )
    )
    imu = ImuObservation(
        grid, windows, data.frame, bias_grid, bias_grid, sigma_acc=sigma_a, sigma_gyro=sigma_g,
        nodes=cfg.quadrature_nodes if np.any(windows.n_samples > 1) else 1, blocks=blocks,
        consumed_redundancy=consumed, acc_misalignment="acc_misalignment" if mis else None,
        gyro_misalignment="gyro_misalignment" if mis else None, **temperature,
    )
    imu, change = fewest_nodes(imu, {name: b.values for name, b in problem.blocks.items()})
    logger.debug("IMU windows: %d nodes each (one fewer moves a window mean by up to %.2g sigma)", imu.nodes, change)
    problem.add_group(imu)
    problem.add_group(BiasRandomWalk("acc_bias_random_walk", "acc_bias", bias_grid, q=d["acc_rw"]))
    problem.add_group(BiasRandomWalk("gyro_bias_random_walk", "gyro_bias", bias_grid, q=d["gyro_rw"]))
    problem.add_group(EuclideanPrior("acc_bias_turn_on", "acc_bias", [0], np.zeros(3), d["acc_turn_on"]))
    problem.add_group(EuclideanPrior("gyro_bias_turn_on", "gyro_bias", [0], np.zeros(3), d["gyro_turn_on"]))
    if cfg.estimate_scale_factors:
        problem.add_group(EuclideanPrior("acc_scale_prior", "acc_scale", [0], np.zeros(3), d["acc_scale"]))
        problem.add_group(EuclideanPrior("gyro_scale_prior", "gyro_scale", [0], np.zeros(3), d["gyro_scale"]))
    if mis is not None:
        problem.add_group(EuclideanPrior("gyro_misalignment_prior", "gyro_misalignment", [0], np.zeros(6), mis[0]))
        problem.add_group(EuclideanPrior("acc_misalignment_prior", "acc_misalignment", [0], np.zeros(6), mis[1]))
    if temp is not None:
        problem.add_group(EuclideanPrior("gyro_temperature_prior", "gyro_temperature", [0], np.zeros(3), temp[0]))
        problem.add_group(EuclideanPrior("acc_temperature_prior", "acc_temperature", [0], np.zeros(3), temp[1]))
    return GnssImuProblem(problem, grid, bias_grid, blocks, data, cfg, cfg.estimate_scale_factors, egrid,
                          estimate_misalignment=mis is not None, gnss_segments=segments, spec=spec,
                          gnss_multipath_grid=mgrid, estimate_temperature=temp is not None,
                          detect_jumps=bool(data.gnss_float is not None and data.gnss_float.detect_jumps
                                            and data.gnss_jumps is None))


def detect_gnss_jumps(built: GnssImuProblem) -> list[GnssJump]:
    """The wrong GNSS fixes the residuals of ``built``'s current solution show among its fixed epochs outside
    every segment (:func:`~georefine.adjustment.gnss_jumps.find_jumps`, on the white part of their sigma)."""
    model = built.data.gnss_float
    g = next(group for group in built.problem.groups if isinstance(group, GnssPositionObservation))
    residual = g.p_w - g.predict({name: b.values for name, b in built.problem.blocks.items()})
    free = np.ones(g.time.size, dtype=bool) if g.segment is None else g.segment < 0
    sigma = np.sqrt(np.diagonal(np.asarray(g.cov_w), axis1=1, axis2=2))
    return find_jumps(g.time[free], residual[free], sigma[free], model.jump_window_s, model.jump_threshold_sigma)


def with_jump_segments(built: GnssImuProblem, spans: np.ndarray) -> GnssImuProblem:
    """``built`` rebuilt in place with a segment per span of fixed epochs (wrong fixes, ``(J, 2)`` s), started
    at its current values; returns ``built``."""
    new = build_gnss_imu_problem(replace(built.data, gnss_jumps=np.asarray(spans, dtype=float).reshape(-1, 2)),
                                 built.spec, built.cfg, built.spline())
    start_imu_errors(new, imu_errors_of(built), gnss_error_of(built))
    for f in fields(built):
        setattr(built, f.name, getattr(new, f.name))
    return built


def start_imu_errors(built: GnssImuProblem, errors: ImuErrorEstimate,
                     gnss_error: GnssErrorEstimate | None = None) -> GnssImuProblem:
    """Start ``built``'s biases, scale factors and misalignments at ``errors`` (same bias knots), its
    correlated GNSS error at ``gnss_error`` where both have one (same knots) and its segments' offsets
    where both have the segment; returns ``built``.

    A problem so started goes on from an earlier solution: it does not search for wrong GNSS fixes
    itself, and takes those ``gnss_error`` holds (segments of quality 1) as segments of its own."""
    seg = None if gnss_error is None else gnss_error.segments
    built.detect_jumps = False
    spans = jump_spans(seg)
    if spans is not None and jump_spans(built.gnss_segments) is None and built.data.gnss_float is not None:
        with_jump_segments(built, spans)
    P = built.problem
    if gnss_error is not None and gnss_error.grid is not None and GNSS_ERROR_BLOCK in P.blocks:
        P.set_values(GNSS_ERROR_BLOCK, gnss_error.value_w)
    if (gnss_error is not None and gnss_error.multipath_w is not None and GNSS_MULTIPATH_BLOCK in P.blocks
            and P.values(GNSS_MULTIPATH_BLOCK).shape == gnss_error.multipath_w.shape):
        P.set_values(GNSS_MULTIPATH_BLOCK, gnss_error.multipath_w)
    own = built.gnss_segments
    if seg is not None and seg.value_w is not None and own is not None:  # the same segments: start at their offsets
        value = P.values(GNSS_SEGMENT_BLOCK)
        for k in range(len(own)):
            same = np.flatnonzero((np.abs(seg.t_start - own.t_start[k]) < 1e-6) & (np.abs(seg.t_end - own.t_end[k]) < 1e-6))
            if same.size:
                value[k] = seg.value_w[same[0]]
        P.set_values(GNSS_SEGMENT_BLOCK, value)
    P.set_values("acc_bias", errors.acc_bias)
    P.set_values("gyro_bias", errors.gyro_bias)
    P.set_values("acc_scale", np.asarray(errors.acc_scale, dtype=float).reshape(1, 3))
    P.set_values("gyro_scale", np.asarray(errors.gyro_scale, dtype=float).reshape(1, 3))
    for name, value in (("acc_misalignment", errors.acc_misalignment), ("gyro_misalignment", errors.gyro_misalignment)):
        if name in P.blocks and value is not None:
            P.set_values(name, np.asarray(value, dtype=float).reshape(1, 6))
    for name, value in (("acc_temperature", errors.acc_temperature), ("gyro_temperature", errors.gyro_temperature)):
        if name in P.blocks and value is not None:
            P.set_values(name, np.asarray(value, dtype=float).reshape(1, 3))
    return built


def imu_errors_of(built: GnssImuProblem) -> ImuErrorEstimate:
    """The IMU errors ``built`` holds now, without sigma."""
    p = built.problem
    mis = {}
    if built.estimate_misalignment:
        mis = dict(acc_misalignment=p.values("acc_misalignment")[0].copy(),
                   gyro_misalignment=p.values("gyro_misalignment")[0].copy())
    if built.estimate_temperature:
        mis |= dict(acc_temperature=p.values("acc_temperature")[0].copy(),
                    gyro_temperature=p.values("gyro_temperature")[0].copy())
    return ImuErrorEstimate(built.bias_grid, p.values("acc_bias"), p.values("gyro_bias"), p.values("acc_scale")[0],
                            p.values("gyro_scale")[0], **mis)


def gnss_error_of(built: GnssImuProblem, scale: float | None = None) -> GnssErrorEstimate | None:
    """The correlated GNSS error and the segments' offsets ``built`` holds now (with posterior sigma,
    covariance times ``scale``, if ``scale`` is given), or None where it has neither."""
    if built.gnss_error_grid is None and built.gnss_segments is None:
        return None
    P = built.problem
    segments = built.gnss_segments
    if segments is not None:
        segments = replace(segments, value_w=P.values(GNSS_SEGMENT_BLOCK).copy(),
                           sigma_w=block_sigma(P, GNSS_SEGMENT_BLOCK, scale) if scale is not None else None)
    if built.gnss_error_grid is None:
        return GnssErrorEstimate(None, None, segments=segments)
    s = block_sigma(P, GNSS_ERROR_BLOCK, scale) if scale is not None else None
    multipath = {}
    if built.gnss_multipath_grid is not None:
        multipath = dict(multipath_grid=built.gnss_multipath_grid, multipath_w=P.values(GNSS_MULTIPATH_BLOCK).copy(),
                         multipath_sigma_w=block_sigma(P, GNSS_MULTIPATH_BLOCK, scale) if scale is not None else None)
    return GnssErrorEstimate(built.gnss_error_grid, P.values(GNSS_ERROR_BLOCK).copy(), s, segments, **multipath)


def euler_rate_inverse(rph: np.ndarray) -> np.ndarray:
    """``E^-1`` with ``omega_nb_b = E(rph) d(rph)/dt``: maps a body rotation to Euler-angle changes."""
    r, p = rph[:, 0], rph[:, 1]
    sr, cr, sp, cp = np.sin(r), np.cos(r), np.sin(p), np.cos(p)
    E = np.zeros((rph.shape[0], 3, 3))
    E[:, 0, 0] = 1.0
    E[:, 0, 2] = -sp
    E[:, 1, 1] = cr
    E[:, 1, 2] = sr * cp
    E[:, 2, 1] = -sr
    E[:, 2, 2] = cr * cp
    return np.linalg.inv(E)


NARROW_BACKEND = "qdldl"
"""The sparse Cholesky that ``linear_solver: auto`` takes for the G/I and the delivered trajectory.

Their normal matrices are narrow by construction (knot neighbours, 10 s bias knots, six scale
factors): on the corridor's G/I the factor holds 50 entries per column in supernodes of 15
columns, for any flight length. There QDLDL's simplicial factorisation (installed with Georefine)
beats CHOLMOD's supernodal one through CVXOPT, whose triplet conversion, symbolic analysis and
factor copy cost more than its BLAS saves: factorisations 0.12 s against 0.20 s, posterior 0.06 s
against 0.08 s (BENCHMARKS.md, Georefine against gtsam; scikit-sparse's CHOLMOD was not measured
there). The planes of the G/I/L fill its factor
(270 entries per column at 10 minutes of flight, supernodes of up to 1,192 columns), where
CVXOPT is 1.8 times faster: it keeps the general order (:func:`~georefine.adjustment.linalg.available_backends`)."""


def trajectory_solver_options(cfg: TrajectoryAdjustmentConfig, narrow: bool = False, **overrides) -> SolverOptions:
    """Solver options of the trajectory adjustments (G/I and delivered trajectory with ``narrow``,
    G/I/L with its own ``overrides``): ``cfg``'s limits, the cost-change test against a fitting
    model's cost (``relative_to_fit``) and on the predicted change (``predicted_stop``;
    docs/ARCHITECTURE.md §4.4); with ``narrow`` and ``linear_solver: auto``, :data:`NARROW_BACKEND`."""
    backend = cfg.linear_solver
    if narrow and backend == "auto" and NARROW_BACKEND in available_backends():
        backend = NARROW_BACKEND
    options = SolverOptions(max_iterations=cfg.max_iterations, function_tolerance=cfg.function_tolerance,
                            initial_lambda=cfg.initial_lambda, relative_to_fit=True, predicted_stop=True,
                            linear_solver=backend)
    return replace(options, **overrides)


def solve_gnss_imu(
    built: GnssImuProblem, options: SolverOptions | None = None, progress=None, covariance: bool = True
) -> GnssImuResult:
    """Solve the built problem and read out trajectory, IMU errors and (optionally) posterior sigma.

    With ``covariance=False`` the sigma arrays are empty and the IMU errors carry no sigma; call
    :func:`with_posterior` on the same ``built`` problem later to add them (the outer iterations
    of the G/I/L workflow need the covariance of their last adjustment only).
    """
    cfg = built.cfg
    t = _time.perf_counter()
    options = options or trajectory_solver_options(cfg, narrow=True)
    result = built.problem.solve(options, progress=progress)
    if built.detect_jumps:  # once: wrong GNSS fixes the residuals show get an offset each, and the G/I runs again
        built.detect_jumps = False
        jumps = detect_gnss_jumps(built)
        for jump in jumps:
            logger.warning(jump_warning(jump, built.data.t0_gps))
        if jumps:
            with_jump_segments(built, np.array([[j.t_start, j.t_end] for j in jumps]))
            result = built.problem.solve(options, progress=progress)
    timings = {"solve": _time.perf_counter() - t}
    errors = imu_errors_of(built)
    out = GnssImuResult(built.spline(), errors, result, np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), timings,
                        gnss_error=gnss_error_of(built))
    return with_posterior(built, out) if covariance else out


def trajectory_sigma(problem: Problem, blocks: TrajectoryBlocks, grid: KnotGrid, cfg: TrajectoryAdjustmentConfig,
                     frame: LocalFrame, spline: SplineTrajectory, scale: float | None = None,
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Posterior roll/pitch/heading, position and velocity sigma of a solved trajectory, at every
    ``covariance_interval_s`` (at most ``max_covariance_knots`` knots): ``(times, sigma_rph, sigma_p, sigma_v)``.

    The covariance is scaled by the a-posteriori variance factor, or by ``scale`` when given."""
    knots = sigma_knots(grid, cfg)
    by_vf = scale is None
    cov_R = problem.covariance(blocks.attitude, knots, scale_by_variance_factor=by_vf) * (1.0 if by_vf else scale)
    cov_p = problem.covariance(blocks.position, knots, scale_by_variance_factor=by_vf,
                               diagonal=True) * (1.0 if by_vf else scale)
    cov_v = problem.covariance(blocks.velocity, knots, scale_by_variance_factor=by_vf,
                               diagonal=True) * (1.0 if by_vf else scale)
    tk = grid.knot_times[knots]
    p_w, R_w_b = spline.pose(tk)
    rph = rph_from_R_n_b(np.swapaxes(frame.R_w_n_at(p_w), 1, 2) @ R_w_b)
    Einv = euler_rate_inverse(rph)
    cov_rph = Einv @ cov_R @ np.swapaxes(Einv, 1, 2)
    sigma_rph = np.sqrt(np.clip(np.diagonal(cov_rph, axis1=1, axis2=2), 0.0, None))
    sigma_p = np.sqrt(np.clip(np.diagonal(cov_p, axis1=1, axis2=2), 0.0, None))
    sigma_v = np.sqrt(np.clip(np.diagonal(cov_v, axis1=1, axis2=2), 0.0, None))
    return tk, sigma_rph, sigma_p, sigma_v


def sigma_knots(grid: KnotGrid, cfg: TrajectoryAdjustmentConfig) -> np.ndarray:
    """The knots :func:`trajectory_sigma` reports: every ``covariance_interval_s``, at most
    ``max_covariance_knots``, the last knot included."""
    step = max(1, int(round(cfg.covariance_interval_s / grid.dt)), int(np.ceil(grid.n_knots / cfg.max_covariance_knots)))
    knots = np.arange(0, grid.n_knots, step)
    if knots[-1] != grid.n_knots - 1:
        knots = np.append(knots, grid.n_knots - 1)
    return knots


def posterior_columns(built: "GnssImuProblem") -> int:
    """About how many unit columns of ``N^-1`` :func:`with_posterior` asks for: attitude, position and
    velocity at :func:`sigma_knots`, the IMU errors, the correlated GNSS error, the segments' offsets."""
    P = built.problem
    n = (9 * sigma_knots(built.grid, built.cfg).size + 6 * built.bias_grid.n_knots + 6 + 12 * built.estimate_misalignment
         + 6 * built.estimate_temperature)
    for name in (GNSS_ERROR_BLOCK, GNSS_MULTIPATH_BLOCK, GNSS_SEGMENT_BLOCK):
        if name in P.blocks:
            n += 3 * P.values(name).shape[0]
    return n


def block_sigma(problem: Problem, name: str, scale: float | None = None) -> np.ndarray:
    """Posterior sigma (n, d) of every element of a Euclidean block (``scale``: as :func:`trajectory_sigma`)."""
    if scale is None:
        c = problem.covariance(name, diagonal=True)
    else:
        c = problem.covariance(name, scale_by_variance_factor=False, diagonal=True) * scale
    return np.sqrt(np.clip(np.diagonal(c, axis1=1, axis2=2), 0.0, None))


def posterior_scale(solve: SolveResult) -> float:
    """The factor on the posterior covariances: 1 where variance components weight the posterior's
    normal matrix (:func:`posterior_components`), else the a-posteriori variance factor where it exceeds 1.

    Below 1 the a-priori sigmas stay: a factor below 1 comes from the robust losses, which
    weight the observations with large residuals down (the plane observations' Cauchy loss takes
    the G/I/L factor to about 0.7 while their median-based sigma0 is 1.0), and from datasheet
    noise figures that are upper bounds; shrinking every sigma by it made the G/I/L attitude
    sigmas optimistic (BENCHMARKS.md, Operating conditions). Above 1 the data say the model
    is too optimistic, and the sigmas grow with it.
    """
    if solve.variance_components:
        return 1.0
    return max(1.0, float(solve.sigma0) ** 2) if np.isfinite(solve.sigma0) else 1.0


POSTERIOR_POOLS = (("planes",),)
"""The variance components of the trajectory posteriors: the LiDAR's plane observations, and the
navigation sensors (GNSS, IMU, their priors and random walks, in the G/I the only component).

Not one per group: the GNSS positions fit at about 1 where rotor vibration takes the IMU
windows to 2.7, but what vibration leaves in a tactical IMU's errors is not white, and the
tilt the GNSS and the IMU determine together was as wrong as the joint factor said: with the
GNSS on its own factor the G/I roll's RMS of error/sigma went from 1.18 to 1.52 over six passes
(BENCHMARKS.md, Operating conditions). The planes are another sensor with its own misfit."""


def posterior_components(problem: Problem, cfg: TrajectoryAdjustmentConfig, solve: SolveResult) -> SolveResult:
    """``solve`` with the variance components (:data:`POSTERIOR_POOLS`) of ``problem``'s last solve
    where ``cfg`` asks for them (``variance_components``; the posterior then uses them:
    :func:`posterior_scale` is 1), else as it is."""
    if not cfg.variance_components or solve.redundancy <= 0:
        return solve
    return replace(solve, variance_components=problem.use_variance_components(POSTERIOR_POOLS))


def with_posterior(built: GnssImuProblem, result: GnssImuResult) -> GnssImuResult:
    """``result`` with posterior sigma of attitude (roll/pitch/yaw), position, velocity and IMU errors.

    ``built`` must be the problem whose last solve gave ``result``. Attitude and position sigma
    are computed at knots every ``covariance_interval_s`` (at most ``max_covariance_knots``);
    the covariances are scaled by :func:`posterior_scale`.
    """
    t = _time.perf_counter()
    p = built.problem
    p.expect_covariance(posterior_columns(built))
    solve = posterior_components(p, built.cfg, result.solve)
    vf = posterior_scale(solve)
    tk, sigma_rph, sigma_p, sigma_v = trajectory_sigma(p, built.blocks, built.grid, built.cfg, built.data.frame,
                                                       result.spline, scale=vf)
    e = result.imu_errors
    errors = ImuErrorEstimate(
        e.bias_grid, e.acc_bias, e.gyro_bias, e.acc_scale, e.gyro_scale,
        acc_bias_sigma=block_sigma(p, "acc_bias", vf), gyro_bias_sigma=block_sigma(p, "gyro_bias", vf),
        acc_scale_sigma=block_sigma(p, "acc_scale", vf)[0] if built.estimate_scale else None,
        gyro_scale_sigma=block_sigma(p, "gyro_scale", vf)[0] if built.estimate_scale else None,
        acc_misalignment=e.acc_misalignment, gyro_misalignment=e.gyro_misalignment,
        acc_misalignment_sigma=block_sigma(p, "acc_misalignment", vf)[0] if built.estimate_misalignment else None,
        gyro_misalignment_sigma=block_sigma(p, "gyro_misalignment", vf)[0] if built.estimate_misalignment else None,
        acc_temperature=e.acc_temperature, gyro_temperature=e.gyro_temperature,
        acc_temperature_sigma=block_sigma(p, "acc_temperature", vf)[0] if built.estimate_temperature else None,
        gyro_temperature_sigma=block_sigma(p, "gyro_temperature", vf)[0] if built.estimate_temperature else None,
    )
    # The posterior's own J and N (where the solve did not leave them formed) count as assembly
    # and normal matrix, not as covariance: BENCHMARKS.md's phases.
    formed = p.posterior_seconds()
    timings = dict(result.timings_s, covariance=_time.perf_counter() - t - formed["assembly"] - formed["normal"],
                   covariance_assembly=formed["assembly"], covariance_normal=formed["normal"])
    gnss_error = gnss_error_of(built, vf)
    if gnss_error is not None and gnss_error.segments is not None:
        for message in segment_warnings(gnss_error.segments, built.data.t0_gps):
            logger.warning(message)
    return replace(result, solve=solve, imu_errors=errors, sigma_time=tk, sigma_rph_rad=sigma_rph,
                   sigma_position_m=sigma_p, sigma_velocity_m_s=sigma_v, timings_s=timings, gnss_error=gnss_error)
