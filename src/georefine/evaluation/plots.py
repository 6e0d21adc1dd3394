"""Figures of trajectory differences (paper 000, Fig. 9), written as PNG.

Matplotlib is imported only when a figure is drawn, and only its object-oriented API with
the Agg canvas is used (no ``pyplot``, no global backend switch), so plotting works headless
and from threads. Files are written to a temporary name and renamed when complete.

Long series are reduced for drawing to the minimum and maximum of each of a few thousand
buckets (an envelope), so spikes stay visible; statistics are always of the full series.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from georefine.io.files import PathLike, atomic_path, week_from_gps_seconds

if TYPE_CHECKING:  # pragma: no cover
    from georefine.evaluation.trajectory import TrajectoryComparison

__all__ = ["plot_attitude_differences", "plot_position_differences"]

_MDEG_PER_RAD = 180e3 / np.pi
_MAX_POINTS = 20_000


def _envelope(t: np.ndarray, y: np.ndarray, max_points: int = _MAX_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Reduce ``(t, y)`` to the min and max of each bucket, in time order, if longer than ``max_points``."""
    n = t.shape[0]
    if n <= max_points:
        return t, y
    b = int(np.ceil(2 * n / max_points))
    m = n // b
    yy = y[: m * b].reshape(m, b)
    base = np.arange(m) * b
    i_min, i_max = base + np.argmin(yy, axis=1), base + np.argmax(yy, axis=1)
    idx = np.sort(np.concatenate([i_min, i_max, np.arange(m * b, n)]))
    return t[idx], y[idx]


def _time_axis(comparisons: Mapping[str, "TrajectoryComparison"]) -> tuple[float, str]:
    """Common origin (the earliest first common time) and the x-axis label."""
    t0 = min(c.t0_gps for c in comparisons.values())
    if all(c.time_scale == "gps" for c in comparisons.values()):
        week, sow = week_from_gps_seconds(t0)
        return t0, f"time (s) since GPS week {int(week)}, {float(sow):.3f} s of week"
    return t0, f"time (s) since {t0:.3f} s of week"


def _panels(
    comparisons: Mapping[str, "TrajectoryComparison"],
    path: PathLike,
    title: str | None,
    series,
    protect: tuple[PathLike, ...],
) -> Path:
    """Three stacked panels sharing the time axis; ``series(c) -> [(ylabel, y, rmse_text)] * 3``."""
    if not comparisons:
        raise ValueError("at least one comparison is needed")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    t_origin, xlabel = _time_axis(comparisons)
    fig = Figure(figsize=(10, 7.5), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(3, 1, sharex=True)
    for label, comp in comparisons.items():
        t = comp.t0_gps - t_origin + comp.time
        for ax, (_, y, rmse_text) in zip(axes, series(comp)):
            tt, yy = _envelope(t, y)
            ax.plot(tt, yy, lw=0.8, label=f"{label} (RMSE {rmse_text})")
    first = next(iter(comparisons.values()))
    for ax, (ylabel, _, _) in zip(axes, series(first)):
        ax.set_ylabel(ylabel)
        ax.axhline(0.0, color="0.6", lw=0.6, zorder=0)
        ax.grid(True, lw=0.3, alpha=0.6)
        ax.legend(loc="best", fontsize="small")
    axes[-1].set_xlabel(xlabel)
    if title:
        fig.suptitle(title)
    path = Path(path)
    with atomic_path(path, protect) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    return path


def plot_attitude_differences(
    comparisons: Mapping[str, "TrajectoryComparison"],
    path: PathLike,
    title: str | None = None,
    *,
    protect: tuple[PathLike, ...] = (),
) -> Path:
    """Roll, pitch and yaw differences (mdeg) over time, one line per comparison (paper 000, Fig. 9).

    Parameters
    ----------
    comparisons
        Legend label -> :class:`~georefine.evaluation.trajectory.TrajectoryComparison`
        (e.g. ``{"G/I - G/I/L": c1, "G/I/L N-S - G/I/L": c2}``); the legend shows each
        RMSE. Times are drawn relative to the earliest first common time.
    path
        PNG file to write (atomically).
    title
        Figure title.
    protect
        Inputs the file must not overwrite.

    Returns
    -------
    pathlib.Path
        ``path``.
    """

    def series(c):
        d = c.d_rph_rad * _MDEG_PER_RAD
        return [(f"{name} (mdeg)", d[:, j], f"{c.stats[f'{key}_rmse_mdeg']:.1f} mdeg")
                for j, (name, key) in enumerate((("roll", "roll"), ("pitch", "pitch"), ("yaw", "yaw")))]

    return _panels(comparisons, path, title, series, protect)


def plot_position_differences(
    comparisons: Mapping[str, "TrajectoryComparison"],
    path: PathLike,
    title: str | None = None,
    *,
    protect: tuple[PathLike, ...] = (),
) -> Path:
    """North, east and down position differences (m) over time, one line per comparison.

    Parameters as :func:`plot_attitude_differences`.
    """

    def series(c):
        return [(f"{name} (m)", c.d_ned_m[:, j], f"{c.stats[f'{name}_rmse_m']:.3f} m")
                for j, name in enumerate(("north", "east", "down"))]

    return _panels(comparisons, path, title, series, protect)
