"""Wind maps: uniform wind, gridded forecasts (CF NetCDF / zarr) sampled on the scenario grid.

Seed 000 (section II-A item 4) uses a static wind map that varies only horizontally and is
constant with altitude; seed 001 (section 2) gives it as intensity, azimuth and elevation.
This module keeps that model (``profile="constant"``) and adds a vertical profile from a
forecast on pressure or height levels.

Conventions
-----------
* Components: ``u`` towards east, ``v`` towards north, ``w`` upward [m/s] (CF
  ``eastward_wind``, ``northward_wind``, ``upward_air_velocity``).
* Direction: meteorological, the direction the wind blows **from**, clockwise from north
  [deg] (wind from north -> ``v < 0``).  ``convention="to"`` takes the direction the air
  moves **towards** (seed 000 Fig. 4: "wind directed towards East").
* Elevation angle [deg]: positive when the air moves upward.  ``speed`` is the 3-D norm.
* Altitudes ``z`` are heights above ground [m].

Vertical interpolation of a forecast (``profile="levels"``)
-----------------------------------------------------------
1. Horizontal first: every variable (u, v, gh, u10, v10, w) is interpolated bilinearly in
   (lon, lat) to each column's centre.  Longitudes are handled modulo 360 (a 0..357.5 grid
   wraps between 357.5 and 360); latitudes may be stored descending.
2. Height of a pressure level above ground = geopotential height ``gh`` [gpm] minus the ground
   height of the column.  The ground height is the scenario terrain [m above the vertical
   datum, ~ mean sea level] at the column (``terrain=``), not the model orography (a 2.5 deg
   model surface is off by hundreds of metres in hills and the files rarely carry it); with
   ``terrain=None`` the ground is at 0 m (sea level).  Geopotential and geometric metres
   differ by < 0.3 % below 10 km, which is ignored.  Levels whose height above ground is not
   above the 10 m reference (below ground in a high) are dropped for that column.
3. The 10 m wind (``u10``, ``v10``) is the reference level ``z_ref = 10 m``.  Below it the
   power law ``V(z) = V_ref (z / z_ref) ** alpha`` applies to each component, with
   ``alpha = 1/7`` by default (neutral stability, open terrain; ~0.25-0.4 is typical over
   cities: pass ``power_exponent``).  Between ``z_ref`` and the lowest pressure level ``z_1``
   the same power law is used plus a linear correction that makes it meet the level exactly:
   ``V(z) = P(z) + (V_1 - P(z_1)) (z - z_ref) / (z_1 - z_ref)`` (continuous profile).  Above
   ``z_1``: linear in height between levels, constant above the top level.  Without a 10 m
   wind the lowest level above ground is the reference.  ``w`` (if given on levels) is linear
   in height between 0 at the ground and the levels.
4. ``profile="power"``: the power law from the 10 m wind at every height.
   ``profile="constant"``: the 10 m wind (or the lowest level) at every height (seed model).

Units and checks of a forecast file
-----------------------------------
Declared ``units`` are converted, never guessed: wind components in m/s (``m s-1``, ``m s**-1``,
``m/s``), km/h, knots (``kt``), mph, ft/s or cm/s are converted to m/s (:data:`SPEED_UNITS`);
geopotential height in gpm / m, dam or km; geopotential in m2 s-2; height levels in m, km or ft.
An unknown unit is refused (DataError naming the variable and the unit); a missing ``units``
attribute is a warning ("assumed m/s").  Level heights (geopotential height on pressure levels,
or the height coordinate) must be finite (all-NaN is refused, and every column the scenario
samples must have finite u, v and heights).  :func:`read_wind` refuses a FIFO or device and a
file larger than :data:`MAX_WIND_BYTES` before NetCDF / zarr opens it.

Before any variable is loaded, :func:`canonical_wind` checks what the file declares: latitude and
longitude are 1-D, finite, within [-90, 90] / [-180, 360] deg and strictly monotonic; a dimension
besides latitude, longitude and the levels (an ensemble ``number``, a ``step``) of length 1 is
dropped, a longer one refused; the memory the read takes (the declared shapes,
:data:`READ_BYTES_PER_VALUE`) must fit the command's ``--max-memory`` and at most
:data:`MAX_WIND_VALUES` values are read.  Every wind component the scenario samples must be at
most :data:`MAX_WIND_SPEED_MPS` in magnitude.

A 2.5 deg forecast varies little across a city, so the result may be stored on a coarser
horizontal grid than the scenario (``horizontal_step_m``): same CRS and bounds, cells of that
size; :func:`sample_wind` reads it at any map point (nearest column, linear in height).
"""

from __future__ import annotations

import os
import re
import stat
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import xarray as xr

from skyroute.stages.base import CRSError, DataError, InputError, memory_limit_bytes
from skyroute.stages.grid import Grid

G0 = 9.80665  # standard gravity [m/s^2], geopotential [m^2/s^2] -> geopotential height [gpm]
Z_REF_M = 10.0  # height of the surface wind [m]
DEFAULT_ALPHA = 1.0 / 7.0

_LAT_NAMES = ("latitude", "lat", "nav_lat")
_LON_NAMES = ("longitude", "lon", "nav_lon")
_PRESSURE_DIMS = ("isobaricInhPa", "isobaricInPa", "plev", "pressure", "level", "lev", "pressure_level")
_HEIGHT_DIMS = ("height", "heightAboveGround", "height_above_ground", "altitude")
_TIME_DIMS = ("valid_time", "time")

_VAR_NAMES = {
    "u": (("u", "ua", "uwnd", "UGRD", "U"), "eastward_wind"),
    "v": (("v", "va", "vwnd", "VGRD", "V"), "northward_wind"),
    "w": (("w", "wa", "W"), "upward_air_velocity"),
    "gh": (("gh", "zg", "hgt", "HGT"), "geopotential_height"),
    "z": (("z", "geopotential"), "geopotential"),
    "u10": (("u10", "10u", "uas", "U10"), None),
    "v10": (("v10", "10v", "vas", "V10"), None),
}

MAX_WIND_BYTES = 2 * 1024**3
"""The largest wind file (or zarr store) read [bytes]: a global 0.25 deg forecast of one time on
all pressure levels is a few hundred MB."""

MAX_WIND_SPEED_MPS = 100.0
"""The strongest wind component a forecast file may hold where the scenario samples it [m/s]: the
same bound as ``skyroute.pipeline.settings.common.MAX_WIND_SPEED_MPS`` for a uniform wind and the
wind events (close to the strongest gust ever measured at the surface, 113 m/s).  Kept here, not
imported, because the stages may not import the pipeline; tests/test_wind_findings.py checks that
the two are equal."""

MAX_WIND_VALUES = 2**29
"""The most values (summed over the variables read: u, v, w, gh, u10, v10) a wind file may
declare over the part that is read, whatever the memory limit: a global 0.25 deg forecast of one
time on 37 pressure levels holds 3 x 38 million."""

READ_BYTES_PER_VALUE = 16
"""Memory a value read takes besides its bytes in the file's dtype [bytes]: its float64 copy (the
canonical form) and one float64 temporary (unit conversion, sorting the coordinates)."""

KNOT_MPS = 1852.0 / 3600.0
#: Wind-speed units (normalised: lower case, ``**`` and ``^`` dropped, blanks single) -> m/s.
SPEED_UNITS: dict[str, float] = {
    **dict.fromkeys(("m s-1", "m/s", "ms-1", "m.s-1", "m sec-1", "m/sec", "mps", "meter/second",
                     "meters/second", "metre/second", "metres/second", "meter second-1",
                     "meters second-1", "metre second-1", "metres second-1", "meters per second",
                     "metres per second", "m s-1 (m/s)"), 1.0),
    **dict.fromkeys(("km h-1", "km/h", "kmh-1", "km.h-1", "km hr-1", "km/hr", "kph", "kmh",
                     "kilometers per hour", "kilometres per hour", "kilometer/hour", "kilometre/hour"),
                    1.0 / 3.6),
    **dict.fromkeys(("kt", "kts", "kn", "knot", "knots"), KNOT_MPS),
    **dict.fromkeys(("mph", "mi/h", "mi h-1", "miles per hour", "mile/hour"), 0.44704),
    **dict.fromkeys(("ft/s", "ft s-1", "feet per second", "fps"), 0.3048),
    **dict.fromkeys(("cm/s", "cm s-1"), 0.01),
}
#: Geopotential-height units -> gpm.
GH_UNITS: dict[str, float] = {
    **dict.fromkeys(("gpm", "m", "meter", "meters", "metre", "metres", "gp m", "geopotential meters",
                     "geopotential metres", "m (geopotential)"), 1.0),
    **dict.fromkeys(("dam", "gpdam", "decameter", "decameters", "decametre", "decametres"), 10.0),
    **dict.fromkeys(("km", "gpkm"), 1000.0),
}
#: Geopotential units -> m2 s-2 (divided by G0 to give gpm).
GEOPOTENTIAL_UNITS: dict[str, float] = dict.fromkeys(("m2 s-2", "m2/s2", "m2.s-2", "m+2 s-2", "j kg-1",
                                                      "j/kg"), 1.0)
#: Height-level units -> m.
HEIGHT_UNITS: dict[str, float] = {
    **dict.fromkeys(("m", "meter", "meters", "metre", "metres"), 1.0),
    **dict.fromkeys(("km",), 1000.0),
    **dict.fromkeys(("ft", "feet", "foot"), 0.3048),
}


def _norm_units(text: str) -> str:
    s = str(text).strip().lower().replace("**", "").replace("^", "").replace("·", " ")
    return re.sub(r"\s+", " ", s)


def _unit_factor(da: xr.DataArray, name: str, table: dict[str, float], what: str, assumed: str,
                 source: str) -> float:
    """The factor converting variable ``name`` (``da``) to SI from its ``units`` attribute
    (``table``); a missing attribute warns (``assumed``), an unknown one is a DataError."""
    units = da.attrs.get("units")
    if units is None or str(units).strip() == "":
        warnings.warn(f"{source}: variable {name!r} ({what}) has no 'units' attribute: assumed {assumed}",
                      stacklevel=3)
        return 1.0
    f = table.get(_norm_units(units))
    if f is None:
        shown: dict[float, str] = {}
        for k, v in table.items():      # the first spelling of each unit
            shown.setdefault(v, k)
        raise DataError(f"{source}: variable {name!r} ({what}) has units {units!r}, which skyroute does not "
                        f"know; give {what} in one of: {', '.join(shown.values())} (or their usual spellings)")
    return f


_ATTRS = {
    "u": {"units": "m s-1", "standard_name": "eastward_wind", "long_name": "wind towards east"},
    "v": {"units": "m s-1", "standard_name": "northward_wind", "long_name": "wind towards north"},
    "w": {"units": "m s-1", "standard_name": "upward_air_velocity", "long_name": "wind upward"},
    "speed": {"units": "m s-1", "standard_name": "wind_speed", "long_name": "3-D wind speed |(u, v, w)|"},
}


@dataclass(frozen=True)
class UniformWind:
    """A wind that is the same everywhere: ``speed_mps`` [m/s] (3-D norm), ``direction_deg``
    [deg, the direction it blows FROM, clockwise from north, unless ``convention="to"``],
    ``elevation_deg`` [deg, positive upward].  ``speed_mps`` is the 10 m value for
    ``profile="power"``."""

    speed_mps: float
    direction_deg: float
    elevation_deg: float = 0.0
    convention: str = "from"

    def components(self) -> tuple[float, float, float]:
        return uniform_wind(self.speed_mps, self.direction_deg, self.elevation_deg, self.convention)


def uniform_wind(speed_mps: float, direction_deg: float, elevation_deg: float = 0.0,
                 convention: str = "from") -> tuple[float, float, float]:
    """Components (u east, v north, w up) [m/s] of a wind of 3-D speed ``speed_mps`` [m/s]
    blowing from ``direction_deg`` [deg clockwise from north] (``convention="to"``: towards),
    with elevation angle ``elevation_deg`` [deg, positive upward].

    >>> [round(c, 6) for c in uniform_wind(5.0, 0.0)]   # from north: towards south
    [-0.0, -5.0, 0.0]
    """
    if not np.isfinite(speed_mps) or speed_mps < 0:
        raise InputError(f"wind speed {speed_mps} m/s must be finite and >= 0")
    if not np.isfinite(direction_deg):
        raise InputError(f"wind direction {direction_deg} deg must be finite")
    if not (np.isfinite(elevation_deg) and -90.0 <= elevation_deg <= 90.0):
        raise InputError(f"wind elevation {elevation_deg} deg must be in [-90, 90]")
    if convention not in ("from", "to"):
        raise InputError(f"wind direction convention {convention!r} must be 'from' or 'to'")
    az = np.deg2rad(direction_deg)
    el = np.deg2rad(elevation_deg)
    h = speed_mps * np.cos(el)
    sign = -1.0 if convention == "from" else 1.0
    return float(sign * h * np.sin(az)), float(sign * h * np.cos(az)), float(speed_mps * np.sin(el))


# --------------------------------------------------------------------------- reading


def _find_var(ds: xr.Dataset, key: str) -> str | None:
    names, std = _VAR_NAMES[key]
    for n in names:
        if n in ds.data_vars:
            return n
    if std is not None:
        for n, da in ds.data_vars.items():
            if da.attrs.get("standard_name") == std and da.ndim >= 2:
                return str(n)
    return None


def _first(ds: xr.Dataset, names: tuple[str, ...]) -> str | None:
    for n in names:
        if n in ds.dims or n in ds.coords:
            return n
    return None


def _select_time(ds: xr.Dataset, time, source: str, tolerance_h: float) -> xr.Dataset:
    tdims = [d for d in _TIME_DIMS if d in ds.dims]
    if tdims:
        d = tdims[0]
        if ds.sizes[d] > 1 and time is None:
            raise InputError(f"{source} holds {ds.sizes[d]} times along {d!r}: pass time= (e.g. '2011-01-15T12:00')")
        if time is None:
            return ds.isel({d: 0})
        t = pd.Timestamp(time).to_datetime64()
        ds = ds.sel({d: t}, method="nearest")
    vt = None
    for n in _TIME_DIMS:
        if n in ds.coords and ds[n].ndim == 0 and np.issubdtype(ds[n].dtype, np.datetime64):
            vt = ds[n].values
            break
    if time is not None and vt is not None:
        gap_h = abs((pd.Timestamp(vt) - pd.Timestamp(time)).total_seconds()) / 3600.0
        if gap_h > tolerance_h:
            raise InputError(f"{source} is valid at {pd.Timestamp(vt)}, {gap_h:.1f} h from the requested "
                             f"time {pd.Timestamp(time)} (tolerance {tolerance_h} h): use a forecast for that time")
    return ds


def _speed_in_mps(da: xr.DataArray, name: str, source: str) -> xr.DataArray:
    """A wind component in m/s from its declared ``units`` (:data:`SPEED_UNITS`)."""
    f = _unit_factor(da, name, SPEED_UNITS, "wind speed", "m/s", source)
    return da if f == 1.0 else da * f


def canonical_wind(ds: xr.Dataset, source: str = "<dataset>", time=None,
                   time_tolerance_h: float = 6.0) -> xr.Dataset:
    """Rename a CF wind dataset to skyroute's form: dims (``level``, ``latitude``,
    ``longitude``) with latitude ascending; variables ``u``, ``v`` [m/s] (+ ``w``), ``gh``
    [gpm] on pressure levels, ``u10``, ``v10`` [m/s]; ``level`` has attribute
    ``level_type`` = ``"pressure"`` [hPa] or ``"height"`` [m above ground]."""
    found = sorted(str(n) for n in ds.data_vars)
    lat = _first(ds, _LAT_NAMES)
    lon = _first(ds, _LON_NAMES)
    if lat is None or lon is None:
        raise DataError(f"{source}: no latitude/longitude coordinates (looked for {_LAT_NAMES} and "
                        f"{_LON_NAMES}; found coords {sorted(map(str, ds.coords))})")
    names = {k: _find_var(ds, k) for k in _VAR_NAMES}
    has_levels = names["u"] is not None and names["v"] is not None
    has_10m = names["u10"] is not None and names["v10"] is not None
    if not (has_levels or has_10m):
        raise DataError(f"{source}: no wind components: need u and v (eastward_wind/northward_wind) "
                        f"or u10 and v10; variables found: {found}")
    ds = _select_time(ds, time, source, time_tolerance_h)
    _check_lonlat(ds, lat, lon, source)
    read = [names[k] for k in ("u", "v", "w") if has_levels and names[k] is not None]
    read += [names["gh"] or names["z"]] if has_levels and (names["gh"] or names["z"]) else []
    read += [names["u10"], names["v10"]] if has_10m else []
    ds = _squeeze_extra_dims(ds, read, lat, lon, source)
    check_wind_read_bytes(ds, read, source)
    out = {}
    coords: dict = {}
    level_type = None
    if has_levels:
        u = ds[names["u"]]
        pdim = next((d for d in _PRESSURE_DIMS if d in u.dims), None)
        hdim = next((d for d in _HEIGHT_DIMS if d in u.dims), None)
        if pdim is not None:
            level_type = "pressure"
            lev = ds[pdim]
            levels = np.asarray(lev.values, dtype=float)
            if str(lev.attrs.get("units", "hPa")).lower() in ("pa", "pascal") or pdim == "isobaricInPa":
                levels = levels / 100.0
            if names["gh"] is not None:
                gh_da = ds[names["gh"]]
                gh = gh_da * _unit_factor(gh_da, names["gh"], GH_UNITS, "geopotential height", "gpm", source)
                gh_name = names["gh"]
            elif names["z"] is not None:
                z_da = ds[names["z"]]
                gh = z_da * (_unit_factor(z_da, names["z"], GEOPOTENTIAL_UNITS, "geopotential", "m2 s-2",
                                          source) / G0)
                gh_name = names["z"]
            else:
                raise DataError(f"{source}: wind on pressure levels ({pdim}) needs the geopotential height "
                                f"(gh, zg or z) to place the levels in height; variables found: {found}")
            if not np.any(np.isfinite(np.asarray(gh.values, dtype=float))):
                raise DataError(f"{source}: variable {gh_name!r} (height of the pressure levels) has no finite "
                                "value (all NaN): the levels cannot be placed in height; give a file with "
                                "the geopotential height")
            if not np.all(np.isfinite(levels)):
                raise DataError(f"{source}: pressure levels {pdim!r} are not all finite ({levels.tolist()})")
            vdim = pdim
        elif hdim is not None:
            level_type = "height"
            h_da = ds[hdim]
            levels = np.asarray(h_da.values, dtype=float) * _unit_factor(h_da, hdim, HEIGHT_UNITS,
                                                                         "level height", "m", source)
            if not np.all(np.isfinite(levels)):
                raise DataError(f"{source}: height levels {hdim!r} are not all finite ({levels.tolist()}); "
                                "every level needs its height above ground [m]")
            gh = None
            vdim = hdim
        else:
            raise DataError(f"{source}: u has dims {u.dims} without a vertical dimension "
                            f"(one of {_PRESSURE_DIMS + _HEIGHT_DIMS})")
        for key in ("u", "v", "w"):
            if names[key] is not None and vdim in ds[names[key]].dims:
                out[key] = _speed_in_mps(ds[names[key]], names[key], source)
        if gh is not None:
            out["gh"] = gh
        out = {k: da.rename({vdim: "level"}) for k, da in out.items()}
        coords["level"] = ("level", levels, {"level_type": level_type,
                                             "units": "hPa" if level_type == "pressure" else "m"})
    if has_10m:
        out["u10"] = _speed_in_mps(ds[names["u10"]], names["u10"], source)
        out["v10"] = _speed_in_mps(ds[names["v10"]], names["v10"], source)
    res = xr.Dataset({k: da.rename({lat: "latitude", lon: "longitude"}).drop_vars(
        [c for c in da.coords if c not in (lat, lon)], errors="ignore") for k, da in out.items()})
    if "level" in coords:
        res = res.assign_coords(level=coords["level"])
    res = res.sortby("latitude").sortby("longitude")
    for k in ("u", "v", "w", "gh", "u10", "v10"):
        if k in res:
            res[k] = res[k].astype("float64")
            if k != "gh":
                res[k] = res[k].transpose(*([d for d in ("level",) if d in res[k].dims]), "latitude", "longitude")
            else:
                res[k] = res[k].transpose("level", "latitude", "longitude")
                res[k].attrs = {"units": "gpm", "standard_name": "geopotential_height"}
    for k in res.data_vars:
        res[k].attrs["file_variable"] = names[str(k)] or names["z"]
    res.attrs = {"source": source, "level_type": level_type or "none"}
    for n in _TIME_DIMS:
        if n in ds.coords and ds[n].ndim == 0:
            res.attrs["valid_time"] = str(pd.Timestamp(ds[n].values))
            break
    return res


def _check_lonlat(ds: xr.Dataset, lat: str, lon: str, source: str) -> None:
    """Refuse latitude / longitude coordinates that are not 1-D, not finite numbers, outside
    [-90, 90] / [-180, 360] deg or not strictly monotonic (a DataError naming the coordinate and
    the offending value)."""
    for name, lo, hi, what in ((lat, -90.0, 90.0, "latitude [degrees_north]"),
                               (lon, -180.0, 360.0, "longitude [degrees_east]")):
        c = ds[name]
        if c.ndim != 1:
            raise DataError(f"{source}: coordinate {name!r} has dims {tuple(map(str, c.dims))}, not one "
                            f"dimension of its own: skyroute reads a regular latitude/longitude grid; regrid "
                            "the file to one (e.g. cdo remapbil)")
        try:
            v = np.asarray(c.values, dtype=float)
        except (TypeError, ValueError):
            raise DataError(f"{source}: coordinate {name!r} holds {c.dtype} values, not numbers: give the "
                            f"{what} in degrees") from None
        bad = ~np.isfinite(v) | (v < lo) | (v > hi)
        if np.any(bad):
            k = int(np.argmax(bad))
            why = "not a finite number" if not np.isfinite(v[k]) else f"outside [{lo:g}, {hi:g}] deg"
            raise DataError(f"{source}: coordinate {name!r} holds {float(v[k])!r} at index {k}, {why}: every "
                            f"{what} must be a finite value in [{lo:g}, {hi:g}]; fix the file's coordinates")
        d = np.diff(v)
        if d.size and not (np.all(d > 0) or np.all(d < 0)):
            k = int(np.argmax((d <= 0) if d[0] > 0 else (d >= 0)))
            raise DataError(f"{source}: coordinate {name!r} is not strictly monotonic: {float(v[k])!r} at index "
                            f"{k} is followed by {float(v[k + 1])!r}; a regular grid's {what.split()[0]}s strictly "
                            "increase or decrease: fix or sort the file's coordinates (e.g. cdo "
                            "invertlat, or xarray ds.sortby)")


def _squeeze_extra_dims(ds: xr.Dataset, read: list[str], lat: str, lon: str, source: str) -> xr.Dataset:
    """Drop the dimensions of length 1 the variables ``read`` have besides latitude, longitude
    and one vertical dimension (an ensemble ``number``, a ``step``); refuse a longer one (a
    DataError naming the variable, the dimension, its length and the fix)."""
    vertical = _PRESSURE_DIMS + _HEIGHT_DIMS
    for n in read:
        da = ds[n]
        if lat not in da.dims or lon not in da.dims:
            raise DataError(f"{source}: variable {n!r} has dims {tuple(map(str, da.dims))}, without the "
                            f"latitude and longitude dimensions ({lat!r}, {lon!r}): give it on the "
                            "latitude/longitude grid")
        keep = next((d for d in vertical if d in da.dims), None)
        for d in da.dims:
            if d in (lat, lon, keep):
                continue
            size = int(ds.sizes[d])
            if size == 1:
                ds = ds.isel({d: 0})
                continue
            raise DataError(f"{source}: variable {n!r} has the dimension {str(d)!r} of length {size} "
                            f"besides latitude, longitude{' and ' + repr(keep) if keep else ''} (e.g. ensemble "
                            "members or forecast steps): skyroute reads one field per variable; select one "
                            f"first, e.g. ncks -d {d},0 IN.nc OUT.nc or xarray ds.isel({d}=0)")
    return ds


def check_wind_read_bytes(ds: xr.Dataset, read: list[str], source: str, *,
                          limit_bytes: float | None = None) -> float:
    """The memory [bytes] reading the variables ``read`` of ``ds`` takes, from their declared
    shapes and dtypes (:data:`READ_BYTES_PER_VALUE`), checked before anything is loaded.

    Parameters
    ----------
    ds : xarray.Dataset
        The opened (lazy) file, with the part read selected (one time).
    read : list of str
        The variables loaded.
    source : str
        The file (named in messages).
    limit_bytes : float, optional
        The limit [bytes]; default the command's ``--max-memory``
        (:func:`~skyroute.stages.base.memory_limit_bytes`).

    Returns
    -------
    float
        The estimate [bytes].

    Raises
    ------
    DataError
        Naming the variables, their declared shape, the estimate, the limit and the fixes, when
        the estimate exceeds the limit or the values exceed :data:`MAX_WIND_VALUES`.
    """
    limit = memory_limit_bytes() if limit_bytes is None else float(limit_bytes)
    values = 0.0
    need = 0.0
    for n in read:
        size = float(np.prod([float(s) for s in ds[n].shape]))
        values += size
        need += size * (ds[n].dtype.itemsize + READ_BYTES_PER_VALUE)
    if need <= limit and values <= MAX_WIND_VALUES:
        return need
    gib = lambda b: f"{b / (1 << 30):,.1f} GiB" if b >= 1 << 30 else f"{b / (1 << 20):,.0f} MiB"  # noqa: E731
    big = max(read, key=lambda n: ds[n].size)
    dims = " x ".join(f"{int(s):,}" for s in ds[big].shape)
    what = (f"variables {', '.join(map(repr, read))} declare {values:,.0f} values ({big!r}: {dims} "
            f"on {tuple(map(str, ds[big].dims))})")
    fix = ("crop the file to the scenario's area (e.g. cdo sellonlatbox,W,E,S,N IN.nc OUT.nc or ncks -d "
           "latitude,S,N -d longitude,W,E IN.nc OUT.nc), keep fewer levels or one time")
    if need > limit:
        raise DataError(f"{source}: reading the wind needs about {gib(need)} of memory, more than --max-memory "
                        f"({gib(limit)}): {what}; {fix}, or raise --max-memory")
    raise DataError(f"{source}: {what}, more than the {MAX_WIND_VALUES:,} values skyroute reads from a wind "
                    f"file; {fix}")


def read_wind(path: str | Path, time=None, time_tolerance_h: float = 6.0) -> xr.Dataset:
    """Read a wind forecast (CF NetCDF via h5netcdf/netCDF4, or zarr; GRIB only if cfgrib is
    installed) and return it in the canonical form of :func:`canonical_wind`, loaded in memory.

    ``time``: the valid time wanted; a file with several times must be given one (nearest is
    taken); a single-time file must be valid within ``time_tolerance_h`` [h] of it.
    """
    p = Path(path)
    if not p.exists():
        raise DataError(f"wind file {p} does not exist")
    _check_wind_file(p)
    suffix = "".join(p.suffixes[-1:]).lower()
    try:
        if p.is_dir() or suffix == ".zarr":
            ds = xr.open_zarr(p)
        elif suffix in (".grib", ".grib2", ".grb", ".grb2"):
            try:
                import cfgrib  # noqa: F401
            except ImportError as exc:
                raise DataError(f"{p}: reading GRIB needs the optional package cfgrib; "
                                "convert the file to NetCDF or install cfgrib") from exc
            ds = xr.open_dataset(p, engine="cfgrib")
        else:
            try:
                ds = xr.open_dataset(p, engine="h5netcdf")
            except Exception:
                ds = xr.open_dataset(p, engine="netcdf4")
    except DataError:
        raise
    except Exception as exc:
        raise DataError(f"cannot read wind file {p}: {exc}") from exc
    with ds:
        res = canonical_wind(ds, source=str(p), time=time, time_tolerance_h=time_tolerance_h).load()
    return res


def _check_wind_file(p: Path, max_bytes: int | None = None) -> None:
    """Refuse, before NetCDF / zarr opens it, a wind path that is not a regular file or a folder
    (a FIFO would block, ``/dev/zero`` never ends) or that holds more than ``max_bytes``
    [bytes] (default :data:`MAX_WIND_BYTES`)."""
    max_bytes = MAX_WIND_BYTES if max_bytes is None else int(max_bytes)
    try:
        st = os.stat(p)
    except OSError as exc:
        raise DataError(f"cannot read wind file {p}: {exc.strerror or exc}") from None
    if stat.S_ISDIR(st.st_mode):      # a zarr store: the sum of its files' sizes
        total = 0
        for root, _dirs, files in os.walk(p):
            for f in files:
                try:
                    fst = os.lstat(os.path.join(root, f))
                except OSError:
                    continue
                if not stat.S_ISREG(fst.st_mode):
                    raise DataError(f"wind store {p}: {os.path.join(root, f)} is not a regular file")
                total += fst.st_size
                if total > max_bytes:
                    raise DataError(f"wind store {p} holds more than {max_bytes:,} bytes; crop it to the "
                                    "scenario's area and time")
        return
    if not stat.S_ISREG(st.st_mode):
        kind = "a FIFO (named pipe)" if stat.S_ISFIFO(st.st_mode) else "a device" if (
            stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode)) else "a socket" if stat.S_ISSOCK(st.st_mode) \
            else "not a regular file"
        raise DataError(f"wind file {p} is {kind}, not a regular file; give a NetCDF, zarr or GRIB file")
    if st.st_size > max_bytes:
        raise DataError(f"wind file {p} is {st.st_size:,} bytes, more than the {max_bytes:,} bytes skyroute reads; "
                        "crop it to the scenario's area and time")


# --------------------------------------------------------------------------- horizontal


def _bilinear_setup(lonv: np.ndarray, latv: np.ndarray, lon: np.ndarray, lat: np.ndarray, source: str):
    """Indices and weights of the bilinear interpolation; longitudes modulo 360."""
    lon = np.asarray(lon, dtype=float)
    lat = np.asarray(lat, dtype=float)
    lonx = np.asarray(lonv, dtype=float)
    step = np.diff(lonx)
    wrap = lonx.size > 1 and np.allclose(step, step[0]) and abs(lonx[-1] + step[0] - lonx[0] - 360.0) < 1e-6
    lon_t = lonx[0] + np.mod(lon - lonx[0], 360.0)
    if wrap:
        lonx = np.append(lonx, lonx[0] + 360.0)
    n = lonx.size
    i = np.clip(np.searchsorted(lonx, lon_t, side="right") - 1, 0, n - 2)
    fx = (lon_t - lonx[i]) / (lonx[i + 1] - lonx[i])
    m = latv.size
    j = np.clip(np.searchsorted(latv, lat, side="right") - 1, 0, m - 2)
    fy = (lat - latv[j]) / (latv[j + 1] - latv[j])
    bad = (fx < -1e-9) | (fx > 1 + 1e-9) | (fy < -1e-9) | (fy > 1 + 1e-9)
    if np.any(bad):
        k = int(np.argmax(bad))
        raise DataError(f"{source}: point lon={float(lon.ravel()[k]):.4f}, lat={float(lat.ravel()[k]):.4f} is outside "
                        f"the wind data (lon {lonv[0]}..{lonv[-1]}, lat {latv[0]}..{latv[-1]})")
    i1 = np.where(i + 1 >= lonv.size, 0, i + 1)  # wrapped column
    return i, i1, j, j + 1, fx, fy


def _bilinear(field: np.ndarray, idx) -> np.ndarray:
    """``field[..., lat, lon]`` -> ``[npts, ...]``."""
    i0, i1, j0, j1, fx, fy = idx
    f00 = field[..., j0, i0]
    f01 = field[..., j0, i1]
    f10 = field[..., j1, i0]
    f11 = field[..., j1, i1]
    val = (1 - fx) * (1 - fy) * f00 + fx * (1 - fy) * f01 + (1 - fx) * fy * f10 + fx * fy * f11
    return np.moveaxis(val, -1, 0)


def sample_columns(wind: xr.Dataset, lon_deg, lat_deg) -> dict[str, np.ndarray]:
    """Bilinear (lon, lat) [deg] interpolation of every variable of a canonical wind dataset:
    ``{name: array (npts,) or (npts, nlevel)}``."""
    wind = _as_canonical(wind)
    lon = np.atleast_1d(np.asarray(lon_deg, dtype=float))
    lat = np.atleast_1d(np.asarray(lat_deg, dtype=float))
    source = wind.attrs.get("source", "wind")
    idx = _bilinear_setup(wind["longitude"].values, wind["latitude"].values, lon, lat, source)
    fields = {k: np.asarray(wind[k].values) for k in ("u", "v", "w", "gh", "u10", "v10") if k in wind}
    out = {k: _bilinear(f, idx) for k, f in fields.items()}
    for k, a in out.items():
        bad = ~np.isfinite(a)
        if np.any(bad):
            i = int(np.argmax(bad.reshape(bad.shape[0], -1).any(axis=1)))
            what = "geopotential height of the levels" if k == "gh" else "wind component"
            raise DataError(f"{source}: {k} ({what}) has no data (NaN) around lon={float(lon.ravel()[i]):.4f}, "
                            f"lat={float(lat.ravel()[i]):.4f}: the wind there is unknown; fill the file or give "
                            "one that covers the scenario")
    for k in ("u", "v", "w", "u10", "v10"):
        if k in fields:
            _check_speed_bound(fields[k], idx, k, wind[k].attrs.get("file_variable", k), lon, lat, source)
    return out


def _check_speed_bound(field: np.ndarray, idx, key: str, file_name: str, lon: np.ndarray, lat: np.ndarray,
                       source: str) -> None:
    """Refuse a wind component [m/s] above :data:`MAX_WIND_SPEED_MPS` in magnitude at any grid
    node the bilinear interpolation ``idx`` reads (the region sampled)."""
    i0, i1, j0, j1 = idx[:4]
    corners = np.stack([field[..., j, i] for j in (j0, j1) for i in (i0, i1)])   # (4, ..., npts)
    mag = np.abs(np.nan_to_num(corners, nan=0.0))
    if not np.any(mag > MAX_WIND_SPEED_MPS):
        return
    flat = np.argmax(mag)
    val = float(corners.ravel()[flat])
    p = int(np.unravel_index(flat, corners.shape)[-1])
    named = repr(key) if file_name == key else f"{key!r} (variable {file_name!r} of the file)"
    raise DataError(f"{source}: wind component {named} is {val:g} m/s around lon={float(lon.ravel()[p]):.4f}, "
                    f"lat={float(lat.ravel()[p]):.4f}, more than {MAX_WIND_SPEED_MPS:g} m/s in magnitude (the "
                    "strongest wind skyroute accepts, close to the strongest gust ever measured): the value "
                    "is not a wind; check the file's values and the variable's 'units' attribute")


def _as_canonical(wind: xr.Dataset) -> xr.Dataset:
    if "latitude" in wind.dims and "longitude" in wind.dims and "level_type" in wind.attrs:
        return wind
    return canonical_wind(wind)


# --------------------------------------------------------------------------- vertical


def _power(ref: np.ndarray, z: np.ndarray, z_ref: np.ndarray, alpha: float) -> np.ndarray:
    zz = np.maximum(z, 0.0)
    return ref * (zz / z_ref) ** alpha


def _profile_levels(cols: dict, ground_m: np.ndarray, z_m: np.ndarray, alpha: float,
                    level_type: str) -> dict[str, np.ndarray]:
    """Per-column vertical interpolation; returns ``{u, v, w}`` arrays (npts, nz)."""
    npts = ground_m.size
    nz = z_m.size
    if "u" in cols:
        h = (cols["gh"] - ground_m[:, None]) if level_type == "pressure" else np.broadcast_to(
            cols["level_h"], cols["u"].shape).astype(float)
        order = np.argsort(h, axis=1, kind="stable")
        h = np.take_along_axis(h, order, axis=1)
        lev = {k: np.take_along_axis(cols[k], order, axis=1) for k in ("u", "v", "w") if k in cols}
    else:
        h = np.empty((npts, 0))
        lev = {}
    if "u10" in cols:
        z_ref = np.full(npts, Z_REF_M)
        ref = {"u": cols["u10"], "v": cols["v10"]}
    else:  # the lowest level above ground is the reference
        k0 = np.argmax(h > 0.0, axis=1)
        if np.any(~np.any(h > 0.0, axis=1)):
            raise DataError("wind: no level above ground in some column (check terrain and gh)")
        z_ref = h[np.arange(npts), k0]
        ref = {c: lev[c][np.arange(npts), k0] for c in ("u", "v")}
    out = {c: np.empty((npts, nz)) for c in ("u", "v", "w")}
    rows = np.arange(npts)
    if h.shape[1]:
        valid = h > z_ref[:, None] + 1.0  # levels above the reference
        has_lev = np.any(valid, axis=1)
        k1 = np.argmax(valid, axis=1)
        z1 = np.where(has_lev, h[rows, k1], np.inf)
    for iz, z in enumerate(z_m):
        zc = np.full(npts, float(z))
        for c in ("u", "v"):
            p = _power(ref[c], zc, z_ref, alpha)
            if h.shape[1]:
                v1 = lev[c][rows, k1]
                p1 = _power(ref[c], z1, z_ref, alpha)
                blend = p + (v1 - p1) * (zc - z_ref) / np.where(has_lev, z1 - z_ref, 1.0)
                cnt = np.sum(h <= zc[:, None], axis=1)
                ja = np.clip(cnt - 1, 0, h.shape[1] - 1)
                jb = np.clip(cnt, 0, h.shape[1] - 1)
                ha, hb = h[rows, ja], h[rows, jb]
                fa = np.where(hb > ha, (zc - ha) / np.where(hb > ha, hb - ha, 1.0), 0.0)
                lin = lev[c][rows, ja] * (1 - fa) + lev[c][rows, jb] * fa
                val = np.where(zc <= z_ref, p, np.where(has_lev & (zc < z1), blend, np.where(has_lev, lin, p)))
            else:
                val = p
            out[c][:, iz] = val
        if "w" in lev:
            hw = np.concatenate([np.zeros((npts, 1)), np.maximum(h, 0.0)], axis=1)
            ww = np.concatenate([np.zeros((npts, 1)), np.where(h > 0, lev["w"], 0.0)], axis=1)
            cnt = np.sum(hw <= zc[:, None], axis=1)
            ja = np.clip(cnt - 1, 0, hw.shape[1] - 1)
            jb = np.clip(cnt, 0, hw.shape[1] - 1)
            ha, hb = hw[rows, ja], hw[rows, jb]
            fa = np.where(hb > ha, (zc - ha) / np.where(hb > ha, hb - ha, 1.0), 0.0)
            out["w"][:, iz] = ww[rows, ja] * (1 - fa) + ww[rows, jb] * fa
        else:
            out["w"][:, iz] = 0.0
    return out


def wind_at_lonlat(wind: xr.Dataset, lon_deg, lat_deg, z_m, ground_m=0.0, profile: str = "levels",
                   power_exponent: float = DEFAULT_ALPHA) -> dict[str, np.ndarray]:
    """Wind (u, v, w) [m/s] at points (lon, lat) [deg] and heights above ground ``z_m`` [m];
    ``ground_m``: ground height of each point [m above the datum of ``gh``].  Returns arrays
    of shape (npts, nz)."""
    wind = _as_canonical(wind)
    z = np.atleast_1d(np.asarray(z_m, dtype=float))
    _check_profile(profile, power_exponent, z)
    cols = sample_columns(wind, lon_deg, lat_deg)
    npts = next(iter(cols.values())).shape[0]
    ground = np.broadcast_to(np.asarray(ground_m, dtype=float), (npts,)).astype(float)
    lt = wind.attrs.get("level_type", "none")
    if lt == "height":
        cols["level_h"] = wind["level"].values[None, :]
    if profile == "levels":
        return _profile_levels(cols, ground, z, power_exponent, lt)
    if "u10" in cols:
        ref = (cols["u10"], cols["v10"])
    else:
        prof = _profile_levels(cols, ground, np.array([Z_REF_M]), 0.0, lt)
        ref = (prof["u"][:, 0], prof["v"][:, 0])
    scale = np.ones((1, z.size)) if profile == "constant" else (np.maximum(z, 0.0) / Z_REF_M)[None, :] ** power_exponent
    return {"u": ref[0][:, None] * scale, "v": ref[1][:, None] * scale, "w": np.zeros((npts, z.size))}


def _check_profile(profile: str, alpha: float, z: np.ndarray) -> None:
    if profile not in ("levels", "power", "constant"):
        raise InputError(f"wind profile {profile!r} must be 'levels', 'power' or 'constant'")
    if not (np.isfinite(alpha) and 0.0 <= alpha <= 1.0):
        raise InputError(f"power-law exponent {alpha} must be in [0, 1] (1/7 open terrain, ~0.3 urban)")
    if z.ndim != 1 or z.size == 0 or not np.all(np.isfinite(z)) or np.any(z < 0):
        raise InputError("altitudes_m must be a non-empty 1-D list of heights above ground >= 0 m")
    if np.any(np.diff(z) <= 0):
        raise InputError("altitudes_m must be strictly increasing")


# --------------------------------------------------------------------------- on the grid


def wind_grid(grid: Grid, horizontal_step_m: float | None = None) -> Grid:
    """The grid the wind is stored on: ``grid`` itself, or the same CRS and bounds with cells of
    ``horizontal_step_m`` [m] (>= the scenario resolution)."""
    if horizontal_step_m is None or horizontal_step_m == grid.resolution_m:
        return grid
    if not (np.isfinite(horizontal_step_m) and horizontal_step_m >= grid.resolution_m):
        raise InputError(f"horizontal_step_m {horizontal_step_m} must be >= the grid resolution "
                         f"{grid.resolution_m} m")
    return Grid.from_bounds(grid.crs, *grid.bounds, resolution_m=float(horizontal_step_m))


def wind_on_grid(wind: xr.Dataset | UniformWind | tuple, grid: Grid, altitudes_m,
                 terrain: xr.DataArray | None = None, profile: str | None = None,
                 power_exponent: float = DEFAULT_ALPHA,
                 horizontal_step_m: float | None = None) -> xr.Dataset:
    """The wind map: ``u``, ``v``, ``w``, ``speed`` [m/s] on dims (``z``, ``y``, ``x``), ``z``
    the heights above ground ``altitudes_m`` [m], (y, x) the cells of ``grid`` (or of the
    coarser :func:`wind_grid` when ``horizontal_step_m`` [m] is given), CRS attached.

    ``wind``: a forecast dataset (:func:`read_wind`), a :class:`UniformWind`, or a tuple
    ``(speed_mps, direction_deg[, elevation_deg])``.  ``profile``: ``"levels"`` (default for a
    forecast), ``"power"`` or ``"constant"`` (default for a uniform wind) -- see the module
    docstring.  ``terrain``: ground height raster [m] of the scenario (same CRS), used to put
    pressure levels above ground; None = ground at 0 m.
    """
    z = np.atleast_1d(np.asarray(altitudes_m, dtype=float))
    uniform = None
    if isinstance(wind, tuple):
        uniform = UniformWind(*wind)
    elif isinstance(wind, UniformWind):
        uniform = wind
    elif not isinstance(wind, xr.Dataset):
        raise InputError(f"wind must be an xarray Dataset, a UniformWind or a (speed, direction, elevation) "
                         f"tuple, not {type(wind).__name__}")
    if profile is None:
        profile = "constant" if uniform is not None else "levels"
    _check_profile(profile, power_exponent, z)
    wg = wind_grid(grid, horizontal_step_m)
    ny, nx = wg.shape
    if uniform is not None:
        if profile == "levels":
            raise InputError("profile='levels' needs a gridded forecast; use 'constant' or 'power' with a uniform wind")
        u0, v0, w0 = uniform.components()
        scale = np.ones_like(z) if profile == "constant" else (z / Z_REF_M) ** power_exponent
        shape = (z.size, ny, nx)
        u = np.broadcast_to((u0 * scale)[:, None, None], shape).copy()
        v = np.broadcast_to((v0 * scale)[:, None, None], shape).copy()
        w = np.full(shape, w0)
        src = f"uniform {uniform.speed_mps} m/s {uniform.convention} {uniform.direction_deg} deg, " \
              f"elevation {uniform.elevation_deg} deg"
    else:
        xx, yy = np.meshgrid(wg.x, wg.y)
        lon, lat = wg.to_lonlat(xx.ravel(), yy.ravel())
        ground = np.zeros(xx.size)
        if terrain is not None:
            ground = _terrain_at(terrain, wg, xx.ravel(), yy.ravel())
        prof = wind_at_lonlat(wind, lon, lat, z, ground, profile, power_exponent)
        u, v, w = (np.moveaxis(prof[c].reshape(ny, nx, z.size), -1, 0) for c in ("u", "v", "w"))
        src = wind.attrs.get("source", "<dataset>")
    coords = {"z": xr.DataArray(z, dims="z", attrs={"units": "m", "long_name": "height above ground",
                                                    "positive": "up", "axis": "Z"}), **wg.coords()}
    ds = xr.Dataset({
        "u": (("z", "y", "x"), u, _ATTRS["u"]),
        "v": (("z", "y", "x"), v, _ATTRS["v"]),
        "w": (("z", "y", "x"), w, _ATTRS["w"]),
        "speed": (("z", "y", "x"), np.sqrt(u**2 + v**2 + w**2), _ATTRS["speed"]),
    }, coords=coords)
    ds.attrs = {"profile": profile, "power_exponent": float(power_exponent), "reference_height_m": Z_REF_M,
                "source": src, "direction_convention": "u east, v north, w up",
                "horizontal_step_m": wg.resolution_m}
    if uniform is None and "valid_time" in wind.attrs:
        ds.attrs["valid_time"] = wind.attrs["valid_time"]
    return ds.rio.write_crs(wg.crs)


def _terrain_at(terrain: xr.DataArray, wg: Grid, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    crs = terrain.rio.crs
    if crs is not None and Grid.from_dataarray(terrain).crs != wg.crs:
        raise CRSError(f"terrain CRS {crs} differs from the grid CRS {wg.crs.to_string()}: reproject it first")
    tg = Grid.from_dataarray(terrain)
    r, c = tg.cell_of(x, y)
    vals = np.asarray(terrain.values, dtype=float)[r, c]
    if not np.all(np.isfinite(vals)):
        raise InputError("terrain has no data (NaN) under the wind grid: fill it before sampling the wind")
    return vals


def sample_wind(wind_map: xr.Dataset, x, y, z) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, w) [m/s] of a :func:`wind_on_grid` map at map points (x, y) [m] and heights above
    ground z [m] (arrays broadcast together): nearest column, linear in height (clamped at the
    lowest and highest level)."""
    x, y, z = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float), np.asarray(z, float))
    g = Grid.from_dataarray(wind_map)
    r, c = g.cell_of(x, y)
    w4 = np.stack([np.asarray(wind_map[name].values, float) for name in ("u", "v", "w")], axis=-1)
    out = wind_in_column(w4, wind_map["z"].values, r, c, z)
    return out[..., 0], out[..., 1], out[..., 2]


def wind_in_column(w4: np.ndarray, z_levels_m: np.ndarray, row, col, z_agl_m) -> np.ndarray:
    """Wind (..., 3) [m/s] from levels ``w4`` (nz, ny, nx, 3) on heights above ground
    ``z_levels_m`` (nz,) [m]: the column (row, col), linear in the height above ground
    ``z_agl_m`` [m], clamped at the lowest and highest level (the one home of this rule; the
    planner's compiled kernel follows it and is tested against it)."""
    zl = np.asarray(z_levels_m, float)
    z = np.asarray(z_agl_m, float)
    if zl.size == 1:
        return w4[0, row, col, :].copy()
    k0 = np.clip(np.searchsorted(zl, z, side="right") - 1, 0, zl.size - 2)
    f = np.clip((z - zl[k0]) / (zl[k0 + 1] - zl[k0]), 0.0, 1.0)[..., None]
    return w4[k0, row, col, :] * (1 - f) + w4[k0 + 1, row, col, :] * f


def wind_nofly(wind_map: xr.Dataset | xr.DataArray, max_wind_mps: float) -> xr.DataArray:
    """True where the wind speed exceeds ``max_wind_mps`` [m/s] (seed 000: excessive-wind areas
    are not flyable); same dims/coords as the speed."""
    if not (np.isfinite(max_wind_mps) and max_wind_mps > 0):
        raise InputError(f"max_wind_mps {max_wind_mps} must be a positive speed in m/s (e.g. 15)")
    speed = wind_map["speed"] if isinstance(wind_map, xr.Dataset) else wind_map
    mask = speed > max_wind_mps
    mask.name = "wind_nofly"
    mask.attrs = {"long_name": f"wind speed above {max_wind_mps} m/s", "max_wind_mps": float(max_wind_mps)}
    return mask
