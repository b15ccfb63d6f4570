"""Reading OpenStreetMap extracts (.osm.pbf / .osm) with pyosmium into shapely features.

One pass over the file gives every tagged node (as a Point) and every closed way or
multipolygon relation (as an area: Polygon / MultiPolygon), in WGS 84 lon/lat [deg], with
their tags.  Stages filter the features they need (buildings, land use, amenities, helipads).

Data (c) OpenStreetMap contributors, ODbL 1.0.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import osmium
import shapely
from shapely.geometry.base import BaseGeometry

from skyroute.stages.base import DataError


@dataclass(frozen=True)
class OsmFeature:
    """One OSM object: ``kind`` is "node", "area" or "way" (open line), ``osm_id`` the
    object id (areas from ways keep the way id), ``geometry`` in lon/lat [deg]."""

    kind: str
    osm_id: int
    tags: dict[str, str] = field(hash=False, compare=False)
    geometry: BaseGeometry = field(hash=False, compare=False)


@lru_cache(maxsize=8)
def _read(path: str, mtime_ns: int, keys: tuple[str, ...] | None) -> tuple[OsmFeature, ...]:
    wkb = osmium.geom.WKBFactory()
    out: list[OsmFeature] = []
    fp = osmium.FileProcessor(path).with_areas().with_locations()
    for obj in fp:
        tags = obj.tags
        if len(tags) == 0:
            continue
        if keys is not None and not any(k in tags for k in keys):
            continue
        try:
            if obj.is_node():
                geom = shapely.Point(obj.location.lon, obj.location.lat)
                kind, oid = "node", obj.id
            elif obj.is_area():
                geom = shapely.from_wkb(wkb.create_multipolygon(obj))
                if geom.is_empty:
                    continue
                if len(geom.geoms) == 1:
                    geom = geom.geoms[0]
                kind, oid = "area", obj.orig_id()
            elif obj.is_way():
                if obj.is_closed() and len(obj.nodes) >= 4:
                    continue  # closed ways come back as areas
                geom = shapely.from_wkb(wkb.create_linestring(obj))
                kind, oid = "way", obj.id
            else:
                continue
        except (RuntimeError, osmium.InvalidLocationError):
            continue  # incomplete geometry at the edge of the extract
        out.append(OsmFeature(kind, int(oid), dict(tags), geom))
    return tuple(out)


def read_osm(path: str | Path, keys: Iterable[str] | None = None) -> tuple[OsmFeature, ...]:
    """All tagged features of an OSM file, optionally only those having one of ``keys``.

    Objects whose geometry is incomplete in the extract (ways cut at its edge) are skipped.
    """
    p = Path(path)
    if not p.is_file():
        raise DataError(f"OSM file not found: {p}; check the scenario's data paths")
    try:
        return _read(str(p.resolve()), p.stat().st_mtime_ns, None if keys is None else tuple(sorted(keys)))
    except RuntimeError as exc:
        raise DataError(f"cannot read OSM file {p}: {exc}") from exc


def named_nodes(path: str | Path, **tag_values: str) -> list[OsmFeature]:
    """Features whose tags equal every ``key=value`` given (e.g. ``amenity="pharmacy"``)."""
    feats = read_osm(path, keys=list(tag_values))
    return [f for f in feats if all(f.tags.get(k) == v for k, v in tag_values.items())]
