"""Seed 002 Table 2 in structure: EEA* against A* (and the exact optimum) on the San Gabriel DEM.

    python benchmarks/bench_fixedwing.py            # 30 seeded missions, 5-15 km (a few minutes)
    python benchmarks/bench_fixedwing.py --quick    # 5 missions (< 60 s with warm kernels)

The maps are those of the ``san-gabriel-fixedwing`` scenario (SRTM 30 m DEM, clearance floor of
the Skywalker X8's sphere, 50-400 m AGL, 5 m/s west wind), computed once by the pipeline (cached
in ``--cache``).  Each mission joins two random points of the AOI 5-15 km apart (1 km from its
edges, 150 m AGL; ``numpy.random.default_rng(seed)``); ``astar-fw`` (shortest path), ``eeastar``
(seed 002 Algorithm 2) and ``energy-optimal`` (exact minimum energy of the lattice) plan it on
the same lattice (:mod:`skyroute.stages.planning.fixedwing`).  Printed: per mission the energy
saved by EEA* against A* [J and %] and the gap of both to the optimum [%]; the share of missions
where EEA* is better / equal / worse (equal: within 1e-9 relative); mean and std of the saving;
the search time per plan [s] (kernels warm: an untimed warm-up plan first), and that of the
missions of 9-11 km (target < 5 s for eeastar and astar-fw).

``--bitstar-dubins N`` adds a continuous comparison: BIT* on OMPL's Dubins-airplane space
(:mod:`skyroute.stages.planning.bitstar_dubins`, shortest curve, N iterations, 120 s cap) per
mission: its length and seed-002 energy against ``astar-fw``'s and the optimum's, and whether
its samples pass the problem's state check.
"""

from __future__ import annotations

import argparse
import math
import time
import warnings

import numpy as np

from skyroute.pipeline.cache import Cache
from skyroute.pipeline.runner import run_scenario
from skyroute.pipeline.settings import load_scenario
from skyroute.stages.planning.fixedwing import plan_fixedwing
from skyroute.stages.planning.problem import build_problem, xyz_from_agl

PLANNERS = ("astar-fw", "eeastar", "energy-optimal")


def maps(cache_dir: str | None):
    """(scenario, surface, clearance, wind) of san-gabriel-fixedwing, by the pipeline."""
    sc = load_scenario("san-gabriel-fixedwing")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = run_scenario(sc, cache=Cache(cache_dir) if cache_dir else None,
                           targets=["surface", "clearance", "wind"])
    return sc, res["surface"].load(), res["clearance"].load(), res["wind"].load()


def missions(sc, n: int, seed: int, d_min: float = 5000.0, d_max: float = 15000.0, inset: float = 1000.0):
    """``n`` (start_xy, goal_xy) pairs d_min..d_max apart inside the AOI less ``inset`` [m]."""
    x0, y0, x1, y1 = sc.grid.bounds
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        a = rng.uniform([x0 + inset, y0 + inset], [x1 - inset, y1 - inset])
        b = rng.uniform([x0 + inset, y0 + inset], [x1 - inset, y1 - inset])
        if d_min <= math.dist(a, b) <= d_max:
            out.append((tuple(a), tuple(b)))
    return out


def problem_for(sc, surface, clearance, wind, start, goal, agl: float = 150.0):
    c = sc.constraints
    return build_problem(surface, clearance["min_altitude_m"], None, None, None, wind, sc.vehicle, (1, 0, 0, 0),
                         xyz_from_agl(surface, *start, agl), xyz_from_agl(surface, *goal, agl),
                         c.min_altitude_agl_m, c.max_altitude_agl_m, nofly=clearance.get("nofly"),
                         check_endpoints=False)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="5 missions instead of 30")
    ap.add_argument("--missions", type=int, default=None)
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--cache", default=None, help="stage cache folder (default: SKYROUTE_CACHE_DIR / the default)")
    ap.add_argument("--bitstar-dubins", type=int, default=0, metavar="N",
                    help="also run BIT* on the Dubins-airplane space for N iterations per mission (0: no)")
    a = ap.parse_args()
    n = a.missions or (5 if a.quick else 30)
    sc, surface, clearance, wind = maps(a.cache)
    ms = missions(sc, n, a.seed)
    print(f"san-gabriel-fixedwing maps: {sc.grid.nx} x {sc.grid.ny} cells of {sc.grid.resolution_m:g} m, vehicle "
          f"{sc.vehicle}, {n} missions (seed {a.seed}), lattice step {sc.planner.step_cells} cells")
    warm = problem_for(sc, surface, clearance, wind, *ms[0])
    for p in PLANNERS:                                    # untimed warm-up (numba cache load)
        plan_fixedwing(warm, p, step_cells=sc.planner.step_cells)
    rows, dub = [], []
    print(f"{'sim':>3} {'D km':>5} {'E A* J':>9} {'E EEA* J':>9} {'E opt J':>9} {'saved J':>8} {'saved %':>8} "
          f"{'gap EEA* %':>10} {'gap A* %':>9} {'t A* s':>7} {'t EEA* s':>8} {'t opt s':>7}")
    for i, (s, g) in enumerate(ms, 1):
        pr = problem_for(sc, surface, clearance, wind, s, g)
        e, t = {}, {}
        for p in PLANNERS:
            t0 = time.perf_counter()
            r = plan_fixedwing(pr, p, step_cells=sc.planner.step_cells)
            t[p] = time.perf_counter() - t0
            e[p] = r.energy_J if r.solved else math.nan
        d = math.dist(s, g) / 1000
        saved = e["astar-fw"] - e["eeastar"]
        pct = 100 * saved / e["astar-fw"]
        gap_e = 100 * (e["eeastar"] / e["energy-optimal"] - 1)
        gap_a = 100 * (e["astar-fw"] / e["energy-optimal"] - 1)
        rows.append((d, e["astar-fw"], e["eeastar"], e["energy-optimal"], saved, pct, gap_e, gap_a,
                     t["astar-fw"], t["eeastar"], t["energy-optimal"]))
        if a.bitstar_dubins > 0:
            from skyroute.stages.planning.bitstar_dubins import plan_bitstar_dubins

            bd = plan_bitstar_dubins(pr, 120.0, seed=a.seed, max_iterations=a.bitstar_dubins)
            la = plan_fixedwing(pr, "astar-fw", step_cells=sc.planner.step_cells).length_m
            valid = bool(pr.state_valid(bd["xyz_m"]).all()) if bd["solved"] else False
            dub.append((i, bd["length_m"], la, bd["energy_J"], e["energy-optimal"], valid, bd["compute_s"],
                        bd["iterations"]))
        print(f"{i:>3} {d:5.1f} {e['astar-fw']:9.0f} {e['eeastar']:9.0f} {e['energy-optimal']:9.0f} {saved:8.1f} "
              f"{pct:8.2f} {gap_e:10.3f} {gap_a:9.3f} {t['astar-fw']:7.2f} {t['eeastar']:8.2f} "
              f"{t['energy-optimal']:7.2f}")
    if dub:
        print("\nBIT* on the Dubins-airplane space (shortest curve) vs the lattice:")
        print(f"{'sim':>3} {'L BIT*D m':>10} {'L A* m':>8} {'E BIT*D J':>10} {'E opt J':>9} {'valid':>5} {'t s':>6} "
              f"{'iter':>5}")
        for r in dub:
            print(f"{r[0]:>3} {r[1]:10.0f} {r[2]:8.0f} {r[3]:10.0f} {r[4]:9.0f} {str(r[5]):>5} {r[6]:6.1f} {r[7]:>5}")
    m = np.array(rows, float)
    ok = np.all(np.isfinite(m[:, 1:4]), axis=1)
    m = m[ok]
    rel = m[:, 4] / m[:, 1]
    better, worse = int(np.sum(rel > 1e-9)), int(np.sum(rel < -1e-9))
    equal = len(m) - better - worse
    print(f"\nsolved by all three: {len(m)} / {n}")
    print(f"EEA* better / equal / worse than A*: {100 * better / len(m):.1f} % / {100 * equal / len(m):.1f} % / "
          f"{100 * worse / len(m):.1f} %")
    print(f"energy saved by EEA*: mean {m[:, 4].mean():.1f} J (std {m[:, 4].std(ddof=1) if len(m) > 1 else 0:.1f} J), "
          f"mean {m[:, 5].mean():.3f} % (std {m[:, 5].std(ddof=1) if len(m) > 1 else 0:.3f} %); "
          f"when better: {m[rel > 1e-9, 5].min() if better else math.nan:.3f}..{m[rel > 1e-9, 5].max() if better else math.nan:.3f} %")
    print(f"gap to the optimum: EEA* mean {m[:, 6].mean():.4f} % (max {m[:, 6].max():.4f} %), "
          f"A* mean {m[:, 7].mean():.4f} % (max {m[:, 7].max():.4f} %)")
    print(f"optimum <= EEA* and <= A* on every mission: "
          f"{bool(np.all(m[:, 3] <= m[:, 2] * (1 + 1e-12)) and np.all(m[:, 3] <= m[:, 1] * (1 + 1e-12)))}")
    print(f"search time per plan [s]: A* {m[:, 8].mean():.2f} (max {m[:, 8].max():.2f}), EEA* {m[:, 9].mean():.2f} "
          f"(max {m[:, 9].max():.2f}), optimum {m[:, 10].mean():.2f} (max {m[:, 10].max():.2f})")
    ten = (m[:, 0] >= 9) & (m[:, 0] <= 11)
    if ten.any():
        print(f"missions of 9-11 km ({int(ten.sum())}): A* {m[ten, 8].mean():.2f} s, EEA* {m[ten, 9].mean():.2f} s, "
              f"optimum {m[ten, 10].mean():.2f} s (target < 5 s for A* and EEA*)")


if __name__ == "__main__":
    main()
