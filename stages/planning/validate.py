"""Independent check of a planned trajectory against the maps (no planner code reused).

:func:`validate_plan` re-derives every bound of seed 000 section III-A.3 from the raster arrays
and the raw intruder tracks with its own, deliberately simple code, and returns **every**
violation as a readable string (an empty list means the plan is valid):

* inside the grid; times finite and strictly increasing;
* clearance floor (fixed obstacles dilated by the vehicle radius, :mod:`~skyroute.stages.clearance`),
  GNSS coverage floor (``D_j``), any combined floor, AGL minimum / maximum, no-fly cells: the
  altitude of each sample against the cell that contains it (the planners' nearest-cell
  convention; the ``"cell"`` clearance floor is conservative anywhere in the cell);
* fixed-wing vehicles (:class:`~skyroute.stages.vehicle.FixedWingProfile`): climb and descent
  angles of every chord against their own limits, the bank a turn needs
  (:func:`turn_radius_violations`: ``atan(v^2 / (g rho))`` from the circumradius ``rho`` of
  three consecutive samples and their ground speed ``v``) against ``max_bank_deg``, and the
  airspeed of every chord >= the stall speed at sea level; the rotorcraft's vertical-rate and
  acceleration limits do not apply;
* flight-path angle of every chord between consecutive samples <= ``alpha`` (tolerance
  ``tol_deg``, numerical only); chords with less than :data:`MIN_HORIZONTAL_M` of horizontal
  motion are exempt (a hover or a stop has no defined angle) but obey the vertical rates;
* vertical speed of every chord ``dz / dt`` within ``[-max_descent_rate_mps, max_climb_rate_mps]``
  (chord speeds: plus the float rounding of the difference, 4 eps |p| / dt);
* acceleration: twice the second divided difference of three consecutive samples, a weighted
  mean of the trajectory's acceleration over their interval (Peano kernel of mass 1, so its
  norm cannot exceed the maximum of |a|), must not exceed ``max_acceleration_mps2`` (plus
  the float rounding of the difference, ~8 eps |p| / dt^2);
* wind: |wind| <= ``max_wind_mps`` at every sample; airspeed |v - w| <= ``max_airspeed_mps``
  (v the chord's mean velocity, w the wind at its first sample);
* traffic (seed 000 eq. 1 without the slicing): at each sample time ``t`` the position must be
  farther than ``r_i + d_c`` from every point intruder ``i`` occupies during
  ``[t - dt_c, t + dt_c]`` (exact point-to-polyline distance on the linearly interpolated
  intruder track, brute force over all intruders);
* energy <= battery * (1 - ``battery_reserve_pct`` / 100) and sigma_p <= dp_max when the
  candidate carries them.

A candidate is any object with ``t_s`` (m,) [s since mission start] and ``xyz_m`` (m, 3) [m]
(e.g. :class:`~skyroute.stages.planning.step3.Candidate`), or a tuple ``(t_s, xyz_m)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping

import numpy as np

from skyroute.stages.base import InputError
from skyroute.stages.grid import Grid
from skyroute.stages.traffic import Intruder, intruders_from_records
from skyroute.stages.vehicle import G0, FixedWingProfile, VehicleProfile, load_vehicle

__all__ = ["intruder_clearance_m", "surface_clearance_m", "turn_radius_violations", "validate_bubble", "validate_plan"]

_MAX_LISTED = 5  # sample indices quoted per violation
MIN_HORIZONTAL_M = 2.0  # [m] chords with less horizontal motion are exempt from the angle limit


def _raster(a, grid: Grid, what: str) -> np.ndarray | None:
    if a is None:
        return None
    v = np.asarray(getattr(a, "values", a), dtype=float)
    if v.shape != grid.shape:
        raise InputError(f"{what} has shape {v.shape}, the grid is {grid.shape} (y, x)")
    return v


def _samples(candidate) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(candidate, tuple):
        t, p = candidate
    else:
        t, p = getattr(candidate, "t_s", None), getattr(candidate, "xyz_m", None)
    if t is None or p is None:
        raise InputError("validate_plan needs a candidate with t_s (m,) and xyz_m (m, 3), or a tuple (t_s, xyz_m)")
    t = np.asarray(t, dtype=float).reshape(-1)
    p = np.asarray(p, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] != t.size:
        raise InputError(f"trajectory samples need t_s (m,) and xyz_m (m, 3); got {t.shape} and {p.shape}")
    return t, p


def _where(mask: np.ndarray, t: np.ndarray, p: np.ndarray) -> str:
    idx = np.nonzero(mask)[0]
    first = ", ".join(f"#{i} t={t[i]:.1f} s ({p[i, 0]:.1f}, {p[i, 1]:.1f}, {p[i, 2]:.1f})" for i in idx[:_MAX_LISTED])
    more = f" and {idx.size - _MAX_LISTED} more" if idx.size > _MAX_LISTED else ""
    return f"{idx.size} sample(s): {first}{more}"


def _point_polyline_d2(q: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared distance of points q (m,3) to segments a-b (m,k,3) -> (m,k)."""
    d = b - a
    l2 = np.einsum("mkj,mkj->mk", d, d)
    s = np.einsum("mkj,mkj->mk", q[:, None, :] - a, d)
    s = np.clip(np.divide(s, l2, out=np.zeros_like(s), where=l2 > 0), 0.0, 1.0)
    c = a + s[..., None] * d - q[:, None, :]
    return np.einsum("mkj,mkj->mk", c, c)


def intruder_clearance_m(t_s, xyz_m, intruder: Intruder, dt_c_s: float) -> np.ndarray:
    """Distance [m] of each sample (t_s (m,), xyz_m (m, 3)) to the set of points the intruder
    occupies during ``[t - dt_c, t + dt_c]`` (its linearly interpolated track, only while it
    exists); +inf where it does not exist in that window."""
    t = np.asarray(t_s, float).reshape(-1)
    q = np.asarray(xyz_m, float).reshape(-1, 3)
    ti, pi = intruder.times_s, intruder.xyz_m
    a = np.maximum(t - dt_c_s, ti[0])
    b = np.minimum(t + dt_c_s, ti[-1])
    out = np.full(t.size, np.inf)
    alive = a <= b
    if not alive.any():
        return out

    def pos(tau):
        return np.stack([np.interp(tau, ti, pi[:, j]) for j in range(3)], axis=-1)

    # window [a, b] cut at the intruder's waypoint times: pieces between consecutive knots
    knots = np.concatenate([a[:, None], np.broadcast_to(ti, (t.size, ti.size)), b[:, None]], axis=1)
    knots = np.sort(np.clip(knots, a[:, None], b[:, None]), axis=1)
    pa = pos(knots[:, :-1])
    pb = pos(knots[:, 1:])
    d2 = _point_polyline_d2(q, pa, pb).min(axis=1)
    out[alive] = np.sqrt(d2[alive])
    return out


def _wind_at(wind, pts: np.ndarray) -> np.ndarray | None:
    if wind is None:
        return None
    if callable(wind):
        w = np.asarray(wind(pts), dtype=float)
    else:
        w = np.broadcast_to(np.asarray(wind, dtype=float), pts.shape)
    if w.shape != pts.shape:
        raise InputError(f"wind must be a (3,) vector [m/s] or a callable points (m, 3) -> (m, 3); got {w.shape}")
    return w


def validate_plan(candidate, *, grid: Grid, terrain_m, vehicle: VehicleProfile | FixedWingProfile | str, terrain_min_m=None,
                  clearance_floor_m=None, gnss_floor_m=None, floor_m=None, ceiling_m=None,
                  min_agl_m: float | None = None, max_agl_m: float | None = None,
                  nofly=None, wind: np.ndarray | Callable | None = None,
                  intruders: Iterable[Intruder | Mapping] = (), d_c_m: float = 0.0, dt_c_s: float = 0.0,
                  start_xyz=None, goal_xyz=None, tol_m: float = 1e-6, tol_deg: float = 1e-6,
                  tol_mps: float = 1e-6, tol_mps2: float = 1e-6, battery_reserve_pct: float = 0.0) -> list[str]:
    """Every violation of the bounds by the trajectory samples of ``candidate`` (see module doc).

    Rasters (``(ny, nx)`` arrays or DataArrays on ``grid`` [m], datum of the surface):
    ``terrain_m`` (ground, for AGL; with ``terrain_min_m``, the lowest ground of each cell, the
    maximum AGL is checked against it), ``clearance_floor_m``, ``gnss_floor_m`` (NaN = no
    altitude has coverage: forbidden), ``floor_m`` / ``ceiling_m`` (any combined bounds),
    ``nofly`` (bool). ``min_agl_m`` / ``max_agl_m`` [m] default to the vehicle's altitude
    limits.  ``wind``: (3,) [m/s] or callable ``points (m,3) -> (m,3)``.  ``intruders``:
    :class:`~skyroute.stages.traffic.Intruder` or scenario records, with spatial margin
    ``d_c_m`` [m] and time margin ``dt_c_s`` [s].  ``start_xyz`` / ``goal_xyz``: expected end
    points (checked within 1 cm).  ``tol_*``: numerical tolerances only (vehicle limits are
    hard).  ``battery_reserve_pct`` [%]: energy reserve kept in the battery.  Returns a list
    of messages; empty = valid.
    """
    veh = load_vehicle(vehicle)
    t, p = _samples(candidate)
    out: list[str] = []
    if t.size == 0:
        return ["trajectory has no samples"]
    if not (np.isfinite(t).all() and np.isfinite(p).all()):
        return ["trajectory samples contain NaN or inf"]
    if t.size > 1 and np.any(np.diff(t) <= 0):
        out.append(f"times are not strictly increasing at {int(np.sum(np.diff(t) <= 0))} step(s)")
    terrain = _raster(terrain_m, grid, "terrain_m")
    cf = _raster(clearance_floor_m, grid, "clearance_floor_m")
    gf = _raster(gnss_floor_m, grid, "gnss_floor_m")
    fl = _raster(floor_m, grid, "floor_m")
    ce = _raster(ceiling_m, grid, "ceiling_m")
    # cell containing each sample (own arithmetic: x0 west edge, y1 north edge)
    col = np.floor((p[:, 0] - grid.x0) / grid.resolution_m).astype(np.int64)
    row = np.floor((grid.y1 - p[:, 1]) / grid.resolution_m).astype(np.int64)
    inside = (row >= 0) & (row < grid.ny) & (col >= 0) & (col < grid.nx)
    if not inside.all():
        out.append(f"outside the map: {_where(~inside, t, p)}")
    r, c, z = row[inside], col[inside], p[inside, 2]
    ti, pi = t[inside], p[inside]

    def below(name: str, ras: np.ndarray | None, nan_forbidden: bool) -> None:
        if ras is None:
            return
        v = ras[r, c]
        bad = ~(z >= v - tol_m) if nan_forbidden else (z < v - tol_m)   # NaN: forbidden / no bound
        if bad.any():
            gap = v[bad] - z[bad]
            worst = f"{float(np.nanmax(gap)):.2f} m" if np.isfinite(gap).any() else "no coverage at any altitude"
            out.append(f"below the {name} (by up to {worst}): {_where(bad, ti, pi)}")

    below("clearance floor", cf, False)
    below("GNSS coverage floor", gf, True)
    below("altitude floor", fl, False)
    if ce is not None:
        bad = z > ce[r, c] + tol_m
        if bad.any():
            out.append(f"above the altitude ceiling (by up to {float(np.max((z - ce[r, c])[bad])):.2f} m): "
                       f"{_where(bad, ti, pi)}")
    lo = veh.min_altitude_m if min_agl_m is None else float(min_agl_m)
    hi = veh.max_altitude_m if max_agl_m is None else float(max_agl_m)
    agl = z - terrain[r, c]
    bad = agl < lo - tol_m
    if bad.any():
        out.append(f"below the minimum altitude {lo} m AGL (lowest {float(agl[bad].min()):.2f} m): {_where(bad, ti, pi)}")
    if terrain_min_m is not None:
        agl = z - _raster(terrain_min_m, grid, "terrain_min_m")[r, c]
    bad = agl > hi + tol_m
    if bad.any():
        out.append(f"above the maximum altitude {hi} m AGL (highest {float(agl[bad].max()):.2f} m): {_where(bad, ti, pi)}")
    if nofly is not None:
        nf = np.asarray(getattr(nofly, "values", nofly), dtype=bool)
        if nf.shape != grid.shape:
            raise InputError(f"nofly has shape {nf.shape}, the grid is {grid.shape}")
        bad = nf[r, c]
        if bad.any():
            out.append(f"inside a no-fly zone: {_where(bad, ti, pi)}")
    # flight-path angle and vertical speed of the chords, acceleration of sample triples
    fixed = isinstance(veh, FixedWingProfile)
    if fixed and t.size > 1:
        d = np.diff(p, axis=0)
        h = np.hypot(d[:, 0], d[:, 1])
        ang = np.degrees(np.arctan2(d[:, 2], h))
        for name, bad, lim in (("climb", ang > veh.max_climb_angle_deg + tol_deg, veh.max_climb_angle_deg),
                               ("descent", -ang > veh.max_descent_angle_deg + tol_deg, veh.max_descent_angle_deg)):
            if bad.any():
                out.append(f"{name} angle above {lim} deg (up to {float(np.abs(ang[bad]).max()):.2f} deg) on chords "
                           f"starting at {_where(np.r_[bad, False], t, p)}")
        out.extend(turn_radius_violations(t, p, veh.max_bank_deg))
    if not fixed and t.size > 1:
        d = np.diff(p, axis=0)
        h = np.hypot(d[:, 0], d[:, 1])
        fpa = np.degrees(np.arctan2(np.abs(d[:, 2]), h))
        bad = (h >= MIN_HORIZONTAL_M) & (fpa > veh.max_flight_path_angle_deg + tol_deg)
        if bad.any():
            out.append(f"flight-path angle above {veh.max_flight_path_angle_deg} deg (up to {float(fpa[bad].max()):.2f} "
                       f"deg) on chords starting at {_where(np.r_[bad, False], t, p)}")
        dt = np.diff(t)
        scale = float(np.abs(p).max())
        with np.errstate(divide="ignore", invalid="ignore"):
            vz = d[:, 2] / dt
            tol_v = tol_mps + 4.0 * np.finfo(float).eps * scale / dt     # float rounding of the difference
        bad = ~(vz <= veh.max_climb_rate_mps + tol_v)
        if bad.any():
            out.append(f"climb rate above {veh.max_climb_rate_mps} m/s (up to {float(np.nanmax(vz)):.2f} m/s) on "
                       f"chords starting at {_where(np.r_[bad, False], t, p)}")
        bad = ~(vz >= -veh.max_descent_rate_mps - tol_v)
        if bad.any():
            out.append(f"descent rate above {veh.max_descent_rate_mps} m/s (up to {float(-np.nanmin(vz)):.2f} m/s) on "
                       f"chords starting at {_where(np.r_[bad, False], t, p)}")
        if t.size > 2:
            with np.errstate(divide="ignore", invalid="ignore"):
                v = d / dt[:, None]
                acc = 2.0 * (v[1:] - v[:-1]) / (dt[1:] + dt[:-1])[:, None]
                rnd = 16.0 * np.finfo(float).eps * scale / (dt[1:] * dt[:-1])
            an = np.linalg.norm(acc, axis=1)
            bad = ~(an <= veh.max_acceleration_mps2 + tol_mps2 + rnd)
            if bad.any():
                out.append(f"acceleration above {veh.max_acceleration_mps2} m/s^2 (up to {float(np.nanmax(an)):.2f} "
                           f"m/s^2) at {_where(np.r_[False, bad, False], t, p)}")
    w = _wind_at(wind, p)
    if w is not None:
        ws = np.linalg.norm(w, axis=1)
        bad = ws > veh.max_wind_mps + tol_mps
        if bad.any():
            out.append(f"wind above {veh.max_wind_mps} m/s (up to {float(ws.max()):.2f} m/s): {_where(bad, t, p)}")
        if t.size > 1:
            dt = np.diff(t)
            with np.errstate(divide="ignore", invalid="ignore"):
                v = np.diff(p, axis=0) / dt[:, None]
            air = np.linalg.norm(v - w[:-1], axis=1)
            with np.errstate(divide="ignore", invalid="ignore"):
                tol_v = tol_mps + 4.0 * np.finfo(float).eps * float(np.abs(p).max()) / dt
            if fixed:
                slow = ~(air >= veh.stall_speed_mps - tol_v)
                if slow.any():
                    out.append(f"airspeed below the stall speed {veh.stall_speed_mps:.2f} m/s (down to "
                               f"{float(np.nanmin(air)):.2f} m/s) on chords starting at {_where(np.r_[slow, False], t, p)}")
            bad = ~(air <= veh.max_airspeed_mps + tol_v)
            if bad.any():
                out.append(f"airspeed above {veh.max_airspeed_mps} m/s (up to {float(np.nanmax(air)):.2f} m/s) on chords "
                           f"starting at {_where(np.r_[bad, False], t, p)}")
    # traffic: brute force against every intruder
    items = list(intruders)
    recs = [i for i in items if not isinstance(i, Intruder)]
    intr = [i for i in items if isinstance(i, Intruder)] + (intruders_from_records(recs) if recs else [])
    for it in intr:
        dist = intruder_clearance_m(t, p, it, dt_c_s)
        need = it.radius_m + d_c_m
        bad = dist < need - tol_m
        if bad.any():
            out.append(f"inside the volume reserved to intruder {it.id!r} (closest {float(dist.min()):.2f} m < "
                       f"r + d_c = {need:.2f} m within +-{dt_c_s} s): {_where(bad, t, p)}")
    for name, want, idx in (("start", start_xyz, 0), ("goal", goal_xyz, -1)):
        if want is not None:
            err = float(np.linalg.norm(p[idx] - np.asarray(want, float)))
            if err > 0.01:
                out.append(f"trajectory {name} {p[idx].round(2).tolist()} is {err:.2f} m from the mission {name}")
    if not 0 <= battery_reserve_pct < 100:
        raise InputError(f"battery_reserve_pct {battery_reserve_pct} must be in [0, 100) [%]")
    usable = veh.battery_energy_j * (1.0 - battery_reserve_pct / 100.0)
    e = getattr(candidate, "energy_J", None)
    if e is not None and np.ndim(e) == 0 and math.isfinite(float(e)) and float(e) > usable:
        out.append(f"energy {float(e) / 3600:.1f} Wh exceeds the usable battery {usable / 3600:.1f} Wh "
                   f"({veh.battery_energy_j / 3600:.1f} Wh less the {battery_reserve_pct:g} % reserve)")
    sig = getattr(candidate, "sigma_p_m", None)
    if sig is not None and np.size(sig):
        s = np.asarray(sig, float)
        if np.isfinite(s).any() and np.nanmax(s) > veh.max_position_error_m:
            out.append(f"navigation error sigma_p {float(np.nanmax(s)):.2f} m exceeds dp_max "
                       f"{veh.max_position_error_m} m")
    return out


def turn_radius_violations(t_s, xyz_m, max_bank_deg: float, min_chord_m: float = 0.5, tol: float = 1e-6
                           ) -> list[str]:
    """Independent turn check of sampled flight: for each triple of consecutive samples (both
    chords >= ``min_chord_m`` horizontally) the horizontal circumradius ``rho`` and the mean
    ground speed ``v`` of the two chords need a bank ``atan(v^2 / (g rho))`` <= ``max_bank_deg``."""
    t = np.asarray(t_s, float)
    p = np.asarray(xyz_m, float)[:, :2]
    if len(p) < 3:
        return []
    a, b, c = p[:-2], p[1:-1], p[2:]
    ab, bc, ca = np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1), np.linalg.norm(a - c, axis=1)
    cross = np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.where(cross > 0, ab * bc * ca / (2 * cross), np.inf)
        v = (ab + bc) / (t[2:] - t[:-2])
        bank = np.degrees(np.arctan(v * v / (G0 * rho)))
    use = (ab >= min_chord_m) & (bc >= min_chord_m)
    bad = use & (bank > max_bank_deg * (1 + tol) + tol)
    if not bad.any():
        return []
    k = int(np.argmax(np.where(bad, bank, -1)))
    return [f"turn needs a bank of {bank[k]:.1f} deg > {max_bank_deg} deg (radius {rho[k]:.1f} m at "
            f"{v[k]:.1f} m/s ground speed) at t = {t[k + 1]:.1f} s ({int(bad.sum())} sample(s))"]


def surface_clearance_m(xyz_m, *, grid: Grid, surface_m, radius_m) -> np.ndarray:
    """Distance [m] from each point ``xyz_m`` (m, 3) to the nearest surface prism (cell footprint
    x (-inf, surface]) among the cells within ``radius_m`` [m] (scalar or (m,)) of it, by brute
    force over every such cell; +inf when none is that close.  Points inside a prism get 0."""
    q = np.asarray(xyz_m, float).reshape(-1, 3)
    r = np.broadcast_to(np.asarray(radius_m, float), (q.shape[0],))
    s = _raster(surface_m, grid, "surface_m")
    res = grid.resolution_m
    out = np.full(q.shape[0], np.inf)
    for i, (x, y, z) in enumerate(q):
        n = int(math.ceil(r[i] / res)) + 1
        col = int(math.floor((x - grid.x0) / res))
        row = int(math.floor((grid.y1 - y) / res))
        r0, r1 = max(row - n, 0), min(row + n + 1, grid.ny)
        c0, c1 = max(col - n, 0), min(col + n + 1, grid.nx)
        if r0 >= r1 or c0 >= c1:
            continue
        cx = grid.x0 + (np.arange(c0, c1) + 0.5) * res            # cell centres
        cy = grid.y1 - (np.arange(r0, r1) + 0.5) * res
        dx = np.maximum(np.abs(x - cx) - res / 2, 0.0)[None, :]
        dy = np.maximum(np.abs(y - cy) - res / 2, 0.0)[:, None]
        dz = np.maximum(z - s[r0:r1, c0:c1], 0.0)            # above the top, or 0 beside the prism
        d = np.sqrt(dx * dx + dy * dy + dz * dz)
        d = d[d <= r[i]]
        if d.size:
            out[i] = float(d.min())
    return out


def validate_bubble(candidate, *, grid: Grid, surface_m, radius_m, tol_m: float = 1e-6) -> list[str]:
    """Safety bubble check (seed 003): every sample of ``candidate`` (``t_s``, ``xyz_m``) at
    least ``radius_m`` [m] (scalar or one per sample) from every surface prism of ``surface_m``
    (:func:`surface_clearance_m`, brute force on the raw raster).  Returns the violations."""
    t, p = _samples(candidate)
    r = np.asarray(radius_m, float)
    if r.ndim and r.shape != t.shape:
        raise InputError(f"radius_m must be a scalar or one value per sample ({t.size}); got shape {r.shape}")
    if not (np.isfinite(r).all() and (r >= 0).all()):
        raise InputError("radius_m must be finite and >= 0 [m]")
    r = np.broadcast_to(r, t.shape)
    d = surface_clearance_m(p, grid=grid, surface_m=surface_m, radius_m=r)
    bad = d < r - tol_m
    if not bad.any():
        return []
    k = int(np.argmin(np.where(bad, d - r, np.inf)))
    return [f"inside the safety bubble of the surface (closest {float(d[k]):.2f} m < r = {float(r[k]):.2f} m at "
            f"t = {t[k]:.1f} s): {_where(bad, t, p)}"]
