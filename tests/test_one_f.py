"""Issue 35 items 3 and 16: one definition of f for every planner, and what the QGroundControl
mission's waypoints are.

Item 3: f is seed 000 eq. 11 (``w_l C_l + w_r C_r + w_d C_d + w_e C_e``) on the written
trajectory for every planner, by the rotorcraft's implementation
(:func:`~skyroute.stages.planning.step3.trajectory_costs`); a planner's own search objective is
``search_cost_m``.  Oracles: the trajectory's length from its samples, the risk / landing maps
averaged by hand, the energy ratio from the public seed-002 energy (``segment_energy_fw``), and
eq. 11 evaluated by hand from the C_* columns and the weights.

Item 16: ``plan.plan`` says its waypoints are chords (top-level ``skyroute`` object, with the
computed deviation), the chords stay in the admissible volume, and a fixed-wing mission ends
with a landing pattern (DO_LAND_START, LOITER_TO_ALT, NAV_LAND).  Oracles: the sagitta of an
arc, pyproj's geodesic inverse, the problem's exact motion check.

Small synthetic problems only (the fixed-wing searches take < 1 s here)."""

from __future__ import annotations

import csv
import dataclasses
import json
import math

import numpy as np
import pytest
import xarray as xr
from pyproj import Geod

from skyroute.stages.base import InputError
from skyroute.stages.exports import arrival_loiter, chord_deviation, qgc_plan
from skyroute.stages.fixedwing_energy import segment_energy_fw
from skyroute.stages.grid import Grid
from skyroute.stages.planning.fixedwing import fixedwing_candidate, plan_fixedwing
from skyroute.stages.planning.outputs import write_plan
from skyroute.stages.planning.problem import build_problem
from skyroute.stages.planning.step3 import eq11_f, smooth_chain, trajectory_costs
from skyroute.stages.planning.strategic import StrategicPlan, plan_from_dataset, plan_to_dataset
from skyroute.stages.vehicle import load_vehicle

WEIGHTS = (1.0, 2.0, 0.5, 3.0)


def _problem(weights=WEIGHTS, wind=(3.0, 1.0, 0.0), vehicle="skywalker-x8", start=(300.0, 900.0),
             goal=(2700.0, 1000.0), agl=100.0):
    """A 3 x 2 km valley at 30 m with a ridge across the route, and risk / landing maps that vary."""
    g = Grid.from_bounds("EPSG:32611", 0, 0, 3000, 2000, 30)
    x = g.x0 + (np.arange(g.nx) + 0.5) * g.resolution_m
    y = g.y1 - (np.arange(g.ny) + 0.5) * g.resolution_m
    xx, yy = np.meshgrid(x, y)
    ridge = 260 * np.exp(-(((xx - 1500) / 250) ** 2)) * (1 - 0.7 * np.exp(-(((yy - 1700) / 250) ** 2)))
    t = 400 + ridge + 0.02 * xx
    da = g.dataarray(t, "terrain", units="m")
    ds = xr.Dataset({"terrain": da, "surface": da})
    risk = 0.2 + 0.8 * (xx / 3000.0)
    landing = 1.0 - 0.5 * (yy / 2000.0)
    r0, c0 = g.index_of(*start)
    r1, c1 = g.index_of(*goal)
    return build_problem(ds, t + 15.0, None, risk, landing, wind, vehicle, weights, (*start, t[r0, c0] + agl),
                         (*goal, t[r1, c1] + agl), 30.0, 300.0)


@pytest.fixture(scope="module")
def fw():
    pr = _problem()
    res = {p: plan_fixedwing(pr, p, corridor_m=600.0) for p in ("astar-fw", "eeastar")}
    assert all(r.solved for r in res.values())
    return pr, res


# ------------------------------------------------------------------ item 3: one f


def test_same_path_two_planners_same_f(fw):
    """The issue: eeastar reported f = C_e (22983 m), astar-fw f = C_l (10914 m) for the same
    path.  Now the same path gives the same f and costs whichever planner found it; only the
    search objective differs (and is its own column)."""
    pr, res = fw
    r = res["eeastar"]
    cands = {p: fixedwing_candidate(pr, dataclasses.replace(r, planner=p))
             for p in ("eeastar", "astar-fw", "energy-optimal", "bitstar-dubins")}
    ref = cands["eeastar"]
    for c in cands.values():
        assert (c.C_l, c.C_r, c.C_d, c.C_e, c.f) == (ref.C_l, ref.C_r, ref.C_d, ref.C_e, ref.f)
    veh = load_vehicle("skywalker-x8")
    assert cands["eeastar"].search_cost_m == pytest.approx(r.energy_J / (veh.weight_n * veh.min_drag_to_lift),
                                                            rel=1e-12)
    assert cands["astar-fw"].search_cost_m == pytest.approx(r.length_m, rel=1e-12)
    assert "energy" in cands["eeastar"].search_objective and "length" in cands["astar-fw"].search_objective
    # weights 1, 0, 0, 0: f is the written trajectory's length for both planners
    pr1 = pr.with_weights((1.0, 0.0, 0.0, 0.0))
    f1 = {p: fixedwing_candidate(pr1, res[p]).f for p in res}
    for p, f in f1.items():
        c = fixedwing_candidate(pr1, res[p])
        assert f == pytest.approx(np.linalg.norm(np.diff(c.xyz_m, axis=0), axis=1).sum(), rel=1e-9)
    assert f1["astar-fw"] <= f1["eeastar"] * (1 + 1e-3)   # the shortest lattice path stays (about) the shortest


def test_f_is_eq11_of_the_costs_and_the_costs_are_independent(fw):
    pr, res = fw
    c = fixedwing_candidate(pr, res["eeastar"])
    assert c.flyable, c.reasons
    wl, wr, wd, we = WEIGHTS
    assert c.f == pytest.approx(wl * c.C_l + wr * c.C_r + wd * c.C_d + we * c.C_e, rel=1e-12)
    # C_l: the length of the written samples; C_r / C_d: the maps averaged over time (by hand)
    p, t = c.xyz_m, c.t_s
    L = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())
    assert c.C_l == pytest.approx(L, rel=1e-9)
    r, col = pr.grid.index_of(p[:, 0], p[:, 1])
    risk, land = np.asarray(pr.risk_cost)[r, col], np.asarray(pr.landing_cost)[r, col]
    dur = t[-1] - t[0]
    mean = lambda v: float(np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(t))) / dur   # noqa: E731
    assert c.C_r == pytest.approx(L * mean(risk), rel=1e-9)
    assert c.C_d == pytest.approx(L * mean(land), rel=1e-9)
    assert 0.2 * L < c.C_r < L and 0.5 * L < c.C_d < L
    # C_e: energy per chord in the wind over in still air (public seed-002 energy), time-averaged
    ew = segment_energy_fw(p[:-1], p[1:], (3.0, 1.0, 0.0), "skywalker-x8")["energy_J"]
    e0 = segment_energy_fw(p[:-1], p[1:], (0.0, 0.0, 0.0), "skywalker-x8")["energy_J"]
    ratio = np.where(e0 > 0, ew / np.where(e0 > 0, e0, 1.0), 1.0)
    assert c.C_e == pytest.approx(L * float(np.sum(ratio * np.diff(t))) / dur, rel=1e-6)
    # still air: C_e = C_l
    calm = _problem(wind=(0.0, 0.0, 0.0))
    cc = fixedwing_candidate(calm, plan_fixedwing(calm, "astar-fw", corridor_m=600.0))
    assert cc.C_e == pytest.approx(cc.C_l, rel=1e-9)


def test_trajectory_costs_is_eq15_by_hand():
    t = np.array([0.0, 1.0, 3.0, 4.0])
    speed = np.array([2.0, 2.0, 4.0, 4.0])
    br, bd, be = np.array([1.0, 0.0, 0.0, 1.0]), np.full(4, 0.5), np.array([1.0, 2.0, 0.5])   # be: per chord
    L = 2.0 * 1 + 3.0 * 2 + 4.0 * 1
    c = trajectory_costs((1.0, 2.0, 3.0, 4.0), t, speed, br, bd, be)
    assert c["C_l"] == pytest.approx(L)
    assert c["C_r"] == pytest.approx(L * (0.5 + 0.0 + 0.5) / 4.0)
    assert c["C_d"] == pytest.approx(L * 0.5)
    assert c["C_e"] == pytest.approx(L * (1.0 + 4.0 + 0.5) / 4.0)
    assert c["f"] == pytest.approx(c["C_l"] + 2 * c["C_r"] + 3 * c["C_d"] + 4 * c["C_e"])
    assert eq11_f((1, 0, 0, 0), 5.0, 1.0, 2.0, 3.0) == 5.0
    with pytest.raises(InputError, match="one per sample or one per chord"):
        trajectory_costs((1, 0, 0, 0), t, speed, br, bd, np.ones(2))


def test_candidates_csv_has_the_search_objective_apart(fw, tmp_path):
    """candidates.csv: f_m is eq. 11 of its own C_* columns with the weights (hand-evaluated from
    the file); the search objective has its own columns; the plan dataset keeps them."""
    pr, res = fw
    cands = [fixedwing_candidate(pr, res[p], label=p) for p in ("eeastar", "astar-fw")]
    ds = plan_to_dataset(StrategicPlan(cands[0], cands), "EPSG:32611", "EGM96 height", "2024-05-01T10:00:00Z")
    chosen, back = plan_from_dataset(ds)
    assert [b.search_cost_m for b in back] == [c.search_cost_m for c in cands]
    assert back[0].search_objective == cands[0].search_objective and back[0].f == cands[0].f
    write_plan(None, cands, "EPSG:32611", tmp_path, "2024-05-01T10:00:00Z", "EGM96 height", figures=False)
    rows = list(csv.DictReader(open(tmp_path / "candidates.csv")))
    for row in rows:
        f = sum(w * float(row[k]) for w, k in zip(WEIGHTS, ("C_l_m", "C_r_m", "C_d_m", "C_e_m"), strict=True))
        assert float(row["f_m"]) == pytest.approx(f, abs=0.5)        # columns rounded to 0.1 m
        assert float(row["search_cost_m"]) > 0 and row["search_objective"]
    assert float(rows[1]["search_cost_m"]) == pytest.approx(res["astar-fw"].length_m, abs=0.06)


# ------------------------------------------------------------------ item 16: the QGC mission


def test_chord_deviation_is_the_sagitta_and_the_drop_of_a_climbing_arc():
    R, theta = 50.0, math.pi / 2
    a = np.linspace(0.0, theta, 2001)
    z = 100.0 + 20.0 * np.sin(a)               # climbs faster first: the chord is below the arc
    arc = np.column_stack([R * np.cos(a), R * np.sin(a), z])
    wp = arc[[0, -1]]
    d = chord_deviation(wp, arc)
    sag = R * (1 - math.cos(theta / 2))
    # exact: the largest distance of an arc point from the chord (the chord's points are closer to the arc)
    u = (wp[1] - wp[0]) / np.linalg.norm(wp[1] - wp[0])
    rel = arc - wp[0]
    exact = float(np.max(np.linalg.norm(rel - (rel @ u)[:, None] * u, axis=1)))
    assert exact > sag
    assert exact <= d["max_chord_deviation_m"] <= exact + 0.13
    assert d["max_chord_below_trajectory_m"] > 0.0
    flat = chord_deviation(np.array([[0, 0, 0], [100, 0, 0]], float), np.array([[0, 0, 0], [100, 0, 0]], float))
    assert flat == {"max_chord_deviation_m": 0.0, "max_chord_below_trajectory_m": 0.0}


def test_rotorcraft_chords_stay_in_the_admissible_volume():
    """The QGC mission of a rotorcraft flies the chords of the corner trajectory's piece
    boundaries: each is a valid exact motion (the fillet check covers its triangle), and a
    climbing turn puts a chord below the trajectory by at most the stated deviation."""
    pr = _problem(vehicle="dji-m300-rtk", start=(300.0, 300.0), goal=(900.0, 900.0), agl=40.0)
    s = np.asarray(pr.start_xyz, float)
    chain = np.array([s, [900.0, 300.0, s[2] + 30.0], [900.0, 900.0, pr.goal_xyz[2]]])
    assert pr.motion_valid(chain[:-1], chain[1:]).all()
    v = 8.0
    traj = smooth_chain(pr, chain, np.linalg.norm(np.diff(chain, axis=0), axis=1) / v)
    wp = np.asarray(traj.waypoints, float)
    assert len(wp) > len(chain)                             # the corner became an arc
    assert pr.motion_valid(wp[:-1], wp[1:]).all()
    samples = traj.sample(traj.sample_times(0.05))
    d = chord_deviation(wp, samples)
    assert d["max_chord_deviation_m"] > 0.0
    # waypoint chords never below the trajectory by more than the stated deviation
    assert d["max_chord_below_trajectory_m"] <= d["max_chord_deviation_m"]


def test_fixed_wing_mission_ends_with_a_landing_pattern(fw):
    pr, res = fw
    c = fixedwing_candidate(pr, res["eeastar"])
    wp = np.asarray(c.waypoints, float)
    assert pr.motion_valid(wp[:-1], wp[1:]).all()            # the mission's legs: exact motions
    lo = arrival_loiter(c.xyz_m, wp)
    assert lo is not None
    k, radius, clockwise = lo
    assert radius == pytest.approx(res["eeastar"].info["turn_radius_m"], rel=1e-6)
    assert np.allclose(c.xyz_m[k, :2], wp[-1, :2])
    dev = chord_deviation(wp, c.xyz_m[:k + 1])
    assert 0.0 < dev["max_chord_deviation_m"] < radius
    # a QGC mission in geographic coordinates near the equator-ish test area
    lon = 7.0 + np.array([0.0, 0.01, 0.02])
    lat = 43.0 + np.array([0.0, 0.0, 0.005])
    rel = np.array([100.0, 120.0, 110.0])
    land = {"ground_rel_m": 15.0, "loiter_radius_m": radius, "clockwise": clockwise, "descent_angle_deg": 8.0}
    doc = json.loads(json.dumps(qgc_plan(lon, lat, rel, 50.0, cruise_speed_mps=16.0, fixed_wing=True, landing=land,
                                         metadata=dev), allow_nan=False))
    items = doc["mission"]["items"]
    assert [i["command"] for i in items] == [22, 16, 16, 16, 189, 31, 21]
    assert all(i["command"] != 17 for i in items)             # no unlimited loiter
    loiter, touch = items[-2], items[-1]
    assert loiter["params"][1] == pytest.approx(radius if clockwise else -radius, abs=1e-3)
    assert loiter["params"][0] == 1 and loiter["params"][6] == 110.0          # exit heading required, goal altitude
    assert touch["params"][4:] == [lat[-1], lon[-1], 15.0]                     # on the ground under the goal
    geod = Geod(ellps="WGS84")
    approach = (110.0 - 15.0) / math.tan(math.radians(8.0))
    dist = geod.inv(lon[-1], lat[-1], loiter["params"][5], loiter["params"][4])[2]
    assert dist == pytest.approx(math.hypot(approach, radius), abs=0.05)
    meta = doc["skyroute"]
    assert "chords" in meta["note"] and meta["max_chord_deviation_m"] == dev["max_chord_deviation_m"]
    assert meta["landing"]["approach_length_m"] == pytest.approx(approach, abs=1e-3)
    assert "not" in meta["landing"]["note"] and "check" in meta["landing"]["note"]
    with pytest.raises(InputError, match="landing pattern"):
        qgc_plan(lon, lat, rel, 50.0, cruise_speed_mps=16.0, fixed_wing=True)
    rotor = qgc_plan(lon, lat, rel, 50.0, cruise_speed_mps=5.0, metadata=dev)
    assert rotor["mission"]["items"][-1]["command"] == 21 and "skyroute" in rotor


def test_a_mission_leg_through_the_ridge_is_refused(fw):
    """A leg of the QGC mission (a straight chord between waypoints) that leaves the admissible
    volume makes the candidate not flyable, with the leg named."""
    pr, res = fw
    r = res["astar-fw"]
    wp = np.array([pr.start_xyz, [1500.0, 950.0, pr.start_xyz[2]], pr.goal_xyz], float)   # straight over the ridge
    bad = dataclasses.replace(r, waypoints=wp, info={**r.info})
    c = fixedwing_candidate(pr, bad)
    assert not c.flyable
    assert any("leg between plan waypoints" in m and "QGroundControl" in m for m in c.reasons), c.reasons
