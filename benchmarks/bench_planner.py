"""Whole strategic plan (every GNSS coverage level D_j, STEP I-III) on real maps: the grid
planner (lattice A* + refinement, levels in parallel threads) against OMPL BIT*, with BIT* given
a long wall-clock budget per level as the reference best f.

    python benchmarks/bench_planner.py                  # A* (1 and 2 workers) + BIT* 5 s
    python benchmarks/bench_planner.py --ref-s 60       # + BIT* 60 s per level (slow: ~3 min per case)
    python benchmarks/bench_planner.py --scenarios all  # cold `skyroute run` and plan-stage time per scenario

Cases: ``helsinki-medical`` (the scenario mission, 0.83 km) and a >= 2.5 km SW -> NE diagonal
across ``monaco-helipads`` (both points 60 m AGL, nudged to the nearest state valid on the
strictest level).  The maps (surface, clearance, environment, wind, coverage, satellites,
traffic) come from the pipeline cache (``--cache``), exactly as the ``plan`` stage gets them.

Printed: one table, one row per (case, configuration): whole-plan wall time [s], STEP I f
(eq. 11) per level, plan f (eq. 15, STEP III) per level, and both against the reference
(BIT* ``--ref-s`` per level; without it against BIT* at the scenario budget).  "BIT* 5 s wall"
is the old behaviour (wall-clock stop: not reproducible); "BIT* 5 s iter" stops on the
iteration count that stands for 5 s (:func:`~skyroute.stages.planning.step1.bitstar_iterations`).
"""

from __future__ import annotations

import argparse
import math
import os
import time
import warnings
from pathlib import Path

import numpy as np

from skyroute.pipeline.cache import Cache
from skyroute.pipeline.errors import InputError
from skyroute.pipeline.runner import run_scenario
from skyroute.pipeline.settings import load_scenario
from skyroute.pipeline.stages_builtin import _plan_settings
from skyroute.stages.planning.problem import build_problem, xyz_from_agl
from skyroute.stages.planning.strategic import plan_strategic

MAPS = ["surface", "environment", "clearance", "wind", "coverage", "satellites", "traffic"]


def case_inputs(name: str, cache: Cache):
    sc = load_scenario(name)
    t = time.perf_counter()
    maps = list(MAPS)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        while True:
            try:
                r = run_scenario(sc, cache=cache, targets=maps)
                break
            except InputError as exc:     # optional map without a data source (e.g. no traffic)
                gone = [m for m in maps[3:] if f"stage(s) {m} " in str(exc) or f" {m}," in str(exc)]
                if not gone:
                    raise
                maps = [m for m in maps if m not in gone]
    return sc, {k: (r[k] if k in maps else None) for k in MAPS}, _plan_settings(sc), time.perf_counter() - t


def strictest_problem(d: dict, s) -> object:
    """The most constrained level (smallest DOP threshold) of the case, for endpoint checks."""
    surf = d["surface"][["terrain", "surface"]].load()
    cov = d["coverage"]["coverage_floor"].load()
    p0 = xyz_from_agl(surf, *s.start_xy, s.start_agl_m)
    return build_problem(surf, d["clearance"]["min_altitude_m"].load(), cov.sel(threshold=cov["threshold"].min()),
                         None, None, None, s.vehicle, s.weights, p0, p0, s.min_agl_m, s.max_agl_m,
                         nofly=d["clearance"]["nofly"].load(), check_endpoints=False), surf


def find_valid(problem, surf, x: float, y: float, agl: float, search_m: float = 200.0) -> tuple[float, float]:
    """Nearest (x, y) to the given point whose ``agl`` state is valid on ``problem``."""
    for rad in np.arange(0.0, search_m, 4.0):
        for ang in np.linspace(0, 2 * math.pi, max(1, int(rad)), endpoint=False):
            px, py = x + rad * math.cos(ang), y + rad * math.sin(ang)
            if problem.state_valid(xyz_from_agl(surf, px, py, agl))[0]:
                return float(px), float(py)
    raise RuntimeError(f"no valid point within {search_m} m of ({x}, {y})")


def long_mission(sc, d, s, inset_m: float = 150.0, agl: float = 60.0):
    """Settings of a SW -> NE corner-to-corner mission at ``agl`` m AGL."""
    pr, surf = strictest_problem(d, s)
    xmin, ymin, xmax, ymax = sc.grid.bounds
    a = find_valid(pr, surf, xmin + inset_m, ymin + inset_m, agl)
    b = find_valid(pr, surf, xmax - inset_m, ymax - inset_m, agl)
    return s.model_copy(update={"start_xy": a, "goal_xy": b, "start_agl_m": agl, "goal_agl_m": agl,
                                "intruders": ()})


def run_plan(d: dict, s, **kw):
    from skyroute.pipeline.stages_builtin import plan_arguments
    from skyroute.stages.planning.request import Maps, PlanRequest

    request = PlanRequest.of(**{**plan_arguments(s, d["surface"]), **kw})
    t = time.perf_counter()
    result = plan_strategic(Maps.from_datasets(d), request)
    return result, time.perf_counter() - t


def _fmt(values, nd=0) -> str:
    return " ".join(f"{v:.{nd}f}" if np.isfinite(v) else "-" for v in values)


def scenario_times(names: list[str], cache_root: str) -> list[tuple]:
    """Per catalog scenario: the cold ``skyroute run`` wall time (fresh cache, a subprocess, as
    a user runs it), then the plan stage alone with the maps cached (``--force plan``, the
    stage's own time from summary.json), the slowest level's STEP I-III time against its
    wall-clock cap, and the exit code (3 = no flyable plan)."""
    import json
    import shutil
    import subprocess
    import sys
    import tempfile

    from skyroute.stages.planning.step1 import LEVEL_CAP_FACTOR

    out = []
    for name in names:
        cache = Path(cache_root) / name
        shutil.rmtree(cache, ignore_errors=True)
        with tempfile.TemporaryDirectory() as tmp:
            cmd = [sys.executable, "-m", "skyroute.pipeline.cli", "run", name, "--cache-dir", str(cache), "-q",
                   "--out", tmp]
            t = time.perf_counter()
            cold = subprocess.run(cmd, capture_output=True, text=True)
            t_cold = time.perf_counter() - t
            t = time.perf_counter()
            warm = subprocess.run([*cmd, "--force", "plan"], capture_output=True, text=True)
            t_warm = time.perf_counter() - t
            summ = json.loads((Path(tmp) / "summary.json").read_text())
        plan_s = next(r["seconds"] for r in summ["stages"] if r["name"] == "plan")
        sc = load_scenario(name)
        cap = LEVEL_CAP_FACTOR * sc.planner.time_budget_s
        levels = Cache(cache).open(Cache(cache).get("plan", next(r["key"] for r in summ["stages"]
                                                                  if r["name"] == "plan")))
        worst = float(np.nanmax(levels["compute_time_s"].values))
        out.append((name, t_cold, cold.returncode, t_warm, plan_s, worst, cap, warm.returncode,
                    summ["plan"]["status"]))
        print(f"  {name}: cold run {t_cold:.1f} s (exit {cold.returncode}), plan stage {plan_s:.1f} s, "
              f"slowest level {worst:.1f} s of its {cap:g} s cap", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenarios", default="",
                    help="comma-separated catalog scenarios (or 'all') for the cold-run / plan-stage timings "
                         "(each cold run recomputes every map: minutes)")
    ap.add_argument("--ref-s", type=float, default=0.0, help="BIT* reference budget per level [s] (0 = skip)")
    ap.add_argument("--budget-s", type=float, default=5.0, help="BIT* budget per level [s] of the compared runs")
    ap.add_argument("--cases", default="helsinki,monaco")
    ap.add_argument("--cache", default="/tmp/perf-cache", help="pipeline cache folder of the maps")
    ap.add_argument("--skip-bitstar", action="store_true", help="only the grid planner (and the reference)")
    a = ap.parse_args()
    if a.scenarios:
        from skyroute.pipeline.settings import scenario_paths

        names = list(scenario_paths()) if a.scenarios == "all" else a.scenarios.split(",")
        rows = scenario_times(names, a.cache + "-cold")
        load = os.getloadavg()
        print(f"\nload average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} on {os.cpu_count()} cores")
        print(f"{'scenario':24s} {'cold run s':>10s} {'plan stage s':>12s} {'slowest level s':>15s} "
              f"{'cap s':>6s} {'level/cap':>9s}  exit  plan")
        for name, tc, _, _, ps, worst, cap, rc, status in rows:
            print(f"{name:24s} {tc:10.1f} {ps:12.1f} {worst:15.1f} {cap:6.0f} {worst / cap:9.2f}  {rc:4d}  {status}")
        return
    cache = Cache(a.cache)
    rows = []
    b = a.budget_s
    for case in a.cases.split(","):
        name = {"helsinki": "helsinki-medical", "monaco": "monaco-helipads"}[case]
        sc, d, s, prep = case_inputs(name, cache)
        if case == "monaco":
            s = long_mission(sc, d, s)
        dist = math.dist(s.start_xy, s.goal_xy)
        print(f"# {name}: {dist:.0f} m start-goal (2-D), maps in {prep:.1f} s", flush=True)
        configs = [("astar 2 threads", {"planner": "astar", "workers": 2}),
                   ("astar 1 thread", {"planner": "astar", "workers": 1})]
        if not a.skip_bitstar:
            configs += [(f"BIT* {b:g} s wall (old)", {"planner": "bitstar", "time_budget_s": b, "max_iterations": 0}),
                        (f"BIT* {b:g} s iter", {"planner": "bitstar", "time_budget_s": b})]
        if a.ref_s:
            configs.append((f"BIT* {a.ref_s:g} s wall (ref)",
                            {"planner": "bitstar", "time_budget_s": a.ref_s, "max_iterations": 0}))
        if not rows:   # untimed warm-up: loads the compiled (numba-cached) kernels once per process
            run_plan(d, s, planner="astar", workers=1)
        res = {}
        for label, kw in configs:
            plan, t = run_plan(d, s, **kw)
            res[label] = (plan, t)
            print(f"  {label}: {t:.1f} s", flush=True)
        ref_label = configs[-1][0] if (a.ref_s or not a.skip_bitstar) else configs[0][0]
        ref = res[ref_label][0]
        ref_f1 = np.array([r.f for r in ref.step1])
        ref_f3 = np.array([c.f for c in ref.candidates])
        for label, (plan, t) in res.items():
            f1 = np.array([r.f for r in plan.step1])
            f3 = np.array([c.f for c in plan.candidates])
            rows.append((f"{case} {dist / 1000:.2f} km", label, t, _fmt(f1), _fmt(f3), _fmt(f1 / ref_f1, 3),
                         _fmt(f3 / ref_f3, 3), "".join("y" if c.flyable else "n" for c in plan.candidates)))
        print(f"  reference: {ref_label}", flush=True)
    load = os.getloadavg()
    ref_txt = f"BIT* {a.ref_s:g} s wall per level" if a.ref_s else "last configuration"
    print(f"\nload average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} on {os.cpu_count()} cores; f_ref = {ref_txt}")
    head = ("case", "planner/config", "time s", "STEP I f per level", "plan f per level", "f1/f1_ref",
            "f/f_ref", "flyable")
    w = [max(len(str(r[i])) if i != 2 else 7 for r in [*rows, head]) for i in range(len(head))]
    print("  ".join(h.ljust(w[i]) for i, h in enumerate(head)))
    for r in rows:
        cells = [r[0], r[1], f"{r[2]:.1f}", *r[3:]]
        print("  ".join(str(c).ljust(w[i]) for i, c in enumerate(cells)))


if __name__ == "__main__":
    main()
