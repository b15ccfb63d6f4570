"""Warm commands into a new folder redo nothing (issue 35 item 8): figures, GeoTIFFs, the plan
files and pilot exports, the flight replay and the maps a report draws are derived outputs of
cached stages, memoised by their keys (pipeline/output_memo.py) and copied from there; each
test fails when the second command draws, writes a plan or replays again."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

from skyroute.pipeline.cli import main
from skyroute.pipeline.settings import catalog_dir

YUMA = catalog_dir() / "data" / "yuma_2020-01-03.txt"
TINY = {"name": "tiny-warm", "aoi": {"bounds": [385000, 6672000, 385120, 6672100], "crs": "EPSG:32635",
                                     "resolution_m": 4.0, "chunk_cells": 64},
        "data": {"almanacs": [str(YUMA)]},
        "mission": {"start": {"x": 385010, "y": 6672010, "alt_agl_m": 30},
                    "goal": {"x": 385110, "y": 6672090, "alt_agl_m": 30},
                    "start_time_utc": "2020-01-03T10:00:00Z"},
        "gnss": {"window_min": 2, "step_min": 1},
        "events": [{"t_s": 3, "kind": "wind", "uniform_wind": {"speed_mps": 8, "direction_deg": 270}}]}


@pytest.fixture(scope="module")
def home(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("warm")
    (d / "s.yaml").write_text(yaml.safe_dump(TINY))
    return d


def _cli(args, home: Path):
    r = CliRunner().invoke(main, [*args, "--cache-dir", str(home / "cache")])
    assert r.exit_code == 0, r.output
    return r


def _contents(folder: Path, skip=("summary.json", "report.html", ".skyroute-manifest.json")) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name not in skip}


def _forbid(monkeypatch, *targets):
    def boom(*a, **k):
        raise AssertionError("a warm command made an output again")

    for mod, name in targets:
        monkeypatch.setattr(mod, name, boom)


def test_a_warm_run_and_plan_into_a_new_folder_copy_every_output(home, monkeypatch):
    import skyroute.pipeline.cli_coverage as cov
    import skyroute.pipeline.fly as fly
    import skyroute.pipeline.maps as maps
    import skyroute.pipeline.outputs as outputs

    _cli(["run", str(home / "s.yaml"), "--out", str(home / "r1"), "-q"], home)
    _cli(["plan", str(home / "s.yaml"), "--out", str(home / "p1"), "-q"], home)
    with monkeypatch.context() as m:
        _forbid(m, (outputs, "write_plan_outputs"), (outputs, "plot_surface"), (maps, "plot_maps_panel"),
                (cov, "plot_coverage"), (fly, "fly_scenario"))
        _cli(["run", str(home / "s.yaml"), "--out", str(home / "r2"), "-q"], home)
        _cli(["plan", str(home / "s.yaml"), "--out", str(home / "p2"), "-q"], home)
    assert _contents(home / "r1") == _contents(home / "r2")
    assert _contents(home / "p1") == _contents(home / "p2")
    s1, s2 = (json.loads((home / d / "summary.json").read_text()) for d in ("r1", "r2"))
    assert s1["plan"] == s2["plan"] and s1["exports"] == s2["exports"] and s1["files"] == s2["files"]
    f1, f2 = (json.loads((home / d / "fly" / "summary.json").read_text())["fly"] for d in ("r1", "r2"))
    assert f1["replayed"] is True and f2["replayed"] is False
    assert {k: v for k, v in f1.items() if k != "replayed"} == {k: v for k, v in f2.items() if k != "replayed"}


def test_a_damaged_memo_entry_is_made_again(home):
    """A memoised output whose bytes changed is not copied: it is drawn again (and memoised)."""
    from skyroute.pipeline.output_memo import MEMO_DIR

    _cli(["plan", str(home / "s.yaml"), "--out", str(home / "d1"), "-q"], home)
    pngs = [p for p in (home / "cache" / MEMO_DIR).rglob("*.png")]
    assert pngs
    for p in pngs:
        p.write_bytes(b"\x89PNG\r\n\x1a\n" + b"damaged")
    _cli(["plan", str(home / "s.yaml"), "--out", str(home / "d2"), "-q"], home)
    for p in (home / "d2").glob("*.png"):
        assert b"damaged" not in p.read_bytes()
    # drawn again: the same figures and tables (the GeoPackage and the map page hold write times)
    same = ("plan.geojson", "waypoints.csv", "candidates.csv", "top_view.png", "profile.png")
    assert {k: v for k, v in _contents(home / "d1").items() if k in same} == \
        {k: v for k, v in _contents(home / "d2").items() if k in same}


def _memoised_flights(home: Path) -> int:
    from skyroute.pipeline.output_memo import MEMO_DIR

    return sum("section" in json.loads(p.read_text()).get("meta", {})
               for p in (home / "cache" / MEMO_DIR).glob("*/meta.json"))


def test_a_flight_a_search_clock_stopped_is_not_memoised(home, monkeypatch):
    """Results never depend on the clock: a replay during which a search stopped at its
    wall-clock safety cap is not memoised (the next flight replays)."""
    from skyroute.stages import control

    real = control.clock_stops
    calls = {"n": 0}

    def ticking():
        calls["n"] += 1
        return real() + calls["n"]         # a different count after the replay: a cap was hit

    monkeypatch.setattr(control, "clock_stops", ticking)
    before = _memoised_flights(home)
    _cli(["fly", str(home / "s.yaml"), "--out", str(home / "f1"), "--seed", "3", "-q"], home)
    assert json.loads((home / "f1" / "summary.json").read_text())["fly"]["replayed"] is True
    assert _memoised_flights(home) == before


def test_force_makes_the_outputs_of_the_forced_stage_again(home, monkeypatch):
    """``--force plan`` recomputes the plan: its files are written again (not copied from the
    memo of the same key), and the memo then holds the new ones."""
    import skyroute.pipeline.outputs as outputs

    _cli(["plan", str(home / "s.yaml"), "--out", str(home / "g1"), "-q"], home)
    real, calls = outputs.write_plan_outputs, []

    def counted(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(outputs, "write_plan_outputs", counted)
    _cli(["run", str(home / "s.yaml"), "--force", "plan", "--out", str(home / "g2"), "-q"], home)
    assert calls == [1]
    _cli(["run", str(home / "s.yaml"), "--out", str(home / "g3"), "-q"], home)
    assert calls == [1]                     # warm again: from the memo the forced run refreshed
