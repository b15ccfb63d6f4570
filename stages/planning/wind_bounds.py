"""Energy-ratio bounds of a wind map, per tile (issue 23): the largest per-plan cost of a
city-scale A* computed once per map and vehicle, then reused by every mission.

The A* heuristic (:func:`~skyroute.stages.planning.grid_planner._move_rates`) bounds E_w / E_0
from below for each of the lattice's edge directions over every wind a plan can meet: every
column and level of the wind map and the level-to-level interpolations
(:func:`~skyroute.stages.planning.heuristic.energy_ratio_lb_dense_each`).  On the 20 km city's
planning window that is 3.1 M winds x 24 directions, about 15 s of CPU per plan.  A minimum
over a union is the minimum of the minima of its parts, so :func:`wind_ratio_tiles` computes
the bound per tile of :data:`TILE_COLS` x :data:`TILE_COLS` wind columns (the same winds, the
same compiled kernel, the same numbers) and :func:`ratio_lb_over` takes the minimum over the
tiles that meet a window's wind columns: a superset of the winds of the window, so the bound is
still a lower bound for every plan in it (on a whole map, exactly the bound computed directly).
The pipeline caches the tiles as the ``wind_bounds`` stage (inputs: the wind map; settings:
the vehicle and the lattice step), so a plan with cached maps reads them in milliseconds.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from skyroute.stages.energy import power_params
from skyroute.stages.planning.grid_planner import lattice_dz_m, lattice_edge_dirs
from skyroute.stages.planning.heuristic import wind_samples_dense
from skyroute.stages.planning.kernels import ratio_each_kernel, vehicle_params
from skyroute.stages.planning.problem import wind_uvw
from skyroute.stages.vehicle import profile_hash

__all__ = ["TILE_COLS", "lattice_dirs", "tiles_fit", "wind_ratio_tiles"]

TILE_COLS = 8          # wind columns per tile side (800 m on the usual 100 m wind grid)


def lattice_dirs(vehicle, resolution_m: float, step_cells: int) -> np.ndarray:
    """The unit edge directions (k, 3) of the A* lattice of ``step_cells`` grid cells of
    ``resolution_m`` [m] for ``vehicle`` (:func:`~.grid_planner.lattice_edge_dirs` with the
    default level spacing of :func:`~.grid_planner.make_lattice`)."""
    step_m = int(step_cells) * float(resolution_m)
    deg = vehicle.max_flight_path_angle_deg
    return lattice_edge_dirs(step_m, lattice_dz_m(step_m, deg), deg)[1]


def wind_ratio_tiles(wind: xr.Dataset, vehicle, resolution_m: float, step_cells: int,
                     tile_cols: int = TILE_COLS) -> xr.Dataset:
    """Per tile of ``tile_cols`` x ``tile_cols`` columns of the wind map and per lattice edge
    direction, the minimum of E_w / E_0 over the tile's winds and their level-to-level
    interpolations (no safety factor; inf where no wind of the tile is flyable).

    Parameters
    ----------
    wind : xarray.Dataset
        The wind stage's map: ``u``, ``v`` (and ``w``) [m/s] on ``(z, y, x)``.
    vehicle : VehicleProfile
        The rotorcraft.
    resolution_m : float
        The AOI grid's cell side [m].
    step_cells : int
        The A* lattice step [cells].
    tile_cols : int, default :data:`TILE_COLS`
        Wind columns per tile side.

    Returns
    -------
    xarray.Dataset
        ``ratio_lb`` (``tile_y``, ``tile_x``, ``direction``) [-], ``dirs`` (``direction``,
        ``xyz``) [-], and the tiles' map extents ``x_min_m``, ``x_max_m`` (``tile_x``) and
        ``y_min_m``, ``y_max_m`` (``tile_y``) [m].
    """
    uvw = wind_uvw(wind).astype(np.float64)
    x = np.asarray(wind["x"].values, float)
    y = np.asarray(wind["y"].values, float)
    rx = abs(x[1] - x[0]) if x.size > 1 else float(wind.attrs.get("horizontal_step_m", resolution_m))
    ry = abs(y[1] - y[0]) if y.size > 1 else rx
    dirs = np.ascontiguousarray(lattice_dirs(vehicle, resolution_m, step_cells))
    veh, power = vehicle_params(vehicle, 10.0), power_params(vehicle)
    t = int(tile_cols)
    ty, tx = range(0, y.size, t), range(0, x.size, t)
    out = np.full((len(ty), len(tx), dirs.shape[0]), np.inf)
    for i, r0 in enumerate(ty):
        for j, c0 in enumerate(tx):
            winds = wind_samples_dense(uvw[:, r0:r0 + t, c0:c0 + t])
            out[i, j] = ratio_each_kernel(dirs, winds, veh, power)
    xs = [x[c0:c0 + t] for c0 in tx]
    ys = [y[r0:r0 + t] for r0 in ty]
    return xr.Dataset(
        {"ratio_lb": (("tile_y", "tile_x", "direction"), out,
                      {"units": "1", "long_name": "min E_w/E_0 over the tile's winds (no safety factor)"}),
         "dirs": (("direction", "xyz"), dirs, {"units": "1", "long_name": "lattice edge unit directions"}),
         "x_min_m": ("tile_x", [float(v.min() - rx / 2) for v in xs], {"units": "m"}),
         "x_max_m": ("tile_x", [float(v.max() + rx / 2) for v in xs], {"units": "m"}),
         "y_min_m": ("tile_y", [float(v.min() - ry / 2) for v in ys], {"units": "m"}),
         "y_max_m": ("tile_y", [float(v.max() + ry / 2) for v in ys], {"units": "m"})},
        attrs={"tile_cols": t, "step_cells": int(step_cells), "resolution_m": float(resolution_m),
               "vehicle": getattr(vehicle, "name", ""), "vehicle_hash": profile_hash(vehicle)})


def tiles_fit(tiles: xr.Dataset | None, vehicle, step_cells: int) -> bool:
    """True when ``tiles`` (:func:`wind_ratio_tiles`) were computed for this vehicle profile
    (by content) and lattice step [cells]."""
    return (tiles is not None and "ratio_lb" in tiles and tiles.attrs.get("vehicle_hash") == profile_hash(vehicle)
            and int(tiles.attrs.get("step_cells", -1)) == int(step_cells))
