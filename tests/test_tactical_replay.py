"""Tactical replay (seed 001 section 3.2) on a synthetic city: levels 1-3, contingency landing,
temporary no-fly zones.  Oracles: closed-form kinematics, brute-force separation at 0.05 s
against the intruders' truth tracks, brute-force point-in-polygon for the zones, the
independent plan validator on the stitched flown trajectory."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from skyroute.pipeline.settings import catalog_dir
from skyroute.stages.almanac import sky_geometry
from skyroute.stages.grid import Grid
from skyroute.stages.planning.deconflict import Step2Result, chain_timing
from skyroute.stages.planning.problem import build_problem
from skyroute.stages.planning.step3 import Candidate, step3
from skyroute.stages.planning.validate import validate_plan
from skyroute.stages.smoothing import KinematicLimits, corner_trajectory
from skyroute.stages.tactical.log import NoFlyZone
from skyroute.stages.tactical.replay import (
    FlyParams,
    TacticalEvent,
    World,
    encounter_geometry,
    replay,
)
from skyroute.stages.tactical.timeline import Segment, Timeline, chain_of
from skyroute.stages.traffic import Intruder
from skyroute.stages.vehicle import load_vehicle

X0, Y0 = 385000.0, 6672000.0
START = pd.Timestamp("2020-01-03T12:00:00Z")
VEH = load_vehicle("dji-m300-rtk")
LIM = KinematicLimits.of(VEH)
CHAIN = np.array([[100, 300, 40], [500, 300, 40], [900, 300, 40.0]]) + [X0, Y0, 0]
SITE = (X0 + 300, Y0 + 200)       # a landing site 100 m south of the route


def grid():
    return Grid.from_bounds("EPSG:32635", X0, Y0, X0 + 1000, Y0 + 600, 4.0)


def world(sky) -> World:
    g = grid()
    terr = np.zeros(g.shape)
    surf = terr.copy()
    surf[30:45, 150:170] = 30.0                    # a 30 m block north of the route (y 420..480)
    r_p = VEH.r_p_m
    floor = np.where(surf > 0, surf + r_p, terr + r_p)
    floor = np.maximum.reduce([np.roll(floor, (a, b), (0, 1)) for a in (-2, -1, 0, 1, 2) for b in (-2, -1, 0, 1, 2)])
    site = np.zeros(g.shape, bool)
    r, c = g.cell_of(np.array([SITE[0]]), np.array([SITE[1]]))
    site[r[0] - 3:r[0] + 4, c[0] - 3:c[0] + 4] = True
    da = lambda a, name, units="m": g.dataarray(np.asarray(a), name, units=units)  # noqa: E731
    surface = xr.Dataset({"terrain": da(terr, "terrain"), "terrain_min": da(terr, "terrain_min"),
                          "surface": da(surf, "surface")})
    for v in surface.data_vars.values():
        v.attrs["vertical_datum"] = "flat local ground"
    surface = surface.rio.write_crs(g.crs)
    clearance = xr.Dataset({"min_altitude_m": da(floor, "min_altitude_m"),
                            "nofly": da(np.zeros(g.shape, bool), "nofly", "1")})
    env = xr.Dataset({"risk_cost": da(np.full(g.shape, 0.5), "risk_cost", "1"),
                      "landing_cost": da(np.full(g.shape, 0.5), "landing_cost", "1"),
                      "landing_site": da(site, "landing_site", "1")})
    env = env.assign_coords(site_x=("site", [SITE[0]]), site_y=("site", [SITE[1]]), site_name=("site", ["field"]))
    return World(surface=surface, environment=env, clearance=clearance, wind=None, coverage=None, satellites=sky)


@pytest.fixture(scope="module")
def sky():
    g = grid()
    lon, lat = g.to_lonlat(X0 + 500, Y0 + 300)
    with pytest.warns(UserWarning, match="unhealthy"):
        return sky_geometry(catalog_dir() / "data" / "yuma_2020-01-03.txt",
                            pd.date_range(START, periods=5, freq="60s"), lat, lon)


@pytest.fixture(scope="module")
def strategic(sky):
    w = world(sky)
    prob = build_problem(w.surface, w.clearance["min_altitude_m"], None, None, None, None, VEH, (1, 0, 0, 1),
                         tuple(CHAIN[0]), tuple(CHAIN[-1]), 0.0, 80.0)
    t, e, ok = chain_timing(prob, CHAIN)
    assert ok.all()
    cand = step3(prob, Step2Result(CHAIN, t, e, "unchanged"), sky, w.surface["surface"].values, start_time_utc=START)
    assert cand.flyable, cand.reasons
    return cand


def _fly(sky, strategic: Candidate, events, **kw):
    w = world(sky)
    return replay(strategic.trajectory, float(strategic.t_s[0]), goal_xyz=CHAIN[-1], world=w, world_at=lambda t: w,
                  events=events, strategic_intruders=[], vehicle=VEH, params=FlyParams(**kw), start_time_utc=START,
                  dop_threshold=None, scenario="synthetic")


def _brute_separation(log, step_s: float = 0.05) -> float:
    """Min over intruders of (distance at equal times - r_p - r_i - d_c), sampled every 0.05 s."""
    t, p = log.flown()
    tt = np.arange(t[0], t[-1], step_s)
    own = np.column_stack([np.interp(tt, t, p[:, k]) for k in range(3)])
    worst = math.inf
    for it in log.intruders:
        live = (tt >= it.t_s[0]) & (tt <= it.t_s[-1])
        if not live.any():
            continue
        ip = np.column_stack([np.interp(tt[live], it.t_s, it.xyz_m[:, k]) for k in range(3)])
        d = np.linalg.norm(own[live] - ip, axis=1) - (log.own_radius_m + it.radius_m + log.margin_m)
        worst = min(worst, float(d.min()))
    return worst


def _stitched_candidate(log) -> Candidate:
    t, p = log.flown()
    z = np.zeros(t.size)
    return Candidate("flown", None, t, p, p[:, 2], z, z, np.zeros(t.size, int), 0, 0, 0, 0, 0, True, 0, 0, 0, 0)


def _continuous(log) -> float:
    """Largest jump [m/s] of the exact ground speed, or [m] of the position, where one flown
    part hands over to the next."""
    jumps = [0.0]
    for a, b in zip(log.parts[:-1], log.parts[1:], strict=True):
        jumps.append(abs(float(a.speed_mps[-1] - b.speed_mps[0])))
        jumps.append(float(np.linalg.norm(a.xyz_m[-1] - b.xyz_m[0])))
    return max(jumps)


# ------------------------------------------------------------------ kinematics


def test_start_speed_closed_form():
    """From 10 m/s along a 100 m line to rest at 3 m/s^2: cruise then brake,
    T = (100 - v^2 / (2 a)) / v + v / a."""
    w = np.array([[0, 0, 50], [100, 0, 50.0]])
    tr = corner_trajectory(w, [10.0], LIM, v_start_mps=10.0)
    assert tr.duration_s == pytest.approx((100 - 100 / 6) / 10 + 10 / 3, abs=1e-9)
    assert np.linalg.norm(tr.velocity([0.0])[0]) == pytest.approx(10.0)
    tr = corner_trajectory(w, [5.0], LIM, v_start_mps=11.0)   # above the target: slow down first
    t = np.linspace(0, tr.duration_s, 4001)
    assert np.linalg.norm(tr.acceleration(t), axis=1).max() <= LIM.max_acceleration_mps2 + 1e-12
    # 6 m/s into 5 m/s: brake to 5 over (36-25)/6 m, cruise, brake to 0 over 25/6 m
    tr = corner_trajectory(w, [5.0], LIM, v_start_mps=6.0)
    assert tr.duration_s == pytest.approx(1 / 3 + (100 - 11 / 6 - 25 / 6) / 5 + 5 / 3, abs=1e-9)


def test_chain_of_recovers_the_chain():
    # a climbing turn, a tight turn and a hairpin; legs 1 and 2 are all fillet (no line phase)
    w = np.array([[0, 0, 50], [200, 0, 50], [200, 150, 60], [50, 160, 60], [250, 170, 60.0]])
    tr = corner_trajectory(w, [10, 8, 12, 6], LIM)
    v, s, leg_of = chain_of(tr)
    assert v.shape == w.shape
    assert np.abs(v - w).max() < 1e-6
    assert s[0] == pytest.approx(10.0) and s[-1] == pytest.approx(6.0)   # the cruise of the line legs
    assert leg_of[0] == 0 and leg_of[-1] == 3
    # the recovered chain flies the same trajectory
    tr2 = corner_trajectory(v, s, LIM)
    t = np.linspace(0, tr.duration_s, 500)
    assert tr2.duration_s == pytest.approx(tr.duration_s, abs=1e-9)
    assert np.abs(tr.sample(t) - tr2.sample(t)).max() < 1e-6


def test_encounter_geometry():
    assert encounter_geometry([10, 0, 0], [0, 8, 0])[0] == "crossing"
    assert encounter_geometry([10, 0, 0], [-8, 0.5, 0])[0] == "frontal"
    assert encounter_geometry([10, 0, 0], [8, 1, 0])[0] == "overtaking"
    assert encounter_geometry([10, 0, 0], [0.1, 0, 0])[0] == "static"
    k, ang = encounter_geometry([10, 0, 0], [-10, 10, 0])
    assert k == "crossing" and ang == pytest.approx(135.0)        # the boundary is not frontal


def test_timeline_replaces_the_rest():
    a = corner_trajectory(np.array([[0, 0, 50], [100, 0, 50.0]]), [10.0], LIM)
    b = corner_trajectory(np.array([[50, 0, 50], [50, 100, 50.0]]), [10.0], LIM)
    tl = Timeline()
    tl.add(Segment(a, 0.0), 0.0)
    tl.add(Segment(b, 6.0, "L2", 0), 6.0)
    assert tl.active(5.9) == 0 and tl.active(6.0) == 1
    t, p = tl.samples(0.0, 0.5)
    assert np.all(np.diff(t) > 0) and t[-1] == pytest.approx(6.0 + b.duration_s)


# ------------------------------------------------------------------ replays


def _crossing(t_event=5.0):
    # crosses the route at x = 500 m, 40 m high, when the ownship gets there (~42 s after take-off)
    return Intruder("cross", np.array([20.0, 80.0]), np.array([[500, 60, 40], [500, 540, 40.0]]) + [X0, Y0, 0], 2.0)


def test_crossing_intruder_is_solved_by_time_scaling(sky, strategic):
    c = strategic.trajectory
    t_at_500 = float(np.interp(X0 + 500, strategic.xyz_m[:, 0], strategic.t_s))
    it = Intruder("cross", np.array([t_at_500 - 30, t_at_500 + 30]),
                  np.array([[500, 300 - 240, 40], [500, 300 + 240, 40.0]]) + [X0, Y0, 0], 2.0)
    log = _fly(sky, strategic, [TacticalEvent(5.0, "intruder", "intruder cross", intruder=it)])
    assert c is not None
    chosen = [a for a in log.attempts if a.chosen]
    assert [a.level for a in chosen] == ["1"], [(a.level, a.reasons) for a in log.attempts]
    assert len(log.attempts) == 3 and all(math.isfinite(a.compute_s) for a in log.attempts)
    assert chosen[0].added_flight_time_s > 0
    assert _brute_separation(log) >= 0.0
    assert _continuous(log) < 1e-3
    # level 1 keeps the geometry: every flown point is on the planned straight route
    t, p = log.flown()
    assert np.abs(p[:, 1] - (Y0 + 300)).max() < 1e-6 and np.abs(p[:, 2] - 40).max() < 1e-6
    assert log.outcome == "goal" and np.linalg.norm(p[-1] - CHAIN[-1]) < 1e-6


def test_head_on_intruder_needs_level_2_or_3(sky, strategic):
    t_at_700 = float(np.interp(X0 + 700, strategic.xyz_m[:, 0], strategic.t_s))
    # flies west along the route at 8 m/s, meeting the ownship near x = 700 m
    it = Intruder("head-on", np.array([t_at_700 - 30, t_at_700 + 30]),
                  np.array([[700 + 240, 300, 40], [700 - 240, 300, 40.0]]) + [X0, Y0, 0], 2.0)
    log = _fly(sky, strategic, [TacticalEvent(10.0, "intruder", "intruder head-on", intruder=it)])
    rows = {a.level: a for a in log.attempts}
    assert "frontal" in rows["1"].reasons and not rows["1"].flyable
    chosen = [a.level for a in log.attempts if a.chosen]
    assert chosen in (["2"], ["3"]), [(a.level, a.reasons) for a in log.attempts]
    assert _brute_separation(log) >= 0.0
    assert _continuous(log) < 1e-3
    viol = validate_plan(_stitched_candidate(log), grid=grid(), terrain_m=np.zeros(grid().shape), vehicle=VEH,
                         floor_m=world(sky).clearance["min_altitude_m"].values, ceiling_m=np.full(grid().shape, 80.0),
                         wind=np.zeros(3))
    assert viol == []
    # same seed, same flight
    log2 = _fly(sky, strategic, [TacticalEvent(10.0, "intruder", "intruder head-on", intruder=it)])
    assert np.array_equal(log.flown()[1], log2.flown()[1])


def test_short_time_to_collision_lands(sky, strategic):
    t_at_400 = float(np.interp(X0 + 400, strategic.xyz_m[:, 0], strategic.t_s))
    it = Intruder("late", np.array([t_at_400 - 10, t_at_400 + 10]),
                  np.array([[400, 300 - 80, 40], [400, 300 + 80, 40.0]]) + [X0, Y0, 0], 2.0)
    t_e = t_at_400 - 3.0                           # known 3 s before the collision: t_coll <= t_rep = 5 s
    log = _fly(sky, strategic, [TacticalEvent(t_e, "intruder", "intruder late", intruder=it)])
    rows = [a for a in log.attempts]
    assert [a.level for a in rows] == ["landing"] and rows[0].chosen and rows[0].flyable
    assert rows[0].t_coll_s <= 5.0 and "t_rep" in rows[0].reasons
    assert log.outcome == "landed" and log.parts[-1].part == "landing"
    end = log.parts[-1].xyz_m[-1]
    g = grid()
    r, c = g.cell_of(np.array([end[0]]), np.array([end[1]]))
    assert world(sky).environment["landing_site"].values[r[0], c[0]]
    assert end[2] == pytest.approx(VEH.r_p_m, abs=1e-6)          # approach point r_p above the site
    floor = world(sky).clearance["min_altitude_m"].values
    _t, p = log.parts[-1].t_s, log.parts[-1].xyz_m
    rr, cc = g.cell_of(p[:, 0], p[:, 1])
    assert np.all(p[:, 2] >= floor[rr, cc] - 1e-6)              # clearance all the way down to the approach point
    assert _brute_separation(log) >= 0.0


def test_temporary_no_fly_zone_is_avoided_while_active(sky, strategic):
    poly = np.array([[600, 260], [660, 260], [660, 340], [600, 340.0]]) + [X0, Y0]
    t_in = float(np.interp(X0 + 600, strategic.xyz_m[:, 0], strategic.t_s))
    zone = NoFlyZone("police", poly, -1.0, 200.0, 0.0, t_in + 600.0)   # too long to wait out (level 1)
    log = _fly(sky, strategic, [TacticalEvent(8.0, "nofly", "nofly police", zone=zone)])
    assert any(a.chosen and a.level in ("2", "3") for a in log.attempts), [(a.level, a.reasons) for a in log.attempts]
    t, p = log.flown()
    from shapely.geometry import Point, Polygon

    widened = Polygon(poly).buffer(VEH.r_p_m)
    tt = np.arange(t[0], t[-1], 0.05)
    q = np.column_stack([np.interp(tt, t, p[:, k]) for k in range(2)])
    active = (tt >= zone.start_s) & (tt <= zone.end_s)
    assert not any(widened.contains(Point(*xy)) for xy in q[active])
    assert log.outcome == "goal"


def test_report_latency_noise_and_track_updates(sky, strategic):
    """An intruder report arrives ``report_latency_s`` after its event; reported positions carry
    seeded noise (the truth does not); after an ``intruder_update`` the truth is the new track
    from the update time on."""
    from skyroute.stages.tactical.replay import _truth_update

    t_at_500 = float(np.interp(X0 + 500, strategic.xyz_m[:, 0], strategic.t_s))
    far = Intruder("far", np.array([0.0, 200.0]), np.array([[500, 560, 40], [520, 560, 40.0]]) + [X0, Y0, 0], 2.0)
    log = _fly(sky, strategic, [TacticalEvent(5.0, "intruder", "intruder far", intruder=far)],
               report_latency_s=2.5, intruder_noise_m=3.0)
    assert log.events[0]["t_known_s"] == pytest.approx(7.5) and log.events[0]["outcome"] == "no conflict"
    truth = log.intruders[0]
    assert np.array_equal(truth.xyz_m, far.xyz_m) and truth.known_from_s == pytest.approx(7.5)
    # the update: old track until t = 50 s, then the new one (with the position jump it declares)
    new = Intruder("far", np.array([40.0, 120.0]), np.array([[0, 0, 30], [80, 0, 30.0]]), 2.0)
    tr = _truth_update(truth, new, 50.0)
    assert np.all(np.diff(tr.t_s) > 0)
    k_old = tr.t_s < 50.0 - 1e-3 + 1e-9
    assert np.allclose(tr.xyz_m[k_old][:, :2], np.column_stack([np.interp(tr.t_s[k_old], far.times_s, far.xyz_m[:, 0]),
                                                                 np.interp(tr.t_s[k_old], far.times_s, far.xyz_m[:, 1])]))
    k_new = tr.t_s >= 50.0
    assert np.allclose(tr.xyz_m[k_new, 0], np.interp(tr.t_s[k_new], new.times_s, new.xyz_m[:, 0]))
    assert tr.t_s[-1] == 120.0 and len(tr.declared) == 2
    # a crossing reported with noise is still resolved, and the same seed gives the same flight
    it = Intruder("cross", np.array([t_at_500 - 30, t_at_500 + 30]),
                  np.array([[500, 60, 40], [500, 540, 40.0]]) + [X0, Y0, 0], 2.0)
    ev = [TacticalEvent(5.0, "intruder", "intruder cross", intruder=it)]
    a = _fly(sky, strategic, ev, intruder_noise_m=1.0, seed=3)
    b = _fly(sky, strategic, ev, intruder_noise_m=1.0, seed=3)
    assert np.array_equal(a.flown()[1], b.flown()[1])
    assert _brute_separation(a) >= -2.0 * 3 * 1.0   # the truth is within 3 sigma of the reports at most


# ------------------------------------------------------------------ octant method (seed 004)


def test_head_on_intruder_with_the_octant_method(sky, strategic):
    """``method="octant"``: the head-on conflict is resolved by the octant manoeuvre (forward
    hemisphere preferred), flown as part ``octant``, continuous, valid for the independent
    validator and separated (brute force 0.05 s); a pair of known intruders flying together far
    from the route makes a dense zone, which the flight never enters while it is active."""
    t_at_700 = float(np.interp(X0 + 700, strategic.xyz_m[:, 0], strategic.t_s))
    it = Intruder("head-on", np.array([t_at_700 - 30, t_at_700 + 30]),
                  np.array([[700 + 240, 300, 40], [700 - 240, 300, 40.0]]) + [X0, Y0, 0], 2.0)
    pair = [Intruder(f"pair-{k}", np.array([0.0, 200.0]), np.array([[850 + 10 * k, 560, 40], [850 + 10 * k, 540, 40.0]])
                     + [X0, Y0, 0], 2.0) for k in range(2)]
    events = [TacticalEvent(1.0, "intruder", f"intruder {p.id}", intruder=p) for p in pair]
    events.append(TacticalEvent(10.0, "intruder", "intruder head-on", intruder=it))
    log = _fly(sky, strategic, events, method="octant")
    assert log.method == "octant"
    chosen = [a for a in log.attempts if a.chosen]
    assert [a.level for a in chosen] == ["octant"], [(a.level, a.reasons) for a in log.attempts]
    assert "escape octant" in chosen[0].reasons or "escape pocket" in chosen[0].reasons
    assert "octant" in [p.part for p in log.parts]
    assert _brute_separation(log) >= 0.0
    assert _continuous(log) < 1e-3
    viol = validate_plan(_stitched_candidate(log), grid=grid(), terrain_m=np.zeros(grid().shape), vehicle=VEH,
                         floor_m=world(sky).clearance["min_altitude_m"].values, ceiling_m=np.full(grid().shape, 80.0),
                         wind=np.zeros(3))
    assert viol == []
    # the pair: predicted 10 s ahead both in one zone far from the route -> a dense zone
    assert log.dense_zones and any(z["dense"] for z in log.dense_zones)
    t, p = log.flown()
    for z in log.dense_zones:
        for x0, x1, y0, y1 in z["boxes_m"]:
            assert x0 <= X0 + 855 <= x1 and y0 <= Y0 + 555 <= y1          # the pair's box
            act = (t >= z["t_s"]) & (t <= z["t_s"] + 10.0)
            r = VEH.r_p_m
            inside = (p[act, 0] > x0 - r) & (p[act, 0] < x1 + r) & (p[act, 1] > y0 - r) & (p[act, 1] < y1 + r)
            assert not inside.any()


# ------------------------------------------------------------------ dense zones -> potential field (seed 004)

ZONE_BOX = (X0 + 250.0, X0 + 500.0, Y0 + 300.0, Y0 + 600.0)   # r = 3: x quarter 2 of 4, y upper half


def _hovering_pair(t_end: float = 400.0):
    """Two known intruders hovering 35 m above the route level at (375..385, 450..460): both in
    the zone x [250, 500] x y [300, 600] of r = 3 (r = 1, 2 put them in the vehicle's zone)."""
    return [Intruder(f"pair-{k}", np.array([0.0, t_end]), np.array([[375 + 10 * k, 450 + 10 * k, 75]] * 2, float)
                     + [X0, Y0, 0], 2.0) for k in range(2)]


def _box_distance(p, box):
    x0, x1, y0, y1 = box
    dx = np.maximum.reduce([x0 - p[:, 0], p[:, 0] - x1, np.zeros(len(p))])
    dy = np.maximum.reduce([y0 - p[:, 1], p[:, 1] - y1, np.zeros(len(p))])
    return np.hypot(dx, dy)


def _dense_samples(chain, step_m: float = 0.25):
    return np.concatenate([a + np.linspace(0, 1, max(2, int(np.linalg.norm(b - a) / step_m) + 1))[:, None] * (b - a)
                           for a, b in zip(chain[:-1], chain[1:], strict=True)])


def test_zone_field_incremental_equals_full():
    """The dense zone as obstacles of the potential field: updating the zone-free field by
    :meth:`ZoneField.set_zones` gives the clearance, skeleton and potential of a full field
    computed with the zone (brute-force EDT of the new bitmap, fresh wave), the new obstacle
    voxels are exactly those whose footprint meets the box widened by r_p, and the descent
    path keeps r_p from the box (exact point-box distance of its segments, sampled 0.25 m);
    removing the zone again gives back the zone-free field."""
    from skyroute.stages.planning import potential as P
    from skyroute.stages.tactical.zone_field import ZoneField, zone_cells
    from skyroute.stages.tactical.zones import ZoneBox

    w = world(None)
    start = CHAIN[0] + [100.0, 0.0, 0.0]
    prob = build_problem(w.surface, w.clearance["min_altitude_m"], None, None, None, None, VEH, (1, 0, 0, 1),
                         tuple(start), tuple(CHAIN[-1]), 0.0, 120.0)
    box = ZoneBox("010", *ZONE_BOX)
    zf = ZoneField.build(prob)
    pf0 = zf.field
    before = zf.path_from(prob, start)
    assert _box_distance(_dense_samples(before), ZONE_BOX).min() < VEH.r_p_m         # the route runs along the box edge
    assert zf.set_zones([box]) and not zf.set_zones([box])            # recomputed once; not when unchanged
    assert (zf.full_computations, zf.incremental_updates) == (1, 1)
    full = ZoneField.build(prob, [box])
    vm = full.field.vmap
    # the bitmap: voxel footprints meeting the widened box (brute force over the footprints)
    h, r = vm.voxel_m, VEH.r_p_m
    xs0 = vm.x0_m + np.arange(vm.shape[2]) * h
    ys1 = vm.y1_m - np.arange(vm.shape[1]) * h
    meets = ((xs0[None] <= ZONE_BOX[1] + r) & (xs0[None] + h >= ZONE_BOX[0] - r)
             & (ys1[:, None] - h <= ZONE_BOX[3] + r) & (ys1[:, None] >= ZONE_BOX[2] - r))
    assert np.array_equal(~vm.free & zf.base.free, np.broadcast_to(meets[None], vm.shape) & zf.base.free)
    assert zone_cells([box], prob.grid, r).sum() > 0
    up = zf.field
    np.testing.assert_allclose(up.clearance_m, P.clearance_map(vm), atol=1e-5)
    np.testing.assert_allclose(full.field.clearance_m, up.clearance_m, atol=1e-5)
    assert np.array_equal(up.skeleton, full.field.skeleton)
    fin = np.isfinite(full.field.potential_m)
    assert np.array_equal(fin, np.isfinite(up.potential_m))
    np.testing.assert_allclose(up.potential_m[fin], full.field.potential_m[fin], rtol=1e-12, atol=1e-9)
    assert up.timings_s["affected_voxels"] < vm.free.sum()
    after = zf.path_from(prob, start)
    assert _box_distance(_dense_samples(after), ZONE_BOX).min() >= r - 1e-9
    assert np.allclose(after[-1], CHAIN[-1]) and prob.motion_valid(after[:-1], after[1:]).all()
    # the zone goes away: the update gives back the zone-free full field
    assert zf.set_zones([]) and zf.incremental_updates == 2
    np.testing.assert_allclose(zf.field.clearance_m, pf0.clearance_m, atol=1e-5)
    assert np.array_equal(zf.field.skeleton, pf0.skeleton)
    fin = np.isfinite(pf0.potential_m)
    assert np.array_equal(fin, np.isfinite(zf.field.potential_m))
    np.testing.assert_allclose(zf.field.potential_m[fin], pf0.potential_m[fin], rtol=1e-12, atol=1e-9)


def test_dense_zone_across_the_path_reroutes_along_the_potential(sky, strategic):
    """Octant method: a hovering pair of known intruders makes the zone x [250, 500] x y [300, 600]
    dense (r = 3); the plan along y = 300 is within r_p of it, so the zones become obstacles
    of the potential field and the vehicle follows its gradient motion (part ``potential``):
    the flight keeps r_p from the box while the zone is active (exact point-box distance every
    0.05 s), stays separated (brute force) and valid for the independent validator.  The
    potential is computed once per zone change after the first that meets the plan (full),
    then incrementally (the pair's update that empties the zone), never when unchanged."""
    pair = _hovering_pair()
    assert float(np.interp(X0 + 500, strategic.xyz_m[:, 0], strategic.t_s)) < 50.0     # past the zone by T_p
    events = [TacticalEvent(1.0, "intruder", f"intruder {p.id}", intruder=p) for p in pair]
    # the same pair re-reported: the definition does not change -> no computation
    events.append(TacticalEvent(8.0, "intruder_update", "intruder pair-0 again", intruder=pair[0]))
    # pair-1 leaves far south-east at t = 52 s (after the period T_p = 50 s): the zone empties ->
    # one incremental update
    gone = Intruder("pair-1", np.array([0.0, 52.0, 53.0, 400.0]),
                    np.array([[385, 460, 75], [385, 460, 75], [990, 10, 75], [990, 10, 75]], float) + [X0, Y0, 0], 2.0)
    events.append(TacticalEvent(52.0, "intruder_update", "intruder pair-1 leaves", intruder=gone))
    log = _fly(sky, strategic, events, method="octant", zone_period_s=50.0)
    chosen = [a for a in log.attempts if a.chosen]
    assert [a.level for a in chosen] == ["potential"], [(a.level, a.reasons) for a in log.attempts]
    assert "potential" in [p.part for p in log.parts]
    zl = log.dense_zones
    assert [z["dense"] != [] for z in zl] == [False, True, False], (zl, log.flown()[0][-1])
    assert [z["potential"] for z in zl] == ["", "full", "incremental"], zl
    assert zl[1]["reroute"].startswith("new path") and zl[1]["boxes_m"] == [list(ZONE_BOX)]
    t, p = log.flown()
    tt = np.arange(t[0], t[-1], 0.05)
    own = np.column_stack([np.interp(tt, t, p[:, k]) for k in range(3)])
    act = (tt >= zl[1]["t_s"]) & (tt <= zl[1]["t_s"] + 50.0)
    assert _box_distance(own[act], ZONE_BOX).min() >= VEH.r_p_m - 1e-6
    assert _brute_separation(log) >= 0.0
    assert _continuous(log) < 1e-3
    assert np.linalg.norm(p[-1] - CHAIN[-1]) < 1.0
    viol = validate_plan(_stitched_candidate(log), grid=grid(), terrain_m=np.zeros(grid().shape), vehicle=VEH,
                         floor_m=world(sky).clearance["min_altitude_m"].values, ceiling_m=np.full(grid().shape, 120.0),
                         wind=np.zeros(3))
    assert viol == []
