"""What a single-flight run and a run of several flights share (docs/ARCHITECTURE.md §4.5).

:mod:`georefine.workflows.lidar` runs one flight, :mod:`georefine.workflows.flights` several in one
G/I/L; each flight of the latter is cached, started and reported as a single-flight run of that
flight would be, so that both read these from one place:

* :func:`navigation_key` and :func:`stage_gnss_imu`: steps 1-2 and their cache key (a run of one
  flight alone with the same cache resumes the G/I a run of all flights computed, and back);
* :func:`outer_knot_interval` and :func:`vibrating`: the coarse first outer iteration, and the
  vibration that rules it out;
* :func:`adjustment_report`: ``adjustment.json`` of an adjustment.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from georefine.adjustment.gnss_imu import GnssImuResult, unmodelled_temperature
from georefine.adjustment.observations.plane import ENCODER_HALF_WIDTH_DEG
from georefine.adjustment.upsampling import high_rate_share
from georefine.config import ProjectConfig
from georefine.io.run_metrics import AdjustmentReport, FrameOrigin, LidarTimeOffset
from georefine.progress import Progress, no_progress
from georefine.workflows.cache import StepCache, StepRunner, file_stamp
from georefine.workflows.delivered import step_delivered
from georefine.workflows.gil import LidarAdjustment
from georefine.workflows.navigation import NavigationData, step_adjust_gnss_imu, step_initialise

log = logging.getLogger(__name__)

__all__ = ["VIBRATION_SHARE", "adjustment_report", "frame_crs", "navigation_key", "outer_knot_interval",
           "stage_gnss_imu", "vibrating"]

VIBRATION_SHARE = 0.5
"""A platform vibrates when at least this share of the G/I's rebuilt high-rate readings stands out
of the IMU noise (:func:`~georefine.adjustment.upsampling.high_rate_share`). Measured on
``corridor-tiny``: 0.024 with a MEMS IMU, 0.109 with a navigation-grade one (its noise is so low
that the smooth motion between the knots stands out), 1.00 with rotor vibration. Above
:data:`~georefine.adjustment.upsampling.MIN_SIGNIFICANT_SHARE` (0.1) the G/I re-solves; the
smooth navigation-grade flight keeps its coarse first outer iteration, which there removes more of
the world tilt (pitch 0.13 / 0.06 mdeg against 0.23 with fine knots throughout)."""


def frame_crs(cfg: ProjectConfig) -> dict:
    """The ``crs`` section as the steps before the final georeferencing see it: the geoid grid
    changes only the final point clouds' heights (step 6's key holds it)."""
    return cfg.crs.model_dump(exclude={"geoid_grid", "vertical_epsg"})


def navigation_key(cfg: ProjectConfig, root: Path) -> str:
    """Key of steps 1-2: the GNSS and IMU files and their configuration (no data read); or the delivered trajectory's."""
    if cfg.delivered_trajectory:
        tc = cfg.trajectory
        files = [file_stamp(root / f, root) for f in (tc.sbet, tc.smrmsg) if f]
        return StepCache.key("delivered", files, frame_crs(cfg), tc.model_dump(),
                             cfg.processing.trajectory.model_dump())
    files = [file_stamp(root / f, root) for f in [*cfg.gnss.files, cfg.imu.file, cfg.gnss.smrmsg] if f]
    return StepCache.key(
        "gi", files, frame_crs(cfg), cfg.gnss.model_dump(), cfg.imu.model_dump(),
        cfg.processing.filter.model_dump(), cfg.processing.trajectory.model_dump(),
    )


def stage_gnss_imu(steps: StepRunner, nav: NavigationData, progress: Progress = no_progress) -> tuple[GnssImuResult, str]:
    """Steps 1-2 (filter, G/I adjustment), or their cached result; and the cache key."""

    def compute() -> GnssImuResult:
        if nav.prior is not None:
            return step_delivered(nav, progress)
        progress("initialisation filter", 0, 1)
        with steps.timed("filter"):
            filt = step_initialise(nav)
        progress("initialisation filter", 1, 1)
        result = step_adjust_gnss_imu(nav, filt, progress)
        progress("G/I adjustment", 1, 1)  # it reports iterations of its limit; it ended here
        return result

    note = None if nav.prior is not None else unmodelled_temperature(
        nav.gnss.imu_temperature, nav.config.imu.errors, nav.config.processing.trajectory)
    if note is not None:  # said whether the G/I is computed or read from the cache
        log.warning(note)
    key = navigation_key(nav.config, nav.root)
    return steps.cached("gi", key, compute, timing="gi_adjustment"), key


def outer_knot_interval(lcfg, knot_interval_s: float, iteration: int, vibrating: bool = False) -> float | None:
    """The coarser knot interval of outer iteration ``iteration`` (only the first, and only when
    more may follow), or None for the configured ``knot_interval_s``
    (``processing.lidar.first_knot_interval_s``).

    Never on a ``vibrating`` platform (the G/I's up-sampling found vibration, §4.6): the motion
    rebuilt above the coarse knots (2 Hz at 0.25 s) holds a band the configured knots follow,
    and the fine iteration after it does not get that band back. A 6.5 Hz rotor line, aliased
    by the 0.25 s knots to 2.5 Hz, stayed in the trajectory: 0.6-0.8 mdeg of roll and pitch
    error with a navigation-grade IMU, against 0.2 with fine knots throughout (BENCHMARKS.md,
    Operating conditions)."""
    fine, coarse = knot_interval_s, lcfg.first_knot_interval_s
    if (iteration == 1 and not vibrating and lcfg.outer_iterations > 1 and coarse is not None
            and coarse > fine * (1.0 + 1e-6)):
        return float(coarse)
    return None


def vibrating(nav: NavigationData, gi: GnssImuResult) -> bool:
    """Whether the G/I's up-sampling found vibration in the raw IMU (§4.6), asked only where
    :func:`outer_knot_interval` would start coarse (logged when it then does not). A delivered
    trajectory's faster motion comes from its SBET (§4.9) and is not tested here."""
    if nav.prior is not None or gi.high_rate is None:
        return False
    if outer_knot_interval(nav.config.processing.lidar, nav.config.processing.trajectory.knot_interval_s, 1) is None:
        return False
    share = high_rate_share(nav.gnss, gi)
    if share < VIBRATION_SHARE:
        return False
    log.info("vibration: %.0f %% of the rebuilt IMU readings stand out of the noise; every outer iteration "
             "on the configured knots (no coarse first iteration)", 100 * share)
    return True


def adjustment_report(nav: NavigationData, adj: GnssImuResult, solution: str,
                      lidar: LidarAdjustment | None = None) -> AdjustmentReport:
    """``adjustment.json`` (:class:`~georefine.io.run_metrics.AdjustmentReport`): statistics, IMU
    errors and timings of the adjustment ``adj``, and with ``lidar`` (G/I/L, hybrid) the boresight
    and the LiDAR time offset."""
    bs = bs_sigma = offset = None
    if lidar is not None and lidar.boresight_deg is not None:
        bs = tuple(float(v) for v in lidar.boresight_deg)
        bs_sigma = None if lidar.boresight_sigma_mdeg is None else tuple(float(v) for v in lidar.boresight_sigma_mdeg)
    if lidar is not None:
        sigma, gnss = lidar.time_offset_sigma_s, lidar.time_offset_gnss_sigma_s
        offset = LidarTimeOffset(
            nav.config.scanner.time_offset_s, float(lidar.time_offset_s), None if sigma is None else sigma * 1e3,
            None if gnss is None or not np.isfinite(gnss) else gnss * 1e3,
            None if lidar.time_offset_start is None else lidar.time_offset_start.prior_s, lidar.time_offset_held)
    return AdjustmentReport(
        solution, nav.t0_gps, dict(adj.timings_s), adjustment=adj.solve.to_dict(),
        imu_errors=None if adj.imu_errors is None else adj.imu_errors.to_dict(),
        # a delivered trajectory: its estimated error (§4.9); the GNSS error that lasts minutes (§4.3)
        sbet_errors=None if adj.sbet_errors is None else adj.sbet_errors.to_dict(),
        gnss_error=None if adj.gnss_error is None else adj.gnss_error.to_dict(),
        boresight_deg=bs, boresight_sigma_mdeg=bs_sigma, lidar_time_offset=offset,
        project=str(Path(nav.root).resolve()), frame=FrameOrigin.of(nav.frame),
        range_calibration=None if lidar is None else range_calibration_record(lidar),
        channel_angles=None if lidar is None else channel_angles_record(lidar),
        encoder_error=None if lidar is None else encoder_error_record(lidar))


def range_calibration_record(lidar) -> dict | None:
    """``adjustment.json``'s ``range_calibration`` of a G/I/L that estimated it, else None."""
    if getattr(lidar, "range_calibration", None) is None:
        return None
    (r0, k), sig = lidar.range_calibration, lidar.range_calibration_sigma
    return {"offset_m": round(r0, 6), "scale_ppm": round(k * 1e6, 3),
            "offset_sigma_m": None if sig is None else round(sig[0], 6),
            "scale_sigma_ppm": None if sig is None else round(sig[1] * 1e6, 3)}


def encoder_error_record(lidar) -> dict | None:
    """``adjustment.json``'s ``encoder_error`` of a G/I/L that estimated it, else None: the coefficients of the
    Legendre terms ``P_1 .. P_4`` of ``alpha / half_width_deg`` and their sigma (mdeg)."""
    if getattr(lidar, "encoder", None) is None:
        return None
    e = np.degrees(lidar.encoder) * 1e3
    sig = None if lidar.encoder_sigma is None else np.degrees(lidar.encoder_sigma) * 1e3
    return {"terms_mdeg": np.round(e, 4).tolist(), "terms_sigma_mdeg": None if sig is None else np.round(sig, 4).tolist(),
            "half_width_deg": ENCODER_HALF_WIDTH_DEG}


def channel_angles_record(lidar) -> dict | None:
    """``adjustment.json``'s ``channel_angles`` of a G/I/L that estimated them, else None: per channel (index =
    the LAS scanner channel) the tilt and scan-angle error and their sigma (mdeg)."""
    if getattr(lidar, "channel_angles", None) is None:
        return None
    a = np.degrees(lidar.channel_angles) * 1e3
    sig = None if lidar.channel_angles_sigma is None else np.degrees(lidar.channel_angles_sigma) * 1e3
    return {"tilt_mdeg": np.round(a[:, 0], 4).tolist(), "scan_angle_mdeg": np.round(a[:, 1], 4).tolist(),
            "tilt_sigma_mdeg": None if sig is None else np.round(sig[:, 0], 4).tolist(),
            "scan_angle_sigma_mdeg": None if sig is None else np.round(sig[:, 1], 4).tolist()}
