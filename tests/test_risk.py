"""Ground-risk levels, cost normalisation and no-fly mask, checked on real OSM/CityJSON data
against brute-force shapely/pyproj oracles and hand-computed integrals."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
import shapely
import yaml
from pyproj import CRS, Transformer

from skyroute.pipeline.errors import DataError, InputError
from skyroute.stages import risk as R
from skyroute.stages.grid import Grid
from skyroute.stages.osm import read_osm

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "catalogs" / "data"
MONACO = DATA / "monaco_2019-09-30.osm.pbf"
HELSINKI = DATA / "helsinki_center.osm.pbf"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
DELFT = SHARED / "city" / "delft_lod1.city.json"
TABLE = yaml.safe_load((ROOT / "catalogs" / "risk_tags.yaml").read_text())


def grid_around(lon0, lat0, lon1, lat1, res, crs=None):
    from skyroute.stages.grid import utm_crs_for

    crs = crs or utm_crs_for((lon0 + lon1) / 2, (lat0 + lat1) / 2)
    b = Transformer.from_crs(4326, crs, always_xy=True).transform_bounds(lon0, lat0, lon1, lat1)
    return Grid.from_bounds(crs, *b, res)


def level_at(da, grid, lon, lat):
    x, y = grid.from_lonlat(lon, lat)
    r, c = grid.index_of(x, y)
    return int(da.values[r, c])


def table_level(tags):
    """Independent reading of the YAML table: highest matching level, '*' = any but 'no'."""
    best = None
    for key, vals in TABLE["osm"].items():
        v = tags.get(key)
        if v is None or v == "no":
            continue
        lv = vals.get(v, vals.get("*"))
        if lv is not None:
            best = lv if best is None else max(best, lv)
    return best


@pytest.fixture(scope="module")
def helsinki_full():
    from skyroute.pipeline.settings import load_scenario

    g = load_scenario("helsinki-medical").grid
    return g, R.risk_levels(g, osm_path=HELSINKI)


# ------------------------------------------------------------------ tag table
def test_default_table_loads_and_matches_seed_levels():
    t = R.load_tag_table()
    assert t.default_level == 4
    assert t.osm["amenity"]["hospital"] == 5 and t.osm["railway"]["station"] == 5
    assert t.osm["building"]["*"] == 3 and t.osm["leisure"]["park"] == 1
    assert t.osm["landuse"]["industrial"] == 2 and t.osm["aeroway"]["aerodrome"] == 6
    assert t.osm_level({"building": "yes", "amenity": "hospital"}) == 5  # highest tag wins
    assert t.osm_level({"building": "no"}) is None
    assert t.cityjson_level("LandUse", {"bgt_fysiekvoorkomen": "onverhard"}) == 1
    assert t.cityjson_level("LandUse", {"bgt_fysiekvoorkomen": "erf"}) == 4


def test_bad_tag_tables_name_key_and_file(tmp_path):
    bad = tmp_path / "my_tags.yaml"
    bad.write_text("landuse: {forest: 1}\nosm: {amenity: {hospital: 7}}\n")
    with pytest.raises(InputError, match=r"my_tags\.yaml") as ei:
        R.load_tag_table(bad)
    msg = str(ei.value)
    assert "unknown top-level key 'landuse'" in msg and "go under 'osm:'" in msg
    assert "osm.amenity.hospital: level 7 is outside 1..6" in msg
    with pytest.raises(InputError, match=r"cityjson\.Road: level 0 is outside 1\.\.6"):
        R.load_tag_table({"cityjson": {"Road": 0}})
    with pytest.raises(InputError, match=r"unknown key landing\.sometimes"):
        R.load_tag_table({"landing": {"sometimes": {"aeroway": ["helipad"]}}})
    with pytest.raises(DataError, match="risk tag table not found"):
        R.load_tag_table(tmp_path / "missing.yaml")


# ------------------------------------------------------------------ levels on real data
def test_monaco_hospital_cell_is_level5():
    feats = [f for f in read_osm(MONACO, keys=["amenity"]) if f.tags.get("name") == "Centre Hospitalier Princesse Grace"]
    assert feats and feats[0].geometry.contains(shapely.Point(7.41109, 43.73033))  # data sanity
    g = grid_around(7.4095, 43.7292, 7.4130, 43.7315, 2.0)
    lv = R.risk_levels(g, osm_path=MONACO)
    assert lv.dtype == np.int8 and lv.rio.crs == g.crs and lv.attrs["units"] == "1"
    assert level_at(lv, g, 7.41109, 43.73033) == 5


def test_helsinki_station_school_park_roof(helsinki_full):
    g, lv = helsinki_full
    feats = read_osm(HELSINKI)
    by_id = {f.osm_id: f for f in feats if f.kind == "area"}
    station = by_id[122595198].geometry.representative_point()   # building=train_station
    school = by_id[596507272].geometry.representative_point()    # amenity=school (Kaisaniemen ala-aste)
    assert level_at(lv, g, station.x, station.y) == 5
    assert level_at(lv, g, school.x, school.y) == 5
    assert level_at(lv, g, 24.9414566, 60.1713198) == 5          # node railway=station "Helsinki"
    tagged = [f for f in feats if f.kind == "area" and table_level(f.tags) is not None]
    # a park point covered by nothing else, and a plain building roof covered by nothing else
    for want, pick in ((1, lambda t: t.get("leisure") == "park"), (3, lambda t: t.get("building") == "yes" and len(t) <= 3)):
        n_checked = 0
        for f in feats:
            if f.kind != "area" or not pick(f.tags) or table_level(f.tags) != want:
                continue
            p = f.geometry.representative_point()
            x, y = g.from_lonlat(p.x, p.y)
            if not g.contains(x, y) or any(o is not f and o.geometry.intersects(p.buffer(5e-5)) for o in tagged):
                continue
            assert level_at(lv, g, p.x, p.y) == want, (f.osm_id, f.tags)
            n_checked += 1
            if n_checked == 3:
                break
        assert n_checked >= 1


def test_osm_levels_match_bruteforce_oracle():
    """Every cell of a 560 m x 670 m Helsinki window against shapely point-in-polygon."""
    g = grid_around(24.9360, 60.1680, 24.9460, 60.1740, 4.0)
    lv = R.risk_levels(g, osm_path=HELSINKI).values
    tf = Transformer.from_crs(4326, g.crs, always_xy=True)
    X, Y = np.meshgrid(g.x, g.y)
    want = np.zeros(g.shape, np.int8)
    box = shapely.box(*g.bounds).buffer(50)
    radius = TABLE["point_radius_m"]
    for f in read_osm(HELSINKI):
        lvl = table_level(f.tags)
        if lvl is None or f.kind not in ("area", "node"):
            continue
        geom = shapely.transform(f.geometry, lambda xy: np.column_stack(tf.transform(xy[:, 0], xy[:, 1])))
        if not geom.intersects(box):
            continue
        if f.kind == "area":
            inside = shapely.contains_xy(geom, X, Y)
        else:
            r, c = g.index_of(geom.x, geom.y)
            inside = np.hypot(X - geom.x, Y - geom.y) < radius
            if 0 <= r < g.ny and 0 <= c < g.nx:
                inside[r, c] = True
        want[inside] = np.maximum(want[inside], lvl)
    want[want == 0] = 4
    mismatch = int((want != lv).sum())
    assert mismatch <= 0.002 * lv.size, f"{mismatch} of {lv.size} cells differ"
    assert set(np.unique(lv)) >= {1, 3, 4, 5}


@pytest.fixture(scope="module")
def delft():
    if not DELFT.exists():
        pytest.skip(f"shared data missing: {DELFT}")
    return json.loads(DELFT.read_text())


def test_cityjson_levels_delft(delft):
    tr = delft["transform"]
    V = np.asarray(delft["vertices"], float)[:, :2] * tr["scale"][:2] + tr["translate"][:2]
    g = Grid.from_bounds("EPSG:28992", V[:, 0].min(), V[:, 1].min(), V[:, 0].max(), V[:, 1].max(), 1.0)
    lv = R.risk_levels(g, cityjson_path=DELFT)
    # footprints: 2-D union of each object's surfaces (independent of the module's rasteriser)
    foot = {}
    for oid, o in delft["CityObjects"].items():
        polys = []
        for geom in o.get("geometry", []):
            b = geom["boundaries"]
            shells = b if geom["type"] == "Solid" else [b]
            for shell in shells:
                for surf in shell:
                    p = shapely.Polygon(V[surf[0]])
                    if p.area > 1e-3:
                        polys.append(p.buffer(0))
        if polys:
            foot[oid] = (o["type"], o.get("attributes", {}), shapely.union_all(polys))
    fps = [v[2] for v in foot.values() if v[0] != "GenericCityObject"]
    tree = shapely.STRtree(shapely.buffer(np.asarray(fps, dtype=object), 1.0))
    expected_of = {"Building": 3, "PlantCover": 1, "Road": 4, "WaterBody": 1}
    checked = dict.fromkeys(expected_of, 0)
    for _, (typ, attrs, fp) in foot.items():
        if typ not in expected_of or checked[typ] >= 5 or fp.area < 20:
            continue
        p = fp.representative_point()
        if len(tree.query(p, predicate="intersects")) > 1:
            continue  # the point is near another object: precedence decides, not tested here
        r, c = g.index_of(p.x, p.y)
        assert int(lv.values[r, c]) == expected_of[typ], (typ, attrs.get("function"))
        checked[typ] += 1
    assert checked == {"Building": 5, "PlantCover": 5, "Road": 5, "WaterBody": 2}, checked  # 3 water bodies exist


def test_default_level_and_bad_default():
    g = grid_around(24.90, 60.10, 24.902, 60.101, 5.0)  # south of the Helsinki extract: nothing mapped
    assert (R.risk_levels(g, osm_path=HELSINKI).values == 4).all()
    assert (R.risk_levels(g, osm_path=HELSINKI, default_level=1).values == 1).all()
    with pytest.raises(InputError, match="default_level 7 must be an integer level 1..6"):
        R.risk_levels(g, default_level=7)


def test_risk_from_geotiff_nearest(tmp_path):
    g = Grid.from_bounds("EPSG:32635", 385000, 6670000, 385040, 6670024, 2.0)  # 20 x 12 cells
    rng = np.random.default_rng(3)
    coarse = rng.integers(1, 7, size=(6, 10)).astype(np.uint8)     # 4 m cells, same origin
    path = tmp_path / "risk.tif"
    with rasterio.open(path, "w", driver="GTiff", width=10, height=6, count=1, dtype="uint8", crs="EPSG:32635",
                       transform=rasterio.Affine(4, 0, 385000, 0, -4, 6670024), nodata=0) as dst:
        dst.write(coarse, 1)
    lv = R.risk_from_geotiff(path, g)
    np.testing.assert_array_equal(lv.values, np.repeat(np.repeat(coarse, 2, 0), 2, 1))
    coarse[0, 0] = 9
    with rasterio.open(path, "r+") as dst:
        dst.write(coarse, 1)
    with pytest.raises(DataError, match="not risk levels 1..6"):
        R.risk_from_geotiff(path, g)


# ------------------------------------------------------------------ cost normalisation
def synthetic_levels(values):
    v = np.asarray(values, np.int8)
    g = Grid(CRS.from_epsg(32635).to_wkt(), 1000.0, 2000.0, v.shape[1], v.shape[0], 5.0)
    return g, R._levels_dataarray(g, v)


def test_cost_integral_along_straight_path_is_hand_value():
    row = [1, 3, 3, 4, 5, 2, 4, 4, 3, 1]
    g, lv = synthetic_levels([row] * 4)
    c = R.risk_cost(lv)
    assert c.attrs["level_min"] == 1 and c.attrs["level_max"] == 5 and c.rio.crs == g.crs
    y = g.y[1]
    # west edge to east edge of the grid through cell centres: sum of (L - 1) / 4 * 5 m
    hand = sum((L - 1) / 4 for L in row) * 5.0
    assert R.integrate_along_path(c, [(g.x0, y), (g.x0 + 50.0, y)]) == pytest.approx(hand, abs=1e-6)
    assert hand == pytest.approx(25.0)
    # a path from the middle of cell 1 to the middle of cell 4: half of 3, cells 3..4, half of 5
    hand2 = (0.5 * 0.5 + 0.5 + 0.75 + 0.5 * 1.0) * 5.0
    assert R.integrate_along_path(c, [(g.x[1], y), (g.x[4], y)]) == pytest.approx(hand2, abs=1e-6)
    # a diagonal through a uniform level-4 block (levels 1 and 5 present elsewhere): 0.75 * length
    blk = np.full((8, 8), 4, np.int8)
    blk[7, 7], blk[7, 0] = 1, 5
    g2, lv2 = synthetic_levels(blk)
    c2 = R.risk_cost(lv2)
    diag = [(g2.x[0], g2.y[0]), (g2.x[6], g2.y[6])]
    assert R.integrate_along_path(c2, diag) == pytest.approx(0.75 * np.hypot(30.0, 30.0), rel=1e-9)


def test_cost_scale_and_level5_nofly():
    g, lv = synthetic_levels([[3, 4, 5, 6], [3, 3, 4, 4]])
    c_map = R.risk_cost(lv).values
    np.testing.assert_allclose(c_map[0], [0.0, 0.5, 1.0, np.inf])          # min-max over 3..5
    c_scale = R.risk_cost(lv, normalization="scale").values
    np.testing.assert_allclose(c_scale[0], [0.5, 0.75, 1.0, np.inf])        # (L - 1) / 4
    c5 = R.risk_cost(lv, level5_nofly=True).values
    np.testing.assert_allclose(c5[0], [0.0, 1.0, np.inf, np.inf])
    assert R.integrate_along_path(R.risk_cost(lv), [(g.x0, g.y[0]), (g.x0 + 20, g.y[0])]) == np.inf
    with pytest.raises(InputError, match="normalization 'minmax'"):
        R.risk_cost(lv, normalization="minmax")
    with pytest.raises(InputError, match="leaves the grid"):
        R.integrate_along_path(R.risk_cost(lv), [(g.x0 - 1, g.y[0]), (g.x0 + 5, g.y[0])])


# ------------------------------------------------------------------ no-fly
def write_geojson(path, features, **extra):
    path.write_text(json.dumps({"type": "FeatureCollection", "features": features, **extra}))
    return path


def lonlat_poly(grid, xy):
    lon, lat = grid.to_lonlat(np.array([p[0] for p in xy]), np.array([p[1] for p in xy]))
    return {"type": "Polygon", "coordinates": [list(zip(lon.tolist(), lat.tolist(), strict=True))]}


def test_nofly_mask_levels_zones_and_volume(tmp_path):
    vals = np.full((20, 20), 4, np.int8)
    vals[2, 2], vals[3, 3] = 6, 5
    g, lv = synthetic_levels(vals)
    x0, y1 = g.x0, g.y1
    zone_a = [(x0 + 23.3, y1 - 41.7), (x0 + 71.9, y1 - 43.2), (x0 + 60.4, y1 - 88.1), (x0 + 23.3, y1 - 41.7)]
    zone_b = [(x0 + 55.2, y1 - 60.6), (x0 + 90.8, y1 - 60.6), (x0 + 90.8, y1 - 95.3), (x0 + 55.2, y1 - 95.3),
              (x0 + 55.2, y1 - 60.6)]
    path = write_geojson(tmp_path / "zones.geojson", [
        {"type": "Feature", "properties": {"name": "A", "min_altitude_m": 30, "max_altitude_m": 60},
         "geometry": lonlat_poly(g, zone_a)},
        {"type": "Feature", "properties": {"name": "B", "max_altitude_m": 40}, "geometry": lonlat_poly(g, zone_b)},
    ])
    ds = R.nofly_mask(lv, path, level5_nofly=True)
    assert ds.rio.crs == g.crs and ds["nofly_floor_m"].attrs["units"] == "m"
    # oracle: cells whose square intersects the (map) polygon
    cells = shapely.box(*np.meshgrid(g.x - 2.5, g.y - 2.5), *np.meshgrid(g.x + 2.5, g.y + 2.5))
    in_a = shapely.intersects(cells, shapely.Polygon(zone_a))
    in_b = shapely.intersects(cells, shapely.Polygon(zone_b))
    zone_bit = (ds["nofly_reason"].values & R.NOFLY_ZONE) > 0
    assert int((zone_bit != (in_a | in_b)).sum()) <= 2  # lon/lat round trip may move an edge by < 1 mm
    assert ds["nofly_reason"].values[2, 2] == R.NOFLY_LEVEL6 and ds["nofly_reason"].values[3, 3] == R.NOFLY_LEVEL5
    fl, ce = ds["nofly_floor_m"].values, ds["nofly_ceiling_m"].values
    only_a, both = in_a & ~in_b & zone_bit, in_a & in_b & zone_bit
    assert only_a.any() and both.any()
    assert (fl[only_a] == 30).all() and (ce[only_a] == 60).all()
    assert (fl[both] == 0).all() and (ce[both] == 60).all()        # envelope of [30, 60] and [0, 40]
    assert fl[2, 2] == 0 and np.isinf(ce[2, 2]) and np.isnan(fl[0, 0]) and not ds["nofly"].values[0, 0]
    vol = R.nofly_volume(ds, [10.0, 50.0, 500.0])
    assert vol.dims == ("z", "y", "x")
    r, c = np.argwhere(only_a)[0]
    assert vol.values[:, r, c].tolist() == [False, True, False]
    assert vol.values[:, 2, 2].tolist() == [True, True, True]
    assert not vol.values[:, 0, 0].any()
    assert int(R.nofly_mask(lv).nofly.sum()) == 1                 # without level5_nofly: level 6 only


def test_bad_geojson_errors(tmp_path):
    g, lv = synthetic_levels(np.full((4, 4), 4))
    empty = write_geojson(tmp_path / "empty.geojson", [])
    with pytest.raises(InputError, match="has no features; add at least one Feature"):
        R.nofly_mask(lv, empty)
    sq = [[385000, 6670000], [385100, 6670000], [385100, 6670100], [385000, 6670000]]
    proj = write_geojson(tmp_path / "utm.geojson", [{"type": "Feature", "properties": {},
                                                     "geometry": {"type": "Polygon", "coordinates": [sq]}}])
    with pytest.raises(InputError, match=r"not longitude/latitude degrees.*ogr2ogr -t_srs EPSG:4326"):
        R.nofly_mask(lv, proj)
    named = write_geojson(tmp_path / "named.geojson", [], crs={"type": "name", "properties": {"name": "EPSG:28992"}})
    with pytest.raises(InputError, match="declares crs 'EPSG:28992'.*WGS 84 lon/lat"):
        R.nofly_mask(lv, named)
    pt = write_geojson(tmp_path / "pt.geojson", [{"type": "Feature", "properties": {},
                                                  "geometry": {"type": "Point", "coordinates": [24.9, 60.1]}}])
    with pytest.raises(InputError, match="is a Point; use one of Polygon, MultiPolygon"):
        R.nofly_mask(lv, pt)
    band = write_geojson(tmp_path / "band.geojson", [{"type": "Feature", "properties": {
        "min_altitude_m": 50, "max_altitude_m": 20}, "geometry": lonlat_poly(g, [(g.x0, g.y1), (g.x0 + 5, g.y1),
                                                                               (g.x0, g.y1 - 5), (g.x0, g.y1)])}])
    with pytest.raises(InputError, match="min_altitude_m < max_altitude_m"):
        R.nofly_mask(lv, band)
    with pytest.raises(DataError, match="not found"):
        R.nofly_mask(lv, tmp_path / "nope.geojson")
    lv_bad = lv.copy(data=np.full((4, 4), 7, np.int8))
    with pytest.raises(InputError, match="risk levels must be 1..6"):
        R.risk_cost(lv_bad)


def test_ring_fill_kernel_matches_shapely():
    """The scanline kernel used for CityJSON against shapely point-in-polygon, random polygons."""
    rng = np.random.default_rng(11)
    g = Grid(CRS.from_epsg(28992).to_wkt(), 0.0, 100.0, 90, 80, 1.25)
    X, Y = np.meshgrid(g.x, g.y)
    xs, ys, offsets, values = [], [], [0], []
    want = np.zeros(g.shape, np.uint8)
    for _ in range(25):
        cx, cy = rng.uniform(-10, 120), rng.uniform(-10, 110)
        ang = np.sort(rng.uniform(0, 2 * np.pi, rng.integers(3, 12)))
        rad = rng.uniform(2, 25, ang.size)
        px, py = cx + rad * np.cos(ang), cy + rad * np.sin(ang)
        lv = int(rng.integers(1, 7))
        inside = shapely.contains_xy(shapely.Polygon(np.column_stack([px, py])), X, Y)
        want[inside] = np.maximum(want[inside], lv)
        xs.append(px)
        ys.append(py)
        offsets.append(offsets[-1] + px.size)
        values.append(lv)
    from skyroute.stages.grid import ring_cells

    out = np.zeros(g.shape, np.uint8)
    ring, rr, cc = ring_cells(np.concatenate(xs), np.concatenate(ys), np.asarray(offsets, np.int64), g)
    np.maximum.at(out, (rr, cc), np.asarray(values, np.uint8)[ring])
    assert (want > 0).sum() > 1000
    np.testing.assert_array_equal(out, want)
