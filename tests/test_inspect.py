"""`skyroute inspect` on each kind of input (issue 24): facts checked against the files read
with plain code, every problem one `error:` / `warning:` line naming the YAML key."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner

from skyroute.pipeline.cli import main
from skyroute.pipeline.settings import catalog_dir
from tests.test_own_city import _own_city_fixtures, _readme_yamls

CATALOG_DATA = catalog_dir() / "data"
CITY_SCENARIOS = ["helsinki-medical", "helsinki-crosstown", "helsinki-traffic", "helsinki-tactical", "helsinki-contingency",
                  "rotterdam-canyon", "rotterdam-tactical", "monaco-helipads"]


@pytest.fixture(scope="module")
def own(tmp_path_factory):
    d = _own_city_fixtures(tmp_path_factory.mktemp("own"))
    for name, text in _readme_yamls().items():
        (d / f"{name}.yaml").write_text(text)
    return d


def _inspect(*args):
    res = CliRunner().invoke(main, ["inspect", *map(str, args)])
    return res.exit_code, res.output


def _json(target):
    code, out = _inspect(target, "--json")
    return code, json.loads(out)


def test_inspect_rasters_heights_and_nodata_match_the_file(own):
    for name in ("dsm.tif", "ahn_tile.tif", "dem.tif"):
        code, doc = _json(own / name)
        assert code == 0, doc["problems"]
        with rasterio.open(own / name) as src:
            a = src.read(1, masked=True)
            b = src.bounds
        assert doc["raster_heights_m"] == pytest.approx([float(a.min()), float(a.max())], abs=1e-3)
        assert doc["raster_extent"] == pytest.approx([b.left, b.bottom, b.right, b.top])
        share = float(np.ma.getmaskarray(a).mean())
        assert doc["raster_nodata"]["share_of_pixels"] == pytest.approx(share, abs=1e-9)
    assert doc["raster_nodata"]["regions"] == 0
    code, doc = _json(own / "ahn_tile.tif")
    assert doc["raster_nodata"]["regions"] == 3 and doc["raster_nodata"]["regions_touching_edge"] == 2
    code, out = _inspect(own / "dem.tif")
    assert code == 0 and "samples at the pixel centres (AREA_OR_POINT=Area)" in out and "EPSG:32611" in out


def test_inspect_cityjson_counts_buildings_parts_and_stacked_grounds(own):
    code, doc = _json(own / "city.city.json")
    assert code == 0
    cj = json.loads((own / "city.city.json").read_text())
    types = [o["type"] for o in cj["CityObjects"].values()]
    assert doc["cityjson"]["buildings"] == types.count("Building") == 1
    assert doc["cityjson"]["building_parts"] == types.count("BuildingPart") == 2
    assert doc["cityjson"]["tin_relief"] is True and doc["cityjson"]["stacked_part_grounds"] == 1
    assert "TINRelief" in doc["facts"]["ground"]


def test_inspect_osm_counts_buildings(tmp_path):
    import osmium

    path = CATALOG_DATA / "monaco_2019-09-30.osm.pbf"
    code, doc = _json(path)
    assert code == 0
    n = sum(1 for o in osmium.FileProcessor(str(path)).with_areas()
            if o.is_area() and ("building" in o.tags or "building:part" in o.tags))
    assert doc["osm"]["buildings"] == n


@pytest.mark.parametrize("name", ["my-city-dsm", "my-city-lidar", "my-city-cityjson", "my-mountains-dem"])
def test_inspect_each_own_city_scenario(own, name):
    code, out = _inspect(own / f"{name}.yaml")
    assert code == 0, out
    assert "absolute heights           yes" in out or "absolute heights" in out
    code, doc = _json(own / f"{name}.yaml")
    assert doc["absolute_heights"]["pilot_files"]["plan.kml"] == "yes"
    assert doc["absolute_heights"]["pilot_files"]["intent.json"] == "yes"
    assert doc["landing_sites"]["count"] == 0 and "open ground" in " ".join(doc["facts"].values())


def _all_scenarios():
    from skyroute.pipeline.settings import scenario_paths

    return sorted(scenario_paths())


@pytest.mark.parametrize("name", _all_scenarios())
def test_every_shipped_scenario_has_absolute_heights_and_landing_sites(name):
    """Every shipped scenario can write plan.kml, plan.plan with a real home altitude and
    intent.json (absolute heights + almanacs); each rotorcraft city scenario also has at least
    two landing sites, the cheap check behind `skyroute fleet SCENARIO --missions 20 --seed 1`
    (the full run is tested on helsinki-medical in test_fleet_cli.py; all were run by hand)."""
    code, doc = _json(name)
    assert not [p for p in doc["problems"] if p["level"] == "error"], doc["problems"]
    ah = doc["absolute_heights"]
    assert ah["available"] and ah["pilot_files"]["plan.kml"] == "yes" and ah["pilot_files"]["intent.json"] == "yes"
    assert ah["pilot_files"]["plan.plan"] == "home altitude above mean sea level"
    if name in CITY_SCENARIOS:
        assert code == 0 and doc["landing_sites"]["count"] >= 2


def test_inspect_problems_name_the_key_to_change(own, tmp_path):
    import yaml

    doc = yaml.safe_load((own / "my-city-dsm.yaml").read_text())
    doc["aoi"]["bounds"] = [91170, 435690, 91420, 435920]          # 10 m west of the raster
    doc["data"]["surface"]["path"] = str(own / "dsm.tif")
    doc["data"]["almanacs"] = [str(own / "yuma.txt")]
    doc["data"].pop("ground")
    doc["data"]["buildings"] = None
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(doc))
    code, out = _inspect(p)
    assert code == 2
    lines = [ln for ln in out.splitlines() if ln.startswith(("error:", "warning:"))]
    assert any(ln.startswith("error: aoi.bounds: covers only") and "set aoi.bounds to [91180, 435690, 91420, 435920]"
               in ln for ln in lines), out
    assert any(ln.startswith("warning: data.ground: plan.kml and intent.json will not be written") for ln in lines)
    # nodata: error with holes under the AOI
    doc = yaml.safe_load((own / "my-city-lidar.yaml").read_text())
    doc["data"]["surface"]["nodata"] = "error"
    doc["data"]["surface"]["path"] = [str(own / "ahn_tile.tif")]
    doc["data"]["almanacs"] = [str(own / "yuma.txt")]
    p.write_text(yaml.safe_dump(doc))
    code, out = _inspect(p)
    assert code == 2 and any(ln.startswith("error: data.surface.nodata:") and "fill-max" in ln and "fill-nearest" in ln
                             for ln in out.splitlines())
    # a scenario that does not validate: its problems, each with its key
    doc["planner"] = {"weights": [0, 0, 0, 0]}
    doc["bogus"] = 1
    p.write_text(yaml.safe_dump(doc))
    code, out = _inspect(p)
    assert code == 2 and "error: bogus:" in out and "error: planner.weights:" in out
    code, out = _inspect(tmp_path / "nothing.xyz")
    assert code == 2 and out.startswith("error: ") and len(out.strip().splitlines()) == 1


def test_a_pilot_file_not_written_is_a_warning_on_stderr_and_in_the_report(own, tmp_path):
    """The CityJSON city without data.ground (NAP has no conversion here): plan.kml and
    intent.json are not written, said on stderr, in summary.json's warnings and in report.html."""
    import yaml

    doc = yaml.safe_load((own / "my-city-cityjson.yaml").read_text())
    doc["data"].pop("ground")
    doc["data"]["buildings"]["path"] = str(own / "city.city.json")
    doc["data"]["almanacs"] = [str(own / "yuma.txt")]
    p = tmp_path / "no-ground.yaml"
    p.write_text(yaml.safe_dump(doc))
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["plan", str(p), "--out", str(out), "--cache-dir", str(tmp_path / "c"), "-q"])
    assert res.exit_code == 0, res.output
    assert "warning: plan.kml not written (nor intent.json; plan.plan gets home altitude 0 m): " in res.output
    assert not (out / "plan.kml").exists() and not (out / "intent.json").exists()
    s = json.loads((out / "summary.json").read_text())
    assert any(w.startswith("plan.kml not written") and "data.ground" in w for w in s["warnings"])
    res = CliRunner().invoke(main, ["report", str(out), "--no-maps"])
    assert res.exit_code == 0, res.output
    assert "plan.kml not written" in (out / "report.html").read_text()
