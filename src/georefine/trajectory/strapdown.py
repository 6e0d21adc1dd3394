"""Strapdown inertial mechanisation in the mapping frame ``w`` (docs/ARCHITECTURE.md §4.1).

``w`` is Earth-fixed, so the navigation equations are exact with the Earth rate and the
normal gravity (which includes the centrifugal acceleration) as the only extra terms::

    R_w_b' = R_w_b [omega_ib_b - R_w_b^T omega_ie_w]x
    v_w'   = R_w_b f_ib_b - 2 omega_ie_w x v_w + g_w(p_w)
    p_w'   = v_w

Integration: a fourth-order Runge-Kutta-Munthe-Kaas scheme (Munthe-Kaas 1998; Iserles et
al. 2000, "Lie-group methods") on SO(3) x R^3 x R^3. The attitude stages are
``R_i = R_k Exp(theta_i)`` with ``theta' = Jr^-1(theta) omega`` (right perturbation; the
right-Jacobian inverse carries the coning correction), velocity and position are the
classical RK4 stages. It needs the IMU at both ends and at the middle of each interval:

* instantaneous samples (default): the mid values are interpolated by a cubic through the
  four samples around the interval (Lagrange weights for the actual, possibly jittered,
  times);
* increments (``increments=True``): ``dtheta_k = int omega dt`` and ``dv_k = int f dt`` over
  ``(t_k-1, t_k]`` in the body frame (what IMUs with integrating outputs deliver; sculling
  and coning are handled by the scheme). The rates at the sample times and midpoints are
  the derivatives of a quartic (cubic for the midpoints) through the cumulative sums.

Gravity is evaluated at every stage position with njit helpers equivalent to
:mod:`georefine.geometry.earth` (tested for equality). With an error-free IMU at 200 Hz the
scheme reproduces a helicopter trajectory to well below a millimetre and a microdegree over
a minute; the cost is about a microsecond per step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from georefine.geometry import earth
from georefine.geometry.frames import LocalFrame
from georefine.geometry.rotation import exp_so3_into

_A, _B = earth.WGS84_A, earth.WGS84_B
_E2, _EP2, _F = earth.WGS84_E2, earth.WGS84_EP2, earth.WGS84_F
_GAMMA_E, _K, _M = earth.GAMMA_E, earth.SOMIGLIANA_K, earth.GRAVITY_M


@dataclass(frozen=True)
class StrapdownState:
    """Navigation state in ``w``: ``p_w_b`` (3,) m, ``v_w_b`` (3,) m/s, ``R_w_b`` (3,3)."""

    p_w_b: np.ndarray
    v_w_b: np.ndarray
    R_w_b: np.ndarray


@dataclass(frozen=True)
class StrapdownResult:
    """Integrated trajectory at the IMU sample times: ``time`` (N,) s, ``p_w_b`` (N,3) m,
    ``v_w_b`` (N,3) m/s, ``R_w_b`` (N,3,3)."""

    time: np.ndarray
    p_w_b: np.ndarray
    v_w_b: np.ndarray
    R_w_b: np.ndarray


# ---------------------------------------------------------------------------- njit kernels
@nb.njit(cache=True)
def _ecef_to_geodetic(x, y, z):
    """Same algorithm as :func:`earth.ecef_to_geodetic` (Bowring start, two iterations)."""
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    theta = np.arctan2(z * _A, p * _B)
    lat = np.arctan2(z + _EP2 * _B * np.sin(theta) ** 3, p - _E2 * _A * np.cos(theta) ** 3)
    for _ in range(2):
        s = np.sin(lat)
        N = _A / np.sqrt(1.0 - _E2 * s * s)
        h = p * np.cos(lat) + z * s - _A * np.sqrt(1.0 - _E2 * s * s)
        lat = np.arctan2(z, p * (1.0 - _E2 * N / (N + h)))
    s = np.sin(lat)
    h = p * np.cos(lat) + z * s - _A * np.sqrt(1.0 - _E2 * s * s)
    return lat, lon, h


@nb.njit(cache=True)
def _normal_gravity(lat, h):
    """Same as :func:`earth.normal_gravity`."""
    s2 = np.sin(lat) ** 2
    gamma0 = _GAMMA_E * (1.0 + _K * s2) / np.sqrt(1.0 - _E2 * s2)
    return gamma0 * (1.0 - 2.0 / _A * (1.0 + _F + _M - 2.0 * _F * s2) * h + 3.0 * h * h / _A**2)


@nb.njit(cache=True)
def _gravity_w(p_w, R_e_w, p_e_w, out):
    """Normal gravity in ``w`` at ``p_w`` (same as ``LocalFrame.gravity_w``), written to ``out``."""
    pe = np.empty(3)
    for i in range(3):
        pe[i] = p_e_w[i] + R_e_w[i, 0] * p_w[0] + R_e_w[i, 1] * p_w[1] + R_e_w[i, 2] * p_w[2]
    lat, lon, h = _ecef_to_geodetic(pe[0], pe[1], pe[2])
    g = _normal_gravity(lat, h)
    cl = np.cos(lat)
    ge0, ge1, ge2 = -g * cl * np.cos(lon), -g * cl * np.sin(lon), -g * np.sin(lat)
    for j in range(3):
        out[j] = R_e_w[0, j] * ge0 + R_e_w[1, j] * ge1 + R_e_w[2, j] * ge2


@nb.njit(cache=True)
def _cross(a, b, out):
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


@nb.njit(cache=True)
def _jr_inv_apply(theta, v, out):
    """``Jr^-1(theta) v = v + theta x v / 2 + d theta x (theta x v)``."""
    t2 = theta[0] * theta[0] + theta[1] * theta[1] + theta[2] * theta[2]
    t = np.sqrt(t2)
    if t < 1e-4:
        d = 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0
    else:
        d = 1.0 / t2 - (1.0 + np.cos(t)) / (2.0 * t * np.sin(t))
    c1 = np.empty(3)
    c2 = np.empty(3)
    _cross(theta, v, c1)
    _cross(theta, c1, c2)
    for i in range(3):
        out[i] = v[i] + 0.5 * c1[i] + d * c2[i]


@nb.njit(cache=True)
def _derivs(R, v, p, w_ib, f_ib, R_e_w, p_e_w, w_ie, omega_out, a_out):
    """Body rate relative to w (``w_ib - R^T w_ie``) and acceleration in w."""
    g = np.empty(3)
    _gravity_w(p, R_e_w, p_e_w, g)
    cor = np.empty(3)
    _cross(w_ie, v, cor)
    for i in range(3):
        omega_out[i] = w_ib[i] - (R[0, i] * w_ie[0] + R[1, i] * w_ie[1] + R[2, i] * w_ie[2])
        a_out[i] = (R[i, 0] * f_ib[0] + R[i, 1] * f_ib[1] + R[i, 2] * f_ib[2]) - 2.0 * cor[i] + g[i]


@nb.njit(cache=True)
def rkmk4_step(p, v, R, w0, f0, wm, fm, w1, f1, dt, R_e_w, p_e_w, w_ie, p_out, v_out, R_out):
    """One RKMK4 step from (p, v, R) over ``dt`` with IMU at start, middle and end (njit).

    The kernel of :func:`strapdown_step` and :func:`integrate`, and of the EKF's prediction
    (:mod:`georefine.trajectory._ekf_kernels`), which calls it from its own njit loop: all
    arrays float64 and contiguous, the frame as :func:`frame_arrays`, the new state written
    into ``p_out``, ``v_out``, ``R_out``.
    """
    om = np.empty(3)
    k1, k2, k3, k4 = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    a1, a2, a3, a4 = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    th = np.empty(3)
    E = np.empty((3, 3))
    Ri = np.empty((3, 3))
    pi = np.empty(3)
    v2, v3, v4 = np.empty(3), np.empty(3), np.empty(3)

    _derivs(R, v, p, w0, f0, R_e_w, p_e_w, w_ie, k1, a1)
    # stage 2
    for i in range(3):
        th[i] = 0.5 * dt * k1[i]
        v2[i] = v[i] + 0.5 * dt * a1[i]
        pi[i] = p[i] + 0.5 * dt * v[i]
    exp_so3_into(th, E)
    Ri[:, :] = R @ E
    _derivs(Ri, v2, pi, wm, fm, R_e_w, p_e_w, w_ie, om, a2)
    _jr_inv_apply(th, om, k2)
    # stage 3
    for i in range(3):
        th[i] = 0.5 * dt * k2[i]
        v3[i] = v[i] + 0.5 * dt * a2[i]
        pi[i] = p[i] + 0.5 * dt * v2[i]
    exp_so3_into(th, E)
    Ri[:, :] = R @ E
    _derivs(Ri, v3, pi, wm, fm, R_e_w, p_e_w, w_ie, om, a3)
    _jr_inv_apply(th, om, k3)
    # stage 4
    for i in range(3):
        th[i] = dt * k3[i]
        v4[i] = v[i] + dt * a3[i]
        pi[i] = p[i] + dt * v3[i]
    exp_so3_into(th, E)
    Ri[:, :] = R @ E
    _derivs(Ri, v4, pi, w1, f1, R_e_w, p_e_w, w_ie, om, a4)
    _jr_inv_apply(th, om, k4)
    for i in range(3):
        th[i] = dt / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
        v_out[i] = v[i] + dt / 6.0 * (a1[i] + 2.0 * a2[i] + 2.0 * a3[i] + a4[i])
        p_out[i] = p[i] + dt / 6.0 * (v[i] + 2.0 * v2[i] + 2.0 * v3[i] + v4[i])
    exp_so3_into(th, E)
    R_out[:, :] = R @ E


@nb.njit(cache=True)
def _integrate(t, w, f, wm, fm, p0, v0, R0, R_e_w, p_e_w, w_ie, P, V, RR):
    n = t.shape[0]
    P[0] = p0
    V[0] = v0
    RR[0] = R0
    for k in range(n - 1):
        rkmk4_step(P[k], V[k], RR[k], w[k], f[k], wm[k], fm[k], w[k + 1], f[k + 1], t[k + 1] - t[k],
                   R_e_w, p_e_w, w_ie, P[k + 1], V[k + 1], RR[k + 1])


# ---------------------------------------------------------------------------- interpolation
def _lagrange_weights(nodes: np.ndarray, x: np.ndarray, deriv: int) -> np.ndarray:
    """Weights (M, m) of the Lagrange polynomial through ``nodes`` (M, m), or of its derivative, at ``x``."""
    M, m = nodes.shape
    W = np.empty((M, m))
    for j in range(m):
        others = [i for i in range(m) if i != j]
        denom = np.prod([nodes[:, j] - nodes[:, i] for i in others], axis=0)
        if deriv == 0:
            num = np.prod([x - nodes[:, i] for i in others], axis=0)
        else:
            num = np.zeros(M)
            for skip in others:
                num += np.prod([x - nodes[:, i] for i in others if i != skip] or [np.ones(M)], axis=0)
        W[:, j] = num / denom
    return W


def _windows(n_nodes: int, centre: np.ndarray, m: int) -> np.ndarray:
    """Indices (M, m) of m consecutive nodes starting near ``centre``, clamped to [0, n_nodes)."""
    m = min(m, n_nodes)
    start = np.clip(centre, 0, n_nodes - m)
    return start[:, None] + np.arange(m)


def midpoints_from_samples(t, x):
    """Cubic (4-point Lagrange) interpolation of samples ``x`` (N,3) at interval midpoints."""
    n = len(t)
    tm = 0.5 * (t[:-1] + t[1:])
    idx = _windows(n, np.arange(n - 1) - 1, 4)
    W = _lagrange_weights(t[idx], tm, 0)
    return np.einsum("mj,mjk->mk", W, x[idx])


def rates_from_increments(t, d):
    """Rates at the sample times and midpoints from increments ``d`` (N,3) over (t_k-1, t_k]."""
    n = len(t)
    dt0 = t[1] - t[0]
    tn = np.concatenate([[t[0] - dt0], t])  # nodes of the cumulative integral
    cum = np.concatenate([np.zeros((1, 3)), np.cumsum(d, axis=0)])
    idx = _windows(n + 1, np.arange(n) + 1 - 2, 5)  # centred on node k+1 (= time t_k)
    W = _lagrange_weights(tn[idx], t, 1)
    rate = np.einsum("mj,mjk->mk", W, cum[idx])
    tm = 0.5 * (t[:-1] + t[1:])
    idx = _windows(n + 1, np.arange(n - 1), 4)  # nodes t_k-1 .. t_k+2
    W = _lagrange_weights(tn[idx], tm, 1)
    mid = np.einsum("mj,mjk->mk", W, cum[idx])
    return rate, mid


def frame_arrays(frame: LocalFrame):
    """``(R_e_w, p_e_w, omega_ie_w)`` of a frame as contiguous float64 arrays, the frame
    arguments of :func:`rkmk4_step`."""
    return (np.ascontiguousarray(frame.R_e_w), np.ascontiguousarray(frame.p_e_w, dtype=float),
            np.ascontiguousarray(frame.omega_ie_w, dtype=float))


# ---------------------------------------------------------------------------- public API
def strapdown_step(
    frame: LocalFrame,
    state: StrapdownState,
    gyro_k: np.ndarray,
    acc_k: np.ndarray,
    gyro_k1: np.ndarray,
    acc_k1: np.ndarray,
    dt: float,
    gyro_mid: np.ndarray | None = None,
    acc_mid: np.ndarray | None = None,
) -> StrapdownState:
    """Propagate ``state`` over one IMU interval of ``dt`` seconds (RKMK4).

    Parameters
    ----------
    frame : LocalFrame
        Mapping frame ``w`` (Earth rate, gravity).
    state : StrapdownState
        State at the first sample time.
    gyro_k, acc_k : ndarray (3,)
        Angular rate ``omega_ib_b`` (rad/s) and specific force ``f_ib_b`` (m/s^2) at the start.
    gyro_k1, acc_k1 : ndarray (3,)
        The same at the end of the interval.
    dt : float
        Interval (s).
    gyro_mid, acc_mid : ndarray (3,), optional
        Values at the middle of the interval; default the mean of the end values (second
        order: pass cubic-interpolated mid values, as :func:`integrate` does, for full accuracy).

    Returns
    -------
    StrapdownState
        State at the end of the interval.
    """
    w0, f0 = np.asarray(gyro_k, float), np.asarray(acc_k, float)
    w1, f1 = np.asarray(gyro_k1, float), np.asarray(acc_k1, float)
    wm = 0.5 * (w0 + w1) if gyro_mid is None else np.asarray(gyro_mid, float)
    fm = 0.5 * (f0 + f1) if acc_mid is None else np.asarray(acc_mid, float)
    p, v, R = np.empty(3), np.empty(3), np.empty((3, 3))
    rkmk4_step(np.asarray(state.p_w_b, float), np.asarray(state.v_w_b, float),
               np.ascontiguousarray(state.R_w_b, dtype=float), w0, f0, wm, fm, w1, f1, float(dt),
               *frame_arrays(frame), p, v, R)
    return StrapdownState(p, v, R)


def integrate(
    frame: LocalFrame,
    time: np.ndarray,
    gyro: np.ndarray,
    acc: np.ndarray,
    p0_w: np.ndarray,
    v0_w: np.ndarray,
    R0_w_b: np.ndarray,
    increments: bool = False,
) -> StrapdownResult:
    """Integrate IMU data from an initial state at ``time[0]`` to every sample time.

    Parameters
    ----------
    frame : LocalFrame
        Mapping frame ``w``.
    time : ndarray (N,)
        Sample times (s), strictly increasing.
    gyro, acc : ndarray (N, 3)
        Instantaneous ``omega_ib_b`` (rad/s) and ``f_ib_b`` (m/s^2) at the sample times, or
        with ``increments=True`` the increments ``dtheta`` (rad) and ``dv`` (m/s) over
        ``(time[k-1], time[k]]`` (the first over ``(time[0] - (time[1] - time[0]), time[0]]``).
    p0_w, v0_w : ndarray (3,)
        Initial position (m) and velocity (m/s) in ``w``.
    R0_w_b : ndarray (3, 3)
        Initial attitude.
    increments : bool
        Interpret ``gyro``/``acc`` as increments.

    Returns
    -------
    StrapdownResult
        States at all ``time`` (the first is the initial state).
    """
    t = np.ascontiguousarray(time, dtype=float)
    gyro = np.ascontiguousarray(gyro, dtype=float)
    acc = np.ascontiguousarray(acc, dtype=float)
    n = len(t)
    if gyro.shape != (n, 3) or acc.shape != (n, 3):
        raise ValueError(f"gyro and acc must have shape ({n}, 3), got {gyro.shape}, {acc.shape}")
    if n < 2:
        raise ValueError("need at least two IMU samples")
    if not np.all(np.diff(t) > 0):
        raise ValueError("IMU times must increase strictly")
    if increments:
        w, wm = rates_from_increments(t, gyro)
        f, fm = rates_from_increments(t, acc)
    else:
        w, f = gyro, acc
        wm, fm = midpoints_from_samples(t, gyro), midpoints_from_samples(t, acc)
    P, V, RR = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3, 3))
    _integrate(t, np.ascontiguousarray(w), np.ascontiguousarray(f), np.ascontiguousarray(wm),
               np.ascontiguousarray(fm), np.asarray(p0_w, float).reshape(3),
               np.asarray(v0_w, float).reshape(3), np.ascontiguousarray(R0_w_b, dtype=float),
               *frame_arrays(frame), P, V, RR)
    return StrapdownResult(t, P, V, RR)
