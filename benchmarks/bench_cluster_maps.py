"""Map build of issue 23's 6 x 6 km Helsinki AOI on a REAL multi-process dask cluster (issue 23
item 3): 1 worker against 2 workers, each run on a fresh cache.

    python benchmarks/bench_cluster_maps.py                    # runs 1 2 1 2 (about 15 min)
    python benchmarks/bench_cluster_maps.py --workers 1 2      # one pair
    python benchmarks/bench_cluster_maps.py --tasks DIR        # + a task-stream summary per run
    python benchmarks/bench_cluster_maps.py --json runs.json   # + the runs as JSON (--from-json reprints)

Per run a new cluster is started as subprocesses: ``dask scheduler`` and N ``dask worker
tcp://HOST:PORT --nworkers 1 --nthreads 1`` processes, every one (and the driver) with
``NUMBA_NUM_THREADS=1``, ``OMP_NUM_THREADS=1`` (and the BLAS thread counts 1), so the ratio
measures scale-out over processes, not threads.  The driver (one more process, as ``skyroute
maps --scheduler tcp://...`` would be) first builds the maps of a small AOI (helsinki-medical)
on its own fresh cache through the same cluster: that warms numba's compiled kernels and the
imports on every worker and in the driver, and is reported as ``warmup_s``, never counted in the
map build.  Then every stage before ``plan`` (surface, environment, clearance, wind, satellites,
coverage) of the 6 km AOI (:func:`bench_city_scale.helsinki_6km_yaml`: helsinki-crosstown's
settings, 2 m cells, 3090 x 3100 cells) is computed on a FRESH cache; its time per stage
(``RunResult.records``) and in all is printed, with ``uptime``'s load average before and after
the run (other jobs on this 2-core machine dilute the ratio).  The runs alternate (1 2 1 2 ...)
so a change in the machine's load hits both worker counts; the ratio t1/t2 is of the runs'
medians per stage.  Each process's CPU seconds (``os.times``; the workers' through ``client.run``)
are printed too: on a shared machine they hardly grow with its load, and driver CPU + the busiest
worker's CPU estimates the wall time with a core per process.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

SINGLE = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
DASK = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
WORKER = [sys.executable, "-m", "distributed.cli.dask_worker"]


def load_average() -> tuple[float, float, float]:
    """The 1, 5 and 15 min load averages (``uptime``)."""
    return os.getloadavg()


def start_cluster(n_workers: int, folder: Path, env: dict) -> tuple[str, list[subprocess.Popen]]:
    """A ``dask scheduler`` and ``n_workers`` single-threaded ``dask worker`` processes: (address,
    processes).  Waits until every worker is connected."""
    from distributed import Client

    sfile = folder / "scheduler.json"
    log = open(folder / "cluster.log", "ab")   # noqa: SIM115 - kept open for the processes' lifetime
    procs = [subprocess.Popen([*DASK, "--scheduler-file", str(sfile), "--port", "0", "--no-dashboard"],
                              stdout=log, stderr=log, env=env)]
    t_end = time.monotonic() + 60
    while not sfile.exists():
        if time.monotonic() > t_end or procs[0].poll() is not None:
            stop_cluster(procs)
            raise RuntimeError(f"the dask scheduler did not start (see {folder / 'cluster.log'})")
        time.sleep(0.2)
    address = json.loads(sfile.read_text())["address"]
    procs += [subprocess.Popen([*WORKER, address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard",
                                "--local-directory", str(folder / f"worker-{i}")], stdout=log, stderr=log, env=env)
              for i in range(n_workers)]
    with Client(address, timeout="30s") as c:
        c.wait_for_workers(n_workers, timeout=120)
    return address, procs


def stop_cluster(procs: list[subprocess.Popen]) -> None:
    for p in reversed(procs):        # workers first, then the scheduler
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def _cpu_s() -> float:
    """CPU seconds (user + system) this process has used."""
    t = os.times()
    return t.user + t.system


def task_summary(stream: list[dict], t0_s: float) -> dict:
    """Per task-key prefix: tasks, compute seconds (summed), transfer seconds, first start and
    last end [s after ``t0_s``], and the busy seconds per worker (from ``get_task_stream``)."""
    prefixes: dict[str, dict] = {}
    workers: dict[str, float] = {}
    for t in stream:
        key = t["key"]
        name = key[0] if isinstance(key, (tuple, list)) else str(key)
        prefix = name.rsplit("-", 1)[0] if len(name.rsplit("-", 1)[-1]) >= 16 else name
        p = prefixes.setdefault(prefix, {"tasks": 0, "compute_s": 0.0, "transfer_s": 0.0, "start_s": 1e18,
                                         "end_s": 0.0, "longest_s": 0.0})
        p["tasks"] += 1
        for ss in t["startstops"]:
            d = ss["stop"] - ss["start"]
            if ss["action"] == "compute":
                p["compute_s"] += d
                p["longest_s"] = max(p["longest_s"], d)
                workers[t["worker"]] = workers.get(t["worker"], 0.0) + d
            elif ss["action"] == "transfer":
                p["transfer_s"] += d
            p["start_s"] = min(p["start_s"], ss["start"] - t0_s)
            p["end_s"] = max(p["end_s"], ss["stop"] - t0_s)
    return {"prefixes": dict(sorted(prefixes.items(), key=lambda kv: kv[1]["start_s"])), "worker_busy_s": workers}


def build(address: str, folder: Path, tasks: str | None) -> dict:
    """(In the driver process) warm-up on helsinki-medical, then every map stage of the 6 km AOI
    on a fresh cache through the cluster at ``address``: seconds per stage."""
    import contextlib
    import warnings

    from bench_city_scale import helsinki_6km_yaml

    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.graph import stages_for
    from skyroute.pipeline.runner import run_scenario
    from skyroute.pipeline.settings import load_scenario

    def maps_of(sc) -> list[str]:
        return [s.name for s in stages_for(sc, ["plan"]) if s.name != "plan"]

    warnings.simplefilter("ignore")
    small = load_scenario("helsinki-medical")
    t = time.perf_counter()
    run_scenario(small, cache=Cache(folder / "cache-warmup"), targets=maps_of(small), scheduler=address)
    warmup_s = time.perf_counter() - t
    sc = load_scenario(str(helsinki_6km_yaml(folder)))
    from distributed import Client, get_task_stream

    client = Client(address)
    ctx: contextlib.AbstractContextManager = get_task_stream(client) if tasks else contextlib.nullcontext()
    cpu0, driver0 = client.run(_cpu_s), _cpu_s()
    t = time.perf_counter()
    with ctx as ts:
        r = run_scenario(sc, cache=Cache(folder / "cache"), targets=maps_of(sc), scheduler=address)
    total_s = time.perf_counter() - t
    cpu1, driver1 = client.run(_cpu_s), _cpu_s()
    if tasks:
        Path(tasks).write_text(json.dumps(task_summary(ts.data, t0_s=time.time() - total_s), indent=1))
    client.close()
    assert not r.cache_hits, "the 6 km maps must be built on a fresh cache"
    return {"warmup_s": warmup_s, "total_s": total_s, "cells": sc.grid.nx * sc.grid.ny,
            "worker_cpu_s": sorted(cpu1[w] - cpu0[w] for w in cpu1), "driver_cpu_s": driver1 - driver0,
            "stages_s": {rec.name: rec.seconds for rec in r.records}}


def one_run(n_workers: int, tasks: str | None, keep: str | None) -> dict:
    env = {**os.environ, **SINGLE}
    folder = Path(tempfile.mkdtemp(prefix=f"cluster-maps-{n_workers}w-", dir=keep))
    load_before = load_average()
    address, procs = start_cluster(n_workers, folder, env)
    try:
        r = subprocess.run([sys.executable, __file__, "--build", address, str(folder),
                            *(["--tasks", tasks] if tasks else [])],
                           capture_output=True, text=True, env=env, check=False)
    finally:
        stop_cluster(procs)
    load_after = load_average()
    if r.returncode != 0:
        raise RuntimeError(f"the map build with {n_workers} worker(s) failed:\n{r.stderr[-3000:]}")
    out = json.loads(r.stdout.strip().splitlines()[-1])
    if keep is None:
        shutil.rmtree(folder, ignore_errors=True)
    return {"workers": n_workers, **out, "load_before": load_before, "load_after": load_after}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2, 1, 2],
                    help="worker counts of the runs, in order (alternate them)")
    ap.add_argument("--tasks", metavar="DIR", help="write a summary of the dask task stream per run into DIR "
                    "(per task prefix: count, compute and transfer seconds, span; busy seconds per worker)")
    ap.add_argument("--keep", metavar="DIR", help="build the caches under DIR and keep them")
    ap.add_argument("--json", metavar="FILE", help="also write the runs as JSON")
    ap.add_argument("--from-json", metavar="FILE", help="no runs: print the summary of the runs in FILE (--json)")
    ap.add_argument("--build", nargs=2, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.build:
        print(json.dumps(build(a.build[0], Path(a.build[1]), a.tasks)))
        return
    if a.from_json:
        summary(json.loads(Path(a.from_json).read_text()))
        return
    if a.tasks:
        Path(a.tasks).mkdir(parents=True, exist_ok=True)
    runs = []
    for i, n in enumerate(a.workers):
        rep = str(Path(a.tasks) / f"run{i}-{n}w.json") if a.tasks else None
        runs.append(one_run(n, rep, a.keep))
        r = runs[-1]
        print(f"run {i}: {n} worker(s): {r['total_s']:.1f} s (warm-up {r['warmup_s']:.1f} s; CPU s: driver "
              f"{r['driver_cpu_s']:.0f}, workers {', '.join(f'{c:.0f}' for c in r['worker_cpu_s'])}; load "
              f"{r['load_before'][0]:.2f} -> {r['load_after'][0]:.2f}); "
              + ", ".join(f"{k} {v:.1f}" for k, v in r["stages_s"].items()), file=sys.stderr, flush=True)
        if a.json:
            Path(a.json).write_text(json.dumps(runs, indent=1))
    summary(runs)


def summary(runs: list[dict]) -> None:
    """Print the table of the runs: median seconds per stage and worker count, t1/t2, load
    averages, CPU seconds and the CPU-bound estimate."""
    stages = list(runs[0]["stages_s"])
    counts = sorted({r["workers"] for r in runs})
    print(f"6 x 6 km Helsinki AOI, {runs[0]['cells'] / 1e6:.1f} M cells, fresh cache per run; runs "
          + " ".join(str(r["workers"]) for r in runs))
    print("| stage | " + " | ".join(f"t{n} [s] (runs)" for n in counts) + " | t1/t2 |")
    print("|---|" + "---|" * len(counts) + "---|")
    for st in [*stages, "total"]:
        med = {}
        cells = []
        for n in counts:
            ts = [r["total_s"] if st == "total" else r["stages_s"][st] for r in runs if r["workers"] == n]
            med[n] = statistics.median(ts)
            cells.append(f"{med[n]:.1f} (" + ", ".join(f"{t:.1f}" for t in ts) + ")")
        ratio = f"{med[1] / med[2]:.2f}" if 1 in med and 2 in med and med[2] > 0 else "-"
        print(f"| {st} | " + " | ".join(cells) + f" | {ratio} |")
    print("load average (1 min) before -> after each run: "
          + "; ".join(f"{r['workers']}w {r['load_before'][0]:.2f} -> {r['load_after'][0]:.2f}" for r in runs))
    print("CPU seconds of the build (user + system; the machine's load does not inflate them much): "
          + "; ".join(f"{r['workers']}w driver {r['driver_cpu_s']:.0f} + workers "
                      + " + ".join(f"{c:.0f}" for c in r["worker_cpu_s"]) for r in runs))
    est = {n: statistics.median(r["driver_cpu_s"] + max(r["worker_cpu_s"]) for r in runs if r["workers"] == n)
           for n in counts}
    print("CPU-bound estimate (driver CPU + the busiest worker's CPU: the wall time when every process has a core "
          "to itself): " + "; ".join(f"{n}w {est[n]:.0f} s" for n in counts)
          + (f"; t1/t2 {est[1] / est[2]:.2f}" if 1 in est and 2 in est else ""))
    print("warm-up (helsinki-medical maps, numba compile on the workers; not counted): "
          + "; ".join(f"{r['workers']}w {r['warmup_s']:.1f} s" for r in runs))


if __name__ == "__main__":
    main()
