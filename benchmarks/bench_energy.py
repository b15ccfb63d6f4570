"""Segment energy (seed 000 eq. 2-12): vectorised call vs one call per segment (baseline).

Run: python benchmarks/bench_energy.py
"""

from __future__ import annotations

import time

import numpy as np

from skyroute.stages.energy import segment_energy
from skyroute.stages.vehicle import load_vehicle


def main():
    veh = load_vehicle("dji-m300-rtk")
    rng = np.random.default_rng(0)
    segment_energy(np.zeros((1, 3)), np.ones((1, 3)), np.zeros((1, 3)), veh)   # load the numba cache
    print(f"{'segments':>9} {'vectorised [s]':>15} {'per-segment loop [s]':>21} {'speed-up':>9} {'us/segment':>11}")
    for n in (1_000, 100_000):
        p0 = rng.uniform(0, 2000, (n, 3))
        p1 = p0 + rng.normal(0, 50, (n, 3))
        w = rng.normal(0, 4, (n, 3))
        t0 = time.perf_counter()
        r = segment_energy(p0, p1, w, veh)
        tv = time.perf_counter() - t0
        k = min(n, 1000)
        t0 = time.perf_counter()
        loop = [segment_energy(p0[j], p1[j], w[j], veh)["energy_J"][0] for j in range(k)]
        tl = (time.perf_counter() - t0) * n / k
        assert np.allclose(loop, r["energy_J"][:k], rtol=1e-12, equal_nan=True)
        print(f"{n:>9} {tv:>15.3f} {tl:>21.3f} {tl / tv:>9.0f} {1e6 * tv / n:>11.2f}")
    print("(loop time extrapolated from the first 1000 segments)")


if __name__ == "__main__":
    main()
