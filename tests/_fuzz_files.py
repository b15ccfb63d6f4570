"""Hostile DATA files (issue 34, item 4), shared by tests/test_fuzz_inputs.py (each mutation once,
plus a small random sample) and benchmarks/fuzz_inputs.py (thousands, counted per family).

Eight families, each a list of named mutations (:data:`OPS`) drawn with a :class:`random.Random`
and run through the command that reads that family fastest without planning:

* ``raster``: a <= 64 x 64 GeoTIFF made from the small DEM (truncated, tile bytes damaged,
  bottom-up, GCPs only, no CRS, ``EPSG:32611+6360`` (US survey feet), NoData everywhere,
  1e30 / -9527 / NaN / inf, 3 bands, int8, complex, a 200000 x 200000 sparse file, a folder, a
  FIFO, ``/dev/zero``...) as ``data.terrain`` or ``data.surface`` of the DEM scenario:
  ``inspect FILE``, ``inspect SCENARIO`` or ``run SCENARIO --stage surface``;
* ``cityjson``: the stacked-city CityJSON with a damaged ``transform``, vertex indices,
  vertices, nesting depth, ``geometry-templates`` / GeometryInstance, missing keys, wrong types:
  ``inspect FILE`` / ``inspect SCENARIO`` / ``run SCENARIO --stage surface``;
* ``osm``: a tiny .osm XML extract whose building ``height`` / ``building:levels`` tags are
  hostile (``12;55``, ``-5``, ``1e9``, ``nan``, ``40'``...) or whose nodes and ways are damaged:
  ``inspect FILE`` / ``run SCENARIO --stage surface``;
* ``wind``: a 4 x 4 NetCDF forecast over the DEM with hostile ``units``, NaN/inf data, all-NaN
  heights, wrong dims, a truncated file: ``run SCENARIO --stage wind``;
* ``almanac``: the YUMA almanac with damaged numbers and lines: ``sky --almanac FILE`` or
  ``run SCENARIO --stage satellites``;
* ``events-values``: helsinki-tactical's events with hostile numbers (1e6 m/s, inf durations...):
  ``fly --events FILE --max-memory 1``;
* ``airspace``: an airspace SQLite (two intents) with damaged rows (intent JSON, WKB, numbers,
  meta) or bytes: ``airspace check`` / ``show`` / ``ls``;
* ``outfolder``: an ``--out`` folder pre-filled with hostile content (symbolic links named like
  outputs, hard links to inputs, hand-written summary.json and manifests...): ``run SCENARIO
  --stage satellites``; the property checked after the run: no file outside ``--out`` and no
  pre-existing file in it that skyroute did not write is changed or removed (SHA-256 of every
  file, the target of every link, links not followed), nothing new outside ``--out`` but the
  documented ``skyroute-unplaced-*`` folder, no staging folder left behind.

The outcome of every case: exit 0, 2 or 3 (``airspace check``: 0, 1 or 2), never a traceback, an
exit 2 with exactly one ``error:`` line, in bounded time.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import os
import shutil
import sqlite3
import stat
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # `tests.` importable (the city builder)
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _fuzz_inputs import Base, mutate_text, mutate_tree  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "catalogs" / "data"
GARBAGE = bytes((i * 197 + 89) % 256 for i in range(4096))   # fixed "random" bytes, not UTF-8

FILE_KINDS = ("raster", "cityjson", "osm", "wind", "almanac", "events-values", "airspace", "outfolder")

# the DEM scenario (catalogs/README.md "my-mountains-dem"); its raster on a 64 x 64 lattice of 50 m
DEM_AOI = (383010.0, 3794010.0, 385980.0, 3796980.0)
DEM_ORIGIN = (382900.0, 3797100.0)
DEM_PX = 50.0
SPARSE_PX = 200_000                      # the sparse raster's declared width and height [px]
TIME = "2020-01-03T18:00:00Z"


@dataclass
class FileCase:
    """One case: the command, what was done, and how its outcome is judged."""

    kind: str
    op: str
    argv: list[str]
    desc: str
    exits: tuple[int, ...] = (0, 2, 3)
    one_error: bool = True                # an exit 2 has exactly one `error:` line
    check: Callable[[], list[str]] | None = None    # property violations after the run
    fifos: list[Path] = field(default_factory=list)   # released by a watchdog so a read cannot block


# ------------------------------------------------------------------------------ the base files
@dataclass
class FileBase:
    """The unmutated files every family starts from, built once under ``folder``."""

    folder: Path
    dem: np.ndarray                       # 64 x 64 heights [m] of the DEM scenario
    dem_scenario: dict                    # my-mountains-dem, data paths relative to the case folder
    city: dict                            # the stacked city (CityJSON document)
    city_scenario: dict                   # my-city-cityjson
    osm_scenario: dict
    yuma: str
    sparse: Path                          # 200000 x 200000 px, a few MB on disk
    airspace: bytes                       # an airspace file with intents "a" and "b"
    events: Base                          # the front-door base of _fuzz_inputs (helsinki-tactical events)
    cache: Path

    @classmethod
    def make(cls, folder: Path) -> FileBase:
        import rasterio
        import rasterio.windows
        from rasterio.enums import Resampling

        folder.mkdir(parents=True, exist_ok=True)
        with rasterio.open(DATA / "srtm_bigtujunga30m_utm11.tif") as src:
            w = rasterio.windows.from_bounds(DEM_ORIGIN[0], DEM_ORIGIN[1] - 64 * DEM_PX,
                                             DEM_ORIGIN[0] + 64 * DEM_PX, DEM_ORIGIN[1], src.transform)
            a = src.read(1, window=w.round_offsets().round_lengths(), out_shape=(64, 64),
                       resampling=Resampling.bilinear)
        dem = a.astype(np.float32)
        dem_sc = yaml.safe_load("""
name: fuzz-dem
aoi: {crs: EPSG:32611, bounds: [383010, 3794010, 385980, 3796980], resolution_m: 30.0}
data:
  terrain: {path: dem.tif, vertical_datum: EGM96 geoid}
  risk_default_level: 1
  almanacs: [yuma.txt]
mission:
  start: {x: 383500, y: 3796200, alt_agl_m: 60}
  goal: {x: 384800, y: 3796600, alt_agl_m: 60}
  start_time_utc: 2020-01-03T18:00:00Z
constraints: {min_altitude_agl_m: 10, max_altitude_agl_m: 80}
planner: {step_cells: 4}
""")
        city_sc = yaml.safe_load("""
name: fuzz-city
aoi: {crs: EPSG:28992, bounds: [81000, 455000, 81040, 455040], resolution_m: 1.0}
data:
  buildings: {path: city.city.json, format: cityjson}
  ground: {height_m: 43.4, vertical_datum: WGS 84 ellipsoid}
mission:
  start: {x: 81002, y: 455002, alt_agl_m: 10}
  goal: {x: 81038, y: 455038, alt_agl_m: 10}
  start_time_utc: 2020-01-03T12:00:00Z
constraints: {max_altitude_agl_m: 40}
""")
        osm_sc = yaml.safe_load("""
name: fuzz-osm
aoi: {bounds_lonlat: [24.9400, 60.1700, 24.9440, 60.1720], resolution_m: 2.0}
data:
  buildings: {path: city.osm, format: osm, storey_height_m: 3.0}
  ground: {height_m: 3.5, vertical_datum: EGM96 geoid}
mission:
  start: {lon: 24.9402, lat: 60.1701, alt_agl_m: 60}
  goal: {lon: 24.9438, lat: 60.1719, alt_agl_m: 60}
  start_time_utc: 2020-01-03T10:00:00Z
""")
        from tests.test_own_city import _stacked_city

        city_path, _, _ = _stacked_city(folder, True, offset=(81000.0, 455000.0), name="city.city.json")
        city = json.loads(city_path.read_text())
        sparse = folder / "sparse.tif"
        _write_sparse(sparse)
        cache = folder / "cache"
        return cls(folder, dem, dem_sc, city, city_sc, osm_sc, (DATA / "yuma_2020-01-03.txt").read_text(),
                   sparse, _airspace_bytes(folder / "airspace-base.sqlite"), Base.make(folder / "front"), cache)

    def dem_case(self, d: Path, resolution_m: float = 30.0, **data) -> Path:
        """The DEM scenario in ``d`` (its dem.tif and yuma.txt beside it), ``data`` merged in."""
        write_tif(d / "dem.tif", self.dem)
        (d / "yuma.txt").write_text(self.yuma)
        sc = copy.deepcopy(self.dem_scenario)
        sc["aoi"]["resolution_m"] = resolution_m
        for k, v in data.items():
            if v is None:
                sc["data"].pop(k, None)
            else:
                sc["data"][k] = v
        p = d / "scenario.yaml"
        p.write_text(yaml.safe_dump(sc, sort_keys=False))
        return p

    def tail(self, d: Path) -> list[str]:
        return ["--no-report", "-q", "--out", str(d / "out"), "--cache-dir", str(self.cache)]


def write_tif(path: Path, a: np.ndarray, *, transform=None, crs="EPSG:32611", nodata=-9999.0,
              dtype=None, gcps=None, **opts) -> Path:
    """A GeoTIFF of ``a`` (2-D: one band; 3-D: bands first) on the DEM lattice by default."""
    import rasterio
    from rasterio.transform import from_origin

    a = np.asarray(a)
    if a.ndim == 2:
        a = a[None]
    dtype = dtype or a.dtype
    prof = dict(driver="GTiff", width=a.shape[2], height=a.shape[1], count=a.shape[0], dtype=dtype, **opts)
    if gcps is not None:
        prof.update(gcps=gcps[0], crs=gcps[1])
    else:
        prof.update(transform=transform if transform is not None else from_origin(*DEM_ORIGIN, DEM_PX, DEM_PX),
                    crs=crs)
    if nodata is not None:
        prof["nodata"] = nodata
    with rasterio.open(path, "w", **prof) as dst:
        dst.write(a.astype(dtype))
    return path


def _write_sparse(path: Path) -> None:
    """200000 x 200000 float32 px over the DEM AOI (0.016 m pixels), tiled, one tile written:
    a few MB on disk, 160 GB if read whole."""
    import rasterio
    from rasterio.transform import from_origin
    from rasterio.windows import Window

    with rasterio.open(path, "w", driver="GTiff", width=SPARSE_PX, height=SPARSE_PX, count=1, dtype="float32",
                       crs="EPSG:32611", transform=from_origin(383000.0, 3797000.0, 0.016, 0.016), nodata=-9999.0,
                       tiled=True, blockxsize=512, blockysize=512, compress="deflate", sparse_ok=True,
                       BIGTIFF="YES") as dst:
        dst.write(np.full((1, 512, 512), 700.0, np.float32), window=Window(1024, 1024, 512, 512))


def _airspace_bytes(path: Path) -> bytes:
    """An airspace file (EPSG:32611) with two accepted intents, "a" (two volumes) and "b"."""
    import shapely

    from skyroute.stages.airspace_store import AirspaceStore
    from skyroute.stages.fleet import Volume4
    from skyroute.stages.intents import IntentVolume, intent_details

    crs, x0, y0 = "EPSG:32611", 383500.0, 3796200.0

    def vol(x, y, a0, a1, t0, t1):
        return Volume4(shapely.box(x0 + x, y0 + y, x0 + x + 10, y0 + y + 10), a0, a1, t0, t1)

    def doc(vols):
        iv = [IntentVolume(np.asarray(v.polygon.exterior.coords)[:-1], v.alt_lower_m, v.alt_upper_m, v.t_start_s,
                           v.t_end_s, 0.0) for v in vols]
        return intent_details(iv, crs, TIME)

    for p in path.parent.glob(path.name + "*"):
        p.unlink()
    with AirspaceStore.create(path, crs, TIME) as s:
        va = [vol(0, 0, 50, 60, 0, 30), vol(10, 0, 50, 60, 30, 60)]
        s.accept("a", doc(va), va, priority=1, operator="op-1", mission={"start": [1, 2]})
        vb = [vol(100, 0, 50, 60, 0, 30)]
        s.accept("b", doc(vb), vb)
        s._conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    return path.read_bytes()


# ------------------------------------------------------------------------------ rasters
RASTER_VALUES = [1e30, -1e30, -9527.0, np.nan, np.inf, -np.inf, 3.4e38, -32768.0, 0.0, 1e7, -1e7, 9000.0]

RASTER_OPS = ("truncate", "tile-bytes", "bottom-up", "gcps-only", "no-crs", "us-survey-feet", "nodata-everywhere",
              "values", "values-undeclared-nodata", "huge-sparse", "three-bands", "int8", "complex", "uint8-photo",
              "rotated", "tiny-pixels", "huge-pixels", "geographic", "far-away", "nan-nodata", "folder", "fifo",
              "dev-zero", "missing", "empty", "garbage", "text-mutated", "unit-feet", "scale-offset", "one-pixel")


def _raster_file(base: FileBase, rnd: __import__("random").Random, op: str, d: Path, case: FileCase) -> str:
    """Write the mutated raster of ``op`` in ``d``; returns its path (or a special path)."""
    from rasterio.control import GroundControlPoint
    from rasterio.transform import Affine, from_origin

    p = d / "hostile.tif"
    z = base.dem.copy()
    if op in ("truncate", "tile-bytes", "text-mutated"):
        write_tif(p, z, tiled=True, blockxsize=16, blockysize=16, compress="deflate")
        b = bytearray(p.read_bytes())
        if op == "truncate":
            del b[rnd.randrange(8, len(b)):]
        elif op == "tile-bytes":
            for _ in range(rnd.randint(1, 20)):
                i = rnd.randrange(len(b) // 4, len(b))
                b[i] = rnd.randrange(256)
        else:
            b = bytearray(mutate_text(bytes(b), rnd, rnd.randint(1, 3))[0])
        p.write_bytes(bytes(b))
    elif op == "bottom-up":
        write_tif(p, z[::-1], transform=Affine(DEM_PX, 0, DEM_ORIGIN[0], 0, DEM_PX, DEM_ORIGIN[1] - 64 * DEM_PX))
    elif op == "gcps-only":
        gcps = [GroundControlPoint(r, c, DEM_ORIGIN[0] + c * DEM_PX, DEM_ORIGIN[1] - r * DEM_PX, 0)
                for r, c in ((0, 0), (0, 64), (64, 0), (64, 64))]
        write_tif(p, z, gcps=(gcps, "EPSG:32611"))
    elif op == "no-crs":
        write_tif(p, z, crs=None)
    elif op == "us-survey-feet":
        write_tif(p, z / 0.3048006096, crs="EPSG:32611+6360")
    elif op == "nodata-everywhere":
        write_tif(p, np.full_like(z, -9999.0))
    elif op in ("values", "values-undeclared-nodata"):
        v = rnd.choice(RASTER_VALUES)
        r0, c0 = rnd.randrange(64), rnd.randrange(64)
        z[r0:r0 + rnd.randint(1, 64), c0:c0 + rnd.randint(1, 64)] = v
        write_tif(p, z, nodata=-9999.0 if op == "values" else None)
        case.desc += f" value {v}"
    elif op == "huge-sparse":
        return str(base.sparse)
    elif op == "three-bands":
        write_tif(p, np.stack([z, z, z]))
    elif op == "int8":
        write_tif(p, np.clip(z / 20, -128, 127), dtype="int8", nodata=None)
    elif op == "complex":
        write_tif(p, z.astype(np.complex64), dtype="complex64", nodata=None)
    elif op == "uint8-photo":
        write_tif(p, np.stack([z, z, z]).clip(0, 255), dtype="uint8", nodata=None, photometric="RGB")
    elif op == "rotated":
        write_tif(p, z, transform=Affine(DEM_PX, rnd.choice([5.0, 50.0, -20.0]), DEM_ORIGIN[0], 3.0, -DEM_PX,
                                         DEM_ORIGIN[1]))
    elif op == "tiny-pixels":
        write_tif(p, z, transform=from_origin(DEM_AOI[0] + 100, DEM_AOI[3] - 100, 1e-9, 1e-9))
    elif op == "huge-pixels":
        write_tif(p, z, transform=from_origin(-1e12, 1e12, 1e11, 1e11))
    elif op == "geographic":
        write_tif(p, z, transform=from_origin(-118.3, 34.32, 0.0005, 0.0005), crs="EPSG:4326")
    elif op == "far-away":
        write_tif(p, z, transform=from_origin(1e6, 1e7, DEM_PX, DEM_PX))
    elif op == "nan-nodata":
        z[rnd.randrange(64):, :rnd.randrange(1, 64)] = np.nan
        write_tif(p, z, nodata=np.nan)
    elif op == "folder":
        p = d / "tiles.tif"
        p.mkdir()
        write_tif(p / "a.tif", z)
    elif op == "fifo":
        p = d / "fifo.tif"
        os.mkfifo(p)
        case.fifos.append(p)
    elif op == "dev-zero":
        return "/dev/zero"
    elif op == "missing":
        return str(d / "absent.tif")
    elif op == "empty":
        p.write_bytes(b"")
    elif op == "garbage":
        p.write_bytes(b"II*\x00" + GARBAGE[:rnd.randrange(4, 4096)])
    elif op == "unit-feet":
        import rasterio

        write_tif(p, z / 0.3048)
        with rasterio.open(p, "r+") as dst:
            dst.units = (rnd.choice(["ft", "US survey foot", "feet", "furlong", "km", ""]),)
    elif op == "scale-offset":
        import rasterio

        write_tif(p, z)
        with rasterio.open(p, "r+") as dst:
            dst.scales = (rnd.choice([0.3048, 0.0, -1.0, 1e30, float("nan")]),)
            dst.offsets = (rnd.choice([0.0, 1e6, float("inf")]),)
    elif op == "one-pixel":
        write_tif(p, z[:1, :1], transform=from_origin(DEM_AOI[0] - 10, DEM_AOI[3] + 10, 4000.0, 4000.0))
    else:
        raise ValueError(op)
    return str(p)


def _raster_case(base: FileBase, rnd, op: str, d: Path) -> FileCase:
    case = FileCase("raster", op, [], f"raster: {op}")
    path = _raster_file(base, rnd, op, d, case)
    cmd = rnd.choice(("inspect-file", "inspect-terrain", "inspect-surface", "run-terrain", "run-surface"))
    role = "surface" if cmd.endswith("surface") else "terrain"
    extra = {"terrain": {"path": path, "vertical_datum": "EGM96 geoid"}} if role == "terrain" else {
        "surface": {"path": path, "vertical_datum": "EGM96 geoid"},
        "terrain": None if rnd.random() < 0.5 else {"path": "dem.tif", "vertical_datum": "EGM96 geoid"},
        "ground": {"height_m": 500.0, "vertical_datum": "EGM96 geoid"}}
    sc = base.dem_case(d, **extra)
    if cmd == "inspect-file":
        case.argv = ["inspect", path]
    elif cmd.startswith("inspect"):
        case.argv = ["inspect", str(sc)]
    else:
        case.argv = ["run", str(sc), "--stage", "surface", "--max-memory", "2G", *base.tail(d)]
    case.desc += f" as {role} ({cmd})"
    return case


# ------------------------------------------------------------------------------ CityJSON
CITY_VALUES = [0, -1, 1.5, "3", True, None, 2**64, -(2**63), 10**9, math.nan, math.inf, 1e300, -1e300, "x", [], {},
               [0], [[0]], [[[[[0]]]]]]
CITY_OPS = ("scale", "translate", "transform-type", "index", "vertex", "vertices-type", "nesting", "geometry-type",
            "template", "instance", "missing-key", "wrong-type", "lod", "semantics", "crs", "tree", "text",
            "deep-json", "huge-index-list", "empty", "garbage", "parents")


def _city_doc(base: FileBase, rnd, op: str, case: FileCase) -> dict | bytes:
    doc = copy.deepcopy(base.city)
    objs = doc["CityObjects"]
    geoms = [(k, g) for k, o in objs.items() for g in o.get("geometry", [])]
    k, g = rnd.choice(geoms)

    def rings(node, depth=0):     # every innermost index list of a boundaries tree
        if isinstance(node, list) and node and all(isinstance(i, int) for i in node):
            return [node]
        return [r for n in (node if isinstance(node, list) else []) for r in rings(n, depth + 1)]

    if op == "scale":
        doc["transform"]["scale"][rnd.randrange(3)] = rnd.choice([0, -1, -0.001, math.nan, math.inf, 1e-300, 1e300,
                                                                   "1", None])
    elif op == "translate":
        doc["transform"]["translate"][rnd.randrange(3)] = rnd.choice([math.nan, math.inf, 1e300, -1e300, "0", None])
    elif op == "transform-type":
        doc["transform"] = rnd.choice([None, [], "x", {"scale": [1, 1]}, {"scale": [1, 1, 1]},
                                       {"scale": [1, 1, 1], "translate": [0, 0, 0, 0]}])
    elif op == "index":
        r = rnd.choice(rings(g["boundaries"]))
        r[rnd.randrange(len(r))] = rnd.choice([-1, len(doc["vertices"]), len(doc["vertices"]) + 10**6, 1.5, "3",
                                               True, None, 2**64, -(2**63)])
    elif op == "vertex":
        v = rnd.choice(doc["vertices"])
        v[rnd.randrange(3)] = rnd.choice([math.nan, math.inf, -math.inf, 1e300, -1e300, "1", None, True, [], 2**70])
    elif op == "vertices-type":
        i = rnd.randrange(len(doc["vertices"]))
        doc["vertices"][i] = rnd.choice([[], [1, 2], [1, 2, 3, 4], "1,2,3", None, {"x": 1}])
    elif op == "nesting":
        if rnd.random() < 0.5:
            g["boundaries"] = [g["boundaries"]]            # one level deeper (a Solid's depth)
        else:
            g["boundaries"] = [r for s in g["boundaries"] for r in s]   # one level shallower
    elif op == "geometry-type":
        g["type"] = rnd.choice(["Solid", "MultiSolid", "CompositeSolid", "CompositeSurface", "MultiPoint",
                                "MultiLineString", "GeometryInstance", "bogus", "", None])
    elif op in ("template", "instance"):
        doc["geometry-templates"] = {"templates": [{"type": "MultiSurface", "lod": "2",
                                                    "boundaries": [[[0, 1, 2]], [[0, 2, 3]]]}],
                                     "vertices-templates": [[0, 0, 0], [5, 0, 0], [5, 5, 8], [0, 5, 8]]}
        inst = {"type": "GeometryInstance", "template": 0, "boundaries": [0],
                "transformationMatrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}
        objs["tree-1"] = {"type": "SolitaryVegetationObject", "geometry": [inst]}
        if op == "template":
            t = doc["geometry-templates"]
            which = rnd.choice(("vt-nan", "vt-index", "templates-type", "vt-type", "missing-vt"))
            if which == "vt-nan":
                t["vertices-templates"][rnd.randrange(4)][rnd.randrange(3)] = rnd.choice([math.nan, 1e300, "x"])
            elif which == "vt-index":
                t["templates"][0]["boundaries"][0][0][0] = rnd.choice([-1, 4, 99, 1.5])
            elif which == "templates-type":
                t["templates"] = rnd.choice([None, {}, "x", [None], [[]]])
            elif which == "vt-type":
                t["vertices-templates"] = rnd.choice([None, {}, "x", [[1, 2]]])
            else:
                del t["vertices-templates"]
            case.desc += f" ({which})"
        else:
            key = rnd.choice(("template", "boundaries", "transformationMatrix"))
            inst[key] = rnd.choice({"template": [-1, 1, 99, 1.5, "0", None],
                                    "boundaries": [[-1], [10**6], [0, 1], [], None, [1.5], [[0]]],
                                    "transformationMatrix": [[1] * 15, [math.nan] * 16, [1e300] * 16,
                                                             [0] * 16, None, "I"]}[key])
            case.desc += f" ({key} {inst[key]!r})"
    elif op == "missing-key":
        key = rnd.choice(["CityObjects", "vertices", "transform", "type", "version", "metadata"])
        doc.pop(key, None)
        case.desc += f" ({key})"
    elif op == "wrong-type":
        key = rnd.choice(["CityObjects", "vertices", "transform", "type", "version", "metadata"])
        doc[key] = rnd.choice(CITY_VALUES)
        case.desc += f" ({key} = {doc[key]!r})"
    elif op == "lod":
        g["lod"] = rnd.choice([None, "", "x", 2, -1, math.nan, [2], "99"])
    elif op == "semantics":
        sem = g.setdefault("semantics", {"surfaces": [{"type": "RoofSurface"}], "values": [0]})
        if rnd.random() < 0.5:
            sem["values"] = rnd.choice([[99] * 7, [-1] * 7, [None] * 7, "x", [[0]], [1.5] * 7, []])
        else:
            sem["surfaces"] = rnd.choice([[], None, [{"type": "bogus"}] * 3, [{"type": None}] * 3, "x"])
    elif op == "crs":
        doc["metadata"]["referenceSystem"] = rnd.choice([
            "", "EPSG:4326", "https://www.opengis.net/def/crs/EPSG/0/4326", "https://www.opengis.net/def/crs/EPSG/0/0",
            "urn:ogc:def:crs:EPSG::28992", "https://www.opengis.net/def/crs/EPSG/0/32611+6360", "bogus", None, 28992,
            "https://www.opengis.net/def/crs/EPSG/0/28992" + "x" * 200])
        case.desc += f" ({doc['metadata']['referenceSystem']!r})"
    elif op == "tree":
        doc, log = mutate_tree(doc, rnd, rnd.randint(1, 3))
        case.desc += " " + "; ".join(log)
    elif op == "text":
        data, log = mutate_text(json.dumps(doc).encode(), rnd, rnd.randint(1, 3))
        case.desc += " " + "; ".join(log)
        return data
    elif op == "deep-json":
        n = rnd.choice([100, 3000, 100000])
        g["boundaries"] = "@@DEEP@@"
        case.desc += f" depth {n}"
        return json.dumps(doc).replace('"@@DEEP@@"', "[" * n + "0" + "]" * n).encode()
    elif op == "huge-index-list":
        g["boundaries"] = [[list(range(len(doc["vertices"]))) * rnd.choice([1, 1000])]]
    elif op == "empty":
        return rnd.choice([b"", b"{}", b"[]", b"null", b'{"type": "CityJSON"}'])
    elif op == "garbage":
        return GARBAGE[:rnd.randrange(1, 4096)]
    elif op == "parents":
        objs[k]["parents"] = rnd.choice([["nope"], [k], "bldg", None, [1]])
        objs.setdefault("bldg", {}).setdefault("children", []).append(rnd.choice(["nope", k, None]))
    else:
        raise ValueError(op)
    return doc


def _city_case(base: FileBase, rnd, op: str, d: Path) -> FileCase:
    case = FileCase("cityjson", op, [], f"cityjson: {op}")
    doc = _city_doc(base, rnd, op, case)
    p = d / "city.city.json"
    p.write_bytes(doc if isinstance(doc, bytes) else json.dumps(doc).encode())   # NaN/Infinity as JSON tokens
    sc = copy.deepcopy(base.city_scenario)
    sc["data"]["buildings"]["path"] = str(p)
    (d / "scenario.yaml").write_text(yaml.safe_dump(sc, sort_keys=False))
    cmd = rnd.choice(("inspect-file", "inspect-scenario", "run"))
    case.argv = {"inspect-file": ["inspect", str(p)], "inspect-scenario": ["inspect", str(d / "scenario.yaml")],
                 "run": ["run", str(d / "scenario.yaml"), "--stage", "surface", "--max-memory", "2G",
                         *base.tail(d)]}[cmd]
    case.desc += f" ({cmd})"
    return case


# ------------------------------------------------------------------------------ OSM
OSM_HEIGHTS = ["12;55", "-5", "1e9", "nan", "inf", "-inf", "1e6", "-3", "12 m", "40'", "40 ft", "12'6\"", "0", "",
               " ", "garbage", "12,5", "1e-320", "NaN m", "1e308", "0x10", "½", "12 km", "3 storeys", "∞", "1_000",
               "12.5.3", "-0", "99999999999999999999999", "12\x00", "yes"]
OSM_LEVEL_TAGS = ("height", "building:levels", "roof:levels", "min_height", "building:min_level", "roof:height",
                  "ele", "building:height")
OSM_OPS = ("height", "levels", "many-tags", "node-coords", "missing-node", "unclosed", "two-nodes", "bowtie",
           "relation", "duplicate-id", "text", "empty", "garbage", "huge-way", "not-building")
LON0, LAT0 = 24.9410, 60.1705


def _osm_xml(rnd, op: str, case: FileCase) -> bytes:
    nodes: list[tuple[int, object, object]] = []
    ways: list[tuple[int, list[int], dict]] = []
    rels: list[str] = []
    nid = 1
    for b in range(4):                           # four 20 m x 20 m buildings in a row
        lon, lat = LON0 + b * 0.0006, LAT0 + b * 0.0003
        ids = []
        for dx, dy in ((0, 0), (0.00036, 0), (0.00036, 0.00018), (0, 0.00018)):
            nodes.append((nid, lon + dx, lat + dy))
            ids.append(nid)
            nid += 1
        ways.append((100 + b, [*ids, ids[0]], {"building": "yes", "height": "12"}))
    w = rnd.randrange(len(ways))
    tags = ways[w][2]
    if op == "height":
        tags["height"] = rnd.choice(OSM_HEIGHTS)
    elif op == "levels":
        tags.pop("height")
        tags["building:levels"] = rnd.choice(OSM_HEIGHTS)
        if rnd.random() < 0.5:
            tags["roof:levels"] = rnd.choice(OSM_HEIGHTS)
    elif op == "many-tags":
        for t in rnd.sample(OSM_LEVEL_TAGS, rnd.randint(1, len(OSM_LEVEL_TAGS))):
            tags[t] = rnd.choice(OSM_HEIGHTS)
        tags["building"] = rnd.choice(["yes", "house", "church", "", "no", "roof", "construction"])
    elif op == "node-coords":
        i = rnd.randrange(len(nodes))
        bad = rnd.choice(["nan", "inf", "1e308", "91", "-181", "", "x", "1e-400"])
        nodes[i] = (nodes[i][0], bad, nodes[i][2]) if rnd.random() < 0.5 else (nodes[i][0], nodes[i][1], bad)
    elif op == "missing-node":
        ways[w][1][rnd.randrange(1, 4)] = 99999
    elif op == "unclosed":
        ways[w][1].pop()
    elif op == "two-nodes":
        ways[w] = (ways[w][0], ways[w][1][:2], tags)
    elif op == "bowtie":
        ids = ways[w][1]
        ways[w] = (ways[w][0], [ids[0], ids[2], ids[1], ids[3], ids[0]], tags)
    elif op == "relation":
        rels.append(f'<relation id="900" version="1"><member type="way" ref="{rnd.choice([100, 555, -1])}" '
                    f'role="{rnd.choice(["outer", "inner", "", "x"])}"/><member type="way" ref="101" role="inner"/>'
                    f'<tag k="type" v="multipolygon"/><tag k="building" v="yes"/>'
                    f'<tag k="height" v="{rnd.choice(OSM_HEIGHTS)}"/></relation>')
    elif op == "duplicate-id":
        ways.append((ways[w][0], ways[(w + 1) % 4][1], {"building": "yes", "height": rnd.choice(OSM_HEIGHTS)}))
    elif op == "huge-way":
        ids = []
        for k in range(rnd.choice([1000, 50000])):
            a = 2 * math.pi * k / 1000
            nodes.append((nid, LON0 + 0.0002 * math.cos(a), LAT0 + 0.0001 * math.sin(a)))
            ids.append(nid)
            nid += 1
        ways.append((500, [*ids, ids[0]], {"building": "yes", "height": rnd.choice(OSM_HEIGHTS)}))
    elif op == "not-building":
        tags.pop("building")
        tags["building:part"] = "yes"
        tags["height"] = rnd.choice(OSM_HEIGHTS)
    elif op == "empty":
        return rnd.choice([b"", b"<osm/>", b'<?xml version="1.0"?><osm version="0.6"></osm>', b"<osm>"])
    elif op == "garbage":
        return GARBAGE[:rnd.randrange(1, 4096)]
    elif op not in ("text",):
        raise ValueError(op)
    if op in ("height", "levels", "many-tags", "not-building", "relation", "duplicate-id", "huge-way"):
        case.desc += " " + json.dumps({k: v for k, v in tags.items() if k != "building"})[:200]

    def q(v) -> str:
        return str(v).replace("&", "&amp;").replace('"', "&quot;").replace("<", "&lt;").replace("\x00", "")

    out = ['<?xml version="1.0" encoding="UTF-8"?>', '<osm version="0.6" generator="skyroute-fuzz">']
    out += [f'<node id="{i}" version="1" lat="{q(la)}" lon="{q(lo)}"/>' for i, lo, la in nodes]
    for i, ids, tg in ways:
        out.append(f'<way id="{i}" version="1">' + "".join(f'<nd ref="{n}"/>' for n in ids)
                   + "".join(f'<tag k="{q(k)}" v="{q(v)}"/>' for k, v in tg.items()) + "</way>")
    out += rels
    out.append("</osm>")
    data = "\n".join(out).encode()
    if op == "text":
        data, log = mutate_text(data, rnd, rnd.randint(1, 3))
        case.desc += " " + "; ".join(log)
    return data


def _osm_case(base: FileBase, rnd, op: str, d: Path) -> FileCase:
    case = FileCase("osm", op, [], f"osm: {op}")
    p = d / "city.osm"
    p.write_bytes(_osm_xml(rnd, op, case))
    sc = copy.deepcopy(base.osm_scenario)
    sc["data"]["buildings"]["path"] = str(p)
    if rnd.random() < 0.3:
        sc["data"]["landuse"] = str(p)
    (d / "scenario.yaml").write_text(yaml.safe_dump(sc, sort_keys=False))
    cmd = rnd.choice(("inspect-file", "inspect-scenario", "run"))
    case.argv = {"inspect-file": ["inspect", str(p)], "inspect-scenario": ["inspect", str(d / "scenario.yaml")],
                 "run": ["run", str(d / "scenario.yaml"), "--stage", "surface", "--max-memory", "2G",
                         *base.tail(d)]}[cmd]
    case.desc += f" ({cmd})"
    return case


# ------------------------------------------------------------------------------ NetCDF wind
WIND_OPS = ("speed-units", "height-units", "no-units", "nan-data", "inf-data", "all-nan-heights", "huge-data",
            "decreasing-heights", "levels-nan", "one-level", "wrong-dims", "transposed", "extra-dim",
            "times", "far-time", "no-coords", "lat-nan", "outside", "lon-180", "height-levels", "truncated",
            "garbage", "empty", "folder", "huge-declared", "attrs-types")


def _wind_dataset(rnd, op: str, case: FileCase):
    import xarray as xr

    lat = np.array([35.0, 34.5, 34.0, 33.5])
    lon = np.array([241.0, 241.5, 242.0, 242.5])
    p = np.array([1000.0, 925.0, 850.0])
    gh = np.broadcast_to(np.array([100.0, 800.0, 1500.0])[:, None, None], (3, 4, 4)).astype(np.float32).copy()
    dims3, dims2 = ("isobaricInhPa", "latitude", "longitude"), ("latitude", "longitude")
    sp = {"units": "m s**-1"}
    ds = xr.Dataset({"u": (dims3, np.full((3, 4, 4), 5.0, np.float32), dict(sp)),
                     "v": (dims3, np.full((3, 4, 4), 1.0, np.float32), dict(sp)),
                     "gh": (dims3, gh, {"units": "gpm"}),
                     "u10": (dims2, np.full((4, 4), 3.0, np.float32), dict(sp)),
                     "v10": (dims2, np.full((4, 4), 1.0, np.float32), dict(sp))},
                    coords={"isobaricInhPa": ("isobaricInhPa", p, {"units": "hPa"}),
                            "latitude": ("latitude", lat, {"units": "degrees_north"}),
                            "longitude": ("longitude", lon, {"units": "degrees_east"}),
                            "valid_time": np.datetime64("2020-01-03T18:00")})
    var = rnd.choice(["u", "v", "u10", "v10"])
    if op == "speed-units":
        ds[var].attrs["units"] = rnd.choice(["km h**-1", "furlongs per fortnight", "knots", "kt", "m/s", "K", "",
                                             "mph", "cm s-1", "m s-2", "M S-1"])
        case.desc += f" {var}: {ds[var].attrs['units']!r}"
    elif op == "height-units":
        ds["gh"].attrs["units"] = rnd.choice(["km", "ft", "m2 s-2", "m**2 s**-2", "dam", "furlong", "", "gpm "])
        case.desc += f" gh: {ds['gh'].attrs['units']!r}"
    elif op == "no-units":
        del ds[rnd.choice(["u", "v", "gh", "u10"])].attrs["units"]
    elif op == "attrs-types":
        ds[var].attrs["units"] = rnd.choice([5, 1.5, np.array([1, 2]), "m s-1;m s-1"])
    elif op in ("nan-data", "inf-data", "huge-data"):
        v = {"nan-data": np.nan, "inf-data": rnd.choice([np.inf, -np.inf]), "huge-data": rnd.choice([1e30, 3e38,
                                                                                                     -1e30])}[op]
        a = ds[var].values.copy()
        if rnd.random() < 0.5:
            a[...] = v
        else:
            a[..., rnd.randrange(4), rnd.randrange(4)] = v
        ds[var] = (ds[var].dims, a, ds[var].attrs)
        case.desc += f" {var} {v}"
    elif op == "all-nan-heights":
        ds["gh"] = (dims3, np.full((3, 4, 4), np.nan, np.float32), {"units": "gpm"})
    elif op == "decreasing-heights":
        ds["gh"] = (dims3, gh[::-1].copy() * rnd.choice([1, -1, 0]), {"units": "gpm"})
    elif op == "levels-nan":
        ds = ds.assign_coords(isobaricInhPa=("isobaricInhPa", rnd.choice([[1000.0, np.nan, 850.0],
                                                                          [1000.0, 1000.0, 1000.0],
                                                                          [np.inf, 925.0, -5.0]]), {"units": "hPa"}))
    elif op == "one-level":
        ds = ds.isel(isobaricInhPa=[0])
    elif op == "wrong-dims":
        ds = ds.drop_vars(["u", "v"]).assign(u=(("a", "b"), np.ones((2, 2)), sp), v=(("a", "b"), np.ones((2, 2)), sp))
    elif op == "transposed":
        ds["u"] = ds["u"].transpose("longitude", "isobaricInhPa", "latitude")
    elif op == "extra-dim":
        ds = ds.expand_dims(number=rnd.choice([1, 2, 5]))
    elif op == "times":
        ds = ds.drop_vars("valid_time").expand_dims(time=np.array(["2020-01-03T12:00", "2020-01-03T18:00",
                                                                  "2020-01-04T00:00"], "datetime64[ns]"))
    elif op == "far-time":
        ds = ds.assign_coords(valid_time=np.datetime64(rnd.choice(["1970-01-01T00:00", "2262-01-01T00:00",
                                                                   "2020-01-03T23:59"])))
    elif op == "no-coords":
        ds = ds.drop_vars(rnd.choice([["latitude"], ["longitude"], ["latitude", "longitude"], ["isobaricInhPa"]]))
    elif op == "lat-nan":
        la = lat.copy()
        la[rnd.randrange(4)] = rnd.choice([np.nan, np.inf, 91.0, 34.5])
        ds = ds.assign_coords(latitude=("latitude", la, {"units": "degrees_north"}))
    elif op == "outside":
        ds = ds.assign_coords(latitude=("latitude", lat + 30, {"units": "degrees_north"}))
    elif op == "lon-180":
        ds = ds.assign_coords(longitude=("longitude", lon - 360.0 + rnd.choice([0, 720, 0.25]),
                                         {"units": "degrees_east"}))
    elif op == "height-levels":
        hz = np.array(rnd.choice([[10.0, 50.0, 100.0], [np.nan, 50.0, 100.0], [-10.0, 0.0, 1e30], [100.0, 50.0, 10.0]]))
        ds = ds.drop_vars("gh").rename({"isobaricInhPa": "heightAboveGround"}).assign_coords(
            heightAboveGround=("heightAboveGround", hz, {"units": rnd.choice(["m", "ft", "km", ""])}))
    elif op not in ("truncated", "garbage", "empty", "folder", "huge-declared"):
        raise ValueError(op)
    return ds


def _wind_file(rnd, op: str, d: Path, case: FileCase) -> Path:
    p = d / "wind.nc"
    if op == "garbage":
        p.write_bytes(rnd.choice([b"CDF\x01", b"\x89HDF\r\n\x1a\n", b""]) + GARBAGE[:rnd.randrange(1, 4096)])
        return p
    if op == "empty":
        p.write_bytes(b"")
        return p
    if op == "folder":
        p.mkdir()
        return p
    if op == "huge-declared":       # 3 x 20000 x 20000 float32 declared, nothing written: a few kB
        import netCDF4

        with netCDF4.Dataset(p, "w") as nc:
            nc.createDimension("isobaricInhPa", 3)
            nc.createDimension("latitude", 20000)
            nc.createDimension("longitude", 20000)
            nc.createVariable("isobaricInhPa", "f8", ("isobaricInhPa",))[:] = [1000.0, 925.0, 850.0]
            nc.createVariable("latitude", "f8", ("latitude",))[:] = np.linspace(89.9, -89.9, 20000)
            nc.createVariable("longitude", "f8", ("longitude",))[:] = np.linspace(0, 359.98, 20000)
            for name, units in (("u", "m s-1"), ("v", "m s-1"), ("gh", "gpm")):
                vv = nc.createVariable(name, "f4", ("isobaricInhPa", "latitude", "longitude"), zlib=True,
                                       chunksizes=(1, 500, 500), fill_value=np.float32(1.0))
                vv.units = units
        return p
    ds = _wind_dataset(rnd, "nan-data" if op == "truncated" else op, case)
    ds.to_netcdf(p, engine=rnd.choice(["netcdf4", "scipy"]) if op != "attrs-types" else "netcdf4")
    if op == "truncated":
        b = p.read_bytes()
        p.write_bytes(b[:rnd.randrange(1, len(b))])
    return p


def _wind_case(base: FileBase, rnd, op: str, d: Path) -> FileCase:
    case = FileCase("wind", op, [], f"wind: {op}")
    try:
        p = _wind_file(rnd, op, d, case)
    except (ValueError, TypeError) as exc:      # a dataset xarray itself will not write: a plain file instead
        p = d / "wind.nc"
        p.write_bytes(b"")
        case.desc += f" (not writable: {type(exc).__name__}; empty file)"
    profile = rnd.choice(["levels", "levels", "power", "constant"])
    sc = base.dem_case(d, resolution_m=150.0, wind={"path": str(p), "time_utc": TIME, "profile": profile})
    case.argv = ["run", str(sc), "--stage", "wind", "--max-memory", "2G", *base.tail(d)]
    case.desc += f" profile {profile}"
    return case


# ------------------------------------------------------------------------------ almanacs
ALM_VALUES = ["1.5", "-5153.6", "nan", "NaN", "inf", "-inf", "1e308", "-1e308", "99999999", "-0", "", "0x1F", "1,5",
              "garbage", "1.0E+999", "1e-320", "000", "-1", "4294967296", "2.0", "1e5"]
ALM_FIELDS = ("ID", "Health", "Eccentricity", "Time of Applicability(s)", "Orbital Inclination(rad)",
              "Rate of Right Ascen(r/s)", "SQRT(A)  (m 1/2)", "Right Ascen at Week(rad)", "Argument of Perigee(rad)",
              "Mean Anom(rad)", "Af0(s)", "Af1(s/s)", "week")
ALM_OPS = ("field", "eccentricity", "sqrt-a", "week", "health", "id", "truncate", "duplicate-record", "double-line",
           "delete-line", "garbage", "empty", "crlf", "utf16", "nul", "long-line", "many-records", "rinex-header",
           "text", "two-almanacs")


def _yuma(base: FileBase, rnd, op: str, case: FileCase) -> bytes:
    lines = base.yuma.splitlines()
    heads = [i for i, ln in enumerate(lines) if ln.startswith("******")]

    def set_field(name: str | None, value: str) -> None:
        cands = [i for i, ln in enumerate(lines) if ":" in ln and (name is None or ln.lower().startswith(name.lower()))]
        i = rnd.choice(cands)
        key = lines[i].split(":", 1)[0]
        lines[i] = f"{key}:  {value}"
        case.desc += f" {key.strip()} = {value!r}"

    if op == "field":
        set_field(None, rnd.choice(ALM_VALUES))
    elif op == "eccentricity":
        set_field("Eccentricity", rnd.choice(["1.5", "1.0", "-0.1", "nan", "0.99999"]))
    elif op == "sqrt-a":
        set_field("SQRT(A)", rnd.choice(["-5153.6", "0", "nan", "1e300", "1e-300", "6.4"]))
    elif op == "week":
        set_field("week", rnd.choice(["99999999", "-1", "1e20", "nan", "4096", "2.5"]))
    elif op == "health":
        set_field("Health", rnd.choice(["garbage", "-1", "256", "1e9", "", "nan", "0x3F"]))
    elif op == "id":
        set_field("ID", rnd.choice(["0", "999", "-1", "01", "nan", "1.5", "G01"]))
    elif op == "truncate":
        return base.yuma.encode()[:rnd.randrange(len(base.yuma))]
    elif op == "duplicate-record":
        k = rnd.randrange(len(heads))
        a, b = heads[k], heads[k + 1] if k + 1 < len(heads) else len(lines)
        lines[b:b] = lines[a:b] * rnd.choice([1, 2])
    elif op == "double-line":
        i = rnd.randrange(len(lines))
        lines.insert(i, lines[i])
    elif op == "delete-line":
        del lines[rnd.randrange(len(lines))]
    elif op == "garbage":
        return GARBAGE[:rnd.randrange(1, 4096)]
    elif op == "empty":
        return rnd.choice([b"", b"\n", b"****** Week 1 almanac for PRN-01 ******\n"])
    elif op == "crlf":
        return base.yuma.replace("\n", "\r\n").encode()
    elif op == "utf16":
        return base.yuma.encode("utf-16")
    elif op == "nul":
        i = rnd.randrange(len(base.yuma))
        return (base.yuma[:i] + "\x00" + base.yuma[i:]).encode()
    elif op == "long-line":
        lines.insert(rnd.randrange(len(lines)), "Eccentricity: " + "9" * rnd.choice([1000, 2_000_000]))
    elif op == "many-records":
        a, b = heads[0], heads[1]
        lines = lines[a:b] * rnd.choice([100, 3000])
    elif op == "rinex-header":
        lines.insert(0, "     2.10           N: GPS NAV DATA                         RINEX VERSION / TYPE")
    elif op == "text":
        data, log = mutate_text(base.yuma.encode(), rnd, rnd.randint(1, 3))
        case.desc += " " + "; ".join(log)
        return data
    elif op == "two-almanacs":
        set_field(None, rnd.choice(ALM_VALUES))
    else:
        raise ValueError(op)
    return ("\n".join(lines) + "\n").encode()


def _almanac_case(base: FileBase, rnd, op: str, d: Path) -> FileCase:
    case = FileCase("almanac", op, [], f"almanac: {op}")
    p = d / "alm.txt"
    p.write_bytes(_yuma(base, rnd, op, case))
    if op == "two-almanacs" or rnd.random() < 0.7:
        alms = ["--almanac", str(p)]
        if op == "two-almanacs":
            (d / "good.txt").write_text(base.yuma)
            alms += ["--almanac", str(d / "good.txt")]
        case.argv = ["sky", *alms, "--time", rnd.choice([TIME, "2020-01-03T12:00:00Z", "2038-01-19T03:14:08Z"]),
                     "--lat", "34.3", "--lon", "-118.2"]
    else:
        sc = base.dem_case(d, almanacs=[str(p)])
        case.argv = ["run", str(sc), "--stage", "satellites", "--max-memory", "2G", *base.tail(d)]
    return case


# ------------------------------------------------------------------------------ events (hostile numbers)
EVENT_NUMBERS = [1e6, -1e6, math.inf, -math.inf, math.nan, 1e300, -1e300, 5e-324, 0.0, -0.0, 1e-9, 86400.0 * 3650,
                 2**63, 2**64 + 1, -(2**63) - 1, 1e7, 400.0, 361.0, -90.0]
EVENT_OPS = ("number", "speed", "duration", "many-numbers", "many-events", "huge-event-list", "big-polygon",
             "huge-polygon")


def _numeric_paths(node, prefix=()):
    out = []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _numeric_paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _numeric_paths(v, (*prefix, i))
    elif isinstance(node, (int, float)) and not isinstance(node, bool):
        out.append(prefix)
    return out


def _events_case(base: FileBase, rnd, op: str, d: Path) -> FileCase:
    case = FileCase("events-values", op, [], f"events-values: {op}")
    ev = copy.deepcopy(base.events.events)
    paths = _numeric_paths(ev)

    def put(path, value):
        node = ev
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value
        case.desc += f" {'.'.join(map(str, path))}={value!r}"

    if op == "number":
        put(rnd.choice(paths), rnd.choice(EVENT_NUMBERS))
    elif op == "speed":
        put(next(p for p in paths if p[-1] == "speed_mps"), rnd.choice([1e6, math.inf, -1.0, 1e300, math.nan, 343.0]))
    elif op == "duration":
        name = rnd.choice(["end_s", "start_s", "t_s"])
        put(rnd.choice([p for p in paths if p[-1] == name]),
            rnd.choice([math.inf, 1e300, -1.0, math.nan, 86400.0 * 3650, 2**64]))
    elif op == "many-numbers":
        for p in rnd.sample(paths, min(len(paths), rnd.randint(2, 8))):
            put(p, rnd.choice(EVENT_NUMBERS))
    elif op in ("many-events", "huge-event-list"):
        n = 1000 if op == "many-events" else 100000
        ev = [dict(ev[1], t_s=float(i % 600)) for i in range(n)]
        case.desc += f" {n} wind events"
    elif op in ("big-polygon", "huge-polygon"):
        nf = next(e for e in ev if e.get("kind") == "nofly")
        n = 1000 if op == "big-polygon" else 200000
        a = np.linspace(0, 2 * math.pi, n, endpoint=False)
        nf["polygon"] = np.column_stack([385725 + 30 * np.cos(a), 6671660 + 30 * np.sin(a)]).tolist()
        case.desc += f" a no-fly polygon of {n} vertices"
    else:
        raise ValueError(op)
    sc_path, ev_path = d / "H.yaml", d / "events.yaml"
    sc_path.write_text(yaml.safe_dump(base.events.scenario, sort_keys=False))
    doc = {"events": ev} if rnd.random() < 0.5 else ev
    if op in ("many-events", "huge-event-list", "big-polygon", "huge-polygon"):   # finite numbers: JSON is YAML, and fast to write
        ev_path.write_text(json.dumps(doc))
    else:
        ev_path.write_text(yaml.safe_dump(doc))
    case.argv = ["fly", str(sc_path), "--events", str(ev_path), "--max-memory", "1", "--cache-dir", str(base.cache),
                 "--out", str(d / "out")]
    return case


# ------------------------------------------------------------------------------ airspace files
AIRSPACE_OPS = ("intent-json", "mission-json", "wkb", "volume-numbers", "intent-numbers", "meta", "rtree",
                "drop-table", "state", "flip-bytes", "truncate", "garbage-after-header", "empty", "wal-garbage",
                "decisions-json", "delete-volumes")
BAD_JSON = ["{", "[]", "null", "1", '"x"', "NaN", '{"volumes": 5}', '{"volumes": [{"volume": null}]}',
            '{"volumes": [{}]}', "[" * 5000 + "]" * 5000, "\x00", '{"priority": "x"}', "x" * 100000]


def _airspace_case(base: FileBase, rnd, op: str, d: Path) -> FileCase:
    case = FileCase("airspace", op, [], f"airspace: {op}")
    p = d / "air.sqlite"
    p.write_bytes(base.airspace)
    who = rnd.choice(["a", "b"])

    def sql(stmt: str, *args) -> None:
        c = sqlite3.connect(p)
        try:
            c.execute(stmt, args)
            c.commit()
        except sqlite3.DatabaseError as exc:
            case.desc += f" (sqlite refused: {exc})"
        finally:
            c.close()

    if op == "intent-json":
        v = rnd.choice(BAD_JSON)
        sql("UPDATE intents SET details = ? WHERE id = ?", v, who)
        case.desc += f" details {v[:40]!r}"
    elif op == "mission-json":
        sql("UPDATE intents SET mission = ? WHERE id = ?", rnd.choice(BAD_JSON), who)
    elif op == "decisions-json":
        sql("UPDATE decisions SET mission_fields = ? WHERE mission = ?", rnd.choice(BAD_JSON), who)
    elif op == "wkb":
        import shapely

        v = rnd.choice([GARBAGE[:rnd.randrange(1, 200)], b"", b"\x01\x03\x00\x00\x00",
                        shapely.to_wkb(shapely.Point(0, 0)), shapely.to_wkb(shapely.Polygon()),
                        shapely.to_wkb(shapely.box(0, 0, 1e300, 1e300)),
                        shapely.to_wkb(shapely.Polygon([(0, 0), (1, 1), (1, 0), (0, 1)])),
                        shapely.to_wkb(shapely.Polygon([(0, 0), (math.nan, 0), (1, 1)])), "text", 5])
        sql("UPDATE volumes SET outline_wkb = ? WHERE intent_id = ?", v, who)
        case.desc += f" {repr(v)[:40]}"
    elif op == "volume-numbers":
        col = rnd.choice(["alt_lower_m", "alt_upper_m", "t_start_s", "t_end_s", "k"])
        v = rnd.choice([math.nan, math.inf, -math.inf, 1e300, "abc", -1, 2**62, b"\x00"])
        sql(f"UPDATE volumes SET {col} = ? WHERE intent_id = ?", v, who)
        case.desc += f" {col} = {v!r}"
    elif op == "intent-numbers":
        col = rnd.choice(["priority", "seq", "t_start_s", "t_end_s", "n_volumes", "departure_utc", "accepted_utc"])
        v = rnd.choice([math.nan, math.inf, 1e300, "abc", -1, 2**62, 0, "2100-13-45T99:00:00Z"])
        sql(f"UPDATE intents SET {col} = ? WHERE id = ?", v, who)
        case.desc += f" {col} = {v!r}"
    elif op == "meta":
        key = rnd.choice(["crs", "epoch_utc", "schema_version", "created_utc"])
        v = rnd.choice(["", "garbage", "EPSG:4326", "nan", "2100-13-45T99:00:00Z", "1", "2", "x" * 10000, "LOCAL_CS[]"])
        sql("UPDATE meta SET value = ? WHERE key = ?", v, key)
        case.desc += f" {key} = {v[:30]!r}"
    elif op == "rtree":
        if rnd.random() < 0.5:
            sql("DELETE FROM volume_rtree")
        else:
            sql("UPDATE volume_rtree SET min_x = ?, max_x = ?", rnd.choice([1e38, -1e38, 0.0]), rnd.choice([0.0, 1.0]))
    elif op == "drop-table":
        t = rnd.choice(["decisions", "volumes", "intents", "meta", "volume_rtree"])
        sql(f"DROP TABLE {t}")
        case.desc += f" {t}"
    elif op == "state":
        sql("UPDATE intents SET state = ? WHERE id = ?", rnd.choice(["Bogus", "", "x" * 1000, None]), who)
    elif op == "delete-volumes":
        sql("DELETE FROM volumes WHERE intent_id = ?", who)
    elif op == "flip-bytes":
        b = bytearray(base.airspace)
        for _ in range(rnd.randint(1, 30)):
            i = rnd.randrange(100, len(b))
            b[i] ^= 1 << rnd.randrange(8)
        p.write_bytes(bytes(b))
    elif op == "truncate":
        p.write_bytes(base.airspace[:rnd.randrange(16, len(base.airspace))])
    elif op == "garbage-after-header":
        p.write_bytes(b"SQLite format 3\x00" + GARBAGE[:rnd.randrange(1, 4096)])
    elif op == "empty":
        p.write_bytes(b"")
    elif op == "wal-garbage":
        (d / "air.sqlite-wal").write_bytes(GARBAGE[:rnd.randrange(32, 4096)])
    else:
        raise ValueError(op)
    cmd = rnd.choice(("check", "check-json", "show", "ls"))
    if cmd == "show":
        case.argv = ["airspace", "show", str(p), rnd.choice([who, "zz"])]
    elif cmd == "ls":
        case.argv = ["airspace", "ls", str(p)]
    else:
        case.argv = ["airspace", "check", str(p), *(["--json"] if cmd == "check-json" else [])]
        case.exits = (0, 1, 2)
    case.desc += f" ({cmd})"
    return case


# ------------------------------------------------------------------------------ output folders
OUT_OPS = ("symlink-summary", "symlink-figures", "symlink-datasets", "user-summary", "hardlink-input",
           "dsm-named-surface", "manifest-garbage", "manifest-crafted", "manifest-above", "out-is-file",
           "out-is-input-folder", "fifo-summary", "folder-named-summary", "edited-previous", "symlink-manifest",
           "out-is-symlink")


def _record(p: str):
    st = os.lstat(p)
    if stat.S_ISLNK(st.st_mode):
        return ("link", os.readlink(p))
    if stat.S_ISREG(st.st_mode):
        with open(p, "rb") as f:
            return ("file", hashlib.sha256(f.read()).hexdigest())
    if stat.S_ISDIR(st.st_mode):
        return ("dir",)
    return ("other", stat.S_IFMT(st.st_mode))


def snapshot(root: Path) -> dict[str, tuple]:
    """Every entry under ``root`` (links not followed): a file's SHA-256, a link's target."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for n in dirnames + filenames:
            p = os.path.join(dirpath, n)
            out[os.path.relpath(p, root)] = _record(p)
    return out


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _file_rec(p: Path) -> dict:
    st = p.stat()
    return {"kind": "file", "size": st.st_size, "sha256": _sha(p)}


def _outfolder_case(base: FileBase, rnd, op: str, d: Path) -> FileCase:
    """A pre-filled --out; the check compares every entry of the case folder before and after."""
    from click.testing import CliRunner

    from skyroute.pipeline.cli import main

    case = FileCase("outfolder", op, [], f"outfolder: {op}")
    sc = base.dem_case(d)
    out = d / "out"
    outside = d / "outside"
    (outside / "f").mkdir(parents=True)
    (outside / "a.txt").write_text("a user's file outside --out\n")
    (outside / "f" / "b.txt").write_text("a user's file in a folder outside --out\n")
    stage = rnd.choice(["satellites", "satellites", "surface"])
    argv = ["run", str(sc), "--stage", stage, "--no-report", "-q", "--max-memory", "2G", "--cache-dir",
            str(base.cache), "--out", str(out)]
    exempt: set[str] = set()       # entries a planted manifest vouches for (right checksum, not an input)
    out.mkdir()
    if op == "symlink-summary":
        os.symlink(rnd.choice(["../outside/a.txt", str(outside / "a.txt"), "../dem.tif", "../scenario.yaml"]),
                   out / "summary.json")
    elif op == "symlink-figures":
        os.symlink(rnd.choice(["../outside/f", str(outside / "f"), ".."]), out / "figures")
    elif op == "symlink-datasets":
        os.symlink(rnd.choice(["../outside/f", "/"]), out / "datasets")
    elif op == "user-summary":
        (out / "user.txt").write_text("mine\n")
        (out / "summary.json").write_text(json.dumps({"outputs": ["user.txt", "../outside/a.txt", str(d / "dem.tif")],
                                                      "files": {"user.txt": {}}, "scenario": "fuzz-dem"}))
    elif op == "hardlink-input":
        os.link(d / rnd.choice(["dem.tif", "scenario.yaml", "yuma.txt"]), out / rnd.choice(["summary.json",
                                                                                           "surface.tif"]))
    elif op == "dsm-named-surface":
        shutil.move(d / "dem.tif", out / "surface.tif")
        sc = base.dem_case(d, terrain={"path": str(out / "surface.tif"), "vertical_datum": "EGM96 geoid"})
        (d / "dem.tif").unlink()
        argv[3] = "surface"
    elif op == "manifest-garbage":
        (out / "user.txt").write_text("mine\n")
        (out / ".skyroute-manifest.json").write_bytes(rnd.choice([
            GARBAGE[:300], b"[]", b"null", b'{"schema": 1}', b'{"schema": 1, "entries": []}',
            b'{"schema": 1, "entries": {"user.txt": 5}}', b'{"schema": "1", "entries": {}}', b"{" * 100000]))
    elif op == "manifest-crafted":
        (out / "user.txt").write_text("mine\n")
        (out / "summary.json").write_text("{}\n")
        os.symlink("../outside/f", out / "figures")
        entries = {"../outside/a.txt": _file_rec(outside / "a.txt"), str(outside / "a.txt"): _file_rec(
            outside / "a.txt"), "user.txt": {"kind": "file", "size": 5, "sha256": "0" * 64},
            "figures/b.txt": _file_rec(outside / "f" / "b.txt"), "./summary.json": _file_rec(out / "summary.json")}
        if rnd.random() < 0.5:      # the right checksum of summary.json: skyroute's file by the manifest's word
            entries["summary.json"] = _file_rec(out / "summary.json")
            exempt.add("out/summary.json")
        if rnd.random() < 0.5:      # a link record that matches: the link (not its target) is skyroute's
            entries["figures"] = {"kind": "link", "target": "../outside/f"}
            exempt.add("out/figures")
        if rnd.random() < 0.5:      # a hard link to an input, vouched for: still an input
            os.link(d / "dem.tif", out / "surface.tif")
            entries["surface.tif"] = _file_rec(out / "surface.tif")
        (out / ".skyroute-manifest.json").write_text(json.dumps({"schema": 1, "written_by": "skyroute",
                                                                 "command": "run", "entries": entries}))
        case.desc += f" (vouched: {sorted(exempt)})"
    elif op == "manifest-above":
        (out / "summary.json").write_text("{}\n")
        entries = {"out/summary.json": _file_rec(out / "summary.json"), "dem.tif": _file_rec(d / "dem.tif"),
                   "outside/a.txt": _file_rec(outside / "a.txt"), "scenario.yaml": _file_rec(sc)}
        (d / ".skyroute-manifest.json").write_text(json.dumps({"schema": 1, "written_by": "skyroute",
                                                               "command": "run", "entries": entries}))
        exempt.add("out/summary.json")
    elif op == "out-is-file":
        out.rmdir()
        out.write_text("a user's file named like the output folder\n")
    elif op == "out-is-input-folder":
        out.rmdir()
        argv[-1] = str(d)
    elif op == "fifo-summary":
        os.mkfifo(out / "summary.json")
        case.fifos.append(out / "summary.json")
    elif op == "folder-named-summary":
        (out / "summary.json").mkdir()
        (out / "summary.json" / "mine.txt").write_text("mine\n")
    elif op == "edited-previous":
        prev = ["run", str(sc), "--stage", stage, "--no-report", "-q", "--max-memory", "2G", "--cache-dir",
                str(base.cache), "--out", str(out)]
        CliRunner().invoke(main, prev)
        what = rnd.choice(["summary", "user-file", "figures-user-file", "manifest-entry-removed"])
        if what == "summary" and (out / "summary.json").is_file():
            (out / "summary.json").write_text('{"edited": "by the user"}\n')
        elif what == "user-file":
            (out / "notes.txt").write_text("mine\n")
        elif what == "figures-user-file" and (out / "figures").is_dir():
            (out / "figures" / "mine.png").write_bytes(b"\x89PNG user")
        elif (out / ".skyroute-manifest.json").is_file():
            m = json.loads((out / ".skyroute-manifest.json").read_text())
            m["entries"].pop("summary.json", None)
            (out / ".skyroute-manifest.json").write_text(json.dumps(m))
        case.desc += f" ({what})"
        # the genuine outputs of the first run are skyroute's: only the user's edits are checked
        man = out / ".skyroute-manifest.json"
        m = json.loads(man.read_text()) if man.is_file() else {"entries": {}}
        for rel, rec in m.get("entries", {}).items():
            p = out / rel
            if rec.get("kind") == "file" and p.is_file() and _sha(p) == rec.get("sha256"):
                exempt.add(f"out/{rel}")
            elif rec.get("kind") == "store":
                exempt.add(f"out/{rel}")
                exempt.update(f"out/{rel}/{q}" for q in (snapshot(p) if p.is_dir() else {}))
        exempt.add("out/.skyroute-manifest.json")
        for q in ("out/datasets", "out/figures"):
            exempt.add(q)
    elif op == "symlink-manifest":
        os.symlink(rnd.choice(["../outside/a.txt", "../dem.tif"]), out / ".skyroute-manifest.json")
    elif op == "out-is-symlink":
        out.rmdir()
        os.symlink("outside/f", out)
    else:
        raise ValueError(op)
    case.argv = argv
    before = snapshot(d)
    out_prefix = os.path.relpath(argv[-1], d)
    out_prefix = "" if out_prefix == "." else out_prefix + os.sep
    out_is_dir = os.path.isdir(argv[-1]) and not os.path.islink(argv[-1])

    def check() -> list[str]:
        after = snapshot(d)
        bad = []
        for rel, rec in before.items():
            mine = out_is_dir and rel.startswith(out_prefix) if out_prefix else False
            if rel in exempt or (rec == ("dir",) and mine) or (mine and os.path.basename(rel) in RESERVED):
                continue      # a name skyroute reserves (its manifest): replaced, never written through
            if rel not in after:
                bad.append(f"removed {rel} {rec[0]}")
            elif after[rel] != rec:
                bad.append(f"changed {rel}: {rec} -> {after[rel]}")
        for rel in after.keys() - before.keys():
            top = rel.split(os.sep)[0]
            if ".skyroute-staging" in rel or ".skyroute-trash" in rel:
                bad.append(f"left behind {rel}")
            elif out_prefix and rel.startswith(out_prefix) and out_is_dir:
                continue
            elif top.startswith("skyroute-unplaced-") or (out_prefix and top == out_prefix.rstrip(os.sep)):
                continue
            elif out_prefix == "" :
                if top in ("datasets", "figures", "summary.json", ".skyroute-manifest.json", "surface.tif"):
                    continue
                bad.append(f"new {rel} in the input folder")
            else:
                bad.append(f"new {rel} outside --out")
        return bad

    case.check = check
    return case


#: Names in --out that skyroute reserves for itself: a file there may be replaced (a link there is
#: replaced, not written through: its target is checked like any other file).
RESERVED = (".skyroute-manifest.json", ".summary.json.previous")

# ------------------------------------------------------------------------------ dispatch
#: Mutations not drawn unless asked (``unsafe=True``): one that could take the machine down.  The
#: NetCDF wind file declaring 3 x 20000 x 20000 values (once read whole: ~20 GB) is now refused from
#: its declared size, so it is drawn like the others.
UNSAFE_OPS: set[tuple[str, str]] = set()   # none left: the huge declared wind grid is refused from its header
#: Mutations too slow for the test suite (tens of seconds each today); benchmarks/fuzz_inputs.py
#: draws them.
SLOW_OPS = {("events-values", "huge-polygon"), ("events-values", "huge-event-list")}

OPS: dict[str, tuple[str, ...]] = {"raster": RASTER_OPS, "cityjson": CITY_OPS, "osm": OSM_OPS, "wind": WIND_OPS,
                                   "almanac": ALM_OPS, "events-values": EVENT_OPS, "airspace": AIRSPACE_OPS,
                                   "outfolder": OUT_OPS}
_BUILD = {"raster": _raster_case, "cityjson": _city_case, "osm": _osm_case, "wind": _wind_case,
          "almanac": _almanac_case, "events-values": _events_case, "airspace": _airspace_case,
          "outfolder": _outfolder_case}


def build_file_case(base: FileBase, rnd, kind: str | None = None, case_dir: Path | None = None,
                    op: str | None = None, unsafe: bool = False) -> FileCase:
    """One case of family ``kind`` (drawn when None), mutation ``op`` (drawn when None; never one
    of :data:`UNSAFE_OPS` unless ``unsafe``), its files in ``case_dir`` (made empty first)."""
    kind = kind or rnd.choice(FILE_KINDS)
    op = op or rnd.choice([o for o in OPS[kind] if unsafe or (kind, o) not in UNSAFE_OPS])
    d = case_dir or base.folder / "case"
    if d.exists() or d.is_symlink():
        shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    return _BUILD[kind](base, rnd, op, d)


def _release(fifos: list[Path], stop: threading.Event, after_s: float) -> None:
    """Open each FIFO for writing (then close it) once ``after_s`` passed: a reader blocked on
    it gets an end of file instead of hanging the whole run."""
    if stop.wait(after_s):
        return
    for f in fifos:
        try:
            fd = os.open(f, os.O_WRONLY | os.O_NONBLOCK)
            os.close(fd)
        except OSError:
            pass


def run_file_case(case: FileCase, fifo_after_s: float = 8.0):
    """Run the case in-process (:func:`_fuzz_inputs.run_case`); a FIFO is released after
    ``fifo_after_s`` so a blocked read shows up as a slow case, not a hung run.  Returns
    (Outcome, problems): the problems are the rule violations (exit code, error lines, the
    folder property)."""
    from _fuzz_inputs import run_case

    stop = threading.Event()
    t = None
    if case.fifos:
        t = threading.Thread(target=_release, args=(case.fifos, stop, fifo_after_s), daemon=True)
        t.start()
    try:
        out = run_case(case.argv)
    finally:
        stop.set()
    problems = []
    one_error = case.one_error and case.argv[0] != "inspect"    # inspect: one line per problem
    if out.traceback is None and out.exit_code not in case.exits:
        problems.append(f"exit {out.exit_code}")
    if out.exit_code == 2 and out.traceback is None and one_error and out.error_lines != 1:
        problems.append(f"exit 2 with {out.error_lines} error: lines")
    if case.check is not None:
        problems += case.check()
    return out, problems
