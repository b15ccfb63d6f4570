"""The STEP I planning problem of one GNSS coverage level D_j (seed 000 section III-A).

A :class:`PlanningProblem` holds everything static a planner needs on the scenario grid and
answers the three questions every planner asks, vectorised and compiled (numba):

* is a state valid? (:meth:`PlanningProblem.state_valid`)
* is a straight motion valid? (:meth:`PlanningProblem.motion_valid`)
* what does a straight motion cost? (:meth:`PlanningProblem.segment_costs`, eq. 11 terms)

Geometry and units
------------------
Map coordinates x east, y north [m] of the grid CRS; altitudes z [m] in the surface's vertical
datum (absolute, like the surface / clearance rasters).  Rasters are nearest-cell (flat-topped
cells).  The admissible altitudes of column (row, col) are ``floor_m <= z <= ceiling_m`` with

    floor_m = max(clearance floor (sphere r_p, eq. 13), terrain + min_agl,
                  GNSS coverage floor of D_j)           (+inf: forbidden column)
    ceiling_m = terrain + max_agl

Motion validity (planner bounds, seed 000 III-A.3) is **exact** for the rasters: the segment
is cut at every cell boundary it crosses (Amanatides-Woo traversal); z is linear along it, so
on each cell interval its extreme altitudes are at the interval ends, which are compared with
that cell's floor and ceiling.  Besides: the flight-path angle ``|asin(dz / L)|`` must not
exceed ``vehicle.max_flight_path_angle_deg``; the wind sampled at the start of every
sub-segment of ``subsegment_m`` (seed 000 Delta s_s) must not exceed ``vehicle.max_wind_mps``
and its ground speed by eq. 3 must exist and be >= v_min (the same rules as
:func:`skyroute.stages.energy.segment_energy`).

Costs of a segment (eq. 11-12), all [m]:

* ``C_l`` = length L (3-D);
* ``C_r`` = integral of the risk map along the segment = L * sum_cells risk * dt (exact for a
  nearest-cell map: dt is the fraction of the segment inside the cell);
* ``C_d`` = the same with the landing-site map;
* ``C_e`` = E_w / E_0 * L (eq. 12): wind energy over no-wind energy, both by the rotor model of
  :mod:`skyroute.stages.energy` (its compiled power kernel is reused), wind sampled at the
  start of each sub-segment (nearest wind column, linear in height above ground).

``f = w_l C_l + w_r C_r + w_d C_d + w_e C_e``.  Because E_w / E_0 can be below 1 (tail wind),
the admissible lower bound of f per metre (:attr:`PlanningProblem.cost_rate_lb`) uses the
smallest ratio over sampled directions and the map's winds, times a 0.9 safety factor; for a
few given directions (the A* lattice edges) :meth:`PlanningProblem.energy_ratio_lb_dense_dirs`
takes every wind of the map and its level-to-level interpolations, times 0.99.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import threading
from dataclasses import dataclass, field

import numba
import numpy as np
import xarray as xr

from skyroute.stages.base import InputError, PlanningError
from skyroute.stages.energy import _power_kernel, eq3_ground_speed, power_params
from skyroute.stages.grid import Grid
from skyroute.stages.vehicle import VehicleProfile, load_vehicle

# validity codes (state and motion)
OK, OUTSIDE, FORBIDDEN, BELOW_FLOOR, ABOVE_CEILING, ANGLE, WIND, GROUND_SPEED, NONFINITE = range(9)
_EPS_Z = 1e-9  # [m] tolerance of the floor/ceiling comparisons
ENERGY_LB_SAFETY = 0.9
ENERGY_LB_DENSE_SAFETY = 0.99   # margin of the dense bound for wind between its interpolation samples
WIND_INTERP_SAMPLES = 8         # samples per gap between two wind levels of the dense bound
_RATIO_MEMO: dict[str, float] = {}   # energy_ratio_lb_dirs memo (shared by the levels)
_WINDS_MEMO: dict[str, np.ndarray] = {}
_RATIO_LOCK = threading.Lock()


def _memoised(store: dict, key: str, make, limit: int):
    """``store[key]``, computed by ``make()`` on a miss (thread-safe; cleared past ``limit``)."""
    with _RATIO_LOCK:
        value = store.get(key)
    if value is None:
        value = make()
        with _RATIO_LOCK:
            if len(store) > limit:
                store.clear()
            store[key] = value
    return value


def _finite_ratio(r: float) -> float:
    return 1.0 if not np.isfinite(r) else float(r)

COST_NAMES = ("C_l", "C_r", "C_d", "C_e")


# --------------------------------------------------------------------------- kernels


@numba.njit(cache=True, nogil=True)
def _wind_at(x, y, z, terrain, gprm, wind, wz, wgprm):
    """(u, v, w) [m/s] at map point (x, y), absolute altitude z: nearest wind column, linear in
    height above the terrain of the point's cell (clamped to the lowest/highest level)."""
    res, x0, y1, nx, ny = gprm[2], gprm[0], gprm[1], int(gprm[3]), int(gprm[4])
    c = int(math.floor((x - x0) / res))
    r = int(math.floor((y1 - y) / res))
    c = min(max(c, 0), nx - 1)
    r = min(max(r, 0), ny - 1)
    h = z - terrain[r, c]
    wres, wx0, wy1, wnx, wny = wgprm[2], wgprm[0], wgprm[1], int(wgprm[3]), int(wgprm[4])
    wc = min(max(int(math.floor((x - wx0) / wres)), 0), wnx - 1)
    wr = min(max(int(math.floor((wy1 - y) / wres)), 0), wny - 1)
    nz = wz.shape[0]
    if nz == 1:
        return wind[0, wr, wc, 0], wind[0, wr, wc, 1], wind[0, wr, wc, 2]
    k0 = np.searchsorted(wz, h, side="right") - 1
    k0 = min(max(k0, 0), nz - 2)
    f = (h - wz[k0]) / (wz[k0 + 1] - wz[k0])
    f = min(max(f, 0.0), 1.0)
    u = wind[k0, wr, wc, 0] * (1 - f) + wind[k0 + 1, wr, wc, 0] * f
    v = wind[k0, wr, wc, 1] * (1 - f) + wind[k0 + 1, wr, wc, 1] * f
    w = wind[k0, wr, wc, 2] * (1 - f) + wind[k0 + 1, wr, wc, 2] * f
    return u, v, w


@numba.njit(cache=True, nogil=True)
def _state_code(x, y, z, terrain, floor, ceiling, gprm, wind, wz, wgprm, vprm):
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return NONFINITE
    res, x0, y1, nx, ny = gprm[2], gprm[0], gprm[1], int(gprm[3]), int(gprm[4])
    c = int(math.floor((x - x0) / res))
    r = int(math.floor((y1 - y) / res))
    if c < 0 or r < 0 or c >= nx or r >= ny:
        return OUTSIDE
    fl = floor[r, c]
    if not math.isfinite(fl):
        return FORBIDDEN
    if z < fl - _EPS_Z:
        return BELOW_FLOOR
    if z > ceiling[r, c] + _EPS_Z:
        return ABOVE_CEILING
    u, v, w = _wind_at(x, y, z, terrain, gprm, wind, wz, wgprm)
    if math.sqrt(u * u + v * v + w * w) > vprm[3]:
        return WIND
    return OK


@numba.njit(cache=True, nogil=True)
def _states_kernel(xyz, terrain, floor, ceiling, gprm, wind, wz, wgprm, vprm, out):
    for i in range(xyz.shape[0]):
        out[i] = _state_code(xyz[i, 0], xyz[i, 1], xyz[i, 2], terrain, floor, ceiling, gprm, wind, wz,
                             wgprm, vprm)


@numba.njit(cache=True, nogil=True)
def segment_eval(x0, y0, z0, x1, y1, z1, want_cost, terrain, floor, ceiling, risk, landing, gprm,
                 wind, wz, wgprm, vprm, pprm, out):
    """Validity code of the straight motion (x0, y0, z0) -> (x1, y1, z1) and, if ``want_cost``
    (or the geometry is valid), its costs in ``out`` (6,): length [m], risk integral [m],
    landing integral [m], energy cost eq. 12 [m], energy E_w [J], time [s] (inf if not
    flyable).  The energy loop runs only when ``want_cost`` is True or to decide flyability."""
    return _segment_eval(x0, y0, z0, x1, y1, z1, want_cost, False, terrain, floor, ceiling, risk, landing,
                         gprm, wind, wz, wgprm, vprm, pprm, out)


@numba.njit(cache=True, nogil=True)
def segment_eval_if_valid(x0, y0, z0, x1, y1, z1, terrain, floor, ceiling, risk, landing, gprm,
                          wind, wz, wgprm, vprm, pprm, out):
    """:func:`segment_eval` for searches: the costs only when the motion is valid (returns at
    the first invalidity found, ``out`` is then incomplete), so invalid motions cost no energy
    evaluation."""
    return _segment_eval(x0, y0, z0, x1, y1, z1, True, True, terrain, floor, ceiling, risk, landing,
                         gprm, wind, wz, wgprm, vprm, pprm, out)


@numba.njit(cache=True, nogil=True)
def _segment_eval(x0, y0, z0, x1, y1, z1, want_cost, valid_only, terrain, floor, ceiling, risk, landing,
                  gprm, wind, wz, wgprm, vprm, pprm, out):
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
    res, gx0, gy1, nx, ny = gprm[2], gprm[0], gprm[1], int(gprm[3]), int(gprm[4])
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
                elif zlo < fl - _EPS_Z:
                    code = BELOW_FLOOR
                elif zhi > ceiling[rr, cc] + _EPS_Z:
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
    if code == OK and abs(dz) > length * vprm[4] + 1e-9:
        code = ANGLE
        if valid_only:
            return code
    # ---- wind, ground speed (eq. 2-3) and energy (eq. 4-12)
    vc, vmax, vmin, wmax, sub = vprm[0], vprm[1], vprm[2], vprm[3], vprm[5]
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
        u, v, w = _wind_at(px, py, pz, terrain, gprm, wind, wz, wgprm)
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
    _power_kernel(va, vs, vzc, pprm, pw)
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
def _segments_kernel(p0, p1, want_cost, terrain, floor, ceiling, risk, landing, gprm, wind, wz, wgprm,
                     vprm, pprm, out, codes):
    buf = np.empty(6)
    for i in range(p0.shape[0]):
        codes[i] = segment_eval(p0[i, 0], p0[i, 1], p0[i, 2], p1[i, 0], p1[i, 1], p1[i, 2], want_cost,
                                terrain, floor, ceiling, risk, landing, gprm, wind, wz, wgprm, vprm, pprm,
                                buf)
        for k in range(6):
            out[i, k] = buf[k]


@numba.njit(cache=True, nogil=True)
def _ratio_kernel(dirs, winds, vprm, pprm):
    """min over (direction, wind) of the one-sub-segment E_w/E_0 (flyable pairs only)."""
    vc, vmax, vmin, wmax = vprm[0], vprm[1], vprm[2], vprm[3]
    best = np.inf
    va = np.empty((2, 3))
    vs = np.empty(2)
    vz = np.empty(2)
    pw = np.empty((2, 8))
    for i in range(dirs.shape[0]):
        sx, sy, sz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        for j in range(winds.shape[0]):
            u, v, w = winds[j, 0], winds[j, 1], winds[j, 2]
            if math.sqrt(u * u + v * v + w * w) > wmax:
                continue
            g = eq3_ground_speed(sx, sy, sz, u, v, w, vc, vmax)
            if math.isnan(g) or g < vmin or g <= 0:
                continue
            va[0, 0], va[0, 1], va[0, 2] = g * sx - u, g * sy - v, g * sz - w
            vs[0] = va[0, 0] * sx + va[0, 1] * sy + va[0, 2] * sz
            vz[0] = g * sz
            va[1, 0], va[1, 1], va[1, 2] = vc * sx, vc * sy, vc * sz
            vs[1] = vc
            vz[1] = vc * sz
            _power_kernel(va, vs, vz, pprm, pw)
            ratio = (pw[0, 4] / g) / (pw[1, 4] / vc)
            if ratio < best:
                best = ratio
    return best


# --------------------------------------------------------------------------- problem


_REASONS = {
    OUTSIDE: "outside the planning area (AOI)",
    FORBIDDEN: "in a forbidden column",
    BELOW_FLOOR: "below the lowest admissible altitude",
    ABOVE_CEILING: "above the maximum altitude",
    ANGLE: "flight-path angle above the vehicle maximum",
    WIND: "wind speed above the vehicle maximum",
    GROUND_SPEED: "not flyable in this wind (no ground speed >= v_min by eq. 3)",
    NONFINITE: "non-finite coordinates",
}


def _vehicle_params(veh: VehicleProfile, subsegment_m: float) -> tuple[np.ndarray, np.ndarray]:
    pprm = power_params(veh)
    vprm = np.array([veh.cruise_speed_mps, veh.max_airspeed_mps, veh.min_ground_speed_mps, veh.max_wind_mps,
                     math.sin(math.radians(veh.max_flight_path_angle_deg)), subsegment_m], dtype=float)
    return vprm, pprm


def _grid_params(g: Grid) -> np.ndarray:
    return np.array([g.x0, g.y1, g.resolution_m, g.nx, g.ny], dtype=float)


def _fibonacci_dirs(n: int, max_sin: float) -> np.ndarray:
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = math.pi * (1 + 5**0.5) * k
    rho = np.sqrt(1 - z * z)
    d = np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)
    lat = np.array([[i, j, kk] for i in (-1, 0, 1) for j in (-1, 0, 1) for kk in (-1, 0, 1)
                    if (i, j, kk) != (0, 0, 0)], dtype=float)
    lat /= np.linalg.norm(lat, axis=1)[:, None]
    ang = np.linspace(0, 2 * math.pi, 72, endpoint=False)
    edge = np.stack([np.cos(ang) * math.sqrt(1 - max_sin**2), np.sin(ang) * math.sqrt(1 - max_sin**2),
                     np.full_like(ang, max_sin)], axis=1)
    d = np.concatenate([d, lat, edge, edge * [1, 1, -1]])
    return np.ascontiguousarray(d[np.abs(d[:, 2]) <= max_sin + 1e-12])


@dataclass(frozen=True, eq=False)
class PlanningProblem:
    """One STEP I problem (one coverage level D_j); see the module docstring.

    Arrays are (ny, nx) float64 on ``grid``; altitudes [m] in the surface datum.
    ``wind_uvw`` is (nz, ny_w, nx_w, 3) [m/s] (u east, v north, w up) on heights above ground
    ``wind_z_agl_m`` (nz,) and the horizontal ``wind_grid`` (None: ``grid``), or a uniform
    (3,) vector.  ``clearance_m`` / ``coverage_m`` / ``nofly`` are the components of
    ``floor_m`` kept to explain invalid states.
    """

    grid: Grid
    terrain_m: np.ndarray
    floor_m: np.ndarray
    ceiling_m: np.ndarray
    risk_cost: np.ndarray
    landing_cost: np.ndarray
    wind_uvw: np.ndarray
    vehicle: VehicleProfile
    weights: tuple[float, float, float, float]
    start_xyz: tuple[float, float, float]
    goal_xyz: tuple[float, float, float]
    dop_threshold: float | None = None
    label: str = ""
    wind_z_agl_m: np.ndarray = field(default_factory=lambda: np.zeros(1))
    wind_grid: Grid | None = None
    clearance_m: np.ndarray | None = None
    coverage_m: np.ndarray | None = None
    nofly: np.ndarray | None = None
    min_agl_m: float = 0.0
    max_agl_m: float = np.inf
    dop_kind: str = "PDOP"
    subsegment_m: float = 10.0

    def __post_init__(self) -> None:
        f64 = lambda a: np.ascontiguousarray(np.asarray(a, dtype=np.float64))  # noqa: E731
        shape = self.grid.shape
        for name in ("terrain_m", "floor_m", "ceiling_m", "risk_cost", "landing_cost"):
            a = f64(getattr(self, name))
            if a.shape != shape:
                raise InputError(f"{name} has shape {a.shape}; expected the grid shape {shape} (ny, nx)")
            object.__setattr__(self, name, a)
        w = f64(self.wind_uvw)
        wz = f64(np.atleast_1d(self.wind_z_agl_m))
        if w.shape == (3,):
            w4 = np.ascontiguousarray(w.reshape(1, 1, 1, 3))
            wz = np.zeros(1)
            wg = Grid(self.grid.crs_wkt, self.grid.x0, self.grid.y1, 1, 1,
                      self.grid.resolution_m * max(self.grid.nx, self.grid.ny))
        elif w.ndim == 4 and w.shape[-1] == 3:
            w4 = w
            wg = self.wind_grid or self.grid
            if w.shape[1:3] != wg.shape:
                raise InputError(f"wind_uvw has {w.shape[1:3]} columns but its grid is {wg.shape}: pass wind_grid")
            if wz.shape != (w.shape[0],) or (wz.size > 1 and np.any(np.diff(wz) <= 0)):
                raise InputError(f"wind_z_agl_m must be {w.shape[0]} increasing heights [m], got {wz}")
        else:
            raise InputError(f"wind_uvw must be (3,) or (nz, ny_w, nx_w, 3) [m/s], got shape {w.shape}")
        if not np.isfinite(w4).all():
            raise InputError("wind_uvw contains NaN/inf: fill the wind map")
        veh = load_vehicle(self.vehicle)
        if not self.subsegment_m > 0:
            raise InputError(f"subsegment_m {self.subsegment_m} must be > 0 [m]")
        vprm, pprm = _vehicle_params(veh, float(self.subsegment_m))
        wgt = tuple(float(x) for x in self.weights)
        object.__setattr__(self, "weights", wgt)
        object.__setattr__(self, "wind_uvw", w4)
        object.__setattr__(self, "wind_z_agl_m", wz)
        object.__setattr__(self, "wind_grid", wg)
        object.__setattr__(self, "start_xyz", tuple(float(v) for v in self.start_xyz))
        object.__setattr__(self, "goal_xyz", tuple(float(v) for v in self.goal_xyz))
        gprm, wgprm = _grid_params(self.grid), _grid_params(wg)
        geo = (self.terrain_m, self.floor_m, self.ceiling_m)
        object.__setattr__(self, "_state_args", (*geo, gprm, w4, wz, wgprm, vprm))
        object.__setattr__(self, "_seg_args", (*geo, self.risk_cost, self.landing_cost, gprm, w4, wz, wgprm,
                                               vprm, pprm))
        object.__setattr__(self, "_lb_cache", None)

    # ------------------------------------------------------------------ helpers
    @property
    def seg_args(self) -> tuple:
        """Arguments after ``want_cost`` of :func:`segment_eval` (for compiled callers)."""
        return self._seg_args

    @staticmethod
    def _pts(a, what: str = "xyz") -> np.ndarray:
        a = np.asarray(a, dtype=np.float64)
        if a.ndim == 1:
            a = a[None, :]
        if a.ndim != 2 or a.shape[1] != 3:
            raise InputError(f"{what} must have shape (n, 3) [m], got {a.shape}")
        return np.ascontiguousarray(a)

    def with_weights(self, weights) -> PlanningProblem:
        """A copy with other cost weights (w_l, w_r, w_d, w_e)."""
        return dataclasses.replace(self, weights=_check_weights(weights))

    # ------------------------------------------------------------------ validity
    def state_codes(self, xyz) -> np.ndarray:
        """Validity code per state (0 = valid; see ``_REASONS``)."""
        p = self._pts(xyz)
        out = np.empty(p.shape[0], dtype=np.int64)
        _states_kernel(p, *self._state_args, out)
        return out

    def state_valid(self, xyz) -> np.ndarray:
        """bool (n,): state inside the AOI, between floor and ceiling, wind <= max."""
        return self.state_codes(xyz) == OK

    def motion_codes(self, p0, p1, want_cost: bool = False) -> tuple[np.ndarray, np.ndarray]:
        a, b = self._pts(p0, "p0"), self._pts(p1, "p1")
        if a.shape != b.shape:
            raise InputError(f"p0 and p1 must have the same shape, got {a.shape} and {b.shape}")
        out = np.empty((a.shape[0], 6))
        codes = np.empty(a.shape[0], dtype=np.int64)
        _segments_kernel(a, b, want_cost, *self._seg_args, out, codes)
        return codes, out

    def motion_valid(self, p0, p1) -> np.ndarray:
        """bool (n,): every straight motion p0[i] -> p1[i] (n,3) valid (module docstring)."""
        return self.motion_codes(p0, p1)[0] == OK

    def segment_details(self, p0, p1) -> dict[str, np.ndarray]:
        """Per segment: ``length_m``, ``risk_m``, ``landing_m``, ``energy_cost_m`` (eq. 12),
        ``energy_J`` (E_w), ``time_s``, ``code`` (0 = valid motion)."""
        codes, out = self.motion_codes(p0, p1, want_cost=True)
        keys = ("length_m", "risk_m", "landing_m", "energy_cost_m", "energy_J", "time_s")
        d = {k: out[:, i] for i, k in enumerate(keys)}
        d["code"] = codes
        return d

    def segment_costs(self, p0, p1) -> np.ndarray:
        """(n, 4) [m]: [C_l, C_r, C_d, C_e] of each segment (eq. 11-12); C_e is inf where the
        segment is not flyable in the wind.  Validity is not required (see motion_valid)."""
        return self.motion_codes(p0, p1, want_cost=True)[1][:, :4].copy()

    def f_of(self, costs) -> np.ndarray:
        """Weighted objective f (eq. 11) of cost rows (..., 4)."""
        return np.asarray(costs, dtype=float) @ np.asarray(self.weights)

    def path_costs(self, waypoints) -> dict:
        """Totals along a polygonal chain (k, 3): ``C_l``, ``C_r``, ``C_d``, ``C_e`` [m], ``f``,
        ``energy_J``, ``time_s``, ``valid`` (every segment valid), ``first_invalid`` (index of
        the first invalid segment or -1)."""
        w = self._pts(waypoints, "waypoints")
        if w.shape[0] < 2:
            raise InputError("a path needs at least 2 waypoints")
        d = self.segment_details(w[:-1], w[1:])
        tot = {"C_l": float(d["length_m"].sum()), "C_r": float(d["risk_m"].sum()),
               "C_d": float(d["landing_m"].sum()), "C_e": float(d["energy_cost_m"].sum())}
        tot["f"] = float(np.dot([tot[k] for k in COST_NAMES], self.weights))
        tot["energy_J"] = float(d["energy_J"].sum())
        tot["time_s"] = float(d["time_s"].sum())
        bad = np.nonzero(d["code"] != OK)[0]
        tot["valid"] = bool(bad.size == 0)
        tot["first_invalid"] = int(bad[0]) if bad.size else -1
        return tot

    # ------------------------------------------------------------------ explanations
    def _cell(self, x: float, y: float) -> tuple[int, int]:
        r, c = self.grid.index_of(x, y)
        return int(r), int(c)

    def explain_invalid(self, xyz) -> str:
        """Why the state ``xyz`` (3,) is invalid ("" if it is valid)."""
        p = self._pts(xyz)[0]
        code = int(self.state_codes(p)[0])
        if code == OK:
            return ""
        x, y, z = (float(v) for v in p)
        if code in (OUTSIDE, NONFINITE):
            return f"point ({x:.1f}, {y:.1f}) is {_REASONS[code]} {self.grid.bounds}"
        r, c = self._cell(x, y)
        ground = self.terrain_m[r, c]
        agl = z - ground
        where = f"at ({x:.1f}, {y:.1f}, z={z:.1f} m = {agl:.1f} m AGL)"
        dop = f"{self.dop_kind} < {self.dop_threshold:g}" if self.dop_threshold is not None else "the DOP threshold"
        if code == FORBIDDEN:
            if self.nofly is not None and self.nofly[r, c]:
                return f"{where}: inside a no-fly zone"
            if self.coverage_m is not None and not np.isfinite(self.coverage_m[r, c]):
                return f"{where}: GNSS coverage never reaches {dop} in this column (unflyable)"
            return f"{where}: forbidden column (no-fly)"
        if code == BELOW_FLOOR:
            parts = []
            if self.clearance_m is not None and z < self.clearance_m[r, c] - _EPS_Z:
                parts.append(f"inside obstacle clearance (sphere r_p = {self.vehicle.r_p_m:g} m needs "
                             f"z >= {self.clearance_m[r, c]:.1f} m)")
            if z < ground + self.min_agl_m - _EPS_Z:
                parts.append(f"below the minimum altitude {self.min_agl_m:g} m AGL")
            if self.coverage_m is not None and z < self.coverage_m[r, c] - _EPS_Z:
                parts.append(f"below GNSS coverage floor for {dop} ({self.coverage_m[r, c]:.1f} m)")
            if not parts:
                parts.append(f"below the floor {self.floor_m[r, c]:.1f} m")
            return f"{where}: " + "; ".join(parts)
        if code == ABOVE_CEILING:
            return f"{where}: above the maximum altitude {self.max_agl_m:g} m AGL ({self.ceiling_m[r, c]:.1f} m)"
        if code == WIND:
            u, v, w = _wind_at(x, y, z, *self._state_args[:1], self._state_args[3], *self._state_args[4:7])
            return (f"{where}: wind {math.sqrt(u * u + v * v + w * w):.1f} m/s above the vehicle maximum "
                    f"{self.vehicle.max_wind_mps:g} m/s")
        return f"{where}: {_REASONS.get(code, 'invalid')}"

    def endpoint_problem(self) -> str:
        """Why the start or the goal is invalid ("" if both are valid states)."""
        for name, p in (("start", self.start_xyz), ("goal", self.goal_xyz)):
            why = self.explain_invalid(p)
            if why:
                return f"{self.label}: {name} {why}"
        return ""

    def explain_motion(self, p0, p1) -> str:
        """Why the motion p0 -> p1 is invalid ("" if valid)."""
        code = int(self.motion_codes(p0, p1)[0][0])
        return "" if code == OK else _REASONS.get(code, "invalid")

    # ------------------------------------------------------------------ heuristic bound
    @property
    def energy_ratio_lb(self) -> float:
        """Lower bound of E_w / E_0 over flyable directions and the map's winds, times 0.9."""
        if self._lb_cache is None:
            vprm = self._seg_args[-2]
            dirs = _fibonacci_dirs(400, float(vprm[4]))
            object.__setattr__(self, "_lb_cache", self.energy_ratio_lb_dirs(dirs))
        return self._lb_cache

    def wind_samples(self, max_n: int = 600) -> np.ndarray:
        """Distinct wind vectors of the map (levels and mid-levels), at most ``max_n`` [m/s]."""
        w = self.wind_uvw
        levels = [w]
        if w.shape[0] > 1:
            levels.append(0.5 * (w[1:] + w[:-1]))
        winds = _unique_rows(np.concatenate([lv.reshape(-1, 3) for lv in levels]))
        if winds.shape[0] > max_n:
            winds = winds[np.linspace(0, winds.shape[0] - 1, max_n).astype(int)]
        return np.ascontiguousarray(winds)

    def energy_ratio_lb_dirs(self, dirs) -> float:
        """min of E_w / E_0 over unit directions ``dirs`` (m, 3) and the map's winds, times 0.9
        (1 * 0.9 when no pair is flyable).  Memoised on the bytes of (winds, vehicle, dirs): the
        coverage levels of one mission share the wind map and the vehicle, so the bound is
        computed once for all of them."""
        d = np.ascontiguousarray(np.asarray(dirs, dtype=float).reshape(-1, 3))
        winds = self._wind_samples_cached()
        key = hashlib.sha1(b"".join(np.ascontiguousarray(a, dtype=np.float64).tobytes() for a in
                                    (winds, self._seg_args[-2], self._seg_args[-1], d))).hexdigest()
        r = _memoised(_RATIO_MEMO, key, lambda: _finite_ratio(
            _ratio_kernel(d, winds, self._seg_args[-2], self._seg_args[-1])), 4096)
        return min(1.0, r) * ENERGY_LB_SAFETY

    def wind_samples_dense(self, per_gap: int = WIND_INTERP_SAMPLES) -> np.ndarray:
        """Every wind vector of the map (all columns and levels) and ``per_gap - 1`` evenly
        spaced linear interpolations between adjacent levels, deduplicated [m/s] (m, 3): the
        winds :func:`_wind_at` returns are on those level-to-level segments."""
        w = self.wind_uvw
        parts = [w.reshape(-1, 3)]
        for i in range(1, int(per_gap) if w.shape[0] > 1 else 1):
            f = i / per_gap
            parts.append(((1 - f) * w[:-1] + f * w[1:]).reshape(-1, 3))
        return np.ascontiguousarray(_unique_rows(np.concatenate(parts)))

    def energy_ratio_lb_dense_dirs(self, dirs) -> float:
        """min of E_w / E_0 over unit directions ``dirs`` (m, 3) and every wind of the map
        (:meth:`wind_samples_dense`: all columns, levels and interpolations, no subsampling),
        times :data:`ENERGY_LB_DENSE_SAFETY` (0.99; 1 * 0.99 when no pair is flyable; not capped
        at 1: every wind a segment meets is in the set, so a head wind everywhere counts).  Much
        tighter than :meth:`energy_ratio_lb_dirs` (0.9 margin on <= 600 sampled winds); the
        A* heuristic uses it for the few lattice edge directions.  Memoised like it."""
        d = np.ascontiguousarray(np.asarray(dirs, dtype=float).reshape(-1, 3))
        wkey = self.__dict__.get("_wind_key")
        if wkey is None:   # hashing a mountain wind map costs ~7 ms: once per problem
            wkey = hashlib.sha1(self.wind_uvw.tobytes() + self.wind_z_agl_m.tobytes()).hexdigest()
            object.__setattr__(self, "_wind_key", wkey)
        key = "dense" + hashlib.sha1(wkey.encode() + b"".join(np.ascontiguousarray(a, dtype=np.float64).tobytes()
                                                               for a in (self._seg_args[-2], self._seg_args[-1], d))
                                     ).hexdigest()

        def make() -> float:
            winds = _memoised(_WINDS_MEMO, "densewinds" + wkey, self.wind_samples_dense, 16)
            return _finite_ratio(_ratio_kernel(d, winds, self._seg_args[-2], self._seg_args[-1]))

        r = _memoised(_RATIO_MEMO, key, make, 4096)
        return r * ENERGY_LB_DENSE_SAFETY

    def _wind_samples_cached(self) -> np.ndarray:
        ws = self.__dict__.get("_winds_cache")
        if ws is None:
            key = hashlib.sha1(self.wind_uvw.tobytes() + self.wind_z_agl_m.tobytes()).hexdigest()
            ws = _memoised(_WINDS_MEMO, key, self.wind_samples, 16)
            object.__setattr__(self, "_winds_cache", ws)
        return ws

    @property
    def cost_rate_lb(self) -> float:
        """Admissible lower bound of f per metre of path [-]: w_l + w_r min(risk) +
        w_d min(landing) + w_e * energy_ratio_lb (every term of eq. 11 is >= rate * length)."""
        wl, wr, wd, we = self.weights
        fin = np.isfinite(self.floor_m)
        rmin = float(self.risk_cost[fin].min()) if fin.any() else 0.0
        dmin = float(self.landing_cost[fin].min()) if fin.any() else 0.0
        e = self.energy_ratio_lb if we > 0 else 0.0
        return wl + wr * max(rmin, 0.0) + wd * max(dmin, 0.0) + we * e


# --------------------------------------------------------------------------- construction


def _check_weights(weights) -> tuple[float, float, float, float]:
    try:
        w = tuple(float(x) for x in weights)
    except Exception as exc:
        raise InputError(f"weights must be 4 numbers (w_l, w_r, w_d, w_e), got {weights!r}") from exc
    if len(w) != 4:
        raise InputError(f"weights must be 4 numbers (w_l, w_r, w_d, w_e), got {len(w)}")
    if not all(math.isfinite(x) and x >= 0 for x in w):
        raise InputError(f"weights {w} must be finite and >= 0 (w_l, w_r, w_d, w_e)")
    if sum(w) == 0:
        raise InputError("weights are all zero: give at least one positive weight (e.g. w_l = 1)")
    return w


def _raster(a, shape, name: str, default: float | None = None) -> np.ndarray:
    if a is None:
        if default is None:
            raise InputError(f"{name} is required")
        return np.full(shape, default)
    if np.isscalar(a):
        return np.full(shape, float(a))
    v = np.asarray(a.values if isinstance(a, xr.DataArray) else a, dtype=np.float64)
    if v.shape != shape:
        raise InputError(f"{name} has shape {v.shape}; expected the grid shape {shape} (ny, nx)")
    return v


def _wind_arrays(wind, grid: Grid):
    """(wind_uvw, wind_z_agl_m, wind_grid) from a wind map, a UniformWind or a (3,) vector."""
    if wind is None:
        return np.zeros(3), np.zeros(1), None
    if hasattr(wind, "components") and callable(wind.components):
        return np.asarray(wind.components(), dtype=float), np.zeros(1), None
    if isinstance(wind, xr.Dataset):
        for k in ("u", "v"):
            if k not in wind:
                raise InputError(f"wind dataset needs variables u, v (and w) on (z, y, x); missing {k}")
        u = wind["u"].transpose("z", "y", "x").values
        v = wind["v"].transpose("z", "y", "x").values
        w = wind["w"].transpose("z", "y", "x").values if "w" in wind else np.zeros_like(u)
        z = np.asarray(wind["z"].values, dtype=float)
        x = np.asarray(wind["x"].values, dtype=float)
        y = np.asarray(wind["y"].values, dtype=float)
        if x.size >= 2 and y.size >= 2:
            wg = Grid.from_dataarray(wind)
        else:
            res = float(wind.attrs.get("horizontal_step_m", grid.resolution_m))
            wg = Grid(grid.crs_wkt, float(x[0] - res / 2), float(y[0] + res / 2), x.size, y.size, res)
        return np.stack([u, v, w], axis=-1), z, wg
    a = np.asarray(wind, dtype=float)
    if a.shape == (3,):
        return a, np.zeros(1), None
    raise InputError("wind must be a wind_on_grid Dataset, a UniformWind or (u, v, w) [m/s]")


def _unique_rows(a: np.ndarray) -> np.ndarray:
    """The distinct rows of ``a`` (n, k) in lexicographic order, as ``np.unique(a, axis=0)``,
    deduplicated by hashing first (``np.unique(axis=0)`` sorts every row: 18 s for the wind
    map of a 30 m mountain grid, 0.4 s this way)."""
    import pandas as pd

    u = pd.DataFrame(np.asarray(a, dtype=float)).drop_duplicates().to_numpy(dtype=float)
    return u[np.lexsort(u.T[::-1])]


def build_problem(surface_ds: xr.Dataset, clearance_floor, coverage_floor_j, risk_cost, landing_cost, wind,
                  vehicle, weights, start_xyz, goal_xyz, min_agl_m: float, max_agl_m: float,
                  dop_threshold: float | None = None, *, dop_kind: str = "PDOP", nofly=None,
                  label: str | None = None, subsegment_m: float = 10.0,
                  check_endpoints: bool = True) -> PlanningProblem:
    """A validated :class:`PlanningProblem` for one coverage level.

    ``surface_ds``: :func:`~skyroute.stages.surface.build_surface` output (``terrain`` [m],
    grid and CRS); ``clearance_floor``: (y, x) lowest sphere-centre altitude [m]
    (:func:`~skyroute.stages.clearance.clearance_floor` with r_p); ``coverage_floor_j``: (y, x)
    altitude [m] above which DOP < D_j (NaN = never: forbidden) or None (no GNSS constraint);
    ``risk_cost`` / ``landing_cost``: dimensionless maps (None = 0; +inf risk = no-fly);
    ``wind``: a :func:`~skyroute.stages.wind.wind_on_grid` Dataset (heights above ground), a
    UniformWind or (u, v, w) [m/s]; ``start_xyz`` / ``goal_xyz``: (x, y, absolute z) [m];
    ``min_agl_m`` / ``max_agl_m``: altitude limits above ground [m]; ``nofly``: optional (y, x)
    bool mask (already dilated by r_p).

    Raises InputError for bad weights/shapes/limits and PlanningError (with the reason) when
    the start or the goal is not a valid state (unless ``check_endpoints=False``: STEP I then
    reports that level as "no solution" with the reason, seed 001 Table 4).
    """
    if not isinstance(surface_ds, xr.Dataset) or "terrain" not in surface_ds:
        raise InputError("surface_ds must be the build_surface Dataset (with a 'terrain' variable)")
    grid = Grid.from_dataarray(surface_ds["terrain"])
    shape = grid.shape
    w = _check_weights(weights)
    if not (np.isfinite(min_agl_m) and np.isfinite(max_agl_m) and 0 <= min_agl_m < max_agl_m):
        raise InputError(f"altitude limits need 0 <= min_agl_m < max_agl_m, got {min_agl_m}, {max_agl_m} m")
    veh = load_vehicle(vehicle)
    terrain = _raster(surface_ds["terrain"], shape, "terrain")
    if not np.isfinite(terrain).all():
        raise InputError("terrain has NaN/inf cells: fill no-data first")
    clear = _raster(clearance_floor, shape, "clearance_floor")
    cover = None if coverage_floor_j is None else _raster(coverage_floor_j, shape, "coverage_floor_j")
    risk = _raster(risk_cost, shape, "risk_cost", 0.0)
    land = _raster(landing_cost, shape, "landing_cost", 0.0)
    for name, a in (("risk_cost", risk), ("landing_cost", land)):
        if np.any(np.nan_to_num(a, nan=-1.0, posinf=0.0) < 0):
            raise InputError(f"{name} must be >= 0 (dimensionless; NaN not allowed)")
    nf = np.zeros(shape, bool) if nofly is None else np.asarray(
        nofly.values if isinstance(nofly, xr.DataArray) else nofly).astype(bool)
    if nf.shape != shape:
        raise InputError(f"nofly has shape {nf.shape}; expected {shape}")
    nf = nf | np.isinf(risk)
    floor = np.maximum(clear, terrain + float(min_agl_m))
    if cover is not None:
        floor = np.maximum(floor, np.where(np.isfinite(cover), cover, np.inf))
    floor = np.where(nf, np.inf, floor)
    # maximum AGL: relative to the LOWEST ground in the cell (``terrain_min`` where the surface
    # stage has it), so the ceiling holds at every point of the cell
    ground_low = _raster(surface_ds["terrain_min"], shape, "terrain_min") if "terrain_min" in surface_ds else terrain
    ceiling = ground_low + float(max_agl_m)
    wuvw, wz, wg = _wind_arrays(wind, grid)
    for name, p in (("start_xyz", start_xyz), ("goal_xyz", goal_xyz)):
        if np.asarray(p, dtype=float).shape != (3,):
            raise InputError(f"{name} must be (x, y, z) [m], got {p!r}")
    if label is None:
        label = f"D={dop_threshold:g}" if dop_threshold is not None else "no GNSS constraint"
    prob = PlanningProblem(grid=grid, terrain_m=terrain, floor_m=floor, ceiling_m=ceiling,
                           risk_cost=np.where(np.isinf(risk), 0.0, risk), landing_cost=land, wind_uvw=wuvw,
                           vehicle=veh, weights=w, start_xyz=tuple(start_xyz), goal_xyz=tuple(goal_xyz),
                           dop_threshold=dop_threshold, label=label, wind_z_agl_m=wz, wind_grid=wg,
                           clearance_m=clear, coverage_m=cover, nofly=nf, min_agl_m=float(min_agl_m),
                           max_agl_m=float(max_agl_m), dop_kind=dop_kind, subsegment_m=subsegment_m)
    if check_endpoints:
        why = prob.endpoint_problem()
        if why:
            raise PlanningError(why)
    return prob


def xyz_from_agl(surface_ds: xr.Dataset, x: float, y: float, alt_agl_m: float) -> tuple[float, float, float]:
    """(x, y, terrain + alt_agl_m) [m] for a mission point given above ground."""
    g = Grid.from_dataarray(surface_ds["terrain"])
    r, c = g.index_of(x, y)
    if not (0 <= r < g.ny and 0 <= c < g.nx):
        raise InputError(f"point ({x}, {y}) is outside the grid {g.bounds}")
    return (float(x), float(y), float(surface_ds["terrain"].values[r, c]) + float(alt_agl_m))


__all__ = ["COST_NAMES", "ENERGY_LB_DENSE_SAFETY", "PlanningProblem", "build_problem", "segment_eval",
           "segment_eval_if_valid", "xyz_from_agl"]
