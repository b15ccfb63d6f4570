"""STEP III: smooth trajectory, navigation error and final selection (seed 000 section III-C;
seed 001 section 3.1).

For each STEP II chain (one per GNSS coverage level D_j):

1. **Flyable trajectory by construction** (:func:`~skyroute.stages.smoothing.corner_trajectory`).
   The STEP II chain already respects the static bounds and the flight-path angle on every
   leg (STEP I and II check each straight motion exactly).  STEP III keeps it and only rounds
   corners: each vertex becomes a circular arc tangent to both legs when every tangent of the
   arc (a non-negative combination of the two leg directions) is inside the flight-path-angle
   cone (an exact quadratic test) and every cell under the triangle that contains the arc
   admits its altitudes; otherwise the vehicle stops at the vertex (138 deg hairpins, turns
   while climbing at the angle limit).  Time is then optimal along this path under the
   acceleration limit (lines: accelerate / cruise / decelerate; arcs: constant speed with
   ``v^2 / R <= a_max``), the legs' STEP II ground speeds, the airspeed limit for every wind
   that can occur along the chain (|v_ground - wind| <= v_max) and the climb / descent rate
   limits -- closed form, no tolerance.  Why not minimum-snap with midpoint insertion: its
   curve keeps its velocity through a corner, so near a hairpin it climbs at 19-22 deg
   whatever the number of inserted points, and a retiming loop cannot fix the geometry; a
   corridor-constrained QP would need iterated checks.  Here every bound holds on the
   continuous trajectory, and on every chord of the samples (the output samples include each
   piece boundary, so a chord lies on one line -- parallel to its leg -- or on one arc).
   The traffic check is re-done on the retimed trajectory (exact capsule test on chords about
   ``check_spacing_m`` apart), since its times differ from STEP II's.
2. **Navigation error** along the samples (every ``sample_dt_s``): at each sample the
   satellites of the nearest almanac epoch of ``sky`` above the elevation mask are in line of
   sight iff the sample altitude is >= their visibility height in the sample's cell
   (:func:`~skyroute.stages.occlusion.visibility_heights_numpy` once per epoch over the
   bounding box of the path plus the longest possible shadow); the GNSS/INS covariance
   analysis (:func:`~skyroute.stages.navigation.navigation_error`) gives sigma_p(t).  A
   candidate with sigma_p > dp_max anywhere is not flyable.
3. **Costs by time integration** (eq. 15).  The paper prints
   ``f = w_r L + (int beta_r + w_d int beta_d + w_e int beta_e) / (t_f - t_0) L``, an evident
   misprint of eq. 11 with time-averaged integrands; implemented as
   ``C_l = L``, ``C_x = L * (1 / (t_f - t_0)) int beta_x(t) dt`` for x = r, d, e and
   ``f = w_l C_l + w_r C_r + w_d C_d + w_e C_e`` [m].  ``beta_r``, ``beta_d``: risk and
   landing maps at the sample's cell; ``beta_e = P(v - w) / P(v)``: the rotor power
   (:func:`~skyroute.stages.energy.rotor_power`) at the trajectory's ground velocity ``v`` with
   and without the wind ``w`` (same time, so the power ratio is the energy ratio of eq. 12).
   ``L = int |v| dt``; energy ``E = int P(v - w) dt``.  :func:`trajectory_costs` is the one
   implementation of these costs and f: the fixed-wing candidates use it too, on their written
   trajectory, so f means the same for every planner (a planner's own search objective, where
   it differs, is ``Candidate.search_cost_m``).
4. The independent :func:`~skyroute.stages.planning.validate.validate_plan` re-checks the
   samples against the rasters; any violation makes the candidate not flyable.

:func:`choose` picks the flyable candidate with the smallest f.
"""

from __future__ import annotations

import datetime as dt
import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import xarray as xr
from scipy.integrate import trapezoid

from skyroute.stages.base import InputError, PlanningError
from skyroute.stages.energy import rotor_power
from skyroute.stages.navigation import DEFAULT_UERE_M, FilterState, FilterTrack
from skyroute.stages.planning.deconflict import Step2Result, leg_conflicts
from skyroute.stages.planning.validate import validate_bubble, validate_plan
from skyroute.stages.sky_visibility import cells_of as _cells
from skyroute.stages.sky_visibility import line_of_sight, navigation_along
from skyroute.stages.smoothing import CornerTrajectory, KinematicLimits, corner_trajectory
from skyroute.stages.traffic import Intruder, TrafficOccupancy
from skyroute.stages.wind import wind_in_column

__all__ = ["Candidate", "choose", "eq11_f", "explain_no_plan", "flight_power_W", "line_of_sight", "navigation_along",
           "smooth_chain", "step3", "trajectory_costs", "wind_sampler"]


@dataclass
class Candidate:
    """One STEP III candidate D_j: the sampled trajectory and its costs (seed 000 Tables II-III).

    ``t_s`` (m,) [s since mission start], ``xyz_m`` (m, 3) [m, map CRS, surface datum],
    ``alt_agl_m`` (m,), ``speed_mps`` (m,), ``sigma_p_m`` (m,) [m] (NaN without GNSS data),
    ``n_visible`` (m,); costs ``C_l, C_r, C_d, C_e, f`` [m] (eq. 15, :func:`trajectory_costs`,
    the same for every planner); ``flyable`` and every reason it is not in ``reasons``;
    ``search_cost_m`` / ``search_objective``: the planner's own search objective when it is not
    f (NaN / "" otherwise)."""

    label: str
    dop_threshold: float | None
    t_s: np.ndarray
    xyz_m: np.ndarray
    alt_agl_m: np.ndarray
    speed_mps: np.ndarray
    sigma_p_m: np.ndarray
    n_visible: np.ndarray
    C_l: float
    C_r: float
    C_d: float
    C_e: float
    f: float
    flyable: bool
    max_sigma_p_m: float
    energy_J: float
    flight_time_s: float
    compute_time_s: float
    reasons: list[str] = field(default_factory=list)
    waypoints: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    segment_times_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    trajectory: CornerTrajectory | None = None
    step2_status: str = ""
    dp_max_m: float = float("nan")
    clearance_radius_m: float = float("nan")   # r_j of a safety-bubble level (NaN: the fixed r_p)
    nav_track: FilterTrack | None = None       # the navigation filter along t_s (step3 keep_nav_track)
    # the planner's own search objective where it is not f (fixed-wing: EEA*'s energy as level
    # still-air distance, A*-fw's lattice length, BIT*-Dubins' curve length) [m], and what it is
    search_cost_m: float = float("nan")
    search_objective: str = ""

    @property
    def energy_Wh(self) -> float:
        return self.energy_J / 3600.0

    @property
    def costs(self) -> dict[str, float]:
        return {"C_l": self.C_l, "C_r": self.C_r, "C_d": self.C_d, "C_e": self.C_e, "f": self.f}


def empty_candidate(label, dop, reasons, t_start, status="") -> Candidate:
    z = np.zeros(0)
    nan = float("nan")
    return Candidate(label, dop, z, np.zeros((0, 3)), z, z, z, np.zeros(0, int), nan, nan, nan, nan, nan, False,
                     nan, nan, nan, time.perf_counter() - t_start, list(reasons), step2_status=status)


# ------------------------------------------------------------------ costs (eq. 11 / 15)


def eq11_f(weights, C_l: float, C_r: float, C_d: float, C_e: float) -> float:
    """Seed 000 eq. 11: ``f = w_l C_l + w_r C_r + w_d C_d + w_e C_e`` [m] with ``weights`` =
    (w_l, w_r, w_d, w_e) [-] and the costs [m]."""
    wl, wr, wd, we = (float(w) for w in weights)
    return wl * C_l + wr * C_r + wd * C_d + we * C_e


def _time_integral(values, t_s) -> float:
    """Integral over time of ``values``: one per sample (trapezoid rule) or one per chord
    between samples (constant on the chord)."""
    v, t = np.asarray(values, float), np.asarray(t_s, float)
    if v.shape == t.shape:
        return float(trapezoid(v, t))
    if v.shape == (t.size - 1,):
        return float(np.sum(v * np.diff(t)))
    raise InputError(f"{v.size} values for {t.size} samples: give one per sample or one per chord")


def trajectory_costs(weights, t_s, speed_mps, beta_r, beta_d, beta_e) -> dict[str, float]:
    """The costs of a sampled trajectory (seed 000 eq. 15 read as eq. 11 with time-averaged
    integrands, module docstring item 3) and f (eq. 11, :func:`eq11_f`): the one
    implementation every planner's candidate is costed with (rotorcraft: :func:`step3`;
    fixed-wing: :func:`~skyroute.stages.planning.fixedwing.fixedwing_candidate`), so f means
    the same for every planner.

    ``t_s`` (m,) [s]: sample times; ``speed_mps`` [m/s]: ground speed; ``beta_r``, ``beta_d``
    [-]: risk and landing maps; ``beta_e`` [-]: energy per metre with the wind over without
    it.  Each holds one value per sample (trapezoid rule) or one per chord (constant on the
    chord).  Returns ``C_l = L = int |v| dt``, ``C_x = L * (1 / (t_f - t_0)) int beta_x dt``
    for x = r, d, e, and ``f`` [m]."""
    t = np.asarray(t_s, float)
    dur = float(t[-1] - t[0])
    L = _time_integral(speed_mps, t)
    C_r = L * _time_integral(beta_r, t) / dur
    C_d = L * _time_integral(beta_d, t) / dur
    C_e = L * _time_integral(beta_e, t) / dur
    return {"C_l": L, "C_r": C_r, "C_d": C_d, "C_e": C_e, "f": eq11_f(weights, L, C_r, C_d, C_e)}


# ------------------------------------------------------------------ helpers


def wind_sampler(problem):
    """Wind (u, v, w) [m/s] at points (m, 3) on the problem's wind map: nearest wind column,
    linear in height above the terrain of the point's cell, clamped to the lowest/highest
    level (the convention of :mod:`~skyroute.stages.planning.problem`)."""
    w4 = np.asarray(problem.wind_uvw, float)
    if w4.shape == (3,):
        return lambda pts: np.broadcast_to(w4, (np.shape(pts)[0], 3)).copy()
    wz = np.asarray(problem.wind_z_agl_m, float)
    wg = problem.wind_grid or problem.grid
    g = problem.grid
    terrain = problem.terrain_m

    def f(pts):
        p = np.asarray(pts, float).reshape(-1, 3)
        h = p[:, 2] - terrain[g.cell_of(p[:, 0], p[:, 1])]
        wr, wc = wg.cell_of(p[:, 0], p[:, 1])
        return wind_in_column(w4, wz, wr, wc, h)

    return f


def flight_power_W(v_mps, wind_mps, vehicle) -> np.ndarray:
    """Rotor power [W] (m,) of the vehicle flying ground velocities ``v_mps`` (m, 3) in the wind
    ``wind_mps`` (m, 3): the airspeed ``v - wind``, its component along the ground track and
    the climb rate (:func:`~skyroute.stages.energy.rotor_power`; eq. 12 / 15 of seed 000)."""
    v = np.asarray(v_mps, float)
    va = v - np.asarray(wind_mps, float)
    speed = np.linalg.norm(v, axis=1)
    sdir = np.divide(v, speed[:, None], out=np.zeros_like(v), where=speed[:, None] > 1e-9)
    return rotor_power(va, np.einsum("ij,ij->i", va, sdir), v[:, 2], vehicle)["total_W"]


def _wind_vectors(problem, pts) -> np.ndarray:
    """Every wind vector (k, 3) [m/s] of the problem's wind map that can apply inside the
    bounding box of ``pts`` (m, 3): all levels of every wind column whose cell meets the box.
    The wind at any point of the box is one of them or a linear interpolation of two (same
    column, adjacent levels), so a bound that holds for all of them and is convex in the wind
    holds everywhere in the box."""
    w4 = np.asarray(problem.wind_uvw, float)
    if w4.shape == (3,):
        return w4[None, :]
    wg = problem.wind_grid or problem.grid
    p = np.asarray(pts, float).reshape(-1, 3)
    c0, c1 = (np.clip(np.floor((np.array([p[:, 0].min(), p[:, 0].max()]) - wg.x0) / wg.resolution_m).astype(int),
                      0, wg.nx - 1))
    r0, r1 = (np.clip(np.floor((wg.y1 - np.array([p[:, 1].max(), p[:, 1].min()])) / wg.resolution_m).astype(int),
                      0, wg.ny - 1))
    return w4[:, r0:r1 + 1, c0:c1 + 1, :].reshape(-1, 3)


def _fillet_checker(problem):
    """``ok(A, P, B)``: every cell under the bounding box of the triangle A P B (which contains
    the fillet arc) is inside the map, has a finite floor <= the lowest corner altitude and a
    ceiling >= the highest, and every wind of those columns is within the vehicle's limit --
    conservative for every point of the arc."""
    g = problem.grid
    floor, ceil = problem.floor_m, problem.ceiling_m
    wmax = problem.vehicle.max_wind_mps

    def ok(a, p, b) -> bool:
        tri = np.stack([a, p, b])
        c = np.floor((np.array([tri[:, 0].min(), tri[:, 0].max()]) - g.x0) / g.resolution_m).astype(int)
        r = np.floor((g.y1 - np.array([tri[:, 1].max(), tri[:, 1].min()])) / g.resolution_m).astype(int)
        if c[0] < 0 or r[0] < 0 or c[1] >= g.nx or r[1] >= g.ny:
            return False
        f = floor[r[0]:r[1] + 1, c[0]:c[1] + 1]
        h = ceil[r[0]:r[1] + 1, c[0]:c[1] + 1]
        if not np.isfinite(f).all() or f.max() > tri[:, 2].min() or h.min() < tri[:, 2].max():
            return False
        return bool(np.linalg.norm(_wind_vectors(problem, tri), axis=1).max() <= wmax)

    return ok


def _retimed_conflicts(occupancy, traj: CornerTrajectory, t0_s: float, spacing_m: float):
    """Traffic re-check of the retimed trajectory: the exact capsule test on chords about
    ``spacing_m`` apart (every piece boundary included).  Returns (times, points, bad chords)."""
    vmax = max(float(np.max(np.abs(traj.v0))), 1e-3)
    t = traj.sample_times(spacing_m / vmax, min_gap_s=0.0)
    p = traj.sample(t)
    if occupancy is None:
        return t, p, np.zeros(t.size - 1, bool)
    return t, p, leg_conflicts(occupancy, p[:-1], t0_s + t[:-1], p[1:], t0_s + t[1:])


# ------------------------------------------------------------------ STEP III


def smooth_chain(problem, waypoints, segment_times_s, *, v_start_mps: float = 0.0,
                 stop_at: tuple[int, ...] = ()) -> CornerTrajectory:
    """Item 1 of STEP III alone: the corner trajectory of a timed chain (the legs' ground
    speeds from ``segment_times_s``) within the vehicle's hard limits, the wind of the chain's
    box and the fillet clearance check of ``problem`` (raises PlanningError when impossible).
    :func:`step3` calls it; the tactical level 1 uses it to screen speed factors cheaply."""
    w = np.asarray(waypoints, float)
    leg_speed = np.linalg.norm(np.diff(w, axis=0), axis=1) / np.asarray(segment_times_s, float)
    return corner_trajectory(w, np.maximum(leg_speed, 1e-3), KinematicLimits.of(problem.vehicle),
                             winds=_wind_vectors(problem, w), fillet_ok=_fillet_checker(problem),
                             v_start_mps=v_start_mps, stop_at=stop_at)


def step3(problem, step2_result: Step2Result, sky: xr.Dataset | None, surface_2d, *, start_time_utc=None,
          occupancy: TrafficOccupancy | None = None, intruders: list[Intruder] | None = None,
          sample_dt_s: float = 0.5, check_spacing_m: float = 1.0, gnss_sigma_m: float = DEFAULT_UERE_M,
          gnss_period_s: float = 1.0, warmup_s: float = 60.0, label: str | None = None,
          battery_reserve_pct: float = 0.0, v_start_mps: float = 0.0, los_cache: dict | None = None,
          stop_at: tuple[int, ...] = (), bubble: tuple[float, float, float] | None = None,
          nav_state: FilterState | None = None, keep_nav_track: bool = False,
          hold_until_s: float | None = None, min_hold_s: float = 1.0,
          trajectory: CornerTrajectory | None = None) -> Candidate:
    """Smooth, retime, check and cost one STEP II chain (see the module docstring).

    ``sky``: :func:`~skyroute.stages.almanac.sky_geometry` Dataset (time, sat) or None (no
    GNSS data: sigma_p is not computed, the candidate is not flyable for lack of navigation
    evidence); ``surface_2d``: (ny, nx) surface heights [m] on ``problem.grid`` (terrain +
    buildings, for the occlusions); ``start_time_utc``: UTC of mission time 0 (default: the
    first sky epoch).  ``occupancy`` / ``intruders``: traffic (capsule maps for the re-check
    of the retimed trajectory; raw tracks for the independent validation, margins from
    ``occupancy``).  ``sample_dt_s`` [s]: output sampling (piece boundaries are added);
    ``check_spacing_m`` [m]: traffic re-check spacing.  ``gnss_period_s`` [s]: GNSS update
    period; ``warmup_s`` [s]: the navigation filter runs this long at the start point before
    take-off (no initial-convergence transient in sigma_p).  ``battery_reserve_pct`` [%]: the
    energy must not exceed ``battery * (1 - reserve / 100)``.  Vehicle limits have no
    tolerance (1e-6 numerical in the validator).  ``v_start_mps`` [m/s]: speed at the first
    waypoint along the first leg (a tactical replan of a vehicle in flight; 0: from rest).
    ``los_cache``: see :func:`line_of_sight` (one dict per sky and surface); ``stop_at``:
    chain vertices where the vehicle stops (:func:`~skyroute.stages.smoothing.corner_trajectory`).
    ``bubble = (k, surface_uncertainty_m, r_p_m)``: safety bubble re-check (seed 003): every
    sample must keep ``max(r_p, k sigma_p(t) + surface_uncertainty)`` [m] from the surface
    prisms of ``surface_2d`` (:func:`~skyroute.stages.planning.validate.validate_bubble`).
    ``nav_state``: the navigation filter of a vehicle in flight
    (:class:`~skyroute.stages.navigation.FilterState` at or before the first sample): sigma_p
    continues it instead of a warm-up at the first waypoint (tactical replans);
    ``keep_nav_track``: keep the filter along the samples in ``Candidate.nav_track`` (so a later
    replan can continue it).  ``hold_until_s`` [s, mission time]: the vehicle hovers at the
    chain's end until then, at least ``min_hold_s`` [s] (a tactical escape,
    :meth:`~skyroute.stages.smoothing.CornerTrajectory.with_hold`); the hover is sampled, costed and
    validated like the rest.  ``trajectory``: fly this corner trajectory (from the chain's first
    waypoint at its first time) instead of smoothing the chain (a tactical escape's turn,
    :func:`~skyroute.stages.smoothing.turn_and_stop`); everything else is the same.
    """
    t_start = time.perf_counter()
    lab = label if label is not None else (getattr(problem, "label", "") or "candidate")
    dop = getattr(problem, "dop_threshold", None)
    if not (sample_dt_s > 0 and check_spacing_m > 0 and gnss_period_s > 0):
        raise InputError("sample_dt_s, check_spacing_m and gnss_period_s must be > 0")
    if not (warmup_s >= 0 and 0 <= battery_reserve_pct < 100):
        raise InputError("warmup_s must be >= 0 [s] and battery_reserve_pct in [0, 100) [%]")
    if not isinstance(step2_result, Step2Result):
        raise InputError(f"step2_result must be a Step2Result, got {type(step2_result).__name__}")
    if not step2_result.ok:
        return empty_candidate(lab, dop, [f"STEP II: {step2_result.reason}"], t_start, step2_result.status)
    veh = problem.vehicle
    w = np.asarray(step2_result.waypoints, float)
    t0 = float(step2_result.times_s[0])
    seg_t = np.diff(step2_result.times_s)
    if np.any(~np.isfinite(seg_t)) or np.any(seg_t <= 0):
        return empty_candidate(lab, dop, ["STEP II chain has non-positive or infinite segment times"], t_start,
                      step2_result.status)
    reasons: list[str] = []
    try:
        traj = (trajectory if trajectory is not None
                else smooth_chain(problem, w, seg_t, v_start_mps=v_start_mps, stop_at=stop_at))
    except PlanningError as exc:
        return empty_candidate(lab, dop, [f"STEP III: {exc}"], t_start, step2_result.status)
    if hold_until_s is not None:
        traj = traj.with_hold(max(float(hold_until_s) - (t0 + traj.duration_s), float(min_hold_s)))
    tc, pc, bad = _retimed_conflicts(occupancy, traj, t0, check_spacing_m)
    if bad.any():
        k = int(np.argmax(bad))
        reasons.append(f"traffic: after retiming to the vehicle limits the trajectory enters a reserved traffic "
                       f"volume at t = {t0 + tc[k]:.1f} s near ({pc[k, 0]:.1f}, {pc[k, 1]:.1f}, {pc[k, 2]:.1f}) "
                       f"({int(bad.sum())} chord(s))")
    bad_pt = ~np.asarray(problem.state_valid(pc), bool)
    if bad_pt.any():   # cannot happen by construction; reported rather than hidden
        k = int(np.argmax(bad_pt))
        reasons.append(f"static bounds: the trajectory leaves the admissible volume at t = {t0 + tc[k]:.1f} s: "
                       f"{problem.explain_invalid(pc[k])}")
    # output samples
    T = traj.duration_s
    tau = traj.sample_times(sample_dt_s)
    p = traj.sample(tau)
    v = traj.velocity(tau)
    t_abs = t0 + tau
    speed = np.linalg.norm(v, axis=1)
    g = problem.grid
    r, c, inside = _cells(g, p)
    agl = p[:, 2] - problem.terrain_m[r, c]
    # wind, power, energy ratio (eq. 12 / 15)
    wind = wind_sampler(problem)(p)
    va = v - wind
    pw = flight_power_W(v, wind, veh)
    p0 = rotor_power(v, speed, v[:, 2], veh)["total_W"]
    beta_e = pw / p0
    beta_r = np.asarray(problem.risk_cost, float)[r, c]
    beta_d = np.asarray(problem.landing_cost, float)[r, c]
    costs = trajectory_costs(problem.weights, tau, speed, beta_r, beta_d, beta_e)
    L, C_r, C_d, C_e, f = (costs[k] for k in ("C_l", "C_r", "C_d", "C_e", "f"))
    energy = float(trapezoid(pw, tau))
    air = np.linalg.norm(va, axis=1)
    usable = veh.battery_energy_j * (1.0 - battery_reserve_pct / 100.0)
    if energy > usable:
        reasons.append(f"energy {energy / 3600:.1f} Wh exceeds the usable battery {usable / 3600:.1f} Wh "
                       f"({veh.battery_energy_j / 3600:.1f} Wh less the {battery_reserve_pct:g} % reserve)")
    if np.max(air) > veh.max_airspeed_mps + 1e-6:   # cannot happen by construction
        reasons.append(f"airspeed reaches {float(np.max(air)):.1f} m/s > v_max {veh.max_airspeed_mps} m/s on the "
                       f"retimed trajectory")
    # navigation error
    sigma = np.full(tau.size, np.nan)
    nvis = np.zeros(tau.size, int)
    nav_track = None
    if sky is None:
        reasons.append("no satellite geometry (sky) given: the navigation error cannot be verified")
    else:
        sigma, nvis, *track = navigation_along(problem, sky, surface_2d, t_abs, p, start_time_utc, veh,
                                               gnss_sigma_m=gnss_sigma_m, gnss_period_s=gnss_period_s,
                                               warmup_s=warmup_s, los_cache=los_cache, initial_state=nav_state,
                                               return_track=keep_nav_track)
        nav_track = track[0] if track else None
        if np.nanmax(sigma) > veh.max_position_error_m:
            k = int(np.nanargmax(sigma))
            reasons.append(f"navigation error sigma_p reaches {float(sigma[k]):.2f} m > dp_max "
                           f"{veh.max_position_error_m} m at t = {t_abs[k]:.1f} s ({int(nvis[k])} satellites in view)")
    cand = Candidate(lab, dop, t_abs, p, agl, speed, sigma, nvis, L, C_r, C_d, C_e, f, False,
                     float(np.nanmax(sigma)) if np.isfinite(sigma).any() else float("nan"), energy, T, 0.0,
                     reasons, traj.waypoints, traj.segment_times_s, traj, step2_result.status)
    cand.nav_track = nav_track
    # independent validation (own code, raw rasters and raw intruder tracks)
    viol = validate_plan(cand, grid=g, terrain_m=problem.terrain_m, vehicle=veh, floor_m=problem.floor_m,
                         ceiling_m=problem.ceiling_m, clearance_floor_m=getattr(problem, "clearance_m", None),
                         gnss_floor_m=getattr(problem, "coverage_m", None),
                         min_agl_m=getattr(problem, "min_agl_m", None),
                         max_agl_m=(problem.max_agl_m if np.isfinite(getattr(problem, "max_agl_m", np.inf))
                                    else 1e12),
                         nofly=getattr(problem, "nofly", None), wind=wind_sampler(problem),
                         intruders=intruders or (), d_c_m=occupancy.d_c_m if occupancy is not None else 0.0,
                         dt_c_s=occupancy.dt_c_s if occupancy is not None else 0.0,
                         start_xyz=step2_result.waypoints[0], goal_xyz=step2_result.waypoints[-1],
                         battery_reserve_pct=battery_reserve_pct)
    reasons.extend(f"validation: {m}" for m in viol if "navigation error" not in m and "battery" not in m)
    if bubble is not None and np.isfinite(sigma).all():
        k_b, su_b, rp_b = bubble
        radius = np.maximum(rp_b, k_b * sigma + su_b)
        reasons.extend(f"validation: {m}" for m in validate_bubble(cand, grid=g, surface_m=surface_2d, radius_m=radius))
    cand.flyable = not reasons
    cand.dp_max_m = float(veh.max_position_error_m)
    cand.compute_time_s = time.perf_counter() - t_start
    return cand


def choose(candidates: list[Candidate], raise_if_none: bool = False) -> Candidate | None:
    """The flyable candidate with the minimum f (seed 000 III-C); ``None`` when none is flyable
    (see :func:`explain_no_plan`), or :class:`PlanningError` with every reason if
    ``raise_if_none``."""
    ok = [c for c in candidates if c.flyable and np.isfinite(c.f)]
    if ok:
        return min(ok, key=lambda c: c.f)
    if raise_if_none:
        raise PlanningError(explain_no_plan(candidates))
    return None


def explain_no_plan(candidates: list[Candidate]) -> str:
    """One message listing why each candidate is not flyable."""
    if not candidates:
        return "no flyable plan: no candidate was produced"
    parts = [f"{c.label}: {'; '.join(c.reasons) or 'not flyable'}" for c in candidates if not c.flyable]
    return "no flyable plan: " + " | ".join(parts) if parts else ""


def utc_of(start_time_utc, t_s) -> list[str]:
    """ISO 8601 UTC strings (``...Z``, millisecond precision) of mission times ``t_s`` [s]."""
    s = pd.Timestamp(start_time_utc)
    s = s.tz_localize("UTC") if s.tzinfo is None else s.tz_convert("UTC")
    s = s.floor("ms")
    out = []
    for v in np.asarray(t_s, float):
        x = (s + pd.Timedelta(milliseconds=int(round(float(v) * 1000.0)))).to_pydatetime()
        out.append(x.astimezone(dt.UTC).strftime("%Y-%m-%dT%H:%M:%S.") + f"{x.microsecond // 1000:03d}Z")
    return out
