"""Cold vs warm run of a scenario's whole pipeline (issue 10: warm/cold < 0.2, numba caches warm).

    python benchmarks/bench_pipeline.py [SCENARIO] [--repeat N] [--quick]

*cold*: an empty stage cache (every stage computed) with warm numba caches (the compiled
kernels are on disk: a first-ever compile is not what a user re-running a scenario waits for);
*warm*: the same cache again (every stage read from zarr, outputs unchanged).  Both are timed as
``skyroute run`` subprocesses, as a user runs them (interpreter start-up, imports, outputs
included), and printed with their ratio.  Without ``--quick`` the pipeline is also timed in
this process, stage by stage, and each warm time is the best of ``--repeat`` runs.

``--pairs N``: N (cold, warm) pairs alternating in this one run, each cold in a new empty
stage cache and its warm right after on that cache, each pair printed with its ratio and the
load average (other processes on the machine slow both alike); the numba caches are primed
first (an untimed run).

``--commands``: each of ``run``, ``plan`` (SCENARIO), ``fly`` (``--fly-scenario``, default
helsinki-tactical) and ``report`` (of a plan folder) cold (an empty stage cache: every stage
computed, every output drawn) and warm INTO A NEW FOLDER (the same cache: every stage cached,
every derived output copied from the output memo, pipeline/output_memo.py), as subprocesses,
with their ratio (issue 35 target: each < 0.10) and the load average.

``--quick`` (under 60 s on a quiet machine): one cold and one warm CLI run, no in-process
table.  A cold run that wrote numba cache files (it compiled kernels) is repeated in a new
stage cache, so the cold time never includes a compile.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path


def numba_cache_files() -> dict[str, int]:
    """The numba cache files of the skyroute package (path -> modification time [ns])."""
    import skyroute.stages

    root = Path(skyroute.stages.__file__).parent
    return {str(p): p.stat().st_mtime_ns for p in root.rglob("__pycache__/*.nb[ic]")}


def cli_run(scenario: str, cache_dir: Path, out_dir: Path) -> float:
    """Seconds of one ``skyroute run`` subprocess (wall clock)."""
    exe = [sys.executable, "-m", "skyroute.pipeline.cli", "run", scenario, "--cache-dir", str(cache_dir),
           "--out", str(out_dir), "-q"]
    t0 = time.perf_counter()
    subprocess.run(exe, check=True, capture_output=True)
    return time.perf_counter() - t0


def in_process(scenario: str, tmp: Path, repeat: int) -> None:
    """Per-stage cold and warm times of the pipeline run in this process."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.runner import run_scenario

    cache = Cache(tmp / "in-process")
    cold = run_scenario(scenario, cache=cache)
    warm = min((run_scenario(scenario, cache=cache) for _ in range(repeat)), key=lambda r: r.seconds)
    print(f"in process       {'cold [s]':>9s} {'warm [s]':>9s}")
    for c, w in zip(cold.records, warm.records, strict=True):
        print(f"  {c.name:14s} {c.seconds:9.3f} {w.seconds:9.3f}")
    print(f"  {'pipeline':14s} {cold.seconds:9.3f} {warm.seconds:9.3f}   warm/cold = {warm.seconds / cold.seconds:.3f}")


def pairs(scenario: str, n: int) -> None:
    """``n`` alternating (cold, warm) ``skyroute run`` pairs (see the module docstring)."""
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        print("priming numba caches (untimed run in a throwaway stage cache) ...", flush=True)
        cli_run(scenario, tmp / "prime", tmp / "prime-out")
        print(f"{scenario}: skyroute run, whole command (numba caches warm)")
        print(f"  {'pair':>4s} {'cold [s]':>9s} {'warm [s]':>9s} {'warm/cold':>9s}   load average (1, 5, 15 min)")
        ratios = []
        for i in range(n):
            load0 = os.getloadavg()
            cold = cli_run(scenario, tmp / f"cache{i}", tmp / f"out{i}")
            warm = cli_run(scenario, tmp / f"cache{i}", tmp / f"out{i}")
            ratios.append(warm / cold)
            load = ", ".join(f"{a:.2f}-{b:.2f}" for a, b in zip(load0, os.getloadavg(), strict=True))
            print(f"  {i + 1:4d} {cold:9.2f} {warm:9.2f} {warm / cold:9.3f}   {load}", flush=True)
        print(f"  warm/cold: min {min(ratios):.3f}, max {max(ratios):.3f}   (issue 25 target: < 0.10)")


def cli(args: list[str], cache_dir: Path) -> float:
    """Seconds of one ``skyroute ARGS --cache-dir CACHE -q`` subprocess (wall clock)."""
    exe = [sys.executable, "-m", "skyroute.pipeline.cli", *args, "--cache-dir", str(cache_dir)]
    t0 = time.perf_counter()
    subprocess.run(exe, check=True, capture_output=True)
    return time.perf_counter() - t0


def commands(scenario: str, fly_scenario: str) -> None:
    """Cold vs warm-into-a-new-folder of run, plan, fly and report (see the module docstring)."""
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        print("priming numba caches (untimed runs in a throwaway stage cache) ...", flush=True)
        cli(["run", scenario, "--out", str(tmp / "prime-run"), "-q"], tmp / "prime")
        cli(["fly", fly_scenario, "--out", str(tmp / "prime-fly"), "-q"], tmp / "prime")
        print(f"{'command':26s} {'cold [s]':>9s} {'warm [s]':>9s} {'warm/cold':>9s}   load average (1 min)")
        rows = []
        cases = [
            ("run " + scenario, lambda c, o: ["run", scenario, "--out", str(o), "-q"]),
            ("plan " + scenario, lambda c, o: ["plan", scenario, "--out", str(o), "-q"]),
            ("fly " + fly_scenario, lambda c, o: ["fly", fly_scenario, "--out", str(o), "-q"]),
        ]
        for name, argv in cases:
            cache = tmp / f"cache-{len(rows)}"
            load = os.getloadavg()[0]
            cold = cli(argv(cache, tmp / f"{len(rows)}-cold"), cache)
            warm = cli(argv(cache, tmp / f"{len(rows)}-warm"), cache)
            rows.append((name, cold, warm, load, os.getloadavg()[0]))
        # report of a plan folder (it draws the scenario's maps into the page): a first plan
        # folder's report on a new cache, then a new plan folder's report on the same cache
        cache = tmp / "cache-report"
        cli(["plan", scenario, "--out", str(tmp / "rp1"), "-q"], cache)
        load = os.getloadavg()[0]
        cold = cli(["report", str(tmp / "rp1")], cache)
        cli(["plan", scenario, "--out", str(tmp / "rp2"), "-q"], cache)
        warm = cli(["report", str(tmp / "rp2")], cache)
        rows.append((f"report (plan {scenario})", cold, warm, load, os.getloadavg()[0]))
        for name, cold, warm, l0, l1 in rows:
            print(f"{name:26s} {cold:9.2f} {warm:9.2f} {warm / cold:9.3f}   {l0:.2f}-{l1:.2f}", flush=True)
        print("(issue 35 target: warm into a new folder < 0.10 of cold)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", nargs="?", default="helsinki-medical")
    ap.add_argument("--repeat", type=int, default=3, help="warm runs; the best counts (default 3)")
    ap.add_argument("--quick", action="store_true", help="one cold and one warm CLI run only")
    ap.add_argument("--pairs", type=int, default=0, help="N alternating (cold, warm) CLI pairs, each cold on a new cache")
    ap.add_argument("--commands", action="store_true",
                    help="run, plan, fly and report: cold vs warm into a new folder")
    ap.add_argument("--fly-scenario", default="helsinki-tactical", help="the scenario --commands flies")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    if args.commands:
        commands(args.scenario, args.fly_scenario)
        return
    if args.pairs > 0:
        pairs(args.scenario, args.pairs)
        return
    repeat = 1 if args.quick else max(args.repeat, 1)
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        if not args.quick:
            print("priming numba caches (untimed run in a throwaway stage cache) ...", flush=True)
            cli_run(args.scenario, tmp / "prime", tmp / "prime-out")
            in_process(args.scenario, tmp, repeat)
        before = numba_cache_files()
        t_cold = cli_run(args.scenario, tmp / "cli", tmp / "out")
        if numba_cache_files() != before:  # that run compiled kernels: not the cold run meant here
            print(f"(the first cold run, {t_cold:.1f} s, compiled numba kernels: timing a second one)", flush=True)
            t_cold = cli_run(args.scenario, tmp / "cli2", tmp / "out2")
        t_warm = min(cli_run(args.scenario, tmp / "cli", tmp / "out") for _ in range(repeat))
        print(f"{args.scenario}: skyroute run (numba caches warm)")
        print(f"  cold, empty stage cache    {t_cold:7.2f} s")
        print(f"  warm, every stage cached   {t_warm:7.2f} s")
        print(f"  warm/cold                  {t_warm / t_cold:7.3f}   (issue 10 target: < 0.2)")


if __name__ == "__main__":
    main()
