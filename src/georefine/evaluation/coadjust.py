"""Evaluation of a lidargrammetric co-adjustment against the simulation's truth (paper 004).

The refined strips keep the input's point order (:mod:`georefine.lidargrammetry.reintersect`),
as the simulator's ``truth/strip_N.laz`` keeps the scan's: the error of every point is its
difference to the same record of the truth. :func:`cloud_errors` compares the jammed input and
the refined output over the points inside the photo block (those the re-intersection moved:
extra dimension ``lidargrams >= 0``); :func:`plot_cloud_errors` maps both.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np

from georefine.errors import InputError

__all__ = ["CloudErrors", "CloudErrorSummary", "cloud_errors", "plot_cloud_errors", "PAPER_004_GRAZ", "PAPER_004_LOOSDORF"]

#: Paper 004, Graz block (5 cm GSD), Tables 1-3: RMSE X/Y/Z (m) and reprojection error (px).
PAPER_004_GRAZ = {
    1: {"control_points": (0.079, 0.059, 0.126, 0.459), "check_points": (0.031, 0.040, 0.113, 0.335)},
    2: {"control_points": (0.077, 0.051, 0.084, 0.448), "check_points": (0.012, 0.028, 0.111, 0.335)},
    3: {"control_points": None, "check_points": (0.077, 0.043, 0.211, 0.375)},
}

#: Paper 004, Loosdorf strip (8 cm GSD), Tables 4-6.
PAPER_004_LOOSDORF = {
    1: {"control_points": (0.044, 0.138, 0.074, 0.131), "check_points": (0.044, 0.090, 0.070, 0.229)},
    2: {"control_points": (0.001, 0.002, 0.005, 0.131), "check_points": (0.002, 0.002, 0.005, 0.229)},
    3: {"control_points": None, "check_points": (0.022, 0.022, 0.033, 0.219)},
}


def _float(value) -> float:
    return float("nan") if value is None else float(value)  # NaN is written to JSON as null


@dataclass(frozen=True)
class CloudErrorSummary:
    """RMS and largest 3-D error (m) of the points inside the block, jammed and refined; ``ratio``: refined / jammed RMS."""

    points: int
    rms_before_m: float
    rms_after_m: float
    ratio: float
    rms_xyz_before_m: tuple[float, float, float]
    rms_xyz_after_m: tuple[float, float, float]
    max_before_m: float
    max_after_m: float

    def to_dict(self) -> dict:
        return {"points": self.points, "rms_before_m": self.rms_before_m, "rms_after_m": self.rms_after_m,
                "ratio": self.ratio, "rms_xyz_before_m": list(self.rms_xyz_before_m),
                "rms_xyz_after_m": list(self.rms_xyz_after_m), "max_before_m": self.max_before_m,
                "max_after_m": self.max_after_m}

    @classmethod
    def from_dict(cls, d: dict) -> CloudErrorSummary:
        return cls(int(d["points"]), _float(d["rms_before_m"]), _float(d["rms_after_m"]), _float(d["ratio"]),
                   tuple(_float(v) for v in d["rms_xyz_before_m"]),  # type: ignore[arg-type]
                   tuple(_float(v) for v in d["rms_xyz_after_m"]),  # type: ignore[arg-type]
                   _float(d["max_before_m"]), _float(d["max_after_m"]))


@dataclass(frozen=True)
class CloudErrors:
    """Point-by-point errors against the truth of the points inside the block."""

    xy: np.ndarray  # (n, 2) positions (output CRS) of the points compared
    before: np.ndarray  # (n, 3) jammed - truth
    after: np.ndarray  # (n, 3) refined - truth

    @staticmethod
    def _rms(e: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.sum(e**2, axis=1)))) if len(e) else float("nan")

    def summary(self) -> CloudErrorSummary:
        b, a = self._rms(self.before), self._rms(self.after)
        return CloudErrorSummary(
            int(len(self.before)), b, a, a / b if b > 0 else float("nan"),
            tuple(np.sqrt(np.mean(self.before**2, axis=0)).tolist()),  # type: ignore[arg-type]
            tuple(np.sqrt(np.mean(self.after**2, axis=0)).tolist()),  # type: ignore[arg-type]
            float(np.linalg.norm(self.before, axis=1).max()) if len(self.before) else float("nan"),
            float(np.linalg.norm(self.after, axis=1).max()) if len(self.after) else float("nan"))


def cloud_errors(jammed: Path, refined: Path, truth: Path, *, every: int = 1) -> CloudErrors:
    """Errors of the points inside the block, strip by strip (files of the same names); ``every``-th point."""
    xy, e0, e1 = [], [], []
    files = sorted(Path(refined).glob("*.laz")) + sorted(Path(refined).glob("*.las"))
    if not files:
        raise InputError("no refined strips", path=Path(refined), expected="LAS/LAZ files written by coadjust")
    for f in files:
        a, b, c = laspy.read(Path(jammed) / f.name), laspy.read(Path(truth) / f.name), laspy.read(f)
        if not (len(a) == len(b) == len(c)) or not np.array_equal(np.asarray(a.gps_time), np.asarray(b.gps_time)):
            raise InputError("strips do not hold the same points in the same order", path=f,
                             expected=f"the records of {Path(truth) / f.name}")
        inside = np.flatnonzero(np.asarray(c.lidargrams) >= 0)[::every]
        t = np.column_stack([b.x, b.y, b.z])[inside]
        xy.append(t[:, :2])
        e0.append(np.column_stack([a.x, a.y, a.z])[inside] - t)
        e1.append(np.column_stack([c.x, c.y, c.z])[inside] - t)
    return CloudErrors(np.concatenate(xy), np.concatenate(e0), np.concatenate(e1))


def _error_grid(xy: np.ndarray, n: np.ndarray, origin: np.ndarray, cell: float, shape: tuple[int, int]) -> np.ndarray:
    """Mean of ``n`` per ``cell``-metre cell (rows north, NaN where no point falls)."""
    ij = np.minimum(((xy - origin) / cell).astype(np.int64), np.array(shape)[::-1] - 1)
    flat = ij[:, 1] * shape[1] + ij[:, 0]
    count = np.bincount(flat, minlength=shape[0] * shape[1])
    total = np.bincount(flat, weights=n, minlength=shape[0] * shape[1])
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan).reshape(shape)


def plot_cloud_errors(errors: CloudErrors, path: Path, *, title: str = "", pixels: int = 250) -> Path:
    """Two maps of the 3-D error (jammed, refined) on one colour scale; PNG.

    Each map is the mean error of the points in square cells, ``pixels`` cells along the longer
    side (as strip-difference maps are drawn): every point counts, whatever the size of the cloud,
    where a scatter plot drew the last point of each pixel and took seconds per million points.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from georefine.evaluation.figures import save_png

    rms0, rms1 = CloudErrors._rms(errors.before), CloudErrors._rms(errors.after)
    n0, n1 = np.linalg.norm(errors.before, axis=1), np.linalg.norm(errors.after, axis=1)
    vmax = float(np.percentile(n0, 99)) if len(n0) else 1.0
    origin = errors.xy.min(axis=0) if len(errors.xy) else np.zeros(2)
    span = np.ptp(errors.xy, axis=0) if len(errors.xy) else np.ones(2)
    cell = max(float(span.max()) / pixels, 1e-3)
    shape = (int(span[1] / cell) + 1, int(span[0] / cell) + 1)
    aspect = float(np.clip(span[1] / max(span[0], 1e-9), 0.3, 2.0))
    # 9 in wide: the report shows it near its size, so its 9-11 pt labels stay readable there.
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6 * aspect + 1.2), sharex=True, sharey=True,
                             constrained_layout=True)
    extent = (0.0, shape[1] * cell, 0.0, shape[0] * cell)
    cmap = plt.get_cmap("viridis").with_extremes(over=(0.85, 0.1, 0.45))  # cells beyond the scale: magenta
    over = 0
    for ax, n, rms, label in ((axes[0], n0, rms0, "jammed G/I cloud"), (axes[1], n1, rms1, "refined")):
        grid = _error_grid(errors.xy, n, origin, cell, shape)
        over += int(np.count_nonzero(grid > vmax))
        im = ax.imshow(grid, origin="lower", extent=extent, cmap=cmap, vmin=0, vmax=vmax, interpolation="nearest")
        ax.set_aspect("equal")
        ax.set_title(f"{label}: RMS {rms:.3f} m", fontsize=11)
        ax.set_xlabel("E - E0 [m]", fontsize=10)
        ax.tick_params(labelsize=9)
    axes[0].set_ylabel("N - N0 [m]", fontsize=10)
    bar = fig.colorbar(im, ax=axes, shrink=0.8, extend="max" if over else "neither")
    bar.set_label(f"mean 3-D error per {cell:.2g} m cell [m]" + (f"; {over:,} cells beyond, in magenta" if over else ""),
                  fontsize=10)
    bar.ax.tick_params(labelsize=9)
    if title:
        fig.suptitle(title, fontsize=11)
    path = Path(path)
    save_png(fig, path, 110)
    plt.close(fig)
    return path
