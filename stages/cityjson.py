"""CityJSON reading (1.0 / 1.1 / 2.0): the document, its CRS, the surfaces of its geometries
and the faces of its buildings, with no rasterisation (that is :mod:`skyroute.stages.surface`
for heights and :mod:`skyroute.stages.risk` for risk levels).

* :func:`load_cityjson`: the strictly validated document (:class:`CityJSONDocument`), the one
  check shared by ``skyroute inspect`` and every stage; :func:`read_cityjson` its normalised dict;
* :func:`cityjson_crs`: its horizontal CRS (``metadata.referenceSystem``);
* :func:`surface_rings` / :func:`surfaces`: the rings (vertex indices) and semantic type of every
  surface of a geometry (MultiSurface, CompositeSurface, TIN, Solid, Multi/CompositeSolid);
* :func:`read_buildings`: the Building/BuildingPart faces of a file, vertices in map
  coordinates [m] of a target CRS, classified as roofs (``RoofSurface``, ``OuterCeilingSurface``,
  ``OuterFloorSurface``, or untyped faces whose unit Newell normal has ``n_z >= steep_nz``) and
  floors (``GroundSurface``, or untyped faces facing down), with the ``TINRelief`` faces and the
  ground points for terrain (:meth:`CityJSONBuildings.ground_points`).

Strict reading (:func:`load_cityjson`): a file is refused (:class:`DataError` naming the file, the
CityObject and the fix) when its ``transform`` is not 3 + 3 finite numbers with a positive scale,
a vertex is not 3 finite numbers, a coordinate leaves the plausible range (:data:`Z_RANGE_M`,
:data:`XY_ABS_MAX_M`), a geometry's boundaries do not nest as its type says, a vertex index is
not an integer in ``0 .. n-1`` (numpy would wrap a negative one onto another building), a ring
lists more than :data:`MAX_RING_VERTICES` vertices, the semantics do not mirror the boundaries, or
a geometry template is malformed, or a ``TINRelief`` face is not a simple polygon in plan (it
crosses itself).  A
``GeometryInstance`` is resolved (CityJSON 1.1 / 2.0 "Geometry templates": the template's
``vertices-templates``, real coordinates not touched by ``transform``, times the row-major 4x4
``transformationMatrix``, plus the reference point, a vertex of ``vertices``).  What is read
with a coercion (a geometry of unknown type skipped, a building without any surface geometry, a
face of fewer than 3 vertices, no ``transform`` in a 1.1+ file) is a counted warning
(:attr:`CityJSONDocument.warnings`), shown by ``skyroute inspect`` and in the run's warnings.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pyproj import CRS, Transformer

from skyroute.stages.base import DataError, read_limited

#: A ground surface of a Building or its parts counts as ground when its lowest vertex is at most
#: this much [m] above the highest vertex of the building's lowest ground surface.
GROUND_TOLERANCE_M = 0.5
#: Semantic surface types that are the top of a building (its roof faces).
ROOF_TYPES = ("RoofSurface", "OuterCeilingSurface", "OuterFloorSurface")
#: Largest CityJSON file read [bytes]: a 3D BAG tile or a district is 10-200 MB; the parsed
#: document takes ~10x its size in memory.  Split a larger file (e.g. ``cjio ... subset --bbox``).
MAX_CITYJSON_BYTES = 1 << 30
#: Plausible heights [m] of any vertex after ``transform`` (and of a ``TerrainHeight``): the lowest
#: dry land is ~-430 m (Dead Sea shore), the highest 8849 m (Everest), and geoid / ellipsoid /
#: local datums differ by less than ~110 m, so -1000 .. 10000 m holds every real building and
#: ground with margin; a height outside is a wrong ``transform`` or unit (mm) -- and a 1e300 m
#: roof would overflow to inf in the surface.
Z_RANGE_M = (-1000.0, 10000.0)
#: Largest plausible |x| and |y| [m] after ``transform``: projected CRSs stay within ~4e7 m (the
#: Earth's circumference, false eastings included); beyond is a broken ``transform``.
XY_ABS_MAX_M = 1e8
#: Most vertices one ring of a surface may list: a real face (a roof, a wall, a ground polygon) has
#: well under a thousand; a longer ring is a broken export (every vertex of the file listed as one
#: ring), and would make the polygon geometry behind the terrain coverage (GEOS) run out of memory.
#: A whole object is bounded by the file's size (:data:`MAX_CITYJSON_BYTES`): a ``TINRelief`` may
#: hold millions of triangles.
MAX_RING_VERTICES = 100_000
#: Geometry types with surfaces (what a roof, a floor or a risk footprint is read from).
SURFACE_TYPES = ("MultiSurface", "CompositeSurface", "TIN", "Solid", "MultiSolid", "CompositeSolid")
#: The arrays each geometry type's ``boundaries`` nest, outermost first (``TIN``: a
#: CompositeSurface of triangles, accepted as such).
BOUNDARY_LEVELS: dict[str, tuple[str, ...]] = {
    "MultiPoint": ("vertex indices",),
    "MultiLineString": ("lines", "vertex indices"),
    "MultiSurface": ("surfaces", "rings", "vertex indices"),
    "CompositeSurface": ("surfaces", "rings", "vertex indices"),
    "TIN": ("surfaces", "rings", "vertex indices"),
    "Solid": ("shells", "surfaces", "rings", "vertex indices"),
    "MultiSolid": ("solids", "shells", "surfaces", "rings", "vertex indices"),
    "CompositeSolid": ("solids", "shells", "surfaces", "rings", "vertex indices"),
}
_SHOWN_IDS = 5      # object ids named in one warning


@dataclass(frozen=True)
class CityJSONDocument:
    """A CityJSON file read strictly (:func:`load_cityjson`).

    ``doc`` is the parsed document, normalised: ``doc["vertices"]`` is :attr:`vertices` (real
    coordinates, ``transform`` applied and removed from ``doc``), each ``GeometryInstance`` is
    replaced by its template's geometry on vertices appended to :attr:`vertices`.
    ``vertices`` ``(n, 3)`` [m] in the file's CRS, finite and within :data:`Z_RANGE_M` /
    :data:`XY_ABS_MAX_M`; ``warnings`` one line per kind of coercion, ``counts`` the numbers
    (keys ``unknown_geometry_types``, ``buildings_without_surfaces``, ``degenerate_faces``,
    ``missing_transform``) and ``instances`` the GeometryInstances resolved."""

    path: Path
    doc: dict
    vertices: np.ndarray
    warnings: tuple[str, ...] = ()
    counts: dict[str, int] = field(default_factory=dict)
    instances: int = 0


def _is_num(x) -> bool:
    return type(x) in (int, float)


def _three_numbers(v) -> bool:
    return type(v) is list and len(v) == 3 and all(_is_num(c) for c in v)


def _finite_numbers(v, n: int) -> bool:
    """Whether ``v`` is a JSON array of ``n`` finite numbers (an integer beyond a float is not)."""
    if type(v) is not list or len(v) != n or not all(_is_num(c) for c in v):
        return False
    try:
        return bool(np.isfinite(np.asarray(v, np.float64)).all())
    except OverflowError:
        return False


def _vertex_array(raw, path: Path, what: str) -> np.ndarray:
    """``raw`` (a JSON array of [x, y, z]) as an ``(n, 3)`` float64 array; refuses anything else,
    naming the first bad vertex (not yet checked for finiteness)."""
    if type(raw) is not list:
        raise DataError(f"{path}: {what} must be an array of [x, y, z] vertices, found {type(raw).__name__}")
    try:
        a = np.asarray(raw)
    except (ValueError, TypeError):
        a = None
    if a is None or a.dtype.kind not in "iuf" or a.ndim != 2 or (len(a) and a.shape[1] != 3):
        if not raw:
            return np.zeros((0, 3))
        k = next((i for i, v in enumerate(raw) if not _three_numbers(v)), None)
        if k is None:      # only reachable with integers beyond 64 bits
            raise DataError(f"{path}: {what} holds integers too large to be coordinates; check the exporter")
        raise DataError(f"{path}: {what}[{k}] is {str(raw[k])[:80]}: each vertex must be 3 numbers [x, y, z]; "
                        "the file is not valid CityJSON (re-export it)")
    return a.reshape(-1, 3).astype(np.float64)


def _transform(cj: dict, path: Path) -> tuple[np.ndarray, np.ndarray, bool]:
    """(scale, translate, present) of ``cj["transform"]``, validated."""
    tr = cj.get("transform")
    if tr is None:
        return np.ones(3), np.zeros(3), False
    if type(tr) is not dict:
        raise DataError(f"{path}: transform must be an object {{\"scale\": [sx, sy, sz], \"translate\": [tx, ty, tz]}}")
    out = []
    for name in ("scale", "translate"):
        v = tr.get(name)
        if not _finite_numbers(v, 3):
            raise DataError(f"{path}: transform.{name} is {str(v)[:80]}: it must be 3 finite numbers "
                            f"(e.g. \"{name}\": {[0.001] * 3 if name == 'scale' else [84616.468, 447422.999, -0.452]}); "
                            "fix or re-export the file")
        out.append(np.asarray(v, np.float64))
    if np.any(out[0] <= 0):
        raise DataError(f"{path}: transform.scale {tr['scale']} has a zero or negative component: every vertex is "
                        "multiplied by it (a scale of 0 flattens every building to 0 m); give the file's real "
                        "scale, e.g. [0.001, 0.001, 0.001] for millimetre integers (re-export the file)")
    return out[0], out[1], True


def _leaf_depths(b) -> tuple[int, int]:
    """(min, max) number of nested arrays above the non-array leaves of ``b`` (an empty array
    counts as a leaf at its depth)."""
    lo, hi = 1 << 30, 0
    stack = [(b, 0)]
    while stack:
        x, d = stack.pop()
        if type(x) is list and x:
            stack.extend((y, d + 1) for y in x)
        else:
            d = d + 1 if type(x) is list else d
            lo, hi = min(lo, d), max(hi, d)
    return (lo if hi else 0), hi


def _example(levels: tuple[str, ...]) -> str:
    return "[" * (len(levels) - 1) + "[0, 1, 2]" + "]" * (len(levels) - 1)


def _walk(b, levels: tuple[str, ...]) -> tuple[list, int, int] | None:
    """(flat vertex indices, number of surfaces whose outer ring has fewer than 3 vertices, the
    most vertices one ring or line lists) of boundaries ``b`` nesting ``levels``; None when the
    nesting is too shallow or a surface has no ring (too deep shows in the indices:
    :meth:`_Indices.check`)."""
    if type(b) is not list:
        return None
    cur = b
    few = 0
    longest = 0     # a MultiPoint has no ring
    for lv in levels[:-1]:
        nxt: list = []
        for c in cur:
            if type(c) is not list or (lv == "surfaces" and not c):
                return None
            nxt.extend(c)
        if lv == "surfaces":
            few += sum(1 for s in cur if type(s[0]) is list and len(s[0]) < 3)
        if lv in ("rings", "lines"):
            longest = max((len(c) for c in cur), default=0)
        cur = nxt
    return cur, few, longest


def _check_ring_length(path: Path, who: str, gtype: str, longest: int) -> None:
    """Refuse a geometry one of whose rings lists more than :data:`MAX_RING_VERTICES` vertices."""
    if longest > MAX_RING_VERTICES:
        raise DataError(f"{path}: {who} ({gtype}): a ring lists {longest:,} vertices, more than the "
                        f"{MAX_RING_VERTICES:,} of any real face (a broken export?); split the face or re-export "
                        "the file")


def _nesting_message(path: Path, who: str, gtype: str, b, levels: tuple[str, ...]) -> str:
    lo, hi = _leaf_depths(b)
    found = f"{hi}" if lo == hi else f"{lo} to {hi}"
    empty = " (a surface with no ring?)" if "surfaces" in levels and hi == len(levels) else ""
    return (f"{path}: {who}: a {gtype} geometry's boundaries must nest {len(levels)} levels of arrays "
            f"({' -> '.join(levels)}, e.g. {_example(levels)}), this one nests {found}{empty}: the geometry type "
            f"does not match its boundaries; fix the type or re-export the file")


def _check_semantics(path: Path, who: str, g: dict, b, levels: tuple[str, ...]) -> None:
    """Refuses ``g["semantics"]`` unless ``surfaces`` is an array of objects and ``values``
    mirrors the boundaries down to the surfaces (null: no semantics), each value an index into
    ``surfaces``."""
    sem = g.get("semantics")
    if sem is None:
        return
    bad = f"{path}: {who}: a {g['type']} geometry's semantics "
    if type(sem) is not dict or type(sem.get("surfaces", [])) is not list or any(
            type(s) is not dict for s in sem.get("surfaces", [])):
        raise DataError(bad + "must be {\"surfaces\": [{\"type\": ...}, ...], \"values\": [...]}; re-export the file")
    values = sem.get("values")
    if values is None or "surfaces" not in levels:
        return
    nsurf = len(sem.get("surfaces", []))
    stack = [(values, b, levels.index("surfaces") + 1)]
    while stack:
        v, bb, k = stack.pop()
        if v is None:
            continue
        if k == 0:
            if type(v) is not int or not 0 <= v < nsurf:
                raise DataError(bad + f"value {str(v)[:40]} is not an index into its {nsurf} semantic surfaces "
                                "(or null); re-export the file")
            continue
        if type(v) is not list or len(v) != len(bb):
            raise DataError(bad + f"values must mirror the boundaries ({' -> '.join(levels[:levels.index('surfaces') + 1])}"
                            f", one value or null per surface); they do not; re-export the file")
        stack.extend((vi, bi, k - 1) for vi, bi in zip(v, bb, strict=True))


def _lod(path: Path, who: str, g: dict) -> float:
    lod = g.get("lod", 0)
    try:
        return float(lod)
    except (TypeError, ValueError):
        raise DataError(f"{path}: {who}: lod {str(lod)[:40]!r} is not a level of detail "
                        "(a number such as 2 or \"2.2\"); fix the file") from None


class _Indices:
    """Vertex indices of many geometries, checked at once (one numpy array)."""

    def __init__(self) -> None:
        self.flat: list = []
        self.starts: list[int] = []
        self.owners: list[tuple[str, str]] = []

    def add(self, flat: list, who: str, gtype: str) -> None:
        """Add the indices of one geometry of ``who`` (``"CityObject 'id'"`` or a template)."""
        self.starts.append(len(self.flat))
        self.owners.append((who, gtype))
        self.flat.extend(flat)

    def owner_of(self, pos: int) -> tuple[str, str]:
        return self.owners[int(np.searchsorted(np.asarray(self.starts), pos, side="right")) - 1]

    def check(self, path: Path, n: int, what: str = "vertices") -> np.ndarray:
        """The indices as int64, refused unless integers in 0 .. n-1."""
        try:
            a = np.asarray(self.flat)
        except (ValueError, TypeError):
            a = None
        if a is None or a.ndim != 1 or (a.size and a.dtype.kind not in "iu"):
            pos = next((i for i, x in enumerate(self.flat) if type(x) is not int), None)
            if pos is None:     # integers too large for int64 (numpy kept them as objects)
                pos = next(i for i, x in enumerate(self.flat) if not 0 <= x < n)
                who, gtype = self.owner_of(pos)
                raise DataError(f"{path}: {who} ({gtype}): vertex index {str(self.flat[pos])[:40]} is not in "
                                f"0 .. {n - 1} ({n} {what}); the file is corrupt: re-export it")
            who, gtype = self.owner_of(pos)
            x = self.flat[pos]
            if type(x) is list:
                levels = BOUNDARY_LEVELS.get(gtype, ())
                raise DataError(f"{path}: {who}: a {gtype} geometry's boundaries nest deeper than "
                                f"{len(levels)} levels of arrays ({' -> '.join(levels)}, e.g. {_example(levels)}): "
                                "the geometry type does not match its boundaries; fix the type or re-export the file")
            raise DataError(f"{path}: {who} ({gtype}): vertex index {str(x)[:40]} is not an integer; "
                            "indices must be integers 0 .. n-1; re-export the file")
        if not a.size:
            return np.zeros(0, np.int64)
        bad = np.flatnonzero((a >= n) if a.dtype.kind == "u" else (a < 0) | (a >= n))
        if bad.size:
            pos = int(bad[0])
            who, gtype = self.owner_of(pos)
            i = int(a[pos])
            why = ("is negative (it would silently take a vertex from the end of the list, another object's)"
                   if i < 0 else f"is past the end of the {n} {what}")
            raise DataError(f"{path}: {who} ({gtype}): vertex index {i} {why}; indices must be "
                            f"0 .. {n - 1} ({n} {what}); the file is truncated or corrupt: re-export it")
        return a.astype(np.int64, copy=False)


def load_cityjson(path: str | Path) -> CityJSONDocument:
    """The CityJSON file at ``path``, read strictly (module docstring): one check shared by
    ``skyroute inspect``, the surface and the risk stages.

    Parameters
    ----------
    path : str or pathlib.Path
        The CityJSON file (1.0, 1.1 or 2.0; at most :data:`MAX_CITYJSON_BYTES`).

    Returns
    -------
    CityJSONDocument
        The normalised document, its real vertices [m] in the file's CRS and the counted
        coercions (warnings).

    Raises
    ------
    DataError
        Naming the file (and the CityObject, vertex or key) when the file is missing, too large
        (:data:`MAX_CITYJSON_BYTES`), not CityJSON, or malformed as listed in the module docstring.
    """
    path = Path(path)
    raw = read_limited(path, MAX_CITYJSON_BYTES, "CityJSON")
    try:
        cj = json.loads(raw.decode("utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"{path} is not valid CityJSON (JSON error: {exc})") from exc
    except RecursionError:
        raise DataError(f"{path} is not valid CityJSON (arrays nested too deep to be a geometry)") from None
    del raw
    if (type(cj) is not dict or cj.get("type") != "CityJSON" or "vertices" not in cj
            or type(cj.get("CityObjects")) is not dict):
        raise DataError(f"{path} is not a CityJSON file (needs type, vertices, CityObjects)")
    V = _vertex_array(cj["vertices"], path, "vertices")
    n = len(V)
    scale, translate, has_tr = _transform(cj, path)
    objects = cj["CityObjects"]
    idx = _Indices()
    unknown: dict[str, list[str]] = {}
    few = 0
    usable: dict[str, bool] = {}
    instances: list[tuple[str, int, dict]] = []      # (object id, position in its geometry list, geometry)
    for oid, obj in objects.items():
        if type(obj) is not dict:
            raise DataError(f"{path}: CityObject {oid!r} is not an object; re-export the file")
        otype = obj.get("type")
        geoms = obj.get("geometry")
        if geoms is None:
            geoms = []
        if type(geoms) is not list or any(type(g) is not dict for g in geoms):
            raise DataError(f"{path}: CityObject {oid!r}: geometry must be an array of geometry objects")
        attrs = obj.get("attributes")
        if attrs is not None and type(attrs) is not dict:
            raise DataError(f"{path}: CityObject {oid!r}: attributes must be an object")
        parents = obj.get("parents")
        if parents is not None and (type(parents) is not list or any(type(p) is not str for p in parents)):
            raise DataError(f"{path}: CityObject {oid!r}: parents must be an array of CityObject ids")
        is_bldg = otype in ("Building", "BuildingPart")
        if is_bldg:
            usable.setdefault(oid, False)
            th = (attrs or {}).get("TerrainHeight")
            if th is not None and (not _is_num(th) or not Z_RANGE_M[0] <= th <= Z_RANGE_M[1]):
                raise DataError(f"{path}: CityObject {oid!r}: attributes.TerrainHeight {str(th)[:40]} is not a height "
                                f"in {Z_RANGE_M[0]:g} .. {Z_RANGE_M[1]:g} m; fix or remove the attribute")
        for k, g in enumerate(geoms):
            gtype = g.get("type")
            if gtype == "GeometryInstance":
                instances.append((oid, k, g))
                continue
            levels = BOUNDARY_LEVELS.get(gtype) if type(gtype) is str else None
            if levels is None:
                unknown.setdefault(str(gtype), []).append(oid)
                continue
            who = f"CityObject {oid!r}"
            _lod(path, who, g)
            walked = _walk(g.get("boundaries"), levels)
            if walked is None:
                raise DataError(_nesting_message(path, who, gtype, g.get("boundaries"), levels))
            flat, nfew, longest = walked
            _check_ring_length(path, who, gtype, longest)
            _check_semantics(path, who, g, g["boundaries"], levels)
            idx.add(flat, who, gtype)
            if is_bldg and gtype in SURFACE_TYPES:
                few += nfew
                usable[oid] = usable[oid] or _has_face(g["boundaries"], levels)
    flat_idx = idx.check(path, n)
    V = V * scale + translate
    V, blocks = _resolve_instances(cj, V, instances, path, usable, objects)
    _check_coordinates(V, path, flat_idx, idx, n, blocks, has_tr, scale)
    _check_tin_faces(path, V, objects)
    cj["vertices"] = V
    cj.pop("transform", None)
    counts: dict[str, int] = {}
    warns: list[str] = []
    version = str(cj.get("version", ""))
    if not has_tr and version and not version.startswith(("0.", "1.0")):     # optional up to 1.0
        counts["missing_transform"] = 1
        warns.append(f"{path.name}: no transform (required since CityJSON 1.1): the vertices are read as real "
                     "coordinates [m]; if they are integers (millimetres, centimetres), add the file's transform")
    if unknown:
        counts["unknown_geometry_types"] = sum(len(v) for v in unknown.values())
        kinds = ", ".join(f"{t} x{len(ids)} (e.g. {ids[0]!r})" for t, ids in sorted(unknown.items()))
        nu = counts["unknown_geometry_types"]
        warns.append(f"{path.name}: {nu} geometr{'y' if nu == 1 else 'ies'} of unknown type skipped: {kinds}; "
                     f"CityJSON types are {', '.join(BOUNDARY_LEVELS)}, GeometryInstance")
    lost = _buildings_without_surfaces(usable, objects)
    if lost:
        counts["buildings_without_surfaces"] = len(lost)
        shown = ", ".join(repr(i) for i in lost[:_SHOWN_IDS]) + (", ..." if len(lost) > _SHOWN_IDS else "")
        warns.append(f"{path.name}: {len(lost)} Building(s) without any surface geometry (in it or its parts) are "
                     f"left out of the surface and the risk map: {shown}; give them a MultiSurface or Solid "
                     "geometry, or add their heights from another source (data.surface)")
    if few:
        counts["degenerate_faces"] = few
        warns.append(f"{path.name}: {few} building face(s) with fewer than 3 vertices are skipped (no area)")
    return CityJSONDocument(path, cj, V, tuple(warns), counts, len(instances))


def _has_face(b, levels: tuple[str, ...]) -> bool:
    """Whether boundaries ``b`` (validated, ``levels``) hold a surface whose outer ring has 3+ vertices."""
    cur = b
    for _ in range(levels.index("surfaces")):
        cur = [x for c in cur for x in c]
    return any(len(s[0]) >= 3 for s in cur)


def _buildings_without_surfaces(usable: dict[str, bool], objects: dict) -> list[str]:
    """Ids of the topmost Buildings (with their parts) none of which has a surface."""
    ok_root: dict[str, bool] = {}
    for oid, has in usable.items():
        root, seen = oid, {oid}
        ps = objects[oid].get("parents") or []
        while ps and ps[0] in objects and ps[0] not in seen:
            root = ps[0]
            seen.add(root)
            ps = (objects.get(root) or {}).get("parents") or []
        ok_root[root] = ok_root.get(root, False) or has
    return [r for r, ok in ok_root.items() if not ok]


def _resolve_instances(cj: dict, V: np.ndarray, instances: list, path: Path, usable: dict[str, bool],
                       objects: dict) -> tuple[np.ndarray, list[tuple[int, str]]]:
    """``V`` with the vertices of every GeometryInstance appended, each instance replaced in its
    object by its template's geometry on them: template vertex ``t`` becomes ``M[:3, :3] @ t +
    M[:3, 3] + r`` (``M`` the row-major ``transformationMatrix``, ``r`` the reference point, a
    vertex of ``vertices``, transformed; ``vertices-templates`` are real coordinates, not
    transformed).  Also returns (first appended vertex, object id) per instance.  Refuses a
    malformed template or instance."""
    if not instances:
        return V, []
    gt = cj.get("geometry-templates")
    where = f"{path}: CityObject {instances[0][0]!r} uses a GeometryInstance but "
    if type(gt) is not dict or type(gt.get("templates")) is not list:
        raise DataError(where + "the file has no geometry-templates {\"templates\": [...], \"vertices-templates\": "
                        "[...]}; re-export it with its templates")
    T = _vertex_array(gt.get("vertices-templates"), path, "geometry-templates.vertices-templates")
    if not np.isfinite(T).all() or (T.size and np.abs(T).max() > XY_ABS_MAX_M):
        k = int(np.flatnonzero(~np.isfinite(T).all(axis=1) | (np.abs(T) > XY_ABS_MAX_M).any(axis=1))[0])
        raise DataError(f"{path}: geometry-templates.vertices-templates[{k}] is {T[k].tolist()}: coordinates must "
                        f"be finite numbers within +-{XY_ABS_MAX_M:g} m; fix the template")
    templates: dict[int, tuple[dict, tuple[str, ...], np.ndarray, np.ndarray]] = {}
    extra: list[np.ndarray] = []
    blocks: list[tuple[int, str]] = []
    n_main = base = len(V)
    for oid, k, g in instances:
        what = f"{path}: CityObject {oid!r}: GeometryInstance "
        t = g.get("template")
        if type(t) is not int or not 0 <= t < len(gt["templates"]):
            raise DataError(what + f"template {str(t)[:40]} is not an index into the {len(gt['templates'])} "
                            "geometry-templates.templates; fix the file")
        if t not in templates:
            templates[t] = _template(gt["templates"][t], t, T, path)
        tg, levels, used, local = templates[t]
        ref = g.get("boundaries")
        if type(ref) is not list or len(ref) != 1 or type(ref[0]) is not int:
            raise DataError(what + f"boundaries {str(ref)[:60]} must be one vertex index [i] (the reference point)")
        if not 0 <= ref[0] < n_main:
            raise DataError(what + f"reference point index {ref[0]} is not a vertex of the file (0 .. {n_main - 1}, "
                            f"{n_main} vertices); fix the file")
        M = g.get("transformationMatrix")
        if not _finite_numbers(M, 16):
            raise DataError(what + f"transformationMatrix must be 16 finite numbers (a 4x4 matrix, row by row), "
                            f"found {str(M)[:80]}")
        M = np.asarray(M, np.float64).reshape(4, 4)
        if not np.array_equal(M[3], [0.0, 0.0, 0.0, 1.0]):
            raise DataError(what + f"transformationMatrix's last row is {M[3].tolist()}: it must be [0, 0, 0, 1] "
                            "(rotation, scaling and translation only); fix the file")
        det = float(np.linalg.det(M[:3, :3]))
        if not abs(det) > 1e-12:
            raise DataError(what + "transformationMatrix is singular (determinant 0): it would flatten the template "
                            "(e.g. a scale of 0); fix the file")
        extra.append(T[used] @ M[:3, :3].T + M[:3, 3] + V[ref[0]])
        blocks.append((base, oid))
        geoms = objects[oid]["geometry"]
        geoms[k] = {**tg, "boundaries": _offset(local, len(levels), base)}
        base += len(used)
        if objects[oid].get("type") in ("Building", "BuildingPart") and tg["type"] in SURFACE_TYPES:
            usable[oid] = usable[oid] or _has_face(tg["boundaries"], levels)
    return (np.vstack([V, *extra]) if extra else V), blocks


def _template(tg, t: int, T: np.ndarray, path: Path) -> tuple[dict, tuple[str, ...], np.ndarray, list]:
    """Template ``t`` validated: (geometry, its boundary levels, the template vertices it uses,
    its boundaries on those, numbered 0 .. len(used)-1)."""
    name = f"geometry-templates.templates[{t}]"
    gtype = tg.get("type") if type(tg) is dict else None
    levels = BOUNDARY_LEVELS.get(gtype) if type(gtype) is str else None
    if levels is None:
        raise DataError(f"{path}: {name} has type {str(gtype)[:40]!r}: a template must be a geometry "
                        f"({', '.join(BOUNDARY_LEVELS)}); fix the file")
    _lod(path, name, tg)
    walked = _walk(tg.get("boundaries"), levels)
    if walked is None:
        raise DataError(_nesting_message(path, name, gtype, tg.get("boundaries"), levels))
    _check_ring_length(path, name, gtype, walked[2])
    _check_semantics(path, name, tg, tg["boundaries"], levels)
    idx = _Indices()
    idx.add(walked[0], name, gtype)
    flat = idx.check(path, len(T), "vertices-templates")
    used, inverse = np.unique(flat, return_inverse=True)
    it = iter(inverse.tolist())
    return tg, levels, used, _rebuild(tg["boundaries"], len(levels), it)


def _rebuild(b: list, depth: int, it) -> list:
    """``b`` (``depth`` levels of arrays) with its indices replaced, in order, by those of ``it``."""
    if depth == 1:
        return [next(it) for _ in b]
    return [_rebuild(x, depth - 1, it) for x in b]


def _offset(b: list, depth: int, off: int) -> list:
    if depth == 1:
        return [i + off for i in b]
    return [_offset(x, depth - 1, off) for x in b]


def _check_coordinates(V: np.ndarray, path: Path, flat_idx: np.ndarray, idx: _Indices, n_file: int,
                       blocks: list[tuple[int, str]], has_tr: bool, scale: np.ndarray) -> None:
    """Refuses a non-finite coordinate, a height outside :data:`Z_RANGE_M` or |x|, |y| beyond
    :data:`XY_ABS_MAX_M`, naming the vertex and an object using it."""
    with np.errstate(invalid="ignore", over="ignore"):
        fin = np.isfinite(V).all(axis=1)
        z_ok = (V[:, 2] >= Z_RANGE_M[0]) & (V[:, 2] <= Z_RANGE_M[1])
        xy_ok = (np.abs(V[:, 0]) <= XY_ABS_MAX_M) & (np.abs(V[:, 1]) <= XY_ABS_MAX_M)
    bad = np.flatnonzero(~(fin & z_ok & xy_ok))
    if not bad.size:
        return
    k = int(bad[0])
    nb = int(bad.size)
    if k < n_file:
        users = np.flatnonzero(flat_idx == k)
        who = f" (used by {idx.owner_of(int(users[0]))[0]})" if users.size else " (used by no geometry)"
        name = f"vertex {k}"
        fix = f" after transform.scale {scale.tolist()}" if has_tr else ""
    else:
        b = int(np.searchsorted(np.asarray([s for s, _ in blocks]), k, side="right")) - 1
        who, name = f" of CityObject {blocks[b][1]!r}", "a vertex of the GeometryInstance"
        fix = ""
    tail = "" if nb == 1 else f" ({nb} vertices in all)"
    xyz = ", ".join(f"{c:.6g}" for c in V[k])
    if not fin[k]:
        raise DataError(f"{path}: {name}{who} is [{xyz}]{fix}: coordinates must be finite numbers{tail}; the file "
                        "is corrupt: re-export it")
    if not z_ok[k]:
        raise DataError(f"{path}: {name}{who} has height {V[k, 2]:.6g} m{fix}, outside the plausible "
                        f"{Z_RANGE_M[0]:g} .. {Z_RANGE_M[1]:g} m{tail}: check transform (scale and translate) and "
                        "the height unit (millimetres?), then re-export the file")
    raise DataError(f"{path}: {name}{who} is at x, y = {V[k, 0]:.6g}, {V[k, 1]:.6g}{fix}, beyond +-{XY_ABS_MAX_M:g} m "
                    f"of any projected CRS{tail}: check transform and metadata.referenceSystem")


def read_cityjson(path: str | Path) -> dict:
    """The CityJSON document at ``path``, validated and normalised (:func:`load_cityjson`:
    ``vertices`` real coordinates, GeometryInstances resolved); raises :class:`DataError`."""
    return load_cityjson(path).doc


def cityjson_crs(cj: dict) -> CRS:
    """The horizontal CRS of a CityJSON document (``metadata.referenceSystem``)."""
    meta = cj.get("metadata")
    if meta is not None and not isinstance(meta, dict):
        raise DataError(f"CityJSON metadata is a {type(meta).__name__}, not an object: give "
                        '"metadata": {"referenceSystem": "https://www.opengis.net/def/crs/EPSG/0/<code>"}')
    ref = (meta or {}).get("referenceSystem")
    if not ref:
        raise DataError("CityJSON has no metadata.referenceSystem; set aoi.crs to the file's CRS")
    m = re.search(r"EPSG[:/]+(?:[0-9.]*/)?(?:0/)?:?(\d+)", str(ref))
    if not m:
        raise DataError(f"cannot read the CityJSON referenceSystem {str(ref)[:120]!r}")
    try:
        crs = CRS.from_epsg(int(m.group(1)))
    except Exception as exc:                 # pyproj.exceptions.CRSError: no such EPSG code
        raise DataError(f"CityJSON metadata.referenceSystem {str(ref)[:120]!r}: EPSG:{m.group(1)} is not a "
                        f"known CRS ({exc}); give the file's real EPSG code") from None
    return crs.sub_crs_list[0] if crs.is_compound else crs


def vertices_in(cj: dict, crs: CRS | None = None) -> np.ndarray:
    """The document's vertices ``(n, 3)`` [m]: ``transform`` applied (a document of
    :func:`read_cityjson` has it applied already), x and y reprojected to ``crs`` (kept in the
    file's CRS when None).  Raises :class:`DataError` when a vertex does not reproject to finite
    coordinates (outside the CRS's area of use)."""
    if isinstance(cj["vertices"], np.ndarray) and "transform" not in cj:
        V = cj["vertices"].astype(np.float64, copy=True)
    else:
        scale, translate, _ = _transform(cj, Path("CityJSON"))
        V = _vertex_array(cj["vertices"], Path("CityJSON"), "vertices") * scale + translate
    if crs is not None:
        src = cityjson_crs(cj)
        if src != crs:
            t = Transformer.from_crs(src, crs, always_xy=True)
            V[:, 0], V[:, 1] = t.transform(V[:, 0], V[:, 1])
            bad = np.flatnonzero(~np.isfinite(V[:, :2]).all(axis=1))
            if bad.size:
                raise DataError(f"CityJSON vertex {int(bad[0])} ({bad.size} in all) does not reproject from "
                                f"{src.name} to {crs.name} (outside its area of use); check "
                                "metadata.referenceSystem and aoi.crs")
    return V


def surfaces(geom: dict) -> Iterator[tuple[list[int], str | None]]:
    """Yield (outer ring vertex indices, semantic type or None) of every surface of a CityJSON
    geometry (MultiSurface, CompositeSurface, Solid, Multi/CompositeSolid; a TIN yields none)."""
    if geom["type"] == "TIN":
        return
    for rings, stype in surface_rings(geom):
        yield rings[0], stype


def surface_rings(geom: dict) -> Iterator[tuple[list[list[int]], str | None]]:
    """Yield (rings: vertex-index lists, outer ring first; semantic type or None) of every surface
    of a CityJSON geometry (MultiSurface, CompositeSurface, TIN, Solid, Multi/CompositeSolid) of a
    document validated by :func:`load_cityjson` (a ``null`` in ``semantics.values``, at any level:
    no semantic type)."""
    gtype = geom["type"]
    if gtype not in SURFACE_TYPES:
        return
    b = geom["boundaries"]
    sem = geom.get("semantics") or {}
    stypes = [s.get("type") for s in sem.get("surfaces", [])]
    values = sem.get("values")
    depth = BOUNDARY_LEVELS[gtype].index("surfaces")      # levels above the surfaces
    out: list[tuple[list, int | None]] = []

    def collect(bb: list, vv, d: int) -> None:      # depth first, in file order
        if d == 0:
            out.extend((p, vv[i] if vv is not None else None) for i, p in enumerate(bb))
            return
        for i, x in enumerate(bb):
            collect(x, vv[i] if vv is not None else None, d - 1)

    collect(b, values, depth)
    for p, v in out:
        yield p, (stypes[v] if (v is not None and 0 <= v < len(stypes)) else None)


def newell_normals(V: np.ndarray, faces: list[list[list[int]]]) -> np.ndarray:
    """Unit Newell normals ``(n, 3)`` of the outer rings of ``faces`` (zero for degenerate rings)."""
    outer = [f[0] for f in faces]
    lengths = np.array([len(r) for r in outer], np.int64)
    if not len(outer):
        return np.zeros((0, 3))
    idx = np.concatenate([np.asarray(r, np.int64) for r in outer])
    off = np.concatenate([[0], np.cumsum(lengths)])
    nxt = np.arange(idx.size) + 1
    nxt[off[1:] - 1] = off[:-1]
    a, b = V[idx], V[idx[nxt]]
    terms = np.column_stack([(a[:, 1] - b[:, 1]) * (a[:, 2] + b[:, 2]), (a[:, 2] - b[:, 2]) * (a[:, 0] + b[:, 0]),
                             (a[:, 0] - b[:, 0]) * (a[:, 1] + b[:, 1])])
    n = np.add.reduceat(terms, off[:-1], axis=0)
    n[lengths < 3] = 0.0
    nn = np.linalg.norm(n, axis=1)
    return np.divide(n, nn[:, None], out=np.zeros_like(n), where=nn[:, None] > 0)


@dataclass(frozen=True)
class CityJSONBuildings:
    """The Building/BuildingPart faces of a CityJSON file (:func:`read_buildings`).

    ``vertices_m`` (n, 3) [m] in the target CRS; ``ids`` the CityObject ids (building b is
    ``ids[b]``); ``faces[k]`` the rings (vertex indices, outer first) of face k, of building
    ``owner[k]``; ``is_roof`` / ``is_floor`` per face; ``terrain_height_m`` per building (the
    ``TerrainHeight`` attribute, NaN if absent); ``tin_faces`` the ``TINRelief`` faces; ``warnings``
    the reading's counted coercions (:attr:`CityJSONDocument.warnings`)."""

    vertices_m: np.ndarray
    ids: tuple[str, ...]
    faces: list[list[list[int]]]
    owner: np.ndarray
    is_roof: np.ndarray
    is_floor: np.ndarray
    terrain_height_m: np.ndarray
    tin_faces: list[list[list[int]]]
    root: np.ndarray | None = None   # per building: group of its root Building (shared with its parts)
    warnings: tuple[str, ...] = ()   # the counted coercions of the reading (CityJSONDocument.warnings)

    def roof_top_m(self) -> np.ndarray:
        """Highest roof vertex [m] of each building (NaN for a building without roof face)."""
        heights = np.full(len(self.ids), np.nan)
        for i in np.flatnonzero(self.is_roof):
            o = self.owner[i]
            heights[o] = np.fmax(heights[o], self.vertices_m[np.asarray(self.faces[i][0]), 2].max())
        return heights

    def ground_points(self, tin: bool = True) -> np.ndarray:
        """Ground points ``(n, 3)`` [m], per Building with its BuildingParts (:attr:`root`):
        with a ``TerrainHeight`` attribute, the roof and floor vertices of all of them at that
        height (some LoD2 models put the ground surface at z = 0); else the vertices of its
        *lowest* ground surface (``GroundSurface``, or an untyped face facing down) among the
        building's and its parts' (and any other within :data:`GROUND_TOLERANCE_M` of its height
        range): the bottom of a part standing on another part is not ground.  Then (``tin``)
        every ``TINRelief`` vertex."""
        V, faces = self.vertices_m, self.faces
        root = self.root if self.root is not None else np.arange(len(self.ids))
        ground: list[np.ndarray] = []
        for r in np.unique(root) if len(root) else ():
            members = np.flatnonzero(root == r)
            sel = (np.flatnonzero(np.isin(self.owner, members) & (self.is_roof | self.is_floor)) if len(faces)
                   else np.zeros(0, np.int64))
            if not sel.size:
                continue
            th = self.terrain_height_m[members]
            th = th[np.isfinite(th)]
            if th.size:
                P = V[np.concatenate([np.asarray(faces[i][0]) for i in sel])]
                ground.append(np.column_stack([P[:, 0], P[:, 1], np.full(len(P), float(th.min()))]))
                continue
            fl = [i for i in sel if self.is_floor[i]]
            if not fl:
                continue
            zs = [V[np.asarray(faces[i][0]), 2] for i in fl]
            k = int(np.argmin([z.min() for z in zs]))
            top = float(zs[k].max()) + GROUND_TOLERANCE_M
            keep = [i for i, z in zip(fl, zs, strict=True) if z.min() <= top]
            ground.append(V[np.concatenate([np.asarray(faces[i][0]) for i in keep])])
        if tin and self.tin_faces:
            ground.append(V[np.unique(np.concatenate([np.asarray(f[0]) for f in self.tin_faces]))])
        return np.vstack(ground) if ground else np.zeros((0, 3))


def read_buildings(path: str | Path, crs: CRS, *, steep_nz: float = 1e-3) -> CityJSONBuildings:
    """The Building/BuildingPart faces of the CityJSON file ``path`` in ``crs`` (module
    docstring): each building's highest-LoD geometry; ``steep_nz`` [1]: an untyped face whose
    unit normal has ``n_z`` below it is a wall, not a roof."""
    doc = load_cityjson(path)
    cj = doc.doc
    V = vertices_in(cj, crs)
    ids: list[str] = []
    parents: list[list[str]] = []
    th_of: list[float] = []     # TerrainHeight attribute per building (NaN if absent)
    faces: list[list[list[int]]] = []
    ftype: list[str | None] = []
    fowner: list[int] = []
    tin_faces: list[list[list[int]]] = []
    for oid, obj in cj["CityObjects"].items():
        otype = obj.get("type")
        geoms = [g for g in obj.get("geometry") or [] if g["type"] in SURFACE_TYPES]
        if not geoms:
            continue
        if otype == "TINRelief":
            for g in geoms:
                tin_faces.extend(rings for rings, _ in surface_rings(g) if len(rings[0]) >= 3)
            continue
        if otype not in ("Building", "BuildingPart"):
            continue
        g = max(geoms, key=lambda gg: float(gg.get("lod", 0)))      # lod validated by load_cityjson
        bidx = len(ids)
        ids.append(oid)
        parents.append([str(p) for p in (obj.get("parents") or [])])
        th = (obj.get("attributes") or {}).get("TerrainHeight")
        th_of.append(float(th) if th is not None else np.nan)
        for rings, stype in surface_rings(g):
            if len(rings[0]) >= 3:
                faces.append(rings)
                ftype.append(stype)
                fowner.append(bidx)
    nrm = newell_normals(V, faces)
    st = np.array(ftype, dtype=object)
    nz = nrm[:, 2] if len(faces) else np.zeros(0)
    degenerate = ~np.any(nrm != 0, axis=1) if len(faces) else np.zeros(0, bool)
    is_floor = ~degenerate & ((st == "GroundSurface") | ((st == None) & (nz < -0.5)))  # noqa: E711
    # roofs: every face typed as one (vertical or degenerate ones too: their trace takes their top),
    # and untyped faces that face up (LoD1 solids without semantics; untyped walls are skipped)
    is_roof = ~is_floor & (np.isin(st, list(ROOF_TYPES)) | ((st == None) & (nz >= steep_nz)))  # noqa: E711
    return CityJSONBuildings(V, tuple(ids), faces, np.asarray(fowner, np.int64), np.asarray(is_roof, bool),
                             np.asarray(is_floor, bool), np.asarray(th_of, np.float64).reshape(-1), tin_faces,
                             _roots(ids, parents, cj["CityObjects"]), doc.warnings)


def _check_tin_faces(path: Path, V: np.ndarray, objects: dict) -> None:
    """Refuse a ``TINRelief`` face (of a validated document, vertices ``V`` [m]) whose outer ring,
    in plan (x, y), is not a simple polygon: it crosses or overlaps itself, or lists a vertex
    twice.  The terrain coverage of the surface unites these polygons (GEOS), which fails on such a
    ring ("side location conflict") or runs out of memory.  Triangles are not checked (three
    points cannot cross; a degenerate one unites as a line)."""
    import shapely

    rings: list[np.ndarray] = []
    owner: list[str] = []
    for oid, obj in objects.items():
        if obj.get("type") != "TINRelief":
            continue
        for g in obj.get("geometry") or []:
            if g.get("type") in SURFACE_TYPES:
                for f, _ in surface_rings(g):
                    if len(f[0]) > 3:
                        rings.append(np.asarray(f[0], dtype=np.int64))
                        owner.append(oid)
    if not rings:
        return
    coords = V[np.concatenate(rings), :2]
    ring_of = np.repeat(np.arange(len(rings)), [len(r) for r in rings])
    try:
        polys = shapely.polygons(shapely.linearrings(coords, indices=ring_of))
        ok = shapely.is_valid(polys)
    except shapely.errors.GEOSException as exc:
        raise DataError(f"{path}: the TINRelief faces cannot be read as polygons ({exc}); fix or "
                        "re-triangulate the TIN") from None
    if not ok.all():
        j = int(np.flatnonzero(~ok)[0])
        why = shapely.is_valid_reason(polys[j])
        n = int((~ok).sum())
        more = f" ({n} such faces)" if n > 1 else ""
        raise DataError(f"{path}: CityObject {owner[j]!r} (TINRelief): a face of {len(rings[j]):,} vertices is "
                        f"not a simple polygon in plan ({why}){more}; a TIN face is a triangle or a polygon "
                        "that does not cross itself: re-triangulate the TIN or fix the face")


def _roots(ids: list[str], parents: list[list[str]], objects: dict) -> np.ndarray:
    """Per building (index into ``ids``): a group number shared by a Building and all its
    BuildingParts, following ``parents`` to the topmost ancestor (a Building without geometry of
    its own still groups its parts)."""
    groups: dict[str, int] = {}
    out = np.zeros(len(ids), dtype=np.int64)
    for k, oid in enumerate(ids):
        seen, cur = {oid}, oid
        ps = parents[k]
        while ps:
            nxt = ps[0]
            if nxt in seen:
                break       # a cycle in a broken file: stop
            seen.add(nxt)
            cur = nxt
            ps = [str(p) for p in ((objects.get(cur) or {}).get("parents") or [])]
        out[k] = groups.setdefault(cur, len(groups))
    return out


__all__ = ["BOUNDARY_LEVELS", "MAX_CITYJSON_BYTES", "MAX_RING_VERTICES", "ROOF_TYPES", "SURFACE_TYPES", "XY_ABS_MAX_M", "Z_RANGE_M",
           "CityJSONBuildings", "CityJSONDocument", "cityjson_crs", "load_cityjson", "newell_normals", "read_buildings",
           "read_cityjson", "surface_rings", "surfaces", "vertices_in"]
