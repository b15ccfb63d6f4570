"""A user's own city, first try (issue 24): the grid never leaves aoi.bounds, NoData regions
touching a lidar tile's edge are filled conservatively, DEMs are read as the surface through
their samples.  Every conservative claim is checked against a truth built finer than the grid,
at points inside cells."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
import rasterio.windows
from affine import Affine

from skyroute.pipeline.errors import DataError, InputError
from skyroute.pipeline.settings import load_scenario, parse_scenario
from skyroute.stages.grid import Grid
from skyroute.stages.surface import build_surface


def _write(path, z, transform, crs, nodata=-9999.0, tags=None):
    z = np.where(np.isnan(z), nodata, z).astype(np.float32)
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype="float32",
                       crs=crs, transform=transform, nodata=nodata) as dst:
        if tags:
            dst.update_tags(**tags)
        dst.write(z, 1)
    return path


def _footprint_max(z, T, grid):
    """Independent: the max of every source pixel overlapping each cell by > 1e-6 m (same CRS)."""
    out = np.full(grid.shape, -np.inf)
    xl = T.c + np.arange(z.shape[1]) * T.a
    yt = T.f + np.arange(z.shape[0]) * T.e
    r = grid.resolution_m
    for i in range(grid.ny):
        rows = (yt > grid.y1 - (i + 1) * r + 1e-6) & (yt + T.e < grid.y1 - i * r - 1e-6)
        for j in range(grid.nx):
            cols = (xl + T.a > grid.x0 + j * r + 1e-6) & (xl < grid.x0 + (j + 1) * r - 1e-6)
            out[i, j] = z[np.ix_(rows, cols)].max()
    return out


# ----------------------------------------------------------------------------- 1. aoi.bounds
def _scenario(aoi_bounds, res, dsm, tmp_path, nodata="fill-max"):
    return parse_scenario({
        "name": "own-dsm", "aoi": {"crs": "EPSG:32631", "bounds": list(aoi_bounds), "resolution_m": res},
        "data": {"surface": {"path": str(dsm), "vertical_datum": "NAP", "nodata": nodata}},
        "mission": {"start": {"x": aoi_bounds[0] + 5, "y": aoi_bounds[1] + 5, "alt_agl_m": 20},
                    "goal": {"x": aoi_bounds[2] - 5, "y": aoi_bounds[3] - 5, "alt_agl_m": 20},
                    "start_time_utc": "2020-01-03T10:00:00Z"}}, base=tmp_path)


def test_the_grid_never_extends_past_aoi_bounds(tmp_path):
    """Bounds 552608..553527 (919 m) at 2 m inside a DSM whose extent ends 0.5 m past them: the
    grid snaps inward (918 m) and the surface is built, >= the DSM over every cell."""
    T = Affine(0.5, 0.0, 552600.0, 0.0, -0.5, 5800100.0)
    rng = np.random.default_rng(4)
    z = rng.uniform(0, 3, (200, 1855))                      # extent x 552600 .. 553527.5
    z[80:120, 400:460] = 25.0
    dsm = _write(tmp_path / "dsm.tif", z, T, "EPSG:32631")
    sc = _scenario((552608, 5800010, 553527, 5800090), 2.0, dsm, tmp_path)
    g = sc.grid
    assert g.bounds == (552608.0, 5800010.0, 553526.0, 5800090.0)
    ds = build_surface(g, surface_path=dsm, surface_datum="NAP")
    assert np.array_equal(ds["surface"].values, _footprint_max(z, T, g).astype(np.float32))
    # the grid the old outward snapping made reached 1 m past the bounds and off the raster
    with pytest.raises(DataError, match=r"set aoi.bounds to \[552608, 5800010, 553526, 5800090\]"):
        build_surface(Grid.from_bounds("EPSG:32631", 552608, 5800010, 553527, 5800090, 2.0), surface_path=dsm,
                      surface_datum="NAP")
    # random bounds: inside them, and no whole lattice cell of them left out
    for _ in range(200):
        x0, y0 = rng.uniform(-1e4, 1e4, 2)
        r = float(rng.choice([0.5, 1.0, 2.0, 3.0]))
        w, h = rng.uniform(2 * r, 50, 2)
        gi = Grid.from_bounds("EPSG:32631", x0, y0, x0 + w, y0 + h, r, inward=True)
        b = gi.bounds
        assert b[0] >= x0 - 1e-6 and b[1] >= y0 - 1e-6 and b[2] <= x0 + w + 1e-6 and b[3] <= y0 + h + 1e-6
        assert b[0] - x0 < r and (x0 + w) - b[2] < r and b[1] - y0 < r and (y0 + h) - b[3] < r
    with pytest.raises(InputError, match=r"aoi.bounds .* holds no whole 2 m cell.* widen aoi.bounds or lower "
                       r"aoi.resolution_m"):
        Grid.from_bounds("EPSG:32631", 10.5, 10.5, 11.9, 30, 2.0, inward=True)


# ------------------------------------------------------------------ 2. lidar tile, NoData at edges
def _lidar_truth():
    """A 0.5 m lidar tile (100 m x 80 m) of a waterfront: ground 1-2 m, a canal at -0.4 m along
    the west and south edges (NoData: water returns nothing), a building at the north edge with a
    glass roof part at its roof height (NoData), an interior glass roof and a 30 m mast."""
    ny, nx = 160, 200
    ii, jj = np.mgrid[0:ny, 0:nx]
    z = 1.0 + 0.005 * jj + 0.002 * ii
    z[130:, :] = -0.4                       # canal along the south edge ...
    z[:, :25] = -0.4                        # ... and the west edge: one region touching two edges
    z[0:40, 90:150] = 14.0                  # building on the north edge
    z[60:80, 120:140] = 9.0                 # building inside
    z[100, 60] = 30.0                       # mast
    holes = np.zeros_like(z, bool)
    holes[132:, 10:] = True                 # water: the canal, minus a few quay pixels at its rim
    holes[:, :23] = True
    holes[134:, :23] = True
    holes[0:12, 100:130] = True             # glass roof part touching the north edge (true height 14 m)
    holes[65:72, 125:133] = True            # glass roof inside (true height 9 m)
    return z, holes


def test_lidar_nodata_touching_two_edges_is_filled_above_the_truth(tmp_path):
    z, holes = _lidar_truth()
    T = Affine(0.5, 0.0, 85000.0, 0.0, -0.5, 446080.0)
    tile = _write(tmp_path / "ahn_tile.tif", np.where(holes, np.nan, z), T, "EPSG:28992")
    for res, bounds in ((1.0, (85000, 446000, 85100, 446080)), (2.0, (85003.3, 446001.1, 85097.9, 446079.2))):
        grid = Grid.from_bounds("EPSG:28992", *bounds, res, inward=True)
        ds = build_surface(grid, surface_path=tile, surface_datum="NAP")
        s = ds["surface"].values.astype(float)
        assert np.all(s >= _footprint_max(z, T, grid) - 1e-5)         # the truth, every point of each cell
        assert float(s.max()) == 30.0
        warns = json.loads(ds.attrs["warnings"])
        w = next(w for w in warns if "NoData region" in w)
        share = (_footprint_max(holes.astype(float), T, grid) > 0).mean()
        assert f"cover {100 * share:.2f} % of the AOI's cells" in w
        assert "3 NoData region(s) of the DSM (2 touching its edge)" in w
        assert "data.surface.nodata: fill-max; the other choices: fill-nearest, error" in w
    # fill-nearest: filled too, named in the warning
    ds = build_surface(grid, surface_path=tile, surface_datum="NAP", surface_nodata="fill-nearest")
    assert np.isfinite(ds["surface"].values).all()
    assert any("nearest valid pixel" in w for w in json.loads(ds.attrs["warnings"]))
    # only the AOI part outside the raster is refused, naming the bounds that fit
    with pytest.raises(DataError, match=r"covers only .* outside the raster's extent; set aoi.bounds to "
                       r"\[85000, 446000, 85100, 446080\]"):
        build_surface(Grid.from_bounds("EPSG:28992", 84990, 446000, 85100, 446080, 2.0), surface_path=tile,
                      surface_datum="NAP")


# ------------------------------------------------------------------ 4. DEM samples and their patches
def _ridge_posts():
    """20 x 20 posts at 30 m: a valley whose ridge crosses between the posts (its crest posts
    alternate sides, so every lattice square on it has one high corner)."""
    ii, jj = np.mgrid[0:20, 0:20].astype(float)
    v = 500.0 + 3.0 * ii + 2.0 * jj
    crest = (ii + jj) % 4 == 0
    v[crest & (np.abs(ii - jj) < 6)] += 120.0
    return v


def _bilinear(v, cx, cy, spacing, x, y, diag=None):
    """The surface through posts ``v`` (post (i, j) at (cx + j s, cy - i s)) at points (x, y):
    bilinear, or with ``diag`` one of the two triangulations of each lattice square."""
    u = (np.asarray(x) - cx) / spacing
    w = (cy - np.asarray(y)) / spacing
    j = np.clip(np.floor(u).astype(int), 0, v.shape[1] - 2)
    i = np.clip(np.floor(w).astype(int), 0, v.shape[0] - 2)
    fu, fw = np.clip(u - j, 0, 1), np.clip(w - i, 0, 1)
    a, b, c, d = v[i, j], v[i, j + 1], v[i + 1, j], v[i + 1, j + 1]
    if diag is None:
        return a * (1 - fu) * (1 - fw) + b * fu * (1 - fw) + c * (1 - fu) * fw + d * fu * fw
    if diag == "main":   # split along (0,0)-(1,1)
        return np.where(fu >= fw, a + (b - a) * fu + (d - b) * fw, a + (c - a) * fw + (d - c) * fu)
    return np.where(fu + fw <= 1, a + (b - a) * fu + (c - a) * fw, d + (c - d) * (1 - fu) + (b - d) * (1 - fw))


def _points_in_cells(grid, k, rng):
    r = grid.resolution_m
    ii, jj = np.mgrid[0:grid.ny, 0:grid.nx]
    pts = []
    for fx, fy in [(0, 0), (1, 0), (0, 1), (1, 1), (0.5, 0.5)] + [tuple(rng.uniform(0, 1, 2)) for _ in range(k)]:
        pts.append((ii, jj, grid.x0 + (jj + fx) * r, grid.y1 - (ii + fy) * r))
    return pts


@pytest.mark.parametrize("shift", [(0.0, 0.0), (0.5, 0.0), (0.5, 0.5)])
def test_point_sampled_dem_with_a_ridge_between_posts_is_read_conservatively(tmp_path, shift):
    """The terrain of every cell is >= any surface through the samples (bilinear, both
    triangulations) at points inside the cell, terrain_min <= it; the same DEM georeferenced half
    a spacing differently (and read with GDAL's PixelIsPoint shift ignored) holds as well; the
    flat-square reading does not."""
    v = _ridge_posts()
    s = 30.0
    T = Affine(s, 0.0, 380000.0 + shift[0] * s, 0.0, -s, 3795000.0 - shift[1] * s)
    path = _write(tmp_path / "dem.tif", v, T, "EPSG:32611", tags={"AREA_OR_POINT": "Point"})
    rng = np.random.default_rng(7)
    cases = [({}, 0.5), ({"GTIFF_POINT_GEO_IGNORE": True}, 0.0)]
    flat_below = 0
    for env, off in cases:
        with rasterio.Env(**env):
            with rasterio.open(path) as src:
                Tr = src.transform
            cx, cy = Tr.c + off * s, Tr.f - off * s      # post (0, 0) where GDAL puts the sample
            for res, pad in ((10.0, 61.3), (45.0, 47.0)):
                grid = Grid.from_bounds("EPSG:32611", Tr.c + pad, Tr.f - 600 + 40, Tr.c + 600 - 40, Tr.f - pad, res)
                ds = build_surface(grid, terrain_path=path, vertical_datum="EGM96 geoid")
                hi, lo = ds["terrain"].values.astype(float), ds["terrain_min"].values.astype(float)
                for ii, jj, x, y in _points_in_cells(grid, 12, rng):
                    for diag in (None, "main", "anti"):
                        truth = _bilinear(v, cx, cy, s, x, y, diag)
                        assert np.all(hi[ii, jj] >= truth - 1e-4), (env, res, diag)
                        assert np.all(lo[ii, jj] <= truth + 1e-4), (env, res, diag)
                    flat = _footprint_max(v, Tr, grid)
                    flat_below += int((flat[ii, jj] < _bilinear(v, cx, cy, s, x, y) - 1.0).sum())
                assert ("pixel corners" in ds.attrs["ground_source"]) == (off == 0.0)
    assert flat_below > 0     # the footprint (flat square) reading is below the surface somewhere


# ------------------------------------------------------------------ 3. CityJSON LoD2 with BuildingParts
def _stacked_city(tmp_path, with_tin: bool, offset=(0.0, 0.0), name=None):
    """A Building with a part on the ground (GroundSurface 3.5 m, roof 13.6 m) and a part standing
    on it (GroundSurface 13.6 m, gable roof up to 21 m), on a sloped TINRelief (3.1-4.4 m), in
    EPSG:28992 -- the Den Haag case."""
    from tests.test_surface_conservative import _cityjson_doc, _gable_house

    xs = np.array([-4.1, 13.3, 28.9, 46.0])
    X, Y = np.meshgrid(xs, xs + 0.7)
    Z = 3.1 + 0.02 * X + 0.01 * Y
    tin_v = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    tris = []
    for i in range(3):
        for j in range(3):
            a, b, c, d = i * 4 + j, i * 4 + j + 1, (i + 1) * 4 + j + 1, (i + 1) * 4 + j
            tris += [[[a, b, c]], [[a, c, d]]]
    V1, f1, sem1 = _gable_house(12.3, 11.7, 16.0, 12.0, 13.6, 13.6, 8.0, ground=3.5)      # flat-roofed part
    V2, f2, sem2 = _gable_house(15.1, 14.9, 8.0, 6.0, 18.0, 21.0, 8.0, ground=13.6)      # part on the part
    verts = [tin_v, V1, V2] if with_tin else [V1, V2]
    b1 = len(tin_v) if with_tin else 0
    b2 = b1 + len(V1)
    objs = {
        "bldg": {"type": "Building", "children": ["bldg-1", "bldg-2"], "attributes": {}},
        "bldg-1": {"type": "BuildingPart", "parents": ["bldg"], "geometry": [{
            "type": "MultiSurface", "lod": "2.2", "semantics": sem1,
            "boundaries": [[[b1 + i for i in ring] for ring in f] for f in f1]}]},
        "bldg-2": {"type": "BuildingPart", "parents": ["bldg"], "geometry": [{
            "type": "MultiSurface", "lod": "2.2", "semantics": sem2,
            "boundaries": [[[b2 + i for i in ring] for ring in f] for f in f2]}]},
    }
    if with_tin:
        objs["relief"] = {"type": "TINRelief", "geometry": [{"type": "TIN", "lod": "1", "boundaries": tris}]}
    path = tmp_path / (name or f"city_{int(with_tin)}.city.json")
    allv = np.vstack(verts) + np.array([offset[0], offset[1], 0.0])
    path.write_text(json.dumps(_cityjson_doc(allv, objs)))
    roofs = [V1[[4, 5, 9, 8]], V1[[7, 8, 9, 6]], V2[[4, 5, 9, 8]], V2[[7, 8, 9, 6]]]
    return path, [tin_v[t[0]] for t in tris], roofs


@pytest.mark.parametrize("with_tin", [True, False])
def test_cityjson_building_part_on_a_part_is_not_ground(tmp_path, with_tin):
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.runner import run_scenario
    from tests.test_surface_conservative import _face_heights_at, _random_points_in_cells

    path, tin_faces, roofs = _stacked_city(tmp_path, with_tin)
    grid = Grid.from_bounds("EPSG:28992", 0, 0, 40, 40, 1.0)
    ds = build_surface(grid, buildings_path=path, buildings_format="cityjson")
    hi, lo = ds["terrain"].values.astype(float), ds["terrain_min"].values.astype(float)
    assert np.all(lo <= hi)
    rng = np.random.default_rng(9)
    rows, cols = np.mgrid[0:grid.ny, 0:grid.nx]
    rr, cc, x, y = _random_points_in_cells(grid, rows.ravel(), cols.ravel(), 6, rng)
    if with_tin:     # the ground is the TIN: bounds of it at every point of every cell
        z = _face_heights_at(tin_faces, x, y)
        assert np.isfinite(z).all()
        assert np.all(hi[rr, cc] >= z - 1e-5) and np.all(lo[rr, cc] <= z + 1e-5)
        assert "TINRelief" in ds.attrs["ground_source"]
    else:            # the ground is the lowest ground surface (3.5 m), never the stacked part's 13.6 m
        assert hi.max() == pytest.approx(3.5, abs=1e-5) and lo.min() == pytest.approx(3.5, abs=1e-5)
        assert "lowest ground surface of each building" in ds.attrs["ground_source"]
    zr = _face_heights_at(roofs, x, y)
    has = np.isfinite(zr)
    assert np.all(ds["surface"].values[rr[has], cc[has]] >= zr[has] - 1e-5)
    assert float(ds["surface"].max()) == pytest.approx(21.0, abs=1e-5)
    # a user who gave only the CityJSON: the maps build (no internal invariant reaches them)
    sc = parse_scenario({
        "name": "own-cityjson", "aoi": {"crs": "EPSG:28992", "bounds": [0, 0, 40, 40], "resolution_m": 1.0},
        "data": {"buildings": {"path": str(path), "format": "cityjson"}},
        "mission": {"start": {"x": 2, "y": 2, "alt_agl_m": 5}, "goal": {"x": 38, "y": 38, "alt_agl_m": 5},
                    "start_time_utc": "2020-01-03T10:00:00Z"}}, base=tmp_path)
    out = run_scenario(sc, cache=Cache(tmp_path / "cache"), targets=["clearance"])
    clr = out["clearance"].load()
    assert np.all(clr["max_altitude_m"].values >= clr["min_altitude_m"].values.min())


# ------------------------------------------------------------------ catalogs/README: bring your own city
def _readme_yamls() -> dict[str, str]:
    from _dem import readme_scenarios

    return readme_scenarios()


def _own_city_fixtures(tmp_path):
    """The files the README's YAMLs name, made from small real or synthetic data."""
    import shutil

    from skyroute.pipeline.settings import catalog_dir

    data = catalog_dir() / "data"
    shutil.copy(data / "yuma_2020-01-03.txt", tmp_path / "yuma.txt")
    dsm_src = Path(__file__).parent / "data" / "rotterdam_dsm_0p5m.tif"
    shutil.copy(dsm_src, tmp_path / "dsm.tif")
    with rasterio.open(dsm_src) as src:                 # a lidar tile: NoData at two edges and inside
        z = src.read(1).astype(float)
        T, crs = src.transform, src.crs
    z[:, :14] = np.nan                                  # water along the west edge ...
    z[480:, :60] = np.nan                               # ... and the south-west corner
    z[:8, 300:360] = np.nan                             # a glass roof at the north edge
    z[200:215, 200:230] = np.nan                        # and one inside
    _write(tmp_path / "ahn_tile.tif", z, T, crs)
    _stacked_city(tmp_path, True, offset=(81000.0, 455000.0), name="city.city.json")
    with rasterio.open(data / "srtm_bigtujunga30m_utm11.tif") as src:
        w = rasterio.windows.from_bounds(382500, 3793500, 386500, 3797500, src.transform).round_offsets().round_lengths()
        a = src.read(1, window=w).astype(float)
        _write(tmp_path / "dem.tif", a, src.window_transform(w), src.crs)
    return tmp_path


def test_bring_your_own_city_yamls_plan_as_written(tmp_path):
    """Each YAML of catalogs/README.md's "Bring your own city" loads as written next to a file of
    its kind, inspects without an error and plans a flyable path (no almanac: no GNSS maps)."""
    import yaml

    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.inspect import inspect_target
    from skyroute.pipeline.runner import run_scenario

    blocks = _readme_yamls()
    assert sorted(blocks) == ["my-city-cityjson", "my-city-dsm", "my-city-lidar", "my-mountains-dem"]
    _own_city_fixtures(tmp_path)
    cache = Cache(tmp_path / "cache")
    for name, text in blocks.items():
        yml = tmp_path / f"{name}.yaml"
        yml.write_text(text)
        assert yaml.safe_load(text)["name"] == name
        ins = inspect_target(str(yml))
        assert ins.ok, (name, ins.problems)
        assert ins.data["absolute_heights"]["available"], name
        sc = load_scenario(yml)
        res = run_scenario(sc, cache=cache, targets=["plan"])
        plan = res["plan"]
        assert int(plan.attrs["chosen_level"]) >= 0, (name, plan.attrs.get("reasons"))
        if name == "my-city-lidar":
            assert any("NoData region" in w for w in json.loads(res["surface"].attrs["warnings"]))


# ------------------------------------------------------------------ 6. fleet landing sites from open ground
def test_open_ground_sites_against_brute_force():
    """Candidate sites: not no-fly, nothing on the cell, nothing higher than the ground + 0.5 m
    within r_p (brute force over the surface raster), lowest risk level present, one per block."""
    from skyroute.stages.clearance import clearance_floor
    from skyroute.stages.landing import open_ground_sites

    rng = np.random.default_rng(3)
    g = Grid.from_bounds("EPSG:32631", 0, 0, 400, 300, 2.0)
    terr = np.zeros(g.shape)
    surf = terr.copy()
    for _ in range(40):                                   # buildings
        r, c, h, w = rng.integers(0, g.ny - 10), rng.integers(0, g.nx - 10), rng.integers(3, 10), rng.integers(3, 10)
        surf[r:r + h, c:c + w] = rng.uniform(5, 30)
    level = np.full(g.shape, 4)
    level[50:90, 20:120] = 1                              # a park
    nofly = np.zeros(g.shape, bool)
    nofly[60:70, 30:60] = True
    r_p = 5.0
    floor = clearance_floor(g.dataarray(surf, "surface", units="m"), r_p).values
    x, y, lv = open_ground_sites(terrain=terr, surface=surf, obstacle_floor=floor, risk_level=level, nofly=nofly,
                                 grid=g, radius_m=r_p)
    assert lv == 1 and len(x) >= 2
    rows, cols = g.index_of(x, y)
    yy, xx = np.meshgrid(g.y, g.x, indexing="ij")
    for r, c in zip(rows, cols, strict=True):
        assert level[r, c] == 1 and not nofly[r, c] and surf[r, c] == 0.0
        near = np.hypot(xx - g.x[c], yy - g.y[r]) <= r_p + g.resolution_m    # every cell within reach
        assert surf[near].max() <= 0.5 + 1e-9
    blocks = {(r // 50, c // 50) for r, c in zip(rows, cols, strict=True)}
    assert len(blocks) == len(rows)                       # one per 100 m block


def test_fleet_draws_missions_on_open_ground_in_a_city_without_sites(tmp_path):
    """The README's DSM city has no landing sites: fleet --missions draws between candidate sites on
    open ground, and says so."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.fleet import draw_missions
    from skyroute.pipeline.runner import run_scenario

    _own_city_fixtures(tmp_path)
    yml = tmp_path / "my-city-dsm.yaml"
    yml.write_text(_readme_yamls()["my-city-dsm"])
    sc = load_scenario(yml)
    res = run_scenario(sc, cache=Cache(tmp_path / "cache"), targets=["clearance"])
    maps = {k: res[k].load() for k in ("surface", "environment", "clearance")}
    notes: list[str] = []
    tasks = draw_missions(sc, maps, 6, 1, 600.0, notes=notes)
    assert len(tasks) == 6 and len(notes) == 1 and "derived from open ground" in notes[0]
    g = sc.grid
    for t in tasks:
        for x, y in (t.start_xy, t.goal_xy):
            r, c = g.cell_of(x, y)
            assert maps["surface"]["surface"].values[r, c] <= maps["surface"]["terrain"].values[r, c] + 1e-6
        assert np.hypot(t.start_xy[0] - t.goal_xy[0], t.start_xy[1] - t.goal_xy[1]) >= 200.0


# ------------------------------------------------------------------ 5. intents of a sampled (fixed-wing) plan
def test_sampled_plan_intent_volumes_contain_the_whole_polyline():
    """A fixed-wing plan is known by its samples: the intent volumes of that polyline contain every
    point of it (checked densely with plain interpolation and shapely), each in its time window
    and altitude band."""
    import shapely

    from skyroute.stages.intents import PolylineTrajectory, plan_volumes

    rng = np.random.default_rng(2)
    t = np.cumsum(np.r_[0.0, rng.uniform(0.5, 2.0, 120)])
    xyz = np.cumsum(np.column_stack([rng.normal(15, 6, t.size), rng.normal(0, 9, t.size),
                                     rng.normal(0, 1.5, t.size)]), axis=0) + [380000.0, 3795000.0, 900.0]
    sigma = rng.uniform(1.0, 3.0, t.size)
    vols = plan_volumes(PolylineTrajectory(t, xyz), 10.0, t + 10.0, sigma, lambda p: p[:, 2] + 30.0,
                        vehicle_radius_m=1.0, k_sigma=3.0, time_buffer_s=5.0, max_volume_s=20.0)
    tt = np.linspace(0.0, t[-1], 20000)
    P = np.column_stack([np.interp(tt, t, xyz[:, k]) for k in range(3)])
    ok = np.zeros(tt.size, bool)
    for v in vols:
        inside = shapely.contains_xy(shapely.Polygon(v.outline_xy_m), P[:, 0], P[:, 1])
        band = (P[:, 2] + 30.0 >= v.alt_lower_m) & (P[:, 2] + 30.0 <= v.alt_upper_m)
        when = (tt + 10.0 >= v.t_start_s) & (tt + 10.0 <= v.t_end_s)
        ok |= inside & band & when
    assert ok.all()
