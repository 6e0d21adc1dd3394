"""The strip-difference map drawn: a PNG in mm, at equal aspect, a long corridor cut into panels.

:mod:`georefine.evaluation.strip_differences` computes the raster (and writes its GeoTIFF); this
module draws it for the report and for people: 0-100 mm green to red, cells beyond the scale in
purple and counted, gated cells grey, the reference surfaces marked.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from georefine.evaluation.figures import save_png
from georefine.evaluation.map_panels import MAX_PANEL_RATIO, label_axes, map_panels, mark_sites, tiled_axes
from georefine.evaluation.strip_differences import GATES, StripDifferenceMap

__all__ = ["MAX_PANEL_RATIO", "map_figure", "map_panels", "write_png"]

def write_png(path: str | Path, m: StripDifferenceMap, *, title: str = "", vmax_m: float = 0.1, epsg: int | None = None,
              sites: list[tuple[str, float, float]] | None = None, max_panel_ratio: float = MAX_PANEL_RATIO) -> Path:
    """PNG map of the spread (:func:`map_figure`), written atomically."""
    import matplotlib.pyplot as plt

    fig = map_figure(m, title=title, vmax_m=vmax_m, epsg=epsg, sites=sites, max_panel_ratio=max_panel_ratio)
    save_png(fig, path)
    plt.close(fig)
    return path


def map_figure(m: StripDifferenceMap, *, title: str = "", vmax_m: float = 0.1, epsg: int | None = None,
               sites: list[tuple[str, float, float]] | None = None, max_panel_ratio: float = MAX_PANEL_RATIO):
    """The map of the spread in mm: 0-``vmax_m`` green to red, cells beyond it in purple (the
    colour bar says so), gated cells grey, axes in the output CRS at equal aspect; a long map cut
    into panels (:func:`map_panels`); ``sites`` ``(label, x, y)`` marked (the reference surfaces).
    Returns the matplotlib figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, cols = m.spread_m.shape
    fig, axes, panels = tiled_axes(rows, cols, m.x0, m.y1, m.cell_size_m, max_panel_ratio)
    cmap = plt.get_cmap("RdYlGn_r").with_extremes(bad=(1.0, 1.0, 1.0, 0.0), over=(0.45, 0.05, 0.55))
    spread_mm = m.spread_m * 1e3
    over = int(np.count_nonzero(spread_mm > vmax_m * 1e3))
    gated = np.where(m.gate >= GATES.index("rough"), 1.0, np.nan)
    im = None
    for ax, (r, q, extent) in zip(axes, panels):
        sub = spread_mm[r, q]
        g = gated[r, q]
        if np.any(g == 1.0):  # gated cells in grey, beneath the map
            ax.imshow(g, extent=extent, cmap=plt.get_cmap("Greys"), vmin=0.0, vmax=2.0, interpolation="nearest",
                      origin="upper")
        im = ax.imshow(sub, extent=extent, cmap=cmap, vmin=0.0, vmax=vmax_m * 1e3, interpolation="nearest",
                       origin="upper")
        mark_sites(ax, extent, sites)
    label_axes(fig, epsg)
    note = f"; {over:,} cells above {vmax_m * 1e3:g} mm in purple" if over else ""
    fig.suptitle((title or "strip differences") + f" (max - min per cell along the normal; grey: gated{note})",
                 fontsize=10)
    fig.colorbar(im, ax=list(axes), label="difference [mm]", shrink=0.8, extend="max")
    return fig
