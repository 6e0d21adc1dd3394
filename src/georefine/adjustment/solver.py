"""Levenberg-Marquardt for sparse non-linear least squares on manifolds (docs/ARCHITECTURE.md §4.4).

Minimises ``F(x) = 1/2 sum_groups sum_i rho_g(||r_i(x)||^2)`` over all non-constant elements
of the parameter blocks, ``r_i`` the whitened residual rows of observation ``i`` and
``rho_g`` the group's robust loss (``rho(s) = s`` without one).

Each iteration
    1. Every group linearises at the current values (vectorised, COO triplets).
    2. IRLS: the rows of observation ``i`` are scaled by ``sqrt(rho'(s_i))`` (see
       :mod:`georefine.adjustment.robust`), giving ``J`` and ``r`` with the exact gradient
       ``g = J^T r`` of ``F``.
    3. ``J`` is assembled as one scipy CSR matrix from the triplets of all groups (columns only
       for non-constant elements; duplicates summed), ``N = J^T J``.
    4. ``(N + lambda D) delta = -g`` with ``D = clip(diag(N), 1e-6, 1e32)`` (Marquardt's
       scaling with a floor, as in Ceres) is solved by sparse Cholesky
       (:mod:`georefine.adjustment.linalg`; the symbolic analysis of the first iteration is
       reused while the pattern of ``N`` stays the same), and the step applied through the
       retraction. From ``SolverOptions.reuse_factor_from`` unknowns on, the steps after the
       first are first tried by conjugate gradients preconditioned with the last factor
       (:func:`~georefine.adjustment.pcg.pcg_step`, ``N`` not formed); a new factorisation when they do not
       converge, or right away after a step that needed many of them (the factor has aged).
    5. Gain ratio ``rho = (F(x) - F(x')) / (L(0) - L(delta))`` with the model decrease
       ``L(0) - L(delta) = 1/2 delta^T (lambda D delta - g)`` (for an inexact step from
       conjugate gradients ``-g^T delta - |J delta|^2 / 2``). Accepted if
       ``rho > 1e-3``; then ``lambda *= max(1/3, 1 - (2 rho - 1)^3)`` and ``nu = 2``, else
       ``lambda *= nu``, ``nu *= 2`` (Nielsen 1999; Madsen, Nielsen & Tingleff 2004, §3.2).

Termination (Ceres Solver's criteria)
    ``function_tolerance``: an accepted step with ``(F - F') / F <= function_tolerance``
    (with ``relative_to_fit`` the left side times ``max(1, sigma0^2)``, ``sigma0^2`` the
    a-posteriori variance factor below at the step's estimate);
    ``parameter_tolerance``: ``||delta|| <= parameter_tolerance (||x|| + parameter_tolerance)``,
    ``||x||`` over the free Euclidean values plus one per free rotation;
    ``gradient_tolerance``: ``max |g| <= gradient_tolerance``;
    ``max_iterations`` (every trial step counts, accepted or not); ``no_progress`` when
    ``lambda`` exceeds 1e16 without an acceptable step.

Statistics (:class:`SolveResult`) refer to the final estimate and its robust weights ``w``:
redundancy ``r = rows - unknowns`` (less what the groups spent before the adjustment,
``consumed_redundancy``: readings cleaned of a signal fitted to themselves); a-posteriori variance factor
``sigma0^2 = sum w r^2 / redundancy``; per group the RMS of the (unweighted) whitened
residuals, the share of the cost, and ``sum w r^2 / rows`` as an *approximate* variance factor
of the group (the exact one divides by the group's share of the redundancy,
``rows - trace(J_g N^-1 J_g^T)``, which is not computed).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse as sp

from georefine.adjustment.blocks import (
    ColumnLayout,
    Linearization,
    ObservationGroup,
    ParameterBlock,
)
from georefine.adjustment.assembly import BlockTriplets, JacobianAssembler, column_squares, lower_triangle, normal_equations
from georefine.adjustment.linalg import NotPositiveDefiniteError, SparseCholesky, available_backends
from georefine.adjustment.pcg import PCG_STALE_ITERATIONS, NormalSystem, pcg_step
from georefine.adjustment.robust import irls_weights
from georefine.adjustment.statistics import (
    GroupStatistics,
    IterationSummary,
    SolveResult,
    Timings,
    expected_downweighted,
    residual_histogram,
    robust_sigma0,
)

__all__ = [
    "SolverOptions",
    "IterationSummary",
    "GroupStatistics",
    "Timings",
    "SolveResult",
    "run_levenberg_marquardt",
]

logger = logging.getLogger(__name__)

_MIN_DIAGONAL = 1e-6
_MAX_DIAGONAL = 1e32
_MIN_LAMBDA = 1e-15
_MAX_LAMBDA = 1e16
_MIN_GAIN_RATIO = 1e-3
_PIVOT_SAFE_LAMBDA = 1e-10  # damping above which a factorisation needs no singularity test
_POLISH_LAMBDA = 1e-13  # a solve that meets the cost-change test at a larger damping goes on (SolverOptions.polish)


@dataclass(frozen=True)
class SolverOptions:
    """Levenberg-Marquardt settings.

    Attributes
    ----------
    max_iterations
        Maximum number of trial steps (accepted or rejected).
    function_tolerance
        Stop when an accepted step decreases the cost by less than this fraction (and, with
        ``predicted_stop``, when the next step is predicted to).
    relative_to_fit
        Take that fraction of ``F / max(1, sigma0^2)`` rather than of the cost ``F``: of the cost
        the model would have if it fitted its weights, so that misfit it cannot remove (a variance
        factor of 100 from vibration left in IMU windows) does not loosen the test a hundredfold
        and stop the adjustment while a weak direction is still moving (BENCHMARKS.md, Operating
        conditions). Where the variance factor is at most 1 the test is the plain one.
    parameter_tolerance
        Stop when ``||delta|| <= parameter_tolerance * (||x|| + parameter_tolerance)``.
    gradient_tolerance
        Stop when the largest gradient component ``|J^T r|`` is below this.
    initial_lambda
        Initial damping (relative to ``diag(J^T J)``).
    robust
        Apply the groups' robust losses (``False``: plain least squares everywhere).
    verbose
        Log every iteration at INFO instead of DEBUG.
    linear_solver
        Sparse Cholesky backend: ``"auto"``, ``"cholmod"``, ``"cvxopt"``, ``"qdldl"``, ``"cholespy"`` or
        ``"scipy"`` (:func:`~georefine.adjustment.linalg.available_backends`).
    reuse_factor_from
        Problems with at least this many unknowns solve the steps after the first by conjugate
        gradients preconditioned with the last Cholesky factor (see :func:`~georefine.adjustment.pcg.pcg_step`), and
        factorise again only when those do not converge; 0: always, a huge number: never.
    predicted_stop
        Also stop, once the Gauss-Newton model has been borne out (the last accepted step's gain
        ratio within ``[0.5, 2]``) and the robust weights have settled (none below 1, or their
        change over that step moves the cost by less than the test: reweighting lowers the cost
        beyond what the model predicts), when the next step's *predicted* decrease (of the damped
        model for a factorised step, of the Gauss-Newton model for one by conjugate gradients) is
        below the cost-change test: the step is then neither evaluated nor taken. The predicted
        decrease is the distance to the model's minimum (half its square in sigma units), which
        the actual change would measure one evaluation later; stopping there saves that
        evaluation, its Jacobian and the normal matrix the posterior would otherwise rebuild (a
        G/I with no observation weighted down: 2 evaluations with Jacobians instead of 4,
        roll/pitch/yaw within 0.1 %). In the polish (below) the weights need not have settled:
        the cost-change test, reweighting included, was met by an evaluated step, and the polish
        looks for what the undamped model predicts (the corridor's G/I, whose Huber loss weights
        a few GNSS epochs down: 3 evaluations instead of 4, predicted 1.6e-5 where the step
        evaluated gave 1.69e-5; roll/pitch/yaw unchanged to 0.01 %). The estimate is then one
        step short of what the plain test returns (by less than the tolerance allows), so exact
        comparisons leave it off.
    polish
        When the cost-change test is first met by a step whose damping exceeded ``_POLISH_LAMBDA``,
        do not stop: go on with the least damping until the test is met again. A damping
        ``lambda diag(J^T J)`` shortens the step along a direction of curvature ``mu`` (relative
        to the diagonal) by ``mu / (mu + lambda)``, and a weak direction can be left short by a
        sigma while each step lowers the cost by less than the test sees (a whole sigma is worth
        1/2). A single pass's heading with a navigation IMU is such a direction: the G/I/L
        stopped with 0.14 mdeg of it still to go, 0.4 of its sigma (docs/ARCHITECTURE.md §4.4).
    """

    max_iterations: int = 50
    function_tolerance: float = 1e-8
    relative_to_fit: bool = False
    parameter_tolerance: float = 1e-10
    gradient_tolerance: float = 1e-10
    initial_lambda: float = 1e-4
    robust: bool = True
    verbose: bool = False
    linear_solver: Literal["auto", "cholmod", "cvxopt", "qdldl", "cholespy", "scipy"] = "auto"
    reuse_factor_from: int = 100_000
    polish: bool = True
    predicted_stop: bool = False

    def __post_init__(self) -> None:
        if self.max_iterations < 0:
            raise ValueError(f"max_iterations must be >= 0, found {self.max_iterations}")
        for name in ("function_tolerance", "parameter_tolerance", "gradient_tolerance"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, found {getattr(self, name)}")
        if not self.initial_lambda > 0:
            raise ValueError(f"initial_lambda must be > 0, found {self.initial_lambda}")


@dataclass
class _GroupEvaluation:
    linearization: Linearization
    row_sqrt_weight: np.ndarray | None  # (M,) sqrt(rho'), None for plain LS
    loss_name: str | None
    n_observations: int
    cost: float
    sum_r2: float
    sum_wr2: float
    n_downweighted: int
    median_s: float = math.nan  # median squared norm of the observations' whitened residuals


@dataclass
class _Evaluation:
    groups: list[_GroupEvaluation]
    cost: float
    finite: bool
    has_jacobians: bool
    seconds: float

    @property
    def n_rows(self) -> int:
        return sum(g.linearization.residuals.size for g in self.groups)

    def variance_factor(self, n_unknowns: float) -> float:
        """A-posteriori ``sigma0^2 = sum w r^2 / redundancy`` (NaN without redundancy);
        ``n_unknowns`` includes the degrees of freedom spent before (``consumed_redundancy``)."""
        redundancy = self.n_rows - n_unknowns
        return sum(g.sum_wr2 for g in self.groups) / redundancy if redundancy > 0 else math.nan


def _evaluate(
    groups: Sequence[ObservationGroup], values: Mapping[str, np.ndarray], jacobians: bool, robust: bool
) -> _Evaluation:
    t0 = time.perf_counter()
    out, total, finite = [], 0.0, True
    for group in groups:
        lin = group.linearize(values, jacobians)
        if not isinstance(lin, Linearization):
            raise TypeError(f"group {group.name!r}: linearize() returned {type(lin).__name__}, not a Linearization")
        r = lin.residuals
        if not np.all(np.isfinite(r)):
            finite = False
            out.append(_GroupEvaluation(lin, None, None, 0, math.inf, math.inf, math.inf, 0))
            total = math.inf
            continue
        loss = getattr(group, "loss", None) if robust else None
        w = irls_weights(loss, lin.observation, r)
        name = None if loss is None else getattr(loss, "name", type(loss).__name__)
        n_down = int(np.count_nonzero(w.weight < 0.5))
        median_s = float(np.median(w.s)) if w.s.size else math.nan
        out.append(_GroupEvaluation(lin, w.row_sqrt_weight, name, w.s.size, w.cost, w.sum_s, w.sum_ws, n_down, median_s))
        total += w.cost
    return _Evaluation(out, total, finite and math.isfinite(total), jacobians, time.perf_counter() - t0)


def _assemble_jacobian(
    evaluation: _Evaluation, layout: ColumnLayout, assembler: JacobianAssembler
) -> tuple[sp.csr_matrix, np.ndarray]:
    """Global whitened, robustly weighted ``J`` (CSR, rows x free columns) and ``r``.

    Validates every JacobianBlock, drops the entries of constant elements and writes all
    sub-blocks at once (:class:`~georefine.adjustment.assembly.JacobianAssembler`, which keeps
    the structure from one iteration to the next).
    """
    pieces, residuals = [], []
    offset = 0
    for ge in evaluation.groups:
        lin = ge.linearization
        m_group = lin.residuals.size
        sqrt_w = ge.row_sqrt_weight
        residuals.append(lin.residuals if sqrt_w is None else lin.residuals * sqrt_w)
        for jb in lin.jacobians:
            starts_block = layout.col_start.get(jb.block)
            if starts_block is None:
                raise KeyError(f"group Jacobian refers to unknown parameter block {jb.block!r}")
            d = layout.dims[jb.block]
            if jb.values.shape[2] != d:
                raise ValueError(
                    f"JacobianBlock for {jb.block!r}: last axis must be the tangent dimension {d}, "
                    f"found {jb.values.shape[2]}"
                )
            if jb.elements.size == 0:
                continue
            if jb.elements.min() < 0 or jb.elements.max() >= starts_block.size:
                raise IndexError(f"JacobianBlock for {jb.block!r}: element index out of range [0, {starts_block.size})")
            if jb.rows.min() < 0 or jb.rows.max() >= m_group:
                raise IndexError(f"JacobianBlock for {jb.block!r}: row index out of range [0, {m_group})")
            starts = starts_block[jb.elements]
            keep = starts >= 0
            if not keep.any():
                continue
            rows, vals = jb.rows, jb.values
            if not keep.all():
                rows, vals, starts = rows[keep], vals[keep], starts[keep]
            pieces.append(BlockTriplets(rows, starts, vals, offset, sqrt_w))
        offset += m_group
    r = np.concatenate(residuals) if residuals else np.zeros(0)
    return assembler.assemble(pieces, (evaluation.n_rows, layout.n_cols)), r


def _normal_equations(evaluation: _Evaluation, layout: ColumnLayout, assembler: JacobianAssembler) -> NormalSystem:
    t0 = time.perf_counter()
    J, r = _assemble_jacobian(evaluation, layout, assembler)
    g = np.asarray(J.T @ r)
    diag = column_squares(J)
    D = np.clip(diag, _MIN_DIAGONAL, _MAX_DIAGONAL)
    pattern = assembler.normal_pattern(J) if J.nnz else None
    return NormalSystem(J, g, diag, D, time.perf_counter() - t0, pattern=pattern)


# ---------------------------------------------------------------------------------------------
# Levenberg-Marquardt
# ---------------------------------------------------------------------------------------------


@dataclass
class LMOutcome:
    """What :meth:`Problem.solve` needs back: result, final values and the normal matrix.

    The normal matrix at the solution is assembled lazily (:meth:`normal_matrix`) when the
    last accepted step ended the iteration, so a solve without covariance queries saves one
    assembly.
    """

    result: SolveResult
    values: dict[str, np.ndarray]
    col_start: dict[str, np.ndarray]
    _normal: NormalSystem | None
    _evaluation: _Evaluation | None
    _layout: ColumnLayout
    factorizer: SparseCholesky | None = None  # its symbolic analysis fits the normal matrix too
    _assembler: JacobianAssembler | None = None  # the solve's, whose structure fits J at the solution

    _jacobian_freed: bool = False
    assembly_s: float = 0.0  # spent after the solve assembling J at the solution (for the posterior)
    normal_s: float = 0.0  # spent after the solve forming N there

    def jacobian(self) -> sp.csr_matrix:
        """The whitened, robustly weighted ``J`` at the solution (rows in group order).

        Available until :meth:`normal_matrix` is called without ``keep_jacobian``.
        """
        if self._normal is None:
            t = time.perf_counter()
            self._normal = _normal_equations(self._evaluation, self._layout, self._assembler or JacobianAssembler())
            self.assembly_s += time.perf_counter() - t
            self._evaluation = None
            self._assembler = None
        if self._jacobian_freed:
            raise RuntimeError("jacobian(): J was freed when the normal matrix was formed")
        return self._normal.J

    def weighted_normal_lower(self, row_weights: np.ndarray) -> sp.csr_matrix:
        """The lower triangle of ``J^T diag(row_weights) J`` at the solution (``J`` must still be
        kept): in the pattern of the solve's damped matrices where the solve kept one (the rows
        scaled in place of a copy of ``J``, same structure), so the factorizer's symbolic
        analysis fits it too; else SciPy's product."""
        J = self.jacobian()
        w = np.sqrt(np.asarray(row_weights, dtype=np.float64))
        t = time.perf_counter()
        pattern = self._normal.pattern
        if pattern is not None and pattern.fits(J):
            Jw = sp.csr_matrix((J.data * np.repeat(w, np.diff(J.indptr)), J.indices, J.indptr), shape=J.shape)
            Jw.has_sorted_indices = True
            N = pattern.lower(Jw)
        else:
            N = lower_triangle(normal_equations(sp.csr_matrix(sp.diags(w) @ J), np.zeros(J.shape[0]))[0])
        self.normal_s += time.perf_counter() - t
        return N

    def normal_matrix(self, keep_jacobian: bool = False, lower: bool = False) -> sp.csr_matrix:
        """``N = J^T W J`` at the solution (CSR; full symmetric, or with ``lower`` its lower
        triangle with the diagonal, in the pattern of the solve's damped matrices, which the
        factorizer's symbolic analysis fits); ``J`` is freed unless ``keep_jacobian``."""
        if self._normal is None:
            self.jacobian()
        t = time.perf_counter()
        N = self._normal.N_lower() if lower else self._normal.N()
        self.normal_s += time.perf_counter() - t
        if not keep_jacobian and not self._jacobian_freed:
            kept = self._normal
            self._normal = NormalSystem(sp.csr_matrix((0, 0)), np.zeros(0), np.zeros(0), np.zeros(0), 0.0,
                                        kept._N, kept._N_lower)  # J freed
            self._jacobian_freed = True
        return N


def _strip_jacobians(evaluation: _Evaluation) -> _Evaluation:
    """Drop the Jacobian arrays (kept: residuals and weights for the statistics) to free memory."""
    groups = []
    for ge in evaluation.groups:
        lin = ge.linearization
        stripped = Linearization(lin.residuals, [], lin.observation)
        groups.append(_GroupEvaluation(stripped, *(getattr(ge, f) for f in _GROUP_FIELDS)))
    return _Evaluation(groups, evaluation.cost, evaluation.finite, False, evaluation.seconds)


def _same_weights(before: _Evaluation, after: _Evaluation, budget: float) -> bool:
    """Whether the robust weights settled over a step: their change, weighted by the squared
    residuals, ``1/2 sum |w_after - w_before| r^2``, is within ``budget`` (the cost-change test's).
    The fixed-weight model then predicts the next step again. Conservative: on the corridor's G/I
    the Huber weights of a few GNSS epochs move the cost by 59 budgets over the first step, 2 over
    the second and 0.1 over the third, while the second step's prediction was already right."""
    moved = 0.0
    for a, b in zip(before.groups, after.groups):
        wa, wb = a.row_sqrt_weight, b.row_sqrt_weight
        if wa is None and wb is None:
            continue
        if wa is None or wb is None or wa.shape != wb.shape:
            return False
        r = b.linearization.residuals
        moved += 0.5 * float(np.abs(wa * wa - wb * wb) @ (r * r))
    return moved <= budget


def _reweighting(evaluation: _Evaluation) -> bool:
    """Whether a robust loss weights some observation down: while the weights still move, the
    iterations lower the cost by reweighting too, which the fixed-weight model of the next step
    does not predict (the hybrid adjustment's Huber loss on 375 returns stopped on a predicted 15
    after actual changes of 257 and 58, short of its solution)."""
    for ge in evaluation.groups:
        w = ge.row_sqrt_weight
        if w is not None and w.size and float(np.min(w)) < 1.0 - 1e-12:
            return True
    return False


_GROUP_FIELDS = ("row_sqrt_weight", "loss_name", "n_observations", "cost", "sum_r2", "sum_wr2", "n_downweighted",
                 "median_s")  # every field of _GroupEvaluation after the linearisation, in order


def run_levenberg_marquardt(
    blocks: Mapping[str, ParameterBlock],
    groups: Sequence[ObservationGroup],
    options: SolverOptions,
    progress: Callable[[IterationSummary], None] | None = None,
) -> LMOutcome:
    """Run Levenberg-Marquardt from the blocks' current values (the blocks are not modified).

    Use :meth:`georefine.adjustment.problem.Problem.solve`; this is its engine.
    """
    t_start = time.perf_counter()
    log = logger.info if options.verbose else logger.debug
    layout = ColumnLayout.build(blocks)
    spent = _spent(layout, groups)
    values: dict[str, np.ndarray] = {}
    for name, block in blocks.items():
        arr = block.values.copy()
        arr.setflags(write=False)
        values[name] = arr
    t_eval = t_asm = t_fac = t_norm = 0.0

    current = _evaluate(groups, values, True, options.robust)
    t_eval += current.seconds
    if not current.finite:
        bad = [g.name for g, ge in zip(groups, current.groups) if not math.isfinite(ge.cost)]
        raise ValueError(f"non-finite residuals at the initial values in group(s): {', '.join(bad)}")
    assembler = JacobianAssembler()  # one structure of J for all iterations
    normal = _normal_equations(current, layout, assembler)
    t_asm += normal.seconds
    normal_is_current = True
    current = _strip_jacobians(current)
    unobserved = int(np.count_nonzero(normal.diag == 0))
    if unobserved:
        logger.warning("%d unknown(s) have no observations; the normal matrix is singular", unobserved)

    initial_cost = cost = current.cost
    history = [cost]
    lam, nu = options.initial_lambda, 2.0
    iterations = accepted_steps = 0
    polishing = False  # the cost-change test was met once at a larger damping (SolverOptions.polish)
    model_trusted = False  # the last accepted step's gain ratio bore the Gauss-Newton model out
    redamped = False  # the last trial step was only re-damped: the factor is of the same N
    settled = False  # the robust weights did not change over the last accepted step
    factorizer = SparseCholesky(options.linear_solver)  # one symbolic analysis for all iterations
    backend_used = options.linear_solver
    reuse = layout.n_cols >= options.reuse_factor_from
    factor = None  # the last factorisation: the preconditioner of the next steps (reuse)
    pcg_iterations = 0  # of the last step by conjugate gradients since that factorisation
    n_factorisations = n_pcg_steps = 0
    termination = "max_iterations"
    log("LM start: cost %.6g, %d unknowns, %d residuals", cost, layout.n_cols, current.n_rows)
    if layout.n_cols == 0:
        termination = "no_unknowns"

    while termination != "no_unknowns":
        g_max = float(np.max(np.abs(normal.g), initial=0.0))
        if g_max <= options.gradient_tolerance:
            termination = "gradient_tolerance"
            break
        if iterations >= options.max_iterations:
            termination = "max_iterations"
            break
        iterations += 1
        t0 = time.perf_counter()
        delta, exact = None, True
        redamped, was_redamped = False, redamped
        if factor is not None and (was_redamped or (reuse and pcg_iterations <= PCG_STALE_ITERATIONS)):
            # Also where only the damping changed since the factorisation (the polish on the
            # predicted change): its factor of N + lambda' D preconditions N + lambda D in a step or two.
            delta, pcg_iterations = pcg_step(normal, lam, factor)
            exact = delta is None
            log("iter %3d: conjugate gradients %s after %d iterations", iterations,
                "converged" if delta is not None else "did not converge", pcg_iterations)
        if delta is not None:
            n_pcg_steps += 1
            solved = bool(np.all(np.isfinite(delta)))
        else:
            try:
                factor = None  # free the old factor first (a G/I/L factor of an hour's flight is GBs)
                t_n = time.perf_counter()
                A = normal.damped_lower(lam)
                t_norm += time.perf_counter() - t_n
                # The damping keeps every pivot above lam * D (SparseCholesky.factorize): no singularity test.
                factor = factorizer.factorize(A, lower=True, check_pivots=lam < _PIVOT_SAFE_LAMBDA)
                del A
                n_factorisations += 1
                pcg_iterations = 0
                backend_used = factor.backend
                delta = factor.solve(-normal.g)
                solved = bool(np.all(np.isfinite(delta)))
            except NotPositiveDefiniteError:
                factor, solved = None, False
        t_fac += time.perf_counter() - t0
        if not solved:
            lam, nu = lam * nu, nu * 2.0
            log("iter %3d: factorisation failed, lambda -> %.3g", iterations, lam)
            _report(progress, iterations, cost, 0.0, -math.inf, math.nan, g_max, lam, False, t_start)
            if lam > _MAX_LAMBDA:
                termination = "no_progress"
                break
            continue

        step_norm = float(np.linalg.norm(delta))
        x_norm = layout.parameter_norm(values)
        if step_norm <= options.parameter_tolerance * (x_norm + options.parameter_tolerance):
            termination = "parameter_tolerance"
            _report(progress, iterations, cost, 0.0, math.nan, step_norm, g_max, lam, False, t_start)
            break
        # The weights need not have settled in the polish: the cost-change test, reweighting
        # included, was met by an evaluated step, and what the polish looks for (a direction the
        # damping left short) is what the undamped model predicts.
        if (options.predicted_stop and model_trusted and normal_is_current
                and (settled or polishing or not _reweighting(current))):
            if exact:
                predicted = 0.5 * float(delta @ (lam * normal.D * delta - normal.g))
            else:  # conjugate gradients: the Gauss-Newton model's decrease
                Jd = normal.J @ delta
                predicted = -float(normal.g @ delta) - 0.5 * float(Jd @ Jd)
            reference = cost
            if options.relative_to_fit and current.n_rows > layout.n_cols:
                reference /= max(1.0, current.variance_factor(spent))
            if predicted <= options.function_tolerance * reference:
                if options.polish and not polishing and lam > _POLISH_LAMBDA:
                    polishing = True
                    log("iter %3d: predicted change %.3g within the tolerance at lambda %.3g: on with lambda %.3g",
                        iterations, predicted, lam, _MIN_LAMBDA)
                    lam = _MIN_LAMBDA
                    redamped = True
                    continue
                termination = "function_tolerance"
                log("iter %3d: predicted change %.3g within the tolerance: stop before the trial", iterations, predicted)
                _report(progress, iterations, cost, 0.0, math.nan, step_norm, g_max, lam, False, t_start)
                break

        trial_values = layout.apply_step(values, delta)
        # Jacobians of the trial are computed right away unless the last step was rejected.
        want_jac = nu <= 2.0
        trial = _evaluate(groups, trial_values, want_jac, options.robust)
        t_eval += trial.seconds
        if exact:
            predicted = 0.5 * float(delta @ (lam * normal.D * delta - normal.g))
        else:  # the Gauss-Newton model's decrease, L(0) - L(delta) = -g.delta - |J delta|^2 / 2
            Jd = normal.J @ delta
            predicted = -float(normal.g @ delta) - 0.5 * float(Jd @ Jd)
        actual = cost - trial.cost if trial.finite else -math.inf
        gain = actual / predicted if predicted > 0 else -math.inf

        if trial.finite and gain > _MIN_GAIN_RATIO:
            accepted_steps += 1
            model_trusted = 0.5 <= gain <= 2.0
            settled = _same_weights(current, trial, options.function_tolerance * trial.cost
                                    / max(1.0, trial.variance_factor(spent) if options.relative_to_fit else 1.0))
            values = trial_values
            if not trial.has_jacobians:
                trial = _evaluate(groups, values, True, options.robust)
                t_eval += trial.seconds
            current, cost = trial, trial.cost
            history.append(cost)
            lam = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3), _MIN_LAMBDA)
            nu = 2.0
            reference = cost + actual
            if options.relative_to_fit and current.n_rows > layout.n_cols:  # the step's sigma0^2, if > 1
                reference /= max(1.0, current.variance_factor(spent))
            converged = actual <= options.function_tolerance * reference
            if converged and options.polish and not polishing and lam > _POLISH_LAMBDA:
                polishing, converged = True, False
                log("iter %3d: cost change within the tolerance at lambda %.3g: on with lambda %.3g",
                    iterations, lam, _MIN_LAMBDA)
                lam = _MIN_LAMBDA
            normal_is_current = False
            if not converged:  # else N at the solution is assembled only if covariances are asked for
                normal = _normal_equations(current, layout, assembler)
                t_asm += normal.seconds
                normal_is_current = True
                current = _strip_jacobians(current)
            trial = None  # free the Jacobians before the next trial evaluation
            log(
                "iter %3d: cost %.9g  change %.3g  gain %.3f  |step| %.3g  max|g| %.3g  lambda %.3g",
                iterations, cost, actual, gain, step_norm, g_max, lam,
            )
            _report(progress, iterations, cost, actual, gain, step_norm, g_max, lam, True, t_start)
            if converged:
                termination = "function_tolerance"
                break
        else:
            model_trusted = False
            lam, nu = lam * nu, nu * 2.0
            log("iter %3d: rejected (gain %.3g), lambda -> %.3g", iterations, gain, lam)
            _report(progress, iterations, cost, actual, gain, step_norm, g_max, lam, False, t_start)
            if lam > _MAX_LAMBDA:
                termination = "no_progress"
                break

    if backend_used == "auto":
        backend_used = available_backends()[0]
    result = _statistics(
        groups, current, layout, spent, termination, iterations, accepted_steps, initial_cost, history, lam,
        Timings(t_eval, t_asm, t_fac - t_norm, time.perf_counter() - t_start, t_norm), backend_used, n_factorisations,
        n_pcg_steps,
    )
    log("LM end: %s", result.summary())
    factor = None
    return LMOutcome(
        result,
        {k: np.array(v) for k, v in values.items()},
        layout.col_start,
        normal if normal_is_current else None,
        None if normal_is_current else current,
        layout,
        factorizer,
        None if normal_is_current else assembler,
    )


def _report(progress, iteration, cost, change, gain, step, g_max, lam, accepted, t_start) -> None:
    if progress is not None:
        progress(
            IterationSummary(
                iteration, float(cost), float(change), float(gain), float(step), float(g_max), float(lam),
                bool(accepted), time.perf_counter() - t_start,
            )
        )


def _spent(layout: ColumnLayout, groups) -> float:
    """Unknowns plus the degrees of freedom the observations spent before the adjustment
    (readings cleaned of a signal fitted to themselves, ``ImuObservation.consumed_redundancy``):
    what the redundancy and the variance factor subtract from the rows."""
    return layout.n_cols + sum(float(getattr(g, "consumed_redundancy", 0.0)) for g in groups)


def _statistics(
    groups, evaluation: _Evaluation, layout: ColumnLayout, spent: float, termination, iterations, accepted,
    initial_cost, history, lam, timings: Timings, backend: str, factorisations: int = 0, iterative_steps: int = 0,
) -> SolveResult:
    total_cost = evaluation.cost
    stats, n_obs = [], 0
    for group, ge in zip(groups, evaluation.groups):
        m = ge.linearization.residuals.size
        stats.append(
            GroupStatistics(
                name=group.name,
                robust_loss=ge.loss_name,
                n_observations=ge.n_observations,
                n_residuals=m,
                rms=math.sqrt(ge.sum_r2 / m) if m else math.nan,
                cost=ge.cost,
                cost_share=ge.cost / total_cost if total_cost > 0 else math.nan,
                variance_factor=ge.sum_wr2 / m if m else math.nan,
                n_downweighted=ge.n_downweighted,
                robust_sigma0=robust_sigma0(ge.median_s, m / ge.n_observations) if ge.n_observations else math.nan,
                expected_downweighted=(expected_downweighted(getattr(group, "loss", None) if ge.loss_name else None,
                                                             m / ge.n_observations) if ge.n_observations else math.nan),
                residual_histogram=residual_histogram(ge.linearization.residuals),
            )
        )
        n_obs += ge.n_observations
    n_rows = evaluation.n_rows
    redundancy = int(round(n_rows - spent))
    return SolveResult(
        termination=termination,
        iterations=iterations,
        successful_iterations=accepted,
        initial_cost=initial_cost,
        final_cost=total_cost,
        cost_history=tuple(float(c) for c in history),
        final_lambda=lam,
        n_unknowns=layout.n_cols,
        n_observations=n_obs,
        n_residuals=n_rows,
        redundancy=redundancy,
        variance_factor=evaluation.variance_factor(spent),
        groups=tuple(stats),
        timings=timings,
        backend=backend,
        factorisations=factorisations,
        iterative_steps=iterative_steps,
    )
