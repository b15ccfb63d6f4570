"""Benchmark: satellite positions for 32 satellites x 10^4 epochs (vectorised numpy).

Baseline in the same run: the same propagation looping over satellites (one numpy call per
satellite); also the bare array propagation, and the az/el + DOP steps on top.  (A numba kernel
of the propagation was tried: no faster than numpy here, the cost is in sin/cos/atan2.)  Run: ``python benchmarks/bench_orbits.py``.
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path

import numpy as np

from skyroute.stages.almanac import read_almanac
from skyroute.stages.dop import dop
from skyroute.stages.orbits import (
    _ELEMENT_VARS,
    kepler_to_ecef,
    satellite_azel,
    satellite_positions,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "gnss"


def best_of(fn, n=3):
    best = np.inf
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        alm = read_almanac(DATA / "alm_gps_ed259.txt")           # 24 sats; tile to 32
    alm = alm.isel(sat=np.arange(32) % alm.sizes["sat"])
    alm = alm.assign_coords(sat=[f"G{i + 1:02d}" for i in range(32)])
    times = np.datetime64("2017-01-01T00:00", "ns") + (np.arange(10_000) * 8).astype("timedelta64[s]")

    tk = np.tile(np.arange(10_000, dtype=float)[:, None] * 8.0, (1, 32))
    els = {v: alm[v].values[None, :] for v in _ELEMENT_VARS}
    mu, we = np.full(32, 3.986005e14), np.full(32, 7.2921151467e-5)
    t_np = best_of(lambda: kepler_to_ecef(tk, **els, mu=mu, omega_e=we))
    t_vec = best_of(lambda: satellite_positions(alm, times))
    t_loop = best_of(lambda: [satellite_positions(alm.isel(sat=[k]), times) for k in range(32)], n=1)
    pos = satellite_positions(alm, times)
    t_azel = best_of(lambda: satellite_azel(pos, 45.0, 7.0, 300.0))
    azel = satellite_azel(pos, 45.0, 7.0, 300.0)
    el = azel["el_deg"].where(azel["el_deg"] >= 5.0)
    t_dop = best_of(lambda: dop(azel["az_deg"].where(el.notnull()), el, axis="sat"))
    n = 32 * 10_000
    print(f"{'step (32 sats x 10^4 epochs)':<40}{'time [s]':>10}{'us/pos':>9}{'ratio':>8}")
    for name, t in [("positions, per-satellite loop (baseline)", t_loop),
                    ("  Kepler + harmonics only (numpy arrays)", t_np),
                    ("positions, vectorised", t_vec), ("az/el + ENU line of sight", t_azel),
                    ("DOP (10^4 epochs)", t_dop)]:
        print(f"{name:<40}{t:10.3f}{t / n * 1e6:9.3f}{t / t_loop:8.2f}")


if __name__ == "__main__":
    main()
