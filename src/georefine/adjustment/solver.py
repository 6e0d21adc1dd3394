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

Each of these rules is one function of :mod:`georefine.adjustment.lm_state`, beside the state a
trial step hands to the next (:class:`~georefine.adjustment.lm_state.LMState`) and
:class:`SolverOptions`; this module evaluates, assembles and solves.

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

import numpy as np
import scipy.sparse as sp

from georefine.adjustment.assembly import (
    BlockTriplets,
    JacobianAssembler,
    column_squares,
    lower_triangle,
    normal_equations,
)
from georefine.adjustment.blocks import (
    ColumnLayout,
    Linearization,
    ObservationGroup,
    ParameterBlock,
)
from georefine.adjustment.linalg import NotPositiveDefiniteError, SparseCholesky, available_backends
from georefine.adjustment.lm_state import (
    PIVOT_SAFE_LAMBDA,
    Evaluation,
    GroupEvaluation,
    LMState,
    SolverOptions,
    damping_after_acceptance,
    enter_polish,
    fit_scale,
    gain_ratio,
    may_stop_on_prediction,
    model_trusted,
    predicted_decrease,
    raise_damping,
    step_accepted,
    step_too_small,
    stop_before_step,
    trial_needs_jacobians,
    tries_conjugate_gradients,
    weights_settled,
    within_tolerance,
)

# PCG_STALE_ITERATIONS: the bound of the reuse rule (lm_state.tries_conjugate_gradients), importable here as before
from georefine.adjustment.pcg import PCG_STALE_ITERATIONS, NormalSystem, pcg_step  # noqa: F401
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


def _evaluate(
    groups: Sequence[ObservationGroup], values: Mapping[str, np.ndarray], jacobians: bool, robust: bool
) -> Evaluation:
    t0 = time.perf_counter()
    out, total, finite = [], 0.0, True
    for group in groups:
        lin = group.linearize(values, jacobians)
        if not isinstance(lin, Linearization):
            raise TypeError(f"group {group.name!r}: linearize() returned {type(lin).__name__}, not a Linearization")
        r = lin.residuals
        if not np.all(np.isfinite(r)):
            finite = False
            out.append(GroupEvaluation(lin, None, None, 0, math.inf, math.inf, math.inf, 0))
            total = math.inf
            continue
        loss = getattr(group, "loss", None) if robust else None
        w = irls_weights(loss, lin.observation, r)
        name = None if loss is None else getattr(loss, "name", type(loss).__name__)
        n_down = int(np.count_nonzero(w.weight < 0.5))
        median_s = float(np.median(w.s)) if w.s.size else math.nan
        out.append(GroupEvaluation(lin, w.row_sqrt_weight, name, w.s.size, w.cost, w.sum_s, w.sum_ws, n_down, median_s))
        total += w.cost
    return Evaluation(out, total, finite and math.isfinite(total), jacobians, time.perf_counter() - t0)


def _assemble_jacobian(
    evaluation: Evaluation, layout: ColumnLayout, assembler: JacobianAssembler
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


def _normal_equations(evaluation: Evaluation, layout: ColumnLayout, assembler: JacobianAssembler) -> NormalSystem:
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
    _evaluation: Evaluation | None
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


@dataclass(frozen=True)
class _Solve:
    """What stays fixed through a solve: the problem, the options and the tools kept for all steps."""

    groups: Sequence[ObservationGroup]
    options: SolverOptions
    layout: ColumnLayout
    spent: float  # unknowns plus the degrees of freedom spent before the adjustment (_spent)
    assembler: JacobianAssembler  # one structure of J for all iterations
    factorizer: SparseCholesky  # one symbolic analysis for all iterations
    reuse: bool  # steps after the first by conjugate gradients on the last factor (reuse_factor_from)
    progress: Callable[[IterationSummary], None] | None
    t_start: float
    log: Callable[..., None]

    def evaluate(self, state: LMState, values: Mapping[str, np.ndarray], jacobians: bool) -> Evaluation:
        """The groups evaluated at ``values`` (the time counted in ``state``)."""
        evaluation = _evaluate(self.groups, values, jacobians, self.options.robust)
        state.t_eval += evaluation.seconds
        return evaluation

    def assemble(self, state: LMState) -> None:
        """The normal equations at the current estimate; its Jacobians are dropped after."""
        state.normal = _normal_equations(state.current, self.layout, self.assembler)
        state.t_asm += state.normal.seconds
        state.normal_is_current = True
        state.current = state.current.without_jacobians()

    def report(self, state: LMState, change, gain, step, g_max, accepted: bool) -> None:
        if self.progress is not None:
            self.progress(
                IterationSummary(
                    state.iterations, float(state.cost), float(change), float(gain), float(step), float(g_max),
                    float(state.lam), bool(accepted), time.perf_counter() - self.t_start,
                )
            )


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
    layout = ColumnLayout.build(blocks)
    run = _Solve(groups, options, layout, _spent(layout, groups), JacobianAssembler(),
                 SparseCholesky(options.linear_solver), layout.n_cols >= options.reuse_factor_from, progress, t_start,
                 logger.info if options.verbose else logger.debug)
    state = _initial_state(run, blocks)
    while state.termination is None:
        _trial_step(run, state)
    state.factor = None  # free the last factor before the statistics and the outcome

    backend = available_backends()[0] if state.backend == "auto" else state.backend
    timings = Timings(state.t_eval, state.t_asm, state.t_fac - state.t_norm, time.perf_counter() - t_start, state.t_norm)
    result = _statistics(groups, state, layout, run.spent, timings, backend)
    run.log("LM end: %s", result.summary())
    current = state.normal_is_current
    return LMOutcome(
        result,
        {k: np.array(v) for k, v in state.values.items()},
        layout.col_start,
        state.normal if current else None,
        None if current else state.current,
        layout,
        run.factorizer,
        None if current else run.assembler,
    )


def _initial_state(run: _Solve, blocks: Mapping[str, ParameterBlock]) -> LMState:
    """The state at the blocks' values: evaluated, the normal equations assembled."""
    values: dict[str, np.ndarray] = {}
    for name, block in blocks.items():
        arr = block.values.copy()
        arr.setflags(write=False)
        values[name] = arr
    current = _evaluate(run.groups, values, True, run.options.robust)
    if not current.finite:
        bad = [g.name for g, ge in zip(run.groups, current.groups) if not math.isfinite(ge.cost)]
        raise ValueError(f"non-finite residuals at the initial values in group(s): {', '.join(bad)}")
    normal = _normal_equations(current, run.layout, run.assembler)
    state = LMState(values, current.without_jacobians(), normal, run.options.initial_lambda, history=[current.cost],
                    backend=run.options.linear_solver, t_eval=current.seconds, t_asm=normal.seconds)
    unobserved = int(np.count_nonzero(normal.diag == 0))
    if unobserved:
        logger.warning("%d unknown(s) have no observations; the normal matrix is singular", unobserved)
    run.log("LM start: cost %.6g, %d unknowns, %d residuals", state.cost, run.layout.n_cols, current.n_rows)
    if run.layout.n_cols == 0:
        state.termination = "no_unknowns"
    return state


def _trial_step(run: _Solve, state: LMState) -> None:
    """One iteration: the tests before a step, the step, the tests on its prediction, its trial."""
    options, log = run.options, run.log
    g_max = float(np.max(np.abs(state.normal.g), initial=0.0))
    state.termination = stop_before_step(state, g_max, options)
    if state.termination is not None:
        return
    state.iterations += 1
    delta, exact = _solve_step(run, state)
    if delta is None:
        state.termination = "no_progress" if raise_damping(state) else None
        log("iter %3d: factorisation failed, lambda -> %.3g", state.iterations, state.lam)
        run.report(state, 0.0, -math.inf, math.nan, g_max, False)
        return

    step_norm = float(np.linalg.norm(delta))
    if step_too_small(step_norm, run.layout.parameter_norm(state.values), options):
        state.termination = "parameter_tolerance"
        run.report(state, 0.0, math.nan, step_norm, g_max, False)
        return
    predicted = predicted_decrease(state.normal, state.lam, delta, exact)
    if may_stop_on_prediction(state, options) and within_tolerance(
            predicted, state.cost, fit_scale(state.current, run.layout.n_cols, run.spent, options), options):
        lam = state.lam
        if enter_polish(state, options):
            state.redamped = True  # the next step solves the same N at the least damping
            log("iter %3d: predicted change %.3g within the tolerance at lambda %.3g: on with lambda %.3g",
                state.iterations, predicted, lam, state.lam)
            return
        state.termination = "function_tolerance"
        log("iter %3d: predicted change %.3g within the tolerance: stop before the trial", state.iterations, predicted)
        run.report(state, 0.0, math.nan, step_norm, g_max, False)
        return

    trial_values = run.layout.apply_step(state.values, delta)
    trial = run.evaluate(state, trial_values, trial_needs_jacobians(state))
    actual = state.cost - trial.cost if trial.finite else -math.inf
    gain = gain_ratio(actual, predicted)
    if step_accepted(trial, gain):
        _accept(run, state, trial_values, trial, actual, gain)
        log("iter %3d: cost %.9g  change %.3g  gain %.3f  |step| %.3g  max|g| %.3g  lambda %.3g",
            state.iterations, state.cost, actual, gain, step_norm, g_max, state.lam)
        run.report(state, actual, gain, step_norm, g_max, True)
    else:
        state.trusted = False
        state.termination = "no_progress" if raise_damping(state) else None
        log("iter %3d: rejected (gain %.3g), lambda -> %.3g", state.iterations, gain, state.lam)
        run.report(state, actual, gain, step_norm, g_max, False)


def _solve_step(run: _Solve, state: LMState) -> tuple[np.ndarray | None, bool]:
    """``(N + lambda D) delta = -g``: by conjugate gradients where :func:`tries_conjugate_gradients`
    says so and they converge, else by a factorisation. Returns ``(delta, exact)``, ``delta`` None
    where the step could not be solved (not positive definite, or not finite)."""
    t0 = time.perf_counter()
    delta, exact = None, True
    by_cg = tries_conjugate_gradients(state, run.reuse)
    state.redamped = False
    if by_cg:
        delta, state.pcg_iterations = pcg_step(state.normal, state.lam, state.factor)
        exact = delta is None
        run.log("iter %3d: conjugate gradients %s after %d iterations", state.iterations,
                "converged" if delta is not None else "did not converge", state.pcg_iterations)
    if delta is not None:
        state.pcg_steps += 1
    else:
        try:
            state.factor = None  # free the old factor first (a G/I/L factor of an hour's flight is GBs)
            t_n = time.perf_counter()
            A = state.normal.damped_lower(state.lam)
            state.t_norm += time.perf_counter() - t_n
            # The damping keeps every pivot above lam * D (SparseCholesky.factorize): no singularity test.
            state.factor = run.factorizer.factorize(A, lower=True, check_pivots=state.lam < PIVOT_SAFE_LAMBDA)
            del A
            state.factorisations += 1
            state.pcg_iterations = 0
            state.backend = state.factor.backend
            delta = state.factor.solve(-state.normal.g)
        except NotPositiveDefiniteError:
            state.factor, delta = None, None
    state.t_fac += time.perf_counter() - t0
    if delta is not None and not np.all(np.isfinite(delta)):
        delta = None
    return delta, exact


def _accept(run: _Solve, state: LMState, values: dict[str, np.ndarray], trial: Evaluation, actual: float,
            gain: float) -> None:
    """Move to an accepted trial: the damping falls, the cost-change test decides whether the solve
    ends (or polishes, :func:`enter_polish`); if it goes on, the normal equations are assembled at
    the new estimate (else at the solution they are assembled only if covariances are asked for)."""
    options = run.options
    state.accepted_steps += 1
    state.trusted = model_trusted(gain)
    state.settled = weights_settled(state.current, trial, fit_scale(trial, run.layout.n_cols, run.spent, options),
                                    options)
    state.values = values
    # The last linearisation's J and N are spent: let them go before the new ones are evaluated and
    # assembled (the factor stays, the next step's preconditioner). Held, they doubled the solve's
    # J and N at the assembly, which set the G/I/L's peak.
    state.normal = None
    if not trial.has_jacobians:
        trial = run.evaluate(state, values, True)
    state.current = trial
    state.history.append(state.cost)
    state.lam, state.nu = damping_after_acceptance(state.lam, gain), 2.0
    converged = within_tolerance(actual, state.cost + actual,
                                 fit_scale(state.current, run.layout.n_cols, run.spent, options), options)
    lam = state.lam
    if converged and enter_polish(state, options):
        converged = False
        run.log("iter %3d: cost change within the tolerance at lambda %.3g: on with lambda %.3g",
                state.iterations, lam, state.lam)
    if converged:
        state.normal_is_current = False
        state.termination = "function_tolerance"
    else:
        run.assemble(state)


def _spent(layout: ColumnLayout, groups) -> float:
    """Unknowns plus the degrees of freedom the observations spent before the adjustment
    (readings cleaned of a signal fitted to themselves, ``ImuObservation.consumed_redundancy``):
    what the redundancy and the variance factor subtract from the rows."""
    return layout.n_cols + sum(float(g.consumed_redundancy) for g in groups)


def _statistics(groups, state: LMState, layout: ColumnLayout, spent: float, timings: Timings, backend: str
                ) -> SolveResult:
    evaluation = state.current
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
        termination=state.termination,
        iterations=state.iterations,
        successful_iterations=state.accepted_steps,
        initial_cost=state.history[0],
        final_cost=total_cost,
        cost_history=tuple(float(c) for c in state.history),
        final_lambda=state.lam,
        n_unknowns=layout.n_cols,
        n_observations=n_obs,
        n_residuals=n_rows,
        redundancy=redundancy,
        variance_factor=evaluation.variance_factor(spent),
        groups=tuple(stats),
        timings=timings,
        backend=backend,
        factorisations=state.factorisations,
        iterative_steps=state.pcg_steps,
    )
