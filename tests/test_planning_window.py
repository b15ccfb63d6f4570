"""The planning window (issue 23, stages/planning/window.py): on a city-scale AOI the strategic
planner reads the maps cropped around the mission.  The window's cells against a brute-force
rectangle test; a windowed plan checked by the validator on the WHOLE AOI's maps (not the
cropped ones) and its f against the plan on the whole AOI; a window that holds no path widens
(counted) until one is found.  Synthetic city (tests/_city.py, procedural, not real data)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import xarray as xr
from _city import city_maps, city_wind, street_point

from skyroute.stages.gridspec import Grid
from skyroute.stages.planning import window
from skyroute.stages.planning.request import Maps, PlanRequest
from skyroute.stages.planning.strategic import plan_strategic, plan_to_dataset
from skyroute.stages.planning.validate import validate_plan
from skyroute.stages.planning.window import crop_maps, planning_windows, window_slices

SIZE = (1600.0, 1200.0)


@pytest.fixture(scope="module")
def city():
    return city_maps(SIZE, 2.0, seed=3)


def _maps(city, nofly=None) -> Maps:
    g = city["grid"]
    zero = g.dataarray(np.zeros(g.shape), "terrain", units="m")
    nf = city["nofly"] if nofly is None else nofly
    return Maps(surface=xr.Dataset({"terrain": zero, "surface": zero}),
                clearance=xr.Dataset({"min_altitude_m": g.dataarray(city["clearance"], "min_altitude_m"),
                                      "nofly": g.dataarray(nf, "nofly")}),
                environment=xr.Dataset({"risk_cost": g.dataarray(city["risk"], "risk_cost"),
                                        "landing_cost": g.dataarray(city["landing"], "landing_cost")}),
                wind=city_wind(city, 3))


def _request(s, e) -> PlanRequest:
    return PlanRequest.of(vehicle="dji-m300-rtk", start_xy=s, start_agl_m=30.0, goal_xy=e, goal_agl_m=30.0,
                          start_time_utc="2020-01-03T10:00:00Z", max_agl_m=80.0, workers=1)


def test_window_cells_brute_force(monkeypatch):
    """Every cell whose square meets the widened box is in the window and every window cell is
    within one cell of it; None below WINDOW_MIN_CELLS or above WINDOW_MAX_FRACTION."""
    monkeypatch.setattr(window, "WINDOW_MIN_CELLS", 100)
    g = Grid.from_bounds("EPSG:32635", 1000.0, 2000.0, 1400.0, 2300.0, 2.0)
    rng = np.random.default_rng(0)
    xc = g.x0 + (np.arange(g.nx) + 0.5) * 2.0
    yc = g.y1 - (np.arange(g.ny) + 0.5) * 2.0
    for _ in range(200):
        s = (rng.uniform(1000, 1400), rng.uniform(2000, 2300))
        e = (rng.uniform(1000, 1400), rng.uniform(2000, 2300))
        m = rng.uniform(0, 60)
        w = window_slices(g, s, e, m)
        lo_x, hi_x = min(s[0], e[0]) - m, max(s[0], e[0]) + m
        lo_y, hi_y = min(s[1], e[1]) - m, max(s[1], e[1]) + m
        touch_c = (xc + 1.0 > lo_x) & (xc - 1.0 < hi_x)
        touch_r = (yc + 1.0 > lo_y) & (yc - 1.0 < hi_y)
        n_box = touch_c.sum() * touch_r.sum()
        if w is None:
            assert n_box > window.WINDOW_MAX_FRACTION * g.nx * g.ny - (touch_c.sum() + touch_r.sum() + 1)
            continue
        rows, cols = w
        inc = np.zeros(g.nx, bool)
        inc[cols] = True
        inr = np.zeros(g.ny, bool)
        inr[rows] = True
        assert (inc | ~touch_c).all() and (inr | ~touch_r).all()          # every touching cell is in
        assert inc.sum() <= touch_c.sum() + 2 and inr.sum() <= touch_r.sum() + 2
    monkeypatch.setattr(window, "WINDOW_MIN_CELLS", g.nx * g.ny + 1)
    assert window_slices(g, (1100, 2100), (1200, 2200), 10.0) is None
    assert planning_windows(g, (1100, 2100), (1200, 2200)) == [None]


def test_crop_keeps_every_value(city):
    """The cropped maps hold the AOI's values at the same map coordinates; the wind on its own
    (400 m) grid keeps the cells around the window."""
    maps = _maps(city)
    rows, cols = slice(100, 300), slice(50, 420)
    c = crop_maps(maps, rows, cols)
    np.testing.assert_array_equal(c.clearance["min_altitude_m"].values, city["clearance"][rows, cols])
    np.testing.assert_array_equal(c.environment["risk_cost"].values, city["risk"][rows, cols])
    np.testing.assert_array_equal(c.surface["x"].values, maps.surface["x"].values[cols])
    assert c.wind.sizes["x"] <= maps.wind.sizes["x"] and c.wind.sizes["y"] <= maps.wind.sizes["y"]
    np.testing.assert_array_equal(c.wind["u"].values, maps.wind["u"].sel(x=c.wind["x"], y=c.wind["y"]).values)


def test_windowed_plan_is_valid_on_the_whole_aoi_and_near_the_whole_aoi_plan(city, monkeypatch):
    s, e = street_point(city, 0.3, 0.3), street_point(city, 0.62, 0.7)
    maps = _maps(city)
    whole = plan_strategic(maps, _request(s, e))
    assert whole.window_xy is None
    monkeypatch.setattr(window, "WINDOW_MIN_CELLS", 1000)
    monkeypatch.setattr(window, "WINDOW_MARGIN_MIN_M", 150.0)
    plan = plan_strategic(maps, _request(s, e))
    assert plan.window_xy is not None and plan.window_widenings == 0
    xmin, ymin, xmax, ymax = plan.window_xy
    assert xmin > city["grid"].x0 and xmax < city["grid"].x0 + SIZE[0]      # a real window
    cand = plan.candidates[0]
    assert plan.step1[0].solved and len(cand.t_s) > 10
    xyz = cand.xyz_m
    assert (xyz[:, 0] >= xmin).all() and (xyz[:, 0] <= xmax).all()
    assert (xyz[:, 1] >= ymin).all() and (xyz[:, 1] <= ymax).all()
    g = city["grid"]
    viol = validate_plan(cand, grid=g, terrain_m=np.zeros(g.shape), vehicle="dji-m300-rtk",
                         clearance_floor_m=city["clearance"], nofly=city["nofly"], min_agl_m=0.0, max_agl_m=80.0,
                         start_xyz=(*s, 30.0), goal_xyz=(*e, 30.0))
    assert viol == []
    f_win, f_whole = cand.f, whole.candidates[0].f
    assert np.isfinite(f_whole) and f_win / f_whole <= 1.03
    ds = plan_to_dataset(plan, g.crs, "EGM96 geoid", "2020-01-03T10:00:00Z")
    assert json.loads(ds.attrs["planning_window_xy_m"]) == pytest.approx(list(plan.window_xy))
    assert ds.attrs["planning_window_widenings"] == 0


def _walled(city, monkeypatch):
    """Small windows (60 m margin) and a mission whose first window a no-fly wall crosses (the
    AOI does not): (start, goal, nofly)."""
    monkeypatch.setattr(window, "WINDOW_MIN_CELLS", 1000)
    monkeypatch.setattr(window, "WINDOW_MARGIN_MIN_M", 60.0)
    s, e = street_point(city, 0.3, 0.45), street_point(city, 0.6, 0.55)
    g = city["grid"]
    xc = g.x0 + (np.arange(g.nx) + 0.5) * 2.0
    yc = g.y1 - (np.arange(g.ny) + 0.5) * 2.0
    wall = (np.abs(xc - 0.5 * (s[0] + e[0])) < 6.0)[None, :] & (np.abs(yc - 0.5 * (s[1] + e[1])) < 200.0)[:, None]
    return s, e, city["nofly"] | wall


def test_a_window_without_a_path_widens(city, monkeypatch):
    """A no-fly wall across the first window (but not across the AOI): the margin doubles until
    the path goes round it; the plan says so and stays valid on the whole AOI."""
    s, e, nofly = _walled(city, monkeypatch)
    g = city["grid"]
    plan = plan_strategic(_maps(city, nofly), _request(s, e))
    assert plan.window_widenings >= 1
    assert any("widened" in w for w in plan.warnings)
    cand = plan.candidates[0]
    assert plan.step1[0].solved
    viol = validate_plan(cand, grid=g, terrain_m=np.zeros(g.shape), vehicle="dji-m300-rtk",
                         clearance_floor_m=city["clearance"], nofly=nofly, min_agl_m=0.0, max_agl_m=80.0,
                         start_xyz=(*s, 30.0), goal_xyz=(*e, 30.0))
    assert viol == []


def test_an_energy_infeasible_plan_does_not_widen(city, monkeypatch):
    """A level whose best path in the window needs more than the battery found a path: the
    window is not widened (the wind and the battery are the same on a wider one)."""
    monkeypatch.setattr(window, "WINDOW_MIN_CELLS", 1000)
    monkeypatch.setattr(window, "WINDOW_MARGIN_MIN_M", 150.0)
    s, e = street_point(city, 0.3, 0.3), street_point(city, 0.62, 0.7)
    req = PlanRequest.of(vehicle="dji-m300-rtk", start_xy=s, start_agl_m=30.0, goal_xy=e, goal_agl_m=30.0,
                         start_time_utc="2020-01-03T10:00:00Z", max_agl_m=80.0, workers=1, battery_reserve_pct=99.9)
    plan = plan_strategic(_maps(city), req)
    assert plan.chosen is None and plan.step1[0].status == "energy_infeasible"
    assert plan.window_xy is not None and plan.window_widenings == 0
    assert not any("widened" in w for w in plan.warnings)


def test_a_fleets_caches_are_kept_per_window(city, monkeypatch):
    """A fleet (heuristic_cache, edge_cache) plans in the window too; its cached heuristic tables and
    STEP I results are keyed by the window: the wall case still widens to a path (the failed first
    window's STEP I result is not served for the wider one), a second plan served from the caches
    is identical to the first, and both stay valid on the whole AOI's maps."""
    s, e, nofly = _walled(city, monkeypatch)
    g = city["grid"]
    hc: dict = {}
    ec: dict = {}
    plans = [plan_strategic(_maps(city, nofly), _request(s, e), heuristic_cache=hc, edge_cache=ec) for _ in range(2)]
    for plan in plans:
        assert plan.window_xy is not None or plan.window_widenings == len(planning_windows(g, s, e)) - 1
        assert plan.window_widenings >= 1 and plan.step1[0].solved
        viol = validate_plan(plan.candidates[0], grid=g, terrain_m=np.zeros(g.shape), vehicle="dji-m300-rtk",
                             clearance_floor_m=city["clearance"], nofly=nofly, min_agl_m=0.0, max_agl_m=80.0,
                             start_xyz=(*s, 30.0), goal_xyz=(*e, 30.0))
        assert viol == []
    np.testing.assert_array_equal(plans[0].step1[0].waypoints, plans[1].step1[0].waypoints)
    assert plans[0].candidates[0].f == plans[1].candidates[0].f
    memo = ec["step1"]
    scopes = {k[-1] for k in memo}
    assert len(scopes) == plans[0].window_widenings + 1            # one STEP I result per window tried
    assert any(not r.solved for r in memo.values()) and any(r.solved for r in memo.values())


def test_cropped_wind_gives_every_point_of_the_window_its_wind_column(city):
    """The wind map on its own 400 m grid, cropped to a window: every point of the window falls
    in a cropped wind cell holding the same (u, v, w) as its cell of the whole map (the
    planner's nearest-column rule, kernels.wind_at)."""
    from skyroute.stages.planning.window import crop_wind

    wind = city_wind(city, 3)
    full = Grid.from_dataarray(wind)
    rng = np.random.default_rng(1)
    for _ in range(20):
        x0, y0 = rng.uniform(full.x0, full.x0 + 1200), rng.uniform(full.y1 - 1150, full.y1 - 450)
        box = (x0, y0, x0 + rng.uniform(10, 400), y0 + rng.uniform(10, 400))
        cw = crop_wind(wind, box)
        cut = Grid.from_dataarray(cw)
        assert cw.sizes["x"] <= wind.sizes["x"] and cw.sizes["y"] <= wind.sizes["y"]
        px, py = rng.uniform(box[0], box[2], 200), rng.uniform(box[1], box[3], 200)
        for g, ds, out in ((full, wind, []), (cut, cw, [])):
            c = np.floor((px - g.x0) / g.resolution_m).astype(int)
            r = np.floor((g.y1 - py) / g.resolution_m).astype(int)
            assert (c >= 0).all() and (c < g.nx).all() and (r >= 0).all() and (r < g.ny).all()
            out.append(ds["u"].values[:, r, c])
            if ds is wind:
                ref = out[0]
            else:
                np.testing.assert_array_equal(out[0], ref)
