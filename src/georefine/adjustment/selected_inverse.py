"""Selected inversion: the entries of ``A^-1`` on the pattern of ``A``'s Cholesky factor.

The posterior sigma of an adjustment are diagonal blocks of ``N^-1``. Solving for their unit
columns costs one forward and backward substitution over the whole factor per column: for the
roll/pitch/yaw and position of 150 knots and the IMU bias nodes (about 2,000 columns) of a
60-minute G/I adjustment (542,000 unknowns) that was 86 s, more than the solve itself. The Takahashi recursion (Takahashi, Fagan and Chen 1973; Erisman
and Tinney 1975) computes every entry of ``Z = A^-1`` that lies on the pattern of ``L``, where
``P A P^T = L L^T``, from the bottom right up, column by column::

    Z_ij = -(1/L_jj) sum_{k in S_j} L_kj Z_ki        (i in S_j, i > j)
    Z_jj = 1/L_jj^2 - (1/L_jj) sum_{k in S_j} L_kj Z_kj

with ``S_j`` the rows below the diagonal of column ``j``. Every ``Z_ki`` it needs is on the
pattern (for ``k`` in ``S_j``, the rows of ``S_j`` below ``k`` are rows of column ``k``:
the fill path property of the elimination tree). The work is ``sum_j |S_j|^2``, about that of
the factorisation itself: 1.6-2.0 s instead of 27 s of solves on the 30-minute G/I matrix
(271,062 unknowns, 15 M non-zeros in ``L``). It is not always the cheaper: see
:func:`_recursion_pays`.

No library in our dependency list exposes it (CHOLMOD has none; MUMPS and PSelInv are not
wheels), so it is written here in numba: :func:`_takahashi_supernodal` takes the factor's
fundamental supernodes (runs of columns with the same structure below) as dense blocks, their
products in BLAS, gathering ``Z`` of the rows below from the later columns; single columns, and
supernodes with very many rows below, go column by column (:func:`_takahashi_column`, each row
pair found by walking the two sorted columns side by side), which is also the reference in the
tests.

The factor ``L`` comes from QDLDL (``factors()``: its ``LDL^T`` rescaled to ``LL^T``, the
default install), from CHOLMOD through scikit-sparse (``Factor.L()``) or from CVXOPT
(``cholmod.getfactor``, which turns its argument into a symbolic factor). With cholespy or SuperLU
(no access to ``L``), or where solving is the cheaper, :func:`selected_inverse` returns no
inverse and the caller solves for unit columns.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve_triangular

from georefine.adjustment.linalg import (
    Factorization,
    NotPositiveDefiniteError,
    SparseCholesky,
    check_by_solve,
    check_pivot_ratios,
    symmetric_matvec,
)

__all__ = ["SelectedInverse", "invert_factor", "selected_inverse"]

log = logging.getLogger(__name__)


NS_PER_WORK_UNIT = 0.6
"""Time of the recursion per unit of ``sum_j |S_j|^2`` (ns, one core): 0.6 on the corridor's G/I
factor (supernodes of 15 columns), 0.13 on its G/I/L factor (16 G units in 2.1 s; supernodes up
to 1,192 columns), against 1.4-2.4 column by column."""
EXPECTED_COLUMNS = 2000
"""Unit columns a posterior asks for (attitude and position at 150 knots, the IMU bias nodes)."""
PROBE_COLUMNS = 64
MIN_SOLVES_PER_FACTORISATION = 2.0
"""Below this ratio of the solves' time to the factorisation's the factor is not even copied out
(scikit-sparse's CHOLMOD, whose ``Factor.L()`` copy took 9.1 s beside a 12.9 s factorisation of
a 60-minute G/I/L matrix).

The copy plus the supernodal recursion cost about one factorisation: on the corridor's G/I/L
factor (30.6 M non-zeros) the recursion took 2.1 s where the factorisation with CVXOPT and the
copy took 4.1 s. Solves predicted at 8.1 (10 minutes of G/I/L: 22.0 s against 2.7 s) and 6.2
factorisations (60 minutes: 156 s against 25 s) lost to the column-by-column recursion (30 s
against 14 s at 10 minutes), which a ratio of 12 kept away; the supernodal one is 13 times
faster there."""


def _probe_solves(factor: Factorization, columns: int = EXPECTED_COLUMNS) -> float:
    """Seconds that ``columns`` unit-column solves take, timed on :data:`PROBE_COLUMNS`.

    The forward half where the factor has it (``solve_half``; CVXOPT's sparse
    ``solve_unit_columns_half``), as the covariance blocks use it.
    """
    cols = np.linspace(0, factor.n - 1, min(PROBE_COLUMNS, factor.n)).astype(np.int64)
    sparse_half = getattr(factor, "solve_unit_columns_half", None)
    t = time.perf_counter()
    if sparse_half is not None:
        sparse_half(cols)
    else:
        E = np.zeros((factor.n, cols.size))
        E[cols, np.arange(cols.size)] = 1.0
        getattr(factor, "solve_half", factor.solve)(E)
    return (time.perf_counter() - t) / cols.size * columns


def _recursion_pays(factor: Factorization, work: float, solve_s: float, columns: int = EXPECTED_COLUMNS) -> bool:
    """Whether the recursion (``work`` multiply-adds) beats ``columns`` unit-column solves (``solve_s``).

    Which one wins depends on the factor's supernodes: on a G/I normal matrix (narrow band,
    small supernodes) the recursion took 2 s against 27 s of solves at 30 minutes of flight; on a
    G/I/L one the planes fill the factor (36 M non-zeros for 108,000 unknowns at 10 minutes) into
    large supernodes, where batched solves run at BLAS-3 speed and the column-by-column recursion
    lost (30 s against 14 s); the supernodal recursion, in BLAS too, took 2.1 s on the corridor's
    G/I/L factor. So a batch of :data:`PROBE_COLUMNS` solves is timed first (``solve_s``,
    :func:`_probe_solves`) and weighed against :data:`NS_PER_WORK_UNIT`.
    """
    recursion_s = NS_PER_WORK_UNIT * 1e-9 * work
    log.debug("selected inverse: recursion ~%.1f s (sum |S_j|^2 = %.3g), %d unit-column solves ~%.1f s (%d unknowns)",
              recursion_s, work, columns, solve_s, factor.n)
    return recursion_s < solve_s


@numba.njit(cache=True, nogil=True)
def _takahashi(indptr: np.ndarray, indices: np.ndarray, lval: np.ndarray, z: np.ndarray) -> bool:  # pragma: no cover
    """``z`` = ``(L L^T)^-1`` on the pattern of ``L`` (CSC, sorted rows, diagonal first in each column),
    column by column (:func:`_takahashi_column`); the reference of :func:`_takahashi_supernodal`.

    False when the pattern is not a factor's (a row of ``S_j`` missing from a column of ``S_j``).
    """
    acc = np.zeros(indptr.size - 1)
    for j in range(indptr.size - 2, -1, -1):
        if not _takahashi_column(j, indptr, indices, lval, z, acc):
            return False
    return True


@numba.njit(cache=True, nogil=True)
def _takahashi_column(j, indptr, indices, lval, z, acc) -> bool:  # pragma: no cover - numba
    """Column ``j`` of the recursion (module docstring), every later column done. ``acc`` (n zeros)
    holds ``sum_{k in S_j} L_kj Z_ki`` by row ``i`` and is zeroed again."""
    p0 = indptr[j]
    p1 = indptr[j + 1]
    d = lval[p0]
    for pb in range(p0 + 1, p1):
        b = indices[pb]
        lb = lval[pb]
        q = indptr[b]
        acc[b] += lb * z[q]  # Z_bb
        q += 1
        q1 = indptr[b + 1]
        for pa in range(pb + 1, p1):  # rows a > b of S_j: also rows of column b
            a = indices[pa]
            while q < q1 and indices[q] < a:
                q += 1
            if q == q1 or indices[q] != a:
                return False
            zab = z[q]
            acc[a] += lb * zab
            acc[b] += lval[pa] * zab
    s = 0.0
    for pa in range(p0 + 1, p1):
        a = indices[pa]
        v = -acc[a] / d
        acc[a] = 0.0
        z[pa] = v
        s += lval[pa] * v
    z[p0] = 1.0 / (d * d) - s / d
    return True


DENSE_ROWS_MAX = 2000
"""Supernodes with more rows below them than this go column by column: their dense ``Z_UU``
(``8 u^2`` bytes, 32 MB here) stays bounded."""


@numba.njit(cache=True, nogil=True)
def _supernodes(indptr: np.ndarray, indices: np.ndarray) -> np.ndarray:  # pragma: no cover - numba
    """Where the fundamental supernodes of ``L`` start (and ``n``): runs of columns each of whose
    structure is the previous one's without its first row below the diagonal."""
    n = indptr.size - 1
    starts = np.empty(n + 1, dtype=np.int64)
    m = 0
    for j in range(n):
        same = False
        if j > 0:
            p0, p1 = indptr[j - 1], indptr[j]
            if p1 - p0 >= 2 and indices[p0 + 1] == j and indptr[j + 1] - p1 == p1 - p0 - 1:
                same = True
                for t in range(p1 - p0 - 1):
                    if indices[p0 + 1 + t] != indices[p1 + t]:
                        same = False
                        break
        if not same:
            starts[m] = j
            m += 1
    starts[m] = n
    return starts[:m + 1].copy()


@numba.njit(cache=True, nogil=True)
def _takahashi_supernodal(indptr: np.ndarray, indices: np.ndarray, lval: np.ndarray, z: np.ndarray,
                          starts: np.ndarray) -> bool:  # pragma: no cover - numba
    """:func:`_takahashi` a supernode at a time, in dense blocks (BLAS for the products).

    For a supernode of columns ``J`` with rows ``U`` below it, ``T = L_UJ L_JJ^-1`` and::

        Z_UJ = -Z_UU T
        Z_JJ = L_JJ^-T L_JJ^-1 - T^T Z_UJ

    ``Z_UU`` is gathered from the columns of ``U`` (later supernodes, already done); a row of ``U``
    missing from one of them makes it return False, as :func:`_takahashi`. About twice the
    scalar recursion's multiply-adds, at BLAS speed: on the corridor's G/I factor (24,009
    unknowns, 1.2 M non-zeros in ``L``, 1,610 supernodes of 15 columns on average) 94 ms -> 18 ms.
    Single columns, and supernodes with more than :data:`DENSE_ROWS_MAX` rows below, go column by
    column (:func:`_takahashi_column`).
    """
    n_super = starts.size - 1
    scratch = np.zeros(indptr.size - 1)
    for sn in range(n_super - 1, -1, -1):
        j0 = starts[sn]
        j1 = starts[sn + 1]
        s = j1 - j0
        last = indptr[j1 - 1]
        u = indptr[j1] - last - 1
        if u > DENSE_ROWS_MAX or s == 1:
            for j in range(j1 - 1, j0 - 1, -1):
                if not _takahashi_column(j, indptr, indices, lval, z, scratch):
                    return False
            continue
        U = indices[last + 1:indptr[j1]]
        LJJ = np.zeros((s, s))
        LUJ = np.empty((u, s))
        for t in range(s):
            p = indptr[j0 + t]
            for r in range(s - t):
                LJJ[t + r, t] = lval[p + r]
            for r in range(u):
                LUJ[r, t] = lval[p + s - t + r]
        # Linv = L_JJ^-1 (lower), column by column by forward substitution.
        Linv = np.zeros((s, s))
        for c in range(s):
            Linv[c, c] = 1.0 / LJJ[c, c]
            for r in range(c + 1, s):
                acc = 0.0
                for k in range(c, r):
                    acc += LJJ[r, k] * Linv[k, c]
                Linv[r, c] = -acc / LJJ[r, r]
        ZJJ = Linv.T @ Linv
        if u > 0:
            ZUU = np.empty((u, u))
            for bi in range(u):
                b = U[bi]
                q = indptr[b]
                q1 = indptr[b + 1]
                ZUU[bi, bi] = z[q]
                q += 1
                for ai in range(bi + 1, u):
                    a = U[ai]
                    while q < q1 and indices[q] < a:
                        q += 1
                    if q == q1 or indices[q] != a:
                        return False
                    ZUU[ai, bi] = z[q]
                    ZUU[bi, ai] = z[q]
            T = LUJ @ Linv
            ZUJ = -(ZUU @ T)
            ZJJ -= T.T @ ZUJ
            for t in range(s):
                p = indptr[j0 + t] + s - t
                for r in range(u):
                    z[p + r] = ZUJ[r, t]
        for t in range(s):
            p = indptr[j0 + t]
            for r in range(s - t):
                z[p + r] = ZJJ[t + r, t]
    return True


@numba.njit(cache=True, nogil=True)
def _lookup(indptr: np.ndarray, indices: np.ndarray, z: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``Z[rows[k], cols[k]]`` (permuted indices, ``rows >= cols``) by bisection; NaN when off the pattern."""
    out = np.empty(rows.size)
    for k in range(rows.size):
        r = rows[k]
        c = cols[k]
        lo = indptr[c] + np.searchsorted(indices[indptr[c]:indptr[c + 1]], r)
        out[k] = z[lo] if lo < indptr[c + 1] and indices[lo] == r else np.nan
    return out


@dataclass(frozen=True)
class SelectedInverse:
    """``A^-1`` on the pattern of ``L`` (``P A P^T = L L^T``; row ``k`` of ``L`` is row ``perm[k]`` of ``A``)."""

    L: sp.csc_matrix
    perm: np.ndarray
    z: np.ndarray  # values of Z on L's pattern (L.indptr, L.indices)

    @property
    def n(self) -> int:
        return self.L.shape[0]

    def blocks(self, col_start: np.ndarray, dim: int, diagonal: bool = False) -> np.ndarray:
        """Diagonal ``dim x dim`` blocks of ``A^-1`` (as :func:`~georefine.adjustment.linalg.marginal_covariance_blocks`).

        Entries off the factor's pattern (two unknowns of one element that nothing couples)
        are solved for: ``(A^-1)_ij = x_i . x_j`` with ``x = L^-1 P e``. With ``diagonal`` only
        the variances are read (always on the pattern) and the blocks are diagonal: the
        solves cost seconds when many elements have uncoupled axes.
        """
        col_start = np.asarray(col_start, dtype=np.int64).reshape(-1)
        out = np.zeros((col_start.size, dim, dim))
        free = np.flatnonzero(col_start >= 0)
        if free.size == 0 or dim == 0:
            return out
        inv_perm = np.empty(self.n, dtype=np.int64)
        inv_perm[self.perm] = np.arange(self.n)
        a, b = (np.arange(dim), np.arange(dim)) if diagonal else np.tril_indices(dim)
        q = inv_perm[col_start[free][:, None] + np.arange(dim)]  # (K, dim) permuted columns
        qa, qb = q[:, a], q[:, b]
        values = _lookup(self.L.indptr, self.L.indices, self.z, np.maximum(qa, qb).ravel(),
                         np.minimum(qa, qb).ravel()).reshape(qa.shape)
        missing = np.flatnonzero(np.isnan(values).any(axis=1))
        if missing.size:
            values[missing] = self._solved(q[missing], a, b)
        blocks = np.zeros((free.size, dim, dim))
        blocks[:, a, b] = values
        blocks[:, b, a] = values
        out[free] = blocks
        return out

    def _solved(self, q: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Lower-triangle entries of the blocks of permuted columns ``q`` (K, dim) by triangular solves."""
        log.debug("selected inverse: %d element(s) off the factor's pattern, solved for", q.shape[0])
        cols = q.ravel()
        E = np.zeros((self.n, cols.size))
        E[cols, np.arange(cols.size)] = 1.0
        X = spsolve_triangular(self.L.tocsr(), E, lower=True).reshape(self.n, q.shape[0], q.shape[1])
        return np.einsum("nka,nkb->kab", X, X)[:, a, b]


def selected_inverse(
    A: sp.spmatrix | sp.sparray, *, backend: str = "auto", solver: SparseCholesky | None = None,
    always: bool = False, columns: int = EXPECTED_COLUMNS, lower: bool = False,
) -> tuple[SelectedInverse | None, Factorization | None]:
    """Factorise the symmetric positive definite ``A`` and invert it on the factor's pattern.

    Returns ``(inverse, None)``; or ``(None, factor)`` when solving for ``columns`` unit columns
    with ``factor`` is the cheaper (:func:`_recursion_pays`) and ``always`` is not set, or when
    the backend gives no access to its factor (cholespy, SciPy). Per backend:

    * QDLDL (``factors()``, a copy of ``L`` and ``D``): always the recursion. Its solves take one
      right-hand side at a time, without BLAS; on the corridor's G/I normal matrix the recursion
      took 0.12 s where 1,100 unit-column solves took 1.5 s with cholespy.
    * scikit-sparse's CHOLMOD: the probe of :func:`_probe_solves` first, then ``Factor.L()``.
    * CVXOPT: the same probe, timed on its sparse forward substitutions (what the covariance
      blocks would use); ``cholmod.getfactor`` turns the factorisation symbolic, so where the
      recursion then does not pay the matrix is factorised again for the solves.

    ``backend`` as :func:`~georefine.adjustment.linalg.cholesky`. ``solver``: a
    :class:`~georefine.adjustment.linalg.SparseCholesky` whose symbolic analysis may fit ``A``
    (that of the adjustment's iterations); it is reused when it does. ``always``: invert even
    where solving would be cheaper. ``columns``: how many unit columns the caller would solve for.
    ``lower``: ``A`` is the lower triangle with the diagonal (as the adjustment's damped
    matrices, so that their analysis fits).

    Raises
    ------
    NotPositiveDefiniteError
        As the factorisation.
    """
    solver = solver if solver is not None else SparseCholesky(backend)
    A = sp.csr_matrix(A)
    t = time.perf_counter()
    # The singularity test comes below: from the diagonal of L where L is copied out anyway,
    # else by a solve (with scikit-sparse the pivot test copies the whole factor, 9.1 s for a
    # 60-minute G/I/L matrix, and the solves' path would not use the copy).
    factor = solver.factorize(A, lower=lower, check_pivots=False)
    return invert_factor(A, factor, solver, always=always, columns=columns, lower=lower,
                         factor_s=time.perf_counter() - t)


def invert_factor(
    A: sp.spmatrix | sp.sparray, factor: Factorization, solver: SparseCholesky, *, always: bool = False,
    columns: int = EXPECTED_COLUMNS, lower: bool = False, factor_s: float | None = None,
) -> tuple[SelectedInverse | None, Factorization | None]:
    """:func:`selected_inverse` from a factorisation of ``A`` already made by ``solver`` (the same
    choice between the recursion and unit-column solves, the same results).

    ``factor_s``: the factorisation's seconds, where known (scikit-sparse's early choice of the
    solves weighs them against it; unknown, the choice goes on to the recursion's work).
    """
    A = sp.csr_matrix(A)

    def solving(f: Factorization = factor) -> tuple[None, Factorization]:
        check_by_solve(f, lambda v: symmetric_matvec(A, v) if lower else A @ v)
        return None, f

    if factor.backend not in ("cholmod", "cvxopt", "qdldl"):
        return solving()
    solve_s = None
    if factor.backend != "qdldl" and not always:
        solve_s = _probe_solves(factor, columns)
        # With scikit-sparse, before the factor is copied out (a G/I/L factor at 60 minutes of
        # flight is GBs): when all the solves cost less than a few factorisations, the scalar
        # recursion cannot win. CVXOPT's probe (a batch of sparse substitutions) underrates what
        # the covariance blocks then cost (0.86 s against 0.22 s predicted on the corridor's G/I),
        # so there the recursion's work decides, from the factor.
        if factor.backend == "cholmod" and factor_s is not None and solve_s < MIN_SOLVES_PER_FACTORISATION * factor_s:
            log.debug("selected inverse: %d unit-column solves ~%.1f s, factorisation %.1f s: solving",
                      columns, solve_s, factor_s)
            return solving()
    L, perm = factor.factor()  # with CVXOPT this leaves the factor symbolic
    check_pivot_ratios(L.diagonal(), A.diagonal()[perm], factor.n)
    if solve_s is not None and not _recursion_pays(factor, _work(L), solve_s, columns):
        if factor.backend == "cvxopt":  # its numeric factor is gone: analyse and factorise again for the solves
            solver.forget()
            return solving(solver.factorize(A, lower=lower, check_pivots=False))
        return solving()
    if factor.backend == "cvxopt":
        solver.forget()  # the factor handed out is symbolic now
    L.sort_indices()
    if L.nnz and np.any(L.indices[L.indptr[:-1]] != np.arange(L.shape[0])):
        raise NotPositiveDefiniteError("selected inverse: the factor has a column without its diagonal entry")
    L.data = np.ascontiguousarray(L.data, dtype=np.float64)
    z = np.empty_like(L.data)
    t = time.perf_counter()
    if not _takahashi_supernodal(L.indptr, L.indices, L.data, z, _supernodes(L.indptr, L.indices)):
        raise RuntimeError("selected inverse: the factor's pattern is not closed under elimination")
    log.debug("selected inverse: %s factor of %d unknowns, %d non-zeros, recursion %.2f s",
              factor.backend, factor.n, L.nnz, time.perf_counter() - t)
    return SelectedInverse(L, perm, z), None


def _work(L: sp.csc_matrix) -> float:
    """``sum_j |S_j|^2``: the recursion's multiply-adds."""
    counts = np.diff(L.indptr).astype(np.float64) - 1.0
    return float(counts @ counts)
