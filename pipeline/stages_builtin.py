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
