"""GNSS occlusion by the surface model: the *visibility height* of a satellite direction.

For a satellite at infinity in direction (azimuth ``a``, elevation ``e``) and a surface model
``h`` (terrain + buildings, a raster of heights [m]), the visibility height ``V`` of a cell is
the lowest altitude above the cell centre from which the line of sight to the satellite is
free: above ``V`` the satellite is visible, below it is occluded.  ``V >= h`` (a receiver
inside a building sees nothing), and since ``e > 0`` every cell has a finite ``V``.

Surface model
    Every cell is a flat-topped prism: its square footprint extruded up to its height.  A ray
    is blocked by a cell when it passes over the cell's footprint below the cell's height, so
    a cell ``c`` entered by the ray at horizontal distance ``t`` imposes ``z >= h(c) - t tan e``
    and ``V(p) = max(h(p), max_c h(c) - t_c tan e)`` over the cells the ray crosses.  Outside
    the map there is no obstacle.

Algorithm (an O(N) column scan after seed 003, section II-B)
    The rays toward one satellite are parallel, so the scan follows a family of parallel
    *lines* in the satellite direction, one per cell across the sweep.  Along one exact
    line the prism traversal is exact and runs as a recurrence: sweeping from the satellite
    side, keep ``G = max(h(c) - kappa * p_in(c))`` over the cells crossed so far (``p_in`` the
    sweep coordinate where the line enters cell ``c``, ``kappa`` the height drop of the ray
    per unit of sweep); at a line point ``p`` the exact requirement is ``G + kappa * p``.
    O(1) per cell and direction, all lines advance in lockstep (contiguous, vectorised
    loops over one map row per step; sweeps along x run on the map transposed once per
    call, the output is transposed back in blocks).  The sweep axis is the grid axis
    closest to the azimuth, so a line crosses at most two cells per step; any azimuth is handled (no 8-direction quantisation, no
    resampling of heights).  Seed 003 compares projected image coordinates along
    columns of a camera-like resampled grid; here the comparison is the running maximum
    ``G`` in the sheared (line, sweep) frame, which needs no resampling.

Remaining approximation
    A cell centre is generally not on a line.  Default (``lateral="linear"``): the cell gets
    ``max(h(cell), requirement)`` of the two lines around its centre, linearly interpolated
    across the sweep (weights = distances along the cross axis, < 1 cell); ``"nearest"``
    takes the nearest of ``lines_per_cell`` lines (at most ``0.5 / lines_per_cell`` cell
    away).  Each line value is exact for the prism model, so errors appear only where a
    shadow edge or a steep slope runs between the line and the centre (edges roughly
    parallel to the azimuth).  Measured against an exact prism ray caster on SRTM and the
    Rotterdam/Helsinki surfaces (tests): 99.90 to 99.95 % identical visible/occluded
    decisions at random cells, altitudes and directions, 99th percentile error 0.57 to
    0.75 x ``(cell * tan(e) + 0.5 m)``, median error 0.  Also: satellites are at infinity (parallel
    rays); the map is flat (Earth curvature ignored: an obstacle d away is d^2 / 2R too
    high, 0.08 m at 1 km, 8 m at 10 km, so long terrain shadows at low elevation are
    slightly too long); true azimuths become grid azimuths with the meridian convergence at
    the map centre (one value per map, < 0.05 deg change over a few km in a UTM zone).

Layers: the numba kernel :func:`_scan_kernel`, the numpy runner
:func:`visibility_heights_numpy`, the dask runner :func:`visibility_heights_dask`
(``map_overlap``-style, halo from the data: :func:`shadow_halo_cells`), and the public
:func:`visibility_height` on ``xarray`` rasters.
"""

from __future__ import annotations

import math
from typing import Literal

import numba
import numpy as np
import xarray as xr
from pyproj import CRS, Proj

from skyroute.pipeline.errors import CRSError, InputError
from skyroute.stages.grid import Grid

__all__ = [
    "DEFAULT_LINES_PER_CELL",
    "grid_azimuth_deg",
    "shadow_halo_cells",
    "visibility_height",
    "visibility_heights_dask",
    "visibility_heights_numpy",
]

#: Scan lines per cell across the sweep (``lateral="nearest"`` may use more).
DEFAULT_LINES_PER_CELL = 1


# ----------------------------------------------------------------------------------------
# numba kernel
# ----------------------------------------------------------------------------------------

@numba.njit(cache=True, nogil=True)
def _line_tables(p_top, n_sweep, m, kappa, lines_per_cell, family):
    """Per sweep step ``k`` (normalised sweep coordinate ``P = p_top - k``) the geometry
    of the lines of one family, identical for every line of the family (they are integer
    translates across the sweep):

    ``lo, hi``: cross offsets of the (one or two) cells crossed in the step; ``q0``: offset of
    the cell containing the line point at ``P``; ``case`` 0: one cell, 1: two cells and the
    upper one is ahead of the query point, 2: two cells and the query cell is the upper one;
    ``kp_lo, kp_hi``: ``kappa * p_in`` of the lower / upper cell; ``kP = kappa * P``;
    ``own``: this family holds the line point nearest the cell centre at this step.
    """
    beta = family / lines_per_cell
    lo = np.empty(n_sweep, np.int64)
    hi = np.empty(n_sweep, np.int64)
    q0 = np.empty(n_sweep, np.int64)
    case = np.empty(n_sweep, np.int8)
    kp_lo = np.empty(n_sweep, np.float64)
    kp_hi = np.empty(n_sweep, np.float64)
    kP = np.empty(n_sweep, np.float64)
    own = np.empty(n_sweep, np.bool_)
    r0 = np.empty(n_sweep, np.int64)
    w1 = np.empty(n_sweep, np.float64)
    for k in range(n_sweep):
        P = float(p_top - k)
        ylo = beta + m * (P - 0.5)
        yhi = beta + m * (P + 0.5)
        y0 = beta + m * P
        lo[k] = math.floor(ylo + 0.5)
        hi[k] = math.floor(yhi + 0.5)
        q0[k] = math.floor(y0 + 0.5)
        r0[k] = math.floor(y0)
        w1[k] = y0 - r0[k]
        kp_lo[k] = kappa * (P - 0.5)
        kP[k] = kappa * P
        if hi[k] > lo[k]:
            # the line enters the upper cell where it crosses q = hi - 0.5
            kp_hi[k] = kappa * ((hi[k] - 0.5 - beta) / m)
            case[k] = 1 if q0[k] == lo[k] else 2
        else:
            kp_hi[k] = kp_lo[k]
            case[k] = 0
        d = abs(y0 - q0[k])
        is_own = True
        for f2 in range(lines_per_cell):
            if f2 == family:
                continue
            y2 = f2 / lines_per_cell + m * P
            d2 = abs(y2 - math.floor(y2 + 0.5))
            if d2 < d or (d2 == d and f2 < family):
                is_own = False
        own[k] = is_own
    return lo, hi, q0, case, kp_lo, kp_hi, kP, own, r0, w1


@numba.njit(cache=True, nogil=True)
def _update_lines(G, L, rlo, rhi, n, cs, klo, khi, kp):
    """One sweep step for ``n`` lines: ``L`` = requirement at the line points (cells ahead
    of them folded in) [m, relative], ``G`` = running max over every crossed cell."""
    if cs == 0:
        for j in range(n):
            g = G[j]
            L[j] = g + kp
            G[j] = max(g, rlo[j] - klo)
    elif cs == 1:      # the upper cell is entered after the line point: ahead of it
        for j in range(n):
            g = max(G[j], rhi[j] - khi)
            L[j] = g + kp
            G[j] = max(g, rlo[j] - klo)
    else:
        for j in range(n):
            g = G[j]
            L[j] = g + kp
            G[j] = max(g, max(rlo[j] - klo, rhi[j] - khi))


_STRIP = 32  # sweep steps per block of the transposed output


@numba.njit(cache=True, nogil=True)
def _scan_kernel(h, out, sa, sb, sweep0, cross0, m, kappa, lines_per_cell, interp, out_t):
    """Visibility heights [m] of one direction over ``h`` (n_sweep, n_cross), sweeping
    along axis 0, written into ``out`` (same shape).

    Normalised global coordinates: ``P = sa * (sweep0 + i_sweep)``, ``Q = sb * (cross0 +
    i_cross)`` with ``i_sweep`` / ``i_cross`` the local indices along axis 0 / 1; the satellite lies toward ``+P``, the rays rise ``m`` (0..1) in ``Q`` per
    unit of ``P`` and drop ``kappa`` [m] per unit of ``P`` seen from the satellite.  Line ``a``
    of a family crosses at sweep step ``k`` (``P = p_top - k``) the cells ``Q = a + lo[k]`` and
    (if two) ``a + hi[k]``.  Lines advance in lockstep, so each step is a few contiguous
    (SIMD) loops over lines, one row of ``h`` per step.  ``interp`` (``lines_per_cell == 1``): a cell gets the
    linear interpolation across the sweep of the two lines around its centre; else the
    value of the nearest line point.  ``out_t``: write ``out`` transposed (``out[i_cross,
    i_sweep]``) through a strip buffer of ``_STRIP`` steps (blocked transposition).
    """
    ns, nc = h.shape
    neg_inf = -np.inf
    p_top = sweep0 + ns - 1 if sa > 0 else -sweep0
    q_min = cross0 if sb > 0 else -(cross0 + nc - 1)
    q_max = q_min + nc - 1
    ls_of = np.empty(ns, np.int64)
    for k in range(ns):
        ls_of[k] = sa * (p_top - k) - sweep0
    pad = 4
    for family in range(lines_per_cell):
        lo, hi, q0, case, kp_lo, kp_hi, kP, own, r0, w1 = _line_tables(
            p_top, ns, m, kappa, lines_per_cell, family)
        a_min = q_min - hi.max() - 2
        a_max = q_max - lo.min() + 2
        # every line at once; row = the map row in normalised order, -inf padded
        n_lines = a_max - a_min + 1
        G = np.full(n_lines, neg_inf)
        L = np.empty(n_lines)
        row = np.full(nc + 2 * pad, neg_inf)
        strip = np.empty((_STRIP, nc), np.float32)
        for k in range(ns):
            ls = ls_of[k]
            hrow = h[ls]
            rc = row[pad:pad + nc]
            if sb > 0:
                for c in range(nc):
                    rc[c] = hrow[c]
            else:
                for c in range(nc):
                    rc[c] = hrow[nc - 1 - c]
            # only the lines over the map at this step change (others meet -inf)
            ia0 = max(q_min - hi[k] - a_min - 1, 0)
            ia1 = min(q_max - lo[k] - a_min + 2, n_lines)
            blo = a_min + lo[k] - q_min + pad
            bhi = a_min + hi[k] - q_min + pad
            _update_lines(G[ia0:ia1], L[ia0:ia1], row[ia0 + blo:ia1 + blo],
                          row[ia0 + bhi:ia1 + bhi], ia1 - ia0, case[k], kp_lo[k],
                          kp_hi[k], kP[k])
            orow = strip[k % _STRIP] if out_t else out[ls]
            if interp:
                d1 = q_min - r0[k] - a_min
                w = w1[k]
                La = L[d1:d1 + nc]
                Lb = L[d1 - 1:d1 - 1 + nc]
                if sb > 0:
                    for c in range(nc):
                        hc = rc[c]
                        orow[c] = (1.0 - w) * max(hc, La[c]) + w * max(hc, Lb[c])
                else:
                    for c in range(nc):
                        hc = rc[c]
                        orow[nc - 1 - c] = (1.0 - w) * max(hc, La[c]) + w * max(hc, Lb[c])
            elif own[k]:
                d0 = q_min - q0[k] - a_min
                Lc = L[d0:d0 + nc]
                if sb > 0:
                    for c in range(nc):
                        orow[c] = max(rc[c], Lc[c])
                else:
                    for c in range(nc):
                        orow[nc - 1 - c] = max(rc[c], Lc[c])
            if out_t and (k % _STRIP == _STRIP - 1 or k == ns - 1):
                kb = k - k % _STRIP
                nt = k - kb + 1
                l0 = min(ls_of[kb], ls_of[k])      # sweep steps kb..k are contiguous in out
                for c in range(nc):
                    seg = out[c, l0:l0 + nt]
                    for t in range(nt):
                        if interp or own[kb + t]:
                            seg[ls_of[kb + t] - l0] = strip[t, c]


# ----------------------------------------------------------------------------------------
# numpy runner
# ----------------------------------------------------------------------------------------

def _direction_geometry(az_grid_deg: float, el_deg: float, cell_m: float):
    """(sweep_axis, sa, sb, m, kappa) of a grid azimuth / elevation (see :func:`_scan_kernel`):
    the sweep runs along the array axis closest to the azimuth (0: y, 1: x)."""
    az = math.radians(az_grid_deg)
    dcol = math.sin(az)          # toward the satellite: +col is grid east
    drow = -math.cos(az)         # +row is grid south
    if abs(dcol) >= abs(drow):
        sweep_axis, d_sweep, d_cross = 1, dcol, drow
    else:
        sweep_axis, d_sweep, d_cross = 0, drow, dcol
    sa = 1 if d_sweep > 0 else -1
    sb = 1 if d_cross >= 0 else -1
    m = min(abs(d_cross) / abs(d_sweep), 1.0)
    if m < 1e-12:  # axis directions: sin/cos round-off would leak 1e-14 m across rows
        m = 0.0
    kappa = cell_m * math.tan(math.radians(el_deg)) * math.sqrt(1.0 + m * m)
    return sweep_axis, sa, sb, m, kappa


def visibility_heights_numpy(surface_2d: np.ndarray, az_grid_deg, el_deg, cell_m: float, *,
                             origin: tuple[int, int] = (0, 0),
                             lines_per_cell: int = DEFAULT_LINES_PER_CELL,
                             lateral: Literal["linear", "nearest"] = "linear") -> np.ndarray:
    """Visibility heights [m] of ``n`` directions over a NaN-free 2-D surface [m].

    ``surface_2d``: heights, row 0 = north edge, columns west to east (a north-up grid);
    ``az_grid_deg``: azimuths [deg] clockwise from **grid** north; ``el_deg``: elevations
    [deg], each in (0, 90]; ``cell_m``: cell size [m].  ``origin``: (row, col) of
    ``surface_2d[0, 0]`` in a larger map, so that blocks of one map (dask) get bit-identical
    results to the whole map.  Outside the array there is no obstacle.  ``lateral``:
    ``"linear"`` interpolates across the sweep between the two scan lines around each cell
    centre (one line per cell); ``"nearest"`` takes the nearest of ``lines_per_cell`` lines
    per cell.
    Returns ``(n, ny, nx)`` float32.  Inputs are not validated beyond shapes: call
    :func:`visibility_height` for checked use.
    """
    h = np.ascontiguousarray(surface_2d, dtype=np.float32)
    if h.ndim != 2:
        raise InputError(f"surface must be 2-D (y, x), got shape {h.shape}")
    az = np.atleast_1d(np.asarray(az_grid_deg, dtype=np.float64))
    el = np.atleast_1d(np.asarray(el_deg, dtype=np.float64))
    if az.shape != el.shape or az.ndim != 1:
        raise InputError(f"az and el must be scalars or 1-D of equal length, got {az.shape} and {el.shape}")
    out = np.empty((az.size,) + h.shape, dtype=np.float32)
    interp = _check_lateral(lateral, lines_per_cell)
    if h.size == 0:
        return out
    relief = float(h.max() - h.min())
    row0, col0 = int(origin[0]), int(origin[1])
    h_t = None     # the map transposed, for sweeps along x (made once per call)
    for i in range(az.size):
        tan_e = math.tan(math.radians(el[i]))
        # a neighbouring cell is entered at >= cell_m / 2: steeper than the relief -> V = h
        if not (el[i] < 90.0) or 0.5 * cell_m * tan_e > relief:
            out[i] = h
            continue
        sweep_axis, sa, sb, m, kappa = _direction_geometry(az[i], el[i], cell_m)
        if sweep_axis == 0:
            _scan_kernel(h, out[i], sa, sb, row0, col0, m, kappa, lines_per_cell, interp, False)
        else:
            if h_t is None:
                h_t = np.ascontiguousarray(h.T)
            _scan_kernel(h_t, out[i], sa, sb, col0, row0, m, kappa, lines_per_cell, interp, True)
    return out


def _check_lateral(lateral: str, lines_per_cell: int) -> bool:
    if lateral not in ("linear", "nearest"):
        raise InputError(f"lateral must be 'linear' or 'nearest', got {lateral!r}")
    if not (isinstance(lines_per_cell, int | np.integer) and 1 <= lines_per_cell <= 16):
        raise InputError(f"lines_per_cell must be an integer 1..16, got {lines_per_cell!r}")
    if lateral == "linear" and lines_per_cell != 1:
        raise InputError("lateral='linear' uses one line per cell: pass lines_per_cell=1 or "
                         "lateral='nearest'")
    return lateral == "linear"


def shadow_halo_cells(surface_2d_or_da, min_el_deg: float, cell_m: float) -> int:
    """Cells [-] a shadow can reach at most: ``(max h - min h) / tan(min elevation)`` in cells,
    plus 2 cells of margin (prism entry distance, line offset).  Only cells within this
    distance can change a visibility height; the dask runner uses it as overlap depth."""
    if not 0.0 < float(min_el_deg) <= 90.0:
        raise InputError(f"min elevation {min_el_deg} deg must be in (0, 90]")
    if not cell_m > 0:
        raise InputError(f"cell size {cell_m} m must be positive")
    data = surface_2d_or_da.data if isinstance(surface_2d_or_da, xr.DataArray) else surface_2d_or_da
    hmax, hmin = _nan_extrema(data)
    return _halo_from_relief(hmax - hmin, min_el_deg, cell_m)


def _nan_extrema(data) -> tuple[float, float]:
    if _is_dask(data):
        import dask
        import dask.array as dsa
        hmax, hmin = dask.compute(dsa.nanmax(data), dsa.nanmin(data))
    else:
        arr = np.asarray(data)
        hmax, hmin = np.nanmax(arr), np.nanmin(arr)
    return float(hmax), float(hmin)


def _halo_from_relief(relief_m: float, min_el_deg: float, cell_m: float) -> int:
    if min_el_deg >= 90.0:
        return 2
    return int(math.ceil(relief_m / math.tan(math.radians(min_el_deg)) / cell_m)) + 2


# ----------------------------------------------------------------------------------------
# dask runner
# ----------------------------------------------------------------------------------------

def _is_dask(data) -> bool:
    return type(data).__module__.startswith("dask")


def visibility_heights_dask(surface, az_grid_deg, el_deg, cell_m: float, *,
                            lines_per_cell: int = DEFAULT_LINES_PER_CELL,
                            lateral: Literal["linear", "nearest"] = "linear",
                            fill_nan: Literal["nearest"] | None = None):
    """Dask version of :func:`visibility_heights_numpy`: ``(n, ny, nx)`` float32 dask array.

    Each block is computed with an overlap of :func:`shadow_halo_cells` cells (from the
    data's max/min and the lowest elevation; computed eagerly) on every side, so results are
    bit-identical to the unchunked runner.  Boundary: outside the map there is no obstacle
    (``boundary="none"``: edge blocks get no padding).  Chunks smaller than the halo are
    merged (rechunk) first.  ``fill_nan="nearest"`` fills NaN holes per overlapped block.
    """
    import dask.array as dsa

    _check_lateral(lateral, lines_per_cell)
    arr = surface if _is_dask(surface) else dsa.from_array(np.asarray(surface))
    az = np.atleast_1d(np.asarray(az_grid_deg, dtype=np.float64))
    el = np.atleast_1d(np.asarray(el_deg, dtype=np.float64))
    hmax, hmin = _nan_extrema(arr)
    halo = _halo_from_relief(hmax - hmin, float(el.min()), cell_m)
    # every chunk must be at least as wide as the overlap: merge small ones first
    depth = {}
    new_chunks = {}
    for ax in (0, 1):
        dim = arr.shape[ax]
        chunks = arr.chunks[ax]
        d = min(halo, dim)
        if len(chunks) > 1 and min(chunks) < d:
            size = max(d, max(chunks))
            n_full, rem = divmod(dim, size)
            merged = [size] * n_full + ([rem] if rem else [])
            if 0 < rem < d:
                merged = merged[:-2] + [size + rem]
            new_chunks[ax] = tuple(merged)
            chunks = new_chunks[ax]
        depth[ax] = 0 if len(chunks) == 1 else d
    if new_chunks:
        arr = arr.rechunk(new_chunks)
    starts = [np.concatenate([[0], np.cumsum(c)[:-1]]) for c in arr.chunks]
    g = dsa.overlap.overlap(arr, depth=depth, boundary={0: "none", 1: "none"})
    n = az.size

    def block(h, block_info=None):
        bi, bj = block_info[0]["chunk-location"]
        r0 = int(starts[0][bi]) - (depth[0] if bi > 0 else 0)
        c0 = int(starts[1][bj]) - (depth[1] if bj > 0 else 0)
        if fill_nan == "nearest":
            h = _fill_nearest(h)
        return visibility_heights_numpy(h, az, el, cell_m, origin=(r0, c0),
                                        lines_per_cell=lines_per_cell, lateral=lateral)

    res = g.map_blocks(block, new_axis=0, chunks=((n,),) + g.chunks, dtype=np.float32)
    return dsa.overlap.trim_internal(res, {0: 0, 1: depth[0], 2: depth[1]},
                                     boundary={0: "none", 1: "none", 2: "none"})


def _fill_nearest(h: np.ndarray) -> np.ndarray:
    from scipy import ndimage

    nan = np.isnan(h)
    if not nan.any():
        return h
    if nan.all():
        raise InputError("surface block is entirely NaN: nothing to fill from; crop the map or fill it")
    idx = ndimage.distance_transform_edt(nan, return_distances=False, return_indices=True)
    return h[tuple(idx)]


# ----------------------------------------------------------------------------------------
# public API
# ----------------------------------------------------------------------------------------

def grid_azimuth_deg(true_az_deg, grid: Grid | xr.DataArray):
    """Grid azimuth [deg, 0..360) of true (ENU) azimuths [deg] on a projected grid.

    ``grid_az = true_az - gamma`` with ``gamma`` the PROJ meridian convergence [deg] at the
    map centre (positive east of a UTM central meridian in the northern hemisphere, where
    true north points west of grid north).  One value per map: over a few km in a UTM zone
    ``gamma`` varies by < 0.05 deg.
    """
    if isinstance(grid, xr.DataArray):
        grid = Grid.from_dataarray(grid)
    crs = CRS.from_user_input(grid.crs_wkt)
    if not crs.is_projected:
        raise CRSError(f"grid CRS {crs.name!r} is not projected: reproject the surface to a "
                       "projected CRS in metres (e.g. its UTM zone)")
    xmin, ymin, xmax, ymax = grid.bounds
    lon, lat = grid.to_lonlat(0.5 * (xmin + xmax), 0.5 * (ymin + ymax))
    gamma = float(Proj(crs).get_factors(lon, lat).meridian_convergence)
    out = np.mod(np.asarray(true_az_deg, dtype=np.float64) - gamma, 360.0)
    return float(out) if out.ndim == 0 else out


def visibility_height(surface: xr.DataArray, az_deg, el_deg, *,
                      azimuth: Literal["true", "grid"] = "true",
                      fill_nan: Literal["nearest"] | None = None,
                      lateral: Literal["linear", "nearest"] = "linear",
                      lines_per_cell: int = DEFAULT_LINES_PER_CELL) -> xr.DataArray:
    """Visibility height [m] of satellite direction(s) over a surface model.

    ``surface``: raster (y, x) of terrain + building heights [m] on a north-up projected
    grid (see :mod:`skyroute.stages.grid`), numpy- or dask-backed (dask: blocks with a halo
    from :func:`shadow_halo_cells`, identical results).  ``az_deg``: satellite azimuth(s)
    [deg], clockwise from true north (``azimuth="true"``, converted with
    :func:`grid_azimuth_deg`) or from grid north (``"grid"``); ``el_deg``: elevation(s) in
    (0, 90] [deg].  Scalars give a (y, x) raster; 1-D arrays of length n give
    (direction, y, x).  ``fill_nan``: ``None`` refuses NaN cells, ``"nearest"`` fills them
    with the nearest valid height first (dask: within each block and its halo).  ``lateral`` / ``lines_per_cell``: see
    :func:`visibility_heights_numpy` (the default is the accuracy/speed optimum measured in
    the tests and benchmark).  Returns float32 heights in the surface's vertical
    datum: at and above them the satellite is in line of sight.
    """
    if not isinstance(surface, xr.DataArray):
        raise InputError(f"surface must be an xarray.DataArray (y, x), got {type(surface).__name__}")
    if surface.dims != ("y", "x"):
        raise InputError(f"surface must have dims ('y', 'x'), got {surface.dims}: select one 2-D slice")
    if azimuth not in ("true", "grid"):
        raise InputError(f"azimuth must be 'true' or 'grid', got {azimuth!r}")
    if fill_nan not in (None, "nearest"):
        raise InputError(f"fill_nan must be None or 'nearest', got {fill_nan!r}")
    _check_lateral(lateral, lines_per_cell)
    grid = Grid.from_dataarray(surface)
    scalar = np.ndim(az_deg) == 0 and np.ndim(el_deg) == 0
    az = np.atleast_1d(np.asarray(az_deg, dtype=np.float64))
    el = np.atleast_1d(np.asarray(el_deg, dtype=np.float64))
    if az.ndim != 1 or az.shape != el.shape:
        raise InputError(f"az_deg and el_deg must be scalars or 1-D arrays of equal length, "
                         f"got shapes {np.shape(az_deg)} and {np.shape(el_deg)}")
    if not (np.all(np.isfinite(az)) and np.all(np.isfinite(el))):
        raise InputError("az_deg and el_deg must be finite")
    bad = (el <= 0.0) | (el > 90.0)
    if bad.any():
        raise InputError(f"elevation(s) {el[bad].tolist()} deg out of (0, 90]: a satellite at or "
                         "below the horizon is never in line of sight; drop it before calling")
    if not np.issubdtype(surface.dtype, np.number):
        raise InputError(f"surface must hold numbers, got dtype {surface.dtype}")
    az_grid = grid_azimuth_deg(az, grid) if azimuth == "true" else np.mod(az, 360.0)
    az_grid = np.atleast_1d(az_grid)
    data = surface.data
    if _is_dask(data):
        import dask.array as dsa
        n_nan = int(dsa.isnan(data).sum().compute())
    else:
        n_nan = int(np.isnan(np.asarray(data, dtype=np.float64)).sum())
    if n_nan and fill_nan is None:
        raise InputError(f"surface has {n_nan} NaN cell(s) (holes): fill them first (e.g. "
                         "rioxarray's interpolate_na) or pass fill_nan='nearest'")
    if n_nan == surface.size:
        raise InputError("surface is entirely NaN: nothing to compute")
    if _is_dask(data):
        values = visibility_heights_dask(data.astype(np.float32), az_grid, el, grid.resolution_m,
                                         lines_per_cell=lines_per_cell, lateral=lateral,
                                         fill_nan=fill_nan)
    else:
        h = np.asarray(data, dtype=np.float32)
        if n_nan:
            h = _fill_nearest(h)
        values = visibility_heights_numpy(h, az_grid, el, grid.resolution_m,
                                          lines_per_cell=lines_per_cell, lateral=lateral)
    attrs = {
        "units": "m",
        "long_name": "visibility height: lowest altitude with line of sight to the satellite",
        "azimuth_reference": azimuth,
    }
    if "vertical_datum" in surface.attrs:
        attrs["vertical_datum"] = surface.attrs["vertical_datum"]
    coords = {"y": surface["y"], "x": surface["x"]}
    if scalar:
        da = xr.DataArray(values[0], dims=("y", "x"), coords=coords, name="visibility_height",
                          attrs=attrs)
        da = da.assign_coords(azimuth_deg=float(az[0]), grid_azimuth_deg=float(az_grid[0]),
                              elevation_deg=float(el[0]))
    else:
        da = xr.DataArray(values, dims=("direction", "y", "x"), coords=coords,
                          name="visibility_height", attrs=attrs)
        da = da.assign_coords(azimuth_deg=("direction", az), grid_azimuth_deg=("direction", az_grid),
                              elevation_deg=("direction", el))
    return da.rio.write_crs(surface.rio.crs)
