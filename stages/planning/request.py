"""One plan request (issue 25): :class:`Maps` (the datasets a planner reads) and
:class:`PlanRequest` (mission, weights, limits, budgets, seed and the resolved vehicle
profile), and :func:`plan` -- the strategic planner's entry point for the pipeline's plan
stage, ``skyroute fleet`` and the benchmarks.

The vehicle is resolved once, when the request is made (:meth:`PlanRequest.of`): the profile
travels with the request and is hashed by content (:meth:`PlanRequest.vehicle_hash`), never
reloaded by name further down.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any, ClassVar

import xarray as xr

from skyroute.stages.vehicle import FixedWingProfile, VehicleProfile, load_vehicle

__all__ = ["PLANNER_STAGES", "Maps", "PlanRequest", "plan"]

# the stage datasets a strategic planner reads (surface and clearance required), in one place:
# the pipeline's plan stage, fly and fleet load exactly these (traffic is optional and separate)
PLANNER_STAGES = ("surface", "environment", "clearance", "wind", "coverage", "satellites")


@dataclass(frozen=True)
class Maps:
    """The maps of one area: ``surface`` (terrain, surface [m]) and ``clearance``
    (``min_altitude_m`` [m], ``nofly``) are required; ``environment`` (risk and landing cost),
    ``wind`` (u, v, w [m/s]), ``coverage`` (``coverage_floor`` per DOP threshold [m]),
    ``satellites`` (for STEP III's navigation error), ``traffic`` (known intruders' occupancy) and
    ``clearance_by_level`` (the safety bubble's clearance per DOP threshold) are optional."""

    STAGES: ClassVar[tuple[str, ...]] = PLANNER_STAGES

    surface: xr.Dataset
    clearance: xr.Dataset
    environment: xr.Dataset | None = None
    wind: xr.Dataset | None = None
    coverage: xr.Dataset | None = None
    satellites: xr.Dataset | None = None
    traffic: Any = None
    clearance_by_level: Mapping[float, xr.Dataset] | None = None

    @classmethod
    def from_datasets(cls, datasets: Mapping[str, Any], **extra) -> Maps:
        """From a mapping of stage name -> dataset (e.g. a pipeline RunResult's ``datasets``);
        ``extra`` sets or overrides fields (``traffic``, ``clearance_by_level``, ``coverage``)."""
        kw = {f.name: datasets.get(f.name) for f in fields(cls) if f.name != "clearance_by_level"}
        kw.update(extra)
        missing = [k for k in ("surface", "clearance") if kw.get(k) is None]
        if missing:
            from skyroute.stages.base import InputError

            raise InputError(f"the maps lack {' and '.join(missing)}: run the "
                             f"{' and '.join(missing)} stage{'s' if len(missing) > 1 else ''} first")
        return cls(**kw)


@dataclass(frozen=True)
class PlanRequest:
    """What to plan: endpoints (map CRS [m], heights above ground [m]), ``start_time_utc``, the
    resolved ``vehicle`` profile, eq. 11 ``weights`` (w_l, w_r, w_d, w_e), the ``planner`` (a
    name of :mod:`~skyroute.stages.planning.registry`), its ``time_budget_s`` [s], ``seed`` and
    ``max_tries``, the altitude band [m AGL], ``dop_kind``, known ``intruders`` and their margins
    (``d_c_m`` [m], ``dt_c_s`` [s]), ``uere_m`` [m], the A* ``step_cells``, BIT*'s
    ``max_iterations``, ``battery_reserve_pct`` [%], the safety ``bubble`` (k, surface
    uncertainty [m]), STEP II's ``step2_max_iter`` and the level ``workers``."""

    start_xy: tuple[float, float]
    start_agl_m: float
    goal_xy: tuple[float, float]
    goal_agl_m: float
    start_time_utc: str
    vehicle: VehicleProfile | FixedWingProfile
    weights: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    planner: str = "astar"
    time_budget_s: float = 5.0
    seed: int = 0
    max_tries: int = 3
    min_agl_m: float = 0.0
    max_agl_m: float = 120.0
    dop_kind: str = "PDOP"
    intruders: tuple = field(default=())
    d_c_m: float = 0.0
    dt_c_s: float = 0.0
    uere_m: float = 3.0
    step_cells: int | None = None
    max_iterations: int | None = None
    battery_reserve_pct: float = 0.0
    bubble: tuple[float, float] | None = None
    step2_max_iter: int | None = None
    workers: int | None = None

    @classmethod
    def of(cls, *, vehicle, **kw) -> PlanRequest:
        """A request whose ``vehicle`` (a profile, catalog name or YAML path) is resolved now."""
        kw["intruders"] = tuple(kw.get("intruders") or ())
        return cls(vehicle=load_vehicle(vehicle), **kw)

    def with_(self, **changes) -> PlanRequest:
        """A copy with ``changes`` (e.g. another departure time or planner)."""
        return replace(self, **changes)

    def vehicle_hash(self) -> str:
        """A hash of the vehicle profile's content (16 hex digits)."""
        doc = json.dumps(self.vehicle.model_dump(mode="json"), sort_keys=True, default=str)
        return hashlib.blake2b(doc.encode(), digest_size=8).hexdigest()

    def kwargs(self) -> dict[str, Any]:
        """The keyword arguments of :func:`~skyroute.stages.planning.strategic.plan_strategic`."""
        kw = {k: v for k, v in asdict(self).items() if k != "vehicle"}
        kw["vehicle"] = self.vehicle
        kw["intruders"] = list(self.intruders) or None
        for k in ("step_cells", "step2_max_iter"):      # None: plan_strategic's default
            if kw[k] is None:
                kw.pop(k)
        return kw


def plan(maps: Maps, request: PlanRequest, *, heuristic_cache: dict | None = None,
         edge_cache: dict | None = None):
    """The strategic plan (STEP I-III on every coverage level, seed 000) of ``request`` on
    ``maps``: a :class:`~skyroute.stages.planning.strategic.StrategicPlan`.  ``heuristic_cache``
    / ``edge_cache``: dicts kept by a caller planning many missions on the same maps (fleet)."""
    from skyroute.stages.planning.strategic import plan_strategic

    return plan_strategic(maps.surface, maps.environment, maps.wind, maps.clearance, maps.coverage,
                          maps.satellites, maps.traffic, clearance_by_level=maps.clearance_by_level,
                          heuristic_cache=heuristic_cache, edge_cache=edge_cache, **request.kwargs())
