"""Generate ``landing_sites.geojson`` (contingency landing sites of the rotterdam-canyon
scenario) from the shipped LoD2 CityJSON ``../rotterdam_delfshaven_lod2.city.json``.

Run from anywhere (``python catalogs/data/rotterdam/make_landing_sites.py``); the output is
deterministic (same input -> byte-identical file).

Why flat roofs
--------------
The CityJSON holds only buildings (853 ``Building`` objects, LoD2 roof/wall/ground faces,
EPSG:28992, heights in NAP) and the scenario has no OpenStreetMap extract, so the open ground
between the buildings cannot be told apart: squares, streets, parks and the harbour water
(Coolhaven, Achterhaven, Voorhaven) all look the same (no building).  The only surfaces the
data *does* describe are the roofs, and a large flat roof is a recognised contingency landing
area for a small UAS (no people on it, nothing to hit, known height).  So a landing site is:

1. a ``RoofSurface`` face that is flat: slope of its plane (Newell normal) <= ``MAX_SLOPE_DEG``
   (5 deg) and height range of its vertices <= ``MAX_RANGE_M`` (0.5 m);
2. the flat faces of one building whose mean heights differ by <= ``MAX_RANGE_M`` are merged
   (one roof level; shapely ``union_all``);
3. minus ``CLEAR_RADIUS_M`` (5 m) around every roof face (of any building) that rises more than
   ``MAX_RANGE_M`` above the level (a higher roof part, a neighbour's gable: an obstacle);
4. eroded by ``CLEAR_RADIUS_M`` (``buffer(-5 m)``): what remains is the set of touch-down points
   whose whole 10 m diameter disc lies on the flat roof level, away from its edges and from
   anything higher; a roof level that keeps no such point is dropped, as is a remainder part
   smaller than ``MIN_AREA_M2`` (1 m^2, slivers of the erosion).

Each site is a Polygon/MultiPolygon in WGS 84 lon/lat (RFC 7946; skyroute's landing stage reads
that, see ``skyroute.stages.landing``), with properties ``name`` (``roof <CityObject id>
<level>``), ``kind`` = ``flat_roof``, ``roof_height_m`` (mean NAP height of the level; NOT an
ellipsoidal height), ``roof_area_m2`` (flat level area) and ``touchdown_area_m2`` (site area),
both measured in EPSG:28992.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import shapely
from pyproj import Transformer

HERE = Path(__file__).resolve().parent
SOURCE = HERE.parent / "rotterdam_delfshaven_lod2.city.json"
OUTPUT = HERE / "landing_sites.geojson"
MAX_SLOPE_DEG = 5.0     # a flat roof face: plane slope at most this [deg]
MAX_RANGE_M = 0.5       # ... and vertex heights within this [m]; also the merge / obstacle tolerance
CLEAR_RADIUS_M = 5.0    # radius of the clear touch-down disc [m] (10 m diameter)
MIN_AREA_M2 = 1.0       # smallest touch-down remainder kept [m^2]


def roof_faces(cj: dict) -> list[tuple[str, np.ndarray]]:
    """(CityObject id, (n, 3) outer ring [m]) of every RoofSurface of a MultiSurface/Solid."""
    tr = cj.get("transform") or {"scale": [1, 1, 1], "translate": [0, 0, 0]}
    verts = np.asarray(cj["vertices"], float) * tr["scale"] + tr["translate"]
    out = []
    for oid in sorted(cj["CityObjects"]):
        for geom in cj["CityObjects"][oid].get("geometry", []):
            sem = geom.get("semantics") or {}
            types = [s.get("type") for s in sem.get("surfaces", [])]
            if geom["type"] == "MultiSurface":
                polys = list(zip(geom["boundaries"], sem.get("values") or [None] * len(geom["boundaries"]),
                                 strict=True))
            elif geom["type"] == "Solid":
                vals = sem.get("values") or [[None] * len(s) for s in geom["boundaries"]]
                polys = [(p, v) for shell, vs in zip(geom["boundaries"], vals, strict=True)
                         for p, v in zip(shell, vs, strict=True)]
            else:
                continue
            for rings, v in polys:
                if v is not None and types[v] == "RoofSurface":
                    out.append((oid, verts[rings[0]]))
    return out


def slope_deg(ring: np.ndarray) -> float:
    """Slope of a planar polygon [deg] from its Newell normal (90 for a degenerate ring)."""
    a, b = ring, np.roll(ring, -1, axis=0)
    n = np.array([np.sum((a[:, 1] - b[:, 1]) * (a[:, 2] + b[:, 2])),
                  np.sum((a[:, 2] - b[:, 2]) * (a[:, 0] + b[:, 0])),
                  np.sum((a[:, 0] - b[:, 0]) * (a[:, 1] + b[:, 1]))])
    norm = float(np.linalg.norm(n))
    return 90.0 if norm == 0 else float(np.degrees(np.arccos(min(abs(n[2]) / norm, 1.0))))


def flat_roof_levels(faces: list[tuple[str, np.ndarray]]) -> list[tuple[str, float, shapely.Geometry]]:
    """(object id, mean height [m], footprint) of each flat roof level (steps 1-2)."""
    by_obj: dict[str, list[tuple[float, shapely.Geometry]]] = {}
    for oid, ring in faces:
        if slope_deg(ring) > MAX_SLOPE_DEG or np.ptp(ring[:, 2]) > MAX_RANGE_M:
            continue
        poly = shapely.make_valid(shapely.Polygon(ring[:, :2]))
        if poly.area > 0:
            by_obj.setdefault(oid, []).append((float(ring[:, 2].mean()), poly))
    levels = []
    for oid, items in by_obj.items():
        items.sort(key=lambda t: t[0])
        group: list[tuple[float, shapely.Geometry]] = []
        for z, p in [*items, (np.inf, None)]:
            if group and z - group[0][0] > MAX_RANGE_M:
                zs = np.array([g[0] for g in group])
                areas = np.array([g[1].area for g in group])
                levels.append((oid, float(np.average(zs, weights=areas)), shapely.union_all([g[1] for g in group])))
                group = []
            if p is not None:
                group.append((z, p))
    return levels


def landing_sites(cj: dict) -> list[dict]:
    """GeoJSON features (EPSG:28992 geometry, converted later) of the flat-roof sites (steps 1-4)."""
    faces = roof_faces(cj)
    polys = [shapely.make_valid(shapely.Polygon(r[:, :2])) for _, r in faces]
    tops = np.array([r[:, 2].max() for _, r in faces])
    tree = shapely.STRtree(polys)
    feats = []
    for oid, z, level in flat_roof_levels(faces):
        site = level
        near = tree.query(level.buffer(CLEAR_RADIUS_M))
        higher = [polys[i] for i in near if tops[i] > z + MAX_RANGE_M]
        if higher:
            site = site.difference(shapely.union_all(higher).buffer(CLEAR_RADIUS_M))
        site = site.buffer(-CLEAR_RADIUS_M)
        parts = [g for g in shapely.get_parts(site) if g.area >= MIN_AREA_M2]
        if not parts:
            continue
        site = parts[0] if len(parts) == 1 else shapely.MultiPolygon(parts)
        feats.append({"oid": oid, "z": z, "geom": site, "roof_area": float(level.area)})
    return feats


def main() -> None:
    cj = json.loads(SOURCE.read_text(encoding="utf-8"))
    ref = cj["metadata"]["referenceSystem"]
    assert ref.endswith("28992"), ref
    to_wgs84 = Transformer.from_crs(28992, 4326, always_xy=True)
    features = []
    sites = sorted(landing_sites(cj), key=lambda f: (-f["geom"].area, f["oid"]))
    for i, s in enumerate(sites):
        g = shapely.transform(s["geom"], lambda xy: np.column_stack(to_wgs84.transform(xy[:, 0], xy[:, 1])))
        g = shapely.set_precision(g, 1e-7)   # ~1 cm
        features.append({"type": "Feature", "geometry": json.loads(shapely.to_geojson(g)), "properties": {
            "name": f"roof {s['oid']} {i}", "kind": "flat_roof",
            "roof_height_m": round(s["z"], 2), "height_datum": "NAP (not ellipsoidal)",
            "roof_area_m2": round(s["roof_area"], 1), "touchdown_area_m2": round(float(s["geom"].area), 1)}})
    head = {"type": "FeatureCollection", "name": "rotterdam-delfshaven flat-roof landing sites",
            "generator": "catalogs/data/rotterdam/make_landing_sites.py", "source": SOURCE.name}
    lines = ",\n".join(json.dumps(f, separators=(",", ":")) for f in features)
    OUTPUT.write_text(json.dumps(head)[:-1] + ', "features": [\n' + lines + "\n]}\n", encoding="utf-8")
    print(f"{OUTPUT}: {len(features)} sites, touch-down area {sum(s['geom'].area for s in sites):.0f} m^2")


if __name__ == "__main__":
    main()
