"""Issue 34, wind files, tactical events and almanacs read strictly: a wind event applies on a
scenario without a base wind, event values are finite and bounded, every almanac record is a
plausible GNSS orbit, almanac and wind files are bounded reads, wind units are converted."""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from click.testing import CliRunner

from skyroute.pipeline.errors import DataError, ScenarioError
from skyroute.pipeline.settings import parse_scenario
from skyroute.stages import almanac as A
from skyroute.stages import wind as W

CATALOG = Path(__file__).resolve().parents[1] / "catalogs" / "data"
YUMA = CATALOG / "yuma_2020-01-03.txt"


def _tiny_raw(events=(), **data) -> dict:
    """A 120 m x 100 m flat AOI in Helsinki (4 m cells), GPS almanac, no wind."""
    return {"name": "tiny-wind", "aoi": {"bounds": [385000, 6672000, 385120, 6672100], "crs": "EPSG:32635",
                                         "resolution_m": 4.0, "chunk_cells": 64},
            "data": {"almanacs": [str(YUMA)], **data},
            "mission": {"start": {"x": 385010, "y": 6672010, "alt_agl_m": 30},
                        "goal": {"x": 385110, "y": 6672090, "alt_agl_m": 30},
                        "start_time_utc": "2020-01-03T10:00:00Z"},
            "gnss": {"window_min": 2, "step_min": 1},
            "events": list(events)}


def _tiny(events=(), **data):
    return parse_scenario(_tiny_raw(events, **data))


def _problems(events) -> str:
    with pytest.raises(ScenarioError) as e:
        _tiny(events)
    return str(e.value)


def _cli(argv) -> tuple[int, str]:
    from skyroute.pipeline.cli import main

    res = CliRunner().invoke(main, [str(a) for a in argv])
    return res.exit_code, res.output


def _one_error(code: int, out: str, needle: str) -> None:
    assert code == 2, out
    assert "Traceback" not in out, out
    assert len([ln for ln in out.splitlines() if ln.startswith("error:")]) == 1, out
    assert needle in out, out


# ------------------------------------------------------------------ 1. wind event without base wind

@pytest.fixture(scope="module")
def fly_cache(tmp_path_factory):
    from skyroute.pipeline.cache import Cache

    return Cache(tmp_path_factory.mktemp("cache"))


def _fly(events, cache, **data):
    from skyroute.pipeline.fly import fly_scenario

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fly_scenario(_tiny(events, **data), cache=cache, scheduler="synchronous").log


def test_wind_event_above_the_limit_ends_a_flight_without_base_wind(fly_cache):
    """Before: 'reached the goal; 0 replannings' -- the wind stage was not run for a scenario
    without data.wind / data.uniform_wind, so the event's wind never reached the replay."""
    log = _fly([{"t_s": 3, "kind": "wind", "uniform_wind": {"speed_mps": 20, "direction_deg": 270}}], fly_cache)
    assert log.outcome != "goal"
    assert "wind 20.0 m/s above the vehicle maximum 15 m/s" in log.reason
    assert [e["outcome"] for e in log.events] == ["failed"]


def test_wind_event_below_the_limit_changes_the_energy_without_base_wind(fly_cache):
    far = {"t_s": 3, "kind": "nofly", "polygon": [[385000, 6672095], [385004, 6672095], [385004, 6672099]]}
    calm = _fly([far], fly_cache)           # the same flight, with an event that changes no map
    windy = _fly([{"t_s": 3, "kind": "wind", "uniform_wind": {"speed_mps": 8, "direction_deg": 270}}], fly_cache)
    assert calm.outcome == windy.outcome == "goal"
    # a west wind (8 m/s towards east) on a north-east flight: a tail wind, less energy
    assert windy.energy_Wh < calm.energy_Wh - 0.05, (windy.energy_Wh, calm.energy_Wh)


# ------------------------------------------------------------------ 2. event values bounded

def _intruder(**kw) -> dict:
    return {"t_s": 2, "kind": "intruder", "id": "x", **kw}


@pytest.mark.parametrize("event, message", [
    (_intruder(position=[385050, 6672050, 30], velocity_mps=[1e6, 0, 0]),
     "events[0].velocity_mps: speed |velocity_mps| = 1e+06 m/s is faster than the 150 m/s an intruder may fly"),
    (_intruder(position=[385050, 6672050, 30], velocity_mps=[120, 120, 0]),
     "events[0].velocity_mps: speed |velocity_mps| = 169.7 m/s is faster than the 150 m/s"),
    (_intruder(waypoints=[[2, 385000, 6672050, 30], [3, 385200, 6672050, 30]]),
     "events[0].waypoints: waypoints 0 -> 1 (2 s -> 3 s) are flown at 200 m/s, faster than the 150 m/s"),
    (_intruder(position=[1e300, 6672050, 30], velocity_mps=[1, 0, 0]),
     "events[0].position: position x 1e+300 m is out of range: it must be in [-1e+08, 1e+08] m"),
    (_intruder(position=[385050, 6672050, 30], velocity_mps=[1, 0, 0], duration_s=1e9),
     "events[0].duration_s: duration_s 1e+09 s is out of range: it must be at most 86400 s"),
    (_intruder(position=[385050, 6672050, 30], velocity_mps=[1, 0, 0], radius_m=1e6),
     "events[0].radius_m: radius_m 1e+06 m is out of range: it must be at most 1000 m"),
    (_intruder(position=[385050, 6672050, 30], velocity_mps=["1e400", 0, 0]),
     "events[0].velocity_mps: velocity [inf, 0.0, 0.0] m/s has a non-finite component"),
    ({"t_s": 2, "kind": "wind", "uniform_wind": {"speed_mps": 1e6, "direction_deg": 270}},
     "events[0].uniform_wind: speed_mps 1e+06 m/s is out of range: it must be at most 100 m/s"),
    ({"t_s": 2, "kind": "wind", "uniform_wind": {"speed_mps": 5, "direction_deg": "1e400"}},
     "events[0].uniform_wind: direction_deg inf is not a finite angle"),
    ({"t_s": 2, "kind": "wind", "uniform_wind": {"speed_mps": 5, "direction_deg": 0, "elevation_deg": 95}},
     "events[0].uniform_wind: elevation_deg 95 deg is out of range: it must be in [-90, 90] deg"),
    ({"t_s": "1e400", "kind": "wind", "uniform_wind": {"speed_mps": 5, "direction_deg": 0}},
     "events[0].t_s: event time inf s is not a finite number"),
    ({"t_s": 2, "kind": "obstacle", "polygon": [[385050, 6672050], [385060, 6672050], [385060, 6672060]],
      "height_agl_m": 1e7}, "events[0].height_agl_m: height_agl_m 1e+07 m is out of range: it must be at most 100000 m"),
])
def test_event_values_are_finite_and_bounded(event, message):
    assert message in _problems([event])


def test_event_values_at_their_bounds_are_accepted():
    sc = _tiny([_intruder(position=[385050, 6672050, 30], velocity_mps=[150, 0, 0], duration_s=60),
                {"t_s": 3, "kind": "intruder", "id": "y",
                 "waypoints": [[3, 385000, 6672050, 30], [4, 385150, 6672050, 30]]},
                {"t_s": 4, "kind": "wind", "uniform_wind": {"speed_mps": 100, "direction_deg": 720}},
                {"t_s": 5, "kind": "nofly", "polygon": [[385050, 6672050], [385060, 6672050], [385060, 6672060]]}])
    assert sc.events[2].uniform_wind.speed_mps == 100 and sc.events[3].max_agl_m == np.inf   # open band


def test_fly_cli_refuses_a_1e6_mps_intruder_with_one_error_line(tmp_path):
    """Before: a traceback (JSON inf when writing the outputs)."""
    import yaml

    scen = tmp_path / "tiny.yaml"
    scen.write_text(yaml.safe_dump(_tiny_raw()))
    ev = tmp_path / "fast.yaml"
    ev.write_text(yaml.safe_dump({"events": [_intruder(position=[385050, 6672050, 30],
                                                       velocity_mps=[1e6, 0, 0], duration_s=60)]}))
    code, out = _cli(["fly", scen, "--events", ev, "--out", tmp_path / "out", "-q",
                      "--cache-dir", tmp_path / "cache"])
    _one_error(code, out, "events[0].velocity_mps: speed |velocity_mps| = 1e+06 m/s is faster than the 150 m/s")
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------ 3. almanac records

def _yuma_with(tmp_path: Path, field: str, value: str, name: str = "bad.txt") -> tuple[Path, int]:
    """The catalog YUMA almanac with ``field`` of its first record (PRN-01) replaced; the line."""
    lines = YUMA.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.lower().startswith(field.lower()))
    lines[k] = f"{lines[k].split(':', 1)[0]}:  {value}"
    p = tmp_path / name
    p.write_text("\n".join(lines) + "\n")
    return p, k + 1


@pytest.mark.parametrize("field, value, message", [
    ("Eccentricity", "1.5", r"PRN 1: eccentricity 1\.5 is not in \[0, 1\)"),
    ("Eccentricity", "-0.01", r"PRN 1: eccentricity -0\.01 is not in \[0, 1\)"),
    ("Eccentricity", "0.9", r"PRN 1: eccentricity 0\.9 puts the perigee .* 2,656 km inside the Earth"),
    ("SQRT(A)", "100.0", r"PRN 1: sqrt\(A\) 100 m\^0\.5 \(semi-major axis 10 km\) is outside 3162\.3\.\.7071\.1"),
    ("SQRT(A)", "-5153.6", r"PRN 1: sqrt\(A\) -5153\.6 m\^0\.5"),
    ("week", "-3", r"PRN 1: week number -3 is not an integer in 0\.\.5000"),
    ("week", "38.5", r"PRN 1: week number 38\.5 is not an integer"),
    ("Health", "0.5", r"PRN 1: health 0\.5 is not a non-negative integer"),
    ("Time of Applicability", "700000", r"PRN 1: time of applicability / ephemeris \(toe_s\) 700000 s of week"),
    ("Orbital Inclination", "4.0", r"PRN 1: inclination \(i0_rad\) 4 rad is outside 0\.\.3\.14159 rad"),
    ("Rate of Right Ascen", "1e-3", r"PRN 1: rate of right ascension \(omega_dot_rad_s\) 0\.001 rad/s"),
])
def test_yuma_record_out_of_range_is_one_error_naming_file_line_prn_field(tmp_path, field, value, message):
    p, line = _yuma_with(tmp_path, field, value)
    with warnings.catch_warnings():
        warnings.simplefilter("error")        # no numpy warning (nor any other) before the refusal
        with pytest.raises(DataError, match=rf"bad\.txt:{line}: {message}"):
            A.read_almanac(p, "2020-01-01")


def test_sky_with_eccentricity_1_5_is_refused_not_no_fix(tmp_path):
    """Before: a numpy sqrt warning, then 'no fix' and exit 0."""
    p, line = _yuma_with(tmp_path, "Eccentricity", "1.5", "e15.txt")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(DataError, match=rf"e15\.txt:{line}: PRN 1: eccentricity 1\.5"):
            A.sky_geometry(p, ["2020-01-03T12:00"], 60.17, 24.94)
    code, out = _cli(["sky", "--almanac", p, "--time", "2020-01-03T12:00:00Z", "--lat", "60.17", "--lon", "24.94"])
    _one_error(code, out, f"e15.txt:{line}: PRN 1: eccentricity 1.5 is not in [0, 1)")


def test_a_high_but_possible_eccentricity_is_kept_with_a_warning(tmp_path):
    p, line = _yuma_with(tmp_path, "Eccentricity", "0.3")
    with pytest.warns(UserWarning, match=rf"bad\.txt:{line}: PRN 1: eccentricity 0\.3 is unusual"):
        alm = A.read_almanac(p, "2020-01-01")
    assert float(alm["e"].sel(sat="G01")) == 0.3


SEM = """\
1  CURRENT.ALM
 862 319488

1
63
0
 {e}  6.84547424316406E-03 -2.48837750405073E-09
 {sqrt_a}  -2.08778738975525E-01  1.46086812019348E-01
 4.55284833908081E-01  1.33514404296875E-05  0.00000000000000E+00
0
11
"""


def test_sem_record_checked(tmp_path):
    p = tmp_path / "ok.al3"
    p.write_text(SEM.format(e="5.10072708129883E-03", sqrt_a="5.15360253906250E+03"))
    alm = A.read_almanac(p, "2016-03-01")
    assert float(alm["e"].sel(sat="G01")) == pytest.approx(5.10072708129883e-3, rel=1e-12)
    p = tmp_path / "e.al3"
    p.write_text(SEM.format(e="1.5E+00", sqrt_a="5.15360253906250E+03"))
    with pytest.raises(DataError, match=r"e\.al3:7: PRN 1: eccentricity 1\.5 is not in \[0, 1\)"):
        A.read_almanac(p, "2016-03-01")
    p = tmp_path / "a.al3"
    p.write_text(SEM.format(e="5.1E-03", sqrt_a="9.0E+04"))
    with pytest.raises(DataError, match=r"a\.al3:8: PRN 1: sqrt\(A\) 90000 m\^0\.5"):
        A.read_almanac(p, "2016-03-01")


RINEX = """\
     2              NAVIGATION DATA                         RINEX VERSION / TYPE
                                                            END OF HEADER
 1 20  1  1  0  0  0.0-0.247901305556D-03-0.121644916362D-10 0.000000000000D+00
    0.720000000000D+02-0.195625000000D+02 0.421803284086D-08-0.148380470489D+01
   -0.957399606705D-06 {e} 0.391341745853D-05 0.515363869095D+04
    0.259200000000D+06 0.206753611565D-06-0.578651745682D+00-0.100582838059D-06
    0.978510092450D+00 0.313593750000D+03 0.759471390003D+00-0.806605026908D-08
    0.571452374714D-11 0.100000000000D+01 {week} 0.000000000000D+00
    0.200000000000D+01 0.000000000000D+00 0.558793544769D-08 0.720000000000D+02
    0.254838000000D+06 0.400000000000D+01 0.000000000000D+00 0.000000000000D+00
"""


def test_rinex_record_checked(tmp_path):
    ok = {"e": "0.923578138463D-02", "week": "0.208600000000D+04"}
    p = tmp_path / "ok.20n"
    p.write_text(RINEX.format(**ok))
    eph = A.read_rinex_nav(p)
    assert float(eph["e"].sel(sat="G01")[0]) == pytest.approx(0.923578138463e-2, rel=1e-12)
    p.write_text(RINEX.format(**{**ok, "e": "0.150000000000D+01"}))
    with pytest.raises(DataError, match=r"ok\.20n:5: G01 \(record at line 3\): eccentricity 1\.5 is not in"):
        A.read_rinex_nav(p)
    p.write_text(RINEX.format(**{**ok, "week": "0.100000000000D+11"}))
    with pytest.raises(DataError, match=r"ok\.20n:8: G01 .*week number 1e\+10 is not an integer in 0\.\.5000"):
        A.read_almanac(p, "2020-01-01")


# ------------------------------------------------------------------ 4. bounded reads

def test_almanac_stream_device_fifo_and_size_are_refused(tmp_path, monkeypatch):
    """Before: ``sky --almanac /dev/urandom`` grew to 4.1 GB in 30 s."""
    with pytest.raises(DataError, match=r"almanac file /dev/urandom is a device, not a regular file"):
        A.read_almanac("/dev/urandom")
    fifo = tmp_path / "alm.fifo"
    os.mkfifo(fifo)
    with pytest.raises(DataError, match=r"is a FIFO \(named pipe\), not a regular file"):
        A.read_almanac(fifo)          # refused before it is opened: no writer, would block
    monkeypatch.setattr(A, "MAX_ALMANAC_BYTES", 1000)
    with pytest.raises(DataError, match=r"more than 1,000 bytes"):
        A.read_almanac(YUMA, "2020-01-01")
    with pytest.raises(DataError, match="cannot read almanac/navigation file .*: not found"):
        A.read_almanac(tmp_path / "missing.alm")


def test_sky_cli_refuses_dev_urandom_with_one_error_line():
    code, out = _cli(["sky", "--almanac", "/dev/urandom", "--time", "2020-01-03T12:00:00Z", "--lat", "60.17",
                      "--lon", "24.94"])
    _one_error(code, out, "almanac file /dev/urandom is a device, not a regular file")


def test_wind_file_device_fifo_and_size_are_refused(tmp_path, monkeypatch):
    with pytest.raises(DataError, match=r"wind file /dev/zero is a device, not a regular file"):
        W.read_wind("/dev/zero")
    fifo = tmp_path / "wind.nc"
    os.mkfifo(fifo)
    with pytest.raises(DataError, match=r"wind\.nc is a FIFO \(named pipe\), not a regular file"):
        W.read_wind(fifo)
    p = _wind10(tmp_path / "w.nc", "m s-1")
    monkeypatch.setattr(W, "MAX_WIND_BYTES", 100)
    with pytest.raises(DataError, match=r"w\.nc is \d[\d,]* bytes, more than the 100 bytes"):
        W.read_wind(p)
    z = tmp_path / "w.zarr"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")         # zarr's note on consolidated metadata
        xr.open_dataset(p).to_zarr(z)
    with pytest.raises(DataError, match=r"wind store .*w\.zarr holds more than 100 bytes"):
        W.read_wind(z)


# ------------------------------------------------------------------ 5. wind units and heights

LAT, LON = [60.0, 60.5], [24.5, 25.0]


def _wind10(path: Path, units: str | None, value: float = 36.0) -> Path:
    attrs = {} if units is None else {"units": units}
    ds = xr.Dataset({"u10": (("latitude", "longitude"), np.full((2, 2), value), attrs),
                     "v10": (("latitude", "longitude"), np.full((2, 2), -value / 2), attrs)},
                    coords={"latitude": LAT, "longitude": LON})
    ds.to_netcdf(path)
    return path


@pytest.mark.parametrize("units, factor", [
    ("m s**-1", 1.0), ("m/s", 1.0), ("m s-1", 1.0), ("km h**-1", 1 / 3.6), ("km/h", 1 / 3.6),
    ("kt", 0.514444), ("knots", 0.514444), ("mph", 0.44704),
])
def test_declared_wind_units_are_converted_to_mps(tmp_path, units, factor):
    """Before: a file in km h**-1 was read as m/s (3.6 times too strong)."""
    wind = W.read_wind(_wind10(tmp_path / "w.nc", units))
    assert float(wind["u10"][0, 0]) == pytest.approx(36.0 * factor, rel=1e-6)
    assert float(wind["v10"][1, 1]) == pytest.approx(-18.0 * factor, rel=1e-6)
    r = W.wind_at_lonlat(wind, 24.7, 60.2, [10.0])
    assert float(r["u"][0, 0]) == pytest.approx(36.0 * factor, rel=1e-6)


def test_unknown_wind_unit_is_refused_and_a_missing_one_warns(tmp_path):
    with pytest.raises(DataError, match=r"w\.nc: variable 'u10' \(wind speed\) has units 'furlong/fortnight', "
                                        r"which skyroute does not know; give wind speed in one of: m s-1, km h-1"):
        W.read_wind(_wind10(tmp_path / "w.nc", "furlong/fortnight"))
    with pytest.warns(UserWarning, match=r"n\.nc: variable 'u10' \(wind speed\) has no 'units' attribute: "
                                         r"assumed m/s"):
        wind = W.read_wind(_wind10(tmp_path / "n.nc", None, 7.0))
    assert float(wind["u10"][0, 0]) == 7.0


def _levels(path: Path, gh: np.ndarray, u_units: str = "km h-1") -> Path:
    shape = (2, 2, 2)
    ds = xr.Dataset({"u": (("isobaricInhPa", "latitude", "longitude"), np.full(shape, 36.0), {"units": u_units}),
                     "v": (("isobaricInhPa", "latitude", "longitude"), np.zeros(shape), {"units": u_units}),
                     "gh": (("isobaricInhPa", "latitude", "longitude"), gh, {"units": "gpm"})},
                    coords={"isobaricInhPa": ("isobaricInhPa", [1000.0, 850.0], {"units": "hPa"}),
                            "latitude": LAT, "longitude": LON})
    ds.to_netcdf(path)
    return path


def test_pressure_levels_units_and_all_nan_heights(tmp_path):
    gh = np.stack([np.full((2, 2), 100.0), np.full((2, 2), 1500.0)])
    wind = W.read_wind(_levels(tmp_path / "ok.nc", gh))
    np.testing.assert_allclose(wind["u"].values, 10.0)                # 36 km/h on both levels
    r = W.wind_at_lonlat(wind, 24.7, 60.2, [100.0], ground_m=0.0)      # at the lowest level
    assert float(r["u"][0, 0]) == pytest.approx(10.0, rel=1e-9)
    with pytest.raises(DataError, match=r"nan\.nc: variable 'gh' \(height of the pressure levels\) has no finite "
                                        r"value \(all NaN\)"):
        W.read_wind(_levels(tmp_path / "nan.nc", np.full((2, 2, 2), np.nan)))
    part = gh.copy()
    part[:, 0, 0] = np.nan                                            # the south-west column has no height
    wind = W.read_wind(_levels(tmp_path / "part.nc", part))
    with pytest.raises(DataError, match=r"part\.nc: gh \(geopotential height of the levels\) has no data \(NaN\)"):
        W.wind_at_lonlat(wind, 24.6, 60.1, [500.0])


def test_height_levels_units_and_non_finite_heights(tmp_path):
    def write(name: str, heights, units: str | None = "m") -> Path:
        attrs = {} if units is None else {"units": units}
        ds = xr.Dataset({"u": (("height", "latitude", "longitude"), np.full((2, 2, 2), 5.0), {"units": "m s-1"}),
                         "v": (("height", "latitude", "longitude"), np.zeros((2, 2, 2)), {"units": "m s-1"})},
                        coords={"height": ("height", np.asarray(heights, float), attrs),
                                "latitude": LAT, "longitude": LON})
        ds.to_netcdf(tmp_path / name)
        return tmp_path / name

    wind = W.read_wind(write("km.nc", [0.05, 0.2], "km"))
    np.testing.assert_allclose(wind["level"].values, [50.0, 200.0])
    for heights in ([np.nan, np.nan], [50.0, np.inf]):
        with pytest.raises(DataError, match=r"h\.nc: height levels 'height' are not all finite"):
            W.read_wind(write("h.nc", heights))
    with pytest.raises(DataError, match=r"variable 'height' \(level height\) has units 'parsec'"):
        W.read_wind(write("p.nc", [50.0, 200.0], "parsec"))


@pytest.mark.parametrize("data, traffic, want", [
    ({"uniform_wind": {"speed_mps": 1e6, "direction_deg": 270}}, None,
     "data.uniform_wind: speed_mps 1e+06 m/s is out of range: it must be at most 100 m/s"),
    ({"uniform_wind": {"speed_mps": 5, "direction_deg": 270, "elevation_deg": 120}}, None,
     "elevation_deg 120 deg is out of range"),
    ({}, {"intruders": [{"id": "fast", "waypoints": [[0, 385000, 6672000, 30], [1, 386000, 6672000, 30]]}]},
     "traffic.intruders[0].waypoints: waypoints 0 -> 1 are flown at 1000 m/s, faster than the 150 m/s"),
    ({}, {"intruders": [{"id": "back", "waypoints": [[5, 385000, 6672000, 30], [5, 385010, 6672000, 30]]}]},
     "times must increase strictly"),
])
def test_the_base_scenario_wind_and_strategic_intruders_are_bounded_too(data, traffic, want):
    """The bounds of the events hold for the scenario's own wind and known traffic (a base wind
    of 1e6 m/s was "no flyable plan" with exit 0)."""
    raw = _tiny_raw(**data)
    if traffic is not None:
        raw["traffic"] = traffic
    with pytest.raises(ScenarioError) as e:
        parse_scenario(raw)
    assert want in str(e.value), str(e.value)
