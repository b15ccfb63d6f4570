"""Pilot exports of a plan (plan.kml, plan.plan, plan.gpkg, intent.json), each re-read by an
independent reader (xml.etree, a JSON schema written from the QGroundControl docs, pyogrio and
sqlite3, uas-standards) and compared with the plan."""

from __future__ import annotations

import json
import sqlite3
import xml.etree.ElementTree as ET

import jsonschema
import numpy as np
import pandas as pd
import pytest
import shapely
from pyproj import Transformer

from skyroute.pipeline.plan_exports import pilot_export_notes, write_pilot_exports
from skyroute.pipeline.settings import GroundReference, load_scenario
from skyroute.stages import geoid
from skyroute.stages.base import DataError
from skyroute.stages.intents import intent_conformance, parse_intent
from skyroute.stages.planning.step3 import Candidate
from skyroute.stages.planning.strategic import StrategicPlan, plan_to_dataset
from skyroute.stages.smoothing import KinematicLimits, corner_trajectory
from skyroute.stages.vehicle import load_vehicle

LOCAL = "local ground (flat terrain, heights above ground level)"
GROUND_M = 10.0   # data.ground.height_m [m, EGM96]
KML = "{http://www.opengis.net/kml/2.2}"

try:
    geoid.find_geoid_grid("EGM96")
    HAVE_EGM96 = True
except DataError:
    HAVE_EGM96 = False

# QGroundControl "Plan File Format" (docs.qgroundcontrol.com/master/en/qgc-dev-guide/file_formats/plan.html):
# top level, the mission object and the SimpleItem as the page describes them.
QGC_SCHEMA = {
    "type": "object",
    "required": ["fileType", "groundStation", "mission", "version"],
    "properties": {
        "fileType": {"const": "Plan"}, "version": {"const": 1}, "groundStation": {"type": "string"},
        "geoFence": {"type": "object", "required": ["circles", "polygons", "version"]},
        "rallyPoints": {"type": "object", "required": ["points", "version"]},
        "mission": {
            "type": "object",
            "required": ["cruiseSpeed", "firmwareType", "hoverSpeed", "items", "plannedHomePosition", "vehicleType",
                         "version"],
            "properties": {
                "version": {"const": 2}, "cruiseSpeed": {"type": "number"}, "hoverSpeed": {"type": "number"},
                "firmwareType": {"type": "integer"}, "vehicleType": {"type": "integer"},
                "globalPlanAltitudeMode": {"type": "integer"},
                "plannedHomePosition": {"type": "array", "minItems": 3, "maxItems": 3, "items": {"type": "number"}},
                "items": {"type": "array", "minItems": 1, "items": {
                    "type": "object",
                    "required": ["autoContinue", "command", "doJumpId", "frame", "params", "type"],
                    "properties": {
                        "type": {"const": "SimpleItem"}, "autoContinue": {"type": "boolean"},
                        "command": {"type": "integer"}, "doJumpId": {"type": "integer", "minimum": 1},
                        "frame": {"type": "integer"}, "AltitudeMode": {"type": "integer"},
                        "Altitude": {"type": "number"}, "AMSLAltAboveTerrain": {"type": ["number", "null"]},
                        "params": {"type": "array", "minItems": 7, "maxItems": 7,
                                   "items": {"type": ["number", "null"]}},
                    }}},
            }},
    },
}


class _Result:
    """The parts of a RunResult the exports read."""

    def __init__(self, scenario, plan, surface=None):
        self.scenario = scenario
        self.datasets = {"plan": plan} if surface is None else {"plan": plan, "surface": surface}

    def __getitem__(self, name):
        return self.datasets[name]


def _plan_dataset(sc):
    x0, y0 = sc.point_xy(sc.mission.start)
    chain = np.array([[x0, y0, 60.0], [x0 + 150, y0 - 300, 70.0], [x0 + 100, y0 - 600, 65.0]])
    veh = load_vehicle(sc.vehicle)
    traj = corner_trajectory(chain, np.full(2, 10.0), KinematicLimits.of(veh))
    tau = traj.sample_times(0.5)
    p = traj.sample(tau)
    sigma = 0.9 + 0.3 * np.cos(tau / 11.0) ** 2
    c = Candidate("D=3", 3.0, tau, p, p[:, 2], np.linalg.norm(traj.velocity(tau), axis=1), sigma,
                  np.full(tau.size, 9), 700.0, 0.0, 0.0, 0.0, 700.0, True, float(sigma.max()), 1e5,
                  traj.duration_s, 0.1, [], traj.waypoints, traj.segment_times_s, traj, "ok")
    return plan_to_dataset(StrategicPlan(chosen=c, candidates=[c]), sc.grid.crs, LOCAL, sc.mission.start_time_utc), traj


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    base = load_scenario("helsinki-medical")
    sc = base.model_copy(update={"data": base.data.model_copy(
        update={"ground": GroundReference(height_m=GROUND_M, vertical_datum="EGM96 geoid")})})
    ds, traj = _plan_dataset(sc)
    out = tmp_path_factory.mktemp("exports")
    if not HAVE_EGM96:
        pytest.skip("egm96_15.gtx not installed (apt-get install proj-data)")
    files = write_pilot_exports(_Result(sc, ds, _surface(sc)), out)
    return sc, ds, traj, out, files


BUILDINGS = {7: (slice(10, 20), slice(30, 45), 25.0), 9: (slice(50, 53), slice(5, 9), 12.5)}   # rows, cols, top


def _surface(sc):
    """Two rectangular buildings on the scenario grid."""
    import xarray as xr

    g = sc.grid
    bid = np.full(g.shape, -1, np.int32)
    surf = np.zeros(g.shape, np.float32)
    for i, (r, c, top) in BUILDINGS.items():
        bid[r, c] = i
        surf[r, c] = top
        surf[r.start, c.start] = top + 1.0   # the top is the highest cell
    return xr.Dataset({"building_id": (("y", "x"), bid), "surface": (("y", "x"), surf)})


def _lonlat(sc, x, y):
    lon, lat = Transformer.from_crs(sc.grid.crs, 4326, always_xy=True).transform(x, y)
    return np.asarray(lon), np.asarray(lat)


def test_files(exported):
    from skyroute.pipeline.plan_exports import exports_section

    sc, ds, _, out, files = exported
    assert sorted(files) == ["intent.json", "plan.gpkg", "plan.kml", "plan.plan"]
    assert all(p.parent == out and p.stat().st_size > 0 for p in files.values())
    sec = exports_section(_Result(sc, ds), [*files, "plan.geojson"], out)
    assert sec["files"] == sorted(files) and sec["notes"] == []
    intent = json.loads((out / "intent.json").read_text())
    assert sec["intent"]["volumes"] == len(intent["volumes"]) and sec["intent"]["conformance"] == 1.0
    assert sec["intent"]["time_start"] == intent["volumes"][0]["time_start"]["value"]


def test_kml_absolute_altitudes(exported):
    sc, ds, _, out, _ = exported
    root = ET.parse(out / "plan.kml").getroot()
    assert root.tag == f"{KML}kml"
    doc = root.find(f"{KML}Document")
    assert "above mean sea level" in doc.find(f"{KML}description").text
    line = doc.find(f"{KML}Placemark/{KML}LineString")
    assert line.find(f"{KML}altitudeMode").text == "absolute"
    c = np.array([[float(v) for v in t.split(",")] for t in line.find(f"{KML}coordinates").text.split()])
    lon, lat = _lonlat(sc, ds["x_m"].values, ds["y_m"].values)
    assert np.max(np.abs(c[:, 0] - lon)) < 1e-7 and np.max(np.abs(c[:, 1] - lat)) < 1e-7
    # local ground at 10 m EGM96: absolute (mean sea level) height = z + 10 m
    assert np.max(np.abs(c[:, 2] - (ds["z_m"].values + GROUND_M))) < 0.01
    whens = [e.text for e in doc.iter(f"{KML}when")]
    assert len(whens) == c.shape[0] and all(w.endswith("Z") for w in whens)


def test_qgc_plan_schema_and_numbers(exported):
    sc, ds, _, out, _ = exported
    doc = json.loads((out / "plan.plan").read_text())
    jsonschema.validate(doc, QGC_SCHEMA)
    items = doc["mission"]["items"]
    assert [it["command"] for it in items][0] == 22 and items[-1]["command"] == 21
    assert all(it["command"] == 16 for it in items[1:-1])
    assert [it["doJumpId"] for it in items] == list(range(1, len(items) + 1))
    assert all(it["frame"] == 3 and it["AltitudeMode"] == 1 for it in items)   # relative to home
    wp = ds["waypoints"].values
    lon, lat = _lonlat(sc, wp[:, 0], wp[:, 1])
    prm = np.array([[it["params"][4], it["params"][5], it["params"][6]] for it in items[1:-1]])
    assert np.max(np.abs(prm[:, 0] - lat)) < 1e-7 and np.max(np.abs(prm[:, 1] - lon)) < 1e-7
    home_ground = ds["z_m"].values[0] - ds["alt_agl_m"].values[0]   # flat local ground: 0
    assert np.max(np.abs(prm[:, 2] - (wp[:, 2] - home_ground))) < 0.01
    assert items[0]["params"][6] == pytest.approx(wp[0, 2] - home_ground, abs=0.01)
    h = doc["mission"]["plannedHomePosition"]
    assert abs(h[0] - lat[0]) < 1e-7 and abs(h[1] - lon[0]) < 1e-7
    assert h[2] == pytest.approx(home_ground + GROUND_M, abs=0.01)   # AMSL of the ground under the start


def test_geopackage_layers(exported):
    import pyogrio
    from pyogrio.raw import read

    sc, ds, _, out, _ = exported
    gpkg = out / "plan.gpkg"
    assert {tuple(r) for r in pyogrio.list_layers(gpkg)} >= {("plan", "LineString Z"), ("waypoints", "Point Z"),
                                                             ("intents", "Polygon"), ("aoi", "Polygon")}
    meta, _, geom, fields = read(gpkg, layer="plan")
    xyz = shapely.get_coordinates(shapely.from_wkb(geom[0]), include_z=True)
    lon, lat = _lonlat(sc, ds["x_m"].values, ds["y_m"].values)
    assert np.max(np.abs(xyz[:, 0] - lon)) < 1e-7 and np.max(np.abs(xyz[:, 1] - lat)) < 1e-7
    assert np.max(np.abs(xyz[:, 2] - ds["z_m"].values)) < 0.01   # surface datum, as plan.geojson
    assert list(fields[list(meta["fields"]).index("vertical_datum")]) == [LOCAL]
    intent = json.loads((out / "intent.json").read_text())
    meta, _, geom, fields = read(gpkg, layer="intents")
    assert len(geom) == len(intent["volumes"])
    lo = fields[list(meta["fields"]).index("alt_lower_w84_m")]
    assert np.allclose(lo, [v["volume"]["altitude_lower"]["value"] for v in intent["volumes"]], atol=1e-9)
    # sqlite3 (no GDAL): the GeoPackage's own table of contents and its CRS
    with sqlite3.connect(gpkg) as con:
        rows = dict(con.execute("SELECT table_name, srs_id FROM gpkg_contents").fetchall())
    assert rows == {"plan": 4326, "waypoints": 4326, "intents": 4326, "aoi": 4326, "map_buildings": 4326}
    # the building layer: back in the map CRS, each footprint is its cells' rectangle
    meta, _, geom, fields = read(gpkg, layer="map_buildings")
    to_map = Transformer.from_crs(4326, sc.grid.crs, always_xy=True)
    g = sc.grid
    ids = list(fields[list(meta["fields"]).index("building_id")])
    tops = fields[list(meta["fields"]).index("top_m")]
    assert sorted(ids) == sorted(BUILDINGS)
    for k, i in enumerate(ids):
        r, c, top = BUILDINGS[i]
        poly = shapely.transform(shapely.from_wkb(geom[k]), lambda xy: np.column_stack(to_map.transform(xy[:, 0], xy[:, 1])))
        want = shapely.box(g.x0 + c.start * g.resolution_m, g.y1 - r.stop * g.resolution_m,
                           g.x0 + c.stop * g.resolution_m, g.y1 - r.start * g.resolution_m)
        assert poly.symmetric_difference(want).area < 1e-3 and tops[k] == top + 1.0


def test_intent_json_contains_the_plan(exported):
    sc, ds, traj, out, _ = exported
    intent = json.loads((out / "intent.json").read_text())
    parse_intent(intent)
    tau = np.append(np.arange(0.0, traj.duration_s, 0.02), traj.duration_s)
    p = traj.sample(tau)
    lon, lat = _lonlat(sc, p[:, 0], p[:, 1])
    h = p[:, 2] + GROUND_M + geoid.geoid_undulation_m(lon, lat, "EGM96")   # WGS 84 ellipsoidal
    t = pd.Timestamp(sc.mission.start_time_utc) + pd.to_timedelta(tau, unit="s")
    assert intent_conformance(intent, lon, lat, h, t) == 1.0
    assert 17.0 < float(np.mean(geoid.geoid_undulation_m(lon, lat))) < 19.0   # EGM96 N in Helsinki ~ 18 m


def test_local_ground_without_data_ground(tmp_path):
    """helsinki-medical without its data.ground: no KML / intent, a warning naming the setting."""
    base = load_scenario("helsinki-medical")
    sc = base.model_copy(update={"data": base.data.model_copy(update={"ground": None})})
    ds, _ = _plan_dataset(sc)
    res = _Result(sc, ds)
    files = write_pilot_exports(res, tmp_path)
    assert sorted(files) == ["plan.gpkg", "plan.plan"]
    (w,) = pilot_export_notes(res)
    assert w.startswith("plan.kml not written") and "data.ground" in w


def test_export_key_follows_data_ground():
    """`skyroute run` reuses plan/* only while the plan key AND this key are unchanged, so an
    edited data.ground rewrites plan.kml / intent.json."""
    from skyroute.pipeline.plan_exports import export_key

    base = load_scenario("helsinki-medical")
    ds, _ = _plan_dataset(base)

    def key(ground):
        sc = base.model_copy(update={"data": base.data.model_copy(update={"ground": ground})})
        return export_key(_Result(sc, ds))

    a = key(GroundReference(height_m=10.0, vertical_datum="EGM96 geoid"))
    assert a == key(GroundReference(height_m=10.0, vertical_datum="EGM96 geoid"))
    assert a != key(GroundReference(height_m=11.0, vertical_datum="EGM96 geoid")) != key(None)


@pytest.mark.skipif(not HAVE_EGM96, reason="egm96_15.gtx not installed (apt-get install proj-data)")
def test_no_sigma_no_intent(tmp_path):
    base = load_scenario("helsinki-medical")
    sc = base.model_copy(update={"data": base.data.model_copy(
        update={"ground": GroundReference(height_m=GROUND_M, vertical_datum="EGM96 geoid")})})
    ds, _ = _plan_dataset(sc)
    ds["sigma_p_m"][:] = np.nan
    res = _Result(sc, ds)
    assert sorted(write_pilot_exports(res, tmp_path)) == ["plan.gpkg", "plan.kml", "plan.plan"]
    (w,) = pilot_export_notes(res)
    assert "intent.json not written" in w and "sigma_p" in w
