"""Hostile input (issue 27): the reproductions of the issue as a table.  Every case must end
with exit code 2, exactly one ``error:`` line naming the problem, and no traceback, before any
long work (each case is refused at the front door: the whole table runs in seconds)."""

from __future__ import annotations

import copy
import json
import re
import time
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

from skyroute.pipeline.cli import main
from skyroute.pipeline.settings import catalog_dir, scenario_paths

H_SRC = scenario_paths()["helsinki-medical"]
DATA = H_SRC.parent.parent / "data"
VEHICLE_SRC = catalog_dir() / "vehicles" / "dji-m300-rtk.yaml"
GARBAGE = bytes((i * 197 + 89) % 256 for i in range(1024))   # fixed "random" bytes, not UTF-8

ALIAS_BOMB = """name: bomb
a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]
b: &b [*a,*a,*a,*a,*a,*a,*a,*a,*a]
c: &c [*b,*b,*b,*b,*b,*b,*b,*b,*b]
d: &d [*c,*c,*c,*c,*c,*c,*c,*c,*c]
e: &e [*d,*d,*d,*d,*d,*d,*d,*d,*d]
f: &f [*e,*e,*e,*e,*e,*e,*e,*e,*e]
g: &g [*f,*f,*f,*f,*f,*f,*f,*f,*f]
h: &h [*g,*g,*g,*g,*g,*g,*g,*g,*g]
i: &i [*h,*h,*h,*h,*h,*h,*h,*h,*h]
"""


def h_raw() -> dict:
    """helsinki-medical.yaml as a mapping with absolute data paths (the issue's H)."""
    raw = yaml.safe_load(H_SRC.read_text())
    return json.loads(json.dumps(raw, default=str).replace("../data/", str(DATA) + "/"))


def _set(raw: dict, dotted: str, value) -> dict:
    raw = copy.deepcopy(raw)
    node = raw
    *head, last = dotted.split(".")
    for k in head:
        node = node.setdefault(k, {})
    node[last] = value
    return raw


def _scenario(tmp: Path, raw: dict | None = None, text: str | bytes | None = None) -> str:
    p = tmp / "H.yaml"
    if text is not None:
        p.write_bytes(text if isinstance(text, bytes) else text.encode())
    else:
        p.write_text(yaml.safe_dump(raw if raw is not None else h_raw(), sort_keys=False))
    return str(p)


def _file(tmp: Path, name: str, content: str | bytes) -> str:
    p = tmp / name
    p.write_bytes(content if isinstance(content, bytes) else content.encode())
    return str(p)


def _rgb_tif(tmp: Path) -> str:
    """A 3-band RGB GeoTIFF over the Helsinki AOI (a photo, not heights)."""
    import numpy as np
    import rasterio
    from rasterio.transform import from_origin

    p = tmp / "photo.tif"
    with rasterio.open(p, "w", driver="GTiff", width=64, height=64, count=3, dtype="uint8", crs="EPSG:32635",
                       transform=from_origin(385300, 6672900, 20, 20), photometric="RGB") as dst:
        dst.write(np.zeros((3, 64, 64), np.uint8))
    return str(p)


def _dsm_with_1e30(tmp: Path) -> str:
    """A one-band float DSM over the Helsinki AOI whose undeclared NoData is 1e30 in one block."""
    import numpy as np
    import rasterio
    from rasterio.transform import from_origin

    p = tmp / "dsm1e30.tif"
    z = np.full((200, 200), 12.0, np.float32)
    z[50:80, 60:90] = 1e30
    with rasterio.open(p, "w", driver="GTiff", width=200, height=200, count=1, dtype="float32", crs="EPSG:32635",
                       transform=from_origin(385000, 6673400, 10, 10)) as dst:
        dst.write(z, 1)
    return str(p)


def _vehicle_with(tmp: Path, line: str) -> str:
    text = VEHICLE_SRC.read_text()
    key = line.split(":")[0]
    text = re.sub(rf"(?m)^{key}:.*$", line, text)
    return _file(tmp, "veh.yaml", text)


# (id, build(tmp) -> argv, words the one error line must hold)
CASES = [
    # ---- files that are not YAML, or YAML that is refused
    ("scenario-random-bytes", lambda t: ["plan", _scenario(t, text=GARBAGE)], ["not a UTF-8"]),
    ("scenario-nul-bytes", lambda t: ["plan", _scenario(t, text=b"name: x\x00\n")], ["NUL"]),
    ("scenario-not-yaml", lambda t: ["plan", _scenario(t, text="name: [unclosed\naoi: {")], ["not valid YAML"]),
    ("scenario-list", lambda t: ["plan", _scenario(t, text="- 1\n- 2\n")], ["mapping"]),
    ("scenario-duplicate-key", lambda t: ["plan", _scenario(t, text=H_SRC.read_text().replace(
        "../data/", str(DATA) + "/") + "\nvehicle: skywalker-x8\n")], ["'vehicle' is given twice"]),
    ("scenario-alias-bomb", lambda t: ["plan", _scenario(t, text=ALIAS_BOMB)], ["alias"]),
    ("scenario-python-tag", lambda t: ["plan", _scenario(t, text="name: !!python/object/apply:os.system [ls]\n")],
     ["not valid YAML"]),
    ("scenario-deep-nesting", lambda t: ["plan", _scenario(t, text="a: " + "[" * 3000 + "]" * 3000)], ["nesting"]),
    ("vehicle-random-bytes", lambda t: ["plan", _scenario(t, _set(h_raw(), "vehicle", _file(t, "v.yaml", GARBAGE)))],
     ["v.yaml", "not a UTF-8"]),
    ("vehicle-battery-inf", lambda t: ["plan", _scenario(t, _set(h_raw(), "vehicle", _vehicle_with(
        t, "battery_voltage_v: .inf")))], ["battery_voltage_v", "finite"]),
    ("vehicle-mass-true", lambda t: ["plan", _scenario(t, _set(h_raw(), "vehicle", _vehicle_with(
        t, "battery_voltage_v: true")))], ["battery_voltage_v", "not true"]),
    ("events-random-bytes", lambda t: ["fly", _scenario(t), "--events", _file(t, "ev.yaml", GARBAGE)],
     ["ev.yaml", "not a UTF-8"]),
    ("events-duplicate-key", lambda t: ["fly", _scenario(t), "--events", _file(
        t, "ev.yaml", "- {t_s: 10, kind: wind, t_s: 20, uniform_wind: {speed_mps: 3, direction_deg: 0}}\n")],
     ["'t_s' is given twice"]),
    ("fleet-random-bytes", lambda t: ["fleet", _scenario(t), "--fleet", _file(t, "fl.yaml", GARBAGE)],
     ["fl.yaml", "not a UTF-8"]),
    ("fleet-duplicate-key", lambda t: ["fleet", _scenario(t), "--fleet", _file(t, "fl.yaml", "missions: []\nmissions: []\n")],
     ["'missions' is given twice"]),
    ("fleet-departure-2100", lambda t: ["fleet", _scenario(t), "--fleet", _file(t, "fl.yaml", yaml.safe_dump({"missions": [
        {"id": "late", "start": {"x": 385747.35, "y": 6672213.62, "alt_agl_m": 60},
         "goal": {"x": 385969.55, "y": 6672495.29, "alt_agl_m": 60}, "departure": "2100-01-01T00:00:00Z"}]}))],
     ["late", "almanacs"]),
    ("fleet-alias-bomb", lambda t: ["fleet", _scenario(t), "--fleet", _file(t, "fl.yaml", ALIAS_BOMB)], ["alias"]),
    # ---- numbers that make no sense
    ("resolution-inf", lambda t: ["plan", _scenario(t, _set(h_raw(), "aoi.resolution_m", float("inf")))],
     ["aoi.resolution_m", "finite"]),
    ("resolution-nan", lambda t: ["plan", _scenario(t, _set(h_raw(), "aoi.resolution_m", float("nan")))],
     ["aoi.resolution_m", "finite"]),
    ("window-inf", lambda t: ["plan", _scenario(t, _set(h_raw(), "gnss.window_min", float("inf")))],
     ["gnss.window_min", "finite"]),
    ("weights-booleans", lambda t: ["plan", _scenario(t, _set(h_raw(), "planner.weights", [True, False, True, True]))],
     ["planner.weights", "not true"]),
    ("seed-boolean", lambda t: ["plan", _scenario(t, _set(h_raw(), "planner.seed", True))], ["planner.seed"]),
    ("intruder-radius-inf", lambda t: ["plan", _scenario(t, _set(h_raw(), "traffic.n_slices", 20) | {
        "traffic": {**h_raw()["traffic"], "margin_m": float("inf")}})], ["traffic.margin_m", "finite"]),
    # ---- names and paths
    ("name-traversal", lambda t: ["plan", _scenario(t, _set(h_raw(), "name", "../../../tmp/x"))], ["name", "path"]),
    ("name-empty", lambda t: ["plan", _scenario(t, _set(h_raw(), "name", ""))], ["name", "empty"]),
    ("name-dot", lambda t: ["plan", _scenario(t, _set(h_raw(), "name", ".."))], ["name"]),
    ("out-empty", lambda t: ["plan", _scenario(t), "--out", ""], ["--out", "empty"]),
    ("cache-dir-empty", lambda t: ["plan", _scenario(t), "--cache-dir", " "], ["--cache-dir", "empty"]),
    # ---- unknown enum values
    ("run-force-bogus", lambda t: ["run", _scenario(t), "--force", "bogus", "--out", str(t / "o")], ["--force", "bogus"]),
    ("run-stage-bogus", lambda t: ["run", _scenario(t), "--stage", "bogus", "--out", str(t / "o")], ["--stage", "bogus"]),
    ("cache-clear-stage-bogus", lambda t: ["cache", "clear", "--stage", "bogus", "--cache-dir", str(t / "c")],
     ["--stage", "bogus"]),
    ("planner-bogus", lambda t: ["plan", _scenario(t, _set(h_raw(), "planner.name", "warp"))], ["planner.name"]),
    # ---- inconsistent sections
    ("wind-twice", lambda t: ["plan", _scenario(t, _set(h_raw(), "data.uniform_wind",
                                                       {"speed_mps": 5, "direction_deg": 90}))], ["uniform_wind", "not both"]),
    ("intruder-ids-twice", lambda t: ["plan", _scenario(t, _set(h_raw(), "traffic.intruders", [
        h_raw()["traffic"]["intruders"][0], h_raw()["traffic"]["intruders"][0]]))], ["traffic.intruders", "courier-1"]),
    ("every-satellite-excluded", lambda t: ["run", _scenario(t, _set(h_raw(), "gnss.exclude_satellites", [
        f"G{i:02d}" for i in range(1, 33)] + [f"E{i:02d}" for i in range(1, 37)])), "--stage", "satellites",
        "--out", str(t / "o"), "--no-report"], ["gnss.exclude_satellites", "at least 4"]),
    ("aoi-crs-geographic", lambda t: ["plan", _scenario(t, _set(h_raw(), "aoi.crs", "EPSG:4326"))],
     ["aoi.crs", "projected"]),
    ("dsm-rgb-image", lambda t: ["plan", _scenario(t, _set(h_raw(), "data.surface", {
        "path": _rgb_tif(t), "vertical_datum": "EGM96 geoid"}))], ["data.surface.path", "3 bands"]),
    ("dsm-1e30", lambda t: ["run", _scenario(t, _set(h_raw(), "data.surface", {
        "path": _dsm_with_1e30(t), "vertical_datum": "EGM96 geoid"})), "--stage", "surface", "--no-report",
        "--out", str(t / "o")], ["surface DSM", "1e+30", "not a height in metres", "-a_nodata"]),
    # ---- command line numbers
    ("fleet-seed-negative", lambda t: ["fleet", _scenario(t), "--missions", "2", "--seed", "-1"], ["--seed"]),
    ("fly-seed-negative", lambda t: ["fly", _scenario(t), "--seed", "-1"], ["--seed"]),
    ("navsim-seed-negative", lambda t: ["navsim", _scenario(t), "--seed", "-1"], ["--seed"]),
    ("plan-seed-negative", lambda t: ["plan", _scenario(t), "--seed", "-1"], ["--seed"]),
    ("fleet-window-nan", lambda t: ["fleet", _scenario(t), "--missions", "2", "--window-min", "nan"], ["--window-min"]),
    ("fleet-window-inf", lambda t: ["fleet", _scenario(t), "--missions", "2", "--window-min", "inf"], ["--window-min"]),
    ("fleet-ground-nan", lambda t: ["fleet", _scenario(t), "--missions", "2", "--ground-m", "nan"], ["--ground-m"]),
    ("fleet-max-delay-inf", lambda t: ["fleet", _scenario(t), "--missions", "2", "--max-delay-min", "inf"],
     ["--max-delay-min"]),
    ("fly-tick-nan", lambda t: ["fly", _scenario(t), "--tick", "nan"], ["--tick"]),
    ("plan-time-budget-inf", lambda t: ["plan", _scenario(t), "--time-budget", "inf"], ["--time-budget"]),
    # ---- resources: refused from the estimate, before any work
    ("resolution-tiny", lambda t: ["plan", _scenario(t, _set(h_raw(), "aoi.resolution_m", 0.01))],
     ["18,3", "cells", "aoi.resolution_m", "--max-memory"]),
    ("window-huge", lambda t: ["plan", _scenario(t, _set(h_raw(), "gnss.window_min", 1e7))],
     ["10,000,001 GNSS epochs", "gnss.window_min"]),
    ("step-tiny", lambda t: ["coverage", _scenario(t, _set(h_raw(), "gnss.step_min", 1e-6))],
     ["20,000,001 GNSS epochs", "gnss.step_min"]),
    ("fly-tick-tiny", lambda t: ["fly", "helsinki-tactical", "--tick", "1e-7", "--out", str(t / "f")],
     ["ticks", "--tick"]),
    ("max-memory-small", lambda t: ["plan", _scenario(t), "--max-memory", "100M"], ["--max-memory", "460,598 cells"]),
    ("max-memory-bogus", lambda t: ["run", _scenario(t), "--max-memory", "lots"], ["--max-memory 'lots'"]),
    ("unknown-option", lambda t: ["plan", _scenario(t), "--bogus"], ["--bogus"]),
]


@pytest.mark.parametrize("build, words", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_hostile_input_one_error_line(tmp_path, monkeypatch, build, words):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("SKYROUTE_CACHE_DIR", str(tmp_path / "cache"))
    argv = build(tmp_path)
    t0 = time.perf_counter()
    res = CliRunner().invoke(main, argv)
    took = time.perf_counter() - t0
    out = res.output
    assert res.exit_code == 2, (argv, res.exit_code, out, res.exception)
    assert "Traceback" not in out
    errors = [ln for ln in out.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1, out
    for w in words:
        assert w in out, (w, out)
    assert not (tmp_path / "skyroute-out").exists() or not any((tmp_path / "skyroute-out").rglob("*.csv"))
    assert took < 20, f"refused only after {took:.1f} s"


def test_footprint_counts_cells_and_epochs():
    """The estimate's counts are the grid's and the epochs' (brute force), and the limit is a
    sharp threshold."""
    from skyroute.pipeline import budget
    from skyroute.pipeline.errors import InputError
    from skyroute.pipeline.settings import load_scenario

    sc = load_scenario("helsinki-medical")
    fp = budget.scenario_footprint(sc)
    assert fp.cells == sc.grid.nx * sc.grid.ny == 460598
    assert fp.epochs == len(sc.mission_times_utc()) == 21
    assert budget.check_scenario(sc, limit_bytes=int(fp.bytes) + 1) == fp
    with pytest.raises(InputError, match="aoi.resolution_m"):
        budget.check_scenario(sc, limit_bytes=int(fp.bytes) - 1)
    assert budget.check_ticks(100.0, 0.1, limit_bytes=1 << 30) == pytest.approx(1000)
    with pytest.raises(InputError, match="1,000,000,000 ticks"):
        budget.check_ticks(100.0, 1e-7, limit_bytes=1 << 30)


def test_max_memory_default_is_the_machines(monkeypatch):
    from skyroute.pipeline import budget

    budget.set_max_memory(None)
    monkeypatch.delenv(budget.ENV, raising=False)
    assert budget.max_memory_bytes() == int(budget.machine_memory_bytes() * budget.DEFAULT_FRACTION)
    monkeypatch.setenv(budget.ENV, "3G")
    assert budget.max_memory_bytes() == 3 << 30


def test_max_memory_holds_for_one_command_only(tmp_path):
    from skyroute.pipeline import budget

    res = CliRunner().invoke(main, ["plan", _scenario(tmp_path), "--max-memory", "1", "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "of memory" in res.output
    assert budget._limit_bytes is None          # the next command (or an API call) has the default again


def test_a_gnss_event_taking_every_satellite_out_is_an_input_error(tmp_path):
    """The maps of `fly` after a gnss event come from the satellites stage of scenario_at: an
    event leaving no satellite is an InputError (exit 2), not a ValueError in dop_table."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.errors import InputError
    from skyroute.pipeline.runner import run_scenario
    from skyroute.pipeline.settings import load_scenario, scenario_at, with_events

    sc = load_scenario(_scenario(tmp_path))
    every = [f"G{i:02d}" for i in range(1, 33)] + [f"E{i:02d}" for i in range(1, 37)]
    sc = with_events(sc, [{"t_s": 30, "kind": "gnss", "out_of_service": every}])
    cache = Cache(tmp_path / "cache")
    assert run_scenario(scenario_at(sc, 10.0), cache=cache, targets=["satellites"])["satellites"].sizes["sat"] > 4
    with pytest.raises(InputError, match="takes out all .* satellites"):
        run_scenario(scenario_at(sc, 40.0), cache=cache, targets=["satellites"])
