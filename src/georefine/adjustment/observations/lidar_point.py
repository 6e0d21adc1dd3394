"""LiDAR returns observing tie points through the trajectory (docs/ARCHITECTURE.md §4.3, §4.8).

A lidargram pixel remembers the LiDAR return it shows (its ULPI): the return's time ``t`` and
its vector ``x_s`` in the scanner frame. A keypoint matched in that lidargram observes a tie
point ``X`` (in ``w``), which the photos observe too by reprojection
(:class:`~georefine.adjustment.observations.reprojection.ReprojectionObservation`). The return
was georeferenced through the trajectory at ``t``, so

``r = L (p_w_b(t) + R_w_b(t) (p_b_s + R_b_s x_s) + d - X)``

is an observation of the spline trajectory, the mounting calibration and the tie point at
once: the relation that lets photos correct the trajectory within a lidargram's footprint,
where paper 004 moves each lidargram rigidly. ``d`` (``offset_w``, constant, zero by default)
is what separates the keypoint's surface point from the return its pixel shows, as far as the
lidargram knows it: the keypoint's offset from the return's exact projection, in the image
plane at the return's depth (a pixel of a sparse cloud's lidargram shows a return up to half a
point spacing away).

Weights: the return's ranging noise ``sigma_range`` along the beam ``u`` (a unit vector in
``w``, from the preliminary georeferencing) and ``sigma_across`` perpendicular to it, which
holds the offset between the keypoint's surface point and the return the pixel shows (half the
pixel footprint, the keypoint's localisation) and the beam divergence. Their covariance
``sigma_across^2 I + (sigma_range^2 - sigma_across^2) u u^T`` has the whitening
``L = (I - u u^T) / sigma_across + u u^T / sigma_range`` in closed form. ``u`` is fixed at
construction: weights do not follow the iterations (as every group's).

Jacobians (right perturbations ``R <- R Exp(delta)``, docs/ARCHITECTURE.md §2;
``d (R x) / d delta = -R skew(x)``), with ``x_b = p_b_s + R_b_s x_s``:

* trajectory: ``L`` times the position-basis weights of the six position knot states;
  ``-L R_w_b skew(x_b)`` w.r.t. the right tangent of ``R_w_b(t)``, chained to the knots with
  :attr:`~georefine.trajectory.spline.OrientationJacobians.dR`;
* tie point: ``-L``;
* boresight ``R_b_s <- R_b_s Exp(eps)``: ``-L R_w_b R_b_s skew(x_s)``; lever arm: ``L R_w_b``;
* LiDAR time offset ``tau`` (the return is georeferenced at ``t + tau``):
  ``L (v_w_b + R_w_b (omega x x_b))``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from georefine.adjustment.blocks import JacobianBlock, Linearization
from georefine.adjustment.observations.trajectory_blocks import (
    TrajectoryBlocks,
    checked_rows,
    orientation_jacobians,
    position_jacobians,
    single_element,
)
from georefine.adjustment.robust import RobustLoss
from georefine.geometry.rotation import skew
from georefine.trajectory.spline import KnotGrid, eval_orientation, knot_sum, locate_near, position_basis

__all__ = ["LidarPointObservation", "beam_whitening"]

_UNIT_TOL = 1e-6


def beam_whitening(beam_w: np.ndarray, sigma_range: np.ndarray, sigma_across: np.ndarray) -> np.ndarray:
    """Whitening matrices ``L`` (N, 3, 3) of a return's position (module docstring).

    ``L^T L`` is the inverse of ``sigma_across^2 I + (sigma_range^2 - sigma_across^2) u u^T``.
    """
    u = np.asarray(beam_w, dtype=float).reshape(-1, 3)
    uu = u[:, :, None] * u[:, None, :]
    a = np.asarray(sigma_across, dtype=float).reshape(-1, 1, 1)
    r = np.asarray(sigma_range, dtype=float).reshape(-1, 1, 1)
    return (np.eye(3) - uu) / a + uu / r


def _rows(name: str, value, n: int, width: int | None) -> np.ndarray:
    return checked_rows("LidarPointObservation", name, value, n, width)


@dataclass
class LidarPointObservation:
    """LiDAR returns (time, scanner-frame vector) observing tie points through a spline trajectory.

    One observation of three whitened rows per return (module docstring).

    Parameters
    ----------
    grid
        Knot grid of the trajectory.
    time : (N,)
        Return times, s relative to the dataset epoch, inside the grid's span.
    x_s : (N, 3)
        Return vectors in the scanner frame (m).
    point_index : (N,) int
        Tie point of each return (element of the ``points`` block).
    beam_w : (N, 3)
        Unit beam directions in ``w`` (weights only).
    sigma_range, sigma_across : (N,) or scalar
        Standard deviations along and across the beam (m).
    p_b_s, R_b_s
        Lever arm (m) and boresight, used when the ``lever_arm`` / ``boresight`` block is None.
    points
        Euclidean block ``(M, 3)`` of tie points in ``w``.
    offset_w : (N, 3), optional
        Constant offset ``d`` from the return to the observed surface point, in ``w`` (m); zero
        when None.
    boresight, lever_arm, time_offset
        Optional blocks ``(1, 3, 3)`` so3, ``(1, 3)`` and ``(1, 1)`` (s).
    blocks
        Trajectory block names.
    loss
        Robust loss per return (against wrong matches); None = plain least squares.
    name
        Group name.
    """

    grid: KnotGrid
    time: np.ndarray
    x_s: np.ndarray
    point_index: np.ndarray
    beam_w: np.ndarray
    sigma_range: np.ndarray
    sigma_across: np.ndarray
    p_b_s: np.ndarray
    R_b_s: np.ndarray
    points: str = "points"
    offset_w: np.ndarray | None = None
    boresight: str | None = None
    lever_arm: str | None = None
    time_offset: str | None = None
    blocks: TrajectoryBlocks = field(default_factory=TrajectoryBlocks)
    loss: RobustLoss | None = None
    consumed_redundancy = 0.0  # degrees of freedom spent before the adjustment (ObservationGroup): none
    name: str = "lidar_points"

    def __post_init__(self) -> None:
        self.time = np.atleast_1d(np.asarray(self.time, dtype=float))
        if self.time.ndim != 1:
            raise ValueError(f"LidarPointObservation: time must be 1-D, found shape {self.time.shape}")
        n = self.time.size
        if not np.all(np.isfinite(self.time)):
            raise ValueError("LidarPointObservation: time contains NaN or inf")
        if n and (self.time.min() < self.grid.t_start or self.time.max() > self.grid.t_end):
            raise ValueError(f"LidarPointObservation: times {self.time.min():.3f} .. {self.time.max():.3f} s leave the "
                             f"trajectory's span {self.grid.t_start:.3f} .. {self.grid.t_end:.3f} s")
        self.x_s = _rows("x_s", self.x_s, n, 3)
        self.beam_w = _rows("beam_w", self.beam_w, n, 3)
        self.offset_w = np.zeros((n, 3)) if self.offset_w is None else _rows("offset_w", self.offset_w, n, 3)
        if np.any(np.abs(np.linalg.norm(self.beam_w, axis=1) - 1.0) > _UNIT_TOL):
            raise ValueError("LidarPointObservation: beam_w must be unit vectors")
        self.sigma_range = _rows("sigma_range", self.sigma_range, n, None)
        self.sigma_across = _rows("sigma_across", self.sigma_across, n, None)
        if np.any(self.sigma_range <= 0) or np.any(self.sigma_across <= 0):
            raise ValueError("LidarPointObservation: sigma_range and sigma_across must be positive")
        idx = np.asarray(self.point_index)
        if idx.shape != (n,) or (n and not np.issubdtype(idx.dtype, np.integer)) or (n and idx.min() < 0):
            raise ValueError(f"LidarPointObservation: point_index must be ({n},) non-negative integers, "
                             f"found {idx.shape} {idx.dtype}")
        self.point_index = idx.astype(np.int64)
        self.p_b_s = np.asarray(self.p_b_s, dtype=float).reshape(3)
        self.R_b_s = np.asarray(self.R_b_s, dtype=float).reshape(3, 3)
        if np.abs(self.R_b_s @ self.R_b_s.T - np.eye(3)).max() > _UNIT_TOL or np.linalg.det(self.R_b_s) <= 0:
            raise ValueError("LidarPointObservation: R_b_s is not a rotation matrix")
        self._L = beam_whitening(self.beam_w, self.sigma_range, self.sigma_across)
        self._k, u = self.grid.locate(self.time) if n else (np.zeros(0, np.int64), np.zeros(0))
        self._w0 = position_basis(u, self.grid.dt, 0)
        self._rows = np.arange(3 * n).reshape(n, 3)
        self._obs = np.repeat(np.arange(n), 3)

    def __len__(self) -> int:
        return int(self.time.size)

    def calibration(self, values: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Current ``(R_b_s (3,3), p_b_s (3,))``: from the blocks when named, else the fixed ones."""
        R_b_s = single_element(values, self.boresight, (3, 3)) if self.boresight else self.R_b_s
        p_b_s = single_element(values, self.lever_arm, (3,)) if self.lever_arm else self.p_b_s
        return R_b_s, p_b_s

    def _located(self, values):
        if self.time_offset is None:
            return self.time, self._k, None, self._w0
        tau = single_element(values, self.time_offset, (1,))[0]
        t = np.clip(self.time + tau, self.grid.t_start, self.grid.t_end)
        k, u = locate_near(self.grid, t, self._k)  # the stamps' intervals: J keeps its structure
        return t, k, u, position_basis(u, self.grid.dt, 0)

    def georeference(self, values: Mapping[str, np.ndarray]) -> np.ndarray:
        """The returns in ``w`` (N, 3) with the current trajectory, calibration and time offset,
        plus ``offset_w``: the surface points they observe."""
        return self._model(values, self._located(values), jacobians=False)[-1]

    def _model(self, values, located, jacobians: bool):
        P, V, A, R, W = self.blocks.knots(values)
        t, k, u, w0 = located
        p = knot_sum(P, V, A, k, w0)
        ev = eval_orientation(self.grid, R, W, t, rate=jacobians and self.time_offset is not None, jacobians=jacobians,
                              located=None if u is None else (k, u))
        R_b_s, p_b_s = self.calibration(values)
        x_b = p_b_s + self.x_s @ R_b_s.T
        return ev, R_b_s, x_b, p + np.einsum("nij,nj->ni", ev.R_w_b, x_b) + self.offset_w

    def linearize(self, values: Mapping[str, np.ndarray], jacobians: bool = True) -> Linearization:
        """Whitened residuals (3 rows per return) and Jacobian blocks; see the module docstring."""
        n = len(self)
        X = np.asarray(values[self.points], dtype=float)
        if X.ndim != 2 or X.shape[1] != 3 or (n and self.point_index.max() >= X.shape[0]):
            raise ValueError(f"block {self.points!r} of shape {X.shape} does not hold the points "
                             f"0 .. {self.point_index.max() if n else 0} this group observes")
        if n == 0:
            return Linearization(np.zeros(0), [], np.zeros(0, dtype=np.int64))
        located = self._located(values)
        ev, R_b_s, x_b, x_w = self._model(values, located, jacobians)
        L = self._L
        r = np.einsum("nij,nj->ni", L, x_w - X[self.point_index])
        if not jacobians:
            return Linearization(r.ravel(), [], self._obs)
        rows = self._rows
        _, k_t, u_t, w0_t = located
        jac = position_jacobians(self.blocks, rows, k_t, w0_t, L)
        L_R = L @ ev.R_w_b
        jac += orientation_jacobians(self.blocks, rows, ev.jacobians, -L_R @ skew(x_b))
        jac.append(JacobianBlock(self.points, rows, self.point_index, -L))
        zeros = np.zeros(n, dtype=np.int64)
        if self.boresight is not None:
            jac.append(JacobianBlock(self.boresight, rows, zeros, -(L_R @ R_b_s) @ skew(self.x_s)))
        if self.lever_arm is not None:
            jac.append(JacobianBlock(self.lever_arm, rows, zeros, L_R))
        if self.time_offset is not None:
            P, V, A, _, _ = self.blocks.knots(values)
            v = knot_sum(P, V, A, k_t, position_basis(u_t, self.grid.dt, 1))
            dx_dt = v + np.einsum("nij,nj->ni", ev.R_w_b, np.cross(ev.omega_wb_b, x_b))
            jac.append(JacobianBlock(self.time_offset, rows, zeros, np.einsum("nij,nj->ni", L, dx_dt)[:, :, None]))
        return Linearization(r.ravel(), jac, self._obs)
