"""Surface ingestion: buildings and terrain to a digital surface model on the scenario grid.

Output (:func:`build_surface`): an ``xarray.Dataset`` on the scenario :class:`~skyroute.stages.grid.Grid`
with

* ``terrain`` [m]: ground height in the scenario's vertical datum (flat 0 m when the scenario has
  no terrain source: heights are then above local ground);
* ``surface`` [m]: terrain + buildings (the top of every cell, modelled as a flat-topped prism);
* ``building_id``: index into the ``building`` dimension (``-1`` where there is no building),
  with per-building ``building_osm_id`` / ``building_height_m`` / ``building_height_source``.

Building heights
----------------
OSM: ``height`` (metres; "12 m", "40 ft" understood), else ``building:levels`` (+ ``roof:levels``)
times the storey height (default :data:`STOREY_HEIGHT_M` = 3.0 m, settable per scenario), else the
default for its ``building=*`` type in :data:`DEFAULT_HEIGHT_BY_TYPE_M` (generic ``yes``: 10 m).
``min_height`` / ``building:min_level`` are ignored: a bridge-like part is filled to the ground,
which is conservative for collision and occlusion.

CityJSON (1.0 / 1.1 / 2.0, LoD1 or LoD2, Building and BuildingPart): every non-vertical upper
surface (``RoofSurface``, or for LoD1 every face that is not the ground) is rasterised as a plane;
a cell takes the highest roof height at its four corners (clamped to the face's own z range), so
it is never lower than the roof over it.  Terrain comes from each building's ``TerrainHeight``
attribute (preferred: some LoD2 models put the ground surface at z = 0) or its ``GroundSurface``
heights, interpolated linearly between buildings.

Rasterisation: a cell belongs to a footprint when its centre is inside (OSM footprints with
:func:`rasterio.features.rasterize`, CityJSON roof faces with the compiled scanline fill
:func:`~skyroute.stages.grid.ring_cells`, identical cell for cell).

DEM and DSM rasters (``data.terrain``, ``data.surface``)
-------------------------------------------------------
Both are read by window at their native resolution (a GeoTIFF, a VRT or a list of tiles) and
resampled to the grid by the footprint max (:func:`~skyroute.stages.grid.footprint_resample`:
every source pixel overlapping the cell counts, in any CRS), never bilinearly: ``surface`` is
the highest point of the DSM over the cell (and of the buildings: surface = max of both);
``terrain`` the highest ground over the cell (minimum-AGL floors) and ``terrain_min`` the lowest
(maximum-AGL ceilings).  NoData: each connected region inside the extent takes the highest height
on its rim (DSM ``nodata: fill-max``, the default; ``fill-nearest``; ``error``); a DEM's holes take
the highest rim height for ``terrain`` and the lowest for ``terrain_min``; regions touching the
raster's edge are outside its extent, and AOI cells outside the extent are an error saying so.
A DSM without a DEM: the ground is the grey opening of the DSM (:func:`ground_from_dsm`, square
window ``ground_window_m``, default 60 m, wider than the largest building), said in the attrs
(``ground_source``) and as a stage warning; ``dsm_building`` marks cells whose every DSM pixel is
more than ``building_threshold_m`` (2.5 m) above it (with a DEM: the cell's lowest DSM point above
its highest ground point), which the risk map takes as roofs (level 3).
What a DSM cannot tell: tall vegetation (a tree canopy wider than a cell) from a roof; a building
wider than the window from ground (its roof becomes ground: AGL floors relative to the roof, higher
and safe; AGL ceilings also relative to the roof, too high by the building's height).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rasterio
import rasterio.features
import rasterio.warp
import shapely
import xarray as xr
from pyproj import CRS, Transformer
from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator

from skyroute.pipeline.errors import DataError, InputError
from skyroute.stages.grid import (
    NODATA_POLICIES,
    Grid,
    coverage_problem,
    fill_holes,
    footprint_resample,
    read_window_holes,
    ring_cells,
)
from skyroute.stages.osm import read_osm

STOREY_HEIGHT_M = 3.0
#: Default building height [m] by OSM ``building=*`` value when neither height nor levels are tagged.
DEFAULT_HEIGHT_BY_TYPE_M: dict[str, float] = {
    "yes": 10.0, "apartments": 18.0, "residential": 15.0, "house": 7.0, "detached": 7.0,
    "terrace": 9.0, "commercial": 15.0, "office": 18.0, "retail": 12.0, "public": 15.0,
    "civic": 15.0, "government": 15.0, "hotel": 18.0, "hospital": 20.0, "school": 12.0,
    "university": 15.0, "church": 20.0, "cathedral": 30.0, "chapel": 8.0, "train_station": 15.0,
    "transportation": 10.0, "industrial": 10.0, "warehouse": 8.0, "garage": 3.0, "garages": 3.0,
    "shed": 3.0, "hut": 3.0, "kiosk": 3.0, "roof": 5.0, "service": 4.0, "construction": 10.0,
}
_NUM = re.compile(r"^\s*([0-9]*[.,]?[0-9]+)\s*(m|metres|meters|ft|feet|')?\s*$", re.IGNORECASE)


def parse_height_m(text: str) -> float | None:
    """A height tag in metres: ``"12"``, ``"12.5 m"``, ``"40 ft"``; None if unparsable."""
    m = _NUM.match(text or "")
    if not m:
        return None
    v = float(m.group(1).replace(",", "."))
    unit = (m.group(2) or "m").lower()
    return v * 0.3048 if unit in ("ft", "feet", "'") else v


def osm_building_height(tags: dict[str, str], storey_height_m: float = STOREY_HEIGHT_M) -> tuple[float, str]:
    """(height [m], source) of an OSM building from its tags (see module docstring)."""
    h = parse_height_m(tags.get("height", "")) if "height" in tags else None
    if h is not None and h > 0:
        return h, "height"
    lv = parse_height_m(tags.get("building:levels", "")) if "building:levels" in tags else None
    if lv is not None and lv > 0:
        roof = parse_height_m(tags.get("roof:levels", "")) or 0.0
        return (lv + roof) * storey_height_m, "levels"
    btype = tags.get("building", tags.get("building:part", "yes"))
    return DEFAULT_HEIGHT_BY_TYPE_M.get(btype, DEFAULT_HEIGHT_BY_TYPE_M["yes"]), f"default:{btype}"


@dataclass(frozen=True)
class BuildingRaster:
    """Rasterised buildings: ``top`` [m] (NaN where none), ``index`` (-1 where none) and a table."""

    top: np.ndarray
    index: np.ndarray
    ids: np.ndarray
    heights_m: np.ndarray
    sources: np.ndarray
    absolute: bool  # True: ``top`` is an absolute height; False: height above ground


def _to_grid_geoms(geoms, src_crs: CRS, grid: Grid):
    if CRS.from_user_input(src_crs) == grid.crs:
        return geoms
    t = Transformer.from_crs(src_crs, grid.crs, always_xy=True)
    return [shapely.transform(g, lambda xy: np.column_stack(t.transform(xy[:, 0], xy[:, 1]))) for g in geoms]


def osm_buildings(path: str | Path, grid: Grid, storey_height_m: float = STOREY_HEIGHT_M) -> BuildingRaster:
    """Rasterise the building footprints of an OSM extract with their heights above ground."""
    feats = [f for f in read_osm(path, keys=["building", "building:part"]) if f.kind == "area"]
    xmin, ymin, xmax, ymax = grid.bounds
    ids, hs, srcs, geoms = [], [], [], []
    for f in feats:
        h, src = osm_building_height(f.tags, storey_height_m)
        ids.append(f.osm_id)
        hs.append(h)
        srcs.append(src)
        geoms.append(f.geometry)
    geoms = _to_grid_geoms(geoms, CRS.from_epsg(4326), grid)
    keep = [i for i, g in enumerate(geoms) if g.intersects(shapely.box(xmin, ymin, xmax, ymax))]
    return _rasterize_flat(grid, [geoms[i] for i in keep], np.array(hs)[keep] if keep else np.zeros(0),
                           np.array(ids, dtype=np.int64)[keep] if keep else np.zeros(0, np.int64),
                           np.array(srcs, dtype=object)[keep] if keep else np.zeros(0, object), absolute=False)


def _rasterize_flat(grid: Grid, geoms, heights, ids, sources, absolute: bool) -> BuildingRaster:
    order = np.argsort(heights, kind="stable")  # highest last, so it wins where footprints overlap
    top = np.full(grid.shape, np.nan, dtype=np.float64)
    index = np.full(grid.shape, -1, dtype=np.int32)
    if len(order):
        index = rasterio.features.rasterize(
            ((geoms[i], int(i)) for i in order), out_shape=grid.shape, transform=grid.transform,
            fill=-1, dtype="int32",
        )
        has = index >= 0
        top[has] = np.asarray(heights, dtype=np.float64)[index[has]]
    return BuildingRaster(top, index, np.asarray(ids, np.int64), np.asarray(heights, np.float64),
                          np.asarray(sources, dtype=object).astype(str), absolute)


# --------------------------------------------------------------------------- CityJSON
def _read_cityjson(path: Path) -> dict:
    if not path.is_file():
        raise DataError(f"CityJSON file not found: {path}")
    try:
        cj = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"{path} is not valid CityJSON (JSON error: {exc})") from exc
    if cj.get("type") != "CityJSON" or "vertices" not in cj or "CityObjects" not in cj:
        raise DataError(f"{path} is not a CityJSON file (needs type, vertices, CityObjects)")
    return cj


def cityjson_crs(cj: dict) -> CRS:
    """The horizontal CRS of a CityJSON document (``metadata.referenceSystem``)."""
    ref = (cj.get("metadata") or {}).get("referenceSystem")
    if not ref:
        raise DataError("CityJSON has no metadata.referenceSystem; set aoi.crs to the file's CRS")
    m = re.search(r"EPSG[:/]+(?:[0-9.]*/)?(?:0/)?:?(\d+)", str(ref))
    if not m:
        raise DataError(f"cannot read the CityJSON referenceSystem {ref!r}")
    crs = CRS.from_epsg(int(m.group(1)))
    return crs.sub_crs_list[0] if crs.is_compound else crs


def _surfaces(geom: dict):
    """Yield (ring vertex indices of the outer ring, semantic type or None) of a CityJSON geometry."""
    gtype = geom["type"]
    b = geom["boundaries"]
    sem = geom.get("semantics") or {}
    stypes = [s.get("type") for s in sem.get("surfaces", [])]
    values = sem.get("values")
    if gtype in ("MultiSurface", "CompositeSurface"):
        polys = [(p, (values[i] if values is not None else None)) for i, p in enumerate(b)]
    elif gtype == "Solid":
        polys = []
        for si, shell in enumerate(b):
            for pi, p in enumerate(shell):
                v = values[si][pi] if values is not None else None
                polys.append((p, v))
    elif gtype in ("MultiSolid", "CompositeSolid"):
        polys = []
        for so_i, solid in enumerate(b):
            for si, shell in enumerate(solid):
                for pi, p in enumerate(shell):
                    v = values[so_i][si][pi] if values is not None else None
                    polys.append((p, v))
    else:
        return
    for p, v in polys:
        yield p[0], (stypes[v] if (v is not None and v < len(stypes)) else None)


def cityjson_buildings(path: str | Path, grid: Grid) -> tuple[BuildingRaster, np.ndarray]:
    """Rasterise CityJSON Building/BuildingPart roofs (absolute heights [m]) on ``grid``.

    Returns the raster and ground points ``(n, 3)`` (x, y, z in the grid CRS) for terrain.
    """
    p = Path(path)
    cj = _read_cityjson(p)
    tr = cj.get("transform") or {"scale": [1, 1, 1], "translate": [0, 0, 0]}
    V = np.asarray(cj["vertices"], dtype=np.float64) * np.asarray(tr["scale"]) + np.asarray(tr["translate"])
    src = cityjson_crs(cj)
    if src != grid.crs:
        t = Transformer.from_crs(src, grid.crs, always_xy=True)
        V[:, 0], V[:, 1] = t.transform(V[:, 0], V[:, 1])
    objs = cj["CityObjects"]
    r = grid.resolution_m
    top = np.full(grid.shape, -np.inf)
    index = np.full(grid.shape, -1, dtype=np.int32)
    ids: list[str] = []
    heights: list[float] = []
    ground: list[np.ndarray] = []
    roof_rings: list[np.ndarray] = []
    roof_normals: list[np.ndarray] = []
    roof_owner: list[int] = []
    for oid, obj in objs.items():
        if obj.get("type") not in ("Building", "BuildingPart"):
            continue
        geoms = obj.get("geometry") or []
        if not geoms:
            continue
        g = max(geoms, key=lambda gg: float(gg.get("lod", 0)))
        bidx = len(ids)
        ids.append(oid)
        roofs, floor_pts = [], []
        for ring, stype in _surfaces(g):
            P = V[np.asarray(ring)]
            if len(P) < 3:
                continue
            nrm = np.zeros(3)  # Newell normal
            for i in range(len(P)):
                a, b = P[i], P[(i + 1) % len(P)]
                nrm += [(a[1] - b[1]) * (a[2] + b[2]), (a[2] - b[2]) * (a[0] + b[0]), (a[0] - b[0]) * (a[1] + b[1])]
            nn = np.linalg.norm(nrm)
            if nn == 0:
                continue
            nrm /= nn
            if stype == "GroundSurface" or (stype is None and nrm[2] < -0.5):
                floor_pts.append(P)
                continue
            if stype in ("WallSurface", "ClosureSurface") or abs(nrm[2]) < 1e-3:
                continue
            if stype is None or stype in ("RoofSurface", "OuterCeilingSurface", "OuterFloorSurface"):
                if nrm[2] > 0 or stype is not None:
                    roofs.append((P, nrm))
        zmax_b = max((float(P[:, 2].max()) for P, _ in roofs), default=np.nan)
        heights.append(zmax_b)
        th = (obj.get("attributes") or {}).get("TerrainHeight")
        if th is not None and (roofs or floor_pts):
            P = np.vstack([pp for pp, _ in roofs] + floor_pts)
            ground.append(np.column_stack([P[:, 0], P[:, 1], np.full(len(P), float(th))]))
        elif floor_pts:
            ground.append(np.vstack(floor_pts))
        for P, nrm in roofs:
            roof_rings.append(P)
            roof_normals.append(nrm)
            roof_owner.append(bidx)
    # every roof face at once: cells whose centre is inside (compiled scanline fill), the face's
    # plane at the cell's four corners, the highest value per cell (clamped to the face's z range)
    if roof_rings:
        lengths = np.array([len(P) for P in roof_rings])
        offsets = np.concatenate([[0], np.cumsum(lengths)])
        allP = np.vstack(roof_rings)
        ring, rr, cc = ring_cells(allP[:, 0], allP[:, 1], offsets, grid)
        P0 = np.array([P[0] for P in roof_rings])[ring]
        N = np.array(roof_normals)[ring]
        zlo = np.array([P[:, 2].min() for P in roof_rings])[ring]
        zhi = np.array([P[:, 2].max() for P in roof_rings])[ring]
        xc = grid.x0 + (cc + 0.5) * r
        yc = grid.y1 - (rr + 0.5) * r
        zc = np.full(xc.shape, -np.inf)
        for dx in (-r / 2, r / 2):
            for dy in (-r / 2, r / 2):
                z = P0[:, 2] - (N[:, 0] * (xc + dx - P0[:, 0]) + N[:, 1] * (yc + dy - P0[:, 1])) / N[:, 2]
                zc = np.maximum(zc, z)
        zc = np.clip(zc, zlo, zhi)
        cell = rr * grid.nx + cc
        order = np.lexsort((zc, cell))  # by cell, then height: the last of each cell is its max
        last = np.r_[cell[order][1:] != cell[order][:-1], True]
        sel = order[last]
        top.ravel()[cell[sel]] = zc[sel]
        index.ravel()[cell[sel]] = np.asarray(roof_owner)[ring[sel]]
    top[~np.isfinite(top)] = np.nan
    gpts = np.vstack(ground) if ground else np.zeros((0, 3))
    raster = BuildingRaster(top, index, np.arange(len(ids), dtype=np.int64), np.asarray(heights, np.float64),
                            np.asarray(["cityjson:" + i for i in ids]), absolute=True)
    return raster, gpts


def terrain_from_points(points: np.ndarray, grid: Grid) -> np.ndarray:
    """Terrain [m] interpolated linearly from scattered ground points, nearest outside their hull."""
    if len(points) < 3:
        return np.zeros(grid.shape)
    # thin to one point per cell to keep the triangulation small
    row, col = grid.index_of(points[:, 0], points[:, 1])
    key = row * (grid.nx + 1) + col
    _, first = np.unique(key, return_index=True)
    pts = points[first]
    X, Y = np.meshgrid(grid.x, grid.y)
    lin = LinearNDInterpolator(pts[:, :2], pts[:, 2])(X, Y)
    near = NearestNDInterpolator(pts[:, :2], pts[:, 2])(X, Y)
    return np.where(np.isfinite(lin), lin, near)


def terrain_from_dem(path: str | Path | list, grid: Grid, *, key: str = "data.terrain") -> tuple[np.ndarray, np.ndarray]:
    """A DEM (GeoTIFF, VRT or list of tiles) on ``grid`` [m] as two bounds of the ground over
    each cell: ``(max, min)`` over every DEM pixel overlapping the cell's footprint
    (:func:`~skyroute.stages.grid.footprint_resample`; the max for minimum-AGL floors, the min
    for maximum-AGL ceilings).  NoData holes inside the DEM's extent take the highest (for the
    max) / lowest (for the min) valid height on their rim; AOI cells outside the extent are an
    error that says so (``key`` names the scenario entry)."""
    win, holes = read_window_holes(path, grid, what="terrain")
    msg = coverage_problem(win, holes, grid, what="terrain DEM", key=key)
    if msg:
        raise DataError(msg)
    hi = footprint_resample(fill_holes(win, holes, "fill-max"), win.transform, win.crs, grid, "max")
    lo = footprint_resample(fill_holes(win, holes, "fill-min"), win.transform, win.crs, grid, "min")
    return hi, lo


#: Default side [m] of the square window of the grey opening that derives the ground from a DSM.
GROUND_WINDOW_M = 60.0
#: Default height [m] above the ground from which a DSM cell counts as a building (risk level 3).
BUILDING_THRESHOLD_M = 2.5


@dataclass(frozen=True)
class DsmRaster:
    """A DSM on the grid: ``surface`` (footprint max) [m]; ``ground`` / ``ground_min`` (footprint
    max / min of the derived ground, None when not derived); ``building`` (every point of the cell
    higher than ground + threshold); ``n_holes`` filled; ``notes`` for the attrs."""

    surface: np.ndarray
    surface_min: np.ndarray
    ground: np.ndarray | None
    ground_min: np.ndarray | None
    building: np.ndarray | None
    n_holes: int
    notes: str


def ground_from_dsm(dsm: np.ndarray, pixel_m: float, window_m: float = GROUND_WINDOW_M) -> np.ndarray:
    """Bare ground [m] under a DSM (square pixels of ``pixel_m`` [m]; NaN pixels take no part and
    stay NaN): the grey opening (erosion then dilation, :func:`scipy.ndimage.grey_erosion` /
    ``grey_dilation``) with a square window of side ``window_m`` [m] (odd number of pixels).  Every object narrower than the window in some
    direction (buildings, trees, masts) is removed; the result is never above the DSM.  Buildings
    wider than the window stay (their roof is taken as ground), hill tops and ridges narrower than
    the window are lowered by the opening."""
    if not (np.isfinite(window_m) and window_m > 0):
        raise InputError(f"ground window {window_m} m must be positive (wider than the largest building)")
    k = int(np.ceil(window_m / pixel_m)) | 1
    from scipy.ndimage import grey_dilation, grey_erosion

    # NaN (outside the extent) takes no part: +inf in the erosion (min), -inf in the dilation (max)
    nan = np.isnan(dsm)
    ero = grey_erosion(np.where(nan, np.inf, dsm), size=(k, k), mode="nearest")
    ero[nan] = -np.inf
    out = grey_dilation(ero, size=(k, k), mode="nearest")
    out[nan] = np.nan
    return out


def dsm_on_grid(path, grid: Grid, *, nodata: str = "fill-max", derive_ground: bool = True,
                ground_window_m: float = GROUND_WINDOW_M, building_threshold_m: float = BUILDING_THRESHOLD_M,
                key: str = "data.surface") -> DsmRaster:
    """A DSM (GeoTIFF, VRT or list of tiles, read by window at its native resolution) on ``grid``:
    NoData holes inside the extent follow ``nodata`` (``fill-max``: each connected hole the
    highest valid height on its rim; ``fill-nearest``; ``error``), then the max over every cell's
    footprint; with ``derive_ground`` also the ground (:func:`ground_from_dsm`, then footprint max
    and min) and the building mask (cells all of whose DSM pixels are more than
    ``building_threshold_m`` above the derived ground); ``surface_min``: the DSM's footprint min."""
    if nodata not in NODATA_POLICIES:
        raise InputError(f"{key}.nodata: {nodata!r} is not one of {', '.join(NODATA_POLICIES)}")
    win, holes = read_window_holes(path, grid, what="surface DSM")
    msg = coverage_problem(win, holes, grid, what="surface DSM", key=key, holes_allowed=nodata != "error")
    if msg:
        raise DataError(msg)
    filled = fill_holes(win, holes, nodata if nodata != "error" else "fill-max")
    surface = footprint_resample(filled, win.transform, win.crs, grid, "max")
    surface_min = footprint_resample(filled, win.transform, win.crs, grid, "min")
    notes = f"NoData holes inside the extent: {holes.n_interior} ({nodata})"
    if not derive_ground:
        return DsmRaster(surface, surface_min, None, None, None, holes.n_interior, notes)
    px = abs(win.transform.a)
    ok = np.isfinite(filled)
    g_src = ground_from_dsm(filled, px, ground_window_m)
    ground = footprint_resample(g_src, win.transform, win.crs, grid, "max")
    ground_min = footprint_resample(g_src, win.transform, win.crs, grid, "min")
    high = np.where(ok, (filled - g_src > building_threshold_m).astype(np.float64), np.nan)
    building = footprint_resample(high, win.transform, win.crs, grid, "min") > 0.5
    notes += (f"; ground derived from the DSM by a grey opening with a {ground_window_m:g} m square window "
              f"({int(np.ceil(ground_window_m / px)) | 1} px of {px:g} m); buildings: more than "
              f"{building_threshold_m:g} m above it over the whole cell (tall vegetation is not told apart)")
    return DsmRaster(surface, surface_min, ground, ground_min, building, holes.n_interior, notes)


def build_surface(grid: Grid, *, buildings_path=None, buildings_format: str | None = None,
                  storey_height_m: float = STOREY_HEIGHT_M, terrain_path=None,
                  vertical_datum: str | None = None, surface_path=None, surface_datum: str | None = None,
                  surface_nodata: str = "fill-max", ground_window_m: float = GROUND_WINDOW_M,
                  building_threshold_m: float = BUILDING_THRESHOLD_M) -> xr.Dataset:
    """Digital surface model of ``grid`` from buildings (OSM or CityJSON), terrain (a DEM) and/or
    a DSM (``surface_path``: GeoTIFF, VRT or list of tiles; heights in ``surface_datum``).

    Returns a Dataset with ``terrain`` (ground: max over the cell), ``terrain_min`` (ground: min
    over the cell), ``surface`` (max of the DSM and the buildings over the cell), ``building_id``
    and a building table; with a DSM also ``dsm_building``.  Ground: the DEM if given, else the
    DSM's ground (:func:`ground_from_dsm`; said in the attrs and in ``warnings``), else CityJSON
    ground points, else flat 0 m.  See the module docstring for the rules and the vertical datum.
    """
    if buildings_format not in (None, "osm", "cityjson"):
        raise InputError(f"unknown buildings format {buildings_format!r}; use 'osm' or 'cityjson'")
    if (surface_path is not None and terrain_path is not None and vertical_datum and surface_datum
            and vertical_datum.strip().lower() != surface_datum.strip().lower()):
        raise InputError(f"data.surface.vertical_datum {surface_datum!r} differs from data.terrain.vertical_datum "
                         f"{vertical_datum!r}: convert one of them so both heights are in one datum")
    if surface_path is not None and not surface_datum:
        raise InputError("data.surface.vertical_datum is required (e.g. 'NAP', 'EGM96 geoid', 'EGM2008')")
    ground_pts = np.zeros((0, 3))
    braster = None
    if buildings_path is not None:
        if buildings_format == "cityjson":
            braster, ground_pts = cityjson_buildings(buildings_path, grid)
        else:
            braster = osm_buildings(buildings_path, grid, storey_height_m)
        if braster.index.max() < 0:
            raise DataError(f"the AOI does not intersect any building of {buildings_path}; check aoi.bounds")
    dsm = None
    if surface_path is not None:
        dsm = dsm_on_grid(surface_path, grid, nodata=surface_nodata, derive_ground=terrain_path is None,
                          ground_window_m=ground_window_m, building_threshold_m=building_threshold_m)
    warns: list[str] = []
    if terrain_path is not None:
        terrain, terrain_min = terrain_from_dem(terrain_path, grid)
        datum = vertical_datum or "EGM96 geoid"
        ground_src = "DEM (data.terrain), max / min over each cell"
    elif dsm is not None:
        terrain, terrain_min = dsm.ground, dsm.ground_min
        datum = surface_datum
        ground_src = dsm.notes.split("; ", 1)[1]
        warns.append(f"surface: no DEM (data.terrain): the ground is derived from the DSM by a grey opening with a "
                     f"{ground_window_m:g} m window; AGL limits, landing and the risk map's buildings use it; "
                     "give data.terrain for a surveyed ground")
    elif len(ground_pts):
        terrain = terrain_from_points(ground_pts, grid)
        terrain_min = terrain
        datum = vertical_datum or "source data heights (CityJSON; NAP for Dutch data)"
        ground_src = "CityJSON ground points, interpolated"
    else:
        terrain = np.zeros(grid.shape)
        terrain_min = terrain
        datum = vertical_datum or "local ground (flat terrain, heights above ground level)"
        ground_src = "flat 0 m"
    surface = terrain.copy()
    if braster is not None:
        has = braster.index >= 0
        top = braster.top if braster.absolute else terrain + braster.top
        surface[has] = np.maximum(terrain[has], top[has])
    if dsm is not None:
        surface = np.maximum(surface, dsm.surface)
    zattrs = {"units": "m", "vertical_datum": datum}
    ds = xr.Dataset({
        "terrain": grid.dataarray(terrain.astype(np.float32), "terrain",
                                  long_name="ground height (highest over the cell)", **zattrs),
        "terrain_min": grid.dataarray(terrain_min.astype(np.float32), "terrain_min",
                                      long_name="ground height (lowest over the cell)", **zattrs),
        "surface": grid.dataarray(surface.astype(np.float32), "surface",
                                  long_name="top of terrain and buildings (flat-topped prism per cell)", **zattrs),
        "building_id": grid.dataarray(
            (braster.index if braster is not None else np.full(grid.shape, -1, np.int32)).astype(np.int32),
            "building_id", units="1", long_name="index into the building dimension, -1 where no building"),
    })
    if dsm is not None:
        # with a DEM: the lowest DSM point of the cell above its highest ground point
        building = dsm.building if dsm.building is not None else dsm.surface_min - terrain > building_threshold_m
        ds["dsm_building"] = grid.dataarray(
            building, "dsm_building", units="1",
            long_name=f"DSM more than {building_threshold_m:g} m above the ground over the whole cell")
    if braster is not None:
        ds["building_osm_id"] = ("building", braster.ids, {"units": "1", "long_name": "OSM id (or CityJSON index)"})
        ds["building_height_m"] = ("building", braster.heights_m.astype(np.float32),
                                   {"units": "m", "long_name": "building height (above ground for OSM, absolute roof top for CityJSON)"})
        ds["building_height_source"] = ("building", braster.sources.astype("U32"))
    ds.attrs.update({"title": "skyroute surface model", "vertical_datum": datum,
                     "resolution_m": grid.resolution_m, "Conventions": "CF-1.10", "ground_source": ground_src})
    if dsm is not None:
        ds.attrs["dsm"] = dsm.notes
    if warns:
        ds.attrs["warnings"] = json.dumps(warns)
    return ds
