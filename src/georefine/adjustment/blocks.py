"""The model of a least-squares problem: parameter blocks, Jacobian blocks, observation groups.

These are the types that :mod:`georefine.adjustment.problem` (the problem a user builds) and
:mod:`georefine.adjustment.solver` (Levenberg-Marquardt) share; keeping them here lets the
problem call the solver without the solver importing the problem (docs/ARCHITECTURE.md §1).

Manifolds and retractions
    ``"euclidean"``: values ``(n, d)``, tangent dimension ``d``, ``x <- x + delta``.
    ``"so3"``: rotation matrices ``(n, 3, 3)``, tangent dimension 3, right perturbation in the
    body frame ``R <- R @ Exp(delta)`` (the project convention, docs/ARCHITECTURE.md §2).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal, Protocol, runtime_checkable

import numpy as np

from georefine.adjustment.robust import RobustLoss
from georefine.geometry.rotation import exp_so3

__all__ = [
    "Manifold",
    "ParameterBlock",
    "JacobianBlock",
    "Linearization",
    "ObservationGroup",
    "ColumnLayout",
    "constant_mask",
    "tangent_dim",
    "retract",
]

Manifold = Literal["euclidean", "so3"]
_MANIFOLDS = ("euclidean", "so3")
_ORTHONORMAL_TOL = 1e-6


Manifold = Literal["euclidean", "so3"]
_MANIFOLDS = ("euclidean", "so3")
_ORTHONORMAL_TOL = 1e-6


def tangent_dim(manifold: str, values: np.ndarray) -> int:
    """Tangent dimension of one element: ``d`` (euclidean ``(n, d)``) or 3 (so3)."""
    return 3 if manifold == "so3" else int(values.shape[1])


def retract(manifold: str, values: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Apply the retraction element-wise: ``x + delta`` or ``R @ Exp(delta)``.

    Parameters
    ----------
    manifold
        ``"euclidean"`` or ``"so3"``.
    values
        ``(k, d)`` or ``(k, 3, 3)`` elements.
    delta
        ``(k, d)`` or ``(k, 3)`` tangent increments.

    Returns
    -------
    np.ndarray
        New elements (a new array).
    """
    if manifold == "so3":
        return values @ exp_so3(delta)
    return values + delta


@dataclass
class ParameterBlock:
    """A named stack of ``n`` parameters on one manifold.

    Attributes
    ----------
    name
        Unique block name (observation groups refer to it).
    values
        ``(n, d)`` (euclidean) or ``(n, 3, 3)`` rotation matrices (so3).
    manifold
        ``"euclidean"`` or ``"so3"``.
    constant
        ``(n,)`` bool: element held constant (no columns in the normal equations).
    """

    name: str
    values: np.ndarray
    manifold: Manifold = "euclidean"
    constant: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.manifold not in _MANIFOLDS:
            raise ValueError(f"block {self.name!r}: manifold must be one of {_MANIFOLDS}, found {self.manifold!r}")
        values = np.array(self.values, dtype=float, copy=True)
        if self.manifold == "so3":
            if values.ndim != 3 or values.shape[1:] != (3, 3):
                raise ValueError(f"block {self.name!r}: so3 values must have shape (n, 3, 3), found {values.shape}")
            err = np.abs(values @ np.swapaxes(values, 1, 2) - np.eye(3)).max(initial=0.0)
            if err > _ORTHONORMAL_TOL or np.any(np.linalg.det(values) <= 0):
                raise ValueError(f"block {self.name!r}: so3 values are not rotation matrices (|R R^T - I| = {err:.1e})")
        elif values.ndim != 2:
            raise ValueError(f"block {self.name!r}: euclidean values must have shape (n, d), found {values.shape}")
        if not np.all(np.isfinite(values)):
            raise ValueError(f"block {self.name!r}: values contain NaN or inf")
        self.values = values
        self.constant = constant_mask(self.name, self.constant, values.shape[0])

    @property
    def size(self) -> int:
        """Number of elements ``n``."""
        return int(self.values.shape[0])

    @property
    def dim(self) -> int:
        """Tangent dimension of one element."""
        return tangent_dim(self.manifold, self.values)


def constant_mask(name: str, mask: np.ndarray | bool | None, n: int) -> np.ndarray:
    if mask is None:
        return np.zeros(n, dtype=bool)
    mask = np.asarray(mask)
    if mask.ndim == 0:
        return np.full(n, bool(mask))
    if mask.shape != (n,):
        raise ValueError(f"block {name!r}: constant mask must be a bool or shape ({n},), found {mask.shape}")
    return mask.astype(bool)


@dataclass(frozen=True)
class JacobianBlock:
    """Jacobian of some residual rows with respect to some elements of one block.

    Attributes
    ----------
    block
        Parameter block name.
    rows
        ``(N, m)`` int: rows (into the group's residual vector) of the ``N`` entries.
    elements
        ``(N,)`` int: element index within the block.
    values
        ``(N, m, d)``: ``d r[rows[k]] / d delta[elements[k]]``, ``d`` the block's tangent dimension.
    """

    block: str
    rows: np.ndarray
    elements: np.ndarray
    values: np.ndarray

    def __post_init__(self) -> None:
        rows, elements, values = np.asarray(self.rows), np.asarray(self.elements), np.asarray(self.values, dtype=float)
        if rows.ndim != 2 or elements.ndim != 1 or values.ndim != 3:
            raise ValueError(
                f"JacobianBlock {self.block!r}: expected rows (N, m), elements (N,), values (N, m, d); found "
                f"{rows.shape}, {elements.shape}, {values.shape}"
            )
        if values.shape[:2] != rows.shape or elements.shape[0] != rows.shape[0]:
            raise ValueError(
                f"JacobianBlock {self.block!r}: inconsistent shapes rows {rows.shape}, elements {elements.shape}, "
                f"values {values.shape}"
            )
        object.__setattr__(self, "rows", rows)
        object.__setattr__(self, "elements", elements)
        object.__setattr__(self, "values", values)


@dataclass(frozen=True)
class Linearization:
    """Residuals and (optionally) Jacobians of one observation group.

    Attributes
    ----------
    residuals
        ``(M,)`` whitened residuals ``r = Sigma^{-1/2} (model - measurement)``.
    jacobians
        :class:`JacobianBlock` list; empty when not requested.
    observation
        ``(M,)`` int >= 0: observation index of every row (rows of one observation share a
        robust weight, e.g. the three rows of a GNSS epoch).
    """

    residuals: np.ndarray
    jacobians: list[JacobianBlock] = field(default_factory=list)
    observation: np.ndarray | None = None

    def __post_init__(self) -> None:
        r = np.asarray(self.residuals, dtype=float)
        if r.ndim != 1:
            raise ValueError(f"Linearization: residuals must be 1-D, found shape {r.shape}")
        obs = np.arange(r.size) if self.observation is None else np.asarray(self.observation)
        if obs.shape != r.shape:
            raise ValueError(f"Linearization: observation must have shape {r.shape}, found {obs.shape}")
        if obs.size and obs.min() < 0:
            raise ValueError("Linearization: observation indices must be >= 0")
        object.__setattr__(self, "residuals", r)
        object.__setattr__(self, "observation", obs.astype(np.int64, copy=False))
        object.__setattr__(self, "jacobians", list(self.jacobians))


@runtime_checkable
class ObservationGroup(Protocol):
    """A set of observations evaluated together (vectorised).

    Attributes
    ----------
    name
        Unique group name (used in the statistics).
    loss
        Robust loss acting on each observation's squared whitened norm; ``None`` = plain LS.
    consumed_redundancy
        Degrees of freedom the observations spent before the adjustment (readings cleaned of a
        signal fitted to themselves: ``ImuObservation``'s vibration windows), which the
        redundancy, the variance factor and the variance components subtract; 0 for most groups.
    """

    name: str
    loss: RobustLoss | None
    consumed_redundancy: float

    def linearize(self, values: Mapping[str, np.ndarray], jacobians: bool = True) -> Linearization:
        """Residuals and, if ``jacobians``, Jacobian blocks at ``values`` (block name -> array)."""
        ...


@dataclass
class ColumnLayout:
    """Columns of the free elements in the normal equations.

    Blocks in insertion order, elements in index order, ``d`` consecutive columns per free
    element; consecutive blocks with as many elements as each other are interleaved element by
    element (the knot states ``p, v, a, R, omega`` of a spline: knot ``k``'s 15 columns side by
    side). An observation at one time then touches a few contiguous runs of columns instead of
    one run in each block's region: at 60 minutes of flight the assembly of ``J`` and of
    ``J^T J`` had gone 1.4 times superlinear from scattered memory access.

    Attributes
    ----------
    col_start
        Block name -> ``(n,)`` int64: first column of each element, -1 for constant ones.
    dims
        Block name -> tangent dimension.
    manifolds
        Block name -> manifold.
    free
        Block name -> indices of the free elements.
    n_cols
        Number of unknowns.
    """

    col_start: dict[str, np.ndarray]
    dims: dict[str, int]
    manifolds: dict[str, str]
    free: dict[str, np.ndarray]
    n_cols: int

    @classmethod
    def build(cls, blocks: Mapping[str, ParameterBlock]) -> ColumnLayout:
        """Layout of the current constant masks of ``blocks``."""
        col_start, dims, manifolds, free, offset = {}, {}, {}, {}, 0
        names = list(blocks)
        i = 0
        while i < len(names):
            group = [names[i]]
            while i + len(group) < len(names) and blocks[names[i + len(group)]].size == blocks[names[i]].size:
                group.append(names[i + len(group)])
            i += len(group)
            # Columns per element and block of the group: d where the element is free, else 0.
            width = np.stack([np.where(blocks[n].constant, 0, blocks[n].dim) for n in group]).astype(np.int64)
            if width.shape[1] == 0:
                before = np.zeros_like(width)
            else:
                per_element = np.concatenate([[0], np.cumsum(width.sum(axis=0))[:-1]])
                before = per_element[None, :] + np.cumsum(width, axis=0) - width
            for row, name in enumerate(group):
                block = blocks[name]
                idx = np.flatnonzero(~block.constant)
                starts = np.full(block.size, -1, dtype=np.int64)
                starts[idx] = offset + before[row, idx]
                col_start[name], dims[name], manifolds[name], free[name] = starts, block.dim, block.manifold, idx
            offset += int(width.sum())
        return cls(col_start, dims, manifolds, free, offset)

    def apply_step(self, values: Mapping[str, np.ndarray], delta: np.ndarray) -> dict[str, np.ndarray]:
        """Retract the free elements by the global tangent step ``delta`` ``(n_cols,)``.

        Returns new read-only arrays for the changed blocks; unchanged blocks are shared.
        """
        new = dict(values)
        for name, free in self.free.items():
            if free.size == 0:
                continue
            step = delta[self.col_start[name][free][:, None] + np.arange(self.dims[name])]
            arr = np.array(values[name], copy=True)
            arr[free] = retract(self.manifolds[name], arr[free], step)
            arr.setflags(write=False)
            new[name] = arr
        return new

    def parameter_norm(self, values: Mapping[str, np.ndarray]) -> float:
        """Norm of the free Euclidean values, counting every free rotation as 1."""
        total = 0.0
        for name, free in self.free.items():
            if self.manifolds[name] == "so3":
                total += float(free.size)
            else:
                total += float(np.sum(values[name][free] ** 2))
        return float(np.sqrt(total))
