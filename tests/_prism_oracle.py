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
def oracle_point(h, r, c, az_grid_deg, el_deg, cell_m, hmax, hmin):
    """Exact visibility height [m] at the point (row r, col c) [fractional cells]; ``hmax``,
    ``hmin``: the extremes of ``h`` [m]."""
    ny, nx = h.shape
    az = math.radians(az_grid_deg)
    dx = math.sin(az)
    dy = -math.cos(az)
    if abs(dx) < 1e-15:
        dx = 0.0
    if abs(dy) < 1e-15:
        dy = 0.0
    drop = cell_m * math.tan(math.radians(el_deg)) if el_deg < 90.0 else 1e300
    reach = (hmax - hmin) / drop + 2.0
    v = -1e300
    # walk the major axis away from the point; at each index the minor span the ray covers,
    # +-1 cell; stop once no farther cell can matter (h max - entry drop <= v)
    if abs(dx) >= abs(dy):
        n_idx = int(reach) + 3
        sj = 1 if dx > 0.0 else -1
        jc = int(math.floor(c))
        for k in range(-1, n_idx):
            j = jc + sj * k
            if j < 0 or j >= nx:
                if k >= 0:
                    break
                continue
            ta = max(min((j - c) / dx, (j + 1 - c) / dx), 0.0)
            tb = max((j - c) / dx, (j + 1 - c) / dx)
            if tb < 0.0:
                continue
            if hmax - ta * drop <= v:
                break
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
        n_idx = int(reach) + 3
        si = 1 if dy > 0.0 else -1
        ic = int(math.floor(r))
        for k in range(-1, n_idx):
            i = ic + si * k
            if i < 0 or i >= ny:
                if k >= 0:
                    break
                continue
            ta = max(min((i - r) / dy, (i + 1 - r) / dy), 0.0)
            tb = max((i - r) / dy, (i + 1 - r) / dy)
            if tb < 0.0:
                continue
            if hmax - ta * drop <= v:
                break
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
    hmax = h.max()
    hmin = h.min()
    for n in numba.prange(rows.size):
        out[n] = oracle_point(h, rows[n], cols[n], az_grid_deg, el_deg, cell_m, hmax, hmin)
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
