"""GNSS antenna position observations (docs/ARCHITECTURE.md §4.3, paper 000 Eq. 3).

``p~_w = p_w(t) + R_w_b(t) p_b_a + d(t) + eps``, whitened with the covariance of ``eps``
rotated into ``w``: ``r = L (p_w(t) + R_w_b(t) p_b_a + d(t) - p~_w)``. ``d(t)``, the GNSS
error that lasts minutes, is optional: piecewise linear on its own knots (a
:class:`~georefine.adjustment.observations.bias.BiasGrid`, block ``error_block``), with a
Gauss-Markov prior (:class:`~georefine.adjustment.observations.trajectory_prior.GaussMarkovPrior`)
added by the problem builder; a second such process, the multipath that lasts tens of seconds
(``multipath_grid``, ``multipath_block``), adds to it where stated. Epochs of a segment without a fixed solution add that segment's
offset (block ``segment_block``, (S, 3); :mod:`georefine.adjustment.gnss_segments`). Right perturbation of ``R(t)`` gives
``d(R l)/d delta = -R skew(l)``. A robust loss (Huber by default) acts on the squared norm
of each epoch's whitened 3-vector, against multipath jumps.
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
    whitening,
)
from georefine.adjustment.robust import RobustLoss
from georefine.geometry.rotation import skew
from georefine.trajectory.spline import KnotGrid, eval_orientation, knot_sum, position_basis


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
    error_grid, error_block
        Knots and block name ((J, 3), m in ``w``) of the correlated GNSS error ``d(t)``; None:
        the error is white.
    multipath_grid, multipath_block
        Knots and block ((K, 3), m in ``w``) of the short-correlated error (multipath), added to
        ``d(t)``; None: not modelled.
    segment, segment_block
        Segment of each epoch ((M,) int, -1 for none) and the block of the segments' offsets
        ((S, 3), m in ``w``); None: no offsets.
    """

    grid: KnotGrid
    time: np.ndarray
    p_w: np.ndarray
    cov_w: np.ndarray
    p_b_a: np.ndarray
    loss: RobustLoss | None = None
    consumed_redundancy = 0.0  # degrees of freedom spent before the adjustment (ObservationGroup): none
    blocks: TrajectoryBlocks = field(default_factory=TrajectoryBlocks)
    name: str = "gnss"
    error_grid: BiasGrid | None = None
    error_block: str | None = None
    segment: np.ndarray | None = None
    segment_block: str | None = None
    multipath_grid: BiasGrid | None = None
    multipath_block: str | None = None

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
        if (self.error_grid is None) != (self.error_block is None):
            raise ValueError(f"{self.name}: error_grid and error_block go together")
        if self.error_grid is not None:
            self._j, self._lam = self.error_grid.weights(self.time)
        if (self.multipath_grid is None) != (self.multipath_block is None):
            raise ValueError(f"{self.name}: multipath_grid and multipath_block go together")
        if self.multipath_grid is not None:
            self._jm, self._lamm = self.multipath_grid.weights(self.time)
        if (self.segment is None) != (self.segment_block is None):
            raise ValueError(f"{self.name}: segment and segment_block go together")
        if self.segment is not None:
            self.segment = np.asarray(self.segment, dtype=np.int64).reshape(m)
            self._in_segment = np.flatnonzero(self.segment >= 0)

    def predict(self, values: Mapping[str, np.ndarray]) -> np.ndarray:
        """Modelled antenna positions (M, 3) in ``w``."""
        P, V, A, R, W = self.blocks.knots(values)
        return self._model(P, V, A, R, W, jacobians=False)[0] + self._error(values)

    def _error(self, values: Mapping[str, np.ndarray]) -> np.ndarray | float:
        """The correlated GNSS error ``d(t)``, the multipath and the segments' offsets at the epochs (M, 3), or 0."""
        out = 0.0
        if self.error_block is not None:
            out = self.error_grid.evaluate(np.asarray(values[self.error_block]), self.time)
        if self.multipath_block is not None:
            out = out + self.multipath_grid.evaluate(np.asarray(values[self.multipath_block]), self.time)
        if self.segment_block is not None:
            offset = np.zeros((self.time.size, 3))
            k = self._in_segment
            offset[k] = np.asarray(values[self.segment_block])[self.segment[k]]
            out = out + offset
        return out

    def _model(self, P, V, A, R, W, jacobians):
        k, w0 = self._k, self._w0
        p = knot_sum(P, V, A, k, w0)
        ev = eval_orientation(self.grid, R, W, self.time, rate=False, jacobians=jacobians)
        return p + ev.R_w_b @ self.p_b_a, ev

    def linearize(self, values: Mapping[str, np.ndarray], jacobians: bool = True) -> Linearization:
        P, V, A, R, W = self.blocks.knots(values)
        model, ev = self._model(P, V, A, R, W, jacobians)
        r = np.einsum("nij,nj->ni", self._L, model + self._error(values) - self.p_w)
        jac = []
        if jacobians:
            L = self._L
            jac += position_jacobians(self.blocks, self._rows, self._k, self._w0, L)
            M_R = -L @ ev.R_w_b @ skew(self.p_b_a)
            jac += orientation_jacobians(self.blocks, self._rows, ev.jacobians, M_R)
            if self.error_block is not None:
                lam = self._lam[:, None, None]
                jac.append(JacobianBlock(self.error_block, self._rows, self._j, L * (1.0 - lam)))
                jac.append(JacobianBlock(self.error_block, self._rows, self._j + 1, L * lam))
            if self.multipath_block is not None:
                lam = self._lamm[:, None, None]
                jac.append(JacobianBlock(self.multipath_block, self._rows, self._jm, L * (1.0 - lam)))
                jac.append(JacobianBlock(self.multipath_block, self._rows, self._jm + 1, L * lam))
            if self.segment_block is not None and self._in_segment.size:
                k = self._in_segment
                jac.append(JacobianBlock(self.segment_block, self._rows[k], self.segment[k], L[k]))
        return Linearization(r.ravel(), jac, self._obs)
