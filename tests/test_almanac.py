"""Almanac / ephemeris readers, orbit propagation, az/el and DOP, checked against independent references."""

from __future__ import annotations

import datetime as dt
import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from skyroute.pipeline.errors import DataError, InputError
from skyroute.stages.almanac import (
    merge_almanacs,
    parse_rinex_nav,
    read_almanac,
    read_rinex_nav,
    resolve_gps_week,
    sky_geometry,
)
from skyroute.stages.dop import dop
from skyroute.stages.orbits import (
    geodetic_to_ecef,
    gps_minus_utc_s,
    gps_ns_to_utc,
    gps_week_seconds,
    satellite_azel,
    satellite_positions,
    solve_kepler,
    utc_to_gps_ns,
)

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
XYZ = ("x_ecef", "y_ecef", "z_ecef")
GPS_A_M = 26_559_700.0     # nominal GPS semi-major axis [m]
GAL_A_M = 29_600_000.0     # nominal Galileo semi-major axis [m]


@pytest.fixture(scope="module")
def gnss() -> Path:
    d = SHARED / "gnss"
    if not d.is_dir():
        pytest.skip(f"shared GNSS data not found at {d} (see /work/shared/data/README.md)")
    return d


def _quiet(fn, *args, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*args, **kw)


def _dist(a: xr.Dataset, b: xr.Dataset) -> xr.DataArray:
    return np.sqrt(sum((a[v] - b[v]) ** 2 for v in XYZ))


def _times(start: str, hours: float, step_s: int) -> np.ndarray:
    n = int(hours * 3600 / step_s) + 1
    return np.datetime64(start, "ns") + (np.arange(n) * step_s).astype("timedelta64[s]")


# ------------------------------------------------------------------------------ time scales

def test_leap_seconds_match_erfa_1999_2030():
    erfa = pytest.importorskip("erfa", reason="pyerfa gives the IERS TAI-UTC table")
    days = np.datetime64("1999-01-01") + np.arange(0, 365 * 31, 5).astype("timedelta64[D]")
    ours = gps_minus_utc_s(days.astype("datetime64[ns]"))
    ref = []
    warnings.simplefilter("ignore", erfa.ErfaWarning)   # "dubious year" beyond its table's date
    for d in days.astype(object):
        ref.append(erfa.dat(d.year, d.month, d.day, 0.5) - 19.0)  # GPS - UTC = TAI - UTC - 19 s
    np.testing.assert_array_equal(ours, np.array(ref))
    # spot values of the issue text
    assert gps_minus_utc_s(np.datetime64("2016-08-01", "ns")) == 17
    assert gps_minus_utc_s(np.datetime64("2016-12-31T23:59:59", "ns")) == 17
    assert gps_minus_utc_s(np.datetime64("2017-01-01T00:00:00", "ns")) == 18


def test_rinex_header_leap_seconds_and_week(gnss):
    # the IGS file header states LEAP SECONDS 18 and DELTA-UTC week 2086 for 2020-01-01
    header = (gnss / "brdc0010.20n").read_text().splitlines()[:8]
    leap = int(next(h for h in header if "LEAP SECONDS" in h).split()[0])
    assert gps_minus_utc_s(np.datetime64("2020-01-01T12:00", "ns")) == leap
    week, sow = gps_week_seconds(np.array(["2020-01-01T00:00:00"], dtype="datetime64[ns]"))
    # independent: calendar days since the GPS epoch (Sunday 1980-01-06)
    days = (dt.date(2020, 1, 1) - dt.date(1980, 1, 6)).days
    assert week[0] == days // 7 == 2086
    assert sow[0] == (days % 7) * 86400 + 18


def test_gps_utc_round_trip():
    t = np.array(["2016-12-31T23:59:40", "2017-01-01T00:00:00", "2020-06-01T12:34:56.789"],
                 dtype="datetime64[ns]")
    np.testing.assert_array_equal(gps_ns_to_utc(utc_to_gps_ns(t)), t)


@pytest.mark.parametrize("week, ref, expected", [
    (38, "2020-01-01", 2086), (862, "2016-03-01", 1886), (149, "2022-02-10", 2197),
    (147, "2022-02-03", 2195), (862, "2000-01-01", 862), (1930, None, 1930),
    (38, "2019-03-01", 2086),  # reference up to a year before the almanac still resolves
])
def test_week_rollover(week, ref, expected):
    assert resolve_gps_week(week, ref) == expected


# ------------------------------------------------------------------------------ parsers

def test_yuma_reader(gnss):
    with pytest.warns(UserWarning, match="G04"):
        alm = read_almanac(gnss / "yuma_2020-01-03.txt", reference_date="2020-01-01")
    assert alm.sizes["sat"] == 30 and "G04" not in alm["sat"].values      # 31 PRN, G04 health 63
    assert alm["sat"].values[0] == "G01" and set(alm["system"].values) == {"G"}
    assert (alm["week"] == 2086).all() and (alm["toe_s"] == 503808.0).all()
    # toa 503808 s of week 2086 = Friday 2020-01-03 19:56:48 GPS = 19:56:30 UTC
    assert alm["t_ref"].values[0] == np.datetime64("2020-01-03T19:56:30", "ns")
    assert alm.attrs["format"] == "YUMA" and "yuma_2020-01-03.txt" in alm.attrs["source"]
    assert alm["sqrt_a"].attrs["units"] == "m0.5" and alm["i0_rad"].attrs["units"] == "rad"
    g01 = alm.sel(sat="G01")
    assert float(g01["e"]) == pytest.approx(0.9250164032e-2, rel=1e-12)
    assert float(g01["omega0_rad"]) == pytest.approx(-0.5806106047, rel=1e-12)


def test_yuma_and_sem_give_the_same_orbits(gnss):
    """Orekit pair: the same week-862 almanac in YUMA (rad, 9-10 decimals) and SEM (semicircles)."""
    yuma = _quiet(read_almanac, gnss / "orekit_week1886_yuma.txt", reference_date="2016-03-01")
    sem = _quiet(read_almanac, gnss / "orekit_week1886_sem.al3", reference_date="2016-03-01")
    assert list(yuma["sat"].values) == list(sem["sat"].values)
    assert sem.attrs["format"] == "SEM" and (sem["week"] == 1886).all()
    for v in ("argp_rad", "m0_rad", "omega0_rad", "i0_rad"):   # YUMA prints 9-10 decimals
        assert float(abs(yuma[v] - sem[v]).max()) < 6e-10, v
    t = _times("2016-03-02T16:44:31", 6, 1800)                 # from the toa on
    d = _dist(satellite_positions(yuma, t), satellite_positions(sem, t))
    # 5e-10 rad of YUMA rounding is 13 mm at the GPS radius: identical to the print precision
    assert float(d.isel(time=0).median()) < 0.015
    assert float(d.max()) < 0.05


def test_multi_constellation_merge(gnss):
    merged = _quiet(merge_almanacs, [gnss / "yuma_2020-01-03.txt", gnss / "alm_gal_ed259.txt"],
                    reference_date="2020-01-01")
    assert merged.sizes["sat"] == 30 + 24
    assert {"G01", "E01", "E24"} <= set(merged["sat"].values)
    assert set(merged.sel(sat="E07")["kind"].values.ravel()) == {"standard"}
    t = _times("2020-01-03T00:00", 24, 3600)   # 3 years after the ED-259 epoch: not age-checked
    pos = satellite_positions(merged, t)
    r = np.sqrt(sum(pos[v] ** 2 for v in XYZ))
    gps, gal = r.sel(sat=pos["system"] == "G"), r.sel(sat=pos["system"] == "E")
    a = merged["sqrt_a"] ** 2
    ae = a * merged["e"]
    assert float(abs(gps.mean() - GPS_A_M)) < 20e3
    assert bool(((abs(r - a) <= ae + 1e-3)).all())               # a (1 - e) <= r <= a (1 + e)
    assert float(abs(gal - a).max()) < 1e-3                  # circular orbits: r = a exactly
    assert float(abs(gal - GAL_A_M).max()) < 1e3              # Galileo a = 29 600 km
    with pytest.raises(InputError, match="more than one almanac"):
        merge_almanacs([merged, merged])


def test_rinex3_layout_reads_like_rinex2(gnss):
    """The same records rewritten in the RINEX 3 layout (plus a GLONASS record to skip)."""
    lines = (gnss / "brdc0010.20n").read_text().splitlines()
    end = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln)
    body = lines[end + 1: end + 1 + 8 * 6]
    out = ["     3.04           N: GNSS NAV DATA    M: MIXED            RINEX VERSION / TYPE",
           "                                                            END OF HEADER",
           "R05 2020 01 01 00 15 00-1.234567890000E-04 0.000000000000E+00 0.000000000000E+00",
           "     1.000000000000E+04 0.000000000000E+00 0.000000000000E+00 0.000000000000E+00",
           "     1.000000000000E+04 0.000000000000E+00 0.000000000000E+00 1.000000000000E+00",
           "     1.000000000000E+04 0.000000000000E+00 0.000000000000E+00 0.000000000000E+00"]
    for k in range(0, len(body), 8):
        h = body[k]
        prn, y, mo, d, hh, mi, ss = (int(float(x)) for x in h[:22].split())
        out.append(f"G{prn:02d} {2000 + y:04d} {mo:02d} {d:02d} {hh:02d} {mi:02d} {ss:02d}" + h[22:])
        out += [" " + c for c in body[k + 1: k + 8]]
    r3 = parse_rinex_nav("\n".join(out) + "\n", "r3")
    r2 = parse_rinex_nav("\n".join(lines[: end + 1] + body) + "\n", "r2")
    assert len(r3) == len(r2) == 6
    for a, b in zip(r3, r2, strict=True):
        assert {k: v for k, v in a.items() if k != "line"} == {k: v for k, v in b.items() if k != "line"}


# ------------------------------------------------------------------------------ propagation

def test_kepler_solver_residual():
    rng = np.random.default_rng(3)
    m = rng.uniform(-10, 10, 20000)
    e = rng.uniform(0, 0.9, 20000)
    E = solve_kepler(m, e)
    resid = np.angle(np.exp(1j * (E - e * np.sin(E) - m)))     # modulo 2 pi
    assert np.abs(resid).max() < 1e-12


def test_almanac_vs_broadcast_ephemeris_2020(gnss):
    """YUMA 2020-01-03 almanac against the IGS broadcast ephemeris of 2020-01-01 (independent data)."""
    alm = _quiet(read_almanac, gnss / "yuma_2020-01-03.txt", reference_date="2020-01-01")
    eph = _quiet(read_rinex_nav, gnss / "brdc0010.20n")
    assert eph.sizes["rec"] >= 12 and "G04" not in eph["sat"].values
    t = _times("2020-01-01T00:30", 22, 900)
    pa = _quiet(satellite_positions, alm, t)                    # 2-3 days from the toa
    pe = satellite_positions(eph, t)
    common = np.intersect1d(pa["sat"], pe["sat"])
    assert len(common) >= 28
    d = _dist(pa.sel(sat=common), pe.sel(sat=common))
    assert 300.0 < float(d.median()) < 3000.0                   # measured 1.13 km
    assert float(d.max()) < 6000.0                              # measured 3.2 km
    # az/el at a ground point (Helsinki) within 0.1 deg
    lat, lon, h = 60.17, 24.94, 30.0
    aa = satellite_azel(pa.sel(sat=common), lat, lon, h)
    ae = satellite_azel(pe.sel(sat=common), lat, lon, h)
    up = ae["el_deg"] > 5.0
    daz = abs((aa["az_deg"] - ae["az_deg"] + 180.0) % 360.0 - 180.0).where(up & (ae["el_deg"] < 85))
    assert float(abs(aa["el_deg"] - ae["el_deg"]).where(up).max()) < 0.1
    assert float(daz.max()) < 0.1


def _record_pairs(eph: xr.Dataset, offset: int) -> xr.Dataset:
    """Records ``offset`` (0 = earlier, 1 = later) of consecutive pairs, as a dim-``sat`` set."""
    n = eph.sizes["rec"]
    part = eph.isel(rec=slice(offset, n - 1 + offset)).stack(pair=("sat", "rec"))
    ok = np.isfinite(eph["t_ref_gps_s"].values[:, 1:]).ravel()   # pair exists
    part = part.isel(pair=ok)
    ids = [f"{s}_{r}" for s, r in zip(part["sat"].values, part["rec"].values, strict=True)]
    part = part.drop_vars(["pair", "sat", "rec"]).rename(pair="sat")
    return part.assign_coords(sat=ids, system=("sat", [i[0] for i in ids]))


def test_ephemeris_propagation_reaches_the_next_record(gnss):
    """Propagate each broadcast record to the next record's toe (2 h later): agree to metres."""
    eph = _quiet(read_rinex_nav, gnss / "brdc0010.20n")
    prev, nxt = _record_pairs(eph, 0), _record_pairs(eph, 1)
    gap_s = nxt["t_ref_gps_s"].values - prev["t_ref_gps_s"].values
    assert len(gap_s) > 300 and np.median(gap_s) == 7200.0
    t_next = gps_ns_to_utc(np.round(nxt["t_ref_gps_s"].values * 1e9).astype(np.int64))
    p_next = _quiet(satellite_positions, nxt, t_next)
    d = _dist(_quiet(satellite_positions, prev, t_next), p_next)
    errs = np.diagonal(d.values)[gap_s <= 4 * 3600]                # own time of each pair
    assert len(errs) > 300
    assert np.median(errs) < 1.5 and errs.max() < 15.0           # measured 0.43 m, max 5.9 m
    # the (sat, rec) dataset picks the record nearest in time: at a toe, that record itself
    full = satellite_positions(eph, t_next[:40])
    for i in range(40):
        sat = str(nxt["sat"].values[i])[:3]
        for v in XYZ:
            assert float(full[v].isel(time=i).sel(sat=sat)) == float(p_next[v].isel(time=i, sat=i))


def test_orbit_radius_and_period(gnss):
    alm = _quiet(read_almanac, gnss / "current_2022-02-03.alm", reference_date="2022-02-03")
    t = _times("2022-02-05T19:50:06", 0, 60)
    t = np.concatenate([t, t + np.timedelta64(86164, "s")])   # one sidereal day later
    pos = satellite_positions(alm, t)
    r = np.sqrt(sum(pos[v] ** 2 for v in XYZ))
    a = alm["sqrt_a"] ** 2
    assert float(abs(r.isel(time=0) - a).max() / a.max()) < 0.03   # |r - a| <= e a, e < 0.03
    assert float(abs(a.mean() - GPS_A_M)) < 2000.0
    # GPS ground tracks repeat after one sidereal day (2 orbits): Earth-fixed positions within ~60 km
    assert float(_dist(pos.isel(time=[0]), pos.isel(time=[1]).assign_coords(time=pos.time[:1])).max()) < 100e3


def test_azel_matches_pyproj_topocentric(gnss):
    from pyproj import Transformer

    alm = _quiet(read_almanac, gnss / "yuma_2020-01-03.txt", reference_date="2020-01-03")
    pos = satellite_positions(alm, _times("2020-01-03T18:00", 2, 600))
    lat, lon, h = -33.86, 151.21, 58.0
    got = satellite_azel(pos, lat, lon, h)
    x0 = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True).transform(lon, lat, h)
    np.testing.assert_allclose(geodetic_to_ecef(lat, lon, h), x0, atol=1e-6)
    topo = Transformer.from_pipeline(
        f"+proj=pipeline +step +proj=topocentric +ellps=WGS84 +lat_0={lat} +lon_0={lon} +h_0={h}")
    e, n, u = topo.transform(*(pos[v].values.ravel() for v in XYZ))
    rng = np.sqrt(e**2 + n**2 + u**2)
    el = np.degrees(np.arcsin(u / rng)).reshape(pos["x_ecef"].shape)
    az = (np.degrees(np.arctan2(e, n)) % 360.0).reshape(el.shape)
    np.testing.assert_allclose(got["el_deg"], el, atol=1e-7)
    np.testing.assert_allclose(np.cos(np.radians(got["az_deg"] - az)), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(got["los_enu"], axis=-1), 1.0, atol=1e-12)


# ------------------------------------------------------------------------------ DOP

def _dop_lstsq(az, el):
    """Reference: covariance of the unit-weight least-squares solution via np.linalg.pinv."""
    az, el = np.radians(az), np.radians(el)
    g = np.column_stack([-np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), -np.sin(el),
                         np.ones_like(az)])
    p = np.linalg.pinv(g)
    q = p @ p.T
    return {"gdop": np.sqrt(np.trace(q)), "pdop": np.sqrt(q[0, 0] + q[1, 1] + q[2, 2]),
            "hdop": np.sqrt(q[0, 0] + q[1, 1]), "vdop": np.sqrt(q[2, 2]), "tdop": np.sqrt(q[3, 3])}


def test_dop_against_least_squares_reference():
    rng = np.random.default_rng(17)
    az = rng.uniform(0, 360, (50, 12))
    el = rng.uniform(5, 90, (50, 12))
    el[:, 8:][rng.uniform(size=(50, 4)) < 0.5] = np.nan        # some satellites masked
    got = dop(az, el)
    for k in range(50):
        ok = np.isfinite(el[k])
        ref = _dop_lstsq(az[k, ok], el[k, ok])
        for name, v in ref.items():
            assert got[name][k] == pytest.approx(v, rel=1e-9)
    # axis argument: satellites along axis 0
    got0 = dop(az.T, el.T, axis=0)
    np.testing.assert_allclose(got0["pdop"], got["pdop"], rtol=1e-12)


def test_dop_monte_carlo_position_scatter():
    """PDOP/HDOP/VDOP are the std of the LSQ position for unit pseudorange noise."""
    az = np.array([0.0, 72.0, 144.0, 216.0, 288.0, 30.0, 200.0])
    el = np.array([15.0, 35.0, 60.0, 20.0, 45.0, 88.0, 10.0])
    ref = dop(az, el)
    a, e_ = np.radians(az), np.radians(el)
    g = np.column_stack([-np.cos(e_) * np.sin(a), -np.cos(e_) * np.cos(a), -np.sin(e_), np.ones(7)])
    noise = np.random.default_rng(5).normal(size=(7, 40000))
    sol = np.linalg.lstsq(g, noise, rcond=None)[0]
    assert np.sqrt(sol[:3].var(axis=1).sum()) == pytest.approx(ref["pdop"], rel=0.02)
    assert np.sqrt(sol[:2].var(axis=1).sum()) == pytest.approx(ref["hdop"], rel=0.02)
    assert np.sqrt(sol[2].var()) == pytest.approx(ref["vdop"], rel=0.02)


def test_dop_degenerate_and_xarray():
    out = dop(np.array([[0.0, 90.0, 180.0, np.nan]]), np.array([[30.0, 40.0, 50.0, np.nan]]))
    assert np.isposinf(out["gdop"][0])                         # only 3 satellites: no fix
    ring = dop(np.array([0.0, 90.0, 180.0, 270.0]), np.full(4, 10.0))
    assert np.isposinf(ring["gdop"])       # one elevation only: height and clock inseparable
    az = xr.DataArray(np.tile([0.0, 90.0, 180.0, 270.0, 0.0], (2, 1)), dims=("time", "sat"))
    el = xr.DataArray(np.tile([10.0, 10.0, 10.0, 10.0, 90.0], (2, 1)), dims=("time", "sat"))
    ds = dop(az, el, axis="sat")
    assert isinstance(ds, xr.Dataset) and ds["hdop"].dims == ("time",)
    # symmetric sky: 4 at 10 deg + zenith: closed form HDOP = sqrt(2 / (2 cos^2 10)) = 1/cos 10
    assert float(ds["hdop"][0]) == pytest.approx(1.0 / np.cos(np.radians(10.0)), rel=1e-12)
    with pytest.raises(InputError, match="shape"):
        dop(np.zeros(4), np.zeros(5))


# ------------------------------------------------------------------------------ sky geometry

def test_sky_geometry(gnss):
    t = _times("2020-01-03T12:00", 1, 600)
    with pytest.warns(UserWarning, match="G04"):
        ds = sky_geometry([gnss / "yuma_2020-01-03.txt", gnss / "alm_gal_ed259.txt"], t,
                          60.17, 24.94, 30.0, mask_deg=10.0)
    assert ds["x_ecef"].dims == ("time", "sat") and ds["x_ecef"].attrs["units"] == "m"
    assert ds["time"].dtype == np.dtype("datetime64[ns]")
    assert ds["above_mask"].dtype == bool
    np.testing.assert_array_equal(ds["above_mask"], ds["el_deg"] >= 10.0)
    np.testing.assert_array_equal(ds["n_visible"], ds["above_mask"].sum("sat"))
    assert (ds["n_visible"] >= 12).all()
    k = 3
    vis = ds["above_mask"].values[k]
    ref = _dop_lstsq(ds["az_deg"].values[k, vis], ds["el_deg"].values[k, vis])
    assert float(ds["gdop"][k]) == pytest.approx(ref["gdop"], rel=1e-9)
    assert 0.5 < float(ds["pdop"].max()) < 2.5


# ------------------------------------------------------------------------------ bad input

def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_corrupt_and_truncated_files(gnss, tmp_path):
    yuma = (gnss / "yuma_2020-01-03.txt").read_text().splitlines()
    bad = list(yuma)
    bad[20] = bad[20].replace("0.", "0.x")                       # a value line of PRN-02
    p = _write(tmp_path, "bad.yuma", "\n".join(bad))
    with pytest.raises(DataError, match=r"bad\.yuma:21: cannot read"):
        read_almanac(p, "2020-01-01")
    p = _write(tmp_path, "cut.yuma", "\n".join(yuma[:40]))       # PRN-03 cut after 10 fields
    with pytest.raises(DataError, match=r"cut\.yuma:31: YUMA record .* truncated"):
        read_almanac(p, "2020-01-01")
    sem = (gnss / "orekit_week1886_sem.al3").read_text().splitlines()
    p = _write(tmp_path, "cut.al3", "\n".join(sem[:100]))
    with pytest.raises(DataError, match=r"cut\.al3:\d+: SEM almanac truncated"):
        read_almanac(p, "2016-03-01")
    rnx = (gnss / "brdc0010.20n").read_text().splitlines()
    p = _write(tmp_path, "cut.20n", "\n".join(rnx[:8 + 8 * 3 + 5]))
    with pytest.raises(DataError, match=r"cut\.20n:33: .*G04.* truncated"):
        read_rinex_nav(p)
    bad = list(rnx)
    bad[10] = bad[10][:30] + "ABC" + bad[10][33:]
    p = _write(tmp_path, "bad.20n", "\n".join(bad))
    with pytest.raises(DataError, match=r"bad\.20n:11: cannot read"):
        read_rinex_nav(p)
    with pytest.raises(DataError, match="cannot read almanac"):
        read_almanac(tmp_path / "missing.alm")
    with pytest.raises(DataError, match="unknown almanac format"):
        read_almanac(_write(tmp_path, "x.txt", "hello\nworld of text\n"))


def test_unhealthy_satellites_excluded(gnss):
    with pytest.warns(UserWarning, match=r"G13, G32"):
        alm = read_almanac(gnss / "orekit_week1886_yuma.txt", "2016-03-01")
    assert not {"G13", "G32"} & set(alm["sat"].values)


def test_epoch_far_from_almanac(gnss):
    alm = _quiet(read_almanac, gnss / "yuma_2020-01-03.txt", reference_date="2020-01-03")
    with pytest.warns(UserWarning, match="days from the almanac.s reference"):
        satellite_positions(alm, ["2020-01-13T00:00"])            # 9 days
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        satellite_positions(alm, ["2020-01-06T00:00"])            # 2 days: silent
    with pytest.raises(InputError, match="limit is 30.0 days"):
        satellite_positions(alm, ["2020-02-10T00:00"])
    with pytest.raises(InputError, match="before the GPS epoch"):
        satellite_positions(alm, ["1979-01-01"])


def test_mask_and_site_validation(gnss):
    f = gnss / "yuma_2020-01-03.txt"
    for m in (-1.0, 60.5, 90.0):
        with pytest.raises(InputError, match="elevation mask"):
            sky_geometry(f, ["2020-01-03T12:00"], 45.0, 7.0, 0.0, mask_deg=m)
    with pytest.raises(InputError, match="latitude"):
        _quiet(sky_geometry, f, ["2020-01-03T12:00"], 95.0, 7.0, 0.0)


# ------------------------------------------------------------------------------ CLI

def test_cli_sky(gnss):
    from click.testing import CliRunner

    from skyroute.pipeline.cli_gnss import sky_command

    args = ["--almanac", str(gnss / "yuma_2020-01-03.txt"), "--almanac",
            str(gnss / "alm_gal_ed259.txt"), "--time", "2020-01-03T12:00:00Z",
            "--lat", "60.17", "--lon", "24.94", "--height", "30"]
    runner = CliRunner()
    res = runner.invoke(sky_command, [*args, "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    ref = _quiet(sky_geometry, [gnss / "yuma_2020-01-03.txt", gnss / "alm_gal_ed259.txt"],
                 ["2020-01-03T12:00"], 60.17, 24.94, 30.0).isel(time=0)
    assert doc["n_visible"] == int(ref["n_visible"]) == len(doc["satellites"])
    assert doc["dop"]["PDOP"] == pytest.approx(float(ref["pdop"]), abs=1e-3)
    s = doc["satellites"][0]
    assert s["el_deg"] == pytest.approx(float(ref["el_deg"].sel(sat=s["id"])), abs=1e-3)
    assert all(x["el_deg"] >= 5.0 for x in doc["satellites"])
    res = runner.invoke(sky_command, args)
    assert res.exit_code == 0 and "PDOP" in res.stdout and "G30" in res.stdout
    res = runner.invoke(sky_command, [*args, "--mask-deg", "75"])
    assert res.exit_code != 0 and isinstance(res.exception, InputError)
    assert "outside 0..60" in str(res.exception)
    res = runner.invoke(sky_command, [*args[:4], "--time", "yesterday", *args[6:]])
    assert isinstance(res.exception, InputError) and "ISO 8601" in str(res.exception)
    assert "Elevation mask" in runner.invoke(sky_command, ["--help"]).output
