"""Trajectory products: SBET at IMU rate with its companion and accuracy files, trajectory CSV
in the output CRS (docs/ARCHITECTURE.md §4.5 step 6).

The pipeline's trajectory product is an SBET (WGS84, wander angle 0, NED velocity,
roll/pitch/true heading, body specific force and angular rate) at the IMU's sample times, in
seconds of the GPS week as POSPac and Inertial Explorer write it, so that any downstream tool
can georeference with it. Beside it: the companion ``<name>.json`` stating the GPS week and
the output CRS, and the POSPac-style accuracy file ``smrmsg_<stem>.out`` with the posterior
1-sigma (formats in :mod:`georefine.io.trajectory`). The CSV carries the position in the
output CRS, the attitude in degrees and the posterior 1-sigma.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.io.files import week_from_gps_seconds
from georefine.io.trajectory import (
    SbetCompanion,
    SbetData,
    SmrmsgData,
    TrajectoryTable,
    smrmsg_path,
    write_sbet,
    write_sbet_companion,
    write_smrmsg,
    write_trajectory_csv,
)

log = logging.getLogger(__name__)


def sbet_from_states(
    frame: LocalFrame,
    t0_gps: float,
    time: np.ndarray,
    p_w_b: np.ndarray,
    v_w_b: np.ndarray,
    R_w_b: np.ndarray,
    f_ib_b: np.ndarray | None = None,
    omega_ib_b: np.ndarray | None = None,
) -> SbetData:
    """SBET records of body states in ``w`` at ``time`` (s relative to ``t0_gps``)."""
    lat, lon, h = frame.to_geodetic(p_w_b)
    R_n_w = np.swapaxes(frame.R_w_n(lat, lon), 1, 2)
    v_n = np.einsum("nij,nj->ni", R_n_w, v_w_b)
    rph = frame.rph_from_R_w_b(p_w_b, R_w_b)
    n = time.size
    return SbetData(
        time_gps=t0_gps + time, lat_rad=lat, lon_rad=lon, h_m=h, velocity_wander=v_n,
        roll_rad=rph[:, 0], pitch_rad=rph[:, 1], heading_rad=rph[:, 2], wander_rad=np.zeros(n),
        accel_b=np.zeros((n, 3)) if f_ib_b is None else f_ib_b,
        angular_rate_b=np.zeros((n, 3)) if omega_ib_b is None else omega_ib_b,
    )


def body_kinematics(frame: LocalFrame, spline, time: np.ndarray) -> tuple[np.ndarray, ...]:
    """Pose, velocity, specific force and angular rate of a spline trajectory at ``time``."""
    p = spline.position(time, 0)
    v = spline.position(time, 1)
    a = spline.position(time, 2)
    R, omega_wb, _ = spline.orientation(time, rate=True)
    Rt = np.swapaxes(R, 1, 2)
    W = frame.omega_ie_w
    f = np.einsum("nij,nj->ni", Rt, a + 2.0 * np.cross(W, v) - frame.gravity_w(p))
    omega_ib = omega_wb + Rt @ W
    return p, v, R, f, omega_ib


def accuracy_from_sigmas(
    frame: LocalFrame, t0_gps: float, time: np.ndarray, p_w_b: np.ndarray, sigma_p_w: np.ndarray,
    sigma_v_w: np.ndarray, sigma_rph_rad: np.ndarray,
) -> SmrmsgData:
    """Accuracy records (``smrmsg``) of posterior sigmas at ``time`` (s relative to ``t0_gps``).

    Position and velocity sigmas are per ``w`` axis (east, north, up at the reference point);
    their diagonal covariance is rotated into the local north-east-down frame at ``p_w_b``
    (correlations between the axes are not in the sigmas and not in the file).
    """
    R_n_w = np.swapaxes(frame.R_w_n_at(p_w_b), 1, 2)

    def ned(sigma_w: np.ndarray) -> np.ndarray:
        return np.sqrt(np.einsum("nij,nj->ni", R_n_w**2, np.asarray(sigma_w, dtype=float) ** 2))

    return SmrmsgData(t0_gps + np.asarray(time, dtype=float), ned(sigma_p_w), ned(sigma_v_w), sigma_rph_rad)


def write_sbet_product(
    path: Path, frame: LocalFrame, t0_gps: float, time, p, v, R, f=None, w=None, *,
    output_epsg: int | None = None, accuracy: SmrmsgData | None = None,
) -> None:
    """``path`` (SBET, seconds of the GPS week), its companion ``path.json`` and, with
    ``accuracy``, the accuracy file ``smrmsg_<stem>.out`` beside it (same week)."""
    sbet = sbet_from_states(frame, t0_gps, time, p, v, R, f, w)
    week = int(week_from_gps_seconds(sbet.time_gps[0])[0])
    write_sbet(path, sbet, time_scale="week")
    accuracy_file = None
    if accuracy is not None:
        accuracy_file = write_smrmsg(smrmsg_path(path), accuracy, gps_week=week).name
    write_sbet_companion(path, SbetCompanion(week, output_epsg, accuracy_file))


def write_csv_product(
    path: Path,
    frame: LocalFrame,
    crs: OutputCRS,
    t0_gps: float,
    time: np.ndarray,
    p_w_b: np.ndarray,
    R_w_b: np.ndarray,
    sigma_rph_rad: np.ndarray | None = None,
    sigma_p_m: np.ndarray | None = None,
) -> None:
    """Trajectory CSV: time, position in the output CRS, roll/pitch/heading (deg), 1-sigma."""
    xyz = crs.from_w(frame, p_w_b)
    rph = frame.rph_from_R_w_b(p_w_b, R_w_b)
    sig_xyz = None
    if sigma_p_m is not None:
        sig_xyz = sigma_p_m  # w is ENU; the output CRS axes agree with it to the meridian convergence
    table = TrajectoryTable(t0_gps + time, xyz, rph, sigma_xyz_m=sig_xyz, sigma_rpy_rad=sigma_rph_rad,
                            crs=f"EPSG:{crs.epsg}")
    write_trajectory_csv(path, table)

