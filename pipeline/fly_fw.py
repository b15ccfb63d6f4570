"""``skyroute fly`` for fixed-wing scenarios: seed 002's local planner (``--tactical local``).

The strategic plan (EEA* or another fixed-wing planner) comes from the cached stages; the
aircraft flies it in :func:`~skyroute.stages.tactical.fw_local.simulate_local` with the
scenario's intruders (``traffic.intruders`` and ``intruder`` / ``intruder_update`` events:
sensed within ``tactical.uav_range_m``, the aircraft turns right) and its ``obstacle`` events
(static obstacles unknown to the plan, present from the event time: sensed within
``tactical.obstacle_range_m``, the aircraft climbs over them).  The maps are not updated
during the flight (the local planner reacts to its sensors only), so wind, GNSS and no-fly
events are refused with a message.
"""

from __future__ import annotations

import math

import numpy as np

from skyroute.pipeline.cache import Cache
from skyroute.pipeline.errors import InputError
from skyroute.pipeline.runner import run_scenario
from skyroute.pipeline.settings import Scenario, check_event_times

__all__ = ["LOCAL_EVENT_KINDS", "crossing_routes", "fleet_problems", "fly_fixedwing", "local_params", "local_problem",
           "obstacles_of"]

LOCAL_EVENT_KINDS = ("intruder", "intruder_update", "obstacle")


def local_params(sc: Scenario, tick_s: float | None = None):
    """:class:`~skyroute.stages.tactical.fw_local.LocalPlannerParams` of a scenario."""
    from skyroute.stages.tactical.fw_local import LocalPlannerParams

    t = sc.tactical
    return LocalPlannerParams(tick_s=t.tick_s if tick_s is None else float(tick_s), obstacle_range_m=t.obstacle_range_m,
                              uav_range_m=t.uav_range_m, d_c_m=sc.traffic.margin_m, avoid_offset_m=t.avoid_offset_m)


def obstacles_of(sc: Scenario, surface) -> list:
    """The scenario's ``obstacle`` events as
    :class:`~skyroute.stages.tactical.fw_local.StaticObstacle` (top: the highest terrain cell
    the polygon touches + ``height_agl_m``)."""
    from skyroute.stages.grid import Grid
    from skyroute.stages.tactical.fw_local import StaticObstacle

    g = Grid.from_dataarray(surface["terrain"])
    terrain = np.asarray(surface["terrain"].values, float)
    out = []
    for n, ev in enumerate(sc.events):
        if ev.kind != "obstacle":
            continue
        poly = np.asarray(ev.polygon_xy(sc), float)
        ground = _ground_max(g, terrain, poly)
        out.append(StaticObstacle(ev.id or f"obstacle-{n}", poly, float(ground + ev.height_agl_m), float(ev.t_s)))
    return out


def _ground_max(g, terrain: np.ndarray, poly: np.ndarray) -> float:
    """Highest terrain [m] over the cells of the polygon's bounding box (>= the ground under it)."""
    r, c = g.cell_of(poly[:, 0], poly[:, 1])
    return float(np.max(terrain[max(r.min(), 0):r.max() + 1, max(c.min(), 0):c.max() + 1]))


def local_problem(sc: Scenario, result):
    """A :class:`~skyroute.stages.planning.problem.PlanningProblem` on the plan's maps (its
    wind sampler and floor: clearance floor and minimum AGL) for the local planner."""
    from skyroute.stages.planning.problem import build_problem, xyz_from_agl

    s, c = result["surface"].load(), result["clearance"].load()
    wind = result["wind"].load() if "wind" in result.datasets else (0.0, 0.0, 0.0)
    m = sc.mission
    return build_problem(s, c["min_altitude_m"], None, None, None, wind, sc.vehicle, (1, 0, 0, 0),
                         xyz_from_agl(s, *sc.point_xy(m.start), m.start.alt_agl_m),
                         xyz_from_agl(s, *sc.point_xy(m.goal), m.goal.alt_agl_m), sc.constraints.min_altitude_agl_m,
                         sc.constraints.max_altitude_agl_m, nofly=c["nofly"], check_endpoints=False)


def fly_fixedwing(sc: Scenario, *, cache: Cache | None = None, scheduler: str = "threads", progress: bool = False,
                  tick_s: float | None = None, seed: int | None = None, result=None):
    """Plan (cached) and fly the fixed-wing scenario ``sc`` with seed 002's local planner.
    Returns a :class:`~skyroute.pipeline.fly.FlyResult` (no map updates)."""
    from skyroute.pipeline.fly_common import FlyResult, tactical_events
    from skyroute.stages.base import PlanningError
    from skyroute.stages.planning.step3 import wind_sampler
    from skyroute.stages.planning.strategic import plan_from_dataset
    from skyroute.stages.tactical.fw_local import (
        LocalAgent,
        LocalTrack,
        floor_sampler,
        local_flight_log,
        simulate_local,
    )
    from skyroute.stages.tactical.log import IntruderTrack
    from skyroute.stages.tactical.replay import _truth_update
    from skyroute.stages.traffic import intruders_for

    bad = sorted({ev.kind for ev in sc.events if ev.kind not in LOCAL_EVENT_KINDS})
    if bad:
        raise InputError(f"the fixed-wing local planner (seed 002) reacts to {', '.join(LOCAL_EVENT_KINDS)} events; "
                         f"scenario {sc.name!r} has {', '.join(bad)} event(s): remove them or plan again with "
                         "`skyroute plan` on the changed scenario")
    params = local_params(sc, tick_s)
    from skyroute.pipeline.budget import check_ticks
    from skyroute.pipeline.fly_common import shortest_flight_s

    if params.tick_s > 0:
        check_ticks(shortest_flight_s(sc), params.tick_s)   # even the straight flight needs too many ticks
    cache = cache or Cache()
    if result is None:
        result = run_scenario(sc, cache=cache, targets=["plan"], scheduler=scheduler, progress=progress)
    plan_ds = result["plan"].load()
    chosen, _ = plan_from_dataset(plan_ds)
    if chosen is None or not chosen.flyable:
        raise PlanningError(f"no flyable strategic plan to fly: {plan_ds.attrs.get('reason', '')}")
    t_plan, x_plan = np.asarray(chosen.t_s, float), np.asarray(chosen.xyz_m, float)
    problems = check_event_times(sc, float(t_plan[-1]))
    if problems:
        raise InputError("; ".join(problems))
    surface = result["surface"].load()
    truth: dict[str, IntruderTrack] = {}
    if sc.traffic.intruders:
        for it in intruders_for([i.model_dump() for i in sc.traffic.intruders], surface):
            truth[it.id] = IntruderTrack(it.id, it.radius_m, it.times_s, it.xyz_m, "strategic", 0.0,
                                         [(0.0, it.times_s, it.xyz_m)])
    ev_dicts = []
    for ev in tactical_events(sc, surface):
        ident = ev.intruder.id if ev.intruder is not None else None
        if ev.kind == "intruder" or (ev.kind == "intruder_update" and ident not in truth):
            it = ev.intruder
            truth[it.id] = IntruderTrack(it.id, it.radius_m, it.times_s, it.xyz_m, "tactical", ev.t_s,
                                         [(ev.t_s, it.times_s, it.xyz_m)])
        elif ev.kind == "intruder_update":
            truth[ident] = _truth_update(truth[ident], ev.intruder, ev.t_s)
        ev_dicts.append({"t_s": ev.t_s, "kind": ev.kind, "label": ev.label, "t_coll_s": math.inf, "id": ident})
    obstacles = obstacles_of(sc, surface)
    obs_ids = iter(o.id for o in obstacles)
    for e in ev_dicts:
        if e["kind"] == "obstacle":
            e["id"] = next(obs_ids)
    tracks = [LocalTrack(tr.id, tr.t_s, tr.xyz_m, tr.radius_m) for tr in truth.values() if len(tr.t_s) >= 2]
    pr = local_problem(sc, result)
    g = pr.grid
    floor_at = floor_sampler(pr)

    known = {tr.id: float(tr.known_from_s) for tr in truth.values()}   # U-space / V2V: known at any range
    sim = simulate_local([LocalAgent("ownship", t_plan, x_plan, sc.vehicle)], obstacles=obstacles, intruders=tracks,
                         params=params, wind_at=wind_sampler(pr), floor_at=floor_at, known_from_s=known)
    log = local_flight_log(sim, 0, scenario=sc.name, crs_wkt=str(surface["surface"].rio.crs),
                           vertical_datum=surface["surface"].attrs.get("vertical_datum", ""),
                           start_time_utc=sc.mission.start_time_utc.isoformat(), planned_t_s=t_plan,
                           planned_xyz_m=x_plan, obstacles=obstacles, tracks=list(truth.values()), events=ev_dicts,
                           seed=sc.tactical.seed if seed is None else seed)
    log.dop_threshold = chosen.dop_threshold
    log.grid = g
    log.terrain_m = np.asarray(surface["terrain"].values, float)
    log.surface_m = np.asarray(surface["surface"].values, float)
    log.compile_s = 0.0
    return FlyResult(result, log, [])


def fleet_problems(sc: Scenario, routes, *, cache: Cache | None = None, alt_agl_m: float = 150.0,
                   alt_m: float | None = None) -> list:
    """One :class:`~skyroute.stages.planning.problem.PlanningProblem` per route ``((x0, y0),
    (x1, y1))`` [m, map CRS] on the maps of ``sc`` (surface, clearance, wind; cached stages),
    start and goal ``alt_agl_m`` [m] above the ground, or at the altitude ``alt_m`` [m, surface
    datum] when given: the input of
    :func:`~skyroute.stages.tactical.fw_local.fly_fixedwing_fleet`."""
    import warnings

    from skyroute.stages.planning.problem import build_problem

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = run_scenario(sc, cache=cache or Cache(), targets=["surface", "clearance", "wind"])
    s, c = res["surface"].load(), res["clearance"].load()
    wind = res["wind"].load() if "wind" in res.datasets else (0.0, 0.0, 0.0)
    out = []
    for k, (a, b) in enumerate(routes):
        out.append(build_problem(s, c["min_altitude_m"], None, None, None, wind, sc.vehicle, (1, 0, 0, 0),
                                 _point(s, a, alt_agl_m, alt_m), _point(s, b, alt_agl_m, alt_m),
                                 sc.constraints.min_altitude_agl_m, sc.constraints.max_altitude_agl_m,
                                 nofly=c["nofly"], label=f"uav-{k + 1}"))
    return out


def _point(s, xy, alt_agl_m: float, alt_m: float | None):
    from skyroute.stages.planning.problem import xyz_from_agl

    if alt_m is None:
        return xyz_from_agl(s, float(xy[0]), float(xy[1]), alt_agl_m)
    return np.array([float(xy[0]), float(xy[1]), float(alt_m)])


def crossing_routes(center_xy, half_length_m: float, headings_deg) -> list:
    """Routes ``((x0, y0), (x1, y1))`` [m] through ``center_xy`` with the given headings [deg,
    counter-clockwise from east], each ``2 half_length_m`` long (all cross at the centre)."""
    out = []
    for h in headings_deg:
        e = np.array([math.cos(math.radians(h)), math.sin(math.radians(h))])
        c = np.asarray(center_xy, float)
        out.append((tuple(c - half_length_m * e), tuple(c + half_length_m * e)))
    return out
