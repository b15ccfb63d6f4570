"""Segment time and energy of a multirotor in wind (seed 000, section III-A.1, eq. 2-12).

Frames and units
----------------
Map coordinates x east, y north, z up [m] (ENU, like :mod:`skyroute.stages.wind`: ``u`` east,
``v`` north, ``w`` up [m/s]).  Seed 000 writes NED; only the sign of the vertical differs.

Velocities of a planner segment (eq. 2-3)
-----------------------------------------
A segment p0 -> p1 (unit direction ``s``, length L) is split into sub-segments of length
``subsegment_m`` (Delta s_s; the last one is shorter).  On sub-segment i with wind ``w_i``
(sampled at its initial point) the tentative airspeed is ``v_a = v_c s - w_i`` (eq. 2) and the
ground speed along ``s`` is (eq. 3)

* m_- case, ``|v_a| > v_max``: the ground speed g is reduced so that ``|g s - w_i| = 0.8 v_max``,
  i.e. ``g = w_s + sqrt((0.8 v_max)^2 - |w_perp|^2)`` (the larger root; ``w_s = w.s``,
  ``w_perp`` the cross-track wind).  No root (cross wind above 0.8 v_max) or ``g < v_min`` ->
  the segment is **not flyable**;
* m_+ case, ``v_a . s < 0`` (tail wind faster than v_c along track): ``g = w_s``, so that the
  along-track airspeed is zero;
* otherwise ``g = v_c``.

Then the current airspeed is ``v~_a = g s - w_i``, the time ``tau_i = Delta s_i / g`` (eq. 4).
A wind speed ``|w_i|`` above ``max_wind_mps`` also makes the segment not flyable (seed 000,
planner bounds).  Non-flyable segments get ``time_s = energy_J = inf``.

Power (eq. 5-10)
----------------
``P = P_r + P_0 + P_p + P_c`` with, per rotor thrust ``T/N_b`` and ``Omega`` from eq. 10
(``T/N_b = C_t rho pi R^4 Omega^2``, C_t of eq. 8 a vehicle constant):

* ``P_r + P_0 = N_b rho pi R^2 (Omega R)^3 (C_pr + C_po)`` (eq. 6) with
  ``C_pr = kappa C_t^1.5 / sqrt(2)`` (eq. 7), which reduces to ``kappa T^1.5 / sqrt(2 rho A)``
  (momentum theory, A total disc area), and
  ``C_po = sigma C_d / 8 (1 + K_v mu^2)``, ``mu = v~_a(s) / (Omega R)`` (eq. 9; the paper prints
  ``Omega R_b^2``, a typo for the advance ratio; as in the paper ``v~_a(s)`` is the airspeed
  component along the segment);
* ``P_p = D . v~_a = 1/2 rho S |v~_a|^3``: quadratic drag along the airspeed with the
  attitude-dependent area ``S = S_side sqrt(1 - (d.t)^2) + S_top |d.t|`` (d unit airspeed,
  t thrust axis); ``T`` and ``t`` come from the 3-D trim ``T t = m g z + 1/2 rho S |v| v``
  (weight plus drag; the trim equations the paper omits), solved by fixed-point iteration;
* ``P_c = m g v_z`` when climbing; **descending costs half of it**, ``P_c = 0.5 m g |v_z|``
  (positive: "in descending phase ... half of climbing power is accounted for"); ``v_z = g s_z``
  is the vertical ground speed.

Energy (eq. 12)
---------------
``E_w = sum_i P_i tau_i``; ``E_0`` is the same with zero wind (``g = v_c``); the energy cost of a
segment is ``Delta C_e = E_w / E_0 * Delta l``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numba
import numpy as np
import xarray as xr

from skyroute.stages.base import InputError
from skyroute.stages.vehicle import G0, VehicleProfile, load_vehicle

RHO0 = 1.225  # ISA sea-level air density [kg/m^3]
M_MINUS_FRACTION = 0.8  # m_-: airspeed kept at 80 % of v_max (seed 000, after eq. 3)

WindLike = np.ndarray | Callable[[np.ndarray], np.ndarray]


@numba.njit(cache=True, nogil=True)
def eq3_ground_speed(sx, sy, sz, u, v, w, vc, vmax):
    """Ground speed [m/s] along the unit direction (sx, sy, sz) in the wind (u, v, w) [m/s] by
    seed 000 eq. 3 (the one home of the rule; compiled, callable from kernels and Python):
    ``v_c`` when the airspeed of eq. 2 is within ``v_max`` and the wind does not outrun the
    vehicle; the wind's along-track part when it does; otherwise the ``m_-`` root (airspeed held
    at ``M_MINUS_FRACTION v_max``), NaN when that root does not exist."""
    ws = u * sx + v * sy + w * sz
    w2 = u * u + v * v + w * w
    van = math.sqrt((vc * sx - u) ** 2 + (vc * sy - v) ** 2 + (vc * sz - w) ** 2)
    if van > vmax:
        a = M_MINUS_FRACTION * vmax
        disc = a * a - max(w2 - ws * ws, 0.0)
        if disc < 0.0:
            return math.nan
        return ws + math.sqrt(disc)
    if vc - ws < 0.0:
        return ws
    return vc


@numba.njit(cache=True, nogil=True)
def _eq3_many(s, w, vc, vmax, out):
    for i in range(s.shape[0]):
        out[i] = eq3_ground_speed(s[i, 0], s[i, 1], s[i, 2], w[i, 0], w[i, 1], w[i, 2], vc, vmax)


class PowerParams(NamedTuple):
    """Rotor-power parameters of :func:`power_kernel` (a numba-friendly record; built by
    :func:`power_params`, its one packing)."""

    weight_n: float                 # vehicle weight m g [N]
    air_density_kgpm3: float        # rho [kg/m^3]
    drag_area_side_m2: float        # S_side [m^2]
    drag_area_top_m2: float         # S_top [m^2]
    rotor_count: float              # N_b [-]
    rotor_radius_m: float           # R [m]
    thrust_coefficient: float       # C_t [-] (eq. 8)
    blade_drag_coefficient: float   # C_d [-]
    solidity: float                 # sigma [-]
    induced_power_factor: float     # kappa [-]
    profile_advance_factor: float   # K_v [-]
    max_iter: int                   # trim fixed-point iterations [-]


@numba.njit(cache=True, nogil=True)
def power_kernel(v, vs, vz, prm, out):
    """Trim (fixed point on the thrust axis) and eq. 6-10 per airspeed sample (compiled; ``prm``
    a :class:`PowerParams`); ``out`` (k, 8) gets the columns of ``_POWER_KEYS``; see rotor_power."""
    weight, rho, s_side, s_top, nb, radius, ct, cd, sigma, kappa, kv, max_iter = prm
    for i in range(v.shape[0]):
        sp = math.sqrt(v[i, 0] ** 2 + v[i, 1] ** 2 + v[i, 2] ** 2)
        dx, dy, dz = 0.0, 0.0, 0.0
        if sp > 0.0:
            dx, dy, dz = v[i, 0] / sp, v[i, 1] / sp, v[i, 2] / sp
        q = 0.5 * rho * sp * sp
        tx, ty, tz = 0.0, 0.0, 1.0
        area = -1.0
        fx, fy, fz = 0.0, 0.0, weight
        for _ in range(int(max_iter)):              # T t = W z + q S d
            c = abs(dx * tx + dy * ty + dz * tz)
            new_area = s_side * math.sqrt(max(1.0 - c * c, 0.0)) + s_top * c
            fx, fy, fz = q * new_area * dx, q * new_area * dy, q * new_area * dz + weight
            tn = math.sqrt(fx * fx + fy * fy + fz * fz)
            tx, ty, tz = fx / tn, fy / tn, fz / tn
            conv = abs(new_area - area) < 1e-14
            area = new_area
            if conv:
                break
        thrust = math.sqrt(fx * fx + fy * fy + fz * fz)
        omega = math.sqrt(thrust / nb / (rho * math.pi * radius**4 * ct))            # eq. 10
        tip = omega * radius
        scale = nb * rho * math.pi * radius**2 * tip**3                              # eq. 6
        mu = vs[i] / tip if tip > 0.0 else 0.0
        p_ind = scale * kappa * ct**1.5 / math.sqrt(2.0)                             # eq. 7
        p_prof = scale * sigma * cd / 8.0 * (1.0 + kv * mu * mu)                     # eq. 9
        p_par = q * area * sp
        p_climb = weight * vz[i] if vz[i] >= 0.0 else -0.5 * weight * vz[i]
        out[i, 0] = p_ind
        out[i, 1] = p_prof
        out[i, 2] = p_par
        out[i, 3] = p_climb
        out[i, 4] = p_ind + p_prof + p_par + p_climb
        out[i, 5] = thrust
        out[i, 6] = math.degrees(math.acos(min(1.0, max(-1.0, fz / thrust))))
        out[i, 7] = omega


_POWER_KEYS = ("induced_W", "profile_W", "parasitic_W", "climb_W", "total_W", "thrust_N", "tilt_deg",
               "omega_radps")


def power_params(veh: VehicleProfile, air_density: float = RHO0, max_iter: int = 200) -> PowerParams:
    """The rotor-power parameters of :func:`power_kernel` for ``veh`` (their one packing)."""
    r, af = veh.rotor, veh.airframe
    f = float
    return PowerParams(f(veh.weight_n), f(air_density), f(af.drag_area_side_m2), f(af.drag_area_top_m2), f(r.count),
                       f(r.radius_m), f(r.thrust_coefficient), f(r.blade_drag_coefficient), f(r.solidity),
                       f(r.induced_power_factor), f(r.profile_advance_factor), int(max_iter))


def rotor_power(airspeed_enu, along_track_airspeed_mps, climb_rate_mps, vehicle: VehicleProfile | str,
                air_density: float = RHO0, max_iter: int = 200) -> dict[str, np.ndarray]:
    """Power terms of eq. 5-10 for airspeed vectors ``airspeed_enu`` (k,3) [m/s].

    ``along_track_airspeed_mps`` (k,) is ``v~_a(s)`` of eq. 9 [m/s]; ``climb_rate_mps`` (k,) the
    vertical ground speed [m/s] (climb term).  Returns arrays (k,) ``induced_W``,
    ``profile_W``, ``parasitic_W``, ``climb_W``, ``total_W``, ``thrust_N``, ``tilt_deg`` (angle of
    the thrust axis from vertical), ``omega_radps`` (rotor speed, eq. 10).  The trim fixed point
    converges geometrically (|dS| < 1e-14 m^2 in ~30 iterations at 23 m/s).
    """
    veh = load_vehicle(vehicle)
    v = np.ascontiguousarray(np.asarray(airspeed_enu, dtype=float).reshape(-1, 3))
    k = v.shape[0]
    vs = np.ascontiguousarray(np.broadcast_to(np.asarray(along_track_airspeed_mps, dtype=float).reshape(-1), (k,)))
    vz = np.ascontiguousarray(np.broadcast_to(np.asarray(climb_rate_mps, dtype=float).reshape(-1), (k,)))
    if not (np.isfinite(v).all() and np.isfinite(vs).all() and np.isfinite(vz).all()):
        raise InputError("airspeed / climb rate contain NaN or inf")
    if not air_density > 0:
        raise InputError(f"air_density must be > 0 [kg/m^3], got {air_density}")
    prm = power_params(veh, air_density, max_iter)
    out = np.empty((k, len(_POWER_KEYS)))
    power_kernel(v, vs, vz, prm, out)
    return {name: out[:, j] for j, name in enumerate(_POWER_KEYS)}


def ground_speed(direction, wind_enu, vehicle: VehicleProfile | str) -> tuple[np.ndarray, np.ndarray]:
    """Ground speed g [m/s] along unit ``direction`` (k,3) in wind ``wind_enu`` (k,3) by eq. 3,
    and the flyable flag (g >= v_min, the m_- root exists, ``|wind| <= max_wind_mps``).
    g is NaN where the m_- root does not exist."""
    veh = load_vehicle(vehicle)
    s = np.asarray(direction, dtype=float).reshape(-1, 3)
    w = np.asarray(wind_enu, dtype=float).reshape(-1, 3)
    vc, vmax = veh.cruise_speed_mps, veh.max_airspeed_mps
    w2 = np.einsum("ij,ij->i", w, w)
    s, w = np.broadcast_arrays(s, w)
    g = np.empty(s.shape[0])
    _eq3_many(np.ascontiguousarray(s), np.ascontiguousarray(w), float(vc), float(vmax), g)
    flyable = (np.isfinite(g) & (g >= veh.min_ground_speed_mps) & (g > 0.0)
               & (np.sqrt(w2) <= veh.max_wind_mps))
    return g, flyable


def _check_points(p0, p1) -> tuple[np.ndarray, np.ndarray]:
    p0 = np.asarray(p0, dtype=float)
    p1 = np.asarray(p1, dtype=float)
    if p0.ndim == 1:
        p0 = p0[None, :]
    if p1.ndim == 1:
        p1 = p1[None, :]
    if p0.shape != p1.shape or p0.ndim != 2 or p0.shape[1] != 3:
        raise InputError(f"p0 and p1 must both have shape (n, 3) [m]; got {p0.shape} and {p1.shape}")
    if not (np.isfinite(p0).all() and np.isfinite(p1).all()):
        raise InputError("p0/p1 contain NaN or inf; give finite map coordinates [m]")
    return p0, p1


def segment_energy(p0, p1, wind_uvw: WindLike, vehicle: VehicleProfile | str = "dji-m300-rtk",
                   subsegment_m: float = 10.0, air_density: float = RHO0) -> dict[str, np.ndarray]:
    """Time and energy of straight segments ``p0[j] -> p1[j]`` (n,3) [m] (seed 000 eq. 2-12).

    ``wind_uvw``: either an array (n,3) [m/s], one wind per segment (then every sub-segment has
    the same wind and sub-division is not needed: results equal the sub-segment sum), or a
    callable ``wind(points (k,3)) -> (k,3)`` sampled at the initial point of every sub-segment of
    length ``subsegment_m`` [m] (Delta s_s).

    Returns a dict of arrays (n,): ``length_m``, ``time_s`` [s] (eq. 4 summed), ``energy_J`` (E_w),
    ``energy_nowind_J`` (E_0), ``flyable`` (bool), ``ground_speed_mps`` (L / time),
    ``airspeed_mps`` (time-weighted mean of |v~_a|), ``power_W`` (E_w / time),
    ``flight_path_angle_deg`` (of the segment, positive up).  Where not flyable ``time_s`` and
    ``energy_J`` are inf; zero-length segments take zero time and energy.
    """
    veh = load_vehicle(vehicle)
    p0, p1 = _check_points(p0, p1)
    n = p0.shape[0]
    if not subsegment_m > 0:
        raise InputError(f"subsegment_m must be > 0 [m], got {subsegment_m}")
    delta = p1 - p0
    length = np.linalg.norm(delta, axis=1)
    s = np.divide(delta, length[:, None], out=np.zeros_like(delta), where=length[:, None] > 0)
    if callable(wind_uvw):
        k = np.maximum(1, np.ceil(length / subsegment_m - 1e-9).astype(np.int64))
        seg = np.repeat(np.arange(n), k)
        first = np.concatenate([[0], np.cumsum(k)[:-1]])
        idx = np.arange(seg.size) - first[seg]
        ds = np.minimum(subsegment_m, length[seg] - idx * subsegment_m)
        start = p0[seg] + s[seg] * (idx * subsegment_m)[:, None]
        w = np.asarray(wind_uvw(start), dtype=float)
        if w.shape != (seg.size, 3):
            raise InputError(f"wind callable returned shape {w.shape}; expected ({seg.size}, 3) [m/s]")
    else:
        w = np.asarray(wind_uvw, dtype=float)
        if w.ndim == 1:
            w = np.broadcast_to(w, (n, 3))
        if w.shape != (n, 3):
            raise InputError(f"wind_uvw must have shape (n, 3) = ({n}, 3) [m/s] or be a callable; got {w.shape}")
        seg, ds, first = np.arange(n), length, np.arange(n)
    if not np.isfinite(w).all():
        raise InputError("wind contains NaN or inf (is a point outside the wind map?)")
    ss = s[seg]
    g, ok = ground_speed(ss, w, veh)
    ok |= ds <= 0
    g_safe = np.where(ok & (g > 0), g, veh.cruise_speed_mps)
    va = g_safe[:, None] * ss - w
    pw = rotor_power(va, np.einsum("ij,ij->i", va, ss), g_safe * ss[:, 2], veh, air_density)["total_W"]
    tau = np.where(ds > 0, ds / g_safe, 0.0)
    time = np.add.reduceat(tau, first) if n else np.zeros(0)
    energy = np.add.reduceat(pw * tau, first) if n else np.zeros(0)
    va_mean = np.add.reduceat(np.linalg.norm(va, axis=1) * tau, first) if n else np.zeros(0)
    flyable = np.logical_and.reduceat(ok, first) if n else np.zeros(0, bool)
    # no wind: g = v_c, airspeed v_c s
    vc = veh.cruise_speed_mps
    p_nowind = rotor_power(vc * s, np.full(n, vc), vc * s[:, 2], veh, air_density)["total_W"]
    e0 = p_nowind * length / vc
    with np.errstate(invalid="ignore", divide="ignore"):
        gs = np.where(time > 0, length / time, 0.0)
        va_mean = np.where(time > 0, va_mean / time, 0.0)
        power = np.where(time > 0, energy / time, 0.0)
    inf = np.inf
    return {"length_m": length,
            "time_s": np.where(flyable, time, inf),
            "energy_J": np.where(flyable, energy, inf),
            "energy_nowind_J": e0,
            "flyable": flyable,
            "ground_speed_mps": np.where(flyable, gs, 0.0),
            "airspeed_mps": np.where(flyable, va_mean, np.nan),
            "power_W": np.where(flyable, power, np.nan),
            "flight_path_angle_deg": np.degrees(np.arcsin(np.clip(s[:, 2], -1.0, 1.0)))}


def energy_cost(p0, p1, wind_uvw: WindLike, vehicle: VehicleProfile | str = "dji-m300-rtk",
                subsegment_m: float = 10.0, air_density: float = RHO0) -> np.ndarray:
    """Energy cost of each segment, ``Delta C_e = E_w / E_0 * Delta l`` [m] (seed 000 eq. 12);
    inf where the segment is not flyable, 0 for zero-length segments."""
    r = segment_energy(p0, p1, wind_uvw, vehicle, subsegment_m, air_density)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = r["energy_J"] / r["energy_nowind_J"] * r["length_m"]
    return np.where(r["length_m"] > 0, c, 0.0)


_UNITS = {"length_m": ("m", "segment length"), "time_s": ("s", "time to fly (eq. 4)"),
          "energy_J": ("J", "energy with wind E_w"), "energy_nowind_J": ("J", "energy without wind E_0"),
          "flyable": ("1", "segment is flyable"), "ground_speed_mps": ("m s-1", "mean ground speed"),
          "airspeed_mps": ("m s-1", "time-mean airspeed"), "power_W": ("W", "mean power"),
          "flight_path_angle_deg": ("degree", "flight path angle (positive up)"),
          "energy_cost_m": ("m", "energy cost E_w/E_0 * length (eq. 12)")}


def segment_energy_dataset(p0, p1, wind_uvw: WindLike, vehicle: VehicleProfile | str = "dji-m300-rtk",
                           subsegment_m: float = 10.0, air_density: float = RHO0) -> xr.Dataset:
    """:func:`segment_energy` as an ``xarray.Dataset`` on dim ``segment`` with ``units`` attrs,
    plus ``energy_cost_m`` (eq. 12)."""
    veh = load_vehicle(vehicle)
    r = segment_energy(p0, p1, wind_uvw, veh, subsegment_m, air_density)
    with np.errstate(invalid="ignore", divide="ignore"):
        r["energy_cost_m"] = np.where(r["length_m"] > 0,
                                      r["energy_J"] / r["energy_nowind_J"] * r["length_m"], 0.0)
    ds = xr.Dataset({k: ("segment", v, {"units": _UNITS[k][0], "long_name": _UNITS[k][1]})
                     for k, v in r.items()})
    ds.attrs.update(vehicle=veh.name, subsegment_m=float(subsegment_m), air_density_kgpm3=float(air_density),
                    source="Causa & Fasano, seed 000, eq. 2-12")
    return ds


__all__ = ["G0", "RHO0", "PowerParams", "energy_cost", "ground_speed", "rotor_power", "segment_energy",
           "segment_energy_dataset"]
