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
