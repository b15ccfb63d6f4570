"""The parameters of a flight replay (:class:`FlyParams`), apart from the replay itself: a command
checks them before any stage without importing the planners (:mod:`skyroute.stages.tactical.replay`
re-exports them)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from skyroute.stages.base import InputError

if TYPE_CHECKING:      # annotations only
    from skyroute.stages.planning.request import PlanRequest

__all__ = ["TACTICAL_METHODS", "FlyParams"]

TACTICAL_METHODS = ("levels", "octant")   # rotorcraft; fixed-wing: local (pipeline/fly_fw.py)


# the planning settings of a replay without a plan request (synthetic replays, tests)
_NO_REQUEST = {"weights": (1.0, 1.0, 1.0, 1.0), "min_agl_m": 0.0, "max_agl_m": 120.0, "dop_kind": "PDOP",
               "uere_m": 3.0, "battery_reserve_pct": 0.0, "step_cells": 8, "d_c_m": 5.0, "bubble": None}


@dataclass(frozen=True)
class FlyParams:
    """Replay parameters: the tactical ones (scenario ``tactical:`` section) and ``request``,
    the :class:`~skyroute.stages.planning.request.PlanRequest` of the flight, the one home of
    the planning settings the replay's replans use.

    Tactical: ``t_rep_s`` [s]: replanning timeout (a replan takes effect that long after its
    event); ``tick_s`` [s]: output and check sampling; ``seed``: the replay's random seed
    (intruder noise, replans); ``dt_c_s`` [s]: time margin of the replanning occupancy maps;
    ``time_scaling_factors``: level-1 speed factors in (0, 1);
    ``level2_iterations`` / ``level3_iterations``: RRT iteration counts; ``intruder_noise_m``
    [m]: 1-sigma noise of reported intruder positions; ``report_latency_s`` [s]: delay before an
    intruder event is known; ``occupancy_slice_s`` [s]: time slice of the replanning
    occupancy maps; ``max_landing_sites``: sites tried for a contingency landing;
    ``method``: ``levels`` (levels 1-3) or ``octant`` (seed 004: zone partitioning and the
    octant manoeuvre for intruder conflicts, :mod:`.octant_replan`); ``periphery_m`` [m]: the
    octant method's sensing periphery P_r; ``zone_period_s`` [s]: its zone prediction period
    T_p; ``zone_potential``: the octant method re-routes along the potential field with the
    dense zones as obstacles when the plan meets one (:func:`.octant_replan.zone_potential`).
    ``escape``: the escape of last resort (:mod:`.escape`: brake, move off the conflict, hold,
    replan; default on); ``escape_latency_s`` [s]: how long after a conflict is known a reflex
    escape takes effect (the decision's compute time, measured p95 < 0.5 s).

    Planning, read from ``request`` (properties of the same names; without a request: eq. 11
    weights (1, 1, 1, 1), 0-120 m AGL, PDOP, UERE 3 m, no battery reserve, an 8-cell A* step,
    a 5 m traffic margin, no bubble): ``weights`` (the tactical cost keeps w_l and w_e),
    ``min_agl_m`` / ``max_agl_m`` [m], ``dop_kind``, ``uere_m`` [m], ``battery_reserve_pct``
    [%], ``step_cells``, ``d_c_m`` [m] (spatial traffic margin: the separation is r_p + r_i +
    d_c) and ``bubble``.

    Safety bubble (``constraints.clearance: sboa``, seed 003; default off): the request's
    ``bubble`` (k, surface uncertainty [m]) makes every STEP III of the replay re-check its
    samples at max(r_p, k sigma_p(t) + surface uncertainty) from the surface (as the strategic
    plan does), and ``clearance_radius_m`` r_j [m] (the radius the world's clearance maps were
    built for) is also the height of the landing approach points above a site."""

    t_rep_s: float = 5.0
    tick_s: float = 0.1
    seed: int = 0
    dt_c_s: float = 0.0
    time_scaling_factors: tuple[float, ...] = (0.8, 0.65, 0.5, 0.35, 0.25)
    level2_iterations: int = 3000
    level3_iterations: int = 5000
    intruder_noise_m: float = 0.0
    report_latency_s: float = 0.0
    occupancy_slice_s: float = 1.0
    max_landing_sites: int = 5
    clearance_radius_m: float | None = None
    method: str = "levels"
    periphery_m: float = 60.0
    zone_period_s: float = 10.0
    zone_potential: bool = True
    escape: bool = True
    escape_latency_s: float = 0.5
    request: PlanRequest | None = None

    def __post_init__(self):
        if self.method not in TACTICAL_METHODS:
            raise InputError(f"tactical method {self.method!r}: use one of {', '.join(TACTICAL_METHODS)}")
        if not (math.isfinite(self.escape_latency_s) and self.escape_latency_s >= 0):
            raise InputError(f"escape_latency_s = {self.escape_latency_s} s must be finite and >= 0")
        if not (self.periphery_m > 0 and self.zone_period_s > 0):
            raise InputError("periphery_m [m] and zone_period_s [s] must be > 0")
        if not (self.t_rep_s > 0 and self.tick_s > 0 and self.occupancy_slice_s > 0):
            raise InputError("t_rep_s, tick_s and occupancy_slice_s must be > 0 [s]")
        if not all(0 < s < 1 for s in self.time_scaling_factors):
            raise InputError(f"time_scaling_factors {self.time_scaling_factors} must be in (0, 1)")
        b = self.bubble
        if b is not None and not (b[0] > 0 and b[1] >= 0):
            raise InputError(f"safety bubble k {b[0]} must be > 0 and the surface uncertainty {b[1]} m >= 0")

    def _planning(self, name: str):
        return _NO_REQUEST[name] if self.request is None else getattr(self.request, name)

    weights = property(lambda self: tuple(self._planning("weights")), doc="Eq. 11 weights (w_l, w_r, w_d, w_e) [-] of the request.")
    min_agl_m = property(lambda self: self._planning("min_agl_m"), doc="Lowest height above ground [m] of the request.")
    max_agl_m = property(lambda self: self._planning("max_agl_m"), doc="Highest height above ground [m] of the request.")
    dop_kind = property(lambda self: self._planning("dop_kind"), doc="DOP kind of the request.")
    uere_m = property(lambda self: self._planning("uere_m"), doc="GNSS user equivalent range error [m] of the request.")
    battery_reserve_pct = property(lambda self: self._planning("battery_reserve_pct"), doc="Battery reserve [%] of the request.")
    step_cells = property(lambda self: _NO_REQUEST["step_cells"] if self._planning("step_cells") is None
                          else self._planning("step_cells"), doc="A* lattice step [cells] of the request.")
    d_c_m = property(lambda self: self._planning("d_c_m"), doc="Spatial traffic margin d_c [m] of the request.")

    @property
    def bubble(self) -> tuple[float, float] | None:
        """``(k, surface_uncertainty_m)`` of the safety bubble (the request's), or None (fixed r_p)."""
        b = self._planning("bubble")
        return None if b is None else (float(b[0]), float(b[1]))


