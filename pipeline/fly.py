"""``skyroute fly``: the tactical replay of a scenario's strategic plan through its events.

The strategic plan and the maps come from the cached stages (:func:`run_scenario`); each
map-changing event (wind, GNSS, obstacle) re-runs the stages it affects on the scenario with
the events so far applied (:func:`~skyroute.pipeline.settings.scenario_at`: same cache, so
unchanged stages are reused); the replay itself is
:func:`skyroute.stages.tactical.replay.replay`.
"""

from __future__ import annotations

import dataclasses
import math

from skyroute.pipeline.budget import check_ticks
from skyroute.pipeline.cache import Cache
from skyroute.pipeline.errors import InputError
from skyroute.pipeline.fly_common import (
    MAP_STAGES,
    FlyResult,
    _world,
    shortest_flight_s,
    tactical_events,
)
from skyroute.pipeline.progress import phase
from skyroute.pipeline.runner import RunResult, run_scenario
from skyroute.pipeline.settings import Scenario, check_event_times, scenario_at

__all__ = ["MAP_STAGES", "MAX_EVENT_CHECKS", "MAX_INTRUDERS", "FlyResult", "check_intruders", "fly_scenario", "tactical_events",
           "tactical_method"]

#: Intruder tracks one tactical replay takes (``traffic.intruders`` + ``intruder`` and
#: ``intruder_update`` events); the traffic benchmark's densest case is 400.
MAX_INTRUDERS = 500
#: Events x intruder tracks: every event checks the rest of the flight against every known
#: intruder, so the replay's work grows as their product.  Measured on helsinki-tactical (2
#: shared cores): 52 events x 54 tracks 8 s, 202 x 204 (41 208) 155 s beyond the plan.
MAX_EVENT_CHECKS = 50_000


def check_intruders(sc: Scenario) -> int:
    """InputError (exit 2, before any work) when ``sc`` gives more than :data:`MAX_INTRUDERS`
    intruder tracks, or more than :data:`MAX_EVENT_CHECKS` events x tracks; returns the
    number of tracks."""
    known = len(sc.traffic.intruders)
    new = sum(1 for e in sc.events if e.kind == "intruder")
    upd = sum(1 for e in sc.events if e.kind == "intruder_update")
    n = known + new + upd
    what = (f"{n:,} intruder tracks (traffic.intruders {known:,}, intruder events {new:,}, intruder_update events "
            f"{upd:,})")
    if n > MAX_INTRUDERS:
        raise InputError(f"scenario {sc.name!r} gives {what}: skyroute fly replays at most {MAX_INTRUDERS:,}; keep the "
                         "intruders that come near the flight")
    checks = len(sc.events) * n
    if checks > MAX_EVENT_CHECKS:
        raise InputError(f"scenario {sc.name!r} gives {len(sc.events):,} events and {what}: each event checks the "
                         f"flight against every intruder, {checks:,} checks (at most {MAX_EVENT_CHECKS:,}); keep the "
                         "events and intruders that come near the flight")
    return n


def fly_params(sc: Scenario, t_rep_s: float | None = None, tick_s: float | None = None, seed: int | None = None,
               method: str | None = None):
    """The replay's :class:`~skyroute.stages.tactical.params.FlyParams`: the scenario's
    ``tactical:`` section (``t_rep_s``, ``tick_s``, ``seed``, ``method`` override it) and its
    plan request (:func:`~skyroute.pipeline.stages_builtin.plan_request`: the planning settings)."""
    from skyroute.pipeline.stages_builtin import plan_request
    from skyroute.stages.tactical.params import FlyParams  # not the replay (its planners: numba)

    t = sc.tactical
    return FlyParams(t_rep_s=t.t_rep_s if t_rep_s is None else t_rep_s, tick_s=t.tick_s if tick_s is None else tick_s,
                     seed=t.seed if seed is None else seed, dt_c_s=t.time_margin_s,
                     time_scaling_factors=tuple(t.time_scaling_factors),
                     level2_iterations=t.level2_iterations, level3_iterations=t.level3_iterations,
                     intruder_noise_m=t.intruder_noise_m, report_latency_s=t.report_latency_s,
                     method=t.method if method is None else method, periphery_m=t.periphery_m,
                     zone_period_s=t.zone_period_s, request=plan_request(sc))


def tactical_method(sc: Scenario, method: str | None = None) -> str:
    """The tactical method for ``sc``: ``method`` if given, else ``tactical.method``; fixed-wing
    vehicles fly ``local`` (seed 002's local planner; their default when ``tactical.method``
    is not set), rotorcraft ``levels`` or ``octant``.  InputError when the method does not fit
    the vehicle kind."""
    from skyroute.stages.vehicle import load_vehicle

    fixed = load_vehicle(sc.vehicle).kind == "fixed-wing"
    if method is None:
        method = sc.tactical.method
        if fixed and "method" not in sc.tactical.model_fields_set:
            method = "local"
    if fixed and method != "local":
        raise InputError(f"tactical method {method!r} flies rotorcraft; vehicle {sc.vehicle!r} is fixed-wing: use "
                         "--tactical local (seed 002's local planner: climb over obstacles, turn right for UAVs)")
    if not fixed and method == "local":
        raise InputError(f"tactical method 'local' (seed 002) flies fixed-wing aircraft; vehicle {sc.vehicle!r} is a "
                         "rotorcraft: use --tactical levels or --tactical octant")
    return method


def check_flight(sc: Scenario, t_rep_s: float | None = None, tick_s: float | None = None, seed: int | None = None,
                 method: str | None = None) -> str:
    """The checks of a flight that need no stage (intruder count, tactical method, parameters,
    the ticks of the straight flight): InputError (exit 2) before any work; returns the method."""
    check_intruders(sc)
    method = tactical_method(sc, method)
    if method != "local":
        params = fly_params(sc, t_rep_s, tick_s, seed, method)
        check_ticks(shortest_flight_s(sc), params.tick_s)
    return method


def fly_scenario(sc: Scenario, *, cache: Cache | None = None, scheduler: str = "threads", progress: bool = False,
                 t_rep_s: float | None = None, tick_s: float | None = None, seed: int | None = None,
                 result: RunResult | None = None, method: str | None = None) -> FlyResult:
    """Plan (cached) and fly ``sc`` through its events.  ``method``: tactical method
    (``levels`` or ``octant`` for rotorcraft, ``local`` for fixed-wing: :func:`tactical_method`;
    ``local`` is :func:`skyroute.pipeline.fly_fw.fly_fixedwing`).  Raises InputError (exit 2) for bad
    parameters or events after the mission, PlanningError when there is no strategic plan.
    ``progress``: show the stages' progress; the replay's (simulated time flown of the flight's
    end) is shown whenever the command shows progress (:mod:`skyroute.pipeline.progress`)."""
    from skyroute.stages.base import PlanningError
    from skyroute.stages.planning.strategic import plan_from_dataset, trajectory_from_dataset
    from skyroute.stages.tactical.replay import replay
    from skyroute.stages.traffic import intruders_for

    method = check_flight(sc, t_rep_s, tick_s, seed, method)
    if method == "local":
        from skyroute.pipeline.fly_fw import fly_fixedwing

        with phase("fly: replay (fixed-wing)", on=True if progress else None):
            return fly_fixedwing(sc, cache=cache, scheduler=scheduler, progress=progress, tick_s=tick_s, seed=seed,
                                 result=result)
    params = fly_params(sc, t_rep_s, tick_s, seed, method)   # checked by check_flight above
    cache = cache or Cache()
    if result is None:
        result = run_scenario(sc, cache=cache, targets=["plan"], scheduler=scheduler, progress=progress)
    plan_ds = result["plan"].load()
    chosen, _cands = plan_from_dataset(plan_ds)
    if chosen is None:
        raise PlanningError(f"no strategic plan to fly: {plan_ds.attrs.get('reason', '')}")
    tr = trajectory_from_dataset(plan_ds)
    if tr is None:
        raise PlanningError("the cached plan has no trajectory phases: re-run with `--force plan`")
    traj, t0 = tr
    radius = None
    if sc.constraints.clearance == "sboa":       # the safety bubble of the plan's level (seed 003)
        radius = float(chosen.clearance_radius_m)
        if not math.isfinite(radius):
            raise PlanningError("the cached plan has no safety-bubble radius: re-run with `--force plan`")
        bubble = (float(sc.constraints.sboa_k), float(sc.navsim.surface_uncertainty_m))
        params = dataclasses.replace(params, request=params.request.with_(bubble=bubble), clearance_radius_m=radius)
    check_ticks(float(t0 + traj.duration_s), params.tick_s)  # the planned flight, before the replay
    problems = check_event_times(sc, float(t0 + traj.duration_s))
    if problems:
        raise InputError("; ".join(problems))
    import numpy as np

    from skyroute.stages.gridspec import Grid
    from skyroute.stages.planning.window import path_window

    surface = result["surface"]     # lazy: a city's maps are read in the flight's window
    # on a city-scale AOI the replay knows the maps of the window around the planned path
    window = path_window(Grid.from_dataarray(surface["terrain"]), np.asarray(chosen.xyz_m)[:, :2])
    events = tactical_events(sc, surface)
    updates: list[RunResult] = []
    targets = [s for s in MAP_STAGES if s in result.datasets]

    def world_at(t_s: float):
        from skyroute.pipeline.graph import stages_for

        sc_t = scenario_at(sc, t_s)
        # a map an event brings in (a wind event on a scenario without wind) is computed too
        now = [s.name for s in stages_for(sc_t) if s.name in MAP_STAGES and s.name not in targets]
        res = run_scenario(sc_t, cache=cache, targets=[*targets, *now], scheduler=scheduler, progress=False)
        updates.append(res)
        return _world(res, sc, radius, window)

    strategic = intruders_for([i.model_dump() for i in sc.traffic.intruders], surface) if sc.traffic.intruders else []
    goal = chosen.xyz_m[-1]
    with phase("fly: replay", unit="s simulated", detail=f"{len(events)} events",
               on=True if progress else None) as shown:
        def flown(t_s: float, t_end_s: float) -> None:    # simulated time [s] since take-off, of the end
            shown.update(t_s - t0, t_end_s - t0)

        log = replay(traj, t0, goal_xyz=goal, world=_world(result, sc, radius, window), world_at=world_at,
                     events=events, strategic_intruders=strategic, vehicle=params.request.vehicle, params=params,
                     start_time_utc=sc.mission.start_time_utc.isoformat(), dop_threshold=chosen.dop_threshold,
                     scenario=sc.name, crs_wkt=str(surface["surface"].rio.crs),
                     vertical_datum=surface["surface"].attrs.get("vertical_datum", ""), progress=flown)
    return FlyResult(result, log, updates)
