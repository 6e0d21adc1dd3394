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

from georefine.evaluation.figures import save_png
from georefine.io.files import PathLike, week_from_gps_seconds

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
    return save_png(fig, path, 120, protect)


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


def plot_overview(trajectory_csv: Path, strip_time_gps: dict, path: Path, *,
                  sites: list[tuple[str, float, float]] | None = None, title: str = "") -> Path:
    """The flight on a map: the whole trajectory in grey, each strip's part of it in colour and
    labelled with its id and direction, the reference surfaces as triangles; equal aspect, the
    output CRS's axes (what a surveyor looks at first)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from georefine.io.trajectory_csv import read_trajectory_csv

    table = read_trajectory_csv(trajectory_csv)
    t, x, y = table.time_gps, table.xyz[:, 0], table.xyz[:, 1]
    span = max(float(np.ptp(x)), float(np.ptp(y)), 1.0)
    wide = float(np.ptp(x)) >= float(np.ptp(y))
    fig = Figure(figsize=(10, 6) if wide else (6, 9), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    ax.plot(x, y, color="0.65", lw=0.8, label="trajectory")
    strips = sorted(strip_time_gps.items(), key=lambda kv: kv[1][0])
    block = len(strips) > 4  # a block of strips side by side and across, not passes over one corridor
    if block:
        from matplotlib import colormaps

        colours = tuple(colormaps["tab20"](j) for j in (0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 1, 3, 5, 7, 9, 11, 13, 15))
    else:
        colours = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")
    for k, (sid, (t0, t1)) in enumerate(strips):
        on = (t >= t0) & (t <= t1)
        if not np.any(on):
            continue
        c = colours[k % len(colours)]
        # Passes over one corridor overlap: each drawn thinner than the last, labelled at its own
        # place and side. A block's strips lie apart: one width, each labelled with its id at a
        # fifth, a half or four fifths of its length in turn, so that labels on a cross strip and
        # on the parallel strips it crosses do not meet.
        ax.plot(x[on], y[on], color=c, lw=2.0 if block else 3.0 - 2.0 * k / max(len(strips), 1), label=f"strip {sid}")
        i = np.flatnonzero(on)
        ax.annotate("", xy=(x[i[-1]], y[i[-1]]), xytext=(x[i[-2]], y[i[-2]]) if i.size > 1 else (x[i[0]], y[i[0]]),
                    arrowprops={"arrowstyle": "-|>", "color": c, "lw": 1.5})
        at = i[int(i.size * ((0.2, 0.5, 0.8)[k % 3] if block else (k + 1) / (len(strips) + 1)))]
        ax.annotate(str(sid) if block else f"strip {sid}", (x[at], y[at]), xytext=(8 if k % 2 == 0 else -8, 0),
                    textcoords="offset points", ha="left" if k % 2 == 0 else "right", fontsize=9, color=c,
                    fontweight="bold" if block else "normal")
    for label, sx, sy in sites or ():
        ax.plot(sx, sy, marker="^", ms=7, mfc="none", mec="black", mew=1.0)
        ax.annotate(label, (sx, sy), xytext=(4, 4), textcoords="offset points", fontsize=8)
    ax.set_aspect("equal")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.tick_params(labelsize=9)
    from matplotlib.ticker import MaxNLocator

    (ax.yaxis if wide else ax.xaxis).set_major_locator(MaxNLocator(3))  # the narrow axis: labels apart
    if not wide:
        ax.tick_params(axis="x", labelrotation=30)
    crs = f" ({table.crs})" if table.crs else ""
    ax.set_xlabel(f"easting [m]{crs}", fontsize=10)
    ax.set_ylabel(f"northing [m]{crs}", fontsize=10)
    ax.grid(True, lw=0.3, alpha=0.6)
    if block:  # beside the map: ten or more entries would cover it
        ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=9, borderaxespad=0.0)
    else:
        ax.legend(loc="best", fontsize=9)
    ax.set_title(title or f"flight overview ({span / 1000:.1f} km across)", fontsize=11)
    return save_png(fig, path, 110)


def plot_residual_histograms(groups: list[dict], path: Path, title: str = "") -> Path | None:
    """Per observation group of an adjustment (``adjustment.json``'s ``groups``), the histogram of
    its whitened residual rows (:attr:`~georefine.adjustment.statistics.GroupStatistics.residual_histogram`)
    on a log scale, beside the counts ``N(0, 1)`` expects of as many rows: the middle shows whether
    the sigmas are honest (wider: optimistic), the outer bins, which hold everything beyond +-5,
    the outliers the robust loss weighs down. None when no group has a histogram (older results)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from scipy.special import ndtr

    from georefine.adjustment.statistics import RESIDUAL_EDGES

    shown = [g for g in groups if g.get("residual_histogram") and sum(g["residual_histogram"]) > 0]
    if not shown:
        return None
    edges = np.asarray(RESIDUAL_EDGES)
    cols = min(3, len(shown))
    rows = -(-len(shown) // cols)
    fig = Figure(figsize=(4.2 * cols, 3.0 * rows + 0.6), layout="constrained")
    FigureCanvasAgg(fig)
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).ravel()
    cdf = ndtr(edges)
    cdf[0], cdf[-1] = 0.0, 1.0  # the outer bins hold the tails
    for ax, g in zip(axes, shown):
        counts = np.asarray(g["residual_histogram"], dtype=float)
        n = counts.sum()
        ax.stairs(np.maximum(counts, 0.5), edges, fill=True, color="tab:blue", alpha=0.55, baseline=0.5,
                  label="residuals")
        ax.stairs(n * np.diff(cdf), edges, color="black", lw=1.0, label="N(0, 1)")
        ax.set_yscale("log")
        ax.set_ylim(0.5, max(counts.max(), n * np.diff(cdf).max()) * 2.0)
        s0 = g.get("robust_sigma0")
        ax.set_title(f"{g['name']}: {int(n):,} rows" + (f", robust σ0 {s0:.2f}" if s0 is not None else ""),
                     fontsize=10)
        ax.set_xlabel("whitened residual [σ]; outer bins: beyond ±5", fontsize=9)
        ax.tick_params(labelsize=9)
        ax.grid(True, lw=0.3, alpha=0.6)
    axes[0].legend(fontsize=9, loc="upper right")
    for ax in axes[len(shown):]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title, fontsize=11)
    return save_png(fig, path, 110)
