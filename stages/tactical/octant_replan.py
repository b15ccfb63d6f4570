"""The octant tactical method of the flight replay (``skyroute fly --tactical octant``, seed 004).

Known traffic, zones (section III-A).  At an intruder event, once a period T_p has passed or the
set of known intruders flying then has changed, the known intruders' states at that time (position and velocity of their believed tracks) are predicted ``zone_period_s``
(T_p) ahead and the map's rectangle is partitioned (:class:`~skyroute.stages.tactical.zones.ZoneTracker`);
when the dense zone definition changes, its zones become temporary obstacles from then to
``t + T_p`` (full height, polygon widened by r_p), which every octant manoeuvre must avoid
(a zone that already holds the vehicle is not one it can avoid and is skipped).  The
definitions are recorded in ``FlightLog.dense_zones``.  Seed 004's coupling with the potential
field (:func:`zone_potential`, ``FlyParams.zone_potential``): at a new definition the dense
zones become obstacles of a :class:`~skyroute.stages.tactical.zone_field.ZoneField` (computed
in full the first time a zone meets the plan, then updated incrementally at every change),
and a plan that enters an active dense zone is replaced by the gradient motion of the updated
W-potential from where the vehicle turns (part ``potential``), through the same STEP III,
validator, exact separation and zone checks; each log entry says ``potential`` ("", "full",
"incremental"), its ``potential_s`` [s] and what happened (``reroute``).

Conflict with one intruder (section III-D).  When the rest of the plan loses separation from
an intruder, the vehicle keeps its plan until that intruder breaches the periphery
``periphery_m`` (P_r) -- not before the replanning time ``t_e + t_rep`` -- then, at that time
``t_eff`` (when no escape below is valid from there, P_r grows by 1.5, 2 and 3: the intruder is
known, so the vehicle may react earlier): the octants crossed inside P_r by the straight
relative paths of that intruder and of every other known intruder then inside P_r are
occupied; the vacant ones are ranked (forward hemisphere first, farther from the paths first,
:func:`~skyroute.stages.tactical.octant.rank_octants`), then the vacant pockets.  For each
escape direction ``e`` (its elevation limited to 80 % of the vehicle's flight-path angle) and
escape distance ``D`` in (2, 4, 6) x the separation, the new chain follows the plan to the point
``P_b`` a braking distance ahead, turns there (a smoothed corner; if that is not flyable, a stop
at ``P_b`` as levels 2 and 3 do), flies to ``E = P_b + D e``, rejoins the plan ``D`` beyond the
encounter point (farther if the leg back would be steeper than that elevation) and follows it to
the goal.  Per direction, the shortest ``D`` that passes the
same STEP III (smoothing, retiming, validator) and exact separation and zone checks as the
levels is kept; of those, the one with minimum f (the levels' tactical cost) is flown (part
``octant``); when none passes, the replay lands (contingency), as after levels 1-3.
Conflicts that are not with an intruder (no-fly zones, wind, maps) are replanned by levels 1-3.
"""

from __future__ import annotations

import math
import time

import numpy as np

from skyroute.stages.tactical.conflict import first_conflict
from skyroute.stages.tactical.events import first_in_zone
from skyroute.stages.tactical.log import LevelAttempt, NoFlyZone
from skyroute.stages.tactical.octant import (
    _chord,
    _seg_point_d,
    body_frame,
    escape_direction,
    pocket_directions,
    rank_octants,
)
from skyroute.stages.tactical.timeline import along
from skyroute.stages.tactical.zones import ZoneTracker

__all__ = ["OctantZones", "intruder_state", "octant_replan", "update_zones", "zone_potential"]

ESCAPE_FACTORS = (2.0, 4.0, 6.0)      # escape distances D in units of the separation
MAX_DIRECTIONS = 6                    # escape directions tried (octants, then pockets)
PERIPHERY_GROWTH = (1.0, 1.5, 2.0, 3.0)   # P_r factors tried when no escape is valid


class OctantZones:
    """The octant method's state in a replay (it owns it; the replay holds one): the zone
    ``tracker`` (:class:`~skyroute.stages.tactical.zones.ZoneTracker`, made at the first
    determination), the active dense ``zones`` (temporary obstacles), their definitions ``log``
    (``FlightLog.dense_zones``), the intruders ``ids`` of the last determination, and the zones'
    potential ``field`` (:class:`~skyroute.stages.tactical.zone_field.ZoneField`) with the world
    ``field_world`` it was computed on."""

    def __init__(self):
        self.tracker: ZoneTracker | None = None
        self.zones: list[NoFlyZone] = []
        self.log: list[dict] = []
        self.ids: tuple[str, ...] | None = None
        self.field = None
        self.field_world = None


def intruder_state(intr, t_s: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Position [m] and velocity [m/s] of an :class:`~skyroute.stages.traffic.Intruder` track
    (linear between waypoints) at ``t_s`` [s]; None outside its time span."""
    t = np.asarray(intr.times_s, float)
    p = np.asarray(intr.xyz_m, float)
    if t.size < 2 or not (t[0] <= t_s <= t[-1]):
        return None
    j = min(max(int(np.searchsorted(t, t_s, side="right")) - 1, 0), t.size - 2)
    v = (p[j + 1] - p[j]) / (t[j + 1] - t[j])
    return p[j] + v * (t_s - t[j]), v


def update_zones(rp, t_s: float) -> None:
    """Zone determination at ``t_s`` for the replay ``rp`` (module docstring)."""
    g = rp.grid()
    if rp.octant.tracker is None:
        ws = (g.x0, g.x0 + g.nx * g.resolution_m, g.y1 - g.ny * g.resolution_m, g.y1)
        rp.octant.tracker = ZoneTracker(ws, period_s=rp.p.zone_period_s)
    live = [(i.id, s) for i in rp.known.intruders() if (s := intruder_state(i, t_s)) is not None]
    xyz = np.array([s[0] for _, s in live]).reshape(-1, 3)
    vel = np.array([s[1] for _, s in live]).reshape(-1, 3)
    own = rp.tl.sample(t_s)
    ids = tuple(sorted(i for i, _ in live))
    part, changed = rp.octant.tracker.update(t_s, own[:2], rp.goal[:2], xyz, vel, force=ids != rp.octant.ids)
    rp.octant.ids = ids
    if not changed:
        return
    T = rp.p.zone_period_s
    rp.octant.zones = [NoFlyZone(f"dense-{b.bits}", b.polygon_xy, -1e9, 1e9, float(t_s), float(t_s) + T)
                      for b in part.boxes]
    entry = {"t_s": float(t_s), "r": int(part.r), "dense": list(part.dense), "ok": bool(part.ok),
             "reason": part.reason, "n_intruders": int(xyz.shape[0]),
             "boxes_m": [[b.x_min_m, b.x_max_m, b.y_min_m, b.y_max_m] for b in part.boxes]}
    rp.octant.log.append(entry)
    if rp.p.zone_potential:
        entry.update(zone_potential(rp, t_s, part.boxes))


def _point_at(chain: np.ndarray, s_m: float) -> tuple[np.ndarray, int]:
    """Point at arc length ``s_m`` along ``chain`` and the index of the next vertex."""
    legs = np.linalg.norm(np.diff(chain, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(legs)])
    if s_m >= cum[-1]:
        return chain[-1].copy(), chain.shape[0]
    j = int(np.searchsorted(cum, s_m, side="right")) - 1
    return chain[j] + (chain[j + 1] - chain[j]) * ((s_m - cum[j]) / max(legs[j], 1e-12)), j + 1


def _breach_time(rp, t_from: float, index: int, periphery_m: float) -> float:
    """First time >= ``t_from`` the intruder ``index`` is within ``periphery_m`` of the plan."""
    tracks, _ = rp.tracks()
    t_s, pts = rp.tl.samples(t_from, rp.p.tick_s)
    sep = np.zeros(tracks.n)
    sep[index] = periphery_m
    c = first_conflict(t_s, pts, tracks, sep)
    return c.t_s if c is not None else t_from


def _direct(rp, chain, speeds, v0: float, t_eff: float, tail, problem, budget_J: float):
    """The escape without a stop: the plan up to a braking distance ahead (the turn's lead-in),
    then ``tail`` from there, the corners smoothed by STEP III: ``(candidate or None, reason)``."""
    from skyroute.stages.base import InputError, PlanningError

    pre, nb = rp.braking_point(chain, v0)
    if nb >= chain.shape[0] - 1 and np.allclose(pre[-1], chain[-1]):
        return None, "the goal is within the braking distance"
    try:
        wp = tail(pre, nb, t_eff)
        full = np.concatenate([pre, wp[1:]])
        sp = np.concatenate([speeds[: pre.shape[0] - 1],
                             np.full(full.shape[0] - pre.shape[0], rp.veh.cruise_speed_mps)])
        cand = rp.finish(problem, full, sp, t_eff, v0, "octant", budget_J)
    except (PlanningError, InputError) as exc:
        return None, str(exc)
    return cand, "; ".join(cand.reasons)


def octant_replan(rp, k: int, ev, t_e: float, t_eff0: float, t_v: float, t_coll: float, update_s: float, cause: str,
                  detail) -> str | None:
    """Resolve the intruder conflict ``detail`` (a :class:`~skyroute.stages.tactical.conflict.Conflict`
    at ``t_v`` [s]) of the replay ``rp`` with the octant manoeuvre; ``"octant"`` when flown, else
    None (the caller lands).  Adds its :class:`LevelAttempt` row.  The manoeuvre starts when
    the intruder breaches P_r (``periphery_m``); when no escape is valid from there, P_r grows
    (x 1.5, 2, 3: the intruder is known, so it can be reacted to earlier), never earlier than
    ``t_eff0`` (the replanning time)."""
    t0 = time.perf_counter()
    tried_all: list[str] = []
    for grow in PERIPHERY_GROWTH:
        P = grow * rp.p.periphery_m
        t_b = _breach_time(rp, t_e, detail.index, P)
        t_eff = rp.effective_time(max(t_eff0, min(t_b, t_v)))
        res = _escape(rp, t_eff, P, detail, cause)
        tried_all.append(res["head"] + (": " + " | ".join(res["tried"][-2:]) if res["chosen"] is None else ""))
        if res["chosen"] is not None or t_b <= t_eff0:
            break
    secs = time.perf_counter() - t0
    if res["chosen"] is None:
        rp.attempts.append(LevelAttempt(k, ev.label, ev.t_s, t_coll, "octant", False, math.nan, math.nan, math.nan,
                                        math.nan, secs, update_s, math.nan, False,
                                        "no escape valid: " + " || ".join(tried_all)))
        return None
    cand, name, D = res["chosen"]
    rp.attempts.append(LevelAttempt(k, ev.label, ev.t_s, t_coll, "octant", True, cand.C_l, cand.C_e, cand.f,
                                    cand.max_sigma_p_m, secs, update_s, float(cand.t_s[-1]) - rp.tl.t_end_s, True,
                                    f"{res['head']}; escape {name} D = {D:.0f} m, min f of {res['n_ok']} valid "
                                    f"escapes ({cause})" + (f"; earlier: {' || '.join(tried_all[:-1])}"
                                                            if len(tried_all) > 1 else "")))
    rp.follow(cand, t_eff, "octant", k)
    return "octant"


def _escape(rp, t_eff: float, P_r: float, detail, cause: str) -> dict:
    """The escapes from ``t_eff`` (module docstring): ``{"chosen": (candidate, name, D) or
    None, "n_ok", "tried", "head"}``."""
    p = rp.p
    chain, speeds, _lead, v0 = rp.rest_chain(t_eff)
    own = chain[0]
    vel = rp.tl.velocity(t_eff)
    problem = rp.problem(own, rp.goal, zones_from_s=t_eff)
    budget = rp.budget_J(t_eff, problem)
    intr = rp.known.believed[detail.id]
    st = intruder_state(intr, t_eff)
    q, w = (st[0] - own, st[1]) if st is not None else (detail.intruder_xyz_m - own, detail.intruder_velocity_mps)
    frame = body_frame(vel, rp.goal - own)
    sep_i = rp.veh.r_p_m + intr.radius_m + p.d_c_m
    P = max(P_r, float(np.linalg.norm(q)) + 1e-6)
    threats = [(q, w)]                     # the conflicting intruder and every other one inside P_r
    for other in rp.known.intruders():
        so = intruder_state(other, t_eff) if other.id != detail.id else None
        if so is not None and float(np.linalg.norm(so[0] - own)) <= P:
            threats.append((so[0] - own, so[1]))
    chords = []
    for qi, wi in threats:
        ch = _chord(frame @ qi, frame @ (wi - vel), P)
        if ch is not None:
            chords.append((qi + ch[0] * (wi - vel), qi + ch[1] * (wi - vel)))
    vac, occ = rank_octants(chords, frame, P)
    el_max = 0.8 * rp.veh.max_flight_path_angle_deg
    tan_el = math.tan(math.radians(el_max))
    dirs = [(f"octant {o}", escape_direction(o, frame, max_elevation_deg=el_max)) for o in vac]
    pdirs, half = pocket_directions(8, elevations_deg=(-0.5 * el_max, 0.0, 0.5 * el_max))
    pockets = []
    for dvec in pdirs @ frame:
        dmin = min((_seg_point_d(P * dvec, a, b) for a, b in chords), default=math.inf)
        if dmin > P * math.sin(half):
            pockets.append((0 if float(dvec @ frame[0]) > 0 else 1, -dmin, dvec))
    pockets.sort(key=lambda x: (x[0], x[1]))
    dirs += [("pocket", d) for _, _, d in pockets]
    dirs = dirs[:MAX_DIRECTIONS]
    d_enc = along(chain, np.asarray(detail.own_xyz_m, float))
    zones = [z for z in rp.octant.zones if z.end_s > t_eff and first_in_zone(np.array([t_eff]), own[None], z,
                                                                              rp.veh.r_p_m) < 0]
    tried: list[str] = []
    chosen = None
    n_ok = 0
    for name, e in dirs:
        for fac in ESCAPE_FACTORS:
            D = fac * sep_i

            def tail(pre, nb, t_b, e=e, D=D):
                pb = pre[-1]
                E = pb + D * e
                s_r = max(d_enc, along(chain, pb)) + D
                R, j = _point_at(chain, s_r)
                while j < chain.shape[0] and abs(R[2] - E[2]) > tan_el * float(np.hypot(*(R - E)[:2])):
                    s_r += 0.25 * D                  # rejoin farther: the leg back within the angle
                    R, j = _point_at(chain, s_r)
                return np.concatenate([pb[None], E[None], R[None], chain[j:]])

            cand, why = _direct(rp, chain, speeds, v0, t_eff, tail, problem, budget)
            if cand is None or not cand.flyable:
                cand, why = rp.via_braking(chain, speeds, v0, t_eff, tail, lambda pb: problem, "octant", budget)
            if cand is not None and cand.flyable and zones:
                for z in zones:
                    kz = first_in_zone(cand.t_s, cand.xyz_m, z, rp.veh.r_p_m)
                    if kz >= 0:
                        cand.reasons.append(f"inside the dense zone {z.id!r} at t = {cand.t_s[kz]:.1f} s")
                        cand.flyable = False
                        why = cand.reasons[-1]
                        break
            if cand is not None and cand.flyable:
                n_ok += 1
                if chosen is None or cand.f < chosen[0].f:
                    chosen = (cand, name, D)
                break                     # a longer escape in the same direction only costs more
            tried.append(f"{name} D={D:.0f} m: {why[:120]}")
    head = (f"intruder {detail.id!r} breaches P_r = {P:.0f} m at t = {t_eff:.1f} s; occupied octants "
            f"{list(occ)}, vacant {vac}")
    return {"chosen": chosen, "n_ok": n_ok, "tried": tried, "head": head}


def zone_potential(rp, t_s: float, boxes) -> dict:
    """Seed 004's coupling of the zones and the potential field, at a change of the dense zone
    definition at ``t_s`` (module docstring): the dense zones ``boxes`` become obstacles of the
    replay's :class:`~skyroute.stages.tactical.zone_field.ZoneField` (computed in full the
    first time a zone meets the plan, updated incrementally at every later change, never
    otherwise); when the rest of the plan from the replanning time enters an active dense
    zone, the new global path is the gradient motion of the updated potential from where the
    vehicle turns (a braking distance ahead, or after a stop there), accepted only through
    STEP III, the validator and the exact separation and zone checks (part ``potential``).
    Returns what to add to the zone definition's log entry: ``potential`` ("", "full",
    "incremental"), ``potential_s`` [s], ``reroute`` (what happened to the plan)."""
    from skyroute.stages.base import InputError, PlanningError
    from skyroute.stages.tactical.zone_field import ZoneField

    out = {"potential": "", "potential_s": 0.0, "reroute": ""}
    t_eff = rp.effective_time(t_s + rp.p.t_rep_s)
    if t_eff >= rp.tl.t_end_s:
        out["reroute"] = "the flight ends before a new path could take effect"
        return out
    own = rp.tl.sample(t_eff)
    r_p = rp.veh.r_p_m
    zones = [z for z in rp.octant.zones if z.end_s > t_eff and first_in_zone(np.array([t_eff]), own[None], z, r_p) < 0]
    keep = {z.id for z in zones}
    boxes = tuple(b for b in boxes if f"dense-{b.bits}" in keep)     # a zone holding the vehicle cannot be avoided
    t_p, pts = rp.tl.samples(t_eff, rp.p.tick_s)
    entries = [(float(t_p[kz]), z) for z in zones if (kz := first_in_zone(t_p, pts, z, r_p)) >= 0]
    t_hit, hit = min(entries, key=lambda e: e[0]) if entries else (math.inf, None)
    zf = rp.octant.field
    t0 = time.perf_counter()
    try:
        if zf is None or rp.octant.field_world is not rp.world or not zf.covers(own):
            if hit is None:
                out["reroute"] = "the plan meets no dense zone"
                return out
            zf = ZoneField.build(rp.problem(own, rp.goal, zones_from_s=math.inf), boxes)
            rp.octant.field, rp.octant.field_world = zf, rp.world
            out["potential"] = "full"
        elif zf.set_zones(boxes):
            out["potential"] = "incremental"
    except (PlanningError, InputError) as exc:
        out["reroute"] = f"no zone potential field: {exc}"
        return out
    finally:
        out["potential_s"] = time.perf_counter() - t0
    if hit is None:
        out["reroute"] = "the plan meets no dense zone"
        return out
    k = rp.n_replan
    t1 = time.perf_counter()
    chain, speeds, _lead, v0 = rp.rest_chain(t_eff)
    problem = rp.problem(chain[0], rp.goal, zones_from_s=t_eff)
    budget = rp.budget_J(t_eff, problem)

    def tail(pre, nb, t_b):
        return zf.path_from(problem, pre[-1])

    cand, why = _direct(rp, chain, speeds, v0, t_eff, tail, problem, budget)
    if cand is None or not cand.flyable:
        cand, why = rp.via_braking(chain, speeds, v0, t_eff, tail, lambda pb: problem, "potential", budget)
    if cand is not None and cand.flyable:
        for z in zones:
            kz = first_in_zone(cand.t_s, cand.xyz_m, z, r_p)
            if kz >= 0:
                cand.flyable = False
                why = f"inside the dense zone {z.id!r} at t = {cand.t_s[kz]:.1f} s"
                break
    if cand is None or not cand.flyable:
        out["reroute"] = f"kept the plan (it enters {hit.id!r}): no valid potential-field path: {why[:200]}"
        return out
    rp.n_replan += 1
    rp.attempts.append(LevelAttempt(k, f"dense zones at t = {t_s:.1f} s", float(t_s), t_hit - t_s,
                                    "potential", True, cand.C_l, cand.C_e, cand.f, cand.max_sigma_p_m,
                                    time.perf_counter() - t1, out["potential_s"],
                                    float(cand.t_s[-1]) - rp.tl.t_end_s, True,
                                    f"the plan entered {hit.id!r}; gradient motion of the {out['potential'] or 'unchanged'}"
                                    " zone potential field"))
    rp.follow(cand, t_eff, "potential", k)
    out["reroute"] = f"new path from t = {t_eff:.1f} s (replanning {k})"
    return out
