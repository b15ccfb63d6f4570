"""STEP III (seed 000 III-C): smoothing, line of sight, navigation error, eq. 15 costs, choice;
the independent validator and the plan outputs.  Oracles: dense numerical integration of the
polynomial, a brute-force ray march for the line of sight, dense intruder sampling, pyproj
back-projection of the GeoJSON."""

from __future__ import annotations

import csv
import dataclasses
import json
import math

import numpy as np
import pandas as pd
import pytest
from pyproj import Transformer

from skyroute.pipeline.errors import InputError, PlanningError
from skyroute.stages.almanac import sky_geometry
from skyroute.stages.grid import Grid
from skyroute.stages.occlusion import grid_azimuth_deg
from skyroute.stages.planning.outputs import CANDIDATE_COLUMNS, WAYPOINT_COLUMNS, write_plan
from skyroute.stages.planning.problem import PlanningProblem
from skyroute.stages.planning.rrt import deconflict
from skyroute.stages.planning.step3 import choose, explain_no_plan, line_of_sight, step3
from skyroute.stages.planning.validate import intruder_clearance_m, validate_plan
from skyroute.stages.traffic import Intruder, build_occupancy
from skyroute.stages.vehicle import load_vehicle

X0, Y0 = 385000.0, 6672000.0
START = pd.Timestamp("2020-01-03T12:00:00Z")
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
def sky(shared_data):
    g = grid()
    lon, lat = g.to_lonlat(X0 + 500, Y0 + 300)
    with pytest.warns(UserWarning, match="unhealthy"):
        return sky_geometry(shared_data / "gnss" / "yuma_2020-01-03.txt",
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
                         intruders=it, d_c_m=D_C, dt_c_s=DT_C, tol_deg=3.0) == []


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
              ceiling_m=problem.ceiling_m, intruders=it, d_c_m=D_C, dt_c_s=DT_C, tol_deg=3.0)
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
