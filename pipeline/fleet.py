"""``skyroute fleet``: first-come-first-served strategic deconfliction of many operators' missions.

The maps (surface, environment, clearance, wind, coverage, satellites) come from the cached
stages of the scenario once.  The missions (a fleet file, :func:`load_fleet`, or drawn by
:func:`draw_missions`) are taken in order of earliest departure (then higher priority, then
id).  Each is planned at ONE DOP level (its ``dop_level``; default the scenario's strictest
flyable level) by the strategic planner (STEP I-III), with the intent volumes of every accepted
mission in its space-time corridor as traffic in STEP II and III
(:func:`~skyroute.stages.traffic.volume_prisms`: the accepted volumes, altitudes brought to
the surface datum conservatively, grown by the new mission's own horizontal, vertical and time
buffers).  The plan becomes ASTM F3548 intent volumes
(:func:`~skyroute.stages.intents.plan_volumes`, vehicle radius ``safety_distance_m + d_c / 2``
so that two disjoint intents keep ``2 r + d_c`` apart) and is accepted only if they intersect
no accepted volume (:class:`~skyroute.stages.fleet.VolumeIndex`: area > 1e-4 m^2 with altitude
and time overlap).  Otherwise its departure is delayed by ``delay_step_s`` up to
``max_delay_s``, else it is rejected with the reason.  A mission that conflicts may preempt
lower-priority accepted missions: it is planned against the volumes of equal or higher
priority only; if accepted, the lower-priority missions its volumes intersect are withdrawn
and re-planned right after it (``preempted-replanned``, or ``rejected`` when that fails).

Determinism: STEP I (A*) is deterministic and STEP II's RRT is seeded from the fleet seed,
the mission id and the departure; a planning attempt sees only the accepted volumes in its
corridor (start-goal box grown by ``corridor_m``, departure to 3 x the direct flight time +
120 s later), and
its result depends only on those.  The parallel driver (dask.distributed) plans the next
missions speculatively against the accepted set of the moment and commits in order; a
speculative plan whose corridor saw a different set of accepted volumes than the one at its
commit is re-planned, so the result equals the sequential one.
"""

from __future__ import annotations

import math
import time
import zlib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from skyroute.pipeline.errors import InputError
from skyroute.pipeline.fleet_check import independent_conflicts, min_separation_m  # noqa: F401  (re-exported)
from skyroute.pipeline.fleet_missions import (  # noqa: F401  (re-exported: the mission model)
    FIRM_PRIORITY,
    FLEET_PLANNER,
    MAX_FLEET_MISSIONS,
    MAX_ID_CHARS,
    MAX_PRIORITY,
    MIN_PRIORITY,
    Attempt,
    FleetFileError,
    FleetMission,
    FleetOptions,
    FleetResult,
    FleetTask,
    MissionOutcome,
    check_fleet_vehicle,
    check_mission_id,
    draw_missions,
    load_fleet,
    mission_fields,
)
from skyroute.pipeline.settings import Scenario
from skyroute.stages.planning.request import (
    PLANNER_STAGES as MAP_STAGES,  # the maps a planner reads
)

# the driver: maps, attempts, the first-come-first-served scheduler; the mission model, the
# independent checks and the outputs live in fleet_missions, fleet_check and fleet_outputs
__all__ = ["Attempt", "FleetFileError", "FleetMission", "FleetOptions", "FleetResult", "FleetTask",
           "MissionOutcome", "default_level", "draw_missions", "fleet_maps", "independent_conflicts", "load_fleet",
           "mission_fields", "min_separation_m", "plan_attempt", "run_fleet", "still_valid"]


# ---------------------------------------------------------------------------------- the maps
_MAPS: dict[str, dict] = {}


def fleet_maps(sc: Scenario, cache_dir: Path | str | None, scheduler: str = "threads") -> dict:
    """The scenario's map datasets and the plan stage's dataset, from the cache (computed once
    when absent); memoised per process (each dask worker loads them once).

    The maps are loaded in memory, except on a city-scale AOI (at least
    :data:`~skyroute.stages.planning.window.WINDOW_MIN_CELLS` cells), where the datasets on the
    AOI's grid stay lazy on the cache's zarr stores: every plan reads only its planning window's
    chunks (:mod:`~skyroute.stages.planning.window`), so a worker holds one plan's window, not
    the city (1e8 cells: about 10 GB in memory)."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.graph import stages_for
    from skyroute.pipeline.model import stable_hash
    from skyroute.pipeline.runner import run_scenario

    key = stable_hash("fleet-maps-1", sc.model_dump(mode="json"), str(cache_dir))
    if key in _MAPS:
        return _MAPS[key]
    from skyroute.stages.planning.window import WINDOW_MIN_CELLS, on_aoi_grid

    names = [s.name for s in stages_for(sc) if s.name in (*MAP_STAGES, "wind_bounds", "plan")]
    res = run_scenario(sc, cache=Cache(cache_dir), targets=names, scheduler=scheduler)
    shape = (res["surface"].sizes["y"], res["surface"].sizes["x"])
    city = shape[0] * shape[1] >= WINDOW_MIN_CELLS
    maps: dict[str, Any] = {k: res[k] if city and on_aoi_grid(res[k], shape) else res[k].load()
                            for k in names if k in res.datasets}
    maps["_result"] = res
    from skyroute.pipeline.plan_exports import scenario_height_reference

    ref = scenario_height_reference(sc, str(maps["surface"]["surface"].attrs.get("vertical_datum", "")))
    ref.ellipsoidal_m(0.0, 0.0, 0.0)   # the geoid grid is on disk
    maps["_ref"] = ref
    _MAPS.clear()
    _MAPS[key] = maps
    return maps


def _warm(sc: Scenario, cache_dir, task: FleetTask | None = None, level: float | None = None,
          opt: FleetOptions | None = None) -> None:
    """Load the maps into this process (a dask worker) and, given a ``task``, plan it once
    without traffic (loads the compiled kernels; the result is dropped)."""
    import dask

    with dask.config.set(scheduler="synchronous"):    # never the worker's own distributed client
        fleet_maps(sc, cache_dir, scheduler="synchronous")
        if task is not None:
            plan_attempt(sc, cache_dir, task, task.earliest_s, level, [], opt or FleetOptions())


def _warm_workers(client, sc: Scenario, cache_dir, task: FleetTask, level: float | None, opt: FleetOptions) -> None:
    """:func:`_warm` on every worker of ``client`` as one ordinary task each (pinned to it), so
    it runs in the worker's thread pool like any task: ``client.run`` would run it in the
    worker's event loop, where a worker that already ran other skyroute tasks has a
    distributed client and the maps' compute failed ("Attempting to use an asynchronous Client
    in a synchronous context")."""
    from skyroute.pipeline.graph import cluster_result

    workers = sorted(client.scheduler_info().get("workers", {}))
    futs = [client.submit(_warm, sc, cache_dir, task, level, opt, workers=[w],
                          pure=False, allow_other_workers=True, key=f"skyroute-warm-{i}-{time.time_ns()}")
            for i, w in enumerate(workers)]
    for f in futs:
        cluster_result(client, f, "fleet: loading the maps on the workers")


def default_level(maps: dict) -> float | None:
    """The scenario's strictest flyable DOP level: the lowest threshold whose candidate of the
    scenario's own plan is flyable (None without coverage maps; the loosest level when none is)."""
    if "coverage" not in maps:
        return None
    levels = sorted(float(d) for d in maps["coverage"]["threshold"].values)
    plan = maps.get("plan")
    if plan is not None:
        ok = [float(d) for d, f in zip(plan["dop_threshold"].values, plan["flyable"].values, strict=True)
              if bool(f) and np.isfinite(d)]
        if ok:
            return min(ok)
    return levels[-1]


def _seed(base: int, mission: str, departure_s: float) -> int:
    return zlib.crc32(f"{base}/{mission}/{departure_s:.3f}".encode()) & 0x7FFFFFFF


def _grow(opt: FleetOptions, vehicle_radius_m: float) -> tuple[float, float, float]:
    """(horizontal [m], vertical [m], time [s]) growth of the accepted volumes for a new plan:
    its own buffer (k sigma + vehicle radius + rounding margins), x 1.5 horizontally for the
    hull of an arc chunk (sagitta <= half the buffer), plus a chunk's climb vertically and a
    chunk's duration + time buffer in time (a volume spans its whole chunk)."""
    r = opt.k_sigma * opt.sigma_est_m + vehicle_radius_m + 0.2
    return 1.5 * r / math.cos(math.pi / 16), r + opt.max_dz_m, opt.time_buffer_s + opt.max_volume_s + 0.5


def plan_attempt(sc: Scenario, cache_dir, task: FleetTask, departure_s: float, level: float | None,
                 obstacles: Sequence[tuple[str, Any]], opt: FleetOptions, seen: tuple = ()) -> Attempt:
    """Plan ``task`` departing ``departure_s`` [s after the scenario start] at DOP ``level``
    with ``obstacles`` ((owner, Volume4 in the surface datum, fleet time)) as STEP II / III
    traffic; the intent volumes of the plan (see the module docstring)."""
    import dask
    import pandas as pd

    from skyroute.stages.base import SkyrouteError
    from skyroute.stages.fleet import Volume4
    from skyroute.stages.intents import intent_details, plan_volumes
    from skyroute.stages.planning.request import Maps, PlanRequest
    from skyroute.stages.planning.strategic import plan_strategic
    from skyroute.stages.traffic import build_occupancy, volume_prisms
    from skyroute.stages.vehicle import load_vehicle

    t_start = time.perf_counter()
    maps = fleet_maps(sc, cache_dir, scheduler="synchronous")
    ref = maps["_ref"]
    veh = load_vehicle(task.vehicle)
    r_veh = veh.safety_distance_m + 0.5 * sc.traffic.margin_m
    gh, gz, gt = _grow(opt, r_veh)
    occ = None
    if obstacles:
        prisms = volume_prisms([v for _, v in obstacles], grow_m=gh, grow_z_m=gz, grow_t_s=gt,
                               owners=[o for o, _ in obstacles]).shifted(-departure_s)
        horizon = max(float(prisms.band[:, 3].max()), 1.0) + 1.0
        occ = build_occupancy([], horizon, 1, 0.0, 0.0).with_volumes(prisms)
    cov = maps.get("coverage")
    if cov is not None and level is not None:
        cov = cov.sel(threshold=[level])
    t0_utc = pd.Timestamp(sc.mission.start_time_utc) + pd.Timedelta(seconds=departure_s)
    p = sc.planner
    try:
        request = PlanRequest.of(
            start_xy=task.start_xy, start_agl_m=task.start_agl_m, goal_xy=task.goal_xy, goal_agl_m=task.goal_agl_m,
            start_time_utc=t0_utc, vehicle=veh, weights=p.weights, planner=FLEET_PLANNER,
            time_budget_s=opt.budget_s(task.start_xy, task.goal_xy),
            seed=_seed(opt.seed, task.id, departure_s), max_tries=p.max_tries, step_cells=p.step_cells,
            min_agl_m=sc.constraints.min_altitude_agl_m, max_agl_m=sc.constraints.max_altitude_agl_m,
            dop_kind=sc.gnss.dop_kind, d_c_m=sc.traffic.margin_m, dt_c_s=sc.traffic.time_margin_s,
            uere_m=sc.gnss.uere_m, workers=1, battery_reserve_pct=sc.constraints.battery_reserve_pct,
            step2_max_iter=opt.step2_max_iter)
        area = Maps(surface=maps["surface"], clearance=maps["clearance"], environment=maps.get("environment"),
                    wind=maps.get("wind"), coverage=cov, satellites=maps.get("satellites"), traffic=occ,
                    wind_bounds=maps.get("wind_bounds"))
        with dask.config.set(scheduler=_map_scheduler()):    # a city's lazy maps: the plan's window is read
            plan = plan_strategic(area, request, heuristic_cache=maps.setdefault("_heuristics", {}),
                                  edge_cache=maps.setdefault("_edges", {}))
    except SkyrouteError as exc:
        return Attempt(task.id, departure_s, False, f"planner: {exc}", compute_s=time.perf_counter() - t_start,
                       seen=seen)
    c = plan.chosen
    if c is None:
        # STEP I failed: it depends on neither the departure nor the traffic, so a later departure
        # repeats the same search (also one cut by the wall-clock safety net: said in the reason)
        static = all(s1 is not None and not s1.solved for s1 in plan.step1)
        capped = any(s1 is not None and s1.info.get("stopped_by") == "time" for s1 in plan.step1)
        s2 = plan.step2[0] if len(plan.step2) == 1 else None
        reason = (plan.reason or "no flyable plan") + (
            " (STEP I was stopped by the wall-clock safety net)" if capped else "")
        return Attempt(task.id, departure_s, False, reason,
                       compute_s=time.perf_counter() - t_start, seen=seen, static=static,
                       step2_status=s2.status if s2 is not None else "",
                       free_legs=s2.free_legs if s2 is not None and s2.status == "failed" else None)
    traj, t0 = c.trajectory, float(c.t_s[0])
    crs = maps["surface"]["surface"].rio.crs
    from pyproj import Transformer

    to_ll = Transformer.from_crs(crs, 4326, always_xy=True)

    def h_w84(q: np.ndarray) -> np.ndarray:
        lon, lat = to_ll.transform(q[:, 0], q[:, 1])
        return ref.ellipsoidal_m(np.asarray(lon), np.asarray(lat), q[:, 2])

    try:
        iv = plan_volumes(traj, t0, c.t_s, c.sigma_p_m, h_w84, vehicle_radius_m=r_veh, k_sigma=opt.k_sigma,
                          time_buffer_s=opt.time_buffer_s, max_volume_s=opt.max_volume_s, max_dz_m=opt.max_dz_m)
    except SkyrouteError as exc:
        return Attempt(task.id, departure_s, False, f"intent: {exc}", compute_s=time.perf_counter() - t_start,
                       seen=seen)
    doc = intent_details(iv, crs, t0_utc.isoformat(), priority=task.priority)
    vols, obst = [], []
    import shapely

    for v in iv:
        poly = shapely.Polygon(v.outline_xy_m)
        ts, te = v.t_start_s + departure_s, v.t_end_s + departure_s
        vols.append(Volume4(poly, v.alt_lower_m, v.alt_upper_m, ts, te))
        obst.append(_obstacle(vols[-1], v.outline_xy_m, to_ll, ref))
    tau = np.append(np.arange(0.0, traj.duration_s, 0.05), traj.duration_s)
    xyz = traj.sample(tau)
    s2 = plan.step2[0]
    return Attempt(task.id, departure_s, True, "", vols, obst, doc, xyz, departure_s + t0 + tau,
                   c.energy_J / 3600.0, float(np.linalg.norm(np.diff(xyz, axis=0), axis=1).sum()),
                   float(c.flight_time_s), time.perf_counter() - t_start, seen,
                   s2.status if s2 is not None else "", None if s2 is None else (s2.waypoints, s2.times_s),
                   (traj, t0), free_legs=None if s2 is None else s2.free_legs)


def _map_scheduler() -> str:
    """The dask scheduler reading a plan's window of lazy maps: this process's threads, or only
    the calling thread inside a dask worker (one thread per worker process: a fleet's scale-out
    is measured in processes)."""
    try:
        from distributed import get_worker

        get_worker()
    except (ImportError, ValueError):
        return "threads"
    return "synchronous"


def _obstacle(v, ring_xy_m: np.ndarray, to_ll, ref):
    """The Volume4 ``v`` (W84 altitudes) as an obstacle in the surface datum: its band brought
    to the datum conservatively over the outline's vertices ``ring_xy_m`` [m] (the lowest and
    highest W84 height of the datum's 0 m there), +- 1 cm."""
    from skyroute.stages.fleet import Volume4

    lon, lat = to_ll.transform(ring_xy_m[:, 0], ring_xy_m[:, 1])
    off = ref.ellipsoidal_m(np.asarray(lon), np.asarray(lat), np.zeros(len(lon)))   # W84 of the datum's 0 m
    return Volume4(v.polygon, v.alt_lower_m - float(np.max(off)) - 0.01, v.alt_upper_m - float(np.min(off)) + 0.01,
                   v.t_start_s, v.t_end_s)


def still_valid(a: Attempt, added: Sequence[tuple[str, Any]], task: FleetTask, sc: Scenario,
                opt: FleetOptions) -> bool:
    """Would planning again with the extra obstacles ``added`` give the same attempt ``a``?
    Conflicts are an OR over the prisms: more obstacles can only turn a traffic test's "free"
    into "conflict".  So the attempt is the same when none of its tests that answered "free"
    meets a new prism:

    * STEP II left the STEP I chain unchanged: that chain's timed legs;
    * STEP II ran its RRT (``a.free_legs``, recorded when no wall clock stopped it): every leg
      it found free, the chain's free legs included -- the RRT then draws the same random
      numbers and gets the same answers, so it builds the same tree, to the same chain or the
      same failure;
    * and, for a plan, the retimed trajectory's chords (STEP III's re-check, the same chords)."""
    from skyroute.stages.planning.deconflict import chain_conflicts, leg_conflicts
    from skyroute.stages.planning.step3 import _retimed_conflicts
    from skyroute.stages.traffic import build_occupancy, volume_prisms
    from skyroute.stages.vehicle import load_vehicle

    if a.static:                       # STEP I failed: traffic plays no part
        return True
    if a.step2_status == "unchanged":
        if not a.ok or a.chain is None or a.trajectory is None:
            return False
    elif a.step2_status in ("deconflicted", "failed"):
        if a.free_legs is None or (a.ok and a.trajectory is None) or (not a.ok and a.step2_status != "failed"):
            return False
    else:
        return False
    if not added:
        return True
    r_veh = load_vehicle(task.vehicle).safety_distance_m + 0.5 * sc.traffic.margin_m
    gh, gz, gt = _grow(opt, r_veh)
    prisms = volume_prisms([v for _, v in added], grow_m=gh, grow_z_m=gz, grow_t_s=gt).shifted(-a.departure_s)
    occ = build_occupancy([], max(float(prisms.band[:, 3].max()), 1.0) + 1.0, 1, 0.0, 0.0).with_volumes(prisms)
    if a.step2_status == "unchanged":
        if chain_conflicts(occ, *a.chain).any():
            return False
    else:
        fl = a.free_legs
        if fl.shape[0] and leg_conflicts(occ, fl[:, 0:3], fl[:, 3], fl[:, 4:7], fl[:, 7]).any():
            return False
    if not a.ok:
        return True
    traj, t0 = a.trajectory
    return not _retimed_conflicts(occ, traj, t0, 1.0)[2].any()   # step3's default check_spacing_m


class _State:
    """The accepted missions: their obstacles (surface datum), a version per mission (bumped
    when withdrawn or re-accepted) and the VolumeIndex of their intent volumes (rebuilt on a
    withdrawal)."""

    def __init__(self):
        from skyroute.stages.fleet import VolumeIndex

        self.accepted: dict[str, Attempt] = {}
        self.priority: dict[str, int] = {}
        self.version: dict[str, int] = {}
        self.changes = 0        # accepts + withdrawals so far: a corridor's accepted set may have changed
        self.index = VolumeIndex()
        self._VolumeIndex = VolumeIndex

    def add(self, a: Attempt, priority: int) -> None:
        self.accepted[a.mission] = a
        self.priority[a.mission] = priority
        self.version[a.mission] = self.version.get(a.mission, 0) + 1
        self.index.add(a.volumes, a.mission)
        self.changes += 1

    def remove(self, mission: str) -> None:
        self.accepted.pop(mission)
        self.version[mission] = self.version.get(mission, 0) + 1
        self.changes += 1
        self.index = self._VolumeIndex()
        for m, a in self.accepted.items():
            self.index.add(a.volumes, m)

    def corridor(self, task: FleetTask, departure_s: float, opt: FleetOptions, min_priority: int | None = None):
        """(seen key, obstacles) of the accepted volumes in the attempt's space-time corridor."""
        (x0, y0), (x1, y1) = task.start_xy, task.goal_xy
        c = opt.corridor_m
        bx = (min(x0, x1) - c, min(y0, y1) - c, max(x0, x1) + c, max(y0, y1) + c)
        ta, tb = departure_s - opt.time_buffer_s - opt.max_volume_s, departure_s + _horizon_s(task, opt)
        seen, obst = [], []
        for m in sorted(self.accepted):
            if min_priority is not None and self.priority[m] < min_priority:
                continue
            vs = [v for v in self.accepted[m].obstacles if v.t_end_s >= ta and v.t_start_s <= tb
                  and _box_overlap(v.polygon.bounds, bx)]
            if vs:
                seen.append((m, self.version[m]))
                obst.extend((m, v) for v in vs)
        return tuple(seen), obst


class _AirspaceLink:
    """The fleet's side of an :class:`~skyroute.stages.airspace_store.AirspaceStore`: missions
    already decided there are skipped; the accepted intents near this run's missions (the
    R*Tree, every corridor grown by another ``corridor_m``) are loaded as firm traffic; every
    attempt is also checked against the whole store (R*Tree + exact test), an intent found
    there is loaded then; every decision is written at once (one transaction each)."""

    def __init__(self, store, sc: Scenario, opt: FleetOptions, state: _State, cache_dir):
        from pyproj import Transformer

        maps = fleet_maps(sc, cache_dir, scheduler="synchronous")
        crs = maps["surface"]["surface"].rio.crs
        if not store.same_crs(crs):
            raise InputError(f"the airspace {store.path} holds volumes in another map CRS than scenario {sc.name}'s "
                             f"({crs}); use one airspace file per map CRS")
        self.store, self.sc, self.opt, self.state = store, sc, opt, state
        self.ref, self.to_ll = maps["_ref"], Transformer.from_crs(crs, 4326, always_xy=True)
        self.shift = store.time_shift_s(sc.mission.start_time_utc)
        self.n_before = len(store)
        self.loaded = 0
        self.continued: list[str] = []

    def split(self, tasks: Sequence[FleetTask]) -> list[FleetTask]:
        """The tasks not yet decided in the store (InputError for an id decided there with other fields)."""
        dec = self.store.decisions()
        todo, bad = [], []
        for t in tasks:
            d = dec.get(t.id)
            if d is None:
                todo.append(t)
            elif d[2] == mission_fields(t, self.sc):
                self.continued.append(t.id)
            else:
                bad.append(t.id)
        if bad:
            raise InputError(f"mission(s) {', '.join(bad[:5])}{' ...' if len(bad) > 5 else ''} already decided in the "
                             f"airspace {self.store.path} with other start, goal, departure, priority or vehicle; give "
                             "them new ids (drawn missions: another --seed)")
        return todo

    def preload(self, tasks: Sequence[FleetTask]) -> None:
        if not tasks or not len(self.store):
            return
        c = 2.0 * self.opt.corridor_m
        x0 = min(min(t.start_xy[0], t.goal_xy[0]) for t in tasks) - c
        y0 = min(min(t.start_xy[1], t.goal_xy[1]) for t in tasks) - c
        x1 = max(max(t.start_xy[0], t.goal_xy[0]) for t in tasks) + c
        y1 = max(max(t.start_xy[1], t.goal_xy[1]) for t in tasks) + c
        t0 = min(t.earliest_s for t in tasks) - self.opt.time_buffer_s - self.opt.max_volume_s - 1.0
        t1 = max(t.earliest_s + _horizon_s(t, self.opt) for t in tasks) + self.opt.max_delay_s + 1.0
        self.load(self.store.ids_in_box(x0, y0, x1, y1, t0 + self.shift, t1 + self.shift))

    def load(self, ids) -> None:
        from skyroute.stages.fleet import Volume4

        ids = [m for m in ids if m not in self.state.accepted]
        got = self.store.volumes(ids, t_shift_s=self.shift)
        if not got:
            return
        # _obstacle of every volume at once (elementwise: the same numbers as one at a time)
        rings = [np.asarray(v.polygon.exterior.coords)[:-1] for vs in got.values() for v in vs]
        xy = np.concatenate(rings)
        lon, lat = self.to_ll.transform(xy[:, 0], xy[:, 1])
        off = self.ref.ellipsoidal_m(np.asarray(lon), np.asarray(lat), np.zeros(len(xy)))
        starts = np.cumsum([0] + [len(r) for r in rings[:-1]])
        hi, lo = np.maximum.reduceat(off, starts), np.minimum.reduceat(off, starts)
        k = 0
        for m, vols in got.items():
            obst = []
            for v in vols:
                obst.append(Volume4(v.polygon, v.alt_lower_m - float(hi[k]) - 0.01, v.alt_upper_m - float(lo[k]) + 0.01,
                                    v.t_start_s, v.t_end_s))
                k += 1
            self.state.add(Attempt(m, math.nan, True, volumes=vols, obstacles=obst), FIRM_PRIORITY)
            self.loaded += 1

    def _to_store(self, vols) -> list:
        from skyroute.stages.fleet import Volume4

        if not self.shift:
            return list(vols)
        return [Volume4(v.polygon, v.alt_lower_m, v.alt_upper_m, v.t_start_s + self.shift, v.t_end_s + self.shift)
                for v in vols]

    def conflicts(self, vols) -> list[str]:
        """Stored intents (not loaded yet) that ``vols`` intersect; they are loaded."""
        hit = sorted({m for _, m in self.store.conflicts(self._to_store(vols), exclude=self.state.accepted)})
        self.load(hit)
        return hit

    def accept(self, o: MissionOutcome, victims: Sequence[str]) -> None:
        import pandas as pd

        a, t = o.attempt, o.task
        t0 = pd.Timestamp(self.sc.mission.start_time_utc)
        t0 = t0.tz_localize("UTC") if t0.tzinfo is None else t0.tz_convert("UTC")
        self.store.accept(t.id, a.doc, self._to_store(a.volumes), priority=t.priority, operator=t.operator,
                          mission=mission_fields(t, self.sc),
                          departure_utc=(t0 + pd.Timedelta(seconds=a.departure_s)).isoformat(),
                          withdraw=victims, decision=(o.status, o.reason))

    def reject(self, o: MissionOutcome) -> None:
        self.store.record_decision(o.task.id, "rejected", o.reason, mission_fields(o.task, self.sc))

    def summary(self) -> dict:
        return {"file": str(self.store.path), "intents_before": self.n_before, "intents_after": len(self.store),
                "loaded_near_this_run": self.loaded, "already_decided": self.continued}


def _horizon_s(task: FleetTask, opt: FleetOptions) -> float:
    """Time span [s] of an attempt's corridor after its departure: 3 x the direct distance at
    the vehicle's cruise speed + 120 s, at most ``opt.horizon_s``."""
    from skyroute.stages.vehicle import load_vehicle

    d = math.dist(task.start_xy, task.goal_xy)
    return min(opt.horizon_s, 120.0 + 3.0 * d / load_vehicle(task.vehicle).cruise_speed_mps)


def _box_overlap(a, b) -> bool:
    return a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]


class _Done:
    """A speculative attempt already back and re-validated against a later accepted set (in
    place of its future)."""

    status = "finished"

    def __init__(self, attempt: Attempt):
        self.attempt = attempt

    def cancel(self) -> None:
        pass


class _Planner:
    """Runs attempts: inline (sequential) or on a dask client (speculative).

    How the work is partitioned (issue 26): by mission, in first-come-first-served order, with
    no spatial or temporal cut: the next ``depth`` missions are planned at once on the workers,
    each against the accepted set of its own space-time corridor (:meth:`_State.corridor`) at
    submission.  An attempt's result depends only on that set, so an attempt whose corridor
    no acceptance touched meanwhile (missions far apart in space or time) is exactly the
    sequential one and is kept as is; one whose corridor gained missions is kept when
    :func:`still_valid` shows the new volumes meet none of the tests it passed; otherwise it
    is planned again.  Re-validation is eager: after every decision, each speculative attempt
    already back is checked against its corridor's new accepted set and, when invalid, planned
    again at once against it (rather than when the driver reaches that mission)."""

    def __init__(self, sc, cache_dir, opt, level_of, queue: list[FleetTask], state: _State, client=None,
                 depth: int = 1, affinity: str = "speculative", later: bool = True):
        self.sc, self.cache_dir, self.opt, self.level_of, self.client = sc, cache_dir, opt, level_of, client
        self.queue, self.state = queue, state       # the driver's: the missions to come, the accepted set
        self.depth, self.affinity, self.later = depth, affinity, later
        self.spec: dict[tuple[str, float], Any] = {}   # (mission id, departure) -> (seen, future, task)
        self.checked: set[tuple[str, float]] = set()
        self.rechecked: dict[tuple[str, float], int] = {}   # spec -> state.changes when last re-validated
        self.workers: list[str] | None = None
        self.stats = {"speculative_used": 0, "speculative_still_valid": 0, "speculative_replanned": 0,
                      "speculative_later_departures": 0, "speculative_revalidated": 0,
                      "speculative_resubmitted": 0, "attempts": 0}

    def _worker_of(self, task) -> list[str] | None:
        """A preferred worker per goal (soft: an idle worker may still take the task): the
        attempts of one mission, and the missions to one goal, meet the same worker's STEP I
        memo, A* heuristic table and edge costs."""
        if self.workers is None:
            self.workers = sorted(self.client.scheduler_info().get("workers", {}))
        if not self.workers:
            return None
        key = f"{task.goal_xy[0]:.3f},{task.goal_xy[1]:.3f}".encode()
        return [self.workers[zlib.crc32(key) % len(self.workers)]]

    def submit(self, task, dep, seen, obst, urgent: bool = True):
        args = (self.sc, self.cache_dir, task, dep, self.level_of(task), obst, self.opt, seen)
        if self.client is None:
            return plan_attempt(*args)
        # the attempt the driver waits for first, then the speculative ones in mission order
        prefer = self.affinity == "all" or (self.affinity == "speculative" and not urgent)
        workers = self._worker_of(task) if prefer else None
        # dask refuses allow_other_workers= without workers= (ValueError): none is known once
        # every worker is lost, and the driver must then reach its 'every worker was lost' error
        return self.client.submit(plan_attempt, *args, pure=False, priority=10**9 if urgent else -task.index,
                                  workers=workers, allow_other_workers=workers is not None)

    def run(self, task, dep, seen, obst) -> Attempt:
        self.stats["attempts"] += 1
        self.speculate()
        s = self.spec.pop((task.id, dep), None)
        self.checked.discard((task.id, dep))
        self.rechecked.pop((task.id, dep), None)
        if s is not None:
            sseen, fut, _ = s
            if sseen == seen:
                self.stats["speculative_used"] += 1
                return self.result(fut)
            if set(sseen) <= set(seen):     # only new accepted missions in the corridor
                a = self.result(fut)
                new = {m for m, _ in set(seen) - set(sseen)}
                if still_valid(a, [(m, v) for m, v in obst if m in new], task, self.sc, self.opt):
                    self.stats["speculative_used"] += 1
                    self.stats["speculative_still_valid"] += 1
                    a.seen = seen
                    return a
            self.stats["speculative_replanned"] += 1
            fut.cancel()
        out = self.submit(task, dep, seen, obst)
        return out if self.client is None else self.result(out)

    def result(self, fut) -> Attempt:
        """The attempt of a future; a ClusterError (never a hang) when every worker is lost."""
        from skyroute.pipeline.graph import cluster_result

        if isinstance(fut, _Done):
            return fut.attempt
        return cluster_result(self.client, fut, "fleet: a planning attempt")

    def done(self, task) -> None:
        """``task`` is decided: drop its speculative attempts."""
        for key in [k for k in self.spec if k[0] == task.id]:
            self.spec.pop(key)[1].cancel()
            self.checked.discard(key)
            self.rechecked.pop(key, None)

    def speculate(self) -> None:
        """Keep the first attempts of the next ``depth`` missions of ``queue`` in flight, each
        against the accepted set of the moment it was submitted, and, when a speculative attempt
        has come back failed (not in STEP I) or meeting an accepted volume, the same mission
        one delay step later: the attempt the driver will ask for next if nothing changes.  A
        running task cannot be stopped: an attempt no longer wanted is left to finish."""
        if self.client is None:
            return
        opt, state = self.opt, self.state
        self.revalidate()
        for t in self.queue[:self.depth]:
            if (t.id, t.earliest_s) in self.spec:
                continue
            seen, obst = state.corridor(t, t.earliest_s, opt)
            self.spec[(t.id, t.earliest_s)] = (seen, self.submit(t, t.earliest_s, seen, obst, urgent=False), t)
        for (mid, dep), (_, fut, t) in list(self.spec.items()) if self.later else ():
            if (mid, dep) in self.checked or fut.status != "finished":
                continue
            self.checked.add((mid, dep))
            a = self.result(fut)
            if a.ok and not state.index.conflicts(a.volumes):
                continue
            if a.static:
                continue
            nd = dep + opt.delay_step_s
            if (mid, nd) in self.spec or nd - t.earliest_s > opt.max_delay_s + 1e-9:
                continue
            seen, obst = state.corridor(t, nd, opt)
            self.spec[(mid, nd)] = (seen, self.submit(t, nd, seen, obst, urgent=False), t)
            self.stats["speculative_later_departures"] += 1

    def revalidate(self) -> None:
        """Each speculative attempt back since the accepted set last changed, whose corridor's
        accepted set differs from the one it was planned against: kept (under the new set) when
        only missions were added and :func:`still_valid` holds, else planned again now."""
        state, opt = self.state, self.opt
        for key, (sseen, fut, t) in list(self.spec.items()):
            if fut.status != "finished" or self.rechecked.get(key) == state.changes:
                continue
            self.rechecked[key] = state.changes
            seen, obst = state.corridor(t, key[1], opt)
            if seen == sseen:
                continue
            if set(sseen) <= set(seen):
                a = self.result(fut)
                new = {m for m, _ in set(seen) - set(sseen)}
                if still_valid(a, [(m, v) for m, v in obst if m in new], t, self.sc, opt):
                    a.seen = seen
                    self.spec[key] = (seen, _Done(a), t)
                    self.stats["speculative_revalidated"] += 1
                    continue
            self.spec[key] = (seen, self.submit(t, key[1], seen, obst, urgent=False), t)
            self.checked.discard(key)
            self.stats["speculative_resubmitted"] += 1


def run_fleet(sc: Scenario, tasks: Sequence[FleetTask], *, cache_dir=None, options: FleetOptions | None = None,
              default_dop: float | None = None, client=None, depth: int = 1, affinity: str = "speculative",
              later_departures: bool = True, echo: Callable[[str], None] | None = None,
              airspace=None) -> FleetResult:
    """First-come-first-served planning of ``tasks`` (see the module docstring); ``client``: a
    dask.distributed Client for the speculative parallel driver (``depth`` missions in flight;
    ``affinity``: which attempts prefer their goal's worker: "all", "speculative" (the driver
    does not wait for them) or "none"; ``later_departures``: also speculate a mission's next
    departure when its speculative attempt came back failed or conflicting); ``airspace``: an
    :class:`~skyroute.stages.airspace_store.AirspaceStore` (same map CRS) the missions are
    planned against and every decision is written to (missions already decided there with
    the same fields are skipped: a run killed midway continues; intents accepted there before
    this run are never preempted)."""
    if affinity not in ("all", "speculative", "none"):
        raise InputError(f"affinity {affinity!r} must be 'all', 'speculative' or 'none'")
    if not (isinstance(depth, int) and depth >= 0):
        raise InputError(f"depth {depth!r} must be an integer >= 0 (speculative missions in flight)")
    opt = options or FleetOptions()
    t_setup = time.perf_counter()
    if client is not None and tasks:   # every worker loads the maps and kernels before the clock starts
        first = min(tasks, key=lambda t: (t.earliest_s, -t.priority, t.id))
        _warm_workers(client, sc, cache_dir, first, default_dop if first.dop_level is None else first.dop_level, opt)
    setup_s = time.perf_counter() - t_setup
    t_start = time.perf_counter()

    def level_of(t: FleetTask):
        return t.dop_level if t.dop_level is not None else default_dop

    state = _State()
    air = None
    if airspace is not None:
        air = _AirspaceLink(airspace, sc, opt, state, cache_dir)
        tasks = air.split(tasks)
        air.preload(tasks)
        if echo is not None:
            for m in air.continued:
                echo(f"fleet: {m} already decided in the airspace")
    order = sorted(tasks, key=lambda t: (t.earliest_s, -t.priority, t.id))
    outcomes = {t.id: MissionOutcome(t, level=level_of(t)) for t in order}
    queue: list[FleetTask] = list(order)
    planner = _Planner(sc, cache_dir, opt, level_of, queue, state, client, depth, affinity, later_departures)
    n_done = 0

    def try_at(task: FleetTask, dep: float, min_priority: int | None = None) -> tuple[Attempt, list[str]]:
        """An attempt and the accepted missions its volumes intersect (of priority >= min_priority)."""
        seen, obst = state.corridor(task, dep, opt, min_priority)
        a = planner.run(task, dep, seen, obst)
        o = outcomes[task.id]
        o.attempts += 1
        o.compute_s += a.compute_s
        if not a.ok:
            return a, []
        pairs = state.index.conflicts(a.volumes)
        who = list(dict.fromkeys(state.index.owner[j] for _, j in pairs))
        if air is not None:
            who += air.conflicts(a.volumes)
        if min_priority is not None:
            who = [m for m in who if state.priority[m] >= min_priority]
        return a, who

    while queue:
        task = queue.pop(0)
        planner.speculate()
        o = outcomes[task.id]
        dep = task.earliest_s
        accepted: Attempt | None = None
        victims: list[str] = []
        last_reason = ""
        a, who = try_at(task, dep)
        if a.ok and not who:
            accepted = a
        else:
            last_reason = a.reason if not a.ok else f"its volumes intersect accepted {', '.join(who)}"
            lower = [m for m in state.accepted if state.priority[m] < task.priority]
            if opt.preempt and lower:
                b, hi_conf = try_at(task, dep, min_priority=task.priority)
                if b.ok and not hi_conf:
                    victims = sorted({state.index.owner[j] for _, j in state.index.conflicts(b.volumes)})
                    for m in victims:
                        state.remove(m)
                        vo = outcomes[m]
                        vo.status, vo.preempted_by, vo.attempt = "preempted", task.id, None
                    accepted = b
                    for m in sorted(victims, key=lambda m: (outcomes[m].task.earliest_s, m), reverse=True):
                        queue.insert(0, outcomes[m].task)
            k = 1
            while accepted is None and not a.static and k * opt.delay_step_s <= opt.max_delay_s + 1e-9:
                a, who = try_at(task, dep + k * opt.delay_step_s)
                if a.ok and not who:
                    accepted = a
                else:
                    last_reason = a.reason if not a.ok else f"its volumes intersect accepted {', '.join(who)}"
                k += 1
        if accepted is not None:
            state.add(accepted, task.priority)
            o.attempt = accepted
            o.delay_s = accepted.departure_s - task.earliest_s
            o.status = ("preempted-replanned" if o.preempted_by else "delayed" if o.delay_s > 0 else "accepted")
            o.reason = f"preempted by {o.preempted_by}, re-planned" if o.preempted_by else ""
            if air is not None:
                air.accept(o, victims)
        else:
            o.status = "rejected"
            o.reason = ((f"preempted by {o.preempted_by}; then " if o.preempted_by else "")
                        + (f"no plan at any departure: {last_reason}" if a.static else
                           f"no conflict-free plan up to {opt.max_delay_s:g} s of delay: {last_reason}"))
            if air is not None:
                air.reject(o)
        planner.done(task)
        n_done += 1
        if echo is not None:
            echo(f"fleet: {task.id} {o.status} (delay {o.delay_s:g} s, {o.attempts} attempt(s))")
    for s in planner.spec.values():
        s[1].cancel()
    res = FleetResult([outcomes[t.id] for t in order], time.perf_counter() - t_start,
                      {**planner.stats, "worker_setup_s": round(setup_s, 3)},
                      airspace={} if air is None else air.summary())
    return res


