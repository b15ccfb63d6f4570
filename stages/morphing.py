"""Digital morphing map (seed 003 section II-C): the GNSS coverage floor epoch by epoch.

Seed 003 calls the surface that envelops the regions where the DOP exceeds a threshold a
*digital morphing map*: a fictitious elevation map that changes with time as the satellites
move.  :mod:`skyroute.stages.coverage` keeps one map per DOP threshold ``D_j``, the worst case
(max) over the epochs of a window, which a plan may rely on for the whole window.  This module
keeps the time axis instead:

* :func:`coverage_floor_series`: per epoch ``t``, per threshold ``D_j``, the lowest altitude
  [m] above which DOP < D_j (``coverage_floor``, dims (time, threshold, y, x)), computed by the
  same visibility scan and the same compiled floor kernel as the window floor, one epoch per
  task.  Identity (tested exactly): ``coverage_maps(...).coverage_floor`` equals
  ``series.coverage_floor.max("time", skipna=False)`` and ``unflyable`` equals
  ``series.unflyable.any("time")`` on the same satellites.  Optionally the DOP at a few altitude
  levels per epoch (``dop_volume``, dims (time, z, y, x): the volume whose isosurface DOP = D_j
  is the floor), from the same visibility heights (no second scan).  The result is lazy
  (dask; one chunk per epoch and spatial block) and can be written to zarr as it is.
* :func:`floor_under_vehicle`: the floor under a moving vehicle at the epochs of a series that
  fall within its flight, with its altitude margin over the floor.
* :func:`animate_floor`: a GIF of the floor map per epoch with the vehicle on it and an inset
  of its altitude against the floor under it.

Conventions as in :mod:`skyroute.stages.coverage`: heights in the surface's vertical datum
[m], ``coverage_floor`` NaN and ``unflyable`` True where DOP never gets below ``D_j`` under the
ceiling at that epoch; DOP +inf where there is no fix, NaN below the surface.  Between epochs
nothing is claimed (the satellites move ~0.5 deg/min: pick epochs a few seconds to a minute
apart with ``times``).
"""

from __future__ import annotations

import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import dask.array as da
import numpy as np
import xarray as xr

from skyroute.stages.base import InputError
from skyroute.stages.coverage import (  # the window floor's own building blocks
    _FULL,
    DOP_KINDS,
    Chunks,
    VisibilityFn,
    _check_surface,
    _default_visibility,
    _floor_epoch_kernel,
    _grid_azimuth,
    _limit,
    _min_el,
    _section_epoch_kernel,
    _spatial_attrs,
    _surface_array,
    _visibility,
    _wrap,
    check_thresholds,
    open_sky_dop,
)
from skyroute.stages.dop import los_rows
from skyroute.stages.orbits import as_time_sat, as_utc_times, epoch_directions
from skyroute.stages.overlap import overlap_maps

__all__ = ["animate_floor", "coverage_floor_series", "epoch_sky", "floor_under_vehicle"]


# --------------------------------------------------------------------------------------------
# satellites at the chosen epochs
# --------------------------------------------------------------------------------------------

def epoch_sky(sky: xr.Dataset, times: Any = None) -> xr.Dataset:
    """``az_deg``, ``el_deg`` (time, sat) [deg] of ``sky`` (e.g. ``almanac.sky_geometry`` or the
    ``satellites`` stage) at the epochs ``times``, with ``t_s`` [s] after the first epoch of
    ``sky`` (the mission start in the ``satellites`` stage).

    ``times``: None (every epoch of ``sky``), UTC instants (datetime64/str/datetime) or numbers
    = seconds after the first epoch of ``sky``; inside the span of ``sky`` (no extrapolation).
    Between two epochs of ``sky`` the elevation and the azimuth (the short way round) are
    interpolated linearly (satellites move ~0.5 deg/min: < 0.001 deg error at 1 min spacing);
    a satellite absent (NaN) at either neighbour is absent."""
    if not isinstance(sky, xr.Dataset) or "az_deg" not in sky or "el_deg" not in sky:
        raise InputError("sky must be an xarray.Dataset with az_deg and el_deg (time, sat), e.g. "
                         "from skyroute.stages.almanac.sky_geometry or the satellites stage")
    if "time" not in sky.dims or "time" not in sky.coords:
        raise InputError("sky needs a time coordinate (UTC datetime64) on dim 'time'")
    az0, el0, _ = as_time_sat(sky["az_deg"], sky["el_deg"])
    t_sky = as_utc_times(sky["time"].values)
    if t_sky.size > 1 and not np.all(np.diff(t_sky) > np.timedelta64(0, "ns")):
        raise InputError("the epochs of sky must be strictly increasing")
    start = t_sky[0]
    if times is None:
        t = t_sky
        az, el = az0, el0
    else:
        raw = np.atleast_1d(np.asarray(times.values if isinstance(times, xr.DataArray) else times))
        if raw.dtype.kind in "iuf":
            if not np.all(np.isfinite(raw)):
                raise InputError("times [s after the first epoch of sky] must be finite")
            t = start + np.round(raw.astype(np.float64) * 1e9).astype("timedelta64[ns]")
        else:
            t = as_utc_times(raw)
        if t.size == 0:
            raise InputError("times is empty: give at least one epoch")
        if t.min() < t_sky[0] or t.max() > t_sky[-1]:
            raise InputError(f"times {t.min()} .. {t.max()} leave the span of sky {t_sky[0]} .. "
                             f"{t_sky[-1]}: compute the satellites over the whole flight "
                             "(e.g. a longer gnss.window_min)")
        n = t_sky.size
        i0 = np.clip(np.searchsorted(t_sky, t, side="right") - 1, 0, n - 1)  # t_sky[i0] <= t
        i1 = np.minimum(i0 + 1, n - 1)
        span = (t_sky[i1] - t_sky[i0]).astype(np.float64)
        w = np.where(span > 0, (t - t_sky[i0]).astype(np.float64) / np.where(span > 0, span, 1), 0.0)
        w = w[:, None]
        d_az = np.mod(az0[i1] - az0[i0] + 180.0, 360.0) - 180.0
        az = np.mod(az0[i0] + w * d_az, 360.0)
        el = el0[i0] + w * (el0[i1] - el0[i0])
        exact = (t_sky[i0] == t)[:, None]  # an epoch of sky: its values as they are
        az = np.where(exact, az0[i0], az)
        el = np.where(exact, el0[i0], el)
    t_s = (t - start) / np.timedelta64(1, "s")
    sat = sky["sat"].values if "sat" in sky.coords else np.arange(az.shape[1])
    coords = {"time": ("time", t), "sat": ("sat", sat),
              "t_s": ("time", t_s, {"units": "s", "long_name": "time since the first epoch of sky"})}
    return xr.Dataset({
        "az_deg": (("time", "sat"), az, {"units": "deg", "long_name": "true azimuth of the satellite"}),
        "el_deg": (("time", "sat"), el, {"units": "deg", "long_name": "elevation of the satellite"}),
    }, coords=coords, attrs={"start_utc": str(start)})


# --------------------------------------------------------------------------------------------
# one (block, epoch) task
# --------------------------------------------------------------------------------------------

def _epoch_block(block: np.ndarray, origin: tuple[int, int], core: tuple[slice, slice], *,
                 az_grid_deg: np.ndarray, el_deg: np.ndarray, cell_m: float,
                 thresholds: np.ndarray, kind: int, mask_deg: float, levels_m: np.ndarray,
                 visibility_fn: VisibilityFn | None) -> np.ndarray:
    """``(J + A, core_y, core_x)`` float32 for one epoch (``az_grid_deg``/``el_deg`` (1, sat)):
    the raw floors of the J thresholds (+inf: never reached; the kernel of the window floor,
    folded once from -inf) then the DOP of ``kind`` at the A levels, from one visibility scan
    of the extended block."""
    fn = visibility_fn or _default_visibility()
    surface_2d = np.ascontiguousarray(block, dtype=np.float32)
    surf_core = surface_2d[core]
    out = np.full((thresholds.size + levels_m.size,) + surf_core.shape, -np.inf, np.float32)
    az, el = epoch_directions(az_grid_deg, el_deg, mask_deg)[0]
    h = np.ascontiguousarray(_visibility(fn, surface_2d, az, el, cell_m, origin))
    hc = h if core == _FULL else h[(slice(None),) + core]
    g = np.ascontiguousarray(los_rows(az, el))
    _floor_epoch_kernel(hc, g, thresholds, int(kind), out[:thresholds.size])
    if levels_m.size:
        sec = np.empty((levels_m.size, 6) + surf_core.shape, np.float32)
        _section_epoch_kernel(hc, g, np.ascontiguousarray(surf_core), levels_m, sec)
        out[thresholds.size:] = sec[:, kind + 1]
    return out


def _as_fn(**kw: Any):
    def fn(block: np.ndarray, origin: tuple[int, int], core: tuple[slice, slice]) -> np.ndarray:
        return _epoch_block(block, origin, core, **kw)
    return fn


# --------------------------------------------------------------------------------------------
# public
# --------------------------------------------------------------------------------------------

def _region_slices(surface: xr.DataArray, region_m: Sequence[float]) -> tuple[slice, slice]:
    """(rows, cols) of the cells of ``surface`` that intersect ``region_m`` = (xmin, ymin,
    xmax, ymax) [m], clipped to the map."""
    try:
        xmin, ymin, xmax, ymax = (float(v) for v in region_m)
    except (TypeError, ValueError):
        raise InputError(f"region_m must be (xmin, ymin, xmax, ymax) [m], got {region_m!r}") from None
    x = np.asarray(surface["x"].values, float)
    y = np.asarray(surface["y"].values, float)
    half = 0.5 * float(x[1] - x[0])
    cols = np.flatnonzero((x + half > xmin) & (x - half < xmax))
    rows = np.flatnonzero((y + half > ymin) & (y - half < ymax))
    if not (xmax > xmin and ymax > ymin) or cols.size == 0 or rows.size == 0:
        raise InputError(f"region_m {tuple(region_m)} does not overlap the map (x {x[0] - half:.1f}"
                         f" .. {x[-1] + half:.1f}, y {y[-1] - half:.1f} .. {y[0] + half:.1f} m)")
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)


def _region_parts(surface: xr.DataArray, rows: slice, cols: slice, min_el_deg: float,
                  cell_m: float, fns: list, n_lead: int) -> list[da.Array]:
    """One lazy ``(n_lead, rows, cols)`` array per epoch function: each runs on the region
    extended by the shadow halo of the whole map (its relief), with the region's offset as
    origin, so the values are those of the whole map's cells (no obstacle that can shadow the
    region is left out)."""
    from skyroute.stages.coverage import _halo_cells

    ny, nx = surface.shape
    halo = _halo_cells(surface.data, min_el_deg, cell_m)
    r0, r1 = max(rows.start - halo, 0), min(rows.stop + halo, ny)
    c0, c1 = max(cols.start - halo, 0), min(cols.stop + halo, nx)
    ext = surface.data[r0:r1, c0:c1]
    ext = (ext.astype(np.float32).rechunk(ext.shape) if isinstance(ext, da.Array)
           else da.from_array(np.asarray(ext, np.float32), chunks=ext.shape))
    core = (slice(rows.start - r0, rows.stop - r0), slice(cols.start - c0, cols.stop - c0))
    shape = ((n_lead,), (rows.stop - rows.start,), (cols.stop - cols.start,))

    def part(fn):
        return ext.map_blocks(lambda b: fn(np.asarray(b), (r0, c0), core), chunks=shape,
                              new_axis=[0], dtype=np.float32, meta=np.empty((0, 0, 0), np.float32))

    return [part(fn) for fn in fns]


def coverage_floor_series(surface: xr.DataArray, sky: xr.Dataset,
                          thresholds: Sequence[float] = (2.0, 3.0, 4.0), *, dop: str = "PDOP",
                          floor_m: float | np.ndarray | xr.DataArray | None = None,
                          ceiling_m: float | np.ndarray | xr.DataArray | None = None,
                          mask_deg: float = 5.0, times: Any = None,
                          levels_m: Sequence[float] | None = None,
                          region_m: Sequence[float] | None = None, chunks: Chunks = None,
                          visibility_fn: VisibilityFn | None = None) -> xr.Dataset:
    """The coverage floor per epoch (the digital morphing map of seed 003), lazily.

    Parameters
    ----------
    surface : (y, x) obstacle surface [m] with CRS, NaN-free (as :func:`coverage_maps`).
    sky : Dataset with ``az_deg``, ``el_deg`` (time, sat) TRUE azimuth / elevation [deg] and a
        UTC ``time`` coordinate (``almanac.sky_geometry``, the ``satellites`` stage).
    thresholds : DOP thresholds D_j (sorted ascending, duplicates dropped).
    dop : "GDOP", "PDOP" (default), "HDOP", "VDOP" or "TDOP".
    floor_m, ceiling_m : altitude limits [m] as in :func:`coverage_maps` (scalars or rasters).
    mask_deg : elevation mask [deg].
    times : the epochs (see :func:`epoch_sky`): None = every epoch of ``sky``; UTC instants; or
        seconds after the first epoch of ``sky`` (e.g. the times of a flight).
    levels_m : optional altitudes [m] (surface datum): adds ``dop_volume`` (time, z, y, x), the
        DOP of kind ``dop`` at these levels per epoch, from the same visibility scan.
    region_m : optional (xmin, ymin, xmax, ymax) [m]: only the cells of the map that meet this
        box (seed 003's control volume, e.g. the flight's corridor), computed on the box
        extended by the shadow halo of the whole map: the values equal those of the whole
        map's series (tested).  One block per epoch (``chunks`` is not used).
    chunks : spatial blocks [cells] as in :func:`coverage_maps` (None: the surface's own dask
        chunks, or one block).  Every (block, epoch) is one dask task.

    Returns
    -------
    Lazy Dataset: ``coverage_floor`` (time, threshold, y, x) float32 [m] (NaN where unflyable),
    ``unflyable`` (time, threshold, y, x) bool, optional ``dop_volume`` (time, z, y, x) float32,
    ``open_sky_dop`` (time), ``az_deg``/``el_deg`` (time, sat) of the epochs, coordinates
    ``time`` (UTC), ``t_s`` [s after the first epoch of ``sky``], ``threshold``, ``y``, ``x``,
    the surface's CRS; chunked (1, all, block, block).  On the same satellites
    ``coverage_floor.max("time", skipna=False)`` is exactly :func:`coverage_maps`' floor.
    """
    cell = _check_surface(surface)
    ep = epoch_sky(sky, times)
    az, el = ep["az_deg"].values, ep["el_deg"].values
    kind, mask, thr, n_max = check_thresholds(thresholds, dop, el, mask_deg)
    kind_name = DOP_KINDS[kind]
    levels = np.asarray([] if levels_m is None else list(levels_m), dtype=np.float64).ravel()
    if not np.all(np.isfinite(levels)):
        raise InputError("levels_m must be finite altitudes [m] in the surface's vertical datum")
    az_grid = _grid_azimuth(az, surface)
    floor_lim = _limit(floor_m, "floor_m", surface, -np.inf)
    ceil_lim = _limit(ceiling_m, "ceiling_m", surface, np.inf)
    n_t = az.shape[0]
    fns = [_as_fn(az_grid_deg=az_grid[t:t + 1], el_deg=el[t:t + 1], cell_m=cell, thresholds=thr,
                  kind=kind, mask_deg=mask, levels_m=levels, visibility_fn=visibility_fn)
           for t in range(n_t)]
    n_lead = thr.size + levels.size
    if region_m is not None:
        rows, cols = _region_slices(surface, region_m)
        parts = _region_parts(surface, rows, cols, _min_el(el, mask), cell, fns, n_lead)
        surface = surface.isel(y=rows, x=cols)  # the output's grid
        floor_lim, ceil_lim = (v[rows, cols] if np.ndim(v) == 2 else v
                               for v in (floor_lim, ceil_lim))
    else:
        if chunks is None and not isinstance(surface.data, da.Array):
            chunks = surface.shape  # one block, still lazy (one task per epoch)
        data, depth = _surface_array(surface, chunks, _min_el(el, mask), cell, n_max, n_lead)
        parts = overlap_maps(data, depth, fns, ((n_lead,),), np.float32)
    stacked = da.stack(parts)  # (time, J + A, y, x), one chunk per (epoch, block)
    raw = stacked[:, :thr.size]
    floor = da.maximum(raw, floor_lim)
    unflyable = da.isinf(raw) | ~(floor <= ceil_lim)
    floor = da.where(unflyable, np.nan, floor).astype(np.float32)

    common = _spatial_attrs(surface)
    thr_coord = xr.DataArray(thr, dims="threshold", attrs={
        "long_name": f"{kind_name} threshold D_j", "units": "1", "dop_kind": kind_name})
    coords: dict[str, Any] = {"threshold": thr_coord, "time": ep["time"], "t_s": ep["t_s"]}
    dims4 = ("time", "threshold", "y", "x")
    out = {
        "coverage_floor": _wrap(surface, floor, dims4, coords, "coverage_floor", {
            "long_name": f"lowest altitude above which {kind_name} < threshold at this epoch",
            "units": "m", **common, "comment": "NaN where unflyable (see `unflyable`)"}),
        "unflyable": _wrap(surface, unflyable, dims4, coords, "unflyable", {
            "long_name": f"{kind_name} never below the threshold under the ceiling at this epoch",
            "units": "1"}),
    }
    if levels.size:
        zc = xr.DataArray(levels, dims="z", attrs={"units": "m", "long_name": "altitude",
                                                   "axis": "Z", "positive": "up", **common})
        out["dop_volume"] = _wrap(surface, stacked[:, thr.size:], ("time", "z", "y", "x"),
                                  {"z": zc, "time": ep["time"], "t_s": ep["t_s"]}, "dop_volume", {
            "long_name": f"{kind_name} at altitude z at this epoch", "units": "1",
            "comment": "+inf with fewer than 4 visible satellites; NaN below the surface"})
    ds = xr.Dataset(out)
    osd = open_sky_dop(az, el, mask)[:, kind]
    ds["open_sky_dop"] = xr.DataArray(osd, dims="time", attrs={
        "long_name": f"open-sky {kind_name} (all satellites above the mask)", "units": "1"})
    ds["az_deg"] = ep["az_deg"]
    ds["el_deg"] = ep["el_deg"]
    ds["time"].attrs.update({"long_name": "epoch (UTC)", "standard_name": "time"})
    ds.attrs.update({
        "title": "GNSS coverage floor per epoch (digital morphing map)",
        "Conventions": "CF-1.8", "dop_kind": kind_name, "thresholds": thr.tolist(),
        "mask_deg": mask, "n_epochs": int(n_t), "start_utc": ep.attrs["start_utc"],
        "reduction": "none: one floor per epoch (max over time = the window floor)",
        "unflyable_convention": "coverage_floor = NaN and unflyable = True", **common,
        "references": "seed 003 section II-C (digital morphing map); issue 12 item 5",
    })
    if surface.rio.crs is not None:
        ds = ds.rio.write_crs(surface.rio.crs)
    return ds


def _path_arrays(path_t_s: Any, path_xyz_m: Any) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(path_t_s, dtype=np.float64).ravel()
    p = np.asarray(path_xyz_m, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] != t.size or t.size < 1:
        raise InputError(f"path_xyz_m must be (n, 3) [x, y, z] rows, one per path time, got "
                         f"shape {p.shape} for {t.size} times")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
        raise InputError("the path times and positions must be finite")
    if t.size > 1 and not np.all(np.diff(t) > 0):
        raise InputError("path_t_s must be strictly increasing [s]")
    return t, p


def floor_under_vehicle(series: xr.Dataset, threshold: float, path_t_s: Any,
                        path_xyz_m: Any) -> xr.Dataset:
    """The floor under a vehicle at the epochs of ``series`` within its flight.

    ``path_t_s`` (n,) [s after the first epoch of the satellites, as ``series.t_s``] and
    ``path_xyz_m`` (n, 3) map x, y [m] and altitude z [m, surface datum]; the position at an
    epoch is interpolated linearly.  Returns (epoch) ``t_s``, ``x_m``, ``y_m``, ``z_m``,
    ``floor_m`` (the coverage floor of the cell under the vehicle at that epoch, NaN where
    unflyable or off the map) and ``margin_m = z_m - floor_m``, plus ``epoch_index`` into
    ``series.time``."""
    t, p = _path_arrays(path_t_s, path_xyz_m)
    j = _threshold_index(series, threshold)
    ts = np.asarray(series["t_s"].values, dtype=np.float64)
    tol = 1e-6
    idx = np.flatnonzero((ts >= t[0] - tol) & (ts <= t[-1] + tol))
    if idx.size == 0:
        raise InputError(f"no epoch of the series falls within the flight ({t[0]:g} .. {t[-1]:g} s; "
                         f"series epochs {ts.min():g} .. {ts.max():g} s): compute the series "
                         "with times= over the flight")
    te = ts[idx]
    xyz = np.stack([np.interp(te, t, p[:, k]) for k in range(3)], axis=1)
    x = np.asarray(series["x"].values, float)
    y = np.asarray(series["y"].values, float)
    cell = float(x[1] - x[0])
    col = np.floor((xyz[:, 0] - (x[0] - cell / 2)) / cell).astype(np.int64)
    row = np.floor(((y[0] + cell / 2) - xyz[:, 1]) / cell).astype(np.int64)
    inside = (col >= 0) & (col < x.size) & (row >= 0) & (row < y.size)
    fl = series["coverage_floor"].isel(threshold=j)
    vals = np.full(idx.size, np.nan)
    if inside.any():
        k = np.flatnonzero(inside)
        picked = fl.isel(time=xr.DataArray(idx[k], dims="p"), y=xr.DataArray(row[k], dims="p"),
                         x=xr.DataArray(col[k], dims="p"))
        vals[k] = np.asarray(picked.values, dtype=np.float64)
    return xr.Dataset({
        "x_m": ("epoch", xyz[:, 0], {"units": "m"}), "y_m": ("epoch", xyz[:, 1], {"units": "m"}),
        "z_m": ("epoch", xyz[:, 2], {"units": "m", "long_name": "vehicle altitude"}),
        "floor_m": ("epoch", vals, {"units": "m", "long_name": "coverage floor under the vehicle",
                                    "comment": "NaN: unflyable at that epoch, or off the map"}),
        "margin_m": ("epoch", xyz[:, 2] - vals, {"units": "m",
                                                  "long_name": "vehicle altitude - floor"}),
        "epoch_index": ("epoch", idx),
    }, coords={"t_s": ("epoch", te, {"units": "s"})},
        attrs={"threshold": float(series["threshold"].values[j]),
               "dop_kind": str(series.attrs.get("dop_kind", "DOP"))})


def _threshold_index(series: xr.Dataset, threshold: float) -> int:
    thr = np.asarray(series["threshold"].values, float)
    hit = np.flatnonzero(np.isclose(thr, float(threshold), rtol=0, atol=1e-9))
    if hit.size == 0:
        raise InputError(f"threshold {threshold:g} is not in the series (thresholds "
                         f"{', '.join(f'{v:g}' for v in thr)})")
    return int(hit[0])


# --------------------------------------------------------------------------------------------
# animation
# --------------------------------------------------------------------------------------------

def _frame_epochs(n: int, max_frames: int) -> np.ndarray:
    """At most ``max_frames`` indices into ``range(n)``, evenly spread, first and last kept."""
    if not (isinstance(max_frames, int | np.integer) and max_frames >= 1):
        raise InputError(f"max_frames must be a positive integer, got {max_frames!r}")
    if n <= max_frames:
        return np.arange(n)
    return np.unique(np.round(np.linspace(0, n - 1, int(max_frames))).astype(np.int64))


def animate_floor(series: xr.Dataset, threshold: float, path_t_s: Any, path_xyz_m: Any,
                  out_gif: str | Path, *, max_frames: int = 60, fps: float = 4.0,
                  dpi: int = 80, frame_png: str | Path | None = None) -> Path:
    """GIF of the coverage floor for ``threshold`` at each epoch of ``series`` within the
    flight, with the vehicle on it and, below, its altitude against the floor under it.

    ``series``: from :func:`coverage_floor_series`; ``path_t_s`` (n,) [s, the series' ``t_s``
    clock] and ``path_xyz_m`` (n, 3) [m] the vehicle's trajectory (map x, y and altitude in
    the surface datum).  At most ``max_frames`` epochs (evenly subsampled), ``fps`` frames per
    second, ``dpi`` (the figure is ~6.6 in wide, its height follows the map).  ``frame_png``: also save the middle frame
    as a PNG (same drawing).  Grey = unflyable at that epoch.  Returns the GIF path."""
    import matplotlib
    from matplotlib.animation import FuncAnimation, PillowWriter
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import BoundaryNorm, ListedColormap
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    from skyroute.stages.figures import add_map_furniture, grow_until_unclipped, image_extent

    if not (float(fps) > 0):
        raise InputError(f"fps must be positive, got {fps!r}")
    t, p = _path_arrays(path_t_s, path_xyz_m)
    under = floor_under_vehicle(series, threshold, t, p)
    j = _threshold_index(series, threshold)
    frames = _frame_epochs(under.sizes["epoch"], max_frames)
    idx = under["epoch_index"].values[frames]
    fl = np.asarray(series["coverage_floor"].isel(threshold=j, time=xr.DataArray(idx, dims="f"))
                    .transpose("f", "y", "x").values, dtype=np.float32)
    te = under["t_s"].values
    z_v, f_v = under["z_m"].values, under["floor_m"].values
    times = series["time"].values[idx]
    kind = str(series.attrs.get("dop_kind", "DOP"))
    dval = float(series["threshold"].values[j])
    finite = fl[np.isfinite(fl)]
    vmin, vmax = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    if not vmax > vmin:
        vmax = vmin + 1.0
    extent = image_extent(series["coverage_floor"])

    # size the figure to the map's aspect: the map ~4.6 in wide (at most 5.6 in tall), the
    # colour bar beside it, the altitude inset 1.6 in tall below
    aspect = (extent[3] - extent[2]) / (extent[1] - extent[0])
    map_w = 4.6 if 4.6 * aspect <= 5.6 else 5.6 / aspect
    map_h = map_w * aspect
    fig = Figure(figsize=(max(map_w + 2.0, 5.2), max(map_h, 2.4) + 2.9), dpi=dpi,
                 layout="constrained")
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(2, 1, height_ratios=[max(map_h, 2.4) + 0.6, 1.6])
    ax = fig.add_subplot(gs[0])
    axz = fig.add_subplot(gs[1])
    # ~12 colour bands at round heights: readable values, and long runs of one colour keep
    # the GIF small
    bands = MaxNLocator(nbins=12).tick_values(vmin, vmax)
    cmap = matplotlib.colormaps["viridis"].resampled(len(bands) - 1)
    im = ax.imshow(fl[0], extent=extent, origin="upper", cmap=cmap,
                   norm=BoundaryNorm(bands, cmap.N), interpolation="nearest")
    grey = ax.imshow(np.where(np.isnan(fl[0]), 1.0, np.nan), extent=extent, origin="upper",
                     cmap=ListedColormap(["0.55"]), vmin=0, vmax=1, interpolation="nearest")
    ax.plot(p[:, 0], p[:, 1], color="white", lw=1.0, ls="--", zorder=5)
    flown, = ax.plot([], [], color="white", lw=2.2, zorder=6)
    dot, = ax.plot([], [], marker="o", ms=8, mfc="red", mec="white", mew=1.5, ls="none", zorder=7)
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.xaxis.set_major_locator(MaxNLocator(4))
    ax.yaxis.set_major_locator(MaxNLocator(5))
    ax.tick_params(labelsize=7)
    add_map_furniture(ax)
    info = ax.text(0.02, 0.98, "", transform=ax.transAxes, ha="left", va="top", fontsize=8,
                   zorder=11, bbox=dict(facecolor="white", alpha=0.8, lw=0, pad=2))
    datum = textwrap.shorten(str(series["coverage_floor"].attrs.get("vertical_datum", "")), 36,
                             placeholder="...")
    fig.colorbar(im, ax=ax, shrink=0.85, label=f"coverage floor [m] for {kind} < {dval:g}"
                 + (f"\ndatum: {datum}" if datum else "") + "\ngrey: unflyable at this epoch")
    title = ax.set_title("", fontsize=9)
    axz.plot(t, p[:, 2], color="C0", lw=1.5, label="vehicle altitude")
    axz.plot(te, f_v, color="C3", lw=1.2, marker=".", ms=3, label="floor under vehicle")
    cursor = axz.axvline(te[frames[0]], color="k", lw=0.8)
    axz.set_xlabel("t [s]")
    axz.set_ylabel("altitude [m]")
    axz.tick_params(labelsize=7)
    axz.legend(fontsize=7, loc="best", ncol=2)

    def draw(k: int) -> list:
        e = frames[k]
        tk = float(te[e])
        im.set_data(fl[k])
        grey.set_data(np.where(np.isnan(fl[k]), 1.0, np.nan))
        done = t <= tk
        xs = np.r_[p[done, 0], under["x_m"].values[e]]
        ys = np.r_[p[done, 1], under["y_m"].values[e]]
        flown.set_data(xs, ys)
        dot.set_data([xs[-1]], [ys[-1]])
        stamp = str(np.datetime_as_string(times[k], unit="s")).replace("T", " ")
        title.set_text(f"{kind} < {dval:g} coverage floor at {stamp} UTC (t = {tk:.0f} s)")
        if np.isfinite(f_v[e]):
            m = z_v[e] - f_v[e]
            info.set_text(f"vehicle {z_v[e]:.1f} m\nfloor {f_v[e]:.1f} m\nmargin {m:+.1f} m")
            info.get_bbox_patch().set_facecolor("#c8f0c8" if m >= 0 else "#f7c0c0")
        else:
            info.set_text(f"vehicle {z_v[e]:.1f} m\nfloor: none\n(unflyable or off map)")
            info.get_bbox_patch().set_facecolor("#f7c0c0")
        cursor.set_xdata([tk, tk])
        return [im, grey, flown, dot, title, info, cursor]

    draw(0)
    cut = grow_until_unclipped(fig)
    if cut:
        raise RuntimeError(f"animation frame text cut off by the canvas: {', '.join(cut)}")
    fig.set_layout_engine("none")  # freeze the layout: no jitter between frames
    out = Path(out_gif)
    out.parent.mkdir(parents=True, exist_ok=True)
    with matplotlib.rc_context({"savefig.bbox": None}):
        anim = FuncAnimation(fig, draw, frames=len(frames), blit=False, repeat=False)
        anim.save(out, writer=PillowWriter(fps=float(fps)), dpi=dpi)
        if frame_png is not None:
            draw(len(frames) // 2)
            fig.savefig(frame_png, dpi=dpi)
    return out
