"""Independent exact oracle of the prism visibility height, for the tests only.

Not a grid traversal (the shipped caster, ``skyroute.stages.raycast``, is Amanatides-Woo):
every cell within reach of the ray is tested on its own with the slab method (ray / closed
axis-aligned box intersection), and a cell the ray meets at ``t_in >= 0`` [cells] requires
``h - t_in * cell * tan(e)``.  Cells are closed boxes: touching counts as blocking, and the
cells containing the point give their own height (``t_in = 0``).  Outside the map: no
obstacle.  Points are (row, col) in fractional cells, cell (i, j) = [i, i+1] x [j, j+1].
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def _slab_t_in(r, c, dx, dy, i, j):
    """Entry distance [cells] of the ray (r, c) + t (dy, dx), t >= 0, into the closed box of
    cell (i, j); -1.0 when it misses."""
    if dx == 0.0:
        if c < j or c > j + 1:
            return -1.0
        tx0, tx1 = -1e300, 1e300
    else:
        a = (j - c) / dx
        b = (j + 1 - c) / dx
        tx0, tx1 = min(a, b), max(a, b)
    if dy == 0.0:
        if r < i or r > i + 1:
            return -1.0
        ty0, ty1 = -1e300, 1e300
    else:
        a = (i - r) / dy
        b = (i + 1 - r) / dy
        ty0, ty1 = min(a, b), max(a, b)
    t_in = max(max(tx0, ty0), 0.0)
    t_out = min(tx1, ty1)
    if t_in <= t_out:
        return t_in
    return -1.0


@numba.njit(cache=True)
def oracle_point(h, r, c, az_grid_deg, el_deg, cell_m):
    """Exact visibility height [m] at the point (row r, col c) [fractional cells]."""
    ny, nx = h.shape
    az = math.radians(az_grid_deg)
    dx = math.sin(az)
    dy = -math.cos(az)
    if abs(dx) < 1e-15:
        dx = 0.0
    if abs(dy) < 1e-15:
        dy = 0.0
    drop = cell_m * math.tan(math.radians(el_deg)) if el_deg < 90.0 else 1e300
    hmax = h.max()
    hmin = h.min()
    reach = (hmax - hmin) / drop + 2.0
    v = -1e300
    # walk the major axis; at each index the minor span the ray covers, +-1 cell
    if abs(dx) >= abs(dy):
        c_end = c + reach * dx
        j0 = max(int(math.floor(min(c, c_end))) - 1, 0)
        j1 = min(int(math.floor(max(c, c_end))) + 1, nx - 1)
        for j in range(j0, j1 + 1):
            if dx != 0.0:
                ta = max(min((j - c) / dx, (j + 1 - c) / dx), 0.0)
                tb = max((j - c) / dx, (j + 1 - c) / dx)
            else:
                ta, tb = 0.0, 0.0
            if tb < 0.0:
                continue
            ra = r + ta * dy
            rb = r + tb * dy
            i0 = max(int(math.floor(min(ra, rb))) - 1, 0)
            i1 = min(int(math.floor(max(ra, rb))) + 1, ny - 1)
            for i in range(i0, i1 + 1):
                t = _slab_t_in(r, c, dx, dy, i, j)
                if t >= 0.0:
                    w = h[i, j] - t * drop
                    if w > v:
                        v = w
    else:
        r_end = r + reach * dy
        i0 = max(int(math.floor(min(r, r_end))) - 1, 0)
        i1 = min(int(math.floor(max(r, r_end))) + 1, ny - 1)
        for i in range(i0, i1 + 1):
            ta = max(min((i - r) / dy, (i + 1 - r) / dy), 0.0)
            tb = max((i - r) / dy, (i + 1 - r) / dy)
            if tb < 0.0:
                continue
            ca = c + ta * dx
            cb = c + tb * dx
            j0 = max(int(math.floor(min(ca, cb))) - 1, 0)
            j1 = min(int(math.floor(max(ca, cb))) + 1, nx - 1)
            for j in range(j0, j1 + 1):
                t = _slab_t_in(r, c, dx, dy, i, j)
                if t >= 0.0:
                    w = h[i, j] - t * drop
                    if w > v:
                        v = w
    return v


@numba.njit(cache=True, parallel=True)
def oracle_points(h, rows, cols, az_grid_deg, el_deg, cell_m):
    """:func:`oracle_point` of many points, one direction."""
    out = np.empty(rows.size)
    for n in numba.prange(rows.size):
        out[n] = oracle_point(h, rows[n], cols[n], az_grid_deg, el_deg, cell_m)
    return out


def shadow_edge_points(h, az_grid_deg, el_deg, cell_m, n, rng, eps=1e-7):
    """``n`` points (rows, cols) [fractional cells] placed on lateral shadow edges: on the
    ray back from a corner of a high cell (away from the satellite), at a random distance
    within the shadow's reach, offset ``eps`` [cells] to either side of that ray."""
    ny, nx = h.shape
    az = math.radians(az_grid_deg)
    dx, dy = math.sin(az), -math.cos(az)
    drop = cell_m * math.tan(math.radians(el_deg))
    thr = np.percentile(h, 90.0)
    hi_i, hi_j = np.nonzero(h >= thr)
    rows, cols = [], []
    tries = 0
    while len(rows) < n and tries < 50 * n:
        tries += 1
        k = rng.integers(hi_i.size)
        ci = hi_i[k] + rng.integers(0, 2)
        cj = hi_j[k] + rng.integers(0, 2)
        reach = max((h[hi_i[k], hi_j[k]] - h.min()) / drop, 0.5)
        t = rng.uniform(0.0, reach)
        side = rng.choice([-1.0, 1.0]) * eps
        r = ci - t * dy + side * dx
        c = cj - t * dx - side * dy
        if 0.0 <= r <= ny and 0.0 <= c <= nx:
            rows.append(r)
            cols.append(c)
    return np.asarray(rows), np.asarray(cols)
