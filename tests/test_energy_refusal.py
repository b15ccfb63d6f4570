"""Refusals before the search (issue 36): the energy lower bound of
:mod:`skyroute.stages.planning.energy_bound` is never above the energy of a plan that flies,
and STEP I refuses a level on it only when no plan flies.

The independent reference is the planner itself: full-resolution lattice A* (with and without
the refinement) on small synthetic cities (buildings, no-fly discs) in random winds that vary
with height and place, and STEP I's old path (three searches with a growing w_l,
``energy_refusal=False``) for the refusal decision.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).parent))
from _city import MAX_AGL_M, city_maps, street_point  # noqa: E402

from skyroute.stages.grid import Grid  # noqa: E402
from skyroute.stages.planning.energy_bound import energy_lower_bound, progress_rates  # noqa: E402
from skyroute.stages.planning.grid_planner import plan_grid  # noqa: E402
from skyroute.stages.planning.problem import build_problem  # noqa: E402
from skyroute.stages.planning.step1 import plan_step1  # noqa: E402
from skyroute.stages.vehicle import load_vehicle  # noqa: E402

SIZE = (480.0, 360.0)     # [m] at 4 m cells: 120 x 90 cells, a 32 m lattice
RES_M = 4.0
SETTINGS = settings(max_examples=12, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def maps():
    return {s: city_maps(SIZE, RES_M, seed=s) for s in range(2)}


def _wind(grid: Grid, speed_mps: float, direction_rad: float, shear: float, seed: int, step_m: float) -> xr.Dataset:
    """u, v, w (z, y, x) [m/s] on ``step_m`` columns at 0 / 15 / 40 / 100 m above ground: calm at
    the ground, ``speed_mps`` aloft, turning by ``shear`` [rad] with height, varying by place,
    small vertical winds."""
    rng = np.random.default_rng(seed)
    wg = Grid.from_bounds(grid.crs, *grid.bounds, resolution_m=step_m)
    z = np.array([0.0, 15.0, 40.0, 100.0])
    prof = np.array([0.0, 0.6, 0.9, 1.0])[:, None, None]
    sp = speed_mps * prof * rng.uniform(0.7, 1.0, (1, wg.ny, wg.nx))
    ang = direction_rad + shear * np.array([0.0, 0.3, 0.6, 1.0])[:, None, None] + rng.normal(0, 0.3, (1, wg.ny, wg.nx))
    w = rng.uniform(-0.5, 0.5, (4, wg.ny, wg.nx)) * (z[:, None, None] > 0)
    dims = ("z", "y", "x")
    ds = xr.Dataset({"u": (dims, sp * np.cos(ang)), "v": (dims, sp * np.sin(ang)), "w": (dims, w)},
                    coords={"z": z, "y": wg.y, "x": wg.x}, attrs={"horizontal_step_m": step_m})
    return ds.rio.write_crs(grid.crs)


def _problem(m: dict, start_f, goal_f, wind, alt_agl_m: float = 30.0, min_agl_m: float = 0.0):
    g = m["grid"]
    t = g.dataarray(np.zeros(g.shape), "terrain", units="m")
    ds = xr.Dataset({"terrain": t, "surface": t})
    s, e = street_point(m, *start_f), street_point(m, *goal_f)
    return build_problem(ds, m["clearance"], None, m["risk"], m["landing"], wind, load_vehicle("dji-m300-rtk"),
                         (1.0, 1.0, 1.0, 1.0), (*s, alt_agl_m), (*e, alt_agl_m), min_agl_m, MAX_AGL_M, None,
                         nofly=m["nofly"], label="synthetic city")


frac = st.floats(0.05, 0.95)
missions = st.fixed_dictionaries({
    "seed": st.integers(0, 1), "sx": frac, "sy": frac, "gx": frac, "gy": frac,
    "speed": st.floats(0.0, 13.0), "dir": st.floats(0.0, 2 * np.pi), "shear": st.floats(-1.0, 1.0),
    "wseed": st.integers(0, 1000), "wstep": st.sampled_from([40.0, 120.0, 1000.0]),
    "alt": st.floats(20.0, 60.0), "min_agl": st.sampled_from([0.0, 10.0]),
    "grid": st.sampled_from([(None, 8), (4, 2), (8, 3)]),   # (coarse factor [cells], ring [cells])
})


def _mission(maps, p):
    m = maps[p["seed"]]
    wind = _wind(m["grid"], p["speed"], p["dir"], p["shear"], p["wseed"], p["wstep"])
    return _problem(m, (p["sx"], p["sy"]), (p["gx"], p["gy"]), wind, p["alt"], p["min_agl"])


@SETTINGS
@given(p=missions)
def test_bound_never_above_the_energy_of_a_plan_that_flies(maps, p):
    """Property: over random missions, winds, coarse cells and rings, the bound <= E_w of the
    lattice A* path and of the refined path (every flyable plan the planner makes)."""
    pr = _mission(maps, p)
    if pr.endpoint_problem() or np.hypot(*np.subtract(pr.start_xyz[:2], pr.goal_xyz[:2])) < 1.0:
        return
    factor, ring = p["grid"]
    lb = energy_lower_bound(pr, factor=factor, ring=ring)
    assert lb["bound_j"] >= max(lb["ring_j"], lb["straight_j"]) - 1e-9 * lb["bound_j"]
    for refine in (False, True):
        r = plan_grid(pr, refine=refine)
        if r["waypoints"] is None:
            continue
        pc = pr.path_costs(r["waypoints"])
        if not (pc["valid"] and np.isfinite(pc["energy_J"])):
            continue
        assert lb["bound_j"] <= pc["energy_J"], (lb, pc["energy_J"], refine)
        assert lb["ring_j"] <= pc["energy_J"] and lb["straight_j"] <= pc["energy_J"]


@SETTINGS
@given(p=missions, share=st.floats(0.5, 1.6))
def test_refused_only_when_no_plan_flies_and_accepted_plans_unchanged(maps, p, share):
    """Property: with a usable battery of ``share`` x the bound, STEP I refuses before the search
    only when the old path (three searches, growing w_l) finds no flyable plan either; a level
    it does not refuse gets exactly the old result (same chain, f, energy, status)."""
    pr = _mission(maps, p)
    if pr.endpoint_problem() or np.hypot(*np.subtract(pr.start_xyz[:2], pr.goal_xyz[:2])) < 1.0:
        return
    lb = energy_lower_bound(pr)["bound_j"]
    if not (np.isfinite(lb) and lb > 0):
        return
    reserve = 100.0 * (1.0 - share * lb / pr.vehicle.battery_energy_j)
    if not 0.0 <= reserve < 100.0:
        return
    new = plan_step1(pr, battery_reserve_pct=reserve, energy_refusal=True)
    old = plan_step1(pr, battery_reserve_pct=reserve, energy_refusal=False)
    usable = pr.vehicle.battery_energy_j * (1 - reserve / 100)
    if new.tries == 0 and new.status == "energy_infeasible":        # refused on the bound
        assert lb > usable
        assert f"{lb / 3600:.1f} Wh" in new.reason and f"{usable / 3600:.1f} Wh" in new.reason
        assert old.status in ("energy_infeasible", "no_solution"), old.reason
        if old.waypoints is not None:
            assert old.energy_J >= lb
        return
    assert lb <= usable
    assert new.status == old.status and new.tries == old.tries
    assert (new.waypoints is None) == (old.waypoints is None)
    if new.waypoints is not None:
        assert new.waypoints.tobytes() == old.waypoints.tobytes()
        assert new.f == old.f and new.energy_J == old.energy_J


def test_bound_sees_the_wind_aloft_not_the_calm_at_the_ground(maps):
    """A head wind of 12 m/s above 15 m (calm at the ground) with a 20 m minimum altitude: the
    bound is well above the calm-air bound (the path cannot fly in the calm ground layer), and
    the rates of the coarse cells come from the winds at their admissible heights only."""
    m = maps[0]
    g = m["grid"]
    s, e = street_point(m, 0.1, 0.5), street_point(m, 0.9, 0.5)
    head = float(np.arctan2(s[1] - e[1], s[0] - e[0]))            # blowing from the goal to the start
    wind = _wind(g, 12.0, head, 0.0, 1, 1000.0)
    pr = _problem(m, (0.1, 0.5), (0.9, 0.5), wind, alt_agl_m=30.0, min_agl_m=20.0)
    calm = _problem(m, (0.1, 0.5), (0.9, 0.5), _wind(g, 0.0, head, 0.0, 1, 1000.0), 30.0, 20.0)
    b, b0 = energy_lower_bound(pr)["bound_j"], energy_lower_bound(calm)["bound_j"]
    assert b > 1.2 * b0
    r = plan_grid(pr)
    assert r["waypoints"] is not None
    assert b <= pr.path_costs(r["waypoints"])["energy_J"]
    rates = progress_rates(pr, 32)
    assert rates["valid"].any() and np.isfinite(rates["rates"][rates["valid"]]).all()


def test_refusal_names_the_bound_and_the_battery_and_searches_nothing(maps):
    """A mission whose bound exceeds the usable battery is refused with no try, the bound and the
    usable battery [Wh] in the reason; the old path made its three tries for the same answer."""
    m = maps[1]
    pr = _problem(m, (0.08, 0.1), (0.92, 0.9), _wind(m["grid"], 6.0, 1.0, 0.5, 3, 120.0))
    lb = energy_lower_bound(pr)["bound_j"]
    reserve = 100.0 * (1.0 - 0.8 * lb / pr.vehicle.battery_energy_j)
    new = plan_step1(pr, battery_reserve_pct=reserve, energy_refusal=True)
    old = plan_step1(pr, battery_reserve_pct=reserve, energy_refusal=False)
    assert new.status == old.status == "energy_infeasible"
    assert new.tries == 0 and new.waypoints is None and old.tries == 3
    assert "refused before the search" in new.reason and f"{lb / 3600:.1f} Wh" in new.reason
    assert new.info["energy_bound_j"] == lb and old.energy_J >= lb
