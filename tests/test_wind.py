"""Wind maps: uniform components, GFS sampling checked against hand bilinear interpolation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from pyproj import Transformer

from skyroute.pipeline.errors import DataError, InputError
from skyroute.stages import wind as W
from skyroute.stages.grid import Grid

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
GFS = SHARED / "wind" / "gfs_2011-01-15T12_wind.nc"
HEL_LON, HEL_LAT = 24.94, 60.17


@pytest.fixture(scope="module")
def raw():
    if not GFS.exists():
        pytest.skip(f"shared data missing: {GFS}")
    with xr.open_dataset(GFS) as ds:
        yield ds.load()


@pytest.fixture(scope="module")
def gfs():
    if not GFS.exists():
        pytest.skip(f"shared data missing: {GFS}")
    return W.read_wind(GFS, time="2011-01-15T12:00")


def hand_bilinear(raw, var, lon, lat, **sel):
    """Bilinear value from the four surrounding 2.5 deg nodes, weights written out."""
    lon360 = lon % 360.0
    lon_w = np.floor(lon360 / 2.5) * 2.5
    lon_e = (lon_w + 2.5) % 360.0
    lat_s = np.floor(lat / 2.5) * 2.5
    lat_n = lat_s + 2.5
    fx = (lon360 - lon_w) / 2.5
    fy = (lat - lat_s) / 2.5
    da = raw[var].sel(**sel) if sel else raw[var]

    def node(la, lo):
        return float(da.sel(latitude=la, longitude=lo))

    return ((1 - fx) * (1 - fy) * node(lat_s, lon_w) + fx * (1 - fy) * node(lat_s, lon_e)
            + (1 - fx) * fy * node(lat_n, lon_w) + fx * fy * node(lat_n, lon_e))


# ------------------------------------------------------------------ uniform wind

@pytest.mark.parametrize("direction, expected", [
    (0.0, (0.0, -5.0)),     # from north -> blows south
    (90.0, (-5.0, 0.0)),    # from east -> blows west
    (180.0, (0.0, 5.0)),
    (270.0, (5.0, 0.0)),    # from west -> blows east
    (45.0, (-5 / np.sqrt(2), -5 / np.sqrt(2))),
])
def test_uniform_wind_directions(direction, expected):
    u, v, w = W.uniform_wind(5.0, direction)
    assert u == pytest.approx(expected[0], abs=1e-12)
    assert v == pytest.approx(expected[1], abs=1e-12)
    assert w == 0.0


def test_uniform_wind_to_convention_and_elevation():
    u, v, w = W.uniform_wind(5.0, 90.0, convention="to")   # seed 000 Fig. 4: towards east
    assert (u, v) == pytest.approx((5.0, 0.0), abs=1e-12)
    u, v, w = W.uniform_wind(10.0, 0.0, elevation_deg=30.0)
    assert v == pytest.approx(-10 * np.cos(np.pi / 6), abs=1e-12)
    assert w == pytest.approx(5.0, abs=1e-12)
    assert np.sqrt(u**2 + v**2 + w**2) == pytest.approx(10.0, abs=1e-12)


def test_uniform_wind_bad_input():
    with pytest.raises(InputError, match="speed"):
        W.uniform_wind(-1.0, 0.0)
    with pytest.raises(InputError, match="elevation"):
        W.uniform_wind(1.0, 0.0, elevation_deg=120.0)
    with pytest.raises(InputError, match="convention"):
        W.uniform_wind(1.0, 0.0, convention="towards")


def test_uniform_on_grid_constant_and_power():
    g = Grid.from_bounds("EPSG:32635", 0, 0, 100, 60, 10.0)
    m = W.wind_on_grid((5.0, 270.0), g, [5.0, 10.0, 80.0])
    assert m["u"].dims == ("z", "y", "x") and m["u"].shape == (3, 6, 10)
    assert np.allclose(m["u"], 5.0) and np.allclose(m["v"], 0.0, atol=1e-12)
    assert m["u"].attrs["units"] == "m s-1" and m.rio.crs.to_epsg() == 32635
    p = W.wind_on_grid(W.UniformWind(5.0, 270.0), g, [5.0, 10.0, 80.0], profile="power")
    assert float(p["u"][1, 0, 0]) == pytest.approx(5.0, abs=1e-12)            # 10 m: the reference
    assert float(p["u"][2, 0, 0]) == pytest.approx(5.0 * 8 ** (1 / 7), abs=1e-9)
    assert float(p["speed"][0, 0, 0]) == pytest.approx(5.0 * 0.5 ** (1 / 7), abs=1e-9)
    with pytest.raises(InputError, match="levels"):
        W.wind_on_grid((5.0, 270.0), g, [10.0], profile="levels")
    with pytest.raises(InputError, match="increasing"):
        W.wind_on_grid((5.0, 270.0), g, [10.0, 5.0])


# ------------------------------------------------------------------ GFS file

def test_read_wind_canonical(gfs):
    assert set(gfs.data_vars) >= {"u", "v", "gh", "u10", "v10"}
    assert np.all(np.diff(gfs["latitude"].values) > 0)   # file is 90..-90: sorted ascending
    assert gfs.attrs["level_type"] == "pressure"
    assert gfs.attrs["valid_time"].startswith("2011-01-15 12:00")


def test_helsinki_10m_and_pressure_level_equal_hand_bilinear(raw, gfs):
    # Helsinki: nodes lat 60 / 62.5, lon 22.5 / 25; fx = 0.976, fy = 0.068
    u10 = hand_bilinear(raw, "u10", HEL_LON, HEL_LAT)
    v10 = hand_bilinear(raw, "v10", HEL_LON, HEL_LAT)
    fx, fy = (24.94 - 22.5) / 2.5, (60.17 - 60.0) / 2.5
    explicit = ((1 - fx) * (1 - fy) * float(raw.u10.sel(latitude=60.0, longitude=22.5))
                + fx * (1 - fy) * float(raw.u10.sel(latitude=60.0, longitude=25.0))
                + (1 - fx) * fy * float(raw.u10.sel(latitude=62.5, longitude=22.5))
                + fx * fy * float(raw.u10.sel(latitude=62.5, longitude=25.0)))
    assert u10 == pytest.approx(explicit, abs=1e-9)
    ground = 15.0
    gh850 = hand_bilinear(raw, "gh", HEL_LON, HEL_LAT, isobaricInhPa=850.0)
    u850 = hand_bilinear(raw, "u", HEL_LON, HEL_LAT, isobaricInhPa=850.0)
    v850 = hand_bilinear(raw, "v", HEL_LON, HEL_LAT, isobaricInhPa=850.0)
    r = W.wind_at_lonlat(gfs, HEL_LON, HEL_LAT, [10.0, gh850 - ground], ground_m=ground)
    assert r["u"][0, 0] == pytest.approx(u10, abs=1e-6)
    assert r["v"][0, 0] == pytest.approx(v10, abs=1e-6)
    assert r["u"][0, 1] == pytest.approx(u850, abs=1e-6)
    assert r["v"][0, 1] == pytest.approx(v850, abs=1e-6)
    assert abs(u10) > 1.0 and abs(u850 - u10) > 0.5    # the two checks are not the same number


def test_longitude_wrap_between_357_5_and_0(raw, gfs):
    lon, lat = -1.0, 51.5   # London: between longitude 357.5 and 0 (= 360)
    expected = hand_bilinear(raw, "u10", lon, lat)
    r = W.wind_at_lonlat(gfs, lon, lat, [10.0])
    assert r["u"][0, 0] == pytest.approx(expected, abs=1e-6)
    assert W.wind_at_lonlat(gfs, 359.0, lat, [10.0])["u"][0, 0] == pytest.approx(expected, abs=1e-6)


def test_wind_on_grid_cell_centres_and_terrain(raw, gfs):
    crs = "EPSG:32635"
    to_xy = Transformer.from_crs(4326, crs, always_xy=True)
    x, y = to_xy.transform(HEL_LON, HEL_LAT)
    g = Grid.from_bounds(crs, x - 2000, y - 1500, x + 2000, y + 1500, 20.0)
    terrain = g.dataarray(np.full(g.shape, 100.0), "terrain", units="m")
    to_ll = Transformer.from_crs(crs, 4326, always_xy=True)
    gh850_c = None
    m = None
    # pick the wind-grid cell (500 m) in row 1, col 2; its lon/lat by pyproj
    wg = W.wind_grid(g, 500.0)
    lon, lat = to_ll.transform(wg.x[2], wg.y[1])
    gh850_c = hand_bilinear(raw, "gh", lon, lat, isobaricInhPa=850.0)
    m = W.wind_on_grid(gfs, g, [10.0, gh850_c - 100.0], terrain=terrain, horizontal_step_m=500.0)
    assert m["u"].shape == (2, wg.ny, wg.nx) and m.rio.crs.to_epsg() == 32635
    assert float(m["u"][0, 1, 2]) == pytest.approx(hand_bilinear(raw, "u10", lon, lat), abs=1e-6)
    assert float(m["v"][0, 1, 2]) == pytest.approx(hand_bilinear(raw, "v10", lon, lat), abs=1e-6)
    assert float(m["u"][1, 1, 2]) == pytest.approx(
        hand_bilinear(raw, "u", lon, lat, isobaricInhPa=850.0), abs=1e-6)
    spd = np.hypot(m["u"].values, m["v"].values)
    assert np.allclose(m["speed"].values, spd)
    # point sampler: nearest column, linear in height
    u, v, w = W.sample_wind(m, wg.x[2] + 100, wg.y[1] - 100, 10.0)
    assert float(u) == pytest.approx(float(m["u"][0, 1, 2]), abs=1e-12)


def test_profiles_power_constant_and_continuity(gfs):
    z = np.array([2.0, 10.0, 40.0])
    pw = W.wind_at_lonlat(gfs, HEL_LON, HEL_LAT, z, profile="power")
    cs = W.wind_at_lonlat(gfs, HEL_LON, HEL_LAT, z, profile="constant")
    lv = W.wind_at_lonlat(gfs, HEL_LON, HEL_LAT, z, ground_m=0.0)
    u10 = cs["u"][0, 1]
    assert pw["u"][0, 1] == pytest.approx(u10, abs=1e-12)          # power law at 10 m = 10 m wind
    assert pw["u"][0, 2] == pytest.approx(u10 * 4 ** (1 / 7), abs=1e-9)
    assert np.allclose(cs["u"][0], u10)
    assert lv["u"][0, 0] == pytest.approx(u10 * 0.2 ** (1 / 7), abs=1e-9)   # below 10 m: power law
    # continuity at the lowest pressure level above the 10 m reference
    c = W.sample_columns(gfs, HEL_LON, HEL_LAT)
    h = np.sort(c["gh"][0])
    z1 = h[h > 11.0][0]
    around = W.wind_at_lonlat(gfs, HEL_LON, HEL_LAT, [z1 - 1e-3, z1 + 1e-3])
    assert abs(around["u"][0, 0] - around["u"][0, 1]) < 1e-3


def test_wind_nofly(gfs):
    g = Grid.from_bounds("EPSG:32635", 384000, 6670000, 388000, 6674000, 100.0)
    m = W.wind_on_grid(gfs, g, [10.0, 300.0], horizontal_step_m=1000.0)
    mask = W.wind_nofly(m, 14.0)
    assert mask.dtype == bool and mask.shape == m["speed"].shape
    assert np.array_equal(mask.values, m["speed"].values > 14.0)
    assert not mask.isel(z=0).any() and mask.isel(z=1).all()   # ~13.4 m/s at 10 m, ~15 m/s at 300 m
    with pytest.raises(InputError, match="max_wind_mps"):
        W.wind_nofly(m, 0.0)


# ------------------------------------------------------------------ errors

def test_missing_uv_names_file_and_variables(tmp_path):
    p = tmp_path / "no_wind.nc"
    ds = xr.Dataset({"t": (("latitude", "longitude"), np.zeros((3, 4))),
                     "gh": (("latitude", "longitude"), np.zeros((3, 4)))},
                    coords={"latitude": [0.0, 1.0, 2.0], "longitude": [0.0, 1.0, 2.0, 3.0]})
    ds.to_netcdf(p)
    with pytest.raises(DataError, match=r"no_wind\.nc.*\['gh', 't'\]"):
        W.read_wind(p)
    with pytest.raises(DataError, match="does not exist"):
        W.read_wind(tmp_path / "absent.nc")


def test_time_mismatch_and_outside_coverage(gfs, tmp_path):
    with pytest.raises(InputError, match="valid at 2011-01-15 12:00"):
        W.read_wind(GFS, time="2011-02-01T00:00")
    regional = xr.Dataset({"u10": (("lat", "lon"), np.ones((2, 2))), "v10": (("lat", "lon"), np.ones((2, 2)))},
                          coords={"lat": [50.0, 52.5], "lon": [0.0, 2.5]})
    with pytest.raises(DataError, match="outside the wind data"):
        W.wind_at_lonlat(regional, 24.94, 60.17, [10.0])
    r = W.wind_at_lonlat(regional, 1.0, 51.0, [10.0, 40.0], profile="levels")   # 10 m only -> power law
    assert r["u"][0, 1] == pytest.approx(4 ** (1 / 7), abs=1e-12)


def test_planner_kernel_and_numpy_sampler_share_the_wind_column_rule():
    """The compiled wind sample of the planner (planning.kernels.wind_at), the one numpy home
    (wind.wind_in_column, used by sample_wind and STEP III) agree in a wind field that varies
    in x, y and height, over sloped terrain, at random points (levels clamped outside)."""
    import numpy as np

    from skyroute.stages.grid import Grid
    from skyroute.stages.planning.kernels import WindParams, grid_params, wind_at
    from skyroute.stages.wind import wind_in_column

    rng = np.random.default_rng(4)
    g = Grid.from_bounds("EPSG:32635", 0, 0, 200, 120, 2.0)
    wg = Grid.from_bounds("EPSG:32635", 0, 0, 200, 120, 40.0)
    terrain = np.add.outer(np.linspace(30, 0, g.ny), np.linspace(0, 20, g.nx)) + rng.normal(0, 1, g.shape)
    wz = np.array([10.0, 30.0, 80.0, 150.0])
    w4 = rng.normal(0, 6, (wz.size, wg.ny, wg.nx, 3))
    x, y = rng.uniform(-10, 210, 3000), rng.uniform(-10, 130, 3000)
    z = rng.uniform(-20, 220, 3000)
    gp, wind = grid_params(g), WindParams(w4, wz, grid_params(wg))
    got = np.array([wind_at(x[i], y[i], z[i], terrain, gp, wind) for i in range(x.size)])
    h = z - terrain[g.cell_of(x, y)]
    want = wind_in_column(w4, wz, *wg.cell_of(x, y), h)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    # spatial variation is really exercised: neighbouring columns differ
    assert np.ptp(want[:, 0]) > 10
