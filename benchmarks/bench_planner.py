"""STEP I on real maps: lattice A* (+ refinement) vs OMPL BIT* (scenario budget) vs BIT* with a
long budget (the reference best f), for every GNSS coverage level D_j.

    python benchmarks/bench_planner.py                 # grid + BIT* at the scenario budget
    python benchmarks/bench_planner.py --ref-s 60      # + BIT* 60 s per level (slow: 3 x 60 s per case)

Cases: ``helsinki-medical`` (scenario mission, 60 m AGL) and a >= 2.5 km diagonal across
``monaco-helipads``.  Inputs: OSM surface, clearance floor (r_p), risk and landing maps
(environment stage), wind (GFS / uniform), GNSS coverage floors from the scenario almanacs.
Prints time and f per level and the ratios grid / BIT* (budget) and grid / BIT* reference.
"""

from __future__ import annotations

import argparse
import math
import time
import warnings

import numpy as np

from skyroute.pipeline.settings import load_scenario
from skyroute.stages.clearance import clearance_floor
from skyroute.stages.planning.problem import build_problem, xyz_from_agl
from skyroute.stages.planning.step1 import step1_all_levels
from skyroute.stages.surface import build_surface
from skyroute.stages.vehicle import load_vehicle


def scenario_inputs(name: str):
    sc = load_scenario(name)
    t0 = time.perf_counter()
    b = sc.data.buildings
    surf = build_surface(sc.grid, buildings_path=b.path, buildings_format=b.format,
                         storey_height_m=getattr(b, "storey_height_m", 3.0))
    veh = load_vehicle(sc.vehicle)
    clear = clearance_floor(surf["surface"], veh.r_p_m)
    notes = []
    try:
        from skyroute.stages.landing import environment_for_scenario

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            env = environment_for_scenario(sc)
        risk, land = env["risk_cost"], env["landing_cost"]
    except Exception as exc:  # noqa: BLE001 - report and fall back
        notes.append(f"environment maps failed ({exc}); risk = landing = 0")
        risk = land = None
    try:
        from skyroute.pipeline.stages_builtin import _wind_settings, wind_stage

        wind = wind_stage(surf, settings=_wind_settings(sc))
    except Exception as exc:  # noqa: BLE001
        notes.append(f"wind failed ({exc}); no wind")
        wind = None
    cons = sc.constraints
    try:
        from skyroute.stages.coverage import coverage_from_almanac

        cov = coverage_from_almanac(surf["surface"], list(sc.data.almanacs), sc.mission.start_time_utc,
                                    window_min=sc.gnss.window_min, step_min=sc.gnss.step_min,
                                    mask_deg=sc.gnss.elevation_mask_deg, thresholds=sc.gnss.dop_thresholds,
                                    dop=sc.gnss.dop_kind,
                                    ceiling_m=surf["terrain"].values + cons.max_altitude_agl_m)
        covs = [(float(t), cov["coverage_floor"].isel(threshold=i).values)
                for i, t in enumerate(cov["threshold"].values)]
    except Exception as exc:  # noqa: BLE001
        notes.append(f"coverage failed ({exc}); no GNSS floor")
        covs = [(None, None)]
    return sc, surf, veh, clear, risk, land, wind, covs, time.perf_counter() - t0, notes


def find_valid(problem_factory, x, y, agl, surf, search_m=150.0):
    """Nearest point to (x, y) whose 60 m AGL state is valid on the least constrained level."""
    pr = problem_factory(xyz_from_agl(surf, x, y, agl), xyz_from_agl(surf, x, y, agl))
    for rad in np.arange(0.0, search_m, 4.0):
        for ang in np.linspace(0, 2 * math.pi, max(1, int(rad)), endpoint=False):
            p = xyz_from_agl(surf, x + rad * math.cos(ang), y + rad * math.sin(ang), agl)
            if pr.state_valid(p)[0]:
                return p
    raise RuntimeError(f"no valid point near ({x}, {y})")


def run_case(label, sc, surf, veh, clear, risk, land, wind, covs, start, goal, budget, ref_s, seed, tries):
    cons = sc.constraints
    problems = [build_problem(surf, clear, cf, risk, land, wind, veh, sc.planner.weights, start, goal,
                              cons.min_altitude_agl_m, cons.max_altitude_agl_m, thr, dop_kind=sc.gnss.dop_kind,
                              check_endpoints=False) for thr, cf in covs]
    d = math.dist(start, goal)
    print(f"\n## {label}: {d:.0f} m start-goal, {len(problems)} level(s), grid {sc.grid.shape}")
    runs = {}
    for name, planner, b in (("grid A*", "astar", budget), (f"BIT* {budget:g}s", "bitstar", budget)) + (
            ((f"BIT* {ref_s:g}s (ref)", "bitstar", ref_s),) if ref_s else ()):
        t = time.perf_counter()
        runs[name] = (step1_all_levels(problems, planner, b, seed, tries), time.perf_counter() - t)
    print(f"{'planner':<16}{'level':<8}{'status':<18}{'f':>10}{'C_l m':>9}{'E Wh':>8}{'time s':>9}")
    for name, (res, _) in runs.items():
        for r in res:
            print(f"{name:<16}{r.label:<8}{r.status:<18}{r.f:>10.1f}{r.costs['C_l']:>9.1f}"
                  f"{r.energy_J / 3600:>8.1f}{r.compute_s:>9.2f}")
    names = list(runs)
    grid_res, grid_t = runs[names[0]]
    print(f"{'whole STEP I':<16}" + "  ".join(f"{n}: {runs[n][1]:.2f} s" for n in names))
    for other in names[1:]:
        res, tt = runs[other]
        ratios = [g.f / o.f for g, o in zip(grid_res, res, strict=True) if g.solved and o.solved]
        print(f"grid / {other}: time {grid_t / tt:.3f}, f ratio per level "
              + ", ".join(f"{x:.4f}" for x in ratios))
    return runs


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--ref-s", type=float, default=0.0, help="BIT* reference budget per level [s] (0 = skip)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cases", default="helsinki,monaco")
    a = ap.parse_args()
    for case in a.cases.split(","):
        name = {"helsinki": "helsinki-medical", "monaco": "monaco-helipads"}[case]
        sc, surf, veh, clear, risk, land, wind, covs, prep_s, notes = scenario_inputs(name)
        print(f"\n# {name}: inputs prepared in {prep_s:.1f} s" + ("".join(f"\n  note: {n}" for n in notes)))
        if case == "helsinki":
            start = xyz_from_agl(surf, *sc.point_xy(sc.mission.start), sc.mission.start.alt_agl_m)
            goal = xyz_from_agl(surf, *sc.point_xy(sc.mission.goal), sc.mission.goal.alt_agl_m)
        else:  # a >= 2.5 km diagonal, SW -> NE corner regions, 60 m AGL, nudged to valid cells
            xmin, ymin, xmax, ymax = sc.grid.bounds
            cons = sc.constraints

            def factory(s, g, surf=surf, clear=clear, risk=risk, land=land, wind=wind, veh=veh, cons=cons):
                return build_problem(surf, clear, None, risk, land, wind, veh, (1, 1, 1, 1), s, g,
                                     cons.min_altitude_agl_m, cons.max_altitude_agl_m, check_endpoints=False)

            start = find_valid(factory, xmin + 300, ymin + 300, 60.0, surf)
            goal = find_valid(factory, xmax - 300, ymax - 300, 60.0, surf)
        run_case(name, sc, surf, veh, clear, risk, land, wind, covs, start, goal, sc.planner.time_budget_s,
                 a.ref_s, a.seed, sc.planner.max_tries)


if __name__ == "__main__":
    main()
