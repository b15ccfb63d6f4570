"""The scenario grid's geometry: :class:`Grid` (a north-up raster in a projected CRS) and its CRS
helpers, importable without xarray or rioxarray (settings, cache keys and a warm run need the grid,
not the raster stack).  :mod:`skyroute.stages.grid` re-exports everything here and holds the
raster readers and resamplers; its docstring states the raster conventions.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from pyproj import CRS, Transformer

from skyroute.stages.base import CRSError, InputError

if TYPE_CHECKING:
    import xarray as xr
    from affine import Affine


def resolve_crs(crs: str | int | CRS) -> CRS:
    """A :class:`pyproj.CRS` from ``"EPSG:32635"``, ``32635``, WKT or PROJ text.

    Parameters
    ----------
    crs : str, int or pyproj.CRS
        Anything :meth:`pyproj.CRS.from_user_input` accepts: ``"EPSG:32635"``, an EPSG code,
        WKT or PROJ text, or a CRS.

    Returns
    -------
    pyproj.CRS
        The resolved CRS.

    Raises
    ------
    CRSError
        When pyproj cannot resolve ``crs`` (the message suggests an EPSG code).
    """
    try:
        return CRS.from_user_input(crs)
    except Exception as exc:  # pyproj raises CRSError subclasses of several kinds
        raise CRSError(f"cannot resolve CRS {crs!r}: {exc}. Give an EPSG code such as 'EPSG:32635'") from exc


def utm_zone(lon_deg: float, lat_deg: float) -> int:
    """UTM zone number of (lon, lat) [deg], with the Norway (32V) and Svalbard (31X-37X) exceptions.

    Parameters
    ----------
    lon_deg : float
        Longitude [deg]; any value, wrapped to [-180, 180).
    lat_deg : float
        Latitude [deg].

    Returns
    -------
    int
        Zone number, 1..60.
    """
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
    """The WGS 84 / UTM zone CRS (EPSG 326zz north, 327zz south) that contains (lon, lat) [deg].

    Parameters
    ----------
    lon_deg : float
        Longitude [deg].
    lat_deg : float
        Latitude [deg]; must lie in the UTM range -80..84.

    Returns
    -------
    pyproj.CRS
        The UTM CRS of the zone :func:`utm_zone` gives (northern zone for ``lat_deg >= 0``).

    Raises
    ------
    CRSError
        When ``lat_deg`` is outside -80..84 (name a CRS in ``aoi.crs`` instead, e.g. a polar
        stereographic EPSG:3413).
    """
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
    """A north-up grid: ``nx`` x ``ny`` square cells of ``resolution_m`` [m].

    Its outer corner is (``x0``, ``y1``) (west, north edge) in ``crs``.

    Parameters
    ----------
    crs_wkt : str
        The CRS as ``EPSG:nnnn`` when it has an EPSG code, else its WKT (a canonical, hashable
        text); :attr:`crs` gives the :class:`pyproj.CRS`.
    x0 : float
        Map x of the west edge [m].
    y1 : float
        Map y of the north edge [m].
    nx : int
        Number of columns (cells along x).
    ny : int
        Number of rows (cells along y); rasters of the grid have shape ``(ny, nx)``.
    resolution_m : float
        Cell side [m].

    See Also
    --------
    Grid.from_bounds, Grid.from_dataarray
    """

    crs_wkt: str
    x0: float
    y1: float
    nx: int
    ny: int
    resolution_m: float

    @classmethod
    def from_bounds(cls, crs: CRS | str, xmin: float, ymin: float, xmax: float, ymax: float,
                    resolution_m: float, *, inward: bool = False, key: str = "aoi.bounds") -> Grid:
        """The grid of cells on the lattice of multiples of ``resolution_m`` [m] that covers the bounds.

        With ``inward=False``: the cells touching the bounds (the grid may reach up to one cell
        beyond); with ``inward=True``: the cells that lie within them (the grid never extends past
        the bounds).

        Parameters
        ----------
        crs : pyproj.CRS or str
            CRS of the bounds and of the grid (see :func:`resolve_crs`).
        xmin, ymin, xmax, ymax : float
            Bounds in map coordinates [m]; need ``xmin < xmax`` and ``ymin < ymax``.
        resolution_m : float
            Cell side [m], positive.
        inward : bool, default False
            Snap the bounds inward (True) or outward (False) to the lattice.
        key : str, default "aoi.bounds"
            The settings key named in the error when ``inward=True`` and no whole cell fits.

        Returns
        -------
        Grid

        Raises
        ------
        InputError
            When ``resolution_m`` is not positive, the bounds are empty, or (``inward=True``) not
            one whole cell fits (the message names ``key``).
        CRSError
            When ``crs`` cannot be resolved.
        """
        if not resolution_m > 0:
            raise InputError(f"resolution {resolution_m} m must be positive (e.g. 2.0)")
        if not (xmax > xmin and ymax > ymin):
            raise InputError(f"empty bounds ({xmin}, {ymin}, {xmax}, {ymax}): need xmin < xmax and ymin < ymax")
        crs = resolve_crs(crs)
        r = resolution_m
        if inward:
            x0 = np.ceil(xmin / r - 1e-9) * r
            y1 = np.floor(ymax / r + 1e-9) * r
            nx = int(np.floor((xmax - x0) / r + 1e-9))
            ny = int(np.floor((y1 - ymin) / r + 1e-9))
            if nx < 1 or ny < 1:
                raise InputError(f"{key} ({xmin:g}, {ymin:g}, {xmax:g}, {ymax:g}) holds no whole {r:g} m cell of the "
                                 f"lattice of multiples of aoi.resolution_m; widen {key} or lower aoi.resolution_m")
            return cls(_crs_text(crs), float(x0), float(y1), nx, ny, float(r))
        x0 = np.floor(xmin / r) * r
        y1 = np.ceil(ymax / r) * r
        nx = int(np.ceil((xmax - x0) / r - 1e-9))
        ny = int(np.ceil((y1 - ymin) / r - 1e-9))
        return cls(_crs_text(crs), float(x0), float(y1), nx, ny, float(r))

    @property
    def crs(self) -> CRS:
        """The grid's CRS as a :class:`pyproj.CRS`.
        """
        return CRS.from_user_input(self.crs_wkt)

    @property
    def shape(self) -> tuple[int, int]:
        """Raster shape ``(ny, nx)``.
        """
        return (self.ny, self.nx)

    @property
    def transform(self) -> Affine:
        """Affine transform from (col, row) to map (x, y) [m] (north-up, origin at (``x0``, ``y1``)).
        """
        from affine import Affine

        return Affine(self.resolution_m, 0.0, self.x0, 0.0, -self.resolution_m, self.y1)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """Grid extent ``(xmin, ymin, xmax, ymax)`` [m] in map coordinates (cell edges).
        """
        r = self.resolution_m
        return (self.x0, self.y1 - self.ny * r, self.x0 + self.nx * r, self.y1)

    @property
    def x(self) -> np.ndarray:
        """Map x of the cell centres [m], ascending, shape ``(nx,)``.
        """
        return self.x0 + (np.arange(self.nx) + 0.5) * self.resolution_m

    @property
    def y(self) -> np.ndarray:
        """Map y of the cell centres [m], descending, shape ``(ny,)``.
        """
        return self.y1 - (np.arange(self.ny) + 0.5) * self.resolution_m

    def coords(self) -> dict[str, xr.DataArray]:
        """CF-annotated ``y`` and ``x`` cell-centre coordinates [m] for a raster of this grid.

        Returns
        -------
        dict of str to xarray.DataArray
            ``{"y": (ny,), "x": (nx,)}`` with ``units``, ``standard_name`` and ``axis`` attributes.
        """
        import xarray as xr

        return {
            "y": xr.DataArray(self.y, dims="y", attrs={"units": "m", "standard_name": "projection_y_coordinate", "axis": "Y"}),
            "x": xr.DataArray(self.x, dims="x", attrs={"units": "m", "standard_name": "projection_x_coordinate", "axis": "X"}),
        }

    def dataarray(self, values: np.ndarray, name: str, **attrs) -> xr.DataArray:
        """Wrap a ``(ny, nx)`` array as a raster of this grid with CRS and attrs.

        Parameters
        ----------
        values : numpy.ndarray
            Values, shape ``(ny, nx)``.
        name : str
            Name of the DataArray.
        **attrs
            Attributes of the DataArray (e.g. ``units``, ``vertical_datum``).

        Returns
        -------
        xarray.DataArray
            Dims ``("y", "x")`` with :meth:`coords` and the CRS written (``da.rio.crs``).
        """
        import rioxarray  # noqa: F401  (registers the .rio accessor)
        import xarray as xr

        da = xr.DataArray(values, dims=("y", "x"), coords=self.coords(), name=name, attrs=attrs)
        return da.rio.write_crs(self.crs, inplace=True)   # a new object: no copy of ``values``

    def index_of(self, x: np.ndarray | float, y: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) of the cells containing map points (x, y) [m]; may fall outside the grid.

        Parameters
        ----------
        x, y : float or numpy.ndarray
            Map coordinates [m] in the grid's CRS.

        Returns
        -------
        row, col : numpy.ndarray of int64
            Cell indices, not clipped (negative or >= ``ny``/``nx`` outside the grid).
        """
        col = np.floor((np.asarray(x) - self.x0) / self.resolution_m).astype(np.int64)
        row = np.floor((self.y1 - np.asarray(y)) / self.resolution_m).astype(np.int64)
        return row, col

    def cell_of(self, x: np.ndarray | float, y: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) of the cells containing map points (x, y) [m], clipped to the grid.

        A point outside takes the nearest edge cell.

        Parameters
        ----------
        x, y : float or numpy.ndarray
            Map coordinates [m] in the grid's CRS.

        Returns
        -------
        row, col : numpy.ndarray of int64
            Cell indices in ``0..ny-1`` and ``0..nx-1``.
        """
        row, col = self.index_of(x, y)
        return np.clip(row, 0, self.ny - 1), np.clip(col, 0, self.nx - 1)

    def contains(self, x: float, y: float) -> bool:
        """Whether map point (x, y) [m] lies within :attr:`bounds` (edges included).

        Parameters
        ----------
        x, y : float
            Map coordinates [m].

        Returns
        -------
        bool
        """
        xmin, ymin, xmax, ymax = self.bounds
        return bool(xmin <= x <= xmax and ymin <= y <= ymax)

    def to_lonlat(self, x, y):
        """Map (x, y) [m] to WGS 84 (lon, lat) [deg].

        Parameters
        ----------
        x, y : float or array_like
            Map coordinates [m] in the grid's CRS.

        Returns
        -------
        lon, lat : float or numpy.ndarray
            WGS 84 longitude and latitude [deg].
        """
        t = Transformer.from_crs(self.crs, 4326, always_xy=True)
        return t.transform(x, y)

    def from_lonlat(self, lon, lat):
        """WGS 84 (lon, lat) [deg] to map (x, y) [m].

        Parameters
        ----------
        lon, lat : float or array_like
            WGS 84 longitude and latitude [deg].

        Returns
        -------
        x, y : float or numpy.ndarray
            Map coordinates [m] in the grid's CRS.
        """
        t = Transformer.from_crs(4326, self.crs, always_xy=True)
        return t.transform(lon, lat)

    @classmethod
    def from_dataarray(cls, da: xr.DataArray | xr.Dataset) -> Grid:
        """Recover the grid of a raster that follows the conventions above.

        Parameters
        ----------
        da : xarray.DataArray or xarray.Dataset
            A raster with ``x`` ascending, ``y`` descending, equal steps, at least 2 x 2 cells and a
            CRS (``da.rio.crs``).

        Returns
        -------
        Grid

        Raises
        ------
        InputError
            When the raster has fewer than 2 x 2 cells or is not north-up with square cells.
        CRSError
            When the raster carries no CRS.
        """
        import rioxarray  # noqa: F401  (registers the .rio accessor)

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
