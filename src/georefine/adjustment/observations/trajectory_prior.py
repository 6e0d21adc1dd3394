"""A delivered trajectory (SBET) as a prior on the spline, with a time-correlated error (docs/ARCHITECTURE.md §4.3).

Without raw GNSS and IMU the adjustment starts from a trajectory a GNSS/IMU post-processor
delivered (POSPac, Inertial Explorer: an SBET and its ``smrmsg`` accuracy file). Its errors are
not white: a heading error of an INS/GNSS solution is a slowly varying offset, the same for
minutes. Weighting every SBET sample as an independent observation with the ``smrmsg`` sigma
would tie the spline to that offset with thousands of observations, and the LiDAR planes could
not move it. So the SBET observes the spline *plus an error process*::

    p_s(t_i) = p_ref(t_i) + e_p(t_i) + n_p        n_p ~ N(0, sigma_white_p^2)
    Log(R_s(t_i) R_ref(t_i)^T) = e_theta(t_i) + n_theta

``p_s, R_s`` the spline (:mod:`georefine.trajectory.spline`), ``p_ref, R_ref`` the reference
(the SBET's low-frequency part, sampled), ``e_p`` (m, in ``w``) and ``e_theta`` (rad, a small
rotation about the axes of ``w``: east, north, up; a heading error is about the third) the
SBET's error, piecewise linear on its own knots (:class:`~georefine.adjustment.observations.bias.BiasGrid`),
and ``n`` a small white part.

The error is a first-order Gauss-Markov process with the ``smrmsg`` sigma as its stationary
sigma and a correlation time ``tau`` per axis (:class:`GaussMarkovPrior`): ``e_0 ~ N(0, sigma_0^2)`` and
``e_{j+1} - phi e_j ~ N(0, sigma_{j+1}^2 (1 - phi^2))`` with ``phi = exp(-dt / tau)``. Over a
pass much shorter than ``tau`` the error is nearly an offset the planes can estimate; its size
stays bounded by the sigma the post-processor states.

Jacobians: position rows are linear; the attitude rows use the right perturbation
``R_s <- R_s Exp(delta)``: ``Log(R_s Exp(delta) R_ref^T) = Log(Exp(phi) Exp(R_ref delta))``, so
``d r / d delta = Jr^-1(phi) R_ref`` (finite-difference tested).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from georefine.adjustment.blocks import JacobianBlock, Linearization
from georefine.adjustment.observations.bias import BiasGrid
from georefine.adjustment.observations.trajectory_blocks import (
    TrajectoryBlocks,
    orientation_jacobians,
    position_jacobians,
)
from georefine.adjustment.robust import RobustLoss
from georefine.geometry.rotation import log_so3, right_jacobian_inv
from georefine.trajectory.spline import KnotGrid, eval_orientation, knot_sum, position_basis

__all__ = ["GaussMarkovPrior", "TrajectoryPoseObservation"]


@dataclass
class TrajectoryPoseObservation:
    """Reference poses at ``time`` observing the spline plus the error process (see module docstring).

    Parameters
    ----------
    grid
        Knot grid of the trajectory.
    time : (M,)
        Sample times, s relative to the dataset epoch, inside the grid's span and the error grid's.
    p_ref : (M, 3), R_ref : (M, 3, 3)
        Reference positions (m) and attitudes ``R_w_b``.
    sigma_white_p, sigma_white_theta : float
        Sigma of the white part (m, rad).
    error_grid
        Knots of the error process (blocks ``error_position``, ``error_attitude``, (J, 3)).
    """

    grid: KnotGrid
    time: np.ndarray
    p_ref: np.ndarray
    R_ref: np.ndarray
    sigma_white_p: float
    sigma_white_theta: float
    error_grid: BiasGrid
    error_position: str = "sbet_position_error"
    error_attitude: str = "sbet_attitude_error"
    blocks: TrajectoryBlocks = field(default_factory=TrajectoryBlocks)
    loss: RobustLoss | None = None
    consumed_redundancy = 0.0  # degrees of freedom spent before the adjustment (ObservationGroup): none
    name: str = "sbet"

    def __post_init__(self) -> None:
        self.time = np.asarray(self.time, dtype=float)
        m = self.time.size
        self.p_ref = np.asarray(self.p_ref, dtype=float).reshape(m, 3)
        self.R_ref = np.asarray(self.R_ref, dtype=float).reshape(m, 3, 3)
        if self.sigma_white_p <= 0 or self.sigma_white_theta <= 0:
            raise ValueError(f"{self.name}: white sigmas must be positive")
        self._k, u = self.grid.locate(self.time)
        self._w0 = position_basis(u, self.grid.dt, 0)
        self._j, self._lam = self.error_grid.weights(self.time)
        self._rows = np.arange(6 * m).reshape(m, 6)
        self._obs = np.repeat(np.arange(m), 6)

    def residuals_unweighted(self, values: Mapping[str, np.ndarray]) -> np.ndarray:
        """``(M, 6)``: position difference (m) and rotation (rad) of the spline from reference plus error."""
        return self._model(values, jacobians=False)[0]

    def _model(self, values, jacobians):
        P, V, A, R, W = self.blocks.knots(values)
        k, w0 = self._k, self._w0
        p = knot_sum(P, V, A, k, w0)
        ev = eval_orientation(self.grid, R, W, self.time, rate=False, jacobians=jacobians)
        phi = log_so3(ev.R_w_b @ np.swapaxes(self.R_ref, 1, 2))
        j, lam = self._j, self._lam[:, None]
        e_p = np.asarray(values[self.error_position])
        e_t = np.asarray(values[self.error_attitude])
        r = np.empty((self.time.size, 6))
        r[:, :3] = p - self.p_ref - ((1.0 - lam) * e_p[j] + lam * e_p[j + 1])
        r[:, 3:] = phi - ((1.0 - lam) * e_t[j] + lam * e_t[j + 1])
        return r, ev, phi

    def linearize(self, values: Mapping[str, np.ndarray], jacobians: bool = True) -> Linearization:
        r, ev, phi = self._model(values, jacobians)
        w = np.array([1.0 / self.sigma_white_p] * 3 + [1.0 / self.sigma_white_theta] * 3)
        jac = []
        if jacobians:
            m = self.time.size
            rows_p, rows_t = self._rows[:, :3], self._rows[:, 3:]
            I_p = np.broadcast_to(np.eye(3) * w[0], (m, 3, 3))
            jac += position_jacobians(self.blocks, rows_p, self._k, self._w0, I_p)
            M_R = (right_jacobian_inv(phi) @ self.R_ref) * w[3]
            jac += orientation_jacobians(self.blocks, rows_t, ev.jacobians, M_R)
            lam = self._lam[:, None, None]
            for block, rows, s in ((self.error_position, rows_p, w[0]), (self.error_attitude, rows_t, w[3])):
                D = np.broadcast_to(-np.eye(3) * s, (m, 3, 3))
                jac.append(JacobianBlock(block, rows, self._j, D * (1.0 - lam)))
                jac.append(JacobianBlock(block, rows, self._j + 1, D * lam))
        return Linearization((r * w).ravel(), jac, self._obs)


@dataclass
class GaussMarkovPrior:
    """First-order Gauss-Markov process on the knots of a (J, 3) block (see module docstring).

    Rows: ``e_0 / sigma_0`` and ``(e_{j+1} - phi e_j) / (sigma_{j+1} sqrt(1 - phi^2))`` per axis.

    Parameters
    ----------
    sigma : (J, 3)
        Stationary sigma at each knot (> 0).
    tau_s : float or (3,)
        Correlation time (s), per axis if given so.
    """

    name: str
    block: str
    grid: BiasGrid
    sigma: np.ndarray
    tau_s: float | np.ndarray
    loss: RobustLoss | None = None
    consumed_redundancy = 0.0  # degrees of freedom spent before the adjustment (ObservationGroup): none

    def __post_init__(self) -> None:
        self.sigma = np.broadcast_to(np.asarray(self.sigma, dtype=float), (self.grid.n_knots, 3)).copy()
        tau = np.broadcast_to(np.asarray(self.tau_s, dtype=float), (3,))
        if np.any(self.sigma <= 0) or not np.all(tau > 0):
            raise ValueError(f"{self.name}: sigma and the correlation time must be positive")
        self.phi = np.exp(-self.grid.dt_s / tau)

    def linearize(self, values: Mapping[str, np.ndarray], jacobians: bool = True) -> Linearization:
        e = np.asarray(values[self.block])
        n = e.shape[0]
        w0 = 1.0 / self.sigma[0]
        w = 1.0 / (self.sigma[1:] * np.sqrt(1.0 - self.phi**2))
        r = np.concatenate([e[0] * w0, ((e[1:] - self.phi * e[:-1]) * w).ravel()])
        rows = np.arange(3 * n).reshape(n, 3)
        jac = []
        if jacobians:
            jac.append(JacobianBlock(self.block, rows[:1], np.array([0]), np.diag(w0)[None]))
            if n > 1:
                D = np.zeros((n - 1, 3, 3))
                D[:, np.arange(3), np.arange(3)] = w
                jac.append(JacobianBlock(self.block, rows[1:], np.arange(n - 1), -D * self.phi[None, :, None]))
                jac.append(JacobianBlock(self.block, rows[1:], np.arange(1, n), D))
        return Linearization(r, jac, np.repeat(np.arange(n), 3))
