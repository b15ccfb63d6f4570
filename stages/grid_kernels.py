"""Compiled (numba) kernels behind :mod:`skyroute.stages.grid`: footprint-overlap resampling,
NoData hole rims and the scanline ring fill.

Call the functions of :mod:`skyroute.stages.grid` (``footprint_resample``, ``find_holes``,
``ring_cells``), not these: they take raw arrays and do no checking.  They live in their own
module so that importing :class:`~skyroute.stages.grid.Grid` (every scenario and cache key
needs it) does not import numba; grid.py imports them inside the functions that run them.
Units: coordinates and sizes in metres of the grid CRS; ``eps`` [m].
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def sat_overlap(qx, qy, X0, X1, Y0, Y1, eps):  # pragma: no cover
    """Does the convex quadrilateral (qx, qy) overlap the box [X0, X1] x [Y0, Y1] by more than
    ``eps`` [m]?  Separating-axis test on the box axes and the 4 edge normals."""
    if max(qx[0], qx[1], qx[2], qx[3]) <= X0 + eps or min(qx[0], qx[1], qx[2], qx[3]) >= X1 - eps:
        return False
    if max(qy[0], qy[1], qy[2], qy[3]) <= Y0 + eps or min(qy[0], qy[1], qy[2], qy[3]) >= Y1 - eps:
        return False
    bx = (X0, X1, X1, X0)
    by = (Y0, Y0, Y1, Y1)
    for k in range(4):
        ex = qx[(k + 1) % 4] - qx[k]
        ey = qy[(k + 1) % 4] - qy[k]
        nrm = np.hypot(ex, ey)
        if nrm == 0.0:
            continue
        nx_, ny_ = -ey / nrm, ex / nrm
        qlo, qhi = np.inf, -np.inf
        for m in range(4):
            v = qx[m] * nx_ + qy[m] * ny_
            qlo = min(qlo, v)
            qhi = max(qhi, v)
        blo, bhi = np.inf, -np.inf
        for m in range(4):
            v = bx[m] * nx_ + by[m] * ny_
            blo = min(blo, v)
            bhi = max(bhi, v)
        if bhi <= qlo + eps or qhi <= blo + eps:
            return False
    return True



@numba.njit(cache=True)
def footprint_kernel(cx, cy, values, x0, y1, res, ny, nx, use_max, eps, out, nan_hit):  # pragma: no cover
    """For every source pixel (corners ``cx/cy[i:i+2, j:j+2]`` in target coordinates), update
    ``out`` (max or min) on every target cell whose footprint it overlaps; a NaN pixel marks
    ``nan_hit`` instead."""
    sy, sx = values.shape
    qx = np.empty(4)
    qy = np.empty(4)
    for i in range(sy):
        for j in range(sx):
            qx[0] = cx[i, j]
            qx[1] = cx[i, j + 1]
            qx[2] = cx[i + 1, j + 1]
            qx[3] = cx[i + 1, j]
            qy[0] = cy[i, j]
            qy[1] = cy[i, j + 1]
            qy[2] = cy[i + 1, j + 1]
            qy[3] = cy[i + 1, j]
            xmin, xmax = qx.min(), qx.max()
            ymin, ymax = qy.min(), qy.max()
            if not (np.isfinite(xmin) and np.isfinite(xmax) and np.isfinite(ymin) and np.isfinite(ymax)):
                continue
            c0 = max(int(np.floor((xmin - x0) / res)), 0)
            c1 = min(int(np.floor((xmax - x0) / res)), nx - 1)
            r0 = max(int(np.floor((y1 - ymax) / res)), 0)
            r1 = min(int(np.floor((y1 - ymin) / res)), ny - 1)
            if c1 < c0 or r1 < r0:
                continue
            v = values[i, j]
            isnan = np.isnan(v)
            for r in range(r0, r1 + 1):
                Y1 = y1 - r * res
                Y0 = Y1 - res
                for c in range(c0, c1 + 1):
                    X0 = x0 + c * res
                    if not sat_overlap(qx, qy, X0, X0 + res, Y0, Y1, eps):
                        continue
                    if isnan:
                        nan_hit[r, c] = True
                    elif use_max:
                        if v > out[r, c]:
                            out[r, c] = v
                    elif v < out[r, c]:
                        out[r, c] = v



@numba.njit(cache=True)
def box_kernel(values, sx0, sy1, spx, spy, x0, y1, res, eps, use_max, out, nan_hit):  # pragma: no cover
    """The same for a north-up source in the grid's CRS (pixel (i, j) spans
    [sx0 + j spx, sx0 + (j + 1) spx] x [sy1 - (i + 1) spy, sy1 - i spy]): the overlapping pixels of
    a cell form an index block, found by interval arithmetic."""
    sy, sx = values.shape
    ny, nx = out.shape
    for r in range(ny):
        top = y1 - r * res
        bot = top - res
        i0 = max(int(np.floor((sy1 - top + eps) / spy)), 0)
        i1 = min(int(np.ceil((sy1 - bot - eps) / spy)) - 1, sy - 1)
        for c in range(nx):
            left = x0 + c * res
            j0 = max(int(np.floor((left + eps - sx0) / spx)), 0)
            j1 = min(int(np.ceil((left + res - eps - sx0) / spx)) - 1, sx - 1)
            if i1 < i0 or j1 < j0:
                continue
            acc = -np.inf if use_max else np.inf
            hit = False
            for i in range(i0, i1 + 1):
                for j in range(j0, j1 + 1):
                    v = values[i, j]
                    if np.isnan(v):
                        hit = True
                    elif use_max:
                        if v > acc:
                            acc = v
                    elif v < acc:
                        acc = v
            out[r, c] = acc
            nan_hit[r, c] = hit



@numba.njit(cache=True)
def rim_kernel(labels, values, inside, full, rim_max, rim_min, outside, at_border):  # pragma: no cover
    """Per hole label k (labels > 0): the highest and lowest valid 8-neighbour (its rim), and
    whether it touches a pixel outside the data's extent or the window's border."""
    ny, nx = labels.shape
    for i in range(ny):
        for j in range(nx):
            k = labels[i, j]
            if k == 0:
                continue
            for di in range(-1, 2):
                for dj in range(-1, 2):
                    a, b = i + di, j + dj
                    if a < 0 or a >= ny or b < 0 or b >= nx:
                        if full:
                            outside[k] = True
                        else:
                            at_border[k] = True
                        continue
                    if not inside[a, b]:
                        outside[k] = True
                        continue
                    v = values[a, b]
                    if not np.isnan(v):
                        if v > rim_max[k]:
                            rim_max[k] = v
                        if v < rim_min[k]:
                            rim_min[k] = v



@numba.njit(cache=True)
def ring_spans_kernel(xs, ys, offsets, x0, y1, res, ny, nx, count_only, ring_out, row_out, c0_out, c1_out):  # pragma: no cover
    n_spans = 0
    cross = np.empty(max(int(np.max(offsets[1:] - offsets[:-1])), 1), np.float64)
    for p in range(offsets.size - 1):
        s, e = offsets[p], offsets[p + 1]
        n = e - s
        if n < 3:
            continue
        ymin, ymax = ys[s], ys[s]
        for k in range(s, e):
            ymin = min(ymin, ys[k])
            ymax = max(ymax, ys[k])
        r0 = max(int(np.ceil((y1 - ymax) / res - 0.5)), 0)
        r1 = min(int(np.floor((y1 - ymin) / res - 0.5)), ny - 1)
        for r in range(r0, r1 + 1):
            yc = y1 - (r + 0.5) * res
            m = 0
            for k in range(n):
                i = s + k
                j = s + (k + 1) % n
                if (ys[i] > yc) != (ys[j] > yc):
                    cross[m] = xs[i] + (yc - ys[i]) * (xs[j] - xs[i]) / (ys[j] - ys[i])
                    m += 1
            if m < 2:
                continue
            c = np.sort(cross[:m])
            for q in range(0, m - 1, 2):
                c0 = max(int(np.ceil((c[q] - x0) / res - 0.5)), 0)
                c1 = min(int(np.floor((c[q + 1] - x0) / res - 0.5)), nx - 1)
                if c1 < c0:
                    continue
                if not count_only:
                    ring_out[n_spans] = p
                    row_out[n_spans] = r
                    c0_out[n_spans] = c0
                    c1_out[n_spans] = c1
                n_spans += 1
    return n_spans
