"""Seed 002's local planner (stages/tactical/fw_local.py): climb over unknown obstacles, turn
right for other UAVs, a 3-UAV fleet over the San Gabriel DEM.  Every check is a brute force
written here (separations every 0.05 s, prism distances with shapely, finite-difference climb
angles and turn banks with tolerance 0)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from shapely.geometry import Point, Polygon

from skyroute.stages.atmosphere import isa_density_kgpm3
from skyroute.stages.base import InputError
from skyroute.stages.tactical.fw_local import (
    LocalAgent,
    LocalPlannerParams,
    StaticObstacle,
    cylinder_polygon,
    simulate_local,
)
from skyroute.stages.vehicle import G0, load_vehicle

X8 = load_vehicle("skywalker-x8")
STEP_S = 0.05


def _line(a, b, z=300.0, t0=0.0):
    """Planned samples every ~15 m along a straight level line, timed at the X8's airspeed."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = int(np.linalg.norm(b - a) / 15) + 1
    f = np.linspace(0, 1, n + 1)[:, None]
    p = np.column_stack([a + (b - a) * f, np.full(n + 1, z)])
    v = X8.airspeed_at(float(isa_density_kgpm3(z)))
    return t0 + np.r_[0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))] / v, p


def _resample(t, x, step=STEP_S, t_lo=None, t_hi=None):
    tq = np.arange(t[0] if t_lo is None else t_lo, (t[-1] if t_hi is None else t_hi) + 1e-12, step)
    return tq, np.column_stack([np.interp(tq, t, x[:, k]) for k in range(3)])


def _min_pair_distance(ta, xa, tb, xb):
    lo, hi = max(ta[0], tb[0]), min(ta[-1], tb[-1])
    if hi < lo:
        return math.inf
    _, pa = _resample(ta, xa, t_lo=lo, t_hi=hi)
    _, pb = _resample(tb, xb, t_lo=lo, t_hi=hi)
    return float(np.linalg.norm(pa - pb, axis=1).min())


def _check_limits(t, x, veh=X8):
    """Finite differences on the flown samples, tolerance 0: climb / descent angle of each chord
    (dz over the horizontal chord) and the bank each triple needs (horizontal circumradius,
    mean chord speed)."""
    d = np.diff(x, axis=0)
    h = np.hypot(d[:, 0], d[:, 1])
    ang = np.degrees(np.arctan2(d[:, 2], h))
    assert ang.max() <= veh.max_climb_angle_deg
    assert -ang.min() <= veh.max_descent_angle_deg
    a, b, c = x[:-2, :2], x[1:-1, :2], x[2:, :2]
    ab, bc, ca = (np.linalg.norm(q, axis=1) for q in (b - a, c - b, a - c))
    cross = np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
    with np.errstate(divide="ignore"):
        rho = np.where(cross > 0, ab * bc * ca / (2 * cross), np.inf)
    v = (ab + bc) / (t[2:] - t[:-2])
    bank = np.degrees(np.arctan(v * v / (G0 * rho)))
    assert bank.max() <= veh.max_bank_deg, bank.max()
    return ang, bank


def _prism_distance(poly: Polygon, z_top: float, p) -> float:
    dxy = poly.distance(Point(p[0], p[1]))
    return math.hypot(dxy, max(p[2] - z_top, 0.0))


def test_climb_over_an_unknown_obstacle_keeps_r_p():
    t, p = _line((0, 0), (2400, 0))
    ring = cylinder_polygon((1200, 10), 15)
    mast = StaticObstacle("mast", ring, 350.0)
    poly = Polygon(ring)
    # the plan itself goes through the mast
    assert min(_prism_distance(poly, 350.0, q) for q in p) == 0.0
    r = simulate_local([LocalAgent("own", t, p)], obstacles=[mast])
    (m,) = r.manoeuvres
    assert m["kind"] == "climb" and m["feasible"] and m["threat"] == "mast"
    assert m["distance_m"] <= r.params.obstacle_range_m
    tq, q = _resample(r.t_s[0], r.xyz_m[0])
    clear = min(_prism_distance(poly, 350.0, qq) for qq in q)
    assert clear >= X8.r_p_m
    assert r.xyz_m[0][:, 2].max() >= 350.0 + X8.r_p_m
    ang, _ = _check_limits(r.t_s[0], r.xyz_m[0])
    assert ang.max() > 0.95 * X8.max_climb_angle_deg        # it climbed at the limit
    # rejoined the plan: back at 300 m, on the line, at the goal
    assert math.isfinite(r.arrived_s[0])
    assert r.xyz_m[0][-1, 2] == pytest.approx(300.0, abs=0.5)
    assert np.hypot(*(r.xyz_m[0][-1, :2] - p[-1, :2])) <= r.params.goal_tol_m + 5
    assert r.added_energy_J[0] > 0 and r.delay_s[0] >= 0


def test_obstacle_sensed_too_late_is_named():
    t, p = _line((0, 0), (1200, 0))
    mast = StaticObstacle("tall", cylinder_polygon((600, 0), 10), 500.0)
    r = simulate_local([LocalAgent("own", t, p)], obstacles=[mast], params=LocalPlannerParams(obstacle_range_m=300),
                       baseline=False)
    assert not r.manoeuvres[0]["feasible"]
    assert any("tall" in w and "raise obstacle_range_m" in w for w in r.warnings)


def test_obstacle_beside_the_route_is_ignored():
    t, p = _line((0, 0), (1200, 0))
    mast = StaticObstacle("far", cylinder_polygon((600, 300), 10), 500.0)
    r = simulate_local([LocalAgent("own", t, p)], obstacles=[mast], baseline=False)
    assert r.manoeuvres == []
    assert np.ptp(r.xyz_m[0][:, 2]) < 1e-9


def _pair(b_from, b_to, baseline=False, **kw):
    ta, pa = _line((0, 0), (2400, 0))
    tb, pb = _line(b_from, b_to)
    return simulate_local([LocalAgent("a", ta, pa), LocalAgent("b", tb, pb)], params=LocalPlannerParams(**kw),
                          baseline=baseline)


def test_head_on_pair_both_turn_right():
    r = _pair((2400, 0), (0, 0))
    S = 2 * X8.r_p_m + r.params.d_c_m
    kinds = {(m["agent"], m["kind"], m["threat"]) for m in r.manoeuvres}
    assert kinds == {("a", "right", "b"), ("b", "right", "a")}
    assert _min_pair_distance(r.t_s[0], r.xyz_m[0], r.t_s[1], r.xyz_m[1]) >= S
    # a flies east: its right is south; b flies west: its right is north
    assert r.xyz_m[0][:, 1].min() < -S and r.xyz_m[0][:, 1].max() < 1.0
    assert r.xyz_m[1][:, 1].max() > S and r.xyz_m[1][:, 1].min() > -1.0
    for i in (0, 1):
        _check_limits(r.t_s[i], r.xyz_m[i])
    # without sensing they would collide (the plans meet head-on at the same time)
    blind = _pair((2400, 0), (0, 0), uav_range_m=1e-6)
    assert blind.manoeuvres == []
    assert _min_pair_distance(blind.t_s[0], blind.xyz_m[0], blind.t_s[1], blind.xyz_m[1]) < S


def test_crossing_pair_both_turn_right_and_keep_separation():
    r = _pair((1200, -1200), (1200, 1200))
    S = 2 * X8.r_p_m + r.params.d_c_m
    assert {(m["agent"], m["kind"]) for m in r.manoeuvres} == {("a", "right"), ("b", "right")}
    assert _min_pair_distance(r.t_s[0], r.xyz_m[0], r.t_s[1], r.xyz_m[1]) >= S
    # the first heading change of each is clockwise (a right turn)
    for i in (0, 1):
        h = np.unwrap(r.heading_rad[i])
        k = int(np.argmax(np.abs(h - h[0]) > 1e-6))
        assert h[k] < h[0]
        _check_limits(r.t_s[i], r.xyz_m[i])
    blind = _pair((1200, -1200), (1200, 1200), uav_range_m=1e-6)
    assert _min_pair_distance(blind.t_s[0], blind.xyz_m[0], blind.t_s[1], blind.xyz_m[1]) < S


def test_determinism():
    a, b = _pair((2400, 0), (0, 0), uav_range_m=300), _pair((2400, 0), (0, 0), uav_range_m=300)
    assert a.manoeuvres
    for i in (0, 1):
        assert np.array_equal(a.t_s[i], b.t_s[i]) and np.array_equal(a.xyz_m[i], b.xyz_m[i])
    assert a.manoeuvres == b.manoeuvres


def test_rotorcraft_and_empty_inputs_are_refused():
    t, p = _line((0, 0), (1000, 0))
    with pytest.raises(InputError, match="fixed-wing"):
        simulate_local([LocalAgent("m", t, p, "dji-m300-rtk")])
    with pytest.raises(InputError, match="at least one agent"):
        simulate_local([])
    with pytest.raises(InputError, match="uav_range_m"):
        LocalPlannerParams(uav_range_m=0)


def test_three_x8_crossing_over_san_gabriel(tmp_path):
    """Seed 002 section 4.4: three Skywalker X8 on routes crossing at one point of the San
    Gabriel DEM (shipped SRTM), each with its EEA* plan, timed to meet there: zero losses of
    separation by brute force every 0.05 s, while the plans themselves would lose it."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.fly_fw import crossing_routes, fleet_problems
    from skyroute.pipeline.settings import load_scenario
    from skyroute.stages.tactical.fw_local import fly_fixedwing_fleet

    centre = (380500.0, 3792300.0)
    prs = fleet_problems(load_scenario("san-gabriel-fixedwing"), crossing_routes(centre, 1200, (0, 60, 120)),
                         cache=Cache(tmp_path), alt_m=700.0)
    sim, cands = fly_fixedwing_fleet(prs, corridor_m=400, meet_at_xy=centre)
    S = 2 * X8.r_p_m + sim.params.d_c_m
    planned = [(np.asarray(a, float), np.asarray(c.xyz_m, float)) for a, c in
               zip([sim.t_s[i][0] - cands[i].t_s[0] + cands[i].t_s for i in range(3)], cands, strict=True)]
    assert min(_min_pair_distance(*planned[i], *planned[j]) for i, j in itertools.combinations(range(3), 2)) < S
    for i, j in itertools.combinations(range(3), 2):
        assert _min_pair_distance(sim.t_s[i], sim.xyz_m[i], sim.t_s[j], sim.xyz_m[j]) >= S
    assert np.all(np.isfinite(sim.arrived_s))
    assert {m["kind"] for m in sim.manoeuvres} == {"right"}
    for i in range(3):
        _check_limits(sim.t_s[i], sim.xyz_m[i])
    assert np.all(np.isfinite(sim.delay_s)) and np.all(np.isfinite(sim.added_energy_J))
    assert np.all(sim.added_energy_J > 0)


def test_fly_cli_refusals(tmp_path):
    """`skyroute fly`: a rotorcraft cannot fly `--tactical local`, a fixed-wing cannot fly
    levels; map events are refused by the local planner (all before any planning)."""
    from click.testing import CliRunner

    from skyroute.pipeline.cli import main

    def fly(*args):
        return CliRunner().invoke(main, ["fly", *args, "--out", str(tmp_path / "out"), "--cache-dir",
                                         str(tmp_path / "cache"), "-q"])

    r = fly("helsinki-tactical", "--tactical", "local")
    assert r.exit_code == 2 and "rotorcraft: use --tactical levels" in r.output
    r = fly("san-gabriel-fixedwing-local", "--tactical", "levels")
    assert r.exit_code == 2 and "use --tactical local" in r.output
    ev = tmp_path / "ev.yaml"
    ev.write_text("events:\n  - {kind: wind, t_s: 10, uniform_wind: {speed_mps: 8, direction_deg: 0}}\n")
    r = fly("san-gabriel-fixedwing-local", "--events", str(ev))
    assert r.exit_code == 2 and "reacts to intruder, intruder_update, obstacle events" in r.output


@pytest.mark.parametrize("wind", [(5.0, 0.0), (-3.0, 4.0)])
def test_climb_over_in_wind_keeps_r_p_and_the_limits_over_the_ground(wind):
    """In a wind the vertical rate is bounded with the ground speed too: the flight-path angle
    over the ground and the bank the ground track needs stay within the limits (tolerance 0),
    and the climb over the obstacle still keeps r_p (feasible at detection)."""
    t, p = _line((0, 0), (1800, 0))
    ring = cylinder_polygon((900, 0), 10)
    mast = StaticObstacle("mast", ring, 340.0)

    def wind_at(xyz):
        return np.tile([wind[0], wind[1], 0.0], (np.atleast_2d(xyz).shape[0], 1))

    r = simulate_local([LocalAgent("own", t, p)], obstacles=[mast], wind_at=wind_at, baseline=False)
    assert r.manoeuvres[0]["feasible"]
    _, q = _resample(r.t_s[0], r.xyz_m[0])
    assert min(_prism_distance(Polygon(ring), 340.0, qq) for qq in q) >= X8.r_p_m
    _check_limits(r.t_s[0], r.xyz_m[0])
    assert math.isfinite(r.arrived_s[0])


@pytest.mark.parametrize(("start", "velocity"), [((1200, 1200), (0, -18)), ((1200, -1200), (0, 18)),
                                                  ((2400, 0), (-18, 0))])
def test_non_cooperative_intruder(start, velocity):
    """An intruder keeps its track (it does not apply the rules of the air): from the left, the
    right or head-on the aircraft flies the escape (seed 002's right turn, a left turn, the climb,
    a loiter, a descent) with the largest predicted minimum distance (issue 22), which is what it
    then flies: the separation r_p + r_i + d_c is kept (brute force, and at least the predicted
    distance less a tick of flight), while flying blind would lose it."""
    from skyroute.stages.tactical.fw_local import LocalTrack

    t, p = _line((0, 0), (2400, 0))
    t_meet = float(np.interp(1200, p[:, 0], t))
    v = np.array([*velocity, 0.0])
    p0 = np.array([1200.0, 0.0, 300.0]) - v * t_meet
    tr = LocalTrack("intruder", np.array([0.0, 300.0]), np.vstack([p0, p0 + 300 * v]), 1.5)
    S = X8.r_p_m + 1.5 + LocalPlannerParams().d_c_m
    r = simulate_local([LocalAgent("own", t, p)], intruders=[tr], baseline=False)
    (m,) = r.manoeuvres
    assert m["kind"] == max(m["options"], key=lambda k: m["options"][k]) and m["keeps_separation"]
    assert _min_pair_distance(r.t_s[0], r.xyz_m[0], tr.t_s, tr.xyz_m) >= S
    win = (r.t_s[0] >= m["t_start_s"]) & (r.t_s[0] <= min(m["t_end_s"], m["t_start_s"] + 40.0))
    during = _min_pair_distance(r.t_s[0][win], r.xyz_m[0][win], tr.t_s, tr.xyz_m)
    assert during >= m["predicted_min_m"] - 18.0 * 0.1 - 1e-6     # flown as predicted (to a tick of travel)
    _check_limits(r.t_s[0], r.xyz_m[0])
    blind = simulate_local([LocalAgent("own", t, p)], intruders=[tr], baseline=False,
                           params=LocalPlannerParams(uav_range_m=1e-6))
    assert _min_pair_distance(blind.t_s[0], blind.xyz_m[0], tr.t_s, tr.xyz_m) < S
