"""The planning window (issue 23): on a city-scale AOI the strategic planner reads only a
rectangle of the maps around the mission.

The maps of a 20 x 20 km city at 2 m hold 1e8 cells; a plan's problem keeps several float64
rasters per coverage level, which for the whole AOI passes the machine's memory (README,
"City-scale planning") although a 15 km mission's path stays near the line between its
endpoints.  So, on an AOI of at least :data:`WINDOW_MIN_CELLS` cells, the planner is given the
maps cropped to the bounding box of the start and the goal widened by a margin
(:func:`window_margin_m`: :data:`WINDOW_MARGIN_FRAC` of the mission's horizontal length, at least
:data:`WINDOW_MARGIN_MIN_M`), read lazily: only the window's chunks of the cached zarr stores
are loaded.

Safety: cropping keeps every cell's value (the clearance and coverage floors were computed on the
whole AOI, with every occluder and building outside the window), so a plan in the window obeys
exactly the maps, limits and validator of a plan on the whole AOI; it only cannot leave the
window, as no plan can leave the AOI.  Optimality: only paths inside the window are searched.
When no coverage level gives a flyable plan and some level's STEP I found no path, the margin is
doubled (a counted widening, never timed) up to :data:`MAX_WINDOW_WIDENINGS` times, and the last
attempt is the whole AOI.  A window larger than :data:`WINDOW_MAX_FRACTION` of the AOI's cells
is not worth it: the whole AOI is used.  Every shipped scenario is smaller than
:data:`WINDOW_MIN_CELLS` and plans on its whole AOI as before.  A fleet (``skyroute fleet``)
plans each mission in its window as well; its cached heuristic tables and STEP I results are
kept per window (``cache_scope`` of :func:`~skyroute.stages.planning.strategic.plan_levels`).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

if TYPE_CHECKING:     # light at import (the memory estimate of a warm run calls window_slices)
    from skyroute.stages.gridspec import Grid

__all__ = ["MAX_WINDOW_WIDENINGS", "WINDOW_MARGIN_FRAC", "WINDOW_MARGIN_MIN_M", "WINDOW_MAX_FRACTION",
           "WINDOW_MIN_CELLS", "crop_maps", "crop_on_grid", "crop_wind", "on_aoi_grid", "path_window", "plan_cells",
           "planning_windows", "window_box", "window_margin_m", "window_slices"]

WINDOW_MIN_CELLS = 16_000_000     # AOIs with fewer grid cells (every shipped scenario) plan on the whole AOI
WINDOW_MARGIN_MIN_M = 1000.0      # [m] smallest margin around the endpoints' bounding box
WINDOW_MARGIN_FRAC = 0.1          # margin as a fraction of the mission's horizontal length [-]
WINDOW_MAX_FRACTION = 0.6         # a window of more of the AOI's cells than this: the whole AOI instead
MAX_WINDOW_WIDENINGS = 2          # margin doublings before the last attempt on the whole AOI


def window_margin_m(start_xy, goal_xy) -> float:
    """The first window's margin [m] around the bounding box of ``start_xy`` and ``goal_xy`` [m].

    Parameters
    ----------
    start_xy, goal_xy : tuple of float
        Mission endpoints, map (x, y) [m].

    Returns
    -------
    float
        ``max(WINDOW_MARGIN_MIN_M, WINDOW_MARGIN_FRAC * |goal - start|)`` [m].
    """
    d = math.hypot(float(goal_xy[0]) - float(start_xy[0]), float(goal_xy[1]) - float(start_xy[1]))
    return max(WINDOW_MARGIN_MIN_M, WINDOW_MARGIN_FRAC * d)


def window_slices(grid: Grid, start_xy, goal_xy, margin_m: float) -> tuple[slice, slice] | None:
    """The (rows, cols) of ``grid`` within ``margin_m`` [m] of the endpoints' bounding box.

    Every cell that touches the widened box is in the window (rounded outwards), clipped to the
    grid.

    Parameters
    ----------
    grid : Grid
        The AOI's grid.
    start_xy, goal_xy : tuple of float
        Mission endpoints, map (x, y) [m].
    margin_m : float
        Margin around their bounding box [m], >= 0.

    Returns
    -------
    tuple of slice or None
        ``(rows, cols)``, or None when the grid has fewer than :data:`WINDOW_MIN_CELLS` cells or
        the window would hold more than :data:`WINDOW_MAX_FRACTION` of them (plan on the whole AOI).
    """
    n = grid.nx * grid.ny
    if n < WINDOW_MIN_CELLS:
        return None
    res = float(grid.resolution_m)
    xmin = min(start_xy[0], goal_xy[0]) - margin_m
    xmax = max(start_xy[0], goal_xy[0]) + margin_m
    ymin = min(start_xy[1], goal_xy[1]) - margin_m
    ymax = max(start_xy[1], goal_xy[1]) + margin_m
    c0 = max(0, math.floor((xmin - grid.x0) / res))
    c1 = min(grid.nx, math.ceil((xmax - grid.x0) / res))
    r0 = max(0, math.floor((grid.y1 - ymax) / res))
    r1 = min(grid.ny, math.ceil((grid.y1 - ymin) / res))
    if c1 <= c0 or r1 <= r0 or (r1 - r0) * (c1 - c0) > WINDOW_MAX_FRACTION * n:
        return None
    return slice(r0, r1), slice(c0, c1)


def planning_windows(grid: Grid, start_xy, goal_xy) -> list[tuple[slice, slice] | None]:
    """The windows a plan tries in turn: margins doubling from :func:`window_margin_m`
    (:data:`MAX_WINDOW_WIDENINGS` times), then the whole AOI (None); a single None on an AOI
    below :data:`WINDOW_MIN_CELLS` cells.

    Parameters
    ----------
    grid : Grid
        The AOI's grid.
    start_xy, goal_xy : tuple of float
        Mission endpoints, map (x, y) [m].

    Returns
    -------
    list of (tuple of slice or None)
        Distinct windows, smallest first, the last always None (the whole AOI).
    """
    out: list[tuple[slice, slice] | None] = []
    m = window_margin_m(start_xy, goal_xy)
    for _ in range(MAX_WINDOW_WIDENINGS + 1):
        w = window_slices(grid, start_xy, goal_xy, m)
        if w is None:
            break
        if w not in out:
            out.append(w)
        m *= 2.0
    out.append(None)
    return out


def window_box(grid: Grid, rows: slice, cols: slice) -> tuple[float, float, float, float]:
    """The bounds (xmin, ymin, xmax, ymax) [m] of the cells ``rows``, ``cols`` of ``grid``
    (row 0 at the top, ``grid.y1``).

    Parameters
    ----------
    grid : Grid
        The AOI's grid.
    rows, cols : slice
        The window (:func:`window_slices`).

    Returns
    -------
    tuple of float
    """
    res = float(grid.resolution_m)
    return (grid.x0 + cols.start * res, grid.y1 - rows.stop * res, grid.x0 + cols.stop * res,
            grid.y1 - rows.start * res)


def plan_cells(grid: Grid, start_xy, goal_xy) -> int:
    """The grid cells a plan of this mission reads first: its first window's
    (:func:`planning_windows`), else the whole AOI's.

    Parameters
    ----------
    grid : Grid
        The AOI's grid.
    start_xy, goal_xy : tuple of float
        Mission endpoints, map (x, y) [m].

    Returns
    -------
    int
    """
    w = planning_windows(grid, start_xy, goal_xy)[0]
    if w is None:
        return grid.nx * grid.ny
    return (w[0].stop - w[0].start) * (w[1].stop - w[1].start)


def _crop(ds, rows: slice, cols: slice):
    import xarray as xr

    if not isinstance(ds, (xr.Dataset, xr.DataArray)):
        return ds
    sel = {d: s for d, s in (("y", rows), ("x", cols)) if d in ds.dims}
    return ds.isel(sel) if sel else ds


def path_window(grid: Grid, xy) -> tuple[slice, slice] | None:
    """The window of a flight along the path ``xy`` (k, 2) [m] (``skyroute fly`` on a city):
    the path's bounding box widened by the first planning window's margin of its ends
    (:func:`window_margin_m`), so a tactical replan or a contingency landing near the path stays
    inside; None on an AOI below :data:`WINDOW_MIN_CELLS` cells (or when the window would hold
    more than :data:`WINDOW_MAX_FRACTION` of them).

    Parameters
    ----------
    grid : Grid
        The AOI's grid.
    xy : array_like
        (k, 2) map points [m] of the path, k >= 1.

    Returns
    -------
    tuple of slice or None
    """
    import numpy as np

    p = np.asarray(xy, float).reshape(-1, 2)
    return window_slices(grid, tuple(p.min(axis=0)), tuple(p.max(axis=0)), window_margin_m(p[0], p[-1]))


def crop_on_grid(ds, rows: slice, cols: slice, shape: tuple[int, int]):
    """``ds`` cropped to ``rows``, ``cols`` when it lies on the AOI's grid of ``shape`` (ny, nx)
    (lazily for a zarr-backed dataset); any other object (a wind map on its own grid, the
    satellites, None) as it is.

    Parameters
    ----------
    ds : xarray.Dataset, xarray.DataArray or other
        A map.
    rows, cols : slice
        The window (:func:`window_slices`).
    shape : tuple of int
        The AOI grid's (ny, nx).

    Returns
    -------
    Same type as ``ds``.
    """
    return _crop(ds, rows, cols) if on_aoi_grid(ds, shape) else ds


def on_aoi_grid(ds, shape: tuple[int, int]) -> bool:
    """True when ``ds`` is an xarray map on the AOI's grid of ``shape`` (ny, nx): dims ``y`` and
    ``x`` of those sizes (a wind map on its own coarser grid, the satellites or None: False)."""
    import xarray as xr

    return (isinstance(ds, (xr.Dataset, xr.DataArray)) and "x" in ds.dims and "y" in ds.dims
            and (ds.sizes["y"], ds.sizes["x"]) == tuple(shape))


def crop_maps(maps, rows: slice, cols: slice):
    """``maps`` (:class:`~skyroute.stages.planning.request.Maps`) with every dataset on the AOI's
    grid cropped to ``rows`` and ``cols`` (lazily: a zarr-backed dataset reads only those chunks).

    The wind keeps its own grid (sampled by map coordinates, usually coarser than the AOI's) and
    the satellites and traffic have no grid; their values are unchanged.

    Parameters
    ----------
    maps : Maps
        The AOI's maps.
    rows, cols : slice
        The window (:func:`window_slices`).

    Returns
    -------
    Maps
    """

    from skyroute.stages.gridspec import Grid

    shape = (maps.surface.sizes["y"], maps.surface.sizes["x"])

    def crop(ds):
        return crop_on_grid(ds, rows, cols, shape)

    wind = crop(maps.wind)
    if wind is maps.wind:       # not on the AOI's grid: its own (coarser) grid, or no grid
        wind = crop_wind(maps.wind, window_box(Grid.from_dataarray(maps.surface["terrain"]), rows, cols))
    by_level = None if maps.clearance_by_level is None else {k: crop(v) for k, v in maps.clearance_by_level.items()}
    return replace(maps, surface=crop(maps.surface), clearance=crop(maps.clearance), environment=crop(maps.environment),
                   wind=wind, coverage=crop(maps.coverage), clearance_by_level=by_level)


def crop_wind(wind, box: tuple[float, float, float, float]):
    """A wind map on its own grid (cells of ``horizontal_step_m``, dims ``y``, ``x``) cropped to
    the wind cells that meet ``box`` = (xmin, ymin, xmax, ymax) [m] plus one cell on every side
    (clipped to the map): every point of the box keeps the wind column it is given on the whole
    map (its nearest column, which the added cells keep away from the clipped edge), and the
    energy bound of the A* heuristic (the minimum over every wind of the map) is taken over the
    winds a plan in the window can meet.  Other winds (uniform, a vector, None, a map of one
    column) are returned as they are.

    Parameters
    ----------
    wind : xarray.Dataset or other
        The wind stage's map (``u``, ``v``, ``w`` on ``z``, ``y``, ``x``).
    box : tuple of float
        The window's bounds [m].

    Returns
    -------
    xarray.Dataset or other
    """
    import numpy as np
    import xarray as xr

    if not (isinstance(wind, xr.Dataset) and "x" in wind.dims and "y" in wind.dims
            and wind.sizes["x"] >= 2 and wind.sizes["y"] >= 2):
        return wind
    wx, wy = np.asarray(wind["x"].values, float), np.asarray(wind["y"].values, float)
    rx, ry = abs(wx[1] - wx[0]), abs(wy[1] - wy[0])
    kx = np.nonzero((wx + 1.5 * rx > box[0]) & (wx - 1.5 * rx < box[2]))[0]
    ky = np.nonzero((wy + 1.5 * ry > box[1]) & (wy - 1.5 * ry < box[3]))[0]
    if kx.size < 2 or ky.size < 2:
        return wind
    return wind.isel(x=slice(int(kx[0]), int(kx[-1]) + 1), y=slice(int(ky[0]), int(ky[-1]) + 1))
