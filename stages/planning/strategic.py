"""The whole strategic planner (seed 000 section III): for every GNSS coverage level D_j,
STEP I (optimised polygonal chain), STEP II (deconfliction against known traffic) and STEP III
(corner smoothing and retiming within the vehicle's hard limits, navigation-error check, eq. 15
costs); then the choice of the flyable
candidate with minimum f.

:func:`plan_strategic` takes the maps (:class:`~skyroute.stages.planning.request.Maps`: surface,
satellites, coverage, environment, wind, clearance, traffic) and a
:class:`~skyroute.stages.planning.request.PlanRequest` and returns a :class:`StrategicPlan`
(:func:`plan_levels` is the same with every setting as a keyword); :func:`plan_to_dataset` /
:func:`plan_from_dataset` convert it to and from an xarray Dataset so the plan is cached like
every other stage output.

Performance: levels whose floor and coverage arrays are identical are solved once; with the
grid planner the levels share the A* heuristic of the loosest level and run in parallel
threads (the compiled kernels release the GIL).  The nested floors (floor(D_2) >= floor(D_3)
>= ...) would also let a looser level reuse a stricter level's path, but only when no cell
where the floors differ can improve f; on the real maps they differ right under the direct
line (Helsinki: 15.7 k and 3.8 k cells), so no such bound holds and every level is solved.
"""

from __future__ import annotations

import copy
import json
import os
import threading
import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import xarray as xr

from skyroute.stages import control
from skyroute.stages.base import InputError, PlanningError
from skyroute.stages.planning.deconflict import MAX_ITER as STEP2_MAX_ITER
from skyroute.stages.planning.deconflict import Step2Result, deconflict
from skyroute.stages.planning.degenerate import check_cost_terms, degenerate_cost_terms
from skyroute.stages.planning.grid_planner import STEP_CELLS, EdgeCache, shared_heuristic
from skyroute.stages.planning.kinds import FIXED_WING_PLANNERS, check_planner_vehicle
from skyroute.stages.planning.problem import PlanningProblem, build_problem, xyz_from_agl
from skyroute.stages.planning.request import Maps, PlanRequest
from skyroute.stages.planning.step1 import LEVEL_CAP_FACTOR, PLANNERS, Step1Result, plan_step1
from skyroute.stages.planning.step3 import (
    Candidate,
    choose,
    empty_candidate,
    explain_no_plan,
    step3,
)
from skyroute.stages.smoothing import CornerTrajectory
from skyroute.stages.traffic import Intruder, TrafficOccupancy
from skyroute.stages.vehicle import FixedWingProfile, VehicleProfile, load_vehicle

LATTICE_ANCHOR_M = 0.0   # [m] the altitude shared A* lattices are aligned on (``edge_cache``)
STEP1_MEMO = 256         # STEP I results kept in an ``edge_cache`` dict
HEURISTIC_MEMO = 64      # A* heuristic tables kept in a ``heuristic_cache`` dict (oldest dropped first)


@dataclass
class StrategicPlan:
    """Every level's STEP I-III outcome and the chosen candidate (None if none is flyable).

    Attributes
    ----------
    chosen : Candidate or None
        The flyable candidate with minimum f, None if none is flyable (:attr:`reason` says why).
    candidates : list of Candidate
        One per coverage level, in the order of the levels.
    step1 : list of Step1Result
        STEP I result per level.
    step2 : list of Step2Result or None
        STEP II result per level (None where STEP I failed, and for the fixed-wing planners).
    compute_s : float
        Wall time of the planning [s].
    warnings : list of str
        Degenerate cost terms, planner caps hit.
    window_xy : tuple of float or None
        The planning window (xmin, ymin, xmax, ymax) [m] (:mod:`~skyroute.stages.planning.window`;
        None: the whole AOI).
    window_widenings : int
        How many times the window was widened.
    """

    chosen: Candidate | None
    candidates: list[Candidate]
    step1: list[Step1Result] = field(default_factory=list)
    step2: list[Step2Result | None] = field(default_factory=list)
    compute_s: float = 0.0
    warnings: list[str] = field(default_factory=list)   # degenerate cost terms, planner caps hit
    window_xy: tuple[float, float, float, float] | None = None   # planning window [m] (None: the whole AOI)
    window_widenings: int = 0

    @property
    def reason(self) -> str:
        """Why no candidate is flyable ("" when one is chosen).
        """
        return "" if self.chosen is not None else explain_no_plan(self.candidates)

    @property
    def wallclock_capped(self) -> list[str]:
        """The labels of the levels whose STEP I or STEP II stopped at its wall-clock safety cap:
        their result depends on the machine's load, so the plan must not be cached."""
        out = [s1.label for s1 in self.step1 if s1.info.get("stopped_by") == "time"]
        out += [s1.label for s1, s2 in zip(self.step1, self.step2, strict=False)
                if s2 is not None and "wall-clock cap" in s2.reason]
        return list(dict.fromkeys(out))


def plan_levels(surface: xr.Dataset, environment: xr.Dataset | None, wind: xr.Dataset | None,
                   clearance: xr.Dataset, coverage: xr.Dataset | None, satellites: xr.Dataset | None,
                   traffic: xr.Dataset | TrafficOccupancy | None, *, start_xy: tuple[float, float], start_agl_m: float,
                   goal_xy: tuple[float, float], goal_agl_m: float, start_time_utc,
                   vehicle: str | VehicleProfile | FixedWingProfile = "dji-m300-rtk", weights=(1.0, 1.0, 1.0, 1.0),
                   planner: str = "astar", time_budget_s: float = 5.0, seed: int = 0, max_tries: int = 3,
                   min_agl_m: float = 0.0, max_agl_m: float = 120.0, dop_kind: str = "PDOP",
                   intruders: list[Intruder] | None = None, d_c_m: float = 0.0, dt_c_s: float = 0.0,
                   uere_m: float = 3.0, workers: int | None = None, step_cells: int = STEP_CELLS,
                   max_iterations: int | None = None, battery_reserve_pct: float = 0.0,
                   clearance_by_level: Mapping[float, xr.Dataset] | None = None,
                   bubble: tuple[float, float] | None = None,
                   heuristic_cache: dict | None = None, edge_cache: dict | None = None,
                   step2_max_iter: int = STEP2_MAX_ITER, wind_bounds: xr.Dataset | None = None,
                   cache_scope: tuple = ()) -> StrategicPlan:
    """Plan the mission for every coverage level of ``coverage`` (one level without GNSS data).

    STEP I (optimised polygonal chain), STEP II (deconfliction against known traffic) and STEP III
    (corner smoothing and retiming, navigation-error check, eq. 15 costs) per level, then the
    flyable candidate with minimum f.  Levels with identical floor and coverage arrays are solved
    once.  With ``planner="astar"`` the levels share one A* heuristic (that of the loosest level,
    admissible for all: see :func:`~skyroute.stages.planning.grid_planner.heuristic_2d`) and run in
    ``workers`` threads; the result does not depend on ``workers``.  Every planner is
    deterministic: the same inputs and ``seed`` give the same plan (BIT* stops on an iteration
    count, :func:`~skyroute.stages.planning.step1.bitstar_iterations`).  Cost terms that are the
    same per metre everywhere are listed in ``warnings`` of the result
    (:mod:`skyroute.stages.planning.degenerate`).

    Parameters
    ----------
    surface : xarray.Dataset
        :func:`~skyroute.stages.surface.build_surface` output (``terrain``, ``terrain_min``,
        ``surface`` [m]).
    environment : xarray.Dataset or None
        ``risk_cost`` and ``landing_cost`` maps [-] (None: both 0).
    wind : xarray.Dataset or None
        Wind on the grid (None: still air).
    clearance : xarray.Dataset
        ``min_altitude_m`` [m] (lowest safe altitude, ``(y, x)``) and optionally ``nofly``.
    coverage : xarray.Dataset or None
        :func:`~skyroute.stages.coverage.coverage_maps` output: one level per ``threshold``
        (None: one level without GNSS constraint).
    satellites : xarray.Dataset or None
        Satellite geometry for the navigation error along the plan (None: it cannot be verified;
        a rotorcraft candidate records that among its reasons, the fixed-wing planners warn).
    traffic : xarray.Dataset, TrafficOccupancy or None
        The traffic stage's dataset or a :class:`~skyroute.stages.traffic.TrafficOccupancy`
        (e.g. one holding other operators' intent volumes as prisms: ``skyroute fleet``).
    start_xy, goal_xy : tuple of float
        Mission end points, map (x, y) [m] in the grid's CRS.
    start_agl_m, goal_agl_m : float
        Their altitudes above ground [m].
    start_time_utc : str, datetime or numpy.datetime64
        Departure time [UTC].
    vehicle : str, VehicleProfile or FixedWingProfile, default "dji-m300-rtk"
        Catalog name, YAML path or profile (:func:`~skyroute.stages.vehicle.load_vehicle`).
    weights : sequence of 4 float, default (1.0, 1.0, 1.0, 1.0)
        Cost weights (w_l, w_r, w_d, w_e) [-]: finite, >= 0, not all 0.
    planner : str, default "astar"
        Planner name (:mod:`~skyroute.stages.planning.registry`); must fit the vehicle's kind.
    time_budget_s : float, default 5.0
        Planning budget per level [s] (the wall-clock safety caps are multiples of it).
    seed : int, default 0
        Random seed (BIT*, STEP II).
    max_tries : int, default 3
        STEP I attempts per level (see :func:`~skyroute.stages.planning.step1.plan_step1`).
    min_agl_m, max_agl_m : float, default 0.0, 120.0
        Altitude limits above ground [m], ``0 <= min_agl_m < max_agl_m``.
    dop_kind : str, default "PDOP"
        DOP kind of the coverage levels.
    intruders : list of Intruder, optional
        Known traffic checked along the smoothed trajectory (STEP III).
    d_c_m : float, default 0.0
        Spatial margin of the fixed-wing traffic check [m] (the rotorcraft levels use that of
        ``traffic``).
    dt_c_s : float, default 0.0
        Time margin of the fixed-wing traffic check [s].
    uere_m : float, default 3.0
        GNSS user equivalent range error [m] for the navigation error sigma_p.
    workers : int, optional
        Threads for the A* levels (default: the CPU count), >= 1.
    step_cells : int, default :data:`~skyroute.stages.planning.grid_planner.STEP_CELLS`
        A* lattice step [cells].
    max_iterations : int, optional
        BIT* stop rule per level (see :func:`~skyroute.stages.planning.step1.plan_step1`; 0 =
        wall clock, not reproducible).
    battery_reserve_pct : float, default 0.0
        Energy kept in the battery [%] (STEP I and III use the rest).
    clearance_by_level : mapping of float to xarray.Dataset, optional
        Safety bubble (seed 003, :mod:`skyroute.stages.sboa`; default off): maps a DOP threshold
        D_j to the clearance dataset of its radius r_j (used instead of ``clearance`` for that
        level; its ``radius_m`` attribute is recorded in the candidate).
    bubble : tuple of float, optional
        Safety bubble ``(k, surface_uncertainty_m)`` (default off): STEP III re-checks every sample
        at ``max(r_p, k sigma_p(t) + surface_uncertainty_m)`` [m] from the surface.
    heuristic_cache : dict, optional
        Kept by a caller that plans many missions on the SAME maps (``skyroute fleet``): the A*
        heuristic table, which depends on the goal, the start altitude (the lattice's levels), the
        levels, the vehicle, the weights and the lattice step only (given the maps), is reused for
        a goal seen before (same result, less time).
    edge_cache : dict, optional
        Kept by such a caller too: the A* lattices of every mission are then aligned on
        ``LATTICE_ANCHOR_M`` (instead of each start's altitude) so that missions share them, and
        the costs of their edges are kept per level
        (:class:`~skyroute.stages.planning.grid_planner.EdgeCache`) and reused: each search
        returns what it would without the dict, on the anchored lattice.  The dict also keeps the
        last ``STEP1_MEMO`` STEP I results (A*): STEP I does not depend on the departure time or
        the traffic, so a mission planned again (a later departure) reuses its chain.
    step2_max_iter : int, default :data:`~skyroute.stages.planning.deconflict.MAX_ITER`
        K, the STEP II RRT's iterations (its reproducible stop rule).
    wind_bounds : xarray.Dataset, optional
        The ``wind_bounds`` stage's energy-ratio bounds per wind tile
        (:mod:`~skyroute.stages.planning.wind_bounds`): used by the A* heuristic instead of
        bounding every wind again when they fit the vehicle and ``step_cells``.
    cache_scope : tuple, default ()
        What else the maps are, for ``heuristic_cache`` and the STEP I results of ``edge_cache``:
        :func:`plan_strategic` passes the planning window (rows, cols), so that a fleet's plans in
        different windows of one AOI never share a heuristic table or a STEP I result
        (:class:`~skyroute.stages.planning.grid_planner.EdgeCache` keys lattices by their nodes'
        coordinates already).

    Returns
    -------
    StrategicPlan
        Every level's outcome and the chosen candidate (None, with :attr:`StrategicPlan.reason`,
        when no level gives a flyable plan).

    Raises
    ------
    DegenerateCostError
        When the weights select only cost terms that are the same per metre everywhere (before
        any planning).
    InputError
        When the weights, altitude limits, ``time_budget_s`` or ``workers`` are invalid, the
        planner does not fit the vehicle's kind, or a mission point is outside the grid.
    UnknownNameError
        When ``vehicle`` names no catalog vehicle or ``planner`` no planner.

    References
    ----------
    Seed 000 section III (STEP I-III); seed 003 (safety bubble).
    """
    t0 = time.perf_counter()
    import dask

    veh = load_vehicle(vehicle)
    check_planner_vehicle(planner, veh, PLANNERS)
    # every map read in one dask computation (the chunks of all of them decompressed in parallel:
    # on a city's planning window GBs); risk_level stays lazy (read only for a uniform risk map)
    env = (None if environment is None else environment[[v for v in ("risk_cost", "landing_cost", "nofly",
           "nofly_floor_m", "nofly_ceiling_m") if v in environment]])
    clear_ds = clearance[[v for v in ("min_altitude_m", "nofly") if v in clearance]]
    objs = (wind, env, surface[[v for v in ("terrain", "terrain_min", "surface") if v in surface]], clear_ds,
            None if coverage is None else coverage["coverage_floor"], satellites)
    if any(_lazy(o) for o in objs):
        wind_map, env, surf, clear_ds, cov, sky = dask.compute(*objs)
    else:                   # in memory already (a fleet's maps): no dask scheduler
        wind_map, env, surf, clear_ds, cov, sky = (None if o is None else o.load() for o in objs)
    if env is not None and "risk_level" in environment:
        env["risk_level"] = environment["risk_level"]
    environment = env
    cost_warnings = check_cost_terms(weights, degenerate_cost_terms(environment, wind_map))
    surface_2d = surf["surface"].values
    clear = clear_ds["min_altitude_m"]
    nofly = clear_ds["nofly"] if "nofly" in clear_ds else None
    risk = environment["risk_cost"] if environment is not None else None
    land = environment["landing_cost"] if environment is not None else None
    occ = (traffic if isinstance(traffic, TrafficOccupancy) or traffic is None
           else TrafficOccupancy.from_dataset(traffic.load()))
    start = xyz_from_agl(surf, *start_xy, start_agl_m)
    goal = xyz_from_agl(surf, *goal_xy, goal_agl_m)
    levels: list[tuple[float | None, xr.DataArray | None]]
    if cov is not None:
        levels = [(float(d), cov.sel(threshold=d)) for d in cov["threshold"].values]
    else:
        levels = [(None, None)]
    by_level = dict(clearance_by_level or {})

    def level_clearance(d):
        if d is None or d not in by_level:
            return clear, nofly
        c = by_level[d]
        return c["min_altitude_m"].load(), (c["nofly"].load() if "nofly" in c else None)

    shared: dict = {}        # the levels share the arrays derived from the same maps (build_problem)
    problems = [build_problem(surf, level_clearance(d)[0], floor_j, risk, land, wind_map, veh, weights, start, goal,
                              min_agl_m, max_agl_m, d, dop_kind=dop_kind, nofly=level_clearance(d)[1],
                              check_endpoints=False, shared=shared)
                for d, floor_j in levels]
    from skyroute.stages.planning.wind_bounds import tiles_fit

    if planner == "astar" and tiles_fit(wind_bounds, veh, step_cells):
        tiles = wind_bounds.load()
        for p in problems:         # the A* heuristic's energy bound (heuristic.energy_ratio_lb_dense_each)
            object.__setattr__(p, "_ratio_tiles", tiles)
    # the problems hold their own float64 maps: release the loaded rasters (1e8 cells: GBs)
    levels = [(d, None) for d, _ in levels]
    shared = clear = nofly = risk = land = environment = surf = cov = None
    if planner in FIXED_WING_PLANNERS:
        return _plan_fixedwing_levels(problems, levels, planner, time_budget_s, step_cells, t0, cost_warnings,
                                      seed=seed, intruders=intruders, d_c_m=d_c_m, dt_c_s=dt_c_s,
                                      battery_reserve_pct=battery_reserve_pct, sky=sky, occ=occ,
                                      surface_2d=surface_2d, start_time_utc=start_time_utc, uere_m=uere_m)
    h2 = None
    anchor = None if edge_cache is None else LATTICE_ANCHOR_M
    if planner == "astar":   # one A* heuristic for all levels: that of the loosest (lowest floors)
        from skyroute.stages.planning.multires import use_multires

        loosest = _loosest(problems)   # (a multi-resolution A* makes its own, within its corridor)
        if loosest is not None and not loosest.endpoint_problem() and not use_multires(loosest):
            zkey = ("anchor", anchor) if anchor is not None else round(float(start[2]), 6)   # the lattice levels
            hkey = (tuple(np.round(goal, 6)), zkey, loosest.dop_threshold, veh.name, tuple(weights), step_cells,
                    min_agl_m, max_agl_m, dop_kind, battery_reserve_pct, cache_scope)
            h2 = None if heuristic_cache is None else heuristic_cache.get(hkey)
            if h2 is None:
                h2 = shared_heuristic(loosest, step_cells, z_anchor_m=anchor)
                if heuristic_cache is not None:
                    while len(heuristic_cache) >= HEURISTIC_MEMO:      # oldest first
                        heuristic_cache.pop(next(iter(heuristic_cache)), None)
                    heuristic_cache[hkey] = h2

    def level_key(d) -> tuple:        # what a level's lattice edge costs depend on, given the maps
        radius = float(by_level[d].attrs["radius_m"]) if d is not None and d in by_level else None
        return (d, radius, veh.name, tuple(weights), step_cells, min_agl_m, max_agl_m, dop_kind)

    ticker = _Progress(planner)

    def one_level(i: int) -> tuple[Step1Result, Step2Result | None, Candidate]:
        control.check()
        problem, d = problems[i], levels[i][0]
        tl = time.perf_counter()
        ticker.phase(problem.label, "STEP I")
        ec = memo = s1key = s1 = None
        if edge_cache is not None and planner == "astar":
            ec = edge_cache.setdefault(level_key(d), EdgeCache())
            memo = edge_cache.setdefault("step1", {})        # the STEP I results, oldest first
            s1key = (level_key(d), problem.start_xyz, problem.goal_xyz, max_tries, battery_reserve_pct, time_budget_s,
                     cache_scope)
            s1 = memo.get(s1key)
        if s1 is None:
            s1 = plan_step1(problem, planner=planner, time_budget_s=time_budget_s, seed=seed, max_tries=max_tries,
                            step_cells=step_cells, max_iterations=max_iterations, h2=h2,
                            battery_reserve_pct=battery_reserve_pct, z_anchor_m=anchor, edge_cache=ec)
            if memo is not None and s1.info.get("stopped_by") != "time":    # a complete search only
                while len(memo) >= STEP1_MEMO:
                    memo.pop(next(iter(memo)), None)
                memo[s1key] = s1
        if not s1.solved:
            ticker.phase(problem.label, None)
            why = (s1.reason or s1.status).removeprefix(f"{problem.label}: ")
            return s1, None, empty_candidate(problem.label, d, [f"STEP I: {why}"], tl, s1.status)
        ticker.phase(problem.label, "STEP II")
        s2 = deconflict(problem, s1.waypoints, occ, seed=seed, time_budget_s=LEVEL_CAP_FACTOR * time_budget_s,
                        max_iter=step2_max_iter)
        if s2.status == "failed":
            ticker.phase(problem.label, None)
            return s1, s2, empty_candidate(problem.label, d, [f"STEP II: {s2.reason}"], tl, s2.status)
        ticker.phase(problem.label, "STEP III")
        cand = step3(problem, s2, sky, surface_2d, start_time_utc=start_time_utc, occupancy=occ,
                     intruders=intruders, label=problem.label, gnss_sigma_m=uere_m,
                     battery_reserve_pct=battery_reserve_pct,
                     bubble=None if bubble is None else (float(bubble[0]), float(bubble[1]), float(veh.r_p_m)))
        if d is not None and d in by_level:
            cand.clearance_radius_m = float(by_level[d].attrs["radius_m"])
        cand.compute_time_s = time.perf_counter() - tl
        ticker.phase(problem.label, None)
        return s1, s2, cand

    # identical levels (same floor and coverage arrays) are solved once
    first_of = _identical_levels(problems)
    todo = sorted(set(first_of))
    n_workers = _n_workers(workers, len(todo), planner)
    with ticker:
        if n_workers > 1:
            pool = ThreadPoolExecutor(max_workers=n_workers, thread_name_prefix="skyroute-level")
            try:
                solved = dict(zip(todo, pool.map(one_level, todo), strict=True))
            except BaseException as exc:
                if isinstance(exc, KeyboardInterrupt):
                    control.request_cancel()
                pool.shutdown(wait=True, cancel_futures=True)   # the running levels see the flag
                raise
            pool.shutdown(wait=True)
        else:
            solved = {i: one_level(i) for i in todo}
    plan = StrategicPlan(None, [])
    for i, j in enumerate(first_of):
        s1, s2, cand = solved[j] if i == j else _relabel(solved[j], problems[j], problems[i])
        plan.step1.append(s1)
        plan.step2.append(s2)
        plan.candidates.append(cand)
    plan.chosen = choose(plan.candidates)
    plan.compute_s = time.perf_counter() - t0
    plan.warnings = [*cost_warnings, *_cap_warnings(plan, planner, time_budget_s)]
    return plan


def _plan_fixedwing_levels(problems: list[PlanningProblem], levels, planner: str, time_budget_s: float,
                           step_cells: int, t0: float, cost_warnings: list[str], *, seed: int = 0, intruders,
                           d_c_m: float,
                           dt_c_s: float, battery_reserve_pct: float, sky, occ, surface_2d, start_time_utc,
                           uere_m: float) -> StrategicPlan:
    """The fixed-wing planners (seed 002, :mod:`~skyroute.stages.planning.fixedwing`) on every
    level: lattice search, written path (fillets + loiter), navigation error (with satellites),
    validation; no STEP II (deconfliction) and no STEP III smoothing.  ``bitstar-dubins``: BIT*
    on the Dubins-airplane space (:mod:`~skyroute.stages.planning.bitstar_dubins`, its
    iterations ``DUBINS_ITERATIONS_PER_S x time_budget_s``), written as its sampled curve."""
    from skyroute.stages.planning.fixedwing import fixedwing_candidate, plan_fixedwing

    plan = StrategicPlan(None, [])
    cap = LEVEL_CAP_FACTOR * time_budget_s
    first_of = _identical_levels(problems)
    done: dict[int, tuple] = {}
    for i, problem in enumerate(problems):
        control.check()
        j = first_of[i]
        if j != i:
            s1, s2, cand = _relabel(done[j], problems[j], problem)
        else:
            if planner == "bitstar-dubins":
                from skyroute.stages.planning.bitstar_dubins import dubins_result

                r = dubins_result(problem, time_budget_s, seed, cap)
            else:
                r = plan_fixedwing(problem, planner, step_cells=step_cells, time_limit_s=cap)
            cand = fixedwing_candidate(problem, r, dop_threshold=levels[i][0], intruders=intruders, d_c_m=d_c_m,
                                       dt_c_s=dt_c_s, battery_reserve_pct=battery_reserve_pct, sky=sky,
                                       surface_2d=surface_2d, start_time_utc=start_time_utc, gnss_sigma_m=uere_m)
            nan = float("nan")
            costs = {"C_l": cand.C_l, "C_r": cand.C_r, "C_d": cand.C_d, "C_e": cand.C_e}
            s1 = Step1Result(r.waypoints, costs, cand.f, r.energy_J if r.solved else nan,
                             r.time_s if r.solved else nan, r.compute_s, r.status, r.reason, problem.label, planner,
                             1, problem.weights, {**r.info, "expanded": r.expanded})
            s2 = None
            done[i] = (s1, s2, cand)
        plan.step1.append(s1)
        plan.step2.append(s2)
        plan.candidates.append(cand)
    plan.chosen = choose(plan.candidates)
    plan.compute_s = time.perf_counter() - t0
    notes = [f"plan: {s1.label}: STEP I ({planner}) stopped at its wall-clock cap of {cap:g} s"
             for s1 in plan.step1 if s1.info.get("stopped_by") == "time"]
    if sky is None:
        notes.append(f"plan: {planner}: no satellite geometry: the navigation error (sigma_p) along the fixed-wing plan "
                     "is not evaluated")
    if occ is not None:
        notes.append(f"plan: {planner}: fixed-wing plans are not deconflicted (no STEP II); the validator refuses a plan "
                     "that enters an intruder's volume")
    plan.warnings = [*cost_warnings, *dict.fromkeys(notes)]
    return plan


def _cap_warnings(plan: StrategicPlan, planner: str, time_budget_s: float) -> list[str]:
    """One warning per level whose STEP I or STEP II was stopped by its wall-clock cap (its
    result may then depend on the machine's load), and STEP II's notes."""
    out = []
    cap = LEVEL_CAP_FACTOR * time_budget_s
    for s1, s2 in zip(plan.step1, plan.step2, strict=True):
        if s1.info.get("stopped_by") == "time":
            out.append(f"plan: {s1.label}: STEP I ({planner}) stopped at its wall-clock cap of {cap:g} s "
                       f"({LEVEL_CAP_FACTOR:g} x the {time_budget_s:g} s budget); the result may depend on the "
                       "machine's load")
        if s2 is not None:
            if "wall-clock cap" in s2.reason:
                out.append(f"plan: {s1.label}: {s2.reason}")
            out.extend(f"plan: {s1.label}: STEP II: {n}" for n in s2.notes)
    return list(dict.fromkeys(out))


class _Progress:
    """Progress notes of the running levels (label, phase, planner, elapsed) every
    ``every_s`` [s] on stderr while progress is enabled (:mod:`skyroute.stages.control`)."""

    def __init__(self, planner: str, every_s: float = 2.0):
        self.planner, self.every_s = planner, every_s
        self.t0 = time.perf_counter()
        self.running: dict[str, tuple[str, float]] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def phase(self, label: str, what: str | None) -> None:
        with self._lock:
            if what is None:
                self.running.pop(label, None)
            else:
                start = self.running.get(label, (what, time.perf_counter()))[1]
                self.running[label] = (what, start)

    def line(self) -> str:
        now = time.perf_counter()
        with self._lock:
            parts = [f"{lab} {what}{f' ({self.planner})' if what == 'STEP I' else ''} {now - t:.0f} s"
                     for lab, (what, t) in self.running.items()]
        return f"plan: {now - self.t0:.0f} s elapsed; running: " + ("; ".join(parts) or "-")

    def _loop(self) -> None:
        while not self._stop.wait(self.every_s):
            control.note(self.line())

    def __enter__(self) -> _Progress:
        if control.progress_enabled():
            self._thread = threading.Thread(target=self._loop, name="skyroute-plan-progress", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()


def _loosest(problems: list[PlanningProblem]) -> PlanningProblem | None:
    """The level whose floors are <= every other level's floors (None if the floors are not
    nested, e.g. hand-made coverage maps)."""
    for p in sorted(problems, key=lambda q: -np.inf if q.dop_threshold is None else -q.dop_threshold):
        if all(np.all((p.floor_m <= q.floor_m) | np.isinf(q.floor_m)) for q in problems):
            return p
    return None


def _same(a: np.ndarray | None, b: np.ndarray | None, rows: int = 64) -> bool:
    """``np.array_equal(a, b, equal_nan=True)``, ``rows`` rows at a time (two levels' floors
    differ in their first rows as a rule: 0.25 s less per pair of 9.6 M-cell levels)."""
    if a is None or b is None:
        return a is None and b is None
    if a is b:
        return True
    if a.shape != b.shape:
        return False
    return all(np.array_equal(a[i:i + rows], b[i:i + rows], equal_nan=True) for i in range(0, max(len(a), 1), rows))


def _lazy(obj) -> bool:
    """True when ``obj`` (an xarray object or None) holds dask-backed data."""
    if isinstance(obj, xr.Dataset):
        return any(v.chunks is not None for v in obj.variables.values())
    return isinstance(obj, xr.DataArray) and obj.chunks is not None


def _identical_levels(problems: list[PlanningProblem]) -> list[int]:
    """For each level the index of the first level with identical floor and coverage arrays
    (everything else is shared by the levels of one mission), so that it is solved once."""
    out: list[int] = []
    for i, p in enumerate(problems):
        j = next((k for k in range(i) if out[k] == k and _same(problems[k].floor_m, p.floor_m)
                  and _same(problems[k].coverage_m, p.coverage_m)), i)
        out.append(j)
    return out


def _relabel(result: tuple, src: PlanningProblem, dst: PlanningProblem) -> tuple:
    """A solved level's (STEP I, STEP II, candidate) for an identical level: same numbers,
    the other label and DOP threshold."""
    s1, s2, cand = (copy.copy(x) for x in result)
    s1.label = dst.label
    s1.reason = s1.reason.replace(src.label, dst.label)
    cand.label = dst.label
    cand.dop_threshold = dst.dop_threshold
    cand.reasons = [r.replace(src.label, dst.label) for r in cand.reasons]
    return s1, s2, cand


def _n_workers(workers: int | None, n_levels: int, planner: str) -> int:
    """Threads for the levels: the A* levels run in parallel (the compiled kernels release the
    GIL); BIT* levels run one after the other (OMPL's random seed is process-global)."""
    if planner != "astar" or n_levels <= 1:
        return 1
    if workers is None:
        workers = os.cpu_count() or 1
    if int(workers) < 1:
        raise InputError(f"workers {workers} must be >= 1 (threads for the coverage levels)")
    return max(1, min(int(workers), n_levels))


# ------------------------------------------------------------------ dataset round trip
_SCALARS = ("C_l", "C_r", "C_d", "C_e", "f", "max_sigma_p_m", "energy_J", "flight_time_s", "compute_time_s")


def plan_to_dataset(plan: StrategicPlan, crs, vertical_datum: str, start_time_utc) -> xr.Dataset:
    """The candidate table (dim ``level``) and the chosen trajectory (dim ``sample``) as a Dataset.

    So the plan is cached like every other stage output; :func:`plan_from_dataset` reads it back.

    Parameters
    ----------
    plan : StrategicPlan
        The plan.
    crs : pyproj.CRS or str
        CRS of the map coordinates (stored as text in the attrs).
    vertical_datum : str
        Vertical datum of the altitudes ``z_m``.
    start_time_utc : str, datetime or numpy.datetime64
        Departure time [UTC] (anything :class:`pandas.Timestamp` accepts).

    Returns
    -------
    xarray.Dataset
        Per ``level``: ``label``, ``dop_threshold``, the costs ``C_l``, ``C_r``, ``C_d``, ``C_e``,
        ``f`` [m], ``max_sigma_p_m`` [m], ``energy_J`` [J], ``flight_time_s`` [s],
        ``compute_time_s`` [s], ``flyable``, ``reasons``, ``status`` (and ``clearance_radius_m``
        [m] with a safety bubble); for the chosen candidate per ``sample``: ``t_s`` [s], ``x_m``,
        ``y_m``, ``z_m``, ``alt_agl_m`` [m], ``speed_mps`` [m/s], ``sigma_p_m`` [m],
        ``n_visible``, its ``waypoints`` ``(waypoint, xyz)`` [m] and the exact trajectory
        (:func:`trajectory_to_dataset`).  Attrs: ``chosen_level`` (-1: none), ``crs``,
        ``vertical_datum``, ``start_time_utc``, ``compute_s``, ``reason``, ``warnings`` (JSON),
        ``planning_window_xy_m`` (JSON ``[xmin, ymin, xmax, ymax]`` [m], null: the whole AOI) and
        ``planning_window_widenings`` when the plan was made in a window
        (:mod:`~skyroute.stages.planning.window`), and ``skyroute_not_cacheable`` when a level
        stopped at its wall-clock cap.
    """
    cands = plan.candidates
    ds = xr.Dataset(coords={"level": np.arange(len(cands))})
    ds["label"] = ("level", np.array([c.label for c in cands], dtype=object))
    ds["dop_threshold"] = ("level", np.array([np.nan if c.dop_threshold is None else c.dop_threshold
                                               for c in cands]), {"units": "1"})
    units = {"C_l": "m", "C_r": "m", "C_d": "m", "C_e": "m", "f": "m", "max_sigma_p_m": "m", "energy_J": "J",
             "flight_time_s": "s", "compute_time_s": "s"}
    for k in _SCALARS:
        ds[k] = ("level", np.array([float(getattr(c, k)) for c in cands]), {"units": units[k]})
    if any(np.isfinite(c.clearance_radius_m) for c in cands):   # safety bubble levels only
        ds["clearance_radius_m"] = ("level", np.array([c.clearance_radius_m for c in cands]), {"units": "m"})
    if any(np.isfinite(c.search_cost_m) for c in cands):       # a search objective that is not f (fixed-wing)
        ds["search_cost_m"] = ("level", np.array([c.search_cost_m for c in cands]),
                               {"units": "m", "definition": next(c.search_objective for c in cands if c.search_objective)})
    ds["flyable"] = ("level", np.array([bool(c.flyable) for c in cands]), {"units": "1"})
    ds["reasons"] = ("level", np.array(["; ".join(c.reasons) for c in cands], dtype=object))
    ds["status"] = ("level", np.array([c.step2_status for c in cands], dtype=object))
    chosen = -1 if plan.chosen is None else next(i for i, c in enumerate(cands) if c is plan.chosen)
    ds.attrs.update({"chosen_level": chosen, "crs": str(crs), "vertical_datum": vertical_datum,
                     "start_time_utc": pd.Timestamp(start_time_utc).isoformat(), "compute_s": plan.compute_s,
                     "reason": plan.reason, "title": "skyroute strategic plan",
                     "warnings": json.dumps(list(plan.warnings))})
    if plan.window_xy is not None or plan.window_widenings:    # planning window (stages/planning/window.py)
        ds.attrs["planning_window_xy_m"] = json.dumps(None if plan.window_xy is None
                                                      else [round(float(v), 3) for v in plan.window_xy])
        ds.attrs["planning_window_widenings"] = int(plan.window_widenings)
    if plan.wallclock_capped:      # a load-dependent result: the pipeline never caches it
        ds.attrs["skyroute_not_cacheable"] = ("the planner stopped at its wall-clock safety cap on "
                                              + ", ".join(plan.wallclock_capped))
    if plan.chosen is not None:
        c = plan.chosen
        ds = ds.assign_coords(sample=np.arange(c.t_s.size))
        ds["t_s"] = ("sample", c.t_s, {"units": "s", "long_name": "time since mission start"})
        for i, ax in enumerate("xyz"):
            ds[f"{ax}_m"] = ("sample", c.xyz_m[:, i], {"units": "m"})
        ds["z_m"].attrs["vertical_datum"] = vertical_datum
        for k in ("alt_agl_m", "speed_mps", "sigma_p_m"):
            ds[k] = ("sample", np.asarray(getattr(c, k), float), {"units": "m" if k != "speed_mps" else "m s-1"})
        ds["n_visible"] = ("sample", np.asarray(c.n_visible, np.int32), {"units": "1"})
        ds = ds.assign_coords(waypoint=np.arange(len(c.waypoints)))
        ds["waypoints"] = (("waypoint", "xyz"), np.asarray(c.waypoints, float), {"units": "m"})
        if c.trajectory is not None:
            tds = trajectory_to_dataset(c.trajectory, float(c.t_s[0]))
            attrs = {**ds.attrs, **tds.attrs}
            ds = ds.merge(tds)
            ds.attrs = attrs
    return ds


_TRAJ_PHASE = {"phase_t0_s": "s", "kind": "1", "s0": "m", "v0": "m s-1", "a": "m s-2", "radius_m": "m"}
_TRAJ_VEC = ("origin", "e1", "e2")


def trajectory_to_dataset(traj: CornerTrajectory, t0_s: float) -> xr.Dataset:
    """The exact trajectory as ``traj_*`` variables (dims ``phase``, ``piece``).

    Its phases (:class:`~skyroute.stages.smoothing.CornerTrajectory`), so a cached plan can be
    flown again exactly (``skyroute fly``).

    Parameters
    ----------
    traj : CornerTrajectory
        The trajectory.
    t0_s : float
        Mission time of the trajectory's time 0 [s] (attr ``traj_t0_s``).

    Returns
    -------
    xarray.Dataset
    """
    ds = xr.Dataset(coords={"phase": np.arange(traj.phase_t0_s.size), "piece": np.arange(traj.piece_t_s.size)})
    for k, u in _TRAJ_PHASE.items():
        ds[f"traj_{k}"] = ("phase", np.asarray(getattr(traj, k)), {"units": u})
    for k in _TRAJ_VEC:
        ds[f"traj_{k}"] = (("phase", "xyz"), np.asarray(getattr(traj, k), float), {"units": "m" if k == "origin" else "1"})
    ds["traj_piece_t_s"] = ("piece", np.asarray(traj.piece_t_s, float), {"units": "s"})
    ds["traj_piece_xyz_m"] = (("piece", "xyz"), np.asarray(traj.waypoints, float), {"units": "m"})
    ds.attrs.update({"traj_t0_s": float(t0_s), "traj_duration_s": float(traj.duration_s),
                     "traj_corner_kind": json.dumps(list(traj.corner_kind)),
                     "traj_corner_reason": json.dumps(list(traj.corner_reason))})
    return ds


def trajectory_from_dataset(ds: xr.Dataset) -> tuple[CornerTrajectory, float] | None:
    """``(trajectory, t0_s)`` back from :func:`trajectory_to_dataset` (None if absent).

    Parameters
    ----------
    ds : xarray.Dataset
        A dataset holding the ``traj_*`` variables (e.g. a cached plan).

    Returns
    -------
    tuple of (CornerTrajectory, float) or None
        The trajectory and the mission time of its time 0 [s].
    """
    if "traj_phase_t0_s" not in ds:
        return None
    kw = {k: np.asarray(ds[f"traj_{k}"].values) for k in (*_TRAJ_PHASE, *_TRAJ_VEC)}
    kw["kind"] = kw["kind"].astype(np.int8)
    traj = CornerTrajectory(duration_s=float(ds.attrs["traj_duration_s"]),
                            piece_t_s=np.asarray(ds["traj_piece_t_s"].values, float),
                            waypoints=np.asarray(ds["traj_piece_xyz_m"].values, float),
                            corner_kind=tuple(json.loads(ds.attrs["traj_corner_kind"])),
                            corner_reason=tuple(json.loads(ds.attrs["traj_corner_reason"])), **kw)
    return traj, float(ds.attrs["traj_t0_s"])


def plan_from_dataset(ds: xr.Dataset) -> tuple[Candidate | None, list[Candidate]]:
    """Candidates (without their polynomial) back from :func:`plan_to_dataset`.

    Parameters
    ----------
    ds : xarray.Dataset
        A dataset written by :func:`plan_to_dataset`.

    Returns
    -------
    chosen : Candidate or None
        The chosen candidate with its samples, waypoints and (when stored) exact trajectory;
        None when no level was flyable.
    candidates : list of Candidate
        One per level; the others without samples.
    """
    cands = []
    z = np.zeros(0)
    chosen_i = int(ds.attrs.get("chosen_level", -1))
    for i in range(ds.sizes["level"]):
        row = ds.isel(level=i)
        d = float(row["dop_threshold"])
        kw = {k: float(row[k]) for k in _SCALARS}
        reasons = [r for r in str(row["reasons"].values).split("; ") if r]
        if i == chosen_i:
            xyz = np.column_stack([ds["x_m"].values, ds["y_m"].values, ds["z_m"].values])
            c = Candidate(str(row["label"].values), None if np.isnan(d) else d, ds["t_s"].values, xyz,
                          ds["alt_agl_m"].values, ds["speed_mps"].values, ds["sigma_p_m"].values,
                          ds["n_visible"].values, flyable=bool(row["flyable"]), reasons=reasons,
                          waypoints=ds["waypoints"].values, step2_status=str(row["status"].values), **kw)
            tr = trajectory_from_dataset(ds)
            c.trajectory = tr[0] if tr is not None else None
            if tr is not None:              # the piece durations: one time per piece boundary
                c.segment_times_s = np.asarray(tr[0].segment_times_s, float)
        else:
            c = Candidate(str(row["label"].values), None if np.isnan(d) else d, z, np.zeros((0, 3)), z, z, z,
                          np.zeros(0, int), flyable=bool(row["flyable"]), reasons=reasons,
                          step2_status=str(row["status"].values), **kw)
        if "clearance_radius_m" in ds:
            c.clearance_radius_m = float(row["clearance_radius_m"])
        if "search_cost_m" in ds:
            c.search_cost_m = float(row["search_cost_m"])
            c.search_objective = str(ds["search_cost_m"].attrs.get("definition", ""))
        cands.append(c)
    chosen = cands[chosen_i] if chosen_i >= 0 else None
    return chosen, cands


def plan_strategic(maps: Maps, request: PlanRequest, *, heuristic_cache: dict | None = None,
                   edge_cache: dict | None = None) -> StrategicPlan:
    """The strategic plan (STEP I-III on every coverage level, seed 000) of ``request`` on ``maps``.

    Parameters
    ----------
    maps : Maps
        The datasets the planner reads (:class:`~skyroute.stages.planning.request.Maps`).
    request : PlanRequest
        What to plan, with the vehicle profile resolved
        (:class:`~skyroute.stages.planning.request.PlanRequest`).
    heuristic_cache, edge_cache : dict, optional
        Dicts kept by a caller planning many missions on the same maps (``skyroute fleet``);
        see :func:`plan_levels`.  On a city-scale AOI each plan is made in its planning window
        (:mod:`~skyroute.stages.planning.window`), fleets included, and the cached heuristic
        tables and STEP I results are kept per window.

    Returns
    -------
    StrategicPlan
        Every level's STEP I-III outcome and the chosen candidate (None if none is flyable).

    Raises
    ------
    DegenerateCostError, InputError
        As :func:`plan_levels`.

    References
    ----------
    Seed 000 (the strategic planner, STEP I-III).
    """
    from skyroute.stages.gridspec import Grid
    from skyroute.stages.planning.window import crop_maps, planning_windows, window_box

    def on(m: Maps, scope: tuple) -> StrategicPlan:
        return plan_levels(m.surface, m.environment, m.wind, m.clearance, m.coverage, m.satellites, m.traffic,
                           clearance_by_level=m.clearance_by_level, wind_bounds=m.wind_bounds,
                           heuristic_cache=heuristic_cache, edge_cache=edge_cache, cache_scope=scope,
                           **request.kwargs())

    grid = Grid.from_dataarray(maps.surface["terrain"])
    windows = planning_windows(grid, request.start_xy, request.goal_xy)
    t0 = time.perf_counter()
    for i, win in enumerate(windows):
        # a fleet's caches (heuristic tables, STEP I results) are kept per window
        scope = () if win is None else ("window", win[0].start, win[0].stop, win[1].start, win[1].stop)
        plan = on(maps if win is None else crop_maps(maps, *win), scope)
        if win is not None:
            plan.window_xy = window_box(grid, *win)
        plan.window_widenings = i
        # widen only when a level's complete search found no path in the window (an energy-infeasible
        # level found one: a wider window does not bring the wind down; a search stopped by the
        # wall-clock safety net would only cost more on a wider one)
        retry = plan.chosen is None and any(s1.status == "no_solution" and s1.info.get("stopped_by") != "time"
                                            for s1 in plan.step1)
        if not retry or i == len(windows) - 1:
            break
    plan.compute_s = time.perf_counter() - t0
    if plan.window_widenings:
        where = "the whole AOI" if plan.window_xy is None else "a wider window"
        plan.warnings.append(f"the planning window around the mission held no path on some level: widened "
                             f"{plan.window_widenings} time(s), planned on {where}")
    return plan


__all__ = ["PlanningError", "StrategicPlan", "plan_from_dataset", "plan_levels", "plan_strategic", "plan_to_dataset",
           "trajectory_from_dataset", "trajectory_to_dataset"]
