"""Direct georeferencing of scanner-frame points (DESIGN §4.5 step 3/6).

``x_w = p_w_b(t) + R_w_b(t) (R_b_s x_s + p_b_s)``, vectorised over points. The trajectory is
interpolated per point (linear position, geodesic attitude) from its samples; at IMU rate the
interpolation error is far below the ranging noise.
"""

from __future__ import annotations

import numpy as np

from georefine.trajectory.sampled import Trajectory


def georeference(
    time: np.ndarray,
    xyz_s: np.ndarray,
    trajectory: Trajectory,
    p_b_s: np.ndarray,
    R_b_s: np.ndarray,
) -> np.ndarray:
    """Map scanner-frame points to the mapping frame ``w``.

    Parameters
    ----------
    time : (N,) float64
        Point times, seconds relative to ``trajectory.t0_gps``.
    xyz_s : (N, 3) float64
        Points in the scanner frame ``s`` (m).
    trajectory
        Body poses in ``w``; every time must lie inside its span.
    p_b_s : (3,) float64
        Scanner origin in the body frame (lever arm, m).
    R_b_s : (3, 3) float64
        Boresight rotation from ``s`` to ``b``.

    Returns
    -------
    (N, 3) float64
        Points in ``w`` (m).
    """
    p_w_b, R_w_b = trajectory.interpolate(time)
    x_b = np.asarray(xyz_s, dtype=float) @ np.asarray(R_b_s).T + np.asarray(p_b_s)
    return p_w_b + np.einsum("nij,nj->ni", R_w_b, x_b)
