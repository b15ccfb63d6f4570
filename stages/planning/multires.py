"""Multi-resolution STEP I for the lattice A* (issue 23): coarse path, then full resolution in a corridor.

Full-resolution 3-D A* (:mod:`.grid_planner`) explores a volume that grows faster than the
area: a 5 km mission in a 6 x 6 km AOI at 2 m cells (9 M cells, 2.4 M lattice nodes) did not
finish in 20 s per level.  :func:`plan_multires` splits the search:

1. **Coarse conservative abstraction** (:func:`coarse_problem`): cells of ``factor`` grid cells
   (:func:`coarse_factor`, about :data:`COARSE_CELL_M` = 64 m, a whole number of lattice
   steps) carrying the HIGHEST floor, the LOWEST ceiling, the WORST (highest) risk and landing
   cost of their children, forbidden when any child is (no-fly, no GNSS coverage); the wind
   heights are above the lowest ground of the block.  Only the coarse cells within one coarse
   cell of the start and the goal are taken optimistically (lowest floor, highest ceiling),
   so that the full-resolution endpoints, which are valid states, are valid coarse states too.
2. **Coarse path**: weighted A* (heuristic x :data:`COARSE_WEIGHT`) on the coarse problem's
   own lattice (one node per coarse cell, the fine edges' directions).
3. **Refinement**: the full-resolution lattice A* of :func:`~.grid_planner.astar` on the
   SAME :class:`~.problem.PlanningProblem` (its maps, limits, wind and motion validator), with
   the lattice nodes outside a corridor of ``half_width`` coarse cells around the coarse path
   switched off (:func:`corridor_columns`); its heuristic is the exact 2-D cost-to-goal within
   the corridor (:func:`~.grid_planner.heuristic_2d`) times :data:`FINE_WEIGHT` plus the
   altitude term: weighted A*, whose lattice f is at most FINE_WEIGHT x the corridor's lattice
   optimum (the inflated heuristic is FINE_WEIGHT-consistent; no node is re-expanded).  Then
   :func:`~.grid_planner.refine_path` on the same problem, as for full-resolution A*.

Safety: the coarse level only chooses WHERE the full-resolution search may look; every edge of
the refined path is accepted by the full-resolution problem's motion check and every later
check (STEP III, the validator) is unchanged, so nothing in the coarse level can make a plan
less safe.  The optimality loss (corridor, weights) is measured, not bounded: on the 6 x 6 km
Helsinki AOI of issue 23 (D=4, 5.0 km) the refined f is 1.000 x that of full-resolution A*
(which needs 340 k expansions against 28 k), see ``benchmarks/bench_city_scale.py``.

The corridor (:data:`CORRIDOR_UNION`) is the union of the corridors around two coarse paths:
the conservative one and that of the OPTIMISTIC abstraction (lowest floor, highest ceiling,
least risk, forbidden only where every child is).  Heights that vary within a coarse cell make
the conservative path avoid blocks the full-resolution optimum crosses, while the optimistic
one misses the climbs: on the synthetic 6 km city (5 km mission) the conservative corridor
alone gave f 1.029 x full-resolution A*, the union 1.000 x.

Widening (counted, never timed): when the corridor holds no path, it is widened (half width x 2,
:data:`WIDEN_FACTOR`), at most :data:`MAX_WIDENINGS` times; when no coarse abstraction has a
path, or the widest corridor fails, the whole lattice is searched (plain full-resolution A*,
the result it would give).  ``info["widenings"]`` counts the steps taken.  A gap narrower than
a coarse cell blocks the conservative abstraction only: the optimistic path threads it.

:func:`plan_astar` is STEP I's A* entry (:func:`~.step1.plan_step1`): problems of at least
:data:`MULTIRES_MIN_CELLS` grid cells use :func:`plan_multires`, smaller ones (every shipped
scenario: at most 1.15 M cells) the full-resolution :func:`~.grid_planner.plan_grid` as before.

Measured (``benchmarks/bench_city_scale.py``, README "City-scale planning"): f of the refined
path / f of full-resolution A* (both refined) per mission is reported there.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numba
import numpy as np

from skyroute.stages import control
from skyroute.stages.base import InputError
from skyroute.stages.grid import Grid
from skyroute.stages.planning.grid_planner import (
    STEP_CELLS,
    EdgeCache,
    Lattice,
    astar,
    heuristic_2d,
    make_lattice,
    plan_grid,
    refine_path,
)
from skyroute.stages.planning.problem import PlanningProblem

MULTIRES_MIN_CELLS = 2_000_000   # grid cells from which STEP I's A* is multi-resolution (Monaco: 1.15 M)
COARSE_CELL_M = 64.0             # [m] target coarse cell side (a whole number of lattice steps)
HALF_WIDTH_CELLS = 3             # initial corridor half width [coarse cells] beside the coarse path (192 m)
WIDEN_FACTOR = 2                 # a widening multiplies the half width by this
MAX_WIDENINGS = 2                # corridor widenings around one coarse path before the next fallback
MAX_EXPANSIONS = 50_000_000      # per search (the coarse one and each corridor search), as plan_grid
COARSE_WEIGHT = 1.2              # weighted A* on the coarse level (its path only places the corridor)
CORRIDOR_UNION = True            # the corridor holds both the conservative and the optimistic coarse path
FINE_WEIGHT = 1.2                # corridor A* heuristic weight: lattice f <= FINE_WEIGHT x the corridor's optimum


def coarse_factor(problem: PlanningProblem, step_cells: int = STEP_CELLS,
                  coarse_cell_m: float = COARSE_CELL_M) -> int:
    """Grid cells per coarse cell side: the multiple of ``step_cells`` closest to
    ``coarse_cell_m`` [m] (at least one lattice step)."""
    if not coarse_cell_m > 0:
        raise InputError(f"coarse_cell_m {coarse_cell_m} must be > 0 [m] (e.g. 32)")
    step_m = int(step_cells) * problem.grid.resolution_m
    return int(step_cells) * max(1, int(round(coarse_cell_m / step_m)))


def _block_reduce(a: np.ndarray, f: int, how: np.ufunc) -> np.ndarray:
    """``how`` (np.maximum / np.minimum) over each block of ``f`` x ``f`` cells of ``a`` (the
    last blocks of a row / column hold the cells left over)."""
    rows = np.arange(0, a.shape[0], f)
    cols = np.arange(0, a.shape[1], f)
    return how.reduceat(how.reduceat(a, rows, axis=0), cols, axis=1)


@numba.njit(cache=True, nogil=True)
def _block_minmax_kernel(a, f, hi, lo):   # pragma: no cover - compiled
    nby, nbx = hi.shape
    ny, nx = a.shape
    for bi in range(nby):
        r0 = bi * f
        r1 = min(r0 + f, ny)
        for bj in range(nbx):
            c0 = bj * f
            c1 = min(c0 + f, nx)
            m = a[r0, c0]
            n = m
            for r in range(r0, r1):
                for c in range(c0, c1):
                    v = a[r, c]
                    if m == m and (v != v or v > m):      # NaN propagates, as np.maximum
                        m = v
                    if n == n and (v != v or v < n):
                        n = v
            hi[bi, bj] = m
            lo[bi, bj] = n


def block_minmax(a: np.ndarray, f: int) -> tuple[np.ndarray, np.ndarray]:
    """(max, min) over each block of ``f`` x ``f`` cells of the 2-D ``a`` in one pass (serial: safe in forked fleet workers):
    :func:`_block_reduce` with ``np.maximum`` and ``np.minimum``, the same values (NaN
    propagates, the last blocks hold the cells left over)."""
    a = np.ascontiguousarray(a)
    shape = (-(-a.shape[0] // f), -(-a.shape[1] // f))
    hi = np.empty(shape, a.dtype)
    lo = np.empty(shape, a.dtype)
    _block_minmax_kernel(a, int(f), hi, lo)
    return hi, lo


def _endpoint_cells(grid: Grid, pts, radius: int) -> np.ndarray:
    """(ny, nx) bool: the cells of ``grid`` within ``radius`` cells of each point (x, y)."""
    m = np.zeros(grid.shape, bool)
    for x, y, *_ in pts:
        c = int(math.floor((x - grid.x0) / grid.resolution_m))
        r = int(math.floor((grid.y1 - y) / grid.resolution_m))
        m[max(0, r - radius):r + radius + 1, max(0, c - radius):c + radius + 1] = True
    return m


def coarse_problem(problem: PlanningProblem, factor: int, optimistic: bool = False,
                   endpoint_radius: int = 1) -> PlanningProblem:
    """The coarse abstraction of ``problem`` with cells of ``factor`` x ``factor`` grid cells
    (module docstring).  Conservative (default): per coarse cell the max floor (+inf when any
    child is forbidden), min ceiling, max risk and landing cost, min ground (wind heights);
    ``optimistic``: min floor (+inf only when every child is forbidden), max ceiling, min risk
    and landing cost.  The coarse cells within ``endpoint_radius`` of the start and the goal
    are optimistic in both.  Same wind, vehicle, weights, endpoints and limits."""
    f = int(factor)
    if f < 1:
        raise InputError(f"coarse factor {factor} must be >= 1 [cells]")
    g = problem.grid
    gc = Grid(g.crs_wkt, g.x0, g.y1, -(-g.nx // f), -(-g.ny // f), g.resolution_m * f)
    memo = problem.__dict__.setdefault("_coarse_blocks", {})     # both abstractions use them
    if f not in memo:
        names = ("terrain_m", "floor_m", "ceiling_m", "risk_cost", "landing_cost")
        shared = problem.__dict__.get("_block_memo")    # the coverage levels' (build_problem(shared=))

        def reduce(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            if shared is None:
                return block_minmax(a, f)
            # keyed on the array's id: the entry holds the array, so the id is not reused meanwhile
            return shared.get(f"{id(a)}:{f}:minmax", lambda: (a, block_minmax(a, f)))[1]

        memo.clear()
        both = {name: reduce(getattr(problem, name)) for name in names}
        memo[f] = ({name: b[0] for name, b in both.items()}, {name: b[1] for name, b in both.items()})
    hi, lo = memo[f]
    opt = dict(terrain_m=hi["terrain_m"], floor_m=lo["floor_m"], ceiling_m=hi["ceiling_m"],
               risk_cost=lo["risk_cost"], landing_cost=lo["landing_cost"])
    if optimistic:
        maps = opt
    else:
        maps = dict(terrain_m=lo["terrain_m"], floor_m=hi["floor_m"], ceiling_m=lo["ceiling_m"],
                    risk_cost=hi["risk_cost"], landing_cost=hi["landing_cost"])
        ends = _endpoint_cells(gc, (problem.start_xyz, problem.goal_xyz), endpoint_radius)
        maps = {k: np.where(ends, opt[k], v) for k, v in maps.items()}
    cp = PlanningProblem(grid=gc, **maps, wind_uvw=problem.wind_uvw, vehicle=problem.vehicle,
                           weights=problem.weights, start_xyz=problem.start_xyz, goal_xyz=problem.goal_xyz,
                           dop_threshold=problem.dop_threshold,
                           label=f"{problem.label} (coarse {gc.resolution_m:g} m)",
                           wind_z_agl_m=problem.wind_z_agl_m, wind_grid=problem.wind_grid,
                           min_agl_m=problem.min_agl_m, max_agl_m=problem.max_agl_m, dop_kind=problem.dop_kind,
                           subsegment_m=problem.subsegment_m)
    if "_ratio_tiles" in problem.__dict__:     # the same wind and vehicle: the same energy-bound tiles
        object.__setattr__(cp, "_ratio_tiles", problem.__dict__["_ratio_tiles"])
    return cp


def corridor_columns(lattice: Lattice, coarse_grid: Grid, path_xyz: np.ndarray, half_width: int) -> np.ndarray:
    """(ny_l, nx_l) bool: the lattice columns whose coarse cell is within ``half_width``
    coarse cells (Chebyshev) of a coarse cell the polyline ``path_xyz`` (k, 3) [m] crosses
    (sampled every quarter coarse cell)."""
    from scipy.ndimage import maximum_filter

    res = coarse_grid.resolution_m
    p = np.asarray(path_xyz, float)[:, :2]
    pts = [p[:1]]
    for a, b in zip(p[:-1], p[1:], strict=True):
        n = max(1, int(math.ceil(np.hypot(*(b - a)) / (res / 4))))
        t = np.arange(1, n + 1)[:, None] / n
        pts.append(a + t * (b - a))
    q = np.concatenate(pts)
    c = np.clip(np.floor((q[:, 0] - coarse_grid.x0) / res).astype(np.int64), 0, coarse_grid.nx - 1)
    r = np.clip(np.floor((coarse_grid.y1 - q[:, 1]) / res).astype(np.int64), 0, coarse_grid.ny - 1)
    mark = np.zeros(coarse_grid.shape, bool)
    mark[r, c] = True
    hw = int(half_width)
    if hw > 0:
        mark = maximum_filter(mark, size=2 * hw + 1, mode="constant", cval=False)
    lc = np.clip(np.floor((lattice.x - coarse_grid.x0) / res).astype(np.int64), 0, coarse_grid.nx - 1)
    lr = np.clip(np.floor((coarse_grid.y1 - lattice.y) / res).astype(np.int64), 0, coarse_grid.ny - 1)
    return mark[np.ix_(lr, lc)]


def lattice_geometry(problem: PlanningProblem, step_cells: int = STEP_CELLS,
                     z_anchor_m: float | None = None) -> Lattice:
    """The full-resolution lattice of :func:`~.grid_planner.make_lattice` (same nodes) with no
    node evaluated yet (``valid`` all False): :func:`corridor_valid` evaluates the corridor's
    nodes only (make_lattice evaluates all of them: 11 M nodes for a 12 km AOI at 2 m)."""
    from types import SimpleNamespace

    shell = SimpleNamespace(grid=problem.grid, vehicle=problem.vehicle, floor_m=problem.floor_m,
                            ceiling_m=problem.ceiling_m, start_xyz=problem.start_xyz, goal_xyz=problem.goal_xyz,
                            state_valid=lambda p: np.zeros(len(p), bool))
    return make_lattice(shell, step_cells, z_anchor_m=z_anchor_m)


def corridor_valid(problem: PlanningProblem, lattice: Lattice, columns: np.ndarray) -> np.ndarray:
    """(nz, ny_l, nx_l) bool: ``problem.state_valid`` of the lattice nodes in the ``columns``
    (ny_l, nx_l) bool, False elsewhere (the ``valid`` of make_lattice restricted to them)."""
    valid = np.zeros(lattice.shape, bool)
    r, c = np.nonzero(columns)
    nz = lattice.z.size
    if r.size:
        pts = np.empty((nz * r.size, 3))
        pts[:, 0] = np.tile(lattice.x[c], nz)
        pts[:, 1] = np.tile(lattice.y[r], nz)
        pts[:, 2] = np.repeat(lattice.z, r.size)
        valid[:, r, c] = problem.state_valid(pts).reshape(nz, r.size)
    return valid


def _coarse_path(problem: PlanningProblem, factor: int, optimistic: bool, fine: Lattice, step_cells: int,
                 z_anchor_m: float | None, max_expansions: int, time_limit_s: float, weight: float
                 ) -> tuple[np.ndarray | None, Grid, int, str]:
    """(coarse waypoints or None, coarse grid, expansions, stopped_by) of A* on the coarse
    problem's lattice: one node per coarse cell, levels ``factor / step_cells`` times the fine
    lattice's apart (so its edges have the fine edges' directions and share their memoised
    energy bounds), heuristic :func:`heuristic_2d` x ``weight`` (weighted A*: the coarse path
    only places the corridor)."""
    cp = coarse_problem(problem, factor, optimistic=optimistic)
    if cp.endpoint_problem():          # cannot happen for valid full-resolution endpoints; kept safe
        return None, cp.grid, 0, ""
    lat = make_lattice(cp, 1, dz_m=fine.dz_m * (factor // int(step_cells)), z_anchor_m=z_anchor_m)
    h2 = heuristic_2d(cp, lat) * float(weight)
    r = astar(cp, lat, max_expansions, h2=h2, time_limit_s=time_limit_s)
    return r["waypoints"], cp.grid, int(r["expanded"]), r["stopped_by"]


def plan_multires(problem: PlanningProblem, step_cells: int = STEP_CELLS, refine: bool = True,
                  max_expansions: int = MAX_EXPANSIONS, time_limit_s: float = math.inf,
                  z_anchor_m: float | None = None, coarse_cell_m: float = COARSE_CELL_M,
                  half_width: int = HALF_WIDTH_CELLS, max_widenings: int = MAX_WIDENINGS,
                  weight: float = FINE_WEIGHT, coarse_weight: float = COARSE_WEIGHT,
                  union: bool = CORRIDOR_UNION) -> dict:
    """Multi-resolution A* (module docstring) on ``problem``; the result of
    :func:`~.grid_planner.plan_grid` (``waypoints`` or None, ``lattice_f`` of the corridor
    search, ``expanded`` = coarse + every corridor search, ``lattice`` (the full lattice, its nodes evaluated in the corridor searched),
    ``compute_s``, ``stopped_by``) plus ``multires``: ``coarse_cell_m``, ``coarse_expanded``,
    ``fine_expanded``, ``widenings`` (corridor widenings and fallbacks taken), ``stage``
    (the coarse paths whose corridor the plan came from: ``"conservative+optimistic"`` (with
    ``union``, the default), ``"conservative"``, ``"optimistic"``, or ``"full"`` = the whole
    lattice), ``half_width_m`` (the corridor's half width beside the coarse
    cells crossed [m], inf for "full") and ``corridor_fraction`` (lattice columns searched /
    all).  Stops on counts (``max_expansions`` per search, ``max_widenings`` per coarse path);
    ``time_limit_s`` [s] is the wall-clock safety net of the level, as for ``plan_grid``."""
    t0 = time.perf_counter()
    if not (weight >= 1 and coarse_weight >= 1):
        raise InputError(f"heuristic weights {weight}, {coarse_weight} must be >= 1 (1: optimal A*)")
    if int(half_width) < 0 or int(max_widenings) < 0:
        raise InputError(f"half_width {half_width} and max_widenings {max_widenings} must be >= 0")
    left = lambda: time_limit_s - (time.perf_counter() - t0)  # noqa: E731
    lat = lattice_geometry(problem, step_cells, z_anchor_m)
    factor = coarse_factor(problem, step_cells, coarse_cell_m)
    info = {"coarse_cell_m": factor * problem.grid.resolution_m, "coarse_expanded": 0, "fine_expanded": 0,
            "widenings": 0, "stage": "", "half_width_m": math.nan, "corridor_fraction": math.nan}
    res = None
    stopped = ""
    steps = 0
    optimistic_path = None
    for stage in ("conservative", "optimistic", "full"):
        control.check()
        if stage == "full":
            paths, labels = [], ["full"]
            hws = [math.inf]
        else:
            if stage == "optimistic" and union:
                if optimistic_path is None:    # computed with the conservative one: nothing new to try
                    steps += 1
                    continue
                cwp = optimistic_path
            else:
                cwp, cgrid, cexp, cstop = _coarse_path(problem, factor, stage == "optimistic", lat, step_cells,
                                                       z_anchor_m, max_expansions, left(), coarse_weight)
                info["coarse_expanded"] += cexp
                if cstop:
                    stopped = cstop
                    break
            paths = [cwp] if cwp is not None else []
            labels = [stage] if cwp is not None else []
            if stage == "conservative" and union:   # the optimistic coarse path's corridor too
                owp, cgrid, cexp, cstop = _coarse_path(problem, factor, True, lat, step_cells, z_anchor_m,
                                                       max_expansions, left(), coarse_weight)
                info["coarse_expanded"] += cexp
                if cstop:
                    stopped = cstop
                    break
                if owp is not None:
                    paths.append(owp)
                    labels.append("optimistic")
                    optimistic_path = None if cwp is None else owp   # not tried alone when used here
            if not paths:
                steps += 1          # no coarse path: on to the next abstraction
                continue
            hws = [int(half_width) * WIDEN_FACTOR ** i for i in range(int(max_widenings) + 1)]
        for hw in hws:
            if paths:
                mask = np.logical_or.reduce([corridor_columns(lat, cgrid, p, hw) for p in paths])
            else:
                mask = np.ones(lat.shape[1:], bool)
            sub = dataclasses.replace(lat, valid=corridor_valid(problem, lat, mask))
            h2 = heuristic_2d(problem, sub) * float(weight)
            r = astar(problem, sub, max_expansions, h2=h2, time_limit_s=left())
            info["fine_expanded"] += int(r["expanded"])
            if r["stopped_by"]:
                stopped = r["stopped_by"]
                break
            if r["waypoints"] is not None:
                res, lat = r, sub
                info.update(stage="+".join(labels), half_width_m=(hw + 0.5) * info["coarse_cell_m"],
                            corridor_fraction=float(mask.mean()))
                break
            steps += 1
        if res is not None or stopped:
            break
    info["widenings"] = steps
    wp = None if res is None else res["waypoints"]
    if wp is not None and refine:
        wp = refine_path(problem, wp, time_limit_s=left())
        if left() < 0:
            stopped = "time"
    return {"waypoints": wp, "lattice_f": math.inf if res is None else res["f"],
            "expanded": info["coarse_expanded"] + info["fine_expanded"], "lattice": lat,
            "compute_s": time.perf_counter() - t0, "stopped_by": stopped, "multires": info}


def use_multires(problem: PlanningProblem) -> bool:
    """True when STEP I's A* on ``problem`` is multi-resolution (grid cells >= MULTIRES_MIN_CELLS)."""
    return problem.grid.nx * problem.grid.ny >= MULTIRES_MIN_CELLS


def plan_astar(problem: PlanningProblem, step_cells: int = STEP_CELLS, refine: bool = True,
               h2: np.ndarray | None = None, time_limit_s: float = math.inf, z_anchor_m: float | None = None,
               edge_cache: EdgeCache | None = None) -> dict:
    """STEP I's A*: :func:`plan_multires` for a problem of at least :data:`MULTIRES_MIN_CELLS`
    grid cells (``h2`` and ``edge_cache``, made for the whole lattice, are not used), else
    :func:`~.grid_planner.plan_grid` with every argument, as before."""
    if use_multires(problem):
        return plan_multires(problem, step_cells=step_cells, refine=refine, time_limit_s=time_limit_s,
                             z_anchor_m=z_anchor_m)
    return plan_grid(problem, step_cells=step_cells, refine=refine, h2=h2, time_limit_s=time_limit_s,
                     z_anchor_m=z_anchor_m, edge_cache=edge_cache)


__all__ = ["COARSE_CELL_M", "HALF_WIDTH_CELLS", "MAX_WIDENINGS", "MULTIRES_MIN_CELLS", "coarse_factor",
           "coarse_problem", "corridor_columns", "corridor_valid", "lattice_geometry", "plan_astar", "plan_multires",
           "use_multires"]
