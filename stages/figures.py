"""Figure helpers shared by every map skyroute draws: a scale bar and a north arrow, and a check
that no text of a figure is cut off by its canvas."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["add_map_furniture", "clipped_texts", "image_extent"]


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


def add_map_furniture(ax, *, north: str = "grid north") -> None:
    """A scale bar (lower left, a round length in metres of the map's x axis) and a north arrow
    (upper right; the axes are map coordinates, so the arrow is ``north``, +y) on map axes."""
    x0, x1 = sorted(ax.get_xlim())
    y0, y1 = sorted(ax.get_ylim())
    w, h = x1 - x0, y1 - y0
    length = _nice_length(w)
    bx, by = x0 + 0.05 * w, y0 + 0.05 * h
    ax.plot([bx, bx + length], [by, by], color="k", lw=3, solid_capstyle="butt", zorder=10)
    label = f"{length / 1000:g} km" if length >= 1000 else f"{length:g} m"
    ax.text(bx + length / 2, by + 0.015 * h, label, ha="center", va="bottom", fontsize=8, zorder=10,
            bbox=dict(facecolor="white", alpha=0.6, lw=0, pad=1))
    ax.annotate("N", xy=(0.92, 0.93), xytext=(0.92, 0.80), xycoords="axes fraction", ha="center", va="center",
                fontsize=9, fontweight="bold", arrowprops=dict(arrowstyle="-|>", color="k", lw=1.5), zorder=10)
    ax.text(0.92, 0.76, north, transform=ax.transAxes, ha="center", va="top", fontsize=6, zorder=10)


def clipped_texts(fig) -> list[str]:
    """What of ``fig`` is cut off by its canvas: for each axes (colour bars included) whose tight
    box (the drawn tick labels, axis labels, title and legend) leaves the canvas, its labels;
    and every figure-level text that leaves it.  Empty when nothing is cut off."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    W, H = fig.bbox.width, fig.bbox.height

    def out(bb) -> bool:
        return bb is not None and (bb.x0 < -0.5 or bb.y0 < -0.5 or bb.x1 > W + 0.5 or bb.y1 > H + 0.5)

    found = []
    for ax in fig.axes:
        if ax.get_visible() and out(ax.get_tightbbox(renderer)):
            names = [t for t in (ax.get_title(), ax.get_xlabel(), ax.get_ylabel()) if t.strip()]
            found.append(f"axes {' / '.join(repr(n) for n in names) or '(unlabelled)'}")
    for t in fig.texts:
        if t.get_visible() and str(t.get_text()).strip() and out(t.get_window_extent(renderer)):
            found.append(repr(t.get_text()))
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

