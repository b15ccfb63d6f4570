"""The command line: the main job on the default scenario and one-line errors with exit code 2."""

from __future__ import annotations

import copy
import csv
import json
import os

import numpy as np
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


def listing(out) -> set[str]:
    """Every file and symlink under ``out`` (symlinked folders not followed), relative; a zarr
    store (a ``*.zarr`` folder) is one entry."""
    found = set()
    for root, dirs, files in os.walk(out):
        stores = [d for d in dirs if d.endswith(".zarr")]
        for name in files + stores + [d for d in dirs if os.path.islink(os.path.join(root, d))]:
            found.add(os.path.relpath(os.path.join(root, name), out).replace(os.sep, "/"))
        dirs[:] = [d for d in dirs if d not in stores]
    return found


def check_summary(out, command) -> dict:
    """summary.json's common fields; its file list is the folder's listing."""
    s = json.loads((out / "summary.json").read_text())
    assert s["schema_version"] == 1 and s["command"] == command
    assert isinstance(s["warnings"], list)
    assert set(s["files"]) == listing(out) and len(s["files"]) == len(set(s["files"]))
    return s


def test_stage_warnings_are_collected():
    import xarray as xr

    from skyroute.pipeline.graph import RunResult
    from skyroute.pipeline.outputs import stage_warnings
    from skyroute.pipeline.settings import load_scenario

    r = RunResult(load_scenario("helsinki-medical"))
    r.datasets["surface"] = xr.Dataset(attrs={"warnings": json.dumps(["surface: 3 nodata cells filled"])})
    r.datasets["environment"] = xr.Dataset()
    r.datasets["wind"] = xr.Dataset(attrs={"warnings": json.dumps(["wind: uniform", "surface: 3 nodata cells filled"])})
    assert stage_warnings(r) == ["surface: 3 nodata cells filled", "wind: uniform"]


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
    assert [ln.split()[1] for ln in lines if ln.startswith("*")] == ["helsinki-medical"]   # the default, marked
    assert not any(ln.startswith("!") for ln in lines)                                      # every scenario valid


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
    import warnings

    import xarray as xr

    with warnings.catch_warnings():          # the exported copies open without the unconsolidated warning
        warnings.simplefilter("error")
        assert float(xr.open_zarr(out / "datasets" / "surface.zarr")["surface"].max()) == pytest.approx(70.0)
    res2 = runner.invoke(main, args)
    assert res2.exit_code == 0
    summary2 = json.loads((out / "summary.json").read_text())
    assert summary2["stages_run"] == [] and summary2["cache_hits"] == len(summary2["stages"])
    check_summary(out, "run")
    assert summary2["plan"]["status"] == "flyable"
    # one summary line of the chosen plan, the numbers of summary.json and candidates.csv
    p = summary2["plan"]
    assert json.loads(res2.stdout)["plan"] == "flyable"
    loud = runner.invoke(main, [a for a in args if a != "--quiet"])
    assert loud.exit_code == 0
    line = [ln for ln in loud.output.splitlines() if ln.startswith("plan ")]
    assert line == [f"plan {p['label']}: f {p['f_m']:.1f} m, length {p['length_m']:.1f} m, energy "
                    f"{p['energy_Wh']:.2f} Wh, flight time {p['flight_time_s']:.1f} s, DOP < {p['dop_threshold']:g}"]
    row = next(r for r in csv.DictReader((out / "plan" / "candidates.csv").open()) if r["chosen"] == "true")
    assert row["label"] == p["label"] and float(row["f_m"]) == pytest.approx(p["f_m"], abs=0.05)
    assert float(row["energy_Wh"]) == pytest.approx(p["energy_Wh"], abs=0.005)
    wp = np.array([[float(r[k]) for k in ("x_m", "y_m", "z_m")] for r in csv.DictReader((out / "plan" / "waypoints.csv").open())])
    assert np.linalg.norm(np.diff(wp, axis=0), axis=1).sum() == pytest.approx(p["length_m"], abs=0.05)
    # no flyable candidate (A* cannot finish within a 4 ms cap): exit 3 after writing every
    # output, one reason line; the earlier plan's files are gone from the folder
    tiny = _write_variant(tmp_path, lambda r: r["planner"].update(time_budget_s=0.001))
    res3 = runner.invoke(main, ["run", str(tiny), "--out", str(out), "--cache-dir", str(tmp_path / "c")])
    assert res3.exit_code == 3, res3.output
    last = res3.output.strip().splitlines()[-1]
    assert last.startswith("no flyable plan: D=2: ") and last.count("no flyable plan") == 1
    assert "budget exhausted" in last and "within the budget" not in last
    s3 = check_summary(out, "run")
    assert s3["plan"]["status"] == "no_flyable_plan" and s3["plan"]["f_m"] is None
    assert [r.split(":")[0] for r in s3["plan"]["reasons"]] == ["D=2", "D=3", "D=4"]
    assert not (out / "plan" / "plan.geojson").exists() and (out / "plan" / "candidates.csv").is_file()
    # the other folder-writing commands, from the same cache
    for cmd in ("maps", "coverage"):
        r = runner.invoke(main, [cmd, "--out", str(tmp_path / cmd), "--cache-dir", str(tmp_path / "c"), "-q"])
        assert r.exit_code == 0, r.output
        check_summary(tmp_path / cmd, cmd)
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
    assert res.output.strip() == ("error: unknown scenario 'atlantis'; known scenarios: helsinki-contingency, helsinki-crosstown, "
                                  "helsinki-medical, helsinki-tactical, helsinki-traffic, monaco-helipads, rotterdam-canyon, "
                                  "rotterdam-tactical, san-gabriel-fixedwing, san-gabriel-fixedwing-local, san-gabriel-long, "
                                  "san-gabriel-mountains")
