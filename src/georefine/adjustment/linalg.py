"""Sparse Cholesky factorisation of symmetric positive definite normal matrices.

Four backends, chosen by :func:`cholesky` (``backend="auto"`` takes the first available):

``"cholmod"``
    scikit-sparse (``sksparse.cholmod``), optional extra ``georefine[cholmod]``; it compiles
    against the system's SuiteSparse 5 (Debian's ``libsuitesparse-dev``).
    CHOLMOD with its default ordering strategy (AMD, METIS/NESDIS when AMD fills badly) and
    automatic simplicial/supernodal choice. Reads the lower triangle of a CSC matrix.
``"cvxopt"``
    CVXOPT's CHOLMOD interface (``cvxopt.cholmod``), optional extra ``georefine[fast]``: a plain
    wheel that bundles SuiteSparse and OpenBLAS, so it needs no system libraries. Supernodal
    ``LL^T`` like scikit-sparse and as fast (measured on a G/I/L normal matrix of 52,764 unknowns
    and 3.5 M non-zeros: 0.31 s numeric factorisation, against 2.6 s for cholespy's simplicial
    one). The lower triangle in CSR is handed over, without conversion, as the *upper* triangle
    in CSC (``uplo="U"``); the permutation for the pivot check comes from ``solve(sys=7)``
    (``x = P b``). CVXOPT is GPL-3 (as is CHOLMOD's supernodal module, which scikit-sparse uses
    too); it is an optional dependency, never required.
``"qdldl"``
    QDLDL (``qdldl.Solver``, OSQP's ``LDL^T`` with AMD ordering, Apache-2.0), a default installed
    dependency: a plain wheel, and the one default backend that hands out its factor
    (``factors()``: ``L``, ``D`` and the permutation), which the posterior's selected inversion
    needs (:mod:`georefine.adjustment.selected_inverse`). Simplicial and up-looking; the
    numeric refactorisation of one pattern (``update``) keeps the ordering and the elimination
    tree. Measured on the corridor's G/I normal matrix (24,009 unknowns, 1.1 M non-zeros in
    ``L``): 65 ms analysis and factorisation, 29 ms refactorisation, against cholespy's 93 ms
    for every factorisation, scikit-sparse's 41 ms and CVXOPT's 21 ms refactorisations. The
    upper triangle in CSC is the lower one in CSR: handed over without conversion
    (``upper=True``). Right-hand sides one vector at a time. It factorises quasi-definite
    matrices without complaint, so positive definiteness is tested on ``D``.
``"cholespy"``
    cholespy (``cholespy.CholeskySolverD``), a default installed dependency. It wraps
    CHOLMOD too: the matrix is copied into a CHOLMOD matrix with ``stype = -1``, i.e. **only
    the lower triangle (row >= column) is read and the strictly upper part is silently
    ignored** -- passing only the upper triangle gives a wrong factor without any error. The
    fill-reducing ordering is chosen inside CHOLMOD (the cholespy source selects nested
    dissection, METIS-based, which is compiled in); the installed 2.2.0 factorises simplicial
    ``LL^T`` (its errors come from CHOLMOD's row-oriented simplicial code). The symbolic
    analysis is redone on every construction. COO and CSR input is copied and converted to CSC
    (duplicates summed); CSC input is used in place (sorted and ``realloc``-ed in the caller's
    buffers, per the source), so we always hand over CSR of the lower triangle with freshly
    allocated ``int32`` index arrays. Indices are 32-bit: matrices with more than 2^31 - 1
    stored entries go to another backend. A matrix that is not positive definite raises
    ``ValueError("Matrix is not positive definite!")`` (CHOLMOD also writes a warning to
    stderr). ``solve(b, x)`` takes C-contiguous float64 ``b`` of shape ``(n,)`` or ``(n, k)``
    and writes the solution into ``x`` of the same shape (no implicit conversion). Measured:
    the cost per right-hand side is flat beyond about 4 columns (~10 ms per column for 300k
    unknowns and 13.5M non-zeros in ``N``), so batching bounds memory but does not make many
    columns cheaper.
``"scipy"``
    Last resort without CHOLMOD: SuperLU (``scipy.sparse.linalg.splu``) in symmetric mode
    (minimum degree on ``A^T + A``, diagonal pivoting), positive definiteness checked from the
    pivots. Several times slower and more memory-hungry on large systems.

All backends return a :class:`Factorization` with ``solve(B)`` for one ``(n,)`` or many
``(n, k)`` right-hand sides.

:class:`SparseCholesky` factorises a sequence of matrices of one sparsity pattern (the
iterations of Levenberg-Marquardt) and reuses the symbolic analysis (ordering, elimination tree,
supernodes) where the backend allows it (``"cholmod"``, ``"cvxopt"``): on the G/I/L matrix above
the analysis is a quarter of a factorisation.
"""

from __future__ import annotations

import abc
import importlib.util
import logging
from dataclasses import dataclass
from typing import Any, Protocol

import numba
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from georefine.adjustment.assembly import lower_triangle
from georefine.errors import GeorefineError

__all__ = [
    "Factorization",
    "NotPositiveDefiniteError",
    "available_backends",
    "cholesky",
    "SparseCholesky",
    "marginal_covariance_blocks",
    "check_by_solve",
    "symmetric_matvec",
    "check_pivot_ratios",
]

logger = logging.getLogger(__name__)

_BACKEND_ORDER = ("cholmod", "cvxopt", "qdldl", "cholespy", "scipy")
_INT32_MAX = np.iinfo(np.int32).max


class NotPositiveDefiniteError(GeorefineError, np.linalg.LinAlgError):
    """The matrix to factorise is not (numerically) positive definite.

    In an adjustment this means a rank-deficient normal matrix: an undetermined datum
    (gauge), parameters without observations, or observations that cannot separate them.
    """


class Factorization(Protocol):
    """Cholesky factor of an ``n x n`` symmetric positive definite matrix ``A``.

    The backends that hand out their factor (``backend`` ``"cholmod"``, ``"cvxopt"``,
    ``"qdldl"``) also have ``factor()``: ``(L, perm)``, ``L`` the lower triangular factor in CSC
    and ``perm`` the pivot order with ``A[perm][:, perm] = L L^T`` (what the selected inversion
    of :mod:`georefine.adjustment.selected_inverse` works on). With CVXOPT it leaves the
    factorisation symbolic (``cholmod.getfactor``): ``solve`` no longer works afterwards.
    """

    backend: str
    n: int

    def solve(self, B: np.ndarray) -> np.ndarray:
        """Return ``A^-1 B`` for ``B`` of shape ``(n,)`` or ``(n, k)``."""
        ...


def available_backends() -> tuple[str, ...]:
    """Backends importable in this environment, in the order ``backend="auto"`` tries them."""
    found = []
    if importlib.util.find_spec("sksparse") is not None:
        found.append("cholmod")
    if importlib.util.find_spec("cvxopt") is not None:
        found.append("cvxopt")
    if importlib.util.find_spec("qdldl") is not None:
        found.append("qdldl")
    if importlib.util.find_spec("cholespy") is not None:
        found.append("cholespy")
    found.append("scipy")
    return tuple(found)


def cholesky(A: sp.spmatrix | sp.sparray, *, lower: bool = False, backend: str = "auto") -> Factorization:
    """Factorise a sparse symmetric positive definite matrix.

    Parameters
    ----------
    A
        ``(n, n)`` sparse matrix. With ``lower=False`` the full symmetric matrix; with
        ``lower=True`` only its lower triangle including the diagonal (entries above the
        diagonal must be absent; this halves the memory handed to CHOLMOD).
    lower
        Whether ``A`` holds only the lower triangle.
    backend
        ``"auto"``, ``"cholmod"``, ``"cvxopt"``, ``"qdldl"``, ``"cholespy"`` or ``"scipy"`` (see
        the module docstring).

    Returns
    -------
    Factorization
        Object with ``solve(B)``.

    Raises
    ------
    NotPositiveDefiniteError
        When the matrix is not positive definite.
    ValueError
        For an unknown or unavailable backend, or a non-square matrix.
    """
    return SparseCholesky(backend).factorize(A, lower=lower)


class SparseCholesky:
    """Factorise matrices of one sparsity pattern, reusing the symbolic analysis.

    ``factorize(A)`` analyses the pattern on the first call (and whenever the pattern changes)
    and then only refactorises numerically, for the backends that separate the two
    (``"cholmod"``, ``"cvxopt"``, ``"qdldl"``); cholespy and SuperLU always start afresh. A
    factorisation returned by the ``"cvxopt"`` or ``"qdldl"`` backend shares its numeric storage
    with this object: it is valid until the next ``factorize`` call (the Levenberg-Marquardt
    loop solves once per factorisation); the other backends return independent objects.

    Parameters
    ----------
    backend
        ``"auto"``, ``"cholmod"``, ``"cvxopt"``, ``"qdldl"``, ``"cholespy"`` or ``"scipy"``.
    """

    def __init__(self, backend: str = "auto") -> None:
        available = available_backends()
        if backend != "auto":
            if backend not in _BACKEND_ORDER:
                raise ValueError(
                    f"unknown linear-algebra backend {backend!r} (expected auto, {', '.join(_BACKEND_ORDER)})"
                )
            if backend not in available:
                raise ValueError(
                    f"linear-algebra backend {backend!r} is not installed (available: {', '.join(available)})"
                )
        self.requested = backend
        self._available = available
        self._pattern: tuple[np.ndarray, np.ndarray] | None = None
        self._symbolic: Any = None
        self.analyses = 0  # symbolic analyses done (for tests and diagnostics)

    def _choose(self, nnz: int) -> str:
        if self.requested != "auto":
            return self.requested
        candidates = list(self._available)
        if nnz > _INT32_MAX and "cholespy" in candidates:
            candidates.remove("cholespy")
        return candidates[0]

    def forget(self) -> None:
        """Drop the symbolic analysis (the next :meth:`factorize` analyses afresh)."""
        self._symbolic = None
        self._pattern = None

    def factorize(self, A: sp.spmatrix | sp.sparray, *, lower: bool = False, check_pivots: bool = True
                  ) -> Factorization:
        """Factorise ``A`` (full symmetric, or only its lower triangle with ``lower=True``).

        ``check_pivots=False`` skips the test for numerically singular matrices (tiny positive
        pivots, which CHOLMOD's supernodal factorisation accepts) where the caller knows it
        cannot fire: Levenberg-Marquardt's ``N + lambda diag(N)`` with ``N`` positive
        semi-definite has every pivot at least ``lambda diag(N)_j`` (Schur complements are
        monotone), far above the test's ``1e-13 A_jj`` for ``lambda >= 1e-10``. With
        scikit-sparse the test reads the diagonal of ``L`` through ``Factor.L()``, a copy of the
        whole factor: 9.1 s on top of a 12.9 s factorisation of a 60-minute G/I/L matrix
        (264 M non-zeros in ``L``). Matrices that are not positive definite still raise, except
        with QDLDL, whose ``D`` is read only for the test (its ``factors()`` copies ``L``); its
        factor raises when ``L`` is read (``factor()``, the selected inverse).

        Raises
        ------
        NotPositiveDefiniteError
            When the matrix is not (numerically) positive definite.
        """
        if A.shape[0] != A.shape[1]:
            raise ValueError(f"cholesky: matrix must be square, found shape {A.shape}")
        n = A.shape[0]
        A_lower = sp.csr_matrix(A, copy=True) if lower else lower_triangle(A)
        A_lower.sum_duplicates()  # also sorts the column indices of every row
        backend = self._choose(A_lower.nnz)
        if n == 0:
            return _EmptyFactorization(backend=backend, n=0)
        if backend == "cholespy":
            return _cholespy(A_lower, n)
        if backend == "scipy":
            return _superlu(A_lower, n)
        same = (
            self._symbolic is not None
            and self._symbolic[0] == backend
            and self._pattern is not None
            and np.array_equal(self._pattern[0], A_lower.indptr)
            and np.array_equal(self._pattern[1], A_lower.indices)
        )
        if not same:
            self._symbolic = None
            analyse = {"cholmod": _cholmod_analyse, "cvxopt": _cvxopt_analyse, "qdldl": _qdldl_analyse}[backend]
            self._symbolic = (backend, analyse(A_lower, n))
            self._pattern = (A_lower.indptr.copy(), A_lower.indices.copy())
            self.analyses += 1
        numeric = {"cholmod": _cholmod_numeric, "cvxopt": _cvxopt_numeric, "qdldl": _qdldl_numeric}[backend]
        try:
            return numeric(self._symbolic[1], A_lower, n, check_pivots)
        except NotPositiveDefiniteError:
            self._symbolic = None  # a failed numeric factorisation may leave the factor unusable
            raise


@dataclass
class _BaseFactorization(abc.ABC):
    """``solve(B)`` for every backend: checks the right-hand side, then ``_solve`` (non-empty ``B``)."""

    backend: str
    n: int

    def solve(self, B: np.ndarray) -> np.ndarray:
        b = np.ascontiguousarray(B, dtype=np.float64)
        if b.shape[0] != self.n or b.ndim not in (1, 2):
            raise ValueError(f"solve: right-hand side must have shape ({self.n},) or ({self.n}, k), found {b.shape}")
        if b.size == 0:
            return b.copy()
        return self._solve(b)

    @abc.abstractmethod
    def _solve(self, b: np.ndarray) -> np.ndarray:
        """``A^-1 b`` for a checked, non-empty ``b`` of shape ``(n,)`` or ``(n, k)`` (each backend)."""


@dataclass
class _EmptyFactorization(_BaseFactorization):
    def _solve(self, b: np.ndarray) -> np.ndarray:  # n = 0: every right-hand side is empty
        return b.copy()


@dataclass
class _CholespyFactorization(_BaseFactorization):
    _solver: Any

    def _solve(self, b: np.ndarray) -> np.ndarray:
        x = np.empty_like(b)
        self._solver.solve(b, x)
        return x


def _cholespy(A_lower: sp.csr_matrix, n: int) -> Factorization:
    import cholespy

    if A_lower.nnz > _INT32_MAX:
        raise ValueError("cholespy backend: more than 2^31 - 1 stored entries; use backend 'cholmod' or 'scipy'")
    A_lower.sum_duplicates()
    indptr = np.array(A_lower.indptr, dtype=np.int32)  # fresh copies: the extension may sort in place
    indices = np.array(A_lower.indices, dtype=np.int32)
    data = np.array(A_lower.data, dtype=np.float64)
    try:
        solver = cholespy.CholeskySolverD(n, indptr, indices, data, cholespy.MatrixType.CSR)
    except ValueError as exc:
        if "positive definite" in str(exc):
            raise NotPositiveDefiniteError(f"normal matrix ({n} unknowns) is not positive definite") from exc
        raise
    factor = _CholespyFactorization(backend="cholespy", n=n, _solver=solver)
    # cholespy does not expose the factor's pivots: the singularity shows in the solve instead.
    check_by_solve(factor, lambda v: symmetric_matvec(A_lower, v))
    return factor


def symmetric_matvec(A_lower: sp.spmatrix | sp.sparray, v: np.ndarray) -> np.ndarray:
    """``A v`` for the symmetric ``A`` given by its lower triangle with the diagonal."""
    return A_lower @ v + A_lower.T @ v - A_lower.diagonal() * v


def check_by_solve(factor: Factorization, matvec) -> None:
    """Raise :class:`NotPositiveDefiniteError` when ``factor`` is of a numerically singular matrix.

    Tiny positive pivots from rounding show in the solve: ``A x = A v`` does not give back
    ``v`` (relative error above 1e-2). ``matvec(v)``: ``A v``. For factors whose pivots are
    not at hand, or only through a copy of the whole factor.
    """
    n = factor.n
    v = np.random.default_rng(0).uniform(1.0, 2.0, n)
    err = np.linalg.norm(factor.solve(matvec(v)) - v) / np.linalg.norm(v)
    if not err < _SINGULAR_SOLVE_ERROR:
        raise NotPositiveDefiniteError(f"normal matrix ({n} unknowns) is numerically singular")


_SINGULAR_PIVOT = 1e-13
# Relative solve error that flags a singular matrix (cholespy): a condition number of about
# 1 / _SINGULAR_PIVOT loses about 1e13 * eps ~ 1e-3 in the solve.
_SINGULAR_SOLVE_ERROR = 1e-2


@dataclass
class _CholmodFactorization(_BaseFactorization):
    _factor: Any

    def _solve(self, b: np.ndarray) -> np.ndarray:
        return np.asarray(self._factor(b), dtype=np.float64).reshape(b.shape)

    def solve_half(self, B: np.ndarray) -> np.ndarray:
        """``L^-1 P B`` (with ``P A P^T = L L^T``): ``A^-1 = (L^-1 P)^T (L^-1 P)``, half the work of a solve."""
        from sksparse import cholmod

        f = self._factor
        try:
            return np.asarray(f.solve_L(f.apply_P(B), use_LDLt_decomposition=False), dtype=np.float64)
        except cholmod.CholmodError as exc:  # a factor CHOLMOD marked as not positive definite
            raise NotPositiveDefiniteError(f"normal matrix ({self.n} unknowns) is not positive definite") from exc

    def factor(self) -> tuple[sp.csc_matrix, np.ndarray]:
        """``(L, perm)`` with ``A[perm][:, perm] = L L^T``: ``Factor.L()``, a copy of the factor in
        ``LL^T`` form (converted from the supernodal one), and ``Factor.P()``."""
        from sksparse import cholmod

        try:
            L = sp.csc_matrix(self._factor.L())
        except cholmod.CholmodError as exc:  # a factor CHOLMOD itself marks as not positive definite
            raise NotPositiveDefiniteError(f"normal matrix ({self.n} unknowns) is not positive definite") from exc
        return L, np.asarray(self._factor.P(), dtype=np.int64)


def _cholmod_analyse(A_lower: sp.csr_matrix, n: int) -> Any:
    from sksparse import cholmod

    return cholmod.analyze(sp.csc_matrix(A_lower), mode="auto")


def _cholmod_numeric(symbolic: Any, A_lower: sp.csr_matrix, n: int, check_pivots: bool = True) -> Factorization:
    from sksparse import cholmod

    not_pd = getattr(cholmod, "CholmodNotPositiveDefiniteError", cholmod.CholmodError)
    A_csc = sp.csc_matrix(A_lower)
    try:
        factor = symbolic.cholesky(A_csc, beta=0)  # a new factor; the analysis is kept
        L_diag = factor.L().diagonal() if check_pivots else None  # L(): a copy of the whole factor
    except not_pd as exc:
        raise NotPositiveDefiniteError(f"normal matrix ({n} unknowns) is not positive definite") from exc
    if L_diag is not None:
        check_pivot_ratios(L_diag, A_csc.diagonal()[factor.P()], n)
    return _CholmodFactorization(backend="cholmod", n=n, _factor=factor)


def check_pivot_ratios(L_diag: np.ndarray, A_diag_permuted: np.ndarray, n: int) -> None:
    """Raise :class:`NotPositiveDefiniteError` for a pivot ``L_jj^2`` below ``1e-13`` of its diagonal entry."""
    # The supernodal factorisation accepts a singular matrix whose rounding leaves tiny positive
    # pivots (a missing datum, say); the simplicial one and cholespy reject it. Make the
    # backends agree: a pivot below 1e-13 of its diagonal entry is numerically singular.
    d = L_diag**2
    if np.any(d <= _SINGULAR_PIVOT * np.maximum(A_diag_permuted, np.finfo(float).tiny)):
        raise NotPositiveDefiniteError(f"normal matrix ({n} unknowns) is numerically singular")


@dataclass
class _CvxoptSymbolic:
    matrix: Any  # cvxopt.spmatrix holding the lower triangle
    order: np.ndarray  # CVXOPT's column-major value order as indices into our CSR data
    factor: Any  # cvxopt CHOLMOD factor (symbolic, then numeric in place)


_LONG_COLUMN = 1000
"""Columns of the lower triangle with more entries than this count as long for CVXOPT's triplet
constructor (:func:`_cvxopt_spmatrix`)."""

_LONG_COLUMN_COST = 256
"""The long columns are built apart when the sum of their squared lengths exceeds this many times
the matrix's entries: CVXOPT's constructor takes about 4e-10 s per squared entry of a column
(measured: 12 columns of 40,000 entries 7.4 s, of 20,000 1.7 s), the sum that joins the two parts
about 1e-7 s per entry."""


def _cvxopt_spmatrix(A_lower: sp.csr_matrix, rows: np.ndarray, order: np.ndarray, n: int) -> Any:
    """CVXOPT's ``spmatrix`` of ``A_lower`` (CSR; ``rows`` every entry's row, ``order`` the entries
    in column-major order).

    CVXOPT's triplet constructor takes time quadratic in the length of a column: the strip
    adjustment's normal matrix of a 30-minute corridor (80,103 unknowns, its 12 strip columns
    beside every one of 26,645 objects) took 41.7 s to convert and 0.05 s to analyse. Where
    long columns make that cost (:data:`_LONG_COLUMN`, :data:`_LONG_COLUMN_COST`), they are
    built transposed, as short columns, transposed back (linear) and added to the rest; the
    pattern is built with ones (the parts are disjoint, so no entry cancels or vanishes) and the
    values set column-major after. Triplets of the rest in row-major order: ten times faster than
    column-major (measured; the same arrays as the upper triangle's column-major triplets took 15
    times longer)."""
    from cvxopt import matrix, spmatrix

    cols = A_lower.indices.astype(np.int64)
    counts = np.bincount(A_lower.indices, minlength=n)
    long_cols = counts > _LONG_COLUMN
    if float(np.sum(counts[long_cols].astype(np.float64) ** 2)) <= _LONG_COLUMN_COST * A_lower.nnz:
        return spmatrix(matrix(A_lower.data), matrix(rows), matrix(cols), (n, n))
    in_long = long_cols[A_lower.indices]
    rest, far = ~in_long, in_long
    ones = matrix(1.0, (int(np.count_nonzero(rest)), 1))
    M = spmatrix(ones, matrix(rows[rest]), matrix(cols[rest]), (n, n))
    ones = matrix(1.0, (int(np.count_nonzero(far)), 1))
    M = M + spmatrix(ones, matrix(cols[far]), matrix(rows[far]), (n, n)).T
    M.V = matrix(A_lower.data[order])
    return M


def _cvxopt_analyse(A_lower: sp.csr_matrix, n: int) -> _CvxoptSymbolic:
    from cvxopt import cholmod

    rows, order = _rows_and_csc_order(A_lower.indptr.astype(np.int64, copy=False), A_lower.indices, n)
    # CVXOPT stores the values column-major, hence the gather order for later value updates.
    M = _cvxopt_spmatrix(A_lower, rows, order, n)
    del rows
    if order.size <= _INT32_MAX:  # kept for every refactorisation: half the memory of int64
        order = order.astype(np.int32)
    return _CvxoptSymbolic(M, order, cholmod.symbolic(M, uplo="L"))


@numba.njit(cache=True, nogil=True)
def _rows_and_csc_order(indptr, indices, n):  # pragma: no cover - numba
    """The row of every CSR entry, and the entries in column-major order (a counting sort: on the
    corridor's G/I/L matrix 0.07 s where np.repeat and np.lexsort took 0.5 s)."""
    rows = np.empty(indices.size, dtype=np.int64)
    start = np.zeros(n + 1, dtype=np.int64)
    for q in range(indices.size):
        start[indices[q] + 1] += 1
    for j in range(n):
        start[j + 1] += start[j]
    order = np.empty(indices.size, dtype=np.int64)
    for i in range(n):
        for q in range(indptr[i], indptr[i + 1]):
            rows[q] = i
            j = indices[q]
            order[start[j]] = q
            start[j] += 1
    return rows, order


@dataclass
class _CvxoptFactorization(_BaseFactorization):
    _factor: Any

    def _solve(self, b: np.ndarray) -> np.ndarray:
        from cvxopt import cholmod, matrix

        x = matrix(np.asfortranarray(b.reshape(self.n, -1)))
        cholmod.solve(self._factor, x)
        return np.array(x).reshape(b.shape)

    def solve_unit_columns_half(self, cols: np.ndarray) -> sp.csc_matrix:
        """``L^-1 P E`` for the unit vectors ``E`` of ``cols`` (sparse, with ``P A P^T = L L^T``).

        ``(A^-1)_{ij} = x_i . x_j`` for the returned columns ``x``: covariance blocks from one
        sparse triangular solve, which touches only the elimination-tree paths of the columns.
        """
        from cvxopt import cholmod, spmatrix

        k = cols.size
        E = spmatrix(1.0, cols.astype(np.int64).tolist(), list(range(k)), (self.n, k))
        X = cholmod.spsolve(self._factor, cholmod.spsolve(self._factor, E, sys=7), sys=4)
        colptr, rowind, values = X.CCS
        return sp.csc_matrix(
            (np.array(values).reshape(-1), np.array(rowind).reshape(-1), np.array(colptr).reshape(-1)),
            shape=(self.n, k),
        )

    def factor(self) -> tuple[sp.csc_matrix, np.ndarray]:
        """``(L, perm)`` with ``A[perm][:, perm] = L L^T``: ``perm`` from ``solve(sys=7)``
        (``x = P b``), ``L`` from ``cholmod.getfactor``, which leaves the factorisation symbolic:
        this object solves nothing afterwards (factorise again for solves)."""
        from cvxopt import cholmod, matrix

        p = matrix(np.arange(self.n, dtype=np.float64))
        cholmod.solve(self._factor, p, sys=7)  # x = P b: the pivot order
        perm = np.array(p).reshape(-1).astype(np.int64)
        colptr, rowind, values = cholmod.getfactor(self._factor).CCS
        L = sp.csc_matrix((np.array(values).reshape(-1), np.array(rowind).reshape(-1),
                           np.array(colptr).reshape(-1)), shape=(self.n, self.n))
        return L, perm


def _cvxopt_numeric(symbolic: _CvxoptSymbolic, A_lower: sp.csr_matrix, n: int, check_pivots: bool = True
                    ) -> Factorization:
    from cvxopt import cholmod, matrix

    symbolic.matrix.V = matrix(A_lower.data[symbolic.order])  # same pattern, new values
    try:
        cholmod.numeric(symbolic.matrix, symbolic.factor)
    except ArithmeticError as exc:
        raise NotPositiveDefiniteError(f"normal matrix ({n} unknowns) is not positive definite") from exc
    if check_pivots:  # cholmod.diag is cheap here; skipped for the same reason as with scikit-sparse
        p = matrix(np.arange(n, dtype=np.float64))
        cholmod.solve(symbolic.factor, p, sys=7)  # x = P b: the pivot order
        perm = np.array(p).reshape(-1).astype(np.int64)
        check_pivot_ratios(np.array(cholmod.diag(symbolic.factor)).reshape(-1), A_lower.diagonal()[perm], n)
    return _CvxoptFactorization(backend="cvxopt", n=n, _factor=symbolic.factor)


@dataclass
class _QdldlSymbolic:
    solver: Any  # qdldl.Solver: analysed (AMD, elimination tree) and factorised once
    fresh: bool = True  # its factor is of the matrix it was analysed with


def _upper_csc(A_lower: sp.csr_matrix, n: int) -> sp.csc_matrix:
    """The lower triangle in CSR read as the upper triangle in CSC (same arrays, no conversion)."""
    return sp.csc_matrix((A_lower.data, A_lower.indices, A_lower.indptr), shape=(n, n), copy=False)


def _qdldl_call(call, n: int):
    try:
        return call()
    except (RuntimeError, ValueError) as exc:  # a missing diagonal entry, a zero pivot
        raise NotPositiveDefiniteError(f"normal matrix ({n} unknowns) is not positive definite ({exc})") from exc


def _qdldl_analyse(A_lower: sp.csr_matrix, n: int) -> _QdldlSymbolic:
    import qdldl

    return _QdldlSymbolic(_qdldl_call(lambda: qdldl.Solver(_upper_csc(A_lower, n), upper=True), n))


@dataclass
class _QdldlFactorization(_BaseFactorization):
    _solver: Any

    def _solve(self, b: np.ndarray) -> np.ndarray:
        if b.ndim == 1:
            return np.asarray(self._solver.solve(b), dtype=np.float64)
        return np.column_stack([self._solver.solve(np.ascontiguousarray(b[:, k])) for k in range(b.shape[1])])

    def factor(self) -> tuple[sp.csc_matrix, np.ndarray]:
        """``(L, perm)`` with ``A[perm][:, perm] = L L^T``: QDLDL's ``(I + L) D (I + L)^T`` as ``LL^T``
        (column ``j`` scaled by ``sqrt(D_j)``, the diagonal first in every column, rows sorted)."""
        L, D, P = self._solver.factors()
        D = np.asarray(D, dtype=np.float64)
        if not np.all(D > 0) or not np.all(np.isfinite(D)):
            raise NotPositiveDefiniteError(f"normal matrix ({self.n} unknowns) is not positive definite")
        return ldl_to_cholesky(sp.csc_matrix(L), D), np.asarray(P, dtype=np.int64)


def ldl_to_cholesky(L_strict: sp.csc_matrix, D: np.ndarray) -> sp.csc_matrix:
    """``(I + L) diag(sqrt(D))`` in CSC with the diagonal the first entry of every column, rows sorted."""
    n = L_strict.shape[0]
    L_strict.sort_indices()
    counts = np.diff(L_strict.indptr)
    indptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(counts + 1, out=indptr[1:])
    diag_at = indptr[:-1]
    off = np.ones(indptr[-1], dtype=bool)
    off[diag_at] = False
    indices = np.empty(indptr[-1], dtype=np.int64)
    data = np.empty(indptr[-1], dtype=np.float64)
    root = np.sqrt(D)
    indices[diag_at] = np.arange(n)
    data[diag_at] = root
    indices[off] = L_strict.indices
    data[off] = L_strict.data * np.repeat(root, counts)
    return sp.csc_matrix((data, indices, indptr), shape=(n, n))


def _qdldl_numeric(symbolic: _QdldlSymbolic, A_lower: sp.csr_matrix, n: int, check_pivots: bool = True
                   ) -> Factorization:
    solver = symbolic.solver
    if not symbolic.fresh:  # same pattern, new values: QDLDL keeps its ordering and elimination tree
        _qdldl_call(lambda: solver.update(_upper_csc(A_lower, n), upper=True), n)
    symbolic.fresh = False
    if check_pivots:
        # QDLDL factorises quasi-definite matrices too: a negative D is a matrix that is not
        # positive definite; tiny positive ones are tested as the other backends' pivots. D is
        # only read here, because factors() copies all of L (15 ms of a 23 ms refactorisation of
        # the corridor's G/I): without the test the caller knows every pivot is positive
        # (Levenberg-Marquardt's damping) or tests the factor itself (the selected inverse reads
        # L anyway, and check_by_solve finds a singular matrix).
        _, D, P = solver.factors()
        D = np.asarray(D)
        if not np.all(D > 0) or not np.all(np.isfinite(D)):
            raise NotPositiveDefiniteError(f"normal matrix ({n} unknowns) is not positive definite")
        check_pivot_ratios(np.sqrt(D), A_lower.diagonal()[np.asarray(P)], n)
    return _QdldlFactorization(backend="qdldl", n=n, _solver=solver)


@dataclass
class _SuperLUFactorization(_BaseFactorization):
    _lu: Any

    def _solve(self, b: np.ndarray) -> np.ndarray:
        return self._lu.solve(b)


def _superlu(A_lower: sp.csr_matrix, n: int) -> Factorization:
    diag = sp.diags(A_lower.diagonal())
    A = sp.csc_matrix(A_lower + A_lower.T - diag)
    if np.any(A.diagonal() <= 0):
        raise NotPositiveDefiniteError(f"normal matrix ({n} unknowns) has non-positive diagonal entries")
    try:
        lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    except RuntimeError as exc:  # "Factor is exactly singular"
        raise NotPositiveDefiniteError(f"normal matrix ({n} unknowns) is singular") from exc
    # With symmetric diagonal pivoting the pivots are the D of L D L^T: all positive iff A is SPD.
    pivots = lu.U.diagonal()
    if not np.all(pivots > 0) or not np.all(np.isfinite(pivots)):
        raise NotPositiveDefiniteError(f"normal matrix ({n} unknowns) is not positive definite")
    return _SuperLUFactorization(backend="scipy", n=n, _lu=lu)


def marginal_covariance_blocks(
    factor: Factorization,
    col_start: np.ndarray,
    dim: int,
    *,
    max_rhs: int = 256,
    max_workspace_doubles: int = 32_000_000,
) -> np.ndarray:
    """Diagonal ``dim x dim`` blocks of ``A^-1`` for chosen groups of consecutive columns.

    Solves ``A X = E`` for the unit vectors ``E`` of the requested columns in batches of at
    most ``max_rhs`` columns and at most ``max_workspace_doubles`` entries of ``X``
    (memory-bounded), and keeps only the diagonal blocks. Where the factor offers it (CHOLMOD:
    ``solve_half``; CVXOPT: sparse ``solve_unit_columns_half``) only the forward half
    ``X = L^-1 P E`` is computed, and a block is ``X_i^T X_i``: half the work of the solves.

    Parameters
    ----------
    factor
        Factorisation of ``A`` (``n x n``).
    col_start
        ``(K,)`` int: first column of each requested element; the element owns columns
        ``col_start[k] ... col_start[k] + dim - 1``. Negative entries (constant elements)
        give zero blocks.
    dim
        Tangent dimension of the elements.
    max_rhs, max_workspace_doubles
        Batch limits.

    Returns
    -------
    np.ndarray
        ``(K, dim, dim)`` symmetric blocks.
    """
    col_start = np.asarray(col_start, dtype=np.int64).reshape(-1)
    out = np.zeros((col_start.size, dim, dim))
    free = np.flatnonzero(col_start >= 0)
    n = factor.n
    if free.size == 0 or dim == 0:
        return out
    per_batch = max(1, min(max_rhs // dim, max_workspace_doubles // max(1, n * dim)))
    offsets = np.arange(dim)
    for first in range(0, free.size, per_batch):
        sel = free[first : first + per_batch]
        cols = (col_start[sel][:, None] + offsets).reshape(-1)
        k = sel.size
        half = getattr(factor, "solve_unit_columns_half", None)
        if half is not None:  # sparse triangular solve: (A^-1)_ij = x_i . x_j
            out[sel] = _diagonal_gram_blocks(half(cols), k, dim)
            continue
        elif hasattr(factor, "solve_half"):  # the forward half of each solve: (A^-1)_ij = x_i . x_j
            E = np.zeros((n, cols.size))
            E[cols, np.arange(cols.size)] = 1.0
            X = factor.solve_half(E).reshape(n, k, dim)
            blocks = np.einsum("nka,nkb->kab", X, X)
            out[sel] = 0.5 * (blocks + np.swapaxes(blocks, 1, 2))
            continue
        else:
            E = np.zeros((n, cols.size))
            E[cols, np.arange(cols.size)] = 1.0
            X = factor.solve(E)
            sub = X[cols, :].reshape(k, dim, k, dim)
        blocks = np.einsum("iaib->iab", sub)
        out[sel] = 0.5 * (blocks + np.swapaxes(blocks, 1, 2))
    return out


def _diagonal_gram_blocks(X: sp.csc_matrix, k: int, dim: int) -> np.ndarray:
    """The ``k`` diagonal ``dim x dim`` blocks of ``X^T X`` for ``X`` of ``k * dim`` columns (sparse).

    Column ``a`` of every block at once: ``X[:, a::dim]``; entry ``(a, b)`` of all blocks is the
    column sums of its elementwise product with ``X[:, b::dim]``. The work is ``dim`` times the
    non-zeros of ``X``; the whole ``X^T X`` (as before) cost the square of the non-zeros per row,
    with ``k * dim`` columns sharing the rows near the root of the elimination tree. On the G/I/L
    posterior of ``corridor-tiny`` (batches of 195 columns, 1.6 M non-zeros): 0.02 s per batch
    against 0.22 s, the G/I/L's covariance step 5.4 s against 6.1 s.
    """
    X = X.tocsc()
    per_a = [X[:, a::dim] for a in range(dim)]
    blocks = np.empty((k, dim, dim))
    for a in range(dim):
        for b in range(a, dim):
            v = np.asarray(per_a[a].multiply(per_a[b]).sum(axis=0)).reshape(-1)
            blocks[:, a, b] = v
            blocks[:, b, a] = v
    return blocks
