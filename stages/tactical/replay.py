"""Tactical flight replay (seed 001 section 3.2): events, conflict checks, levels 1-3, landing.

The vehicle flies the strategic plan in simulated time.  At each event (in the order the
ownship learns of them) the knowledge is updated -- intruder tracks, temporary no-fly zones,
and the maps (wind, GNSS coverage, new obstacles: ``world_at(t)`` recomputes them through the
same cached stages) -- and the rest of the plan is checked from the event time ``t_e``:

* separation from every known intruder (exact, :func:`~skyroute.stages.tactical.conflict.first_conflict`,
  distance at equal times >= r_p + r_i + d_c),
* the static bounds of the current maps (clearance and GNSS coverage floors, AGL limits,
  no-fly cells: ``PlanningProblem.state_valid``), active temporary no-fly zones (polygon
  widened by r_p, altitude band widened by r_p), and the airspeed limit in the current wind.

The first violation at ``t_v`` gives ``t_coll = t_v - t_e``.  If ``t_coll <= t_rep`` the
vehicle lands at once (contingency).  Otherwise a replanning takes effect at
``t_eff = t_e + t_rep`` (the end of the fillet arc the vehicle is on, if it is on one): the
vehicle keeps flying the plan until then, whatever the compute time, and the new plan starts
there with the vehicle's velocity (:func:`~skyroute.stages.smoothing.corner_trajectory` with
``v_start_mps``).  Three levels are tried, each deterministic (iteration counts, seeded RNG):

1. **time scaling** (intruder conflicts in a non-frontal geometry, and temporary no-fly zones):
   the same chain (:func:`~skyroute.stages.tactical.timeline.chain_of`), its legs up to the
   encounter flown at ``s`` times their speed for ``s`` in ``time_scaling_factors`` (largest
   first); the first ``s`` that gives a valid plan is the level's solution;
2. **local RRT informed by the strategic path**: STEP II's RRT
   (:func:`~skyroute.stages.planning.deconflict.deconflict`) grown from the braking point ``P_b``
   along the rest of the plan's chain, against the known traffic (occupancy maps of slices of
   ``occupancy_slice_s``) and the current static bounds;
3. **global RRT** from ``P_b`` to the goal, informed only by the straight line to the goal.

``P_b`` is the point of the current plan a braking distance ``v^2 / (2 a_max)`` after
``t_eff``: the vehicle stops there (a forced stop corner), so the new chain may turn sharply.  Every
solution goes through the same STEP III (:func:`~skyroute.stages.planning.step3.step3`:
corner smoothing, retiming within the hard limits, navigation error, eq. 15 costs with the
tactical weights ``(w_l, 0, 0, w_e)`` -- seed 001 drops the risk and landing terms -- and the
independent validator) with the energy left in the battery, and an exact separation check
against every known intruder.  The valid solution with minimum f replaces the rest of the
plan.  When none is valid the vehicle lands: the nearest landing site (environment stage)
reachable with the energy left over a valid path (STEP I A* + STEP II + STEP III) to the
approach point ``r_p`` above it.

Randomness: intruder report noise and the RRTs come from ``np.random.default_rng(seed)``
streams, so a seed gives one result on any machine.
"""

from __future__ import annotations

import dataclasses
import heapq
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import xarray as xr

from skyroute.stages import control
from skyroute.stages.base import InputError, PlanningError
from skyroute.stages.planning.deconflict import Step2Result, deconflict
from skyroute.stages.planning.problem import PlanningProblem, build_problem
from skyroute.stages.planning.step1 import plan_step1
from skyroute.stages.planning.step3 import (
    Candidate,
    flight_power_W,
    smooth_chain,
    step3,
    wind_sampler,
)
from skyroute.stages.smoothing import KinematicLimits
from skyroute.stages.tactical.conflict import IntruderTracks, first_conflict
from skyroute.stages.tactical.daa import alert_of
from skyroute.stages.tactical.events import TacticalEvent, event_record, first_in_zone
from skyroute.stages.tactical.log import (
    FlightLog,
    FlownPart,
    IntruderTrack,
    LevelAttempt,
    NoFlyZone,
)
from skyroute.stages.tactical.params import _NO_REQUEST, TACTICAL_METHODS, FlyParams  # noqa: F401  (re-exported)
from skyroute.stages.tactical.timeline import Segment, Timeline, along, chain_of, line_phase_at
from skyroute.stages.traffic import Intruder, build_occupancy
from skyroute.stages.vehicle import VehicleProfile

__all__ = ["TACTICAL_METHODS", "FlyParams", "TacticalEvent", "World", "encounter_geometry", "replay"]

STRATEGIC_SAMPLE_DT_S = 0.5   # [s] the strategic STEP III's sampling (step3's default): the filter's epochs
FRONTAL_DEG = 135.0        # encounter angle above which the geometry is frontal (level 1 refused)
STATIC_INTRUDER_MPS = 0.5  # an intruder slower than this is treated as static (level 1 refused)


@dataclass
class World:
    """The maps the ownship knows at some time (pipeline stage outputs, loaded)."""

    surface: xr.Dataset
    environment: xr.Dataset | None
    clearance: xr.Dataset
    wind: xr.Dataset | None
    coverage: xr.Dataset | None
    satellites: xr.Dataset | None
    los_cache: dict = field(default_factory=dict)   # visibility heights per sky epoch (STEP III)
    problems: dict = field(default_factory=dict)    # planning problems built on these maps
    # the float64 rasters build_problem derives from these maps, shared by all those problems
    # (``build_problem(shared=)``: the same problems; a city's window holds 46 M cells, 370 MB a raster)
    derived: dict = field(default_factory=dict)

    def layer(self, dataset: str, name: str) -> xr.DataArray | None:
        """``getattr(self, dataset)[name]`` as one object per world (``build_problem(shared=)``
        keys on the objects it is given), None when the dataset is absent."""
        ds = getattr(self, dataset)
        if ds is None:
            return None
        key = ("layer", dataset, name)
        if key not in self.derived:
            self.derived[key] = ds[name]
        return self.derived[key]


def encounter_geometry(own_velocity_mps, intruder_velocity_mps) -> tuple[str, float]:
    """``(kind, angle_deg)`` of an encounter from the two velocities (3,) [m/s]: the angle
    between the horizontal velocities; ``"frontal"`` above :data:`FRONTAL_DEG` (head-on: a
    change of speed along the path cannot separate the two), ``"static"`` for an intruder
    slower than :data:`STATIC_INTRUDER_MPS` (nor can it then), else ``"crossing"`` (or
    ``"overtaking"`` below 45 deg)."""
    vo = np.asarray(own_velocity_mps, float)[:2]
    vi = np.asarray(intruder_velocity_mps, float)[:2]
    if np.linalg.norm(vi) < STATIC_INTRUDER_MPS:
        return "static", float("nan")
    if np.linalg.norm(vo) < 1e-9:
        return "crossing", float("nan")
    c = float(np.dot(vo, vi) / (np.linalg.norm(vo) * np.linalg.norm(vi)))
    ang = math.degrees(math.acos(min(max(c, -1.0), 1.0)))
    if ang > FRONTAL_DEG:
        return "frontal", ang
    return ("overtaking" if ang < 45.0 else "crossing"), ang


# ------------------------------------------------------------------ knowledge


@dataclass
class _Known:
    """What the ownship knows: believed intruder tracks, truth, zones."""

    believed: dict[str, Intruder] = field(default_factory=dict)
    truth: dict[str, IntruderTrack] = field(default_factory=dict)
    zones: list[NoFlyZone] = field(default_factory=list)

    def intruders(self) -> list[Intruder]:
        return list(self.believed.values())


def _noisy(intr: Intruder, sigma_m: float, rng: np.random.Generator) -> Intruder:
    if sigma_m <= 0:
        return intr
    return Intruder(intr.id, intr.times_s, intr.xyz_m + rng.normal(0.0, sigma_m, intr.xyz_m.shape), intr.radius_m)


def _truth_update(old: IntruderTrack, new: Intruder, t_upd: float) -> IntruderTrack:
    """The old track until ``t_upd``, the new one from then (the latest declared track)."""
    keep = old.t_s < t_upd - 1e-3
    ts = [old.t_s[keep]]
    ps = [old.xyz_m[keep]]
    if old.t_s[0] < t_upd - 1e-3 < old.t_s[-1]:
        ts.append(np.array([t_upd - 1e-3]))
        ps.append(np.array([[np.interp(t_upd - 1e-3, old.t_s, old.xyz_m[:, k]) for k in range(3)]]))
    later = new.times_s >= t_upd
    if new.times_s[0] < t_upd < new.times_s[-1]:
        ts.append(np.array([t_upd]))
        ps.append(np.array([[np.interp(t_upd, new.times_s, new.xyz_m[:, k]) for k in range(3)]]))
        later = new.times_s > t_upd
    ts.append(new.times_s[later])
    ps.append(new.xyz_m[later])
    t = np.concatenate(ts)
    p = np.concatenate(ps)
    return IntruderTrack(old.id, new.radius_m, t, p, old.kind, old.known_from_s,
                         [*old.declared, (t_upd, new.times_s.copy(), new.xyz_m.copy())])


# ------------------------------------------------------------------ the replay


class _Replay:
    def __init__(self, timeline: Timeline, goal_xyz, world: World, world_at, events, strategic_intruders,
                 vehicle: VehicleProfile, params: FlyParams, start_time_utc, dop_threshold):
        self.tl = timeline
        self.goal = np.asarray(goal_xyz, float)
        self.world = world
        self.world_at = world_at
        self.veh = vehicle
        self.p = params
        self.events = sorted(events, key=lambda e: (self._known_at(e), e.t_s))
        self.start_time_utc = start_time_utc
        self.dop = dop_threshold
        self.lim = KinematicLimits.of(vehicle)
        self.known = _Known()
        self.rng_noise = np.random.default_rng([params.seed, 1])
        for it in strategic_intruders:
            self.known.believed[it.id] = it
            self.known.truth[it.id] = IntruderTrack(it.id, it.radius_m, it.times_s, it.xyz_m, "strategic", 0.0,
                                                    [(0.0, it.times_s, it.xyz_m)])
        self.attempts: list[LevelAttempt] = []
        self.event_log: list[dict] = []
        self.on_progress: Callable[[float, float], None] | None = None   # (t_s, t_end_s) per event
        self.n_replan = 0
        self.outcome, self.reason = "goal", ""
        self.warnings: list[str] = []
        self._zone_masks: dict[str, np.ndarray] = {}
        self._grid_obj = None
        from skyroute.stages.tactical.octant_replan import OctantZones

        self.octant = OctantZones()           # the octant method's zones and their potential field
        from skyroute.stages.tactical.escape import Escapes

        self.escapes = Escapes()              # the escape of last resort, its decisions and accepted losses
        self._queue: list = []                # pending events (known time, event time, order, event)
        self._seq = 0

    def _known_at(self, ev: TacticalEvent) -> float:
        lat = self.p.report_latency_s if ev.kind in ("intruder", "intruder_update") else 0.0
        return ev.t_s + lat

    # -------------------------------------------------------------- maps -> problem
    def problem(self, start, goal, *, gnss: bool = True, zones_from_s: float = 0.0) -> PlanningProblem:
        """The planning problem on the current maps: tactical weights, temporary no-fly zones
        active at or after ``zones_from_s`` as no-fly cells (all altitudes: conservative).
        Built once per maps, zones and GNSS flag; only the endpoints change between calls."""
        zkey = tuple((z.id, tuple(z.polygon_xy.ravel())) for z in self.known.zones if z.end_s > zones_from_s)
        key = (zkey, gnss, self.dop, self.p.weights, self.p.min_agl_m, self.p.max_agl_m, self.p.dop_kind, self.veh.name)
        base = self.world.problems.get(key)
        if base is None:
            base = self.world.problems[key] = self._build_problem(start, goal, gnss, zones_from_s)
            return base
        return dataclasses.replace(base, start_xyz=tuple(map(float, start)), goal_xyz=tuple(map(float, goal)))

    def _build_problem(self, start, goal, gnss: bool, zones_from_s: float) -> PlanningProblem:
        w = self.world
        surf = w.surface
        clear = w.layer("clearance", "min_altitude_m")
        nofly = w.clearance["nofly"].values.astype(bool) if "nofly" in w.clearance else None
        zmask = self._zone_mask(zones_from_s)
        if zmask is not None:
            nofly = zmask if nofly is None else (nofly | zmask)
        floor_j = None
        if gnss and w.coverage is not None and self.dop is not None:
            floor_j = w.coverage["coverage_floor"].sel(threshold=self.dop)
        risk = w.layer("environment", "risk_cost")
        land = w.layer("environment", "landing_cost")
        wl, _wr, _wd, we = self.p.weights
        if wl == 0 and we == 0:
            wl = 1.0
        return build_problem(surf, clear, floor_j, risk, land, w.wind, self.veh, (wl, 0.0, 0.0, we),
                             tuple(start), tuple(goal), self.p.min_agl_m, self.p.max_agl_m, self.dop,
                             dop_kind=self.p.dop_kind, nofly=nofly, check_endpoints=False, shared=w.derived)

    def _zone_mask(self, t_from_s: float) -> np.ndarray | None:
        zones = [z for z in self.known.zones if z.end_s > t_from_s]
        if not zones:
            return None
        g = self.grid()
        m = np.zeros(g.shape, bool)
        for z in zones:
            zm = self._zone_masks.get(z.id)
            if zm is None:
                zm = self._zone_masks[z.id] = self._one_zone_mask(z, g)
            m |= zm
        return m

    def _one_zone_mask(self, z: NoFlyZone, g) -> np.ndarray:
        """Cells whose closed square meets the zone polygon widened by r_p."""
        from shapely.geometry import Polygon, box

        m = np.zeros(g.shape, bool)
        r = self.veh.r_p_m
        poly = Polygon(z.polygon_xy).buffer(r)
        x0, y0, x1, y1 = poly.bounds
        c0, c1 = int(np.floor((x0 - g.x0) / g.resolution_m)), int(np.floor((x1 - g.x0) / g.resolution_m))
        r0, r1 = int(np.floor((g.y1 - y1) / g.resolution_m)), int(np.floor((g.y1 - y0) / g.resolution_m))
        for rr in range(max(r0, 0), min(r1, g.ny - 1) + 1):
            for cc in range(max(c0, 0), min(c1, g.nx - 1) + 1):
                xa = g.x0 + cc * g.resolution_m
                ya = g.y1 - (rr + 1) * g.resolution_m
                if poly.intersects(box(xa, ya, xa + g.resolution_m, ya + g.resolution_m)):
                    m[rr, cc] = True
        return m

    def grid(self):
        if self._grid_obj is None:
            from skyroute.stages.grid import Grid

            self._grid_obj = Grid.from_dataarray(self.world.surface["terrain"])
        return self._grid_obj

    # -------------------------------------------------------------- checks
    def tracks(self, buffer_m: float = 0.0) -> tuple[IntruderTracks, np.ndarray]:
        """The known intruders' believed tracks and the separation [m] from each, r_p + r_i + d_c
        (+ ``buffer_m``)."""
        intr = self.known.intruders()
        sep = np.array([self.veh.r_p_m + i.radius_m + self.p.d_c_m + buffer_m for i in intr])
        return IntruderTracks.from_intruders(intr), sep

    def chord_buffer_m(self, t_s: np.ndarray) -> float:
        """How far [m] the exact trajectory can be from the chords between its samples ``t_s``:
        a_max dt^2 / 8 for the longest gap dt (every phase of a corner trajectory accelerates at
        most a_max, tangentially or normally), so separation checks on the sampled polyline
        hold for the trajectory itself."""
        if t_s.size < 2:
            return 0.0
        dt = float(np.max(np.diff(t_s)))
        return self.lim.max_acceleration_mps2 * dt * dt / 8.0 + 1e-6

    def first_violation(self, t_s: np.ndarray, p: np.ndarray, problem: PlanningProblem) -> tuple[float, str, object]:
        """Earliest violation ``(t [s], cause, detail)`` of a timed path; ``(inf, '', None)``."""
        best = (math.inf, "", None)
        if t_s.size < 2:
            return best
        intr = self.known.intruders()
        if intr:
            tracks, sep = self.tracks()
            c = first_conflict(t_s, p, tracks, sep)
            if c is not None and c.t_s < best[0]:
                best = (c.t_s, f"separation from intruder {c.id!r} below {sep[c.index]:g} m "
                               f"(closest {c.distance_m:.1f} m at t = {c.t_cpa_s:.1f} s)", c)
        ok = np.asarray(problem.state_valid(p), bool)
        if not ok.all():
            k = int(np.argmin(ok))
            if t_s[k] < best[0]:
                best = (float(t_s[k]), f"static bounds at t = {t_s[k]:.1f} s: {problem.explain_invalid(p[k])}", None)
        for z in self.known.zones:
            k = first_in_zone(t_s, p, z, self.veh.r_p_m)
            if k >= 0 and t_s[k] < best[0]:
                best = (float(t_s[k]), f"inside the temporary no-fly zone {z.id!r} at t = {t_s[k]:.1f} s", z)
        v = np.gradient(p, t_s, axis=0) if t_s.size > 2 else np.diff(p, axis=0) / np.diff(t_s)[:, None]
        if v.shape[0] == p.shape[0]:
            air = np.linalg.norm(v - wind_sampler(problem)(p), axis=1)
            bad = air > self.veh.max_airspeed_mps + 1e-6
            if bad.any():
                k = int(np.argmax(bad))
                if t_s[k] < best[0]:
                    best = (float(t_s[k]), f"airspeed {air[k]:.1f} m/s above {self.veh.max_airspeed_mps} m/s in the "
                                           f"new wind at t = {t_s[k]:.1f} s", None)
        return best

    # -------------------------------------------------------------- energy
    def energy_J(self, t_s: np.ndarray, p: np.ndarray, problem: PlanningProblem) -> float:
        """Energy [J] of a timed path: rotor power at the airspeed (current wind), trapezoid."""
        if t_s.size < 2:
            return 0.0
        v = np.gradient(p, t_s, axis=0)
        return float(np.trapezoid(flight_power_W(v, wind_sampler(problem)(p), self.veh), t_s))

    # -------------------------------------------------------------- the loop
    def push(self, ev: TacticalEvent, t_known_s: float) -> None:
        """Queue an event the ownship learns of at ``t_known_s`` [s]."""
        heapq.heappush(self._queue, (float(t_known_s), float(ev.t_s), self._seq, ev))
        self._seq += 1

    def run(self) -> None:
        p = self.p
        for ev in self.events:
            self.push(ev, self._known_at(ev))
        while self._queue:
            t_e, _t, _n, ev = heapq.heappop(self._queue)
            control.check()
            if ev.kind == "resume":
                if not self.escapes.resume(self, ev, t_e):
                    return
                continue
            if self.on_progress is not None:
                self.on_progress(min(t_e, self.tl.t_end_s), self.tl.t_end_s)
            if t_e >= self.tl.t_end_s:
                self.event_log.append(event_record(ev, t_e, math.inf, "after the flight ended"))
                continue
            t0 = time.perf_counter()
            batch = [ev]
            while self._queue and self._queue[0][0] <= t_e + 1e-9 and self._queue[0][3].kind != "resume":
                batch.append(heapq.heappop(self._queue)[3])   # known together before the plan is checked
            for e in batch:
                self.apply(e, t_e)
                if p.method == "octant" and e.kind in ("intruder", "intruder_update"):
                    from skyroute.stages.tactical.octant_replan import update_zones

                    update_zones(self, t_e)
            for e in batch[1:]:
                self.event_log.append(event_record(e, t_e, math.inf, f"known with {ev.label}"))
            update_s = time.perf_counter() - t0
            t_s, pts = self.rest_samples(t_e)
            prob = self.problem(self.tl.sample(t_e), self.goal, zones_from_s=math.inf)   # zones: checked in time
            t_v, cause, detail = self.first_violation(t_s, pts, prob)
            if not math.isfinite(t_v):
                self.event_log.append(event_record(ev, t_e, math.inf, "no conflict"))
                continue
            t_coll = t_v - t_e
            k = self.n_replan
            self.n_replan += 1
            alert = self.alert(t_s, pts, t_e, t_v, detail)
            intruder_conflict = hasattr(detail, "own_velocity_mps")
            if intruder_conflict:      # losses before any manoeuvre can act: declared, whatever resolves the rest
                for loss in self.escapes.committed(self, k, ev, t_e, self.effective_time(t_e + p.escape_latency_s)):
                    self.warnings.append(f"unavoidable loss of separation from intruder {loss['intruder']!r}: "
                                         f"{loss['why']} (margin {loss['predicted_margin_m']:+.1f} m)")
            if t_coll <= p.t_rep_s:
                why = f"t_coll {t_coll:.2f} s <= t_rep {p.t_rep_s:g} s ({cause})"
                ok, tried = self.land(k, ev, t_e, t_e, t_coll, update_s, why)
                outcome = "landing" if ok else self.escapes.last_resort(self, k, ev, t_e, t_e + p.escape_latency_s, t_coll,
                                                                 update_s, why, tried)
                self._tag(k, alert)
                self.event_log.append(event_record(ev, t_e, t_coll, outcome, cause))
                if outcome == "failed":
                    return
                continue
            t_eff = self.effective_time(t_e + p.t_rep_s)
            if (p.escape and intruder_conflict and t_eff < self.tl.t_end_s
                    and not self.escapes.available(self, t_eff)):
                # waiting t_rep for a plan would leave no escape that keeps the separation:
                # escape now (a reflex), replan from the hold
                t_now = self.effective_time(t_e + p.escape_latency_s)
                why = (f"no escape would keep the separation after waiting t_rep {p.t_rep_s:g} s for a plan "
                       f"({cause})")
                outcome = self.escapes.last_resort(self, k, ev, t_e, t_now, t_coll, update_s, why, "", reflex=True)
                self._tag(k, alert)
                self.event_log.append(event_record(ev, t_e, t_coll, outcome, cause))
                if outcome == "failed":
                    return
                continue
            if p.method == "octant" and intruder_conflict:
                from skyroute.stages.tactical.octant_replan import octant_replan

                best = octant_replan(self, k, ev, t_e, t_eff, t_v, t_coll, update_s, cause, detail)
            else:
                best = self.replan(k, ev, t_e, t_eff, t_coll, update_s, cause, detail)
            if best is None:
                why = f"no level found a valid plan ({cause})"
                ok, tried = self.land(k, ev, t_e, t_eff, t_coll, update_s, why)
                outcome = "landing" if ok else self.escapes.last_resort(self, k, ev, t_e, t_eff, t_coll, update_s, why, tried)
                self._tag(k, alert)
                self.event_log.append(event_record(ev, t_e, t_coll, outcome, cause))
                if outcome == "failed":
                    return
                continue
            self._tag(k, alert)
            self.event_log.append(event_record(ev, t_e, t_coll, f"replanned {best}", cause))

    def rest_samples(self, t_from: float) -> tuple[np.ndarray, np.ndarray]:
        """The plan from ``t_from`` [s] sampled every tick; a plan that ends in an escape's hold
        is checked as holding :data:`~skyroute.stages.tactical.escape.HOLD_LOOKAHEAD_S` longer
        (a hold ends only when a new plan replaces it)."""
        from skyroute.stages.tactical.escape import HOLD_LOOKAHEAD_S

        t_s, pts = self.tl.samples(t_from, self.p.tick_s)
        if t_s.size and self.tl.segments[-1].part == "escape":
            extra = t_s[-1] + np.arange(1, int(HOLD_LOOKAHEAD_S / self.p.tick_s) + 1) * self.p.tick_s
            t_s = np.concatenate([t_s, extra])
            pts = np.concatenate([pts, np.repeat(pts[-1:], extra.size, axis=0)])
        return t_s, pts

    # -------------------------------------------------------------- alerting
    def alert(self, t_s: np.ndarray, pts: np.ndarray, t_e: float, t_v: float, detail) -> dict:
        """The DAA alert (:mod:`.daa`, intent-based) of a conflict found at ``t_e``: the
        intruder, time to loss of separation and to the preventive volume [s], level."""
        if not hasattr(detail, "own_velocity_mps"):
            return {"intruder": "", "t_los_s": math.nan, "alert": ""}
        from skyroute.stages.tactical.daa import PREVENTIVE_FACTOR

        tracks, sep = self.tracks()
        sep_pre = sep * 0.0
        sep_pre[detail.index] = PREVENTIVE_FACTOR * sep[detail.index]
        c = first_conflict(t_s, pts, tracks, sep_pre)
        t_pre = (c.t_s - t_e) if c is not None else math.inf
        t_los = t_v - t_e
        return {"intruder": detail.id, "t_los_s": t_los, "alert": alert_of(t_los, t_pre)}

    def _tag(self, k: int, alert: dict) -> None:
        for a in self.attempts:
            if a.replanning == k:
                a.intruder, a.t_los_s, a.alert = alert["intruder"], alert["t_los_s"], alert["alert"]

    def apply(self, ev: TacticalEvent, t_e: float) -> None:
        if ev.kind == "intruder" or ev.kind == "intruder_update":
            it = ev.intruder
            assert it is not None
            self.known.believed[it.id] = _noisy(it, self.p.intruder_noise_m, self.rng_noise)
            if ev.kind == "intruder" or it.id not in self.known.truth:
                self.known.truth[it.id] = IntruderTrack(it.id, it.radius_m, it.times_s, it.xyz_m, "tactical", t_e,
                                                        [(ev.t_s, it.times_s, it.xyz_m)])
            else:
                self.known.truth[it.id] = _truth_update(self.known.truth[it.id], it, ev.t_s)
        elif ev.kind == "nofly":
            assert ev.zone is not None
            self.known.zones.append(ev.zone)
        elif ev.changes_maps:
            self.world = self.world_at(ev.t_s)
            self._grid_obj = None
            self.prepare_world()

    def prepare_world(self) -> None:
        """Compute the maps every level reads on the current world once, before the levels
        are timed (their cost is the replanning's ``update_s``): the line-of-sight heights of
        every sky epoch from take-off to an hour after the planned arrival, over the whole grid
        (:func:`~skyroute.stages.planning.step3.line_of_sight` with the world's cache), as many
        epochs as :data:`~skyroute.stages.sky_visibility.LOS_CACHE_MAX_BYTES` holds."""
        sky = self.world.satellites
        if sky is None:
            return
        from skyroute.stages.sky_visibility import line_of_sight, sky_times_s

        ts = sky_times_s(sky, self.start_time_utc)
        horizon = self.tl.t_end_s + 3600.0
        want = ts[(ts >= -120.0) & (ts <= horizon)]
        if want.size == 0:
            return
        prob = self.problem(self.goal, self.goal, zones_from_s=math.inf)
        pts = np.repeat(self.goal[None], want.size, axis=0)
        line_of_sight(prob, sky, self.world.surface["surface"].values, want, pts, self.start_time_utc,
                      cache=self.world.los_cache)

    def effective_time(self, t: float) -> float:
        """``t`` (capped at the end of the plan)."""
        return min(t, self.tl.t_end_s)

    def rest_chain(self, t_eff: float) -> tuple[np.ndarray, np.ndarray, int, float]:
        """The current plan's chain from its position at ``t_eff``: ``(vertices, leg speeds,
        number of leading vertices that are not the plan's own (0 or 1), speed at t_eff)``.
        The first leg is along the vehicle's velocity: on a line phase it is the rest of that
        line; on a fillet arc it is the tangent up to where it meets the next leg (the rest
        of the arc is that corner's fillet, which STEP III re-creates when there is room)."""
        seg = self.tl.segments[self.tl.active(t_eff)]
        tau = t_eff - seg.t0_s
        verts, speeds, leg_of = chain_of(seg.traj)
        i, line = line_phase_at(seg.traj, tau)
        leg = int(leg_of[i])
        p0 = seg.sample([t_eff])[0]
        vel = seg.velocity([t_eff])[0]
        v0 = float(np.linalg.norm(vel))
        if line or v0 < 1e-6:
            ch, sp = np.concatenate([p0[None], verts[leg + 1:]]), speeds[leg:]
            if seg.then_chain is not None:      # an escape's hold: the mission goes on from its end
                ch, sp = np.concatenate([ch, seg.then_chain[1:]]), np.concatenate([sp, seg.then_speeds])
            return ch, sp, 0, v0
        # on the fillet arc at the corner verts[leg] (between legs leg-1 and leg): the rest of the
        # arc is the fillet of the corner where the current tangent meets the next leg, at
        # R tan(phi_rem / 2) ahead (phi_rem: the arc angle left); the chain goes through it
        t1 = float(seg.traj.phase_t0_s[i + 1]) if i + 1 < seg.traj.phase_t0_s.size else float(seg.traj.duration_s)
        R = float(seg.traj.radius_m[i])
        phi = min(v0 * (t1 - tau) / R, math.pi * 0.99)
        v_rem = p0 + vel / v0 * (R * math.tan(phi / 2.0))
        ch = np.concatenate([p0[None], v_rem[None], verts[leg + 1:]])
        sp = np.concatenate([[max(v0, speeds[leg])], speeds[leg:]])
        if seg.then_chain is not None:
            ch, sp = np.concatenate([ch, seg.then_chain[1:]]), np.concatenate([sp, seg.then_speeds])
        return ch, sp, 1, v0

    def follow(self, cand: Candidate, t_eff: float, part: str, k: int | None, then=None) -> None:
        """Fly ``cand`` (its trajectory from ``t_eff`` [s]) as part ``part`` of replanning ``k``;
        ``then``: ``(chain, leg speeds)`` of the mission after it (an escape's hold)."""
        tc, ts = (None, None) if then is None else (np.asarray(then[0], float), np.asarray(then[1], float))
        self.tl.add(Segment(cand.trajectory, t_eff, part, k, nav=cand.nav_track, then_chain=tc, then_speeds=ts),
                    t_eff)

    def nav_state_at(self, t_s: float):
        """The navigation filter the vehicle has at ``t_s`` [s] (a
        :class:`~skyroute.stages.navigation.FilterState`), None without GNSS data."""
        nav = self.tl.segments[self.tl.active(t_s)].nav
        return None if nav is None else nav.state_at(t_s)

    def init_navigation(self) -> None:
        """The filter along the strategic plan as its STEP III computed it (same samples,
        warm-up and maps), so every replan continues it (issue 22)."""
        sky = self.world.satellites
        if sky is None:
            return
        from skyroute.stages.sky_visibility import navigation_along

        seg = self.tl.segments[0]
        tau = seg.traj.sample_times(STRATEGIC_SAMPLE_DT_S)
        prob = self.problem(self.goal, self.goal, zones_from_s=math.inf)
        *_, track = navigation_along(prob, sky, self.world.surface["surface"].values, seg.t0_s + tau,
                                     seg.traj.sample(tau), self.start_time_utc, self.veh, gnss_sigma_m=self.p.uere_m,
                                     los_cache=self.world.los_cache, return_track=True)
        self.tl.segments[0] = dataclasses.replace(seg, nav=track)

    def braking_point(self, chain: np.ndarray, v0: float, scale: float = 1.0) -> tuple[np.ndarray, int]:
        """The chain cut the braking distance v0^2 / (2 a_max) (plus 0.5 m) after its start,
        where the vehicle stops before turning onto the new chain (``stop_at``):
        ``(chain up to and including P_b, number of vertices before P_b)``."""
        d_b = scale * v0 * v0 / (2.0 * self.lim.max_acceleration_mps2) + 0.5
        legs = np.linalg.norm(np.diff(chain, axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(legs)])
        if d_b >= cum[-1]:
            return chain.copy(), chain.shape[0] - 1
        j = int(np.searchsorted(cum, d_b, side="right")) - 1
        if d_b - cum[j] < 1e-6:                      # P_b is a vertex of the chain
            return chain[: j + 1].copy(), j
        pb = chain[j] + (chain[j + 1] - chain[j]) * ((d_b - cum[j]) / legs[j])
        return np.concatenate([chain[: j + 1], pb[None]]), j + 1

    # -------------------------------------------------------------- levels
    def finish(self, problem: PlanningProblem, chain: np.ndarray, speeds: np.ndarray, t_eff: float, v0: float,
               label: str, budget_J: float, stop_at: tuple[int, ...] = (),
               hold_until_s: float | None = None, trajectory=None, min_hold_s: float = 1.0) -> Candidate:
        """STEP III of a tactical chain from ``t_eff`` at ``v0`` (the navigation filter continued
        from the vehicle's at ``t_eff``; ``hold_until_s``: hover at the end until then), then the
        exact separation check (on the samples, the separation grown by the chord buffer) and
        the temporary zones.  ``trajectory``: fly this corner trajectory instead of smoothing
        the chain (an escape's turn; ``chain`` is then its start and end)."""
        chain, speeds, lengths, stop_at = _dedupe(chain, speeds, stop_at)
        times = t_eff + np.concatenate([[0.0], np.cumsum(lengths / np.maximum(speeds, 1e-3))])
        s2 = Step2Result(chain, times, np.zeros(chain.shape[0]), "tactical")
        reserve = 100.0 * (1.0 - budget_J / self.veh.battery_energy_j)
        if not reserve < 100.0:
            raise PlanningError("no energy left in the battery")
        sky = self.world.satellites
        cand = step3(problem, s2, sky, self.world.surface["surface"].values, start_time_utc=self.start_time_utc,
                     label=label, gnss_sigma_m=self.p.uere_m, battery_reserve_pct=max(reserve, 0.0),
                     v_start_mps=v0, sample_dt_s=min(0.5, self.p.tick_s * 5), los_cache=self.world.los_cache,
                     stop_at=stop_at,
                     bubble=None if self.p.bubble is None else (*self.p.bubble, float(self.veh.r_p_m)),
                     nav_state=self.nav_state_at(t_eff), keep_nav_track=True, hold_until_s=hold_until_s,
                     trajectory=trajectory, min_hold_s=min_hold_s)
        if cand.t_s.size:
            c = (first_conflict(cand.t_s, cand.xyz_m, *self.tracks(self.chord_buffer_m(cand.t_s)))
                 if self.known.intruders() else None)
            if c is not None:
                cand.reasons.append(f"separation from intruder {c.id!r}: {c.distance_m:.1f} m at t = {c.t_cpa_s:.1f} s")
            for z in self.known.zones:
                k = first_in_zone(cand.t_s, cand.xyz_m, z, self.veh.r_p_m)
                if k >= 0:
                    cand.reasons.append(f"inside the temporary no-fly zone {z.id!r} at t = {cand.t_s[k]:.1f} s")
            cand.flyable = not cand.reasons
        return cand

    def _screen_l1(self, problem, chain, speeds, t_eff: float, v0: float) -> str:
        """Why a level-1 speed profile cannot work, from its corner trajectory alone (STEP
        III's smoothing) and the exact separation and zone checks; '' when it may (then the
        full STEP III and validator decide)."""
        chain, speeds, lengths, _ = _dedupe(chain, speeds)
        try:
            tr = smooth_chain(problem, chain, lengths / np.maximum(speeds, 1e-3), v_start_mps=v0)
        except PlanningError as exc:
            return f"STEP III: {exc}"
        tau = tr.sample_times(self.p.tick_s * 5)
        t, pts = t_eff + tau, tr.sample(tau)
        if self.known.intruders():
            c = first_conflict(t, pts, *self.tracks(self.chord_buffer_m(t)))
            if c is not None:
                return f"separation from intruder {c.id!r}: {c.distance_m:.1f} m at t = {c.t_cpa_s:.1f} s"
        for z in self.known.zones:
            k = first_in_zone(t, pts, z, self.veh.r_p_m)
            if k >= 0:
                return f"inside the temporary no-fly zone {z.id!r} at t = {t[k]:.1f} s"
        return ""

    def budget_J(self, t_eff: float, problem: PlanningProblem) -> float:
        t, p = self.tl.samples(0.0, self.p.tick_s, t_eff)
        spent = self.energy_J(t, p, problem)
        return self.veh.battery_energy_j * (1.0 - self.p.battery_reserve_pct / 100.0) - spent

    def replan(self, k: int, ev: TacticalEvent, t_e: float, t_eff: float, t_coll: float, update_s: float,
               cause: str, detail, resume: bool = False) -> str | None:
        """Levels 1-3 from ``t_eff`` [s] (module docstring); with ``resume`` (the end of an
        escape's hold) the rest of the mission as it is comes first (row ``resume``).  The
        valid solution with minimum f is flown; None when there is none."""
        p = self.p
        chain, speeds, _lead, v0 = self.rest_chain(t_eff)
        t_arrive_old = self.tl.t_end_s
        problem = self.problem(chain[0], self.goal, zones_from_s=t_eff)
        budget = self.budget_J(t_eff, problem)
        rows: list[tuple[LevelAttempt, Candidate | None, str]] = []

        def row(level: str, cand: Candidate | None, secs: float, reasons: str) -> None:
            ok = cand is not None and cand.flyable
            rows.append((LevelAttempt(k, ev.label, ev.t_s, t_coll, level, ok,
                                      cand.C_l if cand is not None else math.nan,
                                      cand.C_e if cand is not None else math.nan,
                                      cand.f if cand is not None else math.nan,
                                      cand.max_sigma_p_m if cand is not None else math.nan, secs, update_s,
                                      (float(cand.t_s[-1]) - t_arrive_old) if ok else math.nan, False, reasons),
                         cand, level))

        if resume:            # the mission from the hold as it is
            t0 = time.perf_counter()
            try:
                cr = self.finish(problem, chain, speeds, t_eff, v0, "resume", budget)
                row("resume", cr, time.perf_counter() - t0, "; ".join(cr.reasons[:2]))
            except (PlanningError, InputError) as exc:
                row("resume", None, time.perf_counter() - t0, str(exc))
        # level 1: time scaling
        t0 = time.perf_counter()
        why1 = ""
        cand1 = None
        if resume:
            why1 = "resuming from a hold: no encounter to time-scale"
        elif detail is not None and hasattr(detail, "own_velocity_mps"):
            kind, ang = encounter_geometry(detail.own_velocity_mps, detail.intruder_velocity_mps)
            if kind in ("frontal", "static"):
                why1 = (f"{kind} encounter ({ang:.0f} deg): time scaling cannot separate it" if kind == "frontal"
                        else "static intruder: time scaling cannot separate it")
            t_enc = detail.t_s
        elif detail is not None and isinstance(detail, NoFlyZone):
            t_enc = detail.end_s
        else:
            why1 = "static conflict (maps or wind): time scaling cannot resolve it"
            t_enc = math.nan
        if not why1:
            # the legs up to the encounter point are slowed
            seg = self.tl.segments[self.tl.active(t_eff)]
            pe = seg.sample([min(t_enc, seg.t_end_s)])[0] if math.isfinite(t_enc) else chain[-1]
            legs = np.linalg.norm(np.diff(chain, axis=0), axis=1)
            cum = np.concatenate([[0.0], np.cumsum(legs)])
            # arc length of the encounter point along the chain: nearest point on the chain
            d_enc = along(chain, pe)
            n_slow = int(np.searchsorted(cum, d_enc, side="left"))
            n_slow = min(max(n_slow, 1), legs.size)
            fails = []
            problem1 = (problem if not any(z.end_s > t_eff for z in self.known.zones)
                        else self.problem(chain[0], self.goal, zones_from_s=math.inf))   # zones: checked in time
            for s in p.time_scaling_factors:
                # slow the legs up to the encounter; when the vehicle cannot slow down on the
                # remnant of its current leg (arcs are flown at constant speed), start the
                # slow-down one or two legs later
                for first in range(min(3, n_slow)):
                    sp = speeds.copy()
                    sp[first:n_slow] *= s
                    why = self._screen_l1(problem1, chain, sp, t_eff, v0)   # cheap: geometry + separation
                    c = None
                    if not why:
                        try:
                            c = self.finish(problem1, chain, sp, t_eff, v0, f"L1 s={s:g}", budget)
                        except PlanningError as exc:
                            why = str(exc)
                        else:
                            why = "; ".join(c.reasons[:2])
                    if c is not None and c.flyable:
                        cand1 = c
                        break
                    if "cannot slow down" not in why:
                        break
                if cand1 is not None:
                    break
                fails.append(f"s={s:g}: {why}")
            if cand1 is None:
                why1 = "no speed factor gave a valid plan: " + " | ".join(fails[-2:])
        row("1", cand1, time.perf_counter() - t0, why1)

        # levels 2 and 3: RRTs from the braking point
        occ = self._occupancy(t_eff)
        for level, iters, sigma, explore in (("2", p.level2_iterations, 30.0, 0.2),
                                             ("3", p.level3_iterations, 60.0, 0.4)):
            t0 = time.perf_counter()

            def tail(pre, nb, t_b, level=level, iters=iters, sigma=sigma, explore=explore):
                W = (np.concatenate([pre[-1:], chain[nb:]]) if level == "2" else np.stack([pre[-1], chain[-1]]))
                s2 = deconflict(problem, W, occ, t0_s=t_b, seed=p.seed + 7919 * (k + 1) + int(level), max_iter=iters,
                                time_budget_s=600.0, sigma_m=sigma, explore=explore, require_valid_chain=False)
                return s2.waypoints if s2.ok else s2.reason

            cand, why = self.via_braking(chain, speeds, v0, t_eff, tail, lambda pb: problem, f"L{level}", budget)
            row(level, cand, time.perf_counter() - t0, why)
        # choose
        valid = [(r, c, lv) for r, c, lv in rows if r.flyable and c is not None and math.isfinite(c.f)]
        if valid:
            r, c, lv = min(valid, key=lambda x: x[1].f)
            r.chosen = True
            for r2, _c2, _ in rows:
                if r2 is not r and r2.flyable:
                    r2.reasons = f"valid but f = {r2.f_m:.1f} m > {r.f_m:.1f} m of level {lv}"
            self.attempts.extend(r2 for r2, _, _ in rows)
            self.follow(c, t_eff, lv if lv == "resume" else f"L{lv}", k)
            return lv if lv == "resume" else f"L{lv}"
        self.attempts.extend(r2 for r2, _, _ in rows)
        return None

    def _occupancy(self, t_from: float):
        intr = self.known.intruders()
        if not intr:
            return None
        horizon = max(max(float(i.times_s[-1]) for i in intr) - t_from, 1.0)
        n = max(int(math.ceil(horizon / self.p.occupancy_slice_s)), 1)
        return build_occupancy(intr, horizon, n, self.veh.r_p_m + self.p.d_c_m, self.p.dt_c_s, t0_s=t_from)

    # -------------------------------------------------------------- contingency landing
    def via_braking(self, chain, speeds, v0: float, t_eff: float, tail, problem_of, label: str, budget_J: float):
        """A new chain that stops at the braking point ``P_b`` of the current one and continues
        with ``tail(pre, nb, t_b)`` (waypoints from ``P_b``, or a reason string): ``(candidate or
        None, reason)``.  When the vehicle cannot slow down in time for the corners between
        ``t_eff`` and ``P_b`` (short remnants of old legs), ``P_b`` moves 2x and 4x farther."""
        why = ""
        for scale in (1.0, 2.0, 4.0):
            pre, nb = self.braking_point(chain, v0, scale)
            if nb >= chain.shape[0] - 1 and np.allclose(pre[-1], chain[-1]):
                return None, "the goal is within the braking distance"
            pre_speeds = speeds[: pre.shape[0] - 1]
            t_b = t_eff + float(np.sum(np.linalg.norm(np.diff(pre, axis=0), axis=1) / np.maximum(pre_speeds, 1e-3)))
            try:
                wp = tail(pre, nb, t_b)
                if isinstance(wp, str):
                    return None, wp
                full = np.concatenate([pre, wp[1:]])
                sp = np.concatenate([pre_speeds, np.full(full.shape[0] - 1 - pre_speeds.size, self.veh.cruise_speed_mps)])
                cand = self.finish(problem_of(pre[-1]), full, sp, t_eff, v0, label, budget_J,
                                    stop_at=(pre.shape[0] - 1,))
                why = "; ".join(cand.reasons)
                if "cannot slow down" in why and scale < 4.0:     # STEP III reports it as a reason
                    continue
                return cand, why
            except PlanningError as exc:
                why = str(exc)
                if "cannot slow down" not in why:
                    return None, why
            except InputError as exc:
                return None, str(exc)
        return None, why

    def land(self, k: int, ev: TacticalEvent, t_e: float, t_from: float, t_coll: float, update_s: float,
             why: str) -> tuple[bool, str]:
        """Contingency landing from ``t_from`` [s] (module docstring): ``(landed, why not)``;
        a landing sets the outcome ``landed``."""
        t_eff = self.effective_time(t_from)
        chain, speeds, _lead, v0 = self.rest_chain(t_eff)
        t0 = time.perf_counter()
        tried = []
        pb0 = self.braking_point(chain, v0)[0][-1]
        for name, approach in self._landing_targets(pb0):
            control.check()
            try:
                problem = self.problem(pb0, approach, gnss=False, zones_from_s=t_eff)
                budget = self.budget_J(t_eff, problem)
            except (PlanningError, InputError) as exc:
                tried.append(f"{name}: {exc}")
                continue

            def tail(pre, nb, t_b, approach=approach):
                prob = self.problem(pre[-1], approach, gnss=False, zones_from_s=t_eff)
                s1 = plan_step1(prob, planner="astar", time_budget_s=5.0, seed=self.p.seed, step_cells=self.p.step_cells)
                if not s1.solved:
                    return s1.reason or s1.status
                s2 = deconflict(prob, s1.waypoints, self._occupancy(t_b), t0_s=t_b, seed=self.p.seed,
                                max_iter=self.p.level2_iterations, time_budget_s=600.0)
                return s2.waypoints if s2.ok else s2.reason

            cand, reason = self.via_braking(chain, speeds, v0, t_eff, tail,
                                             lambda pb, approach=approach: self.problem(pb, approach, gnss=False,
                                                                                        zones_from_s=t_eff),
                                             "landing", budget)
            if cand is None:
                tried.append(f"{name}: {reason}")
                continue
            if not cand.flyable:
                tried.append(f"{name}: {'; '.join(cand.reasons[:2])}")
                continue
            self.attempts.append(LevelAttempt(k, ev.label, ev.t_s, t_coll, "landing", True, cand.C_l, cand.C_e,
                                              cand.f, cand.max_sigma_p_m, time.perf_counter() - t0, update_s,
                                              float(cand.t_s[-1]) - self.tl.t_end_s, True,
                                              f"{why}; landing at {name}"))
            self.follow(cand, t_eff, "landing", k)
            self.outcome, self.reason = "landed", f"contingency landing at {name}: {why}"
            return True, ""
        self.attempts.append(LevelAttempt(k, ev.label, ev.t_s, t_coll, "landing", False, math.nan, math.nan,
                                          math.nan, math.nan, time.perf_counter() - t0, update_s, math.nan, False,
                                          f"{why}; no reachable landing site: " + " | ".join(tried[:3])))
        return False, "no landing site reachable: " + (" | ".join(tried[:3]) or "no landing site on the map")

    def _landing_targets(self, pb) -> list[tuple[str, np.ndarray]]:
        """Approach points r_p (with the safety bubble: r_j) above the landing sites nearest
        to ``pb`` (one cell per site: the site cell nearest to the site's centre whose
        clearance floor allows it; the surface there is the ground of a field or the roof of
        a flat-roof site)."""
        env = self.world.environment
        if env is None or "site_x" not in env.coords:
            return []
        g = self.grid()
        site = np.asarray(env["landing_site"].values, bool)
        top = np.asarray(self.world.surface["surface"].values, float)     # the ground or the flat roof
        floor = np.asarray(self.world.clearance["min_altitude_m"].values, float)
        r_p = max(self.veh.r_p_m, self.p.clearance_radius_m or 0.0)
        zone = self._zone_mask(0.0)
        ok = site & np.isfinite(floor) & (floor <= top + r_p + 1e-9)
        if zone is not None:
            ok &= ~zone
        rows, cols = np.nonzero(ok)
        if rows.size == 0:
            return []
        cx = g.x0 + (cols + 0.5) * g.resolution_m
        cy = g.y1 - (rows + 0.5) * g.resolution_m
        sx, sy = np.asarray(env["site_x"].values, float), np.asarray(env["site_y"].values, float)
        names = [str(n) for n in env["site_name"].values] if "site_name" in env.coords else [str(i) for i in range(sx.size)]
        order = np.argsort(np.hypot(sx - pb[0], sy - pb[1]))
        out = []
        for i in order:
            d = np.hypot(cx - sx[i], cy - sy[i])
            j = int(np.argmin(d))
            if d[j] > 100.0:
                continue
            z = top[rows[j], cols[j]] + r_p
            out.append((f"{names[i] or 'site'} ({cx[j]:.0f}, {cy[j]:.0f})", np.array([cx[j], cy[j], z])))
            if len(out) >= self.p.max_landing_sites:
                break
        return out


def _dedupe(chain, speeds, stop_at=()):
    """Drop repeated vertices (and their legs) of a chain: ``(chain, speeds, leg lengths, stop_at)``."""
    chain = np.asarray(chain, float)
    lengths = np.linalg.norm(np.diff(chain, axis=0), axis=1)
    speeds = np.asarray(speeds, float)
    if np.any(lengths <= 1e-6):
        keep = np.r_[True, lengths > 1e-6]
        new_index = np.cumsum(keep) - 1
        stop_at = tuple(int(new_index[i]) for i in stop_at)
        chain, speeds, lengths = chain[keep], speeds[keep[1:]], lengths[keep[1:]]
    return chain, speeds, lengths, tuple(stop_at)


# ------------------------------------------------------------------ public entry


def replay(plan_traj, plan_t0_s: float, *, goal_xyz, world: World, world_at: Callable[[float], World],
           events: Sequence[TacticalEvent], strategic_intruders: Sequence[Intruder], vehicle: VehicleProfile,
           params: FlyParams, start_time_utc, dop_threshold: float | None, scenario: str = "",
           crs_wkt: str = "", vertical_datum: str = "",
           progress: Callable[[float, float], None] | None = None) -> FlightLog:
    """Fly the strategic plan ``plan_traj`` (a CornerTrajectory starting at mission time
    ``plan_t0_s`` [s]) through ``events`` (see the module docstring).  ``world``: the maps at
    take-off; ``world_at(t_s)``: the maps after the map-changing events up to ``t_s``.
    ``progress(t_s, t_end_s)``: called as each event is reached, with its mission time and the
    flight's planned end [s] (a progress display; it never changes the flight).
    Returns the :class:`~skyroute.stages.tactical.log.FlightLog` (outcome ``goal``,
    ``landed`` or ``failed`` with its reason)."""
    if plan_traj is None:
        raise InputError("the strategic plan has no trajectory to fly (re-run `skyroute plan`)")
    tl = Timeline()
    tl.add(Segment(plan_traj, float(plan_t0_s), "strategic", None), float(plan_t0_s))
    t_comp = time.perf_counter()
    _warm_up()
    r = _Replay(tl, goal_xyz, world, world_at, events, strategic_intruders, vehicle, params, start_time_utc,
                dop_threshold)
    r.prepare_world()
    r.init_navigation()
    compile_s = time.perf_counter() - t_comp
    r.on_progress = progress
    r.run()
    if progress is not None:
        progress(r.tl.t_end_s, r.tl.t_end_s)      # flown to the end (or stopped: the display ends)
    from skyroute.stages.grid import Grid

    grid = Grid.from_dataarray(world.surface["terrain"])
    planned_t = Segment(plan_traj, float(plan_t0_s)).times(plan_t0_s, plan_t0_s + plan_traj.duration_s, params.tick_s)
    log = FlightLog(scenario, crs_wkt, vertical_datum, str(start_time_utc), planned_t,
                    Segment(plan_traj, float(plan_t0_s)).sample(planned_t))
    for seg, a, b in tl.pieces():
        t = seg.times(a, b, params.tick_s)
        if t.size < 2:
            continue
        log.parts.append(FlownPart(seg.part, t, seg.sample(t), np.linalg.norm(seg.velocity(t), axis=1),
                                   seg.replanning))
    t_f, p_f = log.flown()
    log.energy_Wh = r.energy_J(t_f, p_f, r.problem(p_f[0], p_f[-1], zones_from_s=math.inf)) / 3600.0
    log.attempts = r.attempts
    log.events = r.event_log
    log.intruders = list(r.known.truth.values())
    log.nofly = list(r.known.zones)
    log.outcome, log.reason = r.outcome, r.reason
    log.dop_threshold = dop_threshold
    log.t_rep_s, log.tick_s, log.seed = params.t_rep_s, params.tick_s, params.seed
    log.own_radius_m, log.margin_m = vehicle.r_p_m, params.d_c_m
    if params.bubble is not None:
        log.bubble = {"k": params.bubble[0], "surface_uncertainty_m": params.bubble[1],
                      "clearance_radius_m": params.clearance_radius_m}
    log.compile_s = compile_s
    log.method = params.method
    log.dense_zones = list(r.octant.log)
    log.escapes = list(r.escapes.log)
    log.losses = list(r.escapes.losses)
    if log.losses:          # what was flown, by brute force, beside what was predicted
        from skyroute.stages.tactical.encounters import flown_losses

        flown = flown_losses(log)
        for loss in log.losses:
            loss["flown_margin_m"] = flown.get(loss["intruder"], math.nan)
            for a in log.attempts:
                if a.replanning == loss["replanning"] and a.level == "escape":
                    a.reasons += f"; flown minimum separation margin {loss['flown_margin_m']:+.1f} m"
    log.warnings = r.warnings
    log.grid = grid
    last = r.world          # the maps at the end of the flight (new obstacles, GNSS outages included)
    log.terrain_m = np.asarray(last.surface["terrain"].values, float)
    log.surface_m = np.asarray(last.surface["surface"].values, float)
    if last.coverage is not None and dop_threshold is not None:
        log.coverage_floor_m = np.asarray(last.coverage["coverage_floor"].sel(threshold=dop_threshold).values, float)
    env = last.environment
    if env is not None and "site_x" in env.coords:
        log.landing_xy = np.column_stack([env["site_x"].values, env["site_y"].values])
    return log


def _warm_up() -> None:
    """Compile the kernels the levels use once (numba caches them on disk), so each level's
    ``compute_s`` is its search + smoothing + validation, not compilation."""
    t = np.array([0.0, 1.0, 2.0])
    p = np.array([[0.0, 0.0, 10.0], [10.0, 0.0, 10.0], [20.0, 0.0, 10.0]])
    it = Intruder("warm-up", np.array([0.0, 2.0]), np.array([[0.0, 100.0, 10.0], [20.0, 100.0, 10.0]]), 1.0)
    first_conflict(t, p, IntruderTracks.from_intruders([it]), np.array([5.0]))
