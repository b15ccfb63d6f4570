"""Cross-checks of a validated scenario (every problem listed with its YAML path): points inside the AOI,
rasters, vehicle and planner, event positions."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from skyroute.pipeline.errors import ScenarioError
from skyroute.pipeline.settings.common import _is_file
from skyroute.pipeline.settings.events import (
    GnssEvent,
    IntruderEvent,
    IntruderUpdateEvent,
    WindEvent,
    _PolygonEvent,
)
from skyroute.pipeline.settings.schema import PLANNERS, Scenario


def _outside_aoi(grid, xy: np.ndarray) -> bool:
    import shapely

    return not shapely.Polygon(xy).intersects(shapely.box(*grid.bounds))

def _event_problems(sc: Scenario, labels: Sequence[str], check: Sequence[bool] | None = None) -> list[str]:
    """Checks of the (time-sorted) events that need the rest of the scenario: intruder ids,
    polygons against the AOI, data files.  ``labels[k]``: the YAML path of ``sc.events[k]``
    (its place in the file); ``check[k]`` False skips an event already checked."""
    problems: list[str] = []
    known: dict[str, str] = {i.id: "traffic.intruders" for i in sc.traffic.intruders}
    first_seen = {e.id: (e.t_s, labels[k]) for k, e in reversed(list(enumerate(sc.events)))
                  if isinstance(e, IntruderEvent)}
    try:
        grid = sc.grid
    except Exception:  # reported by the AOI check
        grid = None
    for k, e in enumerate(sc.events):
        lab, mine = labels[k], check is None or check[k]
        if isinstance(e, IntruderEvent):
            if mine and e.id in known:
                problems.append(f"{lab}: intruder {e.id!r} is already known ({known[e.id]}); "
                                "use kind intruder_update to give it a new track")
            known.setdefault(e.id, lab)
        elif isinstance(e, IntruderUpdateEvent) and mine and e.id not in known:
            later = first_seen.get(e.id)
            hint = (f"; intruder {e.id!r} appears only later, at {later[0]:g} s ({later[1]})" if later else "")
            problems.append(f"{lab}: intruder_update of unknown intruder {e.id!r} "
                            f"(known: {', '.join(known) or 'none'}){hint}")
        if not mine:
            continue
        if isinstance(e, _PolygonEvent) and grid is not None:
            key = "polygon" if e.polygon is not None else "polygon_lonlat"
            try:
                xy = e.polygon_xy(sc)
            except Exception as exc:
                problems.append(f"{lab}.{key}: cannot place the polygon on the map: {exc}")
                continue
            if _outside_aoi(grid, xy):
                xmin, ymin, xmax, ymax = grid.bounds
                problems.append(f"{lab}.{key}: the polygon lies outside the AOI x {xmin:.0f}..{xmax:.0f}, "
                                f"y {ymin:.0f}..{ymax:.0f} m (polygon x {xy[:, 0].min():.0f}..{xy[:, 0].max():.0f}, "
                                f"y {xy[:, 1].min():.0f}..{xy[:, 1].max():.0f}); check the coordinates"
                                + (" ([lon, lat] order)" if key == "polygon_lonlat" else " (map CRS metres)"))
        files: list[tuple[str, Path]] = []
        if isinstance(e, WindEvent) and e.wind is not None:
            files = [(f"{lab}.wind.path", e.wind.path)]
        elif isinstance(e, GnssEvent):
            files = [(f"{lab}.almanacs", a) for a in e.almanacs]
        for where, f in files:
            why = _data_file_problem(f)
            if why is not None:
                problems.append(f"{where}: {why}")
    return problems

def _data_file_problem(p) -> str | None:
    """Why a data path is not a regular file: not found, a folder, a FIFO, a device (the wording
    of :func:`~skyroute.stages.base.read_limited`), or None."""
    from skyroute.stages.base import file_problem

    return file_problem(p, "data")


def _semantic_problems(sc: Scenario) -> list[str]:
    """Checks that need several sections at once (all collected, none raised)."""
    problems: list[str] = []
    for section, paths in (
        ("data.buildings.path", [sc.data.buildings.path] if sc.data.buildings else []),
        ("data.terrain.path", [sc.data.terrain.path] if sc.data.terrain else []),
        ("data.surface.path", list(sc.data.surface.paths) if sc.data.surface else []),
        ("data.landuse", [sc.data.landuse] if sc.data.landuse else []),
        ("data.landing_sites", [sc.data.landing_sites] if sc.data.landing_sites else []),
        ("data.risk_tags", [sc.data.risk_tags] if sc.data.risk_tags else []),
        ("data.wind.path", [sc.data.wind.path] if sc.data.wind else []),
        ("data.almanacs", list(sc.data.almanacs)),
        ("constraints.nofly_zones", [sc.constraints.nofly_zones] if sc.constraints.nofly_zones else []),
    ):
        for p in paths:
            why = _data_file_problem(p)
            if why is not None:
                problems.append(f"{section}: {why}")
            elif not os.access(p, os.R_OK):
                problems.append(f"{section}: data file is not readable: {p}")
    ds_, dt_ = sc.data.surface, sc.data.terrain
    if ds_ is not None and dt_ is not None and ds_.vertical_datum.strip().lower() != dt_.vertical_datum.strip().lower():
        problems.append(f"data.surface.vertical_datum: {ds_.vertical_datum!r} differs from data.terrain.vertical_datum "
                        f"{dt_.vertical_datum!r}; convert one raster so the DSM and the DEM share a vertical datum")
    from skyroute.stages.vehicle import known_vehicles

    if sc.vehicle not in known_vehicles() and not _is_file(sc.vehicle):
        problems.append(f"vehicle: unknown vehicle {sc.vehicle!r}; known vehicles: {', '.join(known_vehicles())}")
    else:
        problems.extend(_vehicle_file_problems(sc))
        problems.extend(_vehicle_altitude_problems(sc))
        problems.extend(planner_vehicle_problems(sc))
    problems.extend(_raster_problems(sc))
    if sc.aoi.crs is not None:
        try:
            from pyproj import CRS

            crs = CRS.from_user_input(sc.aoi.crs)
            if not crs.is_projected:
                problems.append(f"aoi.crs: {sc.aoi.crs!r} is not a projected CRS in metres (its units are "
                                f"{crs.axis_info[0].unit_name if crs.axis_info else 'not metres'}); give a projected "
                                "CRS such as the UTM zone ('EPSG:326NN'), or omit aoi.crs with bounds_lonlat")
                return problems
        except Exception:
            pass  # an unknown CRS: the grid below says so
    try:
        grid = sc.grid
    except Exception as exc:  # CRSError / InputError
        problems.append(f"aoi: {exc}")
        return problems
    cmax = sc.constraints.max_altitude_agl_m
    cmin = sc.constraints.min_altitude_agl_m
    placed: dict[str, tuple[float, float]] = {}
    for name in ("start", "goal"):
        p = getattr(sc.mission, name)
        try:
            x, y = sc.point_xy(p)
        except Exception as exc:
            problems.append(f"mission.{name}: cannot place the point on the map: {exc}")
            continue
        placed[name] = (float(x), float(y))
        why = mission_point_problem(grid, float(x), float(y))
        if why:
            problems.append(f"mission.{name}: {why}")
        if p.alt_agl_m > cmax:
            problems.append(f"mission.{name}: altitude {p.alt_agl_m:g} m is above constraints.max_altitude_agl_m {cmax:g}")
        if p.alt_agl_m < cmin:
            problems.append(f"mission.{name}: altitude {p.alt_agl_m:g} m is below constraints.min_altitude_agl_m {cmin:g}")
    if len(placed) == 2:
        problems.extend(_coincident_problems(sc, placed["start"], placed["goal"]))
    for k, o in enumerate(sc.data.obstacles):
        if _outside_aoi(grid, np.asarray(o.polygon)):
            problems.append(f"data.obstacles[{k}].polygon: the polygon lies outside the AOI; check the coordinates (map CRS metres)")
    return problems

COINCIDE_M = 1e-6   # [m] start and goal this close (horizontally and in altitude) are one point


def mission_point_problem(grid, x: float, y: float) -> str:
    """Why the map point (x, y) [m] cannot be a mission point of ``grid`` ("" when it can).

    A point belongs to the cell whose west and north edges it lies on (cells are half-open:
    ``x0 + c r <= x < x0 + (c + 1) r``), so the grid holds ``xmin <= x < xmax`` and
    ``ymin < y <= ymax``: a point on the east or south edge of the grid (e.g. the AOI's
    south-east corner) lies in no cell, and the planner would refuse it only after the maps.
    The message gives the grid's actual bounds (the AOI snapped to the lattice of multiples of
    ``aoi.resolution_m``: ``aoi.bounds`` inward, ``aoi.bounds_lonlat`` outward) and the x / y
    that work.
    """
    xmin, ymin, xmax, ymax = grid.bounds
    r = grid.resolution_m
    if xmin <= x < xmax and ymin < y <= ymax:
        return ""
    box = (f"the AOI's planning grid x {xmin:.10g}..{xmax:.10g}, y {ymin:.10g}..{ymax:.10g} m "
           f"(the aoi snapped to its {r:g} m lattice; {grid.crs.name})")
    if xmin <= x <= xmax and ymin <= y <= ymax:   # on the east or south edge
        edge = " and ".join(e for e, on in (("east", x >= xmax), ("south", y <= ymin)) if on)
        edge += " edges" if " and " in edge else " edge"
        return (f"point ({x:.10g}, {y:.10g}) m lies on the {edge} of {box}, which no cell holds: "
                f"give x < {xmax:.10g} and y > {ymin:.10g} (e.g. move it {min(r / 2, 1.0):g} m inside) "
                "or enlarge aoi")
    return (f"point ({x:.10g}, {y:.10g}) m is outside {box}; give {xmin:.10g} <= x < {xmax:.10g} and "
            f"{ymin:.10g} < y <= {ymax:.10g}, or enlarge aoi")


def _coincident_problems(sc: Scenario, start_xy: tuple[float, float],
                         goal_xy: tuple[float, float]) -> list[str]:
    """Start and goal at one point (same map position and altitude above ground): there is no
    mission to plan (the planner would refuse it only after the maps)."""
    d = float(np.hypot(goal_xy[0] - start_xy[0], goal_xy[1] - start_xy[1]))
    dz = abs(sc.mission.goal.alt_agl_m - sc.mission.start.alt_agl_m)
    if d > COINCIDE_M or dz > COINCIDE_M:
        return []
    return [f"mission.goal: the goal ({goal_xy[0]:.10g}, {goal_xy[1]:.10g}) m at "
            f"{sc.mission.goal.alt_agl_m:g} m AGL is the start (mission.start): there is no flight to plan; "
            "move mission.goal (or give it another alt_agl_m for a vertical flight)"]


def _raster_problems(sc: Scenario) -> list[str]:
    """A DSM or DEM must be one band of numeric heights (a 3-band RGB image or a paletted map
    is not); only the header is read."""
    out = []
    rasters = [("data.surface.path", p) for p in (sc.data.surface.paths if sc.data.surface else ())]
    rasters += [("data.terrain.path", sc.data.terrain.path)] if sc.data.terrain else []
    for key, p in rasters:
        if not _is_file(p):
            continue
        try:
            import rasterio

            with rasterio.open(p) as src:
                count, dtype = src.count, np.dtype(src.dtypes[0])
                interp = [str(c.name) for c in src.colorinterp]
        except Exception:   # not a raster rasterio can open: the stage says so with its reader's message
            continue
        if count != 1:
            out.append(f"{key}: {p} has {count} bands ({', '.join(interp)}); a DSM / DEM is one band of heights [m] "
                       "(an RGB image is not): give the height raster")
        elif dtype.kind not in "iuf" or interp[0] == "palette":
            out.append(f"{key}: {p} holds {dtype} {interp[0]} values, not heights [m]: give the height raster")
    return out

def _vehicle_max_altitude_m(sc: Scenario) -> float | None:
    from skyroute.stages.vehicle import load_vehicle

    try:
        return float(load_vehicle(sc.vehicle).max_altitude_m)
    except Exception:  # an unreadable vehicle is reported by its own check
        return None

def planner_vehicle_problems(sc: Scenario) -> list[str]:
    """``planner.name`` must fit the vehicle's kind (rotorcraft / fixed-wing planners)."""
    from skyroute.stages.base import InputError
    from skyroute.stages.planning.kinds import check_planner_vehicle

    try:
        check_planner_vehicle(sc.planner.name, sc.vehicle, PLANNERS)
    except InputError as exc:
        return [f"planner.name: {exc}"]
    except Exception:  # an unreadable vehicle is reported by its own check
        return []
    return []

def _vehicle_file_problems(sc: Scenario) -> list[str]:
    """The vehicle profile's own problems (a vehicle YAML that is not UTF-8, not YAML or not a
    valid profile), found when the scenario is loaded rather than when a stage needs it."""
    from skyroute.stages.base import SkyrouteError
    from skyroute.stages.vehicle import load_vehicle

    try:
        load_vehicle(sc.vehicle)
    except ScenarioError as exc:
        return [f"vehicle ({exc.source}): {p}" for p in exc.problems]
    except SkyrouteError as exc:
        return [f"vehicle: {exc}"]
    return []

def _vehicle_altitude_problems(sc: Scenario) -> list[str]:
    vmax = _vehicle_max_altitude_m(sc)
    cmax = sc.constraints.max_altitude_agl_m
    if vmax is None or "max_altitude_agl_m" not in sc.constraints.model_fields_set or cmax <= vmax:
        return []
    return [f"constraints.max_altitude_agl_m: {cmax:g} m AGL exceeds the maximum altitude of vehicle "
            f"{sc.vehicle!r}, {vmax:g} m AGL; lower it to <= {vmax:g}"]

def _clamp_default_max_altitude(sc: Scenario) -> Scenario:
    """No ``max_altitude_agl_m`` given: the vehicle's maximum applies when it is lower."""
    vmax = _vehicle_max_altitude_m(sc)
    c = sc.constraints
    if vmax is None or "max_altitude_agl_m" in c.model_fields_set or c.max_altitude_agl_m <= vmax:
        return sc
    return sc.model_copy(update={"constraints": c.model_copy(update={"max_altitude_agl_m": vmax})})
