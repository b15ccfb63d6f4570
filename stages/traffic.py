"""Traffic occupancy: time-sliced reserved volumes around other drones (seed 000 eq. 1).

The mission time ``[t0, t0 + T_tot]`` is cut into ``N_o`` slices of ``dt = T_tot / N_o``
[s]; slice ``k`` covers ``[t_k, t_{k+1}]`` with ``t_k = t0 + k dt``.  Its occupancy map is the
union of the volumes reserved to the intruders: each intruder's path flown during
``[t_k - dt_c, t_{k+1} + dt_c]`` (time margin ``dt_c`` [s]) swept by a sphere of radius
``r_i + d_c`` (intruder radius + spatial margin ``d_c`` [m]).  An intruder only exists between
its first and last waypoint times; between waypoints it moves linearly in time.

Sparse storage: the swept volume of a linear piece is a *capsule* (segment + radius), so a
slice is a list of capsules, exactly.  A uniform 2-D bucket grid over (x, y) indexes the
capsules of every slice; queries are exact distance tests (numba):

* :meth:`TrafficOccupancy.occupied` -- point (x, y, z) at time t inside a capsule of the slice
  containing t (a time on a slice boundary belongs to the later slice; ``t0 + T_tot`` to the
  last one);
* :meth:`TrafficOccupancy.segment_conflicts` -- a segment flown linearly in time from
  (p0, t0) to (p1, t1) is split at slice boundaries and each piece tested (closest distance
  segment-segment) against the capsules of its slice (pieces are closed: a boundary instant is
  tested against both slices).

:meth:`TrafficOccupancy.to_dataset` stores the capsules as an xarray Dataset (dim
``capsule``) that caches in zarr; :meth:`TrafficOccupancy.from_dataset` rebuilds the index.

Polygon 4-D volumes (the operational intents of other operators, :class:`VolumePrisms`):
besides capsules an occupancy may hold convex prisms, each a convex polygon (x, y) [m], an
altitude band [m] in the surface datum and a time window [s] (closed: touching counts).  They
are not sliced: a segment flown linearly in time is clipped exactly against each prism's
half-spaces (Cyrus-Beck, with time as a fourth coordinate), so the test is exact for the
prisms as given.  :func:`volume_prisms` makes them from polygon volumes, grown by the
caller's own buffers (horizontal [m], vertical [m], time [s]) so that acceptance stays
conservative; a non-convex outline is replaced by its convex hull (it contains it).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numba
import numpy as np
import xarray as xr

from skyroute.stages.base import InputError
from skyroute.stages.grid import Grid

_MAX_BUCKETS = 2_000_000


@dataclass(frozen=True)
class Intruder:
    """Another drone: waypoint times ``times_s`` [s since mission start, strictly increasing],
    positions ``xyz_m`` (n, 3) [m, scenario CRS, altitude in the datum of the surface] and its
    radius ``radius_m`` [m]."""

    id: str
    times_s: np.ndarray
    xyz_m: np.ndarray
    radius_m: float = 0.0

    def __post_init__(self):
        t = np.asarray(self.times_s, dtype=float).reshape(-1)
        p = np.asarray(self.xyz_m, dtype=float)
        object.__setattr__(self, "times_s", t)
        object.__setattr__(self, "xyz_m", p)
        if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] != t.size or t.size == 0:
            raise InputError(f"intruder {self.id!r}: need n >= 1 waypoints with times (n,) and x, y, z (n, 3); "
                             f"got times {t.shape} and positions {p.shape}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
            raise InputError(f"intruder {self.id!r}: waypoint times/positions must be finite")
        bad = np.nonzero(np.diff(t) <= 0)[0]
        if bad.size:
            i = int(bad[0]) + 1
            raise InputError(f"intruder {self.id!r}: waypoint times must increase strictly, but waypoint {i} "
                             f"(t = {t[i]} s) is not after waypoint {i - 1} (t = {t[i - 1]} s)")
        if not (np.isfinite(self.radius_m) and self.radius_m >= 0):
            raise InputError(f"intruder {self.id!r}: radius {self.radius_m} m must be >= 0")


def intruders_from_records(records: Iterable[Mapping]) -> list[Intruder]:
    """Intruders from scenario records: ``{"id": ..., "radius_m": ..., "waypoints": [[t_s, x_m,
    y_m, z_m], ...]}`` (or keys ``times_s`` and ``xyz_m``)."""
    out = []
    for n, rec in enumerate(records):
        ident = str(rec.get("id", n))
        if "waypoints" in rec:
            w = np.asarray(rec["waypoints"], dtype=float)
            if w.ndim != 2 or w.shape[1] != 4:
                raise InputError(f"intruder {ident!r}: waypoints must be rows [t_s, x_m, y_m, z_m], got shape {w.shape}")
            t, p = w[:, 0], w[:, 1:]
        elif "times_s" in rec and "xyz_m" in rec:
            t, p = rec["times_s"], rec["xyz_m"]
        else:
            raise InputError(f"intruder {ident!r}: give 'waypoints' ([[t, x, y, z], ...]) or 'times_s' and 'xyz_m'")
        out.append(Intruder(ident, t, p, float(rec.get("radius_m", 0.0))))
    return out


def intruders_for(traffic_settings_intruders: Iterable[Mapping], surface: xr.Dataset) -> list[Intruder]:
    """Scenario intruder records (``id``, ``radius_m`` [m], ``waypoints`` rows ``t [s], x, y [m],
    altitude AGL [m]``) -> :class:`Intruder` objects in the datum of ``surface`` (the terrain [m]
    under each waypoint is added to its altitude)."""
    grid = Grid.from_dataarray(surface["terrain"])
    terrain = surface["terrain"].values
    recs = []
    for it in traffic_settings_intruders:
        wp = np.asarray(it["waypoints"], dtype=float)
        wp[:, 3] += terrain[grid.cell_of(wp[:, 1], wp[:, 2])]
        recs.append({"id": it["id"], "radius_m": it["radius_m"], "waypoints": wp.tolist()})
    return intruders_from_records(recs)


# ------------------------------------------------------------------ capsules
def _capsules_of(intr: Intruder, a: float, b: float):
    """Linear pieces of the intruder path during [a, b] (clipped to its life): (m, 6) endpoints."""
    t, p = intr.times_s, intr.xyz_m
    a, b = max(a, t[0]), min(b, t[-1])
    if a > b:
        return np.empty((0, 6))
    if t.size == 1:
        return np.concatenate([p[0], p[0]])[None, :]
    i0 = min(max(int(np.searchsorted(t, a, side="right")) - 1, 0), t.size - 2)
    i1 = min(int(np.searchsorted(t, b, side="left")), t.size - 1)
    segs = []
    for i in range(i0, max(i1, i0 + 1)):
        sa, sb = max(t[i], a), min(t[i + 1], b)
        if sa > sb:
            continue
        fa = (sa - t[i]) / (t[i + 1] - t[i])
        fb = (sb - t[i]) / (t[i + 1] - t[i])
        segs.append(np.concatenate([p[i] + fa * (p[i + 1] - p[i]), p[i] + fb * (p[i + 1] - p[i])]))
    return np.array(segs).reshape(-1, 6)


@numba.njit(cache=True)
def _bucket_box(bb, c, ox, oy, b, nbx, nby):
    """Bucket index range (bx0, by0, bx1, by1), clipped to the index, of capsule ``c``'s box."""
    bx0 = min(max(int(math.floor((bb[c, 0] - ox) / b)), 0), nbx - 1)
    by0 = min(max(int(math.floor((bb[c, 1] - oy) / b)), 0), nby - 1)
    bx1 = min(max(int(math.floor((bb[c, 2] - ox) / b)), 0), nbx - 1)
    by1 = min(max(int(math.floor((bb[c, 3] - oy) / b)), 0), nby - 1)
    return bx0, by0, bx1, by1


@numba.njit(cache=True)
def _count_buckets(bb, ox, oy, b, nbx, nby, sl, counts):
    """bb: (m, 4) xmin, ymin, xmax, ymax of each capsule; counts[key + 1] += 1 per bucket hit."""
    m = bb.shape[0]
    for c in range(m):
        bx0, by0, bx1, by1 = _bucket_box(bb, c, ox, oy, b, nbx, nby)
        for by in range(by0, by1 + 1):
            for bx in range(bx0, bx1 + 1):
                counts[(sl[c] * nby + by) * nbx + bx + 1] += 1


@numba.njit(cache=True)
def _fill_buckets(bb, ox, oy, b, nbx, nby, sl, start):
    m = bb.shape[0]
    fill = start.copy()
    entries = np.empty(start[-1], dtype=np.int64)
    for c in range(m):
        bx0, by0, bx1, by1 = _bucket_box(bb, c, ox, oy, b, nbx, nby)
        for by in range(by0, by1 + 1):
            for bx in range(bx0, bx1 + 1):
                key = (sl[c] * nby + by) * nbx + bx
                entries[fill[key]] = c
                fill[key] += 1
    return entries


# ------------------------------------------------------------------ numba geometry


@numba.njit(cache=True)
def _point_seg_d2(px, py, pz, ax, ay, az, bx, by, bz):
    dx, dy, dz = bx - ax, by - ay, bz - az
    L2 = dx * dx + dy * dy + dz * dz
    s = 0.0
    if L2 > 0.0:
        s = ((px - ax) * dx + (py - ay) * dy + (pz - az) * dz) / L2
        s = min(max(s, 0.0), 1.0)
    qx, qy, qz = ax + s * dx - px, ay + s * dy - py, az + s * dz - pz
    return qx * qx + qy * qy + qz * qz


@numba.njit(cache=True)
def _dot(ax, ay, az, bx, by, bz):
    return ax * bx + ay * by + az * bz


@numba.njit(cache=True, nogil=True)
def seg_seg_d2(p1x, p1y, p1z, q1x, q1y, q1z, p2x, p2y, p2z, q2x, q2y, q2z):
    """Squared closest distance [m^2] between segments p1-q1 and p2-q2 given by their
    coordinates (Ericson, Real-Time Collision Detection, 5.1.9): the one implementation
    (the traffic capsules and the tactical conflict checks call it)."""
    eps = 1e-12
    d1x, d1y, d1z = q1x - p1x, q1y - p1y, q1z - p1z
    d2x, d2y, d2z = q2x - p2x, q2y - p2y, q2z - p2z
    rx, ry, rz = p1x - p2x, p1y - p2y, p1z - p2z
    a = _dot(d1x, d1y, d1z, d1x, d1y, d1z)
    e = _dot(d2x, d2y, d2z, d2x, d2y, d2z)
    f = _dot(d2x, d2y, d2z, rx, ry, rz)
    if a <= eps and e <= eps:
        return _dot(rx, ry, rz, rx, ry, rz)
    if a <= eps:
        s = 0.0
        t = min(max(f / e, 0.0), 1.0)
    else:
        c = _dot(d1x, d1y, d1z, rx, ry, rz)
        if e <= eps:
            t = 0.0
            s = min(max(-c / a, 0.0), 1.0)
        else:
            b = _dot(d1x, d1y, d1z, d2x, d2y, d2z)
            den = a * e - b * b
            s = min(max((b * f - c * e) / den, 0.0), 1.0) if den > eps * a * e else 0.0
            t = (b * s + f) / e
            if t < 0.0:
                t = 0.0
                s = min(max(-c / a, 0.0), 1.0)
            elif t > 1.0:
                t = 1.0
                s = min(max((b - c) / a, 0.0), 1.0)
    wx = rx + d1x * s - d2x * t
    wy = ry + d1y * s - d2y * t
    wz = rz + d1z * s - d2z * t
    return wx * wx + wy * wy + wz * wz


@numba.njit(cache=True, nogil=True)
def _seg_seg_d2(p1, q1, p2, q2):
    """:func:`seg_seg_d2` of segments given as (3,) arrays."""
    return seg_seg_d2(p1[0], p1[1], p1[2], q1[0], q1[1], q1[2], p2[0], p2[1], p2[2], q2[0], q2[1], q2[2])


@numba.njit(cache=True)
def _points_kernel(x, y, z, k, cap, rad, start, entries, ox, oy, b, nbx, nby, out):
    for n in range(x.size):
        bx = int(math.floor((x[n] - ox) / b))
        by = int(math.floor((y[n] - oy) / b))
        hit = False
        if 0 <= bx < nbx and 0 <= by < nby:
            key = (k[n] * nby + by) * nbx + bx
            for e in range(start[key], start[key + 1]):
                c = entries[e]
                d2 = _point_seg_d2(x[n], y[n], z[n], cap[c, 0], cap[c, 1], cap[c, 2], cap[c, 3], cap[c, 4], cap[c, 5])
                if d2 <= rad[c] * rad[c]:
                    hit = True
                    break
        out[n] = hit


@numba.njit(cache=True)
def _piece_hits(pa, pb, k, cap, rad, slice_start, start, entries, ox, oy, b, nbx, nby):
    xmin, xmax = min(pa[0], pb[0]), max(pa[0], pb[0])
    ymin, ymax = min(pa[1], pb[1]), max(pa[1], pb[1])
    bx0 = int(math.floor((xmin - ox) / b))
    by0 = int(math.floor((ymin - oy) / b))
    bx1 = int(math.floor((xmax - ox) / b))
    by1 = int(math.floor((ymax - oy) / b))
    if bx1 < 0 or by1 < 0 or bx0 >= nbx or by0 >= nby:
        return False
    bx0, by0 = max(bx0, 0), max(by0, 0)
    bx1, by1 = min(bx1, nbx - 1), min(by1, nby - 1)
    nslice = slice_start[k + 1] - slice_start[k]
    if (bx1 - bx0 + 1) * (by1 - by0 + 1) > nslice:  # long piece: test every capsule of the slice
        for c in range(slice_start[k], slice_start[k + 1]):
            if _seg_seg_d2(pa, pb, cap[c, 0:3], cap[c, 3:6]) <= rad[c] * rad[c]:
                return True
        return False
    for by in range(by0, by1 + 1):
        for bx in range(bx0, bx1 + 1):
            key = (k * nby + by) * nbx + bx
            for e in range(start[key], start[key + 1]):
                c = entries[e]
                if _seg_seg_d2(pa, pb, cap[c, 0:3], cap[c, 3:6]) <= rad[c] * rad[c]:
                    return True
    return False


@numba.njit(cache=True)
def _segments_kernel(p0, t0, p1, t1, tm0, dt, nsl, cap, rad, slice_start, start, entries,
                     ox, oy, b, nbx, nby, out):
    for n in range(p0.shape[0]):
        if out[n]:
            continue
        ka = min(max(int(math.floor((t0[n] - tm0) / dt)), 0), nsl - 1)
        kb = min(max(int(math.floor((t1[n] - tm0) / dt)), 0), nsl - 1)
        dur = t1[n] - t0[n]
        hit = False
        for k in range(ka, kb + 1):
            if dur > 0.0:
                sa = max((tm0 + k * dt - t0[n]) / dur, 0.0)
                sb = min((tm0 + (k + 1) * dt - t0[n]) / dur, 1.0)
            else:
                sa, sb = 0.0, 1.0
            pa = p0[n] + sa * (p1[n] - p0[n])
            pb = p0[n] + sb * (p1[n] - p0[n])
            if _piece_hits(pa, pb, k, cap, rad, slice_start, start, entries, ox, oy, b, nbx, nby):
                hit = True
                break
        out[n] = hit


# ------------------------------------------------------------------ the occupancy maps


@dataclass
class TrafficOccupancy:
    """Time-sliced occupancy of the intruders as capsules (build with :func:`build_occupancy`).

    ``caps`` (m, 6) [m]: capsule axis endpoints (ax, ay, az, bx, by, bz), sorted by slice;
    ``radius_m`` (m,): capsule radius (intruder radius + d_c); ``slice_index`` (m,);
    ``intruder_index`` (m,) into ``intruder_ids``."""

    caps: np.ndarray
    radius_m: np.ndarray
    slice_index: np.ndarray
    intruder_index: np.ndarray
    intruder_ids: tuple[str, ...]
    t0_s: float
    t_total_s: float
    n_slices: int
    d_c_m: float
    dt_c_s: float
    bucket_m: float | None = None
    volumes: VolumePrisms | None = None
    _index: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        self._build_index()

    @property
    def empty(self) -> bool:
        """No capsule and no prism: nothing to conflict with."""
        return self.caps.shape[0] == 0 and (self.volumes is None or self.volumes.n == 0)

    @property
    def dt_s(self) -> float:
        """Slice duration dt = T_tot / N_o [s] (seed 000 eq. 1)."""
        return self.t_total_s / self.n_slices

    def slice_bounds(self, k: int) -> tuple[float, float]:
        """[t_k, t_{k+1}] [s] of slice k."""
        return self.t0_s + k * self.dt_s, self.t0_s + (k + 1) * self.dt_s

    def _build_index(self) -> None:
        m = self.caps.shape[0]
        sl = self.slice_index.astype(np.int64)
        self.slice_start = np.searchsorted(sl, np.arange(self.n_slices + 1)).astype(np.int64)
        if m:
            r = self.radius_m
            bb = np.stack([np.minimum(self.caps[:, 0], self.caps[:, 3]) - r,
                           np.minimum(self.caps[:, 1], self.caps[:, 4]) - r,
                           np.maximum(self.caps[:, 0], self.caps[:, 3]) + r,
                           np.maximum(self.caps[:, 1], self.caps[:, 4]) + r], axis=1)
            ox, oy = float(bb[:, 0].min()), float(bb[:, 1].min())
            ext = max(float(bb[:, 2].max()) - ox, float(bb[:, 3].max()) - oy, 1e-6)
            b = self.bucket_m or max(float(np.median(np.maximum(bb[:, 2] - bb[:, 0], bb[:, 3] - bb[:, 1]))),
                                     ext / 256.0)
            while self.n_slices * math.ceil((float(bb[:, 2].max()) - ox) / b + 1e-9) * \
                    math.ceil((float(bb[:, 3].max()) - oy) / b + 1e-9) > _MAX_BUCKETS:
                b *= 1.5
            nbx = max(int(math.ceil((float(bb[:, 2].max()) - ox) / b + 1e-9)), 1)
            nby = max(int(math.ceil((float(bb[:, 3].max()) - oy) / b + 1e-9)), 1)
        else:
            bb = np.zeros((0, 4))
            ox = oy = 0.0
            b, nbx, nby = 1.0, 1, 1
        counts = np.zeros(self.n_slices * nbx * nby + 1, dtype=np.int64)
        if m:
            _count_buckets(bb, ox, oy, b, nbx, nby, sl, counts)
        start = np.cumsum(counts)
        entries = _fill_buckets(bb, ox, oy, b, nbx, nby, sl, start) if m else np.zeros(0, np.int64)
        self._index = {"ox": ox, "oy": oy, "b": float(b), "nbx": nbx, "nby": nby, "start": start,
                       "entries": entries}

    def _slice_of(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        lo, hi = self.t0_s, self.t0_s + self.t_total_s
        bad = ~((t >= lo) & (t <= hi))
        if np.any(bad):
            v = float(t[bad].ravel()[0])
            raise InputError(f"time {v} s is outside the occupancy maps [{lo}, {hi}] s: rebuild them with a "
                             f"larger t_total_s or an earlier t0_s")
        return np.minimum(np.floor((t - lo) / self.dt_s).astype(np.int64), self.n_slices - 1)

    def occupied(self, x, y, z, t) -> np.ndarray:
        """Is the point (x, y, z) [m] at time t [s] inside a reserved volume of the slice that
        contains t?  Arrays broadcast together; returns a bool array of their shape."""
        x, y, z, t = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (x, y, z, t)))
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y)) and np.all(np.isfinite(z))):
            raise InputError("occupied(): x, y, z must be finite")
        k = self._slice_of(t).ravel()
        return self._occupied_k(x.ravel(), y.ravel(), z.ravel(), k).reshape(x.shape)

    def _occupied_k(self, x, y, z, k) -> np.ndarray:
        ix = self._index
        out = np.zeros(x.size, dtype=np.bool_)
        _points_kernel(np.ascontiguousarray(x), np.ascontiguousarray(y), np.ascontiguousarray(z),
                       np.ascontiguousarray(k, dtype=np.int64), self.caps, self.radius_m, ix["start"],
                       ix["entries"], ix["ox"], ix["oy"], ix["b"], ix["nbx"], ix["nby"], out)
        return out

    def segment_conflicts(self, p0, t0, p1, t1):
        """Does the segment flown linearly in time from ``p0`` (x, y, z) [m] at ``t0`` [s] to
        ``p1`` at ``t1`` [s] cross a reserved volume of any slice it passes through?  ``p0``,
        ``p1``: (3,) or (n, 3); ``t0``, ``t1``: scalars or (n,).  Returns bool or (n,) bools."""
        single = np.ndim(p0) == 1 and np.ndim(p1) == 1
        a = np.atleast_2d(np.asarray(p0, dtype=float))
        c = np.atleast_2d(np.asarray(p1, dtype=float))
        if a.shape[-1] != 3 or c.shape[-1] != 3:
            raise InputError("segment endpoints must be (x, y, z) [m]: shape (3,) or (n, 3)")
        a, c = np.broadcast_arrays(a, c)
        n = a.shape[0]
        ta = np.broadcast_to(np.asarray(t0, dtype=float), (n,))
        tb = np.broadcast_to(np.asarray(t1, dtype=float), (n,))
        if np.any(tb < ta):
            i = int(np.argmax(tb < ta))
            raise InputError(f"segment {i}: end time {tb[i]} s is before start time {ta[i]} s")
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(c))):
            raise InputError("segment endpoints must be finite")
        self._slice_of(ta)
        self._slice_of(tb)
        ix = self._index
        out = np.zeros(n, dtype=np.bool_)
        if self.volumes is not None and self.volumes.n:
            self.volumes.segment_hits(a, ta, c, tb, out)
        _segments_kernel(np.ascontiguousarray(a), np.ascontiguousarray(ta), np.ascontiguousarray(c),
                         np.ascontiguousarray(tb), self.t0_s, self.dt_s, self.n_slices, self.caps,
                         self.radius_m, self.slice_start, ix["start"], ix["entries"], ix["ox"], ix["oy"],
                         ix["b"], ix["nbx"], ix["nby"], out)
        return bool(out[0]) if single else out

    def with_volumes(self, volumes: VolumePrisms | None) -> TrafficOccupancy:
        """A copy of these maps that also holds the prisms ``volumes``."""
        return TrafficOccupancy(self.caps, self.radius_m, self.slice_index, self.intruder_index, self.intruder_ids,
                                self.t0_s, self.t_total_s, self.n_slices, self.d_c_m, self.dt_c_s, self.bucket_m,
                                volumes)

    def occupancy_slice(self, grid: Grid, k: int, z_m: float) -> xr.DataArray:
        """Dense view of slice ``k`` on ``grid`` at altitude ``z_m`` [m]: True where the cell
        centre is inside a reserved volume (for figures; planners use the exact queries)."""
        if not (0 <= int(k) < self.n_slices):
            raise InputError(f"slice {k} out of range 0..{self.n_slices - 1}")
        xx, yy = np.meshgrid(grid.x, grid.y)
        occ = self._occupied_k(xx.ravel(), yy.ravel(), np.full(xx.size, float(z_m)),
                               np.full(xx.size, int(k), dtype=np.int64)).reshape(grid.shape)
        t_a, t_b = self.slice_bounds(int(k))
        return grid.dataarray(occ, "occupancy", long_name=f"intruder reserved volume, slice {k} "
                              f"[{t_a}, {t_b}] s at z = {z_m} m", slice=int(k), z_m=float(z_m))

    def to_dataset(self) -> xr.Dataset:
        """The capsules as a Dataset (dim ``capsule``) that caches in zarr."""
        ds = xr.Dataset(
            {
                "slice": ("capsule", self.slice_index.astype(np.int64), {"units": "1", "long_name": "occupancy slice index"}),
                "intruder": ("capsule", self.intruder_index.astype(np.int64), {"units": "1", "long_name": "index into intruder_id"}),
                "start": (("capsule", "xyz"), self.caps[:, :3], {"units": "m", "long_name": "capsule axis start (x, y, z)"}),
                "end": (("capsule", "xyz"), self.caps[:, 3:], {"units": "m", "long_name": "capsule axis end (x, y, z)"}),
                "radius": ("capsule", self.radius_m, {"units": "m", "long_name": "intruder radius + d_c"}),
                "intruder_id": ("intruder_dim", np.array(self.intruder_ids, dtype=object)),
            },
        )
        ds.attrs = {"t0_s": self.t0_s, "t_total_s": self.t_total_s, "n_slices": self.n_slices,
                    "dt_s": self.dt_s, "d_c_m": self.d_c_m, "dt_c_s": self.dt_c_s,
                    "bucket_m": self.bucket_m if self.bucket_m is not None else -1.0}
        return ds

    @classmethod
    def from_dataset(cls, ds: xr.Dataset) -> TrafficOccupancy:
        a = ds.attrs
        caps = np.concatenate([np.asarray(ds["start"].values, float), np.asarray(ds["end"].values, float)],
                              axis=1).reshape(-1, 6)
        bm = float(a.get("bucket_m", -1.0))
        return cls(np.ascontiguousarray(caps), np.asarray(ds["radius"].values, float),
                   np.asarray(ds["slice"].values, np.int64), np.asarray(ds["intruder"].values, np.int64),
                   tuple(str(s) for s in ds["intruder_id"].values), float(a["t0_s"]), float(a["t_total_s"]),
                   int(a["n_slices"]), float(a["d_c_m"]), float(a["dt_c_s"]), bm if bm > 0 else None)


def build_occupancy(intruders: Iterable[Intruder | Mapping], t_total_s: float, n_slices: int,
                    d_c_m: float, dt_c_s: float, t0_s: float = 0.0,
                    bucket_m: float | None = None) -> TrafficOccupancy:
    """Seed 000 eq. 1: ``n_slices`` (N_o) occupancy maps of ``dt = t_total_s / n_slices`` [s]
    from ``t0_s`` [s]; spatial margin ``d_c_m`` [m], time margin ``dt_c_s`` [s].  ``intruders``:
    :class:`Intruder` objects or scenario records (:func:`intruders_from_records`).
    ``bucket_m``: spatial index cell [m] (default: the median capsule extent, at least
    1/256 of the traffic extent)."""
    if not (isinstance(n_slices, (int, np.integer)) and n_slices >= 1):
        raise InputError(f"number of occupancy maps N_o = {n_slices} must be an integer >= 1")
    if not (np.isfinite(t_total_s) and t_total_s > 0):
        raise InputError(f"T_tot = {t_total_s} s must be > 0 (vehicle endurance)")
    if not (np.isfinite(d_c_m) and d_c_m >= 0):
        raise InputError(f"spatial margin d_c = {d_c_m} m must be >= 0")
    if not (np.isfinite(dt_c_s) and dt_c_s >= 0):
        raise InputError(f"time margin dt_c = {dt_c_s} s must be >= 0")
    if not np.isfinite(t0_s):
        raise InputError(f"t0_s = {t0_s} must be finite")
    if bucket_m is not None and not (np.isfinite(bucket_m) and bucket_m > 0):
        raise InputError(f"bucket_m = {bucket_m} m must be > 0")
    items = list(intruders)
    recs = [i for i in items if not isinstance(i, Intruder)]
    intr = [i if isinstance(i, Intruder) else None for i in items]
    if recs:
        conv = iter(intruders_from_records(recs))
        intr = [i if i is not None else next(conv) for i in intr]
    dt = t_total_s / n_slices
    caps, rad, sl, ii = [], [], [], []
    for k in range(n_slices):
        a = t0_s + k * dt - dt_c_s
        b = t0_s + (k + 1) * dt + dt_c_s
        for n, it in enumerate(intr):
            c = _capsules_of(it, a, b)
            if c.shape[0]:
                caps.append(c)
                rad.append(np.full(c.shape[0], it.radius_m + d_c_m))
                sl.append(np.full(c.shape[0], k, dtype=np.int64))
                ii.append(np.full(c.shape[0], n, dtype=np.int64))

    def cat(xs, shape, dtype):
        return np.concatenate(xs) if xs else np.zeros(shape, dtype=dtype)

    return TrafficOccupancy(np.ascontiguousarray(cat(caps, (0, 6), float)), cat(rad, (0,), float),
                            cat(sl, (0,), np.int64), cat(ii, (0,), np.int64), tuple(i.id for i in intr),
                            float(t0_s), float(t_total_s), int(n_slices), float(d_c_m), float(dt_c_s),
                            None if bucket_m is None else float(bucket_m))


# ------------------------------------------------------------------ polygon 4-D volumes (prisms)


@numba.njit(cache=True)
def _prism_kernel(p0, t0, p1, t1, hp, hp_start, band, tlo_sorted, order, max_dur, bbox, out):
    """out[n] |= segment n (p0 at t0 -> p1 at t1, linear in time) meets a prism (closed)."""
    m = order.size
    for n in range(p0.shape[0]):
        if out[n]:
            continue
        ta, tb = t0[n], t1[n]
        # prisms with t_lo <= tb and t_hi >= ta: t_lo in [ta - max_dur, tb]
        lo = np.searchsorted(tlo_sorted, ta - max_dur, side="left")
        hi = np.searchsorted(tlo_sorted, tb, side="right")
        xmin, xmax = min(p0[n, 0], p1[n, 0]), max(p0[n, 0], p1[n, 0])
        ymin, ymax = min(p0[n, 1], p1[n, 1]), max(p0[n, 1], p1[n, 1])
        dx, dy, dz = p1[n, 0] - p0[n, 0], p1[n, 1] - p0[n, 1], p1[n, 2] - p0[n, 2]
        dt = tb - ta
        for q in range(lo, min(hi, m)):
            j = order[q]
            if band[j, 3] < ta or band[j, 2] > tb:
                continue
            if bbox[j, 0] > xmax or bbox[j, 2] < xmin or bbox[j, 1] > ymax or bbox[j, 3] < ymin:
                continue
            s0, s1 = 0.0, 1.0
            # each constraint: a + b s <= 0
            ok = True
            for k in range(4 + hp_start[j + 1] - hp_start[j]):
                if k == 0:
                    a, b = band[j, 0] - p0[n, 2], -dz          # z >= z_lo
                elif k == 1:
                    a, b = p0[n, 2] - band[j, 1], dz           # z <= z_hi
                elif k == 2:
                    a, b = band[j, 2] - ta, -dt                # t >= t_lo
                elif k == 3:
                    a, b = ta - band[j, 3], dt                 # t <= t_hi
                else:
                    h = hp_start[j] + k - 4                    # nx x + ny y <= d
                    a = hp[h, 0] * p0[n, 0] + hp[h, 1] * p0[n, 1] - hp[h, 2]
                    b = hp[h, 0] * dx + hp[h, 1] * dy
                if b == 0.0:
                    if a > 0.0:
                        ok = False
                        break
                elif b > 0.0:
                    s1 = min(s1, -a / b)
                else:
                    s0 = max(s0, -a / b)
                if s0 > s1:
                    ok = False
                    break
            if ok:
                out[n] = True
                break


@dataclass
class VolumePrisms:
    """Convex prisms (see the module docstring): ``halfplanes`` (H, 3) rows (nx, ny, d) of the
    constraints ``nx x + ny y <= d`` [m], those of prism i at ``hp_start[i]:hp_start[i+1]``;
    ``band`` (m, 4): z_lo, z_hi [m] (surface datum), t_lo, t_hi [s] (mission time);
    ``owner`` (m,): who reserved each prism (e.g. an intent id)."""

    halfplanes: np.ndarray
    hp_start: np.ndarray
    band: np.ndarray
    owner: tuple = ()
    _aux: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        self.halfplanes = np.ascontiguousarray(np.asarray(self.halfplanes, float).reshape(-1, 3))
        self.hp_start = np.ascontiguousarray(np.asarray(self.hp_start, np.int64))
        self.band = np.ascontiguousarray(np.asarray(self.band, float).reshape(-1, 4))
        m = self.band.shape[0]
        if self.hp_start.size != m + 1:
            raise InputError("VolumePrisms: hp_start must have one entry per prism plus one")
        order = np.argsort(self.band[:, 2], kind="stable")
        bbox = self._aux.get("bbox_in")     # vertex boxes (xmin, ymin, xmax, ymax) [m] from volume_prisms
        if bbox is None:
            bbox = np.tile([-np.inf, -np.inf, np.inf, np.inf], (m, 1))
        self._aux = {"order": order.astype(np.int64), "tlo": np.ascontiguousarray(self.band[order, 2]),
                     "max_dur": float(np.max(self.band[:, 3] - self.band[:, 2])) if m else 0.0,
                     "bbox": np.ascontiguousarray(np.asarray(bbox, float).reshape(m, 4))}

    @property
    def n(self) -> int:
        return int(self.band.shape[0])

    def shifted(self, dt_s: float) -> VolumePrisms:
        """The same prisms with their times shifted by ``dt_s`` [s] (another mission clock)."""
        band = self.band.copy()
        band[:, 2:] += dt_s
        out = VolumePrisms.__new__(VolumePrisms)
        out.halfplanes, out.hp_start, out.band, out.owner = self.halfplanes, self.hp_start, band, self.owner
        out._aux = {**self._aux, "tlo": self._aux["tlo"] + dt_s}
        return out

    def segment_hits(self, p0: np.ndarray, t0: np.ndarray, p1: np.ndarray, t1: np.ndarray, out: np.ndarray) -> None:
        """``out[n] |= `` segment n (``p0[n]`` at ``t0[n]`` -> ``p1[n]`` at ``t1[n]``) meets a prism."""
        if not self.n:
            return
        a = self._aux
        _prism_kernel(np.ascontiguousarray(p0, float), np.ascontiguousarray(t0, float),
                      np.ascontiguousarray(p1, float), np.ascontiguousarray(t1, float), self.halfplanes,
                      self.hp_start, self.band, a["tlo"], a["order"], a["max_dur"], a["bbox"], out)


def volume_prisms(volumes: Iterable, *, grow_m: float = 0.0, grow_z_m: float = 0.0, grow_t_s: float = 0.0,
                  z_offset_m: Iterable[tuple[float, float]] | None = None, owners: Iterable | None = None,
                  quad_segs: int = 4) -> VolumePrisms:
    """:class:`VolumePrisms` of polygon volumes (objects with ``polygon`` (shapely, map CRS [m]),
    ``alt_lower_m``, ``alt_upper_m``, ``t_start_s``, ``t_end_s``, e.g.
    :class:`~skyroute.stages.fleet.Volume4`).  The outline's convex hull is grown by ``grow_m``
    [m] (circumscribed: the polygon's vertices at ``grow_m / cos(pi / (4 quad_segs))``, so the
    Minkowski sum with the disk of radius ``grow_m`` is inside), the band by ``grow_z_m`` [m]
    and the window by ``grow_t_s`` [s] on both sides.  ``z_offset_m``: per volume (lo, hi)
    [m] subtracted from (alt_lower_m, alt_upper_m) to reach the surface datum (e.g. the
    largest and smallest geoid-to-ellipsoid offset under the outline, which keeps the band
    conservative)."""
    import shapely

    if not (grow_m >= 0 and grow_z_m >= 0 and grow_t_s >= 0):
        raise InputError("volume_prisms: grow_m, grow_z_m and grow_t_s must be >= 0")
    vols = list(volumes)
    offs = list(z_offset_m) if z_offset_m is not None else [(0.0, 0.0)] * len(vols)
    own = tuple(owners) if owners is not None else tuple(range(len(vols)))
    if len(offs) != len(vols) or len(own) != len(vols):
        raise InputError("volume_prisms: z_offset_m and owners need one entry per volume")
    hps, starts, band, boxes = [], [0], [], []
    r = grow_m / math.cos(math.pi / (4 * quad_segs)) if grow_m > 0 else 0.0
    for v, (olo, ohi) in zip(vols, offs, strict=True):
        hull = v.polygon.convex_hull
        if r > 0:
            hull = hull.buffer(r, quad_segs=quad_segs).convex_hull
        ring = np.asarray(shapely.get_coordinates(hull.exterior))[:-1]
        x, y = ring[:, 0], ring[:, 1]
        if float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) < 0:   # make it counter-clockwise
            ring = ring[::-1]
        e = np.roll(ring, -1, axis=0) - ring
        nrm = np.column_stack([e[:, 1], -e[:, 0]])             # outward normal of a ccw ring
        L = np.linalg.norm(nrm, axis=1)
        keep = L > 1e-12
        nrm = nrm[keep] / L[keep, None]
        d = np.einsum("ij,ij->i", nrm, ring[keep])
        hps.append(np.column_stack([nrm, d]))
        starts.append(starts[-1] + int(keep.sum()))
        band.append((v.alt_lower_m - olo - grow_z_m, v.alt_upper_m - ohi + grow_z_m,
                     v.t_start_s - grow_t_s, v.t_end_s + grow_t_s))
        boxes.append((*ring.min(axis=0), *ring.max(axis=0)))
    out = VolumePrisms.__new__(VolumePrisms)
    out.halfplanes = np.concatenate(hps) if hps else np.zeros((0, 3))
    out.hp_start, out.band, out.owner = np.asarray(starts, np.int64), np.asarray(band, float).reshape(-1, 4), own
    out._aux = {"bbox_in": np.asarray(boxes, float).reshape(-1, 4)}
    VolumePrisms.__post_init__(out)
    return out
