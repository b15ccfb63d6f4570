"""The scenario key reference (``catalogs/README.md``), generated from the settings models.

``python -m skyroute.pipeline.settings_reference > catalogs/README.md`` rewrites it; a test
checks that the shipped file equals the generated text, so the reference never drifts from
the models that validate the YAML.
"""

from __future__ import annotations

import types
import typing
from pathlib import Path
from typing import Any, get_args, get_origin

from pydantic import BaseModel
from pydantic_core import PydanticUndefined

from skyroute.pipeline.settings import Scenario

_UNITS = (("_mps2", "m/s^2"), ("_mps", "m/s"), ("_m2", "m^2"), ("_m", "m"), ("_deg", "deg"), ("_s", "s"),
          ("_min", "min"), ("_pct", "%"), ("_Wh", "Wh"), ("_mah", "mAh"), ("_kg", "kg"), ("_utc", "UTC"))

HEADER = """# Scenario keys

Every key a scenario YAML may hold (`catalogs/scenarios/*.yaml`, or your own file passed to any
command), with its type, unit and default. Unknown keys are an error. Paths are relative to the
YAML file. Heights are in the surface model's vertical datum; mission altitudes are above ground
level (AGL). This file is generated from the settings models
(`python -m skyroute.pipeline.settings_reference > catalogs/README.md`); a test keeps it in step.
"""


def _type_name(tp: Any) -> str:
    origin = get_origin(tp)
    if origin is typing.Annotated:
        return _type_name(get_args(tp)[0])
    if origin in (typing.Union, types.UnionType):
        return " | ".join(_type_name(a) for a in get_args(tp))
    if origin is typing.Literal:
        return " | ".join(repr(a) for a in get_args(tp))
    if origin in (tuple, list):
        args = get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"list of {_type_name(args[0])}"
        return f"[{', '.join(_type_name(a) for a in args)}]" if args else "list"
    if isinstance(tp, type):
        return {"NoneType": "null", "Path": "path", "datetime": "ISO 8601 time"}.get(tp.__name__, tp.__name__)
    return str(tp).replace("typing.", "")


def _unit(name: str) -> str:
    for suffix, unit in _UNITS:
        if name.endswith(suffix):
            return unit
    return ""


def _models(tp: Any) -> list[type[BaseModel]]:
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return [tp]
    return [m for a in get_args(tp) for m in _models(a)]


def scenario_keys(model: type[BaseModel] = Scenario, prefix: str = "") -> list[tuple[str, str, str, str, str]]:
    """``(key, type, unit, default, section doc)`` of every settable key, depth first."""
    rows = []
    for name, field in model.model_fields.items():
        if field.exclude:
            continue
        key = f"{prefix}{name}"
        subs = [m for m in _models(field.annotation) if m is not model]
        default = "required" if field.is_required() else (
            "" if field.default is PydanticUndefined else repr(field.default) if not isinstance(field.default, BaseModel)
            else "(section)")
        if isinstance(field.default, Path):
            default = str(field.default)
        tags = [_tag(sub) for sub in subs] if len(subs) > 1 else []
        doc = (f"a list of items told apart by their `kind`: {', '.join(str(t) for t in tags)}" if tags and all(tags)
               else _first_paragraph(subs[0]) if subs else "")
        rows.append((key, _type_name(field.annotation), _unit(name), default, doc))
        for sub in subs:
            tag = _tag(sub) if len(subs) > 1 else None
            if get_origin(field.annotation) in (tuple, list):
                if tag:
                    rows.append((f"{key}[kind={tag}]", sub.__name__, "", "", _first_paragraph(sub)))
                rows.extend(scenario_keys(sub, f"{key}[kind={tag}]." if tag else f"{key}[]."))
            else:
                rows.extend(scenario_keys(sub, key + "."))
    if prefix.endswith("].") and "[kind=" in prefix:  # a tagged union member: its kind first
        rows.sort(key=lambda r: r[0] != f"{prefix}kind")
    return rows


def _first_paragraph(model: type[BaseModel]) -> str:
    return (model.__doc__ or "").strip().split("\n\n")[0]


def _tag(model: type[BaseModel]) -> str | None:
    """The ``kind`` of a member of a tagged union (``Literal['wind']`` -> ``wind``)."""
    f = model.model_fields.get("kind")
    if f is None or get_origin(f.annotation) is not typing.Literal:
        return None
    return str(get_args(f.annotation)[0])


OWN_CITY = """## Bring your own city

Four minimal scenarios, one per kind of data, that work as written once your file sits next to
the YAML under the name it gives (`tests/test_own_city.py` loads each block below as written,
inspects it and plans it on a small fixture of that kind).  Before planning, `skyroute inspect my-city.yaml`
(or `skyroute inspect dsm.tif`) says in seconds what skyroute will make of the data: CRS and
vertical datum, extent against the AOI, how cells are read, NoData and how it is filled, height
range, buildings and parts, ground source, absolute heights and which pilot files can be
written, landing sites, and every problem as one `error:` / `warning:` line naming the key to
change.  What skyroute does with each kind, conservatively (a cell's value holds for every
point of the cell):

* the grid never extends past `aoi.bounds`: they are snapped inward to the lattice of multiples
  of `aoi.resolution_m` (`bounds_lonlat` take the projected box that contains them);
* a DSM or lidar tile (`data.surface`): each cell the highest pixel of its footprint.  NoData
  regions inside the raster's extent, also those touching its edge (water, glass roofs, a tile's
  border), are filled (`nodata: fill-max`: the highest height on each region's rim within the
  raster; `fill-nearest`: the nearest valid pixel; `error`: refused) with a warning giving the
  share of the AOI filled; only AOI cells outside the raster are refused, with the `aoi.bounds`
  that fit.  Without `data.terrain` the ground is derived from the DSM (a grey opening);
* a DEM (`data.terrain`: SRTM, Copernicus, any GeoTIFF) is read as the surface through its
  samples, not as flat squares: `terrain` is the highest, `terrain_min` the lowest sample of
  every lattice square (four neighbouring samples) that touches the cell, so no surface between
  the samples (bilinear, a TIN) can be higher or lower anywhere in the cell.  The samples sit at
  the pixel centres (GDAL moves a `PixelIsPoint` tie point by half a pixel; with
  `GTIFF_POINT_GEO_IGNORE=TRUE` a `Point` raster's samples sit at the corners);
* a CityJSON (`data.buildings`, LoD1/LoD2, Building and BuildingPart): roofs as faces; the ground
  is the file's TINRelief where it has one, else the lowest ground surface of each Building with
  its parts (a part standing on another part is not ground), else `TerrainHeight` attributes.

A DSM (heights in NAP; `data.ground` gives the ellipsoidal height of NAP 0 m for absolute heights):

```yaml
name: my-city-dsm
aoi: {crs: EPSG:28992, bounds: [91190, 435690, 91420, 435920], resolution_m: 1.0}
data:
  surface: {path: dsm.tif, vertical_datum: NAP}
  ground: {height_m: 43.61, vertical_datum: WGS 84 ellipsoid}
  almanacs: [yuma.txt]
mission:
  start: {x: 91200, y: 435700, alt_agl_m: 30}
  goal: {x: 91410, y: 435910, alt_agl_m: 30}
  start_time_utc: 2020-01-03T12:00:00Z
```

A raw lidar tile (an AHN GeoTIFF with NoData over water, glass roofs and at its border; a list
of tiles or a VRT works the same):

```yaml
name: my-city-lidar
aoi: {crs: EPSG:28992, bounds: [91180, 435680, 91430, 435930], resolution_m: 2.0}
data:
  surface: {path: [ahn_tile.tif], vertical_datum: NAP, nodata: fill-max}
  ground: {height_m: 43.61, vertical_datum: WGS 84 ellipsoid}
  almanacs: [yuma.txt]
mission:
  start: {x: 91195, y: 435695, alt_agl_m: 40}
  goal: {x: 91415, y: 435915, alt_agl_m: 40}
  start_time_utc: 2020-01-03T12:00:00Z
```

A CityJSON LoD2 model (Building with BuildingParts and a TINRelief, heights in NAP):

```yaml
name: my-city-cityjson
aoi: {crs: EPSG:28992, bounds: [81000, 455000, 81040, 455040], resolution_m: 1.0}
data:
  buildings: {path: city.city.json, format: cityjson}
  ground: {height_m: 43.4, vertical_datum: WGS 84 ellipsoid}
  almanacs: [yuma.txt]
mission:
  start: {x: 81002, y: 455002, alt_agl_m: 10}
  goal: {x: 81038, y: 455038, alt_agl_m: 10}
  start_time_utc: 2020-01-03T12:00:00Z
constraints: {max_altitude_agl_m: 40}
```

A DEM (SRTM-style, heights above the EGM96 geoid: absolute heights need nothing more):

```yaml
name: my-mountains-dem
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
planner: {step_cells: 4}      # a 120 m lattice on 30 m cells
```

`yuma.txt` is a GPS almanac (YUMA, SEM or RINEX navigation file, e.g. `catalogs/data/yuma_2020-01-03.txt`
for the start time above): the planner verifies the navigation error of every plan against
it, and `intent.json` sizes its volumes by it.  Without landing sites (`data.landing_sites`,
a GeoJSON, or OSM helipads and parks) `skyroute fleet --missions` derives candidate sites from
open ground (no obstacle within r_p, not no-fly, the lowest risk level present) and says so.

## Absolute heights of the shipped scenarios

Every shipped scenario writes `plan.kml`, `plan.plan` with a real home altitude and
`intent.json`.  The SRTM scenarios' heights are above the EGM96 geoid already; the city
scenarios carry a sourced `data.ground` (sources: `catalogs/data/ATTRIBUTION.md`):

| scenarios | surface datum | `data.ground` | source | what it costs |
|---|---|---|---|---|
| `helsinki-*` | flat local ground (OSM) | 3.5 m, EGM96 geoid | median of the 4 OSM `ele` points within 175 m of the start (barometric, 3.0-4.0 m) | the ground is not flat: OSM `ele` in the AOI spans 1.5-22 m, so a building on higher ground is modelled up to 18.5 m too low and AGL limits hold above the plane |
| `rotterdam-*` | NAP (CityJSON) | 43.61 m, WGS 84 ellipsoid | NLGEO2018 quasi-geoid (RDNAPTRANS2018) at the AOI centre, 43.609-43.618 m over the AOI | under 1 cm over the AOI; ETRS89 taken as WGS 84 (centimetres) |
| `monaco-helipads` | flat local ground (OSM) | 5.8 m, EGM96 geoid | Monaco heliport (LNMC) altitude 19 ft, French AIP VAC | Monaco is not flat: 0 m at the sea to 161-169 m (Chemin des Revoires, 250 m from the start) and more in France at the AOI's north. Buildings on higher ground are modelled up to ~160 m too low and the hillside is no obstacle in the model; AGL limits hold above the plane (a 60 m AGL cruise can meet the slope); absolute heights are right only where the ground is at 5.8 m (the port). A planning demonstration, not a flyable plan: give a DEM (`data.terrain`) before flying there |
"""


def reference_markdown() -> str:
    lines = [HEADER, "| key | type | unit | default |", "|---|---|---|---|"]
    notes = []
    for key, tp, unit, default, doc in scenario_keys():
        lines.append(f"| `{key}` | {tp.replace('|', '/')} | {unit} | {default.replace('|', '/')} |")
        if doc:
            notes.append(f"- `{key}`: {' '.join(doc.split())}")
    return "\n".join([*lines, "", "## Sections", "", *notes, "", OWN_CITY])


if __name__ == "__main__":  # pragma: no cover
    print(reference_markdown(), end="")
