"""OSM building heights read strictly (issue 34): ``;``-separated values, units, and tags that
are no heights (``-5``, ``1e9``, ``nan``, ``inf``, ``building:levels=1e6``) never silently become
a default lower than the building may be; each such building is a counted warning naming its OSM
id, in the surface stage's warnings and in ``skyroute inspect`` before any work."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from pyproj import CRS, Transformer

from skyroute.pipeline.cli import main
from skyroute.stages.grid import Grid
from skyroute.stages.surface import (
    DEFAULT_HEIGHT_BY_TYPE_M,
    MAX_BUILDING_HEIGHT_M,
    MAX_BUILDING_LEVELS,
    STOREY_HEIGHT_M,
    build_surface,
    osm_building_footprints,
    osm_building_height,
    parse_height_m,
)

FT = 0.3048
UTM = CRS.from_epsg(32633)
#: (way id, tags, expected height [m]) of the test extract: 8 buildings in a row, 30 m apart.
BUILDINGS = [
    (101, {"building": "yes", "height": "12;55"}, 55.0),
    (102, {"building": "yes", "height": "-5"}, 10.0),
    (103, {"building": "yes", "height": "1e9"}, MAX_BUILDING_HEIGHT_M),
    (104, {"building": "yes", "height": "nan", "building:levels": "20"}, 20 * STOREY_HEIGHT_M),
    (105, {"building": "yes", "height": "inf"}, MAX_BUILDING_HEIGHT_M),
    (106, {"building": "yes", "building:levels": "1e6"}, MAX_BUILDING_LEVELS * STOREY_HEIGHT_M),
    (107, {"building": "yes", "building:levels": "-3"}, 10.0),
    (108, {"building": "house", "height": "40'"}, 40 * FT),
]
BAD_IDS = [102, 103, 104, 105, 106, 107]


def test_height_values_and_units_osm_allows():
    assert parse_height_m("12;55") == 55.0                     # several values: the highest
    assert parse_height_m("55;12") == 55.0
    assert parse_height_m("12 m") == 12.0
    assert parse_height_m("40'") == pytest.approx(40 * FT)
    assert parse_height_m("12 ft") == pytest.approx(12 * FT)
    assert parse_height_m("3'6\"") == pytest.approx(3.5 * FT)
    assert parse_height_m("12,5") == 12.5
    assert parse_height_m("tall") is None
    assert parse_height_m("1,234.5") is None                   # ambiguous separators: not guessed
    problems: list[str] = []
    assert osm_building_height({"building": "yes", "height": "12;55"}, problems=problems) == (55.0, "height")
    assert problems == []


@pytest.mark.parametrize(("tags", "height", "source", "said"), [
    ({"height": "-5"}, 10.0, "default*:yes", "height='-5' (not above 0)"),
    ({"height": "0"}, 10.0, "default*:yes", "not above 0"),
    ({"height": "nan"}, 10.0, "default*:yes", "height='nan' (not a number"),
    ({"height": "1e9"}, MAX_BUILDING_HEIGHT_M, "height", "above 1000 m: taken as 1000 m"),
    ({"height": "inf"}, MAX_BUILDING_HEIGHT_M, "height", "above 1000 m"),
    ({"height": "12;abc;55"}, 55.0, "height", "height='12;abc;55' (not a number"),
    ({"building:levels": "1e6"}, 600.0, "levels", "above 200 levels: taken as 200 levels"),
    ({"building:levels": "-3"}, 10.0, "default:yes", "building:levels='-3' (not above 0)"),
    ({"building:levels": "5", "roof:levels": "nan"}, 15.0, "levels", "roof:levels='nan'"),
    # a broken height gives way to the HIGHEST of the levels' height and the type's default
    ({"height": "nan", "building:levels": "1"}, 10.0, "default*:yes", "height='nan'"),
    ({"height": "nan", "building:levels": "20"}, 60.0, "levels*", "height='nan'"),
    ({"building": "cathedral", "height": "-1", "building:levels": "2"}, DEFAULT_HEIGHT_BY_TYPE_M["cathedral"],
     "default*:cathedral", "height='-1'"),
])
def test_unusable_height_tags_are_conservative_and_said(tags, height, source, said):
    problems: list[str] = []
    h, src = osm_building_height({"building": "yes", **tags}, problems=problems)
    assert (h, src) == (pytest.approx(height), source)
    assert len(problems) == 1 and said in problems[0], problems


def _extract(tmp_path: Path) -> tuple[Path, Grid]:
    """An OSM XML extract with :data:`BUILDINGS` (20 x 20 m squares, 30 m apart) and its grid."""
    grid = Grid.from_bounds(UTM, 500000, 5000000, 500260, 5000040, 2.0)
    to_ll = Transformer.from_crs(UTM, 4326, always_xy=True)
    nodes, ways = [], []
    nid = 1
    for k, (wid, tags, _) in enumerate(BUILDINGS):
        x0, y0 = 500010 + 30 * k, 5000010
        refs = []
        for x, y in ((x0, y0), (x0 + 20, y0), (x0 + 20, y0 + 20), (x0, y0 + 20)):
            lon, lat = to_ll.transform(x, y)
            nodes.append(f'  <node id="{nid}" version="1" lat="{lat:.9f}" lon="{lon:.9f}"/>')
            refs.append(nid)
            nid += 1
        nds = "".join(f'<nd ref="{r}"/>' for r in [*refs, refs[0]])
        tg = "".join(f'<tag k="{k_}" v="{v}"/>' for k_, v in tags.items())
        ways.append(f'  <way id="{wid}" version="1">{nds}{tg}</way>')
    p = tmp_path / "heights.osm"
    p.write_text('<?xml version="1.0" encoding="UTF-8"?>\n<osm version="0.6" generator="test">\n'
                 + "\n".join(nodes + ways) + "\n</osm>\n")
    return p, grid


def test_the_surface_takes_the_conservative_heights_and_warns_with_the_way_ids(tmp_path):
    path, grid = _extract(tmp_path)
    problems: list[tuple[int, str]] = []
    ids, hs, _, _ = osm_building_footprints(path, problems=problems)
    assert dict(zip(ids, hs, strict=True)) == {w: pytest.approx(h) for w, _, h in BUILDINGS}
    assert [i for i, _ in problems] == BAD_IDS
    ds = build_surface(grid, buildings_path=path)
    # each building's cells: its height above the flat ground (the 12;55 one: 55 m, not 10 m)
    for k, (wid, _, h) in enumerate(BUILDINGS):
        r, c = (5000040 - 5000020) // 2, (500020 + 30 * k - 500000) // 2   # the footprint's centre cell
        assert ds["building_id"].values[r, c] >= 0
        assert int(ds["building_osm_id"].values[ds["building_id"].values[r, c]]) == wid
        assert float(ds["surface"].values[r, c]) == pytest.approx(h, rel=1e-6)
    warns = json.loads(ds.attrs["warnings"])
    assert len(warns) == 1
    assert warns[0].startswith(f"data.buildings: {len(BAD_IDS)} OSM building(s) with an unusable or implausible")
    for wid in BAD_IDS[:5]:
        assert f"way/relation {wid}:" in warns[0]
    assert "and 1 more" in warns[0]
    assert np.isfinite(ds["surface"].values).all()


def test_inspect_counts_the_coerced_height_tags_before_any_work(tmp_path):
    path, _ = _extract(tmp_path)
    res = CliRunner().invoke(main, ["inspect", str(path), "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.output)
    assert doc["osm"]["height_tags_coerced"] == len(BAD_IDS)
    assert doc["osm"]["height_tags_coerced_ids"] == BAD_IDS
    warn = [p for p in doc["problems"] if p["level"] == "warning" and "height tag" in p["message"]]
    assert len(warn) == 1 and warn[0]["key"] == "data.buildings"
    assert warn[0]["message"].startswith(f"{len(BAD_IDS)} OSM building(s)") and "way/relation 102:" in warn[0]["message"]
    res = CliRunner().invoke(main, ["inspect", str(path)])
    lines = [ln for ln in res.output.splitlines() if ln.startswith("warning: data.buildings:")]
    assert res.exit_code == 0 and len(lines) == 1 and "height='1e9'" in lines[0]
