"""The ISA troposphere (seed 002 eq. 7): air density with altitude, the one home of it.

``rho(h) = p(h) / (R T(h))`` with ``T(h) = T0 - L h`` and ``p(h) = P0 (T(h) / T0)^(g / (L R))``
(P0 = 101 325 Pa, T0 = 288.15 K, L = 0.0065 K/m, R = 287.04 J/(kg K), g = 9.80665 m/s^2;
g / (L R) = 5.2561 as printed in the seed).  Valid in the troposphere, h < 11 000 m.
"""

from __future__ import annotations

import numba
import numpy as np

from skyroute.stages.base import InputError

P0_PA = 101_325.0        # sea-level pressure [Pa]
T0_K = 288.15            # sea-level temperature [K]
LAPSE_KPM = 0.0065       # temperature lapse rate [K/m]
R_AIR = 287.04           # specific gas constant of air [J/(kg K)] (seed 002)
G_ISA = 9.80665          # [m/s^2]
TROPOPAUSE_M = 11_000.0  # [m]


@numba.njit(cache=True, nogil=True)
def density_kernel(alt_m):
    """Compiled ISA density [kg/m^3] (float or array; no checks: kernels call it)."""
    t = T0_K - LAPSE_KPM * alt_m
    return P0_PA * (t / T0_K) ** (G_ISA / (LAPSE_KPM * R_AIR)) / (R_AIR * t)


def isa_density_kgpm3(alt_m):
    """ISA air density [kg/m^3] at altitude ``alt_m`` [m] above mean sea level (scalar or array).

    InputError outside [-500, 11 000] m (the troposphere of the model)."""
    a = np.asarray(alt_m, dtype=float)
    if not np.all(np.isfinite(a)) or np.any(a < -500.0) or np.any(a > TROPOPAUSE_M):
        raise InputError(f"altitude {alt_m} m is outside the ISA troposphere model [-500, 11000] m")
    if a.ndim == 0:
        return float(density_kernel(float(a)))
    return density_kernel(np.ascontiguousarray(a))


__all__ = ["G_ISA", "density_kernel", "LAPSE_KPM", "P0_PA", "R_AIR", "T0_K", "isa_density_kgpm3"]
