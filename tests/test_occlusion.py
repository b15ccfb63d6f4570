"""Tests of skyroute.stages.occlusion against an exact prism ray caster (Amanatides-Woo)."""

from __future__ import annotations

import math
from pathlib import Path

import numba
import numpy as np
import pytest
import xarray as xr
from pyproj import Transformer

from skyroute.pipeline.errors import CRSError, InputError
from skyroute.stages.grid import Grid
from skyroute.stages.occlusion import (
    grid_azimuth_deg,
    shadow_halo_cells,
    visibility_height,
    visibility_heights_numpy,
)

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
SRTM = SHARED / "terrain" / "srtm_bigtujunga30m_utm11.tif"
ROTTERDAM = SHARED / "city" / "rotterdam_delfshaven_lod2.city.json"
HELSINKI = SHARED / "city" / "helsinki_center.osm.pbf"


# ----------------------------------------------------------------------------- oracle

@numba.njit(cache=True)
def prism_oracle(h, i, j, az_grid_deg, el_deg, cell_m):
    """Exact visibility height at the centre of cell (i, j) for flat-topped prism cells:
    walk every cell the horizontal ray crosses (Amanatides & Woo 1987 grid traversal) and
    take max(h(i, j), h(c) - t_entry(c) * tan(e)).  Outside the grid: no obstacle."""
    ny, nx = h.shape
    az = math.radians(az_grid_deg)
    dx = math.sin(az)    # columns per unit of horizontal distance (cell units)
    dy = -math.cos(az)   # rows (row index grows southward)
    tan_e = math.tan(math.radians(el_deg))
    x = j + 0.5
    y = i + 0.5
    cx = j
    cy = i
    big = 1e300
    step_x = 1 if dx > 0 else -1
    step_y = 1 if dy > 0 else -1
    t_dx = abs(1.0 / dx) if dx != 0 else big
    t_dy = abs(1.0 / dy) if dy != 0 else big
    if dx > 0:
        t_mx = (cx + 1 - x) / dx
    elif dx < 0:
        t_mx = (cx - x) / dx
    else:
        t_mx = big
    if dy > 0:
        t_my = (cy + 1 - y) / dy
    elif dy < 0:
        t_my = (cy - y) / dy
    else:
        t_my = big
    v = float(h[i, j])
    hmax = h.max()
    while True:
        if t_mx < t_my:
            t = t_mx
            t_mx += t_dx
            cx += step_x
        else:
            t = t_my
            t_my += t_dy
            cy += step_y
        if cx < 0 or cx >= nx or cy < 0 or cy >= ny:
            break
        drop = t * cell_m * tan_e
        if hmax - drop <= v:
            break
        c = h[cy, cx] - drop
        if c > v:
            v = c
    return v


# ----------------------------------------------------------------------------- real data

@pytest.fixture(scope="module")
def shared() -> Path:
    if not SHARED.is_dir():
        pytest.skip(f"shared real data folder {SHARED} is missing")
    return SHARED


@pytest.fixture(scope="module")
def srtm(shared) -> xr.DataArray:
    import rioxarray

    da = rioxarray.open_rasterio(SRTM).squeeze("band", drop=True)
    values = da.values.astype(np.float32)
    values[values == 32767] = np.nan
    da = da.copy(data=values)
    da.attrs = {"units": "m", "vertical_datum": "EGM96"}
    return da


def _shared_surface(grid: Grid, path: Path, fmt: str) -> xr.DataArray:
    """The lead's surface stage (terrain + flat-topped buildings) on ``grid``."""
    from skyroute.stages.surface import build_surface

    return build_surface(grid, buildings_path=path, buildings_format=fmt)["surface"]


@pytest.fixture(scope="module")
def rotterdam(shared) -> xr.DataArray:
    # the LoD2 extent of the file (EPSG:28992), 2 m cells
    grid = Grid.from_bounds("EPSG:28992", 90409.3, 435440.4, 91453.9, 436090.0, 2.0)
    return _shared_surface(grid, ROTTERDAM, "cityjson")


@pytest.fixture(scope="module")
def helsinki(shared) -> xr.DataArray:
    # the OSM extract (lat 60.164..60.179, lon 24.935..24.953) in UTM 35N, 2 m cells
    t = Transformer.from_crs(4326, "EPSG:32635", always_xy=True)
    (x0, x1), (y0, y1) = t.transform([24.935, 24.953], [60.164, 60.179])
    grid = Grid.from_bounds("EPSG:32635", x0, y0, x1, y1, 2.0)
    return _shared_surface(grid, HELSINKI, "osm")


def compare_with_oracle(surface: xr.DataArray, el_range, z_range_m, seed, n_dir=40, n_cell=50):
    """(agreement of visible/occluded decisions, 99th percentile of |error| / tolerance,
    all |errors|) at random cells, altitudes and directions."""
    h = np.asarray(surface.values, dtype=np.float32)
    cell = Grid.from_dataarray(surface).resolution_m
    rng = np.random.default_rng(seed)
    agree, ratio, errs = [], [], []
    for _ in range(n_dir):
        az = rng.uniform(0.0, 360.0)
        el = rng.uniform(*el_range)
        v = visibility_heights_numpy(h, az, el, cell)[0]
        ii = rng.integers(0, h.shape[0], n_cell)
        jj = rng.integers(0, h.shape[1], n_cell)
        tol = cell * math.tan(math.radians(el)) + 0.5
        for i, j in zip(ii, jj, strict=True):
            exact = prism_oracle(h, i, j, az, el, cell)
            z = rng.uniform(h[i, j], h[i, j] + z_range_m)
            agree.append((z >= exact) == (z >= v[i, j]))
            errs.append(abs(float(v[i, j]) - exact))
            ratio.append(errs[-1] / tol)
    return float(np.mean(agree)), float(np.percentile(ratio, 99)), np.asarray(errs)


# ----------------------------------------------------------------------------- exactness

def test_srtm_matches_prism_oracle(srtm):
    # 2000 random (cell, altitude, direction) samples, elevations 5..60 deg, altitudes up to
    # 300 m above ground; measured: agreement 0.9995, p99(err / tol) 0.57
    agree, p99_ratio, errs = compare_with_oracle(srtm, (5.0, 60.0), 300.0, seed=1)
    print(f"SRTM: agreement {agree:.4f}, p99 err/tol {p99_ratio:.3f}, p99 err {np.percentile(errs, 99):.2f} m")
    assert agree >= 0.995
    assert p99_ratio < 1.0
    assert np.median(errs) < 0.5


@pytest.mark.parametrize("city", ["rotterdam", "helsinki"])
def test_city_surfaces_match_prism_oracle(city, request):
    # 2 m surfaces of the surface stage (Rotterdam LoD2 CityJSON, Helsinki OSM buildings),
    # elevations 10..70 deg, altitudes up to 50 m above roof or ground
    surface = request.getfixturevalue(city)
    agree, p99_ratio, errs = compare_with_oracle(surface, (10.0, 70.0), 50.0, seed=2)
    print(f"{city}: agreement {agree:.4f}, p99 err/tol {p99_ratio:.3f}, p99 err {np.percentile(errs, 99):.2f} m")
    assert agree >= 0.995
    assert p99_ratio < 1.0
    assert np.median(errs) < 0.01


@pytest.mark.parametrize("az", [0.0, 90.0, 180.0, 270.0])
def test_axis_directions_are_exact(srtm, az):
    # along the grid axes every cell centre lies on a scan line: the scan is exact.  (On
    # diagonals rays pass exactly through cell corners, where prisms only touch the ray and
    # the oracle and the scan may legitimately pick different corner cells.)
    h = srtm.values.astype(np.float32)
    v = visibility_heights_numpy(h, az, 12.0, 30.0)[0]
    rng = np.random.default_rng(int(az))
    ii = rng.integers(0, h.shape[0], 300)
    jj = rng.integers(0, h.shape[1], 300)
    exact = np.array([prism_oracle(h, i, j, az, 12.0, 30.0) for i, j in zip(ii, jj, strict=True)])
    np.testing.assert_allclose(v[ii, jj], exact, atol=1e-3)


def test_more_nearest_lines_converge_to_exact(rotterdam):
    h = rotterdam.values
    rng = np.random.default_rng(5)
    ii = rng.integers(0, h.shape[0], 400)
    jj = rng.integers(0, h.shape[1], 400)
    exact = np.array([prism_oracle(h, i, j, 33.3, 20.0, 2.0) for i, j in zip(ii, jj, strict=True)])
    err = {}
    for q in (1, 8):
        v = visibility_heights_numpy(h, 33.3, 20.0, 2.0, lines_per_cell=q, lateral="nearest")[0]
        err[q] = np.abs(v[ii, jj] - exact).mean()
    assert err[8] < 0.5 * err[1]


def test_single_prism_closed_form():
    # flat ground 0 m, one 30 m prism; sun from due east at 20 deg: cells west of it in its
    # row need 30 - (distance to its west... east face) * tan(20), others are free
    c = 2.0
    h = np.zeros((9, 40), np.float32)
    h[4, 30] = 30.0
    v = visibility_heights_numpy(h, 90.0, 20.0, c)[0]
    j = np.arange(30)
    expected = np.maximum(30.0 - (30 - j - 0.5) * c * math.tan(math.radians(20.0)), 0.0)
    np.testing.assert_allclose(v[4, :30], expected, atol=1e-4)
    assert v[4, 30] == 30.0
    assert np.all(v[4, 31:] == 0.0)
    assert np.all(v[[0, 1, 2, 3, 5, 6, 7, 8]] == 0.0)
    # satellite in the west: the shadow falls east
    v = visibility_heights_numpy(h, 270.0, 20.0, c)[0]
    assert v[4, 31] == pytest.approx(30.0 - 0.5 * c * math.tan(math.radians(20.0)), abs=1e-4)
    assert np.all(v[4, :30] == 0.0)


def test_output_properties(srtm):
    sub = srtm.isel(y=slice(0, 120), x=slice(0, 150))
    vh = visibility_height(sub, [10.0, 200.0], [15.0, 50.0])
    assert vh.dims == ("direction", "y", "x")
    assert vh.rio.crs == sub.rio.crs
    assert vh.attrs["units"] == "m" and vh.attrs["vertical_datum"] == "EGM96"
    np.testing.assert_array_equal(vh["x"], sub["x"])
    assert vh.dtype == np.float32
    assert np.all(np.isfinite(vh))
    assert np.all(vh >= sub.values)
    # steeper satellite -> lower or equal visibility height somewhere everywhere on average
    assert float(vh.isel(direction=1).mean()) < float(vh.isel(direction=0).mean())
    one = visibility_height(sub, 10.0, 15.0)
    assert one.dims == ("y", "x")
    np.testing.assert_array_equal(one.values, vh.isel(direction=0).values)


# ----------------------------------------------------------------------------- azimuths

@pytest.mark.parametrize("lon", [-118.6, -116.0])
def test_grid_azimuth_sign_from_meridian(lon):
    # grid azimuth of true north = direction of a short step north along the meridian
    lat = 34.3
    crs = "EPSG:32611"
    t = Transformer.from_crs(4326, crs, always_xy=True)
    x0, y0 = t.transform(lon, lat)
    x1, y1 = t.transform(lon, lat + 1e-3)
    expected = math.degrees(math.atan2(x1 - x0, y1 - y0))
    grid = Grid.from_bounds(crs, x0 - 3000, y0 - 3000, x0 + 3000, y0 + 3000, 30.0)
    got = grid_azimuth_deg(0.0, grid)
    assert ((got - expected + 180) % 360 - 180) == pytest.approx(0.0, abs=2e-3)
    assert abs(expected) > 0.5  # the test can see a sign error
    arr = grid_azimuth_deg(np.array([90.0, 359.9]), grid)
    np.testing.assert_allclose(arr, np.mod([90.0 + expected, 359.9 + expected], 360), atol=2e-3)


def test_true_azimuth_is_turned_to_grid(srtm):
    sub = srtm.isel(y=slice(0, 100), x=slice(0, 100))
    gamma_grid = grid_azimuth_deg(0.0, sub)
    assert 0.4 < gamma_grid < 1.5  # Big Tujunga lies west of the zone 11 central meridian
    a = visibility_height(sub, 37.0, 20.0, azimuth="true")
    b = visibility_height(sub, 37.0 + gamma_grid, 20.0, azimuth="grid")
    np.testing.assert_array_equal(a.values, b.values)
    assert float(a["grid_azimuth_deg"]) == pytest.approx(37.0 + gamma_grid)


# ----------------------------------------------------------------------------- dask

@pytest.mark.parametrize("el, chunks", [
    ((55.0, 70.0, 80.0), (80, 90)),   # halo 34 cells < chunks: plain overlaps
    ((40.0, 60.0), (70, 100)),        # halo 56: last row chunk (30) merged, overlaps
    ((8.0, 30.0), (100, 120)),        # halo 322 > map: chunks merged into one
    ((45.0, 45.0, 45.0, 45.0), (90, 100)),  # + a 1500 m mast: its shadows cross chunks
])
def test_chunked_equals_unchunked(srtm, el, chunks):
    sub = srtm.isel(y=slice(100, 340), x=slice(200, 560)).copy()
    if len(el) == 4:
        sub.values[60, 60] += 1500.0  # 30 cells inside its chunk, shadow ~50 cells
    az = np.linspace(17.0, 320.0, len(el))
    ref = visibility_height(sub, az, list(el))
    lazy = visibility_height(sub.chunk({"y": chunks[0], "x": chunks[1]}), az, list(el))
    assert lazy.chunks is not None
    halo = shadow_halo_cells(sub, min(el), 30.0)
    if halo < 100:
        assert lazy.data.numblocks[1] > 1 and lazy.data.numblocks[2] > 1
    np.testing.assert_array_equal(lazy.values, ref.values)


def test_shadow_halo_cells_closed_form():
    h = np.zeros((5, 5), np.float32)
    h[2, 2] = 100.0
    assert shadow_halo_cells(h, 60.0, 10.0) == 6 + 2  # 100 m / tan 60 = 57.7 m = 5.8 cells
    assert shadow_halo_cells(h, 5.0, 10.0) == 115 + 2  # 1143 m
    # the halo is enough: farther obstacles do not change the result
    rng = np.random.default_rng(3)
    big = rng.uniform(0, 40, (200, 200)).astype(np.float32)
    halo = shadow_halo_cells(big, 30.0, 5.0)
    full = visibility_heights_numpy(big, 123.0, 30.0, 5.0)[0]
    lo, hi = 100 - 10, 100 + 10
    crop = big[lo - halo:hi + halo, lo - halo:hi + halo]
    part = visibility_heights_numpy(crop, 123.0, 30.0, 5.0, origin=(lo - halo, lo - halo))[0]
    np.testing.assert_array_equal(part[halo:-halo, halo:-halo], full[lo:hi, lo:hi])


# ----------------------------------------------------------------------------- bad input

def test_nan_holes_refused_or_filled(srtm):
    sub = srtm.isel(y=slice(0, 60), x=slice(0, 60)).copy()
    sub.values[8:15, 18:24] = 900.0  # a plateau: every nearest-neighbour fill gives 900
    filled = sub.values.copy()
    sub.values[10:13, 20:22] = np.nan
    with pytest.raises(InputError, match="NaN.*fill_nan='nearest'"):
        visibility_height(sub, 100.0, 30.0)
    got = visibility_height(sub, 100.0, 30.0, fill_nan="nearest")
    expect = visibility_height(sub.copy(data=filled), 100.0, 30.0)
    np.testing.assert_array_equal(got.values, expect.values)
    with pytest.raises(InputError, match="NaN"):
        visibility_height(sub.chunk(30), 100.0, 30.0)


def test_bad_directions_and_grids(srtm):
    sub = srtm.isel(y=slice(0, 30), x=slice(0, 30))
    with pytest.raises(InputError, match=r"out of \(0, 90\]"):
        visibility_height(sub, [10.0, 20.0], [15.0, 0.0])
    with pytest.raises(InputError, match=r"out of \(0, 90\]"):
        visibility_height(sub, 10.0, -5.0)
    with pytest.raises(InputError, match="equal length"):
        visibility_height(sub, [10.0, 20.0], [15.0])
    with pytest.raises(InputError, match="azimuth must be"):
        visibility_height(sub, 10.0, 15.0, azimuth="magnetic")
    with pytest.raises(InputError, match="dims"):
        visibility_height(sub.T, 10.0, 15.0)
    geo = Grid.from_bounds("EPSG:4326", 24.9, 60.1, 24.95, 60.15, 0.01)
    with pytest.raises(CRSError, match="not projected"):
        grid_azimuth_deg(10.0, geo)
    with pytest.raises(InputError, match="lines_per_cell=1"):
        visibility_height(sub, 10.0, 15.0, lines_per_cell=4)


# ----------------------------------------------------------------------------- CLI

def test_cli_writes_geotiff(tmp_path, srtm):
    import rasterio
    from click.testing import CliRunner

    from skyroute.pipeline.cli_occlusion import visibility_height_command

    sub = srtm.isel(y=slice(0, 50), x=slice(0, 70))
    src = tmp_path / "surface.tif"
    sub.rio.to_raster(src)
    out = tmp_path / "vh.tif"
    res = CliRunner().invoke(visibility_height_command, ["--surface", str(src), "--az-deg", "250",
                                                         "--el-deg", "20", "--out", str(out)])
    assert res.exit_code == 0, res.output
    with rasterio.open(out) as ds:
        got = ds.read(1)
        assert ds.crs.to_epsg() == 32611
        assert ds.transform == Grid.from_dataarray(sub).transform
    expect = visibility_heights_numpy(sub.values, 250.0, 20.0, 30.0)[0]
    np.testing.assert_array_equal(got, expect)
    assert "GRID north" in CliRunner().invoke(visibility_height_command, ["--help"]).output
    bad = CliRunner().invoke(visibility_height_command, ["--surface", str(src), "--az-deg", "250",
                                                         "--el-deg", "0", "--out", str(out)])
    assert isinstance(bad.exception, InputError)
