"""Scenario catalog validation: every problem reported at once, with its YAML path."""

from __future__ import annotations

import copy

import pytest
import yaml

from skyroute.pipeline.errors import ScenarioError, UnknownNameError
from skyroute.pipeline.settings import load_scenario, parse_scenario, scenario_paths

KNOWN = ["helsinki-medical", "helsinki-traffic", "rotterdam-canyon", "monaco-helipads", "san-gabriel-mountains"]


def _raw(name="helsinki-medical"):
    p = scenario_paths()[name]
    return yaml.safe_load(p.read_text()), p.parent


@pytest.mark.parametrize("name", KNOWN)
def test_catalog_scenarios_validate(name):
    sc = load_scenario(name)
    assert sc.name == name
    g = sc.grid
    assert g.nx > 100 and g.ny > 100
    for p in (sc.mission.start, sc.mission.goal):
        assert g.contains(*sc.point_xy(p))


def test_default_crs_is_the_utm_zone():
    sc = load_scenario("helsinki-medical")
    assert sc.grid.crs.to_epsg() == 32635  # Helsinki, 24.94 E -> UTM 35N
    assert load_scenario("monaco-helipads").grid.crs.to_epsg() == 32632  # 7.42 E -> UTM 32N


def test_mission_points_are_the_named_osm_features_about_1km_apart():
    sc = load_scenario("helsinki-medical")
    (x0, y0), (x1, y1) = sc.point_xy(sc.mission.start), sc.point_xy(sc.mission.goal)
    d = ((x1 - x0) ** 2 + (y1 - y0) ** 2) ** 0.5
    # geodesic reference distance between the two OSM nodes
    from pyproj import Geod

    _, _, d_ref = Geod(ellps="WGS84").inv(24.9405421, 60.1717091, 24.9408349, 60.1642173)
    assert abs(d - d_ref) < 1.0 and 700 < d < 1300  # UTM scale error < 1 m over 0.8 km


def test_every_problem_is_reported_with_its_yaml_path():
    raw, base = _raw()
    raw = copy.deepcopy(raw)
    raw["mission"]["start"]["alt_agl_m"] = 900
    raw["mission"]["goal"]["lon"] = 30.0  # far outside the AOI
    raw["constraints"]["max_altitude_agl_m"] = 150
    raw["data"]["buildings"]["path"] = "../data/nope.osm.pbf"
    with pytest.raises(ScenarioError) as ei:
        parse_scenario(raw, "test.yaml", base)
    msg = str(ei.value)
    assert "mission.start: altitude 900 m is above constraints.max_altitude_agl_m 150" in msg
    assert "mission.goal: point" in msg and "outside the AOI" in msg
    assert "data.buildings.path: data file not found" in msg and "nope.osm.pbf" in msg
    assert "max_altitude_agl_m: 150 m AGL exceeds the maximum altitude of vehicle 'dji-m300-rtk', 80 m" in msg
    assert len(ei.value.problems) == 4


def test_type_errors_are_collected_with_paths():
    raw, base = _raw()
    raw = copy.deepcopy(raw)
    raw["aoi"]["resolution_m"] = 0
    raw["gnss"]["dop_thresholds"] = [0.5, 3]
    raw["planner"]["colour"] = "blue"
    del raw["mission"]["start_time_utc"]
    with pytest.raises(ScenarioError) as ei:
        parse_scenario(raw, "test.yaml", base)
    probs = ei.value.problems
    assert any(p.startswith("aoi.resolution_m: ") and "greater than 0" in p for p in probs)
    assert any(p.startswith("gnss.dop_thresholds: ") and "> 1" in p for p in probs)
    assert any(p.startswith("planner.colour: unknown key") for p in probs)
    assert any(p.startswith("mission.start_time_utc: required key is missing") for p in probs)


def test_bad_crs_is_reported():
    raw, base = _raw()
    raw = copy.deepcopy(raw)
    raw["aoi"]["crs"] = "EPSG:999999"
    with pytest.raises(ScenarioError, match=r"aoi: cannot resolve CRS 'EPSG:999999'"):
        parse_scenario(raw, "test.yaml", base)


def test_unknown_scenario_lists_known_ones():
    with pytest.raises(UnknownNameError, match="unknown scenario 'atlantis'; known scenarios: helsinki-contingency, helsinki-crosstown, helsinki-medical"):
        load_scenario("atlantis")


def test_not_a_mapping_and_bad_yaml(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("name: [unclosed\n")
    with pytest.raises(ScenarioError, match="not valid YAML"):
        load_scenario(p)
    with pytest.raises(ScenarioError, match="must be a YAML mapping"):
        parse_scenario([1, 2], "x.yaml")


def test_settings_are_frozen():
    sc = load_scenario("helsinki-medical")
    with pytest.raises(Exception, match="frozen"):
        sc.aoi.resolution_m = 5.0  # type: ignore[misc]
