"""Trajectories through a polygonal chain.

STEP III flies the chain with :func:`corner_trajectory` (circular fillets within the
flight-path-angle cone or stops, timed exactly under the vehicle's hard limits; see its
docstring).  The minimum-snap polynomials below are kept as a library function (they keep the
velocity through a corner, so they cannot bound the flight-path angle near a hairpin).

Minimum-snap polynomial trajectories through a polygonal chain (seed 000 step III, ref. [50];
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

from skyroute.stages.base import InputError, PlanningError

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


class _Kinematics:
    """``sample`` / ``velocity`` / ``acceleration`` of a trajectory with ``_eval(t, order)``."""

    def _eval(self, t, r: int) -> np.ndarray:  # pragma: no cover - provided by the subclass
        raise NotImplementedError

    def sample(self, t) -> np.ndarray:
        """Position (m, 3) [m] at times ``t`` [s] (clipped to [0, duration])."""
        return self._eval(t, 0)

    def velocity(self, t) -> np.ndarray:
        """Velocity (m, 3) [m/s]."""
        return self._eval(t, 1)

    def acceleration(self, t) -> np.ndarray:
        """Acceleration (m, 3) [m/s^2] (right-continuous where it jumps)."""
        return self._eval(t, 2)


@dataclass(frozen=True)
class MinSnapTrajectory(_Kinematics):
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
    :class:`~skyroute.stages.base.PlanningError` if samples still violate after ``max_iter``."""
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




# --------------------------------------------------------------------------------------------
# Corner-filleted chain with an exact speed profile (STEP III, hard vehicle limits)
# --------------------------------------------------------------------------------------------

_LINE, _ARC = 0, 1
STOP_TURN_RAD = math.radians(175.0)   # turns sharper than this always stop (tiny, slow fillets)
PASS_TURN_RAD = 1e-9                  # straighter than this: no corner at all
MIN_SAMPLE_GAP_S = 0.01               # [s] smallest interval between two output samples
_MIN_PHASE_S = 1e-9                   # [s] shorter phases (float rounding) are dropped


@dataclass(frozen=True)
class KinematicLimits:
    """Hard limits of the trajectory (tolerance 0): ``max_flight_path_angle_deg`` [deg],
    ``max_airspeed_mps`` [m/s] (|v_ground - wind|), ``max_climb_rate_mps`` /
    ``max_descent_rate_mps`` [m/s] (positive), ``max_acceleration_mps2`` [m/s^2] (3-D norm)."""

    max_flight_path_angle_deg: float
    max_airspeed_mps: float
    max_climb_rate_mps: float
    max_descent_rate_mps: float
    max_acceleration_mps2: float

    @classmethod
    def of(cls, vehicle) -> KinematicLimits:
        """The limits of a :class:`~skyroute.stages.vehicle.VehicleProfile`."""
        return cls(vehicle.max_flight_path_angle_deg, vehicle.max_airspeed_mps, vehicle.max_climb_rate_mps,
                   vehicle.max_descent_rate_mps, vehicle.max_acceleration_mps2)


@dataclass(frozen=True)
class CornerTrajectory(_Kinematics):
    """Straight lines and circular fillet arcs, timed by phases of constant tangential
    acceleration (lines) or constant speed (arcs).

    Phase ``i`` starts at ``phase_t0_s[i]`` [s]; lines: ``p = origin + (s0 + v0 tau + a tau^2 / 2) e1``;
    arcs (radius ``R``, start ``origin``, start tangent ``e1``, unit normal ``e2`` towards the
    centre): ``phi = (v0 tau) / R``, ``p = origin + R sin(phi) e1 + R (1 - cos(phi)) e2``.
    ``piece_t_s``: times of the piece boundaries (every point where a line meets an arc or a
    stop corner); ``waypoints`` the positions there; ``corner_kind`` per interior chain vertex:
    ``"arc"``, ``"stop"`` or ``"pass"`` (collinear)."""

    phase_t0_s: np.ndarray
    kind: np.ndarray
    origin: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    s0: np.ndarray
    v0: np.ndarray
    a: np.ndarray
    radius_m: np.ndarray
    duration_s: float
    piece_t_s: np.ndarray
    waypoints: np.ndarray
    corner_kind: tuple[str, ...]
    corner_reason: tuple[str, ...]

    @property
    def knots_s(self) -> np.ndarray:
        """Times of the piece boundaries [s] (0 ... duration)."""
        return self.piece_t_s

    @property
    def segment_times_s(self) -> np.ndarray:
        """Durations of the pieces [s]."""
        return np.diff(self.piece_t_s)

    def _eval(self, t, order: int) -> np.ndarray:
        t = np.clip(np.atleast_1d(np.asarray(t, dtype=float)), 0.0, self.duration_s)
        i = np.clip(np.searchsorted(self.phase_t0_s, t, side="right") - 1, 0, self.phase_t0_s.size - 1)
        tau = t - self.phase_t0_s[i]
        e1, e2, o = self.e1[i], self.e2[i], self.origin[i]
        v0, a, s0, R = self.v0[i], self.a[i], self.s0[i], self.radius_m[i]
        line = self.kind[i] == _LINE
        out = np.zeros((t.size, 3))
        # lines
        if order == 0:
            s = s0 + v0 * tau + 0.5 * a * tau * tau
            out = o + s[:, None] * e1
        elif order == 1:
            out = (v0 + a * tau)[:, None] * e1
        else:
            out = a[:, None] * e1
        arc = ~line
        if arc.any():
            Ra = R[arc]
            phi = v0[arc] * tau[arc] / Ra
            sp, cp = np.sin(phi)[:, None], np.cos(phi)[:, None]
            if order == 0:
                out[arc] = o[arc] + Ra[:, None] * (sp * e1[arc] + (1 - cp) * e2[arc])
            elif order == 1:
                out[arc] = v0[arc][:, None] * (cp * e1[arc] + sp * e2[arc])
            else:
                out[arc] = (v0[arc] ** 2 / Ra)[:, None] * (-sp * e1[arc] + cp * e2[arc])
        return out

    @classmethod
    def at_rest(cls, point_xyz_m) -> CornerTrajectory:
        """A vehicle at rest at ``point_xyz_m`` (3,) [m]: a trajectory of duration 0 (give it a
        :meth:`with_hold` to hover there)."""
        p = np.asarray(point_xyz_m, float).reshape(3)
        return cls(phase_t0_s=np.zeros(1), kind=np.array([_LINE], np.int8), origin=p[None].copy(),
                   e1=np.array([[1.0, 0.0, 0.0]]), e2=np.zeros((1, 3)), s0=np.zeros(1), v0=np.zeros(1),
                   a=np.zeros(1), radius_m=np.zeros(1), duration_s=0.0, piece_t_s=np.zeros(1), waypoints=p[None].copy(),
                   corner_kind=(), corner_reason=())

    def with_hold(self, hold_s: float) -> CornerTrajectory:
        """The same trajectory followed by a hover of ``hold_s`` [s] (> 0) at its end point: one
        more line phase at speed 0 (acceleration 0) and one more piece.  The trajectory ends
        at rest, so the speed stays continuous (a tactical escape holds there until a conflict
        clears, :mod:`skyroute.stages.tactical.escape`)."""
        h = float(hold_s)
        if not (math.isfinite(h) and h > 0):
            raise InputError(f"hold_s = {hold_s} s must be finite and > 0")
        v_end = float(self.v0[-1] + self.a[-1] * (self.duration_s - self.phase_t0_s[-1]))
        if self.kind[-1] != _LINE or abs(v_end) > 1e-6:
            raise InputError("a hold can only follow a trajectory that ends at rest on a line")
        end = self.sample([self.duration_s])[0]
        T = float(self.duration_s)
        return CornerTrajectory(
            phase_t0_s=np.append(self.phase_t0_s, T), kind=np.append(self.kind, np.int8(_LINE)),
            origin=np.vstack([self.origin, end]), e1=np.vstack([self.e1, self.e1[-1]]),
            e2=np.vstack([self.e2, self.e2[-1]]), s0=np.append(self.s0, 0.0), v0=np.append(self.v0, 0.0),
            a=np.append(self.a, 0.0), radius_m=np.append(self.radius_m, 0.0), duration_s=T + h,
            piece_t_s=np.append(self.piece_t_s, T + h), waypoints=np.vstack([self.waypoints, end]),
            corner_kind=self.corner_kind, corner_reason=self.corner_reason)

    def sample_times(self, dt_s: float, min_gap_s: float = 0.1) -> np.ndarray:
        """Output times: every ``dt_s`` [s] plus every piece and phase boundary (so no chord
        spans two pieces, and the speed is linear between samples: the trapezoidal length is
        exact); a regular time closer than ``min_gap_s`` to a boundary is dropped, and of
        boundaries closer than :data:`MIN_SAMPLE_GAP_S` only the first is kept (float rounding
        of positions ~1e6 m would dominate a finite difference over a shorter interval; the
        piece skipped is then shorter than v_max x 10 ms)."""
        n = max(int(math.ceil(self.duration_s / dt_s - 1e-9)), 1)
        reg = np.linspace(0.0, self.duration_s, n + 1)
        out = [0.0]
        for x in np.unique(np.concatenate([self.piece_t_s, self.phase_t0_s, [self.duration_s]])):
            if x - out[-1] >= MIN_SAMPLE_GAP_S:
                out.append(float(x))
        if out[-1] != self.duration_s:          # the end point replaces a boundary just before it
            if len(out) > 1 and self.duration_s - out[-1] < MIN_SAMPLE_GAP_S:
                out[-1] = self.duration_s
            else:
                out.append(self.duration_s)
        k = np.array(out)
        gap = max(min_gap_s, MIN_SAMPLE_GAP_S)
        near = np.min(np.abs(reg[:, None] - k[None, :]), axis=1) < gap
        return np.unique(np.concatenate([reg[~near], k]))


def turn_and_stop(p0, e1, e2, v0_mps: float, radius_m: float, angle_rad: float,
                  limits: KinematicLimits) -> CornerTrajectory:
    """A vehicle at ``p0`` (3,) [m] flying ``v0_mps`` [m/s] along the unit vector ``e1`` turns at
    once on a circular arc of ``radius_m`` [m] towards the unit vector ``e2`` (perpendicular to
    ``e1``) by ``angle_rad`` [rad] at constant speed, then brakes to rest along the arc's end
    tangent at the acceleration limit (the tactical escape's turn, :mod:`skyroute.stages.tactical.escape`).

    Hard limits: the normal acceleration ``v0^2 / R`` and the braking must be within
    ``max_acceleration_mps2``, the arc's tangents (combinations of ``e1`` and ``e2``) within the
    flight-path-angle cone and the vertical-rate limits (PlanningError otherwise); the airspeed
    in wind is the validator's to check."""
    p0, e1, e2 = (np.asarray(a, float) for a in (p0, e1, e2))
    v, R, phi = float(v0_mps), float(radius_m), float(angle_rad)
    if not (v > 0 and R > 0 and 0 < phi < math.pi):
        raise InputError(f"turn_and_stop: need v0 > 0, R > 0 and 0 < angle < pi; got {v}, {R}, {phi}")
    if abs(float(e1 @ e2)) > 1e-9 or abs(np.linalg.norm(e1) - 1) > 1e-9 or abs(np.linalg.norm(e2) - 1) > 1e-9:
        raise InputError("turn_and_stop: e1 and e2 must be orthogonal unit vectors")
    a_max = float(limits.max_acceleration_mps2)
    if v * v / R > a_max * (1 + 1e-12):
        raise PlanningError(f"a turn of radius {R:.1f} m at {v:.2f} m/s needs {v * v / R:.2f} m/s^2 > "
                            f"{a_max} m/s^2")
    end_t = math.cos(phi) * e1 + math.sin(phi) * e2
    tan_a = math.tan(math.radians(limits.max_flight_path_angle_deg))
    if not _cone_ok(e1, end_t, tan_a):
        raise PlanningError("the turn's tangents leave the flight-path-angle cone")
    uz_max, uz_min = max(e1[2], end_t[2]), min(e1[2], end_t[2])
    if v * uz_max > limits.max_climb_rate_mps + 1e-9 or -v * uz_min > limits.max_descent_rate_mps + 1e-9:
        raise PlanningError("the turn exceeds the vertical-rate limits")
    t_arc = R * phi / v
    p1 = p0 + R * math.sin(phi) * e1 + R * (1 - math.cos(phi)) * e2
    t_stop = v / a_max
    rows = [(0.0, _ARC, p0, e1, e2, 0.0, v, 0.0, R), (t_arc, _LINE, p1, end_t, np.zeros(3), 0.0, v, -a_max, 0.0)]
    p2 = p1 + end_t * (v * v / (2 * a_max))
    cols = list(zip(*rows, strict=True))
    return CornerTrajectory(
        phase_t0_s=np.array(cols[0]), kind=np.array(cols[1], dtype=np.int8), origin=np.array(cols[2]),
        e1=np.array(cols[3]), e2=np.array(cols[4]), s0=np.array(cols[5]), v0=np.array(cols[6]),
        a=np.array(cols[7]), radius_m=np.array(cols[8]), duration_s=t_arc + t_stop,
        piece_t_s=np.array([0.0, t_arc, t_arc + t_stop]), waypoints=np.array([p0, p1, p2]),
        corner_kind=(), corner_reason=())


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _cone_ok(u1: np.ndarray, u2: np.ndarray, tan_a: float) -> bool:
    """Every non-negative combination ``c = (1-s) u1 + s u2`` (s in [0, 1]) has a flight-path
    angle <= alpha: ``q(s) = tan^2(alpha) |c_h|^2 - c_z^2 >= 0``, a quadratic in s checked
    exactly at its end points and its stationary point."""
    h1, h2, z1, z2 = u1[:2], u2[:2], u1[2], u2[2]
    dh, dz = h2 - h1, z2 - z1
    t2 = tan_a * tan_a
    c2 = t2 * float(dh @ dh) - dz * dz          # q(s) = c2 s^2 + c1 s + c0
    c1 = 2 * (t2 * float(h1 @ dh) - z1 * dz)
    c0 = t2 * float(h1 @ h1) - z1 * z1
    cand = [0.0, 1.0]
    if c2 != 0.0:
        s = -c1 / (2 * c2)
        if 0.0 < s < 1.0:
            cand.append(s)
    tol = 1e-12
    return all(c2 * s * s + c1 * s + c0 >= -tol for s in cand)


def _airspeed_cap(u: np.ndarray, winds: np.ndarray, v_max: float) -> float:
    """Largest ground speed v along unit ``u`` with |v u - w| <= v_max for every wind w (k, 3):
    ``v <= u.w + sqrt((u.w)^2 - |w|^2 + v_max^2)``.  Also for every wind in their convex hull
    (|v u - w| is convex in w)."""
    uw = winds @ u
    disc = uw * uw - np.einsum("ij,ij->i", winds, winds) + v_max * v_max
    if np.any(disc < 0):
        return 0.0
    return float(np.min(uw + np.sqrt(disc)))


def _vertical_cap(uz_max: float, uz_min: float, lim: KinematicLimits) -> float:
    cap = math.inf
    if uz_max > 0:
        cap = min(cap, lim.max_climb_rate_mps / uz_max)
    if uz_min < 0:
        cap = min(cap, lim.max_descent_rate_mps / -uz_min)
    return cap


def corner_trajectory(waypoints, leg_speed_mps, limits: KinematicLimits, winds=np.zeros((1, 3)),
                      fillet_ok: Callable[[np.ndarray, np.ndarray, np.ndarray], bool] | None = None,
                      max_shrink: int = 6, v_start_mps: float = 0.0, stop_at: tuple[int, ...] = ()) -> CornerTrajectory:
    """Fly the polygonal chain ``waypoints`` (n, 3) [m] from rest (or from ``v_start_mps``
    along the first leg) to rest within ``limits``.

    Geometry: each interior vertex P (incoming unit u1, outgoing u2, turn angle theta) becomes
    a circular arc tangent to both legs, cut back ``d`` = half the shorter adjacent leg
    (radius ``d / tan(theta / 2)``), if (a) every tangent of the arc -- a non-negative
    combination of u1 and u2 -- is within the flight-path-angle cone (:func:`_cone_ok`,
    exact) and (b) ``fillet_ok(A, P, B)`` accepts the triangle A P B that contains the arc
    (e.g. a clearance check of every cell under it); ``d`` is halved up to ``max_shrink``
    times for (b).  Otherwise the vehicle stops at P (speed 0: the direction may change).
    Every chord between two points of one piece is then a non-negative combination of u1, u2
    (arc) or parallel to the leg (line), so it is within the angle limit.

    Timing (exact, closed form): lines accelerate / cruise / decelerate at the acceleration
    limit; arcs are flown at constant speed ``v <= sqrt(a_max R)`` (normal acceleration only).
    The speed of each piece is capped by ``leg_speed_mps`` (n-1,) [m/s] (the legs' target
    ground speeds), the airspeed limit for every wind vector of ``winds`` (k, 3) [m/s]
    (:func:`_airspeed_cap`; on an arc with the bound |c| >= cos(theta / 2) of the tangents'
    combinations) and the vertical-rate limits; node speeds come from one forward and one
    backward pass (|v_1^2 - v_0^2| <= 2 a L on lines, equal speeds at both ends of an arc).

    ``v_start_mps`` [m/s] (>= 0): the speed at the first waypoint, along the first leg (a
    vehicle already flying that leg: the tactical replans of :mod:`skyroute.stages.tactical`).
    Above the first leg's target speed it decelerates at the limit; above the first leg's
    airspeed or vertical-rate cap, or too fast to stop where the chain requires it, it is a
    :class:`~skyroute.stages.base.PlanningError`.  ``stop_at``: indices of interior vertices
    where the vehicle must stop (no fillet), e.g. the point a tactical replan turns at."""
    w = np.asarray(waypoints, dtype=float)
    if w.ndim != 2 or w.shape[1] != 3 or w.shape[0] < 2 or not np.isfinite(w).all():
        raise InputError(f"waypoints must be finite with shape (n >= 2, 3) [m]; got {w.shape}")
    legs = np.diff(w, axis=0)
    length = np.linalg.norm(legs, axis=1)
    vleg = np.broadcast_to(np.asarray(leg_speed_mps, dtype=float), (legs.shape[0],)).copy()
    keep = length > 1e-9                     # drop repeated points
    new_index = np.cumsum(np.r_[True, keep]) - 1
    stop_at = {int(new_index[j]) for j in stop_at if 0 < j < w.shape[0] - 1}
    if not keep.all():
        w = np.concatenate([w[:1], w[1:][keep]])
        vleg, legs, length = vleg[keep], legs[keep], length[keep]
    if w.shape[0] < 2:
        raise InputError("waypoints must contain two distinct points")
    if not (np.isfinite(vleg).all() and (vleg > 0).all()):
        raise InputError("leg_speed_mps must be finite and > 0 [m/s]")
    v_start = float(v_start_mps)
    if not (math.isfinite(v_start) and v_start >= 0):
        raise InputError(f"v_start_mps = {v_start_mps} must be finite and >= 0 [m/s]")
    winds = np.atleast_2d(np.asarray(winds, dtype=float))
    a_max = float(limits.max_acceleration_mps2)
    tan_a = math.tan(math.radians(limits.max_flight_path_angle_deg))
    u = legs / length[:, None]
    nl = u.shape[0]
    cut = np.zeros(w.shape[0])                  # cut-back d at each vertex (0: no arc)
    kinds: list[str] = []
    why: list[str] = []
    for i in range(1, w.shape[0] - 1):
        u1, u2 = u[i - 1], u[i]
        cth = float(np.clip(u1 @ u2, -1.0, 1.0))
        th = math.acos(cth)
        if i in stop_at:
            kinds.append("stop")
            why.append("requested stop")
            continue
        if th < PASS_TURN_RAD:
            kinds.append("pass")
            why.append("")
            continue
        if th > STOP_TURN_RAD:
            kinds.append("stop")
            why.append(f"turn {math.degrees(th):.0f} deg")
            continue
        if not _cone_ok(u1, u2, tan_a):
            kinds.append("stop")
            why.append("a fillet would exceed the flight-path angle")
            continue
        d = 0.5 * min(length[i - 1], length[i])
        ok = False
        for _ in range(max_shrink + 1):
            if fillet_ok is None or fillet_ok(w[i] - d * u1, w[i], w[i] + d * u2):
                ok = True
                break
            d *= 0.5
        if ok:
            cut[i] = d
            kinds.append("arc")
            why.append("")
        else:
            kinds.append("stop")
            why.append("no clearance for a fillet")
    # pieces: (kind, start point, length, cap, e1, e2, R)
    pieces = []
    node_cap = [0.0]                            # speed cap at each piece boundary
    for k in range(nl):
        a_pt = w[k] + cut[k] * u[k]
        b_pt = w[k + 1] - cut[k + 1] * u[k]
        lk = float(np.linalg.norm(b_pt - a_pt))
        cap = min(vleg[k], _airspeed_cap(u[k], winds, limits.max_airspeed_mps),
                  _vertical_cap(u[k][2], u[k][2], limits))
        if not cap > 0:
            raise PlanningError(f"leg {k} ({w[k].round(1).tolist()} -> {w[k + 1].round(1).tolist()}): the wind "
                                f"exceeds the airspeed limit {limits.max_airspeed_mps} m/s, no ground speed is possible")
        if k == 0 and v_start > 0:
            hard = min(_airspeed_cap(u[0], winds, limits.max_airspeed_mps), _vertical_cap(u[0][2], u[0][2], limits))
            if v_start > hard:
                raise PlanningError(f"the current speed {v_start:.2f} m/s exceeds the first leg's airspeed / "
                                    f"vertical-rate cap {hard:.2f} m/s")
            node_cap[0] = v_start
        if lk > 1e-9:
            pieces.append((_LINE, a_pt, lk, cap, u[k], np.zeros(3), 0.0))
            node_cap.append(cap)
        if k + 1 < w.shape[0] - 1:
            kind = kinds[k]
            if kind == "arc":
                u1, u2 = u[k], u[k + 1]
                cth = float(np.clip(u1 @ u2, -1.0, 1.0))
                th = math.acos(cth)
                n = _unit(u2 - cth * u1)
                R = cut[k + 1] / math.tan(th / 2)
                ch = math.cos(th / 2)
                vcap = min(vleg[k], vleg[k + 1], math.sqrt(a_max * R),
                           ch * min(_airspeed_cap(u1, winds, limits.max_airspeed_mps),
                                    _airspeed_cap(u2, winds, limits.max_airspeed_mps)),
                           _vertical_cap(max(u1[2], u2[2]) / (ch if max(u1[2], u2[2]) > 0 else 1.0),
                                         min(u1[2], u2[2]) / (ch if min(u1[2], u2[2]) < 0 else 1.0), limits))
                pieces.append((_ARC, b_pt, R * th, vcap, u1, n, R))
                node_cap[-1] = min(node_cap[-1], vcap)
                node_cap.append(vcap)
            elif kind == "stop":
                node_cap[-1] = 0.0
            else:   # pass: the next line's cap applies at the joint too
                nxt = min(vleg[k + 1], _airspeed_cap(u[k + 1], winds, limits.max_airspeed_mps),
                          _vertical_cap(u[k + 1][2], u[k + 1][2], limits))
                node_cap[-1] = min(node_cap[-1], nxt)
    node_cap[-1] = 0.0
    v = np.array(node_cap, dtype=float)
    # node j is the start of piece j; node j + 1 its end
    for j, pc in enumerate(pieces):                     # forward
        if pc[0] == _LINE:
            v[j + 1] = min(v[j + 1], math.sqrt(v[j] ** 2 + 2 * a_max * pc[2]))
        else:
            v[j + 1] = min(v[j + 1], v[j])
    if v_start > 0:   # the start speed is given, not a cap: no pass may lower it
        need = v_start
    for j in range(len(pieces) - 1, -1, -1):            # backward
        pc = pieces[j]
        if pc[0] == _LINE:
            v[j] = min(v[j], math.sqrt(v[j + 1] ** 2 + 2 * a_max * pc[2]))
        else:
            v[j] = min(v[j], v[j + 1])
    if v_start > 0 and v[0] < need - 1e-9:
        raise PlanningError(f"from {v_start:.2f} m/s the vehicle cannot slow down in time for the chain "
                            f"(at most {v[0]:.2f} m/s at its start)")
    if v_start > 0:
        v[0] = v_start
    # phases
    rows = []       # (t0, kind, origin, e1, e2, s0, v0, a, R)
    t = 0.0
    piece_t = [0.0]
    pts = [pieces[0][1]]
    for j, (kind, p0, lk, cap, e1, e2, R) in enumerate(pieces):
        v0, v1 = float(v[j]), float(v[j + 1])
        if kind == _ARC:
            if not v0 > 0:
                raise PlanningError("internal: a fillet arc got speed 0")
            rows.append((t, _ARC, p0, e1, e2, 0.0, v0, 0.0, R))
            t += lk / v0
        else:
            if v0 > cap:   # the start speed above the first leg's target: decelerate to it first
                sd = (v0 * v0 - cap * cap) / (2 * a_max)
                rows.append((t, _LINE, p0, e1, e2, 0.0, v0, -a_max, 0.0))
                t += (v0 - cap) / a_max
                p0, lk, v0 = p0 + sd * e1, lk - sd, cap
            vp = min(cap, math.sqrt(0.5 * (v0 * v0 + v1 * v1) + a_max * lk))
            vp = max(vp, v0, v1)
            s1 = max((vp * vp - v0 * v0) / (2 * a_max), 0.0)
            s3 = max((vp * vp - v1 * v1) / (2 * a_max), 0.0)
            s2 = max(lk - s1 - s3, 0.0)
            if (vp - v0) / a_max > _MIN_PHASE_S:
                rows.append((t, _LINE, p0, e1, e2, 0.0, v0, a_max, 0.0))
                t += (vp - v0) / a_max
            if s2 / vp > _MIN_PHASE_S:
                rows.append((t, _LINE, p0, e1, e2, s1, vp, 0.0, 0.0))
                t += s2 / vp
            if (vp - v1) / a_max > _MIN_PHASE_S:
                rows.append((t, _LINE, p0, e1, e2, s1 + s2, vp, -a_max, 0.0))
                t += (vp - v1) / a_max
        piece_t.append(t)
        pts.append(pieces[j + 1][1] if j + 1 < len(pieces) else w[-1])
    # guard: the speed is continuous from phase to phase (a defect here would be an infinite
    # acceleration the later checks sample only by chance)
    for r0, r1 in zip(rows[:-1], rows[1:], strict=True):
        v_end = r0[6] + r0[7] * (r1[0] - r0[0])
        if abs(v_end - r1[6]) > 1e-6 * max(1.0, abs(r1[6])):
            raise PlanningError(f"internal: speed jumps from {v_end:.3f} to {r1[6]:.3f} m/s at t = {r1[0]:.2f} s")
    cols = list(zip(*rows, strict=True))
    return CornerTrajectory(
        phase_t0_s=np.array(cols[0]), kind=np.array(cols[1], dtype=np.int8), origin=np.array(cols[2]),
        e1=np.array(cols[3]), e2=np.array(cols[4]), s0=np.array(cols[5]), v0=np.array(cols[6]),
        a=np.array(cols[7]), radius_m=np.array(cols[8]), duration_s=float(t), piece_t_s=np.array(piece_t),
        waypoints=np.array(pts), corner_kind=tuple(kinds), corner_reason=tuple(why))


__all__ = ["CornerTrajectory", "KinematicLimits", "MinSnapTrajectory", "corner_trajectory", "insert_midpoints_where",
           "turn_and_stop",
           "min_snap", "smooth_with_clearance"]
