"""Sparse NLS engine: Levenberg-Marquardt, robust losses, hold-constant, covariance, backends.

Every observation group below has its Jacobians checked against central differences through
the retraction (``georefine.adjustment.testing.check_jacobians``).
"""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import scipy.optimize
import scipy.sparse as sp

from georefine.adjustment import assembly, linalg
from georefine.adjustment.blocks import JacobianBlock, Linearization
from georefine.adjustment.linalg import (
    NotPositiveDefiniteError,
    available_backends,
    cholesky,
    marginal_covariance_blocks,
)
from georefine.adjustment.pcg import NormalSystem
from georefine.adjustment.problem import Problem
from georefine.adjustment.robust import CauchyLoss, HuberLoss, TrivialLoss, make_loss
from georefine.adjustment.selected_inverse import SelectedInverse, selected_inverse
from georefine.adjustment.solver import SolverOptions
from georefine.adjustment.testing import check_jacobians
from georefine.geometry.rotation import exp_so3, log_so3, right_jacobian_inv

SEEDS = [0, 1, 2]


# ---------------------------------------------------------------------------------------------
# Observation groups used by the tests
# ---------------------------------------------------------------------------------------------


class LinearGroup:
    """r = (A x - b) / sigma for one Euclidean element ``x`` (block ``block``, element 0)."""

    consumed_redundancy = 0.0

    def __init__(self, A, b, sigma, block="x", name="linear", loss=None):
        self.A, self.b, self.sigma = np.asarray(A, float), np.asarray(b, float), np.asarray(sigma, float)
        self.block, self.name, self.loss = block, name, loss

    def linearize(self, values, jacobians=True):
        x = values[self.block][0]
        r = (self.A @ x - self.b) / self.sigma
        jac = []
        if jacobians:
            m = r.size
            J = (self.A / self.sigma[:, None])[:, None, :]
            jac = [JacobianBlock(self.block, np.arange(m)[:, None], np.zeros(m, int), J)]
        return Linearization(r, jac, np.arange(r.size))


class ExpCurveGroup:
    """y = a exp(b t) + c, theta = (a, b, c) in block ``theta`` (one element)."""

    name = "curve"
    loss = None
    consumed_redundancy = 0.0

    def __init__(self, t, y, sigma):
        self.t, self.y, self.sigma = t, y, sigma

    def linearize(self, values, jacobians=True):
        a, b, c = values["theta"][0]
        e = np.exp(b * self.t)
        r = (a * e + c - self.y) / self.sigma
        jac = []
        if jacobians:
            J = np.stack([e, a * self.t * e, np.ones_like(e)], axis=1) / self.sigma
            # one JacobianBlock holding all rows of the single element
            jac = [JacobianBlock("theta", np.arange(r.size)[None, :], np.zeros(1, int), J[None])]
        return Linearization(r, jac)


class AbsoluteRotationGroup:
    """r_i = Log(Rm_i^T R_{idx_i}) / sigma: direct rotation measurements (3 rows per observation)."""

    loss = None
    consumed_redundancy = 0.0

    def __init__(self, idx, R_meas, sigma, name="abs"):
        self.idx, self.R_meas, self.sigma, self.name = np.asarray(idx), R_meas, sigma, name

    def linearize(self, values, jacobians=True):
        R = values["R"][self.idx]
        phi = log_so3(np.swapaxes(self.R_meas, 1, 2) @ R)
        r = (phi / self.sigma).reshape(-1)
        n = self.idx.size
        rows = np.arange(3 * n).reshape(n, 3)
        jac = [JacobianBlock("R", rows, self.idx, right_jacobian_inv(phi) / self.sigma)] if jacobians else []
        return Linearization(r, jac, np.repeat(np.arange(n), 3))


class RelativeRotationGroup:
    """r = Log(Rm_ij^T R_i^T R_j) / sigma for pairs (i, j)."""

    loss = None
    consumed_redundancy = 0.0

    def __init__(self, i, j, R_meas, sigma, name="rel"):
        self.i, self.j, self.R_meas, self.sigma, self.name = np.asarray(i), np.asarray(j), R_meas, sigma, name

    def linearize(self, values, jacobians=True):
        Ri, Rj = values["R"][self.i], values["R"][self.j]
        phi = log_so3(np.swapaxes(self.R_meas, 1, 2) @ np.swapaxes(Ri, 1, 2) @ Rj)
        r = (phi / self.sigma).reshape(-1)
        n = self.i.size
        rows = np.arange(3 * n).reshape(n, 3)
        jac = []
        if jacobians:
            Jinv = right_jacobian_inv(phi) / self.sigma
            jac = [
                JacobianBlock("R", rows, self.j, Jinv),
                JacobianBlock("R", rows, self.i, -Jinv @ np.swapaxes(Rj, 1, 2) @ Ri),
            ]
        return Linearization(r, jac, np.repeat(np.arange(n), 3))


class LineGroup:
    """y_k = m x_k + q; theta = (m, q)."""

    name = "line"
    consumed_redundancy = 0.0

    def __init__(self, x, y, sigma, loss=None):
        self.x, self.y, self.sigma, self.loss = x, y, sigma, loss

    def linearize(self, values, jacobians=True):
        m, q = values["theta"][0]
        r = (m * self.x + q - self.y) / self.sigma
        jac = []
        if jacobians:
            J = np.stack([self.x, np.ones_like(self.x)], axis=1) / self.sigma
            jac = [JacobianBlock("theta", np.arange(r.size)[:, None], np.zeros(r.size, int), J[:, None, :])]
        return Linearization(r, jac)


class SplineGroup:
    """Banded 'spline' observations: z_k = sum_{l<4} w_kl x_{i_k + l} + 0.05 |x_{i_k}|^2 (3-D).

    Mildly non-linear, each 3-row observation touches four consecutive 3-D elements.
    """

    loss = None
    consumed_redundancy = 0.0

    def __init__(self, first, w, z, sigma, name="spline"):
        self.first, self.w, self.z, self.sigma, self.name = first, w, z, sigma, name

    def linearize(self, values, jacobians=True):
        x = values["x"]
        n = self.first.size
        idx = self.first[:, None] + np.arange(4)
        xs = x[idx]  # (n, 4, 3)
        x0 = xs[:, 0]
        model = np.einsum("nl,nld->nd", self.w, xs) + 0.05 * np.sum(x0 * x0, axis=1, keepdims=True)
        r = ((model - self.z) / self.sigma).reshape(-1)
        jac = []
        if jacobians:
            rows = np.arange(3 * n).reshape(n, 3)
            eye = np.eye(3)
            for l in range(4):
                J = self.w[:, l, None, None] * eye
                if l == 0:
                    J = J + 0.1 * np.broadcast_to(x0[:, None, :], (n, 3, 3))
                jac.append(JacobianBlock("x", rows, idx[:, l], J / self.sigma))
        return Linearization(r, jac, np.repeat(np.arange(n), 3))


class DifferenceGroup:
    """Smoothness: (x_{i+1} - x_i) / sigma for all consecutive elements."""

    loss = None
    name = "smooth"
    consumed_redundancy = 0.0

    def __init__(self, n, sigma):
        self.n, self.sigma = n, sigma

    def linearize(self, values, jacobians=True):
        x = values["x"]
        r = ((x[1:] - x[:-1]) / self.sigma).reshape(-1)
        k = self.n - 1
        jac = []
        if jacobians:
            rows = np.arange(3 * k).reshape(k, 3)
            I = np.broadcast_to(np.eye(3) / self.sigma, (k, 3, 3))
            jac = [JacobianBlock("x", rows, np.arange(1, self.n), I), JacobianBlock("x", rows, np.arange(k), -I)]
        return Linearization(r, jac, np.repeat(np.arange(k), 3))


def random_rotations(rng, n, max_angle=np.pi):
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return exp_so3(axis * rng.uniform(0, max_angle, size=(n, 1)))


def noisy(rng, R, sigma):
    return R @ exp_so3(rng.normal(scale=sigma, size=R.shape[:-2] + (3,)))


# ---------------------------------------------------------------------------------------------
# (1) linear least squares vs numpy lstsq
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", SEEDS)
def test_linear_least_squares_matches_lstsq(seed):
    rng = np.random.default_rng(seed)
    m, p = 60, 5
    A = rng.normal(size=(m, p))
    sigma = rng.uniform(0.5, 2.0, m)
    b = A @ rng.normal(size=p) + rng.normal(size=m) * sigma
    group = LinearGroup(A, b, sigma)
    chk = check_jacobians(group, {"x": np.zeros((1, p))}, {"x": "euclidean"})
    assert chk.max_rel_error < 1e-8 and chk.residual_mismatch == 0

    problem = Problem()
    problem.add_block("x", rng.normal(size=(1, p)) * 10)
    problem.add_group(group)
    result = problem.solve()
    assert result.converged

    Aw, bw = A / sigma[:, None], b / sigma
    x_ref, *_ = np.linalg.lstsq(Aw, bw, rcond=None)
    np.testing.assert_allclose(problem.values("x")[0], x_ref, rtol=1e-9, atol=1e-10)
    res = Aw @ x_ref - bw
    s0 = res @ res / (m - p)
    assert result.redundancy == m - p
    assert result.variance_factor == pytest.approx(s0, rel=1e-9)
    cov_ref = s0 * np.linalg.inv(Aw.T @ Aw)
    np.testing.assert_allclose(problem.covariance("x")[0], cov_ref, rtol=1e-8)
    np.testing.assert_allclose(problem.covariance("x", scale_by_variance_factor=False)[0], cov_ref / s0, rtol=1e-8)


@pytest.mark.parametrize("backend", [b for b in ("cholmod", "cvxopt", "qdldl", "cholespy", "scipy")
                                     if b in available_backends()])
def test_marginal_covariance_blocks_batches_match_dense_inverse(backend):
    """Whole solves (cholespy, SciPy) or their forward half (CHOLMOD dense, CVXOPT sparse): the same blocks."""
    rng = np.random.default_rng(3)
    n = 60
    B = sp.random(n, n, density=0.1, random_state=rng)
    A = (B @ B.T + sp.eye(n) * 2.0).tocsr()
    inv = np.linalg.inv(A.toarray())
    starts = np.array([0, 9, -1, 30, 57])
    factor = cholesky(A, backend=backend)
    assert hasattr(factor, "solve_half") == (backend == "cholmod")
    for max_rhs in (4, 256):  # one element per batch, all in one (only the diagonal blocks of a batch are kept)
        blocks = marginal_covariance_blocks(factor, starts, 3, max_rhs=max_rhs)
        for k, s in enumerate(starts):
            expected = np.zeros((3, 3)) if s < 0 else inv[s : s + 3, s : s + 3]
            np.testing.assert_allclose(blocks[k], expected, atol=1e-12)



def _random_pieces(rng, shape, rows_from=None):
    """Sub-blocks with repeated rows and columns, row offsets and row scales, and their dense sum."""
    pieces, dense = [], np.zeros(shape)
    for n, (offset, d, scaled) in enumerate(((0, 3, False), (10, 2, True), (0, 3, True))):
        if rows_from is None:
            rows = rng.integers(0, 40, (25, 4))
            starts = rng.integers(0, shape[1] - d + 1, 25)
        else:  # the same pattern as an earlier set (new arrays, equal contents)
            rows, starts = rows_from[n].rows.copy(), rows_from[n].col_start.copy()
        values = rng.normal(size=(25, 4, d))
        scale = rng.uniform(0.5, 2.0, 40) if scaled else None
        pieces.append(assembly.BlockTriplets(rows, starts, values, offset, scale))
        for k in range(25):
            for i in range(4):
                w = 1.0 if scale is None else scale[rows[k, i]]
                dense[rows[k, i] + offset, starts[k] : starts[k] + d] += values[k, i] * w
    return pieces, dense


def test_assembled_jacobian_equals_the_summed_triplets():
    """Sub-blocks with repeated rows and columns, row offsets and row scales: the CSR matrix sums them."""
    rng = np.random.default_rng(13)
    shape = (50, 30)
    pieces, dense = _random_pieces(rng, shape)
    J = assembly.assemble_block_coo(pieces, shape)
    assert J.format == "csr" and J.has_canonical_format and J.nnz < sum(p.values.size for p in pieces)
    assert J.nnz == np.count_nonzero(dense)
    np.testing.assert_allclose(J.toarray(), dense, atol=1e-12)
    np.testing.assert_allclose((J.T @ J).toarray(), dense.T @ dense, atol=1e-10)
    # What assemble() claims about the structure is what scipy finds in it.
    K = sp.csr_matrix((J.data, J.indices, J.indptr), shape=shape)
    assert K.has_sorted_indices and K.has_canonical_format


def test_assembler_reuses_its_structure_and_notices_a_new_pattern():
    """New values and row scales on the same pattern go through the kept structure; a new pattern is analysed again."""
    rng = np.random.default_rng(15)
    shape = (50, 30)
    assembler = assembly.JacobianAssembler()
    first, dense = _random_pieces(rng, shape)
    np.testing.assert_allclose(assembler.assemble(first, shape).toarray(), dense, atol=1e-12)
    kept = assembler._dest
    same, dense = _random_pieces(rng, shape, rows_from=first)
    J = assembler.assemble(same, shape)
    assert assembler._dest is kept  # no second analysis
    np.testing.assert_allclose(J.toarray(), dense, atol=1e-12)
    other, dense = _random_pieces(rng, shape)  # other rows and columns
    J = assembler.assemble(other, shape)
    assert assembler._dest is not kept
    np.testing.assert_allclose(J.toarray(), dense, atol=1e-12)
    fewer = [other[0], other[1]]  # a piece left out (e.g. all its elements held constant)
    dense_fewer = assembly.assemble_block_coo(fewer, shape).toarray()
    np.testing.assert_allclose(assembler.assemble(fewer, shape).toarray(), dense_fewer, atol=1e-12)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("slots_per_entry", [0, 100])
def test_normal_pattern_fills_scipys_lower_gram_matrix(seed, slots_per_entry, monkeypatch):
    """lower(J^T J) filled into the kept pattern equals SciPy's product, empty columns keep an
    explicit zero diagonal, the damped copy adds on the diagonal only, and the pattern is reused
    for new values of the same structure; by the sets' slots and row by row alike."""
    monkeypatch.setattr(assembly, "SLOTS_PER_ENTRY", slots_per_entry)
    rng = np.random.default_rng(seed)
    shape = (120, 45)
    pieces, _ = _random_pieces(rng, shape)
    assembler = assembly.JacobianAssembler()
    J = assembler.assemble(pieces, shape)
    P = assembler.normal_pattern(J)
    assert P.by_slots == (slots_per_entry > 0)
    L = P.lower(J)
    np.testing.assert_allclose(L.toarray(), np.tril((J.T @ J).toarray()), rtol=1e-13, atol=1e-13)
    assert np.all(L.indices[P.diagonal] == np.arange(shape[1]))  # every diagonal entry, the last of its row
    d = rng.uniform(size=shape[1])
    np.testing.assert_allclose(P.lower(J, d).toarray(), L.toarray() + np.diag(d), atol=1e-13)
    again, _ = _random_pieces(np.random.default_rng(seed), shape)  # same structure, other values
    for p in again:
        p.values[...] = rng.normal(size=p.values.shape)
    J2 = assembler.assemble(again, shape)
    assert assembler.normal_pattern(J2) is P
    np.testing.assert_allclose(P.lower(J2).toarray(), np.tril((J2.T @ J2).toarray()), rtol=1e-12, atol=1e-12)
    # Rows with the same columns far apart (repeated, shuffled, rescaled) and empty rows: one set each.
    rows = rng.permutation(np.concatenate([np.repeat(np.arange(shape[0]), 3), [-1, -1]]))
    dup = sp.vstack([J2, sp.csr_matrix((1, shape[1]))]).tocsr()[np.where(rows < 0, shape[0], rows)]
    dup_scaled = sp.csr_matrix(sp.diags(rng.uniform(0.5, 2.0, dup.shape[0])) @ dup)
    dup_scaled.sort_indices()
    P_dup = assembly.NormalPattern(dup_scaled)
    assert P_dup.n_sets <= P.n_sets + 1  # the copies join their originals' sets
    np.testing.assert_allclose(P_dup.lower(dup_scaled).toarray(),
                               np.tril((dup_scaled.T @ dup_scaled).toarray()), rtol=1e-12, atol=1e-12)
    system = NormalSystem(J2, J2.T @ np.ones(shape[0]), np.zeros(shape[1]), np.ones(shape[1]), 0.0, pattern=P)
    np.testing.assert_allclose(system.N().toarray(), (J2.T @ J2).toarray(), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(system.damped_lower(0.5).toarray(), np.tril((J2.T @ J2).toarray()) + 0.5 * np.eye(shape[1]),
                               rtol=1e-12, atol=1e-12)


def test_column_sets_keep_rows_of_equal_hash_but_other_columns_apart():
    """Rows whose hashes collide (all equal here) but whose columns differ never share a set."""
    rng = np.random.default_rng(15)
    J = sp.random(60, 20, density=0.2, random_state=rng, format="csr")
    J = sp.vstack([J, J]).tocsr()
    J.sort_indices()
    order = rng.permutation(J.shape[0])
    starts = assembly._column_sets(order, np.zeros(J.shape[0], dtype=np.uint64), J.indptr.astype(np.int64), J.indices)
    assert starts[0] == 0 and starts[-1] == J.shape[0]
    for a, b in zip(starts[:-1], starts[1:]):
        first = J.indices[J.indptr[order[a]]:J.indptr[order[a] + 1]]
        for r in order[a:b]:
            np.testing.assert_array_equal(J.indices[J.indptr[r]:J.indptr[r + 1]], first)


def test_lower_triangle_is_scipys_tril():
    rng = np.random.default_rng(14)
    A = sp.random(300, 300, density=0.05, random_state=rng, format="csr")
    A = (A + A.T).tocsr()
    L = assembly.lower_triangle(A)
    assert L.format == "csr" and L.shape == A.shape
    np.testing.assert_array_equal(L.toarray(), np.tril(A.toarray()))

def _banded_spd(rng, n_elements: int, dim: int, reach: int) -> sp.csr_matrix:
    """A trajectory-like normal matrix: elements coupled to their ``reach`` neighbours, plus a few global unknowns."""
    n = n_elements * dim + 6
    rows, cols = [], []
    for e in range(n_elements):
        lo, hi = e * dim, min(n_elements, e + reach + 1) * dim
        r, c = np.meshgrid(np.arange(lo, lo + dim), np.arange(lo, hi), indexing="ij")
        rows.append(r.ravel())
        cols.append(c.ravel())
    rows.append(np.repeat(np.arange(n - 6, n), n))
    cols.append(np.tile(np.arange(n), 6))
    r, c = np.concatenate(rows), np.concatenate(cols)
    B = sp.csr_matrix((rng.normal(size=r.size), (r, c)), shape=(n, n))
    return (B @ B.T + sp.eye(n) * 0.1).tocsr()


@pytest.mark.parametrize("backend", [b for b in ("cholmod", "cvxopt", "qdldl") if b in available_backends()])
def test_selected_inverse_matches_dense_inverse(backend):
    """Takahashi's recursion on a supernodal (CHOLMOD) or simplicial LDL^T (QDLDL) factor of a block-banded
    matrix with dense global rows gives the exact blocks."""
    rng = np.random.default_rng(11)
    A = _banded_spd(rng, 400, 3, 4)
    inv = np.linalg.inv(A.toarray())
    si, factor = selected_inverse(A, backend=backend, always=True)
    assert factor is None and si.z.size == si.L.nnz
    starts = np.array([0, 3, -1, 600, 1197, 1200])  # the last: the 6 global unknowns
    for dim in (3, 6):
        blocks = si.blocks(starts, dim)
        for k, s in enumerate(starts):
            expected = np.zeros((dim, dim)) if s < 0 else inv[s : s + dim, s : s + dim]
            np.testing.assert_allclose(blocks[k], expected, atol=1e-10 * np.abs(inv).max())


@pytest.mark.parametrize("backend", [b for b in ("cholmod", "cvxopt", "qdldl") if b in available_backends()])
def test_selected_inverse_solves_for_entries_off_the_factor_pattern(backend, monkeypatch):
    """Leaves coupled only through a hub: their mutual entries of A^-1 lie off L's pattern and are solved for."""
    solved = []
    original = SelectedInverse._solved
    monkeypatch.setattr(SelectedInverse, "_solved", lambda self, q, a, b: solved.append(q.shape) or original(self, q, a, b))
    rng = np.random.default_rng(12)
    n = 40
    A = sp.lil_matrix((n, n))
    A.setdiag(rng.uniform(2.0, 3.0, n) + n)
    A[: n - 1, n - 1] = rng.uniform(0.5, 1.0, (n - 1, 1))
    A[n - 1, : n - 1] = A[: n - 1, n - 1].T
    A = A.tocsr()
    si, _ = selected_inverse(A, backend=backend, always=True)
    inv = np.linalg.inv(A.toarray())
    starts = np.array([0, 10, 37])
    blocks = si.blocks(starts, 3)
    for k, s in enumerate(starts):
        np.testing.assert_allclose(blocks[k], inv[s : s + 3, s : s + 3], atol=1e-14)
    assert abs(inv[0, 1]) > 1e-6  # non-zero although A's leaves 0 and 1 do not touch
    assert solved and solved[0][1] == 3
    # Only the variances: read from the pattern, nothing solved, the same diagonal.
    solved.clear()
    diag = si.blocks(starts, 3, diagonal=True)
    assert not solved
    for k, s in enumerate(starts):
        np.testing.assert_allclose(diag[k], np.diag(np.diag(inv[s : s + 3, s : s + 3])), atol=1e-14)


def test_selected_inverse_is_none_without_access_to_the_factor():
    A = sp.eye(5, format="csr") * 2.0
    si, factor = selected_inverse(A, backend="scipy")
    assert si is None and factor.backend == "scipy"


@pytest.mark.parametrize("backend", [b for b in ("cholmod", "cvxopt", "qdldl") if b in available_backends()])
@pytest.mark.parametrize(("ns_per_unit", "min_ratio"), [(1e-9, 0.0), (1e9, 0.0), (1e-9, 1e9)])
def test_covariance_is_the_same_whether_inverted_or_solved(backend, ns_per_unit, min_ratio, monkeypatch):
    """The cost model picks the recursion (cheap) or unit-column solves (dear by the count of the
    recursion's products, or with scikit-sparse by the probe against the factorisation); QDLDL always
    inverts; the blocks are the same, also where CVXOPT's factor went symbolic and is factorised again."""
    from georefine.adjustment import selected_inverse as module

    monkeypatch.setattr(module, "NS_PER_WORK_UNIT", ns_per_unit)
    monkeypatch.setattr(module, "MIN_SOLVES_PER_FACTORISATION", min_ratio)
    rng = np.random.default_rng(15)
    A = _banded_spd(rng, 200, 3, 3)
    si, factor = selected_inverse(A, backend=backend)
    starts = np.array([0, 300, 597])
    if backend == "qdldl" or (ns_per_unit < 1 and (min_ratio == 0.0 or backend == "cvxopt")):
        assert si is not None and factor is None
        blocks = si.blocks(starts, 3)
    else:
        assert si is None and factor is not None
        blocks = marginal_covariance_blocks(factor, starts, 3)
    inv = np.linalg.inv(A.toarray())
    for k, s in enumerate(starts):
        np.testing.assert_allclose(blocks[k], inv[s : s + 3, s : s + 3], atol=1e-10 * np.abs(inv).max())


@pytest.mark.parametrize("dense_rows_max", [2000, 20, 0])
def test_supernodal_recursion_equals_the_column_recursion(dense_rows_max, monkeypatch):
    """The dense supernode blocks give the column-by-column recursion's entries (all of them, on a
    factor with supernodes from 1 to 15 or more columns), also where supernodes with many rows below
    go column by column; a pattern that is not a factor's is refused by both."""
    from georefine.adjustment import selected_inverse as module

    monkeypatch.setattr(module, "DENSE_ROWS_MAX", dense_rows_max)
    kernel = module._takahashi_supernodal.py_func  # the module constant is read at compile time
    rng = np.random.default_rng(19)
    A = _banded_spd(rng, 150, 15, 1)
    R = sp.random(A.shape[0], A.shape[0], density=2e-4, random_state=rng, format="csr")
    A = (A + R @ R.T).tocsr()  # scattered couplings: supernodes of every size
    L, perm = cholesky(A, backend="qdldl").factor()
    L.sort_indices()
    indptr, indices = L.indptr.astype(np.int64), L.indices.astype(np.int64)
    starts = module._supernodes(indptr, indices)
    sizes = np.diff(starts)
    assert sizes.min() == 1 and sizes.max() >= 15 and np.unique(sizes).size >= 5, np.unique(sizes)
    z_col, z_sup = np.empty(L.nnz), np.empty(L.nnz)
    assert module._takahashi(indptr, indices, L.data, z_col)
    assert kernel(indptr, indices, L.data, z_sup, starts)
    np.testing.assert_allclose(z_sup, z_col, rtol=1e-10, atol=1e-12 * np.abs(z_col).max())
    # A row dropped from the last column with two or more below its diagonal: not a factor's pattern.
    j = int(np.flatnonzero(np.diff(L.indptr) >= 3)[-1])
    keep = np.ones(L.nnz, dtype=bool)
    keep[L.indptr[j] + 1] = False
    bp = np.concatenate([indptr[:j + 1], indptr[j + 1:] - 1])
    bi, bd = indices[keep], np.ascontiguousarray(L.data[keep])
    assert not module._takahashi(bp, bi, bd, np.empty(bd.size))
    assert not kernel(bp, bi, bd, np.empty(bd.size), module._supernodes(bp, bi))


def test_selected_inverse_agrees_with_solves_to_1e_8_on_a_gnss_imu_matrix():
    """The posterior of a trajectory-like system (block band, bias-like elements coupling many knots,
    global unknowns): the recursion's diagonal blocks equal unit-column solves to 1e-8 relative."""
    rng = np.random.default_rng(17)
    A = _banded_spd(rng, 600, 15, 1)
    # bias-like elements: 6 unknowns every 25 knots, coupled to all of them
    n0 = A.shape[0]
    extra = 6 * 24
    rows, cols, vals = [], [], []
    for j in range(24):
        for k in range(25 * j, min(600, 25 * (j + 2))):
            r = np.repeat(np.arange(n0 + 6 * j, n0 + 6 * j + 6), 15)
            c = np.tile(np.arange(15 * k, 15 * k + 15), 6)
            rows += [r, c]
            cols += [c, r]
            v = rng.normal(scale=0.1, size=r.size)
            vals += [v, v]
    C = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n0 + extra,) * 2)
    A = (sp.block_diag([A, sp.eye(extra) * 50.0]) + C).tocsr()
    starts = np.concatenate([np.arange(0, 9000, 15 * 50), n0 + 6 * np.arange(24)])
    ref = marginal_covariance_blocks(cholesky(A, backend="cholespy"), starts, 6)
    for backend in [b for b in ("cholmod", "cvxopt", "qdldl") if b in available_backends()]:
        si, _ = selected_inverse(A, backend=backend, always=True)
        blocks = si.blocks(starts, 6)
        rel = np.abs(blocks - ref).max(axis=(1, 2)) / np.abs(ref).max(axis=(1, 2))
        assert rel.max() < 1e-8, (backend, rel.max())


@pytest.mark.parametrize("backend", [b for b in ("cholmod", "cvxopt", "qdldl") if b in available_backends()])
@pytest.mark.parametrize(("ns_per_unit", "min_ratio"), [(1e-9, 0.0), (1e9, 0.0), (1e-9, 1e9)])
def test_selected_inverse_rejects_a_singular_matrix_on_every_path(backend, ns_per_unit, min_ratio, monkeypatch):
    """A gauge left free (a null space): refused whether the recursion runs (pivots of the copied factor) or
    the solves (by a solve), though the factorisation itself skips the pivot test."""
    from georefine.adjustment import selected_inverse as module

    monkeypatch.setattr(module, "NS_PER_WORK_UNIT", ns_per_unit)
    monkeypatch.setattr(module, "MIN_SOLVES_PER_FACTORISATION", min_ratio)
    rng = np.random.default_rng(16)
    A = _banded_spd(rng, 200, 3, 3).toarray()
    null = np.zeros(A.shape[0])
    null[:603:3] = 1.0  # the first coordinate of every element moves together
    P = np.eye(A.shape[0]) - np.outer(null, null) / (null @ null)
    with pytest.raises(NotPositiveDefiniteError):
        selected_inverse(sp.csr_matrix(P @ A @ P), backend=backend)


# ---------------------------------------------------------------------------------------------
# (2) non-linear Euclidean problem from a poor start
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("start", [[10.0, -0.05, -5.0], [0.1, -4.0, -1.0]])
def test_exponential_curve_fit_from_poor_start(seed, start):
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 4.0, 80)
    theta_true = np.array([2.5, -0.8, 0.7])
    sigma = 0.02
    y = theta_true[0] * np.exp(theta_true[1] * t) + theta_true[2] + rng.normal(scale=sigma, size=t.size)
    group = ExpCurveGroup(t, y, sigma)
    # Amplitude 4x or 25x off, rate 16x too slow or 5x too fast, offset of the wrong sign. (A start
    # with a growing exponential runs into the degenerate valley b -> 0, a -> -inf, c -> +inf,
    # where MINPACK's LM ends up as well.)
    start = np.array([start])
    chk = check_jacobians(group, {"theta": start}, {"theta": "euclidean"})
    assert chk.max_rel_error < 1e-7

    problem = Problem()
    problem.add_block("theta", start)
    problem.add_group(group)
    result = problem.solve(SolverOptions(max_iterations=200))
    assert result.converged, result.termination
    ref = scipy.optimize.least_squares(
        lambda th: (th[0] * np.exp(th[1] * t) + th[2] - y) / sigma, theta_true, xtol=1e-15, ftol=1e-15
    ).x
    np.testing.assert_allclose(problem.values("theta")[0], ref, rtol=1e-6, atol=1e-8)
    sd = np.sqrt(np.diagonal(problem.covariance("theta")[0]))
    assert np.all(np.abs(problem.values("theta")[0] - theta_true) < 5 * sd)
    assert result.final_cost < 1e-3 * result.initial_cost
    assert result.final_cost == pytest.approx(0.5 * result.redundancy, abs=3.0 * np.sqrt(2.0 * result.redundancy))
    assert list(result.cost_history) == sorted(result.cost_history, reverse=True)


# ---------------------------------------------------------------------------------------------
# (3) SO(3): rotation averaging, convergence and Monte-Carlo covariance consistency
# ---------------------------------------------------------------------------------------------


def _rotation_chain(rng, R_true, sigma_abs, sigma_rel, abs_idx):
    n = R_true.shape[0]
    i = np.concatenate([np.arange(n - 1), np.arange(n - 2)])
    j = np.concatenate([np.arange(1, n), np.arange(2, n)])
    rel = noisy(rng, np.swapaxes(R_true[i], 1, 2) @ R_true[j], sigma_rel)
    ab = noisy(rng, R_true[abs_idx], sigma_abs)
    return AbsoluteRotationGroup(abs_idx, ab, sigma_abs), RelativeRotationGroup(i, j, rel, sigma_rel)


@pytest.mark.parametrize("seed", SEEDS)
def test_rotation_jacobians_through_retraction(seed):
    rng = np.random.default_rng(seed)
    R = random_rotations(rng, 6)
    g_abs, g_rel = _rotation_chain(rng, R, 0.3, 0.3, np.array([0, 2, 5]))
    R_lin = noisy(rng, R, 0.5)  # far from the measurements: Jr^-1 matters
    for group in (g_abs, g_rel):
        chk = check_jacobians(group, {"R": R_lin}, {"R": "so3"})
        assert chk.max_rel_error < 1e-7, chk


def test_rotation_averaging_converges_and_covariance_matches_monte_carlo():
    rng = np.random.default_rng(42)
    n, sigma_abs, sigma_rel = 8, 0.02, 0.005
    R_true = random_rotations(rng, n)
    abs_idx = np.array([0, 4, 7])
    runs, errors, covs = 150, [], None
    for _ in range(runs):
        g_abs, g_rel = _rotation_chain(rng, R_true, sigma_abs, sigma_rel, abs_idx)
        problem = Problem()
        problem.add_block("R", noisy(rng, R_true, 0.3), manifold="so3")  # ~17 deg start error
        problem.add_group(g_abs)
        problem.add_group(g_rel)
        result = problem.solve()
        assert result.converged, result.termination
        R_est = problem.values("R")
        np.testing.assert_allclose(R_est @ np.swapaxes(R_est, 1, 2), np.broadcast_to(np.eye(3), (n, 3, 3)), atol=1e-12)
        # covariance of delta in R_true = R_est Exp(delta)
        errors.append(log_so3(np.swapaxes(R_est, 1, 2) @ R_true))
        if covs is None:
            covs = problem.covariance("R", scale_by_variance_factor=False)
    errors = np.asarray(errors)  # (runs, n, 3)
    assert np.abs(errors).max() < 0.05
    empirical = np.einsum("kni,knj->nij", errors, errors) / runs
    ratio = np.trace(empirical, axis1=1, axis2=2) / np.trace(covs, axis1=1, axis2=2)
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio
    # Normalised estimation errors: mean of e^T C^-1 e should be ~3 per element.
    nees = np.einsum("kni,nij,knj->kn", errors, np.linalg.inv(covs), errors).mean()
    assert 2.4 < nees < 3.6


def test_steps_by_preconditioned_conjugate_gradients_reach_the_direct_solution():
    """Steps after the first solved by CG on the last factor: the same estimate, fewer factorisations."""
    rng = np.random.default_rng(21)
    n = 400
    R_true = random_rotations(rng, n)
    g_abs, g_rel = _rotation_chain(rng, R_true, 0.02, 0.005, np.array([0, 100, 250, 399]))
    start = noisy(rng, R_true, 0.3)  # ~17 deg: several iterations with changing linearisation and damping
    estimates, results = {}, {}
    for name, reuse_from in (("direct", 10**9), ("cg", 0)):
        problem = Problem()
        problem.add_block("R", start, manifold="so3")
        problem.add_group(g_abs)
        problem.add_group(g_rel)
        results[name] = problem.solve(SolverOptions(reuse_factor_from=reuse_from, function_tolerance=1e-12))
        assert results[name].converged, results[name].termination
        estimates[name] = problem.values("R")
    direct, cg = results["direct"], results["cg"]
    assert direct.iterative_steps == 0 and direct.factorisations == direct.iterations
    assert cg.iterative_steps > 0 and cg.factorisations < direct.factorisations
    assert cg.factorisations + cg.iterative_steps == cg.iterations
    assert "conjugate-gradient steps" in cg.summary()
    diff = log_so3(np.swapaxes(estimates["cg"], 1, 2) @ estimates["direct"])
    assert np.abs(diff).max() < 1e-8
    assert cg.final_cost == pytest.approx(direct.final_cost, rel=1e-10)


@pytest.mark.parametrize("reported", [3, 20])
def test_a_factor_that_needed_many_conjugate_gradient_iterations_is_replaced_next(monkeypatch, reported):
    """After a step whose conjugate gradients needed more than half their cap, the next step is
    factorised without trying them (the old factor has aged); after a cheap one they go on."""
    from georefine.adjustment import solver

    events = []
    pcg, factorize = solver.pcg_step, solver.SparseCholesky.factorize

    def counted_pcg(normal, lam, factor):
        delta, _ = pcg(normal, lam, factor)
        events.append("cg")
        return delta, reported  # the iterations the step is said to have needed

    def counted_factorize(self, *args, **kwargs):
        events.append("factor")
        return factorize(self, *args, **kwargs)

    monkeypatch.setattr(solver, "pcg_step", counted_pcg)
    monkeypatch.setattr(solver.SparseCholesky, "factorize", counted_factorize)
    rng = np.random.default_rng(21)
    R_true = random_rotations(rng, 400)
    g_abs, g_rel = _rotation_chain(rng, R_true, 0.02, 0.005, np.array([0, 100, 250, 399]))
    problem = Problem()
    problem.add_block("R", noisy(rng, R_true, 0.3), manifold="so3")
    problem.add_group(g_abs)
    problem.add_group(g_rel)
    result = problem.solve(SolverOptions(reuse_factor_from=0, function_tolerance=1e-12))
    assert result.converged and result.iterations >= 4, result.termination
    pairs = list(zip(events, events[1:]))
    assert events[0] == "factor" and "cg" in events
    if reported > solver.PCG_STALE_ITERATIONS:
        assert ("cg", "cg") not in pairs
    else:
        assert ("cg", "cg") in pairs


def test_an_accepted_step_lets_the_spent_normal_equations_go_before_the_next_assembly(monkeypatch):
    """The J and N of the last linearisation are released before the next are evaluated and
    assembled (held, they doubled the G/I/L's J and N at every assembly); the result is unchanged."""
    import gc
    import weakref

    from georefine.adjustment import solver

    rng = np.random.default_rng(21)
    R_true = random_rotations(rng, 400)
    g_abs, g_rel = _rotation_chain(rng, R_true, 0.02, 0.005, np.array([0, 100, 250, 399]))
    start = noisy(rng, R_true, 0.3)
    assembled, alive_at_assembly = [], []
    normal_equations = solver._normal_equations

    def watched(*args, **kwargs):
        gc.collect()
        alive_at_assembly.append(sum(ref() is not None for ref in assembled))
        normal = normal_equations(*args, **kwargs)
        assembled.append(weakref.ref(normal))
        return normal

    monkeypatch.setattr(solver, "_normal_equations", watched)
    problem = Problem()
    problem.add_block("R", start, manifold="so3")
    problem.add_group(g_abs)
    problem.add_group(g_rel)
    result = problem.solve(SolverOptions(reuse_factor_from=0, function_tolerance=1e-12))
    assert result.converged and len(assembled) >= 3, result.termination
    assert alive_at_assembly == [0] * len(assembled)


def _line_with_outliers(n=400, sigma=0.1):
    """``n`` points of y = 0.7 x - 1.2 with noise ``sigma``, a fifth of them 3-8 m too high (seeded)."""
    rng = np.random.default_rng(22)
    x = rng.uniform(0.0, 10.0, n)
    y = 0.7 * x - 1.2 + rng.normal(scale=sigma, size=n)
    bad = rng.choice(n, size=n // 5, replace=False)
    y[bad] += rng.uniform(3.0, 8.0, bad.size)
    return x, y


def test_conjugate_gradient_steps_under_changing_robust_weights():
    """Cauchy IRLS reweights the rows every iteration; CG steps on the old factor still reach the same fit."""
    n, sigma = 400, 0.1
    x, y = _line_with_outliers(n, sigma)
    fits = {}
    for name, reuse_from in (("direct", 10**9), ("cg", 0)):
        problem = Problem()
        problem.add_block("theta", np.zeros((1, 2)))
        problem.add_group(LineGroup(x, y, sigma, CauchyLoss(2.385)))
        result = problem.solve(SolverOptions(max_iterations=100, reuse_factor_from=reuse_from, function_tolerance=1e-12))
        assert result.converged, result.termination
        fits[name] = (problem.values("theta")[0], result)
    assert fits["cg"][1].iterative_steps > 0
    np.testing.assert_allclose(fits["cg"][0], fits["direct"][0], rtol=0, atol=1e-7)


class MisfitGroup:
    """Residuals that no parameter moves (zero Jacobian): misfit the model cannot remove."""

    name = "misfit"
    loss = None
    consumed_redundancy = 0.0

    def __init__(self, r):
        self.r = r

    def linearize(self, values, jacobians=True):
        jac = []
        if jacobians:
            jac = [JacobianBlock("theta", np.arange(self.r.size)[:, None], np.zeros(self.r.size, int),
                                 np.zeros((self.r.size, 1, 2)))]
        return Linearization(self.r.copy(), jac)


def test_the_cost_change_test_relative_to_fit_ignores_misfit_it_cannot_remove():
    """Cauchy IRLS converges linearly; 2000 rows of 30 sigma that no parameter moves make the cost
    900 times a fitting model's. The plain relative test then stops after 2 steps, 0.2 sigma of the
    intercept short; ``relative_to_fit`` stops as near the optimum as the problem without that misfit."""
    n, sigma = 400, 0.1
    x, y = _line_with_outliers(n, sigma)

    def fit(misfit, relative_to_fit, tol=1e-4):
        problem = Problem()
        problem.add_block("theta", np.zeros((1, 2)))
        problem.add_group(LineGroup(x, y, sigma, CauchyLoss(2.385)))
        if misfit:
            problem.add_group(MisfitGroup(np.full(2000, 30.0)))
        # polish=False: the test is of the cost-change test under IRLS, not of the steps at the
        # least damping that follow it by default (test_polish_*).
        result = problem.solve(SolverOptions(max_iterations=200, function_tolerance=tol, relative_to_fit=relative_to_fit,
                                             polish=False))
        assert result.termination == "function_tolerance"
        return problem.values("theta")[0], result.iterations

    exact, _ = fit(False, False, tol=1e-14)
    clean, _ = fit(False, False)
    plain, plain_iterations = fit(True, False)
    relative, relative_iterations = fit(True, True)
    sigma_q = sigma * np.sqrt(4.0 / n)  # the intercept's, near enough
    assert relative_iterations > plain_iterations
    for estimate in (clean, relative):
        assert abs(estimate[1] - exact[1]) < 0.02 * sigma_q
    assert abs(plain[1] - exact[1]) > 0.1 * sigma_q


class ChainGroup:
    """``K`` states tied by precise differences (sigma ``sigma_d``), each observed once (sigma 1).

    The common mode is the weak direction: its curvature ``K`` against a diagonal of about
    ``2 / sigma_d^2`` per state, as a pass's heading against the IMU windows of its knots."""

    name = "chain"
    loss = None
    consumed_redundancy = 0.0

    def __init__(self, y, sigma_d):
        self.y, self.sigma_d = y, sigma_d

    def linearize(self, values, jacobians=True):
        x = values["x"][:, 0]
        k = x.size
        r = np.concatenate([x - self.y, np.diff(x) / self.sigma_d])
        jac = []
        if jacobians:
            rows = np.concatenate([np.arange(k), k + np.arange(k - 1), k + np.arange(k - 1)])
            elements = np.concatenate([np.arange(k), np.arange(k - 1), np.arange(1, k)])
            vals = np.concatenate([np.ones(k), np.full(k - 1, -1.0 / self.sigma_d), np.full(k - 1, 1.0 / self.sigma_d)])
            jac = [JacobianBlock("x", rows[:, None], elements, vals[:, None, None])]
        return Linearization(r, jac)


def test_polish_takes_a_weak_direction_to_its_optimum():
    """A damping of 1e-9 times the diagonal moves the chain's common mode (relative curvature 5e-13)
    by 1/2000 of the way per step, and the cost-change test of 1e-2 stops it there, 10 sigma short.
    The steps at the least damping that ``polish`` adds reach the optimum in one or two more."""
    rng = np.random.default_rng(11)
    k, sigma_d = 100, 1e-6
    y = 1.0 + rng.normal(size=k)
    exact = y.mean()  # the differences pin the states together: the optimum is the mean
    sigma_mean = 1.0 / np.sqrt(k)
    out = {}
    for polish in (False, True):
        problem = Problem()
        problem.add_block("x", np.zeros((k, 1)))
        problem.add_group(ChainGroup(y, sigma_d))
        result = problem.solve(SolverOptions(max_iterations=50, function_tolerance=1e-2, initial_lambda=1e-9,
                                             polish=polish))
        assert result.termination == "function_tolerance"
        out[polish] = (problem.values("x")[:, 0].mean(), result.iterations)
    assert abs(out[False][0] - exact) > 5 * sigma_mean, out
    assert abs(out[True][0] - exact) < 0.01 * sigma_mean, out
    assert out[True][1] <= out[False][1] + 3, out


def _exp_curve_with_and_without_predicted_stop(seed, monkeypatch, outliers=0, loss=None):
    """The exp curve (400 points, sigma 0.02, ``outliers`` of them moved by noise of 0.1, five sigma)
    solved with ``predicted_stop`` off and on: per flag the estimate, the evaluations, the final
    cost and the result; and the last problem (for its covariance)."""
    import georefine.adjustment.solver as solver_module

    calls = []
    original = solver_module._evaluate
    monkeypatch.setattr(solver_module, "_evaluate",
                        lambda groups, values, jacobians, robust: calls.append(jacobians) or original(
                            groups, values, jacobians, robust))
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.0, 4.0, 400)
    y = 2.5 * np.exp(-0.3 * x) + 0.7 + rng.normal(scale=0.02, size=x.size)
    if outliers:
        y[rng.choice(x.size, outliers, replace=False)] += rng.normal(scale=0.1, size=outliers)
    out = {}
    for predicted in (False, True):
        calls.clear()
        problem = Problem()
        problem.add_block("theta", np.array([[2.4, -0.29, 0.71]]))
        group = ExpCurveGroup(x, y, 0.02)
        group.loss = loss
        problem.add_group(group)
        result = problem.solve(SolverOptions(function_tolerance=1e-6, initial_lambda=1e-6, predicted_stop=predicted))
        out[predicted] = (problem.values("theta")[0].copy(), len(calls), result.final_cost, result)
    return out, problem


def _assert_within_the_tolerance(out, problem):
    """The two estimates differ by less than the cost-change test allows: far below a sigma."""
    assert abs(out[True][2] - out[False][2]) <= 1e-6 * out[False][2]
    cov = problem.covariance("theta")[0]
    d = out[True][0] - out[False][0]
    assert d @ np.linalg.solve(cov, d) < 1e-4


@pytest.mark.parametrize("seed", SEEDS)
def test_predicted_stop_saves_the_last_evaluations_within_the_tolerance(seed, monkeypatch):
    """A near-linear fit: the plain test evaluates the steps whose actual change it then finds too
    small; ``predicted_stop`` stops on the model's prediction before evaluating them. The estimates
    differ by less than the tolerance allows (a cost change of 1e-6 is a step of 1.4e-3 sigma), and
    the polish with the least damping still happens (on the model)."""
    out, problem = _exp_curve_with_and_without_predicted_stop(seed, monkeypatch)
    for *_, result in out.values():
        # the polish's re-damped step may be below the parameter tolerance: converged either way
        assert result.termination in ("function_tolerance", "parameter_tolerance") and result.converged
    assert out[True][1] < out[False][1], out
    _assert_within_the_tolerance(out, problem)


@pytest.mark.parametrize("seed", SEEDS)
def test_predicted_stop_ends_the_polish_while_robust_weights_still_move(seed, monkeypatch):
    """Outliers under a Huber loss: the weights move a little with every step, so the predicted stop
    waits for them, but not in the polish, whose cost-change test an evaluated step (reweighting
    included) has met. One evaluation fewer, the estimate within the tolerance of the plain one."""
    out, problem = _exp_curve_with_and_without_predicted_stop(seed, monkeypatch, outliers=30, loss=HuberLoss(1.5))
    for *_, result in out.values():
        assert result.termination == "function_tolerance" and result.converged
        assert result.groups[0].n_downweighted > 0
    assert out[True][1] == out[False][1] - 1, out
    _assert_within_the_tolerance(out, problem)


def test_predicted_stop_does_not_trust_a_model_no_step_has_borne_out():
    """From far away the first steps are rejected or badly predicted: the predicted test waits for an
    accepted step with a gain near 1, and the solve ends where the plain one does."""
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 4.0, 80)
    y = 2.5 * np.exp(-0.8 * t) + 0.7 + rng.normal(scale=0.02, size=t.size)
    out = {}
    for predicted in (False, True):
        problem = Problem()
        problem.add_block("theta", np.array([[10.0, -0.05, -5.0]]))
        problem.add_group(ExpCurveGroup(t, y, 0.02))
        result = problem.solve(SolverOptions(function_tolerance=1e-10, predicted_stop=predicted))
        assert result.converged
        out[predicted] = problem.values("theta")[0].copy()
    np.testing.assert_allclose(out[True], out[False], rtol=1e-5)


def test_posterior_seconds_count_what_the_posterior_formed_itself():
    """A solve ended by an evaluated step leaves J and N at the solution to the posterior, which
    times them apart (they are assembly and normal-matrix work, not covariance); a solve ended on
    the predicted change leaves both formed."""
    rng = np.random.default_rng(29)
    x = rng.uniform(0.0, 4.0, 400)
    y = 2.5 * np.exp(-0.3 * x) + 0.7 + rng.normal(scale=0.02, size=x.size)
    for predicted, formed in ((False, True), (True, False)):
        problem = Problem()
        problem.add_block("theta", np.array([[2.4, -0.29, 0.71]]))
        problem.add_group(ExpCurveGroup(x, y, 0.02))
        result = problem.solve(SolverOptions(function_tolerance=1e-4, initial_lambda=1e-6, predicted_stop=predicted,
                                             polish=False))
        assert result.termination == "function_tolerance"
        assert problem.posterior_seconds() == {"assembly": 0.0, "normal": 0.0}
        problem.covariance("theta")
        seconds = problem.posterior_seconds()
        assert (seconds["assembly"] > 0.0) == formed, (result.termination, seconds)
        assert seconds["normal"] >= 0.0


def test_relative_to_fit_changes_nothing_where_the_variance_factor_is_below_one():
    """Weights a fifth looser than the noise (variance factor about 0.7): the same steps, the same estimate."""
    rng = np.random.default_rng(23)
    x = rng.uniform(0.0, 10.0, 300)
    y = 0.7 * x - 1.2 + rng.normal(scale=0.1, size=x.size)
    out = {}
    for relative_to_fit in (False, True):
        problem = Problem()
        problem.add_block("theta", np.zeros((1, 2)))
        problem.add_group(LineGroup(x, y, 0.12, CauchyLoss(2.385)))
        result = problem.solve(SolverOptions(function_tolerance=1e-6, relative_to_fit=relative_to_fit))
        assert result.variance_factor < 1.0
        out[relative_to_fit] = (problem.values("theta")[0].copy(), result.iterations)
    assert out[True][1] == out[False][1]
    np.testing.assert_array_equal(out[True][0], out[False][0])


# ---------------------------------------------------------------------------------------------
# (4) robust losses
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("loss", [TrivialLoss(), HuberLoss(1.5), CauchyLoss(2.0)])
def test_robust_loss_derivatives(loss):
    s = np.concatenate([np.linspace(0.0, 30.0, 301), [1e-12, 1e4]])
    rho, drho = loss.evaluate(s)
    h = 1e-6
    num = (loss.evaluate(s + h)[0] - loss.evaluate(np.maximum(s - h, 0.0))[0]) / (s + h - np.maximum(s - h, 0.0))
    np.testing.assert_allclose(drho, num, rtol=1e-5, atol=1e-7)
    assert rho[0] == 0 and drho[0] == pytest.approx(1.0)
    assert np.all(drho > 0) and np.all(drho <= 1.0 + 1e-15)


def test_make_loss():
    assert make_loss(None) is None and make_loss("none") is None
    assert make_loss("huber", 2.0) == HuberLoss(2.0)
    assert make_loss("Cauchy") == CauchyLoss()
    with pytest.raises(ValueError):
        make_loss("tukey")
    with pytest.raises(ValueError):
        HuberLoss(-1.0)


@pytest.mark.parametrize("seed", SEEDS)
def test_robust_line_fit_rejects_gross_outliers(seed):
    rng = np.random.default_rng(seed)
    n, sigma = 200, 0.1
    x = rng.uniform(0.0, 10.0, n)
    m_true, q_true = 0.7, -1.2
    y = m_true * x + q_true + rng.normal(scale=sigma, size=n)
    bad = rng.choice(n, size=n // 10, replace=False)
    y[bad] += rng.uniform(3.0, 8.0, bad.size) * np.where(x[bad] > 5, 1.0, 0.3)  # one-sided, leverage
    truth = np.array([m_true, q_true])
    chk = check_jacobians(LineGroup(x, y, sigma), {"theta": np.zeros((1, 2))}, {"theta": "euclidean"})
    assert chk.max_rel_error < 1e-8

    estimates, results = {}, {}
    for name, loss in [("ls", None), ("huber", HuberLoss(1.345)), ("cauchy", CauchyLoss(2.385))]:
        problem = Problem()
        problem.add_block("theta", np.zeros((1, 2)))
        problem.add_group(LineGroup(x, y, sigma, loss))
        results[name] = problem.solve(SolverOptions(max_iterations=100))
        assert results[name].converged, (name, results[name].termination)
        estimates[name] = problem.values("theta")[0]
    # a clean-data fit has sigma_m ~ 0.0025, sigma_q ~ 0.015
    assert np.abs(estimates["ls"] - truth).max() > 0.1
    assert np.all(np.abs(estimates["huber"] - truth) < [0.02, 0.1])
    assert np.all(np.abs(estimates["cauchy"] - truth) < [0.01, 0.05])
    stats = results["cauchy"].group("line")
    assert stats.robust_loss == "cauchy" and stats.n_downweighted >= 0.8 * bad.size
    # What the good points alone would put below weight 0.5: one row each, |r| > c.
    from scipy.special import chdtrc

    assert stats.expected_downweighted == pytest.approx(chdtrc(1, 2.385**2))
    good_down = stats.n_downweighted - bad.size
    assert abs(good_down - stats.expected_downweighted * (n - bad.size)) < 4 * np.sqrt(0.017 * n), good_down
    assert results["ls"].group("line").expected_downweighted == 0.0
    assert results["huber"].group("line").expected_downweighted == pytest.approx(chdtrc(1, 4 * 1.345**2))
    # sigma0 from the median squared residual: the outliers (10 %) move it to the 56th percentile of
    # the good points' chi2(1), a factor sqrt(0.587 / 0.455) = 1.14 (NaN here until the statistics
    # kept the median through the solver's Jacobian-free copy of the evaluation).
    assert 0.9 < stats.robust_sigma0 < 1.4, stats.robust_sigma0
    # The whitened residuals' histogram: every row counted, the outliers (3-8 / 0.1 sigma) in the outer bin.
    from georefine.adjustment.statistics import RESIDUAL_EDGES

    theta = estimates["cauchy"]
    r = (y - (theta[0] * x + theta[1])) / sigma
    hist = np.asarray(stats.residual_histogram)
    assert hist.sum() == n and hist.size == len(RESIDUAL_EDGES) - 1
    assert hist[0] + hist[-1] == np.count_nonzero(np.abs(r) >= 5.0) >= bad.size * 0.9, (hist[0], hist[-1])
    assert np.count_nonzero(np.abs(r) < 1.0) == pytest.approx(hist[16:24].sum(), abs=2)  # edges at +-1: rounding
    # robust=False switches the loss off
    problem = Problem()
    problem.add_block("theta", np.zeros((1, 2)))
    problem.add_group(LineGroup(x, y, sigma, CauchyLoss()))
    problem.solve(SolverOptions(robust=False))
    np.testing.assert_allclose(problem.values("theta")[0], estimates["ls"], rtol=1e-7)


# ---------------------------------------------------------------------------------------------
# (5) hold constant / datum
# ---------------------------------------------------------------------------------------------


def test_constant_element_fixes_gauge_of_relative_rotations():
    rng = np.random.default_rng(5)
    n = 10
    R_true = random_rotations(rng, n)
    _, g_rel = _rotation_chain(rng, R_true, 0.01, 0.01, np.array([0]))
    start = noisy(rng, R_true, 0.2)
    start[3] = R_true[3]
    problem = Problem()
    problem.add_block("R", start, manifold="so3", constant=np.arange(n) == 3)
    problem.add_group(g_rel)
    result = problem.solve()
    assert result.converged
    assert result.n_unknowns == 3 * (n - 1)
    np.testing.assert_array_equal(problem.values("R")[3], start[3])  # bit-identical
    err = np.linalg.norm(log_so3(np.swapaxes(problem.values("R"), 1, 2) @ R_true), axis=1)
    assert err.max() < 0.05
    cov = problem.covariance("R")
    assert np.all(cov[3] == 0)
    assert np.all(np.linalg.eigvalsh(np.delete(cov, 3, axis=0)) > 0)
    # the covariance grows with the distance from the datum element
    tr = np.trace(cov, axis1=1, axis2=2)
    assert tr[9] > tr[5] > tr[4] and tr[0] > tr[2]


def test_without_datum_covariance_reports_singular_normal_matrix():
    rng = np.random.default_rng(6)
    R_true = random_rotations(rng, 5)
    _, g_rel = _rotation_chain(rng, R_true, 0.01, 0.01, np.array([0]))
    problem = Problem()
    problem.add_block("R", noisy(rng, R_true, 0.1), manifold="so3")
    problem.add_group(g_rel)
    result = problem.solve()  # LM damping still finds a (gauge-free) minimum
    assert result.converged
    # 7 relative rotations (21 rows), 15 unknowns of which 3 are gauge: chi^2 with 9 dof
    assert result.final_cost < 15.0 < 1e-2 * result.initial_cost
    with pytest.raises(NotPositiveDefiniteError):
        problem.covariance("R", scale_by_variance_factor=False)


def test_constant_block_adds_no_columns_and_jacobians_to_it_are_dropped():
    rng = np.random.default_rng(7)
    A1, A2 = rng.normal(size=(30, 3)), rng.normal(size=(30, 2))
    x1, x2 = rng.normal(size=3), rng.normal(size=2)
    b = A1 @ x1 + A2 @ x2 + rng.normal(scale=0.01, size=30)

    class TwoBlockGroup:
        name, loss = "two", None
        consumed_redundancy = 0.0

        def linearize(self, values, jacobians=True):
            r = (A1 @ values["a"][0] + A2 @ values["b"][0] - b) / 0.01
            rows = np.arange(30)[:, None]
            jac = [
                JacobianBlock("a", rows, np.zeros(30, int), A1[:, None, :] / 0.01),
                JacobianBlock("b", rows, np.zeros(30, int), A2[:, None, :] / 0.01),
            ] if jacobians else []
            return Linearization(r, jac)

    assert check_jacobians(TwoBlockGroup(), {"a": np.zeros((1, 3)), "b": np.zeros((1, 2))},
                           {"a": "euclidean", "b": "euclidean"}).max_rel_error < 1e-8
    problem = Problem()
    problem.add_block("a", np.zeros((1, 3)))
    problem.add_block("b", x2[None])
    problem.set_constant("b", True)
    problem.add_group(TwoBlockGroup())
    result = problem.solve()
    assert result.n_unknowns == 3 and result.redundancy == 27
    np.testing.assert_array_equal(problem.values("b")[0], x2)
    np.testing.assert_allclose(problem.values("a")[0], np.linalg.lstsq(A1, b - A2 @ x2, rcond=None)[0], rtol=1e-8)
    assert np.all(problem.covariance("b") == 0)
    problem.set_constant("b", False)
    problem.set_constant("a", np.array([True]))
    result = problem.solve()
    assert result.n_unknowns == 2


def test_all_constant_problem_reports_no_unknowns():
    problem = Problem()
    problem.add_block("theta", np.array([[0.7, -1.2]]), constant=True)
    problem.add_group(LineGroup(np.arange(5.0), 0.7 * np.arange(5.0) - 1.2, 0.1))
    result = problem.solve()
    assert result.termination == "no_unknowns" and result.converged and result.n_unknowns == 0
    assert result.final_cost == pytest.approx(0.0, abs=1e-20)


# ---------------------------------------------------------------------------------------------
# (6) linear-algebra backends
# ---------------------------------------------------------------------------------------------


def _random_spd(rng, n, density=0.02):
    B = sp.random(n, n, density=density, random_state=rng.integers(1 << 31))
    return (B @ B.T + sp.eye(n) * 0.1).tocsr()


def test_backends_agree_on_the_same_system():
    rng = np.random.default_rng(8)
    A = _random_spd(rng, 400)
    B = rng.normal(size=(400, 7))
    ref = np.linalg.solve(A.toarray(), B)
    backends = linalg.available_backends()
    assert "cholespy" in backends and "qdldl" in backends and backends[-1] == "scipy"
    for backend in backends:
        for lower in (False, True):
            M = sp.tril(A, format="csr") if lower else A
            f = cholesky(M, lower=lower, backend=backend)
            assert f.backend == backend and f.n == 400
            np.testing.assert_allclose(f.solve(B), ref, rtol=1e-9, atol=1e-11)
            np.testing.assert_allclose(f.solve(B[:, 0]), ref[:, 0], rtol=1e-9, atol=1e-11)
            with pytest.raises(ValueError, match="right-hand side"):
                f.solve(np.ones(399))
    # Full solve: same estimate with either backend
    estimates = []
    for backend in _installed("cholmod", "cvxopt", "qdldl", "cholespy", "scipy"):
        r = np.random.default_rng(9)
        R_true = random_rotations(r, 12)
        g_abs, g_rel = _rotation_chain(r, R_true, 0.02, 0.01, np.array([0, 11]))
        problem = Problem()
        problem.add_block("R", noisy(r, R_true, 0.2), manifold="so3")
        problem.add_group(g_abs)
        problem.add_group(g_rel)
        result = problem.solve(SolverOptions(linear_solver=backend))
        assert result.backend == backend
        estimates.append((problem.values("R"), problem.covariance("R")))
    for values, cov in estimates[1:]:
        np.testing.assert_allclose(values, estimates[0][0], atol=1e-10)
        np.testing.assert_allclose(cov, estimates[0][1], rtol=1e-7)


def _installed(*names):
    return [b for b in names if b in linalg.available_backends()]


@pytest.mark.parametrize("backend", _installed("cholmod", "cvxopt", "qdldl", "cholespy", "scipy"))
def test_backends_reject_indefinite_matrices(backend):
    A = sp.csr_matrix(np.array([[2.0, 3.0, 0.0], [3.0, 2.0, 0.0], [0.0, 0.0, 1.0]]))
    with pytest.raises(NotPositiveDefiniteError):
        cholesky(A, backend=backend)
    with pytest.raises(ValueError):
        cholesky(A, backend="mumps")


@pytest.mark.parametrize("backend", _installed("cholmod", "cvxopt", "qdldl", "cholespy", "scipy"))
def test_backends_reject_numerically_singular_matrices(backend):
    """A missing datum: rounding leaves a tiny positive pivot, which must not pass as a factor."""
    rng = np.random.default_rng(12)
    G = rng.normal(size=(40, 6))
    G[:, 5] = G[:, :5] @ rng.normal(size=5)  # rank 5
    A = sp.csr_matrix(G.T @ G)
    with pytest.raises(NotPositiveDefiniteError):
        cholesky(A, backend=backend)


@pytest.mark.parametrize("backend", _installed("cholmod", "cvxopt", "qdldl", "cholespy", "scipy"))
def test_sparse_cholesky_reuses_the_analysis_while_the_pattern_holds(backend):
    rng = np.random.default_rng(13)
    A = _random_spd(rng, 300)
    B = rng.normal(size=(300, 3))
    solver = linalg.SparseCholesky(backend)
    for scale in (1.0, 2.0, 5.0):  # LM: N + lambda D, same pattern, new values
        M = A + sp.diags(scale * A.diagonal())
        np.testing.assert_allclose(solver.factorize(M).solve(B), np.linalg.solve(M.toarray(), B), rtol=1e-9, atol=1e-12)
    separate = backend in ("cholmod", "cvxopt", "qdldl")
    assert solver.analyses == (1 if separate else 0)
    A2 = _random_spd(rng, 300)  # another pattern: analysed anew
    np.testing.assert_allclose(solver.factorize(A2).solve(B), np.linalg.solve(A2.toarray(), B), rtol=1e-9, atol=1e-12)
    assert solver.analyses == (2 if separate else 0)
    bad = sp.csr_matrix(A2.toarray() - 1e3 * np.eye(300))
    with pytest.raises(NotPositiveDefiniteError):
        solver.factorize(bad)
    np.testing.assert_allclose(solver.factorize(A2).solve(B[:, 0]), np.linalg.solve(A2.toarray(), B[:, 0]), rtol=1e-9)


@pytest.mark.skipif("cvxopt" not in linalg.available_backends(), reason="CVXOPT not installed")
@pytest.mark.parametrize("split", [False, True])
def test_cvxopt_builds_matrices_with_long_columns_apart_to_the_same_pattern_and_solves(split, monkeypatch):
    """An arrowhead (a few columns beside every other, as the strip adjustment's strip columns, and an
    explicit zero as the normal pattern keeps for unobserved columns): built with the long columns
    apart (transposed) or in one, CVXOPT holds the same column-major pattern and values as SciPy's CSC,
    and the factor solves the system, also after a refactorisation with new values."""
    if split:  # the long-column path on a small matrix
        monkeypatch.setattr(linalg, "_LONG_COLUMN", 5)
        monkeypatch.setattr(linalg, "_LONG_COLUMN_COST", 0)
    rng = np.random.default_rng(14)
    n, k = 300, 4
    rows = np.repeat(np.arange(k, n), k)
    cols = np.tile(np.arange(k), n - k)
    B = sp.csr_matrix((rng.normal(size=rows.size), (rows, cols)), shape=(n, n))
    A = (B @ B.T + B + B.T + sp.diags(np.full(n, 50.0))).tocsr()
    A_lower = sp.tril(A, format="csr")
    A_lower.sum_duplicates()
    data = A_lower.data.copy()
    data[A_lower.indptr[7]] = 0.0  # an explicit zero keeps its slot
    A_lower = sp.csr_matrix((data, A_lower.indices, A_lower.indptr), shape=(n, n))
    r, order = linalg._rows_and_csc_order(A_lower.indptr.astype(np.int64), A_lower.indices, n)
    M = linalg._cvxopt_spmatrix(A_lower, r, order, n)
    colptr, rowind, values = (np.array(x).ravel() for x in M.CCS)
    C = A_lower.tocsc()
    C.sort_indices()
    np.testing.assert_array_equal(colptr, C.indptr)
    np.testing.assert_array_equal(rowind, C.indices)
    np.testing.assert_array_equal(values, C.data)
    full = (A_lower + sp.tril(A_lower, k=-1).T).toarray()
    b = rng.normal(size=n)
    solver = linalg.SparseCholesky("cvxopt")
    np.testing.assert_allclose(solver.factorize(A_lower, lower=True).solve(b), np.linalg.solve(full, b), rtol=1e-9)
    data = A_lower.data.copy()
    data[A_lower.indptr[1:] - 1] += 3.0  # the diagonal, last in every row: same pattern, new values
    A2 = sp.csr_matrix((data, A_lower.indices, A_lower.indptr), shape=(n, n))
    np.testing.assert_allclose(solver.factorize(A2, lower=True).solve(b), np.linalg.solve(full + 3.0 * np.eye(n), b),
                               rtol=1e-9)
    assert solver.analyses == 1


def test_cholespy_reads_only_the_lower_triangle():
    """Documents the pitfall the linalg wrapper avoids: cholespy silently ignores the upper part."""
    cholespy = pytest.importorskip("cholespy")
    rng = np.random.default_rng(10)
    A = _random_spd(rng, 50, 0.1)
    b = rng.normal(size=50)
    upper = sp.triu(A, format="coo")
    solver = cholespy.CholeskySolverD(
        50, upper.row.astype(np.int32), upper.col.astype(np.int32), upper.data, cholespy.MatrixType.COO
    )
    x = np.zeros(50)
    solver.solve(b, x)
    assert np.abs(A @ x - b).max() > 1e-3  # wrong: only the diagonal was used
    np.testing.assert_allclose(A @ cholesky(A, backend="cholespy").solve(b), b, atol=1e-10)


# ---------------------------------------------------------------------------------------------
# (7) a-posteriori variance factor and statistics
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", SEEDS)
def test_variance_factor_is_one_for_correct_weights(seed):
    rng = np.random.default_rng(seed)
    n = 200
    R_true = random_rotations(rng, n)
    g_abs, g_rel = _rotation_chain(rng, R_true, 0.01, 0.003, np.arange(0, n, 4))
    problem = Problem()
    problem.add_block("R", noisy(rng, R_true, 0.05), manifold="so3")
    problem.add_group(g_abs)
    problem.add_group(g_rel)
    result = problem.solve()
    f = result.redundancy
    assert f == 3 * (50 + (n - 1) + (n - 2)) - 3 * n
    assert abs(result.variance_factor - 1.0) < 4.0 * np.sqrt(2.0 / f)
    assert result.n_observations == 50 + 2 * n - 3 and result.n_residuals == 3 * result.n_observations
    stats = {g.name: g for g in result.groups}
    assert stats["abs"].n_observations == 50 and stats["rel"].n_residuals == 3 * (2 * n - 3)
    assert sum(g.cost_share for g in result.groups) == pytest.approx(1.0)
    assert sum(g.cost for g in result.groups) == pytest.approx(result.final_cost)
    for g in result.groups:
        assert 0.5 < g.rms < 1.1 and g.variance_factor == pytest.approx(g.rms**2)
    payload = json.loads(json.dumps(result.to_dict()))
    assert payload["termination"] == result.termination and payload["groups"][0]["name"] == "abs"
    assert payload["timings"]["total_s"] >= payload["timings"]["factorization_s"] >= 0
    assert "sigma0^2" in result.summary()


def test_progress_callback_and_iteration_limit():
    rng = np.random.default_rng(11)
    t = np.linspace(0.0, 4.0, 50)
    y = 2.0 * np.exp(-0.5 * t) + 0.3 + rng.normal(scale=0.01, size=t.size)
    problem = Problem()
    problem.add_block("theta", np.array([[0.5, 0.5, -1.0]]))
    problem.add_group(ExpCurveGroup(t, y, 0.01))
    seen = []
    result = problem.solve(SolverOptions(max_iterations=3), progress=seen.append)
    assert result.termination == "max_iterations" and not result.converged
    assert result.iterations == 3 and [s.iteration for s in seen] == [1, 2, 3]
    assert len(result.cost_history) == result.successful_iterations + 1


def test_problem_validation_errors():
    problem = Problem()
    with pytest.raises(ValueError):
        problem.add_block("R", np.ones((2, 3, 3)), manifold="so3")
    with pytest.raises(ValueError):
        problem.add_block("x", np.zeros(4))
    with pytest.raises(ValueError):
        problem.add_block("x", np.zeros((4, 2)), manifold="se3")
    problem.add_block("x", np.zeros((4, 2)))
    with pytest.raises(ValueError):
        problem.add_block("x", np.zeros((4, 2)))
    with pytest.raises(ValueError):
        problem.set_constant("x", np.array([True, False]))
    with pytest.raises(KeyError):
        problem.values("y")
    with pytest.raises(RuntimeError):
        problem.covariance("x")
    with pytest.raises(ValueError):
        JacobianBlock("x", np.zeros((3, 2), int), np.zeros(3, int), np.zeros((3, 1, 2)))


# ---------------------------------------------------------------------------------------------
# (8) scale
# ---------------------------------------------------------------------------------------------


def _spline_problem(rng, n_elements, obs_per_element=2):
    x_true = np.cumsum(rng.normal(scale=0.1, size=(n_elements, 3)), axis=0)
    n_obs = obs_per_element * n_elements
    first = rng.integers(0, n_elements - 3, n_obs)
    w = rng.uniform(0.1, 1.0, (n_obs, 4))
    sigma = 0.01
    x0 = x_true[first]
    z = np.einsum("nl,nld->nd", w, x_true[first[:, None] + np.arange(4)]) + 0.05 * np.sum(x0 * x0, 1, keepdims=True)
    z += rng.normal(scale=sigma, size=z.shape)
    # the random walk of x_true is exactly what the smoothness pseudo-observations assume
    return x_true, SplineGroup(first, w, z, sigma), DifferenceGroup(n_elements, 0.1)


def test_spline_group_jacobians():
    rng = np.random.default_rng(12)
    x_true, spline, smooth = _spline_problem(rng, 12)
    x = x_true + rng.normal(scale=0.3, size=x_true.shape)
    for group in (spline, smooth):
        assert check_jacobians(group, {"x": x}, {"x": "euclidean"}).max_rel_error < 1e-7
    chk = check_jacobians(spline, {"x": x}, {"x": "euclidean"}, constant={"x": np.arange(12) < 3}, max_elements=4)
    assert chk.max_rel_error < 1e-7


def test_scale_100k_unknowns_solves_in_seconds():
    rng = np.random.default_rng(13)
    n_elements = 33_400  # 100,200 unknowns
    x_true, spline, smooth = _spline_problem(rng, n_elements)
    problem = Problem()
    problem.add_block("x", x_true + rng.normal(scale=0.05, size=x_true.shape))
    problem.add_group(spline)
    problem.add_group(smooth)
    t0 = time.perf_counter()
    result = problem.solve()
    elapsed = time.perf_counter() - t0
    assert result.converged, result.termination
    assert result.n_unknowns == 3 * n_elements
    assert abs(result.variance_factor - 1.0) < 0.05
    err = problem.values("x") - x_true
    assert np.sqrt(np.mean(err**2)) < 0.02
    assert elapsed < 20.0, result.summary()
    cov = problem.covariance("x", elements=np.arange(0, n_elements, 1000))
    assert cov.shape == (34, 3, 3) and np.all(np.linalg.eigvalsh(cov) > 0)
