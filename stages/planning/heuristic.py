"""The admissible lower bound of the STEP I objective per metre (A* / BIT* heuristics).

Eq. 11 costs ``f = w_l C_l + w_r C_r + w_d C_d + w_e C_e`` with every term >= a rate times the
length [m] of the segment: 1 for C_l, the smallest risk / landing cost of a flyable cell for
C_r / C_d, and for C_e = E_w / E_0 * L the smallest ratio E_w / E_0 over the winds a segment
can meet.  That ratio can be below 1 (tail wind), so it is bounded from below by the compiled
:func:`~skyroute.stages.planning.kernels.ratio_kernel` over directions and wind samples:

* :func:`energy_ratio_lb` -- every flyable direction (a Fibonacci sphere plus the lattice
  directions and the flight-path-angle cone edge, :func:`fibonacci_dirs`), the map's winds
  subsampled to <= 600 (:func:`wind_samples`), times :data:`ENERGY_LB_SAFETY` (0.9);
* :func:`energy_ratio_lb_dense_dirs` -- a few given directions (the A* lattice edges), every
  wind of the map and :data:`WIND_INTERP_SAMPLES` level-to-level interpolations per gap
  (:func:`wind_samples_dense`), times :data:`ENERGY_LB_DENSE_SAFETY` (0.99);
  :func:`energy_ratio_lb_dense_each` the same bound for each direction of a set, in one
  parallel pass.

The coverage levels of one mission share the wind map and the vehicle, so the bounds are
memoised (:class:`BoundMemo`) on the bytes of their inputs and computed once for all levels.
"""

from __future__ import annotations

import hashlib
import math
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from skyroute.stages.planning.kernels import ratio_each_kernel, ratio_kernel

if TYPE_CHECKING:
    from skyroute.stages.planning.problem import PlanningProblem

ENERGY_LB_SAFETY = 0.9
ENERGY_LB_DENSE_SAFETY = 0.99   # margin of the dense bound for wind between its interpolation samples
DIRS_ATOL = 1e-12               # wind_bounds tiles' directions matched to a lattice's within this [-]
WIND_INTERP_SAMPLES = 8         # samples per gap between two wind levels of the dense bound


class BoundMemo:
    """A thread-safe memo ``key -> value`` holding at most ``limit`` entries (cleared when full).
    A key is computed by one thread at a time: the coverage levels planned in parallel threads
    ask for the same bounds, and a second thread waits for the first one's value instead of
    computing it again (on the 6 km Helsinki AOI each bound costs ~0.1-0.2 s, 24 per lattice)."""

    def __init__(self, limit: int) -> None:
        self.limit = int(limit)
        self._store: dict[str, Any] = {}
        self._pending: dict[str, threading.Event] = {}
        self._lock = threading.Lock()

    def get(self, key: str, make: Callable[[], Any]) -> Any:
        """The value of ``key``, computed by ``make()`` on a miss (outside the lock; a thread
        asking while another computes it waits for that value)."""
        while True:
            with self._lock:
                value = self._store.get(key)
                if value is not None:
                    return value
                event = self._pending.get(key)
                owner = event is None
                if owner:
                    event = self._pending[key] = threading.Event()
            if owner:
                break
            event.wait()          # then read it (or compute it, if that thread failed)
        try:
            value = make()
            with self._lock:
                if len(self._store) > self.limit:
                    self._store.clear()
                self._store[key] = value
        finally:
            with self._lock:
                self._pending.pop(key, None)
            event.set()
        return value

    def clear(self) -> None:
        with self._lock:
            self._store.clear()

    def __len__(self) -> int:
        return len(self._store)


RATIO_MEMO = BoundMemo(4096)   # energy ratio bounds, shared by the coverage levels
WINDS_MEMO = BoundMemo(16)     # wind sample sets of a wind map


def _finite_ratio(r: float) -> float:
    return 1.0 if not np.isfinite(r) else float(r)


def _params_bytes(*arrays) -> bytes:
    return b"".join(np.ascontiguousarray(a, dtype=np.float64).tobytes() for a in arrays)


def fibonacci_dirs(n: int, max_sin: float) -> np.ndarray:
    """Unit directions (m, 3) with ``|sin(flight-path angle)| <= max_sin``: a Fibonacci sphere
    of ``n`` points, the 26 lattice directions and 72 directions on each edge of the cone."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = math.pi * (1 + 5**0.5) * k
    rho = np.sqrt(1 - z * z)
    d = np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)
    lat = np.array([[i, j, kk] for i in (-1, 0, 1) for j in (-1, 0, 1) for kk in (-1, 0, 1)
                    if (i, j, kk) != (0, 0, 0)], dtype=float)
    lat /= np.linalg.norm(lat, axis=1)[:, None]
    ang = np.linspace(0, 2 * math.pi, 72, endpoint=False)
    edge = np.stack([np.cos(ang) * math.sqrt(1 - max_sin**2), np.sin(ang) * math.sqrt(1 - max_sin**2),
                     np.full_like(ang, max_sin)], axis=1)
    d = np.concatenate([d, lat, edge, edge * [1, 1, -1]])
    return np.ascontiguousarray(d[np.abs(d[:, 2]) <= max_sin + 1e-12])


def unique_rows(a: np.ndarray) -> np.ndarray:
    """The distinct rows of ``a`` (n, k) in lexicographic order, as ``np.unique(a, axis=0)``,
    deduplicated by hashing first (``np.unique(axis=0)`` sorts every row: 18 s for the wind
    map of a 30 m mountain grid, 0.4 s this way)."""
    import pandas as pd

    u = pd.DataFrame(np.asarray(a, dtype=float)).drop_duplicates().to_numpy(dtype=float)
    return u[np.lexsort(u.T[::-1])]


def wind_samples(wind_uvw: np.ndarray, max_n: int = 600) -> np.ndarray:
    """Distinct wind vectors of ``wind_uvw`` (nz, ny, nx, 3) (levels and mid-levels), at most
    ``max_n`` [m/s]."""
    w = wind_uvw
    levels = [w]
    if w.shape[0] > 1:
        levels.append(0.5 * (w[1:] + w[:-1]))
    winds = unique_rows(np.concatenate([lv.reshape(-1, 3) for lv in levels]))
    if winds.shape[0] > max_n:
        winds = winds[np.linspace(0, winds.shape[0] - 1, max_n).astype(int)]
    return np.ascontiguousarray(winds)


def wind_samples_dense(wind_uvw: np.ndarray, per_gap: int = WIND_INTERP_SAMPLES) -> np.ndarray:
    """Every wind vector of ``wind_uvw`` (nz, ny, nx, 3) (all columns and levels) and
    ``per_gap - 1`` evenly spaced linear interpolations between adjacent levels, deduplicated
    [m/s] (m, 3): the winds :func:`~skyroute.stages.planning.kernels.wind_at` returns are on
    those level-to-level segments."""
    w = wind_uvw
    parts = [w.reshape(-1, 3)]
    for i in range(1, int(per_gap) if w.shape[0] > 1 else 1):
        f = i / per_gap
        parts.append(((1 - f) * w[:-1] + f * w[1:]).reshape(-1, 3))
    return np.ascontiguousarray(unique_rows(np.concatenate(parts)))


def _wind_key(problem: PlanningProblem) -> str:
    """SHA-1 of the problem's wind map (hashing a mountain wind map costs ~7 ms: once per problem)."""
    key = problem.__dict__.get("_wind_key")
    if key is None:
        key = hashlib.sha1(problem.wind_uvw.tobytes() + problem.wind_z_agl_m.tobytes()).hexdigest()
        object.__setattr__(problem, "_wind_key", key)
    return key


def _wind_samples_cached(problem: PlanningProblem) -> np.ndarray:
    ws = problem.__dict__.get("_winds_cache")
    if ws is None:
        ws = WINDS_MEMO.get(_wind_key(problem), lambda: wind_samples(problem.wind_uvw))
        object.__setattr__(problem, "_winds_cache", ws)
    return ws


def energy_ratio_lb_dirs(problem: PlanningProblem, dirs) -> float:
    """min of E_w / E_0 over unit directions ``dirs`` (m, 3) and the problem's wind samples
    (:func:`wind_samples`), capped at 1, times :data:`ENERGY_LB_SAFETY` (1 * 0.9 when no pair
    is flyable).  Memoised on the bytes of (winds, vehicle, dirs)."""
    d = np.ascontiguousarray(np.asarray(dirs, dtype=float).reshape(-1, 3))
    winds = _wind_samples_cached(problem)
    _, _, veh, power = problem.seg_args
    key = hashlib.sha1(_params_bytes(winds, veh, power, d)).hexdigest()
    r = RATIO_MEMO.get(key, lambda: _finite_ratio(ratio_kernel(d, winds, veh, power)))
    return min(1.0, r) * ENERGY_LB_SAFETY


def energy_ratio_lb_dense_dirs(problem: PlanningProblem, dirs) -> float:
    """min of E_w / E_0 over unit directions ``dirs`` (m, 3) and every wind of the map
    (:func:`wind_samples_dense`: all columns, levels and interpolations, no subsampling), times
    :data:`ENERGY_LB_DENSE_SAFETY` (0.99; 1 * 0.99 when no pair is flyable; not capped at 1:
    every wind a segment meets is in the set, so a head wind everywhere counts).  Much tighter
    than :func:`energy_ratio_lb_dirs`; the A* heuristic uses it for the few lattice edge
    directions.  Memoised like it."""
    d = np.ascontiguousarray(np.asarray(dirs, dtype=float).reshape(-1, 3))
    wkey = _wind_key(problem)
    _, _, veh, power = problem.seg_args
    key = "dense" + hashlib.sha1(wkey.encode() + _params_bytes(veh, power, d)).hexdigest()

    def make() -> float:
        winds = WINDS_MEMO.get("densewinds" + wkey, lambda: wind_samples_dense(problem.wind_uvw))
        return _finite_ratio(ratio_kernel(d, winds, veh, power))

    return RATIO_MEMO.get(key, make) * ENERGY_LB_DENSE_SAFETY


def energy_ratio_lb_dense_each(problem: PlanningProblem, dirs) -> np.ndarray:
    """(m,): :func:`energy_ratio_lb_dense_dirs` of each unit direction of ``dirs`` (m, 3) alone
    (the same numbers), in one pass over the winds on every core
    (:func:`~skyroute.stages.planning.kernels.ratio_each_kernel`): the A* lattice's 24 edge
    directions over the 0.3 M winds of the 6 km Helsinki map took 5.4 s one by one.  Memoised
    on the bytes of (winds, vehicle, dirs).  A problem carrying the ``wind_bounds`` stage's
    tiles (``_ratio_tiles``, attached by the strategic planner; the same vehicle and lattice
    directions) takes the minimum over the tiles that meet its wind map instead
    (:func:`~skyroute.stages.planning.wind_bounds.ratio_lb_over`)."""
    d = np.ascontiguousarray(np.asarray(dirs, dtype=float).reshape(-1, 3))
    tiles = problem.__dict__.get("_ratio_tiles")      # the wind_bounds stage's (plan_levels attaches them)
    if tiles is not None and problem.wind_grid is not None:
        r = ratio_lb_over(tiles, problem.wind_grid.bounds, d)
        if r is not None:
            return r * ENERGY_LB_DENSE_SAFETY
    wkey = _wind_key(problem)
    _, _, veh, power = problem.seg_args
    key = "denseeach" + hashlib.sha1(wkey.encode() + _params_bytes(veh, power, d)).hexdigest()

    def make() -> np.ndarray:
        winds = WINDS_MEMO.get("densewinds" + wkey, lambda: wind_samples_dense(problem.wind_uvw))
        return np.array([_finite_ratio(r) for r in ratio_each_kernel(d, winds, veh, power)])

    return RATIO_MEMO.get(key, make) * ENERGY_LB_DENSE_SAFETY


def energy_ratio_lb(problem: PlanningProblem) -> float:
    """:func:`energy_ratio_lb_dirs` over every flyable direction (:func:`fibonacci_dirs`, 400
    points), once per problem."""
    lb = problem.__dict__.get("_lb_cache")
    if lb is None:
        lb = energy_ratio_lb_dirs(problem, fibonacci_dirs(400, problem.seg_args.vehicle.max_sin_path_angle))
        object.__setattr__(problem, "_lb_cache", lb)
    return lb


def cost_rate_lb(problem: PlanningProblem) -> float:
    """Admissible lower bound of f per metre of path [-]: w_l + w_r min(risk) + w_d min(landing)
    + w_e * :func:`energy_ratio_lb` (every term of eq. 11 is >= rate * length), the minima over
    the flyable cells."""
    wl, wr, wd, we = problem.weights
    fin = np.isfinite(problem.floor_m)
    rmin = float(problem.risk_cost[fin].min()) if fin.any() else 0.0
    dmin = float(problem.landing_cost[fin].min()) if fin.any() else 0.0
    e = energy_ratio_lb(problem) if we > 0 else 0.0
    return wl + wr * max(rmin, 0.0) + wd * max(dmin, 0.0) + we * e


__all__ = ["DIRS_ATOL", "ENERGY_LB_DENSE_SAFETY", "ENERGY_LB_SAFETY", "WIND_INTERP_SAMPLES", "BoundMemo", "cost_rate_lb", "ratio_lb_over",
           "energy_ratio_lb", "energy_ratio_lb_dense_dirs", "energy_ratio_lb_dense_each", "energy_ratio_lb_dirs", "fibonacci_dirs", "unique_rows",
           "wind_samples", "wind_samples_dense"]


def ratio_lb_over(tiles, bounds: tuple[float, float, float, float], dirs) -> np.ndarray | None:
    """(k,): per direction of ``dirs`` the minimum of ``ratio_lb`` over the tiles that meet the
    map box ``bounds`` = (xmin, ymin, xmax, ymax) [m] (a wind map's extent; 1 where no wind is
    flyable, as :func:`~.heuristic.energy_ratio_lb_dense_each`), or None when
    ``dirs`` are not the tiles' directions (within :data:`DIRS_ATOL`) or no tile meets the box.

    Parameters
    ----------
    tiles : xarray.Dataset
        :func:`wind_ratio_tiles` output.
    bounds : tuple of float
        The box [m].
    dirs : array_like
        Unit directions (k, 3) [-].

    Returns
    -------
    numpy.ndarray or None
    """
    d = np.asarray(dirs, float).reshape(-1, 3)
    td = np.asarray(tiles["dirs"].values, float)
    if td.shape != d.shape or not np.allclose(td, d, rtol=0.0, atol=DIRS_ATOL):
        return None
    xmin, ymin, xmax, ymax = bounds
    kx = (np.asarray(tiles["x_max_m"].values) > xmin) & (np.asarray(tiles["x_min_m"].values) < xmax)
    ky = (np.asarray(tiles["y_max_m"].values) > ymin) & (np.asarray(tiles["y_min_m"].values) < ymax)
    if not (kx.any() and ky.any()):
        return None
    r = np.asarray(tiles["ratio_lb"].values)[np.ix_(ky, kx)]
    return np.array([_finite_ratio(v) for v in r.reshape(-1, d.shape[0]).min(axis=0)])
