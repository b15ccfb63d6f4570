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
  ``plannedHomePosition`` [lat, lon, AMSL altitude] on the ground under the start.  **The
  waypoints are chords of the smoothed trajectory**: the vehicle flies straight between them
  (rotorcraft: the trajectory's piece boundaries, so on a fillet arc the chord, inside the arc
  by at most its sagitta and, on a climbing turn, below it; fixed-wing: the lattice vertices,
  outside the fillet arcs).  Every such straight leg stays in the plan's admissible volume
  (rotorcraft: the chord of an arc lies in the triangle of the fillet check, at or above its
  lowest corner; fixed-wing: the planner checks every leg as an exact motion), but it is not
  the trajectory: the file's top-level ``skyroute`` object (QGroundControl ignores keys it does
  not know) says so and gives ``max_chord_deviation_m``, the largest distance between the
  waypoint chords and the trajectory (both ways, :func:`chord_deviation`), and
  ``max_chord_below_trajectory_m``.  A fixed-wing mission ends with a landing pattern instead
  of the plan's arrival loiter (:func:`qgc_plan`): MAV_CMD_DO_LAND_START (189),
  MAV_CMD_NAV_LOITER_TO_ALT (31) at the goal altitude on a circle of the plan's turn radius
  whose exit leads along the final course, MAV_CMD_NAV_LAND (21) on the ground under the
  goal, reached at the vehicle's maximum descent angle (PX4 / ArduPilot fixed-wing mission
  landing); the approach and touchdown are beyond the planned trajectory and not checked.
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

__all__ = ["KML_NS", "QGC_FRAME_GLOBAL_RELATIVE_ALT", "arrival_loiter", "building_footprints", "chord_deviation",
           "continuous_lon", "crosses_antimeridian", "lon_near", "plan_kml", "qgc_plan", "wrap_lon", "write_json",
           "write_plan_gpkg"]

KML_NS = "http://www.opengis.net/kml/2.2"
GX_NS = "http://www.google.com/kml/ext/2.2"
QGC_FRAME_GLOBAL_RELATIVE_ALT = 3
MAV_CMD_NAV_WAYPOINT, MAV_CMD_NAV_LAND, MAV_CMD_NAV_TAKEOFF = 16, 21, 22
MAV_CMD_NAV_LOITER_TO_ALT, MAV_CMD_DO_LAND_START = 31, 189
MAV_FRAME_MISSION = 2
CHORD_SPACING_M = 0.25     # densification of the polylines compared by chord_deviation [m]
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


def _item(seq: int, command: int, lat: float, lon: float, alt: float, p1: float = 0, p2: float = 0,
          frame: int = QGC_FRAME_GLOBAL_RELATIVE_ALT) -> dict:
    return {"AMSLAltAboveTerrain": None, "Altitude": round(alt, 3), "AltitudeMode": 1, "autoContinue": True,
            "command": command, "doJumpId": seq, "frame": frame,
            "params": [p1, p2, 0, None, round(lat, 9), round(lon, 9), round(alt, 3)], "type": "SimpleItem"}


def _densify(xyz: np.ndarray, spacing_m: float) -> np.ndarray:
    """Points of the polyline ``xyz`` (k, 3) at most ``spacing_m`` [m] apart (its vertices kept)."""
    p = np.asarray(xyz, float).reshape(-1, 3)
    if p.shape[0] < 2:
        return p.copy()
    seg = np.diff(p, axis=0)
    n = np.maximum(np.ceil(np.linalg.norm(seg, axis=1) / spacing_m).astype(np.int64), 1)
    idx = np.repeat(np.arange(seg.shape[0]), n)
    frac = (np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(n, n)
    return np.vstack([p[idx] + seg[idx] * frac[:, None], p[-1:]])


def chord_deviation(waypoints_xyz_m, trajectory_xyz_m, spacing_m: float = CHORD_SPACING_M) -> dict[str, float]:
    """How far the straight chords between mission waypoints (k, 3) are from the trajectory
    samples (m, 3) (map frame, one vertical datum) [m]:

    * ``max_chord_deviation_m``: the largest distance from a point of either polyline to the
      other (Hausdorff; both densified every ``spacing_m``, so at most ``spacing_m / 2``
      above the exact value, never below);
    * ``max_chord_below_trajectory_m``: the largest height of a trajectory point above the
      chord point horizontally nearest to it (0 when no chord is below the trajectory).
    """
    from scipy.spatial import cKDTree

    a = _densify(waypoints_xyz_m, spacing_m)
    b = _densify(trajectory_xyz_m, spacing_m)
    if a.shape[0] == 0 or b.shape[0] == 0:
        raise InputError("chord_deviation needs waypoints and trajectory samples")
    d_ab = cKDTree(b).query(a)[0]
    d_ba = cKDTree(a).query(b)[0]
    near = cKDTree(a[:, :2]).query(b[:, :2])[1]
    below = float(np.max(b[:, 2] - a[near, 2], initial=0.0))
    return {"max_chord_deviation_m": round(float(max(d_ab.max(), d_ba.max())), 3),
            "max_chord_below_trajectory_m": round(max(below, 0.0), 3)}


def arrival_loiter(trajectory_xyz_m, waypoints_xyz_m) -> tuple[int, float, bool] | None:
    """The fixed-wing arrival loiter at the end of a written trajectory (one full turn after
    the last waypoint, :func:`~skyroute.stages.planning.fixedwing.loiter_circle`): (index of its
    first sample, radius [m], clockwise) measured on the samples, or None without one."""
    p = np.asarray(trajectory_xyz_m, float)
    w = np.asarray(waypoints_xyz_m, float)
    if p.shape[0] < 8 or w.shape[0] < 2:
        return None
    hit = np.nonzero(np.all(np.abs(p[:-1, :2] - w[-1, :2]) < 1e-6, axis=1))[0]
    if hit.size == 0 or p.shape[0] - hit[0] < 8:
        return None
    k = int(hit[0])
    ring = p[k + 1:, :2]                 # equally spaced angles over the whole turn: their mean is the centre
    centre = ring.mean(axis=0)
    r = np.linalg.norm(ring - centre, axis=1)
    if not (r.mean() > 0 and np.ptp(r) <= 1e-3 * r.mean()):
        return None
    u = w[-1, :2] - w[-2, :2]
    v = centre - p[k, :2]
    return k, float(r.mean()), bool(u[0] * v[1] - u[1] * v[0] < 0)


def _landing_items(seq0: int, lon: float, lat: float, rel_m: float, course_deg: float, *, ground_rel_m: float,
                   loiter_radius_m: float, clockwise: bool, descent_angle_deg: float) -> tuple[list[dict], dict]:
    """A fixed-wing mission landing after the last waypoint (``lon, lat`` [deg] at ``rel_m``
    [m] above home, reached on ``course_deg`` [deg from north]): DO_LAND_START, LOITER_TO_ALT
    at ``rel_m`` on a circle of ``loiter_radius_m`` [m] (``clockwise``) tangent to the approach
    line, exit heading required, and NAV_LAND on the ground (``ground_rel_m`` [m] above home)
    under the last waypoint, the approach ``(rel_m - ground_rel_m) / tan(descent_angle_deg)``
    [m] long.  Returns the items and their description."""
    from pyproj import Geod

    if not (loiter_radius_m > 0 and 0 < descent_angle_deg < 90 and math.isfinite(ground_rel_m)):
        raise InputError("a fixed-wing landing needs a loiter radius > 0 [m], a descent angle in (0, 90) deg and a "
                         "finite ground height [m]")
    geod = Geod(ellps="WGS84")
    height = max(float(rel_m) - float(ground_rel_m), 0.0)
    approach = max(height / math.tan(math.radians(descent_angle_deg)), 2.0 * loiter_radius_m)
    t_lon, t_lat, _ = geod.fwd(lon, lat, course_deg + 180.0, approach)          # loiter exit, on the approach line
    c_lon, c_lat, _ = geod.fwd(t_lon, t_lat, course_deg + (90.0 if clockwise else -90.0), loiter_radius_m)
    c_lon = float(wrap_lon(c_lon))
    items = [_item(seq0, MAV_CMD_DO_LAND_START, lat, lon, 0.0, frame=MAV_FRAME_MISSION),
             _item(seq0 + 1, MAV_CMD_NAV_LOITER_TO_ALT, c_lat, c_lon, float(rel_m), p1=1,
                   p2=round(loiter_radius_m if clockwise else -loiter_radius_m, 3)),
             _item(seq0 + 2, MAV_CMD_NAV_LAND, lat, lon, float(ground_rel_m))]
    desc = {"pattern": "DO_LAND_START (189), NAV_LOITER_TO_ALT (31), NAV_LAND (21)",
            "loiter_radius_m": round(float(loiter_radius_m), 3), "loiter_clockwise": bool(clockwise),
            "approach_length_m": round(approach, 3), "descent_angle_deg": float(descent_angle_deg),
            "touchdown": "on the ground under the goal",
            "note": "the landing approach and the touchdown are beyond the planned trajectory: skyroute did not "
                    "check them (terrain, obstacles, airspace); check them before the flight"}
    return items, desc


def qgc_plan(lon_deg, lat_deg, rel_alt_m, home_amsl_m: float, *, cruise_speed_mps: float,
             hover_speed_mps: float = 5.0, fixed_wing: bool = False, landing: dict | None = None,
             metadata: dict | None = None) -> dict:
    """QGroundControl Plan document (see the module docstring): waypoints ``lon_deg, lat_deg``
    [deg] at ``rel_alt_m`` [m] above home (home = the ground under the first waypoint, at
    ``home_amsl_m`` [m] above mean sea level); take-off at the first, landing at the last.

    ``fixed_wing``: vehicle type fixed wing, and the mission ends with a landing pattern
    (:func:`_landing_items`, module docstring) described by ``landing``: ``ground_rel_m`` [m]
    (the ground under the last waypoint above home), ``loiter_radius_m`` [m], ``clockwise``
    and ``descent_angle_deg`` [deg] (a fixed-wing aircraft cannot land on a waypoint: without
    ``landing`` it is refused).  ``metadata``: what the file's top-level ``skyroute`` object
    holds besides its note (e.g. :func:`chord_deviation`)."""
    lon, lat, rel = _check(lon_deg, lat_deg, rel_alt_m)
    lon = wrap_lon(lon)      # MAVLink waypoint longitudes are in [-180, 180]
    if not (math.isfinite(home_amsl_m) and cruise_speed_mps > 0 and hover_speed_mps > 0):
        raise InputError("home_amsl_m must be finite, the speeds > 0 [m/s]")
    if fixed_wing and landing is None:
        raise InputError("a fixed-wing QGroundControl mission needs its landing pattern (landing=: ground_rel_m, "
                         "loiter_radius_m, clockwise, descent_angle_deg)")
    items = [_item(1, MAV_CMD_NAV_TAKEOFF, lat[0], lon[0], float(rel[0]))]
    for i in range(lon.size):
        items.append(_item(len(items) + 1, MAV_CMD_NAV_WAYPOINT, lat[i], lon[i], float(rel[i])))
    meta = {"note": "The mission waypoints are chords of skyroute's smoothed trajectory (plan.geojson, "
                    "waypoints.csv): the vehicle flies straight between them, up to max_chord_deviation_m from the "
                    "trajectory. Every straight leg stays in the plan's admissible volume; the take-off climb"
                    + (" and the landing pattern are" if fixed_wing else " and the final descent to land are")
                    + " not part of the planned trajectory.",
            **(metadata or {})}
    if fixed_wing:
        from pyproj import Geod

        course = float(Geod(ellps="WGS84").inv(lon[-2], lat[-2], lon[-1], lat[-1])[0])
        more, meta["landing"] = _landing_items(len(items) + 1, float(lon[-1]), float(lat[-1]), float(rel[-1]), course,
                                               **landing)
        items.extend(more)
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
                                                round(float(home_amsl_m), 3)]},
            "skyroute": meta}


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
