"""The scenario grid helpers."""

from __future__ import annotations

import numpy as np
import pytest
from pyproj.aoi import AreaOfInterest
from pyproj.database import query_utm_crs_info

from skyroute.pipeline.errors import CRSError, InputError
from skyroute.stages.grid import Grid, resolve_crs, utm_crs_for


def test_utm_zone_matches_the_proj_database_outside_the_exceptions():
    rng = np.random.default_rng(0)
    n = 0
    for lon, lat in zip(rng.uniform(-179.9, 179.9, 60), rng.uniform(-79.9, 83.9, 60), strict=True):
        if (56 <= lat < 64 and 3 <= lon < 12) or (lat >= 72 and 0 <= lon < 42):
            continue
        infos = query_utm_crs_info(datum_name="WGS 84", area_of_interest=AreaOfInterest(lon, lat, lon, lat))
        codes = {int(i.code) for i in infos if i.code.startswith(("326", "327"))}
        assert utm_crs_for(lon, lat).to_epsg() in codes
        n += 1
    assert n > 40


def test_utm_exceptions_and_limits():
    assert utm_crs_for(5.3, 60.4).to_epsg() == 32632  # Bergen: zone 32V, not 31
    assert utm_crs_for(15.6, 78.2).to_epsg() == 32633  # Longyearbyen, Svalbard
    assert utm_crs_for(-70.6, -33.4).to_epsg() == 32719  # Santiago de Chile: south
    with pytest.raises(CRSError, match="outside the UTM range"):
        utm_crs_for(0.0, 89.0)
    with pytest.raises(CRSError, match="cannot resolve CRS"):
        resolve_crs("EPSG:123456789")


def test_grid_geometry_round_trips():
    g = Grid.from_bounds("EPSG:32635", 385001.0, 6671003.0, 385099.0, 6671097.0, 2.0)
    assert g.bounds == (385000.0, 6671002.0, 385100.0, 6671098.0)
    assert g.shape == (48, 50)
    r, c = g.index_of(g.x[7], g.y[5])
    assert (int(r), int(c)) == (5, 7)
    lon, lat = g.to_lonlat(g.x[7], g.y[5])
    x, y = g.from_lonlat(lon, lat)
    assert abs(x - g.x[7]) < 1e-6 and abs(y - g.y[5]) < 1e-6
    da = g.dataarray(np.zeros(g.shape), "z", units="m")
    assert Grid.from_dataarray(da) == g
    with pytest.raises(InputError, match="must be positive"):
        Grid.from_bounds("EPSG:32635", 0, 0, 1, 1, -1.0)


# ------------------------------------------------------------------ footprint-overlap resampling
def _footprint_oracle(values, T, src_crs, grid, how="max", dens=8):
    """Brute force: every source pixel as a shapely polygon (edges densified and projected point
    by point with pyproj), intersected with every target cell; max/min over positive areas."""
    import shapely
    from pyproj import CRS, Transformer

    tr = None if CRS.from_user_input(src_crs) == grid.crs else Transformer.from_crs(src_crs, grid.crs, always_xy=True)
    r = grid.resolution_m
    cells = shapely.box(grid.x0 + np.arange(grid.nx)[None] * r + 0 * np.arange(grid.ny)[:, None],
                        grid.y1 - (np.arange(grid.ny)[:, None] + 1) * r + 0 * np.arange(grid.nx)[None],
                        grid.x0 + (np.arange(grid.nx)[None] + 1) * r + 0 * np.arange(grid.ny)[:, None],
                        grid.y1 - np.arange(grid.ny)[:, None] * r + 0 * np.arange(grid.nx)[None])
    out = np.full(grid.shape, -np.inf if how == "max" else np.inf)
    t = np.linspace(0, 1, dens, endpoint=False)
    u = np.concatenate([t, np.ones_like(t), 1 - t, np.zeros_like(t)])
    w = np.concatenate([np.zeros_like(t), t, np.ones_like(t), 1 - t])
    for i in range(values.shape[0]):
        for j in range(values.shape[1]):
            X, Y = T * (j + u, i + w)
            if tr is not None:
                X, Y = tr.transform(X, Y)
            hit = shapely.area(shapely.intersection(shapely.Polygon(np.column_stack([X, Y])), cells)) > 1e-9
            out[hit] = (np.maximum if how == "max" else np.minimum)(out[hit], values[i, j])
    return out


def test_footprint_resample_equals_brute_force_on_misaligned_grids_and_another_crs():
    from affine import Affine
    from pyproj import Transformer

    from skyroute.stages.grid import footprint_resample

    rng = np.random.default_rng(3)
    n_cells = 0
    for trial in range(6):
        src_res = rng.uniform(0.3, 3.0)
        vals = rng.normal(10.0, 5.0, (14, 16))
        if trial % 2 == 0:   # same CRS, arbitrary offsets: target coarser, finer or misaligned
            T = Affine(src_res, 0, 500000 + rng.uniform(0, 5), 0, -src_res, 6000000 + rng.uniform(0, 5))
            src_crs, dst_crs = "EPSG:32635", "EPSG:32635"
        else:                # source in ETRS-TM35FIN, target in UTM 34N: pixels rotated by ~3 deg
            x0, y0 = Transformer.from_crs(32634, 3067, always_xy=True).transform(500000.0, 6000000.0)
            T = Affine(src_res, 0, x0 - rng.uniform(1, 4), 0, -src_res, y0 + rng.uniform(1, 4))
            src_crs, dst_crs = "EPSG:3067", "EPSG:32634"
        res = src_res * rng.choice([0.37, 1.0, 1.6, 3.3])
        g = Grid(dst_crs, 500000 + rng.uniform(0, 6), 6000000 - rng.uniform(0, 4), int(rng.integers(3, 9)),
                 int(rng.integers(3, 9)), float(res))
        for how in ("max", "min"):
            got = footprint_resample(vals, T, src_crs, g, how=how)
            ref = _footprint_oracle(vals, T, src_crs, g, how=how)
            covered = np.isfinite(ref)
            assert np.array_equal(np.isfinite(got), covered)
            np.testing.assert_array_equal(got[covered], ref[covered])
            n_cells += int(covered.sum())
    assert n_cells > 100


def test_gdal_max_misses_pixels_the_footprint_max_keeps():
    """GDAL's Resampling.max (3.10) equals the footprint max on grids of one CRS, but between
    rotated CRSs it misses source pixels that overlap the target cell only partly: it comes out
    lower than an obstacle there.  The footprint max equals the brute force in both cases."""
    import rasterio.warp
    from affine import Affine
    from pyproj import Transformer

    from skyroute.stages.grid import footprint_resample

    rng = np.random.default_rng(5)
    vals = rng.uniform(0, 30, (24, 24))
    x0, y0 = Transformer.from_crs(32634, 3067, always_xy=True).transform(500000.0, 6000000.0)
    T = Affine(1.0, 0, x0 - 3, 0, -1.0, y0 + 3)
    g = Grid("EPSG:32634", 500000.0 + 3.3, 6000000.0 - 3.6, 12, 12, 1.3)
    gdal = np.full(g.shape, np.nan)
    rasterio.warp.reproject(vals, gdal, src_transform=T, src_crs="EPSG:3067", dst_transform=g.transform,
                            dst_crs="EPSG:32634", dst_nodata=np.nan, resampling=rasterio.warp.Resampling.max)
    ours = footprint_resample(vals, T, "EPSG:3067", g)
    ref = _footprint_oracle(vals, T, "EPSG:3067", g)
    np.testing.assert_array_equal(ours, ref)
    assert np.nanmin(gdal - ref) < -1.0     # GDAL under-estimates somewhere by more than 1 m
    assert np.all(ours >= gdal)


def test_cell_of_clips_to_the_grid_and_agrees_with_index_of_inside():
    import numpy as np

    from skyroute.stages.grid import Grid

    g = Grid.from_bounds("EPSG:32635", 0, 0, 100, 50, 2.0)
    rng = np.random.default_rng(0)
    x, y = rng.uniform(0, 100, 1000), rng.uniform(0, 50, 1000)
    np.testing.assert_array_equal(np.stack(g.cell_of(x, y)), np.stack(g.index_of(x, y)))
    r, c = g.cell_of(np.array([-5.0, 105.0, 50.0]), np.array([60.0, -3.0, 25.0]))
    assert r.tolist() == [0, g.ny - 1, 12] and c.tolist() == [0, g.nx - 1, 25]


def test_check_heights_refuses_values_that_are_not_heights_in_metres():
    """An undeclared NoData such as 1e30 (or -3.4e38) in a DSM / DEM is a DataError naming the
    value, the pixel count and the fix; plausible heights (Dead Sea to Everest) and NaN pass."""
    from skyroute.stages.base import DataError
    from skyroute.stages.grid import HEIGHT_RANGE_M, check_heights

    ok = np.array([[-430.0, 8849.0], [np.nan, 12.5]])
    check_heights(ok, "dsm.tif", "surface DSM")
    check_heights(np.array(HEIGHT_RANGE_M), "dsm.tif", "surface DSM")       # the bounds themselves
    bad = ok.copy()
    bad[1, 0] = 1e30
    with pytest.raises(DataError, match=r"surface DSM dsm\.tif: 1 pixel\(s\) hold 1e\+30, not a height in metres"
                                        r".*gdal_edit\.py -a_nodata"):
        check_heights(bad, "dsm.tif", "surface DSM")
    with pytest.raises(DataError, match=r"terrain DEM d\.tif: 2 pixel\(s\) hold -3\.4e\+38"):
        check_heights(np.array([-3.4e38, -3.4e38, 100.0]), "d.tif", "terrain DEM")
