"""Fleet throughput (issue 15): N missions drawn between the landing sites of helsinki-medical
over a window, planned first-come-first-served (one DOP level each, accepted intents as STEP II
traffic), sequentially in this process and then on a dask LocalCluster of 2 workers (the
speculative parallel driver); prints accepted / delayed / preempted / rejected counts, the mean
delay, the independent conflict count (pairwise shapely over the written intents: must be 0),
plans per minute and the speed-up, and checks that both runs decide the same.

    SKYROUTE_CACHE_DIR=... python benchmarks/bench_fleet.py [--quick] [--missions 1000]
        [--window-min 120] [--seed 3] [--workers 2] [--no-parallel] [--configs 4:speculative,1:none]
        [--scenario helsinki-crosstown] [--min-km 0.2] [--max-km 1.5] [--dask-processes]

``--dask-processes`` (issue 26 item 3): instead of a LocalCluster, start a real ``dask scheduler``
(scheduler file) and ``--workers`` single-threaded ``dask worker`` processes (``--no-nanny``,
``NUMBA_NUM_THREADS=1``), as a user's cluster would be, and run every config on them.  Each
parallel run must decide exactly as the sequential one (mission, status, delay, attempts, the
intent documents: asserted); the load average of the machine is printed before and after each
run (the cores are shared).

Full run: 1000 missions over 2 hours (target >= 100 plans/min on 2 cores, maps cached).
--quick: 4 missions over 10 min (about 30 s once the maps are cached).  ``--configs``: the
parallel runs to make, DEPTH:AFFINITY each (speculative missions in flight; which attempts
prefer the worker of their goal, see :func:`skyroute.pipeline.fleet.run_fleet`).  The
sequential run's plans/min counts every planning attempt (first tries and later departures).  The maps come from the stage cache (computed on the first run).  The clock starts
after the maps are loaded (and, on the cluster, after each worker has loaded them and planned
one mission to load the kernels: ``worker_setup_s``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


@contextlib.contextmanager
def dask_processes(n_workers: int, cache_root: Path, tmp: Path):
    """A ``dask scheduler`` and ``n_workers`` single-threaded ``dask worker`` processes (as
    tests/test_cluster.py starts them); yields a connected Client, kills them all on exit."""
    from distributed import Client

    tmp.mkdir(parents=True, exist_ok=True)
    sfile = tmp / "scheduler.json"
    env = {**os.environ, "NUMBA_NUM_THREADS": "1", "SKYROUTE_CACHE_DIR": str(cache_root)}
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--scheduler-file",
                               str(sfile), "--port", "0", "--no-dashboard"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)]
    try:
        t_end = time.monotonic() + 120
        while not sfile.exists():
            if time.monotonic() > t_end:
                raise RuntimeError("the dask scheduler did not start within 120 s")
            time.sleep(0.2)
        procs += [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", "--scheduler-file",
                                    str(sfile), "--nthreads", "1", "--no-nanny", "--no-dashboard"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
                  for _ in range(n_workers)]
        with Client(json.loads(sfile.read_text())["address"], timeout="60s") as client:
            client.wait_for_workers(n_workers, timeout=120)
            yield client
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.wait()


def _decisions(res) -> list:
    return [(o.task.id, o.status, o.delay_s, o.attempts, None if o.attempt is None else json.dumps(o.attempt.doc,
                                                                                                   sort_keys=True))
            for o in res.outcomes]


def _reason(res, mission: str) -> str:
    return next((o.reason for o in res.outcomes if o.task.id == mission), "")


def _load() -> str:
    return "load average {:.2f} {:.2f} {:.2f}".format(*os.getloadavg())


def _peak_rss_gb() -> float:
    """This process's peak resident memory so far [GB] (Linux ``ru_maxrss`` is in KiB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9


def _peaks(client=None) -> str:
    """The driver's peak resident memory and, given a dask ``client``, each worker's [GB]."""
    txt = f"peak memory: driver {_peak_rss_gb():.2f} GB"
    if client is not None:
        w = client.run(_peak_rss_gb)
        txt += ", workers " + " / ".join(f"{v:.2f}" for _, v in sorted(w.items())) + " GB"
    return txt


def main() -> None:
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.fleet import (
        FleetOptions,
        default_level,
        draw_missions,
        fleet_maps,
        run_fleet,
    )
    from skyroute.pipeline.fleet_outputs import write_fleet
    from skyroute.pipeline.graph import scheduler_context
    from skyroute.pipeline.settings import GroundReference, load_scenario

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="4 missions over 10 min")
    ap.add_argument("--missions", type=int, default=None)
    ap.add_argument("--window-min", type=float, default=None)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--no-parallel", action="store_true", help="only the sequential run")
    ap.add_argument("--configs", default="1:speculative",
                    help="parallel runs DEPTH:AFFINITY[:nolater],... (speculative missions in flight; attempts "
                         "that prefer their goal's worker: all, speculative, none; nolater: no speculation of "
                         "later departures)")
    ap.add_argument("--scenario", default="helsinki-medical")
    ap.add_argument("--min-km", type=float, default=0.2, help="shortest drawn mission [km]")
    ap.add_argument("--max-km", type=float, default=1.5, help="longest drawn mission [km]")
    ap.add_argument("--dask-processes", action="store_true",
                    help="real `dask scheduler` + --workers `dask worker` processes instead of a LocalCluster")
    a = ap.parse_args()
    n = a.missions or (4 if a.quick else 1000)
    window = a.window_min or (10.0 if a.quick else 120.0)
    sc = load_scenario(a.scenario)
    if sc.data.ground is None:   # OSM-only Helsinki: ground about 10 m above the EGM96 geoid (intents need W84)
        sc = sc.model_copy(update={"data": sc.data.model_copy(
            update={"ground": GroundReference(height_m=10.0, vertical_datum="EGM96 geoid")})})
    cache = Cache(os.environ.get("SKYROUTE_CACHE_DIR"))
    t = time.perf_counter()
    maps = fleet_maps(sc, cache.root)
    print(f"maps loaded in {time.perf_counter() - t:.1f} s (cache {cache.root})")
    tasks = draw_missions(sc, maps, n, a.seed, window * 60.0, min_km=a.min_km, max_km=a.max_km)
    level = default_level(maps)
    opt = FleetOptions(seed=a.seed)

    def report(name, res, out):
        _, sec = write_fleet(res, sc, maps, out)
        c = sec["counts"]
        print(f"{name}: {n} missions in {res.seconds:.1f} s: accepted {c['accepted']}, delayed {c['delayed']}, "
              f"preempted-replanned {c['preempted-replanned']}, rejected {c['rejected']}; mean delay "
              f"{sec['mean_delay_s'] or 0:.1f} s; conflicts (independent check) {sec['conflicts_independent_check']}; "
              f"min separation {sec['min_separation_m']} m; {sec['planning_attempts']} plans = "
              f"{sec['throughput_plans_per_min']:.1f} plans/min ({sec['missions_per_min']:.1f} missions/min)"
              + f"; mean planning time per mission {sum(o.compute_s for o in res.outcomes) / n:.2f} s"
              + (f"; speculative {res.speculative}" if res.speculative.get("worker_setup_s") else ""))
        return sec

    with tempfile.TemporaryDirectory() as tmp:
        print(f"{a.scenario}: {n} missions {a.min_km}-{a.max_km} km over {window:g} min; before the sequential run: "
              f"{_load()}")
        seq = run_fleet(sc, tasks, cache_dir=cache.root, options=opt, default_dop=level)
        s1 = report("sequential", seq, Path(tmp) / "seq")
        print(_peaks(), flush=True)
        target = "met" if s1["throughput_plans_per_min"] >= 100 else "NOT met"
        print(f"target >= 100 plans/min (sequential, this machine): {target}"
              + (" (--quick: a few cold-cache plans, not the target's measure)" if a.quick else ""))
        if a.no_parallel:
            return
        print(f"after the sequential run: {_load()}")
        kind = f"{a.workers} dask worker processes" if a.dask_processes else f"LocalCluster {a.workers} workers"
        for i, cfg in enumerate(a.configs.split(",")):
            depth, affinity, *later = cfg.split(":")
            # a fresh cluster per config: workers that planned these missions before would reuse
            # their STEP I memos and edge costs (a later config would not be comparable)
            cluster = (dask_processes(a.workers, Path(cache.root), Path(tmp) / f"c{i}") if a.dask_processes
                       else scheduler_context("distributed", a.workers))
            with cluster as client:
                par = run_fleet(sc, tasks, cache_dir=cache.root, options=opt, default_dop=level, client=client,
                                depth=int(depth), affinity=affinity, later_departures=later != ["nolater"])
                report(f"{kind}, {cfg}", par, Path(tmp) / f"par{i}")
                print(_peaks(client) + " (the driver's peak includes its sequential run)", flush=True)
                same = _decisions(seq) == _decisions(par)
                print(f"speed-up with {kind} ({cfg}): "
                      f"{seq.seconds / par.seconds:.2f}x (worker setup {par.speculative['worker_setup_s']:.1f} s not "
                      f"counted); same decisions: {same}; {_load()}", flush=True)
                if not same:
                    for d1, d2 in zip(_decisions(seq), _decisions(par), strict=True):
                        if d1 != d2:
                            print(f"  differs: {d1[:4]} sequential, {d2[:4]} parallel; reasons "
                                  f"{_reason(seq, d1[0])!r} / {_reason(par, d2[0])!r}", flush=True)
                assert same, "the parallel driver decided otherwise than the sequential one"


if __name__ == "__main__":
    main()
