"""`skyroute plan` on the default scenario: outputs checked against the maps with plain code."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from click.testing import CliRunner
from pyproj import Transformer

from skyroute.pipeline.cli import main
from skyroute.pipeline.settings import load_scenario
from skyroute.stages.vehicle import load_vehicle


@pytest.fixture(scope="module")
def planned(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("plan")
    res = CliRunner().invoke(main, ["plan", "--out", str(tmp / "out"), "--cache-dir", str(tmp / "c"), "-q"])
    assert res.exit_code == 0, res.output
    (tmp / "output.txt").write_text(res.output)
    return tmp


def test_plan_files_and_candidate_table(planned):
    out = planned / "out"
    rows = list(csv.DictReader((out / "candidates.csv").open()))
    assert [r["label"] for r in rows] == ["D=2", "D=3", "D=4"]
    chosen = [r for r in rows if r["chosen"] == "true"]
    assert len(chosen) == 1 and chosen[0]["flyable"] == "true"
    flyable_f = [float(r["f_m"]) for r in rows if r["flyable"] == "true"]
    assert float(chosen[0]["f_m"]) == min(flyable_f)  # seed 000 III-C: minimum f among the flyable
    for name in ("plan.geojson", "waypoints.csv", "top_view.png", "profile.png", "sigma_p.png"):
        assert (out / name).stat().st_size > 0


def test_plan_summary_line_and_json(planned):
    out = planned / "out"
    s = json.loads((out / "summary.json").read_text())
    assert s["schema_version"] == 1 and s["command"] == "plan" and isinstance(s["warnings"], list)
    assert sorted(s["files"]) == sorted(p.name for p in out.iterdir())
    # pilot exports: helsinki-medical has a sourced data.ground (issue 24): every pilot file, the
    # QGroundControl home at that height above mean sea level, no "not written" warning
    assert s["exports"]["files"] == ["intent.json", "plan.gpkg", "plan.kml", "plan.plan"]
    assert s["exports"]["notes"] == [] and not any("not written" in w for w in s["warnings"])
    home = json.loads((out / "plan.plan").read_text())["mission"]["plannedHomePosition"]
    assert home[2] == pytest.approx(load_scenario("helsinki-medical").data.ground.height_m, abs=1e-6)
    p = s["plan"]
    row = next(r for r in csv.DictReader((out / "candidates.csv").open()) if r["chosen"] == "true")
    assert p["status"] == "flyable" and p["reasons"] == [] and p["label"] == row["label"]
    for key, col, tol in (("f_m", "f_m", 0.05), ("C_l_m", "C_l_m", 0.05), ("C_r_m", "C_r_m", 0.05),
                          ("C_d_m", "C_d_m", 0.05), ("C_e_m", "C_e_m", 0.05), ("energy_Wh", "energy_Wh", 0.005),
                          ("flight_time_s", "flight_time_s", 0.05), ("dop_threshold", "dop_threshold", 0.005)):
        assert p[key] == pytest.approx(float(row[col]), abs=tol), key
    wp = np.array([[float(r[k]) for k in ("x_m", "y_m", "z_m")] for r in csv.DictReader((out / "waypoints.csv").open())])
    assert p["length_m"] == pytest.approx(np.linalg.norm(np.diff(wp, axis=0), axis=1).sum(), abs=0.05)
    lines = (planned / "output.txt").read_text().splitlines()
    assert lines[-1] == (f"plan {p['label']}: f {p['f_m']:.1f} m, length {p['length_m']:.1f} m, energy "
                         f"{p['energy_Wh']:.2f} Wh, flight time {p['flight_time_s']:.1f} s, DOP < {p['dop_threshold']:g}")


def test_trajectory_respects_the_maps(planned):
    sc = load_scenario("helsinki-medical")
    veh = load_vehicle(sc.vehicle)
    wp = list(csv.DictReader((planned / "out" / "waypoints.csv").open()))
    t = np.array([float(r["t_s"]) for r in wp])
    p = np.array([[float(r["x_m"]), float(r["y_m"]), float(r["z_m"])] for r in wp])
    assert np.all(np.diff(t) > 0)
    # starts and ends at the mission points, 60 m above the (flat) ground
    for i, pt in ((0, sc.mission.start), (-1, sc.mission.goal)):
        x, y = sc.point_xy(pt)
        assert np.hypot(p[i, 0] - x, p[i, 1] - y) < 1.0 and abs(p[i, 2] - pt.alt_agl_m) < 0.5
    # never within r_p of a building: brute force over every surface cell near each sample
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.runner import run_scenario

    surf = run_scenario(sc, cache=Cache(planned / "c"), targets=["surface"])["surface"].load()
    g = sc.grid
    zs = surf["surface"].values
    r_p = veh.r_p_m
    X, Y = np.meshgrid(g.x, g.y)
    for k in range(0, len(p), 3):
        near = (np.abs(X - p[k, 0]) <= r_p + g.resolution_m) & (np.abs(Y - p[k, 1]) <= r_p + g.resolution_m)
        # distance from the sample to each nearby prism (cell footprint x [0, height])
        dx = np.maximum(np.abs(X[near] - p[k, 0]) - g.resolution_m / 2, 0)
        dy = np.maximum(np.abs(Y[near] - p[k, 1]) - g.resolution_m / 2, 0)
        dz = np.maximum(p[k, 2] - zs[near], 0)  # the sample is above every prism top
        assert np.min(np.sqrt(dx**2 + dy**2 + dz**2)) >= r_p - 1e-3
    assert np.all(p[:, 2] <= 80.0 + 1e-6)  # max altitude AGL (flat terrain at 0)
    sig = np.array([float(r["sigma_p_m"]) for r in wp])
    assert np.nanmax(sig) <= veh.max_position_error_m


def test_geojson_is_wgs84_with_stated_datum(planned):
    gj = json.loads((planned / "out" / "plan.geojson").read_text())
    feats = gj["features"] if gj.get("type") == "FeatureCollection" else [gj]
    line = next(f for f in feats if f["geometry"]["type"] == "LineString")
    coords = np.array(line["geometry"]["coordinates"])
    assert coords.shape[1] == 3
    lon, lat = coords[:, 0], coords[:, 1]
    assert np.all((24.93 < lon) & (lon < 24.96) & (60.16 < lat) & (lat < 60.18))
    text = json.dumps(line["properties"]).lower()
    assert "ellipsoidal" in text and "local ground" in text
    # lon/lat project back onto the waypoints (UTM 35N)
    wp = list(csv.DictReader((planned / "out" / "waypoints.csv").open()))
    x, y = Transformer.from_crs(4326, 32635, always_xy=True).transform(lon[0], lat[0])
    assert abs(x - float(wp[0]["x_m"])) < 0.01 and abs(y - float(wp[0]["y_m"])) < 0.01
    # the piece boundaries: one time per point, increasing, on the written trajectory's times
    pieces = next(f for f in feats if f["geometry"]["type"] == "MultiPoint")
    n = len(pieces["geometry"]["coordinates"])
    assert n > 2 and len(pieces["properties"]["t_s"]) == n == len(pieces["properties"]["times_utc"])
    tk = np.asarray(pieces["properties"]["t_s"])
    assert np.all(np.diff(tk) > 0) and tk[-1] == pytest.approx(float(wp[-1]["t_s"]), abs=1e-6)


def test_summary_lists_the_warnings_printed_on_stderr(planned):
    """The almanac's unhealthy-satellite warning is printed on stderr by the CLI and listed in
    summary.json (issue 25), once, and not carried into the next command's summary."""
    doc = json.loads((planned / "out" / "summary.json").read_text())
    unhealthy = [w for w in doc["warnings"] if "unhealthy satellites excluded" in w]
    assert len(unhealthy) == 1
    from skyroute.pipeline.outputs import PRINTED_WARNINGS

    res = CliRunner().invoke(main, ["scenarios"])
    assert res.exit_code == 0 and PRINTED_WARNINGS == []


def test_weights_override_replans_only_the_plan(planned):
    res = CliRunner().invoke(main, ["plan", "--weights", "1,0,0,0", "--planner", "astar", "--out",
                                    str(planned / "out2"), "--cache-dir", str(planned / "c"), "-q"])
    assert res.exit_code == 0, res.output
    rows = list(csv.DictReader((planned / "out2" / "candidates.csv").open()))
    base = list(csv.DictReader((planned / "out" / "candidates.csv").open()))
    # length only: the path is not longer than the weighted one
    assert float(rows[0]["C_l_m"]) <= float(base[0]["C_l_m"]) + 1.0


def test_bad_plan_options_exit_2(tmp_path):
    r = CliRunner().invoke(main, ["plan", "--weights", "1,2,3", "--cache-dir", str(tmp_path)])
    assert r.exit_code == 2 and "give four numbers" in r.output
    r = CliRunner().invoke(main, ["plan", "--weights", "0,0,0,0", "--cache-dir", str(tmp_path)])
    assert r.exit_code == 2 and "at least one weight must be > 0" in r.output
    r = CliRunner().invoke(main, ["plan", "--planner", "dijkstra", "--cache-dir", str(tmp_path)])
    assert r.exit_code == 2 and "known planners: astar, bitstar" in r.output
    r = CliRunner().invoke(main, ["plan", "--time-budget", "0", "--cache-dir", str(tmp_path)])
    assert r.exit_code == 2 and "time_budget_s" in r.output


def test_step2_deconflicts_a_crossing_drone(tmp_path):
    """helsinki-traffic: courier-1 crosses the default route; every candidate is deconflicted and
    the chosen trajectory keeps r + d_c from the intruder at every sample (brute force)."""
    res = CliRunner().invoke(main, ["plan", "helsinki-traffic", "--out", str(tmp_path / "o"),
                                    "--cache-dir", str(tmp_path / "c"), "-q"])
    assert res.exit_code == 0, res.output
    rows = list(csv.DictReader((tmp_path / "o" / "candidates.csv").open()))
    assert any(r["flyable"] == "true" for r in rows)
    sc = load_scenario("helsinki-traffic")
    wp = list(csv.DictReader((tmp_path / "o" / "waypoints.csv").open()))
    t = np.array([float(r["t_s"]) for r in wp])
    p = np.array([[float(r["x_m"]), float(r["y_m"]), float(r["z_m"])] for r in wp])
    for it in sc.traffic.intruders:
        w = np.asarray(it.waypoints)
        inside = (t >= w[0, 0]) & (t <= w[-1, 0])
        q = np.column_stack([np.interp(t[inside], w[:, 0], w[:, k]) for k in (1, 2, 3)])
        d = np.linalg.norm(p[inside] - q, axis=1)
        # the reserved volume is r + d_c around the intruder (plus the time margin): never entered
        assert d.min() >= it.radius_m + sc.traffic.margin_m - 0.5
    # and STEP II really had to act: the cached plan says every level was deconflicted
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.runner import run_scenario

    plan = run_scenario(sc, cache=Cache(tmp_path / "c"), targets=["plan"])["plan"]
    assert list(plan["status"].values) == ["deconflicted"] * 3
