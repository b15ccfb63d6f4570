"""BIT* on OMPL's Dubins-airplane state space (``OwenStateSpace``): a continuous comparison for
the fixed-wing lattice planners (seed 002; issue 13 "beyond the seed").

The state is ``(x, y, z, yaw)``; OMPL's ``OwenStateSpace(R, gamma_max)`` connects two states by
the shortest Dubins-airplane curve (Owen, Beard & McLain 2015) with the minimum turn radius
``R`` [m] and the pitch limit ``gamma_max`` [rad].  Here ``R`` is the lattice planners' ground
radius (:func:`~skyroute.stages.planning.fixedwing.turn_radius_m`: airspeed at the highest
altitude plus the strongest wind) and ``gamma_max`` the smaller of the climb and descent angle
limits (the space is symmetric), its tangent less 1 % (the chords of the sampled helices,
shorter than the arcs, then stay within the limit).  Validity: the problem's compiled state check (floor, ceiling,
AOI) at every state OMPL checks along a motion (``longest valid segment`` = half a raster
cell); the objective is OMPL's path length (the Dubins-airplane length), so BIT* converges to
the shortest flyable curve -- the continuous counterpart of ``astar-fw``.  Its seed-002 energy
is computed on the densely interpolated curve with
:func:`~skyroute.stages.planning.fixedwing.path_energy`, like the lattice paths'.

Reproducible with ``seed`` and ``max_iterations`` (as :mod:`.bitstar`).
"""

from __future__ import annotations

import math
import time

import numpy as np
from ompl import base as ob
from ompl import geometric as og
from ompl import util as ou

from skyroute.stages import control
from skyroute.stages.base import InputError
from skyroute.stages.planning.bitstar import StateValidity
from skyroute.stages.planning.fixedwing import FwPlanResult, _vehicle, path_energy, turn_radius_m
from skyroute.stages.planning.problem import PlanningProblem

__all__ = ["DUBINS_ITERATIONS_PER_S", "dubins_iterations", "dubins_result", "plan_bitstar_dubins"]


class _Length(ob.OptimizationObjective):
    """The Dubins-airplane length (OMPL's informed samplers do not support this space: a plain
    objective, whose default informed sampler is rejection sampling), with the straight-line
    3-D distance as its admissible heuristics."""

    def __init__(self, si, space, goal_xyz):
        super().__init__(si)
        self._space = space
        self._goal = goal_xyz

    def stateCost(self, s):
        return ob.Cost(0.0)

    def motionCost(self, s1, s2):
        return ob.Cost(self._space.distance(s1, s2))

    def motionCostHeuristic(self, s1, s2):
        return ob.Cost(math.sqrt((s1[0] - s2[0]) ** 2 + (s1[1] - s2[1]) ** 2 + (s1[2] - s2[2]) ** 2))

    def hasCostToGoHeuristic(self) -> bool:
        return True

    def costToGo(self, s, goal):
        gx, gy, gz = self._goal
        return ob.Cost(math.sqrt((s[0] - gx) ** 2 + (s[1] - gy) ** 2 + (s[2] - gz) ** 2))


def plan_bitstar_dubins(problem: PlanningProblem, time_budget_s: float = 10.0, seed: int = 0,
                        max_iterations: int | None = None, spacing_m: float | None = None) -> dict:
    """BIT* from the start (heading: towards the goal) to the goal (same heading) in the
    Dubins-airplane space of ``problem`` (module docstring).  Returns ``solved``, ``xyz_m``
    (m, 3) [m] the curve sampled every ``spacing_m`` (default: half a cell, at most R / 10) or None,
    ``length_m`` (3-D, of the samples), ``energy_J`` (seed 002), ``turn_radius_m``,
    ``max_pitch_deg``, ``compute_s``, ``iterations``."""
    if not time_budget_s > 0:
        raise InputError(f"time budget {time_budget_s} s must be > 0")
    veh = _vehicle(problem)
    g = problem.grid
    fin = problem.floor_m[np.isfinite(problem.floor_m)]
    zlo = float(fin.min()) if fin.size else float(problem.terrain_m.min())
    zhi = float(np.max(problem.ceiling_m[np.isfinite(problem.ceiling_m)]))
    radius = turn_radius_m(problem, max(zhi, problem.start_xyz[2], problem.goal_xyz[2]))
    # 1 % below the limit: chords of the sampled helices are shorter than their arcs
    pitch = math.atan(0.99 * math.tan(math.radians(min(veh.max_climb_angle_deg, veh.max_descent_angle_deg))))
    ou.setLogLevel(ou.LOG_NONE)
    ou.RNG.setSeed(int(seed) + 1)
    ou.setLogLevel(ou.LOG_ERROR)
    space = ob.OwenStateSpace(float(radius), float(pitch))
    b = ob.RealVectorBounds(3)
    xmin, ymin, xmax, ymax = g.bounds
    for i, (lo, hi) in enumerate(((xmin, xmax), (ymin, ymax), (zlo, max(zhi, zlo + 1.0)))):
        b.setLow(i, lo)
        b.setHigh(i, hi)
    space.setBounds(b)
    si = ob.SpaceInformation(space)
    checker = StateValidity(si, problem)
    si.setStateValidityChecker(checker)
    space.setLongestValidSegmentFraction(0.5 * g.resolution_m / space.getMaximumExtent())
    si.setup()
    start, goal = si.allocState(), si.allocState()
    s0, s1 = np.asarray(problem.start_xyz, float), np.asarray(problem.goal_xyz, float)
    yaw = math.atan2(s1[1] - s0[1], s1[0] - s0[0])
    for st, p in ((start, s0), (goal, s1)):
        for i in range(3):
            st[i] = float(p[i])
        st.setYaw(yaw)
    pdef = ob.ProblemDefinition(si)
    pdef.setStartAndGoalStates(start, goal, 1e-6)
    objective = _Length(si, space, tuple(float(v) for v in s1))
    pdef.setOptimizationObjective(objective)
    planner = og.BITstar(si)
    planner.setProblemDefinition(pdef)
    planner.setup()
    t0 = time.perf_counter()
    deadline = control.work_clock() + float(time_budget_s)   # safety net; JIT excluded
    n = None if max_iterations is None else int(max_iterations)

    def stop() -> bool:
        return ((n is not None and planner.numIterations() >= n) or control.work_clock() > deadline
                or control.cancelled())

    ptc = ob.PlannerTerminationCondition(stop)
    ok = bool(planner.solve(ptc)) and pdef.hasExactSolution()
    control.check()
    dt = time.perf_counter() - t0
    out = {"solved": ok, "xyz_m": None, "length_m": math.nan, "energy_J": math.nan, "turn_radius_m": radius,
           "max_pitch_deg": math.degrees(pitch), "compute_s": dt, "iterations": int(planner.numIterations())}
    if not ok:
        return out
    path = pdef.getSolutionPath()
    step = float(spacing_m) if spacing_m else min(0.5 * g.resolution_m, 0.1 * radius)
    path.interpolate(max(2, int(math.ceil(path.length() / step)) + 1))
    xyz = np.array([[s[0], s[1], s[2]] for s in path.getStates()], float)
    keep = np.r_[True, np.linalg.norm(np.diff(xyz, axis=0), axis=1) > 1e-9]
    xyz = xyz[keep]
    out.update(xyz_m=xyz, length_m=float(np.linalg.norm(np.diff(xyz, axis=0), axis=1).sum()),
               energy_J=path_energy(problem, xyz)["energy_J"])
    return out


DUBINS_ITERATIONS_PER_S = 100.0   # bitstar-dubins: BIT* iterations per second of planner.time_budget_s


def dubins_iterations(time_budget_s: float) -> int:
    """The BIT* iteration count of ``bitstar-dubins`` for a budget of ``time_budget_s`` [s]:
    ``ceil(DUBINS_ITERATIONS_PER_S * time_budget_s)``, at least 1."""
    return max(1, math.ceil(DUBINS_ITERATIONS_PER_S * float(time_budget_s)))


def dubins_result(problem: PlanningProblem, time_budget_s: float, seed: int = 0,
                  time_limit_s: float | None = None) -> FwPlanResult:
    """``bitstar-dubins`` as a :class:`FwPlanResult`: BIT* on the Dubins-airplane space
    (:func:`plan_bitstar_dubins`) for
    ``ceil(DUBINS_ITERATIONS_PER_S x time_budget_s)`` iterations (``time_limit_s`` [s]: the
    wall-clock cap); ``waypoints`` is the sampled curve (``info["continuous"]``: the written
    plan takes it as it is, no fillets), ``energy_J`` its seed-002 energy."""
    t0 = time.perf_counter()
    why = problem.endpoint_problem()
    if why:
        return FwPlanResult(None, math.nan, math.nan, math.nan, 0, 0.0, "no_solution", why, "bitstar-dubins")
    n = dubins_iterations(time_budget_s)
    cap = float(time_limit_s) if time_limit_s else 4.0 * float(time_budget_s) + 10.0
    r = plan_bitstar_dubins(problem, cap, seed=seed, max_iterations=n)
    info = {"turn_radius_m": r["turn_radius_m"], "max_pitch_deg": r["max_pitch_deg"], "iterations": r["iterations"],
            "continuous": True, "stopped_by": "time" if (not r["solved"] and r["iterations"] < n) else "completed"}
    if not r["solved"]:
        return FwPlanResult(None, math.nan, math.nan, math.nan, r["iterations"], time.perf_counter() - t0,
                            "no_solution", f"{problem.label}: bitstar-dubins found no curve in {r['iterations']} "
                            "iterations", "bitstar-dubins", info)
    pe = path_energy(problem, r["xyz_m"])
    return FwPlanResult(r["xyz_m"], pe["energy_J"], pe["length_m"], pe["time_s"], r["iterations"],
                        time.perf_counter() - t0, "solved", "", "bitstar-dubins", {**info, **pe})
