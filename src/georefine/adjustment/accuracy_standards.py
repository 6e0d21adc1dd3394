"""Accuracy in the forms clients ask for: ASPRS Positional Accuracy Standards (Edition 2, 2023)
and the NSSDA (FGDC-STD-007.3-1998), from check points or reference surfaces.

**ASPRS Edition 2.** Against independent check points:

* ``RMSE_H1 = sqrt(RMSE_x^2 + RMSE_y^2)`` and ``RMSE_V1 = RMSE_z`` of the product;
* the check points' own survey accuracy is included: ``RMSE_H = sqrt(RMSE_H1^2 + RMSE_H2^2)``,
  ``RMSE_V = sqrt(RMSE_V1^2 + RMSE_V2^2)`` with ``RMSE_H2``, ``RMSE_V2`` the survey's (here the
  RMS of the check points' stated sigmas, 0 where none is stated);
* ``RMSE_3D = sqrt(RMSE_H^2 + RMSE_V^2)``;
* the data meet the "X-cm horizontal accuracy class" for any ``X >= RMSE_H`` and, for
  elevation data, the "X-cm vertical accuracy class" for ``X >= RMSE_V`` in non-vegetated terrain
  (NVA); Edition 2 drops the 95 % figures and the vegetated pass/fail;
* at least 30 check points (at most 120 are required for large projects): fewer are reported as
  too few to claim a class.

**NSSDA** (the 95 % figures that Edition 2 dropped but many contracts still quote):
``Accuracy_r = 1.7308 RMSE_r`` when ``RMSE_x`` and ``RMSE_y`` are within a ratio 0.6-1.0, else
the circular approximation ``2.4477 * (RMSE_x + RMSE_y) / 2``; ``Accuracy_z = 1.9600 RMSE_z``.

**Reference surfaces as vertical check points.** Each surveyed plane whose slope is at most 10 %
(Edition 2's terrain for vertical check points) gives one vertical error: the mean over the
views that see it of the points' mean distance along the plane's normal, divided by the normal's
vertical component. Its survey term is the plane's fit residual over the square root of its
surveyed points (a plane surveyed from many points is known better than any one of them).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["ASPRS_MIN_CHECKPOINTS", "MAX_SLOPE_VERTICAL", "PositionalAccuracy", "positional_accuracy",
           "surface_vertical_errors"]

ASPRS_MIN_CHECKPOINTS = 30
MAX_SLOPE_VERTICAL = 0.10  # rise over run: Edition 2's terrain for vertical check points
_NSSDA_R_EQUAL = 1.7308  # 95 % radial, RMSE_x = RMSE_y
_NSSDA_R_CIRCULAR = 2.4477  # 95 % radial, circular approximation
_NSSDA_Z = 1.9600  # 95 % vertical


def _num(value: Any) -> float | None:
    return None if value is None else float(value)


@dataclass(frozen=True)
class PositionalAccuracy:
    """ASPRS 2023 and NSSDA figures of one product against ``n`` check points (module docstring).

    Horizontal fields are ``None`` for a vertical-only test (reference surfaces). Lengths in metres.
    """

    n_checkpoints: int
    rmse_v1_m: float | None  # the product's RMSE_z against the check points
    rmse_v2_m: float  # the check points' survey accuracy, vertical
    rmse_v_m: float | None  # ASPRS Edition 2's RMSE_V (survey included): the NVA
    mean_v_m: float | None  # mean vertical error (a bias the RMSE hides)
    nssda_vertical_95_m: float | None
    rmse_h1_m: float | None = None
    rmse_h2_m: float | None = None
    rmse_h_m: float | None = None  # ASPRS Edition 2's RMSE_H (survey included)
    rmse_3d_m: float | None = None
    nssda_horizontal_95_m: float | None = None
    nssda_rule: str | None = None  # which NSSDA horizontal formula applied

    @property
    def enough_checkpoints(self) -> bool:
        """Whether ASPRS Edition 2's minimum of 30 check points is met."""
        return self.n_checkpoints >= ASPRS_MIN_CHECKPOINTS

    def to_dict(self) -> dict[str, Any]:
        return {"standard": "ASPRS Positional Accuracy Standards, Edition 2 (2023); NSSDA 95 %",
                "n_checkpoints": self.n_checkpoints, "enough_checkpoints": self.enough_checkpoints,
                "rmse_h1_m": self.rmse_h1_m, "rmse_h2_m": self.rmse_h2_m, "rmse_h_m": self.rmse_h_m,
                "rmse_v1_m": self.rmse_v1_m, "rmse_v2_m": self.rmse_v2_m, "rmse_v_m": self.rmse_v_m,
                "mean_v_m": self.mean_v_m, "rmse_3d_m": self.rmse_3d_m,
                "nssda_horizontal_95_m": self.nssda_horizontal_95_m, "nssda_rule": self.nssda_rule,
                "nssda_vertical_95_m": self.nssda_vertical_95_m}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PositionalAccuracy:
        return cls(int(d["n_checkpoints"]), _num(d["rmse_v1_m"]), float(d["rmse_v2_m"]), _num(d["rmse_v_m"]),
                   _num(d["mean_v_m"]), _num(d["nssda_vertical_95_m"]), _num(d.get("rmse_h1_m")),
                   _num(d.get("rmse_h2_m")), _num(d.get("rmse_h_m")), _num(d.get("rmse_3d_m")),
                   _num(d.get("nssda_horizontal_95_m")), d.get("nssda_rule"))


def positional_accuracy(errors_m: np.ndarray, survey_sigma_m: np.ndarray | None = None) -> PositionalAccuracy:
    """ASPRS 2023 and NSSDA figures from check point errors.

    Parameters
    ----------
    errors_m
        ``(n, 3)`` product minus check point (x, y, z), or ``(n,)`` vertical errors only.
    survey_sigma_m
        The check points' stated survey sigma, ``(n, 3)`` (or ``(n,)`` vertical); None: 0.
    """
    e = np.asarray(errors_m, dtype=float)
    vertical_only = e.ndim == 1
    e3 = e[:, None] if vertical_only else e
    n = int(e3.shape[0])
    if survey_sigma_m is None:
        s3 = np.zeros_like(e3)
    else:
        s3 = np.asarray(survey_sigma_m, dtype=float).reshape(e3.shape)
    if n == 0:
        return PositionalAccuracy(0, None, 0.0, None, None, None)
    rms = np.sqrt(np.mean(e3 * e3, axis=0))
    survey = np.sqrt(np.mean(s3 * s3, axis=0))
    rmse_v1, rmse_v2 = float(rms[-1]), float(survey[-1])
    rmse_v = math.hypot(rmse_v1, rmse_v2)
    mean_v = float(np.mean(e3[:, -1]))
    if vertical_only:
        return PositionalAccuracy(n, rmse_v1, rmse_v2, rmse_v, mean_v, _NSSDA_Z * rmse_v1)
    rx, ry = float(rms[0]), float(rms[1])
    rmse_h1 = math.hypot(rx, ry)
    rmse_h2 = math.hypot(float(survey[0]), float(survey[1]))
    rmse_h = math.hypot(rmse_h1, rmse_h2)
    low, high = min(rx, ry), max(rx, ry)
    if high == 0.0 or low / high >= 0.6:
        nssda_h, rule = _NSSDA_R_EQUAL * rmse_h1, "1.7308 RMSE_r (RMSE_x and RMSE_y within 0.6-1.0)"
    else:
        nssda_h, rule = _NSSDA_R_CIRCULAR * 0.5 * (rx + ry), "2.4477 (RMSE_x + RMSE_y) / 2 (circular approximation)"
    return PositionalAccuracy(n, rmse_v1, rmse_v2, rmse_v, mean_v, _NSSDA_Z * rmse_v1, rmse_h1, rmse_h2, rmse_h,
                              math.hypot(rmse_h, rmse_v), nssda_h, rule)


def surface_vertical_errors(observations: Iterable, planes: Sequence, max_slope: float = MAX_SLOPE_VERTICAL
                            ) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Vertical errors of the reference surfaces that may serve as vertical check points.

    ``observations``: :class:`~georefine.evaluation.reference_planes.PlaneObservation` (one per
    view and surface: the mean signed distance along the normal); ``planes``: the
    :class:`~georefine.evaluation.reference_planes.ReferencePlane` list. Returns the vertical
    error per surface (the views' mean distance over the normal's vertical component), its
    survey sigma (fit residual over the square root of the surveyed points, at least 3)
    and the surface ids, for the surfaces no steeper than ``max_slope`` that some view saw.
    """
    by_id = {p.surface_id: p for p in planes}
    distances: dict[str, list[float]] = {}
    for o in observations:
        distances.setdefault(o.surface_id, []).append(o.mean_m)
    errors, sigmas, ids = [], [], []
    for sid, values in distances.items():
        plane = by_id.get(sid)
        if plane is None:
            continue
        nz = float(plane.normal[2])
        if nz <= 0.0 or math.sqrt(max(0.0, 1.0 - nz * nz)) / nz > max_slope:
            continue
        errors.append(float(np.mean(values)) / nz)
        sigmas.append(float(plane.rms_survey_m) / math.sqrt(max(plane.n_survey_points, 3)))
        ids.append(sid)
    return np.array(errors, dtype=float), np.array(sigmas, dtype=float), ids
