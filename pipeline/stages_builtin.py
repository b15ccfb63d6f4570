"""Wiring of the built-in stages into the pipeline graph (settings selection per stage)."""

from __future__ import annotations

from pathlib import Path

import xarray as xr

from skyroute.pipeline.graph import Stage, register
from skyroute.pipeline.model import FrozenModel
from skyroute.pipeline.settings import Scenario
from skyroute.stages.grid import Grid
from skyroute.stages.surface import build_surface


class SurfaceSettings(FrozenModel):
    grid: Grid
    buildings_path: Path | None = None
    buildings_format: str | None = None
    storey_height_m: float = 3.0
    terrain_path: Path | None = None
    vertical_datum: str | None = None
    chunk_cells: int = 1024


def _surface_settings(sc: Scenario) -> SurfaceSettings:
    b, t = sc.data.buildings, sc.data.terrain
    return SurfaceSettings(
        grid=sc.grid,
        buildings_path=b.path if b else None, buildings_format=b.format if b else None,
        storey_height_m=b.storey_height_m if b else 3.0,
        terrain_path=t.path if t else None, vertical_datum=t.vertical_datum if t else None,
        chunk_cells=sc.aoi.chunk_cells,
    )


def surface_stage(*, settings: SurfaceSettings) -> xr.Dataset:
    ds = build_surface(settings.grid, buildings_path=settings.buildings_path,
                       buildings_format=settings.buildings_format, storey_height_m=settings.storey_height_m,
                       terrain_path=settings.terrain_path, vertical_datum=settings.vertical_datum)
    c = settings.chunk_cells
    return ds.chunk({"y": c, "x": c})


register(Stage("surface", surface_stage, _surface_settings, code_modules=("skyroute.stages.surface", "skyroute.stages.osm", "skyroute.stages.grid"),
               description="buildings + terrain -> digital surface model"))


# --------------------------------------------------------------------------- GNSS geometry
class SatellitesSettings(FrozenModel):
    almanacs: tuple[Path, ...]
    times_utc: tuple[str, ...]
    lat_deg: float
    lon_deg: float
    height_m: float = 0.0
    mask_deg: float = 5.0


def _satellites_settings(sc: Scenario) -> SatellitesSettings:
    g = sc.grid
    xmin, ymin, xmax, ymax = g.bounds
    lon, lat = g.to_lonlat((xmin + xmax) / 2, (ymin + ymax) / 2)
    return SatellitesSettings(
        almanacs=tuple(sc.data.almanacs),
        times_utc=tuple(t.replace(tzinfo=None).isoformat() for t in sc.mission_times_utc()),
        lat_deg=round(float(lat), 7), lon_deg=round(float(lon), 7),
        mask_deg=sc.gnss.elevation_mask_deg,
    )


def satellites_stage(*, settings: SatellitesSettings) -> xr.Dataset:
    """Satellite ECEF positions, true azimuth/elevation and open-sky DOP at the AOI centre,
    dims (time, sat), at the scenario's GNSS epochs (mission start + window)."""
    import numpy as np

    from skyroute.stages.almanac import sky_geometry

    times = np.array(settings.times_utc, dtype="datetime64[ns]")
    ds = sky_geometry(list(settings.almanacs), times, settings.lat_deg, settings.lon_deg,
                      settings.height_m, mask_deg=settings.mask_deg)
    return ds


register(Stage("satellites", satellites_stage, _satellites_settings, applies=lambda sc: bool(sc.data.almanacs),
               code_modules=("skyroute.stages.almanac", "skyroute.stages.orbits", "skyroute.stages.dop"),
               description="almanacs -> satellite positions, az/el, open-sky DOP over the mission window"))
