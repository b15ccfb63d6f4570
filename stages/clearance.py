"""Obstacle clearance for a spherical vehicle (seed 000 section II-B.3, eq. 13).

The vehicle is a sphere of radius ``r_p = d_m + K_m * dp_max`` [m] (:func:`vehicle_radius`).
Fixed obstacles are the surface height field (terrain + buildings): every cell is a
flat-topped prism from below the ground up to ``surface`` [m].  The sphere centred at
``p = (x, y, z)`` is clear of all prisms iff ``z >= F(x, y)`` with the *clearance floor*

    F(x, y) = max over cells c with d_h(p, footprint(c)) <= r_p of  surface(c) + sqrt(r_p^2 - d_h^2)

(d_h: horizontal distance from p to the cell's square footprint).  Storing F as a raster
makes the collision check O(1) (:func:`is_clear`).  Two variants (``mode``):

* ``"centre"``: F exactly at each cell centre (d_h from the centre point);
* ``"cell"`` (default): d_h is the distance between the two footprints, so the value is the
  maximum of the exact F over the whole cell: a nearest-cell lookup is then conservative
  (never clears a point that touches an obstacle) anywhere in the cell.

Cells outside the raster are not obstacles (pad the surface if the scenario extends beyond).

No-fly zones: a 2-D mask (unlimited in altitude) is dilated by ``r_p`` (same disc of offsets
and the same two modes).  An altitude-limited volume ``mask x [zmin, zmax]`` becomes, per
cell, a forbidden altitude interval ``[zmin - L, zmax + L]`` with ``L = sqrt(r_p^2 - d_h^2)``
(exact sphere-vs-box test) -- :func:`nofly_volume`.  Altitude limits above ground are the
rasters ``terrain + min_agl`` and ``terrain_min + max_agl`` (:func:`altitude_bounds`), with
``terrain`` the highest and ``terrain_min`` the lowest ground over each cell, so that both hold at
every point of the cell.
"""

from __future__ import annotations

import math

import dask.array as dsa
import numba
import numpy as np
import xarray as xr
from scipy import ndimage

from skyroute.stages.base import InputError
from skyroute.stages.grid import Grid

MODES = ("cell", "centre")


def vehicle_radius(d_m: float, k_m: float, dp_max_m: float) -> float:
    """Seed 000 eq. 13: ``r_p = d_m + K_m * dp_max`` [m]; safety distance ``d_m`` [m] >= 0,
    ``K_m`` >= 1, maximum positioning error ``dp_max_m`` [m] >= 0."""
    if not (np.isfinite(d_m) and d_m >= 0):
        raise InputError(f"safety distance d_m = {d_m} m must be >= 0")
    if not (np.isfinite(k_m) and k_m >= 1):
        raise InputError(f"K_m = {k_m} must be >= 1 (seed 000 eq. 13)")
    if not (np.isfinite(dp_max_m) and dp_max_m >= 0):
        raise InputError(f"maximum positioning error {dp_max_m} m must be >= 0")
    return float(d_m + k_m * dp_max_m)


# ------------------------------------------------------------------ disc of offsets


def disc_offsets(radius_m: float, resolution_m: float, mode: str = "cell"):
    """Offsets (di rows, dj cols) [cells] whose footprint lies within ``radius_m`` [m] and the
    lift ``sqrt(r^2 - d_h^2)`` [m] of each (see the module docstring for ``mode``)."""
    n = int(math.ceil(radius_m / resolution_m)) + 1
    d = np.arange(-n, n + 1)
    di, dj = np.meshgrid(d, d, indexing="ij")
    if mode == "cell":
        gx = np.maximum(np.abs(dj) - 1, 0) * resolution_m
        gy = np.maximum(np.abs(di) - 1, 0) * resolution_m
    else:
        gx = np.maximum(np.abs(dj) * resolution_m - resolution_m / 2, 0.0)
        gy = np.maximum(np.abs(di) * resolution_m - resolution_m / 2, 0.0)
    d2 = gx * gx + gy * gy
    keep = d2 <= radius_m * radius_m
    lift = np.sqrt(np.maximum(radius_m * radius_m - d2[keep], 0.0))
    order = np.argsort(-lift, kind="stable")
    return (di[keep][order].astype(np.int64), dj[keep][order].astype(np.int64),
            lift[order].astype(np.float64), n)


@numba.njit(cache=True)
def _max_lift_kernel(padded, di, dj, lift, pad, out):
    """out[i, j] = max_k padded[i + pad + di_k, j + pad + dj_k] + lift_k  (offset-major loop:
    the inner loop runs along a row, contiguous in memory, and vectorises)."""
    ny, nx = out.shape
    out[:, :] = -np.inf
    for k in range(di.size):
        h = lift[k]
        for i in range(ny):
            src = padded[i + pad + di[k], pad + dj[k]: pad + dj[k] + nx]
            dst = out[i]
            for j in range(nx):
                v = src[j] + h
                if v > dst[j]:
                    dst[j] = v


def _max_lift_numpy(a: np.ndarray, di, dj, lift, pad: int) -> np.ndarray:
    padded = np.pad(np.asarray(a, dtype=np.float64), pad, constant_values=-np.inf)
    out = np.empty(a.shape, dtype=np.float64)
    _max_lift_kernel(padded, di, dj, lift, pad, out)
    return out


def _max_lift_dask(a: dsa.Array, di, dj, lift, pad: int) -> dsa.Array:
    def block(b):  # b carries a halo of `pad` cells; its own rim is trimmed away by dask
        return _max_lift_numpy(b, di, dj, lift, pad)

    return dsa.map_overlap(block, a.astype(np.float64), depth=pad, boundary=-np.inf,
                           trim=True, dtype=np.float64)


def _max_lift(values, di, dj, lift, pad):
    if isinstance(values, dsa.Array):
        return _max_lift_dask(values, di, dj, lift, pad)
    return _max_lift_numpy(values, di, dj, lift, pad)


# ------------------------------------------------------------------ validation


def _check_radius(radius_m: float) -> float:
    if not (np.isfinite(radius_m) and radius_m >= 0):
        raise InputError(f"vehicle radius {radius_m} m must be finite and >= 0 (r_p = d_m + K_m dp_max)")
    return float(radius_m)


def _check_raster(da: xr.DataArray, what: str) -> Grid:
    if not isinstance(da, xr.DataArray) or da.dims[-2:] != ("y", "x") or da.ndim != 2:
        raise InputError(f"{what} must be a 2-D DataArray with dims ('y', 'x')")
    return Grid.from_dataarray(da)


def _check_mode(mode: str) -> None:
    if mode not in MODES:
        raise InputError(f"clearance mode {mode!r} must be one of {MODES}")


def _like(template: xr.DataArray, values, name: str, attrs: dict) -> xr.DataArray:
    da = xr.DataArray(values, dims=("y", "x"), coords={k: template.coords[k] for k in ("y", "x")},
                      name=name, attrs=attrs)
    crs = template.rio.crs
    return da.rio.write_crs(crs) if crs is not None else da


# ------------------------------------------------------------------ public


def clearance_floor(surface: xr.DataArray, radius_m: float, mode: str = "cell") -> xr.DataArray:
    """Lowest altitude [m, datum of ``surface``] of the sphere centre that keeps a sphere of
    ``radius_m`` [m] out of every surface prism (module docstring).  Works on numpy- or
    dask-backed rasters (dask: ``map_overlap`` with a halo of ceil(r / res) + 1 cells)."""
    r = _check_radius(radius_m)
    _check_mode(mode)
    grid = _check_raster(surface, "surface")
    data = surface.data
    if isinstance(data, dsa.Array):
        pass  # NaNs are checked lazily below
    elif not np.all(np.isfinite(np.asarray(data, dtype=float))):
        raise InputError("surface has NaN/inf cells: fill no-data (e.g. with the terrain) before computing clearance")
    di, dj, lift, pad = disc_offsets(r, grid.resolution_m, mode)
    out = _max_lift(data if isinstance(data, dsa.Array) else np.asarray(data, dtype=np.float64), di, dj, lift, pad)
    return _like(surface, out, "clearance_floor", {
        "units": "m", "long_name": "lowest sphere-centre altitude clear of the surface",
        "vertical_datum": surface.attrs.get("vertical_datum", ""), "radius_m": r, "mode": mode})


def dilate_nofly(mask: xr.DataArray, radius_m: float, mode: str = "cell") -> xr.DataArray:
    """Cells whose sphere (radius ``radius_m`` [m]) reaches a no-fly cell horizontally: the
    binary dilation of ``mask`` by the disc of :func:`disc_offsets` (scipy.ndimage)."""
    r = _check_radius(radius_m)
    _check_mode(mode)
    grid = _check_raster(mask, "no-fly mask")
    m = np.asarray(mask.values).astype(bool)
    di, dj, _, pad = disc_offsets(r, grid.resolution_m, mode)
    st = np.zeros((2 * pad + 1, 2 * pad + 1), dtype=bool)
    st[di + pad, dj + pad] = True
    out = ndimage.binary_dilation(m, structure=st) if m.any() else m.copy()
    return _like(mask, out, "nofly", {"long_name": "no-fly cells dilated by the vehicle radius",
                                      "radius_m": r, "mode": mode})


def nofly_volume(mask: xr.DataArray, radius_m: float, zmin_m: float = -np.inf, zmax_m: float = np.inf,
                 mode: str = "cell") -> xr.Dataset:
    """An altitude-limited no-fly volume ``mask x [zmin_m, zmax_m]`` [m] seen by a sphere of
    ``radius_m`` [m]: ``bottom_m``/``top_m`` rasters of the forbidden sphere-centre altitudes
    per cell (NaN where the volume is out of reach) and ``forbidden`` (reach mask)."""
    r = _check_radius(radius_m)
    _check_mode(mode)
    grid = _check_raster(mask, "no-fly mask")
    if not zmin_m <= zmax_m:
        raise InputError(f"no-fly volume needs zmin_m <= zmax_m, got [{zmin_m}, {zmax_m}] m")
    di, dj, lift, pad = disc_offsets(r, grid.resolution_m, mode)
    base = np.where(np.asarray(mask.values).astype(bool), 0.0, -np.inf)
    L = _max_lift_numpy(base, di, dj, lift, pad)
    reach = np.isfinite(L)
    bottom = np.where(reach, zmin_m - L, np.nan)
    top = np.where(reach, zmax_m + L, np.nan)
    ds = xr.Dataset({
        "forbidden": _like(mask, reach, "forbidden", {"long_name": "cells reached by the no-fly volume"}),
        "bottom_m": _like(mask, bottom, "bottom_m", {"units": "m", "long_name": "lowest forbidden centre altitude"}),
        "top_m": _like(mask, top, "top_m", {"units": "m", "long_name": "highest forbidden centre altitude"}),
    })
    ds.attrs = {"radius_m": r, "zmin_m": float(zmin_m), "zmax_m": float(zmax_m), "mode": mode}
    return ds


def altitude_bounds(terrain: xr.DataArray, min_agl_m: float, max_agl_m: float,
                    terrain_min: xr.DataArray | None = None) -> xr.Dataset:
    """Altitude limits above ground as rasters that hold at every point of a cell:
    ``floor_m = terrain + min_agl_m`` with ``terrain`` the highest ground over the cell, and
    ``ceiling_m = terrain_min + max_agl_m`` with ``terrain_min`` the lowest (``terrain`` when
    None: a ground known at one height per cell) [m, datum of the terrain]."""
    _check_raster(terrain, "terrain")
    if terrain_min is None:
        terrain_min = terrain
    elif _check_raster(terrain_min, "terrain_min") != Grid.from_dataarray(terrain):
        raise InputError("terrain_min must be on the grid of terrain")
    elif bool((terrain_min > terrain).any()):
        raise InputError("terrain_min is above terrain somewhere: give the lowest and the highest ground per cell")
    if not (np.isfinite(min_agl_m) and np.isfinite(max_agl_m) and 0 <= min_agl_m < max_agl_m):
        raise InputError(f"altitude limits need 0 <= min_agl_m < max_agl_m, got {min_agl_m}, {max_agl_m} m")
    datum = terrain.attrs.get("vertical_datum", "")
    fl = (terrain + float(min_agl_m)).rename("floor_m")
    fl.attrs = {"units": "m", "long_name": f"minimum altitude ({min_agl_m} m above ground)", "vertical_datum": datum}
    ce = (terrain_min + float(max_agl_m)).rename("ceiling_m")
    ce.attrs = {"units": "m", "long_name": f"maximum altitude ({max_agl_m} m above ground)", "vertical_datum": datum}
    return xr.Dataset({"floor_m": fl, "ceiling_m": ce}, attrs={"min_agl_m": float(min_agl_m),
                                                             "max_agl_m": float(max_agl_m)})


def clearance_dataset(surface: xr.DataArray, radius_m: float, terrain: xr.DataArray | None = None,
                      terrain_min: xr.DataArray | None = None, min_agl_m: float = 0.0, max_agl_m: float = np.inf, nofly: xr.DataArray | None = None,
                      volumes: list[tuple[xr.DataArray, float, float]] | None = None,
                      mode: str = "cell", obstacle_floor: np.ndarray | None = None) -> xr.Dataset:
    """Everything a planner needs for O(1) fixed-obstacle checks, on the surface grid:

    * ``obstacle_floor_m``: :func:`clearance_floor` of ``surface``;
    * ``min_altitude_m`` = max(obstacle floor, terrain + min_agl), ``max_altitude_m`` =
      terrain_min + max_agl (+inf without limit) [m] (:func:`altitude_bounds`);
    * ``nofly``: :func:`dilate_nofly` of the unlimited no-fly mask (False if none);
    * for each altitude-limited volume ``(mask, zmin_m, zmax_m)`` of ``volumes``:
      ``volume_bottom_m``/``volume_top_m`` with a leading ``volume`` dim (:func:`nofly_volume`).

    ``obstacle_floor``: a (y, x) floor [m] computed otherwise (:func:`dsm_clearance_floor`)
    replaces :func:`clearance_floor` of ``surface``.  Query with :func:`is_clear`.
    """
    r = _check_radius(radius_m)
    if obstacle_floor is None:
        floor = clearance_floor(surface, r, mode)
    else:
        if np.shape(obstacle_floor) != surface.shape or not np.all(np.isfinite(obstacle_floor)):
            raise InputError(f"obstacle_floor must be a finite array of the surface's shape {surface.shape}")
        floor = _like(surface, np.asarray(obstacle_floor, np.float64), "clearance_floor", {
            "units": "m", "long_name": "lowest sphere-centre altitude clear of the surface",
            "vertical_datum": surface.attrs.get("vertical_datum", ""), "radius_m": r, "mode": mode})
    if terrain is None:
        terrain = surface
    if np.isfinite(max_agl_m):
        ab = altitude_bounds(terrain, min_agl_m, max_agl_m, terrain_min=terrain_min)
        lo, hi = ab["floor_m"], ab["ceiling_m"]
    else:
        if not (np.isfinite(min_agl_m) and min_agl_m >= 0):
            raise InputError(f"min_agl_m {min_agl_m} m must be >= 0")
        lo, hi = terrain + float(min_agl_m), xr.full_like(terrain, np.inf, dtype=float)
    ds = xr.Dataset(coords={k: surface.coords[k] for k in ("y", "x")})
    ds["obstacle_floor_m"] = floor
    # .data: numpy or dask (chunked rasters stay lazy, computed block by block when stored)
    ds["min_altitude_m"] = xr.DataArray(np.maximum(floor.data, lo.data.astype(float)), dims=("y", "x"),
                                        attrs={"units": "m", "long_name": "lowest allowed sphere-centre altitude"})
    ds["max_altitude_m"] = xr.DataArray(hi.data.astype(float), dims=("y", "x"),
                                        attrs={"units": "m", "long_name": "highest allowed sphere-centre altitude"})
    if nofly is not None:
        ds["nofly"] = (("y", "x"), dilate_nofly(nofly, r, mode).values, {"long_name": "dilated no-fly cells"})
    else:
        ds["nofly"] = (("y", "x"), np.zeros(floor.shape, dtype=bool))
    if volumes:
        vols = [nofly_volume(m, r, zmin, zmax, mode) for m, zmin, zmax in volumes]
        ds["volume_bottom_m"] = xr.concat([v["bottom_m"] for v in vols], dim="volume").drop_vars(
            "spatial_ref", errors="ignore")
        ds["volume_top_m"] = xr.concat([v["top_m"] for v in vols], dim="volume").drop_vars(
            "spatial_ref", errors="ignore")
    ds.attrs = {"radius_m": r, "mode": mode, "min_agl_m": float(min_agl_m), "max_agl_m": float(max_agl_m)}
    crs = surface.rio.crs
    return ds.rio.write_crs(crs) if crs is not None else ds


def is_clear(clearance: xr.DataArray | xr.Dataset, x, y, z) -> np.ndarray:
    """Vectorised point query: is a sphere centred at map points (x, y) [m], altitude z [m]
    clear?  ``clearance`` is a :func:`clearance_floor` raster (``z >= floor``) or a
    :func:`clearance_dataset` (floor, ceiling, no-fly and volumes).  Nearest cell; points
    outside the raster are not clear."""
    x, y, z = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float), np.asarray(z, float))
    g = Grid.from_dataarray(clearance)
    r, c = g.index_of(x, y)
    inside = (r >= 0) & (r < g.ny) & (c >= 0) & (c < g.nx)
    rr = np.where(inside, r, 0)
    cc = np.where(inside, c, 0)
    if isinstance(clearance, xr.DataArray):
        return inside & (z >= np.asarray(clearance.values)[rr, cc])
    ok = inside & (z >= clearance["min_altitude_m"].values[rr, cc]) & (z <= clearance["max_altitude_m"].values[rr, cc])
    ok &= ~clearance["nofly"].values[rr, cc]
    if "volume_bottom_m" in clearance:
        b = clearance["volume_bottom_m"].values[:, rr, cc]
        t = clearance["volume_top_m"].values[:, rr, cc]
        hit = (z[None] >= b) & (z[None] <= t)   # NaN compares False
        ok &= ~hit.any(axis=0)
    return ok


# ------------------------------------------------------------------ floor on a DSM's own prisms


def clearance_floor_native(values: np.ndarray, transform, crs, grid: Grid, radius_m: float) -> np.ndarray | None:
    """The ``"cell"`` clearance floor [m] of a raster's own prisms (``values``, NaN = no obstacle;
    square north-up pixels, affine ``transform`` in ``crs``) computed on the raster's lattice, then
    the max over every cell of ``grid`` (:func:`~skyroute.stages.grid.footprint_resample`).  The
    fine floor of a pixel is the highest exact floor over its footprint, so the max over the pixels
    overlapping a grid cell is the highest exact floor over that cell: exact per cell (no
    quantisation to the grid's cells), where the floor of the resampled surface costs metres near
    every edge.  NaN where no prism is in reach; None when the raster is not north-up with square
    pixels in the grid's CRS (use :func:`clearance_floor` of the resampled surface then)."""
    from pyproj import CRS

    from skyroute.stages.grid import footprint_resample

    r = _check_radius(radius_m)
    t = transform
    if not (t.b == 0 and t.d == 0 and t.a > 0 and np.isclose(-t.e, t.a, rtol=1e-9)
            and CRS.from_user_input(crs) == grid.crs):
        return None
    di, dj, lift, pad = disc_offsets(r, float(t.a), "cell")
    v = np.asarray(values, dtype=np.float64)
    fine = _max_lift_numpy(np.where(np.isnan(v), -np.inf, v), di, dj, lift, pad)
    fine[~np.isfinite(fine)] = -1e300   # no obstacle in reach: lower than anything, not NaN
    out = footprint_resample(fine, t, crs, grid, "max")
    out[out <= -1e299] = np.nan
    return out


def dsm_clearance_floor(path, grid: Grid, radius_m: float, nodata: str = "fill-max") -> np.ndarray | None:
    """:func:`clearance_floor_native` of a DSM (GeoTIFF, VRT or tiles) read by window with a margin
    of r_p beyond the grid, NoData holes filled as the surface stage fills them (``nodata``)."""
    from skyroute.stages.grid import fill_holes, read_window_holes

    r = _check_radius(radius_m)
    win, holes = read_window_holes(path, grid, what="surface DSM", margin_px=32)
    need = int(np.ceil(r / abs(win.transform.a))) + 2
    if need > 32:
        win, holes = read_window_holes(path, grid, what="surface DSM", margin_px=need)
    filled = fill_holes(win, holes, "fill-nearest" if nodata == "fill-nearest" else "fill-max")
    return clearance_floor_native(filled, win.transform, win.crs, grid, r)


def dsm_obstacle_floor(surface_ds: xr.Dataset, dsm_path, radius_m: float, nodata: str = "fill-max",
                       has_dem: bool = False) -> np.ndarray | None:
    """Obstacle floor [m] with a DSM: the DSM's floor on its own prisms
    (:func:`dsm_clearance_floor`, exact per cell), the max with the floor of the grid-resolution
    buildings (``building_id >= 0``) and, with a DEM, of the terrain; cells none of them reaches
    take the surface's floor.  None when the DSM is not on a grid this can use (the caller then
    uses the surface's floor)."""
    surf = surface_ds["surface"].load()
    native = dsm_clearance_floor(dsm_path, Grid.from_dataarray(surf), radius_m, nodata)
    if native is None:
        return None
    parts = [np.nan_to_num(native, nan=-np.inf)]
    bid = surface_ds["building_id"].values
    if (bid >= 0).any():
        parts.append(clearance_floor(surf.astype("float64").where(bid >= 0, -1e300), radius_m).values)
    if has_dem:
        parts.append(clearance_floor(surface_ds["terrain"].load(), radius_m).values)
    floor = np.maximum.reduce(parts)
    if not np.isfinite(floor).all():
        floor = np.where(np.isfinite(floor), floor, clearance_floor(surf, radius_m).values)
    return floor
