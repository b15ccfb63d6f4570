"""Issue 34: mission points checked at the front door, the antimeridian in the pilot exports, and
hand-edited summaries read strictly.

* start == goal and a start on the grid's east / south edge are refused when the scenario is
  loaded (before any map stage), naming ``mission.start`` / ``mission.goal`` and what works;
  the edge rule is checked against :meth:`Grid.index_of` (the planner's own cell lookup);
* a path across longitude 180 in EPSG:32660 (x 833-835 km near the equator: lon 179.99 ->
  -179.99): plan.geojson feature 0 stays one continuous LineString, the GeoPackage's layers are
  continuous and small, KML / QGC / F3548 longitudes are in [-180, 180], every intent volume is
  the small polygon (its span measured on longitudes taken modulo 360) and the intent contains
  the whole trajectory;
* a real ``skyroute plan`` folder whose summary.json is corrupted by hand (``"f_m": "NaN"``,
  ``"files": 5``, ``"plan": []``, ``"warnings": {}``, a nested wrong type) gives exactly one
  ``error:`` line from ``skyroute report`` and ``skyroute diff`` naming the folder, the key and
  the expected type; no traceback.
"""

from __future__ import annotations

import json
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from pyproj import Transformer

from skyroute.pipeline.cli import main
from skyroute.pipeline.errors import InputError, ScenarioError

DATA = Path(__file__).resolve().parents[1] / "catalogs" / "data"

SCENARIO = f"""
name: strict-points
aoi: {{crs: EPSG:32611, bounds: [383010, 3794010, 385980, 3796980], resolution_m: 30.0}}
data:
  terrain: {{path: {DATA}/srtm_bigtujunga30m_utm11.tif, vertical_datum: EGM96 geoid}}
  risk_default_level: 1
  almanacs: [{DATA}/yuma_2020-01-03.txt]
mission:
  start: {{x: START_X, y: START_Y, alt_agl_m: 60}}
  goal: {{x: GOAL_X, y: GOAL_Y, alt_agl_m: GOAL_ALT}}
  start_time_utc: 2020-01-03T18:00:00Z
constraints: {{min_altitude_agl_m: 10, max_altitude_agl_m: 80}}
planner: {{step_cells: 4}}
"""


def _scenario(tmp_path: Path, start=(383500, 3796200), goal=(384800, 3796600), goal_alt=60, name="s.yaml") -> Path:
    text = (SCENARIO.replace("START_X", str(start[0])).replace("START_Y", str(start[1]))
            .replace("GOAL_X", str(goal[0])).replace("GOAL_Y", str(goal[1])).replace("GOAL_ALT", str(goal_alt)))
    p = tmp_path / name
    p.write_text(text)
    return p


# ------------------------------------------------------------------ 1, 2: mission points


def test_start_equal_goal_is_refused_at_load(tmp_path):
    from skyroute.pipeline.settings import load_scenario

    with pytest.raises(ScenarioError) as exc:
        load_scenario(_scenario(tmp_path, goal=(383500, 3796200)))
    text = "\n".join(exc.value.problems)
    assert "mission.goal" in text and "mission.start" in text and "step1_waypoints" not in text
    assert "no flight to plan" in text
    # the same point at another altitude is a vertical flight: accepted
    load_scenario(_scenario(tmp_path, goal=(383500, 3796200), goal_alt=70, name="v.yaml"))
    # two points in one cell plan (checked by hand: `skyroute plan` flies 11 m): accepted at load
    load_scenario(_scenario(tmp_path, goal=(383510, 3796205), name="c.yaml"))


def test_start_equal_goal_cli_exits_2_before_the_maps(tmp_path):
    sc = _scenario(tmp_path, goal=(383500, 3796200))
    res = CliRunner().invoke(main, ["plan", str(sc), "--out", str(tmp_path / "o"), "--cache-dir", str(tmp_path / "c")])
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output and res.output.count("error:") == 1
    assert "mission.goal" in res.output and "step1_waypoints" not in res.output
    assert not (tmp_path / "c").exists() or not any((tmp_path / "c").rglob("*.zarr"))   # no map was made


@pytest.mark.parametrize("start, edge", [((385980, 3795000), "east edge"), ((384000, 3794010), "south edge"),
                                         ((385980, 3794010), "east and south edges")])
def test_start_on_the_east_or_south_edge_is_refused_with_the_bounds(tmp_path, start, edge):
    from skyroute.pipeline.settings import load_scenario

    with pytest.raises(ScenarioError) as exc:
        load_scenario(_scenario(tmp_path, start=start))
    (p,) = [p for p in exc.value.problems if p.startswith("mission.start")]
    assert edge in p and "383010..385980" in p and "3794010..3796980" in p
    assert "x < 385980" in p and "y > 3794010" in p


def test_start_on_the_west_or_north_edge_is_accepted(tmp_path):
    from skyroute.pipeline.settings import load_scenario

    sc = load_scenario(_scenario(tmp_path, start=(383010, 3796980)))     # the north-west corner: cell (0, 0)
    assert sc.grid.index_of(383010, 3796980) == (0, 0)


def test_outside_the_snapped_grid_is_refused(tmp_path):
    """aoi.bounds off the lattice: the grid snaps inward, a point on the given bound is outside
    it, and the message gives the grid's actual bounds."""
    from skyroute.pipeline.settings import load_scenario

    p = _scenario(tmp_path, start=(383015, 3796200))
    p.write_text(p.read_text().replace("bounds: [383010,", "bounds: [383015,"))
    with pytest.raises(ScenarioError) as exc:
        load_scenario(p)
    (msg,) = [m for m in exc.value.problems if m.startswith("mission.start")]
    assert "outside the AOI's planning grid x 383040..385980" in msg and "383040 <= x < 385980" in msg


def test_edge_rule_matches_the_planner_cell_lookup():
    """mission_point_problem accepts exactly the points Grid.index_of puts in a cell."""
    from skyroute.pipeline.settings.checks import mission_point_problem
    from skyroute.stages.gridspec import Grid

    g = Grid.from_bounds("EPSG:32611", 1000.0, 2000.0, 1300.0, 2210.0, 30.0, inward=True)
    xmin, ymin, xmax, ymax = g.bounds
    rng = np.random.default_rng(3)
    xs = np.r_[xmin, xmax, xmin - 1e-6, xmax - 1e-6, rng.uniform(xmin - 40, xmax + 40, 300)]
    ys = np.r_[ymin, ymax, ymin + 1e-6, ymax + 1e-6, rng.uniform(ymin - 40, ymax + 40, 300)]
    for x in xs:
        for y in ys[::7]:
            r, c = g.index_of(x, y)
            in_cell = bool(0 <= r < g.ny and 0 <= c < g.nx)
            assert (mission_point_problem(g, float(x), float(y)) == "") == in_cell, (x, y)


# ------------------------------------------------------------------ 3: the antimeridian

CRS = "EPSG:32660"     # UTM 60N: central meridian 177 E; x 833.9 km at the equator is lon 180


def _path(n: int = 201):
    """A 2 km eastward path at y 10 km: lon 179.991 -> -179.991 (x 833 -> 835 km), 10 m/s."""
    t = np.linspace(0.0, 200.0, n)
    x = 833000.0 + 10.0 * t
    y = 10000.0 + 50.0 * np.sin(t / 40.0)
    z = 100.0 + 0.1 * t
    return t, np.column_stack([x, y, z])


def _lonlat(xyz):
    lon, lat = Transformer.from_crs(CRS, 4326, always_xy=True).transform(xyz[:, 0], xyz[:, 1])
    return np.asarray(lon), np.asarray(lat)


def test_path_really_crosses_the_antimeridian():
    lon, _ = _lonlat(_path()[1])
    assert lon.max() > 179.99 and lon.min() < -179.99      # the wrapped values jump by ~360


def test_plan_geojson_line_is_continuous():
    from skyroute.stages.planning.outputs import plan_geojson
    from skyroute.stages.planning.step3 import Candidate

    t, p = _path()
    cand = Candidate("D=2", 2.0, t, p, np.full(t.size, 60.0), np.full(t.size, 10.0), np.full(t.size, 1.0),
                     np.full(t.size, 8), 1.0, 0.0, 1.0, 1.0, 3.0, True, 1.0, 1000.0, 200.0, 0.1,
                     waypoints=p[[0, 100, -1]], segment_times_s=np.array([100.0, 100.0]))
    gj = plan_geojson(cand, CRS, "2020-01-03T00:00:00Z", "EGM96 geoid")
    f0 = gj["features"][0]
    assert f0["geometry"]["type"] == "LineString"
    c = np.asarray(f0["geometry"]["coordinates"])
    assert c.shape == (t.size, 3)
    assert np.max(np.abs(np.diff(c[:, 0]))) < 0.001                 # 10 m steps: no 360 deg jump
    lon, lat = _lonlat(p)
    np.testing.assert_allclose(np.mod(c[:, 0], 360.0), np.mod(lon, 360.0), atol=1e-9)   # the same places
    np.testing.assert_allclose(c[:, 1], lat)
    assert -180.0 <= c[0, 0] <= 180.0 and c[:, 0].max() > 180.0
    assert f0["properties"]["crosses_antimeridian"] is True
    w = np.asarray(gj["features"][1]["geometry"]["coordinates"])
    assert np.max(np.abs(w[:, 0] - c[0, 0])) < 0.05                 # the waypoints in the same frame


def test_kml_and_qgc_longitudes_in_range():
    from skyroute.stages.exports import KML_NS, continuous_lon, plan_kml, qgc_plan

    t, p = _path()
    lon, lat = _lonlat(p)
    ulon = continuous_lon(lon)
    doc = plan_kml(ulon, lat, p[:, 2], [f"2020-01-03T00:00:{i % 60:02d}Z" for i in range(t.size)], "x")
    coords = ET.fromstring(doc.split("\n", 1)[1]).find(f".//{{{KML_NS}}}LineString/{{{KML_NS}}}coordinates").text
    klon = np.array([float(v.split(",")[0]) for v in coords.split()])
    assert np.all(np.abs(klon) <= 180.0)
    np.testing.assert_allclose(np.mod(klon, 360), np.mod(lon, 360), atol=1e-8)
    plan = qgc_plan(ulon, lat, p[:, 2] - 100.0, 10.0, cruise_speed_mps=10.0)
    qlon = np.array([it["params"][5] for it in plan["mission"]["items"]])
    assert np.all(np.abs(qlon) <= 180.0) and abs(plan["mission"]["plannedHomePosition"][1]) <= 180.0


@pytest.fixture(scope="module")
def intent():
    from skyroute.stages.intents import PolylineTrajectory, intent_details, plan_volumes

    t, p = _path()
    vols = plan_volumes(PolylineTrajectory(t, p), 0.0, t, np.full(t.size, 1.0), lambda q: q[:, 2],
                        vehicle_radius_m=0.5, max_volume_s=10.0)
    return intent_details(vols, CRS, "2020-01-03T00:00:00Z")


def test_intent_volumes_are_small_and_contain_the_path(intent):
    import pandas as pd

    from skyroute.stages.intents import intent_conformance, parse_intent

    parse_intent(intent)
    across = 0
    for v in intent["volumes"]:
        lng = np.array([q["lng"] for q in v["volume"]["outline_polygon"]["vertices"]])
        assert np.all(np.abs(lng) <= 180.0)                          # F3548 LatLngPoint
        assert np.ptp(np.mod(lng, 360.0)) < 0.01                     # ~20 m wide near lon 180, never the globe
        across += bool(lng.max() > 179 and lng.min() < -179)
    assert across >= 1                                               # some volume straddles lon 180
    t, p = _path(2001)
    lon, lat = _lonlat(p)
    times = pd.Timestamp("2020-01-03T00:00:00Z") + pd.to_timedelta(t, unit="s")
    assert intent_conformance(intent, lon, lat, p[:, 2], times) == 1.0


def test_parse_intent_refuses_a_polygon_spanning_half_the_globe(intent):
    from skyroute.stages.intents import parse_intent

    bad = json.loads(json.dumps(intent))
    bad["volumes"][0]["volume"]["outline_polygon"]["vertices"] = [
        {"lng": -100.0, "lat": 0.0}, {"lng": 0.0, "lat": 1.0}, {"lng": 100.0, "lat": 0.0}]
    with pytest.raises(InputError, match="volume 0: the polygon's edges .* go once around the globe"):
        parse_intent(bad)
    bad["volumes"][0]["volume"]["outline_polygon"]["vertices"] = [
        {"lng": lo, "lat": la} for lo, la in ((0.0, 0.0), (170.0, 0.0), (-60.0, 0.0), (-60.0, 1.0), (170.0, 1.0),
                                              (0.0, 1.0))]
    with pytest.raises(InputError, match="volume 0: the polygon spans 300.0 deg of longitude"):
        parse_intent(bad)
    bad["volumes"][0]["volume"]["outline_polygon"]["vertices"] = [
        {"lng": 181.0, "lat": 0.0}, {"lng": 181.1, "lat": 1.0}, {"lng": 181.0, "lat": 1.0}]
    with pytest.raises(InputError, match=r"longitudes must be in \[-180, 180\]"):
        parse_intent(bad)


def test_geopackage_layers_are_continuous(tmp_path, intent):
    import shapely
    from pyogrio.raw import read

    from skyroute.stages.exports import write_plan_gpkg

    def geoms(path, layer):
        return shapely.from_wkb(read(path, layer=layer)[2])

    t, p = _path()
    lon, lat = _lonlat(p)
    wl, wa = lon[[0, 100, -1]], lat[[0, 100, -1]]
    cx, cy = _lonlat(np.array([[833000.0, 9000.0, 0], [835000.0, 9000.0, 0], [835000.0, 11000.0, 0],
                               [833000.0, 11000.0, 0]]))
    west, east = cx[0], cx[1]                     # (west, south, east, north): east < west across 180
    poly = shapely.Polygon([(179.99995, 0.0901), (180.00005, 0.0901), (180.00005, 0.0902)])
    bld = shapely.transform(poly, lambda xy: np.column_stack([np.where(xy[:, 0] > 180, xy[:, 0] - 360, xy[:, 0]),
                                                                 xy[:, 1]]))
    out = write_plan_gpkg(tmp_path / "plan.gpkg", lon_deg=lon, lat_deg=lat, z_m=p[:, 2], vertical_datum="EGM96 geoid",
                          times_utc=["2020-01-03T00:00:00Z"] * t.size, label="D=2",
                          waypoints_lonlat_z=np.column_stack([wl, wa, p[[0, 100, -1], 2]]),
                          waypoints_rel_m=[60.0, 60.0, 60.0], intent=intent,
                          aoi_lonlat=(west, min(cy), east, max(cy)),
                          buildings=([bld], np.array([7]), np.array([12.0])))
    line = geoms(out, "plan")[0]
    x = np.asarray(line.coords)[:, 0]
    assert np.max(np.abs(np.diff(x))) < 0.001 and x.max() > 180.0
    for layer, width in (("intents", 0.01), ("aoi", 0.05), ("map_buildings", 0.001), ("waypoints", 0.05)):
        b = shapely.bounds(geoms(out, layer))
        assert np.all(b[:, 2] - b[:, 0] < width), (layer, b)
        assert np.all(np.abs(b[:, [0, 2]] - x[0]) < 0.05), (layer, b)   # beside the line, not across the globe


# ------------------------------------------------------------------ 4: hand-edited summaries


@pytest.fixture(scope="module")
def plan_folder(tmp_path_factory):
    """One real `skyroute plan` folder of the small DEM scenario (~10 s once)."""
    tmp = tmp_path_factory.mktemp("strict-summary")
    sc = _scenario(tmp)
    res = CliRunner().invoke(main, ["plan", str(sc), "--out", str(tmp / "good"), "--cache-dir", str(tmp / "c"), "-q"])
    assert res.exit_code == 0, res.output
    return tmp / "good"


def _corrupt(folder: Path, tmp_path: Path, edit) -> Path:
    bad = tmp_path / "bad"
    shutil.copytree(folder, bad)
    doc = json.loads((bad / "summary.json").read_text())
    edit(doc)
    (bad / "summary.json").write_text(json.dumps(doc))
    return bad


def _set(*path_and_value):
    *path, value = path_and_value

    def edit(doc):
        d = doc
        for k in path[:-1]:
            d = d[k]
        d[path[-1]] = value
    return edit


@pytest.mark.parametrize("edit, key, expected", [
    (_set("plan", "f_m", "NaN"), "plan.f_m", "a number or null"),
    (_set("files", 5), "files", "expected a list"),
    (_set("plan", []), "plan", "expected an object"),
    (_set("warnings", {}), "warnings", "expected a list"),
    (_set("plan", "reasons", [1]), "plan.reasons[0]", "expected a string"),
    (_set("plan", "provenance", "weights", ["heavy"]), "plan.provenance.weights[0]", "expected a number"),
    (_set("stages", [{"name": "plan", "cache_hit": "yes"}]), "stages[0].cache_hit", "expected true or false"),
    (_set("command", None), "command", "expected a string"),
])
def test_corrupted_summary_is_one_error_line(plan_folder, tmp_path, edit, key, expected):
    bad = _corrupt(plan_folder, tmp_path, edit)
    r = CliRunner()
    for args in (["report", str(bad), "--no-maps"], ["diff", str(plan_folder), str(bad), "--no-maps"],
                 ["diff", str(bad), str(plan_folder), "--no-maps"]):
        res = r.invoke(main, args)
        assert res.exit_code == 2, (args, res.output)
        assert "Traceback" not in res.output and not isinstance(res.exception, (KeyError, TypeError, ValueError))
        lines = [ln for ln in res.output.splitlines() if ln.strip()]
        errors = [ln for ln in lines if ln.startswith("error:")]
        assert len(errors) == 1, res.output
        msg = errors[0]
        assert str(bad) in msg and f"summary.json {key} is" in msg and expected in msg, msg
        assert "run the command that wrote it again" in msg


def test_good_summary_still_reports_and_diffs(plan_folder, tmp_path):
    r = CliRunner()
    res = r.invoke(main, ["report", str(plan_folder), "--no-maps", "--out", str(tmp_path / "r.html")])
    assert res.exit_code == 0, res.output
    res = r.invoke(main, ["diff", str(plan_folder), str(plan_folder), "--no-maps"])
    assert res.exit_code == 0 and "no differences" in res.output, res.output


def test_null_plan_numbers_do_not_break_the_report(plan_folder, tmp_path):
    """A flyable plan whose numbers are null (a non-finite value as skyroute writes it) reports."""
    bad = _corrupt(plan_folder, tmp_path, _set("plan", "energy_Wh", None))
    res = CliRunner().invoke(main, ["report", str(bad), "--no-maps", "--out", str(tmp_path / "r.html")])
    assert res.exit_code == 0, res.output
    assert "energy n/a Wh" in (tmp_path / "r.html").read_text()
