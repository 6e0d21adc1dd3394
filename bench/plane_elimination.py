"""The plane parameters eliminated from the G/I/L's normal equations: measured against the solver's factorisation (a script, not a test).

docs/ARCHITECTURE.md §4.4 solves every Levenberg-Marquardt step of the G/I/L by a sparse Cholesky
factorisation of the whole damped normal matrix (AMD order), or by conjugate gradients
preconditioned with an earlier step's factor. This script measures, on one G/I/L problem of a
run, the alternatives that keep the planar objects' parameters out of that factorisation. The
G/I/L's unknowns split into the trajectory and its companions ``y`` (knots, IMU errors, GNSS
error, boresight, time offset) and the objects' plane parameters ``z`` (three per object). Every
plane observation touches one object, so ``N_zz`` is block diagonal and

``S = A - B^T C^-1 B``,   ``S dy = -g_y + B^T C^-1 g_z``,   ``dz = C^-1 (-g_z - B dy)``

with ``A = N_yy + lambda D_y``, ``B = N_zy``, ``C = N_zz + lambda D_z`` (Triggs et al. 2000,
§6.1: the reduced camera system, planes in the role of points). Two ways to solve ``S``:

* ``direct``: ``S`` formed and factorised (the same backend, its own AMD order).
* ``pcg``: conjugate gradients on ``S`` (products with ``J``, ``S`` never formed), preconditioned
  by the Schur complement of the planes *per visit*: an object's rows split where their first
  trajectory column jumps by more than ``--gaps`` columns (15 per knot), each run eliminating a
  plane of its own. That matrix couples only the columns one visit touches, the trajectory's
  own bandwidth (its factor grows linearly with the flight), and lies below ``S`` (``B^T C^-1 B``
  is jointly convex and homogeneous in ``(B, C)``, hence subadditive over the visits, with the
  damping of ``C`` shared among them), so every eigenvalue of the preconditioned matrix is at
  least 1: what the iterations add is the agreement of the passes.

The problem is the run's last outer iteration's (``features/``), built at the simulated truth
as ``workflows/cramer_rao.py`` builds it, and the normal system is that of its first
Levenberg-Marquardt step. Printed: the unknowns, the factor's non-zeros and times of each way,
conjugate-gradient iterations to a preconditioned residual of ``--tolerance``, each step's
distance from the factorised step, and the ratio of each way's time to a refactorisation.

Usage::

    python bench/plane_elimination.py PROJECT RUN [--lambdas 1e-9 1e-4] [--gaps 150 1500]

PROJECT a simulated project (``georefine simulate corridor --out PROJECT``), RUN its
``georefine run PROJECT --out RUN --no-points``.

References
----------
Triggs, B., McLauchlan, P., Hartley, R., Fitzgibbon, A. (2000): Bundle adjustment - a modern
synthesis. Vision Algorithms: Theory and Practice, LNCS 1883.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from georefine.adjustment import solver
from georefine.adjustment.gnss_imu import solve_gnss_imu, trajectory_solver_options
from georefine.adjustment.linalg import NotPositiveDefiniteError, SparseCholesky
from georefine.lidar.object_files import read_objects
from georefine.lidar.planes import read_features
from georefine.workflows.cramer_rao import truth_start
from georefine.workflows.gil import build_gil_problem
from georefine.workflows.opened import load_navigation

VISIT_GAP_COLUMNS = 150
"""Rows of one object whose smallest trajectory columns lie more than this apart begin another
visit (ten knots of 15 columns: one second on 0.1 s knots; the passes over an object are minutes
apart)."""


@dataclass(frozen=True)
class SchurSplit:
    """The eliminated columns (``elim``, ``d`` consecutive per element, element-major) and the kept ones."""

    elim: np.ndarray
    keep: np.ndarray
    d: int

    @property
    def n_elements(self) -> int:
        return self.elim.size // self.d


def split_columns(col_start: np.ndarray, d: int, n_cols: int) -> SchurSplit:
    """The split for the free elements of one block (``col_start`` of the layout, -1 for constant ones)."""
    starts = np.asarray(col_start, dtype=np.int64)
    starts = starts[starts >= 0]
    elim = (starts[:, None] + np.arange(d)[None, :]).ravel()
    mask = np.ones(n_cols, dtype=bool)
    mask[elim] = False
    return SchurSplit(elim, np.flatnonzero(mask), d)


@dataclass
class SchurStep:
    """What one step by the Schur complement did (for the log and the timings)."""

    delta: np.ndarray | None
    method: str
    iterations: int = 0
    seconds: dict[str, float] = field(default_factory=dict)
    nnz_reduced: int = 0
    visits: int = 0


def _element_of_rows(Jz: sp.csr_matrix, d: int) -> np.ndarray:
    """For each row of ``J_z`` (CSR, columns element-major) the element it touches, -1 for none.

    Raises ValueError when a row touches two elements: then ``N_zz`` is not block diagonal."""
    counts = np.diff(Jz.indptr)
    first = np.full(Jz.shape[0], -1, dtype=np.int64)
    has = counts > 0
    first[has] = Jz.indices[Jz.indptr[:-1][has]] // d
    row_of = np.repeat(np.arange(Jz.shape[0]), counts)
    if np.any(Jz.indices // d != first[row_of]):
        raise ValueError("a row touches two eliminated elements: their block of the normal matrix is not block diagonal")
    return first


def _block_inverse(Jz: sp.csr_matrix, damp_z: np.ndarray, d: int, n_el: int) -> sp.csr_matrix:
    """``(J_z^T J_z + diag(damp_z))^-1``, block diagonal with ``d x d`` blocks, as a sparse matrix."""
    coo = (Jz.T @ Jz).tocoo()
    dense = np.zeros((n_el, d, d))
    dense[coo.row // d, coo.row % d, coo.col % d] += coo.data
    dense[:, np.arange(d), np.arange(d)] += damp_z.reshape(n_el, d)
    try:
        inv = np.linalg.inv(dense)
    except np.linalg.LinAlgError:
        raise NotPositiveDefiniteError("an eliminated block is singular") from None
    rows = np.repeat(np.arange(n_el * d), d)
    cols = (np.arange(n_el)[:, None, None] * d + np.arange(d)[None, None, :]).repeat(d, axis=1).ravel()
    return sp.csr_matrix((inv.ravel(), (rows, cols)), shape=(n_el * d, n_el * d))


def reduced_matrix(Jy: sp.csr_matrix, Jz: sp.csr_matrix, damp_y: np.ndarray, damp_z: np.ndarray, d: int,
                   n_el: int) -> sp.csr_matrix:
    """``S = J_y^T J_y + diag(damp_y) - B^T C^-1 B`` with ``B = J_z^T J_y``, ``C = J_z^T J_z + diag(damp_z)``."""
    Cinv = _block_inverse(Jz, damp_z, d, n_el)
    B = (Jz.T @ Jy).tocsr()
    S = (Jy.T @ Jy).tocsr() + sp.diags(damp_y, format="csr") - (B.T @ (Cinv @ B)).tocsr()
    S.sum_duplicates()
    return S


def visits(Jy: sp.csr_matrix, element: np.ndarray, gap: int = VISIT_GAP_COLUMNS) -> np.ndarray:
    """Each row's visit, numbered from 0: the rows of one element sorted by their smallest ``J_y``
    column, a new visit wherever that column jumps by more than ``gap``; rows of no element get -1."""
    rows = np.flatnonzero(element >= 0)
    lo, hi = Jy.indptr[rows], Jy.indptr[rows + 1]
    first = np.full(rows.size, -1, dtype=np.int64)
    has = hi > lo
    first[has] = Jy.indices[lo[has]]
    order = np.lexsort((first, element[rows]))
    el, f = element[rows][order], first[order]
    new = np.ones(order.size, dtype=bool)
    new[1:] = (el[1:] != el[:-1]) | (f[1:] - f[:-1] > gap)
    out = np.full(element.size, -1, dtype=np.int64)
    out[rows[order]] = np.cumsum(new) - 1
    return out


def _regroup(Jz: sp.csr_matrix, element: np.ndarray, visit: np.ndarray, d: int) -> tuple[sp.csr_matrix, np.ndarray, int]:
    """``J_z`` with each row's columns moved from its element's to its visit's; the damping share per visit."""
    counts = np.diff(Jz.indptr)
    row_of = np.repeat(np.arange(Jz.shape[0]), counts)
    cols = visit[row_of] * d + Jz.indices % d
    n_v = int(visit.max()) + 1 if visit.size else 0
    Jv = sp.csr_matrix((Jz.data, cols, Jz.indptr), shape=(Jz.shape[0], n_v * d))
    el_of_visit = np.full(n_v, -1, dtype=np.int64)
    el_of_visit[visit[element >= 0]] = element[element >= 0]
    return Jv, el_of_visit, n_v


def schur_step(J: sp.csr_matrix, g: np.ndarray, D: np.ndarray, lam: float, split: SchurSplit, method: str,
               factorizer: SparseCholesky, tolerance: float = 1e-3, max_iterations: int = 1000,
               gap: int = VISIT_GAP_COLUMNS) -> SchurStep:
    """``(J^T J + lam D) delta = -g`` with the split's columns eliminated (see the module docstring)."""
    t = {}
    t0 = time.perf_counter()
    d, n_el = split.d, split.n_elements
    Jc = J.tocsc()
    Jy, Jz = Jc[:, split.keep].tocsr(), Jc[:, split.elim].tocsr()
    del Jc
    damp = lam * D
    damp_y, damp_z = damp[split.keep], damp[split.elim]
    g_y, g_z = g[split.keep], g[split.elim]
    Cinv = _block_inverse(Jz, damp_z, d, n_el)
    rhs = -g_y + Jy.T @ (Jz @ (Cinv @ g_z))
    t["split"] = time.perf_counter() - t0
    iterations, nnz = 0, 0

    def back(dy: np.ndarray) -> np.ndarray:
        dz = Cinv @ (-g_z - Jz.T @ (Jy @ dy))
        delta = np.empty(J.shape[1])
        delta[split.keep], delta[split.elim] = dy, dz
        return delta

    if method == "direct":
        t0 = time.perf_counter()
        S = reduced_matrix(Jy, Jz, damp_y, damp_z, d, n_el)
        nnz = S.nnz
        t["form"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        factor = factorizer.factorize(S, lower=False, check_pivots=False)
        dy = factor.solve(rhs)
        t["factorise"] = time.perf_counter() - t0
        return SchurStep(back(dy), method, 0, t, nnz)
    if method != "pcg":
        raise ValueError(f"unknown Schur method {method!r} (expected 'direct' or 'pcg')")
    t0 = time.perf_counter()
    element = _element_of_rows(Jz, d)
    visit = visits(Jy, element, gap)
    Jv, el_of_visit, n_v = _regroup(Jz, element, visit, d)
    share = np.bincount(el_of_visit, minlength=n_el).astype(float)
    damp_v = (damp_z.reshape(n_el, d)[el_of_visit] / share[el_of_visit, None]).ravel()
    M = reduced_matrix(Jy, Jv, damp_y, damp_v, d, n_v)
    nnz = M.nnz
    n_visits = n_v
    t["form"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    factor = factorizer.factorize(M, lower=False, check_pivots=False)
    t["factorise"] = time.perf_counter() - t0
    t0 = time.perf_counter()

    def S_times(v: np.ndarray) -> np.ndarray:
        u = Jy @ v
        w = Cinv @ (Jz.T @ u)
        return Jy.T @ (u - Jz @ w) + damp_y * v

    x = np.zeros_like(rhs)
    r = rhs.copy()
    z = factor.solve(r)
    rz = float(r @ z)
    stop = tolerance**2 * rz
    p = z.copy()
    ok = rz > 0.0
    while ok and rz > stop and iterations < max_iterations:
        iterations += 1
        q = S_times(p)
        pq = float(p @ q)
        if not pq > 0.0:
            ok = False
            break
        a = rz / pq
        x += a * p
        r -= a * q
        z = factor.solve(r)
        rz_new = float(r @ z)
        p *= rz_new / rz
        p += z
        rz = rz_new
    t["iterate"] = time.perf_counter() - t0
    if not ok or rz > stop:
        return SchurStep(None, method, iterations, t, nnz, n_visits)
    return SchurStep(back(x), method, iterations, t, nnz, n_visits)


def first_normal_system(project: Path, run: Path) -> tuple[dict, float]:
    """The normal system of the first Levenberg-Marquardt step of the run's last G/I/L problem at the
    truth, and the whole solve's time."""
    nav = load_navigation(project)
    features = read_features(run / "features" / "features.csv")
    objects = read_objects(run / "features" / "objects.csv")
    gil = build_gil_problem(nav, truth_start(nav, project), features, objects)
    saved: dict = {}
    solve_step = solver._solve_step

    def spy(run_, state):
        if not saved:
            n = state.normal
            saved.update(J=n.J.copy(), g=n.g.copy(), D=n.D.copy(), N_lower=n.N_lower().copy(),
                         planes=run_.layout.col_start["plane_params"].copy())
        return solve_step(run_, state)

    tcfg, lcfg = nav.config.processing.trajectory, nav.config.processing.lidar
    options = trajectory_solver_options(tcfg, function_tolerance=lcfg.function_tolerance,
                                        initial_lambda=lcfg.initial_lambda)
    solver._solve_step = spy
    try:
        t = time.perf_counter()
        solve_gnss_imu(gil.built, options, covariance=False)
        seconds = time.perf_counter() - t
    finally:
        solver._solve_step = solve_step
    return saved, seconds


def factor_nnz(factor) -> int:
    """Non-zeros of the factor's ``L`` (the factor is spent: it solves nothing afterwards)."""
    return int(factor.factor()[0].nnz)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("project", type=Path)
    ap.add_argument("run", type=Path)
    ap.add_argument("--lambdas", type=float, nargs="+", default=[1e-9, 1e-4])
    ap.add_argument("--gaps", type=int, nargs="+", default=[150, 1500])
    ap.add_argument("--tolerance", type=float, default=1e-3)
    ap.add_argument("--no-direct", action="store_true", help="Skip forming and factorising S itself.")
    a = ap.parse_args()
    system, solve_s = first_normal_system(a.project, a.run)
    J, g, D = system["J"], system["g"], system["D"]
    n = J.shape[1]
    split = split_columns(system["planes"], 3, n)
    print(f"{a.project.name}: {n:,} unknowns ({split.n_elements:,} objects, {split.elim.size:,} plane unknowns), "
          f"{J.shape[0]:,} rows, {J.nnz:,} non-zeros in J; the whole G/I/L solve {solve_s:.1f} s", flush=True)
    for lam in a.lambdas:
        A = system["N_lower"] + sp.diags(lam * D, format="csr")
        chol = SparseCholesky("auto")
        t = time.perf_counter()
        ref = chol.factorize(A, lower=True, check_pivots=False).solve(-g)
        first = time.perf_counter() - t
        t = time.perf_counter()
        factor = chol.factorize(A, lower=True, check_pivots=False)
        factor.solve(-g)
        refactor = time.perf_counter() - t
        print(f"lambda {lam:.0e}: the solver's factorisation ({factor.backend}): analysis + factorisation + solve "
              f"{first:.2f} s, again {refactor:.2f} s; {A.nnz:,} non-zeros in lower(N), {factor_nnz(factor):,} in L",
              flush=True)
        cases = [("pcg", gap) for gap in a.gaps] + ([] if a.no_direct else [("direct", 0)])
        for method, gap in cases:
            chol_s = SparseCholesky(factor.backend)
            t = time.perf_counter()
            try:
                st = schur_step(J, g, D, lam, split, method, chol_s, a.tolerance, gap=gap or VISIT_GAP_COLUMNS)
            except NotPositiveDefiniteError as exc:
                print(f"  {method}: {exc}")
                continue
            wall = time.perf_counter() - t
            err = float("nan")
            if st.delta is not None:
                err = float(np.linalg.norm(st.delta - ref) / np.linalg.norm(ref))
            what = "S" if method == "direct" else f"per-visit M (gap {gap} columns, {st.visits:,} visits)"
            phases = ", ".join(f"{k} {v:.2f}" for k, v in st.seconds.items())
            iters = f", {st.iterations} iterations" if method == "pcg" else ""
            print(f"  schur {method}: {wall:.2f} s ({wall / refactor:.1f}x the refactorisation){iters}; "
                  f"{st.nnz_reduced:,} non-zeros in {what}; |step - factorised| / |factorised| {err:.1e}; "
                  f"seconds: {phases}", flush=True)


if __name__ == "__main__":
    main()
