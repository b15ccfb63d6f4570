"""The compiled kernels of the STEP I planning problem (numba; see
:mod:`skyroute.stages.planning.problem` for the geometry, validity rules and costs).

Their parameters are numba-friendly records (``typing.NamedTuple``), built once per problem by
:class:`~skyroute.stages.planning.problem.PlanningProblem`:

* :class:`GridParams` -- raster geometry (north-up, rows southwards);
* :class:`MapParams` -- the planning rasters on that grid;
* :class:`WindParams` -- the wind columns and their heights above ground;
* :class:`VehicleParams` -- speed, wind and flight-path-angle limits, sub-segment length;
* :class:`~skyroute.stages.energy.PowerParams` -- the rotor model (:mod:`skyroute.stages.energy`);
* :class:`SegmentArgs` -- (maps, wind, vehicle, power), the trailing arguments of
  :func:`segment_eval` (``*problem.seg_args``).

Calling a kernel from Python with NamedTuple arguments costs numba a slow type dispatch
(about 7 us per call); per-call callers (the OMPL callbacks) bind :func:`entry_point` once.
These kernels are internal: users call the :class:`PlanningProblem` methods.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from skyroute.stages.energy import PowerParams, eq3_ground_speed, power_kernel
from skyroute.stages.grid import Grid
from skyroute.stages.vehicle import FixedWingProfile, VehicleProfile

# validity codes (state and motion)
OK, OUTSIDE, FORBIDDEN, BELOW_FLOOR, ABOVE_CEILING, ANGLE, WIND, GROUND_SPEED, NONFINITE = range(9)
EPS_Z = 1e-9  # [m] tolerance of the floor/ceiling comparisons


class GridParams(NamedTuple):
    """Geometry of a north-up raster: cell (r, c) spans x0_m + [c, c + 1] res_m, y1_m - [r + 1, r] res_m."""

    x0_m: float    # west edge [m]
    y1_m: float    # north edge [m]
    res_m: float   # cell size [m]
    nx: int        # columns [-]
    ny: int        # rows [-]


def grid_params(g: Grid) -> GridParams:
    """:class:`GridParams` of ``g``."""
    return GridParams(float(g.x0), float(g.y1), float(g.resolution_m), int(g.nx), int(g.ny))


class MapParams(NamedTuple):
    """The planning rasters (ny, nx) float64 on ``grid``."""

    terrain_m: np.ndarray   # ground altitude [m]
    floor_m: np.ndarray     # lowest admissible altitude [m] (+inf: forbidden column)
    ceiling_m: np.ndarray   # highest admissible altitude [m]
    risk: np.ndarray        # risk cost per metre [-]
    landing: np.ndarray     # landing-site cost per metre [-]
    grid: GridParams


class WindParams(NamedTuple):
    """Wind columns: ``uvw_mps`` (nz, ny_w, nx_w, 3) [m/s] (u east, v north, w up) at heights
    ``z_agl_m`` (nz,) [m] above ground, columns on ``grid``."""

    uvw_mps: np.ndarray
    z_agl_m: np.ndarray
    grid: GridParams


class VehicleParams(NamedTuple):
    """The vehicle limits the kernels check."""

    cruise_speed_mps: float       # v_c [m/s]
    max_airspeed_mps: float       # v_max [m/s]
    min_ground_speed_mps: float   # v_min [m/s]
    max_wind_mps: float           # wind speed limit [m/s]
    max_sin_path_angle: float     # sin of the maximum flight-path angle [-]
    subsegment_m: float           # wind sampling step Delta s_s [m]


def vehicle_params(veh: VehicleProfile | FixedWingProfile, subsegment_m: float) -> VehicleParams:
    """:class:`VehicleParams` of ``veh`` with wind sampled every ``subsegment_m`` [m].

    A fixed-wing profile gets the limits its validity checks share with the rotorcraft (the
    wind speed limit, the larger of its climb / descent angles); its airspeed and ground
    speed are checked by the fixed-wing planner (wind triangle,
    :mod:`skyroute.stages.fixedwing_energy`), so eq. 3's limits are left open here."""
    if isinstance(veh, FixedWingProfile):
        return VehicleParams(float(veh.airspeed_at(1.225)), 1e9, 0.0, float(veh.max_wind_mps),
                             math.sin(math.radians(veh.max_flight_path_angle_deg)), float(subsegment_m))
    return VehicleParams(float(veh.cruise_speed_mps), float(veh.max_airspeed_mps), float(veh.min_ground_speed_mps),
                         float(veh.max_wind_mps), math.sin(math.radians(veh.max_flight_path_angle_deg)),
                         float(subsegment_m))


class SegmentArgs(NamedTuple):
    """The trailing arguments of :func:`segment_eval` / :func:`segment_eval_if_valid`."""

    maps: MapParams
    wind: WindParams
    vehicle: VehicleParams
    power: PowerParams


def entry_point(kernel, *example_args):
    """The compiled function of the numba ``kernel`` for the types of ``example_args``,
    callable from Python without numba's per-call type dispatch (slow with NamedTuple
    arguments).  Call it only with arguments of those exact types."""
    return kernel.compile(tuple(numba.typeof(a) for a in example_args))


@numba.njit(cache=True, nogil=True)
def wind_at(x, y, z, terrain, grid, wind):
    """(u, v, w) [m/s] at map point (x, y), absolute altitude z [m]: nearest column of ``wind``
    (:class:`WindParams`), linear in height above ``terrain`` [m] (on ``grid``) of the point's
    cell (clamped to the lowest/highest level)."""
    res, x0, y1, nx, ny = grid.res_m, grid.x0_m, grid.y1_m, grid.nx, grid.ny
    c = int(math.floor((x - x0) / res))
    r = int(math.floor((y1 - y) / res))
    c = min(max(c, 0), nx - 1)
    r = min(max(r, 0), ny - 1)
    h = z - terrain[r, c]
    wg = wind.grid
    wres, wx0, wy1, wnx, wny = wg.res_m, wg.x0_m, wg.y1_m, wg.nx, wg.ny
    wz = wind.z_agl_m
    uvw = wind.uvw_mps
    wc = min(max(int(math.floor((x - wx0) / wres)), 0), wnx - 1)
    wr = min(max(int(math.floor((wy1 - y) / wres)), 0), wny - 1)
    nz = wz.shape[0]
    if nz == 1:
        return uvw[0, wr, wc, 0], uvw[0, wr, wc, 1], uvw[0, wr, wc, 2]
    k0 = np.searchsorted(wz, h, side="right") - 1
    k0 = min(max(k0, 0), nz - 2)
    f = (h - wz[k0]) / (wz[k0 + 1] - wz[k0])
    f = min(max(f, 0.0), 1.0)
    u = uvw[k0, wr, wc, 0] * (1 - f) + uvw[k0 + 1, wr, wc, 0] * f
    v = uvw[k0, wr, wc, 1] * (1 - f) + uvw[k0 + 1, wr, wc, 1] * f
    w = uvw[k0, wr, wc, 2] * (1 - f) + uvw[k0 + 1, wr, wc, 2] * f
    return u, v, w


@numba.njit(cache=True, nogil=True)
def state_code(x, y, z, maps, wind, vehicle):
    """Validity code of the state (x, y, z) [m] (``OK`` = 0 or the first reason found)."""
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return NONFINITE
    g = maps.grid
    res, x0, y1, nx, ny = g.res_m, g.x0_m, g.y1_m, g.nx, g.ny
    c = int(math.floor((x - x0) / res))
    r = int(math.floor((y1 - y) / res))
    if c < 0 or r < 0 or c >= nx or r >= ny:
        return OUTSIDE
    fl = maps.floor_m[r, c]
    if not math.isfinite(fl):
        return FORBIDDEN
    if z < fl - EPS_Z:
        return BELOW_FLOOR
    if z > maps.ceiling_m[r, c] + EPS_Z:
        return ABOVE_CEILING
    u, v, w = wind_at(x, y, z, maps.terrain_m, g, wind)
    if math.sqrt(u * u + v * v + w * w) > vehicle.max_wind_mps:
        return WIND
    return OK


@numba.njit(cache=True, nogil=True)
def states_kernel(xyz, maps, wind, vehicle, out):
    """:func:`state_code` of each state xyz[i] (n, 3) [m] into ``out`` (n,)."""
    for i in range(xyz.shape[0]):
        out[i] = state_code(xyz[i, 0], xyz[i, 1], xyz[i, 2], maps, wind, vehicle)


@numba.njit(cache=True, nogil=True)
def segment_eval(x0, y0, z0, x1, y1, z1, want_cost, maps, wind, vehicle, power, out):
    """Validity code of the straight motion (x0, y0, z0) -> (x1, y1, z1) and, if ``want_cost``
    (or the geometry is valid), its costs in ``out`` (6,): length [m], risk integral [m],
    landing integral [m], energy cost eq. 12 [m], energy E_w [J], time [s] (inf if not
    flyable).  The energy loop runs only when ``want_cost`` is True or to decide flyability.
    ``maps, wind, vehicle, power`` are the fields of :class:`SegmentArgs`
    (:attr:`~skyroute.stages.planning.problem.PlanningProblem.seg_args`)."""
    return _segment_eval(x0, y0, z0, x1, y1, z1, want_cost, False, maps, wind, vehicle, power, out)


@numba.njit(cache=True, nogil=True)
def segment_eval_if_valid(x0, y0, z0, x1, y1, z1, maps, wind, vehicle, power, out):
    """:func:`segment_eval` for searches: the costs only when the motion is valid (returns at
    the first invalidity found, ``out`` is then incomplete), so invalid motions cost no energy
    evaluation."""
    return _segment_eval(x0, y0, z0, x1, y1, z1, True, True, maps, wind, vehicle, power, out)


@numba.njit(cache=True, nogil=True)
def _segment_eval(x0, y0, z0, x1, y1, z1, want_cost, valid_only, maps, wind, vehicle, power, out):
    terrain, floor, ceiling, risk, landing = maps.terrain_m, maps.floor_m, maps.ceiling_m, maps.risk, maps.landing
    grid = maps.grid
    for k in range(6):
        out[k] = 0.0
    if not (math.isfinite(x0) and math.isfinite(y0) and math.isfinite(z0)
            and math.isfinite(x1) and math.isfinite(y1) and math.isfinite(z1)):
        for k in range(6):
            out[k] = np.inf
        return NONFINITE
    dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
    length = math.sqrt(dx * dx + dy * dy + dz * dz)
    out[0] = length
    res, gx0, gy1, nx, ny = grid.res_m, grid.x0_m, grid.y1_m, grid.nx, grid.ny
    code = OK
    # ---- cell traversal: floor / ceiling and the map integrals
    c = int(math.floor((x0 - gx0) / res))
    r = int(math.floor((gy1 - y0) / res))
    stepc = 1 if dx > 0 else -1
    stepr = -1 if dy > 0 else 1   # rows grow southwards
    if dx != 0.0:
        xb = gx0 + (c + (1 if dx > 0 else 0)) * res
        tmx = (xb - x0) / dx
        tdx = res / abs(dx)
    else:
        tmx = np.inf
        tdx = np.inf
    if dy != 0.0:
        yb = gy1 - (r + (0 if dy > 0 else 1)) * res
        tmy = (yb - y0) / dy
        tdy = res / abs(dy)
    else:
        tmy = np.inf
        tdy = np.inf
    t = 0.0
    srisk = 0.0
    sland = 0.0
    for _ in range(4 * (nx + ny) + 8):
        tn = min(tmx, tmy, 1.0)
        if tn < t:
            tn = t
        if c < 0 or r < 0 or c >= nx or r >= ny:
            if code == OK:
                code = OUTSIDE
            cc = min(max(c, 0), nx - 1)
            rr = min(max(r, 0), ny - 1)
        else:
            cc = c
            rr = r
            fl = floor[rr, cc]
            za = z0 + t * dz
            zb = z0 + tn * dz
            zlo = min(za, zb)
            zhi = max(za, zb)
            if code == OK:
                if not math.isfinite(fl):
                    code = FORBIDDEN
                elif zlo < fl - EPS_Z:
                    code = BELOW_FLOOR
                elif zhi > ceiling[rr, cc] + EPS_Z:
                    code = ABOVE_CEILING
        if tn > t:
            srisk += risk[rr, cc] * (tn - t)
            sland += landing[rr, cc] * (tn - t)
        if tn >= 1.0:
            break
        t = tn
        if tmx <= tmy:
            c += stepc
            tmx += tdx
        else:
            r += stepr
            tmy += tdy
    out[1] = srisk * length
    out[2] = sland * length
    if code != OK and (valid_only or not want_cost):
        return code
    if length == 0.0:
        return code
    # ---- flight-path angle
    if code == OK and abs(dz) > length * vehicle.max_sin_path_angle + 1e-9:
        code = ANGLE
        if valid_only:
            return code
    # ---- wind, ground speed (eq. 2-3) and energy (eq. 4-12)
    vc, vmax, vmin = vehicle.cruise_speed_mps, vehicle.max_airspeed_mps, vehicle.min_ground_speed_mps
    wmax, sub = vehicle.max_wind_mps, vehicle.subsegment_m
    sx, sy, sz = dx / length, dy / length, dz / length
    nsub = max(1, int(math.ceil(length / sub - 1e-9)))
    nbuf = nsub + 1 if want_cost else 1
    va = np.empty((nbuf, 3))
    vs = np.empty(nbuf)
    vzc = np.empty(nbuf)
    tau = np.empty(nbuf)
    flyable = True
    for i in range(nsub):
        ds = min(sub, length - i * sub)
        px = x0 + sx * i * sub
        py = y0 + sy * i * sub
        pz = z0 + sz * i * sub
        u, v, w = wind_at(px, py, pz, terrain, grid, wind)
        ok_i = True
        if math.sqrt(u * u + v * v + w * w) > wmax:
            ok_i = False
            if code == OK:
                code = WIND
        g = eq3_ground_speed(sx, sy, sz, u, v, w, vc, vmax)
        if math.isnan(g):  # no m_- root
            g = vc
            ok_i = False
        if ok_i and (g < vmin or g <= 0.0):
            ok_i = False
        if not ok_i:
            flyable = False
            if code == OK:
                code = GROUND_SPEED
            if valid_only:
                return code
            g = vc
        if want_cost:
            va[i, 0] = g * sx - u
            va[i, 1] = g * sy - v
            va[i, 2] = g * sz - w
            vs[i] = va[i, 0] * sx + va[i, 1] * sy + va[i, 2] * sz
            vzc[i] = g * sz
            tau[i] = ds / g if ds > 0 else 0.0
        elif not flyable:
            return code
    if not want_cost:
        return code
    # no-wind reference sample in the last row
    va[nsub, 0] = vc * sx
    va[nsub, 1] = vc * sy
    va[nsub, 2] = vc * sz
    vs[nsub] = vc
    vzc[nsub] = vc * sz
    pw = np.empty((nsub + 1, 8))
    power_kernel(va, vs, vzc, power, pw)
    if flyable:
        ew = 0.0
        tt = 0.0
        for i in range(nsub):
            ew += pw[i, 4] * tau[i]
            tt += tau[i]
        e0 = pw[nsub, 4] * length / vc
        out[3] = ew / e0 * length
        out[4] = ew
        out[5] = tt
    else:
        out[3] = np.inf
        out[4] = np.inf
        out[5] = np.inf
    return code


@numba.njit(cache=True, nogil=True)
def segments_kernel(p0, p1, want_cost, valid_only, maps, wind, vehicle, power, out, codes):
    """:func:`segment_eval` (``valid_only``: :func:`segment_eval_if_valid`, the costs of the
    valid motions only, an invalid one costing no energy evaluation) of each motion p0[i] ->
    p1[i] (n, 3) [m]: ``out`` (n, 6), ``codes`` (n,)."""
    buf = np.empty(6)
    for i in range(p0.shape[0]):
        codes[i] = _segment_eval(p0[i, 0], p0[i, 1], p0[i, 2], p1[i, 0], p1[i, 1], p1[i, 2], want_cost,
                                 valid_only, maps, wind, vehicle, power, buf)
        for k in range(6):
            out[i, k] = buf[k]


@numba.njit(cache=True, nogil=True)
def _still_air_power(dirs, vehicle, power):
    """(m,): the power [W] of E_0 for each unit direction dirs[i]: still air, cruise speed."""
    vc = vehicle.cruise_speed_mps
    p0 = np.empty(dirs.shape[0])
    va = np.empty((1, 3))
    vs = np.empty(1)
    vz = np.empty(1)
    pw = np.empty((1, 8))
    for i in range(dirs.shape[0]):
        va[0, 0], va[0, 1], va[0, 2] = vc * dirs[i, 0], vc * dirs[i, 1], vc * dirs[i, 2]
        vs[0] = vc
        vz[0] = vc * dirs[i, 2]
        power_kernel(va, vs, vz, power, pw)
        p0[i] = pw[0, 4]
    return p0


@numba.njit(cache=True, nogil=True)
def ratio_kernel(dirs, winds, vehicle, power):
    """min over (unit direction dirs[i], wind winds[j] [m/s]) of the one-sub-segment E_w/E_0
    (flyable pairs only; inf when none is).  The still-air power of a direction is computed
    once per direction (the rows of ``power_kernel`` are independent: the same numbers as
    computing it per wind, in half the time)."""
    best = np.full(dirs.shape[0], np.inf)
    _ratio_rows(dirs, _still_air_power(dirs, vehicle, power), winds, 0, winds.shape[0], vehicle, power, best)
    out = np.inf
    for i in range(best.shape[0]):
        if best[i] < out:
            out = best[i]
    return out


@numba.njit(cache=True, nogil=True)
def _ratio_rows(dirs, p0, winds, j0, j1, vehicle, power, best):
    """``best[i]`` = min(best[i], min over winds[j0:j1] of the one-sub-segment E_w/E_0 of
    direction dirs[i]) (flyable pairs only), ``p0[i]`` its still-air power
    (:func:`_still_air_power`): the loop of :func:`ratio_kernel` and :func:`ratio_each_kernel`."""
    vc, vmax, vmin = vehicle.cruise_speed_mps, vehicle.max_airspeed_mps, vehicle.min_ground_speed_mps
    wmax = vehicle.max_wind_mps
    va = np.empty((1, 3))
    vs = np.empty(1)
    vz = np.empty(1)
    pw = np.empty((1, 8))
    for i in range(dirs.shape[0]):
        sx, sy, sz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        b = best[i]
        for j in range(j0, j1):
            u, v, w = winds[j, 0], winds[j, 1], winds[j, 2]
            if math.sqrt(u * u + v * v + w * w) > wmax:
                continue
            g = eq3_ground_speed(sx, sy, sz, u, v, w, vc, vmax)
            if math.isnan(g) or g < vmin or g <= 0:
                continue
            va[0, 0], va[0, 1], va[0, 2] = g * sx - u, g * sy - v, g * sz - w
            vs[0] = va[0, 0] * sx + va[0, 1] * sy + va[0, 2] * sz
            vz[0] = g * sz
            power_kernel(va, vs, vz, power, pw)
            ratio = (pw[0, 4] / g) / (p0[i] / vc)
            if ratio < b:
                b = ratio
        best[i] = b


RATIO_CHUNK = 4096   # winds per task of ratio_each_kernel


@numba.njit(cache=True, nogil=True, parallel=True)
def ratio_each_kernel(dirs, winds, vehicle, power):
    """(m,): for each unit direction dirs[i] the min over winds[j] [m/s] of the one-sub-segment
    E_w/E_0 (flyable pairs only; inf when none is): :func:`ratio_kernel` of each direction alone,
    the same numbers (a minimum does not depend on the order it is taken in), the winds split in
    chunks of :data:`RATIO_CHUNK` over the cores."""
    nd = dirs.shape[0]
    p0 = _still_air_power(dirs, vehicle, power)
    nw = winds.shape[0]
    nchunk = max(1, (nw + RATIO_CHUNK - 1) // RATIO_CHUNK)
    part = np.full((nchunk, nd), np.inf)
    for c in numba.prange(nchunk):
        _ratio_rows(dirs, p0, winds, c * RATIO_CHUNK, min(nw, (c + 1) * RATIO_CHUNK), vehicle, power, part[c])
    out = np.full(nd, np.inf)
    for c in range(nchunk):
        for i in range(nd):
            if part[c, i] < out[i]:
                out[i] = part[c, i]
    return out


__all__ = ["GridParams", "MapParams", "SegmentArgs", "VehicleParams", "WindParams", "entry_point", "grid_params",
           "ratio_each_kernel", "ratio_kernel", "segment_eval", "segment_eval_if_valid", "segments_kernel", "state_code", "states_kernel",
           "vehicle_params", "wind_at"]


@numba.njit(cache=True, nogil=True)
def level_floor_kernel(floor, cover, nofly, out):   # pragma: no cover - compiled
    """``out`` (ny, nx) = +inf where ``nofly``, else ``np.maximum(floor, cover)`` with a
    non-finite ``cover`` taken as +inf (never reachable), NaN floors propagating as in numpy;
    ``cover`` of shape (0, 0): no coverage floor.  One pass of :func:`build_problem`'s three."""
    ny, nx = floor.shape
    has_cover = cover.shape[0] > 0
    for r in range(ny):
        for c in range(nx):
            if nofly[r, c]:
                out[r, c] = np.inf
                continue
            f = floor[r, c]
            if has_cover:
                v = cover[r, c]
                if not np.isfinite(v):
                    v = np.inf
                if f == f and v > f:
                    f = v
            out[r, c] = f
