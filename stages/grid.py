"""The scenario grid: a north-up raster in a projected CRS, and the raster conventions.

Conventions every stage follows (see ARCHITECTURE.md):

* A raster is an ``xarray.DataArray`` with dims ``("y", "x")`` (or leading dims before them),
  ``x`` ascending and ``y`` descending, coordinates at **cell centres** in metres of the
  projected CRS, which travels with the data as the rioxarray/CF ``spatial_ref`` coordinate
  (``da.rio.crs``).
* Every variable has a CF ``units`` attribute; heights also carry ``vertical_datum``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import rioxarray  # noqa: F401  (registers the .rio accessor)
from affine import Affine
from pyproj import CRS, Transformer

from skyroute.stages.base import CRSError, DataError, InputError
from skyroute.stages.gridspec import Grid, _crs_text, resolve_crs, utm_crs_for, utm_zone  # noqa: F401  (their home)


def warp_to_grid(path, grid: Grid, *, what: str, resampling: str = "bilinear",
                 require_overlap: bool = True) -> np.ndarray:
    """Band 1 of a GeoTIFF reprojected to ``grid`` (float64; NaN outside the raster and at its nodata).

    ``resampling="max"`` / ``"min"``: the max (min) over every source pixel whose footprint
    overlaps the target cell's footprint (:func:`footprint_resample`).  GDAL's
    ``Resampling.max`` (3.10) gives the same between grids of one CRS, but between rotated CRSs
    it misses pixels that overlap the target cell only partly and lowers obstacles
    (tests/test_grid.py).  A target cell touching a nodata pixel is NaN.  Surfaces and grounds
    are resampled this way.

    Parameters
    ----------
    path : str or pathlib.Path
        The GeoTIFF (for ``"max"``/``"min"`` also a VRT or a list of tiles, see
        :func:`read_window`).
    grid : Grid
        Target grid.
    what : str
        Names the layer in error messages ("terrain", "risk GeoTIFF").
    resampling : str, default "bilinear"
        ``"max"``, ``"min"`` or the name of a :class:`rasterio.warp.Resampling` method.
    require_overlap : bool, default True
        A raster that does not intersect the grid is a :class:`DataError`.

    Returns
    -------
    numpy.ndarray
        float64, shape ``(ny, nx)`` of ``grid``, in the raster's units.

    Raises
    ------
    DataError
        When the file is missing or unreadable, or (``require_overlap``) does not intersect the grid.
    CRSError
        When the raster has no CRS.
    """
    if resampling in ("max", "min"):
        win = read_window(path, grid, what=what, require_overlap=require_overlap)
        return footprint_resample(win.values, win.transform, win.crs, grid, how=resampling)
    from pathlib import Path

    import rasterio
    import rasterio.warp

    p = Path(path)
    if not p.is_file():
        raise DataError(f"{what} file not found: {p}")
    try:
        src = rasterio.open(p)
    except rasterio.errors.RasterioIOError as exc:
        raise DataError(f"cannot read {what} GeoTIFF {p}: {exc}") from exc
    with src:
        if src.crs is None:
            raise CRSError(f"{what} GeoTIFF {p} has no CRS; assign one with gdal_edit.py -a_srs EPSG:...")
        if require_overlap:
            b = rasterio.warp.transform_bounds(grid.crs, src.crs, *grid.bounds)
            sb = src.bounds
            if b[0] >= sb.right or b[2] <= sb.left or b[1] >= sb.top or b[3] <= sb.bottom:
                raise DataError(f"the AOI {tuple(round(v) for v in grid.bounds)} does not intersect {what} {p} "
                                f"(bounds {tuple(round(v) for v in sb)} in {src.crs}); fix aoi or the {what} path")
        out = np.full(grid.shape, np.nan, dtype=np.float64)
        rasterio.warp.reproject(
            source=rasterio.band(src, 1), destination=out, dst_transform=grid.transform, dst_crs=grid.crs,
            src_nodata=src.nodata, dst_nodata=np.nan, init_dest_nodata=True,
            resampling=getattr(rasterio.warp.Resampling, resampling))
    return out


# ------------------------------------------------------------------ footprint-overlap resampling
#: Two footprints overlap when they share more than a strip of this width [m]: footprints that
#: only touch along an edge (aligned grids) do not count (float noise is ~1e-9 m).
OVERLAP_EPS_M = 1e-6


def pixel_corners(transform, shape: tuple[int, int], src_crs, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """Map coordinates in ``grid``'s CRS of the ``(ny + 1, nx + 1)`` pixel corners of a raster.

    Exact affine map in the same CRS, pyproj otherwise; pixel edges are taken straight between
    their projected corners.

    Parameters
    ----------
    transform : affine.Affine
        The raster's affine transform in ``src_crs``.
    shape : tuple of int
        The raster's shape ``(ny, nx)``.
    src_crs : pyproj.CRS, str or int
        The raster's CRS.
    grid : Grid
        The grid whose CRS the corners are mapped to.

    Returns
    -------
    X, Y : numpy.ndarray
        float64, shape ``(ny + 1, nx + 1)``: corner map coordinates [m] in ``grid``'s CRS.
    """
    sy, sx = shape
    jj, ii = np.meshgrid(np.arange(sx + 1, dtype=np.float64), np.arange(sy + 1, dtype=np.float64))
    t = transform
    X = t.a * jj + t.b * ii + t.c
    Y = t.d * jj + t.e * ii + t.f
    if CRS.from_user_input(src_crs) != grid.crs:
        tr = Transformer.from_crs(CRS.from_user_input(src_crs), grid.crs, always_xy=True)
        X, Y = tr.transform(X, Y)
        X, Y = np.asarray(X, np.float64), np.asarray(Y, np.float64)
    return np.ascontiguousarray(X), np.ascontiguousarray(Y)


def footprint_resample(values: np.ndarray, transform, src_crs, grid: Grid, how: str = "max") -> np.ndarray:
    """Resample a raster to ``grid`` by the max or min over the footprint of every target cell.

    Each source pixel whose footprint overlaps the target cell's footprint (by more than
    :data:`OVERLAP_EPS_M`) counts, whatever the two resolutions, alignments and CRSs.
    Conservative for obstacles (``max``: no point of the cell is higher than its value) and
    for grounds under a ceiling (``min``).

    Parameters
    ----------
    values : numpy.ndarray
        Source raster, shape ``(sy, sx)``, NaN at nodata.
    transform : affine.Affine
        The source raster's affine transform in ``src_crs``.
    src_crs : pyproj.CRS, str or int
        The source raster's CRS.
    grid : Grid
        Target grid.
    how : {"max", "min"}, default "max"
        Reduction over the overlapping pixels.

    Returns
    -------
    numpy.ndarray
        float64, shape ``grid.shape`` ``(ny, nx)``: NaN where a cell overlaps a NaN pixel or no
        pixel at all (a cell only partly over the raster takes the part it overlaps: pad the
        raster with NaN, as :func:`read_window` does, to have such cells NaN).

    Raises
    ------
    InputError
        When ``how`` is neither ``"max"`` nor ``"min"``.
    """
    from skyroute.stages.grid_kernels import box_kernel, footprint_kernel

    if how not in ("max", "min"):
        raise InputError(f"footprint resampling {how!r} must be 'max' or 'min'")
    v = np.ascontiguousarray(values, dtype=np.float64)
    out = np.full(grid.shape, -np.inf if how == "max" else np.inf)
    nan_hit = np.zeros(grid.shape, dtype=np.bool_)
    t = transform
    if t.b == 0 and t.d == 0 and t.a > 0 and t.e < 0 and CRS.from_user_input(src_crs) == grid.crs:
        box_kernel(v, t.c, t.f, t.a, -t.e, grid.x0, grid.y1, grid.resolution_m, OVERLAP_EPS_M, how == "max",
                   out, nan_hit)
    else:
        if t.b == 0 and t.d == 0 and t.a > 0 and t.e < 0:   # crop to the pixels that can reach the grid
            from rasterio.warp import transform_bounds

            bx0, by0, bx1, by1 = transform_bounds(grid.crs, CRS.from_user_input(src_crs), *grid.bounds, densify_pts=21)
            j0 = max(int(np.floor((bx0 - t.c) / t.a)) - 2, 0)
            j1 = min(int(np.ceil((bx1 - t.c) / t.a)) + 2, v.shape[1])
            i0 = max(int(np.floor((t.f - by1) / -t.e)) - 2, 0)
            i1 = min(int(np.ceil((t.f - by0) / -t.e)) + 2, v.shape[0])
            if i1 <= i0 or j1 <= j0:
                return np.full(grid.shape, np.nan)
            v = np.ascontiguousarray(v[i0:i1, j0:j1])
            transform = t * Affine.translation(j0, i0)
        cx, cy = pixel_corners(transform, v.shape, src_crs, grid)
        footprint_kernel(cx, cy, v, grid.x0, grid.y1, grid.resolution_m, grid.ny, grid.nx, how == "max",
                         OVERLAP_EPS_M, out, nan_hit)
    out[nan_hit | ~np.isfinite(out)] = np.nan
    return out


@dataclass(frozen=True)
class SourceWindow:
    """Band 1 of a raster (one file, a VRT or a list of tiles) read over a window.

    Attributes
    ----------
    values : numpy.ndarray
        float64, shape ``(h, w)``, NaN at nodata, in the raster's units.
    inside : numpy.ndarray of bool
        Shape ``(h, w)``: pixel lies within the data's extent (a tile's bounds).
    transform : affine.Affine
        Affine transform of the window in ``crs``.
    crs : pyproj.CRS
        The raster's CRS.
    full : bool
        The window holds the whole extent (no hole can reach beyond it).
    """

    values: np.ndarray
    inside: np.ndarray
    transform: Affine
    crs: CRS
    full: bool  # the window holds the whole extent (no hole can reach beyond it)


#: Memory a raster read takes per window pixel [bytes]: the float64 values and the ``inside``
#: mask of the window, a tile's block while it is read (masked, converted), the NoData labels
#: (int32 and int64) and one filled float64 copy.
READ_BYTES_PER_PX = 48

#: Linear units a band's ``units`` metadata may declare -> metres per unit.
_UNIT_M = {
    "m": 1.0, "metre": 1.0, "meter": 1.0, "metres": 1.0, "meters": 1.0,
    "cm": 0.01, "centimetre": 0.01, "centimeter": 0.01, "centimetres": 0.01, "centimeters": 0.01,
    "mm": 0.001, "millimetre": 0.001, "millimeter": 0.001, "millimetres": 0.001, "millimeters": 0.001,
    "ft": 0.3048, "foot": 0.3048, "feet": 0.3048, "international foot": 0.3048, "international feet": 0.3048,
    "us survey foot": 1200.0 / 3937.0, "us survey feet": 1200.0 / 3937.0, "ftus": 1200.0 / 3937.0,
    "us-ft": 1200.0 / 3937.0, "us foot": 1200.0 / 3937.0, "survey foot": 1200.0 / 3937.0,
}


@dataclass(frozen=True)
class RasterHeader:
    """What a height raster's header says, checked by :func:`raster_header` (nothing read).

    Attributes
    ----------
    path : pathlib.Path
        The file.
    width, height : int
        Size [px].
    transform : affine.Affine
        North-up geotransform (of a bottom-up raster: the flipped one; ``flipped`` is True).
    crs : pyproj.CRS
        The raster's CRS (a compound CRS keeps its vertical part).
    flipped : bool
        Stored bottom-up (positive pixel height): rows are read in reverse.
    z_scale : float
        Metres per stored value [m]: the band's scale times its vertical unit.
    z_offset : float
        Added after scaling [m] (the band's offset in metres).
    z_unit : str
        The declared vertical unit and where it comes from, for messages.
    dtype : str
        Band 1's data type.
    nodata : float or None
        Band 1's NoData value.
    driver : str
        GDAL driver.
    """

    path: object
    width: int
    height: int
    transform: Affine
    crs: CRS
    flipped: bool
    z_scale: float
    z_offset: float
    z_unit: str
    dtype: str
    nodata: float | None
    driver: str

    @property
    def res(self) -> tuple[float, float]:
        """(pixel width, pixel height) [map units], both positive."""
        return abs(self.transform.a), abs(self.transform.e)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(left, bottom, right, top) [map units]."""
        t = self.transform
        return t.c, t.f + t.e * self.height, t.c + t.a * self.width, t.f


def _vertical_unit(crs: CRS) -> tuple[float, str] | None:
    """(metres per unit, unit name) of the vertical axis of ``crs`` (a compound CRS's vertical
    part, or the third axis of a 3-D CRS), None when it has none; factor 0 for a unit PROJ
    cannot convert."""
    subs = crs.sub_crs_list if crs.is_compound else [crs]
    for c in subs:
        for ax in c.axis_info:
            if ax.direction.lower() in ("up", "down") or "height" in ax.name.lower():
                f = float(ax.unit_conversion_factor or 0.0)
                return (f if np.isfinite(f) and f > 0 else 0.0), str(ax.unit_name)
    return None


def raster_read_error(what: str, p, exc: BaseException) -> DataError:
    """The :class:`DataError` of a raster GDAL cannot open or read (truncated, a corrupt tile).

    Parameters
    ----------
    what : str
        Names the layer ("surface DSM", "terrain DEM").
    p : str or pathlib.Path
        The file.
    exc : BaseException
        rasterio's error (its cause holds GDAL's message).

    Returns
    -------
    DataError
        Naming the file, GDAL's reason and the fix (re-download, gdalinfo -checksum, gdal_translate).
    """
    why = str(exc)
    cause = exc.__cause__ or exc.__context__
    if cause is not None and str(cause) and str(cause) not in why:
        why = f"{why} ({cause})" if "previous exception" not in why else str(cause)
    return DataError(f"cannot read {what} raster {p}: it is truncated or corrupt ({why.strip()}); re-download it, "
                     f"or check it with `gdalinfo -checksum {p}` and rewrite a readable copy with gdal_translate")


def raster_header(src, path, what: str) -> RasterHeader:
    """The checked header of band 1 of an open rasterio dataset (nothing is read).

    A raster georeferenced by ground control points (GCPs) or RPCs only, without CRS, rotated or
    with columns running west, is refused; a bottom-up raster (positive pixel height) is read
    flipped; the vertical unit is the CRS's vertical axis (a compound CRS such as
    ``EPSG:32611+6360``, US survey feet) or the band's ``units`` metadata, converted to metres
    together with the band's scale and offset.

    Parameters
    ----------
    src : rasterio.io.DatasetReader
        The open raster.
    path : str or pathlib.Path
        Its file (named in messages).
    what : str
        Names the layer in messages ("surface DSM", "terrain DEM").

    Returns
    -------
    RasterHeader

    Raises
    ------
    DataError
        GCP / RPC-only georeferencing, a rotated or east-west flipped raster, a vertical unit
        that cannot be converted to metres, a CRS and a band unit that disagree.
    CRSError
        When the raster has no CRS.
    """
    t = src.transform
    gcps, _ = src.gcps
    if (gcps or getattr(src, "rpcs", None)) and t.is_identity:
        how = f"{len(gcps)} ground control points (GCPs)" if gcps else "rational polynomial coefficients (RPCs)"
        raise DataError(f"{what} raster {path} is georeferenced by {how}, not by a geotransform: warp it onto a "
                        f"map grid first (gdalwarp -t_srs EPSG:<code> {path} warped.tif) and give the warped file")
    if src.crs is None:
        raise CRSError(f"{what} raster {path} has no CRS; assign one with gdal_edit.py -a_srs EPSG:...")
    if t.b != 0 or t.d != 0:
        raise DataError(f"{what} raster {path} is rotated (geotransform terms {t.b:g}, {t.d:g} are not 0): warp it "
                        "north-up first (gdalwarp)")
    if t.a <= 0 or t.e == 0:
        raise DataError(f"{what} raster {path} has a pixel width of {t.a:g} (columns must run west to east): "
                        "warp it north-up first (gdalwarp)")
    flipped = t.e > 0
    if flipped:
        t = Affine(t.a, 0.0, t.c, 0.0, -t.e, t.f + t.e * src.height)
    crs = CRS.from_user_input(src.crs)
    vert = _vertical_unit(crs)
    band = str(src.units[0] or "").strip() if src.units else ""
    band_f = _UNIT_M.get(band.lower()) if band else None
    if vert is not None and vert[0] == 0.0:
        raise DataError(f"{what} raster {path}: its CRS's vertical unit {vert[1]!r} cannot be converted to metres; "
                        "convert the heights to metres (gdal_translate / gdalwarp with a vertical CRS in metres)")
    if band and band_f is None:
        raise DataError(f"{what} raster {path}: its band unit is {band!r}, not a length skyroute can convert to "
                        "metres (m, cm, ft, US survey foot); convert the heights to metres, or correct the unit "
                        "(gdal_edit.py -units m) if they are metres")
    if vert is not None and band_f is not None and not np.isclose(vert[0], band_f, rtol=1e-6):
        raise DataError(f"{what} raster {path}: its CRS's vertical unit is {vert[1]!r} but its band unit is "
                        f"{band!r}; correct one of them (gdal_edit.py -a_srs / -units) so the heights' unit is known")
    factor, unit = ((vert[0], f"{vert[1]} (the CRS's vertical axis)") if vert is not None else
                    (band_f, f"{band} (the band's unit)") if band_f is not None else (1.0, "metre (none declared)"))
    scale = float(src.scales[0]) if src.scales and src.scales[0] is not None else 1.0
    offset = float(src.offsets[0]) if src.offsets and src.offsets[0] is not None else 0.0
    if not (np.isfinite(scale) and np.isfinite(offset)) or scale == 0:
        raise DataError(f"{what} raster {path}: band scale {scale:g} / offset {offset:g} make no heights; fix them "
                        "(gdal_edit.py -scale / -offset)")
    if scale != 1.0 or offset != 0.0:
        unit += f", stored values x {scale:g} + {offset:g} (band scale / offset)"
    return RasterHeader(path, int(src.width), int(src.height), t, crs, flipped, scale * factor, offset * factor,
                        unit, str(src.dtypes[0]), src.nodata, str(src.driver))


def _open_all(paths, what: str):
    """Open every file (a regular file; GDAL's errors as :class:`DataError`) -> (datasets, headers)."""
    import rasterio

    from skyroute.stages.base import file_problem

    srcs, heads = [], []
    try:
        for p in paths:
            why = file_problem(p, f"{what} raster")
            if why is not None:
                raise DataError(why)
            try:
                srcs.append(rasterio.open(p))
            except rasterio.errors.RasterioIOError as exc:
                raise raster_read_error(what, p, exc) from exc
            heads.append(raster_header(srcs[-1], p, what))
    except BaseException:
        for s in srcs:
            s.close()
        raise
    return srcs, heads


def raster_headers(path, what: str) -> list[RasterHeader]:
    """The checked headers (:func:`raster_header`) of a raster, a VRT or a list of tiles; the
    files are closed again, no pixel is read.

    Parameters
    ----------
    path : str, pathlib.Path or list of them
        The raster (as :func:`read_window` takes it).
    what : str
        Names the layer in messages.

    Returns
    -------
    list of RasterHeader
        One per file.

    Raises
    ------
    DataError
        As :func:`raster_header`, and for a file that is missing, not a regular file (a folder, a
        FIFO, a device) or that GDAL cannot open (truncated, corrupt).
    CRSError
        When the raster has no CRS.
    """
    from pathlib import Path

    paths = [Path(p) for p in (path if isinstance(path, (list, tuple)) else [path])]
    if not paths:
        raise DataError(f"{what}: no raster file given")
    srcs, heads = _open_all(paths, what)
    for s in srcs:
        s.close()
    return heads


def check_read_bytes(shape: tuple[int, int], what: str, path, *, limit_bytes: float | None = None,
                     growing: bool = False) -> float:
    """The memory [bytes] reading a window of ``shape`` takes (:data:`READ_BYTES_PER_PX`), checked
    against the limit before anything is allocated.

    Parameters
    ----------
    shape : tuple of int
        (height, width) of the window [px].
    what : str
        Names the layer in messages.
    path : str or pathlib.Path
        The raster (named in messages).
    limit_bytes : float, optional
        The limit [bytes]; default the command's ``--max-memory``
        (:func:`~skyroute.stages.base.memory_limit_bytes`).
    growing : bool, default False
        The window grows to reach the rims of NoData regions (:func:`read_window_holes`): said
        in the message, with its own fix.

    Returns
    -------
    float
        The estimate [bytes].

    Raises
    ------
    InputError
        Naming the window, the estimate, the limit and the fixes when it exceeds the limit.
    """
    from skyroute.stages.base import memory_limit_bytes

    limit = memory_limit_bytes() if limit_bytes is None else float(limit_bytes)
    need = float(shape[0]) * float(shape[1]) * READ_BYTES_PER_PX
    if need <= limit:
        return need
    gib = lambda n: f"{n / (1 << 30):,.1f} GiB" if n >= 1 << 30 else f"{n / (1 << 20):,.0f} MiB"  # noqa: E731
    why, fix = (("to know the whole rim of its NoData regions, which reach beyond the AOI,",
                 "clip the raster to the AOI (gdal_translate -projwin) so they end at its edge, or fill its NoData")
                if growing else ("over the AOI", "shrink aoi.bounds, give a coarser raster (gdalwarp -tr) or clip it "
                                 "to the AOI (gdal_translate -projwin)"))
    raise InputError(f"{what} {path}: reading a window of {shape[1]:,} x {shape[0]:,} px {why} needs about "
                     f"{gib(need)} of memory, more than --max-memory ({gib(limit)}): {fix}, or raise --max-memory")


def window_box(heads: list[RasterHeader], b, margin_px: int) -> tuple[int, int, int, int, bool]:
    """The window :func:`read_window` reads: on the pixel lattice of the first tile, ``margin_px``
    beyond the box ``b``, never more than one pixel beyond the whole extent.

    Parameters
    ----------
    heads : list of RasterHeader
        The tiles (:func:`raster_headers`).
    b : tuple of float
        (left, bottom, right, top) to cover, in the raster's CRS.
    margin_px : int
        Pixels beyond ``b``.

    Returns
    -------
    tuple
        (first column, first row, height, width [px] in the first tile's lattice, whether the
        window holds the whole extent).
    """
    t0 = heads[0].transform
    rx, ry = heads[0].res
    left = min(hd.bounds[0] for hd in heads)
    bottom = min(hd.bounds[1] for hd in heads)
    right = max(hd.bounds[2] for hd in heads)
    top = max(hd.bounds[3] for hd in heads)
    c0 = int(np.floor((b[0] - t0.c) / rx)) - margin_px
    c1 = int(np.ceil((b[2] - t0.c) / rx)) + margin_px
    r0 = int(np.floor((t0.f - b[3]) / ry)) - margin_px
    r1 = int(np.ceil((t0.f - b[1]) / ry)) + margin_px
    e0, e1 = int(np.floor((left - t0.c) / rx)) - 1, int(np.ceil((right - t0.c) / rx)) + 1
    f0, f1 = int(np.floor((t0.f - top) / ry)) - 1, int(np.ceil((t0.f - bottom) / ry)) + 1
    c0, c1, r0, r1 = max(c0, e0), min(c1, e1), max(r0, f0), min(r1, f1)
    full = c0 <= e0 and c1 >= e1 and r0 <= f0 and r1 >= f1
    return c0, r0, max(r1 - r0, 1), max(c1 - c0, 1), full


def read_window(path, grid: Grid, *, what: str, margin_px: int = 32, require_overlap: bool = True,
                _growing: bool = False) -> SourceWindow:
    """Read band 1 of ``path`` over the window that covers ``grid`` plus ``margin_px`` pixels.

    At the native resolution, without resampling, heights converted to metres from the declared
    vertical unit, scale and offset (:func:`raster_header`); a bottom-up raster is read flipped.
    Nodata -> NaN; pixels outside every tile are NaN with ``inside`` False.  Overlapping tiles:
    the highest value wins.  The window's memory (:func:`check_read_bytes`) is checked against
    ``--max-memory`` before anything is read.

    Parameters
    ----------
    path : str, pathlib.Path or list of them
        A GeoTIFF, a VRT, or a list of tiles sharing CRS, pixel size and pixel lattice; north-up.
    grid : Grid
        The grid the window must cover.
    what : str
        Names the layer in error messages.
    margin_px : int, default 32
        Pixels read beyond the grid's footprint (never more than one pixel beyond the whole
        extent).
    require_overlap : bool, default True
        A raster that does not intersect the grid is a :class:`DataError`.
    _growing : bool, default False
        Internal (:func:`read_window_holes`): the window grows over NoData regions (said when
        it passes ``--max-memory``).

    Returns
    -------
    SourceWindow

    Raises
    ------
    DataError
        When no file is given, a file is missing, not a regular file, unreadable, truncated or
        corrupt, the raster is georeferenced by GCPs only or rotated, its vertical unit cannot
        be converted, the tiles differ in CRS, pixel size or lattice, or (``require_overlap``)
        the raster does not intersect the grid.
    CRSError
        When the raster has no CRS.
    InputError
        When the window needs more memory than ``--max-memory``.
    """
    from pathlib import Path

    import rasterio.errors
    import rasterio.warp
    import rasterio.windows

    paths = [Path(p) for p in (path if isinstance(path, (list, tuple)) else [path])]
    if not paths:
        raise DataError(f"{what}: no raster file given")
    srcs, heads = _open_all(paths, what)
    try:
        crs0 = srcs[0].crs
        h0 = heads[0]
        t0 = h0.transform
        for hd, p in zip(heads[1:], paths[1:], strict=True):
            if hd.crs != h0.crs or not np.allclose(hd.res, h0.res):
                raise DataError(f"{what} tile {p} differs from {paths[0]} in CRS, pixel size or orientation; "
                                "give tiles of one raster (or build a VRT with gdalbuildvrt)")
        rx, ry = h0.res
        left = min(hd.bounds[0] for hd in heads)
        bottom = min(hd.bounds[1] for hd in heads)
        right = max(hd.bounds[2] for hd in heads)
        top = max(hd.bounds[3] for hd in heads)
        b = rasterio.warp.transform_bounds(grid.crs, crs0, *grid.bounds, densify_pts=21)
        if require_overlap and (b[0] >= right or b[2] <= left or b[1] >= top or b[3] <= bottom):
            raise DataError(f"the AOI {tuple(round(v) for v in grid.bounds)} does not intersect {what} "
                            f"{paths[0] if len(paths) == 1 else f'{len(paths)} tiles'} (bounds "
                            f"{tuple(round(v) for v in (left, bottom, right, top))} in {crs0}); fix aoi or the {what} path")
        c0, r0, h, w, full = window_box(heads, b, margin_px)
        check_read_bytes((h, w), what, paths[0] if len(paths) == 1 else f"({len(paths)} tiles)", growing=_growing)
        wt = Affine(rx, 0.0, t0.c + c0 * rx, 0.0, -ry, t0.f - r0 * ry)
        values = np.full((h, w), np.nan)
        inside = np.zeros((h, w), dtype=bool)
        for s, hd, p in zip(srcs, heads, paths, strict=True):
            so = (hd.transform.c - wt.c) / rx
            sr = (wt.f - hd.transform.f) / ry
            if abs(so - round(so)) > 1e-6 or abs(sr - round(sr)) > 1e-6:
                raise DataError(f"{what} tiles are not on one pixel lattice; build a VRT with gdalbuildvrt")
            so, sr = int(round(so)), int(round(sr))
            # intersection of the tile with the window, in window pixels
            a0, a1 = max(sr, 0), min(sr + hd.height, h)
            b0, b1 = max(so, 0), min(so + hd.width, w)
            if a1 <= a0 or b1 <= b0:
                continue
            row0 = hd.height - (a1 - sr) if hd.flipped else a0 - sr   # stored row of the block's first row
            win = rasterio.windows.Window(b0 - so, row0, b1 - b0, a1 - a0)
            try:
                a = s.read(1, window=win, masked=True)
            except rasterio.errors.RasterioIOError as exc:
                raise raster_read_error(what, p, exc) from exc
            if hd.flipped:
                a = a[::-1]
            block = np.where(np.ma.getmaskarray(a), np.nan, np.ma.getdata(a).astype(np.float64))
            block[~np.isfinite(block)] = np.nan
            if hd.z_scale != 1.0 or hd.z_offset != 0.0:
                block = block * hd.z_scale + hd.z_offset
            cur = values[a0:a1, b0:b1]
            values[a0:a1, b0:b1] = np.fmax(cur, block)
            inside[a0:a1, b0:b1] = True
    finally:
        for s in srcs:
            s.close()
    return SourceWindow(values, inside, wt, h0.crs, full)


NODATA_POLICIES = ("fill-max", "fill-nearest", "error")


@dataclass(frozen=True)
class Holes:
    """NoData regions of a :class:`SourceWindow` (pixels inside the data's extent without a value).

    Attributes
    ----------
    labels : numpy.ndarray of int
        Shape of the window ``(h, w)``: region label per pixel (0 = data).
    rim_max, rim_min : numpy.ndarray of float
        Per label ``(n + 1,)``: the highest / lowest valid 8-neighbour within the extent [m];
        -inf / inf for a region without any valid rim.
    outside : numpy.ndarray of bool
        Per label: the region touches the extent's edge (a pixel outside the extent, e.g. a
        lidar tile's border).
    at_border : numpy.ndarray of bool
        Per label: the region touches the border of a partial window (read more to know its
        whole rim).
    """

    labels: np.ndarray
    rim_max: np.ndarray
    rim_min: np.ndarray
    outside: np.ndarray
    at_border: np.ndarray

    @property
    def fillable(self) -> np.ndarray:
        """Per label: the region has a valid rim, so it can be filled (label 0 excluded); ``(n + 1,)`` bool.
        """
        ok = np.isfinite(self.rim_max)
        ok[0] = False
        return ok

    @property
    def interior(self) -> np.ndarray:
        """Pixels of the NoData regions that are filled.

        Every region with a valid rim, whether it touches the extent's edge or not; bool, shape of
        the window.
        """
        return self.fillable[self.labels]

    @property
    def n_interior(self) -> int:
        """Number of NoData regions filled."""
        return int(self.fillable.sum())

    @property
    def n_edge(self) -> int:
        """Number of filled NoData regions that touch the extent's edge."""
        return int((self.fillable & self.outside).sum())


def find_holes(win: SourceWindow) -> Holes:
    """Connected (8-neighbour) NoData regions inside the extent of ``win`` and their rims.

    A region touching the extent's edge is still inside the extent: it is filled from its rim
    within the extent (a lidar tile's holes over water or at its border).

    Parameters
    ----------
    win : SourceWindow
        The window read by :func:`read_window`.

    Returns
    -------
    Holes
        The labelled regions (see :class:`Holes`).
    """
    from scipy import ndimage

    nan = np.isnan(win.values) & win.inside
    labels, n = ndimage.label(nan, structure=np.ones((3, 3), bool))
    rim_max = np.full(n + 1, -np.inf)
    rim_min = np.full(n + 1, np.inf)
    outside = np.zeros(n + 1, np.bool_)
    at_border = np.zeros(n + 1, np.bool_)
    if n:
        from skyroute.stages.grid_kernels import rim_kernel

        rim_kernel(labels.astype(np.int64), win.values, win.inside, win.full, rim_max, rim_min, outside, at_border)
    return Holes(labels, rim_max, rim_min, outside, at_border)


def read_window_holes(path, grid: Grid, *, what: str, margin_px: int = 32) -> tuple[SourceWindow, Holes]:
    """:func:`read_window` grown until each NoData region's rim is known whole; and its :func:`find_holes`.

    The window starts at least ``margin_px`` beyond the grid and grows (x4) until no NoData
    region reaches the window's border inside the extent.

    Parameters
    ----------
    path : str, pathlib.Path or list of them
        As in :func:`read_window`.
    grid : Grid
        The grid the window must cover.
    what : str
        Names the layer in error messages.
    margin_px : int, default 32
        Initial margin [px] (at least 1).

    Returns
    -------
    win : SourceWindow
    holes : Holes

    Raises
    ------
    DataError, CRSError
        As :func:`read_window`.
    """
    margin = max(int(margin_px), 1)
    grown = False
    while True:
        win = read_window(path, grid, what=what, margin_px=margin, _growing=grown)
        check_heights(win.values, path, what)
        holes = find_holes(win)
        if win.full or not holes.at_border[1:].any():
            return win, holes
        margin *= 4
        grown = True


#: Heights a DSM or DEM may hold [m]: from below the Dead Sea shore to above Everest's summit.
#: Anything outside is not a height in metres (an undeclared NoData value such as 1e30 or
#: -3.4e38, a raster in centimetres or feet ...).
HEIGHT_RANGE_M = (-1000.0, 10000.0)


def check_heights(values: np.ndarray, path, what: str) -> None:
    """Raise :class:`DataError` when finite ``values`` of a height raster fall outside
    :data:`HEIGHT_RANGE_M`.

    Parameters
    ----------
    values : numpy.ndarray
        The raster's values [m] (NaN: NoData).
    path : str, pathlib.Path or list of them
        The raster (named in the message).
    what : str
        Names the layer ("surface DSM", "terrain DEM").

    Raises
    ------
    DataError
        Naming the extreme value, how many pixels hold values outside the range and the fix.
    """
    v = np.asarray(values)
    fin = v[np.isfinite(v)]
    if fin.size == 0:
        return
    lo, hi = float(fin.min()), float(fin.max())
    if lo >= HEIGHT_RANGE_M[0] and hi <= HEIGHT_RANGE_M[1]:
        return
    bad = int(np.count_nonzero((fin < HEIGHT_RANGE_M[0]) | (fin > HEIGHT_RANGE_M[1])))
    worst = hi if hi > HEIGHT_RANGE_M[1] else lo
    raise DataError(f"{what} {path}: {bad} pixel(s) hold {worst:g}, not a height in metres (heights lie within "
                    f"{HEIGHT_RANGE_M[0]:g} to {HEIGHT_RANGE_M[1]:g} m): declare the raster's NoData value "
                    "(gdal_edit.py -a_nodata VALUE FILE) or give heights in metres")


def fill_holes(win: SourceWindow, holes: Holes, how: str) -> np.ndarray:
    """``win.values`` with every NoData region inside the extent filled (also those touching its edge).

    Pixels outside the extent (and regions without any valid rim) stay NaN.

    Parameters
    ----------
    win : SourceWindow
        The window.
    holes : Holes
        Its NoData regions (:func:`find_holes`).
    how : {"fill-max", "fill-min", "fill-nearest"}
        ``"fill-max"``: the highest valid height on its rim within the extent; ``"fill-min"``:
        the lowest (for grounds under a ceiling); ``"fill-nearest"``: each pixel the nearest
        valid pixel.

    Returns
    -------
    numpy.ndarray
        A filled copy of ``win.values``, shape ``(h, w)``.

    Raises
    ------
    InputError
        When ``how`` is not a fill policy.
    """
    v = win.values.copy()
    interior = holes.interior
    if not interior.any():
        return v
    if how == "fill-max":
        v[interior] = holes.rim_max[holes.labels[interior]]
    elif how == "fill-min":
        v[interior] = holes.rim_min[holes.labels[interior]]
    elif how == "fill-nearest":
        from scipy.ndimage import distance_transform_edt

        _, (ri, ci) = distance_transform_edt(np.isnan(v), return_indices=True)
        v[interior] = v[ri, ci][interior]
    else:
        raise InputError(f"nodata policy {how!r} must be one of {NODATA_POLICIES}")
    return v


def _inside_box(win: SourceWindow, grid: Grid) -> tuple[float, float, float, float] | None:
    """Bounds (grid CRS) of the AOI cells over the raster's extent, snapped inward, when those
    cells form the whole rectangle (else None)."""
    out = np.isnan(footprint_resample(np.where(win.inside, 0.0, np.nan), win.transform, win.crs, grid))
    rows = np.flatnonzero((~out).any(axis=1))
    cols = np.flatnonzero((~out).any(axis=0))
    if not rows.size or not cols.size or out[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1].any():
        return None
    r = grid.resolution_m
    return (grid.x0 + cols[0] * r, grid.y1 - (rows[-1] + 1) * r, grid.x0 + (cols[-1] + 1) * r, grid.y1 - rows[0] * r)


def coverage_problem(win: SourceWindow, holes: Holes, grid: Grid, *, what: str, key: str,
                     holes_allowed: bool = True) -> str | None:
    """The message for AOI cells the raster cannot give (None if every cell is covered).

    Cells outside the data's extent are refused with the ``aoi.bounds`` that would fit (the AOI
    within the raster, in the grid's CRS); cells over NoData regions inside the extent are
    refused only when ``holes_allowed`` is False (``nodata: error``).

    Parameters
    ----------
    win : SourceWindow
        The window read over the grid.
    holes : Holes
        Its NoData regions.
    grid : Grid
        The AOI grid.
    what : str
        Names the layer in the message.
    key : str
        The settings key the message starts with.
    holes_allowed : bool, default True
        NoData regions inside the extent are acceptable (they are filled).

    Returns
    -------
    str or None
        One error message saying what is wrong and how to fix it, or None.
    """
    outside_px = np.isnan(win.values) & ~holes.interior
    out_cells = np.isnan(footprint_resample(np.where(outside_px, np.nan, 0.0), win.transform, win.crs, grid))
    if out_cells.any():
        box = _inside_box(win, grid)
        epsg = grid.crs.to_epsg()
        crs = f"EPSG:{epsg}" if epsg else "the grid's CRS"
        fix = (f"set aoi.bounds to [{box[0]:.0f}, {box[1]:.0f}, {box[2]:.0f}, {box[3]:.0f}] (with aoi.crs {crs}) "
               "or add tiles" if box is not None else f"shrink aoi.bounds to the {what} or add tiles")
        n_out = int(out_cells.sum())
        no_rim = int((~np.isfinite(holes.rim_max[1:])).sum())
        why = (f"{n_out} cells are outside the raster's extent" if not no_rim else
               f"{n_out} cells are outside the raster's extent or in NoData regions without any valid pixel around them")
        return f"{key}: covers only {100 * (1 - out_cells.mean()):.1f} % of the AOI: {why}; {fix}"
    if not holes_allowed:
        hole_cells = np.isnan(footprint_resample(np.where(holes.interior, np.nan, 0.0), win.transform, win.crs, grid))
        if hole_cells.any():
            n, n_edge = regions_in_aoi(win, holes, grid)
            return (f"{key}: {n} NoData region(s) inside the raster's extent ({n_edge} touching "
                    f"its edge) cover {100 * hole_cells.mean():.2f} % of the AOI ({int(hole_cells.sum())} cells) and "
                    f"{key}.nodata is 'error'; set {key}.nodata to fill-max (each region the highest height on its "
                    "rim) or fill-nearest (each pixel the nearest valid one)")
    return None


def regions_in_aoi(win: SourceWindow, holes: Holes, grid: Grid) -> tuple[int, int]:
    """(filled NoData regions with a pixel under the AOI, how many of them touch the extent's edge).

    Parameters
    ----------
    win : SourceWindow
        The window.
    holes : Holes
        Its NoData regions.
    grid : Grid
        The AOI grid.

    Returns
    -------
    n_regions : int
        Filled NoData regions with a pixel under the AOI's bounding box.
    n_edge : int
        How many of them touch the extent's edge.
    """
    from rasterio.warp import transform_bounds

    t = win.transform
    bx0, by0, bx1, by1 = transform_bounds(grid.crs, win.crs, *grid.bounds, densify_pts=21)
    j0, j1 = max(int(np.floor((bx0 - t.c) / t.a)), 0), int(np.ceil((bx1 - t.c) / t.a))
    i0, i1 = max(int(np.floor((t.f - by1) / -t.e)), 0), int(np.ceil((t.f - by0) / -t.e))
    lab = np.unique(holes.labels[i0:i1, j0:j1])
    lab = lab[(lab > 0) & holes.fillable[lab]]
    return int(lab.size), int(holes.outside[lab].sum())


def filled_share(win: SourceWindow, holes: Holes, grid: Grid) -> float:
    """Share [0..1] of the AOI cells that overlap a filled NoData pixel.

    Parameters
    ----------
    win : SourceWindow
        The window.
    holes : Holes
        Its NoData regions.
    grid : Grid
        The AOI grid.

    Returns
    -------
    float
        Share of the cells, 0..1.
    """
    if not holes.interior.any():
        return 0.0
    return float(np.isnan(footprint_resample(np.where(holes.interior, np.nan, 0.0), win.transform, win.crs,
                                             grid)).mean())


def ring_cells(xs: np.ndarray, ys: np.ndarray, offsets: np.ndarray, grid: Grid
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ring, row, col) of every cell whose centre lies inside a ring (even-odd rule).

    Rings are given flat: vertices ``xs[offsets[k]:offsets[k+1]]`` (map coordinates [m], not
    closed) form ring k.  A compiled scanline fill: millions of small polygons (CityJSON
    surfaces) in well under a second, where a Python loop over rasterio calls takes minutes.

    Parameters
    ----------
    xs, ys : numpy.ndarray
        Vertex map coordinates [m] in the grid's CRS, shape ``(n_vertices,)``.
    offsets : numpy.ndarray of int
        Shape ``(n_rings + 1,)``: ring k's vertices are ``offsets[k]:offsets[k+1]``.
    grid : Grid
        The grid whose cell centres are tested.

    Returns
    -------
    ring, row, col : numpy.ndarray of int64
        One entry per (ring, cell) pair, shape ``(n,)``; empty when ``offsets`` has fewer than
        two entries.
    """
    xs = np.ascontiguousarray(xs, np.float64)
    ys = np.ascontiguousarray(ys, np.float64)
    offsets = np.ascontiguousarray(offsets, np.int64)
    if offsets.size < 2:
        z = np.zeros(0, np.int64)
        return z, z, z
    dummy = np.zeros(0, np.int64)
    from skyroute.stages.grid_kernels import ring_spans_kernel

    n = ring_spans_kernel(xs, ys, offsets, grid.x0, grid.y1, grid.resolution_m, grid.ny, grid.nx, True,
                          dummy, dummy, dummy, dummy)
    ring, row, c0, c1 = (np.empty(n, np.int64) for _ in range(4))
    ring_spans_kernel(xs, ys, offsets, grid.x0, grid.y1, grid.resolution_m, grid.ny, grid.nx, False,
                      ring, row, c0, c1)
    width = c1 - c0 + 1
    rep = np.repeat(np.arange(n), width)
    col = c0[rep] + (np.arange(rep.size) - np.repeat(np.cumsum(width) - width, width))
    return ring[rep], row[rep], col
