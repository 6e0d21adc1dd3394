"""Continuous-time trajectory on uniform knots (docs/ARCHITECTURE.md §4.2).

Position: a quintic Hermite spline in ``w`` with knot states ``p_k, v_k, a_k`` (C²).
Orientation: the cumulative cubic quaternion Hermite spline of Kim, Kim & Shin (1995) with
knot states ``R_k`` (``R_w_b``) and body rates ``omega_k`` (``omega_wb_b``). For a time ``t``
in knot interval ``k``, ``u = (t - t_k) / dt`` in [0, 1] and::

    p(u)  = H0 p_k + dt H1 v_k + dt² H2 a_k + H3 p_k+1 + dt H4 v_k+1 + dt² H5 a_k+1
    R(u)  = R_k Exp(b1 phi1) Exp(b2 phi2) Exp(b3 phi3)
    phi1  = dt omega_k / 3,   phi3 = dt omega_k+1 / 3,
    phi2  = Log(Exp(phi1)^T R_k^T R_k+1 Exp(phi3)^T)
    b1 = 1 - (1-u)³,  b2 = 3u² - 2u³,  b3 = u³
    omega(u) = [A3^T A2^T b1' phi1 + A3^T b2' phi2 + b3' phi3] / dt,   A_i = Exp(b_i phi_i)

The spline interpolates ``p, v, a`` and ``R, omega`` at the knots. The position is linear in
its knot states, so its Jacobians are the basis weights (:func:`position_basis`) times I3.
Orientation Jacobians are analytic (:func:`eval_orientation`) in the house convention:
right perturbations ``R <- R Exp(dtheta)`` of the knot attitudes and of the result, additive
perturbations of the knot rates. ``phi2`` is the principal Log, so the rotation between
neighbouring knots must stay below pi (true by far for aircraft at dt <= 0.5 s). Times are
float64 seconds relative to the dataset epoch; the spline never extrapolates.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np

from georefine.errors import InputError
from georefine.geometry.rotation import (
    exp_so3,
    left_jacobian,
    log_so3,
    right_jacobian,
    right_jacobian_inv,
)
from georefine.trajectory.sampled import Trajectory

_log = logging.getLogger(__name__)

_TIME_TOL_S = 1e-9  # times this close outside the span are rounding, evaluated at the end

# Quintic Hermite basis on [0, 1] in powers of u: H_i(u) = sum_j _HERMITE5[i, j] u^j, for
# [p_k, p'_k, p''_k, p_k+1, p'_k+1, p''_k+1] (derivatives with respect to u).
_HERMITE5 = np.array(
    [
        [1.0, 0.0, 0.0, -10.0, 15.0, -6.0],
        [0.0, 1.0, 0.0, -6.0, 8.0, -3.0],
        [0.0, 0.0, 0.5, -1.5, 1.5, -0.5],
        [0.0, 0.0, 0.0, 10.0, -15.0, 6.0],
        [0.0, 0.0, 0.0, -4.0, 7.0, -3.0],
        [0.0, 0.0, 0.0, 0.5, -1.0, 0.5],
    ]
)
# d^r/du^r of the basis in powers of u^(j-r), j = r..5 (d^r/du^r u^j = j!/(j-r)! u^(j-r)).
_HERMITE5_D = [_HERMITE5[:, r:] * np.array([math.perm(j, r) for j in range(r, 6)]) for r in range(4)]


@dataclass(frozen=True)
class KnotGrid:
    """Uniform knots ``t_k = t_start + k dt``, ``k = 0 .. n_knots-1``.

    Attributes
    ----------
    t_start : float
        First knot (s, relative to the dataset epoch).
    dt : float
        Knot spacing (s), > 0.
    n_knots : int
        Number of knots, >= 2.
    """

    t_start: float
    dt: float
    n_knots: int

    def __post_init__(self) -> None:
        if not (np.isfinite(self.t_start) and np.isfinite(self.dt) and self.dt > 0.0):
            raise ValueError(f"need a finite t_start and dt > 0, got t_start={self.t_start}, dt={self.dt}")
        if int(self.n_knots) != self.n_knots or self.n_knots < 2:
            raise ValueError(f"n_knots must be an integer >= 2, got {self.n_knots}")
        object.__setattr__(self, "t_start", float(self.t_start))
        object.__setattr__(self, "dt", float(self.dt))
        object.__setattr__(self, "n_knots", int(self.n_knots))

    @classmethod
    def covering(cls, t_first: float, t_last: float, dt: float) -> KnotGrid:
        """The shortest grid starting at ``t_first`` whose last knot is at or after ``t_last``."""
        if not t_last > t_first:
            raise ValueError(f"need t_last > t_first, got {t_first} .. {t_last}")
        n = int(np.ceil((t_last - t_first) / dt * (1.0 - 1e-12))) + 1
        if t_first + (n - 1) * dt < t_last - _TIME_TOL_S:
            n += 1
        return cls(t_first, dt, max(n, 2))

    @classmethod
    def spanning(cls, t_first: float, t_last: float, dt: float) -> KnotGrid:
        """The grid from ``t_first`` to ``t_last`` whose whole intervals are nearest ``dt`` long.

        Two grids spanning the same times share their end knots whatever their intervals, so a
        trajectory moves between them without extrapolating (:meth:`SplineTrajectory.resampled`).
        """
        if not t_last > t_first:
            raise ValueError(f"need t_last > t_first, got {t_first} .. {t_last}")
        if not dt > 0.0:
            raise ValueError(f"need dt > 0, got {dt}")
        n = max(int(round((t_last - t_first) / dt)), 1)
        return cls(t_first, (t_last - t_first) / n, n + 1)

    @property
    def t_end(self) -> float:
        """Last knot (s)."""
        return self.t_start + (self.n_knots - 1) * self.dt

    @property
    def n_intervals(self) -> int:
        """Number of knot intervals, ``n_knots - 1``."""
        return self.n_knots - 1

    @property
    def knot_times(self) -> np.ndarray:
        """Knot times (n_knots,) s."""
        return self.t_start + self.dt * np.arange(self.n_knots)

    def locate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Knot interval and normalised time of each time.

        Parameters
        ----------
        t : (N,) float
            Times (s); a scalar counts as one time.

        Returns
        -------
        k : (N,) int64
            Interval index: ``t`` lies in ``[t_k, t_k+1)``; the last interval is closed.
        u : (N,) float64
            ``(t - t_k) / dt`` in [0, 1].

        Raises
        ------
        InputError (a ValueError)
            If any time is outside ``[t_start, t_end]`` (or NaN). Times within 1 ns of the
            span are rounding and evaluated at the end knot.
        """
        t = np.atleast_1d(np.asarray(t, dtype=float))
        if t.ndim != 1:
            raise ValueError(f"times must be 1-D, got shape {t.shape}")
        inside = (t >= self.t_start - _TIME_TOL_S) & (t <= self.t_end + _TIME_TOL_S)
        if not np.all(inside):
            bad = t[~inside]
            finite = bad[np.isfinite(bad)]
            raise InputError(
                f"{bad.size} times outside the spline span",
                field="time",
                expected=f"[{self.t_start:.6f}, {self.t_end:.6f}] s",
                found=f"{finite.min():.6f} .. {finite.max():.6f} s" if finite.size else "NaN",
            )
        x = (t - self.t_start) / self.dt
        snap = np.round(x)  # a time at a knot starts that knot's interval despite rounding
        x = np.where(np.abs(x - snap) < 1e-9, snap, x)
        k = np.clip(np.floor(x).astype(np.int64), 0, self.n_knots - 2)
        u = np.clip(x - k, 0.0, 1.0)
        return k, u


# --------------------------------------------------------------------------- position


def position_basis(u: np.ndarray, dt: float, order: int = 0) -> np.ndarray:
    """Weights of the knot states in the position spline or its time derivatives.

    Parameters
    ----------
    u : (N,) float
        Normalised time in the knot interval, [0, 1].
    dt : float
        Knot spacing (s).
    order : {0, 1, 2, 3}
        0 position, 1 velocity, 2 acceleration, 3 jerk.

    Returns
    -------
    (N, 6) float64
        ``w`` such that ``d^order p / dt^order = sum_j w[:, j] x_j`` for
        ``x = [p_k, v_k, a_k, p_k+1, v_k+1, a_k+1]`` (m, m/s, m/s²). The dt factors are
        included, so the Jacobian with respect to ``x_j`` is ``w[:, j] * I3``.
    """
    if order not in (0, 1, 2, 3):
        raise ValueError(f"order must be 0, 1, 2 or 3, got {order}")
    u = np.atleast_1d(np.asarray(u, dtype=float))
    scale = np.array([1.0, dt, dt * dt, 1.0, dt, dt * dt]) / dt**order
    powers = np.empty((6 - order, u.size))  # u^0 .. u^(5-order), rows
    powers[0] = 1.0
    for j in range(1, 6 - order):
        np.multiply(powers[j - 1], u, out=powers[j])
    # (6, n) @ (n, N) with the long axis last: far faster in BLAS than (N, n) @ (n, 6).
    return ((_HERMITE5_D[order] * scale[:, None]) @ powers).T


def eval_position(
    grid: KnotGrid, P: np.ndarray, V: np.ndarray, A: np.ndarray, t: np.ndarray, order: int = 0
) -> np.ndarray:
    """Position (``order=0``, m), velocity (1, m/s) or acceleration (2, m/s²) in ``w``.

    ``P, V, A`` are the knot positions, velocities and accelerations, (K, 3) each with
    ``K = grid.n_knots``; ``t`` (N,) s. Returns (N, 3).
    """
    k, u = grid.locate(t)
    _check_knots(grid, P=P, V=V, A=A)
    return knot_sum(P, V, A, k, position_basis(u, grid.dt, order))


def knot_sum(P: np.ndarray, V: np.ndarray, A: np.ndarray, k: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``sum_j w[:, j] x_j`` over the six position knot states of interval ``k`` (N, 3): the position
    (or a derivative) for weights ``w`` (N, 6) of :func:`position_basis`, for callers that located
    their times once (the observation groups)."""
    out = np.empty((np.size(k), 3))
    _knot_sum(np.ascontiguousarray(P, dtype=np.float64), np.ascontiguousarray(V, dtype=np.float64),
              np.ascontiguousarray(A, dtype=np.float64), np.ascontiguousarray(k, dtype=np.int64),
              np.ascontiguousarray(w, dtype=np.float64), out)
    return out


@numba.njit(cache=True, nogil=True)
def _knot_sum(P, V, A, k, w, out):  # pragma: no cover - numba
    """:func:`knot_sum` time by time (numpy's six gathers and products took 2.5 ms per 20,000 times)."""
    for n in range(k.size):
        a = k[n]
        b = a + 1
        for c in range(3):
            out[n, c] = (w[n, 0] * P[a, c] + w[n, 1] * V[a, c] + w[n, 2] * A[a, c]
                         + w[n, 3] * P[b, c] + w[n, 4] * V[b, c] + w[n, 5] * A[b, c])


# ------------------------------------------------------------------------ orientation


@dataclass(frozen=True, eq=False)
class OrientationJacobians:
    """Jacobians of the spline attitude and body rate with respect to the knot states.

    For time ``n`` in interval ``k[n]`` the columns of ``dR`` and ``domega`` are the blocks
    ``[dtheta_k, domega_k, dtheta_k+1, domega_k+1]`` (3 each): right perturbations of the knot
    attitudes (``R_k <- R_k Exp(dtheta_k)``) and additive ones of the knot rates. ``dR`` maps
    them to the right tangent ``delta`` of ``R(t)`` (``R' = R(t) Exp(delta)``), ``domega`` to
    ``omega(t)``. The eight (N, 3, 3) blocks are available as views (``dR_dtheta_k`` ...).

    Attributes
    ----------
    k : (N,) int64
        Knot interval of each time.
    dR : (N, 3, 12) float64
    domega : (N, 3, 12) float64 or None
        None when the rate was not evaluated.
    """

    k: np.ndarray
    dR: np.ndarray
    domega: np.ndarray | None = None

    # The eight (N, 3, 3) blocks, views into dR and domega.
    dR_dtheta_k = property(lambda self: self.dR[:, :, 0:3])
    dR_domega_k = property(lambda self: self.dR[:, :, 3:6])
    dR_dtheta_k1 = property(lambda self: self.dR[:, :, 6:9])
    dR_domega_k1 = property(lambda self: self.dR[:, :, 9:12])
    domega_dtheta_k = property(lambda self: self.domega[:, :, 0:3])
    domega_domega_k = property(lambda self: self.domega[:, :, 3:6])
    domega_dtheta_k1 = property(lambda self: self.domega[:, :, 6:9])
    domega_domega_k1 = property(lambda self: self.domega[:, :, 9:12])


class OrientationEval(NamedTuple):
    """Result of :func:`eval_orientation`: ``R_w_b`` (N,3,3), ``omega_wb_b`` (N,3) rad/s or
    None, ``jacobians`` or None."""

    R_w_b: np.ndarray
    omega_wb_b: np.ndarray | None
    jacobians: OrientationJacobians | None


class _Terms(NamedTuple):
    """Per-interval quantities of the orientation spline (leading axis: intervals)."""

    phi: np.ndarray  # (3, M, 3): phi1, phi2, phi3
    theta: np.ndarray  # (3, M): their norms
    dphi2: np.ndarray | None  # (M, 3, 12): dphi2 / d[theta_k, omega_k, theta_k+1, omega_k+1]


def interval_terms(R0, R1, w0, w1, dt: float, jacobians: bool) -> _Terms:
    """phi1..3 of intervals with end states (R0, w0), (R1, w1) and, if asked, dphi2/dx."""
    phi1 = w0 * (dt / 3.0)
    phi3 = w1 * (dt / 3.0)
    E1, E3 = exp_so3(phi1), exp_so3(phi3)
    D = np.swapaxes(E1, 1, 2) @ np.swapaxes(R0, 1, 2) @ R1 @ np.swapaxes(E3, 1, 2)
    phi2 = log_so3(D)
    phis = np.stack([phi1, phi2, phi3])
    dphi2 = None
    if jacobians:
        # D = Exp(-phi1) R0^T R1 Exp(-phi3); right-perturbation of D for each knot state,
        # then dphi2 = Jr^-1(phi2) dD (Log(D Exp(d)) = phi2 + Jr^-1(phi2) d):
        #   R0 <- R0 Exp(e):      dD = -D^T Exp(phi1)^T e
        #   R1 <- R1 Exp(e):      dD = Exp(phi3) e
        #   phi1 <- phi1 + d:     dD = -D^T Jr(phi1) d      (Exp(phi)^T Jl(phi) = Jr(phi))
        #   phi3 <- phi3 + d:     dD = -Jl(phi3) d
        # with dphi1 = dt/3 domega_k, dphi3 = dt/3 domega_k+1.
        Jri2 = right_jacobian_inv(phi2)
        JDt = -Jri2 @ np.swapaxes(D, 1, 2)
        dphi2 = np.concatenate(
            [
                JDt @ np.swapaxes(E1, 1, 2),
                (dt / 3.0) * (JDt @ right_jacobian(phi1)),
                Jri2 @ E3,
                -(dt / 3.0) * (Jri2 @ left_jacobian(phi3)),
            ],
            axis=2,
        )
    return _Terms(phis, np.linalg.norm(phis, axis=2), dphi2)


def evaluate_terms(terms: _Terms, idx, R0, u, dt: float, rate: bool, jacobians: bool, k) -> OrientationEval:
    """Per-time evaluation from per-interval ``terms`` indexed by ``idx`` (N,): :func:`_orientation_kernel`."""
    n = np.size(idx)
    R = np.empty((n, 3, 3))
    omega = np.empty((n, 3)) if rate else None
    dR = np.empty((n, 3, 12)) if jacobians else None
    dW = np.empty((n, 3, 12)) if jacobians and rate else None
    empty3, empty12 = np.empty((0, 3)), np.empty((0, 3, 12))
    _orientation_kernel(terms.phi, terms.theta, terms.dphi2 if jacobians else empty12,
                        np.ascontiguousarray(idx, dtype=np.int64), np.ascontiguousarray(R0, dtype=np.float64),
                        np.ascontiguousarray(u, dtype=np.float64), float(dt), bool(rate), bool(jacobians),
                        R, omega if rate else empty3, dR if jacobians else empty12, dW if dW is not None else empty12)
    return OrientationEval(R, omega, OrientationJacobians(np.asarray(k), dR, dW) if jacobians else None)


@numba.njit(cache=True, nogil=True, inline="always")
def _abc(x):  # pragma: no cover - numba
    """``sin x / x``, ``(1 - cos x) / x²``, ``(x - sin x) / x³`` (even functions); Taylor series
    below 0.01 in magnitude, where they are exact to rounding and the closed forms lose digits."""
    x2 = x * x
    if abs(x) < 1e-2:
        return (1.0 - x2 / 6.0 + x2 * x2 / 120.0, 0.5 - x2 / 24.0 + x2 * x2 / 720.0,
                1.0 / 6.0 - x2 / 120.0 + x2 * x2 / 5040.0)
    s = math.sin(x)
    return s / x, (1.0 - math.cos(x)) / x2, (x - s) / (x2 * x)


@numba.njit(cache=True, nogil=True, inline="always")
def _mm(A, B, out):  # pragma: no cover - numba
    """out = A @ B (3x3)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@numba.njit(cache=True, nogil=True, inline="always")
def _mtm(A, B, out):  # pragma: no cover - numba
    """out = A^T @ B (3x3)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = A[0, i] * B[0, j] + A[1, i] * B[1, j] + A[2, i] * B[2, j]


@numba.njit(cache=True, nogil=True, inline="always")
def _skew_mm(y, B, out):  # pragma: no cover - numba
    """out = skew(y) @ B (3x3)."""
    for j in range(3):
        out[0, j] = -y[2] * B[1, j] + y[1] * B[2, j]
        out[1, j] = y[2] * B[0, j] - y[0] * B[2, j]
        out[2, j] = -y[1] * B[0, j] + y[0] * B[1, j]


@numba.njit(cache=True, nogil=True, inline="always")
def _exp_terms(p, s1, s2, out):  # pragma: no cover - numba
    """out = I + s1 K + s2 K^2, K = skew(p) (K^2 = p p^T - |p|^2 I)."""
    pp = p[0] * p[0] + p[1] * p[1] + p[2] * p[2]
    for i in range(3):
        for j in range(3):
            out[i, j] = s2 * p[i] * p[j]
        out[i, i] += 1.0 - s2 * pp
    out[0, 1] -= s1 * p[2]
    out[1, 0] += s1 * p[2]
    out[0, 2] += s1 * p[1]
    out[2, 0] -= s1 * p[1]
    out[1, 2] -= s1 * p[0]
    out[2, 1] += s1 * p[0]


@numba.njit(cache=True, nogil=True)
def _orientation_kernel(phi, theta, dphi2, idx, R0, u, dt, rate, jacobians, R_out, omega_out, dR_out,
                        dW_out):  # pragma: no cover - numba
    """The attitude, rate and Jacobians of :func:`eval_orientation` time by time (derivation there).

    ``A_i = Exp(b_i phi_i) = I + b_i a K_i + b_i^2 b K_i^2`` and ``b_i Jr(b_i phi_i) = b_i (I - b_i b
    K_i + b_i^2 c K_i^2)`` with ``a, b, c`` of ``b_i |phi_i|`` (:func:`_abc`). Written in numba: the
    numpy version went through (N, 3, 3) stacks op by op, three to four times slower, and the
    spline is evaluated at every IMU node, GNSS epoch, plane and LiDAR return of every iteration.
    """
    A = np.empty((3, 3, 3))
    Jr = np.empty((3, 3, 3))
    M23 = np.empty((3, 3))
    M123 = np.empty((3, 3))
    T = np.empty((3, 3))
    T2 = np.empty((3, 3))
    y2 = np.empty(3)
    y3 = np.empty(3)
    v = np.empty(3)
    beta = np.empty(3)
    dbeta = np.empty(3)
    c3 = dt / 3.0
    for n in range(idx.size):
        m = idx[n]
        x = u[n]
        beta[0] = 1.0 - (1.0 - x) ** 3
        beta[1] = x * x * (3.0 - 2.0 * x)
        beta[2] = x ** 3
        dbeta[0] = 3.0 * (1.0 - x) ** 2
        dbeta[1] = 6.0 * x * (1.0 - x)
        dbeta[2] = 3.0 * x * x
        for i in range(3):
            bi = beta[i]
            a, b, c = _abc(bi * theta[i, m])
            _exp_terms(phi[i, m], bi * a, bi * bi * b, A[i])
            if jacobians:
                _exp_terms(phi[i, m], -bi * b, bi * bi * c, Jr[i])
                for r in range(3):
                    for q in range(3):
                        Jr[i, r, q] *= bi
        _mm(A[1], A[2], M23)
        _mm(A[0], M23, M123)
        _mm(R0[n], M123, R_out[n])
        if rate:
            for r in range(3):
                v[r] = dbeta[0] * phi[0, m, r]
            for r in range(3):
                y2[r] = A[1, 0, r] * v[0] + A[1, 1, r] * v[1] + A[1, 2, r] * v[2]
            for r in range(3):
                v[r] = y2[r] + dbeta[1] * phi[1, m, r]
            for r in range(3):
                y3[r] = A[2, 0, r] * v[0] + A[2, 1, r] * v[1] + A[2, 2, r] * v[2]
                omega_out[n, r] = (y3[r] + dbeta[2] * phi[2, m, r]) / dt
        if not jacobians:
            continue
        _mtm(A[2], Jr[1], T)  # A3^T Jr2: dR/dphi2
        for r in range(3):
            for q in range(12):
                dR_out[n, r, q] = T[r, 0] * dphi2[m, 0, q] + T[r, 1] * dphi2[m, 1, q] + T[r, 2] * dphi2[m, 2, q]
        _mtm(M23, Jr[0], T)
        for r in range(3):
            for q in range(3):
                dR_out[n, r, q] += M123[q, r]
                dR_out[n, r, 3 + q] += c3 * T[r, q]
                dR_out[n, r, 9 + q] += c3 * Jr[2, r, q]
        if not rate:
            continue
        _skew_mm(y2, Jr[1], T2)  # H2 = A3^T (skew(y2) Jr2 + b2' I)
        for r in range(3):
            T2[r, r] += dbeta[1]
        _mtm(A[2], T2, T)
        for r in range(3):
            for q in range(12):
                dW_out[n, r, q] = (T[r, 0] * dphi2[m, 0, q] + T[r, 1] * dphi2[m, 1, q]
                                   + T[r, 2] * dphi2[m, 2, q]) / dt
        _skew_mm(y3, Jr[2], T2)
        for r in range(3):
            T2[r, r] += dbeta[2]
        for r in range(3):
            for q in range(3):
                dW_out[n, r, 3 + q] += M23[q, r] * (c3 * dbeta[0] / dt)
                dW_out[n, r, 9 + q] += T2[r, q] * (c3 / dt)


def eval_orientation(
    grid: KnotGrid, R: np.ndarray, W: np.ndarray, t: np.ndarray, rate: bool = True, jacobians: bool = False,
    located: tuple[np.ndarray, np.ndarray] | None = None,
) -> OrientationEval:
    """Attitude, body rate and their Jacobians of the cumulative cubic Hermite spline.

    Parameters
    ----------
    grid : KnotGrid
    R : (K, 3, 3)
        Knot attitudes ``R_w_b``.
    W : (K, 3)
        Knot body rates ``omega_wb_b`` (rad/s).
    t : (N,)
        Times (s) in the grid's span.
    rate, jacobians : bool
        Evaluate the body rate; the Jacobians (of the rate too if ``rate``).
    located : ((N,) int, (N,) float), optional
        The intervals and normalised times to use instead of ``grid.locate(t)``: a normalised time
        a little outside ``[0, 1]`` continues that interval's polynomial (a caller that keeps its
        Jacobian's structure while its times move, :mod:`georefine.adjustment.observations.plane`).

    Returns
    -------
    OrientationEval
        ``(R_w_b (N,3,3), omega_wb_b (N,3) or None, OrientationJacobians or None)``.

    Notes
    -----
    Derivation (A_i = Exp(b_i phi_i), M23 = A2 A3, M123 = A1 A2 A3, right tangents):

    * ``R = R_k M123``: ``R_k <- R_k Exp(e)`` gives ``delta = M123^T e``; a change ``d`` of
      ``phi_i`` gives ``delta = (A_i+1 .. A3)^T b_i Jr(b_i phi_i) d`` (Exp(x + dx) ~=
      Exp(x) Exp(Jr(x) dx)).
    * ``phi1, phi3`` depend only on ``omega_k, omega_k+1`` (factor dt/3); ``phi2`` on all
      four states through ``D = Exp(-phi1) R_k^T R_k+1 Exp(-phi3)`` with
      ``dphi2 = Jr^-1(phi2) dD`` (see ``interval_terms`` for the four ``dD``; they use
      ``Ad_R = R``: ``Exp(x) D = D Exp(D^T x)``).
    * ``omega``: ``(A <- A Exp(e))`` changes ``A^T x`` by ``skew(A^T x) e``, so
      ``d(dt omega)/dphi1 = M23^T b1'``,
      ``d(dt omega)/dphi2 = A3^T (skew(A2^T b1' phi1) b2 Jr(b2 phi2) + b2' I)``,
      ``d(dt omega)/dphi3 = skew(A3^T (A2^T b1' phi1 + b2' phi2)) b3 Jr(b3 phi3) + b3' I``.

    The total Jacobians chain these through ``dphi_i / d(knot state)``. Cost (one core, the
    per-time part in numba): ~0.2 µs per time without, ~0.55 µs with Jacobians and rate (20,000
    times on 2,000 intervals: 4.8 and 11.1 ms, against 15.0 and 44.5 ms op by op in numpy).
    """
    k, u = grid.locate(t) if located is None else located
    _check_knots(grid, R=R, W=W)
    if k.size >= grid.n_intervals:  # per-interval terms once, gathered per time
        terms = interval_terms(R[:-1], R[1:], W[:-1], W[1:], grid.dt, jacobians)
        idx = k
    else:  # few times: compute the interval terms per time
        terms = interval_terms(R[k], R[k + 1], W[k], W[k + 1], grid.dt, jacobians)
        idx = np.arange(k.size)
    return evaluate_terms(terms, idx, R[k], u, grid.dt, rate, jacobians, k)


def locate_near(grid: KnotGrid, t: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Intervals and normalised times of ``t`` that keep the intervals ``k`` (of nearby earlier
    times) while ``t`` stays within half an interval of them; beyond, :meth:`KnotGrid.locate`.

    The normalised time then lies in ``[-0.5, 1.5]``: the interval's polynomial continued a little
    beyond its knots, which every evaluation here accepts (``eval_orientation(located=...)``,
    ``position_basis``). An observation whose times move with an estimated time offset keeps its
    Jacobian's structure this way, and the solver its analysis of it.
    """
    k = np.asarray(k, dtype=np.int64)
    u = (t - (grid.t_start + k * grid.dt)) / grid.dt
    away = np.flatnonzero((u < -0.5) | (u > 1.5))
    if away.size:
        k = k.copy()
        k[away], u[away] = grid.locate(t[away])
    return k, u


def _check_knots(grid: KnotGrid, **arrays: np.ndarray) -> None:
    shapes = {"P": (3,), "V": (3,), "A": (3,), "R": (3, 3), "W": (3,)}
    for name, arr in arrays.items():
        want = (grid.n_knots,) + shapes[name]
        if np.shape(arr) != want:
            raise ValueError(f"knot array {name} must have shape {want}, got {np.shape(arr)}")


# ------------------------------------------------------------------------- container


@dataclass(frozen=True, eq=False)
class SplineTrajectory:
    """A continuous-time trajectory: knot states on a :class:`KnotGrid`.

    Attributes
    ----------
    grid : KnotGrid
    p_w_b, v_w_b, a_w_b : (K, 3) float64
        Knot positions (m), velocities (m/s) and accelerations (m/s²) of the IMU in ``w``.
    R_w_b : (K, 3, 3) float64
        Knot attitudes.
    omega_wb_b : (K, 3) float64
        Knot body rates relative to ``w`` (rad/s).
    t0_gps : float
        Dataset epoch (GPS s); times are relative to it.
    """

    grid: KnotGrid
    p_w_b: np.ndarray
    v_w_b: np.ndarray
    a_w_b: np.ndarray
    R_w_b: np.ndarray
    omega_wb_b: np.ndarray
    t0_gps: float = 0.0

    def __post_init__(self) -> None:
        _check_knots(self.grid, P=self.p_w_b, V=self.v_w_b, A=self.a_w_b, R=self.R_w_b, W=self.omega_wb_b)

    @property
    def span(self) -> tuple[float, float]:
        """First and last knot time (s)."""
        return self.grid.t_start, self.grid.t_end

    def position(self, t: np.ndarray, order: int = 0) -> np.ndarray:
        """``p_w_b`` (order 0), ``v_w_b`` (1) or ``a_w_b`` (2) at times ``t`` (N,): (N, 3)."""
        return eval_position(self.grid, self.p_w_b, self.v_w_b, self.a_w_b, t, order)

    def pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(p_w_b (N,3) m, R_w_b (N,3,3))`` at times ``t`` (N,) s."""
        return self.position(t), self.orientation(t, rate=False).R_w_b

    def velocity(self, t: np.ndarray) -> np.ndarray:
        """``v_w_b`` (N, 3) m/s."""
        return self.position(t, 1)

    def acceleration(self, t: np.ndarray) -> np.ndarray:
        """Kinematic acceleration in ``w`` (N, 3) m/s²."""
        return self.position(t, 2)

    def body_rate(self, t: np.ndarray) -> np.ndarray:
        """``omega_wb_b`` (N, 3) rad/s."""
        return self.orientation(t).omega_wb_b

    def orientation(self, t: np.ndarray, rate: bool = True, jacobians: bool = False) -> OrientationEval:
        """See :func:`eval_orientation`."""
        return eval_orientation(self.grid, self.R_w_b, self.omega_wb_b, t, rate, jacobians)

    def resampled(self, grid: KnotGrid) -> SplineTrajectory:
        """The trajectory's states at ``grid``'s knots, which must lie inside its span.

        On a finer grid the result is the same curve at its knots and close between them; on a
        coarser one it keeps the states at the new knots only. A starting value for an adjustment
        on another grid, not an approximation of the curve.
        """
        t = grid.knot_times
        ori = self.orientation(t)
        return SplineTrajectory(grid, self.position(t), self.velocity(t), self.acceleration(t), ori.R_w_b,
                                ori.omega_wb_b, self.t0_gps)

    def to_sampled(self, times: np.ndarray) -> Trajectory:
        """The trajectory at ``times`` (N,) s (strictly increasing), with ``v_w_b``."""
        times = np.asarray(times, dtype=float)
        p, R = self.pose(times)
        return Trajectory(times, p, R, t0_gps=self.t0_gps, v_w_b=self.velocity(times))
