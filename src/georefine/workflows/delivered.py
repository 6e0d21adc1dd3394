"""The workflow on a delivered trajectory: an SBET (and ``smrmsg``) instead of raw GNSS and IMU (docs/ARCHITECTURE.md §4.9).

A project whose ``project.yaml`` has a ``trajectory`` section and no ``gnss``/``imu``
(``georefine import-strips`` writes one) runs the same steps 3-6 as a raw one. Steps 1-2 become:

* reading the SBET (seconds of the week, ``trajectory.gps_week``) and its ``smrmsg`` sigmas into
  ``w`` (:func:`read_delivered`);
* the "G/I" trajectory is the delivered one: the spline fitted to it, the SBET's faster motion
  on top, and the posterior of the prior alone (:func:`step_delivered`; written to ``gi/`` as a
  G/I adjustment is, so that G/I and G/I/L compare the same way in both modes);
* each G/I/L adjustment builds the delivered-trajectory problem
  (:mod:`georefine.adjustment.trajectory_prior`) instead of the GNSS/IMU one
  (:func:`build_delivered_problem`); the plane observations, the time offset and the outer
  iterations are those of :mod:`georefine.workflows.lidar`.

The functions take the workflow's ``NavigationData`` (``nav.prior`` set); they do not import it,
so that :mod:`georefine.workflows.navigation` can import this module.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from georefine.adjustment.gnss_imu import GnssImuResult
from georefine.adjustment.trajectory_prior import (
    TrajectoryPriorData,
    TrajectoryPriorProblem,
    build_trajectory_prior_problem,
    reference_from_sbet,
    solve_trajectory_prior,
)
from georefine.config import ProjectConfig, TrajectoryAdjustmentConfig
from georefine.errors import InputError
from georefine.geometry.frames import LocalFrame
from georefine.io.trajectory import SbetData, read_sbet
from georefine.progress import Progress, no_progress
from georefine.trajectory.highrate import HighRateMotion
from georefine.trajectory.sampled import interp_columns, trajectory_from_sbet
from georefine.trajectory.spline import KnotGrid, SplineTrajectory

log = logging.getLogger(__name__)

__all__ = ["build_delivered_problem", "delivered_sigmas", "read_delivered", "step_delivered", "warn_delivered_pull"]

def delivered_sigmas(cfg: ProjectConfig, sbet: SbetData, smrmsg=None) -> tuple[np.ndarray, np.ndarray]:
    """Position sigma (east, north, up; m) and attitude sigma (about east, north, up; rad) per SBET record.

    From the ``smrmsg`` records (:class:`~georefine.io.trajectory.SmrmsgData`: north/east/down
    position RMS, roll/pitch/heading RMS) interpolated to the SBET times, or
    ``trajectory.default_sigma_*``. Roll and pitch
    become one sigma for both horizontal axes (:mod:`georefine.adjustment.trajectory_prior`).
    """
    tc = cfg.trajectory
    n = len(sbet)
    if smrmsg is None:
        sp = np.tile([tc.default_sigma_position_m] * 3, (n, 1))
        h = np.radians(tc.default_sigma_roll_pitch_deg)
        st = np.tile([h, h, np.radians(tc.default_sigma_heading_deg)], (n, 1))
        return sp, st

    def at(x):
        return np.interp(sbet.time_gps, smrmsg.time_gps, x)

    ned, rph = smrmsg.sigma_ned_m, smrmsg.sigma_rph_rad
    sp = np.column_stack([at(ned[:, 1]), at(ned[:, 0]), at(ned[:, 2])])
    h = np.sqrt(0.5 * (at(rph[:, 0]) ** 2 + at(rph[:, 1]) ** 2))
    st = np.column_stack([h, h, at(rph[:, 2])])
    return sp, st


def read_delivered(root: Path, cfg: ProjectConfig) -> tuple[LocalFrame, float, TrajectoryPriorData]:
    """The SBET of ``trajectory.sbet`` in ``w`` (defined at its first record), the epoch, the sigmas.

    Raises
    ------
    InputError
        A bad SBET or smrmsg (the readers' errors), a wander angle other than 0, an smrmsg that
        does not cover the SBET, a non-positive sigma.
    """
    tc = cfg.trajectory
    path = root / tc.sbet
    sbet = read_sbet(path, gps_week=tc.gps_week)
    if len(sbet) < 4:
        raise InputError("the SBET has fewer than 4 records", path=path)
    if np.any(sbet.wander_rad != 0.0):
        k = int(np.flatnonzero(sbet.wander_rad != 0.0)[0])
        raise InputError("wander angle is not 0: only north-aligned SBETs are read", path=path, line=k + 1,
                         record_kind="record", field="wander", expected="0", found=f"{sbet.wander_rad[k]:.6f} rad")
    smrmsg = None
    if tc.smrmsg:
        from georefine.io.trajectory import read_smrmsg

        spath = root / tc.smrmsg
        smrmsg = read_smrmsg(spath, gps_week=tc.gps_week)
        t0s, t1s = float(smrmsg.time_gps[0]), float(smrmsg.time_gps[-1])
        t0, t1 = float(sbet.time_gps[0]), float(sbet.time_gps[-1])
        if t0s > t0 + 1.0 or t1s < t1 - 1.0:
            raise InputError("the smrmsg file does not cover the SBET", path=spath, field="time",
                             expected=f"GPS s {t0:.1f} to {t1:.1f} (the SBET)", found=f"{t0s:.1f} to {t1s:.1f}")
    sp, st = delivered_sigmas(cfg, sbet, smrmsg)
    if not (np.all(sp > 0) and np.all(st > 0)):
        raise InputError("non-positive accuracy in the smrmsg file", path=root / (tc.smrmsg or tc.sbet), field="rms",
                         expected="> 0")
    frame = LocalFrame(float(sbet.lat_rad[0]), float(sbet.lon_rad[0]), float(sbet.h_m[0]))
    if cfg.crs.reference_point is not None:
        rp = cfg.crs.reference_point
        frame = LocalFrame.from_degrees(rp.lat_deg, rp.lon_deg, rp.h_m)
    t0 = float(np.floor(sbet.time_gps[0]))
    traj = trajectory_from_sbet(sbet, frame, t0)
    # The SBET's angular rate is omega_ib_b; the spline's body rate is against w.
    omega = sbet.angular_rate_b - np.einsum("nji,j->ni", traj.R_w_b, frame.omega_ie_w)
    if not np.any(sbet.angular_rate_b):
        omega = None  # a file without rates: fit from the attitudes alone
    rate = 1.0 / float(np.median(np.diff(traj.time)))
    data = TrajectoryPriorData(frame, t0, traj.time, traj.p_w_b, traj.R_w_b, traj.v_w_b, omega, sp, st, rate)
    return frame, t0, data


def _grid(data: TrajectoryPriorData, tcfg: TrajectoryAdjustmentConfig) -> KnotGrid:
    n = int(np.floor((data.time[-1] - data.time[0]) / tcfg.knot_interval_s + 1e-9)) + 1
    return KnotGrid(float(data.time[0]), tcfg.knot_interval_s, n)


def step_delivered(nav, progress: Progress = no_progress) -> GnssImuResult:
    """Steps 1-2 on a delivered trajectory: its spline, faster motion and prior posterior (module docstring)."""
    cfg = nav.config
    tcfg = cfg.processing.trajectory
    progress("delivered trajectory", 0, 1)
    reference, high_rate = reference_from_sbet(nav.prior, _grid(nav.prior, tcfg))
    built = build_trajectory_prior_problem(nav.prior, cfg.trajectory, tcfg, reference)
    result = solve_trajectory_prior(built, high_rate=high_rate)
    progress("delivered trajectory", 1, 1)
    rot, off = high_rate.rms()
    log.info("delivered trajectory: %d samples, spline of %d knots; motion faster than the knots %.2f mdeg, %.1f mm RMS",
             nav.prior.time.size, reference.grid.n_knots, np.degrees(rot) * 1e3, off * 1e3)
    return result


def build_delivered_problem(nav, tcfg: TrajectoryAdjustmentConfig, spline: SplineTrajectory,
                            previous: GnssImuResult) -> tuple[TrajectoryPriorProblem, HighRateMotion]:
    """The delivered-trajectory problem on ``spline``'s grid, started at ``previous``; the motion to add.

    The reference is the SBET fitted on that grid (the first outer iteration may use coarser
    knots), so the SBET's motion faster than those knots comes with it.
    """
    reference, high_rate = reference_from_sbet(nav.prior, spline.grid)
    built = build_trajectory_prior_problem(nav.prior, nav.config.trajectory, tcfg, reference, initial=spline,
                                           errors=previous.sbet_errors)
    return built, high_rate


DELIVERED_PULL_SIGMAS = 3.0
"""Warn when the planes move the delivered trajectory by more than this many of its stated sigmas."""


def warn_delivered_pull(nav, result: GnssImuResult, records=()) -> None:
    """Warn, with the figures, when the estimated SBET error exceeds :data:`DELIVERED_PULL_SIGMAS` of its sigma.

    The ``smrmsg`` sigma (times ``trajectory.sigma_scale``) is what the post-processor claims;
    planes that need the trajectory moved further either found a real error the claim hides, or
    a model error (time offset, boresight, lever arm): both need a look.
    """
    e = result.sbet_errors
    tc = nav.config.trajectory
    tk = e.grid.times
    worst = []
    for est, sig, unit, f in ((e.position_m, nav.prior.sigma_p_w, "mm", 1e3),
                              (e.attitude_rad, nav.prior.sigma_theta_w, "mdeg", np.degrees(1.0) * 1e3)):
        s = tc.sigma_scale * interp_columns(tk, nav.prior.time, sig)
        ratio = np.abs(est) / s
        j, i = np.unravel_index(int(np.argmax(ratio)), ratio.shape)
        worst.append((float(ratio[j, i]), "ENU"[i], float(est[j, i] * f), float(s[j, i] * f), unit, float(tk[j])))
    ratio, axis, value, sigma, unit, t = max(worst)
    if ratio <= DELIVERED_PULL_SIGMAS:
        return
    log.warning(
        "the LiDAR planes move the delivered trajectory by %.1f times its stated accuracy: %s error %+.1f %s about/along "
        "%s at %.1f s against a sigma of %.1f %s (trajectory.smrmsg x trajectory.sigma_scale %.3g); outer iterations "
        "changed it by %s. Either the smrmsg sigmas are optimistic (raise trajectory.sigma_scale) or the model does "
        "not fit: check scanner.time_offset_s, the boresight, the lever arm and the scanner channels",
        ratio, "attitude" if unit == "mdeg" else "position", value, unit, axis, t, sigma, unit, tc.sigma_scale,
        ", ".join(f"{r.attitude_change_mdeg:.2f}" for r in records) + " mdeg" if records else "-",
    )
