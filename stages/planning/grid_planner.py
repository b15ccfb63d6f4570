"""Deterministic STEP I planner: A* on a 3-D lattice with the eq. 11 cost, plus path refinement.

Lattice (:func:`make_lattice`)
------------------------------
Nodes at the centres of every ``step_cells``-th grid cell (horizontal spacing
``h = step_cells * resolution`` [m]) and on altitude levels ``dz_m`` apart (default
``0.98 h tan(alpha_max)``, so that a move of one level over one horizontal step respects the
flight-path angle).  The levels are aligned on the start altitude.  Edges: 26-connectivity
(|di|, |dj|, |dk| <= 1); the start and the goal are extra nodes linked to every lattice node
within 2 horizontal steps and 1 level of them (and to each other).  An edge exists when the
problem's :meth:`~skyroute.stages.planning.problem.PlanningProblem.motion_valid` accepts the
straight motion; its weight is f of eq. 11 on that segment (same kernel as BIT*).

Search: A* (binary heap, numba), edges evaluated lazily when a node is expanded, so only the
explored part of the lattice is costed (an invalid motion costs no energy evaluation).
Heuristic: the exact cost-to-goal of a horizontal 2-D relaxation (:func:`heuristic_2d`; it sees
obstacles that fill whole columns and the risk / landing maps) plus an altitude term
phi(z) = b_up (z_goal - z)+ + c_down (z - z_goal)+ (:func:`vertical_rates`), consistent; or
``cost_rate_lb * distance`` (every edge costs at least ``cost_rate_lb`` per metre).  The
energy term of both 2-D and altitude rates uses the energy ratio of the exact lattice edge
directions over every wind of the map (:meth:`PlanningProblem.energy_ratio_lb_dense_each`,
0.99 margin): on Monaco 2.7 km it cut the expansions per level from 52 k to 6.1 k (h(start) =
0.997 x the lattice optimum instead of 0.966).  Without refinement the result is the exact
shortest path on the lattice (tested against scipy's Dijkstra, and h <= the Dijkstra
cost-to-go at every node).

Refinement (:func:`refine_path`, also applied to BIT* paths): greedy shortcutting (a vertex
is dropped when the direct segment is valid and not costlier) and a pattern search moving each
interior vertex along 26 directions with halving steps while f decreases and both adjacent
segments stay valid.  Refinement never increases f.
"""

from __future__ import annotations

import heapq
import math
import time
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np

from skyroute.stages import control
from skyroute.stages.base import InputError
from skyroute.stages.planning.kernels import OK, segment_eval_if_valid
from skyroute.stages.planning.problem import PlanningProblem

STEP_CELLS = 8   # default lattice step [cells]: measured on Helsinki (2 m cells) 8 beats 6 in time
#                  (21 k vs 52 k expansions) and refined f, and its paths smooth in STEP III
_OFFS = np.array([(dk, di, dj) for dk in (-1, 0, 1) for di in (-1, 0, 1) for dj in (-1, 0, 1)
                  if (dk, di, dj) != (0, 0, 0)], dtype=np.int64)


@dataclass(frozen=True)
class Lattice:
    """Lattice geometry: node (k, r, c) at (x[c], y[r], z[k]); id = (k * ny + r) * nx + c."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    valid: np.ndarray          # (nz, ny, nx) bool, state_valid of each node
    start_links: np.ndarray    # node ids linked to the start (candidates; motion checked in search)
    goal_links: np.ndarray     # node ids linked to the goal
    step_m: float
    dz_m: float

    @property
    def shape(self) -> tuple[int, int, int]:
        return (self.z.size, self.y.size, self.x.size)

    def xyz(self, ids: np.ndarray) -> np.ndarray:
        nz, ny, nx = self.shape
        ids = np.asarray(ids, dtype=np.int64)
        k, rem = np.divmod(ids, ny * nx)
        r, c = np.divmod(rem, nx)
        return np.stack([self.x[c], self.y[r], self.z[k]], axis=-1)


def _links(lat_x, lat_y, lat_z, p, radius_h: int = 2, radius_v: int = 1) -> np.ndarray:
    nz, ny, nx = lat_z.size, lat_y.size, lat_x.size
    c0 = int(np.argmin(np.abs(lat_x - p[0])))
    r0 = int(np.argmin(np.abs(lat_y - p[1])))
    k0 = int(np.argmin(np.abs(lat_z - p[2])))
    ids = []
    for k in range(max(0, k0 - radius_v), min(nz, k0 + radius_v + 1)):
        for r in range(max(0, r0 - radius_h), min(ny, r0 + radius_h + 1)):
            for c in range(max(0, c0 - radius_h), min(nx, c0 + radius_h + 1)):
                ids.append((k * ny + r) * nx + c)
    return np.array(ids, dtype=np.int64)


def make_lattice(problem: PlanningProblem, step_cells: int = STEP_CELLS, dz_m: float | None = None,
                 z_anchor_m: float | None = None) -> Lattice:
    """The A* lattice of ``problem`` (module docstring).  ``z_anchor_m`` [m]: an altitude the
    levels are aligned on (default the start's); missions planned with the same anchor on the
    same maps share one lattice (and its :class:`EdgeCache`)."""
    if int(step_cells) < 1:
        raise InputError(f"step_cells {step_cells} must be >= 1")
    g = problem.grid
    step = int(step_cells)
    h = step * g.resolution_m
    if dz_m is None:
        dz_m = lattice_dz_m(h, problem.vehicle.max_flight_path_angle_deg)
    if not dz_m > 0:
        raise InputError(f"dz_m {dz_m} must be > 0 [m]")
    cols = np.arange(step // 2, g.nx, step)
    rows = np.arange(step // 2, g.ny, step)
    x = g.x[cols]
    y = g.y[rows]
    zlo = float(np.min(problem.floor_m))     # finite: no NaN or -inf, so the lowest finite floor
    if not math.isfinite(zlo):               # (+inf cells do not lower it); else the slow way
        fin = problem.floor_m[np.isfinite(problem.floor_m)]
        zlo = float(fin.min()) if fin.size else float(problem.terrain_m.min())
    zhi = float(problem.ceiling_m.max())
    if z_anchor_m is None:
        zs = problem.start_xyz[2]
        kdown = math.floor((zs - zlo) / dz_m + 1e-9)
        kup = math.floor((zhi - zs) / dz_m + 1e-9)
    else:     # the anchor's levels within [zlo, zhi]
        zs = float(z_anchor_m)
        kdown = -math.ceil((zlo - zs) / dz_m - 1e-9)
        kup = math.floor((zhi - zs) / dz_m + 1e-9)
    z = zs + dz_m * np.arange(-kdown, kup + 1)
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    valid = problem.state_valid(np.stack([xx.ravel(), yy.ravel(), zz.ravel()], axis=1)).reshape(zz.shape)
    return Lattice(x=x, y=y, z=z, valid=valid, start_links=_links(x, y, z, problem.start_xyz),
                   goal_links=_links(x, y, z, problem.goal_xyz), step_m=h, dz_m=float(dz_m))


class LatticeNodes(NamedTuple):
    """The lattice as :func:`_astar_kernel` reads it (see :class:`Lattice`)."""

    x_m: np.ndarray             # (nx_l,) node x [m]
    y_m: np.ndarray             # (ny_l,) node y [m]
    z_m: np.ndarray             # (nz_l,) node altitudes [m]
    valid: np.ndarray           # (nz_l, ny_l, nx_l) bool
    offsets: np.ndarray         # (26, 3) int64 neighbour steps (dk, di, dj) [nodes]
    start_links: np.ndarray     # node ids linked to the start
    goal_links: np.ndarray      # node ids linked to the goal


class SearchParams(NamedTuple):
    """Endpoints, objective and heuristic of one A* search."""

    start_m: tuple[float, float, float]           # (x, y, z) [m]
    goal_m: tuple[float, float, float]            # (x, y, z) [m]
    weights: tuple[float, float, float, float]    # (w_l, w_r, w_d, w_e) [-]
    rate: float                                   # cost_rate_lb [-] (f per metre)
    max_expansions: int
    h2: np.ndarray                                # (ny_l, nx_l) 2-D heuristic table [-] (unused if not use_h2)
    use_h2: bool
    b_up: float                                   # heuristic cost per metre of climb to the goal [-]
    c_down: float                                 # heuristic cost per metre of descent to the goal [-]


@numba.njit(cache=True, nogil=True)
def _astar_kernel(nodes, search, stop, edges, maps, wind, vehicle, power):
    lx, ly, lz, valid, offs, start_links, goal_links = nodes
    sx, sy, sz = search.start_m
    gx, gy, gz = search.goal_m
    wts = search.weights
    rate, max_expansions, h2, use_h2 = search.rate, search.max_expansions, search.h2, search.use_h2
    b_up, c_down = search.b_up, search.c_down
    nz, ny, nx = valid.shape
    n = nz * ny * nx
    S = n
    G = n + 1
    gcost = np.full(n + 2, np.inf)
    parent = np.full(n + 2, -1, dtype=np.int64)
    closed = np.zeros(n + 2, dtype=np.bool_)
    is_goal_link = np.zeros(n, dtype=np.bool_)
    for i in range(goal_links.shape[0]):
        is_goal_link[goal_links[i]] = True
    buf = np.empty(6)
    use_edges = edges.shape[0] == n     # the lattice's EdgeCache (else a (0, 26) placeholder)
    gcost[S] = 0.0
    heap = [(rate * math.sqrt((sx - gx) ** 2 + (sy - gy) ** 2 + (sz - gz) ** 2), S)]
    expanded = 0
    while len(heap) > 0:
        fcur, u = heapq.heappop(heap)
        if closed[u]:
            continue
        closed[u] = True
        if u == G:
            break
        expanded += 1
        if expanded > max_expansions:
            break
        if (expanded & 1023) == 1 and stop[0] != 0:   # cancelled or out of time: give up
            return np.inf, parent, expanded
        if u == S:
            ux, uy, uz = sx, sy, sz
        else:
            k = u // (ny * nx)
            rem = u - k * ny * nx
            r = rem // nx
            c = rem - r * nx
            ux, uy, uz = lx[c], ly[r], lz[k]
        # candidate successors
        if u == S:
            ncand = start_links.shape[0] + 1
        else:
            ncand = offs.shape[0] + 1
        for m in range(ncand):
            if m == ncand - 1:
                if u != S and not is_goal_link[u]:
                    continue
                v = G
                vx, vy, vz = gx, gy, gz
            elif u == S:
                v = start_links[m]
                kk = v // (ny * nx)
                rem = v - kk * ny * nx
                rr = rem // nx
                cc = rem - rr * nx
                if not valid[kk, rr, cc]:
                    continue
                vx, vy, vz = lx[cc], ly[rr], lz[kk]
            else:
                kk = k + offs[m, 0]
                rr = r + offs[m, 1]
                cc = c + offs[m, 2]
                if kk < 0 or rr < 0 or cc < 0 or kk >= nz or rr >= ny or cc >= nx:
                    continue
                if not valid[kk, rr, cc]:
                    continue
                v = (kk * ny + rr) * nx + cc
                vx, vy, vz = lx[cc], ly[rr], lz[kk]
            if closed[v]:
                continue
            inner = use_edges and u != S and v != G
            w = edges[u, m] if inner else np.nan
            if w != w:                  # not cached: evaluate the motion
                code = segment_eval_if_valid(ux, uy, uz, vx, vy, vz, maps, wind, vehicle, power, buf)
                if code != OK:
                    w = np.inf
                else:
                    w = wts[0] * buf[0] + wts[1] * buf[1] + wts[2] * buf[2]
                    if wts[3] > 0:
                        w += wts[3] * buf[3]
                if inner:
                    edges[u, m] = w
            if w == np.inf:
                continue
            ng = gcost[u] + w
            if ng < gcost[v]:
                gcost[v] = ng
                parent[v] = u
                if v == G:
                    hv = 0.0
                elif use_h2:
                    hv = (h2[(v % (ny * nx)) // nx, v % nx] + b_up * max(gz - vz, 0.0)
                          + c_down * max(vz - gz, 0.0))
                else:
                    hv = rate * math.sqrt((vx - gx) ** 2 + (vy - gy) ** 2 + (vz - gz) ** 2)
                heapq.heappush(heap, (ng + hv, v))
    return gcost[G], parent, expanded


_MOVES = [(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1) if (di, dj) != (0, 0)]


def lattice_edge_dirs(step_m: float, dz_m: float, max_flight_path_angle_deg: float
                      ) -> tuple[list[tuple[int, int, float]], np.ndarray]:
    """The flyable edge directions of an A* lattice of horizontal step ``step_m`` [m] and level
    spacing ``dz_m`` [m]: ``(edges, dirs)``, per edge (move index of :data:`_MOVES`, dk index
    0/1/2 for -1/0/+1 level, 3-D length [m]) and its unit direction (k, 3) [-] (the directions
    :func:`_move_rates` bounds the energy ratio on; edges steeper than the flight-path angle
    are left out)."""
    sin_max = math.sin(math.radians(max_flight_path_angle_deg))
    edges, dirs = [], []
    for m, (di, dj) in enumerate(_MOVES):
        for k, dk in enumerate((-1, 0, 1)):
            v = np.array([dj * step_m, -di * step_m, dk * dz_m])
            l3 = float(np.linalg.norm(v))
            if abs(v[2]) > l3 * sin_max + 1e-9:
                continue
            edges.append((m, k, l3))
            dirs.append(v / l3)
    return edges, np.array(dirs).reshape(-1, 3)


def lattice_dz_m(step_m: float, max_flight_path_angle_deg: float) -> float:
    """The default level spacing [m] of an A* lattice of horizontal step ``step_m`` [m]: 98 %
    of the climb the flight-path angle allows over one step (:func:`make_lattice`)."""
    return 0.98 * step_m * math.tan(math.radians(max_flight_path_angle_deg))


def _move_rates(problem: PlanningProblem, lattice: Lattice) -> tuple[np.ndarray, float, float]:
    """Per horizontal move m (:data:`_MOVES`) the length + energy weight per horizontal metre
    ``rho_m`` [-], and the altitude rates ``b_up``, ``c_down`` [-] (per metre of climb / of
    descent) such that every lattice edge (dk = -1, 0, 1) projecting on move m costs at least
    ``w_l L + w_e C_e >= rho_m L_h + b_up dz+ + c_down dz-`` (energy ratio bounded below over
    the map's winds, :meth:`~PlanningProblem.energy_ratio_lb_dirs`).  ``b_up`` / ``c_down`` are
    the smallest extra cost of a climbing / descending edge over the level edge of the same
    move, so ``rho_m`` is the level edge's bound.  With phi(z) = b_up (z_goal - z)+ + c_down
    (z - z_goal)+, phi(z_u) - phi(z_v) <= b_up dz+ + c_down dz- on every edge u -> v: adding phi
    to a consistent 2-D heuristic keeps it consistent."""
    wl, _, _, we = problem.weights
    cost = np.full((len(_MOVES), 3), np.inf)     # w_l L + w_e lb(C_e) of the edge (move, dk)
    lh = np.array([lattice.step_m * math.hypot(di, dj) for di, dj in _MOVES])
    edges, dirs = lattice_edge_dirs(lattice.step_m, lattice.dz_m, problem.vehicle.max_flight_path_angle_deg)
    e = problem.energy_ratio_lb_dense_each(dirs) if we > 0 and len(dirs) else np.zeros(len(dirs))
    for (m, k, l3), e_mk in zip(edges, e, strict=True):
        cost[m, k] = (wl + we * float(e_mk)) * l3
    flat = cost[:, 1]
    dz = lattice.dz_m
    up = (cost[:, 2] - flat) / dz
    down = (cost[:, 0] - flat) / dz
    b_up = float(max(0.0, up.min())) if np.isfinite(up).any() else 0.0
    c_down = float(max(0.0, down.min())) if np.isfinite(down).any() else 0.0
    rho = np.minimum.reduce([flat, cost[:, 2] - b_up * dz, cost[:, 0] - c_down * dz]) / lh
    return rho, b_up, c_down


def vertical_rates(problem: PlanningProblem, lattice: Lattice) -> tuple[float, float]:
    """``(b_up, c_down)`` [-]: the altitude term of the A* heuristic, phi(z) = b_up
    (z_goal - z)+ + c_down (z - z_goal)+ added to :func:`heuristic_2d` (see ``_move_rates``).
    It depends on the wind map, vehicle, weights and lattice steps, not on the floors, so it
    holds for every coverage level of a mission."""
    _, b_up, c_down = _move_rates(problem, lattice)
    return b_up, c_down


def heuristic_2d(problem: PlanningProblem, lattice: Lattice, col_ok: np.ndarray | None = None) -> np.ndarray:
    """Admissible, consistent A* heuristic (ny_l, nx_l): exact cost-to-goal on the horizontal
    8-connected lattice (scipy Dijkstra, directed) with edge cost ``rho_m L_h + w_r R_h + w_d
    D_h`` (L_h horizontal length, R_h / D_h exact map integrals along it, rho_m the length +
    energy bound per horizontal metre of move m of ``_move_rates``: every 3-D lattice edge
    projecting on m costs at least ``rho_m L_h + b_up dz+ + c_down dz-`` in length + energy,
    over every wind of the map).  The projection of every 3-D lattice path is such a 2-D path
    and each 3-D edge costs at least its projection (3-D length >= horizontal length, same
    cells crossed in the same proportions), so h(u) <= true cost-to-go, also with the altitude
    term of :func:`vertical_rates` added (goal links drop the largest altitude term of their
    nodes).  Columns without any admissible altitude (floor > ceiling or forbidden) are removed.

    ``col_ok`` (ny_l, nx_l) bool: the columns kept (default: those with a valid lattice node).
    With the columns of a LESS constrained problem (a looser coverage level D_j, whose floors
    are lower everywhere) the heuristic stays admissible and consistent for this problem: its
    2-D graph contains the projection of every edge of this problem's lattice.  The levels of
    one mission share it that way (:func:`shared_heuristic`)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    ny, nx = lattice.y.size, lattice.x.size
    rr, cc = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    if col_ok is None:
        col_ok = lattice.valid.any(axis=0)
    elif np.shape(col_ok) != (ny, nx):
        raise InputError(f"col_ok has shape {np.shape(col_ok)}; the lattice has {(ny, nx)} columns")
    ids = rr * nx + cc
    wl, wr, wd, we = problem.weights
    rates, b_up, c_down = _move_rates(problem, lattice)
    a_l, b_l, e_l = [], [], []
    for m, (di, dj) in enumerate(_MOVES):
        r2, c2 = rr + di, cc + dj
        ins = (r2 >= 0) & (r2 < ny) & (c2 >= 0) & (c2 < nx)
        a_l.append(ids[ins])
        b_l.append((r2 * nx + c2)[ins])
        e_l.append(np.full(int(ins.sum()), rates[m]))
    a, b = np.concatenate(a_l), np.concatenate(b_l)
    lw_rate = np.concatenate(e_l)          # (length + energy) weight per horizontal metre
    n = ny * nx
    G = n
    gx, gy, gz = problem.goal_xyz
    glinks = np.unique(lattice.goal_links % n)
    # a goal link may end a path with a vertical step that the altitude term phi (see
    # _move_rates) already counts: its 2-D weight drops the largest phi of its linked nodes
    zl = lattice.z[lattice.goal_links // n]
    phi = b_up * np.maximum(gz - zl, 0.0) + c_down * np.maximum(zl - gz, 0.0)
    phi_col = np.zeros(n)
    np.maximum.at(phi_col, lattice.goal_links % n, phi)
    a = np.concatenate([a, glinks])
    b = np.concatenate([b, np.full(glinks.size, G)])
    e_goal = problem.energy_ratio_lb if we > 0 else 0.0
    lw_rate = np.concatenate([lw_rate, np.full(glinks.size, wl + we * e_goal)])
    sub = np.concatenate([np.zeros(a.size - glinks.size), phi_col[glinks]])
    okn = np.concatenate([col_ok.ravel(), [True]])
    keep = okn[a] & okn[b]
    a, b, lw_rate, sub = a[keep], b[keep], lw_rate[keep], sub[keep]
    xy = np.concatenate([np.stack([lattice.x[cc.ravel()], lattice.y[rr.ravel()]], axis=1), [[gx, gy]]])
    z = np.full((a.size, 1), gz)
    _, out = problem.motion_codes(np.hstack([xy[a], z]), np.hstack([xy[b], z]), want_cost=False)
    w = lw_rate * out[:, 0] + wr * out[:, 1] + wd * out[:, 2] - sub
    w = np.maximum(w, 1e-12)   # csgraph drops explicit zeros
    m = coo_matrix((w, (a, b)), shape=(n + 1, n + 1)).tocsr()
    d = dijkstra(m.T.tocsr(), directed=True, indices=G)   # cost to reach G along directed edges
    return np.ascontiguousarray(np.where(np.isfinite(d[:n]), d[:n], np.inf).reshape(ny, nx))


class EdgeCache:
    """The costs f of the inner edges of lattices (node -> 26 neighbours), filled lazily by the
    A* searches and reused by later ones: for a caller that plans many missions on the SAME
    problem maps, weights and vehicle (``skyroute fleet``), with lattices anchored on one
    altitude (:func:`make_lattice` ``z_anchor_m``) so that they coincide.  An edge cost does not
    depend on the endpoints (the start and goal links are never cached), so a search returns
    exactly what it would without the cache.  One (n, 26) float64 array per lattice geometry
    (NaN: not evaluated, inf: invalid motion), 8 bytes x 26 per lattice node."""

    def __init__(self, max_lattices: int = 4):
        self.max_lattices = int(max_lattices)
        self._arrays: dict[tuple, np.ndarray] = {}

    def for_lattice(self, lattice: Lattice) -> np.ndarray:
        key = (lattice.shape, lattice.x.tobytes(), lattice.y.tobytes(), lattice.z.tobytes(),
               lattice.valid.tobytes())
        a = self._arrays.get(key)
        if a is None:
            while len(self._arrays) >= self.max_lattices:
                self._arrays.pop(next(iter(self._arrays)))
            a = np.full((lattice.valid.size, _OFFS.shape[0]), np.nan)
            self._arrays[key] = a
        return a

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self._arrays.values())


_NO_EDGES = np.empty((0, _OFFS.shape[0]))
ASTAR_MAX_EXPANSIONS = 50_000_000   # A*'s counted budget: it stops after that many node expansions (no path)


def astar(problem: PlanningProblem, lattice: Lattice, max_expansions: int = ASTAR_MAX_EXPANSIONS,
          heuristic: str = "dijkstra2d", h2: np.ndarray | None = None, time_limit_s: float | None = None,
          edge_cache: EdgeCache | None = None) -> dict:
    """A* from start to goal on ``lattice``.  Returns ``waypoints`` (k, 3) or None, ``f`` (the
    lattice optimum), ``expanded`` (node expansions), ``stopped_by`` (``""``, or ``"time"`` when
    the search ran out of ``time_limit_s`` [s] wall clock before reaching the goal: no path).
    ``heuristic``: ``"dijkstra2d"`` (:func:`heuristic_2d` plus the altitude term of
    :func:`vertical_rates`, default) or ``"euclid"`` (``cost_rate_lb * distance``); both are
    consistent, so the result is the lattice optimum either way.  ``h2``: a precomputed
    ``"dijkstra2d"`` table (ny_l, nx_l) (e.g. :func:`shared_heuristic` of the loosest level).
    The compiled search polls a stop flag every 1024 expansions: a cancel request
    (:mod:`skyroute.stages.control`) raises ``Interrupted`` within milliseconds.
    ``edge_cache``: an :class:`EdgeCache` kept for ``problem``'s maps, weights and vehicle
    (same result, fewer motion evaluations)."""
    sx, sy, sz = problem.start_xyz
    gx, gy, gz = problem.goal_xyz
    if heuristic == "dijkstra2d":
        if h2 is None:
            h2 = heuristic_2d(problem, lattice)
        elif np.shape(h2) != lattice.shape[1:]:
            raise InputError(f"h2 has shape {np.shape(h2)}; the lattice has {lattice.shape[1:]} columns")
        h2 = np.ascontiguousarray(h2, dtype=np.float64)
        use_h2 = True
        b_up, c_down = vertical_rates(problem, lattice)
    elif heuristic == "euclid":
        h2 = np.zeros((1, 1))
        use_h2 = False
        b_up = c_down = 0.0
    else:
        raise InputError(f"heuristic {heuristic!r} must be 'dijkstra2d' or 'euclid'")
    with control.StopFlag(time_limit_s) as stop:
        nodes = LatticeNodes(lattice.x, lattice.y, lattice.z, lattice.valid, _OFFS, lattice.start_links,
                             lattice.goal_links)
        search = SearchParams((float(sx), float(sy), float(sz)), (float(gx), float(gy), float(gz)),
                              tuple(float(w) for w in problem.weights), float(problem.cost_rate_lb),
                              int(max_expansions), h2, bool(use_h2), float(b_up), float(c_down))
        edges = _NO_EDGES if edge_cache is None else edge_cache.for_lattice(lattice)
        f, parent, expanded = _astar_kernel(nodes, search, stop.array, edges, *problem.seg_args)
        stop.check()
        stopped = "time" if stop.expired and not np.isfinite(f) else ""
    if not np.isfinite(f):
        return {"waypoints": None, "f": math.inf, "expanded": int(expanded), "stopped_by": stopped}
    n = lattice.valid.size
    ids = []
    v = n + 1
    while v != -1:
        ids.append(v)
        v = parent[v]
    ids = ids[::-1]
    pts = [problem.start_xyz]
    inner = np.array([i for i in ids if i < n], dtype=np.int64)
    if inner.size:
        pts.extend(map(tuple, lattice.xyz(inner)))
    pts.append(problem.goal_xyz)
    return {"waypoints": np.array(pts, dtype=float), "f": float(f), "expanded": int(expanded), "stopped_by": ""}


# --------------------------------------------------------------------------- refinement


def _seg_f(problem: PlanningProblem, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(f per segment, valid per segment); invalid segments get f = inf (and cost no energy
    evaluation: :meth:`~.problem.PlanningProblem.motion_f_if_valid`)."""
    return problem.motion_f_if_valid(a, b)


def shortcut(problem: PlanningProblem, wp: np.ndarray) -> np.ndarray:
    """Greedy shortcutting: from each kept vertex jump to the farthest later vertex whose
    direct segment is valid and not costlier than the chain it replaces."""
    wp = np.asarray(wp, float)
    if len(wp) <= 2:
        return wp
    segf, _ = _seg_f(problem, wp[:-1], wp[1:])
    cum = np.concatenate([[0.0], np.cumsum(segf)])
    out = [0]
    i = 0
    while i < len(wp) - 1:
        js = np.arange(len(wp) - 1, i, -1)
        fd, ok = _seg_f(problem, np.repeat(wp[i:i + 1], js.size, axis=0), wp[js])
        good = ok & (fd <= cum[js] - cum[i] + 1e-9)
        j = int(js[np.argmax(good)]) if good.any() else i + 1
        out.append(j)
        i = j
    return wp[out]


_DIRS = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) != (0, 0, 0)],
                 dtype=float)
_DIRS /= np.linalg.norm(_DIRS, axis=1)[:, None]


RELAX_MAX_SEGMENTS = 40_000   # segment evaluations of one relaxation: Helsinki's levels use ~26 k,
#                               a 23 km mountain mission on a 30 m grid would use > 250 k (2 ms per 26)


def relax_vertices(problem: PlanningProblem, wp: np.ndarray, step0_m: float, min_step_m: float = 0.05,
                   max_passes: int = 30, deadline: float = math.inf,
                   max_segments: int = RELAX_MAX_SEGMENTS) -> np.ndarray:
    """Pattern search on each interior vertex (26 directions, step halving): move it while the
    two adjacent segments stay valid and their f decreases.  Stops, keeping every move made so
    far, after ``max_segments`` segment evaluations (a work bound: the same result on any
    machine) or when ``time.perf_counter()`` passes ``deadline`` (the level's wall-clock cap)."""
    wp = np.array(wp, float)
    k = len(wp)
    if k <= 2:
        return wp
    steps = [step0_m]
    while steps[-1] / 2 >= min_step_m:
        steps.append(steps[-1] / 2)
    evals = 0
    for _ in range(max_passes):
        improved = False
        for i in range(1, k - 1):
            control.check()
            if control.work_clock() > deadline or evals >= max_segments:
                return wp
            fa, _ = _seg_f(problem, wp[i - 1:i], wp[i:i + 1])
            fb, _ = _seg_f(problem, wp[i:i + 1], wp[i + 1:i + 2])
            best = float(fa[0] + fb[0])
            for s in steps:
                moved = True
                while moved and evals < max_segments:
                    moved = False
                    evals += 2 * len(_DIRS)
                    cand = wp[i] + s * _DIRS
                    fa, _ = _seg_f(problem, np.repeat(wp[i - 1:i], len(cand), 0), cand)
                    fb, _ = _seg_f(problem, cand, np.repeat(wp[i + 1:i + 2], len(cand), 0))
                    tot = fa + fb
                    j = int(np.argmin(tot))
                    if tot[j] < best - 1e-9:
                        best = float(tot[j])
                        wp[i] = cand[j]
                        moved = improved = True
        if not improved:
            break
    return wp


def refine_path(problem: PlanningProblem, wp: np.ndarray, step0_m: float | None = None,
                time_limit_s: float = np.inf) -> np.ndarray:
    """Shortcut, relax vertices, shortcut again (f never increases; validity kept).  Past
    ``time_limit_s`` [s] the vertex relaxation stops where it is (a valid, not costlier path)."""
    t0 = control.work_clock()
    if step0_m is None:
        step0_m = 2.0 * problem.grid.resolution_m
    wp = shortcut(problem, wp)
    if control.work_clock() - t0 < time_limit_s:
        wp = relax_vertices(problem, wp, step0_m, deadline=t0 + time_limit_s)
        control.check()
        wp = shortcut(problem, wp)
    return wp


def shared_heuristic(loosest: PlanningProblem, step_cells: int = STEP_CELLS, dz_m: float | None = None,
                     z_anchor_m: float | None = None) -> np.ndarray:
    """The :func:`heuristic_2d` table of the least constrained problem (the loosest coverage
    level, lowest floors): admissible and consistent for every level with the same grid, map
    costs, wind, vehicle, weights and goal whose floors are >= its floors (see
    :func:`heuristic_2d`), so it is computed once per mission."""
    lat = make_lattice(loosest, step_cells, dz_m, z_anchor_m)
    return heuristic_2d(loosest, lat)


def plan_grid(problem: PlanningProblem, step_cells: int = STEP_CELLS, dz_m: float | None = None,
              refine: bool = True, max_expansions: int = ASTAR_MAX_EXPANSIONS, heuristic: str = "dijkstra2d",
              h2: np.ndarray | None = None, time_limit_s: float = math.inf, z_anchor_m: float | None = None,
              edge_cache: EdgeCache | None = None) -> dict:
    """A* on the lattice then (optionally) :func:`refine_path`, within ``time_limit_s`` [s] wall
    clock.  Returns a dict with ``waypoints`` (or None), ``lattice_f``, ``expanded``,
    ``lattice``, ``compute_s`` and ``stopped_by`` (``""``; ``"time"`` when the limit cut the
    search, then no path, or the refinement, then the path refined so far).
    ``h2``: precomputed heuristic table (:func:`shared_heuristic`); ``z_anchor_m``,
    ``edge_cache``: see :func:`make_lattice` and :class:`EdgeCache`."""
    t0 = time.perf_counter()
    w0 = control.work_clock()        # the safety cap's clock (JIT compilation excluded)
    lat = make_lattice(problem, step_cells, dz_m, z_anchor_m)
    res = astar(problem, lat, max_expansions, heuristic, h2, time_limit_s=time_limit_s - (control.work_clock() - w0),
                edge_cache=edge_cache)
    wp = res["waypoints"]
    stopped = res["stopped_by"]
    if wp is not None and refine:
        left = time_limit_s - (control.work_clock() - w0)
        wp = refine_path(problem, wp, time_limit_s=left)
        if control.work_clock() - w0 > time_limit_s:
            stopped = "time"
    return {"waypoints": wp, "lattice_f": res["f"], "expanded": res["expanded"], "lattice": lat,
            "compute_s": time.perf_counter() - t0, "stopped_by": stopped}


__all__ = ["ASTAR_MAX_EXPANSIONS", "STEP_CELLS", "EdgeCache", "Lattice", "astar", "heuristic_2d", "lattice_dz_m",
           "lattice_edge_dirs", "make_lattice", "plan_grid", "refine_path",
           "relax_vertices", "shared_heuristic", "shortcut", "vertical_rates"]
