"""Maps and histograms of a photo block as a surveyor reads it (the block demo's report, paper 004).

* :func:`plot_block_layout`: where the block is -- camera stations with photo ids, photo and
  lidargram footprints, control and check points -- in the output CRS;
* :func:`plot_point_vectors`: each check (and control) point's horizontal error as an arrow and
  its vertical error as the marker's colour, one panel per case on one scale;
* :func:`plot_residual_histograms`: the tie observations' image residuals (photos, lidargrams) and
  the check points' errors of one case.

The functions take arrays (the demo reads them from the files the co-adjustment wrote) and each
``draw_*`` returns the figure, which its ``plot_*`` saves as PNG (atomically), so tests can look at
the axes. Every map is at equal aspect; the fonts are 8 pt or more at 110 dpi. Errors that lie far
beyond the rest (a point off by 1.5 m among centimetre ones) stay visible: an arrow longer than the
scale's limit is drawn at the limit in another colour and labelled with its length, a vertical error
beyond the colour scale is labelled with its value.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["BlockLayout", "PointPanel", "ResidualHistogram", "VectorScale", "ground_footprint", "nice_ceil", "nice_step",
           "vector_scale",
           "sparse_labels", "draw_block_layout", "plot_block_layout", "draw_point_vectors", "plot_point_vectors",
           "draw_residual_histograms", "plot_residual_histograms", "DPI"]

DPI = 110
"""Resolution of the saved figures; the report shows them near their size (8 pt is 12 px there)."""

_FONT = 9  # labels and ticks
_SMALL = 8  # point and photo ids


def nice_step(value: float) -> float:
    """The largest of 1, 2, 5 times a power of ten not above ``value`` (a scale bar's length)."""
    if not np.isfinite(value) or value <= 0:
        return 1.0
    e = np.floor(np.log10(value))
    for m in (5.0, 2.0, 1.0):
        if m * 10**e <= value * (1 + 1e-9):
            return float(m * 10**e)
    return float(10**e)


def nice_ceil(value: float) -> float:
    """The smallest of 1, 1.5, 2, 2.5, 3, 4, 5, 6, 8 times a power of ten at or above ``value``
    (a scale's limit: round, and at most a third above the value)."""
    if not np.isfinite(value) or value <= 0:
        return 1.0
    e = np.floor(np.log10(value))
    for m in (1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0):
        if m * 10**e >= value * (1 - 1e-9):
            return float(m * 10**e)
    return float(10 ** (e + 1))


def ground_footprint(camera, R_w_c: np.ndarray, p_w_c: np.ndarray, height_w: float,
                     box_px: tuple[float, float, float, float] | None = None, samples: int = 6) -> np.ndarray:
    """``(k, 2)`` horizontal polygon (``w``) where the image border meets the plane ``z = height_w``.

    ``box_px``: ``(u0, v0, u1, v1)``, a part of the image (e.g. the pixels a lidargram shows); the
    whole image by default. Each side is sampled ``samples`` times, so the lens distortion bends the
    outline as it bends the rays. Rays that do not reach the plane (pointing above the horizon) are
    left out; all of them: an empty polygon.
    """
    u0, v0, u1, v1 = box_px if box_px is not None else (0.0, 0.0, float(camera.width_px), float(camera.height_px))
    t = np.linspace(0.0, 1.0, samples, endpoint=False)
    uv = np.concatenate([np.column_stack([u0 + (u1 - u0) * t, np.full_like(t, v0)]),
                         np.column_stack([np.full_like(t, u1), v0 + (v1 - v0) * t]),
                         np.column_stack([u1 - (u1 - u0) * t, np.full_like(t, v1)]),
                         np.column_stack([np.full_like(t, u0), v1 - (v1 - v0) * t])])
    d = np.asarray(camera.rays(uv)) @ np.asarray(R_w_c).T  # directions in w
    p = np.asarray(p_w_c, dtype=float)
    down = d[:, 2] < -1e-9
    s = (height_w - p[2]) / np.where(down, d[:, 2], -1.0)
    ok = down & (s > 0)
    return (p[:2] + s[ok, None] * d[ok, :2]).reshape(-1, 2)


def sparse_labels(xy: np.ndarray, min_distance: float) -> np.ndarray:
    """Indices of points to label, in order, each at least ``min_distance`` from those chosen before."""
    chosen: list[int] = []
    for k, p in enumerate(np.asarray(xy, dtype=float)):
        if not np.all(np.isfinite(p)):
            continue
        if all(np.hypot(*(p - xy[j])) >= min_distance for j in chosen):
            chosen.append(k)
    return np.asarray(chosen, dtype=np.int64)


@dataclass(frozen=True)
class BlockLayout:
    """What the layout map shows, in the output CRS (easting, northing in metres).

    ``lidargram_group``: the LiDAR strip each lidargram was rendered from (its colour);
    ``footprint_height``: the height (output CRS) the footprints are intersected at.
    """

    crs_name: str
    photo_ids: tuple[str, ...]
    photo_xy: np.ndarray  # (n, 2) projection centres
    photo_footprints: list[np.ndarray]  # (k, 2) each
    point_ids: tuple[str, ...]
    point_xy: np.ndarray  # (m, 2)
    point_is_control: np.ndarray  # (m,) bool
    lidargram_names: tuple[str, ...] = ()
    lidargram_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    lidargram_footprints: list[np.ndarray] = field(default_factory=list)
    lidargram_group: tuple[str, ...] = ()
    footprint_height: float = float("nan")

    def extent(self) -> tuple[float, float, float, float]:
        """``(xmin, xmax, ymin, ymax)`` of everything drawn."""
        parts = [self.photo_xy, self.point_xy, self.lidargram_xy, *self.photo_footprints, *self.lidargram_footprints]
        xy = np.concatenate([np.asarray(p, dtype=float).reshape(-1, 2) for p in parts])
        xy = xy[np.all(np.isfinite(xy), axis=1)]
        if not len(xy):
            return (0.0, 1.0, 0.0, 1.0)
        return float(xy[:, 0].min()), float(xy[:, 0].max()), float(xy[:, 1].min()), float(xy[:, 1].max())


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _map_axes(ax, crs_name: str, extent, *, ylabel: bool = True) -> None:
    """Equal aspect, the CRS's metres written out in full (no offset), a few ticks, a light grid."""
    from matplotlib.ticker import MaxNLocator

    x0, x1, y0, y1 = extent
    pad = 0.04 * max(x1 - x0, y1 - y0, 1.0)
    ax.set_xlim(x0 - pad, x1 + pad)
    ax.set_ylim(y0 - pad, y1 + pad)
    ax.set_aspect("equal")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.xaxis.set_major_locator(MaxNLocator(4))
    ax.yaxis.set_major_locator(MaxNLocator(6))
    ax.tick_params(labelsize=_FONT)
    ax.set_xlabel(f"easting [m], {crs_name}", fontsize=_FONT)
    if ylabel:
        ax.set_ylabel("northing [m]", fontsize=_FONT)
    ax.grid(True, color="0.9", lw=0.6, zorder=0)


def _figsize(extent, panels: int, *, width: float = 11.0, extra_h: float = 1.6) -> tuple[float, float]:
    """A figure ``width`` inches wide whose ``panels`` maps side by side keep the data's aspect."""
    x0, x1, y0, y1 = extent
    aspect = float(np.clip((y1 - y0) / max(x1 - x0, 1e-9), 0.4, 3.0))
    panel_w = (width - 1.2) / panels
    return width, min(panel_w * aspect + extra_h, 11.0)


def _draw_points(ax, layout: BlockLayout, *, labels: bool = True) -> list:
    """Control points (red triangles) and check points (blue circles), labelled; their legend handles."""
    handles = []
    xy, ctl = layout.point_xy, np.asarray(layout.point_is_control, dtype=bool)
    for mask, marker, colour, label in ((ctl, "^", "#d62728", "control point"), (~ctl, "o", "#1f5fbf", "check point")):
        if mask.any():
            handles.append(ax.scatter(xy[mask, 0], xy[mask, 1], marker=marker, s=46, facecolor=colour,
                                      edgecolor="black", linewidth=0.6, zorder=5, label=label))
    if labels:
        for pid, (x, y) in zip(layout.point_ids, xy):
            ax.annotate(pid, (x, y), xytext=(4, 3), textcoords="offset points", fontsize=_SMALL, zorder=6,
                        color="0.1")
    return handles


def draw_block_layout(layout: BlockLayout, *, title: str = ""):
    """The block's layout as a figure: (a) photos -- projection centres with sparse ids, footprints;
    (b) lidargrams -- projection centres and the ground each covers, coloured by LiDAR strip; both
    with the control and check points. The legend sits below the maps, off the data."""
    plt = _pyplot()
    from matplotlib.lines import Line2D

    extent = layout.extent()
    two = len(layout.lidargram_names) > 0
    fig, axes = plt.subplots(1, 2 if two else 1, figsize=_figsize(extent, 2 if two else 1, width=11 if two else 7),
                             sharex=True, sharey=True, layout="constrained", squeeze=False)
    axes = axes[0]
    handles: list = []
    ax = axes[0]
    grey = (0.3, 0.3, 0.3)
    for fp in layout.photo_footprints:
        if len(fp) >= 3:
            ax.fill(fp[:, 0], fp[:, 1], facecolor=(*grey, 0.035), edgecolor=(*grey, 0.55), lw=0.8, zorder=1)
    if any(len(fp) >= 3 for fp in layout.photo_footprints):
        handles.append(Line2D([], [], color=grey, lw=1.0, label="photo footprint"))
    handles.append(ax.scatter(layout.photo_xy[:, 0], layout.photo_xy[:, 1], marker="s", s=22, color="black",
                              zorder=4, label="photo projection centre"))
    x0, x1, y0, y1 = extent
    middle = float(np.median(layout.photo_xy[:, 0])) if len(layout.photo_xy) else 0.0
    for k in sparse_labels(layout.photo_xy, 0.07 * max(x1 - x0, y1 - y0)):
        right = layout.photo_xy[k, 0] > middle  # ids outwards, off the block's points
        ax.annotate(Path(layout.photo_ids[k]).stem, layout.photo_xy[k], xytext=(5 if right else -5, 0),
                    textcoords="offset points", ha="left" if right else "right", va="center", fontsize=_SMALL,
                    zorder=6, bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.75})
    handles += _draw_points(ax, layout)
    _map_axes(ax, layout.crs_name, extent)
    ax.set_title(f"photos ({len(layout.photo_ids)})", fontsize=10)
    if two:
        ax = axes[1]
        groups = list(dict.fromkeys(layout.lidargram_group))
        # Lidargrams of several strips at one station often cover the same ground: the first strip
        # wide and solid, the next narrower and dashed on top, so coinciding outlines show both.
        styles = [("#d95f02", 2.0, "-", "x"), ("#7570b3", 1.0, "--", "+"), ("#1b9e77", 1.0, ":", "1"),
                  ("#e7298a", 1.0, "-.", "2")]
        for g_i, g in enumerate(groups):
            c, lw, ls, marker = styles[g_i % len(styles)]
            sel = [k for k, x in enumerate(layout.lidargram_group) if x == g]
            for k in sel:
                fp = layout.lidargram_footprints[k] if k < len(layout.lidargram_footprints) else np.zeros((0, 2))
                if len(fp) >= 3:
                    ax.fill(fp[:, 0], fp[:, 1], facecolor="none", edgecolor=c, lw=lw, ls=ls, alpha=0.8,
                            zorder=2 + g_i)
            ax.scatter(layout.lidargram_xy[sel, 0], layout.lidargram_xy[sel, 1], marker=marker, s=40, color=c,
                       linewidths=1.2, zorder=4)
            handles.append(Line2D([], [], color=c, lw=lw, ls=ls, marker=marker,
                                  label=f"lidargrams of {g}: centre, footprint"))
        _draw_points(ax, layout)
        _map_axes(ax, layout.crs_name, extent, ylabel=False)
        ax.set_title(f"lidargrams ({len(layout.lidargram_names)})", fontsize=10)
    fig.legend(handles=handles, loc="outside lower center", ncols=min(len(handles), 3), fontsize=_FONT,
               frameon=False)
    if title:
        fig.suptitle(title, fontsize=11)
    return fig


def _save(fig, path: Path) -> Path:
    from georefine.evaluation.figures import save_png

    save_png(fig, path, DPI)
    _pyplot().close(fig)
    return Path(path)


def plot_block_layout(layout: BlockLayout, path: Path, *, title: str = "") -> Path:
    """:func:`draw_block_layout` saved as PNG at ``path``."""
    return _save(draw_block_layout(layout, title=title), path)


@dataclass(frozen=True)
class PointPanel:
    """One case's points for :func:`draw_point_vectors`: surveyed position (output CRS), error
    (intersected minus surveyed, m, east/north/up; NaN rows are points not intersected)."""

    title: str
    ids: tuple[str, ...]
    xy: np.ndarray  # (m, 2)
    error_m: np.ndarray  # (m, 3)
    is_control: np.ndarray  # (m,) bool


@dataclass(frozen=True)
class VectorScale:
    """The scale shared by the panels: ``metres_per_m`` map metres per metre of error, the scale
    arrow's length ``reference_m`` and the longest arrow drawn, ``limit_m`` (errors beyond it are
    clipped); the vertical colour scale's half range ``z_limit_m``."""

    metres_per_m: float
    reference_m: float
    limit_m: float
    z_limit_m: float


def vector_scale(panels: list[PointPanel], span_m: float) -> VectorScale:
    """Arrows on which the typical error (the 80th percentile of horizontal errors over every panel)
    is 7 % of the map's span ``span_m``; errors above 2.5 times it are clipped. The colour scale's
    half range: the largest vertical error, rounded up to a round number -- or, when that is more
    than twice their 90th percentile (an outlier would wash out every other colour), the 90th
    percentile rounded up (the outliers beyond are labelled)."""
    e = np.concatenate([np.asarray(p.error_m, dtype=float).reshape(-1, 3) for p in panels]) if panels \
        else np.zeros((0, 3))
    e = e[np.all(np.isfinite(e), axis=1)]
    h = np.hypot(e[:, 0], e[:, 1])
    typical = float(np.percentile(h, 80)) if len(h) else 0.01
    typical = max(typical, 1e-3)
    metres_per_m = 0.07 * span_m / typical
    z90 = float(np.percentile(np.abs(e[:, 2]), 90)) if len(e) else 0.01
    zmax = float(np.max(np.abs(e[:, 2]))) if len(e) else 0.01
    z = zmax if zmax <= 2.0 * z90 else z90
    return VectorScale(metres_per_m, nice_step(typical), 2.5 * typical, nice_ceil(max(z, 1e-3)))


def _drawn(error_m: np.ndarray, sc: VectorScale) -> np.ndarray:
    """``(m, 2)`` horizontal errors as drawn: those longer than ``sc.limit_m`` shortened to it."""
    e = np.asarray(error_m, dtype=float).reshape(-1, 3)[:, :2]
    h = np.hypot(e[:, 0], e[:, 1])
    with np.errstate(invalid="ignore"):
        clip = h > sc.limit_m
    return np.where(clip[:, None], e * (sc.limit_m / np.where(clip, h, 1.0))[:, None], e)


def _z_cmap():
    plt = _pyplot()
    # Beyond the scale: darker than either end, so an outlier never passes for a scale end.
    return plt.get_cmap("RdBu_r").with_extremes(over=(0.35, 0.0, 0.1), under=(0.0, 0.1, 0.3))


def draw_point_vectors(panels: list[PointPanel], crs_name: str, *, context: BlockLayout | None = None,
                       unit: str = "cm", title: str = ""):
    """Horizontal errors as arrows from the surveyed positions, vertical errors as colours; one panel
    per case, all on one scale (:func:`vector_scale`), with a scale arrow and a colour bar in ``unit``
    (``cm`` or ``mm``). ``context``: a layout whose photo footprints are drawn faintly behind.

    An arrow longer than the scale's limit is drawn at the limit in magenta with its length written
    beside it; a point whose vertical error lies beyond the colour scale gets its value written too.
    Control points are triangles, check points circles.
    """
    plt = _pyplot()
    from matplotlib.colors import Normalize

    factor = {"cm": 100.0, "mm": 1000.0}[unit]
    xy_all = np.concatenate([np.asarray(p.xy, dtype=float).reshape(-1, 2) for p in panels]) if panels \
        else np.zeros((0, 2))
    if context is not None:
        extent = context.extent()
    elif len(xy_all):
        extent = (float(xy_all[:, 0].min()), float(xy_all[:, 0].max()), float(xy_all[:, 1].min()),
                  float(xy_all[:, 1].max()))
    else:
        extent = (0.0, 1.0, 0.0, 1.0)
    span = max(extent[1] - extent[0], extent[3] - extent[2], 1.0)
    sc = vector_scale(panels, span)
    # The map holds every arrow's tip (the clipped ones at the limit).
    tips = [np.asarray(p.xy, dtype=float).reshape(-1, 2) + _drawn(p.error_m, sc) * sc.metres_per_m for p in panels]
    tips_xy = np.concatenate(tips) if tips else np.zeros((0, 2))
    tips_xy = tips_xy[np.all(np.isfinite(tips_xy), axis=1)]
    if len(tips_xy):
        extent = (min(extent[0], float(tips_xy[:, 0].min())), max(extent[1], float(tips_xy[:, 0].max())),
                  min(extent[2], float(tips_xy[:, 1].min())), max(extent[3], float(tips_xy[:, 1].max())))
    n = max(len(panels), 1)
    fig, axes = plt.subplots(1, n, figsize=_figsize(extent, n, width=min(4.0 * n + 1.2, 13.0), extra_h=1.9),
                             sharex=True, sharey=True, layout="constrained", squeeze=False)
    axes = axes[0]
    norm = Normalize(-sc.z_limit_m * factor, sc.z_limit_m * factor)
    cmap = _z_cmap()
    mappable = None
    any_over = False
    for k, (ax, p) in enumerate(zip(axes, panels)):
        if context is not None:
            for fp in context.photo_footprints:
                if len(fp) >= 3:
                    ax.fill(fp[:, 0], fp[:, 1], facecolor="none", edgecolor="0.82", lw=0.6, zorder=1)
        e = np.asarray(p.error_m, dtype=float).reshape(-1, 3)
        xy = np.asarray(p.xy, dtype=float).reshape(-1, 2)
        ok = np.all(np.isfinite(e), axis=1)
        h = np.hypot(e[:, 0], e[:, 1])
        clipped = ok & (h > sc.limit_m)
        draw = _drawn(e, sc)
        for sel, colour in ((ok & ~clipped, "black"), (clipped, "#c000c0")):
            ax.quiver(xy[sel, 0], xy[sel, 1], draw[sel, 0] * sc.metres_per_m, draw[sel, 1] * sc.metres_per_m,
                      angles="xy", scale_units="xy", scale=1.0, color=colour, width=0.006, headwidth=3.5,
                      headlength=4.0, zorder=6)
        for i in np.flatnonzero(clipped):
            tip = xy[i] + draw[i] * sc.metres_per_m
            ax.annotate(f"{h[i] * factor:.0f} {unit}", tip, xytext=(3, 3), textcoords="offset points",
                        fontsize=_SMALL, color="#c000c0", zorder=7)
        ctl = np.asarray(p.is_control, dtype=bool)
        for sel, marker in ((ok & ctl, "^"), (ok & ~ctl, "o")):
            mappable = ax.scatter(xy[sel, 0], xy[sel, 1], c=e[sel, 2] * factor, cmap=cmap, norm=norm, marker=marker,
                                  s=60, edgecolor="black", linewidth=0.7, zorder=5)
        nan = ~ok
        if nan.any():  # measured in fewer than two photos: no error to draw
            ax.scatter(xy[nan, 0], xy[nan, 1], marker="x", s=40, color="0.4", zorder=5)
        for i in np.flatnonzero(ok & (np.abs(e[:, 2]) > sc.z_limit_m)):
            any_over = True
            ax.annotate(f"dZ {e[i, 2] * factor:+.0f}", xy[i], xytext=(5, -10), textcoords="offset points",
                        fontsize=_SMALL, color=(0.35, 0.0, 0.1) if e[i, 2] > 0 else (0.0, 0.1, 0.3), zorder=7)
        for pid, (x, y) in zip(p.ids, xy):
            ax.annotate(pid, (x, y), xytext=(-4, 4), textcoords="offset points", ha="right", fontsize=_SMALL,
                        color="0.25", zorder=7)
        _map_axes(ax, crs_name, extent, ylabel=k == 0)
        ax.set_title(p.title, fontsize=10)
    # The scale arrow, in the lower left corner of the first panel (above the data's margin).
    ax0 = axes[0]
    x0, x1 = ax0.get_xlim()
    y0, y1 = ax0.get_ylim()
    ref = sc.reference_m * sc.metres_per_m
    ax0.quiver([x0 + 0.06 * (x1 - x0)], [y0 + 0.025 * (y1 - y0)], [ref], [0.0], angles="xy", scale_units="xy",
               scale=1.0, color="black", width=0.006, headwidth=3.5, headlength=4.0, zorder=8)
    ax0.annotate(f"{sc.reference_m * factor:g} {unit}", (x0 + 0.06 * (x1 - x0) + ref / 2, y0 + 0.025 * (y1 - y0)),
                 xytext=(0, 4), textcoords="offset points", ha="center", fontsize=_FONT, zorder=8,
                 bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.8})
    if mappable is not None:
        bar = fig.colorbar(mappable, ax=list(axes), location="bottom", shrink=0.5, aspect=35,
                           extend="both" if any_over else "neither")
        bar.set_label(f"vertical error dZ [{unit}] (intersected - surveyed)", fontsize=_FONT)
        bar.ax.tick_params(labelsize=_FONT)
    note = (f"arrows: horizontal error, {sc.metres_per_m:.0f}x; longer than {sc.limit_m * factor:.0f} {unit} "
            "clipped (magenta, length written); triangles: control points, circles: check points")
    fig.supxlabel(note, fontsize=_SMALL, color="0.3")
    if title:
        fig.suptitle(title, fontsize=11)
    return fig


def plot_point_vectors(panels: list[PointPanel], crs_name: str, path: Path, *, context: BlockLayout | None = None,
                       unit: str = "cm", title: str = "") -> Path:
    """:func:`draw_point_vectors` saved as PNG at ``path``."""
    return _save(draw_point_vectors(panels, crs_name, context=context, unit=unit, title=title), path)


@dataclass(frozen=True)
class ResidualHistogram:
    """One case for :func:`draw_residual_histograms`: image residual lengths (px) of the adjusted tie
    observations in photos and in lidargrams (None where not known) and the check points' errors
    (m, east/north/up)."""

    title: str
    photo_px: np.ndarray | None
    lidargram_px: np.ndarray | None
    check_error_m: np.ndarray  # (m, 3)
    inlier_limit_px: float | None = None  # the adjustment's inlier limit: RMS below it, a line at it


def draw_residual_histograms(h: ResidualHistogram, *, max_px: float | None = None, max_error_m: float | None = None,
                             unit: str = "cm"):
    """Two histograms side by side: the tie observations' image residuals (photos and lidargrams,
    px; values beyond ``max_px`` counted in the last bin; the RMS over those below the inlier limit,
    as ``metrics.json`` takes it) and the check points' dX, dY, dZ in ``unit`` (beyond
    ``±max_error_m`` in the end bins, counted in the legend)."""
    plt = _pyplot()
    factor = {"cm": 100.0, "mm": 1000.0}[unit]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.4), layout="constrained")
    series = [(v, label, colour) for v, label, colour in ((h.photo_px, "photos", "#1f5fbf"),
                                                           (h.lidargram_px, "lidargrams", "#d95f02")) if v is not None]
    if series:
        allv = np.concatenate([np.asarray(v, dtype=float) for v, _, _ in series])
        allv = allv[np.isfinite(allv)]
        top = max_px if max_px is not None else nice_ceil(float(np.percentile(allv, 99)) if len(allv) else 1.0)
        bins = np.linspace(0.0, top, 49)
        for v, label, colour in series:
            v = np.asarray(v, dtype=float)
            v = v[np.isfinite(v)]
            over = int(np.count_nonzero(v > top))
            inl = v[v < h.inlier_limit_px] if h.inlier_limit_px is not None else v
            rms = float(np.sqrt(np.mean(inl**2))) if len(inl) else float("nan")
            a.hist(np.minimum(v, top), bins=bins, histtype="step", lw=1.4, color=colour,
                   label=f"{label}: {len(v):,}, RMS{' of inliers' if h.inlier_limit_px is not None else ''} "
                   f"{rms:.2f} px" + (f"\n{over:,} beyond {top:g} px, in the last bin" if over else ""))
        if h.inlier_limit_px is not None and h.inlier_limit_px <= top:
            a.axvline(h.inlier_limit_px, color="0.4", lw=0.9, ls=":", label=f"inlier limit {h.inlier_limit_px:g} px")
        a.set_xlabel("image residual of a tie observation [px]", fontsize=_FONT)
        a.set_ylabel("observations", fontsize=_FONT)
        a.set_ylim(0, a.get_ylim()[1] * 1.45)  # headroom: the legend above the bars
        a.legend(fontsize=_SMALL, frameon=False, loc="upper right")
    else:
        a.text(0.5, 0.5, "image residuals not available", ha="center", va="center", fontsize=_FONT,
               transform=a.transAxes)
    a.tick_params(labelsize=_FONT)
    a.set_title("tie points: image residuals", fontsize=10)
    e = np.asarray(h.check_error_m, dtype=float).reshape(-1, 3)
    e = e[np.all(np.isfinite(e), axis=1)] * factor
    if len(e):
        lim = (max_error_m * factor if max_error_m is not None
               else nice_ceil(float(np.percentile(np.abs(e), 90))))
        step = nice_step(lim / 6)
        lim = step * np.ceil(lim / step)
        bins = np.arange(-lim, lim + step / 2, step)
        over = int(np.count_nonzero(np.abs(e) > lim))
        b.hist([np.clip(e[:, k], -lim, lim) for k in range(3)], bins=bins, histtype="bar",
               color=["#1f77b4", "#2ca02c", "#d62728"], label=["dX", "dY", "dZ"], rwidth=0.9)
        b.legend(fontsize=_SMALL, frameon=False, loc="upper left", bbox_to_anchor=(1.01, 1.0),
                 title=f"{len(e)} check points" + (f"\n{over} beyond ±{lim:g} {unit},\nin the end bins" if over else ""),
                 title_fontsize=_SMALL, alignment="left")
        b.set_xlabel(f"error (intersected - surveyed) [{unit}]", fontsize=_FONT)
        b.set_ylabel("check points", fontsize=_FONT)
        b.yaxis.get_major_locator().set_params(integer=True)
    else:
        b.text(0.5, 0.5, "no check point intersected", ha="center", va="center", fontsize=_FONT,
               transform=b.transAxes)
    b.tick_params(labelsize=_FONT)
    b.set_title("check points: dX, dY, dZ", fontsize=10)
    if h.title:
        fig.suptitle(h.title, fontsize=11)
    return fig


def plot_residual_histograms(h: ResidualHistogram, path: Path, *, max_px: float | None = None,
                             max_error_m: float | None = None, unit: str = "cm") -> Path:
    """:func:`draw_residual_histograms` saved as PNG at ``path``."""
    return _save(draw_residual_histograms(h, max_px=max_px, max_error_m=max_error_m, unit=unit), path)
