"""Seed 002's local path planner (Aiello et al., sections 4.3-4.4) as a fixed-wing flight simulation.

Every aircraft follows its global (EEA*) path -- the written plan: lattice path, turn fillets,
loiter at the goal -- in simulated time, and a local planner reacts to what its sensors see.

**Guidance model** (point mass, Dubins-like, documented here and nowhere else).  State
``(x, y, z, psi)``: position [m] and air-frame heading [rad].  Inputs held constant over a
tick ``dt``: the turn rate ``omega`` [rad/s] and the vertical rate ``h_dot`` [m/s].  The
airspeed is the vehicle's flown airspeed at the local density
(:meth:`~skyroute.stages.vehicle.FixedWingProfile.airspeed_at`, the seed's constant Carson
speed), ``V_h = sqrt(V^2 - h_dot^2)`` is its horizontal part and the ground velocity is
``V_h (cos psi, sin psi) + (u, v)`` with the horizontal wind ``(u, v)`` sampled at the
aircraft every :data:`SLOW_EVERY` ticks (the vertical wind is ignored).  One tick is integrated exactly (a horizontal
air-frame arc of radius ``V_h / omega`` plus the wind drift).  Limits (the same tolerance-free
checks as the validator, :func:`~skyroute.stages.planning.validate.turn_radius_violations`):

* turn rate ``|omega| <= (1 - 1e-3) g tan(bank_max) cos(gamma_max) / V``, so the horizontal
  radius ``V_h / omega >= V^2 / (g tan(bank_max))`` and, in wind, the ground track needs a
  bank ``atan(v_g^2 kappa / g) <= bank_max`` (``v_g^2 kappa <= V_h omega``);
* vertical rate ``h_dot <= (1 - 1e-3) tan(gamma_climb) min(V cos(gamma_climb), v_gh)`` (and
  the same with the descent angle), ``v_gh`` the horizontal ground speed: the flight-path
  angle stays within the limits both in the air and over the ground.

**Path following**: the reference is the plan's sample chain; the aircraft's progress ``s``
[m] is its projection on the chain (monotone) and it steers (heading command with the wind
correction angle, proportional with a 1 s time constant, saturated at the turn-rate limit)
towards a carrot ``L`` ahead on the chain (``L = max(R_ground, 3 s V)``); its altitude
command is the chain's altitude ``V tau_z`` ahead (``tau_z`` = 2 s), raised by the local
planner and by the terrain guard.

**Local planner** (seed 002 section 4.3), every tick:

* *unknown static obstacles* (prisms: a polygon from the ground to ``z_top``): sensed when
  their 3-D distance is <= ``obstacle_range_m``; a sensed obstacle that the chain ahead
  (``obstacle_range_m + L``) passes within ``r_p + d_c + track_tol_m`` of, horizontally,
  engages the climb: an intermediate waypoint above it at ``z_top + r_p + d_c``, generated
  again at every tick while the obstacle is sensed (so the aircraft stays above until it
  has left the sensor range), then it rejoins the plan descending within its limits.  The
  climb is feasible when ``(d - r_p) tan(gamma_climb) >= z_top + r_p + d_c - z`` at the
  detection distance ``d``; an obstacle sensed too late is named in the warnings.
* *other UAVs* (the other aircraft of a fleet, and intruder tracks): sensed within
  ``uav_range_m``; a sensed UAV is on a collision course when the closest point of approach
  of the two straight-line extrapolations (current 3-D ground velocities) is ahead within
  ``horizon_s`` and closer than ``alert_factor * S``, with the separation threshold
  ``S = r_i + r_j + d_c``.  Then (rules of the air) the aircraft turns **right**: its carrot
  becomes an intermediate waypoint ``avoid_offset_m`` to the right of the chain, generated
  again every tick until that UAV is no longer sensed; then it rejoins.  In a fleet both
  aircraft of a pair see each other and both turn right.  Intruders are non-cooperative (they
  keep their track, so the rule cannot be relied on): the aircraft turns right head-on and
  unless a 45 deg turn to the left predicts a miss distance larger by more than 1 m (e.g. an
  intruder crossing from the left: pass behind it), then it turns **left** the same way
  (beyond the seed).
* *terrain guard* (beyond the seed): the altitude command is at least the floor raster
  (clearance floor, minimum AGL) along the ground course over ``terrain_lookahead_m``, less
  what a climb at 0.9 x the limit gains on the way (checked every :data:`SLOW_EVERY` ticks).

A UAV that reaches the end of its chain (remaining length below one tick of flight, or within
``goal_tol_m`` of the end) has arrived and leaves the airspace.  Energy: seed 002
(:func:`~skyroute.stages.fixedwing_energy.segment_energy_fw`) along the flown samples and
along the planned samples, with the same wind (added energy = the difference).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from skyroute.stages import control
from skyroute.stages.atmosphere import density_kernel
from skyroute.stages.base import InputError
from skyroute.stages.fixedwing_energy import airspeed_kernel, fixedwing_params, segment_energy_fw
from skyroute.stages.vehicle import G0, FixedWingProfile, load_vehicle

__all__ = ["LocalPlannerParams", "StaticObstacle", "LocalAgent", "LocalTrack", "LocalResult", "cylinder_polygon",
           "prism_distance_m", "simulate_local", "separation_threshold_m", "fly_fixedwing_fleet",
           "brute_force_min_separation", "floor_sampler", "obstacle_clearance_m", "local_flight_log"]

MODES = ("strategic", "climb", "right", "left", "loiter", "descend")
ESCAPES = ("right", "left", "climb", "loiter", "descend")   # a non-cooperative UAV: the one that keeps most
ESCAPE_TURN_RAD = math.pi / 2                                # right / left: a 90 deg turn, then straight
SLOW_EVERY = 5     # ticks between wind samples and terrain-guard checks


@dataclass(frozen=True)
class LocalPlannerParams:
    """Local planner settings (module docstring).  ``tick_s`` [s]: simulation step;
    ``obstacle_range_m`` / ``uav_range_m`` [m]: sensor ranges for static obstacles and for
    other UAVs; ``d_c_m`` [m]: separation margin (``S = r_i + r_j + d_c``; the climb goes to
    ``z_top + r_p + d_c``); ``avoid_offset_m`` [m]: the rightward waypoint's offset;
    ``alert_factor``: collision course when the CPA distance is < ``alert_factor * S``;
    ``horizon_s`` [s]: CPA horizon; ``track_tol_m`` [m]: horizontal tolerance of the threat
    test of an obstacle; ``terrain_lookahead_m`` [m]; ``goal_tol_m`` [m]; ``t_max_factor``:
    the simulation stops at this multiple of the planned duration (+ 120 s)."""

    tick_s: float = 0.1
    obstacle_range_m: float = 500.0
    uav_range_m: float = 400.0
    d_c_m: float = 5.0
    avoid_offset_m: float = 150.0
    alert_factor: float = 2.0
    horizon_s: float = 40.0
    track_tol_m: float = 30.0
    terrain_lookahead_m: float = 400.0
    goal_tol_m: float = 10.0
    t_max_factor: float = 2.0

    def __post_init__(self):
        for k in ("tick_s", "obstacle_range_m", "uav_range_m", "avoid_offset_m", "alert_factor", "horizon_s",
                  "goal_tol_m", "t_max_factor"):
            if not getattr(self, k) > 0:
                raise InputError(f"local planner: {k} = {getattr(self, k)} must be > 0")
        for k in ("d_c_m", "track_tol_m", "terrain_lookahead_m"):
            if not getattr(self, k) >= 0:
                raise InputError(f"local planner: {k} = {getattr(self, k)} must be >= 0")


@dataclass(frozen=True)
class StaticObstacle:
    """An obstacle unknown to the global planner: the prism ``polygon_xy`` (k, 2) [m] from the
    ground up to ``z_top_m`` [m, surface datum], present from ``t_s`` [s] on."""

    id: str
    polygon_xy: np.ndarray
    z_top_m: float
    t_s: float = 0.0


@dataclass
class LocalAgent:
    """One aircraft: ``plan_t_s`` (n,) [s] and ``plan_xyz_m`` (n, 3) [m], its planned samples
    (start time = ``plan_t_s[0]``), the ``vehicle`` (fixed-wing) and its ``id``."""

    id: str
    plan_t_s: np.ndarray
    plan_xyz_m: np.ndarray
    vehicle: FixedWingProfile | str = "skywalker-x8"


@dataclass
class LocalTrack:
    """A non-cooperative UAV (intruder): linear between ``t_s`` (k,) [s] and ``xyz_m`` (k, 3) [m],
    radius ``radius_m`` [m]; it exists from ``t_s[0]`` to ``t_s[-1]``."""

    id: str
    t_s: np.ndarray
    xyz_m: np.ndarray
    radius_m: float


@dataclass
class LocalResult:
    """One simulated flight per agent (index = agent): ``t_s`` (m,) [s], ``xyz_m`` (m, 3) [m],
    ``heading_rad``, ``speed_mps`` (horizontal ground speed), ``mode`` (m,) str (one of
    :data:`MODES`); ``arrived_s`` [s] (inf when it did not arrive), ``planned_end_s`` [s],
    ``delay_s`` / ``added_energy_J`` (vs the undisturbed flight, :func:`simulate_local`),
    ``energy_J`` / ``planned_energy_J`` (seed 002, flown / planned samples), ``manoeuvres``: dicts
    (agent, kind climb/right, threat id, t_start_s, t_end_s, t_cpa_s, d_cpa_m, feasible);
    ``warnings``; ``params``; ``radius_m`` per agent (r_p); ``compute_s`` [s]."""

    ids: list[str]
    t_s: list[np.ndarray]
    xyz_m: list[np.ndarray]
    heading_rad: list[np.ndarray]
    speed_mps: list[np.ndarray]
    mode: list[np.ndarray]
    arrived_s: np.ndarray
    planned_end_s: np.ndarray
    energy_J: np.ndarray
    planned_energy_J: np.ndarray
    radius_m: np.ndarray
    params: LocalPlannerParams
    manoeuvres: list[dict] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    compute_s: float = 0.0
    baseline_arrived_s: np.ndarray | None = None
    baseline_energy_J: np.ndarray | None = None

    @property
    def delay_s(self) -> np.ndarray:
        """Arrival minus the undisturbed flight's arrival [s] per agent."""
        return self.arrived_s - self.baseline_arrived_s

    @property
    def added_energy_J(self) -> np.ndarray:
        """Energy minus the undisturbed flight's energy [J] per agent (seed 002 model)."""
        return self.energy_J - self.baseline_energy_J

    @property
    def delay_vs_plan_s(self) -> np.ndarray:
        """Arrival minus the plan's arrival [s] (includes the path-following error)."""
        return self.arrived_s - self.planned_end_s


def separation_threshold_m(r_i_m: float, r_j_m: float, d_c_m: float) -> float:
    """S = r_i + r_j + d_c [m]: two UAVs closer than this have lost separation."""
    return float(r_i_m) + float(r_j_m) + float(d_c_m)


def cylinder_polygon(center_xy, radius_m: float, n: int = 24) -> np.ndarray:
    """A regular ``n``-gon (n, 2) [m] circumscribing the circle of ``radius_m`` around
    ``center_xy`` (a cylinder obstacle as a conservative prism)."""
    a = (np.arange(n) + 0.5) * 2 * math.pi / n
    r = float(radius_m) / math.cos(math.pi / n)
    return np.column_stack([center_xy[0] + r * np.cos(a), center_xy[1] + r * np.sin(a)])


def _poly_dist_xy(poly: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Horizontal distance [m] of points q (m, 2) to the closed polygon (0 inside)."""
    q = np.atleast_2d(q)
    a = poly
    b = np.roll(poly, -1, axis=0)
    ab = b - a
    ap = q[:, None, :] - a[None]
    tt = np.clip(np.einsum("mkj,kj->mk", ap, ab) / np.einsum("kj,kj->k", ab, ab), 0.0, 1.0)
    d = np.linalg.norm(ap - tt[..., None] * ab[None], axis=2).min(axis=1)
    # even-odd rule
    y = q[:, 1][:, None]
    x = q[:, 0][:, None]
    cond = (a[None, :, 1] > y) != (b[None, :, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xint = a[None, :, 0] + (y - a[None, :, 1]) * ab[None, :, 0] / ab[None, :, 1]
    inside = (np.sum(cond & (x < xint), axis=1) % 2) == 1
    return np.where(inside, 0.0, d)


def prism_distance_m(obstacle: StaticObstacle, xyz_m) -> np.ndarray:
    """3-D distance [m] of points (m, 3) to the obstacle's prism (polygon x (-inf, z_top])."""
    q = np.atleast_2d(np.asarray(xyz_m, float))
    dxy = _poly_dist_xy(np.asarray(obstacle.polygon_xy, float), q[:, :2])
    dz = np.maximum(q[:, 2] - obstacle.z_top_m, 0.0)
    return np.hypot(dxy, dz)


class _Chain:
    """A sample chain with horizontal arc length: projection, points, tangents."""

    def __init__(self, xyz: np.ndarray):
        x = np.asarray(xyz, float)
        keep = np.r_[True, np.linalg.norm(np.diff(x[:, :2], axis=0), axis=1) > 1e-9]
        self.p = x[keep]
        self.s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(self.p[:, :2], axis=0), axis=1))]
        self.length = float(self.s[-1])

    def at(self, s: float) -> np.ndarray:
        s = min(max(s, 0.0), self.length)
        i = min(int(np.searchsorted(self.s, s, side="right")) - 1, len(self.s) - 2)
        f = (s - self.s[i]) / (self.s[i + 1] - self.s[i])
        return self.p[i] + f * (self.p[i + 1] - self.p[i])

    def tangent(self, s: float) -> np.ndarray:
        i = min(max(int(np.searchsorted(self.s, s, side="right")) - 1, 0), len(self.s) - 2)
        d = self.p[i + 1, :2] - self.p[i, :2]
        return d / np.linalg.norm(d)

    def project(self, xy: np.ndarray, s0: float, window_m: float) -> float:
        last = len(self.s) - 1
        i0 = min(max(int(np.searchsorted(self.s, s0, side="right")) - 1, 0), last - 1)
        i1 = min(max(int(np.searchsorted(self.s, s0 + window_m, side="right")), i0 + 1), last)
        a, b = self.p[i0:i1, :2], self.p[i0 + 1:i1 + 1, :2]
        ab = b - a
        tt = np.clip(np.einsum("kj,kj->k", xy - a, ab) / np.einsum("kj,kj->k", ab, ab), 0.0, 1.0)
        d = np.linalg.norm(a + tt[:, None] * ab - xy, axis=1)
        k = int(np.argmin(d))
        return max(s0, float(self.s[i0 + k] + tt[k] * (self.s[i0 + k + 1] - self.s[i0 + k])))

    def segment(self, s0: float, s1: float) -> np.ndarray:
        m = (self.s > s0) & (self.s < s1)
        return np.vstack([self.at(s0)[None], self.p[m], self.at(s1)[None]])


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _track_at(tr: LocalTrack, t: float) -> tuple[np.ndarray, np.ndarray] | None:
    ts = np.asarray(tr.t_s, float)
    if t < ts[0] or t > ts[-1]:
        return None
    x = np.asarray(tr.xyz_m, float)
    p = np.array([np.interp(t, ts, x[:, k]) for k in range(3)])
    i = int(np.clip(np.searchsorted(ts, t, side="right") - 1, 0, len(ts) - 2))
    v = (x[i + 1] - x[i]) / (ts[i + 1] - ts[i])
    return p, v


def _cpa(dp: np.ndarray, dv: np.ndarray) -> tuple[float, float]:
    vv = float(dv @ dv)
    tc = 0.0 if vv < 1e-12 else -float(dp @ dv) / vv
    return tc, float(np.linalg.norm(dp + dv * max(tc, 0.0)))


def _choose_escape(pos, psi: float, V: float, wind, t0: float, track: LocalTrack, S: float, params: LocalPlannerParams,
                   gam_u: float, gam_d: float, tanb: float, cosg: float, floor_at) -> dict:
    """The escape from a non-cooperative UAV (issue 22): among :data:`ESCAPES` -- seed 002's
    right turn (90 deg at the turn-rate limit, then straight), the left turn, the climb (straight
    at the climb-rate limit), a loiter (a continuous right turn on the tightest circle) and a
    descent (where the floor allows) -- the one whose predicted minimum distance to the UAV's
    known track over ``horizon_s`` is largest (right first on a tie: the rules of the air).
    Prediction and flight use the same point-mass integration with the same commands.  Returns
    what the manoeuvre record needs: ``kind``, the commands, ``predicted_min_m``,
    ``t_cpa_pred_s``, ``keeps_separation``, ``options`` (every escape's predicted minimum)."""
    wall = time.perf_counter()
    dt = params.tick_s
    n = int(params.horizon_s / dt)
    tt = t0 + dt * np.arange(1, n + 1)
    ts, xs = np.asarray(track.t_s, float), np.asarray(track.xyz_m, float)
    live = (tt >= ts[0]) & (tt <= ts[-1])
    q = np.column_stack([np.interp(tt, ts, xs[:, k]) for k in range(3)])
    om_max = (1 - 1e-3) * G0 * tanb * cosg / V
    w = np.asarray(wind, float)
    out = {}
    for kind in ESCAPES:
        osg = {"right": -1.0, "left": 1.0, "loiter": -1.0}.get(kind, 0.0)
        hsg = {"climb": 1.0, "descend": -1.0}.get(kind, 0.0)
        lim = ESCAPE_TURN_RAD if kind in ("right", "left") else (math.inf if kind == "loiter" else 0.0)
        x, y, z, ps, turned = float(pos[0]), float(pos[1]), float(pos[2]), float(psi), 0.0
        path = np.empty((n, 3))
        for k in range(n):
            om = osg * om_max if turned < lim else 0.0
            turned += abs(om) * dt
            v_gh = math.hypot(V * math.cos(ps) + w[0], V * math.sin(ps) + w[1])
            hd = 0.0
            if hsg > 0:
                hd = (1 - 1e-3) * math.tan(gam_u) * min(V * math.cos(gam_u), v_gh)
            elif hsg < 0:
                hd = -(1 - 1e-3) * math.tan(gam_d) * min(V * math.cos(gam_d), v_gh)
            Vh = math.sqrt(max(V * V - hd * hd, 0.0))
            if abs(om) < 1e-12:
                dx, dy = Vh * math.cos(ps) * dt, Vh * math.sin(ps) * dt
            else:
                dx = Vh / om * (math.sin(ps + om * dt) - math.sin(ps))
                dy = -Vh / om * (math.cos(ps + om * dt) - math.cos(ps))
            x, y, z, ps = x + dx + w[0] * dt, y + dy + w[1] * dt, z + hd * dt, ps + om * dt
            path[k] = (x, y, z)
        if kind == "descend" and floor_at is not None:
            fl = np.asarray(floor_at(path[:, 0], path[:, 1]), float)
            if np.any(~np.isfinite(fl) | (path[:, 2] < fl)):
                continue                              # the descent would go below the floor
        d = np.where(live, np.linalg.norm(path - q, axis=1), np.inf)
        k = int(np.argmin(d))
        out[kind] = (float(d[k]), float(tt[k]), osg, hsg, lim)
    best = max(out, key=lambda kk: (out[kk][0], -ESCAPES.index(kk)))
    dmin, tcpa, osg, hsg, lim = out[best]
    return {"kind": best, "omega_sign": osg, "hdot_sign": hsg, "turn_limit_rad": lim, "turned_rad": 0.0,
            "predicted_min_m": dmin, "t_cpa_pred_s": tcpa, "keeps_separation": bool(dmin >= S),
            "options": {kk: round(v[0], 2) for kk, v in out.items()}, "compute_s": time.perf_counter() - wall}


def _energy(xyz: np.ndarray, wind_at, vehicle) -> float:
    x = np.asarray(xyz, float)
    if len(x) < 2:
        return 0.0
    a, b = x[:-1], x[1:]
    keep = np.linalg.norm(b - a, axis=1) > 0
    a, b = a[keep], b[keep]
    w = np.asarray(wind_at(a), float).reshape(-1, 3).copy()
    w[:, 2] = 0.0
    return float(np.sum(segment_energy_fw(a, b, w, vehicle)["energy_J"]))


def _zero_wind(xyz):
    return np.zeros((np.atleast_2d(xyz).shape[0], 3))


def simulate_local(agents: Sequence[LocalAgent], *, obstacles: Sequence[StaticObstacle] = (),
                   intruders: Sequence[LocalTrack] = (), params: LocalPlannerParams = LocalPlannerParams(),
                   wind_at: Callable | None = None, floor_at: Callable | None = None,
                   baseline: bool = True, known_from_s: dict[str, float] | None = None) -> LocalResult:
    """Fly ``agents`` together with seed 002's local planner (module docstring).

    ``wind_at(xyz (m, 3)) -> (m, 3)`` [m/s] (default still air); ``floor_at(x (m,), y (m,))
    -> (m,)`` the lowest admissible altitude [m] (terrain guard; default none).  Every agent
    starts at its first planned sample and time with the heading of its first chord.  With
    ``baseline`` each agent also flies alone without obstacles and intruders (the undisturbed
    flight: ``baseline_arrived_s``, ``baseline_energy_J``), the reference of ``delay_s`` and
    ``added_energy_J`` (so that they measure the manoeuvres, not the path following).
    ``known_from_s``: intruder id -> the time [s] from which the aircraft knows of it (U-space /
    V2V, issue 22): it is then sensed whatever its distance."""
    t_wall = time.perf_counter()
    known_from_s = dict(known_from_s or {})
    wind_at = wind_at or _zero_wind
    dt = float(params.tick_s)
    n = len(agents)
    if n == 0:
        raise InputError("simulate_local needs at least one agent")
    veh = [load_vehicle(a.vehicle) for a in agents]
    for v in veh:
        if not isinstance(v, FixedWingProfile):
            raise InputError(f"vehicle {v.name!r} is a {v.kind}: seed 002's local planner flies fixed-wing aircraft")
    prms = [fixedwing_params(v) for v in veh]

    def airspeed(i: int, z: float) -> float:
        return float(airspeed_kernel(density_kernel(float(z)), prms[i]))

    chains = [_Chain(a.plan_xyz_m) for a in agents]
    for a, c in zip(agents, chains, strict=True):
        if len(c.p) < 2:
            raise InputError(f"agent {a.id!r}: its plan needs at least two distinct samples")
    radius = np.array([v.r_p_m for v in veh])
    t0 = np.array([float(np.asarray(a.plan_t_s)[0]) for a in agents])
    t_end_plan = np.array([float(np.asarray(a.plan_t_s)[-1]) for a in agents])
    t_stop = float(np.max(t0 + params.t_max_factor * (t_end_plan - t0) + 120.0))
    gam_u = [math.radians(v.max_climb_angle_deg) for v in veh]
    gam_d = [math.radians(v.max_descent_angle_deg) for v in veh]
    tanb = [math.tan(math.radians(v.max_bank_deg)) for v in veh]
    cosg = [math.cos(max(gu, gd)) for gu, gd in zip(gam_u, gam_d, strict=True)]
    r_ground = [max((airspeed(i, float(np.max(c.p[:, 2]))) + 10.0) ** 2 / (G0 * tanb[i]), 1.0)
                for i, c in enumerate(chains)]
    look = [max(r_ground[i], 3.0 * airspeed(i, float(c.p[0, 2]))) for i, c in enumerate(chains)]
    pos = np.array([c.p[0] for c in chains], float)
    psi = np.array([math.atan2(*(c.tangent(0.0)[::-1])) for c in chains])
    s = np.zeros(n)
    vel = np.zeros((n, 3))
    active = np.zeros(n, bool)
    arrived = np.full(n, math.inf)
    logs: list[dict[str, list]] = [{"t": [], "p": [], "psi": [], "v": [], "mode": []} for _ in range(n)]
    engaged_obs: list[dict[str, dict]] = [{} for _ in range(n)]
    engaged_uav: list[dict[str, dict]] = [{} for _ in range(n)]
    manoeuvres: list[dict] = []
    warnings: list[str] = []
    z_over = {o.id: float(o.z_top_m) for o in obstacles}
    guard: dict[int, float] = {}
    hdot_prev = np.zeros(n)                      # vertical rate of the last tick (CPA extrapolation)
    winds = np.zeros((n, 3))
    t_first = float(np.min(t0))
    t = t_first
    k_step = 0
    while t <= t_stop + 1e-9:
        if k_step % 200 == 0:
            control.check()
        k_step += 1
        for i in range(n):                       # start, log the current state
            if not active[i] and not math.isfinite(arrived[i]) and t >= t0[i] - 1e-9:
                active[i] = True
        if not active.any() and np.all(np.isfinite(arrived)):
            break
        if k_step % SLOW_EVERY == 1:             # wind and terrain guard: every SLOW_EVERY ticks
            winds = np.asarray(wind_at(pos), float).reshape(n, 3)
        # ground velocities now (for the CPA of the others)
        for i in range(n):
            if active[i]:
                V = airspeed(i, pos[i, 2])
                vel[i] = [V * math.cos(psi[i]) + winds[i, 0], V * math.sin(psi[i]) + winds[i, 1], hdot_prev[i]]
        others = []                              # (key, position, velocity, radius, agent index or -1)
        for j in range(n):
            if active[j]:
                others.append((agents[j].id, pos[j].copy(), vel[j].copy(), radius[j], j))
        for tr in intruders:
            pv = _track_at(tr, t)
            if pv is not None:
                others.append((tr.id, pv[0], pv[1], float(tr.radius_m), -1))
        new_pos = pos.copy()
        new_psi = psi.copy()
        for i in range(n):
            if not active[i]:
                continue
            V = airspeed(i, pos[i, 2])
            ch = chains[i]
            L = look[i]
            s[i] = ch.project(pos[i, :2], s[i], L + V * dt * 4)
            # arrival
            rem = ch.length - s[i]
            if rem <= V * dt or (rem < L and np.linalg.norm(pos[i, :2] - ch.p[-1, :2]) <= params.goal_tol_m):
                active[i] = False
                arrived[i] = t
                for d in (engaged_obs[i], engaged_uav[i]):
                    for m in d.values():
                        m["t_end_s"] = t
                continue
            carrot = ch.at(s[i] + L)
            mode = "strategic"
            # ---- other UAVs: rules of the air, turn right
            for key, pj, vj, rj, j in others:
                if j == i:
                    continue
                dist = float(np.linalg.norm(pj - pos[i]))
                m = engaged_uav[i].get(key)
                S = separation_threshold_m(radius[i], rj, params.d_c_m)
                sensed = dist <= params.uav_range_m or (j < 0 and t >= known_from_s.get(key, math.inf))
                prim_m = m is not None and "omega_sign" in m      # an escape ends when its threat has cleared
                cleared = prim_m and t > m["t_cpa_pred_s"] and dist > params.alert_factor * S
                if (not sensed and not prim_m) or cleared:
                    if m is not None:
                        m["t_end_s"] = t
                        del engaged_uav[i][key]
                    continue
                if m is None:
                    tc, dcpa = _cpa(pj - pos[i], vj - vel[i])
                    if (0.0 < tc <= params.horizon_s and dcpa < params.alert_factor * S) or dist < params.alert_factor * S:
                        m = {"agent": agents[i].id, "kind": "right", "threat": key, "t_start_s": t, "t_end_s": math.inf,
                             "t_cpa_s": t + tc, "d_cpa_m": dcpa, "distance_m": dist, "feasible": True}
                        if j < 0:             # non-cooperative: the escape that keeps the most separation
                            tr = next(x for x in intruders if x.id == key)
                            m.update(_choose_escape(pos[i], psi[i], airspeed(i, pos[i, 2]), winds[i], t, tr, S,
                                                    params, gam_u[i], gam_d[i], tanb[i], cosg[i], floor_at))
                        engaged_uav[i][key] = m
                        manoeuvres.append(m)
            prim = next((m for m in engaged_uav[i].values() if "omega_sign" in m), None)
            if engaged_uav[i] and prim is None:       # UAVs of the fleet: rules of the air, both turn right
                tg = ch.tangent(min(s[i] + L, ch.length))
                carrot = carrot + params.avoid_offset_m * np.array([tg[1], -tg[0], 0.0])
                mode = "right"
            # ---- altitude command
            z_cmd = float(ch.at(s[i] + V * 2.0)[2])
            for o in obstacles:
                if t < o.t_s:
                    continue
                d = float(prism_distance_m(o, pos[i])[0])
                m = engaged_obs[i].get(o.id)
                if d > params.obstacle_range_m:
                    if m is not None:
                        m["t_end_s"] = t
                        del engaged_obs[i][o.id]
                    continue
                if m is None:
                    ahead = ch.segment(s[i], s[i] + params.obstacle_range_m + L)
                    buf = radius[i] + params.d_c_m + params.track_tol_m
                    dxy = _poly_dist_xy(np.asarray(o.polygon_xy, float), np.vstack([ahead[:, :2], pos[i, :2]]))
                    if np.any(dxy <= buf):
                        need = o.z_top_m + radius[i] + params.d_c_m - pos[i, 2]
                        dxy_now = float(_poly_dist_xy(np.asarray(o.polygon_xy, float), pos[i:i + 1, :2])[0])
                        v_gh0 = math.hypot(V * math.cos(psi[i]) + winds[i, 0], V * math.sin(psi[i]) + winds[i, 1])
                        grad = (1 - 1e-3) * math.tan(gam_u[i]) * min(V * math.cos(gam_u[i]), v_gh0) / v_gh0
                        ok = need <= max(dxy_now - radius[i], 0.0) * grad
                        m = {"agent": agents[i].id, "kind": "climb", "threat": o.id, "t_start_s": t,
                             "t_end_s": math.inf, "t_cpa_s": math.nan, "d_cpa_m": dxy_now, "distance_m": d,
                             "feasible": bool(ok), "climb_m": float(need)}
                        engaged_obs[i][o.id] = m
                        manoeuvres.append(m)
                        if not ok:
                            warnings.append(f"{agents[i].id}: obstacle {o.id} sensed {dxy_now:.0f} m away needs a climb "
                                            f"of {need:.0f} m, more than the climb angle "
                                            f"{veh[i].max_climb_angle_deg:g} deg allows over the ground "
                                            f"(gradient {grad:.3f}): raise obstacle_range_m")
                if o.id in engaged_obs[i]:
                    z_cmd = max(z_cmd, z_over[o.id] + radius[i] + params.d_c_m)
                    mode = "climb" if mode == "strategic" else mode
            # ---- heading command towards the carrot (wind correction angle)
            d_xy = carrot[:2] - pos[i, :2]
            chi = math.atan2(d_xy[1], d_xy[0])
            V_h_nom = V * math.cos(gam_u[i])
            w = winds[i]
            w_perp = -w[0] * math.sin(chi) + w[1] * math.cos(chi)
            psi_d = chi - math.asin(max(-0.99, min(0.99, w_perp / V_h_nom)))
            om_max = (1 - 1e-3) * G0 * tanb[i] * cosg[i] / V
            om = max(-om_max, min(om_max, _wrap(psi_d - psi[i]) / 1.0))
            # ---- terrain guard along the ground course
            if floor_at is not None and params.terrain_lookahead_m > 0:
                if k_step % SLOW_EVERY == 1 or i not in guard:
                    e = np.array([math.cos(chi), math.sin(chi)])
                    dd = np.arange(0.0, params.terrain_lookahead_m + 1e-9, 30.0)
                    fl = np.asarray(floor_at(pos[i, 0] + dd * e[0], pos[i, 1] + dd * e[1]), float)
                    fl = np.where(np.isfinite(fl), fl, -np.inf)
                    # held until the next check: the floor ahead counted 30 m closer than it is
                    guard[i] = float(np.max(fl - np.maximum(dd - 30.0, 0.0) * 0.9 * math.tan(gam_u[i])))
                z_cmd = max(z_cmd, guard[i])
            v_gh = math.hypot(V_h_nom * math.cos(psi[i]) + w[0], V_h_nom * math.sin(psi[i]) + w[1])
            h_up = (1 - 1e-3) * math.tan(gam_u[i]) * min(V * math.cos(gam_u[i]), v_gh)
            h_dn = (1 - 1e-3) * math.tan(gam_d[i]) * min(V * math.cos(gam_d[i]), v_gh)
            hdot = max(-h_dn, min(h_up, (z_cmd - pos[i, 2]) / 2.0))
            if prim is not None:                       # the chosen escape, flown as it was predicted
                om = 0.0
                if prim["turned_rad"] < prim["turn_limit_rad"]:
                    om = prim["omega_sign"] * om_max
                    prim["turned_rad"] += om_max * dt
                if prim["hdot_sign"] > 0:
                    hdot = h_up
                elif prim["hdot_sign"] < 0:
                    hdot = -h_dn
                    if floor_at is not None and i in guard:   # the terrain guard has the last word
                        hdot = max(hdot, min(h_up, (guard[i] - pos[i, 2]) / 2.0))
                else:
                    hdot = 0.0 if mode != "climb" else hdot
                mode = prim["kind"] if mode == "strategic" or prim["kind"] != "climb" else mode
            # ---- log the state at t, then integrate one tick exactly
            lg = logs[i]
            lg["t"].append(t)
            lg["p"].append(pos[i].copy())
            lg["psi"].append(psi[i])
            lg["v"].append(math.hypot(vel[i, 0], vel[i, 1]))
            lg["mode"].append(mode)
            Vh = math.sqrt(max(V * V - hdot * hdot, 0.0))
            if abs(om) < 1e-12:
                dx, dy = Vh * math.cos(psi[i]) * dt, Vh * math.sin(psi[i]) * dt
            else:
                dx = Vh / om * (math.sin(psi[i] + om * dt) - math.sin(psi[i]))
                dy = -Vh / om * (math.cos(psi[i] + om * dt) - math.cos(psi[i]))
            new_pos[i] = pos[i] + np.array([dx + w[0] * dt, dy + w[1] * dt, hdot * dt])
            hdot_prev[i] = hdot
            new_psi[i] = psi[i] + om * dt
        pos, psi = new_pos, new_psi
        t = t_first + k_step * dt
    res_t, res_p, res_psi, res_v, res_m = [], [], [], [], []
    energy, planned_energy = np.zeros(n), np.zeros(n)
    for i in range(n):
        lg = logs[i]
        tt = np.asarray(lg["t"], float)
        pp = np.asarray(lg["p"], float).reshape(-1, 3)
        if math.isfinite(arrived[i]):          # the arrival state
            tt = np.r_[tt, arrived[i]] if (not tt.size or arrived[i] > tt[-1]) else tt
            if pp.shape[0] < tt.size:
                pp = np.vstack([pp, pos[i]])
        res_t.append(tt)
        res_p.append(pp[:tt.size])
        res_psi.append(np.r_[np.asarray(lg["psi"], float), psi[i]][:tt.size])
        res_v.append(np.r_[np.asarray(lg["v"], float), lg["v"][-1] if lg["v"] else 0.0][:tt.size])
        res_m.append(np.array((lg["mode"] + ["strategic"])[:tt.size], dtype=object))
        energy[i] = _energy(res_p[i], wind_at, veh[i])
        planned_energy[i] = _energy(np.asarray(agents[i].plan_xyz_m, float), wind_at, veh[i])
        if not math.isfinite(arrived[i]):
            warnings.append(f"{agents[i].id}: did not reach the end of its plan by t = {t_stop:.0f} s")
    out = LocalResult([a.id for a in agents], res_t, res_p, res_psi, res_v, res_m, arrived, t_end_plan, energy,
                      planned_energy, radius, params, manoeuvres, warnings)
    out.baseline_arrived_s, out.baseline_energy_J = arrived.copy(), energy.copy()
    if baseline and (n > 1 or obstacles or intruders):
        for i in range(n):
            b = simulate_local([agents[i]], params=params, wind_at=wind_at, floor_at=floor_at, baseline=False)
            out.baseline_arrived_s[i], out.baseline_energy_J[i] = b.arrived_s[0], b.energy_J[0]
    out.compute_s = time.perf_counter() - t_wall
    return out


def brute_force_min_separation(result: LocalResult, tracks: Sequence[LocalTrack] = (), step_s: float = 0.05
                               ) -> list[dict]:
    """Minimum distance [m] of every pair (agent-agent, agent-intruder) every ``step_s`` [s]
    (linear between the flown samples; an agent counts from its start to its arrival) with
    the threshold ``S = r_i + r_j + d_c``: dicts ``a``, ``b``, ``min_distance_m``, ``t_s``,
    ``threshold_m``, ``lost`` (bool)."""
    out = []
    items = [(result.ids[i], result.t_s[i], result.xyz_m[i], float(result.radius_m[i])) for i in range(len(result.ids))]
    tr_items = [(tr.id, np.asarray(tr.t_s, float), np.asarray(tr.xyz_m, float), float(tr.radius_m)) for tr in tracks]
    for ia, (ida, ta, xa, ra) in enumerate(items):
        for idb, tb, xb, rb in items[ia + 1:] + tr_items:
            lo, hi = max(ta[0], tb[0]), min(ta[-1], tb[-1])
            S = separation_threshold_m(ra, rb, result.params.d_c_m)
            if not hi >= lo:
                out.append({"a": ida, "b": idb, "min_distance_m": math.inf, "t_s": math.nan, "threshold_m": S,
                            "lost": False})
                continue
            tq = np.arange(lo, hi + 1e-12, step_s)
            pa = np.column_stack([np.interp(tq, ta, xa[:, k]) for k in range(3)])
            pb = np.column_stack([np.interp(tq, tb, xb[:, k]) for k in range(3)])
            d = np.linalg.norm(pa - pb, axis=1)
            k = int(np.argmin(d))
            out.append({"a": ida, "b": idb, "min_distance_m": float(d[k]), "t_s": float(tq[k]), "threshold_m": S,
                        "lost": bool(d[k] < S)})
    return out


def fly_fixedwing_fleet(problems: Sequence, *, planner: str = "eeastar", start_times_s: Sequence[float] | None = None,
                        ids: Sequence[str] | None = None, params: LocalPlannerParams = LocalPlannerParams(),
                        obstacles: Sequence[StaticObstacle] = (), step_cells: int = 4,
                        corridor_m: float | None = None, meet_at_xy=None) -> tuple[LocalResult, list]:
    """Seed 002 section 4.4: each UAV of ``problems``
    (:class:`~skyroute.stages.planning.problem.PlanningProblem`, one per UAV, same maps) plans
    its own path with ``planner`` (:func:`~skyroute.stages.planning.fixedwing.plan_fixedwing`,
    written plan :func:`~skyroute.stages.planning.fixedwing.fixedwing_candidate`), then all
    fly together with the local planner (:func:`simulate_local`: the wind and floor of the
    first problem).  ``start_times_s`` [s]: take-off of each UAV (default 0); with
    ``meet_at_xy`` (x, y) [m] instead, the take-offs are chosen so that every plan passes its
    point closest to ``meet_at_xy`` at the same time (the latest take-off is 0): a worst case
    for crossing routes.  Returns the simulation and the candidates.  InputError when a UAV
    has no flyable plan."""
    from skyroute.stages.planning.fixedwing import fixedwing_candidate, plan_fixedwing
    from skyroute.stages.planning.step3 import wind_sampler

    n = len(problems)
    ids = list(ids) if ids is not None else [f"uav-{k + 1}" for k in range(n)]
    starts = list(start_times_s) if start_times_s is not None else [0.0] * n
    if len(ids) != n or len(starts) != n:
        raise InputError(f"{n} problems need {n} ids and start times, got {len(ids)} and {len(starts)}")
    agents, cands = [], []
    for pr, ident in zip(problems, ids, strict=True):
        res = plan_fixedwing(pr, planner, step_cells=step_cells, corridor_m=corridor_m)
        cand = fixedwing_candidate(pr, res, label=ident)
        if not res.solved or not cand.flyable:
            raise InputError(f"UAV {ident}: no flyable {planner} plan ({res.reason or '; '.join(cand.reasons)})")
        cands.append(cand)
    if meet_at_xy is not None:
        t_meet = [float(c.t_s[int(np.argmin(np.linalg.norm(np.asarray(c.xyz_m)[:, :2] - np.asarray(meet_at_xy, float),
                                                             axis=1)))]) for c in cands]
        starts = [max(t_meet) - tm for tm in t_meet]
    for cand, pr, ident, t0 in zip(cands, problems, ids, starts, strict=True):
        agents.append(LocalAgent(ident, np.asarray(cand.t_s, float) + float(t0), np.asarray(cand.xyz_m, float),
                                 pr.vehicle))
    pr0 = problems[0]
    sim = simulate_local(agents, obstacles=obstacles, params=params, wind_at=wind_sampler(pr0),
                         floor_at=floor_sampler(pr0))
    return sim, cands


def floor_sampler(problem) -> Callable:
    """``floor_at(x, y) -> (m,)``: the lowest admissible altitude [m] of ``problem``'s floor
    raster at map points (NaN outside the grid), the terrain guard of :func:`simulate_local`."""
    g = problem.grid

    def floor_at(x, y):
        r, c = g.index_of(np.asarray(x, float), np.asarray(y, float))
        ok = (r >= 0) & (r < g.ny) & (c >= 0) & (c < g.nx)
        return np.where(ok, problem.floor_m[np.clip(r, 0, g.ny - 1), np.clip(c, 0, g.nx - 1)], np.nan)

    return floor_at


def obstacle_clearance_m(result: LocalResult, obstacles: Sequence[StaticObstacle], agent: int = 0,
                         step_s: float = 0.05) -> dict[str, float]:
    """Minimum 3-D distance [m] of ``agent``'s flown trajectory (linear between samples, every
    ``step_s`` [s]) to each obstacle's prism while it exists, by brute force."""
    t, x = result.t_s[agent], result.xyz_m[agent]
    out = {}
    for o in obstacles:
        tq = np.arange(max(t[0], o.t_s), t[-1] + 1e-12, step_s)
        if tq.size == 0:
            out[o.id] = math.inf
            continue
        p = np.column_stack([np.interp(tq, t, x[:, k]) for k in range(3)])
        out[o.id] = float(prism_distance_m(o, p).min())
    return out


def local_flight_log(result: LocalResult, agent: int, *, scenario: str, crs_wkt: str, vertical_datum: str,
                     start_time_utc: str, planned_t_s, planned_xyz_m, obstacles: Sequence[StaticObstacle] = (),
                     tracks: Sequence = (), events: Sequence[dict] = (), seed: int = 0):
    """The :class:`~skyroute.stages.tactical.log.FlightLog` of one agent of a local-planner
    simulation (``skyroute fly`` outputs): flown parts per mode (``strategic`` / ``climb`` /
    ``right`` / ``left``), one ``tactical.csv`` row per manoeuvre (level ``climb``, ``right``
    or ``left``),
    ``tracks`` (:class:`~skyroute.stages.tactical.log.IntruderTrack`, the truth of the
    intruders), ``events`` (dicts as in the replay; their ``outcome`` is filled from the
    manoeuvres) and the ``local`` summary (ranges, threshold, delay, added energy, obstacle
    clearance)."""
    from skyroute.stages.tactical.log import FlightLog, FlownPart, LevelAttempt

    t, x, v, mode = result.t_s[agent], result.xyz_m[agent], result.speed_mps[agent], result.mode[agent]
    log = FlightLog(scenario, crs_wkt, vertical_datum, start_time_utc, np.asarray(planned_t_s, float),
                    np.asarray(planned_xyz_m, float))
    k0 = 0
    for k in range(1, len(t) + 1):
        if k == len(t) or mode[k] != mode[k0]:
            hi = min(k + 1, len(t))          # parts share their boundary sample
            if hi - k0 >= 2:
                log.parts.append(FlownPart(str(mode[k0]), t[k0:hi], x[k0:hi], v[k0:hi]))
            k0 = k
    ident = result.ids[agent]
    mine = [m for m in result.manoeuvres if m["agent"] == ident]
    for r, m in enumerate(mine):
        reason = "" if m["feasible"] else "sensed too late for the climb angle"
        uav = "omega_sign" in m or m["kind"] != "climb"
        t_coll = m["t_cpa_s"] - m["t_start_s"] if uav else math.nan
        ok = bool(m["feasible"]) and bool(m.get("keeps_separation", True))
        if "predicted_min_m" in m:
            opts = ", ".join(f"{k} {v:.1f} m" for k, v in m["options"].items())
            reason = (f"predicted minimum distance {m['predicted_min_m']:.1f} m (best of: {opts})"
                      + ("" if m["keeps_separation"] else "; UNAVOIDABLE: no manoeuvre keeps the separation"))
        log.attempts.append(LevelAttempt(r, f"{m['kind']} {m['threat']}", float(m["t_start_s"]), float(t_coll),
                                         m["kind"], ok, math.nan, math.nan, math.nan, math.nan, 0.0,
                                         0.0, math.nan, True, reason))
    evs = []
    for e in events:
        e = dict(e)
        hit = [m for m in mine if m["threat"] == e.get("id")]
        e["t_known_s"] = float(hit[0]["t_start_s"]) if hit else math.inf
        e["outcome"] = ({"climb": "climbed", "loiter": "loitered", "descend": "descended"}.get(
            hit[0]["kind"], f"turned {hit[0]['kind']}") if hit else "not a threat")
        evs.append(e)
    log.events = evs
    log.intruders = list(tracks)
    log.own_radius_m, log.margin_m = float(result.radius_m[agent]), float(result.params.d_c_m)
    log.tick_s, log.seed, log.method = result.params.tick_s, seed, "local"
    arrived = math.isfinite(result.arrived_s[agent])
    log.outcome = "goal" if arrived else "failed"
    log.reason = "" if arrived else f"did not reach the end of the plan by t = {t[-1]:.0f} s"
    log.energy_Wh = float(result.energy_J[agent]) / 3600.0
    log.losses = [{"intruder": m["threat"], "t_s": float(m["t_start_s"]), "predicted_min_m": m["predicted_min_m"],
                   "why": "no fixed-wing escape keeps the separation (the UAV is too fast or known too late)",
                   "options": m["options"]} for m in mine if not m.get("keeps_separation", True)]
    log.warnings = [w for w in result.warnings if w.startswith(f"{ident}:")]
    p = result.params
    clear = obstacle_clearance_m(result, obstacles, agent)
    log.local = {"obstacle_range_m": p.obstacle_range_m, "uav_range_m": p.uav_range_m, "d_c_m": p.d_c_m,
                 "avoid_offset_m": p.avoid_offset_m, "alert_factor": p.alert_factor, "horizon_s": p.horizon_s,
                 "r_p_m": float(result.radius_m[agent]),
                 "separation_threshold": "S = r_i + r_j + d_c",
                 "planned_end_s": float(result.planned_end_s[agent]), "arrived_s": float(result.arrived_s[agent]),
                 "undisturbed_arrived_s": float(result.baseline_arrived_s[agent]),
                 "delay_s": float(result.delay_s[agent]), "delay_vs_plan_s": float(result.delay_vs_plan_s[agent]),
                 "energy_Wh": float(result.energy_J[agent]) / 3600.0,
                 "planned_energy_Wh": float(result.planned_energy_J[agent]) / 3600.0,
                 "undisturbed_energy_Wh": float(result.baseline_energy_J[agent]) / 3600.0,
                 "added_energy_Wh": float(result.added_energy_J[agent]) / 3600.0,
                 "manoeuvres": [{k: (float(v) if isinstance(v, float) else v) for k, v in m.items()} for m in mine],
                 "obstacle_clearance_m": clear, "obstacles": [
                     {"id": o.id, "z_top_m": float(o.z_top_m), "t_s": float(o.t_s),
                      "polygon_xy": np.asarray(o.polygon_xy, float).round(3).tolist()} for o in obstacles]}
    return log
