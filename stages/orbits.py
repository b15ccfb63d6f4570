"""GNSS orbit propagation: GPS time, Keplerian/broadcast orbits to ECEF, ECEF -> local ENU az/el.

Conventions
-----------
* Times are **UTC** ``datetime64[ns]`` at the edges (the ``time`` coordinate) and **GPS time**
  inside (integer nanoseconds since the GPS epoch 1980-01-06T00:00:00).  GPS - UTC comes from a
  table of leap seconds (:data:`LEAP_SECONDS`, 18 s since 2017-01-01; no leap second has been
  announced up to the time of writing, so 18 s is assumed after that).
* Orbital elements are an ``xarray.Dataset`` from :mod:`skyroute.stages.almanac`: dim ``sat``
  (one element set per satellite, almanacs) or dims ``(sat, rec)`` (several broadcast
  ephemeris records per satellite, the one nearest in time is used).  Almanacs carry zero
  harmonic corrections, so one propagator (IS-GPS-200 Table 20-IV) serves both.
* ECEF is the Earth-fixed WGS 84 frame at the epoch of each position [m].  Azimuth is clockwise
  from north [deg, 0..360), elevation above the local ellipsoidal horizon [deg].  The Earth
  rotation during the signal travel time (Sagnac, < 0.001 deg in az/el) is not applied.
"""

from __future__ import annotations

import datetime as _dt
import math
import warnings
from typing import Any

import numpy as np
import xarray as xr

from skyroute.stages.base import InputError

#: GPS epoch (UTC = GPS time at this instant).
GPS_EPOCH = np.datetime64("1980-01-06T00:00:00", "ns")
SECONDS_PER_WEEK = 604800
_NS = 1_000_000_000

#: (UTC instant from which it applies, GPS - UTC [s]).  Source: IERS Bulletin C / USNO.
LEAP_SECONDS: tuple[tuple[str, int], ...] = (
    ("1980-01-06", 0), ("1981-07-01", 1), ("1982-07-01", 2), ("1983-07-01", 3),
    ("1985-07-01", 4), ("1988-01-01", 5), ("1990-01-01", 6), ("1991-01-01", 7),
    ("1992-07-01", 8), ("1993-07-01", 9), ("1994-07-01", 10), ("1996-01-01", 11),
    ("1997-07-01", 12), ("1999-01-01", 13), ("2006-01-01", 14), ("2009-01-01", 15),
    ("2012-07-01", 16), ("2015-07-01", 17), ("2017-01-01", 18),
)
_LEAP_T = np.array([np.datetime64(d, "ns") for d, _ in LEAP_SECONDS])
_LEAP_S = np.array([s for _, s in LEAP_SECONDS], dtype=np.int64)

#: Per-system constants: (mu [m^3/s^2], Earth rotation rate [rad/s]) of each interface document.
SYSTEM_CONSTANTS: dict[str, tuple[float, float]] = {
    "G": (3.986005e14, 7.2921151467e-5),     # GPS, IS-GPS-200
    "J": (3.986005e14, 7.2921151467e-5),     # QZSS, IS-QZSS
    "E": (3.986004418e14, 7.2921151467e-5),  # Galileo, OS SIS ICD
    "C": (3.986004418e14, 7.292115e-5),      # BeiDou, BDS-SIS-ICD
    "I": (3.986005e14, 7.2921151467e-5),     # NavIC/IRNSS
}

#: WGS 84 ellipsoid.
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)

#: Age limits of element sets [s]: (warn beyond, refuse beyond), per element kind.
AGE_LIMITS_S = {
    "almanac": (7 * 86400.0, 30 * 86400.0),
    "ephemeris": (4 * 3600.0, 7 * 86400.0),   # IS-GPS-200 curve-fit interval is 4 h
}


# --------------------------------------------------------------------------------------------
# time
# --------------------------------------------------------------------------------------------

def as_utc_times(times_utc) -> np.ndarray:
    """1-D ``datetime64[ns]`` array from datetime64/str/datetime/pandas input (UTC, naive)."""
    try:
        if isinstance(times_utc, xr.DataArray):
            times_utc = times_utc.values
        arr = np.atleast_1d(np.asarray(times_utc))
        if arr.dtype.kind == "O" and arr.size and getattr(arr.flat[0], "tzinfo", None) is not None:
            arr = np.array([t.astimezone(_dt.UTC).replace(tzinfo=None)
                            for t in arr.ravel()]).reshape(arr.shape)
        out = arr.astype("datetime64[ns]").ravel()
    except (TypeError, ValueError) as exc:
        raise InputError(f"cannot read times {times_utc!r} as UTC datetimes: {exc}; "
                         "give ISO 8601 strings such as '2020-01-01T12:00:00' or datetime64") from exc
    if np.isnat(out).any():
        raise InputError("times contain NaT; give valid UTC datetimes")
    if (out < GPS_EPOCH).any():
        raise InputError(f"time {out.min()} is before the GPS epoch 1980-01-06; give a later time")
    return out


def gps_minus_utc_s(times_utc) -> np.ndarray:
    """GPS - UTC [s] (integer leap seconds) at UTC instants ``times_utc``."""
    t = np.asarray(times_utc, dtype="datetime64[ns]")
    idx = np.searchsorted(_LEAP_T, t, side="right") - 1
    return _LEAP_S[np.clip(idx, 0, None)]


def utc_to_gps_ns(times_utc) -> np.ndarray:
    """GPS time as int64 nanoseconds since the GPS epoch, from UTC ``datetime64``."""
    t = np.asarray(times_utc, dtype="datetime64[ns]")
    return (t - GPS_EPOCH).astype(np.int64) + gps_minus_utc_s(t) * _NS


def gps_ns_to_utc(gps_ns) -> np.ndarray:
    """UTC ``datetime64[ns]`` from GPS int64 nanoseconds since the GPS epoch."""
    g = np.asarray(gps_ns, dtype=np.int64)
    approx = GPS_EPOCH + g.astype("timedelta64[ns]")
    # the leap count at (GPS - leap) equals the one at UTC except within the leap second itself
    leap = gps_minus_utc_s(approx - gps_minus_utc_s(approx).astype("timedelta64[s]"))
    return approx - (leap * _NS).astype("timedelta64[ns]")


def gps_week_seconds(times_utc) -> tuple[np.ndarray, np.ndarray]:
    """(full GPS week, seconds of week [s]) of UTC instants."""
    g = utc_to_gps_ns(times_utc)
    week = g // (SECONDS_PER_WEEK * _NS)
    return week, (g - week * SECONDS_PER_WEEK * _NS) / _NS


# --------------------------------------------------------------------------------------------
# propagation
# --------------------------------------------------------------------------------------------

def solve_kepler(mean_anomaly_rad, e, tol_rad: float = 1e-12, max_iter: int = 30) -> np.ndarray:
    """Eccentric anomaly E [rad] with E - e sin E = M, Newton iteration to ``tol_rad``."""
    m = np.mod(np.asarray(mean_anomaly_rad, dtype=float) + np.pi, 2 * np.pi) - np.pi
    e = np.asarray(e, dtype=float)
    ecc = e + np.zeros_like(m)
    big = ecc > 0.8
    E = np.where(big, np.pi * np.sign(m), m + ecc * np.sin(m))
    for _ in range(max_iter):
        dE = (E - ecc * np.sin(E) - m) / (1.0 - ecc * np.cos(E))
        E = E - dE
        if not np.any(np.abs(dE) > tol_rad):  # NaN-safe: NaN elements do not keep iterating
            break
    return E


def kepler_to_ecef(tk_s, toe_s, sqrt_a, e, i0_rad, omega0_rad, omega_dot_rad_s, argp_rad, m0_rad,
                   delta_n_rad_s=0.0, idot_rad_s=0.0, cuc_rad=0.0, cus_rad=0.0, crc_m=0.0,
                   crs_m=0.0, cic_rad=0.0, cis_rad=0.0, mu=3.986005e14,
                   omega_e=7.2921151467e-5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ECEF position [m] of broadcast/almanac elements at ``tk_s`` [s] after the reference epoch.

    IS-GPS-200 Table 20-IV: mean motion, Kepler equation, second-harmonic corrections, and the
    Earth rotation term ``Omega = Omega0 + (Omega_dot - Omega_e) tk - Omega_e toe``.
    All arguments broadcast against each other.
    """
    a = np.square(sqrt_a)
    n = np.sqrt(mu / a**3) + delta_n_rad_s
    M = m0_rad + n * tk_s
    E = solve_kepler(M, e)
    nu = np.arctan2(np.sqrt(1.0 - e * e) * np.sin(E), np.cos(E) - e)
    phi = nu + argp_rad
    s2, c2 = np.sin(2 * phi), np.cos(2 * phi)
    u = phi + cus_rad * s2 + cuc_rad * c2
    r = a * (1.0 - e * np.cos(E)) + crs_m * s2 + crc_m * c2
    inc = i0_rad + cis_rad * s2 + cic_rad * c2 + idot_rad_s * tk_s
    xp, yp = r * np.cos(u), r * np.sin(u)
    om = omega0_rad + (omega_dot_rad_s - omega_e) * tk_s - omega_e * toe_s
    co, so, ci = np.cos(om), np.sin(om), np.cos(inc)
    return xp * co - yp * ci * so, xp * so + yp * ci * co, yp * np.sin(inc)


_ELEMENT_VARS = ("toe_s", "sqrt_a", "e", "i0_rad", "omega0_rad", "omega_dot_rad_s", "argp_rad",
                 "m0_rad", "delta_n_rad_s", "idot_rad_s", "cuc_rad", "cus_rad", "crc_m", "crs_m",
                 "cic_rad", "cis_rad")


def _fmt_age(seconds: float) -> str:
    return f"{seconds / 3600:.1f} h" if seconds < 86400 else f"{seconds / 86400:.1f} days"


def _names(sats: np.ndarray, most: int = 8) -> str:
    s = ", ".join(sats[:most])
    return s + (f" and {len(sats) - most} more" if len(sats) > most else "")


def _check_age(age_s: np.ndarray, kinds: np.ndarray, sats: np.ndarray) -> None:
    """Warn / refuse when the query epoch is far from an element set's reference epoch."""
    for kind, (warn_s, refuse_s) in AGE_LIMITS_S.items():
        sel = kinds == kind
        if not sel.any():
            continue
        worst = np.where(sel, np.max(age_s, axis=0), -np.inf)  # per sat
        bad = worst > refuse_s
        if bad.any():
            raise InputError(
                f"epoch is {_fmt_age(np.max(worst[bad]))} from the {kind}'s reference epoch "
                f"(satellites {_names(sats[bad])}); limit is {_fmt_age(refuse_s)}. "
                f"Use a {kind} closer to the requested times")
        old = worst > warn_s
        if old.any():
            warnings.warn(
                f"epoch is up to {_fmt_age(np.max(worst[old]))} from the {kind}'s reference "
                f"epoch for {_names(sats[old])} (accuracy degrades beyond {_fmt_age(warn_s)})",
                stacklevel=3)


def satellite_positions(elements: xr.Dataset, times_utc) -> xr.Dataset:
    """ECEF satellite positions [m] at UTC ``times_utc``, dims ``(time, sat)``.

    ``elements``: from :func:`~skyroute.stages.almanac.read_almanac` /
    :func:`~skyroute.stages.almanac.merge_almanacs` (dim ``sat``) or
    :func:`~skyroute.stages.almanac.read_rinex_nav` (dims ``sat, rec``: the record whose
    reference epoch is nearest to each time is used).  Warns when a time is more than 7 days
    (ephemeris: 4 h) from the reference epoch and raises :class:`InputError` beyond 30 days
    (ephemeris: 7 days); ``kind == "standard"`` constellations (idealised) are not age-checked.
    """
    if not isinstance(elements, xr.Dataset) or "sat" not in elements.dims:
        raise InputError("elements must be an xarray.Dataset with a 'sat' dim (use read_almanac)")
    missing = [v for v in (*_ELEMENT_VARS, "t_ref_gps_s", "system", "kind") if v not in elements]
    if missing:
        raise InputError(f"elements lack variables {missing}; build them with read_almanac")
    times = as_utc_times(times_utc)
    t_ns = utc_to_gps_ns(times)                           # (T,)
    el = elements.transpose("sat", ...)
    sats = el["sat"].values.astype(str)
    if "rec" in el.dims:
        tref = el["t_ref_gps_s"].values                   # (S, R), NaN padded
        tref_ns = np.where(np.isfinite(tref), np.round(np.nan_to_num(tref) * _NS), np.nan)
        dist = np.abs(t_ns[:, None, None] - tref_ns[None, :, :])   # (T, S, R)
        dist = np.where(np.isfinite(dist), dist, np.inf)
        idx = np.argmin(dist, axis=2)                     # (T, S)
        cols = np.arange(len(sats))[None, :]
        arrays = {v: el[v].values[cols, idx] for v in (*_ELEMENT_VARS, "t_ref_gps_s")}
    else:
        arrays = {v: el[v].values[None, :] for v in (*_ELEMENT_VARS, "t_ref_gps_s")}
    tref_ns = np.round(arrays.pop("t_ref_gps_s") * _NS).astype(np.int64)
    tk = (t_ns[:, None] - tref_ns) / _NS                  # (T, S) [s], exact integer ns difference
    _check_age(np.abs(tk), el["kind"].values.astype(str), sats)
    system = el["system"].values.astype(str)
    try:
        consts = np.array([SYSTEM_CONSTANTS[s] for s in system]).reshape(-1, 2)
    except KeyError as exc:
        raise InputError(f"no orbit constants for system {exc}; known: {sorted(SYSTEM_CONSTANTS)}") from None
    x, y, z = kepler_to_ecef(tk, **arrays, mu=consts[:, 0], omega_e=consts[:, 1])
    attrs = {"units": "m", "frame": "ECEF WGS 84, Earth-fixed at each epoch"}
    ds = xr.Dataset(
        {"x_ecef": (("time", "sat"), x, {**attrs, "long_name": "satellite ECEF X"}),
         "y_ecef": (("time", "sat"), y, {**attrs, "long_name": "satellite ECEF Y"}),
         "z_ecef": (("time", "sat"), z, {**attrs, "long_name": "satellite ECEF Z"}),
         "age_s": (("time", "sat"), tk, {"units": "s",
                                         "long_name": "time since the element set's reference epoch"})},
        coords={"time": ("time", times, {"long_name": "time (UTC)"}),
                "sat": sats, "system": ("sat", system)},
        attrs={"source": elements.attrs.get("source", ""),
               "time_scale": "coordinate 'time' is UTC; propagation in GPS time"},
    )
    return ds


# --------------------------------------------------------------------------------------------
# local frame
# --------------------------------------------------------------------------------------------

def _check_site(lat_deg: float, lon_deg: float, height_m: float) -> None:
    if not (np.isfinite(lat_deg) and -90.0 <= lat_deg <= 90.0):
        raise InputError(f"latitude {lat_deg} deg is outside -90..90")
    if not (np.isfinite(lon_deg) and -180.0 <= lon_deg <= 360.0):
        raise InputError(f"longitude {lon_deg} deg is outside -180..360")
    if not (np.isfinite(height_m) and -1000.0 <= height_m <= 100_000.0):
        raise InputError(f"height {height_m} m (ellipsoidal) is outside -1000..100000 m")


def geodetic_to_ecef(lat_deg, lon_deg, height_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """WGS 84 geodetic latitude/longitude [deg] and ellipsoidal height [m] to ECEF [m]."""
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    return ((n + height_m) * np.cos(lat) * np.cos(lon), (n + height_m) * np.cos(lat) * np.sin(lon),
            (n * (1.0 - WGS84_E2) + height_m) * np.sin(lat))


def enu_rotation(lat_deg: float, lon_deg: float) -> np.ndarray:
    """3x3 matrix whose rows are the local east, north, up unit vectors in ECEF."""
    la, lo = np.radians(lat_deg), np.radians(lon_deg)
    return np.array([[-np.sin(lo), np.cos(lo), 0.0],
                     [-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)],
                     [np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)]])


def satellite_azel(positions: xr.Dataset, lat_deg: float, lon_deg: float,
                   height_m: float = 0.0) -> xr.Dataset:
    """Azimuth/elevation [deg] and unit ENU line-of-sight of each satellite from a ground point.

    ``positions``: from :func:`satellite_positions`.  The point is geodetic WGS 84
    (``lat_deg``, ``lon_deg`` [deg], ellipsoidal ``height_m`` [m]).  Returns variables
    ``az_deg``, ``el_deg``, ``range_m`` (time, sat) and ``los_enu`` (time, sat, enu).
    """
    _check_site(float(lat_deg), float(lon_deg), float(height_m))
    for v in ("x_ecef", "y_ecef", "z_ecef"):
        if v not in positions:
            raise InputError(f"positions lack {v!r}; compute them with satellite_positions")
    rx = np.array(geodetic_to_ecef(lat_deg, lon_deg, height_m))
    d = np.stack([positions[v].values for v in ("x_ecef", "y_ecef", "z_ecef")], axis=-1) - rx
    enu = d @ enu_rotation(lat_deg, lon_deg).T
    rng = np.linalg.norm(enu, axis=-1)
    los = enu / rng[..., None]
    az = np.degrees(np.arctan2(los[..., 0], los[..., 1])) % 360.0
    el = np.degrees(np.arcsin(np.clip(los[..., 2], -1.0, 1.0)))
    dims = positions["x_ecef"].dims
    coords = {k: v for k, v in positions.coords.items()}
    return xr.Dataset(
        {"az_deg": (dims, az, {"units": "deg", "long_name": "azimuth, clockwise from north"}),
         "el_deg": (dims, el, {"units": "deg", "long_name": "elevation above the ellipsoidal horizon"}),
         "range_m": (dims, rng, {"units": "m", "long_name": "geometric range"}),
         "los_enu": ((*dims, "enu"), los, {"units": "1", "long_name": "unit line of sight, local ENU"})},
        coords={**coords, "enu": ["e", "n", "u"]},
        attrs={"site_lat_deg": float(lat_deg), "site_lon_deg": float(lon_deg),
               "site_height_m": float(height_m)},
    )


def check_mask(mask_deg: float) -> float:
    """The elevation mask [deg], validated to 0..60."""
    try:
        m = float(mask_deg)
    except (TypeError, ValueError):
        raise InputError(f"elevation mask {mask_deg!r} is not a number; give degrees 0..60") from None
    if not (0.0 <= m <= 60.0):
        raise InputError(f"elevation mask {mask_deg} deg is outside 0..60 deg (typical: 5, 10, 15)")
    return m


# ------------------------------------------------------------------------------ epochs

def window_times(start_utc: Any, window_min: float = 20.0, step_min: float = 1.0) -> np.ndarray:
    """Epochs [datetime64[s], UTC] of a time window: ``start``, ``start + step``, ... up to and
    including ``start + window`` (default 20 min at every whole minute = 21 epochs; the
    coverage floor is only claimed at the epochs: benchmarks/bench_coverage.py measures the
    cost of 1 min vs seed 001's 5 min)."""
    if not (step_min > 0 and window_min >= 0):
        raise InputError(f"need step_min > 0 and window_min >= 0, got {step_min}, {window_min}")
    start = np.datetime64(np.datetime64(start_utc, "s"))
    n = int(math.floor(window_min / step_min + 1e-9)) + 1
    return start + (np.arange(n) * step_min * 60.0).astype("timedelta64[s]")


def as_time_sat(az_deg: Any, el_deg: Any) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Validated (time, sat) azimuth/elevation [deg] float64 arrays and ``{"time": values}``
    when ``az_deg`` is a DataArray with a ``time`` dim (transposed to (time, sat) if it has a
    ``sat`` dim); a 1D input is one epoch.  NaN marks an absent satellite."""
    meta: dict[str, Any] = {}
    if isinstance(az_deg, xr.DataArray) and "time" in az_deg.dims:
        meta["time"] = az_deg["time"].values if "time" in az_deg.coords else None
        if "sat" in az_deg.dims:
            az_deg = az_deg.transpose("time", "sat")
            if isinstance(el_deg, xr.DataArray) and "sat" in el_deg.dims:
                el_deg = el_deg.transpose("time", "sat")
    az = np.asarray(az_deg, dtype=np.float64)
    el = np.asarray(el_deg, dtype=np.float64)
    if az.shape != el.shape:
        raise InputError(f"azimuth shape {az.shape} and elevation shape {el.shape} differ: "
                         "give both as (time, sat) arrays of the same satellites")
    if az.ndim == 1:
        az, el = az[None, :], el[None, :]
    if az.ndim != 2 or az.shape[0] == 0 or az.shape[1] == 0:
        raise InputError(f"azimuth/elevation must be (time, sat) arrays, got shape {az.shape}")
    if np.any(np.abs(el[np.isfinite(el)]) > 90.0):
        raise InputError("elevations must be in [-90, 90] deg; did you pass radians or swap az/el?")
    return az, el, meta


def epoch_directions(az_deg: np.ndarray, el_deg: np.ndarray, mask_deg: float
                     ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per epoch (row of the (time, sat) arrays), the (az, el) [deg] of the satellites at or
    above the mask and above the horizon, in satellite order."""
    out = []
    for t in range(az_deg.shape[0]):
        ok = (np.isfinite(az_deg[t]) & np.isfinite(el_deg[t]) & (el_deg[t] >= mask_deg)
              & (el_deg[t] > 0.0))
        out.append((az_deg[t, ok], el_deg[t, ok]))
    return out
