"""Dynamic zone partitioning by predicted known-traffic density (seed 004 section III-A).

Every ``T_p`` seconds the known intruders are predicted ``T_p`` ahead with the seed's linear
discrete-time model (eq. 5, :func:`predict_intruders`)::

    [p_{t+1}; v_{t+1}] = [[1, dt], [0, 1]] [p_t; v_t] + [dt^2 / 2; dt] a_t + nu_t

(``a_t`` held constant over the horizon: ``p(T_p) = p + v T_p + a T_p^2 / 2`` exactly; the noise
``nu_t`` is white acceleration noise of 1-sigma ``sigma_a`` [m/s^2] entering through the same
``[dt^2/2; dt]`` column, whose covariance is propagated alongside and gives the 1-sigma position
spread ``sigma_p`` [m] at ``T_p``).

The workspace rectangle ``[x_min, x_max] x [y_min, y_max]`` is then split into ``Z = 2^r``
zones named by ``r``-bit binary sequences, most significant bit first: bits at odd positions
(1st, 3rd, ...) halve the zone along X, bits at even positions along Y; bit 0 keeps the lower
half, 1 the upper one (seed Fig. 5 and the evaluation algorithm of Fig. 7,
:func:`zone_bounds`).  A zone is *sparse* when at most one predicted intruder is in it, *dense*
otherwise.  ``r`` grows from 1 until the three conditions hold (:func:`partition`):

1. the zone of the UAS's present position is sparse;
2. if the goal is within ``goal_threshold_m`` [m] of the present position, its zone is sparse;
3. the two zones are connected through sparse zones (breadth-first search on the grid of
   zones, neighbours sharing an edge; the goal zone itself may be entered even when dense).

The dense zones, except the goal's, are the *dense zone definition*; they are obstacles
(full-height boxes, :class:`ZoneBox`) until the next prediction.  :func:`dense_mask` rasterises
them into the grid's no-fly mask (every cell whose closed square meets a box: conservative),
the form the planners and the tactical replay take temporary zones in.
:class:`ZoneTracker` runs the prediction every ``T_p`` and reports whether the definition
changed, so a potential field or mask is recomputed only then.

An intruder counts in every zone met by the square ``mean +- k_sigma * sigma_p`` of its
predicted position (``k_sigma = 0``: the seed's count of predicted positions); points on a
split line belong to the upper half (the last zone takes the workspace's upper edge).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from skyroute.stages.base import InputError

__all__ = ["Prediction", "ZoneBox", "ZonePartition", "ZoneTracker", "dense_mask", "partition", "predict_intruders",
           "zone_bounds", "zone_of"]


@dataclass(frozen=True)
class Prediction:
    """Known intruders ``T_p`` ahead: ``xyz_m`` (N, 3) [m] mean position, ``vel_mps`` (N, 3)
    [m/s] mean velocity, ``sigma_p_m`` (N,) [m] 1-sigma position spread per axis."""

    xyz_m: np.ndarray
    vel_mps: np.ndarray
    sigma_p_m: np.ndarray


@dataclass(frozen=True)
class ZoneBox:
    """A dense zone as an obstacle: ``x_min_m <= x <= x_max_m``, ``y_min_m <= y <= y_max_m``
    [m, map CRS], all altitudes; ``bits``: its binary sequence."""

    bits: str
    x_min_m: float
    x_max_m: float
    y_min_m: float
    y_max_m: float

    @property
    def polygon_xy(self) -> np.ndarray:
        """(4, 2) [m] corners, counter-clockwise."""
        return np.array([[self.x_min_m, self.y_min_m], [self.x_max_m, self.y_min_m],
                         [self.x_max_m, self.y_max_m], [self.x_min_m, self.y_max_m]])


@dataclass(frozen=True)
class ZonePartition:
    """Result of :func:`partition`: bit length ``r``; ``counts`` (2^r,) predicted intruders per
    zone (zone ``k`` is the binary sequence of ``k`` on ``r`` bits); ``own_zone`` /
    ``goal_zone`` bit strings; ``dense`` the dense zone definition (sorted bit strings, the
    goal's zone left out); ``ok`` False when no ``r <= r_max`` met the three conditions (then
    ``reason`` says which failed at ``r_max``)."""

    r: int
    counts: np.ndarray
    own_zone: str
    goal_zone: str
    dense: tuple[str, ...]
    boxes: tuple[ZoneBox, ...]
    ok: bool = True
    reason: str = ""

    @property
    def definition(self) -> tuple[int, tuple[str, ...]]:
        """What a change of is a new zone definition: ``(r, dense bit strings)``."""
        return (self.r, self.dense)


# ------------------------------------------------------------------ prediction (eq. 5)


def predict_intruders(xyz_m, vel_mps, horizon_s: float, acc_mps2=None, *, dt_s: float = 0.1,
                      sigma_a_mps2: float = 0.0) -> Prediction:
    """Propagate eq. 5 from the present states ``xyz_m`` (N, 3) [m], ``vel_mps`` (N, 3) [m/s],
    ``acc_mps2`` (N, 3) [m/s^2] (default 0) over ``horizon_s`` [s] in steps of ``dt_s`` [s]
    (the last step shortened to land on the horizon).  The mean is exact for any ``dt_s``
    (constant acceleration); the covariance of white acceleration noise of 1-sigma
    ``sigma_a_mps2`` per axis is propagated as ``P <- F P F^T + G G^T sigma_a^2``."""
    p = np.atleast_2d(np.asarray(xyz_m, float)).copy()
    v = np.atleast_2d(np.asarray(vel_mps, float)).copy()
    a = np.zeros_like(p) if acc_mps2 is None else np.atleast_2d(np.asarray(acc_mps2, float))
    if p.shape != v.shape or p.shape != a.shape or p.shape[-1] != 3:
        raise InputError(f"intruder positions {p.shape}, velocities {v.shape} and accelerations {a.shape} must all be "
                         "(N, 3) [m, m/s, m/s^2]")
    if not (math.isfinite(horizon_s) and horizon_s >= 0):
        raise InputError(f"prediction horizon T_p = {horizon_s} s must be finite and >= 0")
    if not (dt_s > 0 and sigma_a_mps2 >= 0):
        raise InputError(f"dt_s = {dt_s} s must be > 0 and sigma_a = {sigma_a_mps2} m/s^2 >= 0")
    P = np.zeros((2, 2))           # per-axis covariance of (position, velocity)
    t = 0.0
    while t < horizon_s - 1e-12:
        dt = min(dt_s, horizon_s - t)
        p = p + dt * v + 0.5 * dt * dt * a
        v = v + dt * a
        F = np.array([[1.0, dt], [0.0, 1.0]])
        G = np.array([[0.5 * dt * dt], [dt]])
        P = F @ P @ F.T + (G @ G.T) * sigma_a_mps2 ** 2
        t += dt
    return Prediction(p, v, np.full(p.shape[0], math.sqrt(P[0, 0])))


# ------------------------------------------------------------------ binary sequences (Fig. 5, 7)


def _check_ws(workspace) -> tuple[float, float, float, float]:
    x0, x1, y0, y1 = map(float, workspace)
    if not (x1 > x0 and y1 > y0):
        raise InputError(f"workspace {workspace} must be (x_min, x_max, y_min, y_max) [m] with x_max > x_min and "
                         "y_max > y_min")
    return x0, x1, y0, y1


def zone_bounds(bits: str, workspace) -> tuple[float, float, float, float]:
    """``(x_min, x_max, y_min, y_max)`` [m] of the zone named ``bits`` (seed Fig. 7: MSB first,
    odd positions split X, even positions split Y; 0 = lower half, 1 = upper half)."""
    x0, x1, y0, y1 = _check_ws(workspace)
    if any(b not in "01" for b in bits):
        raise InputError(f"zone name {bits!r} must be a string of 0 and 1")
    for pos, b in enumerate(bits, start=1):
        if pos % 2 == 1:
            mid = 0.5 * (x0 + x1)
            x0, x1 = (x0, mid) if b == "0" else (mid, x1)
        else:
            mid = 0.5 * (y0 + y1)
            y0, y1 = (y0, mid) if b == "0" else (mid, y1)
    return x0, x1, y0, y1


def _shape(r: int) -> tuple[int, int]:
    """(columns along X, rows along Y) of the 2^r zones."""
    return 2 ** ((r + 1) // 2), 2 ** (r // 2)


def _bits_of(ix: int, iy: int, r: int) -> str:
    """Binary sequence of the zone in column ``ix`` (X) and row ``iy`` (Y): interleave the
    column's bits (odd positions) and the row's (even positions), MSB first."""
    nxb, nyb = (r + 1) // 2, r // 2
    xs = format(ix, f"0{nxb}b") if nxb else ""
    ys = format(iy, f"0{nyb}b") if nyb else ""
    return "".join(xs[k // 2] if k % 2 == 0 else ys[k // 2] for k in range(r))


def _cells(xy: np.ndarray, r: int, ws) -> tuple[np.ndarray, np.ndarray]:
    x0, x1, y0, y1 = ws
    nx, ny = _shape(r)
    ix = np.clip(np.floor((xy[:, 0] - x0) / (x1 - x0) * nx).astype(np.int64), 0, nx - 1)
    iy = np.clip(np.floor((xy[:, 1] - y0) / (y1 - y0) * ny).astype(np.int64), 0, ny - 1)
    return ix, iy


def zone_of(xy, r: int, workspace) -> str:
    """Binary sequence of the zone (of ``2^r``) holding the point ``xy`` [m] (clamped into the
    workspace)."""
    ws = _check_ws(workspace)
    ix, iy = _cells(np.asarray(xy, float).reshape(1, -1)[:, :2], r, ws)
    return _bits_of(int(ix[0]), int(iy[0]), r)


def _count(pred_xy: np.ndarray, half_m: np.ndarray, r: int, ws) -> np.ndarray:
    """(ny, nx) predicted intruders per zone (each counted once in every zone its square meets)."""
    nx, ny = _shape(r)
    cnt = np.zeros((ny, nx), np.int64)
    if pred_xy.shape[0] == 0:
        return cnt
    lo_x, lo_y = _cells(pred_xy - half_m[:, None], r, ws)
    hi_x, hi_y = _cells(pred_xy + half_m[:, None], r, ws)
    x0, x1, y0, y1 = ws
    inside = ((pred_xy[:, 0] + half_m >= x0) & (pred_xy[:, 0] - half_m <= x1)
              & (pred_xy[:, 1] + half_m >= y0) & (pred_xy[:, 1] - half_m <= y1))
    for k in np.nonzero(inside)[0]:
        cnt[lo_y[k]:hi_y[k] + 1, lo_x[k]:hi_x[k] + 1] += 1
    return cnt


def _connected(sparse: np.ndarray, a: tuple[int, int], b: tuple[int, int]) -> bool:
    """Breadth-first search from zone ``a`` to zone ``b`` (row, col) through sparse zones
    (edge neighbours); ``b`` may be dense."""
    if a == b:
        return True
    ny, nx = sparse.shape
    seen = np.zeros_like(sparse)
    seen[a] = True
    q = deque([a])
    while q:
        i, j = q.popleft()
        for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            u, w = i + di, j + dj
            if 0 <= u < ny and 0 <= w < nx and not seen[u, w]:
                if (u, w) == b:
                    return True
                if sparse[u, w]:
                    seen[u, w] = True
                    q.append((u, w))
    return False


def partition(own_xy, goal_xy, predicted_xy, workspace, *, r_max: int = 12, goal_threshold_m: float = math.inf,
              sigma_p_m=None, k_sigma: float = 0.0) -> ZonePartition:
    """Seed 004 zone determination: the smallest ``r`` in ``1..r_max`` whose 2^r zones meet the
    three conditions of the module docstring, for the UAS at ``own_xy``, its goal ``goal_xy``
    and the predicted intruder positions ``predicted_xy`` (N, 2 or 3) [m].  ``sigma_p_m`` (N,)
    [m] and ``k_sigma``: count each intruder in every zone its +-k sigma square meets."""
    ws = _check_ws(workspace)
    if not (isinstance(r_max, int | np.integer) and 1 <= r_max <= 24):
        raise InputError(f"r_max = {r_max} must be an integer in 1..24 (2^r zones)")
    pred = np.asarray(predicted_xy, float)
    pred = np.zeros((0, 2)) if pred.size == 0 else pred.reshape(-1, pred.shape[-1])[:, :2]
    half = np.zeros(pred.shape[0]) if sigma_p_m is None else k_sigma * np.broadcast_to(
        np.asarray(sigma_p_m, float), (pred.shape[0],))
    own = np.asarray(own_xy, float).reshape(1, -1)[:, :2]
    goal = np.asarray(goal_xy, float).reshape(1, -1)[:, :2]
    near_goal = float(np.hypot(*(own - goal)[0])) <= goal_threshold_m
    why = ""
    for r in range(1, r_max + 1):
        cnt = _count(pred, half, r, ws)
        sparse = cnt <= 1
        oi, oj = _cells(own, r, ws)
        gi, gj = _cells(goal, r, ws)
        a, b = (int(oj[0]), int(oi[0])), (int(gj[0]), int(gi[0]))
        fails = []
        if not sparse[a]:
            fails.append("own zone dense")
        if near_goal and not sparse[b]:
            fails.append("goal zone dense")
        if not fails and not _connected(sparse, a, b):
            fails.append("own and goal zones not connected through sparse zones")
        own_bits, goal_bits = _bits_of(a[1], a[0], r), _bits_of(b[1], b[0], r)
        dense = sorted(_bits_of(j, i, r) for i, j in zip(*np.nonzero(~sparse), strict=True)
                       if (i, j) != b)
        flat = np.zeros(2 ** r, np.int64)
        for i in range(cnt.shape[0]):
            for j in range(cnt.shape[1]):
                flat[int(_bits_of(j, i, r), 2)] = cnt[i, j]
        if not fails:
            boxes = tuple(ZoneBox(d, *zone_bounds(d, ws)) for d in dense)
            return ZonePartition(r, flat, own_bits, goal_bits, tuple(dense), boxes)
        why = f"r = {r}: " + "; ".join(fails)
    boxes = ()
    return ZonePartition(r_max, flat, own_bits, goal_bits, (), boxes, ok=False,
                         reason=f"no r <= {r_max} meets the zone conditions ({why}); no dense zone is used")


# ------------------------------------------------------------------ zones as obstacles


def dense_mask(boxes, x0_m: float, y1_m: float, resolution_m: float, shape: tuple[int, int]) -> np.ndarray:
    """(ny, nx) bool: grid cells (north-up raster, top-left corner ``(x0_m, y1_m)`` [m], square
    cells of ``resolution_m`` [m]) whose closed square meets one of ``boxes``
    (:class:`ZoneBox`), conservative at the box edges."""
    ny, nx = shape
    m = np.zeros((ny, nx), bool)
    for b in boxes:
        c0 = int(math.floor((b.x_min_m - x0_m) / resolution_m - 1e-9))
        c1 = int(math.floor((b.x_max_m - x0_m) / resolution_m + 1e-9))
        r0 = int(math.floor((y1_m - b.y_max_m) / resolution_m - 1e-9))
        r1 = int(math.floor((y1_m - b.y_min_m) / resolution_m + 1e-9))
        c0, c1 = max(c0, 0), min(c1, nx - 1)
        r0, r1 = max(r0, 0), min(r1, ny - 1)
        if c0 <= c1 and r0 <= r1:
            m[r0:r1 + 1, c0:c1 + 1] = True
    return m


@dataclass
class ZoneTracker:
    """Zone determination every ``period_s`` = T_p [s] with a horizon of T_p: :meth:`update`
    returns the current partition and whether its definition changed since the last call that
    recomputed (``recomputations`` counts changes: what a potential field or no-fly mask
    would be rebuilt for)."""

    workspace: tuple[float, float, float, float]
    period_s: float = 10.0
    r_max: int = 12
    goal_threshold_m: float = math.inf
    sigma_a_mps2: float = 0.0
    k_sigma: float = 0.0
    current: ZonePartition | None = None
    t_last_s: float = -math.inf
    recomputations: int = 0
    history: list = field(default_factory=list)

    def update(self, t_s: float, own_xy, goal_xy, xyz_m, vel_mps, acc_mps2=None, *,
               force: bool = False) -> tuple[ZonePartition, bool]:
        """At ``t_s`` [s]: if a period has passed (or ``force``: e.g. the known traffic changed),
        predict and partition again.  Returns ``(partition, changed)``."""
        if self.current is not None and not force and t_s < self.t_last_s + self.period_s - 1e-9:
            return self.current, False
        pred = predict_intruders(np.reshape(xyz_m, (-1, 3)), np.reshape(vel_mps, (-1, 3)), self.period_s,
                                 None if acc_mps2 is None else np.reshape(acc_mps2, (-1, 3)),
                                 sigma_a_mps2=self.sigma_a_mps2)
        part = partition(own_xy, goal_xy, pred.xyz_m, self.workspace, r_max=self.r_max,
                         goal_threshold_m=self.goal_threshold_m, sigma_p_m=pred.sigma_p_m, k_sigma=self.k_sigma)
        changed = self.current is None or part.definition != self.current.definition
        if changed:
            self.recomputations += 1
        self.current, self.t_last_s = part, float(t_s)
        self.history.append((float(t_s), part.definition, changed))
        return part, changed
