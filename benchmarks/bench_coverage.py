"""Benchmark of GNSS coverage maps (skyroute.stages.coverage).

1. Rotterdam-Delfshaven LoD2 (whole model, ~1045 m x 650 m = 0.68 km^2 at 2 m = 170 k cells),
   GPS almanac 2020-01-03 (30 healthy PRN), window 20 min every 5 min (5 epochs), PDOP
   thresholds 2, 3, 4: numpy runner (1 thread) and the dask runner (threads, 2 workers).
   Target: < 10 s on 2 cores.
2. The same surface tiled to >= 10^7 cells, computed by a dask.distributed LocalCluster with
   1 worker vs 2 workers (1 thread each).  Target: speed-up >= 1.6x.

Run:  /work/venv/bin/python benchmarks/bench_coverage.py [--cells 1e7] [--skip-cluster]
"""

from __future__ import annotations

import argparse
import math
import time
import warnings
from pathlib import Path

import dask.array as da
import numpy as np
import xarray as xr

from skyroute.stages import coverage as cv
from skyroute.stages.almanac import sky_geometry
from skyroute.stages.grid import Grid
from skyroute.stages.surface import build_surface

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
CATALOG = Path(__file__).resolve().parents[1] / "catalogs" / "data"


def data_file(name: str) -> Path:
    for folder in (SHARED / "city", SHARED / "gnss", CATALOG):
        if (folder / name).is_file():
            return folder / name
    raise SystemExit(f"{name} not found under {SHARED} or {CATALOG}")


def rotterdam_surface() -> xr.DataArray:
    grid = Grid.from_bounds("EPSG:28992", 90409.32, 435440.44, 91453.879, 436089.946, 2.0)
    ds = build_surface(grid, buildings_path=data_file("rotterdam_delfshaven_lod2.city.json"),
                       buildings_format="cityjson")
    return ds["surface"]


def satellites(surface: xr.DataArray) -> xr.Dataset:
    grid = Grid.from_dataarray(surface)
    xmin, ymin, xmax, ymax = grid.bounds
    lon, lat = grid.to_lonlat((xmin + xmax) / 2, (ymin + ymax) / 2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return sky_geometry(data_file("yuma_2020-01-03.txt"), cv.window_times("2020-01-03T08:00"),
                            lat, lon, 0.0)


def timed(fn, repeat: int = 1) -> float:
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def tiled(surface: xr.DataArray, n_cells: float, chunk: tuple[int, int]) -> xr.DataArray:
    """The surface mirrored/tiled to >= n_cells, lazily (dask), on a grid of the same CRS."""
    ny0, nx0 = surface.shape
    k = math.ceil(math.sqrt(n_cells / (ny0 * nx0)))
    ry, rx = k, math.ceil(n_cells / (ny0 * nx0 * k))
    base = da.from_array(surface.values.astype(np.float32), chunks=surface.shape)
    flip = da.concatenate([base, base[:, ::-1]], axis=1)       # mirrored: no seams
    flip = da.concatenate([flip, flip[::-1, :]], axis=0)
    big = da.tile(flip, ((ry + 1) // 2, (rx + 1) // 2))[: ny0 * ry, : nx0 * rx].rechunk(chunk)
    grid = Grid.from_dataarray(surface)
    r = grid.resolution_m
    g2 = Grid(grid.crs_wkt, grid.x0, grid.y1, big.shape[1], big.shape[0], r)
    out = xr.DataArray(big, dims=("y", "x"), coords=g2.coords(), name="surface",
                       attrs=dict(surface.attrs))
    return out.rio.write_crs(g2.crs)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cells", type=float, default=1.0e7)
    ap.add_argument("--skip-cluster", action="store_true")
    ap.add_argument("--order", default="1,2", help="worker counts in run order, e.g. 2,1")
    args = ap.parse_args()

    t0 = time.perf_counter()
    surf = rotterdam_surface()
    sky = satellites(surf)
    print(f"surface {surf.shape} cells ({surf.size / 1e3:.0f} k, "
          f"{surf.size * 4 / 1e6:.2f} km^2 at 2 m), built in {time.perf_counter() - t0:.1f} s; "
          f"{sky.sizes['sat']} satellites, {int(sky['n_visible'].max())} above the mask, "
          f"{sky.sizes['time']} epochs")
    az, el = sky["az_deg"], sky["el_deg"]
    cv.coverage_maps(surf.isel(y=slice(0, 20), x=slice(0, 20)), az, el)  # JIT warm-up

    rows = []
    t_np = timed(lambda: cv.coverage_maps(surf, az, el), repeat=2)
    rows.append(("Rotterdam 0.68 km^2, numpy runner (1 thread)", surf.size, t_np, 1.0))
    t_th = timed(lambda: cv.coverage_maps(surf, az, el, chunks=(170, 270)).compute(
        scheduler="threads", num_workers=2), repeat=2)
    rows.append(("Rotterdam, dask threads x2, 2x2 blocks (halo>block)", surf.size, t_th,
                 t_np / t_th))

    if not args.skip_cluster:
        from dask.distributed import Client, LocalCluster

        big = tiled(surf, args.cells, chunk=(1700, 820))
        print(f"tiled map {big.shape} = {big.size / 1e6:.1f} M cells, blocks {big.data.chunksize}, "
              f"halo {cv._halo_cells(big.data, cv._min_el(el.values, 5.0), 2.0)} cells")
        times = {}
        for n in (int(v) for v in args.order.split(",")):
            with LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                              dashboard_address=None) as cluster, Client(cluster) as client:
                client.run(lambda: cv.coverage_maps(
                    surf.isel(y=slice(0, 20), x=slice(0, 20)), az, el))  # warm the JIT cache
                ds = cv.coverage_maps(big, az, el)
                t = timed(lambda ds=ds: ds["coverage_floor"].data.sum().compute())
                times[n] = t
        rows.append((f"tiled {big.size / 1e6:.1f} M cells, LocalCluster 1 worker", big.size,
                     times[1], 1.0))
        rows.append((f"tiled {big.size / 1e6:.1f} M cells, LocalCluster 2 workers", big.size,
                     times[2], times[1] / times[2]))

    print()
    print(f"{'case':<52} {'cells':>11} {'time [s]':>9} {'us/cell':>8} {'speed-up':>9}")
    for name, n, t, ratio in rows:
        print(f"{name:<52} {n:>11,d} {t:>9.2f} {1e6 * t / n:>8.2f} {ratio:>8.2f}x")
    print("\ntargets: Rotterdam < 10 s on 2 cores; 2 vs 1 workers >= 1.6x "
          "(shared machine: numbers are noisy)")


if __name__ == "__main__":
    main()
