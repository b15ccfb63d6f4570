"""Plan outputs: GeoJSON, CSV tables and PNG figures of the STEP III result.

* ``plan.geojson``: RFC 7946 FeatureCollection.  Feature 1 is the chosen trajectory as a
  ``LineString`` of ``[lon, lat, altitude]`` (WGS 84, altitude [m] in the surface's vertical
  datum).  RFC 7946 altitudes are ellipsoidal heights, which the maps do not give: the feature
  properties state ``vertical_datum`` and ``heights_are_ellipsoidal: false``.  Its properties
  also carry ``times_utc`` (ISO 8601 UTC per vertex), ``t_s``, ``alt_agl_m``, ``sigma_p_m``
  and the map-CRS coordinates (``map_crs``, ``map_xyz_m``: [x, y, z] per vertex); feature 2
  is a ``MultiPoint`` of the trajectory's piece boundaries (same conventions).  A path across
  the antimeridian stays one LineString with continuous longitudes (past 180 or -180; RFC 7946
  section 3.1.9 would cut it, which would break the one-to-one match of its vertices and
  per-vertex properties), ``crosses_antimeridian: true`` (see :mod:`skyroute.stages.exports`).
* ``waypoints.csv``: one row per trajectory sample: ``t_utc, t_s, x_m, y_m, z_m, lon, lat,
  alt_agl_m, sigma_p_m``; ``t_s`` and the map coordinates at full float precision (shortest
  round-trip repr), so the written samples meet the vehicle limits exactly (mm / ms rounding
  alone makes a 0.1 s chord look 0.01 deg steeper or 0.2 m/s^2 harder than it is).
* ``candidates.csv``: one row per candidate D_j (seed 000 Tables II-III): ``label,
  dop_threshold, C_l_m, C_r_m, C_d_m, C_e_m, f_m, flyable, max_sigma_p_m, energy_Wh,
  flight_time_s, compute_time_s, chosen, reasons``.  ``f_m`` is seed 000 eq. 11 with the
  scenario's weights, ``w_l C_l + w_r C_r + w_d C_d + w_e C_e``, on the written trajectory, for
  every planner (:func:`~skyroute.stages.planning.step3.trajectory_costs`); a planner whose
  search minimises something else (the fixed-wing planners) adds ``search_cost_m`` (that
  objective [m]) and ``search_objective`` (its definition).
* ``top_view.png``, ``profile.png``, ``sigma_p.png`` and, given the bubble parameters,
  ``bubble.png`` (matplotlib Agg).
"""

from __future__ import annotations

import csv
import json
import math
import textwrap
from pathlib import Path

import numpy as np
from pyproj import CRS, Transformer

from skyroute.stages.base import InputError
from skyroute.stages.exports import continuous_lon, crosses_antimeridian, lon_near
from skyroute.stages.figures import GOAL_STYLE, START_STYLE, add_map_furniture
from skyroute.stages.grid import Grid
from skyroute.stages.planning.step3 import Candidate, utc_of

__all__ = ["write_plan", "plan_geojson", "CANDIDATE_COLUMNS", "PROVENANCE_COLUMNS", "SEARCH_COLUMNS", "WAYPOINT_COLUMNS"]

WAYPOINT_COLUMNS = ("t_utc", "t_s", "x_m", "y_m", "z_m", "lon", "lat", "alt_agl_m", "sigma_p_m")
CANDIDATE_COLUMNS = ("label", "dop_threshold", "C_l_m", "C_r_m", "C_d_m", "C_e_m", "f_m", "flyable",
                     "max_sigma_p_m", "energy_Wh", "flight_time_s", "compute_time_s", "chosen", "reasons")
# appended to candidates.csv when a planner's search objective is not f (the fixed-wing planners):
# its value [m] and its definition (f is eq. 11 on the written trajectory for every planner)
SEARCH_COLUMNS = ("search_cost_m", "search_objective")
# appended to candidates.csv when the plan's provenance is known (the plan stage records it)
PROVENANCE_COLUMNS = ("planner", "seed", "weights", "time_budget_s", "skyroute_version")


def crs_of(grid_or_crs) -> tuple[CRS, Grid | None]:
    """(CRS, Grid or None) of a :class:`Grid` or anything ``pyproj.CRS`` reads; InputError if neither."""
    if isinstance(grid_or_crs, Grid):
        return grid_or_crs.crs, grid_or_crs
    try:
        return CRS.from_user_input(grid_or_crs), None
    except Exception as exc:
        raise InputError(f"cannot resolve CRS {grid_or_crs!r}: {exc}") from exc


def _num(v: float) -> float | None:
    return None if v is None or not math.isfinite(float(v)) else float(v)


def plan_geojson(candidate: Candidate, grid_or_crs, start_time_utc, vertical_datum: str,
                 provenance: dict | None = None) -> dict:
    """The RFC 7946 FeatureCollection of ``candidate`` (see module docstring); ``provenance``
    (how the plan was made: planner, seed, weights, budgets, version) goes into feature 0's
    properties."""
    if candidate.xyz_m.shape[0] < 2:
        raise InputError(f"candidate {candidate.label!r} has no trajectory to write")
    crs, _ = crs_of(grid_or_crs)
    tr = Transformer.from_crs(crs, 4326, always_xy=True)
    p = candidate.xyz_m
    lon, lat = tr.transform(p[:, 0], p[:, 1])
    lon = continuous_lon(lon)   # across the antimeridian: one continuous line (longitudes may pass 180)
    coords = [[float(a), float(b), float(z)] for a, b, z in zip(lon, lat, p[:, 2], strict=True)]
    epsg = crs.to_epsg()
    crs_txt = f"EPSG:{epsg}" if epsg is not None else crs.to_wkt()
    note = (f"altitudes are in the vertical datum '{vertical_datum}' of the surface model; heights are NOT "
            "ellipsoidal (RFC 7946 expects ellipsoidal heights)")
    props = {
        "name": f"skyroute plan {candidate.label}",
        "label": candidate.label,
        "dop_threshold": _num(candidate.dop_threshold) if candidate.dop_threshold is not None else None,
        "vertical_datum": vertical_datum,
        "heights_are_ellipsoidal": False,
        "altitude_note": note,
        "start_time_utc": utc_of(start_time_utc, [0.0])[0],
        "times_utc": utc_of(start_time_utc, candidate.t_s),
        "t_s": [float(v) for v in candidate.t_s],
        "alt_agl_m": [float(v) for v in candidate.alt_agl_m],
        "sigma_p_m": [_num(v) for v in candidate.sigma_p_m],
        "map_crs": crs_txt,
        "crosses_antimeridian": crosses_antimeridian(lon),   # then longitudes run past +-180, unwrapped
        "map_xyz_m": [[float(a), float(b), float(c)] for a, b, c in p],
        "C_l_m": _num(candidate.C_l), "C_r_m": _num(candidate.C_r), "C_d_m": _num(candidate.C_d),
        "C_e_m": _num(candidate.C_e), "f_m": _num(candidate.f), "flyable": bool(candidate.flyable),
        "max_sigma_p_m": _num(candidate.max_sigma_p_m), "energy_Wh": _num(candidate.energy_Wh),
        "flight_time_s": _num(candidate.flight_time_s),
    }
    if provenance:
        props["provenance"] = provenance
    features = [{"type": "Feature", "geometry": {"type": "LineString", "coordinates": coords}, "properties": props}]
    wp = np.asarray(candidate.waypoints, float)
    if wp.shape[0]:
        wl, wa = tr.transform(wp[:, 0], wp[:, 1])
        wl = lon_near(wl, float(lon[0]))
        knots = np.concatenate([[0.0], np.cumsum(candidate.segment_times_s)]) + float(candidate.t_s[0])
        features.append({"type": "Feature",
                         "geometry": {"type": "MultiPoint",
                                      "coordinates": [[float(a), float(b), float(z)]
                                                      for a, b, z in zip(wl, wa, wp[:, 2], strict=True)]},
                         "properties": {"name": "trajectory piece boundaries", "vertical_datum": vertical_datum,
                                        "heights_are_ellipsoidal": False, "map_crs": crs_txt,
                                        "map_xyz_m": wp.tolist(), "times_utc": utc_of(start_time_utc, knots),
                                        "t_s": knots.tolist()}})
    return {"type": "FeatureCollection", "features": features}


def write_csv(path: Path, header, rows) -> None:
    """Write ``rows`` under ``header`` to the CSV file ``path``."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)


def _fmt(v, nd=3) -> str:
    if v is None:
        return ""
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    v = float(v)
    return "nan" if not math.isfinite(v) else f"{v:.{nd}f}"


def write_plan(candidate: Candidate | None, candidates: list[Candidate], grid_or_crs, out_dir, start_time_utc,
               vertical_datum: str, *, surface_m=None, terrain_m=None, floor_m=None, cost_m=None,
               cost_label: str = "cost [-]",
               figures: bool = True, bubble: tuple[float, float, float] | None = None,
               provenance: dict | None = None, profile: dict | None = None) -> dict[str, Path]:
    """Write ``plan.geojson``, ``waypoints.csv``, ``candidates.csv`` and the figures to ``out_dir``.
    ``provenance``: how the plan was made (the plan stage's ``provenance`` attribute): in
    plan.geojson's properties and as the :data:`PROVENANCE_COLUMNS` of candidates.csv.

    ``candidate``: the chosen one (:func:`~skyroute.stages.planning.step3.choose`) or None (no
    flyable plan: only ``candidates.csv`` is written, with every reason).  ``grid_or_crs``: the
    scenario :class:`~skyroute.stages.grid.Grid` (needed for the map figures) or a CRS.
    ``start_time_utc``: UTC of mission time 0.  Optional (ny, nx) rasters for the figures:
    ``surface_m`` / ``terrain_m`` (profile), ``floor_m`` (lowest admissible altitude, e.g. the
    coverage floor), ``cost_m`` (dimensionless cost map for the top view).  ``bubble``: (k,
    surface uncertainty [m], r_p [m]) for ``bubble.png``, the safety bubble
    ``max(r_p, k sigma_p + surface uncertainty)`` along the chosen trajectory (seed 003).
    ``profile``: optional ``{"surface", "terrain", "floor"}`` arrays [m], one value per point of
    ``candidate``, drawn in the profile instead of the rasters' cells under its points (a city's
    figures are drawn over block maxima: the profile keeps the full-resolution values).
    Returns the paths.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    crs, grid = crs_of(grid_or_crs)
    files: dict[str, Path] = {}
    rows = []
    for c in candidates:
        rows.append([c.label, _fmt(c.dop_threshold, 2), _fmt(c.C_l, 1), _fmt(c.C_r, 1), _fmt(c.C_d, 1),
                     _fmt(c.C_e, 1), _fmt(c.f, 1), _fmt(bool(c.flyable)), _fmt(c.max_sigma_p_m, 3),
                     _fmt(c.energy_Wh, 2), _fmt(c.flight_time_s, 1), _fmt(c.compute_time_s, 2),
                     _fmt(candidate is not None and c is candidate), "; ".join(c.reasons)])
    cols = CANDIDATE_COLUMNS
    radii = [float(getattr(c, "clearance_radius_m", math.nan)) for c in candidates]
    if any(math.isfinite(r) for r in radii):   # safety bubble levels (sboa)
        cols = (*cols, "clearance_radius_m")
        rows = [[*row, _fmt(r, 2)] for row, r in zip(rows, radii, strict=True)]
    searched = [float(getattr(c, "search_cost_m", math.nan)) for c in candidates]
    if any(math.isfinite(v) for v in searched):   # the planner's own objective is not f (fixed-wing)
        cols = (*cols, *SEARCH_COLUMNS)
        rows = [[*row, _fmt(v, 1), getattr(c, "search_objective", "")]
                for row, v, c in zip(rows, searched, candidates, strict=True)]
    if provenance:
        cols = (*cols, *PROVENANCE_COLUMNS)
        prov = [provenance.get("planner", ""), provenance.get("seed", ""),
                ";".join(f"{float(w):g}" for w in provenance.get("weights", ())),
                provenance.get("time_budget_s", ""), provenance.get("skyroute_version", "")]
        rows = [[*row, *prov] for row in rows]
    files["candidates.csv"] = out / "candidates.csv"
    write_csv(files["candidates.csv"], cols, rows)
    if candidate is None:
        return files
    gj = plan_geojson(candidate, grid_or_crs, start_time_utc, vertical_datum, provenance)
    files["plan.geojson"] = out / "plan.geojson"
    files["plan.geojson"].write_text(json.dumps(gj, indent=1, allow_nan=False))
    tr = Transformer.from_crs(crs, 4326, always_xy=True)
    p = candidate.xyz_m
    lon, lat = tr.transform(p[:, 0], p[:, 1])
    utc = utc_of(start_time_utc, candidate.t_s)
    wrows = [[utc[i], repr(float(candidate.t_s[i])), repr(float(p[i, 0])), repr(float(p[i, 1])), repr(float(p[i, 2])),
              f"{lon[i]:.9f}", f"{lat[i]:.9f}", f"{candidate.alt_agl_m[i]:.3f}", _fmt(candidate.sigma_p_m[i], 4)]
             for i in range(p.shape[0])]
    files["waypoints.csv"] = out / "waypoints.csv"
    write_csv(files["waypoints.csv"], WAYPOINT_COLUMNS, wrows)
    if figures:
        files.update(_figures(candidate, candidates, grid, out, vertical_datum, surface_m, terrain_m, floor_m,
                              cost_m, cost_label, profile))
        if bubble is not None:
            files["bubble.png"] = _bubble_figure(candidate, *bubble, out / "bubble.png")
    return files


def raster_values(a):
    """A raster (DataArray or array) as a float ndarray; None stays None."""
    return None if a is None else np.asarray(getattr(a, "values", a), dtype=float)


def _figures(cand, cands, grid, out, datum, surface_m, terrain_m, floor_m, cost_m,
             cost_label: str = "cost [-]", profile: dict | None = None) -> dict[str, Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from skyroute.stages.figures import colorbar_or_note, uniform_value

    files = {}
    p = cand.xyz_m
    # top view
    fig, ax = plt.subplots(figsize=(8, 6), dpi=100)
    if grid is not None:
        xmin, ymin, xmax, ymax = grid.bounds
        ext = (xmin, xmax, ymin, ymax)
        cm, fl = raster_values(cost_m), raster_values(floor_m)
        if cm is not None:
            im = ax.imshow(cm, extent=ext, cmap="YlOrRd", interpolation="nearest", alpha=0.8)
            u = uniform_value(cm)   # a uniform map gets a note, not a colour bar of a made-up range
            colorbar_or_note(fig, ax, im, cm, cost_label, f"{cost_label.split(' [')[0]}: {u:g} everywhere"
                             if u is not None else "no cost map", note_xy=(0.5, 0.05))   # off the path
        if fl is not None:
            ax.contour(np.linspace(xmin, xmax, grid.nx), np.linspace(ymax, ymin, grid.ny),
                       np.where(np.isfinite(fl), fl, np.nanmax(np.where(np.isfinite(fl), fl, np.nan)) + 50),
                       levels=8, colors="steelblue", linewidths=0.6)
            ax.plot([], [], color="steelblue", lw=0.6, label="admissible floor (contours)")
    for c in cands:
        if c.xyz_m.shape[0] and c is not cand:
            ax.plot(c.xyz_m[:, 0], c.xyz_m[:, 1], lw=1, alpha=0.6, label=f"{c.label} (f={c.f:.0f} m)")
    ax.plot(p[:, 0], p[:, 1], "k-", lw=2, label=f"chosen {cand.label} (f={cand.f:.0f} m)")
    ax.plot(p[0, 0], p[0, 1], **START_STYLE, label="start")
    ax.plot(p[-1, 0], p[-1, 1], **GOAL_STYLE, label="goal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.locator_params(axis="x", nbins=4)   # 6-7-digit eastings on a narrow map never run into each other
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=2)   # below the map
    ax.set_title("plan, top view")
    add_map_furniture(ax)
    fig.tight_layout()
    files["top_view.png"] = out / "top_view.png"
    fig.savefig(files["top_view.png"])
    plt.close(fig)
    # vertical profile
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1))])
    fig, ax = plt.subplots(figsize=(9, 4), dpi=100)
    if profile is None and grid is not None:
        row, col = grid.cell_of(p[:, 0], p[:, 1])
        profile = {k: raster_values(r)[row, col] for k, r in (("surface", surface_m), ("terrain", terrain_m),
                                                               ("floor", floor_m)) if r is not None}
    if profile is not None:
        bottom = [float(np.nanmin(profile[k])) for k in ("surface", "terrain") if k in profile]
        for k, style, lab in (("surface", dict(color="0.5", alpha=0.5), "surface (buildings)"),
                              ("terrain", dict(color="saddlebrown", alpha=0.6), "terrain")):
            if k in profile:
                ax.fill_between(dist, min(bottom) - 5, profile[k], step="mid", label=lab, **style)
        if "floor" in profile:
            fl = np.asarray(profile["floor"], float)
            ax.plot(dist, np.where(np.isfinite(fl), fl, np.nan), "b--", lw=1, label="admissible floor")
    ax.plot(dist, p[:, 2], "k-", lw=2, label=f"trajectory {cand.label}")
    ax.set_xlabel("horizontal distance along the path [m]")
    ax.set_ylabel("altitude [m]\n" + "\n".join(textwrap.wrap(datum, 32)[:2]), fontsize=8)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))   # beside the plot, never over it
    ax.set_title("vertical profile along the path")
    fig.tight_layout()
    files["profile.png"] = out / "profile.png"
    fig.savefig(files["profile.png"])
    plt.close(fig)
    # sigma_p
    fig, ax = plt.subplots(figsize=(9, 3.5), dpi=100)
    for c in cands:
        if c.xyz_m.shape[0] and np.isfinite(c.sigma_p_m).any():
            ax.plot(c.t_s, c.sigma_p_m, lw=2 if c is cand else 1, label=c.label)
    dp = getattr(cand, "dp_max_m", None)
    if dp is not None and np.isfinite(dp):
        ax.axhline(dp, color="r", ls="--", label=f"dp_max = {dp:g} m")
        top = max([dp] + [float(np.nanmax(c.sigma_p_m)) for c in cands
                          if c.xyz_m.shape[0] and np.isfinite(c.sigma_p_m).any()])
        ax.set_ylim(0.0, 1.1 * top)
    ax.set_xlabel("mission time [s]")
    ax.set_ylabel("sigma_p [m]")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7)
    else:   # no GNSS data, or a fixed-wing plan (its navigation error is not evaluated)
        ax.text(0.5, 0.5, "navigation error not evaluated for these candidates", ha="center", va="center",
                transform=ax.transAxes)
    ax.set_title("predicted navigation error along the trajectories")
    fig.tight_layout()
    files["sigma_p.png"] = out / "sigma_p.png"
    fig.savefig(files["sigma_p.png"])
    plt.close(fig)
    return files


def _bubble_figure(cand: Candidate, k: float, surface_uncertainty_m: float, r_p_m: float, path: Path) -> Path:
    """The safety bubble along ``cand``: r_phi = k sigma_p + surface uncertainty
    (:func:`~skyroute.stages.navsim.bubble_radius_m`), the collision sphere r_p and the
    level's clearance radius r_j (``constraints.clearance: sboa``) [m] against mission time [s]."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from skyroute.stages.sboa import bubble_radius_m

    t = np.asarray(cand.t_s, float)
    r_phi = bubble_radius_m(np.asarray(cand.sigma_p_m, float), k, surface_uncertainty_m)
    fig, ax = plt.subplots(figsize=(9, 3.5), dpi=100)
    ax.plot(t, r_phi, "k-", lw=1.5, label=f"r_phi = {k:g} sigma_p + {surface_uncertainty_m:g} m")
    ax.plot(t, np.maximum(r_phi, r_p_m), color="tab:red", lw=2.5, alpha=0.5,
            label="safety bubble max(r_p, r_phi)")
    ax.axhline(r_p_m, color="tab:blue", ls="--", lw=1, label=f"collision sphere r_p = {r_p_m:.2f} m")
    r_j = float(getattr(cand, "clearance_radius_m", math.nan))
    if math.isfinite(r_j):
        ax.axhline(r_j, color="tab:green", ls=":", lw=1.5, label=f"level clearance r_j = {r_j:.2f} m")
    finite = r_phi[np.isfinite(r_phi)]
    top = max([r_p_m, r_j if math.isfinite(r_j) else 0.0] + ([float(finite.max())] if finite.size else []))
    ax.set_ylim(0.0, 1.25 * top)
    ax.set_xlabel("mission time [s]")
    ax.set_ylabel("radius [m]")
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title(f"safety bubble along the chosen trajectory {cand.label}")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
