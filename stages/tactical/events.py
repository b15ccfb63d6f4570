"""Tactical events of the replay and the tests on them shared by its behaviours (levels,
octant, escape): :class:`TacticalEvent`, the event-log record, and when a timed path is inside a
temporary no-fly zone."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from skyroute.stages.tactical.log import NoFlyZone
from skyroute.stages.traffic import Intruder

__all__ = ["TacticalEvent", "event_record", "first_in_zone"]


@dataclass(frozen=True)
class TacticalEvent:
    """One event, in the map CRS with heights in the surface datum.

    ``kind``: intruder, intruder_update, wind, gnss, nofly, obstacle; ``t_s`` [s]: when it
    happens; ``label``: e.g. ``"intruder tac-1"``.  ``intruder``: the declared track (intruder
    kinds); ``zone``: the temporary no-fly zone (nofly); map-changing kinds (wind, gnss,
    obstacle) are applied by the ``world_at`` callback of :func:`replay`."""

    t_s: float
    kind: str
    label: str
    intruder: Intruder | None = None
    zone: NoFlyZone | None = None

    @property
    def changes_maps(self) -> bool:
        return self.kind in ("wind", "gnss", "obstacle")


def event_record(ev: TacticalEvent, t_known: float, t_coll: float, outcome: str, cause: str = "") -> dict:
    """One entry of ``FlightLog.events``: the event, when it was known, ``t_coll_s`` [s] and
    what happened (``outcome``, ``cause``)."""
    return {"t_s": ev.t_s, "kind": ev.kind, "label": ev.label, "t_known_s": t_known, "t_coll_s": t_coll,
            "outcome": outcome, "cause": cause}


def first_in_zone(t_s: np.ndarray, p: np.ndarray, z: NoFlyZone, r_m: float) -> int:
    """Index of the first sample inside zone ``z`` (polygon and band widened by ``r_m``)
    while it is active, or -1."""
    from matplotlib.path import Path as MplPath

    act = (t_s >= z.start_s) & (t_s <= z.end_s) & (p[:, 2] >= z.z_min_m - r_m) & (p[:, 2] <= z.z_max_m + r_m)
    if not act.any():
        return -1
    from shapely.geometry import Polygon

    poly = Polygon(z.polygon_xy).buffer(r_m)
    path = MplPath(np.asarray(poly.exterior.coords))
    inside = path.contains_points(p[:, :2]) & act
    return int(np.argmax(inside)) if inside.any() else -1
