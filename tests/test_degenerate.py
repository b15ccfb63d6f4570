"""Degenerate cost terms (issue 8 part 4) and the rotterdam-canyon landing sites.

A term is degenerate when its cost per metre is the same for every cell, altitude and heading;
the premise is checked against the planner's own exact segment costs (build_problem), the
detection against maps built by the real environment stage, the refusal at the function, stage
and command level.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import xarray as xr
from click.testing import CliRunner
from pyproj import Transformer

from skyroute.pipeline.cli import main
from skyroute.pipeline.errors import DegenerateCostError, InputError
from skyroute.pipeline.settings import catalog_dir, load_scenario
from skyroute.stages.environment import environment_risk_dataset
from skyroute.stages.grid import Grid
from skyroute.stages.planning.degenerate import check_cost_terms, degenerate_cost_terms
from skyroute.stages.planning.problem import build_problem
from skyroute.stages.planning.strategic import plan_levels, plan_to_dataset

DATA = catalog_dir() / "data"


def _grid() -> Grid:
    return Grid.from_bounds("EPSG:32635", 384000, 6670000, 384200, 6670100, 2.0)


def _bare_environment(grid: Grid, **kw) -> xr.Dataset:
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="no landing sites")
        return environment_risk_dataset(grid, **kw)


def _point_geojson(path, lon_lat) -> str:
    path.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"name": "pad"}, "geometry": {"type": "Point", "coordinates": lon_lat}}]}))
    return str(path)


@pytest.fixture(scope="module")
def bare():
    g = _grid()
    return g, _bare_environment(g)


# ------------------------------------------------------------------ the premise, by the planner's costs
def test_degenerate_maps_give_costs_proportional_to_length(bare):
    """With the maps of a scenario without land use, landing sites or wind, the planner's exact
    segment costs are C_r = 0, C_d = C_l, C_e = C_l for random segments in every direction;
    with a uniform non-zero wind C_e / C_l depends on the heading (not degenerate)."""
    g, env = bare
    t = g.dataarray(np.zeros(g.shape), "terrain", units="m")
    surf = xr.Dataset({"terrain": t, "surface": t})
    rng = np.random.default_rng(8)
    p0 = np.column_stack([rng.uniform(384005, 384195, 200), rng.uniform(6670005, 6670095, 200),
                          rng.uniform(10, 60, 200)])
    p1 = np.column_stack([rng.uniform(384005, 384195, 200), rng.uniform(6670005, 6670095, 200),
                          p0[:, 2] + rng.uniform(-2, 2, 200)])
    args = (np.zeros(g.shape), None, env["risk_cost"], env["landing_cost"])
    tail = ("dji-m300-rtk", (1, 1, 1, 1), tuple(p0[0]), tuple(p1[0]), 0.0, 80.0)
    d = build_problem(surf, *args, None, *tail).segment_details(p0, p1)
    L = np.linalg.norm(p1 - p0, axis=1)
    np.testing.assert_allclose(d["length_m"], L, rtol=1e-12)
    np.testing.assert_array_equal(d["risk_m"], 0.0)
    np.testing.assert_allclose(d["landing_m"], L, rtol=1e-12)
    np.testing.assert_allclose(d["energy_cost_m"], L, rtol=1e-12)
    windy = build_problem(surf, *args, (4.0, 0.0, 0.0), *tail).segment_details(p0, p1)
    ratio = windy["energy_cost_m"] / L
    assert ratio.max() - ratio.min() > 0.05
    assert set(degenerate_cost_terms(env)) == {"C_r", "C_d", "C_e"}
    assert set(degenerate_cost_terms(env, (4.0, 0.0, 0.0))) == {"C_r", "C_d"}


# ------------------------------------------------------------------ detection
def test_detection_on_the_environment_stage_maps(bare, tmp_path):
    g, env = bare
    deg = degenerate_cost_terms(env)
    assert "no land use" in deg["C_r"] and "level 4" in deg["C_r"] and "risk cost 0 " in deg["C_r"]
    assert "no landing sites" in deg["C_d"] and "landing cost 1 " in deg["C_d"]
    assert deg["C_e"].startswith("there is no wind")
    # one landing pad in the AOI: the landing distance varies, C_d is meaningful
    lon, lat = Transformer.from_crs(g.crs, 4326, always_xy=True).transform(384050.0, 6670050.0)
    pad = _bare_environment(g, landing_geojson=_point_geojson(tmp_path / "pad.geojson", [lon, lat]))
    assert pad["landing_cost"].values.max() > pad["landing_cost"].values.min()
    assert "C_d" not in degenerate_cost_terms(pad) and "C_r" in degenerate_cost_terms(pad)
    # rural default level 1: uniform too (san-gabriel-mountains)
    assert "level 1" in degenerate_cost_terms(_bare_environment(g, default_level=1))["C_r"]


def test_detection_ignores_nofly_cells_and_uses_the_tolerance(bare):
    g, env = bare
    risk = np.zeros(g.shape, np.float64)
    risk[:5, :5] = np.inf                  # level-6 cells: no-fly, not part of the flyable map
    nofly = np.isinf(risk)
    land = np.full(g.shape, 0.5)
    land[0, 0] = 0.9                       # differs only on a no-fly cell
    ds = xr.Dataset({"risk_cost": (("y", "x"), risk), "landing_cost": (("y", "x"), land),
                     "nofly": (("y", "x"), nofly)})
    assert set(degenerate_cost_terms(ds, (0.0, 0.0, 0.0))) == {"C_r", "C_d", "C_e"}
    ds["risk_cost"][10, 10] = 1e-13        # within 1e-12: still uniform
    ds["landing_cost"][10, 10] = 0.5 + 1e-9  # beyond: varies
    assert set(degenerate_cost_terms(ds, (0.0, 0.0, 0.0))) == {"C_r", "C_e"}
    # a no-fly zone limited to 30..60 m above ground stays flyable below and above: its cells count
    land = np.where(nofly & (np.arange(g.nx) == 0), 0.9, 0.5)   # differs only on no-fly cells
    zone = xr.Dataset({"risk_cost": (("y", "x"), np.zeros(g.shape)), "landing_cost": (("y", "x"), land),
                       "nofly": (("y", "x"), nofly), "nofly_floor_m": (("y", "x"), np.where(nofly, 30.0, np.nan)),
                       "nofly_ceiling_m": (("y", "x"), np.where(nofly, 60.0, np.nan))})
    assert "C_d" not in degenerate_cost_terms(zone)
    zone["nofly_floor_m"][:] = np.where(nofly, 0.0, np.nan)
    zone["nofly_ceiling_m"][:] = np.where(nofly, np.inf, np.nan)
    assert "C_d" in degenerate_cost_terms(zone)
    # wind maps: zero everywhere is degenerate, any non-zero component is not
    z = xr.Dataset({k: (("z", "y", "x"), np.zeros((2, 3, 4))) for k in "uvw"})
    assert "zero everywhere" in degenerate_cost_terms(env, z)["C_e"]
    z["w"][1, 2, 3] = 0.3
    assert "C_e" not in degenerate_cost_terms(env, z)
    assert degenerate_cost_terms(None)["C_r"].startswith("there is no risk map")


# ------------------------------------------------------------------ weights
def test_weights_on_degenerate_terms_only_are_an_error(bare):
    _, env = bare
    deg = degenerate_cost_terms(env, (3.0, 0.0, 0.0))   # C_r, C_d degenerate; C_e meaningful
    with pytest.raises(DegenerateCostError, match=r"select only the risk term, but the risk map is uniform "
                       r"\(no land use.*add data\.landuse .*, or set w_l/w_e$"):
        check_cost_terms((0, 1, 0, 0), deg)
    with pytest.raises(DegenerateCostError, match=r"select only the risk and landing terms, .*there are no "
                       r"landing sites.*add data\.landuse .* and data\.landing_sites"):
        check_cost_terms((0, 2, 0.5, 0), deg)
    with pytest.raises(DegenerateCostError, match=r"select only the energy term, but there is no wind.*"
                       r"add data\.wind .*, or set w_l$"):
        check_cost_terms((0, 0, 0, 1), degenerate_cost_terms(env))
    with pytest.raises(InputError, match="weights are all zero"):   # the existing check comes first
        check_cost_terms((0, 0, 0, 0), deg)
    # a meaningful term among the weighted ones: warnings only, one per degenerate WEIGHTED term
    # (C_d is degenerate too but weighted 0: it does not enter f, no warning; issue 25)
    w = check_cost_terms((0, 1, 0, 1), deg)
    assert len(w) == 1 and w[0].startswith("plan: the risk cost C_r (w_r = 1) carries no information")
    w = check_cost_terms((1, 1, 0.5, 0), deg)
    assert len(w) == 2 and "landing cost C_d (w_d = 0.5)" in w[1] and "add data.landing_sites" in w[1]
    assert check_cost_terms((1, 0, 0, 0), deg) == []
    assert check_cost_terms((1, 0, 0, 0), {}) == []


def _plan_inputs():
    g = Grid.from_bounds("EPSG:32635", 0, 0, 200, 100, 4.0)
    t = g.dataarray(np.zeros(g.shape), "terrain", units="m")
    clearance = xr.Dataset({"min_altitude_m": g.dataarray(np.zeros(g.shape), "min_altitude_m", units="m")})
    return g, xr.Dataset({"terrain": t, "surface": t}), clearance


def _plan(surface, env, clearance, weights, **kw):
    return plan_levels(surface, env, None, clearance, None, None, None, start_xy=(10, 50), start_agl_m=20.0,
                          goal_xy=(190, 50), goal_agl_m=20.0, start_time_utc="2020-01-03T10:00:00Z",
                          planner="astar", weights=weights, min_agl_m=0.0, max_agl_m=80.0, step_cells=4, **kw)


def test_plan_strategic_refuses_before_planning_and_warns(monkeypatch):
    g, surface, clearance = _plan_inputs()
    env = _bare_environment(g)
    import skyroute.stages.planning.strategic as strategic

    def no_planning(*a, **k):
        raise AssertionError("build_problem called: the refusal must come before any planning")

    with monkeypatch.context() as m:
        m.setattr(strategic, "build_problem", no_planning)
        with pytest.raises(DegenerateCostError, match="select only the landing term, but there are no landing sites"):
            _plan(surface, env, clearance, (0, 0, 1, 0))
    plan = _plan(surface, env, clearance, (1, 1, 1, 1))
    assert [w.split(" carries")[0] for w in plan.warnings] == [
        "plan: the risk cost C_r (w_r = 1)", "plan: the landing cost C_d (w_d = 1)",
        "plan: the energy cost C_e (w_e = 1)"]
    ds = plan_to_dataset(plan, g.crs, "flat local ground", "2020-01-03T10:00:00Z")
    assert json.loads(ds.attrs["warnings"]) == plan.warnings
    # and the candidate costs say the same: C_r = 0, C_d = C_l, C_e = C_l
    c = plan.candidates[0]
    assert c.C_l > 0 and c.C_r == 0 and c.C_d == pytest.approx(c.C_l, rel=1e-9)
    assert c.C_e == pytest.approx(c.C_l, rel=1e-9)


# ------------------------------------------------------------------ command line
_YAML = """name: flat-nothing
description: flat ground, no land use, no landing sites, no wind
aoi: {{crs: "EPSG:32635", bounds: [384000, 6670000, 384400, 6670300], resolution_m: 5.0}}
mission:
  start: {{x: 384050, y: 6670150, alt_agl_m: 30}}
  goal: {{x: 384350, y: 6670150, alt_agl_m: 30}}
  start_time_utc: 2020-01-03T12:00:00Z
vehicle: dji-m300-rtk
planner: {{name: astar, weights: [{w}]}}
"""


@pytest.mark.parametrize("command", ["plan", "run"])
def test_cli_refuses_degenerate_weights_before_the_long_stages(tmp_path, command):
    yml = tmp_path / "flat.yaml"
    yml.write_text(_YAML.format(w="1, 1, 1, 1"))
    args = [command, str(yml), "--out", str(tmp_path / "o"), "--cache-dir", str(tmp_path / "c"), "-q"]
    if command == "plan":
        args += ["--weights", "0,1,0,0"]
    else:
        yml.write_text(_YAML.format(w="0, 1, 0, 0"))
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 2, r.output
    line = [x for x in r.output.splitlines() if x.startswith("error:")]
    assert len(line) == 1 and "select only the risk term, but the risk map is uniform (no land use" in line[0]
    assert line[0].endswith("add data.landuse (an OSM extract with land use) or CityJSON data.buildings, or set w_l")
    # refused right after the environment stage: clearance and plan never ran
    ran = {p.name.split("-")[0] for p in (tmp_path / "c" / "stages").iterdir()}
    assert "environment" in ran and ran <= {"surface", "environment"}


# ------------------------------------------------------------------ rotterdam-canyon landing sites
def test_rotterdam_landing_sites_are_flat_clear_roofs():
    """The shipped sites (catalogs/data/rotterdam/landing_sites.geojson) on the surface skyroute
    rasterises from the same LoD2 file, in a 250 m window: every cell whose centre is in a site
    is at the site's roof height, and no cell whose footprint lies within the 10 m touch-down
    disc of that cell rises above it; the landing cost is no longer uniform."""
    from scipy.ndimage import maximum_filter

    from skyroute.stages.surface import build_surface

    sc = load_scenario("rotterdam-canyon")
    assert sc.data.landing_sites is not None and sc.data.landing_sites.name == "landing_sites.geojson"
    g = Grid.from_bounds("EPSG:28992", 90950, 435500, 91200, 435750, 1.0)
    surf = build_surface(g, buildings_path=DATA / "rotterdam_delfshaven_lod2.city.json",
                         buildings_format="cityjson")["surface"].values
    doc = json.loads(sc.data.landing_sites.read_text())
    to_rd = Transformer.from_crs(4326, 28992, always_xy=True)
    X, Y = np.meshgrid(g.x, g.y)
    import shapely

    r_in = 5.0 - np.sqrt(0.5)                    # cells entirely inside a 5 m disc around a cell centre
    k = int(np.ceil(r_in))
    oy, ox = np.mgrid[-k:k + 1, -k:k + 1]
    disc_max = maximum_filter(surf, footprint=np.hypot(ox, oy) <= r_in, mode="nearest")
    n_cells = 0
    for f in doc["features"]:
        geom = shapely.transform(shapely.geometry.shape(f["geometry"]),
                                 lambda xy: np.column_stack(to_rd.transform(xy[:, 0], xy[:, 1])))
        inside = shapely.contains_xy(geom, X, Y)
        if not inside.any():
            continue
        z = f["properties"]["roof_height_m"]
        n_cells += int(inside.sum())
        assert np.abs(surf[inside] - z).max() <= 0.5, f["properties"]["name"]
        assert disc_max[inside].max() <= z + 0.5, f["properties"]["name"]
    assert n_cells > 500
    env = environment_risk_dataset(g, landing_geojson=sc.data.landing_sites, osm_landing_sites=False)
    assert env.attrs["n_landing_sites"] > 50
    assert "C_d" not in degenerate_cost_terms(env, (6.0, 0.0, 0.0))
    d = env["landing_distance_m"].values
    assert d.min() == 0 and d.max() > 30
