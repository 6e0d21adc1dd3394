"""A trajectory sampled at discrete times, with vectorised interpolation.

This is the container every stage exchanges (docs/ARCHITECTURE.md §2 names): body poses in the mapping
frame ``w`` at increasing times. Interpolation is linear in position and geodesic (SLERP) in
attitude, which at IMU rate (>= 100 Hz) is accurate to micrometres for aircraft motion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from georefine.errors import InputError
from georefine.geometry.rotation import exp_so3, log_so3


def interp_columns(t: np.ndarray, time: np.ndarray, series: np.ndarray) -> np.ndarray:
    """The three columns of ``series`` (N, 3), sampled at increasing ``time`` (N,), linearly
    interpolated at ``t`` (M,): (M, 3), held constant beyond the ends (``np.interp``)."""
    return np.column_stack([np.interp(t, time, series[:, i]) for i in range(3)])


@dataclass(frozen=True)
class Trajectory:
    """Body poses in ``w``.

    Attributes
    ----------
    time : (N,) float64
        Seconds relative to the dataset epoch ``t0_gps``; strictly increasing.
    p_w_b : (N, 3) float64
        Position of the IMU in ``w`` (m).
    R_w_b : (N, 3, 3) float64
        Attitude of the IMU body frame.
    t0_gps : float
        Dataset epoch in GPS seconds.
    v_w_b : (N, 3) float64 or None
        Velocity in ``w`` (m/s), if known.
    """

    time: np.ndarray
    p_w_b: np.ndarray
    R_w_b: np.ndarray
    t0_gps: float = 0.0
    v_w_b: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = self.time.shape[0]
        if self.time.ndim != 1 or n < 2:
            raise ValueError(f"time must be 1-D with at least 2 samples, got shape {self.time.shape}")
        if self.p_w_b.shape != (n, 3) or self.R_w_b.shape != (n, 3, 3):
            raise ValueError(f"shape mismatch: time {self.time.shape}, p_w_b {self.p_w_b.shape}, R_w_b {self.R_w_b.shape}")
        if self.v_w_b is not None and self.v_w_b.shape != (n, 3):
            raise ValueError(f"v_w_b must have shape {(n, 3)}, got {self.v_w_b.shape}")
        if not np.all(np.diff(self.time) > 0):
            k = int(np.argmin(np.diff(self.time)))
            raise ValueError(f"time must increase strictly: sample {k + 1} ({self.time[k + 1]}) after {self.time[k]}")

    @property
    def span(self) -> tuple[float, float]:
        """First and last time (s, relative to ``t0_gps``)."""
        return float(self.time[0]), float(self.time[-1])

    def contains(self, t: np.ndarray) -> np.ndarray:
        """Boolean mask of times inside the trajectory's span (no extrapolation)."""
        t = np.asarray(t, dtype=float)
        return (t >= self.time[0]) & (t <= self.time[-1])

    def interpolate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pose ``(p_w_b (M,3), R_w_b (M,3,3))`` at times ``t`` (M,) inside the span.

        Raises
        ------
        InputError
            If any time lies outside the span (never extrapolated silently).
        """
        t = np.asarray(t, dtype=float)
        inside = self.contains(t)
        if not np.all(inside):
            bad = t[~inside]
            raise InputError(
                f"{bad.size} times outside the trajectory span",
                field="time",
                expected=f"[{self.time[0]:.3f}, {self.time[-1]:.3f}] s",
                found=f"{bad.min():.3f} .. {bad.max():.3f} s",
            )
        k = np.clip(np.searchsorted(self.time, t, side="right") - 1, 0, self.time.size - 2)
        u = (t - self.time[k]) / (self.time[k + 1] - self.time[k])
        p = self.p_w_b[k] + u[:, None] * (self.p_w_b[k + 1] - self.p_w_b[k])
        R0 = self.R_w_b[k]
        dphi = log_so3(np.swapaxes(R0, 1, 2) @ self.R_w_b[k + 1])
        R = R0 @ exp_so3(u[:, None] * dphi)
        return p, R


def trajectory_from_sbet(sbet, frame, t0_gps: float) -> Trajectory:
    """Convert an SBET (:class:`georefine.io.trajectory.SbetData`, wander angle 0) to ``w``.

    Parameters
    ----------
    sbet
        SBET records (absolute GPS times, WGS84 radians, NED roll/pitch/true heading).
    frame : georefine.geometry.frames.LocalFrame
        The mapping frame ``w``.
    t0_gps
        Dataset epoch (GPS seconds); the returned times are relative to it.
    """
    p_w = frame.from_geodetic(sbet.lat_rad, sbet.lon_rad, sbet.h_m)
    rph = np.column_stack([sbet.roll_rad, sbet.pitch_rad, sbet.heading_rad])
    R_w_b = frame.R_w_b_from_rph(p_w, rph)
    v_w = None
    if np.all(sbet.wander_rad == 0.0):
        R_w_n = frame.R_w_n(sbet.lat_rad, sbet.lon_rad)
        v_w = np.einsum("nij,nj->ni", R_w_n, sbet.velocity_wander)
    return Trajectory(np.asarray(sbet.time_gps) - t0_gps, p_w, R_w_b, t0_gps=t0_gps, v_w_b=v_w)
