"""Seed 002 section 4.4: a fleet of fixed-wing UAVs with the local planner over the San Gabriel DEM.

    python benchmarks/bench_fw_local.py            # 3, 4 and 5 Skywalker X8 on crossing routes
    python benchmarks/bench_fw_local.py --quick    # 3 X8 only (< 60 s)

The maps are those of the ``san-gabriel-fixedwing`` scenario (SRTM 30 m DEM, X8 clearance
floor, 50-400 m AGL, 5 m/s west wind), computed once by the pipeline (cached in ``--cache``).
N UAVs fly routes of 2.4 km crossing at one point (headings spread over 180 deg, level at 700 m
in the SRTM datum over a valley at 370-520 m), each with its own EEA* plan
(:func:`~skyroute.stages.tactical.fw_local.fly_fixedwing_fleet`), their take-offs timed so that
all plans pass the crossing point at the same moment (the worst case).  Printed per fleet: the
minimum distance of every pair by brute force every 0.05 s against S = r_i + r_j + d_c (and the
same for the plans as timed, without the local planner), the manoeuvres, and per UAV the delay
[s] and the added energy [Wh, seed 002 model] against its undisturbed flight, and the
simulation time.
"""

from __future__ import annotations

import argparse
import itertools
import time

import numpy as np

from skyroute.pipeline.cache import Cache
from skyroute.pipeline.fly_fw import crossing_routes, fleet_problems
from skyroute.pipeline.settings import load_scenario
from skyroute.stages.tactical.fw_local import brute_force_min_separation, fly_fixedwing_fleet

CENTRE = (380500.0, 3792300.0)
ALT_M = 700.0


def _planned_min(sim, cands, i, j, step=0.05):
    t = [sim.t_s[k][0] - cands[k].t_s[0] + np.asarray(cands[k].t_s) for k in (i, j)]
    x = [np.asarray(cands[k].xyz_m, float) for k in (i, j)]
    lo, hi = max(t[0][0], t[1][0]), min(t[0][-1], t[1][-1])
    tq = np.arange(lo, hi, step)
    p = [np.column_stack([np.interp(tq, t[a], x[a][:, k]) for k in range(3)]) for a in (0, 1)]
    return float(np.linalg.norm(p[0] - p[1], axis=1).min())


def run(n: int, cache: Cache) -> None:
    headings = [180.0 * k / n for k in range(n)]
    sc = load_scenario("san-gabriel-fixedwing")
    prs = fleet_problems(sc, crossing_routes(CENTRE, 1200.0, headings), cache=cache, alt_m=ALT_M)
    t0 = time.perf_counter()
    sim, cands = fly_fixedwing_fleet(prs, corridor_m=400, meet_at_xy=CENTRE)
    total = time.perf_counter() - t0
    print(f"\n== {n} Skywalker X8, headings {', '.join(f'{h:.0f}' for h in headings)} deg; plans + flight "
          f"{total:.1f} s (simulation {sim.compute_s:.1f} s, tick {sim.params.tick_s} s)")
    print(f"   ranges: obstacles {sim.params.obstacle_range_m:g} m, UAVs {sim.params.uav_range_m:g} m; "
          f"S = r_i + r_j + d_c = {sim.radius_m[0]:g} + {sim.radius_m[0]:g} + {sim.params.d_c_m:g} m")
    print("   pair        min dist [m]   planned min [m]   S [m]   lost")
    lost = 0
    for row, (i, j) in zip(brute_force_min_separation(sim), itertools.combinations(range(n), 2), strict=True):
        lost += row["lost"]
        print(f"   {row['a']}-{row['b']}   {row['min_distance_m']:12.1f}   {_planned_min(sim, cands, i, j):15.1f}"
              f"   {row['threshold_m']:5.1f}   {row['lost']}")
    print(f"   losses of separation: {lost}; manoeuvres: {len(sim.manoeuvres)} "
          f"({', '.join(sorted({m['kind'] for m in sim.manoeuvres})) or 'none'})")
    print("   UAV    take-off [s]  arrival [s]  delay [s]  added energy [Wh]  energy [Wh]")
    for k, ident in enumerate(sim.ids):
        print(f"   {ident}  {sim.t_s[k][0]:12.1f}  {sim.arrived_s[k]:11.1f}  {sim.delay_s[k]:9.1f}"
              f"  {sim.added_energy_J[k] / 3600:17.4f}  {sim.energy_J[k] / 3600:11.3f}")
    for w in sim.warnings:
        print("   warning:", w)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="3 UAVs only")
    ap.add_argument("--cache", default=None, help="stage cache folder")
    a = ap.parse_args()
    cache = Cache(a.cache)
    for n in (3,) if a.quick else (3, 4, 5):
        run(n, cache)


if __name__ == "__main__":
    main()
