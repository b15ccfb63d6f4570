"""Safety bubble obstacle avoidance in planning (seed 003, SBOA): a clearance radius per coverage level.

Seed 003 keeps the vehicle at a distance ``r_phi = k sigma + surface uncertainty`` [m] from the
obstacles, ``sigma = sqrt(sigma_x^2 + sigma_y^2 + sigma_z^2)`` of the navigation filter
(:func:`~skyroute.stages.navsim.bubble_radius_m`).  The strategic planner flies level ``D_j``
only where DOP < ``D_j`` (the coverage floor), so one conservative sigma per level,
:func:`level_sigma_m`, gives one radius per level, :func:`level_radius_m`:
``r_j = max(r_p, k sigma(D_j) + surface_uncertainty)``.

How ``sigma(D)`` is bounded (an argument, checked by tests on random geometries)
------------------------------------------------------------------------------
The filter is that of :func:`~skyroute.stages.navigation.navigation_error` (same IMU, UERE,
GNSS period, warm-up and initial prior as STEP III).  For a static geometry ``G`` (rows
``[-u, 1]``) with equal UERE:

1. a filter whose clock is re-estimated from scratch at each epoch (infinite clock noise) has a
   covariance at least as large as the real one (less prior information); it sees the position
   through the Schur complement ``M = [(G^T G)^{-1}]_pos^{-1} / UERE^2``, whose inverse has
   trace ``UERE^2 PDOP^2``;
2. the position/velocity/bias dynamics are the same on the three axes and isotropic, so in the
   eigenbasis of ``M`` the filter splits into three 1-D filters; the position variance of each is
   an increasing, concave (checked numerically, not proved) function ``g`` of its measurement
   variance ``s_i``
   (``sum s_i = UERE^2 PDOP^2``), so by Jensen ``sum g(s_i) <= 3 g(UERE^2 PDOP^2 / 3)``: the
   worst geometry for a given PDOP is the isotropic one;
3. the isotropic geometry used here, six lines of sight along +-E, +-N, +-U (``G^T G =
   diag(2, 2, 2, 6)``, clock decoupled, PDOP = sqrt(1.5)) with the pseudorange sigma scaled
   to ``UERE D / sqrt(1.5)``, has PDOP ``D`` at UERE;
4. after the first seconds the covariance decreases with time towards the steady state
   (checked numerically: the largest value after the 60 s warm-up is at its first cycle),
   so its largest value in flight is just after the warm-up.  The bound is
   the largest sigma over the first update cycle after the warm-up, with the longest gap
   between updates STEP III can produce (``gnss_period_s + sample_dt_s``), sampled finely.

Points 1-2 hold for a static geometry; with a geometry changing in flight the bound is not
proved, which is why STEP III re-checks each sample with its own predicted sigma_p(t)
(:func:`~skyroute.stages.planning.validate.validate_bubble`).  Only PDOP and GDOP
(GDOP >= PDOP) coverage levels bound the PDOP.
"""

from __future__ import annotations

import math

import numpy as np

from skyroute.stages.base import InputError
from skyroute.stages.navigation import DEFAULT_UERE_M, navigation_error
from skyroute.stages.vehicle import ImuSpec, VehicleProfile

ISOTROPIC_PDOP = math.sqrt(1.5)
BOUNDED_DOPS = ("PDOP", "GDOP")


def bubble_radius_m(sigma_m, k: float, surface_uncertainty_m: float = 0.0) -> np.ndarray:
    """Safety bubble radius r_phi = k sigma + the surface model's uncertainty [m] (seed 003
    Fig. 11: sigma = sqrt(sigma_x^2 + sigma_y^2 + sigma_z^2) of the filter)."""
    if not (k > 0 and surface_uncertainty_m >= 0):
        raise InputError(f"k = {k} must be > 0 and surface_uncertainty_m = {surface_uncertainty_m} >= 0 [m]")
    return k * np.asarray(sigma_m, float) + float(surface_uncertainty_m)


def isotropic_los() -> np.ndarray:
    """Six unit lines of sight along +-E, +-N, +-U (6, 3): PDOP sqrt(1.5), clock decoupled."""
    e = np.eye(3)
    return np.concatenate([e, -e])


def level_sigma_m(dop: float, imu: ImuSpec | VehicleProfile | str | dict = "dji-m300-rtk",
                  uere_m: float = DEFAULT_UERE_M, gnss_period_s: float = 1.0, sample_dt_s: float = 0.5,
                  warmup_s: float = 60.0, fine_dt_s: float = 0.05) -> float:
    """Conservative 3-D position sigma [m] of the STEP III filter in flight anywhere PDOP <= ``dop``
    (module docstring): the isotropic geometry scaled to PDOP ``dop``, the same prior and warm-up
    ``warmup_s`` [s], updates every ``gnss_period_s + sample_dt_s`` [s], maximum over the first
    cycle after the warm-up (sampled every ``fine_dt_s`` [s])."""
    if not (np.isfinite(dop) and dop > 0):
        raise InputError(f"DOP threshold {dop} must be finite and > 0")
    if not (uere_m > 0 and gnss_period_s > 0 and sample_dt_s >= 0 and warmup_s >= 0 and fine_dt_s > 0):
        raise InputError("level_sigma_m needs uere_m > 0, gnss_period_s > 0, sample_dt_s >= 0, warmup_s >= 0 "
                         "and fine_dt_s > 0")
    gap = gnss_period_s + sample_dt_s
    n_w = int(math.floor(warmup_s / gap))
    coarse = gap * np.arange(n_w + 1)                       # updates up to (and just after) the warm-up
    fine = coarse[-1] + np.arange(1, int(math.ceil(gap / fine_dt_s)) + 1) * (gap / math.ceil(gap / fine_dt_s))
    t = np.concatenate([coarse, fine])
    los = np.broadcast_to(isotropic_los(), (t.size, 6, 3))
    vis = np.ones((t.size, 6), bool)
    nav = navigation_error(t, los, vis, imu=imu, gnss_sigma_m=uere_m * dop / ISOTROPIC_PDOP, dt_s=gap - 1e-6)
    s = np.asarray(nav["sigma_p_m"].values)
    return float(s[n_w:].max())


def level_radius_m(dop: float, r_p_m: float, k: float, surface_uncertainty_m: float, **kw) -> float:
    """``r_j = max(r_p, k level_sigma_m(dop) + surface_uncertainty)`` [m] (``kw``: :func:`level_sigma_m`)."""
    r_phi = float(bubble_radius_m(level_sigma_m(dop, **kw), k, surface_uncertainty_m))
    return max(float(r_p_m), r_phi)


def check_dop_kind(dop_kind: str) -> None:
    """SBOA levels need a DOP that bounds the PDOP (PDOP or GDOP)."""
    if dop_kind not in BOUNDED_DOPS:
        raise InputError(f"constraints.clearance: sboa needs gnss.dop_kind PDOP or GDOP (it bounds the 3-D "
                         f"error); got {dop_kind}")


__all__ = ["ISOTROPIC_PDOP", "check_dop_kind", "isotropic_los", "level_radius_m", "level_sigma_m"]
