"""Environment stages through the pipeline and `skyroute maps` on real scenarios."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner

from skyroute.pipeline.cli import main
from skyroute.pipeline.runner import run_scenario
from skyroute.stages.traffic import TrafficOccupancy
from skyroute.stages.vehicle import load_vehicle
from skyroute.stages.wind import read_wind, wind_at_lonlat


@pytest.fixture(scope="module")
def helsinki_run(tmp_path_factory):
    from skyroute.pipeline.cache import Cache

    return run_scenario("helsinki-medical", cache=Cache(tmp_path_factory.mktemp("c")),
                        targets=["environment", "wind", "clearance", "traffic"])


def test_clearance_floor_keeps_the_vehicle_sphere_off_every_building(helsinki_run):
    surf = helsinki_run["surface"]["surface"].values
    cl = helsinki_run["clearance"].load()
    r_p = load_vehicle("dji-m300-rtk").r_p_m
    assert cl.attrs["radius_m"] == r_p == 5.0
    floor = cl["obstacle_floor_m"].values
    # directly above a surface cell the sphere centre must be r_p above it (closed form)
    assert np.all(floor >= surf + r_p - 1e-6)
    # and the AGL ceiling is terrain + 80 m
    np.testing.assert_allclose(cl["max_altitude_m"].values, helsinki_run["surface"]["terrain"].values + 80.0)


def test_wind_stage_equals_the_gfs_profile_at_a_cell(helsinki_run):
    from skyroute.pipeline.settings import catalog_dir

    w = helsinki_run["wind"].load()
    grid_x, grid_y = w["x"].values[3], w["y"].values[4]
    from pyproj import Transformer

    lon, lat = Transformer.from_crs(32635, 4326, always_xy=True).transform(grid_x, grid_y)
    gfs = read_wind(catalog_dir() / "data" / "gfs_2011-01-15T12_wind.nc", time=np.datetime64("2011-01-15T12:00"))
    prof = wind_at_lonlat(gfs, np.array([lon]), np.array([lat]), w["z"].values, np.array([0.0]), "levels")
    np.testing.assert_allclose(w["u"].values[:, 4, 3], np.ravel(prof["u"]), atol=1e-6)
    np.testing.assert_allclose(w["v"].values[:, 4, 3], np.ravel(prof["v"]), atol=1e-6)
    assert not bool(w["wind_nofly"].any())  # 10-15 m/s at Helsinki that day, below the 15 m/s limit


def test_traffic_stage_round_trips_and_blocks_the_crossing(helsinki_run):
    occ = TrafficOccupancy.from_dataset(helsinki_run["traffic"].load())
    # courier-1 flies x = 385400 + 8.75 (t - 50) along y = 6671900 at 35 m AGL (flat ground):
    # reserved at x = 385662.5 at t = 80 s, free there at t = 5 s and 10 m above its margin
    x, y = np.array([385662.5]), np.array([6671900.0])
    assert occ.occupied(x, y, np.array([35.0]), np.array([80.0]))[0]
    assert not occ.occupied(x, y, np.array([35.0]), np.array([5.0]))[0]
    assert not occ.occupied(x, y, np.array([35.0 + 2.0 + 5.0 + 0.5]), np.array([80.0]))[0]


def test_maps_command_writes_geotiffs_and_panel(tmp_path):
    res = CliRunner().invoke(main, ["maps", "--out", str(tmp_path / "m"), "--cache-dir", str(tmp_path / "c"), "-q"])
    assert res.exit_code == 0, res.output
    with rasterio.open(tmp_path / "m" / "risk_level.tif") as src:
        lv = src.read(1)
        assert src.crs.to_epsg() == 32635
    assert set(np.unique(lv)) <= {1, 2, 3, 4, 5, 6} and {1, 3, 4, 5} <= set(np.unique(lv))
    assert (tmp_path / "m" / "maps.png").stat().st_size > 50_000
