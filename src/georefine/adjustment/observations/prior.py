"""Prior (pseudo-)observations on parameter elements (docs/ARCHITECTURE.md §4.3 "Priors").

``EuclideanPrior``: ``r = L (x - x0)`` per element, ``L`` the whitening matrix of the prior
covariance (diagonal sigma or full square-root information). ``RotationPrior``:
``r = Log(R0^T R) / sigma``; its Jacobian w.r.t. the right perturbation ``R <- R Exp(d)`` is
``Jr^-1(Log(R0^T R)) / sigma``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from georefine.adjustment.blocks import JacobianBlock, Linearization
from georefine.adjustment.robust import RobustLoss
from georefine.geometry.rotation import log_so3, right_jacobian_inv


def _rows(n: int, m: int) -> np.ndarray:
    return np.arange(n * m).reshape(n, m)


@dataclass
class EuclideanPrior:
    """Prior ``x_e ~ N(mean_e, diag(sigma_e^2))`` on elements ``elements`` of a Euclidean block.

    Parameters
    ----------
    name
        Group name (statistics).
    block
        Parameter block name.
    elements : (n,) int
        Element indices within the block.
    mean : (n, d)
        Prior values.
    sigma : (n, d)
        Prior standard deviations (> 0), in the block's units.
    """

    name: str
    block: str
    elements: np.ndarray
    mean: np.ndarray
    sigma: np.ndarray
    loss: RobustLoss | None = None
    consumed_redundancy = 0.0  # degrees of freedom spent before the adjustment (ObservationGroup): none
    _w: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.elements = np.atleast_1d(np.asarray(self.elements, dtype=np.int64))
        n = self.elements.size
        self.mean = np.asarray(self.mean, dtype=float).reshape(n, -1)
        self.sigma = np.broadcast_to(np.asarray(self.sigma, dtype=float), self.mean.shape).copy()
        if np.any(self.sigma <= 0):
            raise ValueError(f"prior {self.name}: sigma must be positive")
        self._w = 1.0 / self.sigma

    def linearize(self, values: Mapping[str, np.ndarray], jacobians: bool = True) -> Linearization:
        x = np.asarray(values[self.block])[self.elements].reshape(self.mean.shape)
        n, d = self.mean.shape
        r = ((x - self.mean) * self._w).ravel()
        obs = np.repeat(np.arange(n), d)
        jac = []
        if jacobians:
            J = np.zeros((n, d, d))
            J[:, np.arange(d), np.arange(d)] = self._w
            jac.append(JacobianBlock(self.block, _rows(n, d), self.elements, J))
        return Linearization(r, jac, obs)


@dataclass
class RotationPrior:
    """Prior on rotations: ``Log(R0^T R) ~ N(0, diag(sigma^2))`` (body-frame tangent)."""

    name: str
    block: str
    elements: np.ndarray
    mean: np.ndarray  # (n, 3, 3)
    sigma: np.ndarray  # (n, 3) rad
    loss: RobustLoss | None = None
    consumed_redundancy = 0.0  # degrees of freedom spent before the adjustment (ObservationGroup): none

    def __post_init__(self) -> None:
        self.elements = np.atleast_1d(np.asarray(self.elements, dtype=np.int64))
        n = self.elements.size
        self.mean = np.asarray(self.mean, dtype=float).reshape(n, 3, 3)
        self.sigma = np.broadcast_to(np.asarray(self.sigma, dtype=float), (n, 3)).copy()
        if np.any(self.sigma <= 0):
            raise ValueError(f"prior {self.name}: sigma must be positive")

    def linearize(self, values: Mapping[str, np.ndarray], jacobians: bool = True) -> Linearization:
        R = np.asarray(values[self.block])[self.elements]
        e = log_so3(np.swapaxes(self.mean, 1, 2) @ R)
        w = 1.0 / self.sigma
        n = e.shape[0]
        jac = []
        if jacobians:
            J = w[:, :, None] * right_jacobian_inv(e)
            jac.append(JacobianBlock(self.block, _rows(n, 3), self.elements, J))
        return Linearization((e * w).ravel(), jac, np.repeat(np.arange(n), 3))
