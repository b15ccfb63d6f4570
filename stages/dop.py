"""Dilution of precision from satellite directions (seed 003, eqs. 17-18).

The geometry matrix has one row ``[-e, -n, -u, 1]`` per satellite (unit line of sight in the
local east/north/up frame, receiver clock column last); ``Q = (G^T G)^-1`` and

* GDOP = sqrt(tr Q), PDOP = sqrt(Qee + Qnn + Quu), HDOP = sqrt(Qee + Qnn),
  VDOP = sqrt(Quu), TDOP = sqrt(Qtt)  (DOPs are dimensionless; TDOP in units of c*dt).

Satellites with a NaN azimuth or elevation are absent (use NaN for "below the mask"); epochs
with fewer than 4 usable satellites or a degenerate geometry give NaN.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from skyroute.stages.base import InputError

DOP_NAMES = ("gdop", "pdop", "hdop", "vdop", "tdop")


def geometry_matrix(az_deg, el_deg) -> np.ndarray:
    """Rows ``[-e, -n, -u, 1]`` [...,sat,4] from azimuth/elevation [deg]; NaN rows -> 0."""
    az, el = np.radians(az_deg), np.radians(el_deg)
    ok = np.isfinite(az) & np.isfinite(el)
    g = np.stack([-np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), -np.sin(el),
                  np.ones_like(az)], axis=-1)
    return np.where(ok[..., None], g, 0.0)


def _dop_numpy(az: np.ndarray, el: np.ndarray) -> dict[str, np.ndarray]:
    g = geometry_matrix(az, el)                           # (..., S, 4)
    n_ok = (np.isfinite(az) & np.isfinite(el)).sum(axis=-1)
    h = np.einsum("...si,...sj->...ij", g, g)             # (..., 4, 4)
    with np.errstate(all="ignore"):
        det = np.linalg.det(h)                            # G^T G of unit rows: O(1)..O(n^4)
    bad = (n_ok < 4) | ~(np.abs(det) > 1e-10)
    h = np.where(bad[..., None, None], np.eye(4), h)
    q = np.linalg.inv(h)
    d = np.diagonal(q, axis1=-2, axis2=-1)
    out = {"gdop": np.sqrt(d.sum(-1)), "pdop": np.sqrt(d[..., :3].sum(-1)),
           "hdop": np.sqrt(d[..., :2].sum(-1)), "vdop": np.sqrt(d[..., 2]),
           "tdop": np.sqrt(d[..., 3])}
    return {k: np.where(bad, np.nan, v) for k, v in out.items()}


def dop(az_deg, el_deg, axis: int | str = -1) -> dict[str, np.ndarray] | xr.Dataset:
    """GDOP, PDOP, HDOP, VDOP, TDOP of the satellites along ``axis``.

    ``az_deg``, ``el_deg``: azimuth/elevation [deg], same shape; NaN marks a satellite that is
    not used (e.g. below the elevation mask).  With numpy input ``axis`` is an int and a dict of
    arrays is returned; with ``xarray.DataArray`` input ``axis`` may be a dim name (default: the
    last dim) and an ``xarray.Dataset`` (variables ``gdop`` ... ``tdop``) is returned.
    """
    if isinstance(az_deg, xr.DataArray) or isinstance(el_deg, xr.DataArray):
        if not (isinstance(az_deg, xr.DataArray) and isinstance(el_deg, xr.DataArray)):
            raise InputError("give az_deg and el_deg both as DataArrays or both as arrays")
        az_deg, el_deg = xr.broadcast(az_deg, el_deg)
        dim = az_deg.dims[axis] if isinstance(axis, int) else axis
        if dim not in az_deg.dims:
            raise InputError(f"dim {dim!r} not in {az_deg.dims}")
        el_deg = el_deg.transpose(*az_deg.dims)
        res = _dop_numpy(np.moveaxis(az_deg.values, az_deg.get_axis_num(dim), -1),
                         np.moveaxis(el_deg.values, az_deg.get_axis_num(dim), -1))
        dims = [d for d in az_deg.dims if d != dim]
        coords = {k: v for k, v in az_deg.coords.items() if dim not in v.dims}
        return xr.Dataset({k: (dims, v, {"units": "1", "long_name": k.upper()})
                           for k, v in res.items()}, coords=coords)
    az = np.asarray(az_deg, dtype=float)
    el = np.asarray(el_deg, dtype=float)
    if az.shape != el.shape:
        raise InputError(f"az_deg shape {az.shape} differs from el_deg shape {el.shape}")
    if az.ndim == 0:
        raise InputError("az_deg/el_deg need at least one dim (the satellites)")
    if not isinstance(axis, int | np.integer):
        raise InputError("axis must be an int for numpy input")
    return _dop_numpy(np.moveaxis(az, axis, -1), np.moveaxis(el, axis, -1))
