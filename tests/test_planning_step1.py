"""STEP I planner (seed 000 III-A): problem costs/validity, lattice A*, OMPL BIT*, energy loop."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import xarray as xr
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from skyroute.pipeline.errors import InputError, PlanningError, UnknownNameError
from skyroute.stages.energy import energy_cost
from skyroute.stages.grid import Grid
from skyroute.stages.planning.grid_planner import (
    _OFFS,
    EdgeCache,
    astar,
    heuristic_2d,
    make_lattice,
    plan_grid,
    shared_heuristic,
    vertical_rates,
)
from skyroute.stages.planning.problem import build_problem
from skyroute.stages.planning.step1 import (
    BITSTAR_ITERATIONS_PER_S,
    bitstar_iterations,
    plan_step1,
    step1_all_levels,
)
from skyroute.stages.planning.strategic import plan_levels, plan_strategic
from skyroute.stages.vehicle import load_vehicle

VEH = load_vehicle("dji-m300-rtk")


def _surface(nx_m=200.0, ny_m=100.0, res=2.0):
    g = Grid.from_bounds("EPSG:32635", 0, 0, nx_m, ny_m, res)
    t = g.dataarray(np.zeros(g.shape), "terrain", units="m")
    return g, xr.Dataset({"terrain": t, "surface": t})


def make_problem(risk=0.3, landing=0.2, wind=(0.0, 0.0, 0.0), block=True, coverage=None, weights=(1, 1, 1, 1),
                 start=(10, 50, 20), goal=(190, 50, 20), vehicle=VEH, size=(200.0, 100.0), **kw):
    g, ds = _surface(*size)
    clear = np.zeros(g.shape)
    if block:  # a tower x 80..120 m, y 20..80 m whose clearance floor is 70 m
        clear[10:40, 40:60] = 70.0
    return build_problem(ds, clear, coverage, risk, landing, wind, vehicle, weights, start, goal, 0.0, 80.0, **kw)


# ------------------------------------------------------------------ costs and validity


def test_costs_closed_form_uniform_maps():
    pr = make_problem(block=False)
    p0 = np.array([[10.0, 50.0, 20.0], [30.0, 10.0, 20.0], [100.0, 50.0, 20.0]])
    p1 = np.array([[190.0, 50.0, 20.0], [170.0, 90.0, 35.0], [100.0, 50.0, 20.0]])
    c = pr.segment_costs(p0, p1)
    L = np.linalg.norm(p1 - p0, axis=1)
    np.testing.assert_allclose(c[:, 0], L, rtol=1e-12)
    np.testing.assert_allclose(c[:, 1], 0.3 * L, rtol=1e-12, atol=1e-12)   # risk * length
    np.testing.assert_allclose(c[:, 2], 0.2 * L, rtol=1e-12, atol=1e-12)   # landing * length
    np.testing.assert_allclose(c[:, 3], L, rtol=1e-12, atol=1e-12)         # no wind: E_w / E_0 = 1
    pc = pr.path_costs([[10, 50, 20], [100, 50, 20], [190, 50, 20]])
    assert pc["f"] == pytest.approx((1 + 0.3 + 0.2 + 1) * 180.0, rel=1e-12)
    assert pc["time_s"] == pytest.approx(180.0 / VEH.cruise_speed_mps, rel=1e-12)   # g = v_c without wind


def test_risk_integral_exact_on_a_step_map():
    g, _ = _surface()
    risk = np.zeros(g.shape)
    risk[:, 50:] = 1.0          # x >= 100 m
    pr = make_problem(risk=risk, block=False)
    p0, p1 = np.array([50.0, 30.0, 20.0]), np.array([150.0, 70.0, 30.0])
    L = float(np.linalg.norm(p1 - p0))
    c = pr.segment_costs(p0, p1)[0]
    assert c[1] == pytest.approx(0.5 * L, rel=1e-12)   # half of the segment lies at x >= 100 m


def test_energy_cost_matches_energy_module_with_wind():
    wind = (4.0, -2.0, 0.0)
    pr = make_problem(block=False, wind=wind)
    p0 = np.array([[10.0, 50.0, 20.0], [190.0, 10.0, 20.0], [20.0, 20.0, 20.0]])
    p1 = np.array([[190.0, 50.0, 20.0], [10.0, 90.0, 40.0], [180.0, 60.0, 30.0]])
    ref = energy_cost(p0, p1, lambda pts: np.tile(wind, (len(pts), 1)), VEH, subsegment_m=10.0)
    np.testing.assert_allclose(pr.segment_costs(p0, p1)[:, 3], ref, rtol=1e-10)
    # tail wind (east): E_w / E_0 < 1, so the heuristic rate must be below 1 + 0.3 + 0.2 + ratio
    assert pr.segment_costs(p0[:1], p1[:1])[0, 3] < 180.0
    ratio = pr.segment_costs(p0, p1)[:, 3] / np.linalg.norm(p1 - p0, axis=1)
    assert pr.energy_ratio_lb <= ratio.min()


def test_motion_validity_reasons():
    pr = make_problem()
    # straight through the tower at 20 m
    assert not pr.motion_valid([10, 50, 20], [190, 50, 20])[0]
    assert "below the lowest admissible altitude" in pr.explain_motion([10, 50, 20], [190, 50, 20])
    # climb of 30 m over 60 m: 26.6 deg > 15 deg
    assert pr.explain_motion([10, 90, 20], [70, 90, 50]) == "flight-path angle above the vehicle maximum"
    # 15 deg exactly-ish is fine: dz = 0.99 * L tan(15 deg)
    dz = 0.99 * 60 * math.tan(math.radians(15))
    assert pr.motion_valid([10, 90, 20], [70, 90, 20 + dz])[0]
    # a one-cell wall crossed between any coarse samples is still caught (exact cell traversal)
    g, ds = _surface()
    clear = np.zeros(g.shape)
    clear[:, 75] = 60.0                       # x in [150, 152) m
    wall = build_problem(ds, clear, None, 0, 0, (0, 0, 0), VEH, (1, 0, 0, 0), (10, 50, 20), (190, 50, 20), 0, 80)
    assert not wall.motion_valid([149.99, 10, 20], [152.01, 90, 20])[0]
    assert wall.motion_valid([100, 10, 20], [149.99, 90, 20])[0]
    assert "inside obstacle clearance" in wall.explain_invalid((151, 50, 20))


# ------------------------------------------------------------------ lattice A* vs Dijkstra


def _dijkstra_oracle(pr, lat):
    n = lat.valid.size
    return dijkstra(_lattice_matrix(pr, lat), directed=True, indices=n)[n + 1]


def _lattice_matrix(pr, lat):
    """The lattice graph (start n, goal n + 1) with the eq. 11 weight of every valid edge (csr)."""
    nz, ny, nx = lat.shape
    n = nz * ny * nx
    kk, rr, cc = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    ids = ((kk * ny + rr) * nx + cc).ravel()
    a_list, b_list = [], []
    for dk, di, dj in _OFFS:
        k2, r2, c2 = kk.ravel() + dk, rr.ravel() + di, cc.ravel() + dj
        inside = (k2 >= 0) & (k2 < nz) & (r2 >= 0) & (r2 < ny) & (c2 >= 0) & (c2 < nx)
        a_list.append(ids[inside])
        b_list.append(((k2 * ny + r2) * nx + c2)[inside])
    a, b = np.concatenate(a_list), np.concatenate(b_list)
    S, G = n, n + 1
    a = np.concatenate([a, np.full(lat.start_links.size, S), lat.goal_links, [S]])
    b = np.concatenate([b, lat.start_links, np.full(lat.goal_links.size, G), [G]])
    valid_node = np.concatenate([lat.valid.ravel(), [True, True]])
    keep = valid_node[a] & valid_node[b]
    a, b = a[keep], b[keep]
    xyz = np.concatenate([lat.xyz(np.arange(n)), [pr.start_xyz, pr.goal_xyz]])
    ok = pr.motion_valid(xyz[a], xyz[b])
    w = pr.f_of(pr.segment_costs(xyz[a[ok]], xyz[b[ok]]))
    return coo_matrix((w, (a[ok], b[ok])), shape=(n + 2, n + 2)).tocsr()


def test_astar_is_exact_on_the_lattice():
    pr = make_problem(size=(120.0, 60.0), start=(8, 30, 20), goal=(112, 30, 20), wind=(3.0, 1.0, 0.0),
                      block=False, risk=None, landing=None, weights=(1, 2, 1, 1))
    g = pr.grid
    risk = np.zeros(g.shape)
    risk[5:25, 20:40] = 1.0      # a risky square in the middle: the optimum bends around it
    pr = dataclasses.replace(pr, risk_cost=risk)
    lat = make_lattice(pr, step_cells=4, dz_m=2.0)
    res = astar(pr, lat)
    assert astar(pr, lat, heuristic="euclid")["f"] == pytest.approx(res["f"], rel=1e-9)
    ref = _dijkstra_oracle(pr, lat)
    assert np.isfinite(ref)
    assert res["f"] == pytest.approx(ref, rel=1e-9)
    assert pr.path_costs(res["waypoints"])["f"] == pytest.approx(ref, rel=1e-9)
    assert pr.path_costs(res["waypoints"])["valid"]


def test_edge_cache_shared_by_missions_keeps_each_lattice_optimum():
    """Missions on the same maps with lattices anchored on one altitude share an EdgeCache
    (skyroute fleet): every search, on a cold or a warm cache, returns the scipy Dijkstra
    optimum of its own lattice and the same path as the uncached search."""
    base = make_problem(wind=(3.0, 1.0, 0.0), weights=(1, 2, 1, 1))     # a 70 m tower in the middle
    cache = EdgeCache()
    ends = [((10, 50, 20), (190, 50, 20)), ((190, 8, 27), (8, 92, 13)), ((100, 5, 31), (100, 95, 18)),
            ((10, 50, 20), (190, 50, 20))]
    seen = []
    for start, goal in ends:
        pr = dataclasses.replace(base, start_xyz=tuple(map(float, start)), goal_xyz=tuple(map(float, goal)))
        lat = make_lattice(pr, step_cells=4, dz_m=3.0, z_anchor_m=1.0)
        np.testing.assert_allclose((lat.z - 1.0) / 3.0, np.round((lat.z - 1.0) / 3.0), atol=1e-12)  # anchored
        assert lat.z.min() >= pr.floor_m[np.isfinite(pr.floor_m)].min() - 1e-9
        cached = astar(pr, lat, edge_cache=cache)
        plain = astar(pr, lat)
        assert np.isfinite(plain["f"])
        assert cached["f"] == plain["f"] and cached["expanded"] == plain["expanded"]
        np.testing.assert_array_equal(cached["waypoints"], plain["waypoints"])
        assert cached["f"] == pytest.approx(_dijkstra_oracle(pr, lat), rel=1e-9)
        seen.append(np.isfinite(cache.for_lattice(lat)).sum())
    assert len(cache._arrays) == 1          # one shared lattice
    assert 0 < seen[0] < seen[-1]           # later missions reuse and extend the costs


def test_heuristic_is_admissible_and_tight_in_a_varying_wind():
    # wind varying in x, y and height on a coarse wind grid; the goal 12 m above the start and a
    # tower in between, so the altitude term (climb / descent) and the dense wind bound both act
    base = make_problem(size=(120.0, 60.0), start=(8, 30, 20), goal=(112, 30, 32), block=False, risk=None,
                        landing=None, weights=(1, 2, 1, 1))
    g = base.grid
    clear = np.zeros(g.shape)
    clear[8:22, 25:35] = 45.0                 # tower x 50..70 m, y 16..44 m, floor 45 m
    rng = np.random.default_rng(7)
    wz = np.array([0.0, 20.0, 60.0])
    wind = rng.uniform(-4.0, 4.0, size=(3, 3, 4, 3))
    wind[..., 2] *= 0.2
    wg = Grid(g.crs_wkt, g.x0, g.y1, 4, 3, 30.0)
    pr = dataclasses.replace(base, floor_m=np.maximum(base.floor_m, clear), wind_uvw=wind, wind_z_agl_m=wz,
                             wind_grid=wg)
    lat = make_lattice(pr, step_cells=4, dz_m=2.0)
    h2 = heuristic_2d(pr, lat)
    b_up, c_down = vertical_rates(pr, lat)
    assert b_up > 0 and c_down > 0
    n = lat.valid.size
    # true cost-to-go of every node: Dijkstra from the goal on the reversed lattice graph
    to_go = dijkstra(_lattice_matrix(pr, lat).T.tocsr(), directed=True, indices=n + 1)[:n]
    z = lat.xyz(np.arange(n))[:, 2]
    gz = pr.goal_xyz[2]
    h = np.broadcast_to(h2, lat.shape).ravel() + b_up * np.maximum(gz - z, 0) + c_down * np.maximum(z - gz, 0)
    fin = np.isfinite(to_go) & lat.valid.ravel()
    assert fin.sum() > 1000
    assert np.all(h[fin] <= to_go[fin] + 1e-9)                     # admissible at every node
    res = astar(pr, lat)
    ref = _dijkstra_oracle(pr, lat)
    assert res["f"] == pytest.approx(ref, rel=1e-9)
    assert res["expanded"] < astar(pr, lat, heuristic="euclid")["expanded"]
    # uniform wind, no tower: the energy bound is that wind's exact ratio x 0.99, so h is within
    # a few % of the cost-to-go next to the start (the former 0.9 margin on <= 600 sampled winds
    # left ~10 % of the energy term out)
    pu = dataclasses.replace(base, wind_uvw=np.array([3.0, 1.0, 0.0]), wind_z_agl_m=np.zeros(1), wind_grid=None)
    lat = make_lattice(pu, step_cells=4, dz_m=2.0)
    b_up, c_down = vertical_rates(pu, lat)
    to_go = dijkstra(_lattice_matrix(pu, lat).T.tocsr(), directed=True, indices=n + 1)[:n]
    h = (np.broadcast_to(heuristic_2d(pu, lat), lat.shape).ravel() + b_up * np.maximum(gz - z, 0)
         + c_down * np.maximum(z - gz, 0))
    fin = np.isfinite(to_go) & lat.valid.ravel()
    assert np.all(h[fin] <= to_go[fin] + 1e-9)
    links = lat.start_links[np.isfinite(to_go[lat.start_links])]
    ratio = h[links] / to_go[links]
    assert np.min(ratio) > 0.97                                    # measured 0.977
    assert astar(pu, lat)["f"] == pytest.approx(_dijkstra_oracle(pu, lat), rel=1e-9)


def test_parallel_energy_bound_of_each_direction_is_the_one_direction_bound():
    """ratio_each_kernel (winds split in chunks over the cores) gives, per direction, exactly
    the minimum ratio_kernel takes over the same winds for that direction alone, with headwinds
    too strong to fly (skipped) and a direction with no flyable wind at all (inf)."""
    from skyroute.stages.planning import kernels
    from skyroute.stages.planning.heuristic import (
        energy_ratio_lb_dense_dirs,
    )

    pr = make_problem(block=False, wind=(2.0, 1.0, 0.0))
    _, _, veh, power = pr.seg_args
    rng = np.random.default_rng(3)
    winds = rng.normal(0.0, 6.0, size=(3 * kernels.RATIO_CHUNK + 17, 3))    # 4 chunks, some > max wind
    winds[:, 2] *= 0.1
    d = rng.normal(size=(30, 3))
    d[:, 2] *= 0.2
    d /= np.linalg.norm(d, axis=1)[:, None]
    each = kernels.ratio_each_kernel(d, winds, veh, power)
    one = np.array([kernels.ratio_kernel(d[i:i + 1], winds, veh, power) for i in range(len(d))])
    assert np.all(np.isfinite(one)) and np.array_equal(each, one)          # bit for bit
    strong = np.array([[40.0, 0.0, 0.0]])                                   # above every vehicle's max wind
    assert np.all(np.isinf(kernels.ratio_each_kernel(d[:3], strong, veh, power)))
    # through the memoised problem API: the same numbers as one direction at a time
    dirs = d[:5]
    np.testing.assert_array_equal(pr.energy_ratio_lb_dense_each(dirs),
                                  [energy_ratio_lb_dense_dirs(pr, dirs[i]) for i in range(len(dirs))])


# ------------------------------------------------------------------ BIT*


def test_bitstar_path_valid_close_to_grid_and_reproducible():
    pr = make_problem(wind=(3.0, -1.0, 0.0))
    grid_res = plan_step1(pr, "astar", 5.0)
    assert grid_res.solved
    a = plan_step1(pr, "bitstar", 5.0, seed=3, max_iterations=6000)
    b = plan_step1(pr, "bitstar", 5.0, seed=3, max_iterations=6000)
    assert a.solved
    wp = a.waypoints
    assert pr.motion_valid(wp[:-1], wp[1:]).all()
    np.testing.assert_allclose(wp[0], pr.start_xyz)
    np.testing.assert_allclose(wp[-1], pr.goal_xyz)
    np.testing.assert_array_equal(a.waypoints, b.waypoints)     # same seed + iterations: same path
    assert a.f == pytest.approx(grid_res.f, rel=0.03)
    # around the tower: longer than the straight line, no shorter than the lower bound
    assert 180.0 < a.costs["C_l"] < 200.0


# ------------------------------------------------------------------ energy loop, levels, bad input


def test_energy_replan_loop_with_tiny_battery():
    tiny = VEH.model_copy(update={"battery_capacity_mah": 10.0})   # 10 mAh * 52.8 V = 1.9 kJ
    pr = make_problem(vehicle=tiny, weights=(1, 1, 1, 1))
    refused = plan_step1(pr, "astar", 5.0, max_tries=3, energy_refusal=True)   # the bound: before any search
    assert refused.status == "energy_infeasible" and refused.tries == 0 and refused.waypoints is None
    assert "refused before the search" in refused.reason
    r = plan_step1(pr, "astar", 5.0, max_tries=3, energy_refusal=False)   # the w_l re-plan loop
    assert r.status == "energy_infeasible"
    assert r.tries == 3
    assert r.energy_J >= refused.info["energy_bound_j"]
    assert [t["weights"][0] for t in r.info["tries"]] == [1.0, 2.0, 4.0]
    assert "more than the battery" in r.reason and r.energy_J > tiny.battery_energy_j
    ok = plan_step1(make_problem(), "astar", 5.0, max_tries=3)
    assert ok.status == "solved" and ok.tries == 1 and ok.energy_J < VEH.battery_energy_j


def test_level_with_start_below_coverage_floor_has_no_solution():
    g, _ = _surface()
    cov_hi = np.full(g.shape, 40.0)        # D1: covered only above 40 m; the start is at 20 m
    cov_lo = np.full(g.shape, 5.0)
    levels = [make_problem(coverage=cov_hi, dop_threshold=2.0, check_endpoints=False),
              make_problem(coverage=cov_lo, dop_threshold=3.0, check_endpoints=False)]
    res = step1_all_levels(levels, "astar", 5.0)
    assert res[0].status == "no_solution" and res[0].waypoints is None
    assert "below GNSS coverage floor for PDOP < 2" in res[0].reason and "start" in res[0].reason
    assert res[1].status == "solved"
    with pytest.raises(PlanningError, match="below GNSS coverage floor for PDOP < 2"):
        make_problem(coverage=cov_hi, dop_threshold=2.0)


def test_bad_inputs():
    with pytest.raises(InputError, match="must be finite and >= 0"):
        make_problem(weights=(1, -1, 0, 0))
    with pytest.raises(InputError, match="all zero"):
        make_problem(weights=(0, 0, 0, 0))
    pr = make_problem()
    with pytest.raises(UnknownNameError, match="known planners: astar, .*bitstar.*, eeastar"):
        plan_step1(pr, "rrtstar", 5.0)
    with pytest.raises(InputError, match="time budget"):
        plan_step1(pr, "astar", 0.0)
    with pytest.raises(PlanningError, match="start .*inside obstacle clearance"):
        make_problem(start=(100, 50, 20))
    with pytest.raises(PlanningError, match="goal .*outside the planning area"):
        make_problem(goal=(500, 50, 20))


def test_grid_planner_refinement_never_increases_f():
    pr = make_problem(wind=(2.0, 2.0, 0.0))
    raw = plan_grid(pr, refine=False)
    ref = plan_grid(pr, refine=True)
    f_raw = pr.path_costs(raw["waypoints"])["f"]
    f_ref = pr.path_costs(ref["waypoints"])
    assert f_ref["valid"] and f_ref["f"] <= f_raw + 1e-9
    assert f_raw == pytest.approx(raw["lattice_f"], rel=1e-12)


# ------------------------------------------------------------------ whole-plan performance features


def test_shared_heuristic_of_the_loosest_level_keeps_the_lattice_optimum():
    # two nested coverage levels: the strict one forbids z < 30 m over the west half
    g, _ = _surface(120.0, 60.0)
    cov_strict = np.where(g.x[None, :] < 60.0, 30.0, 5.0) * np.ones(g.shape)
    kw = dict(size=(120.0, 60.0), start=(8, 30, 40), goal=(112, 30, 20), wind=(3.0, 1.0, 0.0), block=False,
              weights=(1, 2, 1, 1))
    strict = make_problem(coverage=cov_strict, dop_threshold=2.0, **kw)
    loose = make_problem(coverage=np.full(g.shape, 5.0), dop_threshold=4.0, **kw)
    h2 = shared_heuristic(loose, step_cells=4, dz_m=2.0)
    lat = make_lattice(strict, step_cells=4, dz_m=2.0)
    assert np.all(h2 <= heuristic_2d(strict, lat) + 1e-9)          # weaker, never stronger
    shared = astar(strict, lat, h2=h2)
    ref = _dijkstra_oracle(strict, lat)
    assert shared["f"] == pytest.approx(ref, rel=1e-9)              # still the exact lattice optimum
    assert shared["f"] == pytest.approx(astar(strict, lat)["f"], rel=1e-9)
    with pytest.raises(InputError, match="h2 has shape"):
        astar(strict, lat, h2=np.zeros((2, 2)))


def test_bitstar_default_stop_is_a_reproducible_iteration_count():
    pr = make_problem(wind=(3.0, -1.0, 0.0))
    a = plan_step1(pr, "bitstar", 0.25, seed=5)
    b = plan_step1(pr, "bitstar", 0.25, seed=5)
    n = bitstar_iterations(0.25)
    assert n == math.ceil(BITSTAR_ITERATIONS_PER_S * 0.25)
    assert a.info["tries"][0]["iterations"] == n and a.info["tries"][0]["stopped_by"] == "iterations"
    assert a.solved and pr.motion_valid(a.waypoints[:-1], a.waypoints[1:]).all()
    np.testing.assert_array_equal(a.waypoints, b.waypoints)


def _plan_inputs(floors: list[np.ndarray], thresholds: list[float]):
    g, ds = _surface(200.0, 100.0)
    clear = np.zeros(g.shape)
    clear[10:40, 40:60] = 70.0
    clearance = xr.Dataset({"min_altitude_m": g.dataarray(clear, "min_altitude_m", units="m")})
    cov = xr.concat([g.dataarray(f, "coverage_floor", units="m") for f in floors], dim="threshold")
    coverage = xr.Dataset({"coverage_floor": cov.assign_coords(threshold=thresholds)})
    return ds, clearance, coverage


def _strategic(ds, clearance, coverage, **kw):
    return plan_levels(ds, None, None, clearance, coverage, None, None, start_xy=(10, 50), start_agl_m=20.0,
                          goal_xy=(190, 50), goal_agl_m=20.0, start_time_utc="2020-01-03T10:00:00Z",
                          planner="astar", min_agl_m=0.0, max_agl_m=80.0, step_cells=4, **kw)


def test_strategic_plan_is_deterministic_and_independent_of_workers_and_level_sharing():
    g, _ = _surface()
    low = np.full(g.shape, 5.0)
    mid = np.where(g.y[:, None] > 70.0, 45.0, 5.0) * np.ones(g.shape)   # D=2.5: north strip needs z >= 45 m
    ds, clearance, coverage = _plan_inputs([mid, low, low], [2.5, 3.0, 4.0])
    seq = _strategic(ds, clearance, coverage, workers=1)
    par = _strategic(ds, clearance, coverage, workers=3)
    assert [c.label for c in seq.candidates] == ["D=2.5", "D=3", "D=4"]
    for a, b in zip(seq.candidates, par.candidates, strict=True):
        assert a.f == b.f and a.label == b.label
        np.testing.assert_array_equal(a.xyz_m, b.xyz_m)
    # D=4 has the same floors as D=3: solved once, relabelled, and equal to solving it alone
    assert seq.step1[2] is not seq.step1[1] and seq.step1[2].label == "D=4"
    np.testing.assert_array_equal(seq.step1[2].waypoints, seq.step1[1].waypoints)
    alone = _strategic(*_plan_inputs([low], [4.0]), workers=1)
    assert alone.candidates[0].f == seq.candidates[2].f
    np.testing.assert_array_equal(alone.candidates[0].xyz_m, seq.candidates[2].xyz_m)
    np.testing.assert_array_equal(alone.step1[0].waypoints, seq.step1[2].waypoints)
    # the shared A* heuristic does not change a level's result either
    alone_mid = _strategic(*_plan_inputs([mid], [2.5]), workers=1)
    np.testing.assert_array_equal(alone_mid.step1[0].waypoints, seq.step1[0].waypoints)
    with pytest.raises(InputError, match="workers 0 must be >= 1"):
        _strategic(ds, clearance, coverage, workers=0)


# ------------------------------------------------------------------ kernels and bound memo


def test_bitstar_entry_points_agree_with_the_energy_module():
    """The compiled entry points the OMPL callbacks call (kernels.entry_point, no numba type
    dispatch) give the costs of the numpy energy model and the validity of state_valid."""
    from skyroute.stages.energy import segment_energy
    from skyroute.stages.planning.kernels import OK, entry_point, segment_eval, state_code

    wind = (4.0, -2.0, 0.5)
    pr = make_problem(block=True, wind=wind)
    buf = np.empty(6)
    seg = entry_point(segment_eval, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, True, *pr.seg_args, buf)
    st = entry_point(state_code, 0.0, 0.0, 0.0, *pr.state_args)
    rng = np.random.default_rng(7)
    p0 = np.column_stack([rng.uniform(0, 200, 60), rng.uniform(0, 100, 60), rng.uniform(5, 75, 60)])
    p1 = np.column_stack([rng.uniform(0, 200, 60), rng.uniform(0, 100, 60), rng.uniform(5, 75, 60)])
    ref = segment_energy(p0, p1, lambda pts: np.tile(wind, (len(pts), 1)), VEH, subsegment_m=10.0)
    valid = pr.motion_valid(p0, p1)
    assert 0 < valid.sum() < valid.size             # the tower blocks some of them
    for i in range(p0.shape[0]):
        code = seg(*p0[i], *p1[i], True, *pr.seg_args, buf)
        assert (code == OK) == valid[i]
        assert buf[0] == pytest.approx(ref["length_m"][i], abs=1e-9)                 # [m]
        if ref["flyable"][i]:
            assert buf[4] == pytest.approx(ref["energy_J"][i], rel=1e-10)          # [J]
            assert buf[5] == pytest.approx(ref["time_s"][i], rel=1e-10)            # [s]
        assert (st(*p0[i], *pr.state_args) == OK) == bool(pr.state_valid(p0[i])[0])


def test_bound_memo_computes_once_and_stays_bounded():
    import threading

    from skyroute.stages.planning.heuristic import BoundMemo

    memo = BoundMemo(limit=4)
    calls: list[str] = []
    assert memo.get("a", lambda: calls.append("a") or 1.5) == 1.5
    assert memo.get("a", lambda: calls.append("a") or 9.0) == 1.5      # a hit does not recompute
    assert calls == ["a"]
    results: dict[int, float] = {}

    def worker(i: int) -> None:
        results[i] = memo.get(f"k{i % 10}", lambda: float(i % 10) ** 2)

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(40)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(v == float(i % 10) ** 2 for i, v in results.items())
    assert len(memo) <= memo.limit + 1                                  # cleared when full


# ------------------------------------------------------------------ reproducible budgets (issue 23)


def _burn_cpus(n: int):
    """``n`` processes that burn a CPU each until killed."""
    import subprocess
    import sys

    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


@pytest.mark.parametrize("planner,budget", [("astar", 5.0), ("bitstar", 0.25), ("potential", 5.0)])
def test_same_plan_bit_for_bit_on_an_idle_and_a_cpu_loaded_machine(planner, budget):
    """Every planner stops on counted work: planned once alone and once beside CPU-burning
    processes (one per core and one more), the plan is the same to the last bit, and neither
    run reached the wall-clock safety net."""
    import os

    pr = make_problem(wind=(3.0, -1.0, 0.0))
    idle = plan_step1(pr, planner, budget, seed=3)
    burners = _burn_cpus((os.cpu_count() or 2) + 1)
    try:
        loaded = plan_step1(pr, planner, budget, seed=3)
    finally:
        for p in burners:
            p.kill()
            p.wait()
    assert idle.solved and loaded.solved
    assert idle.info.get("stopped_by") != "time" and loaded.info.get("stopped_by") != "time"
    np.testing.assert_array_equal(idle.waypoints, loaded.waypoints)
    assert idle.f == loaded.f


def test_work_clock_and_stop_flag_do_not_count_jit_compilation():
    """A deadline on the work clock excludes numba compilation: a StopFlag of 0.05 s around the
    first call of a new kernel (compiling it takes far longer) is not expired after it, and does
    expire once 0.05 s of work have passed."""
    import time

    import numba

    from skyroute.stages import control

    @numba.njit(cache=False)
    def _fresh_kernel(a):      # a new function: compiled on its first call (~0.1-1 s)
        s = 0.0
        for i in range(a.size):
            s += math.sqrt(abs(a[i])) * math.sin(a[i])
        return s

    w0, c0 = time.perf_counter(), control.compile_seconds()
    with control.StopFlag(0.05) as stop:
        _fresh_kernel(np.arange(10.0))
        compiled_s = control.compile_seconds() - c0
        assert compiled_s > 0.05 and not stop.expired, (compiled_s, time.perf_counter() - w0)
        time.sleep(0.3)
        assert stop.expired
    assert control.work_clock() - control.work_clock() <= 0.0


def test_a_plan_that_hit_its_wall_clock_safety_net_is_never_cached(monkeypatch):
    """A level stopped by the wall-clock safety net is flagged in the plan, said in its warnings,
    and the plan dataset carries ``skyroute_not_cacheable``: the pipeline keeps it in memory
    only (a later run computes it again)."""
    import skyroute.stages.planning.step1 as step1_mod
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.graph import REGISTRY, Stage, register, run_pipeline
    from skyroute.pipeline.model import FrozenModel
    from skyroute.pipeline.settings import load_scenario
    from skyroute.stages.planning.strategic import plan_to_dataset

    g, _ = _surface()
    ds, clearance, coverage = _plan_inputs([np.full(g.shape, 5.0)], [3.0])
    monkeypatch.setattr(step1_mod, "LEVEL_CAP_FACTOR", 0.0)    # every level's cap is 0 s: always hit
    plan = _strategic(ds, clearance, coverage)
    assert plan.wallclock_capped and any("wall-clock cap" in w for w in plan.warnings)
    out = plan_to_dataset(plan, "EPSG:32635", "EGM96", "2020-01-03T10:00:00Z")
    assert "wall-clock safety cap" in out.attrs["skyroute_not_cacheable"]

    class _S(FrozenModel):
        n: int = 1

    register(Stage("capped_plan", lambda *, settings: out, lambda sc: _S(), inputs=()))
    try:
        import tempfile

        with tempfile.TemporaryDirectory() as d:
            cache = Cache(d)
            sc = load_scenario("helsinki-medical")
            with pytest.warns(RuntimeWarning, match="not cached"):
                r = run_pipeline(sc, cache=cache, targets=["capped_plan"])
            assert [(x.name, x.cache_hit, x.path) for x in r.records] == [("capped_plan", False, "")]
            assert cache.entries() == []
            assert r["capped_plan"].attrs["skyroute_not_cacheable"]
    finally:
        REGISTRY.pop("capped_plan", None)


def test_plan_request_gives_the_plan_of_the_keyword_call_and_resolves_the_vehicle_once(tmp_path):
    """Issue 25: plan_strategic(Maps, PlanRequest) is plan_levels with the same arguments (same chain,
    same f); the request holds the vehicle profile (a YAML path is read once, when the request
    is made: editing the file afterwards does not change the request) and hashes it by content."""
    import shutil

    from skyroute.stages.planning.request import Maps, PlanRequest

    g, _ = _surface()
    ds, clearance, coverage = _plan_inputs([np.full(g.shape, 5.0)], [3.0])
    ref = _strategic(ds, clearance, coverage)
    maps = Maps.from_datasets({"surface": ds, "clearance": clearance, "coverage": coverage})
    req = PlanRequest.of(start_xy=(10, 50), start_agl_m=20.0, goal_xy=(190, 50), goal_agl_m=20.0,
                         start_time_utc="2020-01-03T10:00:00Z", vehicle="dji-m300-rtk", planner="astar",
                         min_agl_m=0.0, max_agl_m=80.0, step_cells=4)
    got = plan_strategic(maps, req)
    assert ref.step1[0].solved
    np.testing.assert_array_equal(got.step1[0].waypoints, ref.step1[0].waypoints)
    assert got.candidates[0].f == ref.candidates[0].f and got.reason == ref.reason
    from skyroute.stages.vehicle import _catalog_dir

    yml = tmp_path / "m300.yaml"
    shutil.copy(str(_catalog_dir().joinpath("dji-m300-rtk.yaml")), yml)
    r1 = PlanRequest.of(**{**{k: getattr(req, k) for k in ("start_xy", "start_agl_m", "goal_xy", "goal_agl_m",
                                                             "start_time_utc")}, "vehicle": yml})
    h = r1.vehicle_hash()
    assert h == req.vehicle_hash()                       # same content, same hash
    yml.write_text(yml.read_text().replace("mass_kg: 6.3", "mass_kg: 9.9"))
    assert r1.vehicle_hash() == h and r1.vehicle.airframe.mass_kg == req.vehicle.airframe.mass_kg  # resolved once
    r2 = PlanRequest.of(**{k: getattr(r1, k) for k in ("start_xy", "start_agl_m", "goal_xy", "goal_agl_m",
                                                        "start_time_utc")}, vehicle=yml)
    assert r2.vehicle_hash() != h and r2.vehicle.airframe.mass_kg == 9.9
    with pytest.raises(InputError, match="lack clearance"):
        Maps.from_datasets({"surface": ds})
