"""Input messages: one clear line that says what is wrong and how to fix it."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
import yaml
from click.testing import CliRunner
from rasterio.transform import from_origin

from skyroute.pipeline.cli import main
from skyroute.pipeline.errors import ScenarioError
from skyroute.pipeline.settings import load_scenario, parse_scenario


def test_yaml_syntax_error_names_file_line_and_column(tmp_path):
    f = tmp_path / "broken.yaml"
    f.write_text("name: x\naoi: [1,\n")
    with pytest.raises(ScenarioError, match=r"(?s)broken\.yaml.*not valid YAML at line 3, column 1: expected the node"):
        load_scenario(f)


@pytest.mark.parametrize(("key", "value", "msg"), [("lat", 95.0, r"latitude 95 out of \[-90, 90\]"),
                                                   ("lon", -190.0, r"longitude -190 out of \[-180, 180\]")])
def test_mission_point_out_of_range_is_named(key, value, msg):
    sc = load_scenario("helsinki-medical")
    raw = yaml.safe_load(sc.source_path.read_text())
    raw["mission"]["start"][key] = value
    with pytest.raises(ScenarioError, match=r"mission\.start: " + msg):
        parse_scenario(raw, base=sc.source_path.parent)


def _tif(path, crs, res):
    a = np.random.default_rng(0).random((40, 40), dtype=np.float32) * 10
    with rasterio.open(path, "w", driver="GTiff", width=40, height=40, count=1, dtype="float32", crs=crs,
                       transform=from_origin(24.9 if crs == "EPSG:4326" else 385000, 60.2 if crs == "EPSG:4326"
                                             else 6672000, res, res)) as d:
        d.write(a, 1)


def test_visibility_height_refuses_a_geographic_surface_and_creates_the_out_folder(tmp_path):
    geo, utm = tmp_path / "geo.tif", tmp_path / "utm.tif"
    _tif(geo, "EPSG:4326", 1e-4)
    _tif(utm, "EPSG:32635", 1.0)
    r = CliRunner().invoke(main, ["visibility-height", "--surface", str(geo), "--az-deg", "10", "--el-deg", "20",
                                  "--out", str(tmp_path / "vh.tif")])
    assert r.exit_code == 2 and "not a projected CRS in metres: reproject it first" in r.output
    out = tmp_path / "new" / "folder" / "vh.tif"
    r = CliRunner().invoke(main, ["visibility-height", "--surface", str(utm), "--az-deg", "10", "--el-deg", "20",
                                  "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert out.is_file()


def test_catalog_readme_lists_every_scenario_key():
    from pathlib import Path

    from skyroute.pipeline.settings_reference import reference_markdown, scenario_keys

    readme = Path(__file__).resolve().parents[1] / "catalogs" / "README.md"
    assert readme.read_text() == reference_markdown(), (
        "catalogs/README.md is out of date: python -m skyroute.pipeline.settings_reference > catalogs/README.md")
    keys = [k for k, *_ in scenario_keys()]
    for k in ("mission.start.alt_agl_m", "planner.weights", "traffic.intruders[].waypoints", "gnss.window_min"):
        assert k in keys


def test_unknown_key_points_to_the_key_reference():
    sc = load_scenario("helsinki-medical")
    raw = yaml.safe_load(sc.source_path.read_text())
    raw["planner"]["wieghts"] = [1, 0, 0, 0]
    with pytest.raises(ScenarioError, match=r"planner\.wieghts: unknown key .*catalogs/README\.md"):
        parse_scenario(raw, base=sc.source_path.parent)


def test_python_warnings_become_one_clean_line(tmp_path):
    import subprocess
    import sys

    code = ("import sys, warnings; from skyroute.pipeline import cli; cli._setup_logging(0);"
            "warnings.warn('almanac.txt: unhealthy satellites excluded (health != 0): G05', UserWarning)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stderr.strip() == "warning: almanac.txt: unhealthy satellites excluded (health != 0): G05"


@pytest.mark.parametrize("bad", ["/proc/skyroute-out", "under-a-file/out"])
def test_unwritable_out_is_refused_before_any_work(tmp_path, bad):
    (tmp_path / "under-a-file").write_text("a file, not a folder")
    out = bad if bad.startswith("/") else str(tmp_path / bad)
    for cmd in (["run"], ["plan"], ["maps"], ["coverage"]):
        r = CliRunner().invoke(main, [*cmd, "--out", out, "--cache-dir", str(tmp_path / "cache")])
        assert r.exit_code == 2, (cmd, r.output)
        assert r.output.startswith(f"error: cannot write to --out {out}: ") and "choose a folder" in r.output
        assert not (tmp_path / "cache").exists()  # refused before any stage ran


def test_run_outputs_are_copies_that_survive_cache_clear(tmp_path):
    import json

    import xarray as xr

    out, cache = tmp_path / "out", tmp_path / "cache"
    args = ["run", "--stage", "surface", "--out", str(out), "--cache-dir", str(cache), "-q"]
    assert CliRunner().invoke(main, args).exit_code == 0
    store = out / "datasets" / "surface.zarr"
    assert store.is_dir() and not store.is_symlink()
    want = xr.open_zarr(store)["surface"].load()
    mtime = store.stat().st_mtime_ns
    assert CliRunner().invoke(main, args).exit_code == 0  # warm: the copy is reused
    assert store.stat().st_mtime_ns == mtime
    assert CliRunner().invoke(main, ["cache", "clear", "--cache-dir", str(cache)]).exit_code == 0
    xr.testing.assert_identical(xr.open_zarr(store)["surface"].load(), want)
    assert "datasets/surface.zarr" in json.loads((out / "summary.json").read_text())["files"]
    # --link: symlinks into the cache, as an explicit choice
    assert CliRunner().invoke(main, [*args, "--link"]).exit_code == 0
    assert store.is_symlink() and store.resolve().is_relative_to(cache.resolve())
