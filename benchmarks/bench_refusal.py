"""Refusals in seconds (issue 36): STEP I on energy-infeasible missions with the energy lower
bound of :mod:`skyroute.stages.planning.energy_bound` (refused before the search) against the
old path in the same run (``plan_step1(..., energy_refusal=False)``: up to three complete
searches with a growing w_l), and the bound's tightness (bound / energy of the plan found) on
feasible missions.

    python benchmarks/bench_refusal.py                          # synthetic 6 km city (tests/_city.py)
    python benchmarks/bench_refusal.py --side-km 2 --lengths 1 1.8
    python benchmarks/bench_refusal.py --san-gabriel CACHE_DIR  # + the real 19 km san-gabriel-long mission
    python benchmarks/bench_refusal.py --json rows.json

Synthetic city: seeded street blocks, towers, no-fly discs, a varying 3-D wind map (procedural,
not real data), 2 m cells, DJI M300, weights (1, 1, 1, 1); missions SW -> NE through the AOI
centre.  A feasible mission is planned (multires STEP I, the plan stage's A*) and its energy E
compared with the bound; then the same mission with a usable battery of ``--battery-share`` x E
(a reserve that leaves less than the bound) is planned both ways.  san-gabriel-long (real SRTM
30 m DEM, 8 m/s west wind; maps built into CACHE_DIR on the first run, a few minutes): the
scenario's mission (FlyCart 30, feasible: tightness), the same mission flown into the wind
(goal -> start) and on the DJI M300 (627 Wh; both not flyable).  Before each timed plan the
memoised bounds and block reductions are forgotten (as the plan stage meets a problem); numba
compilation is done by a warm-up and never timed.  The times are noisy on a shared 2-core
machine: the ratio old / new of the same run is the figure; the load average is printed.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))


def _cold(problem) -> None:
    from bench_city_scale import _cold as cold

    cold(problem)


def _warm() -> None:
    """Compile every kernel on a small problem (not timed)."""
    from _city import city_problem

    from skyroute.stages.planning.step1 import plan_step1

    warm, _ = city_problem((400.0, 400.0), (0.1, 0.1), (0.9, 0.9))
    plan_step1(warm)
    plan_step1(warm, battery_reserve_pct=99.99)


def _step1(pr, reserve_pct: float, refusal: bool, step_cells: int) -> dict:
    from skyroute.stages.planning.step1 import plan_step1

    _cold(pr)
    t, c = time.perf_counter(), time.process_time()
    r = plan_step1(pr, battery_reserve_pct=reserve_pct, energy_refusal=refusal, step_cells=step_cells)
    return {"status": r.status, "tries": r.tries, "wall_s": time.perf_counter() - t, "cpu_s": time.process_time() - c,
            "energy_Wh": r.energy_J / 3600 if r.waypoints is not None else math.nan,
            "bound_Wh": r.info.get("energy_bound_j", math.nan) / 3600, "reason": r.reason}


def case(pr, name: str, feasible_reserve: float, battery_share: float | None, step_cells: int = 8) -> dict:
    """Tightness of the bound on ``pr`` at ``feasible_reserve`` [%], then (``battery_share``
    given) both paths at a reserve leaving ``battery_share`` x the plan's energy; (``None``)
    both paths at ``feasible_reserve`` (a mission already infeasible)."""
    from skyroute.stages.planning.energy_bound import energy_lower_bound

    load = os.getloadavg()[0]
    _cold(pr)
    t = time.perf_counter()
    lb = energy_lower_bound(pr)
    bound_s = time.perf_counter() - t
    row = {"case": name, "cells": pr.grid.nx * pr.grid.ny, "mission_km": math.dist(pr.start_xyz[:2], pr.goal_xyz[:2]) / 1e3,
           "bound_Wh": lb["bound_j"] / 3600, "ring_Wh": lb["ring_j"] / 3600, "straight_Wh": lb["straight_j"] / 3600,
           "bound_s": bound_s, "winds": lb["n_winds"], "battery_Wh": pr.vehicle.battery_energy_j / 3600}
    if battery_share is not None:
        ok = _step1(pr, feasible_reserve, True, step_cells)
        row.update(feasible_status=ok["status"], plan_Wh=ok["energy_Wh"], feasible_s=ok["wall_s"],
                   tightness=lb["bound_j"] / 3600 / ok["energy_Wh"])
        usable = battery_share * ok["energy_Wh"]
        reserve = 100.0 * (1.0 - usable * 3600 / pr.vehicle.battery_energy_j)
    else:
        reserve = feasible_reserve
    row["usable_Wh"] = pr.vehicle.battery_energy_j / 3600 * (1 - reserve / 100)
    new = _step1(pr, reserve, True, step_cells)
    old = _step1(pr, reserve, False, step_cells)
    row.update(new_status=new["status"], new_tries=new["tries"], new_s=new["wall_s"], new_cpu_s=new["cpu_s"],
               old_status=old["status"], old_tries=old["tries"], old_s=old["wall_s"], old_cpu_s=old["cpu_s"],
               old_best_Wh=old["energy_Wh"], speedup=old["wall_s"] / new["wall_s"], reason=new["reason"])
    if math.isfinite(old["energy_Wh"]):
        row["tightness_refused"] = row["bound_Wh"] / old["energy_Wh"]
    row["load_average_1min"] = max(load, os.getloadavg()[0])
    return row


def synthetic(side_km: float, lengths_km: list[float], battery_share: float) -> list[dict]:
    from _city import city_maps, city_problem

    side = side_km * 1000.0
    maps = city_maps((side, side), 2.0, seed=1)
    rows = []
    for length in lengths_km:
        d = length * 1000.0 / math.sqrt(2) / side / 2
        pr, _ = city_problem((side, side), (0.5 - d, 0.5 - d), (0.5 + d, 0.5 + d), seed=1, maps=maps)
        rows.append(case(pr, f"synthetic {side_km:g} km city, {length:g} km", 0.0, battery_share))
        print(json.dumps(rows[-1]), flush=True)
    return rows


def san_gabriel(cache_dir: str) -> list[dict]:
    """The san-gabriel-long mission (module docstring) on its cached maps, at its coverage level."""
    import numpy as np

    from skyroute.pipeline.fleet import fleet_maps
    from skyroute.pipeline.settings.io import load_scenario
    from skyroute.pipeline.stages_builtin import plan_request
    from skyroute.stages.planning.problem import build_problem, xyz_from_agl
    from skyroute.stages.vehicle import load_vehicle

    sc = load_scenario(ROOT / "catalogs" / "scenarios" / "san-gabriel-long.yaml")
    req = plan_request(sc)
    maps = fleet_maps(sc, cache_dir)
    cov = maps["coverage"]["coverage_floor"]
    thr = float(np.asarray(cov["threshold"].values).max())           # the loosest level: the one that flies
    surf = maps["surface"][["terrain", "surface"]].load()
    pr = build_problem(surf, maps["clearance"]["min_altitude_m"].load(), cov.sel(threshold=thr).load(),
                       maps["environment"]["risk_cost"].load(), maps["environment"]["landing_cost"].load(),
                       maps["wind"].load(), req.vehicle, req.weights, xyz_from_agl(surf, *req.start_xy, req.start_agl_m),
                       xyz_from_agl(surf, *req.goal_xy, req.goal_agl_m), req.min_agl_m, req.max_agl_m, thr,
                       nofly=maps["clearance"]["nofly"].load(), label=f"D={thr:g}")
    reserve = float(req.battery_reserve_pct)
    step = int(req.step_cells or 8)
    rows = []
    for name, p in (("san-gabriel-long, FlyCart 30 (feasible)", pr),
                    ("san-gabriel-long into the wind, FlyCart 30", dataclasses.replace(
                        pr, start_xyz=pr.goal_xyz, goal_xyz=pr.start_xyz)),
                    ("san-gabriel-long, DJI M300", dataclasses.replace(pr, vehicle=load_vehicle("dji-m300-rtk")))):
        row = case(p, name, reserve, None, step)
        if p is pr:
            row["tightness"] = row["bound_Wh"] / row["old_best_Wh"]
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def _table(rows: list[dict]) -> None:
    print(f"\n{'case':46s} {'km':>5s} {'bound Wh':>9s} {'plan Wh':>8s} {'tight':>6s} {'usable':>7s} "
          f"{'new':>18s} {'old':>22s} {'old/new':>8s} load")
    for r in rows:
        tight = r.get("tightness", r.get("tightness_refused", math.nan))
        plan_wh = r.get("plan_Wh", r.get("old_best_Wh", math.nan))
        print(f"{r['case']:46s} {r['mission_km']:5.1f} {r['bound_Wh']:9.1f} {plan_wh:8.1f} {tight:6.3f} "
              f"{r['usable_Wh']:7.1f} {r['new_status'][:8]:>8s} {r['new_tries']}t {r['new_s']:6.2f}s "
              f"{r['old_status'][:8]:>8s} {r['old_tries']}t {r['old_s']:7.2f}s {r['speedup']:8.1f} "
              f"{r['load_average_1min']:.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side-km", type=float, default=6.0, help="synthetic city side [km] (0: none)")
    ap.add_argument("--lengths", type=float, nargs="+", default=[1.0, 2.5, 5.0], help="mission lengths [km]")
    ap.add_argument("--battery-share", type=float, default=0.7,
                    help="the infeasible case's usable battery / the feasible plan's energy")
    ap.add_argument("--san-gabriel", metavar="CACHE_DIR", help="+ the san-gabriel-long cases (maps cached there)")
    ap.add_argument("--json", metavar="FILE", help="write the rows as JSON")
    a = ap.parse_args()
    print(f"load average {os.getloadavg()}", flush=True)
    _warm()
    rows = []
    if a.side_km > 0:
        rows += synthetic(a.side_km, a.lengths, a.battery_share)
    if a.san_gabriel:
        rows += san_gabriel(a.san_gabriel)
    _table(rows)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
