"""An admissible lower bound of the energy [J] of every plan of a problem (issue 36): refusals
before the search.

STEP I used to find out that a mission cannot be flown on its battery by planning it: three
complete searches with a growing w_l (seed 000 III-A.3), 50-80 s for a refused 13.7 km city
mission.  :func:`energy_lower_bound` bounds the energy E_w of EVERY flyable polygonal chain from
the start to the goal from below, in about a second, so that :func:`~.step1.plan_step1` refuses
the level before any search when even the bound exceeds the usable battery.

The bound reuses the energy model of :mod:`skyroute.stages.energy` through
:func:`~skyroute.stages.planning.kernels.segment_eval`'s rules (eq. 3 ground speed, the rotor
power of :func:`~skyroute.stages.energy.power_kernel`): a sub-segment of length ds, unit
direction d, flown in the wind w sampled at its start, costs ``ds * e(d, w)`` with
``e = P(g d - w) / g`` [J/m] (g the ground speed of eq. 3), and E_w is the sum over the
sub-segments.

Energy per metre of progress
----------------------------
For a horizontal unit vector u (one of :data:`N_PROGRESS` azimuths) and a set W of winds let

    t_W(u) = min over w in W, flyable directions d with u . d_h > 0 of  e(d, w) / (u . d_h)

(d_h the horizontal part of d; every flight-path angle allowed).  Since e > 0, every
sub-segment whose wind is in W costs ``ds e >= t_W(u) (u . ds d)``: a piece of path whose winds
are all in W costs at least ``t_W(u)`` times its progress along u, whatever its shape and
altitudes.  The minimum over d is taken over :data:`N_AZIMUTHS` x :data:`N_GAMMAS` sampled
directions plus, at each flight-path angle, the two azimuths where eq. 3 leaves v_c for the
m_- root (the minimum often lies on that edge: without them 72 azimuths were 6 % above the
fine minimum, 1152 still 0.4 %), and the winds of a wind-level gap over
:data:`~.heuristic.WIND_INTERP_SAMPLES` samples, so the rates are multiplied by
:data:`ENERGY_BOUND_SAFETY` (as the A* heuristic's sampled bounds are, :mod:`.heuristic`).

Where the path can fly
----------------------
The winds a path can meet in a coarse cell (about :data:`~.multires.COARSE_CELL_M` = 64 m,
as the multi-resolution search's) are those of the wind columns overlapping it at
heights above ground between the LOWEST floor and the HIGHEST ceiling of its admissible grid
cells (floor finite and <= ceiling) -- not the calm wind at ground level, which the map-wide
bounds of :mod:`.heuristic` must include.  A coarse cell without an admissible grid cell holds no
point of a flyable path.

The ring recursion
------------------
Let N(C) be the block of Chebyshev radius ``ring - 1`` coarse cells around cell C and T(C) the
rates over the winds of the block of radius ``ring`` (which also holds the start of every
sub-segment ending in N(C): a sub-segment is shorter than a coarse cell).  A path from a point
p of C to a goal outside N(C) leaves N(C) for the first time at a point p' of an admissible cell
C' of the ring at Chebyshev distance ``ring``; the piece p -> p' costs at least
``T(C)(u) * min over p in C, p' in C' of u . (p' - p)``.  So

    phi(C) = min over admissible ring cells C' of  [T(C)(u_CC') prog(C, C') + phi(C')],
    phi(C) = 0 when the goal's cell is in N(C),

is a lower bound of the energy of every path from C to the goal: a Dijkstra from the goal over
the coarse cells (:func:`_ring_dijkstra_kernel`).  The bound of the problem is the larger of
phi(start cell) and the straight-line bound ``t_all(u) u . (goal - start)`` (rates over every
cell).  Each ring step loses at most one coarse cell of progress out of ``ring``
(:data:`RING_CELLS`); obstacles narrower than the ring are jumped over (the bound stays a lower
bound); climbs count nothing.  The bound only ever refuses: a plan that flies needs at least
its energy, so no plan that would have been accepted is changed
(``tests/test_energy_refusal.py``: the bound against the plans A* finds over random missions,
winds and batteries).
"""

from __future__ import annotations

import heapq
import math
import time

import numba
import numpy as np

from skyroute.stages.energy import eq3_ground_speed, power_kernel
from skyroute.stages.planning.heuristic import WIND_INTERP_SAMPLES
from skyroute.stages.vehicle import FixedWingProfile

__all__ = ["ENERGY_BOUND_SAFETY", "N_AZIMUTHS", "N_GAMMAS", "N_PROGRESS", "RING_CELLS", "energy_lower_bound",
           "progress_rates"]

N_PROGRESS = 32            # progress directions u (horizontal azimuths) of the rates [-]
N_AZIMUTHS = 36            # sampled azimuths of the flight direction d (10 degrees apart) [-]
N_GAMMAS = 5               # sampled flight-path angles of d: -max, -max/2, 0, max/2, max [-]
# margin of the rates for directions and winds between their samples [-]: with the v_max edge
# directions (_progress_rates_kernel) the sampled rates of 36 x 5 directions were at most 1.6 %
# (M300) / 0.9 % (FlyCart 30) above those of 2304 x 9 over 3000 random winds up to 15 m/s
ENERGY_BOUND_SAFETY = 0.95
RING_CELLS = 8             # Chebyshev radius [coarse cells] of a step of the ring recursion


def _progress_dirs() -> np.ndarray:
    a = 2.0 * math.pi * np.arange(N_PROGRESS) / N_PROGRESS
    return np.ascontiguousarray(np.stack([np.cos(a), np.sin(a)], axis=1))


def _gammas(max_sin: float) -> np.ndarray:
    """The sampled flight-path angles [rad]: :data:`N_GAMMAS` from -max to max."""
    gmax = math.asin(min(max(max_sin, 0.0), 1.0))
    return np.linspace(-gmax, gmax, N_GAMMAS) if N_GAMMAS > 1 else np.zeros(1)


@numba.njit(cache=True, nogil=True)
def _block_heights_kernel(floor, ceiling, terrain, f, lo, hi):   # pragma: no cover - compiled
    """Per block of ``f`` x ``f`` grid cells (the last ones hold the cells left over): ``lo`` the
    lowest ``floor - terrain`` and ``hi`` the highest ``ceiling - terrain`` [m] over its
    admissible cells (floor finite and <= ceiling); +inf / -inf without one.  One pass, no
    full-size temporaries."""
    nby, nbx = lo.shape
    ny, nx = floor.shape
    for bi in range(nby):
        for bj in range(nbx):
            a = np.inf
            b = -np.inf
            for r in range(bi * f, min(bi * f + f, ny)):
                for c in range(bj * f, min(bj * f + f, nx)):
                    fl = floor[r, c]
                    ce = ceiling[r, c]
                    if math.isfinite(fl) and fl <= ce + 1e-9:
                        t = terrain[r, c]
                        if fl - t < a:
                            a = fl - t
                        if ce - t > b:
                            b = ce - t
            lo[bi, bj] = a
            hi[bi, bj] = b


@numba.njit(cache=True, nogil=True)
def _column_winds_kernel(uvw, z_agl, h_lo, h_hi, per_gap, out, count):   # pragma: no cover - compiled
    """Per wind column (r, c) with ``h_lo[r, c] <= h_hi[r, c]`` [m above ground]: the winds of
    :func:`~.kernels.wind_at` at the heights ``h_lo``, ``h_hi``, the levels between them and
    ``per_gap - 1`` evenly spaced heights of each level gap's part inside [h_lo, h_hi]
    (clamped at the lowest / highest level as wind_at), into ``out[r, c, :count[r, c]]``."""
    nz, ny, nx, _ = uvw.shape
    for r in range(ny):
        for c in range(nx):
            lo, hi = h_lo[r, c], h_hi[r, c]
            n = 0
            if not lo <= hi:
                count[r, c] = 0
                continue
            if nz == 1:
                for j in range(3):
                    out[r, c, 0, j] = uvw[0, r, c, j]
                count[r, c] = 1
                continue
            # heights: lo, hi, the levels inside, and per_gap - 1 interior points per gap part
            m = 0
            hs = np.empty(2 + nz + (nz - 1) * (per_gap - 1))
            hs[m] = lo
            m += 1
            hs[m] = hi
            m += 1
            for k in range(nz):
                if lo < z_agl[k] < hi:
                    hs[m] = z_agl[k]
                    m += 1
            for k in range(nz - 1):
                a = max(lo, z_agl[k])
                b = min(hi, z_agl[k + 1])
                if b > a:
                    for i in range(1, per_gap):
                        hs[m] = a + (b - a) * i / per_gap
                        m += 1
            for i in range(m):
                h = hs[i]
                k0 = np.searchsorted(z_agl, h, side="right") - 1
                k0 = min(max(k0, 0), nz - 2)
                f = (h - z_agl[k0]) / (z_agl[k0 + 1] - z_agl[k0])
                f = min(max(f, 0.0), 1.0)
                for j in range(3):
                    out[r, c, n, j] = uvw[k0, r, c, j] * (1 - f) + uvw[k0 + 1, r, c, j] * f
                n += 1
            count[r, c] = n


@numba.njit(cache=True, nogil=True)
def _rate_update(sx, sy, sz, u, v, w, udirs, vehicle, power, va, vs, vz, pw, best):   # pragma: no cover
    """``best[k]`` = min(best[k], e(d, w) / (udirs[k] . d_h)) over the k with udirs[k] . d_h > 0,
    e = P / g [J/m] of the unit direction d = (sx, sy, sz) in the wind (u, v, w) by eq. 3 and the
    rotor power (the rules of :func:`~.kernels.segment_eval`; nothing when not flyable)."""
    vc, vmax, vmin = vehicle.cruise_speed_mps, vehicle.max_airspeed_mps, vehicle.min_ground_speed_mps
    g = eq3_ground_speed(sx, sy, sz, u, v, w, vc, vmax)
    if math.isnan(g) or g < vmin or g <= 0:
        return
    va[0, 0], va[0, 1], va[0, 2] = g * sx - u, g * sy - v, g * sz - w
    vs[0] = va[0, 0] * sx + va[0, 1] * sy + va[0, 2] * sz
    vz[0] = g * sz
    power_kernel(va, vs, vz, power, pw)
    e = pw[0, 4] / g
    for k in range(udirs.shape[0]):
        p = udirs[k, 0] * sx + udirs[k, 1] * sy
        if p > 1e-12:
            q = e / p
            if q < best[k]:
                best[k] = q


@numba.njit(cache=True, nogil=True, parallel=True)
def _progress_rates_kernel(winds, gammas, n_az, udirs, vehicle, power, out):   # pragma: no cover - compiled
    """``out[i, k]`` = min over the flyable sampled directions d with ``udirs[k] . d_h > 0`` of
    ``e(d, winds[i]) / (udirs[k] . d_h)`` [J/m] (:func:`_rate_update`); inf when none.  The
    directions: ``n_az`` azimuths at each flight-path angle of ``gammas`` [rad], and at each
    angle the two azimuths where the tentative airspeed ``|v_c d - w|`` reaches v_max, just
    inside (eq. 3's ground speed drops from v_c to the m_- root there: the minimum is often on
    that edge, which a fixed set of azimuths would only approach)."""
    vc, vmax = vehicle.cruise_speed_mps, vehicle.max_airspeed_mps
    wmax = vehicle.max_wind_mps
    nw, nu = winds.shape[0], udirs.shape[0]
    for i in numba.prange(nw):
        va = np.empty((1, 3))
        vs = np.empty(1)
        vz = np.empty(1)
        pw = np.empty((1, 8))
        best = np.full(nu, np.inf)
        u, v, w = winds[i, 0], winds[i, 1], winds[i, 2]
        if math.sqrt(u * u + v * v + w * w) <= wmax:
            wh = math.sqrt(u * u + v * v)
            phw = math.atan2(v, u)
            for gi in range(gammas.shape[0]):
                cg, sg = math.cos(gammas[gi]), math.sin(gammas[gi])
                for j in range(n_az):
                    a = 2.0 * math.pi * j / n_az
                    _rate_update(cg * math.cos(a), cg * math.sin(a), sg, u, v, w, udirs, vehicle, power,
                                 va, vs, vz, pw, best)
                # |v_c d - w|^2 = v_max^2  <=>  d . w = (v_c^2 + |w|^2 - v_max^2) / (2 v_c)
                if wh * cg > 0:
                    x = ((vc * vc + u * u + v * v + w * w - vmax * vmax) / (2.0 * vc) - w * sg) / (wh * cg)
                    if -1.0 < x < 1.0:
                        half = math.acos(x) * (1.0 - 1e-9)     # inside: |v_c d - w| <= v_max
                        for sgn in (-1.0, 1.0):
                            a = phw + sgn * half
                            _rate_update(cg * math.cos(a), cg * math.sin(a), sg, u, v, w, udirs, vehicle, power,
                                         va, vs, vz, pw, best)
        for k in range(nu):
            out[i, k] = best[k]


@numba.njit(cache=True, nogil=True)
def _cell_rates_kernel(col_rates, valid, cx0, cy1, cres, wx0, wy1, wres, out):   # pragma: no cover - compiled
    """``out[r, c]`` (n_u,) = min of ``col_rates`` (ny_w, nx_w, n_u) over the wind columns that
    overlap the admissible coarse cell (r, c) (extent x0 + [c, c+1] res, y1 - [r+1, r] res,
    boundaries included); inf elsewhere."""
    ny, nx, nu = out.shape
    wny, wnx = col_rates.shape[0], col_rates.shape[1]
    for r in range(ny):
        for c in range(nx):
            for k in range(nu):
                out[r, c, k] = np.inf
            if not valid[r, c]:
                continue
            c0 = min(max(int(math.floor((cx0 + c * cres - wx0) / wres)), 0), wnx - 1)
            c1 = min(max(int(math.floor((cx0 + (c + 1) * cres - wx0) / wres)), 0), wnx - 1)
            r0 = min(max(int(math.floor((wy1 - (cy1 - r * cres)) / wres)), 0), wny - 1)
            r1 = min(max(int(math.floor((wy1 - (cy1 - (r + 1) * cres)) / wres)), 0), wny - 1)
            for wr in range(r0, r1 + 1):
                for wc in range(c0, c1 + 1):
                    for k in range(nu):
                        if col_rates[wr, wc, k] < out[r, c, k]:
                            out[r, c, k] = col_rates[wr, wc, k]


@numba.njit(cache=True, nogil=True)
def _ring_dijkstra_kernel(rates, valid, straight, goal_rc, start_rc, offs, ku, prog, near):   # pragma: no cover
    """phi (ny, nx) of the module docstring's ring recursion, Dijkstra from the goal cell
    ``goal_rc``, stopped when ``start_rc`` is settled: ``rates`` (ny, nx, n_u) [J/m] the block
    minima T, ``straight`` (ny, nx) [J] the straight-line bound of each cell (phi is the larger
    of it and the recursion: max(w + phi', s) is non-decreasing in phi' and >= it, so the
    labels still settle in order), ``offs`` (m, 2) the ring offsets (dr, dc) from C to C',
    ``ku`` (m,) their progress direction, ``prog`` (m,) [m] their least progress, ``near`` the
    radius of N(C) [cells]."""
    ny, nx = valid.shape
    phi = np.full((ny, nx), np.inf)
    done = np.zeros((ny, nx), np.bool_)
    gr, gc = goal_rc
    heap = [(0.0, np.int64(0))]
    heap.pop()
    for r in range(max(0, gr - near), min(ny, gr + near + 1)):
        for c in range(max(0, gc - near), min(nx, gc + near + 1)):
            if valid[r, c]:
                phi[r, c] = straight[r, c]
                heap.append((straight[r, c], np.int64(r * nx + c)))
    heapq.heapify(heap)
    sr, sc = start_rc
    while len(heap) > 0:
        d, idx = heapq.heappop(heap)
        r = idx // nx
        c = idx - r * nx
        if done[r, c]:
            continue
        done[r, c] = True
        if r == sr and c == sc:
            break
        for m in range(offs.shape[0]):        # predecessors C = C' - offset
            pr = r - offs[m, 0]
            pc = c - offs[m, 1]
            if pr < 0 or pc < 0 or pr >= ny or pc >= nx or done[pr, pc] or not valid[pr, pc]:
                continue
            t = rates[pr, pc, ku[m]]
            if not t < np.inf:
                continue
            nd = max(d + t * prog[m], straight[pr, pc])
            if nd < phi[pr, pc]:
                phi[pr, pc] = nd
                heapq.heappush(heap, (nd, np.int64(pr * nx + pc)))
    return phi


def _ring(ring: int, cell_m: float, udirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The offsets (dr, dc) (m, 2) of the cells at Chebyshev distance ``ring``, the index of the
    progress direction nearest to each (map x east = +dc, y north = -dr), and the least
    progress [m] along it between two cells of side ``cell_m`` [m] at that offset."""
    offs = np.array([(dr, dc) for dr in range(-ring, ring + 1) for dc in range(-ring, ring + 1)
                     if max(abs(dr), abs(dc)) == ring], dtype=np.int64)
    vec = np.stack([offs[:, 1], -offs[:, 0]], axis=1).astype(float) * cell_m
    ku = np.argmax(vec @ udirs.T, axis=1).astype(np.int64)
    u = udirs[ku]
    prog = np.einsum("ij,ij->i", vec, u) - cell_m * (np.abs(u[:, 0]) + np.abs(u[:, 1]))
    return offs, ku, np.maximum(prog, 0.0)


def _distinct_winds(flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(codes (n,), winds (m, 3)): the distinct rows of ``flat`` (n, 3) [m/s] and the row of
    each, ``winds[codes] == flat`` exactly (hashed on their bits, checked; pandas' exact
    MultiIndex on a hash collision)."""
    import pandas as pd

    bits = np.ascontiguousarray(flat).view(np.uint64)
    key = bits[:, 0] ^ (bits[:, 1] * np.uint64(0x9E3779B97F4A7C15)) ^ (bits[:, 2] * np.uint64(0xC2B2AE3D27D4EB4F))
    codes, uniq = pd.factorize(key)
    first = np.full(uniq.size, -1, np.int64)
    first[codes[::-1]] = np.arange(codes.size - 1, -1, -1)       # the first row of each code
    winds = np.ascontiguousarray(flat[first])
    if not np.array_equal(winds[codes].view(np.uint64), bits):    # a collision: exact, slower
        mi = pd.MultiIndex.from_arrays([flat[:, 0], flat[:, 1], flat[:, 2]])
        codes, uniq = mi.factorize()
        winds = np.ascontiguousarray(np.column_stack([np.asarray(uniq.get_level_values(i), np.float64)
                                                      for i in range(3)]))
    return np.ascontiguousarray(codes, dtype=np.int64), winds


@numba.njit(cache=True, nogil=True)
def _column_min_kernel(rates, codes, count, out):   # pragma: no cover - compiled
    """``out[j]`` = min over the ``count[j]`` consecutive samples of column j (their rows of
    ``rates`` by ``codes``), inf without one."""
    i = 0
    for j in range(count.shape[0]):
        for k in range(out.shape[1]):
            out[j, k] = np.inf
        for _ in range(count[j]):
            c = codes[i]
            for k in range(out.shape[1]):
                if rates[c, k] < out[j, k]:
                    out[j, k] = rates[c, k]
            i += 1


def progress_rates(problem, factor: int) -> dict:
    """The energy per metre of progress of the module docstring per coarse cell.

    Parameters
    ----------
    problem : PlanningProblem
        A rotorcraft problem.
    factor : int
        Grid cells per coarse cell side (:func:`~.multires.coarse_factor`).

    Returns
    -------
    dict
        ``rates`` (ny_c, nx_c, N_PROGRESS) [J/m] (times :data:`ENERGY_BOUND_SAFETY`; inf in a
        cell without an admissible grid cell or without a flyable wind), ``valid`` (ny_c, nx_c)
        bool (the cell has an admissible grid cell), ``udirs`` (N_PROGRESS, 2) [-],
        ``cell_m`` [m], ``n_winds`` (distinct winds evaluated).
    """
    f = int(factor)
    g = problem.grid
    shape = (-(-g.ny // f), -(-g.nx // f))
    h_lo_c = np.empty(shape)                      # the lowest floor above ground per coarse cell [m]
    h_hi_c = np.empty(shape)                      # the highest ceiling above ground [m]
    _block_heights_kernel(problem.floor_m, problem.ceiling_m, problem.terrain_m, f, h_lo_c, h_hi_c)
    valid = h_lo_c <= h_hi_c
    cres = g.resolution_m * f
    wg = problem.wind_grid
    wres = wg.resolution_m
    uvw = problem.wind_uvw
    nz, wny, wnx, _ = uvw.shape
    # per wind column: the union of the height ranges of the coarse cells overlapping it
    col_lo = np.full((wny, wnx), np.inf)
    col_hi = np.full((wny, wnx), -np.inf)
    rr, cc = np.nonzero(valid)
    if rr.size:
        c0 = np.clip(np.floor((g.x0 + cc * cres - wg.x0) / wres).astype(np.int64), 0, wnx - 1)
        c1 = np.clip(np.floor((g.x0 + (cc + 1) * cres - wg.x0) / wres).astype(np.int64), 0, wnx - 1)
        r0 = np.clip(np.floor((wg.y1 - (g.y1 - rr * cres)) / wres).astype(np.int64), 0, wny - 1)
        r1 = np.clip(np.floor((wg.y1 - (g.y1 - (rr + 1) * cres)) / wres).astype(np.int64), 0, wny - 1)
        span = int(max((c1 - c0).max(), (r1 - r0).max())) + 1
        for i in range(span):
            for j in range(span):
                m = (r0 + i <= r1) & (c0 + j <= c1)
                np.minimum.at(col_lo, (r0[m] + i, c0[m] + j), h_lo_c[rr[m], cc[m]])
                np.maximum.at(col_hi, (r0[m] + i, c0[m] + j), h_hi_c[rr[m], cc[m]])
    per_gap = int(WIND_INTERP_SAMPLES)
    nmax = 2 + nz + (nz - 1) * (per_gap - 1)
    samples = np.zeros((wny, wnx, nmax, 3))
    count = np.zeros((wny, wnx), np.int64)
    _column_winds_kernel(np.ascontiguousarray(uvw), np.ascontiguousarray(problem.wind_z_agl_m), col_lo, col_hi,
                         per_gap, samples, count)
    keep = np.arange(nmax)[None, None, :] < count[:, :, None]
    flat = samples[keep]
    udirs = _progress_dirs()
    col_rates = np.full((wny, wnx, N_PROGRESS), np.inf)
    n_winds = 0
    if flat.shape[0]:
        codes, winds = _distinct_winds(flat)
        n_winds = winds.shape[0]
        _, _, veh, power = problem.seg_args
        wr = np.empty((n_winds, N_PROGRESS))
        _progress_rates_kernel(winds, _gammas(veh.max_sin_path_angle), N_AZIMUTHS, udirs, veh, power, wr)
        _column_min_kernel(wr, codes, count.ravel(), col_rates.reshape(-1, N_PROGRESS))
    rates = np.empty(valid.shape + (N_PROGRESS,))
    _cell_rates_kernel(col_rates, valid, float(g.x0), float(g.y1), float(cres), float(wg.x0), float(wg.y1),
                       float(wres), rates)
    return {"rates": rates * ENERGY_BOUND_SAFETY, "valid": valid, "udirs": udirs, "cell_m": float(cres),
            "n_winds": int(n_winds)}


def energy_lower_bound(problem, factor: int | None = None, ring: int = RING_CELLS) -> dict:
    """A lower bound [J] of the energy E_w of every flyable chain from ``problem``'s start to
    its goal (module docstring).

    Parameters
    ----------
    problem : PlanningProblem
        The problem of one coverage level.
    factor : int, optional
        Grid cells per coarse cell side; default the nearest to
        :data:`~.multires.COARSE_CELL_M` (64 m), doubled while a coarse cell would be shorter
        than a sub-segment.
    ring : int, default :data:`RING_CELLS`
        Chebyshev radius [coarse cells] of a ring step, >= 2.

    Returns
    -------
    dict
        ``bound_j`` [J] (0 for a fixed-wing vehicle, which this rotor model does not bound;
        inf when no chain of admissible cells joins the endpoints), ``ring_j`` (the ring
        recursion's) and ``straight_j`` (the straight-line bound's) [J], ``cell_m`` [m],
        ``n_winds``, ``compute_s`` [s].
    """
    from skyroute.stages.planning.multires import COARSE_CELL_M

    t0 = time.perf_counter()
    if isinstance(problem.vehicle, FixedWingProfile):
        return {"bound_j": 0.0, "ring_j": 0.0, "straight_j": 0.0, "cell_m": math.nan, "n_winds": 0,
                "compute_s": time.perf_counter() - t0}
    ring = max(2, int(ring))
    res = problem.grid.resolution_m
    f = int(factor) if factor is not None else max(1, int(round(COARSE_CELL_M / res)))
    while f * res < problem.subsegment_m:     # a sub-segment never spans more than one coarse cell
        f *= 2
    memo = problem.__dict__.setdefault("_energy_rates", {})    # weight-free: kept by with_weights
    pr = memo.get(f)
    if pr is None:
        memo.clear()
        pr = memo[f] = progress_rates(problem, f)
    rates, valid, udirs, cell_m = pr["rates"], pr["valid"], pr["udirs"], pr["cell_m"]
    g = problem.grid
    ny, nx = valid.shape

    def cell_of(p) -> tuple[int, int]:
        c = int(math.floor((p[0] - g.x0) / cell_m))
        r = int(math.floor((g.y1 - p[1]) / cell_m))
        return min(max(r, 0), ny - 1), min(max(c, 0), nx - 1)

    sr, sc = cell_of(problem.start_xyz)
    gr, gc = cell_of(problem.goal_xyz)
    # the straight line: every cell's rates (the whole path's winds), from the start point and
    # from the worst point of each cell (the recursion's floor)
    t_all = rates[valid].min(axis=0) if valid.any() else np.full(udirs.shape[0], np.inf)
    gxy = np.array(problem.goal_xyz[:2], float)
    dxy = gxy - np.array(problem.start_xyz[:2], float)
    with np.errstate(invalid="ignore"):
        straight = max(0.0, float(np.max(np.where(udirs @ dxy > 0, t_all * (udirs @ dxy), 0.0))))
    cx = g.x0 + (np.arange(nx) + 0.5) * cell_m               # cell centres [m]
    cy = g.y1 - (np.arange(ny) + 0.5) * cell_m
    lead = np.maximum(0.0, (gxy[0] - cx[None, :, None]) * udirs[:, 0] + (gxy[1] - cy[:, None, None]) * udirs[:, 1]
                      - 0.5 * cell_m * (np.abs(udirs[:, 0]) + np.abs(udirs[:, 1])))
    with np.errstate(invalid="ignore"):
        s_cell = np.max(np.where(lead > 0, t_all * lead, 0.0), axis=2)
    # the ring recursion over block minima of radius `ring`
    from scipy.ndimage import minimum_filter

    blk = minimum_filter(rates, size=(2 * ring + 1, 2 * ring + 1, 1), mode="constant", cval=np.inf)
    offs, ku, prog = _ring(ring, cell_m, udirs)
    if valid[sr, sc] and valid[gr, gc]:
        phi = _ring_dijkstra_kernel(np.ascontiguousarray(blk), valid, np.ascontiguousarray(s_cell), (gr, gc), (sr, sc),
                                    offs, ku, prog, ring - 1)
        ring_j = float(phi[sr, sc])
    else:
        ring_j = math.inf
    return {"bound_j": max(ring_j, straight), "ring_j": ring_j, "straight_j": straight, "cell_m": cell_m,
            "n_winds": pr["n_winds"], "compute_s": time.perf_counter() - t0}
