"""The scenario schema: one frozen pydantic model per YAML section and :class:`Scenario`."""

from __future__ import annotations

import datetime as dt
import math
from functools import cached_property
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, ValidationError, field_validator, model_validator

from skyroute.pipeline.errors import ScenarioError
from skyroute.pipeline.model import FrozenModel
from skyroute.pipeline.settings.common import (
    Bounds,
    GriddedWind,
    NonNegFloat,
    PositiveFloat,
    UniformWind,
    Vertex,
    _check_polygon,
    _check_sat_ids,
    _problems_from,
    unsafe_name,
)
from skyroute.pipeline.settings.events import Event
from skyroute.stages.planning.registry import PLANNERS  # noqa: E402  (the one list of planners)


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

    @field_validator("waypoints")
    @classmethod
    def _flyable(cls, v: tuple[tuple[float, float, float, float], ...]):
        """Finite waypoints in increasing time, flown at most :data:`MAX_INTRUDER_SPEED_MPS`."""
        import math

        from skyroute.pipeline.settings.common import MAX_INTRUDER_SPEED_MPS

        for k, w in enumerate(v):
            if not all(math.isfinite(c) for c in w):
                raise ValueError(f"waypoint {k} {list(w)} has a value that is not a finite number")
        for k in range(1, len(v)):
            (t0, *p0), (t1, *p1) = v[k - 1], v[k]
            if not t1 > t0:
                raise ValueError(f"times must increase strictly (waypoint {k} at {t1:g} s is not after waypoint "
                                 f"{k - 1} at {t0:g} s)")
            speed = math.dist(p0, p1) / (t1 - t0)
            if speed > MAX_INTRUDER_SPEED_MPS:
                raise ValueError(f"waypoints {k - 1} -> {k} are flown at {speed:.4g} m/s, faster than the "
                                 f"{MAX_INTRUDER_SPEED_MPS:g} m/s an intruder may fly; check the times [s] and "
                                 "coordinates [m]")
        return v

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
        from skyroute.stages.gridspec import Grid, resolve_crs, utm_crs_for

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
