"""Compiled search of the fixed-wing lattice planners (private; users call
:func:`skyroute.stages.planning.fixedwing.plan_fixedwing`).

State ``s = ((col * kb) + kk) * 8 + h``: lattice column ``col = i * nj + j``, level
``k = k_lo[col] + kk`` (altitude ``z0 + k dz``), heading ``h`` (0..7, the lattice move it
arrived with).  Modes: 0 = distance A* (``astar-fw``), 1 = EEA* (seed 002 Algorithm 2: energy
cost, admissible heuristic, each climbing node deferred once by its ascent energy, closed nodes
not reopened), 2 = exact minimum energy (A* with a consistent heuristic, no deferral).
"""

from __future__ import annotations

import heapq
import math
from typing import NamedTuple

import numba
import numpy as np

from skyroute.stages.fixedwing_energy import piece_energy_kernel
from skyroute.stages.planning.kernels import OK, segment_eval, wind_at

MODE_DISTANCE, MODE_EEASTAR, MODE_OPTIMAL = 0, 1, 2


class FwLattice(NamedTuple):
    """The lattice arrays (see the module docstring)."""

    col_x: np.ndarray       # (ncol,) [m]
    col_y: np.ndarray       # (ncol,) [m]
    k_lo: np.ndarray        # (ncol,) int64 lowest level of the column's band
    k_n: np.ndarray         # (ncol,) int64 levels in the band (0: unusable column)
    ni: int
    nj: int
    kb: int                 # band size (max of k_n)
    z0_m: float             # altitude of level 0 [m]
    dz_m: float
    moves: np.ndarray       # (8, 2) int64 (di, dj)
    move_h_m: np.ndarray    # (8,) horizontal move length [m]
    turn_ok: np.ndarray     # (8, 8) bool, heading h -> h'
    dk_up: np.ndarray       # (8,) max levels up per move of heading h
    dk_down: np.ndarray     # (8,) max levels down per move of heading h


class FwSearch(NamedTuple):
    mode: int
    start_col: int
    start_k: int
    goal_i: int
    goal_j: int
    goal_k: int
    du_m: float
    dv_m: float
    drag_lb_j_per_m: float   # admissible drag work per metre of track [J/m]
    weight_n: float          # m g [N] (climb term of the heuristic)
    subsegment_m: float      # wind sampling step along an edge [m]
    max_expansions: int
    e_u: tuple               # unit vector of the lattice's i axis (x, y)
    e_v: tuple               # unit vector of the lattice's j axis (x, y)
    wind_xy: tuple           # the uniform horizontal wind (u, v) [m/s] of the gauge bound
    use_gauge: bool          # wind uniform and horizontal: use the wind-triangle gauge bound
    v_lo: float              # lowest / highest flown airspeed on the lattice [m/s]
    v_hi: float
    dl_w_n: float            # W (D/L)_opt [N]: drag work per metre of air path, lower bound


@numba.njit(cache=True, nogil=True)
def _air_ratio(a, b2, v):
    """V / g for a unit track with along-track wind a and cross-wind b^2 (wind triangle)."""
    d = v * v - b2
    if d <= 0.0:
        return np.inf
    g = a + math.sqrt(d)
    if g <= 0.0:
        return np.inf
    return v / g


@numba.njit(cache=True, nogil=True)
def air_distance_lb(dx, dy, wu, wv, v_lo, v_hi):
    """Least air distance [m] to cover the horizontal displacement (dx, dy) [m] in the uniform
    wind (wu, wv) [m/s] at an airspeed anywhere in [v_lo, v_hi]: min over V of V |d| / g_V
    (the gauge of the union of the per-metre displacement disks, a convex set: the bound obeys
    the triangle inequality, so the heuristic built on it is consistent)."""
    dist = math.sqrt(dx * dx + dy * dy)
    if dist == 0.0:
        return 0.0
    ux, uy = dx / dist, dy / dist
    a = ux * wu + uy * wv
    b2 = max(wu * wu + wv * wv - a * a, 0.0)
    best = min(_air_ratio(a, b2, v_lo), _air_ratio(a, b2, v_hi))
    if a > 0.0:                                   # interior minimum at sqrt(V^2 - b^2) = b^2 / a
        s = b2 / a
        vs = math.sqrt(s * s + b2)
        if v_lo < vs < v_hi:
            best = min(best, _air_ratio(a, b2, vs))
    return best * dist


@numba.njit(cache=True, nogil=True)
def _octile(di, dj, du, dv):
    a = abs(di)
    b = abs(dj)
    m = min(a, b)
    return m * math.sqrt(du * du + dv * dv) + (a - m) * du + (b - m) * dv


@numba.njit(cache=True, nogil=True)
def edge_energy(x0, y0, z0, x1, y1, z1, sub, maps, wind, prm, out):
    """Seed-002 energy [J] and time [s] of the straight edge, wind sampled at the start of
    every sub-segment of ``sub`` [m] (the planning convention); out = (energy_J, time_s,
    drag_J, potential_J, speed_change_J); energy inf when the wind triangle fails."""
    dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
    length = math.sqrt(dx * dx + dy * dy + dz * dz)
    for k in range(5):
        out[k] = 0.0
    if length == 0.0:
        return
    sx, sy, sz = dx / length, dy / length, dz / length
    nsub = max(1, int(math.ceil(length / sub - 1e-9)))
    buf = np.empty(7)
    for i in range(nsub):
        a = i * sub
        b = min(length, (i + 1) * sub)
        px, py, pz = x0 + sx * a, y0 + sy * a, z0 + sz * a
        u, v, w = wind_at(px, py, pz, maps.terrain_m, maps.grid, wind)
        piece_energy_kernel(b - a, sx, sy, sz, pz, z0 + sz * b, u, v, w, prm, buf)
        out[0] += buf[3]
        out[1] += buf[4]
        out[2] += buf[0]
        out[3] += buf[1]
        out[4] += buf[2]


@numba.njit(cache=True, nogil=True)
def _heur(mode, i, j, z, srch, gz):
    di, dj = srch.goal_i - i, srch.goal_j - j
    d = _octile(di, dj, srch.du_m, srch.dv_m)
    if mode == MODE_DISTANCE:
        return d
    drag = srch.drag_lb_j_per_m * d
    if srch.use_gauge:
        dx = (di * srch.du_m * srch.e_u[0] + dj * srch.dv_m * srch.e_v[0])
        dy = (di * srch.du_m * srch.e_u[1] + dj * srch.dv_m * srch.e_v[1])
        air = air_distance_lb(dx, dy, srch.wind_xy[0], srch.wind_xy[1], srch.v_lo, srch.v_hi)
        drag = max(drag, srch.dl_w_n * air * (1.0 - 1e-9))
    return drag + srch.weight_n * max(gz - z, 0.0)


@numba.njit(cache=True, nogil=True)
def search_kernel(lat, srch, stop, maps, wind, vehicle, power, prm):
    """A* / EEA* / exact search; returns (goal state or -1, parent, g, expanded)."""
    ni, nj, kb = lat.ni, lat.nj, lat.kb
    ncol = ni * nj
    n = ncol * kb * 8
    mode = srch.mode
    g = np.full(n, np.inf)
    parent = np.full(n, -1, dtype=np.int64)
    closed = np.zeros(n, dtype=np.uint8)
    deferred = np.zeros(n, dtype=np.uint8)
    seg = np.empty(6)
    eb = np.empty(5)
    gz = lat.z0_m + srch.goal_k * lat.dz_m
    sc = srch.start_col
    skk = srch.start_k - lat.k_lo[sc]
    heap = [(0.0, np.int64(0))]
    heap.pop()
    si = sc // nj
    sj = sc - si * nj
    sz = lat.z0_m + srch.start_k * lat.dz_m
    h0 = _heur(mode, si, sj, sz, srch, gz)
    for h in range(8):
        s = (sc * kb + skk) * 8 + h
        g[s] = 0.0
        heapq.heappush(heap, (h0, np.int64(s) * 2))
    expanded = 0
    found = -1
    while len(heap) > 0:
        fcur, code = heapq.heappop(heap)
        s = code // 2
        tag = code - 2 * s
        if closed[s]:
            continue
        h = s % 8
        rest = s // 8
        kk = rest % kb
        col = rest // kb
        i = col // nj
        j = col - i * nj
        k = lat.k_lo[col] + kk
        z = lat.z0_m + k * lat.dz_m
        hv = _heur(mode, i, j, z, srch, gz)
        pen = 0.0
        p = parent[s]
        if mode == MODE_EEASTAR and p >= 0:
            pk = lat.k_lo[(p // 8) // kb] + ((p // 8) % kb)
            if k > pk:
                pen = srch.weight_n * (k - pk) * lat.dz_m
        if tag == 0 and fcur > g[s] + hv + 1e-9 * (1.0 + abs(fcur)):
            continue                                     # stale entry
        if tag == 1 and abs(fcur - (g[s] + hv + pen)) > 1e-9 * (1.0 + abs(fcur)):
            continue                                     # stale deferred entry
        if mode == MODE_EEASTAR and pen > 0.0 and deferred[s] == 0:
            deferred[s] = 1                              # Algorithm 2: reject a climbing node once
            heapq.heappush(heap, (g[s] + hv + pen, s * 2 + 1))
            continue
        closed[s] = 1
        if i == srch.goal_i and j == srch.goal_j and k == srch.goal_k:
            found = s
            break
        expanded += 1
        if expanded > srch.max_expansions:
            break
        if (expanded & 1023) == 1 and stop[0] != 0:
            return -1, parent, g, expanded
        x0, y0 = lat.col_x[col], lat.col_y[col]
        for dh in range(-1, 2):
            h2 = (h + dh) % 8
            if p >= 0 and not lat.turn_ok[h, h2]:
                continue
            i2 = i + lat.moves[h2, 0]
            j2 = j + lat.moves[h2, 1]
            if i2 < 0 or j2 < 0 or i2 >= ni or j2 >= nj:
                continue
            col2 = i2 * nj + j2
            if lat.k_n[col2] == 0:
                continue
            x1, y1 = lat.col_x[col2], lat.col_y[col2]
            for dk in range(-lat.dk_down[h2], lat.dk_up[h2] + 1):
                k2 = k + dk
                kk2 = k2 - lat.k_lo[col2]
                if kk2 < 0 or kk2 >= lat.k_n[col2]:
                    continue
                s2 = (col2 * kb + kk2) * 8 + h2
                if closed[s2]:
                    continue
                z1 = lat.z0_m + k2 * lat.dz_m
                if segment_eval(x0, y0, z, x1, y1, z1, False, maps, wind, vehicle, power, seg) != OK:
                    continue
                edge_energy(x0, y0, z, x1, y1, z1, srch.subsegment_m, maps, wind, prm, eb)
                if not math.isfinite(eb[0]):
                    continue                             # the wind triangle has no solution
                if mode == MODE_DISTANCE:
                    w = seg[0]
                else:
                    w = eb[0]
                ng = g[s] + w
                if ng < g[s2]:
                    g[s2] = ng
                    parent[s2] = s
                    heapq.heappush(heap, (ng + _heur(mode, i2, j2, z1, srch, gz), s2 * 2))
    return found, parent, g, expanded
