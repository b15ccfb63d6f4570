"""GNSS almanac and broadcast-ephemeris readers (YUMA, SEM, RINEX 2/3 navigation) to xarray.

Every reader returns orbital elements as an ``xarray.Dataset`` with dim ``sat`` (string ids
with the RINEX system letter: ``"G01"``, ``"E07"``), SI/radian units in each variable's
``units`` attribute, and ``attrs`` ``source`` (file), ``format`` and ``units``.  Almanacs have
zero harmonic corrections (``cuc_rad`` ... ``cis_rad``, ``delta_n_rad_s``, ``idot_rad_s``) so
that one propagator (:func:`skyroute.stages.orbits.satellite_positions`) serves almanacs and
broadcast ephemerides alike.

* ``kind`` (per satellite): ``"almanac"``, ``"ephemeris"`` or ``"standard"`` (idealised
  constellations such as EUROCAE ED-259: eccentricity and argument of perigee exactly 0; they
  are not age-checked).
* GPS weeks in YUMA/SEM are modulo 1024: :func:`resolve_gps_week` picks the latest full week
  that is not more than one year after ``reference_date`` (default: today).
* Unhealthy satellites (health != 0) are dropped with a ``warnings.warn`` naming them.
* Malformed files raise :class:`~skyroute.stages.base.DataError` naming file and line.
* Every file is read through :func:`~skyroute.stages.base.read_limited`: at most
  :data:`MAX_ALMANAC_BYTES` (64 MB; a day of mixed RINEX 3 navigation is a few MB), a FIFO or
  device (``/dev/urandom``) is refused before it is read.
* Every record is checked (:func:`check_elements`) before it is used: finite values, a
  plausible GNSS orbit -- semi-major axis A = sqrt(A)^2 in 10,000..50,000 km (MEO 25,500-29,600
  km, IGSO/GEO 42,164 km), eccentricity in [0, 1) with the perigee A (1 - e) above the Earth's
  surface (a counted warning above :data:`E_WARN` = 0.2: GPS < 0.03, the eccentric Galileo E14/E18
  0.16), inclination in [0, pi] rad, angles within [-2 pi, 2 pi] rad, rates (node rate, delta
  n, di/dt) within 1e-6 rad/s, seconds of week in [0, 604800] s, week numbers integers in
  0..5000 (up to 2075), health and PRN non-negative integers (PRN 1..99).  A value outside is
  one DataError naming the file, line, satellite and field.
"""

from __future__ import annotations

import datetime as _dt
import re
import warnings
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
import xarray as xr

from skyroute.stages.base import DataError, InputError, read_limited
from skyroute.stages.orbits import (
    GPS_EPOCH,
    SECONDS_PER_WEEK,
    SYSTEM_CONSTANTS,
    as_utc_times,
    check_mask,
    gps_ns_to_utc,
    gps_week_seconds,
    satellite_azel,
    satellite_positions,
)

#: pi as defined by IS-GPS-200 for semicircle conversions.
GPS_PI = 3.1415926535898
#: SEM inclination reference [semicircles] (the file stores i0 - 0.30 semicircles).
SEM_I_REF = 0.30

_UNITS = {
    "toe_s": "s", "t_ref_gps_s": "s", "sqrt_a": "m0.5", "e": "1", "i0_rad": "rad",
    "omega0_rad": "rad", "omega_dot_rad_s": "rad s-1", "argp_rad": "rad", "m0_rad": "rad",
    "delta_n_rad_s": "rad s-1", "idot_rad_s": "rad s-1", "cuc_rad": "rad", "cus_rad": "rad",
    "crc_m": "m", "crs_m": "m", "cic_rad": "rad", "cis_rad": "rad", "af0_s": "s", "af1_s_s": "s s-1",
    "week": "1", "prn": "1", "health": "1",
}
_LONG = {
    "toe_s": "reference epoch (time of applicability / ephemeris), seconds of week",
    "t_ref_gps_s": "reference epoch, GPS seconds since 1980-01-06",
    "t_ref": "reference epoch (UTC)", "sqrt_a": "square root of semi-major axis",
    "omega0_rad": "longitude of ascending node at weekly epoch",
    "week": "full GPS week of the reference epoch",
}
_HARMONIC = ("delta_n_rad_s", "idot_rad_s", "cuc_rad", "cus_rad", "crc_m", "crs_m", "cic_rad", "cis_rad")
_DS_UNITS = "SI: m, s, rad (per-variable 'units' attributes)"


MAX_ALMANAC_BYTES = 64 * 1024 * 1024
"""The largest almanac / RINEX navigation file read [bytes]."""
E_WARN = 0.2
"""Eccentricity above which a record is kept with a warning (unusual for a GNSS orbit)."""
_A_MIN_M, _A_MAX_M = 10.0e6, 50.0e6        # plausible GNSS semi-major axes [m]
_EARTH_RADIUS_M = 6_378_137.0               # WGS 84 equatorial radius [m]
_MAX_RATE_RAD_S = 1.0e-6                    # |node rate|, |delta n|, |di/dt| [rad/s]
_MAX_WEEK = 5000                            # a full GPS week in 2075
_TWO_PI = 2.0 * np.pi + 1e-9
# (record key, name in messages, lower bound, upper bound, units): a closed range [lo, hi]
_RANGES = (
    ("i0_rad", "inclination", 0.0, np.pi + 1e-9, "rad"),
    ("omega0_rad", "longitude of the ascending node", -_TWO_PI, _TWO_PI, "rad"),
    ("omega_toa_rad", "right ascension at TOA", -_TWO_PI, _TWO_PI, "rad"),
    ("argp_rad", "argument of perigee", -_TWO_PI, _TWO_PI, "rad"),
    ("m0_rad", "mean anomaly", -_TWO_PI, _TWO_PI, "rad"),
    ("omega_dot_rad_s", "rate of right ascension", -_MAX_RATE_RAD_S, _MAX_RATE_RAD_S, "rad/s"),
    ("delta_n_rad_s", "mean motion difference delta n", -_MAX_RATE_RAD_S, _MAX_RATE_RAD_S, "rad/s"),
    ("idot_rad_s", "rate of inclination", -_MAX_RATE_RAD_S, _MAX_RATE_RAD_S, "rad/s"),
    ("toe_s", "time of applicability / ephemeris", 0.0, float(SECONDS_PER_WEEK), "s of week"),
    ("crs_m", "radius correction crs", -1.0e4, 1.0e4, "m"),
    ("crc_m", "radius correction crc", -1.0e4, 1.0e4, "m"),
    ("cuc_rad", "latitude correction cuc", -0.1, 0.1, "rad"),
    ("cus_rad", "latitude correction cus", -0.1, 0.1, "rad"),
    ("cic_rad", "inclination correction cic", -0.1, 0.1, "rad"),
    ("cis_rad", "inclination correction cis", -0.1, 0.1, "rad"),
)


def _path_text(path: str | Path) -> str:
    return str(path)


def _number_text(v: float | int) -> str:
    """``v`` for a message: ``%g`` for a float, at most 20 digits of an int (a 400-digit PRN read
    from a header cannot be converted to float for ``%g``)."""
    if isinstance(v, int):
        t = str(v)
        return t if len(t) <= 20 else t[:20] + "..."
    return f"{v:g}"


def check_elements(rec: dict, path: str, lines: dict[str, int] | int, sat: str | None = None) -> None:
    """Refuse a record whose orbital elements cannot be a GNSS orbit (see the module docstring).

    ``rec``: the record's elements (keys as in the Datasets: ``sqrt_a``, ``e``, ``i0_rad`` ...;
    ``week``, ``health``, ``prn`` as read, before any week resolution); ``lines``: the line of
    each key in the file (or one line for all); ``sat``: the satellite's name in messages.
    Raises one :class:`DataError` ``path:line: satellite: field ... (the limit)``; warns
    (``warnings.warn``, counted in a run's warnings) for an eccentricity above :data:`E_WARN`.
    """
    who = sat or (f"PRN {_number_text(rec['prn'])}" if isinstance(rec.get("prn"), int | float) else "record")

    def line(key: str) -> int:
        return lines if isinstance(lines, int) else lines.get(key, min(lines.values(), default=0))

    def bad(key: str, what: str) -> DataError:
        return DataError(f"{path}:{line(key)}: {who}: {what}; the almanac is corrupt or not a GNSS almanac "
                         "(fix or replace the file)")

    for key, v in rec.items():
        if isinstance(v, float) and not np.isfinite(v) and key not in ("line",):
            raise bad(key, f"{key} is not a finite number ({v})")
    if "prn" in rec:
        prn = rec["prn"]
        if not (1 <= prn <= 99 and float(prn) == int(prn)):   # the range first: a 400-digit int has no float
            raise bad("prn", f"satellite number (PRN) {_number_text(prn)} is not an integer in 1..99")
    if "health" in rec:
        h = rec["health"]
        if not (float(h) == int(h) and h >= 0):
            raise bad("health", f"health {h:g} is not a non-negative integer (0 = healthy)")
    if "week" in rec:
        w = rec["week"]
        if not (float(w) == int(w) and 0 <= w <= _MAX_WEEK):
            raise bad("week", f"week number {w:g} is not an integer in 0..{_MAX_WEEK}")
    sqrt_a = float(rec["sqrt_a"])
    lo, hi = np.sqrt(_A_MIN_M), np.sqrt(_A_MAX_M)
    if not lo <= sqrt_a <= hi:
        # A = sqrt(A)^2 only where it is a number (1e300 ** 2 overflows: OverflowError)
        a_km = f"{sqrt_a * sqrt_a / 1e3:,.0f} km" if abs(sqrt_a) < 1e100 else "over 1e197 km"
        raise bad("sqrt_a", f"sqrt(A) {sqrt_a:g} m^0.5 (semi-major axis {a_km}) is outside "
                            f"{lo:.1f}..{hi:.1f} m^0.5 (A = {_A_MIN_M / 1e3:,.0f}..{_A_MAX_M / 1e3:,.0f} km: "
                            "GNSS orbits are 25,500..42,164 km)")
    e = float(rec["e"])
    if not 0.0 <= e < 1.0:
        raise bad("e", f"eccentricity {e:g} is not in [0, 1) (an ellipse; GPS orbits have e < 0.03)")
    perigee = sqrt_a * sqrt_a * (1.0 - e)      # sqrt_a within lo..hi: no overflow
    if perigee <= _EARTH_RADIUS_M:
        raise bad("e", f"eccentricity {e:g} puts the perigee A (1 - e) = {perigee / 1e3:,.0f} km inside the Earth "
                       f"(radius {_EARTH_RADIUS_M / 1e3:,.0f} km)")
    for key, name, vlo, vhi, units in _RANGES:
        if key in rec and not vlo <= float(rec[key]) <= vhi:
            raise bad(key, f"{name} ({key}) {float(rec[key]):g} {units} is outside {vlo:.6g}..{vhi:.6g} {units}")
    if e > E_WARN:
        warnings.warn(f"{path}:{line('e')}: {who}: eccentricity {e:g} is unusual for a GNSS orbit (GPS < 0.03, "
                      f"Galileo E14/E18 0.16); check the almanac", stacklevel=3)


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------

def resolve_gps_week(week: int, reference_date=None) -> int:
    """Full GPS week from a week number that may be modulo 1024.

    Weeks >= 1024 are taken as full.  Otherwise the latest ``week + k * 1024`` that is not more
    than 52 weeks after ``reference_date`` (UTC; default: today) is chosen, so a reference date
    from one year before to ~18 years after the almanac resolves it correctly.
    """
    week = int(week)
    if week < 0:
        raise InputError(f"GPS week {week} is negative")
    if week >= 1024:
        return week
    ref = _dt.datetime.now(_dt.UTC).replace(tzinfo=None) if reference_date is None else reference_date
    ref_week = int(gps_week_seconds(as_utc_times(ref))[0][0])
    k = (ref_week + 52 - week) // 1024
    return week + 1024 * max(k, 0)


def infer_system(sqrt_a_m05: np.ndarray) -> str:
    """System letter from the orbit size (GPS a = 26560 km, Galileo 29600 km, BeiDou MEO 27906 km)."""
    med = float(np.nanmedian(sqrt_a_m05))
    for letter, nominal in (("G", 5153.7), ("E", 5440.6), ("C", 5282.6)):
        if abs(med - nominal) < 30.0:
            return letter
    raise InputError(f"cannot infer the constellation from sqrt(A) = {med:.1f} m^0.5; "
                     "pass system='G' (GPS), 'E' (Galileo), 'C' (BeiDou) ...")


def _float(text: str, path: str, lineno: int, what: str) -> float:
    try:
        v = float(text.strip().replace("D", "E").replace("d", "e"))
    except ValueError:
        raise DataError(f"{path}:{lineno}: cannot read {what} from {text.strip()!r}; "
                        "the file is corrupt or not in the expected format") from None
    if not np.isfinite(v):
        raise DataError(f"{path}:{lineno}: {what} is not finite ({text.strip()!r})")
    return v


def _warn_unhealthy(records: list[dict], path: str) -> list[dict]:
    bad = [r["sat"] for r in records if r["health"] != 0]
    if bad:
        warnings.warn(f"{path}: unhealthy satellites excluded (health != 0): {', '.join(bad)}",
                      stacklevel=3)
    return [r for r in records if r["health"] == 0]


def _finish(records: list[dict], path: str, fmt: str, kind: str | None) -> xr.Dataset:
    """Dataset (dim sat) from per-satellite dicts of elements (week already full)."""
    if not records:
        raise DataError(f"{path}: no healthy satellite records found")
    sats = [r["sat"] for r in records]
    dup = sorted({s for s in sats if sats.count(s) > 1})
    if dup:
        raise DataError(f"{path}: satellites listed twice: {', '.join(dup)}")
    for r in records:
        for h in _HARMONIC:
            r.setdefault(h, 0.0)
        r["t_ref_gps_s"] = r["week"] * float(SECONDS_PER_WEEK) + r["toe_s"]
    if kind is None:
        e = np.array([r["e"] for r in records])
        w = np.array([r["argp_rad"] for r in records])
        kind = "standard" if np.all(e == 0.0) and np.all(w == 0.0) else "almanac"
    names = [k for k in records[0] if k not in ("sat", "system")]
    data = {k: ("sat", np.array([r[k] for r in records])) for k in names}
    ds = xr.Dataset(data, coords={"sat": np.array(sats, dtype=str),
                                  "system": ("sat", np.array([r["system"] for r in records], dtype=str))})
    ds["kind"] = ("sat", np.full(len(sats), kind))
    ds["t_ref"] = ("sat", gps_ns_to_utc(np.round(ds["t_ref_gps_s"].values * 1e9).astype(np.int64)))
    _attrs(ds)
    ds.attrs = {"source": path, "format": fmt, "units": _DS_UNITS,
                "time_scale": "t_ref is UTC; toe_s, t_ref_gps_s are GPS time"}
    return ds.sortby("sat")


def _attrs(ds: xr.Dataset) -> None:
    for v in ds.data_vars:
        if v in _UNITS:
            ds[v].attrs["units"] = _UNITS[v]
        if v in _LONG:
            ds[v].attrs["long_name"] = _LONG[v]


# --------------------------------------------------------------------------------------------
# YUMA
# --------------------------------------------------------------------------------------------

_YUMA_KEYS = (  # (prefix of the lower-cased field name, record key)
    ("id", "id"), ("health", "health"), ("eccentricity", "e"),
    ("time of applicability", "toe_s"), ("orbital inclination", "i0_rad"),
    ("rate of right ascen", "omega_dot_rad_s"), ("sqrt(a)", "sqrt_a"),
    ("right ascen at week", "omega0_rad"), ("right ascen at toa", "omega_toa_rad"),
    ("argument of perigee", "argp_rad"), ("mean anom", "m0_rad"), ("af0", "af0_s"),
    ("af1", "af1_s_s"), ("week", "week"),
)
_YUMA_REQUIRED = ("health", "e", "toe_s", "i0_rad", "omega_dot_rad_s", "sqrt_a", "argp_rad",
                  "m0_rad", "af0_s", "af1_s_s", "week")
_YUMA_HEAD = re.compile(r"almanac\s+for\s+(?:PRN|SVID|SV)\s*-?\s*(\d+)", re.IGNORECASE)


def parse_yuma(text: str, path: str = "<yuma>", reference_date=None, system: str | None = None,
               kind: str | None = None) -> xr.Dataset:
    """Elements from YUMA almanac text (``Right Ascen at Week`` or ``... at TOA`` variants)."""
    blocks: list[tuple[int, int | None, dict, dict]] = []   # (header line, prn, values, value lines)
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("*"):
            m = _YUMA_HEAD.search(line)
            blocks.append((lineno, int(m.group(1)) if m else None, {}, {}))
            continue
        if ":" not in line or not blocks:
            raise DataError(f"{path}:{lineno}: unexpected line {line[:40]!r} in a YUMA almanac "
                            "(expected '******** Week ... almanac for PRN-nn' or 'Field: value')")
        name, value = line.split(":", 1)
        name = name.strip().lower()
        key = next((k for p, k in _YUMA_KEYS if name.startswith(p)), None)
        if key is None:
            raise DataError(f"{path}:{lineno}: unknown YUMA field {name!r}")
        blocks[-1][2][key] = _float(value, path, lineno, name)
        blocks[-1][3][key] = lineno
    if not blocks:
        raise DataError(f"{path}: no YUMA almanac records found")
    records = []
    for head, prn, vals, lines in blocks:
        missing = [k for k in _YUMA_REQUIRED if k not in vals]
        if "omega0_rad" not in vals and "omega_toa_rad" not in vals:
            missing.append("right ascen")
        if prn is None and "id" not in vals:
            missing.append("id")
        if missing:
            raise DataError(f"{path}:{head}: YUMA record starting here is incomplete or truncated "
                            f"(missing {', '.join(missing)})")
        number = prn if prn is not None else vals["id"]
        lines.setdefault("prn", lines.get("id", head))
        check_elements({**vals, "prn": number}, path, lines, f"PRN {_number_text(number)}")
        vals["prn"] = int(number)
        vals["health"] = int(vals["health"])
        vals["week"] = int(vals["week"])
        records.append(vals)
    letter = system or infer_system(np.array([r["sqrt_a"] for r in records]))
    out = []
    for r in records:
        week = resolve_gps_week(r["week"], reference_date)
        rec = {"sat": f"{letter}{r['prn']:02d}", "system": letter, "prn": r["prn"],
               "health": r["health"], "week": week, "toe_s": r["toe_s"], "sqrt_a": r["sqrt_a"],
               "e": r["e"], "i0_rad": r["i0_rad"], "omega_dot_rad_s": r["omega_dot_rad_s"],
               "argp_rad": r["argp_rad"], "m0_rad": r["m0_rad"], "af0_s": r["af0_s"],
               "af1_s_s": r["af1_s_s"]}
        if "omega0_rad" in r:
            rec["omega0_rad"] = r["omega0_rad"]
        else:  # node longitude given at toa: Omega(toa) = Omega0 - Omega_e * toa
            rec["omega0_rad"] = r["omega_toa_rad"] + SYSTEM_CONSTANTS[letter][1] * r["toe_s"]
        out.append(rec)
    return _finish(_warn_unhealthy(out, path), path, "YUMA", kind)


# --------------------------------------------------------------------------------------------
# SEM
# --------------------------------------------------------------------------------------------

def parse_sem(text: str, path: str = "<sem>", reference_date=None, system: str | None = "G",
              kind: str | None = None) -> xr.Dataset:
    """Elements from SEM almanac text (angles in semicircles, inclination offset from 0.30)."""
    lines = [(i, ln.split()) for i, ln in enumerate(text.splitlines(), start=1) if ln.strip()]
    if len(lines) < 2:
        raise DataError(f"{path}: too short for a SEM almanac (needs a count line and a week/toa line)")
    (l1, t1), (l2, t2) = lines[0], lines[1]
    n = _float(t1[0], path, l1, "number of records")
    if len(t2) < 2:
        raise DataError(f"{path}:{l2}: expected 'week toa' on the second line")
    week_read = _float(t2[0], path, l2, "week")
    toa = _float(t2[1], path, l2, "time of applicability")
    if not (week_read == int(week_read) and 0 <= week_read <= _MAX_WEEK):
        raise DataError(f"{path}:{l2}: week number {week_read:g} is not an integer in 0..{_MAX_WEEK}")
    if not 0.0 <= toa <= float(SECONDS_PER_WEEK):
        raise DataError(f"{path}:{l2}: time of applicability {toa:g} s is outside 0..{SECONDS_PER_WEEK} s of week")
    if not (n == int(n) and n >= 1):
        raise DataError(f"{path}:{l1}: the number of records {n:g} is not a positive integer")
    n = int(n)
    week = resolve_gps_week(int(week_read), reference_date)
    body = lines[2:]
    if len(body) < 8 * n:
        raise DataError(f"{path}:{body[-1][0] if body else l2}: SEM almanac truncated: header "
                        f"announces {n} records, only {len(body) // 8} complete")
    out = []
    for k in range(n):
        rec_lines = body[8 * k: 8 * k + 8]
        shape = [1, 1, 1, 3, 3, 3, 1, 1]
        for (ln, toks), want in zip(rec_lines, shape, strict=True):
            if len(toks) != want:
                raise DataError(f"{path}:{ln}: expected {want} value(s) in SEM record {k + 1}, "
                                f"found {len(toks)}: {' '.join(toks)[:60]!r}")
        v = [_float(t, path, ln, "SEM value") for ln, toks in rec_lines for t in toks]
        prn, _svn, _ura, e, di, odot, sqrt_a, om0, argp, m0, af0, af1, health, _cfg = v
        letter = system or "G"
        ln = [x[0] for x in rec_lines]
        check_elements({"prn": prn, "health": health, "sqrt_a": sqrt_a, "e": e, "i0_rad": (SEM_I_REF + di) * GPS_PI,
                        "omega_dot_rad_s": odot * GPS_PI, "omega0_rad": om0 * GPS_PI, "argp_rad": argp * GPS_PI,
                        "m0_rad": m0 * GPS_PI},
                       path, {"prn": ln[0], "e": ln[3], "i0_rad": ln[3], "omega_dot_rad_s": ln[3], "sqrt_a": ln[4],
                              "omega0_rad": ln[4], "argp_rad": ln[4], "m0_rad": ln[5], "health": ln[6]},
                       f"PRN {prn:g}")
        out.append({"sat": f"{letter}{int(prn):02d}", "system": letter, "prn": int(prn),
                    "health": int(health), "week": week, "toe_s": toa, "sqrt_a": sqrt_a, "e": e,
                    "i0_rad": (SEM_I_REF + di) * GPS_PI, "omega_dot_rad_s": odot * GPS_PI,
                    "argp_rad": argp * GPS_PI, "m0_rad": m0 * GPS_PI, "af0_s": af0,
                    "af1_s_s": af1, "omega0_rad": om0 * GPS_PI})
    return _finish(_warn_unhealthy(out, path), path, "SEM", kind)


# --------------------------------------------------------------------------------------------
# RINEX navigation
# --------------------------------------------------------------------------------------------

_KEPLER_SYSTEMS = ("G", "E", "J", "C", "I")
# value index in a RINEX navigation record -> element key (for the line of a refused value)
_RINEX_FIELDS = {0: "af0_s", 1: "af1_s_s", 4: "crs_m", 5: "delta_n_rad_s", 6: "m0_rad", 7: "cuc_rad", 8: "e",
                 9: "cus_rad", 10: "sqrt_a", 11: "toe_s", 12: "cic_rad", 13: "omega0_rad", 14: "cis_rad",
                 15: "i0_rad", 16: "crc_m", 17: "argp_rad", 18: "omega_dot_rad_s", 19: "idot_rad_s",
                 21: "week", 24: "health"}
_BDS_WEEK_OFFSET, _BDS_GPS_OFFSET_S = 1356, 14.0


def _rinex_values(line: str, starts: Sequence[int]) -> list[str]:
    line = line.rstrip("\n").ljust(starts[-1] + 19)
    return [line[s:s + 19] for s in starts]


def parse_rinex_nav(text: str, path: str = "<rinex>") -> list[dict]:
    """All Keplerian records of a RINEX 2 (GPS) or 3 (mixed) navigation file, as dicts."""
    lines = text.splitlines()
    if not lines or "RINEX VERSION / TYPE" not in lines[0]:
        raise DataError(f"{path}:1: not a RINEX file (no 'RINEX VERSION / TYPE' header line)")
    version = _float(lines[0][:9], path, 1, "RINEX version")
    ftype = lines[0][20:21].upper()
    if ftype != "N" and not (version < 3 and ftype in "E"):
        raise DataError(f"{path}:1: RINEX file type {ftype!r} is not a (Keplerian) navigation file; "
                        "give a GPS/mixed navigation file (type N)")
    try:
        end = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln)
    except StopIteration:
        raise DataError(f"{path}: RINEX header has no 'END OF HEADER' line (truncated?)") from None
    v3 = version >= 3
    first_starts = (23, 42, 61) if v3 else (22, 41, 60)
    cont_starts = (4, 23, 42, 61) if v3 else (3, 22, 41, 60)
    default_sys = "E" if (not v3 and ftype == "E") else "G"
    records: list[dict] = []
    i = end + 1
    while i < len(lines):
        head = lines[i]
        lineno = i + 1
        if not head.strip():
            i += 1
            continue
        if v3:
            letter = head[0].upper()
            if not head[0].isalpha():
                raise DataError(f"{path}:{lineno}: expected a record header 'Snn yyyy mm dd ...', "
                                f"found {head[:30]!r}")
            if letter not in _KEPLER_SYSTEMS:    # GLONASS/SBAS state vectors: skip record
                i += 1
                while i < len(lines) and lines[i][:1] == " ":
                    i += 1
                continue
            prn_text = head[1:3]
        else:
            letter, prn_text = default_sys, head[0:2]
        try:
            prn = int(prn_text)
        except ValueError:
            raise DataError(f"{path}:{lineno}: cannot read the satellite number from {head[:30]!r}; "
                            "the record is corrupt or misaligned") from None
        if i + 8 > len(lines):
            raise DataError(f"{path}:{lineno}: navigation record of {letter}{prn:02d} is truncated "
                            f"(needs 8 lines, {len(lines) - i} left)")
        raw = [(lineno, t) for t in _rinex_values(head, first_starts)]
        for k in range(1, 8):
            cont = lines[i + k]
            if v3 and cont[:1].isalpha():
                raise DataError(f"{path}:{i + k + 1}: navigation record of {letter}{prn:02d} "
                                f"starting at line {lineno} is truncated")
            raw += [(i + k + 1, t) for t in _rinex_values(cont, cont_starts)]
        vals = []
        for j, (ln, t) in enumerate(raw):
            if not t.strip():
                if j < 20 or j in (21, 24):
                    raise DataError(f"{path}:{ln}: missing value {j} of {letter}{prn:02d} record "
                                    f"starting at line {lineno}")
                vals.append(np.nan)
            else:
                vals.append(_float(t, path, ln, f"{letter}{prn:02d} navigation value"))
        rec = {"sat": f"{letter}{prn:02d}", "system": letter, "prn": prn, "line": lineno,
               "af0_s": vals[0], "af1_s_s": vals[1], "crs_m": vals[4], "delta_n_rad_s": vals[5],
               "m0_rad": vals[6], "cuc_rad": vals[7], "e": vals[8], "cus_rad": vals[9],
               "sqrt_a": vals[10], "toe_s": vals[11], "cic_rad": vals[12], "omega0_rad": vals[13],
               "cis_rad": vals[14], "i0_rad": vals[15], "crc_m": vals[16], "argp_rad": vals[17],
               "omega_dot_rad_s": vals[18], "idot_rad_s": vals[19], "week": vals[21],
               "health": vals[24]}
        at = {key: raw[j][0] for j, key in _RINEX_FIELDS.items()}
        check_elements({k: v for k, v in rec.items() if k not in ("sat", "system", "line")}, path,
                       {**at, "prn": lineno}, f"{letter}{prn:02d} (record at line {lineno})")
        rec["week"], rec["health"] = int(rec["week"]), int(rec["health"])
        if letter == "C":  # BDT: week offset 1356, BDT = GPST - 14 s
            rec["t_ref_gps_s"] = ((rec["week"] + _BDS_WEEK_OFFSET) * float(SECONDS_PER_WEEK)
                                  + rec["toe_s"] + _BDS_GPS_OFFSET_S)
            if prn <= 5 or prn >= 59:   # GEO satellites need the BDS GEO transformation
                i += 8
                continue
        else:
            rec["t_ref_gps_s"] = rec["week"] * float(SECONDS_PER_WEEK) + rec["toe_s"]
        records.append(rec)
        i += 8
    if not records:
        raise DataError(f"{path}: no Keplerian navigation records found")
    return records


def _read_text(path: str | Path) -> str:
    """The text of an almanac / navigation file, read through :func:`read_limited` (at most
    :data:`MAX_ALMANAC_BYTES`; FIFOs and devices refused)."""
    p = Path(path)
    if not p.exists():
        raise DataError(f"cannot read almanac/navigation file {p}: not found; check the path")
    try:
        return read_limited(p, MAX_ALMANAC_BYTES, "almanac").decode("ascii", errors="replace")
    except DataError:
        raise
    except OSError as exc:
        raise DataError(f"cannot read almanac/navigation file {p}: {exc.strerror or exc}") from exc


def read_rinex_nav(path: str | Path) -> xr.Dataset:
    """All healthy broadcast ephemeris records of a RINEX 2/3 navigation file.

    Returns a Dataset with dims ``(sat, rec)``: ``rec`` indexes each satellite's records in
    order of reference epoch (NaN padded).  Unhealthy records are dropped (warning naming the
    satellites); duplicates (same satellite and reference epoch) keep the first.
    """
    spath = _path_text(path)
    records = parse_rinex_nav(_read_text(path), spath)
    bad = sorted({r["sat"] for r in records if r["health"] != 0})
    if bad:
        warnings.warn(f"{spath}: unhealthy navigation records excluded (health != 0) for "
                      f"{', '.join(bad)}", stacklevel=2)
    records = [r for r in records if r["health"] == 0]
    if not records:
        raise DataError(f"{spath}: no healthy navigation records")
    by_sat: dict[str, dict[float, dict]] = {}
    for r in records:
        by_sat.setdefault(r["sat"], {}).setdefault(r["t_ref_gps_s"], r)
    sats = sorted(by_sat)
    nrec = max(len(v) for v in by_sat.values())
    fields = ["toe_s", "t_ref_gps_s", "sqrt_a", "e", "i0_rad", "omega0_rad", "omega_dot_rad_s",
              "argp_rad", "m0_rad", *_HARMONIC, "af0_s", "af1_s_s", "week", "health", "line"]
    arr = {f: np.full((len(sats), nrec), np.nan) for f in fields}
    for si, s in enumerate(sats):
        for ri, (_, r) in enumerate(sorted(by_sat[s].items())):
            for f in fields:
                arr[f][si, ri] = r[f]
    ds = xr.Dataset({f: (("sat", "rec"), a) for f, a in arr.items()},
                    coords={"sat": np.array(sats, dtype=str),
                            "system": ("sat", np.array([s[0] for s in sats], dtype=str))})
    ds["prn"] = ("sat", np.array([int(s[1:]) for s in sats]))
    ds["kind"] = ("sat", np.full(len(sats), "ephemeris"))
    tref = arr["t_ref_gps_s"]
    ns = np.where(np.isfinite(tref), np.round(np.nan_to_num(tref) * 1e9), 0).astype(np.int64)
    ds["t_ref"] = (("sat", "rec"), np.where(np.isfinite(tref), gps_ns_to_utc(ns), np.datetime64("NaT")))
    _attrs(ds)
    ds["line"].attrs["long_name"] = "line number of the record in the source file"
    ds.attrs = {"source": spath, "format": "RINEX navigation", "units": _DS_UNITS,
                "time_scale": "t_ref is UTC; toe_s, t_ref_gps_s are the system's own time / GPS time"}
    return ds


def _nearest_record(eph: xr.Dataset, reference_date) -> xr.Dataset:
    """One record per satellite (dim sat): nearest to ``reference_date`` or the earliest."""
    tref = eph["t_ref_gps_s"].values
    if reference_date is None:
        idx = np.nanargmin(tref, axis=1)
    else:
        week, sow = gps_week_seconds(as_utc_times(reference_date))
        t = float(week[0]) * SECONDS_PER_WEEK + float(sow[0])
        idx = np.nanargmin(np.where(np.isfinite(tref), np.abs(tref - t), np.inf), axis=1)
    out = eph.isel(rec=xr.DataArray(idx, dims="sat"))
    out = out.drop_vars([c for c in ("rec",) if c in out.coords])
    for v in ("week", "health", "line"):
        out[v] = out[v].astype(np.int64)
    _attrs(out)
    return out


# --------------------------------------------------------------------------------------------
# public
# --------------------------------------------------------------------------------------------

def detect_format(text: str) -> str:
    """``"rinex"``, ``"yuma"`` or ``"sem"`` from the first lines of a file."""
    head = text.lstrip()[:400]
    if "RINEX VERSION / TYPE" in text[:200]:
        return "rinex"
    if "almanac for" in head.lower() or head.startswith("*"):
        return "yuma"
    first = head.splitlines()[:2]
    if len(first) == 2 and first[0].split()[:1] and first[0].split()[0].isdigit() \
            and len(first[1].split()) == 2:
        return "sem"
    raise DataError("unknown almanac format (expected YUMA, SEM or RINEX navigation)")


def read_almanac(path: str | Path, reference_date=None, system: str | None = None,
                 kind: str | None = None) -> xr.Dataset:
    """Orbital elements of one almanac file (YUMA, SEM or RINEX 2/3 navigation), dim ``sat``.

    ``reference_date`` (UTC date/datetime/ISO string) resolves GPS weeks given modulo 1024
    (default: today; see :func:`resolve_gps_week`).  For a RINEX file it selects, per
    satellite, the record nearest to it (default: the earliest record).  ``system`` forces the
    constellation letter of YUMA/SEM files (default: inferred from the orbit size).
    """
    spath = _path_text(path)
    text = _read_text(path)
    try:
        fmt = detect_format(text)
    except DataError as exc:
        raise DataError(f"{spath}: {exc}") from None
    if system is not None and system not in SYSTEM_CONSTANTS:
        raise InputError(f"system {system!r} is not one of {sorted(SYSTEM_CONSTANTS)}")
    if fmt == "yuma":
        return parse_yuma(text, spath, reference_date, system, kind)
    if fmt == "sem":
        return parse_sem(text, spath, reference_date, system or "G", kind)
    ds = _nearest_record(read_rinex_nav(path), reference_date)
    ds.attrs["format"] = "RINEX navigation (one record per satellite)"
    return ds


def merge_almanacs(items: Iterable[str | Path | xr.Dataset], reference_date=None) -> xr.Dataset:
    """One element Dataset (dim ``sat``) from several almanac files/Datasets, e.g. GPS + Galileo.

    Raises :class:`InputError` if two inputs give the same satellite id.
    """
    dsets = [it if isinstance(it, xr.Dataset) else read_almanac(it, reference_date) for it in items]
    if not dsets:
        raise InputError("no almanac given; pass at least one file")
    for d in dsets:
        if "rec" in d.dims:
            raise InputError(f"{d.attrs.get('source')}: has several records per satellite; "
                             "merge almanacs from read_almanac (one record per satellite)")
    ids = np.concatenate([d["sat"].values for d in dsets])
    uniq, counts = np.unique(ids, return_counts=True)
    if (counts > 1).any():
        raise InputError(f"satellites given by more than one almanac: {', '.join(uniq[counts > 1])}; "
                         "merge almanacs of different constellations only")
    common = set.intersection(*(set(d.data_vars) for d in dsets))
    out = xr.concat([d[sorted(common)] for d in dsets], dim="sat", join="outer",
                    combine_attrs="drop").sortby("sat")
    _attrs(out)
    out.attrs = {"source": "; ".join(str(d.attrs.get("source", "?")) for d in dsets),
                 "format": "; ".join(str(d.attrs.get("format", "?")) for d in dsets),
                 "units": _DS_UNITS}
    return out


def sky_geometry(almanac_paths: str | Path | Sequence[str | Path], times_utc, lat_deg: float,
                 lon_deg: float, height_m: float = 0.0, mask_deg: float = 5.0,
                 reference_date=None) -> xr.Dataset:
    """Satellite positions, az/el, visibility and DOP over a ground point, dims ``(time, sat)``.

    ``almanac_paths``: one or several almanac files (merged, e.g. GPS + Galileo).  GPS weeks
    modulo 1024 are resolved against ``reference_date`` (default: the earliest of
    ``times_utc``).  ``mask_deg`` [deg] is the elevation mask (0..60).  Variables:
    ``x_ecef, y_ecef, z_ecef`` [m], ``az_deg, el_deg`` [deg], ``los_enu``, ``above_mask``
    (bool), ``n_visible`` and ``gdop, pdop, hdop, vdop, tdop`` (time) of the satellites above
    the mask (:func:`skyroute.stages.dop.dop`: +inf where there is no fix, i.e. fewer than 4
    satellites above the mask or a singular geometry).
    """
    from skyroute.stages.dop import DOP_NAMES, dop  # numba: imported when computing

    mask = check_mask(mask_deg)
    times = as_utc_times(times_utc)
    if isinstance(almanac_paths, str | Path):
        almanac_paths = [almanac_paths]
    paths = list(almanac_paths)
    if not paths:
        raise InputError("no almanac given; pass at least one file")
    ref = times.min() if reference_date is None else reference_date
    elements = merge_almanacs(paths, ref) if len(paths) > 1 else read_almanac(paths[0], ref)
    pos = satellite_positions(elements, times)
    azel = satellite_azel(pos, lat_deg, lon_deg, height_m)
    ds = xr.merge([pos, azel], combine_attrs="override")
    ds["kind"] = elements["kind"].reindex(sat=ds["sat"])
    above = ds["el_deg"] >= mask
    ds["above_mask"] = above.assign_attrs(long_name=f"elevation >= mask ({mask} deg)")
    ds["n_visible"] = above.sum("sat").assign_attrs(units="1", long_name="satellites above mask")
    d = dop(ds["az_deg"].where(above), ds["el_deg"].where(above), axis="sat")
    for k in DOP_NAMES:
        ds[k] = d[k]
    ds.attrs.update({"source": elements.attrs.get("source", ""), "mask_deg": mask,
                     "site_lat_deg": float(lat_deg), "site_lon_deg": float(lon_deg),
                     "site_height_m": float(height_m)})
    return ds


__all__ = ["GPS_EPOCH", "detect_format", "infer_system", "merge_almanacs", "parse_rinex_nav",
           "parse_sem", "parse_yuma", "read_almanac", "read_rinex_nav", "resolve_gps_week",
           "satellite_azel", "satellite_positions", "sky_geometry"]
