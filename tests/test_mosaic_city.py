"""The SYNTHETIC mosaic city generator (issue 23): a 0.5 km mosaic checked against an independent
reconstruction of its translated buildings (shapely, cell by cell), its determinism, its land use
and the nature statement in every file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
import shapely
from pyproj import Transformer

from skyroute.catalogs import generate_mosaic_city as M

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def mosaic(tmp_path_factory):
    out = tmp_path_factory.mktemp("mosaic")
    info = M.generate(out, side_km=0.5, seed=3, green_share=0.5)
    return out, info


def _dsm(path):
    with rasterio.open(path) as d:
        return d.read(1), d.transform, d.tags()


def _reference_buildings(info):
    """The translated buildings rebuilt from the source OSM file and mosaic.json alone: every
    building (read with pyosmium directly, height from its tags by the documented rule) whose
    representative point lies in a tile's source block, moved by the tile's offset."""
    import osmium

    from skyroute.stages.surface import osm_building_height

    wkb = osmium.geom.WKBFactory()
    t = Transformer.from_crs(4326, 32635, always_xy=True)
    src = []
    for obj in osmium.FileProcessor(str(M.SOURCE_PBF)).with_areas().with_locations():
        if obj.is_area() and ("building" in obj.tags or "building:part" in obj.tags):
            try:
                g = shapely.from_wkb(wkb.create_multipolygon(obj))
            except RuntimeError:
                continue
            g = shapely.transform(g, lambda xy: np.column_stack(t.transform(xy[:, 0], xy[:, 1])))
            src.append((g, osm_building_height(dict(obj.tags))[0]))
    tile = info["tile_m"]
    n_side = int(round(info["side_km"] * 1000 / tile))
    x0, y0 = info["bounds"][:2]
    out = []
    for k, (sx, sy) in enumerate(info["tile_source_sw_xy_m"]):
        tx, ty = x0 + (k % n_side) * tile, y0 + (k // n_side) * tile
        for g, h in src:
            p = g.point_on_surface()
            if sx <= p.x < sx + tile and sy <= p.y < sy + tile:
                out.append((shapely.affinity.translate(g, tx - sx, ty - sy), h))
    return out


def test_dsm_cells_are_the_highest_translated_building(mosaic):
    out, info = mosaic
    dsm, tr, tags = _dsm(out / "mosaic_dsm.tif")
    ground = info["ground_m"]
    ref = _reference_buildings(info)
    assert len(ref) == info["buildings"] > 20
    tree = shapely.STRtree([g for g, _ in ref])
    hs = np.array([h for _, h in ref])
    rng = np.random.default_rng(0)
    bld = np.argwhere(dsm > ground)
    assert len(bld) == info["building_cells"] > 1000
    cells = np.vstack([bld[rng.choice(len(bld), 300, replace=False)],
                       rng.integers(0, dsm.shape[0], (300, 2))])
    for r, c in cells:
        xa, yb = tr * (c, r)
        box = shapely.box(xa, yb - tr.a, xa + tr.a, yb)       # the cell's closed square
        hit = tree.query(box, predicate="intersects")
        want = ground + (hs[hit].max() if len(hit) else 0.0)
        assert dsm[r, c] == pytest.approx(want, abs=1e-4), (r, c)


def test_deterministic_for_a_seed_and_seeds_differ(mosaic, tmp_path):
    out, info = mosaic
    again = M.generate(tmp_path / "a", side_km=0.5, seed=3, green_share=0.5)
    other = M.generate(tmp_path / "b", side_km=0.5, seed=4, green_share=0.5)
    a0, _, _ = _dsm(out / "mosaic_dsm.tif")
    a1, _, _ = _dsm(tmp_path / "a" / "mosaic_dsm.tif")
    a2, _, _ = _dsm(tmp_path / "b" / "mosaic_dsm.tif")
    assert np.array_equal(a0, a1) and again["tile_source_sw_xy_m"] == info["tile_source_sw_xy_m"]
    assert (out / "mosaic_landuse.osm.pbf").read_bytes() == (tmp_path / "a" / "mosaic_landuse.osm.pbf").read_bytes()
    assert not np.array_equal(a0, a2) and other["tile_source_sw_xy_m"] != info["tile_source_sw_xy_m"]


def test_parks_open_ground_and_the_nature_statement(mosaic):
    from skyroute.pipeline.settings import load_scenario
    from skyroute.stages.landing import landing_sites
    from skyroute.stages.risk import risk_levels

    out, info = mosaic
    assert info["green_tiles"] >= 1
    sc = load_scenario(out / "mosaic-city.yaml")
    assert "SYNTHETIC mosaic of translated real Helsinki blocks" in sc.description
    assert sc.grid.nx == sc.grid.ny == 250
    lv = risk_levels(sc.grid, osm_path=out / "mosaic_landuse.osm.pbf").values
    assert (lv == 1).mean() > 0.05        # parks, grass, water: natural ground
    assert (lv == 3).mean() > 0.05        # the translated buildings
    assert len(landing_sites(sc.grid, osm_path=out / "mosaic_landuse.osm.pbf")) >= 1   # parks, pitches, grass
    for f in ("mosaic_dsm.tif", "mosaic_dem.tif"):
        assert "SYNTHETIC mosaic of translated real Helsinki blocks" in _dsm(out / f)[2]["NATURE"]
    import osmium

    r = osmium.io.Reader(str(out / "mosaic_landuse.osm.pbf"))
    assert "SYNTHETIC mosaic of translated real Helsinki blocks" in r.header().get("generator")
    r.close()
    from skyroute.stages.osm import read_osm

    feats = read_osm(out / "mosaic_landuse.osm.pbf")
    assert feats and all(f.tags["skyroute:nature"] == M.NATURE for f in feats)
    assert json.loads((out / "mosaic.json").read_text())["nature"] == M.NATURE


def test_shipped_benchmark_scenario_is_the_generated_one():
    shipped = (ROOT / "benchmarks" / "scenarios" / "mosaic-city-20km.yaml").read_text()
    assert shipped == M.scenario_yaml(20.0, 0, 2.0)
    assert "SYNTHETIC mosaic of translated real Helsinki blocks" in shipped


def test_bad_sizes_are_one_error_line(tmp_path, capsys):
    assert M.main([str(tmp_path / "x"), "--side-km", "0.3"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: --side-km 0.3 must be a whole number")


def test_small_mosaic_maps_and_the_chunked_clearance_equal_the_dsm_floor(mosaic, tmp_path):
    """The mosaic scenario through surface -> environment -> clearance: the DSM's pixels are the
    grid's cells, so the clearance stage takes the chunked floor of the surface; it must equal the
    DSM's own-prism floor (the path for any other DSM) exactly."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.runner import run_scenario
    from skyroute.pipeline.stages_builtin import _dsm_on_grid_lattice
    from skyroute.stages.clearance import dsm_obstacle_floor
    from skyroute.stages.grid import Grid
    from skyroute.stages.vehicle import load_vehicle

    out, info = mosaic
    res = run_scenario(str(out / "mosaic-city.yaml"), cache=Cache(tmp_path / "c"), targets=["clearance"])
    surf = res["surface"]
    grid = Grid.from_dataarray(surf["surface"])
    assert _dsm_on_grid_lattice((out / "mosaic_dsm.tif",), grid)
    dsm, _, _ = _dsm(out / "mosaic_dsm.tif")
    assert np.array_equal(surf["surface"].values, dsm)            # the aligned DSM copied cell by cell
    r = load_vehicle("dji-m300-rtk").r_p_m
    want = dsm_obstacle_floor(surf, out / "mosaic_dsm.tif", r, "fill-max", has_dem=True)
    cl = res["clearance"]
    assert np.array_equal(cl["obstacle_floor_m"].values, want)
    assert np.array_equal(cl["min_altitude_m"].values, np.maximum(want, surf["terrain"].values.astype(float)))
    assert (res["environment"]["risk_level"].values == 1).any()
    # a DSM off the lattice (half a cell) or reaching beyond the grid takes the DSM-floor path
    shifted = grid.__class__(grid.crs_wkt, grid.x0 + 1.0, grid.y1, grid.nx, grid.ny, grid.resolution_m)
    assert not _dsm_on_grid_lattice((out / "mosaic_dsm.tif",), shifted)
    smaller = grid.__class__(grid.crs_wkt, grid.x0 + 2.0, grid.y1, grid.nx - 1, grid.ny, grid.resolution_m)
    assert not _dsm_on_grid_lattice((out / "mosaic_dsm.tif",), smaller)


def test_maps_and_coverage_commands_stream_their_outputs(mosaic, tmp_path, monkeypatch):
    """``skyroute maps`` and ``skyroute coverage`` on the mosaic with small uneven chunks (64-cell blocks
    of a 250-cell grid) and a figure limit of 100 cells a side (so the figures use the reduced view
    city-scale maps get): the GeoTIFFs, written chunk by chunk, hold the cached layers exactly."""
    from click.testing import CliRunner

    import skyroute.pipeline.maps as maps
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.cli import main
    from skyroute.pipeline.runner import run_scenario

    out, _ = mosaic
    text = (out / "mosaic-city.yaml").read_text().replace("  resolution_m: 2\n", "  resolution_m: 2\n  chunk_cells: 64\n")
    text = text.replace("window_min: 20", "window_min: 2")   # 3 GNSS epochs: a fast coverage
    yml = out / "mosaic-city-chunked.yaml"
    yml.write_text(text)
    monkeypatch.setattr(maps, "DISPLAY_MAX_CELLS", 100)
    cache = tmp_path / "c"
    for cmd in ("maps", "coverage"):
        r = CliRunner().invoke(main, [cmd, str(yml), "--out", str(tmp_path / cmd), "--cache-dir", str(cache), "-q"])
        assert r.exit_code == 0, r.output
    res = run_scenario(str(yml), cache=Cache(cache), targets=["clearance", "coverage"])
    assert res["surface"]["surface"].chunks[0] == (64, 64, 64, 58)
    for stage, var in (("surface", "surface"), ("environment", "risk_level"), ("clearance", "min_altitude_m")):
        with rasterio.open(tmp_path / "maps" / f"{var}.tif") as d:
            assert np.array_equal(d.read(1), res[stage][var].values.astype(d.dtypes[0]))
    cov = res["coverage"]["coverage_floor"]
    with rasterio.open(tmp_path / "coverage" / f"coverage_PDOP_{cov['threshold'].values[-1]:g}.tif") as d:
        np.testing.assert_array_equal(d.read(1), cov.isel(threshold=-1).values.astype(np.float32))
    assert list((tmp_path / "maps").glob("*.png")) and list((tmp_path / "coverage").glob("*.png"))


def test_map_commands_are_estimated_without_the_planner(mosaic):
    """The up-front memory estimate of a request without the plan stage (maps, coverage) counts the
    chunked map stages (64 B per cell), not the planner's arrays: the 20 km city's maps pass the
    default limit of a 16 GB machine, its plan does not."""
    from skyroute.pipeline import budget
    from skyroute.pipeline.settings import load_scenario

    sc = load_scenario(mosaic[0] / "mosaic-city.yaml")
    full, maps = budget.scenario_footprint(sc), budget.scenario_footprint(sc, maps_only=True)
    assert maps.bytes_cells == sc.grid.nx * sc.grid.ny * budget.BYTES_PER_CELL_MAPS and maps.bytes_levels == 0
    k = 1e8 / maps.cells       # the same scenario at 20 km: 1e8 cells
    big = budget.BASE_BYTES + k * maps.bytes_cells + maps.bytes_epochs
    assert big < 0.8 * (16 << 30) < budget.BASE_BYTES + k * (full.bytes_cells + full.bytes_levels)


def test_bad_arguments_are_one_error_line(tmp_path, capsys):
    from skyroute.stages.base import InputError

    with pytest.raises(InputError, match=r"--seed -3 must be an integer in 0\.\.2\*\*32-1"):
        M.generate(tmp_path, side_km=0.5, seed=-3)
    with pytest.raises(InputError, match="must be positive"):
        M.generate(tmp_path, side_km=float("nan"))
    assert M.main([str(tmp_path / "o"), "--side-km", "0.5", "--seed", "-3"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --seed -3") and "Traceback" not in err
