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

Modules: the compiled kernels and their parameter records are in
:mod:`skyroute.stages.planning.kernels`, the lower bounds and their memo in
:mod:`skyroute.stages.planning.heuristic`; this module builds and validates the problem.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import xarray as xr

from skyroute.stages.base import InputError, PlanningError
from skyroute.stages.energy import RHO0, PowerParams, power_params
from skyroute.stages.grid import Grid
from skyroute.stages.planning import heuristic as _heuristic
from skyroute.stages.planning.heuristic import (
    ENERGY_LB_DENSE_SAFETY,
    ENERGY_LB_SAFETY,
    WIND_INTERP_SAMPLES,
)
from skyroute.stages.planning.kernels import (
    ABOVE_CEILING,
    ANGLE,
    BELOW_FLOOR,
    EPS_Z,
    FORBIDDEN,
    GROUND_SPEED,
    NONFINITE,
    OK,
    OUTSIDE,
    WIND,
    MapParams,
    SegmentArgs,
    WindParams,
    grid_params,
    level_floor_kernel,
    segment_eval,
    segment_eval_if_valid,
    segments_kernel,
    states_kernel,
    vehicle_params,
    wind_at,
)
from skyroute.stages.vehicle import FixedWingProfile, VehicleProfile, load_vehicle

COST_NAMES = ("C_l", "C_r", "C_d", "C_e")
# a fixed-wing problem uses the kernels for validity only (want_cost=False never reads the
# rotor parameters); its energy is :mod:`skyroute.stages.fixedwing_energy`
_NO_ROTOR = PowerParams(1.0, RHO0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 1.0, 0.0, 1)


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


# private memos a problem carries that depend on its maps, wind and vehicle but not on its
# weights (kept by PlanningProblem.with_weights)
_WEIGHT_FREE_MEMOS = ("_ratio_tiles", "_block_memo", "_coarse_blocks", "_wind_key", "_winds_cache", "_lb_cache",
                      "_energy_rates")


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
    vehicle: VehicleProfile | FixedWingProfile
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
        wgt = tuple(float(x) for x in self.weights)
        object.__setattr__(self, "weights", wgt)
        object.__setattr__(self, "wind_uvw", w4)
        object.__setattr__(self, "wind_z_agl_m", wz)
        object.__setattr__(self, "wind_grid", wg)
        object.__setattr__(self, "start_xyz", tuple(float(v) for v in self.start_xyz))
        object.__setattr__(self, "goal_xyz", tuple(float(v) for v in self.goal_xyz))
        maps = MapParams(self.terrain_m, self.floor_m, self.ceiling_m, self.risk_cost, self.landing_cost,
                         grid_params(self.grid))
        power = power_params(veh) if isinstance(veh, VehicleProfile) else _NO_ROTOR
        args = SegmentArgs(maps, WindParams(w4, wz, grid_params(wg)), vehicle_params(veh, float(self.subsegment_m)),
                           power)
        object.__setattr__(self, "_seg_args", args)

    # ------------------------------------------------------------------ helpers
    @property
    def seg_args(self) -> SegmentArgs:
        """Arguments after ``want_cost`` of :func:`segment_eval`, (maps, wind, vehicle, power)
        (for compiled callers: ``segment_eval(..., want_cost, *problem.seg_args, out)``)."""
        return self._seg_args

    @property
    def state_args(self) -> tuple:
        """Arguments after (x, y, z) of :func:`~skyroute.stages.planning.kernels.state_code`,
        (maps, wind, vehicle)."""
        return self._seg_args[:3]

    @staticmethod
    def _pts(a, what: str = "xyz") -> np.ndarray:
        a = np.asarray(a, dtype=np.float64)
        if a.ndim == 1:
            a = a[None, :]
        if a.ndim != 2 or a.shape[1] != 3:
            raise InputError(f"{what} must have shape (n, 3) [m], got {a.shape}")
        return np.ascontiguousarray(a)

    def with_weights(self, weights) -> PlanningProblem:
        """A copy with other cost weights (w_l, w_r, w_d, w_e), keeping the memos that do not
        depend on them (:data:`_WEIGHT_FREE_MEMOS`: the wind-bound tiles, block minima and
        wind samples; STEP I's re-plans with a larger w_l recomputed them, 7 s per refused
        15 km city mission)."""
        p = dataclasses.replace(self, weights=check_weights(weights))
        for k in _WEIGHT_FREE_MEMOS:
            if k in self.__dict__:
                object.__setattr__(p, k, self.__dict__[k])
        return p

    # ------------------------------------------------------------------ validity
    def state_codes(self, xyz) -> np.ndarray:
        """Validity code per state (0 = valid; see ``_REASONS``)."""
        p = self._pts(xyz)
        out = np.empty(p.shape[0], dtype=np.int64)
        states_kernel(p, *self.state_args, out)
        return out

    def state_valid(self, xyz) -> np.ndarray:
        """bool (n,): state inside the AOI, between floor and ceiling, wind <= max."""
        return self.state_codes(xyz) == OK

    def motion_codes(self, p0, p1, want_cost: bool = False,
                     valid_only: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(codes (n,), costs (n, 6)) of each straight motion p0[i] -> p1[i] (n, 3) [m];
        ``valid_only``: the costs of the valid motions only (an invalid one stops at the first
        invalidity found and costs no energy evaluation; its row is incomplete)."""
        if want_cost and isinstance(self.vehicle, FixedWingProfile):
            raise InputError(f"vehicle {self.vehicle.name!r} is fixed-wing: the rotor costs of this problem do not "
                             "apply; use skyroute.stages.fixedwing_energy / the fixed-wing planners")
        a, b = self._pts(p0, "p0"), self._pts(p1, "p1")
        if a.shape != b.shape:
            raise InputError(f"p0 and p1 must have the same shape, got {a.shape} and {b.shape}")
        out = np.empty((a.shape[0], 6))
        codes = np.empty(a.shape[0], dtype=np.int64)
        segments_kernel(a, b, want_cost, valid_only, *self._seg_args, out, codes)
        return codes, out

    def motion_f_if_valid(self, p0, p1) -> tuple[np.ndarray, np.ndarray]:
        """(f per motion p0[i] -> p1[i] (n, 3) [m] (inf where invalid), valid (n,) bool): the
        costs of :meth:`motion_codes` for the valid motions, none computed for the others (the
        searches' and refinement's use)."""
        codes, out = self.motion_codes(p0, p1, want_cost=True, valid_only=True)
        ok = codes == OK
        c = out[:, :4]
        f = self.f_of(np.where(ok[:, None], np.where(np.isfinite(c), c, np.inf), 0.0))
        return np.where(ok, f, np.inf), ok

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
            if self.clearance_m is not None and z < self.clearance_m[r, c] - EPS_Z:
                parts.append(f"inside obstacle clearance (sphere r_p = {self.vehicle.r_p_m:g} m needs "
                             f"z >= {self.clearance_m[r, c]:.1f} m)")
            if z < ground + self.min_agl_m - EPS_Z:
                parts.append(f"below the minimum altitude {self.min_agl_m:g} m AGL")
            if self.coverage_m is not None and z < self.coverage_m[r, c] - EPS_Z:
                parts.append(f"below GNSS coverage floor for {dop} ({self.coverage_m[r, c]:.1f} m)")
            if not parts:
                parts.append(f"below the floor {self.floor_m[r, c]:.1f} m")
            return f"{where}: " + "; ".join(parts)
        if code == ABOVE_CEILING:
            return f"{where}: above the maximum altitude {self.max_agl_m:g} m AGL ({self.ceiling_m[r, c]:.1f} m)"
        if code == WIND:
            maps, wind, _, _ = self._seg_args
            u, v, w = wind_at(x, y, z, maps.terrain_m, maps.grid, wind)
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
    # (implemented in skyroute.stages.planning.heuristic)
    @property
    def energy_ratio_lb(self) -> float:
        """Lower bound of E_w / E_0 over flyable directions and the map's winds, times 0.9."""
        return _heuristic.energy_ratio_lb(self)

    def wind_samples(self, max_n: int = 600) -> np.ndarray:
        """Distinct wind vectors of the map (levels and mid-levels), at most ``max_n`` [m/s]."""
        return _heuristic.wind_samples(self.wind_uvw, max_n)

    def energy_ratio_lb_dirs(self, dirs) -> float:
        """min of E_w / E_0 over unit directions ``dirs`` (m, 3) and the map's winds, times 0.9
        (1 * 0.9 when no pair is flyable).  Memoised on the bytes of (winds, vehicle, dirs): the
        coverage levels of one mission share the wind map and the vehicle, so the bound is
        computed once for all of them."""
        return _heuristic.energy_ratio_lb_dirs(self, dirs)

    def wind_samples_dense(self, per_gap: int = WIND_INTERP_SAMPLES) -> np.ndarray:
        """Every wind vector of the map (all columns and levels) and ``per_gap - 1`` evenly
        spaced linear interpolations between adjacent levels, deduplicated [m/s] (m, 3)."""
        return _heuristic.wind_samples_dense(self.wind_uvw, per_gap)

    def energy_ratio_lb_dense_dirs(self, dirs) -> float:
        """min of E_w / E_0 over unit directions ``dirs`` (m, 3) and every wind of the map
        (:meth:`wind_samples_dense`), times :data:`ENERGY_LB_DENSE_SAFETY` (0.99); see
        :func:`skyroute.stages.planning.heuristic.energy_ratio_lb_dense_dirs`."""
        return _heuristic.energy_ratio_lb_dense_dirs(self, dirs)

    def energy_ratio_lb_dense_each(self, dirs) -> np.ndarray:
        """(m,): :meth:`energy_ratio_lb_dense_dirs` of each unit direction of ``dirs`` (m, 3),
        in one parallel pass (:func:`skyroute.stages.planning.heuristic.energy_ratio_lb_dense_each`)."""
        return _heuristic.energy_ratio_lb_dense_each(self, dirs)

    @property
    def cost_rate_lb(self) -> float:
        """Admissible lower bound of f per metre of path [-]: w_l + w_r min(risk) +
        w_d min(landing) + w_e * energy_ratio_lb (every term of eq. 11 is >= rate * length)."""
        return _heuristic.cost_rate_lb(self)


# --------------------------------------------------------------------------- construction


def check_weights(weights) -> tuple[float, float, float, float]:
    """The cost weights (w_l, w_r, w_d, w_e) [-] as 4 floats; InputError unless finite, >= 0, not all 0."""
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


def wind_uvw(wind: xr.Dataset) -> np.ndarray:
    """The wind vectors of a wind map, stacked.

    Parameters
    ----------
    wind : xarray.Dataset
        A :func:`~skyroute.stages.wind.wind_on_grid` map: ``u``, ``v`` (and ``w``, else 0) [m/s]
        on ``(z, y, x)`` in any order.

    Returns
    -------
    numpy.ndarray
        (nz, ny, nx, 3) [m/s], the maps' dtype.

    Raises
    ------
    InputError
        When ``u`` or ``v`` is missing.
    """
    for k in ("u", "v"):
        if k not in wind:
            raise InputError(f"wind dataset needs variables u, v (and w) on (z, y, x); missing {k}")
    u = wind["u"].transpose("z", "y", "x").values
    v = wind["v"].transpose("z", "y", "x").values
    w = wind["w"].transpose("z", "y", "x").values if "w" in wind else np.zeros_like(u)
    return np.stack([u, v, w], axis=-1)


def _wind_arrays(wind, grid: Grid):
    """(wind_uvw, wind_z_agl_m, wind_grid) from a wind map, a UniformWind or a (3,) vector."""
    if wind is None:
        return np.zeros(3), np.zeros(1), None
    if hasattr(wind, "components") and callable(wind.components):
        return np.asarray(wind.components(), dtype=float), np.zeros(1), None
    if isinstance(wind, xr.Dataset):
        uvw = wind_uvw(wind)
        z = np.asarray(wind["z"].values, dtype=float)
        x = np.asarray(wind["x"].values, dtype=float)
        y = np.asarray(wind["y"].values, dtype=float)
        if x.size >= 2 and y.size >= 2:
            wg = Grid.from_dataarray(wind)
        else:
            res = float(wind.attrs.get("horizontal_step_m", grid.resolution_m))
            wg = Grid(grid.crs_wkt, float(x[0] - res / 2), float(y[0] + res / 2), x.size, y.size, res)
        return uvw, z, wg
    a = np.asarray(wind, dtype=float)
    if a.shape == (3,):
        return a, np.zeros(1), None
    raise InputError("wind must be a wind_on_grid Dataset, a UniformWind or (u, v, w) [m/s]")


def build_problem(surface_ds: xr.Dataset, clearance_floor, coverage_floor_j, risk_cost, landing_cost, wind,
                  vehicle, weights, start_xyz, goal_xyz, min_agl_m: float, max_agl_m: float,
                  dop_threshold: float | None = None, *, dop_kind: str = "PDOP", nofly=None,
                  label: str | None = None, subsegment_m: float = 10.0,
                  check_endpoints: bool = True, shared: dict | None = None) -> PlanningProblem:
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

    ``shared``: an optional dict, the same for the coverage levels of one plan: the arrays
    derived from inputs the levels share (the same ``surface_ds``, ``risk_cost``,
    ``landing_cost``, ``wind``, ``nofly`` and ``clearance_floor`` objects) are computed once and
    the levels' problems share them (no array of a problem is ever written in place); the
    problems are the same as without it (on the 6 km Helsinki AOI it saves ~2 s per level),
    and they share one memo of the block reductions of those arrays
    (:func:`~skyroute.stages.planning.multires.coarse_problem`).

    Raises InputError for bad weights/shapes/limits and PlanningError (with the reason) when
    the start or the goal is not a valid state (unless ``check_endpoints=False``: STEP I then
    reports that level as "no solution" with the reason, seed 001 Table 4).
    """
    if not isinstance(surface_ds, xr.Dataset) or "terrain" not in surface_ds:
        raise InputError("surface_ds must be the build_surface Dataset (with a 'terrain' variable)")
    grid = Grid.from_dataarray(surface_ds["terrain"])
    shape = grid.shape
    w = check_weights(weights)
    if not (np.isfinite(min_agl_m) and np.isfinite(max_agl_m) and 0 <= min_agl_m < max_agl_m):
        raise InputError(f"altitude limits need 0 <= min_agl_m < max_agl_m, got {min_agl_m}, {max_agl_m} m")
    veh = load_vehicle(vehicle)
    memo = {} if shared is None else shared

    def once(key: tuple, make):
        # keyed on names and ids of the input objects; the entry keeps those objects alive (an
        # id is never reused while its entry exists)
        ids = tuple(k if isinstance(k, (str, float)) else id(k) for k in key)
        hit = memo.get(ids)
        if hit is None:
            hit = memo[ids] = (key, make())
        return hit[1]

    def terrain_of():
        t = _raster(surface_ds["terrain"], shape, "terrain")
        if not np.isfinite(t).all():
            raise InputError("terrain has NaN/inf cells: fill no-data first")
        return t

    def cost_map(a, name):
        v = _raster(a, shape, name, 0.0)
        if not np.all(v >= 0):                      # NaN or negative (+inf risk: no-fly)
            raise InputError(f"{name} must be >= 0 (dimensionless; NaN not allowed)")
        return v

    def nofly_of():
        nf = np.zeros(shape, bool) if nofly is None else np.asarray(
            nofly.values if isinstance(nofly, xr.DataArray) else nofly).astype(bool)
        if nf.shape != shape:
            raise InputError(f"nofly has shape {nf.shape}; expected {shape}")
        return nf | np.isinf(risk)

    sid = ("surface", surface_ds)
    terrain = once(("terrain",) + sid, terrain_of)
    clear = once(("clearance", clearance_floor),
                 lambda: _raster(clearance_floor, shape, "clearance_floor"))
    cover = None if coverage_floor_j is None else _raster(coverage_floor_j, shape, "coverage_floor_j")
    risk = once(("risk", risk_cost), lambda: cost_map(risk_cost, "risk_cost"))
    land = once(("land", landing_cost), lambda: cost_map(landing_cost, "landing_cost"))
    nf = once(("nofly", nofly, risk_cost), nofly_of)
    floor = once(("floor", clearance_floor, float(min_agl_m)) + sid,
                 lambda: np.maximum(clear, terrain + float(min_agl_m)))
    # np.where(nf, inf, np.maximum(floor, np.where(np.isfinite(cover), cover, inf))) in one pass
    level_floor = np.empty_like(floor)
    level_floor_kernel(np.ascontiguousarray(floor), np.zeros((0, 0)) if cover is None else np.ascontiguousarray(cover),
                       np.ascontiguousarray(nf), level_floor)
    floor = level_floor
    # maximum AGL: relative to the LOWEST ground in the cell (``terrain_min`` where the surface
    # stage has it), so the ceiling holds at every point of the cell
    ceiling = once(("ceiling", float(max_agl_m)) + sid, lambda: (
        _raster(surface_ds["terrain_min"], shape, "terrain_min") if "terrain_min" in surface_ds
        else terrain) + float(max_agl_m))
    wuvw, wz, wg = once(("wind", wind) + sid, lambda: _wind_arrays(wind, grid))
    risk_fly = once(("risk_fly", risk_cost), lambda: np.where(np.isinf(risk), 0.0, risk))
    for name, p in (("start_xyz", start_xyz), ("goal_xyz", goal_xyz)):
        if np.asarray(p, dtype=float).shape != (3,):
            raise InputError(f"{name} must be (x, y, z) [m], got {p!r}")
    if label is None:
        label = f"D={dop_threshold:g}" if dop_threshold is not None else "no GNSS constraint"
    prob = PlanningProblem(grid=grid, terrain_m=terrain, floor_m=floor, ceiling_m=ceiling,
                           risk_cost=risk_fly, landing_cost=land, wind_uvw=wuvw,
                           vehicle=veh, weights=w, start_xyz=tuple(start_xyz), goal_xyz=tuple(goal_xyz),
                           dop_threshold=dop_threshold, label=label, wind_z_agl_m=wz, wind_grid=wg,
                           clearance_m=clear, coverage_m=cover, nofly=nf, min_agl_m=float(min_agl_m),
                           max_agl_m=float(max_agl_m), dop_kind=dop_kind, subsegment_m=subsegment_m)
    if shared is not None:   # the levels' coarse abstractions share block reductions (multires)
        object.__setattr__(prob, "_block_memo", shared.setdefault("block_memo", _heuristic.BoundMemo(64)))
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


__all__ = ["COST_NAMES", "ENERGY_LB_DENSE_SAFETY", "ENERGY_LB_SAFETY", "PlanningProblem", "build_problem",
           "check_weights", "segment_eval", "segment_eval_if_valid", "wind_uvw", "xyz_from_agl"]
