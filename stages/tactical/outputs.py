"""Outputs of a tactical replay (``skyroute fly``), written from a :class:`~.log.FlightLog` only.

* ``tactical.csv``: one row per level attempted per replanning (seed 001 Tables 3, 5):
  :data:`TACTICAL_COLUMNS`.  ``level`` is ``1``, ``2``, ``3``, ``octant``, ``potential``, ``landing`` or (fixed-wing
  local planner, one row per manoeuvre) ``climb`` / ``right`` / ``left``; infinite values
  are written ``inf``, undefined ones ``nan``; exactly one ``chosen=true`` per replanning
  (:func:`write_flight` raises :class:`~skyroute.stages.base.InputError` otherwise).
* ``flown.geojson``: RFC 7946 FeatureCollection of the ownship only, one ``LineString`` per
  flown part (``part`` = strategic / L1 / L2 / L3 / octant / potential / landing; fixed-wing: climb / right / left)
  of ``[lon, lat, z]`` (WGS 84,
  ``z`` [m] in the surface's vertical datum, NOT ellipsoidal: the properties say so), with
  ``t_s`` and ``times_utc`` (ISO 8601 UTC) per vertex.
* ``intruders.geojson``: one ``LineString`` per intruder (truth track: ``id``, ``kind``,
  ``radius_m``, ``known_from_s``, ``t_s``, ``times_utc``) and one ``Polygon`` per temporary
  no-fly zone (altitude band ``z_min_m`` .. ``z_max_m`` and active window ``start_s`` .. ``end_s``).
* ``flown.csv``: one row per flown sample (:data:`FLOWN_COLUMNS`), part boundaries once (the
  shared sample belongs to the earlier part), ``t_s`` and map coordinates at full precision.
* ``fly_top.png``, ``fly_profile.png``, ``fly_speed.png``: seed 001 Fig. 9 (top and vertical
  views with the strategic and tactical intruders and the coverage floor; ground-speed history).

:func:`flight_section` gives the ``fly`` section of ``summary.json``, with the minimum
separation to each intruder measured by brute force on the flown trajectory every
:data:`SEPARATION_STEP_S` s.
"""

from __future__ import annotations

import json
import math
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import Transformer

from skyroute.stages.base import InputError
from skyroute.stages.figures import add_map_furniture, grow_until_unclipped
from skyroute.stages.planning.outputs import crs_of, raster_values, write_csv
from skyroute.stages.planning.step3 import utc_of
from skyroute.stages.tactical.daa import ALERT_LEVELS, daa_series
from skyroute.stages.tactical.log import PART_NAMES, FlightLog, fly_summary_line  # noqa: F401  (re-exported)

__all__ = ["write_flight", "flight_section", "fly_summary_line", "flown_samples", "min_separations", "nofly_time_inside",
           "TACTICAL_COLUMNS", "FLOWN_COLUMNS", "SEPARATION_STEP_S", "PART_COLOURS"]

TACTICAL_COLUMNS = ("replanning", "event", "t_event_s", "t_coll_s", "level", "flyable", "C_l_m", "C_e_m", "f_m",
                    "max_sigma_p_m", "compute_s", "update_s", "added_flight_time_s", "chosen", "reasons",
                    "intruder", "t_los_s", "alert")
DAA_COLUMNS = ("t_s", "intruder", "range_m", "required_m", "t_los_s", "t_preventive_s", "alert")
FLOWN_COLUMNS = ("t_utc", "t_s", "part", "x_m", "y_m", "z_m", "lon", "lat", "speed_mps")
LEVELS = ("1", "2", "3", "octant", "potential", "landing", "escape", "resume", "climb", "right", "left", "loiter",
          "descend")
SEPARATION_STEP_S = 0.05
PART_COLOURS = {"strategic": "tab:blue", "L1": "tab:green", "L2": "tab:orange", "L3": "tab:purple",
                "octant": "tab:cyan", "potential": "tab:gray", "landing": "tab:red", "escape": "gold",
                "resume": "darkgreen", "climb": "tab:brown", "right": "tab:olive", "left": "tab:pink",
                "loiter": "darkgoldenrod", "descend": "slategray"}
ALERT_COLOURS = {"none": "#ffffff", "preventive": "#fff3b0", "corrective": "#ffc06b", "warning": "#ff7b7b"}


# ------------------------------------------------------------------ checks and samples


def _level(v) -> str:
    s = str(v).strip()
    s = {"L1": "1", "L2": "2", "L3": "3", "1.0": "1", "2.0": "2", "3.0": "3"}.get(s, s)
    if s not in LEVELS:
        raise InputError(f"level {v!r} of a tactical attempt is not one of 1, 2, 3, 'octant', 'potential', 'landing', "
                         "'climb', 'right' or 'left'")
    return s


def _check(log: FlightLog) -> None:
    """Raise InputError when ``log`` cannot be written: a replanning without exactly one chosen
    attempt, an unknown part name or level, a part whose arrays disagree."""
    by: dict[int, list] = {}
    for a in log.attempts:
        _level(a.level)
        by.setdefault(int(a.replanning), []).append(a)
    for r, rows in sorted(by.items()):
        n = sum(bool(a.chosen) for a in rows)
        if n != 1:
            raise InputError(f"replanning {r} (event {rows[0].event!r} at t={rows[0].t_event_s:g} s) has {n} chosen "
                             "attempts in the flight log; exactly one LevelAttempt per replanning must have "
                             "chosen=True (the landing when no level is flyable)")
    for i, p in enumerate(log.parts):
        if p.part not in PART_NAMES:
            raise InputError(f"flown part {i} is named {p.part!r}; use one of {', '.join(PART_NAMES)}")
        t, x, v = np.asarray(p.t_s, float), np.asarray(p.xyz_m, float), np.asarray(p.speed_mps, float)
        if x.ndim != 2 or x.shape[1] != 3 or t.shape != (x.shape[0],) or v.shape != t.shape:
            raise InputError(f"flown part {i} ({p.part}): t_s {t.shape}, xyz_m {x.shape} and speed_mps {v.shape} "
                             "must be (k,), (k, 3) and (k,)")
        if t.size and np.any(np.diff(t) <= 0):
            raise InputError(f"flown part {i} ({p.part}): t_s must be strictly increasing")


def flown_samples(log: FlightLog) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """The whole flown trajectory as in :meth:`FlightLog.flown` (shared part boundaries once,
    kept in the earlier part): ``t_s`` (m,) [s], ``xyz_m`` (m, 3) [m], ``speed_mps`` (m,)
    [m/s] and the part name of each sample."""
    ts, ps, vs, names = [], [], [], []
    last = -math.inf
    for p in log.parts:
        t = np.asarray(p.t_s, float)
        k = 1 if (t.size and math.isfinite(last) and t[0] <= last) else 0
        ts.append(t[k:])
        ps.append(np.asarray(p.xyz_m, float)[k:])
        vs.append(np.asarray(p.speed_mps, float)[k:])
        names += [p.part] * (t.size - k)
        if t.size:
            last = float(t[-1])
    if not ts:
        return np.zeros(0), np.zeros((0, 3)), np.zeros(0), []
    return np.concatenate(ts), np.concatenate(ps), np.concatenate(vs), names


def _at(t_query: np.ndarray, t_s: np.ndarray, xyz_m: np.ndarray) -> np.ndarray:
    """Linear interpolation of a track (``t_s``, ``xyz_m``) at ``t_query`` [s]."""
    t_s, xyz_m = np.asarray(t_s, float), np.asarray(xyz_m, float).reshape(-1, 3)
    if t_s.size == 1:
        return np.repeat(xyz_m, np.size(t_query), axis=0)
    return np.stack([np.interp(t_query, t_s, xyz_m[:, j]) for j in range(3)], axis=-1)


def _tau(t: np.ndarray, step_s: float) -> np.ndarray:
    n = int(math.floor((t[-1] - t[0]) / step_s + 1e-9))
    tau = t[0] + step_s * np.arange(n + 1)
    return tau if tau[-1] >= t[-1] - 1e-9 else np.append(tau, t[-1])


def min_separations(log: FlightLog, step_s: float = SEPARATION_STEP_S) -> list[dict[str, Any]]:
    """Per intruder, the minimum centre-to-centre distance [m] between the flown trajectory and
    its truth track, by brute force at every ``step_s`` [s] of the flight (both linear between
    samples; an intruder counts only inside its track's time span, a one-point track is
    stationary): ``id``, ``kind``, ``min_distance_m``, ``t_s`` (when), ``required_m`` (own
    radius + intruder radius + margin) and ``clearance_m`` (distance minus required); the
    distance values are None when the intruder never flies during the flight."""
    t, p = log.flown()
    out = []
    tau = _tau(t, step_s) if t.size >= 2 else t
    own = _at(tau, t, p) if t.size else np.zeros((0, 3))
    for it in log.intruders:
        ti = np.asarray(it.t_s, float)
        need = float(log.own_radius_m) + float(it.radius_m) + float(log.margin_m)
        m = np.ones(tau.size, bool) if ti.size == 1 else (tau >= ti[0]) & (tau <= ti[-1])
        rec: dict[str, Any] = {"id": str(it.id), "kind": str(it.kind), "min_distance_m": None, "t_s": None,
                               "required_m": need, "clearance_m": None}
        if m.any():
            d = np.linalg.norm(_at(tau[m], ti, it.xyz_m) - own[m], axis=1)
            k = int(np.argmin(d))
            rec.update(min_distance_m=float(d[k]), t_s=float(tau[m][k]), clearance_m=float(d[k]) - need)
        out.append(rec)
    return out


def _inside(xy: np.ndarray, poly: np.ndarray) -> np.ndarray:
    from matplotlib.path import Path as MplPath

    return MplPath(np.asarray(poly, float)[:, :2]).contains_points(np.asarray(xy, float).reshape(-1, 2))


def nofly_time_inside(log: FlightLog, step_s: float = SEPARATION_STEP_S) -> list[dict[str, Any]]:
    """Per temporary no-fly zone, the flown time [s] inside it while it is active (inside the
    polygon, inside its altitude band, inside its window), by brute force every ``step_s``."""
    t, p = log.flown()
    out = []
    tau = _tau(t, step_s) if t.size >= 2 else t
    own = _at(tau, t, p) if t.size else np.zeros((0, 3))
    for z in log.nofly:
        act = (tau >= z.start_s) & (tau <= z.end_s) & (own[:, 2] >= z.z_min_m) & (own[:, 2] <= z.z_max_m)
        if act.any():
            act[act] = _inside(own[act, :2], z.polygon_xy)
        out.append({"id": str(z.id), "inside_active_s": float(act.sum() * step_s)})
    return out


# ------------------------------------------------------------------ tables


def _val(v, nd: int = 3) -> str:
    """CSV text of a value: booleans ``true``/``false``, ``inf``/``-inf``/``nan`` spelled out."""
    if v is None:
        return "nan"
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    v = float(v)
    if math.isnan(v):
        return "nan"
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    return f"{v:.{nd}f}"


def _num(v) -> float | None:
    return None if v is None or not math.isfinite(float(v)) else float(v)


def _tactical_rows(log: FlightLog) -> list[list[str]]:
    rows = []
    for a in log.attempts:
        rows.append([str(int(a.replanning)), str(a.event), _val(a.t_event_s, 3), _val(a.t_coll_s, 3), _level(a.level),
                     _val(bool(a.flyable)), _val(a.C_l_m, 1), _val(a.C_e_m, 1), _val(a.f_m, 1),
                     _val(a.max_sigma_p_m, 3), _val(a.compute_s, 6), _val(a.update_s, 6),
                     _val(a.added_flight_time_s, 2), _val(bool(a.chosen)), str(a.reasons),
                     str(getattr(a, "intruder", "")), _val(getattr(a, "t_los_s", math.nan), 3),
                     str(getattr(a, "alert", ""))])
    return rows


# ------------------------------------------------------------------ GeoJSON


def _geo(log: FlightLog):
    crs, _ = crs_of(log.crs_wkt)
    epsg = crs.to_epsg()
    return Transformer.from_crs(crs, 4326, always_xy=True), (f"EPSG:{epsg}" if epsg is not None else crs.to_wkt())


def _lonlatz(tr, xyz: np.ndarray) -> list[list[float]]:
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    lon, lat = tr.transform(xyz[:, 0], xyz[:, 1])
    return [[float(a), float(b), float(z)] for a, b, z in zip(np.atleast_1d(lon), np.atleast_1d(lat), xyz[:, 2],
                                                                strict=True)]


def _height_props(log: FlightLog, crs_txt: str) -> dict[str, Any]:
    return {"vertical_datum": log.vertical_datum, "heights_are_ellipsoidal": False,
            "altitude_note": (f"altitudes are in the vertical datum '{log.vertical_datum}' of the surface model; "
                              "heights are NOT ellipsoidal (RFC 7946 expects ellipsoidal heights)"),
            "map_crs": crs_txt}


def flown_geojson(log: FlightLog) -> dict:
    """The RFC 7946 FeatureCollection of the ownship's flown parts (see the module docstring)."""
    tr, crs_txt = _geo(log)
    start = utc_of(log.start_time_utc, [0.0])[0]
    feats = []
    for i, p in enumerate(log.parts):
        t = np.asarray(p.t_s, float)
        geom = ({"type": "LineString", "coordinates": _lonlatz(tr, p.xyz_m)} if t.size >= 2 else
                {"type": "Point", "coordinates": _lonlatz(tr, p.xyz_m)[0]})
        props = {"name": f"skyroute flown part {i}: {p.part}", "part": p.part,
                 "replanning": None if p.replanning is None else int(p.replanning),
                 "t_s": [float(v) for v in t], "times_utc": utc_of(log.start_time_utc, t),
                 "start_time_utc": start, **_height_props(log, crs_txt),
                 "dop_threshold": _num(log.dop_threshold) if log.dop_threshold is not None else None,
                 "speed_mps": [float(v) for v in np.asarray(p.speed_mps, float)],
                 "map_xyz_m": np.asarray(p.xyz_m, float).tolist()}
        feats.append({"type": "Feature", "geometry": geom, "properties": props})
    return {"type": "FeatureCollection", "features": feats}


def _ccw(ring: list[list[float]]) -> list[list[float]]:
    a = np.asarray(ring, float)
    area2 = float(np.sum(a[:-1, 0] * a[1:, 1] - a[1:, 0] * a[:-1, 1]))
    return ring if area2 >= 0 else ring[::-1]


def intruders_geojson(log: FlightLog) -> dict:
    """The RFC 7946 FeatureCollection of the intruders' truth tracks and the no-fly zones."""
    tr, crs_txt = _geo(log)
    feats = []
    for it in log.intruders:
        t = np.asarray(it.t_s, float)
        coords = _lonlatz(tr, it.xyz_m)
        geom = ({"type": "LineString", "coordinates": coords} if len(coords) >= 2 else
                {"type": "Point", "coordinates": coords[0]})
        props = {"name": f"intruder {it.id}", "feature": "intruder", "id": str(it.id), "kind": str(it.kind),
                 "radius_m": float(it.radius_m), "known_from_s": float(it.known_from_s),
                 "known_from_utc": utc_of(log.start_time_utc, [it.known_from_s])[0],
                 "t_s": [float(v) for v in t], "times_utc": utc_of(log.start_time_utc, t),
                 "n_declarations": len(it.declared), **_height_props(log, crs_txt),
                 "map_xyz_m": np.asarray(it.xyz_m, float).tolist()}
        feats.append({"type": "Feature", "geometry": geom, "properties": props})
    for z in log.nofly:
        poly = np.asarray(z.polygon_xy, float)[:, :2]
        if not np.allclose(poly[0], poly[-1]):
            poly = np.vstack([poly, poly[:1]])
        lon, lat = tr.transform(poly[:, 0], poly[:, 1])
        ring = _ccw([[float(a), float(b)] for a, b in zip(lon, lat, strict=True)])
        props = {"name": f"no-fly zone {z.id}", "feature": "nofly", "id": str(z.id),
                 "z_min_m": _num(z.z_min_m), "z_max_m": _num(z.z_max_m),
                 "start_s": _num(z.start_s), "end_s": _num(z.end_s),
                 "start_utc": utc_of(log.start_time_utc, [z.start_s])[0] if math.isfinite(z.start_s) else None,
                 "end_utc": utc_of(log.start_time_utc, [z.end_s])[0] if math.isfinite(z.end_s) else None,
                 **_height_props(log, crs_txt), "map_xy_m": poly.tolist()}
        feats.append({"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [ring]}, "properties": props})
    return {"type": "FeatureCollection", "features": feats}


# ------------------------------------------------------------------ entry points


def write_flight(log: FlightLog, out_dir, *, figures: bool = True) -> dict[str, Path]:
    """Write ``tactical.csv``, ``flown.geojson``, ``intruders.geojson``, ``flown.csv`` and (with
    ``figures``) ``fly_top.png``, ``fly_profile.png``, ``fly_speed.png`` to ``out_dir``; return
    the paths by file name.  Raises InputError when a replanning has not exactly one chosen
    attempt (or the log is malformed), before writing anything."""
    _check(log)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {"tactical.csv": out / "tactical.csv"}
    write_csv(files["tactical.csv"], TACTICAL_COLUMNS, _tactical_rows(log))
    files["flown.geojson"] = out / "flown.geojson"
    files["flown.geojson"].write_text(json.dumps(flown_geojson(log), indent=1, allow_nan=False))
    files["intruders.geojson"] = out / "intruders.geojson"
    files["intruders.geojson"].write_text(json.dumps(intruders_geojson(log), indent=1, allow_nan=False))
    t, p, v, names = flown_samples(log)
    tr, _ = _geo(log)
    lon, lat = tr.transform(p[:, 0], p[:, 1]) if t.size else (np.zeros(0), np.zeros(0))
    utc = utc_of(log.start_time_utc, t)
    rows = [[utc[i], repr(float(t[i])), names[i], repr(float(p[i, 0])), repr(float(p[i, 1])), repr(float(p[i, 2])),
             f"{lon[i]:.9f}", f"{lat[i]:.9f}", _val(v[i], 3)] for i in range(t.size)]
    files["flown.csv"] = out / "flown.csv"
    write_csv(files["flown.csv"], FLOWN_COLUMNS, rows)
    daa = daa_series(log)
    if daa:
        files["daa.csv"] = out / "daa.csv"
        write_csv(files["daa.csv"], DAA_COLUMNS,
                  [[_val(r["t_s"], 2), r["intruder"], _val(r["range_m"], 2), _val(r["required_m"], 2),
                    _val(r["t_los_s"], 2), _val(r["t_preventive_s"], 2), r["alert"]] for r in daa])
    if figures and t.size >= 2:
        files.update(_figures(log, out))
        if daa:
            files["fly_daa.png"] = _daa_figure(log, daa, out / "fly_daa.png")
    return files


def flight_section(log: FlightLog) -> dict[str, Any]:
    """The ``fly`` section of ``summary.json`` (JSON-safe: non-finite numbers are None).

    ``outcome`` (goal / landed / failed), ``reason``, ``reached_goal``, ``n_replannings``,
    ``chosen_levels`` (one per replanning), ``events`` (time, kind, label, t_coll_s, outcome),
    ``replannings`` (per replanning: event, times, chosen level, levels tried and flyable,
    summed compute_s, update_s, added flight time), ``parts`` (name, replanning, start/end
    time, horizontal and 3-D length), ``min_separation`` (:func:`min_separations`, brute force
    every ``separation_step_s``), ``nofly`` (:func:`nofly_time_inside`), ``flight_time_s``,
    ``length_m``, ``energy_Wh`` (None when the log has none), ``compile_s`` and the replay's
    settings (``t_rep_s``, ``tick_s``, ``seed``, ``dop_threshold``), ``tactical_method`` (levels or
    octant) and ``dense_zones`` (octant method: the zone definitions, :mod:`.octant_replan`);
    issue 22: ``escapes`` (each escape decision: kind, reflex, predicted margin, hold),
    ``unavoidable_losses`` (predicted losses the flight had to accept, with why),
    ``separation_lost`` (the brute-force flown minimum is below the required separation for
    some intruder: ``skyroute fly`` exits 3) and ``alerts`` (per intruder: the highest DAA
    alert level shown, when each level first showed, the smallest time to loss of separation)."""
    _check(log)
    t, p = log.flown()
    by: dict[int, list] = {}
    for a in log.attempts:
        by.setdefault(int(a.replanning), []).append(a)
    reps = []
    for r, rows in sorted(by.items()):
        ch = next(a for a in rows if a.chosen)
        reps.append({"replanning": r, "event": str(rows[0].event), "t_event_s": _num(rows[0].t_event_s),
                     "t_coll_s": _num(rows[0].t_coll_s), "chosen_level": _level(ch.level),
                     "levels_tried": [_level(a.level) for a in rows],
                     "levels_flyable": [_level(a.level) for a in rows if a.flyable],
                     "compute_s": _num(sum(float(a.compute_s) for a in rows)), "update_s": _num(rows[0].update_s),
                     "added_flight_time_s": _num(ch.added_flight_time_s), "f_m": _num(ch.f_m)})
    parts = []
    for pt in log.parts:
        x = np.asarray(pt.xyz_m, float)
        parts.append({"part": pt.part, "replanning": None if pt.replanning is None else int(pt.replanning),
                      "t_start_s": _num(pt.t_s[0]) if len(pt.t_s) else None,
                      "t_end_s": _num(pt.t_s[-1]) if len(pt.t_s) else None,
                      "length_2d_m": float(np.linalg.norm(np.diff(x[:, :2], axis=0), axis=1).sum()),
                      "length_m": float(np.linalg.norm(np.diff(x, axis=0), axis=1).sum())})
    events = [{"t_s": _num(e.get("t_s", math.nan)), "kind": str(e.get("kind", "")), "label": str(e.get("label", "")),
               "t_known_s": _num(e.get("t_known_s", e.get("t_s", math.nan))),
               "t_coll_s": _num(e.get("t_coll_s", math.inf)), "outcome": str(e.get("outcome", ""))}
              for e in log.events]
    energy = getattr(log, "energy_Wh", None)
    seps = min_separations(log)
    return {"scenario": log.scenario, "outcome": log.outcome, "reason": log.reason,
            "reached_goal": log.outcome == "goal", "n_replannings": len(reps),
            "chosen_levels": [r["chosen_level"] for r in reps], "events": events, "replannings": reps,
            "parts": parts, "separation_step_s": SEPARATION_STEP_S, "min_separation": seps,
            "nofly": nofly_time_inside(log),
            "flight_time_s": float(t[-1] - t[0]) if t.size else None,
            "length_m": float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if t.size else None,
            "energy_Wh": _num(energy) if energy is not None else None, "compile_s": _num(log.compile_s),
            "t_rep_s": _num(log.t_rep_s), "tick_s": _num(log.tick_s), "seed": int(log.seed),
            "dop_threshold": _num(log.dop_threshold) if log.dop_threshold is not None else None,
            "clearance": "sboa" if getattr(log, "bubble", None) else "fixed",
            "safety_bubble": {k: _num(v) for k, v in log.bubble.items()} if getattr(log, "bubble", None) else None,
            "warnings": list(log.warnings), "tactical_method": str(getattr(log, "method", "levels")),
            "dense_zones": list(getattr(log, "dense_zones", [])),
            "local_planner": _json_safe(log.local) if getattr(log, "local", None) else None,
            "escapes": _json_safe(list(getattr(log, "escapes", []))),
            "unavoidable_losses": _json_safe(list(getattr(log, "losses", []))),
            "separation_lost": any(r["clearance_m"] is not None and r["clearance_m"] < 0 for r in seps),
            "alerts": _alert_summary(log)}


def _alert_summary(log: FlightLog) -> list[dict[str, Any]]:
    """Per known intruder: the highest alert level shown (state-based, :func:`daa_series`),
    when it first showed each level, and the smallest predicted time to loss of separation."""
    out = []
    rows = daa_series(log)
    for ident in dict.fromkeys(r["intruder"] for r in rows):
        rr = [r for r in rows if r["intruder"] == ident]
        levels = [r["alert"] for r in rr]
        top = max(levels, key=ALERT_LEVELS.index)
        first = {a: _num(next(r["t_s"] for r in rr if r["alert"] == a)) for a in ALERT_LEVELS[1:] if a in levels}
        out.append({"intruder": ident, "highest_alert": top, "first_alert_s": first,
                    "min_t_los_s": _num(min(r["t_los_s"] for r in rr))})
    return out


def _json_safe(v):
    if isinstance(v, dict):
        return {str(k): _json_safe(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_json_safe(x) for x in v]
    if isinstance(v, float | np.floating):
        return _num(v)
    if isinstance(v, np.integer | np.bool_):
        return v.item()
    return v


# ------------------------------------------------------------------ figures


def _event_legend(log: FlightLog) -> list[str]:
    out = []
    for i, e in enumerate(log.events):
        what = e.get("label") or e.get("kind", "event")
        out.append(f"E{i + 1}: t = {float(e.get('t_s', math.nan)):.1f} s, {what} -> {e.get('outcome', '?')}")
    return out


def _local_obstacles(log: FlightLog) -> list[dict]:
    """The unknown static obstacles of a local-planner flight (fixed-wing), else []."""
    loc = getattr(log, "local", None)
    return list(loc.get("obstacles", [])) if loc else []


def _window(z) -> str:
    """Active window of a no-fly zone as text, e.g. ``t 75-300 s`` or ``from t 75 s``."""
    if not math.isfinite(z.end_s):
        return f"from t {z.start_s:.0f} s"
    return f"t {z.start_s:.0f}-{z.end_s:.0f} s"


CITY_VIEW_M = 4000.0   # a top view wider than this [m] draws faint, unlabelled floor contours
MANY_SITES = 150       # more landing sites than this in the view: small marks


def _window_of(grid, box, max_cells: int = 1200):
    """The raster window of ``grid`` covering ``box`` (xmin, xmax, ymin, ymax) [m], strided to
    at most ``max_cells`` per side (figures only): ``(slices, imshow extent, x, y)``."""
    x0, x1, y0, y1 = box
    r0, c0 = grid.cell_of(x0, y1)
    r1, c1 = grid.cell_of(x1, y0)
    step = max(1, int(math.ceil(max(r1 - r0 + 1, c1 - c0 + 1) / max_cells)))
    rs, cs = slice(int(r0), int(r1) + 1, step), slice(int(c0), int(c1) + 1, step)
    gx, gy = grid.x[cs], grid.y[rs]
    h = grid.resolution_m * step / 2
    return (rs, cs), (gx[0] - h, gx[-1] + h, gy[-1] - h, gy[0] + h), gx, gy


def _part_index(log: FlightLog) -> list[np.ndarray]:
    """Indices of each part's samples in :func:`flown_samples` (a shared boundary sample counted
    in both parts)."""
    out, count, last = [], 0, -math.inf
    for p in log.parts:
        t = np.asarray(p.t_s, float)
        k = 1 if (t.size and math.isfinite(last) and t[0] <= last) else 0
        out.append(np.arange(count - k, count - k + t.size))
        count += t.size - k
        if t.size:
            last = float(t[-1])
    return out


def _dist_along(xy: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy[:, :2], axis=0), axis=1))])


def _view_box(log: FlightLog, t: np.ndarray, p: np.ndarray) -> tuple[float, float, float, float]:
    """Map extent (xmin, xmax, ymin, ymax) [m] of the top view: the flown and planned paths and
    the no-fly zones, padded, inside the grid."""
    pts = [p[:, :2], np.asarray(log.planned_xyz_m, float).reshape(-1, 3)[:, :2]]
    pts += [np.asarray(z.polygon_xy, float)[:, :2] for z in log.nofly]
    a = np.vstack(pts)
    x0, y0 = a.min(axis=0)
    x1, y1 = a.max(axis=0)
    pad = 0.1 * max(x1 - x0, y1 - y0, 100.0)
    x0, x1, y0, y1 = x0 - pad, x1 + pad, y0 - pad, y1 + pad
    w, h = x1 - x0, y1 - y0                    # no thinner than 0.6:1 either way (room for context)
    if h < 0.6 * w:
        y0, y1 = y0 - (0.6 * w - h) / 2, y1 + (0.6 * w - h) / 2
    elif w < 0.6 * h:
        x0, x1 = x0 - (0.6 * h - w) / 2, x1 + (0.6 * h - w) / 2
    g = log.grid
    if g is not None:
        gx0, gy0, gx1, gy1 = g.bounds
        x0, x1, y0, y1 = max(x0, gx0), min(x1, gx1), max(y0, gy0), min(y1, gy1)
    return x0, x1, y0, y1


def _figures(log: FlightLog, out: Path) -> dict[str, Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon

    files: dict[str, Path] = {}
    t, p, v, names = flown_samples(log)
    planned = np.asarray(log.planned_xyz_m, float).reshape(-1, 3)
    planned_t = np.asarray(log.planned_t_s, float)
    ev_t = np.array([float(e.get("t_s", math.nan)) for e in log.events])
    ev_xyz = _at(ev_t, t, p) if ev_t.size else np.zeros((0, 3))
    ev_legend = _event_legend(log)
    grid = log.grid
    datum_label = "altitude [m]\n" + "\n".join(textwrap.wrap(log.vertical_datum, 32)[:2])

    def part_lines(ax, xs, ys):
        seen = set()
        for pt in log.parts:
            if len(pt.t_s) < 2:
                continue
            lab = None if pt.part in seen else f"flown: {pt.part}"
            seen.add(pt.part)
            ax.plot(xs(pt), ys(pt), color=PART_COLOURS[pt.part], lw=2.2, label=lab, zorder=5)

    # ---------------------------------------------------------- top view
    x0, x1, y0, y1 = _view_box(log, t, p)
    aspect = (y1 - y0) / (x1 - x0)
    fig, ax = plt.subplots(figsize=(12, min(max(7.0 * aspect + 2.4, 6.5), 11)), dpi=100, layout="constrained")
    if grid is not None:
        win, ext, gxs, gys = _window_of(grid, (x0, x1, y0, y1))
        surf, terr, fl = (None if a is None else raster_values(a)[win] for a in (log.surface_m, log.terrain_m,
                                                                          log.coverage_floor_m))
        if surf is not None:
            h = surf - terr if terr is not None else surf
            if terr is not None and float(np.nanmax(h)) < 0.5:
                # no buildings (a DEM only, e.g. the fixed-wing scenarios): the terrain itself
                im = ax.imshow(terr, extent=ext, cmap="terrain", interpolation="nearest", alpha=0.8, origin="upper")
                label = f"terrain height [m] ({log.vertical_datum})"
            else:
                lab = "height above terrain [m]" if terr is not None else f"surface height [m] ({log.vertical_datum})"
                im = ax.imshow(h, extent=ext, cmap="Greys", interpolation="nearest", alpha=0.7, origin="upper")
                label = "surface (buildings), " + lab
            fig.colorbar(im, ax=ax, shrink=0.6, location="bottom", pad=0.01, aspect=40).set_label(label)
        if fl is not None:
            fin = np.isfinite(fl)
            if (~fin).any():
                ax.contourf(gxs, gys, (~fin).astype(float), levels=[0.5, 1.5], colors="none",
                            hatches=["xxx"], zorder=2)
            if fin.any() and np.nanmax(np.where(fin, fl, np.nan)) > np.nanmin(np.where(fin, fl, np.nan)):
                # a city-wide view (more than CITY_VIEW_M a side): thin faint contours, unlabelled,
                # so that the flight stays readable over thousands of buildings
                wide = max(x1 - x0, y1 - y0) > CITY_VIEW_M
                cs = ax.contour(gxs, gys, np.where(fin, fl, np.nan), levels=6, colors="steelblue",
                                linewidths=0.25 if wide else 0.7, alpha=0.45 if wide else 1.0, zorder=3)
                if not wide:
                    ax.clabel(cs, fontsize=6, fmt="%.0f m")
            dop = f" (DOP < {log.dop_threshold:g})" if log.dop_threshold is not None else ""
            ax.plot([], [], color="steelblue", lw=0.7, label=f"coverage floor{dop} [m] contours")
            if (~fin).any():
                ax.fill([], [], facecolor="none", edgecolor="0.3", hatch="xxx", label="no coverage at any altitude")
    for z in log.nofly:
        ax.add_patch(Polygon(np.asarray(z.polygon_xy, float)[:, :2], closed=True, facecolor="red", alpha=0.25,
                             edgecolor="red", lw=1.2, hatch="//", zorder=4,
                             label=f"no-fly {z.id}: {z.z_min_m:.0f}-{z.z_max_m:.0f} m, {_window(z)}"))
    for o in _local_obstacles(log):
        ax.add_patch(Polygon(np.asarray(o["polygon_xy"], float), closed=True, facecolor="black", alpha=0.6,
                             edgecolor="black", lw=1.0, zorder=4,
                             label=f"unknown obstacle {o['id']}: top {o['z_top_m']:.0f} m, from {o['t_s']:g} s"))
    if planned.shape[0]:
        ax.plot(planned[:, 0], planned[:, 1], "k--", lw=1.2, label="planned (strategic)", zorder=4)
    part_lines(ax, lambda q: np.asarray(q.xyz_m)[:, 0], lambda q: np.asarray(q.xyz_m)[:, 1])
    styles = {"strategic": dict(color="dimgray", ls="-", marker="s"),
              "tactical": dict(color="magenta", ls="-.", marker="D")}
    seen, marked = set(), set()
    for it in log.intruders:
        st = styles.get(it.kind, styles["tactical"])
        xyz = np.asarray(it.xyz_m, float).reshape(-1, 3)
        lab = None if it.kind in seen else f"{it.kind} intruder (truth track)"
        seen.add(it.kind)
        ax.plot(xyz[:, 0], xyz[:, 1], color=st["color"], ls=st["ls"], lw=1.2, label=lab, zorder=4)
        for dec in list(it.declared)[:-1]:                  # superseded declarations, faint
            dx = np.asarray(dec[2], float).reshape(-1, 3)
            ax.plot(dx[:, 0], dx[:, 1], color=st["color"], ls=":", lw=1.0, alpha=0.6, zorder=3,
                    label=None if "superseded" in seen else "superseded declared track")
            seen.add("superseded")
        if xyz.shape[0] >= 2:
            ax.annotate("", xy=xyz[-1, :2], xytext=xyz[-1, :2] - 0.001 * (xyz[-1, :2] - xyz[-2, :2]),
                        arrowprops=dict(arrowstyle="-|>", color=st["color"], lw=1.2), zorder=4)
        ti = np.asarray(it.t_s, float)
        m = (ev_t >= ti[0]) & (ev_t <= ti[-1]) if ti.size > 1 else np.isfinite(ev_t)
        m &= ev_t >= float(it.known_from_s)      # where it was when the ownship knew of it
        if m.any():
            marked.add(it.kind)
            q = _at(ev_t[m], ti, xyz)
            ax.plot(q[:, 0], q[:, 1], ls="none", marker=st["marker"], ms=6, mfc="white", mec=st["color"], zorder=6)
            for i, qq in zip(np.flatnonzero(m), q, strict=True):
                ax.annotate(f"E{i + 1}", qq[:2], xytext=(5, -3), textcoords="offset points", fontsize=6,
                            color=st["color"], va="top", zorder=8, annotation_clip=True)
        ax.text(xyz[0, 0], xyz[0, 1], f" {it.id}", fontsize=7, color=st["color"], va="bottom", clip_on=True,
                in_layout=False)     # the track may start outside the view: clipped, not laid out
    for kind in sorted(marked):
        st = styles.get(kind, styles["tactical"])
        ax.plot([], [], ls="none", marker=st["marker"], mfc="white", mec=st["color"],
                label=f"{kind} intruder at event times (once known)")
    if ev_t.size:
        ax.plot(ev_xyz[:, 0], ev_xyz[:, 1], "kX", ms=7, label="ownship at event times", zorder=7)
        for i, q in enumerate(ev_xyz):
            ax.annotate(f"E{i + 1}", q[:2], xytext=(4, 4), textcoords="offset points", fontsize=8,
                        fontweight="bold", zorder=8, annotation_clip=True)
    if log.landing_xy is not None and np.size(log.landing_xy):
        lx = np.asarray(log.landing_xy, float).reshape(-1, 2)
        n = int(np.count_nonzero((lx[:, 0] >= x0) & (lx[:, 0] <= x1) & (lx[:, 1] >= y0) & (lx[:, 1] <= y1)))
        if n <= MANY_SITES:
            ax.plot(lx[:, 0], lx[:, 1], "^", color="darkorange", mec="k", ms=7, ls="none", label="landing sites",
                    zorder=6)
        else:       # thousands in a city-wide view: small marks under the flight, not a carpet over it
            ax.plot(lx[:, 0], lx[:, 1], "^", color="darkorange", mec="none", alpha=0.6,
                    ms=max(1.5, 7.0 * math.sqrt(MANY_SITES / n)), ls="none", label=f"landing sites ({n} in view)",
                    zorder=3)
    start = planned[0] if planned.shape[0] else p[0]
    ax.plot(start[0], start[1], "go", ms=9, label="start", zorder=8)
    if planned.shape[0]:
        ax.plot(planned[-1, 0], planned[-1, 1], "r*", ms=13, label="goal", zorder=8)
    if log.outcome != "goal":
        ax.plot(p[-1, 0], p[-1, 1], "v", mfc="none", mec="k", mew=1.5, ms=11, label=f"end of flight ({log.outcome})",
                zorder=8)
    for s in ev_legend:
        ax.plot([], [], ls="none", label=s)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{log.scenario}: tactical replay, top view (outcome: {log.outcome})")
    fig.legend(fontsize=7, loc="outside right upper")
    add_map_furniture(ax)
    files["fly_top.png"] = out / "fly_top.png"
    grow_until_unclipped(fig)
    fig.savefig(files["fly_top.png"])
    plt.close(fig)

    # ---------------------------------------------------------- vertical profile
    dist = _dist_along(p)
    fig, ax = plt.subplots(figsize=(11, 4.8), dpi=100, layout="constrained")
    if grid is not None:
        row, col = grid.cell_of(p[:, 0], p[:, 1])
        surf, terr, fl = raster_values(log.surface_m), raster_values(log.terrain_m), raster_values(log.coverage_floor_m)
        base = min(float(np.nanmin(a[row, col])) for a in (surf, terr) if a is not None) - 5.0 \
            if (surf is not None or terr is not None) else None
        if surf is not None:
            ax.fill_between(dist, base, surf[row, col], step="mid", color="0.55", alpha=0.5,
                            label="surface (buildings) under the path")
        if terr is not None:
            ax.fill_between(dist, base, terr[row, col], step="mid", color="saddlebrown", alpha=0.6,
                            label="terrain under the path")
        if fl is not None:
            f = fl[row, col]
            dop = f" (DOP < {log.dop_threshold:g})" if log.dop_threshold is not None else ""
            ax.plot(dist, np.where(np.isfinite(f), f, np.nan), color="steelblue", ls="--", lw=1.2,
                    label=f"coverage floor{dop} under the path")
            if (~np.isfinite(f)).any():
                ax.fill_between(dist, 0, 1, where=~np.isfinite(f), transform=ax.get_xaxis_transform(),
                                color="steelblue", alpha=0.12, label="no coverage at any altitude")
    for z in log.nofly:
        inside = _inside(p[:, :2], z.polygon_xy)
        if inside.any():
            ax.fill_between(dist, z.z_min_m, z.z_max_m, where=inside, color="red", alpha=0.2, hatch="//",
                            label=f"no-fly {z.id} over the path, {_window(z)}")
    for o in _local_obstacles(log):
        inside = _inside(p[:, :2], np.asarray(o["polygon_xy"], float))
        if inside.any():
            lo = base if (grid is not None and base is not None) else float(np.nanmin(p[:, 2])) - 50.0
            ax.fill_between(dist, lo, o["z_top_m"], where=inside, color="black", alpha=0.6,
                            label=f"unknown obstacle {o['id']} under the path")
    if planned.shape[0] >= 2:
        ax.plot(_dist_along(planned), planned[:, 2], "k--", lw=1.2, label="planned (strategic), its own distance")
    idx = _part_index(log)
    seen = set()
    for pt, ii in zip(log.parts, idx, strict=True):
        if ii.size < 2:
            continue
        ax.plot(dist[ii], p[ii, 2], color=PART_COLOURS[pt.part], lw=2.2, zorder=5,
                label=None if pt.part in seen else f"flown: {pt.part}")
        seen.add(pt.part)
    if ev_t.size:
        ev_d = np.interp(ev_t, t, dist)
        for i, d in enumerate(ev_d):
            ax.axvline(d, color="k", ls=":", lw=0.9)
            ax.text(d, 1.01, f"E{i + 1}", transform=ax.get_xaxis_transform(), ha="center", va="bottom", fontsize=8,
                    fontweight="bold")
    for s in ev_legend:
        ax.plot([], [], ls="none", label=s)
    ax.set_xlabel("horizontal distance flown [m]")
    ax.set_ylabel(datum_label, fontsize=8)
    ax.set_title(f"{log.scenario}: tactical replay, vertical profile along the flown path", pad=14)
    fig.legend(fontsize=7, loc="outside right upper")
    files["fly_profile.png"] = out / "fly_profile.png"
    grow_until_unclipped(fig)
    fig.savefig(files["fly_profile.png"])
    plt.close(fig)

    # ---------------------------------------------------------- speed history
    fig, ax = plt.subplots(figsize=(11, 4.2), dpi=100, layout="constrained")
    if planned_t.size >= 2:
        vp = np.linalg.norm(np.diff(planned[:, :2], axis=0), axis=1) / np.diff(planned_t)
        ax.step(planned_t, np.append(vp, vp[-1]), where="post", color="k", ls="--", lw=1.1,
                label="planned (strategic) ground speed")
    for pt, ii in zip(log.parts, idx, strict=True):
        if pt.part != "strategic" and ii.size:
            ax.axvspan(t[ii[0]], t[ii[-1]], color=PART_COLOURS[pt.part], alpha=0.08, lw=0)
    part_lines(ax, lambda q: np.asarray(q.t_s), lambda q: np.asarray(q.speed_mps))
    for i, te in enumerate(ev_t):
        ax.axvline(te, color="k", ls=":", lw=0.9)
        ax.text(te, 1.01, f"E{i + 1}", transform=ax.get_xaxis_transform(), ha="center", va="bottom", fontsize=8,
                fontweight="bold")
        if log.t_rep_s and np.isfinite(te) and str(log.events[i].get("outcome", "")) not in ("", "no conflict"):
            ax.axvline(te + log.t_rep_s, color="0.4", ls="-.", lw=0.8)
    if len(ev_t) and log.t_rep_s:
        ax.plot([], [], color="0.4", ls="-.", lw=0.8, label=f"replan takes effect (t_event + t_rep = +{log.t_rep_s:g} s)")
    ax.plot([], [], color="k", ls=":", lw=0.9, label="event times")
    for s in ev_legend:
        ax.plot([], [], ls="none", label=s)
    ax.set_ylim(bottom=0.0)
    ax.set_xlabel("mission time [s]")
    ax.set_ylabel("ground speed [m/s]")
    ax.set_title(f"{log.scenario}: tactical replay, ground speed history", pad=14)
    fig.legend(fontsize=7, loc="outside right upper")
    files["fly_speed.png"] = out / "fly_speed.png"
    grow_until_unclipped(fig)
    fig.savefig(files["fly_speed.png"])
    plt.close(fig)
    return files


def _daa_figure(log: FlightLog, rows: list[dict], path: Path) -> Path:
    """``fly_daa.png``: per known intruder, the range [m] over time as a DAA display shows it
    (state-based, :func:`~skyroute.stages.tactical.daa.daa_series`), on bands coloured by the
    alert level, with the required separation, and the flown parts along the time axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    ids = list(dict.fromkeys(r["intruder"] for r in rows))
    n = len(ids)
    fig, axes = plt.subplots(n, 1, figsize=(11, 2.6 * n + 1.4), dpi=100, sharex=True, squeeze=False,
                             layout="constrained")
    for ax, ident in zip(axes[:, 0], ids, strict=True):
        rr = [r for r in rows if r["intruder"] == ident]
        t = np.array([r["t_s"] for r in rr])
        rng = np.array([r["range_m"] for r in rr])
        need = float(rr[0]["required_m"])
        step = float(np.median(np.diff(t))) if t.size > 1 else 1.0
        for r in rr:
            if r["alert"] != "none":
                ax.axvspan(r["t_s"] - step / 2, r["t_s"] + step / 2, color=ALERT_COLOURS[r["alert"]], lw=0)
        ax.plot(t, rng, color="k", lw=1.6, label="range (centres)")
        ax.axhline(need, color="tab:red", ls="--", lw=1.2, label=f"required separation {need:.1f} m")
        ax.set_ylabel("range [m] (log)")
        ax.set_yscale("log")
        top = float(np.nanmax(rng)) if rng.size else need
        low = float(np.nanmin(rng)) if rng.size else need
        ax.set_ylim(max(min(low, need) * 0.5, 0.1), max(top, 2.0 * need) * 1.5)
        ax.set_title(f"intruder {ident}: detect-and-avoid alerts (DO-365 levels scaled to the separation)",
                     fontsize=10, loc="left")
        ax.grid(True, alpha=0.3)
        for pt in log.parts:
            if len(pt.t_s) >= 2 and pt.part != "strategic":
                ax.axvline(float(pt.t_s[0]), color=PART_COLOURS[pt.part], lw=1.0, alpha=0.9)
    axes[-1, 0].set_xlabel("mission time [s]")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    handles += [Patch(color=ALERT_COLOURS[a], label=f"alert: {a}") for a in ALERT_LEVELS[1:]]
    handles += [plt.Line2D([], [], color=PART_COLOURS[p], label=f"start of {p}")
                for p in dict.fromkeys(pt.part for pt in log.parts if pt.part != "strategic")]
    fig.legend(handles=handles, loc="outside lower center", ncol=4, fontsize=8, frameon=False)
    fig.savefig(path)
    plt.close(fig)
    return path
