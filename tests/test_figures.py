"""The figure checks themselves: a clipped label is found; the map furniture is drawn."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from skyroute.stages.figures import _nice_length, add_map_furniture, clipped_texts  # noqa: E402


def test_clipped_label_is_found_and_a_fitted_one_is_not():
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.set_ylabel("a label far too long to fit beside such a small figure, cut off at both ends " * 2)
    assert clipped_texts(fig)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(4, 3))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    fig.tight_layout()
    assert clipped_texts(fig) == []
    plt.close(fig)


def test_scale_bar_has_a_round_length_and_the_map_a_north_arrow():
    assert [_nice_length(w) for w in (1000, 2600, 87, 40000)] == [200, 500, 10, 5000]
    fig, ax = plt.subplots()
    ax.set_xlim(385400, 386450)
    ax.set_ylim(6671400, 6673150)
    add_map_furniture(ax)
    texts = [t.get_text() for t in ax.texts]
    assert "200 m" in texts and "N" in texts and "grid north" in texts
    bar = ax.lines[-1].get_xdata()
    assert abs((bar[1] - bar[0]) - 200) < 1e-9
    plt.close(fig)


def test_image_extent_is_the_outer_cell_edges():
    import numpy as np

    from skyroute.stages.figures import image_extent
    from skyroute.stages.grid import Grid

    g = Grid.from_bounds("EPSG:32635", 100, 200, 160, 240, 4.0)
    da = g.dataarray(np.zeros(g.shape), "z")
    xmin, ymin, xmax, ymax = g.bounds
    assert image_extent(da) == (xmin, xmax, ymin, ymax)
