"""Outputs of a tactical replay (stages/tactical/outputs.py) on a synthetic 1 km flight: a
strategic part, a level-1 time scaling, a level-2 deviation and a contingency landing, one
strategic and one tactical intruder and one temporary no-fly zone."""

from __future__ import annotations

import csv
import dataclasses
import json
import math

import numpy as np
import pandas as pd
import pytest
from pyproj import Transformer

from skyroute.stages.base import InputError
from skyroute.stages.grid import Grid
from skyroute.stages.tactical.log import (
    FlightLog,
    FlownPart,
    IntruderTrack,
    LevelAttempt,
    NoFlyZone,
)
from skyroute.stages.tactical.outputs import (
    FLOWN_COLUMNS,
    TACTICAL_COLUMNS,
    flight_section,
    flown_samples,
    fly_summary_line,
    min_separations,
    nofly_time_inside,
    write_flight,
)

X0, Y0 = 385000.0, 6672000.0
START = pd.Timestamp("2020-01-03T12:00:00Z")
TICK = 0.1
ORIGIN = np.array([X0, Y0, 0.0])


def _grid() -> Grid:
    return Grid.from_bounds("EPSG:32635", X0, Y0, X0 + 1200, Y0 + 700, 5.0)


def _maps(g: Grid):
    xx, yy = np.meshgrid(g.x - X0, g.y - Y0)
    terrain = 5.0 + 0.005 * xx
    bld = np.zeros(g.shape)
    for bx0, bx1, by0, by1, h in ((600, 650, 330, 420, 30.0), (380, 430, 180, 260, 22.0), (700, 760, 200, 260, 18.0)):
        bld[(xx >= bx0) & (xx < bx1) & (yy >= by0) & (yy < by1)] = h
    surface = terrain + bld
    floor = terrain + 20.0 + 18.0 * np.exp(-((xx - 620) ** 2 + (yy - 380) ** 2) / 80.0 ** 2)
    floor[(xx > 1000) & (yy > 550)] = np.inf                      # no coverage at any altitude
    return terrain, surface, floor


def _polyline(points, t0: float, v_of_t, t_end: float | None = None):
    """Samples every TICK of a flight along the 3-D polyline ``points`` (relative to X0, Y0)
    with path speed v_of_t(t) [m/s], from t0 until the polyline's end (or ``t_end``)."""
    pts = np.asarray(points, float) + ORIGIN
    s_knots = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    ts, ss = [t0], [0.0]
    while ss[-1] < s_knots[-1] - 1e-9 and (t_end is None or ts[-1] < t_end - 1e-9):
        t = ts[-1] + TICK
        ss.append(min(ss[-1] + 0.5 * (v_of_t(ts[-1]) + v_of_t(t)) * TICK, s_knots[-1]))
        ts.append(t)
    ts, ss = np.round(np.array(ts), 9), np.array(ss)
    xyz = np.stack([np.interp(ss, s_knots, pts[:, j]) for j in range(3)], axis=1)
    return ts, xyz


def _part(name, ts, xyz, rep):
    speed = np.linalg.norm(np.gradient(xyz[:, :2], ts, axis=0), axis=1)
    return FlownPart(name, ts, xyz, speed, rep)


def make_log(g: Grid | None = None) -> FlightLog:
    g = g or _grid()
    terrain, surface, floor = _maps(g)
    pt, pxyz = _polyline([[100, 300, 40], [1100, 300, 40]], 0.0, lambda t: 10.0)
    # strategic until E2's replan takes effect (15 + 5 s)
    t1, x1 = _polyline([[100, 300, 40], [1100, 300, 40]], 0.0, lambda t: 10.0, t_end=20.0)
    # L1: same geometry, slowed to 4 m/s and back (cosine window over 20 s), then 10 m/s until t = 45 s
    v1 = lambda t: 10.0 - 6.0 * math.sin(math.pi * min(max(t - 20.0, 0.0), 20.0) / 20.0) ** 2  # noqa: E731
    t2, x2 = _polyline([x1[-1] - ORIGIN, [1100, 300, 40]], 20.0, v1, t_end=45.0)
    # L2: a deviation north that rejoins the strategic path, until E4's landing takes effect (75 + 5 s)
    a = x2[-1] - ORIGIN
    t3, x3 = _polyline([a, [a[0] + 70, 360, 45], [a[0] + 230, 360, 45], [a[0] + 300, 300, 40], [1100, 300, 40]],
                       45.0, lambda t: 10.0, t_end=80.0)
    # landing: to the site at (850, 200), descending, then a vertical descent to the ground
    b = x3[-1] - ORIGIN
    site_z = 5.0 + 0.005 * 850
    t4, x4 = _polyline([b, [850, 200, 25.0], [850, 200, site_z]], 80.0,
                       lambda t: 8.0 if t < 93.0 else 2.0)
    parts = [_part("strategic", t1, x1, None), _part("L1", t2, x2, 0), _part("L2", t3, x3, 1),
             _part("landing", t4, x4, 2)]
    tactical = IntruderTrack("T1", 2.0, np.array([0.0, 60.0]), np.array([[470, 0, 40], [470, 600, 40.0]]) + ORIGIN,
                             kind="tactical", known_from_s=15.0)
    s_xyz = np.array([[1000, 500, 60], [1000, 300, 40], [400, 300, 40.0]]) + ORIGIN
    strategic = IntruderTrack("S1", 1.5, np.array([0.0, 40.0, 115.0]), s_xyz, kind="strategic", known_from_s=0.0,
                              declared=[(0.0, np.array([0.0, 115.0]), np.array([[1000, 500, 60], [200, 500, 60.0]]) + ORIGIN),
                                        (40.0, np.array([0.0, 40.0, 115.0]), s_xyz)])
    zone = NoFlyZone("N1", np.array([[830, 260], [980, 260], [980, 340], [830, 340.0]]) + ORIGIN[:2], 0.0, 120.0,
                     75.0, 300.0)
    events = [dict(t_s=5.0, kind="wind", label="wind 6 m/s from W", t_known_s=5.0, t_coll_s=math.inf,
                   outcome="no conflict"),
              dict(t_s=15.0, kind="intruder", label="intruder T1 (crossing)", t_known_s=15.0, t_coll_s=28.0,
                   outcome="replanned L1"),
              dict(t_s=40.0, kind="intruder_update", label="S1 new track (head-on)", t_known_s=40.0, t_coll_s=33.0,
                   outcome="replanned L2"),
              dict(t_s=75.0, kind="nofly", label="no-fly N1", t_known_s=75.0, t_coll_s=4.0, outcome="landing")]

    def att(r, ev, te, tc, lvl, fly, f, comp, chosen, why="", added=5.0):
        return LevelAttempt(r, ev, te, tc, lvl, fly, f - 20.0 if fly else math.inf, 20.0 if fly else math.nan,
                            f if fly else math.inf, 0.8 if fly else math.nan, comp, 0.012, added, chosen, why)

    attempts = [att(0, "intruder T1 (crossing)", 15.0, 28.0, "1", True, 1020.0, 0.0041, True, added=10.0),
                att(0, "intruder T1 (crossing)", 15.0, 28.0, "2", True, 1061.0, 0.21, False, "higher cost"),
                att(0, "intruder T1 (crossing)", 15.0, 28.0, "3", True, 1150.0, 0.35, False, "higher cost"),
                att(1, "S1 new track (head-on)", 40.0, 33.0, "1", False, 0.0, 0.0012, False, "frontal geometry"),
                att(1, "S1 new track (head-on)", 40.0, 33.0, "2", True, 1071.0, 0.18, True, added=4.0),
                att(1, "S1 new track (head-on)", 40.0, 33.0, "3", True, 1190.0, 0.41, False, "higher cost"),
                att(2, "no-fly N1", 75.0, 4.0, "landing", True, 140.0, 0.05, True,
                    "t_coll 4.0 s <= t_rep 5 s", added=math.inf)]
    return FlightLog(scenario="synthetic-tactical", crs_wkt=g.crs_wkt, vertical_datum="flat local ground (test)",
                     start_time_utc=str(START), planned_t_s=pt, planned_xyz_m=pxyz, parts=parts, attempts=attempts,
                     events=events, intruders=[strategic, tactical], nofly=[zone], outcome="landed",
                     reason="no-fly zone N1 on the route with t_coll 4.0 s <= t_rep 5 s", dop_threshold=3.0,
                     own_radius_m=1.0, margin_m=10.0, grid=g, terrain_m=terrain, surface_m=surface,
                     coverage_floor_m=floor, landing_xy=np.array([[850, 200], [300, 550], [1050, 120.0]]) + ORIGIN[:2])


@pytest.fixture(scope="module")
def log() -> FlightLog:
    return make_log()


@pytest.fixture(scope="module")
def written(log, tmp_path_factory):
    return write_flight(log, tmp_path_factory.mktemp("fly"))


def _exact_min_distance(t, p, ti, pi) -> float:
    """Closed-form minimum distance between two piecewise-linear 4-D tracks over their common
    time span: on each interval between the merged knots the relative position is linear in
    time, so |d(t)|^2 is a quadratic minimised in closed form."""
    lo, hi = max(t[0], ti[0]), min(t[-1], ti[-1])
    knots = np.unique(np.concatenate([t, ti, [lo, hi]]))
    knots = knots[(knots >= lo) & (knots <= hi)]
    d = lambda s: np.stack([np.interp(s, t, p[:, j]) - np.interp(s, ti, pi[:, j]) for j in range(3)], -1)  # noqa: E731
    best = math.inf
    for a, b in zip(knots[:-1], knots[1:], strict=True):
        da, db = d(a), d(b)
        w = db - da
        u = 0.0 if not w @ w else min(max(-(da @ w) / (w @ w), 0.0), 1.0)
        best = min(best, float(np.linalg.norm(da + u * w)))
    return best


def test_tactical_csv(log, written):
    with open(written["tactical.csv"]) as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0].keys()) == TACTICAL_COLUMNS
    assert len(rows) == len(log.attempts)
    assert [r["level"] for r in rows] == ["1", "2", "3", "1", "2", "3", "landing"]
    for rep in {r["replanning"] for r in rows}:
        assert sum(r["chosen"] == "true" for r in rows if r["replanning"] == rep) == 1
    for r, a in zip(rows, log.attempts, strict=True):
        assert r["compute_s"] != "" and float(r["compute_s"]) == pytest.approx(a.compute_s, abs=1e-6)
        assert float(r["t_event_s"]) == pytest.approx(a.t_event_s, abs=1e-3)
        assert r["flyable"] in ("true", "false")
    assert rows[3]["C_l_m"] == "inf" and rows[3]["f_m"] == "inf" and rows[3]["reasons"] == "frontal geometry"
    assert rows[6]["added_flight_time_s"] == "inf"
    assert float(rows[0]["f_m"]) == pytest.approx(1020.0, abs=0.05)


@pytest.mark.parametrize("n_chosen", [0, 2])
def test_one_chosen_per_replanning(log, tmp_path, n_chosen):
    att = [dataclasses.replace(a) for a in log.attempts]
    att[4].chosen = n_chosen == 2              # replanning 1: L2 chosen (0) or also L3 (2)
    att[5].chosen = n_chosen == 2
    bad = dataclasses.replace(log, attempts=att)
    with pytest.raises(InputError, match=f"replanning 1 .* has {n_chosen} chosen"):
        write_flight(bad, tmp_path)
    assert not (tmp_path / "tactical.csv").exists()
    with pytest.raises(InputError, match="level 'L4'"):
        write_flight(dataclasses.replace(log, attempts=[dataclasses.replace(log.attempts[0], level="L4")]), tmp_path)


def test_flown_geojson_round_trip(log, written):
    gj = json.loads(written["flown.geojson"].read_text())
    assert gj["type"] == "FeatureCollection"
    assert [f["properties"]["part"] for f in gj["features"]] == ["strategic", "L1", "L2", "landing"]
    assert [f["properties"]["replanning"] for f in gj["features"]] == [None, 0, 1, 2]
    back = Transformer.from_crs(4326, log.grid.crs, always_xy=True)
    for f, part in zip(gj["features"], log.parts, strict=True):
        pr = f["properties"]
        assert f["geometry"]["type"] == "LineString"
        assert pr["heights_are_ellipsoidal"] is False and pr["vertical_datum"] == log.vertical_datum
        assert pr["dop_threshold"] == 3.0 and pr["start_time_utc"] == "2020-01-03T12:00:00.000Z"
        ll = np.array(f["geometry"]["coordinates"])
        assert ll.shape == (part.t_s.size, 3)
        assert 24.0 < ll[:, 0].min() and ll[:, 0].max() < 25.0 and 60.0 < ll[:, 1].min() < 60.3   # Helsinki
        x, y = back.transform(ll[:, 0], ll[:, 1])
        assert np.max(np.hypot(x - part.xyz_m[:, 0], y - part.xyz_m[:, 1])) < 0.001            # 1 mm
        np.testing.assert_allclose(ll[:, 2], part.xyz_m[:, 2], atol=1e-9)
        np.testing.assert_allclose(pr["t_s"], part.t_s)
        assert all(s.endswith("Z") for s in pr["times_utc"])
        dt_s = (pd.to_datetime(pr["times_utc"]) - START).total_seconds().to_numpy()
        np.testing.assert_allclose(dt_s, part.t_s, atol=0.6e-3)
    # consecutive parts share their boundary sample
    for f0, f1 in zip(gj["features"][:-1], gj["features"][1:], strict=True):
        assert f0["geometry"]["coordinates"][-1] == f1["geometry"]["coordinates"][0]


def test_intruders_geojson(log, written):
    gj = json.loads(written["intruders.geojson"].read_text())
    feats = gj["features"]
    assert [f["geometry"]["type"] for f in feats] == ["LineString", "LineString", "Polygon"]
    back = Transformer.from_crs(4326, log.grid.crs, always_xy=True)
    for f, it in zip(feats[:2], log.intruders, strict=True):
        pr = f["properties"]
        assert (pr["id"], pr["kind"], pr["radius_m"], pr["known_from_s"]) == (it.id, it.kind, it.radius_m,
                                                                              it.known_from_s)
        ll = np.array(f["geometry"]["coordinates"])
        x, y = back.transform(ll[:, 0], ll[:, 1])
        assert np.max(np.hypot(x - it.xyz_m[:, 0], y - it.xyz_m[:, 1])) < 0.001
        dt_s = (pd.to_datetime(pr["times_utc"]) - START).total_seconds().to_numpy()
        np.testing.assert_allclose(dt_s, it.t_s, atol=0.6e-3)
    zone = feats[2]
    ring = np.array(zone["geometry"]["coordinates"][0])
    assert ring.shape == (5, 2) and (ring[0] == ring[-1]).all()
    area2 = np.sum(ring[:-1, 0] * ring[1:, 1] - ring[1:, 0] * ring[:-1, 1])
    assert area2 > 0                                                   # RFC 7946: exterior ring counterclockwise
    x, y = back.transform(ring[:, 0], ring[:, 1])
    assert {(round(a - X0, 3), round(b - Y0, 3)) for a, b in zip(x, y, strict=True)} == {
        (830.0, 260.0), (980.0, 260.0), (980.0, 340.0), (830.0, 340.0)}
    pr = zone["properties"]
    assert (pr["z_min_m"], pr["z_max_m"], pr["start_s"], pr["end_s"]) == (0.0, 120.0, 75.0, 300.0)
    assert pr["start_utc"] == "2020-01-03T12:01:15.000Z"


def test_flown_csv(log, written):
    with open(written["flown.csv"]) as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0].keys()) == FLOWN_COLUMNS
    t, p = log.flown()
    assert len(rows) == t.size == sum(pt.t_s.size for pt in log.parts) - 3
    w = np.array([[float(r[k]) for k in ("t_s", "x_m", "y_m", "z_m", "lon", "lat", "speed_mps")] for r in rows])
    np.testing.assert_array_equal(w[:, 0], t)
    np.testing.assert_array_equal(w[:, 1:4], p)
    x, y = Transformer.from_crs(4326, log.grid.crs, always_xy=True).transform(w[:, 4], w[:, 5])
    assert np.max(np.hypot(x - p[:, 0], y - p[:, 1])) < 0.01          # lon/lat at 1e-9 deg
    dt_s = (pd.to_datetime([r["t_utc"] for r in rows]) - START).total_seconds().to_numpy()
    np.testing.assert_allclose(dt_s, t, atol=0.6e-3)
    parts = [r["part"] for r in rows]
    # the boundary sample belongs to the earlier part
    assert parts.count("strategic") == log.parts[0].t_s.size and parts.count("L1") == log.parts[1].t_s.size - 1
    assert parts[-1] == "landing" and float(rows[-1]["speed_mps"]) == pytest.approx(0.0, abs=0.01)
    _, _, v, names = flown_samples(log)
    assert names == parts and np.allclose(w[:, 6], v, atol=5e-4)


def test_flight_section_numbers(log):
    sec = flight_section(log)
    json.dumps(sec, allow_nan=False)                                   # summary.json is strict JSON
    assert sec["outcome"] == "landed" and sec["reached_goal"] is False and "t_rep" in sec["reason"]
    assert sec["n_replannings"] == 3 and sec["chosen_levels"] == ["1", "2", "landing"]
    assert [e["outcome"] for e in sec["events"]] == ["no conflict", "replanned L1", "replanned L2", "landing"]
    assert sec["events"][0]["t_coll_s"] is None                        # inf -> null
    r1 = sec["replannings"][1]
    assert r1["levels_tried"] == ["1", "2", "3"] and r1["levels_flyable"] == ["2", "3"]
    assert r1["compute_s"] == pytest.approx(0.0012 + 0.18 + 0.41, abs=1e-9)
    assert sec["replannings"][2]["added_flight_time_s"] is None
    t, p = log.flown()
    assert sec["flight_time_s"] == pytest.approx(t[-1], abs=1e-9)
    assert sec["length_m"] == pytest.approx(sum(pt["length_m"] for pt in sec["parts"]), abs=1e-6)
    # minimum separation: brute force at 0.05 s against the closed-form minimum of the
    # piecewise-linear tracks; sampling can only overestimate, by at most v_rel * dt / 2
    for rec, it in zip(sec["min_separation"], log.intruders, strict=True):
        exact = _exact_min_distance(t, p, it.t_s, it.xyz_m)
        assert exact - 1e-9 <= rec["min_distance_m"] <= exact + 20.0 * 0.025
        assert rec["required_m"] == pytest.approx(1.0 + it.radius_m + 10.0)
        assert rec["clearance_m"] == pytest.approx(rec["min_distance_m"] - rec["required_m"])
    assert sec["nofly"] == [{"id": "N1", "inside_active_s": 0.0}]
    assert sec["energy_Wh"] is None
    line = fly_summary_line(sec)
    assert line.startswith("fly: landed (no-fly zone N1") and "3 replannings (L1, L2, landing)" in line
    assert f"closest intruder S1 at {sec['min_separation'][0]['min_distance_m']:.1f} m" in line


def test_separation_and_nofly_detect_a_violation(log):
    # an intruder flying the ownship's strategic part 3 m above it between t = 2 and 8 s
    x1 = log.parts[0].xyz_m
    shadow = IntruderTrack("shadow", 1.0, np.array([2.0, 8.0]), x1[[20, 80]] + [0, 0, 3.0], kind="tactical")
    # a zone over x 200..260 m of the strategic part, active from t = 0: 6 s inside at 10 m/s
    zone = NoFlyZone("box", np.array([[200, 250], [260, 250], [260, 350], [200, 350.0]]) + ORIGIN[:2], 0.0, 120.0,
                     0.0, math.inf)
    late = NoFlyZone("late", zone.polygon_xy, 0.0, 120.0, 30.0, 60.0)   # active after the ownship passed
    low = NoFlyZone("low", zone.polygon_xy, 0.0, 30.0, 0.0, 60.0)       # below the ownship's 40 m
    bad = dataclasses.replace(log, intruders=[shadow], nofly=[zone, late, low])
    sep = min_separations(bad)[0]
    assert sep["min_distance_m"] == pytest.approx(3.0, abs=1e-6) and sep["clearance_m"] < 0
    assert 2.0 <= sep["t_s"] <= 8.0
    inside = {z["id"]: z["inside_active_s"] for z in nofly_time_inside(bad)}
    assert inside["box"] == pytest.approx(6.0, abs=0.06)
    assert inside["late"] == 0.0 and inside["low"] == 0.0


def test_figures_written_and_not_blank(written):
    import matplotlib.image as mpimg

    for name in ("fly_top.png", "fly_profile.png", "fly_speed.png"):
        assert written[name].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        img = mpimg.imread(written[name])[..., :3]
        assert img.shape[0] > 300 and img.shape[1] > 800
        assert (img.std(axis=(0, 1)) > 0.05).any()                     # not a blank canvas
        assert (np.abs(img - 1.0).sum(axis=2) > 0.3).mean() > 0.03     # a few % of the pixels are drawn


def test_figures_without_map_context(log, tmp_path):
    bare = dataclasses.replace(log, grid=None, terrain_m=None, surface_m=None, coverage_floor_m=None,
                               landing_xy=None, events=[], nofly=[])
    files = write_flight(bare, tmp_path)
    assert {"fly_top.png", "fly_profile.png", "fly_speed.png"} <= set(files)
