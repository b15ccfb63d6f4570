"""Issue 34, the wind findings of the input fuzzer (benchmarks/fuzz_inputs.py): a forecast file
with an extra dimension (an ensemble ``number``), a file declaring far more values than it holds
(3 x 20000 x 20000, a few hundred kB on disk), wind components that are not winds (3e38 m/s) and
latitude / longitude coordinates that are NaN, inf, out of range or not monotonic.  Each is one
DataError (CLI: one ``error:`` line, exit 2) before any variable is loaded."""

from __future__ import annotations

import re
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from skyroute.pipeline.errors import DataError
from skyroute.stages import base as B
from skyroute.stages import wind as W

LAT = np.array([35.0, 34.5, 34.0, 33.5])          # descending, as GRIB / ERA5 files store it
LON = np.array([241.0, 241.5, 242.0, 242.5])
P_HPA = np.array([1000.0, 925.0, 850.0])
DIMS3, DIMS2 = ("isobaricInhPa", "latitude", "longitude"), ("latitude", "longitude")
SP = {"units": "m s**-1"}


def _forecast(u: float = 5.0, v10: float = 1.0) -> xr.Dataset:
    """A 4 x 4 forecast on 3 pressure levels (the fuzzer's base file): u = ``u`` on the levels,
    v = 1, gh = 100 / 800 / 1500 gpm, u10 = 3, v10 = ``v10`` [m/s]."""
    gh = np.broadcast_to(np.array([100.0, 800.0, 1500.0])[:, None, None], (3, 4, 4)).astype(np.float32)
    return xr.Dataset({"u": (DIMS3, np.full((3, 4, 4), u, np.float32), dict(SP)),
                       "v": (DIMS3, np.full((3, 4, 4), 1.0, np.float32), dict(SP)),
                       "gh": (DIMS3, gh.copy(), {"units": "gpm"}),
                       "u10": (DIMS2, np.full((4, 4), 3.0, np.float32), dict(SP)),
                       "v10": (DIMS2, np.full((4, 4), v10, np.float32), dict(SP))},
                      coords={"isobaricInhPa": ("isobaricInhPa", P_HPA, {"units": "hPa"}),
                              "latitude": ("latitude", LAT, {"units": "degrees_north"}),
                              "longitude": ("longitude", LON, {"units": "degrees_east"}),
                              "valid_time": np.datetime64("2020-01-03T18:00")})


def _write(ds: xr.Dataset, path: Path) -> Path:
    ds.to_netcdf(path)
    return path


# ------------------------------------------------------------------ 1. extra dimensions

def test_a_length_one_ensemble_dimension_is_dropped(tmp_path):
    """Before: ValueError ('level', 'latitude', 'longitude') must be a permuted list of
    ('number', 'level', ...) from a transpose (--repro wind:extra-dim:*)."""
    ds = _forecast()
    ds["u"] = ds["u"] * xr.DataArray(np.linspace(0.5, 2.0, 4), dims="longitude")   # varies with lon
    plain = W.read_wind(_write(ds, tmp_path / "plain.nc"))
    one = W.read_wind(_write(ds.expand_dims(number=1).expand_dims(step=1), tmp_path / "one.nc"))
    assert one["u"].dims == ("level", "latitude", "longitude") and one["u10"].dims == ("latitude", "longitude")
    for k in ("u", "v", "gh", "u10", "v10"):
        np.testing.assert_array_equal(one[k].values, plain[k].values)
    # u at the first level along latitude 33.5 (the first row once sorted ascending): 5 * (0.5 .. 2)
    np.testing.assert_allclose(one["u"].values[0, 0], 5.0 * np.linspace(0.5, 2.0, 4), rtol=1e-6)


@pytest.mark.parametrize("dim, n", [("number", 5), ("step", 2)])
def test_a_longer_extra_dimension_is_refused_with_the_fix(tmp_path, dim, n):
    p = _write(_forecast().expand_dims({dim: n}), tmp_path / "ens.nc")
    with pytest.raises(DataError, match=rf"ens\.nc: variable 'u' has the dimension '{dim}' of length {n} besides "
                                        rf"latitude, longitude and 'isobaricInhPa' .*select one first, e\.g\. "
                                        rf"ncks -d {dim},0 IN\.nc OUT\.nc or xarray ds\.isel\({dim}=0\)"):
        W.read_wind(p)


def test_a_10m_wind_with_a_longer_extra_dimension_is_refused(tmp_path):
    ds = _forecast().drop_vars(["u", "v", "gh", "isobaricInhPa"])
    ds["v10"] = ds["v10"].expand_dims(number=3)
    with pytest.raises(DataError, match=r"variable 'v10' has the dimension 'number' of length 3 besides "
                                        r"latitude, longitude \(e\.g\."):
        W.read_wind(_write(ds, tmp_path / "e.nc"))


# ------------------------------------------------------------------ 2. the declared size is bounded

def _declared(path: Path, n: int, levels: int = 3) -> Path:
    """A NetCDF-4 file declaring u, v, gh as ``levels`` x n x n float32 without writing them."""
    import netCDF4

    with netCDF4.Dataset(path, "w") as nc:
        nc.createDimension("isobaricInhPa", levels)
        nc.createDimension("latitude", n)
        nc.createDimension("longitude", n)
        nc.createVariable("isobaricInhPa", "f8", ("isobaricInhPa",))[:] = np.linspace(1000.0, 850.0, levels)
        nc.createVariable("latitude", "f8", ("latitude",))[:] = np.linspace(89.9, -89.9, n)
        nc.createVariable("longitude", "f8", ("longitude",))[:] = np.linspace(0, 359.98, n)
        for name, units in (("u", "m s-1"), ("v", "m s-1"), ("gh", "gpm")):
            vv = nc.createVariable(name, "f4", ("isobaricInhPa", "latitude", "longitude"), zlib=True,
                                   chunksizes=(1, min(n, 500), min(n, 500)), fill_value=np.float32(1.0))
            vv.units = units
    return path


def test_a_file_declaring_20000_x_20000_values_is_refused_before_reading(tmp_path, monkeypatch):
    """Before: ``run --stage wind --max-memory 2G`` on this 330 kB file used 20.1 GB and 27-51 s
    (--repro wind:huge-declared:1 --unsafe)."""
    p = _declared(tmp_path / "huge.nc", 20000)
    assert p.stat().st_size < 2_000_000
    monkeypatch.setattr(B, "memory_limit_hook", lambda: 2 * 1024**3)
    tracemalloc.start()
    try:
        with pytest.raises(DataError) as e:
            W.read_wind(p)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 50e6, peak                      # nothing of the 3.6e9 values was allocated
    need = 3 * 3 * 20000 * 20000 * (4 + 16)       # u, v, gh in float32 + a float64 copy + a temporary
    assert f"needs about {need / 2**30:,.1f} GiB of memory, more than --max-memory (2.0 GiB)" in str(e.value)
    assert "'u', 'v', 'gh' declare 3,600,000,000 values ('u': 3 x 20,000 x 20,000" in str(e.value)
    assert "cdo sellonlatbox" in str(e.value) and "or raise --max-memory" in str(e.value)


def test_the_estimate_and_the_value_cap_without_a_memory_limit(tmp_path, monkeypatch):
    p = _declared(tmp_path / "mid.nc", 200, levels=2)
    with xr.open_dataset(p) as ds:
        need = W.check_wind_read_bytes(ds, ["u", "v", "gh"], "mid.nc", limit_bytes=1e12)
        assert need == 3 * 2 * 200 * 200 * (4 + W.READ_BYTES_PER_VALUE)
        with pytest.raises(DataError, match=r"mid\.nc: reading the wind needs about 5 MiB of memory, more than "
                                            r"--max-memory \(1 MiB\)"):
            W.check_wind_read_bytes(ds, ["u", "v", "gh"], "mid.nc", limit_bytes=2**20)
    monkeypatch.setattr(B, "memory_limit_hook", None)           # no --max-memory: the cap still holds
    monkeypatch.setattr(W, "MAX_WIND_VALUES", 200_000)
    with pytest.raises(DataError, match=r"mid\.nc: variables 'u', 'v', 'gh' declare 240,000 values \('u': "
                                        r"2 x 200 x 200 .*more than the 200,000 values skyroute reads"):
        W.read_wind(p)


def test_only_the_selected_time_counts(tmp_path, monkeypatch):
    """A file of 3 times: the estimate is that of the one time read."""
    ds = _forecast().drop_vars("valid_time").expand_dims(
        time=np.array(["2020-01-03T12:00", "2020-01-03T18:00", "2020-01-04T00:00"], "datetime64[ns]"))
    p = _write(ds, tmp_path / "t.nc")
    one_time = (3 * 3 * 16 + 2 * 16) * (4 + W.READ_BYTES_PER_VALUE)   # u, v, gh + u10, v10 of one time
    monkeypatch.setattr(B, "memory_limit_hook", lambda: one_time)
    wind = W.read_wind(p, time="2020-01-03T18:00")
    assert float(wind["u"][0, 0, 0]) == 5.0
    monkeypatch.setattr(B, "memory_limit_hook", lambda: one_time - 1)
    with pytest.raises(DataError, match="reading the wind needs about"):
        W.read_wind(p, time="2020-01-03T18:00")


# ------------------------------------------------------------------ 3. physically impossible data

def test_the_bound_is_the_one_of_the_scenario_wind_and_events():
    from skyroute.pipeline.settings import common

    assert W.MAX_WIND_SPEED_MPS == common.MAX_WIND_SPEED_MPS == 100.0


@pytest.mark.parametrize("var, value, profile", [("v10", 3e38, "power"), ("u", -1e30, "levels"),
                                                 ("u10", 100.5, "constant")])
def test_a_wind_component_above_100_mps_where_sampled_is_refused(tmp_path, var, value, profile):
    """Before: v10 = 3e38 m/s with the power profile was exit 0, no warning
    (--repro wind:huge-data:*)."""
    ds = _forecast()
    a = ds[var].values.copy()
    a[..., 1, 1] = value                          # lat 34.5, lon 241.5: a corner of the cell sampled
    ds[var] = (ds[var].dims, a, ds[var].attrs)
    wind = W.read_wind(_write(ds, tmp_path / "big.nc"))
    with pytest.raises(DataError, match=rf"big\.nc: wind component '{var}' is {re.escape(f'{value:g}')} m/s around "
                                        r"lon=241\.7000, lat=34\.3000, more than 100 m/s in magnitude"):
        W.wind_at_lonlat(wind, 241.7, 34.3, [10.0, 50.0], profile=profile)


def test_the_bound_applies_after_the_unit_conversion_and_only_where_sampled(tmp_path):
    ds = _forecast()
    ds["u10"] = (DIMS2, np.full((4, 4), 300.0, np.float32), {"units": "km h-1"})      # 83.3 m/s: a wind
    ds["v10"] = (DIMS2, np.full((4, 4), 300.0, np.float32), {"units": "m s-1"})
    ds["v10"][0, 3] = 1.0                                        # lat 35, lon 242.5: the only sane cell
    wind = W.read_wind(_write(ds, tmp_path / "kmh.nc"))
    with pytest.raises(DataError, match=r"wind component 'v10' is 300 m/s"):
        W.wind_at_lonlat(wind, 241.7, 34.3, [10.0], profile="power")
    ds["v10"] = (DIMS2, np.ones((4, 4), np.float32), {"units": "m s-1"})
    ds["v10"][3, 0] = 3e38                                       # lat 33.5, lon 241: not sampled
    r = W.wind_at_lonlat(W.read_wind(_write(ds, tmp_path / "far.nc")), 241.7, 34.3, [10.0], profile="power")
    assert float(r["u"][0, 0]) == pytest.approx(300.0 / 3.6, rel=1e-6)
    assert float(r["v"][0, 0]) == pytest.approx(1.0)


def test_a_renamed_component_is_named_as_in_the_file(tmp_path):
    ds = _forecast().rename({"u10": "uas"})
    ds["uas"][1, 1] = 1e6
    wind = W.read_wind(_write(ds, tmp_path / "uas.nc"))
    with pytest.raises(DataError, match=r"wind component 'u10' \(variable 'uas' of the file\) is 1e\+06 m/s"):
        W.wind_at_lonlat(wind, 241.7, 34.3, [10.0], profile="power")


@pytest.mark.parametrize("coord, values, want", [
    ("latitude", [35.0, 34.5, np.nan, 33.5], r"coordinate 'latitude' holds nan at index 2, not a finite number"),
    ("latitude", [np.inf, 34.5, 34.0, 33.5], r"coordinate 'latitude' holds inf at index 0, not a finite number"),
    ("latitude", [91.0, 34.5, 34.0, 33.5], r"coordinate 'latitude' holds 91\.0 at index 0, outside \[-90, 90\] deg"),
    ("longitude", [601.0, 601.5, 602.0, 602.5],
     r"coordinate 'longitude' holds 601\.0 at index 0, outside \[-180, 360\] deg"),
    ("longitude", [-181.0, 241.5, 242.0, 242.5], r"coordinate 'longitude' holds -181\.0 at index 0"),
    ("latitude", [35.0, 34.5, 34.5, 33.5],
     r"coordinate 'latitude' is not strictly monotonic: 34\.5 at index 1 is followed by 34\.5"),
    ("longitude", [241.0, 242.0, 241.5, 242.5],
     r"coordinate 'longitude' is not strictly monotonic: 242\.0 at index 1 is followed by 241\.5"),
])
def test_bad_latitude_longitude_coordinates_are_refused(tmp_path, coord, values, want):
    """Before: latitudes holding NaN, inf or 91 were accepted, exit 0 (--repro wind:lat-nan:1..4)."""
    ds = _forecast().assign_coords({coord: (coord, np.array(values), {"units": "degrees"})})
    with pytest.raises(DataError, match=r"bad\.nc: " + want):
        W.read_wind(_write(ds, tmp_path / "bad.nc"))


def test_ascending_descending_and_minus_180_coordinates_still_read(tmp_path):
    ds = _forecast().assign_coords(longitude=("longitude", LON - 360.0, {"units": "degrees_east"}))
    wind = W.read_wind(_write(ds, tmp_path / "w.nc"))
    np.testing.assert_array_equal(wind["latitude"].values, LAT[::-1])
    r = W.wind_at_lonlat(wind, -118.3, 34.3, [10.0], profile="constant")
    assert float(r["u"][0, 0]) == pytest.approx(3.0) and float(r["v"][0, 0]) == pytest.approx(1.0)


# ------------------------------------------------------------------ through the CLI

def test_cli_one_error_line_for_an_ensemble_file(tmp_path):
    """``skyroute run S --stage wind``: exit 2, one ``error:`` line, no traceback."""
    import yaml
    from click.testing import CliRunner

    from skyroute.pipeline.cli import main

    p = _write(_forecast().expand_dims(number=2), tmp_path / "ens.nc")
    raw = {"name": "wind-ens", "aoi": {"bounds": [383010, 3794010, 383310, 3794310], "crs": "EPSG:32611",
                                       "resolution_m": 50.0},
           "data": {"wind": {"path": str(p), "time_utc": "2020-01-03T18:00:00Z"}},
           "mission": {"start": {"x": 383060, "y": 3794060, "alt_agl_m": 30},
                       "goal": {"x": 383260, "y": 3794260, "alt_agl_m": 30},
                       "start_time_utc": "2020-01-03T18:00:00Z"}}
    scen = tmp_path / "s.yaml"
    scen.write_text(yaml.safe_dump(raw))
    res = CliRunner().invoke(main, ["run", str(scen), "--stage", "wind", "--max-memory", "2G", "-q", "--no-report",
                                    "--out", str(tmp_path / "out"), "--cache-dir", str(tmp_path / "cache")])
    out = res.output
    assert res.exit_code == 2, out
    assert "Traceback" not in out, out
    errors = [ln for ln in out.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1, out
    assert "variable 'u' has the dimension 'number' of length 2" in errors[0], out
