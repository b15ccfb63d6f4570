"""STEP III: smooth trajectory, navigation error and final selection (seed 000 section III-C;
seed 001 section 3.1).

For each STEP II chain (one per GNSS coverage level D_j):

1. **Minimum-snap trajectory** (:func:`~skyroute.stages.smoothing.min_snap`, Richter et al.)
   through the chain with the STEP II segment times, so every waypoint is reached at the time
   STEP II deconflicted.  Legs longer than ``max_leg_s`` are first split at equal times (the
   chain's own constant-speed timing) so the polynomial keeps close to the chain's speed and
   timing.  The curve is re-checked on samples about ``check_spacing_m`` apart:
   ``problem.state_valid`` (floors, ceiling, no-fly, wind), flight-path angle of the chords,
   and the traffic occupancy of every chord at its times (exact capsule test); a segment with
   a violation gets a midpoint waypoint at half its time (Richter et al. section 5, as
   :func:`~skyroute.stages.smoothing.smooth_with_clearance`, but time-aware because the
   traffic check needs the sample times) and the problem is re-solved, at most
   ``max_insert_iter`` times.
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
   ``L = int |v| dt``; energy ``E = int P(v - w) dt``.
4. The independent :func:`~skyroute.stages.planning.validate.validate_plan` re-checks the
   samples against the rasters; any violation makes the candidate not flyable.

:func:`choose` picks the flyable candidate with the smallest f.
"""

from __future__ import annotations

import datetime as dt
import math
import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import xarray as xr
from scipy.integrate import trapezoid

from skyroute.pipeline.errors import InputError, PlanningError
from skyroute.stages.energy import rotor_power
from skyroute.stages.navigation import DEFAULT_UERE_M, navigation_error
from skyroute.stages.occlusion import grid_azimuth_deg, visibility_heights_numpy
from skyroute.stages.planning.rrt import Step2Result, _conflicts
from skyroute.stages.planning.validate import validate_plan
from skyroute.stages.smoothing import MinSnapTrajectory, insert_midpoints_where, min_snap
from skyroute.stages.traffic import Intruder, TrafficOccupancy

__all__ = ["Candidate", "choose", "explain_no_plan", "step3", "wind_sampler", "line_of_sight"]


@dataclass
class Candidate:
    """One STEP III candidate D_j: the sampled trajectory and its costs (seed 000 Tables II-III).

    ``t_s`` (m,) [s since mission start], ``xyz_m`` (m, 3) [m, map CRS, surface datum],
    ``alt_agl_m`` (m,), ``speed_mps`` (m,), ``sigma_p_m`` (m,) [m] (NaN without GNSS data),
    ``n_visible`` (m,); costs ``C_l, C_r, C_d, C_e, f`` [m] (eq. 15); ``flyable`` and every
    reason it is not in ``reasons``."""

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
    trajectory: MinSnapTrajectory | None = None
    step2_status: str = ""
    dp_max_m: float = float("nan")

    @property
    def energy_Wh(self) -> float:
        return self.energy_J / 3600.0

    @property
    def costs(self) -> dict[str, float]:
        return {"C_l": self.C_l, "C_r": self.C_r, "C_d": self.C_d, "C_e": self.C_e, "f": self.f}


def _empty(label, dop, reasons, t_start, status="") -> Candidate:
    z = np.zeros(0)
    nan = float("nan")
    return Candidate(label, dop, z, np.zeros((0, 3)), z, z, z, np.zeros(0, int), nan, nan, nan, nan, nan, False,
                     nan, nan, nan, time.perf_counter() - t_start, list(reasons), step2_status=status)


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
        c = np.clip(np.floor((p[:, 0] - g.x0) / g.resolution_m).astype(int), 0, g.nx - 1)
        r = np.clip(np.floor((g.y1 - p[:, 1]) / g.resolution_m).astype(int), 0, g.ny - 1)
        h = p[:, 2] - terrain[r, c]
        wc = np.clip(np.floor((p[:, 0] - wg.x0) / wg.resolution_m).astype(int), 0, wg.nx - 1)
        wr = np.clip(np.floor((wg.y1 - p[:, 1]) / wg.resolution_m).astype(int), 0, wg.ny - 1)
        if wz.size == 1:
            return w4[0, wr, wc, :].copy()
        k0 = np.clip(np.searchsorted(wz, h, side="right") - 1, 0, wz.size - 2)
        fr = np.clip((h - wz[k0]) / (wz[k0 + 1] - wz[k0]), 0.0, 1.0)[:, None]
        return w4[k0, wr, wc, :] * (1 - fr) + w4[k0 + 1, wr, wc, :] * fr

    return f


def _cells(grid, pts):
    c = np.floor((pts[:, 0] - grid.x0) / grid.resolution_m).astype(np.int64)
    r = np.floor((grid.y1 - pts[:, 1]) / grid.resolution_m).astype(np.int64)
    inside = (r >= 0) & (r < grid.ny) & (c >= 0) & (c < grid.nx)
    return np.clip(r, 0, grid.ny - 1), np.clip(c, 0, grid.nx - 1), inside


def _split_long_legs(w, times, max_leg_s):
    w, t = np.asarray(w, float), np.asarray(times, float)
    out_w, out_t = [w[0]], []
    for k in range(t.size):
        n = max(1, int(math.ceil(t[k] / max_leg_s - 1e-9)))
        for j in range(1, n + 1):
            out_w.append(w[k] + (w[k + 1] - w[k]) * (j / n))
            out_t.append(t[k] / n)
    return np.array(out_w), np.array(out_t)


def _sample_times(duration_s: float, dt_s: float) -> np.ndarray:
    """The output sampling of a trajectory: 0..duration in equal steps of at most ``dt_s`` [s]
    (also what the smoothing and retiming checks look at, so they see the validator's chords)."""
    n = max(int(math.ceil(duration_s / dt_s - 1e-9)), 1)
    return np.linspace(0.0, duration_s, n + 1)


def _add_accel_legs(w, times, accel_mps2: float):
    """Trapezoidal speed profile at the ends: the chain starts and ends at rest, so the first
    (last) leg gets a waypoint at the end (start) of an acceleration (deceleration) phase at
    ``accel_mps2`` [m/s^2]; the phase takes 2 d / v instead of d / v, so the schedule of the
    rest of the chain shifts by d / v = v / (2 a) only (a few seconds at cruise speed)."""
    w, t = np.asarray(w, float), np.asarray(times, float)
    if t.size == 0 or accel_mps2 <= 0:
        return w, t
    out_w, out_t = list(w), list(t)
    # last leg first, so the indices of the first one stay valid
    for k, at_start in ((t.size - 1, False), (0, True)):
        length = float(np.linalg.norm(out_w[k + 1] - out_w[k]))
        if length <= 0:
            continue
        v = length / out_t[k]
        d = min(v * v / (2 * accel_mps2), 0.45 * length)
        if d <= 0:
            continue
        frac = d / length if at_start else 1 - d / length
        mid = out_w[k] + (out_w[k + 1] - out_w[k]) * frac
        t_ramp = 2 * d / v
        t_rest = (length - d) / v
        out_w.insert(k + 1, mid)
        out_t[k:k + 1] = [t_ramp, t_rest] if at_start else [t_rest, t_ramp]
    return np.array(out_w), np.array(out_t)


def _check_samples(traj: MinSnapTrajectory, spacing_m: float):
    """Sample times of each segment (about spacing_m apart along the chord)."""
    chord = np.linalg.norm(np.diff(traj.waypoints, axis=0), axis=1)
    counts = np.maximum(4, np.ceil(chord / spacing_m).astype(int) + 1)
    knots = traj.knots_s
    ts = [knots[k] + np.linspace(0.0, traj.segment_times_s[k], c)[:-1] for k, c in enumerate(counts)]
    seg = [np.full(c - 1, k) for k, c in enumerate(counts)]
    t = np.concatenate(ts + [[traj.duration_s]])
    s = np.concatenate(seg + [[len(counts) - 1]])
    return t, s


def _smooth(problem, w, seg_t, t0_s, occupancy, spacing_m, max_iter, fpa_tol_deg, sample_dt_s=None):
    """Min-snap with time-aware midpoint insertion; returns (traj, message or '').
    Chords are checked at ``spacing_m`` and, if given, at the output sampling ``sample_dt_s``
    (the validator's chords), so the output passes the same flight-path-angle rule."""
    tan_a = math.tan(math.radians(problem.vehicle.max_flight_path_angle_deg + fpa_tol_deg))
    for it in range(max_iter + 1):
        traj = min_snap(w, seg_t)
        t, seg = _check_samples(traj, spacing_m)
        p = traj.sample(t)
        bad_pt = ~np.asarray(problem.state_valid(p), bool)
        d = np.diff(p, axis=0)
        h = np.hypot(d[:, 0], d[:, 1])
        bad_ch = np.abs(d[:, 2]) > tan_a * h + 1e-9
        if occupancy is not None:
            bad_ch |= _conflicts(occupancy, p[:-1], t0_s + t[:-1], p[1:], t0_s + t[1:])
        bad_out = np.zeros(0, dtype=int)
        if sample_dt_s:
            to = _sample_times(traj.duration_s, sample_dt_s)
            po = traj.sample(to)
            do = np.diff(po, axis=0)
            steep = np.abs(do[:, 2]) > tan_a * np.hypot(do[:, 0], do[:, 1]) + 1e-9
            knots = np.concatenate([[0.0], np.cumsum(traj.segment_times_s)])
            bad_out = np.clip(np.searchsorted(knots, to[:-1][steep], side="right") - 1, 0, len(knots) - 2)
        bad = np.unique(np.concatenate([seg[bad_pt], seg[:-1][bad_ch], bad_out]))
        if bad.size == 0:
            return traj, ""
        if it < max_iter:
            w, seg_t = insert_midpoints_where(w, seg_t, bad)
    what = []
    if bad_pt.any():
        what.append(f"{int(bad_pt.sum())} sample(s) outside the static bounds")
    if bad_ch.any():
        what.append(f"{int(bad_ch.sum())} chord(s) too steep or in a reserved traffic volume")
    return traj, (f"smoothed trajectory still violates the bounds after {max_iter} midpoint insertions "
                  f"({', '.join(what)})")


def _sky_times_s(sky: xr.Dataset, start_time_utc) -> np.ndarray:
    t = pd.DatetimeIndex(pd.to_datetime(sky["time"].values))
    if t.tz is not None:
        t = t.tz_convert("UTC").tz_localize(None)
    s = pd.Timestamp(start_time_utc)
    if s.tzinfo is not None:
        s = s.tz_convert("UTC").tz_localize(None)
    return (t - s).total_seconds().to_numpy()


def line_of_sight(problem, sky: xr.Dataset, surface_2d, t_s, xyz, start_time_utc,
                  min_el_deg: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """LOS unit vectors (m, nsat, 3) (ENU) and visibility (m, nsat) bool of the sky's satellites
    at samples ``xyz`` (m, 3) at mission times ``t_s`` [s]: nearest epoch of ``sky``; a satellite
    is visible iff it is above the mask (``above_mask``, else el > ``min_el_deg`` or 0) and the
    sample altitude is >= its visibility height in the sample's cell (outside the map: no
    obstacle)."""
    for v in ("az_deg", "el_deg", "los_enu"):
        if v not in sky:
            raise InputError(f"sky dataset lacks {v!r}: build it with skyroute.stages.almanac.sky_geometry")
    g = problem.grid
    h = np.asarray(getattr(surface_2d, "values", surface_2d), dtype=np.float64)
    if h.shape != g.shape:
        raise InputError(f"surface_2d has shape {h.shape}; the problem grid is {g.shape}")
    if not np.isfinite(h).all():
        raise InputError("surface_2d has NaN/inf cells: fill them first")
    ts = _sky_times_s(sky, start_time_utc)
    az = np.asarray(sky["az_deg"].transpose("time", "sat").values, float)
    el = np.asarray(sky["el_deg"].transpose("time", "sat").values, float)
    los_all = np.asarray(sky["los_enu"].transpose("time", "sat", ...).values, float)
    if "above_mask" in sky:
        up = np.asarray(sky["above_mask"].transpose("time", "sat").values, bool)
    else:
        up = el > (0.0 if min_el_deg is None else float(min_el_deg))
    up &= np.isfinite(el) & (el > 0) & np.isfinite(az)
    t = np.asarray(t_s, float)
    p = np.asarray(xyz, float)
    ep = np.clip(np.searchsorted(ts, t), 1, max(ts.size - 1, 1)) if ts.size > 1 else np.zeros(t.size, int)
    if ts.size > 1:
        ep = np.where(np.abs(ts[ep - 1] - t) <= np.abs(ts[ep] - t), ep - 1, ep)
    r, c, inside = _cells(g, p)
    m, nsat = t.size, az.shape[1]
    vis = np.zeros((m, nsat), bool)
    los = np.zeros((m, nsat, 3))
    # bounding box of the path + the longest shadow onto it
    el_min = float(np.min(el[np.unique(ep)][up[np.unique(ep)]])) if up[np.unique(ep)].any() else 90.0
    relief = max(float(h.max()) - float(p[:, 2].min()), 0.0)
    halo = int(math.ceil(relief / math.tan(math.radians(max(el_min, 0.1))) / g.resolution_m)) + 2
    r0, r1 = max(int(r[inside].min()) - halo, 0) if inside.any() else 0, min(int(r.max()) + halo + 1, g.ny)
    c0, c1 = max(int(c[inside].min()) - halo, 0) if inside.any() else 0, min(int(c.max()) + halo + 1, g.nx)
    sub = h[r0:r1, c0:c1]
    for e in np.unique(ep):
        rows = np.nonzero(ep == e)[0]
        sats = np.nonzero(up[e])[0]
        los[rows] = los_all[e][None, :, :]
        if sats.size == 0:
            continue
        az_g = np.atleast_1d(grid_azimuth_deg(az[e, sats], g))
        vh = visibility_heights_numpy(sub, az_g, el[e, sats], g.resolution_m, origin=(r0, c0))
        rr, cc, ii = r[rows], c[rows], inside[rows]
        for j, s in enumerate(sats):
            hv = np.where(ii, vh[j][np.clip(rr - r0, 0, sub.shape[0] - 1), np.clip(cc - c0, 0, sub.shape[1] - 1)],
                          -np.inf)
            vis[rows, s] = p[rows, 2] >= hv
    # LOS rows of invisible satellites are irrelevant; keep them unit-length where finite
    los = np.where(np.isfinite(los), los, 0.0)
    return los, vis


# ------------------------------------------------------------------ STEP III


def step3(problem, step2_result: Step2Result, sky: xr.Dataset | None, surface_2d, *, start_time_utc=None,
          occupancy: TrafficOccupancy | None = None, intruders: list[Intruder] | None = None,
          sample_dt_s: float = 0.5, check_spacing_m: float = 1.0, max_insert_iter: int = 10,
          max_leg_s: float = 10.0, gnss_sigma_m: float = DEFAULT_UERE_M, gnss_period_s: float = 1.0,
          warmup_s: float = 60.0, fpa_tol_deg: float = 3.0, label: str | None = None,
          max_retime_iter: int = 8, accel_mps2: float = 2.0) -> Candidate:
    """Smooth, check and cost one STEP II chain (see the module docstring).

    ``sky``: :func:`~skyroute.stages.almanac.sky_geometry` Dataset (time, sat) or None (no
    GNSS data: sigma_p is not computed, the candidate is not flyable for lack of navigation
    evidence); ``surface_2d``: (ny, nx) surface heights [m] on ``problem.grid`` (terrain +
    buildings, for the occlusions); ``start_time_utc``: UTC of mission time 0 (default: the
    first sky epoch).  ``occupancy`` / ``intruders``: traffic (capsule maps for the smoothing
    re-check; raw tracks for the independent validation, margins from ``occupancy``).
    ``sample_dt_s`` [s]: output sampling; ``check_spacing_m`` [m]: clearance re-check spacing.
    ``gnss_period_s`` [s]: GNSS update period; ``warmup_s`` [s]: the navigation filter runs
    this long at the start point before take-off (no initial-convergence transient in
    sigma_p).  ``fpa_tol_deg`` [deg]: tolerance on the flight-path angle of the *smooth*
    curve (the chain respects alpha exactly; min-snap rounding of a sharp vertical corner
    overshoots it by up to ~2 deg whatever the number of inserted midpoints).
    ``max_retime_iter``: how many 10 % stretches of the schedule may bring the airspeed of the
    smooth curve below the vehicle limit.
    ``accel_mps2`` [m/s^2]: take-off and landing legs get a constant-acceleration ramp.
    """
    t_start = time.perf_counter()
    lab = label if label is not None else (getattr(problem, "label", "") or "candidate")
    dop = getattr(problem, "dop_threshold", None)
    if not (sample_dt_s > 0 and check_spacing_m > 0 and max_leg_s > 0 and gnss_period_s > 0):
        raise InputError("sample_dt_s, check_spacing_m, max_leg_s and gnss_period_s must be > 0")
    if not (warmup_s >= 0 and 0 <= fpa_tol_deg < 30):
        raise InputError("warmup_s must be >= 0 [s] and fpa_tol_deg in [0, 30) [deg]")
    if not isinstance(step2_result, Step2Result):
        raise InputError(f"step2_result must be a Step2Result, got {type(step2_result).__name__}")
    if not step2_result.ok:
        return _empty(lab, dop, [f"STEP II: {step2_result.reason}"], t_start, step2_result.status)
    veh = problem.vehicle
    w = np.asarray(step2_result.waypoints, float)
    t0 = float(step2_result.times_s[0])
    seg_t = np.diff(step2_result.times_s)
    if np.any(~np.isfinite(seg_t)) or np.any(seg_t <= 0):
        return _empty(lab, dop, ["STEP II chain has non-positive or infinite segment times"], t_start,
                      step2_result.status)
    reasons: list[str] = []
    w, seg_t = _add_accel_legs(w, seg_t, accel_mps2)
    w, seg_t = _split_long_legs(w, seg_t, max_leg_s)
    traj, msg = _smooth(problem, w, seg_t, t0, occupancy, check_spacing_m, max_insert_iter, fpa_tol_deg,
                        sample_dt_s)
    wind_of = wind_sampler(problem)
    # time allocation: the take-off and landing ramps keep the minimum-snap curve near the
    # chain's speeds; where it still exceeds the airspeed limit (headwind legs), the whole
    # schedule is stretched by 10 % and re-solved (uniform scaling divides every velocity by
    # the same factor, so this converges; the traffic re-check runs on the new schedule)
    for _ in range(max_retime_iter):
        if msg:
            break
        tt = _sample_times(traj.duration_s, sample_dt_s)
        air = np.linalg.norm(traj.velocity(tt) - wind_of(traj.sample(tt)), axis=1)
        if air.max() <= 0.97 * veh.max_airspeed_mps:
            break
        traj, msg = _smooth(problem, np.asarray(traj.waypoints, float), np.asarray(traj.segment_times_s) * 1.1,
                            t0, occupancy, check_spacing_m, max_insert_iter, fpa_tol_deg, sample_dt_s)
    if msg:
        reasons.append(msg)
    # output samples
    T = traj.duration_s
    tau = _sample_times(T, sample_dt_s)
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
    sdir = np.divide(v, speed[:, None], out=np.zeros_like(v), where=speed[:, None] > 1e-9)
    pw = rotor_power(va, np.einsum("ij,ij->i", va, sdir), v[:, 2], veh)["total_W"]
    p0 = rotor_power(v, speed, v[:, 2], veh)["total_W"]
    beta_e = pw / p0
    beta_r = np.asarray(problem.risk_cost, float)[r, c]
    beta_d = np.asarray(problem.landing_cost, float)[r, c]
    L = float(trapezoid(speed, tau))
    dur = T
    C_r = L * float(trapezoid(beta_r, tau)) / dur
    C_d = L * float(trapezoid(beta_d, tau)) / dur
    C_e = L * float(trapezoid(beta_e, tau)) / dur
    wl, wr, wd, we = problem.weights
    f = wl * L + wr * C_r + wd * C_d + we * C_e
    energy = float(trapezoid(pw, tau))
    air = np.linalg.norm(va, axis=1)
    if energy > veh.battery_energy_j:
        reasons.append(f"energy {energy / 3600:.1f} Wh exceeds the battery {veh.battery_energy_j / 3600:.1f} Wh")
    if np.max(air) > veh.max_airspeed_mps:
        reasons.append(f"airspeed reaches {float(np.max(air)):.1f} m/s > v_max {veh.max_airspeed_mps} m/s on the "
                       f"smoothed trajectory")
    # navigation error
    sigma = np.full(tau.size, np.nan)
    nvis = np.zeros(tau.size, int)
    if sky is None:
        reasons.append("no satellite geometry (sky) given: the navigation error cannot be verified")
    else:
        if start_time_utc is None:
            start_time_utc = pd.Timestamp(sky["time"].values[0])
        # warm-up: the receiver/filter runs at the start point before take-off
        nw = int(math.floor(warmup_s / gnss_period_s + 1e-9)) if warmup_s > 0 else 0
        t_w = t_abs[0] - gnss_period_s * np.arange(nw, 0, -1)
        t_all = np.concatenate([t_w, t_abs])
        p_all = np.concatenate([np.repeat(p[:1], nw, axis=0), p])
        los, vis = line_of_sight(problem, sky, surface_2d, t_all, p_all, start_time_utc)
        nav = navigation_error(t_all, los, vis, imu=veh, gnss_sigma_m=gnss_sigma_m, dt_s=gnss_period_s)
        sigma = np.asarray(nav["sigma_p_m"].values, float)[nw:]
        nvis = vis.sum(axis=1)[nw:]
        if np.nanmax(sigma) > veh.max_position_error_m:
            k = int(np.nanargmax(sigma))
            reasons.append(f"navigation error sigma_p reaches {float(sigma[k]):.2f} m > dp_max "
                           f"{veh.max_position_error_m} m at t = {t_abs[k]:.1f} s ({int(nvis[k])} satellites in view)")
    cand = Candidate(lab, dop, t_abs, p, agl, speed, sigma, nvis, L, C_r, C_d, C_e, f, False,
                     float(np.nanmax(sigma)) if np.isfinite(sigma).any() else float("nan"), energy, T, 0.0,
                     reasons, traj.waypoints, traj.segment_times_s, traj, step2_result.status)
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
                         tol_deg=fpa_tol_deg + 1e-6)
    reasons.extend(f"validation: {m}" for m in viol if "navigation error" not in m and "battery" not in m)
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
