"""ASTM F3548-21 operational intents of a plan: 4-D volumes that wholly contain the trajectory.

A plan's exact trajectory (:class:`~skyroute.stages.smoothing.CornerTrajectory`: straight
lines and circular fillet arcs) is cut into chunks: at every piece boundary (a line meets an
arc or a stop) and, within a piece, into equal parts of at most ``max_volume_s`` [s] (on an
arc also short enough that its sagitta is at most half the buffer; on a climb or descent
also of at most ``max_dz_m`` [m] of height).  Each
chunk becomes one ``Volume4D``:

* **outline**: the convex hull of the chunk's densely sampled path (spacing <= ``spacing_m``),
  simplified by ``simplify_m`` (Douglas-Peucker keeps every hull vertex within that distance of
  the simplified convex polygon, so the hull is inside it grown by ``simplify_m``), buffered by
  ``r = k sigma_p + vehicle_radius_m + chord_m + margin_m + simplify_m``, where ``sigma_p`` is
  the largest predicted 3-D navigation error [m] of the plan samples bracketing the chunk,
  ``chord_m = d^2 / (8 R_min)`` bounds how far an arc of radius ``R_min`` leaves the chord
  between two samples ``d`` apart (0 for lines), and ``margin_m`` covers the vertex
  rounding and the map-to-WGS 84 edge bending (edges are split to <= 100 m).  The buffer is
  a polygon circumscribing each circle (vertex radius ``r / cos(pi / (4 quad_segs))``), so
  the disk of radius r around every point of the path is inside; on a line piece the hull of
  the buffer is the buffer itself (a stadium), on an arc the hull adds the arc's inside.
* **altitudes**: WGS 84 ellipsoidal [m] (``reference: W84``) of the chunk's samples (the
  caller's ``HeightReference``) +- ``k sigma_p + vehicle_radius_m + chord_m``, rounded
  outwards to 1 cm.  sigma_p is the 3-D error, so the vertical buffer is on the safe side.
* **times**: the chunk's start and end, +- ``time_buffer_s``, rounded outwards to 1 ms,
  RFC 3339 with ``Z``.

F3548 limits are checked: at most :data:`MAX_VERTICES` (10,000) outline vertices per intent
(chunks are merged pairwise until the intent fits), end after start, polygons without a
repeated closing vertex.  Near the antimeridian: vertex longitudes are in [-180, 180] (the
F3548 ``LatLngPoint``), a polygon's edges are the shortest paths between its vertices (F3548
``Polygon``), so a volume whose vertices lie on both sides of longitude 180 is the small
polygon across it; :func:`parse_intent` refuses a polygon spanning 180 deg of longitude or
more, and :func:`intent_polygons_lonlat` / :func:`intent_conformance` unwrap the vertices
(:func:`~skyroute.stages.exports.lon_near`) before any planar geometry.
:func:`intent_conformance` measures the share of a densely sampled trajectory inside the
volumes (position, altitude and time at once).
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd

from skyroute.stages.base import InputError
from skyroute.stages.exports import continuous_lon, lon_near, wrap_lon

__all__ = ["MAX_VERTICES", "IntentVolume", "intent_conformance", "intent_details", "intent_polygons_lonlat",
           "parse_intent", "plan_intent", "plan_volumes", "rfc3339"]

MAX_VERTICES = 10_000          # ASTM F3548-21 OiMaxVertices (uas_standards.astm.f3548.v21.constants)
_QUAD_SEGS = 4
_EDGE_MAX_M = 100.0


@dataclass(frozen=True)
class IntentVolume:
    """One 4-D volume in the map CRS: ``outline_xy_m`` (n, 2) polygon vertices [m] (not closed),
    ``alt_lower_m`` / ``alt_upper_m`` WGS 84 ellipsoidal [m], ``t_start_s`` / ``t_end_s``
    mission times [s] (buffers included), ``buffer_m`` the horizontal buffer used [m]."""

    outline_xy_m: np.ndarray
    alt_lower_m: float
    alt_upper_m: float
    t_start_s: float
    t_end_s: float
    buffer_m: float


def _chunks(trajectory, max_volume_s: float, r_m: float, max_dz_m: float) -> list[tuple[float, float]]:
    """Chunk times: the pieces, each cut into parts of at most ``max_volume_s``; on an arc of
    radius R flown at v also of at most ``sqrt(4 R r_m) / v`` (the arc's sagitta over a part,
    which the convex hull adds, stays below r_m / 2); a piece climbing or descending |dz| is
    cut into at least ``|dz| / max_dz_m`` parts (thin altitude bands)."""
    piece_t_s = np.asarray(trajectory.piece_t_s, float)
    out = []
    for a, b in zip(piece_t_s[:-1], piece_t_s[1:], strict=True):
        if b - a <= 1e-9:
            continue
        i = int(np.clip(np.searchsorted(trajectory.phase_t0_s, 0.5 * (a + b), side="right") - 1, 0,
                        len(trajectory.phase_t0_s) - 1))
        dur = max_volume_s
        if int(trajectory.kind[i]) != 0 and float(trajectory.v0[i]) > 0:
            dur = min(dur, math.sqrt(4.0 * float(trajectory.radius_m[i]) * max(r_m, 0.01)) / float(trajectory.v0[i]))
        dz = float(np.ptp(trajectory.sample([a, b])[:, 2]))
        n = max(1, int(math.ceil((b - a) / dur - 1e-9)), int(math.ceil(dz / max_dz_m - 1e-9)))
        edges = np.linspace(a, b, n + 1)
        out.extend(zip(edges[:-1].tolist(), edges[1:].tolist(), strict=True))
    return out


def _sigma_bracket(t_s: np.ndarray, sigma: np.ndarray, ta: float, tb: float) -> float:
    """Largest sigma of the samples in [ta, tb] and the one just outside each end."""
    i0 = max(int(np.searchsorted(t_s, ta, side="right")) - 1, 0)
    i1 = min(int(np.searchsorted(t_s, tb, side="left")), t_s.size - 1)
    return float(np.max(sigma[i0:i1 + 1]))


def plan_volumes(trajectory, t0_s: float, t_s, sigma_p_m, height_w84: Callable[[np.ndarray], np.ndarray], *,
                 vehicle_radius_m: float, k_sigma: float = 3.0, time_buffer_s: float = 5.0,
                 max_volume_s: float = 30.0, spacing_m: float = 1.0, margin_m: float = 0.05,
                 simplify_m: float = 0.1, max_dz_m: float = 10.0, max_vertices: int = MAX_VERTICES) -> list[IntentVolume]:
    """The 4-D volumes of a plan (see the module docstring).

    ``trajectory``: the plan's CornerTrajectory (map CRS [m], z in the surface datum) whose time
    0 is mission time ``t0_s`` [s]; ``t_s`` [s] / ``sigma_p_m`` [m]: the plan samples' mission
    times and predicted 3-D navigation error (finite); ``height_w84(p)``: (n, 3) map points ->
    WGS 84 ellipsoidal heights [m]; ``vehicle_radius_m`` [m]: half the vehicle's size;
    ``k_sigma``: sigma multiplier; ``time_buffer_s`` [s] before and after each chunk;
    ``max_volume_s`` [s]: longest chunk; ``spacing_m`` [m]: path sampling; ``simplify_m`` [m]:
    the hull of the samples is simplified by this much and the buffer grown by as much;
    ``max_dz_m`` [m]: largest climb or descent within one volume."""
    import shapely

    t_s = np.asarray(t_s, float)
    sigma = np.asarray(sigma_p_m, float)
    if t_s.ndim != 1 or t_s.shape != sigma.shape or t_s.size < 1:
        raise InputError("t_s and sigma_p_m must be 1-D arrays of the same length (the plan samples)")
    if not np.all(np.isfinite(sigma)):
        raise InputError("the plan has no navigation error sigma_p (NaN: no GNSS data); operational intent volumes "
                         "need it for the horizontal buffer")
    for name, v in (("vehicle_radius_m", vehicle_radius_m), ("k_sigma", k_sigma), ("time_buffer_s", time_buffer_s),
                    ("margin_m", margin_m), ("simplify_m", simplify_m)):
        if not (math.isfinite(v) and v >= 0):
            raise InputError(f"{name} must be a finite number >= 0, got {v}")
    if margin_m < 0.01:
        raise InputError(f"margin_m {margin_m} must be >= 0.01 m (F3548's 1 cm intersection precision)")
    if not (max_volume_s > 0 and spacing_m > 0 and max_dz_m > 0):
        raise InputError("max_volume_s, spacing_m and max_dz_m must be > 0")
    T = float(trajectory.duration_s)
    if not T > 0:
        raise InputError("the trajectory has no duration")
    arcs = np.asarray(trajectory.kind) != 0
    r_min = float(np.min(np.asarray(trajectory.radius_m)[arcs])) if arcs.any() else math.inf
    tc = np.linspace(0.0, T, max(int(T / 0.05), 2) + 1)
    v_max = float(np.max(np.linalg.norm(trajectory.velocity(tc), axis=1))) * 1.05 + 1e-3
    chunks = _chunks(trajectory, max_volume_s, k_sigma * float(np.min(sigma)) + vehicle_radius_m + margin_m, max_dz_m)
    pts_per_chunk = []
    for ta, tb in chunks:
        n = max(2, int(math.ceil((tb - ta) * v_max / spacing_m)) + 1)
        tt = np.linspace(ta, tb, n)
        pts_per_chunk.append((tt, trajectory.sample(tt)))
    groups = [[i] for i in range(len(chunks))]
    while True:
        vols = [_volume([pts_per_chunk[i] for i in g], t0_s, t_s, sigma, height_w84, r_min, vehicle_radius_m,
                        k_sigma, time_buffer_s, margin_m, simplify_m, shapely) for g in groups]
        nv = sum(v.outline_xy_m.shape[0] for v in vols)
        if nv <= max_vertices or len(groups) == 1:
            break
        groups = [sum(groups[i:i + 2], []) for i in range(0, len(groups), 2)]
    if nv > max_vertices:
        raise InputError(f"the intent needs {nv} vertices > the F3548 limit {max_vertices}")
    return vols


def _volume(parts, t0_s, t_s, sigma, height_w84, r_min, vehicle_radius_m, k_sigma, time_buffer_s, margin_m,
            simplify_m, shapely) -> IntentVolume:
    tt = np.concatenate([p[0] for p in parts])
    pp = np.concatenate([p[1] for p in parts])
    ta, tb = float(tt[0]), float(tt[-1])
    d = np.linalg.norm(np.diff(pp, axis=0), axis=1)
    chord = float(np.max(d) ** 2 / (8.0 * r_min)) if math.isfinite(r_min) and d.size else 0.0
    sig = _sigma_bracket(t_s, sigma, t0_s + ta, t0_s + tb)
    r_v = k_sigma * sig + vehicle_radius_m + chord
    r_h = r_v + margin_m
    core = shapely.MultiPoint(pp[:, :2]).convex_hull
    if isinstance(core, shapely.Polygon):
        core = core.simplify(simplify_m)   # every hull vertex within simplify_m of the simplified hull
    r_h += simplify_m
    poly = core.buffer(r_h / math.cos(math.pi / (4 * _QUAD_SEGS)), quad_segs=_QUAD_SEGS).convex_hull
    poly = shapely.segmentize(poly, _EDGE_MAX_M)
    ring = np.asarray(poly.exterior.coords)[:-1]
    h = np.asarray(height_w84(pp), float)
    return IntentVolume(ring, math.floor((float(h.min()) - r_v) * 100.0) / 100.0,
                        math.ceil((float(h.max()) + r_v) * 100.0) / 100.0,
                        t0_s + ta - time_buffer_s, t0_s + tb + time_buffer_s, r_h)


def _utc0(start_time_utc) -> pd.Timestamp:
    s = pd.Timestamp(start_time_utc)
    return s.tz_localize("UTC") if s.tzinfo is None else s.tz_convert("UTC")


def rfc3339(start_time_utc, t_s: float, rounding: str = "floor") -> str:
    """RFC 3339 UTC text (``...Z``, millisecond precision) of mission time ``t_s`` [s];
    ``rounding``: ``floor`` or ``ceil`` to the millisecond (volumes round outwards)."""
    x = _utc0(start_time_utc) + pd.Timedelta(seconds=float(t_s))
    x = x.floor("ms") if rounding == "floor" else x.ceil("ms")
    p = x.to_pydatetime().astimezone(dt.UTC)
    return p.strftime("%Y-%m-%dT%H:%M:%S.") + f"{p.microsecond // 1000:03d}Z"


def intent_details(volumes: list[IntentVolume], crs, start_time_utc, priority: int = 0) -> dict:
    """The ``OperationalIntentDetails`` document (a JSON-ready dict of the
    ``uas_standards.astm.f3548.v21.api`` schema) of ``volumes`` in map ``crs``, mission time 0
    at ``start_time_utc``; vertices as WGS 84 lat/lng [deg]."""
    from pyproj import Transformer

    if not volumes:
        raise InputError("an operational intent needs at least one volume")
    tr = Transformer.from_crs(crs, 4326, always_xy=True)
    out = []
    for v in volumes:
        if not v.t_end_s > v.t_start_s or not v.alt_upper_m > v.alt_lower_m:
            raise InputError("a volume must end after it starts and have its upper altitude above the lower one")
        lon, lat = tr.transform(v.outline_xy_m[:, 0], v.outline_xy_m[:, 1])
        lon = wrap_lon(lon)           # LatLngPoint.lng in [-180, 180]; edges are the shortest paths
        out.append({
            "volume": {
                "outline_polygon": {"vertices": [{"lng": float(a), "lat": float(b)} for a, b in zip(lon, lat, strict=True)]},
                "altitude_lower": {"value": float(v.alt_lower_m), "reference": "W84", "units": "M"},
                "altitude_upper": {"value": float(v.alt_upper_m), "reference": "W84", "units": "M"},
            },
            "time_start": {"value": rfc3339(start_time_utc, v.t_start_s, "floor"), "format": "RFC3339"},
            "time_end": {"value": rfc3339(start_time_utc, v.t_end_s, "ceil"), "format": "RFC3339"},
        })
    return {"volumes": out, "off_nominal_volumes": [], "priority": int(priority)}


def parse_intent(doc: dict):
    """``doc`` parsed into ``uas_standards.astm.f3548.v21.api.OperationalIntentDetails`` (an
    ImplicitDict; InputError with the reason when it does not fit the schema or F3548's
    limits: vertices, Z times, end after start)."""
    from implicitdict import ImplicitDict
    from uas_standards.astm.f3548.v21.api import OperationalIntentDetails

    try:
        oi = ImplicitDict.parse(doc, OperationalIntentDetails)
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"not an F3548 OperationalIntentDetails: {exc}") from None
    nv = 0
    for i, v in enumerate(oi.volumes):
        verts = v.volume.outline_polygon.vertices
        nv += len(verts)
        if len(verts) < 3 or len({(p.lat, p.lng) for p in verts}) != len(verts):
            raise InputError(f"volume {i}: a polygon needs >= 3 vertices, none repeated (nor the closing one)")
        lng = np.array([float(p.lng) for p in verts])
        lat = np.array([float(p.lat) for p in verts])
        if not (np.all(np.isfinite(lng)) and np.all(np.abs(lng) <= 180.0) and np.all(np.isfinite(lat))
                and np.all(np.abs(lat) <= 90.0)):
            raise InputError(f"volume {i}: vertex longitudes must be in [-180, 180] and latitudes in "
                             "[-90, 90] [deg]")
        ring = continuous_lon(np.r_[lng, lng[0]])     # each edge the short way (F3548 Polygon)
        if abs(float(ring[-1] - ring[0])) > 1e-6:
            raise InputError(f"volume {i}: the polygon's edges (the shortest paths between its vertices) go once "
                             "around the globe: it is not a small area")
        if float(np.ptp(ring)) >= 180.0:
            raise InputError(f"volume {i}: the polygon spans {float(np.ptp(ring)):.1f} deg of longitude (>= 180): "
                             "not a small area")
        for which in ("time_start", "time_end"):
            if not str(v[which].value).endswith("Z"):
                raise InputError(f"volume {i}: {which} {v[which].value} is not RFC 3339 UTC ending in Z")
        if not v.time_end.value.datetime > v.time_start.value.datetime:
            raise InputError(f"volume {i}: time_end is not after time_start")
    if nv > MAX_VERTICES:
        raise InputError(f"{nv} vertices > the F3548 limit {MAX_VERTICES} per operational intent")
    return oi


def intent_polygons_lonlat(doc: dict, ref_lon_deg: float | None = None) -> list:
    """Shapely polygons (lon, lat [deg]) of the volumes of an intent document, each in one
    continuous frame (:func:`~skyroute.stages.exports.lon_near`: its longitudes within 180 deg
    of ``ref_lon_deg``, default its own first vertex), so a volume across the antimeridian is
    the small polygon (longitudes may exceed 180), not one spanning the globe."""
    import shapely

    out = []
    for v in doc["volumes"]:
        verts = v["volume"]["outline_polygon"]["vertices"]
        lng = np.array([float(p["lng"]) for p in verts])
        ref = float(lng[0]) if ref_lon_deg is None else float(ref_lon_deg)
        out.append(shapely.Polygon(np.column_stack([lon_near(lng, ref), [float(p["lat"]) for p in verts]])))
    return out


def intent_conformance(doc: dict, lon_deg, lat_deg, h_w84_m, times_utc) -> float:
    """Share (0-1) of the points (``lon_deg``, ``lat_deg`` [deg], WGS 84 ellipsoidal
    ``h_w84_m`` [m], ``times_utc``: datetime64 / ISO texts) inside at least one volume of the
    intent ``doc`` (outline, altitude band and time window at once)."""
    import shapely

    lon, lat, h = (np.asarray(a, float) for a in (lon_deg, lat_deg, h_w84_m))
    t = pd.DatetimeIndex(pd.to_datetime(np.asarray(times_utc), utc=True)).as_unit("ns").asi8
    inside = np.zeros(lon.size, bool)
    for poly, v in zip(intent_polygons_lonlat(doc), doc["volumes"], strict=True):
        ts = pd.Timestamp(v["time_start"]["value"]).value
        te = pd.Timestamp(v["time_end"]["value"]).value
        lo, hi = v["volume"]["altitude_lower"]["value"], v["volume"]["altitude_upper"]["value"]
        m = (t >= ts) & (t <= te) & (h >= lo) & (h <= hi)
        if m.any():   # the points in the polygon's continuous frame (around its first vertex)
            m[m] = shapely.contains_xy(poly, lon_near(lon[m], float(poly.exterior.coords[0][0])), lat[m])
        inside |= m
    return float(inside.mean()) if inside.size else 1.0


class PolylineTrajectory:
    """A plan known only by its samples (fixed-wing plans: the lattice path with its turn fillets,
    sampled): the polyline through ``xyz`` [m] at times ``t_s`` [s from 0], with the interface
    :func:`plan_volumes` reads of a CornerTrajectory (one straight piece per chunk of samples,
    no arcs: the hull of points sampled along each segment holds the segment)."""

    def __init__(self, t_s, xyz):
        t = np.asarray(t_s, float)
        p = np.asarray(xyz, float).reshape(-1, 3)
        keep = np.r_[True, np.diff(t) > 1e-9]
        self.t, self.p = t[keep], p[keep]
        if self.t.size < 2:
            raise InputError("a sampled plan needs at least two samples at distinct times")
        self.duration_s = float(self.t[-1])
        self.piece_t_s = np.array([0.0, self.duration_s])
        self.phase_t0_s = np.array([0.0])
        self.kind = np.array([0], np.int8)
        self.radius_m = np.array([math.inf])
        v = np.linalg.norm(np.diff(self.p, axis=0), axis=1) / np.diff(self.t)
        self.v0 = np.array([float(v.max())])

    def sample(self, t) -> np.ndarray:
        t = np.clip(np.asarray(t, float), 0.0, self.duration_s)
        return np.column_stack([np.interp(t, self.t, self.p[:, k]) for k in range(3)])

    def velocity(self, t) -> np.ndarray:
        t = np.clip(np.asarray(t, float), 0.0, self.duration_s)
        i = np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, self.t.size - 2)
        return (self.p[i + 1] - self.p[i]) / (self.t[i + 1] - self.t[i])[:, None]


def plan_path(plan_ds):
    """``(trajectory, t0_s)`` of a plan-stage dataset: its exact CornerTrajectory (rotorcraft),
    else the polyline of its samples (:class:`PolylineTrajectory`, fixed-wing plans); None when
    neither is there."""
    from skyroute.stages.planning.strategic import trajectory_from_dataset

    tr = trajectory_from_dataset(plan_ds)
    if tr is not None:
        return tr
    if "t_s" not in plan_ds or "x_m" not in plan_ds:
        return None
    t = np.asarray(plan_ds["t_s"].values, float)
    xyz = np.column_stack([np.asarray(plan_ds[k].values, float) for k in ("x_m", "y_m", "z_m")])
    return PolylineTrajectory(t - t[0], xyz), float(t[0])


def plan_intent(plan_ds, height_w84_of_lonlat: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray], *,
                vehicle_radius_m: float, k_sigma: float = 3.0, time_buffer_s: float = 5.0,
                max_volume_s: float = 30.0, priority: int = 0) -> tuple[list[IntentVolume], dict]:
    """``(volumes, OperationalIntentDetails dict)`` of the chosen plan of a plan-stage dataset
    (:func:`~skyroute.stages.planning.strategic.plan_to_dataset`: exact trajectory or, for a
    fixed-wing plan, its samples (:func:`plan_path`), ``t_s``,
    ``sigma_p_m``, ``crs`` and ``start_time_utc`` attrs).  ``height_w84_of_lonlat(lon, lat, z)``:
    surface-datum heights [m] -> WGS 84 ellipsoidal [m] (e.g.
    :meth:`~skyroute.stages.geoid.HeightReference.ellipsoidal_m`).  InputError when the
    dataset has no chosen plan or no exact trajectory."""
    from pyproj import Transformer

    if int(plan_ds.attrs.get("chosen_level", -1)) < 0:
        raise InputError("no flyable plan: there is no trajectory to make an operational intent of")
    tr = plan_path(plan_ds)
    if tr is None:
        raise InputError("the plan dataset has no trajectory (traj_* variables or samples); re-run the plan stage")
    traj, t0 = tr
    crs = plan_ds.attrs["crs"]
    to_ll = Transformer.from_crs(crs, 4326, always_xy=True)

    def h_w84(p: np.ndarray) -> np.ndarray:
        lon, lat = to_ll.transform(p[:, 0], p[:, 1])
        return height_w84_of_lonlat(np.asarray(lon), np.asarray(lat), p[:, 2])

    vols = plan_volumes(traj, t0, plan_ds["t_s"].values, plan_ds["sigma_p_m"].values, h_w84,
                        vehicle_radius_m=vehicle_radius_m, k_sigma=k_sigma, time_buffer_s=time_buffer_s,
                        max_volume_s=max_volume_s)
    return vols, intent_details(vols, crs, plan_ds.attrs["start_time_utc"], priority)
