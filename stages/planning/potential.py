"""Numerical potential field global planner (seed 004 section III-B, after Barraquand, Langlois
and Latombe 1992): STEP I as a W-potential on a 3-D bitmap of the workspace.

Pipeline of :func:`plan_potential`
----------------------------------
1. **Bitmap** (:func:`occupancy_bitmap`): voxels of ``block`` x ``block`` raster cells
   (``voxel_m = block * resolution``) and ``dz_m`` [m] high, levels aligned so that a chosen
   altitude (the start's) is a voxel centre.  A voxel is *free* only if every point of it
   (closed box) is an admissible altitude of every cell of its footprint:
   ``max(floor_m over the block) <= z_bottom`` and ``z_top <= min(ceiling_m over the block)``.
   ``floor_m`` is the problem's conservative floor (clearance floor of the sphere r_p, minimum
   AGL, coverage floor, no-fly = +inf), itself a bound for every point of its cell, so every
   point of a free voxel is a valid state (wind limits aside: the chain is checked by
   :meth:`PlanningProblem.motion_valid` in the end).  *Obstacle* voxels are those that meet
   the region below the floor; voxels blocked only by the ceiling are not obstacles (the
   ceiling is a rule, not a surface).
2. **Clearance** (:func:`clearance_map`): scipy's exact Euclidean distance transform [m] from
   every voxel centre to the nearest obstacle voxel centre.
3. **W-skeleton** (:func:`skeleton`): its ridges: free voxels where, along at least one of the
   13 lines through the voxel, the clearance is >= both neighbours and > one of them (the
   cells where the wave fronts from different obstacles meet, seed Fig. 9, here from the EDT).
   Under the ceiling of open areas the top free layer is a ridge (clearance grows upward).
4. **Connection** (seed III-B): the goal (and start) voxels climb the clearance (steepest
   ascent over the 26 neighbours) until they reach the skeleton; the climbs join the skeleton.
5. **W-potential**: one wave (compiled Dijkstra over the 26 neighbours) from the goal voxel
   where a move costs its length times the mean of the two voxels' weights, 1 on the skeleton
   and ``off_skeleton_weight`` (K, default 8) elsewhere; vertical offsets count
   ``vertical_weight`` times their length (default ``1 / tan(max flight-path angle)``, the
   horizontal distance a climb needs).  As in the seed's eq. 6 the potential grows away from
   the goal along the skeleton and faster off it, so gradient motion first joins the
   skeleton, then slides along it; with K -> infinity it is Barraquand-Latombe's two-stage
   potential.  Every free voxel reached by the wave has a neighbour of strictly lower
   potential (the one its value came from): no local minima.
6. **Gradient motion** (:func:`descend`): from the start voxel to the 26-neighbour of least
   potential until the goal voxel.
7. **Waypoint reduction** (:func:`reduce_waypoints`): greedy shortcuts of the voxel chain that
   are valid motions of the problem (floors, ceilings, flight-path angle, wind) and keep the
   clearance of the part they replace (least EDT along the shortcut >= least EDT of the
   replaced voxels - ``clearance_tol_m``), so STEP II / III get a short polygonal chain that
   keeps the standoff.  (The seed flies minimum-jerk segments between the waypoints,
   :func:`minimum_jerk`; in skyroute STEP III does the timing.)

:func:`update_potential` recomputes the field after a local change of the bitmap (a new
obstacle, a dense traffic zone, seed III-A): the EDT and skeleton in a window around the
change and the wave only on the voxels whose potential came through the change.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import ndimage

from skyroute.stages import control
from skyroute.stages.base import InputError
from skyroute.stages.planning.problem import PlanningProblem

DEFAULT_OFF_SKELETON_WEIGHT = 8.0
DEFAULT_VOXEL_M = 2.0       # [m] default voxel edge (snapped to a multiple of the grid resolution)
DEFAULT_MARGIN_M = 250.0    # [m] default workspace: the start-goal box plus this margin
# 26 neighbour offsets (dk, di, dj), centre excluded, in the kernels' order
_OFFS = np.array([(dk, di, dj) for dk in (-1, 0, 1) for di in (-1, 0, 1) for dj in (-1, 0, 1)
                  if (dk, di, dj) != (0, 0, 0)], dtype=np.int64)

# offset o' of the kernel run on (y, x, z) arrays -> index of the same move in _OFFS (z, y, x)
_P2O = np.array([int(np.nonzero((_OFFS == (dc, da, db)).all(axis=1))[0][0]) for da, db, dc in _OFFS],
                dtype=np.int64)


# --------------------------------------------------------------------------- bitmap


@dataclass(frozen=True, eq=False)
class VoxelMap:
    """3-D occupancy bitmap.  Voxel (k, i, j) is the box x in [x0 + j h, x0 + (j+1) h],
    y in [y1 - (i+1) h, y1 - i h], z in [z0 + k dz, z0 + (k+1) dz] [m] (row i from the north,
    like the rasters; ``h = voxel_m``).  ``free`` / ``obstacle`` (nz, ny, nx) bool;
    ``floor_m`` / ``ceiling_m`` (ny, nx): the block maximum floor / minimum ceiling [m]."""

    x0_m: float
    y1_m: float
    z0_m: float
    voxel_m: float
    dz_m: float
    block: int
    free: np.ndarray
    obstacle: np.ndarray
    floor_m: np.ndarray
    ceiling_m: np.ndarray

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.free.shape)  # type: ignore[return-value]

    @property
    def x(self) -> np.ndarray:
        """Voxel centre x [m] per column."""
        return self.x0_m + (np.arange(self.shape[2]) + 0.5) * self.voxel_m

    @property
    def y(self) -> np.ndarray:
        """Voxel centre y [m] per row."""
        return self.y1_m - (np.arange(self.shape[1]) + 0.5) * self.voxel_m

    @property
    def z(self) -> np.ndarray:
        """Voxel centre z [m] per level."""
        return self.z0_m + (np.arange(self.shape[0]) + 0.5) * self.dz_m

    def index_of(self, xyz) -> np.ndarray:
        """(n, 3) int (k, i, j) of the voxels containing points (n, 3) [m] (may be outside)."""
        p = np.atleast_2d(np.asarray(xyz, dtype=float))
        return np.stack([np.floor((p[:, 2] - self.z0_m) / self.dz_m),
                         np.floor((self.y1_m - p[:, 1]) / self.voxel_m),
                         np.floor((p[:, 0] - self.x0_m) / self.voxel_m)], axis=1).astype(np.int64)

    def centres(self, flat) -> np.ndarray:
        """(n, 3) [m] centres of voxels given by flat C-order indices."""
        k, i, j = np.unravel_index(np.asarray(flat, dtype=np.int64), self.shape)
        return np.stack([self.x[j], self.y[i], self.z[k]], axis=-1)

    def inside(self, kij) -> np.ndarray:
        kij = np.atleast_2d(kij)
        return np.all((kij >= 0) & (kij < np.array(self.shape)), axis=1)


def default_voxel_m(resolution_m: float) -> float:
    """The default voxel size [m]: the multiple of the grid resolution nearest to
    :data:`DEFAULT_VOXEL_M` (at least one cell)."""
    return resolution_m * max(1, round(DEFAULT_VOXEL_M / resolution_m))


def occupancy_bitmap(problem: PlanningProblem, voxel_m: float | None = None, dz_m: float | None = None,
                     z_ref_m: float | None = None, bounds_m: tuple[float, float, float, float] | None = None
                     ) -> VoxelMap:
    """The conservative 3-D bitmap of ``problem`` (module docstring, step 1).

    ``voxel_m`` [m]: horizontal voxel size, a whole multiple of the grid resolution (default
    :func:`default_voxel_m`); ``dz_m`` [m]: voxel height (default ``voxel_m``); ``z_ref_m``
    [m]: an altitude that falls on a voxel centre (default the start's); ``bounds_m``
    (xmin, ymin, xmax, ymax) [m]: the part of the grid to cover (default all; snapped outward
    to cells, clipped to the grid).  Rows / columns that do not fill a whole block are left out
    (east / south edge)."""
    g = problem.grid
    res = g.resolution_m
    h = default_voxel_m(res) if voxel_m is None else float(voxel_m)
    block = int(round(h / res))
    if block < 1 or abs(block * res - h) > 1e-6 * res:
        raise InputError(f"voxel_m {voxel_m} m must be a whole multiple of the grid resolution {res:g} m")
    dz = h if dz_m is None else float(dz_m)
    if not (math.isfinite(dz) and dz > 0):
        raise InputError(f"dz_m {dz_m} must be > 0 [m]")
    r0, c0, r1, c1 = 0, 0, g.ny, g.nx
    if bounds_m is not None:
        xmin, ymin, xmax, ymax = (float(v) for v in bounds_m)
        c0, c1 = max(0, math.floor((xmin - g.x0) / res)), min(g.nx, math.ceil((xmax - g.x0) / res))
        r0, r1 = max(0, math.floor((g.y1 - ymax) / res)), min(g.ny, math.ceil((g.y1 - ymin) / res))
    NY, NX = (r1 - r0) // block, (c1 - c0) // block
    if NY < 1 or NX < 1:
        raise InputError(f"voxel_m {h:g} m is larger than the area ({r1 - r0} x {c1 - c0} cells of {res:g} m)")
    rs, cs = slice(r0, r0 + NY * block), slice(c0, c0 + NX * block)
    fl = problem.floor_m[rs, cs].reshape(NY, block, NX, block).max(axis=(1, 3))
    ce = problem.ceiling_m[rs, cs].reshape(NY, block, NX, block).min(axis=(1, 3))
    ok = np.isfinite(fl) & (fl <= ce)
    if not ok.any():
        raise InputError(f"{problem.label}: no column admits any altitude (floors above ceilings everywhere)")
    zmin, zmax = float(fl[ok].min()), float(ce[ok].max())
    zr = problem.start_xyz[2] if z_ref_m is None else float(z_ref_m)
    z0 = zr - dz / 2 - math.floor((zr - dz / 2 - zmin) / dz) * dz
    nz = int(math.floor((zmax - z0) / dz + 1e-9))
    if nz < 1:
        raise InputError(f"{problem.label}: dz_m {dz:g} m is taller than the admissible altitude band")
    zlo = z0 + np.arange(nz) * dz
    zhi = zlo + dz
    free = (fl[None] <= zlo[:, None, None]) & (zhi[:, None, None] <= ce[None])
    obstacle = zlo[:, None, None] < fl[None]
    return VoxelMap(g.x0 + c0 * res, g.y1 - r0 * res, float(z0), h, dz, block, free, obstacle, fl, ce)


def clearance_map(vmap: VoxelMap) -> np.ndarray:
    """(nz, ny, nx) float32 [m]: exact Euclidean distance (scipy EDT, anisotropic sampling) from
    each voxel centre to the nearest obstacle voxel centre, the AOI's lateral edges counting as
    obstacles one voxel beyond the bitmap (nothing is known there; seed III-A: cells
    "intersected by the W boundary" are occupied); 0 on obstacles."""
    return _edt(vmap.obstacle, vmap, (True, True, True, True))


def _edt(obstacle: np.ndarray, vmap: VoxelMap, walls: tuple[bool, bool, bool, bool]) -> np.ndarray:
    """EDT [m] of ~obstacle with obstacle walls one voxel beyond the (north, south, west, east)
    sides flagged in ``walls`` (the AOI's edges: nothing is known beyond them): the compiled
    separable exact transform (Felzenszwalb-Huttenlocher, lines in parallel; equal to scipy's
    ``distance_transform_edt`` on the padded array, a test checks it)."""
    from skyroute.stages.planning.potential_kernels import edt_kernel

    pn, ps, pw, pe = (bool(w) for w in walls)
    obstacle = np.ascontiguousarray(obstacle, dtype=bool)
    if not (obstacle.any() or pn or ps or pw or pe):
        return np.full(obstacle.shape, 1e9, dtype=np.float32)
    out = np.empty(obstacle.shape, dtype=np.float32)
    edt_kernel(obstacle, float(vmap.dz_m), float(vmap.voxel_m), pn, ps, pw, pe, out)
    return out


def _edt_scipy(obstacle: np.ndarray, vmap: VoxelMap, walls: tuple[bool, bool, bool, bool]) -> np.ndarray:
    """:func:`_edt` by scipy's ``distance_transform_edt`` on the padded array (the reference)."""
    pn, ps, pw, pe = (int(bool(w)) for w in walls)
    a = np.pad(obstacle, ((0, 0), (pn, ps), (pw, pe)), constant_values=True)
    if not a.any():
        return np.full(obstacle.shape, 1e9, dtype=np.float32)
    d = ndimage.distance_transform_edt(~a, sampling=(vmap.dz_m, vmap.voxel_m, vmap.voxel_m))
    return d[:, pn:d.shape[1] - ps, pw:d.shape[2] - pe].astype(np.float32)


def skeleton(vmap: VoxelMap, clearance_m: np.ndarray, min_clearance_m: float = 0.0) -> np.ndarray:
    """(nz, ny, nx) bool: the W-skeleton, ridges of ``clearance_m`` among the free voxels with
    clearance >= ``min_clearance_m`` [m] (module docstring, step 3)."""
    from skyroute.stages.planning.potential_kernels import ridge_kernel

    out = np.zeros(vmap.shape, dtype=np.uint8)
    nz, ny, nx = vmap.shape
    ridge_kernel(vmap.free.view(np.uint8), np.ascontiguousarray(clearance_m, dtype=np.float32), nz, ny, nx,
                 float(min_clearance_m), out)
    return out.view(bool)


def neighbour_steps_m(vmap: VoxelMap, vertical_weight: float = 1.0) -> np.ndarray:
    """(26,) [m] metric length of each 26-neighbour move (kernel order), vertical part x
    ``vertical_weight``."""
    d = _OFFS.astype(float) * np.array([vmap.dz_m * vertical_weight, vmap.voxel_m, vmap.voxel_m])
    return np.sqrt((d * d).sum(axis=1))


def wave_propagation(free: np.ndarray, seeds, seed_values=None, steps_m=None, weight=None,
                     stop: np.ndarray | None = None, target: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Wave propagation (26 neighbours, compiled Dijkstra) over the ``free`` voxels (nz, ny, nx)
    from ``seeds`` (flat indices) with ``seed_values`` [m] (default 0).  ``steps_m`` (26,):
    length of each neighbour move (default 1 for all: the seed's L^1 wave, a BFS hop count);
    ``weight`` (nz, ny, nx) > 0: cost per metre of each voxel (a move costs its length times
    the mean of its two voxels' weights; default 1).  Returns (potential (nz, ny, nx) float64,
    inf where not reached; parent (nz, ny, nx) int8: offset index towards the neighbour the
    value came from, -1 for seeds and unreached).  A diagonal move needs every voxel of the box
    it spans free (no corner cutting: the segment between the centres stays in free voxels).
    ``target`` (a flat index): stop once it is reached; only the voxels of potential up to
    about the target's keep a value (the rest inf), enough for the gradient motion from it."""
    from skyroute.stages.planning.potential_kernels import wave_kernel, zfast_kernel, zslow_kernel

    free = np.ascontiguousarray(free, dtype=bool)
    shape = free.shape
    if free.ndim != 3:
        raise InputError(f"free must be a (nz, ny, nx) bool array, got shape {shape}")
    seeds = np.atleast_1d(np.asarray(seeds, dtype=np.int64))
    if seeds.size == 0 or seeds.min() < 0 or seeds.max() >= free.size:
        raise InputError("seeds must be flat indices of voxels of the bitmap")
    if not free.ravel()[seeds].all():
        raise InputError("every seed must be a free voxel")
    vals = np.zeros(seeds.size) if seed_values is None else np.broadcast_to(np.asarray(seed_values, float), seeds.shape)
    steps = np.ones(26) if steps_m is None else np.asarray(steps_m, dtype=float)
    if steps.shape != (26,) or not (steps > 0).all():
        raise InputError("steps_m must be 26 positive lengths [m]")
    w = (np.ones(free.size, dtype=np.float32) if weight is None
         else np.ascontiguousarray(weight, dtype=np.float32).ravel())
    if w.size != free.size or not (w > 0).all():
        raise InputError("weight must be > 0 on the bitmap's shape")
    st = np.zeros(1, dtype=np.int8) if stop is None else stop
    if shape[0] < shape[2]:
        # the kernel runs with the shortest axis (the levels) fastest in memory: a voxel's 26
        # neighbours then lie in 3 short runs (1.6 x faster on the Helsinki bitmap)
        pshape = (shape[1], shape[2], shape[0])
        fr = np.empty(pshape, dtype=bool)
        zfast_kernel(free, fr)
        wp = np.empty(pshape, dtype=np.float32)
        zfast_kernel(w.reshape(shape), wp)
        k, i, j = np.unravel_index(seeds, shape)
        ps = np.ravel_multi_index((i, j, k), pshape)
        U = np.full(free.size, np.inf)
        U[ps] = np.minimum(U[ps], vals)
        parent = np.full(free.size, -1, dtype=np.int8)
        tp = -1
        if target is not None:
            tk, ti, tj = np.unravel_index(int(target), shape)
            tp = int(np.ravel_multi_index((ti, tj, tk), pshape))
        n = wave_kernel(fr.ravel().view(np.uint8), wp.ravel(), *pshape, steps[_P2O], ps, U, parent, st, tp)
        U_out = np.empty(shape)
        parent_out = np.empty(shape, dtype=np.int8)
        zslow_kernel(U.reshape(pshape), parent.reshape(pshape), _P2O.astype(np.int8), U_out, parent_out)
        U, parent = U_out, parent_out
    else:
        U = np.full(free.size, np.inf)
        U[seeds] = np.minimum(U[seeds], vals)
        parent = np.full(free.size, -1, dtype=np.int8)
        n = wave_kernel(free.ravel().view(np.uint8), w, *shape, steps, seeds, U, parent, st,
                        -1 if target is None else int(target))
    if n < 0:
        control.check()
    return U.reshape(shape), parent.reshape(shape)


# --------------------------------------------------------------------------- potential field


@dataclass(frozen=True, eq=False)
class PotentialField:
    """A W-potential on a bitmap.  ``clearance_m`` (EDT [m]), ``skeleton`` (bool, connections
    included), ``potential_m`` (float64 [m of weighted length], inf where not reached),
    ``parent`` (int8, see :func:`wave_propagation`), all (nz, ny, nx); ``goal`` (k, i, j);
    ``connections``: flat indices added to the skeleton by the start / goal connection;
    ``timings_s``: wall clock of each step [s]; ``partial``: the wave stopped at the start."""

    vmap: VoxelMap
    clearance_m: np.ndarray
    skeleton: np.ndarray
    potential_m: np.ndarray
    parent: np.ndarray
    goal: tuple[int, int, int]
    off_skeleton_weight: float
    vertical_weight: float
    connections: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    timings_s: dict = field(default_factory=dict)
    partial: bool = False       # the wave stopped at a target (``until``): values only up to it

    @property
    def steps_m(self) -> np.ndarray:
        return neighbour_steps_m(self.vmap, self.vertical_weight)

    def weight(self, skel: np.ndarray | None = None) -> np.ndarray:
        s = self.skeleton if skel is None else skel
        return np.where(s, np.float32(1.0), np.float32(self.off_skeleton_weight)).astype(np.float32)


def connect_to_skeleton(vmap: VoxelMap, clearance_m: np.ndarray, skel: np.ndarray, kij) -> np.ndarray:
    """Flat indices of the steepest clearance ascent from voxel ``kij`` (free) to the skeleton
    (seed III-B: "search for cells with largest distance value in its neighbourhood ... until a
    cell in S is reached"); ends early at a local maximum of the clearance."""
    from skyroute.stages.planning.potential_kernels import ascent_kernel

    nz, ny, nx = vmap.shape
    out = np.empty(nz + ny + nx + 8 * max(nz, ny, nx), dtype=np.int64)
    n = ascent_kernel(vmap.free.view(np.uint8), np.ascontiguousarray(clearance_m, np.float32),
                      skel.view(np.uint8), nz, ny, nx, int(kij[0]), int(kij[1]), int(kij[2]), out)
    return out[:n].copy()


def potential_field(vmap: VoxelMap, goal_kij, connect=(), *, off_skeleton_weight: float = DEFAULT_OFF_SKELETON_WEIGHT,
                    vertical_weight: float = 1.0, min_clearance_m: float = 0.0,
                    clearance_m: np.ndarray | None = None, time_limit_s: float = math.inf,
                    until=None) -> PotentialField:
    """The W-potential of ``vmap`` towards the free voxel ``goal_kij`` (k, i, j) (module
    docstring, steps 2-5).  ``connect``: further voxels (the start's) joined to the skeleton
    by clearance ascent; ``off_skeleton_weight`` >= 1 (K); ``vertical_weight`` > 0;
    ``clearance_m``: a precomputed :func:`clearance_map`.  Past ``time_limit_s`` [s] the wave
    stops with TimeoutError (a cancel request raises Interrupted).  ``until`` (k, i, j): stop
    the wave once that voxel (the start) is reached (:func:`wave_propagation` ``target``; such
    a field cannot be given to :func:`update_potential`)."""
    if not (math.isfinite(off_skeleton_weight) and off_skeleton_weight >= 1):
        raise InputError(f"off_skeleton_weight {off_skeleton_weight} must be >= 1 (1: plain shortest path)")
    if not (math.isfinite(vertical_weight) and vertical_weight > 0):
        raise InputError(f"vertical_weight {vertical_weight} must be > 0")
    g = tuple(int(v) for v in goal_kij)
    if not (vmap.inside(np.array(g))[0] and vmap.free[g]):
        raise InputError(f"goal voxel {g} is not a free voxel of the bitmap {vmap.shape}")
    t = {}
    t0 = time.perf_counter()
    D = clearance_map(vmap) if clearance_m is None else clearance_m
    t["clearance"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    skel = skeleton(vmap, D, min_clearance_m)
    t["skeleton"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    conn = [connect_to_skeleton(vmap, D, skel, g)]
    for c in connect:
        c = tuple(int(v) for v in c)
        if vmap.inside(np.array(c))[0] and vmap.free[c]:
            conn.append(connect_to_skeleton(vmap, D, skel, c))
    conn_idx = np.unique(np.concatenate(conn))
    skel = skel.copy()
    skel.ravel()[conn_idx] = True
    t["connect"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    pf = PotentialField(vmap, D, skel, np.empty(0), np.empty(0, np.int8), g, float(off_skeleton_weight),
                        float(vertical_weight), conn_idx, t)
    with control.StopFlag(time_limit_s) as stop:
        tgt = None if until is None else int(np.ravel_multi_index(tuple(int(c) for c in until), vmap.shape))
        U, parent = wave_propagation(vmap.free, [np.ravel_multi_index(g, vmap.shape)], None, pf.steps_m,
                                     pf.weight(), stop.array, tgt)
        if stop.expired:
            raise TimeoutError(f"potential field: the wave did not finish within {time_limit_s:g} s")
    t["wave"] = time.perf_counter() - t1
    t["total"] = time.perf_counter() - t0
    return replace(pf, potential_m=U, parent=parent, partial=until is not None)


def descend(pf: PotentialField, start_kij) -> np.ndarray:
    """Gradient motion (seed III-C): flat voxel indices from ``start_kij`` to the 26-neighbour
    of least potential, while strictly lower; ends at the goal voxel when the start was
    reached by the wave."""
    from skyroute.stages.planning.potential_kernels import descent_kernel

    nz, ny, nx = pf.vmap.shape
    v = int(np.ravel_multi_index(tuple(int(c) for c in start_kij), pf.vmap.shape))
    out = np.empty(pf.potential_m.size if pf.potential_m.size < 10_000_000 else 10_000_000, dtype=np.int64)
    n = descent_kernel(pf.vmap.free.ravel().view(np.uint8), pf.potential_m.ravel(), nz, ny, nx, v, out)
    return out[:n].copy()


def update_potential(pf: PotentialField, free_new: np.ndarray, obstacle_new: np.ndarray | None = None
                     ) -> PotentialField:
    """The field after a local change of the bitmap (new ``free`` mask, and ``obstacle`` mask:
    default ``~free_new & pf.vmap.obstacle | (pf.vmap.free & ~free_new)``, i.e. newly blocked
    voxels are obstacles).  Recomputes the EDT and skeleton in a window around the changed
    voxels (the window is wide enough for every voxel whose nearest obstacle can change: the
    largest clearance of the old field plus the change's extent), keeps the start / goal
    connections, and re-runs the wave only from the voxels whose potential came through a
    changed voxel (their parent chain) and the neighbours of changed weights: the result is
    the same as a full :func:`potential_field` with the same skeleton.  ``pf`` is not modified."""
    from skyroute.stages.planning.potential_kernels import (
        affected_kernel,
        neighbours_kernel,
        reseed_kernel,
        wave_kernel,
    )

    t0 = time.perf_counter()
    if pf.partial:
        raise InputError("update_potential needs a whole field: compute it with potential_field(..., until=None)")
    vm = pf.vmap
    free_new = np.ascontiguousarray(free_new, dtype=bool)
    if free_new.shape != vm.shape:
        raise InputError(f"free_new has shape {free_new.shape}; expected the bitmap's {vm.shape}")
    if obstacle_new is None:
        obstacle_new = vm.obstacle | (vm.free & ~free_new)
    obstacle_new = np.ascontiguousarray(obstacle_new, dtype=bool)
    if not free_new[pf.goal]:
        raise InputError(f"the change blocks the goal voxel {pf.goal}: compute a new field")
    changed = (free_new != vm.free) | (obstacle_new != vm.obstacle)
    if not changed.any():
        return pf
    nz, ny, nx = vm.shape
    idx = np.argwhere(changed)
    lo, hi = idx.min(axis=0), idx.max(axis=0) + 1
    ext = float(np.linalg.norm((hi - lo) * np.array([vm.dz_m, vm.voxel_m, vm.voxel_m])))
    dmax = float(pf.clearance_m[vm.free].max()) if vm.free.any() else 0.0
    dmax = min(dmax, 1e6)
    pad = np.ceil((dmax + vm.voxel_m) / np.array([vm.dz_m, vm.voxel_m, vm.voxel_m])).astype(int) + 1
    shape = np.array(vm.shape)
    ilo, ihi = np.maximum(lo - pad, 0), np.minimum(hi + pad, shape)           # D may change here
    opad = pad + np.ceil(ext / np.array([vm.dz_m, vm.voxel_m, vm.voxel_m])).astype(int)
    olo, ohi = np.maximum(ilo - opad, 0), np.minimum(ihi + opad, shape)      # obstacles that matter
    vm2 = replace(vm, free=free_new, obstacle=obstacle_new)
    D = pf.clearance_m.copy()
    osl = tuple(slice(a, b) for a, b in zip(olo, ohi, strict=True))
    Dw = _edt(obstacle_new[osl], vm, (olo[1] == 0, ohi[1] == ny, olo[2] == 0, ohi[2] == nx))
    isl = tuple(slice(a, b) for a, b in zip(ilo, ihi, strict=True))
    D[isl] = Dw[tuple(slice(a - o, b - o) for a, b, o in zip(ilo, ihi, olo, strict=True))]
    # ridges depend on the neighbours: recompute one voxel beyond the window (context of 2)
    rlo, rhi = np.maximum(ilo - 1, 0), np.minimum(ihi + 1, shape)
    clo, chi = np.maximum(rlo - 1, 0), np.minimum(rhi + 1, shape)
    csl = tuple(slice(a, b) for a, b in zip(clo, chi, strict=True))
    sub_vm = replace(vm2, free=np.ascontiguousarray(free_new[csl]), obstacle=obstacle_new[csl])
    ridges = skeleton(sub_vm, np.ascontiguousarray(D[csl]))
    skel = pf.skeleton.copy()
    skel[tuple(slice(a, b) for a, b in zip(rlo, rhi, strict=True))] = ridges[
        tuple(slice(a - c, b - c) for a, b, c in zip(rlo, rhi, clo, strict=True))]
    conn = pf.connections[free_new.ravel()[pf.connections]]
    skel.ravel()[conn] = True
    skel &= free_new
    t_maps = time.perf_counter() - t0
    # weights / freedom that changed
    wchg = changed | (skel != pf.skeleton)
    cidx = np.flatnonzero(wchg.ravel())
    U = pf.potential_m.ravel().copy()
    parent = pf.parent.ravel().copy()
    # a move needs its whole box free (no corner cutting): a voxel whose freedom changed
    # touches the moves between any two of its neighbours
    through = np.zeros(U.size, dtype=np.uint8)
    neighbours_kernel(np.flatnonzero((free_new != vm.free).ravel()), nz, ny, nx, through)
    through |= wchg.ravel().view(np.uint8)
    aff = np.empty(U.size, dtype=np.uint8)
    affected_kernel(parent, through, nz, ny, nx, aff)
    g = int(np.ravel_multi_index(pf.goal, vm.shape))
    aff[g] = 0
    U[aff.view(bool)] = np.inf
    parent[aff.view(bool)] = -1
    near = np.zeros(U.size, dtype=np.uint8)
    neighbours_kernel(cidx, nz, ny, nx, near)
    cand = np.flatnonzero(aff.view(bool) | near.view(bool))
    freeu8 = free_new.ravel().view(np.uint8)
    w = np.where(skel, np.float32(1.0), np.float32(pf.off_skeleton_weight)).astype(np.float32).ravel()
    U[~free_new.ravel()] = np.inf
    parent[~free_new.ravel()] = -1
    steps = pf.steps_m
    seeds = reseed_kernel(freeu8, w, U, parent, nz, ny, nx, steps, cand, aff)
    if seeds.size:
        wave_kernel(freeu8, w, nz, ny, nx, steps, seeds, U, parent, np.zeros(1, np.int8))
    t = {"maps": t_maps, "affected_voxels": int(aff.sum()), "total": time.perf_counter() - t0}
    return replace(pf, vmap=vm2, clearance_m=D, skeleton=skel, potential_m=U.reshape(vm.shape),
                   parent=parent.reshape(vm.shape), connections=conn, timings_s=t)


# --------------------------------------------------------------------------- waypoints


def entry_voxel(problem: PlanningProblem, vmap: VoxelMap, xyz, radius: int = 4) -> tuple[int, int, int] | None:
    """The free voxel nearest ``xyz`` [m] (within ``radius`` voxels) whose centre is joined to
    ``xyz`` by a valid motion of ``problem`` (None if there is none)."""
    p = np.asarray(xyz, dtype=float)
    k0, i0, j0 = vmap.index_of(p)[0]
    r = int(radius)
    kk, ii, jj = np.meshgrid(np.arange(k0 - r, k0 + r + 1), np.arange(i0 - r, i0 + r + 1),
                             np.arange(j0 - r, j0 + r + 1), indexing="ij")
    kij = np.stack([kk.ravel(), ii.ravel(), jj.ravel()], axis=1)
    kij = kij[vmap.inside(kij)]
    kij = kij[vmap.free[kij[:, 0], kij[:, 1], kij[:, 2]]]
    if kij.size == 0:
        return None
    c = np.stack([vmap.x[kij[:, 2]], vmap.y[kij[:, 1]], vmap.z[kij[:, 0]]], axis=1)
    d = np.linalg.norm(c - p, axis=1)
    order = np.argsort(d, kind="stable")
    kij, c, d = kij[order], c[order], d[order]
    ok = problem.motion_valid(np.repeat(p[None], len(c), 0), c) | (d < 1e-9)
    if not ok.any():
        return None
    return tuple(int(v) for v in kij[int(np.argmax(ok))])


def reduce_waypoints(problem: PlanningProblem, pf: PotentialField, chain, clearance_tol_m: float | None = None
                     ) -> tuple[np.ndarray, bool]:
    """Greedy waypoint reduction of a chain (n, 3) [m] (module docstring, step 7): from each
    kept vertex jump to the farthest later vertex whose direct segment is a valid motion and
    whose least clearance (EDT along it, samples every voxel_m / 4) is >= the least clearance
    of the vertices it replaces minus ``clearance_tol_m`` (default one voxel_m); if no later
    vertex qualifies, the farthest valid motion, else the next vertex.  Returns (chain,
    every segment valid)."""
    from skyroute.stages.planning.potential_kernels import segment_clearance_kernel

    vm = pf.vmap
    w = np.asarray(chain, dtype=float)
    tol = vm.voxel_m if clearance_tol_m is None else float(clearance_tol_m)
    if len(w) <= 2:
        return w, bool(problem.motion_valid(w[:1], w[1:]).all()) if len(w) == 2 else True
    kij = vm.index_of(w)
    inside = vm.inside(kij)
    kc = np.clip(kij, 0, np.array(vm.shape) - 1)
    dv = np.where(inside & vm.free[kc[:, 0], kc[:, 1], kc[:, 2]], pf.clearance_m[kc[:, 0], kc[:, 1], kc[:, 2]], 0.0)
    dv[0] = dv[-1] = np.inf                  # start / goal may sit in a partly blocked voxel
    nz, ny, nx = vm.shape
    out = [0]
    i = 0
    all_ok = True
    freeu8 = vm.free.view(np.uint8)
    while i < len(w) - 1:
        control.check()
        js = np.arange(len(w) - 1, i, -1)
        ok = problem.motion_valid(np.repeat(w[i:i + 1], js.size, axis=0), w[js])
        clear = np.empty(js.size)
        segment_clearance_kernel(w[i], np.ascontiguousarray(w[js]), freeu8, pf.clearance_m, vm.x0_m, vm.y1_m,
                                 vm.z0_m, vm.voxel_m, vm.dz_m, nz, ny, nx, vm.voxel_m / 4, clear)
        # least clearance of the vertices each shortcut replaces: need[j] = min dv[i+1:j]
        cm = np.minimum.accumulate(dv[i + 1:])                      # cm[m] = min dv[i+1 .. i+1+m]
        need = np.where(js > i + 1, cm[np.maximum(js - i - 2, 0)], np.inf)
        good = ok & (clear >= need - tol)
        good |= ok & (js == i + 1)
        if good.any():
            j = int(js[np.argmax(good)])
        elif ok.any():
            j = int(js[np.argmax(ok)])
        else:
            # stuck (e.g. right above the goal, steeper than the flight-path angle allows):
            # from the previous kept vertex, the farthest valid motion beyond this one
            p = out[-2] if len(out) >= 2 else -1
            okp = (problem.motion_valid(np.repeat(w[p:p + 1], js.size, axis=0), w[js]) if p >= 0
                   else np.zeros(js.size, bool))
            if okp.any():
                out.pop()
                j = int(js[np.argmax(okp)])
            else:
                j = i + 1
                all_ok = False
        out.append(j)
        i = j
    return w[out], all_ok


def minimum_jerk(p0, p1, duration_s: float, t_s) -> np.ndarray:
    """Minimum-jerk rest-to-rest motion (seed 004 ref. [21]) from ``p0`` to ``p1`` (3,) [m] in
    ``duration_s`` [s], sampled at times ``t_s`` (m,) [s]: p0 + (p1 - p0)(10 s^3 - 15 s^4 + 6 s^5),
    s = t / T clipped to [0, 1]."""
    if not duration_s > 0:
        raise InputError(f"duration_s {duration_s} must be > 0 [s]")
    s = np.clip(np.asarray(t_s, dtype=float) / float(duration_s), 0.0, 1.0)[:, None]
    a, b = np.asarray(p0, float), np.asarray(p1, float)
    return a + (b - a) * (10 * s**3 - 15 * s**4 + 6 * s**5)


def plan_potential(problem: PlanningProblem, voxel_m: float | None = None, dz_m: float | None = None, *,
                   margin_m: float | None = DEFAULT_MARGIN_M,
                   off_skeleton_weight: float = DEFAULT_OFF_SKELETON_WEIGHT, vertical_weight: float | None = None,
                   clearance_tol_m: float | None = None, time_limit_s: float = math.inf) -> dict:
    """STEP I by the numerical potential field (module docstring).  The workspace is the
    start-goal box plus ``margin_m`` [m] (None: the whole grid); ``vertical_weight`` default
    ``1 / tan(max flight-path angle)``.  Returns a dict: ``waypoints`` (k, 3) [m] or
    None, ``reason`` ("" when solved), ``field`` (:class:`PotentialField` or None),
    ``voxel_path`` (flat indices of the gradient motion), ``valid`` (every chain segment a
    valid motion), ``compute_s``, ``stopped_by`` ("" or "time")."""
    t0 = time.perf_counter()
    w0 = control.work_clock()        # the safety cap's clock (JIT compilation excluded)
    if vertical_weight is None:
        vertical_weight = 1.0 / math.tan(math.radians(problem.vehicle.max_flight_path_angle_deg))
    res = {"waypoints": None, "reason": "", "field": None, "voxel_path": None, "valid": False, "stopped_by": ""}
    # the wave stops at the start (until=s): the field holds the potential up to the start's
    bounds = None
    if margin_m is not None:
        (xs, ys, _), (xg, yg, _) = problem.start_xyz, problem.goal_xyz
        bounds = (min(xs, xg) - margin_m, min(ys, yg) - margin_m, max(xs, xg) + margin_m, max(ys, yg) + margin_m)
    vm = occupancy_bitmap(problem, voxel_m, dz_m, bounds_m=bounds)
    s = entry_voxel(problem, vm, problem.start_xyz)
    gl = entry_voxel(problem, vm, problem.goal_xyz)
    if s is None or gl is None:
        which = "start" if s is None else "goal"
        res["reason"] = (f"{problem.label}: no free voxel of {vm.voxel_m:g} x {vm.voxel_m:g} x {vm.dz_m:g} m near "
                         f"the {which} is joined to it by a valid motion (use a smaller planner voxel)")
        res["compute_s"] = time.perf_counter() - t0
        return res
    try:
        pf = potential_field(vm, gl, [s], off_skeleton_weight=off_skeleton_weight, vertical_weight=vertical_weight,
                             time_limit_s=time_limit_s - (control.work_clock() - w0), until=s)
    except TimeoutError as exc:
        res["reason"], res["stopped_by"] = f"{problem.label}: {exc}", "time"
        res["compute_s"] = time.perf_counter() - t0
        return res
    res["field"] = pf
    if not np.isfinite(pf.potential_m[s]):
        res["reason"] = (f"{problem.label}: the start's voxel is not connected to the goal's through free voxels "
                         f"of {vm.voxel_m:g} m (altitude bounds, no-fly zones, clearance)")
        res["compute_s"] = time.perf_counter() - t0
        return res
    path = descend(pf, s)
    res["voxel_path"] = path
    chain = np.vstack([np.asarray(problem.start_xyz)[None], vm.centres(path), np.asarray(problem.goal_xyz)[None]])
    wp, ok = reduce_waypoints(problem, pf, chain, clearance_tol_m)
    res["valid"] = ok
    if ok:
        res["waypoints"] = wp
    else:
        bad = int(np.argmin(problem.motion_valid(wp[:-1], wp[1:])))
        res["reason"] = (f"{problem.label}: the potential-field path has no valid reduction near "
                         f"({wp[bad, 0]:.1f}, {wp[bad, 1]:.1f}, {wp[bad, 2]:.1f}): "
                         f"{problem.explain_motion(wp[bad], wp[bad + 1])}")
    res["compute_s"] = time.perf_counter() - t0
    return res


__all__ = ["DEFAULT_MARGIN_M", "DEFAULT_OFF_SKELETON_WEIGHT", "DEFAULT_VOXEL_M", "PotentialField", "VoxelMap",
           "clearance_map", "connect_to_skeleton", "default_voxel_m", "descend", "entry_voxel", "minimum_jerk", "neighbour_steps_m", "occupancy_bitmap", "plan_potential",
           "potential_field", "reduce_waypoints", "skeleton", "update_potential", "wave_propagation"]
