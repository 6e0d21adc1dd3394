"""Saving the report's figures: PNG, written atomically, that say how they will read.

Every plot of the reports is saved by :func:`save_png`. Besides writing under a temporary name,
it records in the PNG's text chunks what a reader of the page cannot measure from pixels: the
smallest font on the figure in pixels at the saved resolution (``georefine:min-font-px``) and how
many of its map axes are drawn at equal aspect (``georefine:axes``, ``"equal/total"``, colour bars
not counted). The browser tests of the corridor and block demos (``tests/browser_helpers.py``)
render the pages, read each image's displayed size and these facts, and so check that every map
keeps equal aspect and that its smallest text is still readable at the size the page shows it.
"""

from __future__ import annotations

from pathlib import Path

from georefine.io.files import atomic_path

__all__ = ["MIN_FONT_KEY", "AXES_KEY", "figure_facts", "save_png"]

MIN_FONT_KEY = "georefine:min-font-px"
AXES_KEY = "georefine:axes"


def figure_facts(fig, dpi: float) -> dict[str, str]:
    """``{MIN_FONT_KEY: smallest visible text in px at dpi, AXES_KEY: "equal/total"}`` of ``fig``."""
    from matplotlib.text import Text

    fig.draw_without_rendering()  # tick labels get their text (and layout its place) when the figure is drawn
    sizes = [t.get_fontsize() for t in fig.findobj(Text) if t.get_visible() and t.get_text().strip()]
    axes = [ax for ax in fig.axes if ax.get_visible() and not hasattr(ax, "_colorbar")]
    equal = sum(1 for ax in axes if ax.get_aspect() == 1.0)
    return {MIN_FONT_KEY: f"{min(sizes) * dpi / 72.0:.1f}" if sizes else "",
            AXES_KEY: f"{equal}/{len(axes)}"}


def save_png(fig, path: str | Path, dpi: float | None = None, protect=()) -> Path:
    """Write ``fig`` to ``path`` as PNG (atomically, refusing to overwrite ``protect``:
    :func:`~georefine.io.files.atomic_path`), with :func:`figure_facts` in its text chunks."""
    dpi = float(dpi if dpi is not None else fig.dpi)
    path = Path(path)
    with atomic_path(path, protect) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi, metadata=figure_facts(fig, dpi))
    return path
