"""Landing sites and the landing-distance cost map (the combined environment dataset is
:mod:`skyroute.stages.environment`).

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

A city without any (a user's DSM or CityJSON): :func:`open_ground_sites` derives candidate
sites from the maps (no obstacle within the vehicle's radius, not no-fly, the lowest risk level
present, one per 100 m block) for ``skyroute fleet --missions``, which says so.

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
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

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
    load_tag_table,
    lonlat_bounds,
    read_geojson_lonlat,
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
        aoi = lonlat_bounds(grid, margin_m)
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


#: Side [m] of the blocks in which :func:`open_ground_sites` keeps one candidate site.
OPEN_GROUND_SPACING_M = 100.0
#: A cell is open ground when its clearance floor is at most this [m] above terrain + r_p.
OPEN_GROUND_TOLERANCE_M = 0.5


def open_ground_sites(*, terrain: np.ndarray, surface: np.ndarray, obstacle_floor: np.ndarray,
                      risk_level: np.ndarray, nofly: np.ndarray, grid: Grid, radius_m: float,
                      spacing_m: float = OPEN_GROUND_SPACING_M, max_level: int = 4
                      ) -> tuple[np.ndarray, np.ndarray, int | None]:
    """Candidate landing sites derived from open ground, for a city without any (``skyroute
    fleet --missions``): cells not no-fly, with nothing on them (``surface <= terrain``) and no
    obstacle within the vehicle's radius ``radius_m`` [m] (the clearance floor at most
    :data:`OPEN_GROUND_TOLERANCE_M` above ``terrain + radius_m``), at the lowest risk level
    present among them (<= ``max_level``: parks and open land before industrial ground before
    streets; never critical or forbidden sites); in each ``spacing_m`` block the one whose
    floor is lowest above its ground.  Returns ``(x, y, level)`` [m] (map coordinates of the
    cell centres; ``level`` None when no cell qualifies)."""
    open_ = (~np.asarray(nofly, bool) & np.isfinite(obstacle_floor)
             & (np.asarray(surface) <= np.asarray(terrain) + 1e-6)
             & (np.asarray(obstacle_floor) <= np.asarray(terrain) + radius_m + OPEN_GROUND_TOLERANCE_M)
             & (np.asarray(risk_level) <= max_level))
    if not open_.any():
        return np.zeros(0), np.zeros(0), None
    level = int(np.asarray(risk_level)[open_].min())
    ok = open_ & (np.asarray(risk_level) == level)
    rows, cols = np.nonzero(ok)
    margin = (np.asarray(obstacle_floor) - np.asarray(terrain))[rows, cols]
    k = max(int(round(spacing_m / grid.resolution_m)), 1)
    block = (rows // k) * (grid.nx // k + 1) + cols // k
    order = np.lexsort((cols, rows, margin, block))
    first = order[np.r_[True, np.diff(block[order]) != 0]]
    return grid.x[cols[first]], grid.y[rows[first]], level


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
