"""Scenario catalogs: YAML files validated into frozen, typed settings.

A scenario names an area of interest, its data sources, a mission, a vehicle profile,
constraints and planner settings.  :func:`load_scenario` reads a catalog entry (by name or
path), resolves data paths relative to the YAML file and validates everything at once:
a :class:`~skyroute.pipeline.errors.ScenarioError` lists *every* problem, each prefixed by
its YAML path (``mission.start: altitude 900 m is above constraints.max_altitude_agl_m 150``).
"""

from __future__ import annotations

import datetime as dt
import os
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import Field, ValidationError, field_validator, model_validator

from skyroute.pipeline.errors import ScenarioError, UnknownNameError
from skyroute.pipeline.model import FrozenModel

PositiveFloat = Annotated[float, Field(gt=0)]
NonNegFloat = Annotated[float, Field(ge=0)]
Bounds = tuple[float, float, float, float]

DEFAULT_SCENARIO = "helsinki-medical"


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
    energy kept in the battery, the plan may use ``battery * (1 - reserve / 100)``."""

    min_altitude_agl_m: NonNegFloat = 0.0
    max_altitude_agl_m: PositiveFloat = 120.0
    nofly_zones: Path | None = None
    level5_nofly: bool = False
    battery_reserve_pct: Annotated[float, Field(ge=0, lt=100)] = 0.0

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


PLANNERS = ("astar", "bitstar")


class PlannerSettings(FrozenModel):
    """STEP I planner (``astar``: deterministic 3-D lattice A* + refinement, the default; or
    ``bitstar``: OMPL BIT*, reproducible with its seed and an iteration budget derived from
    ``time_budget_s``), eq. 11 weights (w_l, w_r, w_d, w_e) >= 0 and
    not all zero, BIT* time per coverage level [s], random seed, energy re-plan tries N_t."""

    name: str = "astar"
    weights: tuple[NonNegFloat, NonNegFloat, NonNegFloat, NonNegFloat] = (1.0, 1.0, 1.0, 1.0)
    time_budget_s: PositiveFloat = 5.0
    seed: int = 0
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
    source_path: Path | None = Field(default=None, exclude=True)

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


def _problems_from(exc: ValidationError) -> list[str]:
    out = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"] if not str(p).startswith("function-"))
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            msg = ("unknown key (check the spelling; valid keys: catalogs/README.md or "
                   "`python -m skyroute.pipeline.settings_reference`)")
        elif err["type"] == "missing":
            msg = "required key is missing"
        out.append(f"{loc or '<root>'}: {msg}")
    return out


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
            if not Path(p).is_file():
                problems.append(f"{section}: data file not found: {p}")
            elif not os.access(p, os.R_OK):
                problems.append(f"{section}: data file is not readable: {p}")
    ds_, dt_ = sc.data.surface, sc.data.terrain
    if ds_ is not None and dt_ is not None and ds_.vertical_datum.strip().lower() != dt_.vertical_datum.strip().lower():
        problems.append(f"data.surface.vertical_datum: {ds_.vertical_datum!r} differs from data.terrain.vertical_datum "
                        f"{dt_.vertical_datum!r}; convert one raster so the DSM and the DEM share a vertical datum")
    from skyroute.stages.vehicle import known_vehicles

    if sc.vehicle not in known_vehicles() and not Path(sc.vehicle).is_file():
        problems.append(f"vehicle: unknown vehicle {sc.vehicle!r}; known vehicles: {', '.join(known_vehicles())}")
    else:
        problems.extend(_vehicle_altitude_problems(sc))
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
    return problems


def _vehicle_max_altitude_m(sc: Scenario) -> float | None:
    from skyroute.stages.vehicle import load_vehicle

    try:
        return float(load_vehicle(sc.vehicle).max_altitude_m)
    except Exception:  # an unreadable vehicle is reported by its own check
        return None


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
    if problems:
        raise ScenarioError(source, problems)
    if base is not None:
        sc = sc.model_copy(update={"source_path": Path(source)})
    return sc


def load_scenario(name_or_path: str | Path = DEFAULT_SCENARIO) -> Scenario:
    """Load and validate a scenario by catalog name (``helsinki-medical``) or YAML path."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.is_file():
        if not p.is_file():
            raise ScenarioError(str(p), [f"<file>: scenario file not found: {p}"])
    else:
        known = scenario_paths()
        if str(name_or_path) not in known:
            raise UnknownNameError("scenario", str(name_or_path), list(known))
        p = known[str(name_or_path)]
    try:
        raw = yaml.safe_load(p.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        what = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ScenarioError(str(p), [f"<file>: not valid YAML{where}: {what}"]) from None
    return parse_scenario(raw, source=str(p), base=p.parent)
