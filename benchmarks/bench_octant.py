"""Octant local collision avoidance on BlueSky's "super conflict" geometries (issue 14): N own
UAVs (4, 8, 16) on a circle of radius R, evenly spaced headings, all flying at the same speed
through the centre to the opposite point, each running the octant avoidance with the priority
rule of :mod:`skyroute.stages.tactical.octant` (coplanar: quadrants in the horizontal plane;
3-D: octants, climbs and descents allowed).

Checked independently: every pair's distance every 0.05 s (positions interpolated from the
flown samples, each UAV until it arrives) against the separation 2 r + d_c.  Reported per
case: minimum distance, losses of separation, delay per UAV (arrival minus straight-line
time), manoeuvre counts, compute time.

    python benchmarks/bench_octant.py [--quick]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from skyroute.stages.tactical.octant import fly_fleet

RADIUS_M = 1.0       # UAV sphere radius r [m]
MARGIN_M = 5.0       # traffic margin d_c [m]: separation 2 r + d_c = 7 m
SPEED_MPS = 10.0


def super_conflict(n: int, ring_m: float, z_m: float = 50.0) -> tuple[np.ndarray, np.ndarray]:
    ang = 2 * np.pi * np.arange(n) / n
    start = np.column_stack([ring_m * np.cos(ang), ring_m * np.sin(ang), np.full(n, z_m)])
    goal = start * [-1.0, -1.0, 1.0]
    return start, goal


def brute_force(res, sep_m: float, step_s: float = 0.05) -> tuple[float, int]:
    """(minimum pair distance [m], number of (pair, sample) losses) every ``step_s``."""
    t = np.arange(0.0, res.t_s[-1] + 1e-9, step_s)
    n = res.xyz_m.shape[1]
    X = np.stack([np.column_stack([np.interp(t, res.t_s, res.xyz_m[:, i, k]) for k in range(3)]) for i in range(n)])
    live = np.array([t <= res.arrival_s[i] for i in range(n)])
    dmin, losses = math.inf, 0
    for i in range(n):
        for j in range(i + 1, n):
            m = live[i] & live[j]
            if m.any():
                d = np.linalg.norm(X[i, m] - X[j, m], axis=1)
                dmin = min(dmin, float(d.min()))
                losses += int(np.sum(d < sep_m - 1e-9))
    return dmin, losses


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="ring of 100 m, coarser step (< 60 s)")
    args = ap.parse_args()
    ring = 100.0 if args.quick else 300.0
    dt = 0.1
    sep = 2 * RADIUS_M + MARGIN_M
    print(f"super conflict: ring {ring:g} m, {SPEED_MPS:g} m/s, separation {sep:g} m, step {dt:g} s, "
          "check every 0.05 s")
    print(f"{'N':>3} {'mode':>9} {'min d [m]':>9} {'LoS':>4} {'arrived':>7} {'delay mean/max [s]':>19} "
          f"{'compute [s]':>11}  manoeuvres")
    worst = 0
    for n in (4, 8, 16):
        for coplanar in (True, False):
            S, G = super_conflict(n, ring)
            t0 = time.perf_counter()
            res = fly_fleet(S, G, speed_mps=SPEED_MPS, radius_m=RADIUS_M, margin_m=MARGIN_M, periphery_m=60.0,
                            horizon_s=6.0, dt_s=dt, t_max_s=4 * ring / SPEED_MPS + 60.0, coplanar=coplanar)
            secs = time.perf_counter() - t0
            dmin, los = brute_force(res, sep)
            arrived = int(np.isfinite(res.arrival_s).sum())
            worst += los + (n - arrived)
            print(f"{n:>3} {'coplanar' if coplanar else '3-D':>9} {dmin:9.2f} {los:4d} {arrived:4d}/{n:<2d} "
                  f"{np.mean(res.delay_s):9.1f} / {np.max(res.delay_s):6.1f} {secs:11.2f}  {res.kinds}")
            print("      delay per UAV [s]: " + " ".join(f"{d:.1f}" for d in res.delay_s))
    if worst:
        raise SystemExit(f"{worst} losses of separation or UAVs not arrived")


if __name__ == "__main__":
    main()
