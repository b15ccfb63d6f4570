"""CityJSON reading (1.0 / 1.1 / 2.0): the document, its CRS, the surfaces of its geometries
and the faces of its buildings, with no rasterisation (that is :mod:`skyroute.stages.surface`
for heights and :mod:`skyroute.stages.risk` for risk levels).

* :func:`read_cityjson`: a validated CityJSON document (``type``, ``vertices``, ``CityObjects``);
* :func:`cityjson_crs`: its horizontal CRS (``metadata.referenceSystem``);
* :func:`surface_rings` / :func:`surfaces`: the rings (vertex indices) and semantic type of every
  surface of a geometry (MultiSurface, CompositeSurface, TIN, Solid, Multi/CompositeSolid);
* :func:`read_buildings`: the Building/BuildingPart faces of a file, vertices in map
  coordinates [m] of a target CRS, classified as roofs (``RoofSurface``, ``OuterCeilingSurface``,
  ``OuterFloorSurface``, or untyped faces whose unit Newell normal has ``n_z >= steep_nz``) and
  floors (``GroundSurface``, or untyped faces facing down), with the ``TINRelief`` faces and the
  ground points for terrain (:meth:`CityJSONBuildings.ground_points`).
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pyproj import CRS, Transformer

from skyroute.stages.base import DataError

#: A ground surface of a Building or its parts counts as ground when its lowest vertex is at most
#: this much [m] above the highest vertex of the building's lowest ground surface.
GROUND_TOLERANCE_M = 0.5
#: Semantic surface types that are the top of a building (its roof faces).
ROOF_TYPES = ("RoofSurface", "OuterCeilingSurface", "OuterFloorSurface")


def read_cityjson(path: str | Path) -> dict:
    """The CityJSON document at ``path`` (raises :class:`DataError` if missing or not CityJSON)."""
    path = Path(path)
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


def vertices_in(cj: dict, crs: CRS | None = None) -> np.ndarray:
    """The document's vertices ``(n, 3)`` [m]: ``transform`` applied, x and y reprojected to
    ``crs`` (kept in the file's CRS when None)."""
    tr = cj.get("transform") or {"scale": [1, 1, 1], "translate": [0, 0, 0]}
    V = np.asarray(cj["vertices"], dtype=np.float64).reshape(-1, 3) * np.asarray(tr["scale"]) \
        + np.asarray(tr["translate"])
    if crs is not None:
        src = cityjson_crs(cj)
        if src != crs:
            t = Transformer.from_crs(src, crs, always_xy=True)
            V[:, 0], V[:, 1] = t.transform(V[:, 0], V[:, 1])
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
    of a CityJSON geometry (MultiSurface, CompositeSurface, TIN, Solid, Multi/CompositeSolid)."""
    gtype = geom["type"]
    b = geom["boundaries"]
    sem = geom.get("semantics") or {}
    stypes = [s.get("type") for s in sem.get("surfaces", [])]
    values = sem.get("values")
    if gtype in ("MultiSurface", "CompositeSurface", "TIN"):
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
        yield p, (stypes[v] if (v is not None and v < len(stypes)) else None)


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
    ``TerrainHeight`` attribute, NaN if absent); ``tin_faces`` the ``TINRelief`` faces."""

    vertices_m: np.ndarray
    ids: tuple[str, ...]
    faces: list[list[list[int]]]
    owner: np.ndarray
    is_roof: np.ndarray
    is_floor: np.ndarray
    terrain_height_m: np.ndarray
    tin_faces: list[list[list[int]]]
    root: np.ndarray | None = None   # per building: group of its root Building (shared with its parts)

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
    cj = read_cityjson(path)
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
        geoms = obj.get("geometry") or []
        if not geoms:
            continue
        if otype == "TINRelief":
            for g in geoms:
                tin_faces.extend(rings for rings, _ in surface_rings(g) if len(rings[0]) >= 3)
            continue
        if otype not in ("Building", "BuildingPart"):
            continue
        g = max(geoms, key=lambda gg: float(gg.get("lod", 0)))
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
                             _roots(ids, parents, cj["CityObjects"]))


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


__all__ = ["ROOF_TYPES", "CityJSONBuildings", "cityjson_crs", "newell_normals", "read_buildings", "read_cityjson",
           "surface_rings", "surfaces", "vertices_in"]
