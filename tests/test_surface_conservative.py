"""Conservative rasterisation (issue 8): a surface cell is >= the real surface at every point of
the cell.  References are independent: shapely intersections of closed cell squares, and roof
heights computed here from the CityJSON text (constrained Delaunay triangles of each face)."""

from __future__ import annotations

import json

import numpy as np
import osmium
import pytest
import shapely
from pyproj import Transformer
from shapely import affinity

from skyroute.pipeline.settings import catalog_dir
from skyroute.stages.grid import Grid
from skyroute.stages.surface import _rasterize_flat, build_surface, cityjson_buildings

CATALOG_DATA = catalog_dir() / "data"
ROTTERDAM = CATALOG_DATA / "rotterdam_delfshaven_lod2.city.json"


def _cell_boxes(grid: Grid) -> np.ndarray:
    R, C = np.mgrid[0:grid.ny, 0:grid.nx]
    r = grid.resolution_m
    return shapely.box(grid.x0 + C * r, grid.y1 - (R + 1) * r, grid.x0 + (C + 1) * r, grid.y1 - R * r)


def _touch_oracle(grid: Grid, geoms, heights) -> np.ndarray:
    """Highest height of the footprints whose closed polygon meets each closed cell square (NaN: none)."""
    boxes = _cell_boxes(grid).ravel()
    out = np.full(boxes.size, -np.inf)
    tree = shapely.STRtree(boxes)
    for g, h in zip(geoms, heights, strict=True):
        hit = tree.query(g, predicate="intersects")
        out[hit] = np.maximum(out[hit], h)
    out[~np.isfinite(out)] = np.nan
    return out.reshape(grid.shape)


# ------------------------------------------------------------------ OSM / flat footprints


@pytest.mark.parametrize("res", [0.5, 1.0, 2.0])
def test_flat_footprints_take_every_touched_cell_highest_wins(res):
    """Thin, rotated, grid-aligned, holed and overlapping footprints: the raster equals the exact
    closed-square intersection oracle cell for cell (nothing missed, nothing extra)."""
    rng = np.random.default_rng(int(res * 10))
    grid = Grid.from_bounds("EPSG:32633", 0, 0, 40, 30, res)
    geoms, heights = [], []
    for k in range(60):
        cx, cy = rng.uniform(3, 37), rng.uniform(3, 27)
        if k % 5 == 0:
            cx, cy = np.round([cx, cy])  # on grid nodes
        w, h = rng.choice([0.01, 0.3, 1.7, 6.0]), rng.choice([0.01, 0.3, 4.0])
        g = affinity.rotate(shapely.box(cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2),
                            0.0 if k % 3 == 0 else rng.uniform(0, 90), origin=(cx, cy))
        if k % 7 == 0:  # edges exactly on grid lines: the neighbours that touch count too
            g = shapely.box(np.round(cx), np.round(cy), np.round(cx) + res, np.round(cy) + 2 * res)
        if k % 11 == 0:  # a courtyard: cells strictly inside the hole stay empty
            g = shapely.Point(cx, cy).buffer(5.0).difference(shapely.Point(cx, cy).buffer(3.0))
        geoms.append(g)
        heights.append(float(rng.uniform(3, 60)))
    br = _rasterize_flat(grid, geoms, heights, np.arange(len(geoms)), np.array(["t"] * len(geoms), object), False)
    ref = _touch_oracle(grid, geoms, heights)
    np.testing.assert_array_equal(np.isnan(br.top), np.isnan(ref))
    np.testing.assert_array_equal(br.top[~np.isnan(ref)], ref[~np.isnan(ref)])
    # the index names a building of that height which touches the cell
    has = br.index >= 0
    assert np.all(np.asarray(heights)[br.index[has]] == br.top[has])
    assert np.all((br.index >= 0) == ~np.isnan(br.top))


def _osm_buildings_direct(path):
    wkb = osmium.geom.WKBFactory()
    out = {}
    for o in osmium.FileProcessor(str(path)).with_areas().with_locations():
        if o.is_area() and ("building" in o.tags or "building:part" in o.tags):
            try:
                out[o.orig_id()] = shapely.from_wkb(wkb.create_multipolygon(o))
            except RuntimeError:
                pass
    return out


def test_helsinki_osm_surface_is_the_touched_cell_maximum(helsinki, helsinki_surface):
    """Every cell touched by a footprint (pyosmium geometry, shapely closed intersection) is at
    least that building's height, and every raised cell is explained by a touching footprint."""
    ds = helsinki_surface
    grid = helsinki.grid
    direct = _osm_buildings_direct(CATALOG_DATA / "helsinki_center.osm.pbf")
    to_map = Transformer.from_crs(4326, grid.crs, always_xy=True)
    geoms, heights = [], []
    for osm_id, h in zip(ds["building_osm_id"].values, ds["building_height_m"].values, strict=True):
        g = direct[int(osm_id)]
        geoms.append(shapely.transform(g, lambda xy: np.column_stack(to_map.transform(xy[:, 0], xy[:, 1]))))
        heights.append(float(h))
    ref = _touch_oracle(grid, geoms, heights)
    surf = ds["surface"].values.astype(np.float64)
    has = ~np.isnan(ref)
    assert has.sum() > 10000
    np.testing.assert_allclose(surf[has], ref[has], atol=1e-4)  # float32 storage
    assert np.all(surf[~has] == 0.0)  # flat terrain at 0 m where no footprint touches


# ------------------------------------------------------------------ CityJSON faces


def _cityjson_doc(vertices, objects, epsg=28992):
    V = np.asarray(vertices, float)
    return {"type": "CityJSON", "version": "1.1", "transform": {"scale": [1, 1, 1], "translate": [0, 0, 0]},
            "metadata": {"referenceSystem": f"https://www.opengis.net/def/crs/EPSG/0/{epsg}"},
            "vertices": V.tolist(), "CityObjects": objects}


def _face_heights_at(faces, x, y) -> np.ndarray:
    """Oracle: the highest face height [m] above each point (x, y) (NaN where no face), each face
    cut into constrained Delaunay triangles (shapely/GEOS) and interpolated linearly on them."""
    pts = shapely.points(x, y)
    out = np.full(x.shape, -np.inf)
    for P in faces:
        poly = shapely.Polygon(P[:, :2])
        tris = shapely.get_parts(shapely.constrained_delaunay_triangles(poly))
        for t in tris:
            T = np.asarray(t.exterior.coords)[:3]
            # z of the triangle's corners: the face vertices at those (x, y)
            k = [int(np.argmin(np.hypot(P[:, 0] - a, P[:, 1] - b))) for a, b in T]
            Z = P[k, 2]
            inside = shapely.intersects(t, pts)
            if not inside.any():
                continue
            A = np.column_stack([T[:, 0], T[:, 1], np.ones(3)])
            abc = np.linalg.solve(A, Z)
            z = abc[0] * x[inside] + abc[1] * y[inside] + abc[2]
            out[inside] = np.maximum(out[inside], z)
    out[~np.isfinite(out)] = np.nan
    return out


def _random_points_in_cells(grid: Grid, rows, cols, n_per_cell: int, rng):
    r = grid.resolution_m
    rows = np.repeat(rows, n_per_cell)
    cols = np.repeat(cols, n_per_cell)
    x = grid.x0 + (cols + rng.uniform(0, 1, rows.size)) * r
    y = grid.y1 - (rows + rng.uniform(0, 1, rows.size)) * r
    return rows, cols, x, y


def _gable_house(x0, y0, w, d, eave, apex, angle_deg, ground=0.0):
    """A gable-roofed box rotated by ``angle_deg`` about (x0, y0): vertices and a MultiSurface
    with RoofSurface / WallSurface / GroundSurface semantics (the ridge at height ``apex``)."""
    loc = np.array([[0, 0, ground], [w, 0, ground], [w, d, ground], [0, d, ground],
                    [0, 0, eave], [w, 0, eave], [w, d, eave], [0, d, eave],
                    [0, d / 2, apex], [w, d / 2, apex]])
    a = np.radians(angle_deg)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    V = loc.copy()
    V[:, :2] = loc[:, :2] @ R.T + [x0, y0]
    faces = [[[0, 3, 2, 1]], [[4, 5, 9, 8]], [[7, 8, 9, 6]],  # ground, two roof slopes
             [[0, 1, 5, 4]], [[2, 3, 7, 6]], [[1, 2, 6, 9, 5]], [[3, 0, 4, 8, 7]]]
    sem = {"surfaces": [{"type": "GroundSurface"}, {"type": "RoofSurface"}, {"type": "WallSurface"}],
           "values": [0, 1, 1, 2, 2, 2, 2]}
    return V, faces, sem


def test_roof_apex_is_not_cut_and_every_point_is_covered(tmp_path):
    """A 17.8 m ridge off the grid, rotated: the cells holding the ridge take 17.8 m exactly, and
    random points inside every cell are no higher than the cell (constrained-Delaunay oracle)."""
    rng = np.random.default_rng(3)
    verts, objs, roofs = [], {}, []
    for k, (x0, y0, ang, apex) in enumerate([(10.37, 6.21, 23.0, 17.8), (31.9, 8.6, 0.0, 14.33),
                                              (12.2, 30.1, 61.7, 22.05), (30.3, 29.4, 90.0, 12.0)]):
        V, faces, sem = _gable_house(x0, y0, 9.3, 7.7, 11.0, apex, ang)
        base = len(verts)
        verts.extend(V.tolist())
        objs[f"b{k}"] = {"type": "Building", "attributes": {"TerrainHeight": 0.0}, "geometry": [{
            "type": "MultiSurface", "lod": "2", "semantics": sem,
            "boundaries": [[[base + i for i in ring] for ring in f] for f in faces]}]}
        roofs += [V[f[0]] for f, v in zip(faces, sem["values"], strict=True) if v == 1]
    path = tmp_path / "houses.city.json"
    path.write_text(json.dumps(_cityjson_doc(verts, objs)))
    for res in (0.5, 1.0, 2.0):
        grid = Grid.from_bounds("EPSG:28992", 0, 0, 45, 45, res)
        br, _ = cityjson_buildings(path, grid)
        # the ridge: every cell a ridge point falls in equals the apex (not lower, not higher)
        for V0 in range(4):
            P = np.asarray(verts[V0 * 10 + 8: V0 * 10 + 10])
            t = np.linspace(0, 1, 101)[:, None]
            ridge = P[0] + t * (P[1] - P[0])
            r, c = grid.index_of(ridge[:, 0], ridge[:, 1])
            np.testing.assert_allclose(br.top[r, c], P[0, 2], atol=1e-9)
        # every point of every cell: oracle <= cell
        rows, cols = np.nonzero(np.isfinite(br.top))
        rr, cc, x, y = _random_points_in_cells(grid, rows, cols, 6, rng)
        z = _face_heights_at(roofs, x, y)
        ok = np.isfinite(z)
        assert ok.sum() > 300
        assert np.all(br.top[rr[ok], cc[ok]] >= z[ok] - 1e-9), float(np.max(z[ok] - br.top[rr[ok], cc[ok]]))
        # cells no roof reaches are empty
        assert np.all(np.isnan(br.top) | np.isfinite(br.top))
        # and the bound is tight: the cell value is attained at some point of the cell
        # (the maximum over many random points approaches it from below)
        cell = rr * grid.nx + cc
        best = np.full(grid.nx * grid.ny, -np.inf)
        np.maximum.at(best, cell[ok], z[ok])
        sel = np.isfinite(best)
        gap = br.top.ravel()[sel] - best[sel]
        assert np.all(gap >= -1e-9) and np.median(gap) < 0.5 * res


def test_rotterdam_lod2_every_point_of_a_cell_is_covered():
    """Real LoD2 roofs (shipped file), a 150 m x 150 m window at 1 m: the highest face height at
    random points inside each cell <= the cell; every building's highest roof vertex in the
    window is kept (not cut)."""
    cj = json.loads(ROTTERDAM.read_text())
    V = np.asarray(cj["vertices"], float) * cj["transform"]["scale"] + cj["transform"]["translate"]
    grid = Grid.from_bounds("EPSG:28992", 90700, 435700, 90850, 435850, 1.0)
    br, _ = cityjson_buildings(ROTTERDAM, grid)
    xmin, ymin, xmax, ymax = grid.bounds
    roofs = []
    for obj in cj["CityObjects"].values():
        g = obj["geometry"][0]
        types = [s["type"] for s in g["semantics"]["surfaces"]]
        for face, v in zip(g["boundaries"], g["semantics"]["values"], strict=True):
            if types[v] == "RoofSurface":
                P = V[np.asarray(face[0])]
                if P[:, 0].max() >= xmin and P[:, 0].min() <= xmax and P[:, 1].max() >= ymin and P[:, 1].min() <= ymax:
                    roofs.append(P)
    assert len(roofs) > 200
    rng = np.random.default_rng(7)
    rows, cols = np.nonzero(np.isfinite(br.top))
    rr, cc, x, y = _random_points_in_cells(grid, rows, cols, 3, rng)
    z = _face_heights_at(roofs, x, y)
    ok = np.isfinite(z)
    assert ok.sum() > 20000
    short = z[ok] - br.top[rr[ok], cc[ok]]
    assert np.all(short <= 1e-9), float(short.max())
    # vertices: every roof vertex inside the window is <= its cell, and the window's top is kept
    P = np.vstack(roofs)
    r, c = grid.index_of(P[:, 0], P[:, 1])
    inside = (r >= 0) & (r < grid.ny) & (c >= 0) & (c < grid.nx)
    assert np.all(br.top[r[inside], c[inside]] >= P[inside, 2] - 1e-9)
    assert np.nanmax(br.top) == pytest.approx(P[inside, 2].max(), abs=0.05)


def test_tin_relief_is_the_terrain_max_over_each_cell(tmp_path):
    """A CityJSON TINRelief (sloped, off-grid triangles) becomes the terrain: each covered cell
    takes the TIN's maximum over the cell (>= the TIN at random points inside, attained at a
    vertex, crossing or corner); buildings stand on it."""
    rng = np.random.default_rng(5)
    xs = np.array([-3.3, 12.1, 27.7, 43.9])
    ys = np.array([-2.9, 14.2, 26.5, 44.1])
    X, Y = np.meshgrid(xs, ys)
    Z = 1.0 + 0.15 * X - 0.07 * Y + rng.uniform(-0.8, 0.8, X.shape)
    tin_v = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    tris = []
    for i in range(3):
        for j in range(3):
            a, b, c, d = i * 4 + j, i * 4 + j + 1, (i + 1) * 4 + j + 1, (i + 1) * 4 + j
            tris += [[[a, b, c]], [[a, c, d]]]
    Vh, faces, sem = _gable_house(15.2, 16.7, 8.0, 6.0, 9.0 + 5, 13.0 + 5, 17.0)
    base = len(tin_v)
    objs = {"relief": {"type": "TINRelief", "geometry": [{"type": "TIN", "lod": "1", "boundaries": tris}]},
            "house": {"type": "Building", "geometry": [{"type": "MultiSurface", "lod": "2", "semantics": sem,
                      "boundaries": [[[base + i for i in ring] for ring in f] for f in faces]}]}}
    path = tmp_path / "tin.city.json"
    path.write_text(json.dumps(_cityjson_doc(np.vstack([tin_v, Vh]), objs)))
    grid = Grid.from_bounds("EPSG:28992", 0, 0, 40, 40, 1.0)
    ds = build_surface(grid, buildings_path=path, buildings_format="cityjson")
    terr = ds["terrain"].values.astype(np.float64)
    rows, cols = np.mgrid[0:grid.ny, 0:grid.nx]
    rr, cc, x, y = _random_points_in_cells(grid, rows.ravel(), cols.ravel(), 8, rng)
    ztin = _face_heights_at([tin_v[t[0]] for t in tris], x, y)
    assert np.isfinite(ztin).all()
    assert np.all(terr[rr, cc] >= ztin - 1e-5)  # float32 storage
    # tight: never more than the TIN's rise across one cell above the sampled maximum
    best = np.full(grid.shape, -np.inf)
    np.maximum.at(best, (rr, cc), ztin)
    slope = 0.15 + 0.07 + 2 * 0.8 / 15.0
    assert np.all(terr - best <= 2 * slope + 1e-5)
    assert np.all(ds["surface"].values >= ds["terrain"].values)
    assert ds["surface"].values.max() == pytest.approx(18.0, abs=1e-5)


# ------------------------------------------------------------------ shipped DSM fixture


def test_rotterdam_dsm_fixture_matches_its_generator():
    """tests/data/rotterdam_dsm_0p5m.tif is what its generator makes (float32 rounded up), in
    EPSG:28992 / NAP, and is >= the roof faces (constrained-Delaunay oracle) inside every cell."""
    import importlib.util

    import rasterio

    here = __import__("pathlib").Path(__file__).resolve().parent / "data"
    spec = importlib.util.spec_from_file_location("make_rotterdam_dsm", here / "make_rotterdam_dsm.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    with rasterio.open(gen.OUT) as src:
        dsm = src.read(1)
        assert src.crs.to_epsg() == 28992 and src.tags()["VERTICAL_DATUM"] == "NAP"
        assert src.res == (0.5, 0.5) and src.shape == (500, 500) and src.dtypes[0] == "float32"
        assert tuple(src.bounds) == gen.BOUNDS
    assert gen.OUT.stat().st_size < 1_000_000
    ref, grid = gen.compute()
    np.testing.assert_array_equal(dsm, ref)
    # independent: roofs at random points of random cells never exceed the fixture
    cj = json.loads(ROTTERDAM.read_text())
    V = np.asarray(cj["vertices"], float) * cj["transform"]["scale"] + cj["transform"]["translate"]
    xmin, ymin, xmax, ymax = grid.bounds
    roofs = []
    for obj in cj["CityObjects"].values():
        g = obj["geometry"][0]
        types = [s["type"] for s in g["semantics"]["surfaces"]]
        for face, v in zip(g["boundaries"], g["semantics"]["values"], strict=True):
            P = V[np.asarray(face[0])]
            if types[v] == "RoofSurface" and P[:, 0].max() >= xmin and P[:, 0].min() <= xmax \
                    and P[:, 1].max() >= ymin and P[:, 1].min() <= ymax:
                roofs.append(P)
    rng = np.random.default_rng(11)
    rows, cols = rng.integers(0, grid.ny, 20000), rng.integers(0, grid.nx, 20000)
    rr, cc, x, y = _random_points_in_cells(grid, rows, cols, 1, rng)
    z = _face_heights_at(roofs, x, y)
    ok = np.isfinite(z)
    assert ok.sum() > 5000
    assert np.all(dsm[rr[ok], cc[ok]] >= z[ok] - 1e-9)
    assert float(dsm.max()) == pytest.approx(41.158, abs=1e-3)  # the district's tallest roof vertex


def test_delft_lod1_solids_every_point_of_a_cell_is_covered(shared_data):
    """Real LoD1 solids without semantics (CityJSON 2.0, EPSG:7415 compound CRS): the highest
    non-vertical face of any building over random points inside each cell <= the cell."""
    path = shared_data / "city" / "delft_lod1.city.json"
    cj = json.loads(path.read_text())
    V = np.asarray(cj["vertices"], float) * cj["transform"]["scale"] + cj["transform"]["translate"]
    grid = Grid.from_bounds("EPSG:28992", 84700, 447450, 85000, 447700, 1.0)
    br, _ = cityjson_buildings(path, grid)
    faces = []
    for o in cj["CityObjects"].values():
        if o["type"] != "Building":
            continue
        for g in o["geometry"]:
            for shell in g["boundaries"]:
                for f in shell:
                    P = V[np.asarray(f[0])]
                    if shapely.Polygon(P[:, :2]).area > 1e-6:  # any orientation: the max is the roof
                        faces.append(P)
    rng = np.random.default_rng(4)
    rows, cols = np.nonzero(np.isfinite(br.top))
    rr, cc, x, y = _random_points_in_cells(grid, rows, cols, 3, rng)
    z = _face_heights_at(faces, x, y)
    ok = np.isfinite(z)
    assert ok.sum() > 5000
    assert np.all(br.top[rr[ok], cc[ok]] >= z[ok] - 1e-9)
