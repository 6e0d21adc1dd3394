"""Test helpers for observation groups: Jacobians against central finite differences.

Every observation model's tests call :func:`check_jacobians`, which perturbs each free element
of each named block *through the retraction* (``x + h e_k`` or ``R @ Exp(h e_k)``), so that
Jacobians of rotation blocks are checked with respect to the right perturbation of the
project convention.

Example
-------
>>> chk = check_jacobians(group, {"R": R, "p": p}, {"R": "so3", "p": "euclidean"})  # doctest: +SKIP
>>> assert chk.max_rel_error < 1e-6, chk                                             # doctest: +SKIP
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass

import numpy as np

from georefine.adjustment.blocks import ObservationGroup, ParameterBlock, retract

__all__ = ["JacobianCheck", "check_jacobians"]


@dataclass(frozen=True)
class JacobianCheck:
    """Result of :func:`check_jacobians`.

    Attributes
    ----------
    max_abs_error
        Largest ``|J_analytic - J_numeric|`` over all checked entries.
    max_rel_error
        Largest, over blocks, of the block's ``max |J_analytic - J_numeric|`` divided by
        ``max(max |J_numeric|, 1e-12)`` (relative to the block's Jacobian scale, which stays
        meaningful for entries that are exactly zero).
    blocks
        Per block ``(max_abs_error, max_rel_error)``.
    residual_mismatch
        ``max |r(jacobians=True) - r(jacobians=False)|``: both calls must agree.

    Unpacks as ``max_abs_error, max_rel_error``.
    """

    max_abs_error: float
    max_rel_error: float
    blocks: dict[str, tuple[float, float]]
    residual_mismatch: float

    def __iter__(self) -> Iterator[float]:
        return iter((self.max_abs_error, self.max_rel_error))


def check_jacobians(
    group: ObservationGroup,
    values: Mapping[str, np.ndarray],
    blocks: Mapping[str, str | ParameterBlock],
    eps: float = 1e-6,
    *,
    constant: Mapping[str, np.ndarray] | None = None,
    max_elements: int | None = None,
    seed: int = 0,
) -> JacobianCheck:
    """Compare a group's analytic Jacobian blocks with central differences on the manifold.

    Parameters
    ----------
    group
        The observation group.
    values
        Linearisation point: block name -> values, for every block the group reads.
    blocks
        Blocks to check: name -> manifold (``"euclidean"``/``"so3"``) or a
        :class:`ParameterBlock` (its manifold and constant mask are used; ``values`` wins
        for the values).
    eps
        Finite-difference step in tangent units (m, rad, ...).
    constant
        Optional constant masks per block; constant elements are not perturbed and their
        analytic entries are ignored (the solver drops them).
    max_elements
        Check at most this many randomly chosen free elements per block (speed on big groups).
    seed
        Seed for that choice.

    Returns
    -------
    JacobianCheck
        Errors overall and per block.
    """
    base = {k: np.asarray(v, dtype=float) for k, v in values.items()}
    lin = group.linearize(base, True)
    r0 = lin.residuals
    r_nojac = group.linearize(base, False).residuals
    mismatch = float(np.max(np.abs(r0 - r_nojac), initial=0.0)) if r_nojac.shape == r0.shape else np.inf
    rng = np.random.default_rng(seed)
    per_block: dict[str, tuple[float, float]] = {}
    for name, spec in blocks.items():
        manifold = spec.manifold if isinstance(spec, ParameterBlock) else str(spec)
        x = base[name]
        n = x.shape[0]
        d = 3 if manifold == "so3" else x.shape[1]
        const = np.zeros(n, dtype=bool)
        if isinstance(spec, ParameterBlock):
            const |= spec.constant
        if constant is not None and name in constant:
            const |= np.asarray(constant[name], dtype=bool)
        free = np.flatnonzero(~const)
        if max_elements is not None and free.size > max_elements:
            free = np.sort(rng.choice(free, size=max_elements, replace=False))
        analytic = np.zeros((r0.size, n, d))
        for jb in lin.jacobians:
            if jb.block != name:
                continue
            n_ent, m = jb.rows.shape
            rows = np.broadcast_to(jb.rows[:, :, None], (n_ent, m, d))
            els = np.broadcast_to(jb.elements[:, None, None], (n_ent, m, d))
            comp = np.broadcast_to(np.arange(d), (n_ent, m, d))
            np.add.at(analytic, (rows, els, comp), jb.values)
        numeric = np.zeros((r0.size, free.size, d))
        for j, e in enumerate(free):
            for k in range(d):
                step = np.zeros((1, d))
                step[0, k] = eps
                plus, minus = dict(base), dict(base)
                xp, xm = x.copy(), x.copy()
                xp[e] = retract(manifold, x[e : e + 1], step)[0]
                xm[e] = retract(manifold, x[e : e + 1], -step)[0]
                plus[name], minus[name] = xp, xm
                rp = group.linearize(plus, False).residuals
                rm = group.linearize(minus, False).residuals
                numeric[:, j, k] = (rp - rm) / (2.0 * eps)
        diff = np.abs(analytic[:, free, :] - numeric)
        abs_err = float(diff.max(initial=0.0))
        scale = max(float(np.abs(numeric).max(initial=0.0)), 1e-12)
        per_block[name] = (abs_err, abs_err / scale)
    max_abs = max((v[0] for v in per_block.values()), default=0.0)
    max_rel = max((v[1] for v in per_block.values()), default=0.0)
    return JacobianCheck(max_abs, max_rel, per_block, mismatch)
