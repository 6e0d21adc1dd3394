"""Results of a least-squares solve: per-iteration summaries, per-group statistics, timings.

Frozen dataclasses returned by :func:`georefine.adjustment.solver.run_levenberg_marquardt` and
:meth:`georefine.adjustment.problem.Problem.solve`, with JSON-able ``to_dict()`` for reports and
``from_dict()`` to read that form back (``SolveResult.from_dict(d).to_dict() == d``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy.special import chdtrc, chdtri  # chi-square tail and quantiles without scipy.stats (0.4 s to import)

from georefine.adjustment.robust import downweight_threshold
from georefine.adjustment.variance_components import VarianceComponent

_CONVERGED = ("function_tolerance", "parameter_tolerance", "gradient_tolerance", "no_unknowns")


@dataclass(frozen=True)
class IterationSummary:
    """One trial step, passed to the ``progress`` callback.

    ``cost`` is the cost after the iteration (unchanged when the step was rejected),
    ``cost_change`` the actual decrease of the trial, ``gain_ratio`` actual / predicted
    decrease, ``step_norm`` ``||delta||``, ``gradient_max_norm`` ``max |g|`` at the start.
    """

    iteration: int
    cost: float
    cost_change: float
    gain_ratio: float
    step_norm: float
    gradient_max_norm: float
    lambda_: float
    accepted: bool
    elapsed_s: float


@dataclass(frozen=True)
class GroupStatistics:
    """Per observation group at the solution.

    Attributes
    ----------
    name
        Group name.
    robust_loss
        Name of the loss applied, ``None`` for plain least squares.
    n_observations, n_residuals
        Number of observations and of residual rows.
    rms
        RMS of the whitened residuals (before robust weighting).
    cost, cost_share
        The group's part of the cost ``1/2 sum rho(s)`` and its fraction of the total.
    variance_factor
        ``sum w r^2 / n_residuals``: approximate (ignores the group's share of the redundancy,
        so it is biased low by about ``unknowns / rows``).
    n_downweighted
        Observations whose robust weight ``rho'(s)`` is below 0.5.
    robust_sigma0
        ``sqrt(median s / median chi2(k))`` over the observations' squared norms ``s`` (``k``
        rows each): about 1 when the model fits, whatever a minority of outliers does; NaN in
        results stored before it was recorded.
    expected_downweighted
        The share of observations a fitting model with honest sigmas weights below 0.5 by
        chance: ``P(chi2(k) > s*)`` with ``s*`` the loss's threshold (Cauchy ``c^2``: with
        ``c = 2`` on three rows 26 %); 0 without a robust loss, NaN in older results. A
        ``n_downweighted`` far above it points to wrong matches or optimistic sigmas.
    residual_histogram
        The whitened residual rows counted per bin of :data:`RESIDUAL_EDGES`, the outer bins
        holding everything beyond them (:func:`residual_histogram`): set against ``N(0, 1)`` in
        the report, it shows whether the residuals look like the noise the sigmas state, and how
        heavy the tails are that the robust loss weighs down.
    """

    name: str
    robust_loss: str | None
    n_observations: int
    n_residuals: int
    rms: float
    cost: float
    cost_share: float
    variance_factor: float
    n_downweighted: int
    robust_sigma0: float = float("nan")
    expected_downweighted: float = float("nan")
    residual_histogram: tuple[int, ...] = ()  # whitened residual rows per bin of RESIDUAL_EDGES; () in older results

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> GroupStatistics:
        """A group as :meth:`SolveResult.to_dict` writes it (the defaults where older results lack a figure)."""
        return cls(str(d["name"]), d["robust_loss"], int(d["n_observations"]), int(d["n_residuals"]), _real(d["rms"]),
                   _real(d["cost"]), _real(d["cost_share"]), _real(d["variance_factor"]), int(d["n_downweighted"]),
                   _real(d.get("robust_sigma0")), _real(d.get("expected_downweighted")),
                   tuple(int(c) for c in d.get("residual_histogram", ())))


@dataclass(frozen=True)
class Timings:
    """Wall-clock seconds: group evaluation (residuals and Jacobians), sparse assembly of ``J``,
    factorisation and solve (conjugate-gradient steps included), total; and the normal matrix
    ``lower(J^T J)`` with its damping (``normal_s``, not part of the factorisation's)."""

    evaluation_s: float
    assembly_s: float
    factorization_s: float
    total_s: float
    normal_s: float = 0.0

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Timings:
        return cls(*(_real(d[k]) for k in ("evaluation_s", "assembly_s", "factorization_s", "total_s")),
                   _real(d.get("normal_s", 0.0)))


@dataclass(frozen=True)
class SolveResult:
    """Outcome and statistics of one adjustment.

    Attributes
    ----------
    termination
        ``function_tolerance``, ``parameter_tolerance``, ``gradient_tolerance``,
        ``max_iterations``, ``no_progress`` or ``no_unknowns``.
    iterations, successful_iterations
        Trial steps and accepted steps.
    initial_cost, final_cost, cost_history
        Cost ``1/2 sum rho`` at the start, at the end, and after every accepted step.
    final_lambda
        Damping at the end.
    n_unknowns, n_observations, n_residuals
        Free tangent dimensions (columns), observations and residual rows.
    redundancy
        ``n_residuals - n_unknowns``.
    variance_factor
        A-posteriori ``sigma0^2 = sum w r^2 / redundancy`` (NaN without redundancy).
    groups
        :class:`GroupStatistics` per group.
    timings
        :class:`Timings`.
    backend
        Sparse Cholesky backend used.
    factorisations, iterative_steps
        Steps solved by a Cholesky factorisation, and by conjugate gradients preconditioned
        with an earlier one (large problems, :class:`~georefine.adjustment.solver.SolverOptions`).
    variance_components
        :class:`~georefine.adjustment.variance_components.VarianceComponent` per group (or pool)
        where the posterior used them; empty otherwise.
    """

    termination: str
    iterations: int
    successful_iterations: int
    initial_cost: float
    final_cost: float
    cost_history: tuple[float, ...]
    final_lambda: float
    n_unknowns: int
    n_observations: int
    n_residuals: int
    redundancy: int
    variance_factor: float
    groups: tuple[GroupStatistics, ...]
    timings: Timings
    backend: str
    factorisations: int = 0
    iterative_steps: int = 0
    variance_components: tuple[Any, ...] = ()

    @property
    def converged(self) -> bool:
        """Whether a convergence criterion (not an iteration limit or failure) ended the solve."""
        return self.termination in _CONVERGED

    @property
    def sigma0(self) -> float:
        """A-posteriori standard deviation of unit weight ``sqrt(sigma0^2)``."""
        return math.sqrt(self.variance_factor) if self.variance_factor >= 0 else math.nan

    def group(self, name: str) -> GroupStatistics:
        """Statistics of one group by name."""
        for stats in self.groups:
            if stats.name == name:
                return stats
        raise KeyError(f"no group {name!r} in the result")

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-serialisable dictionary (non-finite numbers become ``None``)."""
        out = _jsonable(asdict(self))
        out["converged"] = self.converged
        out["sigma0"] = _jsonable(self.sigma0)
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SolveResult:
        """The result :meth:`to_dict` wrote (``converged`` and ``sigma0`` follow from it), so that
        ``from_dict(d).to_dict() == d``: null reads as NaN, the numbers keep their JSON type."""
        return cls(
            str(d["termination"]), int(d["iterations"]), int(d["successful_iterations"]), _real(d["initial_cost"]),
            _real(d["final_cost"]), tuple(_real(c) for c in d["cost_history"]), _real(d["final_lambda"]),
            int(d["n_unknowns"]), int(d["n_observations"]), int(d["n_residuals"]), int(d["redundancy"]),
            _real(d["variance_factor"]), tuple(GroupStatistics.from_dict(g) for g in d["groups"]),
            Timings.from_dict(d["timings"]), str(d["backend"]), int(d.get("factorisations", 0)),
            int(d.get("iterative_steps", 0)),
            tuple(VarianceComponent.from_dict(c) for c in d.get("variance_components", ())),
        )

    def summary(self) -> str:
        """A few lines for logs and reports."""
        lines = [
            f"{self.termination} after {self.iterations} iterations ({self.successful_iterations} accepted), "
            f"cost {self.initial_cost:.6g} -> {self.final_cost:.6g}",
            f"unknowns {self.n_unknowns}, residuals {self.n_residuals}, redundancy {self.redundancy}, "
            f"sigma0^2 {self.variance_factor:.4g}, {self.timings.total_s:.2f} s ({self.backend}; "
            f"{self.factorisations} factorisations, {self.iterative_steps} conjugate-gradient steps)",
        ]
        for g in self.groups:
            lines.append(
                f"  {g.name}: {g.n_observations} obs, {g.n_residuals} rows, rms {g.rms:.4g}, "
                f"cost share {g.cost_share:.1%}, s0^2~{g.variance_factor:.4g}, robust s0 {g.robust_sigma0:.3g}, "
                f"downweighted {g.n_downweighted}"
            )
        for c in self.variance_components:
            lines.append(f"  variance component {'+'.join(c.groups)}: redundancy {c.redundancy:.1f}, "
                         f"factor {c.factor:.4g}, posterior scale {c.scale:.4g}")
        return "\n".join(lines)


def _real(v: Any) -> float:
    """A number of :meth:`SolveResult.to_dict`'s form: null (a non-finite number) as NaN; an
    integer stays one, so that writing it again gives the same text."""
    return math.nan if v is None else v


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


# ---------------------------------------------------------------------------------------------
# Layout, evaluation and assembly
# ---------------------------------------------------------------------------------------------


RESIDUAL_EDGES = tuple(float(e) for e in np.linspace(-5.0, 5.0, 41))
"""Bin edges of :attr:`GroupStatistics.residual_histogram`: a quarter sigma wide, +-5 sigma."""


def residual_histogram(r: np.ndarray) -> tuple[int, ...]:
    """Counts of the whitened residuals ``r`` per bin of :data:`RESIDUAL_EDGES`, those beyond the
    outer edges in the outer bins (a few numbers in ``adjustment.json`` whatever the rows)."""
    edges = np.asarray(RESIDUAL_EDGES)
    counts, _ = np.histogram(np.clip(np.ravel(r), edges[0], edges[-1]), bins=edges)
    return tuple(int(c) for c in counts)


def robust_sigma0(median_s: float, dof: float) -> float:
    """``sqrt(median s / median chi2(dof))``: sigma0 from the median squared norm ``s`` of
    observations with ``dof`` rows each; about 1 when the model and the sigmas fit, whatever a
    minority of outliers does."""
    return math.sqrt(median_s / chdtri(dof, 0.5)) if math.isfinite(median_s) else math.nan


def expected_downweighted(loss, dof: float) -> float:
    """``P(chi2(dof) > s*)``: the share of observations (``dof`` rows each) that ``loss`` weights
    below 0.5 by chance when the model fits (:attr:`GroupStatistics.expected_downweighted`); 0
    without a robust loss."""
    threshold = downweight_threshold(loss)
    return 0.0 if threshold is None else float(chdtrc(dof, threshold))
