"""Clearance floor / no-fly dilation against closed forms and a brute-force sphere-vs-prism oracle."""

from __future__ import annotations

from pathlib import Path

import dask.array as dsa
import numpy as np
import pytest
import rioxarray
import xarray as xr
from scipy import ndimage

from skyroute.pipeline.errors import InputError
from skyroute.stages import clearance as C
from skyroute.stages.grid import Grid

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
SRTM = SHARED / "terrain" / "srtm_bigtujunga30m_utm11.tif"


@pytest.fixture(scope="module")
def srtm_patch():
    if not SRTM.exists():
        pytest.skip(f"shared data missing: {SRTM}")
    da = rioxarray.open_rasterio(SRTM).squeeze("band", drop=True)
    patch = da.isel(y=slice(300, 336), x=slice(500, 540)).astype("float64").load()
    assert np.all(patch.values < 32767)  # no nodata in this window
    # add three flat-topped "buildings" 25-40 m tall on the real terrain
    v = patch.values.copy()
    v[5:8, 6:10] += 25.0
    v[20:22, 20:21] += 40.0
    v[28:33, 30:34] += 30.0
    out = xr.DataArray(v, dims=("y", "x"), coords={"y": patch.y.values, "x": patch.x.values},
                       name="surface", attrs={"units": "m"})
    return out.rio.write_crs(patch.rio.crs)


def prism_distance(surface: xr.DataArray, x, y, z):
    """Exact distance [m] from points (n,) to every prism footprint x (-inf, surface]: (n, ncell)."""
    g = Grid.from_dataarray(surface)
    cx, cy = np.meshgrid(g.x, g.y)
    h = g.resolution_m / 2
    dx = np.maximum(np.abs(x[:, None] - cx.ravel()[None]) - h, 0.0)
    dy = np.maximum(np.abs(y[:, None] - cy.ravel()[None]) - h, 0.0)
    dz = np.maximum(z[:, None] - surface.values.ravel()[None], 0.0)
    return np.sqrt(dx**2 + dy**2 + dz**2), np.hypot(dx, dy)


def exact_floor(surface, r, x, y):
    """Oracle floor at arbitrary points: max over cells within r of s + sqrt(r^2 - d_h^2)."""
    _, dh = prism_distance(surface, x, y, np.zeros_like(x))
    lift = np.where(dh <= r, np.sqrt(np.maximum(r * r - dh**2, 0)), -np.inf)
    return np.max(surface.values.ravel()[None] + lift, axis=1)


def test_vehicle_radius_eq13():
    assert C.vehicle_radius(3.0, 1.0, 2.0) == 5.0   # seed 000 Table: d_m = 3 m, K_m = 1
    with pytest.raises(InputError, match="K_m"):
        C.vehicle_radius(3.0, 0.5, 2.0)


def test_single_box_closed_form():
    g = Grid.from_bounds("EPSG:32633", 0, 0, 60, 60, 2.0)
    s = np.zeros(g.shape)
    s[10:15, 12:16] = 20.0                           # box x in [24, 32], y in [30, 40]
    surf = g.dataarray(s, "surface", units="m")
    r = 5.0
    fl = C.clearance_floor(surf, r, mode="centre").values
    cx, cy = np.meshgrid(g.x, g.y)
    dx = np.maximum(np.maximum(24.0 - cx, cx - 32.0), 0.0)
    dy = np.maximum(np.maximum(30.0 - cy, cy - 40.0), 0.0)
    d = np.hypot(dx, dy)
    expected = np.where(d <= r, 20.0 + np.sqrt(np.maximum(r * r - d * d, 0.0)), r)
    assert np.max(np.abs(fl - expected)) < 1e-9
    assert fl[12, 14] == pytest.approx(25.0) and fl[0, 0] == pytest.approx(5.0)
    # cell mode: distance between footprints -> the 2 m ring next to the box sees d = 0
    fc = C.clearance_floor(surf, r, mode="cell").values
    assert fc[12, 11] == pytest.approx(25.0) and fc[12, 10] == pytest.approx(20.0 + np.sqrt(21.0))


def test_centre_mode_equals_oracle_at_cell_centres(srtm_patch):
    r = 45.0
    fl = C.clearance_floor(srtm_patch, r, mode="centre")
    g = Grid.from_dataarray(srtm_patch)
    rng = np.random.default_rng(7)
    n = 3000
    i = rng.integers(0, g.ny, n)
    j = rng.integers(0, g.nx, n)
    x, y = g.x[j], g.y[i]
    z = fl.values[i, j] + rng.uniform(-30.0, 30.0, n)
    d, _ = prism_distance(srtm_patch, x, y, z)
    dmin = d.min(axis=1)
    oracle = dmin >= r
    away = np.abs(dmin - r) > 0.01
    got = C.is_clear(fl, x, y, z)
    assert away.sum() > 0.9 * n and 0.2 < oracle.mean() < 0.8
    assert np.array_equal(got[away], oracle[away])
    # and the floor itself equals the oracle floor at cell centres
    assert np.max(np.abs(exact_floor(srtm_patch, r, x, y) - fl.values[i, j])) < 1e-9


def test_cell_mode_conservative_and_tight(srtm_patch):
    r = 45.0
    fl = C.clearance_floor(srtm_patch, r)          # default mode "cell"
    g = Grid.from_dataarray(srtm_patch)
    rng = np.random.default_rng(11)
    n = 3000
    x = rng.uniform(g.bounds[0], g.bounds[2], n)
    y = rng.uniform(g.bounds[1], g.bounds[3], n)
    row, col = g.index_of(x, y)
    z = fl.values[row, col] + rng.uniform(-40.0, 20.0, n)
    d, _ = prism_distance(srtm_patch, x, y, z)
    clear_oracle = d.min(axis=1) >= r - 1e-9
    got = C.is_clear(fl, x, y, z)
    assert got.sum() > 0.2 * n
    assert not np.any(got & ~clear_oracle)          # never clears a touching sphere
    # tight: the cell value is the maximum of the exact floor over the cell (edges sampled)
    for (ii, jj) in [(3, 4), (6, 8), (19, 20), (30, 31), (17, 2)]:
        s = np.linspace(-0.5, 0.5, 11) * g.resolution_m
        qx, qy = np.meshgrid(g.x[jj] + s, g.y[ii] + s)
        sup = exact_floor(srtm_patch, r, qx.ravel(), qy.ravel()).max()
        assert fl.values[ii, jj] == pytest.approx(sup, abs=1e-9)


def test_dask_equals_numpy(srtm_patch):
    r = 70.0
    ref = C.clearance_floor(srtm_patch, r)
    lazy = srtm_patch.copy(data=dsa.from_array(srtm_patch.values, chunks=(10, 13)))
    out = C.clearance_floor(lazy, r)
    assert isinstance(out.data, dsa.Array)
    assert np.array_equal(out.values, ref.values)
    assert out.rio.crs == srtm_patch.rio.crs and out.attrs["units"] == "m"


def test_dilate_nofly_brute_force_and_edt():
    g = Grid.from_bounds("EPSG:32633", 0, 0, 100, 80, 2.0)
    rng = np.random.default_rng(3)
    m = np.zeros(g.shape, dtype=bool)
    m[rng.integers(0, g.ny, 6), rng.integers(0, g.nx, 6)] = True
    m[20:25, 10:30] = True
    mask = g.dataarray(m, "nofly")
    r = 7.3
    cx, cy = np.meshgrid(g.x, g.y)
    mx, my = cx[m], cy[m]
    for mode, shrink in (("cell", 1.0), ("centre", 0.5)):
        out = C.dilate_nofly(mask, r, mode=mode).values
        # brute force: footprint-to-footprint (cell) or centre-to-footprint (centre) distance <= r
        gx = np.maximum(np.abs(cx.ravel()[:, None] - mx[None]) - shrink * g.resolution_m, 0)
        gy = np.maximum(np.abs(cy.ravel()[:, None] - my[None]) - shrink * g.resolution_m, 0)
        expected = (np.hypot(gx, gy) <= r).any(axis=1).reshape(g.shape)
        assert np.array_equal(out, expected), mode
    # radius right within one cell, by an independent distance transform (centre to centre)
    edt = ndimage.distance_transform_edt(~m) * g.resolution_m
    out = C.dilate_nofly(mask, r).values
    assert np.all(out[edt <= r]) and not np.any(out[edt > r + np.sqrt(2) * g.resolution_m])
    assert C.dilate_nofly(mask, 0.0, mode="centre").values.sum() == m.sum()


def test_nofly_volume_against_sphere_box():
    g = Grid.from_bounds("EPSG:32633", 0, 0, 40, 40, 1.0)
    m = np.zeros(g.shape, dtype=bool)
    m[15:25, 15:25] = True                          # x, y in [15, 25]
    vol = C.nofly_volume(g.dataarray(m, "m"), 4.0, 50.0, 80.0, mode="centre")
    ds = xr.Dataset({"min_altitude_m": g.dataarray(np.full(g.shape, -np.inf), "a"),
                     "max_altitude_m": g.dataarray(np.full(g.shape, np.inf), "b"),
                     "nofly": g.dataarray(np.zeros(g.shape, bool), "c"),
                     "volume_bottom_m": vol["bottom_m"].expand_dims("volume"),
                     "volume_top_m": vol["top_m"].expand_dims("volume")})
    rng = np.random.default_rng(5)
    i = rng.integers(0, g.ny, 4000)
    j = rng.integers(0, g.nx, 4000)
    x, y, z = g.x[j], g.y[i], rng.uniform(40, 90, 4000)
    dx = np.maximum(np.maximum(15 - x, x - 25), 0)
    dy = np.maximum(np.maximum(15 - y, y - 25), 0)
    dz = np.maximum(np.maximum(50 - z, z - 80), 0)
    dist = np.sqrt(dx**2 + dy**2 + dz**2)
    away = np.abs(dist - 4.0) > 0.01
    assert np.array_equal(C.is_clear(ds, x, y, z)[away], (dist > 4.0)[away])


def test_clearance_dataset_and_bounds(srtm_patch):
    g = Grid.from_dataarray(srtm_patch)
    terrain = srtm_patch.copy(data=srtm_patch.values)
    nf = np.zeros(g.shape, bool)
    nf[0:3, 0:3] = True
    ds = C.clearance_dataset(srtm_patch, 10.0, terrain=terrain, min_agl_m=30.0, max_agl_m=120.0,
                             nofly=g.dataarray(nf, "nofly"))
    assert ds.rio.crs == srtm_patch.rio.crs
    lo = ds["min_altitude_m"].values
    assert np.all(lo >= terrain.values + 30.0) and np.all(lo >= ds["obstacle_floor_m"].values)
    x, y = g.x[20], g.y[20]
    t = float(terrain.values[20, 20])
    assert C.is_clear(ds, x, y, lo[20, 20])
    assert not C.is_clear(ds, x, y, lo[20, 20] - 0.01)
    assert C.is_clear(ds, x, y, t + 120.0) and not C.is_clear(ds, x, y, t + 120.01)
    assert not C.is_clear(ds, g.x[3], g.y[3], t + 100.0)          # dilated no-fly (10 m < 1 cell)
    assert not C.is_clear(ds, g.bounds[2] + 5.0, y, 5000.0)        # outside the raster
    ab = C.altitude_bounds(terrain, 30.0, 120.0)
    assert np.allclose(ab["ceiling_m"] - ab["floor_m"], 90.0)


def test_bad_input(srtm_patch):
    with pytest.raises(InputError, match="radius"):
        C.clearance_floor(srtm_patch, -1.0)
    with pytest.raises(InputError, match="radius"):
        C.dilate_nofly(srtm_patch > 1000, -0.5)
    with pytest.raises(InputError, match="NaN"):
        C.clearance_floor(srtm_patch.where(srtm_patch < float(srtm_patch.median())), 5.0)
    with pytest.raises(InputError, match="mode"):
        C.clearance_floor(srtm_patch, 5.0, mode="corner")
    with pytest.raises(InputError, match="min_agl_m < max_agl_m"):
        C.altitude_bounds(srtm_patch, 100.0, 50.0)
    with pytest.raises(InputError, match="zmin_m <= zmax_m"):
        C.nofly_volume(srtm_patch > 1000, 5.0, 80.0, 50.0)


def test_agl_floor_and_ceiling_hold_at_every_point_of_the_cell():
    """The minimum-AGL floor uses the highest DEM sample whose patch touches the cell, the
    maximum-AGL ceiling the lowest: at random points inside cells (misaligned 45 m grid on the
    30 m SRTM), the ground under the point (its DEM pixel, and the bilinear surface through the
    four samples around it) is <= floor - min_agl and >= ceiling - max_agl."""
    import rasterio

    from skyroute.pipeline.settings import catalog_dir
    from skyroute.stages.surface import build_surface

    path = catalog_dir() / "data" / "srtm_bigtujunga30m_utm11.tif"
    with rasterio.open(path) as src:
        dem, T, b = src.read(1).astype(float), src.transform, src.bounds
        crs = src.crs.to_string()
    g = Grid.from_bounds(crs, b.left + 2017, b.bottom + 3011, b.left + 5000, b.bottom + 6000, 45.0)
    ds = build_surface(g, terrain_path=path, vertical_datum="EGM96 geoid")
    ab = C.altitude_bounds(ds["terrain"], 30.0, 120.0, terrain_min=ds["terrain_min"])
    rng = np.random.default_rng(4)
    n = 20000
    r, c = rng.integers(0, g.ny, n), rng.integers(0, g.nx, n)
    x = g.x0 + (c + rng.uniform(0, 1, n)) * g.resolution_m
    y = g.y1 - (r + rng.uniform(0, 1, n)) * g.resolution_m
    col, row = ~T * (x, y)
    ground = dem[np.floor(row).astype(int), np.floor(col).astype(int)]
    u, w = col - 0.5, row - 0.5                     # samples at the pixel centres
    j, i = np.floor(u).astype(int), np.floor(w).astype(int)
    fu, fw = u - j, w - i
    four = np.stack([dem[i, j], dem[i, j + 1], dem[i + 1, j], dem[i + 1, j + 1]])
    bil = (dem[i, j] * (1 - fu) * (1 - fw) + dem[i, j + 1] * fu * (1 - fw) + dem[i + 1, j] * (1 - fu) * fw
           + dem[i + 1, j + 1] * fu * fw)
    for g_ in (ground, bil):
        assert np.all(ab["floor_m"].values[r, c] - 30.0 >= g_ - 1e-4)
        assert np.all(ab["ceiling_m"].values[r, c] - 120.0 <= g_ + 1e-4)
    # both bounds are tight: at some points of the cells they are the highest / lowest of the four
    # samples around the point (the patch max / min over the cell)
    assert np.isclose(ab["floor_m"].values[r, c] - 30.0, four.max(axis=0), atol=1e-3).mean() > 0.1
    assert np.isclose(ab["ceiling_m"].values[r, c] - 120.0, four.min(axis=0), atol=1e-3).mean() > 0.1
    # a centre-sampled (or bilinear) ground would not hold: it is above some point's ground by metres
    centre = dem[np.floor((~T * (g.x[c], g.y[r]))[1]).astype(int), np.floor((~T * (g.x[c], g.y[r]))[0]).astype(int)]
    assert (ground - centre).max() > 5.0
    with pytest.raises(InputError, match="terrain_min is above terrain"):
        C.altitude_bounds(ds["terrain_min"], 30.0, 120.0, terrain_min=ds["terrain"])


def test_native_floor_is_the_highest_exact_floor_of_each_cell():
    """clearance_floor_native: a 0.5 m raster's cell-mode floor, max over each grid cell, equals
    the exact highest floor over the cell (brute force: max over the prisms within r of the cell's
    square of h + sqrt(r^2 - gap^2)) on an aligned 1 m grid; on a misaligned 1.3 m grid it is that
    over the cell grown to the 0.5 m pixels it overlaps; >= the oracle floor at random points."""
    from affine import Affine

    from skyroute.stages.grid import footprint_resample

    rng = np.random.default_rng(8)
    z = rng.uniform(0, 3, (60, 60))
    z[20:24, 30:31] = 40.0                   # a 0.5 m x 2 m mast
    z[40:50, 10:25] = 15.0
    T = Affine(0.5, 0, 1000.0, 0, -0.5, 2000.0)
    fine = Grid("EPSG:32635", 1000.0, 2000.0, 60, 60, 0.5).dataarray(z, "surface")
    px0 = 1000.0 + 0.5 * np.arange(60)
    py1 = 2000.0 - 0.5 * np.arange(60)
    r = 5.0

    def exact_over(X0, X1, Y0, Y1):
        gy = np.maximum(np.maximum((py1 - 0.5) - Y1, Y0 - py1), 0.0)[:, None]
        gx = np.maximum(np.maximum(px0 - X1, X0 - (px0 + 0.5)), 0.0)[None, :]
        gap2 = gx * gx + gy * gy
        return np.max(np.where(gap2 <= r * r, z + np.sqrt(np.maximum(r * r - gap2, 0.0)), -np.inf))

    for g, snap in ((Grid("EPSG:32635", 1003.0, 1997.0, 24, 24, 1.0), False),
                    (Grid("EPSG:32635", 1003.1, 1996.7, 18, 18, 1.3), True)):
        got = C.clearance_floor_native(z, T, "EPSG:32635", g, r)
        ref = np.empty(g.shape)
        for i in range(g.ny):
            for j in range(g.nx):
                X0, Y1 = g.x0 + g.resolution_m * j, g.y1 - g.resolution_m * i
                X1, Y0 = X0 + g.resolution_m, Y1 - g.resolution_m
                if snap:
                    X0, X1 = np.floor(X0 * 2) / 2, np.ceil(X1 * 2) / 2
                    Y0, Y1 = np.floor(Y0 * 2) / 2, np.ceil(Y1 * 2) / 2
                ref[i, j] = exact_over(X0, X1, Y0, Y1)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)
        xs = g.x0 + rng.uniform(0, g.nx * g.resolution_m, 800)
        ys = g.y1 - rng.uniform(0, g.ny * g.resolution_m, 800)
        rr, cc = g.index_of(xs, ys)
        assert np.all(got[rr, cc] >= exact_floor(fine, r, xs, ys) - 1e-9)
        # the floor of the resampled surface: also safe, but metres higher near edges
        coarse = C.clearance_floor(g.dataarray(footprint_resample(z, T, "EPSG:32635", g), "surface"), r).values
        assert (coarse - got).max() > 2.0
        assert snap or np.all(coarse[6:-6, 6:-6] >= got[6:-6, 6:-6] - 1e-9)   # (it ignores prisms off the grid)
    assert C.clearance_floor_native(z, Affine(0.5, 0, 1000.0, 0, -0.4, 2000.0), "EPSG:32635", g, r) is None
