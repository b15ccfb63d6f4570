"""Landing sites, the landing-distance cost map, and the combined environment dataset.

Seed 000 section II-A item 3: "2D maps containing information about distance from the
landing sites ... a lower cost is associated to the points whose horizontal distance from
the landing sites is smaller"; seed 001 section 2: the cost "increases as the distance from
the contingency landing area increases".

Landing sites (:func:`landing_sites`)
-------------------------------------
* from the scenario: a GeoJSON FeatureCollection (WGS 84 lon/lat) of Point / MultiPoint /
  Polygon / MultiPolygon features (optional property ``name``);
* from OSM, by the ``landing`` section of ``catalogs/risk_tags.yaml``: ``any_size`` features
  (``aeroway=helipad|heliport``, ``emergency=landing_site``; hospital helipads are
  ``aeroway=helipad``) and ``open_ground`` areas (parks, pitches, grass, meadows) of at least
  ``min_area_m2`` [m^2] (default 400, about 20 m x 20 m), area measured in the grid CRS;
* or both.  Sites up to ``margin_m`` outside the grid are kept (default: the grid diagonal,
  so that the distance is exact whenever one site lies in the grid): they set the distance
  near the edges.

Distance and cost (:func:`landing_cost`)
----------------------------------------
``landing_distance_m`` [m]: horizontal distance from each cell centre to the nearest site,
by the exact Euclidean distance transform (:func:`scipy.ndimage.distance_transform_edt`,
``sampling`` = resolution) of the site raster, on a grid padded to hold every kept site.  A
site covers every cell it touches, so the distance is that to the nearest touched cell
centre: within ``resolution / sqrt(2)`` of the distance to the site geometry.

``landing_cost`` (dimensionless) ``beta_d = d / d_max`` with ``d_max`` the largest distance
in the grid (min-max normalisation, the minimum being 0 at the sites), as for the risk map
(see :mod:`skyroute.stages.risk`): ``integral of beta_d dl`` along a path is the landing
cost ``C_d`` [m] of seed 000 eq. (11).  With ``max_distance_m`` the scale is fixed instead:
``beta_d = min(d / max_distance_m, 1)``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rasterio.features
import shapely
import xarray as xr
from scipy.ndimage import distance_transform_edt
from shapely.geometry.base import BaseGeometry

from skyroute.stages.base import InputError
from skyroute.stages.figures import image_extent
from skyroute.stages.grid import Grid
from skyroute.stages.risk import (
    TagTable,
    _lonlat_bounds,
    load_tag_table,
    nofly_mask,
    read_geojson_lonlat,
    risk_cost,
    risk_from_geotiff,
    risk_levels,
    to_grid_crs,
)

DEFAULT_MIN_AREA_M2 = 400.0


@dataclass(frozen=True)
class LandingSite:
    """One landing site: ``geometry`` in the grid CRS [m], ``kind`` (helipad, heliport,
    park, ..., or ``scenario``), ``source`` (``osm:area/123``, ``geojson:<file>#3``)."""

    name: str
    kind: str
    source: str
    geometry: BaseGeometry
    area_m2: float

    @property
    def xy(self) -> tuple[float, float]:
        """A point inside the site (map coordinates [m]), for markers and labels."""
        p = self.geometry.representative_point() if self.geometry.area > 0 else self.geometry.centroid
        return (float(p.x), float(p.y))


@dataclass(frozen=True)
class LandingSites:
    """The landing sites of a grid (a sequence of :class:`LandingSite`) and ``mask``, the
    boolean raster of the cells they touch (inside the grid)."""

    sites: tuple[LandingSite, ...]
    mask: xr.DataArray

    def __len__(self) -> int:
        return len(self.sites)

    def __iter__(self) -> Iterator[LandingSite]:
        return iter(self.sites)

    def __getitem__(self, i: int) -> LandingSite:
        return self.sites[i]

    @property
    def geometries(self) -> list[BaseGeometry]:
        return [s.geometry for s in self.sites]

    def table(self) -> dict[str, np.ndarray]:
        """Columns ``name, kind, source, x, y, area_m2`` (GeoDataFrame-like, without geometry)."""
        xy = np.array([s.xy for s in self.sites]).reshape(-1, 2)
        return {"name": np.array([s.name for s in self.sites], dtype=str),
                "kind": np.array([s.kind for s in self.sites], dtype=str),
                "source": np.array([s.source for s in self.sites], dtype=str),
                "x": xy[:, 0], "y": xy[:, 1],
                "area_m2": np.array([s.area_m2 for s in self.sites], dtype=np.float64)}


def _match(tags: Mapping[str, str], rules: Mapping[str, tuple[str, ...]]) -> str | None:
    for key, values in rules.items():
        v = tags.get(key)
        if v is not None and (v in values or "*" in values):
            return v
    return None


def _burn_sites(grid: Grid, geoms: list[BaseGeometry]) -> np.ndarray:
    if not geoms:
        return np.zeros(grid.shape, bool)
    return rasterio.features.rasterize(((g, 1) for g in geoms), out_shape=grid.shape, transform=grid.transform,
                                       fill=0, dtype="uint8", all_touched=True).astype(bool)


def landing_sites(grid: Grid, osm_path: str | Path | None = None, geojson: str | Path | None = None,
                  min_area_m2: float = DEFAULT_MIN_AREA_M2,
                  tag_table: str | Path | Mapping | TagTable | None = None,
                  margin_m: float | None = None) -> LandingSites:
    """Landing sites from an OSM extract and/or a GeoJSON file (module docstring)."""
    if not min_area_m2 >= 0:
        raise InputError(f"min_area_m2 {min_area_m2} must be >= 0 [m^2] (default 400)")
    xmin, ymin, xmax, ymax = grid.bounds
    if margin_m is None:
        margin_m = float(np.hypot(xmax - xmin, ymax - ymin))
    if not margin_m >= 0:
        raise InputError(f"margin_m {margin_m} must be >= 0 [m]")
    if osm_path is None and geojson is None:
        raise InputError("no landing-site source: give osm_path (an OSM extract) and/or geojson (a file of sites)")
    near = shapely.box(xmin - margin_m, ymin - margin_m, xmax + margin_m, ymax + margin_m)
    sites: list[LandingSite] = []
    if geojson is not None:
        p = Path(geojson)
        feats = read_geojson_lonlat(p, "landing sites", allowed=("Point", "MultiPoint", "Polygon", "MultiPolygon"))
        geoms = to_grid_crs([g for g, _ in feats], 4326, grid)
        for i, (g, (_, props)) in enumerate(zip(geoms, feats, strict=True)):
            if g.intersects(near):
                sites.append(LandingSite(str(props.get("name", f"site {i}")), str(props.get("kind", "scenario")),
                                         f"geojson:{p.name}#{i}", g, float(g.area)))
    if osm_path is not None:
        from skyroute.stages.osm import read_osm

        table = load_tag_table(tag_table)
        keys = set(table.landing_any_size) | set(table.landing_open_ground)
        aoi = _lonlat_bounds(grid, margin_m)
        cand = [f for f in read_osm(osm_path, keys=sorted(keys))
                if f.kind in ("node", "area") and f.geometry.intersects(aoi)]
        geoms = to_grid_crs([f.geometry for f in cand], 4326, grid)
        for f, g in zip(cand, geoms, strict=True):
            kind = _match(f.tags, table.landing_any_size)
            if kind is None:
                kind = _match(f.tags, table.landing_open_ground)
                if kind is None or f.kind != "area" or g.area < min_area_m2:
                    continue
            if not g.intersects(near):
                continue
            sites.append(LandingSite(f.tags.get("name", f"{kind} {f.osm_id}"), kind, f"osm:{f.kind}/{f.osm_id}",
                                     g, float(g.area)))
    mask = grid.dataarray(_burn_sites(grid, [s.geometry for s in sites]), "landing_site", units="1",
                          long_name="cell touched by a landing site")
    return LandingSites(tuple(sites), mask)


def landing_cost(grid: Grid, sites: LandingSites | list[LandingSite],
                 max_distance_m: float | None = None) -> xr.Dataset:
    """``landing_distance_m`` [m] to the nearest site and the dimensionless ``landing_cost``.

    Raises :class:`InputError` when there is no site (add a GeoJSON of sites or enable OSM
    landing sites).
    """
    site_list = list(sites)
    if not site_list:
        raise InputError("no landing sites: give data.landing_sites (GeoJSON) or enable data.osm_landing_sites "
                         "with an OSM extract that has helipads or parks")
    if max_distance_m is not None and not max_distance_m > 0:
        raise InputError(f"max_distance_m {max_distance_m} must be > 0 [m]")
    r = grid.resolution_m
    xmin, ymin, xmax, ymax = grid.bounds
    sb = shapely.total_bounds(np.asarray([s.geometry for s in site_list], dtype=object))
    # pad by whole cells so that the padded grid stays aligned with the scenario grid
    pw = max(0, math.ceil((xmin - sb[0]) / r) + 1)
    pe = max(0, math.ceil((sb[2] - xmax) / r) + 1)
    ps = max(0, math.ceil((ymin - sb[1]) / r) + 1)
    pn = max(0, math.ceil((sb[3] - ymax) / r) + 1)
    big = Grid(grid.crs_wkt, grid.x0 - pw * r, grid.y1 + pn * r, grid.nx + pw + pe, grid.ny + pn + ps, r)
    site_mask = _burn_sites(big, [s.geometry for s in site_list])
    dist = distance_transform_edt(~site_mask, sampling=(r, r))[pn:pn + grid.ny, pw:pw + grid.nx]
    if max_distance_m is None:
        dmax = float(dist.max())
        beta = dist / dmax if dmax > 0 else np.zeros_like(dist)
        scale = dmax
    else:
        beta = np.minimum(dist / max_distance_m, 1.0)
        scale = float(max_distance_m)
    ds = xr.Dataset({
        "landing_distance_m": grid.dataarray(dist.astype(np.float32), "landing_distance_m", units="m",
                                             long_name="horizontal distance to the nearest landing site"),
        "landing_cost": grid.dataarray(beta.astype(np.float32), "landing_cost", units="1",
                                       long_name="dimensionless landing-site cost (integral along a path gives metres)",
                                       normalization="distance / max distance in the grid" if max_distance_m is None
                                       else "min(distance / max_distance_m, 1)", distance_scale_m=scale),
    })
    xy = np.array([s.xy for s in site_list])
    ds = ds.assign_coords(
        site_x=("site", xy[:, 0], {"units": "m", "long_name": "landing site marker x"}),
        site_y=("site", xy[:, 1], {"units": "m", "long_name": "landing site marker y"}),
        site_name=("site", np.array([s.name for s in site_list], dtype=str)),
        site_kind=("site", np.array([s.kind for s in site_list], dtype=str)),
    )
    ds.attrs["n_landing_sites"] = len(site_list)
    return ds


# --------------------------------------------------------------------------- combined
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
    ds = ds.rio.write_crs(grid.crs)
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
def plot_landing_cost(ds: xr.Dataset, ax=None):
    """Landing cost map with the sites marked (red asterisks, as seed 000 Fig. 1c)."""
    import matplotlib.pyplot as plt

    if ax is None:
        _, ax = plt.subplots(figsize=(6, 6))
    da = ds["landing_cost"]
    extent = image_extent(da)
    im = ax.imshow(da.values, cmap="viridis", vmin=0, vmax=1, extent=extent, origin="upper", interpolation="nearest")
    ax.figure.colorbar(im, ax=ax, shrink=0.8, label="landing cost [-]")
    if "site_x" in ds.coords and ds.sizes.get("site", 0):
        sx, sy = ds["site_x"].values, ds["site_y"].values
        inside = (sx >= extent[0]) & (sx <= extent[1]) & (sy >= extent[2]) & (sy <= extent[3])
        ax.plot(sx[inside], sy[inside], "*", color="red", markersize=8, linestyle="none", label="landing site")
        ax.legend(loc="lower right", fontsize=8)
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("landing-site cost")
    ax.set_aspect("equal")
    return ax


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
