"""Energy of a fixed-wing aircraft along straight flight (seed 002 eq. 2-11), with wind.

Seed 002 (Aiello et al.) splits the energy to fly from node i to node j into (eq. 2)

* the drag work ("kinetic" term, eq. 8-9): ``D = W (A V^2 + B / V^2)`` (eq. 4-6, lift = weight)
  times the distance flown **through the air**.  In still air that is ``D * Delta d``; in a
  wind ``w`` the aircraft holds its airspeed ``V`` and the wind triangle gives the ground speed
  ``g`` along the track (:func:`ground_speed_mps`), the flight takes ``Delta d / g`` and the
  air distance is ``V Delta d / g``.  ``rho`` in A and B is the mean of the densities at both
  ends (eq. 10, ISA: :mod:`skyroute.stages.atmosphere`); the airspeed is the vehicle's flown
  airspeed at that density (:meth:`~skyroute.stages.vehicle.FixedWingProfile.airspeed_at`:
  the Carson speed ``(B/A)^(1/4)`` of the seed, kept above the stall margin).
* the potential energy, counted only when climbing (eq. 3, whose printed sign is a misprint):
  ``max(m g (z_j - z_i), 0)``;
* the kinetic energy of a change of airspeed, counted only when speeding up:
  ``max(m (V_j^2 - V_i^2) / 2, 0)`` with ``V`` the flown airspeed at the end altitudes (the
  Carson speed grows as ``rho^(-1/2)`` with altitude; descending costs nothing back);
* turns (eq. 11) are neglected as in the seed (section 3.2, last paragraph).

Efficiency is 100 % as in the seed (the result is the mechanical work, the battery's share of
it is not modelled).  The compiled kernels (``*_kernel``) are called by the fixed-wing lattice
planner (:mod:`skyroute.stages.planning.fixedwing`); :func:`segment_energy_fw` is the public
vectorised function.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from skyroute.stages import vehicle as _veh
from skyroute.stages.atmosphere import density_kernel, isa_density_kgpm3
from skyroute.stages.base import InputError
from skyroute.stages.vehicle import FixedWingProfile, load_vehicle

ENERGY_KEYS = ("drag_J", "potential_J", "speed_change_J", "energy_J", "time_s", "airspeed_mps", "ground_speed_mps")


class FixedWingParams(NamedTuple):
    """The numbers of a :class:`~skyroute.stages.vehicle.FixedWingProfile` the kernels need."""

    mass_kg: float
    weight_n: float
    parasite_area_m2: float       # f = C_D0 S
    span_m: float                 # b
    oswald: float                 # e
    wing_area_m2: float           # S
    max_lift_coefficient: float   # C_L,max
    min_airspeed_factor: float    # flown airspeed >= factor x stall
    max_airspeed_mps: float


def fixedwing_params(vehicle: FixedWingProfile | str) -> FixedWingParams:
    """:class:`FixedWingParams` of a fixed-wing profile (InputError for a multirotor)."""
    v = load_vehicle(vehicle)
    if not isinstance(v, FixedWingProfile):
        raise InputError(f"vehicle {v.name!r} is a {v.kind}; the fixed-wing energy model needs kind fixed-wing")
    return FixedWingParams(float(v.mass_kg), float(v.weight_n), float(v.parasite_area_m2), float(v.wing_span_m),
                           float(v.oswald_factor), float(v.wing_area_m2), float(v.max_lift_coefficient),
                           float(v.min_airspeed_factor), float(v.max_airspeed_mps))


# the drag-polar formulas of :mod:`skyroute.stages.vehicle` (their one home), compiled
_polar_a = numba.njit(cache=True, nogil=True)(_veh.polar_a)
_polar_b = numba.njit(cache=True, nogil=True)(_veh.polar_b)
_carson = numba.njit(cache=True, nogil=True)(_veh.carson_speed)
_stall = numba.njit(cache=True, nogil=True)(_veh.stall_speed)
_flown = numba.njit(cache=True, nogil=True)(_veh.flown_airspeed)


@numba.njit(cache=True, nogil=True)
def airspeed_kernel(rho, prm):
    """Flown airspeed [m/s] at density ``rho``: min(max(V_opt, k V_stall), V_max)."""
    a = _polar_a(rho, prm.parasite_area_m2, prm.weight_n)
    b = _polar_b(rho, prm.weight_n, prm.span_m, prm.oswald)
    return _flown(_carson(a, b), _stall(rho, prm.weight_n, prm.wing_area_m2, prm.max_lift_coefficient),
                  prm.min_airspeed_factor, prm.max_airspeed_mps)


@numba.njit(cache=True, nogil=True)
def drag_n_kernel(rho, v, prm):
    """Drag D = W (A V^2 + B / V^2) [N] at density ``rho`` and airspeed ``v`` (eq. 4-6)."""
    a = _polar_a(rho, prm.parasite_area_m2, prm.weight_n)
    b = _polar_b(rho, prm.weight_n, prm.span_m, prm.oswald)
    return prm.weight_n * (a * v * v + b / (v * v))


@numba.njit(cache=True, nogil=True)
def ground_speed_kernel(sx, sy, sz, u, v, w, airspeed):
    """Wind triangle: ground speed g [m/s] along the unit track (sx, sy, sz) flown at
    ``airspeed`` [m/s] in the wind (u, v, w) [m/s], i.e. the root g > 0 of
    ``|g s - wind| = airspeed``: ``g = s.w + sqrt(V^2 - |w|^2 + (s.w)^2)``; NaN when the
    aircraft cannot hold the track or makes no progress along it."""
    ws = sx * u + sy * v + sz * w
    disc = airspeed * airspeed - (u * u + v * v + w * w) + ws * ws
    if disc < 0.0:
        return math.nan
    g = ws + math.sqrt(disc)
    if g <= 0.0:
        return math.nan
    return g


@numba.njit(cache=True, nogil=True)
def piece_energy_kernel(length, sx, sy, sz, z0, z1, u, v, w, prm, out):
    """Energy of a straight piece of 3-D ``length`` [m] along the unit (sx, sy, sz) from
    altitude z0 to z1 [m] in the constant wind (u, v, w) [m/s]; ``out`` (7,) gets the columns
    of ``ENERGY_KEYS`` (inf energy and time when the wind triangle has no solution)."""
    r0 = density_kernel(z0)
    r1 = density_kernel(z1)
    rho = 0.5 * (r0 + r1)                                   # eq. 10
    va = airspeed_kernel(rho, prm)
    g = ground_speed_kernel(sx, sy, sz, u, v, w, va)
    out[5] = va
    out[1] = max(prm.weight_n * (z1 - z0), 0.0)             # eq. 3 (climb only)
    out[2] = 0.0
    if z1 > z0:                                             # the airspeed only grows when climbing
        v0 = airspeed_kernel(r0, prm)
        v1 = airspeed_kernel(r1, prm)
        out[2] = max(0.5 * prm.mass_kg * (v1 * v1 - v0 * v0), 0.0)
    if length == 0.0:
        out[0] = 0.0
        out[3] = out[1] + out[2]
        out[4] = 0.0
        out[6] = va
        return
    if math.isnan(g):
        out[0] = np.inf
        out[3] = np.inf
        out[4] = np.inf
        out[6] = math.nan
        return
    t = length / g
    out[0] = drag_n_kernel(rho, va, prm) * va * t           # eq. 8-9: drag x air distance
    out[3] = out[0] + out[1] + out[2]
    out[4] = t
    out[6] = g


@numba.njit(cache=True, nogil=True)
def _segments(p0, p1, wind, prm, out):
    buf = np.empty(7)
    for i in range(p0.shape[0]):
        dx, dy, dz = p1[i, 0] - p0[i, 0], p1[i, 1] - p0[i, 1], p1[i, 2] - p0[i, 2]
        length = math.sqrt(dx * dx + dy * dy + dz * dz)
        sx = dx / length if length > 0 else 0.0
        sy = dy / length if length > 0 else 0.0
        sz = dz / length if length > 0 else 0.0
        piece_energy_kernel(length, sx, sy, sz, p0[i, 2], p1[i, 2], wind[i, 0], wind[i, 1], wind[i, 2], prm, buf)
        for k in range(7):
            out[i, k] = buf[k]


def segment_energy_fw(p0, p1, wind_uvw=(0.0, 0.0, 0.0), vehicle: FixedWingProfile | str = "skywalker-x8"
                      ) -> dict[str, np.ndarray]:
    """Seed-002 energy of straight segments p0[i] -> p1[i] ((n, 3) [m], z above mean sea level)
    in a constant wind per segment (``wind_uvw`` (3,) or (n, 3) [m/s], u east, v north, w up).

    Returns arrays (n,): ``drag_J``, ``potential_J``, ``speed_change_J``, ``energy_J`` (their
    sum), ``time_s``, ``airspeed_mps`` (flown), ``ground_speed_mps`` (wind triangle; NaN and
    inf energy/time where the aircraft cannot hold the track against the wind)."""
    a = np.ascontiguousarray(np.asarray(p0, float).reshape(-1, 3))
    b = np.ascontiguousarray(np.asarray(p1, float).reshape(-1, 3))
    if a.shape != b.shape:
        raise InputError(f"p0 and p1 must have the same shape (n, 3), got {a.shape} and {b.shape}")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise InputError("segment end points contain NaN or inf")
    isa_density_kgpm3(np.r_[a[:, 2], b[:, 2]])            # altitude range check
    w = np.ascontiguousarray(np.broadcast_to(np.asarray(wind_uvw, float), a.shape))
    prm = fixedwing_params(vehicle)
    out = np.empty((a.shape[0], len(ENERGY_KEYS)))
    _segments(a, b, w, prm, out)
    return {k: out[:, i] for i, k in enumerate(ENERGY_KEYS)}


def drag_energy_lb_j_per_m(vehicle: FixedWingProfile | str, max_wind_mps: float, z_min_m: float, z_max_m: float,
                           n: int = 64) -> float:
    """A lower bound of the drag work per metre of track [J/m] anywhere between altitudes
    z_min_m and z_max_m [m] in winds up to ``max_wind_mps`` [m/s]:
    ``W (D/L)_opt * min_z V(z) / (V(z) + |w|max)`` (D/L >= 2 sqrt(AB) at any speed, and the
    ground speed is at most V + |w|); times ``1 - 1e-9``.  The airspeed is increasing in the
    altitude, so the minimum over z is at ``z_min_m`` (checked on ``n`` altitudes)."""
    v = load_vehicle(vehicle)
    prm = fixedwing_params(v)
    z = np.linspace(z_min_m, z_max_m, n)
    va = np.array([airspeed_kernel(density_kernel(float(zz)), prm) for zz in z])
    ratio = float(np.min(va / (va + max(0.0, float(max_wind_mps)))))
    return v.weight_n * v.min_drag_to_lift * ratio * (1.0 - 1e-9)


__all__ = ["ENERGY_KEYS", "FixedWingParams", "airspeed_kernel", "drag_energy_lb_j_per_m", "drag_n_kernel",
           "fixedwing_params", "ground_speed_kernel", "piece_energy_kernel", "segment_energy_fw"]

