"""The escape of last resort of a multirotor in the tactical replay (issue 22).

A multirotor always has a manoeuvre that needs no plan: brake, move a short way off the
predicted conflict, and hold there.  The replay (:mod:`.replay`) uses it

* when levels 1-3 (or the octant manoeuvre) and the contingency landing found nothing, from the
  time the replanning takes effect ``t_eff``;
* at once (a reflex, ``t_e + escape_latency_s``) when a known intruder conflict is found and no
  escape from ``t_eff`` would keep the separation: waiting for a plan would then risk a loss of
  separation that braking now avoids (the vehicle keeps an escape available);
* when the conflict is closer than ``t_rep`` and no landing is reachable.

**Options** (from the vehicle's state at ``t0``: position, speed ``v0`` along its current
direction ``e``).  Every option first brakes to a stop at the earliest point the deceleration
``a_max`` allows, ``P_b = p0 + (v0^2 / (2 a_max) + 0.5 m) e`` straight ahead (and, when the
plan turns within that distance, also at the same distance along the plan), then

* ``hover``: holds at ``P_b``;
* ``forward`` / ``back`` / ``left`` / ``right`` and the four diagonals between them (horizontal
  directions relative to ``e``), each level,
  ``climb`` or ``descend`` (a ramp at 0.98 x the vehicle's flight-path-angle limit: the limit is
  hard, so a multirotor's vertical escape climbs along a ramp, inside the AGL band of the maps)
  and over :data:`DISTANCE_FACTORS` x the separation ``S = r_p + r_i + d_c``: a stop corner at
  ``P_b``, a straight leg to the target ``E``, and a hold there;

and without braking first:

* ``dash``: straight on along ``e`` for :data:`DASH_FACTORS` x S, as fast as the airspeed limit
  allows (away from an intruder closing from behind), then a stop and a hold;
* ``turn-left`` / ``turn-right``: a level turn at once on the tightest radius the acceleration
  limit allows (``v0^2 / a_max``) by :data:`TURN_ANGLES_DEG`, then braking straight to a stop
  (:func:`~skyroute.stages.smoothing.turn_and_stop`) and a hold.

The hold lasts until the conflict clears: every known intruder stays farther than
:data:`CLEAR_FACTOR` x S from ``E`` (closed form on its believed track, :func:`clear_time`), and
the route from ``E`` back to the plan and on to the goal, flown at its leg speeds from the end of
the hold, keeps :data:`RESUME_FACTOR` x S from every known intruder (:func:`resume_time`: the
earliest such start on a :data:`RESUME_STEP_S` grid); at least :data:`MIN_HOLD_S` and
at most :data:`MAX_HOLD_S` (the n-th escape of a flight holds at least ``2^n`` x the minimum:
a conflict that does not clear with time, e.g. a new obstacle, is not retried in a tight loop);
the replay then replans from the hold (levels 1-3 again, first the
old plan as it is: ``resume``).

**Selection**: every option is screened (its exact corner trajectory with the hold, sampled
every :data:`SCREEN_DT_S`; the static bounds of the current maps at every sample, the
temporary no-fly zones, and the exact minimum separation from every known intruder over the
whole escape, :func:`~skyroute.stages.tactical.conflict.min_separation`), ranked by its
predicted minimum separation margin ``min_i (d_i - S_i)`` (largest first; ties: the order
above, the smallest manoeuvre first), and the best ones go through the same STEP III, validator,
navigation filter, battery and exact separation check as every replan (at most
:data:`MAX_FULL_CHECKS`, or :data:`MAX_FULL_CHECKS_IF_NONE` while none is acceptable).  The
first that passes is flown (part ``escape``).  Otherwise, in this order: the best one that keeps
the separation and fails only the navigation budget (sigma_p above dp_max: flown as a *degraded
navigation* escape, said in tactical.csv and the warnings: a known collision is worse than a
navigation excursion; the maps, the hard limits and the validator still hold); the best valid
one that does not keep the separation (the intruder is too fast or known too late: physically
unavoidable with these manoeuvres: the loss is reported with the predicted minimum separation
and why); the best one failing both.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from skyroute.stages.base import InputError, PlanningError
from skyroute.stages.smoothing import CornerTrajectory, turn_and_stop
from skyroute.stages.tactical.conflict import IntruderTracks, first_conflict, min_separation
from skyroute.stages.tactical.events import TacticalEvent, event_record, first_in_zone
from skyroute.stages.tactical.log import LevelAttempt

__all__ = ["CLEAR_FACTOR", "DISTANCE_FACTORS", "EscapeDecision", "EscapeOption", "Escapes", "HOLD_LOOKAHEAD_S", "MAX_ESCAPES",
           "MAX_HOLD_S", "MIN_HOLD_S", "clear_time", "plan_escape", "resume_time"]

CLEAR_FACTOR = 2.0              # the hold ends once every known intruder stays this many separations away
MIN_HOLD_S = 1.0                # [s] shortest hold at the escape point
MAX_HOLD_S = 300.0              # [s] longest hold before the replay tries to resume anyway
MAX_ESCAPES = 6                 # escapes per flight; then the vehicle stays on hold (operator)
DISTANCE_FACTORS = (1.5, 3.0)   # escape distances in separations S
DASH_FACTORS = (3.0, 6.0)       # dashes straight on at full speed, in separations S
RAMP_FRACTION = 0.98            # climb / descent ramps at this fraction of the flight-path-angle limit
SCREEN_DT_S = 0.25              # [s] sampling of the screen
TURN_ANGLES_DEG = (45.0, 90.0, 135.0)   # turns at once (tightest radius), then brake
RESUME_STEP_S = 0.5             # [s] step of the search for the end of a hold
RESUME_FACTOR = 1.25            # the route resumed after a hold keeps this many separations (its smoothing differs)
HOLD_LOOKAHEAD_S = 15.0         # [s] a hold is checked as lasting this much longer (it ends only when replaced)
MAX_FULL_CHECKS = 6             # options that go through the full STEP III per decision ...
MAX_FULL_CHECKS_IF_NONE = 14    # ... or more while none is acceptable
NAVIGATION_PREFIX = "navigation error sigma_p"
SEPARATION_PREFIX = "separation from intruder"


@dataclass
class EscapeOption:
    """One escape manoeuvre from ``t0_s``: ``kind`` (e.g. ``hover``, ``left``, ``back-climb``),
    target ``target_xyz_m`` (3,) [m], the chain it flies (``chain`` (k, 3), leg ``speeds`` (k-1,),
    ``stop_at`` vertices), ``hold_until_s`` [s], and the screen's verdict: ``static_ok`` (maps,
    zones, kinematics), ``margin_m`` [m] (min over known intruders of distance - separation over
    the escape and its hold; +inf without intruders), ``intruder`` (the closest), ``why`` (why
    not valid); ``candidate``: the full STEP III result when it was checked."""

    kind: str
    target_xyz_m: np.ndarray
    chain: np.ndarray
    speeds: np.ndarray
    stop_at: tuple[int, ...]
    hold_until_s: float
    static_ok: bool = False
    margin_m: float = -math.inf
    intruder: str = ""
    why: str = ""
    candidate: object | None = None
    rejoin: tuple[np.ndarray, np.ndarray] | None = None   # the mission after the hold (chain, leg speeds)
    trajectory: object | None = None    # a turn's exact trajectory (no chain to smooth), before the hold

    @property
    def keeps_separation(self) -> bool:
        return self.static_ok and self.margin_m >= 0.0


@dataclass
class EscapeDecision:
    """The escape decision at ``t0_s`` [s]: every option screened, the ``chosen`` one (flown:
    flyable, or the best valid one when none keeps the separation) or None, and the time the
    decision took ``compute_s`` [s]."""

    t0_s: float
    options: list[EscapeOption] = field(default_factory=list)
    chosen: EscapeOption | None = None
    compute_s: float = 0.0

    @property
    def keeps_separation(self) -> bool:
        c = self.chosen
        return c is not None and c.candidate is not None and bool(c.candidate.flyable)

    def summary(self, n: int = 3) -> str:
        """The best ``n`` options as text (kind, margin, why not)."""
        ranked = sorted(self.options, key=lambda o: (not o.static_ok, -o.margin_m))
        out = []
        for o in ranked[:n]:
            m = "inf" if math.isinf(o.margin_m) and o.margin_m > 0 else f"{o.margin_m:+.1f} m"
            out.append(f"{o.kind} (margin {m}{'; ' + o.why[:100] if o.why else ''})")
        return " | ".join(out)


def clear_time(tracks: IntruderTracks, radius_m: np.ndarray, point_xyz_m, t_from_s: float) -> float:
    """The last time [s] at or after ``t_from_s`` that some intruder of ``tracks`` is strictly
    closer than its ``radius_m`` (N,) [m] to the fixed point ``point_xyz_m`` (3,) [m]
    (closed form per track segment; an intruder exists only on its track's time span); ``t_from_s``
    when none is."""
    q = np.asarray(point_xyz_m, float)
    last = float(t_from_s)
    for i in range(tracks.n):
        lo, hi = int(tracks.offsets[i]), int(tracks.offsets[i + 1])
        t, p = tracks.t_s[lo:hi], tracks.xyz_m[lo:hi]
        r2 = float(radius_m[i]) ** 2
        if t.size == 1:
            if t[0] >= t_from_s and float(np.sum((p[0] - q) ** 2)) < r2:
                last = max(last, float(t[0]))
            continue
        for k in range(t.size - 1):
            a, b = float(t[k]), float(t[k + 1])
            if b < t_from_s:
                continue
            v = (p[k + 1] - p[k]) / (b - a)
            d0 = p[k] - q
            A, B, C = float(v @ v), float(d0 @ v), float(d0 @ d0) - r2
            # |d0 + v tau|^2 < r^2 on tau in [0, b - a]: the roots of A tau^2 + 2 B tau + C
            if A <= 0.0:
                if C < 0.0:
                    last = max(last, b)
                continue
            disc = B * B - A * C
            if disc <= 0.0:
                continue
            hi_tau = (-B + math.sqrt(disc)) / A
            lo_tau = (-B - math.sqrt(disc)) / A
            if hi_tau <= 0.0 or lo_tau >= b - a:
                continue
            last = max(last, a + min(hi_tau, b - a))
    return last


def resume_time(tracks: IntruderTracks, sep_m: np.ndarray, chain: np.ndarray, speeds: np.ndarray, t_from_s: float,
                t_to_s: float, step_s: float = RESUME_STEP_S) -> float | None:
    """The earliest time [s] in ``[t_from_s, t_to_s]`` (every ``step_s``) from which flying
    ``chain`` (k, 3) [m] at its leg ``speeds`` (k-1,) [m/s] (a piecewise-linear timing, the
    route after a hold) keeps ``sep_m`` (N,) [m] from every intruder of ``tracks``
    (:func:`~skyroute.stages.tactical.conflict.first_conflict`, exact on the polyline); None when
    no start time in the window does."""
    legs = np.linalg.norm(np.diff(chain, axis=0), axis=1)
    keep = np.r_[True, legs > 1e-6]
    ch = chain[keep]
    sp = np.maximum(speeds[keep[1:]], 1e-3)
    legs = legs[keep[1:]]
    if ch.shape[0] < 2:
        return t_from_s
    rel = np.concatenate([[0.0], np.cumsum(legs / sp)])
    for T in np.arange(t_from_s, t_to_s + 1e-9, step_s):
        if first_conflict(T + rel, ch, tracks, sep_m) is None:
            return float(T)
    return None


def _unit(v: np.ndarray) -> np.ndarray | None:
    n = float(np.linalg.norm(v))
    return v / n if n > 1e-9 else None


def _targets(pb: np.ndarray, e_h: np.ndarray, sep_m: float, tan_ramp: float) -> list[tuple[str, np.ndarray]]:
    """Escape targets from the stop point ``pb``: (kind, E)."""
    n = np.array([-e_h[1], e_h[0], 0.0])                    # left of the direction of travel
    out: list[tuple[str, np.ndarray]] = [("hover", pb.copy())]
    r2 = math.sqrt(0.5)
    dirs = (("left", n), ("right", -n), ("back", -e_h), ("forward", e_h), ("back-left", r2 * (n - e_h)),
            ("back-right", r2 * (-n - e_h)), ("forward-left", r2 * (n + e_h)), ("forward-right", r2 * (e_h - n)))
    for fac in DISTANCE_FACTORS:
        d = fac * sep_m
        for vert, sz in (("", 0.0), ("-climb", 1.0), ("-descend", -1.0)):
            for name, u in dirs:
                out.append((f"{name}{vert} {d:.0f} m", pb + d * u + np.array([0.0, 0.0, sz * d * tan_ramp])))
    return out


def _rejoin(target: np.ndarray, chain: np.ndarray, speeds: np.ndarray, nb: int, pb_path: np.ndarray,
            cruise_mps: float) -> tuple[np.ndarray, np.ndarray]:
    """The rest of the mission after an escape to ``target``: back to the plan at its braking
    point ``pb_path`` (``nb`` chain vertices before it), then the plan's chain to the goal."""
    ch = np.concatenate([target[None], pb_path[None], chain[nb:]])
    sp = np.concatenate([[cruise_mps], speeds[max(nb - 1, 0):]])
    return ch, sp[: ch.shape[0] - 1]


def plan_escape(rp, t0_s: float, *, full: bool = True, label: str = "escape") -> EscapeDecision:
    """The escape decision of the replay ``rp`` (a :class:`~skyroute.stages.tactical.replay._Replay`:
    its timeline, knowledge, maps and STEP III) from mission time ``t0_s`` [s] (module
    docstring).  ``full=False``: the screen only (is an escape that keeps the separation
    available?); the chosen option is then the best screened one without a candidate."""
    from skyroute.stages.planning.step3 import smooth_chain

    wall = time.perf_counter()
    dec = EscapeDecision(float(t0_s))
    min_hold = MIN_HOLD_S * 2.0 ** min(rp.escapes.n, 6)     # each further escape of a flight waits longer
    chain, speeds, _lead, v0 = rp.rest_chain(t0_s)
    p0 = chain[0]
    vel = rp.tl.velocity(t0_s)
    e = _unit(vel) if v0 > 1e-6 else None
    if e is None:
        e = _unit(chain[1] - p0) if chain.shape[0] > 1 else None
    if e is None:
        e = _unit(rp.goal - p0)
    if e is None:
        e = np.array([1.0, 0.0, 0.0])
    e_h = _unit(np.array([e[0], e[1], 0.0]))
    if e_h is None:
        e_h = _unit(np.array([*(rp.goal - p0)[:2], 0.0]))
    if e_h is None:
        e_h = np.array([1.0, 0.0, 0.0])
    lim = rp.lim
    d_b = v0 * v0 / (2.0 * lim.max_acceleration_mps2) + 0.5
    cruise = float(rp.veh.cruise_speed_mps)
    problem = rp.problem(p0, rp.goal, zones_from_s=math.inf)      # temporary zones: checked in time
    intr = rp.known.intruders()
    tracks, sep = rp.tracks() if intr else (None, np.zeros(0))
    sep_m = float(np.max(sep)) if sep.size else float(rp.veh.r_p_m + rp.p.d_c_m)
    tan_ramp = RAMP_FRACTION * math.tan(math.radians(rp.veh.max_flight_path_angle_deg))
    # the braking bases: straight ahead, and along the plan when it turns within d_b
    pre_path, nb = rp.braking_point(chain, v0)
    pb_path = pre_path[-1]
    at_rest = v0 <= 1e-6                     # already holding: no braking, moves start from rest
    bases = [("", p0[None], np.zeros(0))] if at_rest else [("", np.stack([p0, p0 + d_b * e]), np.array([v0]))]
    if pre_path.shape[0] > 2 and not at_rest:
        bases.append(("path ", pre_path, np.maximum(speeds[: pre_path.shape[0] - 1], 1e-3)))
    zones = [z for z in rp.known.zones if z.end_s > t0_s]
    candidates = []                          # (kind, chain, speeds, stop_at, target, turn trajectory)
    for bname, base, bsp in bases:
        pb = base[-1]
        for kind, E in _targets(pb, e_h, sep_m, tan_ramp):
            if kind == "hover" and at_rest:    # stay where it is
                candidates.append((bname + kind, np.stack([p0, p0]), np.array([cruise]), (), E,
                                   CornerTrajectory.at_rest(p0)))
            elif kind == "hover":
                candidates.append((bname + kind, base, bsp, (), E, None))
            else:
                candidates.append((bname + kind, np.concatenate([base, E[None]]), np.concatenate([bsp, [cruise]]),
                                   (base.shape[0] - 1,) if base.shape[0] > 1 else (), E, None))
    v_dash = float(rp.veh.max_airspeed_mps)  # corner_trajectory caps it by the airspeed in the wind
    for fac in DASH_FACTORS:                 # straight on, as fast as the limits allow, then brake
        E = p0 + fac * sep_m * e
        candidates.append((f"dash {fac * sep_m:.0f} m", np.stack([p0, E]), np.array([max(v_dash, v0)]), (), E, None))
    if v0 > 1.0:                             # turns at once, at the acceleration limit, then brake
        n = np.array([-e_h[1], e_h[0], 0.0])
        R = v0 * v0 / lim.max_acceleration_mps2 * (1.0 + 1e-9)
        for side, e2 in (("left", n), ("right", -n)):
            for ang in TURN_ANGLES_DEG:
                try:
                    tr = turn_and_stop(p0, e, e2, v0, R, math.radians(ang), lim)
                except (PlanningError, InputError):
                    continue
                E = tr.sample([tr.duration_s])[0]
                candidates.append((f"turn-{side} {ang:.0f} deg", np.stack([p0, E]), np.array([cruise]), (), E, tr))
    for kind, ch, sp, stop, E, turn in candidates:
        hold_until = clear_time(tracks, CLEAR_FACTOR * sep, E, t0_s) if tracks is not None else t0_s
        opt = EscapeOption(kind, E, ch, sp, stop, hold_until, trajectory=turn,
                           rejoin=_rejoin(E, chain, speeds, nb, pb_path, cruise))
        dec.options.append(opt)
        try:
            if turn is not None:
                traj = turn
            else:
                legs = np.linalg.norm(np.diff(ch, axis=0), axis=1)
                traj = smooth_chain(problem, ch, legs / sp, v_start_mps=v0, stop_at=stop)
            arrive = t0_s + traj.duration_s
            if tracks is not None:
                t_res = resume_time(tracks, RESUME_FACTOR * sep, *opt.rejoin, max(arrive + min_hold, hold_until),
                                    arrive + MAX_HOLD_S)
                hold_until = max(hold_until, t_res if t_res is not None else hold_until)
            hold = min(max(hold_until - arrive, min_hold), MAX_HOLD_S)
            opt.hold_until_s = arrive + hold
            traj = traj.with_hold(hold)
        except (PlanningError, InputError) as exc:
            opt.why = f"STEP III: {exc}"
            continue
        tau = traj.sample_times(SCREEN_DT_S)
        t, pts = t0_s + tau, traj.sample(tau)
        ok = np.asarray(problem.state_valid(pts), bool)
        if not ok.all():
            k = int(np.argmin(ok))
            opt.why = f"static bounds at t = {t[k]:.1f} s: {problem.explain_invalid(pts[k])}"
            continue
        hit = next((z for z in zones if first_in_zone(t, pts, z, rp.veh.r_p_m) >= 0), None)
        if hit is not None:
            opt.why = f"inside the temporary no-fly zone {hit.id!r}"
            continue
        opt.static_ok = True
        if tracks is None:
            opt.margin_m = math.inf
        else:
            d = min_separation(t, pts, tracks, t_from_s=t0_s) - sep - rp.chord_buffer_m(t)
            i = int(np.argmin(d))
            opt.margin_m, opt.intruder = float(d[i]), tracks.ids[i]
    order = sorted(range(len(dec.options)), key=lambda i: (not dec.options[i].static_ok, -dec.options[i].margin_m, i))
    ranked = [dec.options[i] for i in order if dec.options[i].static_ok]
    if not full:
        dec.chosen = ranked[0] if ranked else None
        dec.compute_s = time.perf_counter() - wall
        return dec
    budget = rp.budget_J(t0_s, problem)
    tiers: dict[int, EscapeOption] = {}
    for n_checked, opt in enumerate(ranked):
        if n_checked >= MAX_FULL_CHECKS and (tiers or n_checked >= MAX_FULL_CHECKS_IF_NONE):
            break
        try:
            cand = rp.finish(problem, opt.chain, opt.speeds, t0_s, v0, f"{label} {opt.kind}", budget,
                             stop_at=opt.stop_at, hold_until_s=opt.hold_until_s, trajectory=opt.trajectory,
                             min_hold_s=min_hold)
        except (PlanningError, InputError) as exc:
            opt.why = str(exc)
            continue
        opt.candidate = cand
        if cand.flyable:
            dec.chosen = opt
            break
        sep = [r for r in cand.reasons if r.startswith(SEPARATION_PREFIX)]
        other = [r for r in cand.reasons if not r.startswith(SEPARATION_PREFIX)]
        nav_only = all(r.startswith(NAVIGATION_PREFIX) for r in other)
        opt.why = "; ".join(cand.reasons[:2])
        tier = 1 if (not sep and nav_only) else 2 if not other else 3 if nav_only else None
        if tier is not None:
            tiers.setdefault(tier, opt)
    if dec.chosen is None and tiers:
        dec.chosen = tiers[min(tiers)]
    dec.compute_s = time.perf_counter() - wall
    return dec


class Escapes:
    """The escape behaviour of a replay (:class:`~skyroute.stages.tactical.replay._Replay`): it
    owns its state -- ``n`` escapes flown, ``log`` (one dict per escape decision) and
    ``losses`` (the predicted losses of separation the flight had to accept) -- and acts on the
    replay ``rp`` through its public interface (timeline, knowledge, STEP III, attempts)."""

    def __init__(self):
        self.n = 0
        self.log: list[dict] = []
        self.losses: list[dict] = []
        self._committed_until: dict[str, float] = {}   # intruder -> end of the interval already checked

    def committed(self, rp, k: int, ev, t_e: float, t_react: float, dt_s: float = 0.01) -> list[dict]:
        """Losses of separation no manoeuvre can avoid because they happen before any can act:
        along the path the vehicle flies from ``t_e`` [s] (the event that made the conflict
        known) to ``t_react`` [s] (the earliest start of an escape: the reaction latency), the
        exact minimum distance to a known intruder's believed track
        (:func:`~skyroute.stages.tactical.conflict.min_separation` on the path sampled every
        ``dt_s`` [s], less the chord buffer) below r_p + r_i + d_c.  Each such loss is recorded
        in :attr:`losses` (declared unavoidable, with its margin) once per intruder and
        interval.  Returns the new records."""
        out: list[dict] = []
        if not (t_react > t_e and rp.known.intruders()):
            return out
        t, p = rp.tl.samples(t_e, dt_s, t_react)
        if t.size < 2:
            return out
        tracks, sep = rp.tracks()
        buf = rp.chord_buffer_m(t)
        for i, iid in enumerate(tracks.ids):
            t_from = max(t_e, self._committed_until.get(iid, -math.inf))
            self._committed_until[iid] = t_react
            if t_from >= t_react:
                continue
            margin = float(min_separation(t, p, tracks, t_from_s=t_from)[i] - sep[i] - buf)
            if not margin < 0:          # kept (inf: the intruder is not flying then)
                continue
            rec = {"replanning": k, "event": ev.label, "t_s": t_from, "intruder": iid,
                   "predicted_margin_m": margin,
                   "why": (f"the separation is lost between t = {t_from:.1f} s and t = {t_react:.1f} s, before any "
                           f"manoeuvre can act (the conflict was known at t = {t_e:.1f} s, an escape starts "
                           f"{t_react - t_e:.1f} s later): the intruder was known too late")}
            self.losses.append(rec)
            out.append(rec)
        return out

    def available(self, rp, t0: float) -> bool:
        """Whether an escape from ``t0`` [s] keeps the separation from every known intruder
        (the screen of :func:`~skyroute.stages.tactical.escape.plan_escape`)."""
        if t0 >= rp.tl.t_end_s and rp.tl.segments[-1].part != "escape":
            return True
        dec = plan_escape(rp, t0, full=False)
        return dec.chosen is not None and dec.chosen.keeps_separation

    def last_resort(self, rp, k: int, ev, t_e: float, t0: float, t_coll: float, update_s: float,
                    why: str, tried: str, reflex: bool = False) -> str:
        """After levels 1-3 and the landing found nothing (or as a reflex): the escape of
        :mod:`.escape` from ``t0`` [s], hold, then replan (a ``resume`` event); when no escape
        is valid the vehicle keeps its plan and the flight fails.  Returns the event outcome."""
        t0 = rp.effective_time(t0)
        dec = None
        holding = rp.tl.segments[-1].part == "escape"        # hovering at the end of the timeline
        if rp.p.escape and self.n < MAX_ESCAPES and (t0 < rp.tl.t_end_s or holding):
            dec = plan_escape(rp, t0)
        opt = dec.chosen if dec is not None else None
        if opt is None or opt.candidate is None:
            if dec is None:
                head = ("escapes are off" if not rp.p.escape else
                        f"{self.n} escapes flown already" if self.n >= MAX_ESCAPES else
                        "the flight ends before an escape could start")
            else:
                head = "no escape is valid: " + dec.summary()
            rp.attempts.append(LevelAttempt(k, ev.label, ev.t_s, t_coll, "escape", False, math.nan, math.nan,
                                              math.nan, math.nan, dec.compute_s if dec else 0.0, update_s, math.nan,
                                              True, f"{why}; {head}; the vehicle keeps its plan"))
            rp.outcome = "failed"
            rp.reason = f"{why}; {tried + '; ' if tried else ''}{head}"
            return "failed"
        cand = opt.candidate
        self.n += 1
        keeps = not any(r.startswith(SEPARATION_PREFIX) for r in cand.reasons)
        degraded = [r for r in cand.reasons if r.startswith(NAVIGATION_PREFIX)]
        verdict = (f"escape {opt.kind}: predicted minimum separation margin {opt.margin_m:+.1f} m"
                   if math.isfinite(opt.margin_m) else f"escape {opt.kind}")
        if degraded:
            verdict += (f"; DEGRADED NAVIGATION accepted to avoid a known loss of separation: {degraded[0]} "
                        "(no escape within the navigation budget)")
            rp.warnings.append(f"escape at t = {t0:.1f} s flown with degraded navigation: {degraded[0]}")
        if not keeps:
            loss = {"replanning": k, "event": ev.label, "t_s": t0, "intruder": opt.intruder,
                    "predicted_margin_m": opt.margin_m,
                    "why": (f"no manoeuvre keeps the separation: the best, {opt.kind}, still comes "
                            f"{-opt.margin_m:.1f} m inside it (the intruder is too fast or known too late)"),
                    "options": dec.summary(6)}
            self.losses.append(loss)
            verdict += f"; UNAVOIDABLE: {loss['why']}"
        rp.attempts.append(LevelAttempt(k, ev.label, ev.t_s, t_coll, "escape", bool(cand.flyable), cand.C_l, cand.C_e,
                                          cand.f,
                                          cand.max_sigma_p_m, dec.compute_s, update_s, math.nan, True,
                                          f"{why}; {'reflex: ' if reflex else ''}{verdict}; hold at "
                                          f"({opt.target_xyz_m[0]:.0f}, {opt.target_xyz_m[1]:.0f}, "
                                          f"{opt.target_xyz_m[2]:.0f}) until t = {float(cand.t_s[-1]):.1f} s"))
        self.log.append({"replanning": k, "t_s": t0, "kind": opt.kind, "reflex": reflex,
                                "margin_m": opt.margin_m, "keeps_separation": keeps,
                                "degraded_navigation": bool(degraded),
                                "hold_until_s": float(cand.t_s[-1]), "compute_s": dec.compute_s,
                                "options": len(dec.options)})
        chain, speeds = opt.rejoin
        rp.follow(cand, t0, "escape", k, then=(chain, speeds))
        t_res = float(cand.t_s[-1])
        rp.push(TacticalEvent(max(t_res - rp.p.t_rep_s, t0), "resume", f"resume after escape {k}"),
                  max(t_res - rp.p.t_rep_s, t0))
        if rp.outcome == "failed":
            rp.outcome, rp.reason = "goal", ""
        return f"escape {opt.kind}" + ("" if keeps else " (unavoidable loss of separation)")

    def resume(self, rp, ev, t_e: float) -> bool:
        """The hold of an escape ends: replan from it (the rest of the old plan as it is, then
        levels 2 and 3, the landing, another escape).  False when the flight ends here."""
        seg = rp.tl.segments[-1]
        t_end = rp.tl.t_end_s
        if (seg.part != "escape" or seg.then_chain is None or t_e > t_end + 1e-9
                or ev.label != f"resume after escape {seg.replanning}"):     # a later escape replaced it
            rp.event_log.append(event_record(ev, t_e, math.inf, "superseded"))
            return True
        k = rp.n_replan
        rp.n_replan += 1
        cause = f"the hold of {ev.label.removeprefix('resume after ')} ends"
        best = rp.replan(k, ev, t_e, t_end, math.inf, 0.0, cause, None, resume=True)
        if best is not None:
            rp.event_log.append(event_record(ev, t_e, math.inf, f"replanned {best}", cause))
            return True
        why = f"no plan from the hold ({cause})"
        ok, tried = rp.land(k, ev, t_e, t_end, math.inf, 0.0, why)
        outcome = "landing" if ok else self.last_resort(rp, k, ev, t_e, t_end, math.inf, 0.0, why, tried)
        rp.event_log.append(event_record(ev, t_e, math.inf, outcome, cause))
        if outcome == "failed":
            rp.reason = f"holding at the escape point: {rp.reason}"
            return False
        return True

