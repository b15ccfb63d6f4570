"""Strict CityJSON reading (issue 34, "silently wrong worlds" and tracebacks): every malformed
file is one DataError naming the file, the CityObject / vertex / key and the fix, refused the
same way by ``skyroute inspect`` and by the surface stage (one validation,
:func:`skyroute.stages.cityjson.load_cityjson`); GeometryInstances are placed from their
templates; every coercion kept is a counted warning."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

from skyroute.pipeline.cli import main
from skyroute.pipeline.inspect import inspect_target
from skyroute.stages.base import DataError
from skyroute.stages.cityjson import load_cityjson
from skyroute.stages.grid import Grid
from skyroute.stages.surface import build_surface

GRID = Grid.from_bounds("EPSG:28992", 80, 180, 130, 230, 1.0)


def _box(x0, y0, x1, y1, z0, z1):
    """Vertices (8) and the 6 faces (outward, CityJSON rings) of a box, with semantics."""
    V = [[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
         [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]]
    faces = [[[0, 3, 2, 1]], [[4, 5, 6, 7]], [[0, 1, 5, 4]], [[1, 2, 6, 5]], [[2, 3, 7, 6]], [[3, 0, 4, 7]]]
    sem = {"surfaces": [{"type": "GroundSurface"}, {"type": "RoofSurface"}, {"type": "WallSurface"}],
           "values": [0, 1, 2, 2, 2, 2]}
    return V, faces, sem


def _offset(faces, k):
    return [[[i + k for i in ring] for ring in f] for f in faces]


def _city(scale=(0.01, 0.01, 0.01), translate=(0.0, 0.0, 0.0)) -> dict:
    """Two box buildings (b1: 90..100 x 190..200, 2..14 m, a Solid; b2: 110..120 x 190..200,
    2..20 m, a MultiSurface), integer vertices under ``transform``."""
    V1, f1, s1 = _box(90, 190, 100, 200, 2, 14)
    V2, f2, s2 = _box(110, 190, 120, 200, 2, 20)
    s, t = np.asarray(scale), np.asarray(translate)
    raw = np.rint((np.asarray(V1 + V2, float) - t) / s).astype(np.int64).tolist()
    return {"type": "CityJSON", "version": "2.0",
            "transform": {"scale": list(scale), "translate": list(translate)},
            "metadata": {"referenceSystem": "https://www.opengis.net/def/crs/EPSG/0/28992"},
            "vertices": raw,
            "CityObjects": {
                "b1": {"type": "Building", "geometry": [{"type": "Solid", "lod": "2.2", "boundaries": [f1],
                                                          "semantics": {**s1, "values": [s1["values"]]}}]},
                "b2": {"type": "Building", "geometry": [{"type": "MultiSurface", "lod": "2.2",
                                                          "boundaries": _offset(f2, 8), "semantics": s2}]}}}


def _write(tmp_path, cj, name="city.city.json"):
    p = tmp_path / name
    p.write_text(json.dumps(cj))      # NaN / Infinity written as JSON extensions, as some exporters do
    return p


def _refused_alike(path, match):
    """The surface stage and ``skyroute inspect`` refuse ``path`` with the same one message."""
    with pytest.raises(DataError, match=match) as exc:
        build_surface(GRID, buildings_path=path, buildings_format="cityjson")
    msg = str(exc.value)
    assert str(path) in msg
    ins = inspect_target(path)
    errors = [m for lv, _, m in ins.problems if lv == "error"]
    assert errors == [msg]
    return msg


def test_a_good_city_reads_with_the_transform_and_no_warning(tmp_path):
    p = _write(tmp_path, _city())
    doc = load_cityjson(p)
    assert doc.warnings == () and doc.counts == {}
    assert doc.vertices[:, 2].min() == pytest.approx(2.0) and doc.vertices[:, 2].max() == pytest.approx(20.0)
    ds = build_surface(GRID, buildings_path=p, buildings_format="cityjson")
    s = ds["surface"].values
    assert np.isfinite(s).all()
    assert float(s.max()) == pytest.approx(20.0)
    assert "warnings" not in ds.attrs
    ins = inspect_target(p)
    assert ins.ok and not ins.problems


@pytest.mark.parametrize("scale, translate", [
    ([1, 1, 0], [0, 0, 0]), ([0.01, 0.01, -0.01], [0, 0, 0]), ([0.01, 0.01, math.nan], [0, 0, 0]),
    ([0.01, 0.01, math.inf], [0, 0, 0]), ([0.01, 0.01], [0, 0, 0]), ("0.01", [0, 0, 0]),
    ([0.01, 0.01, "0.01"], [0, 0, 0]), ([0.01, 0.01, True], [0, 0, 0]), ([0.01] * 3, [0, 0, math.inf]),
    ([0.01] * 3, [0, 0]),
])
def test_a_transform_that_is_not_3_positive_finite_scales_and_3_finite_shifts_is_refused(tmp_path, scale, translate):
    cj = _city()
    cj["transform"] = {"scale": scale, "translate": translate}
    bad = "scale" if scale != [0.01] * 3 else "translate"
    msg = _refused_alike(_write(tmp_path, cj), rf"transform\.{bad}")
    assert "re-export" in msg


def test_a_zero_height_scale_no_longer_flattens_the_city(tmp_path):
    """The reproduction: scale [1, 1, 0] made every building 0 m and inspect said 0.00 .. 0.00."""
    cj = _city(scale=(1, 1, 1))
    cj["transform"]["scale"] = [1, 1, 0]
    p = _write(tmp_path, cj)
    msg = _refused_alike(p, r"transform\.scale \[1, 1, 0\] has a zero or negative component")
    assert "flattens every building to 0 m" in msg
    res = CliRunner().invoke(main, ["inspect", str(p)])
    assert res.exit_code == 2
    assert [ln for ln in res.output.splitlines() if ln.startswith("error:")] == [f"error: data.buildings.path: {msg}"]
    assert "Traceback" not in res.output and "heights" not in res.output


def test_a_negative_vertex_index_does_not_wrap_onto_another_building(tmp_path):
    cj = _city()
    cj["CityObjects"]["b2"]["geometry"][0]["boundaries"][1] = [[-4, -3, -2, -1]]   # b2's own roof, wrapped
    msg = _refused_alike(_write(tmp_path, cj), r"CityObject 'b2' \(MultiSurface\): vertex index -4 is negative")
    assert "0 .. 15 (16 vertices)" in msg


def test_a_vertex_index_past_the_end_is_refused_naming_the_object(tmp_path):
    cj = _city()
    cj["CityObjects"]["b1"]["geometry"][0]["boundaries"][0][1] = [[4, 5, 99999, 7]]
    msg = _refused_alike(_write(tmp_path, cj), r"CityObject 'b1' \(Solid\): vertex index 99999 is past the end")
    assert "of the 16 vertices" in msg
    cj["CityObjects"]["b1"]["geometry"][0]["boundaries"][0][1] = [[4, 5, 2**70, 7]]     # beyond int64
    _refused_alike(_write(tmp_path, cj), r"CityObject 'b1' \(Solid\): vertex index 1180591620717411303424 is not "
                                         r"in 0 \.\. 15")
    cj = _city()
    cj["transform"]["scale"] = [10**400, 1, 1]                                          # beyond a float
    _refused_alike(_write(tmp_path, cj), r"transform\.scale is \[1000.*must be 3 finite numbers")


@pytest.mark.parametrize("value, match", [
    (math.nan, r"vertex 13 \(used by CityObject 'b2'\) is \[120, 190, nan\].*must be finite numbers"),
    (math.inf, r"vertex 13 \(used by CityObject 'b2'\) is \[120, 190, inf\].*must be finite numbers"),
    ("2000", r"vertices\[13\] is \[12000, 19000, '2000'\]: each vertex must be 3 numbers"),
    (None, r"vertices\[13\] is \[12000, 19000, None\]: each vertex must be 3 numbers"),
    (1e300, r"vertex 13 \(used by CityObject 'b2'\) has height 1e\+298 m after transform\.scale"),
    (1_000_100, r"vertex 13 \(used by CityObject 'b2'\) has height 10001 m.*outside the plausible -1000 \.\. "
                r"10000 m"),
    (-100_001, r"vertex 13 .* has height -1000\.01 m"),
])
def test_a_vertex_not_finite_not_a_number_or_implausibly_high_is_refused(tmp_path, value, match):
    cj = _city()
    cj["vertices"][13][2] = value
    _refused_alike(_write(tmp_path, cj), match)


def test_an_implausible_x_is_refused_and_an_unused_bad_vertex_too(tmp_path):
    cj = _city()
    cj["vertices"][3][0] = 10**11
    _refused_alike(_write(tmp_path, cj), r"vertex 3 \(used by CityObject 'b1'\) is at x, y = 1e\+09")
    cj = _city()
    cj["vertices"].append([0, 0, math.nan])
    _refused_alike(_write(tmp_path, cj), r"vertex 16 \(used by no geometry\)")


def test_a_1e300_roof_leaves_no_inf_in_any_map(tmp_path):
    """The reproduction: z = 1e300 overflowed after an inf surface was cached; now the reading
    refuses it before any map, and a surface from any accepted file is finite."""
    cj = _city(scale=(1, 1, 1))
    cj["vertices"][13] = [110, 200, 1e300]
    _refused_alike(_write(tmp_path, cj), "height 1e\\+300 m")
    cj["vertices"][13] = [110, 200, 9999.0]       # the bound itself is accepted, and stays finite
    ds = build_surface(GRID, buildings_path=_write(tmp_path, cj), buildings_format="cityjson")
    assert np.isfinite(ds["surface"].values).all() and float(ds["surface"].max()) == pytest.approx(9999.0)


@pytest.mark.parametrize("kind, match", [
    ("solid_as_multisurface", r"CityObject 'b1': a Solid geometry's boundaries must nest 4 levels of arrays "
                              r"\(shells -> surfaces -> rings -> vertex indices, e\.g\. \[\[\[\[0, 1, 2\]\]\]\]\), "
                              r"this one nests 3"),
    ("multisurface_as_solid", r"CityObject 'b2': a MultiSurface geometry's boundaries nest deeper than 3 levels"),
    ("multisolid_as_solid", r"CityObject 'b1': a MultiSolid geometry's boundaries must nest 5 levels.*nests 4"),
    ("float_index", r"CityObject 'b2' \(MultiSurface\): vertex index 9\.5 is not an integer"),
    ("string_index", r"CityObject 'b2' \(MultiSurface\): vertex index 9 is not an integer"),
    ("surface_without_ring", r"CityObject 'b2': a MultiSurface geometry's boundaries must nest 3 levels.*"
                             r"nests 2 to 3 \(a surface with no ring\?\)"),
    ("boundaries_missing", r"CityObject 'b2': a MultiSurface geometry's boundaries must nest 3 levels"),
    ("semantics_short", r"CityObject 'b2': a MultiSurface geometry's semantics values must mirror the boundaries"),
    ("semantics_value", r"CityObject 'b2': a MultiSurface geometry's semantics value 7 is not an index into its 3"),
    ("lod", r"CityObject 'b2': lod 'LOD2' is not a level of detail"),
    ("terrain_height", r"CityObject 'b2': attributes\.TerrainHeight nan is not a height"),
])
def test_boundaries_nested_wrong_or_holding_non_integers_are_refused_with_the_expected_depth(tmp_path, kind, match):
    cj = _city()
    g1 = cj["CityObjects"]["b1"]["geometry"][0]
    g2 = cj["CityObjects"]["b2"]["geometry"][0]
    if kind == "solid_as_multisurface":
        g1["boundaries"] = g1["boundaries"][0]        # the reproduction (TypeError traceback before)
        g1.pop("semantics")
    elif kind == "multisurface_as_solid":
        g2["boundaries"] = [g2["boundaries"]]
        g2.pop("semantics")
    elif kind == "multisolid_as_solid":
        g1["type"] = "MultiSolid"
        g1.pop("semantics")
    elif kind == "float_index":
        g2["boundaries"][0][0][1] = 9.5
    elif kind == "string_index":
        g2["boundaries"][0][0][1] = "9"
    elif kind == "surface_without_ring":
        g2["boundaries"][2] = []
    elif kind == "boundaries_missing":
        g2.pop("boundaries")
    elif kind == "semantics_short":
        g2["semantics"]["values"] = [0, 1]
    elif kind == "semantics_value":
        g2["semantics"]["values"][1] = 7
    elif kind == "lod":
        g2["lod"] = "LOD2"
    elif kind == "terrain_height":
        cj["CityObjects"]["b2"]["attributes"] = {"TerrainHeight": math.nan}
    _refused_alike(_write(tmp_path, cj), match)


def test_null_semantics_values_mean_no_semantic_type(tmp_path):
    """``null`` values (per surface, or a whole shell) are valid CityJSON: untyped faces, read by
    their normals (the roof still faces up)."""
    cj = _city()
    cj["CityObjects"]["b1"]["geometry"][0]["semantics"]["values"] = [None]
    cj["CityObjects"]["b2"]["geometry"][0]["semantics"]["values"] = [None, None, 2, 2, 2, None]
    ds = build_surface(GRID, buildings_path=_write(tmp_path, cj), buildings_format="cityjson")
    assert float(ds["surface"].max()) == pytest.approx(20.0)
    assert float(ds["surface"].sel(x=95.5, y=195.5, method="nearest")) == pytest.approx(14.0)


# ------------------------------------------------------------------ geometry templates
# template: the unit cube (0..1)^3, MultiSurface with semantics; the instance maps (u, v, w) to
# (-8 v + 2, 10 u + 3, 12 w + 0.5) + the reference point (100, 200, 4) (integers 10000, 20000, 400
# under transform.scale 0.01): x 94..102, y 203..213, ground 4.5 m, roof 16.5 m
M = [0, -8, 0, 2,
     10, 0, 0, 3,
     0, 0, 12, 0.5,
     0, 0, 0, 1]


def _templated_city(matrix=M, template=0, ref=16, **over):
    cj = _city()
    cj["vertices"].append([10000, 20000, 400])        # vertex 16: the reference point
    TV, tf, ts = _box(0, 0, 1, 1, 0, 1)
    cj["geometry-templates"] = {"templates": [{"type": "MultiSurface", "lod": "2.2", "boundaries": tf,
                                               "semantics": ts}], "vertices-templates": TV}
    cj["CityObjects"]["tower"] = {"type": "Building", "geometry": [
        {"type": "GeometryInstance", "template": template, "boundaries": [ref], "transformationMatrix": matrix}]}
    for k, v in over.items():
        if v is None:
            cj["geometry-templates"].pop(k)
        else:
            cj["geometry-templates"][k] = v
    return cj


def test_a_geometry_instance_is_placed_by_its_matrix_and_reference_point(tmp_path):
    p = _write(tmp_path, _templated_city())
    ds = build_surface(GRID, buildings_path=p, buildings_format="cityjson")
    s, bid = ds["surface"], ds["building_id"]
    # hand-computed: roof 4 + 0.5 + 12 = 16.5 m over x 94..102, y 203..213
    assert float(s.sel(x=98.5, y=208.5, method="nearest")) == pytest.approx(16.5)
    X, Y = np.meshgrid(ds["x"].values, ds["y"].values)
    inside = (X > 94.5) & (X < 101.5) & (Y > 203.5) & (Y < 212.5)
    np.testing.assert_allclose(s.values[inside], 16.5, atol=1e-4)
    tower = list(ds["building_height_source"].values).index("cityjson:tower")
    cells = bid.values == tower
    assert cells[inside].all()
    assert not cells[(X < 93) | (X > 103) | (Y < 202) | (Y > 214)].any()
    assert float(ds["building_height_m"].values[tower]) == pytest.approx(16.5, abs=1e-4)
    ins = inspect_target(p)
    assert ins.ok and not ins.problems
    assert "1 GeometryInstance(s) placed from geometry-templates" in ins.facts["checked"]
    assert ins.data["cityjson_heights_m"][1] == pytest.approx(20.0)      # b2 still the tallest
    assert ins.data["cityjson"]["geometry_instances"] == 1


@pytest.mark.parametrize("kw, match", [
    ({"template": 3}, r"CityObject 'tower': GeometryInstance template 3 is not an index into the 1 "),
    ({"ref": 17}, r"CityObject 'tower': GeometryInstance reference point index 17 is not a vertex of the file "
                  r"\(0 \.\. 16, 17 vertices\)"),
    ({"ref": [16]}, r"GeometryInstance boundaries \[\[16\]\] must be one vertex index"),
    ({"matrix": M[:15]}, r"transformationMatrix must be 16 finite numbers"),
    ({"matrix": M[:14] + [math.nan, 1]}, r"transformationMatrix must be 16 finite numbers"),
    ({"matrix": M[:12] + [0, 0, 1, 1]}, r"transformationMatrix's last row is \[0\.0, 0\.0, 1\.0, 1\.0\]"),
    ({"matrix": M[:10] + [0] + M[11:]}, r"transformationMatrix is singular"),
    ({"templates": None}, r"CityObject 'tower' uses a GeometryInstance but the file has no geometry-templates"),
    ({"vertices-templates": [[0, 0, 0]]}, r"geometry-templates\.templates\[0\] \(MultiSurface\): vertex index 3 "
                                          r"is past the end of the 1 vertices-templates"),
    ({"vertices-templates": [[0, 0, math.inf]] * 8}, r"vertices-templates\[0\] is \[0\.0, 0\.0, inf\]"),
    ({"templates": [{"type": "Solid", "boundaries": [[[0, 1, 2]]]}]},
     r"geometry-templates\.templates\[0\]: a Solid geometry's boundaries must nest 4"),
    ({"templates": [{"type": "GeometryInstance"}]}, r"geometry-templates\.templates\[0\] has type 'GeometryInstance'"),
    ({"matrix": [1e6, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1e6, 0, 0, 0, 0, 1]},
     r"a vertex of the GeometryInstance of CityObject 'tower' has height 1e\+06 m, outside"),
])
def test_a_malformed_template_or_instance_is_refused(tmp_path, kw, match):
    args = {k: v for k, v in kw.items() if k in ("matrix", "template", "ref")}
    over = {k: v for k, v in kw.items() if k not in args}
    _refused_alike(_write(tmp_path, _templated_city(**args, **over)), match)


# ------------------------------------------------------------------ counted warnings
def test_every_coercion_is_a_counted_warning_in_inspect_and_in_the_surface(tmp_path):
    cj = _city()
    del cj["transform"]                                 # 2.0 without transform: read as real coordinates
    cj["vertices"] = (np.asarray(cj["vertices"]) * 0.01).tolist()
    objs = cj["CityObjects"]
    objs["b1"]["geometry"].append({"type": "Spline", "lod": "3", "boundaries": [0, 1]})
    objs["b2"]["geometry"][0]["boundaries"].append([[0, 1]])       # a 2-vertex face
    objs["b2"]["geometry"][0]["semantics"]["values"].append(None)
    objs["ghost"] = {"type": "Building", "attributes": {}}          # no geometry, no parts
    objs["parent"] = {"type": "Building", "children": ["part"]}     # its part has the geometry: fine
    objs["part"] = {"type": "BuildingPart", "parents": ["parent"], "geometry": [
        {"type": "MultiSurface", "lod": 1, "boundaries": objs["b2"]["geometry"][0]["boundaries"][:2]}]}
    p = _write(tmp_path, cj)
    doc = load_cityjson(p)
    assert doc.counts == {"missing_transform": 1, "unknown_geometry_types": 1, "buildings_without_surfaces": 1,
                          "degenerate_faces": 1}
    ins = inspect_target(p)
    assert ins.ok
    warns = [m for lv, k, m in ins.problems if lv == "warning" and k == "data.buildings"]
    assert warns == list(doc.warnings) and len(warns) == 4
    assert any("1 geometry of unknown type skipped: Spline x1 (e.g. 'b1')" in w for w in warns)
    assert any("1 Building(s) without any surface geometry" in w and "'ghost'" in w for w in warns)
    assert any("1 building face(s) with fewer than 3 vertices" in w for w in warns)
    assert any("no transform (required since CityJSON 1.1)" in w for w in warns)
    assert ins.data["cityjson"]["coercions"] == doc.counts
    ds = build_surface(GRID, buildings_path=p, buildings_format="cityjson")
    assert json.loads(ds.attrs["warnings"])[:4] == [f"data.buildings: {w}" for w in warns]
    assert float(ds["surface"].max()) == pytest.approx(20.0)        # the Spline did not stop b1


def test_not_cityjson_too_deep_or_not_an_object_is_one_data_error(tmp_path):
    p = tmp_path / "deep.city.json"
    p.write_text('{"type": "CityJSON", "CityObjects": {}, "vertices": ' + "[" * 100_000 + "]" * 100_000 + "}")
    _refused_alike(p, "not valid CityJSON")
    cj = _city()
    cj["CityObjects"]["b2"] = ["not", "an", "object"]
    _refused_alike(_write(tmp_path, cj), r"CityObject 'b2' is not an object")
    cj = _city()
    cj["CityObjects"]["b2"]["parents"] = "b1"
    _refused_alike(_write(tmp_path, cj), r"CityObject 'b2': parents must be an array")
