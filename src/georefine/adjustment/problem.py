"""Parameter blocks, observation groups and the sparse least-squares problem (DESIGN §4.4).

A :class:`Problem` holds named *parameter blocks* -- stacks of ``n`` elements that live on a
manifold -- and *observation groups* that evaluate all their residuals and Jacobians at once.

Manifolds and retractions
    ``"euclidean"``: values ``(n, d)``, tangent dimension ``d``, ``x <- x + delta``.
    ``"so3"``: rotation matrices ``(n, 3, 3)``, tangent dimension 3, right perturbation in the
    body frame ``R <- R @ Exp(delta)`` (the project convention, DESIGN §2).

Observation groups (the contract every observation model implements)
    ``group.linearize(values, jacobians)`` receives a read-only mapping ``block name ->
    current values`` (all blocks, constant ones included) and returns a
    :class:`Linearization`: whitened residuals ``r = Sigma^{-1/2} (model - measurement)``,
    one :class:`JacobianBlock` per (block, residual-row pattern) with
    ``d r / d delta`` for the tangent ``delta`` of the retraction above, and the observation
    index of every row (the robust loss acts on an observation's squared norm). Jacobian
    entries for constant elements are allowed and dropped by the solver; several
    JacobianBlocks may hit the same element and are summed.

Hold constant
    Per element (``constant`` mask) or per block (:meth:`Problem.set_constant`). Constant
    elements have no columns in the normal equations and zero posterior covariance; a block
    whose elements are all constant adds no columns at all. Use it to fix the datum (gauge).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal, Protocol, runtime_checkable

import numpy as np
import scipy.sparse as sp

from georefine.adjustment.linalg import Factorization, cholesky, marginal_covariance_blocks
from georefine.adjustment.robust import RobustLoss
from georefine.geometry.rotation import exp_so3

if TYPE_CHECKING:
    from georefine.adjustment.solver import IterationSummary, SolveResult, SolverOptions

__all__ = [
    "Manifold",
    "ParameterBlock",
    "JacobianBlock",
    "Linearization",
    "ObservationGroup",
    "Problem",
    "ColumnLayout",
    "tangent_dim",
    "retract",
]

logger = logging.getLogger(__name__)

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
        self.constant = _constant_mask(self.name, self.constant, values.shape[0])

    @property
    def size(self) -> int:
        """Number of elements ``n``."""
        return int(self.values.shape[0])

    @property
    def dim(self) -> int:
        """Tangent dimension of one element."""
        return tangent_dim(self.manifold, self.values)


def _constant_mask(name: str, mask: np.ndarray | bool | None, n: int) -> np.ndarray:
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
    """

    name: str
    loss: RobustLoss | None

    def linearize(self, values: Mapping[str, np.ndarray], jacobians: bool = True) -> Linearization:
        """Residuals and, if ``jacobians``, Jacobian blocks at ``values`` (block name -> array)."""
        ...


@dataclass
class ColumnLayout:
    """Columns of the free elements in the normal equations.

    Blocks in insertion order, elements in index order, ``d`` consecutive columns per free
    element.

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
        for name, block in blocks.items():
            d = block.dim
            idx = np.flatnonzero(~block.constant)
            starts = np.full(block.size, -1, dtype=np.int64)
            starts[idx] = offset + d * np.arange(idx.size)
            offset += d * idx.size
            col_start[name], dims[name], manifolds[name], free[name] = starts, d, block.manifold, idx
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


@dataclass
class _Posterior:
    """Normal matrix at the solution of the last solve, for covariance queries."""

    normal: Callable[[], sp.csr_matrix]
    col_start: dict[str, np.ndarray]
    dims: dict[str, int]
    variance_factor: float
    backend: str
    factor: Factorization | None = None


class Problem:
    """A sparse non-linear least-squares problem on parameter blocks.

    Examples
    --------
    >>> problem = Problem()
    >>> problem.add_block("x", np.zeros((10, 3)))
    >>> problem.add_group(my_group)          # doctest: +SKIP
    >>> result = problem.solve()              # doctest: +SKIP
    >>> sigma = problem.covariance("x")       # (10, 3, 3)  # doctest: +SKIP
    """

    def __init__(self) -> None:
        self._blocks: dict[str, ParameterBlock] = {}
        self._groups: dict[str, ObservationGroup] = {}
        self._posterior: _Posterior | None = None

    # -- blocks -----------------------------------------------------------------------------
    def add_block(
        self,
        name: str,
        values: np.ndarray,
        manifold: Manifold = "euclidean",
        constant: np.ndarray | bool | None = None,
    ) -> None:
        """Add a parameter block (values are copied). See :class:`ParameterBlock`."""
        if name in self._blocks:
            raise ValueError(f"parameter block {name!r} already exists")
        self._blocks[name] = ParameterBlock(name, values, manifold, constant)

    def set_constant(self, name: str, mask_or_bool: np.ndarray | bool) -> None:
        """Hold a whole block (``True``/``False``) or chosen elements (``(n,)`` bool) constant."""
        block = self._block(name)
        block.constant = _constant_mask(name, mask_or_bool, block.size)

    def set_values(self, name: str, values: np.ndarray) -> None:
        """Replace a block's current values (same shape), e.g. to restart from a new guess."""
        block = self._block(name)
        values = np.asarray(values, dtype=float)
        if values.shape != block.values.shape:
            raise ValueError(f"block {name!r}: values must have shape {block.values.shape}, found {values.shape}")
        self._blocks[name] = ParameterBlock(name, values, block.manifold, block.constant)

    def values(self, name: str) -> np.ndarray:
        """Current estimate of a block (a copy)."""
        return self._block(name).values.copy()

    def constant(self, name: str) -> np.ndarray:
        """Constant mask of a block (a copy)."""
        return self._block(name).constant.copy()

    @property
    def blocks(self) -> Mapping[str, ParameterBlock]:
        """The parameter blocks by name (do not modify them in place; use the setters)."""
        return dict(self._blocks)

    def _block(self, name: str) -> ParameterBlock:
        try:
            return self._blocks[name]
        except KeyError:
            raise KeyError(f"no parameter block {name!r} (have: {', '.join(self._blocks) or 'none'})") from None

    # -- groups -----------------------------------------------------------------------------
    def add_group(self, group: ObservationGroup) -> None:
        """Add an observation group (names must be unique)."""
        if not hasattr(group, "linearize") or not hasattr(group, "name"):
            raise TypeError(f"{type(group).__name__} is not an ObservationGroup (needs name and linearize)")
        if group.name in self._groups:
            raise ValueError(f"observation group {group.name!r} already exists")
        self._groups[group.name] = group

    def remove_group(self, name: str) -> None:
        """Remove an observation group, e.g. to replace re-matched plane correspondences."""
        if name not in self._groups:
            raise KeyError(f"no observation group {name!r}")
        del self._groups[name]

    @property
    def groups(self) -> tuple[ObservationGroup, ...]:
        """The observation groups in insertion order."""
        return tuple(self._groups.values())

    # -- solving ----------------------------------------------------------------------------
    def solve(
        self,
        options: SolverOptions | None = None,
        progress: Callable[[IterationSummary], None] | None = None,
    ) -> SolveResult:
        """Estimate all non-constant parameters by Levenberg-Marquardt.

        Parameters
        ----------
        options
            :class:`~georefine.adjustment.solver.SolverOptions`; defaults when ``None``.
        progress
            Called after every iteration with an
            :class:`~georefine.adjustment.solver.IterationSummary`.

        Returns
        -------
        SolveResult
            Statistics; the block values are updated in place to the estimate.
        """
        from georefine.adjustment.solver import SolverOptions, run_levenberg_marquardt

        options = SolverOptions() if options is None else options
        outcome = run_levenberg_marquardt(self._blocks, tuple(self._groups.values()), options, progress)
        for name, values in outcome.values.items():
            block = self._blocks[name]
            block.values = np.array(values, dtype=float, copy=True)
        self._posterior = _Posterior(
            normal=outcome.normal_matrix,
            col_start=outcome.col_start,
            dims={name: block.dim for name, block in self._blocks.items()},
            variance_factor=outcome.result.variance_factor,
            backend=options.linear_solver,
        )
        return outcome.result

    def covariance(
        self,
        block: str,
        elements: np.ndarray | None = None,
        scale_by_variance_factor: bool = True,
    ) -> np.ndarray:
        """Marginal posterior covariances of chosen elements (tangent space), from the last solve.

        The blocks are the diagonal blocks of ``N^-1`` (``N = J^T W J`` at the solution, with
        the final robust weights), computed column batch by column batch with the sparse
        factor; multiplied by the a-posteriori variance factor ``sigma0^2`` when
        ``scale_by_variance_factor``. For so3 blocks the covariance is that of the right
        perturbation ``delta`` in ``R_true = R_est Exp(delta)`` (body frame). Constant elements get
        zero covariance.

        Cost: the first call factorises ``N`` (and assembles it if the solve ended on an
        accepted step); then one forward/backward substitution per requested column, ``K d``
        in total -- about 10 ms each for 300k unknowns. Subsample long trajectories (e.g. every
        10th knot) rather than asking for every element.

        Parameters
        ----------
        block
            Parameter block name.
        elements
            ``(K,)`` element indices; all elements when ``None``.
        scale_by_variance_factor
            Multiply by ``sigma0^2`` (needs redundancy > 0).

        Returns
        -------
        np.ndarray
            ``(K, d, d)``.

        Raises
        ------
        RuntimeError
            Before the first solve.
        NotPositiveDefiniteError
            When the normal matrix is singular (datum not fixed, unobserved parameters).
        """
        post = self._posterior
        if post is None:
            raise RuntimeError("covariance(): call solve() first")
        if block not in post.col_start:
            raise KeyError(f"no parameter block {block!r} in the last solve")
        starts = post.col_start[block]
        idx = np.arange(starts.size) if elements is None else np.asarray(elements, dtype=np.int64).reshape(-1)
        if idx.size and (idx.min() < -starts.size or idx.max() >= starts.size):
            raise IndexError(f"covariance(): element index out of range for block {block!r} ({starts.size} elements)")
        dim = post.dims[block]
        if np.all(starts[idx] < 0):
            return np.zeros((idx.size, dim, dim))
        if post.factor is None:
            post.factor = cholesky(post.normal(), backend=post.backend)
        cov = marginal_covariance_blocks(post.factor, starts[idx], dim)
        if scale_by_variance_factor:
            if not np.isfinite(post.variance_factor):
                raise ValueError(
                    "covariance(): no redundancy, the variance factor is undefined; "
                    "use scale_by_variance_factor=False"
                )
            cov *= post.variance_factor
        return cov
