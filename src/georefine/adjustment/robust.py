"""Robust loss functions for the least-squares adjustment (M-estimators).

A loss acts on the squared norm ``s = ||r_i||^2`` of one *observation*'s whitened residual
rows ``r_i`` (one GNSS epoch is one observation of three rows, one plane correspondence one
observation of three rows, ...). The adjustment minimises ``F = 1/2 sum_i rho(s_i)``;
plain least squares is ``rho(s) = s``.

Every loss returns ``rho(s)`` and its derivative ``rho'(s)``. The solver
(:mod:`georefine.adjustment.solver`) uses iteratively reweighted least squares: the rows of
observation ``i`` are scaled by ``sqrt(rho'(s_i))``, which gives the exact gradient of ``F``
and the first-order (Gauss-Newton) Hessian ``sum_i rho'(s_i) J_i^T J_i``. The second-order
term of Triggs et al. (2000, Eq. 11) is omitted: for the losses here ``rho'' <= 0``, where it
could make the normal matrix indefinite, and Ceres Solver drops it in exactly that case too.

Scales are in units of the whitened residual, i.e. in multiples of the a-priori standard
deviation: ``HuberLoss(delta=2.0)`` treats observations whose residual norm exceeds 2 sigma
as suspicious.

References
----------
Huber, P. J. (1964): Robust estimation of a location parameter. Ann. Math. Statist. 35.
Triggs, B., McLauchlan, P., Hartley, R., Fitzgibbon, A. (2000): Bundle adjustment - a modern
synthesis. Vision Algorithms: Theory and Practice, LNCS 1883, §6.8.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

__all__ = [
    "RobustLoss",
    "TrivialLoss",
    "HuberLoss",
    "CauchyLoss",
    "make_loss",
    "IRLSWeights",
    "irls_weights",
    "downweight_threshold",
]


@runtime_checkable
class RobustLoss(Protocol):
    """A robust loss ``rho(s)`` of the squared residual norm ``s >= 0`` of one observation.

    Conventions: ``rho(0) = 0``, ``rho'(0) = 1`` (near zero the loss is least squares) and
    ``rho'(s) > 0``, so that ``sqrt(rho'(s))`` is a valid IRLS row weight.
    """

    name: str

    def evaluate(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return ``rho(s)`` and ``rho'(s)``, both with the shape of ``s``."""
        ...


@dataclass(frozen=True)
class TrivialLoss:
    """Plain least squares: ``rho(s) = s``, ``rho'(s) = 1``."""

    name: str = "trivial"

    def evaluate(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return ``(s, 1)``."""
        s = np.asarray(s, dtype=float)
        return s.copy(), np.ones_like(s)


@dataclass(frozen=True)
class HuberLoss:
    """Huber loss with threshold ``delta`` (whitened units, i.e. in sigma).

    ``rho(s) = s`` for ``s <= delta^2``, else ``2 delta sqrt(s) - delta^2``;
    ``rho'(s) = min(1, delta / sqrt(s))``. Quadratic for small residuals, linear (L1-like)
    for large ones; convex, so it cannot introduce local minima. ``delta = 1.345`` gives 95 %
    efficiency for Gaussian scalar residuals.
    """

    delta: float = 1.345
    name: str = "huber"

    def __post_init__(self) -> None:
        if not np.isfinite(self.delta) or self.delta <= 0:
            raise ValueError(f"HuberLoss: delta must be positive and finite, found {self.delta}")

    def evaluate(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return ``rho(s)`` and ``rho'(s)`` of the Huber loss."""
        s = np.asarray(s, dtype=float)
        d2 = self.delta * self.delta
        root = np.sqrt(np.maximum(s, d2))
        outlier = s > d2
        rho = np.where(outlier, 2.0 * self.delta * root - d2, s)
        drho = np.where(outlier, self.delta / root, 1.0)
        return rho, drho


@dataclass(frozen=True)
class CauchyLoss:
    """Cauchy (Lorentzian) loss with scale ``c`` (whitened units).

    ``rho(s) = c^2 log(1 + s / c^2)``, ``rho'(s) = 1 / (1 + s / c^2)``. Redescending
    influence: gross errors get almost no weight, at the price of non-convexity (start close
    enough). ``c = 2.3849`` gives 95 % efficiency for Gaussian scalar residuals.
    """

    c: float = 2.3849
    name: str = "cauchy"

    def __post_init__(self) -> None:
        if not np.isfinite(self.c) or self.c <= 0:
            raise ValueError(f"CauchyLoss: c must be positive and finite, found {self.c}")

    def evaluate(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return ``rho(s)`` and ``rho'(s)`` of the Cauchy loss."""
        s = np.asarray(s, dtype=float)
        c2 = self.c * self.c
        u = s / c2
        return c2 * np.log1p(u), 1.0 / (1.0 + u)


def make_loss(name: str | None, scale: float | None = None) -> RobustLoss | None:
    """Loss from a configuration name: ``"none"``/``None`` (plain LS), ``"trivial"``,
    ``"huber"`` or ``"cauchy"``; ``scale`` is Huber's ``delta`` or Cauchy's ``c`` (sigma units),
    the loss's default when ``None``.
    """
    key = "none" if name is None else name.strip().lower()
    if key == "none":
        return None
    if key == "trivial":
        return TrivialLoss()
    if key == "huber":
        return HuberLoss() if scale is None else HuberLoss(delta=float(scale))
    if key == "cauchy":
        return CauchyLoss() if scale is None else CauchyLoss(c=float(scale))
    raise ValueError(f"unknown robust loss {name!r} (expected none, trivial, huber or cauchy)")


@dataclass(frozen=True)
class IRLSWeights:
    """Robust weighting of one group's residual rows.

    Attributes
    ----------
    s
        ``(K,)`` squared norm of each observation present (dense re-numbering).
    weight
        ``(K,)`` ``rho'(s)`` (ones for plain least squares).
    row_sqrt_weight
        ``(M,)`` ``sqrt(rho'(s))`` of each row's observation, ``None`` for plain least squares.
    cost
        ``1/2 sum rho(s)``.
    sum_s, sum_ws
        ``sum s`` and ``sum rho'(s) s``.
    """

    s: np.ndarray
    weight: np.ndarray
    row_sqrt_weight: np.ndarray | None
    cost: float
    sum_s: float
    sum_ws: float


def irls_weights(loss: RobustLoss | None, observation: np.ndarray, residuals: np.ndarray) -> IRLSWeights:
    """Per-observation squared norms, robust cost and IRLS row weights.

    Parameters
    ----------
    loss
        Robust loss, ``None`` for plain least squares.
    observation
        ``(M,)`` int >= 0: observation of every row (any numbering).
    residuals
        ``(M,)`` whitened residuals.
    """
    with np.errstate(over="ignore"):  # a wild trial step may overflow: cost inf, step rejected
        r2 = residuals * residuals
    obs = np.asarray(observation)
    if obs.size and obs.max() > 4 * obs.size + 1024:  # sparse ids: compress first
        _, obs = np.unique(obs, return_inverse=True)
    counts = np.bincount(obs) if obs.size else np.zeros(0, dtype=np.int64)
    s = np.bincount(obs, weights=r2, minlength=counts.size) if obs.size else np.zeros(0)
    used = counts > 0
    if not np.all(used):
        s, obs = s[used], (np.cumsum(used) - 1)[obs]
    sum_s = float(np.sum(s))
    if loss is None:
        return IRLSWeights(s, np.ones_like(s), None, 0.5 * sum_s, sum_s, sum_s)
    rho, weight = loss.evaluate(s)
    return IRLSWeights(s, weight, np.sqrt(weight)[obs], 0.5 * float(np.sum(rho)), sum_s, float(np.sum(weight * s)))


def downweight_threshold(loss: RobustLoss | None, weight: float = 0.5) -> float | None:
    """The squared norm ``s`` beyond which ``loss`` weights an observation below ``weight``
    (``rho'(s) = weight``; Cauchy: ``c^2``, Huber: ``4 delta^2`` for 0.5), or None where it never
    does (plain least squares). Found by bisection: ``rho'`` falls monotonically."""
    if loss is None or float(loss.evaluate(np.array([1e12]))[1][0]) >= weight:
        return None
    lo, hi = 0.0, 1.0
    while float(loss.evaluate(np.array([hi]))[1][0]) >= weight:
        lo, hi = hi, hi * 4.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if float(loss.evaluate(np.array([mid]))[1][0]) >= weight:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)
