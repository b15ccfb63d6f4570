"""GNSS dilution of precision (DOP) above a surface: column DOP profiles and coverage maps.

Physics
-------
Satellites are ~20 000 km away, so within a map of a few km the direction (azimuth, elevation)
of a satellite is the same from every point, and whether it is in line of sight from a point
(x, y, z) only depends on the *visibility height* ``h_s(x, y)`` of the column: the satellite is
visible from every altitude ``z >= h_s`` (computed by :mod:`skyroute.stages.occlusion`).  The
visible set of a column therefore only changes at the sorted visibility heights, and since adding
a satellite adds a positive semi-definite rank-one term ``g g^T`` to the normal matrix
``N = G^T G`` (the DOP algebra of :mod:`skyroute.stages.dop`: rows
``g = [cos(el) sin(az), cos(el) cos(az), sin(el), 1]``), ``Q = N^-1`` and every DOP
(GDOP, PDOP, HDOP, VDOP, TDOP) never increases with altitude.  Each column's DOP profile is
computed *exactly* from its breakpoints (rank-one updates of the 4x4 normal matrix and a 4x4
Cholesky inverse-diagonal at each distinct breakpoint, numba kernel) instead of sampling a
voxel grid; the coverage floor's kernel shares these operations between columns with the same
breakpoint groups (memoised, floors bit-identical to the direct kernel).

GNSS coverage map (seeds 000 item 5, 001 item 5): for a DOP threshold ``D_j`` the altitude
above which DOP < D_j, worst case (max) over the epochs of a time window (default 20 min at
every whole minute = 21 epochs; seed 001 sampled every 5 min), clipped to altitude limits.
Heights are in the vertical datum of the surface [m].

Conservative by construction: the visibility heights of :mod:`skyroute.stages.occlusion` are
bounds valid for every point of a cell, and since DOP never increases when a satellite is
added, a visible set computed from upper bounds is a subset of the true one at every point:
above the stored floor, DOP < D_j holds at every point of the cell and at every epoch of the
window (tests: exact line of sight at random points of cells, least-squares DOP).  Between
epochs nothing is claimed: the default step is one minute so that every whole minute of the
window is an epoch.

Conventions: a DOP is **+inf** where there is no fix (fewer than 4 visible satellites or a
singular geometry) and **NaN** only for missing data (below the surface, in sections and
volumes), as everywhere in skyroute (:mod:`skyroute.stages.dop`).  Unflyable cells (a coverage
*floor*, an altitude, not a DOP): ``coverage_floor`` is **NaN** and the boolean ``unflyable`` is
True where DOP never gets below ``D_j`` under the ceiling in at least one epoch (no fix, bad
geometry, or the floor above ``ceiling_m``).  The surface must be NaN-free (fill holes first).

Thresholds must exceed the universal lower bound ``c / sqrt(n)`` of the DOP kind
(:data:`~skyroute.stages.dop.DOP_BOUND_COEF`, derived in :mod:`skyroute.stages.dop`):
:func:`coverage_maps` rejects thresholds <= ``c / sqrt(n_max)`` (``n_max`` = most satellites
above the mask in one epoch), which no geometry can reach, and reports the open-sky DOP of the
window in the attrs.

Layers: numba kernels (``_*_kernel``, on the 4x4 building blocks of
:mod:`skyroute.stages.dop`), numpy runners (``*_numpy``, one spatial block, all epochs), dask
runners (the overlapped blocks of :mod:`skyroute.stages.overlap`, depth
``shadow_halo_cells`` at the lowest elevation used) and public xarray functions
(:func:`coverage_maps`, :func:`dop_section`, :func:`dop_volume`, :func:`column_dop_profile`).
The (time, sat, y, x) visibility heights are never materialised for the whole map: each block
computes them one epoch at a time and reduces them at once.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from typing import Any

import dask.array as da
import numba
import numpy as np
import rioxarray  # noqa: F401  (registers the .rio accessor)
import xarray as xr

from skyroute.stages.base import InputError
from skyroute.stages.dop import (
    DOP_BOUND_COEF,
    DOP_KINDS,
    add_rank_one,
    dop_kind_index,
    dop_lower_bound,
    dop_of_kind,
    dop_profile,
    dop_table,
    inv4,
    inv_diag4,
    los_rows,
)
from skyroute.stages.orbits import as_time_sat, check_mask, epoch_directions, window_times
from skyroute.stages.overlap import BlockFn, ensure_min_chunks, overlap_map, overlap_maps

__all__ = [
    "DOP_BOUND_COEF", "DOP_KINDS", "Chunks", "VisibilityFn", "column_dop_profile",
    "coverage_floor_numpy", "coverage_from_almanac", "coverage_maps", "dop_kind_index",
    "check_thresholds", "dop_lower_bound", "dop_section", "dop_section_numpy", "dop_volume", "los_rows",
    "open_sky_dop", "window_times",
]

VisibilityFn = Callable[..., np.ndarray]
"""``fn(surface_2d, az_grid_deg (n,), el_deg (n,), cell_m, origin=(row, col)) -> (n, ny, nx)``
(the signature of ``occlusion.visibility_heights_numpy``)."""


# --------------------------------------------------------------------------------------------
# numba kernels
# --------------------------------------------------------------------------------------------

@numba.njit(cache=True, nogil=True, inline="always")
def _sorted_column(h: np.ndarray, i: int, j: int, hs: np.ndarray, order: np.ndarray) -> int:
    """Finite visibility heights of cell (i, j), sorted ascending into ``hs`` (indices into
    ``order``); returns their count (insertion sort: n is ~10)."""
    m = 0
    for s in range(h.shape[0]):
        v = h[s, i, j]
        if not (v == v) or v == np.inf:  # NaN or never visible
            continue
        p = m
        while p > 0 and hs[p - 1] > v:
            hs[p] = hs[p - 1]
            order[p] = order[p - 1]
            p -= 1
        hs[p] = v
        order[p] = s
        m += 1
    return m


@numba.njit(cache=True, nogil=True)
def _reference_floor_epoch_kernel(h, g, thresholds, kind, out):
    """Fold one epoch into the running worst-case floor: the direct kernel (the reference of
    the memoised :func:`_floor_epoch_kernel`, which gives bit-identical floors; kept for the
    tests, the benchmark and more than :data:`_MEMO_MAX_SAT` satellites).

    h: (n, ny, nx) visibility heights [m] (+inf/NaN = never visible; any strides, e.g. the
    core of an overlapped block); g: (n, 4) rows [e_east, e_north, e_up, 1]; thresholds:
    (J,) ascending; out: (J, ny, nx), running max of the lowest altitude with DOP < D_j
    (+inf = never).  Updated in place.

    Per column the breakpoints are visited in ascending order by selection (the next
    larger height, then every satellite at it, in index order), which stops as soon as the
    smallest threshold is reached: most columns need one or two of them, so no
    full sort.  The normal matrix is inverted (Cholesky) at the first breakpoint where it is
    regular; later satellites update the inverse by Sherman-Morrison (one division instead
    of a 4x4 factorisation)."""
    n, ny, nx = h.shape
    nj = thresholds.shape[0]
    vals = np.empty(n)
    nm = np.zeros((4, 4))
    lo = np.zeros((4, 4))
    mi = np.zeros((4, 4))
    qm = np.zeros((4, 4))
    u = np.zeros(4)
    q = np.zeros(4)
    inf = np.inf
    for i in range(ny):
        for j in range(nx):
            m = 0
            for s in range(n):
                v = h[s, i, j]
                if v == v and v < inf:
                    vals[s] = v
                    m += 1
                else:  # NaN or never visible
                    vals[s] = inf
            nm[:, :] = 0.0
            regular = False  # qm holds inv(nm)
            jj = nj - 1  # the largest threshold is reached first
            k = 0
            z_prev = -inf
            while k < m and jj >= 0:
                z = inf  # next breakpoint: the smallest height above the previous one
                for s in range(n):
                    v = vals[s]
                    if v > z_prev and v < z:
                        z = v
                # add the whole group of satellites that appear at this height
                for s in range(n):
                    if vals[s] == z:
                        gs = g[s]
                        if regular:
                            add_rank_one(qm, gs, u)
                        else:
                            for a in range(4):  # lower triangle (all inv4 reads)
                                for b in range(a + 1):
                                    nm[a, b] += gs[a] * gs[b]
                        k += 1
                z_prev = z
                if not regular:
                    if k < 4 or not inv4(nm, lo, mi, qm):
                        continue
                    regular = True
                for a in range(4):
                    q[a] = qm[a, a]
                d = dop_of_kind(q, kind)
                while jj >= 0 and d < thresholds[jj]:
                    if z > out[jj, i, j]:
                        out[jj, i, j] = z
                    jj -= 1
            while jj >= 0:  # never reached in this epoch
                out[jj, i, j] = inf
                jj -= 1


#: Most satellites per epoch the memoised floor kernel handles (a breakpoint's group of
#: satellites is a bit mask in one int64); more: the direct kernel.
_MEMO_MAX_SAT = 62

#: Nodes of the memo of :func:`_floor_epoch_kernel` (one per distinct sequence of breakpoint
#: groups up to the first regular breakpoint; 160 bytes each); when it is full, it is
#: cleared before the next column.
_MEMO_NODES = 1 << 14


@numba.njit(cache=True, nogil=True, inline="always")
def _memo_slot(parent, mask, tmask):
    """Hash-table slot of the edge (``parent`` node, group ``mask``); ``tmask`` = size - 1."""
    x = (mask ^ (parent * -7046029254386353131)) * -4658895280553007687  # wraps (int64)
    return (x >> 40) & tmask


@numba.njit(cache=True, nogil=True)
def _memo_child(tab, nd, nodes, parent, mask, tmask, g, kind, nm, lo, mi, qs, q):
    """Node of the prefix ``parent`` + the group ``mask`` (looked up in the hash table ``tab``
    or computed into node ``nodes``); returns (node, nodes).  A new node gets the direct
    kernel's operations in its order: the group's rows added in index order to the lower
    triangle of the parent's normal matrix, then, with >= 4 satellites, the Cholesky inverse
    (kept when regular)."""
    slot = _memo_slot(parent, mask, tmask)
    while True:
        km = tab[slot, 0]
        if km == mask and (tab[slot, 1] >> 32) == parent:
            return tab[slot, 1] & 0xFFFFFFFF, nodes
        if km == 0:
            break
        slot = (slot + 1) & tmask
    c = nodes
    for a in range(4):
        for b in range(4):
            nm[a, b] = nd[parent, a, b]
    k = nd[parent, 4, 1]
    for s in range(g.shape[0]):
        if (mask >> s) & 1:
            gs = g[s]
            for a in range(4):  # lower triangle (all inv4 reads)
                for b in range(a + 1):
                    nm[a, b] += gs[a] * gs[b]
            k += 1.0
    res = nm
    d = np.inf
    reg = 0.0
    if k >= 4.0 and inv4(nm, lo, mi, qs):
        res = qs
        for a in range(4):
            q[a] = qs[a, a]
        d = dop_of_kind(q, kind)
        reg = 1.0
    for a in range(4):
        for b in range(4):
            nd[c, a, b] = res[a, b]
    nd[c, 4, 0] = d
    nd[c, 4, 1] = k
    nd[c, 4, 2] = reg
    tab[slot, 0] = mask
    tab[slot, 1] = (parent << 32) | c
    return c, nodes + 1


@numba.njit(cache=True, nogil=True, inline="always")
def _rank_one16(q, g0, g1, g2, g3):
    """:func:`~skyroute.stages.dop.add_rank_one` on a row-major 16-tuple ``q`` (held in
    registers), the same operations in the same order (the same bits)."""
    u0 = q[0] * g0 + q[1] * g1 + q[2] * g2 + q[3] * g3
    u1 = q[4] * g0 + q[5] * g1 + q[6] * g2 + q[7] * g3
    u2 = q[8] * g0 + q[9] * g1 + q[10] * g2 + q[11] * g3
    u3 = q[12] * g0 + q[13] * g1 + q[14] * g2 + q[15] * g3
    s = 1.0 / (1.0 + g0 * u0 + g1 * u1 + g2 * u2 + g3 * u3)
    a0 = u0 * s
    a1 = u1 * s
    a2 = u2 * s
    a3 = u3 * s
    return (q[0] - a0 * u0, q[1] - a0 * u1, q[2] - a0 * u2, q[3] - a0 * u3,
            q[4] - a1 * u0, q[5] - a1 * u1, q[6] - a1 * u2, q[7] - a1 * u3,
            q[8] - a2 * u0, q[9] - a2 * u1, q[10] - a2 * u2, q[11] - a2 * u3,
            q[12] - a3 * u0, q[13] - a3 * u1, q[14] - a3 * u2, q[15] - a3 * u3)


@numba.njit(cache=True, nogil=True, inline="always")
def _rank_column(h, i, j, col, rank):
    """Heights of column (i, j) into ``col`` (NaN -> +inf) and ``rank[s]``, the number of
    satellites strictly lower than ``s``: the same for every satellite of a breakpoint group,
    and the group of ``c`` satellites at rank ``r`` is followed by the one at rank ``r + c``
    (:func:`_group_at`).  Branch-free, O(n^2) comparisons: cheaper than a selection pass per
    breakpoint for the columns that need several."""
    n = col.shape[0]
    inf = np.inf
    for s in range(n):
        v = h[s, i, j]
        col[s] = v if v == v else inf
    for s in range(n):
        v = col[s]
        r = 0
        for t in range(n):
            r += col[t] < v
        rank[s] = r


@numba.njit(cache=True, nogil=True, inline="always")
def _group_at(rank, r):
    """(bit mask, size, first satellite) of the group at rank ``r`` (:func:`_rank_column`);
    one branch-free pass."""
    n = rank.shape[0]
    mask = 0
    c = 0
    smin = n
    for s in range(n):
        e = rank[s] == r
        mask |= np.int64(e) << s
        c += e
        smin = min(smin, s if e else n)
    return mask, c, smin


@numba.njit(cache=True, nogil=True)
def _memo_floor_epoch_kernel(h, g, thresholds, kind, out):
    """:func:`_floor_epoch_kernel` for at most :data:`_MEMO_MAX_SAT` satellites and at least
    one threshold: the memoised kernel, floors bit-identical to
    :func:`_reference_floor_epoch_kernel`.

    h: (n, ny, nx) visibility heights [m] (finite, +inf or NaN = never visible, never -inf;
    any strides, e.g. the core of an overlapped block); g: (n, 4) rows [e_east, e_north,
    e_up, 1]; thresholds: (J,) ascending; out: (J, ny, nx), running max of the lowest altitude
    with DOP < D_j (+inf = never).  Updated in place.

    Why the same bits: a column's floors depend on its heights only through the sequence of
    its breakpoint *groups* (the satellites that appear at each distinct height, ascending)
    and their heights: the direct kernel adds a group's rows in index order to the lower
    triangle of the normal matrix, inverts it (Cholesky) at the first breakpoint with >= 4
    satellites where it is regular, updates the inverse by Sherman-Morrison (index order)
    after it and compares the DOP with the thresholds after each group, stopping at the
    smallest.  This kernel performs exactly these floating-point operations in the same order
    (no fast-math, the same compiled building blocks or their operation-for-operation
    copies :func:`_rank_one16`), but shares them between columns:

    * the states up to the first regular breakpoint are nodes of a trie, edges (node, group
      bit mask) in an open-addressing hash table (:func:`_memo_child`): a city has a few
      thousand distinct first groups per epoch for 10^5-10^6 columns (a quarter of its
      columns see every satellite at the surface: one group, one look-up);
    * the previous column's state after each group is kept and reused while the groups are
      the same (71 % of the first groups of Helsinki are the left neighbour's);
    * past both, the Sherman-Morrison chain runs in registers, and every state is kept for
      the next column.

    Finding the groups costs no selection loop with branches: the first breakpoint of every
    column of a row comes from vectorised passes along the rows of ``h``; a column that needs
    more ranks its satellites once (:func:`_rank_column`, :func:`_group_at`).  Benchmark:
    ``benchmarks/bench_coverage_scale.py --kernels``; tests: ``tests/test_coverage_incremental.py``
    (property-generated columns, shipped scenarios, ``np.array_equal``)."""
    n, ny, nx = h.shape
    nj = thresholds.shape[0]
    cap = _MEMO_NODES
    tsize = 4 * cap  # load factor <= 1/4
    tmask = tsize - 1
    tab = np.zeros((tsize, 2), np.int64)  # [group mask (0 = empty), parent << 32 | child]
    nd = np.empty((cap, 5, 4))  # matrix (normal, lower triangle; or its inverse), [d, k, reg]
    nd[0, :, :] = 0.0  # the root: no satellite
    nodes = 1
    # the current (and the previous) column's state after each group
    pm = np.zeros(n + 1, np.int64)  # group masks
    pq = np.empty((n + 1, 16))  # inverse of the normal matrix, row-major (regular states)
    pd = np.empty(n + 1)  # DOP (regular states)
    pk = np.empty(n + 1, np.int64)  # satellites added
    preg = np.zeros(n + 1, np.bool_)
    pnode = np.zeros(n + 1, np.int64)  # trie node (states before the first regular one)
    plen = 0  # valid levels
    nm = np.zeros((4, 4))
    lo = np.zeros((4, 4))
    mi = np.zeros((4, 4))
    qs = np.zeros((4, 4))
    q = np.zeros(4)
    inf = np.inf
    zr = np.empty(nx, h.dtype)  # per column of the row: first breakpoint [m],
    mr = np.empty(nx, np.int64)  # visible satellites,
    gr = np.empty(nx, np.int64)  # the group at the first breakpoint
    col = np.empty(n)  # one column's heights (NaN -> +inf) and ranks, once it needs a
    rank = np.empty(n, np.int64)  # second breakpoint (_rank_column)
    for i in range(ny):
        # the first breakpoint of every column of the row: branch-free passes along the rows
        # of h (contiguous, vectorised)
        zr[:] = inf
        mr[:] = 0
        gr[:] = 0
        for s in range(n):
            for j in range(nx):
                v = h[s, i, j]
                mr[j] += v < inf  # NaN and +inf: never visible
                zr[j] = v if v < zr[j] else zr[j]
        for s in range(n):
            for j in range(nx):
                gr[j] |= np.int64(h[s, i, j] == zr[j]) << s
        for j in range(nx):
            if nodes + n > cap:  # a column adds at most n nodes: clear the memo
                tab[:, 0] = 0
                nodes = 1
                plen = 0
            m = mr[j]
            z = np.float64(zr[j])
            mask = gr[j]
            smin = 0
            r = 0  # rank and size of the current group (_rank_column)
            c = 0
            jj = nj - 1  # the largest threshold is reached first
            lv = 0
            same = True  # the groups so far are the previous column's
            gathered = False
            done = m == 0
            # phase 1: the previous column's states, then the trie, while they hold the state
            while not done:
                if not (same and lv < plen and pm[lv] == mask):
                    same = False
                    if lv and preg[lv - 1]:
                        break  # a regular state no column before had: phase 2
                    pm[lv] = mask
                    nc, nodes = _memo_child(tab, nd, nodes, pnode[lv - 1] if lv else 0, mask,
                                            tmask, g, kind, nm, lo, mi, qs, q)
                    pnode[lv] = nc
                    pk[lv] = int(nd[nc, 4, 1])
                    preg[lv] = nd[nc, 4, 2] != 0.0
                    if preg[lv]:
                        pd[lv] = nd[nc, 4, 0]
                        for a in range(4):
                            for b in range(4):
                                pq[lv, 4 * a + b] = nd[nc, a, b]
                if preg[lv]:
                    d = pd[lv]
                    while jj >= 0 and d < thresholds[jj]:
                        if z > out[jj, i, j]:
                            out[jj, i, j] = z
                        jj -= 1
                lv += 1
                if pk[lv - 1] >= m or jj < 0:
                    done = True
                    break
                if not gathered:
                    _rank_column(h, i, j, col, rank)
                    c = _group_at(rank, 0)[1]  # the first group's size
                    gathered = True
                r += c  # the next group
                mask, c, smin = _group_at(rank, r)
                z = col[smin]
            if not done:
                # phase 2: Sherman-Morrison in registers from the state of level lv - 1, each
                # group in index order; every state kept for the next column
                qt = (pq[lv - 1, 0], pq[lv - 1, 1], pq[lv - 1, 2], pq[lv - 1, 3],
                      pq[lv - 1, 4], pq[lv - 1, 5], pq[lv - 1, 6], pq[lv - 1, 7],
                      pq[lv - 1, 8], pq[lv - 1, 9], pq[lv - 1, 10], pq[lv - 1, 11],
                      pq[lv - 1, 12], pq[lv - 1, 13], pq[lv - 1, 14], pq[lv - 1, 15])
                k = pk[lv - 1]
                while True:
                    if c == 1:  # one satellite (the usual case)
                        gs = g[smin]
                        qt = _rank_one16(qt, gs[0], gs[1], gs[2], gs[3])
                        k += 1
                    else:
                        for s in range(smin, n):
                            if (mask >> s) & 1:
                                gs = g[s]
                                qt = _rank_one16(qt, gs[0], gs[1], gs[2], gs[3])
                                k += 1
                    pq[lv, 0] = qt[0]
                    pq[lv, 1] = qt[1]
                    pq[lv, 2] = qt[2]
                    pq[lv, 3] = qt[3]
                    pq[lv, 4] = qt[4]
                    pq[lv, 5] = qt[5]
                    pq[lv, 6] = qt[6]
                    pq[lv, 7] = qt[7]
                    pq[lv, 8] = qt[8]
                    pq[lv, 9] = qt[9]
                    pq[lv, 10] = qt[10]
                    pq[lv, 11] = qt[11]
                    pq[lv, 12] = qt[12]
                    pq[lv, 13] = qt[13]
                    pq[lv, 14] = qt[14]
                    pq[lv, 15] = qt[15]
                    q[0] = qt[0]
                    q[1] = qt[5]
                    q[2] = qt[10]
                    q[3] = qt[15]
                    d = dop_of_kind(q, kind)
                    pm[lv] = mask
                    pk[lv] = k
                    preg[lv] = True
                    pd[lv] = d
                    while jj >= 0 and d < thresholds[jj]:
                        if z > out[jj, i, j]:
                            out[jj, i, j] = z
                        jj -= 1
                    lv += 1
                    if k >= m or jj < 0:
                        break
                    r += c  # the next group
                    mask, c, smin = _group_at(rank, r)
                    z = col[smin]
            plen = max(plen, lv) if same else lv
            while jj >= 0:  # never reached in this epoch
                out[jj, i, j] = inf
                jj -= 1


def _floor_epoch_kernel(h: np.ndarray, g: np.ndarray, thresholds: np.ndarray, kind: int,
                        out: np.ndarray) -> None:
    """Fold one epoch into the running worst-case floor ``out`` (in place).

    h: (n, ny, nx) visibility heights [m] (finite, +inf or NaN = never visible, never -inf;
    any strides); g: (n, 4) rows [e_east, e_north, e_up, 1]; thresholds: (J,) ascending;
    out: (J, ny, nx), running max of the lowest altitude with DOP < D_j (+inf = never).
    The memoised kernel (:func:`_memo_floor_epoch_kernel`) up to :data:`_MEMO_MAX_SAT`
    satellites, else the direct one: the same floors, bit for bit."""
    if h.shape[0] > _MEMO_MAX_SAT or thresholds.shape[0] == 0:
        _reference_floor_epoch_kernel(h, g, thresholds, kind, out)
    else:
        _memo_floor_epoch_kernel(h, g, thresholds, kind, out)


@numba.njit(cache=True, nogil=True)
def _section_epoch_kernel(h, g, surface, altitudes, out):
    """DOP on horizontal sections for one epoch.

    h: (n, ny, nx) visibility heights [m]; g: (n, 4); surface: (ny, nx) [m];
    altitudes: (A,) [m], any order; out: (A, 6, ny, nx) float32 with
    [n_visible, GDOP, PDOP, HDOP, VDOP, TDOP]; DOP = +inf with < 4 satellites or singular
    geometry, NaN (and n_visible 0) below the surface."""
    n, ny, nx = h.shape
    na = altitudes.shape[0]
    hs = np.empty(n)
    order = np.empty(n, np.int64)
    prof = np.empty((n + 1, 5))  # DOPs with the first k satellites
    nm = np.zeros((4, 4))
    lo = np.zeros((4, 4))
    mi = np.zeros((4, 4))
    q = np.zeros(4)
    for i in range(ny):
        for j in range(nx):
            m = _sorted_column(h, i, j, hs, order)
            nm[:, :] = 0.0
            for c in range(5):
                prof[0, c] = np.inf
            for k in range(m):
                gs = g[order[k]]
                for a in range(4):
                    for b in range(4):
                        nm[a, b] += gs[a] * gs[b]
                if k + 1 < 4 or (k + 1 < m and hs[k + 1] == hs[k]):
                    # fewer than 4, or not a breakpoint (ties): value never looked up
                    for c in range(5):
                        prof[k + 1, c] = np.inf
                    continue
                if inv_diag4(nm, lo, mi, q):
                    for c in range(5):
                        prof[k + 1, c] = dop_of_kind(q, c)
                else:
                    for c in range(5):
                        prof[k + 1, c] = np.inf
            zs = surface[i, j]
            for a in range(na):
                z = altitudes[a]
                if not (z >= zs):  # below the surface, or surface NaN
                    out[a, 0, i, j] = 0.0
                    for c in range(5):
                        out[a, c + 1, i, j] = np.nan
                    continue
                kv = np.searchsorted(hs[:m], z, side="right")
                out[a, 0, i, j] = kv
                for c in range(5):
                    out[a, c + 1, i, j] = prof[kv, c]


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------

def _default_visibility() -> VisibilityFn:
    from skyroute.stages.occlusion import visibility_heights_numpy

    return visibility_heights_numpy


def _halo_cells(surface_2d: Any, min_el_deg: float, cell_m: float) -> int:
    """Halo [cells] a block needs so that every obstacle that can shadow it at elevations
    >= ``min_el_deg`` is inside it (``occlusion.shadow_halo_cells``)."""
    from skyroute.stages.occlusion import shadow_halo_cells

    return int(shadow_halo_cells(surface_2d, float(min_el_deg), float(cell_m)))


def _grid_azimuth(true_az_deg: np.ndarray, surface: xr.DataArray) -> np.ndarray:
    """True -> grid azimuth [deg] (meridian convergence at the map centre); NaN stays NaN."""
    from skyroute.stages.occlusion import grid_azimuth_deg

    az = np.asarray(true_az_deg, dtype=np.float64)
    out = np.asarray(grid_azimuth_deg(np.nan_to_num(az), surface), dtype=np.float64)
    return np.where(np.isfinite(az), out, np.nan)


def _visibility(fn: VisibilityFn, surface: np.ndarray, az: np.ndarray, el: np.ndarray,
                cell_m: float, origin: tuple[int, int]) -> np.ndarray:
    if az.size == 0:
        return np.empty((0,) + surface.shape, np.float32)
    return np.asarray(fn(surface, az, el, cell_m, origin=origin))


# --------------------------------------------------------------------------------------------
# numpy runners (one spatial block, all epochs)
# --------------------------------------------------------------------------------------------

def coverage_floor_numpy(surface_2d: np.ndarray, az_grid_deg: np.ndarray, el_deg: np.ndarray,
                         cell_m: float, thresholds: np.ndarray, kind: int, mask_deg: float = 5.0,
                         visibility_fn: VisibilityFn | None = None,
                         origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Worst-case (over epochs) lowest altitude [m] with DOP < ``thresholds[j]``, one spatial block.

    Visibility heights are computed one epoch at a time with ``visibility_fn``.

    Parameters
    ----------
    surface_2d : numpy.ndarray
        ``(ny, nx)`` NaN-free surface heights [m].
    az_grid_deg, el_deg : numpy.ndarray
        ``(time, sat)`` azimuth relative to grid north and elevation [deg] (DOP does not depend on
        a rotation about the vertical); NaN = absent.
    cell_m : float
        Cell size [m].
    thresholds : numpy.ndarray
        ``(J,)`` DOP thresholds, ascending.
    kind : int
        DOP kind index (:func:`dop_kind_index`).
    mask_deg : float, default 5.0
        Elevation mask [deg].
    visibility_fn : VisibilityFn, optional
        Default :func:`skyroute.stages.occlusion.visibility_heights_numpy`.
    origin : tuple of int, default (0, 0)
        (row, col) of the block in the whole map, for bit-identical blocks.

    Returns
    -------
    numpy.ndarray
        float64 ``(J, ny, nx)`` altitudes [m], +inf where some epoch never gets there.
    """
    return _floor_block(surface_2d, az_grid_deg, el_deg, cell_m, thresholds, kind, mask_deg,
                        visibility_fn, origin)


_FULL = (slice(None), slice(None))


def _floor_block(surface_2d: np.ndarray, az_grid_deg: np.ndarray, el_deg: np.ndarray,
                 cell_m: float, thresholds: np.ndarray, kind: int, mask_deg: float,
                 visibility_fn: VisibilityFn | None, origin: tuple[int, int],
                 core: tuple[slice, slice] = _FULL, epochs: Sequence[int] | None = None,
                 dtype: Any = np.float64) -> np.ndarray:
    """:func:`coverage_floor_numpy` of the ``core`` window of an overlapped block (the
    visibility heights need the whole block, the DOP kernel only runs on the core) over the
    epochs ``epochs`` (default all), as ``dtype`` (float32 holds every value exactly: the
    floors are float32 visibility heights or +-inf)."""
    fn = visibility_fn or _default_visibility()
    surface_2d = np.ascontiguousarray(surface_2d, dtype=np.float32)
    thr = np.ascontiguousarray(thresholds, dtype=np.float64)
    out = np.full((thr.size,) + surface_2d[core].shape, -np.inf, dtype)
    dirs = epoch_directions(np.asarray(az_grid_deg, float), np.asarray(el_deg, float), mask_deg)
    for t in range(len(dirs)) if epochs is None else epochs:
        az, el = dirs[t]
        h = np.ascontiguousarray(_visibility(fn, surface_2d, az, el, cell_m, origin))
        g = np.ascontiguousarray(los_rows(az, el))
        _floor_epoch_kernel(h if core == _FULL else h[(slice(None),) + core], g, thr,
                            int(kind), out)
    return out


def dop_section_numpy(surface_2d: np.ndarray, az_grid_deg: np.ndarray, el_deg: np.ndarray,
                      cell_m: float, altitudes_m: np.ndarray, mask_deg: float = 5.0,
                      visibility_fn: VisibilityFn | None = None,
                      origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """``(time, altitude, 6, ny, nx)`` float32: n_visible, GDOP, PDOP, HDOP, VDOP, TDOP at absolute altitudes [m].

    Conventions of :func:`_section_epoch_kernel`: DOP = +inf with < 4 satellites or a singular
    geometry, NaN (and n_visible 0) below the surface.

    Parameters
    ----------
    surface_2d : numpy.ndarray
        ``(ny, nx)`` NaN-free surface heights [m].
    az_grid_deg, el_deg : numpy.ndarray
        ``(time, sat)`` azimuth relative to grid north and elevation [deg]; NaN = absent.
    cell_m : float
        Cell size [m].
    altitudes_m : numpy.ndarray
        ``(A,)`` section altitudes [m] in the surface's vertical datum, any order.
    mask_deg : float, default 5.0
        Elevation mask [deg].
    visibility_fn : VisibilityFn, optional
        Default :func:`skyroute.stages.occlusion.visibility_heights_numpy`.
    origin : tuple of int, default (0, 0)
        (row, col) of the block in the whole map, for bit-identical blocks.

    Returns
    -------
    numpy.ndarray
        float32 ``(time, A, 6, ny, nx)``.
    """
    return _section_block(surface_2d, az_grid_deg, el_deg, cell_m, altitudes_m, mask_deg,
                          visibility_fn, origin)


def _section_block(surface_2d: np.ndarray, az_grid_deg: np.ndarray, el_deg: np.ndarray,
                   cell_m: float, altitudes_m: np.ndarray, mask_deg: float,
                   visibility_fn: VisibilityFn | None, origin: tuple[int, int],
                   core: tuple[slice, slice] = _FULL) -> np.ndarray:
    """:func:`dop_section_numpy` of the ``core`` window of an overlapped block."""
    fn = visibility_fn or _default_visibility()
    surface_2d = np.ascontiguousarray(surface_2d, dtype=np.float32)
    alts = np.ascontiguousarray(altitudes_m, dtype=np.float64)
    dirs = epoch_directions(np.asarray(az_grid_deg, float), np.asarray(el_deg, float), mask_deg)
    surf_core = surface_2d[core]
    out = np.empty((len(dirs), alts.size, 6) + surf_core.shape, np.float32)
    for t, (az, el) in enumerate(dirs):
        h = np.ascontiguousarray(_visibility(fn, surface_2d, az, el, cell_m, origin))
        g = np.ascontiguousarray(los_rows(az, el))
        _section_epoch_kernel(h if core == _FULL else h[(slice(None),) + core], g, surf_core,
                              alts, out[t])
    return out


# --------------------------------------------------------------------------------------------
# dask runners (block sizing and epoch split; the overlapped blocks: stages/overlap.py)
# --------------------------------------------------------------------------------------------

#: Fewer spatial blocks than this: one dask task per (block, epoch), reduced by a max over the
#: epochs, so that a few large blocks still keep every worker busy (the epochs share nothing
#: but the surface block).  With more blocks, one task per block (less memory in flight).
_EPOCH_SPLIT_BELOW_BLOCKS = 8

#: Memory budget [bytes] of one block's working set that ``chunks="auto"`` aims at.
_AUTO_BLOCK_BYTES = 1 << 30

#: Block side [cells] ``chunks="auto"`` aims at: ``max(_AUTO_MIN_SIDE, _AUTO_HALO_FACTOR *
#: halo)``; the overlap costs ``(1 + 2 halo / side)^2`` times the visibility scan of the block
#: alone (the DOP kernel, most of the work, only runs on the block's own cells).
_AUTO_MIN_SIDE = 2048
_AUTO_HALO_FACTOR = 8
#: ``chunks="auto"`` splits an axis in two rather than keep one block when both halves stay
#: at least this wide and 3 halos wide (4 blocks x epochs keep 2+ workers evenly busy).
_AUTO_SPLIT_MIN_SIDE = 1024


def _auto_block_cells(shape: tuple[int, int], halo: int, n_sat: int, n_lead: int = 3,
                      budget_bytes: int = _AUTO_BLOCK_BYTES) -> tuple[int, int]:
    """Block size (rows, cols) [cells] for the overlapped dask runners of a map ``shape``
    with a halo of ``halo`` cells and at most ``n_sat`` satellites per epoch.

    Aim: sides of ``max(_AUTO_MIN_SIDE, _AUTO_HALO_FACTOR * halo)`` cells, shrunk so that the
    extended block's working set (surface, its transpose and one epoch of ``n_sat`` float32
    visibility heights, plus ``n_lead`` float32 outputs per cell) stays within
    ``budget_bytes``, never below the halo.  Each axis is then split into equal blocks (no
    thin remainder block: equal work per block balances the workers), and in two if it
    would be one block but both halves stay wide (:data:`_AUTO_SPLIT_MIN_SIDE`, 3 halos)."""
    halo = int(halo)
    per_cell = 4 * (int(n_sat) + 2 + int(n_lead))
    side_mem = int(math.isqrt(max(int(budget_bytes) // per_cell, 1))) - 2 * halo
    side = max(min(max(_AUTO_MIN_SIDE, _AUTO_HALO_FACTOR * halo), side_mem), halo, 256)
    out = []
    for dim in shape:
        n = max(1, math.ceil(dim / side))
        if n == 1 and dim >= 2 * max(_AUTO_SPLIT_MIN_SIDE, 3 * halo):
            n = 2
        out.append(math.ceil(dim / n))
    return out[0], out[1]


# --------------------------------------------------------------------------------------------
# public xarray layer
# --------------------------------------------------------------------------------------------

def _check_surface(surface: xr.DataArray) -> float:
    if not isinstance(surface, xr.DataArray) or surface.dims[-2:] != ("y", "x") or surface.ndim != 2:
        raise InputError("surface must be a 2D xarray.DataArray with dims ('y', 'x') "
                         "(see skyroute.stages.grid)")
    x = np.asarray(surface["x"].values)
    y = np.asarray(surface["y"].values)
    if x.size < 2 or y.size < 2:
        raise InputError("surface needs at least 2 x 2 cells")
    cell = float(x[1] - x[0])
    if not (cell > 0 and np.isclose(float(y[0] - y[1]), cell)):
        raise InputError("surface must be north-up with square cells: x ascending, y descending")
    if not np.issubdtype(surface.dtype, np.number):
        raise InputError(f"surface must hold numbers [m], got dtype {surface.dtype}")
    n_nan = surface.isnull().sum().values
    if int(n_nan):
        raise InputError(f"surface has {int(n_nan)} NaN cell(s): fill them first (e.g. with the "
                         "terrain height or rioxarray's interpolate_na)")
    return cell


def _min_el(el: np.ndarray, mask: float) -> float:
    ok = el[np.isfinite(el) & (el >= mask)]
    return float(ok.min()) if ok.size else 90.0


Chunks = int | tuple[int, int] | str | None


def _surface_array(surface: xr.DataArray, chunks: Chunks, min_el_deg: float, cell_m: float,
                   n_sat: int, n_lead: int) -> tuple[np.ndarray | da.Array, int]:
    """(surface as float32 numpy or dask, halo [cells] for a dask array, else 0).
    ``chunks="auto"``: blocks from :func:`_auto_block_cells`."""
    if not (chunks is None or chunks == "auto" or isinstance(chunks, int | tuple)):
        raise InputError(f"chunks must be None, 'auto', an int or a (rows, cols) tuple of "
                         f"cells, got {chunks!r}")
    data = surface.data
    if isinstance(data, da.Array):
        data = data.astype(np.float32)
    else:
        data = np.asarray(data, dtype=np.float32)
    if chunks is None and not isinstance(data, da.Array):
        return data, 0
    depth = _halo_cells(data, min_el_deg, cell_m)
    if chunks == "auto":
        chunks = _auto_block_cells(data.shape, depth, n_sat, n_lead)
    if chunks is not None:
        data = data.rechunk(chunks) if isinstance(data, da.Array) else da.from_array(data, chunks=chunks)
    return data, depth


def _as_block_fn(run: Callable[..., np.ndarray]) -> BlockFn:
    """``run(block, origin=, core=)`` as a positional :data:`BlockFn`."""
    def fn(block: np.ndarray, origin: tuple[int, int], core: tuple[slice, slice]) -> np.ndarray:
        return run(block, origin=origin, core=core)
    return fn


def _limit(value: Any, name: str, surface: xr.DataArray, default: float) -> np.ndarray | da.Array:
    if value is None:
        return np.float32(default)
    if isinstance(value, xr.DataArray):
        if set(value.dims) - {"y", "x"}:
            raise InputError(f"{name} must be a scalar or a (y, x) raster, got dims {value.dims}")
        value = value.broadcast_like(surface).transpose("y", "x").data
    else:
        value = np.asarray(value, dtype=np.float32)
        if value.ndim not in (0, 2) or (value.ndim == 2 and value.shape != surface.shape):
            raise InputError(f"{name} must be a scalar or an array of the surface shape "
                             f"{surface.shape}, got shape {value.shape}")
    return value


def _spatial_attrs(surface: xr.DataArray) -> dict[str, Any]:
    datum = surface.attrs.get("vertical_datum")
    return {"vertical_datum": datum} if datum is not None else {}


def _wrap(surface: xr.DataArray, data: Any, dims: tuple[str, ...], coords: dict, name: str,
          attrs: dict) -> xr.DataArray:
    c = {k: v for k, v in coords.items()}
    c["y"], c["x"] = surface["y"], surface["x"]
    out = xr.DataArray(data, dims=dims, coords=c, name=name, attrs=attrs)
    if surface.rio.crs is not None:
        out = out.rio.write_crs(surface.rio.crs)
    return out


def _window_attrs(meta: dict[str, Any], n_epochs: int) -> dict[str, Any]:
    attrs: dict[str, Any] = {"n_epochs": int(n_epochs)}
    t = meta.get("time")
    if t is not None and len(t):
        t = np.asarray(t)
        attrs["window_start"] = str(t[0])
        attrs["window_end"] = str(t[-1])
        if len(t) > 1 and np.issubdtype(t.dtype, np.datetime64):
            attrs["window_step_s"] = float(np.median(np.diff(t)) / np.timedelta64(1, "s"))
    return attrs


def open_sky_dop(az_deg: Any, el_deg: Any, mask_deg: float = 5.0) -> np.ndarray:
    """``(time, 5)`` GDOP, PDOP, HDOP, VDOP, TDOP with every satellite above the mask visible.

    Parameters
    ----------
    az_deg, el_deg : array_like
        ``(time, sat)`` (or ``(sat,)`` for one epoch) azimuth / elevation [deg]; NaN = absent.
    mask_deg : float, default 5.0
        Elevation mask [deg], 0..60.

    Returns
    -------
    numpy.ndarray
        ``(time, 5)`` DOPs [-] (+inf: no fix).

    Raises
    ------
    InputError
        When the shapes of ``az_deg`` and ``el_deg`` differ or ``mask_deg`` is outside 0..60.
    """
    az, el, _ = as_time_sat(az_deg, el_deg)
    mask = check_mask(mask_deg)
    ok = np.isfinite(az) & np.isfinite(el) & (el >= mask) & (el > 0.0)
    return dop_table(np.where(ok, az, np.nan), np.where(ok, el, np.nan))


def column_dop_profile(visibility_height_m: Any, az_deg: Any, el_deg: Any,
                       mask_deg: float = 5.0) -> dict[str, np.ndarray]:
    """Exact DOP profile of one column for one epoch.

    Parameters
    ----------
    visibility_height_m : array_like
        ``(sat,)`` visibility heights [m] (+inf/NaN = never visible).
    az_deg, el_deg : array_like
        ``(sat,)`` azimuth / elevation [deg].
    mask_deg : float, default 5.0
        Elevation mask [deg], 0..60; satellites below it are not used.

    Returns
    -------
    dict of str to numpy.ndarray
        ``altitude_m`` (k,) breakpoints [m] ascending (the distinct visibility heights),
        ``n_visible`` (k,) and one (k,) array per DOP kind (``GDOP`` ... ``TDOP``): the value for
        ``altitude_m[i] <= z < altitude_m[i+1]`` (+inf with fewer than 4 satellites).

    Raises
    ------
    InputError
        When the three inputs differ in length or ``mask_deg`` is outside 0..60.
    """
    h = np.asarray(visibility_height_m, dtype=np.float64).ravel()
    az = np.asarray(az_deg, dtype=np.float64).ravel()
    el = np.asarray(el_deg, dtype=np.float64).ravel()
    if not (h.shape == az.shape == el.shape):
        raise InputError(f"heights {h.shape}, azimuths {az.shape} and elevations {el.shape} "
                         "must have the same length (one per satellite)")
    ok = np.isfinite(h) & np.isfinite(el) & (el >= check_mask(mask_deg))
    h, az, el = h[ok], az[ok], el[ok]
    order = np.argsort(h, kind="stable")
    h = h[order]
    prof = dop_profile(los_rows(az[order], el[order]))
    last = np.r_[h[1:] != h[:-1], True] if h.size else np.zeros(0, bool)
    res = {"altitude_m": h[last], "n_visible": np.flatnonzero(last) + 1}
    for c, name in enumerate(DOP_KINDS):
        res[name] = prof[last, c]
    return res


def check_thresholds(thresholds, dop: str, el_deg: np.ndarray, mask_deg: float
                     ) -> tuple[int, float, np.ndarray, int]:
    """Validate the coverage request: DOP kind, mask, thresholds and the most satellites above the mask.

    A threshold at or below the lowest DOP possible with the most satellites above the mask at
    any epoch of ``el_deg`` can never be reached: InputError.

    Parameters
    ----------
    thresholds : iterable of float
        DOP thresholds D_j, finite, non-empty.
    dop : str
        DOP kind: ``"GDOP"``, ``"PDOP"``, ``"HDOP"``, ``"VDOP"`` or ``"TDOP"``.
    el_deg : numpy.ndarray
        ``(time, sat)`` elevations [deg]; NaN = absent.
    mask_deg : float
        Elevation mask [deg], 0..60.

    Returns
    -------
    kind : int
        DOP kind index.
    mask_deg : float
        The validated mask [deg].
    thresholds : numpy.ndarray
        Sorted, without duplicates.
    n_max : int
        The most satellites above the mask at one epoch.

    Raises
    ------
    InputError
        When the thresholds are empty or not finite, the smallest is at or below
        :func:`dop_lower_bound` for ``n_max`` satellites, or ``mask_deg`` is outside 0..60.
    UnknownNameError
        When ``dop`` is not a DOP kind.
    """
    kind = dop_kind_index(dop)
    kind_name = DOP_KINDS[kind]
    mask = check_mask(mask_deg)
    thr = np.asarray(list(thresholds), dtype=np.float64).ravel()
    if thr.size == 0 or not np.all(np.isfinite(thr)):
        raise InputError(f"thresholds {list(thresholds)} must be a non-empty list of finite "
                         "DOP values, e.g. (2, 3, 4)")
    thr = np.unique(thr)  # sorted, duplicates dropped
    n_max = int(max(np.sum(np.isfinite(el_deg) & (el_deg >= mask), axis=1).max(), 0))
    bound = dop_lower_bound(kind_name, n_max)
    if thr[0] <= bound:
        raise InputError(
            f"{kind_name} threshold {thr[0]:g} can never be reached: with at most {n_max} "
            f"satellites above the {mask:g} deg mask, {kind_name} >= "
            f"{DOP_BOUND_COEF[kind_name]:.3g}/sqrt({n_max}) = {bound:.3f}; use thresholds above "
            "it (typically 2-6)")
    return kind, mask, thr, n_max


def coverage_maps(surface: xr.DataArray, az_deg: Any, el_deg: Any, *,
                  thresholds: Sequence[float] = (2.0, 3.0, 4.0), dop: str = "PDOP",
                  floor_m: float | np.ndarray | xr.DataArray | None = None,
                  ceiling_m: float | np.ndarray | xr.DataArray | None = None,
                  mask_deg: float = 5.0, chunks: Chunks = None,
                  visibility_fn: VisibilityFn | None = None) -> xr.Dataset:
    """GNSS coverage maps: per DOP threshold D_j, the altitude [m] above which DOP < D_j.

    The worst case over epochs is taken: a cell is unflyable if any epoch fails.

    Parameters
    ----------
    surface : xarray.DataArray
        ``(y, x)`` heights [m] of the obstacle surface (DSM: terrain + buildings) with CRS,
        NaN-free, north-up with square cells.  A dask-backed surface (or ``chunks``) is computed
        lazily block by block.
    az_deg, el_deg : array_like or xarray.DataArray
        ``(time, sat)`` TRUE azimuth / elevation [deg] of the satellites at the epochs of the
        window (NaN = absent), e.g. from ``almanac.sky_geometry``; DataArrays with a ``time``
        coordinate record the window in the attrs.
    thresholds : sequence of float, default (2.0, 3.0, 4.0)
        DOP thresholds D_j (sorted ascending in the output).
    dop : str, default "PDOP"
        "GDOP", "PDOP", "HDOP", "VDOP" or "TDOP".
    floor_m, ceiling_m : float, numpy.ndarray or xarray.DataArray, optional
        Altitude limits [m] in the surface's vertical datum (scalars or ``(y, x)`` rasters; AGL
        limits are ``surface + 150``).  The coverage floor is raised to ``floor_m``; cells whose
        floor lies above ``ceiling_m`` are unflyable.
    mask_deg : float, default 5.0
        Elevation mask [deg]; satellites below it are never used.
    chunks : int, tuple of int, "auto" or None, optional
        Block size [cells] for the dask runner (default: the surface's own chunks), or
        ``"auto"``: blocks of ``max(2048, 8 x halo)`` cells, shrunk to keep one block's working
        set near 1 GiB, split evenly along each axis (in two when both halves stay >= 1024
        cells and 3 halos wide).  Each block is extended by ``occlusion.shadow_halo_cells`` at
        the lowest satellite elevation used (~230 cells for 42 m of relief, 5 deg, 2 m cells):
        the visibility scan runs on the extended block, the DOP kernel on the block's own cells
        only, so blocks much larger than the halo (2000-4000 cells) keep the overlap cost small.
        With fewer than 8 blocks there is one task per (block, epoch) (reduced by a max over the
        epochs), so that 2+ workers stay busy.  Memory per task: one epoch of (sat, y, x)
        float32 heights on the extended block plus (threshold, y, x) float32; the numpy path (no
        chunks) holds that (float64 floors) for the whole map.
    visibility_fn : VisibilityFn, optional
        Default :func:`skyroute.stages.occlusion.visibility_heights_numpy`.

    Returns
    -------
    xarray.Dataset
        ``coverage_floor`` ``(threshold, y, x)`` float32 [m] (NaN where unflyable),
        ``unflyable`` ``(threshold, y, x)`` bool, ``open_sky_dop`` ``(time)`` and the surface's
        CRS.

    Raises
    ------
    InputError
        When the surface is not a NaN-free numeric 2-D ``(y, x)`` north-up raster of at least
        2 x 2 square cells, the satellite arrays differ in shape, a threshold can never be
        reached (see :func:`check_thresholds`), ``mask_deg`` is outside 0..60, a limit is neither
        a scalar nor a raster of the surface's shape, or ``chunks`` is invalid.
    UnknownNameError
        When ``dop`` is not a DOP kind.

    References
    ----------
    Seed 000 item 5; seed 001 item 5; seed 003 eqs. 15-19 (recorded in the ``references`` attr).
    """
    cell = _check_surface(surface)
    az, el, meta = as_time_sat(az_deg, el_deg)
    kind, mask, thr, n_max = check_thresholds(thresholds, dop, el, mask_deg)
    kind_name = DOP_KINDS[kind]
    az_grid = _grid_azimuth(az, surface)
    min_el = _min_el(el, mask)
    floor_lim = _limit(floor_m, "floor_m", surface, -np.inf)
    ceil_lim = _limit(ceiling_m, "ceiling_m", surface, np.inf)
    data, depth = _surface_array(surface, chunks, min_el, cell, n_max, thr.size)
    fn = visibility_fn or _default_visibility()

    if isinstance(data, da.Array):
        data, _, _ = ensure_min_chunks(data, depth)
        n_epochs = az.shape[0]
        if n_epochs > 1 and data.npartitions < _EPOCH_SPLIT_BELOW_BLOCKS:
            epoch_sets: list[tuple[int, ...] | None] = [(t,) for t in range(n_epochs)]
        else:
            epoch_sets = [None]
        runs = [functools.partial(_floor_block, az_grid_deg=az_grid, el_deg=el, cell_m=cell,
                                  thresholds=thr, kind=kind, mask_deg=mask, visibility_fn=fn,
                                  epochs=ep, dtype=np.float32) for ep in epoch_sets]
        parts = overlap_maps(data, depth, [_as_block_fn(r) for r in runs], ((thr.size,),),
                              np.float32)
        raw = parts[0] if len(parts) == 1 else da.stack(parts).max(axis=0)
    else:
        raw = coverage_floor_numpy(data, az_grid, el, cell, thr, kind, mask, fn)
    lib = da if isinstance(raw, da.Array) else np
    floor = lib.maximum(raw, floor_lim)
    unflyable = lib.isinf(raw) | ~(floor <= ceil_lim)  # never reached, or above the ceiling
    floor = lib.where(unflyable, np.nan, floor).astype(np.float32)

    common = _spatial_attrs(surface)
    window = _window_attrs(meta, az.shape[0])
    thr_coord = xr.DataArray(thr, dims="threshold", attrs={
        "long_name": f"{kind_name} threshold D_j", "units": "1", "dop_kind": kind_name})
    coords = {"threshold": thr_coord}
    ds = xr.Dataset({
        "coverage_floor": _wrap(surface, floor, ("threshold", "y", "x"), coords, "coverage_floor", {
            "long_name": f"lowest altitude above which {kind_name} < threshold (worst case over the window)",
            "units": "m", **common,
            "comment": "NaN where unflyable (see `unflyable`)"}),
        "unflyable": _wrap(surface, unflyable, ("threshold", "y", "x"), coords, "unflyable", {
            "long_name": f"{kind_name} never below the threshold under the ceiling in some epoch",
            "units": "1"}),
    })
    osd = open_sky_dop(az, el, mask)[:, kind]
    tcoord = meta.get("time")
    ds["open_sky_dop"] = xr.DataArray(
        osd, dims="time", coords={"time": tcoord} if tcoord is not None else None,
        attrs={"long_name": f"open-sky {kind_name} (all satellites above the mask)", "units": "1"})
    ds.attrs.update({
        "title": "GNSS coverage maps", "dop_kind": kind_name, "thresholds": thr.tolist(),
        "mask_deg": mask, "reduction": "max over epochs (worst case)",
        "unflyable_convention": "coverage_floor = NaN and unflyable = True",
        "open_sky_dop_max": float(np.max(osd)), **window, **common,
        "references": "seed 000 item 5; seed 001 item 5; seed 003 eqs. 15-19",
    })
    if surface.rio.crs is not None:
        ds = ds.rio.write_crs(surface.rio.crs)
    return ds


def _prepare_sections(surface: xr.DataArray, az_deg: Any, el_deg: Any, altitudes_m: Any,
                      mask_deg: float) -> tuple:
    cell = _check_surface(surface)
    az, el, meta = as_time_sat(az_deg, el_deg)
    mask = check_mask(mask_deg)
    alts = np.atleast_1d(np.asarray(altitudes_m, dtype=np.float64))
    if alts.ndim != 1 or alts.size == 0 or not np.all(np.isfinite(alts)):
        raise InputError("altitudes_m must be a non-empty 1D list of finite altitudes [m] "
                         "in the surface's vertical datum")
    return cell, az, el, meta, mask, alts


def _section_array(surface: xr.DataArray, az: np.ndarray, el: np.ndarray, cell: float,
                   alts: np.ndarray, mask: float, chunks: Any,
                   visibility_fn: VisibilityFn | None) -> Any:
    az_grid = _grid_azimuth(az, surface)
    n_max = int(max(np.sum(np.isfinite(el) & (el >= mask), axis=1).max(), 0))
    data, depth = _surface_array(surface, chunks, _min_el(el, mask), cell, n_max,
                                 az.shape[0] * alts.size * 6)
    fn = visibility_fn or _default_visibility()
    if isinstance(data, da.Array):
        run = functools.partial(_section_block, az_grid_deg=az_grid, el_deg=el, cell_m=cell,
                                altitudes_m=alts, mask_deg=mask, visibility_fn=fn)
        return overlap_map(data, depth, _as_block_fn(run),
                            ((az.shape[0],), (alts.size,), (6,)), np.float32)
    return dop_section_numpy(data, az_grid, el, cell, alts, mask, fn)


def dop_section(surface: xr.DataArray, az_deg: Any, el_deg: Any, altitudes_m: Any, *,
                mask_deg: float = 5.0, chunks: Chunks = None,
                visibility_fn: VisibilityFn | None = None) -> xr.Dataset:
    """Number of visible satellites and DOPs on horizontal sections at absolute altitudes [m], per epoch.

    Altitudes are in the surface's vertical datum.

    Parameters
    ----------
    surface : xarray.DataArray
        ``(y, x)`` NaN-free surface heights [m], as in :func:`coverage_maps`.
    az_deg, el_deg : array_like or xarray.DataArray
        ``(time, sat)`` TRUE azimuth / elevation [deg], as in :func:`coverage_maps`.
    altitudes_m : float or array_like
        ``(altitude,)`` section altitudes [m], finite, non-empty.
    mask_deg : float, default 5.0
        Elevation mask [deg].
    chunks : int, tuple of int, "auto" or None, optional
        Dask blocks, as in :func:`coverage_maps`.
    visibility_fn : VisibilityFn, optional
        Default :func:`skyroute.stages.occlusion.visibility_heights_numpy`.

    Returns
    -------
    xarray.Dataset
        On ``(time, altitude, y, x)``: ``n_visible`` (int16) and ``gdop``, ``pdop``, ``hdop``,
        ``vdop``, ``tdop`` (float32; +inf with fewer than 4 visible satellites, NaN below the
        surface).

    Raises
    ------
    InputError
        When the surface or the satellite arrays are invalid (as :func:`coverage_maps`), or
        ``altitudes_m`` is empty, not 1-D or not finite.
    """
    cell, az, el, meta, mask, alts = _prepare_sections(surface, az_deg, el_deg, altitudes_m,
                                                      mask_deg)
    arr = _section_array(surface, az, el, cell, alts, mask, chunks, visibility_fn)
    t = meta.get("time")
    coords: dict[str, Any] = {"altitude": xr.DataArray(alts, dims="altitude", attrs={
        "units": "m", "long_name": "section altitude", **_spatial_attrs(surface)})}
    if t is not None:
        coords["time"] = t
    dims = ("time", "altitude", "y", "x")
    out = {"n_visible": _wrap(surface, arr[:, :, 0].astype(np.int16), dims, coords, "n_visible",
                              {"long_name": "number of satellites in line of sight above the mask",
                               "units": "1"})}
    for c, name in enumerate(DOP_KINDS):
        out[name.lower()] = _wrap(surface, arr[:, :, c + 1], dims, coords, name.lower(), {
            "long_name": name, "units": "1",
            "comment": "+inf with fewer than 4 visible satellites; NaN below the surface"})
    ds = xr.Dataset(out, attrs={"title": "DOP on horizontal sections", "mask_deg": mask,
                                **_window_attrs(meta, az.shape[0])})
    if surface.rio.crs is not None:
        ds = ds.rio.write_crs(surface.rio.crs)
    return ds


def dop_volume(surface: xr.DataArray, az_deg: Any, el_deg: Any, z_m: Any, *,
               dop: str = "PDOP", reduce: str | None = "max", mask_deg: float = 5.0,
               chunks: Chunks = None,
               visibility_fn: VisibilityFn | None = None) -> xr.DataArray:
    """3D DOP volume on ``(z, y, x)`` levels ``z_m`` [m] (the "digital morphing map" of seed 003).

    Its isosurface DOP = D is the coverage floor.

    Parameters
    ----------
    surface : xarray.DataArray
        ``(y, x)`` NaN-free surface heights [m], as in :func:`coverage_maps`.
    az_deg, el_deg : array_like or xarray.DataArray
        ``(time, sat)`` TRUE azimuth / elevation [deg], as in :func:`coverage_maps`.
    z_m : float or array_like
        ``(z,)`` levels [m] in the surface's vertical datum, finite, non-empty.
    dop : str, default "PDOP"
        DOP kind.
    reduce : {"max", None}, default "max"
        ``"max"`` gives the worst case over the epochs, ``None`` keeps a leading ``time`` dim.
    mask_deg : float, default 5.0
        Elevation mask [deg].
    chunks : int, tuple of int, "auto" or None, optional
        Dask blocks, as in :func:`coverage_maps`.
    visibility_fn : VisibilityFn, optional
        Default :func:`skyroute.stages.occlusion.visibility_heights_numpy`.

    Returns
    -------
    xarray.DataArray
        float32 ``(z, y, x)`` (or ``(time, z, y, x)``) DOP [-]: +inf with fewer than 4 visible
        satellites, NaN below the surface.

    Raises
    ------
    InputError
        When ``reduce`` is invalid, or the inputs are (as :func:`dop_section`).
    UnknownNameError
        When ``dop`` is not a DOP kind.

    References
    ----------
    Seed 003 (the digital morphing map).
    """
    kind = dop_kind_index(dop)
    if reduce not in ("max", None):
        raise InputError(f"reduce must be 'max' or None, got {reduce!r}")
    cell, az, el, meta, mask, alts = _prepare_sections(surface, az_deg, el_deg, z_m, mask_deg)
    arr = _section_array(surface, az, el, cell, alts, mask, chunks, visibility_fn)
    vol = arr[:, :, kind + 1]
    coords: dict[str, Any] = {"z": xr.DataArray(alts, dims="z", attrs={
        "units": "m", "long_name": "altitude", "axis": "Z", **_spatial_attrs(surface)})}
    dims: tuple[str, ...] = ("time", "z", "y", "x")
    if reduce == "max":
        vol = vol.max(axis=0)
        dims = dims[1:]
    elif meta.get("time") is not None:
        coords["time"] = meta["time"]
    return _wrap(surface, vol, dims, coords, DOP_KINDS[kind].lower(), {
        "long_name": f"{DOP_KINDS[kind]}" + (" (worst case over the window)" if reduce else ""),
        "units": "1", "mask_deg": mask, **_window_attrs(meta, az.shape[0]),
        "comment": "+inf with fewer than 4 visible satellites; NaN below the surface"})


def coverage_from_almanac(surface: xr.DataArray, almanac_paths: Any, start_utc: Any, *,
                          window_min: float = 20.0, step_min: float = 1.0,
                          mask_deg: float = 5.0, **kwargs: Any) -> xr.Dataset:
    """:func:`coverage_maps` with the satellite geometry of an almanac over a time window.

    Seen from the centre of the surface (far satellites: one geometry for the whole map), at the
    surface's median height.

    Parameters
    ----------
    surface : xarray.DataArray
        ``(y, x)`` surface heights [m] with CRS, as in :func:`coverage_maps`.
    almanac_paths : str, pathlib.Path or list of them
        The almanac file(s) (see :func:`skyroute.stages.almanac.sky_geometry`).
    start_utc : str, datetime.datetime or numpy.datetime64
        Start of the window [UTC] (anything :class:`numpy.datetime64` accepts).
    window_min : float, default 20.0
        Window length [min].
    step_min : float, default 1.0
        Epoch step [min].
    mask_deg : float, default 5.0
        Elevation mask [deg].
    **kwargs
        Go to :func:`coverage_maps` (thresholds, dop, floor_m, ceiling_m, chunks).

    Returns
    -------
    xarray.Dataset
        As :func:`coverage_maps`, with ``window_min`` and ``step_min`` attrs.

    Raises
    ------
    InputError
        When ``step_min <= 0`` or ``window_min < 0``, or as :func:`coverage_maps`.
    """
    from skyroute.stages.almanac import sky_geometry
    from skyroute.stages.grid import Grid

    grid = Grid.from_dataarray(surface)
    xmin, ymin, xmax, ymax = grid.bounds
    lon, lat = grid.to_lonlat((xmin + xmax) / 2, (ymin + ymax) / 2)
    h0 = float(np.nanmedian(np.asarray(surface.values)))
    times = window_times(start_utc, window_min, step_min)
    sky = sky_geometry(almanac_paths, times, float(lat), float(lon), h0, mask_deg=mask_deg)
    ds = coverage_maps(surface, sky["az_deg"], sky["el_deg"], mask_deg=mask_deg, **kwargs)
    ds.attrs.update({"window_min": float(window_min), "step_min": float(step_min)})
    return ds
