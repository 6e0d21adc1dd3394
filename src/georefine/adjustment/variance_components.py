"""Variance components: a variance factor per group of observations, for the posterior.

One a-posteriori variance factor ``sigma0^2 = sum w r^2 / (rows - unknowns)`` scales every
posterior covariance alike. Where two sensors misfit differently that is wrong for the
directions one of them alone determines. In the G/I/L adjustment of a vibrating platform the
IMU windows fit at about 2.3-2.7 (what the up-sampling leaves, docs/ARCHITECTURE.md §4.3) and
51,000 plane observations at 0.6-0.7, so the whole adjustment's factor is 1.04-1.15. The tilt
of the scene about the corridor, which no plane sees, keeps the G/I's information and was
given a sigma about 1.5x too small: the G/I/L roll over two passes had error/sigma 1.70 over
three draws where the G/I's was 1.18 (BENCHMARKS.md, Operating conditions).

Each component ``c`` (a group, or a pool of groups) gets its own factor (Foerstner 1979;
Koch 1999, §3.6)::

    s_c = Omega_c / r_c,      r_c = m_c - tr(N^-1 N_c),      Omega_c = sum_c w r^2

``N = sum_c N_c = J^T J`` the whitened, robustly weighted normal matrix at the solution,
``m_c`` the component's residual rows and ``r_c`` its redundancy (the sum of its rows'
redundancy numbers; ``sum_c r_c = rows - unknowns``, so one component's follows from the
others'). The posterior is then ``(sum_c N_c / s_c)^-1``: the covariance of the estimate with
the components so re-weighted. The estimate itself keeps the a-priori weights; its exact
covariance would be the sandwich ``N^-1 (sum_c s_c N_c) N^-1``, which equals the re-weighted
one in every direction one component alone determines (the case above) and exceeds it where
components with different factors share a direction (by at most 17 % in sigma for factors 2.3
and 0.7 sharing one equally). One more factorisation here; the sandwich would need the full
solution columns for every requested element.

Each factor is floored at 1, as the single factor was (``gnss_imu.posterior_scale``): a factor
below 1 comes from the robust losses and from datasheet noise figures that are upper bounds.
Which groups form a component is the caller's choice (``pools``; the trajectory posteriors pool
the navigation sensors, ``gnss_imu.POSTERIOR_POOLS``, and say why); without it every group with
at least ``min_redundancy`` is one and the small groups (priors, random walks) are pooled.

The trace ``tr(N^-1 N_c) = tr(H_c)``, with ``H_c = J_c N^-1 J_c^T`` the component's hat matrix
(eigenvalues in [0, 1] since ``N >= N_c``), is exact for groups of at most ``probes`` rows
(their unit vectors) and otherwise Hutchinson's estimate ``mean_k u_k^T H_c u_k`` over
``probes`` Rademacher vectors ``u_k`` (Hutchinson 1990): ``v = J_c^T u`` and one solve with
the factor of ``N`` each. Its standard deviation is ``sqrt(2 (||H_c||_F^2 - sum diag(H_c)^2) / K)
<= sqrt(2 tr(H_c) / K)``: for the planes of a 1.2 km corridor (a trace of about 16,500 over
155,000 rows) and 32 probes, 24-28 (0.02 % of their redundancy; the bound says 32). No library in the dependency list estimates
redundancy numbers; it is the solve per probe that costs, done by the backend.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from georefine.adjustment.linalg import Factorization

__all__ = ["VarianceComponent", "group_traces", "row_weights", "traces_needed", "variance_components"]

MIN_REDUNDANCY = 30.0
"""Groups with less redundancy are pooled into one component (the priors, the random walks)."""
PROBES = 32
"""Rademacher probes per large group (standard deviation of a trace ``t`` at most ``sqrt(t / 16)``)."""
_ROW_CHUNK = 200_000
_MAX_RHS = 64


@dataclass(frozen=True)
class VarianceComponent:
    """One variance component: the groups it covers and its estimate.

    Attributes
    ----------
    groups
        Names of the observation groups (one, or a pool).
    n_residuals
        Residual rows.
    redundancy
        ``rows - tr(N^-1 N_g)`` summed over the groups; for the one component whose traces were
        not estimated, the adjustment's redundancy less the other components'.
    redundancy_sd
        Standard deviation of ``redundancy`` from the trace estimates (0 where exact).
    sum_wr2
        ``sum w r^2`` of the rows (robust weights at the solution).
    factor
        ``sum_wr2 / redundancy`` (NaN without redundancy).
    scale
        What the posterior uses: ``factor`` floored at 1; 1 with less than one unit of
        redundancy.
    """

    groups: tuple[str, ...]
    n_residuals: int
    redundancy: float
    redundancy_sd: float
    sum_wr2: float
    factor: float
    scale: float

    @classmethod
    def from_dict(cls, d: dict) -> VarianceComponent:
        """A component as :meth:`~georefine.adjustment.statistics.SolveResult.to_dict` writes it (NaN as null)."""
        def real(k: str) -> float:
            return math.nan if d[k] is None else d[k]

        return cls(tuple(str(g) for g in d["groups"]), int(d["n_residuals"]),
                   *(real(k) for k in ("redundancy", "redundancy_sd", "sum_wr2", "factor", "scale")))


def group_traces(J: sp.csr_matrix, row_counts: Sequence[int], factor: Factorization, *,
                 probes: int = PROBES, seed: int = 0, which: Sequence[bool] | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """``tr(N^-1 N_g)`` per group and its standard deviation (0 where exact; NaN where not ``which``).

    ``J``: whitened, weighted Jacobian (rows in group order, ``row_counts`` each); ``factor``:
    of ``N = J^T J``. Seeded (``seed``), so a rerun gives the same figures.
    """
    rng = np.random.default_rng(seed)
    J = sp.csr_matrix(J)
    n = J.shape[1]
    starts = np.concatenate([[0], np.cumsum(row_counts)]).astype(np.int64)
    if starts[-1] != J.shape[0]:
        raise ValueError(f"group_traces: row counts sum to {starts[-1]}, J has {J.shape[0]} rows")
    traces = np.zeros(len(row_counts))
    sds = np.zeros(len(row_counts))
    for g in range(len(row_counts)):
        if which is not None and not which[g]:
            traces[g] = sds[g] = math.nan
            continue
        a, b = int(starts[g]), int(starts[g + 1])
        m = b - a
        if m == 0 or n == 0:
            continue
        exact = m <= probes
        k = m if exact else probes
        if exact:
            V = J[a:b].T.toarray()  # (n, m): the rows themselves
        else:
            V = np.zeros((n, k))
            for c in range(a, b, _ROW_CHUNK):
                e = min(b, c + _ROW_CHUNK)
                U = rng.choice(np.array([-1.0, 1.0]), size=(e - c, k))
                V += J[c:e].T @ U
        quad = np.empty(k)
        for c in range(0, k, _MAX_RHS):
            Vb = V[:, c:c + _MAX_RHS]
            quad[c:c + Vb.shape[1]] = np.einsum("ij,ij->j", Vb, factor.solve(Vb))
        if exact:
            traces[g] = quad.sum()
        else:
            traces[g] = quad.mean()
            sds[g] = quad.std(ddof=1) / math.sqrt(k)
    return traces, sds


def variance_components(names: Sequence[str], row_counts: Sequence[int], sum_wr2: Sequence[float],
                        traces: np.ndarray, trace_sds: np.ndarray, redundancy: float, *,
                        pools: Sequence[Sequence[str]] | None = None,
                        min_redundancy: float = MIN_REDUNDANCY,
                        consumed: Sequence[float] | None = None) -> tuple[VarianceComponent, ...]:
    """The components and their factors.

    ``pools`` None: one component per group with at least ``min_redundancy``, the rest pooled.
    ``pools`` given: one component per pool (names of groups; those absent are ignored) and one
    for the groups in none. ``traces`` may be NaN (not estimated) for the groups of one
    component: its redundancy is then the adjustment's ``redundancy`` (rows - unknowns, exact)
    less the others', and it carries their estimates' standard deviation. ``consumed``: per group,
    degrees of freedom spent before the adjustment (``ImuObservation.consumed_redundancy``),
    taken off its redundancy (``redundancy`` already excludes them). Each ``scale`` is the factor floored at 1; a component
    with less than one unit of redundancy keeps the a-priori weights (scale 1): nothing in the
    data measures its fit.
    """
    m = np.asarray(row_counts, dtype=float)
    omega = np.asarray(sum_wr2, dtype=float)
    r = m - np.asarray(traces, dtype=float)
    if consumed is not None:
        r = r - np.asarray(consumed, dtype=float)
    sds = np.asarray(trace_sds, dtype=float)
    present = [i for i in range(len(names)) if m[i] > 0]
    if pools is None:
        members = [[i] for i in present if r[i] >= min_redundancy]
    else:
        index = {n: i for i, n in enumerate(names)}
        members = [[index[n] for n in pool if n in index and m[index[n]] > 0] for pool in pools]
        members = [ix for ix in members if ix]
    taken = {i for ix in members for i in ix}
    rest = [i for i in present if i not in taken]
    if rest:
        members.append(rest)
    unknown = [k for k, idx in enumerate(members) if not np.all(np.isfinite(r[idx]))]
    if len(unknown) > 1:
        raise ValueError("variance_components: the traces of more than one component are missing")
    out = []
    for k, idx in enumerate(members):
        if k in unknown:  # the total's redundancy less the others'
            others = [i for j, ix in enumerate(members) if j != k for i in ix]
            red = float(redundancy - r[others].sum())
            sd = float(np.sqrt(np.sum(sds[others] ** 2)))
        else:
            red, sd = float(r[idx].sum()), float(np.sqrt(np.sum(sds[idx] ** 2)))
        om = float(omega[idx].sum())
        f = om / red if red > 0 else math.nan
        scale = max(1.0, f) if red >= 1.0 and math.isfinite(f) else 1.0
        out.append(VarianceComponent(tuple(names[i] for i in idx), int(m[idx].sum()), red, sd, om, f, scale))
    return tuple(out)


def traces_needed(names: Sequence[str], row_counts: Sequence[int], pools: Sequence[Sequence[str]] | None
                  ) -> list[bool]:
    """Which groups' traces :func:`variance_components` needs: all with ``pools`` None (the pooling
    depends on them), else those named in a pool (the rest's redundancy follows from the total)."""
    if pools is None:
        return [c > 0 for c in row_counts]
    named = {n for pool in pools for n in pool}
    return [n in named and c > 0 for n, c in zip(names, row_counts)]


def row_weights(components: Sequence[VarianceComponent], names: Sequence[str], row_counts: Sequence[int]
                ) -> np.ndarray:
    """``1 / scale`` for every residual row (groups in ``names`` order, ``row_counts`` rows each)."""
    scale_of = {g: c.scale for c in components for g in c.groups}
    return np.repeat([1.0 / scale_of.get(g, 1.0) for g in names], np.asarray(row_counts, dtype=np.int64))
