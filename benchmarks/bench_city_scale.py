"""City-scale STEP I (issue 23): multi-resolution A* against full-resolution A* on missions of
increasing length in a SYNTHETIC city (tests/_city.py: seeded street blocks of random building
heights, towers above the 80 m AGL limit, no-fly discs, a risk map higher over buildings, a
varying 3-D wind map; procedural, not real data), 2 m cells, DJI M300, weights (1, 1, 1, 1).

    python benchmarks/bench_city_scale.py                       # sides 2 and 6 km
    python benchmarks/bench_city_scale.py --sides 2 6 12        # + 12 km (about 4 GB per case)
    python benchmarks/bench_city_scale.py --full-max-expansions 0   # multires only

Each case runs in its own process (its peak RSS is that process's ``ru_maxrss``), after a
small warm-up plan, so numba compilation is never timed; before each timed plan the memoised
energy bounds and block reductions are forgotten, so both planners start from the maps alone
(as the plan stage does).  Per case: grid cells, mission
length (straight line), multi-resolution plan time [s] (lattice, coarse A*, corridor A*,
refinement), expansions (coarse + corridor), widenings, corridor share of the lattice columns,
f (eq. 11, refined), and the same for full-resolution A* (:func:`plan_grid`) when it finishes
within ``--full-max-expansions`` node expansions (a count, not a time), with the ratio
f_multires / f_full.  A log-log fit of multires plan time against grid cells is printed.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

# (side [km], mission [km]): missions SW -> NE through the AOI centre
CASES = {2: (1.0,), 6: (1.0, 5.0), 12: (5.0, 10.0), 20: (15.0,)}


def _fractions(side_m: float, length_m: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """AOI fractions of a diagonal mission of ``length_m`` centred in a square AOI of ``side_m``."""
    d = length_m / math.sqrt(2) / side_m / 2
    return (0.5 - d, 0.5 - d), (0.5 + d, 0.5 + d)


def _cold(problem) -> None:
    """Forget every bound and block reduction memoised for ``problem`` (both planners are timed
    as the plan stage meets a problem: maps cached, nothing derived from them yet)."""
    from skyroute.stages.planning import heuristic

    heuristic.RATIO_MEMO.clear()
    heuristic.WINDS_MEMO.clear()
    for k in [k for k in problem.__dict__ if k.startswith("_") and k != "_seg_args"]:
        del problem.__dict__[k]


def run_case(side_km: float, length_km: float, full_max: int) -> dict:
    from _city import city_problem

    from skyroute.stages.planning.grid_planner import plan_grid
    from skyroute.stages.planning.multires import plan_multires

    warm, _ = city_problem((400.0, 400.0), (0.1, 0.1), (0.9, 0.9))      # compile the kernels (not timed)
    plan_multires(warm)
    plan_grid(warm)
    side = side_km * 1000.0
    s, g = _fractions(side, length_km * 1000.0)
    t = time.perf_counter()
    pr, _ = city_problem((side, side), s, g, seed=1)
    build_s = time.perf_counter() - t
    straight = math.dist(pr.start_xyz[:2], pr.goal_xyz[:2])
    _cold(pr)
    t = time.perf_counter()
    mr = plan_multires(pr)
    mr_s = time.perf_counter() - t
    out = {"side_km": side_km, "cells": pr.grid.nx * pr.grid.ny, "mission_km": straight / 1000.0,
           "maps_s": build_s, "multires_s": mr_s, "multires_expanded": mr["expanded"],
           "widenings": mr["multires"]["widenings"], "stage": mr["multires"]["stage"],
           "corridor_fraction": mr["multires"]["corridor_fraction"]}
    if mr["waypoints"] is not None:
        pc = pr.path_costs(mr["waypoints"])
        out.update(multires_f=pc["f"], multires_valid=pc["valid"])
    out["rss_multires_MiB"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if full_max > 0:
        _cold(pr)
        t = time.perf_counter()
        fr = plan_grid(pr, max_expansions=full_max)
        out["full_s"] = time.perf_counter() - t
        out["full_expanded"] = fr["expanded"]
        if fr["waypoints"] is not None:
            out["full_f"] = pr.path_costs(fr["waypoints"])["f"]
            out["ratio"] = out.get("multires_f", math.nan) / out["full_f"]
        out["rss_MiB"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sides", type=float, nargs="+", default=[2, 6], help="AOI sides [km] (of 2, 6, 12, 20)")
    ap.add_argument("--full-max-expansions", type=int, default=3_000_000,
                    help="full-resolution A* stops (as not finished) after this many expansions; 0: skip it")
    ap.add_argument("--case", type=float, nargs=2, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.case:
        print(json.dumps(run_case(a.case[0], a.case[1], a.full_max_expansions)))
        return
    rows = []
    for side in a.sides:
        for length in CASES.get(int(side), (min(5.0, side * 0.7),)):
            r = subprocess.run([sys.executable, __file__, "--case", str(side), str(length),
                                "--full-max-expansions", str(a.full_max_expansions)],
                               capture_output=True, text=True, check=False)
            if r.returncode != 0:
                print(f"side {side} km, mission {length} km failed:\n{r.stderr[-2000:]}", file=sys.stderr)
                continue
            rows.append(json.loads(r.stdout.strip().splitlines()[-1]))
            print(json.dumps(rows[-1]), file=sys.stderr)
    print("| AOI side [km] | cells [M] | mission [km] | multires plan [s] | expansions | widenings | corridor [%] "
          "| full A* [s] | full expansions | f multires / f full | peak RSS [MiB] |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        full = (f"{r['full_s']:.1f} | {r['full_expanded']:,}" if "full_f" in r
                else ("not finished | > {:,}".format(r["full_expanded"]) if "full_s" in r else "- | -"))
        ratio = f"{r['ratio']:.4f}" if "ratio" in r else "-"
        print(f"| {r['side_km']:g} | {r['cells'] / 1e6:.1f} | {r['mission_km']:.2f} | {r['multires_s']:.1f} | "
              f"{r['multires_expanded']:,} | {r['widenings']} | {100 * r['corridor_fraction']:.1f} | {full} | {ratio} | "
              f"{r.get('rss_MiB', r['rss_multires_MiB']):.0f} |")
    import numpy as np

    if len(rows) >= 2:
        x = np.log([r["cells"] for r in rows])
        y = np.log([r["multires_s"] for r in rows])
        slope = np.polyfit(x, y, 1)[0]
        print(f"\nlog-log slope of multires plan time against grid cells: {slope:.2f}")


if __name__ == "__main__":
    main()
