"""Names of the parameter blocks of a spline trajectory and helpers shared by its observations.

A continuous-time trajectory (docs/ARCHITECTURE.md §4.2) enters the adjustment as five blocks over the knots
of a :class:`~georefine.trajectory.spline.KnotGrid`: positions, velocities, accelerations
(Euclidean, (K, 3) each), attitudes (SO(3), (K, 3, 3)) and body rates (Euclidean, (K, 3)).
Observation groups receive a :class:`TrajectoryBlocks` so that several trajectories (or
renamed blocks) can live in one problem.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from georefine.adjustment.blocks import JacobianBlock
from georefine.trajectory.spline import OrientationJacobians


@dataclass(frozen=True)
class TrajectoryBlocks:
    """Block names of one spline trajectory."""

    position: str = "p_w_b"
    velocity: str = "v_w_b"
    acceleration: str = "a_w_b"
    attitude: str = "R_w_b"
    rate: str = "omega_wb_b"

    @property
    def position_states(self) -> tuple[str, str, str, str, str, str]:
        """Block of each column of :func:`~georefine.trajectory.spline.position_basis`."""
        return (self.position, self.velocity, self.acceleration) * 2

    def knots(self, values) -> tuple[np.ndarray, ...]:
        """``(P, V, A, R, W)`` knot arrays from a values mapping."""
        return tuple(np.asarray(values[n]) for n in (self.position, self.velocity, self.acceleration, self.attitude, self.rate))


def position_jacobians(
    blocks: TrajectoryBlocks, rows: np.ndarray, k: np.ndarray, weights: np.ndarray, M: np.ndarray
) -> list[JacobianBlock]:
    """Jacobian blocks of ``M @ (d^r p / dt^r)(t)`` w.r.t. the six position knot states.

    Parameters
    ----------
    rows : (N, m) residual rows; k : (N,) knot interval; weights : (N, 6) position basis;
    M : (N, m, 3) the residual's derivative w.r.t. the position derivative.
    """
    out = []
    for j, name in enumerate(blocks.position_states):
        elem = k if j < 3 else k + 1
        out.append(JacobianBlock(name, rows, elem, M * weights[:, j, None, None]))
    return out


def orientation_jacobians(
    blocks: TrajectoryBlocks, rows: np.ndarray, jac: OrientationJacobians, M_R: np.ndarray | None, M_w: np.ndarray | None = None
) -> list[JacobianBlock]:
    """Jacobian blocks of a residual depending on ``R(t)`` (via ``M_R @ delta``) and ``omega(t)`` (via ``M_w``).

    ``M_R``: (N, m, 3) derivative w.r.t. the right tangent of ``R(t)``; ``M_w``: (N, m, 3)
    derivative w.r.t. ``omega(t)`` (or None).
    """
    total = 0.0
    if M_R is not None:
        total = total + M_R @ jac.dR
    if M_w is not None:
        total = total + M_w @ jac.domega
    k = jac.k
    return [
        JacobianBlock(blocks.attitude, rows, k, total[:, :, 0:3]),
        JacobianBlock(blocks.rate, rows, k, total[:, :, 3:6]),
        JacobianBlock(blocks.attitude, rows, k + 1, total[:, :, 6:9]),
        JacobianBlock(blocks.rate, rows, k + 1, total[:, :, 9:12]),
    ]


def checked_rows(owner: str, name: str, value, n: int, width: int | None = 3) -> np.ndarray:
    """``value`` as float ``(n, width)``, or ``(n,)`` when ``width`` is None (a scalar broadcasts
    then), finite; else a ValueError naming ``owner`` and ``name``."""
    arr = np.asarray(value, dtype=float)
    shape = (n,) if width is None else (n, width)
    if width is None and arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != shape:
        raise ValueError(f"{owner}: {name} must have shape {shape}, found {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{owner}: {name} contains NaN or inf")
    return arr


def single_element(values, name: str, shape: tuple[int, ...]) -> np.ndarray:
    """The one element of a calibration block (``(1,) + shape``: boresight, lever arm, time offset)."""
    arr = np.asarray(values[name], dtype=float)
    if arr.shape != (1,) + shape:
        raise ValueError(f"block {name!r} must have shape {(1,) + shape}, found {arr.shape}")
    return arr[0]


def whitening(cov: np.ndarray) -> np.ndarray:
    """Whitening matrices ``L`` (N, 3, 3) with ``L^T L = cov^-1`` (``L = C^-1``, ``cov = C C^T``)."""
    C = np.linalg.cholesky(cov)
    eye = np.broadcast_to(np.eye(cov.shape[-1]), cov.shape)
    return np.linalg.solve(C, eye)
