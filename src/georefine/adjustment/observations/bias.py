"""Piecewise-linear sensor biases and their random-walk pseudo-observations (docs/ARCHITECTURE.md §4.3).

A bias ``b(t)`` (e.g. accelerometer or gyro, 3 axes) lives on its own uniform knots
``t_j = t_start + j dt_b``; between knots it is linear. Its in-run change is constrained by
the random-walk model ``b_{j+1} - b_j ~ N(0, q^2 dt_b)`` with density ``q`` per axis
(from the datasheet bias instability ``B`` over the correlation time ``tau``:
``q = B sqrt(2 / tau)``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from georefine.adjustment.blocks import JacobianBlock, Linearization
from georefine.adjustment.robust import RobustLoss


@dataclass(frozen=True)
class BiasGrid:
    """Uniform bias knots ``t_start + j dt_s``, ``j = 0 .. n_knots-1`` (s, relative to the epoch)."""

    t_start: float
    dt_s: float
    n_knots: int

    @classmethod
    def covering(cls, t_first: float, t_last: float, dt_s: float) -> "BiasGrid":
        n = max(2, int(np.ceil((t_last - t_first) / dt_s - 1e-9)) + 1)
        return cls(float(t_first), float(dt_s), n)

    @property
    def times(self) -> np.ndarray:
        return self.t_start + self.dt_s * np.arange(self.n_knots)

    def weights(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Knot index ``j`` (N,) and weight ``lam`` (N,) with ``b(t) = (1-lam) b_j + lam b_{j+1}``."""
        s = (np.asarray(t, dtype=float) - self.t_start) / self.dt_s
        j = np.clip(np.floor(s).astype(np.int64), 0, self.n_knots - 2)
        return j, s - j

    def evaluate(self, b: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Bias values (N, 3) at times ``t`` from knot values ``b`` (n_knots, 3)."""
        j, lam = self.weights(t)
        return (1.0 - lam)[:, None] * b[j] + lam[:, None] * b[j + 1]


@dataclass
class BiasRandomWalk:
    """``r_j = (b_{j+1} - b_j) / (q sqrt(dt_b))`` for all consecutive bias knots of ``block``."""

    name: str
    block: str
    grid: BiasGrid
    q: np.ndarray  # (3,) random-walk density per axis (unit/s/sqrt(s) for rates)
    loss: RobustLoss | None = None
    consumed_redundancy = 0.0  # degrees of freedom spent before the adjustment (ObservationGroup): none

    def __post_init__(self) -> None:
        self.q = np.broadcast_to(np.asarray(self.q, dtype=float), (3,)).copy()
        if np.any(self.q <= 0):
            raise ValueError(f"{self.name}: random-walk density must be positive (use a floor)")

    def linearize(self, values: Mapping[str, np.ndarray], jacobians: bool = True) -> Linearization:
        b = np.asarray(values[self.block])
        n = b.shape[0] - 1
        w = 1.0 / (self.q * np.sqrt(self.grid.dt_s))
        r = ((b[1:] - b[:-1]) * w).ravel()
        rows = np.arange(3 * n).reshape(n, 3)
        jac = []
        if jacobians:
            D = np.broadcast_to(np.diag(w), (n, 3, 3))
            idx = np.arange(n)
            jac = [JacobianBlock(self.block, rows, idx, -D), JacobianBlock(self.block, rows, idx + 1, D.copy())]
        return Linearization(r, jac, np.repeat(np.arange(n), 3))
