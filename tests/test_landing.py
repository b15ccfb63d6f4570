"""Landing sites and the landing-distance cost, checked against shapely/pyproj distances on real
OSM data (Monaco helipads, Helsinki parks) and hand-computed integrals."""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import numpy as np
import pytest
import shapely
import yaml
from pyproj import CRS, Transformer

from skyroute.pipeline.errors import InputError
from skyroute.stages import environment as E
from skyroute.stages import landing as L
from skyroute.stages import risk as R
from skyroute.stages.grid import Grid, utm_crs_for
from skyroute.stages.osm import read_osm

ROOT = Path(__file__).resolve().parents[1]
MONACO = ROOT / "catalogs" / "data" / "monaco_2019-09-30.osm.pbf"
HELSINKI = ROOT / "catalogs" / "data" / "helsinki_center.osm.pbf"
TABLE = yaml.safe_load((ROOT / "catalogs" / "risk_tags.yaml").read_text())


def grid_around(lon0, lat0, lon1, lat1, res):
    crs = utm_crs_for((lon0 + lon1) / 2, (lat0 + lat1) / 2)
    b = Transformer.from_crs(4326, crs, always_xy=True).transform_bounds(lon0, lat0, lon1, lat1)
    return Grid.from_bounds(crs, *b, res)


def projected(geom, crs):
    tf = Transformer.from_crs(4326, crs, always_xy=True)
    return shapely.transform(geom, lambda xy: np.column_stack(tf.transform(xy[:, 0], xy[:, 1])))


def write_sites(path, geoms_lonlat, names=None):
    feats = [{"type": "Feature", "properties": {"name": (names or [f"s{i}" for i in range(len(geoms_lonlat))])[i]},
              "geometry": shapely.geometry.mapping(g)} for i, g in enumerate(geoms_lonlat)]
    path.write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    return path


@pytest.fixture(scope="module")
def monaco_helipads():
    """Monaco window around the Centre Cardio-Thoracique helipad; helipads/heliports only."""
    g = grid_around(7.4215, 43.7350, 7.4285, 43.7405, 2.0)
    table = dict(TABLE, landing={"any_size": {"aeroway": ["helipad", "heliport"]}})
    sites = L.landing_sites(g, osm_path=MONACO, tag_table=table)
    return g, sites, L.landing_cost(g, sites)


def test_helipad_distance_within_one_cell(monaco_helipads):
    g, sites, lc = monaco_helipads
    assert "osm:area/572938549" in {s.source for s in sites}        # Centre Cardio-Thoracique helipad
    # reference: every helipad/heliport of the file, projected with pyproj, shapely distance
    ref_geom = shapely.union_all([projected(f.geometry, g.crs) for f in read_osm(MONACO, keys=["aeroway"])
                                  if f.tags["aeroway"] in ("helipad", "heliport")])
    rng = np.random.default_rng(7)
    rows, cols = rng.integers(0, g.ny, 600), rng.integers(0, g.nx, 600)
    ref = shapely.distance(shapely.points(g.x[cols], g.y[rows]), ref_geom)
    got = lc["landing_distance_m"].values[rows, cols]
    err = np.abs(got - ref)
    assert err.max() <= g.resolution_m / np.sqrt(2) + 1e-3, err.max()   # within one cell (bound r / sqrt 2)
    assert ref.max() > 200  # the window reaches far from the pad: the test is not trivial
    # the helipad cell itself is at distance 0 and the cost is distance / max distance
    x, y = g.from_lonlat(7.42483, 43.73776)
    r, c = g.index_of(x, y)
    assert lc["landing_distance_m"].values[r, c] == 0
    d = lc["landing_distance_m"].values
    np.testing.assert_allclose(lc["landing_cost"].values, d / d.max(), atol=1e-6)
    assert lc["landing_cost"].attrs["units"] == "1" and lc["landing_distance_m"].attrs["units"] == "m"
    assert lc.rio.crs == g.crs


def test_point_site_geojson_exact_bound_and_cost_integral(tmp_path):
    g = Grid(CRS.from_epsg(32635).to_wkt(), 385000.0, 6672000.0, 60, 40, 5.0)
    sx, sy = g.x[10] + 1.3, g.y[20] - 0.7                 # inside cell (20, 10), off-centre
    lon, lat = g.to_lonlat(sx, sy)
    sites = L.landing_sites(g, geojson=write_sites(tmp_path / "s.geojson", [shapely.Point(lon, lat)], ["pad"]))
    assert len(sites) == 1 and sites[0].name == "pad" and sites[0].kind == "scenario"
    assert int(sites.mask.sum()) == 1 and bool(sites.mask.values[20, 10])
    lc = L.landing_cost(g, sites)
    X, Y = np.meshgrid(g.x, g.y)
    exact = np.hypot(X - sx, Y - sy)
    assert np.abs(lc["landing_distance_m"].values - exact).max() <= g.resolution_m / np.sqrt(2) + 1e-3
    # EDT distance is to the site cell centre: exactly the cell-centre distance
    np.testing.assert_allclose(lc["landing_distance_m"].values, np.hypot(X - g.x[10], Y - g.y[20]), atol=1e-3)
    dmax = np.hypot(49 * 5.0, 20 * 5.0)                   # farthest cell centre: column 59, row 0 or 39
    assert float(lc["landing_cost"].attrs["distance_scale_m"]) == pytest.approx(dmax, abs=1e-3)
    # C_d along the row from the site cell centre 8 cells east, by hand:
    # half cell at 0 + cells k = 1..7 (beta = 5k / dmax, 5 m each) + half cell at k = 8
    hand = (sum(5.0 * k * 5.0 for k in range(1, 8)) + 0.5 * 5.0 * 8 * 5.0) / dmax
    got = R.integrate_along_path(lc["landing_cost"], [(g.x[10], g.y[20]), (g.x[18], g.y[20])])
    assert got == pytest.approx(hand, rel=1e-5)
    fixed = L.landing_cost(g, sites, max_distance_m=50.0)
    assert float(fixed["landing_cost"].max()) == 1.0
    assert float(fixed["landing_cost"].values[20, 15]) == pytest.approx(25.0 / 50.0, abs=1e-6)


def test_site_outside_grid_sets_edge_distance(tmp_path):
    g = Grid(CRS.from_epsg(32635).to_wkt(), 385000.0, 6672000.0, 20, 20, 5.0)
    sx, sy = g.x0 - 37.5, g.y[5]                           # 37.5 m west of the grid
    lon, lat = g.to_lonlat(sx, sy)
    sites = L.landing_sites(g, geojson=write_sites(tmp_path / "out.geojson", [shapely.Point(lon, lat)]))
    assert len(sites) == 1 and int(sites.mask.sum()) == 0
    d = L.landing_cost(g, sites)["landing_distance_m"].values
    X, Y = np.meshgrid(g.x, g.y)
    assert np.abs(d - np.hypot(X - sx, Y - sy)).max() <= 5.0 / np.sqrt(2) + 1e-3


def test_open_ground_min_area_matches_independent_selection():
    g = grid_around(24.9400, 60.1700, 24.9530, 60.1790, 4.0)
    sites = L.landing_sites(g, osm_path=HELSINKI, min_area_m2=400.0, margin_m=0.0)
    got = {s.source for s in sites if s.kind != "helipad"}
    rules = TABLE["landing"]["open_ground"]
    box = shapely.box(*g.bounds)
    want = set()
    n_small = 0
    for f in read_osm(HELSINKI):
        if f.kind != "area" or not any(f.tags.get(k) in v for k, v in rules.items()):
            continue
        pg = projected(f.geometry, g.crs)
        if not pg.intersects(box):
            continue
        if pg.area >= 400.0:
            want.add(f"osm:area/{f.osm_id}")
        else:
            n_small += 1
    assert got == want and len(want) >= 5 and n_small >= 1
    assert all(s.area_m2 >= 400.0 for s in sites)
    more = L.landing_sites(g, osm_path=HELSINKI, min_area_m2=0.0, margin_m=0.0)
    assert len(more) == len(sites) + n_small
    tab = sites.table()
    assert set(tab) == {"name", "kind", "source", "x", "y", "area_m2"} and len(tab["x"]) == len(sites)


def test_landing_errors(tmp_path):
    g = Grid(CRS.from_epsg(32635).to_wkt(), 385000.0, 6672000.0, 10, 10, 5.0)
    with pytest.raises(InputError, match="no landing-site source"):
        L.landing_sites(g)
    with pytest.raises(InputError, match="no landing sites: give data.landing_sites"):
        L.landing_cost(g, [])
    empty = tmp_path / "empty.geojson"
    empty.write_text(json.dumps({"type": "FeatureCollection", "features": []}))
    with pytest.raises(InputError, match="landing sites file .* has no features"):
        L.landing_sites(g, geojson=empty)
    line = write_sites(tmp_path / "line.geojson", [shapely.LineString([(24.9, 60.1), (24.91, 60.1)])])
    with pytest.raises(InputError, match="is a LineString; use one of Point"):
        L.landing_sites(g, geojson=line)
    with pytest.raises(InputError, match="min_area_m2 -5"):
        L.landing_sites(g, geojson=line, min_area_m2=-5)


def test_environment_dataset_and_figure(tmp_path):
    g = grid_around(24.9380, 60.1690, 24.9470, 60.1745, 4.0)
    cx, cy = g.x[g.nx // 2], g.y[g.ny // 2]
    sq = shapely.box(cx - 30, cy - 30, cx + 30, cy + 30)
    tf = Transformer.from_crs(g.crs, 4326, always_xy=True)
    zone = shapely.transform(sq, lambda xy: np.column_stack(tf.transform(xy[:, 0], xy[:, 1])))
    zpath = tmp_path / "zones.geojson"
    zpath.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"max_altitude_m": 50}, "geometry": shapely.geometry.mapping(zone)}]}))
    ds = E.environment_risk_dataset(g, osm_path=HELSINKI, nofly_zones=zpath, level5_nofly=True)
    for v in ("risk_level", "risk_cost", "nofly", "nofly_floor_m", "nofly_ceiling_m", "nofly_reason",
              "landing_site", "landing_distance_m", "landing_cost"):
        assert v in ds and ds[v].dims == ("y", "x") and "units" in ds[v].attrs, v
    assert ds.rio.crs == g.crs and ds.attrs["n_landing_sites"] == ds.sizes["site"] > 0
    lv = ds["risk_level"].values
    assert ds["nofly"].values[lv == 5].all() and np.isinf(ds["risk_cost"].values[lv == 5]).all()
    r, c = g.index_of(cx, cy)
    assert ds["nofly"].values[r, c] and (ds["nofly_reason"].values[r, c] & R.NOFLY_ZONE)
    assert ds["landing_distance_m"].values[ds["landing_site"].values].max() == 0
    fig = E.plot_environment(ds)
    ax_risk, ax_land = fig.axes[0], fig.axes[1]
    assert len(ax_risk.get_legend().get_texts()) == 6
    stars = [ln for ln in ax_land.get_lines() if ln.get_marker() == "*"]
    x0, x1 = ax_land.get_xlim()
    n_in = int(((ds["site_x"] >= x0) & (ds["site_x"] <= x1) & (ds["site_y"] >= ax_land.get_ylim()[0])
                & (ds["site_y"] <= ax_land.get_ylim()[1])).sum())
    assert len(stars) == 1 and len(stars[0].get_xdata()) == n_in > 0
    fig.savefig(tmp_path / "env.png", dpi=60)
    assert (tmp_path / "env.png").stat().st_size > 10_000
    with pytest.raises(InputError, match="pair of matplotlib axes"):
        E.plot_environment(ds, ax=ax_risk)
    import matplotlib.pyplot as plt

    plt.close("all")
