"""Issue 35 items 13-15: figures and pages that can be read.

Every figure is drawn from small synthetic inputs and checked on its matplotlib artist tree: no
colour bar of a made-up range over a uniform layer, a note on an empty layer, the terrain shown
in a terrain-only scenario, no title running into a colour bar, no legend or map furniture over
a marker, identical paths told apart, integer mission rows; the pages are checked on their HTML
(and, with chromium, on their layout at 1400 px)."""

from __future__ import annotations

import re
import shutil
import subprocess
from types import SimpleNamespace

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import xarray as xr  # noqa: E402

from skyroute.stages.figures import (  # noqa: E402
    GOAL_STYLE,
    add_map_furniture,
    all_axes,
    covered_markers,
    degenerate_colorbars,
    furniture_boxes,
    overlapping_titles,
)

CRS = "EPSG:32611"
X0, Y0, RES = 382000.0, 3798000.0, 30.0


def _grid_da(values: np.ndarray, name: str) -> xr.DataArray:
    ny, nx = values.shape
    return xr.DataArray(values, dims=("y", "x"), name=name,
                        coords={"x": X0 + RES * (np.arange(nx) + 0.5), "y": Y0 - RES * (np.arange(ny) + 0.5)})


def _terrain_only(ny: int = 40, nx: int = 60):
    """The maps of a terrain-only scenario (San Gabriel): hills, no building, no landing site, no
    no-fly cell, no traffic, uniform risk level 1 and landing cost 1."""
    yy, xx = np.mgrid[0:ny, 0:nx]
    terrain = 600.0 + 300.0 * np.sin(xx / 9.0) * np.cos(yy / 7.0) + 5.0 * xx
    surface = xr.Dataset({"surface": _grid_da(terrain.copy(), "surface"), "terrain": _grid_da(terrain, "terrain")},
                         attrs={"vertical_datum": "EGM96 geoid"})
    env = xr.Dataset({"risk_level": _grid_da(np.ones((ny, nx), np.int8), "risk_level"),
                      "landing_cost": _grid_da(np.ones((ny, nx)), "landing_cost")})
    env = env.assign_coords(site_x=("site", np.zeros(0)), site_y=("site", np.zeros(0)))
    floor = terrain + 10.0 + 60.0 * (np.abs(np.sin(xx / 3.0)) > 0.9)
    clear = xr.Dataset({"nofly": _grid_da(np.zeros((ny, nx), bool), "nofly"),
                        "min_altitude_m": _grid_da(floor, "min_altitude_m")}, attrs={"radius_m": 15.0})
    w = xr.Dataset({"u": _grid_da(np.full((ny, nx), 5.0), "u"), "v": _grid_da(np.zeros((ny, nx)), "v"),
                    "speed": _grid_da(np.full((ny, nx), 5.0), "speed")}).assign_coords(z=50.0)
    start = (X0 + 0.3 * nx * RES, Y0 - 0.3 * ny * RES)
    goal = (X0 + 0.97 * nx * RES, Y0 - 0.04 * ny * RES)     # in the upper right corner: the north arrow's
    return surface, env, clear, (w, "constant", False), start, goal


@pytest.fixture
def captured(monkeypatch):
    """The figures drawn (savefig still writes them), kept open for the checks."""
    figs: list = []
    orig = matplotlib.figure.Figure.savefig

    def keep(self, *a, **k):
        figs.append(self)
        return orig(self, *a, **k)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", keep)
    monkeypatch.setattr(plt, "close", lambda *a, **k: None)
    yield figs
    monkeypatch.undo()
    for f in figs:
        plt.close(f)


# ------------------------------------------------------------------ item 13: maps.png, top view


def test_terrain_only_maps_show_the_terrain_and_notes_not_made_up_colour_bars():
    from skyroute.pipeline.maps import maps_figure

    surface, env, clear, wind, start, goal = _terrain_only()
    fig = maps_figure(surface, env=env, clear=clear, wind=wind, start_xy=start, goal_xy=goal, title="t")
    try:
        assert degenerate_colorbars(fig) == []            # was: building height -0.1 .. 0.1
        labels = [a.get_ylabel() for a in all_axes(fig)]
        assert any(lab.startswith("terrain height [m]") for lab in labels)   # the terrain itself is shown
        notes = " | ".join(t.get_text() for a in fig.axes for t in a.texts)
        assert "no landing sites in this scenario" in notes and "landing cost 1 everywhere" in notes
        assert "no no-fly cells in this scenario" in notes
        assert "no known traffic in this scenario" in notes
        assert not any("landing cost" in lab for lab in labels)   # no colour bar over the uniform cost
        # every panel draws something under its markers (the terrain's hill shade at least)
        assert all(a.images for a in fig.axes[:6])
        assert overlapping_titles(fig) == []              # "r_p = 15.0 m" ran into the colour bar
        assert any("r_p = 15.0 m" in a.get_title() for a in fig.axes)
        assert covered_markers(fig) == []                 # the north arrow was over the goal
    finally:
        plt.close(fig)


def test_goal_is_not_drawn_like_the_landing_sites():
    from skyroute.pipeline.maps import maps_figure

    surface, env, clear, wind, start, goal = _terrain_only()
    lc = np.linspace(0, 1, env["landing_cost"].size).reshape(env["landing_cost"].shape)
    env = env.assign(landing_cost=(("y", "x"), lc)).drop_vars(["site_x", "site_y"])
    env = env.assign_coords(site_x=("site", [X0 + 600.0]), site_y=("site", [Y0 - 600.0]))
    fig = maps_figure(surface, env=env, clear=clear, wind=wind, start_xy=start, goal_xy=goal)
    try:
        lines = {ln.get_label(): ln for a in fig.axes for ln in a.lines}
        site, goal_ln = lines["landing site"], lines["goal"]
        assert (goal_ln.get_marker(), goal_ln.get_markerfacecolor()) != (site.get_marker(), site.get_markerfacecolor())
        assert goal_ln.get_marker() != "*"
        legend = [t.get_text() for lg in fig.legends for t in lg.get_texts()]
        assert legend == ["start", "goal", "landing site"]
        assert covered_markers(fig) == []
    finally:
        plt.close(fig)


def _candidate(label: str, xy: np.ndarray, z: float = 40.0, f: float = 1000.0):
    from skyroute.stages.planning.step3 import Candidate

    n = xy.shape[0]
    t = np.linspace(0.0, 100.0, n)
    xyz = np.column_stack([xy, np.full(n, z)])
    return Candidate(label, 3.0, t, xyz, np.full(n, 30.0), np.full(n, 10.0), 1.0 + 0.1 * np.sin(t), np.full(n, 8),
                     f, 0.0, 0.0, 0.0, f, True, 1.1, 1000.0, 100.0, 0.1)


def _plan_figures(tmp_path, cost):
    from skyroute.stages.grid import Grid
    from skyroute.stages.planning.outputs import _figures

    g = Grid.from_bounds(CRS, X0, Y0 - 1200, X0 + 1800, Y0, RES)
    xmin, ymin, xmax, ymax = g.bounds
    # from the lower left to the upper right corner: under the scale bar and the north arrow
    xy = np.column_stack([np.linspace(xmin + 40, xmax - 30, 50), np.linspace(ymin + 40, ymax - 30, 50)])
    cand = _candidate("D=3", xy)
    ground = np.full(g.shape, 600.0)
    _figures(cand, [cand], g, tmp_path, "EGM96 geoid", ground + 0.0, ground, ground + 20.0,
             np.full(g.shape, cost) if np.isscalar(cost) else cost, "ground risk cost (normalised, 0-1) [-]")
    return cand


def test_top_view_of_a_uniform_risk_map_has_a_note_not_a_colour_bar(tmp_path, captured):
    _plan_figures(tmp_path, 0.0)
    top = captured[0]
    assert degenerate_colorbars(top) == []     # was: a -0.1 .. 0.1 risk colour bar
    assert not [a for a in all_axes(top) if getattr(a, "_colorbar", None) is not None]
    assert any("ground risk cost (normalised, 0-1): 0 everywhere" in t.get_text() for t in top.axes[0].texts)
    assert covered_markers(top) == []          # the arrow was over the goal, the bar over the start


def test_top_view_of_a_varying_risk_map_keeps_its_colour_bar(tmp_path, captured):
    _plan_figures(tmp_path, np.linspace(0, 1, 40 * 60).reshape(40, 60))
    top = captured[0]
    assert [a for a in all_axes(top) if getattr(a, "_colorbar", None) is not None]
    assert degenerate_colorbars(top) == [] and covered_markers(top) == []


def test_profile_legend_is_beside_the_plot_not_in_it(tmp_path, captured):
    _plan_figures(tmp_path, 0.0)
    prof = captured[1]
    prof.canvas.draw()
    r = prof.canvas.get_renderer()
    ax = prof.axes[0]
    assert not ax.get_legend().get_window_extent(r).overlaps(ax.get_window_extent(r))


def test_sigma_p_caption_describes_what_is_drawn(tmp_path, captured):
    from skyroute.pipeline.report import FIGURES

    cand = _plan_figures(tmp_path, 0.0)
    sig = captured[2]
    dashed = [ln for ln in sig.axes[0].lines if ln.get_linestyle() == "--"]
    caption = next(c for _, g, c in FIGURES if g == "sigma_p.png")
    assert not np.isfinite(cand.dp_max_m) and dashed == []    # a plan read back has no dp_max: no dashed line
    assert "dashed" not in caption or "where the plan records it" in caption   # was: "(dp_max dashed)"


def test_scale_bar_and_north_arrow_avoid_the_markers():
    fig, ax = plt.subplots(figsize=(5, 4))
    ax.set_xlim(0, 1000)
    ax.set_ylim(0, 800)
    ax.plot(975, 770, **GOAL_STYLE, label="goal")        # upper right: where the arrow used to be
    ax.plot(70, 50, "o", ms=9, label="start")              # lower left: where the bar used to be
    ax.legend(loc="lower right")                            # the bar's next choice: taken by the legend
    add_map_furniture(ax)
    try:
        assert covered_markers(fig) == []
        assert ax._skyroute_furniture["arrow"] != "upper right" and ax._skyroute_furniture["bar"] != "lower left"
        fig.canvas.draw()
        r = fig.canvas.get_renderer()
        legend = ax.get_legend().get_window_extent(r)
        assert not any(b.overlaps(legend) for b in furniture_boxes(ax, r))
    finally:
        plt.close(fig)


# ------------------------------------------------------------------ item 14: compare.png, fleet.png


def test_compare_legend_leaves_the_paths_and_identical_paths_are_told_apart(tmp_path, captured):
    from skyroute.pipeline.compare import CompareRow, _figure

    surf = _grid_da(np.full((40, 60), 5.0) + np.arange(60) * 0.1, "surface")
    surf.attrs["vertical_datum"] = "NAP"
    xy = np.column_stack([np.linspace(X0 + 60, X0 + 1700, 40), np.linspace(Y0 - 1100, Y0 - 100, 40)])
    xyz = np.column_stack([xy, np.full(40, 30.0)])
    vals = {"f_m": 1000.0, "length_m": 1900.0, "min_clearance_m": 6.0}
    rows = [CompareRow("astar", dict(vals), xyz), CompareRow("bitstar", dict(vals), xyz + [60, -60, 0]),
            CompareRow("potential", dict(vals), xyz.copy())]
    _figure(rows, {"surface": {"surface": surf}}, tmp_path / "compare.png", "t")
    fig = captured[0]
    assert covered_markers(fig) == []                 # the legend covered the start of every path
    top = fig.axes[0]
    lines = {ln.get_label(): ln for ln in top.lines}
    pot = next(ln for lab, ln in lines.items() if lab.startswith("potential"))
    assert "same path as astar" in pot.get_label() and pot.get_linestyle() != "-"
    bit = next(ln for lab, ln in lines.items() if lab.startswith("bitstar"))
    assert "same path" not in bit.get_label() and bit.get_linestyle() == "-"   # 85 m apart: another path


def test_fleet_rows_are_whole_missions_and_the_paths_are_numbered(tmp_path, captured):
    from skyroute.pipeline.fleet_outputs import plot_fleet

    surf = _grid_da(np.full((40, 60), 3.0), "surface")
    outs = []
    for i in range(20):
        y = Y0 - 100 - 50 * i
        xyz = np.array([[X0 + 100, y, 30.0], [X0 + 1500, y - 20, 30.0]])
        vols = [SimpleNamespace(t_start_s=60.0 * i, t_end_s=60.0 * i + 300.0)]
        outs.append(SimpleNamespace(task=SimpleNamespace(id=f"m{i:02d}"), status="accepted" if i % 3 else "delayed",
                                    attempt=SimpleNamespace(xyz_m=xyz, volumes=vols)))
    res = SimpleNamespace(outcomes=outs)
    plot_fleet(res, SimpleNamespace(name="synthetic"), {"surface": {"surface": surf}}, tmp_path / "fleet.png")
    fig = captured[0]
    ax, bx = fig.axes[0], fig.axes[1]
    ticks = bx.get_yticks()
    assert np.allclose(ticks, np.round(ticks)) and len(ticks) == 20    # was: 2.5, 7.5 ...
    assert [t.get_text() for t in bx.get_yticklabels()][:2] == ["0: m00", "1: m01"]
    labels = [int(n) for t in ax.texts for n in t.get_text().replace("\n", " ").split(", ")]
    assert sorted(labels) == list(range(20))            # every path labelled with its row


# ------------------------------------------------------------------ item 15: report.html, plan.html, fly.html


def test_wide_tables_scroll_and_long_reasons_wrap():
    from skyroute.pipeline.report import PAGE, _table

    reason = "level D=2: no path within the time budget; the coverage floor is above the ceiling " * 3
    html = _table(["mission", "status", *[f"col{i}" for i in range(18)], "reason"],
                  [[f"m{i}", "rejected", *range(18), reason] for i in range(30)], text_cols=(0, 1, 20))
    assert html.startswith('<div class="table-wrap long"><table')
    assert html.count('<td class="wrap">') == 30 and html.count('<td class="text">') == 60
    css = PAGE.template
    assert re.search(r"\.table-wrap \{[^}]*overflow-x: auto", css)
    assert re.search(r"td\.wrap \{[^}]*min-width: 22em", css)


def _tiny_grid():
    from skyroute.stages.grid import Grid

    return Grid.from_bounds("EPSG:32635", 385400, 6671400, 385600, 6671560, 4.0)


def test_plan_map_has_a_colour_legend_for_the_coverage_layers():
    from skyroute.pipeline.planmap import plan_map_html

    g = _tiny_grid()
    xy = np.column_stack([np.linspace(385420, 385580, 10), np.linspace(6671420, 6671540, 10)])
    cand = _candidate("D=3", xy)
    floor = np.full(g.shape, 30.0)
    floor[:5] = np.inf
    html = plan_map_html(title="t", grid=g, chosen=cand, candidates=[cand], coverage={3.0: floor},
                         terrain_m=np.zeros(g.shape), max_agl_m=120.0)
    legend = re.search(r'<div id="map-legend".*?</div></div>', html, re.S)
    assert legend, "no legend on plan.html"
    text = re.sub(r"<[^>]+>", " ", legend.group(0))
    assert "coverage floor per D_j [m above ground]" in text and "120" in text and "unflyable" in text
    assert "linear-gradient" in legend.group(0) and "chosen plan D=3" in text


def _lonlat(g, x, y):
    from pyproj import Transformer

    return list(Transformer.from_crs(g.crs, 4326, always_xy=True).transform(x, y))


def test_fly_map_has_buildings_start_goal_legend_and_labelled_intruders():
    from skyroute.pipeline.planmap import fly_map_html

    g = _tiny_grid()
    a, b, c = _lonlat(g, 385420, 6671420), _lonlat(g, 385500, 6671480), _lonlat(g, 385580, 6671540)
    flown = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "geometry": {"type": "LineString", "coordinates": [a + [30], b + [30]]},
         "properties": {"part": "strategic"}},
        {"type": "Feature", "geometry": {"type": "LineString", "coordinates": [b + [30], c + [30]]},
         "properties": {"part": "L1"}}]}
    intr = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "geometry": {"type": "LineString", "coordinates": [c + [30], a + [30]]},
         "properties": {"feature": "intruder", "id": "courier-1"}}]}
    height = np.zeros(g.shape)
    height[10:20, 10:20] = 15.0
    html = fly_map_html("t", flown, intr, None, {"grid": g, "height_m": height, "terrain_m": np.zeros(g.shape),
                                                 "coverage": {3.0: np.full(g.shape, 25.0)}, "max_agl_m": 100.0,
                                                 "shown_threshold": 3.0, "start": a, "goal": c})
    legend = re.sub(r"<[^>]+>", " ", re.search(r'<div id="map-legend".*?</div></div>', html, re.S).group(0))
    for row in ("start", "goal", "flown: strategic", "flown: L1", "buildings", "intruders", "coverage floor"):
        assert row in legend, row
    assert '"buildings (footprints)"' in html and html.count("image/png;base64") >= 2   # buildings + coverage
    assert re.search(r'"permanent": true', html) and "courier-1" in html               # the intruder labelled
    assert html.count('"tooltip"') >= 0 and "goal" in html


@pytest.mark.skipif(shutil.which("chromium") is None, reason="no chromium on PATH")
def test_report_page_layout_at_1400_px(tmp_path):
    """A wide 30-row table with long reasons scrolls inside the page; a figure wider than the
    page is shrunk and opens full size on a click (the page stays self-contained)."""
    from PIL import Image

    from skyroute.pipeline.report import PAGE, _figure, _table

    png = tmp_path / "maps.png"
    Image.new("RGB", (2400, 1600), (200, 220, 240)).save(png)
    reason = "no flyable level: the coverage floor is above the ceiling everywhere along the path " * 2
    table = _table(["mission", *[f"a_long_column_name_{i}" for i in range(16)], "reason"],
                   [[f"m{i}", *[1234.5678] * 16, reason] for i in range(20)], text_cols=(0, 17))
    probe = """<script>window.addEventListener("load", function () { setTimeout(function () {
      var td = document.querySelector("td.wrap"), box = td.getBoundingClientRect();
      document.body.setAttribute("data-probe", [document.documentElement.scrollWidth,
        Math.round(box.width), Math.round(box.height)].join(",")); }, 50); });</script>"""
    page = PAGE.substitute(title="t", body=table + _figure(png, "maps") + probe, n_images=1)
    (tmp_path / "r.html").write_text(page)
    proc = subprocess.run([shutil.which("chromium"), "--headless", "--no-sandbox", "--disable-gpu",
                           "--disable-background-networking", "--disable-component-update", "--disable-sync",
                           "--no-first-run", "--virtual-time-budget=3000", "--window-size=1400,2400", "--dump-dom",
                           (tmp_path / "r.html").as_uri()], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    width, td_w, td_h = (int(v) for v in re.search(r'data-probe="(\d+),(\d+),(\d+)"', proc.stdout).groups())
    assert width <= 1400                    # the page does not run off at 1400 px: the table scrolls in its box
    assert td_w >= 250 and td_h < 200       # the reasons wrap in a readable column (was 50 px x 9000 px)
    assert 'data-images-zoomable="1"' in proc.stdout and "click the image for full size" in proc.stdout
