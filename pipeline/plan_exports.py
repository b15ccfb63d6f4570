"""Pilot exports of the chosen plan (``skyroute plan`` and ``skyroute run``): ``plan.kml``,
``plan.plan`` (QGroundControl), ``plan.gpkg`` and ``intent.json`` (the ASTM F3548
OperationalIntentDetails of the plan), beside plan.geojson (which keeps the surface datum).

Absolute heights come from :func:`scenario_height_reference` (the surface model's vertical
datum, or ``data.ground``).  When they cannot be had (local ground without ``data.ground``, a
datum without a conversion, no geoid grid on disk) ``plan.kml`` and ``intent.json`` are not
written, ``plan.plan`` gets home altitude 0 m, the GeoPackage has no intents layer, and
:func:`pilot_export_notes` says why: summary.json ``exports.notes`` and ``warnings`` (so
``warning: plan.kml not written: ...`` on stderr and in report.html).  Every shipped scenario
has absolute heights (``data.ground`` or a geoid-referenced DEM)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from skyroute.pipeline.errors import SkyrouteError
from skyroute.pipeline.graph import RunResult, stage_attrs
from skyroute.stages.geoid import HeightReference, height_reference

__all__ = ["INTENT_TIME_BUFFER_S", "export_key", "exports_section", "intent_summary", "pilot_export_notes", "scenario_height_reference", "write_pilot_exports"]

INTENT_TIME_BUFFER_S = 5.0    # [s] before and after each volume
INTENT_MAX_VOLUME_S = 30.0    # [s] longest volume
MAP_LAYER_MAX_CELLS = 4_000_000   # the GeoPackage's building layer only for maps up to this size


def scenario_height_reference(scenario, surface_datum: str) -> HeightReference:
    """The :class:`~skyroute.stages.geoid.HeightReference` of a scenario whose surface model
    is in ``surface_datum`` (``data.ground`` when given); InputError naming ``data.ground``."""
    g = scenario.data.ground
    return height_reference(surface_datum, g.height_m if g else None, g.vertical_datum if g else None)


def _reference_or_reason(result: RunResult) -> tuple[HeightReference | None, str | None]:
    try:
        ref = scenario_height_reference(result.scenario, str(stage_attrs(result, "plan").get("vertical_datum", "")))
        ref.ellipsoidal_m(0.0, 0.0, 0.0)   # the geoid grid is on disk
        return ref, None
    except SkyrouteError as exc:
        return None, str(exc)


def pilot_export_notes(result: RunResult) -> list[str]:
    """Why plan.kml / intent.json were not written (empty when they were or no plan flies)."""
    if "plan" not in result.datasets or int(stage_attrs(result, "plan").get("chosen_level", -1)) < 0:
        return []
    _, why = _reference_or_reason(result)
    if why is not None:
        return [f"plan.kml not written (nor intent.json; plan.plan gets home altitude 0 m): {why}"]
    if not _has_sigma(result["plan"]):
        return ["intent.json not written: the plan has no predicted navigation error sigma_p (no GNSS "
                "data: data.almanacs), which sizes the intent's volumes"]
    return []


def _has_sigma(plan) -> bool:
    return "sigma_p_m" in plan and bool(np.all(np.isfinite(np.asarray(plan["sigma_p_m"].values, float))))


def export_key(result: RunResult) -> str:
    """Hash of what the exports depend on beyond the plan stage's key: ``data.ground``, the
    buffers (``constraints.sboa_k``, the vehicle's ``safety_distance_m``, the intent time
    constants) and whether absolute heights are available (a geoid grid installed later)."""
    from skyroute.pipeline.model import stable_hash

    sc = result.scenario
    g = sc.data.ground
    # why absolute heights are missing (None: they are not), from the plan's attributes and the
    # geoid grids on disk; the rest of :func:`pilot_export_notes` (no sigma_p) follows the plan
    # stage's key, so the plan's data is not read here (a warm run reads no dataset)
    flies = "plan" in result.datasets and int(stage_attrs(result, "plan").get("chosen_level", -1)) >= 0
    why = _reference_or_reason(result)[1] if flies else None
    return stable_hash("pilot-exports-2", None if g is None else (g.height_m, g.vertical_datum),
                       sc.constraints.sboa_k, INTENT_TIME_BUFFER_S, INTENT_MAX_VOLUME_S, why)


def exports_section(result: RunResult, files: list[str], out_dir: Path | None = None) -> dict:
    """summary.json ``exports``: the pilot export ``files`` written (of ``files``, paths
    relative to ``out_dir``), the ``notes`` of :func:`pilot_export_notes` and, when
    ``intent.json`` was written, ``intent``: its ``volumes``, ``vertices``, ``time_start`` /
    ``time_end`` and ``conformance`` (:func:`intent_conformance`: share of the exact trajectory,
    sampled every 0.05 s, inside the volumes; 1.0 by construction)."""
    names = ("plan.kml", "plan.plan", "plan.gpkg", "intent.json")
    sec: dict = {"files": sorted(f for f in files if f.rsplit("/", 1)[-1] in names),
                 "notes": pilot_export_notes(result)}
    intent_file = next((f for f in sec["files"] if f.endswith("intent.json")), None)
    if intent_file is not None and out_dir is not None:
        sec["intent"] = intent_summary(result, json.loads((Path(out_dir) / intent_file).read_text()))
    return sec


def intent_summary(result: RunResult, intent: dict) -> dict:
    """Size, time span and measured conformance of the plan's ``intent`` (see :func:`exports_section`)."""
    import pandas as pd
    from pyproj import Transformer

    from skyroute.stages.intents import intent_conformance, plan_path

    ds = result["plan"]
    traj, t0 = plan_path(ds)
    ref, _ = _reference_or_reason(result)
    tau = np.append(np.arange(0.0, traj.duration_s, 0.05), traj.duration_s)
    p = traj.sample(tau)
    lon, lat = Transformer.from_crs(ds.attrs["crs"], 4326, always_xy=True).transform(p[:, 0], p[:, 1])
    t = pd.Timestamp(ds.attrs["start_time_utc"]) + pd.to_timedelta(t0 + tau, unit="s")
    vols = intent["volumes"]
    return {"volumes": len(vols), "vertices": sum(len(v["volume"]["outline_polygon"]["vertices"]) for v in vols),
            "time_start": min(v["time_start"]["value"] for v in vols),
            "time_end": max(v["time_end"]["value"] for v in vols),
            "conformance": intent_conformance(intent, lon, lat, ref.ellipsoidal_m(lon, lat, p[:, 2]), t)}


def write_pilot_exports(result: RunResult, out_dir: Path) -> dict[str, Path]:
    """Write the pilot exports of the chosen plan of ``result`` to ``out_dir``; returns the
    paths by file name (nothing when no plan flies)."""
    from pyproj import Transformer

    from skyroute.stages.exports import (
        arrival_loiter,
        chord_deviation,
        lon_near,
        plan_kml,
        qgc_plan,
        write_json,
        write_plan_gpkg,
    )
    from skyroute.stages.intents import parse_intent, plan_intent
    from skyroute.stages.planning.step3 import utc_of
    from skyroute.stages.vehicle import load_vehicle

    ds = result["plan"].load()
    if int(ds.attrs.get("chosen_level", -1)) < 0:
        return {}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sc = result.scenario
    veh = load_vehicle(sc.vehicle)
    ref, _ = _reference_or_reason(result)
    to_ll = Transformer.from_crs(ds.attrs["crs"], 4326, always_xy=True)
    x, y, z = (np.asarray(ds[k].values, float) for k in ("x_m", "y_m", "z_m"))
    lon, lat = (np.asarray(a) for a in to_ll.transform(x, y))
    times = utc_of(ds.attrs["start_time_utc"], ds["t_s"].values)
    home_z = float(z[0] - float(ds["alt_agl_m"].values[0]))       # ground under the start, surface datum
    wp = np.asarray(ds["waypoints"].values, float)
    wlon, wlat = (np.asarray(a) for a in to_ll.transform(wp[:, 0], wp[:, 1]))
    files: dict[str, Path] = {}
    label = str(ds["label"].values[int(ds.attrs["chosen_level"])])
    home_amsl = 0.0
    intent = None
    wabs = None
    if ref is not None:
        home_amsl = float(ref.egm96_m(lon[0], lat[0], home_z))
        wabs = ref.egm96_m(wlon, wlat, wp[:, 2])
        files["plan.kml"] = out / "plan.kml"
        files["plan.kml"].write_text(plan_kml(lon, lat, ref.egm96_m(lon, lat, z), times, f"skyroute {sc.name} {label}",
                                              f"Surface datum of the plan: {ds.attrs.get('vertical_datum', '')}."))
    if ref is not None and _has_sigma(ds):
        _, intent = plan_intent(ds, ref.ellipsoidal_m, vehicle_radius_m=veh.safety_distance_m,
                                k_sigma=sc.constraints.sboa_k, time_buffer_s=INTENT_TIME_BUFFER_S,
                                max_volume_s=INTENT_MAX_VOLUME_S)
        parse_intent(intent)   # F3548 schema and limits
        files["intent.json"] = write_json(out / "intent.json", intent)
    fixed_wing, landing, flown = veh.kind == "fixed-wing", None, np.column_stack([x, y, z])
    if fixed_wing:     # the arrival loiter becomes the mission's landing pattern (stages/exports.py)
        lo = arrival_loiter(flown, wp)
        flown = flown if lo is None else flown[:lo[0] + 1]
        landing = {"ground_rel_m": float(z[-1] - ds["alt_agl_m"].values[-1]) - home_z,
                   "loiter_radius_m": lo[1] if lo else veh.turn_radius_at(veh.cruise_speed_mps),
                   "clockwise": lo[2] if lo else True, "descent_angle_deg": float(veh.max_descent_angle_deg)}
    files["plan.plan"] = write_json(out / "plan.plan", qgc_plan(wlon, wlat, wp[:, 2] - home_z, home_amsl,
                                                                cruise_speed_mps=veh.cruise_speed_mps,
                                                                fixed_wing=fixed_wing, landing=landing,
                                                                metadata=chord_deviation(wp, flown)))
    buildings = None
    if "surface" in result.datasets and sc.grid.nx * sc.grid.ny <= MAP_LAYER_MAX_CELLS:
        from skyroute.stages.exports import building_footprints

        surf = result["surface"]
        buildings = building_footprints(surf["building_id"].values, surf["surface"].values, sc.grid.transform,
                                        sc.grid.crs)
    b = sc.grid.bounds
    cx, cy = to_ll.transform([b[0], b[2], b[2], b[0]], [b[1], b[1], b[3], b[3]])
    cx = lon_near(cx, float(lon[0]))     # continuous around the plan (a map across the antimeridian)
    files["plan.gpkg"] = write_plan_gpkg(out / "plan.gpkg", lon_deg=lon, lat_deg=lat, z_m=z,
                                         vertical_datum=str(ds.attrs.get("vertical_datum", "")), times_utc=times,
                                         label=label, waypoints_lonlat_z=np.column_stack([wlon, wlat, wp[:, 2]]),
                                         waypoints_rel_m=wp[:, 2] - home_z, waypoints_abs_m=wabs, intent=intent,
                                         aoi_lonlat=(min(cx), min(cy), max(cx), max(cy)), buildings=buildings)
    return files
