"""Scenario events of the tactical replay (issue 11): parsing, messages with their YAML paths,
the ``--events FILE`` loader, and the map updates through the same (cached) stages."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import shapely
import yaml

from skyroute.pipeline import graph
from skyroute.pipeline.errors import ScenarioError
from skyroute.pipeline.settings import (
    GnssEvent,
    IntruderEvent,
    IntruderUpdateEvent,
    NoFlyEvent,
    Obstacle,
    ObstacleEvent,
    TacticalSettings,
    WindEvent,
    check_event_times,
    load_events_file,
    load_scenario,
    parse_scenario,
    scenario_at,
    scenario_paths,
    with_events,
)

YUMA = Path(__file__).resolve().parents[1] / "catalogs" / "data" / "yuma_2020-01-03.txt"
# helsinki-traffic map coordinates (UTM 35N) [m]: the AOI is x 385400..386454, y 6671390..6673138
X0, Y0 = 385600.0, 6671800.0

EVENTS = [
    {"t_s": 30, "kind": "wind", "uniform_wind": {"speed_mps": 8, "direction_deg": 270}},
    {"t_s": 10, "kind": "intruder", "id": "hawk",
     "waypoints": [[10, 385500, 6671900, 30], [60, 386000, 6671900, 30]]},
    {"t_s": 12, "kind": "intruder", "id": "kite", "via": "v2v", "radius_m": 1.5,
     "position": [385500, 6672000, 40], "velocity_mps": [5, -2, 0.5], "duration_s": 60},
    {"t_s": 20, "kind": "intruder_update", "id": "courier-1",
     "position": [385500, 6671900, 26], "velocity_mps": [0, 5, 0]},
    {"t_s": 20, "kind": "intruder_update", "id": "hawk",
     "waypoints": [[20, 385700, 6671900, 30], [70, 385700, 6672400, 35]]},
    {"t_s": 25, "kind": "gnss", "out_of_service": ["G05", "E11"]},
    {"t_s": 26, "kind": "gnss", "almanacs": [str(YUMA)]},
    {"t_s": 40, "kind": "nofly", "max_agl_m": 100, "end_s": 300,
     "polygon_lonlat": [[24.938, 60.168], [24.942, 60.168], [24.942, 60.170], [24.938, 60.170]]},
    {"t_s": 50, "kind": "obstacle", "polygon": [[X0, Y0], [X0 + 10, Y0], [X0 + 10, Y0 + 10]], "height_agl_m": 45},
]


def _raw(name="helsinki-traffic"):
    p = scenario_paths()[name]
    return yaml.safe_load(p.read_text()), p.parent


def _with(events, name="helsinki-traffic"):
    raw, base = _raw(name)
    raw["events"] = events
    return parse_scenario(raw, base=base)


def _problems(events, name="helsinki-traffic") -> str:
    with pytest.raises(ScenarioError) as e:
        _with(events, name)
    return str(e.value)


# --------------------------------------------------------------------------- parsing
def test_every_kind_parses_and_events_are_sorted_by_time_stably():
    sc = _with(EVENTS)
    assert [e.t_s for e in sc.events] == sorted(e["t_s"] for e in EVENTS)
    kinds = [type(e) for e in sc.events]
    assert kinds == [IntruderEvent, IntruderEvent, IntruderUpdateEvent, IntruderUpdateEvent, GnssEvent, GnssEvent,
                     WindEvent, NoFlyEvent, ObstacleEvent]
    # the two updates at 20 s keep their file order
    assert [e.id for e in sc.events[2:4]] == ["courier-1", "hawk"]
    assert [e.label for e in sc.events[:2]] == ["intruder hawk at 10 s", "intruder kite at 12 s"]
    assert sc.events[6].label == "wind at 30 s"
    assert sc.tactical == TacticalSettings()
    assert sc.tactical.t_rep_s == 5.0 and sc.tactical.tick_s == 0.1
    assert sc.tactical.time_scaling_factors == (0.8, 0.65, 0.5, 0.35, 0.25)


def test_both_track_forms():
    sc = _with(EVENTS)
    hawk, kite = sc.events[0], sc.events[1]
    np.testing.assert_array_equal(hawk.track(), [[10, 385500, 6671900, 30], [60, 386000, 6671900, 30]])
    assert hawk.via == "uspace" and hawk.radius_m == 2.0
    # position + velocity: two waypoints, at the event time and duration_s later (closed form)
    np.testing.assert_allclose(kite.track(), [[12, 385500, 6672000, 40], [72, 385800, 6671880, 70]], atol=1e-9)
    assert kite.via == "v2v" and kite.radius_m == 1.5
    upd = sc.events[2]
    assert upd.radius_m is None  # unchanged
    np.testing.assert_allclose(upd.track()[-1], [320, 385500, 6673400, 26])  # default duration 300 s


def test_nofly_window_defaults_and_polygon_in_map_crs():
    sc = _with(EVENTS)
    nf = next(e for e in sc.events if isinstance(e, NoFlyEvent))
    assert nf.start_s == 40 and nf.end_s == 300 and nf.min_agl_m == 0 and nf.max_agl_m == 100
    nf2 = _with([{"t_s": 7, "kind": "nofly", "polygon": [[X0, Y0], [X0 + 50, Y0], [X0, Y0 + 50]]}]).events[0]
    assert nf2.start_s == 7 and math.isinf(nf2.end_s) and math.isinf(nf2.max_agl_m)
    # lon/lat -> map x/y: against pyproj directly (UTM 35N)
    from pyproj import Transformer

    xy = nf.polygon_xy(sc)
    x, y = Transformer.from_crs(4326, 32635, always_xy=True).transform(24.942, 60.170)
    assert xy.shape == (4, 2)
    assert abs(xy[2, 0] - x) < 0.01 and abs(xy[2, 1] - y) < 0.01
    ob = sc.events[-1]
    np.testing.assert_array_equal(ob.polygon_xy(sc), [[X0, Y0], [X0 + 10, Y0], [X0 + 10, Y0 + 10]])


# --------------------------------------------------------------------------- messages
@pytest.mark.parametrize(("event", "msg"), [
    ({"t_s": 5, "kind": "fog"},
     "events[0]: unknown kind 'fog'; kinds: intruder, intruder_update, wind, gnss, nofly, obstacle"),
    ({"t_s": 5, "polygon": [[0, 0], [1, 0], [0, 1]]}, "events[0]: give the event's kind: intruder, "),
    ({"t_s": 10, "kind": "intruder", "id": "a", "waypoints": [[0, X0, Y0, 30], [40, X0, Y0, 30], [30, X0, Y0, 30]]},
     "events[0].waypoints: times must increase strictly (waypoint 2 at 30 s is not after waypoint 1 at 40 s)"),
    ({"t_s": 10, "kind": "intruder", "id": "a", "waypoints": [[0, X0, Y0, 30]]},
     "events[0].waypoints: a track needs at least 2 waypoints"),
    ({"t_s": 10, "kind": "intruder", "id": "a", "position": [X0, Y0, 30]},
     "events[0]: position [x_m, y_m, alt_agl_m] needs velocity_mps"),
    ({"t_s": 10, "kind": "intruder", "id": "a", "position": [X0, Y0, 30], "velocity_mps": [1, 0, 0],
      "waypoints": [[0, X0, Y0, 30], [40, X0, Y0, 30]]}, "events[0]: give exactly one track form"),
    ({"t_s": 10, "kind": "intruder", "id": "a", "position": [X0, Y0, 30], "velocity_mps": [1, 0, -1]},
     "events[0]: the track goes below the ground (altitude -270 m AGL at 310 s)"),
    ({"t_s": 10, "kind": "intruder", "waypoints": [[0, X0, Y0, 30], [40, X0, Y0, 30]]},
     "events[0].id: required key is missing"),
    ({"t_s": -1, "kind": "gnss", "out_of_service": ["G05"]}, "events[0].t_s: Input should be greater than or equal to 0"),
    ({"t_s": 1, "kind": "gnss", "out_of_service": ["G5", "E11"]}, "events[0].out_of_service: satellite id(s) 'G5' not understood"),
    ({"t_s": 1, "kind": "gnss"}, "events[0]: give out_of_service [G05, ...] and/or almanacs"),
    ({"t_s": 1, "kind": "gnss", "almanacs": ["nothere.txt"]}, "events[0].almanacs: data file not found: "),
    ({"t_s": 1, "kind": "wind"}, "events[0]: give exactly one of uniform_wind"),
    ({"t_s": 1, "kind": "nofly", "polygon": [[X0, Y0], [X0 + 9, Y0 + 9], [X0 + 9, Y0], [X0, Y0 + 9]]},
     "events[0].polygon: the polygon is not valid (Self-intersection"),
    ({"t_s": 1, "kind": "nofly", "polygon": [[X0, Y0], [X0 + 9, Y0 + 9]]},
     "events[0].polygon: a polygon needs at least 3 vertices"),
    ({"t_s": 1, "kind": "nofly", "polygon": [[X0, Y0], [X0 + 9, Y0 + 9], [X0 + 9, Y0]], "polygon_lonlat": [[0, 0], [1, 0], [1, 1]]},
     "events[0]: give exactly one of polygon_lonlat"),
    ({"t_s": 1, "kind": "nofly", "polygon": [[X0, Y0], [X0 + 9, Y0 + 9], [X0 + 9, Y0]], "min_agl_m": 50, "max_agl_m": 20},
     "events[0]: max_agl_m 20 must be above min_agl_m 50"),
    ({"t_s": 40, "kind": "nofly", "polygon": [[X0, Y0], [X0 + 9, Y0 + 9], [X0 + 9, Y0]], "start_s": 10},
     "events[0]: start_s 10 s is before the event time t_s 40 s"),
    ({"t_s": 40, "kind": "nofly", "polygon": [[X0, Y0], [X0 + 9, Y0 + 9], [X0 + 9, Y0]], "end_s": 40},
     "events[0]: end_s 40 s must be after start_s 40 s"),
    ({"t_s": 40, "kind": "obstacle", "polygon": [[0, 0], [9, 9], [9, 0]], "height_agl_m": 30},
     "events[0].polygon: the polygon lies outside the AOI x 385400..386454, y 6671390..6673138 m"),
    ({"t_s": 40, "kind": "obstacle", "polygon_lonlat": [[60.17, 24.94], [60.18, 24.94], [60.18, 24.95]], "height_agl_m": 3},
     "events[0].polygon_lonlat: the polygon lies outside the AOI"),
    ({"t_s": 40, "kind": "obstacle", "polygon": [[X0, Y0], [X0 + 9, Y0 + 9], [X0 + 9, Y0]]},
     "events[0].height_agl_m: required key is missing"),
    ({"t_s": 4, "kind": "intruder_update", "id": "x", "position": [X0, Y0, 30], "velocity_mps": [1, 0, 0]},
     "events[0]: intruder_update of unknown intruder 'x' (known: courier-1, survey-2)"),
    ({"t_s": 4, "kind": "intruder", "id": "courier-1", "position": [X0, Y0, 30], "velocity_mps": [1, 0, 0]},
     "events[0]: intruder 'courier-1' is already known (traffic.intruders); use kind intruder_update"),
])
def test_event_messages_name_their_yaml_path(event, msg):
    out = _problems([event])
    assert msg in out, out


def test_messages_keep_file_positions_when_events_are_unsorted():
    out = _problems([
        {"t_s": 60, "kind": "intruder", "id": "late", "position": [X0, Y0, 30], "velocity_mps": [1, 0, 0]},
        {"t_s": 5, "kind": "wind", "uniform_wind": {"speed_mps": 3, "direction_deg": 0}},
        {"t_s": 30, "kind": "intruder_update", "id": "late", "position": [X0, Y0, 30], "velocity_mps": [1, 0, 0]},
        {"t_s": 40, "kind": "fog"},
    ])
    assert "events[3]: unknown kind 'fog'" in out
    # the update (file position 2) comes before the intruder (file position 0) in time
    raw_ok = [{"t_s": 60, "kind": "intruder", "id": "late", "position": [X0, Y0, 30], "velocity_mps": [1, 0, 0]},
              {"t_s": 30, "kind": "intruder_update", "id": "late", "position": [X0, Y0, 30], "velocity_mps": [1, 0, 0]}]
    out = _problems(raw_ok)
    assert ("events[1]: intruder_update of unknown intruder 'late' (known: courier-1, survey-2); "
            "intruder 'late' appears only later, at 60 s (events[0])") in out
    # an update of an intruder announced earlier in time is fine, whatever the file order
    sc = _with([raw_ok[1] | {"t_s": 70}, raw_ok[0]])
    assert [e.kind for e in sc.events] == ["intruder", "intruder_update"]


def test_tactical_settings_are_validated():
    raw, base = _raw()
    raw["tactical"] = {"t_rep_s": 0, "time_scaling_factors": [0.8, 1.2], "level2_iterations": 0, "tick_s": 0.1}
    with pytest.raises(ScenarioError) as e:
        parse_scenario(raw, base=base)
    s = str(e.value)
    assert "tactical.t_rep_s: Input should be greater than 0" in s
    assert "tactical.time_scaling_factors[1]: Input should be less than 1" in s
    assert "tactical.level2_iterations: Input should be greater than or equal to 1" in s
    raw["tactical"] = {"t_rep_s": 2, "tick_s": 3}
    with pytest.raises(ScenarioError, match=r"tactical: tick_s 3 s must not exceed t_rep_s 2 s"):
        parse_scenario(raw, base=base)
    raw["tactical"] = {"t_rep_s": 2, "seed": 7, "intruder_noise_m": 1.5, "report_latency_s": 0.4}
    t = parse_scenario(raw, base=base).tactical
    assert (t.t_rep_s, t.seed, t.intruder_noise_m, t.report_latency_s) == (2, 7, 1.5, 0.4)


def test_check_event_times_lists_the_events_after_the_mission():
    sc = _with(EVENTS)
    assert check_event_times(sc, 1000.0) == []
    out = check_event_times(sc, 35.0)
    assert len(out) == 2
    assert out[0].startswith("events[7]: nofly event at 40 s comes after the end of the mission at 35.0 s")
    assert out[1].startswith("events[8]: obstacle event at 50 s comes after")


# --------------------------------------------------------------------------- --events FILE
def test_load_events_file_both_layouts_and_with_events(tmp_path):
    almanac = tmp_path / "alm" / "new.txt"
    almanac.parent.mkdir()
    almanac.write_bytes(YUMA.read_bytes())
    events = [e for e in EVENTS if e["kind"] != "gnss"] + [{"t_s": 26, "kind": "gnss", "almanacs": ["alm/new.txt"]}]
    f1, f2 = tmp_path / "a.yaml", tmp_path / "b.yaml"
    f1.write_text(yaml.safe_dump({"events": events}))
    f2.write_text(yaml.safe_dump(events))
    e1, e2 = load_events_file(f1), load_events_file(f2)
    assert e1 == e2 and len(e1) == len(events)
    assert [e.kind for e in e1] == [e["kind"] for e in events]  # file order
    assert e1[-1].almanacs == (almanac.resolve(),)  # relative to the events file
    sc = load_scenario("helsinki-traffic")
    out = with_events(sc, f1)
    assert [e.t_s for e in out.events] == sorted(e["t_s"] for e in events)
    assert out.source_path == sc.source_path and out.traffic == sc.traffic
    # the same events again: the intruders are then known already -> error naming the file
    with pytest.raises(ScenarioError) as e:
        with_events(out, f2)
    s = str(e.value)
    assert str(f2) in s and "(events added to scenario 'helsinki-traffic')" in s
    assert "events[1]: intruder 'hawk' is already known (scenario events[0])" in s


def test_events_file_errors_name_the_file(tmp_path):
    f = tmp_path / "ev.yaml"
    f.write_text("events:\n  - {t_s: 1, kind: fog}\n  - {t_s: 3, kind: intruder_update, id: zz, "
                 "position: [385600, 6671800, 30], velocity_mps: [1, 0, 0]}\n")
    with pytest.raises(ScenarioError, match=r"(?s)ev\.yaml.*events\[0\]: unknown kind 'fog'"):
        load_events_file(f)
    f.write_text("events:\n  - {t_s: 3, kind: intruder_update, id: zz, position: [385600, 6671800, 30], "
                 "velocity_mps: [1, 0, 0]}\n")
    with pytest.raises(ScenarioError, match=r"(?s)ev\.yaml \(events added.*events\[0\]: intruder_update of "
                                            r"unknown intruder 'zz' \(known: courier-1, survey-2\)"):
        with_events(load_scenario("helsinki-traffic"), f)
    f.write_text("wind: 3\n")
    with pytest.raises(ScenarioError, match=r"an events file holds a list of events"):
        load_events_file(f)
    with pytest.raises(ScenarioError, match=r"events file not found"):
        load_events_file(tmp_path / "missing.yaml")


# --------------------------------------------------------------------------- map updates
def _keys(sc) -> dict[str, str]:
    keys: dict[str, str] = {}
    for st in graph.stages_for(sc):
        keys[st.name] = graph.stage_key(st, sc, [keys[d] for d in st.inputs]
                                        + [keys.get(d, "absent") for d in st.optional_inputs])
    return keys


def test_scenario_at_applies_map_events_up_to_t():
    sc = _with(EVENTS)
    assert scenario_at(sc, 5.0) is sc  # intruders only before 25 s: no map changes
    s = scenario_at(sc, 45.0)
    assert s.data.uniform_wind is not None and s.data.uniform_wind.speed_mps == 8 and s.data.wind is None
    assert s.gnss.exclude_satellites == ("G05", "E11")
    assert s.data.almanacs == (YUMA.resolve(),)
    assert s.data.obstacles == ()
    s = scenario_at(sc, 50.0)
    assert s.data.obstacles == (Obstacle(polygon=((X0, Y0), (X0 + 10, Y0), (X0 + 10, Y0 + 10)), height_agl_m=45),)
    assert s.events == sc.events and s.traffic == sc.traffic


def test_wind_event_changes_only_the_wind_keys():
    sc = _with([{"t_s": 30, "kind": "wind", "uniform_wind": {"speed_mps": 8, "direction_deg": 270}},
                {"t_s": 35, "kind": "nofly", "polygon": [[X0, Y0], [X0 + 50, Y0], [X0, Y0 + 50]]},
                {"t_s": 36, "kind": "intruder", "id": "a", "position": [X0, Y0, 30], "velocity_mps": [1, 0, 0]}])
    before, after = _keys(sc), _keys(scenario_at(sc, 40.0))
    assert {"surface", "satellites", "coverage", "environment", "clearance", "traffic", "wind"} <= set(before)
    changed = {n for n in before if before[n] != after[n]}
    assert changed == {"wind", "wind_bounds", "plan"}     # wind_bounds: the A* energy bound of the wind map
    assert _keys(scenario_at(sc, 29.0)) == before


def test_gnss_and_obstacle_events_change_their_stages():
    sc = _with([{"t_s": 30, "kind": "gnss", "out_of_service": ["G05"]}])
    before, after = _keys(sc), _keys(scenario_at(sc, 30.0))
    assert {n for n in before if before[n] != after[n]} == {"satellites", "coverage", "plan"}
    sc = _with([{"t_s": 30, "kind": "obstacle", "polygon": [[X0, Y0], [X0 + 9, Y0], [X0, Y0 + 9]], "height_agl_m": 5}])
    before, after = _keys(sc), _keys(scenario_at(sc, 30.0))
    assert {n for n in before if before[n] != after[n]} == set(before) - {"satellites"}


def _tiny(events=(), **data):
    """A 120 m x 100 m AOI in Helsinki without buildings (flat ground), GPS almanac."""
    raw = {"name": "tiny", "aoi": {"bounds": [385000, 6672000, 385120, 6672100], "crs": "EPSG:32635",
                                   "resolution_m": 2.0, "chunk_cells": 64},
           "data": {"almanacs": [str(YUMA)], **data},
           "mission": {"start": {"x": 385010, "y": 6672010, "alt_agl_m": 30},
                       "goal": {"x": 385110, "y": 6672090, "alt_agl_m": 30},
                       "start_time_utc": "2020-01-03T10:00:00Z"},
           "gnss": {"window_min": 2, "step_min": 1},
           "events": list(events)}
    return parse_scenario(raw)


def _touched_brute_force(grid, poly: shapely.Polygon) -> np.ndarray:
    """Cells whose closed square shares any point with the polygon (shapely, cell by cell)."""
    out = np.zeros(grid.shape, bool)
    r = grid.resolution_m
    for i in range(grid.ny):
        for j in range(grid.nx):
            x0, y1 = grid.x0 + j * r, grid.y1 - i * r
            out[i, j] = shapely.box(x0, y1 - r, x0 + r, y1).intersects(poly)
    return out


def test_burn_obstacles_matches_a_shapely_brute_force_on_sloping_ground():
    from skyroute.stages.grid import Grid
    from skyroute.stages.surface import burn_obstacles

    g = Grid.from_bounds("EPSG:32635", 0, 0, 40, 40, 2.0)
    rng = np.random.default_rng(3)
    terrain = 10.0 + 0.3 * np.arange(g.nx)[None, :] + rng.random(g.shape)  # sloping, rough ground [m]
    surface = terrain + np.where(rng.random(g.shape) < 0.2, 30.0, 0.0)     # some tall buildings
    # a diamond whose west vertex is exactly the grid corner (10, 20): the cells west of it are
    # touched only at that corner; a thin sliver crossing cells obliquely
    diamond = [(10.0, 20.0), (16.0, 14.3), (22.0, 20.0), (16.0, 25.1)]
    sliver = [(25.3, 3.1), (38.7, 33.9), (38.9, 33.8)]
    obs = [(np.array(diamond), 12.5), (np.array(sliver), 40.0)]
    out = burn_obstacles(surface, terrain, g, obs)
    expect = surface.copy()
    for xy, h in obs:
        m = _touched_brute_force(g, shapely.Polygon(xy))
        expect[m] = np.maximum(expect[m], terrain[m].max() + h)
    # the corner-only cells: rows around y = 20 m, column of x in [8, 10]
    corner_cells = [(i, 4) for i in range(g.ny) if abs((g.y1 - i * 2.0) - 20.0) < 1e-9 or abs((g.y1 - (i + 1) * 2.0) - 20.0) < 1e-9]
    assert len(corner_cells) == 2
    d_top = terrain[_touched_brute_force(g, shapely.Polygon(diamond))].max() + 12.5
    for i, j in corner_cells:
        assert out[i, j] == pytest.approx(max(surface[i, j], d_top), abs=1e-9)
        assert out[i, j] > surface[i, j] + 1.0  # really raised
    np.testing.assert_allclose(out, expect, atol=1e-9)
    assert out is not surface and np.all(out >= surface)


def test_obstacle_event_raises_the_surface_stage_output(tmp_path):
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.runner import run_scenario

    # a vertex exactly on the grid corner (385050, 6672050): its neighbour cells touch it at that corner only
    poly = [[385050.0, 6672050.0], [385057.0, 6672043.5], [385063.0, 6672050.0], [385057.0, 6672056.5]]
    sc = _tiny([{"t_s": 12, "kind": "obstacle", "polygon": poly, "height_agl_m": 33.0}])
    cache = Cache(tmp_path / "cache")
    s0 = run_scenario(scenario_at(sc, 10.0), cache=cache, targets=["surface"])["surface"]["surface"].values
    s1 = run_scenario(scenario_at(sc, 12.0), cache=cache, targets=["surface"])["surface"]["surface"].values
    assert np.all(s0 == 0.0)  # flat ground, no buildings
    touched = _touched_brute_force(sc.grid, shapely.Polygon(poly))
    row, col = sc.grid.index_of(385049.0, 6672051.0)  # the north-west corner-only cell
    assert touched[row, col]
    np.testing.assert_allclose(s1[touched], 33.0, atol=1e-5)
    assert np.all(s1[~touched] == 0.0)


def test_gnss_exclusion_removes_exactly_those_satellites(tmp_path):
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.runner import run_scenario
    sc = _tiny([{"t_s": 5, "kind": "gnss", "out_of_service": ["G05", "G10", "E11"]}])
    cache = Cache(tmp_path / "cache")
    with pytest.warns(UserWarning, match="unhealthy"):
        full = run_scenario(sc, cache=cache, targets=["satellites"])["satellites"].load()
        cut = run_scenario(scenario_at(sc, 5.0), cache=cache, targets=["satellites"])["satellites"].load()
    sats_full, sats_cut = set(full["sat"].values), set(cut["sat"].values)
    assert {"G05", "G10"} <= sats_full
    assert sats_full - sats_cut == {"G05", "G10"} and sats_cut < sats_full
    assert cut.attrs["excluded_satellites"] == "G05, G10" and "E11" in cut.attrs["warnings"]
    keep = full.sel(sat=sorted(sats_cut))
    np.testing.assert_allclose(cut["az_deg"].values, keep["az_deg"].values)
    # visibility count and DOP of the satellites left, recomputed independently
    above = keep["el_deg"] >= full.attrs["mask_deg"]
    np.testing.assert_array_equal(cut["n_visible"].values, above.sum("sat").values)
    for k in range(full.sizes["time"]):  # PDOP by least squares geometry: sqrt(trace((G^T G)^-1)[:3])
        vis = above.values[k]
        az, el = np.radians(keep["az_deg"].values[k, vis]), np.radians(keep["el_deg"].values[k, vis])
        G = np.column_stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el), np.ones(vis.sum())])
        Q = np.linalg.inv(G.T @ G)
        assert float(cut["pdop"].values[k]) == pytest.approx(np.sqrt(np.trace(Q[:3, :3])), rel=1e-9)
        assert float(cut["pdop"].values[k]) > float(full["pdop"].values[k])  # fewer satellites: worse DOP
    removed_visible = (full["el_deg"].sel(sat=["G05", "G10"]) >= full.attrs["mask_deg"]).sum("sat").values
    np.testing.assert_array_equal(full["n_visible"].values - cut["n_visible"].values, removed_visible)
