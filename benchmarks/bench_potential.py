"""Numerical potential field (seed 004 III-B) against lattice A* and BIT*, and its scale.

    python benchmarks/bench_potential.py --quick     # < 60 s on an idle 2-core machine
    python benchmarks/bench_potential.py             # whole AOIs for (a), a full recompute in (b)
    python benchmarks/bench_potential.py --quick --part b   # only the scale part (b)

(a) helsinki-medical and rotterdam-canyon, STEP I without a GNSS constraint (clearance floor of
    r_p, AGL bounds, no-fly zones), potential vs astar vs bitstar: the STEP I chain is timed at
    the energy model's speeds and smoothed by STEP III's corner trajectory
    (``step3.smooth_chain``), sampled every 0.5 m; the exact clearance of every sample is the
    brute-force 3-D distance to the raw surface prisms (every cell a closed box from below the
    ground up to ``surface``) within 120 m (larger distances print as 120).  Printed: min and
    mean clearance [m], length [m], f (eq. 11, the problem's costs of the chain), STEP I compute
    time [s].  Acceptance: potential min clearance >= r_p and >= A*'s - 0.05 m, its mean larger.
    Figure ``<out>/potential_<case>.png``: the three smoothed paths over the surface heights
    (plan view) and their exact clearance along the path, with r_p.
    ``--quick`` plans on the mission's box plus 150 m instead of the whole AOI (all planners).
    Budget 5 s per planner (the scenarios'; level cap 20 s).
(b) the potential field on the whole Helsinki AOI at 2 m x 2 m x 2 m, 0-80 m AGL (~527 x 874 x
    37 voxels): bitmap, EDT, skeleton, wave times (wall and this process's CPU); the compiled
    EDT against scipy's and the row-wise skeleton against the voxel-wise one (the previous
    implementations) in the same run (ratios); then a new
    30 m x 30 m obstacle up to 60 m AGL next to the path: :func:`update_potential` time vs
    the full field's (ratio); without ``--quick`` also the full recompute after the change and
    the check that both potentials agree.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import warnings
from pathlib import Path

import numba
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_planner import case_inputs  # noqa: E402

from skyroute.pipeline.cache import Cache  # noqa: E402
from skyroute.stages.planning import potential as P  # noqa: E402
from skyroute.stages.planning.deconflict import chain_timing  # noqa: E402
from skyroute.stages.planning.problem import build_problem, xyz_from_agl  # noqa: E402
from skyroute.stages.planning.step1 import plan_step1  # noqa: E402
from skyroute.stages.planning.step3 import smooth_chain  # noqa: E402

REACH_M = 120.0


@numba.njit(cache=True)
def _prism_clearance(pts, surf, x0, y1, res, reach):
    """Brute force: least distance [m] from each point to the closed prisms of the cells within
    ``reach`` [m] (capped at ``reach``)."""
    ny, nx = surf.shape
    out = np.empty(pts.shape[0])
    w = int(math.ceil(reach / res)) + 1
    for n in range(pts.shape[0]):
        x, y, z = pts[n, 0], pts[n, 1], pts[n, 2]
        c0 = int(math.floor((x - x0) / res))
        r0 = int(math.floor((y1 - y) / res))
        best = reach * reach
        for r in range(max(0, r0 - w), min(ny, r0 + w + 1)):
            cy0 = y1 - (r + 1) * res
            dy = max(cy0 - y, y - (cy0 + res), 0.0)
            if dy * dy >= best:
                continue
            for c in range(max(0, c0 - w), min(nx, c0 + w + 1)):
                cx0 = x0 + c * res
                dx = max(cx0 - x, x - (cx0 + res), 0.0)
                dz = max(z - surf[r, c], 0.0)
                d2 = dx * dx + dy * dy + dz * dz
                if d2 < best:
                    best = d2
        out[n] = math.sqrt(best)
    return out


@numba.njit(cache=True, parallel=True)
def _ridge_voxelwise(free, D, nz, ny, nx, min_d, out):
    """The skeleton's ridge test as it was before (voxel by voxel, the 13 lines innermost):
    the reference of the before / after ratio."""
    for k in numba.prange(nz):
        for i in range(ny):
            for j in range(nx):
                out[k, i, j] = 0
                if free[k, i, j] == 0 or D[k, i, j] < min_d:
                    continue
                d = D[k, i, j]
                for o in range(13):
                    dk, di, dj = o // 9 - 1, (o // 3) % 3 - 1, o % 3 - 1
                    ka, ia, ja = k + dk, i + di, j + dj
                    kb, ib, jb = k - dk, i - di, j - dj
                    da = -1.0
                    db = -1.0
                    if 0 <= ka < nz and 0 <= ia < ny and 0 <= ja < nx and free[ka, ia, ja] != 0:
                        da = D[ka, ia, ja]
                    if 0 <= kb < nz and 0 <= ib < ny and 0 <= jb < nx and free[kb, ib, jb] != 0:
                        db = D[kb, ib, jb]
                    if d >= da and d >= db and (d > da or d > db):
                        out[k, i, j] = 1
                        break


def _problem(d, s, box_m: float | None):
    surf = d["surface"][[v for v in ("terrain", "terrain_min", "surface") if v in d["surface"]]].load()
    clear, nofly = d["clearance"]["min_altitude_m"].load(), d["clearance"]["nofly"].load()
    if box_m is not None:
        xs, ys = (s.start_xy[0], s.goal_xy[0]), (s.start_xy[1], s.goal_xy[1])
        sel = dict(x=slice(min(xs) - box_m, max(xs) + box_m), y=slice(max(ys) + box_m, min(ys) - box_m))
        surf, clear, nofly = surf.sel(**sel), clear.sel(**sel), nofly.sel(**sel)
    p0 = xyz_from_agl(surf, *s.start_xy, s.start_agl_m)
    p1 = xyz_from_agl(surf, *s.goal_xy, s.goal_agl_m)
    wind = d["wind"]
    return build_problem(surf, clear, None, None, None, wind, s.vehicle, s.weights, p0, p1, s.min_agl_m, s.max_agl_m,
                         nofly=nofly, check_endpoints=False), surf


def _clearance_of(problem, surf, wp):
    t, _, _ = chain_timing(problem, wp)
    traj = smooth_chain(problem, wp, np.diff(t))
    ts = np.linspace(0.0, traj.duration_s, max(2, int(traj.duration_s * 20)))   # ~0.5 m at 10 m/s
    pts = traj.sample(ts)
    step = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    g = problem.grid
    d = _prism_clearance(pts, np.ascontiguousarray(surf["surface"].values, dtype=np.float64), g.x0, g.y1,
                         g.resolution_m, REACH_M)
    return d, float(step.sum()), float(step.max()), pts


COLOURS = {"potential": "tab:red", "astar": "tab:blue", "bitstar": "tab:green"}


def comparison_figure(name: str, surf, problem, paths: dict, out_png: Path) -> None:
    """Plan view of the smoothed paths over the surface heights, and the exact clearance [m]
    along each path (distance along the path [m]) with r_p."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from skyroute.stages.figures import add_map_furniture, grow_until_unclipped, image_extent

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(13, 5.6), layout="constrained", width_ratios=(1.1, 1))
    ext = image_extent(surf["surface"])
    im = ax.imshow(surf["surface"].values, extent=ext, cmap="Greys", origin="upper")
    fig.colorbar(im, ax=ax, shrink=0.8, label="surface height [m]")
    allp = np.concatenate([p for p, _ in paths.values()])
    pad = 80.0
    for planner, (pts, d) in paths.items():
        ax.plot(pts[:, 0], pts[:, 1], color=COLOURS[planner], lw=1.6, label=planner)
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        bx.plot(s, d, color=COLOURS[planner], lw=1.2,
                label=f"{planner}: min {d.min():.1f} m, mean {d.mean():.1f} m")
    ax.plot(*problem.start_xyz[:2], "k^", ms=8, label="start")
    ax.plot(*problem.goal_xyz[:2], "k*", ms=10, label="goal")
    (x0, y0), (x1, y1) = allp[:, :2].min(axis=0) - pad, allp[:, :2].max(axis=0) + pad
    half = 0.5 * max(x1 - x0, y1 - y0)                # a square window: narrow paths stay readable
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    ax.set_xlim(cx - half, cx + half)
    ax.set_ylim(cy - half, cy + half)
    ax.set_aspect("equal")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.xaxis.set_major_locator(plt.MaxNLocator(4))
    ax.yaxis.set_major_locator(plt.MaxNLocator(5))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{name}: STEP I paths smoothed by STEP III")
    ax.legend(loc="lower right", fontsize=8)
    add_map_furniture(ax)
    bx.axhline(problem.vehicle.r_p_m, color="k", ls="--", lw=1, label=f"r_p = {problem.vehicle.r_p_m:g} m")
    bx.set_xlabel("distance along the path [m]")
    bx.set_ylabel(f"exact clearance to the surface prisms [m] (capped at {REACH_M:g})")
    bx.set_title("clearance along the path")
    bx.set_ylim(0, None)
    bx.legend(fontsize=8, loc="best")
    grow_until_unclipped(fig)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=110)
    plt.close(fig)


def compare(name: str, cache: Cache, quick: bool, out_dir: Path | None = None) -> list[str]:
    sc, d, s, _ = case_inputs(name, cache)
    pr, surf = _problem(d, s, 150.0 if quick else None)
    rp = pr.vehicle.r_p_m
    rows, res, paths = [], {}, {}
    for planner in ("potential", "astar", "bitstar"):
        r = plan_step1(pr, planner=planner, time_budget_s=5.0)
        if not r.solved:
            rows.append(f"  {name:17s} {planner:9s} {r.status}: {r.reason}")
            continue
        clr, L, gap, pts = _clearance_of(pr, surf, r.waypoints)
        res[planner] = (clr.min(), clr.mean(), L, r.f)
        paths[planner] = (pts, clr)
        rows.append(f"  {name:17s} {planner:9s} {clr.min():7.2f} {clr.mean():7.2f} {L:8.1f} {r.f:9.1f} "
                    f"{r.compute_s:7.1f} {len(r.waypoints):4d}")
    if "potential" in res and "astar" in res:
        p, a = res["potential"], res["astar"]
        ok = p[0] >= rp - 1e-9 and p[0] >= a[0] - 0.05 and p[1] > a[1]
        rows.append(f"  {name:17s} acceptance (min >= r_p = {rp:g} m, >= A* min - 0.05 m, mean > A*'s): "
                    f"{'PASS' if ok else 'FAIL'}; length cost {p[2] / a[2] - 1:+.1%}, f {p[3] / a[3] - 1:+.1%}")
    if out_dir is not None and paths:
        png = out_dir / f"potential_{name}.png"
        comparison_figure(name, surf, pr, paths, png)
        rows.append(f"  figure: {png}")
    return rows


def scale(cache: Cache, quick: bool) -> list[str]:
    sc, d, s, _ = case_inputs("helsinki-medical", cache)
    pr, _ = _problem(d, s, None)
    rows = []
    c0, t0 = time.process_time(), time.perf_counter()
    vm = P.occupancy_bitmap(pr, 2.0, 2.0)
    t_bm = time.perf_counter() - t0
    st, gl = P.entry_voxel(pr, vm, pr.start_xyz), P.entry_voxel(pr, vm, pr.goal_xyz)
    vw = 1.0 / math.tan(math.radians(pr.vehicle.max_flight_path_angle_deg))
    t1 = time.perf_counter()
    pf = P.potential_field(vm, gl, [st], vertical_weight=vw)
    t_full = time.perf_counter() - t1
    cpu = time.process_time() - c0
    tm = pf.timings_s
    rows.append(f"  bitmap {vm.shape[2]} x {vm.shape[1]} x {vm.shape[0]} = {vm.free.size / 1e6:.1f} M voxels "
                f"({vm.free.mean():.0%} free): bitmap {t_bm:.2f} s, EDT {tm['clearance']:.1f} s, skeleton "
                f"{tm['skeleton']:.1f} s, wave {tm['wave']:.1f} s; total {t_bm + t_full:.1f} s wall, {cpu:.1f} s CPU")
    # the EDT: compiled (now) vs scipy (before), same process, same bitmap
    c1, t1 = time.process_time(), time.perf_counter()
    d_new = P.clearance_map(vm)
    w_new, c_new = time.perf_counter() - t1, time.process_time() - c1
    c1, t1 = time.process_time(), time.perf_counter()
    d_old = P._edt_scipy(vm.obstacle, vm, (True, True, True, True))
    w_old, c_old = time.perf_counter() - t1, time.process_time() - c1
    rows.append(f"  EDT compiled {w_new:.2f} s wall / {c_new:.2f} s CPU vs scipy {w_old:.2f} s / {c_old:.2f} s: "
                f"ratio {w_new / w_old:.2f} (wall), max |difference| {float(np.abs(d_new - d_old).max()):.1e} m")
    # the skeleton: row-wise ridge kernel (now) vs the voxel-by-voxel one (before)
    nz, ny, nx = vm.shape
    ref = np.zeros(vm.shape, np.uint8)
    _ridge_voxelwise(vm.free.view(np.uint8)[:1, :2, :2], d_new[:1, :2, :2], 1, 2, 2, 0.0, ref[:1, :2, :2])   # compile
    c1, t1 = time.process_time(), time.perf_counter()
    sk_new = P.skeleton(vm, d_new)
    w_new, c_new = time.perf_counter() - t1, time.process_time() - c1
    c1, t1 = time.process_time(), time.perf_counter()
    _ridge_voxelwise(vm.free.view(np.uint8), d_new, nz, ny, nx, 0.0, ref)
    w_old, c_old = time.perf_counter() - t1, time.process_time() - c1
    rows.append(f"  skeleton row-wise {w_new:.2f} s wall / {c_new:.2f} s CPU vs voxel-wise {w_old:.2f} s / {c_old:.2f} s: "
                f"ratio {w_new / w_old:.2f} (wall), identical: {bool(np.array_equal(sk_new, ref.view(bool)))}")
    t4 = time.perf_counter()
    P.potential_field(vm, gl, [st], vertical_weight=vw, clearance_m=pf.clearance_m, until=st)
    rows.append(f"  the same field with the wave stopped at the start (as plan_potential does; EDT reused): "
                f"{time.perf_counter() - t4:.1f} s")
    # a new obstacle next to the middle of the path (a building, or a dense traffic zone)
    path = P.descend(pf, st)
    k, i, j = np.unravel_index(path[len(path) // 2], vm.shape)
    free2, obst2 = vm.free.copy(), vm.obstacle.copy()
    top = int(min(vm.shape[0], round(60.0 / vm.dz_m)))
    box = (slice(0, top), slice(max(0, i - 7), i + 8), slice(max(0, j + 3), j + 18))
    free2[box], obst2[box] = False, True
    t2 = time.perf_counter()
    up = P.update_potential(pf, free2, obst2)
    t_up = time.perf_counter() - t2
    rows.append(f"  incremental update (30 m x 30 m x 60 m obstacle at the path's middle): {t_up:.2f} s, "
                f"{up.timings_s['affected_voxels'] / 1e6:.2f} M voxels re-waved; full field {t_full:.1f} s; "
                f"ratio update / full = {t_up / t_full:.3f}")
    if not quick:
        vm2 = P.VoxelMap(vm.x0_m, vm.y1_m, vm.z0_m, vm.voxel_m, vm.dz_m, vm.block, free2, obst2, vm.floor_m,
                         vm.ceiling_m)
        t3 = time.perf_counter()
        U, _ = P.wave_propagation(free2, [np.ravel_multi_index(gl, vm.shape)], steps_m=up.steps_m,
                                  weight=up.weight())
        full2 = P.clearance_map(vm2)
        t_re = time.perf_counter() - t3
        same = np.allclose(U, up.potential_m, rtol=1e-12, atol=1e-9) and np.allclose(full2, up.clearance_m, atol=1e-5)
        rows.append(f"  full recompute after the change (EDT + wave): {t_re:.1f} s; incremental == full: {same}")
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="mission box for (a), no full recompute in (b)")
    ap.add_argument("--cache", default="/tmp/skyroute-bench-cache", help="pipeline cache of the maps")
    ap.add_argument("--out", default="/tmp/skyroute-bench-potential", help="directory of the comparison figures")
    ap.add_argument("--part", choices=("a", "b", "ab"), default="ab", help="run only part (a) or (b) (default both)")
    a = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    cache = Cache(a.cache)
    t = time.perf_counter()
    if "a" in a.part:
        print("(a) STEP I chains smoothed by STEP III's corner trajectory; exact clearance to the surface prisms [m]")
        print(f"  {'case':17s} {'planner':9s} {'min':>7s} {'mean':>7s} {'length':>8s} {'f eq.11':>9s} "
              f"{'STEP I s':>7s} {'wps':>4s}")
        for name in ("helsinki-medical", "rotterdam-canyon"):
            for row in compare(name, cache, a.quick, Path(a.out)):
                print(row, flush=True)
    if "b" in a.part:
        print("(b) scale: potential field on the whole Helsinki AOI, 2 m voxels, 0-80 m AGL")
        for row in scale(cache, a.quick):
            print(row, flush=True)
    print(f"total {time.perf_counter() - t:.0f} s")


if __name__ == "__main__":
    main()
