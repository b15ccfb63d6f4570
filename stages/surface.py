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
which is conservative for collision and occlusion.  Several ``;``-separated values: the highest.
Broken tags are never read lower than they may mean (:func:`osm_building_height`): a value above
:data:`MAX_BUILDING_HEIGHT_M` (1000 m) or :data:`MAX_BUILDING_LEVELS` (200), ``inf`` included, is
taken as that maximum; an unparsable, NaN, negative or zero ``height`` gives way to the highest of
the levels' height and the type's default; each such building is a counted stage warning naming
its OSM id (also shown by ``skyroute inspect``).

CityJSON (1.0 / 1.1 / 2.0, LoD1 or LoD2, Building and BuildingPart): every upper surface
(``RoofSurface`` / ``OuterCeilingSurface`` / ``OuterFloorSurface``, or for LoD1 without semantics
every face whose normal points up) is a roof face.  Terrain: a ``TINRelief``, where the file has
one, is the ground (``terrain``: the TIN's maximum over the cell, the same rasterisation as roofs,
``terrain_min`` its minimum; where it covers a cell only in part, combined with the buildings'
ground); otherwise, per Building with its BuildingParts, the ``TerrainHeight`` attribute
(preferred: some LoD2 models put the ground surface at z = 0) or its *lowest* ``GroundSurface``
(the bottom of a part standing on another part is not ground), interpolated linearly on the
points' Delaunay triangles, each cell the maximum (``terrain``) / minimum (``terrain_min``) over
the cell (nearest point outside their hull): :func:`terrain_from_points`.

Rasterisation (conservative: a cell's value holds for every point of the cell)
-----------------------------------------------------------------------------
Cells are closed squares; a polygon *touches* a cell when the two share any point (a sliver or
a corner counts).  :func:`polygon_max` (compiled kernel) gives each cell the maximum over every
touching polygon of the polygon's height over the part inside the cell:

* OSM footprints are flat polygons (holes respected): every touched cell takes the building's
  height, the highest building where several touch it (``all_touched`` semantics, including
  the cells that only touch a footprint's edge or corner, which GDAL's ``all_touched`` leaves out);
* a CityJSON roof face is the plane of its outer ring (Newell normal through the vertex mean); a
  linear function's maximum over the face-cell intersection lies at one of its vertices: the
  face's vertices in the cell, its edges' crossings of the cell sides and the cell corners inside
  the face, all three visited.  A non-planar face adds its largest vertex deviation from that
  plane (an upper bound of any triangulation of it), clamped to the face's z range; a vertical or
  degenerate face typed as roof gives its top along its trace.  A ridge keeps its height in
  every cell it crosses (sampling faces at cell centres and corners cut thin roof parts).

Static obstacles announced during a flight (a crane: polygon + height above ground) are burnt
into ``surface`` by :func:`burn_obstacles`: every touched cell (as above) takes at least the
highest ground under the polygon plus the obstacle's height.

The cost grows with the polygons' perimeter and area in cells (vertices, grid-line crossings,
interior cell corners), not with the grid.  :func:`~skyroute.stages.grid.ring_cells` (centre-in
scanline fill) stays for land use, where a cell takes the class at its centre.

DEM and DSM rasters (``data.terrain``, ``data.surface``)
-------------------------------------------------------
Both are read by window at their native resolution (a GeoTIFF, a VRT or a list of tiles), never
bilinearly.  A DSM is resampled by the footprint max (:func:`~skyroute.stages.grid.footprint_resample`:
every source pixel overlapping the cell counts, in any CRS): ``surface`` is the highest point of
the DSM over the cell (and of the buildings: surface = max of both).  A DEM is a set of samples of
a continuous surface (:func:`terrain_from_dem`, :func:`patch_resample`): ``terrain`` (minimum-AGL
floors) is the highest and ``terrain_min`` (maximum-AGL ceilings) the lowest sample of every
lattice square touching the cell.  NoData: each connected region inside the extent, also one
touching the raster's edge, takes the highest height on its rim within the raster (DSM
``nodata: fill-max``, the default; ``fill-nearest``; ``error``), with a warning giving the share of
the AOI filled; a DEM's regions take the highest rim height for ``terrain`` and the lowest for
``terrain_min``; AOI cells outside the extent are an error giving the ``aoi.bounds`` that fit.
Read strictly (:func:`~skyroute.stages.grid.raster_header`): heights are converted to metres from
the declared vertical unit (the CRS's vertical axis, e.g. US survey feet in ``EPSG:32611+6360``, or
the band's unit, with its scale and offset; a unit that cannot be converted is refused), a
bottom-up raster is read flipped, and a raster georeferenced by GCPs only, rotated, truncated or
corrupt is refused naming the file and the fix; the window's memory is checked against
``--max-memory`` from the header, before any pixel is read, also while it grows over NoData.
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

import dataclasses
import json
import re
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np
import shapely
import xarray as xr
from pyproj import CRS, Transformer
from scipy.interpolate import NearestNDInterpolator
from scipy.spatial import Delaunay, QhullError

from skyroute.stages.base import DataError, InputError
from skyroute.stages.cityjson import read_buildings
from skyroute.stages.grid import (
    NODATA_POLICIES,
    Grid,
    coverage_problem,
    fill_holes,
    filled_share,
    footprint_resample,
    read_window_holes,
    regions_in_aoi,
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
#: A tagged building height above this [m] is not a height (the tallest building is 828 m): it is
#: taken as this value (conservative) with a warning.
MAX_BUILDING_HEIGHT_M = 1000.0
#: A tagged ``building:levels`` / ``roof:levels`` above this is not a storey count (the tallest
#: building has 163): it is taken as this value (conservative) with a warning.
MAX_BUILDING_LEVELS = 200.0
_FT = 0.3048
_NUMBER = r"[+-]?(?:[0-9]+[.,]?[0-9]*|[.,][0-9]+)(?:[eE][+-]?[0-9]+)?|[+-]?(?:nan|inf|infinity)"
_NUM = re.compile(rf"^\s*({_NUMBER})\s*(m|metres|meters|metre|meter|ft|feet|foot|')?\s*$", re.IGNORECASE)
_FEET_INCHES = re.compile(r"^\s*([0-9]+)\s*'\s*([0-9]+(?:\.[0-9]+)?)\s*(?:\"|'')\s*$")


def _parse_one_m(text: str) -> float | None:
    """One height value [m] (``"12"``, ``"12.5 m"``, ``"40 ft"``, ``"40'"``, ``"3'6\""``), the
    number as written (negative, non-finite or huge values included); None if unparsable."""
    m = _FEET_INCHES.match(text)
    if m:
        return (float(m.group(1)) + float(m.group(2)) / 12.0) * _FT
    m = _NUM.match(text)
    if not m:
        return None
    num = m.group(1)
    v = float(num.replace(",", ".")) if not ("," in num and "." in num) else None
    if v is None:
        return None
    unit = (m.group(2) or "m").lower()
    return v * _FT if unit in ("ft", "feet", "foot", "'") else v


def parse_height_m(text: str) -> float | None:
    """A height tag in metres: ``"12"``, ``"12.5 m"``, ``"40 ft"``, ``"3'6\""``; None if unparsable.

    OSM separates several values with ``;``: the highest is taken.  The number is returned as
    written (it may be negative, non-finite or implausibly large: :func:`osm_building_height`
    judges it).

    Parameters
    ----------
    text : str
        The tag value; units ``m``/``metres``/``meters`` (default) or ``ft``/``feet``/``'``
        (international feet, 0.3048 m), feet and inches ``3'6"``; a decimal comma is understood.

    Returns
    -------
    float or None
        The height [m] (the highest of ``;``-separated values that parse), or None when
        ``text`` is empty or no value parses.
    """
    vals = [v for v in (_parse_one_m(t) for t in (text or "").split(";") if t.strip()) if v is not None]
    if not vals:
        return None
    return max(vals, key=lambda v: (not np.isnan(v), v))


def _tag_value(tags: dict[str, str], key: str, limit: float, unit: str, problems: list[str] | None,
               levels: bool = False) -> float | None:
    """The usable value of the height-like tag ``key`` (``;``-separated values: the highest
    usable one), None when the tag is absent or holds no usable value.  A value above ``limit``
    (``+inf`` included) is taken as ``limit`` (conservative); an unparsable, NaN, negative or zero
    value is unusable.  Each such case appends one text to ``problems``."""
    if key not in tags:
        return None
    raw = tags[key]
    parts = [t for t in str(raw).split(";") if t.strip()] or [""]
    good: list[float] = []
    bad: list[str] = []
    for t in parts:
        v = _parse_one_m(t) if not levels else _parse_levels(t)
        if v is None or np.isnan(v):
            bad.append("not a number" + ("" if levels else " (with an optional unit m or ft)"))
        elif v <= 0 and not (levels and v == 0 and key == "roof:levels"):
            bad.append("not above 0")
        elif v > limit:
            bad.append(f"above {limit:g} {unit}: taken as {limit:g} {unit}")
            good.append(limit)
        else:
            good.append(v)
    if bad and problems is not None:
        problems.append(f"{key}={raw!r} ({'; '.join(dict.fromkeys(bad))})")
    return max(good) if good else None


def _parse_levels(text: str) -> float | None:
    m = _NUM.match(text)
    if not m or m.group(2):
        return None
    num = m.group(1)
    return float(num.replace(",", ".")) if not ("," in num and "." in num) else None


def osm_building_height(tags: dict[str, str], storey_height_m: float = STOREY_HEIGHT_M,
                        problems: list[str] | None = None) -> tuple[float, str]:
    """(height [m], source) of an OSM building from its tags (see module docstring).

    ``height``, else (``building:levels`` + ``roof:levels``) x ``storey_height_m``, else the default
    for its ``building=*`` type in :data:`DEFAULT_HEIGHT_BY_TYPE_M`.  Several ``;``-separated
    values: the highest.  Conservative on broken tags, never silently lower than the tags may
    mean: a value above :data:`MAX_BUILDING_HEIGHT_M` / :data:`MAX_BUILDING_LEVELS` (``inf``
    included) is taken as that maximum; a ``height`` that is unparsable, NaN, negative or zero is
    replaced by the *highest* of the levels' height and the type's default (source
    ``"levels*"`` / ``"default*:<type>"``); an unusable ``building:levels`` falls back to the
    type's default.  Each such tag appends one text to ``problems`` (the caller names the way).

    Parameters
    ----------
    tags : dict of str to str
        The OSM tags of the building (or building part).
    storey_height_m : float, default :data:`STOREY_HEIGHT_M`
        Height of one storey [m].
    problems : list of str, optional
        Receives one text per unusable or implausible tag (``"height='nan' (not a number ...)"``).

    Returns
    -------
    height_m : float
        Building height above ground [m].
    source : str
        ``"height"``, ``"levels"`` or ``"default:<building type>"`` (with ``*`` when a broken
        ``height`` tag was replaced).
    """
    h = _tag_value(tags, "height", MAX_BUILDING_HEIGHT_M, "m", problems)
    if h is not None:
        return h, "height"
    broken = "height" in tags
    lv = _tag_value(tags, "building:levels", MAX_BUILDING_LEVELS, "levels", problems, levels=True)
    btype = tags.get("building", tags.get("building:part", "yes"))
    default = DEFAULT_HEIGHT_BY_TYPE_M.get(btype, DEFAULT_HEIGHT_BY_TYPE_M["yes"])
    star = "*" if broken else ""
    if lv is not None:
        roof = _tag_value(tags, "roof:levels", MAX_BUILDING_LEVELS, "levels", problems, levels=True) or 0.0
        by_levels = (lv + roof) * storey_height_m
        if not broken or by_levels >= default:
            return by_levels, f"levels{star}"
    return default, f"default{star}:{btype}"


def osm_height_warnings(problems: list[tuple[int, str]], key: str | None = "data.buildings",
                        show: int = 5) -> list[str]:
    """The warnings of the buildings whose height tags were coerced: one line with the count,
    the first ``show`` OSM ids and their tags, and the rule applied.

    Parameters
    ----------
    problems : list of (int, str)
        ``(OSM id, text)`` per building (the texts of :func:`osm_building_height`).
    key : str or None, default "data.buildings"
        The scenario key the message starts with (None: none).
    show : int, default 5
        How many buildings the message lists.

    Returns
    -------
    list of str
        Empty or one warning.
    """
    if not problems:
        return []
    ids = sorted({i for i, _ in problems})
    first = "; ".join(f"way/relation {i}: {t}" for i, t in problems[:show])
    more = f"; and {len(problems) - show} more" if len(problems) > show else ""
    return [f"{key + ': ' if key else ''}{len(ids)} OSM building(s) with an unusable or implausible height tag ({first}{more}): a value "
            f"above {MAX_BUILDING_HEIGHT_M:g} m / {MAX_BUILDING_LEVELS:g} levels is taken as that maximum, an "
            "unusable height as the highest of its levels and its type's default height; fix the tags in OSM "
            "for real heights"]


@dataclass(frozen=True)
class BuildingRaster:
    """Rasterised buildings: ``top`` [m] (NaN where none), ``index`` (-1 where none) and a table.

    Attributes
    ----------
    top : numpy.ndarray
        ``(ny, nx)``: highest building point over each cell [m], NaN where none.
    index : numpy.ndarray of int32
        ``(ny, nx)``: index into the building table, -1 where none.
    ids : numpy.ndarray of int64
        ``(n_buildings,)``: OSM id (CityJSON: index).
    heights_m : numpy.ndarray
        ``(n_buildings,)``: building height [m] (above ground for OSM, absolute roof top for
        CityJSON).
    sources : numpy.ndarray of str
        ``(n_buildings,)``: where each height comes from.
    absolute : bool
        True: ``top`` is an absolute height; False: height above ground.
    terrain : numpy.ndarray or None
        CityJSON with a ``TINRelief`` only: the TIN's maximum over each cell [m], NaN where the
        TIN does not reach the cell; None otherwise.
    terrain_min : numpy.ndarray or None
        The TIN's minimum over each cell [m].
    tin_full : numpy.ndarray of bool or None
        Cells the TIN covers whole.
    warnings : tuple of str
        Stage warnings (e.g. OSM height tags coerced, :func:`osm_height_warnings`).
    """

    top: np.ndarray
    index: np.ndarray
    ids: np.ndarray
    heights_m: np.ndarray
    sources: np.ndarray
    absolute: bool  # True: ``top`` is an absolute height; False: height above ground
    terrain: np.ndarray | None = None
    terrain_min: np.ndarray | None = None   # the TIN's minimum over each cell
    tin_full: np.ndarray | None = None      # cells the TIN covers whole
    warnings: tuple[str, ...] = ()          # coerced heights (stage warnings)


# --------------------------------------------------------------------------- polygon-over-cell maxima
#: Cells are closed squares: a point within this many cells [1] of a grid line counts on both sides
#: (absorbs the ~1e-11 rounding of map coordinates; never shrinks a footprint).
_EDGE_EPS_CELLS = 1e-9
#: A face whose unit normal has |n_z| below this is treated as vertical: its cells take its top.
_STEEP_NZ = 1e-3


@numba.njit(cache=True)
def _put(top, index, owner, u, v, z):  # pragma: no cover - compiled
    """Raise every cell whose closed square holds the grid point (u, v) [cells] to ``z``."""
    ny, nx = top.shape
    eps = _EDGE_EPS_CELLS
    c0 = max(int(np.ceil(u - 1.0 - eps)), 0)
    c1 = min(int(np.floor(u + eps)), nx - 1)
    r0 = max(int(np.ceil(v - 1.0 - eps)), 0)
    r1 = min(int(np.floor(v + eps)), ny - 1)
    for r in range(r0, r1 + 1):
        for c in range(c0, c1 + 1):
            if z > top[r, c]:
                top[r, c] = z
                index[r, c] = owner


@numba.njit(cache=True)
def _polygon_max_kernel(xs, ys, zs, ring_off, poly_off, owner, x0, y1, res, top, index):  # pragma: no cover
    """For every polygon p (rings ``ring_off[poly_off[p]:poly_off[p+1]]``, the first one outer,
    vertices (xs, ys, zs) [m]): every cell whose closed square meets the polygon (even-odd rule)
    takes max(current, upper bound of the polygon's height over the cell), owner ``owner[p]``.

    Height: the Newell plane of the outer ring through its vertex mean, plus the largest vertex
    deviation from that plane, clamped to the polygon's z range (exact for a planar face; an upper
    bound of every triangulation of a non-planar one).  A linear function's maximum over the
    polygon-cell intersection lies at one of its vertices: the polygon's vertices in the cell, its
    edges' crossings of the cell's sides and the cell corners inside the polygon -- all three
    sets are visited, so the bound holds for every point of the cell."""
    eps = _EDGE_EPS_CELLS
    nmax = 1
    for p in range(poly_off.size - 1):
        nmax = max(nmax, ring_off[poly_off[p + 1]] - ring_off[poly_off[p]])
    cross = np.empty(nmax, np.float64)
    for p in range(poly_off.size - 1):
        rs, re_ = poly_off[p], poly_off[p + 1]
        vs, ve = ring_off[rs], ring_off[re_]
        os_, oe = ring_off[rs], ring_off[rs + 1]
        if oe - os_ < 3:
            continue
        own = owner[p]
        # Newell normal and vertex mean of the outer ring
        nx_ = 0.0
        ny_ = 0.0
        nz_ = 0.0
        cx = 0.0
        cy = 0.0
        cz = 0.0
        for i in range(os_, oe):
            j = i + 1 if i + 1 < oe else os_
            nx_ += (ys[i] - ys[j]) * (zs[i] + zs[j])
            ny_ += (zs[i] - zs[j]) * (xs[i] + xs[j])
            nz_ += (xs[i] - xs[j]) * (ys[i] + ys[j])
            cx += xs[i]
            cy += ys[i]
            cz += zs[i]
        m = oe - os_
        cx /= m
        cy /= m
        cz /= m
        nn = np.sqrt(nx_ * nx_ + ny_ * ny_ + nz_ * nz_)
        zlo = zs[vs]
        zhi = zs[vs]
        for i in range(vs, ve):
            zlo = min(zlo, zs[i])
            zhi = max(zhi, zs[i])
        steep = nn == 0.0 or abs(nz_) < _STEEP_NZ * nn
        a = 0.0
        b = 0.0
        dev = 0.0
        if not steep:
            a = -nx_ / nz_
            b = -ny_ / nz_
            for i in range(vs, ve):
                dev = max(dev, abs(zs[i] - (cz + a * (xs[i] - cx) + b * (ys[i] - cy))))
        # 1. the polygon's vertices
        umin = np.inf
        umax = -np.inf
        vmin = np.inf
        vmax = -np.inf
        for i in range(vs, ve):
            u = (xs[i] - x0) / res
            v = (y1 - ys[i]) / res
            umin = min(umin, u)
            umax = max(umax, u)
            vmin = min(vmin, v)
            vmax = max(vmax, v)
            z = zhi if steep else min(max(cz + a * (xs[i] - cx) + b * (ys[i] - cy) + dev, zlo), zhi)
            _put(top, index, own, u, v, z)
        # 2. every ring edge's crossings of the grid lines x = x0 + k res and y = y1 - k res
        for q in range(rs, re_):
            s0, s1 = ring_off[q], ring_off[q + 1]
            for i in range(s0, s1):
                j = i + 1 if i + 1 < s1 else s0
                ua = (xs[i] - x0) / res
                ub = (xs[j] - x0) / res
                va = (y1 - ys[i]) / res
                vb = (y1 - ys[j]) / res
                if ua != ub:
                    for k in range(int(np.ceil(min(ua, ub) - eps)), int(np.floor(max(ua, ub) + eps)) + 1):
                        t = min(max((k - ua) / (ub - ua), 0.0), 1.0)
                        x = xs[i] + t * (xs[j] - xs[i])
                        y = ys[i] + t * (ys[j] - ys[i])
                        z = zhi if steep else min(max(cz + a * (x - cx) + b * (y - cy) + dev, zlo), zhi)
                        _put(top, index, own, float(k), va + t * (vb - va), z)
                if va != vb:
                    for k in range(int(np.ceil(min(va, vb) - eps)), int(np.floor(max(va, vb) + eps)) + 1):
                        t = min(max((k - va) / (vb - va), 0.0), 1.0)
                        x = xs[i] + t * (xs[j] - xs[i])
                        y = ys[i] + t * (ys[j] - ys[i])
                        z = zhi if steep else min(max(cz + a * (x - cx) + b * (y - cy) + dev, zlo), zhi)
                        _put(top, index, own, ua + t * (ub - ua), float(k), z)
        # 3. grid nodes (cell corners) strictly inside: scanline along each grid row line, even-odd
        #    over all rings (nodes on the boundary were visited as edge crossings)
        ny, nx = top.shape
        for k in range(max(int(np.ceil(vmin)), 0), min(int(np.floor(vmax)), ny) + 1):
            yk = y1 - k * res
            nc = 0
            for q in range(rs, re_):
                s0, s1 = ring_off[q], ring_off[q + 1]
                for i in range(s0, s1):
                    j = i + 1 if i + 1 < s1 else s0
                    if (ys[i] > yk) != (ys[j] > yk):
                        cross[nc] = (xs[i] + (yk - ys[i]) * (xs[j] - xs[i]) / (ys[j] - ys[i]) - x0) / res
                        nc += 1
            if nc < 2:
                continue
            cs = np.sort(cross[:nc])
            for w in range(0, nc - 1, 2):
                for c in range(max(int(np.ceil(cs[w])), 0), min(int(np.floor(cs[w + 1])), nx) + 1):
                    x = x0 + c * res
                    z = zhi if steep else min(max(cz + a * (x - cx) + b * (yk - cy) + dev, zlo), zhi)
                    _put(top, index, own, float(c), float(k), z)


def polygon_max(polygons, grid: Grid, owner=None) -> tuple[np.ndarray, np.ndarray]:
    """Rasterise 3-D polygons conservatively: each cell takes the highest point [m] of every polygon over it.

    Each cell of ``grid`` takes the highest point of every polygon over the cell's closed square
    (NaN where no polygon touches it) and the ``owner`` of the polygon giving that maximum.
    Planes, deviations and the candidate points are described in :func:`_polygon_max_kernel`; a
    compiled kernel visits each polygon's vertices, its edges' grid-line crossings and its interior
    cell corners, so the cost grows with the polygons' perimeter and area in cells, not with the
    grid.

    Parameters
    ----------
    polygons : sequence of sequence of array_like
        Each polygon a sequence of rings (the first the outer one, then holes), each ring an
        ``(n, 3)`` array of map x, y [m] and z [m] (not closed; a flat footprint has a constant z).
    grid : Grid
        The grid.
    owner : array_like of int, optional
        Per polygon, the value written to ``index``; default: the polygon number.

    Returns
    -------
    top : numpy.ndarray
        float64 ``(ny, nx)``: highest point over each cell [m], NaN where no polygon touches it.
    index : numpy.ndarray of int32
        ``(ny, nx)``: ``owner`` of the polygon giving ``top``, -1 where none.
    """
    rings = [np.asarray(r, np.float64).reshape(-1, 3) for poly in polygons for r in poly]
    if not rings:
        return np.full(grid.shape, np.nan), np.full(grid.shape, -1, np.int32)
    P = np.vstack(rings)
    ring_off = np.concatenate([[0], np.cumsum([len(r) for r in rings])]).astype(np.int64)
    poly_off = np.concatenate([[0], np.cumsum([len(poly) for poly in polygons])]).astype(np.int64)
    own = np.arange(len(polygons)) if owner is None else np.asarray(owner)
    return _polygon_max_flat(P, ring_off, poly_off, own, grid)


def _polygon_max_flat(P: np.ndarray, ring_off: np.ndarray, poly_off: np.ndarray, owner: np.ndarray,
                      grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """:func:`polygon_max` on flat arrays: vertices ``P`` (n, 3), ring k = ``P[ring_off[k]:ring_off[k+1]]``,
    polygon p = rings ``poly_off[p]:poly_off[p+1]``."""
    top = np.full(grid.shape, -np.inf)
    index = np.full(grid.shape, -1, np.int32)
    _polygon_max_kernel(np.ascontiguousarray(P[:, 0], np.float64), np.ascontiguousarray(P[:, 1], np.float64),
                        np.ascontiguousarray(P[:, 2], np.float64), np.ascontiguousarray(ring_off, np.int64),
                        np.ascontiguousarray(poly_off, np.int64), np.ascontiguousarray(owner, np.int32),
                        float(grid.x0), float(grid.y1), float(grid.resolution_m), top, index)
    top[index < 0] = np.nan
    return top, index


def _to_grid_geoms(geoms, src_crs: CRS, grid: Grid):
    if CRS.from_user_input(src_crs) == grid.crs:
        return geoms
    t = Transformer.from_crs(src_crs, grid.crs, always_xy=True)
    return [shapely.transform(g, lambda xy: np.column_stack(t.transform(xy[:, 0], xy[:, 1]))) for g in geoms]


def osm_building_footprints(path: str | Path, storey_height_m: float = STOREY_HEIGHT_M,
                            problems: list[tuple[int, str]] | None = None
                            ) -> tuple[list[int], list[float], list[str], list]:
    """The building footprints of an OSM extract.

    Every area tagged ``building`` or ``building:part``, heights from
    :func:`osm_building_height` (the one reading of building heights: :func:`osm_buildings`
    and the mosaic-city generator use it).

    Parameters
    ----------
    path : str or Path
        OSM extract (``.osm.pbf`` or ``.osm``).
    storey_height_m : float
        Height of one storey [m], for buildings tagged with ``building:levels`` only.
    problems : list of (int, str), optional
        Receives ``(OSM id, text)`` for every unusable or implausible height tag
        (:func:`osm_building_height`; :func:`osm_height_warnings` words them).

    Returns
    -------
    tuple of list
        (OSM ids, heights above ground [m], height sources, shapely footprints in WGS 84
        lon/lat [deg]), one entry per footprint.
    """
    ids, hs, srcs, geoms = [], [], [], []
    for f in read_osm(path, keys=["building", "building:part"]):
        if f.kind != "area":
            continue
        why: list[str] = []
        h, src = osm_building_height(f.tags, storey_height_m, why)
        if why and problems is not None:
            problems.append((f.osm_id, ", ".join(why)))
        ids.append(f.osm_id)
        hs.append(h)
        srcs.append(src)
        geoms.append(f.geometry)
    return ids, hs, srcs, geoms


def osm_buildings(path: str | Path, grid: Grid, storey_height_m: float = STOREY_HEIGHT_M) -> BuildingRaster:
    """Rasterise the building footprints of an OSM extract with their heights above ground.

    Every cell touched by a footprint takes its height, the highest building where several touch
    it (:func:`polygon_max`); heights from :func:`osm_building_height`.

    Parameters
    ----------
    path : str or pathlib.Path
        OSM extract (WGS 84).
    grid : Grid
        The grid.
    storey_height_m : float, default :data:`STOREY_HEIGHT_M`
        Height of one storey [m].

    Returns
    -------
    BuildingRaster
        With ``absolute=False`` (heights above ground); ``warnings``: the buildings in the AOI
        whose height tags were coerced (:func:`osm_height_warnings`).

    Raises
    ------
    DataError
        When the OSM file is missing or unreadable.
    """
    problems: list[tuple[int, str]] = []
    ids, hs, srcs, geoms = osm_building_footprints(path, storey_height_m, problems)
    xmin, ymin, xmax, ymax = grid.bounds
    geoms = _to_grid_geoms(geoms, CRS.from_epsg(4326), grid)
    keep = [i for i, g in enumerate(geoms) if g.intersects(shapely.box(xmin, ymin, xmax, ymax))]
    kept = {ids[i] for i in keep}
    raster = _rasterize_flat(grid, [geoms[i] for i in keep], np.array(hs)[keep] if keep else np.zeros(0),
                             np.array(ids, dtype=np.int64)[keep] if keep else np.zeros(0, np.int64),
                             np.array(srcs, dtype=object)[keep] if keep else np.zeros(0, object), absolute=False)
    warns = osm_height_warnings([(i, t) for i, t in problems if i in kept])
    return dataclasses.replace(raster, warnings=tuple(warns)) if warns else raster


def _rasterize_flat(grid: Grid, geoms, heights, ids, sources, absolute: bool) -> BuildingRaster:
    """Flat-topped footprints (shapely (Multi)Polygons in the grid CRS, ``heights`` [m]): every cell
    whose closed square meets a footprint (holes respected) takes the highest such height
    (:func:`polygon_max`); ``index`` names the building giving it."""
    heights = np.asarray(heights, dtype=np.float64)
    polys, owner = [], []
    for i, g in enumerate(geoms):
        for part in getattr(g, "geoms", [g]):
            if part.is_empty or part.geom_type != "Polygon":
                continue
            rings = [part.exterior, *part.interiors]
            polys.append([np.column_stack([np.asarray(r.coords)[:-1, :2], np.full(len(r.coords) - 1, heights[i])])
                          for r in rings])
            owner.append(i)
    top, index = polygon_max(polys, grid, owner)
    return BuildingRaster(top, index, np.asarray(ids, np.int64), heights,
                          np.asarray(sources, dtype=object).astype(str), absolute)


def cityjson_buildings(path: str | Path, grid: Grid) -> tuple[BuildingRaster, np.ndarray]:
    """Rasterise CityJSON Building/BuildingPart roofs (absolute heights [m]) on ``grid``.

    Each cell takes the highest point of every roof face over the cell (:func:`polygon_max`).
    Reading and face classification: :func:`skyroute.stages.cityjson.read_buildings`.

    Parameters
    ----------
    path : str or pathlib.Path
        CityJSON file.
    grid : Grid
        The grid (the file's vertices are transformed to its CRS).

    Returns
    -------
    raster : BuildingRaster
        With ``absolute=True``; a ``TINRelief`` gives ``raster.terrain`` (its maximum over each
        cell), ``raster.terrain_min`` and ``raster.tin_full``.
    ground_points : numpy.ndarray
        ``(n, 3)`` ground points (x, y, z [m] in the grid CRS) for terrain; a ``TINRelief``'s
        vertices are among them.  ``raster.warnings``: the reading's counted coercions
        (:attr:`skyroute.stages.cityjson.CityJSONDocument.warnings`, the lines ``skyroute
        inspect`` shows).

    Raises
    ------
    DataError
        When the file is missing, not CityJSON, has no readable reference system, or is refused by
        the strict reading (:func:`skyroute.stages.cityjson.load_cityjson`: a bad ``transform``,
        vertex, coordinate, boundary nesting, vertex index or geometry template).
    """
    b = read_buildings(path, grid.crs, steep_nz=_STEEP_NZ)
    V, faces = b.vertices_m, b.faces
    roof_i = np.flatnonzero(b.is_roof)
    top, index = polygon_max([[V[np.asarray(r)] for r in faces[i]] for i in roof_i], grid, b.owner[roof_i])
    tin = tin_min = tin_full = None
    if b.tin_faces:
        polys = [[V[np.asarray(r)] for r in f] for f in b.tin_faces]
        tin, _ = polygon_max(polys, grid)
        tin_min = -polygon_max([[P * np.array([1.0, 1.0, -1.0]) for P in poly] for poly in polys], grid)[0]
        tin_full = _covered_cells(polys, grid) & np.isfinite(tin)
    raster = BuildingRaster(top, index, np.arange(len(b.ids), dtype=np.int64), b.roof_top_m(),
                            np.asarray(["cityjson:" + i for i in b.ids]), absolute=True, terrain=tin,
                            terrain_min=tin_min, tin_full=tin_full,
                            warnings=tuple(f"data.buildings: {w}" for w in b.warnings))
    ground = b.ground_points()
    # the reading bounds every vertex (finite, plausible heights): a non-finite height here is a bug
    if not (np.isfinite(top[index >= 0]).all() and np.isfinite(ground).all()
            and (tin is None or not np.isinf(tin).any() and not np.isinf(tin_min).any())):
        raise DataError(f"{path}: the CityJSON gives non-finite heights after reading; report this file")
    return raster, ground


def _covered_cells(polys, grid: Grid) -> np.ndarray:
    """Cells whose closed square lies within the union of ``polys`` (outer rings, map x, y [m]):
    every cell the complement (the grid's box minus the union) does not touch."""
    r = grid.resolution_m
    x0, y0, x1, y1 = grid.bounds
    try:    # the reading refuses TIN faces that cross themselves (cityjson._check_tin_faces)
        union = shapely.union_all([shapely.Polygon(np.asarray(p[0])[:, :2]) for p in polys])
        rest = shapely.box(x0 - r, y0 - r, x1 + r, y1 + r).difference(union)
    except shapely.errors.GEOSException as exc:
        raise DataError(f"the CityJSON TINRelief faces cannot be united into the terrain's coverage ({exc}); "
                        "re-triangulate the TIN (faces that do not cross or overlap)") from None
    parts = [g for g in getattr(rest, "geoms", [rest]) if g.geom_type == "Polygon" and not g.is_empty]
    if not parts:
        return np.ones(grid.shape, bool)
    rings = [[np.column_stack([np.asarray(ring.coords)[:-1, :2], np.zeros(len(ring.coords) - 1)])
              for ring in (g.exterior, *g.interiors)] for g in parts]
    _, index = polygon_max(rings, grid)
    return index < 0


def terrain_from_points(points: np.ndarray, grid: Grid, tin: np.ndarray | None = None, *,
                        lowest: bool = False, tin_full: np.ndarray | None = None) -> np.ndarray:
    """Terrain [m] from scattered ground points: linear on their Delaunay triangles, maximum over each cell.

    Each cell the maximum of that surface over the cell (:func:`polygon_max`; conservative for
    floors, like the surface); cells outside the points' hull take the nearest point's height.

    Parameters
    ----------
    points : numpy.ndarray
        ``(n, 3)`` ground points, map x, y [m] and height z [m].
    grid : Grid
        The grid.
    tin : numpy.ndarray, optional
        ``(ny, nx)``, CityJSON ``TINRelief``: its maximum over each cell,
        :attr:`BuildingRaster.terrain`, or with ``lowest`` its minimum,
        :attr:`BuildingRaster.terrain_min`: the ground where it covers the cell whole
        (``tin_full``; every cell it touches when None); a cell it covers in part takes the higher
        (``lowest``: the lower) of the TIN and the interpolation.
    lowest : bool, default False
        The minimum over each cell instead (for maximum-AGL ceilings; the same kernel on the
        negated heights, exact for the linear interpolation).
    tin_full : numpy.ndarray of bool, optional
        ``(ny, nx)``: cells the TIN covers whole.

    Returns
    -------
    numpy.ndarray
        float64 ``(ny, nx)`` terrain [m]; 0 everywhere when there are no points and no ``tin``.
    """
    if lowest:
        pts = np.asarray(points, np.float64).reshape(-1, 3) * np.array([1.0, 1.0, -1.0])
        return -terrain_from_points(pts, grid, None if tin is None else -np.asarray(tin), tin_full=tin_full)
    out = np.zeros(grid.shape)
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if len(pts):
        # one point per distinct (x, y): the highest
        order = np.lexsort((-pts[:, 2], pts[:, 1], pts[:, 0]))
        pts = pts[order]
        first = np.r_[True, np.any(np.diff(pts[:, :2], axis=0) != 0, axis=1)]
        pts = pts[first]
        lin = np.full(grid.shape, np.nan)
        if len(pts) >= 3:
            try:
                tri = Delaunay(pts[:, :2])
            except QhullError:  # collinear points: no triangle
                tri = None
            if tri is not None:
                n = len(tri.simplices)
                lin, _ = _polygon_max_flat(pts[tri.simplices.ravel()], np.arange(0, 3 * n + 1, 3),
                                           np.arange(n + 1), np.zeros(n, np.int32), grid)
        out = lin
        miss = ~np.isfinite(lin)
        if miss.any():
            r, c = np.nonzero(miss)
            out[r, c] = NearestNDInterpolator(pts[:, :2], pts[:, 2])(grid.x[c], grid.y[r])
    if tin is not None:
        has = np.isfinite(tin)
        full = has if tin_full is None else has & tin_full
        out = np.where(full, tin, np.where(has, np.fmax(tin, out), out))
    return out


def dem_sample_offset_px(path) -> tuple[float, str]:
    """Where the samples of a DEM sit, in pixels from the corner of the pixel, and a text for the attrs.

    GDAL's geotransform always describes pixel areas and moves a ``PixelIsPoint`` tie point by half
    a pixel (RFC 33), so the samples sit at the pixel centres (0.5) for ``AREA_OR_POINT=Area`` and
    ``Point`` alike -- unless GDAL is told to ignore that (``GTIFF_POINT_GEO_IGNORE=TRUE``): then
    the samples of a ``Point`` raster sit at the corners (0.0).

    Parameters
    ----------
    path : str, pathlib.Path or list of them
        The DEM (for a list of tiles, the first is read).

    Returns
    -------
    offset_px : float
        0.5 (pixel centres) or 0.0 (corners) [px].
    reading : str
        How the samples were read, for the attrs.
    """
    import os

    import rasterio
    from rasterio.env import get_gdal_config

    first = path[0] if isinstance(path, (list, tuple)) else path
    with rasterio.open(first) as src:
        aop = str(src.tags().get("AREA_OR_POINT") or "Area")
    ignore = str(get_gdal_config("GTIFF_POINT_GEO_IGNORE") or os.environ.get("GTIFF_POINT_GEO_IGNORE", "")).upper()
    if aop.lower() == "point" and ignore in ("TRUE", "YES", "ON", "1"):
        return 0.0, "samples at the pixel corners (AREA_OR_POINT=Point read with GTIFF_POINT_GEO_IGNORE)"
    return 0.5, f"samples at the pixel centres (AREA_OR_POINT={aop})"


def patch_resample(values: np.ndarray, transform, crs, grid: Grid, how: str = "max", offset_px: float = 0.5
                   ) -> np.ndarray:
    """A sampled surface on ``grid`` [m]: each cell the max (min) over the lattice squares touching it.

    ``how="max"`` gives each cell the highest sample of every lattice square (four neighbouring
    samples) that overlaps the cell, ``"min"`` the lowest.  Any surface that stays between the
    lowest and the highest sample of each lattice square (bilinear, either triangulation of the
    square, nearest sample, ...) therefore lies within ``[min, max]`` at every point of the cell.
    NaN samples take the value of the nearest sample first (the surface is extended as a constant
    beyond the outer samples: callers refuse cells outside the data's extent).

    Parameters
    ----------
    values : numpy.ndarray
        ``(sy, sx)`` samples of a continuous surface [m], NaN where none, at
        ``transform * (j + offset_px, i + offset_px)``.
    transform : affine.Affine
        Affine transform of the sample raster in ``crs``.
    crs : pyproj.CRS, str or int
        CRS of the samples.
    grid : Grid
        Target grid.
    how : {"max", "min"}, default "max"
        Reduction.
    offset_px : float, default 0.5
        Sample position within its pixel [px] (:func:`dem_sample_offset_px`).

    Returns
    -------
    numpy.ndarray
        float64 ``(ny, nx)`` [m]; all NaN when every sample is NaN.

    Raises
    ------
    InputError
        When ``how`` is neither ``"max"`` nor ``"min"``.
    """
    if how not in ("max", "min"):
        raise InputError(f"patch resampling {how!r} must be 'max' or 'min'")
    v = np.asarray(values, dtype=np.float64)
    nan = np.isnan(v)
    if nan.all():
        return np.full(grid.shape, np.nan)
    if nan.any():
        from scipy.ndimage import distance_transform_edt

        _, (ri, ci) = distance_transform_edt(nan, return_indices=True)
        v = v[ri, ci]
    v = np.pad(v, 1, mode="edge")
    red = np.maximum if how == "max" else np.minimum
    sq = red(red(v[:-1, :-1], v[1:, :-1]), red(v[:-1, 1:], v[1:, 1:]))
    from affine import Affine

    return footprint_resample(sq, transform * Affine.translation(offset_px - 1.0, offset_px - 1.0), crs, grid, how)


@dataclass(frozen=True)
class DemRaster:
    """A DEM on the grid (see :func:`terrain_from_dem`).

    Attributes
    ----------
    terrain : numpy.ndarray
        ``(ny, nx)``: highest sample of every lattice square touching the cell [m].
    terrain_min : numpy.ndarray
        ``(ny, nx)``: lowest sample of every lattice square touching the cell [m].
    notes : str
        How the DEM was read, for the attrs.
    warnings : tuple of str
        Stage warnings (NoData regions filled).
    """

    terrain: np.ndarray
    terrain_min: np.ndarray
    notes: str
    warnings: tuple[str, ...] = ()


def terrain_from_dem(path: str | Path | list, grid: Grid, *, key: str = "data.terrain") -> DemRaster:
    """A DEM (GeoTIFF, VRT or list of tiles) on ``grid`` [m], read as the continuous surface through its samples.

    Not as flat-topped squares: ``terrain`` is the highest sample of every lattice square (four
    neighbouring samples) that overlaps the cell (minimum-AGL floors), and ``terrain_min`` the
    lowest (maximum-AGL ceilings), :func:`patch_resample`; between two samples the ground can be as
    high as the higher of them.  The samples sit at the pixel centres, or at the corners for a
    ``Point`` raster GDAL reads without its half-pixel shift (:func:`dem_sample_offset_px`).
    NoData regions inside the DEM's extent (also those touching its edge) take the highest (for
    ``terrain``) / lowest (for ``terrain_min``) valid height on their rim, with a warning giving
    the share of the AOI filled.

    Parameters
    ----------
    path : str, pathlib.Path or list
        The DEM: a GeoTIFF, a VRT or a list of tiles.
    grid : Grid
        The grid.
    key : str, default "data.terrain"
        Names the scenario entry in messages.

    Returns
    -------
    DemRaster

    Raises
    ------
    DataError
        When AOI cells are outside the DEM's extent (the message says which ``aoi.bounds`` fit),
        or the file is missing or unreadable.
    CRSError
        When the DEM has no CRS.
    """
    win, holes = read_window_holes(path, grid, what="terrain DEM")
    msg = coverage_problem(win, holes, grid, what="terrain DEM", key=key)
    if msg:
        raise DataError(msg)
    off, reading = dem_sample_offset_px(path)
    hi = patch_resample(fill_holes(win, holes, "fill-max"), win.transform, win.crs, grid, "max", off)
    lo = patch_resample(fill_holes(win, holes, "fill-min"), win.transform, win.crs, grid, "min", off)
    share = filled_share(win, holes, grid)
    warns = []
    if share > 0:
        n, n_edge = regions_in_aoi(win, holes, grid)
        warns.append(f"{key}: {n} NoData region(s) of the DEM ({n_edge} touching its edge) "
                     f"cover {100 * share:.2f} % of the AOI's cells: filled with the highest height on each region's "
                     "rim within the DEM for terrain (the lowest for terrain_min); give a DEM without holes for a "
                     "surveyed ground")
    notes = (f"DEM (data.terrain) read as the surface through its samples ({reading}): terrain = the highest, "
             "terrain_min = the lowest sample of every lattice square touching the cell")
    return DemRaster(hi, lo, notes, tuple(warns))


#: Default side [m] of the square window of the grey opening that derives the ground from a DSM.
GROUND_WINDOW_M = 60.0
#: Default height [m] above the ground from which a DSM cell counts as a building (risk level 3).
BUILDING_THRESHOLD_M = 2.5


@dataclass(frozen=True)
class DsmRaster:
    """A DSM on the grid (see :func:`dsm_on_grid`).

    Attributes
    ----------
    surface : numpy.ndarray
        ``(ny, nx)``: footprint max of the DSM [m].
    surface_min : numpy.ndarray
        ``(ny, nx)``: footprint min of the DSM [m].
    ground, ground_min : numpy.ndarray or None
        ``(ny, nx)``: footprint max / min of the derived ground [m], None when not derived.
    building : numpy.ndarray of bool or None
        ``(ny, nx)``: every point of the cell higher than ground + threshold; None when the
        ground is not derived.
    n_holes : int
        NoData regions filled (under the AOI).
    notes : str
        How the DSM was read, for the attrs.
    warnings : tuple of str
        Stage warnings (NoData regions filled).
    """

    surface: np.ndarray
    surface_min: np.ndarray
    ground: np.ndarray | None
    ground_min: np.ndarray | None
    building: np.ndarray | None
    n_holes: int
    notes: str
    warnings: tuple[str, ...] = ()


def ground_from_dsm(dsm: np.ndarray, pixel_m: float, window_m: float = GROUND_WINDOW_M) -> np.ndarray:
    """Bare ground [m] under a DSM: its grey opening with a square window of side ``window_m`` [m].

    Erosion then dilation (:func:`scipy.ndimage.grey_erosion` / ``grey_dilation``) with a square
    window of an odd number of pixels.  Every object narrower than the window in some direction
    (buildings, trees, masts) is removed; the result is never above the DSM.  Buildings wider than
    the window stay (their roof is taken as ground), hill tops and ridges narrower than the window
    are lowered by the opening.

    Parameters
    ----------
    dsm : numpy.ndarray
        2-D DSM [m], square pixels; NaN pixels take no part and stay NaN.
    pixel_m : float
        Pixel side [m].
    window_m : float, default :data:`GROUND_WINDOW_M`
        Window side [m], wider than the largest building.

    Returns
    -------
    numpy.ndarray
        The ground [m], same shape as ``dsm``.

    Raises
    ------
    InputError
        When ``window_m`` is not a positive finite number.
    """
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
    """A DSM (GeoTIFF, VRT or list of tiles, read by window at its native resolution) on ``grid``.

    NoData holes inside the extent follow ``nodata``, then the max over every cell's footprint;
    with ``derive_ground`` also the ground (:func:`ground_from_dsm`, then footprint max and min)
    and the building mask (cells all of whose DSM pixels are more than ``building_threshold_m``
    above the derived ground); ``surface_min``: the DSM's footprint min.

    Parameters
    ----------
    path : str, pathlib.Path or list of them
        The DSM: a GeoTIFF, a VRT or a list of tiles.
    grid : Grid
        The grid.
    nodata : {"fill-max", "fill-nearest", "error"}, default "fill-max"
        ``fill-max``: each connected hole the highest valid height on its rim; ``fill-nearest``:
        each pixel the nearest valid one; ``error``: holes under the AOI are refused.
    derive_ground : bool, default True
        Derive the ground and the building mask from the DSM.
    ground_window_m : float, default :data:`GROUND_WINDOW_M`
        Window side of the grey opening [m].
    building_threshold_m : float, default :data:`BUILDING_THRESHOLD_M`
        Height above the derived ground from which a pixel counts as a building [m].
    key : str, default "data.surface"
        Names the scenario entry in messages.

    Returns
    -------
    DsmRaster

    Raises
    ------
    InputError
        When ``nodata`` is not one of :data:`~skyroute.stages.grid.NODATA_POLICIES`.
    DataError
        When AOI cells are outside the DSM's extent, or over NoData with ``nodata="error"``, or
        the file is missing or unreadable.
    CRSError
        When the DSM has no CRS.
    """
    if nodata not in NODATA_POLICIES:
        raise InputError(f"{key}.nodata: {nodata!r} is not one of {', '.join(NODATA_POLICIES)}")
    win, holes = read_window_holes(path, grid, what="surface DSM")
    msg = coverage_problem(win, holes, grid, what="surface DSM", key=key, holes_allowed=nodata != "error")
    if msg:
        raise DataError(msg)
    filled = fill_holes(win, holes, nodata if nodata != "error" else "fill-max")
    n, n_edge = regions_in_aoi(win, holes, grid)
    share = filled_share(win, holes, grid)
    transform, crs = win.transform, win.crs
    del win, holes   # the raw window and its hole labels: not needed past here (city-scale memory)
    surface = footprint_resample(filled, transform, crs, grid, "max")
    surface_min = footprint_resample(filled, transform, crs, grid, "min")
    notes = f"NoData regions filled under the AOI: {n} ({nodata}, {n_edge} touching the raster's edge)"
    how = ("the highest height on each region's rim within the raster" if nodata == "fill-max"
           else "the nearest valid pixel")
    warns = (f"{key}: {n} NoData region(s) of the DSM ({n_edge} touching its edge) cover "
             f"{100 * share:.2f} % of the AOI's cells: filled with {how} ({key}.nodata: {nodata}; the other choices: "
             f"{', '.join(p for p in NODATA_POLICIES if p != nodata)})",) if share > 0 else ()
    if not derive_ground:
        return DsmRaster(surface, surface_min, None, None, None, n, notes, warns)
    px = abs(transform.a)
    ok = np.isfinite(filled)
    g_src = ground_from_dsm(filled, px, ground_window_m)
    ground = footprint_resample(g_src, transform, crs, grid, "max")
    ground_min = footprint_resample(g_src, transform, crs, grid, "min")
    high = np.where(ok, (filled - g_src > building_threshold_m).astype(np.float64), np.nan)
    building = footprint_resample(high, transform, crs, grid, "min") > 0.5
    notes += (f"; ground derived from the DSM by a grey opening with a {ground_window_m:g} m square window "
              f"({int(np.ceil(ground_window_m / px)) | 1} px of {px:g} m); buildings: more than "
              f"{building_threshold_m:g} m above it over the whole cell (tall vegetation is not told apart)")
    return DsmRaster(surface, surface_min, ground, ground_min, building, n, notes, warns)


def burn_obstacles(surface: np.ndarray, terrain: np.ndarray, grid: Grid, obstacles) -> np.ndarray:
    """The surface [m] with static obstacles (e.g. cranes) burnt in, conservatively.

    Every cell whose closed square the polygon touches (:func:`polygon_max`: a corner or an edge
    counts) takes ``max(surface, top)`` with ``top`` = the highest ``terrain`` [m] (cell maxima)
    over all the cells the polygon touches + ``height_agl_m``: a rigid structure may stand on the
    highest ground under it.  An obstacle outside the grid changes nothing.

    Parameters
    ----------
    surface : numpy.ndarray
        ``grid.shape`` ``(ny, nx)`` surface [m].
    terrain : numpy.ndarray
        ``grid.shape`` ``(ny, nx)`` terrain [m] (cell maxima).
    grid : Grid
        The grid.
    obstacles : sequence of (array_like, float)
        ``(polygon, height_agl_m)``: the polygon an ``(k, 2)`` array of map x, y [m] (not
        closed), the height [m] above the ground.

    Returns
    -------
    numpy.ndarray
        A new float64 ``(ny, nx)`` array [m].
    """
    out = np.array(surface, dtype=np.float64)
    terrain = np.asarray(terrain, dtype=np.float64)
    for polygon, height_agl_m in obstacles:
        xy = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
        _, index = polygon_max([[np.column_stack([xy, np.zeros(len(xy))])]], grid)
        touched = index >= 0
        if not touched.any():
            continue  # outside the grid
        top = float(terrain[touched].max()) + float(height_agl_m)
        out[touched] = np.maximum(out[touched], top)
    return out


def build_surface(grid: Grid, *, buildings_path=None, buildings_format: str | None = None,
                  storey_height_m: float = STOREY_HEIGHT_M, terrain_path=None,
                  vertical_datum: str | None = None, surface_path=None, surface_datum: str | None = None,
                  surface_nodata: str = "fill-max", ground_window_m: float = GROUND_WINDOW_M,
                  building_threshold_m: float = BUILDING_THRESHOLD_M) -> xr.Dataset:
    """Digital surface model of ``grid`` from buildings (OSM or CityJSON), terrain (a DEM) and/or a DSM.

    Ground: the DEM if given, else the DSM's ground (:func:`ground_from_dsm`; said in the attrs and
    in ``warnings``), else CityJSON ground points, else flat 0 m.  See the module docstring for the
    rules and the vertical datum.

    Parameters
    ----------
    grid : Grid
        The scenario grid.
    buildings_path : str or pathlib.Path, optional
        OSM extract or CityJSON file.
    buildings_format : {"osm", "cityjson"}, optional
        Format of ``buildings_path`` (default OSM).
    storey_height_m : float, default :data:`STOREY_HEIGHT_M`
        Height of one storey for OSM ``building:levels`` [m].
    terrain_path : str, pathlib.Path or list, optional
        DEM: GeoTIFF, VRT or list of tiles.
    vertical_datum : str, optional
        Vertical datum of the DEM (default "EGM96 geoid" with a DEM).
    surface_path : str, pathlib.Path or list, optional
        DSM: GeoTIFF, VRT or list of tiles; heights in ``surface_datum``.
    surface_datum : str, optional
        Vertical datum of the DSM; required with ``surface_path`` and equal to
        ``vertical_datum`` when both are given.
    surface_nodata : str, default "fill-max"
        NoData policy of the DSM (see :func:`dsm_on_grid`).
    ground_window_m : float, default :data:`GROUND_WINDOW_M`
        Window side of the grey opening deriving the ground from a DSM without DEM [m].
    building_threshold_m : float, default :data:`BUILDING_THRESHOLD_M`
        Height above ground from which a DSM cell counts as a building [m].

    Returns
    -------
    xarray.Dataset
        On ``grid``: ``terrain`` [m] (ground: max over the cell), ``terrain_min`` [m] (ground: min
        over the cell), ``surface`` [m] (max of the DSM and the buildings over the cell),
        ``building_id`` and a building table (``building_osm_id``, ``building_height_m``,
        ``building_height_source``); with a DSM also ``dsm_building``.  Attrs: ``vertical_datum``,
        ``ground_source``, ``warnings`` (JSON list) when any.

    Raises
    ------
    InputError
        When ``buildings_format`` is unknown, the two vertical datums differ, or a DSM comes without
        ``surface_datum``.
    DataError
        When the AOI does not intersect any building of ``buildings_path``, or a raster does not
        cover the AOI, or a file is missing or unreadable.
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
    warns: list[str] = list(braster.warnings) if braster is not None else []
    warns.extend(dsm.warnings if dsm is not None else ())
    if terrain_path is not None:
        dem = terrain_from_dem(terrain_path, grid)
        terrain, terrain_min = dem.terrain, dem.terrain_min
        warns.extend(dem.warnings)
        datum = vertical_datum or "EGM96 geoid"
        ground_src = dem.notes
        del dem
    elif dsm is not None:
        terrain, terrain_min = dsm.ground, dsm.ground_min
        datum = surface_datum
        ground_src = dsm.notes.split("; ", 1)[1]
        warns.append(f"surface: no DEM (data.terrain): the ground is derived from the DSM by a grey opening with a "
                     f"{ground_window_m:g} m window; AGL limits, landing and the risk map's buildings use it; "
                     "give data.terrain for a surveyed ground")
    elif len(ground_pts):
        terrain = terrain_from_points(ground_pts, grid, braster.terrain, tin_full=braster.tin_full)
        terrain_min = terrain_from_points(ground_pts, grid, braster.terrain_min, lowest=True, tin_full=braster.tin_full)
        # both bounds come from the same surfaces; the min also guards the one corner case where two
        # Delaunay triangulations of cocircular points differ (lowering terrain_min is safe for ceilings)
        terrain_min = np.minimum(terrain_min, terrain)
        datum = vertical_datum or "source data heights (CityJSON; NAP for Dutch data)"
        ground_src = ("CityJSON TINRelief (max / min over each cell), building ground surfaces where it does not "
                      "reach" if braster.terrain is not None else
                      "CityJSON ground: the lowest ground surface of each building (its parts included), "
                      "interpolated")
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
    dsm_building = None
    if dsm is not None:
        np.maximum(surface, dsm.surface, out=surface)
        # with a DEM: the lowest DSM point of the cell above its highest ground point
        dsm_building = dsm.building if dsm.building is not None else dsm.surface_min - terrain > building_threshold_m
        dsm_notes = dsm.notes
        dsm = True   # its float64 rasters are no longer needed (city-scale memory)
    # float32 one layer at a time, each float64 original released before the next (city-scale memory)
    zattrs = {"units": "m", "vertical_datum": datum}
    ds = xr.Dataset()
    ds["terrain"] = grid.dataarray(terrain.astype(np.float32), "terrain",
                                   long_name="ground height (highest over the cell)", **zattrs)
    ds["terrain_min"] = grid.dataarray(terrain_min.astype(np.float32), "terrain_min",
                                       long_name="ground height (lowest over the cell)", **zattrs)
    del terrain, terrain_min
    ds["surface"] = grid.dataarray(surface.astype(np.float32), "surface",
                                   long_name="top of terrain and buildings (flat-topped prism per cell)", **zattrs)
    del surface
    ds["building_id"] = grid.dataarray(
        (braster.index if braster is not None else np.full(grid.shape, -1, np.int32)).astype(np.int32),
        "building_id", units="1", long_name="index into the building dimension, -1 where no building")
    if dsm_building is not None:
        ds["dsm_building"] = grid.dataarray(
            dsm_building, "dsm_building", units="1",
            long_name=f"DSM more than {building_threshold_m:g} m above the ground over the whole cell")
    if braster is not None:
        ds["building_osm_id"] = ("building", braster.ids, {"units": "1", "long_name": "OSM id (or CityJSON index)"})
        ds["building_height_m"] = ("building", braster.heights_m.astype(np.float32),
                                   {"units": "m", "long_name": "building height (above ground for OSM, absolute roof top for CityJSON)"})
        ds["building_height_source"] = ("building", braster.sources.astype("U32"))
    ds.attrs.update({"title": "skyroute surface model", "vertical_datum": datum,
                     "resolution_m": grid.resolution_m, "Conventions": "CF-1.10", "ground_source": ground_src})
    if dsm is not None:
        ds.attrs["dsm"] = dsm_notes
    if warns:
        ds.attrs["warnings"] = json.dumps(warns)
    return ds
