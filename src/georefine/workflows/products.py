"""Trajectory products: SBET at IMU rate, trajectory CSV in the output CRS, JSON statistics.

The pipeline's trajectory product (docs/ARCHITECTURE.md §4.5 step 6) is an SBET (WGS84, wander angle 0,
NED velocity, roll/pitch/true heading, body specific force and angular rate) at the IMU's
sample times, so that any downstream tool can georeference with it; the CSV carries the
position in the output CRS, the attitude in degrees and the posterior 1-sigma.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.io.trajectory import (
    SbetData,
    TrajectoryTable,
    write_sbet,
    write_trajectory_csv,
)


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


def write_sbet_product(path: Path, frame: LocalFrame, t0_gps: float, time, p, v, R, f=None, w=None) -> None:
    write_sbet(path, sbet_from_states(frame, t0_gps, time, p, v, R, f, w), time_scale="gps")


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
