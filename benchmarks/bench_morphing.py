"""Benchmark of the digital morphing map (skyroute.stages.morphing).

A synthetic downtown of 500 x 500 cells at 2 m (towers 10-120 m), GPS almanac 2020-01-03:
time per epoch of the per-epoch coverage floor (``coverage_floor_series``, dask threads) against
the window floor (``coverage_maps``, numpy runner, same epochs), with 4 DOP levels added
(``levels_m``), the lazy zarr write, and the GIF (frames, seconds, size).

Run:  /work/venv/bin/python benchmarks/bench_morphing.py [--quick]
(--quick: 5 epochs, 10 frames, < 60 s on 2 cores; default: 21 epochs, 60 frames).
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import dask
import numpy as np
import xarray as xr

from skyroute.stages import coverage as cv
from skyroute.stages.almanac import sky_geometry
from skyroute.stages.grid import Grid
from skyroute.stages.morphing import animate_floor, coverage_floor_series

CATALOG = Path(__file__).resolve().parents[1] / "catalogs" / "data"


def towers(n: int = 500, seed: int = 3) -> xr.DataArray:
    rng = np.random.default_rng(seed)
    h = np.zeros((n, n), np.float32)
    for _ in range(n * n // 400):
        w, length = rng.integers(4, 20, 2)
        i, j = rng.integers(0, n - 20, 2)
        h[i:i + w, j:j + length] = max(float(h[i:i + w, j:j + length].max()), rng.uniform(10, 120))
    g = Grid.from_bounds("EPSG:28992", 91000.0, 435000.0, 91000.0 + 2 * n, 435000.0 + 2 * n, 2.0)
    return g.dataarray(h, "surface", units="m", vertical_datum="NAP")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    n_ep, n_frames = (5, 10) if args.quick else (21, 60)
    surf = towers()
    g = Grid.from_dataarray(surf)
    lon, lat = g.to_lonlat(91500.0, 435500.0)
    times = cv.window_times("2020-01-03T08:00", window_min=float(n_ep - 1))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        sky = sky_geometry(CATALOG / "yuma_2020-01-03.txt", times, lat, lon, 0.0)
    thr = (2.0, 3.0, 4.0)
    # warm the numba kernels
    small = surf.isel(y=slice(0, 40), x=slice(0, 40))
    cv.coverage_maps(small, sky["az_deg"][:1], sky["el_deg"][:1], thresholds=thr)
    coverage_floor_series(small, sky.isel(time=[0]), thr, levels_m=[30.0]).load()

    t0 = time.perf_counter()
    window = cv.coverage_maps(surf, sky["az_deg"], sky["el_deg"], thresholds=thr)
    t_win = time.perf_counter() - t0
    with dask.config.set(scheduler="threads", num_workers=2):
        t0 = time.perf_counter()
        s = coverage_floor_series(surf, sky, thr).load()
        t_ser = time.perf_counter() - t0
        t0 = time.perf_counter()
        sv = coverage_floor_series(surf, sky, thr, levels_m=[20.0, 40.0, 60.0, 80.0]).load()
        t_vol = time.perf_counter() - t0
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            coverage_floor_series(surf, sky, thr).to_zarr(Path(tmp) / "s.zarr", mode="w",
                                                          consolidated=False)
            t_zarr = time.perf_counter() - t0
            same = np.array_equal(s["coverage_floor"].max("time", skipna=False).values,
                                  window["coverage_floor"].values, equal_nan=True)
            t_path = np.linspace(0.0, 60.0 * (n_ep - 1), 40)
            xyz = np.c_[91050 + 900 * t_path / t_path[-1], 435100 + 800 * t_path / t_path[-1],
                        60 + 10 * np.sin(t_path / 90)]
            tser = coverage_floor_series(surf, sky, thr, times=np.linspace(0, t_path[-1], n_frames))
            tser = tser.load()
            t0 = time.perf_counter()
            out = animate_floor(tser, 3.0, t_path, xyz, Path(tmp) / "f.gif", max_frames=n_frames)
            t_gif = time.perf_counter() - t0
            size = out.stat().st_size
    print(f"map {surf.shape[0]} x {surf.shape[1]} cells at 2 m, {n_ep} epochs, "
          f"{len(thr)} PDOP thresholds, {int((sv['el_deg'] >= 5.0).sum()) // n_ep} sats/epoch above 5 deg")
    print(f"window floor (coverage_maps, numpy, 1 thread): {t_win:.2f} s = {t_win / n_ep:.3f} s/epoch")
    print(f"per-epoch floor (series, dask 2 threads):      {t_ser:.2f} s = {t_ser / n_ep:.3f} s/epoch")
    print(f"  + dop_volume at 4 levels:                    {t_vol:.2f} s = {t_vol / n_ep:.3f} s/epoch")
    print(f"  lazy zarr write:                             {t_zarr:.2f} s")
    print(f"max over epochs == window floor: {same}")
    print(f"GIF: {n_frames} frames in {t_gif:.1f} s, {size / 1e6:.2f} MB")


if __name__ == "__main__":
    main()
