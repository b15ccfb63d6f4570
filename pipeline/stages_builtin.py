"""Wiring of the built-in stages into the pipeline graph (settings selection per stage)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

from skyroute.pipeline.graph import SKYROUTE_VERSION, Stage, register
from skyroute.pipeline.model import FrozenModel
from skyroute.pipeline.settings import Obstacle, Scenario
from skyroute.stages.gridspec import Grid

if TYPE_CHECKING:
    import xarray as xr


class SurfaceSettings(FrozenModel):
    grid: Grid
    buildings_path: Path | None = None
    buildings_format: str | None = None
    storey_height_m: float = 3.0
    terrain_path: Path | None = None
    vertical_datum: str | None = None
    chunk_cells: int = 1024
    surface_paths: tuple[Path, ...] = ()
    surface_datum: str | None = None
    surface_nodata: str = "fill-max"
    ground_window_m: float = 60.0
    building_threshold_m: float = 2.5
    raster_sources: tuple[Path, ...] = ()  # files a VRT reads: in the settings so their content is hashed
    obstacles: tuple[Obstacle, ...] = ()   # static obstacles (tactical events): burnt into `surface`


def _vrt_sources(paths) -> tuple[Path, ...]:
    """The files named by the VRTs among ``paths`` (``SourceFilename``), so that editing a tile
    changes the surface stage's cache key."""
    import xml.etree.ElementTree as ET

    out: list[Path] = []
    for p in paths:
        if Path(p).suffix.lower() != ".vrt" or not Path(p).is_file():
            continue
        try:
            root = ET.parse(p).getroot()
        except ET.ParseError:
            continue   # reading it reports the problem
        for el in root.iter("SourceFilename"):
            src = Path((el.text or "").strip())
            out.append(Path(p).parent / src if el.get("relativeToVRT", "0") == "1" else src)
    return tuple(out)


def _surface_settings(sc: Scenario) -> SurfaceSettings:
    b, t = sc.data.buildings, sc.data.terrain
    return SurfaceSettings(
        grid=sc.grid,
        buildings_path=b.path if b else None, buildings_format=b.format if b else None,
        storey_height_m=b.storey_height_m if b else 3.0,
        terrain_path=t.path if t else None, vertical_datum=t.vertical_datum if t else None,
        chunk_cells=sc.aoi.chunk_cells,
        **({} if sc.data.surface is None else dict(
            surface_paths=sc.data.surface.paths, surface_datum=sc.data.surface.vertical_datum,
            surface_nodata=sc.data.surface.nodata, ground_window_m=sc.data.surface.ground_window_m,
            building_threshold_m=sc.data.surface.building_threshold_m)),
        raster_sources=_vrt_sources([*(sc.data.surface.paths if sc.data.surface else ()), *([t.path] if t else [])]),
        obstacles=sc.data.obstacles,
    )


def surface_stage(*, settings: SurfaceSettings) -> xr.Dataset:
    """Digital surface model: terrain + buildings + DSM on the scenario grid (chunked)."""
    from skyroute.stages.surface import build_surface

    sp = settings.surface_paths
    ds = build_surface(settings.grid, buildings_path=settings.buildings_path,
                       buildings_format=settings.buildings_format, storey_height_m=settings.storey_height_m,
                       terrain_path=settings.terrain_path, vertical_datum=settings.vertical_datum,
                       surface_path=_raster_source(sp) if sp else None,
                       surface_datum=settings.surface_datum, surface_nodata=settings.surface_nodata,
                       ground_window_m=settings.ground_window_m, building_threshold_m=settings.building_threshold_m)
    if settings.obstacles:
        from skyroute.stages.surface import burn_obstacles

        burnt = burn_obstacles(ds["surface"].values, ds["terrain"].values, settings.grid,
                               [(o.polygon, o.height_agl_m) for o in settings.obstacles])
        ds["surface"] = ds["surface"].copy(data=burnt.astype(ds["surface"].dtype))
        ds.attrs["obstacles"] = (f"{len(settings.obstacles)} static obstacle(s) burnt into surface "
                                 "(every touched cell: highest ground under the polygon + height)")
    c = settings.chunk_cells
    return ds.chunk({"y": c, "x": c})


register(Stage("surface", surface_stage, _surface_settings, code_modules=("skyroute.stages.surface", "skyroute.stages.osm", "skyroute.stages.grid"),
               description="buildings + terrain + DSM -> digital surface model"))


# --------------------------------------------------------------------------- GNSS geometry
class SatellitesSettings(FrozenModel):
    almanacs: tuple[Path, ...]
    times_utc: tuple[str, ...]
    lat_deg: float
    lon_deg: float
    height_m: float = 0.0
    mask_deg: float = 5.0
    exclude: tuple[str, ...] = ()  # satellites out of service (ids as `skyroute sky` prints them)


def _satellites_settings(sc: Scenario) -> SatellitesSettings:
    g = sc.grid
    xmin, ymin, xmax, ymax = g.bounds
    lon, lat = g.to_lonlat((xmin + xmax) / 2, (ymin + ymax) / 2)
    return SatellitesSettings(
        almanacs=tuple(sc.data.almanacs),
        times_utc=tuple(t.replace(tzinfo=None).isoformat() for t in sc.mission_times_utc()),
        lat_deg=round(float(lat), 7), lon_deg=round(float(lon), 7),
        mask_deg=sc.gnss.elevation_mask_deg,
        exclude=tuple(sorted(sc.gnss.exclude_satellites)),
    )


def satellites_stage(*, settings: SatellitesSettings) -> xr.Dataset:
    """Satellite ECEF positions, true azimuth/elevation and open-sky DOP at the AOI centre,
    dims (time, sat), at the scenario's GNSS epochs (mission start + window); the almanac
    readers' warnings (unhealthy satellites excluded) are also in ``attrs["warnings"]``."""
    import warnings

    import numpy as np

    from skyroute.stages.almanac import sky_geometry

    times = np.array(settings.times_utc, dtype="datetime64[ns]")
    with warnings.catch_warnings(record=True) as caught:   # e.g. unhealthy satellites excluded
        warnings.simplefilter("always")
        ds = sky_geometry(list(settings.almanacs), times, settings.lat_deg, settings.lon_deg,
                          settings.height_m, mask_deg=settings.mask_deg)
    for w in caught:          # shown as before, and kept with the dataset: a warm run reports them too
        warnings.warn(w.message, w.category, stacklevel=2)
    if settings.exclude:
        ds = _without_satellites(ds, settings.exclude)
    own = str(Path(sky_geometry.__code__.co_filename).parent)    # skyroute's stages: the almanac readers
    texts = [" ".join(str(w.message).split()) for w in caught
             if issubclass(w.category, UserWarning) and str(w.filename).startswith(own)]
    if texts:
        ds.attrs["warnings"] = json.dumps(list(dict.fromkeys([*texts, *json.loads(ds.attrs.get("warnings", "[]"))])))
    return ds


def _without_satellites(ds: xr.Dataset, exclude: tuple[str, ...]) -> xr.Dataset:
    """``ds`` (from ``sky_geometry``) without the satellites ``exclude``, its visibility count and
    open-sky DOP recomputed from the satellites left."""
    import json

    import numpy as np

    from skyroute.stages.dop import DOP_NAMES, dop

    sats = [str(s) for s in ds["sat"].values]
    gone = [s for s in exclude if s in sats]
    if len(gone) == len(sats):
        from skyroute.pipeline.errors import InputError

        raise InputError(f"gnss.exclude_satellites (with the out_of_service of gnss events) takes out all "
                         f"{len(sats)} satellites of the almanacs: no position can be computed; list fewer "
                         "satellites (at least 4 must stay in service)")
    ds = ds.isel(sat=np.array([s not in exclude for s in sats]))
    above = ds["above_mask"]
    ds["n_visible"] = above.sum("sat").assign_attrs(ds["n_visible"].attrs)
    d = dop(ds["az_deg"].where(above), ds["el_deg"].where(above), axis="sat")
    for k in DOP_NAMES:
        ds[k] = d[k]
    ds.attrs["excluded_satellites"] = ", ".join(gone)
    absent = [s for s in exclude if s not in sats]
    if absent:
        ds.attrs["warnings"] = json.dumps([f"satellites {', '.join(absent)} are out of service but not in the "
                                           "almanacs: nothing to exclude for them"])
    return ds


register(Stage("satellites", satellites_stage, _satellites_settings, applies=lambda sc: bool(sc.data.almanacs),
               code_modules=("skyroute.stages.almanac", "skyroute.stages.orbits", "skyroute.stages.dop"),
               description="almanacs -> satellite positions, az/el, open-sky DOP over the mission window"))


# --------------------------------------------------------------------------- environment
class EnvironmentSettings(FrozenModel):
    grid: Grid
    osm_path: Path | None = None
    cityjson_path: Path | None = None
    tag_table: Path | None = None
    level5_nofly: bool = False
    nofly_zones: Path | None = None
    landing_geojson: Path | None = None
    osm_landing_sites: bool = True
    default_level: int | None = None


def _environment_settings(sc: Scenario) -> EnvironmentSettings:
    from skyroute.pipeline.settings import catalog_dir

    b = sc.data.buildings
    osm = sc.data.landuse or (b.path if b is not None and b.format == "osm" else None)
    return EnvironmentSettings(
        grid=sc.grid, osm_path=osm, cityjson_path=b.path if b is not None and b.format == "cityjson" else None,
        tag_table=sc.data.risk_tags or catalog_dir() / "risk_tags.yaml", level5_nofly=sc.constraints.level5_nofly,
        nofly_zones=sc.constraints.nofly_zones, landing_geojson=sc.data.landing_sites,
        osm_landing_sites=sc.data.osm_landing_sites, default_level=sc.data.risk_default_level,
    )


def environment_stage(surface: xr.Dataset, *, settings: EnvironmentSettings) -> xr.Dataset:
    """Ground-risk levels and cost, no-fly mask, landing sites, distance and cost (roofs seen
    only in a DSM, the surface's ``dsm_building``, count as buildings)."""
    import warnings

    from skyroute.stages.environment import environment_risk_dataset

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="no landing sites")
        ds = environment_risk_dataset(
            settings.grid, osm_path=settings.osm_path, cityjson_path=settings.cityjson_path,
            tag_table=settings.tag_table, level5_nofly=settings.level5_nofly, nofly_zones=settings.nofly_zones,
            landing_geojson=settings.landing_geojson, osm_landing_sites=settings.osm_landing_sites,
            default_level=settings.default_level,
            building_mask=surface["dsm_building"].values if "dsm_building" in surface else None)
    return ds


register(Stage("environment", environment_stage, _environment_settings, inputs=("surface",),
               description="risk levels 1-6, risk cost, no-fly, landing sites and landing cost"))


class WindSettings(FrozenModel):
    grid: Grid
    path: Path | None = None
    time_utc: str | None = None
    uniform: tuple[float, float, float] | None = None
    profile: str = "constant"
    altitudes_m: tuple[float, ...]
    horizontal_step_m: float
    max_wind_mps: float


def _wind_settings(sc: Scenario) -> WindSettings:
    from skyroute.stages.vehicle import load_vehicle

    top = sc.constraints.max_altitude_agl_m
    levels = tuple(float(z) for z in sorted({*range(0, int(top) + 1, 10), top}))
    step = max(sc.grid.resolution_m, 100.0)
    veh = load_vehicle(sc.vehicle)
    if sc.data.wind is not None:
        w = sc.data.wind
        return WindSettings(grid=sc.grid, path=w.path, profile=w.profile, altitudes_m=levels,
                            time_utc=w.time_utc.replace(tzinfo=None).isoformat() if w.time_utc else None,
                            horizontal_step_m=step, max_wind_mps=veh.max_wind_mps)
    u = sc.data.uniform_wind
    assert u is not None
    return WindSettings(grid=sc.grid, uniform=(u.speed_mps, u.direction_deg, u.elevation_deg), profile="constant",
                        altitudes_m=levels, horizontal_step_m=step, max_wind_mps=veh.max_wind_mps)


def wind_stage(surface: xr.Dataset, *, settings: WindSettings) -> xr.Dataset:
    """Wind u, v, w, speed on (z above ground, y, x) at ``horizontal_step_m``, and the wind
    no-fly mask (speed above the vehicle's limit)."""
    import numpy as np

    from skyroute.stages.wind import read_wind, wind_nofly, wind_on_grid

    if settings.path is not None:
        src = read_wind(settings.path, time=np.datetime64(settings.time_utc) if settings.time_utc else None)
    else:
        src = settings.uniform
    ds = wind_on_grid(src, settings.grid, list(settings.altitudes_m), terrain=surface["terrain"].load(),
                      profile=settings.profile, horizontal_step_m=settings.horizontal_step_m)
    ds["wind_nofly"] = wind_nofly(ds, settings.max_wind_mps).assign_attrs(units="1")
    return ds


register(Stage("wind", wind_stage, _wind_settings, inputs=("surface",),
               applies=lambda sc: sc.data.wind is not None or sc.data.uniform_wind is not None,
               code_modules=("skyroute.stages.wind",), description="wind field and wind no-fly mask"))


class ClearanceSettings(FrozenModel):
    radius_m: float
    min_agl_m: float
    max_agl_m: float
    surface_paths: tuple[Path, ...] = ()   # a DSM: its floor is computed on its own prisms
    surface_nodata: str = "fill-max"
    has_dem: bool = False
    raster_sources: tuple[Path, ...] = ()


def _clearance_settings(sc: Scenario) -> ClearanceSettings:
    from skyroute.stages.vehicle import load_vehicle

    d = sc.data.surface
    return ClearanceSettings(radius_m=load_vehicle(sc.vehicle).r_p_m, min_agl_m=sc.constraints.min_altitude_agl_m,
                             max_agl_m=sc.constraints.max_altitude_agl_m,
                             **({} if d is None else dict(surface_paths=d.paths, surface_nodata=d.nodata,
                                                          has_dem=sc.data.terrain is not None,
                                                          raster_sources=_vrt_sources(d.paths))))


def _raster_source(paths: tuple[Path, ...]) -> Path | list[Path]:
    """A DSM source as the readers take it: one path, or the list of tiles."""
    return list(paths) if len(paths) > 1 else paths[0]


def _dsm_on_grid_lattice(paths: tuple[Path, ...], grid: Grid) -> bool:
    """True when the DSM is one raster whose pixels are the grid's cells (same CRS, pixel side =
    ``resolution_m``, origin on the grid's lattice) and none lies outside the grid: then the
    surface stage's footprint max copied every (filled) DSM pixel onto its cell, and the DSM's floor
    on its own prisms (:func:`~skyroute.stages.clearance.dsm_obstacle_floor`) is exactly the floor of
    the surface (the floor of a max is the max of the floors), which is computed chunk by chunk."""
    import numpy as np
    import rasterio
    from pyproj import CRS

    if len(paths) != 1:
        return False
    try:
        with rasterio.open(paths[0]) as src:
            t, crs, (h, w) = src.transform, src.crs, src.shape
    except rasterio.errors.RasterioIOError:
        return False   # the surface stage reported it
    r = grid.resolution_m
    if crs is None or CRS.from_user_input(crs) != grid.crs or t.b != 0 or t.d != 0:
        return False
    if not (np.isclose(t.a, r, rtol=1e-9) and np.isclose(-t.e, r, rtol=1e-9)):
        return False
    ox, oy = (t.c - grid.x0) / r, (grid.y1 - t.f) / r
    if not (np.isclose(ox, round(ox), atol=1e-6) and np.isclose(oy, round(oy), atol=1e-6)):
        return False
    c0, r0 = round(ox), round(oy)
    return c0 >= 0 and r0 >= 0 and c0 + w <= grid.nx and r0 + h <= grid.ny


def clearance_stage(surface: xr.Dataset, environment: xr.Dataset, *, settings: ClearanceSettings) -> xr.Dataset:
    """Obstacle clearance for the vehicle sphere r_p (seed 000 eq. 13): lowest allowed
    sphere-centre altitude, AGL ceiling, dilated no-fly cells and altitude-limited volumes.
    Chunked (dask ``map_overlap``) unless a DSM off the grid's lattice needs its own-prism floor."""
    import numpy as np

    from skyroute.stages.clearance import clearance_dataset, dsm_obstacle_floor

    grid = Grid.from_dataarray(surface["surface"])
    native = bool(settings.surface_paths) and not _dsm_on_grid_lattice(settings.surface_paths, grid)
    c = surface["surface"].chunksizes if surface["surface"].chunks is not None else None

    def lazy(da: xr.DataArray) -> xr.DataArray:
        return da.chunk({k: v[0] for k, v in c.items()}) if c and da.chunks is None else da

    terrain = lazy(surface["terrain"])
    terrain_min = lazy(surface["terrain_min"]) if "terrain_min" in surface else terrain
    env = environment[["nofly", "nofly_floor_m", "nofly_ceiling_m"]].load()
    floor, ceil = env["nofly_floor_m"].values, env["nofly_ceiling_m"].values
    unlimited = env["nofly"].values & (np.nan_to_num(floor, nan=0.0) <= 0) & np.isinf(ceil)
    limited = env["nofly"].values & ~unlimited
    volumes = []
    if limited.any():
        t = terrain.values
        for lo, hi in {(float(a), float(b)) for a, b in zip(floor[limited], ceil[limited], strict=True)}:
            m = limited & (floor == lo) & (ceil == hi)
            # AGL band -> absolute altitudes with the mean terrain of the zone (exact on flat ground)
            base = float(t[m].mean())
            volumes.append((env["nofly"].copy(data=m), base + lo, base + hi))
    surf = surface["surface"].load() if native else lazy(surface["surface"])
    ds = clearance_dataset(surf, settings.radius_m, terrain=terrain,
                           terrain_min=terrain_min, min_agl_m=settings.min_agl_m, max_agl_m=settings.max_agl_m,
                           nofly=env["nofly"].copy(data=unlimited), volumes=volumes or None,
                           obstacle_floor=dsm_obstacle_floor(surface, _raster_source(settings.surface_paths),
                                                             settings.radius_m, settings.surface_nodata,
                                                             settings.has_dem) if native else None)
    datum = surface["surface"].attrs.get("vertical_datum", "")
    for v in ds.data_vars.values():
        v.attrs.setdefault("units", "1" if v.dtype == bool else "m")
        if v.attrs["units"] == "m":
            v.attrs.setdefault("vertical_datum", datum)
    return ds


register(Stage("clearance", clearance_stage, _clearance_settings, inputs=("surface", "environment"),
               code_modules=("skyroute.stages.clearance", "skyroute.stages.grid"),
               description="obstacle clearance floor for the vehicle sphere, AGL bounds, no-fly"))


class TrafficStageSettings(FrozenModel):
    intruders: tuple
    n_slices: int
    margin_m: float
    time_margin_s: float
    terrain_base_m: float = 0.0


def _traffic_settings(sc: Scenario) -> TrafficStageSettings:
    t = sc.traffic
    return TrafficStageSettings(intruders=tuple(i.model_dump() for i in t.intruders), n_slices=t.n_slices,
                                margin_m=t.margin_m, time_margin_s=t.time_margin_s)


def traffic_stage(surface: xr.Dataset, *, settings: TrafficStageSettings) -> xr.Dataset:
    """Time-sliced occupancy of the known traffic (seed 000 eq. 1) as capsules per slice.
    Intruder altitudes are AGL in the scenario; they are converted to the surface datum with
    the terrain under each waypoint."""
    import numpy as np

    from skyroute.stages.traffic import build_occupancy, intruders_for

    records = [{"id": i.id, "radius_m": i.radius_m, "waypoints": np.column_stack([i.times_s, i.xyz_m]).tolist()}
               for i in intruders_for(settings.intruders, surface)]
    t_end = max(float(np.asarray(it["waypoints"])[:, 0].max()) for it in settings.intruders)
    occ = build_occupancy(records, t_total_s=t_end, n_slices=settings.n_slices, d_c_m=settings.margin_m,
                          dt_c_s=settings.time_margin_s)
    ds = occ.to_dataset()
    ds.attrs["vertical_datum"] = surface["surface"].attrs.get("vertical_datum", "")
    return ds


register(Stage("traffic", traffic_stage, _traffic_settings, inputs=("surface",),
               applies=lambda sc: len(sc.traffic.intruders) > 0, code_modules=("skyroute.stages.traffic",),
               description="time-sliced occupancy of known traffic (capsules, exact queries)"))


# --------------------------------------------------------------------------- GNSS coverage
class CoverageSettings(FrozenModel):
    thresholds: tuple[float, ...]
    dop_kind: str
    mask_deg: float
    min_agl_m: float
    max_agl_m: float
    chunk_cells: int


def _coverage_settings(sc: Scenario) -> CoverageSettings:
    g = sc.gnss
    return CoverageSettings(thresholds=g.dop_thresholds, dop_kind=g.dop_kind, mask_deg=g.elevation_mask_deg,
                            min_agl_m=sc.constraints.min_altitude_agl_m, max_agl_m=sc.constraints.max_altitude_agl_m,
                            chunk_cells=sc.aoi.chunk_cells)


def coverage_stage(surface: xr.Dataset, satellites: xr.Dataset, *, settings: CoverageSettings) -> xr.Dataset:
    """GNSS coverage maps (seed 000 item 5, seed 001 item 5): per DOP threshold D_j the altitude
    above which DOP < D_j, worst case over the mission window, clipped to the AGL limits; the
    number of visible satellites and DOP on sections come from `stages.coverage.dop_section`."""
    from skyroute.stages.coverage import coverage_maps

    terrain = surface["terrain"]
    az = satellites["az_deg"].load()
    el = satellites["el_deg"].load()
    ds = coverage_maps(surface["surface"], az, el, thresholds=settings.thresholds, dop=settings.dop_kind,
                       floor_m=terrain + settings.min_agl_m,
                       ceiling_m=surface.get("terrain_min", terrain) + settings.max_agl_m,
                       mask_deg=settings.mask_deg, chunks="auto")
    return ds


register(Stage("coverage", coverage_stage, _coverage_settings, inputs=("surface", "satellites"),
               code_modules=("skyroute.stages.coverage", "skyroute.stages.occlusion", "skyroute.stages.dop"),
               description="GNSS coverage floors per DOP threshold (worst case over the window)"))


# --------------------------------------------------------------------------- energy-bound tiles
class WindBoundsSettings(FrozenModel):
    vehicle_profile: dict   # the profile's content
    resolution_m: float
    step_cells: int


def _wind_bounds_settings(sc: Scenario) -> WindBoundsSettings:
    from skyroute.stages.vehicle import load_vehicle

    return WindBoundsSettings(vehicle_profile=load_vehicle(sc.vehicle).model_dump(mode="json"),
                              resolution_m=sc.aoi.resolution_m, step_cells=sc.planner.step_cells)


def wind_bounds_stage(wind: xr.Dataset, *, settings: WindBoundsSettings) -> xr.Dataset:
    """The A* heuristic's energy-ratio bounds per wind tile and lattice edge direction
    (:func:`~skyroute.stages.planning.wind_bounds.wind_ratio_tiles`): computed once per wind map,
    vehicle and lattice step, read by every plan on those maps."""
    from skyroute.stages.planning.wind_bounds import wind_ratio_tiles
    from skyroute.stages.vehicle import vehicle_from_dict

    return wind_ratio_tiles(wind, vehicle_from_dict(settings.vehicle_profile), settings.resolution_m,
                            settings.step_cells)


register(Stage("wind_bounds", wind_bounds_stage, _wind_bounds_settings, inputs=("wind",),
               applies=lambda sc: ((sc.data.wind is not None or sc.data.uniform_wind is not None)
                                   and sc.planner.name == "astar" and sc.planner.weights[3] > 0),
               code_modules=("skyroute.stages.planning.wind_bounds", "skyroute.stages.planning.heuristic",
                             "skyroute.stages.planning.kernels", "skyroute.stages.planning.grid_planner",
                             "skyroute.stages.energy", "skyroute.stages.vehicle"),
               description="A* energy-ratio bounds per wind tile (reused by every plan on these maps)"))


# --------------------------------------------------------------------------- strategic plan
class PlanSettings(FrozenModel):
    start_xy: tuple[float, float]
    start_agl_m: float
    goal_xy: tuple[float, float]
    goal_agl_m: float
    start_time_utc: str
    vehicle: str
    vehicle_profile: dict  # the profile's content, so editing the vehicle YAML recomputes the plan
    weights: tuple[float, float, float, float]
    planner: str
    time_budget_s: float
    seed: int
    max_tries: int
    step_cells: int = 8
    min_agl_m: float
    max_agl_m: float
    dop_kind: str
    intruders: tuple
    d_c_m: float
    dt_c_s: float
    uere_m: float = 3.0
    battery_reserve_pct: float = 0.0


class PlanSboaSettings(PlanSettings):
    """Plan settings with the safety bubble (``constraints.clearance: sboa``, seed 003): a
    separate model so that the default ``fixed`` keeps its cache keys."""
    sboa_k: float
    surface_uncertainty_m: float
    clearance: ClearanceSettings


def _plan_settings(sc: Scenario) -> PlanSettings:
    base = _plan_settings_fixed(sc)
    if sc.constraints.clearance != "sboa":
        return base
    from skyroute.stages.sboa import check_dop_kind

    check_dop_kind(sc.gnss.dop_kind)
    return PlanSboaSettings(**dict(base), sboa_k=sc.constraints.sboa_k,
                            surface_uncertainty_m=sc.navsim.surface_uncertainty_m, clearance=_clearance_settings(sc))


def _plan_settings_fixed(sc: Scenario) -> PlanSettings:
    from skyroute.stages.vehicle import load_vehicle

    m, p = sc.mission, sc.planner
    return PlanSettings(vehicle_profile=load_vehicle(sc.vehicle).model_dump(mode="json"),
        start_xy=sc.point_xy(m.start), start_agl_m=m.start.alt_agl_m, goal_xy=sc.point_xy(m.goal),
        goal_agl_m=m.goal.alt_agl_m, start_time_utc=m.start_time_utc.isoformat(), vehicle=sc.vehicle,
        weights=p.weights, planner=p.name, time_budget_s=p.time_budget_s, seed=p.seed, max_tries=p.max_tries, step_cells=p.step_cells,
        min_agl_m=sc.constraints.min_altitude_agl_m, max_agl_m=sc.constraints.max_altitude_agl_m,
        dop_kind=sc.gnss.dop_kind, intruders=tuple(i.model_dump() for i in sc.traffic.intruders),
        d_c_m=sc.traffic.margin_m, dt_c_s=sc.traffic.time_margin_s, uere_m=sc.gnss.uere_m,
        battery_reserve_pct=sc.constraints.battery_reserve_pct)


def plan_stage(surface: xr.Dataset, environment: xr.Dataset, clearance: xr.Dataset, wind: xr.Dataset | None,
               coverage: xr.Dataset | None, satellites: xr.Dataset | None, traffic: xr.Dataset | None,
               wind_bounds: xr.Dataset | None = None, *, settings: PlanSettings) -> xr.Dataset:
    """Strategic plan (seed 000 III): STEP I-III for every coverage level and the choice."""
    from skyroute.stages.planning.request import Maps, PlanRequest
    from skyroute.stages.planning.strategic import plan_strategic, plan_to_dataset

    kw = plan_arguments(settings, surface)
    extra = {}
    if isinstance(settings, PlanSboaSettings):
        sb = sboa_levels(settings, surface, environment, coverage)
        extra["clearance_by_level"] = sb["clearance_by_level"]
        kw["bubble"] = sb["bubble"]
    maps = Maps(surface=surface, clearance=clearance, environment=environment, wind=wind, coverage=coverage,
                satellites=satellites, traffic=traffic, wind_bounds=wind_bounds, **extra)
    plan = plan_strategic(maps, PlanRequest.of(**kw))
    ds = plan_to_dataset(plan, surface["surface"].rio.crs, surface["surface"].attrs.get("vertical_datum", ""),
                         settings.start_time_utc)
    ds.attrs["provenance"] = json.dumps(plan_provenance(settings))
    return ds


def plan_provenance(s: PlanSettings) -> dict:
    """How a plan was made (summary.json, plan.geojson, candidates.csv, report.html, ``skyroute
    diff``): ``planner``, ``seed``, ``weights`` (w_l, w_r, w_d, w_e), ``time_budget_s`` [s],
    ``max_tries``, ``step_cells``, the counted ``budgets`` the planner stops on and its
    wall-clock safety cap [s], the ``vehicle`` and a hash of its profile, ``skyroute_version``."""
    from skyroute.pipeline.model import stable_hash
    from skyroute.stages.planning.grid_planner import ASTAR_MAX_EXPANSIONS, RELAX_MAX_SEGMENTS
    from skyroute.stages.planning.step1 import LEVEL_CAP_FACTOR, bitstar_iterations

    budgets: dict = {"wallclock_safety_cap_s": LEVEL_CAP_FACTOR * s.time_budget_s}
    if s.planner == "astar":
        budgets["max_expansions"] = ASTAR_MAX_EXPANSIONS
        budgets["refine_max_segment_evaluations"] = RELAX_MAX_SEGMENTS
    if s.planner == "bitstar":
        budgets["bitstar_iterations"] = bitstar_iterations(s.time_budget_s)
    if s.planner == "bitstar-dubins":
        from skyroute.stages.planning.bitstar_dubins import dubins_iterations

        budgets["bitstar_iterations"] = dubins_iterations(s.time_budget_s)
    return {"planner": s.planner, "seed": int(s.seed), "weights": [float(w) for w in s.weights],
            "time_budget_s": float(s.time_budget_s), "max_tries": int(s.max_tries), "step_cells": int(s.step_cells),
            "budgets": budgets, "vehicle": s.vehicle, "vehicle_profile_hash": stable_hash(s.vehicle_profile),
            "skyroute_version": SKYROUTE_VERSION}


def plan_arguments(s: PlanSettings, surface: xr.Dataset) -> dict:
    """The keyword arguments of :func:`~skyroute.stages.planning.strategic.plan_levels` (the fields of a
    :class:`~skyroute.stages.planning.request.PlanRequest`) for
    these settings (one place: the plan stage and the benchmarks call it)."""
    from skyroute.stages.vehicle import vehicle_from_dict

    intr = None
    if s.intruders:     # only then (its maps' module imports rioxarray: a warm fly needs none)
        from skyroute.stages.traffic import intruders_for

        intr = intruders_for(s.intruders, surface)
    # the vehicle travels as its profile (the content the cache key hashed), never reloaded by name
    return dict(start_xy=s.start_xy, start_agl_m=s.start_agl_m, goal_xy=s.goal_xy, goal_agl_m=s.goal_agl_m,
                start_time_utc=s.start_time_utc, vehicle=vehicle_from_dict(s.vehicle_profile), weights=s.weights, planner=s.planner,
                time_budget_s=s.time_budget_s, seed=s.seed, max_tries=s.max_tries, step_cells=s.step_cells,
                min_agl_m=s.min_agl_m, max_agl_m=s.max_agl_m, dop_kind=s.dop_kind, intruders=intr, d_c_m=s.d_c_m,
                dt_c_s=s.dt_c_s, uere_m=s.uere_m, battery_reserve_pct=s.battery_reserve_pct)


def plan_request(sc: Scenario, surface: xr.Dataset | None = None):
    """The scenario's :class:`~skyroute.stages.planning.request.PlanRequest` as the plan stage
    makes it from its settings (:func:`plan_arguments`; vehicle resolved once), for the replays
    of ``skyroute fly``: without the safety bubble (the replay adds it with the plan's radius)
    and, without ``surface``, without the known intruders (a replay gets them as tracks)."""
    from skyroute.stages.planning.request import PlanRequest

    s = _plan_settings_fixed(sc)
    if surface is None:
        s = s.model_copy(update={"intruders": ()})
    return PlanRequest.of(**plan_arguments(s, surface))


def sboa_levels(s: PlanSboaSettings, surface: xr.Dataset, environment: xr.Dataset,
                coverage: xr.Dataset | None) -> dict:
    """The safety-bubble arguments of ``plan_strategic``: per coverage level D_j the clearance
    dataset of the clearance stage recomputed for ``r_j`` (:func:`~skyroute.stages.sboa.level_radius_m`)
    and ``bubble = (k, surface_uncertainty_m)`` for the STEP III re-check."""
    from skyroute.stages.sboa import level_radius_m
    from skyroute.stages.vehicle import vehicle_from_dict

    veh = vehicle_from_dict(s.vehicle_profile)
    by_level = {}
    if coverage is not None:
        for d in coverage["threshold"].values:
            r = level_radius_m(float(d), veh.r_p_m, s.sboa_k, s.surface_uncertainty_m, imu=veh.imu, uere_m=s.uere_m)
            by_level[float(d)] = clearance_stage(surface, environment,
                                                 settings=s.clearance.model_copy(update={"radius_m": r}))
    return dict(clearance_by_level=by_level, bubble=(s.sboa_k, s.surface_uncertainty_m))


def plan_precheck(sc: Scenario, datasets: dict[str, xr.Dataset]) -> None:
    """Refuse, before the coverage and planning work, weights that select only degenerate
    cost terms (:mod:`skyroute.stages.planning.degenerate`; the plan stage repeats the check
    and lists the degenerate terms in its ``warnings``)."""
    from skyroute.stages.planning.degenerate import check_cost_terms, degenerate_cost_terms
    from skyroute.stages.planning.window import planning_windows

    env = datasets.get("environment")
    if env is not None:     # on a city-scale AOI the maps of the first planning window, as the planner sees them
        win = planning_windows(sc.grid, sc.point_xy(sc.mission.start), sc.point_xy(sc.mission.goal))[0]
        if win is not None:
            env = env.isel(y=win[0], x=win[1])
    check_cost_terms(sc.planner.weights, degenerate_cost_terms(env, datasets.get("wind")))


register(Stage("plan", plan_stage, _plan_settings, inputs=("surface", "environment", "clearance"),
               optional_inputs=("wind", "coverage", "satellites", "traffic", "wind_bounds"),
               precheck=plan_precheck, precheck_after=("environment", "wind"),
               code_modules=("skyroute.stages.planning.strategic", "skyroute.stages.planning.problem",
                             "skyroute.stages.planning.kernels", "skyroute.stages.planning.heuristic",
                             "skyroute.stages.planning.degenerate",
                             "skyroute.stages.planning.step1", "skyroute.stages.planning.grid_planner",
                             "skyroute.stages.planning.bitstar", "skyroute.stages.planning.deconflict",
                             "skyroute.stages.planning.step3", "skyroute.stages.planning.validate",
                             "skyroute.stages.energy", "skyroute.stages.smoothing", "skyroute.stages.navigation",
                             "skyroute.stages.vehicle", "skyroute.stages.sboa", "skyroute.stages.clearance",
                             "skyroute.stages.planning.kinds", "skyroute.stages.planning.fixedwing",
                             "skyroute.stages.planning.fw_kernels", "skyroute.stages.fixedwing_energy",
                             "skyroute.stages.atmosphere"),
               description="strategic plan: STEP I-III per DOP level and the chosen trajectory"))
