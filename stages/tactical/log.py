"""The flight record of a tactical replay (``skyroute fly``): what was flown, what was tried.

Every array is in the scenario's map CRS [m] with heights in the surface model's vertical
datum (``FlightLog.vertical_datum``); times are seconds since the mission start
(``FlightLog.start_time_utc``, UTC).  The outputs (:mod:`.outputs`) are written from a
:class:`FlightLog` only.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["FlightLog", "FlownPart", "IntruderTrack", "LevelAttempt", "NoFlyZone", "PART_NAMES", "fly_summary_line"]

PART_NAMES = ("strategic", "L1", "L2", "L3", "octant", "potential", "landing", "escape", "resume", "climb", "right",
              "left", "loiter", "descend")


@dataclass
class FlownPart:
    """One contiguous piece of the ownship's flown trajectory.

    ``part``: one of :data:`PART_NAMES`; ``t_s`` (k,) [s] strictly increasing; ``xyz_m``
    (k, 3) [m]; ``speed_mps`` (k,) ground speed [m/s]; ``replanning``: index of the
    replanning (into ``FlightLog.attempts``' ``replanning``) that produced it, ``None`` for the
    strategic part.  Consecutive parts share their boundary sample."""

    part: str
    t_s: np.ndarray
    xyz_m: np.ndarray
    speed_mps: np.ndarray
    replanning: int | None = None


@dataclass
class LevelAttempt:
    """One row of ``tactical.csv``: one level tried at one replanning (seed 001 Tables 3, 5).

    ``level``: ``"1"``, ``"2"``, ``"3"`` or ``"landing"``; costs [m] are the tactical eq. 11
    terms of the new remainder of the flight (risk and landing terms dropped); ``compute_s``
    [s]: search + smoothing + validation of that level with compiled kernels warm; ``update_s``
    [s]: the map updates of that replanning (same value on each of its rows);
    ``added_flight_time_s`` [s]: arrival time at the goal (or touchdown) minus the arrival time
    of the plan it replaces; ``reasons``: why not flyable, or why not chosen."""

    replanning: int
    event: str
    t_event_s: float
    t_coll_s: float
    level: str
    flyable: bool
    C_l_m: float
    C_e_m: float
    f_m: float
    max_sigma_p_m: float
    compute_s: float
    update_s: float
    added_flight_time_s: float
    chosen: bool
    reasons: str = ""
    intruder: str = ""              # the intruder of the conflict ("" for maps, zones, wind)
    t_los_s: float = float("nan")   # [s] predicted time to loss of separation when the conflict was known
    alert: str = ""                 # DAA alert level then (none / preventive / corrective / warning, :mod:`.daa`)


@dataclass
class IntruderTrack:
    """An intruder's truth: its latest declared track (waypoint times ``t_s`` [s] and
    positions ``xyz_m`` (k, 3) [m], linear between waypoints), radius ``radius_m`` [m];
    ``kind``: ``"strategic"`` (known at planning time) or ``"tactical"``; ``known_from_s``:
    when the ownship learnt of it [s]; ``declared``: every track version as
    ``(t_declared_s, t_s, xyz_m)`` (for the figures)."""

    id: str
    radius_m: float
    t_s: np.ndarray
    xyz_m: np.ndarray
    kind: str = "strategic"
    known_from_s: float = 0.0
    declared: list = field(default_factory=list)


@dataclass
class NoFlyZone:
    """A temporary no-fly zone: polygon ``polygon_xy`` (k, 2) [m, map CRS], altitude band
    ``z_min_m`` .. ``z_max_m`` [m, surface datum], active ``start_s`` .. ``end_s`` [s]."""

    id: str
    polygon_xy: np.ndarray
    z_min_m: float
    z_max_m: float
    start_s: float
    end_s: float


@dataclass
class FlightLog:
    """Everything a replay produced.

    ``parts``: the flown trajectory (:class:`FlownPart`, in time order); ``planned``: the
    strategic plan as planned (``t_s`` (n,), ``xyz_m`` (n, 3)); ``attempts``: every level tried
    (:class:`LevelAttempt`); ``events``: one dict per event (``t_s``, ``kind``, ``label``,
    ``t_known_s``, ``t_coll_s`` (inf when the plan was not compromised), ``outcome``: ``"no
    conflict"``, ``"replanned L1"`` ..., ``"landing"``); ``intruders`` and ``nofly``: the
    traffic and temporary zones (truth); ``outcome``: ``"goal"``, ``"landed"`` or
    ``"failed"`` with ``reason``.  Map context for the figures (the maps at the end of the
    flight, so new obstacles show): ``grid`` (a
    :class:`~skyroute.stages.grid.Grid`), ``terrain_m``, ``surface_m`` and
    ``coverage_floor_m`` (ny, nx) [m] (the floor of the plan's DOP level ``dop_threshold``;
    ``None`` without GNSS data), ``landing_xy`` (k, 2) [m] landing sites; ``energy_Wh``: the
    energy of the flown trajectory (rotor power in the last known wind)."""

    scenario: str
    crs_wkt: str
    vertical_datum: str
    start_time_utc: str
    planned_t_s: np.ndarray
    planned_xyz_m: np.ndarray
    parts: list[FlownPart] = field(default_factory=list)
    attempts: list[LevelAttempt] = field(default_factory=list)
    events: list[dict] = field(default_factory=list)
    intruders: list[IntruderTrack] = field(default_factory=list)
    nofly: list[NoFlyZone] = field(default_factory=list)
    outcome: str = "goal"
    reason: str = ""
    dop_threshold: float | None = None
    t_rep_s: float = 5.0
    tick_s: float = 0.1
    seed: int = 0
    own_radius_m: float = 0.0
    margin_m: float = 0.0
    # safety bubble (constraints.clearance: sboa): {"k", "surface_uncertainty_m", "clearance_radius_m"}
    bubble: dict | None = None
    compile_s: float = 0.0       # [s] kernel compilation and the take-off maps' line-of-sight heights
    warnings: list[str] = field(default_factory=list)
    grid: object | None = None
    terrain_m: np.ndarray | None = None
    surface_m: np.ndarray | None = None
    coverage_floor_m: np.ndarray | None = None
    landing_xy: np.ndarray | None = None
    energy_Wh: float | None = None
    method: str = "levels"                  # tactical method: levels (1-3), octant (seed 004) or local (seed 002)
    dense_zones: list = field(default_factory=list)   # octant method: dense zone definitions (dicts)
    local: dict | None = None     # local method (fixed-wing, seed 002): ranges, delay, added energy, clearance
    escapes: list = field(default_factory=list)   # escape decisions (dicts, :mod:`.escape`)
    losses: list = field(default_factory=list)    # accepted (unavoidable) predicted losses of separation (dicts)

    def flown(self) -> tuple[np.ndarray, np.ndarray]:
        """The whole flown trajectory ``(t_s (m,), xyz_m (m, 3))``, shared part boundaries once."""
        if not self.parts:
            return np.zeros(0), np.zeros((0, 3))
        ts, ps = [self.parts[0].t_s], [self.parts[0].xyz_m]
        for p in self.parts[1:]:
            k = 1 if (p.t_s.size and ts[-1].size and p.t_s[0] <= ts[-1][-1]) else 0
            ts.append(p.t_s[k:])
            ps.append(p.xyz_m[k:])
        return np.concatenate(ts), np.concatenate(ps)


def fly_summary_line(sec: dict[str, Any]) -> str:
    """One line of a :func:`flight_section`: outcome, replannings and chosen levels, flight
    time and the smallest separation margin."""
    levels = ", ".join(f"L{v}" if v in ("1", "2", "3") else v for v in sec["chosen_levels"]) or "none"
    head = {"goal": "reached the goal", "landed": "landed", "failed": "failed"}.get(sec["outcome"], sec["outcome"])
    why = f" ({sec['reason']})" if sec["reason"] and sec["outcome"] != "goal" else ""
    seps = [r for r in sec["min_separation"] if r["clearance_m"] is not None]
    sep = ""
    if seps:
        r = min(seps, key=lambda r: r["clearance_m"])
        sep = f", closest intruder {r['id']} at {r['min_distance_m']:.1f} m (margin {r['clearance_m']:+.1f} m)"
    ft = "" if sec["flight_time_s"] is None else f", flight time {sec['flight_time_s']:.1f} s"
    return f"fly: {head}{why}; {sec['n_replannings']} replannings ({levels}){ft}{sep}"
