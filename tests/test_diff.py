"""``skyroute diff``: hand-made output folders whose differences are known by construction, the
raster difference against a per-cell loop, the errors, and one real pair (the same run twice
through one cache: no differences)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import rasterio
import xarray as xr
import yaml
from click.testing import CliRunner
from rasterio.transform import from_origin

from skyroute.pipeline.cli import main
from skyroute.pipeline.diff import diff_folders, format_diff, raster_difference
from skyroute.pipeline.settings import scenario_paths

PLAN = {"status": "flyable", "label": "D=2", "dop_threshold": 2.0, "f_m": 100.0, "C_l_m": 40.0, "C_r_m": 20.0,
        "C_d_m": 10.0, "C_e_m": 30.0, "length_m": 40.0, "energy_Wh": 10.0, "flight_time_s": 50.0, "reasons": []}
CANDIDATES = [
    {"label": "D=2", "dop_threshold": "2.00", "C_l_m": "40.0", "C_r_m": "20.0", "C_d_m": "10.0", "C_e_m": "30.0",
     "f_m": "100.0", "flyable": "true", "max_sigma_p_m": "1.200", "energy_Wh": "10.00", "flight_time_s": "50.0",
     "compute_time_s": "3.10", "chosen": "true", "reasons": ""},
    {"label": "D=4", "dop_threshold": "4.00", "C_l_m": "41.0", "C_r_m": "21.0", "C_d_m": "11.0", "C_e_m": "31.0",
     "f_m": "104.0", "flyable": "true", "max_sigma_p_m": "1.300", "energy_Wh": "10.10", "flight_time_s": "51.0",
     "compute_time_s": "2.00", "chosen": "false", "reasons": ""},
]
STAGES = [{"name": "surface", "key": "s1", "cache_hit": False, "seconds": 4.0},
          {"name": "plan", "key": "p1", "cache_hit": False, "seconds": 9.0}]
FLY = {"outcome": "goal", "reason": "", "n_replannings": 2, "chosen_levels": ["1", "2"], "flight_time_s": 106.0,
       "length_m": 900.0, "energy_Wh": 40.0, "t_rep_s": 5.0, "tick_s": 0.1, "seed": 0, "dop_threshold": 2.0,
       "replannings": [{"replanning": 0, "event": "intruder a", "chosen_level": "1", "levels_tried": ["1", "2", "3"],
                        "levels_flyable": ["1", "2", "3"], "compute_s": 0.5, "f_m": 2000.0},
                       {"replanning": 1, "event": "intruder b", "chosen_level": "2", "levels_tried": ["1", "2", "3"],
                        "levels_flyable": ["2", "3"], "compute_s": 0.4, "f_m": 1200.0}],
       "min_separation": [{"id": "a", "min_distance_m": 60.5}, {"id": "b", "min_distance_m": 16.5}]}
NAVSIM = {"runs": 50, "epochs": 891, "seed": 0, "source": "plan", "surface_uncertainty_m": 1.0,
          "containment": {"proposed": {"1sigma": 0.66, "2sigma": 0.97, "3sigma": 0.99},
                          "weak": {"1sigma": 0.56, "2sigma": 0.92, "3sigma": 0.98}},
          "proposed_beats_weak": 0.43, "proposed": {"rms_error_m": 1.5}, "weak": {"rms_error_m": 1.7}}


def _raster(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0, 30, (10, 12))


def _folder(path: Path, command: str = "run", *, plan=None, candidates=None, stages=None, fly=None, navsim=None,
            rasters: dict[str, np.ndarray] | None = None, tif: np.ndarray | None = None, extra_files=()) -> Path:
    """A folder laid out as skyroute writes it (summary.json, plan/candidates.csv,
    datasets/maps.zarr with (y, x) rasters, surface.tif)."""
    path.mkdir(parents=True)
    files = ["summary.json", *extra_files]
    doc = {"schema_version": 1, "command": command, "warnings": [], "scenario": "hand-made", "seconds": 1.0,
           "crs": "EPSG:32635", "grid": {"nx": 12, "ny": 10, "resolution_m": 2.0, "bounds": [0, 0, 24, 20]},
           "stages": stages if stages is not None else STAGES}
    for name, sec in (("plan", plan), ("fly", fly), ("navsim", navsim)):
        if sec is not None:
            doc[name] = sec
    if candidates is not None:
        (path / "plan").mkdir()
        with open(path / "plan" / "candidates.csv", "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(candidates[0]))
            w.writeheader()
            w.writerows(candidates)
        files.append("plan/candidates.csv")
    if rasters is not None:
        y = 19.0 - 2.0 * np.arange(10)
        x = 1.0 + 2.0 * np.arange(12)
        ds = xr.Dataset({k: (("y", "x"), v, {"units": "m"}) for k, v in rasters.items()}, coords={"y": y, "x": x})
        ds["n_sites"] = ("site", np.arange(3))                    # not a raster: never compared
        (path / "datasets").mkdir()
        ds.to_zarr(path / "datasets" / "maps.zarr", consolidated=False)
        files.append("datasets/maps.zarr")
    if tif is not None:
        with rasterio.open(path / "surface.tif", "w", driver="GTiff", height=tif.shape[0], width=tif.shape[1], count=1,
                           dtype="float64", crs="EPSG:32635", transform=from_origin(0, 20, 2, 2), nodata=-9999.0) as dst:
            dst.write(np.where(np.isnan(tif), -9999.0, tif), 1)
        files.append("surface.tif")
    for f in extra_files:
        (path / f).write_text("x")
    doc["files"] = sorted(files)
    (path / "summary.json").write_text(json.dumps(doc))
    return path


def _items(res, section):
    return {c.item: c for c in res.by_section(section)}


def _cell_loop(a: np.ndarray, b: np.ndarray) -> tuple[float, int]:
    """The definition, one cell at a time: equal values, NaN against NaN and the same infinity are
    unchanged; a NaN or infinity against anything else is a change of infinite size."""
    worst, n = 0.0, 0
    for x, y in zip(a.ravel().tolist(), b.ravel().tolist(), strict=True):
        if (math.isnan(x) and math.isnan(y)) or x == y:
            continue
        n += 1
        worst = max(worst, abs(y - x) if math.isfinite(x) and math.isfinite(y) else math.inf)
    return worst, n


def test_raster_difference_against_a_cell_loop():
    rng = np.random.default_rng(3)
    a = rng.uniform(-5, 5, (7, 9))
    b = a + np.where(rng.random(a.shape) < 0.3, rng.uniform(-2, 2, a.shape), 0.0)
    a[0, 0] = b[0, 0] = np.nan                 # NaN on both sides: equal
    a[1, 1] = b[1, 1] = np.inf                 # the same infinity: equal
    worst, n = _cell_loop(a, b)
    assert 0 < n < a.size and math.isfinite(worst)
    assert raster_difference(a, b) == (pytest.approx(worst), n)
    b[2, 2] = np.nan                           # a value against NaN
    b[3, 3] = -np.inf                          # a value against an infinity
    assert raster_difference(a, b) == _cell_loop(a, b) and _cell_loop(a, b)[0] == math.inf
    assert raster_difference(a, a) == (0.0, 0)
    assert raster_difference(a.astype(np.float32), a.astype(np.float32)) == (0.0, 0)


def test_known_differences(tmp_path):
    ra, ta = {"surface": _raster(0), "floor": _raster(1)}, _raster(2)
    rb = {k: v.copy() for k, v in ra.items()}
    rb["surface"][2, 3] += 2.5
    rb["surface"][4, 5] -= 1.0
    rb["surface"][9, 11] += 0.5
    ra["floor"][0, 0] = rb["floor"][0, 0] = np.nan          # equal
    rb["floor"][5, 5] = np.nan                               # changed
    tb = ta.copy()
    tb[0, :4] += 0.75
    plan_b = {**PLAN, "label": "D=3", "dop_threshold": 3.0, "f_m": 103.5, "C_r_m": 23.5, "energy_Wh": 10.25}
    cand_b = [dict(CANDIDATES[0], C_r_m="23.5", f_m="103.5", compute_time_s="9.99"),
              dict(CANDIDATES[1], flyable="false", reasons="coverage floor above the ceiling"),
              dict(CANDIDATES[1], label="D=5")]
    stages_b = [dict(STAGES[0], cache_hit=True, seconds=0.1), dict(STAGES[1], key="p2", seconds=1.0)]
    fly_b = {**FLY, "outcome": "landed", "chosen_levels": ["1", "3"], "energy_Wh": 41.5,
             "replannings": [FLY["replannings"][0], {**FLY["replannings"][1], "chosen_level": "3", "compute_s": 9.0}],
             "min_separation": [{"id": "a", "min_distance_m": 60.5}, {"id": "b", "min_distance_m": 14.0}]}
    nav_b = {**NAVSIM, "containment": {"proposed": {"1sigma": 0.66, "2sigma": 0.97, "3sigma": 0.95},
                                       "weak": NAVSIM["containment"]["weak"]}}
    a = _folder(tmp_path / "a", plan=PLAN, candidates=CANDIDATES, fly=FLY, navsim=NAVSIM, rasters=ra, tif=ta,
                extra_files=["old.png"])
    b = _folder(tmp_path / "b", plan=plan_b, candidates=cand_b, stages=stages_b, fly=fly_b, navsim=nav_b, rasters=rb,
                tif=tb, extra_files=["new.png"])
    res = diff_folders(a, b)

    plan = _items(res, "plan")
    assert set(plan) == {"label", "dop_threshold", "f_m", "C_r_m", "energy_Wh"}
    assert (plan["label"].a, plan["label"].b, plan["label"].delta) == ("D=2", "D=3", None)
    assert plan["f_m"].delta == pytest.approx(3.5) and plan["f_m"].unit == "m"
    assert plan["energy_Wh"].delta == pytest.approx(0.25) and plan["energy_Wh"].unit == "Wh"

    cand = _items(res, "candidates")
    assert set(cand) == {"D=2.C_r_m", "D=2.f_m", "D=4.flyable", "D=4.reasons", "D=5"}   # compute time ignored
    assert cand["D=2.C_r_m"].delta == pytest.approx(3.5)
    assert (cand["D=4.flyable"].a, cand["D=4.flyable"].b) == ("true", "false")
    assert cand["D=5"].note == "level only in B"

    st = _items(res, "stages")
    assert set(st) == {"plan"} and (st["plan"].a, st["plan"].b) == ("p1", "p2")
    assert any(n.startswith("A: stages computed") and "surface" in n for n in res.notes)

    fly = _items(res, "fly")
    assert set(fly) == {"outcome", "chosen_levels", "energy_Wh", "replanning 1.chosen_level", "closest approach b"}
    assert fly["chosen_levels"].b == "1,3"
    assert fly["closest approach b"].delta == pytest.approx(-2.5) and fly["closest approach b"].unit == "m"
    assert fly["energy_Wh"].delta == pytest.approx(1.5)

    nav = _items(res, "navsim")
    assert set(nav) == {"containment.proposed.3sigma"}
    assert nav["containment.proposed.3sigma"].delta == pytest.approx(-0.04)

    maps = _items(res, "maps")
    assert set(maps) == {"maps.surface", "maps.floor", "surface.tif"}
    assert maps["maps.surface"].delta == pytest.approx(2.5) and maps["maps.surface"].note.startswith("3 of 120 cells")
    assert maps["maps.floor"].delta == math.inf and maps["maps.floor"].note.startswith("1 of 120 cells")
    assert maps["surface.tif"].delta == pytest.approx(0.75) and maps["surface.tif"].note.startswith("4 of 120 cells")

    files = _items(res, "files")
    assert set(files) == {"old.png", "new.png"}
    assert _items(res, "scenario") == {}

    text = format_diff(res)
    assert "[plan] 5 changes" in text and "+3.5 m" in text and "+0.25 Wh" in text
    doc = json.loads(json.dumps(res.to_json(), allow_nan=False))
    assert doc["same"] is False and len(doc["changes"]) == len(res.changes)


def test_settings_and_grid_changes(tmp_path):
    a = _folder(tmp_path / "a", fly=FLY)
    b = _folder(tmp_path / "b", fly={**FLY, "t_rep_s": 3.0, "seed": 7})
    doc = json.loads((b / "summary.json").read_text())
    doc["grid"]["resolution_m"] = 4.0
    (b / "summary.json").write_text(json.dumps(doc))
    sc = _items(diff_folders(a, b), "scenario")
    assert set(sc) == {"fly.t_rep_s", "fly.seed", "grid.resolution_m"}
    assert sc["fly.t_rep_s"].delta == pytest.approx(-2.0) and sc["fly.t_rep_s"].unit == "s"
    assert sc["grid.resolution_m"].delta == pytest.approx(2.0)


def test_cli_table_json_and_errors(tmp_path):
    a = _folder(tmp_path / "a", plan=PLAN)
    b = _folder(tmp_path / "b", plan={**PLAN, "f_m": 90.0})
    runner = CliRunner()
    r = runner.invoke(main, ["diff", str(a), str(b)])
    assert r.exit_code == 0, r.output
    assert "f_m" in r.output and "-10 m" in r.output
    r = runner.invoke(main, ["diff", str(a), str(b), "--json"])
    assert r.exit_code == 0
    doc = json.loads(r.output)
    assert [(c["item"], c["delta"]) for c in doc["changes"]] == [("f_m", -10.0)]
    r = runner.invoke(main, ["diff", str(a), str(a)])
    assert r.exit_code == 0 and "no differences" in r.output
    (tmp_path / "empty").mkdir()
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "summary.json").write_text("{not json")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "summary.json").write_text(json.dumps({"hello": 1}))
    for bad in ("empty", "bad", "other", "missing"):
        r = runner.invoke(main, ["diff", str(a), str(tmp_path / bad)])
        assert r.exit_code == 2, (bad, r.output)
        lines = r.output.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: RUN_B") and "skyroute" in lines[0], lines


def _small_helsinki(tmp_path) -> Path:
    """A small helsinki-medical variant (8 m cells, one coverage level, a 2-minute window, no
    traffic) written as a YAML file in ``tmp_path``."""
    p = scenario_paths()["helsinki-medical"]
    raw = json.loads(json.dumps(yaml.safe_load(p.read_text()), default=str)
                     .replace("../data/", str(p.parent.parent / "data") + "/"))
    raw["aoi"] = {"bounds_lonlat": [24.9370, 60.1636, 24.9440, 60.1725], "resolution_m": 8.0}
    raw["gnss"] = {"elevation_mask_deg": 5, "dop_kind": "PDOP", "dop_thresholds": [4], "window_min": 2, "step_min": 1}
    raw.pop("traffic", None)
    yml = tmp_path / "small.yaml"
    yml.write_text(yaml.safe_dump(raw))
    return yml


def test_same_run_twice_has_no_differences(tmp_path):
    """A real pair: a small helsinki-medical variant (8 m cells, one coverage level, a 2-minute
    window, no traffic) run twice through one cache."""
    yml = _small_helsinki(tmp_path)
    runner = CliRunner()
    cache = str(tmp_path / "cache")
    for out in ("A", "B"):
        r = runner.invoke(main, ["run", str(yml), "--out", str(tmp_path / out), "--cache-dir", cache, "-q"])
        assert r.exit_code == 0, r.output
    res = diff_folders(tmp_path / "A", tmp_path / "B")
    assert res.same, format_diff(res)
    assert {"plan", "candidates", "stages", "maps", "files"} <= set(res.compared)
    assert any(n.startswith("A: stages computed") for n in res.notes)
    assert not any(n.startswith("B: stages computed") for n in res.notes)      # B read every stage from the cache
    # the comparison is not blind: one raster cell changed in B's copy is found
    store = tmp_path / "B" / "datasets" / "clearance.zarr"
    ds = xr.open_zarr(store, consolidated=False).load()
    ds["min_altitude_m"][0, 0] = ds["min_altitude_m"][0, 0] + 1.25
    ds.to_zarr(store, mode="a", consolidated=False)
    maps = _items(diff_folders(tmp_path / "A", tmp_path / "B"), "maps")
    assert set(maps) == {"clearance.min_altitude_m"}
    assert maps["clearance.min_altitude_m"].delta == pytest.approx(1.25)
    assert maps["clearance.min_altitude_m"].note.startswith("1 of ")


def test_outputs_say_how_the_plan_was_made_and_diff_shows_a_planner_change(tmp_path):
    """Provenance (issue 25): summary.json, plan.geojson, candidates.csv and report.html record
    the planner, seed, weights, budgets and version; `skyroute diff` of an A* and a BIT* plan of
    the same scenario reports the planner (and its counted budgets) as changed."""
    import csv

    yml = _small_helsinki(tmp_path)
    runner = CliRunner()
    cache = str(tmp_path / "cache")
    for out, extra in (("A", []), ("B", ["--planner", "bitstar", "--seed", "7"])):
        r = runner.invoke(main, ["plan", str(yml), "--out", str(tmp_path / out), "--cache-dir", cache, "-q", *extra])
        assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "B" / "summary.json").read_text())
    prov = doc["plan"]["provenance"]
    assert prov["planner"] == "bitstar" and prov["seed"] == 7 and len(prov["weights"]) == 4
    assert prov["budgets"]["bitstar_iterations"] > 0 and prov["skyroute_version"]
    gj = json.loads((tmp_path / "B" / "plan.geojson").read_text())
    assert gj["features"][0]["properties"]["provenance"] == prov
    rows = list(csv.DictReader((tmp_path / "B" / "candidates.csv").open()))
    assert rows and all(r["planner"] == "bitstar" and r["seed"] == "7" for r in rows)
    a = json.loads((tmp_path / "A" / "summary.json").read_text())["plan"]["provenance"]
    assert a["planner"] == "astar" and a["budgets"]["max_expansions"] > 0
    res = diff_folders(tmp_path / "A", tmp_path / "B")
    plan = _items(res, "plan")
    assert plan["provenance.planner"].a == "astar" and plan["provenance.planner"].b == "bitstar"
    assert "provenance.seed" in plan and "provenance.budgets.bitstar_iterations" in plan
    assert "provenance.planner" in format_diff(res)
    from skyroute.pipeline.report import report_html

    html = report_html(tmp_path / "B")
    assert 'id="plan-provenance"' in html and "planner bitstar (seed 7" in html
