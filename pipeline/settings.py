"""Scenario catalogs: YAML files validated into frozen, typed settings.

A scenario names an area of interest, its data sources, a mission, a vehicle profile,
constraints and planner settings.  :func:`load_scenario` reads a catalog entry (by name or
path), resolves data paths relative to the YAML file and validates everything at once:
a :class:`~skyroute.pipeline.errors.ScenarioError` lists *every* problem, each prefixed by
its YAML path (``mission.start: altitude 900 m is above constraints.max_altitude_agl_m 150``).
"""

from __future__ import annotations

import datetime as dt
import math
import os
import re
from collections.abc import Sequence
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, TypeAdapter, ValidationError, field_validator, model_validator

from skyroute.pipeline.errors import ScenarioError, UnknownNameError
from skyroute.pipeline.model import FrozenModel
from skyroute.stages.yaml_io import read_yaml_file

PositiveFloat = Annotated[float, Field(gt=0)]
NonNegFloat = Annotated[float, Field(ge=0)]
Bounds = tuple[float, float, float, float]

DEFAULT_SCENARIO = "helsinki-medical"


_NAME_OK = re.compile(r"^[^\x00-\x1f\x7f/\\:*?\"<>|]+$")


def _is_file(p: str | Path) -> bool:
    """``Path(p).is_file()`` that is False, not an exception, for a name too long or with a NUL."""
    try:
        return Path(p).is_file()
    except (OSError, ValueError):
        return False


def unsafe_name(v: str) -> str | None:
    """Why ``v`` is not a safe single path component (a folder name under skyroute-out/), or None."""
    if not v or not v.strip():
        return "is empty"
    if v != v.strip():
        return "has leading or trailing spaces"
    if not _NAME_OK.match(v):
        return "is not a single folder name: it holds a path separator or a character not allowed in file names (/ \\ : * ? \" < > | or a control character)"
    if v in (".", "..") or v.startswith((".", "-")):
        return "starts with '.' or '-'"
    if len(v) > 100:
        return f"is {len(v)} characters long (at most 100)"
    return None


# --------------------------------------------------------------------------- sections
class AoiSettings(FrozenModel):
    """Area of interest: ``bounds_lonlat`` [deg] (west, south, east, north) or ``bounds`` [m]
    in ``crs``; ``crs`` defaults to the UTM zone of the AOI centre."""

    crs: str | None = None
    bounds_lonlat: Bounds | None = None
    bounds: Bounds | None = None
    resolution_m: PositiveFloat = 2.0
    chunk_cells: Annotated[int, Field(ge=64)] = 1024

    @model_validator(mode="after")
    def _one_bounds(self) -> AoiSettings:
        if (self.bounds_lonlat is None) == (self.bounds is None):
            raise ValueError("give exactly one of bounds_lonlat [deg] or bounds [m] (with crs)")
        if self.bounds is not None and self.crs is None:
            raise ValueError("bounds [m] need a crs (e.g. 'EPSG:28992')")
        b = self.bounds_lonlat or self.bounds
        assert b is not None
        if not (b[0] < b[2] and b[1] < b[3]):
            raise ValueError(f"bounds {list(b)} must be (xmin, ymin, xmax, ymax) with xmin < xmax and ymin < ymax")
        if self.bounds_lonlat is not None:
            w, s, e, n = self.bounds_lonlat
            if not (-180 <= w <= 180 and -180 <= e <= 180 and -90 <= s <= 90 and -90 <= n <= 90):
                raise ValueError("bounds_lonlat must be longitudes in [-180, 180] and latitudes in [-90, 90]")
        return self


class BuildingsSource(FrozenModel):
    """Buildings: an OSM extract or a CityJSON file (LoD1/LoD2)."""

    path: Path
    format: Literal["osm", "cityjson"]
    storey_height_m: PositiveFloat = 3.0


class TerrainSource(FrozenModel):
    """A GeoTIFF digital elevation model and the vertical datum of its heights."""

    path: Path
    vertical_datum: str = "EGM96 geoid"


class SurfaceSource(FrozenModel):
    """A DSM (lidar or rasterised): a GeoTIFF, a VRT or a list of tiles, read by window; its
    vertical datum (required); the NoData policy (``fill-max``: each hole inside the extent takes
    the highest height on its rim); the ground filter window [m] and building threshold [m] used
    when no DEM (``data.terrain``) is given."""

    path: Path | tuple[Path, ...]
    vertical_datum: str
    nodata: Literal["fill-max", "fill-nearest", "error"] = "fill-max"
    ground_window_m: PositiveFloat = 60.0
    building_threshold_m: PositiveFloat = 2.5

    @field_validator("path")
    @classmethod
    def _some(cls, v):
        if isinstance(v, tuple) and not v:
            raise ValueError("give a GeoTIFF, a VRT or a non-empty list of tiles")
        return v

    @property
    def paths(self) -> tuple[Path, ...]:
        return self.path if isinstance(self.path, tuple) else (self.path,)


class UniformWind(FrozenModel):
    """Vertically constant wind: ``speed_mps`` [m/s], ``direction_deg`` [deg, meteorological:
    where it blows FROM, clockwise from north], ``elevation_deg`` [deg]."""

    speed_mps: NonNegFloat
    direction_deg: float
    elevation_deg: float = 0.0


class GriddedWind(FrozenModel):
    """Gridded wind from CF NetCDF/zarr (u, v [, w] on pressure or height levels)."""

    path: Path
    time_utc: dt.datetime | None = None
    profile: Literal["levels", "power", "constant"] = "levels"


SAT_ID = re.compile(r"^[GERCJ]\d{2}$")


def _check_sat_ids(ids: Sequence[str]) -> tuple[str, ...]:
    bad = [s for s in ids if not SAT_ID.match(str(s))]
    if bad:
        raise ValueError(f"satellite id(s) {', '.join(repr(b) for b in bad)} not understood; give them as "
                         "`skyroute sky` prints them: a system letter G, E, R, C or J and two digits (G05, E11)")
    return tuple(dict.fromkeys(ids))


Vertex = tuple[float, float]


def _check_polygon(v: tuple[Vertex, ...], units: str) -> tuple[Vertex, ...]:
    """A simple polygon: >= 3 distinct vertices, not self-intersecting (shapely's validity)."""
    import shapely
    from shapely.validation import explain_validity

    pts = list(v)
    if len(pts) > 1 and pts[0] == pts[-1]:
        pts = pts[:-1]  # a closed ring given with its first vertex repeated
    if len(pts) < 3:
        raise ValueError(f"a polygon needs at least 3 vertices [{units}], got {len(pts)}")
    if not all(math.isfinite(c) for p in pts for c in p):
        raise ValueError("polygon vertices must be finite numbers")
    poly = shapely.Polygon(pts)
    if not poly.is_valid:
        raise ValueError(f"the polygon is not valid ({explain_validity(poly)}): it must not cross itself "
                         "and its vertices must go around it in order")
    if poly.area <= 0:
        raise ValueError("the polygon has no area (its vertices are on one line)")
    return tuple(pts)


class Obstacle(FrozenModel):
    """A static obstacle burnt into the surface model (e.g. a crane): ``polygon`` in map x/y [m]
    and its height above the highest ground under it ``height_agl_m`` [m]."""

    polygon: tuple[Vertex, ...]
    height_agl_m: PositiveFloat

    @field_validator("polygon")
    @classmethod
    def _poly(cls, v: tuple[Vertex, ...]) -> tuple[Vertex, ...]:
        return _check_polygon(v, "x_m, y_m")


class GroundReference(FrozenModel):
    """Where the surface model's 0 m lies, for absolute heights (operational intents in WGS 84
    ellipsoidal metres, KML, QGroundControl home altitude): surface heights + ``height_m`` [m]
    are heights in ``vertical_datum`` ('EGM96 geoid', 'EGM2008 geoid' or 'WGS 84 ellipsoid').
    Required when the ground is flat local ground (OSM-only cities: the height of the ground
    there) or in a datum skyroute cannot convert (e.g. NAP: the EGM96 height of NAP 0 m)."""

    height_m: float
    vertical_datum: str

    @field_validator("vertical_datum")
    @classmethod
    def _known(cls, v: str) -> str:
        from skyroute.stages.geoid import datum_kind

        if datum_kind(v) not in ("EGM96", "EGM2008", "ellipsoid"):
            raise ValueError(f"vertical datum {v!r} not understood: use 'EGM96 geoid', 'EGM2008 geoid' or "
                             "'WGS 84 ellipsoid'")
        return v

    @field_validator("height_m")
    @classmethod
    def _finite(cls, v: float) -> float:
        if not math.isfinite(v):
            raise ValueError("height_m must be a finite number [m]")
        return v


class DataSources(FrozenModel):
    buildings: BuildingsSource | None = None
    terrain: TerrainSource | None = None
    surface: SurfaceSource | None = None
    landuse: Path | None = None
    landing_sites: Path | None = None
    osm_landing_sites: bool = True
    risk_tags: Path | None = None
    risk_default_level: Annotated[int, Field(ge=1, le=6)] | None = None
    uniform_wind: UniformWind | None = None
    wind: GriddedWind | None = None
    almanacs: tuple[Path, ...] = ()
    obstacles: tuple[Obstacle, ...] = ()
    ground: GroundReference | None = None

    @model_validator(mode="after")
    def _one_wind(self) -> DataSources:
        if self.uniform_wind is not None and self.wind is not None:
            raise ValueError("give either uniform_wind (one constant wind) or wind (a gridded file), not both: "
                             "remove one of them")
        return self


class MissionPoint(FrozenModel):
    """A mission point in lon/lat [deg] or map x/y [m], with its altitude above ground [m]."""

    lon: float | None = None
    lat: float | None = None
    x: float | None = None
    y: float | None = None
    alt_agl_m: NonNegFloat
    name: str | None = None

    @model_validator(mode="after")
    def _xy_or_lonlat(self) -> MissionPoint:
        ll = self.lon is not None and self.lat is not None
        xy = self.x is not None and self.y is not None
        if ll == xy:
            raise ValueError("give either lon and lat [deg] or x and y [m]")
        if ll and not -90.0 <= self.lat <= 90.0:
            raise ValueError(f"latitude {self.lat:g} out of [-90, 90] deg")
        if ll and not -180.0 <= self.lon <= 180.0:
            raise ValueError(f"longitude {self.lon:g} out of [-180, 180] deg")
        return self


class Mission(FrozenModel):
    start: MissionPoint
    goal: MissionPoint
    start_time_utc: dt.datetime

    @field_validator("start_time_utc")
    @classmethod
    def _utc(cls, v: dt.datetime) -> dt.datetime:
        if v.tzinfo is None:
            return v.replace(tzinfo=dt.UTC)
        return v.astimezone(dt.UTC)


class Constraints(FrozenModel):
    """Airspace and operating constraints.  ``max_altitude_agl_m`` may not exceed the
    vehicle's ``max_altitude_m`` (a scenario that asks more is an error listing both); when it
    is not given, the vehicle's maximum applies (120 m at most).  ``battery_reserve_pct`` [%]:
    energy kept in the battery, the plan may use ``battery * (1 - reserve / 100)``.
    ``clearance``: ``fixed`` keeps the vehicle sphere r_p from the obstacles; ``sboa`` (seed 003
    safety bubble) plans each coverage level D_j with ``r_j = max(r_p, sboa_k sigma(D_j) +
    navsim.surface_uncertainty_m)``, sigma(D_j) the navigation error bound where PDOP < D_j
    (needs dop_kind PDOP or GDOP), and re-checks each sample with its predicted sigma_p(t)."""

    min_altitude_agl_m: NonNegFloat = 0.0
    max_altitude_agl_m: PositiveFloat = 120.0
    nofly_zones: Path | None = None
    level5_nofly: bool = False
    battery_reserve_pct: Annotated[float, Field(ge=0, lt=100)] = 0.0
    clearance: Literal["fixed", "sboa"] = "fixed"
    sboa_k: PositiveFloat = 3.0

    @model_validator(mode="after")
    def _order(self) -> Constraints:
        if self.min_altitude_agl_m >= self.max_altitude_agl_m:
            raise ValueError(f"min_altitude_agl_m {self.min_altitude_agl_m} must be below max_altitude_agl_m {self.max_altitude_agl_m}")
        return self


class GnssSettings(FrozenModel):
    """GNSS coverage: elevation mask [deg], DOP kind and thresholds D_j, time window [min]
    sampled every ``step_min`` from the mission start (default every whole minute: the
    coverage floor holds at each epoch, not in between)."""

    elevation_mask_deg: Annotated[float, Field(ge=0, le=60)] = 5.0
    dop_kind: Literal["GDOP", "PDOP", "HDOP", "VDOP"] = "PDOP"
    dop_thresholds: tuple[float, ...] = (2.0, 3.0, 4.0)
    window_min: NonNegFloat = 20.0
    step_min: PositiveFloat = 1.0
    uere_m: PositiveFloat = 3.0  # pseudorange error (1 sigma) of the navigation filter [m]
    # satellites out of service (ids as `skyroute sky` prints them: G05, E11): dropped from the
    # satellites stage, so every DOP and coverage map is computed without them
    exclude_satellites: tuple[str, ...] = ()

    @field_validator("exclude_satellites")
    @classmethod
    def _sat_ids(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        return _check_sat_ids(v)

    @field_validator("dop_thresholds")
    @classmethod
    def _thr(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not v:
            raise ValueError("give at least one DOP threshold, e.g. [2, 3, 4]")
        if any(t <= 1.0 for t in v):
            raise ValueError(f"DOP thresholds {list(v)} must all be > 1 (DOP is never below 1)")
        return tuple(sorted(v))


class Intruder(FrozenModel):
    """Another drone's 4D trajectory: waypoints ``[t_s, x_m, y_m, z_m]`` (time since mission
    start [s], map coordinates [m], altitude above ground [m]) and its radius [m]."""

    id: str
    radius_m: PositiveFloat = 2.0
    waypoints: tuple[tuple[float, float, float, float], ...]


class TrafficSettings(FrozenModel):
    intruders: tuple[Intruder, ...] = ()
    n_slices: Annotated[int, Field(ge=1)] = 20
    margin_m: NonNegFloat = 5.0
    time_margin_s: NonNegFloat = 5.0

    @field_validator("intruders")
    @classmethod
    def _unique_ids(cls, v: tuple[Intruder, ...]) -> tuple[Intruder, ...]:
        seen: set[str] = set()
        dup = [i.id for i in v if i.id in seen or seen.add(i.id)]
        if dup:
            raise ValueError(f"intruder id(s) {', '.join(map(repr, dict.fromkeys(dup)))} given more than once; "
                             "give every intruder its own id")
        return v


from skyroute.stages.planning.registry import PLANNERS  # noqa: E402  (the one list of planners)


class PlannerSettings(FrozenModel):
    """STEP I planner (``astar``: deterministic 3-D lattice A* + refinement, the default; or
    ``bitstar``: OMPL BIT*, reproducible with its seed and an iteration budget derived from
    ``time_budget_s``; for fixed-wing vehicles ``eeastar``, ``astar-fw``, ``energy-optimal`` or
    ``bitstar-dubins`` (BIT* on OMPL's Dubins-airplane space, shortest curve, iterations from
    ``time_budget_s``),
    seed 002, :mod:`skyroute.stages.planning.fixedwing`), eq. 11 weights (w_l, w_r, w_d, w_e) >= 0 and
    not all zero, BIT* time per coverage level [s], random seed, energy re-plan tries N_t."""

    name: str = "astar"
    weights: tuple[NonNegFloat, NonNegFloat, NonNegFloat, NonNegFloat] = (1.0, 1.0, 1.0, 1.0)
    time_budget_s: PositiveFloat = 5.0
    seed: Annotated[int, Field(ge=0, le=2**32 - 1)] = 0
    max_tries: Annotated[int, Field(ge=1)] = 3
    # A* lattice step [cells] (8: measured best on 2 m city grids; a coarse mountain grid whose
    # cells span tens of metres of relief may need a finer lattice to follow a canyon)
    step_cells: Annotated[int, Field(ge=1, le=64)] = 8

    @field_validator("name")
    @classmethod
    def _known(cls, v: str) -> str:
        if v not in PLANNERS:
            raise ValueError(f"unknown planner {v!r}; known planners: {', '.join(PLANNERS)}")
        return v

    @field_validator("weights")
    @classmethod
    def _not_all_zero(cls, v):
        if not any(w > 0 for w in v):
            raise ValueError("at least one weight must be > 0 (all zero makes every path equally good)")
        return v


def parse_planner(raw: dict) -> PlannerSettings:
    """Validate planner settings (CLI overrides) with the same messages as the catalog."""
    try:
        return PlannerSettings.model_validate(raw)
    except ValidationError as exc:
        raise ScenarioError("planner settings", [f"planner.{p}" for p in _problems_from(exc)]) from None


# --------------------------------------------------------------------------- tactical replay
class NavsimSettings(FrozenModel):
    """Navigation Monte Carlo (``skyroute navsim``, seed 003 section III): ``runs`` and
    ``seed``; the trajectory is sampled at ``rate_hz`` [Hz] (GNSS updates at ``gnss_rate_hz``);
    pseudorange error model of the satellites hidden by the surface (NLOS): received by
    reflection with probability ``nlos_reception_prob``, with a positive bias per pass of mean
    ``nlos_bias_mean_m`` [m] (``exponential`` or ``half-normal``) and white noise
    ``nlos_noise_factor`` x UERE (``gnss.uere_m``); the weak filter's ``mu_nlos_weak``; the
    proposed filter scales R by the local DOP (``scale_r_by_dop``); the surface model's own
    uncertainty ``surface_uncertainty_m`` [m] is added to the safety bubble
    r_phi = k sigma + surface_uncertainty_m (reported separately).  The digital morphing
    map (the coverage floor per epoch under the flight) is computed every ``morphing_step_s``
    [s] over the flight's box widened by ``morphing_margin_m`` [m] (0: not computed).  The
    protection level's budgets per epoch: integrity ``pl_p_hmi`` and false alert ``pl_p_fa``
    (each split equally between horizontal and vertical), satellite fault prior ``pl_p_sat``
    (:class:`skyroute.stages.integrity.IntegrityBudget` explains the defaults)."""

    runs: Annotated[int, Field(ge=1, le=100000)] = 50
    seed: Annotated[int, Field(ge=0, le=2**32 - 1)] = 0
    rate_hz: PositiveFloat = 10.0
    gnss_rate_hz: PositiveFloat = 1.0
    nlos_reception_prob: Annotated[float, Field(ge=0, le=1)] = 0.7
    nlos_bias_mean_m: NonNegFloat = 15.0
    nlos_bias_distribution: Literal["exponential", "half-normal"] = "exponential"
    nlos_noise_factor: PositiveFloat = 2.0
    mu_nlos_weak: PositiveFloat = 10.0
    scale_r_by_dop: bool = True
    surface_uncertainty_m: NonNegFloat = 1.0
    morphing_step_s: NonNegFloat = 10.0
    morphing_margin_m: NonNegFloat = 100.0
    pl_p_hmi: Annotated[float, Field(gt=0, lt=1)] = 1e-7
    pl_p_fa: Annotated[float, Field(gt=0, lt=1)] = 4e-6
    pl_p_sat: Annotated[float, Field(ge=0, lt=1)] = 1e-5


class TacticalSettings(FrozenModel):
    """Tactical replay (``skyroute fly``): replanning timeout ``t_rep_s`` [s] (a replan takes
    effect that long after its event), simulation tick ``tick_s`` [s], random ``seed``, 1-sigma
    position noise of reported intruder tracks ``intruder_noise_m`` [m], delay between an intruder
    event and when the ownship knows it ``report_latency_s`` [s], iteration budgets of the level-2
    and level-3 RRTs, the level-1 velocity scale factors tried in order, and the time margin
    ``time_margin_s`` [s] of the replanning occupancy maps (the tracks are fresh during the
    flight; the strategic maps use ``traffic.time_margin_s``).  ``method``: how an intruder
    conflict is resolved, ``levels`` (levels 1-3, seed 001) or ``octant`` (seed 004: dense-traffic
    zones predicted ``zone_period_s`` [s] ahead and the octant manoeuvre once the intruder is
    within ``periphery_m`` [m]; other conflicts still go through levels 1-3) -- rotorcraft; or
    ``local`` (fixed-wing vehicles, their default: seed 002's local planner,
    :mod:`skyroute.stages.tactical.fw_local`: unknown obstacles sensed within
    ``obstacle_range_m`` [m] are climbed over, another UAV on a collision course within
    ``uav_range_m`` [m] makes the aircraft turn right through a waypoint ``avoid_offset_m`` [m]
    to the right of its path; separation ``r_i + r_j + traffic.margin_m``)."""

    t_rep_s: PositiveFloat = 5.0
    tick_s: PositiveFloat = 0.1
    seed: Annotated[int, Field(ge=0, le=2**32 - 1)] = 0
    intruder_noise_m: NonNegFloat = 0.0
    report_latency_s: NonNegFloat = 0.0
    level2_iterations: Annotated[int, Field(ge=1)] = 3000
    level3_iterations: Annotated[int, Field(ge=1)] = 5000
    time_scaling_factors: tuple[Annotated[float, Field(gt=0, lt=1)], ...] = (0.8, 0.65, 0.5, 0.35, 0.25)
    time_margin_s: NonNegFloat = 1.0
    method: Literal["levels", "octant", "local"] = "levels"
    periphery_m: PositiveFloat = 60.0
    zone_period_s: PositiveFloat = 10.0
    obstacle_range_m: PositiveFloat = 500.0
    uav_range_m: PositiveFloat = 400.0
    avoid_offset_m: PositiveFloat = 150.0

    @field_validator("time_scaling_factors")
    @classmethod
    def _some_factor(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not v:
            raise ValueError("give at least one velocity scale factor in (0, 1), e.g. [0.8, 0.65, 0.5]")
        return v

    @model_validator(mode="after")
    def _tick(self) -> TacticalSettings:
        if self.tick_s > self.t_rep_s:
            raise ValueError(f"tick_s {self.tick_s:g} s must not exceed t_rep_s {self.t_rep_s:g} s")
        return self


EVENT_KINDS = ("intruder", "intruder_update", "wind", "gnss", "nofly", "obstacle")
Waypoint = tuple[float, float, float, float]


class _EventBase(FrozenModel):
    t_s: NonNegFloat  # time of the event [s after the mission start]
    id: str | None = None

    @property
    def label(self) -> str:
        """A short name for tables and logs: ``intruder hawk at 10 s``, ``wind at 30 s``."""
        who = f" {self.id}" if self.id else ""
        return f"{getattr(self, 'kind', 'event')}{who} at {self.t_s:g} s"


class _TrackForms(_EventBase):
    """An intruder track: ``waypoints`` [[t_s, x_m, y_m, alt_agl_m], ...] (map x/y [m], AGL [m],
    times strictly increasing) or ``position`` [x_m, y_m, alt_agl_m] + ``velocity_mps`` [vx, vy, vz]
    [m/s] flown for ``duration_s`` [s] from the event time."""

    via: Literal["uspace", "v2v"] = "uspace"
    waypoints: tuple[Waypoint, ...] | None = None
    position: tuple[float, float, float] | None = None
    velocity_mps: tuple[float, float, float] | None = None
    duration_s: PositiveFloat = 300.0

    @field_validator("waypoints")
    @classmethod
    def _waypoints(cls, v: tuple[Waypoint, ...] | None) -> tuple[Waypoint, ...] | None:
        if v is None:
            return v
        if len(v) < 2:
            raise ValueError(f"a track needs at least 2 waypoints [[t_s, x_m, y_m, alt_agl_m], ...], got {len(v)}")
        for k in range(1, len(v)):
            if not v[k][0] > v[k - 1][0]:
                raise ValueError(f"times must increase strictly (waypoint {k} at {v[k][0]:g} s is not after "
                                 f"waypoint {k - 1} at {v[k - 1][0]:g} s)")
        for k, w in enumerate(v):
            if w[3] < 0:
                raise ValueError(f"waypoint {k} at {w[0]:g} s: altitude {w[3]:g} m AGL is below the ground")
        return v

    @model_validator(mode="after")
    def _one_form(self):
        has_wp, has_pos = self.waypoints is not None, self.position is not None
        if has_wp == has_pos:
            raise ValueError("give exactly one track form: waypoints [[t_s, x_m, y_m, alt_agl_m], ...] or "
                             "position [x_m, y_m, alt_agl_m] with velocity_mps [vx, vy, vz]")
        if has_pos and self.velocity_mps is None:
            raise ValueError("position [x_m, y_m, alt_agl_m] needs velocity_mps [vx, vy, vz] [m/s]")
        if has_wp and ({"velocity_mps", "duration_s"} & self.model_fields_set):
            raise ValueError("velocity_mps and duration_s go with position, not with waypoints")
        if has_pos:
            assert self.position is not None
            if self.position[2] < 0:
                raise ValueError(f"position altitude {self.position[2]:g} m AGL is below the ground")
            end = self.track()[-1]
            if end[3] < 0:
                raise ValueError(f"the track goes below the ground (altitude {end[3]:g} m AGL at {end[0]:g} s); "
                                 "shorten duration_s or change velocity_mps")
        return self

    def track(self) -> np.ndarray:
        """The track as ``(k, 4)`` rows [t_s, x_m, y_m, alt_agl_m] (position + velocity: two
        waypoints, at the event time and ``duration_s`` later)."""
        if self.waypoints is not None:
            return np.asarray(self.waypoints, dtype=np.float64)
        assert self.position is not None and self.velocity_mps is not None
        p, v = np.asarray(self.position, np.float64), np.asarray(self.velocity_mps, np.float64)
        return np.array([[self.t_s, *p], [self.t_s + self.duration_s, *(p + v * self.duration_s)]])


class IntruderEvent(_TrackForms):
    """A tactical intruder not known at planning time, known from ``t_s`` [s] on (via the
    U-space service or V2V): ``id``, ``radius_m`` [m] and its track (waypoints or position +
    velocity)."""

    kind: Literal["intruder"]
    id: str
    radius_m: PositiveFloat = 2.0


class IntruderUpdateEvent(_TrackForms):
    """A new track for an intruder known earlier (``traffic.intruders`` or an earlier
    ``intruder`` event), from ``t_s`` [s] on; ``radius_m`` [m] unchanged when not given."""

    kind: Literal["intruder_update"]
    id: str
    radius_m: PositiveFloat | None = None


class WindEvent(_EventBase):
    """A new wind from ``t_s`` [s] on: exactly one of ``uniform_wind`` or ``wind`` (gridded)."""

    kind: Literal["wind"]
    uniform_wind: UniformWind | None = None
    wind: GriddedWind | None = None

    @model_validator(mode="after")
    def _one(self) -> WindEvent:
        if (self.uniform_wind is None) == (self.wind is None):
            raise ValueError("give exactly one of uniform_wind {speed_mps, direction_deg} or wind {path, ...}")
        return self


class GnssEvent(_EventBase):
    """GNSS change from ``t_s`` [s] on: satellites ``out_of_service`` (ids as ``skyroute sky``
    prints them: G05, E11) and/or a new almanac set ``almanacs`` (paths relative to the YAML)."""

    kind: Literal["gnss"]
    out_of_service: tuple[str, ...] = ()
    almanacs: tuple[Path, ...] = ()

    @field_validator("out_of_service")
    @classmethod
    def _ids(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        return _check_sat_ids(v)

    @model_validator(mode="after")
    def _some(self) -> GnssEvent:
        if not self.out_of_service and not self.almanacs:
            raise ValueError("give out_of_service [G05, ...] and/or almanacs [file, ...]")
        return self


class _PolygonEvent(_EventBase):
    """A polygon as ``polygon_lonlat`` [[lon, lat], ...] [deg] or ``polygon`` [[x_m, y_m], ...]
    in the map CRS [m] (>= 3 vertices, not self-intersecting)."""

    polygon_lonlat: tuple[Vertex, ...] | None = None
    polygon: tuple[Vertex, ...] | None = None

    @field_validator("polygon_lonlat")
    @classmethod
    def _ll(cls, v: tuple[Vertex, ...] | None) -> tuple[Vertex, ...] | None:
        if v is None:
            return v
        for lon, lat in v:
            if not (-180 <= lon <= 180 and -90 <= lat <= 90):
                raise ValueError(f"vertex ({lon:g}, {lat:g}) is not [lon, lat] in [-180, 180] x [-90, 90] deg")
        return _check_polygon(v, "lon, lat")

    @field_validator("polygon")
    @classmethod
    def _xy(cls, v: tuple[Vertex, ...] | None) -> tuple[Vertex, ...] | None:
        return v if v is None else _check_polygon(v, "x_m, y_m")

    @model_validator(mode="after")
    def _one_polygon(self):
        if (self.polygon_lonlat is None) == (self.polygon is None):
            raise ValueError("give exactly one of polygon_lonlat [[lon, lat], ...] [deg] or polygon [[x_m, y_m], ...] [m]")
        return self

    def polygon_xy(self, sc: Scenario) -> np.ndarray:
        """The polygon's vertices ``(k, 2)`` in the map CRS of ``sc`` [m]."""
        if self.polygon is not None:
            return np.asarray(self.polygon, dtype=np.float64)
        ll = np.asarray(self.polygon_lonlat, dtype=np.float64)
        x, y = sc.grid.from_lonlat(ll[:, 0], ll[:, 1])
        return np.column_stack([x, y]).astype(np.float64)


class NoFlyEvent(_PolygonEvent):
    """A new no-fly zone (e.g. a police operation): polygon, altitude band ``min_agl_m`` ..
    ``max_agl_m`` [m AGL] and time window ``start_s`` (default: the event time) .. ``end_s``
    (default: open) [s after the mission start]."""

    kind: Literal["nofly"]
    min_agl_m: NonNegFloat = 0.0
    max_agl_m: float = math.inf
    start_s: NonNegFloat | None = None
    end_s: float = math.inf

    @model_validator(mode="before")
    @classmethod
    def _default_start(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("start_s") is None and "t_s" in data:
            data = {**data, "start_s": data["t_s"]}
        return data

    @model_validator(mode="after")
    def _bands(self) -> NoFlyEvent:
        if not self.max_agl_m > self.min_agl_m:
            raise ValueError(f"max_agl_m {self.max_agl_m:g} must be above min_agl_m {self.min_agl_m:g}")
        assert self.start_s is not None
        if self.start_s < self.t_s:
            raise ValueError(f"start_s {self.start_s:g} s is before the event time t_s {self.t_s:g} s "
                             "(a zone cannot be active before it is announced)")
        if not self.end_s > self.start_s:
            raise ValueError(f"end_s {self.end_s:g} s must be after start_s {self.start_s:g} s")
        return self


class ObstacleEvent(_PolygonEvent):
    """A new static obstacle (e.g. a crane): polygon and ``height_agl_m`` [m] above the
    highest ground under it, burnt into the surface model from ``t_s`` [s] on."""

    kind: Literal["obstacle"]
    height_agl_m: PositiveFloat


#: One scenario event, told apart by its ``kind``.
Event = Annotated[IntruderEvent | IntruderUpdateEvent | WindEvent | GnssEvent | NoFlyEvent | ObstacleEvent,
                  Field(discriminator="kind")]
MAP_EVENT_KINDS = ("wind", "gnss", "obstacle")


class Scenario(FrozenModel):
    """A validated scenario catalog entry."""

    name: str
    description: str = ""
    aoi: AoiSettings
    data: DataSources = DataSources()
    mission: Mission
    vehicle: str = "dji-m300-rtk"
    constraints: Constraints = Constraints()
    gnss: GnssSettings = GnssSettings()
    traffic: TrafficSettings = TrafficSettings()
    planner: PlannerSettings = PlannerSettings()
    tactical: TacticalSettings = TacticalSettings()
    navsim: NavsimSettings = NavsimSettings()
    events: tuple[Event, ...] = ()
    source_path: Path | None = Field(default=None, exclude=True)

    @field_validator("name")
    @classmethod
    def _safe_name(cls, v: str) -> str:
        why = unsafe_name(v)
        if why:
            raise ValueError(f"{v!r} {why} (the name is the output folder skyroute-out/NAME): use letters, digits, "
                             "'-', '_' and '.', e.g. my-city-delivery")
        return v

    @field_validator("events")
    @classmethod
    def _by_time(cls, v: tuple) -> tuple:
        return tuple(sorted(v, key=lambda e: e.t_s))  # stable: events at one time keep their order

    @cached_property
    def grid(self):
        """The scenario :class:`~skyroute.stages.grid.Grid` (CRS, bounds, resolution)."""
        from skyroute.stages.grid import Grid, resolve_crs, utm_crs_for

        a = self.aoi
        if a.bounds_lonlat is not None:
            w, s, e, n = a.bounds_lonlat
            crs = resolve_crs(a.crs) if a.crs else utm_crs_for((w + e) / 2, (s + n) / 2)
            from pyproj import Transformer

            xmin, ymin, xmax, ymax = Transformer.from_crs(4326, crs, always_xy=True).transform_bounds(w, s, e, n, densify_pts=21)
        else:
            assert a.bounds is not None and a.crs is not None
            crs = resolve_crs(a.crs)
            xmin, ymin, xmax, ymax = a.bounds
            # map bounds: the grid never extends past them (snapped inward to the resolution lattice)
            return Grid.from_bounds(crs, xmin, ymin, xmax, ymax, a.resolution_m, inward=True)
        return Grid.from_bounds(crs, xmin, ymin, xmax, ymax, a.resolution_m)

    def point_xy(self, p: MissionPoint) -> tuple[float, float]:
        """Map coordinates (x, y) [m] of a mission point."""
        if p.x is not None and p.y is not None:
            return (p.x, p.y)
        x, y = self.grid.from_lonlat(p.lon, p.lat)
        return (float(x), float(y))

    def mission_times_utc(self) -> list[dt.datetime]:
        """GNSS epochs: mission start, then every ``gnss.step_min`` up to ``gnss.window_min``."""
        g = self.gnss
        n = int(g.window_min // g.step_min) + 1
        return [self.mission.start_time_utc + dt.timedelta(minutes=g.step_min * k) for k in range(n)]


# --------------------------------------------------------------------------- loading
def catalog_dir() -> Path:
    """The folder of the installed scenario catalog."""
    return Path(str(resources.files("skyroute.catalogs")))


def scenario_paths() -> dict[str, Path]:
    """Known scenario names -> YAML files (built-in catalog plus ``$SKYROUTE_CATALOG`` folders)."""
    folders = [catalog_dir() / "scenarios"]
    extra = os.environ.get("SKYROUTE_CATALOG")
    if extra:
        folders += [Path(p) for p in extra.split(os.pathsep) if p]
    out: dict[str, Path] = {}
    for folder in folders:
        for f in sorted(folder.glob("*.yaml")):
            out.setdefault(f.stem, f)
    return out


def _resolve_paths(node: Any, base: Path, key: str = "") -> Any:
    """Make every relative path in a ``path`` / ``*_path`` / data field absolute w.r.t. ``base``."""
    path_keys = {"path", "landuse", "landing_sites", "nofly_zones", "risk_tags"}
    if isinstance(node, dict):
        return {k: _resolve_paths(v, base, k) for k, v in node.items()}
    if isinstance(node, list):
        if key == "almanacs":
            return [str((base / Path(os.path.expandvars(str(v)))).resolve()) if isinstance(v, str) else v for v in node]
        return [_resolve_paths(v, base, key) for v in node]
    if isinstance(node, str) and key in path_keys:
        return str((base / Path(os.path.expandvars(node))).resolve())
    return node


def _yaml_path(loc: Sequence[Any]) -> str:
    """``('events', 2, 'intruder', 'waypoints')`` -> ``events[2].waypoints`` (list indices in
    brackets; the tag pydantic adds for a tagged union member is not part of the YAML path)."""
    out = ""
    for k, p in enumerate(loc):
        s = str(p)
        if s.startswith("function-"):
            continue
        if isinstance(p, int):
            out += f"[{p}]"
        elif k > 0 and isinstance(loc[k - 1], int) and s in EVENT_KINDS:
            continue
        else:
            out += f".{s}" if out else s
    return out


def _problems_from(exc: ValidationError, prefix: Sequence[Any] = ()) -> list[str]:
    out = []
    kinds = ", ".join(EVENT_KINDS)
    for err in exc.errors():
        loc = _yaml_path([*prefix, *err["loc"]])
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "number_field":      # FrozenModel: true/false or .inf/.nan given for a number
            loc = _yaml_path([*prefix, *err["loc"], err["ctx"]["key"]])
            msg = err["ctx"]["why"]
        elif err["type"] == "extra_forbidden":
            msg = ("unknown key (check the spelling; valid keys: catalogs/README.md or "
                   "`python -m skyroute.pipeline.settings_reference`)")
        elif err["type"] == "missing":
            msg = "required key is missing"
        elif err["type"] == "union_tag_invalid":
            msg = f"unknown kind {err.get('ctx', {}).get('tag')!r}; kinds: {kinds}"
        elif err["type"] == "union_tag_not_found":
            msg = f"give the event's kind: {kinds}"
        out.append(f"{loc or '<root>'}: {msg}")
    return out


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
            if not _is_file(f):
                problems.append(f"{where}: data file not found: {f}")
    return problems


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
            if not _is_file(p):
                problems.append(f"{section}: data file not found: {p}")
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
    for name in ("start", "goal"):
        p = getattr(sc.mission, name)
        try:
            x, y = sc.point_xy(p)
        except Exception as exc:
            problems.append(f"mission.{name}: cannot place the point on the map: {exc}")
            continue
        if not grid.contains(x, y):
            xmin, ymin, xmax, ymax = grid.bounds
            problems.append(
                f"mission.{name}: point ({x:.1f}, {y:.1f}) m is outside the AOI "
                f"x {xmin:.0f}..{xmax:.0f}, y {ymin:.0f}..{ymax:.0f} ({grid.crs_wkt[:40]}); move it or enlarge aoi"
            )
        if p.alt_agl_m > cmax:
            problems.append(f"mission.{name}: altitude {p.alt_agl_m:g} m is above constraints.max_altitude_agl_m {cmax:g}")
        if p.alt_agl_m < cmin:
            problems.append(f"mission.{name}: altitude {p.alt_agl_m:g} m is below constraints.min_altitude_agl_m {cmin:g}")
    for k, o in enumerate(sc.data.obstacles):
        if _outside_aoi(grid, np.asarray(o.polygon)):
            problems.append(f"data.obstacles[{k}].polygon: the polygon lies outside the AOI; check the coordinates (map CRS metres)")
    return problems


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


def _sorted_labels(raw_events: Any, fmt: str = "events[{}]") -> list[str]:
    """YAML paths of the events in the order the scenario keeps them (by time, stable)."""
    if not isinstance(raw_events, list):
        return []
    order = sorted(range(len(raw_events)), key=lambda i: float(raw_events[i]["t_s"]))
    return [fmt.format(i) for i in order]


def parse_scenario(raw: Any, source: str = "<scenario>", base: Path | None = None) -> Scenario:
    """Validate a scenario mapping (already parsed YAML).  Raises ScenarioError with every problem."""
    if not isinstance(raw, dict):
        raise ScenarioError(source, ["<root>: a scenario must be a YAML mapping (key: value)"])
    if base is not None:
        raw = _resolve_paths(raw, base)
    try:
        sc = Scenario.model_validate(raw)
    except ValidationError as exc:
        raise ScenarioError(source, _problems_from(exc)) from None
    sc = _clamp_default_max_altitude(sc)
    problems = _semantic_problems(sc)
    if sc.events:
        problems += _event_problems(sc, _sorted_labels(raw.get("events")))
    if problems:
        raise ScenarioError(source, problems)
    if base is not None:
        sc = sc.model_copy(update={"source_path": Path(source)})
    return sc


def load_scenario(name_or_path: str | Path = DEFAULT_SCENARIO) -> Scenario:
    """Load and validate a scenario by catalog name (``helsinki-medical``) or YAML path."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or _is_file(p):
        if not _is_file(p):
            raise ScenarioError(str(p), [f"<file>: scenario file not found: {p}"])
    else:
        known = scenario_paths()
        if str(name_or_path) not in known:
            raise UnknownNameError("scenario", str(name_or_path), list(known))
        p = known[str(name_or_path)]
    raw = read_yaml_file(p, "scenario")
    return parse_scenario(raw, source=str(p), base=p.parent)


# --------------------------------------------------------------------------- events
_EVENTS = TypeAdapter(tuple[Event, ...])


def _read_yaml(p: Path) -> Any:
    return read_yaml_file(p, "events")


def _raw_events_of(path: str | Path) -> list:
    p = Path(path)
    if not _is_file(p):
        raise ScenarioError(str(p), [f"<file>: events file not found: {p}"])
    raw = _read_yaml(p)
    if isinstance(raw, dict) and set(raw) == {"events"}:
        raw = raw["events"]
    if not isinstance(raw, list):
        raise ScenarioError(str(p), ["<root>: an events file holds a list of events, or a mapping with one key "
                                     "`events:` holding that list (each event: t_s, kind, ...)"])
    return _resolve_paths({"events": raw}, p.parent)["events"]


def load_events_file(path: str | Path) -> tuple[Event, ...]:
    """Read and validate an events file: a YAML list of events, or a mapping whose only key
    ``events`` holds that list (the ``events:`` section of a scenario).  Relative paths
    (almanacs, gridded wind) are resolved against the file's folder.  Events stay in file order
    (:func:`with_events` sorts them by time).  Raises ScenarioError naming the file and each
    problem's YAML path (``events[2]: unknown kind 'fog'; ...``)."""
    raw = _raw_events_of(path)
    try:
        return _EVENTS.validate_python(raw)
    except ValidationError as exc:
        raise ScenarioError(str(path), _problems_from(exc, prefix=("events",))) from None


def with_events(sc: Scenario, events: Sequence[Event] | str | Path, source: str | None = None) -> Scenario:
    """``sc`` with ``events`` (a sequence of events, or an events file read with
    :func:`load_events_file`) appended and the whole list re-validated against the scenario
    (intruder ids, polygons in the AOI, data files) and sorted by time (stable).  Backs
    ``skyroute fly --events FILE``; errors name the file (or ``source``) and the event's place in it."""
    if isinstance(events, str | Path):
        source = source or str(events)
        events = load_events_file(events)
    source = source or "added events"
    new = list(events)
    try:
        new = list(_EVENTS.validate_python(new))  # events built by hand are checked too
    except ValidationError as exc:
        raise ScenarioError(source, _problems_from(exc, prefix=("events",))) from None
    tagged = [(f"scenario events[{i}]", False, e) for i, e in enumerate(sc.events)]
    tagged += [(f"events[{i}]", True, e) for i, e in enumerate(new)]
    tagged.sort(key=lambda t: t[2].t_s)
    out = sc.model_copy(update={"events": tuple(t[2] for t in tagged)})
    problems = _event_problems(out, [t[0] for t in tagged], [t[1] for t in tagged])
    if problems:
        raise ScenarioError(f"{source} (events added to scenario {sc.name!r})", problems)
    return out


def check_event_times(sc: Scenario, mission_end_s: float) -> list[str]:
    """Problems of events that come after the end of the mission (``mission_end_s`` [s after the
    start], known only once the plan is made): one line each, for the engine to raise."""
    out = []
    for k, e in enumerate(sc.events):
        if e.t_s > mission_end_s:
            name = f" {e.id!r}" if e.id else ""
            out.append(f"events[{k}]: {e.kind} event{name} at {e.t_s:g} s comes after the end of the mission at "
                       f"{mission_end_s:.1f} s (events are times after the mission start); move it earlier or drop it")
    return out


def scenario_at(sc: Scenario, t_s: float) -> Scenario:
    """The scenario with every map-changing event up to ``t_s`` [s after the start] applied, so
    the affected maps are recomputed through the same (cached) stages:

    * ``wind``: replaces ``data.uniform_wind`` / ``data.wind`` (wind stage);
    * ``gnss``: ``out_of_service`` adds to ``gnss.exclude_satellites``, ``almanacs`` replaces
      ``data.almanacs`` (satellites stage, then coverage);
    * ``obstacle``: adds to ``data.obstacles`` (surface stage, then everything built on it).

    ``intruder``, ``intruder_update`` and ``nofly`` events change no map.  Stages whose settings
    these do not touch keep their cache keys."""
    data, gnss = sc.data, sc.gnss
    d_upd: dict[str, Any] = {}
    excluded = list(gnss.exclude_satellites)
    obstacles = list(data.obstacles)
    for e in sc.events:
        if e.t_s > t_s:
            break  # sorted by time
        if isinstance(e, WindEvent):
            d_upd.update(uniform_wind=e.uniform_wind, wind=e.wind)
        elif isinstance(e, GnssEvent):
            excluded += [s for s in e.out_of_service if s not in excluded]
            if e.almanacs:
                d_upd["almanacs"] = e.almanacs
        elif isinstance(e, ObstacleEvent):
            xy = e.polygon_xy(sc)
            obstacles.append(Obstacle(polygon=tuple((float(x), float(y)) for x, y in xy), height_agl_m=e.height_agl_m))
    if len(obstacles) != len(data.obstacles):
        d_upd["obstacles"] = tuple(obstacles)
    upd: dict[str, Any] = {}
    if d_upd:
        upd["data"] = data.model_copy(update=d_upd)
    if tuple(excluded) != gnss.exclude_satellites:
        upd["gnss"] = gnss.model_copy(update={"exclude_satellites": tuple(excluded)})
    return sc.model_copy(update=upd) if upd else sc
