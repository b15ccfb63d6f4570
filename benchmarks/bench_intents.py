"""Conflict check of operational intents (issue 15): an STRtree over the accepted volumes'
footprints + altitude / time interval filters + the exact area test (stages/fleet.py
VolumeIndex) vs the naive pairwise check (volumes_intersect on every pair), same data.

Synthetic U-space traffic: intents of missions 0.5-3 km long in a 20 km x 20 km city over a
2-hour window, cut into volumes like stages/intents.py does (stadiums ~30 s x 12 m/s long,
buffer 4-8 m, altitude bands 15-25 m thick between 0 and 150 m, +-5 s time buffers).

    python benchmarks/bench_intents.py [--quick] [--accepted 10000] [--queries 2000]

Target (issue 15): >= 1000 intents/s against 10,000 accepted intents.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import shapely

from skyroute.stages.fleet import Volume4, VolumeIndex, conflicts_naive


def make_intent(rng, extent_m=20_000.0, window_s=7200.0, speed_mps=12.0, chunk_s=30.0) -> list[Volume4]:
    x, y = rng.uniform(0, extent_m, 2)
    ang = rng.uniform(0, 2 * np.pi)
    length = rng.uniform(500, 3000)
    t0 = rng.uniform(0, window_s)
    n = max(1, int(np.ceil(length / (speed_mps * chunk_s))))
    lo = rng.uniform(0, 130)
    r = rng.uniform(4, 8)
    out = []
    for k in range(n):
        a, b = k * length / n, (k + 1) * length / n
        seg = shapely.LineString([(x + a * np.cos(ang), y + a * np.sin(ang)), (x + b * np.cos(ang), y + b * np.sin(ang))])
        ta = t0 + a / speed_mps
        tb = t0 + b / speed_mps
        out.append(Volume4(seg.buffer(r, quad_segs=4), lo, lo + rng.uniform(15, 25), ta - 5.0, tb + 5.0))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer queries and naive samples (< 60 s)")
    ap.add_argument("--accepted", type=int, default=10_000)
    ap.add_argument("--queries", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    nq = a.queries or (500 if a.quick else 2000)
    n_naive = 2 if a.quick else 10
    rng = np.random.default_rng(a.seed)
    t = time.perf_counter()
    accepted = [make_intent(rng) for _ in range(a.accepted)]
    queries = [make_intent(rng) for _ in range(nq)]
    t_make = time.perf_counter() - t
    flat = [v for vols in accepted for v in vols]
    t = time.perf_counter()
    idx = VolumeIndex(rebuild_every=len(flat))
    for i, vols in enumerate(accepted):
        idx.add(vols, i)
    t_build = time.perf_counter() - t
    t = time.perf_counter()
    hits = [idx.conflicts(q) for q in queries]
    t_q = time.perf_counter() - t
    rate = nq / t_q
    t = time.perf_counter()
    naive = [conflicts_naive(q, flat) for q in queries[:n_naive]]
    t_n = time.perf_counter() - t
    assert naive == hits[:n_naive], "index and pairwise check disagree"
    n_conf = sum(bool(h) for h in hits)
    print(f"accepted: {a.accepted} intents, {len(flat)} volumes (made in {t_make:.1f} s); index built in {t_build:.2f} s")
    print(f"STRtree + intervals: {nq} intents checked in {t_q:.2f} s = {rate:.0f} intents/s "
          f"({n_conf} in conflict, {np.mean([len(q) for q in queries]):.1f} volumes per intent)")
    print(f"naive pairwise: {n_naive} intents in {t_n:.2f} s = {n_naive / t_n:.2f} intents/s "
          f"(speed-up {rate / (n_naive / t_n):.0f}x); same conflicts on those {n_naive}")
    print(f"target >= 1000 intents/s: {'met' if rate >= 1000 else 'NOT met'}")


if __name__ == "__main__":
    main()
