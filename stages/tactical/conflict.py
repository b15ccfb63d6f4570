"""Separation checks of a timed ownship trajectory against intruder tracks (issue 11).

The ownship's remaining plan is a timed polyline: sample times ``t_s`` (n,) [s, strictly
increasing] and positions ``xyz_m`` (n, 3) [m], linear in time between samples, existing on
``[t_s[0], t_s[-1]]``.  Each intruder is a piecewise-linear 4-D track (waypoint times [s] and
positions [m]) that exists only between its first and last waypoint.  Both are packed once per
traffic update into :class:`IntruderTracks`.

Exact check (``dt_c_s = 0``, :func:`first_conflict`): on every interval of the merged
breakpoints of the two tracks both move linearly, so the relative position is
``D(tau) = D0 + Dv tau`` and ``|D|^2 < sep^2`` is a quadratic inequality in ``tau``: the first
conflict time is the smaller root (closed form, no sampling).  A conflict means *strictly*
closer than ``sep_m`` (a trajectory that touches the sphere of radius ``sep_m`` is clear);
the reported ``t_s`` is the infimum of the conflict set (where the distance equals
``sep_m``), and ``distance_m``/``t_cpa_s`` are the minimum distance over that encounter (up to
where the distance is back to ``sep_m`` or either track ends).

Time margin (``dt_c_s > 0``): the intruder may be anywhere on its track within
``[t - dt_c, t + dt_c]``, i.e. a conflict at ``t`` when
``f(t) = min over tau in [t - dt_c, t + dt_c] of |P(t) - Q(tau)| < sep``.  The test is
conservative (never misses a conflict): for a piece ``[a, b]`` of the ownship's chord,
``g = segment-segment distance(P([a, b]), Q([a - dt_c, b + dt_c]))`` is <= ``f(t)`` for every
``t`` in ``[a, b]``; pieces with ``g < sep`` are bisected down to leaves of
``max(DTC_RESOLUTION_S, DTC_RELATIVE_RESOLUTION * dt_c_s)`` [s] and the start of the first
such leaf is reported, so ``t_s`` is never later than the exact first time of ``f < sep``.  ``distance_m`` is then the minimum of
``g`` over the run of consecutive hit leaves (a lower bound of ``f``).

N-aircraft picture (:func:`pairwise_conflicts`): state-based closest point of approach of
aircraft flying straight, BlueSky's method (cylinder: horizontal ``sep_m``, vertical
``vsep_m``); :func:`pairwise_conflicts_numpy` is BlueSky's vectorised numpy formulation and
the reference the numba version (uniform grid on lookahead-swept boxes) reproduces.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numba
import numpy as np

from skyroute.stages.base import InputError
from skyroute.stages.traffic import Intruder, intruders_from_records, seg_seg_d2

__all__ = ["Conflict", "DTC_RELATIVE_RESOLUTION", "DTC_RESOLUTION_S", "IntruderTracks", "first_conflict", "min_separation",
           "pairwise_conflicts", "pairwise_conflicts_numpy"]

DTC_RESOLUTION_S = 0.01          # [s] leaf duration of the time-margin bisection (dt_c_s > 0) ...
DTC_RELATIVE_RESOLUTION = 0.01   # ... or this fraction of dt_c_s if longer


# ------------------------------------------------------------------ data


@dataclass(frozen=True)
class IntruderTracks:
    """Intruder tracks packed for the compiled kernels.

    Track ``i`` is rows ``offsets[i]:offsets[i + 1]`` of ``t_s`` (M,) [s, strictly increasing
    within a track] and ``xyz_m`` (M, 3) [m]; ``radius_m`` (N,) [m]; ``ids`` (N,) names."""

    t_s: np.ndarray
    xyz_m: np.ndarray
    offsets: np.ndarray
    radius_m: np.ndarray
    ids: tuple[str, ...]

    def __post_init__(self):
        t = np.ascontiguousarray(np.asarray(self.t_s, dtype=float).reshape(-1))
        p = np.ascontiguousarray(np.asarray(self.xyz_m, dtype=float))
        off = np.ascontiguousarray(np.asarray(self.offsets, dtype=np.int64).reshape(-1))
        r = np.ascontiguousarray(np.asarray(self.radius_m, dtype=float).reshape(-1))
        ids = tuple(str(i) for i in self.ids)
        n = len(ids)
        if p.shape != (t.size, 3) or off.shape != (n + 1,) or r.shape != (n,):
            raise InputError(f"IntruderTracks: need t_s (M,), xyz_m (M, 3), offsets (N+1,), radius_m (N,) and N ids; "
                             f"got {t.shape}, {p.shape}, {off.shape}, {r.shape} and {n} ids "
                             f"(build it with IntruderTracks.from_intruders)")
        if off[0] != 0 or off[-1] != t.size or np.any(np.diff(off) < 1):
            raise InputError("IntruderTracks: offsets must start at 0, end at M and give each track >= 1 waypoint")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p)) and np.all(np.isfinite(r)) and np.all(r >= 0)):
            raise InputError("IntruderTracks: times, positions and radii must be finite (radii >= 0)")
        inner = np.ones(max(t.size - 1, 0), bool)
        inner[off[1:-1] - 1] = False                    # pairs that straddle two tracks
        if np.any(np.diff(t)[inner] <= 0):
            raise InputError("IntruderTracks: waypoint times must increase strictly within each track")
        for name, value in (("t_s", t), ("xyz_m", p), ("offsets", off), ("radius_m", r), ("ids", ids)):
            object.__setattr__(self, name, value)

    @property
    def n(self) -> int:
        """Number of intruders."""
        return len(self.ids)

    @classmethod
    def from_intruders(cls, intruders: Iterable[Intruder | Mapping]) -> IntruderTracks:
        """Pack :class:`~skyroute.stages.traffic.Intruder` objects (or scenario records, see
        :func:`~skyroute.stages.traffic.intruders_from_records`); they are validated there."""
        items = list(intruders)
        out: list[Intruder] = []
        for n, it in enumerate(items):
            if isinstance(it, Intruder):
                out.append(it)
            elif isinstance(it, Mapping):
                out.extend(intruders_from_records([{"id": str(n), **it}]))
            else:
                raise InputError(f"intruder {n}: expected a skyroute.stages.traffic.Intruder or a record "
                                 f"mapping, got {type(it).__name__}")
        counts = np.array([it.times_s.size for it in out], dtype=np.int64)
        offsets = np.zeros(len(out) + 1, dtype=np.int64)
        np.cumsum(counts, out=offsets[1:])
        t = np.ascontiguousarray(np.concatenate([it.times_s for it in out]) if out else np.zeros(0), float)
        p = np.ascontiguousarray(np.concatenate([it.xyz_m for it in out]) if out else np.zeros((0, 3)), float)
        r = np.array([float(it.radius_m) for it in out], dtype=float)
        return cls(t, p, offsets, r, tuple(str(it.id) for it in out))


@dataclass(frozen=True)
class Conflict:
    """The first loss of separation with one intruder.

    ``t_s`` [s]: first time the distance drops below the separation (for ``dt_c_s > 0``: the
    conservative, never later, estimate); ``index``/``id``: the intruder; ``distance_m`` [m]
    and ``t_cpa_s`` [s]: minimum distance over that encounter and when; ``own_xyz_m``,
    ``intruder_xyz_m`` (3,) [m] and ``own_velocity_mps``, ``intruder_velocity_mps`` (3,)
    [m/s] at ``t_s`` (the intruder's clamped to its track's time span)."""

    t_s: float
    index: int
    id: str
    distance_m: float
    t_cpa_s: float
    own_xyz_m: np.ndarray
    intruder_xyz_m: np.ndarray
    own_velocity_mps: np.ndarray
    intruder_velocity_mps: np.ndarray


# ------------------------------------------------------------------ kernels: track geometry
#
# A track is rows lo:hi of (t, p, v): times [s], positions [m] and the velocity [m/s] of the
# segment starting at each row (zero on a track's last row), so that the position at time x
# on segment k is p[k] + v[k] (x - t[k]); a one-row track is a point that exists at t[lo].


@numba.njit(cache=True, nogil=True)
def _velocities(t, p, off):
    """Per-row segment velocities [m/s] of the tracks rows off[i]:off[i + 1]."""
    v = np.zeros((t.size, 3))
    for i in range(off.size - 1):
        for k in range(off[i], off[i + 1] - 1):
            dt = t[k + 1] - t[k]
            for d in range(3):
                v[k, d] = (p[k + 1, d] - p[k, d]) / dt
    return v


@numba.njit(cache=True, nogil=True)
def _seg(t, lo, hi, x):
    """Segment index k in [lo, hi - 2] with t[k] <= x < t[k+1] (clipped); lo if one row."""
    if hi - lo < 2:
        return lo
    k = lo + np.searchsorted(t[lo:hi], x, side="right") - 1
    return min(max(k, lo), hi - 2)


@numba.njit(cache=True, nogil=True)
def _seg_end(t, lo, hi, k):
    return t[k + 1] if hi - lo >= 2 else t[lo]


@numba.njit(cache=True, nogil=True)
def _at(t, p, v, k, x):
    s = x - t[k]
    return p[k, 0] + v[k, 0] * s, p[k, 1] + v[k, 1] * s, p[k, 2] + v[k, 2] * s


@numba.njit(cache=True, nogil=True)
def _walk(ot, op, ov, it, ip, iv, ilo, ihi, s2, lo, hi, mode, res):
    """Walk the merged breakpoints of the ownship (rows 0:no) and intruder rows ilo:ihi on
    [lo, hi].  mode 0: first conflict time only (res[0]); mode 1: first conflict + encounter
    (res = t_s, d_min, t_cpa, P, Q, V, W at t_s); mode 2: minimum distance (res[0], res[1]).
    Returns True if a conflict (modes 0/1) was found."""
    no = ot.size
    if lo > hi:
        return False
    a = _seg(ot, 0, no, lo)
    b = _seg(it, ilo, ihi, lo)
    u = lo
    inside = False
    found = False
    dmin2 = np.inf
    while True:
        ea = _seg_end(ot, 0, no, a)
        eb = _seg_end(it, ilo, ihi, b)
        w = min(ea, eb, hi)
        L = max(w - u, 0.0)
        px, py, pz = _at(ot, op, ov, a, u)
        qx, qy, qz = _at(it, ip, iv, b, u)
        d0x, d0y, d0z = px - qx, py - qy, pz - qz
        dvx, dvy, dvz = ov[a, 0] - iv[b, 0], ov[a, 1] - iv[b, 1], ov[a, 2] - iv[b, 2]
        aa = dvx * dvx + dvy * dvy + dvz * dvz
        bb = d0x * dvx + d0y * dvy + d0z * dvz
        cc0 = d0x * d0x + d0y * d0y + d0z * d0z
        if mode == 2:
            tm = 0.0
            if aa > 0.0:
                tm = min(max(-bb / aa, 0.0), L)
            d2 = max(aa * tm * tm + 2.0 * bb * tm + cc0, 0.0)
            if d2 < dmin2:
                dmin2 = d2
                res[1] = u + tm
        else:
            cc = cc0 - s2
            tstart = 0.0
            if not inside:
                t1 = np.inf
                if cc < 0.0:
                    t1 = 0.0
                elif bb < 0.0 and aa > 0.0:
                    disc = bb * bb - aa * cc
                    if disc > 0.0:
                        t1 = cc / (-bb + math.sqrt(disc))
                if t1 <= L:
                    found = True
                    inside = True
                    tstart = t1
                    res[0] = u + t1
                    if mode == 0:
                        return True
                    res[3], res[4], res[5] = px + ov[a, 0] * t1, py + ov[a, 1] * t1, pz + ov[a, 2] * t1
                    res[6], res[7], res[8] = qx + iv[b, 0] * t1, qy + iv[b, 1] * t1, qz + iv[b, 2] * t1
                    for d in range(3):
                        res[9 + d] = ov[a, d]
                        res[12 + d] = iv[b, d]
            if inside:
                if aa > 0.0:
                    disc = bb * bb - aa * cc
                    t2 = (-bb + math.sqrt(disc)) / aa if disc >= 0.0 else tstart
                    tend = min(max(t2, tstart), L)
                    tm = min(max(-bb / aa, tstart), tend)
                else:
                    t2 = np.inf
                    tm = tstart
                d2 = max(aa * tm * tm + 2.0 * bb * tm + cc0, 0.0)
                if d2 < dmin2:
                    dmin2 = d2
                    res[2] = u + tm
                if t2 < L:
                    break
        if w >= hi:
            break
        if ea <= w and a < no - 2:
            a += 1
        if eb <= w and b < ihi - 2:
            b += 1
        u = w
    if mode == 2:
        res[0] = math.sqrt(dmin2)
    elif found:
        res[1] = math.sqrt(dmin2)
    return found


@numba.njit(cache=True, nogil=True)
def _first_exact(ot, op, tt, tp, off, sep2, t_from):
    """(index, t) of the first exact conflict over all intruders (-1, inf if none)."""
    ov = _velocities(ot, op, np.array([0, ot.size]))
    tv = _velocities(tt, tp, off)
    res = np.empty(15)
    best = np.inf
    ib = -1
    for i in range(off.size - 1):
        ilo, ihi = off[i], off[i + 1]
        lo = max(ot[0], tt[ilo], t_from)
        hi = min(ot[-1], tt[ihi - 1], best)
        if _walk(ot, op, ov, tt, tp, tv, ilo, ihi, sep2[i], lo, hi, 0, res):
            if res[0] < best:
                best = res[0]
                ib = i
    return ib, best


@numba.njit(cache=True, nogil=True)
def _encounter(ot, op, tt, tp, ilo, ihi, s2, lo, hi, res):
    """First conflict with one intruder and its encounter (_walk mode 1)."""
    ov = _velocities(ot, op, np.array([0, ot.size]))
    tv = _velocities(tt, tp, np.array([ilo, ihi]))
    return _walk(ot, op, ov, tt, tp, tv, ilo, ihi, s2, lo, hi, 1, res)


@numba.njit(cache=True, nogil=True)
def _min_sep(ot, op, tt, tp, off, t_from, out):
    ov = _velocities(ot, op, np.array([0, ot.size]))
    tv = _velocities(tt, tp, off)
    res = np.empty(15)
    for i in range(off.size - 1):
        ilo, ihi = off[i], off[i + 1]
        lo = max(ot[0], tt[ilo], t_from)
        hi = min(ot[-1], tt[ihi - 1])
        out[i] = np.inf
        if lo <= hi:
            _walk(ot, op, ov, tt, tp, tv, ilo, ihi, 0.0, lo, hi, 2, res)
            out[i] = res[0]


# ------------------------------------------------------------------ kernels: time margin


@numba.njit(cache=True, nogil=True)
def _pos(t, p, v, lo, hi, x):
    """Position at time x (clamped to the track's span) of track rows lo:hi."""
    x = min(max(x, t[lo]), t[hi - 1])
    return _at(t, p, v, _seg(t, lo, hi, x), x)


@numba.njit(cache=True, nogil=True)
def _swept_d2(ot, op, ov, ka, a, b, it, ip, iv, ilo, ihi, dtc):
    """Squared distance between the ownship chord P([a, b]) (on segment ka) and the
    intruder's track over [a - dtc, b + dtc] (inf if the intruder does not exist then)."""
    ax, ay, az = _at(ot, op, ov, ka, a)
    bx, by, bz = _at(ot, op, ov, ka, b)
    ta = max(a - dtc, it[ilo])
    tb = min(b + dtc, it[ihi - 1])
    if ta > tb:
        return np.inf
    k = _seg(it, ilo, ihi, ta)
    q0x, q0y, q0z = _at(it, ip, iv, k, ta)
    best = np.inf
    while True:
        te = min(_seg_end(it, ilo, ihi, k), tb)
        q1x, q1y, q1z = _at(it, ip, iv, k, te)
        best = min(best, seg_seg_d2(ax, ay, az, bx, by, bz, q0x, q0y, q0z, q1x, q1y, q1z))
        if te >= tb or k >= ihi - 2:
            break
        k += 1
        q0x, q0y, q0z = q1x, q1y, q1z
    return best


@numba.njit(cache=True, nogil=True)
def _walk_dtc(ot, op, ov, it, ip, iv, ilo, ihi, s2, dtc, lo, hi, leaf, encounter, res):
    """Time-margin test on [lo, hi] (see the module docstring).  res[0] = start of the first
    hit leaf; with ``encounter`` also res[1] = min distance over the run of hit leaves and
    res[2] its leaf start.  Returns True if a leaf hits."""
    if lo > hi:
        return False
    no = ot.size
    stack_a = np.empty(128)
    stack_b = np.empty(128)
    inside = False
    dmin2 = np.inf
    k0 = _seg(ot, 0, no, lo)
    for k in range(k0, max(no - 1, k0 + 1)):
        ca = max(lo, ot[k])
        cb = min(hi, ot[k + 1]) if no >= 2 else ca
        if cb < ca:
            break
        stack_a[0] = ca
        stack_b[0] = cb
        sp = 1
        while sp > 0:
            sp -= 1
            x0, x1 = stack_a[sp], stack_b[sp]
            g = _swept_d2(ot, op, ov, k, x0, x1, it, ip, iv, ilo, ihi, dtc)
            if g >= s2:
                if inside:
                    res[1] = math.sqrt(dmin2)
                    return True
                continue
            if x1 - x0 > leaf and sp < 126:
                xm = 0.5 * (x0 + x1)
                stack_a[sp], stack_b[sp] = xm, x1      # right half processed after the left
                stack_a[sp + 1], stack_b[sp + 1] = x0, xm
                sp += 2
                continue
            if not inside:
                inside = True
                res[0] = x0
                if not encounter:
                    return True
            if g < dmin2:
                dmin2 = g
                res[2] = x0
        if cb >= hi:
            break
    if inside:
        res[1] = math.sqrt(dmin2)
    return inside


@numba.njit(cache=True, nogil=True)
def _first_dtc(ot, op, tt, tp, off, sep2, t_from, dtc, leaf, only):
    """(index, t) of the first time-margin conflict (-1, inf if none); ``only`` >= 0: that
    intruder alone, with its encounter in res."""
    ov = _velocities(ot, op, np.array([0, ot.size]))
    tv = _velocities(tt, tp, off)
    res = np.empty(3)
    best = np.inf
    ib = -1
    for i in range(off.size - 1):
        if only >= 0 and i != only:
            continue
        ilo, ihi = off[i], off[i + 1]
        lo = max(ot[0], tt[ilo] - dtc, t_from)
        hi = min(ot[-1], tt[ihi - 1] + dtc, best)
        if _walk_dtc(ot, op, ov, tt, tp, tv, ilo, ihi, sep2[i], dtc, lo, hi, leaf, only >= 0, res):
            if res[0] < best:
                best = res[0]
                ib = i
    return ib, best, res


# ------------------------------------------------------------------ public: trajectory checks


def _own(t_s, xyz_m) -> tuple[np.ndarray, np.ndarray]:
    t = np.ascontiguousarray(np.asarray(t_s, dtype=float))
    p = np.ascontiguousarray(np.asarray(xyz_m, dtype=float))
    if t.ndim != 1 or t.size == 0 or p.shape != (t.size, 3):
        raise InputError(f"ownship trajectory: need sample times t_s (n,) with n >= 1 and positions xyz_m (n, 3); "
                         f"got t_s {t.shape} and xyz_m {p.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
        raise InputError("ownship trajectory: sample times and positions must be finite (no NaN/inf)")
    bad = np.nonzero(np.diff(t) <= 0)[0]
    if bad.size:
        i = int(bad[0]) + 1
        raise InputError(f"ownship trajectory: sample times must increase strictly, but sample {i} "
                         f"(t = {t[i]} s) is not after sample {i - 1} (t = {t[i - 1]} s)")
    return t, p


def _tracks(tracks) -> IntruderTracks:
    if not isinstance(tracks, IntruderTracks):
        raise InputError(f"tracks must be an IntruderTracks (IntruderTracks.from_intruders(intruders)), "
                         f"got {type(tracks).__name__}")
    return tracks


def _per_aircraft(value, n: int, name: str) -> np.ndarray:
    v = np.asarray(value, dtype=float)
    if v.ndim == 0:
        v = np.full(n, float(v))
    if v.shape != (n,):
        raise InputError(f"{name} must be a scalar or an array of shape ({n},) (one per aircraft), got {v.shape}")
    if not (np.all(np.isfinite(v)) and np.all(v >= 0)):
        raise InputError(f"{name} [m] must be finite and >= 0")
    return np.ascontiguousarray(v)


def _t_from(t_from_s: float) -> float:
    t = float(t_from_s)
    if math.isnan(t) or t == math.inf:
        raise InputError(f"t_from_s = {t_from_s} s must be a time or -inf")
    return t


def first_conflict(t_s, xyz_m, tracks: IntruderTracks, sep_m, t_from_s: float = -math.inf,
                   dt_c_s: float = 0.0) -> Conflict | None:
    """The earliest loss of separation at or after ``t_from_s`` [s] between the ownship's
    timed polyline (``t_s`` (n,) [s], ``xyz_m`` (n, 3) [m]) and the intruders, or ``None``.

    ``sep_m`` [m]: scalar or (N,) separation per intruder (e.g. ``r_own + r_i + d_c``); a
    conflict is a distance strictly below it.  ``dt_c_s`` [s] >= 0: time margin on the
    intruders' positions (conservative test, see the module docstring).  Exact (closed form)
    for ``dt_c_s = 0``."""
    t, p = _own(t_s, xyz_m)
    tr = _tracks(tracks)
    sep = _per_aircraft(sep_m, tr.n, "sep_m")
    t0 = _t_from(t_from_s)
    dtc = float(dt_c_s)
    if not (math.isfinite(dtc) and dtc >= 0):
        raise InputError(f"time margin dt_c_s = {dt_c_s} s must be finite and >= 0")
    if tr.n == 0:
        return None
    sep2 = sep * sep
    if dtc == 0.0:
        i, _ = _first_exact(t, p, tr.t_s, tr.xyz_m, tr.offsets, sep2, t0)
        if i < 0:
            return None
        ilo, ihi = tr.offsets[i], tr.offsets[i + 1]
        res = np.empty(15)
        lo = max(t[0], tr.t_s[ilo], t0)
        hi = min(t[-1], tr.t_s[ihi - 1])
        _encounter(t, p, tr.t_s, tr.xyz_m, ilo, ihi, sep2[i], lo, hi, res)
        return Conflict(float(res[0]), int(i), tr.ids[i], float(res[1]), float(res[2]),
                        res[3:6].copy(), res[6:9].copy(), res[9:12].copy(), res[12:15].copy())
    leaf = max(DTC_RESOLUTION_S, DTC_RELATIVE_RESOLUTION * dtc)
    i, _, _ = _first_dtc(t, p, tr.t_s, tr.xyz_m, tr.offsets, sep2, t0, dtc, leaf, -1)
    if i < 0:
        return None
    _, ts, res = _first_dtc(t, p, tr.t_s, tr.xyz_m, tr.offsets, sep2, t0, dtc, leaf, i)
    ilo, ihi = tr.offsets[i], tr.offsets[i + 1]
    P, V = _state_at(t, p, ts)
    Q, W = _state_at(tr.t_s[ilo:ihi], tr.xyz_m[ilo:ihi], ts)
    return Conflict(float(ts), int(i), tr.ids[i], float(res[1]), float(res[2]), P, Q, V, W)


def _state_at(t: np.ndarray, p: np.ndarray, x: float) -> tuple[np.ndarray, np.ndarray]:
    """Position [m] and velocity [m/s] of a polyline at time x [s] clamped to its span."""
    x = min(max(x, t[0]), t[-1])
    if t.size < 2:
        return p[0].copy(), np.zeros(3)
    k = min(max(int(np.searchsorted(t, x, side="right")) - 1, 0), t.size - 2)
    v = (p[k + 1] - p[k]) / (t[k + 1] - t[k])
    return p[k] + v * (x - t[k]), v


def min_separation(t_s, xyz_m, tracks: IntruderTracks, t_from_s: float = -math.inf) -> np.ndarray:
    """(N,) exact minimum distance [m] between the ownship's timed polyline and each intruder
    over their common time span from ``t_from_s`` [s] on (``inf`` where they never coexist)."""
    t, p = _own(t_s, xyz_m)
    tr = _tracks(tracks)
    out = np.empty(tr.n)
    if tr.n:
        _min_sep(t, p, tr.t_s, tr.xyz_m, tr.offsets, _t_from(t_from_s), out)
    return out


# ------------------------------------------------------------------ N-aircraft picture


def _picture(xyz_m, vel_mps, sep_m, lookahead_s, vsep_m):
    x = np.ascontiguousarray(np.asarray(xyz_m, dtype=float))
    v = np.ascontiguousarray(np.asarray(vel_mps, dtype=float))
    if x.ndim != 2 or x.shape[1] != 3 or v.shape != x.shape:
        raise InputError(f"traffic picture: need positions xyz_m (N, 3) [m] and velocities vel_mps (N, 3) [m/s] "
                         f"of the same shape; got {x.shape} and {v.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
        raise InputError("traffic picture: positions and velocities must be finite")
    n = x.shape[0]
    r = _per_aircraft(sep_m, n, "sep_m")
    h = r if vsep_m is None else _per_aircraft(vsep_m, n, "vsep_m")
    T = float(lookahead_s)
    if not (math.isfinite(T) and T > 0):
        raise InputError(f"lookahead_s = {lookahead_s} s must be finite and > 0")
    return x, v, r, h, T


_EMPTY = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0))


def pairwise_conflicts_numpy(xyz_m, vel_mps, sep_m, lookahead_s: float, vsep_m=None, block: int = 256):
    """Baseline: BlueSky's state-based conflict detection, vectorised numpy (TU Delft,
    ``bluesky/traffic/asas/statebased.py``, ``StateBased.detect``), in Cartesian coordinates.

    Aircraft fly straight at constant velocity.  Pair (i, j) (i < j) separation is the
    larger of the two aircraft's ``sep_m`` (horizontal [m]) and ``vsep_m`` (vertical [m],
    default ``sep_m``), a cylinder as in BlueSky.  Horizontal CPA ``t_cpa = -(dx du + dy dv) /
    |dv|^2`` (``|dv|^2`` limited below by 1e-6), ``d_cpa^2 = |dist^2 - t_cpa^2 |dv|^2|``,
    horizontal conflict interval ``t_cpa -+ sqrt(R^2 - d_cpa^2) / |dv|``, vertical crossing
    times of ``-+vsep`` (vertical rate difference limited to 1e-6), a conflict if the two
    intervals overlap, ``t_out > 0`` and ``t_in < lookahead_s``.  Evaluated in blocks of
    ``block`` rows (BlueSky's full N x N matrices, memory-bounded).

    Returns ``(i, j, t_cpa_s, d_cpa_m, t_in_s)`` sorted by (i, j); ``d_cpa_m`` horizontal,
    ``t_in_s`` < 0 when already in conflict."""
    x, v, r, h, T = _picture(xyz_m, vel_mps, sep_m, lookahead_s, vsep_m)
    n = x.shape[0]
    out = []
    for s in range(0, n, block):
        e = min(n, s + block)
        rows = np.arange(s, e)[:, None]
        cols = np.arange(n)[None, :]
        dx = x[None, :, 0] - x[s:e, None, 0]
        dy = x[None, :, 1] - x[s:e, None, 1]
        dist = np.sqrt(dx * dx + dy * dy)
        du = v[None, :, 0] - v[s:e, None, 0]
        dv = v[None, :, 1] - v[s:e, None, 1]
        dv2 = du * du + dv * dv
        dv2 = np.where(np.abs(dv2) < 1e-6, 1e-6, dv2)
        vrel = np.sqrt(dv2)
        tcpa = -(du * dx + dv * dy) / dv2
        dcpa2 = np.abs(dist * dist - tcpa * tcpa * dv2)
        rpz = np.maximum(r[s:e, None], r[None, :])
        R2 = rpz * rpz
        swhorconf = dcpa2 < R2
        dxinhor = np.sqrt(np.maximum(0.0, R2 - dcpa2))
        dtinhor = dxinhor / vrel
        tinhor = np.where(swhorconf, tcpa - dtinhor, 1e8)
        touthor = np.where(swhorconf, tcpa + dtinhor, -1e8)
        dalt = x[None, :, 2] - x[s:e, None, 2]
        dvs = v[None, :, 2] - v[s:e, None, 2]
        dvs = np.where(np.abs(dvs) < 1e-6, 1e-6, dvs)
        hpz = np.maximum(h[s:e, None], h[None, :])
        tcrosshi = (dalt + hpz) / -dvs
        tcrosslo = (dalt - hpz) / -dvs
        tinver = np.minimum(tcrosshi, tcrosslo)
        toutver = np.maximum(tcrosshi, tcrosslo)
        tinconf = np.maximum(tinver, tinhor)
        toutconf = np.minimum(toutver, touthor)
        sw = swhorconf & (tinconf <= toutconf) & (toutconf > 0.0) & (tinconf < T) & (cols > rows)
        ii, jj = np.nonzero(sw)
        out.append((ii + s, jj, tcpa[ii, jj], np.sqrt(dcpa2[ii, jj]), tinconf[ii, jj]))
    if not out:
        return _EMPTY
    return tuple(np.concatenate([o[k] for o in out]) for k in range(5))


@numba.njit(cache=True, nogil=True, inline="always")
def _pair(x, v, r, h, T, i, j, res):
    """BlueSky's state-based test of pair (i, j), same operations as the numpy baseline."""
    dx = x[j, 0] - x[i, 0]
    dy = x[j, 1] - x[i, 1]
    du = v[j, 0] - v[i, 0]
    dv = v[j, 1] - v[i, 1]
    dv2 = du * du + dv * dv
    if abs(dv2) < 1e-6:
        dv2 = 1e-6
    rpz = max(r[i], r[j])
    R2 = rpz * rpz
    # cheap exact-arithmetic pre-test (no sqrt, no division): the squared horizontal CPA
    # distance is (d2 dv2 - (r.v)^2) / dv2; the margin 1e-12 (d2 + R2) is far above the
    # rounding of the baseline's dcpa2 (~10 eps d2), so only pairs it rejects too are skipped
    d2 = dx * dx + dy * dy
    rv = du * dx + dv * dy
    if d2 * dv2 - rv * rv > dv2 * (R2 + 1e-12 * (d2 + R2)):
        return False
    dist = math.sqrt(dx * dx + dy * dy)
    vrel = math.sqrt(dv2)
    tcpa = -(du * dx + dv * dy) / dv2
    dcpa2 = abs(dist * dist - tcpa * tcpa * dv2)
    if not dcpa2 < R2:
        return False
    dtinhor = math.sqrt(max(0.0, R2 - dcpa2)) / vrel
    tinhor = tcpa - dtinhor
    touthor = tcpa + dtinhor
    dalt = x[j, 2] - x[i, 2]
    dvs = v[j, 2] - v[i, 2]
    if abs(dvs) < 1e-6:
        dvs = 1e-6
    hpz = max(h[i], h[j])
    tcrosshi = (dalt + hpz) / -dvs
    tcrosslo = (dalt - hpz) / -dvs
    tinconf = max(min(tcrosshi, tcrosslo), tinhor)
    toutconf = min(max(tcrosshi, tcrosslo), touthor)
    if tinconf <= toutconf and toutconf > 0.0 and tinconf < T:
        res[0] = tcpa
        res[1] = math.sqrt(dcpa2)
        res[2] = tinconf
        return True
    return False


@numba.njit(cache=True, nogil=True)
def _grid_pairs(x, v, r, h, T, oi, oj, ov):
    """Conflicting pairs into oi, oj, ov (t_cpa, d_cpa, t_in); returns their number (those
    beyond the outputs' capacity are counted, not written: call again with room)."""
    n = x.shape[0]
    # lookahead-swept horizontal boxes, widened so that any pair the state-based test can
    # report has overlapping boxes: conflict => horizontal distance < R + |dv| T at some
    # t in [0, T] (|dv| >= 1e-3 m/s after BlueSky's limiting), each box takes half + slack
    bx0, bx1, by0, by1 = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    ext = np.empty(n)
    scale = 0.0
    for i in range(n):
        scale = max(scale, abs(x[i, 0]), abs(x[i, 1]))
    slack = 0.5e-3 * T + 1e-9 * scale + 1e-6
    for i in range(n):
        e = r[i] + slack
        xa, xb = x[i, 0], x[i, 0] + v[i, 0] * T
        ya, yb = x[i, 1], x[i, 1] + v[i, 1] * T
        bx0[i] = min(xa, xb) - e
        bx1[i] = max(xa, xb) + e
        by0[i] = min(ya, yb) - e
        by1[i] = max(ya, yb) + e
        ext[i] = max(bx1[i] - bx0[i], by1[i] - by0[i])
    gx0, gx1, gy0, gy1 = bx0.min(), bx1.max(), by0.min(), by1.max()
    cell = max(np.median(ext), math.sqrt((gx1 - gx0) * (gy1 - gy0) / (4.0 * n)), 1e-3)
    nx = min(int((gx1 - gx0) / cell) + 1, 4096)
    ny = min(int((gy1 - gy0) / cell) + 1, 4096)
    cx = (gx1 - gx0) / nx * (1 + 1e-12) + 1e-12
    cy = (gy1 - gy0) / ny * (1 + 1e-12) + 1e-12
    c0x, c1x, c0y, c1y = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.int64)
    counts = np.zeros(nx * ny + 1, np.int64)
    for i in range(n):
        c0x[i] = min(int((bx0[i] - gx0) / cx), nx - 1)
        c1x[i] = min(int((bx1[i] - gx0) / cx), nx - 1)
        c0y[i] = min(int((by0[i] - gy0) / cy), ny - 1)
        c1y[i] = min(int((by1[i] - gy0) / cy), ny - 1)
        for a in range(c0y[i], c1y[i] + 1):
            for b in range(c0x[i], c1x[i] + 1):
                counts[a * nx + b + 1] += 1
    for k in range(nx * ny):
        counts[k + 1] += counts[k]
    fill = counts[:-1].copy()
    entries = np.empty(counts[-1], np.int64)
    for i in range(n):
        for a in range(c0y[i], c1y[i] + 1):
            for b in range(c0x[i], c1x[i] + 1):
                k = a * nx + b
                entries[fill[k]] = i
                fill[k] += 1
    # pairs visited through the grid; dense pictures (boxes over much of the area) are
    # cheaper with a sweep over the boxes sorted in x
    visits = 0.0
    for k in range(nx * ny):
        c = counts[k + 1] - counts[k]
        visits += 0.5 * c * (c - 1)
    dense = visits > 0.1 * n * (n - 1)
    res = np.empty(3)
    m = 0
    cap = oi.size
    if dense:
        # sweep and prune: boxes sorted by their x start, each paired with the following
        # boxes that start before it ends in x, then tested in y
        order = np.argsort(bx0)
        for p in range(n):
            i0 = order[p]
            xe = bx1[i0]
            for q in range(p + 1, n):
                j0 = order[q]
                if bx0[j0] > xe:
                    break
                if by0[i0] > by1[j0] or by0[j0] > by1[i0]:
                    continue
                i, j = min(i0, j0), max(i0, j0)
                if _pair(x, v, r, h, T, i, j, res):
                    if m < cap:
                        oi[m], oj[m] = i, j
                        ov[m, 0], ov[m, 1], ov[m, 2] = res[0], res[1], res[2]
                    m += 1
        return m
    for a in range(ny):
        for b in range(nx):
            k = a * nx + b
            for p in range(counts[k], counts[k + 1]):
                i0 = entries[p]
                for q in range(p + 1, counts[k + 1]):
                    j0 = entries[q]
                    # home cell of the pair: the lower-left corner of the boxes' intersection
                    if max(c0x[i0], c0x[j0]) != b or max(c0y[i0], c0y[j0]) != a:
                        continue
                    if bx0[i0] > bx1[j0] or bx0[j0] > bx1[i0] or by0[i0] > by1[j0] or by0[j0] > by1[i0]:
                        continue
                    i, j = min(i0, j0), max(i0, j0)
                    if _pair(x, v, r, h, T, i, j, res):
                        if m < cap:
                            oi[m], oj[m] = i, j
                            ov[m, 0], ov[m, 1], ov[m, 2] = res[0], res[1], res[2]
                        m += 1
    return m


def pairwise_conflicts(xyz_m, vel_mps, sep_m, lookahead_s: float, vsep_m=None):
    """State-based conflicts of N aircraft flying straight within ``lookahead_s`` [s]: the
    same test and result as :func:`pairwise_conflicts_numpy` (BlueSky's method), numba over
    the candidate pairs of a uniform grid of the lookahead-swept horizontal boxes (not N^2
    when traffic is sparse; a sweep over the boxes sorted in x when they cover much of the
    area).  Positions ``xyz_m`` (N, 3) [m], velocities ``vel_mps`` (N, 3)
    [m/s], ``sep_m``/``vsep_m`` [m] scalar or (N,).

    Returns ``(i, j, t_cpa_s, d_cpa_m, t_in_s)`` sorted by (i, j), i < j."""
    x, v, r, h, T = _picture(xyz_m, vel_mps, sep_m, lookahead_s, vsep_m)
    if x.shape[0] < 2:
        return _EMPTY
    cap = 4 * x.shape[0]
    while True:
        oi, oj, ov = np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty((cap, 3))
        m = _grid_pairs(x, v, r, h, T, oi, oj, ov)
        if m <= cap:
            break
        cap = m
    oi, oj, ov = oi[:m], oj[:m], ov[:m]
    order = np.lexsort((oj, oi))
    return oi[order], oj[order], ov[order, 0].copy(), ov[order, 1].copy(), ov[order, 2].copy()
