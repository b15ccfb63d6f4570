"""Exact visibility height at arbitrary points: a prism ray caster (the truth model).

The surface model is the one of :mod:`skyroute.stages.occlusion`: every cell is a
flat-topped prism, its closed square footprint extruded up to its height [m]; outside the
map there is no obstacle.  For a point ``(x, y)`` and a satellite at infinity in direction
(grid azimuth ``a``, elevation ``e``), the *exact* visibility height is

    ``V(x, y) = max(h(cells whose footprint contains the point),
                    max_c h(c) - t_c tan(e))``

over the cells ``c`` the horizontal ray from ``(x, y)`` toward the satellite meets, ``t_c``
[m] the horizontal distance at which it enters ``c``.  At and above ``V`` the satellite is
in line of sight.  A ray that only touches a prism (through a corner, or along a face) is
counted as blocked, and a point on a cell edge stands on both cells: the value is the upper
limit of the values of nearby points, the safe side.

Algorithm: Amanatides & Woo (1987) grid traversal of the ray, cell by cell in order of
entry, stopping when no cell can still raise ``V`` (``max h - t tan e <= V``) or at the map
edge.  O(cells crossed) per point and direction; numba, parallel over points.  This is what
the navigation simulation uses as truth, and what the conservative column scan
(:func:`skyroute.stages.occlusion.visibility_height`) bounds from above at every point of
each cell.

Layers: the numba kernel :func:`_cast_kernel`, the numpy runner
:func:`exact_visibility_heights_numpy` (points in fractional cell coordinates) and the public
:func:`exact_visibility_height` (map coordinates on an ``xarray`` surface).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import xarray as xr

from skyroute.stages.base import InputError
from skyroute.stages.grid import Grid

__all__ = ["exact_visibility_height", "exact_visibility_heights_numpy"]


@numba.njit(cache=True, nogil=True, inline="always")
def _own_height(h, r, c):
    """Highest cell whose closed footprint contains the point at (row, col) ``r, c``
    [cells, fractional, 0..n]."""
    ny, nx = h.shape
    i0 = min(int(math.floor(r)), ny - 1)
    j0 = min(int(math.floor(c)), nx - 1)
    i1 = i0 - 1 if (r == i0 and i0 > 0) else i0          # on the edge with the row above
    j1 = j0 - 1 if (c == j0 and j0 > 0) else j0
    i2 = i0 + 1 if (r == i0 + 1 and i0 + 1 < ny) else i0  # r == ny on the south edge
    j2 = j0 + 1 if (c == j0 + 1 and j0 + 1 < nx) else j0
    v = -np.inf
    for i in (i1, i0, i2):
        for j in (j1, j0, j2):
            if h[i, j] > v:
                v = h[i, j]
    return v


@numba.njit(cache=True, nogil=True)
def _cast_one(h, hmax, r, c, dx, dy, drop_per_cell):
    """Exact visibility height [m] of one point (row ``r``, col ``c``, fractional cells);
    ``(dx, dy)``: unit horizontal direction toward the satellite in (col, row) units;
    ``drop_per_cell``: ray height gain [m] per cell of horizontal distance (cell tan e).
    A ray running along a grid line touches the cells on both sides: both are walked."""
    ny, nx = h.shape
    cx = min(int(math.floor(c)), nx - 1)
    cy = min(int(math.floor(r)), ny - 1)
    v = _walk(h, hmax, r, c, dx, dy, drop_per_cell, cx, cy, _own_height(h, r, c))
    if dx == 0.0 and c == math.floor(c) and 0 < c < nx:
        v = _walk(h, hmax, r, c, dx, dy, drop_per_cell, int(c) - 1, cy, v)
    if dy == 0.0 and r == math.floor(r) and 0 < r < ny:
        v = _walk(h, hmax, r, c, dx, dy, drop_per_cell, cx, int(r) - 1, v)
    return v


@numba.njit(cache=True, nogil=True)
def _walk(h, hmax, r, c, dx, dy, drop_per_cell, cx, cy, v):
    """Amanatides-Woo walk of the ray of the point (r, c) from the cell (cy, cx), raising
    ``v`` [m] by every cell entered."""
    ny, nx = h.shape
    big = 1e300
    sx = 1 if dx > 0.0 else -1
    sy = 1 if dy > 0.0 else -1
    # distance to the next vertical / horizontal grid line, and between lines
    if dx > 0.0:
        tmx = (cx + 1 - c) / dx
        tdx = 1.0 / dx
    elif dx < 0.0:
        tmx = (cx - c) / dx
        tdx = -1.0 / dx
    else:
        tmx = big
        tdx = big
    if dy > 0.0:
        tmy = (cy + 1 - r) / dy
        tdy = 1.0 / dy
    elif dy < 0.0:
        tmy = (cy - r) / dy
        tdy = -1.0 / dy
    else:
        tmy = big
        tdy = big
    while True:
        if tmx < tmy:
            t = tmx
            tmx += tdx
            cx += sx
        elif tmy < tmx:
            t = tmy
            tmy += tdy
            cy += sy
        else:
            # through a grid corner: the ray touches both side cells there, then goes on
            # diagonally
            t = tmx
            rq = t * drop_per_cell
            ax = cx + sx
            ay = cy + sy
            if 0 <= ax < nx and 0 <= cy < ny and h[cy, ax] - rq > v:
                v = h[cy, ax] - rq
            if 0 <= cx < nx and 0 <= ay < ny and h[ay, cx] - rq > v:
                v = h[ay, cx] - rq
            tmx += tdx
            tmy += tdy
            cx = ax
            cy = ay
        if cx < 0 or cx >= nx or cy < 0 or cy >= ny:
            break
        rq = t * drop_per_cell
        if hmax - rq <= v:
            break
        w = h[cy, cx] - rq
        if w > v:
            v = w
    return v


@numba.njit(cache=True, parallel=True)
def _cast_kernel(h, rows, cols, dirs, out):
    """``out[d, n]``: exact visibility height of point ``n`` (``rows``, ``cols``) for the
    direction ``dirs[d] = (dx, dy, drop_per_cell)``."""
    hmax = -np.inf
    for v in h.ravel():
        if v > hmax:
            hmax = v
    for n in numba.prange(rows.size):
        for d in range(dirs.shape[0]):
            dx = dirs[d, 0]
            dy = dirs[d, 1]
            if dirs[d, 2] == np.inf:   # zenith: only the ground under the point
                out[d, n] = _own_height(h, rows[n], cols[n])
            else:
                out[d, n] = _cast_one(h, hmax, rows[n], cols[n], dx, dy, dirs[d, 2])


def _directions(az_grid_deg, el_deg, cell_m: float) -> tuple[np.ndarray, tuple[int, ...]]:
    az = np.asarray(az_grid_deg, dtype=np.float64)
    el = np.asarray(el_deg, dtype=np.float64)
    if az.shape != el.shape or az.ndim > 1:
        raise InputError(f"az and el must be scalars or 1-D of equal length, got shapes "
                         f"{az.shape} and {el.shape}")
    if not (np.all(np.isfinite(az)) and np.all(np.isfinite(el))):
        raise InputError("azimuths and elevations must be finite")
    bad = (el <= 0.0) | (el > 90.0)
    if np.any(bad):
        raise InputError(f"elevation(s) {np.atleast_1d(el)[np.atleast_1d(bad)].tolist()} deg out of "
                         "(0, 90]: a satellite at or below the horizon is never in line of sight")
    a = np.deg2rad(np.atleast_1d(az))
    e = np.atleast_1d(el)
    dirs = np.empty((a.size, 3))
    dirs[:, 0] = np.sin(a)          # +col is grid east
    dirs[:, 1] = -np.cos(a)         # +row is grid south
    xy = dirs[:, :2]
    xy[np.abs(xy) < 1e-15] = 0.0    # axis directions: no sin/cos round-off drift
    dirs[:, 2] = np.inf
    lo = e < 90.0
    dirs[lo, 2] = cell_m * np.tan(np.deg2rad(e[lo]))
    return dirs, az.shape


def exact_visibility_heights_numpy(surface_2d: np.ndarray, rows, cols, az_grid_deg, el_deg,
                                   cell_m: float) -> np.ndarray:
    """Exact visibility heights [m] at points given in fractional cell coordinates.

    ``surface_2d``: NaN-free heights [m] (row 0 = north edge); ``rows``, ``cols`` [cells]:
    point positions, cell ``(i, j)`` covering ``[i, i + 1] x [j, j + 1]`` (so the centre of
    cell (i, j) is (i + 0.5, j + 0.5)), inside ``[0, ny] x [0, nx]``; ``az_grid_deg``:
    azimuth(s) [deg] clockwise from grid north; ``el_deg``: elevation(s) in (0, 90] [deg];
    ``cell_m``: cell size [m].  Returns ``az.shape + rows.shape`` float64.
    """
    h = np.ascontiguousarray(surface_2d, dtype=np.float64)
    if h.ndim != 2 or h.size == 0:
        raise InputError(f"surface must be a non-empty 2-D (y, x) array, got shape {h.shape}")
    if not np.all(np.isfinite(h)):
        raise InputError("surface has NaN or infinite cells: fill them first")
    if not cell_m > 0:
        raise InputError(f"cell size {cell_m} m must be positive")
    r, c = np.broadcast_arrays(np.asarray(rows, dtype=np.float64), np.asarray(cols, dtype=np.float64))
    shape = r.shape
    r = np.ascontiguousarray(r.ravel())
    c = np.ascontiguousarray(c.ravel())
    ny, nx = h.shape
    outside = ~((r >= 0) & (r <= ny) & (c >= 0) & (c <= nx))
    if np.any(outside):
        k = int(np.flatnonzero(outside)[0])
        raise InputError(f"{int(outside.sum())} point(s) outside the surface, e.g. (row, col) = "
                         f"({r[k]:g}, {c[k]:g}) for a {ny} x {nx} map: crop the points or extend "
                         "the surface")
    dirs, dshape = _directions(az_grid_deg, el_deg, float(cell_m))
    out = np.empty((dirs.shape[0], r.size))
    _cast_kernel(h, r, c, dirs, out)
    return out.reshape(dshape + shape)


def exact_visibility_height(surface: xr.DataArray, x, y, az_grid_deg, el_deg) -> np.ndarray:
    """Exact visibility height [m] at map points ``(x, y)`` [m, surface CRS] over a surface.

    ``surface``: (y, x) heights [m] on a north-up projected grid (see
    :mod:`skyroute.stages.grid`), NaN-free; ``x``, ``y``: point coordinates (broadcast
    together), inside the map's outer edges; ``az_grid_deg``: azimuth(s) [deg] clockwise
    from the map's **grid** north (convert true azimuths with
    :func:`skyroute.stages.occlusion.grid_azimuth_deg`); ``el_deg``: elevation(s) in (0, 90]
    [deg].  Returns ``az.shape + points shape`` float64 heights in the surface's vertical
    datum: at and above them the satellite is in line of sight from the point (flat-topped
    prism cells, satellites at infinity, flat Earth as in :mod:`skyroute.stages.occlusion`).
    """
    if not isinstance(surface, xr.DataArray) or surface.dims != ("y", "x"):
        raise InputError("surface must be an xarray.DataArray with dims ('y', 'x')")
    grid = Grid.from_dataarray(surface)
    cell = grid.resolution_m
    xs = np.asarray(x, dtype=np.float64)
    ys = np.asarray(y, dtype=np.float64)
    cols = (xs - grid.x0) / cell
    rows = (grid.y1 - ys) / cell
    return exact_visibility_heights_numpy(np.asarray(surface.values), rows, cols, az_grid_deg,
                                          el_deg, cell)
