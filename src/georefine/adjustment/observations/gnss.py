"""GNSS antenna position observations (docs/ARCHITECTURE.md §4.3, paper 000 Eq. 3).

``p~_w = p_w(t) + R_w_b(t) p_b_a + eps``, whitened with the ``.pos`` covariance rotated into
``w``: ``r = L (p_w(t) + R_w_b(t) p_b_a - p~_w)``. Right perturbation of ``R(t)`` gives
``d(R l)/d delta = -R skew(l)``. A robust loss (Huber by default) acts on the squared norm
of each epoch's whitened 3-vector, against multipath jumps.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from georefine.adjustment.blocks import Linearization
from georefine.adjustment.observations.trajectory_blocks import (
    TrajectoryBlocks,
    orientation_jacobians,
    position_jacobians,
    whitening,
)
from georefine.adjustment.robust import RobustLoss
from georefine.geometry.rotation import skew
from georefine.trajectory.spline import KnotGrid, eval_orientation, position_basis


@dataclass
class GnssPositionObservation:
    """Antenna positions at epochs ``time`` with covariances, observing a spline trajectory.

    Parameters
    ----------
    grid
        Knot grid of the trajectory.
    time : (M,)
        Epochs, s relative to the dataset epoch, inside the grid's span.
    p_w : (M, 3)
        Measured antenna positions in ``w`` (m).
    cov_w : (M, 3, 3)
        Their covariances in ``w`` (m²).
    p_b_a : (3,)
        Antenna lever arm in the body frame (m).
    """

    grid: KnotGrid
    time: np.ndarray
    p_w: np.ndarray
    cov_w: np.ndarray
    p_b_a: np.ndarray
    loss: RobustLoss | None = None
    blocks: TrajectoryBlocks = field(default_factory=TrajectoryBlocks)
    name: str = "gnss"

    def __post_init__(self) -> None:
        self.time = np.asarray(self.time, dtype=float)
        m = self.time.size
        self.p_w = np.asarray(self.p_w, dtype=float).reshape(m, 3)
        self.p_b_a = np.asarray(self.p_b_a, dtype=float).reshape(3)
        self._L = whitening(np.asarray(self.cov_w, dtype=float).reshape(m, 3, 3))
        self._k, u = self.grid.locate(self.time)
        self._w0 = position_basis(u, self.grid.dt, 0)
        self._rows = np.arange(3 * m).reshape(m, 3)
        self._obs = np.repeat(np.arange(m), 3)

    def predict(self, values: Mapping[str, np.ndarray]) -> np.ndarray:
        """Modelled antenna positions (M, 3) in ``w``."""
        P, V, A, R, W = self.blocks.knots(values)
        return self._model(P, V, A, R, W, jacobians=False)[0]

    def _model(self, P, V, A, R, W, jacobians):
        k, w0 = self._k, self._w0
        p = (
            w0[:, 0:1] * P[k] + w0[:, 1:2] * V[k] + w0[:, 2:3] * A[k]
            + w0[:, 3:4] * P[k + 1] + w0[:, 4:5] * V[k + 1] + w0[:, 5:6] * A[k + 1]
        )
        ev = eval_orientation(self.grid, R, W, self.time, rate=False, jacobians=jacobians)
        return p + ev.R_w_b @ self.p_b_a, ev

    def linearize(self, values: Mapping[str, np.ndarray], jacobians: bool = True) -> Linearization:
        P, V, A, R, W = self.blocks.knots(values)
        model, ev = self._model(P, V, A, R, W, jacobians)
        r = np.einsum("nij,nj->ni", self._L, model - self.p_w)
        jac = []
        if jacobians:
            L = self._L
            jac += position_jacobians(self.blocks, self._rows, self._k, self._w0, L)
            M_R = -L @ ev.R_w_b @ skew(self.p_b_a)
            jac += orientation_jacobians(self.blocks, self._rows, ev.jacobians, M_R)
        return Linearization(r.ravel(), jac, self._obs)
