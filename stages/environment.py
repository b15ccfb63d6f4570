"""The environment dataset (stage ``environment``): ground-risk levels and cost, no-fly mask,
landing sites, landing distance and cost on the scenario grid, in one Dataset.

:func:`environment_risk_dataset` combines :mod:`skyroute.stages.risk` (levels from OSM, CityJSON
or a GeoTIFF; risk cost; no-fly zones) and :mod:`skyroute.stages.landing` (sites, distance [m]
and cost); :func:`environment_for_scenario` calls it with a loaded scenario's sources;
:func:`plot_environment` draws the risk levels and the landing cost side by side.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from skyroute.stages.base import InputError
from skyroute.stages.grid import Grid
from skyroute.stages.landing import (
    DEFAULT_MIN_AREA_M2,
    landing_cost,
    landing_sites,
    plot_landing_cost,
)
from skyroute.stages.risk import (
    TagTable,
    load_tag_table,
    nofly_mask,
    risk_cost,
    risk_from_geotiff,
    risk_levels,
)


def environment_risk_dataset(
    grid: Grid, *, osm_path: str | Path | None = None, cityjson_path: str | Path | None = None,
    risk_geotiff: str | Path | None = None, tag_table: str | Path | Mapping | TagTable | None = None,
    default_level: int | None = None, level5_nofly: bool = False, nofly_zones: str | Path | None = None,
    landing_geojson: str | Path | None = None, osm_landing_sites: bool = True,
    min_area_m2: float = DEFAULT_MIN_AREA_M2, normalization: str = "map",
    landing_max_distance_m: float | None = None, building_mask: np.ndarray | None = None,
) -> xr.Dataset:
    """Risk levels, risk cost, no-fly mask, landing sites, distance and cost in one Dataset.

    ``risk_geotiff`` replaces the OSM/CityJSON derivation of the levels.  Without any landing
    site the landing variables are filled (distance inf, cost 1) with a warning.
    """
    table = load_tag_table(tag_table)
    if risk_geotiff is not None:
        levels = risk_from_geotiff(risk_geotiff, grid,
                                   default_level=table.default_level if default_level is None else default_level)
    else:
        levels = risk_levels(grid, osm_path=osm_path, cityjson_path=cityjson_path, tag_table=table,
                             default_level=default_level, building_mask=building_mask)
    ds = xr.Dataset({"risk_level": levels,
                     "risk_cost": risk_cost(levels, level5_nofly=level5_nofly, normalization=normalization)})  # type: ignore[arg-type]
    nofly = nofly_mask(levels, nofly_zones, level5_nofly=level5_nofly, grid=grid)
    for k, v in nofly.data_vars.items():
        ds[k] = v
    ds.attrs["n_nofly_zones"] = nofly.attrs["n_zones"]
    have_source = landing_geojson is not None or (osm_landing_sites and osm_path is not None)
    sites = (landing_sites(grid, osm_path=osm_path if osm_landing_sites else None, geojson=landing_geojson,
                           min_area_m2=min_area_m2, tag_table=table) if have_source else None)
    if sites is not None and len(sites):
        ds["landing_site"] = sites.mask
        lc = landing_cost(grid, sites, max_distance_m=landing_max_distance_m)
        ds = ds.assign_coords({k: lc.coords[k] for k in ("site_x", "site_y", "site_name", "site_kind")})
        for k, v in lc.data_vars.items():
            ds[k] = v
    else:
        warnings.warn("no landing sites for this grid: landing_distance_m is inf and landing_cost 1 everywhere",
                      stacklevel=2)
        ds["landing_site"] = grid.dataarray(np.zeros(grid.shape, bool), "landing_site", units="1")
        ds["landing_distance_m"] = grid.dataarray(np.full(grid.shape, np.inf, np.float32), "landing_distance_m", units="m")
        ds["landing_cost"] = grid.dataarray(np.ones(grid.shape, np.float32), "landing_cost", units="1")
    ds = ds.rio.write_crs(grid.crs, inplace=True)   # ds is ours: no copy of every layer
    ds.attrs.update({"title": "skyroute ground risk, no-fly and landing-site maps", "Conventions": "CF-1.10",
                     "resolution_m": grid.resolution_m, "level5_nofly": int(level5_nofly),
                     "risk_sources": levels.attrs.get("sources", ""), "tag_table": table.source,
                     "n_landing_sites": 0 if sites is None else len(sites)})
    return ds


def environment_for_scenario(scenario: Any, tag_table: str | Path | Mapping | TagTable | None = None) -> xr.Dataset:
    """:func:`environment_risk_dataset` from a loaded scenario (``load_scenario(...)``).

    Levels from ``data.landuse`` (an OSM extract, or a CityJSON file by its ``.json`` suffix)
    plus CityJSON buildings of ``data.buildings``; OSM landing sites from the OSM extract when
    ``data.osm_landing_sites``; no-fly zones and ``level5_nofly`` from ``constraints``.
    """
    d, c = scenario.data, scenario.constraints
    osm_path = cj_path = None
    for p in [d.landuse, d.buildings.path if d.buildings else None]:
        if p is None:
            continue
        if str(p).lower().endswith(".json"):
            cj_path = cj_path or p
        else:
            osm_path = osm_path or p
    return environment_risk_dataset(
        scenario.grid, osm_path=osm_path, cityjson_path=cj_path, tag_table=tag_table,
        level5_nofly=c.level5_nofly, nofly_zones=c.nofly_zones, landing_geojson=d.landing_sites,
        osm_landing_sites=d.osm_landing_sites)


# --------------------------------------------------------------------------- figures
def plot_environment(ds: xr.Dataset, ax=None):
    """Two panels: risk levels (categorical legend) and landing cost with the sites marked.

    ``ax``: None (a new figure) or a pair of axes.  Returns the figure.
    """
    import matplotlib.pyplot as plt

    from skyroute.stages.risk import plot_risk_levels

    if ax is None:
        fig, axes = plt.subplots(1, 2, figsize=(13, 5.5), layout="constrained")
    else:
        axes = list(ax) if not hasattr(ax, "imshow") else None
        if axes is None or len(axes) != 2:
            raise InputError("plot_environment needs ax=None or a pair of matplotlib axes (risk, landing)")
        fig = axes[0].figure
    plot_risk_levels(ds, axes[0])
    plot_landing_cost(ds, axes[1])
    return fig


__all__ = ["environment_for_scenario", "environment_risk_dataset", "plot_environment"]
