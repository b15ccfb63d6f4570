"""GNSS line of sight along a trajectory and the navigation error it gives (seed 000 STEP III,
seed 003): which satellites a point of a flight sees through the surface model's occlusions
(:func:`line_of_sight`, on the occlusion stage's visibility heights), and the GNSS/INS filter's
sigma_p along the samples (:func:`navigation_along`).  One home, below the planners, the
navigation Monte Carlo and the tactical replay (all of them call it)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import xarray as xr

from skyroute.stages.base import InputError
from skyroute.stages.navigation import DEFAULT_UERE_M, FilterState, FilterTrack, navigation_error
from skyroute.stages.occlusion import grid_azimuth_deg, occluder_window, visibility_heights_numpy

__all__ = ["LOS_CACHE_MAX_BYTES", "cells_of", "line_of_sight", "navigation_along", "sky_times_s"]

#: whole-grid visibility heights a ``line_of_sight`` cache keeps (float32, one (nsat, ny, nx) array
#: per sky epoch: 0.8 GB per epoch on the 6 km Helsinki AOI, whose 21 epochs took 17.8 GB in a
#: tactical replay); samples of further epochs are answered on their window, with the same answers
LOS_CACHE_MAX_BYTES = 1 << 30


def cells_of(grid, pts):
    """``(rows, cols, inside)`` of the cells holding the points ``pts`` (m, >= 2) [m] (clipped
    rows / cols; ``inside``: within the grid)."""
    r, c = grid.index_of(pts[:, 0], pts[:, 1])
    inside = (r >= 0) & (r < grid.ny) & (c >= 0) & (c < grid.nx)
    return *grid.cell_of(pts[:, 0], pts[:, 1]), inside


def sky_times_s(sky: xr.Dataset, start_time_utc) -> np.ndarray:
    t = pd.DatetimeIndex(pd.to_datetime(sky["time"].values))
    if t.tz is not None:
        t = t.tz_convert("UTC").tz_localize(None)
    s = pd.Timestamp(start_time_utc)
    if s.tzinfo is not None:
        s = s.tz_convert("UTC").tz_localize(None)
    return (t - s).total_seconds().to_numpy()


def line_of_sight(problem, sky: xr.Dataset, surface_2d, t_s, xyz, start_time_utc,
                  min_el_deg: float | None = None, cache: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """LOS unit vectors (m, nsat, 3) (ENU) and visibility (m, nsat) bool of the sky's satellites
    at samples ``xyz`` (m, 3) at mission times ``t_s`` [s]: nearest epoch of ``sky``; a satellite
    is visible iff it is above the mask (``above_mask``, else el > ``min_el_deg`` or 0) and the
    sample altitude is >= its visibility height in the sample's cell (outside the map: no
    obstacle).  ``cache``: a dict kept by the caller for one (sky, surface) pair: the
    visibility heights of each epoch are then computed once over the whole grid and reused
    (the tactical replans call this many times on the same maps), up to
    :data:`LOS_CACHE_MAX_BYTES`; the samples of epochs beyond it are answered as without a cache."""
    for v in ("az_deg", "el_deg", "los_enu"):
        if v not in sky:
            raise InputError(f"sky dataset lacks {v!r}: build it with skyroute.stages.almanac.sky_geometry")
    g = problem.grid
    h = np.asarray(getattr(surface_2d, "values", surface_2d), dtype=np.float64)
    if h.shape != g.shape:
        raise InputError(f"surface_2d has shape {h.shape}; the problem grid is {g.shape}")
    if not np.isfinite(h).all():
        raise InputError("surface_2d has NaN/inf cells: fill them first")
    ts = sky_times_s(sky, start_time_utc)
    az = np.asarray(sky["az_deg"].transpose("time", "sat").values, float)
    el = np.asarray(sky["el_deg"].transpose("time", "sat").values, float)
    los_all = np.asarray(sky["los_enu"].transpose("time", "sat", ...).values, float)
    if "above_mask" in sky:
        up = np.asarray(sky["above_mask"].transpose("time", "sat").values, bool)
    else:
        up = el > (0.0 if min_el_deg is None else float(min_el_deg))
    up &= np.isfinite(el) & (el > 0) & np.isfinite(az)
    t = np.asarray(t_s, float)
    p = np.asarray(xyz, float)
    ep = np.clip(np.searchsorted(ts, t), 1, max(ts.size - 1, 1)) if ts.size > 1 else np.zeros(t.size, int)
    if ts.size > 1:
        ep = np.where(np.abs(ts[ep - 1] - t) <= np.abs(ts[ep] - t), ep - 1, ep)
    r, c, inside = cells_of(g, p)
    m, nsat = t.size, az.shape[1]
    vis = np.zeros((m, nsat), bool)
    los = np.zeros((m, nsat, 3))
    if cache is None:   # the bounding box of the path + the longest shadow onto it
        _windowed_rows(vis, los, los_all, h, g, p, r, c, inside, ep, up, az, el, np.arange(m))
    else:               # whole-grid visibility heights per epoch, kept in ``cache`` within its budget
        used = sum(v.nbytes for v in cache.values())
        beyond = []     # samples of epochs whose whole-grid heights would pass LOS_CACHE_MAX_BYTES
        for e in np.unique(ep):
            rows = np.nonzero(ep == e)[0]
            sats = np.nonzero(up[e])[0]
            los[rows] = los_all[e][None, :, :]
            if sats.size == 0:
                continue
            vh = cache.get(int(e))
            if vh is None:
                if used + sats.size * h.size * 4 > LOS_CACHE_MAX_BYTES:      # float32 heights
                    beyond.append(rows)
                    continue
                az_g = np.atleast_1d(grid_azimuth_deg(az[e, sats], g))
                vh = cache[int(e)] = visibility_heights_numpy(h, az_g, el[e, sats], g.resolution_m, origin=(0, 0))
                used += vh.nbytes
            rr, cc, ii = r[rows], c[rows], inside[rows]
            for j, s in enumerate(sats):
                hv = np.where(ii, vh[j][np.clip(rr, 0, g.ny - 1), np.clip(cc, 0, g.nx - 1)], -np.inf)
                vis[rows, s] = p[rows, 2] >= hv
        if beyond:
            _windowed_rows(vis, los, los_all, h, g, p, r, c, inside, ep, up, az, el, np.concatenate(beyond))
    # LOS rows of invisible satellites are irrelevant; keep them unit-length where finite
    return np.where(np.isfinite(los), los, 0.0), vis


def _windowed_rows(vis, los, los_all, h, g, p, r, c, inside, ep, up, az, el, idx) -> None:
    """:func:`line_of_sight` without a cache for the samples ``idx``: on the bounding box of
    those samples plus the longest shadow onto them (:func:`_visibility_windowed`)."""
    if idx.size == 0:
        return
    rs, cs, ins, es = r[idx], c[idx], inside[idx], ep[idx]
    eps = np.unique(es)
    el_min = float(np.min(el[eps][up[eps]])) if up[eps].any() else 90.0
    relief = max(float(h.max()) - float(p[idx, 2].min()), 0.0)
    halo = int(math.ceil(relief / math.tan(math.radians(max(el_min, 0.1))) / g.resolution_m)) + 2
    r0, r1 = max(int(rs[ins].min()) - halo, 0) if ins.any() else 0, min(int(rs.max()) + halo + 1, g.ny)
    c0, c1 = max(int(cs[ins].min()) - halo, 0) if ins.any() else 0, min(int(cs.max()) + halo + 1, g.nx)
    v = np.zeros((idx.size, vis.shape[1]), bool)
    lo = np.zeros((idx.size, *los.shape[1:]))
    _visibility_windowed(v, lo, los_all, h[r0:r1, c0:c1], (r0, c0), g, p[idx, 2], rs, cs, ins, es, up, az, el)
    vis[idx] = v
    los[idx] = lo


def _visibility_windowed(vis, los, los_all, sub, origin, g, z, r, c, inside, ep, up, az, el) -> None:
    """The loop of :func:`line_of_sight` over the epochs without a cache, on the window ``sub``
    (at ``origin`` in the map) -- with the same answers, faster: a sample at or above the
    highest cell of the window sees every satellite (a visibility height never exceeds the
    heights it comes from); for the others each satellite is scanned only over its
    :func:`~skyroute.stages.occlusion.occluder_window` within ``sub`` (the cells that can
    decide those samples), and not at all when they are at or above its highest cell."""
    r0, c0 = origin
    h_max = float(np.float32(sub.max())) if sub.size else -np.inf   # the kernel works in float32
    for e in np.unique(ep):
        rows = np.nonzero(ep == e)[0]
        sats = np.nonzero(up[e])[0]
        los[rows] = los_all[e][None, :, :]
        if sats.size == 0:
            continue
        zr = z[rows]
        vis[np.ix_(rows, sats)] = (zr >= -np.inf)[:, None]      # outside the map / above every cell
        need = inside[rows] & ~(zr >= h_max)
        if not need.any():
            continue
        nr = rows[need]
        rr, cc, zn = r[nr] - r0, c[nr] - c0, z[nr]
        az_g = np.atleast_1d(grid_azimuth_deg(az[e, sats], g))
        for j, s in enumerate(sats):
            w0, w1, v0, v1 = occluder_window(rr, cc, float(zn.min()), h_max, float(az_g[j]), float(el[e, s]),
                                             g.resolution_m, sub.shape)
            win = sub[w0:w1, v0:v1]
            if np.all(zn >= np.float32(win.max())):       # above every cell that can decide them
                vis[nr, s] = True
                continue
            vh = visibility_heights_numpy(win, az_g[j:j + 1], el[e, s:s + 1], g.resolution_m,
                                          origin=(r0 + w0, c0 + v0))[0]
            vis[nr, s] = zn >= vh[rr - w0, cc - v0]


def navigation_along(problem, sky: xr.Dataset, surface_2d, t_abs, p, start_time_utc, imu, *,
                     gnss_sigma_m: float = DEFAULT_UERE_M, gnss_period_s: float = 1.0, warmup_s: float = 60.0,
                     los_cache: dict | None = None, initial_state: FilterState | None = None,
                     return_track: bool = False):
    """``(sigma_p_m, n_visible)`` per sample of the flight ``t_abs`` (m,) [s], ``p`` (m, 3) [m]:
    GNSS in line of sight (:func:`line_of_sight`) and the covariance analysis
    (:func:`~skyroute.stages.navigation.navigation_error`, ``imu``: a vehicle profile or IMU
    spec); the filter first runs ``warmup_s`` [s] at the start point (no initial transient),
    or, with ``initial_state`` (:class:`~skyroute.stages.navigation.FilterState`, the filter a
    vehicle in flight has: a tactical replan), continues that filter without a warm-up.
    ``start_time_utc`` None: the first sky epoch.  ``return_track``: also return the
    :class:`~skyroute.stages.navigation.FilterTrack` of the samples (a third item)."""
    if start_time_utc is None:
        start_time_utc = pd.Timestamp(sky["time"].values[0])
    t_abs = np.asarray(t_abs, float)
    p = np.asarray(p, float)
    nw = int(math.floor(warmup_s / gnss_period_s + 1e-9)) if (warmup_s > 0 and initial_state is None) else 0
    t_w = t_abs[0] - gnss_period_s * np.arange(nw, 0, -1)
    t_all = np.concatenate([t_w, t_abs])
    p_all = np.concatenate([np.repeat(p[:1], nw, axis=0), p])
    los, vis = line_of_sight(problem, sky, surface_2d, t_all, p_all, start_time_utc, cache=los_cache)
    nav = navigation_error(t_all, los, vis, imu=imu, gnss_sigma_m=gnss_sigma_m, dt_s=gnss_period_s,
                           initial_state=initial_state, return_covariance=return_track)
    sigma, nvis = np.asarray(nav["sigma_p_m"].values, float)[nw:], vis.sum(axis=1)[nw:]
    if not return_track:
        return sigma, nvis
    return sigma, nvis, FilterTrack.from_dataset(nav.isel(time=slice(nw, None)))
