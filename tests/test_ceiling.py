"""Maximum-AGL ceilings hold at every point of a cell: relative to the LOWEST ground of the cell."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from skyroute.pipeline.errors import InputError
from skyroute.stages.grid import Grid
from skyroute.stages.planning.problem import build_problem
from skyroute.stages.planning.validate import validate_plan
from skyroute.stages.vehicle import load_vehicle

VEH = load_vehicle("dji-m300-rtk")


def _sloped(res=2.0):
    """A ramp rising 1 m per metre along x: each cell's ground spans [x0, x0 + res] m."""
    g = Grid.from_bounds("EPSG:32635", 0, 0, 200.0, 100.0, res)
    xs = np.broadcast_to(g.x, g.shape)
    hi = g.dataarray(xs + res / 2, "terrain", units="m")       # highest ground of the cell
    lo = g.dataarray(xs - res / 2, "terrain_min", units="m")   # lowest ground of the cell
    return g, xr.Dataset({"terrain": hi, "terrain_min": lo, "surface": hi})


def test_ceiling_is_max_agl_above_the_lowest_ground_of_the_cell():
    g, ds = _sloped()
    pr = build_problem(ds, np.zeros(g.shape), None, 0, 0, (0, 0, 0), VEH, (1, 0, 0, 0), (10, 50, 40),
                       (190, 50, 220), 0.0, 80.0)
    np.testing.assert_allclose(pr.ceiling_m, ds["terrain_min"].values + 80.0)
    # exact check at points inside cells: the ground under (x, y) is x; the highest allowed
    # altitude of the point's cell may not exceed x + 80 anywhere in the cell
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 200, 5000)
    y = rng.uniform(0, 100, 5000)
    r, c = g.index_of(x, y)
    assert np.all(pr.ceiling_m[r, c] <= x + 80.0 + 1e-9)
    # without terrain_min the old raster would allow up to 2 m too high
    pr_old = build_problem(ds.drop_vars("terrain_min"), np.zeros(g.shape), None, 0, 0, (0, 0, 0), VEH,
                           (1, 0, 0, 0), (10, 50, 40), (190, 50, 220), 0.0, 80.0)
    assert np.any(pr_old.ceiling_m[r, c] > x + 80.0 + 1.0)


def test_validator_checks_max_agl_against_the_lowest_ground():
    g, ds = _sloped()
    # hover 79 m above the cell's highest ground: 81 m above its lowest point
    x0 = 101.0
    r, c = g.index_of(x0, 50.0)
    z = float(ds["terrain"].values[r, c]) + 79.0
    t = np.array([0.0, 1.0])
    p = np.array([[x0, 50.0, z], [x0, 50.0, z]])
    kw = dict(grid=g, terrain_m=ds["terrain"].values, vehicle=VEH, min_agl_m=0.0, max_agl_m=80.0)
    assert not any("maximum altitude" in m for m in validate_plan((t, p), **kw))
    msgs = validate_plan((t, p), **kw, terrain_min_m=ds["terrain_min"].values)
    assert any("above the maximum altitude 80.0 m AGL (highest 81.00 m)" in m for m in msgs)


def test_cost_maps_must_be_non_negative():
    """risk_cost / landing_cost: NaN or a negative cell (also -inf) is refused, +inf risk is a
    no-fly cell (its cost becomes 0, its floor +inf)."""
    g, ds = _sloped()

    def build(risk, land):
        return build_problem(ds, np.zeros(g.shape), None, risk, land, (0, 0, 0), VEH, (1, 0, 0, 0), (10, 50, 40),
                             (190, 50, 220), 0.0, 80.0)

    for bad in (np.nan, -1e-9, -np.inf):
        for which in (0, 1):
            maps = [np.ones(g.shape), np.ones(g.shape)]
            maps[which][10, 20] = bad
            with pytest.raises(InputError, match="must be >= 0"):
                build(*maps)
    risk = np.ones(g.shape)
    risk[10, 20] = np.inf
    pr = build(risk, np.zeros(g.shape))
    assert pr.risk_cost[10, 20] == 0.0 and np.isinf(pr.floor_m[10, 20]) and pr.nofly[10, 20]
    assert np.isfinite(pr.floor_m[10, 21])
