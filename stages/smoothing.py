"""Minimum-snap polynomial trajectories through a polygonal chain (seed 000 step III, ref. [50];
Richter, Bry & Roy, "Polynomial trajectory planning for aggressive quadrotor flight in dense
indoor environments", ISRR 2013, section 3, unconstrained QP).

Formulation
-----------
Each of the n-1 segments is a 7th-order polynomial per axis (8 coefficients) on its own time
``t in [0, T_k]``.  Its end-point derivatives ``d_k = [p, p', p'', p'''](0), [p, p', p'', p'''](T_k)``
map one-to-one to the coefficients (``d_k = A_k c_k``), so the cost
``J = sum_k int_0^T_k |p''''(t)|^2 dt = sum_k d_k^T A_k^-T Q_k A_k^-1 d_k`` is a quadratic form in
the joint derivatives.  Fixed: every waypoint position, and velocity = acceleration = jerk = 0
at the start and the end (at rest).  Free: velocity, acceleration, jerk at the interior
waypoints (shared by the two segments meeting there, which imposes C^3 continuity).  With the
Hessian ``R`` partitioned into fixed (F) and free (P) parts the optimum is the closed form
``d_P = -R_PP^-1 R_FP^T d_F``.  At the optimum the 4th to 6th derivatives are continuous too
(natural conditions of the variational problem), so the curve is C^6 at interior waypoints.

Time is scaled by the mean segment time before solving (conditioning); the axes share the
matrices and are solved together.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from skyroute.pipeline.errors import InputError, PlanningError

N_COEF = 8  # 7th order
N_DER = 4   # derivatives 0..3 fixed/shared at each joint


def _fact_ratio(k: int, r: int) -> float:
    """k! / (k - r)! (0 when k < r)."""
    return math.perm(k, r) if k >= r else 0.0


def _a_matrix(T: float) -> np.ndarray:
    """8x8 map from coefficients to [p..p'''](0), [p..p'''](T)."""
    a = np.zeros((N_COEF, N_COEF))
    for r in range(N_DER):
        a[r, r] = math.factorial(r)
        for k in range(r, N_COEF):
            a[N_DER + r, k] = _fact_ratio(k, r) * T ** (k - r)
    return a


def _q_matrix(T: float, r: int = 4) -> np.ndarray:
    """Hessian of int_0^T (d^r p / dt^r)^2 dt in the coefficients."""
    q = np.zeros((N_COEF, N_COEF))
    for i in range(r, N_COEF):
        for j in range(r, N_COEF):
            e = i + j - 2 * r + 1
            q[i, j] = _fact_ratio(i, r) * _fact_ratio(j, r) * T**e / e
    return q


@dataclass(frozen=True)
class MinSnapTrajectory:
    """Piecewise 7th-order polynomial: ``coef[k, :, axis]`` in ``t - t_k`` [s] of segment k."""

    coef: np.ndarray            # (nseg, 8, 3) coefficients in physical time
    segment_times_s: np.ndarray  # (nseg,)
    waypoints: np.ndarray        # (nseg+1, 3)

    @property
    def knots_s(self) -> np.ndarray:
        """Times of the waypoints [s], from 0 to ``duration_s``."""
        return np.concatenate([[0.0], np.cumsum(self.segment_times_s)])

    @property
    def duration_s(self) -> float:
        return float(np.sum(self.segment_times_s))

    def _eval(self, t, r: int) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t, dtype=float))
        knots = self.knots_s
        k = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, len(self.segment_times_s) - 1)
        tau = np.clip(t, 0.0, self.duration_s) - knots[k]
        out = np.zeros((t.size, 3))
        for j in range(N_COEF - 1, r - 1, -1):        # Horner on d^r/dt^r
            out = out * tau[:, None] + _fact_ratio(j, r) * self.coef[k, j, :]
        return out

    def sample(self, t) -> np.ndarray:
        """Position (m,3) [m] at times ``t`` [s] (clipped to [0, duration])."""
        return self._eval(t, 0)

    def velocity(self, t) -> np.ndarray:
        """Velocity (m,3) [m/s]."""
        return self._eval(t, 1)

    def acceleration(self, t) -> np.ndarray:
        """Acceleration (m,3) [m/s^2]."""
        return self._eval(t, 2)

    def derivative(self, t, order: int) -> np.ndarray:
        """Derivative of any order 0..7 (m,3) [m/s^order]."""
        if not 0 <= order < N_COEF:
            raise InputError(f"order must be 0..7, got {order}")
        return self._eval(t, order)

    def snap_cost(self) -> float:
        """J = int |p''''|^2 dt summed over axes and segments [m^2/s^7]."""
        return float(sum(np.einsum("ia,ij,ja->", c, _q_matrix(T), c)
                         for c, T in zip(self.coef, self.segment_times_s, strict=True)))

    def segment_samples(self, spacing_m: float = 1.0, min_per_segment: int = 8) -> tuple[np.ndarray, np.ndarray]:
        """Points along the curve, about ``spacing_m`` apart (by chord length), and the index of the
        segment each comes from."""
        chord = np.linalg.norm(np.diff(self.waypoints, axis=0), axis=1)
        counts = np.maximum(min_per_segment, np.ceil(chord / spacing_m).astype(int) + 1)
        knots = self.knots_s
        ts, seg = [], []
        for k, c in enumerate(counts):
            ts.append(knots[k] + np.linspace(0.0, self.segment_times_s[k], c))
            seg.append(np.full(c, k))
        t = np.concatenate(ts)
        return self._eval(t, 0), np.concatenate(seg)


def _validate(waypoints, segment_times_s) -> tuple[np.ndarray, np.ndarray]:
    w = np.asarray(waypoints, dtype=float)
    if w.ndim != 2 or w.shape[1] != 3 or w.shape[0] < 2:
        raise InputError(f"waypoints must have shape (n >= 2, 3) [m]; got {w.shape}")
    t = np.asarray(segment_times_s, dtype=float).reshape(-1)
    if t.shape[0] != w.shape[0] - 1:
        raise InputError(f"segment_times_s needs n-1 = {w.shape[0] - 1} values [s]; got {t.shape[0]}")
    if not (np.isfinite(w).all() and np.isfinite(t).all()) or (t <= 0).any():
        raise InputError("waypoints must be finite and segment_times_s finite and > 0 [s]")
    return w, t


def _solve_banded_spd(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve ``a x = b`` for the symmetric positive-definite block-tridiagonal matrix of the free
    joint derivatives (velocity, acceleration, jerk of neighbouring joints: bandwidth 5) in
    O(n) with a banded Cholesky, instead of a dense O(n^3) solve."""
    from scipy.linalg import solveh_banded

    n = a.shape[0]
    bw = 5
    if n <= bw + 1 or np.any(np.triu(a, bw + 1)):  # small, or not banded: dense solve
        return np.linalg.solve(a, b)
    ab = np.zeros((bw + 1, n))
    for k in range(bw + 1):
        ab[bw - k, k:] = np.diagonal(a, k)
    return solveh_banded(ab, b)


def min_snap(waypoints, segment_times_s) -> MinSnapTrajectory:
    """Minimum-snap trajectory through ``waypoints`` (n,3) [m] with ``segment_times_s`` (n-1,) [s],
    at rest at both ends (closed form of Richter et al. 2013, see the module docstring)."""
    w, times = _validate(waypoints, segment_times_s)
    nseg = times.size
    t0 = float(times.mean())                        # time unit for conditioning
    tn = times / t0
    # joint derivative vector: joint j has 4 entries [p, v, a, j] (scaled time units)
    nj = nseg + 1
    ndof = nj * N_DER
    hess = np.zeros((ndof, ndof))
    amaps = []
    for k, T in enumerate(tn):
        ainv = np.linalg.inv(_a_matrix(T))
        amaps.append(ainv)
        h = ainv.T @ _q_matrix(T) @ ainv
        idx = np.r_[k * N_DER:(k + 1) * N_DER, (k + 1) * N_DER:(k + 2) * N_DER]
        hess[np.ix_(idx, idx)] += h
    fixed = np.zeros(ndof, bool)
    fixed[::N_DER] = True                           # every position
    fixed[1:N_DER] = True                           # start v, a, j = 0
    fixed[ndof - N_DER + 1:] = True                 # end v, a, j = 0
    d = np.zeros((ndof, 3))
    d[::N_DER] = w
    free = ~fixed
    if free.any():
        rpp = hess[np.ix_(free, free)]
        rfp = hess[np.ix_(fixed, free)]
        d[free] = -_solve_banded_spd(rpp, rfp.T @ d[fixed])
    coef = np.empty((nseg, N_COEF, 3))
    scale = t0 ** -np.arange(N_COEF)                # c_phys_k = c_scaled_k / t0^k
    for k in range(nseg):
        ck = amaps[k] @ d[k * N_DER:(k + 2) * N_DER]
        coef[k] = ck * scale[:, None]
    return MinSnapTrajectory(coef=coef, segment_times_s=times.copy(), waypoints=w.copy())


def insert_midpoints_where(traj_waypoints, times, bad_segment_indices) -> tuple[np.ndarray, np.ndarray]:
    """Split every listed segment at the midpoint of its straight chord; its time is halved.
    Returns new ``(waypoints (n + nbad, 3), times (n - 1 + nbad,))``."""
    w, t = _validate(traj_waypoints, times)
    bad = np.unique(np.asarray(bad_segment_indices, dtype=int).reshape(-1))
    if bad.size and (bad.min() < 0 or bad.max() >= t.size):
        raise InputError(f"bad_segment_indices must be in 0..{t.size - 1}; got {bad.tolist()}")
    mids = 0.5 * (w[bad] + w[bad + 1])
    new_w = np.insert(w, bad + 1, mids, axis=0)
    t_half = t.copy()
    t_half[bad] *= 0.5
    new_t = np.insert(t_half, bad + 1, t_half[bad])
    return new_w, new_t


def smooth_with_clearance(waypoints, times, is_clear: Callable[[np.ndarray], np.ndarray],
                          max_iter: int = 10, sample_spacing_m: float = 1.0) -> MinSnapTrajectory:
    """Minimum-snap trajectory whose samples (about ``sample_spacing_m`` [m] apart) all satisfy
    ``is_clear(points (m,3)) -> bool (m,)``: segments with a violating sample get a midpoint
    waypoint (Richter et al. 2013, section 5) and the problem is re-solved, at most ``max_iter``
    times.  The polygonal chain itself is assumed clear.  Raises
    :class:`~skyroute.pipeline.errors.PlanningError` if samples still violate after ``max_iter``."""
    w, t = _validate(waypoints, times)
    if max_iter < 0 or not sample_spacing_m > 0:
        raise InputError("max_iter must be >= 0 and sample_spacing_m > 0 [m]")
    for it in range(max_iter + 1):
        traj = min_snap(w, t)
        pts, seg = traj.segment_samples(sample_spacing_m)
        ok = np.asarray(is_clear(pts), dtype=bool).reshape(-1)
        if ok.shape[0] != pts.shape[0]:
            raise InputError(f"is_clear returned {ok.shape[0]} flags for {pts.shape[0]} points")
        bad = np.unique(seg[~ok])
        if bad.size == 0:
            return traj
        if it < max_iter:
            w, t = insert_midpoints_where(w, t, bad)
    raise PlanningError(f"smoothed trajectory still violates clearance on {bad.size} segment(s) after "
                        f"{max_iter} midpoint insertions; raise max_iter or use the polygonal chain")


__all__ = ["MinSnapTrajectory", "insert_midpoints_where", "min_snap", "smooth_with_clearance"]
