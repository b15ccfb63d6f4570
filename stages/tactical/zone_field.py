"""Dense traffic zones as obstacles of the numerical potential field (seed 004 III-A -> III-B).

Seed 004 treats the dense zones of the current *dense zone definition* as static obstacles
until the next prediction: "whenever there is a change, the workspace potential generation
sub-module is invoked" (update of the obstacle bitmap, then the W-potential), and the vehicle
follows the gradient motion of that potential from where it is.  Here:

* :func:`zone_cells` rasterises the dense zones (:class:`~skyroute.stages.tactical.zones.ZoneBox`,
  full height) widened by the vehicle radius r_p [m] into grid cells (every cell whose closed
  square meets the widened rectangle: conservative, a superset of the r_p buffer of the box);
* :func:`zone_problem` makes those cells no-fly columns of a planning problem (floor +inf), so
  the bitmap of :func:`~skyroute.stages.planning.potential.occupancy_bitmap` has them as
  obstacles and every motion check of the waypoint reduction refuses them;
* :class:`ZoneField` holds the W-potential of a workspace box with the current zones as
  obstacles.  It is computed in full once (:meth:`ZoneField.build`, with the zones of that
  time) and afterwards only :meth:`ZoneField.set_zones` changes it, by
  :func:`~skyroute.stages.planning.potential.update_potential` (the EDT and skeleton in a
  window around the changed voxels, the wave only where the potential came through them),
  and only when the zones differ; ``full_computations`` / ``incremental_updates`` count them;
* :meth:`ZoneField.path_from` is the new global path: gradient motion of the potential from a
  point to the goal voxel, the voxel chain reduced by
  :func:`~skyroute.stages.planning.potential.reduce_waypoints` against the problem with the
  zones (so no shortcut enters them), ending at the goal.

The tactical replay uses it in the octant method (:func:`~skyroute.stages.tactical.octant_replan.update_zones`):
the chain goes through the same STEP III, validator and exact separation / zone checks as every
other tactical candidate before it is flown.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from skyroute.stages.base import InputError, PlanningError
from skyroute.stages.planning import potential as P
from skyroute.stages.planning.problem import PlanningProblem
from skyroute.stages.tactical.zones import ZoneBox, dense_mask

__all__ = ["ZoneField", "zone_cells", "zone_problem", "zone_voxels"]


def zone_cells(boxes, grid, widen_m: float) -> np.ndarray:
    """(ny, nx) bool: cells of ``grid`` whose closed square meets one of ``boxes``
    (:class:`ZoneBox`) widened by ``widen_m`` [m] on every side."""
    if not widen_m >= 0:
        raise InputError(f"zone widening {widen_m} m must be >= 0 (the vehicle radius r_p)")
    wide = [ZoneBox(b.bits, b.x_min_m - widen_m, b.x_max_m + widen_m, b.y_min_m - widen_m, b.y_max_m + widen_m)
            for b in boxes]
    return dense_mask(wide, grid.x0, grid.y1, grid.resolution_m, grid.shape)


def zone_problem(problem: PlanningProblem, cells: np.ndarray) -> PlanningProblem:
    """``problem`` with the columns ``cells`` (ny, nx) bool forbidden (floor +inf, no-fly)."""
    cells = np.asarray(cells, bool)
    if cells.shape != problem.grid.shape:
        raise InputError(f"zone cells have shape {cells.shape}; expected the grid's {problem.grid.shape}")
    if not cells.any():
        return problem
    nofly = cells if problem.nofly is None else (np.asarray(problem.nofly, bool) | cells)
    return replace(problem, floor_m=np.where(cells, np.inf, problem.floor_m), nofly=nofly)


def zone_voxels(vmap: P.VoxelMap, cells: np.ndarray, origin_rc: tuple[int, int]) -> np.ndarray:
    """(nz, ny, nx) bool: the voxels of ``vmap`` whose footprint holds a cell of ``cells``
    (grid (ny, nx) bool); ``origin_rc``: grid (row, col) of the bitmap's top-left cell."""
    r0, c0 = origin_rc
    b = vmap.block
    _, ny, nx = vmap.shape
    sub = np.asarray(cells, bool)[r0:r0 + ny * b, c0:c0 + nx * b]
    if sub.shape != (ny * b, nx * b):
        raise InputError("the bitmap reaches beyond the grid of the zone cells")
    col = sub.reshape(ny, b, nx, b).any(axis=(1, 3))
    return np.broadcast_to(col[None], vmap.shape)


@dataclass(eq=False)
class ZoneField:
    """The W-potential of a workspace box with dense zones as obstacles (module docstring).

    ``base``: the bitmap without zones; ``field``: the current
    :class:`~skyroute.stages.planning.potential.PotentialField`; ``boxes``: the zones it holds;
    ``widen_m`` [m]: their widening (r_p); ``origin_rc``: grid (row, col) of the bitmap's
    top-left cell; ``full_computations`` / ``incremental_updates``: how often the potential
    was computed in full / updated; ``timings_s``: one ``(kind, seconds, re-waved voxels)``
    per computation."""

    problem: PlanningProblem
    base: P.VoxelMap
    field: P.PotentialField
    boxes: tuple
    widen_m: float
    origin_rc: tuple[int, int]
    full_computations: int = 1
    incremental_updates: int = 0
    timings_s: list = field(default_factory=list)

    # ---------------------------------------------------------------- construction
    @classmethod
    def build(cls, problem: PlanningProblem, boxes=(), *, widen_m: float | None = None,
              margin_m: float = P.DEFAULT_MARGIN_M, voxel_m: float | None = None, dz_m: float | None = None,
              off_skeleton_weight: float = P.DEFAULT_OFF_SKELETON_WEIGHT,
              vertical_weight: float | None = None) -> ZoneField:
        """The full field of ``problem`` (static maps; its start and goal span the workspace,
        plus ``margin_m`` [m]) with the zones ``boxes`` widened by ``widen_m`` (default r_p) as
        obstacles; the potential's goal is the voxel of ``problem.goal_xyz``.  ``voxel_m`` [m]
        default :func:`~skyroute.stages.planning.potential.default_voxel_m`; ``dz_m`` [m]
        default ``voxel_m tan(0.95 gamma_max)``: then every 26-neighbour move of the gradient
        motion is within the vehicle's flight-path angle, so the voxel chain itself is a
        flyable fallback of the waypoint reduction."""
        t0 = time.perf_counter()
        r_p = float(problem.vehicle.r_p_m) if widen_m is None else float(widen_m)
        if vertical_weight is None:
            vertical_weight = 1.0 / math.tan(math.radians(problem.vehicle.max_flight_path_angle_deg))
        (xs, ys, _), (xg, yg, _) = problem.start_xyz, problem.goal_xyz
        bounds = (min(xs, xg) - margin_m, min(ys, yg) - margin_m, max(xs, xg) + margin_m, max(ys, yg) + margin_m)
        h = P.default_voxel_m(problem.grid.resolution_m) if voxel_m is None else float(voxel_m)
        if dz_m is None:
            dz_m = h * math.tan(math.radians(0.95 * problem.vehicle.max_flight_path_angle_deg))
        base = P.occupancy_bitmap(problem, h, dz_m, bounds_m=bounds)
        g = problem.grid
        origin = (int(round((g.y1 - base.y1_m) / g.resolution_m)), int(round((base.x0_m - g.x0) / g.resolution_m)))
        gl = P.entry_voxel(problem, base, problem.goal_xyz)
        if gl is None:
            raise PlanningError(f"{problem.label}: no free voxel near the goal for the zone potential field")
        zf = cls(problem, base, None, tuple(boxes), r_p, origin)  # type: ignore[arg-type]
        vm = zf._with_zones(zf.boxes)
        if not vm.free[gl]:
            raise PlanningError("a dense zone covers the goal: no zone potential field")
        zf.field = P.potential_field(vm, gl, off_skeleton_weight=off_skeleton_weight, vertical_weight=vertical_weight)
        zf.timings_s.append(("full", time.perf_counter() - t0, int(np.isfinite(zf.field.potential_m).sum())))
        return zf

    def _with_zones(self, boxes) -> P.VoxelMap:
        cells = zone_cells(boxes, self.problem.grid, self.widen_m)
        zv = zone_voxels(self.base, cells, self.origin_rc)
        return replace(self.base, free=self.base.free & ~zv, obstacle=self.base.obstacle | zv)

    def covers(self, xyz) -> bool:
        """Whether the point ``xyz`` [m] lies inside the field's bitmap."""
        return bool(self.base.inside(self.base.index_of(xyz))[0])

    # ---------------------------------------------------------------- zone changes
    def set_zones(self, boxes) -> bool:
        """Make ``boxes`` the field's zones: :func:`update_potential` when they differ from the
        current ones (counted in ``incremental_updates``); returns whether it recomputed."""
        boxes = tuple(boxes)
        if boxes == self.boxes:
            return False
        t0 = time.perf_counter()
        vm = self._with_zones(boxes)
        if not vm.free[self.field.goal]:
            raise PlanningError("a dense zone covers the goal: the zone potential field cannot be updated")
        self.field = P.update_potential(self.field, vm.free, vm.obstacle)
        self.boxes = boxes
        self.incremental_updates += 1
        self.timings_s.append(("incremental", time.perf_counter() - t0,
                               int(self.field.timings_s.get("affected_voxels", 0))))
        return True

    # ---------------------------------------------------------------- the new global path
    def path_from(self, problem: PlanningProblem, xyz) -> np.ndarray:
        """Waypoints (k, 3) [m] from ``xyz`` to ``problem.goal_xyz``: gradient motion of the
        potential from the voxel entered from ``xyz``, reduced against ``problem`` with the
        zones as no-fly columns.  Raises PlanningError when ``xyz`` has no free voxel joined to
        it or the potential does not reach it."""
        vm = self.field.vmap
        cells = zone_cells(self.boxes, problem.grid, self.widen_m)
        zprob = zone_problem(problem, cells)
        p = np.asarray(xyz, float)
        s = P.entry_voxel(zprob, vm, p)
        if s is None:
            raise PlanningError(f"no free voxel of the zone potential field is joined to ({p[0]:.0f}, {p[1]:.0f}, "
                                f"{p[2]:.0f}) by a valid motion")
        if not np.isfinite(self.field.potential_m[s]):
            raise PlanningError("the dense zones cut the vehicle off from the goal in the potential field")
        path = P.descend(self.field, s)
        if path[-1] != np.ravel_multi_index(self.field.goal, vm.shape):
            raise PlanningError("the gradient motion stopped before the goal voxel")
        chain = np.vstack([p[None], vm.centres(path), np.asarray(problem.goal_xyz, float)[None]])
        wp, ok = P.reduce_waypoints(zprob, self.field, chain)
        if not ok:
            bad = int(np.argmin(zprob.motion_valid(wp[:-1], wp[1:])))
            raise PlanningError(f"the potential-field path is not a valid motion near ({wp[bad, 0]:.0f}, "
                                f"{wp[bad, 1]:.0f}, {wp[bad, 2]:.0f}): {zprob.explain_motion(wp[bad], wp[bad + 1])}")
        return wp
