"""Raster maps cut into panels along a long corridor, at equal aspect, in the output CRS.

Shared by the report's raster maps: the strip differences
(:mod:`georefine.evaluation.strip_difference_maps`) and the point density and strip overlap
(:mod:`georefine.evaluation.coverage`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["MAX_PANEL_RATIO", "label_axes", "map_panels", "mark_sites", "tiled_axes"]

MAX_PANEL_RATIO = 2.5
"""A map longer than this many times its width is cut along its long axis into panels of at most
this ratio, shown side by side (a north-south corridor) or stacked (an east-west one), each at
equal aspect: one panel of a 3.3 km by 0.5 km corridor was a sliver beside a white page."""


def map_panels(rows: int, cols: int, max_ratio: float = MAX_PANEL_RATIO) -> tuple[str, list[slice]]:
    """How :func:`tiled_axes` cuts a ``rows`` x ``cols`` map: ``("rows", slices)`` for panels of
    rows side by side, ``("cols", slices)`` for panels of columns stacked; one slice when it is
    compact enough."""
    along, across = (rows, cols) if rows >= cols else (cols, rows)
    k = max(1, int(np.ceil(along / (max_ratio * max(across, 1)))))
    edges = np.linspace(0, along, k + 1).round().astype(int)
    return ("rows" if rows >= cols else "cols"), [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def tiled_axes(rows: int, cols: int, x0: float, y1: float, cell_size_m: float,
               max_panel_ratio: float = MAX_PANEL_RATIO):
    """A figure for a ``rows`` x ``cols`` raster (row 0 the northern edge at ``y1``, column 0 the
    western at ``x0``) cut into panels (:func:`map_panels`): ``(fig, axes, panels)`` with one
    ``(row slice, column slice, imshow extent)`` per axes, every axes at equal aspect with plain
    coordinates in metres. Shared by the report's raster maps (strip differences, coverage)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    axis, parts = map_panels(rows, cols, max_panel_ratio)
    c = cell_size_m
    panel_rows = max(p.stop - p.start for p in parts) if axis == "rows" else rows
    panel_cols = cols if axis == "rows" else max(p.stop - p.start for p in parts)
    ratio = panel_rows / max(panel_cols, 1)  # height / width of one panel
    n = len(parts)
    # At most about 11.5 inches wide: the page shows a map at 1120 px whatever its size, so a wider
    # figure only shrinks its text (at 13.8 inches, 8 pt came out 9.0 px high on the page).
    if axis == "rows":  # tall panels side by side
        w = min(3.2, 9.6 / n, 11.0 / ratio)
        fig, axes = plt.subplots(1, n, figsize=(n * w + 1.8, 0.9 * w * ratio + 1.3), dpi=150, squeeze=False,
                                 layout="constrained")
    else:  # wide panels stacked
        w = min(9.6, 14.0 / (n * ratio))
        fig, axes = plt.subplots(n, 1, figsize=(w + 1.8, n * w * ratio + 1.3), dpi=150, squeeze=False,
                                 layout="constrained")
    axes = list(axes.ravel())
    panels = []
    for ax, part in zip(axes, parts):
        r, q = (part, slice(0, cols)) if axis == "rows" else (slice(0, rows), part)
        extent = (x0 + q.start * c, x0 + q.stop * c, y1 - r.stop * c, y1 - r.start * c)
        panels.append((r, q, extent))
        ax.set_aspect("equal")
        ax.ticklabel_format(useOffset=False, style="plain")
        ax.tick_params(labelsize=8)
    return fig, axes, panels


def mark_sites(ax, extent, sites: list[tuple[str, float, float]] | None) -> None:
    """``sites`` ``(label, x, y)`` inside ``extent`` as labelled triangles (on one panel where two meet)."""
    for label, x, y in sites or ():
        if extent[0] <= x < extent[1] and extent[2] < y <= extent[3]:
            ax.plot(x, y, marker="^", ms=6, mfc="none", mec="black", mew=1.0)
            ax.annotate(label, (x, y), xytext=(4, 4), textcoords="offset points", fontsize=8)


def label_axes(fig, epsg: int | None) -> None:
    """Easting and northing in metres, and the CRS, once for all panels."""
    crs = f" (EPSG:{epsg})" if epsg else ""
    fig.supxlabel(f"easting [m]{crs}", fontsize=9)
    fig.supylabel(f"northing [m]{crs}", fontsize=9)
