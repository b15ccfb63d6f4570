"""Figure helpers shared by every map skyroute draws: a scale bar and a north arrow placed where
they cover no marker, the start / goal marker styles, a colour bar only for a layer that varies
(a note otherwise), and checks that no text of a figure is cut off by its canvas, no legend or
map furniture covers a marker, and no title runs into another axes."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["add_map_furniture", "clipped_texts", "image_extent", "START_STYLE", "GOAL_STYLE", "value_range",
           "colorbar_or_note", "marker_boxes", "covered_markers", "degenerate_colorbars", "overlapping_titles",
           "furniture_boxes", "uniform_value", "add_note", "side_colorbar", "all_axes"]

#: the mission's start and goal on every map (the goal is not a star: landing sites are red stars)
START_STYLE = dict(marker="o", ms=9, mfc="white", mec="k", ls="none")
GOAL_STYLE = dict(marker="D", ms=8, mfc="gold", mec="k", ls="none")


def image_extent(da) -> tuple[float, float, float, float]:
    """``imshow`` extent (left, right, bottom, top) [m] of a north-up raster with cell-centre
    ``x``/``y`` coordinates (x ascending, y descending): the outer cell edges."""
    x, y = np.asarray(da["x"].values, float), np.asarray(da["y"].values, float)
    r = float(x[1] - x[0]) if x.size > 1 else float(abs(y[0] - y[1])) if y.size > 1 else 1.0
    return (x[0] - r / 2, x[-1] + r / 2, y[-1] - r / 2, y[0] + r / 2)


def _nice_length(span_m: float) -> float:
    """A round scale-bar length [m] of about a fifth of ``span_m``."""
    target = max(span_m / 5.0, 1e-9)
    base = 10.0 ** math.floor(math.log10(target))
    return max(m * base for m in (1, 2, 5) if m * base <= target)


# corners of the map furniture in axes fraction: (x0, y0, x1, y1) of the north arrow with its
# "grid north" label, and the anchor of the scale bar (its box is sized by the bar's length)
_ARROW_BOXES = {"upper right": (0.85, 0.70, 0.99, 0.97), "upper left": (0.01, 0.70, 0.15, 0.97),
                "lower right": (0.85, 0.03, 0.99, 0.30), "lower left": (0.01, 0.03, 0.15, 0.30)}


def _axes_points(ax, markers_only: bool) -> np.ndarray:
    """(n, 2) axes-fraction positions of what ``ax``'s lines draw: the marker positions only, or
    every line densified to about 200 points (a segment crossing a corner counts there)."""
    to_axes = ax.transData + ax.transAxes.inverted()
    out = []
    for ln in ax.lines:
        if getattr(ln, "_skyroute_furniture", False) or not ln.get_visible():
            continue
        xy = np.column_stack([np.asarray(ln.get_xdata(), float), np.asarray(ln.get_ydata(), float)])
        if xy.size == 0:
            continue
        has_marker = ln.get_marker() not in (None, "None", "none", "", " ")
        if markers_only:
            if not has_marker:
                continue
        elif xy.shape[0] > 1:
            t = np.linspace(0, xy.shape[0] - 1, max(200, xy.shape[0]))
            xy = np.column_stack([np.interp(t, np.arange(xy.shape[0]), xy[:, 0]),
                                  np.interp(t, np.arange(xy.shape[0]), xy[:, 1])])
        out.append(to_axes.transform(xy[np.isfinite(xy).all(axis=1)]))
    return np.concatenate(out) if out else np.zeros((0, 2))


def _legend_box(ax) -> tuple[float, float, float, float] | None:
    """The axes-fraction box of ``ax``'s legend (drawn before the furniture), or None."""
    lg = ax.get_legend()
    if lg is None or not lg.get_visible():
        return None
    bb = lg.get_window_extent(ax.figure.canvas.get_renderer()).transformed(ax.transAxes.inverted())
    return (bb.x0, bb.y0, bb.x1, bb.y1)


def _score(box: tuple[float, float, float, float], marks: np.ndarray, verts: np.ndarray,
           legend: tuple[float, float, float, float] | None = None) -> float:
    x0, y0, x1, y1 = box
    if legend is not None and legend[0] < x1 and legend[2] > x0 and legend[1] < y1 and legend[3] > y0:
        return 1e6   # under the legend

    def n_in(p: np.ndarray, pad: float) -> int:
        return int(((p[:, 0] > x0 - pad) & (p[:, 0] < x1 + pad) & (p[:, 1] > y0 - pad)
                    & (p[:, 1] < y1 + pad)).sum()) if p.size else 0

    return 1000.0 * n_in(marks, 0.04) + n_in(verts, 0.0)


def add_map_furniture(ax, *, north: str = "grid north") -> None:
    """A scale bar (a round length in metres of the map's x axis) and a north arrow (the axes are
    map coordinates, so the arrow is ``north``, +y) on map axes, each in the corner that covers
    no marker (start, goal, landing sites), nor the legend, and the fewest line points: the arrow
    preferably upper right, the bar lower left.  Call it after the markers and the legend."""
    x0, x1 = sorted(ax.get_xlim())
    y0, y1 = sorted(ax.get_ylim())
    w, h = x1 - x0, y1 - y0
    length = _nice_length(w)
    marks, verts, legend = _axes_points(ax, True), _axes_points(ax, False), _legend_box(ax)
    order = ("upper right", "upper left", "lower right", "lower left")
    arrow = min(order, key=lambda c: (_score(_ARROW_BOXES[c], marks, verts, legend), order.index(c)))
    ax0, ay0, ax1, ay1 = _ARROW_BOXES[arrow]
    fx = length / w
    bars = {c: b for c, b in {"lower left": (0.03, 0.03, 0.05 + fx, 0.11), "lower right": (0.95 - fx, 0.03, 0.97, 0.11),
                              "upper left": (0.03, 0.89, 0.05 + fx, 0.97), "upper right": (0.95 - fx, 0.89, 0.97, 0.97)
                              }.items() if c != arrow}
    border = ("lower left", "lower right", "upper left", "upper right")
    bar = min(bars, key=lambda c: (_score(bars[c], marks, verts, legend), border.index(c)))
    bx0, by0, _, _ = bars[bar]
    bx, by = x0 + (bx0 + 0.01) * w, y0 + (by0 + 0.02) * h
    furniture = []
    from matplotlib import patheffects

    halo = [patheffects.withStroke(linewidth=5, foreground="white")]   # readable on a dark layer too
    line, = ax.plot([bx, bx + length], [by, by], color="k", lw=3, solid_capstyle="butt", zorder=10,
                    path_effects=halo)
    line._skyroute_furniture = True
    label = f"{length / 1000:g} km" if length >= 1000 else f"{length:g} m"
    furniture.append(ax.text(bx + length / 2, by + 0.015 * h, label, ha="center", va="bottom", fontsize=8, zorder=10,
                             bbox=dict(facecolor="white", alpha=0.6, lw=0, pad=1)))
    xc = 0.5 * (ax0 + ax1)
    furniture.append(ax.annotate("N", xy=(xc, ay1 - 0.04), xytext=(xc, ay1 - 0.17), xycoords="axes fraction",
                                 ha="center", va="center", fontsize=9, fontweight="bold",
                                 arrowprops=dict(arrowstyle="-|>", color="k", lw=1.5), zorder=10))
    furniture.append(ax.text(xc, ay1 - 0.21, north, transform=ax.transAxes, ha="center", va="top", fontsize=6,
                             zorder=10))
    for t in furniture:
        t._skyroute_furniture = True
    ax._skyroute_furniture = {"arrow": arrow, "bar": bar, "line": line}


def all_axes(fig) -> list:
    """Every axes of ``fig``: ``fig.axes`` and their inset axes (the colour bars beside a map
    from :func:`side_colorbar` are insets of the map), depth first."""
    out = []

    def add(ax) -> None:
        out.append(ax)
        for child in getattr(ax, "child_axes", []):
            add(child)

    for ax in fig.axes:
        add(ax)
    return out


def furniture_boxes(ax, renderer=None) -> list:
    """Display boxes of the map furniture :func:`add_map_furniture` drew on ``ax`` (the scale
    bar, its label, the north arrow and its label)."""
    renderer = renderer or ax.figure.canvas.get_renderer()
    out = [t.get_window_extent(renderer) for t in ax.texts if getattr(t, "_skyroute_furniture", False)]
    out += [ln.get_window_extent(renderer) for ln in ax.lines if getattr(ln, "_skyroute_furniture", False)]
    return out


def marker_boxes(fig, renderer=None) -> list[tuple[str, object]]:
    """(label, display box) of every marker the axes of ``fig`` draw (lines with a marker: start,
    goal, landing sites...), each box the marker's size around its position."""
    from matplotlib.transforms import Bbox

    renderer = renderer or fig.canvas.get_renderer()
    out = []
    for ax in all_axes(fig):
        for ln in ax.lines:
            if getattr(ln, "_skyroute_furniture", False) or ln.get_marker() in (None, "None", "none", "", " "):
                continue
            r = 0.5 * ln.get_markersize() * fig.dpi / 72.0
            xy = np.column_stack([np.asarray(ln.get_xdata(), float), np.asarray(ln.get_ydata(), float)])
            xy = xy[np.isfinite(xy).all(axis=1)]
            if not xy.size:
                continue
            box = ax.get_window_extent(renderer)
            for px, py in ax.transData.transform(xy):
                if box.x0 <= px <= box.x1 and box.y0 <= py <= box.y1:
                    out.append((str(ln.get_label()), Bbox.from_extents(px - r, py - r, px + r, py + r)))
    return out


def covered_markers(fig) -> list[str]:
    """Which markers of ``fig`` a legend or the map furniture covers: ``"<legend|furniture> covers
    <marker label>"`` per covered marker; empty when none is."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    marks = marker_boxes(fig, renderer)
    axes = all_axes(fig)
    covers = [("legend", lg.get_window_extent(renderer)) for lg in
              [a.get_legend() for a in axes] + list(fig.legends) if lg is not None and lg.get_visible()]
    covers += [("furniture", b) for a in axes for b in furniture_boxes(a, renderer)]
    return [f"{what} covers {label}" for what, b in covers for label, m in marks if b.overlaps(m)]


def value_range(values) -> tuple[float, float] | None:
    """(min, max) of the finite ``values``, or None when they do not vary (or none is finite): a
    colour bar of such a layer would only show matplotlib's made-up range (e.g. -0.1 .. 0.1)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return None
    lo, hi = float(v.min()), float(v.max())
    return (lo, hi) if hi - lo > 1e-9 * max(1.0, abs(lo), abs(hi)) else None


def uniform_value(values) -> float | None:
    """The one finite value of ``values`` when they do not vary, else (or none finite) None."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return float(v[0]) if v.size and value_range(v) is None else None


def colorbar_or_note(fig, ax, mappable, values, label: str, note: str, note_xy=(0.5, 0.5), **kwargs):
    """A colour bar of ``mappable`` labelled ``label`` when ``values`` vary; otherwise no colour bar
    but ``note`` written on the map (e.g. "no landing sites: landing cost 1 everywhere").
    ``note_xy``: where the note goes [axes fraction]; returns the colour bar or None."""
    if value_range(values) is not None:
        return side_colorbar(fig, ax, mappable, label, **kwargs)
    add_note(ax, note, note_xy)
    return None


def side_colorbar(fig, ax, mappable, label: str, **kwargs):
    """A colour bar right beside ``ax`` itself (an inset axes: it stays next to an equal-aspect
    map however the layout shrinks the map in its cell)."""
    kwargs.pop("shrink", None)
    cax = ax.inset_axes([1.03, 0.04, 0.035, 0.92])
    return fig.colorbar(mappable, cax=cax, label=label, **kwargs)


def add_note(ax, note: str, xy=(0.5, 0.5)) -> None:
    """``note`` in a white box at ``xy`` [axes fraction] of ``ax``, by default its middle (an empty
    or uniform layer says so)."""
    ax.text(*xy, note, transform=ax.transAxes, ha="center", va="center", fontsize=9, zorder=11, wrap=True,
            bbox=dict(facecolor="white", alpha=0.85, edgecolor="0.6", boxstyle="round,pad=0.4"))


def degenerate_colorbars(fig) -> list[str]:
    """Labels of the colour bars of ``fig`` whose image has no varying finite value (the bar's
    range is then made up); empty when every colour bar shows a real range."""
    out = []
    for ax in all_axes(fig):
        cb = getattr(ax, "_colorbar", None)
        if cb is None:
            continue
        arr = cb.mappable.get_array()
        if arr is not None and value_range(np.ma.filled(np.ma.asarray(arr, float), np.nan)) is None:
            out.append(str(cb.ax.get_ylabel() or cb.ax.get_xlabel() or "(unlabelled)"))
    return out


def overlapping_titles(fig) -> list[str]:
    """Axes titles of ``fig`` that run into another axes (a colour bar with its label, a
    neighbouring panel); empty when none does."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    out = []
    axes = all_axes(fig)
    for ax in axes:
        for t in (ax.title, ax._left_title, ax._right_title):
            if not t.get_text().strip() or not t.get_visible():
                continue
            tb = t.get_window_extent(renderer)
            for other in axes:
                if other is ax or not other.get_visible():
                    continue
                ob = other.get_tightbbox(renderer)
                if ob is not None and tb.overlaps(ob):
                    out.append(f"{t.get_text()!r} runs into {other.get_ylabel() or other.get_title() or 'axes'!r}")
    return out


def clipped_texts(fig) -> list[str]:
    """What of ``fig`` is cut off by its canvas: for each axes (colour bars included) whose tight
    box (the drawn tick labels, axis labels, title and legend) leaves the canvas, its labels;
    and every figure-level text that leaves it.  Empty when nothing is cut off."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    W, H = fig.bbox.width, fig.bbox.height

    def out(bb) -> bool:
        return bb is not None and (bb.x0 < -0.5 or bb.y0 < -0.5 or bb.x1 > W + 0.5 or bb.y1 > H + 0.5)

    def cut() -> list[str]:
        found = []
        for ax in fig.axes:
            if ax.get_visible() and out(ax.get_tightbbox(renderer)):
                names = [t for t in (ax.get_title(), ax.get_xlabel(), ax.get_ylabel()) if t.strip()]
                found.append(f"axes {' / '.join(repr(n) for n in names) or '(unlabelled)'}")
        for t in fig.texts:
            if t.get_visible() and str(t.get_text()).strip() and out(t.get_window_extent(renderer)):
                found.append(repr(t.get_text()))
        return found

    found = cut()
    if found and fig.get_layout_engine() is not None:   # a constrained layout settles on its second draw
        fig.canvas.draw()
        found = cut()
    return found


def grow_until_unclipped(fig, tries: int = 4, step: float = 1.12) -> list[str]:
    """Enlarge ``fig`` by ``step`` per try (up to ``tries`` times) while :func:`clipped_texts`
    finds text cut off by the canvas (a constrained layout with an equal-aspect map, a colour
    bar and an outside legend can leave tick labels outside a figure that is too small);
    returns what is still cut off (empty when nothing is)."""
    cut = clipped_texts(fig)
    for _ in range(tries):
        if not cut:
            break
        w, h = fig.get_size_inches()
        fig.set_size_inches(w * step, h * step)
        cut = clipped_texts(fig)
    return cut

