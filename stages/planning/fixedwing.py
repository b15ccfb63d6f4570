"""Fixed-wing lattice planners (seed 002, Aiello et al.): ``eeastar``, ``astar-fw``, ``energy-optimal``.

The lattice (:func:`make_fw_lattice`) is 3-D and heading-aware, over the terrain of a
:class:`~skyroute.stages.planning.problem.PlanningProblem` (its floor -- clearance, minimum AGL,
GNSS coverage, no-fly -- and ceiling are the same as for the rotorcraft planners):

* horizontal: a grid rotated onto the start -> goal line, start and goal both nodes; step
  ``du = D / round(D / s)`` along the line and ``dv = s`` across it (``s = step_cells`` x the
  raster cell), inside a corridor of ``corridor_m`` around the line;
* vertical: levels ``z_start + k dz`` (``dz`` adjusted so that the goal altitude is a level
  when it differs from the start by at least half a step; otherwise the loiter at the goal
  absorbs the difference);
* moves: 8 headings; from a node the aircraft keeps its heading or turns by one heading
  (about 45 deg) if a fillet of the ground-frame turn radius ``R = (V_air,max + |w|max)^2 /
  (g tan(bank_max))`` fits in half of each leg (``R tan(dpsi/2) <= L/2``); climbs and descents
  by whole levels within the climb / descent angle limits divided by the fillet factor
  ``2 tan(dpsi/2) / dpsi`` (so the arcs, which are shorter than the corner, keep the limit);
  every straight motion is checked exactly against the rasters
  (:func:`~skyroute.stages.planning.kernels.segment_eval`) and by the wind triangle
  (:mod:`skyroute.stages.fixedwing_energy`: the aircraft must make progress along it).

Searches (compiled, :mod:`skyroute.stages.planning.fw_kernels`): ``astar-fw`` minimises the 3-D
length (the plain A* of seed 002's comparison; heuristic: the 8-connected lattice distance);
``eeastar`` is seed 002 Algorithm 2: A* on the seed-002 energy of the path with the admissible,
consistent heuristic ``drag_lb * lattice distance + m g max(z_goal - z, 0)``
(:func:`~skyroute.stages.fixedwing_energy.drag_energy_lb_j_per_m`), in which a node reached by a
climb is, the first time it is taken from OPEN, put back with its f raised by the energy of
that climb (the auxArray step) and closed nodes are not reopened -- so it may miss the optimum;
``energy-optimal`` is the same A* without the deferral: the exact minimum-energy path of the
lattice (a lower bound for both).

The written plan (:func:`fixedwing_candidate`) is the lattice path with a horizontal circular
fillet of radius ``R`` at every heading change (altitude linear along the arc), timed by the
wind triangle at the flown airspeed, then one **loiter** turn: a right-hand circle of radius
``R`` tangent to the last course, flown once, ending at the goal (a fixed-wing aircraft
cannot hover; the left-hand circle is used when the right one leaves the admissible
airspace); the helix absorbs the altitude difference between the last node and the goal, if
any.  ``energy_J`` of the candidate is the seed-002 energy of the lattice path (the quantity
``energy-optimal`` minimises; turns neglected as in the seed, which is what the fillets cut:
at most ``(2 tan(dpsi/2) - dpsi) R`` of track per turn); the loiter's energy is reported in
``info["loiter_energy_J"]``, not included.

**f is the same for every planner** (rotorcraft and fixed-wing): seed 000 eq. 11 / 15 with the
scenario's weights on the written trajectory (fillets and loiter included), by the one
implementation :func:`~skyroute.stages.planning.step3.trajectory_costs`: ``C_l`` its length,
``C_r`` / ``C_d`` the time-averaged risk / landing maps times ``C_l``, ``C_e`` the time-averaged
``beta_e`` times ``C_l`` with ``beta_e`` = seed-002 energy of each chord in the wind over in
still air (:func:`chord_energy_ratio`, eq. 12's ratio).  What each planner minimised is
``search_cost_m`` (:func:`search_objective`): the energy as still-air level distance
``E / (W (D/L)_min)`` [m] for ``eeastar`` / ``energy-optimal``, the lattice length for
``astar-fw``, the curve length for ``bitstar-dubins``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from skyroute.stages import control
from skyroute.stages.atmosphere import isa_density_kgpm3
from skyroute.stages.base import InputError
from skyroute.stages.fixedwing_energy import (
    airspeed_kernel,
    drag_energy_lb_j_per_m,
    fixedwing_params,
    ground_speed_kernel,
)
from skyroute.stages.planning.fw_kernels import (
    MODE_DISTANCE,
    MODE_EEASTAR,
    MODE_OPTIMAL,
    FwLattice,
    FwSearch,
    edge_energy,
    search_kernel,
)
from skyroute.stages.planning.kernels import WindParams
from skyroute.stages.planning.kinds import FIXED_WING_PLANNERS, check_planner_vehicle
from skyroute.stages.planning.problem import PlanningProblem
from skyroute.stages.planning.step3 import (
    Candidate,
    empty_candidate,
    trajectory_costs,
    wind_sampler,
)
from skyroute.stages.planning.validate import validate_plan
from skyroute.stages.sky_visibility import navigation_along
from skyroute.stages.vehicle import G0, FixedWingProfile, load_vehicle

_MODES = {"astar-fw": MODE_DISTANCE, "eeastar": MODE_EEASTAR, "energy-optimal": MODE_OPTIMAL}
FW_STEP_CELLS = 4          # default horizontal lattice step [cells]
FW_DZ_M = 20.0             # default vertical lattice step [m]
_DIRS = np.array([(1, 0), (1, 1), (0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1)], dtype=np.int64)


@dataclass
class FwPlanResult:
    """One fixed-wing search: ``waypoints`` (k, 3) [m] (the lattice path; None without one),
    ``energy_J`` (seed 002, the path), ``length_m`` (3-D), ``time_s`` (wind triangle),
    ``expanded`` nodes, ``compute_s`` [s], ``status`` ("solved" / "no_solution"), ``reason``,
    ``info`` (lattice sizes, turn radius, ...)."""

    waypoints: np.ndarray | None
    energy_J: float
    length_m: float
    time_s: float
    expanded: int
    compute_s: float
    status: str
    reason: str = ""
    planner: str = ""
    info: dict = field(default_factory=dict)

    @property
    def solved(self) -> bool:
        return self.status == "solved"


def _vehicle(problem: PlanningProblem) -> FixedWingProfile:
    veh = load_vehicle(problem.vehicle)
    if not isinstance(veh, FixedWingProfile):
        raise InputError(f"vehicle {veh.name!r} is a {veh.kind}: the fixed-wing planners ({', '.join(FIXED_WING_PLANNERS)}) "
                         "need a kind: fixed-wing profile (e.g. skywalker-x8)")
    return veh


def max_wind_mps(problem: PlanningProblem) -> float:
    """Largest wind speed of the problem's wind map [m/s]."""
    return float(np.max(np.linalg.norm(np.asarray(problem.wind_uvw, float).reshape(-1, 3), axis=1)))


def turn_radius_m(problem: PlanningProblem, z_max_m: float) -> float:
    """Ground-frame fillet radius ``(V_air,max + |w|max)^2 / (g tan(bank_max))`` [m] (V_air,max:
    the flown airspeed at ``z_max_m``, where the air is thinnest)."""
    veh = _vehicle(problem)
    v = float(airspeed_kernel(isa_density_kgpm3(float(z_max_m)), fixedwing_params(veh)))
    return (v + max_wind_mps(problem)) ** 2 / (G0 * math.tan(math.radians(veh.max_bank_deg)))


def make_fw_lattice(problem: PlanningProblem, step_cells: int = FW_STEP_CELLS, dz_m: float = FW_DZ_M,
                    corridor_m: float | None = None) -> tuple[FwLattice, dict]:
    """The heading-aware lattice (module docstring) and its description (``du_m``, ``dv_m``,
    ``dz_m``, ``turn_radius_m``, ``goal_k``, ``e_u``, ``e_v``, ``states``).  ``corridor_m``
    [m]: margin around the start -> goal segment (default ``max(1500, 0.4 D)``)."""
    veh = _vehicle(problem)
    if int(step_cells) < 1 or not dz_m > 0:
        raise InputError(f"step_cells {step_cells} must be >= 1 and dz_m {dz_m} > 0 [m]")
    g = problem.grid
    sx, sy, sz = problem.start_xyz
    gx, gy, gz = problem.goal_xyz
    dist = math.hypot(gx - sx, gy - sy)
    s0 = float(step_cells) * g.resolution_m
    if dist < 2 * s0:
        raise InputError(f"start and goal are {dist:.0f} m apart: the fixed-wing lattice (step {s0:g} m) needs at "
                         f"least {2 * s0:g} m; lower planner.step_cells")
    n = max(1, round(dist / s0))
    du, dv = dist / n, s0
    eu = np.array([(gx - sx) / dist, (gy - sy) / dist])
    ev = np.array([-eu[1], eu[0]])
    corr = max(1500.0, 0.4 * dist) if corridor_m is None else float(corridor_m)
    mi = int(math.ceil(corr / du))
    mj = int(math.ceil(corr / dv))
    ii = np.arange(-mi, n + mi + 1)
    jj = np.arange(-mj, mj + 1)
    ig, jg = np.meshgrid(ii, jj, indexing="ij")
    cx = sx + ig.ravel() * du * eu[0] + jg.ravel() * dv * ev[0]
    cy = sy + ig.ravel() * du * eu[1] + jg.ravel() * dv * ev[1]
    # vertical levels
    dzz = float(dz_m)
    nlev = round(abs(gz - sz) / dzz)
    if nlev >= 1:
        dzz = abs(gz - sz) / nlev
        goal_k = int(np.sign(gz - sz)) * nlev
    else:
        goal_k = 0
    r, c = g.index_of(cx, cy)
    inside = (r >= 0) & (r < g.ny) & (c >= 0) & (c < g.nx)
    rr, cc = np.clip(r, 0, g.ny - 1), np.clip(c, 0, g.nx - 1)
    fl = np.where(inside, problem.floor_m[rr, cc], np.inf)
    ce = np.where(inside, problem.ceiling_m[rr, cc], -np.inf)
    ok = np.isfinite(fl) & (ce >= fl)
    k_lo = np.where(ok, np.ceil((fl - sz) / dzz - 1e-9), 0).astype(np.int64)
    k_hi = np.where(ok, np.floor((ce - sz) / dzz + 1e-9), -1).astype(np.int64)
    k_n = np.where(ok, np.maximum(k_hi - k_lo + 1, 0), 0).astype(np.int64)
    kb = int(max(1, k_n.max(initial=1)))
    z_top = sz + dzz * float(np.max(np.where(k_n > 0, k_hi, 0), initial=0))
    radius = turn_radius_m(problem, max(z_top, sz, gz))
    # moves, turns, climb limits
    vec = _DIRS * np.array([du, dv])
    hlen = np.hypot(vec[:, 0], vec[:, 1])
    psi = np.arctan2(vec[:, 1], vec[:, 0])
    turn_ok = np.zeros((8, 8), dtype=np.bool_)
    kappa = 1.0
    for h in range(8):
        for dh in (-1, 0, 1):
            h2 = (h + dh) % 8
            dpsi = abs((psi[h2] - psi[h] + math.pi) % (2 * math.pi) - math.pi)
            if dpsi < 1e-12 or radius * math.tan(dpsi / 2) <= min(hlen[h], hlen[h2]) / 2:
                turn_ok[h, h2] = True
                if dpsi > 1e-12:
                    kappa = max(kappa, 2 * math.tan(dpsi / 2) / dpsi)
    if not turn_ok[~np.eye(8, dtype=bool)].any():
        need = int(math.ceil(2 * radius * math.tan(math.pi / 8) / g.resolution_m / 0.999))
        raise InputError(f"fixed-wing lattice step {min(du, dv):.0f} m is too short for turns of radius {radius:.0f} m "
                         f"(fillet needs {2 * radius * math.tan(math.pi / 8):.0f} m per leg): use planner.step_cells "
                         f">= {max(need, int(step_cells) + 1)}")
    tan_up = math.tan(math.radians(veh.max_climb_angle_deg)) / kappa
    tan_dn = math.tan(math.radians(veh.max_descent_angle_deg)) / kappa
    dk_up = np.floor(hlen * tan_up / dzz + 1e-9).astype(np.int64)
    dk_dn = np.floor(hlen * tan_dn / dzz + 1e-9).astype(np.int64)
    lat = FwLattice(np.ascontiguousarray(cx), np.ascontiguousarray(cy), k_lo, k_n, int(ii.size), int(jj.size), kb,
                    float(sz), float(dzz), _DIRS.copy(), hlen, turn_ok, dk_up, dk_dn)
    desc = {"du_m": du, "dv_m": dv, "dz_m": dzz, "turn_radius_m": radius, "goal_k": goal_k, "mi": mi, "mj": mj,
            "n_u": n, "e_u": eu, "e_v": ev, "states": int(ii.size * jj.size * kb * 8), "fillet_factor": kappa,
            "corridor_m": corr}
    return lat, desc


def wind_step_m(problem: PlanningProblem) -> float:
    """Wind sampling step along an edge [m]: ``problem.subsegment_m``, or one piece per edge
    (1e12) when the wind map holds one vector everywhere."""
    w = np.asarray(problem.wind_uvw, float).reshape(-1, 3)
    return 1e12 if np.all(w == w[0]) else float(problem.subsegment_m)


def path_energy(problem: PlanningProblem, waypoints) -> dict[str, float]:
    """Seed-002 totals along a polygonal chain (k, 3) [m]: ``energy_J``, ``drag_J``,
    ``potential_J``, ``speed_change_J``, ``time_s``, ``length_m`` (3-D); wind sampled as the
    planners do (start of every sub-segment of :func:`wind_step_m`)."""
    veh = _vehicle(problem)
    prm = fixedwing_params(veh)
    w = np.asarray(waypoints, float)
    maps, wind = problem.seg_args[0], problem.seg_args[1]
    tot = np.zeros(5)
    out = np.empty(5)
    step = wind_step_m(problem)          # once: it scans the whole wind map
    for a, b in zip(w[:-1], w[1:], strict=True):
        edge_energy(float(a[0]), float(a[1]), float(a[2]), float(b[0]), float(b[1]), float(b[2]),
                    step, maps, wind, prm, out)
        tot += out
    length = float(np.linalg.norm(np.diff(w, axis=0), axis=1).sum()) if len(w) > 1 else 0.0
    return {"energy_J": float(tot[0]), "time_s": float(tot[1]), "drag_J": float(tot[2]),
            "potential_J": float(tot[3]), "speed_change_J": float(tot[4]), "length_m": length}


def chord_energy_ratio(problem: PlanningProblem, pts) -> np.ndarray:
    """``beta_e`` of seed 000 eq. 12 per chord of the samples ``pts`` (m, 3) [m]: the seed-002
    energy of the chord in the problem's wind over its energy in still air (same chord, same
    flown airspeed; wind sampled as :func:`path_energy` does) [-], (m - 1,); 1 for a chord of
    zero length, inf where the aircraft cannot fly the chord against the wind."""
    prm = fixedwing_params(_vehicle(problem))
    w = np.asarray(pts, float)
    maps, wind = problem.seg_args[0], problem.seg_args[1]
    calm = WindParams(np.zeros_like(wind.uvw_mps), wind.z_agl_m, wind.grid)
    step = wind_step_m(problem)
    out_w, out_0 = np.empty(5), np.empty(5)
    ratio = np.ones(max(len(w) - 1, 0))
    for i, (a, b) in enumerate(zip(w[:-1], w[1:], strict=True)):
        args = (float(a[0]), float(a[1]), float(a[2]), float(b[0]), float(b[1]), float(b[2]), step, maps)
        edge_energy(*args, wind, prm, out_w)
        edge_energy(*args, calm, prm, out_0)
        if out_0[0] > 0:
            ratio[i] = out_w[0] / out_0[0]
    return ratio


_SEARCH_OBJECTIVES = {
    "eeastar": "EEA* (seed 002 Algorithm 2) objective: the seed-002 energy of the lattice path / (W (D/L)_min), "
               "as still-air level distance [m]",
    "energy-optimal": "the seed-002 energy of the lattice path / (W (D/L)_min) (its exact minimum over the lattice), "
                      "as still-air level distance [m]",
    "astar-fw": "3-D length of the lattice path (before fillets and loiter) [m]",
    "bitstar-dubins": "length of the Dubins-airplane curve (BIT*'s objective, before the loiter) [m]",
}


def search_objective(result: FwPlanResult, vehicle: FixedWingProfile) -> tuple[float, str]:
    """The search objective of ``result``'s planner (``search_cost_m`` [m], its definition): the
    quantity the planner minimised, which is not f (eq. 11 on the written trajectory)."""
    if result.planner in ("eeastar", "energy-optimal"):
        return float(result.energy_J) / (vehicle.weight_n * vehicle.min_drag_to_lift), _SEARCH_OBJECTIVES[result.planner]
    return float(result.length_m), _SEARCH_OBJECTIVES.get(result.planner, "path length [m]")


def plan_fixedwing(problem: PlanningProblem, planner: str = "eeastar", *, step_cells: int = FW_STEP_CELLS,
                   dz_m: float = FW_DZ_M, corridor_m: float | None = None, max_expansions: int = 20_000_000,
                   time_limit_s: float | None = None) -> FwPlanResult:
    """Search the fixed-wing lattice with ``planner`` (one of :data:`FIXED_WING_PLANNERS`).

    Returns a :class:`FwPlanResult`; ``status`` "no_solution" with the reason when the start
    or the goal is not a valid state or no lattice path exists.  ``time_limit_s`` [s]: wall
    clock cap of the search (then no path, ``info["stopped_by"] == "time"``)."""
    if planner not in _MODES:
        raise InputError(f"unknown fixed-wing planner {planner!r}; known: {', '.join(FIXED_WING_PLANNERS)}")
    t0 = time.perf_counter()
    veh = _vehicle(problem)
    why = problem.endpoint_problem()
    if why:
        return FwPlanResult(None, math.nan, math.nan, math.nan, 0, time.perf_counter() - t0, "no_solution", why, planner)
    lat, desc = make_fw_lattice(problem, step_cells, dz_m, corridor_m)
    sz, gz = problem.start_xyz[2], problem.goal_xyz[2]
    start_col = desc["mi"] * lat.nj + desc["mj"]
    goal_i, goal_j, goal_k = desc["mi"] + desc["n_u"], desc["mj"], desc["goal_k"]
    goal_col = goal_i * lat.nj + goal_j
    for name, col, k in (("start", start_col, 0), ("goal", goal_col, goal_k)):
        if not (lat.k_n[col] > 0 and lat.k_lo[col] <= k < lat.k_lo[col] + lat.k_n[col]):
            zk = sz + k * lat.dz_m
            return FwPlanResult(None, math.nan, math.nan, math.nan, 0, time.perf_counter() - t0, "no_solution",
                                f"{problem.label}: the {name} lattice level z = {zk:.1f} m is outside the admissible "
                                f"altitudes of its column (lattice dz {lat.dz_m:.1f} m)", planner, desc)
    prm = fixedwing_params(veh)
    z_lo = sz + lat.dz_m * float(np.min(np.where(lat.k_n > 0, lat.k_lo, 0)))
    z_hi = max(z_lo, sz, gz) + lat.dz_m * lat.kb
    lb = drag_energy_lb_j_per_m(veh, max_wind_mps(problem), max(z_lo, -400.0), z_hi)
    v_lo, v_hi = (float(airspeed_kernel(isa_density_kgpm3(float(z)), prm)) for z in (max(z_lo, -400.0), z_hi))
    wvec = np.asarray(problem.wind_uvw, float).reshape(-1, 3)
    gauge = bool(np.all(wvec == wvec[0]) and wvec[0, 2] == 0.0)
    srch = FwSearch(_MODES[planner], int(start_col), 0, int(goal_i), int(goal_j), int(goal_k), float(desc["du_m"]),
                    float(desc["dv_m"]), float(lb), float(veh.weight_n), wind_step_m(problem),
                    int(max_expansions), (float(desc["e_u"][0]), float(desc["e_u"][1])),
                    (float(desc["e_v"][0]), float(desc["e_v"][1])), (float(wvec[0, 0]), float(wvec[0, 1])), gauge,
                    min(v_lo, v_hi) * (1 - 1e-9), max(v_lo, v_hi) * (1 + 1e-9),
                    float(veh.weight_n * veh.min_drag_to_lift))
    # validity: one wind check per edge when the wind is the same everywhere (exact then)
    vprob = dataclasses.replace(problem, subsegment_m=1e12) if wind_step_m(problem) > 1e11 else problem
    maps, wind, vparams, power = vprob.seg_args
    with control.StopFlag(time_limit_s) as stop:
        found, parent, _g, expanded = search_kernel(lat, srch, stop.array, maps, wind, vparams, power, prm)
        stop.check()
        stopped = "time" if stop.expired and found < 0 else ""
    desc["stopped_by"] = stopped or "completed"
    desc["drag_lb_j_per_m"] = lb
    if found < 0:
        why = (f"{problem.label}: {planner} stopped at its wall-clock cap of {time_limit_s:g} s" if stopped else
               f"{problem.label}: {planner} searched the lattice ({expanded} nodes expanded): no path within the "
               "altitude bounds, no-fly zones, climb/descent angles, turn radius and wind")
        return FwPlanResult(None, math.nan, math.nan, math.nan, int(expanded), time.perf_counter() - t0,
                            "no_solution", why, planner, desc)
    states = []
    s = int(found)
    while s >= 0:
        states.append(s)
        s = int(parent[s])
    states = np.array(states[::-1], dtype=np.int64)
    col = (states // 8) // lat.kb
    k = lat.k_lo[col] + (states // 8) % lat.kb
    wp = np.column_stack([lat.col_x[col], lat.col_y[col], sz + k * lat.dz_m])
    wp[0] = problem.start_xyz
    if goal_k * lat.dz_m == gz - sz or abs(wp[-1, 2] - gz) < 1e-6:
        wp[-1] = problem.goal_xyz
    else:
        wp[-1, :2] = problem.goal_xyz[:2]
    pe = path_energy(problem, wp)
    desc["headings"] = (states % 8).tolist()
    return FwPlanResult(wp, pe["energy_J"], pe["length_m"], pe["time_s"], int(expanded), time.perf_counter() - t0,
                        "solved", "", planner, {**desc, **pe})


def _arc_pts(center, r0, sign, dpsi, z0, z1, step_rad):
    """Points of a horizontal arc around ``center`` starting at radius vector ``r0``, turning
    ``sign * dpsi`` (sign +1 left / counter-clockwise), altitude linear from z0 to z1."""
    n = max(2, int(math.ceil(dpsi / step_rad)) + 1)
    a = np.linspace(0.0, dpsi, n) * sign
    ca, sa = np.cos(a), np.sin(a)
    x = center[0] + r0[0] * ca - r0[1] * sa
    y = center[1] + r0[0] * sa + r0[1] * ca
    return np.column_stack([x, y, np.linspace(z0, z1, n)])


def _line_pts(a, b, spacing):
    n = max(1, int(math.ceil(np.linalg.norm(b[:2] - a[:2]) / spacing)))
    f = np.linspace(0.0, 1.0, n + 1)[:, None]
    return a + (b - a) * f


def fillet_path(waypoints, radius_m: float, spacing_m: float, arc_step_deg: float = 3.0) -> np.ndarray:
    """Samples (m, 3) of the chain with a horizontal circular fillet of ``radius_m`` [m] at every
    heading change (tangent length ``R tan(dpsi/2)``, which must fit in half of each leg),
    altitude linear along each arc; straight parts sampled every ``spacing_m`` [m] or closer."""
    w = np.asarray(waypoints, float)
    pts = [w[:1]]
    cur = w[0]
    step = math.radians(arc_step_deg)
    for i in range(1, len(w) - 1):
        a, b = w[i] - w[i - 1], w[i + 1] - w[i]
        ha, hb = np.hypot(*a[:2]), np.hypot(*b[:2])
        ua, ub = a[:2] / ha, b[:2] / hb
        cross = ua[0] * ub[1] - ua[1] * ub[0]
        dpsi = math.atan2(abs(cross), float(ua @ ub))
        if dpsi < 1e-9:              # straight on (maybe a change of slope): keep the vertex
            pts.append(_line_pts(cur, w[i], spacing_m)[1:])
            cur = w[i]
            continue
        t = radius_m * math.tan(dpsi / 2)
        if t > min(ha, hb) / 2 + 1e-9:
            raise InputError(f"turn of {math.degrees(dpsi):.0f} deg at waypoint {i} needs legs of {2 * t:.0f} m")
        p1 = np.r_[w[i, :2] - ua * t, w[i, 2] - a[2] * t / ha]
        p2 = np.r_[w[i, :2] + ub * t, w[i, 2] + b[2] * t / hb]
        sign = 1.0 if cross > 0 else -1.0
        normal = np.array([-ua[1], ua[0]]) * sign
        center = p1[:2] + normal * radius_m
        pts.append(_line_pts(cur, p1, spacing_m)[1:])
        pts.append(_arc_pts(center, p1[:2] - center, sign, dpsi, p1[2], p2[2], step)[1:])
        cur = p2
    pts.append(_line_pts(cur, w[-1], spacing_m)[1:])
    return np.vstack(pts)


def loiter_circle(end_xyz, course_xy, radius_m: float, z_end_m: float, right: bool = True,
                  arc_step_deg: float = 3.0) -> np.ndarray:
    """One full turn (m, 3) of radius ``radius_m`` [m] tangent to the unit ``course_xy`` at
    ``end_xyz``, to the right (clockwise) or left, altitude linear to ``z_end_m``; it starts
    after ``end_xyz`` and ends at ``(end_xyz[:2], z_end_m)``."""
    u = np.asarray(course_xy, float) / np.hypot(*course_xy)
    sign = -1.0 if right else 1.0
    normal = np.array([-u[1], u[0]]) * sign
    center = np.asarray(end_xyz[:2], float) + normal * radius_m
    pts = _arc_pts(center, np.asarray(end_xyz[:2], float) - center, sign, 2 * math.pi, float(end_xyz[2]),
                   float(z_end_m), math.radians(arc_step_deg))
    pts[-1, :2] = end_xyz[:2]
    return pts[1:]


def _timing(problem: PlanningProblem, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Times [s] of the samples (chord by chord: wind triangle at the flown airspeed with the
    wind at the chord's start) and the airspeed per chord [m/s]."""
    prm = fixedwing_params(_vehicle(problem))
    wind = wind_sampler(problem)(pts[:-1])
    d = np.diff(pts, axis=0)
    length = np.linalg.norm(d, axis=1)
    rho = 0.5 * (isa_density_kgpm3(pts[:-1, 2]) + isa_density_kgpm3(pts[1:, 2]))
    va = np.array([airspeed_kernel(float(r), prm) for r in np.atleast_1d(rho)])
    gs = np.array([ground_speed_kernel(*(d[i] / length[i]), *wind[i], va[i]) if length[i] > 0 else va[i]
                   for i in range(len(d))])
    if not np.isfinite(gs).all():
        raise InputError("the written path has a chord the aircraft cannot fly against the wind")
    return np.r_[0.0, np.cumsum(length / gs)], va


def fixedwing_candidate(problem: PlanningProblem, result: FwPlanResult, *, label: str = "",
                        dop_threshold: float | None = None, intruders=(), d_c_m: float = 0.0, dt_c_s: float = 0.0,
                        battery_reserve_pct: float = 0.0, sky=None, surface_2d=None, start_time_utc=None,
                        gnss_sigma_m: float = 3.0) -> Candidate:
    """The written plan of a solved search (module docstring: fillets, loiter, wind-triangle
    timing), its costs and the independent validation (rasters, climb / descent angles, turn
    radius, wind, traffic, battery; and the straight chords between the waypoints, the legs of the
    QGroundControl mission, as exact motions).  ``C_l`` .. ``C_e`` and ``f``: eq. 11 / 15 on the
    written trajectory (module docstring), ``search_cost_m``: the planner's own objective.  With ``sky`` (satellite geometry) and
    ``surface_2d`` (surface heights on the grid, for occlusions) the navigation error along the
    samples is computed as for the rotorcraft
    (:func:`~skyroute.stages.planning.step3.navigation_along`) and must stay <= dp_max;
    without, it is not evaluated (NaN)."""
    t_start = time.perf_counter()
    lab = label or problem.label
    if not result.solved:
        return empty_candidate(lab, dop_threshold, [f"STEP I: {result.reason}"], t_start, result.status)
    veh = _vehicle(problem)
    info = result.info
    radius = float(info["turn_radius_m"])
    wp = result.waypoints
    spacing = 0.5 * problem.grid.resolution_m
    path = np.asarray(wp, float) if info.get("continuous") else fillet_path(wp, radius, spacing)
    last = wp[-1] - wp[-2]
    reasons: list[str] = []
    loiter = None
    for right in (True, False):
        lo = loiter_circle(path[-1], last[:2], radius, problem.goal_xyz[2], right=right)
        if problem.state_valid(lo).all():
            loiter = lo
            break
    if loiter is None:
        loiter = loiter_circle(path[-1], last[:2], radius, problem.goal_xyz[2], right=True)
    pts = np.vstack([path, loiter])
    t, va = _timing(problem, pts)
    n_path = len(path)
    e = float(result.energy_J)
    # f and its terms: eq. 11 / 15 on the written trajectory by the rotorcraft's implementation
    # (step3.trajectory_costs), the same for every planner; the search objective apart
    d = np.diff(pts, axis=0)
    dt = np.diff(t)
    chord_len = np.linalg.norm(d, axis=1)
    chord_speed = np.divide(chord_len, dt, out=np.zeros_like(chord_len), where=dt > 0)
    cell = problem.grid.cell_of(pts[:, 0], pts[:, 1])
    costs = trajectory_costs(problem.weights, t, chord_speed, np.asarray(problem.risk_cost, float)[cell],
                             np.asarray(problem.landing_cost, float)[cell], chord_energy_ratio(problem, pts))
    search_cost, objective = search_objective(result, veh)
    legs_ok = np.asarray(problem.motion_valid(wp[:-1], wp[1:]), bool)    # the QGC mission flies these chords
    if not legs_ok.all():
        k = int(np.argmin(legs_ok))
        reasons.append(f"validation: the straight leg between plan waypoints {k} and {k + 1} (a leg of the "
                       f"QGroundControl mission) is not flyable: {problem.explain_motion(wp[k], wp[k + 1])}")
    lo_e = path_energy(problem, pts[n_path - 1:])
    info["loiter_energy_J"] = lo_e["energy_J"]
    info["loiter_radius_m"] = radius
    agl = pts[:, 2] - problem.terrain_m[problem.grid.cell_of(pts[:, 0], pts[:, 1])]
    speed = np.r_[np.linalg.norm(np.diff(pts, axis=0), axis=1) / np.diff(t), np.nan]
    speed[-1] = speed[-2]
    sigma, nvis = np.full(len(t), np.nan), np.zeros(len(t), int)
    if sky is not None and surface_2d is not None:
        sigma, nvis = navigation_along(problem, sky, surface_2d, t, pts, start_time_utc, veh, gnss_sigma_m=gnss_sigma_m)
        if np.nanmax(sigma) > veh.max_position_error_m:
            k = int(np.nanargmax(sigma))
            reasons.append(f"navigation error sigma_p reaches {float(sigma[k]):.2f} m > dp_max "
                           f"{veh.max_position_error_m} m at t = {t[k]:.1f} s ({int(nvis[k])} satellites in view)")
    max_sigma = float(np.nanmax(sigma)) if np.isfinite(sigma).any() else float("nan")
    cand = Candidate(lab, dop_threshold, t, pts, agl, speed, sigma, nvis, costs["C_l"], costs["C_r"], costs["C_d"],
                     costs["C_e"], costs["f"], False, max_sigma, e, float(t[n_path - 1]), 0.0, reasons,
                     np.asarray(wp, float), np.diff(t[[0, n_path - 1]]), None, "solved",
                     search_cost_m=search_cost, search_objective=objective)
    viol = validate_plan(cand, grid=problem.grid, terrain_m=problem.terrain_m, vehicle=veh, floor_m=problem.floor_m,
                         ceiling_m=problem.ceiling_m, clearance_floor_m=problem.clearance_m,
                         gnss_floor_m=problem.coverage_m, min_agl_m=problem.min_agl_m,
                         max_agl_m=problem.max_agl_m if np.isfinite(problem.max_agl_m) else 1e12,
                         nofly=problem.nofly, wind=wind_sampler(problem), intruders=intruders or (), d_c_m=d_c_m,
                         dt_c_s=dt_c_s, start_xyz=problem.start_xyz, goal_xyz=problem.goal_xyz,
                         battery_reserve_pct=battery_reserve_pct)
    reasons.extend(f"validation: {m}" for m in viol if "navigation error" not in m)
    cand.flyable = not reasons
    cand.dp_max_m = float(veh.max_position_error_m)
    cand.compute_time_s = result.compute_s + time.perf_counter() - t_start
    return cand


__all__ = ["FIXED_WING_PLANNERS", "FW_DZ_M", "FW_STEP_CELLS", "FwPlanResult", "check_planner_vehicle",
           "chord_energy_ratio", "fillet_path", "fixedwing_candidate", "loiter_circle", "make_fw_lattice",
           "max_wind_mps", "path_energy", "plan_fixedwing", "search_objective", "turn_radius_m"]
