"""Tests of skyroute.stages.occlusion (conservative column scan) and skyroute.stages.raycast
(exact prism caster) against an independent exact oracle (tests/_prism_oracle.py: every cell
within reach tested on its own by ray/box slab intersection, no grid traversal).

The contract: the value stored for a cell is >= the exact prism value at every point of the
cell (up to 0.01 m); over-estimation is allowed and measured.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from _prism_oracle import oracle_points, shadow_edge_points
from pyproj import Transformer

from skyroute.pipeline.errors import CRSError, InputError
from skyroute.stages.grid import Grid
from skyroute.stages.occlusion import (
    grid_azimuth_deg,
    occluder_window,
    shadow_halo_cells,
    visibility_height,
    visibility_heights_numpy,
)
from skyroute.stages.raycast import exact_visibility_height, exact_visibility_heights_numpy

CATALOG = Path(__file__).resolve().parents[1] / "catalogs" / "data"
SRTM = CATALOG / "srtm_bigtujunga30m_utm11.tif"  # the shipped copy of shared/data/terrain's file
ROTTERDAM = CATALOG / "rotterdam_delfshaven_lod2.city.json"
HELSINKI = CATALOG / "helsinki_center.osm.pbf"
MONACO = CATALOG / "monaco_2019-09-30.osm.pbf"
TOL_M = 0.01  # numerical tolerance of the contract [m]


# ----------------------------------------------------------------------------- surfaces

@pytest.fixture(scope="module")
def srtm() -> xr.DataArray:
    import rioxarray

    da = rioxarray.open_rasterio(SRTM).squeeze("band", drop=True)
    values = da.values.astype(np.float32)
    values[values == 32767] = np.nan
    da = da.copy(data=values)
    da.attrs = {"units": "m", "vertical_datum": "EGM96"}
    return da


def _surface(grid: Grid, path: Path, fmt: str) -> xr.DataArray:
    """The surface stage (terrain + flat-topped buildings) on ``grid``."""
    from skyroute.stages.surface import build_surface

    return build_surface(grid, buildings_path=path, buildings_format=fmt)["surface"]


def _lonlat_grid(crs: str, lon0: float, lat0: float, lon1: float, lat1: float) -> Grid:
    t = Transformer.from_crs(4326, crs, always_xy=True)
    (x0, x1), (y0, y1) = t.transform([lon0, lon1], [lat0, lat1])
    return Grid.from_bounds(crs, x0, y0, x1, y1, 2.0)


@pytest.fixture(scope="module")
def rotterdam() -> xr.DataArray:
    # part of the LoD2 extent of the shipped file (EPSG:28992), 2 m cells
    grid = Grid.from_bounds("EPSG:28992", 90900.0, 435650.0, 91400.0, 436000.0, 2.0)
    return _surface(grid, ROTTERDAM, "cityjson")


@pytest.fixture(scope="module")
def helsinki() -> xr.DataArray:
    # the centre of the shipped OSM extract in UTM 35N, 2 m cells
    return _surface(_lonlat_grid("EPSG:32635", 24.935, 60.164, 24.947, 60.171), HELSINKI, "osm")


@pytest.fixture(scope="module")
def monaco() -> xr.DataArray:
    return _surface(_lonlat_grid("EPSG:32632", 7.415, 43.730, 7.425, 43.738), MONACO, "osm")


def towers_city(seed: int = 7, n: int = 180) -> xr.DataArray:
    """Synthetic downtown (always available): 2 m cells, 45 rectangular towers of 10..210 m
    on flat ground, some touching."""
    rng = np.random.default_rng(seed)
    h = np.zeros((n, n), np.float32)
    for _ in range(45):
        w, length = rng.integers(2, 14, 2)
        i, j = rng.integers(0, n - 14, 2)
        h[i:i + w, j:j + length] = max(float(h[i:i + w, j:j + length].max()),
                                       rng.uniform(10.0, 210.0))
    g = Grid.from_bounds("EPSG:32631", 600000.0, 5700000.0, 600000.0 + 2 * n, 5700000.0 + 2 * n, 2.0)
    return g.dataarray(h, "surface", units="m", vertical_datum="EGM96")


# ----------------------------------------------------------------------------- the contract

def check_conservative(surface: xr.DataArray, seed: int, n_dir: int = 16, n_pts: int = 600,
                       n_edge: int = 200, n_cell: int = 120, el_range=(5.0, 60.0),
                       z_range_m: float = 50.0):
    """Zero unsafe values at random interior points and on shadow edges; returns (share of
    agreeing visible/occluded decisions at cell centres outside the band cell tan(el) +
    0.5 m, the same share for the sampled supremum over each cell, mean over-estimation
    [m] at the points)."""
    h = np.asarray(surface.values, dtype=np.float32)
    cell = Grid.from_dataarray(surface).resolution_m
    ny, nx = h.shape
    rng = np.random.default_rng(seed)
    agree, agree_sup, over = [], [], []
    for _ in range(n_dir):
        az, el = rng.uniform(0.0, 360.0), rng.uniform(*el_range)
        v = visibility_heights_numpy(h, az, el, cell)[0]
        er, ec = shadow_edge_points(h, az, el, cell, n_edge, rng)
        r = np.r_[rng.uniform(0, ny, n_pts), er]
        c = np.r_[rng.uniform(0, nx, n_pts), ec]
        exact = oracle_points(h, r, c, az, el, cell)
        i = np.minimum(r.astype(int), ny - 1)
        j = np.minimum(c.astype(int), nx - 1)
        # a point exactly on a cell edge belongs to both cells: take the cell it was cut from
        diff = v[i, j] - exact
        bad = np.flatnonzero(diff < -TOL_M)
        assert bad.size == 0, (f"unsafe: az {az:.2f} el {el:.2f} point (row, col) "
                               f"({r[bad[0]]:.6f}, {c[bad[0]]:.6f}) scan {v[i[bad[0]], j[bad[0]]]:.3f}"
                               f" < exact {exact[bad[0]]:.3f} m")
        over.append(diff)
        ii, jj = rng.integers(0, ny, n_cell), rng.integers(0, nx, n_cell)
        centre = oracle_points(h, ii + 0.5, jj + 0.5, az, el, cell)
        # the best any per-cell value valid for every point can do: the supremum over the
        # cell, sampled on 7 x 7 interior points
        sr = (ii[:, None] + _GR).ravel()
        sc = (jj[:, None] + _GC).ravel()
        sup = oracle_points(h, sr, sc, az, el, cell).reshape(n_cell, -1).max(axis=1)
        z = h[ii, jj] + rng.uniform(0.0, z_range_m, n_cell)
        out = np.abs(z - centre) > cell * math.tan(math.radians(el)) + 0.5
        agree.append(((z >= centre) == (z >= v[ii, jj]))[out])
        agree_sup.append(((z >= centre) == (z >= sup))[out])
    return (float(np.concatenate(agree).mean()), float(np.concatenate(agree_sup).mean()),
            float(np.concatenate(over).mean()))


_G = 1e-9 + (1.0 - 2e-9) * np.arange(7) / 6.0
_GR, _GC = (a.ravel() for a in np.meshgrid(_G, _G, indexing="ij"))


def test_towers_city_never_unsafe():
    # towers up to 210 m on 2 m cells: the hardest case for lateral shadow edges (the issue's
    # 8.1 m reported vs 90.4 m exact).  Agreement is bounded by the contract itself here (a
    # cell beside a tower must carry the tower's height)
    agree, agree_sup, over = check_conservative(towers_city(), seed=11, n_dir=8)
    print(f"towers: agreement {agree:.4f} (supremum {agree_sup:.4f}), over-estimation {over:.2f} m")
    assert agree >= agree_sup - 0.03


@pytest.mark.parametrize("city", ["rotterdam", "helsinki", "monaco"])
def test_city_surfaces_never_unsafe_and_tight(city, request):
    # measured (seed 2): agreement 0.991..0.994, within 0.3 % of the supremum over the cell
    # (itself 0.994..0.996: the contract charges cells beside walls with their height)
    agree, agree_sup, over = check_conservative(request.getfixturevalue(city), seed=2)
    print(f"{city}: agreement {agree:.4f} (supremum {agree_sup:.4f}), over-estimation {over:.2f} m")
    assert agree >= 0.99
    assert agree >= agree_sup - 0.005
    assert over < 1.5


def test_srtm_never_unsafe_and_tight(srtm):
    sub = srtm.isel(y=slice(0, 260), x=slice(0, 260))
    agree, agree_sup, over = check_conservative(sub, seed=1, n_dir=10, z_range_m=300.0)
    print(f"SRTM: agreement {agree:.4f} (supremum {agree_sup:.4f}), over-estimation {over:.2f} m")
    assert agree >= 0.99
    assert agree >= agree_sup - 0.005


def test_issue_shadow_edge_case():
    # a 183 m tower, a point 76 m from it whose ray grazes its corner (az 191.7, el 50.6):
    # every point of the point's cell must get at least the exact value
    h = np.zeros((120, 120), np.float32)
    h[90:100, 50:60] = 183.0
    az, el, cell = 191.7, 50.6, 1.0
    a = math.radians(az)
    dx, dy = math.sin(a), -math.cos(a)
    # back from the tower's north-west corner (row 90, col 50), 76 cells, 1e-7 cell aside
    t = 76.0
    r = np.array([90 - t * dy + 1e-7 * dx, 90 - t * dy - 1e-7 * dx])
    c = np.array([50 - t * dx - 1e-7 * dy, 50 - t * dx + 1e-7 * dy])
    assert np.all((r > 0) & (r < 120) & (c > 0) & (c < 120))
    exact = oracle_points(h, r, c, az, el, cell)
    assert exact.max() > 90.0  # one side of the edge is in the tower's shadow
    v = visibility_heights_numpy(h, az, el, cell)[0]
    assert np.all(v[r.astype(int), c.astype(int)] >= exact - TOL_M)


@pytest.mark.parametrize("az", [0.0, 90.0, 180.0, 270.0])
def test_axis_directions_give_the_supremum(srtm, az):
    # along the grid axes the rays of a cell's interior stay in its row: the bound is the
    # exact value at the cell's edge toward the satellite (the supremum over the cell)
    h = srtm.values.astype(np.float32)
    v = visibility_heights_numpy(h, az, 12.0, 30.0)[0]
    rng = np.random.default_rng(int(az))
    ii = rng.integers(0, h.shape[0], 300)
    jj = rng.integers(0, h.shape[1], 300)
    a = math.radians(az)
    eps = 1e-6
    r = ii + 0.5 - math.cos(a) * (0.5 - eps)
    c = jj + 0.5 + math.sin(a) * (0.5 - eps)
    exact = oracle_points(h, r, c, az, 12.0, 30.0)
    np.testing.assert_allclose(v[ii, jj], exact, atol=1e-2)


def test_more_lines_are_tighter(rotterdam):
    h = rotterdam.values.astype(np.float32)
    rng = np.random.default_rng(5)
    r = rng.uniform(0, h.shape[0], 3000)
    c = rng.uniform(0, h.shape[1], 3000)
    exact = oracle_points(h, r, c, 33.3, 20.0, 2.0)
    over = {}
    for q in (1, 2, 6):
        v = visibility_heights_numpy(h, 33.3, 20.0, 2.0, lines_per_cell=q)[0]
        d = v[r.astype(int), c.astype(int)] - exact
        assert d.min() >= -TOL_M
        over[q] = d.mean()
    assert over[6] <= over[2] <= over[1]
    assert over[6] < over[1]


def test_single_prism_closed_form():
    # flat ground 0 m, one 30 m prism; satellite due east at 20 deg (rays along the rows):
    # a cell west of it in its row needs 30 m minus the drop over the distance from its EAST
    # edge to the prism's west face; the cell touching the prism needs 30 m
    c = 2.0
    tan20 = math.tan(math.radians(20.0))
    h = np.zeros((9, 40), np.float32)
    h[4, 30] = 30.0
    v = visibility_heights_numpy(h, 90.0, 20.0, c)[0]
    j = np.arange(30)
    expected = np.maximum(30.0 - (29 - j) * c * tan20, 0.0)
    np.testing.assert_allclose(v[4, :30], expected, atol=1e-4)
    assert v[4, 30] == 30.0
    assert np.all(v[4, 31:] == 0.0)
    assert np.all(v[[0, 1, 2, 3, 5, 6, 7, 8]] == 0.0)
    # satellite in the west: the shadow falls east
    v = visibility_heights_numpy(h, 270.0, 20.0, c)[0]
    assert v[4, 31] == pytest.approx(30.0, abs=1e-4)
    assert v[4, 33] == pytest.approx(30.0 - 2 * c * tan20, abs=1e-4)
    assert np.all(v[4, :30] == 0.0)
    # slightly north of east: rays rise one row in 1/tan(5 deg) = 11.4 cells; the cell south
    # of the prism carries it in full (points near its north edge enter the prism at once),
    # the cell north of it does not (its rays go away from the prism's row)
    v = visibility_heights_numpy(h, 85.0, 20.0, c)[0]
    assert v[5, 30] == pytest.approx(30.0, abs=1e-4)
    assert v[3, 30] == 0.0
    assert v[3, 29] == 0.0


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
    assert shadow_halo_cells(h, 60.0, 10.0) == 6 + 4  # 100 m / tan 60 = 57.7 m = 5.8 cells
    assert shadow_halo_cells(h, 5.0, 10.0) == 115 + 4  # 1143 m
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
    with pytest.raises(InputError, match="lines_per_cell must be an integer 1..8"):
        visibility_heights_numpy(sub.values, 10.0, 15.0, 30.0, lines_per_cell=0)


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


# ----------------------------------------------------------------------------- exact caster

@pytest.mark.parametrize("which", ["towers", "rotterdam"])
def test_shipped_caster_matches_oracle(which, request):
    # the shipped Amanatides-Woo caster against the independent slab oracle, at random
    # points, shadow-edge points and cell corners/edges (exact grid coordinates)
    surface = towers_city() if which == "towers" else request.getfixturevalue(which)
    h = surface.values.astype(np.float32)
    ny, nx = h.shape
    rng = np.random.default_rng(3)
    for az, el in [(0.0, 30.0), (90.0, 45.0), (45.0, 20.0), (191.7, 50.6), (301.3, 7.5)]:
        er, ec = shadow_edge_points(h, az, el, 2.0, 100, rng)
        r = np.r_[rng.uniform(0, ny, 400), er, rng.integers(0, ny, 50), rng.uniform(0, ny, 50)]
        c = np.r_[rng.uniform(0, nx, 400), ec, rng.uniform(0, nx, 50), rng.integers(0, nx, 50)]
        got = exact_visibility_heights_numpy(h, r, c, az, el, 2.0)
        np.testing.assert_allclose(got, oracle_points(h, r, c, az, el, 2.0), atol=1e-6)


def test_exact_visibility_height_map_coordinates():
    surface = towers_city()
    g = Grid.from_dataarray(surface)
    rng = np.random.default_rng(4)
    x = rng.uniform(g.x0, g.x0 + g.nx * 2.0, 200)
    y = rng.uniform(g.y1 - g.ny * 2.0, g.y1, 200)
    az = np.array([10.0, 200.0, 90.0])
    el = np.array([15.0, 45.0, 90.0])
    got = exact_visibility_height(surface, x, y, az, el)
    assert got.shape == (3, 200)
    h = surface.values
    rows, cols = (g.y1 - y) / 2.0, (x - g.x0) / 2.0
    for k in range(2):
        np.testing.assert_allclose(got[k], oracle_points(h, rows, cols, az[k], el[k], 2.0), atol=1e-6)
    # zenith: the ground under the point
    np.testing.assert_array_equal(got[2], h[rows.astype(int), cols.astype(int)])
    assert exact_visibility_height(surface, x[0], y[0], 10.0, 15.0).shape == ()
    with pytest.raises(InputError, match="outside the surface"):
        exact_visibility_height(surface, g.x0 - 1.0, y[0], 10.0, 15.0)
    with pytest.raises(InputError, match=r"out of \(0, 90\]"):
        exact_visibility_height(surface, x, y, 10.0, 0.0)
    with pytest.raises(InputError, match="equal length"):
        exact_visibility_height(surface, x, y, [10.0, 20.0], [15.0])


def test_occluder_window_keeps_the_decisions():
    """Visibility heights of a cluster of cells computed on its occluder window equal those of
    the whole map wherever either reaches the cluster's lowest altitude (and stay below it
    otherwise): the same visible / occluded decisions at and above that altitude, on a
    window much smaller than the map.  Random directions, clusters and altitudes."""
    h = towers_city().values.astype(np.float32)
    cell = 2.0
    rng = np.random.default_rng(5)
    checked = decided_by_towers = 0
    area = []
    for _ in range(60):
        az, el = rng.uniform(0.0, 360.0), rng.uniform(3.0, 85.0)
        full = visibility_heights_numpy(h, az, el, cell)[0]
        r = rng.integers(0, h.shape[0], 6) // 3 + rng.integers(0, 2 * h.shape[0] // 3)
        c = rng.integers(0, h.shape[1], 6) // 3 + rng.integers(0, 2 * h.shape[1] // 3)
        z_min = float(rng.uniform(0.0, 220.0))
        r0, r1, c0, c1 = occluder_window(r, c, z_min, float(h.max()), az, el, cell, h.shape)
        assert r0 <= r.min() and r.max() < r1 and c0 <= c.min() and c.max() < c1
        win = visibility_heights_numpy(h[r0:r1, c0:c1], az, el, cell, origin=(r0, c0))[0]
        f, w = full[r, c], win[r - r0, c - c0]
        high = f >= z_min
        assert np.array_equal(w[high], f[high])
        assert np.all(w[~high] < z_min)
        checked += r.size
        decided_by_towers += int((high & (f > h[r, c])).sum())
        area.append((r1 - r0) * (c1 - c0) / h.size)
    assert decided_by_towers >= 10                 # shadows of other cells were part of the test
    assert np.median(area) < 0.5
