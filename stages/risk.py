"""Ground-risk levels, the dimensionless risk cost map and the no-fly mask (seed 000, II-A 1-2).

Risk levels (seed 000, section II-A item 2; seed 001, section 2), ascending:

==  =====================  ==========================================================
1   natural / rural        forest, grass, parks, water, farmland
2   industrial             industrial land use, railway yards, ports, works
3   building roofs         any building (people inside are sheltered)
4   other urban ground     streets, squares, everything urban not listed
5   critical sites         hospitals, schools, universities, railway stations, power plants
6   forbidden              airports, heliports, military areas, prisons (always no-fly)
==  =====================  ==========================================================

Derivation (:func:`risk_levels`)
--------------------------------
* The tag -> level table is the editable catalog file ``catalogs/risk_tags.yaml``
  (:func:`load_tag_table`; pass ``tag_table=`` a path or a dict to use another one).
* An OSM feature takes the **highest** level among its tags that match the table
  (``amenity=hospital`` + ``building=yes`` -> 5); ``"*"`` matches any value except ``no``.
  Areas (closed ways, multipolygons) count by their footprint; tagged nodes as a disk of
  ``point_radius_m`` [m] (the cell holding the node always counts); open ways are not used.
* A CityJSON object takes the level of its type (``Building`` -> 3, ``PlantCover`` -> 1, ...)
  unless a rule of ``cityjson_attributes`` matches one of its attributes (the rule replaces
  it); its footprint is the 2-D projection of all its surfaces.
* **Precedence**: where features overlap, the **highest level wins** (a school in a park is 5,
  a hospital roof is 5 not 3).  A cell belongs to a footprint when its centre is inside.
* Cells covered by no feature take ``default_level`` (4, urban ground, as in the seed's
  urban scenes; use 1 for rural scenes).  Urban land use polygons (``landuse=residential``)
  are deliberately absent from the table: with "highest wins" they would lift every roof in
  them to 4.
* :func:`risk_from_geotiff` takes a ready-made level raster instead (nearest resampling).

Dimensionless cost (:func:`risk_cost`)
--------------------------------------
Seed 000 eq. (11) adds ``w_r C_r`` to the path length, with ``C_r = integral of beta_r dl``
along the path of the *normalised, dimensionless* risk map ``beta_r``, so that ``C_r`` is in
metres (section III-A-2; seed 001 eq. (1): "integrating the normalized version of the risk
map").  The seeds do not print the normalisation; we use the min-max normalisation over the
flyable levels present in the map (``normalization="map"``, default)::

    beta_r = (L - L_min) / (L_max - L_min)      (0 where L_max == L_min)

which is the one consistent with seed 000 Table II: a path "mainly over buildings" (level 3,
the lowest urban level) has ``C_r / C_l = 479.2 / 1533.7 = 0.31``, impossible with ``L / 6``
(>= 0.5 over roofs) or ``(L - 1) / 4`` (>= 0.5).  ``normalization="scale"`` uses the fixed
scale ``(L - 1) / (L_fly - 1)`` (comparable between scenes).  Cells that are no-fly (level 6,
and level 5 when ``level5_nofly``, the user's stricter safety level of seed 000 II-A) have
cost ``+inf``.  :func:`integrate_along_path` computes ``C = integral of beta dl`` [m].

No-fly mask (:func:`nofly_mask`)
--------------------------------
Representation (chosen over a (z, y, x) cube, which :func:`nofly_volume` derives on any
altitudes): a 2-D boolean ``nofly`` plus, per cell, the forbidden altitude band
``[nofly_floor_m, nofly_ceiling_m]`` in metres **above ground** (the reference of
``constraints.*_altitude_agl_m``), NaN where nothing is forbidden, ceiling ``+inf`` when
unlimited.  Level-6 cells (and level 5 with ``level5_nofly``) are forbidden from the ground
(0 m) to ``+inf``.  Scenario zones are a GeoJSON FeatureCollection of Polygon/MultiPolygon in
WGS 84 lon/lat (RFC 7946) with optional properties ``min_altitude_m`` (default 0) and
``max_altitude_m`` (default unlimited); a zone covers every cell it touches (conservative).
Where several volumes overlap in a cell the band is their envelope (lowest floor, highest
ceiling): conservative when the bands are disjoint.  ``nofly_reason`` holds bit flags
1 = level 6, 2 = level 5 (``level5_nofly``), 4 = scenario zone.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import numpy as np
import rasterio
import rasterio.features
import rasterio.warp
import shapely
import xarray as xr
from pyproj import CRS, Transformer
from shapely.geometry.base import BaseGeometry

from skyroute.stages.base import DataError, InputError
from skyroute.stages.figures import image_extent
from skyroute.stages.grid import Grid, ring_cells, warp_to_grid
from skyroute.stages.yaml_io import read_yaml_file

LEVELS = (1, 2, 3, 4, 5, 6)
LEVEL_NAMES = {
    1: "natural / rural", 2: "industrial", 3: "building roof", 4: "urban ground",
    5: "critical site", 6: "forbidden",
}
FLAG_MEANINGS = "natural_rural industrial building_roof urban_ground critical_site forbidden"
NOFLY_LEVEL6, NOFLY_LEVEL5, NOFLY_ZONE = 1, 2, 4

_TOP_KEYS = ("default_level", "point_radius_m", "osm", "cityjson", "cityjson_attributes", "landing")
_LANDING_KEYS = ("any_size", "open_ground")


# --------------------------------------------------------------------------- tag table
@dataclass(frozen=True)
class TagTable:
    """A validated tag -> risk level table (see ``catalogs/risk_tags.yaml``)."""

    source: str
    default_level: int = 4
    point_radius_m: float = 10.0
    osm: Mapping[str, Mapping[str, int]] = field(default_factory=dict)
    cityjson: Mapping[str, int] = field(default_factory=dict)
    cityjson_attributes: Mapping[str, Mapping[str, Mapping[str, int]]] = field(default_factory=dict)
    landing_any_size: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    landing_open_ground: Mapping[str, tuple[str, ...]] = field(default_factory=dict)

    def osm_level(self, tags: Mapping[str, str]) -> int | None:
        """Highest level among the matching tags of one OSM feature (None if none match)."""
        best = None
        for key, values in self.osm.items():
            v = tags.get(key)
            if v is None or v == "no":
                continue
            lv = values.get(v, values.get("*"))
            if lv is not None and (best is None or lv > best):
                best = lv
        return best

    def cityjson_level(self, obj_type: str, attributes: Mapping[str, Any] | None) -> int | None:
        """Level of a CityJSON object: an attribute rule if one matches, else its type level."""
        rules = self.cityjson_attributes.get(obj_type, {})
        attrs = attributes or {}
        for attr, values in rules.items():
            if attr in attrs and str(attrs[attr]) in values:
                return values[str(attrs[attr])]
        return self.cityjson.get(obj_type)


def default_tag_table_path() -> Path:
    """The catalog file shipped with skyroute (``catalogs/risk_tags.yaml``)."""
    return Path(str(resources.files("skyroute.catalogs"))) / "risk_tags.yaml"


def _check_level(value: Any, where: str, src: str, problems: list[str]) -> int | None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        problems.append(f"{src}: {where}: level {value!r} is not an integer; use a level 1..6")
        return None
    if not 1 <= int(value) <= 6:
        problems.append(f"{src}: {where}: level {value} is outside 1..6; use 1 (natural) .. 6 (forbidden)")
        return None
    return int(value)


def _parse_table(raw: Any, src: str) -> TagTable:
    if not isinstance(raw, Mapping):
        raise InputError(f"{src}: the risk tag table must be a mapping with sections {', '.join(_TOP_KEYS)}")
    problems: list[str] = []
    for k in raw:
        if k not in _TOP_KEYS:
            problems.append(f"{src}: unknown top-level key {k!r}; valid keys are {', '.join(_TOP_KEYS)} "
                            "(OSM keys such as 'landuse' go under 'osm:')")
    default = _check_level(raw.get("default_level", 4), "default_level", src, problems)
    radius = raw.get("point_radius_m", 10.0)
    if isinstance(radius, bool) or not isinstance(radius, (int, float)) or not radius >= 0:
        problems.append(f"{src}: point_radius_m: {radius!r} must be a number >= 0 [m]")
        radius = 0.0
    osm: dict[str, dict[str, int]] = {}
    for key, values in (raw.get("osm") or {}).items():
        if not isinstance(values, Mapping):
            problems.append(f"{src}: osm.{key}: expected a mapping value -> level, e.g. {{park: 1}}")
            continue
        osm[str(key)] = {}
        for val, lv in values.items():
            ok = _check_level(lv, f"osm.{key}.{val}", src, problems)
            if ok is not None:
                osm[str(key)][str(val)] = ok
    cj: dict[str, int] = {}
    for typ, lv in (raw.get("cityjson") or {}).items():
        ok = _check_level(lv, f"cityjson.{typ}", src, problems)
        if ok is not None:
            cj[str(typ)] = ok
    cja: dict[str, dict[str, dict[str, int]]] = {}
    for typ, attrs in (raw.get("cityjson_attributes") or {}).items():
        if not isinstance(attrs, Mapping):
            problems.append(f"{src}: cityjson_attributes.{typ}: expected attribute -> value -> level")
            continue
        cja[str(typ)] = {}
        for attr, values in attrs.items():
            if not isinstance(values, Mapping):
                problems.append(f"{src}: cityjson_attributes.{typ}.{attr}: expected value -> level")
                continue
            cja[str(typ)][str(attr)] = {}
            for val, lv in values.items():
                ok = _check_level(lv, f"cityjson_attributes.{typ}.{attr}.{val}", src, problems)
                if ok is not None:
                    cja[str(typ)][str(attr)][str(val)] = ok
    landing = raw.get("landing") or {}
    lnd: dict[str, dict[str, tuple[str, ...]]] = {"any_size": {}, "open_ground": {}}
    if not isinstance(landing, Mapping):
        problems.append(f"{src}: landing: expected sections {', '.join(_LANDING_KEYS)}")
        landing = {}
    for sec, tags in landing.items():
        if sec not in _LANDING_KEYS:
            problems.append(f"{src}: unknown key landing.{sec}; valid keys are {', '.join(_LANDING_KEYS)}")
            continue
        for key, vals in (tags or {}).items():
            vals = [vals] if isinstance(vals, str) else vals
            if not isinstance(vals, list) or not all(isinstance(v, str) for v in vals):
                problems.append(f"{src}: landing.{sec}.{key}: expected a list of tag values, e.g. [helipad]")
                continue
            lnd[sec][str(key)] = tuple(vals)
    if problems:
        raise InputError(f"invalid risk tag table {src}:\n" + "\n".join(f"  - {p}" for p in problems))
    assert default is not None
    return TagTable(src, default, float(radius), osm, cj, cja, lnd["any_size"], lnd["open_ground"])


@lru_cache(maxsize=8)
def _load_file(path: str, mtime_ns: int) -> TagTable:
    raw = read_yaml_file(path, "risk tag table")
    return _parse_table(raw or {}, path)


def load_tag_table(tag_table: str | Path | Mapping | TagTable | None = None) -> TagTable:
    """The tag table from a YAML file, a dict (same layout) or the shipped catalog (None).

    Raises :class:`InputError` naming the key and the file for unknown sections and levels
    outside 1..6, :class:`DataError` for a missing or unreadable file.
    """
    if isinstance(tag_table, TagTable):
        return tag_table
    if isinstance(tag_table, Mapping):
        return _parse_table(tag_table, "<tag_table dict>")
    p = Path(tag_table) if tag_table is not None else default_tag_table_path()
    if not p.is_file():
        raise DataError(f"risk tag table not found: {p}; copy catalogs/risk_tags.yaml and edit it")
    return _load_file(str(p.resolve()), p.stat().st_mtime_ns)


# --------------------------------------------------------------------------- geometry helpers
def to_grid_crs(geoms: Sequence[BaseGeometry] | np.ndarray, src_crs: CRS | str | int, grid: Grid) -> np.ndarray:
    """Geometries reprojected from ``src_crs`` to the grid CRS (vectorised over all vertices)."""
    arr = np.asarray(list(geoms), dtype=object)
    if arr.size == 0:
        return arr
    src = CRS.from_user_input(src_crs)
    if src == grid.crs:
        return arr
    t = Transformer.from_crs(src, grid.crs, always_xy=True)
    return shapely.transform(arr, lambda xy: np.column_stack(t.transform(xy[:, 0], xy[:, 1])))


def lonlat_bounds(grid: Grid, margin_m: float = 0.0) -> shapely.Polygon:
    """The WGS 84 lon/lat box [deg] holding ``grid`` grown by ``margin_m`` [m] on every side
    (edges densified, so it holds the projected box), for selecting OSM features near the grid."""
    xmin, ymin, xmax, ymax = grid.bounds
    t = Transformer.from_crs(grid.crs, 4326, always_xy=True)
    b = t.transform_bounds(xmin - margin_m, ymin - margin_m, xmax + margin_m, ymax + margin_m, densify_pts=21)
    return shapely.box(*b)


def _burn_max(grid: Grid, geoms: Sequence[BaseGeometry], values: Sequence[int], all_touched: bool) -> np.ndarray:
    """uint8 raster of the highest value of the shapes covering each cell (0: none)."""
    if len(geoms) == 0:
        return np.zeros(grid.shape, np.uint8)
    order = np.argsort(np.asarray(values), kind="stable")  # highest burnt last: it wins
    return rasterio.features.rasterize(
        ((geoms[i], int(values[i])) for i in order), out_shape=grid.shape,
        transform=grid.transform, fill=0, dtype="uint8", all_touched=all_touched)


# --------------------------------------------------------------------------- levels
def _osm_levels(path: str | Path, grid: Grid, table: TagTable) -> np.ndarray:
    from skyroute.stages.osm import read_osm

    feats = [f for f in read_osm(path, keys=list(table.osm)) if f.kind in ("area", "node")]
    aoi = lonlat_bounds(grid, margin_m=table.point_radius_m + grid.resolution_m)
    areas, a_lv, nodes, n_lv = [], [], [], []
    for f in feats:
        lv = table.osm_level(f.tags)
        if lv is None:
            continue
        (areas if f.kind == "area" else nodes).append(f.geometry)
        (a_lv if f.kind == "area" else n_lv).append(lv)
    out = np.zeros(grid.shape, np.uint8)
    for geoms, lvs, is_node in ((areas, a_lv, False), (nodes, n_lv, True)):
        if not geoms:
            continue
        g = np.asarray(geoms, dtype=object)
        keep = shapely.intersects(g, aoi)
        g = to_grid_crs(g[keep], 4326, grid)
        lv_arr = np.asarray(lvs)[keep]
        if is_node:
            # the cell holding the node always counts, plus the disk of point_radius_m
            out = np.maximum(out, _burn_max(grid, list(g), lv_arr, all_touched=True))
            if table.point_radius_m > 0:
                disks = shapely.buffer(g, table.point_radius_m, quad_segs=8)
                out = np.maximum(out, _burn_max(grid, list(disks), lv_arr, all_touched=False))
        else:
            out = np.maximum(out, _burn_max(grid, list(g), lv_arr, all_touched=False))
    return out


def _cityjson_levels(path: str | Path, grid: Grid, table: TagTable) -> np.ndarray:
    from skyroute.stages.cityjson import read_cityjson, surfaces, vertices_in

    cj = read_cityjson(path)
    V = vertices_in(cj, grid.crs)[:, :2]
    ring_vertices: list[np.ndarray] = []
    ring_owner: list[int] = []
    lvs: list[int] = []
    for obj in cj["CityObjects"].values():
        lv = table.cityjson_level(obj.get("type", ""), obj.get("attributes"))
        if lv is None:
            continue
        k = len(lvs)
        for g in obj.get("geometry") or []:
            for ring, _stype in surfaces(g):
                if len(ring) >= 3:
                    ring_vertices.append(np.asarray(ring, dtype=np.int64))
                    ring_owner.append(k)
        lvs.append(lv)
    if not ring_vertices:
        return np.zeros(grid.shape, np.uint8)
    # every surface as a 2-D ring; the compiled scanline fill gives the cells, the highest level wins
    # (TIN surfaces hold tens of thousands of triangles: too many for rasterio's Python path)
    lengths = np.array([len(r) for r in ring_vertices], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(lengths)])
    P = V[np.concatenate(ring_vertices)]
    values = np.asarray(lvs, dtype=np.uint8)[np.asarray(ring_owner)]
    out = np.zeros(grid.shape, np.uint8)
    ring, rr, cc = ring_cells(P[:, 0], P[:, 1], offsets, grid)
    np.maximum.at(out, (rr, cc), values[ring])
    return out


def _levels_dataarray(grid: Grid, levels: np.ndarray, **extra: Any) -> xr.DataArray:
    return grid.dataarray(
        levels.astype(np.int8), "risk_level", units="1", long_name="ground risk level (1 natural .. 6 forbidden)",
        flag_values=np.arange(1, 7, dtype=np.int8), flag_meanings=FLAG_MEANINGS,
        precedence="highest level wins where features overlap", **extra)


def risk_levels(grid: Grid, osm_path: str | Path | None = None, cityjson_path: str | Path | None = None,
                tag_table: str | Path | Mapping | TagTable | None = None,
                default_level: int | None = None, building_mask: np.ndarray | None = None) -> xr.DataArray:
    """Ground-risk level 1..6 of every cell (int8) from OSM and/or CityJSON features.

    ``default_level`` (None: the table's, 4) fills cells covered by no feature.
    ``building_mask``: (y, x) bool cells that are roofs by another source (a DSM's
    ``dsm_building``), a feature of level 3 (building roofs).  See the module docstring for
    the rules and the precedence (highest level wins).
    """
    table = load_tag_table(tag_table)
    if default_level is None:
        default_level = table.default_level
    if isinstance(default_level, bool) or not isinstance(default_level, (int, np.integer)) or not 1 <= default_level <= 6:
        raise InputError(f"default_level {default_level!r} must be an integer level 1..6 (4 = urban ground, 1 = rural)")
    out = np.zeros(grid.shape, np.uint8)
    sources = []
    if osm_path is not None:
        out = np.maximum(out, _osm_levels(osm_path, grid, table))
        sources.append(f"osm:{Path(osm_path).name}")
    if cityjson_path is not None:
        out = np.maximum(out, _cityjson_levels(cityjson_path, grid, table))
        sources.append(f"cityjson:{Path(cityjson_path).name}")
    if building_mask is not None:
        out = np.maximum(out, np.where(np.asarray(building_mask, bool), np.uint8(3), np.uint8(0)))
        sources.append("dsm:buildings")
    covered = out > 0
    out[~covered] = default_level
    return _levels_dataarray(grid, out, default_level=int(default_level), tag_table=table.source,
                             sources=", ".join(sources) or "none (default level everywhere)",
                             covered_fraction=float(covered.mean()))


def risk_from_geotiff(path: str | Path, grid: Grid, default_level: int = 4) -> xr.DataArray:
    """A risk-level GeoTIFF (values 1..6) resampled to ``grid`` by nearest neighbour.

    Cells outside the raster or at its nodata take ``default_level``.
    """
    p = Path(path)
    if not 1 <= int(default_level) <= 6:
        raise InputError(f"default_level {default_level!r} must be 1..6")
    out = np.nan_to_num(warp_to_grid(p, grid, what="risk GeoTIFF", resampling="nearest", require_overlap=False),
                        nan=0.0)
    vals = np.unique(out)
    bad = [v for v in vals if v != 0 and (v not in LEVELS)]
    if bad:
        raise DataError(f"risk GeoTIFF {p} holds values {bad[:5]} that are not risk levels 1..6 "
                        "(or set its nodata value)")
    missing = out == 0
    out[missing] = default_level
    return _levels_dataarray(grid, out.astype(np.int8), default_level=int(default_level),
                             sources=f"geotiff:{p.name}", covered_fraction=float((~missing).mean()))


def _check_levels(levels: xr.DataArray) -> np.ndarray:
    if not isinstance(levels, xr.DataArray) or levels.dims[-2:] != ("y", "x"):
        raise InputError("levels must be an xarray.DataArray with dims (y, x), e.g. the output of risk_levels()")
    v = np.asarray(levels.values)
    if v.size and (v.min() < 1 or v.max() > 6):
        raise InputError(f"risk levels must be 1..6; found {int(v.min())}..{int(v.max())}")
    return v


# --------------------------------------------------------------------------- cost
def risk_cost(levels: xr.DataArray, level5_nofly: bool = False,
              normalization: Literal["map", "scale"] = "map") -> xr.DataArray:
    """Dimensionless risk cost ``beta_r`` (float32) of a level map (module docstring).

    ``integral of beta_r dl`` along a path is the risk cost ``C_r`` [m] of seed 000 eq. (11).
    No-fly levels (6; and 5 with ``level5_nofly``) get ``+inf``.
    """
    v = _check_levels(levels)
    if normalization not in ("map", "scale"):
        raise InputError(f"normalization {normalization!r} is not 'map' (min-max over the map) or 'scale'")
    top = 4 if level5_nofly else 5
    fly = v <= top
    if normalization == "map":
        lmin = int(v[fly].min()) if fly.any() else 1
        lmax = int(v[fly].max()) if fly.any() else top
    else:
        lmin, lmax = 1, top
    span = lmax - lmin
    beta = np.where(fly, (v - lmin) / span if span > 0 else 0.0, np.inf).astype(np.float32)
    out = levels.copy(data=beta)
    out.name = "risk_cost"
    out.attrs = {
        "units": "1", "long_name": "dimensionless ground-risk cost (integral along a path gives metres)",
        "normalization": normalization, "level_min": lmin, "level_max": lmax,
        "formula": "(level - level_min) / (level_max - level_min); +inf on no-fly levels",
        "level5_nofly": int(level5_nofly),
    }
    return out


def integrate_along_path(cost: xr.DataArray, xy: np.ndarray | Sequence[Sequence[float]],
                         step_m: float | None = None) -> float:
    """``integral of cost dl`` [m] along the polyline ``xy`` ((n, 2) map coordinates [m]).

    Midpoint rule on sub-segments of at most ``step_m`` (default: resolution / 20), the cost
    taken at the cell containing each midpoint.  Infinite cost in a crossed cell gives inf.
    """
    grid = Grid.from_dataarray(cost)
    pts = np.asarray(xy, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 2:
        raise InputError("xy must be an (n >= 2, 2) array of map coordinates [m]")
    step = grid.resolution_m / 20 if step_m is None else float(step_m)
    if not step > 0:
        raise InputError(f"step_m {step_m} must be > 0 [m]")
    vals = np.asarray(cost.values, dtype=np.float64)
    total = 0.0
    for a, b in zip(pts[:-1], pts[1:], strict=True):
        seg = float(np.hypot(*(b - a)))
        if seg == 0:
            continue
        n = max(1, math.ceil(seg / step))
        t = (np.arange(n) + 0.5) / n
        mx, my = a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])
        row, col = grid.index_of(mx, my)
        if row.min() < 0 or col.min() < 0 or row.max() >= grid.ny or col.max() >= grid.nx:
            raise InputError(f"path segment {a.tolist()} -> {b.tolist()} leaves the grid {grid.bounds}")
        total += float(vals[row, col].sum()) * seg / n
    return total


# --------------------------------------------------------------------------- GeoJSON & no-fly
MAX_GEOJSON_BYTES = 256 << 20   # a landing-site / no-fly GeoJSON: read within this size (a device never ends)


def read_geojson_lonlat(path: str | Path, what: str = "features",
                        allowed: Iterable[str] | None = None) -> list[tuple[BaseGeometry, dict]]:
    """(geometry in lon/lat [deg], properties) of every feature of a GeoJSON file.

    The file must be RFC 7946 GeoJSON (WGS 84 lon/lat): a projected ``crs`` member or
    coordinates outside [-180, 180] x [-90, 90] are an :class:`InputError`, as is a file
    with no features.  ``allowed``: accepted geometry types.
    """
    from skyroute.stages.base import read_limited

    p = Path(path)
    if not p.is_file():
        raise DataError(f"{what} GeoJSON not found: {p}")
    try:
        doc = json.loads(read_limited(p, MAX_GEOJSON_BYTES, f"{what} GeoJSON").decode("utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"{what} file {p} is not valid JSON ({exc})") from exc
    if not isinstance(doc, dict) or doc.get("type") not in ("FeatureCollection", "Feature"):
        raise InputError(f"{what} file {p} must be a GeoJSON FeatureCollection (found type "
                         f"{doc.get('type') if isinstance(doc, dict) else type(doc).__name__!r})")
    crs_name = str(((doc.get("crs") or {}).get("properties") or {}).get("name", ""))
    if crs_name and not any(s in crs_name.upper() for s in ("CRS84", "4326")):
        raise InputError(f"{what} file {p} declares crs {crs_name!r}: GeoJSON must be in WGS 84 lon/lat "
                         f"(RFC 7946); reproject it, e.g. ogr2ogr -t_srs EPSG:4326 out.geojson {p.name}")
    feats = doc["features"] if doc["type"] == "FeatureCollection" else [doc]
    if not feats:
        raise InputError(f"{what} file {p} has no features; add at least one Feature or remove the setting")
    allowed = tuple(allowed) if allowed is not None else None
    out = []
    for i, f in enumerate(feats):
        gj = (f or {}).get("geometry")
        if not gj:
            raise InputError(f"{what} file {p}: feature {i} has no geometry")
        try:
            g = shapely.geometry.shape(gj)
        except Exception as exc:
            raise InputError(f"{what} file {p}: feature {i} has an invalid geometry ({exc})") from exc
        if allowed is not None and g.geom_type not in allowed:
            raise InputError(f"{what} file {p}: feature {i} is a {g.geom_type}; use one of {', '.join(allowed)}")
        if g.is_empty:
            raise InputError(f"{what} file {p}: feature {i} has an empty geometry")
        x0, y0, x1, y1 = g.bounds
        if x0 < -180 or x1 > 180 or y0 < -90 or y1 > 90:
            raise InputError(
                f"{what} file {p}: feature {i} has coordinates ({x0:.1f}, {y0:.1f}) .. ({x1:.1f}, {y1:.1f}) that are "
                f"not longitude/latitude degrees (projected metres?); GeoJSON must be WGS 84 lon/lat (RFC 7946): "
                f"reproject it, e.g. ogr2ogr -t_srs EPSG:4326 out.geojson {p.name}")
        out.append((g, dict(f.get("properties") or {})))
    return out


def _zone_band(props: dict, i: int, path: Path) -> tuple[float, float]:
    def num(key: str, default: float) -> float:
        v = props.get(key)
        if v is None:
            return default
        if isinstance(v, bool) or not isinstance(v, (int, float)) or math.isnan(v):
            raise InputError(f"no-fly zones {path}: feature {i} property {key}={v!r} must be a number [m above ground]")
        return float(v)
    lo, hi = num("min_altitude_m", 0.0), num("max_altitude_m", math.inf)
    if lo < 0 or not lo < hi:
        raise InputError(f"no-fly zones {path}: feature {i} ({props.get('name', 'unnamed')}) needs "
                         f"0 <= min_altitude_m < max_altitude_m; got {lo}, {hi}")
    return lo, hi


def nofly_mask(levels: xr.DataArray, zones_geojson: str | Path | None = None, level5_nofly: bool = False,
               grid: Grid | None = None) -> xr.Dataset:
    """No-fly mask: ``nofly`` (bool), ``nofly_floor_m`` / ``nofly_ceiling_m`` [m above ground]
    (NaN where free), ``nofly_reason`` (bit flags); see the module docstring."""
    v = _check_levels(levels)
    grid = grid if grid is not None else Grid.from_dataarray(levels)
    if grid.shape != v.shape:
        raise InputError(f"grid shape {grid.shape} differs from the levels shape {v.shape}")
    reason = np.where(v == 6, NOFLY_LEVEL6, 0).astype(np.int8)
    if level5_nofly:
        reason |= np.where(v == 5, NOFLY_LEVEL5, 0).astype(np.int8)
    floor = np.where(reason > 0, 0.0, np.nan)
    ceiling = np.where(reason > 0, np.inf, np.nan)
    n_zones = 0
    if zones_geojson is not None:
        p = Path(zones_geojson)
        zones = read_geojson_lonlat(p, "no-fly zones", allowed=("Polygon", "MultiPolygon"))
        n_zones = len(zones)
        geoms = to_grid_crs([g for g, _ in zones], 4326, grid)
        gbox = shapely.box(*grid.bounds)
        hit = 0
        for i, (g, (_, props)) in enumerate(zip(geoms, zones, strict=True)):
            lo, hi = _zone_band(props, i, p)
            if not g.intersects(gbox):
                continue
            m = rasterio.features.rasterize([(g, 1)], out_shape=grid.shape, transform=grid.transform,
                                            fill=0, dtype="uint8", all_touched=True).astype(bool)
            hit += 1
            reason[m] |= NOFLY_ZONE
            floor[m] = np.fmin(floor[m], lo)
            ceiling[m] = np.fmax(ceiling[m], hi)
        if hit == 0:
            warnings.warn(f"none of the {n_zones} no-fly zones of {p} intersects the grid {grid.bounds}",
                          stacklevel=2)
    nofly = reason > 0
    ds = xr.Dataset({
        "nofly": grid.dataarray(nofly, "nofly", units="1", long_name="a forbidden volume exists over the cell"),
        "nofly_floor_m": grid.dataarray(floor.astype(np.float32), "nofly_floor_m", units="m",
                                        long_name="bottom of the forbidden volume above ground (NaN: none)"),
        "nofly_ceiling_m": grid.dataarray(ceiling.astype(np.float32), "nofly_ceiling_m", units="m",
                                          long_name="top of the forbidden volume above ground (inf: unlimited, NaN: none)"),
        "nofly_reason": grid.dataarray(reason, "nofly_reason", units="1", long_name="why the cell is no-fly",
                                       flag_masks=np.array([1, 2, 4], np.int8),
                                       flag_meanings="risk_level_6 risk_level_5_user_safety scenario_zone"),
    })
    ds.attrs.update({"level5_nofly": int(level5_nofly), "n_zones": n_zones,
                     "altitude_reference": "metres above ground level",
                     "overlap_rule": "envelope of overlapping volumes (lowest floor, highest ceiling)"})
    return ds


def nofly_volume(nofly: xr.Dataset, z_agl_m: Sequence[float] | np.ndarray) -> xr.DataArray:
    """(z, y, x) boolean cube: True where altitude ``z_agl_m`` [m above ground] is forbidden."""
    z = np.asarray(z_agl_m, dtype=np.float64)
    if z.ndim != 1 or z.size == 0:
        raise InputError("z_agl_m must be a non-empty 1-D sequence of heights above ground [m]")
    fl = nofly["nofly_floor_m"].values.astype(np.float64)
    ce = nofly["nofly_ceiling_m"].values.astype(np.float64)
    with np.errstate(invalid="ignore"):
        cube = (z[:, None, None] >= fl[None]) & (z[:, None, None] <= ce[None])
    da = xr.DataArray(cube, dims=("z", "y", "x"),
                      coords={"z": ("z", z, {"units": "m", "long_name": "height above ground"}),
                              "y": nofly["y"], "x": nofly["x"]},
                      name="nofly_volume", attrs={"units": "1", "long_name": "altitude forbidden"})
    return da.rio.write_crs(nofly.rio.crs) if nofly.rio.crs is not None else da


# --------------------------------------------------------------------------- figure
RISK_COLORS = ("#4daf4a", "#a6761d", "#404040", "#bdbdbd", "#ff7f00", "#e41a1c")


def plot_risk_levels(ds: xr.Dataset | xr.DataArray, ax=None):
    """Risk-level map with a categorical legend (levels 1..6).  Returns the axes."""
    import matplotlib.pyplot as plt
    from matplotlib.colors import BoundaryNorm, ListedColormap
    from matplotlib.patches import Patch

    da = ds["risk_level"] if isinstance(ds, xr.Dataset) else ds
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 6))
    extent = image_extent(da)
    cmap = ListedColormap(RISK_COLORS)
    ax.imshow(da.values, cmap=cmap, norm=BoundaryNorm(np.arange(0.5, 7.5), cmap.N), extent=extent,
              origin="upper", interpolation="nearest")
    present = set(np.unique(da.values).tolist())
    handles = [Patch(facecolor=RISK_COLORS[lv - 1], edgecolor="k", linewidth=0.3,
                     label=f"{lv} {LEVEL_NAMES[lv]}" + ("" if lv in present else " (none)")) for lv in LEVELS]
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, title="risk level")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("ground risk level")
    ax.set_aspect("equal")
    return ax
