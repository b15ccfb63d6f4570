"""GNSS occlusion by the surface model: the *visibility height* of a satellite direction.

For a satellite at infinity in direction (azimuth ``a``, elevation ``e``) and a surface model
``h`` (terrain + buildings, a raster of heights [m]), the visibility height ``V(p)`` of a point
``p`` is the lowest altitude above it from which the line of sight to the satellite is free:
above ``V`` the satellite is visible, below it is occluded.  The value stored for a cell is
the supremum-side bound ``>= V(p)`` for every point ``p`` of the cell (see "Conservative
bound").  ``V >= h`` (a receiver
inside a building sees nothing), and since ``e > 0`` every cell has a finite ``V``.

Surface model
    Every cell is a flat-topped prism: its square footprint extruded up to its height.  A ray
    is blocked by a cell when it passes over the cell's footprint below the cell's height, so
    a cell ``c`` entered by the ray at horizontal distance ``t`` imposes ``z >= h(c) - t tan e``
    and ``V(p) = max(h(p), max_c h(c) - t_c tan e)`` over the cells the ray crosses.  Outside
    the map there is no obstacle.

Algorithm (an O(N) column scan after seed 003, section II-B)
    The rays toward one satellite are parallel, so the scan follows a family of parallel
    *lines* in the satellite direction, ``LINES_PER_CELL`` per cell across the sweep.  Along one
    line the prism traversal is exact and runs as a recurrence: sweeping from the satellite
    side, keep ``G = max(h(c) - kappa * p_in(c))`` over the cells crossed so far (``p_in`` the
    sweep coordinate where the line enters cell ``c``, ``kappa`` the height drop of the ray
    per unit of sweep); at a line point ``p`` the exact requirement is ``G + kappa * p``.
    O(1) per cell and direction, all lines advance in lockstep (contiguous, vectorised
    loops over one map row per step; sweeps along x run on the map transposed once per
    call, the output is transposed back in blocks).  The sweep axis is the grid axis
    closest to the azimuth, so a line crosses at most two cells per step; any azimuth is handled (no 8-direction quantisation, no
    resampling of heights).  Seed 003 compares projected image coordinates along
    columns of a camera-like resampled grid; here the comparison is the running maximum
    ``G`` in the sheared (line, sweep) frame, which needs no resampling.

Conservative bound (the contract)
    The value stored for a cell is a bound valid for **every point of the cell**: ``>= V(p)``
    for every ``p`` in the cell's footprint (up to float32 rounding, < 0.01 m).
    Over-estimation is allowed and measured; under-estimation is a defect.  A cell centre is
    generally not on a line, and points near a cell's edges see neighbouring prisms at a
    vanishing distance, so each cell takes ``max`` of: its own height, its neighbours toward
    the satellite (own column and the next one, at full height), and, for the columns
    beyond, the running maxima of every scan line bracketing the cell's rays (``LINES_PER_CELL``
    = 2 lines per cell; proof in :func:`_scan_kernel`).  Measured against the exact prism
    caster (:mod:`skyroute.stages.raycast`) and an independent oracle (tests): zero unsafe
    values at random interior points and on shadow edges of Helsinki, Rotterdam, Monaco,
    SRTM and a towers city, el 5-60 deg; mean over-estimation 0.5-0.8 m on 2 m cities,
    7-8 m on 30 m SRTM; 99.2-99.7 % of the visible/occluded decisions at cell centres agree
    with the exact caster outside ``cell tan(e) + 0.5 m``, within 0.5 % of the best any
    per-cell bound can do (the supremum over the cell: 99.4-99.9 %; 96-97 % on 200 m
    towers, where cells beside a tower must carry its height).  Also: satellites are at
    infinity (parallel rays); the map is flat (Earth curvature ignored: an obstacle d away
    is d^2 / 2R too high, 0.08 m at 1 km, 8 m at 10 km, so long terrain shadows at low
    elevation are slightly too long); true azimuths become grid azimuths with the meridian
    convergence at the map centre (one value per map, < 0.05 deg change over a few km in a
    UTM zone).

Layers: the numba kernel :func:`_scan_kernel`, the numpy runner
:func:`visibility_heights_numpy`, the dask runner :func:`visibility_heights_dask`
(overlapped blocks of :mod:`skyroute.stages.overlap`, halo from the data:
:func:`shadow_halo_cells`), and the public
:func:`visibility_height` on ``xarray`` rasters.
"""

from __future__ import annotations

import functools
import math
from typing import Literal

import numba
import numpy as np
import xarray as xr
from pyproj import CRS, Proj

from skyroute.stages.base import CRSError, InputError
from skyroute.stages.grid import Grid

__all__ = [
    "grid_azimuth_deg",
    "occluder_window",
    "shadow_halo_cells",
    "visibility_height",
    "visibility_heights_dask",
    "visibility_heights_numpy",
]

# ----------------------------------------------------------------------------------------
# numba kernel
# ----------------------------------------------------------------------------------------

#: Scan lines per cell across the sweep (spacing ``1 / LINES_PER_CELL`` cell).  Each extra
#: line costs one more O(1) update per cell and step; the bound charges each cell's rays
#: with at most one line spacing more than their own width on either side, so denser lines
#: make it tighter.  2 is the measured optimum (benchmarks/bench_occlusion.py).
LINES_PER_CELL = 2


@numba.njit(cache=True, nogil=True)
def _step_tables(p_top, n_sweep, m, kappa, n_fam):
    """Per sweep step ``k`` (normalised sweep coordinate ``P = p_top - k``) and line family
    ``f`` (lines ``Q = a + f / n_fam + m P``, integer ``a``) the geometry shared by every line
    of the family (they are integer translates across the sweep):

    ``lo, hi[f, k]``: cross offsets of the (one or two) cells line ``a`` crosses in column
    ``P`` (cells ``a + lo``, ``a + hi``); ``kp_lo[k], kp_hi[f, k]``: ``kappa`` times the sweep
    coordinate where it enters them; ``kpl[k] = kappa (P + 1/2)`` (the plane between column
    ``P`` and ``P + 1``); ``d_lo, n_w[f, k]``: the lines of family ``f`` bracketing the rays of
    the cell ``Q0`` of column ``P`` on that plane are ``a = Q0 + d_lo .. Q0 + d_lo + n_w - 1``
    (see :func:`_scan_kernel`).
    """
    lo = np.empty((n_fam, n_sweep), np.int64)
    hi = np.empty((n_fam, n_sweep), np.int64)
    kp_lo = np.empty(n_sweep, np.float64)
    kp_hi = np.empty((n_fam, n_sweep), np.float64)
    kpl = np.empty(n_sweep, np.float64)
    d_lo = np.empty((n_fam, n_sweep), np.int64)
    n_w = np.zeros((n_fam, n_sweep), np.int64)
    for k in range(n_sweep):
        P = float(p_top - k)
        kp_lo[k] = kappa * (P - 0.5)
        kpl[k] = kappa * (P + 0.5)
        y = m * (P + 1.5)   # line (f, a) crosses the plane P + 3/2 at Q = a + f / n_fam + y
        du_lo = math.floor(n_fam * (-0.5 + m - y))
        du_hi = math.ceil(n_fam * (0.5 + 2.0 * m - y))
        for f in range(n_fam):
            beta = f / n_fam
            lo[f, k] = math.floor(beta + m * (P - 0.5) + 0.5)
            hi[f, k] = math.floor(beta + m * (P + 0.5) + 0.5)
            if hi[f, k] > lo[f, k]:
                # the line enters the upper cell where it crosses Q = hi - 1/2
                kp_hi[f, k] = kappa * ((hi[f, k] - 0.5 - beta) / m)
            else:
                kp_hi[f, k] = kp_lo[k]
            if m == 0.0:
                # rays of the cell's interior stay in its own row: its line is exact for them
                d_lo[f, k] = 0
                n_w[f, k] = 1 if f == 0 else 0
            else:
                # lines u = n_fam a + f in [du_lo, du_hi] (relative to n_fam Q0)
                d_lo[f, k] = -((f - du_lo) // n_fam)          # ceil((du_lo - f) / n_fam)
                n_w[f, k] = (du_hi - f) // n_fam - d_lo[f, k] + 1
    return lo, hi, kp_lo, kp_hi, kpl, d_lo, n_w


@numba.njit(cache=True, nogil=True)
def _fold_column(G, rlo, rhi, n, two, klo, khi):
    """Fold one column into the running maxima ``G`` of ``n`` lines: the cell each line
    enters at the column's near face (``rlo``, at ``klo``) and, if ``two``, the upper cell it
    enters through its side (``rhi``, at ``khi``)."""
    if two:
        for j in range(n):
            G[j] = max(G[j], max(rlo[j] - klo, rhi[j] - khi))
    else:
        for j in range(n):
            G[j] = max(G[j], rlo[j] - klo)


@numba.njit(cache=True, nogil=True)
def _window_max(acc, G, base, nw, nc, first):
    """``acc[c] (max)= max(G[base + c .. base + c + nw - 1])`` for ``nc`` cells (``nw`` <= 4;
    nothing if 0); ``first``: overwrite ``acc``.  One branch-free loop per case (SIMD)."""
    if nw <= 0:
        return
    g0 = G[base:base + nc]
    if first:
        if nw == 1:
            for c in range(nc):
                acc[c] = g0[c]
        elif nw == 2:
            g1 = G[base + 1:base + 1 + nc]
            for c in range(nc):
                acc[c] = max(g0[c], g1[c])
        elif nw == 3:
            g1 = G[base + 1:base + 1 + nc]
            g2 = G[base + 2:base + 2 + nc]
            for c in range(nc):
                acc[c] = max(max(g0[c], g1[c]), g2[c])
        else:
            g1 = G[base + 1:base + 1 + nc]
            g2 = G[base + 2:base + 2 + nc]
            g3 = G[base + 3:base + 3 + nc]
            for c in range(nc):
                acc[c] = max(max(g0[c], g1[c]), max(g2[c], g3[c]))
    else:
        if nw == 1:
            for c in range(nc):
                acc[c] = max(acc[c], g0[c])
        elif nw == 2:
            g1 = G[base + 1:base + 1 + nc]
            for c in range(nc):
                acc[c] = max(acc[c], max(g0[c], g1[c]))
        elif nw == 3:
            g1 = G[base + 1:base + 1 + nc]
            g2 = G[base + 2:base + 2 + nc]
            for c in range(nc):
                acc[c] = max(acc[c], max(max(g0[c], g1[c]), g2[c]))
        else:
            g1 = G[base + 1:base + 1 + nc]
            g2 = G[base + 2:base + 2 + nc]
            g3 = G[base + 3:base + 3 + nc]
            for c in range(nc):
                acc[c] = max(acc[c], max(max(g0[c], g1[c]), max(g2[c], g3[c])))


@numba.njit(cache=True, nogil=True)
def _bound_row_fused(orow, rc, rn, ra, rb, rd, d2, acc, G, base, nw, kpl, nc, rev):
    """:func:`_bound_row` with the window of the last family (``nw`` 1..3 lines of ``G`` from
    ``base``) folded in on the fly."""
    g0 = G[base:base + nc]
    g1 = G[base + 1:base + 1 + nc] if nw > 1 else g0
    g2 = G[base + 2:base + 2 + nc] if nw > 2 else g0
    for c in range(nc):
        a = max(acc[c], max(max(g0[c], g1[c]), g2[c]))
        v = max(max(max(rc[c], rn[c]), max(ra[c], rb[c])), max(rd[c] - d2, kpl + a))
        if rev:
            orow[nc - 1 - c] = v
        else:
            orow[c] = v


@numba.njit(cache=True, nogil=True)
def _bound_row_two(orow, rc, rn, ra, rb, rd, d2, G0, b0, n0, G1, b1, n1, kpl, nc, rev):
    """:func:`_bound_row` for two line families, their windows (``n0``, ``n1`` of 1..3 lines
    of ``G0`` / ``G1`` from ``b0`` / ``b1``) read on the fly: one branch-free pass (a window
    narrower than 3 re-reads its first line)."""
    p0 = G0[b0:b0 + nc]
    p1 = G0[b0 + 1:b0 + 1 + nc] if n0 > 1 else p0
    p2 = G0[b0 + 2:b0 + 2 + nc] if n0 > 2 else p0
    q0 = G1[b1:b1 + nc]
    q1 = G1[b1 + 1:b1 + 1 + nc] if n1 > 1 else q0
    q2 = G1[b1 + 2:b1 + 2 + nc] if n1 > 2 else q0
    if rev:
        for c in range(nc):
            a = max(max(max(p0[c], p1[c]), p2[c]), max(max(q0[c], q1[c]), q2[c]))
            orow[nc - 1 - c] = max(max(max(rc[c], rn[c]), max(ra[c], rb[c])),
                                   max(rd[c] - d2, kpl + a))
    else:
        for c in range(nc):
            a = max(max(max(p0[c], p1[c]), p2[c]), max(max(q0[c], q1[c]), q2[c]))
            orow[c] = max(max(max(rc[c], rn[c]), max(ra[c], rb[c])), max(rd[c] - d2, kpl + a))


@numba.njit(cache=True, nogil=True)
def _bound_row(orow, rc, rn, ra, rb, rd, d2, acc, kpl, nc, rev):
    """``orow[c] = max(rc, rn, ra, rb, rd - d2, kpl + acc)`` for the ``nc`` cells of one
    column (written reversed if ``rev``): the own cell, its upper neighbour, the cells
    ``Q0``, ``Q0 + 1``, ``Q0 + 2`` of the next column and the lines."""
    if rev:
        for c in range(nc):
            orow[nc - 1 - c] = max(max(max(rc[c], rn[c]), max(ra[c], rb[c])),
                                   max(rd[c] - d2, kpl + acc[c]))
    else:
        for c in range(nc):
            orow[c] = max(max(max(rc[c], rn[c]), max(ra[c], rb[c])),
                          max(rd[c] - d2, kpl + acc[c]))


_STRIP = 32  # sweep steps per block of the transposed output


@numba.njit(cache=True, nogil=True)
def _scan_kernel(h, out, sa, sb, sweep0, cross0, m, kappa, n_fam, out_t):
    """Conservative visibility heights [m] of one direction over ``h`` (n_sweep, n_cross),
    sweeping along axis 0, written into ``out`` (same shape, or transposed if ``out_t``).

    Normalised global coordinates: ``P = sa * (sweep0 + i_sweep)``, ``Q = sb * (cross0 +
    i_cross)`` with ``i_sweep`` / ``i_cross`` the local indices along axis 0 / 1; cell
    ``(P, Q)`` covers ``[P - 1/2, P + 1/2] x [Q - 1/2, Q + 1/2]``.  The satellite lies toward
    ``+P``, rays rise ``m`` (0..1) in ``Q`` per unit of ``P`` and the ray height drops
    ``kappa`` [m] per unit of ``P`` away from the satellite.

    Scan lines ``Q = s + m P``, ``s`` on a lattice of spacing ``1 / n_fam`` (``n_fam``
    families of integer translates), advance in lockstep from the satellite side.
    ``G[s] = max(h(c) - kappa * p_in(s, c))`` over the cells ``c`` line ``s`` crossed in the
    columns already swept (``p_in`` its entry coordinate).  At column ``P``, *before* folding
    it in, ``G`` covers exactly the columns ``> P``, and the cell ``(P, Q0)`` gets

        ``U = max(h(P, Q0), h(P, Q0 + 1), h(P + 1, Q0), h(P + 1, Q0 + 1),
                  h(P + 1, Q0 + 2) - kappa (1 - m) / m,  kappa (P + 1/2) + max_s G'[s])``

    (the ``Q0 + 1`` terms only if ``m > 0``, the ``Q0 + 2`` term only if ``m > 1/2``), ``G'``
    the running maxima over the columns ``>= P + 2`` (the fold lags one column), over the
    lines ``s`` bracketing the cell's rays on the plane ``P + 3/2``: the last line at or below
    ``Q0 - 1/2 + m``, every line inside, the first at or above ``Q0 + 1/2 + 2 m``.

    Proof that ``U >= V(p, q)`` for every point ``(p, q)`` of the cell (``V`` the exact prism
    value, cells closed, touching counts).  The ray of the point, ``Q = q + m (P' - p)``,
    meets (i) the own cell; (ii) in column ``P`` at most the upper neighbour ``(P, Q0 + 1)``
    (it rises <= ``m`` <= 1 before leaving the column; none if ``m = 0``), entered at
    ``P' >= p``, so requiring at most that cell's height; (iii) in column ``P + 1``, which it
    enters at ``Q_e = q + m (P + 1/2 - p)`` in ``I = [Q0 - 1/2, Q0 + 1/2 + m]`` and leaves
    below ``Q_e + m``: the rows ``Q0`` and ``Q0 + 1`` (``Q0 + 1`` only if ``m > 0``), entered at
    ``>= P + 1/2 >= p``, and, only if ``m > 1/2``, row ``Q0 + 2``, whose lower side
    ``Q0 + 3/2`` it crosses at ``>= P + 1/2 + (1 - m) / m``; (iv) cells of the columns
    ``>= P + 2``, entered at ``p_in >= P + 3/2 >= p``, requiring ``h(c) - kappa (p_in - p) <=
    h(c) - kappa (p_in - P - 1/2)``.  On the plane ``P + 3/2`` the ray is at ``Q_e + m`` in
    ``I + m``, so it runs in the band between two consecutive chosen lines ``s1 < s2``
    (spacing ``d <= 1``): ``s1 <= s <= s2``.  In any column ``P'`` a
    cell ``c`` the ray meets is met by line ``s2`` no later, or by line ``s1`` through its
    near face ``P' - 1/2`` (the earliest possible entry): the ray enters ``c`` at
    ``max(P' - 1/2, (Qc - 1/2 - s) / m)``, non-increasing in ``s``, so if ``s2`` meets ``c`` it
    enters no later; if ``s2`` passes above ``c`` (``s2 + m (P' - 1/2) > Qc + 1/2``) then
    ``s1 + m (P' - 1/2) > Qc - 1/2 + (1 - d) >= Qc - 1/2`` and ``s1`` (which then enters ``c``
    through its near face, since ``s <= s2``... meets ``c`` and ``s1 <= s``) enters at
    ``P' - 1/2``; ``s2`` cannot pass below a cell ``s`` meets (``s <= s2``, same slope).  So the
    ray's requirement in (iv) is at most ``kappa (P + 1/2) + max(G'[s1], G'[s2])`` and
    (i)-(iv) give ``V <= U``.  With ``m = 0`` (axis directions) the rays of the cell's
    interior stay in its row and the cell's own line alone is exact.  Over-estimation: the
    neighbours toward the satellite (own column and next) are charged at full height
    (required: points near the cell's edges see them at a vanishing distance); beyond, the
    bands charge the cell with at most one line spacing more than ``I + m`` on each side.
    Taking column ``P + 1`` out of the lines matters: on the plane ``P + 1/2`` the lowest
    ray of the cell runs exactly on the row boundary ``Q0 - 1/2``, so the line below it would
    charge the whole row ``Q0 - 1`` (a wall along the sweep) to a cell the rays leave.

    One row of ``h`` per step, a few contiguous (SIMD) loops over lines and cells.
    ``out_t``: write ``out`` transposed (``out[i_cross, i_sweep]``) through a strip buffer of
    ``_STRIP`` steps (blocked transposition).
    """
    ns, nc = h.shape
    neg_inf = -np.inf
    p_top = sweep0 + ns - 1 if sa > 0 else -sweep0
    q_min = cross0 if sb > 0 else -(cross0 + nc - 1)
    q_max = q_min + nc - 1
    ls_of = np.empty(ns, np.int64)
    for k in range(ns):
        ls_of[k] = sa * (p_top - k) - sweep0
    pad = 4
    lo, hi, kp_lo, kp_hi, kpl, d_lo, n_w = _step_tables(p_top, ns, m, kappa, n_fam)
    a_min = min(q_min - hi.max(), q_min + d_lo.min()) - 2
    a_max = max(q_max - lo.min(), q_max + (d_lo + n_w).max()) + 2
    n_lines = a_max - a_min + 1
    G = np.full((n_fam, n_lines), neg_inf)
    rows = np.full((2, nc + 2 * pad), neg_inf)   # this column and the previous (P + 1)
    acc = np.empty(nc)
    strip = np.empty((_STRIP, nc), np.float32)
    lateral = m > 0.0
    d2 = kappa * (1.0 - m) / m if m > 0.5 else np.inf
    for k in range(ns):
        ls = ls_of[k]
        hrow = h[ls]
        row = rows[k % 2]
        prev = rows[(k + 1) % 2]
        rc = row[pad:pad + nc]
        if sb > 0:
            for c in range(nc):
                rc[c] = hrow[c]
        else:
            for c in range(nc):
                rc[c] = hrow[nc - 1 - c]
        # 1. the cells of this column: neighbours, column P + 1 (prev), and the lines,
        #    which hold the columns >= P + 2
        orow = strip[k % _STRIP] if out_t else out[ls]
        ra = prev[pad:pad + nc]
        fl = n_fam - 1
        if n_fam == 2 and 1 <= n_w[0, k] <= 3 and 1 <= n_w[1, k] <= 3:
            b0 = q_min + d_lo[0, k] - a_min
            b1 = q_min + d_lo[1, k] - a_min
            if lateral:
                _bound_row_two(orow, rc, row[pad + 1:pad + 1 + nc], ra,
                               prev[pad + 1:pad + 1 + nc], prev[pad + 2:pad + 2 + nc], d2,
                               G[0], b0, n_w[0, k], G[1], b1, n_w[1, k], kpl[k], nc, sb < 0)
            else:
                _bound_row_two(orow, rc, rc, ra, ra, ra, d2, G[0], b0, n_w[0, k], G[1], b1,
                               n_w[1, k], kpl[k], nc, sb < 0)
        elif n_w[fl, k] < 1 or n_w[fl, k] > 3 or n_fam == 1:
            for f in range(n_fam):
                _window_max(acc, G[f], q_min + d_lo[f, k] - a_min, n_w[f, k], nc, f == 0)
            if lateral:
                _bound_row(orow, rc, row[pad + 1:pad + 1 + nc], ra, prev[pad + 1:pad + 1 + nc],
                           prev[pad + 2:pad + 2 + nc], d2, acc, kpl[k], nc, sb < 0)
            else:
                _bound_row(orow, rc, rc, ra, ra, ra, d2, acc, kpl[k], nc, sb < 0)
        else:
            for f in range(fl):
                _window_max(acc, G[f], q_min + d_lo[f, k] - a_min, n_w[f, k], nc, f == 0)
            bl = q_min + d_lo[fl, k] - a_min
            if lateral:
                _bound_row_fused(orow, rc, row[pad + 1:pad + 1 + nc], ra,
                                 prev[pad + 1:pad + 1 + nc], prev[pad + 2:pad + 2 + nc], d2,
                                 acc, G[fl], bl, n_w[fl, k], kpl[k], nc, sb < 0)
            else:
                _bound_row_fused(orow, rc, rc, ra, ra, ra, d2, acc, G[fl], bl, n_w[fl, k],
                                 kpl[k], nc, sb < 0)
        # 2. fold column P + 1 into the lines over the map (others meet -inf)
        if k > 0:
            kk = k - 1
            for f in range(n_fam):
                lk = lo[f, kk]
                hk = hi[f, kk]
                ia0 = max(q_min - hk - a_min - 1, 0)
                ia1 = min(q_max - lk - a_min + 2, n_lines)
                blo = a_min + lk - q_min + pad
                bhi = a_min + hk - q_min + pad
                _fold_column(G[f, ia0:ia1], prev[ia0 + blo:ia1 + blo],
                             prev[ia0 + bhi:ia1 + bhi], ia1 - ia0, hk > lk, kp_lo[kk],
                             kp_hi[f, kk])
        if out_t and (k % _STRIP == _STRIP - 1 or k == ns - 1):
            kb = k - k % _STRIP
            nt = k - kb + 1
            l0 = min(ls_of[kb], ls_of[k])      # sweep steps kb..k are contiguous in out
            for c in range(nc):
                seg = out[c, l0:l0 + nt]
                for t in range(nt):
                    seg[ls_of[kb + t] - l0] = strip[t, c]


# ----------------------------------------------------------------------------------------
# numpy runner
# ----------------------------------------------------------------------------------------

def _direction_geometry(az_grid_deg: float, el_deg: float, cell_m: float):
    """(sweep_axis, sa, sb, m, kappa) of a grid azimuth / elevation (see :func:`_scan_kernel`):
    the sweep runs along the array axis closest to the azimuth (0: y, 1: x)."""
    az = math.radians(az_grid_deg)
    dcol = math.sin(az)          # toward the satellite: +col is grid east
    drow = -math.cos(az)         # +row is grid south
    if abs(dcol) >= abs(drow):
        sweep_axis, d_sweep, d_cross = 1, dcol, drow
    else:
        sweep_axis, d_sweep, d_cross = 0, drow, dcol
    sa = 1 if d_sweep > 0 else -1
    sb = 1 if d_cross >= 0 else -1
    m = min(abs(d_cross) / abs(d_sweep), 1.0)
    if m < 1e-12:  # axis directions: sin/cos round-off would leak 1e-14 m across rows
        m = 0.0
    kappa = cell_m * math.tan(math.radians(el_deg)) * math.sqrt(1.0 + m * m)
    return sweep_axis, sa, sb, m, kappa


def occluder_window(rows, cols, z_min_m: float, h_max_m: float, az_grid_deg: float, el_deg: float,
                    cell_m: float, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """Bounds of the cells that can decide whether points of ``(rows, cols)`` see a satellite.

    The window ``(r0, r1, c0, c1)`` (rows ``r0:r1``, columns ``c0:c1`` of a map of ``shape``)
    holds the cells that can decide whether points at altitudes >= ``z_min_m`` [m] in the cells
    ``(rows, cols)`` see the satellite when every height of the map is <= ``h_max_m`` [m].
    Every other cell requires less than ``z_min_m - kappa`` of these cells (``kappa`` the drop
    of the ray over one cell, > 0) in :func:`visibility_heights_numpy`'s bound (:func:`_scan_kernel`:
    a cell ``d`` columns toward the satellite requires at most ``h - kappa (d - 1)``, and the
    terms of a cell only involve its own column and the next one within 3 rows, and beyond,
    the lines that bracket its rays, which stay within 2 rows below them and
    ``2 + m (d + 1)`` rows above them).  So the visibility heights of ``(rows, cols)``
    computed on this window (with its ``origin``) are those of any larger window wherever
    either is >= ``z_min_m`` -- the same visible / occluded decisions for those points.

    Parameters
    ----------
    rows, cols : array_like of int
        Cells of interest (row, column indices in the map).
    z_min_m : float
        Lowest altitude of interest [m]; not finite: the whole map.
    h_max_m : float
        Upper bound of every height of the map [m]; not finite: the whole map.
    az_grid_deg : float
        Satellite azimuth [deg] clockwise from grid north.
    el_deg : float
        Satellite elevation [deg], in (0, 90].
    cell_m : float
        Cell size [m].
    shape : tuple of int
        Map shape ``(ny, nx)``.

    Returns
    -------
    r0, r1, c0, c1 : int
        Window bounds (half-open), clipped to the map; ``(0, 0, 0, 0)`` for no cells.
    """
    rows = np.asarray(rows)
    cols = np.asarray(cols)
    ny, nx = int(shape[0]), int(shape[1])
    if rows.size == 0:
        return 0, 0, 0, 0
    if not (math.isfinite(z_min_m) and math.isfinite(h_max_m)):
        return 0, ny, 0, nx
    sweep_axis, sa, sb, m, _ = _direction_geometry(az_grid_deg, el_deg, cell_m)
    kappa = cell_m * math.tan(math.radians(min(el_deg, 89.999)))   # <= the kernel's kappa
    reach = int(math.ceil(max(h_max_m - z_min_m, 0.0) / kappa)) + 3       # columns toward the satellite
    across = int(math.ceil(m * reach)) + 5                                 # rows the rays rise meanwhile
    ext_sweep = (3, reach) if sa > 0 else (reach, 3)                       # (low index side, high side)
    ext_cross = (5, across) if sb > 0 else (across, 5)
    ext_r, ext_c = (ext_sweep, ext_cross) if sweep_axis == 0 else (ext_cross, ext_sweep)
    r0 = max(int(rows.min()) - ext_r[0], 0)
    r1 = min(int(rows.max()) + ext_r[1] + 1, ny)
    c0 = max(int(cols.min()) - ext_c[0], 0)
    c1 = min(int(cols.max()) + ext_c[1] + 1, nx)
    return r0, max(r1, r0), c0, max(c1, c0)


def visibility_heights_numpy(surface_2d: np.ndarray, az_grid_deg, el_deg, cell_m: float, *,
                             origin: tuple[int, int] = (0, 0),
                             lines_per_cell: int = LINES_PER_CELL) -> np.ndarray:
    """Conservative visibility heights [m] of ``n`` directions over a NaN-free 2-D surface [m].

    Each cell's value is >= the exact prism value at every point of the cell.  Outside the array
    there is no obstacle.  Inputs are not validated beyond shapes: call :func:`visibility_height`
    for checked use.

    Parameters
    ----------
    surface_2d : numpy.ndarray
        ``(ny, nx)`` heights [m], row 0 = north edge, columns west to east (a north-up grid).
    az_grid_deg : float or array_like
        Azimuths [deg] clockwise from **grid** north, scalar or ``(n,)``.
    el_deg : float or array_like
        Elevations [deg], each in (0, 90], same shape as ``az_grid_deg``.
    cell_m : float
        Cell size [m].
    origin : tuple of int, default (0, 0)
        (row, col) of ``surface_2d[0, 0]`` in a larger map, so that blocks of one map (dask) get
        bit-identical results to the whole map.
    lines_per_cell : int, default :data:`LINES_PER_CELL`
        1..8: scan lines per cell across the sweep; every value is conservative, more lines are
        tighter (less over-estimation at lateral shadow edges) and slower.

    Returns
    -------
    numpy.ndarray
        float32 ``(n, ny, nx)`` visibility heights [m].

    Raises
    ------
    InputError
        When ``surface_2d`` is not 2-D, ``az_grid_deg`` and ``el_deg`` are not scalars or 1-D of
        equal length, or ``lines_per_cell`` is not an integer 1..8.

    References
    ----------
    Seed 003, section II-B (the column scan this O(N) algorithm follows; see the module docstring).
    """
    h = np.ascontiguousarray(surface_2d, dtype=np.float32)
    if h.ndim != 2:
        raise InputError(f"surface must be 2-D (y, x), got shape {h.shape}")
    az = np.atleast_1d(np.asarray(az_grid_deg, dtype=np.float64))
    el = np.atleast_1d(np.asarray(el_deg, dtype=np.float64))
    if az.shape != el.shape or az.ndim != 1:
        raise InputError(f"az and el must be scalars or 1-D of equal length, got {az.shape} and {el.shape}")
    out = np.empty((az.size,) + h.shape, dtype=np.float32)
    if not (isinstance(lines_per_cell, int | np.integer) and 1 <= lines_per_cell <= 8):
        raise InputError(f"lines_per_cell must be an integer 1..8, got {lines_per_cell!r}")
    n_fam = int(lines_per_cell)
    if h.size == 0:
        return out
    flat = bool(h.max() == h.min())
    row0, col0 = int(origin[0]), int(origin[1])
    h_t = None     # the map transposed, for sweeps along x (made once per call)
    for i in range(az.size):
        # zenith (vertical rays) or no relief: nothing but the own cell blocks
        if not (el[i] < 90.0) or flat:
            out[i] = h
            continue
        sweep_axis, sa, sb, m, kappa = _direction_geometry(az[i], el[i], cell_m)
        if sweep_axis == 0:
            _scan_kernel(h, out[i], sa, sb, row0, col0, m, kappa, n_fam, False)
        else:
            if h_t is None:
                h_t = np.ascontiguousarray(h.T)
            _scan_kernel(h_t, out[i], sa, sb, col0, row0, m, kappa, n_fam, True)
    return out


def shadow_halo_cells(surface_2d_or_da, min_el_deg: float, cell_m: float) -> int:
    """Cells [-] a shadow can reach at most: ``(max h - min h) / tan(min elevation)`` in cells, plus 4.

    The 4 cells of margin cover the next column and the bracketing lines up to ~2.5 cells aside.
    Only cells within this distance can change a visibility height; the dask runner uses it as
    overlap depth.

    Parameters
    ----------
    surface_2d_or_da : numpy.ndarray, dask array or xarray.DataArray
        ``(ny, nx)`` heights [m]; NaN ignored.
    min_el_deg : float
        Lowest satellite elevation [deg], in (0, 90].
    cell_m : float
        Cell size [m], positive.

    Returns
    -------
    int
        Halo width [cells].

    Raises
    ------
    InputError
        When ``min_el_deg`` is outside (0, 90] or ``cell_m`` is not positive.
    """
    if not 0.0 < float(min_el_deg) <= 90.0:
        raise InputError(f"min elevation {min_el_deg} deg must be in (0, 90]")
    if not cell_m > 0:
        raise InputError(f"cell size {cell_m} m must be positive")
    data = surface_2d_or_da.data if isinstance(surface_2d_or_da, xr.DataArray) else surface_2d_or_da
    hmax, hmin = _nan_extrema(data)
    return _halo_from_relief(hmax - hmin, min_el_deg, cell_m)


def _nan_extrema(data) -> tuple[float, float]:
    if _is_dask(data):
        import dask
        import dask.array as dsa
        hmax, hmin = dask.compute(dsa.nanmax(data), dsa.nanmin(data))
    else:
        arr = np.asarray(data)
        hmax, hmin = np.nanmax(arr), np.nanmin(arr)
    return float(hmax), float(hmin)


def _halo_from_relief(relief_m: float, min_el_deg: float, cell_m: float) -> int:
    if min_el_deg >= 90.0:
        return 4
    return int(math.ceil(relief_m / math.tan(math.radians(min_el_deg)) / cell_m)) + 4


# ----------------------------------------------------------------------------------------
# dask runner
# ----------------------------------------------------------------------------------------

def _is_dask(data) -> bool:
    return type(data).__module__.startswith("dask")


def visibility_heights_dask(surface, az_grid_deg, el_deg, cell_m: float, *,
                            fill_nan: Literal["nearest"] | None = None):
    """Dask version of :func:`visibility_heights_numpy`: ``(n, ny, nx)`` float32 dask array.

    Each block is computed with an overlap of :func:`shadow_halo_cells` cells (from the data's
    max/min and the lowest elevation; computed eagerly) on every side, so results are
    bit-identical to the unchunked runner.  Boundary: outside the map there is no obstacle
    (``boundary="none"``: edge blocks get no padding).  Chunks smaller than the halo are merged
    (rechunk) first (runner: :func:`skyroute.stages.overlap.overlap_map`).

    Parameters
    ----------
    surface : dask.array.Array or numpy.ndarray
        ``(ny, nx)`` heights [m] (a numpy array is wrapped in one dask chunk).
    az_grid_deg : float or array_like
        Azimuths [deg] clockwise from grid north, scalar or ``(n,)``.
    el_deg : float or array_like
        Elevations [deg] in (0, 90], same shape as ``az_grid_deg``.
    cell_m : float
        Cell size [m].
    fill_nan : {"nearest", None}, optional
        ``"nearest"`` fills NaN holes per overlapped block.

    Returns
    -------
    dask.array.Array
        float32 ``(n, ny, nx)`` visibility heights [m], lazy.
    """
    import dask.array as dsa

    from skyroute.stages.overlap import overlap_map

    arr = surface if _is_dask(surface) else dsa.from_array(np.asarray(surface))
    az = np.atleast_1d(np.asarray(az_grid_deg, dtype=np.float64))
    el = np.atleast_1d(np.asarray(el_deg, dtype=np.float64))
    hmax, hmin = _nan_extrema(arr)
    halo = _halo_from_relief(hmax - hmin, float(el.min()), cell_m)

    def block(h: np.ndarray, origin: tuple[int, int], core: tuple[slice, slice]) -> np.ndarray:
        if fill_nan == "nearest":
            h = _fill_nearest(h)
        return visibility_heights_numpy(h, az, el, cell_m, origin=origin)[(slice(None),) + core]

    return overlap_map(arr, halo, block, ((az.size,),), np.float32)


def _fill_nearest(h: np.ndarray) -> np.ndarray:
    from scipy import ndimage

    nan = np.isnan(h)
    if not nan.any():
        return h
    if nan.all():
        raise InputError("surface block is entirely NaN: nothing to fill from; crop the map or fill it")
    idx = ndimage.distance_transform_edt(nan, return_distances=False, return_indices=True)
    return h[tuple(idx)]


# ----------------------------------------------------------------------------------------
# public API
# ----------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=64)
def _meridian_convergence_deg(grid: Grid) -> float:
    """PROJ meridian convergence [deg] at the centre of ``grid`` (a projected CRS; memoised:
    one value per map, asked once per sky epoch)."""
    crs = CRS.from_user_input(grid.crs_wkt)
    if not crs.is_projected:
        raise CRSError(f"grid CRS {crs.name!r} is not projected: reproject the surface to a "
                       "projected CRS in metres (e.g. its UTM zone)")
    xmin, ymin, xmax, ymax = grid.bounds
    lon, lat = grid.to_lonlat(0.5 * (xmin + xmax), 0.5 * (ymin + ymax))
    return float(Proj(crs).get_factors(lon, lat).meridian_convergence)


def grid_azimuth_deg(true_az_deg, grid: Grid | xr.DataArray):
    """Grid azimuth [deg, 0..360) of true (ENU) azimuths [deg] on a projected grid.

    ``grid_az = true_az - gamma`` with ``gamma`` the PROJ meridian convergence [deg] at the map
    centre (positive east of a UTM central meridian in the northern hemisphere, where true north
    points west of grid north).  One value per map: over a few km in a UTM zone ``gamma`` varies
    by < 0.05 deg.

    Parameters
    ----------
    true_az_deg : float or array_like
        Azimuths [deg] clockwise from true north.
    grid : Grid or xarray.DataArray
        The grid (or a raster of it) in a projected CRS.

    Returns
    -------
    float or numpy.ndarray
        Grid azimuths [deg] in [0, 360); a float for a scalar input.

    Raises
    ------
    CRSError
        When the grid's CRS is not projected.
    """
    if isinstance(grid, xr.DataArray):
        grid = Grid.from_dataarray(grid)
    gamma = _meridian_convergence_deg(grid)
    out = np.mod(np.asarray(true_az_deg, dtype=np.float64) - gamma, 360.0)
    return float(out) if out.ndim == 0 else out


def visibility_height(surface: xr.DataArray, az_deg, el_deg, *,
                      azimuth: Literal["true", "grid"] = "true",
                      fill_nan: Literal["nearest"] | None = None) -> xr.DataArray:
    """Visibility height [m] of satellite direction(s) over a surface model.

    Each value is a bound valid for every point of its cell: at and above it the satellite is in
    line of sight from anywhere in the cell.

    Parameters
    ----------
    surface : xarray.DataArray
        Raster ``(y, x)`` of terrain + building heights [m] on a north-up projected grid (see
        :mod:`skyroute.stages.grid`), numpy- or dask-backed (dask: blocks with a halo from
        :func:`shadow_halo_cells`, identical results).
    az_deg : float or array_like
        Satellite azimuth(s) [deg], clockwise from true north (``azimuth="true"``, converted with
        :func:`grid_azimuth_deg`) or from grid north (``"grid"``); finite.
    el_deg : float or array_like
        Elevation(s) [deg] in (0, 90], same shape as ``az_deg``.
    azimuth : {"true", "grid"}, default "true"
        Reference of ``az_deg``.
    fill_nan : {None, "nearest"}, optional
        ``None`` refuses NaN cells, ``"nearest"`` fills them with the nearest valid height first
        (dask: within each block and its halo).

    Returns
    -------
    xarray.DataArray
        float32 heights [m] in the surface's vertical datum, named ``visibility_height``:
        ``(y, x)`` for scalars, ``(direction, y, x)`` for 1-D arrays of length n; coordinates
        ``azimuth_deg``, ``grid_azimuth_deg``, ``elevation_deg``; the surface's CRS.

    Raises
    ------
    InputError
        When ``surface`` is not a numeric ``(y, x)`` DataArray on a north-up grid of square
        cells, ``azimuth`` or ``fill_nan`` is not one of its values, the directions are not
        finite scalars or equal-length 1-D arrays, an elevation is outside (0, 90], or the
        surface has NaN cells (``fill_nan=None``) or is entirely NaN.
    CRSError
        When the surface carries no CRS, or (``azimuth="true"``) its CRS is not projected.

    References
    ----------
    Seed 003, section II-B (the column scan this O(N) algorithm follows; see the module docstring).
    """
    if not isinstance(surface, xr.DataArray):
        raise InputError(f"surface must be an xarray.DataArray (y, x), got {type(surface).__name__}")
    if surface.dims != ("y", "x"):
        raise InputError(f"surface must have dims ('y', 'x'), got {surface.dims}: select one 2-D slice")
    if azimuth not in ("true", "grid"):
        raise InputError(f"azimuth must be 'true' or 'grid', got {azimuth!r}")
    if fill_nan not in (None, "nearest"):
        raise InputError(f"fill_nan must be None or 'nearest', got {fill_nan!r}")
    grid = Grid.from_dataarray(surface)
    scalar = np.ndim(az_deg) == 0 and np.ndim(el_deg) == 0
    az = np.atleast_1d(np.asarray(az_deg, dtype=np.float64))
    el = np.atleast_1d(np.asarray(el_deg, dtype=np.float64))
    if az.ndim != 1 or az.shape != el.shape:
        raise InputError(f"az_deg and el_deg must be scalars or 1-D arrays of equal length, "
                         f"got shapes {np.shape(az_deg)} and {np.shape(el_deg)}")
    if not (np.all(np.isfinite(az)) and np.all(np.isfinite(el))):
        raise InputError("az_deg and el_deg must be finite")
    bad = (el <= 0.0) | (el > 90.0)
    if bad.any():
        raise InputError(f"elevation(s) {el[bad].tolist()} deg out of (0, 90]: a satellite at or "
                         "below the horizon is never in line of sight; drop it before calling")
    if not np.issubdtype(surface.dtype, np.number):
        raise InputError(f"surface must hold numbers, got dtype {surface.dtype}")
    az_grid = grid_azimuth_deg(az, grid) if azimuth == "true" else np.mod(az, 360.0)
    az_grid = np.atleast_1d(az_grid)
    data = surface.data
    if _is_dask(data):
        import dask.array as dsa
        n_nan = int(dsa.isnan(data).sum().compute())
    else:
        n_nan = int(np.isnan(np.asarray(data, dtype=np.float64)).sum())
    if n_nan and fill_nan is None:
        raise InputError(f"surface has {n_nan} NaN cell(s) (holes): fill them first (e.g. "
                         "rioxarray's interpolate_na) or pass fill_nan='nearest'")
    if n_nan == surface.size:
        raise InputError("surface is entirely NaN: nothing to compute")
    if _is_dask(data):
        values = visibility_heights_dask(data.astype(np.float32), az_grid, el, grid.resolution_m,
                                         fill_nan=fill_nan)
    else:
        h = np.asarray(data, dtype=np.float32)
        if n_nan:
            h = _fill_nearest(h)
        values = visibility_heights_numpy(h, az_grid, el, grid.resolution_m)
    attrs = {
        "units": "m",
        "long_name": "visibility height: lowest altitude with line of sight to the satellite",
        "azimuth_reference": azimuth,
    }
    if "vertical_datum" in surface.attrs:
        attrs["vertical_datum"] = surface.attrs["vertical_datum"]
    coords = {"y": surface["y"], "x": surface["x"]}
    if scalar:
        da = xr.DataArray(values[0], dims=("y", "x"), coords=coords, name="visibility_height",
                          attrs=attrs)
        da = da.assign_coords(azimuth_deg=float(az[0]), grid_azimuth_deg=float(az_grid[0]),
                              elevation_deg=float(el[0]))
    else:
        da = xr.DataArray(values, dims=("direction", "y", "x"), coords=coords,
                          name="visibility_height", attrs=attrs)
        da = da.assign_coords(azimuth_deg=("direction", az), grid_azimuth_deg=("direction", az_grid),
                              elevation_deg=("direction", el))
    return da.rio.write_crs(surface.rio.crs)
