"""The wind_bounds stage's energy-ratio tiles (issue 23, stages/planning/wind_bounds.py): over a
whole wind map the minimum over the tiles IS the bound computed directly (bit for bit); over a
window it is a lower bound of the window's own winds (a superset), and never below the whole
map's; tiles of another vehicle or lattice step are not used.  Synthetic wind
(tests/_city.py, procedural)."""

from __future__ import annotations

import numpy as np
import pytest
from _city import city_maps, city_problem, city_wind

from skyroute.stages.gridspec import Grid
from skyroute.stages.planning.grid_planner import make_lattice
from skyroute.stages.planning.heuristic import (
    ENERGY_LB_DENSE_SAFETY,
    energy_ratio_lb_dense_each,
    ratio_lb_over,
)
from skyroute.stages.planning.wind_bounds import lattice_dirs, tiles_fit, wind_ratio_tiles
from skyroute.stages.planning.window import crop_wind
from skyroute.stages.vehicle import load_vehicle

SIZE = (2400.0, 1600.0)


@pytest.fixture(scope="module")
def setup():
    maps = city_maps(SIZE, 4.0, seed=1)
    wind = city_wind(maps, 1, step_m=200.0)
    veh = load_vehicle("dji-m300-rtk")
    tiles = wind_ratio_tiles(wind, veh, 4.0, 8, tile_cols=3)
    return maps, wind, veh, tiles


def _direct(maps, wind, dirs):
    pr, _ = city_problem(SIZE, (0.1, 0.1), (0.9, 0.9), res_m=4.0, seed=1, wind=wind, maps=maps)
    return energy_ratio_lb_dense_each(pr, dirs)


def test_lattice_dirs_are_the_lattices(setup):
    """The stage's directions are those the A* heuristic bounds (make_lattice's step and levels)."""
    maps, wind, veh, tiles = setup
    pr, _ = city_problem(SIZE, (0.1, 0.1), (0.9, 0.9), res_m=4.0, seed=1, wind=wind, maps=maps)
    lat = make_lattice(pr, 8)
    from skyroute.stages.planning.grid_planner import lattice_edge_dirs

    np.testing.assert_array_equal(lattice_dirs(veh, 4.0, 8),
                                  lattice_edge_dirs(lat.step_m, lat.dz_m, veh.max_flight_path_angle_deg)[1])
    assert tiles["dirs"].shape == (24, 3)


def test_whole_map_tiles_equal_the_direct_bound(setup):
    maps, wind, veh, tiles = setup
    g = Grid.from_dataarray(wind)
    dirs = tiles["dirs"].values
    got = ratio_lb_over(tiles, g.bounds, dirs) * ENERGY_LB_DENSE_SAFETY
    np.testing.assert_array_equal(got, _direct(maps, wind, dirs))
    assert np.isfinite(got).all() and (got > 0).all()


def test_window_tiles_bound_the_windows_winds_from_below(setup):
    maps, wind, veh, tiles = setup
    g = Grid.from_dataarray(wind)
    dirs = tiles["dirs"].values
    whole = ratio_lb_over(tiles, g.bounds, dirs)
    rng = np.random.default_rng(4)
    for _ in range(6):
        x0, y0 = rng.uniform(g.x0, g.x0 + 1600), rng.uniform(g.y1 - 1500, g.y1 - 700)
        box = (x0, y0, x0 + rng.uniform(50, 700), y0 + rng.uniform(50, 600))
        cw = crop_wind(wind, box)
        own = _direct(maps, cw, dirs) / ENERGY_LB_DENSE_SAFETY          # the window's own winds
        t = ratio_lb_over(tiles, Grid.from_dataarray(cw).bounds, dirs)
        assert (t <= own).all() and (t >= whole).all()


def test_tiles_fit_only_their_vehicle_and_step(setup):
    _, _, veh, tiles = setup
    assert tiles_fit(tiles, veh, 8)
    assert not tiles_fit(tiles, veh, 4)
    assert not tiles_fit(tiles, load_vehicle("dji-flycart-30"), 8)
    assert not tiles_fit(None, veh, 8)
    assert ratio_lb_over(tiles, (0, 0, 1, 1), tiles["dirs"].values) is None           # no tile there
    assert ratio_lb_over(tiles, Grid.from_dataarray(setup[1]).bounds, tiles["dirs"].values[:5]) is None


def test_a_reweighted_problem_keeps_the_tiles_and_its_bounds(setup, monkeypatch):
    """STEP I's re-plans with a larger w_l (``with_weights``) keep the weight-free memos: the
    tiles' bound, not the dense pass over the window's winds (7 s per refused 15 km city
    mission before), and the same numbers as a fresh problem of those weights given the tiles."""
    import skyroute.stages.planning.heuristic as heuristic

    maps, wind, veh, tiles = setup
    pr, _ = city_problem(SIZE, (0.1, 0.1), (0.9, 0.9), res_m=4.0, seed=1, wind=wind, maps=maps)
    object.__setattr__(pr, "_ratio_tiles", tiles)
    dirs = tiles["dirs"].values
    p2 = pr.with_weights((2.0, 1.0, 1.0, 1.0))
    assert p2.weights == (2.0, 1.0, 1.0, 1.0) and pr.weights != p2.weights
    assert p2.__dict__["_ratio_tiles"] is tiles
    fresh, _ = city_problem(SIZE, (0.1, 0.1), (0.9, 0.9), res_m=4.0, seed=1, wind=wind, maps=maps)
    fresh = fresh.with_weights((2.0, 1.0, 1.0, 1.0))
    object.__setattr__(fresh, "_ratio_tiles", tiles)
    monkeypatch.setattr(heuristic, "ratio_each_kernel",
                        lambda *a: pytest.fail("the dense pass over the winds ran: the tiles were lost"))
    np.testing.assert_array_equal(energy_ratio_lb_dense_each(p2, dirs), energy_ratio_lb_dense_each(fresh, dirs))
    assert heuristic.cost_rate_lb(p2) == heuristic.cost_rate_lb(fresh)
