"""Fixed-wing aircraft (seed 002, issue 13): profiles, ISA density, the seed-002 segment energy
with the wind triangle, and the lattice planners eeastar / astar-fw / energy-optimal.

Oracles: hand-computed closed forms from the raw catalog numbers (not the profile's properties),
the ISA standard-atmosphere table, a numerical minimum of the drag polar, and a brute-force
Dijkstra (scipy) over the same lattice graph whose edge costs come from the public energy
function, not from the planner's kernel."""

from __future__ import annotations

import math

import numpy as np
import pytest
import xarray as xr
from click.testing import CliRunner
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from skyroute.pipeline.cli import main
from skyroute.pipeline.errors import InputError, ScenarioError
from skyroute.stages.atmosphere import isa_density_kgpm3
from skyroute.stages.fixedwing_energy import segment_energy_fw
from skyroute.stages.grid import Grid
from skyroute.stages.planning.fixedwing import (
    fixedwing_candidate,
    make_fw_lattice,
    path_energy,
    plan_fixedwing,
)
from skyroute.stages.planning.kinds import check_planner_vehicle
from skyroute.stages.planning.problem import build_problem
from skyroute.stages.planning.step1 import PLANNERS
from skyroute.stages.planning.validate import turn_radius_violations
from skyroute.stages.vehicle import FixedWingProfile, VehicleProfile, load_vehicle

G = 9.80665
X8 = dict(m=3.364, S=0.75, b=2.1, cd0=0.0197, e=0.9, clmax=1.0)   # the catalog numbers (Gryte 2018 + assumed)


def _polar(rho, v, p=X8):
    """D/L = A V^2 + B / V^2 from the raw numbers (seed 002 eq. 4-6)."""
    w = p["m"] * G
    a = rho * p["cd0"] * p["S"] / (2 * w)
    b = 2 * w / (rho * p["b"] ** 2 * math.pi * p["e"])
    return a * v * v + b / (v * v), a, b


# ------------------------------------------------------------------ profiles


def test_profiles_load_by_kind_with_derived_quantities():
    x8 = load_vehicle("skywalker-x8")
    ae = load_vehicle("aerosonde")
    assert isinstance(x8, FixedWingProfile) and isinstance(ae, FixedWingProfile)
    assert isinstance(load_vehicle("dji-m300-rtk"), VehicleProfile)
    _, a, b = _polar(1.225, 1.0)
    assert x8.A == pytest.approx(a, rel=1e-12) and x8.B == pytest.approx(b, rel=1e-12)
    assert x8.carson_speed_mps == pytest.approx((b / a) ** 0.25, rel=1e-12)
    v = np.linspace(5, 30, 200001)                          # the polar's minimum, numerically
    dl = _polar(1.0, v)[0]
    assert x8.min_drag_to_lift == pytest.approx(dl.min(), rel=1e-8)
    assert v[np.argmin(dl)] == pytest.approx(x8.carson_speed_at(1.0), abs=2e-4)
    assert x8.stall_speed_mps == pytest.approx(math.sqrt(2 * 3.364 * G / (1.225 * 0.75 * 1.0)), rel=1e-12)
    assert x8.turn_radius_at(12.0) == pytest.approx(144 / (G * math.tan(math.radians(30))), rel=1e-12)
    assert x8.battery_energy_j == pytest.approx(10.0 * 14.8 * 3600)
    # Aerosonde (Beard & McLain 2012): f = 0.03 * 0.55, W = 13.5 g
    assert ae.min_drag_to_lift == pytest.approx(2 * math.sqrt(0.03 * 0.55 / (2.8956**2 * math.pi * 0.9)), rel=1e-12)


def test_vehicle_kind_default_and_errors(tmp_path):
    raw = (load_vehicle("dji-m300-rtk").model_dump(mode="json"))
    raw.pop("kind")
    import yaml

    p = tmp_path / "rotor.yaml"
    p.write_text(yaml.safe_dump(raw))
    assert isinstance(load_vehicle(p), VehicleProfile)       # no kind: multirotor
    p.write_text(yaml.safe_dump({**raw, "kind": "glider"}))
    with pytest.raises(ScenarioError, match="unknown vehicle kind 'glider'"):
        load_vehicle(p)
    fw = load_vehicle("skywalker-x8").model_dump(mode="json")
    fw.pop("wing_span_m")
    p.write_text(yaml.safe_dump(fw))
    with pytest.raises(ScenarioError, match="wing_span_m"):
        load_vehicle(p)


def test_planner_must_fit_the_vehicle_kind(tmp_path):
    with pytest.raises(InputError, match="use one of eeastar, astar-fw, energy-optimal"):
        check_planner_vehicle("astar", "skywalker-x8", PLANNERS)
    with pytest.raises(InputError, match="fixed-wing aircraft; vehicle 'dji-m300-rtk'.*use one of astar, bitstar"):
        check_planner_vehicle("eeastar", "dji-m300-rtk", PLANNERS)
    r = CliRunner().invoke(main, ["plan", "san-gabriel-mountains", "--planner", "eeastar", "--cache-dir", str(tmp_path)])
    assert r.exit_code == 2 and r.output.count("error:") == 1 and "use one of" in r.output
    r = CliRunner().invoke(main, ["plan", "san-gabriel-fixedwing", "--planner", "astar", "--cache-dir", str(tmp_path)])
    assert r.exit_code == 2 and "eeastar, astar-fw, energy-optimal" in r.output


# ------------------------------------------------------------------ atmosphere and energy


def test_isa_density_against_the_standard_table():
    # U.S. Standard Atmosphere 1976 / ISA: density [kg/m^3]
    table = {0: 1.2250, 1000: 1.1117, 2000: 1.0066, 3000: 0.9093, 5000: 0.7364}
    for h, rho in table.items():
        assert isa_density_kgpm3(h) == pytest.approx(rho, abs=6e-4)
    with pytest.raises(InputError, match="troposphere"):
        isa_density_kgpm3(12_000)


def test_segment_energy_hand_computed():
    x8 = load_vehicle("skywalker-x8")
    z = 1000.0
    rho = isa_density_kgpm3(z)
    v = (_polar(rho, 1.0)[2] / _polar(rho, 1.0)[1]) ** 0.25            # Carson speed (above 1.2 V_stall here)
    assert v > 1.2 * math.sqrt(2 * 3.364 * G / (rho * 0.75))
    drag = 3.364 * G * _polar(rho, v)[0]
    d = 1000.0
    p0 = [[0, 0, z]] * 5
    p1 = [[d, 0, z], [d, 0, z], [d, 0, z], [0, d, z], [-d, 0, z]]
    wind = [[0, 0, 0], [-4, 0, 0], [4, 0, 0], [4, 0, 0], [4, 0, 0]]     # none, head, tail, cross, tail on a westward leg
    r = segment_energy_fw(p0, p1, wind, x8)
    g = np.array([v, v - 4, v + 4, math.sqrt(v * v - 16), v - 4])
    assert r["ground_speed_mps"] == pytest.approx(g, rel=1e-12)
    assert r["drag_J"] == pytest.approx(drag * v * d / g, rel=1e-9)   # drag x air distance
    assert r["time_s"] == pytest.approx(d / g, rel=1e-12)
    assert r["drag_J"][0] == pytest.approx(3.364 * G * x8.min_drag_to_lift * d, rel=1e-9)   # eq. 9
    assert np.all(r["potential_J"] == 0) and np.all(r["speed_change_J"] == 0)
    # climb vs descent: potential energy only when climbing (eq. 3)
    r = segment_energy_fw([[0, 0, 1000], [0, 0, 1100]], [[1000, 0, 1100], [1000, 0, 1000]], (0, 0, 0), x8)
    assert r["potential_J"] == pytest.approx([3.364 * G * 100, 0.0], rel=1e-12)
    rho0, rho1 = isa_density_kgpm3(1000), isa_density_kgpm3(1100)
    v0, v1 = (x8.carson_speed_at(q) for q in (rho0, rho1))
    assert r["speed_change_J"] == pytest.approx([0.5 * 3.364 * (v1**2 - v0**2), 0.0], rel=1e-9)
    va = x8.carson_speed_at(0.5 * (rho0 + rho1))
    length = math.hypot(1000, 100)
    assert r["drag_J"] == pytest.approx(3.364 * G * x8.min_drag_to_lift * length * np.ones(2), rel=1e-9)
    assert r["airspeed_mps"] == pytest.approx([va, va], rel=1e-12)
    # a head wind stronger than the airspeed: no solution
    r = segment_energy_fw([0, 0, 500], [1000, 0, 500], (-30, 0, 0), x8)
    assert np.isinf(r["energy_J"][0]) and np.isnan(r["ground_speed_mps"][0])


# ------------------------------------------------------------------ planners


def _terrain_problem(wind=(3.0, 1.0, 0.0), start=(300.0, 900.0), goal=(2700.0, 1000.0), vehicle="skywalker-x8",
                     power_profile=False):
    """A 3 x 2 km valley at 30 m: a ridge across the route with a saddle near y = 1700 m."""
    g = Grid.from_bounds("EPSG:32611", 0, 0, 3000, 2000, 30)
    x = g.x0 + (np.arange(g.nx) + 0.5) * g.resolution_m
    y = g.y1 - (np.arange(g.ny) + 0.5) * g.resolution_m
    xx, yy = np.meshgrid(x, y)
    ridge = 260 * np.exp(-(((xx - 1500) / 250) ** 2)) * (1 - 0.7 * np.exp(-(((yy - 1700) / 250) ** 2)))
    t = 400 + ridge + 0.02 * xx
    da = g.dataarray(t, "terrain", units="m")
    ds = xr.Dataset({"terrain": da, "surface": da})
    r0, c0 = g.index_of(*start)
    r1, c1 = g.index_of(*goal)
    if power_profile:                    # a wind that grows with height above ground (power law)
        from skyroute.stages.wind import wind_on_grid

        wind = wind_on_grid(wind, g, [0, 10, 50, 100, 200, 300], terrain=da, profile="power", horizontal_step_m=300)
    return build_problem(ds, t + 15.0, None, 0, 0, wind, vehicle, (1, 0, 0, 0), (*start, t[r0, c0] + 100),
                         (*goal, t[r1, c1] + 100), 30.0, 300.0)


def _brute_force_energy(problem, step_cells=4, dz_m=20.0, corridor_m=600.0):
    """Minimum energy over the lattice graph by scipy's Dijkstra, edges enumerated in Python
    (turn and climb rules of the lattice, exact validity, energy by segment_energy_fw)."""
    lat, desc = make_fw_lattice(problem, step_cells, dz_m, corridor_m)
    kb, nj = lat.kb, lat.nj
    ncol = lat.ni * nj
    n = ncol * kb * 8
    col, kk, h = np.meshgrid(np.arange(ncol), np.arange(kb), np.arange(8), indexing="ij")
    col, kk, h = col.ravel(), kk.ravel(), h.ravel()
    ok = kk < lat.k_n[col]
    col, kk, h = col[ok], kk[ok], h[ok]
    k = lat.k_lo[col] + kk
    src_all, dst_all, w_all = [], [], []
    wind = np.asarray(problem.wind_uvw, float).reshape(-1, 3)[0]
    for dh in (-1, 0, 1):
        h2 = (h + dh) % 8
        turn = lat.turn_ok[h, h2]
        i2 = col // nj + lat.moves[h2, 0]
        j2 = col % nj + lat.moves[h2, 1]
        inside = (i2 >= 0) & (i2 < lat.ni) & (j2 >= 0) & (j2 < nj)
        for dk in range(-int(lat.dk_down.max()), int(lat.dk_up.max()) + 1):
            sel = turn & inside & (dk <= lat.dk_up[h2]) & (-dk <= lat.dk_down[h2])
            c2 = np.where(sel, i2 * nj + j2, 0)
            k2 = k + dk
            kk2 = k2 - lat.k_lo[c2]
            sel &= (lat.k_n[c2] > 0) & (kk2 >= 0) & (kk2 < lat.k_n[c2])
            a = np.column_stack([lat.col_x[col], lat.col_y[col], lat.z0_m + k * lat.dz_m])[sel]
            b = np.column_stack([lat.col_x[c2], lat.col_y[c2], lat.z0_m + k2 * lat.dz_m])[sel]
            valid = problem.motion_valid(a, b)
            e = segment_energy_fw(a, b, wind, problem.vehicle)["energy_J"]
            good = valid & np.isfinite(e)
            s = ((col * kb + kk) * 8 + h)[sel][good]
            t = ((c2 * kb + kk2) * 8 + h2)[sel][good]
            src_all.append(s)
            dst_all.append(t)
            w_all.append(e[good])
    src, dst, w = np.concatenate(src_all), np.concatenate(dst_all), np.concatenate(w_all)
    mat = coo_matrix((w + 1e-300, (src, dst)), shape=(n, n)).tocsr()
    start_col = desc["mi"] * nj + desc["mj"]
    # a virtual source: the start with any heading (the first move may take any heading)
    starts = (start_col * kb + (0 - lat.k_lo[start_col])) * 8 + np.arange(8)
    dist = dijkstra(mat, indices=starts, min_only=True)
    goal_col = (desc["mi"] + desc["n_u"]) * nj + desc["mj"]
    goal = (goal_col * kb + (desc["goal_k"] - lat.k_lo[goal_col])) * 8 + np.arange(8)
    return float(dist[goal].min())


def test_energy_optimal_is_exact_and_a_lower_bound():
    pr = _terrain_problem()
    res = {p: plan_fixedwing(pr, p, corridor_m=600.0) for p in ("astar-fw", "eeastar", "energy-optimal")}
    assert all(r.solved for r in res.values()), {p: r.reason for p, r in res.items()}
    # the first move from the start may take any heading (brute force: min over the 8 start states,
    # where turn rules do not apply to the first edge either)
    brute = _brute_force_energy(pr)
    assert res["energy-optimal"].energy_J == pytest.approx(brute, rel=1e-9)
    assert res["energy-optimal"].energy_J <= res["eeastar"].energy_J * (1 + 1e-12)
    assert res["energy-optimal"].energy_J <= res["astar-fw"].energy_J * (1 + 1e-12)
    assert res["astar-fw"].length_m <= min(res["eeastar"].length_m, res["energy-optimal"].length_m) + 1e-6
    # the reported energy is that of the returned path (independent recomputation)
    for r in res.values():
        assert r.energy_J == pytest.approx(path_energy(pr, r.waypoints)["energy_J"], rel=1e-12)
        wind = np.asarray(pr.wind_uvw, float).reshape(-1, 3)[0]
        e = segment_energy_fw(r.waypoints[:-1], r.waypoints[1:], wind, "skywalker-x8")["energy_J"].sum()
        assert r.energy_J == pytest.approx(e, rel=1e-12)


def test_written_plan_turns_loiter_and_validation():
    pr = _terrain_problem()
    r = plan_fixedwing(pr, "eeastar", corridor_m=600.0)
    c = fixedwing_candidate(pr, r)
    assert c.flyable, c.reasons
    assert np.allclose(c.xyz_m[0], pr.start_xyz) and np.allclose(c.xyz_m[-1], pr.goal_xyz, atol=1e-6)
    assert c.energy_J == r.energy_J
    x8 = load_vehicle("skywalker-x8")
    # independent: bank needed by every sample triple <= max bank (finite differences here)
    p, t = c.xyz_m[:, :2], c.t_s
    a, b, q = p[:-2], p[1:-1], p[2:]
    ab, bc, ca = (np.linalg.norm(u, axis=1) for u in (b - a, q - b, a - q))
    cross = np.abs((b - a)[:, 0] * (q - a)[:, 1] - (b - a)[:, 1] * (q - a)[:, 0])
    rad = np.where(cross > 1e-9, ab * bc * ca / np.maximum(2 * cross, 1e-300), np.inf)
    v = (ab + bc) / (t[2:] - t[:-2])
    assert np.all(v * v / (G * rad) <= math.tan(math.radians(x8.max_bank_deg)) * (1 + 1e-6))
    # the loiter: the last 120 samples (3 deg apart) are one full circle of the fillet radius
    lo = c.xyz_m[-120:, :2]
    ctr = lo.mean(axis=0)
    assert np.linalg.norm(lo - ctr, axis=1) == pytest.approx(r.info["turn_radius_m"], rel=1e-6)
    assert np.linalg.norm(ctr - np.asarray(pr.goal_xyz[:2])) == pytest.approx(r.info["turn_radius_m"], rel=1e-6)
    # the validator catches a turn that is too tight: a 90 deg corner at 12 m/s sampled every 2 m
    s = np.arange(0, 100, 2.0)
    path = np.vstack([np.column_stack([s, 0 * s]), np.column_stack([100 + 0 * s, s])])
    tt = np.arange(len(path)) * 2.0 / 12.0
    assert turn_radius_violations(tt, np.column_stack([path, np.zeros(len(path))]), 30.0)


def test_five_missions_table2_relations():
    """Seed 002 Table 2 relations on 5 small missions: the optimum never uses more energy than
    EEA* or A*, and EEA* uses no more than A* in the majority."""
    rng = np.random.default_rng(2)
    better_or_equal = 0
    for _ in range(5):
        sx, sy = rng.uniform([250, 300], [700, 1700])
        gx, gy = rng.uniform([2300, 300], [2750, 1700])
        pr = _terrain_problem(wind=tuple(rng.uniform(-4, 4, 2)) + (0.0,), start=(sx, sy), goal=(gx, gy))
        e = {p: plan_fixedwing(pr, p, corridor_m=500.0).energy_J for p in ("astar-fw", "eeastar", "energy-optimal")}
        assert e["energy-optimal"] <= e["eeastar"] * (1 + 1e-12)
        assert e["energy-optimal"] <= e["astar-fw"] * (1 + 1e-12)
        better_or_equal += e["eeastar"] <= e["astar-fw"] * (1 + 1e-12)
    assert better_or_equal >= 3


def test_wind_varying_with_height():
    """A power-law wind profile (non-uniform: sub-segment sampling, isotropic heuristic): the
    optimum is still a lower bound and every reported energy is that of its path."""
    pr = _terrain_problem(wind=(6.0, 300.0), power_profile=True)
    assert np.ptp(np.asarray(pr.wind_uvw)[..., 0]) > 1.0
    res = {p: plan_fixedwing(pr, p, corridor_m=500.0) for p in ("astar-fw", "eeastar", "energy-optimal")}
    e = {p: r.energy_J for p, r in res.items()}
    assert e["energy-optimal"] <= min(e["eeastar"], e["astar-fw"]) * (1 + 1e-12)
    for r in res.values():
        assert r.energy_J == pytest.approx(path_energy(pr, r.waypoints)["energy_J"], rel=1e-12)
    assert fixedwing_candidate(pr, res["eeastar"]).flyable


def test_lattice_rejects_a_step_too_short_for_the_turns():
    pr = _terrain_problem()
    with pytest.raises(InputError, match="too short for turns"):
        make_fw_lattice(pr, step_cells=1)
    with pytest.raises(InputError, match="fixed-wing"):
        plan_fixedwing(_terrain_problem(vehicle="dji-m300-rtk"), "eeastar")


@pytest.mark.slow
def test_scenario_eeastar_within_half_a_percent_of_astar(tmp_path):
    """san-gabriel-fixedwing (SRTM DEM, Skywalker X8): the optimum is a lower bound and EEA* uses
    no more energy than A* (+0.5 %) on the scenario's mission (the catalog test flies its plan)."""
    import warnings

    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.runner import run_scenario
    from skyroute.pipeline.settings import load_scenario
    from skyroute.stages.planning.problem import xyz_from_agl

    sc = load_scenario("san-gabriel-fixedwing")
    assert sc.planner.name == "eeastar" and sc.vehicle == "skywalker-x8"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = run_scenario(sc, cache=Cache(tmp_path), targets=["surface", "clearance", "wind"])
    s, c, m = res["surface"].load(), res["clearance"].load(), sc.mission
    pr = build_problem(s, c["min_altitude_m"], None, None, None, res["wind"].load(), sc.vehicle, (1, 0, 0, 0),
                       xyz_from_agl(s, *sc.point_xy(m.start), m.start.alt_agl_m),
                       xyz_from_agl(s, *sc.point_xy(m.goal), m.goal.alt_agl_m), sc.constraints.min_altitude_agl_m,
                       sc.constraints.max_altitude_agl_m, nofly=c["nofly"])
    e = {p: plan_fixedwing(pr, p, step_cells=sc.planner.step_cells).energy_J
         for p in ("astar-fw", "eeastar", "energy-optimal")}
    assert e["energy-optimal"] <= min(e["eeastar"], e["astar-fw"]) * (1 + 1e-12)
    assert e["eeastar"] <= 1.005 * e["astar-fw"]


def test_fly_refuses_rotorcraft_methods_for_a_fixed_wing_scenario():
    """A fixed-wing vehicle flies the local planner (tests/test_fw_local.py); levels and octant
    are refused before any work, naming the method that fits."""
    from skyroute.pipeline.fly import fly_scenario, tactical_method
    from skyroute.pipeline.settings import load_scenario

    sc = load_scenario("san-gabriel-fixedwing")
    assert tactical_method(sc) == "local"
    for m in ("levels", "octant"):
        with pytest.raises(InputError, match="fixed-wing: use --tactical local"):
            fly_scenario(sc, method=m)


def test_qgc_plan_of_a_fixed_wing_ends_with_a_landing_pattern():
    from skyroute.stages.exports import qgc_plan

    land = {"ground_rel_m": 20.0, "loiter_radius_m": 50.0, "clockwise": True, "descent_angle_deg": 10.0}
    doc = qgc_plan([7.0, 7.01], [43.0, 43.01], [100.0, 120.0], 50.0, cruise_speed_mps=11.2, fixed_wing=True,
                   landing=land)
    m = doc["mission"]
    assert m["vehicleType"] == 1 and [i["command"] for i in m["items"][-3:]] == [189, 31, 21]
    assert m["items"][-2]["params"][6] == 120.0 and m["items"][-1]["params"][6] == 20.0
    assert qgc_plan([7.0, 7.01], [43.0, 43.01], [100.0, 120.0], 50.0, cruise_speed_mps=5.0)["mission"]["items"][-1][
        "command"] == 21


def test_bitstar_dubins_is_a_flyable_curve():
    """BIT* on OMPL's Dubins-airplane space (continuous comparison): its samples pass the
    problem's state check, turn no tighter than its radius and climb / descend within the
    limits (finite differences, tolerance 0); reproducible with a seed and an iteration count."""
    from skyroute.stages.planning.bitstar_dubins import plan_bitstar_dubins

    pr = _terrain_problem(wind=(0.0, 0.0, 0.0))
    r = plan_bitstar_dubins(pr, 60.0, seed=3, max_iterations=300)
    assert r["solved"]
    x = r["xyz_m"]
    assert pr.state_valid(x).all()
    assert np.allclose(x[0], pr.start_xyz) and np.allclose(x[-1], pr.goal_xyz, atol=1e-6)
    d = np.diff(x, axis=0)
    ang = np.degrees(np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])))
    veh = load_vehicle("skywalker-x8")
    assert ang.max() <= veh.max_climb_angle_deg and -ang.min() <= veh.max_descent_angle_deg
    a, b, c = x[:-2, :2], x[1:-1, :2], x[2:, :2]
    ab, bc, ca = (np.linalg.norm(q, axis=1) for q in (b - a, c - b, a - c))
    cross = np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
    rho = np.where(cross > 1e-9, ab * bc * ca / np.maximum(2 * cross, 1e-300), np.inf)
    assert rho.min() >= r["turn_radius_m"] * (1 - 1e-9)
    assert r["energy_J"] == pytest.approx(path_energy(pr, x)["energy_J"], rel=1e-12)
    # never shorter than the straight line; reproducible
    assert r["length_m"] >= math.dist(pr.goal_xyz, pr.start_xyz)
    assert np.array_equal(plan_bitstar_dubins(pr, 60.0, seed=3, max_iterations=300)["xyz_m"], x)


def test_bitstar_dubins_written_plan_is_flyable():
    """`--planner bitstar-dubins`: the curve is written as it is (no fillets) with the loiter,
    validated like the lattice plans; its search objective is the curve's length, f (eq. 11, weights
    1, 0, 0, 0) the length of the written trajectory, loiter included."""
    from skyroute.stages.planning.bitstar_dubins import dubins_result

    check_planner_vehicle("bitstar-dubins", "skywalker-x8", PLANNERS)
    with pytest.raises(InputError, match="fixed-wing"):
        check_planner_vehicle("bitstar-dubins", "dji-m300-rtk", PLANNERS)
    pr = _terrain_problem()
    r = dubins_result(pr, 3.0, seed=1)
    assert r.solved and r.info["continuous"] and r.info["iterations"] == 300
    cand = fixedwing_candidate(pr, r)
    assert cand.flyable, cand.reasons
    assert cand.search_cost_m == pytest.approx(r.length_m, rel=1e-12)
    assert cand.f == pytest.approx(np.linalg.norm(np.diff(cand.xyz_m, axis=0), axis=1).sum(), rel=1e-9)
    n = len(r.waypoints)
    assert np.array_equal(cand.xyz_m[:n], r.waypoints)
