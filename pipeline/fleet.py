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

import csv
import datetime as dt
import math
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError, field_validator

from skyroute.pipeline.errors import InputError
from skyroute.pipeline.model import FrozenModel
from skyroute.pipeline.settings import MissionPoint, Scenario
from skyroute.stages.planning.request import (
    PLANNER_STAGES as MAP_STAGES,  # the maps a planner reads
)

__all__ = ["FLEET_COLUMNS", "Attempt", "FleetFileError", "FleetMission", "FleetOptions", "FleetResult", "FleetTask",
           "MissionOutcome", "default_level", "draw_missions", "fleet_maps", "independent_conflicts", "load_fleet",
           "mission_fields",
           "min_separation_m", "plan_attempt", "plot_fleet", "run_fleet", "still_valid", "write_fleet"]

FLEET_COLUMNS = ("mission", "operator", "priority", "status", "departure_utc", "earliest_s", "delay_s", "dop_level",
                 "energy_Wh", "length_m", "flight_time_s", "compute_s", "attempts", "volumes", "preempted_by",
                 "reason")


class FleetFileError(InputError):
    """A fleet file with problems: ``problems`` lists each (one ``error:`` line each)."""

    def __init__(self, source: str, problems: list[str]):
        self.problems = [f"{source}: {p}" for p in problems]
        super().__init__("\n".join(self.problems))


class FleetMission(FrozenModel):
    """One mission of a fleet file: ``departure`` is the earliest departure, seconds after the
    scenario's mission start or a UTC time; ``priority``: higher wins (F3548); ``vehicle``
    (default the scenario's); ``dop_level``: the DOP threshold D_j to plan at (default: the
    scenario's strictest flyable level)."""

    id: str
    operator: str = "operator"
    start: MissionPoint
    goal: MissionPoint
    departure: float | dt.datetime = 0.0
    priority: int = 0
    vehicle: str | None = None
    dop_level: float | None = None

    @field_validator("id")
    @classmethod
    def _id(cls, v: str) -> str:
        if not v or "/" in v or v.strip() != v:
            raise ValueError(f"mission id {v!r} must be non-empty, without '/' or surrounding spaces")
        return v


@dataclass(frozen=True)
class FleetTask:
    """A mission resolved on the scenario's map: x/y [m], earliest departure [s after the
    scenario start], DOP level."""

    index: int
    id: str
    operator: str
    start_xy: tuple[float, float]
    start_agl_m: float
    goal_xy: tuple[float, float]
    goal_agl_m: float
    earliest_s: float
    priority: int
    vehicle: str
    dop_level: float | None


@dataclass(frozen=True)
class FleetOptions:
    """Fleet settings: ``delay_step_s`` / ``max_delay_s`` [s]; ``seed`` (STEP II); ``k_sigma``
    and ``time_buffer_s`` [s], ``max_volume_s`` [s], ``max_dz_m`` [m] of the intent volumes;
    ``sigma_est_m`` [m]: the navigation error assumed to grow the obstacles before a plan
    exists; ``corridor_m`` [m], ``horizon_s`` [s]: the space-time corridor of an attempt (start-goal box
    grown by ``corridor_m``; from the departure to 3 x the direct flight time + 120 s, at most
    ``horizon_s``);
    ``preempt``: allow priority preemption; ``step2_max_iter``: K of each attempt's STEP II RRT
    (the seed's 5000, as ``skyroute plan``; a failed deconfliction costs all K iterations, on
    Helsinki 0.14 s, before the mission is tried at a later departure)."""

    delay_step_s: float = 60.0
    max_delay_s: float = 600.0
    seed: int = 0
    k_sigma: float = 3.0
    time_buffer_s: float = 5.0
    max_volume_s: float = 10.0
    max_dz_m: float = 5.0
    sigma_est_m: float = 1.5
    corridor_m: float = 250.0
    horizon_s: float = 900.0
    preempt: bool = True
    time_budget_s: float = 5.0
    step2_max_iter: int = 5000


# ---------------------------------------------------------------------------------- fleet input
def _csv_records(path: Path) -> list[dict]:
    out = []
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            rec: dict[str, Any] = {}
            pts: dict[str, dict] = {"start": {}, "goal": {}}
            for k, v in row.items():
                if k is None or v is None or str(v).strip() == "":
                    continue
                k, v = k.strip(), str(v).strip()
                head, _, tail = k.partition("_")
                if head in pts and tail:
                    pts[head][tail] = v
                else:
                    rec[k] = v
            rec.update({k: p for k, p in pts.items() if p})
            out.append(rec)
    return out


def _departure_s(dep, t0: dt.datetime) -> float:
    if isinstance(dep, dt.datetime):
        d = dep if dep.tzinfo is not None else dep.replace(tzinfo=dt.UTC)
        return (d - t0).total_seconds()
    return float(dep)


def load_fleet(path: Path | str, sc: Scenario, levels: Sequence[float] = ()) -> list[FleetTask]:
    """The missions of a fleet file (YAML ``missions: [...]`` or CSV with columns id, operator,
    start_x / start_y or start_lon / start_lat, start_alt_agl_m, goal_..., departure, priority,
    vehicle, dop_level) as :class:`FleetTask` s.  Every problem is collected and raised at once
    (:class:`FleetFileError`): schema, duplicate ids, points outside the map, departures before
    the scenario start, unknown vehicles, DOP levels not among the scenario's ``levels``."""
    import yaml

    from skyroute.stages.vehicle import load_vehicle

    path = Path(path)
    src = str(path)
    if not path.is_file():
        raise FleetFileError(src, ["no such file; give a YAML or CSV fleet file"])
    try:
        if path.suffix.lower() == ".csv":
            records = _csv_records(path)
        else:
            doc = yaml.safe_load(path.read_text())
            if not isinstance(doc, dict) or not isinstance(doc.get("missions"), list):
                raise FleetFileError(src, ["the YAML needs a top-level list 'missions: [...]'"])
            records = doc["missions"]
    except (yaml.YAMLError, csv.Error, UnicodeDecodeError) as exc:
        raise FleetFileError(src, [f"cannot be read: {exc}".replace("\n", " ")]) from None
    if not records:
        raise FleetFileError(src, ["no mission in the file"])
    problems: list[str] = []
    missions: list[tuple[int, FleetMission]] = []
    for i, rec in enumerate(records):
        name = rec.get("id", f"#{i + 1}") if isinstance(rec, dict) else f"#{i + 1}"
        try:
            missions.append((i, FleetMission.model_validate(rec)))
        except ValidationError as exc:
            for e in exc.errors():
                loc = ".".join(str(x) for x in e["loc"])
                problems.append(f"mission {name}: {loc + ': ' if loc else ''}{e['msg']}")
    seen: dict[str, int] = {}
    g = sc.grid
    xmin, ymin, xmax, ymax = g.bounds
    t0 = sc.mission.start_time_utc
    tasks = []
    for i, m in missions:
        if m.id in seen:
            problems.append(f"mission {m.id}: id already used by mission #{seen[m.id] + 1}")
        seen.setdefault(m.id, i)
        xy = {}
        for which in ("start", "goal"):
            x, y = sc.point_xy(getattr(m, which))
            if not (xmin <= x <= xmax and ymin <= y <= ymax):
                problems.append(f"mission {m.id}: {which} ({x:.1f}, {y:.1f}) is outside the scenario's map "
                                f"[{xmin:.1f}, {xmax:.1f}] x [{ymin:.1f}, {ymax:.1f}]")
            xy[which] = (float(x), float(y))
        dep = _departure_s(m.departure, t0)
        if not math.isfinite(dep) or dep < 0:
            problems.append(f"mission {m.id}: departure {m.departure} is before the scenario start {t0.isoformat()}")
        veh = m.vehicle or sc.vehicle
        try:
            load_vehicle(veh)
        except Exception as exc:   # noqa: BLE001 - the loader's own message says what is known
            problems.append(f"mission {m.id}: vehicle: {exc}")
        if m.dop_level is not None and levels and not any(abs(m.dop_level - d) < 1e-9 for d in levels):
            problems.append(f"mission {m.id}: dop_level {m.dop_level:g} is not one of the scenario's levels "
                            f"{', '.join(f'{d:g}' for d in levels)}")
        tasks.append(FleetTask(i, m.id, m.operator, xy["start"], m.start.alt_agl_m, xy["goal"], m.goal.alt_agl_m,
                               dep, m.priority, veh, m.dop_level))
    if problems:
        raise FleetFileError(src, problems)
    return tasks


def draw_missions(sc: Scenario, maps: dict, n: int, seed: int, window_s: float, *, alt_agl_m: float | None = None,
                  min_km: float = 0.2, max_km: float = 1.5, operators: int = 5,
                  priority_share: float = 0.1, notes: list[str] | None = None) -> list[FleetTask]:
    """``n`` missions between the landing sites of the environment stage (``site_x`` /
    ``site_y``; OSM helipads, hospitals' pads, parks, ... as :mod:`skyroute.stages.landing`
    finds them) whose cell is not no-fly and whose clearance floor lies below ``alt_agl_m``
    (default the scenario's start altitude) above the ground: start and goal drawn uniformly
    among the pairs ``min_km``-``max_km`` apart, departure uniform in ``[0, window_s]`` [s],
    operator ``op-1..op-<operators>``, priority 1 with probability ``priority_share`` (else 0),
    the scenario's vehicle and the default DOP level.  ``np.random.default_rng(seed)``.  A site
    is usable when the mission altitude above it lies between the clearance floor and ceiling
    (not no-fly); a pair is drawn only when both lie in one 8-connected region of cells where
    the vehicle may be at some altitude.

    A city without such a pair of landing sites (a user's own DSM or CityJSON) gets candidate
    sites derived from open ground (:func:`skyroute.stages.landing.open_ground_sites`: no
    obstacle within r_p, not no-fly, the lowest risk level present), said in ``notes``."""
    env, surf, clear = maps["environment"], maps["surface"], maps["clearance"]
    alt = float(sc.mission.start.alt_agl_m if alt_agl_m is None else alt_agl_m)
    g = sc.grid
    n_sites = int(len(env["site_x"])) if "site_x" in env.coords else 0
    if n_sites:
        sx, sy = np.asarray(env["site_x"].values, float), np.asarray(env["site_y"].values, float)
    else:
        sx = sy = np.zeros(0)

    from scipy import ndimage

    floor_all = np.asarray(clear["min_altitude_m"].values, float)
    ceil_all = np.asarray(clear["max_altitude_m"].values, float)
    nofly_all = np.asarray(clear["nofly"].values, bool) if "nofly" in clear else np.zeros(g.shape, bool)
    # cells where the vehicle may be at some altitude, and their 8-connected regions: a pair of
    # sites in two regions has no path at all
    region, _ = ndimage.label(np.isfinite(floor_all) & (floor_all <= ceil_all) & ~nofly_all, np.ones((3, 3), bool))

    def usable_pairs(sx, sy):
        r, c = g.cell_of(sx, sy)
        top = np.asarray(surf["terrain"].values)[r, c] + alt     # the mission's start / goal altitude
        ok = np.isfinite(floor_all[r, c]) & (floor_all[r, c] <= top) & (top <= ceil_all[r, c]) & ~nofly_all[r, c]
        idx = np.flatnonzero(ok)
        d = np.hypot(sx[idx, None] - sx[None, idx], sy[idx, None] - sy[None, idx])
        lab = region[r[idx], c[idx]]
        ii, jj = np.nonzero((d >= min_km * 1e3) & (d <= max_km * 1e3) & (lab[:, None] == lab[None, :]))
        return idx, ii, jj

    idx, ii, jj = usable_pairs(sx, sy)
    if ii.size == 0:
        from skyroute.stages.landing import OPEN_GROUND_SPACING_M, open_ground_sites

        nofly = nofly_all
        ox, oy, level = open_ground_sites(
            terrain=np.asarray(surf["terrain"].values, float), surface=np.asarray(surf["surface"].values, float),
            obstacle_floor=np.asarray(clear["obstacle_floor_m"].values, float),
            risk_level=np.asarray(env["risk_level"].values), nofly=nofly, grid=g,
            radius_m=float(clear.attrs.get("radius_m", 0.0)))
        idx, ii, jj = usable_pairs(ox, oy)
        if ii.size == 0:
            raise InputError(f"no pair of usable landing sites of {sc.name} lies {min_km}-{max_km} km apart, nor of "
                             "candidate sites on open ground; give data.landing_sites (a GeoJSON) or a fleet file "
                             "(--fleet)")
        sx, sy = ox, oy
        if notes is not None:
            notes.append(f"fleet: scenario {sc.name} has {n_sites} landing site(s) and no usable pair of them "
                         f"(the mission altitude {alt:g} m AGL between the clearance floor and ceiling, connected) "
                         f"{min_km}-{max_km} km apart: missions are drawn between {len(ox)} candidate sites derived "
                         f"from open ground (no obstacle within r_p, not no-fly, risk level {level}, one per "
                         f"{OPEN_GROUND_SPACING_M:g} m block); give data.landing_sites (a GeoJSON) for real ones")
    rng = np.random.default_rng(seed)
    pick = rng.integers(0, ii.size, n)
    dep = np.sort(rng.uniform(0.0, window_s, n))
    ops = rng.integers(1, operators + 1, n)
    pri = (rng.random(n) < priority_share).astype(int)
    out = []
    for k in range(n):
        a, b = idx[ii[pick[k]]], idx[jj[pick[k]]]
        out.append(FleetTask(k, f"m{k + 1:04d}", f"op-{ops[k]}", (float(sx[a]), float(sy[a])), alt,
                             (float(sx[b]), float(sy[b])), alt, round(float(dep[k]), 1), int(pri[k]), sc.vehicle,
                             None))
    return out


# ---------------------------------------------------------------------------------- the maps
_MAPS: dict[str, dict] = {}


def fleet_maps(sc: Scenario, cache_dir: Path | str | None, scheduler: str = "threads") -> dict:
    """The scenario's map datasets (loaded in memory) and the plan stage's dataset, from the
    cache (computed once when absent); memoised per process (each dask worker loads them once)."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.graph import stages_for
    from skyroute.pipeline.model import stable_hash
    from skyroute.pipeline.runner import run_scenario

    key = stable_hash("fleet-maps-1", sc.model_dump(mode="json"), str(cache_dir))
    if key in _MAPS:
        return _MAPS[key]
    names = [s.name for s in stages_for(sc) if s.name in (*MAP_STAGES, "plan")]
    res = run_scenario(sc, cache=Cache(cache_dir), targets=names, scheduler=scheduler)
    maps: dict[str, Any] = {k: res[k].load() for k in names if k in res.datasets}
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
    fleet_maps(sc, cache_dir, scheduler="synchronous")
    if task is not None:
        plan_attempt(sc, cache_dir, task, task.earliest_s, level, [], opt or FleetOptions())


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


# ---------------------------------------------------------------------------------- one attempt
@dataclass
class Attempt:
    """One planning attempt of a mission at a departure: ``ok`` when a flyable plan came out
    (not yet checked against the accepted volumes); its intent ``volumes`` (W84, fleet time
    [s]), ``obstacles`` (the same in the surface datum, conservative band) and ``doc`` (the
    F3548 OperationalIntentDetails dict); ``xyz_m`` / ``t_s``: the trajectory sampled every
    0.05 s (map CRS, surface datum; fleet time)."""

    mission: str
    departure_s: float
    ok: bool
    reason: str = ""
    volumes: list = field(default_factory=list)
    obstacles: list = field(default_factory=list)
    doc: dict | None = None
    xyz_m: np.ndarray | None = None
    t_s: np.ndarray | None = None
    energy_Wh: float = math.nan
    length_m: float = math.nan
    flight_time_s: float = math.nan
    compute_s: float = 0.0
    seen: tuple = ()
    step2_status: str = ""
    chain: tuple | None = None        # STEP II chain (waypoints (k, 3) [m], times [s] mission time)
    trajectory: tuple | None = None   # (CornerTrajectory, t0 [s] mission time)
    static: bool = False              # failed (ok False) in STEP I: no departure can help
    free_legs: np.ndarray | None = None   # Step2Result.free_legs of an RRT run (mission time)


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
            start_time_utc=t0_utc, vehicle=veh, weights=p.weights, planner="astar", time_budget_s=opt.time_budget_s,
            seed=_seed(opt.seed, task.id, departure_s), max_tries=p.max_tries, step_cells=p.step_cells,
            min_agl_m=sc.constraints.min_altitude_agl_m, max_agl_m=sc.constraints.max_altitude_agl_m,
            dop_kind=sc.gnss.dop_kind, d_c_m=sc.traffic.margin_m, dt_c_s=sc.traffic.time_margin_s,
            uere_m=sc.gnss.uere_m, workers=1, battery_reserve_pct=sc.constraints.battery_reserve_pct,
            step2_max_iter=opt.step2_max_iter)
        area = Maps(surface=maps["surface"], clearance=maps["clearance"], environment=maps.get("environment"),
                    wind=maps.get("wind"), coverage=cov, satellites=maps.get("satellites"), traffic=occ)
        plan = plan_strategic(area, request, heuristic_cache=maps.setdefault("_heuristics", {}),
                         edge_cache=maps.setdefault("_edges", {}))
    except SkyrouteError as exc:
        return Attempt(task.id, departure_s, False, f"planner: {exc}", compute_s=time.perf_counter() - t_start,
                       seen=seen)
    c = plan.chosen
    if c is None:
        static = all(s1 is not None and not s1.solved and s1.info.get("stopped_by") != "time"
                     for s1 in plan.step1)   # STEP I failed: the same at any departure
        s2 = plan.step2[0] if len(plan.step2) == 1 else None
        return Attempt(task.id, departure_s, False, plan.reason or "no flyable plan",
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


# ---------------------------------------------------------------------------------- the fleet
@dataclass
class MissionOutcome:
    """The fleet decision of one mission (a row of fleet.csv)."""

    task: FleetTask
    status: str = "pending"
    attempt: Attempt | None = None
    delay_s: float = 0.0
    attempts: int = 0
    compute_s: float = 0.0
    reason: str = ""
    preempted_by: str = ""
    level: float | None = None


@dataclass
class FleetResult:
    outcomes: list[MissionOutcome]
    seconds: float
    speculative: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    airspace: dict = field(default_factory=dict)

    def counts(self) -> dict[str, int]:
        out = {k: 0 for k in ("accepted", "delayed", "rejected", "preempted-replanned")}
        for o in self.outcomes:
            out[o.status] = out.get(o.status, 0) + 1
        return out


class _State:
    """The accepted missions: their obstacles (surface datum), a version per mission (bumped
    when withdrawn or re-accepted) and the VolumeIndex of their intent volumes (rebuilt on a
    withdrawal)."""

    def __init__(self):
        from skyroute.stages.fleet import VolumeIndex

        self.accepted: dict[str, Attempt] = {}
        self.priority: dict[str, int] = {}
        self.version: dict[str, int] = {}
        self.index = VolumeIndex()
        self._VolumeIndex = VolumeIndex

    def add(self, a: Attempt, priority: int) -> None:
        self.accepted[a.mission] = a
        self.priority[a.mission] = priority
        self.version[a.mission] = self.version.get(a.mission, 0) + 1
        self.index.add(a.volumes, a.mission)

    def remove(self, mission: str) -> None:
        self.accepted.pop(mission)
        self.version[mission] = self.version.get(mission, 0) + 1
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


FIRM_PRIORITY = 2**62      # intents accepted before this run (an airspace store): never preempted


def mission_fields(task: FleetTask, sc: Scenario) -> dict:
    """The fields that identify a mission in an airspace store (a later run with the same id
    and the same fields continues; another mission under that id is an error)."""
    import pandas as pd

    t0 = pd.Timestamp(sc.mission.start_time_utc)
    t0 = t0.tz_localize("UTC") if t0.tzinfo is None else t0.tz_convert("UTC")
    return {"scenario": sc.name, "operator": task.operator,
            "start_xy_m": [round(float(v), 3) for v in task.start_xy], "start_agl_m": float(task.start_agl_m),
            "goal_xy_m": [round(float(v), 3) for v in task.goal_xy], "goal_agl_m": float(task.goal_agl_m),
            "earliest_departure_utc": (t0 + pd.Timedelta(seconds=task.earliest_s)).isoformat(),
            "priority": int(task.priority), "vehicle": task.vehicle, "dop_level": task.dop_level}


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


class _Planner:
    """Runs attempts: inline (sequential) or on a dask client (speculative)."""

    def __init__(self, sc, cache_dir, opt, level_of, queue: list[FleetTask], state: _State, client=None,
                 depth: int = 1, affinity: str = "speculative", later: bool = True):
        self.sc, self.cache_dir, self.opt, self.level_of, self.client = sc, cache_dir, opt, level_of, client
        self.queue, self.state = queue, state       # the driver's: the missions to come, the accepted set
        self.depth, self.affinity, self.later = depth, affinity, later
        self.spec: dict[tuple[str, float], Any] = {}   # (mission id, departure) -> (seen, future, task)
        self.checked: set[tuple[str, float]] = set()
        self.workers: list[str] | None = None
        self.stats = {"speculative_used": 0, "speculative_still_valid": 0, "speculative_replanned": 0,
                      "speculative_later_departures": 0, "attempts": 0}

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
        return self.client.submit(plan_attempt, *args, pure=False, priority=10**9 if urgent else -task.index,
                                  workers=self._worker_of(task) if prefer else None, allow_other_workers=prefer)

    def run(self, task, dep, seen, obst) -> Attempt:
        self.stats["attempts"] += 1
        self.speculate()
        s = self.spec.pop((task.id, dep), None)
        self.checked.discard((task.id, dep))
        if s is not None:
            sseen, fut, _ = s
            if sseen == seen:
                self.stats["speculative_used"] += 1
                return fut.result()
            if set(sseen) <= set(seen):     # only new accepted missions in the corridor
                a = fut.result()
                new = {m for m, _ in set(seen) - set(sseen)}
                if still_valid(a, [(m, v) for m, v in obst if m in new], task, self.sc, self.opt):
                    self.stats["speculative_used"] += 1
                    self.stats["speculative_still_valid"] += 1
                    a.seen = seen
                    return a
            self.stats["speculative_replanned"] += 1
            fut.cancel()
        out = self.submit(task, dep, seen, obst)
        return out if self.client is None else out.result()

    def done(self, task) -> None:
        """``task`` is decided: drop its speculative attempts."""
        for key in [k for k in self.spec if k[0] == task.id]:
            self.spec.pop(key)[1].cancel()
            self.checked.discard(key)

    def speculate(self) -> None:
        """Keep the first attempts of the next ``depth`` missions of ``queue`` in flight, each
        against the accepted set of the moment it was submitted, and, when a speculative attempt
        has come back failed (not in STEP I) or meeting an accepted volume, the same mission
        one delay step later: the attempt the driver will ask for next if nothing changes.  A
        running task cannot be stopped: an attempt no longer wanted is left to finish."""
        if self.client is None:
            return
        opt, state = self.opt, self.state
        for t in self.queue[:self.depth]:
            if (t.id, t.earliest_s) in self.spec:
                continue
            seen, obst = state.corridor(t, t.earliest_s, opt)
            self.spec[(t.id, t.earliest_s)] = (seen, self.submit(t, t.earliest_s, seen, obst, urgent=False), t)
        for (mid, dep), (_, fut, t) in list(self.spec.items()) if self.later else ():
            if (mid, dep) in self.checked or fut.status != "finished":
                continue
            self.checked.add((mid, dep))
            a = fut.result()
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
        client.run(_warm, sc, cache_dir, first, default_dop if first.dop_level is None else first.dop_level, opt)
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


# ---------------------------------------------------------------------------------- independent checks
def independent_conflicts(docs: dict[str, dict], crs, start_time_utc) -> list[tuple[str, str]]:
    """Pairs of missions whose intent documents intersect, by plain pairwise shapely code (every
    pair of volumes of two different intents: altitude overlap, time overlap and intersection
    area > 1e-4 m^2 in the metric ``crs``), independent of the VolumeIndex that accepted them."""
    from skyroute.stages.fleet import MIN_AREA_M2, volumes_of_intent

    vols = {m: volumes_of_intent(d, crs, start_time_utc) for m, d in docs.items()}
    ids = sorted(vols)
    span = {m: (min((u.t_start_s for u in vs), default=math.inf), max((u.t_end_s for u in vs), default=-math.inf))
            for m, vs in vols.items()}
    bad = []
    for i, a in enumerate(ids):
        for b in ids[i + 1:]:
            if not (span[a][0] < span[b][1] and span[b][0] < span[a][1]):
                continue       # no volume of a overlaps a volume of b in time
            hit = False
            for u in vols[a]:
                for v in vols[b]:
                    if (u.alt_lower_m < v.alt_upper_m and v.alt_lower_m < u.alt_upper_m and u.t_start_s < v.t_end_s
                            and v.t_start_s < u.t_end_s and u.polygon.intersection(v.polygon).area > MIN_AREA_M2):
                        hit = True
                        break
                if hit:
                    break
            if hit:
                bad.append((a, b))
    return bad


def min_separation_m(tracks: dict[str, tuple[np.ndarray, np.ndarray]]) -> tuple[float, tuple[str, str] | None]:
    """Smallest 3-D distance [m] between two tracks at the same time (each track: times [s],
    positions (n, 3) [m]; the other track linearly interpolated at one track's samples)."""
    ids = sorted(tracks)
    best, who = math.inf, None
    for i, a in enumerate(ids):
        ta, pa = tracks[a]
        for b in ids[i + 1:]:
            tb, pb = tracks[b]
            if ta[-1] < tb[0] or tb[-1] < ta[0]:
                continue
            m = (ta >= tb[0]) & (ta <= tb[-1])
            if not m.any():
                continue
            q = np.column_stack([np.interp(ta[m], tb, pb[:, k]) for k in range(3)])
            d = float(np.min(np.linalg.norm(pa[m] - q, axis=1)))
            if d < best:
                best, who = d, (a, b)
    return best, who


# ---------------------------------------------------------------------------------- outputs
def _accepted(res: FleetResult) -> list[MissionOutcome]:
    return [o for o in res.outcomes if o.attempt is not None and o.status != "rejected"]


def write_fleet(res: FleetResult, sc: Scenario, maps: dict, out_dir: Path) -> tuple[list[Path], dict]:
    """fleet.csv, intents/<mission>.json (accepted, delayed, re-planned), fleet.geojson,
    tracks.csv (0.05 s), fleet.png; returns (files, summary ``fleet`` section)."""
    import json

    import pandas as pd
    from pyproj import Transformer

    from skyroute.stages.intents import parse_intent

    out = Path(out_dir)
    (out / "intents").mkdir(parents=True, exist_ok=True)
    for old in (out / "intents").glob("*.json"):
        old.unlink()
    t0 = pd.Timestamp(sc.mission.start_time_utc)
    files: list[Path] = []
    rows = []
    for o in res.outcomes:
        a = o.attempt if o.status != "rejected" else None
        rows.append({"mission": o.task.id, "operator": o.task.operator, "priority": o.task.priority,
                     "status": o.status,
                     "departure_utc": (t0 + pd.Timedelta(seconds=a.departure_s)).isoformat() if a else "",
                     "earliest_s": round(o.task.earliest_s, 3), "delay_s": round(o.delay_s, 3) if a else "",
                     "dop_level": "" if o.level is None else o.level,
                     "energy_Wh": round(a.energy_Wh, 3) if a else "", "length_m": round(a.length_m, 2) if a else "",
                     "flight_time_s": round(a.flight_time_s, 2) if a else "", "compute_s": round(o.compute_s, 3),
                     "attempts": o.attempts, "volumes": len(a.volumes) if a else 0, "preempted_by": o.preempted_by,
                     "reason": o.reason})
    p = out / "fleet.csv"
    with open(p, "w", newline="") as f:
        w = csv.DictWriter(f, FLEET_COLUMNS)
        w.writeheader()
        w.writerows(rows)
    files.append(p)
    acc = _accepted(res)
    docs = {}
    for o in acc:
        parse_intent(o.attempt.doc)          # F3548 schema and limits (uas-standards)
        docs[o.task.id] = o.attempt.doc
        q = out / "intents" / f"{o.task.id}.json"
        q.write_text(json.dumps(o.attempt.doc, indent=1))
        files.append(q)
    crs = maps["surface"]["surface"].rio.crs
    datum = str(maps["surface"]["surface"].attrs.get("vertical_datum", ""))
    to_ll = Transformer.from_crs(crs, 4326, always_xy=True)
    feats = []
    with open(out / "tracks.csv", "w") as f:
        f.write("mission,t_s,x_m,y_m,z_m\n")
        for o in acc:
            a = o.attempt
            np.savetxt(f, np.column_stack([a.t_s, a.xyz_m]), fmt=[o.task.id + ",%.3f", "%.3f", "%.3f", "%.3f"],
                       delimiter=",")
            k = np.unique(np.r_[np.arange(0, a.t_s.size, 20), a.t_s.size - 1])
            lon, lat = to_ll.transform(a.xyz_m[k, 0], a.xyz_m[k, 1])
            feats.append({"type": "Feature", "geometry": {"type": "LineString", "coordinates": [
                [round(float(x), 7), round(float(y), 7), round(float(z), 2)] for x, y, z in zip(lon, lat, a.xyz_m[k, 2],
                                                                                             strict=True)]},
                "properties": {"mission": o.task.id, "operator": o.task.operator, "status": o.status,
                               "priority": o.task.priority,
                               "departure_utc": (t0 + pd.Timedelta(seconds=a.departure_s)).isoformat(),
                               "delay_s": o.delay_s, "z_datum": datum}})
    files.append(out / "tracks.csv")
    gj = {"type": "FeatureCollection", "name": f"skyroute fleet {sc.name}",
          "description": f"accepted trajectories (lon, lat [deg] WGS 84; z [m] in the surface datum of the maps: "
                         f"{datum}; absolute heights are in intents/*.json, WGS 84 ellipsoidal)",
          "vertical_datum": datum, "features": feats}
    (out / "fleet.geojson").write_text(json.dumps(gj))
    files.append(out / "fleet.geojson")
    files.append(plot_fleet(res, sc, maps, out / "fleet.png"))
    conflicts = independent_conflicts(docs, crs, sc.mission.start_time_utc.isoformat())
    sep, pair = min_separation_m({o.task.id: (o.attempt.t_s, o.attempt.xyz_m) for o in acc})
    counts = res.counts()
    delays = [o.delay_s for o in acc]
    attempts = sum(o.attempts for o in res.outcomes)
    section = {"missions": len(res.outcomes), "counts": counts, "accepted_total": len(acc),
               "mean_delay_s": float(np.mean(delays)) if delays else None,
               "seconds": round(res.seconds, 3), "planning_attempts": attempts,
               "throughput_plans_per_min": round(attempts / res.seconds * 60.0, 2) if res.seconds > 0 else None,
               "missions_per_min": round(len(res.outcomes) / res.seconds * 60.0, 2) if res.seconds > 0 else None,
               "conflicts_independent_check": len(conflicts), "conflicting_pairs": [list(c) for c in conflicts],
               "min_separation_m": None if not math.isfinite(sep) else round(sep, 3),
               "min_separation_pair": list(pair) if pair else None,
               "required_separation_m": _required_separation_m(acc, sc), "preempted": sorted(o.task.id for o in res.outcomes if o.preempted_by),
               "speculative": res.speculative, "z_datum_geojson": datum,
               "notes": ["the scenario's own intruders are not fleet traffic: the traffic of each mission is the "
                         "accepted intents"]}
    return files, section


def _required_separation_m(acc: Sequence[MissionOutcome], sc: Scenario) -> float | None:
    """The separation the accepted tracks must keep [m]: the least r_p of their vehicles + d_c."""
    from skyroute.stages.vehicle import load_vehicle

    r = [load_vehicle(o.task.vehicle).r_p_m for o in acc]
    return round(min(r) + float(sc.traffic.margin_m), 3) if r else None


def plot_fleet(res: FleetResult, sc: Scenario, maps: dict, path: Path) -> Path:
    """Two panels: the accepted paths over the surface model, and the timeline of every
    accepted mission's intent volumes (one row per mission)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    acc = _accepted(res)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(13, 6.2), gridspec_kw={"width_ratios": [1, 1.25]})
    s = maps["surface"]["surface"]
    x, y = np.asarray(s["x"].values), np.asarray(s["y"].values)
    step = max(1, int(max(x.size, y.size) / 800))
    im = ax.imshow(np.asarray(s.values)[::step, ::step], extent=(x.min(), x.max(), y.min(), y.max()), origin="upper"
                   if y[0] > y[-1] else "lower", cmap="Greys", interpolation="nearest")
    fig.colorbar(im, ax=ax, shrink=0.7, label="surface [m]")
    cmap = plt.get_cmap("tab20")
    for i, o in enumerate(acc):
        p = o.attempt.xyz_m
        ax.plot(p[:, 0], p[:, 1], lw=0.9, color=cmap(i % 20))
        ax.plot(p[0, 0], p[0, 1], "o", ms=2.5, color=cmap(i % 20))
    ax.set_title(f"{sc.name}: {len(acc)} accepted paths")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.tick_params(axis="x", labelrotation=30)
    colors = {"accepted": "tab:green", "delayed": "tab:orange", "preempted-replanned": "tab:purple"}
    for i, o in enumerate(acc):
        for v in o.attempt.volumes:
            bx.plot([v.t_start_s / 60.0, v.t_end_s / 60.0], [i, i], lw=2.5, color=colors.get(o.status, "k"),
                    solid_capstyle="butt")
    for k, c in colors.items():
        bx.plot([], [], color=c, lw=3, label=k)
    rej = sum(o.status == "rejected" for o in res.outcomes)
    bx.legend(loc="lower right", fontsize=8, title=f"rejected: {rej}", title_fontsize=8)
    bx.set_xlabel("time after the scenario start [min]")
    bx.set_ylabel("accepted mission (order of acceptance)")
    bx.set_title("intent volumes' time windows")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
