"""Airspace store (issue 26): the online answer time of adding one mission to an airspace that
already holds many accepted intents, and the R*Tree candidate query against all pairs.

    SKYROUTE_CACHE_DIR=... python benchmarks/bench_airspace.py --store DAY.sqlite [--additions 100]
        [--scenario helsinki-medical] [--window-min 480] [--cli 5] [--sample 200]

DAY.sqlite: an airspace of real planned intents, e.g. written by
``skyroute fleet helsinki-medical --missions 2200 --seed 7 --window-min 480 --airspace DAY.sqlite``.
It is copied first (the additions go into the copy).

1. Online answers: ``--additions`` missions, one at a time, each drawn between the scenario's
   landing sites with a departure uniform over ``--window-min`` (seed 1000 + k), answered by
   :func:`skyroute.pipeline.fleet.run_fleet` with the store (maps cached in this process; the
   first addition, which loads the compiled kernels, is left out): accepted with its intent,
   delayed, or rejected with the reason, written to the store in one transaction.  p50 / p95 /
   max [s] of the wall time of each answer.  ``--cli N``: also N answers by the command line
   (``skyroute fleet --airspace FILE --missions 1``: a new process each, maps from the stage cache).
2. Conflict queries: every intent added in 1. checked against the whole store through the
   R*Tree (:meth:`AirspaceStore.conflicts`) and by all pairs (the exact test on every pair of
   volumes, vectorised; and ``conflicts_naive``, one shapely call per pair, on 10 of them):
   time per query and ratio; both must find the same pairs.
3. ``airspace check`` of the whole store (consistency, R*Tree self-check, independent all-pairs
   check of the F3548 documents), and agreement of the R*Tree with all pairs on a sample of
   ``--sample`` intents.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _pct(x, q):
    return float(np.percentile(np.asarray(x, float), q)) if len(x) else float("nan")


def main() -> None:
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.fleet import (
        FleetOptions,
        default_level,
        draw_missions,
        fleet_maps,
        independent_conflicts,
        run_fleet,
    )
    from skyroute.pipeline.settings import load_scenario
    from skyroute.stages.airspace_store import AirspaceStore
    from skyroute.stages.fleet import conflicts_naive, pairs_intersect

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--store", type=Path, required=True, help="an airspace file of accepted intents (copied)")
    ap.add_argument("--additions", type=int, default=100)
    ap.add_argument("--scenario", default="helsinki-medical")
    ap.add_argument("--window-min", type=float, default=480.0)
    ap.add_argument("--cli", type=int, default=0, help="also N answers by the command line (a process each)")
    ap.add_argument("--sample", type=int, default=200)
    ap.add_argument("--json", type=Path, default=None, help="write the figures here")
    a = ap.parse_args()

    sc = load_scenario(a.scenario)
    cache = Cache(None)
    tmp = Path(tempfile.mkdtemp(prefix="bench-airspace-"))
    path = tmp / "air.sqlite"
    with AirspaceStore.open(a.store) as src:     # a consistent copy (WAL included) through SQLite's backup
        import sqlite3

        dst = sqlite3.connect(path)
        src._conn.backup(dst)
        dst.close()
    store = AirspaceStore.open(path)
    n0, v0 = len(store), store.n_volumes()
    print(f"store: {a.store}: {n0} accepted intents, {v0} volumes", flush=True)

    t = time.perf_counter()
    maps = fleet_maps(sc, cache.root)
    level = default_level(maps)
    print(f"maps loaded in {time.perf_counter() - t:.1f} s", flush=True)
    opt = FleetOptions()

    # 1. online answers -------------------------------------------------------------------
    times, status, added = [], {}, []
    for k in range(a.additions + 1):
        (task,) = draw_missions(sc, maps, 1, 1000 + k, a.window_min * 60.0)
        import dataclasses

        task = dataclasses.replace(task, id=f"online-{k:03d}")
        t = time.perf_counter()
        res = run_fleet(sc, [task], cache_dir=cache.root, options=opt, default_dop=level, airspace=store)
        dt = time.perf_counter() - t
        (o,) = res.outcomes
        if k == 0:
            print(f"warm-up addition: {o.status} in {dt:.2f} s (kernels loaded; not counted)", flush=True)
            continue
        times.append(dt)
        status[o.status] = status.get(o.status, 0) + 1
        if o.status != "rejected":
            added.append(task.id)
        if k % 20 == 0:
            print(f"  {k} additions: p50 {_pct(times, 50):.3f} s, p95 {_pct(times, 95):.3f} s", flush=True)
    online = {"additions": len(times), "p50_s": round(_pct(times, 50), 3), "p95_s": round(_pct(times, 95), 3),
              "max_s": round(max(times), 3), "mean_s": round(statistics.fmean(times), 3), "decisions": status,
              "store_intents_before": n0}
    print(f"online answers ({len(times)} additions to {n0}+ intents): p50 {online['p50_s']} s, p95 "
          f"{online['p95_s']} s, max {online['max_s']} s; {status}", flush=True)

    cli = None
    if a.cli:
        ct = []
        for k in range(a.cli):
            t = time.perf_counter()
            r = subprocess.run([sys.executable, "-m", "skyroute.pipeline.cli", "fleet", a.scenario, "--missions", "1",
                                "--seed", str(5000 + k), "--window-min", str(a.window_min), "--airspace", str(path),
                                "--out", str(tmp / f"cli{k}"), "-q"], capture_output=True, text=True)
            ct.append(time.perf_counter() - t)
            if r.returncode not in (0, 3):
                print(r.stderr, file=sys.stderr)
                raise SystemExit(f"the CLI failed: exit {r.returncode}")
        cli = {"runs": len(ct), "p50_s": round(_pct(ct, 50), 3), "max_s": round(max(ct), 3)}
        print(f"command line (a process each, maps from the stage cache): p50 {cli['p50_s']} s, max {cli['max_s']} s",
              flush=True)

    # 2. index query vs all pairs ------------------------------------------------------------
    allv = store.volumes()
    owners = [m for m, vs in allv.items() for _ in vs]
    flat = [v for vs in allv.values() for v in vs]
    t_idx, t_all, t_naive, n_naive = [], [], [], 0
    for m in added:
        q = allv[m]
        t = time.perf_counter()
        got = {o for _, o in store.conflicts(q, exclude=(m,))}
        t_idx.append(time.perf_counter() - t)
        t = time.perf_counter()
        qi, ai = (x.ravel() for x in np.meshgrid(np.arange(len(q)), np.arange(len(flat)), indexing="ij"))
        ok = pairs_intersect(q, flat, qi, ai)
        ref = {owners[j] for j in ai[ok]} - {m}
        t_all.append(time.perf_counter() - t)
        if got != ref:
            raise SystemExit(f"R*Tree and all pairs disagree for {m}: {sorted(got)} vs {sorted(ref)}")
        if n_naive < 10:
            t = time.perf_counter()
            conflicts_naive(q, flat)
            t_naive.append(time.perf_counter() - t)
            n_naive += 1
    query = {"queries": len(t_idx), "rtree_ms": round(1e3 * statistics.fmean(t_idx), 2),
             "all_pairs_vectorised_ms": round(1e3 * statistics.fmean(t_all), 2),
             "all_pairs_naive_ms": round(1e3 * statistics.fmean(t_naive), 2) if t_naive else None,
             "ratio_vectorised_over_rtree": round(statistics.fmean(t_all) / statistics.fmean(t_idx), 1),
             "ratio_naive_over_rtree": round(statistics.fmean(t_naive) / statistics.fmean(t_idx), 1) if t_naive
             else None, "store_volumes": len(flat), "same_answers": True}
    print(f"conflict query of one intent against {len(flat)} volumes: R*Tree {query['rtree_ms']} ms, all pairs "
          f"vectorised {query['all_pairs_vectorised_ms']} ms ({query['ratio_vectorised_over_rtree']}x), all pairs "
          f"one shapely call each {query['all_pairs_naive_ms']} ms ({query['ratio_naive_over_rtree']}x); same pairs",
          flush=True)

    # 3. airspace check ----------------------------------------------------------------------
    t = time.perf_counter()
    problems = store.check()
    t_cons = time.perf_counter() - t
    t = time.perf_counter()
    self_pairs = store.self_conflicts()
    t_self = time.perf_counter() - t
    recs = store.records(details=True)
    docs = {r.id: r.details for r in recs}
    t = time.perf_counter()
    pairs = independent_conflicts(docs, store.crs_wkt, store.epoch_utc.isoformat())
    t_ind = time.perf_counter() - t
    rng = np.random.default_rng(0)
    sample = sorted(rng.choice(sorted(docs), size=min(a.sample, len(docs)), replace=False).tolist())
    samp_all = independent_conflicts({m: docs[m] for m in sample}, store.crs_wkt, store.epoch_utc.isoformat())
    samp_idx = [p for p in self_pairs if p[0] in set(sample) and p[1] in set(sample)]
    check = {"intents": len(docs), "consistent": not problems, "problems": problems[:5],
             "conflicts_all_pairs": len(pairs), "conflicts_rtree": len(self_pairs),
             "seconds": {"consistency": round(t_cons, 2), "rtree_self_check": round(t_self, 2),
                         "all_pairs_independent": round(t_ind, 2)},
             "sample": len(sample), "sample_all_pairs_conflicts": len(samp_all),
             "sample_agrees": sorted(map(tuple, map(sorted, samp_all))) == samp_idx}
    print(f"airspace check of {len(docs)} intents: {'consistent' if not problems else problems[:3]}; conflicts: "
          f"all pairs {len(pairs)} ({t_ind:.1f} s), R*Tree {len(self_pairs)} ({t_self:.1f} s); consistency "
          f"{t_cons:.1f} s; {len(sample)}-intent sample: all pairs {len(samp_all)} conflicts, agrees "
          f"{check['sample_agrees']}", flush=True)
    store.close()
    out = {"online": online, "cli": cli, "query": query, "check": check}
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))
    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
