"""Compiled kernels of the numerical potential field (:mod:`skyroute.stages.planning.potential`).

Private to that module: the voxel arrays are flat C-order views of (nz, ny, nx) arrays, the
26 neighbour offsets are ``OFFS`` (dk, di, dj) with their lengths ``steps`` [m] given by the
caller.  Every kernel polls ``stop`` (a :class:`~skyroute.stages.control.StopFlag` array) and
returns early when it is set.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

OFFS = np.array([(dk, di, dj) for dk in (-1, 0, 1) for di in (-1, 0, 1) for dj in (-1, 0, 1)
                 if (dk, di, dj) != (0, 0, 0)], dtype=np.int64)
# index of the opposite offset: OFFS[OPP[o]] == -OFFS[o]
OPP = np.array([int(np.nonzero((OFFS == -OFFS[o]).all(axis=1))[0][0]) for o in range(26)], dtype=np.int64)
NO_PARENT = -1


@numba.njit(cache=True, inline="always")
def _move_ok(free, k, i, j, dk, di, dj, ny, nx):
    """No corner cutting: every voxel of the box spanned by the move (k, i, j) -> (k+dk, i+di,
    j+dj) is free (the straight segment between the two centres then stays inside free voxels;
    the target is checked by the caller)."""
    for a in range(2):
        for b in range(2):
            for c in range(2):
                if a * dk == 0 and b * di == 0 and c * dj == 0:
                    continue
                if a == 1 and b == 1 and c == 1:
                    continue
                u = ((k + a * dk) * ny + (i + b * di)) * nx + (j + c * dj)
                if free[u] == 0:
                    return False
    return True


# --------------------------------------------------------------------------- wave propagation


@intrinsic
def _prefetch(typingctx, arr, idx):
    """Hint the CPU to fetch ``arr[idx]`` into the caches (LLVM ``llvm.prefetch``, read, high
    locality); no effect on the results.  The wave is memory-latency bound: a voxel's 26
    neighbours span 9 cache lines of each array, fetched a few voxels ahead."""
    sig = types.void(arr, idx)

    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [args[1]], wraparound=False)
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]),
                                            "llvm.prefetch.p0")
        builder.call(fn, [builder.bitcast(ptr, i8p), ir.Constant(i32, 0), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return sig, codegen


@numba.njit(cache=True, inline="always")
def _bucket_push(buf, cnt, cap, sl, v):
    """Append voxel ``v`` to bucket slot ``sl`` of ``buf`` (nb, cap), doubling the capacity
    (a new array of the same dtype) when the slot is full; returns ``(buf, cap)``."""
    if cnt[sl] >= cap:
        buf2 = np.empty((buf.shape[0], 2 * cap), dtype=buf.dtype)
        buf2[:, :cap] = buf
        buf = buf2
        cap *= 2
    buf[sl, cnt[sl]] = v
    cnt[sl] += 1
    return buf, cap


@numba.njit(cache=True, parallel=True)
def _classify_kernel(free, nz, ny, nx, state):
    """state[v] = 1 blocked, 0 free with all 26 neighbours free (inside the box), 3 other free.
    Planes k in parallel, row by row: the AND of the 9 rows (k + dk, i + di) column by column,
    then of three consecutive columns (streaming, no per-voxel neighbour loop)."""
    for k in numba.prange(nz):
        col = np.empty(nx, dtype=np.uint8)
        for i in range(ny):
            base = (k * ny + i) * nx
            if k == 0 or k == nz - 1 or i == 0 or i == ny - 1 or nx < 3:
                for j in range(nx):
                    state[base + j] = 1 if free[base + j] == 0 else 3
                continue
            for j in range(nx):
                col[j] = 1 if free[base + j] != 0 else 0
            for dk in range(-1, 2):
                for di in range(-1, 2):
                    rb = base + (dk * ny + di) * nx
                    for j in range(nx):
                        col[j] = min(col[j], free[rb + j])    # col is 0 / 1: AND with "free != 0"
            for j in range(nx):
                if free[base + j] == 0:
                    state[base + j] = 1
                elif 0 < j < nx - 1 and (col[j - 1] & col[j] & col[j + 1]) != 0:
                    state[base + j] = 0
                else:
                    state[base + j] = 3


def wave_kernel(free, weight, nz, ny, nx, steps, seeds, U, parent, stop, target=-1):
    """Exact Dijkstra wave from ``seeds`` over the free voxels (26 neighbours, no corner
    cutting), with buckets of width q = the least edge cost (Dinitz): a voxel of bucket b
    cannot be improved by another voxel of bucket b (that would cost >= q more), so a bucket's
    voxels are settled together, every voxel once, in O(N * 26).  The kernel is indifferent to
    the axis order: (nz, ny, nx) are the three axes of the flat C-order arrays, ``steps`` in
    the matching offset order.

    ``free`` (N,) uint8; ``weight`` (N,) float32 > 0 per voxel (edge u-v costs
    ``steps[o] * (weight[u] + weight[v]) / 2``); ``U`` (N,) float64: inf except the seeds'
    start values (finite upper bounds elsewhere are allowed: the wave only lowers values, which
    makes it the incremental update too); ``parent`` (N,) int8: offset index towards the voxel a
    value came from (-1 for seeds).  ``target`` >= 0: stop once the bucket holding that voxel is
    settled (every voxel of lower potential is then final); the unsettled voxels get inf / -1
    (their tentative values are larger than the target's anyway).  Returns the number of voxels
    settled (-1 if stopped).  Bucket lists are int32 when N < 2^31 (half the memory traffic).
    A Python wrapper: the voxel classes come from a parallel kernel, which must be launched
    from Python (called from inside a cached compiled function, numba's thread pool may not be
    started: a crash)."""
    state = np.empty(free.size, dtype=np.uint8)
    _classify_kernel(free, nz, ny, nx, state)
    wtab = np.empty(2, dtype=np.float32)
    packed = _weight_bit(free, weight, state, wtab)
    like = np.empty(1, dtype=np.int32 if free.size < 2**31 - 2**20 else np.int64)
    return _wave(free, weight, int(nz), int(ny), int(nx), np.asarray(steps, dtype=np.float64), seeds, U, parent,
                 stop, int(target), like, state, packed, wtab)


@numba.njit(cache=True)
def _weight_bit(free, weight, state, wtab):
    """When the free voxels' weights take at most two values (the planner's: 1 on the
    skeleton, K off it): ``wtab`` = the two values, bit 3 of ``state`` set where the weight is
    ``wtab[1]``, returns True (the wave then reads a voxel's weight from its state byte, one
    array less in its random accesses); else False."""
    n = 0
    for v in range(free.size):
        if free[v] == 0:
            continue
        x = weight[v]
        if n == 0:
            wtab[0] = x
            wtab[1] = x
            n = 1
        elif x != wtab[0] and x != wtab[1]:
            if n == 2:
                return False
            wtab[1] = x
            n = 2
    if n == 2:
        for v in range(free.size):
            if free[v] != 0 and weight[v] == wtab[1]:
                state[v] |= 8
    return True


@numba.njit(cache=True)
def _wave(free, weight, nz, ny, nx, steps, seeds, U, parent, stop, target, like, state, packed, wtab):
    """:func:`wave_kernel` with bucket lists of ``like.dtype``; ``state`` (N,) uint8 from
    :func:`_classify_kernel` (overwritten); ``packed``: the weights are ``wtab[bit 3 of
    state]`` (:func:`_weight_bit`), else read from ``weight``.

    Per bucket: its voxels are marked settled (state 128 | class), sorted by index (memory
    locality; the order does not change the result, see the tie rule), then each relaxes its
    neighbours.  *Inner* voxels (all 26 neighbours free, inside the box) take the fast path:
    flat offsets ``off``, no bounds or corner checks, and a branch-free screen of the 26
    neighbours by the lower bound ``U[v] + steps/2 (w[v] + w_min) <= U[u]`` (it rejects the
    settled neighbours too); the neighbourhoods of the voxels a few places ahead are
    prefetched.  Other free voxels build a 27-bit mask of their free box neighbours: a move is
    allowed when the box it spans (``box[o]``) is all free.

    Tie rule (the parents are those of a serial Dijkstra settling buckets in increasing order
    and a bucket's voxels by increasing index, the first strict improvement winning): when a
    relaxation from ``v`` equals ``U[u]`` and that value was set by a relaxation of this wave
    (not an initial upper bound), ``u`` takes ``v`` as parent if its current parent was
    settled in the same bucket with a larger index.  The result does not depend on the
    settling order within a bucket."""
    N = free.size
    wmin = np.inf
    wmax = 0.0
    for v in range(N):
        if free[v] != 0:
            if weight[v] < wmin:
                wmin = weight[v]
            if weight[v] > wmax:
                wmax = weight[v]
    wmin32 = np.float32(wmin)
    q = steps.min() * wmin
    nb = int(math.ceil(steps.max() * wmax / q)) + 2
    cap = 1024
    buf = np.empty((nb, cap), dtype=like.dtype)
    cnt = np.zeros(nb, dtype=np.int64)
    off = np.empty(26, dtype=np.int64)           # flat offset of each move
    hc = np.empty(26)                            # half its length: cost = hc * (w[u] + w[v])
    box = np.empty(26, dtype=np.int64)           # bits (of the 27-cell neighbourhood) the move spans
    off27 = np.empty(27, dtype=np.int64)
    for o in range(27):
        off27[o] = ((o // 9 - 1) * ny + ((o // 3) % 3 - 1)) * nx + (o % 3 - 1)
    for oi in range(26):
        o = oi if oi < 13 else oi + 1
        dk = o // 9 - 1
        di = (o // 3) % 3 - 1
        dj = o % 3 - 1
        off[oi] = off27[o]
        hc[oi] = steps[oi] * 0.5
        m = 0
        for a in range(2):
            for b in range(2):
                for c in range(2):
                    m |= 1 << ((a * dk + 1) * 9 + (b * di + 1) * 3 + (c * dj + 1))
        box[oi] = m
    # state: 0 inner, 3 other free, 1 blocked; | 8 weight wtab[1] (packed); | 4 queued, | 32 value set
    # by a relaxation of this wave; 64 settled, 128 | class | weight bit: settled in the current bucket
    order = np.argsort(U[seeds])
    sp = 0
    nseeds = seeds.size
    queued = 0
    cur = 0
    nyx = ny * nx
    settled = 0
    while True:
        if queued == 0:
            while sp < nseeds and state[seeds[order[sp]]] >= 64:
                sp += 1
            if sp >= nseeds:
                break
            cur = int(math.floor(U[seeds[order[sp]]] / q))
        while sp < nseeds:                        # seeds inside the window [cur, cur + nb - 2]
            sv = seeds[order[sp]]
            if state[sv] >= 64:
                sp += 1
                continue
            b = int(math.floor(U[sv] / q))
            if b > cur + nb - 2:
                break
            if b < cur:
                b = cur
            buf, cap = _bucket_push(buf, cnt, cap, b % nb, sv)
            state[sv] |= 4
            queued += 1
            sp += 1
        slot = cur % nb
        m = cnt[slot]
        if m == 0:
            cur += 1
            continue
        cnt[slot] = 0
        queued -= m
        n = 0                                     # settle the bucket: unique, not yet settled
        for t in range(m):
            v = buf[slot, t]
            s = state[v]
            if s >= 64:
                continue
            state[v] = 128 | (s & 11)
            buf[slot, n] = v
            n += 1
        items = buf[slot, :n]
        items.sort()
        for t in range(n):
            v = items[t]
            if t + 6 < n:
                w2 = items[t + 6]
                for oi in range(1, 26, 3):       # the middle of each run of 3 neighbours
                    _prefetch(U, w2 + off[oi])
                    if not packed:
                        _prefetch(weight, w2 + off[oi])
                    _prefetch(state, w2 + off[oi])
            settled += 1
            if (settled & 0xFFFF) == 0 and stop[0] != 0:
                return -1
            Uv = U[v]
            wv = wtab[(state[v] >> 3) & 1] if packed else weight[v]
            lbv = wv + wmin32
            sel = 0                               # bit oi: move oi allowed and may improve / tie
            if (state[v] & 0xF7) == 128:
                for oi in range(26):
                    sel |= np.int64(Uv + hc[oi] * lbv <= U[v + off[oi]]) << oi
            else:
                k = v // nyx
                r = v - k * nyx
                i = r // nx
                j = r - i * nx
                msk = 0
                if 0 < k < nz - 1 and 0 < i < ny - 1 and 0 < j < nx - 1:
                    for o in range(27):
                        msk |= np.int64(free[v + off27[o]] != 0) << o
                else:
                    for o in range(27):
                        kk = k + o // 9 - 1
                        ii = i + (o // 3) % 3 - 1
                        jj = j + o % 3 - 1
                        if 0 <= kk < nz and 0 <= ii < ny and 0 <= jj < nx:
                            if free[v + off27[o]] != 0:
                                msk |= 1 << o
                for oi in range(26):
                    bx = box[oi]
                    if (msk & bx) == bx and Uv + hc[oi] * lbv <= U[v + off[oi]]:
                        sel |= 1 << oi
            for oi in range(26):
                if ((sel >> oi) & 1) == 0:
                    continue
                u = v + off[oi]
                su = state[u]
                if su >= 64:
                    continue
                Uu = U[u]
                c = Uv + hc[oi] * (wv + (wtab[(su >> 3) & 1] if packed else weight[u]))
                if c < Uu:
                    U[u] = c
                    parent[u] = 25 - oi           # offset from u back to v (opposite)
                    b = int(math.floor(c / q))
                    if b <= cur:
                        b = cur + 1
                    elif (su & 4) != 0 and b == int(math.floor(Uu / q)):
                        state[u] = su | 32
                        continue                  # already queued in that bucket: it reads U[u] when settled
                    state[u] = su | 36
                    buf, cap = _bucket_push(buf, cnt, cap, b % nb, u)
                    queued += 1
                elif c == Uu and (su & 32) != 0:  # tie rule (docstring)
                    pp = parent[u]
                    if pp >= 0:
                        p = u + off[pp]
                        if state[p] >= 128 and p > v:
                            parent[u] = 25 - oi
        for t in range(n):
            state[items[t]] = 64
        cur += 1
        if target >= 0 and state[target] >= 64:
            for v in range(N):
                if state[v] < 64:
                    U[v] = np.inf
                    parent[v] = -1
            break
    return settled


@numba.njit(cache=True, parallel=True)
def zfast_kernel(a, out):
    """``out[i, j, k] = a[k, i, j]``: a (nz, ny, nx) array with the levels made the fastest
    axis (ny, nx, nz), rows in parallel."""
    nz, ny, nx = a.shape
    for i in numba.prange(ny):
        for j in range(nx):
            for k in range(nz):
                out[i, j, k] = a[k, i, j]


@numba.njit(cache=True, parallel=True)
def zslow_kernel(U, parent, p2o, U_out, parent_out):
    """Back from :func:`zfast_kernel`'s order: ``U_out[k, i, j] = U[i, j, k]`` and the parent
    offset indices mapped by ``p2o`` (-1 kept), rows in parallel."""
    ny, nx, nz = U.shape
    for i in numba.prange(ny):
        for j in range(nx):
            for k in range(nz):
                U_out[k, i, j] = U[i, j, k]
                p = parent[i, j, k]
                parent_out[k, i, j] = p2o[p] if p >= 0 else -1


@numba.njit(cache=True)
def affected_kernel(parent, changed, nz, ny, nx, out):
    """``out[v] = 1`` when the parent chain of ``v`` reaches a voxel with ``changed != 0``
    (``v`` included), else 0: the voxels whose value may depend on a change.  Searched forward:
    from the changed voxels to their children in the parent tree (the neighbours ``u`` whose
    parent offset points back), depth first; O(N) for the scan of ``changed`` plus 26 x the
    affected voxels (instead of walking every voxel's chain)."""
    N = parent.size
    nyx = ny * nx
    m = 0
    for v in range(N):
        out[v] = 0
        if changed[v] != 0:
            m += 1
    stack = np.empty(max(m, 1024), dtype=np.int64)
    top = 0
    for v in range(N):
        if changed[v] != 0:
            out[v] = 1
            stack[top] = v
            top += 1
    while top > 0:
        top -= 1
        v = stack[top]
        k = v // nyx
        r = v - k * nyx
        i = r // nx
        j = r - i * nx
        for oi in range(26):
            o = oi if oi < 13 else oi + 1
            kk = k + o // 9 - 1
            ii = i + (o // 3) % 3 - 1
            jj = j + o % 3 - 1
            if kk < 0 or kk >= nz or ii < 0 or ii >= ny or jj < 0 or jj >= nx:
                continue
            u = (kk * ny + ii) * nx + jj
            if out[u] == 0 and parent[u] == 25 - oi:      # u's parent offset points back to v
                out[u] = 1
                if top >= stack.size:
                    s2 = np.empty(2 * stack.size, dtype=np.int64)
                    s2[:top] = stack[:top]
                    stack = s2
                stack[top] = u
                top += 1


# --------------------------------------------------------------------------- skeleton


@numba.njit(cache=True, parallel=True)
def ridge_kernel(free, D, nz, ny, nx, min_d, out):
    """``out[k, i, j] = 1`` for free voxels on a ridge of the clearance ``D``: along at least
    one of the 13 lines through the voxel, D is >= both line neighbours and > one of them (a
    neighbour that is not free or outside counts as lower), and D >= ``min_d``.  Row by row
    (k, i) in parallel, line by line, the columns j innermost (streaming, 11x faster than a
    voxel-by-voxel loop on the Helsinki bitmap; same result)."""
    for t in numba.prange(nz * ny):
        k = t // ny
        i = t - k * ny
        acc = np.zeros(nx, dtype=np.uint8)
        for o in range(13):
            dk = o // 9 - 1
            di = (o // 3) % 3 - 1
            dj = o % 3 - 1
            ka, ia = k + dk, i + di
            kb, ib = k - dk, i - di
            a_ok = 0 <= ka < nz and 0 <= ia < ny
            b_ok = 0 <= kb < nz and 0 <= ib < ny
            kac = min(max(ka, 0), nz - 1)
            iac = min(max(ia, 0), ny - 1)
            kbc = min(max(kb, 0), nz - 1)
            ibc = min(max(ib, 0), ny - 1)
            for j in range(nx):
                d = D[k, i, j]
                ja = j + dj
                jb = j - dj
                da = -1.0
                db = -1.0
                if a_ok and 0 <= ja < nx:
                    if free[kac, iac, ja] != 0:
                        da = D[kac, iac, ja]
                if b_ok and 0 <= jb < nx:
                    if free[kbc, ibc, jb] != 0:
                        db = D[kbc, ibc, jb]
                if d >= da and d >= db and (d > da or d > db):
                    acc[j] = 1
        for j in range(nx):
            out[k, i, j] = acc[j] if (free[k, i, j] != 0 and D[k, i, j] >= min_d) else 0


@numba.njit(cache=True)
def ascent_kernel(free, D, skel, nz, ny, nx, k, i, j, out):
    """Steepest ascent of ``D`` over the free 26 neighbours from (k, i, j) until a skeleton
    voxel or a local maximum; writes the visited flat indices to ``out``, returns their count."""
    n = 0
    out[n] = (k * ny + i) * nx + j
    n += 1
    while n < out.size and skel[k, i, j] == 0:
        best = D[k, i, j]
        bk, bi, bj = -1, -1, -1
        for o in range(27):
            dk = o // 9 - 1
            di = (o // 3) % 3 - 1
            dj = o % 3 - 1
            if dk == 0 and di == 0 and dj == 0:
                continue
            kk, ii, jj = k + dk, i + di, j + dj
            if 0 <= kk < nz and 0 <= ii < ny and 0 <= jj < nx and free[kk, ii, jj] != 0:
                if D[kk, ii, jj] > best:
                    best = D[kk, ii, jj]
                    bk, bi, bj = kk, ii, jj
        if bk < 0:
            break
        k, i, j = bk, bi, bj
        out[n] = (k * ny + i) * nx + j
        n += 1
    return n


@numba.njit(cache=True)
def descent_kernel(free, U, nz, ny, nx, v, out):
    """Gradient motion: from flat index ``v`` move to the free 26-neighbour of least ``U``
    while it is strictly lower; writes the visited indices to ``out``, returns their count."""
    nyx = ny * nx
    n = 0
    out[n] = v
    n += 1
    while n < out.size:
        k = v // nyx
        r = v - k * nyx
        i = r // nx
        j = r - i * nx
        best = U[v]
        bv = -1
        for o in range(27):
            dk = o // 9 - 1
            di = (o // 3) % 3 - 1
            dj = o % 3 - 1
            if dk == 0 and di == 0 and dj == 0:
                continue
            kk, ii, jj = k + dk, i + di, j + dj
            if 0 <= kk < nz and 0 <= ii < ny and 0 <= jj < nx:
                u = (kk * ny + ii) * nx + jj
                if free[u] != 0 and U[u] < best and _move_ok(free, k, i, j, dk, di, dj, ny, nx):
                    best = U[u]
                    bv = u
        if bv < 0:
            break
        v = bv
        out[n] = v
        n += 1
    return n


@numba.njit(cache=True)
def segment_clearance_kernel(a, bs, free, D, x0, y1, z0, h, dz, nz, ny, nx, step, out):
    """For each segment a -> bs[m] [m]: the least ``D`` over the voxels met at samples every
    ``step`` [m] (a voxel that is not free or outside counts 0); the end points themselves are
    not sampled (the start / goal may sit in a partly blocked voxel)."""
    for m in range(bs.shape[0]):
        dx = bs[m, 0] - a[0]
        dy = bs[m, 1] - a[1]
        dzz = bs[m, 2] - a[2]
        L = math.sqrt(dx * dx + dy * dy + dzz * dzz)
        ns = max(1, int(math.ceil(L / step)))
        best = np.inf
        for s in range(1, ns):
            t = s / ns
            x = a[0] + t * dx
            y = a[1] + t * dy
            z = a[2] + t * dzz
            j = int(math.floor((x - x0) / h))
            i = int(math.floor((y1 - y) / h))
            k = int(math.floor((z - z0) / dz))
            d = 0.0
            if 0 <= k < nz and 0 <= i < ny and 0 <= j < nx and free[k, i, j] != 0:
                d = D[k, i, j]
            if d < best:
                best = d
        out[m] = best


@numba.njit(cache=True)
def reseed_kernel(free, weight, U, parent, nz, ny, nx, steps, cand, blocked_from):
    """For each flat index in ``cand`` (free voxels): lower ``U`` / set ``parent`` from the best
    free 26-neighbour not flagged in ``blocked_from`` (``U[n] + edge cost``).  Returns the
    candidates with a finite value (the seeds of the incremental wave)."""
    nyx = ny * nx
    out = np.empty(cand.size, dtype=np.int64)
    m = 0
    for t in range(cand.size):
        v = cand[t]
        if free[v] == 0:
            continue
        k = v // nyx
        r = v - k * nyx
        i = r // nx
        j = r - i * nx
        for o in range(27):
            if o == 13:
                continue
            kk = k + o // 9 - 1
            ii = i + (o // 3) % 3 - 1
            jj = j + o % 3 - 1
            if kk < 0 or kk >= nz or ii < 0 or ii >= ny or jj < 0 or jj >= nx:
                continue
            u = (kk * ny + ii) * nx + jj
            if free[u] == 0 or blocked_from[u] != 0 or not np.isfinite(U[u]):
                continue
            if not _move_ok(free, k, i, j, o // 9 - 1, (o // 3) % 3 - 1, o % 3 - 1, ny, nx):
                continue
            oi = o if o < 13 else o - 1
            c = U[u] + steps[oi] * 0.5 * (weight[v] + weight[u])
            if c < U[v]:
                U[v] = c
                parent[v] = oi                    # offset from v to u
        if np.isfinite(U[v]):
            out[m] = v
            m += 1
    return out[:m]


@numba.njit(cache=True)
def neighbours_kernel(idx, nz, ny, nx, out):
    """``out[u] = 1`` for every voxel in ``idx`` and its 26 neighbours."""
    nyx = ny * nx
    for t in range(idx.size):
        v = idx[t]
        k = v // nyx
        r = v - k * nyx
        i = r // nx
        j = r - i * nx
        for o in range(27):
            kk = k + o // 9 - 1
            ii = i + (o // 3) % 3 - 1
            jj = j + o % 3 - 1
            if 0 <= kk < nz and 0 <= ii < ny and 0 <= jj < nx:
                out[(kk * ny + ii) * nx + jj] = 1


# --------------------------------------------------------------------------- Euclidean distance transform


@numba.njit(cache=True, inline="always")
def _line_scratch(n):
    """The line ``f`` (n), the scratch of :func:`_edt_line` and its output ``o`` (n)."""
    return (np.empty(n), np.empty(n + 2), np.empty(n + 2), np.empty(n + 2, dtype=np.int64), np.empty(n + 3),
            np.empty(n))


@numba.njit(cache=True, inline="always")
def _edt_line(f, n, h2, lo_wall, hi_wall, pos, val, v, z, out):
    """Exact 1-D squared distance transform (Felzenszwalb-Huttenlocher lower envelope of
    parabolas): ``out[p] = min_q h2 (p - q)^2 + f[q]`` over the finite ``f[q]`` and, when
    flagged, obstacle sites (value 0) just outside the line at -1 / n.  ``h2``: squared
    spacing [m^2]; ``pos`` / ``val`` / ``v`` (n + 2) and ``z`` (n + 3): scratch."""
    m = 0
    if lo_wall:
        pos[m] = -1.0
        val[m] = 0.0
        m += 1
    for q in range(n):
        if f[q] < np.inf:
            pos[m] = q
            val[m] = f[q]
            m += 1
    if hi_wall:
        pos[m] = n
        val[m] = 0.0
        m += 1
    if m == 0:
        for p in range(n):
            out[p] = np.inf
        return
    k = 0
    v[0] = 0
    z[0] = -np.inf
    z[1] = np.inf
    for s in range(1, m):
        a = val[s] + h2 * pos[s] * pos[s]
        while True:
            r = v[k]
            x = (a - (val[r] + h2 * pos[r] * pos[r])) / (2.0 * h2 * (pos[s] - pos[r]))
            if x <= z[k] and k > 0:
                k -= 1
            else:
                break
        if x <= z[k]:           # k == 0: the new parabola is lower everywhere
            v[0] = s
            z[1] = np.inf
            continue
        k += 1
        v[k] = s
        z[k] = x
        z[k + 1] = np.inf
    k = 0
    for p in range(n):
        while z[k + 1] < p:
            k += 1
        r = v[k]
        d = p - pos[r]
        out[p] = h2 * d * d + val[r]


@numba.njit(cache=True, parallel=True)
def edt_kernel(obstacle, dz, h, north, south, west, east, out):
    """Exact Euclidean distance [m] from each voxel centre of ``obstacle`` (nz, ny, nx) bool to
    the nearest obstacle voxel centre (voxel sizes ``dz`` x ``h`` x ``h`` [m]), obstacle walls
    one voxel beyond the flagged sides (north = row -1, south = row ny, west = column -1, east =
    column nx); written to ``out`` (nz, ny, nx) float32 (inf when there is no obstacle at all).
    Separable: squared transforms along x, then y, then z, each line in parallel."""
    nz, ny, nx = obstacle.shape
    g = np.empty((nz, ny, nx))
    h2 = h * h
    for t in numba.prange(nz * ny):           # along x (rows), walls west / east
        k = t // ny
        i = t - k * ny
        f, pos, val, v, zz, o = _line_scratch(nx)
        for j in range(nx):
            f[j] = 0.0 if obstacle[k, i, j] else np.inf
        _edt_line(f, nx, h2, west, east, pos, val, v, zz, o)
        for j in range(nx):
            g[k, i, j] = o[j]
    for t in numba.prange(nz * nx):           # along y (columns), walls north / south
        k = t // nx
        j = t - k * nx
        f, pos, val, v, zz, o = _line_scratch(ny)
        for i in range(ny):
            f[i] = g[k, i, j]
        _edt_line(f, ny, h2, north, south, pos, val, v, zz, o)
        for i in range(ny):
            g[k, i, j] = o[i]
    d2 = dz * dz
    for t in numba.prange(ny):                # along z (levels), no walls
        f, pos, val, v, zz, o = _line_scratch(nz)
        for j in range(nx):
            for k in range(nz):
                f[k] = g[k, t, j]
            _edt_line(f, nz, d2, False, False, pos, val, v, zz, o)
            for k in range(nz):
                out[k, t, j] = math.sqrt(o[k])
