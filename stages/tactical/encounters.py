"""Synthetic encounters for the tactical replay: intruders crossing the ownship's plan (issue 22).

An :class:`Encounter` is one to three intruders, each crossing the ownship's **planned** position
at a mission time ``t_cross_s``: it flies a straight line through that point (shifted sideways by
``offset_m``; 0 is a collision course with the plan) with heading ``bearing_deg`` relative to the
ownship's horizontal velocity there (0: same direction, 180: head-on), horizontal speed
``speed_mps`` and vertical speed ``climb_mps`` (level when 0), and becomes known
``known_ahead_s`` before the crossing (a ``uspace`` report of its whole track, or a ``v2v``
broadcast of its position and velocity: both are straight lines, so the two only differ in the
label).  :func:`encounter_events` turns it into the replay's events, :func:`flown_losses`
measures what was flown by brute force, and :func:`unavoidable_certificate` is an independent
physical proof that a loss could not be avoided by any manoeuvre within the acceleration limit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from skyroute.stages.traffic import Intruder

__all__ = ["Encounter", "EncounterIntruder", "draw_encounter", "encounter_events", "flown_losses",
           "unavoidable_certificate"]


@dataclass(frozen=True)
class EncounterIntruder:
    """One intruder of an :class:`Encounter` (module docstring); ``radius_m`` [m]."""

    t_cross_s: float
    bearing_deg: float
    speed_mps: float
    climb_mps: float
    known_ahead_s: float
    via: str = "uspace"
    offset_m: float = 0.0
    radius_m: float = 1.0


@dataclass(frozen=True)
class Encounter:
    intruders: tuple[EncounterIntruder, ...]


def draw_encounter(rng: np.random.Generator, t_from_s: float, t_to_s: float, max_intruders: int = 3) -> Encounter:
    """A random encounter: 1..``max_intruders`` intruders crossing the plan by ``t_to_s`` [s] and
    known 5-60 s ahead, not before ``t_from_s`` [s] (so the crossing is at least that long after
    it), from any bearing, 0-25 m/s, climbing (-3..3 m/s) or level, via U-space or V2V, on a
    collision course or up to 10 m off."""
    n = int(rng.integers(1, max_intruders + 1))
    out = []
    for _ in range(n):
        ahead = float(rng.uniform(5.0, min(60.0, max(t_to_s - t_from_s, 5.0))))
        out.append(EncounterIntruder(
            t_cross_s=float(rng.uniform(t_from_s + ahead, max(t_to_s, t_from_s + ahead))),
            bearing_deg=float(rng.uniform(0.0, 360.0)), speed_mps=float(rng.uniform(0.0, 25.0)),
            climb_mps=float(rng.choice([0.0, rng.uniform(-3.0, 3.0)])),
            known_ahead_s=ahead, via=str(rng.choice(["uspace", "v2v"])),
            offset_m=float(rng.choice([0.0, rng.uniform(-10.0, 10.0)])), radius_m=float(rng.uniform(0.5, 2.0))))
    return Encounter(tuple(out))


def _state(traj, t0_s: float, t_s: float) -> tuple[np.ndarray, np.ndarray]:
    tau = min(max(t_s - t0_s, 0.0), float(traj.duration_s))
    return traj.sample([tau])[0], traj.velocity([tau])[0]


def encounter_intruders(enc: Encounter, plan_traj, plan_t0_s: float, *, before_s: float = 90.0,
                        after_s: float = 90.0) -> list[tuple[float, Intruder, str]]:
    """``(t_known_s, Intruder, via)`` per intruder of ``enc`` against the plan (a
    CornerTrajectory flown from ``plan_t0_s``): straight tracks from ``before_s`` [s] before the
    crossing to ``after_s`` after it (heights in the plan's datum)."""
    out = []
    for j, it in enumerate(enc.intruders):
        p, v = _state(plan_traj, plan_t0_s, it.t_cross_s)
        h = np.array([v[0], v[1]])
        nh = float(np.linalg.norm(h))
        head = math.atan2(h[1], h[0]) if nh > 1e-6 else 0.0
        a = head + math.radians(it.bearing_deg)
        w = np.array([it.speed_mps * math.cos(a), it.speed_mps * math.sin(a), it.climb_mps])
        side = np.array([-math.sin(head), math.cos(head), 0.0])
        pc = p + it.offset_m * side
        t = np.array([it.t_cross_s - before_s, it.t_cross_s + after_s])
        xyz = np.stack([pc - w * before_s, pc + w * after_s])
        out.append((it.t_cross_s - it.known_ahead_s, Intruder(f"enc-{j}", t, xyz, it.radius_m), it.via))
    return out


def encounter_events(enc: Encounter, plan_traj, plan_t0_s: float) -> list:
    """The replay's :class:`~skyroute.stages.tactical.events.TacticalEvent` of ``enc``."""
    from skyroute.stages.tactical.events import TacticalEvent

    return [TacticalEvent(max(t_known, 0.0), "intruder", f"intruder {it.id} ({via})", intruder=it)
            for t_known, it, via in encounter_intruders(enc, plan_traj, plan_t0_s)]


def flown_losses(log, step_s: float = 0.05, known_only: bool = False) -> dict[str, float]:
    """Per intruder of a FlightLog, the smallest distance minus the required separation [m]
    (r_p + r_i + d_c) over the flight, by brute force every ``step_s`` [s] (both linear between
    their samples); negative = a loss of separation.  ``known_only``: only from the time the
    ownship knew of the intruder (a replanned path may meet an intruder before anyone reports
    it: no replay can avoid what it does not know)."""
    t, p = log.flown()
    out: dict[str, float] = {}
    if t.size < 2:
        return out
    tt = np.arange(t[0], t[-1] + 1e-9, step_s)
    own = np.column_stack([np.interp(tt, t, p[:, k]) for k in range(3)])
    for it in log.intruders:
        ti, xi = np.asarray(it.t_s, float), np.asarray(it.xyz_m, float)
        live = (tt >= ti[0]) & (tt <= ti[-1])
        if known_only:
            live &= tt >= float(getattr(it, "known_from_s", -math.inf))
        if not live.any():
            continue
        q = np.column_stack([np.interp(tt[live], ti, xi[:, k]) for k in range(3)])
        need = float(log.own_radius_m) + float(it.radius_m) + float(log.margin_m)
        out[str(it.id)] = float(np.min(np.linalg.norm(own[live] - q, axis=1)) - need)
    return out


def unavoidable_certificate(p0, v0, t0_s: float, intruder_t_s, intruder_xyz_m, sep_m: float, a_max_mps2: float,
                            horizon_s: float = 60.0, step_s: float = 0.01) -> float | None:
    """An independent proof that a loss of separation cannot be avoided: the first time [s] >=
    ``t0_s`` at which the ball of every position reachable from the state (``p0`` [m], ``v0``
    [m/s]) at ``t0_s`` with accelerations of norm <= ``a_max_mps2`` -- centre ``p0 + v0 tau``,
    radius ``a_max tau^2 / 2`` -- lies entirely inside the intruder's separation sphere
    (``sep_m`` around its position), or None (no proof: some trajectory may escape).  Checked on
    a grid of ``step_s``; the intruder track is linear between its waypoints."""
    ti = np.asarray(intruder_t_s, float)
    xi = np.asarray(intruder_xyz_m, float)
    t = np.arange(max(t0_s, ti[0]), min(t0_s + horizon_s, ti[-1]) + 1e-12, step_s)
    if t.size == 0:
        return None
    tau = t - t0_s
    q = np.column_stack([np.interp(t, ti, xi[:, k]) for k in range(3)])
    c = np.asarray(p0, float)[None] + np.asarray(v0, float)[None] * tau[:, None]
    inside = np.linalg.norm(q - c, axis=1) + 0.5 * a_max_mps2 * tau * tau < sep_m
    return float(t[np.argmax(inside)]) if inside.any() else None
