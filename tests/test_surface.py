"""Surface model against its sources: OSM tags, CityJSON roofs, the SRTM DEM."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import osmium
import pytest
import rasterio
import shapely
import xarray as xr
from affine import Affine
from pyproj import Transformer

from skyroute.pipeline.errors import DataError, InputError
from skyroute.pipeline.settings import catalog_dir, load_scenario
from skyroute.stages.grid import Grid, warp_to_grid
from skyroute.stages.surface import build_surface, osm_building_height, parse_height_m

CATALOG_DATA = catalog_dir() / "data"


def _osm_buildings_direct(path):
    """Independent reader: building areas with their raw tags, straight from pyosmium."""
    wkb = osmium.geom.WKBFactory()
    out = {}
    for o in osmium.FileProcessor(str(path)).with_areas().with_locations():
        if o.is_area() and ("building" in o.tags or "building:part" in o.tags):
            try:
                out[o.orig_id()] = (dict(o.tags), shapely.from_wkb(wkb.create_multipolygon(o)))
            except RuntimeError:
                pass
    return out


def test_height_parsing():
    assert parse_height_m("12") == 12.0
    assert parse_height_m("12.13 m") == pytest.approx(12.13)
    assert parse_height_m("40 ft") == pytest.approx(12.192)
    assert parse_height_m("12,5") == 12.5
    assert parse_height_m("tall") is None
    assert osm_building_height({"building": "yes", "height": "21"}) == (21.0, "height")
    assert osm_building_height({"building": "yes", "building:levels": "6"}) == (18.0, "levels")
    assert osm_building_height({"building": "yes", "building:levels": "5", "roof:levels": "1"}, 3.5) == (21.0, "levels")
    assert osm_building_height({"building": "church"}) == (20.0, "default:church")


def test_helsinki_building_heights_match_osm_tags(helsinki, helsinki_surface):
    ds = helsinki_surface
    grid = helsinki.grid
    direct = _osm_buildings_direct(CATALOG_DATA / "helsinki_center.osm.pbf")
    ids = ds["building_osm_id"].values
    bid = ds["building_id"].values
    surf = ds["surface"].values
    to_map = Transformer.from_crs(4326, grid.crs, always_xy=True)
    checked = {"height": 0, "levels": 0}
    for i, osm_id in enumerate(ids):
        tags, geom = direct[int(osm_id)]
        cells = bid == i
        if not cells.any():
            continue
        if "height" in tags and tags["height"].replace(".", "").isdigit():
            expected, kind = float(tags["height"]), "height"
        elif "building:levels" in tags and tags["building:levels"].isdigit() and "roof:levels" not in tags:
            expected, kind = 3.0 * int(tags["building:levels"]), "levels"
        else:
            continue
        # every cell attributed to this building has exactly its tagged height (flat terrain at 0)
        np.testing.assert_allclose(surf[cells], expected, atol=1e-4)
        checked[kind] += 1
        # every cell whose centre lies in the footprint is at least this high (the highest
        # building wins where footprints overlap), and covers the footprint's area
        g = shapely.transform(geom, lambda xy: np.column_stack(to_map.transform(xy[:, 0], xy[:, 1])))
        r0, c0 = grid.index_of(g.bounds[0], g.bounds[3])
        r1, c1 = grid.index_of(g.bounds[2], g.bounds[1])
        r0, c0 = max(r0, 0), max(c0, 0)
        r1, c1 = min(r1 + 1, grid.ny), min(c1 + 1, grid.nx)
        X, Y = np.meshgrid(grid.x[c0:c1], grid.y[r0:r1])
        inside = shapely.contains_xy(g, X, Y)
        assert np.all(surf[r0:r1, c0:c1][inside] >= expected - 1e-4)
        assert np.all(bid[r0:r1, c0:c1][inside] >= 0)
        xmin, ymin, xmax, ymax = grid.bounds
        if g.area > 400 and shapely.box(xmin, ymin, xmax, ymax).contains(g):
            assert abs(inside.sum() * grid.resolution_m**2 - g.area) < 0.1 * g.area + 40
    assert checked["height"] >= 5 and checked["levels"] >= 50, checked


def test_rotterdam_roofs_match_cityjson():
    sc = load_scenario("rotterdam-canyon")
    ds = build_surface(sc.grid, buildings_path=sc.data.buildings.path, buildings_format="cityjson")
    cj = json.loads((CATALOG_DATA / "rotterdam_delfshaven_lod2.city.json").read_text())
    V = np.asarray(cj["vertices"]) * cj["transform"]["scale"] + cj["transform"]["translate"]
    grid = sc.grid
    surf = ds["surface"].values
    terr = ds["terrain"].values
    rng = np.random.default_rng(1)
    names = list(cj["CityObjects"])
    n_ok = 0
    for oid in rng.choice(names, 60, replace=False):
        obj = cj["CityObjects"][oid]
        g = obj["geometry"][0]
        idx = np.unique(np.concatenate([np.ravel(ring) for surf_ in g["boundaries"] for ring in surf_]))
        P = V[idx]
        zmax = P[:, 2].max()
        r, c = grid.index_of(P[:, 0], P[:, 1])
        ok = (r >= 0) & (r < grid.ny) & (c >= 0) & (c < grid.nx)
        if ok.sum() < 3:
            continue
        # the highest cell over the building footprint is its highest roof vertex (within 0.5 m)
        r0, r1, c0, c1 = r[ok].min(), r[ok].max() + 1, c[ok].min(), c[ok].max() + 1
        assert surf[r0:r1, c0:c1].max() >= zmax - 0.5
        # the terrain under it is the TerrainHeight attribute (interpolated between buildings)
        th = obj["attributes"]["TerrainHeight"]
        rc, cc = int(np.median(r[ok])), int(np.median(c[ok]))
        assert abs(terr[rc, cc] - th) < 1.5
        n_ok += 1
    assert n_ok >= 40
    assert float(ds["surface"].max()) == pytest.approx(V[:, 2].max(), abs=0.01)


def _box_oracle(src, T, grid, how="max", width_px=1.0):
    """Independent footprint max/min for a north-up source on the grid's CRS: pixel j spans
    [T.c + j a, T.c + (j + 1) a]; it counts for a cell when the two intervals overlap (> 1e-6 m)
    on both axes.  ``width_px=2``: the sample at the centre of pixel j counts for every cell its
    surface patch [centre - a, centre + a] (the four lattice squares around it) overlaps."""
    sy, sx = src.shape
    xl = T.c + (np.arange(sx) + 0.5 - width_px / 2) * T.a
    yt = T.f + (np.arange(sy) + 0.5 - width_px / 2) * T.e
    out = np.full(grid.shape, np.nan)
    r = grid.resolution_m
    red = np.max if how == "max" else np.min
    cols = [(xl + width_px * T.a > grid.x0 + j * r + 1e-6) & (xl < grid.x0 + (j + 1) * r - 1e-6)
            for j in range(grid.nx)]
    for i in range(grid.ny):
        Y1 = grid.y1 - i * r
        line = red(src[(yt > Y1 - r + 1e-6) & (yt + width_px * T.e < Y1 - 1e-6)], axis=0)
        out[i] = [red(line[c]) for c in cols]
    return out


def test_dem_is_the_max_and_min_of_the_samples_whose_patch_touches_each_cell():
    """A DEM is read as the surface through its samples: a cell's terrain is the highest sample
    whose patch (the four lattice squares around it) overlaps the cell, terrain_min the lowest;
    the footprint reading (flat-topped squares) is never above it."""
    path = CATALOG_DATA / "srtm_bigtujunga30m_utm11.tif"
    with rasterio.open(path) as src:
        b = src.bounds
        dem = src.read(1).astype(float)
        T = src.transform
        crs = src.crs.to_string()
    for res, dx in ((30.0, 7.3), (45.0, 0.0), (12.5, 3.1)):
        grid = Grid.from_bounds(crs, b.left + 3000 + dx, b.bottom + 3000 + dx, b.left + 4500, b.bottom + 4000, res)
        ds = build_surface(grid, terrain_path=path, vertical_datum="EGM96 geoid")
        hi, lo = _box_oracle(dem, T, grid, "max", 2.0), _box_oracle(dem, T, grid, "min", 2.0)
        np.testing.assert_array_equal(ds["terrain"].values, hi.astype(np.float32))
        np.testing.assert_array_equal(ds["terrain_min"].values, lo.astype(np.float32))
        box_lo = _box_oracle(dem, T, grid, "min")
        np.testing.assert_array_equal(warp_to_grid(path, grid, what="terrain", resampling="min"), box_lo)
        assert np.all(hi >= _box_oracle(dem, T, grid, "max")) and np.all(lo <= box_lo)
        assert (hi - lo).max() > 5.0   # mountains: the two bounds differ
    assert "samples at the pixel centres" in ds.attrs["ground_source"]
    assert ds.attrs["vertical_datum"] == "EGM96 geoid"
    assert ds["surface"].rio.crs.to_epsg() == 32611


# ------------------------------------------------------------------ data.surface (DSM)
DSM_T = Affine(0.5, 0.0, 92000.25, 0.0, -0.5, 437120.25)
DSM_SHAPE = (240, 240)   # 120 m x 120 m of 0.5 m pixels


def _true_dsm():
    """A 0.5 m DSM of a little town on a gentle slope: two buildings (one with a pitched roof and
    a glass roof part), 30 tree crowns, a 0.5 m wide 40 m mast; heights in 'NAP'."""
    rng = np.random.default_rng(11)
    ny, nx = DSM_SHAPE
    ii, jj = np.mgrid[0:ny, 0:nx]
    z = 1.0 + 0.01 * jj + 0.005 * ii
    z[60:100, 50:110] = 18.0                                   # flat roof, 20 m x 30 m
    z[140:180, 120:170] = 12.0 + 0.2 * np.minimum(jj - 120, 170 - jj)[140:180, 120:170]   # pitched roof
    n = 0
    while n < 30:                                              # tree crowns 2-6 m wide, 6-14 m tall
        ci, cj, rad, h = rng.integers(20, 220), rng.integers(20, 220), rng.uniform(4, 12), rng.uniform(6, 14)
        if 185 < ci < 230 and 15 < cj < 75:                    # not over the pond (a NoData hole)
            continue
        d = np.hypot(ii - ci, jj - cj)
        z = np.where(d < rad, np.maximum(z, z[ci, cj] + h * np.sqrt(np.clip(1 - (d / rad) ** 2, 0, 1))), z)
        n += 1
    z[120, 200] = 41.0                                         # mast: one 0.5 m pixel
    return z


def _write_dsm(path, z, holes=True, transform=DSM_T, crs="EPSG:28992"):
    """Write ``z`` with NoData holes: a glass roof part (true height below its rim), a pond, and a
    strip along the file's edge (outside the extent)."""
    z = z.astype(np.float32).copy()
    if holes:
        z[70:80, 60:75] = -9999.0         # glass roof inside the flat roof
        z[200:215, 30:60] = -9999.0       # pond on the ground
        z[0:3, 100:140] = -9999.0         # NoData strip on the file's north edge
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype="float32",
                       crs=crs, transform=transform, nodata=-9999.0) as dst:
        dst.write(z, 1)
    return path


def _dsm_grid(res, x0=92010.3, y0=437010.7, size=100.0):
    return Grid.from_bounds("EPSG:28992", x0, y0, x0 + size, y0 + size, res)


def test_dsm_holes_are_filled_with_their_rim_max_then_footprint_max(tmp_path):
    z = _true_dsm()
    path = _write_dsm(tmp_path / "dsm.tif", z)
    filled = z.copy()
    for sl in ((slice(70, 80), slice(60, 75)), (slice(200, 215), slice(30, 60))):
        ring = z[sl[0].start - 1:sl[0].stop + 1, sl[1].start - 1:sl[1].stop + 1].copy()
        ring[1:-1, 1:-1] = -np.inf
        filled[sl] = ring.max()
    for res in (1.0, 2.0, 0.4):
        grid = _dsm_grid(res)
        ds = build_surface(grid, surface_path=path, surface_datum="NAP")
        ref = _box_oracle(filled.astype(np.float32).astype(float), DSM_T, grid)
        np.testing.assert_array_equal(ds["surface"].values, ref.astype(np.float32))
        assert float(ds["surface"].max()) == 41.0                # the mast survives every resolution
        assert np.all(ds["surface"].values >= _box_oracle(z, DSM_T, grid) - 1e-5)  # above the true DSM
    assert ds.attrs["vertical_datum"] == "NAP"
    assert "NoData regions filled under the AOI: 2 (fill-max, 0 touching the raster's edge)" in ds.attrs["dsm"]


def test_dsm_tiles_and_vrt_read_like_one_file(tmp_path):
    z = _true_dsm()
    one = build_surface(_dsm_grid(1.0), surface_path=_write_dsm(tmp_path / "all.tif", z), surface_datum="NAP")
    tiles = []
    for k, (rs, cs) in enumerate([(slice(0, 130), slice(0, 110)), (slice(0, 130), slice(110, 240)),
                                  (slice(130, 240), slice(0, 110)), (slice(130, 240), slice(110, 240))]):
        zt = z.copy()
        _write_dsm(tmp_path / "full.tif", zt)   # holes applied, then cut
        with rasterio.open(tmp_path / "full.tif") as src:
            part = src.read(1)[rs, cs]
        T = DSM_T * Affine.translation(cs.start, rs.start)
        p = tmp_path / f"tile{k}.tif"
        with rasterio.open(p, "w", driver="GTiff", width=part.shape[1], height=part.shape[0], count=1,
                           dtype="float32", crs="EPSG:28992", transform=T, nodata=-9999.0) as dst:
            dst.write(part, 1)
        tiles.append((p, rs, cs))
    many = build_surface(_dsm_grid(1.0), surface_path=[t[0] for t in tiles], surface_datum="NAP")
    xr.testing.assert_equal(one[["surface", "terrain", "terrain_min"]], many[["surface", "terrain", "terrain_min"]])
    srcs = "".join(
        f"<SimpleSource><SourceFilename relativeToVRT='1'>{p.name}</SourceFilename><SourceBand>1</SourceBand>"
        f"<SrcRect xOff='0' yOff='0' xSize='{cs.stop - cs.start}' ySize='{rs.stop - rs.start}'/>"
        f"<DstRect xOff='{cs.start}' yOff='{rs.start}' xSize='{cs.stop - cs.start}' ySize='{rs.stop - rs.start}'/>"
        f"<NODATA>-9999</NODATA></SimpleSource>" for p, rs, cs in tiles)
    vrt = tmp_path / "dsm.vrt"
    vrt.write_text(
        f"<VRTDataset rasterXSize='240' rasterYSize='240'><SRS>EPSG:28992</SRS>"
        f"<GeoTransform>{DSM_T.c}, 0.5, 0, {DSM_T.f}, 0, -0.5</GeoTransform>"
        f"<VRTRasterBand dataType='Float32' band='1'><NoDataValue>-9999</NoDataValue>{srcs}</VRTRasterBand></VRTDataset>")
    via_vrt = build_surface(_dsm_grid(1.0), surface_path=vrt, surface_datum="NAP")
    xr.testing.assert_equal(one[["surface", "terrain"]], via_vrt[["surface", "terrain"]])
    # the surface stage's cache key follows the content of the tiles a VRT reads
    from skyroute.pipeline.model import stable_hash
    from skyroute.pipeline.stages_builtin import _surface_settings

    sc = load_scenario(_dsm_scenario(tmp_path, vrt, 1.0))
    key0 = stable_hash(_surface_settings(sc))
    assert stable_hash(_surface_settings(load_scenario(_dsm_scenario(tmp_path, vrt, 1.0)))) == key0
    with rasterio.open(tiles[0][0], "r+") as dst:
        dst.write(dst.read(1) + np.float32(1.0), 1)
    assert stable_hash(_surface_settings(load_scenario(_dsm_scenario(tmp_path, vrt, 1.0)))) != key0


def test_dsm_nodata_policies_and_extent_messages(tmp_path):
    z = _true_dsm()
    path = _write_dsm(tmp_path / "dsm.tif", z)
    with pytest.raises(DataError, match=r"data.surface: 2 NoData region\(s\) inside the raster's extent \(0 touching "
                       r"its edge\) cover .* data.surface.nodata is 'error'; set data.surface.nodata to fill-max .* or "
                       r"fill-nearest"):
        build_surface(_dsm_grid(1.0), surface_path=path, surface_datum="NAP", surface_nodata="error")
    # the AOI reaching over the NoData strip on the file's edge: inside the extent, filled from its rim
    ds = build_surface(Grid.from_bounds("EPSG:28992", 92040, 437020, 92100, 437120, 1.0), surface_path=path,
                       surface_datum="NAP")
    assert np.isfinite(ds["surface"].values).all()
    assert any("1 NoData region(s) of the DSM (1 touching its edge)" in w and "fill-nearest, error" in w
               for w in json.loads(ds.attrs["warnings"]))
    # the AOI reaching past the raster's extent: refused with the aoi.bounds that fit
    with pytest.raises(DataError, match=r"data.surface: covers only 9\d\.\d % of the AOI: \d+ cells are outside the "
                       r"raster's extent; set aoi.bounds to \[92040, 437020, 92120, 437120\] \(with aoi.crs EPSG:28992\)"):
        build_surface(Grid.from_bounds("EPSG:28992", 92040, 437020, 92125, 437120, 1.0), surface_path=path,
                      surface_datum="NAP")
    with pytest.raises(DataError, match="covers only"):
        build_surface(Grid.from_bounds("EPSG:28992", 91990, 437020, 92050, 437100, 1.0), surface_path=path,
                      surface_datum="NAP")
    # fill-nearest: every hole pixel takes the value of a valid pixel at the minimum distance
    from skyroute.stages.grid import fill_holes, read_window_holes

    grid = _dsm_grid(1.0)
    assert np.isfinite(build_surface(grid, surface_path=path, surface_datum="NAP",
                                     surface_nodata="fill-nearest")["surface"].values).all()
    win, holes = read_window_holes(path, grid, what="DSM")
    near = fill_holes(win, holes, "fill-nearest")
    c0, r0 = int(round((win.transform.c - DSM_T.c) / 0.5)), int(round((DSM_T.f - win.transform.f) / 0.5))
    with rasterio.open(path) as src:
        raw = src.read(1, masked=True).filled(np.nan).astype(float)
    valid = np.argwhere(np.isfinite(raw))
    hole_px = np.argwhere(holes.interior)
    assert len(hole_px) == 10 * 15 + 15 * 30 + 3 * 40   # the strip on the edge too
    for i, j in hole_px[::23]:
        d = np.hypot(valid[:, 0] - (i + r0), valid[:, 1] - (j + c0))
        best = valid[np.abs(d - d.min()) < 1e-9]
        assert any(near[i, j] == raw[a_, b_] for a_, b_ in best)
    with pytest.raises(InputError, match="vertical_datum is required"):
        build_surface(_dsm_grid(1.0), surface_path=path, surface_datum=None)
    with pytest.raises(InputError, match="differs from data.terrain.vertical_datum"):
        build_surface(_dsm_grid(1.0), surface_path=path, surface_datum="NAP",
                      terrain_path=path, vertical_datum="EGM96 geoid")
    with pytest.raises(DataError, match="does not intersect surface DSM"):
        build_surface(Grid.from_bounds("EPSG:28992", 0, 0, 100, 100, 1.0), surface_path=path, surface_datum="NAP")


def test_ground_from_dsm_is_a_grey_opening_and_finds_the_buildings(tmp_path):
    from skyroute.stages.surface import ground_from_dsm

    rng = np.random.default_rng(2)
    a = rng.normal(0, 1, (30, 40)).cumsum(axis=1)
    a[:, :9] = np.nan                      # outside the extent: takes no part
    a[20:, 30:] = np.nan
    g = ground_from_dsm(a, 1.0, 5.0)
    pad = np.pad(a, 2, mode="edge")
    ero = np.array([[np.nanmin(pad[i:i + 5, j:j + 5]) if np.isfinite(pad[i:i + 5, j:j + 5]).any() else np.inf
                     for j in range(40)] for i in range(30)])
    ero[np.isnan(a)] = -np.inf
    pad = np.pad(ero, 2, mode="edge")
    ref = np.array([[pad[i:i + 5, j:j + 5].max() for j in range(40)] for i in range(30)])
    ref[np.isnan(a)] = np.nan
    np.testing.assert_allclose(g, ref)
    assert np.all(g[np.isfinite(a)] <= a[np.isfinite(a)])
    z = _true_dsm()
    ds = build_surface(_dsm_grid(1.0), surface_path=_write_dsm(tmp_path / "dsm.tif", z, holes=False),
                       surface_datum="NAP")
    grid = _dsm_grid(1.0)
    slope = _box_oracle(1.0 + 0.01 * np.arange(240)[None] + 0.005 * np.arange(240)[:, None], DSM_T, grid)
    roof = _box_oracle(np.pad(np.ones((40, 60)), ((60, 140), (50, 130))), DSM_T, grid, "min") > 0
    # the ground under the flat roof is the slope (window 60 m > 30 m building), up to the
    # opening's bias on a slope: the lowest point around the roof, <= slope x roof width (0.3 m)
    err = ds["terrain"].values[roof] - slope[roof]
    assert err.min() > -0.02 and err.max() < 0.3
    assert ds["dsm_building"].values[roof].all()
    assert not ds["dsm_building"].values[~roof & (slope > 0)].all()
    assert json.loads(ds.attrs["warnings"])[0].startswith("surface: no DEM (data.terrain): the ground is derived")
    assert "grey opening with a 60 m square window" in ds.attrs["ground_source"]
    assert np.all(ds["terrain_min"].values <= ds["terrain"].values)
    assert np.all(ds["terrain"].values <= ds["surface"].values)
    # with a DEM (the slope): no derived ground, no warning; roofs = lowest DSM > highest ground + 2.5 m
    dem = tmp_path / "dem.tif"
    with rasterio.open(dem, "w", driver="GTiff", width=240, height=240, count=1, dtype="float64", crs="EPSG:28992",
                       transform=DSM_T) as dst:
        dst.write(1.0 + 0.01 * np.arange(240)[None] + 0.005 * np.arange(240)[:, None], 1)
    ds2 = build_surface(grid, surface_path=tmp_path / "dsm.tif", surface_datum="NAP", terrain_path=dem,
                        vertical_datum="nap")
    np.testing.assert_array_equal(ds2["terrain"].values, slope.astype(np.float32))
    assert "warnings" not in ds2.attrs and ds2.attrs["ground_source"].startswith("DEM")
    low = _box_oracle(z.astype(np.float32).astype(float), DSM_T, grid, "min")
    np.testing.assert_array_equal(ds2["dsm_building"].values, low - slope > 2.5)
    assert ds2["dsm_building"].values[roof].all()


def test_dataset_conventions(helsinki_surface):
    ds = helsinki_surface
    for v in ("terrain", "surface", "building_id"):
        assert ds[v].dims == ("y", "x")
        assert "units" in ds[v].attrs
    assert ds["surface"].attrs["vertical_datum"].startswith("local ground")
    assert ds["surface"].rio.crs.to_epsg() == 32635
    x, y = ds["x"].values, ds["y"].values
    assert np.all(np.diff(x) == 2.0) and np.all(np.diff(y) == -2.0)
    assert float((ds["surface"] >= ds["terrain"]).all())


def test_bad_inputs(tmp_path, helsinki):
    g = helsinki.grid
    with pytest.raises(DataError, match="OSM file not found"):
        build_surface(g, buildings_path=tmp_path / "x.osm.pbf", buildings_format="osm")
    with pytest.raises(InputError, match="unknown buildings format 'shp'"):
        build_surface(g, buildings_path=tmp_path / "x", buildings_format="shp")
    with pytest.raises(DataError, match="does not intersect any building"):
        far = Grid.from_bounds(g.crs, 500000, 6600000, 501000, 6601000, 5.0)
        build_surface(far, buildings_path=CATALOG_DATA / "helsinki_center.osm.pbf", buildings_format="osm")
    with pytest.raises(DataError, match="does not intersect terrain"):
        build_surface(g, terrain_path=CATALOG_DATA / "srtm_bigtujunga30m_utm11.tif")
    bad = tmp_path / "bad.city.json"
    bad.write_text("{not json")
    with pytest.raises(DataError, match="not valid CityJSON"):
        build_surface(g, buildings_path=bad, buildings_format="cityjson")
    with pytest.raises(InputError, match="resolution 0 m must be positive"):
        Grid.from_bounds(g.crs, 0, 0, 10, 10, 0)


def _dsm_scenario(tmp_path, dsm_path, res, extra_data=""):
    yaml_text = f"""
name: my-dsm
aoi: {{crs: "EPSG:28992", bounds: [92010.3, 437010.7, 92110.3, 437110.7], resolution_m: {res}}}
data:
  surface: {{path: {dsm_path.name}, vertical_datum: NAP}}
{extra_data}mission:
  start: {{x: 92015, y: 437015, alt_agl_m: 30}}
  goal: {{x: 92100, y: 437100, alt_agl_m: 30}}
  start_time_utc: 2020-01-03T12:00:00Z
constraints: {{min_altitude_agl_m: 0, max_altitude_agl_m: 80}}
"""
    p = tmp_path / f"my-dsm-{res:g}.yaml"
    p.write_text(yaml_text)
    return p


def _prism_clearance_at_cells(true_z, T, grid, z_cell):
    """Exact distance [m] from every point of each cell's square at altitude ``z_cell`` to the
    nearest 0.5 m prism of ``true_z`` (clipped to the grid's extent, the clearance contract),
    by brute force over the prisms within reach."""
    sy, sx = true_z.shape
    xl = T.c + np.arange(sx) * T.a
    yt = T.f + np.arange(sy) * T.e
    bx0, by0, bx1, by1 = grid.bounds
    px0, px1 = np.maximum(xl, bx0), np.minimum(xl + T.a, bx1)
    py1, py0 = np.minimum(yt, by1), np.maximum(yt + T.e, by0)
    colok, rowok = px1 > px0, py1 > py0
    r = grid.resolution_m
    out = np.empty(grid.shape)
    for i in range(grid.ny):
        Y1 = grid.y1 - i * r
        rows = rowok & (py0 < Y1 + 6) & (py1 > Y1 - r - 6)
        dy = np.maximum(np.maximum(py0[rows] - Y1, (Y1 - r) - py1[rows]), 0.0)[:, None]
        zz = true_z[rows]
        for j in range(grid.nx):
            X0 = grid.x0 + j * r
            cols = colok & (px0 < X0 + r + 6) & (px1 > X0 - 6)
            dx = np.maximum(np.maximum(px0[cols] - (X0 + r), X0 - px1[cols]), 0.0)[None, :]
            dz = np.maximum(z_cell[i, j] - zz[:, cols], 0.0)
            out[i, j] = np.sqrt(dx * dx + dy * dy + dz * dz).min()
    return out


def test_plan_on_my_own_dsm_from_a_scenario_yaml(tmp_path):
    """A user's DSM with NoData holes through run_scenario: surface, environment, clearance; the
    exact sphere-prism clearance over the true 0.5 m DSM is >= r_p at every cell's lowest allowed
    altitude, at 1 m and 2 m; DSM roofs are level 3 in the risk map; the derived ground is a warning."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.runner import run_scenario
    from skyroute.stages.vehicle import load_vehicle

    z = _true_dsm()
    dsm = _write_dsm(tmp_path / "town_dsm.tif", z)
    r_p = load_vehicle("dji-m300-rtk").r_p_m
    for res in (1.0, 2.0):
        sc = load_scenario(_dsm_scenario(tmp_path, dsm, res))
        out = run_scenario(sc, cache=Cache(tmp_path / "cache"), targets=["clearance"])
        surf, clr, env = out["surface"].load(), out["clearance"].load(), out["environment"].load()
        grid = sc.grid
        lo = clr["min_altitude_m"].values
        d = _prism_clearance_at_cells(z, DSM_T, grid, lo)
        assert d.min() >= r_p - 1e-4, (res, d.min())
        assert d.min() < r_p + 1e-3             # and tight: the floor is computed on the 0.5 m prisms
        assert np.all(clr["max_altitude_m"].values == surf["terrain_min"].values + np.float32(80.0))
        assert np.all(lo >= surf["terrain"].values)
        roofs = surf["dsm_building"].values
        assert roofs.sum() > 100
        lv = env["risk_level"].values
        assert np.all(lv[roofs] == 3) and np.all(lv[~roofs] == 4)
        assert any("ground is derived from the DSM" in w for w in json.loads(surf.attrs["warnings"]))


def test_dsm_scenario_errors(tmp_path):
    from skyroute.pipeline.errors import ScenarioError

    dsm = _write_dsm(tmp_path / "town_dsm.tif", _true_dsm())
    dem = tmp_path / "dem.tif"
    dem.write_bytes(dsm.read_bytes())
    p = _dsm_scenario(tmp_path, dsm, 1.0, extra_data="  terrain: {path: dem.tif, vertical_datum: EGM96 geoid}\n")
    with pytest.raises(ScenarioError, match="data.surface.vertical_datum: 'NAP' differs from data.terrain.vertical_datum"):
        load_scenario(p)
    p.write_text(p.read_text().replace("vertical_datum: NAP", "nodata: fill-min").replace(
        "  terrain: {path: dem.tif, vertical_datum: EGM96 geoid}\n", ""))
    with pytest.raises(ScenarioError, match=r"(?s)data.surface.vertical_datum: required key is missing.*data.surface.nodata"):
        load_scenario(p)
    p.write_text(p.read_text().replace("path: town_dsm.tif, nodata: fill-min", "path: [], vertical_datum: NAP"))
    with pytest.raises(ScenarioError, match="data.surface.path: give a GeoTIFF, a VRT or a non-empty list of tiles"):
        load_scenario(p)
    p.write_text(p.read_text().replace("path: []", "path: [town_dsm.tif, missing_tile.tif]"))
    with pytest.raises(ScenarioError, match="data.surface.path: data file not found: .*missing_tile.tif"):
        load_scenario(p)


ROTTERDAM_DSM = Path(__file__).parent / "data" / "rotterdam_dsm_0p5m.tif"


@pytest.mark.parametrize("res", [1.0, 2.0])
def test_rotterdam_lod2_dsm_planned_at_1_and_2_m_keeps_r_p_everywhere(tmp_path, res):
    """The 0.5 m DSM rasterised exactly from the Rotterdam LoD2 CityJSON (250 m x 250 m fixture
    of tests/data), given as data.surface and planned at 1 and 2 m: the exact sphere-prism
    clearance over the 0.5 m prisms is >= r_p at every cell's lowest allowed altitude, every
    cell of the window."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.runner import run_scenario
    from skyroute.stages.vehicle import load_vehicle

    if not ROTTERDAM_DSM.is_file():
        pytest.skip(f"fixture {ROTTERDAM_DSM} (rasterised by tests/data/make_rotterdam_dsm.py) not present")
    with rasterio.open(ROTTERDAM_DSM) as src:
        z, T, b = src.read(1).astype(np.float64), src.transform, src.bounds
    p = tmp_path / "rotterdam-dsm.yaml"
    p.write_text(f"""
name: rotterdam-dsm
aoi: {{crs: "EPSG:28992", bounds: [{b.left}, {b.bottom}, {b.right}, {b.top}], resolution_m: {res}}}
data:
  surface: {{path: {ROTTERDAM_DSM}, vertical_datum: NAP}}
mission:
  start: {{x: {b.left + 5}, y: {b.bottom + 5}, alt_agl_m: 60}}
  goal: {{x: {b.right - 5}, y: {b.top - 5}, alt_agl_m: 60}}
  start_time_utc: 2020-01-03T12:00:00Z
constraints: {{min_altitude_agl_m: 0, max_altitude_agl_m: 80}}
""")
    sc = load_scenario(p)
    out = run_scenario(sc, cache=Cache(tmp_path / "cache"), targets=["clearance"])
    lo = out["clearance"]["min_altitude_m"].values
    grid = sc.grid
    assert grid.shape == (int(250 / res), int(250 / res))
    r_p = load_vehicle(sc.vehicle).r_p_m
    d = _prism_clearance_at_cells(z, T, grid, lo)
    assert d.min() >= r_p - 1e-4, d.min()
    # exact, not only safe: away from the window's edge (where the oracle sees no prism beyond it)
    # every cell's floor is exactly r_p from the nearest prism (the floor on the DSM's own prisms)
    k = int(np.ceil((r_p + 1) / res))
    assert np.abs(d[k:-k, k:-k] - r_p).max() < 1e-3
    assert float(out["surface"]["surface"].max()) == pytest.approx(z.max(), abs=1e-4)


def test_dsm_in_another_crs_keeps_r_p_at_every_cell(tmp_path):
    """The town DSM (Dutch RD, EPSG:28992) planned on a UTM 31N grid (pixels rotated by ~2 deg):
    footprint max across CRSs, then the clearance floor; the exact distance from each cell's square
    (at its lowest allowed altitude) to every rotated 0.5 m prism, by shapely, is >= r_p."""
    from pyproj import Transformer

    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.runner import run_scenario

    z = _true_dsm()
    dsm = _write_dsm(tmp_path / "town_dsm.tif", z)
    cx, cy = Transformer.from_crs(28992, 32631, always_xy=True).transform(92060.0, 437060.0)
    p = tmp_path / "utm.yaml"
    p.write_text(f"""
name: town-utm
aoi: {{crs: "EPSG:32631", bounds: [{cx - 20:.1f}, {cy - 20:.1f}, {cx + 20:.1f}, {cy + 20:.1f}], resolution_m: 2.0}}
data:
  surface: {{path: {dsm.name}, vertical_datum: NAP}}
mission:
  start: {{x: {cx - 15:.1f}, y: {cy - 15:.1f}, alt_agl_m: 60}}
  goal: {{x: {cx + 15:.1f}, y: {cy + 15:.1f}, alt_agl_m: 60}}
  start_time_utc: 2020-01-03T12:00:00Z
""")
    sc = load_scenario(p)
    out = run_scenario(sc, cache=Cache(tmp_path / "cache"), targets=["clearance"])
    lo = out["clearance"]["min_altitude_m"].values
    g = sc.grid
    to_utm = Transformer.from_crs(28992, 32631, always_xy=True)
    # every 0.5 m prism whose footprint overlaps the grid (clipped to it), as a rotated polygon
    jj, ii = np.meshgrid(np.arange(DSM_SHAPE[1] + 1), np.arange(DSM_SHAPE[0] + 1))
    X, Y = to_utm.transform(*(DSM_T * (jj, ii)))
    quads = np.stack([np.stack([X[:-1, :-1], X[:-1, 1:], X[1:, 1:], X[1:, :-1]], -1),
                      np.stack([Y[:-1, :-1], Y[:-1, 1:], Y[1:, 1:], Y[1:, :-1]], -1)], -1)
    box = shapely.box(*g.bounds)
    near = (quads[..., 0].max(-1) > g.bounds[0] - 6) & (quads[..., 0].min(-1) < g.bounds[2] + 6) & \
           (quads[..., 1].max(-1) > g.bounds[1] - 6) & (quads[..., 1].min(-1) < g.bounds[3] + 6)
    polys = shapely.intersection(shapely.polygons(quads[near]), box)
    keep = ~shapely.is_empty(polys)
    polys, h = polys[keep], z[near][keep]
    tree = shapely.STRtree(polys)
    r_p = 5.0
    worst = np.inf
    for i in range(g.ny):
        for j in range(g.nx):
            cell = shapely.box(g.x0 + 2 * j, g.y1 - 2 * (i + 1), g.x0 + 2 * (j + 1), g.y1 - 2 * i)
            idx = tree.query(cell, predicate="dwithin", distance=r_p)
            dh = shapely.distance(cell, polys[idx])
            dz = np.maximum(lo[i, j] - h[idx], 0.0)
            worst = min(worst, float(np.sqrt(dh * dh + dz * dz).min()))
    assert worst >= r_p - 1e-4
    assert worst < r_p + 1.0


def test_dsm_with_osm_buildings_and_a_dem(tmp_path):
    """data.surface with OSM buildings and a DEM (Helsinki): surface = max of both, the DEM is the
    ground (no warning), roofs from the DSM; the clearance floor keeps r_p from the 0.5 m DSM prisms
    and from the grid's building prisms at every cell's lowest allowed altitude."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.runner import run_scenario

    T = Affine(0.5, 0.0, 385900.25, 0.0, -0.5, 6672300.25)
    z = _true_dsm() + 5.0
    _write_dsm(tmp_path / "hel_dsm.tif", z, holes=False, transform=T, crs="EPSG:32635")
    ground = 6.0 + 0.01 * np.arange(240)[None] + 0.005 * np.arange(240)[:, None]
    with rasterio.open(tmp_path / "hel_dem.tif", "w", driver="GTiff", width=240, height=240, count=1,
                       dtype="float64", crs="EPSG:32635", transform=T) as dst:
        dst.write(ground, 1)
    osm = CATALOG_DATA / "helsinki_center.osm.pbf"
    p = tmp_path / "hel.yaml"
    p.write_text(f"""
name: hel-dsm
aoi: {{crs: "EPSG:32635", bounds: [385910, 6672190, 386010, 6672290], resolution_m: 2.0}}
data:
  buildings: {{path: {osm}, format: osm}}
  terrain: {{path: hel_dem.tif, vertical_datum: N2000}}
  surface: {{path: hel_dsm.tif, vertical_datum: N2000}}
mission:
  start: {{x: 385915, y: 6672195, alt_agl_m: 60}}
  goal: {{x: 386005, y: 6672285, alt_agl_m: 60}}
  start_time_utc: 2020-01-03T12:00:00Z
""")
    sc = load_scenario(p)
    out = run_scenario(sc, cache=Cache(tmp_path / "cache"), targets=["clearance"])
    surf, lo = out["surface"].load(), out["clearance"]["min_altitude_m"].values
    g = sc.grid
    assert "warnings" not in surf.attrs and surf.attrs["vertical_datum"] == "N2000"
    bid = surf["building_id"].values
    assert (bid >= 0).sum() > 50
    np.testing.assert_array_equal(surf["terrain"].values, _box_oracle(ground, T, g).astype(np.float32))
    top = np.where(bid >= 0, surf["terrain"].values + surf["building_height_m"].values[np.maximum(bid, 0)], -np.inf)
    np.testing.assert_allclose(surf["surface"].values, np.maximum(_box_oracle(z.astype(np.float32), T, g), top),
                               rtol=0, atol=1e-4)
    r_p = 5.0
    assert _prism_clearance_at_cells(z, T, g, lo).min() >= r_p - 1e-4
    # the grid's building prisms: every cell of the grid as a prism of its building top
    bt = np.where(bid >= 0, surf["surface"].values, -1e9).astype(float)
    d_b = _prism_clearance_at_cells(bt, g.transform, g, lo)
    assert d_b.min() >= r_p - 1e-4
    assert min(d_b.min(), _prism_clearance_at_cells(z, T, g, lo).min()) < r_p + 1e-3
