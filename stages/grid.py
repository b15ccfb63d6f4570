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

import numba
import numpy as np
import rioxarray  # noqa: F401  (registers the .rio accessor)
import xarray as xr
from affine import Affine
from pyproj import CRS, Transformer

from skyroute.pipeline.errors import CRSError, DataError, InputError


def resolve_crs(crs: str | int | CRS) -> CRS:
    """A :class:`pyproj.CRS` from ``"EPSG:32635"``, ``32635``, WKT or PROJ text."""
    try:
        return CRS.from_user_input(crs)
    except Exception as exc:  # pyproj raises CRSError subclasses of several kinds
        raise CRSError(f"cannot resolve CRS {crs!r}: {exc}. Give an EPSG code such as 'EPSG:32635'") from exc


def utm_zone(lon_deg: float, lat_deg: float) -> int:
    """UTM zone number of (lon, lat) [deg], with the Norway (32V) and Svalbard (31X-37X) exceptions."""
    lon = (float(lon_deg) + 180.0) % 360.0 - 180.0
    zone = int((lon + 180.0) // 6.0) + 1
    if 56.0 <= lat_deg < 64.0 and 3.0 <= lon < 12.0:
        zone = 32
    elif 72.0 <= lat_deg < 84.0 and lon >= 0.0:
        for lo, hi, z in ((0.0, 9.0, 31), (9.0, 21.0, 33), (21.0, 33.0, 35), (33.0, 42.0, 37)):
            if lo <= lon < hi:
                zone = z
    return min(zone, 60)


def utm_crs_for(lon_deg: float, lat_deg: float) -> CRS:
    """The WGS 84 / UTM zone CRS (EPSG 326zz north, 327zz south) that contains (lon, lat) [deg]."""
    if not (-80.0 <= lat_deg <= 84.0):
        raise CRSError(f"latitude {lat_deg} deg is outside the UTM range -80..84; name a CRS in aoi.crs "
                       "(e.g. a polar stereographic EPSG:3413)")
    zone = utm_zone(lon_deg, lat_deg)
    return CRS.from_epsg((32600 if lat_deg >= 0 else 32700) + zone)


def _crs_text(crs: CRS) -> str:
    """``EPSG:nnnn`` when the CRS has an EPSG code, else its WKT (a canonical, hashable text)."""
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg is not None else crs.to_wkt()


@dataclass(frozen=True)
class Grid:
    """A north-up grid: ``nx`` x ``ny`` square cells of ``resolution_m`` [m] whose outer
    corner is (``x0``, ``y1``) (west, north edge) in ``crs``."""

    crs_wkt: str
    x0: float
    y1: float
    nx: int
    ny: int
    resolution_m: float

    @classmethod
    def from_bounds(cls, crs: CRS | str, xmin: float, ymin: float, xmax: float, ymax: float,
                    resolution_m: float) -> Grid:
        if not resolution_m > 0:
            raise InputError(f"resolution {resolution_m} m must be positive (e.g. 2.0)")
        if not (xmax > xmin and ymax > ymin):
            raise InputError(f"empty bounds ({xmin}, {ymin}, {xmax}, {ymax}): need xmin < xmax and ymin < ymax")
        crs = resolve_crs(crs)
        x0 = np.floor(xmin / resolution_m) * resolution_m
        y1 = np.ceil(ymax / resolution_m) * resolution_m
        nx = int(np.ceil((xmax - x0) / resolution_m - 1e-9))
        ny = int(np.ceil((y1 - ymin) / resolution_m - 1e-9))
        return cls(_crs_text(crs), float(x0), float(y1), nx, ny, float(resolution_m))

    @property
    def crs(self) -> CRS:
        return CRS.from_user_input(self.crs_wkt)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.ny, self.nx)

    @property
    def transform(self) -> Affine:
        return Affine(self.resolution_m, 0.0, self.x0, 0.0, -self.resolution_m, self.y1)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        r = self.resolution_m
        return (self.x0, self.y1 - self.ny * r, self.x0 + self.nx * r, self.y1)

    @property
    def x(self) -> np.ndarray:
        return self.x0 + (np.arange(self.nx) + 0.5) * self.resolution_m

    @property
    def y(self) -> np.ndarray:
        return self.y1 - (np.arange(self.ny) + 0.5) * self.resolution_m

    def coords(self) -> dict[str, xr.DataArray]:
        return {
            "y": xr.DataArray(self.y, dims="y", attrs={"units": "m", "standard_name": "projection_y_coordinate", "axis": "Y"}),
            "x": xr.DataArray(self.x, dims="x", attrs={"units": "m", "standard_name": "projection_x_coordinate", "axis": "X"}),
        }

    def dataarray(self, values: np.ndarray, name: str, **attrs) -> xr.DataArray:
        """Wrap a ``(ny, nx)`` array as a raster of this grid with CRS and attrs."""
        da = xr.DataArray(values, dims=("y", "x"), coords=self.coords(), name=name, attrs=attrs)
        return da.rio.write_crs(self.crs)

    def index_of(self, x: np.ndarray | float, y: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) of the cells containing map points (x, y) [m]; may fall outside the grid."""
        col = np.floor((np.asarray(x) - self.x0) / self.resolution_m).astype(np.int64)
        row = np.floor((self.y1 - np.asarray(y)) / self.resolution_m).astype(np.int64)
        return row, col

    def contains(self, x: float, y: float) -> bool:
        xmin, ymin, xmax, ymax = self.bounds
        return bool(xmin <= x <= xmax and ymin <= y <= ymax)

    def to_lonlat(self, x, y):
        """Map (x, y) [m] to WGS 84 (lon, lat) [deg]."""
        t = Transformer.from_crs(self.crs, 4326, always_xy=True)
        return t.transform(x, y)

    def from_lonlat(self, lon, lat):
        """WGS 84 (lon, lat) [deg] to map (x, y) [m]."""
        t = Transformer.from_crs(4326, self.crs, always_xy=True)
        return t.transform(lon, lat)

    @classmethod
    def from_dataarray(cls, da: xr.DataArray | xr.Dataset) -> Grid:
        """Recover the grid of a raster that follows the conventions above."""
        x = np.asarray(da["x"].values)
        y = np.asarray(da["y"].values)
        if x.size < 2 or y.size < 2:
            raise InputError("a raster needs at least 2 x 2 cells")
        r = float(x[1] - x[0])
        if not np.isclose(float(y[0] - y[1]), r) or r <= 0:
            raise InputError("raster must be north-up with square cells: x ascending, y descending, equal steps")
        crs = da.rio.crs
        if crs is None:
            raise CRSError("raster carries no CRS: write one with da.rio.write_crs('EPSG:...')")
        return cls(_crs_text(CRS.from_user_input(crs)), float(x[0] - r / 2), float(y[0] + r / 2),
                   int(x.size), int(y.size), r)


def warp_to_grid(path, grid: Grid, *, what: str, resampling: str = "bilinear",
                 require_overlap: bool = True) -> np.ndarray:
    """Band 1 of a GeoTIFF reprojected to ``grid`` (float64; NaN outside the raster and at its
    nodata).  ``what`` names the layer in error messages ("terrain", "risk GeoTIFF").
    ``require_overlap``: a raster that does not intersect the grid is a :class:`DataError`."""
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


@numba.njit(cache=True)
def _ring_spans_kernel(xs, ys, offsets, x0, y1, res, ny, nx, count_only, ring_out, row_out, c0_out, c1_out):  # pragma: no cover
    n_spans = 0
    cross = np.empty(max(int(np.max(offsets[1:] - offsets[:-1])), 1), np.float64)
    for p in range(offsets.size - 1):
        s, e = offsets[p], offsets[p + 1]
        n = e - s
        if n < 3:
            continue
        ymin, ymax = ys[s], ys[s]
        for k in range(s, e):
            ymin = min(ymin, ys[k])
            ymax = max(ymax, ys[k])
        r0 = max(int(np.ceil((y1 - ymax) / res - 0.5)), 0)
        r1 = min(int(np.floor((y1 - ymin) / res - 0.5)), ny - 1)
        for r in range(r0, r1 + 1):
            yc = y1 - (r + 0.5) * res
            m = 0
            for k in range(n):
                i = s + k
                j = s + (k + 1) % n
                if (ys[i] > yc) != (ys[j] > yc):
                    cross[m] = xs[i] + (yc - ys[i]) * (xs[j] - xs[i]) / (ys[j] - ys[i])
                    m += 1
            if m < 2:
                continue
            c = np.sort(cross[:m])
            for q in range(0, m - 1, 2):
                c0 = max(int(np.ceil((c[q] - x0) / res - 0.5)), 0)
                c1 = min(int(np.floor((c[q + 1] - x0) / res - 0.5)), nx - 1)
                if c1 < c0:
                    continue
                if not count_only:
                    ring_out[n_spans] = p
                    row_out[n_spans] = r
                    c0_out[n_spans] = c0
                    c1_out[n_spans] = c1
                n_spans += 1
    return n_spans


def ring_cells(xs: np.ndarray, ys: np.ndarray, offsets: np.ndarray, grid: Grid
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ring, row, col) of every cell whose centre lies inside a ring (even-odd rule).

    Rings are given flat: vertices ``xs[offsets[k]:offsets[k+1]]`` (map coordinates [m], not
    closed) form ring k.  A compiled scanline fill: millions of small polygons (CityJSON
    surfaces) in well under a second, where a Python loop over rasterio calls takes minutes.
    """
    xs = np.ascontiguousarray(xs, np.float64)
    ys = np.ascontiguousarray(ys, np.float64)
    offsets = np.ascontiguousarray(offsets, np.int64)
    if offsets.size < 2:
        z = np.zeros(0, np.int64)
        return z, z, z
    dummy = np.zeros(0, np.int64)
    n = _ring_spans_kernel(xs, ys, offsets, grid.x0, grid.y1, grid.resolution_m, grid.ny, grid.nx, True,
                           dummy, dummy, dummy, dummy)
    ring, row, c0, c1 = (np.empty(n, np.int64) for _ in range(4))
    _ring_spans_kernel(xs, ys, offsets, grid.x0, grid.y1, grid.resolution_m, grid.ny, grid.nx, False,
                       ring, row, c0, c1)
    width = c1 - c0 + 1
    rep = np.repeat(np.arange(n), width)
    col = c0[rep] + (np.arange(rep.size) - np.repeat(np.cumsum(width) - width, width))
    return ring[rep], row[rep], col
