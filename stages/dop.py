"""Dilution of precision (DOP): the one home of skyroute's 4x4 DOP algebra (seed 003, eqs. 17-18).

Geometry
--------
One row ``g = [e_east, e_north, e_up, 1]`` per satellite (unit line of sight in the local
east/north/up frame, receiver clock column last: :func:`los_rows`), the normal matrix
``N = G^T G = sum g g^T`` and ``Q = N^-1``:

* GDOP = sqrt(tr Q), PDOP = sqrt(Qee + Qnn + Quu), HDOP = sqrt(Qee + Qnn),
  VDOP = sqrt(Quu), TDOP = sqrt(Qtt)  (DOPs are dimensionless; TDOP in units of c*dt).

Seed 003 writes the rows ``[-e, -n, -u, 1]`` (:func:`geometry_matrix`); the sign of the first
three columns does not change any DOP (``Q -> D Q D`` with ``D = diag(-1, -1, -1, 1)``).

Conventions (every module of skyroute follows them)
---------------------------------------------------
* **+inf = no fix**: with fewer than 4 usable satellites or a singular geometry (a Cholesky
  pivot of ``N`` below ``1e-10`` times its diagonal, e.g. 4 satellites at one elevation, where
  height and clock cannot be separated) the DOP is unbounded and every kind is ``+inf``.
  DOP thresholds then compare naturally (``inf < D`` is False).
* **NaN = missing data**, never "no fix": a satellite with a NaN azimuth or elevation is absent
  (use NaN for "below the mask"); :mod:`skyroute.stages.coverage` gives NaN below the surface,
  where no receiver can be.

Consumers: :func:`skyroute.stages.almanac.sky_geometry` (the ``satellites`` stage, open-sky DOP
per epoch), :mod:`skyroute.stages.coverage` (coverage floors, sections, volumes, column
profiles: its numba kernels call the compiled building blocks below) and ``skyroute sky``
(prints "no fix", JSON ``null``).

Lower bound of DOP (why thresholds must exceed ``c / sqrt(n)``)
----------------------------------------------------------------
With ``n`` unit line-of-sight vectors ``e_i``, ``A = sum e e^T`` (trace n), ``b = sum e``, the
position block of ``Q`` is ``S^-1`` with the Schur complement ``S = A - b b^T / n <= A``.  Hence
``PDOP^2 = tr(S^-1) >= tr(A^-1) >= 9 / tr(A) = 9 / n`` (AM-HM on eigenvalues),
``HDOP^2 >= 4 / n``, ``VDOP^2 >= 1 / n``, ``TDOP^2 = Q_tt >= 1 / N_tt = 1 / n`` and
``GDOP^2 >= 10 / n`` (:data:`DOP_BOUND_COEF`, :func:`dop_lower_bound`).  So PDOP < 1 *is*
possible with 10 or more satellites; the "PDOP >= 1" folklore is not a bound.

Layers: compiled building blocks for other numba kernels (:func:`inv_diag4`, :func:`inv4`,
:func:`add_rank_one`, :func:`dop_of_kind`; inlined, never called from Python), private
kernels, and the numpy/xarray functions :func:`dop`, :func:`dop_table`, :func:`dop_profile`.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import xarray as xr

from skyroute.stages.base import InputError, UnknownNameError

DOP_KINDS: tuple[str, ...] = ("GDOP", "PDOP", "HDOP", "VDOP", "TDOP")
"""DOP kinds, in the order of the ``kind`` index used by the kernels (last axis of
:func:`dop_table`)."""

DOP_NAMES: tuple[str, ...] = tuple(k.lower() for k in DOP_KINDS)
"""Variable names of the DOP kinds (``gdop`` ... ``tdop``)."""

DOP_BOUND_COEF: dict[str, float] = {
    "GDOP": math.sqrt(10.0), "PDOP": 3.0, "HDOP": 2.0, "VDOP": 1.0, "TDOP": 1.0,
}
"""``c`` of the universal lower bound ``DOP >= c / sqrt(n)`` for ``n`` satellites (see module doc)."""


# --------------------------------------------------------------------------------------------
# compiled building blocks (numba, inlined into the kernels that call them)
# --------------------------------------------------------------------------------------------

@numba.njit(cache=True, nogil=True, inline="always")
def inv_diag4(nm: np.ndarray, lo: np.ndarray, mi: np.ndarray, q: np.ndarray) -> bool:
    """Diagonal of ``inv(nm)`` for a symmetric 4x4 ``nm`` into ``q`` (Cholesky; reads the
    lower triangle only).  False when ``nm`` is (numerically) singular: no fix.  ``lo``,
    ``mi``: 4x4 scratch."""
    for j in range(4):
        s = nm[j, j]
        for k in range(j):
            s -= lo[j, k] * lo[j, k]
        if s <= 1e-10 * nm[j, j] or s <= 0.0:
            return False
        d = math.sqrt(s)
        lo[j, j] = d
        for i in range(j + 1, 4):
            t = nm[i, j]
            for k in range(j):
                t -= lo[i, k] * lo[j, k]
            lo[i, j] = t / d
    # mi = inv(lo), lower triangular
    for i in range(4):
        mi[i, i] = 1.0 / lo[i, i]
        for j in range(i):
            t = 0.0
            for k in range(j, i):
                t -= lo[i, k] * mi[k, j]
            mi[i, j] = t / lo[i, i]
        for j in range(i + 1, 4):
            mi[i, j] = 0.0
    # inv(nm) = mi^T mi  ->  diag_j = sum_i mi[i, j]^2
    for j in range(4):
        t = 0.0
        for i in range(j, 4):
            t += mi[i, j] * mi[i, j]
        q[j] = t
    return True


@numba.njit(cache=True, nogil=True, inline="always")
def inv4(nm: np.ndarray, lo: np.ndarray, mi: np.ndarray, qm: np.ndarray) -> bool:
    """Full ``inv(nm)`` of a symmetric 4x4 ``nm`` into ``qm`` (Cholesky, same singularity
    test as :func:`inv_diag4`).  False when ``nm`` is (numerically) singular."""
    if not inv_diag4(nm, lo, mi, qm[0]):
        return False
    # inv(nm) = mi^T mi with mi = inv(cholesky factor), lower triangular
    for a in range(4):
        for b in range(a, 4):
            t = 0.0
            for i in range(b, 4):
                t += mi[i, a] * mi[i, b]
            qm[a, b] = t
            qm[b, a] = t
    return True


@numba.njit(cache=True, nogil=True, inline="always")
def add_rank_one(qm: np.ndarray, gs: np.ndarray, u: np.ndarray) -> None:
    """``qm <- inv(inv(qm) + gs gs^T)``: one more satellite (Sherman-Morrison; ``1 + g^T Q g
    >= 1`` for a positive definite ``qm``, so no cancellation in the denominator).  ``u``:
    scratch (4,)."""
    for a in range(4):
        u[a] = qm[a, 0] * gs[0] + qm[a, 1] * gs[1] + qm[a, 2] * gs[2] + qm[a, 3] * gs[3]
    s = 1.0 / (1.0 + gs[0] * u[0] + gs[1] * u[1] + gs[2] * u[2] + gs[3] * u[3])
    for a in range(4):
        ua = u[a] * s
        for b in range(4):
            qm[a, b] -= ua * u[b]


@numba.njit(cache=True, nogil=True, inline="always")
def dop_of_kind(q: np.ndarray, kind: int) -> float:
    """DOP of kind ``kind`` (index into :data:`DOP_KINDS`) from the diagonal ``q`` of ``Q``."""
    if kind == 0:
        return math.sqrt(q[0] + q[1] + q[2] + q[3])
    if kind == 1:
        return math.sqrt(q[0] + q[1] + q[2])
    if kind == 2:
        return math.sqrt(q[0] + q[1])
    if kind == 3:
        return math.sqrt(q[2])
    return math.sqrt(q[3])


# --------------------------------------------------------------------------------------------
# kernels
# --------------------------------------------------------------------------------------------

@numba.njit(cache=True, nogil=True)
def _table_kernel(g, ok, out):
    """DOPs of sets of satellites: g (E, S, 4) rows, ok (E, S) bool (satellite used);
    out (E, 5) GDOP..TDOP, +inf with fewer than 4 satellites or a singular geometry."""
    ne, ns = ok.shape
    nm = np.zeros((4, 4))
    lo = np.zeros((4, 4))
    mi = np.zeros((4, 4))
    q = np.zeros(4)
    for e in range(ne):
        nm[:, :] = 0.0
        n = 0
        for s in range(ns):
            if ok[e, s]:
                n += 1
                for a in range(4):
                    for b in range(4):
                        nm[a, b] += g[e, s, a] * g[e, s, b]
        if n >= 4 and inv_diag4(nm, lo, mi, q):
            for c in range(5):
                out[e, c] = dop_of_kind(q, c)
        else:
            for c in range(5):
                out[e, c] = np.inf


@numba.njit(cache=True, nogil=True)
def _profile_kernel(gs):
    """(n, 5) DOPs after adding the satellites of rows ``gs`` (n, 4) one by one, in order
    (+inf with fewer than 4 or a singular geometry)."""
    n = gs.shape[0]
    prof = np.full((n, 5), np.inf)
    nm = np.zeros((4, 4))
    lo = np.zeros((4, 4))
    mi = np.zeros((4, 4))
    q = np.zeros(4)
    for k in range(n):
        for a in range(4):
            for b in range(4):
                nm[a, b] += gs[k, a] * gs[k, b]
        if k + 1 >= 4 and inv_diag4(nm, lo, mi, q):
            for c in range(5):
                prof[k, c] = dop_of_kind(q, c)
    return prof


# --------------------------------------------------------------------------------------------
# numpy / xarray
# --------------------------------------------------------------------------------------------

def los_rows(az_deg, el_deg) -> np.ndarray:
    """Rows ``[cos(el) sin(az), cos(el) cos(az), sin(el), 1]`` (ENU unit vector and clock) of
    the geometry matrix for azimuths/elevations [deg]; shape ``az.shape + (4,)``."""
    az = np.deg2rad(np.asarray(az_deg, dtype=np.float64))
    el = np.deg2rad(np.asarray(el_deg, dtype=np.float64))
    ce = np.cos(el)
    return np.stack([ce * np.sin(az), ce * np.cos(az), np.sin(el), np.ones_like(az)], axis=-1)


def geometry_matrix(az_deg, el_deg) -> np.ndarray:
    """Seed 003's rows ``[-e, -n, -u, 1]`` [..., sat, 4] from azimuth/elevation [deg]
    (:func:`los_rows` with the other sign); rows of absent (NaN) satellites are 0."""
    az = np.asarray(az_deg, dtype=np.float64)
    el = np.asarray(el_deg, dtype=np.float64)
    ok = np.isfinite(az) & np.isfinite(el)
    g = los_rows(az, el) * np.array([-1.0, -1.0, -1.0, 1.0])
    return np.where(ok[..., None], g, 0.0)


def dop_kind_index(dop: str) -> int:
    """Index of a DOP kind name (case-insensitive) in :data:`DOP_KINDS`."""
    name = str(dop).upper()
    if name not in DOP_KINDS:
        raise UnknownNameError("DOP kind", str(dop), DOP_KINDS)
    return DOP_KINDS.index(name)


def dop_lower_bound(dop: str, n_sat: int) -> float:
    """Universal lower bound ``c / sqrt(n)`` of a DOP kind with ``n_sat`` satellites (any
    geometry; see the module docstring for the derivation)."""
    return DOP_BOUND_COEF[DOP_KINDS[dop_kind_index(dop)]] / math.sqrt(max(int(n_sat), 1))


def dop_table(az_deg, el_deg) -> np.ndarray:
    """``(..., 5)`` GDOP, PDOP, HDOP, VDOP, TDOP of the satellites along the last axis of
    azimuth/elevation [deg] (same shape; NaN = absent satellite).  +inf = no fix (fewer than 4
    satellites or a singular geometry)."""
    az = np.asarray(az_deg, dtype=np.float64)
    el = np.asarray(el_deg, dtype=np.float64)
    if az.shape != el.shape:
        raise InputError(f"az_deg shape {az.shape} differs from el_deg shape {el.shape}")
    if az.ndim == 0:
        raise InputError("az_deg/el_deg need at least one dim (the satellites)")
    ok = np.isfinite(az) & np.isfinite(el)
    g = los_rows(np.where(ok, az, 0.0), np.where(ok, el, 0.0))
    lead = az.shape[:-1]
    n = az.shape[-1]
    out = np.empty((int(np.prod(lead, dtype=np.int64)), 5))
    _table_kernel(np.ascontiguousarray(g.reshape(-1, n, 4)),
                  np.ascontiguousarray(ok.reshape(-1, n)), out)
    return out.reshape(lead + (5,))


def dop_profile(rows: np.ndarray) -> np.ndarray:
    """``(n, 5)`` DOPs (GDOP..TDOP) after adding the satellites of the geometry rows ``rows``
    (n, 4) one by one, in order (row k: the first k + 1 satellites; +inf = no fix)."""
    g = np.ascontiguousarray(rows, dtype=np.float64)
    if g.ndim != 2 or g.shape[1] != 4:
        raise InputError(f"rows must be (n, 4) geometry rows (see los_rows), got shape {g.shape}")
    return _profile_kernel(g)


def dop(az_deg, el_deg, axis: int | str = -1) -> dict[str, np.ndarray] | xr.Dataset:
    """GDOP, PDOP, HDOP, VDOP, TDOP of the satellites along ``axis``.

    ``az_deg``, ``el_deg``: azimuth/elevation [deg], same shape; NaN marks a satellite that is
    not used (e.g. below the elevation mask).  +inf where there is no fix (fewer than 4 used
    satellites or a singular geometry; see the module docstring).  With numpy input ``axis``
    is an int and a dict of arrays is returned; with ``xarray.DataArray`` input ``axis`` may be
    a dim name (default: the last dim) and an ``xarray.Dataset`` (variables ``gdop`` ...
    ``tdop``) is returned.
    """
    if isinstance(az_deg, xr.DataArray) or isinstance(el_deg, xr.DataArray):
        if not (isinstance(az_deg, xr.DataArray) and isinstance(el_deg, xr.DataArray)):
            raise InputError("give az_deg and el_deg both as DataArrays or both as arrays")
        az_deg, el_deg = xr.broadcast(az_deg, el_deg)
        dim = az_deg.dims[axis] if isinstance(axis, int) else axis
        if dim not in az_deg.dims:
            raise InputError(f"dim {dim!r} not in {az_deg.dims}")
        el_deg = el_deg.transpose(*az_deg.dims)
        tab = dop_table(np.moveaxis(az_deg.values, az_deg.get_axis_num(dim), -1),
                        np.moveaxis(el_deg.values, az_deg.get_axis_num(dim), -1))
        dims = [d for d in az_deg.dims if d != dim]
        coords = {k: v for k, v in az_deg.coords.items() if dim not in v.dims}
        return xr.Dataset({k: (dims, tab[..., c], {
            "units": "1", "long_name": k.upper(),
            "comment": "+inf: no fix (fewer than 4 satellites or singular geometry)"})
            for c, k in enumerate(DOP_NAMES)}, coords=coords)
    az = np.asarray(az_deg, dtype=float)
    el = np.asarray(el_deg, dtype=float)
    if az.shape != el.shape:
        raise InputError(f"az_deg shape {az.shape} differs from el_deg shape {el.shape}")
    if az.ndim == 0:
        raise InputError("az_deg/el_deg need at least one dim (the satellites)")
    if not isinstance(axis, int | np.integer):
        raise InputError("axis must be an int for numpy input")
    tab = dop_table(np.moveaxis(az, axis, -1), np.moveaxis(el, axis, -1))
    return {k: tab[..., c] for c, k in enumerate(DOP_NAMES)}


__all__ = ["DOP_BOUND_COEF", "DOP_KINDS", "DOP_NAMES", "dop", "dop_kind_index", "dop_lower_bound",
           "dop_profile", "dop_table", "geometry_matrix", "los_rows"]
