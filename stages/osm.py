"""Reading OpenStreetMap extracts (.osm.pbf / .osm) with pyosmium into shapely features.

One pass over the file gives every tagged node (as a Point) and every closed way or
multipolygon relation (as an area: Polygon / MultiPolygon), in WGS 84 lon/lat [deg], with
their tags.  Stages filter the features they need (buildings, land use, amenities, helipads).

Data (c) OpenStreetMap contributors, ODbL 1.0.
"""

from __future__ import annotations

import math
import re
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


#: a coordinate attribute of an OSM XML element, e.g. ``lat="60.17"``, capturing its text
_XML_COORD = re.compile(rb"""\b(lat|lon)\s*=\s*(["'])(.{0,64}?)\2""", re.DOTALL)
#: the same with no closing quote in reach: its first 20 bytes
_XML_COORD_OPEN = re.compile(rb"""(lat|lon)\s*=\s*["']()(.{0,20})""", re.DOTALL)
#: the plain decimal form every OSM tool writes (no exponent, no sign other than ``-``)
_PLAIN = re.compile(rb"-?[0-9]{1,3}(?:\.[0-9]{0,15})?")
#: any number libosmium can read (no ``+``, no spaces, no ``inf``/``nan``)
_NUMBER = re.compile(rb"-?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?")
_COORD_RANGE = {b"lat": 90.0, b"lon": 180.0}
#: the start of a coordinate attribute whose value is not plain decimal within +-179.99.. (found at
#: C speed: a valid file has almost none); a plain latitude beyond 90 is a location libosmium
#: itself marks invalid, which :func:`_read` refuses
_SUSPECT = re.compile(rb"""\b(?:lat|lon)\s*=\s*(["'])(?!-?(?:1[0-7][0-9]|[0-9]{1,2})(?:\.[0-9]{0,15})?\1)""")
_BLOCK = 16 << 20   # bytes read at a time by the coordinate scan [bytes]


def _coordinate_ok(name: bytes, text: bytes) -> bool:
    """Whether ``text`` (the value of a ``lat``/``lon`` attribute) is a finite number in range."""
    if not (_PLAIN.fullmatch(text) or _NUMBER.fullmatch(text)):
        return False
    v = float(text)
    return math.isfinite(v) and abs(v) <= _COORD_RANGE[name]


def _open_xml(path: str):
    """The OSM XML file at ``path`` opened for binary reading (decompressed when it is gzip or
    bzip2), or ``None`` when it is not XML (a PBF file)."""
    import bz2
    import gzip

    with open(path, "rb") as f:
        magic = f.read(3)
    opener = gzip.open if magic[:2] == b"\x1f\x8b" else bz2.open if magic == b"BZh" else open
    f = opener(path, "rb")
    try:
        head = f.read(512).lstrip(b"\xef\xbb\xbf \t\r\n")
        f.seek(0)
    except (OSError, EOFError, ValueError):
        f.close()
        return None     # a broken archive: libosmium says what is wrong
    if not head.startswith(b"<"):
        f.close()
        return None
    return f


def _xml_bad_coordinate(path: str) -> str | None:
    """The first coordinate of an OSM XML file (plain, gzip or bzip2) that is not a finite number
    within range (lat within +-90 deg, lon within +-180 deg), as ``'node 9 (byte 623) has
    lon="inf"'``, or ``None`` (also for a PBF file, whose coordinates are integers).

    libosmium refuses ``inf``, ``nan`` or text in a coordinate without naming the node, and reads
    an exponent that overflows (``1e400``) as 0 deg in silence: this scan, run before it, finds both
    and names the node.  It reads the file in blocks of 16 MB [bytes] (memory bounded); a block
    overlap of 256 bytes keeps an attribute cut at a block edge whole.
    """
    f = _open_xml(path)
    if f is None:
        return None
    overlap = 256
    with f:
        start = 0       # file offset of buf[0] [bytes]
        buf = b""
        while True:
            try:
                block = f.read(_BLOCK)
            except (OSError, EOFError, ValueError):
                return None     # a broken archive: libosmium says what is wrong
            buf += block
            keep = max(len(buf) - overlap, 0)
            for sus in _SUSPECT.finditer(buf):
                if block and sus.start() > len(buf) - overlap:
                    keep = min(keep, sus.start())
                    break   # may be cut at the block edge: seen again with the next block
                m = _XML_COORD.match(buf, sus.start())
                if m is not None and _coordinate_ok(m.group(1), m.group(3)):
                    continue
                if m is None:   # no closing quote within 64 bytes
                    m = _XML_COORD_OPEN.match(buf, sus.start())
                lt = buf.rfind(b"<", max(m.start() - 4096, 0), m.start())
                head = buf[lt:m.start()] if lt >= 0 else b""
                kind = re.match(rb"<\s*([A-Za-z]+)", head)
                oid = re.search(rb"""\bid\s*=\s*["'](-?[0-9]{1,20})["']""", head + buf[m.end():m.end() + 200])
                what = (kind.group(1).decode() if kind else "element") + (f" {oid.group(1).decode()}" if oid else "")
                val = m.group(3).decode("utf-8", "replace")
                return f'{what} (byte {start + m.start():,}) has {m.group(1).decode()}="{val}"'
            if not block:
                return None
            start += keep
            buf = buf[keep:]


@lru_cache(maxsize=8)
def _read(path: str, mtime_ns: int, keys: tuple[str, ...] | None) -> tuple[OsmFeature, ...]:
    fix = "write the coordinates in decimal degrees (lat within +-90, lon within +-180) or delete the object"
    bad = _xml_bad_coordinate(path)
    if bad is not None:
        raise DataError(f"OSM file {path}: {bad}, not a coordinate in degrees; {fix}")
    wkb = osmium.geom.WKBFactory()
    out: list[OsmFeature] = []
    fp = osmium.FileProcessor(path).with_areas().with_locations()
    try:
        for obj in fp:
            if obj.is_node():
                if obj.visible and not obj.location.valid():
                    raise DataError(f"OSM file {path}: node {obj.id} has a location out of range "
                                    f"(or none); {fix}")
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
    except osmium.InvalidLocationError as exc:   # raised by the file reader, e.g. lat="inf"
        raise DataError(f"OSM file {path}: a node coordinate cannot be read ({exc}); {fix}") from None
    except (RuntimeError, ValueError) as exc:     # libosmium's parser: a damaged file ("illegal id: ' 1'")
        raise DataError(f"OSM file {path} cannot be read: {exc}; the file is damaged or not OSM XML / PBF: "
                        "download the extract again (or check it with `osmium fileinfo`)") from None
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
