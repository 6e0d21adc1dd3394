"""The state of a Levenberg-Marquardt solve and the rules that move it (docs/ARCHITECTURE.md §4.4).

:func:`georefine.adjustment.solver.run_levenberg_marquardt` evaluates the groups, assembles the
normal equations and solves the steps; what it does with them is decided here, each rule in one
function: whether a step is first tried by conjugate gradients (:func:`tries_conjugate_gradients`),
the decrease the model predicts for it (:func:`predicted_decrease`), whether it is accepted
(:func:`gain_ratio`, :func:`step_accepted`), how the damping changes (:func:`damping_after_acceptance`,
:func:`raise_damping`), when the model is trusted (:func:`model_trusted`) and the robust weights
have settled (:func:`weights_settled`, :func:`reweighting`), the cost-change test
(:func:`fit_scale`, :func:`within_tolerance`), when the solve may stop on a prediction
(:func:`may_stop_on_prediction`) or goes on at the least damping instead (:func:`enter_polish`),
and the termination tests before a step (:func:`stop_before_step`, :func:`step_too_small`).
:class:`LMState` holds what one trial step hands to the next; :class:`SolverOptions` (re-exported
by :mod:`~georefine.adjustment.solver`) sets the rules' tolerances and switches.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from georefine.adjustment.blocks import Linearization
from georefine.adjustment.linalg import Factorization
from georefine.adjustment.pcg import PCG_STALE_ITERATIONS, NormalSystem

__all__ = [
    "SolverOptions",
    "MIN_LAMBDA",
    "MAX_LAMBDA",
    "MIN_GAIN_RATIO",
    "PIVOT_SAFE_LAMBDA",
    "POLISH_LAMBDA",
    "GroupEvaluation",
    "Evaluation",
    "LMState",
    "stop_before_step",
    "tries_conjugate_gradients",
    "step_too_small",
    "predicted_decrease",
    "gain_ratio",
    "step_accepted",
    "trial_needs_jacobians",
    "damping_after_acceptance",
    "raise_damping",
    "model_trusted",
    "fit_scale",
    "within_tolerance",
    "reweighting",
    "weights_settled",
    "may_stop_on_prediction",
    "enter_polish",
]

MIN_LAMBDA = 1e-15
MAX_LAMBDA = 1e16
MIN_GAIN_RATIO = 1e-3
PIVOT_SAFE_LAMBDA = 1e-10  # damping above which a factorisation needs no singularity test
POLISH_LAMBDA = 1e-13  # a solve that meets the cost-change test at a larger damping goes on (SolverOptions.polish)


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
        When the cost-change test is first met by a step whose damping exceeded ``POLISH_LAMBDA``,
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


# ---------------------------------------------------------------------------------------------
# Evaluations
# ---------------------------------------------------------------------------------------------


@dataclass
class GroupEvaluation:
    """One group's linearisation at an estimate, with its robust weights and sums."""

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
class Evaluation:
    """All groups evaluated at one estimate: their linearisations and the total cost."""

    groups: list[GroupEvaluation]
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

    def without_jacobians(self) -> Evaluation:
        """The same evaluation without the Jacobian arrays (kept: residuals and weights for the
        statistics), to free memory."""
        groups = [replace(ge, linearization=Linearization(ge.linearization.residuals, [], ge.linearization.observation))
                  for ge in self.groups]
        return Evaluation(groups, self.cost, self.finite, False, self.seconds)


# ---------------------------------------------------------------------------------------------
# The state
# ---------------------------------------------------------------------------------------------


@dataclass
class LMState:
    """What one trial step of a Levenberg-Marquardt solve hands to the next.

    ``normal`` is the linearisation at ``values`` (``normal_is_current``) until the accepted step
    that ends the solve; that one leaves it to the posterior, which assembles it from ``current``
    only if covariances are asked for.
    """

    values: dict[str, np.ndarray]  # the current estimate (read-only arrays)
    current: Evaluation  # its evaluation (Jacobians dropped once ``normal`` is assembled)
    normal: NormalSystem | None  # J, g and D at the last assembly (None between an accepted step and the next assembly)
    lam: float  # the damping, relative to D
    nu: float = 2.0  # the factor of the next rise of the damping
    normal_is_current: bool = True
    history: list[float] = field(default_factory=list)  # the cost at the start and after every accepted step
    iterations: int = 0  # trial steps, accepted or not
    accepted_steps: int = 0
    polishing: bool = False  # the cost-change test was met once at a larger damping (SolverOptions.polish)
    trusted: bool = False  # the last accepted step's gain ratio bore the Gauss-Newton model out
    settled: bool = False  # the robust weights did not change over the last accepted step
    redamped: bool = False  # the last trial step was only re-damped: the factor is of the same N
    factor: Factorization | None = None  # the last factorisation: the preconditioner of the next steps
    pcg_iterations: int = 0  # of the last step by conjugate gradients since that factorisation
    factorisations: int = 0
    pcg_steps: int = 0
    backend: str = "auto"  # of the last factorisation
    termination: str | None = None  # set when the solve ends
    t_eval: float = 0.0  # seconds evaluating the groups
    t_asm: float = 0.0  # assembling J, g and D
    t_fac: float = 0.0  # solving the steps (factorisations, conjugate gradients), forming N + lambda D included
    t_norm: float = 0.0  # forming N + lambda D

    @property
    def cost(self) -> float:
        """The cost at the current estimate."""
        return self.current.cost


# ---------------------------------------------------------------------------------------------
# The rules
# ---------------------------------------------------------------------------------------------


def stop_before_step(state: LMState, g_max: float, options: SolverOptions) -> str | None:
    """Termination before a trial step: ``"gradient_tolerance"`` when the largest gradient
    component ``g_max`` is at most ``gradient_tolerance``, else ``"max_iterations"`` when
    ``max_iterations`` trial steps (accepted or not) have been taken; ``None``: take one."""
    if g_max <= options.gradient_tolerance:
        return "gradient_tolerance"
    if state.iterations >= options.max_iterations:
        return "max_iterations"
    return None


def tries_conjugate_gradients(state: LMState, reuse: bool) -> bool:
    """Whether the next step is first tried by conjugate gradients preconditioned with the last
    factor (else it is factorised): there is a factor, and either the last trial step was only
    re-damped (its factor of ``N + lambda' D`` preconditions ``N + lambda D`` in a step or two), or
    the problem reuses factors (``reuse``: ``SolverOptions.reuse_factor_from``) and the last step
    by conjugate gradients since that factorisation needed at most ``PCG_STALE_ITERATIONS``
    iterations (past that the factor has aged)."""
    return state.factor is not None and (state.redamped or (reuse and state.pcg_iterations <= PCG_STALE_ITERATIONS))


def step_too_small(step_norm: float, x_norm: float, options: SolverOptions) -> bool:
    """The parameter test: ``||delta|| <= parameter_tolerance (||x|| + parameter_tolerance)``."""
    return step_norm <= options.parameter_tolerance * (x_norm + options.parameter_tolerance)


def predicted_decrease(normal: NormalSystem, lam: float, delta: np.ndarray, exact: bool) -> float:
    """The decrease ``L(0) - L(delta)`` the linear model predicts for the step ``delta``.

    Of the damped model, ``1/2 delta^T (lambda D delta - g)``, for a step that solved
    ``(N + lambda D) delta = -g`` exactly (factorised); of the Gauss-Newton model,
    ``-g^T delta - |J delta|^2 / 2``, for an inexact one (conjugate gradients)."""
    if exact:
        return 0.5 * float(delta @ (lam * normal.D * delta - normal.g))
    Jd = normal.J @ delta
    return -float(normal.g @ delta) - 0.5 * float(Jd @ Jd)


def gain_ratio(actual: float, predicted: float) -> float:
    """``rho = actual / predicted`` decrease; ``-inf`` where the model predicts none."""
    return actual / predicted if predicted > 0 else -math.inf


def step_accepted(trial: Evaluation, gain: float) -> bool:
    """A trial step is accepted where its cost is finite and its gain ratio exceeds ``MIN_GAIN_RATIO``."""
    return trial.finite and gain > MIN_GAIN_RATIO


def trial_needs_jacobians(state: LMState) -> bool:
    """The trial is evaluated with its Jacobians right away unless the last step was rejected
    (``nu`` above 2): after an acceptance the next one is likely accepted too."""
    return state.nu <= 2.0


def damping_after_acceptance(lam: float, gain: float) -> float:
    """After an accepted step: ``lambda *= max(1/3, 1 - (2 rho - 1)^3)``, at least ``MIN_LAMBDA``
    (Nielsen 1999); ``nu`` goes back to 2."""
    return max(lam * max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3), MIN_LAMBDA)


def raise_damping(state: LMState) -> bool:
    """After a rejected step or one that could not be solved: ``lambda *= nu``, ``nu *= 2``.
    Returns whether ``lambda`` now exceeds ``MAX_LAMBDA``: no acceptable step (``"no_progress"``)."""
    state.lam, state.nu = state.lam * state.nu, state.nu * 2.0
    return state.lam > MAX_LAMBDA


def model_trusted(gain: float) -> bool:
    """The Gauss-Newton model is borne out by an accepted step whose gain ratio lies within ``[0.5, 2]``."""
    return 0.5 <= gain <= 2.0


def fit_scale(evaluation: Evaluation, n_cols: int, spent: float, options: SolverOptions) -> float:
    """What the cost-change test divides the cost by: with ``relative_to_fit`` and more rows than
    unknowns, ``max(1, sigma0^2)`` at ``evaluation`` (``spent``: the unknowns plus the degrees of
    freedom spent before the adjustment); else 1."""
    if options.relative_to_fit and evaluation.n_rows > n_cols:
        return max(1.0, evaluation.variance_factor(spent))
    return 1.0


def within_tolerance(change: float, cost: float, scale: float, options: SolverOptions) -> bool:
    """The cost-change test: ``change <= function_tolerance * cost / scale`` (``scale`` from
    :func:`fit_scale`)."""
    return change <= options.function_tolerance * (cost / scale)


def reweighting(evaluation: Evaluation) -> bool:
    """Whether a robust loss weights some observation down: while the weights still move, the
    iterations lower the cost by reweighting too, which the fixed-weight model of the next step
    does not predict (the hybrid adjustment's Huber loss on 375 returns stopped on a predicted 15
    after actual changes of 257 and 58, short of its solution)."""
    for ge in evaluation.groups:
        w = ge.row_sqrt_weight
        if w is not None and w.size and float(np.min(w)) < 1.0 - 1e-12:
            return True
    return False


def weights_settled(before: Evaluation, after: Evaluation, scale: float, options: SolverOptions) -> bool:
    """Whether the robust weights settled over a step: their change, weighted by the squared
    residuals, ``1/2 sum |w_after - w_before| r^2``, is within the cost-change test's budget
    ``function_tolerance * F_after / scale``. The fixed-weight model then predicts the next step
    again. Conservative: on the corridor's G/I the Huber weights of a few GNSS epochs move the
    cost by 59 budgets over the first step, 2 over the second and 0.1 over the third, while the
    second step's prediction was already right."""
    budget = options.function_tolerance * after.cost / scale
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


def may_stop_on_prediction(state: LMState, options: SolverOptions) -> bool:
    """Whether the predicted decrease of the next step may end the solve (``predicted_stop``): the
    model has been borne out (:func:`model_trusted`) and the robust weights no longer move the cost
    beyond the model (settled over the last step, or none weighted down). In the polish the
    weights need not have settled: the cost-change test, reweighting included, was met by an
    evaluated step, and what the polish looks for (a direction the damping left short) is what
    the undamped model predicts."""
    return (options.predicted_stop and state.trusted
            and (state.settled or state.polishing or not reweighting(state.current)))


def enter_polish(state: LMState, options: SolverOptions) -> bool:
    """When the cost-change test is met (by an evaluated step or a prediction): with ``polish``,
    the first time and at a damping above ``POLISH_LAMBDA``, the solve goes on at ``MIN_LAMBDA``
    instead of stopping. Returns whether it does (the state then polishing, at that damping)."""
    if options.polish and not state.polishing and state.lam > POLISH_LAMBDA:
        state.polishing, state.lam = True, MIN_LAMBDA
        return True
    return False
