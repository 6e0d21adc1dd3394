"""Estimated IMU errors and boresight against the simulated truth (``PROJECT/truth``).

The adjustments write their IMU error model into ``adjustment.json``
(:class:`~georefine.io.run_metrics.AdjustmentReport`; ``imu_errors``: scale
factors with sigma, piecewise-linear biases at ``bias_knot_times_s`` after ``t0_gps`` with sigma)
and, where estimated, the boresight (``boresight_deg``, ``boresight_sigma_mdeg``). The simulator
keeps what it applied (``truth/imu_errors.npz``: per-sample biases in rad/s and m/s^2, scale
factors, each triad's misalignment matrix; ``truth/scenario.yaml``: ``scenario.boresight_deg``). Both
use the sensor model ``raw = (I + S + A) true + b``.

Figures per solution: every scale factor estimated, true and its sigma; where estimated, every
misalignment element (xy, xz, yx, yz, zx, zy) the same way; the biases' RMS error over the knots
against their RMS sigma (about 1 when the sigmas are honest); the boresight's error.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from georefine.io.run_metrics import AdjustmentReport

__all__ = ["BoresightFigures", "ImuErrorFigures", "boresight_figures", "imu_error_figures", "plot_imu_errors"]

G0 = 9.80665  # m/s^2 per g
_DEG_PER_H = 180.0 / math.pi * 3600.0  # rad/s -> deg/h
_UG = 1e6 / G0  # m/s^2 -> micro-g


def _triple(v) -> tuple[float, float, float]:
    return tuple(float("nan") if x is None else float(x) for x in v)  # type: ignore[return-value]


def _list(v) -> list[float | None] | None:
    return None if v is None else [None if not math.isfinite(x) else float(x) for x in v]


MISALIGNMENT_ELEMENTS = ("xy", "xz", "yx", "yz", "zx", "zy")
"""Row and column axes of the six misalignment elements, in the adjustment's order."""


@dataclass(frozen=True)
class ImuErrorFigures:
    """One solution's IMU errors against the truth (units in the field names; x, y, z)."""

    acc_scale_ppm: tuple[float, float, float]
    acc_scale_true_ppm: tuple[float, float, float]
    acc_scale_sigma_ppm: tuple[float, float, float]
    gyro_scale_ppm: tuple[float, float, float]
    gyro_scale_true_ppm: tuple[float, float, float]
    gyro_scale_sigma_ppm: tuple[float, float, float]
    acc_bias_rms_error_ug: tuple[float, float, float]
    acc_bias_rms_sigma_ug: tuple[float, float, float]
    gyro_bias_rms_error_deg_per_h: tuple[float, float, float]
    gyro_bias_rms_sigma_deg_per_h: tuple[float, float, float]
    acc_misalignment_mrad: tuple[float, ...] | None = None  # MISALIGNMENT_ELEMENTS; None: not estimated
    acc_misalignment_true_mrad: tuple[float, ...] | None = None
    acc_misalignment_sigma_mrad: tuple[float, ...] | None = None
    gyro_misalignment_mrad: tuple[float, ...] | None = None
    gyro_misalignment_true_mrad: tuple[float, ...] | None = None
    gyro_misalignment_sigma_mrad: tuple[float, ...] | None = None

    def to_dict(self) -> dict[str, Any]:
        return {k: _list(v) for k, v in self.__dict__.items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ImuErrorFigures:
        return cls(**{k: _triple(d[k]) if f.default is dataclasses.MISSING or d.get(k) is not None else None
                      for k, f in cls.__dataclass_fields__.items()})


@dataclass(frozen=True)
class BoresightFigures:
    """The estimated boresight (roll, pitch, yaw) against the truth and the project's start value."""

    estimated_deg: tuple[float, float, float]
    sigma_mdeg: tuple[float, float, float]
    true_deg: tuple[float, float, float]
    stated_deg: tuple[float, float, float]  # project.yaml's, where the adjustment started

    @property
    def error_mdeg(self) -> tuple[float, float, float]:
        return tuple(1e3 * (e - t) for e, t in zip(self.estimated_deg, self.true_deg))  # type: ignore[return-value]

    def to_dict(self) -> dict[str, Any]:
        return {"estimated_deg": _list(self.estimated_deg), "sigma_mdeg": _list(self.sigma_mdeg),
                "true_deg": _list(self.true_deg), "stated_deg": _list(self.stated_deg),
                "error_mdeg": _list(self.error_mdeg)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> BoresightFigures:
        return cls(_triple(d["estimated_deg"]), _triple(d["sigma_mdeg"]), _triple(d["true_deg"]),
                   _triple(d["stated_deg"]))


def _true_biases(truth: dict[str, np.ndarray], times_gps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The true accelerometer (micro-g) and gyro (deg/h) biases at ``times_gps``, ``(K, 3)`` each."""
    t = truth["time_gps"]
    acc = np.column_stack([np.interp(times_gps, t, truth["bias_acc"][:, i]) for i in range(3)]) * _UG
    gyro = np.column_stack([np.interp(times_gps, t, truth["bias_gyro"][:, i]) for i in range(3)]) * _DEG_PER_H
    return acc, gyro


def _temperature_part(e: dict, times_gps: np.ndarray, truth: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The estimated biases' temperature part ``k (T - T_first)`` at ``times_gps`` (micro-g and deg/h, ``(K, 3)``,
    keyed as the biases in ``imu_errors`` ``e``), at the truth's temperature change (the file's ``T - T_first``);
    empty where the coefficients were not estimated. The biases on the knots are then the walk's part only."""
    if e.get("gyro_temperature_deg_per_h_per_c") is None or "temperature_c" not in truth:
        return {}
    d_t = np.interp(times_gps, truth["time_gps"], truth["temperature_c"])[:, None]
    return {"gyro_bias_deg_per_h": d_t * np.asarray(e["gyro_temperature_deg_per_h_per_c"], dtype=float),
            "acc_bias_ug": d_t * np.asarray(e["acc_temperature_ug_per_c"], dtype=float)}


def imu_error_figures(adjustment: AdjustmentReport, truth_npz: Path) -> ImuErrorFigures | None:
    """Figures of one ``adjustment.json`` (its ``imu_errors`` and ``t0_gps``) against ``truth_npz``;
    None where either has no IMU errors."""
    e = adjustment.imu_errors or {}
    if not e or not Path(truth_npz).is_file() or not e.get("bias_knot_times_s"):
        return None
    with np.load(truth_npz) as z:
        truth = {k: np.asarray(z[k]) for k in z.files}
    times = float(adjustment.t0_gps) + np.asarray(e["bias_knot_times_s"], dtype=float)
    inside = (times >= truth["time_gps"][0]) & (times <= truth["time_gps"][-1])
    acc_true, gyro_true = _true_biases(truth, times[inside])

    def rms(a: np.ndarray) -> tuple[float, float, float]:
        return tuple(np.sqrt(np.mean(np.asarray(a, dtype=float) ** 2, axis=0)))  # type: ignore[return-value]

    temp_part = _temperature_part(e, times[inside], truth)

    def est(name: str) -> np.ndarray:
        return np.asarray(e[name], dtype=float)[inside] + temp_part.get(name, 0.0)

    nan3 = (math.nan,) * 3
    off = ~np.eye(3, dtype=bool)
    misalignment = {}
    for triad in ("acc", "gyro"):
        if e.get(f"{triad}_misalignment_mrad") is not None:
            true = truth.get(f"misalignment_{triad}", np.zeros((3, 3)))[off] * 1e3
            misalignment |= {f"{triad}_misalignment_mrad": _triple(e[f"{triad}_misalignment_mrad"]),
                             f"{triad}_misalignment_true_mrad": _triple(true),
                             f"{triad}_misalignment_sigma_mrad": _triple(e.get(f"{triad}_misalignment_sigma_mrad")
                                                                         or (math.nan,) * 6)}
    return ImuErrorFigures(
        _triple(e.get("acc_scale_ppm", nan3)), _triple(1e6 * truth["scale_acc"]), _triple(e.get("acc_scale_sigma_ppm", nan3)),
        _triple(e.get("gyro_scale_ppm", nan3)), _triple(1e6 * truth["scale_gyro"]),
        _triple(e.get("gyro_scale_sigma_ppm", nan3)),
        rms(est("acc_bias_ug") - acc_true), rms(est("acc_bias_sigma_ug")),
        rms(est("gyro_bias_deg_per_h") - gyro_true), rms(est("gyro_bias_sigma_deg_per_h")), **misalignment,
    )


def boresight_figures(adjustment: AdjustmentReport, true_deg, stated_deg) -> BoresightFigures | None:
    """The boresight of ``adjustment.json`` against ``true_deg``; None where it was not estimated."""
    b = adjustment.boresight_deg
    if b is None:
        return None
    sigma = adjustment.boresight_sigma_mdeg or (math.nan,) * 3
    return BoresightFigures(_triple(b), _triple(sigma), _triple(true_deg), _triple(stated_deg))


def plot_imu_errors(adjustments: dict[str, AdjustmentReport], truth_npz: Path, path: Path) -> Path:
    """Estimated biases (with their 2-sigma band) of each solution against the true ones over
    time: accelerometer (micro-g) and gyro (deg/h), x, y, z."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from georefine.evaluation.figures import save_png

    with np.load(truth_npz) as z:
        truth = {k: np.asarray(z[k]) for k in z.files}
    t0 = min(float(a.t0_gps) for a in adjustments.values())
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5), sharex=True, constrained_layout=True)
    tt = truth["time_gps"][:: max(1, truth["time_gps"].size // 4000)]
    acc_true, gyro_true = _true_biases(truth, tt)
    for row, (key, true, unit) in enumerate((("acc_bias_ug", acc_true, "µg"), ("gyro_bias_deg_per_h", gyro_true,
                                                                                 "deg/h"))):
        for i, axis in enumerate("xyz"):
            ax = axes[row, i]
            ax.plot(tt - t0, true[:, i], color="black", lw=1.2, label="truth")
            for (label, adj), colour in zip(adjustments.items(), ("tab:orange", "tab:blue", "tab:green")):
                e = adj.imu_errors or {}
                if key not in e:
                    continue
                t = float(adj.t0_gps) + np.asarray(e["bias_knot_times_s"]) - t0
                part = _temperature_part(e, t + t0, truth).get(key, np.zeros((t.size, 3)))
                v, s = np.asarray(e[key])[:, i] + part[:, i], np.asarray(e[key.replace("_bias_", "_bias_sigma_")])[:, i]
                ax.plot(t, v, color=colour, lw=1.0, label=label)
                ax.fill_between(t, v - 2 * s, v + 2 * s, color=colour, alpha=0.15, lw=0)
            ax.set_title(f"{'accelerometer' if row == 0 else 'gyro'} bias {axis} ({unit})", fontsize=10)
            ax.grid(alpha=0.3)
            if row == 1:
                ax.set_xlabel("time since start (s)")
    axes[0, 0].legend(fontsize=8, loc="best")
    fig.suptitle("Estimated IMU biases (±2σ bands) against the simulated truth", fontsize=11)
    save_png(fig, path, 110)
    plt.close(fig)
    return path
