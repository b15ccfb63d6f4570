"""STEP II (seed 000 Algorithm 1): RRT deconfliction against intruders crossing the STEP I
chain (as in seed 000 Fig. 10-11).  Oracles: the exact capsule queries of the occupancy maps on
every leg, and an independent dense brute force of own positions vs intruder positions in time;
leg times against the energy model (stages.energy.segment_energy)."""

from __future__ import annotations

import numpy as np
import pytest

from skyroute.pipeline.errors import InputError
from skyroute.stages.energy import segment_energy
from skyroute.stages.grid import Grid
from skyroute.stages.planning.deconflict import Step2Result, chain_conflicts, deconflict
from skyroute.stages.planning.problem import PlanningProblem
from skyroute.stages.traffic import Intruder, build_occupancy
from skyroute.stages.vehicle import load_vehicle

X0, Y0 = 385000.0, 6672000.0                       # UTM 35N, Helsinki
WIND = np.array([3.0, 0.0, 0.0])
T_TOT, N_O, D_C, DT_C = 400.0, 20, 10.0, 10.0      # seed 000 case 2: dt = 20 s, dt_c = 10 s, d_c = 10 m
CHAIN = np.array([[100, 300, 30], [300, 320, 30], [500, 300, 30], [700, 280, 30], [900, 300, 30.0]]) + [X0, Y0, 0]


def make_problem(vehicle=None, wind=WIND):
    g = Grid.from_bounds("EPSG:32635", X0, Y0, X0 + 1000, Y0 + 600, 5.0)
    terr = np.zeros(g.shape)
    veh = vehicle or load_vehicle("dji-m300-rtk")
    return PlanningProblem(grid=g, terrain_m=terr, floor_m=terr + 10.0, ceiling_m=terr + 80.0,
                           risk_cost=np.zeros(g.shape), landing_cost=np.zeros(g.shape), wind_uvw=wind,
                           vehicle=veh, weights=(1, 1, 1, 1), start_xyz=tuple(CHAIN[0]),
                           goal_xyz=tuple(CHAIN[-1]), min_agl_m=0.0, max_agl_m=80.0)


def crossing_intruders():
    """Two intruders that cross the chain when the drone gets there (t ~ 40 s and ~ 65 s)."""
    return [Intruder("north-south", np.array([0.0, 80.0]), np.array([[500, -100, 30], [500, 700, 30.0]]) + [X0, Y0, 0], 2.0),
            Intruder("diagonal", np.array([20.0, 120.0]), np.array([[800, 600, 30], [650, 0, 30.0]]) + [X0, Y0, 0], 2.0)]


@pytest.fixture(scope="module")
def problem():
    return make_problem()


@pytest.fixture(scope="module")
def intruders():
    return crossing_intruders()


@pytest.fixture(scope="module")
def occ(intruders):
    return build_occupancy(intruders, T_TOT, N_O, D_C, DT_C)


def reference_leg_times(w):
    r = segment_energy(w[:-1], w[1:], np.broadcast_to(WIND, (w.shape[0] - 1, 3)), "dji-m300-rtk")
    return r["time_s"], r["energy_J"]


def brute_force_min_gap(res: Step2Result, intruders, occ, dt=0.05, strict_slices=True):
    """Smallest (distance - (r_i + d_c)) [m] between own positions (legs flown linearly in
    time, sampled every dt s) and intruder positions sampled every dt s over the window the
    occupancy maps reserve: [t_k - dt_c, t_{k+1} + dt_c] of the slice k containing t
    (strict_slices) or [t - dt_c, t + dt_c]."""
    t = np.arange(res.times_s[0], res.times_s[-1], dt)
    t = np.r_[t, res.times_s[-1]]
    own = np.stack([np.interp(t, res.times_s, res.waypoints[:, j]) for j in range(3)], axis=1)
    gap = np.inf
    for it in intruders:
        if strict_slices:
            k = np.minimum(np.floor((t - occ.t0_s) / occ.dt_s), occ.n_slices - 1)
            a, b = occ.t0_s + k * occ.dt_s - DT_C, occ.t0_s + (k + 1) * occ.dt_s + DT_C
        else:
            a, b = t - DT_C, t + DT_C
        a, b = np.maximum(a, it.times_s[0]), np.minimum(b, it.times_s[-1])
        for i in np.nonzero(a <= b)[0]:
            tau = np.r_[np.arange(a[i], b[i], dt), b[i]]
            q = np.stack([np.interp(tau, it.times_s, it.xyz_m[:, j]) for j in range(3)], axis=1)
            d = np.min(np.linalg.norm(q - own[i], axis=1))
            gap = min(gap, d - (it.radius_m + D_C))
    return gap


def test_unchanged_when_conflict_free(problem):
    res = deconflict(problem, CHAIN, None, t0_s=5.0)
    assert res.status == "unchanged" and res.ok
    np.testing.assert_array_equal(res.waypoints, CHAIN)
    tau, e = reference_leg_times(CHAIN)
    # arrival times / cumulative energy from the energy model (uniform wind: sub-segments equal)
    np.testing.assert_allclose(np.diff(res.times_s), tau, rtol=1e-9)
    np.testing.assert_allclose(res.times_s[0], 5.0)
    np.testing.assert_allclose(np.diff(res.energy_J), e, rtol=1e-9)
    # far traffic: also unchanged, same timing
    far = [Intruder("far", np.array([0.0, 300.0]), np.array([[X0 + 50, Y0 + 550, 70], [X0 + 950, Y0 + 550, 70]]), 2.0)]
    res2 = deconflict(problem, CHAIN, build_occupancy(far, T_TOT, N_O, D_C, DT_C))
    assert res2.status == "unchanged"
    np.testing.assert_allclose(np.diff(res2.times_s), tau, rtol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_deconflicts_crossing_traffic(problem, intruders, occ, seed):
    tau, _ = reference_leg_times(CHAIN)
    t_chain = np.r_[0.0, np.cumsum(tau)]
    assert chain_conflicts(occ, CHAIN, t_chain).sum() >= 2          # the scenario does conflict
    assert brute_force_min_gap(Step2Result(CHAIN, t_chain, t_chain, "x"), intruders, occ) < -5.0
    res = deconflict(problem, CHAIN, occ, seed=seed, time_budget_s=30.0)
    assert res.status == "deconflicted", res.reason
    w, t = res.waypoints, res.times_s
    np.testing.assert_allclose(w[0], CHAIN[0])
    np.testing.assert_allclose(w[-1], CHAIN[-1])
    assert np.all(np.diff(t) > 0)
    # exact capsule queries on every leg
    assert not occ.segment_conflicts(w[:-1], t[:-1], w[1:], t[1:]).any()
    # static bounds on every leg, times and energies of the energy model, battery
    assert problem.motion_valid(w[:-1], w[1:]).all()
    ref_tau, ref_e = reference_leg_times(w)
    np.testing.assert_allclose(np.diff(t), ref_tau, rtol=1e-9)
    np.testing.assert_allclose(np.diff(res.energy_J), ref_e, rtol=1e-9)
    assert res.energy_J[-1] <= problem.vehicle.battery_energy_j
    # brute force (sampling error <= 10 m/s * 0.025 s per side: 0.5 m band)
    assert brute_force_min_gap(res, intruders, occ, strict_slices=True) > -0.5
    assert brute_force_min_gap(res, intruders, occ, strict_slices=False) > -0.5


def test_seeded_and_reproducible(problem, occ):
    a = deconflict(problem, CHAIN, occ, seed=7)
    b = deconflict(problem, CHAIN, occ, seed=7)
    assert a.status == b.status == "deconflicted"
    np.testing.assert_array_equal(a.waypoints, b.waypoints)
    np.testing.assert_array_equal(a.times_s, b.times_s)


def test_iteration_count_not_the_clock_decides(problem, occ):
    """The RRT stops on its iteration count: the wall-clock cap does not change the result, and
    a run stopped by the cap says so."""
    a = deconflict(problem, CHAIN, occ, seed=3, time_budget_s=5.0)
    b = deconflict(problem, CHAIN, occ, seed=3, time_budget_s=500.0)
    assert a.status == b.status == "deconflicted" and a.iterations == b.iterations
    np.testing.assert_array_equal(a.waypoints, b.waypoints)
    g = CHAIN[-1]
    hover = build_occupancy([Intruder("on-goal", np.array([0.0, 400.0]), np.array([g, g]), 5.0)], T_TOT, N_O, D_C, DT_C)
    capped = deconflict(problem, CHAIN, hover, max_iter=100_000, time_budget_s=0.2)
    assert capped.status == "failed" and capped.iterations < 100_000
    assert "wall-clock cap of 0.2 s before its 100000 iterations" in capped.reason


def test_energy_infeasible():
    veh = load_vehicle("dji-m300-rtk").model_copy(update={"battery_capacity_mah": 100.0})   # 5.3 Wh
    prob = make_problem(veh)
    res = deconflict(prob, CHAIN, None)
    assert res.status == "failed" and not res.ok and res.waypoints.shape == (0, 3)
    assert "energy infeasible" in res.reason
    res = deconflict(prob, CHAIN, build_occupancy(crossing_intruders(), T_TOT, N_O, D_C, DT_C), max_iter=200)
    assert res.status == "failed" and "battery" in res.reason


def test_unreachable_goal_reports_reasons(problem):
    # an intruder hovering on the goal for the whole mission: the goal is always reserved
    g = CHAIN[-1]
    hover = [Intruder("on-goal", np.array([0.0, 400.0]), np.array([g, g]), 5.0)]
    occ = build_occupancy(hover, T_TOT, N_O, D_C, DT_C)
    res = deconflict(problem, CHAIN, occ, max_iter=300)
    assert res.status == "failed"
    assert "without reaching the goal" in res.reason and "traffic" in res.reason
    assert "its 300 iterations" in res.reason and res.iterations == 300


def test_static_violation_of_step1_chain_is_reported(problem):
    bad = CHAIN.copy()
    bad[2, 2] = 5.0                                  # below the 10 m floor
    res = deconflict(problem, bad, None)
    assert res.status == "failed" and "violates the bounds" in res.reason


def test_bad_input(problem, occ):
    with pytest.raises(InputError, match="time_budget_s"):
        deconflict(problem, CHAIN, occ, time_budget_s=0)
    with pytest.raises(InputError, match="step1_waypoints"):
        deconflict(problem, CHAIN[:1], occ)
    with pytest.raises(InputError, match="max_iter"):
        deconflict(problem, CHAIN, occ, max_iter=0)
    with pytest.raises(InputError, match="before the occupancy maps"):
        deconflict(problem, CHAIN, occ, t0_s=-50.0)


class _StockProblem(PlanningProblem):
    """The same problem, but ``segment_details`` overridden: STEP II then evaluates its legs
    through it (the reference path) instead of the compiled kernel directly."""

    def segment_details(self, p0, p1):
        return super().segment_details(p0, p1)


def _traffic_with_prisms(occ):
    import shapely

    from skyroute.stages.fleet import Volume4
    from skyroute.stages.traffic import volume_prisms
    box = Volume4(shapely.box(X0 + 380, Y0 + 250, X0 + 430, Y0 + 380), 0.0, 60.0, 20.0, 60.0)
    return occ.with_volumes(volume_prisms([box], grow_m=2.0))


def test_feasibility_matches_the_stock_leg_functions(problem, occ):
    """IS_FEASIBLE's one-leg fast path (compiled kernel called directly, scalar traffic test)
    against the stock vectorised functions (np.allclose, leg_time_energy, leg_conflicts) on
    random legs: same flag, time, energy and reject reason, bit for bit."""
    from skyroute.stages.planning.deconflict import (
        _Feasibility,
        _Tree,
        leg_conflicts,
        leg_time_energy,
    )
    rng = np.random.default_rng(11)
    seen = set()
    for traffic in (None, occ, _traffic_with_prisms(occ)):
        for battery in (problem.vehicle.battery_energy_j, 3.0e4):
            feas = _Feasibility(problem, traffic, battery)
            assert feas._eval is not None
            tree = _Tree(CHAIN[0], 0.0)
            for _ in range(40):
                tree.add(CHAIN[0] + rng.normal(0, 1, 3) * [300, 150, 15] + [400, 0, 0], rng.uniform(0, 150),
                         rng.uniform(0, 2e4), 0)
            for _ in range(600):
                a = int(rng.integers(tree.n))
                q = tree.p[a].copy() if rng.random() < 0.05 else tree.p[a] + rng.normal(0, 1, 3) * [80, 80, 12]
                before = dict(feas.rejects)
                got = feas.leg(tree, a, q)
                why = [k for k in feas.rejects if feas.rejects[k] != before[k]]
                pa = tree.p[a]
                if np.allclose(pa, q):
                    ref, ref_why = (False, 0.0, 0.0), []
                else:
                    tau, e, ok = leg_time_energy(problem, pa, q)
                    tau, e = float(tau[0]), float(e[0])
                    if not ok[0]:
                        ref, ref_why = (False, 0.0, 0.0), ["bounds"]
                    elif tree.e[a] + e > battery:
                        ref, ref_why = (False, tau, e), ["battery"]
                    elif leg_conflicts(traffic, pa, tree.t[a], q, tree.t[a] + tau)[0]:
                        ref, ref_why = (False, tau, e), ["traffic"]
                    else:
                        ref, ref_why = (True, tau, e), []
                assert got == ref and why == ref_why
                seen.update(why)
    assert seen == {"bounds", "battery", "traffic"}                  # every branch was exercised


@pytest.mark.parametrize("seed", [0, 5])
def test_same_result_as_the_stock_leg_functions(occ, seed):
    """deconflict with the fast IS_FEASIBLE and the memoised leg requests gives the result of
    the reference path (legs through an overridden ``segment_details``) exactly, reject
    counters included; with capsules and prisms."""
    fast, stock = make_problem(), make_problem()
    object.__setattr__(stock, "__class__", _StockProblem)     # a frozen dataclass
    for traffic in (occ, _traffic_with_prisms(occ)):
        a = deconflict(fast, CHAIN, traffic, seed=seed, max_iter=400)
        b = deconflict(stock, CHAIN, traffic, seed=seed, max_iter=400)
        assert a.status == b.status and a.iterations == b.iterations and a.tree_size == b.tree_size
        np.testing.assert_array_equal(a.waypoints, b.waypoints)
        np.testing.assert_array_equal(a.times_s, b.times_s)
        np.testing.assert_array_equal(a.energy_J, b.energy_J)
    g = CHAIN[-1]                                     # a failing search: same counters in the reason
    hover = build_occupancy([Intruder("on-goal", np.array([0.0, 400.0]), np.array([g, g]), 5.0)], T_TOT, N_O, D_C, DT_C)
    a = deconflict(fast, CHAIN, hover, seed=seed, max_iter=300)
    b = deconflict(stock, CHAIN, hover, seed=seed, max_iter=300)
    assert a.status == b.status == "failed"
    assert a.reason.split("rejected legs:")[1] == b.reason.split("rejected legs:")[1]


def test_free_legs_decide_whether_more_traffic_changes_the_rrt(problem, occ):
    """Step2Result.free_legs (what ``skyroute fleet`` uses to keep a speculative plan): random
    extra prisms that meet none of a run's free legs give the SAME run (chain, times, tree
    size, iterations) when added to the traffic; the check is not vacuous (some prisms meet a
    free leg, and adding one of those changes a run)."""
    import shapely

    from skyroute.stages.fleet import Volume4
    from skyroute.stages.planning.deconflict import leg_conflicts
    from skyroute.stages.traffic import volume_prisms

    box0 = Volume4(shapely.box(X0 + 380, Y0 + 250, X0 + 430, Y0 + 380), 0.0, 60.0, 20.0, 60.0)
    base = occ.with_volumes(volume_prisms([box0], grow_m=2.0))
    rng = np.random.default_rng(4)
    kept = hit = changed = 0
    for seed in (0, 3):
        ref = deconflict(problem, CHAIN, base, seed=seed, max_iter=400)
        assert ref.status in ("deconflicted", "failed") and ref.free_legs is not None and ref.free_legs.shape[0] > 0
        fl = ref.free_legs
        for _ in range(25):
            x, y, t = X0 + rng.uniform(50, 950), Y0 + rng.uniform(230, 370), rng.uniform(0, 150)
            box = Volume4(shapely.box(x, y, x + rng.uniform(10, 60), y + rng.uniform(10, 60)), 0.0, 80.0, t,
                          t + rng.uniform(5, 60))
            alone = build_occupancy([], T_TOT, N_O, D_C, DT_C).with_volumes(volume_prisms([box], grow_m=2.0))
            touches = leg_conflicts(alone, fl[:, 0:3], fl[:, 3], fl[:, 4:7], fl[:, 7]).any()
            run = deconflict(problem, CHAIN, occ.with_volumes(volume_prisms([box0, box], grow_m=2.0)), seed=seed,
                             max_iter=400)
            same = (run.status == ref.status and run.iterations == ref.iterations and run.tree_size == ref.tree_size
                    and np.array_equal(run.waypoints, ref.waypoints) and np.array_equal(run.times_s, ref.times_s))
            if touches:
                hit += 1
                changed += not same
            else:
                kept += 1
                assert same
    assert kept >= 10 and hit >= 3 and changed >= 1
