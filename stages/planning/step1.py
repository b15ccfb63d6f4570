"""STEP I driver (seed 000 section III-A, seed 001 section 3.1).

For each GNSS coverage level D_j one :class:`~skyroute.stages.planning.problem.PlanningProblem`
is solved by a planner (``"bitstar"``: OMPL BIT*, seed 000; ``"astar"``: the deterministic
lattice A* of :mod:`.grid_planner`; ``"potential"``: the numerical potential field of
:mod:`.potential`, seed 004 III-B, deterministic, no refinement so that its standoff is kept),
giving an optimised polygonal chain and its costs.

Energy feasibility (seed 000 III-A.3): when the chain needs more energy E_w than the battery
holds, the level is re-planned with a larger length weight (w_l doubled; w_l = sum of the
weights if it was 0), at most ``max_tries`` plans in all (N_t).  If every try is still
infeasible the level's status is ``"energy_infeasible"`` with the numbers in ``reason``.
Before any search, a rotorcraft level of a mission of at least :data:`ENERGY_BOUND_MIN_M` whose
admissible energy lower bound
(:func:`~skyroute.stages.planning.energy_bound.energy_lower_bound`: the winds at the admissible
altitudes of the coarse cells, a ring recursion from the goal) exceeds the usable battery is
refused at once (``"energy_infeasible"``, no chain, ``tries == 0``, the bound and the battery
[Wh] in ``reason``): no plan can fly it, so no plan that would have been accepted changes.

Reproducibility: both planners are deterministic for given inputs and ``seed``.  A* is
deterministic by construction; BIT* stops on an iteration count that stands for the budget
(:func:`bitstar_iterations`), not on the wall clock (a wall-clock stop makes the plan depend on
the machine's load: the pipeline caches plans and compares runs).  The grid planner ("astar",
lattice step :data:`~skyroute.stages.planning.grid_planner.STEP_CELLS`) is the recommended
STEP I: on the benchmarks (``benchmarks/bench_planner.py``) its STEP I f is 0.95 x (Helsinki,
0.83 km) and 1.007 x (Monaco, 2.7 km) the f of BIT* given 60 s per level.

A level whose start or goal is not a valid state (e.g. below the coverage floor of D_j) yields
``status="no_solution"`` and the reason (seed 001 Table 4, mission 2, D1).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from skyroute.stages import control
from skyroute.stages.base import InputError, UnknownNameError
from skyroute.stages.planning.energy_bound import energy_lower_bound
from skyroute.stages.planning.grid_planner import STEP_CELLS, EdgeCache, refine_path
from skyroute.stages.planning.problem import COST_NAMES, PlanningProblem

# the one list of planners; the fixed-wing ones (seed 002) are solved by
# skyroute.stages.planning.fixedwing (plan_strategic dispatches them; plan_step1 refuses them)
from skyroute.stages.planning.registry import PLANNERS
from skyroute.stages.vehicle import FixedWingProfile

#: The shortest straight start-goal distance [m] for which a level's energy lower bound is worked
#: out before the search: it costs 0.3-1.2 s a level (it grows with the distinct winds of the
#: window), while a refused 1-2 km mission costs the old three tries only a few seconds; the bound
#: only refuses what no plan can fly, so the choice changes no plan, only when a refusal comes.
ENERGY_BOUND_MIN_M = 3000.0

# Every planner stops on counted work, so the same scenario and seed give the same plan on an
# idle or a loaded machine: A* on its expansions (``max_expansions``) and the refinement on its
# segment evaluations (RELAX_MAX_SEGMENTS), BIT* on an iteration count, the potential field when
# its wave reaches the start, STEP II on its RRT iterations.  BIT*'s count stands for the time
# budget at BITSTAR_ITERATIONS_PER_S, measured on the Helsinki default scenario (2 m grid, real
# wind): 48-60 k iterations in 5 s on an idle core, 4.6 k/s on a loaded one.
BITSTAR_ITERATIONS_PER_S = 8000.0
# The wall clock is only a safety net: every level (all energy tries and the refinement) stops at
# WALLCLOCK_CAP_FACTOR x the budget on the work clock (:func:`skyroute.stages.control.work_clock`:
# numba compilation never counts).  Normal runs end far inside it (a loaded 2-core machine runs
# BIT* at about half the reference rate); a result that hit it says so (info["stopped_by"] ==
# "time", a plan warning) and the plan stage never caches it (its result depends on the load).
WALLCLOCK_CAP_FACTOR = 10.0
BITSTAR_TIME_CAP_FACTOR = WALLCLOCK_CAP_FACTOR
LEVEL_CAP_FACTOR = WALLCLOCK_CAP_FACTOR


@dataclass
class Step1Result:
    """One level's STEP I outcome.

    Attributes
    ----------
    waypoints : numpy.ndarray or None
        ``(k, 3)`` chain vertices (x, y, z) [m]; None without a solution.
    costs : dict of str to float
        ``{C_l, C_r, C_d, C_e}`` [m].
    f : float
        Cost (eq. 11) with the ORIGINAL weights [m]; inf without a solution.
    energy_J : float
        Energy the chain needs [J].
    time_s : float
        Flight time of the chain [s].
    compute_s : float
        Wall clock of the whole level [s].
    status : str
        ``"solved"``, ``"no_solution"`` or ``"energy_infeasible"``.
    reason : str
        Why not solved, ``""`` otherwise.
    label : str
        The level's label.
    planner : str
        The planner that solved it.
    tries : int
        Plans made (N_t tries at most).
    weights_used : tuple of float
        The weights (w_l, w_r, w_d, w_e) of the plan kept.
    info : dict
        Per-try details (``tries``) and ``stopped_by == "time"`` when a wall-clock cap was hit.
    """

    waypoints: np.ndarray | None
    costs: dict
    f: float
    energy_J: float
    time_s: float
    compute_s: float
    status: str
    reason: str = ""
    label: str = ""
    planner: str = ""
    tries: int = 0
    weights_used: tuple[float, ...] = ()
    info: dict = field(default_factory=dict)

    @property
    def solved(self) -> bool:
        """True when ``status == "solved"``.
        """
        return self.status == "solved"


def _empty(problem: PlanningProblem, planner: str, status: str, reason: str, t0: float, tries: int = 0
           ) -> Step1Result:
    return Step1Result(None, {k: math.nan for k in COST_NAMES}, math.inf, math.nan, math.nan,
                       time.perf_counter() - t0, status, reason, problem.label, planner, tries, problem.weights)


def _check(planner: str, time_budget_s: float) -> None:
    if planner not in PLANNERS:
        raise UnknownNameError("planner", planner, PLANNERS)
    if not (isinstance(time_budget_s, int | float) and math.isfinite(time_budget_s) and time_budget_s > 0):
        raise InputError(f"time budget {time_budget_s} s must be a positive number of seconds (e.g. 5)")


def bitstar_iterations(time_budget_s: float) -> int:
    """The BIT* iteration count that stands for a budget of ``time_budget_s`` [s].

    Parameters
    ----------
    time_budget_s : float
        Planning budget [s].

    Returns
    -------
    int
        ``ceil(BITSTAR_ITERATIONS_PER_S * time_budget_s)``, at least 1.
    """
    return max(1, math.ceil(BITSTAR_ITERATIONS_PER_S * float(time_budget_s)))


def _solve_once(problem: PlanningProblem, planner: str, time_budget_s: float, seed: int, refine: bool,
                step_cells: int, max_iterations: int | None, h2: np.ndarray | None = None,
                deadline: float = math.inf, z_anchor_m: float | None = None,
                edge_cache: EdgeCache | None = None) -> tuple[np.ndarray | None, dict]:
    """One plan; ``deadline``: ``time.perf_counter()`` value at which the level's cap ends."""
    left = deadline - control.work_clock()
    if planner == "potential":          # seed 004 III-B: numerical potential field (deterministic)
        from skyroute.stages.planning.potential import plan_potential

        r = plan_potential(problem, time_limit_s=left)
        return r["waypoints"], {"stopped_by": r["stopped_by"] or "completed", "reason": r["reason"],
                                "compute_s": r["compute_s"]}
    if planner == "astar":   # multi-resolution above a problem size (issue 23), else plan_grid as before
        from skyroute.stages.planning.multires import plan_astar

        r = plan_astar(problem, step_cells=step_cells, refine=refine, h2=h2, time_limit_s=left, z_anchor_m=z_anchor_m,
                       edge_cache=edge_cache)
        return r["waypoints"], {"lattice_f": r["lattice_f"], "expanded": r["expanded"],
                                "stopped_by": r["stopped_by"] or "completed",
                                **({"multires": r["multires"]} if "multires" in r else {})}
    from skyroute.stages.planning.bitstar import plan_bitstar

    if max_iterations is None:          # deterministic: an iteration count, wall clock as a safety cap
        max_iterations = bitstar_iterations(time_budget_s)
        cap_s = BITSTAR_TIME_CAP_FACTOR * time_budget_s
    elif max_iterations == 0:           # wall clock only (not reproducible run to run)
        max_iterations, cap_s = None, time_budget_s
    else:
        cap_s = time_budget_s
    r = plan_bitstar(problem, max(min(cap_s, left), 1e-3), seed=seed, max_iterations=max_iterations)
    r["stopped_by"] = ("iterations" if max_iterations is not None and r["iterations"] >= max_iterations
                       else "time")
    wp = r["waypoints"]
    info = {k: v for k, v in r.items() if k != "waypoints"}
    if wp is not None and refine:
        wp = refine_path(problem, wp, time_limit_s=deadline - control.work_clock())
        if control.work_clock() > deadline:
            info["refine_stopped_by"] = "time"
    return wp, info


def _no_path_reason(label: str, planner: str, info: dict, cap_s: float, time_budget_s: float) -> str:
    if info.get("stopped_by") == "time":
        return (f"{label}: {planner} budget exhausted: no path found within the wall-clock cap of {cap_s:g} s "
                f"({LEVEL_CAP_FACTOR:g} x the {time_budget_s:g} s budget)")
    if planner == "potential":
        return info.get("reason") or f"{label}: the potential field found no path"
    if planner == "astar":
        return (f"{label}: A* searched the whole lattice ({info.get('expanded', 0)} nodes expanded): no path "
                "from start to goal within the altitude bounds, no-fly zones, flight-path angle and wind limits")
    return f"{label}: BIT* found no path in {info.get('iterations', 0)} iterations ({info.get('compute_s', 0):.1f} s)"


def plan_step1(problem: PlanningProblem, planner: str = "astar", time_budget_s: float = 5.0, seed: int = 0,
               max_tries: int = 3, refine: bool = True, step_cells: int = STEP_CELLS,
               max_iterations: int | None = None, h2: np.ndarray | None = None,
               battery_reserve_pct: float = 0.0, z_anchor_m: float | None = None,
               edge_cache: EdgeCache | None = None, energy_refusal: bool | None = None) -> Step1Result:
    """STEP I on one level: plan, check the energy, re-plan with larger w_l if needed.

    Every level, all tries and refinement included, stops at the wall-clock cap
    ``LEVEL_CAP_FACTOR * time_budget_s`` (A*: no path, reason "budget exhausted", or the path
    refined so far; ``info["stopped_by"] == "time"`` says the cap was hit).  A level whose start
    or goal is not a valid state gives ``status="no_solution"`` and the reason.

    Parameters
    ----------
    problem : PlanningProblem
        One coverage level's problem.
    planner : str, default "astar"
        One of :data:`PLANNERS` (not a fixed-wing planner).
    time_budget_s : float, default 5.0
        BIT*'s budget per try [s], > 0 (A* runs to completion).
    seed : int, default 0
        BIT* random seed (OMPL seed = seed + 1, OMPL ignores 0); try ``i`` uses ``seed + i``.
    max_tries : int, default 3
        Plans in all (N_t), >= 1.
    refine : bool, default True
        Shortcut + vertex relaxation of the chain (never increases f).
    step_cells : int, default :data:`~skyroute.stages.planning.grid_planner.STEP_CELLS`
        A* lattice step [cells].
    max_iterations : int, optional
        BIT* stops after that many iterations; None (default): after :func:`bitstar_iterations`
        (``time_budget_s``) iterations, with a wall-clock cap of
        ``BITSTAR_TIME_CAP_FACTOR * time_budget_s`` -- reproducible run to run; 0: wall clock only
        (``time_budget_s``; the result depends on the machine's load).
    h2 : numpy.ndarray, optional
        Precomputed A* heuristic table for the first try
        (:func:`~skyroute.stages.planning.grid_planner.shared_heuristic`).
    battery_reserve_pct : float, default 0.0
        Reserve [%] in [0, 100): the chain may use ``battery * (1 - reserve / 100)``.
    z_anchor_m : float, optional
        A* only: the altitude [m] its lattice levels are aligned on (default the start's).
    edge_cache : EdgeCache, optional
        A* only: the :class:`~skyroute.stages.planning.grid_planner.EdgeCache` of ``problem``'s
        maps, weights and vehicle, used by the first try (the later ones change the weights).
    energy_refusal : bool, optional
        True: refuse a rotorcraft level before any search when its energy lower bound
        (:func:`~skyroute.stages.planning.energy_bound.energy_lower_bound`) exceeds the usable
        battery; False: plan it as before (the benchmarks' reference path); default: True for a
        mission whose start and goal are at least :data:`ENERGY_BOUND_MIN_M` apart.

    Returns
    -------
    Step1Result
        ``status`` "solved", "no_solution" or "energy_infeasible" (with the numbers in
        ``reason``); ``info["energy_bound_j"]`` the energy lower bound [J] when it was computed.

    Raises
    ------
    UnknownNameError
        When ``planner`` is not one of :data:`PLANNERS`.
    InputError
        When ``time_budget_s`` is not a positive number, ``planner`` is a fixed-wing planner,
        ``max_tries < 1`` or ``battery_reserve_pct`` is outside [0, 100).

    References
    ----------
    Seed 000 section III-A (STEP I, energy feasibility III-A.3); seed 001 section 3.1.
    """
    _check(planner, time_budget_s)
    if planner in ("eeastar", "astar-fw", "energy-optimal"):
        raise InputError(f"planner {planner!r} is a fixed-wing planner: call "
                         "skyroute.stages.planning.fixedwing.plan_fixedwing (plan_strategic does)")
    if int(max_tries) < 1:
        raise InputError(f"max_tries {max_tries} must be >= 1 (N_t)")
    t0 = time.perf_counter()
    cap_s = LEVEL_CAP_FACTOR * float(time_budget_s)
    deadline = control.work_clock() + cap_s          # the safety net (JIT compilation excluded)
    why = problem.endpoint_problem()
    if why:
        return _empty(problem, planner, "no_solution", why, t0)
    if not 0 <= battery_reserve_pct < 100:
        raise InputError(f"battery_reserve_pct {battery_reserve_pct} must be in [0, 100) [%]")
    battery = problem.vehicle.battery_energy_j * (1.0 - battery_reserve_pct / 100.0)
    w = list(problem.weights)
    best = None
    info: dict = {"tries": []}
    if energy_refusal is None:        # by default for missions long enough for the bound to pay
        energy_refusal = math.dist(problem.start_xyz[:2], problem.goal_xyz[:2]) >= ENERGY_BOUND_MIN_M
    if energy_refusal and not isinstance(problem.vehicle, FixedWingProfile):
        lb = energy_lower_bound(problem)
        info["energy_bound_j"] = lb["bound_j"]
        info["energy_bound_s"] = lb["compute_s"]
        if math.isfinite(lb["bound_j"]) and lb["bound_j"] > battery:   # inf (no chain of cells): the search says why
            r = _empty(problem, planner, "energy_infeasible",
                       f"{problem.label}: no path can be flown on the battery: every path needs at least "
                       f"{lb['bound_j'] / 3600:.1f} Wh (energy lower bound over the winds at the admissible altitudes), "
                       f"more than the battery's usable {battery / 3600:.1f} Wh (refused before the search)", t0)
            r.info = info
            return r
    for attempt in range(int(max_tries)):
        if attempt > 0 and control.work_clock() >= deadline:
            info["stopped_by"] = "time"
            break
        prob = problem if attempt == 0 else problem.with_weights(w)
        wp, inf = _solve_once(prob, planner, time_budget_s, seed + attempt, refine, step_cells, max_iterations,
                              h2 if attempt == 0 else None, deadline, z_anchor_m,
                              edge_cache if attempt == 0 else None)
        if "time" in (inf.get("stopped_by"), inf.get("refine_stopped_by")):
            info["stopped_by"] = "time"
        if wp is None:
            info["tries"].append({"weights": tuple(w), "solved": False, **inf})
            if attempt == 0:
                r = _empty(problem, planner, "no_solution", _no_path_reason(problem.label, planner, inf, cap_s,
                                                                            time_budget_s), t0, 1)
                r.info = info
                return r
            break
        pc = problem.path_costs(wp)
        info["tries"].append({"weights": tuple(w), "solved": True, "energy_J": pc["energy_J"], "f": pc["f"], **inf})
        if best is None or pc["energy_J"] < best[1]["energy_J"]:
            best = (wp, pc, tuple(w), attempt + 1)
        if pc["energy_J"] <= battery or planner == "potential":   # the potential ignores the weights
            break
        w[0] = 2.0 * w[0] if w[0] > 0 else float(sum(w))
    wp, pc, wused, ntry = best
    status, reason = "solved", ""
    if pc["energy_J"] > battery:
        status = "energy_infeasible"
        reason = (f"{problem.label}: the best path needs {pc['energy_J'] / 3600:.1f} Wh, more than the battery's "
                  f"usable {battery / 3600:.1f} Wh after {len(info['tries'])} tries with increasing w_l (N_t = {max_tries})")
    return Step1Result(wp, {k: pc[k] for k in COST_NAMES}, pc["f"], pc["energy_J"], pc["time_s"],
                       time.perf_counter() - t0, status, reason, problem.label, planner, len(info["tries"]),
                       wused, info)


def step1_all_levels(problems: list[PlanningProblem], planner: str = "astar", time_budget_s: float = 5.0,
                     seed: int = 0, max_tries: int = 3, **kwargs) -> list[Step1Result]:
    """:func:`plan_step1` on every coverage level (same planner, budget and seed per level).

    Parameters
    ----------
    problems : list of PlanningProblem
        One per coverage level.
    planner : str, default "astar"
        One of :data:`PLANNERS`.
    time_budget_s : float, default 5.0
        Budget per level [s], > 0.
    seed : int, default 0
        Random seed.
    max_tries : int, default 3
        Plans per level (N_t).
    **kwargs
        Go to :func:`plan_step1`.

    Returns
    -------
    list of Step1Result
        One per level, in order.

    Raises
    ------
    UnknownNameError, InputError
        As :func:`plan_step1`.
    """
    _check(planner, time_budget_s)
    return [plan_step1(p, planner, time_budget_s, seed, max_tries, **kwargs) for p in problems]


__all__ = ["BITSTAR_ITERATIONS_PER_S", "LEVEL_CAP_FACTOR", "WALLCLOCK_CAP_FACTOR", "PLANNERS", "Step1Result", "bitstar_iterations", "plan_step1",
           "step1_all_levels"]
