"""Sparse matrices from dense sub-blocks: the Jacobian's assembly and the normal equations (docs/ARCHITECTURE.md §4.4).

:class:`JacobianAssembler` writes the sub-blocks of all observation groups straight into CSR
arrays (numba loops; no library assembles dense blocks into a merged CSR matrix and keeps its
structure for the next values) and keeps the structure across the iterations of one solve;
:func:`lower_triangle` and :func:`normal_equations` prepare the factorisation
(:mod:`georefine.adjustment.linalg`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse as sp

__all__ = ["BlockTriplets", "JacobianAssembler", "NormalPattern", "assemble_block_coo", "column_squares",
           "lower_triangle", "normal_equations"]

_INT32_MAX = np.iinfo(np.int32).max


@dataclass(frozen=True)
class BlockTriplets:
    """Dense ``m x d`` sub-blocks of a sparse matrix, ``n`` of them.

    Entry ``(k, i, j)`` goes to row ``rows[k, i] + row_offset`` and column ``col_start[k] + j``,
    value ``values[k, i, j] * row_scale[rows[k, i]]`` (``row_scale`` optional, indexed by the
    un-offset row).
    """

    rows: np.ndarray  # (n, m) int
    col_start: np.ndarray  # (n,) int
    values: np.ndarray  # (n, m, d)
    row_offset: int = 0
    row_scale: np.ndarray | None = None


def assemble_block_coo(pieces: list[BlockTriplets], shape: tuple[int, int]) -> sp.csr_matrix:
    """CSR matrix from dense sub-blocks, duplicates summed, columns sorted (one-off use).

    See :class:`JacobianAssembler`, which does the same and keeps the structure for the next
    matrix of the same pattern.
    """
    return JacobianAssembler().assemble(pieces, shape)


class JacobianAssembler:
    """Assembles CSR matrices from dense sub-blocks; reuses the structure while the pattern stays.

    The first call counts the rows (``indptr``), copies every sub-block row to its row's next
    free slots (:func:`_fill_csr`, a numba loop) together with each entry's origin, then sorts
    each row's distinct columns and merges duplicates (:func:`_merge_rows`): a G/I Jacobian holds each
    spline coefficient several times per row, and unsummed they made ``J^T J`` six times
    dearer. What it keeps is the destination of every sub-block entry in the merged matrix.

    Later calls whose pieces have the same shapes, rows, row offsets and first columns (the
    iterations of one Levenberg-Marquardt solve: the observations and the constant elements do
    not change, only the values and robust weights) skip all of that and add each entry to its
    destination (:func:`_scatter_csr`). On the 60-minute G/I adjustment an assembly took
    4.9 s through fill and ``sum_duplicates``, of which the fill 3.2 s into freshly allocated
    memory; the scatter replaces both. 32-bit indices when possible.

    Memory kept: one destination index per sub-block entry (4 bytes, 8 beyond 2**31 entries)
    and references to the pieces' row and column arrays (compared on the next call).
    """

    def __init__(self) -> None:
        self._key: list[tuple] | None = None
        self._shape: tuple[int, int] | None = None
        self._dest: list[np.ndarray] = []
        self._indices: np.ndarray | None = None
        self._indptr: np.ndarray | None = None
        self._normal: NormalPattern | None = None

    def normal_pattern(self, J: sp.csr_matrix) -> "NormalPattern":
        """The :class:`NormalPattern` of ``J`` (a matrix this assembler made), built once per structure."""
        if self._normal is None or not self._normal.fits(J):
            self._normal = NormalPattern(J)
        return self._normal

    def _matches(self, pieces: list[BlockTriplets], shape: tuple[int, int]) -> bool:
        if self._key is None or shape != self._shape or len(pieces) != len(self._key):
            return False
        for p, (rows, starts, vshape, offset) in zip(pieces, self._key):
            if p.values.shape != vshape or p.row_offset != offset:
                return False
            if not (p.rows is rows or np.array_equal(p.rows, rows)):
                return False
            if not (p.col_start is starts or np.array_equal(p.col_start, starts)):
                return False
        return True

    def assemble(self, pieces: list[BlockTriplets], shape: tuple[int, int]) -> sp.csr_matrix:
        """The CSR matrix of ``pieces`` (canonical: sorted columns, no duplicates)."""
        shape = (int(shape[0]), int(shape[1]))
        total = sum(p.values.size for p in pieces)
        if total == 0:
            return sp.csr_matrix(shape)
        if not self._matches(pieces, shape):
            self._analyse(pieces, shape, total)
        data = np.zeros(self._indices.size, dtype=np.float64)
        arrays = []
        for p, dest in zip(pieces, self._dest):
            values = np.ascontiguousarray(p.values, dtype=np.float64)
            scale = np.ones(0) if p.row_scale is None else np.asarray(p.row_scale, dtype=np.float64)
            arrays.append((np.ascontiguousarray(p.rows, dtype=np.int64), values, scale, dest))
        # As the fill of _analyse, chunk by chunk of sub-block rows across the pieces: their
        # writes stay in a few MB of the output (at 60 minutes of flight the scatter, one piece
        # after the other over all of J, took 0.18 s per assembly; one tenth of the flight 0.015 s).
        chunks = max(1, max(a[0].shape[0] for a in arrays) // _FILL_CHUNK)
        for c in range(chunks):
            for rows, values, scale, dest in arrays:
                n, m, d = values.shape
                a, b = n * c // chunks, n * (c + 1) // chunks
                if b > a:
                    _scatter_csr(rows[a:b], values[a:b], scale, dest[a * m * d:b * m * d], data)
        J = sp.csr_matrix((data, self._indices, self._indptr), shape=shape, copy=False)
        J.has_sorted_indices = True
        J.has_canonical_format = True
        return J

    def _analyse(self, pieces: list[BlockTriplets], shape: tuple[int, int], total: int) -> None:
        index_dtype = np.int32 if max(shape) < _INT32_MAX else np.int64
        dest_dtype = np.int32 if total < _INT32_MAX else np.int64
        counts = np.zeros(shape[0], dtype=np.int64)
        for p in pieces:
            counts += np.bincount((p.rows + p.row_offset).ravel(), minlength=shape[0]) * p.values.shape[2]
        indptr = np.zeros(shape[0] + 1, dtype=np.int64)
        np.cumsum(counts, out=indptr[1:])
        cursor = indptr[:-1].copy()
        indices = np.empty(total, dtype=index_dtype)
        arrays, base = [], 0
        for p in pieces:
            arrays.append((np.ascontiguousarray(p.rows, dtype=np.int64),
                           np.ascontiguousarray(p.col_start, dtype=np.int64), p.values.shape, p.row_offset, base))
            base += p.values.size
        # The pieces of one observation group cover the same rows in the same order (one piece
        # per parameter block and spline coefficient): filled in step, chunk by chunk, their
        # writes stay in a few MB of the output instead of sweeping all of it once per piece.
        chunks = max(1, max(p.values.shape[0] for p in pieces) // _FILL_CHUNK)
        for c in range(chunks):
            for rows, starts, vshape, row_offset, _ in arrays:
                n = rows.shape[0]
                a, b = n * c // chunks, n * (c + 1) // chunks
                if b > a:
                    _fill_csr(rows[a:b], starts[a:b], vshape[1], vshape[2], row_offset, cursor, indices)
        merged = np.empty(total, dtype=index_dtype)
        merged_indptr = np.zeros(shape[0] + 1, dtype=np.int64)
        nnz = _merge_rows(indptr, indices, merged, merged_indptr, shape[1])
        del indices
        csr_dtype = index_dtype if nnz < _INT32_MAX else np.int64
        self._indices = merged[:nnz].astype(csr_dtype, copy=True)
        self._indptr = merged_indptr.astype(csr_dtype)
        del merged
        for shared in (self._indices, self._indptr):  # every matrix assembled shares them: read-only
            shared.setflags(write=False)
        # Each entry's slot in the merged rows, written in the pieces' order (chunk by chunk, as
        # the fill): found by bisection in its row, where the rows' own order would scatter the
        # writes over all of J (0.39 s of the first assembly at 60 minutes of flight).
        dest = np.empty(total, dtype=dest_dtype)
        for c in range(chunks):
            for rows, starts, vshape, row_offset, first in arrays:
                n = rows.shape[0]
                a, b = n * c // chunks, n * (c + 1) // chunks
                if b > a:
                    _destinations(rows[a:b], starts[a:b], vshape[1], vshape[2], row_offset, self._indptr,
                                  self._indices, dest[first + a * vshape[1] * vshape[2]:first + b * vshape[1] * vshape[2]])
        self._dest = [dest[first : first + vshape[0] * vshape[1] * vshape[2]] for _, _, vshape, _, first in arrays]
        self._key = [(p.rows, p.col_start, p.values.shape, p.row_offset) for p in pieces]
        self._shape = shape


_FILL_CHUNK = 2048
"""Sub-block rows per piece and call of :func:`_fill_csr` (see :class:`JacobianAssembler`)."""


@numba.njit(cache=True, nogil=True)
def _fill_csr(rows, col_start, m, d, row_offset, cursor, indices):  # pragma: no cover - numba
    """Copy sub-block rows' columns to their CSR rows' next slots."""
    n = rows.shape[0]
    for k in range(n):
        c0 = col_start[k]
        for i in range(m):
            r = rows[k, i] + row_offset
            pos = cursor[r]
            for j in range(d):
                indices[pos + j] = c0 + j
            cursor[r] = pos + d


@numba.njit(cache=True, nogil=True)
def _merge_rows(indptr, indices, merged, merged_indptr, n_cols):  # pragma: no cover - numba
    """The distinct columns of each row, sorted. Returns nnz.

    A column marker finds the repeats, so only the distinct columns of a row are sorted (about
    a third of its entries in a G/I Jacobian).
    """
    marker = np.full(n_cols, -1, dtype=np.int64)
    slot = 0
    for r in range(indptr.size - 1):
        a, b = indptr[r], indptr[r + 1]
        start = slot
        for p in range(a, b):
            c = indices[p]
            if marker[c] < start:  # not seen in this row (slots of earlier rows are smaller)
                marker[c] = slot
                merged[slot] = c
                slot += 1
        for q in range(start + 1, slot):  # insertion sort: the pieces come nearly in column order
            c = merged[q]
            t = q - 1
            while t >= start and merged[t] > c:
                merged[t + 1] = merged[t]
                t -= 1
            merged[t + 1] = c
        merged_indptr[r + 1] = slot
    return slot


@numba.njit(cache=True, nogil=True)
def _destinations(rows, col_start, m, d, row_offset, indptr, indices, dest):  # pragma: no cover - numba
    """``dest`` = the slot of every entry of sub-blocks in their merged, sorted CSR rows (bisection)."""
    e = 0
    for k in range(rows.shape[0]):
        c0 = col_start[k]
        for i in range(m):
            r = rows[k, i] + row_offset
            row = indices[indptr[r]:indptr[r + 1]]
            for j in range(d):
                dest[e] = indptr[r] + np.searchsorted(row, c0 + j)
                e += 1


@numba.njit(cache=True, nogil=True)
def _scatter_csr(rows, values, row_scale, dest, data):  # pragma: no cover - numba
    """``data[dest[e]] += value_e * row_scale[row_e]`` over the entries of one piece, in order."""
    n, m, d = values.shape
    scaled = row_scale.size > 0
    e = 0
    for k in range(n):
        for i in range(m):
            s = row_scale[rows[k, i]] if scaled else 1.0
            for j in range(d):
                data[dest[e]] += values[k, i, j] * s
                e += 1


def lower_triangle(A: sp.spmatrix | sp.sparray) -> sp.csr_matrix:
    """The lower triangle with the diagonal of ``A`` as CSR (``scipy.sparse.tril``, four times faster).

    ``tril`` goes through COO triplets; here the CSR rows are masked in place (1.2 s against
    0.3 s on a 60-minute G/I normal matrix of 54 M non-zeros).
    """
    A = sp.csr_matrix(A)
    rows = np.repeat(np.arange(A.shape[0], dtype=A.indices.dtype), np.diff(A.indptr))
    keep = A.indices <= rows
    indptr = np.zeros(A.shape[0] + 1, dtype=A.indptr.dtype)
    np.cumsum(np.bincount(rows[keep], minlength=A.shape[0]), out=indptr[1:])
    return sp.csr_matrix((A.data[keep], A.indices[keep], indptr), shape=A.shape)


def normal_equations(J: sp.csr_matrix, r: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """``N = J^T J`` (full symmetric CSR) and ``g = J^T r``."""
    Jt = J.T.tocsr()
    return (Jt @ J).tocsr(), Jt @ r


class NormalPattern:
    """The lower triangle of ``N = J^T J`` for one sparsity pattern of ``J``, filled without forming ``J^T``.

    Built once per pattern of ``J`` (a Levenberg-Marquardt solve keeps it: see
    :class:`JacobianAssembler`). The rows of ``J`` with the same columns, wherever they are, form
    a *set* (an IMU window's axes, and every window and GNSS epoch between the same two knots:
    the corridor's G/I has 47,232 rows in 6,140 sets), found by hashing each row's columns
    (:func:`_row_hashes`, :func:`_column_sets`; rows that only share a hash stay apart). The CSR
    pattern of ``lower(N)`` follows from one row per set, and every entry of a set's dense
    ``L x L`` lower Gram matrix gets its slot in that pattern, row by row of ``N`` in the same pass
    (:func:`_lower_gram_pattern`). Each :meth:`lower` is then one numba pass (:func:`_lower_gram_fill`):
    per set, the Gram matrix of its rows in a small dense buffer (contiguous row reads), added to
    its slots. The sets are ordered by their first column, so that the additions of neighbouring
    sets fall on neighbouring rows of ``N``. Against the former pass over groups of consecutive
    rows (a dot product per pair of columns, gathered through a scratch row): 51 ms -> 14 ms on
    the corridor's G/I Jacobian (1.5 M entries). SciPy's product forms ``J^T`` (a copy), counts
    and fills the whole symmetric ``N`` and the lower triangle is then cut from it. Written by
    hand because no library in our dependency list fills a Gram matrix into a kept pattern.

    Memory kept: a row order (4 bytes a row) and a slot per entry of every set's lower Gram
    matrix (4 bytes; 8 beyond 2**31 entries of ``N``): 15 MB on the corridor's G/I, 3.4 slots per
    entry of ``lower(N)``. Where the sets hold few rows each the slots would outnumber ``N``'s
    entries (more than :data:`SLOTS_PER_ENTRY` of them: the G/I/L's LiDAR returns, 3.6 rows a set):
    there the sets' column lists are kept (8 bytes per column of a set) and :meth:`lower` goes row
    by row of ``N`` (:func:`_lower_gram_fill_rows`; on the corridor's G/I/L a build of 0.28 s and
    fills of 0.28 s, against 0.83 s and 0.12 s with 186 MB of slots).
    """

    def __init__(self, J: sp.csr_matrix) -> None:
        if not getattr(J, "has_sorted_indices", False):
            raise ValueError("NormalPattern: J must have sorted column indices in every row")
        self.shape_J = J.shape
        self.J_indptr = J.indptr
        self.J_indices = J.indices
        m, n = J.shape
        J_indptr = J.indptr.astype(np.int64, copy=False)
        J_indices = J.indices
        hashes = _row_hashes(J_indptr, J_indices)
        first = np.full(m, -1, dtype=np.int64)
        filled = np.diff(J_indptr) > 0
        first[filled] = J_indices[J_indptr[:-1][filled]]
        order = np.lexsort((hashes, first))  # the rows of a set together, the sets by their first column
        self.set_start = _column_sets(order, hashes, J_indptr, J_indices)
        self.order = order.astype(np.int32 if m < _INT32_MAX else np.int64)
        set_of = np.full(m, -1, dtype=np.int64)  # the set of each set's first row (its representative)
        set_of[order[self.set_start[:-1]]] = np.arange(self.set_start.size - 1)
        col_ptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(_representative_column_counts(J_indptr, J_indices, set_of, n), out=col_ptr[1:])
        col_row = np.empty(col_ptr[-1], dtype=np.int64)
        col_pos = np.empty(col_ptr[-1], dtype=np.int64)
        _column_lists(J_indptr, J_indices, set_of, col_ptr, col_row, col_pos)
        counts = _lower_gram_counts(col_ptr, col_row, J_indptr, J_indices, n)
        indptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(counts, out=indptr[1:])
        indices = np.empty(indptr[-1], dtype=np.int64)
        self.slot_ptr = _set_slot_counts(self.set_start, self.order, J_indptr)
        self.by_slots = self.slot_ptr[-1] <= SLOTS_PER_ENTRY * indptr[-1]
        small = max(m, col_ptr[-1], J.nnz) < _INT32_MAX
        if self.by_slots:
            self.slots = np.empty(self.slot_ptr[-1], dtype=np.int32 if indptr[-1] < _INT32_MAX else np.int64)
        else:  # the sets' column lists are kept instead, to fill N row by row
            self.slots = np.empty(0, dtype=np.int64)
        _lower_gram_pattern(col_ptr, col_row, col_pos, set_of, J_indptr, J_indices, indptr, indices,
                            self.slot_ptr, self.slots, self.by_slots)
        if not self.by_slots:
            self.col_ptr = col_ptr
            self.col_row = col_row.astype(np.int32 if small else np.int64)
            self.col_pos = col_pos.astype(np.int32)
            self.set_of = set_of.astype(np.int32 if small else np.int64)
        del col_ptr, col_row, col_pos, set_of
        self.row_max = int(np.max(np.diff(J_indptr), initial=0))
        index_dtype = np.int32 if max(n, indptr[-1]) < _INT32_MAX else np.int64
        self.indptr = indptr.astype(index_dtype)
        self.indices = indices.astype(index_dtype)
        self.diagonal = (indptr[1:] - 1).astype(np.int64)  # the diagonal: the last entry of every row
        for shared in (self.indptr, self.indices):
            shared.setflags(write=False)

    @property
    def n_sets(self) -> int:
        """Sets of rows of ``J`` with the same columns."""
        return self.set_start.size - 1

    def fits(self, J: sp.csr_matrix) -> bool:
        """Whether ``J`` has the pattern this was built for."""
        return J.shape == self.shape_J and (
            (J.indices is self.J_indices or np.array_equal(J.indices, self.J_indices))
            and (J.indptr is self.J_indptr or np.array_equal(J.indptr, self.J_indptr))
        )

    def lower(self, J: sp.csr_matrix, diagonal_add: np.ndarray | None = None) -> sp.csr_matrix:
        """``lower(J^T J)`` (CSR, sorted, the diagonal entry last in every row; columns without
        entries in ``J`` have an explicit zero there), plus ``diagonal_add`` on the diagonal."""
        n = self.shape_J[1]
        data = np.zeros(self.indices.size, dtype=np.float64)
        J_indptr = self.J_indptr.astype(np.int64, copy=False)
        values = np.ascontiguousarray(J.data, dtype=np.float64)
        if self.by_slots:
            _lower_gram_fill(self.set_start, self.order, J_indptr, values, self.slot_ptr, self.slots, data,
                             np.empty((self.row_max, self.row_max)))
        else:
            _lower_gram_fill_rows(self.col_ptr, self.col_row, self.col_pos, self.set_of, self.set_start, self.order,
                                  J_indptr, self.J_indices, values, self.indptr, self.indices, data, np.zeros(n),
                                  np.empty(self.row_max))
        if diagonal_add is not None:
            data[self.diagonal] += diagonal_add
        N = sp.csr_matrix((data, self.indices, self.indptr), shape=(n, n), copy=False)
        N.has_sorted_indices = True
        N.has_canonical_format = True
        return N


@numba.njit(cache=True, nogil=True)
def _row_hashes(indptr, indices):  # pragma: no cover - numba
    """An FNV-1a hash of every row's length and columns."""
    m = indptr.size - 1
    out = np.empty(m, dtype=np.uint64)
    for r in range(m):
        h = np.uint64(14695981039346656037) ^ np.uint64(indptr[r + 1] - indptr[r])
        for q in range(indptr[r], indptr[r + 1]):
            h = (h ^ np.uint64(indices[q])) * np.uint64(1099511628211)
        out[r] = h
    return out


@numba.njit(cache=True, nogil=True)
def _column_sets(order, hashes, indptr, indices):  # pragma: no cover - numba
    """Where each set starts in ``order`` (and the end): a new set wherever a row's hash or columns
    differ from those of the current set's first row (rows of equal hash but other columns
    interleaved in ``order`` then make sets of their own: correct, only less merged)."""
    m = order.size
    start = np.empty(m + 1, dtype=np.int64)
    n_sets = 0
    rep = -1
    for k in range(m):
        r = order[k]
        new = True
        if rep >= 0 and hashes[r] == hashes[rep]:
            length = indptr[r + 1] - indptr[r]
            if length == indptr[rep + 1] - indptr[rep]:
                new = False
                a, b = indptr[rep], indptr[r]
                for q in range(length):
                    if indices[a + q] != indices[b + q]:
                        new = True
                        break
        if new:
            start[n_sets] = k
            n_sets += 1
            rep = r
    start[n_sets] = m
    return start[:n_sets + 1].copy()


@numba.njit(cache=True, nogil=True)
def _representative_column_counts(indptr, indices, set_of, n):  # pragma: no cover - numba
    """Sets each column is in (the entries of the sets' first rows per column)."""
    counts = np.zeros(n, dtype=np.int64)
    for r in range(indptr.size - 1):
        if set_of[r] >= 0:
            for q in range(indptr[r], indptr[r + 1]):
                counts[indices[q]] += 1
    return counts


@numba.njit(cache=True, nogil=True)
def _column_lists(indptr, indices, set_of, col_ptr, col_row, col_pos):  # pragma: no cover - numba
    """The sets' first rows each column is in, ascending, and the column's place in each: a counting
    sort (a CSC view of those rows)."""
    cursor = col_ptr[:-1].copy()
    for r in range(indptr.size - 1):
        if set_of[r] >= 0:
            for q in range(indptr[r], indptr[r + 1]):
                c = indices[q]
                col_row[cursor[c]] = r
                col_pos[cursor[c]] = q - indptr[r]
                cursor[c] += 1


@numba.njit(cache=True, nogil=True)
def _lower_gram_counts(col_ptr, col_row, indptr, indices, n):  # pragma: no cover - numba
    """Entries of each row ``i`` of ``lower(J^T J)``: the columns ``j <= i`` sharing a row of ``J``
    with column ``i``, and ``i`` itself (kept even for an empty column, so the diagonal is always there)."""
    marker = np.full(n, -1, dtype=np.int64)
    counts = np.zeros(n, dtype=np.int64)
    for i in range(n):
        marker[i] = i
        c = 1
        for p in range(col_ptr[i], col_ptr[i + 1]):
            r = col_row[p]
            for q in range(indptr[r], indptr[r + 1]):
                j = indices[q]
                if j >= i:
                    break
                if marker[j] != i:
                    marker[j] = i
                    c += 1
        counts[i] = c
    return counts


@numba.njit(cache=True, nogil=True)
def _lower_gram_pattern(col_ptr, col_row, col_pos, set_of, indptr, indices, out_ptr, out_ind, slot_ptr,
                        slots, with_slots):  # pragma: no cover - numba
    """The column indices of each row of ``lower(J^T J)`` (sorted, the diagonal last), and the slot of
    every entry of every set's lower Gram matrix, row by row of ``N``.

    Row ``i`` is gathered from the sets containing column ``i`` (the marker walk of
    :func:`_lower_gram_counts`), sorted, and its places kept in ``place`` (by column); then every
    set with column ``i`` at its place ``a`` finds the slots of its entries ``(a, b <= a)`` there,
    without a search: ``O(nnz(N) + slots)``. Set ``s``'s entry ``(a, b)`` is its slot number
    ``slot_ptr[s] + a (a + 1) / 2 + b`` (the order of :func:`_lower_gram_fill`)."""
    n = out_ptr.size - 1
    marker = np.full(n, -1, dtype=np.int64)
    place = np.empty(n, dtype=np.int64)
    for i in range(n):
        pos = out_ptr[i]
        for p in range(col_ptr[i], col_ptr[i + 1]):
            r = col_row[p]
            for q in range(indptr[r], indptr[r + 1]):
                j = indices[q]
                if j >= i:
                    break
                if marker[j] != i:
                    marker[j] = i
                    out_ind[pos] = j
                    pos += 1
        out_ind[out_ptr[i]:pos] = np.sort(out_ind[out_ptr[i]:pos])
        out_ind[pos] = i
        if not with_slots:
            continue
        for q in range(out_ptr[i], pos + 1):
            place[out_ind[q]] = q
        for p in range(col_ptr[i], col_ptr[i + 1]):
            r = col_row[p]
            a = col_pos[p]
            k = slot_ptr[set_of[r]] + a * (a + 1) // 2
            base = indptr[r]
            for b in range(a + 1):
                slots[k + b] = place[indices[base + b]]


@numba.njit(cache=True, nogil=True)
def _set_slot_counts(set_start, order, indptr):  # pragma: no cover - numba
    """Where each set's slots start: ``L (L + 1) / 2`` entries for a set of rows of length ``L``."""
    n_sets = set_start.size - 1
    out = np.empty(n_sets + 1, dtype=np.int64)
    out[0] = 0
    for s in range(n_sets):
        r = order[set_start[s]]
        length = indptr[r + 1] - indptr[r]
        out[s + 1] = out[s] + length * (length + 1) // 2
    return out


@numba.njit(cache=True, nogil=True)
def _lower_gram_fill(set_start, order, indptr, data, slot_ptr, slots, out, gram):  # pragma: no cover - numba
    """Add every set's lower Gram matrix (built in ``gram``, ``L x L`` scratch) to its slots of ``out``."""
    for s in range(set_start.size - 1):
        r0 = order[set_start[s]]
        length = indptr[r0 + 1] - indptr[r0]
        for a in range(length):
            for b in range(a + 1):
                gram[a, b] = 0.0
        for k in range(set_start[s], set_start[s + 1]):
            base = indptr[order[k]]
            for a in range(length):
                x = data[base + a]
                for b in range(a + 1):
                    gram[a, b] += x * data[base + b]
        k = slot_ptr[s]
        for a in range(length):
            for b in range(a + 1):
                out[slots[k]] += gram[a, b]
                k += 1


@numba.njit(cache=True, nogil=True)
def _lower_gram_fill_rows(col_ptr, col_row, col_pos, set_of, set_start, order, indptr, indices, data, out_ptr,
                          out_ind, out, acc, gram_row):  # pragma: no cover - numba
    """``out`` = values of ``lower(J^T J)``, row ``i`` at a time: for every set with column ``i`` at
    place ``a``, row ``a`` of its lower Gram matrix (in ``gram_row``) added to ``acc`` (n zeros,
    zeroed again) by column, then gathered into row ``i``'s pattern. No slots kept (the sets of
    few rows, where they would outnumber N's entries: see :data:`SLOTS_PER_ENTRY`)."""
    n = out_ptr.size - 1
    for i in range(n):
        for p in range(col_ptr[i], col_ptr[i + 1]):
            r = col_row[p]
            a = col_pos[p]
            s = set_of[r]
            for b in range(a + 1):
                gram_row[b] = 0.0
            for k in range(set_start[s], set_start[s + 1]):
                base = indptr[order[k]]
                x = data[base + a]
                for b in range(a + 1):
                    gram_row[b] += x * data[base + b]
            base = indptr[r]
            for b in range(a + 1):
                acc[indices[base + b]] += gram_row[b]
        for q in range(out_ptr[i], out_ptr[i + 1]):
            j = out_ind[q]
            out[q] = acc[j]
            acc[j] = 0.0


SLOTS_PER_ENTRY = 4
"""The sets' Gram entries keep a slot each (4 bytes) where they number at most this many times the
entries of ``lower(N)``, i.e. cost at most 4/3 of ``N``'s own 12 bytes an entry: the corridor's G/I
(47,232 rows in 6,140 sets, 3.4 slots an entry). Sets of few rows need more (its G/I/L: 3.6 rows a
set, 5.6 slots an entry, 186 MB at 10 minutes of flight): there ``N`` is filled row by row
(:func:`_lower_gram_fill_rows`), keeping the sets' column lists instead."""


def column_squares(J: sp.csr_matrix) -> np.ndarray:
    """``diag(J^T J)``: the sum of squares of every column (``np.bincount`` with weights took 0.1 s
    for the 8.7 M entries of a 60-minute G/I Jacobian, converting its indices and weights first)."""
    out = np.zeros(J.shape[1])
    _column_squares(J.indices, np.ascontiguousarray(J.data, dtype=np.float64), out)
    return out


@numba.njit(cache=True, nogil=True)
def _column_squares(indices, data, out):  # pragma: no cover - numba
    for q in range(indices.size):
        out[indices[q]] += data[q] * data[q]
