"""The fleet's mission model (``skyroute fleet``): a fleet file's missions (:func:`load_fleet`) or
missions drawn on a map (:func:`draw_missions`), the driver's options, attempts and outcomes."""

from __future__ import annotations

import csv
import datetime as dt
import io
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError, field_validator

from skyroute.pipeline.errors import InputError
from skyroute.pipeline.model import FrozenModel
from skyroute.pipeline.settings import MissionPoint, Scenario

__all__ = ["Attempt", "FIRM_PRIORITY", "FLEET_PLANNER", "FleetFileError", "FleetMission", "FleetOptions", "FleetResult",
           "FleetTask", "MAX_FLEET_MISSIONS", "MAX_ID_CHARS", "MAX_PRIORITY", "MIN_PRIORITY", "MissionOutcome",
           "check_fleet_vehicle", "check_mission_id", "draw_missions", "load_fleet", "mission_fields"]

#: The STEP I planner of every fleet mission (:func:`skyroute.pipeline.fleet.plan_attempt`): a
#: rotorcraft planner, so a fixed-wing vehicle is refused before the maps are built.
FLEET_PLANNER = "astar"
#: Missions of one fleet run (a fleet file or --missions): a busy city's day is a few thousand;
#: a larger day is split into runs that add to one airspace file (--airspace FILE).
MAX_FLEET_MISSIONS = 100_000
#: A mission id names files (``intents/<id>.json``) and airspace rows: at most this many
#: characters of ``A-Z a-z 0-9 . _ -``, not starting with a dot or a dash.
MAX_ID_CHARS = 64
#: F3548 priorities of a fleet file (higher wins), stored as SQLite integers: a signed 32-bit
#: range (the driver keeps 2**62 for intents accepted before the run, :data:`FIRM_PRIORITY`).
MIN_PRIORITY, MAX_PRIORITY = -(2**31), 2**31 - 1
MAX_OPERATOR_CHARS = 128
_ID_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9._-]*")


def _shown(v: str, n: int = 40) -> str:
    """``v`` for a message: repr, truncated to ``n`` characters with its length."""
    return repr(v) if len(v) <= n else f"{v[:n]!r}... ({len(v):,} characters)"


def check_mission_id(v: str, what: str = "mission id") -> str:
    """``v`` when it is a safe mission / intent id (it names a file): 1 to :data:`MAX_ID_CHARS`
    characters of letters, digits, ``.``, ``_`` and ``-``, not starting with ``.`` or ``-``;
    else ValueError showing it (truncated) and the rule."""
    if not isinstance(v, str):
        raise ValueError(f"{what} must be a text, got {type(v).__name__}")
    if not v:
        raise ValueError(f"{what} is empty; give a short name such as m0001")
    if len(v) > MAX_ID_CHARS:
        raise ValueError(f"{what} {_shown(v)} is longer than {MAX_ID_CHARS} characters (it names the file "
                         "intents/<id>.json); give a shorter id")
    if not _ID_RE.fullmatch(v):
        bad = sorted({c for c in v if not (c.isascii() and (c.isalnum() or c in "._-"))})
        why = (f"holds {', '.join(repr(c) for c in bad[:5])}" if bad else "starts with '.' or '-'")
        raise ValueError(f"{what} {_shown(v)} {why}: use letters, digits, '.', '_' and '-' (not first: '.', '-'); "
                         "it names the file intents/<id>.json")
    return v


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
        return check_mission_id(v)

    @field_validator("operator")
    @classmethod
    def _operator(cls, v: str) -> str:
        if not v.strip() or len(v) > MAX_OPERATOR_CHARS or not v.isprintable():
            raise ValueError(f"operator {_shown(v)} must be 1 to {MAX_OPERATOR_CHARS} printable characters")
        return v

    @field_validator("priority")
    @classmethod
    def _priority(cls, v: int) -> int:
        if not MIN_PRIORITY <= v <= MAX_PRIORITY:
            digits = str(abs(v))
            shown = f"{v:,}" if len(digits) <= 15 else f"{'-' if v < 0 else ''}{digits[0]}.{digits[1:3]}e{len(digits) - 1}"
            raise ValueError(f"priority {shown} is outside {MIN_PRIORITY:,}..{MAX_PRIORITY:,} (an integer, higher "
                             "wins; stored as an SQLite integer); give a smaller priority")
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
    Helsinki 0.14 s, before the mission is tried at a later departure); ``time_budget_s`` [s]:
    the planner's time budget of a mission up to :data:`BUDGET_KM` long, in proportion to the
    length beyond (:meth:`budget_s`).  Planners stop on counted work; the budget only sets the
    wall-clock safety net (x ``WALLCLOCK_CAP_FACTOR``), which must not cut a city-wide
    mission's plan short: a cut plan would depend on the machine's load, and a speculative
    plan on a worker could differ from the sequential one."""

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

    def budget_s(self, start_xy, goal_xy) -> float:
        """The time budget [s] of a mission from ``start_xy`` to ``goal_xy`` [m]:
        ``time_budget_s x max(1, distance / BUDGET_KM)``."""
        d_km = math.hypot(goal_xy[0] - start_xy[0], goal_xy[1] - start_xy[1]) / 1000.0
        return self.time_budget_s * max(1.0, d_km / BUDGET_KM)


BUDGET_KM = 1.5      # [km] missions up to this long get FleetOptions.time_budget_s; longer ones in proportion


# ---------------------------------------------------------------------------------- fleet input
def _csv_records(text: str) -> list[dict]:
    out = []
    with io.StringIO(text, newline="") as f:
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
    vehicle, dop_level) as :class:`FleetTask` s.  The file is read within the YAML reader's
    size limit (a device, FIFO or endless stream is a DataError) and parsed by it (YAML).  Every
    problem is collected and raised at once (:class:`FleetFileError`), before any map is built:
    schema, ids that are not safe file names (:func:`check_mission_id`), duplicate ids,
    priorities beyond :data:`MIN_PRIORITY` .. :data:`MAX_PRIORITY`, points outside the map or
    outside the scenario's altitude constraints, start and goal less than one cell apart,
    departures before the scenario start, unknown vehicles or fixed-wing ones
    (:func:`check_fleet_vehicle`), DOP levels not among the scenario's ``levels``; more than
    :data:`MAX_FLEET_MISSIONS` missions."""
    from skyroute.stages.base import ScenarioError, read_limited
    from skyroute.stages.yaml_io import MAX_BYTES, read_yaml_text

    path = Path(path)
    src = str(path)
    data = read_limited(path, MAX_BYTES, "fleet")   # DataError naming the file: missing, a device, endless, too large
    try:
        if path.suffix.lower() == ".csv":
            if b"\x00" in data:
                raise FleetFileError(src, ["holds NUL bytes, so it is not a CSV text file"])
            records = _csv_records(data.decode("utf-8").removeprefix("\ufeff"))
        else:
            try:
                doc = read_yaml_text(data, src, "fleet")    # not UTF-8, duplicate keys, alias bombs
            except ScenarioError as exc:
                raise FleetFileError(src, [p.removeprefix("<file>: ") for p in exc.problems]) from None
            if not isinstance(doc, dict) or not isinstance(doc.get("missions"), list):
                raise FleetFileError(src, ["the YAML needs a top-level list 'missions: [...]'"])
            records = doc["missions"]
    except (csv.Error, UnicodeDecodeError) as exc:
        raise FleetFileError(src, [f"cannot be read: {exc}".replace("\n", " ")]) from None
    if not records:
        raise FleetFileError(src, ["no mission in the file"])
    if len(records) > MAX_FLEET_MISSIONS:
        raise FleetFileError(src, [f"{len(records):,} missions: one fleet run takes at most {MAX_FLEET_MISSIONS:,}; "
                                   "split the file into runs that add to one airspace (--airspace FILE)"])
    return _fleet_tasks(src, records, sc, levels)


def _fleet_tasks(src: str, records: list, sc: Scenario, levels: Sequence[float]) -> list[FleetTask]:
    """The :class:`FleetTask` s of a fleet file's ``records`` (see :func:`load_fleet`)."""
    from skyroute.stages.vehicle import load_vehicle

    problems: list[str] = []
    missions: list[tuple[int, FleetMission]] = []
    for i, rec in enumerate(records):
        name = rec.get("id", f"#{i + 1}") if isinstance(rec, dict) else f"#{i + 1}"
        name = _shown(name) if isinstance(name, str) and len(name) > 40 else name
        if not isinstance(rec, dict):
            problems.append(f"mission #{i + 1}: expected a mapping of mission fields (id, start, goal, ...), got "
                            f"{type(rec).__name__}")
            continue
        try:
            missions.append((i, FleetMission.model_validate(rec)))
        except ValidationError as exc:
            for e in exc.errors():
                loc = ".".join(str(x) for x in e["loc"])
                problems.append(f"mission {name}: {loc + ': ' if loc else ''}{e['msg']}")
    seen: dict[str, int] = {}
    g = sc.grid
    xmin, ymin, xmax, ymax = g.bounds
    res = float(sc.aoi.resolution_m)
    cmin, cmax = sc.constraints.min_altitude_agl_m, sc.constraints.max_altitude_agl_m
    t0 = sc.mission.start_time_utc
    tasks = []
    for i, m in missions:
        if m.id in seen:
            problems.append(f"mission {m.id}: id already used by mission #{seen[m.id] + 1}")
        seen.setdefault(m.id, i)
        xy = {}
        for which in ("start", "goal"):
            pt = getattr(m, which)
            x, y = sc.point_xy(pt)
            if not (xmin <= x <= xmax and ymin <= y <= ymax):
                problems.append(f"mission {m.id}: {which} ({x:.1f}, {y:.1f}) is outside the scenario's map "
                                f"[{xmin:.1f}, {xmax:.1f}] x [{ymin:.1f}, {ymax:.1f}]")
            if not cmin <= pt.alt_agl_m <= cmax:
                problems.append(f"mission {m.id}: {which} altitude {pt.alt_agl_m:g} m AGL is outside the scenario's "
                                f"constraints.min_altitude_agl_m {cmin:g} .. max_altitude_agl_m {cmax:g}")
            xy[which] = (float(x), float(y))
        gap = math.hypot(xy["goal"][0] - xy["start"][0], xy["goal"][1] - xy["start"][1])
        if not gap >= res:        # (nan: reported as outside the map)
            if math.isfinite(gap):
                problems.append(f"mission {m.id}: start and goal are {gap:.2f} m apart, less than one cell "
                                f"(aoi.resolution_m {res:g} m): give a goal elsewhere")
        dep = _departure_s(m.departure, t0)
        if not math.isfinite(dep) or dep < 0:
            problems.append(f"mission {m.id}: departure {m.departure} is before the scenario start {t0.isoformat()}")
        veh = m.vehicle or sc.vehicle
        try:
            load_vehicle(veh)
        except Exception as exc:   # noqa: BLE001 - the loader's own message says what is known
            problems.append(f"mission {m.id}: vehicle: {exc}")
        else:
            try:
                check_fleet_vehicle(veh)
            except InputError as exc:
                problems.append(f"mission {m.id}: vehicle: {exc}")
        if m.dop_level is not None and levels and not any(abs(m.dop_level - d) < 1e-9 for d in levels):
            problems.append(f"mission {m.id}: dop_level {m.dop_level:g} is not one of the scenario's levels "
                            f"{', '.join(f'{d:g}' for d in levels)}")
        tasks.append(FleetTask(i, m.id, m.operator, xy["start"], m.start.alt_agl_m, xy["goal"], m.goal.alt_agl_m,
                               dep, m.priority, veh, m.dop_level))
    if problems:
        raise FleetFileError(src, problems)
    return tasks


def check_fleet_vehicle(vehicle) -> None:
    """InputError when the fleet's planner (:data:`FLEET_PLANNER`, rotorcraft) cannot fly
    ``vehicle`` (a fixed-wing aircraft), before any map is built."""
    from skyroute.stages.planning.kinds import check_planner_vehicle

    try:
        check_planner_vehicle(FLEET_PLANNER, vehicle)
    except InputError:
        raise InputError(f"{vehicle!r} is a fixed-wing vehicle and skyroute fleet plans every mission with the "
                         f"rotorcraft planner {FLEET_PLANNER!r}: give a rotorcraft vehicle, or plan the fixed-wing "
                         "mission alone with `skyroute plan`") from None


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

    import xarray as xr
    from scipy import ndimage

    # the maps may be lazy (a city's zarr stores, 1e8 cells): whole-grid work is one boolean mask,
    # values are read at the candidate sites only
    floor_da, ceil_da = clear["min_altitude_m"], clear["max_altitude_m"]
    nofly_da = clear["nofly"].astype(bool) if "nofly" in clear else None
    # cells where the vehicle may be at some altitude, and their 8-connected regions: a pair of
    # sites in two regions has no path at all
    free = np.isfinite(floor_da) & (floor_da <= ceil_da)
    region, _ = ndimage.label(np.asarray((free if nofly_da is None else free & ~nofly_da).values), np.ones((3, 3), bool))

    def at(da, r, c) -> np.ndarray:
        return np.asarray(da.isel(y=xr.DataArray(r, dims="site"), x=xr.DataArray(c, dims="site")).values)

    def usable_pairs(sx, sy):
        r, c = g.cell_of(sx, sy)
        top = at(surf["terrain"], r, c) + alt     # the mission's start / goal altitude
        fl, ce = at(floor_da, r, c).astype(float), at(ceil_da, r, c).astype(float)
        nf = np.zeros(r.shape, bool) if nofly_da is None else at(nofly_da, r, c)
        ok = np.isfinite(fl) & (fl <= top) & (top <= ce) & ~nf
        idx = np.flatnonzero(ok)
        return idx, _Pairs(sx[idx], sy[idx], region[r[idx], c[idx]], min_km * 1e3, max_km * 1e3)

    idx, pairs = usable_pairs(sx, sy)
    if pairs.size == 0:
        from skyroute.stages.landing import OPEN_GROUND_SPACING_M, open_ground_sites

        nofly = np.zeros(g.shape, bool) if nofly_da is None else np.asarray(nofly_da.values, bool)
        ox, oy, level = open_ground_sites(
            terrain=np.asarray(surf["terrain"].values, float), surface=np.asarray(surf["surface"].values, float),
            obstacle_floor=np.asarray(clear["obstacle_floor_m"].values, float),
            risk_level=np.asarray(env["risk_level"].values), nofly=nofly, grid=g,
            radius_m=float(clear.attrs.get("radius_m", 0.0)))
        idx, pairs = usable_pairs(ox, oy)
        if pairs.size == 0:
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
    pick = rng.integers(0, pairs.size, n)
    dep = np.sort(rng.uniform(0.0, window_s, n))
    ops = rng.integers(1, operators + 1, n)
    pri = (rng.random(n) < priority_share).astype(int)
    out = []
    for k in range(n):
        i, j = pairs[int(pick[k])]
        a, b = idx[i], idx[j]
        out.append(FleetTask(k, f"m{k + 1:04d}", f"op-{ops[k]}", (float(sx[a]), float(sy[a])), alt,
                             (float(sx[b]), float(sy[b])), alt, round(float(dep[k]), 1), int(pri[k]), sc.vehicle,
                             None))
    return out


class _Pairs:
    """The ordered pairs (i, j) of sites ``lo_m``-``hi_m`` [m] apart in one region, in row-major
    order (that of ``np.nonzero`` on the (n, n) matrix), without the matrix: a city's tens of
    thousands of sites would need GBs.  Rows are evaluated in blocks of :attr:`BLOCK`."""

    BLOCK = 256

    def __init__(self, x: np.ndarray, y: np.ndarray, label: np.ndarray, lo_m: float, hi_m: float):
        self.x, self.y, self.label, self.lo_m, self.hi_m = x, y, label, lo_m, hi_m
        n = x.size
        counts = [self._rows(i, min(i + self.BLOCK, n)).sum(axis=1) for i in range(0, n, self.BLOCK)]
        self.first = np.concatenate([[0], np.cumsum(np.concatenate(counts) if counts else [])]).astype(np.int64)
        self.size = int(self.first[-1])

    def _rows(self, i0: int, i1: int) -> np.ndarray:
        d = np.hypot(self.x[i0:i1, None] - self.x[None, :], self.y[i0:i1, None] - self.y[None, :])
        return (d >= self.lo_m) & (d <= self.hi_m) & (self.label[i0:i1, None] == self.label[None, :])

    def __getitem__(self, k: int) -> tuple[int, int]:
        """The k-th pair (i, j), 0 <= k < size."""
        i = int(np.searchsorted(self.first, k, side="right")) - 1
        return i, int(np.flatnonzero(self._rows(i, i + 1)[0])[k - self.first[i]])


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
