"""Plan files a pilot can load: Google Earth KML, a QGroundControl mission, a GeoPackage.

* ``plan.kml`` (OGC KML 2.2): the trajectory as a ``LineString`` and a ``gx:Track`` (one
  timestamp per sample, for Google Earth's time slider), start and goal points, all with
  ``altitudeMode absolute``: heights above mean sea level, i.e. the EGM96 geoid (KML 2.2
  section 16.1 ``absolute``: "relative to sea level"); the document description says so.
* ``plan.plan`` (QGroundControl Plan file, JSON; format of docs.qgroundcontrol.com "Plan File
  Format"): ``mission.items`` are MAVLink ``SimpleItem`` s with ``frame`` 3
  (MAV_FRAME_GLOBAL_RELATIVE_ALT: altitude relative to the home position) and
  ``AltitudeMode`` 1 (relative): MAV_CMD_NAV_TAKEOFF (22) at the start to the first waypoint's
  height, MAV_CMD_NAV_WAYPOINT (16) at every piece boundary of the trajectory, MAV_CMD_NAV_LAND
  (21) at the goal.  ``params`` = [p1..p4, latitude, longitude, altitude]; home =
  ``plannedHomePosition`` [lat, lon, AMSL altitude] on the ground under the start.  The
  vehicle flies straight between waypoints: on a fillet arc of the plan that is the chord,
  inside the arc by at most its sagitta (the arc's own volume is the intent's business).
* ``plan.gpkg`` (OGC GeoPackage via pyogrio, EPSG:4326): layer ``plan`` (the trajectory,
  LineString Z, z in the surface datum as in plan.geojson, stated in a field), ``waypoints``
  (piece boundaries, Point Z, relative and absolute heights), ``intents`` (the F3548 volumes:
  polygons with altitude bands [m, WGS 84 ellipsoid] and RFC 3339 times), ``map_buildings``
  (the surface model's building footprints with their top heights) and ``aoi`` (the map
  extent).

**The antimeridian.**  A plan near longitude 180 (e.g. UTM zone 60 or 1) has map points on both
sides of it.  The planar exports keep every geometry continuous: the trajectory's longitudes are
unwrapped along the path (:func:`continuous_lon`) and every other geometry of the plan
(waypoints, intent volumes, buildings, the map extent) is given the longitudes nearest to the
plan's first point (:func:`lon_near`), so a longitude may exceed 180 (or go below -180) and no
polygon spans the globe.  This is what ``plan.geojson`` and ``plan.gpkg`` do (RFC 7946 section
3.1.9 would cut such a line into a MultiLineString; skyroute keeps feature 0 one LineString whose
vertices match its per-vertex properties and says so in its properties).  Formats whose
longitudes are defined on [-180, 180] get them wrapped (:func:`wrap_lon`): KML 2.2
(``kml:longitude``), the QGroundControl plan (MAVLink waypoints) and the F3548 intent (the
``LatLngPoint`` of :mod:`skyroute.stages.intents`, whose polygon edges are the shortest paths).
"""

from __future__ import annotations

import json
import math
import os
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from skyroute.stages.base import InputError

__all__ = ["KML_NS", "QGC_FRAME_GLOBAL_RELATIVE_ALT", "building_footprints", "continuous_lon",
           "crosses_antimeridian", "lon_near", "plan_kml", "qgc_plan", "wrap_lon", "write_json", "write_plan_gpkg"]

KML_NS = "http://www.opengis.net/kml/2.2"
GX_NS = "http://www.google.com/kml/ext/2.2"
QGC_FRAME_GLOBAL_RELATIVE_ALT = 3
MAV_CMD_NAV_WAYPOINT, MAV_CMD_NAV_LAND, MAV_CMD_NAV_TAKEOFF = 16, 21, 22
MAV_CMD_NAV_LOITER_UNLIM = 17
MAV_AUTOPILOT_PX4, MAV_TYPE_QUADROTOR, MAV_TYPE_FIXED_WING = 12, 2, 1


def wrap_lon(lon_deg) -> np.ndarray:
    """Longitudes [deg] wrapped to [-180, 180] (a value already in the range is kept as it is,
    so 180 stays 180)."""
    lon = np.asarray(lon_deg, float)
    return np.where((lon >= -180.0) & (lon <= 180.0), lon, (lon + 180.0) % 360.0 - 180.0)


def lon_near(lon_deg, ref_deg: float) -> np.ndarray:
    """Longitudes [deg] shifted by whole turns to lie within 180 deg of ``ref_deg`` (the
    continuous representation around a reference point; may exceed 180 or go below -180)."""
    lon = np.asarray(lon_deg, float)
    return ref_deg + (lon - ref_deg + 180.0) % 360.0 - 180.0


def continuous_lon(lon_deg) -> np.ndarray:
    """Longitudes [deg] of a path, unwrapped: the first in [-180, 180], each next one within
    180 deg of the previous (no jump of ~360 deg where the path crosses the antimeridian)."""
    lon = np.asarray(lon_deg, float)
    if lon.size == 0:
        return lon.copy()
    first = float(wrap_lon(lon.reshape(-1)[0]))
    return np.unwrap(lon - lon.reshape(-1)[0] + first, period=360.0)


def crosses_antimeridian(lon_deg) -> bool:
    """Whether continuous longitudes [deg] (:func:`continuous_lon`, :func:`lon_near`) reach
    past 180 or -180."""
    lon = np.asarray(lon_deg, float)
    return bool(lon.size and (np.max(lon) > 180.0 or np.min(lon) < -180.0))


def _check(lon, lat, *more) -> tuple[np.ndarray, ...]:
    arrs = [np.asarray(a, float) for a in (lon, lat, *more)]
    n = arrs[0].shape
    if any(a.shape != n for a in arrs) or arrs[0].ndim != 1 or arrs[0].size < 2:
        raise InputError("lon, lat and heights must be 1-D arrays of the same length (>= 2 points)")
    if not all(np.all(np.isfinite(a)) for a in arrs):
        raise InputError("coordinates and heights must be finite")
    return tuple(arrs)


def plan_kml(lon_deg, lat_deg, h_amsl_m, times_utc: list[str], name: str, description: str = "") -> str:
    """KML 2.2 document (text) of a trajectory: ``lon_deg, lat_deg`` [deg] WGS 84,
    ``h_amsl_m`` [m] above mean sea level (EGM96), ``times_utc`` ISO 8601 Z per point."""
    lon, lat, h = _check(lon_deg, lat_deg, h_amsl_m)
    lon = wrap_lon(lon)      # kml:longitude is in [-180, 180]; Google Earth joins points by the short way
    if len(times_utc) != lon.size:
        raise InputError("times_utc needs one time per point")
    ET.register_namespace("", KML_NS)
    ET.register_namespace("gx", GX_NS)
    k = f"{{{KML_NS}}}"
    root = ET.Element(f"{k}kml")
    doc = ET.SubElement(root, f"{k}Document")
    ET.SubElement(doc, f"{k}name").text = name
    note = ("Altitudes are absolute (altitudeMode absolute): metres above mean sea level, EGM96 geoid. "
            + description).strip()
    ET.SubElement(doc, f"{k}description").text = note
    style = ET.SubElement(doc, f"{k}Style", id="track")
    ls = ET.SubElement(style, f"{k}LineStyle")
    ET.SubElement(ls, f"{k}color").text = "ff0000ff"
    ET.SubElement(ls, f"{k}width").text = "3"

    def coord(i: int) -> str:
        return f"{lon[i]:.9f},{lat[i]:.9f},{h[i]:.3f}"

    pm = ET.SubElement(doc, f"{k}Placemark")
    ET.SubElement(pm, f"{k}name").text = f"{name}: trajectory"
    ET.SubElement(pm, f"{k}styleUrl").text = "#track"
    line = ET.SubElement(pm, f"{k}LineString")
    ET.SubElement(line, f"{k}altitudeMode").text = "absolute"
    ET.SubElement(line, f"{k}coordinates").text = " ".join(coord(i) for i in range(lon.size))
    pm = ET.SubElement(doc, f"{k}Placemark")
    ET.SubElement(pm, f"{k}name").text = f"{name}: timed track"
    track = ET.SubElement(pm, f"{{{GX_NS}}}Track")
    ET.SubElement(track, f"{k}altitudeMode").text = "absolute"
    for t in times_utc:
        ET.SubElement(track, f"{k}when").text = t
    for i in range(lon.size):
        ET.SubElement(track, f"{{{GX_NS}}}coord").text = f"{lon[i]:.9f} {lat[i]:.9f} {h[i]:.3f}"
    for label, i in (("start", 0), ("goal", lon.size - 1)):
        pm = ET.SubElement(doc, f"{k}Placemark")
        ET.SubElement(pm, f"{k}name").text = label
        pt = ET.SubElement(pm, f"{k}Point")
        ET.SubElement(pt, f"{k}altitudeMode").text = "absolute"
        ET.SubElement(pt, f"{k}coordinates").text = coord(i)
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def _item(seq: int, command: int, lat: float, lon: float, alt: float) -> dict:
    return {"AMSLAltAboveTerrain": None, "Altitude": round(alt, 3), "AltitudeMode": 1, "autoContinue": True,
            "command": command, "doJumpId": seq, "frame": QGC_FRAME_GLOBAL_RELATIVE_ALT,
            "params": [0, 0, 0, None, round(lat, 9), round(lon, 9), round(alt, 3)], "type": "SimpleItem"}


def qgc_plan(lon_deg, lat_deg, rel_alt_m, home_amsl_m: float, *, cruise_speed_mps: float,
             hover_speed_mps: float = 5.0, fixed_wing: bool = False) -> dict:
    """QGroundControl Plan document (see the module docstring): waypoints ``lon_deg, lat_deg``
    [deg] at ``rel_alt_m`` [m] above home (home = the ground under the first waypoint, at
    ``home_amsl_m`` [m] above mean sea level); take-off at the first, landing at the last
    (``fixed_wing``: vehicle type fixed wing, and an unlimited loiter at the last waypoint
    instead of the landing: a fixed-wing aircraft cannot land on a waypoint)."""
    lon, lat, rel = _check(lon_deg, lat_deg, rel_alt_m)
    lon = wrap_lon(lon)      # MAVLink waypoint longitudes are in [-180, 180]
    if not (math.isfinite(home_amsl_m) and cruise_speed_mps > 0 and hover_speed_mps > 0):
        raise InputError("home_amsl_m must be finite, the speeds > 0 [m/s]")
    items = [_item(1, MAV_CMD_NAV_TAKEOFF, lat[0], lon[0], float(rel[0]))]
    for i in range(lon.size):
        items.append(_item(len(items) + 1, MAV_CMD_NAV_WAYPOINT, lat[i], lon[i], float(rel[i])))
    if fixed_wing:
        items.append(_item(len(items) + 1, MAV_CMD_NAV_LOITER_UNLIM, lat[-1], lon[-1], float(rel[-1])))
    else:
        items.append(_item(len(items) + 1, MAV_CMD_NAV_LAND, lat[-1], lon[-1], 0.0))
    return {"fileType": "Plan", "groundStation": "QGroundControl", "version": 1,
            "geoFence": {"circles": [], "polygons": [], "version": 2},
            "rallyPoints": {"points": [], "version": 2},
            "mission": {"cruiseSpeed": float(cruise_speed_mps), "hoverSpeed": float(hover_speed_mps),
                        "firmwareType": MAV_AUTOPILOT_PX4,
                        "vehicleType": MAV_TYPE_FIXED_WING if fixed_wing else MAV_TYPE_QUADROTOR,
                        "globalPlanAltitudeMode": 1, "version": 2, "items": items,
                        "plannedHomePosition": [round(float(lat[0]), 9), round(float(lon[0]), 9),
                                                round(float(home_amsl_m), 3)]}}


def write_json(path: Path | str, doc: dict) -> Path:
    """Write ``doc`` as JSON (no NaN) atomically."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(doc, indent=1, allow_nan=False))
    os.replace(tmp, path)
    return path


def building_footprints(building_id, surface_m, transform, crs) -> tuple[list, np.ndarray, np.ndarray]:
    """Footprints of the surface model's buildings as WGS 84 polygons (lon, lat [deg]): one per
    ``building_id`` >= 0 (the cells it covers, merged; ``transform``: the grid's affine),
    with its id and top height [m] (highest ``surface_m`` cell, the surface datum)."""
    import shapely
    from pyproj import Transformer
    from rasterio.features import shapes

    bid = np.asarray(building_id, np.int32)
    surf = np.asarray(surface_m, float)
    if bid.shape != surf.shape:
        raise InputError("building_id and surface_m must have the same shape")
    tr = Transformer.from_crs(crs, 4326, always_xy=True)
    parts: dict[int, list] = {}
    for geom, val in shapes(bid, mask=bid >= 0, transform=transform, connectivity=4):
        parts.setdefault(int(val), []).append(shapely.geometry.shape(geom))
    ids = np.array(sorted(parts), dtype=np.int32)
    tops = np.full(ids.size, np.nan)
    if ids.size:
        order = np.argsort(bid.ravel(), kind="stable")
        sb = bid.ravel()[order]
        lo, hi = np.searchsorted(sb, ids, "left"), np.searchsorted(sb, ids, "right")
        sv = surf.ravel()[order]
        tops = np.array([float(np.max(sv[a:b])) for a, b in zip(lo, hi, strict=True)])
    polys = [shapely.transform(shapely.union_all(parts[int(i)]), lambda xy: np.column_stack(tr.transform(xy[:, 0], xy[:, 1])))
             for i in ids]
    return polys, ids, tops


def write_plan_gpkg(path: Path | str, *, lon_deg, lat_deg, z_m, vertical_datum: str, times_utc: list[str],
                    label: str, waypoints_lonlat_z: np.ndarray, waypoints_rel_m, waypoints_abs_m=None,
                    intent: dict | None = None, aoi_lonlat: tuple[float, float, float, float] | None = None,
                    buildings: tuple[list, np.ndarray, np.ndarray] | None = None) -> Path:
    """GeoPackage of a plan (see the module docstring).  ``z_m`` [m]: trajectory heights in
    ``vertical_datum``; ``waypoints_lonlat_z`` (n, 3) piece boundaries [deg, deg, m in the
    surface datum], ``waypoints_rel_m`` [m] above home, ``waypoints_abs_m`` [m] above mean sea
    level (or None); ``intent``: an F3548 OperationalIntentDetails dict; ``aoi_lonlat``
    (west, south, east, north) [deg] (``east < west``: across the antimeridian); ``buildings``:
    :func:`building_footprints` output (layer ``map_buildings``, tops in ``vertical_datum``).
    Longitudes of the planar layers are continuous around the trajectory's first point (see
    the module docstring: the antimeridian)."""
    import shapely
    from pyogrio.raw import write

    lon, lat, z = _check(lon_deg, lat_deg, z_m)
    lon = continuous_lon(lon)     # planar EPSG:4326 layers: one continuous frame around the plan's start
    ref = float(lon[0])
    path = Path(path)
    if path.exists():
        path.unlink()
    line = shapely.LineString(np.column_stack([lon, lat, z]))
    common = dict(driver="GPKG", crs="EPSG:4326")
    write(path, np.array([shapely.to_wkb(line)], dtype=object),
          [np.array([label], dtype=object), np.array([vertical_datum], dtype=object),
           np.array([times_utc[0]], dtype=object), np.array([times_utc[-1]], dtype=object),
           np.array([lon.size], dtype=np.int32)],
          ["label", "vertical_datum", "time_start_utc", "time_end_utc", "n_points"],
          layer="plan", geometry_type="LineString Z", **common)
    w = np.array(waypoints_lonlat_z, float).reshape(-1, 3)
    w[:, 0] = lon_near(w[:, 0], ref)
    rel = np.asarray(waypoints_rel_m, float)
    ab = np.full(w.shape[0], np.nan) if waypoints_abs_m is None else np.asarray(waypoints_abs_m, float)
    pts = shapely.points(w)
    write(path, np.asarray(shapely.to_wkb(pts), dtype=object),
          [np.arange(w.shape[0], dtype=np.int32), rel, ab],
          ["index", "alt_rel_home_m", "alt_amsl_m"], layer="waypoints", geometry_type="Point Z", append=True, **common)
    if intent is not None:
        vols = intent["volumes"]
        polys = [shapely.Polygon([(float(lon_near(p["lng"], ref)), p["lat"])
                                  for p in v["volume"]["outline_polygon"]["vertices"]]) for v in vols]
        write(path, np.asarray(shapely.to_wkb(polys), dtype=object),
              [np.arange(len(vols), dtype=np.int32),
               np.array([v["volume"]["altitude_lower"]["value"] for v in vols], float),
               np.array([v["volume"]["altitude_upper"]["value"] for v in vols], float),
               np.array([v["time_start"]["value"] for v in vols], dtype=object),
               np.array([v["time_end"]["value"] for v in vols], dtype=object)],
              ["volume", "alt_lower_w84_m", "alt_upper_w84_m", "time_start", "time_end"],
              layer="intents", geometry_type="Polygon", append=True, **common)
    if buildings is not None and len(buildings[0]):
        polys, ids, tops = buildings
        polys = [shapely.transform(g, lambda xy: np.column_stack([lon_near(xy[:, 0], ref), xy[:, 1]]))
                 for g in polys]
        write(path, np.asarray(shapely.to_wkb(polys), dtype=object),
              [np.asarray(ids, np.int32), np.asarray(tops, float), np.array([vertical_datum] * len(ids), dtype=object)],
              ["building_id", "top_m", "vertical_datum"], layer="map_buildings", geometry_type="MultiPolygon",
              promote_to_multi=True, append=True, **common)
    if aoi_lonlat is not None:
        w_, s_, e_, n_ = (float(v) for v in aoi_lonlat)
        w_ = float(lon_near(w_, ref))
        e_ = w_ + (e_ - float(aoi_lonlat[0])) % 360.0   # east of west: a box across the antimeridian stays small
        write(path, np.array([shapely.to_wkb(shapely.box(w_, s_, e_, n_))], dtype=object),
              [np.array(["map extent"], dtype=object)], ["name"], layer="aoi", geometry_type="Polygon",
              append=True, **common)
    return path
