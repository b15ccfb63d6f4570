"""The command line: the main job on the default scenario and one-line errors with exit code 2."""

from __future__ import annotations

import copy
import json

import pytest
import rasterio
import yaml
from click.testing import CliRunner

from skyroute.pipeline.cli import main
from skyroute.pipeline.settings import scenario_paths


@pytest.fixture
def runner():
    return CliRunner()


def _write_variant(tmp_path, edit, name="helsinki-medical"):
    p = scenario_paths()[name]
    raw = copy.deepcopy(yaml.safe_load(p.read_text()))
    # keep data paths valid from the temporary folder
    raw = json.loads(json.dumps(raw, default=str).replace("../data/", str(p.parent.parent / "data") + "/"))
    edit(raw)
    out = tmp_path / "variant.yaml"
    out.write_text(yaml.safe_dump(raw))
    return out


def test_help_reads_well(runner):
    res = runner.invoke(main, ["--help"])
    assert res.exit_code == 0
    for cmd in ("run", "scenarios", "cache"):
        assert cmd in res.output
    assert "helsinki-medical" in res.output


def test_scenarios_lists_one_line_each(runner):
    res = runner.invoke(main, ["scenarios"])
    assert res.exit_code == 0
    lines = res.output.strip().splitlines()
    assert len(lines) == len(scenario_paths())
    assert lines[0].startswith("* helsinki-medical")


def test_run_default_scenario_writes_outputs(runner, tmp_path):
    out = tmp_path / "out"
    args = ["run", "--out", str(out), "--cache-dir", str(tmp_path / "c"), "--quiet"]
    res = runner.invoke(main, args)
    assert res.exit_code == 0, res.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scenario"] == "helsinki-medical"
    assert "surface" in summary["stages_run"] and summary["cache_hits"] == 0
    with rasterio.open(out / "surface.tif") as src:
        assert src.crs.to_epsg() == 32635 and src.res == (2.0, 2.0)
        assert src.read(1).max() == pytest.approx(70.0)
    assert (out / "figures" / "surface.png").stat().st_size > 10_000
    assert (out / "datasets" / "surface.zarr").resolve().is_dir()
    res2 = runner.invoke(main, args)
    assert res2.exit_code == 0
    summary2 = json.loads((out / "summary.json").read_text())
    assert summary2["stages_run"] == [] and summary2["cache_hits"] == len(summary2["stages"])
    ls = runner.invoke(main, ["cache", "ls", "--cache-dir", str(tmp_path / "c")])
    assert "surface" in ls.output and "helsinki-medical" in ls.output
    clear = runner.invoke(main, ["cache", "clear", "--cache-dir", str(tmp_path / "c")])
    assert clear.exit_code == 0 and "removed" in clear.output


@pytest.mark.parametrize("edit, message", [
    (lambda r: r["mission"]["start"].update(lon=25.5), "mission.start: point"),
    (lambda r: r["aoi"].update(resolution_m=-1), "aoi.resolution_m: Input should be greater than 0"),
    (lambda r: r["data"]["buildings"].update(path="/nonexistent/city.osm.pbf"), "data.buildings.path: data file not found: /nonexistent/city.osm.pbf"),
    (lambda r: r["aoi"].update(crs="EPSG:0"), "aoi: cannot resolve CRS 'EPSG:0'"),
    (lambda r: r["aoi"].update(bounds_lonlat=[24.0, 60.0, 24.01, 60.01]) or r["mission"]["start"].update(lon=24.005, lat=60.005)
     or r["mission"]["goal"].update(lon=24.006, lat=60.006), "does not intersect any building"),
    (lambda r: r["mission"]["start"].update(alt_agl_m=10), "mission.start: altitude 10 m above ground is inside a building"),
])
def test_bad_input_is_one_line_exit_2(runner, tmp_path, edit, message):
    path = _write_variant(tmp_path, edit)
    res = runner.invoke(main, ["run", str(path), "--cache-dir", str(tmp_path / "c"), "--out", str(tmp_path / "o"), "-q"])
    assert res.exit_code == 2, res.output
    assert message in res.output
    assert "Traceback" not in res.output


def test_unknown_scenario_exit_2(runner):
    res = runner.invoke(main, ["run", "atlantis"])
    assert res.exit_code == 2
    assert res.output.strip() == ("error: unknown scenario 'atlantis'; known scenarios: helsinki-medical, "
                                  "helsinki-traffic, monaco-helipads, rotterdam-canyon, san-gabriel-mountains")
