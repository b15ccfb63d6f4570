"""Clearance floor: numba kernel (numpy and dask runners) vs a pure-numpy shift-and-max baseline.

    python benchmarks/bench_clearance.py
"""

from __future__ import annotations

import time

import dask
import dask.array as dsa
import numpy as np

from skyroute.stages import clearance as C
from skyroute.stages.grid import Grid


def numpy_baseline(s: np.ndarray, di, dj, lift, pad) -> np.ndarray:
    p = np.pad(s, pad, constant_values=-np.inf)
    out = np.full(s.shape, -np.inf)
    ny, nx = s.shape
    for a, b, h in zip(di, dj, lift, strict=True):
        np.maximum(out, p[pad + a: pad + a + ny, pad + b: pad + b + nx] + h, out=out)
    return out


def timed(f, *args, repeat=3):
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        res = f(*args)
        best = min(best, time.perf_counter() - t)
    return best, res


def main() -> None:
    rng = np.random.default_rng(0)
    n, res = 1000, 1.0
    s = rng.uniform(0, 5, (n, n))
    for _ in range(400):  # buildings
        i, j = rng.integers(0, n - 30, 2)
        s[i: i + rng.integers(5, 30), j: j + rng.integers(5, 30)] += rng.uniform(5, 60)
    g = Grid.from_bounds("EPSG:32633", 0, 0, n * res, n * res, res)
    surf = g.dataarray(s, "surface", units="m")
    print(f"surface {n} x {n} cells of {res} m")
    print(f"{'radius [m]':>10} {'offsets':>8} {'numpy [s]':>10} {'numba [s]':>10} {'dask 2thr [s]':>14} "
          f"{'numpy/numba':>12} {'numpy/dask':>11}")
    C.clearance_floor(surf.isel(y=slice(0, 50), x=slice(0, 50)), 2.0)  # compile
    for r in (3.0, 5.0, 10.0):
        di, dj, lift, pad = C.disc_offsets(r, res)
        tb, ref = timed(numpy_baseline, s, di, dj, lift, pad, repeat=1)
        tn, out = timed(lambda a, rr: C.clearance_floor(a, rr).values, surf, r)
        lazy = surf.copy(data=dsa.from_array(s, chunks=(500, 500)))
        with dask.config.set(scheduler="threads", num_workers=2):
            td, outd = timed(lambda a, rr: C.clearance_floor(a, rr).values, lazy, r)
        assert np.array_equal(out, ref) and np.array_equal(outd, ref)
        print(f"{r:>10.1f} {di.size:>8d} {tb:>10.3f} {tn:>10.3f} {td:>14.3f} {tb / tn:>12.1f} {tb / td:>11.1f}")


if __name__ == "__main__":
    main()
