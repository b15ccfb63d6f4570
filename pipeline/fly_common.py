"""What both ``skyroute fly`` paths share (the rotorcraft replay in :mod:`.fly`, seed 002's
fixed-wing local planner in :mod:`.fly_fw`): the result type, the replay's maps from a run's
stages, and the scenario's events as :class:`~skyroute.stages.tactical.events.TacticalEvent`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import xarray as xr

from skyroute.pipeline.runner import RunResult
from skyroute.pipeline.settings import Scenario
from skyroute.stages.planning.request import (
    PLANNER_STAGES as MAP_STAGES,  # the maps a planner reads (one list)
)

__all__ = ["MAP_STAGES", "FlyResult", "tactical_events"]


@dataclass
class FlyResult:
    result: RunResult      # the stages of the strategic plan
    log: object            # skyroute.stages.tactical.log.FlightLog
    map_updates: list      # RunResult of each map update


def _world(result: RunResult, sc: Scenario | None = None, radius_m: float | None = None,
           window: tuple[slice, slice] | None = None):
    """The replay's maps from a run's stages.  With ``radius_m`` (the safety bubble's r_j of
    the plan's level, ``constraints.clearance: sboa``) the clearance maps are the clearance
    stage's for r_j, as the plan stage used them, instead of the cached ones for r_p.  With a
    ``window`` (rows, cols; :func:`~skyroute.stages.planning.window.path_window`, a city-scale
    AOI) the maps on the AOI's grid are read cropped to it: cropping keeps every cell's value."""
    from skyroute.stages.planning.window import crop_on_grid
    from skyroute.stages.tactical.replay import World

    shape = (result["surface"].sizes["y"], result["surface"].sizes["x"])

    def crop(ds):
        return ds if window is None or ds is None else crop_on_grid(ds, *window, shape)

    def get(name):
        return crop(result.datasets[name]).load() if name in result.datasets else None

    surf = result["surface"]
    clearance = get("clearance")
    if radius_m is not None and sc is not None:
        from skyroute.pipeline.stages_builtin import _clearance_settings, clearance_stage

        clearance = clearance_stage(surf, result["environment"],
                                    settings=_clearance_settings(sc).model_copy(update={"radius_m": float(radius_m)}))
        clearance = crop(clearance).load()
    return World(surface=crop(surf[[v for v in ("terrain", "terrain_min", "surface") if v in surf]]).load(),
                 environment=get("environment"), clearance=clearance, wind=get("wind"),
                 coverage=get("coverage"), satellites=get("satellites"))


def tactical_events(sc: Scenario, surface: xr.Dataset) -> list:
    """The scenario's events as :class:`~skyroute.stages.tactical.replay.TacticalEvent`
    (map CRS, heights in the surface datum: AGL + the terrain of the cell)."""
    from skyroute.stages.grid import Grid
    from skyroute.stages.tactical.events import TacticalEvent
    from skyroute.stages.tactical.log import NoFlyZone
    from skyroute.stages.traffic import intruders_for

    g = Grid.from_dataarray(surface["terrain"])
    terrain = surface["terrain"]      # (lazy on a city: only each zone's box is read)
    out = []
    for n, ev in enumerate(sc.events):
        ident = getattr(ev, "id", None) or f"{ev.kind}-{n}"
        label = f"{ev.kind} {ident}"
        if ev.kind in ("intruder", "intruder_update"):
            radius = getattr(ev, "radius_m", None)
            if radius is None:
                radius = _radius_of(sc, ev.id)
            (it,) = intruders_for([{"id": ev.id, "radius_m": float(radius), "waypoints": ev.track()}], surface)
            out.append(TacticalEvent(float(ev.t_s), ev.kind, label, intruder=it))
        elif ev.kind == "nofly":
            poly = np.asarray(ev.polygon_xy(sc), float)
            r, c = g.cell_of(poly[:, 0], poly[:, 1])
            r0, r1, c0, c1 = r.min(), r.max(), c.min(), c.max()
            t_box = np.asarray(terrain[r0:r1 + 1, c0:c1 + 1].values, float)
            start = float(ev.start_s if ev.start_s is not None else ev.t_s)
            end = float(ev.end_s) if ev.end_s is not None else math.inf
            zone = NoFlyZone(ident, poly, float(np.min(t_box) + ev.min_agl_m), float(np.max(t_box) + ev.max_agl_m),
                             start, end)
            out.append(TacticalEvent(float(ev.t_s), ev.kind, label, zone=zone))
        else:
            out.append(TacticalEvent(float(ev.t_s), ev.kind, label))
    return out


def _radius_of(sc: Scenario, ident: str) -> float:
    for it in sc.traffic.intruders:
        if it.id == ident:
            return float(it.radius_m)
    for ev in sc.events:
        if ev.kind == "intruder" and ev.id == ident:
            return float(ev.radius_m)
    return 2.0


def shortest_flight_s(sc: Scenario) -> float:
    """A lower bound of the flight's duration [s]: the straight line at the vehicle's top speed."""
    from skyroute.stages.vehicle import load_vehicle

    (x0, y0), (x1, y1) = sc.point_xy(sc.mission.start), sc.point_xy(sc.mission.goal)
    veh = load_vehicle(sc.vehicle)
    v = max(float(getattr(veh, name, 0.0) or 0.0) for name in ("max_airspeed_mps", "cruise_speed_mps"))
    return math.hypot(x1 - x0, y1 - y0) / v if v > 0 else 0.0
