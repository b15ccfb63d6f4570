"""STEP II: strategic deconfliction against known traffic (seed 000 section III-B, Algorithm 1),
by a time- and energy-aware RRT.

The STEP I polygonal chain ``W`` is flown at the speeds of the energy model
(:func:`~skyroute.stages.energy.segment_energy`, eq. 2-4), which gives each waypoint an arrival
time and a cumulative energy.  If no leg crosses a volume reserved to an intruder at the time
it is flown (:meth:`~skyroute.stages.traffic.TrafficOccupancy.segment_conflicts`, exact), the
chain is returned unchanged.  Otherwise an RRT whose nodes store position, arrival time and
cumulative energy (``Gamma_p, Gamma_t, Gamma_e``) is grown from ``w_start`` following
Algorithm 1:

* GET_NEXT_POINT: the first point of ``W`` not yet in the tree satisfying eq. 14,
  ``0 < (w_goal - n(w_goal)) . (w_n - n(w_goal)) / |w_goal - n(w_goal)|^2 <= 1`` (the paper
  prints the dot product without the normalisation; normalised, it says "ahead of the tree's
  frontier towards the goal and not beyond it"); ``w_goal`` when none does;
* IS_FEASIBLE(a, b): the leg from tree node ``a`` (at its arrival time and energy) to ``b`` is
  statically valid (``problem.motion_valid``: floors, ceiling, flight-path angle, no-fly,
  wind), flyable (eq. 3), keeps the cumulative energy within the battery, and has no traffic
  conflict over ``[t_a, t_a + tau]``;
* GET_LAST_FEASIBLE: the farthest feasible point along ``n(w_n) -> w_n`` (steps of
  ``step_m``); RANDOM_SAMPLE: a Gaussian around it (``sigma_m`` horizontally,
  ``sigma_m * vertical_ratio`` vertically, both widened up to 4x while consecutive
  iterations fail) -- the sampling bias around the STEP I chain.
  Addition to the paper: with probability ``explore`` the Gaussian is centred on a uniformly
  drawn point of the STEP I chain instead, so that other branches grow when the frontier is
  boxed in by a reserved volume (no waiting/hovering is modelled, so a node whose arrival time
  lies inside a moving reservation can be a dead end);
* GET_CONNECTING_POINT: the parent of the nearest node if the leg from it is feasible, else the
  nearest node (short-cuts without post-hoc pruning, which would change node times);
* after each insertion, the leg to ``w_{n+}`` (the point after ``w_n`` in ``W``) is tried and
  added when feasible; the search ends when ``w_goal`` enters the tree.

The RRT is not asymptotically optimal and uses no risk/landing costs (seed 000: they only
shape the optimisation, which this step does not do).  Randomness comes from
``np.random.default_rng(seed)`` and the search stops on its iteration count ``max_iter`` (or
when the goal enters the tree), so a seed gives one result on any machine.  The wall clock
only caps a run (``time_budget_s``, a safety net far above the normal run time); a run stopped
by it says so in its ``reason`` and ``notes`` (that result could depend on the machine's load).

Beyond the occupancy maps' horizon ``[t0, t0 + T_tot]`` nothing is known about the traffic:
leg pieces after the horizon are not checked (the result reports it in ``reason``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from skyroute.stages import control
from skyroute.stages.base import InputError
from skyroute.stages.planning.kernels import OK, entry_point, segment_eval_if_valid
from skyroute.stages.planning.problem import PlanningProblem
from skyroute.stages.traffic import TrafficOccupancy
from skyroute.stages.vehicle import FixedWingProfile

__all__ = ["Step2Result", "chain_conflicts", "chain_timing", "deconflict", "leg_conflicts", "leg_time_energy"]

MAX_ITER = 5000   # K, the RRT's iterations (seed 000)
STATUS_UNCHANGED = "unchanged"
STATUS_DECONFLICTED = "deconflicted"
STATUS_FAILED = "failed"


@dataclass(frozen=True)
class Step2Result:
    """STEP II output: polygonal chain ``waypoints`` (k, 3) [m], arrival times ``times_s`` (k,)
    [s since mission start] and cumulative energy ``energy_J`` (k,) [J] at each waypoint.
    ``status``: ``"unchanged"`` (STEP I chain already conflict-free), ``"deconflicted"`` (RRT
    result) or ``"failed"`` (no chain; ``reason`` says why, arrays are empty)."""

    waypoints: np.ndarray
    times_s: np.ndarray
    energy_J: np.ndarray
    status: str
    reason: str = ""
    iterations: int = 0
    tree_size: int = 0
    compute_time_s: float = 0.0
    notes: tuple[str, ...] = field(default_factory=tuple)
    # (n, 8) [x0, y0, z0, t0, x1, y1, z1, t1] ([m], [s]) every leg the RRT found free of traffic
    # (bounds and battery passed); more traffic changes an RRT run only if it conflicts with one
    # of them (the other answers stay "infeasible").  None: no RRT ran, or the wall clock stopped it.
    free_legs: np.ndarray | None = None

    @property
    def ok(self) -> bool:
        return self.status != STATUS_FAILED

    @property
    def segment_times_s(self) -> np.ndarray:
        return np.diff(self.times_s)


def _failed(reason: str, iterations: int = 0, tree: int = 0, t_start: float | None = None,
            free_legs: np.ndarray | None = None) -> Step2Result:
    e = np.zeros(0)
    return Step2Result(np.zeros((0, 3)), e, e, STATUS_FAILED, reason, iterations, tree,
                       0.0 if t_start is None else time.perf_counter() - t_start, free_legs=free_legs)


# ------------------------------------------------------------------ legs


def leg_time_energy(problem, p0, p1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Time [s], energy E_w [J] and validity of legs ``p0 -> p1`` ((n,3) or (3,)) by the
    problem's own model (``PlanningProblem.segment_details``: seed 000 eq. 2-12 with the
    problem's wind map, and the same bounds as ``motion_valid``).  Time and energy are inf
    where the leg is not flyable in the wind."""
    d = problem.segment_details(np.atleast_2d(p0), np.atleast_2d(p1))
    return d["time_s"], d["energy_J"], d["code"] == 0


def chain_timing(problem, waypoints, t0_s: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Arrival times [s], cumulative energy [J] at each waypoint and per-leg validity flags of
    a chain flown at the energy model's speeds (eq. 3-4)."""
    w = np.asarray(waypoints, dtype=float)
    if w.shape[0] < 2:
        return np.array([t0_s]), np.zeros(1), np.zeros(0, bool)
    tau, e, ok = leg_time_energy(problem, w[:-1], w[1:])
    return (t0_s + np.concatenate([[0.0], np.cumsum(tau)]), np.concatenate([[0.0], np.cumsum(e)]), ok)


def leg_conflicts(occ: TrafficOccupancy | None, p0, t0, p1, t1) -> np.ndarray:
    """Traffic conflict flags (n,) of legs p0[i] -> p1[i] (n, 3) [m] flown linearly in time from
    t0[i] to t1[i] [s] (:meth:`~skyroute.stages.traffic.TrafficOccupancy.segment_conflicts`),
    restricted to the maps' horizon (pieces beyond it are free; polygon prisms,
    ``occ.volumes``, are tested over the whole leg); all False without traffic."""
    p0 = np.atleast_2d(np.asarray(p0, float))
    p1 = np.atleast_2d(np.asarray(p1, float))
    t0 = np.broadcast_to(np.asarray(t0, float), (p0.shape[0],))
    t1 = np.broadcast_to(np.asarray(t1, float), (p0.shape[0],))
    out = np.zeros(p0.shape[0], bool)
    if occ is None or occ.empty:
        return out
    if occ.volumes is not None and occ.volumes.n:     # prisms: their own time windows, no horizon
        occ.volumes.segment_hits(p0, np.ascontiguousarray(t0), p1, np.ascontiguousarray(t1), out)
    if occ.caps.shape[0] == 0:
        return out
    lo, hi = occ.t0_s, occ.t0_s + occ.t_total_s
    a, b = np.maximum(t0, lo), np.minimum(t1, hi)
    live = (a <= b) & ~out
    if not live.any():
        return out
    dur = t1 - t0
    with np.errstate(invalid="ignore", divide="ignore"):
        sa = np.where(dur > 0, (a - t0) / dur, 0.0)
        sb = np.where(dur > 0, (b - t0) / dur, 1.0)
    qa = p0 + sa[:, None] * (p1 - p0)
    qb = p0 + sb[:, None] * (p1 - p0)
    out[live] = occ.segment_conflicts(qa[live], a[live], qb[live], b[live])
    return out


def chain_conflicts(occupancy: TrafficOccupancy | None, waypoints, times_s) -> np.ndarray:
    """Per-leg traffic conflict flags (k-1,) of a timed chain."""
    w = np.asarray(waypoints, float)
    t = np.asarray(times_s, float)
    return leg_conflicts(occupancy, w[:-1], t[:-1], w[1:], t[1:])


# ------------------------------------------------------------------ the tree


class _Tree:
    def __init__(self, p0, t0, cap: int = 1024):
        self.p = np.empty((cap, 3))
        self.t = np.empty(cap)
        self.e = np.empty(cap)
        self.parent = np.empty(cap, np.int64)
        self.n = 0
        self.add(p0, t0, 0.0, -1)

    def add(self, p, t, e, parent) -> int:
        if self.n == self.p.shape[0]:
            for name in ("p", "t", "e", "parent"):
                a = getattr(self, name)
                setattr(self, name, np.concatenate([a, np.empty_like(a)]))
        i = self.n
        self.p[i], self.t[i], self.e[i], self.parent[i] = p, t, e, parent
        self.n += 1
        return i

    def nearest(self, q) -> int:
        if self.n == 1:              # what the argmin below gives for a single node
            return 0
        d = self.p[: self.n] - np.asarray(q, float)
        return int(np.argmin(np.einsum("ij,ij->i", d, d)))

    def path(self, i) -> list[int]:
        out = []
        while i >= 0:
            out.append(i)
            i = int(self.parent[i])
        return out[::-1]


def _close(x: float, y: float) -> bool:
    """``np.isclose(x, y)`` of two floats (rtol 1e-5, atol 1e-8, NaN never close), without
    numpy's per-call overhead."""
    return (abs(x - y) <= 1e-08 + 1e-05 * abs(y) and math.isfinite(y)) or x == y


def _fast_problem(problem) -> bool:
    """True when ``problem``'s legs can be evaluated by the compiled segment kernel directly:
    a rotorcraft :class:`PlanningProblem` whose ``segment_details`` is the stock one."""
    return (isinstance(problem, PlanningProblem)
            and type(problem).segment_details is PlanningProblem.segment_details
            and type(problem).motion_codes is PlanningProblem.motion_codes
            and not isinstance(problem.vehicle, FixedWingProfile))


class _Feasibility:
    """IS_FEASIBLE of Algorithm 1 with counters (for the failure reason).

    One leg at a time without numpy's per-call overheads: the compiled segment kernel is
    called directly (the one :meth:`PlanningProblem.segment_details` loops over; an invalid
    leg stops at its first violation, whose costs IS_FEASIBLE does not use) and the traffic
    test of :func:`leg_conflicts` is done on scalars -- the same floating-point operations,
    so the same answers.  Tree nodes never change once added, so the legs from a node to a
    point of the STEP I chain (asked again and again while the tree is stuck) are memoised
    (``leg_w``; the counters still count every request)."""

    def __init__(self, problem, occ, battery_j):
        self.problem, self.occ, self.battery = problem, occ, battery_j
        self.rejects = {"bounds": 0, "battery": 0, "traffic": 0}
        self._eval = None
        if _fast_problem(problem):
            self._buf = np.empty(6)
            self._args = tuple(problem.seg_args)
            self._eval = entry_point(segment_eval_if_valid, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, *self._args, self._buf)
        self._traffic = occ is not None and not occ.empty
        self._vols = occ.volumes if self._traffic and occ.volumes is not None and occ.volumes.n else None
        self._caps = self._traffic and occ.caps.shape[0] > 0
        self._p0, self._p1 = np.empty((1, 3)), np.empty((1, 3))
        self._t0, self._t1 = np.empty(1), np.empty(1)
        self._hit = np.zeros(1, bool)
        self._memo: dict = {}
        self.free: list[tuple[float, ...]] = []     # Step2Result.free_legs

    def _conflict(self, pa: np.ndarray, ta: float, q: np.ndarray, tb: float) -> bool:
        """``leg_conflicts(occ, pa, ta, q, tb)[0]`` of one leg with finite times."""
        if not self._traffic:
            return False
        if self._vols is not None:
            self._p0[0], self._p1[0], self._t0[0], self._t1[0] = pa, q, ta, tb
            self._hit[0] = False
            self._vols.segment_hits(self._p0, self._t0, self._p1, self._t1, self._hit)
            if self._hit[0]:
                return True
        if not self._caps:
            return False
        occ = self.occ
        lo, hi = occ.t0_s, occ.t0_s + occ.t_total_s
        a, b = max(ta, lo), min(tb, hi)
        if not a <= b:
            return False
        dur = tb - ta
        sa = (a - ta) / dur if dur > 0 else 0.0
        sb = (b - ta) / dur if dur > 0 else 1.0
        qa = pa + sa * (q - pa)
        qb = pa + sb * (q - pa)
        return bool(occ.segment_conflicts(qa[None, :], np.array([a]), qb[None, :], np.array([b]))[0])

    def _leg(self, tree: _Tree, a: int, q) -> tuple[tuple[bool, float, float], str | None]:
        pa = tree.p[a]
        q = np.asarray(q, float)
        x0, y0, z0 = float(pa[0]), float(pa[1]), float(pa[2])
        x1, y1, z1 = float(q[0]), float(q[1]), float(q[2])
        if _close(x0, x1) and _close(y0, y1) and _close(z0, z1):      # np.allclose(pa, q)
            return (False, 0.0, 0.0), None
        if self._eval is not None:
            ok = self._eval(x0, y0, z0, x1, y1, z1, *self._args, self._buf) == OK
            tau, e = float(self._buf[5]), float(self._buf[4])
        else:
            tau_a, e_a, ok_a = leg_time_energy(self.problem, pa, q)
            ok, tau, e = bool(ok_a[0]), float(tau_a[0]), float(e_a[0])
        if not ok:
            return (False, 0.0, 0.0), "bounds"
        if tree.e[a] + e > self.battery:
            return (False, tau, e), "battery"
        ta = float(tree.t[a])
        if self._conflict(pa, ta, q, ta + tau):
            return (False, tau, e), "traffic"
        self.free.append((x0, y0, z0, ta, x1, y1, z1, ta + tau))
        return (True, tau, e), None

    def free_legs(self) -> np.ndarray:
        return np.array(self.free, dtype=float).reshape(-1, 8)

    def leg(self, tree: _Tree, a: int, q) -> tuple[bool, float, float]:
        """(feasible, tau [s], energy [J]) of the leg node a -> q."""
        out, why = self._leg(tree, a, q)
        if why is not None:
            self.rejects[why] += 1
        return out

    def leg_w(self, tree: _Tree, a: int, i: int, q) -> tuple[bool, float, float]:
        """:meth:`leg` to ``q``, the STEP I point ``i`` (memoised on (a, i))."""
        key = ("w", a, i)
        hit = self._memo.get(key)
        if hit is None:
            hit = self._memo[key] = self._leg(tree, a, q)
        out, why = hit
        if why is not None:
            self.rejects[why] += 1
        return out

    def memo(self, key, compute, *args):
        """``compute(*args)`` once per ``key`` (a result that depends on tree nodes and STEP I
        points only); the reject counters of the computation are replayed on every call."""
        hit = self._memo.get(key)
        if hit is None:
            before = dict(self.rejects)
            val = compute(*args)
            hit = self._memo[key] = (val, {k: v - before[k] for k, v in self.rejects.items() if v != before[k]})
        else:
            for k, v in hit[1].items():
                self.rejects[k] += v
        return hit[0]


def deconflict(problem, step1_waypoints, occupancy: TrafficOccupancy | None, t0_s: float = 0.0, seed: int = 0,
               max_iter: int = MAX_ITER, time_budget_s: float = 30.0, sigma_m: float = 30.0,
               vertical_ratio: float = 0.5, step_m: float = 5.0, explore: float = 0.2,
               require_valid_chain: bool = True) -> Step2Result:
    """STEP II of seed 000 (Algorithm 1): make the STEP I chain conflict-free in time.

    Parameters
    ----------
    problem : :class:`~skyroute.stages.planning.problem.PlanningProblem` (bounds via
        ``motion_valid``, wind and vehicle for the energy model).
    step1_waypoints : (n, 3) [m] STEP I polygonal chain, ``w_start`` to ``w_goal``.
    occupancy : traffic occupancy maps (``None``: no known traffic).
    t0_s : mission time of ``w_start`` [s] (same clock as the occupancy maps).
    seed : RNG seed (``np.random.default_rng(seed)``).
    max_iter : K, the RRT's iterations: the stop rule (reproducible).
    time_budget_s : wall-clock cap [s] (> 0), a safety net; when it stops the search first the
        result says so (``reason``, ``notes``).
    sigma_m : standard deviation [m] of RANDOM_SAMPLE around the last feasible point
        (horizontal; ``vertical_ratio`` times it vertically).
    step_m : resolution [m] of GET_LAST_FEASIBLE along a blocked leg.
    explore : probability that RANDOM_SAMPLE is centred on a uniformly drawn point of the STEP I
        chain instead of the last feasible point (lets other branches grow when the frontier is
        boxed in by a reserved volume; the paper's sampler always uses the last feasible point).
    require_valid_chain : when False, legs of the chain that violate the static bounds do not
        fail the call: the RRT grows around them (the tactical replans of
        :mod:`skyroute.stages.tactical`, whose guiding chain may cross a new obstacle or zone).

    Returns a :class:`Step2Result`; never raises for an unsolvable case (status ``"failed"``
    with the reason), raises :class:`~skyroute.stages.base.InputError` for bad arguments.
    """
    t_start = time.perf_counter()
    w_start = control.work_clock()     # the safety cap's clock (JIT compilation excluded)
    W = np.asarray(step1_waypoints, dtype=float)
    if W.ndim != 2 or W.shape[1] != 3 or W.shape[0] < 2:
        raise InputError(f"step1_waypoints must be a chain of shape (n >= 2, 3) [m]; got {W.shape}")
    if not np.isfinite(W).all():
        raise InputError("step1_waypoints contain NaN or inf")
    if not (np.isfinite(t0_s)):
        raise InputError(f"t0_s = {t0_s} must be finite [s]")
    if not (isinstance(max_iter, (int, np.integer)) and max_iter >= 1):
        raise InputError(f"max_iter = {max_iter} must be an integer >= 1")
    if not (np.isfinite(time_budget_s) and time_budget_s > 0):
        raise InputError(f"time_budget_s = {time_budget_s} s must be > 0: STEP II needs time to build its tree")
    if not (sigma_m > 0 and step_m > 0 and vertical_ratio >= 0 and 0 <= explore <= 1):
        raise InputError("sigma_m and step_m must be > 0 [m], vertical_ratio >= 0, 0 <= explore <= 1")
    if occupancy is not None and not isinstance(occupancy, TrafficOccupancy):
        raise InputError(f"occupancy must be a TrafficOccupancy or None, got {type(occupancy).__name__}")
    # drop repeated points (zero-length legs)
    keep = np.r_[True, np.linalg.norm(np.diff(W, axis=0), axis=1) > 1e-9]
    W = W[keep]
    if W.shape[0] < 2:
        raise InputError("step1_waypoints: start and goal coincide")
    veh = problem.vehicle
    battery = float(veh.battery_energy_j)
    notes: list[str] = []
    if occupancy is not None and occupancy.caps.shape[0] and t0_s < occupancy.t0_s:
        raise InputError(f"t0_s = {t0_s} s is before the occupancy maps start ({occupancy.t0_s} s)")

    # STEP I chain timing; bounds of its legs
    times, energy, valid = chain_timing(problem, W, t0_s)
    if not valid.all() and not require_valid_chain:
        times = t0_s + np.zeros(W.shape[0])
        conf = np.ones(W.shape[0] - 1, bool)      # grow the RRT around the invalid legs
    elif not valid.all():
        i = int(np.argmin(valid))
        why = problem.explain_motion(W[i], W[i + 1]) if hasattr(problem, "explain_motion") else "invalid"
        return _failed(f"STEP I leg {i} ({W[i].round(1).tolist()} -> {W[i + 1].round(1).tolist()}) violates the "
                       f"bounds ({why}); STEP II only resolves traffic conflicts", t_start=t_start)
    else:
        if occupancy is not None and occupancy.caps.shape[0] and times[-1] > occupancy.t0_s + occupancy.t_total_s:
            notes.append(f"the chain ends at t = {times[-1]:.1f} s, after the occupancy horizon "
                         f"{occupancy.t0_s + occupancy.t_total_s:.1f} s: later traffic is unknown")
        conf = chain_conflicts(occupancy, W, times)
    if not conf.any():
        if energy[-1] > battery:
            return _failed(f"the STEP I chain needs {energy[-1] / 3600:.1f} Wh, more than the battery "
                           f"{battery / 3600:.1f} Wh (energy infeasible)", t_start=t_start)
        return Step2Result(W, times, energy, STATUS_UNCHANGED, "STEP I chain is conflict-free", 0, 0,
                           time.perf_counter() - t_start, tuple(notes))

    # ---------------------------------------------------------------- Algorithm 1
    rng = np.random.default_rng(seed)
    feas = _Feasibility(problem, occupancy, battery)
    for i in np.flatnonzero(~conf):                # the chain's free legs (more traffic would change conf)
        feas.free.append((*map(float, W[i]), float(times[i]), *map(float, W[i + 1]), float(times[i + 1])))
    tree = _Tree(W[0], t0_s)
    in_tree = np.zeros(W.shape[0], bool)       # W / Gamma_p bookkeeping
    in_tree[0] = True
    node_of_w = {0: 0}
    goal = W.shape[0] - 1
    sig = np.array([sigma_m, sigma_m, sigma_m * vertical_ratio])

    next_cache = [-1, goal]                        # (tree size, answer): in_tree changes with the tree

    def next_point() -> int:
        if next_cache[0] != tree.n:
            next_cache[0], next_cache[1] = tree.n, _next_point()
        return next_cache[1]

    def _next_point() -> int:                      # GET_NEXT_POINT, eq. 14
        ng = tree.p[tree.nearest(W[goal])]
        d = W[goal] - ng
        dd = float(d @ d)
        for i in np.nonzero(~in_tree)[0]:
            s = float(d @ (W[i] - ng)) / dd if dd > 0 else 1.0
            if 0.0 < s <= 1.0:
                return int(i)
        return goal

    def last_feasible(a: int, q) -> np.ndarray:    # GET_LAST_FEASIBLE
        pa = tree.p[a]
        L = float(np.linalg.norm(q - pa))
        n = max(int(np.ceil(L / step_m)), 1)
        best = pa
        for k in range(1, n + 1):
            x = pa + (q - pa) * (k / n)
            ok, _, _ = feas.leg(tree, a, x)
            if not ok:
                break
            best = x
        return best

    seg_len = np.linalg.norm(np.diff(W, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])

    def chain_point(u: float) -> np.ndarray:     # point at fraction u of the chain length
        s = u * cum[-1]
        i = min(int(np.searchsorted(cum, s, side="right")) - 1, W.shape[0] - 2)
        return W[i] + (W[i + 1] - W[i]) * ((s - cum[i]) / seg_len[i])

    def insert(x, near: int, tau: float, e: float, w_index: int | None) -> int:
        # GET_CONNECTING_POINT: try the parent of the nearest node first
        par = int(tree.parent[near])
        a, ta, ea = near, tau, e
        if par >= 0:
            ok, tp, ep = feas.leg(tree, par, x)
            if ok:
                a, ta, ea = par, tp, ep
        i = tree.add(x, tree.t[a] + ta, tree.e[a] + ea, a)
        if w_index is not None:
            in_tree[w_index] = True
            node_of_w[w_index] = i
        return i

    iterations = 0
    fails = 0
    goal_node = -1
    capped = False
    for k in range(1, max_iter + 1):
        if (k & 63) == 0:
            control.check()
            if control.work_clock() - w_start > time_budget_s:
                capped = True
                control.note_clock_stop()
                break
        iterations = k
        wn = next_point()
        near = feas.memo(("near", tree.n, wn), tree.nearest, W[wn])
        ok, tau, e = feas.leg_w(tree, near, wn, W[wn])
        x_w, w_idx = None, None
        if ok:
            x_w, w_idx = W[wn], wn
        else:
            if rng.random() < explore:             # exploration: anywhere along the STEP I chain
                xc = chain_point(rng.random())
            else:                                  # nodes and W never change: memoised
                xc = feas.memo(("last", near, wn), last_feasible, near, W[wn])
            grow = min(1.0 + fails / 25.0, 4.0)    # widen the search while stuck
            xr = xc + rng.normal(0.0, 1.0, 3) * sig * grow
            near = tree.nearest(xr)
            ok, tau, e = feas.leg(tree, near, xr)
            if ok:
                x_w = xr
        if x_w is None:
            fails += 1
            continue
        fails = 0
        i = insert(x_w, near, tau, e, w_idx)
        if w_idx == goal:
            goal_node = i
            break
        nxt = min(wn + 1, goal)                     # w_{n+}: the point after w_n in W
        ok, tau, e = feas.leg_w(tree, i, nxt, W[nxt])
        if ok:
            j = tree.add(W[nxt], tree.t[i] + tau, tree.e[i] + e, i)
            in_tree[nxt] = True
            node_of_w[nxt] = j
            if nxt == goal:
                goal_node = j
                break
    elapsed = time.perf_counter() - t_start
    if goal_node < 0:
        why = (f"its wall-clock cap of {time_budget_s:g} s before its {max_iter} iterations (a result that "
               "depends on the machine's load)" if capped else f"its {max_iter} iterations")
        rej = ", ".join(f"{n} {v}" for n, v in feas.rejects.items() if v)
        return _failed(f"STEP II reached {why} ({iterations} iterations, {elapsed:.2f} s, {tree.n} nodes) "
                       f"without reaching the goal; rejected legs: {rej or 'none'}", iterations, tree.n, t_start,
                       None if capped else feas.free_legs())
    idx = tree.path(goal_node)
    wp, tt, ee = tree.p[idx].copy(), tree.t[idx].copy(), tree.e[idx].copy()
    return Step2Result(wp, tt, ee, STATUS_DECONFLICTED,
                       f"{int(conf.sum())} conflicting STEP I leg(s) resolved by the RRT", iterations, tree.n, elapsed,
                       tuple(notes), None if capped else feas.free_legs())
