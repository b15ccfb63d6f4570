"""City-scale STEP I (issue 23): multi-resolution A* against full-resolution A* on missions of
increasing length in a SYNTHETIC city (tests/_city.py: seeded street blocks of random building
heights, towers above the 80 m AGL limit, no-fly discs, a risk map higher over buildings, a
varying 3-D wind map; procedural, not real data), 2 m cells, DJI M300, weights (1, 1, 1, 1).

    python benchmarks/bench_city_scale.py                       # sides 2 and 6 km
    python benchmarks/bench_city_scale.py --sides 2 6 12        # + 12 km (about 4 GB per case)
    python benchmarks/bench_city_scale.py --full-max-expansions 0   # multires only
    python benchmarks/bench_city_scale.py --helsinki-6km CACHE_DIR  # real maps: issue 23's 6 km AOI
    python benchmarks/bench_city_scale.py --mosaic-20km OUTDIR     # the 20 km mosaic city: map stages
    python benchmarks/bench_city_scale.py --mosaic-missions OUTDIR # its 1-15 km missions, multires vs full
    python benchmarks/bench_city_scale.py --sides 2 6 12 --json rows.json --figure city_scale.png
    python benchmarks/bench_city_scale.py --from-json rows.json --figure city_scale.png  # redraw only

Each case runs in its own process (its peak RSS is that process's ``ru_maxrss``), after a
small warm-up plan, so numba compilation is never timed; before each timed plan the memoised
energy bounds and block reductions are forgotten, so both planners start from the maps alone
(as the plan stage does).  Per case: grid cells, mission
length (straight line), multi-resolution plan time [s] (lattice, coarse A*, corridor A*,
refinement), expansions (coarse + corridor), widenings, corridor share of the lattice columns,
f (eq. 11, refined), and the same for full-resolution A* (:func:`plan_grid`) when it finishes
within ``--full-max-expansions`` node expansions (a count, not a time), with the ratio
f_multires / f_full.  A log-log fit of multires plan time against grid cells is printed; ``--figure``
draws it (both planners' times against cells, each with its fitted slope).
"""

from __future__ import annotations

import argparse
import json
import math
import os
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


def _compare(pr, full_max: int, cold=None) -> dict:
    """STEP I of ``pr`` by multires, then by full-resolution A* (stopped after ``full_max``
    expansions, a count; none when 0), each after ``cold(pr)`` (default :func:`_cold`): times
    (wall and CPU) [s], expansions, widenings, corridor share, f of each, their ratio, and
    this process's peak RSS [MiB] after each."""
    from skyroute.stages.planning.grid_planner import plan_grid
    from skyroute.stages.planning.multires import plan_multires

    cold = cold or _cold
    cold(pr)
    t, c = time.perf_counter(), time.process_time()
    mr = plan_multires(pr)
    out = {"multires_s": time.perf_counter() - t, "multires_cpu_s": time.process_time() - c,
           "multires_expanded": mr["expanded"], "widenings": mr["multires"]["widenings"],
           "stage": mr["multires"]["stage"], "corridor_fraction": mr["multires"]["corridor_fraction"]}
    if mr["waypoints"] is not None:
        pc = pr.path_costs(mr["waypoints"])
        out.update(multires_f=pc["f"], multires_valid=bool(pc["valid"]))
    out["rss_multires_MiB"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if full_max > 0:
        cold(pr)
        t, c = time.perf_counter(), time.process_time()
        fr = plan_grid(pr, max_expansions=full_max)
        out.update(full_s=time.perf_counter() - t, full_cpu_s=time.process_time() - c, full_expanded=fr["expanded"])
        if fr["waypoints"] is not None:
            out["full_f"] = pr.path_costs(fr["waypoints"])["f"]
            out["ratio"] = out.get("multires_f", math.nan) / out["full_f"]
        out["rss_MiB"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


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
    load = os.getloadavg()[0]
    out = {"side_km": side_km, "cells": pr.grid.nx * pr.grid.ny, "mission_km": straight / 1000.0,
           "maps_s": build_s, **_compare(pr, full_max)}
    out["load_average_1min"] = max(load, os.getloadavg()[0])
    return out


HELSINKI_6KM = {"bounds_lonlat": [24.890, 60.145, 24.998, 60.199],          # issue 23's AOI
                "goal": {"name": "issue 23 6 km AOI, NE (unnamed point)", "lon": 24.9960, "lat": 60.1975,
                         "alt_agl_m": 60}}


def helsinki_6km_yaml(folder: str | Path) -> Path:
    """``folder``/helsinki-6km.yaml: helsinki-crosstown widened to issue 23's 6 x 6 km AOI
    (buildings and land use only where the shipped extract has them; data paths made absolute)
    with a 5 km mission from the same start."""
    import yaml

    sc = yaml.safe_load((ROOT / "catalogs" / "scenarios" / "helsinki-crosstown.yaml").read_text())
    sc["name"] = "helsinki-6km"
    sc["aoi"]["bounds_lonlat"] = HELSINKI_6KM["bounds_lonlat"]
    sc["mission"]["goal"] = HELSINKI_6KM["goal"]
    data = ROOT / "catalogs" / "data"
    for k, v in list(sc["data"].items()):
        if isinstance(v, str) and v.startswith("../data/"):
            sc["data"][k] = str(data / v.removeprefix("../data/"))
        elif isinstance(v, dict) and str(v.get("path", "")).startswith("../data/"):
            v["path"] = str(data / v["path"].removeprefix("../data/"))
        elif isinstance(v, list):
            sc["data"][k] = [str(data / x.removeprefix("../data/")) for x in v]
    path = Path(folder) / "helsinki-6km.yaml"
    path.write_text(yaml.safe_dump(sc))
    return path


def helsinki_6km(cache_dir: str, threshold: float = 4.0, full_max: int = 3_000_000) -> dict:
    """helsinki-crosstown widened to issue 23's 6 x 6 km AOI (:func:`helsinki_6km_yaml`): the
    maps are built (or read) in ``cache_dir``, then STEP I of level D=``threshold`` by multires
    and by full-resolution A*, both cold."""
    import tempfile

    from bench_planner import case_inputs

    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.stages_builtin import plan_arguments
    from skyroute.stages.planning.problem import build_problem, xyz_from_agl

    with tempfile.TemporaryDirectory() as tmp:
        path = helsinki_6km_yaml(tmp)
        t = time.perf_counter()
        _, d, s, _ = case_inputs(str(path), Cache(cache_dir))
        maps_s = time.perf_counter() - t
    args = plan_arguments(s, d["surface"])
    surf = d["surface"][["terrain", "surface"]].load()
    cov = d["coverage"]["coverage_floor"].load()
    start = xyz_from_agl(surf, *args["start_xy"], args["start_agl_m"])
    goal = xyz_from_agl(surf, *args["goal_xy"], args["goal_agl_m"])
    pr = build_problem(surf, d["clearance"]["min_altitude_m"].load(), cov.sel(threshold=threshold),
                       d["environment"]["risk_cost"].load(), d["environment"]["landing_cost"].load(), d["wind"].load(),
                       args["vehicle"], args["weights"], start, goal, args["min_agl_m"], args["max_agl_m"], threshold,
                       nofly=d["clearance"]["nofly"].load(), check_endpoints=False)
    return {"case": f"helsinki 6 km, D={threshold:g}", "cells": pr.grid.nx * pr.grid.ny,
            "mission_km": math.dist(start[:2], goal[:2]) / 1000.0, "maps_s": maps_s, **_compare(pr, full_max)}


MOSAIC_LENGTHS_KM = (1.0, 5.0, 10.0, 15.0)


def mosaic_case(scenario: str, cache_dir: str, length_km: float, threshold: float = 4.0,
                full_max: int = 3_000_000) -> dict:
    """One mission of ``length_km`` [km] on the 20 km mosaic city (maps cached in ``cache_dir``):
    on the line of the scenario's SE -> NW mission, centred on its midpoint (downwind, so
    energy-feasible at every length), at the scenario's start height AGL, each endpoint moved to
    the nearest valid state within 200 m.  The planning window the plan stage reads first
    (:func:`~skyroute.stages.planning.window.planning_windows`, cropped lazily from the cache),
    then STEP I at D=``threshold`` by multires and by full-resolution A* (stopped after
    ``full_max`` expansions, a count) on that window, both cold, with the cached wind_bounds
    tiles attached as the plan stage attaches them."""
    import dataclasses

    import numpy as np
    from bench_planner import find_valid

    from skyroute.pipeline.fleet import fleet_maps
    from skyroute.pipeline.settings.io import load_scenario
    from skyroute.pipeline.stages_builtin import plan_request
    from skyroute.stages.gridspec import Grid
    from skyroute.stages.planning.problem import build_problem, xyz_from_agl
    from skyroute.stages.planning.window import crop_wind, planning_windows, window_box

    sc = load_scenario(scenario)
    req = plan_request(sc)
    maps = fleet_maps(sc, cache_dir)
    grid = Grid.from_dataarray(maps["surface"]["terrain"])
    a, b = np.asarray(req.start_xy, float), np.asarray(req.goal_xy, float)
    mid, u = 0.5 * (a + b), (b - a) / np.linalg.norm(b - a)
    s_xy, g_xy = mid - 500.0 * length_km * u, mid + 500.0 * length_km * u
    rows, cols = planning_windows(grid, tuple(s_xy), tuple(g_xy))[0] or (slice(0, grid.ny), slice(0, grid.nx))
    box = window_box(grid, rows, cols)
    t = time.perf_counter()
    win = {k: maps[k].isel(y=rows, x=cols) for k in ("surface", "clearance", "environment")}
    surf = win["surface"][["terrain", "surface"]].load()
    cov = maps["coverage"]["coverage_floor"].sel(threshold=threshold).isel(y=rows, x=cols).load()
    clear, nofly = win["clearance"]["min_altitude_m"].load(), win["clearance"]["nofly"].load()
    risk, land = win["environment"]["risk_cost"].load(), win["environment"]["landing_cost"].load()
    wind = crop_wind(maps["wind"], box).load()
    agl = float(req.start_agl_m)
    p0 = xyz_from_agl(surf, *s_xy, agl)
    pr = build_problem(surf, clear, cov, risk, land, wind, req.vehicle, req.weights, p0, p0, req.min_agl_m,
                       req.max_agl_m, threshold, nofly=nofly, check_endpoints=False)
    s_xy, g_xy = find_valid(pr, surf, *s_xy, agl), find_valid(pr, surf, *g_xy, agl)
    pr = dataclasses.replace(pr, start_xyz=xyz_from_agl(surf, *s_xy, agl), goal_xyz=xyz_from_agl(surf, *g_xy, agl))
    maps_s = time.perf_counter() - t
    tiles = maps["wind_bounds"].load()

    def cold(problem):
        _cold(problem)
        object.__setattr__(problem, "_ratio_tiles", tiles)

    load = os.getloadavg()[0]
    out = {"case": f"mosaic 20 km, {length_km:g} km, D={threshold:g}", "side_km": grid.nx * grid.resolution_m / 1000,
           "aoi_cells": grid.nx * grid.ny, "cells": pr.grid.nx * pr.grid.ny, "window_xy_m": [round(v) for v in box],
           "mission_km": math.dist(s_xy, g_xy) / 1000.0, "window_read_s": maps_s, **_compare(pr, full_max, cold)}
    out["load_average_1min"] = max(load, os.getloadavg()[0])
    return out


MAPS_STAGES = ("surface", "environment", "wind", "clearance", "satellites", "coverage",   # maps + coverage
               "wind_bounds")                                  # + the A* energy bound per wind tile


def _rss_mib() -> int:
    try:
        return int(Path("/proc/self/status").read_text().split("VmRSS:")[1].split()[0]) // 1024
    except (OSError, IndexError, ValueError):
        return 0


def _main_stack(depth: int = 10) -> list[str]:
    """The main thread's innermost ``depth`` frames, as "file:line function"."""
    import threading
    import traceback

    frame = sys._current_frames().get(threading.main_thread().ident)
    if frame is None:
        return []
    return [f"{Path(f.filename).name}:{f.lineno} {f.name}" for f in traceback.extract_stack(frame)[-depth:]]


def _rss_sampler(samples: list, stop, report: dict, period_s: float = 0.5, step_mib: int = 512,
                 kill_mib: int = 0) -> None:
    """Append (t [s], RSS [MiB]) of this process every ``period_s`` until ``stop`` is set.  With
    tracemalloc on, at every new RSS high ``step_mib`` above the last one, record where the memory
    is (the largest live allocations by line) and the main thread's stack; past ``kill_mib`` write
    the report and stop the process (exit 3) before the machine runs out of memory."""
    import tracemalloc

    t0 = time.perf_counter()
    last = 0
    while not stop.wait(period_s):
        rss = _rss_mib()
        samples.append((round(time.perf_counter() - t0, 1), rss))
        if rss >= last + step_mib:
            last = rss
            snap = {"t_s": samples[-1][0], "rss_MiB": rss, "stack": _main_stack()}
            if tracemalloc.is_tracing():
                top = tracemalloc.take_snapshot().statistics("lineno")[:12]
                snap["traced_MiB"] = round(tracemalloc.get_traced_memory()[0] / 2 ** 20)
                snap["largest"] = [f"{st.size / 2 ** 20:.0f} MiB in {st.count} blocks at "
                                   f"{Path(st.traceback[0].filename).name}:{st.traceback[0].lineno}" for st in top]
            report.setdefault("memory_highs", []).append(snap)
        if kill_mib and rss > kill_mib:
            report["killed"] = f"RSS {rss} MiB > {kill_mib} MiB at {samples[-1][0]} s"
            report.update(ok=False, error=f"stopped: {report['killed']} (see memory_highs)", s=samples[-1][0],
                          rss_MiB=rss)
            print(json.dumps(report), flush=True)
            os._exit(3)


def stage_child(scenario: str, stage: str, cache_dir: str) -> dict:
    """One pipeline stage of ``scenario`` (its inputs from the cache in ``cache_dir``, built before by
    earlier children): wall time [s] and this process's peak RSS [MiB] (``ru_maxrss``: the stage,
    reading its inputs and writing its zarr store)."""
    import threading

    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.runner import run_scenario

    samples: list = []
    stop = threading.Event()
    out: dict = {"stage": stage}
    if os.environ.get("BENCH_TRACEMALLOC"):
        import tracemalloc

        tracemalloc.start(1)
    threading.Thread(target=_rss_sampler, args=(samples, stop, out),
                     kwargs={"kill_mib": int(os.environ.get("BENCH_KILL_MIB", "0"))}, daemon=True).start()
    t = time.perf_counter()
    try:
        # the stage itself is computed even when cached (its inputs come from the cache)
        res = run_scenario(scenario, cache=Cache(cache_dir), targets=[stage], force=[stage])
        out["ok"] = True
        if stage == "plan":
            ds = res.datasets["plan"]
            out["plan_attrs"] = {k: str(v)[:300] for k, v in ds.attrs.items()
                                 if k in ("chosen_level", "warnings", "planning_window_xy_m", "reason")}
            out["plan_f_m"] = [round(float(v), 1) for v in ds["f"].values]
    except Exception as exc:  # reported, not raised: the benchmark goes on with the next stage
        out.update(ok=False, error=f"{type(exc).__name__}: {str(exc)[:500]}")
    stop.set()
    out["s"] = round(time.perf_counter() - t, 1)
    out["rss_MiB"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    out["rss_samples"] = samples[:: max(1, len(samples) // 40)]
    return out


def mosaic_20km(out_dir: str, plan: bool = True, side_km: float = 20.0) -> list[dict]:
    """Issue 23's benchmark city: generate the SYNTHETIC mosaic of translated real Helsinki blocks
    (``skyroute.catalogs.generate_mosaic_city``) in ``out_dir`` unless it is there, then every map
    stage of ``skyroute maps`` and ``skyroute coverage`` on a fresh cache (``out_dir/cache``), each
    in its own process (cold: its inputs from the earlier ones), then the plan stage: per stage the
    wall time, the peak RSS and the load average."""

    out = Path(out_dir)
    rows = []
    if not (out / "mosaic-city.yaml").is_file():
        t = time.perf_counter()
        r = subprocess.run([sys.executable, "-c", "import resource, sys; from skyroute.catalogs.generate_mosaic_city "
                            "import main; rc = main(sys.argv[1:]); print(resource.getrusage(resource.RUSAGE_SELF)"
                            ".ru_maxrss // 1024); sys.exit(rc)", str(out), "--side-km", f"{side_km:g}", "--seed", "0"],
                           capture_output=True, text=True, check=True)
        rows.append({"stage": "generate", "ok": True, "s": round(time.perf_counter() - t, 1),
                     "rss_MiB": int(r.stdout.strip().splitlines()[-1]), "load": os.getloadavg()})
        print(json.dumps(rows[-1]), file=sys.stderr)
    cache = out / "cache"
    # the up-front estimate (pipeline/budget.py: 350 B per cell, calibrated on whole plans) refuses
    # 1e8 cells; the stages are measured instead
    env = {**os.environ, "SKYROUTE_MAX_MEMORY": os.environ.get("SKYROUTE_MAX_MEMORY", "64G")}
    for stage in (*MAPS_STAGES, *(("plan",) if plan else ())):
        # the plan child: where its memory goes (tracemalloc, stack at every 512 MiB high) and a stop at
        # BENCH_KILL_MIB (default 11000 MiB) so that a blow-up is reported, not the machine's OOM killer
        extra = {"BENCH_TRACEMALLOC": "1", "BENCH_KILL_MIB": os.environ.get("BENCH_KILL_MIB", "11000")} if stage == "plan" else {}
        r = subprocess.run([sys.executable, __file__, "--stage-child", str(out / "mosaic-city.yaml"), stage, str(cache)],
                           capture_output=True, text=True, check=False, env={**env, **extra})
        try:
            row = json.loads(r.stdout.strip().splitlines()[-1])
        except (IndexError, json.JSONDecodeError):
            row = {"stage": stage, "ok": False, "error": f"exit {r.returncode}: {r.stderr[-800:]}"}
        row["load"] = os.getloadavg()
        rows.append(row)
        print(json.dumps(row), file=sys.stderr)
    print("| stage | ok | wall [s] | peak RSS [MiB] | load average (1, 5, 15 min) |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['stage']} | {'yes' if r.get('ok') else 'NO: ' + r.get('error', '')[:120]} | {r.get('s', '-')} | "
              f"{r.get('rss_MiB', '-')} | {', '.join(f'{x:.1f}' for x in r['load'])} |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sides", type=float, nargs="+", default=[2, 6], help="AOI sides [km] (of 2, 6, 12, 20)")
    ap.add_argument("--full-max-expansions", type=int, default=3_000_000,
                    help="full-resolution A* stops (as not finished) after this many expansions; 0: skip it")
    ap.add_argument("--json", metavar="FILE", help="write the rows as JSON (the figure is drawn from it)")
    ap.add_argument("--figure", metavar="PNG", help="draw the log-log figure of plan time against grid cells "
                    "(with the fitted slope) into PNG")
    ap.add_argument("--figure-time", choices=["cpu", "wall"], default="cpu",
                    help="the figure's time: the planning process's CPU seconds (default; hardly load-dependent) "
                         "or wall-clock seconds (the table's)")
    ap.add_argument("--from-json", metavar="FILE", help="no runs: read the rows from FILE (written by --json) "
                    "and print the table and draw the figure")
    ap.add_argument("--case", type=float, nargs=2, help=argparse.SUPPRESS)
    ap.add_argument("--helsinki-6km", metavar="CACHE_DIR",
                    help="only the real-map case: issue 23's 6 x 6 km Helsinki AOI (maps built in CACHE_DIR: "
                         "about 2 min and 3 GB the first time), level D=4, multires vs full-resolution A*")
    ap.add_argument("--mosaic-20km", metavar="OUTDIR",
                    help="issue 23's benchmark city (SYNTHETIC mosaic of translated real Helsinki blocks): generate "
                         "it in OUTDIR, build the maps and coverage on a fresh cache OUTDIR/cache stage by stage "
                         "(time, peak RSS), then plan its 15 km mission")
    ap.add_argument("--mosaic-side-km", type=float, default=20.0, help=argparse.SUPPRESS)
    ap.add_argument("--no-plan", action="store_true", help="--mosaic-20km: maps and coverage only")
    ap.add_argument("--mosaic-missions", metavar="OUTDIR",
                    help="missions of 1, 5, 10 and 15 km on the mosaic city of OUTDIR (--mosaic-20km built its maps): "
                         "multires and full-resolution A* on each planning window, each mission in its own process")
    ap.add_argument("--mosaic-case", nargs=2, help=argparse.SUPPRESS)
    ap.add_argument("--stage-child", nargs=3, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.stage_child:
        print(json.dumps(stage_child(*a.stage_child)))
        return
    if a.mosaic_20km:
        mosaic_20km(a.mosaic_20km, plan=not a.no_plan, side_km=a.mosaic_side_km)
        return
    if a.mosaic_case:
        sys.path.insert(0, str(ROOT / "benchmarks"))
        print(json.dumps(mosaic_case(str(Path(a.mosaic_case[0]) / "mosaic-city.yaml"), str(Path(a.mosaic_case[0]) / "cache"),
                                     float(a.mosaic_case[1]), full_max=a.full_max_expansions)))
        return
    if a.mosaic_missions:
        env = {**os.environ, "SKYROUTE_MAX_MEMORY": os.environ.get("SKYROUTE_MAX_MEMORY", "64G")}
        rows = [r for length in MOSAIC_LENGTHS_KM
                if (r := _child_row(["--mosaic-case", a.mosaic_missions, str(length)], a.full_max_expansions,
                                    f"mosaic mission {length} km", env))]
        if a.json:
            Path(a.json).write_text(json.dumps(rows, indent=1))
        _table(rows)
        return
    if a.helsinki_6km:
        sys.path.insert(0, str(ROOT / "benchmarks"))
        print(json.dumps(helsinki_6km(a.helsinki_6km, full_max=a.full_max_expansions), indent=1))
        return
    if a.case:
        print(json.dumps(run_case(a.case[0], a.case[1], a.full_max_expansions)))
        return
    if a.from_json:
        rows = json.loads(Path(a.from_json).read_text())
    else:
        rows = [r for side in a.sides for length in CASES.get(int(side), (min(5.0, side * 0.7),))
                if (r := _child_row(["--case", str(side), str(length)], a.full_max_expansions,
                                    f"side {side} km, mission {length} km"))]
        if a.json:
            Path(a.json).write_text(json.dumps(rows, indent=1))
    _table(rows)
    if len(rows) >= 2:
        print(f"\nlog-log slope of multires plan time against grid cells: {loglog_slope(rows, 'multires_s'):.2f} "
              f"(wall), {loglog_slope(rows, 'multires_cpu_s'):.2f} (CPU seconds)")
    if a.figure:
        figure(rows, a.figure, a.figure_time)
        print(f"figure: {a.figure}")


def _child_row(args: list[str], full_max: int, what: str, env: dict | None = None) -> dict | None:
    """One case of this script in its own process (its peak RSS is the case's): the JSON row it
    prints last, or None (the failure reported on stderr)."""
    r = subprocess.run([sys.executable, __file__, *args, "--full-max-expansions", str(full_max)],
                       capture_output=True, text=True, check=False, env=env)
    if r.returncode != 0:
        print(f"{what} failed:\n{r.stderr[-2000:]}", file=sys.stderr)
        return None
    row = json.loads(r.stdout.strip().splitlines()[-1])
    print(json.dumps(row), file=sys.stderr)
    return row


def _table(rows: list[dict]) -> None:
    """The markdown table of the rows (cells: the planned grid's, the window's on the mosaic city)."""
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


def loglog_slope(rows: list[dict], key: str) -> float:
    """Slope of the least-squares line of log(``key``) against log(cells) over ``rows`` (NaN with
    fewer than two distinct cell counts)."""
    import numpy as np

    pts = [(r["cells"], r[key]) for r in rows if r.get(key) is not None and r[key] > 0]
    if len({c for c, _ in pts}) < 2:
        return math.nan
    x, y = np.log([c for c, _ in pts]), np.log([t for _, t in pts])
    return float(np.polyfit(x, y, 1)[0])


def figure(rows: list[dict], path: str | Path, clock: str = "cpu") -> None:
    """Log-log figure of plan time [s] against grid cells: multires (every row) and
    full-resolution A* (rows where it finished), each with its least-squares line and slope;
    points labelled by AOI side and mission length.  ``clock``: "cpu" (the planning process's CPU
    seconds, when the rows have them: on a shared machine they hardly depend on its load) or
    "wall"."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(figsize=(7.5, 5.2), dpi=130)
    cpu = clock == "cpu" and all("multires_cpu_s" in r for r in rows)
    sfx = "_cpu_s" if cpu else "_s"
    series = [("multires" + sfx, "multi-resolution A*", "tab:blue", "o"),
              ("full" + sfx, "full-resolution A*", "tab:orange", "s")]
    cells = np.array([r["cells"] for r in rows], float)
    for key, label, color, marker in series:
        sel = [r for r in rows if r.get(key) is not None and (not key.startswith("full") or "full_f" in r)]
        if not sel:
            continue
        x = np.array([r["cells"] for r in sel], float)
        y = np.array([r[key] for r in sel], float)
        slope = loglog_slope(sel, key)
        ax.loglog(x, y, marker, color=color, ms=7, label=f"{label} (fitted slope {slope:.2f})"
                  if not math.isnan(slope) else label)
        if not math.isnan(slope):
            b, a0 = np.polyfit(np.log(x), np.log(y), 1)
            xs = np.geomspace(x.min() / 1.3, x.max() * 1.3, 50)
            ax.loglog(xs, np.exp(a0) * xs ** b, "-", color=color, lw=1.2, alpha=0.7)
        left = key.startswith("multires")      # multires labels left of their point, full A* right
        for cells_i in sorted({r["cells"] for r in sel}):
            group = sorted((r for r in sel if r["cells"] == cells_i), key=lambda r: r[key])
            ys = list(np.log10([r[key] for r in group]))
            for i in range(1, len(ys)):     # labels of one AOI at least 0.09 decades apart
                ys[i] = max(ys[i], ys[i - 1] + 0.09)
            for r, y in zip(group, ys, strict=True):
                ax.text(cells_i / 1.15 if left else cells_i * 1.15, 10 ** y,
                        f"{r['side_km']:g} km / {r['mission_km']:.1f} km", ha="right" if left else "left",
                        va="center", fontsize=8, color=color)
    ax.set_xlabel("grid cells of the AOI (2 m cells) [-]")
    ax.set_ylabel("STEP I plan time [s]" + (" (CPU)" if cpu else " (wall clock)"))
    ax.set_xlim(cells.min() / 4.0, cells.max() * 4.0)
    ax.set_title("City-scale STEP I on a synthetic city (issue 23): time against cells", fontsize=10)
    ax.grid(True, which="both", lw=0.4, alpha=0.5)
    ax.legend(loc="upper left", fontsize=9)
    loads = [r["load_average_1min"] for r in rows if "load_average_1min" in r]
    load = f", load average {min(loads):.1f}-{max(loads):.1f}" if loads else ""
    what = "CPU seconds of the planning process" if cpu else "wall-clock seconds"
    fig.text(0.01, 0.01, "Labels: AOI side / mission length (straight line).  SYNTHETIC city (tests/_city.py: "
             "procedural, not real data).\nBoth planners cold, compilation excluded, NUMBA_NUM_THREADS=1; "
             f"{what}\non a 2-core machine shared with other jobs{load}.", fontsize=7, color="0.3")
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(path)
    plt.close(fig)

if __name__ == "__main__":
    main()
