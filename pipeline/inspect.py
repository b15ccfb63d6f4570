"""``skyroute inspect``: what skyroute will make of a data file or a scenario, in seconds.

:func:`inspect_target` takes a DSM / DEM (GeoTIFF, VRT), a CityJSON file, an OSM extract or a
scenario (catalog name or YAML) and returns an :class:`Inspection`: one row per fact (CRS and
vertical datum, extent against the AOI, how cells are read, NoData share and how it will be
filled, height range, buildings and parts, ground source, absolute heights and the pilot files
they allow, landing sites, the mission points checked as ``plan`` checks them) and every
problem as one ``error:`` / ``warning:`` line naming the YAML key to change.  Nothing heavy is
computed: rasters are read over the AOI only (decimated beyond :data:`MAX_PIXELS`), and no map
is rasterised at the scenario's resolution except the surface of a small window around each
mission point (:data:`MISSION_WINDOW_M`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from skyroute.pipeline.errors import ScenarioError, SkyrouteError

__all__ = ["MAX_PIXELS", "Inspection", "format_inspection", "inspect_target"]

#: Rasters larger than this over the AOI are read decimated (the NoData share is then estimated).
MAX_PIXELS = 16_000_000

RASTER_SUFFIXES = (".tif", ".tiff", ".vrt", ".gtiff", ".img", ".asc")


@dataclass
class Inspection:
    """What :func:`inspect_target` found: ``target`` and its ``kind`` (``dsm-or-dem``,
    ``cityjson``, ``osm``, ``scenario``), ``facts`` (ordered label -> text), ``data`` (the same
    as numbers and lists, for ``--json``) and ``problems`` (``(level, key, message)``)."""

    target: str
    kind: str
    facts: dict[str, str] = field(default_factory=dict)
    data: dict[str, Any] = field(default_factory=dict)
    problems: list[tuple[str, str, str]] = field(default_factory=list)

    def error(self, key: str, message: str) -> None:
        self.problems.append(("error", key, message))

    def warning(self, key: str, message: str) -> None:
        self.problems.append(("warning", key, message))

    @property
    def ok(self) -> bool:
        return not any(level == "error" for level, _, _ in self.problems)

    def to_json(self) -> dict:
        return {"target": self.target, "kind": self.kind, "facts": self.facts, **self.data,
                "problems": [{"level": lv, "key": k, "message": m} for lv, k, m in self.problems]}


def format_inspection(ins: Inspection) -> str:
    """The one-screen text: facts, then one ``error:`` / ``warning:`` line per problem."""
    width = max((len(k) for k in ins.facts), default=0)
    lines = [f"skyroute inspect {ins.target} ({ins.kind})"]
    lines += [f"  {k:<{width}}  {v}" for k, v in ins.facts.items()]
    lines += [f"{lv}: {k}: {m}" if k else f"{lv}: {m}" for lv, k, m in ins.problems]
    return "\n".join(lines)


# ------------------------------------------------------------------------------ rasters
def _crs_text(crs) -> str:
    if crs is None:
        return "none"
    epsg = crs.to_epsg()
    name = crs.name if hasattr(crs, "name") else str(crs)
    return f"EPSG:{epsg} ({name})" if epsg else name


def _raster(ins: Inspection, paths: list[Path], grid, *, role: str, key: str, datum: str | None,
            nodata: str = "fill-max") -> dict | None:
    """Facts of a DSM (``role="surface"``) or DEM (``role="terrain"``) over ``grid`` (None: the
    file's own extent).  The header checks, the memory check of the window and the height check
    are the readers' own (:func:`~skyroute.stages.grid.raster_headers`,
    :func:`~skyroute.stages.grid.read_window_holes`): inspect refuses what ``plan`` refuses."""
    import rasterio.warp

    import skyroute.pipeline.budget  # noqa: F401  (registers --max-memory for the readers' memory check)
    from skyroute.stages.grid import (
        Grid,
        check_heights,
        check_read_bytes,
        coverage_problem,
        filled_share,
        raster_headers,
        read_window_holes,
        regions_in_aoi,
        window_box,
    )

    what = {"surface": "surface DSM", "terrain": "terrain DEM"}.get(role, "DSM / DEM")
    src = paths if len(paths) > 1 else paths[0]
    try:
        heads = raster_headers(paths, what)
    except SkyrouteError as exc:
        ins.error(f"{key}.path", str(exc))
        return None
    h0 = heads[0]
    crs = h0.crs
    left = min(hd.bounds[0] for hd in heads)
    bottom = min(hd.bounds[1] for hd in heads)
    right = max(hd.bounds[2] for hd in heads)
    top = max(hd.bounds[3] for hd in heads)
    px = h0.res[0]
    with rasterio.open(paths[0]) as s0:
        ovr = bool(s0.overviews(1))
        aop = str(s0.tags().get("AREA_OR_POINT") or "Area")
        vdat = _raster_vertical_datum(s0)
        rio_crs = s0.crs
    ins.facts["file"] = (f"{', '.join(p.name for p in paths)}: {h0.driver}, "
                         f"{sum(hd.width for hd in heads) if len(heads) > 1 else h0.width} x {h0.height} px of "
                         f"{px:g} x {h0.res[1]:g}, {h0.dtype}, nodata {h0.nodata}"
                         + (", stored bottom-up (read flipped)" if h0.flipped else ""))
    ins.facts["CRS"] = _crs_text(crs)
    ins.facts["vertical datum"] = (datum if datum else "not given") + (
        f" (the file says: {vdat})" if vdat else " (the file names none)")
    ins.facts["vertical unit"] = (h0.z_unit + (f": heights x {h0.z_scale:.10g} to metres" if h0.z_scale != 1.0 else "")
                                  + (f" + {h0.z_offset:g} m" if h0.z_offset else ""))
    ins.data[f"{role}_vertical_unit"] = {"unit": h0.z_unit, "metres_per_unit": h0.z_scale, "offset_m": h0.z_offset}
    if datum is None and role == "surface":
        ins.warning(f"{key}.vertical_datum", "give the datum of the DSM's heights (e.g. 'NAP', 'EGM96 geoid'): "
                    "it is required")
    ins.facts["extent"] = (f"x {left:.1f}..{right:.1f}, y {bottom:.1f}..{top:.1f} [m] "
                           f"({(right - left) / 1e3:.2f} x {(top - bottom) / 1e3:.2f} km)")
    ins.data[f"{role}_extent"] = [left, bottom, right, top]
    whole = grid is None
    if whole:
        r = max(px, 1.0)
        grid = Grid.from_bounds(crs, left, bottom, right, top, r, inward=True)
    dsm = "DSM: each cell the highest pixel of its footprint (flat-topped pixels)"
    dem = ("DEM: the surface through its samples; terrain = the highest, terrain_min = the lowest sample of every "
           "lattice square touching the cell")
    reading = dsm if role == "surface" else dem if role == "terrain" else f"as data.surface, {dsm}; as data.terrain, {dem}"
    if role != "surface":
        from skyroute.stages.surface import dem_sample_offset_px

        _, where = dem_sample_offset_px(src)
        reading += f" ({where})"
    ins.facts["reading"] = reading + (f"; AREA_OR_POINT={aop}" if role == "surface" else "")
    # the window under the AOI (decimated beyond MAX_PIXELS)
    b = rasterio.warp.transform_bounds(grid.crs, rio_crs, *grid.bounds, densify_pts=21)
    if b[0] >= right or b[2] <= left or b[1] >= top or b[3] <= bottom:
        ins.error("aoi.bounds", f"the AOI does not intersect the {role} raster (extent x {left:.0f}..{right:.0f}, "
                  f"y {bottom:.0f}..{top:.0f} in {_crs_text(crs)}); fix aoi or {key}.path")
        return None
    _, _, wh, ww, _ = window_box(heads, b, 32)
    n_px = float(wh) * float(ww)
    step = max(int(np.ceil(np.sqrt(n_px / MAX_PIXELS))), 1)
    ins.data[f"{role}_window_px"] = [ww, wh]
    try:
        if step == 1:
            # the stage's own read: the memory check, the window grown over NoData, the height check
            win, holes = read_window_holes(src, grid, what=what)
        else:
            if not whole:   # the stage reads this window whole: the same memory check, before any read
                check_read_bytes((wh, ww), what, src)
            elif not ovr:
                # no AOI and no overviews: GDAL would decode every block of the raster to decimate it
                from skyroute.pipeline.budget import _gib
                from skyroute.stages.base import memory_limit_bytes
                from skyroute.stages.grid import READ_BYTES_PER_PX

                need, limit = float(wh) * ww * READ_BYTES_PER_PX, memory_limit_bytes()
                if need > limit:
                    ins.facts["heights"] = ins.facts["NoData"] = "not inspected (the raster is too large to scan)"
                    ins.warning(f"{key}.path", f"heights and NoData not inspected: the raster is {ww:,} x {wh:,} px "
                                f"without overviews, scanning it needs about {_gib(need)}, more than --max-memory "
                                f"({_gib(limit)}); inspect a scenario using it (only the window over its AOI is "
                                "read) or build overviews (gdaladdo)")
                    return {"crs": crs, "grid": grid, "extent": (left, bottom, right, top)}
            win, holes = _decimated_window(paths, heads, grid, step, what)
            check_heights(win.values, src, what)
            ins.facts["reading"] += f" [inspected every {step} px]"
    except SkyrouteError as exc:
        ins.error(f"{key}.path", str(exc))
        return None
    vals = win.values[np.isfinite(win.values)]
    if vals.size:
        ins.facts["heights"] = f"{vals.min():.2f} .. {vals.max():.2f} m"
        ins.data[f"{role}_heights_m"] = [float(vals.min()), float(vals.max())]
    under = np.isnan(win.values) & win.inside
    share_px = float(under.sum() / max(int(win.inside.sum()), 1))     # of the pixels inside the extent read
    share_cells = filled_share(win, holes, grid) if step == 1 else share_px
    n, n_edge = regions_in_aoi(win, holes, grid) if step == 1 else (holes.n_interior, holes.n_edge)
    how = {"fill-max": "each region the highest height on its rim within the raster",
           "fill-nearest": "each pixel the nearest valid pixel", "error": "refused (nodata: error)"}[nodata]
    if role == "terrain":
        how = "each region the highest height on its rim for terrain, the lowest for terrain_min"
    ins.facts["NoData"] = (f"{100 * share_px:.2f} % of the pixels around the AOI, {n} region(s) under it "
                           f"({n_edge} touching the raster's edge): {how}" if n else "none under the AOI")
    ins.data[f"{role}_nodata"] = {"share_of_pixels": share_px, "share_of_cells": share_cells, "regions": n,
                                  "regions_touching_edge": n_edge, "fill": nodata if role == "surface" else "fill-max"}
    if n and share_cells > 0:
        if role == "surface" and nodata == "error":
            ins.error(f"{key}.nodata", f"{n} NoData region(s) cover {100 * share_cells:.2f} % of the AOI and nodata is "
                      "'error'; set it to fill-max (each region the highest height on its rim) or fill-nearest")
        else:
            ins.warning(f"{key}.nodata" if role == "surface" else f"{key}.path",
                        f"{n} NoData region(s) cover {100 * share_cells:.2f} % of the AOI's cells: filled ({how})"
                        + ("; the choices: fill-max, fill-nearest, error" if role == "surface" else ""))
    if step == 1:
        msg = coverage_problem(win, holes, grid, what=f"{role} raster", key=key)
        if msg:
            ins.error("aoi.bounds", msg.split(": ", 1)[1])
    return {"crs": crs, "grid": grid, "extent": (left, bottom, right, top)}


def _decimated_window(paths: list[Path], heads: list, grid, step: int, what: str):
    """(:class:`~skyroute.stages.grid.SourceWindow`, its holes) of the first tile over the AOI,
    every ``step`` pixels (nearest), heights in metres, for an estimate of the NoData share of
    very large rasters; GDAL's block cache is bounded (one row of blocks, at least 256 MB)."""
    import rasterio
    import rasterio.errors
    import rasterio.warp
    import rasterio.windows
    from affine import Affine

    from skyroute.stages.grid import SourceWindow, find_holes, raster_read_error

    hd = heads[0]
    with rasterio.open(paths[0]) as s:
        bh = s.block_shapes[0][0] if s.block_shapes else 256
    cache_mb = max(256, int(2 * hd.width * bh * np.dtype(hd.dtype).itemsize) >> 20)
    with rasterio.Env(GDAL_CACHEMAX=cache_mb), rasterio.open(paths[0]) as s:
        b = rasterio.warp.transform_bounds(grid.crs, s.crs, *grid.bounds, densify_pts=21)
        w = rasterio.windows.from_bounds(*b, transform=hd.transform).round_offsets().round_lengths()
        w = w.intersection(rasterio.windows.Window(0, 0, hd.width, hd.height))
        shape = (max(int(w.height // step), 1), max(int(w.width // step), 1))
        sw = (rasterio.windows.Window(w.col_off, hd.height - w.row_off - w.height, w.width, w.height)
              if hd.flipped else w)
        try:
            a = s.read(1, window=sw, out_shape=shape, masked=True)
        except rasterio.errors.RasterioIOError as exc:
            raise raster_read_error(what, paths[0], exc) from exc
    if hd.flipped:
        a = a[::-1]
    vals = np.where(np.ma.getmaskarray(a), np.nan, np.ma.getdata(a).astype(float))
    vals[~np.isfinite(vals)] = np.nan
    vals = vals * hd.z_scale + hd.z_offset
    t = (hd.transform * Affine.translation(w.col_off, w.row_off)
         * Affine.scale(w.width / shape[1], w.height / shape[0]))
    win = SourceWindow(vals, np.ones(vals.shape, bool), t, hd.crs, False)
    return win, find_holes(win)


def _raster_vertical_datum(src) -> str | None:
    """The vertical datum a raster names (a compound CRS's vertical part), else None."""
    try:
        from pyproj import CRS

        crs = CRS.from_user_input(src.crs)
        if crs.is_compound and len(crs.sub_crs_list) > 1:
            return crs.sub_crs_list[1].name
    except Exception:  # noqa: BLE001 - an odd CRS only hides this hint
        return None
    return None


# ------------------------------------------------------------------------------ CityJSON
def _cityjson(ins: Inspection, path: Path, grid, key: str) -> dict | None:
    from pyproj import CRS, Transformer

    from skyroute.stages.cityjson import Z_RANGE_M, cityjson_crs, load_cityjson, surface_rings

    try:
        # the one strict reading the surface and risk stages use: what it refuses, inspect refuses
        doc = load_cityjson(path)
        cj = doc.doc
        crs = cityjson_crs(cj)
    except SkyrouteError as exc:
        ins.error(f"{key}.path", str(exc))
        return None
    ref = str((cj.get("metadata") or {}).get("referenceSystem", ""))
    vdat = None
    try:
        import re

        m = re.search(r"EPSG[:/]+(?:[0-9.]*/)?(?:0/)?:?(\d+)", ref)
        full = CRS.from_epsg(int(m.group(1))) if m else None
        if full is not None and full.is_compound and len(full.sub_crs_list) > 1:
            vdat = full.sub_crs_list[1].name
    except Exception:  # noqa: BLE001
        vdat = None
    V = doc.vertices
    objs = cj["CityObjects"]
    kinds: dict[str, int] = {}
    for o in objs.values():
        kinds[o.get("type", "?")] = kinds.get(o.get("type", "?"), 0) + 1
    n_b, n_p = kinds.get("Building", 0), kinds.get("BuildingPart", 0)
    has_tin = kinds.get("TINRelief", 0) > 0
    lods: set[str] = set()
    n_ground = n_th = 0
    stacked = 0
    ground_by_root: dict[str, list[tuple[float, float]]] = {}
    for oid, o in objs.items():
        if o.get("type") not in ("Building", "BuildingPart"):
            continue
        if (o.get("attributes") or {}).get("TerrainHeight") is not None:
            n_th += 1
        root = oid
        seen = {oid}
        ps = o.get("parents") or []
        while ps and ps[0] not in seen:
            root = ps[0]
            seen.add(root)
            ps = (objs.get(root) or {}).get("parents") or []
        for g in o.get("geometry") or []:
            lods.add(str(g.get("lod")))
            for rings, st in surface_rings(g):
                if st == "GroundSurface" and len(rings[0]) >= 3:
                    z = V[np.asarray(rings[0]), 2]
                    ground_by_root.setdefault(root, []).append((float(z.min()), float(z.max())))
                    n_ground += 1
    from skyroute.stages.cityjson import GROUND_TOLERANCE_M

    for faces in ground_by_root.values():
        lo = min(faces)
        stacked += sum(1 for f in faces if f[0] > lo[1] + GROUND_TOLERANCE_M)
    ins.facts["file"] = f"{path.name}: CityJSON {cj.get('version', '?')}, {len(V)} vertices, LoD {', '.join(sorted(lods))}"
    ins.facts["CRS"] = _crs_text(crs)
    ins.facts["vertical datum"] = vdat or "not named by referenceSystem (heights as in the file)"
    if len(V):
        x0, y0, x1, y1 = V[:, 0].min(), V[:, 1].min(), V[:, 0].max(), V[:, 1].max()
        ins.facts["extent"] = f"x {x0:.1f}..{x1:.1f}, y {y0:.1f}..{y1:.1f} [m] in the file's CRS"
        ins.facts["heights"] = f"{V[:, 2].min():.2f} .. {V[:, 2].max():.2f} m"
        ins.data["cityjson_extent"] = [float(x0), float(y0), float(x1), float(y1)]
        ins.data["cityjson_heights_m"] = [float(V[:, 2].min()), float(V[:, 2].max())]
        if grid is not None:
            t = Transformer.from_crs(crs, grid.crs, always_xy=True)
            gx, gy = t.transform(V[:, 0], V[:, 1])
            gb = grid.bounds
            inside = (gx >= gb[0]) & (gx <= gb[2]) & (gy >= gb[1]) & (gy <= gb[3])
            if not inside.any():
                ins.error("aoi.bounds", f"the AOI does not reach any vertex of {path.name}; move aoi.bounds onto "
                          f"x {x0:.0f}..{x1:.0f}, y {y0:.0f}..{y1:.0f} ({_crs_text(crs)})")
    ins.facts["reading"] = ("roof faces: each cell the face's maximum over its part in the cell; ground likewise "
                            "(max for terrain, min for terrain_min)")
    ins.facts["buildings"] = (f"{n_b} Building, {n_p} BuildingPart, {n_ground} GroundSurface faces"
                              + (f", {stacked} ground surface(s) of parts standing on other parts (not ground)"
                                 if stacked else "") + (f", TerrainHeight on {n_th}" if n_th else ""))
    ground = ("TINRelief (max / min over each cell), the buildings' lowest ground surfaces where it does not reach"
              if has_tin else "TerrainHeight attributes" if n_th else
              "the lowest ground surface of each building (its parts included), interpolated"
              if n_ground else "none in the file: flat 0 m")
    ins.facts["ground"] = ground
    ins.facts["checked"] = (f"transform, {len(V)} vertices (finite, heights {Z_RANGE_M[0]:g} .. {Z_RANGE_M[1]:g} m), "
                            "boundary nesting, vertex indices, semantics"
                            + (f"; {doc.instances} GeometryInstance(s) placed from geometry-templates"
                               if doc.instances else "")
                            + (f"; {len(doc.warnings)} coercion warning(s)" if doc.warnings else ""))
    ins.data["cityjson"] = {"buildings": n_b, "building_parts": n_p, "ground_surfaces": n_ground,
                            "stacked_part_grounds": stacked, "tin_relief": has_tin, "terrain_height": n_th,
                            "vertical_datum": vdat, "geometry_instances": doc.instances,
                            "coercions": dict(doc.counts)}
    for w in doc.warnings:
        ins.warning(key, w)
    if not (has_tin or n_th or n_ground):
        ins.warning("data.terrain", "the CityJSON holds no ground (no TINRelief, GroundSurface or TerrainHeight): "
                    "roof heights are taken above a flat 0 m; give data.terrain (a DEM in the same datum)")
    return {"crs": crs, "vertical_datum": vdat}


# ------------------------------------------------------------------------------ OSM
def _osm(ins: Inspection, path: Path, grid, key: str, landing: bool = True) -> dict | None:
    from skyroute.stages.base import file_problem
    from skyroute.stages.osm import read_osm

    why = file_problem(path, "OSM")
    if why is not None:
        ins.error(f"{key}.path", why)
        return None
    try:
        feats = read_osm(path, keys=["building", "building:part", "ele"])
    except SkyrouteError as exc:
        ins.error(f"{key}.path", str(exc))
        return None
    import shapely

    box = None
    if grid is not None:
        x0, y0, x1, y1 = grid.bounds
        from pyproj import Transformer

        lon, lat = Transformer.from_crs(grid.crs, 4326, always_xy=True).transform([x0, x1, x1, x0], [y0, y0, y1, y1])
        box = shapely.Polygon(list(zip(lon, lat, strict=True)))
    bld = [f for f in feats if f.kind == "area" and ("building" in f.tags or "building:part" in f.tags)
           and (box is None or f.geometry.intersects(box))]
    from skyroute.stages.surface import osm_building_height, osm_height_warnings

    problems: list[tuple[int, str]] = []
    for f in bld:   # the stage's own reading of the height tags: the same warnings, before any work
        why: list[str] = []
        osm_building_height(f.tags, problems=why)
        if why:
            problems.append((f.osm_id, ", ".join(why)))
    n_h = sum(1 for f in bld if "height" in f.tags)
    n_l = sum(1 for f in bld if "building:levels" in f.tags and "height" not in f.tags)
    ele = [float(f.tags["ele"]) for f in feats if "ele" in f.tags and _is_float(f.tags["ele"])
           and f.kind == "node" and (box is None or f.geometry.intersects(box))]
    ins.facts["file"] = f"{path.name}: OpenStreetMap extract"
    ins.facts["CRS"] = "EPSG:4326 (WGS 84 lon/lat); the grid is the UTM zone of the AOI unless aoi.crs names one"
    ins.facts["vertical datum"] = "local ground (flat 0 m): building heights above the ground"
    ins.facts["buildings"] = (f"{len(bld)} building areas in the AOI: {n_h} with height, {n_l} with levels only, "
                              f"{len(bld) - n_h - n_l} with a default height by type")
    ins.facts["ground"] = "flat 0 m (OSM has no terrain)" + (
        f"; {len(ele)} OSM ele points in the AOI span {min(ele):.1f}..{max(ele):.1f} m (EGM96)" if ele else "")
    ins.data["osm"] = {"buildings": len(bld), "with_height": n_h, "with_levels": n_l,
                       "ele_points": len(ele), "ele_range_m": [min(ele), max(ele)] if ele else None,
                       "height_tags_coerced": len(problems), "height_tags_coerced_ids": [i for i, _ in problems]}
    if problems:
        ins.facts["buildings"] += f"; {len(problems)} with an unusable or implausible height tag (coerced)"
    for w in osm_height_warnings(problems, key=None):
        ins.warning(key, w)
    if grid is not None and not bld:
        ins.error("aoi.bounds", f"the AOI does not intersect any building of {path.name}; check aoi.bounds")
    return {"ele": ele}


def _is_float(t: str) -> bool:
    try:
        float(t)
        return True
    except ValueError:
        return False


def _landing(ins: Inspection, sc) -> None:
    """Landing sites of a scenario: counted on a coarse copy of its grid (no rasterising at
    the scenario's resolution)."""
    from skyroute.stages.grid import Grid
    from skyroute.stages.landing import landing_sites

    d = sc.data
    g = sc.grid
    osm = None
    for p in (d.landuse, d.buildings.path if d.buildings else None):
        if p is not None and not str(p).lower().endswith(".json"):
            osm = osm or p
    coarse = Grid.from_bounds(g.crs, *g.bounds, max(g.resolution_m, 25.0))
    if d.landing_sites is None and (osm is None or not d.osm_landing_sites):
        ins.facts["landing sites"] = ("none (no data.landing_sites, no OSM extract): `skyroute fleet --missions` "
                                      "derives candidate sites from open ground (no obstacle within r_p, lowest risk "
                                      "level)")
        ins.data["landing_sites"] = {"count": 0, "kinds": {}}
        return
    try:
        sites = landing_sites(coarse, osm_path=osm if d.osm_landing_sites else None, geojson=d.landing_sites,
                              tag_table=d.risk_tags)
        n = len(sites)
        kinds: dict[str, int] = {}
        for s in sites:
            kinds[s.kind] = kinds.get(s.kind, 0) + 1
    except SkyrouteError as exc:
        ins.error("data.landing_sites", str(exc))
        return
    if n:
        ins.facts["landing sites"] = f"{n}: " + ", ".join(f"{v} {k}" for k, v in sorted(kinds.items()))
    else:
        ins.facts["landing sites"] = ("none: `skyroute fleet --missions` derives candidate sites from open ground "
                                      "(no obstacle within r_p, lowest risk level); give data.landing_sites "
                                      "(a GeoJSON) for real ones")
        ins.warning("data.landing_sites", "no landing sites: the landing cost term is uniform and contingency "
                    "landing has nowhere to go; give a GeoJSON of sites")
    ins.data["landing_sites"] = {"count": n, "kinds": kinds if n else {}}


# ------------------------------------------------------------------------------ scenario
def _surface_datum(sc, cj: dict | None) -> str:
    d = sc.data
    if d.terrain is not None:
        return d.terrain.vertical_datum
    if d.surface is not None:
        return d.surface.vertical_datum
    if d.buildings is not None and d.buildings.format == "cityjson":
        return (cj or {}).get("vertical_datum") or "source data heights (CityJSON; NAP for Dutch data)"
    return "local ground (flat terrain, heights above ground level)"


def _absolute(ins: Inspection, sc, cj: dict | None) -> None:
    from skyroute.stages.geoid import datum_kind, find_geoid_grid, height_reference

    datum = _surface_datum(sc, cj)
    g = sc.data.ground
    try:
        ref = height_reference(datum, g.height_m if g else None, g.vertical_datum if g else None)
        kind = datum_kind(ref.datum)
        if kind in ("EGM96", "EGM2008"):
            find_geoid_grid(kind)
        if kind != "EGM96":
            find_geoid_grid("EGM96")      # KML / QGroundControl heights are above EGM96
        why = None
    except SkyrouteError as exc:
        why = str(exc)
    sigma = bool(sc.data.almanacs)
    files = {"plan.plan": "home altitude above mean sea level" if why is None else "home altitude 0 m",
             "plan.gpkg": "yes", "plan.kml": "yes" if why is None else "no",
             "intent.json": "yes" if why is None and sigma else "no"}
    src = (f"data.ground: {g.height_m:g} m in {g.vertical_datum}" if g else f"the surface datum ({datum})")
    ins.facts["absolute heights"] = (f"{'yes' if why is None else 'no'} ({src}); pilot files: "
                                     + ", ".join(f"{k} {v}" for k, v in files.items()))
    ins.data["absolute_heights"] = {"available": why is None, "why_not": why, "surface_datum": datum,
                                    "pilot_files": files}
    if why is not None:
        ins.warning("data.ground", f"plan.kml and intent.json will not be written, plan.plan gets home altitude "
                    f"0 m: {why}")
    elif not sigma:
        ins.warning("data.almanacs", "intent.json will not be written: no GNSS almanac, so no predicted navigation "
                    "error to size its volumes")
    if g is not None and datum_kind(datum) == "local":
        ins.warning("data.ground", f"the ground is one flat plane at {g.height_m:g} m ({g.vertical_datum}): buildings "
                    "on higher ground are modelled too low by the ground's rise and AGL limits hold above the plane; "
                    "give data.terrain (a DEM) for real relief")


def _scenario(ins: Inspection, sc) -> None:
    d = sc.data
    g = sc.grid
    ins.facts["scenario"] = f"{sc.name}" + (f" ({sc.source_path})" if sc.source_path else "")
    ins.facts["AOI"] = (f"{g.crs_wkt if g.crs_wkt.startswith('EPSG') else 'custom CRS'}: x {g.bounds[0]:.1f}.."
                        f"{g.bounds[2]:.1f}, y {g.bounds[1]:.1f}..{g.bounds[3]:.1f}; grid {g.nx} x {g.ny} cells of "
                        f"{g.resolution_m:g} m ({g.nx * g.ny / 1e6:.2f} M cells)")
    ins.data["grid"] = {"crs": g.crs_wkt, "bounds": list(g.bounds), "nx": g.nx, "ny": g.ny,
                        "resolution_m": g.resolution_m}
    if sc.aoi.bounds is not None and tuple(g.bounds) != tuple(float(v) for v in sc.aoi.bounds):
        ins.facts["AOI"] += " (aoi.bounds snapped inward to the resolution lattice)"
    sub: dict[str, dict] = {}
    cj = None
    for role, key, src in (("surface", "data.surface", d.surface), ("terrain", "data.terrain", d.terrain)):
        if src is None:
            continue
        part = Inspection(str(src.path), role)
        paths = [Path(p) for p in (src.paths if role == "surface" else (src.path,))]
        _raster(part, paths, g, role=role, key=key, datum=src.vertical_datum,
                nodata=getattr(src, "nodata", "fill-max"))
        _merge(ins, part, role)
        sub[role] = part.data
    if d.buildings is not None:
        part = Inspection(str(d.buildings.path), d.buildings.format)
        if d.buildings.format == "cityjson":
            cj = _cityjson(part, Path(d.buildings.path), g, "data.buildings")
        else:
            _osm(part, Path(d.buildings.path), g, "data.buildings")
        _merge(ins, part, "buildings")
    ground = ("DEM (data.terrain), the surface through its samples" if d.terrain is not None else
              "derived from the DSM by a grey opening (no DEM)" if d.surface is not None else
              ins.facts.get("buildings: ground", "flat 0 m") if cj is not None else
              "flat 0 m: heights above local ground")
    ins.facts["ground source"] = ground
    if d.terrain is None and d.surface is not None:
        ins.warning("data.terrain", f"no DEM: the ground is derived from the DSM by a grey opening with a "
                    f"{d.surface.ground_window_m:g} m window (data.surface.ground_window_m); give data.terrain for a "
                    "surveyed ground")
    _absolute(ins, sc, cj)
    _landing(ins, sc)
    if ins.ok:     # the surface around the points is built only from data that passed every check above
        _mission_points(ins, sc)


#: half side of the window around each mission point on which :func:`_mission_points` builds the
#: surface [m] (at least twice a DSM's ground window, so the derived ground there is the full map's)
MISSION_WINDOW_M = 100.0


def _point_window(sc, name: str, pad_m: float):
    """The cells of the scenario grid within ``pad_m`` [m] of mission point ``name``, as a grid on
    the same lattice (its cells are cells of the scenario grid)."""
    import math

    from skyroute.stages.gridspec import Grid

    g = sc.grid
    r = g.resolution_m
    x, y = sc.point_xy(getattr(sc.mission, name))
    row, col = (int(i) for i in g.cell_of(x, y))
    k = max(1, math.ceil(pad_m / r))
    r0, r1, c0, c1 = max(0, row - k), min(g.ny, row + k + 1), max(0, col - k), min(g.nx, col + k + 1)
    return Grid(g.crs_wkt, g.x0 + c0 * r, g.y1 - r0 * r, c1 - c0, r1 - r0, r)


def _mission_points(ins: Inspection, sc) -> None:
    """``plan``'s own check of the mission points (:func:`skyroute.pipeline.runner.check_mission`:
    not inside a building or the terrain), on the surface stage's model of a small window around
    each point (:data:`MISSION_WINDOW_M`): the same cells, not the whole map."""
    from skyroute.pipeline.runner import check_mission
    from skyroute.pipeline.stages_builtin import _surface_settings, surface_stage

    settings = _surface_settings(sc)
    pad_m = max(MISSION_WINDOW_M, 2.0 * settings.ground_window_m)
    checked = []
    for name in ("start", "goal"):
        win = _point_window(sc, name, pad_m)
        try:
            try:
                ds = surface_stage(settings=settings.model_copy(update={"grid": win}))
            except SkyrouteError as exc:   # no building near the point: the surface there is the ground
                if settings.buildings_path is None or "does not intersect any building" not in str(exc):
                    raise
                ds = surface_stage(settings=settings.model_copy(update={"grid": win, "buildings_path": None}))
            check_mission(sc, ds, grid=win, points=(name,))
            checked.append(name)
        except ScenarioError as exc:
            for prob in exc.problems:
                key, _, msg = prob.partition(": ")
                ins.error(key, msg or prob)
        except SkyrouteError as exc:
            if ins.ok:          # a data problem is reported once by its own check above
                ins.warning(f"mission.{name}", f"not checked against the surface: {exc}")
    if checked:
        ins.facts["mission points"] = (" and ".join(checked) + " above the surface (plan's check: not inside a "
                                       "building or the terrain)")


def _merge(ins: Inspection, part: Inspection, prefix: str) -> None:
    for k, v in part.facts.items():
        ins.facts[f"{prefix}: {k}"] = v
    ins.data.update(part.data)
    ins.problems.extend(part.problems)


def _is_scenario(target: str) -> bool:
    p = Path(target)
    if p.suffix.lower() in (".yaml", ".yml"):
        return True
    from skyroute.pipeline.settings import scenario_paths

    return not p.exists() and target in scenario_paths()


def inspect_target(target: str | Path) -> Inspection:
    """Inspect a data file (DSM / DEM raster, CityJSON, OSM extract) or a scenario (catalog name
    or YAML); see the module docstring.  A scenario that does not validate gives its problems as
    errors (each with its YAML key)."""
    t = str(target)
    if _is_scenario(t):
        import warnings

        from skyroute.pipeline.settings import load_scenario

        ins = Inspection(t, "scenario")
        try:
            with warnings.catch_warnings(record=True) as caught:   # e.g. a data path resolved to the shipped file
                warnings.simplefilter("always")
                sc = load_scenario(t)
        except ScenarioError as exc:
            for p in exc.problems:
                key, _, msg = p.partition(": ")
                ins.error(key, msg or p)
            return ins
        for w in caught:
            key, _, msg = " ".join(str(w.message).split()).partition(": ")
            ins.warning(key if msg else "", msg or key)
        _scenario(ins, sc)
        return ins
    p = Path(t)
    if not p.exists():
        from skyroute.pipeline.errors import InputError

        raise InputError(f"{t} is neither a file nor a catalog scenario; give a DSM / DEM GeoTIFF or VRT, a CityJSON "
                         "file, an OSM extract or a scenario (name or YAML)")
    name = p.name.lower()
    if name.endswith(RASTER_SUFFIXES):
        ins = Inspection(t, "raster (DSM or DEM)")
        _raster(ins, [p], None, role="raster", key="data.surface or data.terrain", datum=None)
        ins.facts["use as"] = ("data.surface: {path, vertical_datum} (a DSM: buildings and trees, footprint max) or "
                               "data.terrain: {path, vertical_datum} (a DEM: bare ground, read through its samples)")
        return ins
    if name.endswith((".json", ".city.json", ".jsonl")):
        ins = Inspection(t, "cityjson")
        _cityjson(ins, p, None, "data.buildings")
        ins.facts["use as"] = "data.buildings: {path, format: cityjson}"
        return ins
    if name.endswith((".osm.pbf", ".pbf", ".osm", ".osm.bz2")):
        ins = Inspection(t, "osm")
        _osm(ins, p, None, "data.buildings")
        ins.facts["use as"] = "data.buildings: {path, format: osm}, data.landuse: path; data.ground for absolute heights"
        return ins
    from skyroute.pipeline.errors import InputError

    raise InputError(f"{t}: unknown file type; skyroute inspects GeoTIFF / VRT rasters, CityJSON (.json), OSM "
                     "extracts (.osm.pbf, .osm) and scenarios (.yaml)")


def inspection_json(ins: Inspection) -> str:
    return json.dumps(ins.to_json(), indent=1, allow_nan=False, default=str)
