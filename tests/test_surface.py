"""Surface model against its sources: OSM tags, CityJSON roofs, the SRTM DEM."""

from __future__ import annotations

import json

import numpy as np
import osmium
import pytest
import rasterio
import shapely
from pyproj import Transformer

from skyroute.pipeline.errors import DataError, InputError
from skyroute.pipeline.settings import catalog_dir, load_scenario
from skyroute.stages.grid import Grid
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


def test_rotterdam_roofs_match_cityjson(shared_data):
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


def test_dem_is_resampled_bilinearly(shared_data):
    from scipy.interpolate import RegularGridInterpolator

    path = shared_data / "terrain" / "srtm_bigtujunga30m_utm11.tif"
    with rasterio.open(path) as src:
        b = src.bounds
        dem = src.read(1).astype(float)
        T = src.transform
        grid = Grid.from_bounds(src.crs.to_string(), b.left + 3000, b.bottom + 3000, b.left + 9000, b.bottom + 6000, 30.0)
    ds = build_surface(grid, terrain_path=path)
    # independent bilinear interpolation between DEM pixel centres
    xc = T.c + (np.arange(dem.shape[1]) + 0.5) * T.a
    yc = T.f + (np.arange(dem.shape[0]) + 0.5) * T.e
    interp = RegularGridInterpolator((yc[::-1], xc), dem[::-1])
    X, Y = np.meshgrid(grid.x, grid.y)
    ref = interp(np.column_stack([Y.ravel(), X.ravel()])).reshape(X.shape)
    np.testing.assert_allclose(ds["terrain"].values, ref, atol=0.05)
    assert ds.attrs["vertical_datum"] == "EGM96 geoid"
    assert ds["surface"].rio.crs.to_epsg() == 32611


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
