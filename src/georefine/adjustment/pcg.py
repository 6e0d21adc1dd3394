"""The damped normal equations of one Levenberg-Marquardt step, and their solve by conjugate gradients.

:class:`NormalSystem` holds ``J``, ``g = J^T r`` and Marquardt's diagonal; ``N = J^T J`` is formed
only when a factorisation needs it. :func:`pcg_step` solves ``(N + lambda D) delta = -g`` with an
earlier iteration's factor as the preconditioner, multiplying by ``J`` and ``J^T`` instead of
forming ``N`` (:mod:`georefine.adjustment.solver` decides when, ``SolverOptions.reuse_factor_from``).
Written by hand: scipy's ``cg`` stops on the plain residual norm, this step on the preconditioned
one ``sqrt(r^T M^-1 r)`` (the measure its tolerance was set on), and it gives up on a
direction of non-positive curvature instead of going on.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from georefine.adjustment.assembly import NormalPattern, lower_triangle, normal_equations

__all__ = ["PCG_MAX_ITERATIONS", "PCG_STALE_ITERATIONS", "PCG_TOLERANCE", "NormalSystem", "pcg_step"]


@dataclass
class NormalSystem:
    """``J``, ``g = J^T r`` and Marquardt's ``D``; ``N = J^T J`` and its lower triangle formed when asked for.

    With ``pattern`` (the :class:`~georefine.adjustment.assembly.NormalPattern` of ``J``'s
    structure, kept by the solve's assembler) the lower triangle is filled into its fixed
    pattern, and the damped matrices share that pattern; without it SciPy forms ``N``.
    """

    J: sp.csr_matrix
    g: np.ndarray
    diag: np.ndarray  # diag(J^T J)
    D: np.ndarray
    seconds: float
    _N: sp.csr_matrix | None = None
    _N_lower: sp.csr_matrix | None = None
    pattern: NormalPattern | None = None

    def N(self) -> sp.csr_matrix:
        """The full symmetric ``N`` (CSR)."""
        if self._N is None:
            t0 = time.perf_counter()
            if self.pattern is not None or self._N_lower is not None:
                L = self.N_lower()
                self._N = (L + sp.triu(L.T, k=1, format="csr")).tocsr()
            else:
                self._N, _ = normal_equations(self.J, np.zeros(self.J.shape[0]))
            self.seconds += time.perf_counter() - t0
        return self._N

    def N_lower(self) -> sp.csr_matrix:
        """The lower triangle of ``N`` with the diagonal (CSR)."""
        if self._N_lower is None:
            if self.pattern is not None:
                self._N_lower = self.pattern.lower(self.J)
            else:
                self._N_lower = lower_triangle(self.N())
        return self._N_lower

    def damped_lower(self, lam: float) -> sp.csr_matrix:
        """The lower triangle of ``N + lam D`` (in ``N``'s pattern where there is one)."""
        L = self.N_lower()
        if self.pattern is None:
            return L + sp.diags(lam * self.D, format="csr")
        data = L.data.copy()
        data[self.pattern.diagonal] += lam * self.D
        A = sp.csr_matrix((data, L.indices, L.indptr), shape=L.shape, copy=False)
        A.has_sorted_indices = True
        A.has_canonical_format = True
        return A


PCG_TOLERANCE = 1e-3
"""Conjugate-gradient steps stop when the preconditioned residual norm ``sqrt(r^T M^-1 r)`` has
fallen to this fraction of the right-hand side's. An inexact step is still judged by its gain
ratio against the Gauss-Newton model; on the last outer iteration of a 60-minute G/I/L
adjustment (712,317 unknowns) 1e-3 ended 0.0008 mdeg RMS (0.0017 mdeg at most) from the
solution by factorisations alone, at the same cost to 6 digits."""

PCG_MAX_ITERATIONS = 25
"""A step whose conjugate gradients need more is solved by a fresh factorisation instead. One
iteration (a solve with the factor, a product with ``J`` and ``J^T``) took 0.55 s on that G/I/L
matrix, a factorisation with ``N`` formed 20 s: 25 iterations stay below it."""

PCG_STALE_ITERATIONS = PCG_MAX_ITERATIONS // 2
"""After a step whose conjugate gradients needed more than this, the next step is factorised
without trying them: the factor ages with every step (other weights, another linearisation
point), and on the first G/I/L outer iterations of the 60-minute and 10-minute flights every
step after one of 15 to 25 iterations failed to converge in 25 (three such attempts of about
10 s each on the 60-minute flight, two on the 10-minute one)."""


def pcg_step(normal: NormalSystem, lam: float, factor) -> tuple[np.ndarray | None, int]:
    """``(N + lambda D) delta = -g`` by conjugate gradients preconditioned with an earlier factor.

    The factor is that of an earlier iteration's ``N' + lambda' D'``: the same observations
    with other robust weights, another linearisation point and another damping. Were only the
    weights and the damping different, the generalised eigenvalues against the current matrix
    would lie between the smallest and largest ratios of the row weights and dampings; the new
    linearisation point adds to that. Measured on the 60-minute G/I/L: 8 to 24 iterations, and
    one step that did not converge in 25 right after the first factorisation. ``N`` itself is
    never formed: each iteration multiplies by ``J`` and ``J^T`` (``J``'s non-zeros are a
    fraction of ``N``'s and of the factor's). Returns ``(None, iterations)`` when the tolerance
    is not reached within :data:`PCG_MAX_ITERATIONS`.
    """
    J, damp = normal.J, lam * normal.D
    b = -normal.g
    x = np.zeros_like(b)
    r = b.copy()
    z = factor.solve(r)
    rz = float(r @ z)
    if not rz > 0.0:
        return (x if rz == 0.0 else None), 0
    stop = PCG_TOLERANCE**2 * rz
    p = z.copy()
    for k in range(1, PCG_MAX_ITERATIONS + 1):
        q = J.T @ (J @ p) + damp * p
        pq = float(p @ q)
        if not pq > 0.0:
            return None, k
        a = rz / pq
        x += a * p
        r -= a * q
        z = factor.solve(r)
        rz_new = float(r @ z)
        if not np.isfinite(rz_new):
            return None, k
        if rz_new <= stop:
            return x, k
        p *= rz_new / rz
        p += z
        rz = rz_new
    return None, PCG_MAX_ITERATIONS
