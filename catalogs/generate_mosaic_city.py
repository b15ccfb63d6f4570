"""Generate the SYNTHETIC benchmark city of issue 23: a seeded mosaic of translated real Helsinki blocks.

No real building data of 20 x 20 km can be fetched on this machine, so the benchmark city is built
from the real footprints shipped with skyroute (``catalogs/data/helsinki_center.osm.pbf``, about
1.06 x 1.69 km of central Helsinki): the city is cut into square tiles (``--tile-m``, default
250 m); each tile receives a copy of a real source block of the same size, chosen at random (seeded)
inside the extract and translated (never rotated or scaled) onto the tile, with

* its buildings, whole, with their heights (:func:`skyroute.stages.surface.osm_building_footprints`,
  the project's one reading of OSM building heights: ``height``, else levels x 3 m, else the
  default of the building type); a building belongs to the block holding its representative point,
  so a building near a block edge may overhang the neighbouring tile (the higher roof wins there);
* its land use, clipped to the block: every OSM area or node whose tags give a ground-risk level
  or a landing site in ``catalogs/risk_tags.yaml`` (parks, grass, water, scrub, schools, ...).

A share ``--green-share`` (default 0.12) of the tiles takes its block from the greenest source
blocks (real parks and open ground: at least half of the block green land use), so the mosaic has
parks and open ground from the real land use.  THE RESULT IS NOT A REAL CITY: it is a SYNTHETIC
mosaic of translated real Helsinki blocks; every file says so (GeoTIFF tags, the OSM file's header,
``mosaic.json``) and so does the scenario that uses it.

Output (OUTDIR), files the ordinary scenario keys read:

``mosaic_dsm.tif``
    ``data.surface``: float32 GeoTIFF, one pixel per grid cell (``--resolution-m``, default 2 m)
    in EPSG:32635 (UTM 35N, Helsinki's zone); height = ground + the highest translated building
    whose footprint touches the cell's closed square (:func:`skyroute.stages.surface.polygon_max`,
    the surface stage's own rasteriser), the ground elsewhere.  Heights in the EGM96 geoid.
``mosaic_dem.tif``
    ``data.terrain``: the flat ground (``--ground-m``, default 3.5 m EGM96: the ground height of
    the shipped Helsinki scenarios) on 100 m pixels reaching 200 m beyond the city.
``mosaic_landuse.osm.pbf``
    ``data.landuse``: the translated land-use areas and nodes (and the translated buildings, so
    critical buildings such as schools keep their level) as an OSM file, lon/lat WGS 84; every
    feature carries the tag ``skyroute:nature`` and the file's ``generator`` header the statement.
``mosaic.json``
    what was generated: seed, sizes, the source block of every tile, counts, the nature statement.

The DSM is written window by window (2048 x 2048 cells) with rasterio, each window rasterising only
the buildings that reach it; the translated features are held as vectors (20 km: 130 k buildings,
69 k land-use features, 28 s and 1.2 GB peak on this machine).

Run::

    python -m skyroute.catalogs.generate_mosaic_city OUTDIR --side-km 20 --seed 0

The same seed and sizes give byte-identical rasters (``tests/test_mosaic_city.py``).
Data (c) OpenStreetMap contributors, ODbL 1.0.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import shapely

NATURE = ("SYNTHETIC mosaic of translated real Helsinki blocks, not a real city: OSM buildings (with their "
          "heights) and land use of catalogs/data/helsinki_center.osm.pbf, copied block by block onto a "
          "seeded mosaic (generator: skyroute.catalogs.generate_mosaic_city)")
CRS_EPSG = 32635
#: South-west corner of the mosaic [m] in EPSG:32635: around Helsinki (the GNSS sky, the GFS wind and
#: the UTM zone are Helsinki's), the real coastline is ignored.
ORIGIN_XY_M = (376000.0, 6662000.0)
SOURCE_PBF = Path(__file__).parent / "data" / "helsinki_center.osm.pbf"
DEM_PIXEL_M = 100.0
DEM_MARGIN_M = 200.0


@dataclass(frozen=True)
class Source:
    """The real source features in EPSG:32635 [m]."""

    buildings: np.ndarray        # shapely polygons
    heights_m: np.ndarray        # above ground [m]
    building_tags: list          # OSM tags of each building
    rep_xy: np.ndarray           # (n, 2) representative point of each building
    extras: np.ndarray           # shapely areas / points with a risk level or a landing tag
    extra_tags: list
    bounds: tuple                # the extract's buildings' bounding box [m]


def _to_utm(geoms):
    from pyproj import Transformer

    t = Transformer.from_crs(4326, CRS_EPSG, always_xy=True)
    return shapely.transform(np.asarray(geoms, dtype=object),
                             lambda xy: np.column_stack(t.transform(xy[:, 0], xy[:, 1])))


def read_source(path: str | Path = SOURCE_PBF, storey_height_m: float = 3.0) -> Source:
    """The buildings (with heights) and the land use of the shipped Helsinki extract, in UTM 35N."""
    from skyroute.stages.osm import read_osm
    from skyroute.stages.risk import load_tag_table
    from skyroute.stages.surface import osm_building_footprints

    ids, hs, _srcs, geoms = osm_building_footprints(path, storey_height_m)
    tags_by_id = {f.osm_id: f.tags for f in read_osm(path, keys=["building", "building:part"]) if f.kind == "area"}
    b = _to_utm(geoms)
    ok = np.array([g.geom_type in ("Polygon", "MultiPolygon") and not g.is_empty for g in b], bool)
    b = b[ok]
    hs = np.asarray(hs, float)[ok]
    btags = [tags_by_id[i] for i, k in zip(ids, ok, strict=True) if k]
    table = load_tag_table(None)
    keys = {*table.osm, *table.landing_any_size, *table.landing_open_ground}
    extras, etags = [], []
    for f in read_osm(path, keys=sorted(keys)):
        if f.kind not in ("area", "node") or "building" in f.tags or "building:part" in f.tags:
            continue
        if table.osm_level(f.tags) is None and not _landing(table, f.tags):
            continue
        extras.append(f.geometry)
        etags.append(f.tags)
    rep = shapely.get_coordinates(shapely.point_on_surface(b))
    bx = shapely.bounds(b)
    return Source(b, hs, btags, rep, _to_utm(extras), etags,
                  (float(bx[:, 0].min()), float(bx[:, 1].min()), float(bx[:, 2].max()), float(bx[:, 3].max())))


def _landing(table, tags) -> bool:
    for sect in (table.landing_any_size, table.landing_open_ground):
        for k, vals in sect.items():
            if tags.get(k) in vals:
                return True
    return False


_GREEN = {("leisure", "park"), ("leisure", "garden"), ("leisure", "pitch"), ("landuse", "grass"),
          ("landuse", "meadow"), ("landuse", "recreation_ground"), ("natural", "scrub"), ("natural", "heath"),
          ("natural", "grassland"), ("natural", "wood"), ("landuse", "forest"), ("natural", "water"),
          ("landuse", "basin"), ("landuse", "village_green")}


def source_blocks(src: Source, tile_m: float, res_m: float, green_share_min: float = 0.5):
    """Candidate source blocks (south-west corners [m], on the ``res_m`` lattice, every 50 m) inside the
    extract, and which of them are green (real parks / open ground cover ``green_share_min`` of them
    and no building stands in them)."""
    xmin, ymin, xmax, ymax = src.bounds
    step = 50.0
    xs = np.floor(np.arange(xmin, xmax - tile_m, step) / res_m) * res_m
    ys = np.floor(np.arange(ymin, ymax - tile_m, step) / res_m) * res_m
    corners = np.array([(x, y) for y in ys for x in xs], float)
    green = [g for g, t in zip(src.extras, src.extra_tags, strict=True)
             if any((k, t.get(k)) in _GREEN for k, _ in _GREEN) and g.geom_type in ("Polygon", "MultiPolygon")]
    gu = shapely.union_all(np.asarray(green, dtype=object)) if green else shapely.Polygon()
    share = np.array([shapely.box(x, y, x + tile_m, y + tile_m).intersection(gu).area / tile_m ** 2
                      for x, y in corners])
    return corners, share >= green_share_min


def tile_plan(n_tiles: int, corners: np.ndarray, is_green: np.ndarray, green_share: float, seed: int):
    """Per tile (row-major from the south-west) the index of its source block (seeded)."""
    rng = np.random.default_rng(seed)
    greens = np.flatnonzero(is_green)
    pick_green = rng.random(n_tiles) < green_share if len(greens) else np.zeros(n_tiles, bool)
    out = rng.integers(0, len(corners), n_tiles)
    if len(greens):
        out[pick_green] = greens[rng.integers(0, len(greens), int(pick_green.sum()))]
    return out, pick_green


def mosaic_buildings(src: Source, plan: np.ndarray, corners: np.ndarray, n_side: int, tile_m: float,
                     origin_xy_m=ORIGIN_XY_M):
    """The translated buildings: (polygons, heights [m], tags index) of every tile."""
    polys, hs, which = [], [], []
    for t, blk in enumerate(plan):
        sx, sy = corners[blk]
        tx = origin_xy_m[0] + (t % n_side) * tile_m
        ty = origin_xy_m[1] + (t // n_side) * tile_m
        r = src.rep_xy
        sel = np.flatnonzero((r[:, 0] >= sx) & (r[:, 0] < sx + tile_m) & (r[:, 1] >= sy) & (r[:, 1] < sy + tile_m))
        if len(sel):
            polys.append(shapely.transform(src.buildings[sel], lambda xy, dx=tx - sx, dy=ty - sy: xy + [dx, dy]))
            hs.append(src.heights_m[sel])
            which.append(sel)
    if not polys:
        return np.zeros(0, object), np.zeros(0), np.zeros(0, int)
    return np.concatenate(polys), np.concatenate(hs), np.concatenate(which)


def _polygon_rings(polys, heights):
    """Rings for :func:`~skyroute.stages.surface.polygon_max`: per polygon part, its rings as (n, 3)."""
    out = []
    for g, h in zip(polys, heights, strict=True):
        for part in getattr(g, "geoms", [g]):
            if part.is_empty or part.geom_type != "Polygon":
                continue
            rings = [part.exterior, *part.interiors]
            out.append([np.column_stack([np.asarray(r.coords)[:-1, :2], np.full(len(r.coords) - 1, h)])
                        for r in rings])
    return out


def write_dsm(path: Path, polys, heights, n_cells: int, res_m: float, ground_m: float, window_cells: int,
              origin_xy_m=ORIGIN_XY_M, tags: dict | None = None) -> dict:
    """The DSM GeoTIFF [m], window by window: ground + the highest building touching each cell."""
    import rasterio
    from rasterio.transform import from_origin
    from rasterio.windows import Window

    from skyroute.stages.grid import Grid
    from skyroute.stages.surface import polygon_max

    x0, y0 = origin_xy_m
    y1 = y0 + n_cells * res_m
    bx = shapely.bounds(polys) if len(polys) else np.zeros((0, 4))
    prof = dict(driver="GTiff", width=n_cells, height=n_cells, count=1, dtype="float32", crs=f"EPSG:{CRS_EPSG}",
                transform=from_origin(x0, y1, res_m, res_m), tiled=True, blockxsize=256, blockysize=256,
                compress="deflate", predictor=3, BIGTIFF="IF_SAFER")
    n_building_cells = 0
    with rasterio.open(path, "w", **prof) as dst:
        dst.update_tags(**(tags or {}))
        dst.update_tags(1, units="m", vertical_datum="EGM96 geoid")
        for r0 in range(0, n_cells, window_cells):
            for c0 in range(0, n_cells, window_cells):
                nr, nc = min(window_cells, n_cells - r0), min(window_cells, n_cells - c0)
                wg = Grid(f"EPSG:{CRS_EPSG}", x0 + c0 * res_m, y1 - r0 * res_m, nc, nr, res_m)
                wxmin, wymin, wxmax, wymax = wg.bounds
                sel = np.flatnonzero((bx[:, 2] >= wxmin) & (bx[:, 0] <= wxmax) & (bx[:, 3] >= wymin)
                                     & (bx[:, 1] <= wymax))
                top, index = polygon_max(_polygon_rings(polys[sel], heights[sel]), wg)
                has = index >= 0
                n_building_cells += int(has.sum())
                out = np.full((nr, nc), ground_m, np.float32)
                out[has] = (ground_m + top[has]).astype(np.float32)
                dst.write(out, 1, window=Window(c0, r0, nc, nr))
    return {"building_cells": n_building_cells}


def write_dem(path: Path, side_m: float, ground_m: float, origin_xy_m=ORIGIN_XY_M, tags: dict | None = None) -> None:
    """The flat ground GeoTIFF [m] on 100 m pixels, reaching 200 m beyond the city on every side."""
    import rasterio
    from rasterio.transform import from_origin

    n = int(np.ceil((side_m + 2 * DEM_MARGIN_M) / DEM_PIXEL_M))
    x0, y0 = origin_xy_m[0] - DEM_MARGIN_M, origin_xy_m[1] - DEM_MARGIN_M
    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32",
                       crs=f"EPSG:{CRS_EPSG}", transform=from_origin(x0, y0 + n * DEM_PIXEL_M, DEM_PIXEL_M, DEM_PIXEL_M),
                       compress="deflate") as dst:
        dst.update_tags(**(tags or {}))
        dst.update_tags(1, units="m", vertical_datum="EGM96 geoid")
        dst.write(np.full((n, n), ground_m, np.float32), 1)


def mosaic_extras(src: Source, plan: np.ndarray, corners: np.ndarray, n_side: int, tile_m: float,
                  origin_xy_m=ORIGIN_XY_M):
    """The translated land use: areas clipped to their block, nodes inside it; (geoms, tags index)."""
    tree = shapely.STRtree(src.extras)
    geoms, which = [], []
    for t, blk in enumerate(plan):
        sx, sy = corners[blk]
        box = shapely.box(sx, sy, sx + tile_m, sy + tile_m)
        idx = tree.query(box, predicate="intersects")
        if not len(idx):
            continue
        clipped = shapely.intersection(src.extras[idx], box)
        keep = ~shapely.is_empty(clipped)
        idx, clipped = idx[keep], clipped[keep]
        tx = origin_xy_m[0] + (t % n_side) * tile_m
        ty = origin_xy_m[1] + (t // n_side) * tile_m
        geoms.append(shapely.transform(clipped, lambda xy, dx=tx - sx, dy=ty - sy: xy + [dx, dy]))
        which.append(idx)
    if not geoms:
        return np.zeros(0, object), np.zeros(0, int)
    return np.concatenate(geoms), np.concatenate(which)


def write_osm(path: Path, items, nature: str) -> dict:
    """An OSM PBF of ``items`` = (shapely geometry in EPSG:32635, tags): nodes, closed ways
    (polygons without holes) and multipolygon relations (holes, several parts); lon/lat WGS 84."""
    import osmium
    from pyproj import Transformer

    t = Transformer.from_crs(CRS_EPSG, 4326, always_xy=True)
    nodes: list[tuple[int, float, float, dict]] = []
    ways: list[tuple[int, list[int], dict]] = []
    rels: list[tuple[int, list[tuple[str, int, str]], dict]] = []
    ids = {"n": 0, "w": 0, "r": 0}

    def nid(x, y, tags=None):
        ids["n"] += 1
        nodes.append((ids["n"], x, y, tags or {}))
        return ids["n"]

    def ring_way(ring, tags=None):
        c = np.asarray(ring.coords)[:-1]
        lon, lat = t.transform(c[:, 0], c[:, 1])
        refs = [nid(a, b) for a, b in zip(lon, lat, strict=True)]
        ids["w"] += 1
        ways.append((ids["w"], [*refs, refs[0]], tags or {}))
        return ids["w"]

    for g, tags in items:
        tags = {**{k: str(v) for k, v in tags.items()}, "skyroute:nature": nature}
        if g.geom_type == "Point":
            lon, lat = t.transform(g.x, g.y)
            nid(float(lon), float(lat), tags)
            continue
        parts = [p for p in getattr(g, "geoms", [g]) if p.geom_type == "Polygon" and not p.is_empty and p.area > 0]
        if not parts:
            continue
        if len(parts) == 1 and not parts[0].interiors:
            ring_way(parts[0].exterior, tags)
            continue
        members = []
        for p in parts:
            members.append(("w", ring_way(p.exterior), "outer"))
            members.extend(("w", ring_way(h), "inner") for h in p.interiors)
        ids["r"] += 1
        rels.append((ids["r"], members, {**tags, "type": "multipolygon"}))
    if path.exists():
        path.unlink()
    hdr = osmium.io.Header()
    hdr.set("generator", f"skyroute.catalogs.generate_mosaic_city: {nature}"[:200])
    with osmium.SimpleWriter(str(path), header=hdr) as w:
        for i, lon, lat, tg in nodes:
            w.add_node(osmium.osm.mutable.Node(id=i, location=(lon, lat), tags=tg, version=1))
        for i, refs, tg in ways:
            w.add_way(osmium.osm.mutable.Way(id=i, nodes=refs, tags=tg, version=1))
        for i, mem, tg in rels:
            w.add_relation(osmium.osm.mutable.Relation(id=i, members=mem, tags=tg, version=1))
    return {"nodes": len(nodes), "ways": len(ways), "relations": len(rels)}


MISSION_KM = 15.0
#: Shipped files copied next to the mosaic, so that its scenario holds only relative paths.
COPIED = ("gfs_2011-01-15T12_wind.nc", "yuma_2020-01-03.txt", "alm_gal_ed259.txt")


def scenario_yaml(side_km: float = 20.0, seed: int = 0, resolution_m: float = 2.0, mission_km: float | None = None) -> str:
    """The scenario of the mosaic city (its data paths relative to the generator's OUTDIR, where
    :func:`generate` writes it as ``mosaic-city.yaml``): a diagonal SE -> NW mission through the
    centre, ``mission_km`` long (default 15 km, at most 3/4 of the diagonal), at 30 m AGL.

    Why SE -> NW at 30 m: the scenario keeps the real GFS wind of ``helsinki-crosstown``, which
    here blows from the south-east at 13.8-15.5 m/s between 10 and 80 m above ground (above the
    M300's 15 m/s limit from about 50 m); downwind, 15 km at the 10 m/s cruise ground speed need
    about 252 Wh of its 627 Wh (straight line, eq. 2-12), SW -> NE about 866 Wh (not flyable); 60 m
    AGL is already in the wind no-fly, so the ceiling is 40 m AGL (wind at most 14.97 m/s there)."""
    side_m = side_km * 1000.0
    length_m = (MISSION_KM if mission_km is None else mission_km) * 1000.0
    length_m = min(length_m, 0.75 * side_m * 2 ** 0.5)
    h = length_m / 2 ** 0.5 / 2
    cx, cy = ORIGIN_XY_M[0] + side_m / 2, ORIGIN_XY_M[1] + side_m / 2
    s = (round(cx + h, 1), round(cy - h, 1))      # south-east
    g = (round(cx - h, 1), round(cy + h, 1))      # north-west
    name = f"mosaic-city-{side_km:g}km"
    return f"""# {name}: the issue 23 benchmark city.  {NATURE}.
# Written by `python -m skyroute.catalogs.generate_mosaic_city OUTDIR --side-km {side_km:g} --seed {seed}` next to
# its data (OUTDIR/mosaic-city.yaml); not in the regression catalog (building its maps takes minutes).
name: {name}
description: >-
  SYNTHETIC mosaic of translated real Helsinki blocks, not a real city ({side_km:g} x {side_km:g} km, seed {seed}):
  250 m blocks of the shipped Helsinki OSM extract (buildings with their heights, land use, parks) copied
  onto a seeded mosaic around Helsinki's coordinates; a {length_m / 1000:.1f} km SE -> NW delivery across it
  (flat ground 3.5 m EGM96), downwind at 30 m AGL under a 40 m AGL ceiling: the real GFS wind of
  helsinki-crosstown blows here from the south-east at 14-15 m/s, above the M300's 15 m/s limit from about
  45 m (about 252 Wh of its 627 Wh for 15 km downwind; upwind SW -> NE would need about 866 Wh).
aoi:
  crs: EPSG:{CRS_EPSG}
  bounds: [{ORIGIN_XY_M[0]:.1f}, {ORIGIN_XY_M[1]:.1f}, {ORIGIN_XY_M[0] + side_m:.1f}, {ORIGIN_XY_M[1] + side_m:.1f}]
  resolution_m: {resolution_m:g}
data:
  surface: {{path: mosaic_dsm.tif, vertical_datum: EGM96 geoid}}
  terrain: {{path: mosaic_dem.tif, vertical_datum: EGM96 geoid}}
  landuse: mosaic_landuse.osm.pbf
  osm_landing_sites: true
  # copies of the shipped GFS wind and almanacs (the GNSS and wind of helsinki-crosstown)
  wind: {{path: {COPIED[0]}, time_utc: 2011-01-15T12:00:00Z, profile: levels}}
  almanacs: [{COPIED[1]}, {COPIED[2]}]
mission:
  start: {{name: "mosaic SE point (synthetic city)", x: {s[0]}, y: {s[1]}, alt_agl_m: 30}}
  goal: {{name: "mosaic NW point (synthetic city)", x: {g[0]}, y: {g[1]}, alt_agl_m: 30}}
  start_time_utc: 2020-01-03T10:00:00Z
vehicle: dji-m300-rtk
# 40 m AGL: above it the wind reaches the M300's 15 m/s limit (14.97 m/s at 40 m, 15.1 at 50 m)
constraints: {{min_altitude_agl_m: 0, max_altitude_agl_m: 40}}
gnss: {{elevation_mask_deg: 5, dop_kind: PDOP, dop_thresholds: [2, 3, 4], window_min: 20, step_min: 1}}
planner: {{name: astar, weights: [1, 1, 1, 1], time_budget_s: 30, seed: 0}}
"""


def generate(out_dir: str | Path, *, side_km: float = 20.0, seed: int = 0, resolution_m: float = 2.0,
             tile_m: float = 250.0, green_share: float = 0.12, ground_m: float = 3.5,
             window_cells: int = 2048, source: str | Path = SOURCE_PBF) -> dict:
    """Write the mosaic city into ``out_dir`` (see the module docstring); returns ``mosaic.json``'s content."""
    from skyroute.stages.base import InputError

    if not (side_km > 0 and resolution_m > 0 and tile_m > 0):
        raise InputError("--side-km, --resolution-m and --tile-m must be positive")
    side_m = side_km * 1000.0
    if abs(side_m / tile_m - round(side_m / tile_m)) > 1e-9 or abs(tile_m / resolution_m - round(tile_m / resolution_m)) > 1e-9:
        raise InputError(f"--side-km {side_km:g} must be a whole number of --tile-m {tile_m:g} m tiles, and the tile a "
                         f"whole number of {resolution_m:g} m cells (e.g. --side-km 20 --tile-m 250)")
    if not 0 <= green_share <= 1:
        raise InputError(f"--green-share {green_share} must be within 0..1")
    if not 0 <= int(seed) < 2**32:
        raise InputError(f"--seed {seed} must be an integer in 0..2**32-1 (e.g. --seed 0)")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    src = read_source(source)
    if src.bounds[2] - src.bounds[0] <= tile_m or src.bounds[3] - src.bounds[1] <= tile_m:
        raise InputError(f"--tile-m {tile_m:g} m is larger than the source extract; use at most 500 m")
    n_side = int(round(side_m / tile_m))
    n_cells = int(round(side_m / resolution_m))
    corners, is_green = source_blocks(src, tile_m, resolution_m)
    plan, green = tile_plan(n_side * n_side, corners, is_green, green_share, seed)
    tags = {"NATURE": NATURE, "skyroute_generator": "skyroute.catalogs.generate_mosaic_city",
            "mosaic_seed": str(seed), "mosaic_tile_m": f"{tile_m:g}", "mosaic_side_km": f"{side_km:g}",
            "source": "catalogs/data/helsinki_center.osm.pbf, (c) OpenStreetMap contributors, ODbL 1.0"}
    polys, hs, bwhich = mosaic_buildings(src, plan, corners, n_side, tile_m)
    dsm_info = write_dsm(out / "mosaic_dsm.tif", polys, hs, n_cells, resolution_m, ground_m, window_cells, tags=tags)
    write_dem(out / "mosaic_dem.tif", side_m, ground_m, tags=tags)
    ex, ewhich = mosaic_extras(src, plan, corners, n_side, tile_m)
    items = [(g, src.extra_tags[i]) for g, i in zip(ex, ewhich, strict=True)]
    items += [(g, src.building_tags[i]) for g, i in zip(polys, bwhich, strict=True)]
    osm_info = write_osm(out / "mosaic_landuse.osm.pbf", items, NATURE)
    info = {"nature": NATURE, "seed": seed, "side_km": side_km, "resolution_m": resolution_m, "tile_m": tile_m,
            "ground_m": ground_m, "vertical_datum": "EGM96 geoid", "crs": f"EPSG:{CRS_EPSG}",
            "bounds": [ORIGIN_XY_M[0], ORIGIN_XY_M[1], ORIGIN_XY_M[0] + side_m, ORIGIN_XY_M[1] + side_m],
            "cells": n_cells * n_cells, "tiles": n_side * n_side, "green_tiles": int(green.sum()),
            "source_blocks": len(corners), "green_source_blocks": int(is_green.sum()),
            "buildings": len(polys), "landuse_features": len(ex), **dsm_info, "osm": osm_info,
            "tile_source_sw_xy_m": corners[plan].tolist(),
            "files": ["mosaic_dsm.tif", "mosaic_dem.tif", "mosaic_landuse.osm.pbf", "mosaic.json", "mosaic-city.yaml", *COPIED]}
    (out / "mosaic.json").write_text(json.dumps(info, indent=1))
    import shutil

    for f in COPIED:
        shutil.copy2(SOURCE_PBF.parent / f, out / f)
    (out / "mosaic-city.yaml").write_text(scenario_yaml(side_km, seed, resolution_m))
    return info


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m skyroute.catalogs.generate_mosaic_city",
                                 description="Generate the SYNTHETIC mosaic city (translated real Helsinki blocks).")
    ap.add_argument("out_dir")
    ap.add_argument("--side-km", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--resolution-m", type=float, default=2.0)
    ap.add_argument("--tile-m", type=float, default=250.0)
    ap.add_argument("--green-share", type=float, default=0.12)
    ap.add_argument("--ground-m", type=float, default=3.5)
    a = ap.parse_args(argv)
    from skyroute.stages.base import InputError

    try:
        info = generate(a.out_dir, side_km=a.side_km, seed=a.seed, resolution_m=a.resolution_m, tile_m=a.tile_m,
                        green_share=a.green_share, ground_m=a.ground_m)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{a.out_dir}: {info['tiles']} tiles ({info['green_tiles']} green), {info['buildings']} buildings, "
          f"{info['landuse_features']} land-use features, {info['cells']} cells; {NATURE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
