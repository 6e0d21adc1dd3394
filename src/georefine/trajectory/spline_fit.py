"""Least-squares fit of spline knots to a densely sampled trajectory (docs/ARCHITECTURE.md §4.5 step 1).

The initialisation filter delivers poses (and velocities, body rates) at IMU rate; the
adjustment needs knot states of the continuous-time trajectory of :mod:`.spline`. Position is
linear in its knot states (a banded least-squares problem with a small jerk regulariser);
orientation is fitted by a few Gauss-Newton iterations on ``Log(R_sample^T R(t))`` with the
analytic Jacobians of :func:`~georefine.trajectory.spline.eval_orientation`.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.linalg
import scipy.sparse

from georefine.geometry.rotation import exp_so3, log_so3, right_jacobian_inv
from georefine.trajectory.sampled import Trajectory, interp_columns
from georefine.trajectory.spline import (
    KnotGrid,
    SplineTrajectory,
    evaluate_terms,
    interval_terms,
    position_basis,
)

_log = logging.getLogger(__name__)

_CHUNK = 8192  # samples per block of the fit's normal equations



# ------------------------------------------------------------------------------- fit


def _accumulate(blocks: np.ndarray, rhs: np.ndarray, k: np.ndarray, JtJ: np.ndarray, Jtr: np.ndarray) -> None:
    """Add per-sample normal-equation terms to their interval blocks (``k`` sorted).

    The sum over the samples of each interval is a product with a sparse 0/1 matrix, which
    is several times faster than ``np.add.reduceat`` on these shapes.
    """
    k0, k1 = int(k[0]), int(k[-1]) + 1
    indptr = np.searchsorted(k, np.arange(k0, k1 + 1))
    S = scipy.sparse.csr_matrix((np.ones(k.size), np.arange(k.size), indptr), shape=(k1 - k0, k.size))
    blocks[k0:k1] += (S @ JtJ.reshape(k.size, -1)).reshape((k1 - k0,) + blocks.shape[1:])
    rhs[k0:k1] += (S @ Jtr.reshape(k.size, -1)).reshape((k1 - k0,) + rhs.shape[1:])


def _solve_block_tridiagonal(blocks: np.ndarray, rhs: np.ndarray, m: int, damping: float = 0.0) -> np.ndarray:
    """Solve the SPD system assembled from interval blocks.

    ``blocks`` (K-1, 2m, 2m) couple the ``m`` unknowns of knots k and k+1 (local order
    [knot k, knot k+1]); ``rhs`` (K-1, 2m, r). The matrix is banded (half-bandwidth 2m-1),
    so a banded Cholesky solves it in O(K m³). Returns (K, m, r).
    """
    n_int = blocks.shape[0]
    n = (n_int + 1) * m
    bw = 2 * m - 1
    ab = np.zeros((bw + 1, n))  # upper banded storage: ab[bw + i - j, j] = N[i, j]
    base = np.arange(n_int) * m
    for r in range(2 * m):
        for c in range(r, 2 * m):
            ab[bw + r - c, base + c] += blocks[:, r, c]
    if damping > 0.0:
        ab[bw] += damping * max(float(np.mean(ab[bw])), 1e-300)
    b = np.zeros((n, rhs.shape[2]))
    for r in range(2 * m):
        b[base + r] += rhs[:, r, :]
    x = scipy.linalg.solveh_banded(ab, b, check_finite=False)
    return x.reshape(n_int + 1, m, -1)


def _fit_position(grid, time, k, u, p, v, sigma_p, sigma_v, jerk_psd) -> np.ndarray:
    """Knot states (K, 3, 3) ``[p, v, a]`` per knot, by linear least squares."""
    dt = grid.dt
    blocks = np.zeros((grid.n_intervals, 6, 6))
    rhs = np.zeros((grid.n_intervals, 6, 3))
    # Unknowns scaled to [p, dt v, dt² a] (all metres) for conditioning.
    unscale = np.array([1.0, dt, dt * dt, 1.0, dt, dt * dt])
    for s in range(0, time.size, _CHUNK):
        sl = slice(s, s + _CHUNK)
        w = position_basis(u[sl], dt, 0) / unscale / sigma_p
        JtJ, Jtr = w[:, :, None] * w[:, None, :], w[:, :, None] * (p[sl] / sigma_p)[:, None, :]
        if v is not None:
            w1 = position_basis(u[sl], dt, 1) / unscale / sigma_v
            JtJ += w1[:, :, None] * w1[:, None, :]
            Jtr += w1[:, :, None] * (v[sl] / sigma_v)[:, None, :]
        _accumulate(blocks, rhs, k[sl], JtJ, Jtr)
    # White-noise jerk prior: int |p'''|² dt / q over each interval (3-point Gauss-Legendre
    # is exact for the quartic integrand). It fixes states in data gaps; where there are
    # samples it acts only above f = (q n / sigma²)^(1/6) / 2 pi (n samples per second):
    # ~18 Hz for the defaults at 200 Hz, beyond what the knots resolve.
    gx, gw = np.polynomial.legendre.leggauss(3)
    w3 = position_basis(0.5 * (gx + 1.0), dt, 3) / unscale
    blocks += (w3.T * (0.5 * gw * dt / jerk_psd)) @ w3
    x = _solve_block_tridiagonal(blocks, rhs, 3)
    return x / np.array([1.0, dt, dt * dt])[None, :, None]


def _initial_rates(time, R, omega, t_knots) -> np.ndarray:
    """Knot body rates interpolated from the samples (or from their Log differences)."""
    if omega is None:
        omega = log_so3(np.swapaxes(R[:-1], 1, 2) @ R[1:]) / np.diff(time)[:, None]
        time = 0.5 * (time[1:] + time[:-1])
    return interp_columns(t_knots, time, omega)


def fit_spline(
    grid: KnotGrid,
    time: np.ndarray,
    p_w_b: np.ndarray,
    R_w_b: np.ndarray,
    v_w_b: np.ndarray | None = None,
    omega_wb_b: np.ndarray | None = None,
    *,
    sigma_p_m: float = 0.01,
    sigma_v_mps: float = 0.01,
    sigma_theta_rad: float = 1e-3,
    sigma_omega_radps: float = 1e-3,
    jerk_psd_m2ps5: float = 1e6,
    max_iterations: int = 5,
    t0_gps: float = 0.0,
) -> SplineTrajectory:
    """Least-squares fit of the knot states to a densely sampled trajectory.

    Meant for initialising the adjustment from the EKF/RTS output (docs/ARCHITECTURE.md §4.5 step 1).

    Parameters
    ----------
    grid : KnotGrid
        Knots; every sample time must lie in its span.
    time : (N,) float
        Strictly increasing sample times (s).
    p_w_b : (N, 3), R_w_b : (N, 3, 3)
        Sampled positions (m) and attitudes.
    v_w_b : (N, 3), optional
        Sampled velocities (m/s), fitted too when given.
    omega_wb_b : (N, 3), optional
        Sampled body rates (rad/s), fitted too when given.
    sigma_p_m, sigma_v_mps, sigma_theta_rad, sigma_omega_radps : float
        Standard deviations weighting the four kinds of samples.
    jerk_psd_m2ps5 : float
        PSD ``q`` of the white-noise jerk prior ``int |p'''|² dt / q`` regularising the
        position fit (keeps data gaps solvable; negligible elsewhere).
    max_iterations : int
        Gauss-Newton iterations of the orientation fit (stops earlier on convergence).
    t0_gps : float
        Dataset epoch, passed to the result.

    Returns
    -------
    SplineTrajectory

    Notes
    -----
    Position (and velocity) are linear in the knot states: per axis the normal equations
    are block-tridiagonal (3 unknowns per knot, weights from :func:`position_basis`) and are
    solved by banded Cholesky; the design matrix is never formed, memory is O(K).
    Orientation: ``R_k`` start from the geodesic interpolation of the samples at the knot
    times, ``omega_k`` from the sampled rates (or Log differences of the samples); then
    Gauss-Newton on ``r = Log(R_sample^T R(t)) / sigma_theta`` (Jacobian
    ``Jr^-1(r) dR/dx``) and ``(omega(t) - omega_sample) / sigma_omega`` with the analytic
    Jacobians of :func:`eval_orientation`, a 1e-9 relative Levenberg damping that leaves
    knots without data at their initial values, and right updates ``R_k <- R_k Exp(dtheta)``.
    """
    time = np.asarray(time, dtype=float)
    n = time.size
    if time.ndim != 1 or n < 3 or not np.all(np.diff(time) > 0):
        raise ValueError("time must be 1-D, strictly increasing, with at least 3 samples")
    arrays = {"p_w_b": p_w_b, "R_w_b": R_w_b, "v_w_b": v_w_b, "omega_wb_b": omega_wb_b}
    for name, arr in arrays.items():
        shape = (n, 3, 3) if name == "R_w_b" else (n, 3)
        if arr is not None and np.shape(arr) != shape:
            raise ValueError(f"{name} must have shape {shape}, got {np.shape(arr)}")
    p_w_b, R_w_b, v_w_b, omega_wb_b = (None if a is None else np.asarray(a, dtype=float) for a in arrays.values())
    k, u = grid.locate(time)

    p_ref = p_w_b[0]  # fit about the first sample: keeps the mm digits of large coordinates
    x = _fit_position(grid, time, k, u, p_w_b - p_ref, v_w_b, sigma_p_m, sigma_v_mps, jerk_psd_m2ps5)
    t_knots = np.clip(grid.knot_times, time[0], time[-1])
    _, R = Trajectory(time, p_w_b, R_w_b).interpolate(t_knots)
    W = _initial_rates(time, R_w_b, omega_wb_b, t_knots)
    R, W = _fit_orientation(grid, k, u, R_w_b, omega_wb_b, R, W, sigma_theta_rad, sigma_omega_radps, max_iterations)
    return SplineTrajectory(grid, x[:, 0] + p_ref, x[:, 1], x[:, 2], R, W, t0_gps=t0_gps)


def _fit_orientation(grid, k, u, R_s, omega_s, R, W, sigma_theta, sigma_omega, max_iterations):
    """Gauss-Newton refinement of the knot attitudes and rates (see :func:`fit_spline`)."""
    dt = grid.dt
    for it in range(max_iterations):
        terms = interval_terms(R[:-1], R[1:], W[:-1], W[1:], dt, True)
        blocks = np.zeros((grid.n_intervals, 12, 12))
        rhs = np.zeros((grid.n_intervals, 12, 1))
        cost = 0.0
        for s in range(0, k.size, _CHUNK):
            sl = slice(s, s + _CHUNK)
            ks = k[sl]
            ev = evaluate_terms(terms, ks, R[ks], u[sl], dt, omega_s is not None, True, ks)
            r = log_so3(np.swapaxes(R_s[sl], 1, 2) @ ev.R_w_b)
            J = right_jacobian_inv(r) @ ev.jacobians.dR / sigma_theta
            r = r / sigma_theta
            if omega_s is not None:
                J = np.concatenate([J, ev.jacobians.domega / sigma_omega], axis=1)
                r = np.concatenate([r, (ev.omega_wb_b - omega_s[sl]) / sigma_omega], axis=1)
            Jt = np.ascontiguousarray(np.swapaxes(J, 1, 2))
            _accumulate(blocks, rhs, ks, Jt @ J, Jt @ r[:, :, None])
            cost += float(np.sum(r * r))
        step = -_solve_block_tridiagonal(blocks, rhs, 6, damping=1e-9)[:, :, 0]
        R = R @ exp_so3(step[:, :3])
        W = W + step[:, 3:]
        size = max(np.abs(step[:, :3]).max(), dt * np.abs(step[:, 3:]).max())
        _log.debug("orientation fit iteration %d: cost %.6g, max step %.3g rad", it, cost, size)
        if size < 1e-8:  # Gauss-Newton converges fast: the next step would be negligible
            break
    return R, W
