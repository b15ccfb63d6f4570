"""Scaling and memory benchmark of GNSS coverage maps (skyroute.stages.coverage, issue "GNSS
stages", performance section).

Surfaces are real: ``build_surface`` on a catalog scenario's grid (Rotterdam-Delfshaven LoD2
CityJSON or Helsinki OSM), at a chosen resolution, mirror-tiled lazily with dask (each block
is cut from the small real surface by index arithmetic, so the big map never exists in the
client).  Satellites: the scenario's almanacs over its mission window (5 epochs).

Modes (combine freely; default: ``--default --cells 1e7``):

``--default``
    the default scenario (helsinki-medical at its own grid): numpy runner, then
    ``chunks="auto"`` with the threaded scheduler on 1 and 2 threads.  Target: < 10 s on 2 cores.
``--cells 1e7 --workers 1,2 [--threads 1,2]``
    the tiled map of >= ``cells`` cells: a dask.distributed LocalCluster (processes, 1 thread
    each) per worker count, and/or the threaded scheduler per thread count.  Result reduced to
    two numbers (sum of floors, count of unflyable cells).  Target: 2 workers >= 1.6x faster.
``--kernels [--city helsinki|rotterdam] [--repeat 3]``
    issue 36 item 3, single core (CPU time of this process, kernels on the same visibility
    heights, interleaved runs, median): the occlusion scan's rate (cells x directions / s),
    the DOP-floor kernel of today (``_reference_floor_epoch_kernel``, kept callable) and the
    memoised one (column x satellite x epoch / s, their floors checked bit-identical), and the
    stage (``coverage_maps``, numpy runner: scan + floor + wrapping) with each kernel: cells x
    visible satellite-epochs / core-s and its ratio to the scan's rate (target >= 0.5).
``--memory --side-m 10000 --res-m 1 [--workers 2]``
    a ``side`` x ``side`` map (10^8 cells at 1 m) on a LocalCluster, written to a zarr store in
    a temporary folder (the result is never held in memory), then a few statistics read back.
    Target: peak RSS of the whole process tree < 6 GiB.

Every row reports wall time, CPU time of the process tree and peak RSS of the process tree
(process + children, sampled every 0.2 s); ratios are against the 1-worker / 1-thread row of
the same run.  "cores free" is measured in the same run: 2 threads of a pure numba loop vs 1
(2.0 = both cores free; the machine is shared, so read ratios against it).

Run:  /work/venv/bin/python benchmarks/bench_coverage_scale.py [--default] [--cells 1e7]
      [--workers 1,2] [--threads 1,2] [--memory --side-m 10000 --res-m 1] [--city rotterdam]
      [--kernels]
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
import tempfile
import threading
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import dask
import dask.array as da
import numba
import numpy as np
import psutil
import xarray as xr

from skyroute.pipeline.settings import DEFAULT_SCENARIO, load_scenario
from skyroute.stages import coverage as cv
from skyroute.stages.almanac import sky_geometry
from skyroute.stages.grid import Grid
from skyroute.stages.surface import build_surface

CITIES = {"rotterdam": "rotterdam-canyon", "helsinki": "helsinki-medical"}
GIB = 1024.0 ** 3


# ----------------------------------------------------------------------------- inputs

def scenario_inputs(name: str, res_m: float | None = None):
    """(surface, terrain, az_deg, el_deg, scenario) of a catalog scenario, the grid at
    ``res_m`` [m] (default: the scenario's own)."""
    sc = load_scenario(name)
    g = sc.grid
    if res_m is not None and res_m != g.resolution_m:
        g = Grid.from_bounds(g.crs, *g.bounds, res_m)
    b = sc.data.buildings
    t = sc.data.terrain
    ds = build_surface(g, buildings_path=b.path if b else None,
                       buildings_format=b.format if b else None,
                       storey_height_m=b.storey_height_m if b else 3.0,
                       terrain_path=t.path if t else None,
                       vertical_datum=t.vertical_datum if t else None)
    xmin, ymin, xmax, ymax = g.bounds
    lon, lat = g.to_lonlat((xmin + xmax) / 2, (ymin + ymax) / 2)
    times = np.array([np.datetime64(x.replace(tzinfo=None), "s") for x in sc.mission_times_utc()])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        sky = sky_geometry(sc.data.almanacs, times, float(lat), float(lon),
                           float(np.median(ds["terrain"].values)),
                           mask_deg=sc.gnss.elevation_mask_deg)
    return ds["surface"], ds["terrain"], sky["az_deg"], sky["el_deg"], sc


def mirror_tiled(base: xr.DataArray, ny: int, nx: int, chunks: tuple[int, int]) -> xr.DataArray:
    """``base`` mirror-tiled (no seams) to ``ny`` x ``nx`` cells, lazily: every dask block is cut
    from ``base`` by index arithmetic (the tiled map is never held anywhere)."""
    src = np.ascontiguousarray(base.values, dtype=np.float32)
    by, bx = src.shape

    def mirror(idx: np.ndarray, n: int) -> np.ndarray:
        k = idx % (2 * n)
        return np.where(k < n, k, 2 * n - 1 - k)

    def block(block_info=None):
        (y0, y1), (x0, x1) = block_info[None]["array-location"]
        return src[np.ix_(mirror(np.arange(y0, y1), by), mirror(np.arange(x0, x1), bx))]

    arr = da.map_blocks(block, chunks=da.core.normalize_chunks(chunks, (ny, nx)),
                        dtype=np.float32, meta=np.empty((0, 0), np.float32))
    g0 = Grid.from_dataarray(base)
    g = Grid(g0.crs_wkt, g0.x0, g0.y1, nx, ny, g0.resolution_m)
    out = xr.DataArray(arr, dims=("y", "x"), coords=g.coords(), name="surface",
                       attrs=dict(base.attrs))
    return out.rio.write_crs(g.crs)


def auto_chunks(base: xr.DataArray, shape: tuple[int, int], el: xr.DataArray, mask: float,
                n_thr: int) -> tuple[tuple[int, int], int, int]:
    """(blocks of ``chunks="auto"``, halo [cells], max satellites per epoch) for the tiled map
    (mirror tiling keeps the relief, hence the halo, of ``base``)."""
    e = el.values
    n_sat = int(np.sum(np.isfinite(e) & (e >= mask), axis=1).max())
    halo = cv._halo_cells(base.values, cv._min_el(e, mask), Grid.from_dataarray(base).resolution_m)
    return cv._auto_block_cells(shape, halo, n_sat, n_thr), halo, n_sat


# ----------------------------------------------------------------------------- measuring

class TreeMonitor:
    """Peak RSS [bytes] of this process + all its children (sum, sampled every ``dt_s``) and
    CPU time [s] of the tree (children alive at the end; workers live through a measurement)."""

    def __init__(self, dt_s: float = 0.2):
        self.dt_s = dt_s
        self.peak = 0
        self._stop = threading.Event()
        self._proc = psutil.Process()

    def _procs(self) -> list[psutil.Process]:
        return [self._proc] + self._proc.children(recursive=True)

    def rss(self) -> int:
        total = 0
        for p in self._procs():
            try:
                total += p.memory_info().rss
            except psutil.Error:
                pass
        return total

    def cpu_s(self) -> float:
        total = 0.0
        for p in self._procs():
            try:
                c = p.cpu_times()
                total += c.user + c.system
            except psutil.Error:
                pass
        return total

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, self.rss())
            self._stop.wait(self.dt_s)

    def __enter__(self) -> TreeMonitor:
        self.peak = self.rss()
        self.cpu0 = self.cpu_s()
        self.t0 = time.perf_counter()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def snapshot_cpu(self) -> None:
        """Record the tree's CPU time now (before children, e.g. workers, exit)."""
        self.cpu_snap = self.cpu_s() - self.cpu0

    def __exit__(self, *exc) -> None:
        self.wall = time.perf_counter() - self.t0
        self.cpu = max(self.cpu_s() - self.cpu0, getattr(self, "cpu_snap", 0.0))
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self.rss())


@numba.njit(nogil=True, cache=True)
def _spin(n: int) -> float:
    s = 0.0
    for i in range(n):
        s += math.sqrt(i + s * 1e-9)
    return s


def cores_free(n: int = 60_000_000) -> float:
    """Effective cores for 2 threads right now: 2 x t(1 thread) / t(2 threads, 2x work)."""
    _spin(10)

    def run(k: int) -> float:
        ts = [threading.Thread(target=_spin, args=(n,)) for _ in range(k)]
        t0 = time.perf_counter()
        for t in ts:
            t.start()
        for t in ts:
            t.join()
        return time.perf_counter() - t0

    return 2.0 * run(1) / run(2)


def load() -> str:
    return "load avg " + " ".join(f"{v:.2f}" for v in os.getloadavg())


ROWS: list[tuple] = []


def row(case: str, cells: int, blocks: str, mon: TreeMonitor, ratio: float | None) -> None:
    free = getattr(mon, "free", float("nan"))
    ROWS.append((case, cells, blocks, mon.wall, mon.cpu, mon.peak / GIB, free, ratio))
    print(f"  {case}: {mon.wall:.2f} s wall, {mon.cpu:.2f} s CPU, peak RSS {mon.peak / GIB:.2f} GiB"
          f" ({load()})", flush=True)


def measured(fn: Callable[[], object]) -> tuple[TreeMonitor, object]:
    """Run ``fn`` under a :class:`TreeMonitor`; ``mon.free``: cores free just before."""
    free = cores_free(20_000_000)
    with TreeMonitor() as mon:
        out = fn()
    mon.free = free
    return mon, out


def print_table() -> None:
    print()
    print(f"{'case':<46} {'cells':>12} {'blocks':>12} {'wall s':>8} {'CPU s':>8} "
          f"{'ns/cell':>8} {'RSS GiB':>8} {'free':>5} {'speed-up':>9}")
    for case, cells, blocks, wall, cpu, rss, free, ratio in ROWS:
        r = f"{ratio:8.2f}x" if ratio is not None else f"{'':>9}"
        print(f"{case:<46} {cells:>12,d} {blocks:>12} {wall:>8.2f} {cpu:>8.2f} "
              f"{1e9 * wall / cells:>8.1f} {rss:>8.2f} {free:>5.2f} {r}")
    print("free: cores free just before the run (2 threads of a numba loop vs 1; 2.00 = idle "
          "machine); speed-up: vs the first row of its group, best of --repeat runs")


def describe(arr: da.Array) -> str:
    ny, nx = (len(c) for c in arr.chunks)
    return f"{ny}x{nx} of {max(arr.chunks[0])}"


def warm(az, el) -> None:
    """JIT: compile / load from numba's cache every kernel specialisation used below."""
    g = Grid.from_bounds("EPSG:32631", 600000.0, 5700000.0, 600080.0, 5700080.0, 2.0)
    s = np.zeros(g.shape, np.float32)
    s[10:20, 10:20] = 20.0
    surf = g.dataarray(s, "surface", units="m")
    cv.coverage_maps(surf, az, el)
    cv.coverage_maps(surf, az, el, chunks=20).compute(scheduler="sync")


# ----------------------------------------------------------------------------- modes

def bench_default(args) -> None:
    surf, terrain, az, el, sc = scenario_inputs(DEFAULT_SCENARIO)
    kw = dict(thresholds=sc.gnss.dop_thresholds, dop=sc.gnss.dop_kind,
              floor_m=terrain + sc.constraints.min_altitude_agl_m,
              ceiling_m=terrain + sc.constraints.max_altitude_agl_m,
              mask_deg=sc.gnss.elevation_mask_deg)
    warm(az, el)
    n_sat = int(np.sum(el.values >= sc.gnss.elevation_mask_deg, axis=1).max())
    print(f"\n[default] {sc.name}: surface {surf.shape} at {Grid.from_dataarray(surf).resolution_m:g} m"
          f" = {surf.size:,d} cells, {el.sizes['time']} epochs, {el.sizes['sat']} satellites "
          f"(<= {n_sat} above the mask), thresholds {list(kw['thresholds'])}")
    best = None
    for _ in range(args.repeat):
        mon, ref = measured(lambda: cv.coverage_maps(surf, az, el, **kw))
        best = mon if best is None or mon.wall < best.wall else best
    row(f"{sc.name}: numpy runner (1 thread)", surf.size, "1 (numpy)", best, None)
    base = None
    for n in (1, 2):
        best = None
        for _ in range(args.repeat):
            ds = cv.coverage_maps(surf, az, el, chunks="auto", **kw)
            mon, got = measured(lambda ds=ds, n=n: ds.compute(scheduler="threads", num_workers=n))
            best = mon if best is None or mon.wall < best.wall else best
        assert np.array_equal(got["coverage_floor"].values, ref["coverage_floor"].values,
                              equal_nan=True), "chunked result differs from the numpy runner"
        base = base or best.wall
        row(f"{sc.name}: auto chunks, {n} thread(s)", surf.size,
            describe(ds["coverage_floor"].data[0]), best, base / best.wall)


def tiled_case(args, n_cells: float | None = None, side: int | None = None):
    base, _, az, el, sc = scenario_inputs(CITIES[args.city], args.res_m)
    mask = sc.gnss.elevation_mask_deg
    if side is None:
        ny0, nx0 = base.shape
        k = math.sqrt(n_cells / (ny0 * nx0))
        ny, nx = math.ceil(ny0 * k), math.ceil(n_cells / math.ceil(ny0 * k))
    else:
        ny = nx = side
    n_thr = len(sc.gnss.dop_thresholds)
    chunks, halo, n_sat = auto_chunks(base, (ny, nx), el, mask, n_thr)
    if args.chunk:
        chunks = (args.chunk, args.chunk)
    big = mirror_tiled(base, ny, nx, chunks)
    kw = dict(thresholds=sc.gnss.dop_thresholds, dop=sc.gnss.dop_kind, mask_deg=mask,
              chunks=chunks)
    res = Grid.from_dataarray(base).resolution_m
    relief = float(base.max() - base.min())
    print(f"\n[tiled] {sc.name} surface {base.shape} at {res:g} m (relief {relief:.1f} m) "
          f"mirror-tiled to {ny} x {nx} = {ny * nx / 1e6:.1f} M cells; halo {halo} cells at "
          f"{cv._min_el(el.values, mask):.1f} deg; blocks {chunks}; <= {n_sat} satellites "
          f"per epoch, {el.sizes['time']} epochs")
    return big, az, el, kw


def reduced(ds: xr.Dataset) -> list:
    """Two numbers that need every block of the coverage result."""
    return [da.nansum(ds["coverage_floor"].data.astype(np.float64)), ds["unflyable"].data.sum()]


def bench_scaling(args) -> None:
    big, az, el, kw = tiled_case(args, n_cells=args.cells)
    warm(az, el)
    ds = cv.coverage_maps(big, az, el, **kw)
    graph = ds["coverage_floor"].data
    blocks = describe(graph[0])
    split = big.data.npartitions < cv._EPOCH_SPLIT_BELOW_BLOCKS
    print(f"  graph: {len(graph.__dask_graph__())} tasks for coverage_floor, one DOP task per "
          f"{'block and epoch' if split else 'block'}")
    results = {}
    if args.threads:
        base = None
        for n in [int(v) for v in args.threads.split(",")]:
            best = None
            for _ in range(args.repeat):
                mon, r = measured(lambda n=n: dask.compute(*reduced(ds), scheduler="threads",
                                                           num_workers=n))
                best = mon if best is None or mon.wall < best.wall else best
            results[("threads", n)] = r
            base = base or best.wall
            row(f"tiled, threaded scheduler, {n} thread(s)", big.size, blocks, best, base / best.wall)
    if args.workers:
        from dask.distributed import Client, LocalCluster

        counts = [int(v) for v in args.workers.split(",")]
        clusters = {}
        try:
            for n in counts:  # all clusters up first: runs then alternate (fair under drift)
                cl = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                  dashboard_address=":0", silence_logs=logging.ERROR)
                c = Client(cl, set_as_default=False)
                c.run(warm, az, el)
                clusters[n] = (cl, c)
            best: dict[int, TreeMonitor] = {}
            for _ in range(args.repeat):
                for n in counts:
                    client = clusters[n][1]
                    mon, r = measured(lambda client=client: client.gather(client.compute(reduced(ds))))
                    results[("workers", n)] = r
                    if n not in best or mon.wall < best[n].wall:
                        best[n] = mon
                    print(f"    {n} worker(s): {mon.wall:.2f} s, cores free before {mon.free:.2f} "
                          f"({load()})", flush=True)
            for n in counts:
                row(f"tiled, LocalCluster {n} worker(s) x 1 thread", big.size, blocks, best[n],
                    best[counts[0]].wall / best[n].wall)
        finally:
            for cl, c in clusters.values():
                c.close()
                cl.close()
    vals = list(results.values())
    for v in vals[1:]:
        assert np.isclose(float(v[0]), float(vals[0][0]), rtol=1e-12) and int(v[1]) == int(vals[0][1])
    if vals:
        print(f"  all runs agree: sum of floors {float(vals[0][0]):.6e} m, "
              f"{int(vals[0][1]):,d} unflyable cell-thresholds")


def bench_memory(args) -> None:
    from dask.distributed import Client, LocalCluster

    side = int(round(args.side_m / args.res_m))
    big, az, el, kw = tiled_case(args, side=side)
    warm(az, el)
    n = int(args.workers.split(",")[-1]) if args.workers else 2
    with tempfile.TemporaryDirectory(prefix="skyroute-cov-") as tmp:
        store = Path(tmp) / "coverage.zarr"
        free = cores_free(20_000_000)
        with TreeMonitor() as mon:
            with LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                              dashboard_address=":0", silence_logs=logging.ERROR) as cl, Client(cl) as client:
                client.run(warm, az, el)
                print(f"  LocalCluster up ({n} workers x 1 thread), tree RSS "
                      f"{mon.rss() / GIB:.2f} GiB ({load()})", flush=True)
                t0 = time.perf_counter()
                ds = cv.coverage_maps(big, az, el, **kw)
                t_graph = time.perf_counter() - t0
                blocks = describe(ds["coverage_floor"].data[0])
                n_tasks = len(ds["coverage_floor"].data.__dask_graph__())
                t0 = time.perf_counter()
                ds.to_zarr(store, mode="w", consolidated=False)
                t_write = time.perf_counter() - t0
                back = xr.open_zarr(store, consolidated=False)
                t0 = time.perf_counter()
                frac = back["unflyable"].mean(("y", "x")).values
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN: unflyable
                    med = back["coverage_floor"].isel(y=slice(0, None, 50),
                                                      x=slice(0, None, 50)).median(("y", "x")).values
                t_read = time.perf_counter() - t0
                mon.snapshot_cpu()
        size = sum(f.stat().st_size for f in store.rglob("*") if f.is_file())
    print(f"  coverage_maps (checks, halo pass, graph of {n_tasks} tasks): {t_graph:.1f} s; "
          f"compute + write zarr: {t_write:.1f} s; read back stats: {t_read:.1f} s; "
          f"zarr {size / 1e6:.0f} MB")
    print(f"  thresholds {back['threshold'].values.tolist()}: unflyable fraction "
          f"{np.round(frac, 4).tolist()}, median floor (1/50 sample) {np.round(med, 2).tolist()} m")
    mon.free = free
    row(f"{side}x{side} map, {n} workers, to zarr (whole run)", big.size, blocks, mon, None)
    print(f"  peak RSS of the process tree {mon.peak / GIB:.2f} GiB (target < 6 GiB); "
          f"compute+write {t_write:.1f} s = {1e9 * t_write / big.size:.0f} ns/cell")


def bench_kernels(args) -> None:
    """Issue 36 item 3: the floor kernels and the stage per core against the occlusion scan."""
    from skyroute.stages.dop import los_rows
    from skyroute.stages.occlusion import visibility_heights_numpy
    from skyroute.stages.orbits import epoch_directions

    name = CITIES[args.city] if args.kernels_city_given else DEFAULT_SCENARIO
    surf, _, az, el, sc = scenario_inputs(name)
    thr = np.unique(np.asarray(sc.gnss.dop_thresholds, np.float64))
    kind = cv.dop_kind_index(sc.gnss.dop_kind)
    mask = sc.gnss.elevation_mask_deg
    cell = Grid.from_dataarray(surf).resolution_m
    s2 = np.ascontiguousarray(surf.values, np.float32)
    dirs = epoch_directions(cv._grid_azimuth(az.values, surf), el.values, mask)
    rows = [np.ascontiguousarray(los_rows(a, e)) for a, e in dirs]
    work = s2.size * sum(a.size for a, _ in dirs)  # cells x visible satellite-epochs
    warm(az, el)
    hs = [np.ascontiguousarray(visibility_heights_numpy(s2, a, e, cell)) for a, e in dirs]
    for fn in (cv._reference_floor_epoch_kernel, cv._floor_epoch_kernel):
        fn(hs[0], rows[0], thr, kind, np.full((thr.size,) + s2.shape, -np.inf))

    def scan() -> None:
        for a, e in dirs:
            visibility_heights_numpy(s2, a, e, cell)

    outs = {}

    def floors(fn) -> Callable[[], None]:
        def run() -> None:
            out = np.full((thr.size,) + s2.shape, -np.inf)
            for h, g in zip(hs, rows, strict=True):
                fn(h, g, thr, kind, out)
            outs[fn] = out
        return run

    kw = dict(thresholds=sc.gnss.dop_thresholds, dop=sc.gnss.dop_kind, mask_deg=mask)
    stage_out = {}

    def stage(fn) -> Callable[[], None]:
        def run() -> None:
            saved = cv._floor_epoch_kernel
            cv._floor_epoch_kernel = fn
            try:
                stage_out[fn] = cv.coverage_maps(surf, az, el, **kw)["coverage_floor"].values
            finally:
                cv._floor_epoch_kernel = saved
        return run

    new, ref = cv._floor_epoch_kernel, cv._reference_floor_epoch_kernel
    cases = {"occlusion scan": scan, "floor kernel, today": floors(ref),
             "floor kernel, memoised": floors(new), "stage, today's kernel": stage(ref),
             "stage, memoised kernel": stage(new)}
    cpu: dict[str, list[float]] = {k: [] for k in cases}
    print(f"\n[kernels] {sc.name}: surface {s2.shape} = {s2.size:,d} cells at {cell:g} m, "
          f"{len(dirs)} epochs, {work / s2.size / len(dirs):.1f} visible satellites per epoch, "
          f"{sc.gnss.dop_kind} thresholds {thr.tolist()}; single thread, CPU s of this process, "
          f"median of {args.repeat} interleaved runs ({load()})", flush=True)
    for _ in range(args.repeat):
        for k, fn in cases.items():
            c0 = time.process_time()
            fn()
            cpu[k].append(time.process_time() - c0)
    assert np.array_equal(outs[ref], outs[new]), "memoised floors differ from today's kernel"
    assert np.array_equal(stage_out[ref], stage_out[new], equal_nan=True), "stage floors differ"
    med = {k: float(np.median(v)) for k, v in cpu.items()}
    rate = {k: work / t for k, t in med.items()}
    r_scan = rate["occlusion scan"]
    print(f"{'case':<28}{'CPU s':>8}{'rate /s/core':>15}{'vs scan':>9}")
    for k in cases:
        print(f"{k:<28}{med[k]:>8.3f}{rate[k]:>15.3e}{rate[k] / r_scan:>8.2f}x")
    print(f"floor kernel: memoised / today {rate['floor kernel, memoised'] / rate['floor kernel, today']:.2f}x "
          f"(floors bit-identical); stage throughput / scan rate: today "
          f"{rate['stage, today' + chr(39) + 's kernel'] / r_scan:.2f}, memoised "
          f"{rate['stage, memoised kernel'] / r_scan:.2f} (target >= 0.50); {load()}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--default", action="store_true", help="time the default scenario")
    ap.add_argument("--cells", type=float, default=None, help="tiled map size for --workers/--threads")
    ap.add_argument("--workers", default=None, help="LocalCluster worker counts, e.g. 1,2")
    ap.add_argument("--threads", default=None, help="threaded-scheduler thread counts, e.g. 1,2")
    ap.add_argument("--memory", action="store_true", help="the side x side map to zarr")
    ap.add_argument("--kernels", action="store_true",
                    help="floor kernels and stage per core vs the occlusion scan (issue 36)")
    ap.add_argument("--side-m", type=float, default=10000.0)
    ap.add_argument("--res-m", type=float, default=None,
                    help="cell size [m] of the tiled maps (default: the scenario's)")
    ap.add_argument("--city", choices=sorted(CITIES), default="rotterdam")
    ap.add_argument("--chunk", type=int, default=None, help="block side [cells] (default: auto)")
    ap.add_argument("--repeat", type=int, default=2, help="runs per case (best is kept)")
    args = ap.parse_args()
    import distributed.deploy.local  # noqa: F401  (create its loggers, then quiet them)

    for name in ["distributed", *[n for n in logging.root.manager.loggerDict if n.startswith("distributed.")]]:
        logging.getLogger(name).setLevel(logging.ERROR)
    args.kernels_city_given = any(a.startswith("--city") for a in sys.argv[1:])
    if not (args.default or args.cells or args.memory or args.kernels):
        args.default, args.cells = True, 1e7
        args.workers = args.workers or "1,2"
    if args.memory and args.res_m is None:
        args.res_m = 1.0
    print(f"{os.cpu_count()} CPUs, {psutil.virtual_memory().total / GIB:.1f} GiB RAM; {load()}; "
          f"cores free (2 threads of a numba loop vs 1): {cores_free():.2f}")
    if args.default:
        bench_default(args)
    if args.cells:
        bench_scaling(args)
    if args.memory:
        bench_memory(args)
    if args.kernels:
        bench_kernels(args)
    if ROWS:
        print_table()
    print(f"\n{load()}; cores free now: {cores_free():.2f}")
    print("targets: default scenario < 10 s on 2 cores; 2 workers >= 1.6x faster than 1 on "
          ">= 1e7 cells; 10^8 cells at 1 m with peak RSS < 6 GiB")


if __name__ == "__main__":
    main()
