"""Navigation Monte Carlo (stages/navsim.py): 1000 runs of a 2-minute flight at 10 Hz on a
synthetic canyon geometry, against the loop baseline (one run per call, x 1000), with the
containment table of the two filters (seed 003 proposed vs weak).

Run: python benchmarks/bench_navsim.py [--quick] [--runs N]
(--quick: one timing of the vectorised call and 20 single-run calls for the baseline; < 60 s.)
"""

from __future__ import annotations

import argparse
import os
import time

import numba
import numpy as np

from skyroute.stages import navigation as N
from skyroute.stages import navsim as S

AZ = np.array([10, 50, 95, 130, 170, 205, 250, 290, 320, 345.0])
EL = np.array([22, 58, 35, 74, 28, 47, 31, 66, 40, 15.0])


def canyon_flight(duration_s: float = 120.0, rate_hz: float = 10.0):
    """Straight flight at 8 m/s; between 30 s and 90 s a street canyon along north hides the
    satellites whose line of sight leaves it below 50 deg elevation (east/west azimuths)."""
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    xyz = np.stack([np.zeros_like(t), 8.0 * t, np.full_like(t, 40.0)], axis=1)
    los = np.broadcast_to(N.los_from_az_el(AZ, EL), (t.size, AZ.size, 3)).copy()
    recv = np.ones((t.size, AZ.size), bool)
    across = np.abs(np.sin(np.radians(AZ))) > 0.5              # azimuth across the street
    hidden = across & (EL < 50.0)
    vis = recv.copy()
    vis[np.ix_((t >= 30.0) & (t < 90.0), hidden)] = False
    return t, xyz, los, vis, recv


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one timing, 20-run loop baseline (< 60 s)")
    ap.add_argument("--runs", type=int, default=1000)
    args = ap.parse_args()
    t, xyz, los, vis, recv = canyon_flight()
    S.simulate(t[:20], xyz[:20], los[:20], vis[:20], recv[:20], runs=2, seed=0)      # compile / load cache

    reps = 1 if args.quick else 3
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        ds = S.simulate(t, xyz, los, vis, recv, runs=args.runs, seed=1)
        times.append(time.perf_counter() - t0)
    tv = min(times)

    n_loop = 20 if args.quick else 100
    t0 = time.perf_counter()
    for r in range(n_loop):
        S.simulate(t, xyz, los, vis, recv, runs=1, seed=100 + r)
    t_loop = (time.perf_counter() - t0) / n_loop * args.runs

    print(f"navsim: {args.runs} runs x {t.size} epochs ({t[-1] - t[0] + 0.1:.0f} s at 10 Hz), "
          f"{AZ.size} satellites, {numba.get_num_threads()} numba threads, {os.cpu_count()} cpus")
    print(f"{'vectorised [s]':>15} {'loop x runs [s]':>16} {'speed-up':>9} {'target':>8}")
    print(f"{tv:>15.2f} {t_loop:>16.2f} {t_loop / tv:>9.1f} {'< 60 s':>8}")
    cont = S.containment(ds)
    beats = S.proposed_beats_weak(ds)
    print(f"\n{'filter':>9} {'1 sigma':>8} {'2 sigma':>8} {'3 sigma':>8}")
    for f in S.FILTERS:
        c = cont[f]
        print(f"{f:>9} {c['1sigma']:>8.3f} {c['2sigma']:>8.3f} {c['3sigma']:>8.3f}")
    win = (t >= 30.0) & (t < 90.0)
    sub = ds.isel(time=np.flatnonzero(win))
    cw = S.containment(sub)
    print("in the canyon (30-90 s):")
    for f in S.FILTERS:
        c = cw[f]
        print(f"{f:>9} {c['1sigma']:>8.3f} {c['2sigma']:>8.3f} {c['3sigma']:>8.3f}")
    print(f"proposed error < weak error: {beats:.3f} of (run, epoch), {S.proposed_beats_weak(sub):.3f} in the canyon")
    print(f"median sigma [m]: proposed {np.median(ds.sigma_proposed_m.values):.2f}, "
          f"weak {np.median(ds.sigma_weak_m.values):.2f}")


if __name__ == "__main__":
    main()
