"""STEP I with OMPL BIT* (seed 000 section III-A; OMPL 2.x Python bindings).

The 3-D state space is ``RealVectorStateSpace(3)`` bounded by the AOI and the altitude range
of the problem (lowest finite floor .. highest ceiling) [m].  Validity and costs come from
:class:`~skyroute.stages.planning.problem.PlanningProblem`:

* state validity checker -> the compiled state check (floor, ceiling, AOI, wind);
* motion validator -> the compiled exact motion check (cells crossed, angle, wind, eq. 3);
* objective: a subclass of ``ob.OptimizationObjective`` (subclassing
  ``StateCostIntegralObjective`` in Python is silently ignored by the OMPL 2.0.1 planners)
  with ``stateCost`` = 0, ``motionCost`` = f of eq. 11 (one compiled call), an admissible
  ``motionCostHeuristic`` = ``cost_rate_lb * |s2 - s1|`` and the same cost-to-go heuristic
  to the goal, so that BIT*'s informed sampling and pruning work.

Every OMPL object and Python callback is kept alive on a :class:`_BitStarSetup` (the C++ side
holds raw pointers to the Python objects).

Reproducibility: ``ompl.util.RNG.setSeed(seed + 1)`` (OMPL ignores 0) is called before the
planner is built.  OMPL logs "Random number generation already started. Changing seed now will
not lead to deterministic sampling" when this is not the first seed of the process, yet the
RNGs the planner creates afterwards are re-seeded: measured here, two runs with the same seed
and iteration limit return identical paths in one process (the message is silenced).  With
a wall-clock budget the number of batches BIT* completes depends on the CPU load, so two runs
may stop at different iterations and return different paths; with ``max_iterations`` the
planner stops on its iteration count and is reproducible run to run (tested).  STEP I
(:func:`~skyroute.stages.planning.step1.plan_step1`) therefore stops BIT* on an iteration count
by default (:func:`~skyroute.stages.planning.step1.bitstar_iterations` of the budget), the
wall clock being only a safety cap.
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
from skyroute.stages.planning.kernels import OK, entry_point, segment_eval, state_code
from skyroute.stages.planning.problem import PlanningProblem

ou.setLogLevel(ou.LOG_ERROR)


class StateValidity(ob.StateValidityChecker):
    """OMPL validity of an (x, y, z) state: the compiled state check of the planning problem
    (also used by :mod:`.bitstar_dubins`)."""

    def __init__(self, si, problem: PlanningProblem):
        super().__init__(si)
        self._args = problem.state_args
        self._code = entry_point(state_code, 0.0, 0.0, 0.0, *self._args)

    def isValid(self, s) -> bool:
        return self._code(s[0], s[1], s[2], *self._args) == OK


class _Motion(ob.MotionValidator):
    def __init__(self, si, problem: PlanningProblem):
        super().__init__(si)
        self._args = problem.seg_args
        self._buf = np.empty(6)
        self._eval = entry_point(segment_eval, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, False, *self._args, self._buf)

    def checkMotion(self, s1, s2) -> bool:
        return self._eval(s1[0], s1[1], s1[2], s2[0], s2[1], s2[2], False, *self._args, self._buf) == OK


class _Objective(ob.OptimizationObjective):
    """f = w_l C_l + w_r C_r + w_d C_d + w_e C_e (eq. 11) with admissible heuristics."""

    def __init__(self, si, problem: PlanningProblem):
        super().__init__(si)
        self._args = problem.seg_args
        self._buf = np.empty(6)
        self._eval = entry_point(segment_eval, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, True, *self._args, self._buf)
        self._w = problem.weights
        self._rate = problem.cost_rate_lb
        self._goal = problem.goal_xyz
        self.n_calls = 0
        self.n_ctg = 0
        self.n_heur = 0

    def hasCostToGoHeuristic(self) -> bool:
        return True

    def costToGo(self, s, goal):
        self.n_ctg += 1
        gx, gy, gz = self._goal
        return ob.Cost(self._rate * math.sqrt((s[0] - gx) ** 2 + (s[1] - gy) ** 2 + (s[2] - gz) ** 2))

    def stateCost(self, s):
        return ob.Cost(0.0)

    def motionCost(self, s1, s2):
        self.n_calls += 1
        b = self._buf
        self._eval(s1[0], s1[1], s1[2], s2[0], s2[1], s2[2], True, *self._args, b)
        w = self._w
        f = w[0] * b[0] + w[1] * b[1] + w[2] * b[2] + (w[3] * b[3] if w[3] > 0 else 0.0)
        return ob.Cost(f if math.isfinite(f) else math.inf)

    def motionCostHeuristic(self, s1, s2):
        self.n_heur += 1
        return ob.Cost(self._rate * math.sqrt((s1[0] - s2[0]) ** 2 + (s1[1] - s2[1]) ** 2 + (s1[2] - s2[2]) ** 2))


class _BitStarSetup:
    """Holds the OMPL objects of one BIT* run (keeps Python references alive)."""

    def __init__(self, problem: PlanningProblem, seed: int, samples_per_batch: int = 100,
                 rewire_factor: float = 1.1):
        if int(seed) < 0:
            raise InputError(f"seed {seed} must be >= 0")
        ou.setLogLevel(ou.LOG_NONE)     # setSeed after the first RNG logs an error, but re-seeds
        ou.RNG.setSeed(int(seed) + 1)   # OMPL ignores seed 0
        ou.setLogLevel(ou.LOG_ERROR)
        self.problem = problem
        g = problem.grid
        xmin, ymin, xmax, ymax = g.bounds
        fin = problem.floor_m[np.isfinite(problem.floor_m)]
        zlo = float(fin.min()) if fin.size else float(problem.terrain_m.min())
        zhi = float(problem.ceiling_m.max())
        self.space = ob.RealVectorStateSpace(3)
        b = ob.RealVectorBounds(3)
        for i, (lo, hi) in enumerate(((xmin, xmax), (ymin, ymax), (zlo, max(zhi, zlo + 1.0)))):
            b.setLow(i, lo)
            b.setHigh(i, hi)
        self.bounds = b
        self.space.setBounds(b)
        self.si = ob.SpaceInformation(self.space)
        self.checker = StateValidity(self.si, problem)
        self.motion = _Motion(self.si, problem)
        self.si.setStateValidityChecker(self.checker)
        self.si.setMotionValidator(self.motion)
        self.si.setup()
        self.objective = _Objective(self.si, problem)
        self.pdef = ob.ProblemDefinition(self.si)
        self.start = self.si.allocState()
        self.goal = self.si.allocState()
        for st, p in ((self.start, problem.start_xyz), (self.goal, problem.goal_xyz)):
            for i in range(3):
                st[i] = float(p[i])
        self.pdef.setStartAndGoalStates(self.start, self.goal, 1e-6)
        self.pdef.setOptimizationObjective(self.objective)
        self.planner = og.BITstar(self.si)
        self.planner.setSamplesPerBatch(int(samples_per_batch))
        self.planner.setRewireFactor(float(rewire_factor))
        self.planner.setProblemDefinition(self.pdef)
        self.planner.setup()

    def solve(self, time_budget_s: float, max_iterations: int | None = None) -> tuple[bool, float]:
        t0 = time.perf_counter()
        planner = self.planner
        n = int(max_iterations) if max_iterations is not None else None
        deadline = control.work_clock() + float(time_budget_s)   # safety net; JIT excluded

        def stop() -> bool:   # iteration count, wall-clock cap, cancel request
            return ((n is not None and planner.numIterations() >= n) or control.work_clock() > deadline
                    or control.cancelled())

        self._ptc = ob.PlannerTerminationCondition(stop)
        status = self.planner.solve(self._ptc)
        control.check()
        if control.work_clock() > deadline and not (n is not None and planner.numIterations() >= n):
            control.note_clock_stop()
        dt = time.perf_counter() - t0
        return bool(status) and self.pdef.hasExactSolution(), dt

    def waypoints(self) -> np.ndarray:
        path = self.pdef.getSolutionPath()
        states = path.getStates()
        return np.array([[s[0], s[1], s[2]] for s in states], dtype=float)


def plan_bitstar(problem: PlanningProblem, time_budget_s: float, seed: int = 0,
                 max_iterations: int | None = None, samples_per_batch: int = 100) -> dict:
    """Run BIT* on ``problem`` for ``time_budget_s`` [s] (or until ``max_iterations`` BIT*
    iterations, the budget still being an upper limit).  Returns a dict with ``waypoints``
    (k, 3) [m] or None, ``solved``, ``compute_s``, ``iterations``, ``motion_cost_calls``."""
    if not time_budget_s > 0:
        raise InputError(f"time budget {time_budget_s} s must be > 0")
    setup = _BitStarSetup(problem, seed, samples_per_batch)
    ok, dt = setup.solve(time_budget_s, max_iterations)
    wp = setup.waypoints() if ok else None
    return {"waypoints": wp, "solved": ok, "compute_s": dt, "iterations": int(setup.planner.numIterations()),
            "motion_cost_calls": setup.objective.n_calls, "heuristic_calls": setup.objective.n_heur,
            "cost_to_go_calls": setup.objective.n_ctg, "best_cost": float(setup.planner.bestCost().value())}


__all__ = ["StateValidity", "plan_bitstar"]
