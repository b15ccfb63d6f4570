"""STEP III (seed 000 III-C): smoothing, line of sight, navigation error, eq. 15 costs, choice;
the independent validator and the plan outputs.  Oracles: dense numerical integration of the
polynomial, a brute-force ray march for the line of sight, dense intruder sampling, pyproj
back-projection of the GeoJSON."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import re

import numpy as np
import pandas as pd
import pytest
from pyproj import Transformer

from skyroute.pipeline.errors import InputError, PlanningError
from skyroute.pipeline.settings import catalog_dir
from skyroute.stages.almanac import sky_geometry
from skyroute.stages.grid import Grid
from skyroute.stages.occlusion import grid_azimuth_deg
from skyroute.stages.planning.deconflict import deconflict
from skyroute.stages.planning.outputs import CANDIDATE_COLUMNS, WAYPOINT_COLUMNS, write_plan
from skyroute.stages.planning.problem import PlanningProblem
from skyroute.stages.planning.step3 import choose, explain_no_plan, line_of_sight, step3
from skyroute.stages.planning.validate import intruder_clearance_m, validate_plan
from skyroute.stages.traffic import Intruder, build_occupancy
from skyroute.stages.vehicle import load_vehicle

X0, Y0 = 385000.0, 6672000.0
START = pd.Timestamp("2020-01-03T12:00:00Z")
CATALOG_DATA = catalog_dir() / "data"
CHAIN = np.array([[100, 300, 30], [300, 320, 30], [500, 300, 30], [700, 280, 30], [900, 300, 30.0]]) + [X0, Y0, 0]
D_C, DT_C = 10.0, 10.0


def grid():
    return Grid.from_bounds("EPSG:32635", X0, Y0, X0 + 1000, Y0 + 600, 5.0)


def surface():
    s = np.zeros(grid().shape)
    s[20:50, 90:110] = 45.0          # a 45 m block 50 m north of the chain (y 350..500, x 450..550)
    return s


def make_problem(wind=(3.0, 0.0, 0.0), vehicle=None):
    g = grid()
    terr = np.zeros(g.shape)
    s = surface()
    floor = np.maximum(terr + 10.0, np.where(s > 0, s + 5.0, 0.0))
    risk = np.where(g.x[None, :] > X0 + 500, 1.0, 0.2) * np.ones(g.shape)
    return PlanningProblem(grid=g, terrain_m=terr, floor_m=floor, ceiling_m=terr + 80.0, risk_cost=risk,
                           landing_cost=np.full(g.shape, 0.5), wind_uvw=np.asarray(wind, float),
                           vehicle=vehicle or load_vehicle("dji-m300-rtk"), weights=(1.0, 4.0, 2.0, 1.0),
                           start_xyz=tuple(CHAIN[0]), goal_xyz=tuple(CHAIN[-1]), min_agl_m=0.0, max_agl_m=80.0,
                           label="D_2", dop_threshold=3.0)


def intruders():
    return [Intruder("north-south", np.array([0.0, 80.0]), np.array([[500, -100, 30], [500, 700, 30.0]]) + [X0, Y0, 0], 2.0),
            Intruder("diagonal", np.array([20.0, 120.0]), np.array([[800, 600, 30], [650, 0, 30.0]]) + [X0, Y0, 0], 2.0)]


@pytest.fixture(scope="module")
def sky():
    g = grid()
    lon, lat = g.to_lonlat(X0 + 500, Y0 + 300)
    with pytest.warns(UserWarning, match="unhealthy"):
        return sky_geometry(CATALOG_DATA / "yuma_2020-01-03.txt",  # shipped copy of shared/data/gnss's
                            pd.date_range(START, periods=4, freq="60s"), lat, lon)


@pytest.fixture(scope="module")
def problem():
    return make_problem()


@pytest.fixture(scope="module")
def traffic():
    it = intruders()
    return it, build_occupancy(it, 400.0, 20, D_C, DT_C)


@pytest.fixture(scope="module")
def cand(problem, traffic, sky):
    it, occ = traffic
    s2 = deconflict(problem, CHAIN, occ, seed=0)
    assert s2.status == "deconflicted"
    return step3(problem, s2, sky, surface(), start_time_utc=START, occupancy=occ, intruders=it)


def test_candidate_flyable_and_valid(cand, problem, traffic):
    it, occ = traffic
    assert cand.flyable, cand.reasons
    assert cand.t_s[0] == 0.0 and np.all(np.diff(cand.t_s) > 0)
    np.testing.assert_allclose(cand.xyz_m[0], CHAIN[0], atol=1e-6)
    np.testing.assert_allclose(cand.xyz_m[-1], CHAIN[-1], atol=1e-6)
    # dense re-check of the smooth curve: static bounds and exact traffic capsules
    tt = np.linspace(0.0, cand.trajectory.duration_s, 20001)
    pp = cand.trajectory.sample(tt)
    assert problem.state_valid(pp).all()
    assert not occ.segment_conflicts(pp[:-1], tt[:-1], pp[1:], tt[1:]).any()
    # independent brute force: intruder positions every 0.02 s within +-dt_c of each sample
    for intr in it:
        for i in range(0, tt.size, 40):
            tau = np.arange(max(tt[i] - DT_C, intr.times_s[0]), min(tt[i] + DT_C, intr.times_s[-1]), 0.02)
            if tau.size:
                q = np.stack([np.interp(tau, intr.times_s, intr.xyz_m[:, j]) for j in range(3)], axis=1)
                assert np.linalg.norm(q - pp[i], axis=1).min() >= intr.radius_m + D_C - 0.2
    assert cand.max_sigma_p_m <= problem.vehicle.max_position_error_m
    assert validate_plan(cand, grid=problem.grid, terrain_m=problem.terrain_m, vehicle=problem.vehicle,
                         floor_m=problem.floor_m, ceiling_m=problem.ceiling_m, wind=np.array([3.0, 0, 0]),
                         intruders=it, d_c_m=D_C, dt_c_s=DT_C) == []


def test_eq15_costs_against_dense_integration(cand, problem):
    traj = cand.trajectory
    tt = np.linspace(0.0, traj.duration_s, 400001)
    pp = traj.sample(tt)
    L = float(np.sum(np.linalg.norm(np.diff(pp, axis=0), axis=1)))
    assert cand.C_l == pytest.approx(L, abs=0.05)                     # 5 cm on ~850 m
    assert cand.flight_time_s == pytest.approx(traj.duration_s)
    g = problem.grid
    col = np.floor((pp[:, 0] - g.x0) / g.resolution_m).astype(int)
    beta_r = np.where(g.x0 + (col + 0.5) * g.resolution_m > X0 + 500, 1.0, 0.2)
    mean_r = float(np.mean(0.5 * (beta_r[1:] + beta_r[:-1])))
    # time average of a step map: the 0.5 s sampling of STEP III resolves the step to ~1 sample
    assert cand.C_r == pytest.approx(L * mean_r, rel=5e-3)
    assert cand.C_d == pytest.approx(0.5 * cand.C_l, rel=1e-12)      # uniform landing map
    wl, wr, wd, we = problem.weights
    assert cand.f == pytest.approx(wl * cand.C_l + wr * cand.C_r + wd * cand.C_d + we * cand.C_e, rel=1e-12)
    assert cand.C_e < cand.C_l                                         # 3 m/s tail wind (flying east)


def test_no_wind_energy_cost_equals_length(sky):
    prob = make_problem(wind=(0.0, 0.0, 0.0))
    s2 = deconflict(prob, CHAIN, None)
    c = step3(prob, s2, sky, surface(), start_time_utc=START)
    assert s2.status == "unchanged" and c.flyable, c.reasons
    assert c.C_e == pytest.approx(c.C_l, rel=1e-12)                  # beta_e = P(v)/P(v) = 1
    # STEP II chain energy (eq. 12 at v_c) vs the smooth trajectory (same chain, same times)
    assert c.energy_J == pytest.approx(s2.energy_J[-1], rel=0.25)


def test_line_of_sight_against_ray_march(problem, sky):
    rng = np.random.default_rng(3)
    n = 60
    pts = np.column_stack([X0 + rng.uniform(400, 600, n), Y0 + rng.uniform(250, 345, n), rng.uniform(10, 40, n)])
    t = np.zeros(n)
    los, vis = line_of_sight(problem, sky, surface(), t, pts, START)
    e = 0
    up = sky["above_mask"].values[e]
    az = sky["az_deg"].values[e]
    el = sky["el_deg"].values[e]
    g, s = problem.grid, surface()
    agree = total = unsafe = 0
    for j in np.nonzero(up)[0]:
        a = math.radians(float(grid_azimuth_deg(az[j], g)))
        d = np.array([math.sin(a), math.cos(a)])
        step = np.arange(0.25, 700.0, 0.25)
        for i in range(n):
            xy = pts[i, :2] + step[:, None] * d
            col = np.floor((xy[:, 0] - g.x0) / g.resolution_m).astype(int)
            row = np.floor((g.y1 - xy[:, 1]) / g.resolution_m).astype(int)
            ok = (col >= 0) & (col < g.nx) & (row >= 0) & (row < g.ny)
            ray = pts[i, 2] + step * math.tan(math.radians(el[j]))
            blocked = np.any(s[row[ok], col[ok]] > ray[ok])
            agree += (not blocked) == vis[i, j]
            unsafe += blocked and vis[i, j]
            total += 1
    assert total > 300
    # the cell's visibility height bounds every point of the cell (occlusion contract): the
    # disagreements are on the safe side (occluded where the point itself sees the satellite)
    assert agree / total >= 0.97
    assert unsafe == 0
    assert not vis[:, ~up].any()
    blocked_frac = 1 - vis[:, up].mean()
    assert blocked_frac > 0.02                                         # the block does occlude


def test_line_of_sight_windowed_equals_whole_map(problem, sky):
    """Without a cache, line_of_sight scans each satellite only over the cells that can decide
    its samples (occluder windows); with a cache, whole-map visibility heights: the same
    answers at every sample (above, beside, in the shadow of the block, outside the map),
    over several sky epochs."""
    rng = np.random.default_rng(8)
    n = 400
    pts = np.column_stack([X0 + rng.uniform(-50, 1050, n), Y0 + rng.uniform(150, 560, n), rng.uniform(5, 60, n)])
    pts[:40, 2] = 45.0                                               # exactly the block's height
    t = np.sort(rng.uniform(-30.0, 200.0, n))
    los_w, vis_w = line_of_sight(problem, sky, surface(), t, pts, START)
    los_c, vis_c = line_of_sight(problem, sky, surface(), t, pts, START, cache={})
    np.testing.assert_array_equal(vis_w, vis_c)
    np.testing.assert_array_equal(los_w, los_c)
    up_any = vis_c.any(axis=0)
    assert 0.02 < 1 - vis_c[:, up_any].mean() < 0.9                  # occlusions are part of the test


def test_line_of_sight_cache_stays_within_its_budget(problem, sky, monkeypatch):
    """A cache keeps whole-map visibility heights only up to LOS_CACHE_MAX_BYTES (a tactical
    replay on the 6 km Helsinki AOI kept 21 epochs of 0.8 GB, 17.8 GB); the samples of the
    epochs beyond it are answered on their windows: the same answers, and the cache holds
    what fits (here 2 epochs' worth), also on later calls."""
    from skyroute.stages import sky_visibility

    rng = np.random.default_rng(9)
    n = 300
    pts = np.column_stack([X0 + rng.uniform(-50, 1050, n), Y0 + rng.uniform(150, 560, n), rng.uniform(5, 60, n)])
    t = np.sort(rng.uniform(-30.0, 400.0, n))
    los_w, vis_w = line_of_sight(problem, sky, surface(), t, pts, START)
    full: dict = {}
    line_of_sight(problem, sky, surface(), t, pts, START, cache=full)
    per_epoch = max(v.nbytes for v in full.values())
    assert len(full) >= 4
    monkeypatch.setattr(sky_visibility, "LOS_CACHE_MAX_BYTES", 2 * per_epoch + per_epoch // 2)
    small: dict = {}
    for _ in range(2):
        los_c, vis_c = line_of_sight(problem, sky, surface(), t, pts, START, cache=small)
        np.testing.assert_array_equal(vis_w, vis_c)
        np.testing.assert_array_equal(los_w, los_c)
        assert 1 <= len(small) <= 2 and sum(v.nbytes for v in small.values()) <= 2.5 * per_epoch


def test_sigma_above_dp_max_is_not_flyable(sky):
    veh = load_vehicle("dji-m300-rtk").model_copy(update={"max_position_error_m": 0.3})
    prob = make_problem(vehicle=veh)
    c = step3(prob, deconflict(prob, CHAIN, None), sky, surface(), start_time_utc=START)
    assert not c.flyable and any("navigation error" in r for r in c.reasons)
    assert c.max_sigma_p_m > 0.3
    c2 = step3(prob, deconflict(prob, CHAIN, None), None, surface())
    assert not c2.flyable and any("no satellite geometry" in r for r in c2.reasons)


def test_failed_step2_and_choose(cand, problem, sky):
    veh = load_vehicle("dji-m300-rtk").model_copy(update={"battery_capacity_mah": 100.0})
    prob = make_problem(vehicle=veh)
    bad = step3(prob, deconflict(prob, CHAIN, None), sky, surface())
    assert not bad.flyable and "energy infeasible" in bad.reasons[0]
    better = dataclasses.replace(cand, label="D_1", f=cand.f - 100.0)
    unflyable_cheaper = dataclasses.replace(cand, label="D_3", f=cand.f - 500.0, flyable=False,
                                            reasons=["navigation error sigma_p reaches 3 m"])
    assert choose([cand, better, unflyable_cheaper, bad]) is better
    assert choose([bad, unflyable_cheaper]) is None
    msg = explain_no_plan([bad, unflyable_cheaper])
    assert "energy infeasible" in msg and "D_3" in msg
    with pytest.raises(PlanningError, match="no flyable plan"):
        choose([bad], raise_if_none=True)
    with pytest.raises(InputError, match="sample_dt_s"):
        step3(problem, deconflict(problem, CHAIN, None), sky, surface(), sample_dt_s=0.0)


def test_validate_plan_finds_every_violation(cand, problem, traffic):
    it, _ = traffic
    kw = dict(grid=problem.grid, terrain_m=problem.terrain_m, vehicle=problem.vehicle, floor_m=problem.floor_m,
              ceiling_m=problem.ceiling_m, intruders=it, d_c_m=D_C, dt_c_s=DT_C)
    p = cand.xyz_m.copy()
    p[10:20, 2] = 5.0                                   # below the 10 m floor (and a steep dive)
    msgs = validate_plan((cand.t_s, p), **kw)
    assert any("below the altitude floor" in m for m in msgs)
    assert any("flight-path angle" in m for m in msgs)
    # the STEP I chain flown at constant speed meets the north-south intruder
    t = np.linspace(0, 85, 400)
    q = np.stack([np.interp(t, [0, 85], [CHAIN[0, j], CHAIN[-1, j]]) for j in range(3)], axis=1)
    msgs = validate_plan((t, q), **kw)
    assert any("north-south" in m for m in msgs)
    msgs = validate_plan((t, q + [0, 1000, 0]), **kw, wind=np.array([16.0, 0, 0]))
    assert any("outside the map" in m for m in msgs) and any("wind above" in m for m in msgs)
    # exact point-to-track distance vs dense sampling of the intruder
    d = intruder_clearance_m(t, q, it[0], DT_C)
    for i in range(0, t.size, 25):
        tau = np.arange(t[i] - DT_C, t[i] + DT_C + 1e-9, 0.001)
        tau = tau[(tau >= it[0].times_s[0]) & (tau <= it[0].times_s[-1])]
        qi = np.stack([np.interp(tau, it[0].times_s, it[0].xyz_m[:, j]) for j in range(3)], axis=1)
        assert d[i] == pytest.approx(np.linalg.norm(qi - q[i], axis=1).min(), abs=0.01)


def test_write_plan_round_trips(cand, tmp_path, problem):
    other = dataclasses.replace(cand, label="D_3", flyable=False, reasons=["navigation error too large"])
    files = write_plan(cand, [cand, other], problem.grid, tmp_path, START, "flat local ground (test)",
                       surface_m=surface(), terrain_m=problem.terrain_m, floor_m=problem.floor_m,
                       cost_m=problem.risk_cost)
    gj = json.loads(files["plan.geojson"].read_text())
    f0 = gj["features"][0]
    assert gj["type"] == "FeatureCollection" and f0["geometry"]["type"] == "LineString"
    assert f0["properties"]["heights_are_ellipsoidal"] is False
    assert "NOT ellipsoidal" in f0["properties"]["altitude_note"]
    assert f0["properties"]["vertical_datum"] == "flat local ground (test)"
    ll = np.array(f0["geometry"]["coordinates"])
    x, y = Transformer.from_crs(4326, problem.grid.crs, always_xy=True).transform(ll[:, 0], ll[:, 1])
    assert np.max(np.hypot(x - cand.xyz_m[:, 0], y - cand.xyz_m[:, 1])) < 0.01          # 1 cm
    np.testing.assert_allclose(ll[:, 2], cand.xyz_m[:, 2])
    np.testing.assert_allclose(np.array(f0["properties"]["map_xyz_m"]), cand.xyz_m)
    times = pd.to_datetime(f0["properties"]["times_utc"])
    assert times.tz is not None
    dt_s = (times - START).total_seconds().to_numpy()
    np.testing.assert_allclose(dt_s, cand.t_s, atol=1e-3)
    with open(files["waypoints.csv"]) as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0].keys()) == WAYPOINT_COLUMNS and len(rows) == cand.t_s.size
    w = np.array([[float(r[k]) for k in ("t_s", "x_m", "y_m", "z_m", "lon", "lat", "alt_agl_m", "sigma_p_m")]
                  for r in rows])
    np.testing.assert_allclose(w[:, 1:4], cand.xyz_m, atol=1e-3)
    x2, y2 = Transformer.from_crs(4326, problem.grid.crs, always_xy=True).transform(w[:, 4], w[:, 5])
    assert np.max(np.hypot(x2 - w[:, 1], y2 - w[:, 2])) < 0.01
    np.testing.assert_allclose(w[:, 7], cand.sigma_p_m, atol=1e-4)
    with open(files["candidates.csv"]) as fh:
        cr = list(csv.DictReader(fh))
    assert tuple(cr[0].keys()) == CANDIDATE_COLUMNS and [r["label"] for r in cr] == ["D_2", "D_3"]
    assert float(cr[0]["f_m"]) == pytest.approx(cand.f, abs=0.05)
    assert float(cr[0]["energy_Wh"]) == pytest.approx(cand.energy_J / 3600, abs=0.005)
    assert cr[0]["chosen"] == "true" and cr[1]["chosen"] == "false" and cr[1]["flyable"] == "false"
    assert "navigation error" in cr[1]["reasons"]
    for name in ("top_view.png", "profile.png", "sigma_p.png"):
        assert files[name].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # no flyable plan: only the candidates table, with the reasons
    files = write_plan(None, [other], problem.grid, tmp_path / "none", START, "x")
    assert set(files) == {"candidates.csv"}


# ------------------------------------------------------------------ hard limits (issue 9)


def _line(t, v, p0=(X0 + 100, Y0 + 300, 50.0), a=(0.0, 0.0, 0.0)):
    """Samples of p0 + v t + a t^2 / 2 at times t."""
    t = np.asarray(t, float)[:, None]
    return np.asarray(p0) + np.asarray(v) * t + 0.5 * np.asarray(a) * t * t


def _kw(problem, **extra):
    return dict(grid=problem.grid, terrain_m=problem.terrain_m, vehicle=problem.vehicle, **extra)


@pytest.mark.parametrize("what, v, a, wind, flagged", [
    # flight-path angle 15 deg: 15.05 flagged, 14.95 not (tolerance 0)
    ("flight-path angle", [10 * math.cos(math.radians(15.05)), 0, 10 * math.sin(math.radians(15.05))], 0, 0, True),
    ("flight-path angle", [10 * math.cos(math.radians(14.95)), 0, 10 * math.sin(math.radians(14.95))], 0, 0, False),
    # descent 5 m/s: 5.02 flagged, 4.98 not (19 m/s horizontal keeps the angle below 15 deg)
    ("descent rate", [19.0, 0, -5.02], 0, 0, True),
    ("descent rate", [19.0, 0, -4.98], 0, 0, False),
    # climb 6 m/s at 23 m/s ground speed needs a tail wind to stay below the airspeed limit
    ("climb rate", [23.0, 0, 6.02], 0, 5.0, True),
    ("climb rate", [23.0, 0, 5.98], 0, 5.0, False),
    # acceleration 3 m/s^2 along the track
    ("acceleration", [5.0, 0, 0], 3.01, 0, True),
    ("acceleration", [5.0, 0, 0], 2.99, 0, False),
    # airspeed 23 m/s = |v_ground - wind|: 10 m/s east into a 13.05 m/s head wind
    ("airspeed", [10.0, 0, 0], 0, -13.05, True),
    ("airspeed", [10.0, 0, 0], 0, -12.95, False),
])
def test_validator_flags_each_limit_by_a_little(problem, what, v, a, wind, flagged):
    t = np.arange(0.0, 4.0, 0.5)
    p = _line(t, v, a=(a, 0, 0))
    msgs = validate_plan((t, p), **_kw(problem, wind=np.array([wind, 0.0, 0.0])))
    hit = [m for m in msgs if m.startswith(what)]
    assert bool(hit) == flagged, msgs
    assert len(msgs) == len(hit)            # nothing else is violated


def test_validator_exempts_short_horizontal_chords_from_the_angle(problem):
    t = np.array([0.0, 1.0, 2.0])
    p = _line(t, [1.5, 0, 1.0])                       # 34 deg but 1.5 m horizontal per chord
    assert validate_plan((t, p), **_kw(problem)) == []
    p = _line(t, [0.0, 0, 6.5])                       # vertical: no angle, but 6.5 m/s > 6 m/s climb
    assert any(m.startswith("climb rate") for m in validate_plan((t, p), **_kw(problem)))


def test_validator_battery_reserve(problem):
    veh = problem.vehicle
    t = np.array([0.0, 1.0])
    cand = dataclasses.make_dataclass("C", ["t_s", "xyz_m", "energy_J"])(t, _line(t, [5.0, 0, 0]),
                                                                        0.81 * veh.battery_energy_j)
    assert validate_plan(cand, **_kw(problem)) == []
    msgs = validate_plan(cand, **_kw(problem), battery_reserve_pct=20.0)
    assert len(msgs) == 1 and "20 % reserve" in msgs[0]
    with pytest.raises(InputError, match="battery_reserve_pct"):
        validate_plan(cand, **_kw(problem), battery_reserve_pct=100.0)


def test_step3_hairpin_chain_is_flown_within_every_limit(problem, sky):
    """A chain with a 138 deg hairpin at the end of a 14.5 deg climb, then a 15 deg descent:
    flyable, the validator (tolerance 0) and a dense check of the continuous trajectory agree."""
    a = np.array([X0 + 100, Y0 + 250, 20.0])
    b = a + [160, 0, 160 * math.tan(math.radians(14.5))]
    hd = math.radians(138)
    c = b + [100 * math.cos(hd), 100 * math.sin(hd), -100 * math.tan(math.radians(15))]
    d = c + [250, 20, 0]
    chain = np.array([a, b, c, d])
    prob = dataclasses.replace(problem, start_xyz=tuple(a), goal_xyz=tuple(d))
    assert prob.motion_valid(chain[:-1], chain[1:]).all()
    s2 = deconflict(prob, chain, None)
    cand = step3(prob, s2, sky, surface(), start_time_utc=START)
    assert cand.flyable, cand.reasons
    tr = cand.trajectory
    tt = np.linspace(0, tr.duration_s, 100001)
    v, acc = tr.velocity(tt), tr.acceleration(tt)
    veh = prob.vehicle
    h = np.hypot(v[:, 0], v[:, 1])
    assert np.all(np.abs(v[:, 2]) <= math.tan(math.radians(veh.max_flight_path_angle_deg)) * h + 1e-9)
    assert np.all(np.linalg.norm(acc, axis=1) <= veh.max_acceleration_mps2 + 1e-9)
    assert np.all(np.linalg.norm(v - [3.0, 0, 0], axis=1) <= veh.max_airspeed_mps + 1e-9)
    assert prob.state_valid(tr.sample(tt)).all()
    d = np.diff(cand.xyz_m, axis=0)
    hh = np.hypot(d[:, 0], d[:, 1])
    assert np.all(np.abs(d[:, 2]) <= math.tan(math.radians(15)) * hh + 1e-9)   # every written chord


def test_step3_rechecks_traffic_at_the_retimed_schedule(problem, sky):
    """STEP II's constant-speed schedule passes in front of a crossing drone; the retimed
    trajectory (at rest at the start, so later everywhere) meets it: not flyable, and the reason
    says where and when."""
    a, b = np.array([X0 + 100, Y0 + 300, 30.0]), np.array([X0 + 900, Y0 + 300, 30.0])
    prob = dataclasses.replace(problem, start_xyz=tuple(a), goal_xyz=tuple(b))
    free = step3(prob, deconflict(prob, np.array([a, b]), None), sky, surface(), start_time_utc=START)
    assert free.flyable, free.reasons
    tr = free.trajectory
    tt = np.linspace(0, tr.duration_s, 200001)
    t_x = float(tt[np.argmin(np.abs(tr.sample(tt)[:, 0] - (X0 + 500)))])   # retimed passage at x = 500
    crossing = Intruder("crosser", np.array([t_x - 10, t_x + 10]),
                        np.array([[500, 500, 30], [500, 100, 30.0]]) + [X0, Y0, 0], 2.0)
    occ = build_occupancy([crossing], 200.0, 1000, 2.0, 0.2)     # 0.2 s slices: capsules ~8 m long
    s2 = deconflict(prob, np.array([a, b]), occ)
    assert s2.status == "unchanged"                  # STEP II's own schedule is conflict-free
    c = step3(prob, s2, sky, surface(), start_time_utc=START, occupancy=occ, intruders=[crossing])
    assert not c.flyable
    msg = next(r for r in c.reasons if r.startswith("traffic:"))
    m = re.search(r"at t = ([\d.]+) s near \(([\d.]+), ([\d.]+), ([\d.]+)\)", msg)
    assert "after retiming" in msg and m, msg
    assert abs(float(m.group(1)) - t_x) < 1.0
    assert math.hypot(float(m.group(2)) - (X0 + 500), float(m.group(3)) - (Y0 + 300)) < 10.0
    assert any("crosser" in r for r in c.reasons)    # the independent validator agrees
