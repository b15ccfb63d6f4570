"""Multi-resolution STEP I A* (issue 23): the refined path is checked against the FULL-resolution
maps and motion validator (never the coarse ones), its f against full-resolution A* on a small
synthetic city (tests/_city.py, procedural) where that finishes fast."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _city import city_maps, city_problem

from skyroute.stages.planning import multires
from skyroute.stages.planning.grid_planner import plan_grid
from skyroute.stages.planning.kernels import EPS_Z
from skyroute.stages.planning.multires import coarse_factor, coarse_problem, plan_multires
from skyroute.stages.planning.step1 import plan_step1

SIZE = (1000.0, 640.0)
NARROW = {"coarse_cell_m": 32.0, "half_width": 2}   # 32 m coarse cells, corridor 80 m each side


@pytest.fixture(scope="module")
def maps():
    return city_maps(SIZE, 2.0, seed=0)


def _samples_ok(problem, maps, wp, step_m=0.25) -> list[str]:
    """Independent check of a path on the full-resolution rasters: every point every
    ``step_m`` along it lies in the AOI, outside the no-fly discs, at or above max(clearance,
    min AGL) and at or below the 80 m AGL ceiling of its 2 m cell (flat 0 m ground)."""
    bad = []
    g = maps["grid"]
    for a, b in zip(wp[:-1], wp[1:], strict=True):
        n = max(2, int(math.ceil(np.linalg.norm(b - a) / step_m)) + 1)
        p = a + np.linspace(0, 1, n)[:, None] * (b - a)
        c = np.floor((p[:, 0] - g.x0) / g.resolution_m).astype(int)
        r = np.floor((g.y1 - p[:, 1]) / g.resolution_m).astype(int)
        if (c < 0).any() or (r < 0).any() or (c >= g.nx).any() or (r >= g.ny).any():
            bad.append("outside the AOI")
            continue
        if maps["nofly"][r, c].any():
            bad.append("in a no-fly disc")
        if (p[:, 2] < maps["clearance"][r, c] - EPS_Z).any():
            bad.append("below the clearance floor")
        if (p[:, 2] > 80.0 + EPS_Z).any():
            bad.append("above 80 m AGL")
    return bad


def test_coarse_abstraction_is_conservative(maps):
    pr, _ = city_problem(SIZE, (0.1, 0.15), (0.9, 0.85), maps=maps)
    f = coarse_factor(pr)
    assert f == 32 and f * pr.grid.resolution_m == 64.0        # 2 m cells, lattice step 8
    cp = coarse_problem(pr, f)
    assert cp.grid.shape == (-(-pr.grid.ny // f), -(-pr.grid.nx // f))
    ends = multires._endpoint_cells(cp.grid, (pr.start_xyz, pr.goal_xyz), 1)
    n_forbidden = 0
    for i in range(cp.grid.ny):
        for j in range(cp.grid.nx):
            if ends[i, j]:
                continue
            sl = (slice(i * f, (i + 1) * f), slice(j * f, (j + 1) * f))
            assert cp.floor_m[i, j] == pr.floor_m[sl].max()
            assert cp.ceiling_m[i, j] == pr.ceiling_m[sl].min()
            assert cp.risk_cost[i, j] == pr.risk_cost[sl].max()
            assert cp.landing_cost[i, j] == pr.landing_cost[sl].max()
            if maps["nofly"][sl].any():
                assert cp.floor_m[i, j] == np.inf
                n_forbidden += 1
    assert n_forbidden > 0
    # the endpoint cells are optimistic, so the valid full-resolution endpoints are valid coarse states
    assert cp.endpoint_problem() == ""


def test_refined_path_valid_on_full_maps_and_f_within_3_percent(maps):
    pr, _ = city_problem(SIZE, (0.05, 0.12), (0.95, 0.88), maps=maps)
    full = plan_grid(pr)
    mr = plan_multires(pr, **NARROW)         # a corridor much narrower than this small AOI
    wp = mr["waypoints"]
    assert wp is not None and mr["multires"]["stage"] == "conservative+optimistic"
    np.testing.assert_allclose(wp[0], pr.start_xyz)
    np.testing.assert_allclose(wp[-1], pr.goal_xyz)
    pc = pr.path_costs(wp)                  # the full-resolution problem's exact motion check
    assert pc["valid"], pc["first_invalid"]
    assert _samples_ok(pr, maps, wp) == []   # and an independent one on the full-resolution rasters
    f_full = pr.path_costs(full["waypoints"])["f"]
    ratio = pc["f"] / f_full
    assert ratio <= 1.03, ratio
    # restricting the lattice only removes paths: never below the full lattice optimum
    assert mr["lattice_f"] >= full["lattice_f"] * (1 - 1e-12)
    assert mr["multires"]["corridor_fraction"] < 0.5
    assert mr["expanded"] < full["expanded"]
    assert mr["expanded"] == mr["multires"]["coarse_expanded"] + mr["multires"]["fine_expanded"]
    # deterministic: the same plan twice
    np.testing.assert_array_equal(plan_multires(pr, **NARROW)["waypoints"], wp)
    # the default corridor and weights
    d = plan_multires(pr)
    assert pr.path_costs(d["waypoints"])["valid"] and _samples_ok(pr, maps, d["waypoints"]) == []
    assert pr.path_costs(d["waypoints"])["f"] <= 1.03 * f_full


def test_gap_narrower_than_a_coarse_cell_falls_back_and_stays_valid(maps):
    """A no-fly wall across the whole AOI with a 20 m gap: every coarse cell of the wall has a
    no-fly child, so the conservative abstraction has no path; the optimistic one does, and the
    refined path threads the gap on the full-resolution maps.  Without the optimistic path
    (``union=False``) the planner falls back on counted steps to the same result."""
    m = dict(maps)
    g = maps["grid"]
    nofly = np.zeros(g.shape, bool)
    c0 = 251                               # x = 502..506 m, inside one coarse column
    nofly[:, c0:c0 + 2] = True
    r_gap = 150                            # y rows 150..159: 20 m, not aligned on the 16-cell blocks
    nofly[r_gap:r_gap + 10, c0:c0 + 2] = False
    m["nofly"] = nofly
    pr, _ = city_problem(SIZE, (0.1, 0.5), (0.9, 0.5), maps=m)
    mr = plan_multires(pr)
    info = mr["multires"]
    assert info["stage"] == "optimistic"        # the conservative abstraction has no path
    wp = mr["waypoints"]
    assert wp is not None
    assert pr.path_costs(wp)["valid"]
    assert _samples_ok(pr, m, wp) == []
    # it crosses the wall through the gap
    gy = g.y1 - (np.array([r_gap, r_gap + 10]) * g.resolution_m)
    xw = g.x0 + c0 * g.resolution_m
    k = int(np.nonzero((wp[:-1, 0] <= xw) & (wp[1:, 0] >= xw))[0][0])
    t = (xw - wp[k, 0]) / (wp[k + 1, 0] - wp[k, 0])
    y_cross = wp[k, 1] + t * (wp[k + 1, 1] - wp[k, 1])
    assert gy[1] <= y_cross <= gy[0]
    alone = plan_multires(pr, union=False)
    assert alone["multires"]["stage"] == "optimistic" and alone["multires"]["widenings"] == 1
    assert pr.path_costs(alone["waypoints"])["valid"]


def test_step1_dispatch_by_problem_size(maps, monkeypatch):
    pr, _ = city_problem(SIZE, (0.05, 0.12), (0.95, 0.88), maps=maps)
    small = plan_step1(pr, "astar")
    assert "multires" not in small.info["tries"][0]          # below MULTIRES_MIN_CELLS: plan_grid as before
    assert pr.grid.nx * pr.grid.ny < multires.MULTIRES_MIN_CELLS
    monkeypatch.setattr(multires, "MULTIRES_MIN_CELLS", 1000)
    big = plan_step1(pr, "astar")
    info = big.info["tries"][0]["multires"]
    assert big.solved and info["stage"] == "conservative+optimistic"
    assert pr.path_costs(big.waypoints)["valid"]
    assert big.f <= 1.03 * small.f


def test_bound_memo_computes_a_key_once_across_threads():
    """The coverage levels run in parallel threads and ask for the same energy bounds: one
    thread computes a key, the others wait for its value; a failed computation is retried."""
    import threading
    import time

    from skyroute.stages.planning.heuristic import BoundMemo

    memo = BoundMemo(limit=8)
    calls: list[int] = []

    def make() -> float:
        calls.append(1)
        time.sleep(0.05)
        return 2.5

    out: list[float] = []
    threads = [threading.Thread(target=lambda: out.append(memo.get("k", make))) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert out == [2.5] * 4 and len(calls) == 1

    def fail() -> float:
        raise RuntimeError("cancelled")

    with pytest.raises(RuntimeError):
        memo.get("x", fail)
    assert memo.get("x", lambda: 7.0) == 7.0


@pytest.mark.parametrize("anchor", [None, 0.0])
def test_corridor_lattice_is_make_lattice_restricted(maps, anchor):
    """The multi-resolution search evaluates only the corridor's nodes, on the very lattice of
    make_lattice (same nodes, same validity there)."""
    from skyroute.stages.planning.grid_planner import make_lattice

    pr, _ = city_problem(SIZE, (0.05, 0.12), (0.95, 0.88), maps=maps)
    ref = make_lattice(pr, z_anchor_m=anchor)
    geo = multires.lattice_geometry(pr, z_anchor_m=anchor)
    for k in ("x", "y", "z", "start_links", "goal_links"):
        np.testing.assert_array_equal(getattr(geo, k), getattr(ref, k))
    assert (geo.step_m, geo.dz_m) == (ref.step_m, ref.dz_m) and not geo.valid.any()
    np.testing.assert_array_equal(multires.corridor_valid(pr, geo, np.ones(ref.shape[1:], bool)), ref.valid)
    cols = np.zeros(ref.shape[1:], bool)
    cols[3:9, 10:30] = True
    part = multires.corridor_valid(pr, geo, cols)
    np.testing.assert_array_equal(part, ref.valid & cols[None])


def test_strategic_plan_with_multires_passes_the_validator(maps, monkeypatch):
    """The whole strategic plan (STEP I multi-resolution, STEP II, III) on the synthetic city:
    its trajectory passes validate_plan on the full-resolution clearance, no-fly and altitude
    limits (without satellite geometry the navigation error is not checked, so the candidate
    is not chosen; the geometry is)."""
    import xarray as xr
    from _city import city_wind, street_point

    from skyroute.stages.planning.strategic import plan_levels
    from skyroute.stages.planning.validate import validate_plan

    monkeypatch.setattr(multires, "MULTIRES_MIN_CELLS", 1000)
    g = maps["grid"]
    zero = g.dataarray(np.zeros(g.shape), "terrain", units="m")
    surface = xr.Dataset({"terrain": zero, "surface": zero})
    clearance = xr.Dataset({"min_altitude_m": g.dataarray(maps["clearance"], "min_altitude_m"),
                            "nofly": g.dataarray(maps["nofly"], "nofly")})
    env = xr.Dataset({"risk_cost": g.dataarray(maps["risk"], "risk_cost"),
                      "landing_cost": g.dataarray(maps["landing"], "landing_cost")})
    s, e = street_point(maps, 0.05, 0.12), street_point(maps, 0.95, 0.88)
    plan = plan_levels(surface, env, city_wind(maps), clearance, None, None, None, start_xy=s, start_agl_m=30.0,
                          goal_xy=e, goal_agl_m=30.0, start_time_utc="2020-01-03T10:00:00Z", max_agl_m=80.0,
                          workers=1)
    assert "multires" in plan.step1[0].info["tries"][0]
    cand = plan.candidates[0]       # smoothed and retimed by STEP III (no satellites: not "chosen")
    assert plan.step1[0].solved and len(cand.t_s) > 10
    viol = validate_plan(cand, grid=g, terrain_m=np.zeros(g.shape), vehicle="dji-m300-rtk",
                         clearance_floor_m=maps["clearance"], nofly=maps["nofly"], min_agl_m=0.0, max_agl_m=80.0,
                         start_xyz=(*s, 30.0), goal_xyz=(*e, 30.0))
    assert viol == []
    # the validator is live: a floor 90 m higher everywhere is violated
    assert validate_plan(cand, grid=g, terrain_m=np.zeros(g.shape), vehicle="dji-m300-rtk",
                         clearance_floor_m=maps["clearance"] + 90.0, min_agl_m=0.0, max_agl_m=80.0)


def test_build_problem_shared_levels_identical():
    """build_problem(shared=...) (plan_levels' coverage levels) gives the problems it gives
    without it, array for array, and the levels share the arrays derived from the same maps."""
    import dataclasses

    import xarray as xr
    from _city import MAX_AGL_M, city_maps, city_wind

    from skyroute.stages.planning.problem import build_problem
    from skyroute.stages.vehicle import load_vehicle

    maps = city_maps((300.0, 240.0), seed=3)
    g = maps["grid"]
    terr = g.dataarray(np.linspace(0.0, 5.0, g.nx)[None, :].repeat(g.ny, 0), "terrain", units="m")
    ds = xr.Dataset({"terrain": terr, "surface": terr, "terrain_min": terr - 0.5})
    wind, veh = city_wind(maps, 3, step_m=100.0), load_vehicle("dji-m300-rtk")
    rng = np.random.default_rng(0)
    covers = {d: np.where(rng.random(g.shape) < 0.05, np.nan, rng.uniform(0, 40, g.shape)) for d in (2.0, 3.0, 4.0)}
    risk = np.where(rng.random(g.shape) < 0.01, np.inf, maps["risk"])
    s, e = (g.x[3], g.y[3], 30.0), (g.x[-4], g.y[-4], 30.0)

    def build(d, shared):
        return build_problem(ds, maps["clearance"], covers[d], risk, maps["landing"], wind, veh, (1, 1, 1, 1), s, e,
                             2.0, MAX_AGL_M, d, nofly=maps["nofly"], check_endpoints=False, shared=shared)

    shared: dict = {}
    together = [build(d, shared) for d in covers]
    alone = [build(d, None) for d in covers]
    for a, b in zip(together, alone, strict=True):
        for f in dataclasses.fields(a):
            x, y = getattr(a, f.name), getattr(b, f.name)
            if isinstance(x, np.ndarray):
                assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True), f.name
            elif f.name not in ("vehicle", "wind_grid", "grid"):
                assert x == y, f.name
    assert together[0].floor_m is not together[1].floor_m         # per level
    assert not np.array_equal(together[0].floor_m, together[1].floor_m)
    for name in ("terrain_m", "ceiling_m", "risk_cost", "landing_cost", "wind_uvw", "nofly"):
        assert getattr(together[0], name) is getattr(together[2], name), name
    for a, b in zip(together, alone, strict=True):          # the shared block reductions: the same coarse maps
        for opt in (False, True):
            ca, cb = coarse_problem(a, 4, optimistic=opt), coarse_problem(b, 4, optimistic=opt)
            for name in ("terrain_m", "floor_m", "ceiling_m", "risk_cost", "landing_cost"):
                assert np.array_equal(getattr(ca, name), getattr(cb, name)), name
    assert len(together[0]._block_memo) == 4 + 3   # (max, min) of 4 shared maps + 3 floors


def test_block_minmax_equals_reduceat():
    """The one-pass parallel block max / min (coarse_problem's) against numpy's reduceat, bit
    for bit: uneven last blocks, +-inf and NaN (propagates), float32 and float64, bool."""
    rng = np.random.default_rng(5)
    for shape, f in (((37, 53), 8), ((64, 64), 16), ((5, 3), 8), ((100, 17), 1)):
        for dtype in (np.float64, np.float32):
            a = rng.normal(size=shape).astype(dtype)
            a[rng.random(shape) < 0.05] = np.inf
            a[rng.random(shape) < 0.05] = -np.inf
            a[rng.random(shape) < 0.01] = np.nan
            hi, lo = multires.block_minmax(a, f)
            np.testing.assert_array_equal(hi, multires._block_reduce(a, f, np.maximum))
            np.testing.assert_array_equal(lo, multires._block_reduce(a, f, np.minimum))
            assert hi.dtype == a.dtype


def test_level_floor_kernel_equals_the_numpy_formula():
    """build_problem's one-pass level floor against the numpy expression it replaces: no-fly
    cells +inf, NaN / inf coverage floors never reachable, NaN floors propagate."""
    from skyroute.stages.planning.kernels import level_floor_kernel

    rng = np.random.default_rng(2)
    floor = rng.uniform(0, 50, (31, 47))
    floor[rng.random(floor.shape) < 0.03] = np.nan
    floor[rng.random(floor.shape) < 0.03] = np.inf
    cover = rng.uniform(0, 80, floor.shape)
    cover[rng.random(floor.shape) < 0.1] = np.nan
    cover[rng.random(floor.shape) < 0.05] = -np.inf
    nf = rng.random(floor.shape) < 0.1
    for cv in (cover, None):
        ref = floor if cv is None else np.maximum(floor, np.where(np.isfinite(cv), cv, np.inf))
        ref = np.where(nf, np.inf, ref)
        out = np.empty_like(floor)
        level_floor_kernel(floor, np.zeros((0, 0)) if cv is None else cv, nf, out)
        np.testing.assert_array_equal(out, ref)
