"""Parameter blocks, observation groups and the sparse least-squares problem (docs/ARCHITECTURE.md §4.4).

A :class:`Problem` holds named *parameter blocks* -- stacks of ``n`` elements that live on a
manifold -- and *observation groups* that evaluate all their residuals and Jacobians at once.

Manifolds and retractions
    ``"euclidean"``: values ``(n, d)``, tangent dimension ``d``, ``x <- x + delta``.
    ``"so3"``: rotation matrices ``(n, 3, 3)``, tangent dimension 3, right perturbation in the
    body frame ``R <- R @ Exp(delta)`` (the project convention, docs/ARCHITECTURE.md §2).

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
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from georefine.adjustment.blocks import (
    Manifold,
    ObservationGroup,
    ParameterBlock,
    constant_mask,
)
from georefine.adjustment.linalg import (
    Factorization,
    SparseCholesky,
    available_backends,
    check_by_solve,
    marginal_covariance_blocks,
    symmetric_matvec,
)
from georefine.adjustment.selected_inverse import EXPECTED_COLUMNS, SelectedInverse, invert_factor, selected_inverse
from georefine.adjustment.solver import (
    IterationSummary,
    LMOutcome,
    SolveResult,
    SolverOptions,
    run_levenberg_marquardt,
)
from georefine.adjustment.variance_components import (
    MIN_REDUNDANCY,
    PROBES,
    VarianceComponent,
    group_traces,
    row_weights,
    traces_needed,
    variance_components,
)

__all__ = ["Problem"]

logger = logging.getLogger(__name__)


@dataclass
class _Posterior:
    """Normal matrix at the solution of the last solve, for covariance queries."""

    normal: Callable[[], sp.csr_matrix]  # its lower triangle with the diagonal (CSR)
    col_start: dict[str, np.ndarray]
    dims: dict[str, int]
    variance_factor: float
    backend: str
    factor: Factorization | None = None
    inverse: SelectedInverse | None = None
    factorizer: SparseCholesky | None = None  # the solve's, whose symbolic analysis fits the normal matrix
    outcome: LMOutcome | None = None  # for J, until the normal matrix is formed
    result: SolveResult | None = None
    components: tuple[VarianceComponent, ...] | None = None  # set: normal() is the component-weighted matrix
    columns: int = EXPECTED_COLUMNS  # unit columns the covariance queries will ask for (expect_covariance)
    formed_s: tuple[float, float] = (0.0, 0.0)  # J's assembly and N's forming for it, once the outcome is gone


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
        block.constant = constant_mask(name, mask_or_bool, block.size)

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
        if not all(hasattr(group, a) for a in ("linearize", "name", "consumed_redundancy")):
            raise TypeError(f"{type(group).__name__} is not an ObservationGroup "
                            "(needs name, consumed_redundancy and linearize)")
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

        options = SolverOptions() if options is None else options
        outcome = run_levenberg_marquardt(self._blocks, tuple(self._groups.values()), options, progress)
        for name, values in outcome.values.items():
            block = self._blocks[name]
            block.values = np.array(values, dtype=float, copy=True)
        self._posterior = _Posterior(
            normal=lambda: outcome.normal_matrix(lower=True),
            col_start=outcome.col_start,
            dims={name: block.dim for name, block in self._blocks.items()},
            variance_factor=outcome.result.variance_factor,
            backend=options.linear_solver,
            factorizer=outcome.factorizer,
            outcome=outcome,
            result=outcome.result,
        )
        return outcome.result

    def posterior_seconds(self) -> dict[str, float]:
        """Time the posterior of the last solve spent so far assembling ``J`` (``"assembly"``) and
        forming ``N`` (``"normal"``) at the solution: the solve leaves them to it when its last
        evaluated step ended it, or when its last steps ran by conjugate gradients without ``N``."""
        post = self._posterior
        if post is None:
            return {"assembly": 0.0, "normal": 0.0}
        a, n = (post.outcome.assembly_s, post.outcome.normal_s) if post.outcome is not None else post.formed_s
        return {"assembly": a, "normal": n}

    def use_variance_components(self, pools: Sequence[Sequence[str]] | None = None, *,
                                min_redundancy: float = MIN_REDUNDANCY, probes: int = PROBES,
                                seed: int = 0) -> tuple[VarianceComponent, ...]:
        """Give groups of observations their own variance factor in the posterior of the last solve.

        Estimates the components (:mod:`georefine.adjustment.variance_components`): with
        ``pools`` None one per group with at least ``min_redundancy`` and the rest pooled;
        otherwise one per pool of group names and one for the groups in none. Each factor is
        floored at 1. Makes :meth:`covariance` return ``(sum_g N_g / s_g)^-1`` from then on;
        call it with ``scale_by_variance_factor=False`` (the components are the scaling). Costs
        one factorisation of ``N`` and a solve per trace probe where a pool's trace is needed;
        the covariance queries then factorise the weighted matrix, or reuse that factor where
        every scale is 1 (not with scikit-sparse's CHOLMOD, whose selected inverse may pay).
        Called again, returns the same components.

        Raises
        ------
        RuntimeError
            Before the first solve, or after a covariance query of the same solve (``J`` is gone).
        """
        post = self._posterior
        if post is None:
            raise RuntimeError("use_variance_components(): call solve() first")
        if post.components is not None:
            return post.components
        if post.outcome is None or post.result is None or post.inverse is not None or post.factor is not None:
            raise RuntimeError("use_variance_components(): call it before the first covariance query of a solve")
        J = post.outcome.jacobian()
        N = post.outcome.normal_matrix(keep_jacobian=True, lower=True)  # the lower triangle
        names = [g.name for g in post.result.groups]
        rows = [g.n_residuals for g in post.result.groups]
        omega = [g.variance_factor * g.n_residuals if g.n_residuals else 0.0 for g in post.result.groups]
        which = traces_needed(names, rows, pools)
        traces, sds = np.full(len(names), np.nan), np.full(len(names), np.nan)
        factor = None
        if any(which):
            solver = post.factorizer if post.factorizer is not None else SparseCholesky(post.backend)
            # The singularity test by a solve, as the posterior's factorisation does it (with
            # scikit-sparse the pivot test copies the whole factor out).
            factor = solver.factorize(N, lower=True, check_pivots=False)
            check_by_solve(factor, lambda v: symmetric_matvec(N, v))
            traces, sds = group_traces(J, rows, factor, probes=probes, seed=seed, which=which)
        spent = {g.name: float(g.consumed_redundancy) for g in self.groups}
        comps = variance_components(names, rows, omega, traces, sds, post.result.redundancy, pools=pools,
                                    min_redundancy=min_redundancy, consumed=[spent.get(n, 0.0) for n in names])
        scales = {c.scale for c in comps}
        if len(scales) == 1:
            s = scales.pop()
            weighted = N if s == 1.0 else N / s
            if s == 1.0 and factor is not None:
                # The posterior's matrix is N: its factor serves the covariance queries, by the
                # selected inverse or by unit-column solves as selected_inverse chooses. Handed to
                # the solves unasked, a 30-minute G/I/L's 3,534 columns of IMU errors, GNSS error
                # and knots took 127 s, where the recursion on this factor takes 4.7 s.
                post.inverse, post.factor = invert_factor(N, factor, solver, columns=post.columns, lower=True)
                post.factorizer = None
        else:
            # In the solve's pattern: its symbolic analysis serves the weighted matrix too (on the
            # corridor's G/I/L a second CVXOPT analysis and SciPy's product took 2.7 s).
            weighted = post.outcome.weighted_normal_lower(row_weights(comps, names, rows))
        del J, factor
        post.outcome.normal_matrix(lower=True)  # frees J
        post.formed_s = (post.outcome.assembly_s, post.outcome.normal_s)
        post.outcome = None
        post.normal = lambda: weighted
        post.components = comps
        logger.debug("variance components: %s", ", ".join(
            f"{'+'.join(c.groups)} {c.factor:.3g} (r {c.redundancy:.0f})" for c in comps))
        return comps

    def expect_covariance(self, columns: int) -> None:
        """Say how many unit columns of ``N^-1`` the coming :meth:`covariance` queries of the last
        solve will ask for (about: elements times their dimension): it weighs the selected
        inversion against solving for them."""
        if self._posterior is None:
            raise RuntimeError("expect_covariance(): call solve() first")
        self._posterior.columns = max(1, int(columns))

    def covariance(
        self,
        block: str,
        elements: np.ndarray | None = None,
        scale_by_variance_factor: bool = True,
        diagonal: bool = False,
    ) -> np.ndarray:
        """Marginal posterior covariances of chosen elements (tangent space), from the last solve.

        The blocks are the diagonal blocks of ``N^-1`` (``N = J^T W J`` at the solution, with
        the final robust weights), multiplied by the a-posteriori variance factor ``sigma0^2``
        when ``scale_by_variance_factor``; after :meth:`use_variance_components`, of
        ``(sum_g N_g / s_g)^-1`` (``scale_by_variance_factor`` must then be False). For so3
        blocks the covariance is that of the right perturbation ``delta`` in
        ``R_true = R_est Exp(delta)`` (body frame). Constant elements get zero covariance.

        Cost: the first call factorises ``N`` (and assembles it if the solve ended on an
        accepted step) and, with scikit-sparse where it pays, inverts it on the factor's pattern
        (:mod:`georefine.adjustment.selected_inverse`, about the cost of the factorisation);
        every block is then a look-up. Otherwise each requested column is one
        forward/backward substitution, ``K d`` in total -- about 10 ms each for 300k unknowns:
        subsample long trajectories there rather than asking for every element.

        Parameters
        ----------
        block
            Parameter block name.
        elements
            ``(K,)`` element indices; all elements when ``None``.
        scale_by_variance_factor
            Multiply by ``sigma0^2`` (needs redundancy > 0).
        diagonal
            Only the variances are wanted: the off-diagonal entries may be left zero (they are
            where the selected inverse holds the factor, which skips solving for entries off
            its pattern).

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
        if scale_by_variance_factor and post.components is not None:
            raise ValueError("covariance(): the variance components scale it already "
                             "(use_variance_components); use scale_by_variance_factor=False")
        starts = post.col_start[block]
        idx = np.arange(starts.size) if elements is None else np.asarray(elements, dtype=np.int64).reshape(-1)
        if idx.size and (idx.min() < -starts.size or idx.max() >= starts.size):
            raise IndexError(f"covariance(): element index out of range for block {block!r} ({starts.size} elements)")
        dim = post.dims[block]
        if np.all(starts[idx] < 0):
            return np.zeros((idx.size, dim, dim))
        if post.inverse is None and post.factor is None:
            # Selected inversion where the backend shows its factor and the recursion pays;
            # unit-column solves otherwise. A backend without access to its factor (cholespy,
            # SciPy) hands the posterior to QDLDL, which is installed with Georefine: its
            # recursion beats cholespy's unit-column solves by far (corridor G/I: 0.2 s against
            # 1.2 s; G/I/L: about 35 s against 140 s).
            backend, solver = post.backend, post.factorizer
            if _resolved(backend) in ("cholespy", "scipy") and "qdldl" in available_backends():
                backend, solver = "qdldl", None
            post.inverse, post.factor = selected_inverse(post.normal(), backend=backend, solver=solver,
                                                         columns=post.columns, lower=True)
            post.factorizer = None
        if post.inverse is not None:
            cov = post.inverse.blocks(starts[idx], dim, diagonal=diagonal)
        else:
            cov = marginal_covariance_blocks(post.factor, starts[idx], dim)
        if scale_by_variance_factor:
            if not np.isfinite(post.variance_factor):
                raise ValueError(
                    "covariance(): no redundancy, the variance factor is undefined; "
                    "use scale_by_variance_factor=False"
                )
            cov *= post.variance_factor
        return cov


def _resolved(backend: str) -> str:
    """``backend``, with ``"auto"`` resolved to the first installed one."""
    return available_backends()[0] if backend == "auto" else backend
