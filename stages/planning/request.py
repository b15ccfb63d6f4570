"""One plan request (issue 25): :class:`Maps` (the datasets a planner reads) and
:class:`PlanRequest` (mission, weights, limits, budgets, seed and the resolved vehicle
profile): the two arguments of
:func:`~skyroute.stages.planning.strategic.plan_strategic`, the strategic planner's entry point
for the pipeline's plan stage, ``skyroute fleet`` and the benchmarks.

The vehicle is resolved once, when the request is made (:meth:`PlanRequest.of`): the profile
travels with the request and is hashed by content (:meth:`PlanRequest.vehicle_hash`), never
reloaded by name further down.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any, ClassVar

import xarray as xr

from skyroute.stages.vehicle import FixedWingProfile, VehicleProfile, load_vehicle

__all__ = ["PLANNER_STAGES", "Maps", "PlanRequest"]

# the stage datasets a strategic planner reads (surface and clearance required), in one place:
# the pipeline's plan stage, fly and fleet load exactly these (traffic is optional and separate)
PLANNER_STAGES = ("surface", "environment", "clearance", "wind", "coverage", "satellites")


@dataclass(frozen=True)
class Maps:
    """The maps of one area: the datasets a strategic planner reads.

    ``surface`` and ``clearance`` are required, the others optional.  :data:`PLANNER_STAGES`
    (``Maps.STAGES``) names the stages the pipeline's plan stage, fly and fleet load.

    Parameters
    ----------
    surface : xarray.Dataset
        Terrain, surface [m] (:func:`~skyroute.stages.surface.build_surface`).
    clearance : xarray.Dataset
        ``min_altitude_m`` [m], ``nofly``.
    environment : xarray.Dataset, optional
        Risk and landing cost.
    wind : xarray.Dataset, optional
        u, v, w [m/s].
    coverage : xarray.Dataset, optional
        ``coverage_floor`` per DOP threshold [m] (:func:`~skyroute.stages.coverage.coverage_maps`).
    satellites : xarray.Dataset, optional
        Satellite geometry, for STEP III's navigation error.
    traffic : xarray.Dataset or TrafficOccupancy, optional
        Known intruders' occupancy.
    clearance_by_level : mapping of float to xarray.Dataset, optional
        The safety bubble's clearance per DOP threshold.
    wind_bounds : xarray.Dataset, optional
        The ``wind_bounds`` stage's energy-ratio bounds per wind tile
        (:func:`~skyroute.stages.planning.wind_bounds.wind_ratio_tiles`).
    """

    STAGES: ClassVar[tuple[str, ...]] = PLANNER_STAGES

    surface: xr.Dataset
    clearance: xr.Dataset
    environment: xr.Dataset | None = None
    wind: xr.Dataset | None = None
    coverage: xr.Dataset | None = None
    satellites: xr.Dataset | None = None
    traffic: Any = None
    clearance_by_level: Mapping[float, xr.Dataset] | None = None
    wind_bounds: xr.Dataset | None = None

    @classmethod
    def from_datasets(cls, datasets: Mapping[str, Any], **extra) -> Maps:
        """Maps from a mapping of stage name -> dataset (e.g. a pipeline RunResult's ``datasets``).

        Parameters
        ----------
        datasets : mapping of str to xarray.Dataset
            Stage datasets by stage name; missing optional stages are None.
        **extra
            Set or override fields (``traffic``, ``clearance_by_level``, ``coverage``).

        Returns
        -------
        Maps

        Raises
        ------
        InputError
            When ``surface`` or ``clearance`` is missing (run those stages first).
        """
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
    """What to plan: mission, weights, limits, budgets, seed and the resolved vehicle profile.

    Make one with :meth:`of`, which resolves the vehicle once; :meth:`kwargs` gives the keyword
    arguments of :func:`~skyroute.stages.planning.strategic.plan_levels`, where every field is
    described further.

    Parameters
    ----------
    start_xy, goal_xy : tuple of float
        Endpoints, map (x, y) [m] in the maps' CRS.
    start_agl_m, goal_agl_m : float
        Their heights above ground [m].
    start_time_utc : str
        Departure time [UTC].
    vehicle : VehicleProfile or FixedWingProfile
        The resolved vehicle profile (hashed by content: :meth:`vehicle_hash`).
    weights : tuple of 4 float, default (1.0, 1.0, 1.0, 1.0)
        Eq. 11 weights (w_l, w_r, w_d, w_e) [-].
    planner : str, default "astar"
        A name of :mod:`~skyroute.stages.planning.registry`.
    time_budget_s : float, default 5.0
        The planner's budget [s].
    seed : int, default 0
        Random seed.
    max_tries : int, default 3
        STEP I tries per level (N_t).
    min_agl_m, max_agl_m : float, default 0.0, 120.0
        The altitude band [m AGL].
    dop_kind : str, default "PDOP"
        DOP kind of the coverage levels.
    intruders : tuple of Intruder, default ()
        Known intruders.
    d_c_m : float, default 0.0
        Their spatial margin [m].
    dt_c_s : float, default 0.0
        Their time margin [s].
    uere_m : float, default 3.0
        GNSS user equivalent range error [m].
    step_cells : int, optional
        The A* lattice step [cells] (None: plan_levels' default).
    max_iterations : int, optional
        BIT*'s iteration stop rule.
    battery_reserve_pct : float, default 0.0
        Battery reserve [%].
    bubble : tuple of float, optional
        The safety bubble (k, surface uncertainty [m]).
    step2_max_iter : int, optional
        STEP II's iterations (None: plan_levels' default).
    workers : int, optional
        Threads for the levels.
    """

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
        """A request whose ``vehicle`` (a profile, catalog name or YAML path) is resolved now.

        Parameters
        ----------
        vehicle : str, pathlib.Path, VehicleProfile or FixedWingProfile
            Resolved with :func:`~skyroute.stages.vehicle.load_vehicle`.
        **kw
            The other fields of :class:`PlanRequest` (``intruders`` becomes a tuple).

        Returns
        -------
        PlanRequest

        Raises
        ------
        UnknownNameError
            For an unknown vehicle name.
        DataError
            For an unreadable vehicle file.
        ScenarioError
            For an invalid vehicle file (every problem listed).
        """
        kw["intruders"] = tuple(kw.get("intruders") or ())
        return cls(vehicle=load_vehicle(vehicle), **kw)

    def with_(self, **changes) -> PlanRequest:
        """A copy with ``changes`` (e.g. another departure time or planner).

        Parameters
        ----------
        **changes
            Fields to replace.

        Returns
        -------
        PlanRequest
        """
        return replace(self, **changes)

    def vehicle_hash(self) -> str:
        """A hash of the vehicle profile's content (16 hex digits).

        Returns
        -------
        str
            BLAKE2b (8 bytes) of the profile's sorted JSON, in hex.
        """
        from skyroute.stages.vehicle import profile_hash

        return profile_hash(self.vehicle)

    def kwargs(self) -> dict[str, Any]:
        """The keyword arguments of :func:`~skyroute.stages.planning.strategic.plan_levels`.

        Returns
        -------
        dict of str to object
            Every field (``intruders`` as a list or None; ``step_cells`` and ``step2_max_iter``
            left out when None, so plan_levels' defaults apply).
        """
        kw = {k: v for k, v in asdict(self).items() if k != "vehicle"}
        kw["vehicle"] = self.vehicle
        kw["intruders"] = list(self.intruders) or None
        for k in ("step_cells", "step2_max_iter"):      # None: plan_levels' default
            if kw[k] is None:
                kw.pop(k)
        return kw
