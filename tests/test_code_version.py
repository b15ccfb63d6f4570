"""Stage code versions come from the import closure of the stage function (AST, not a list)."""

from __future__ import annotations

import numpy as np
import pytest

from skyroute.pipeline import graph
from skyroute.pipeline.graph import REGISTRY, Stage, _load_registry, code_closure


def _plan_like(*, settings):  # an import inside the body, as the built-in stages do
    from skyroute.stages.planning.strategic import plan_strategic

    return plan_strategic


def _select(sc):
    return None


def test_closure_follows_imports_inside_function_bodies():
    st = Stage("probe", _plan_like, _select)
    _, mods = graph._function_imports(_plan_like)
    assert "skyroute.stages.planning.strategic" in mods
    closure = code_closure(mods)
    # strategic imports these at module level or inside its functions
    for m in ("skyroute.stages.planning.problem", "skyroute.stages.planning.step3", "skyroute.stages.energy",
              "skyroute.stages.traffic", "skyroute.stages.base"):
        assert m in closure, m
    assert all(m.startswith("skyroute.") for m in closure)
    assert st.code_version() == Stage("probe", _plan_like, _select).code_version()


def test_built_in_stages_see_the_modules_the_hand_lists_missed():
    _load_registry()
    closure = {name: code_closure(set(st.code_modules) | graph._function_imports(st.func)[1])
               for name, st in REGISTRY.items()}
    # environment reads CityJSON for risk levels (stages/cityjson.py, once inside surface.py)
    assert {"skyroute.stages.cityjson", "skyroute.stages.grid"} <= closure["environment"]
    assert "skyroute.stages.occlusion" in closure["coverage"]


def test_stage_closures_hold_the_moved_modules():
    """After the issue-10 moves: the environment builder lives in stages/environment.py,
    intruders_for in stages/traffic.py, CityJSON reading in stages/cityjson.py."""
    _load_registry()
    closure = {name: code_closure(set(st.code_modules) | graph._function_imports(st.func)[1])
               for name, st in REGISTRY.items()}
    assert {"skyroute.stages.environment", "skyroute.stages.landing", "skyroute.stages.risk",
            "skyroute.stages.cityjson"} <= closure["environment"]
    assert "skyroute.stages.cityjson" in closure["surface"]
    assert "skyroute.stages.traffic" in closure["traffic"]
    # the traffic stage no longer reaches the planner through intruders_for
    assert not any(m.startswith("skyroute.stages.planning") for m in closure["traffic"])
    assert "skyroute.stages.traffic" in closure["plan"]


def test_module_imports_are_memoised_by_source_digest(tmp_path, monkeypatch):
    """A warm run parses no module: each module's imports are kept in <cache>/code_imports.json
    under its source's SHA-256 (an edited module has another digest and is parsed again)."""
    import hashlib
    import json
    from pathlib import Path

    name = "skyroute.stages.environment"
    memo_file = tmp_path / "code_imports.json"
    digest = hashlib.sha256(Path(graph._module_file(name)).read_bytes()).hexdigest()

    def fresh(memo=None):
        if memo is not None:
            memo_file.write_text(json.dumps(memo))
        monkeypatch.setattr(graph, "_IMPORT_MEMO", {})
        monkeypatch.setattr(graph, "_IMPORT_MEMO_STATE", {"path": None, "dirty": False})
        graph._module_imports.cache_clear()
        return graph._module_imports(name)

    monkeypatch.setenv("SKYROUTE_CACHE_DIR", str(tmp_path))
    try:
        assert {"skyroute.stages.landing", "skyroute.stages.risk", "skyroute.stages.grid"} <= fresh()
        graph._save_import_memo()
        memo = json.loads(memo_file.read_text())
        key = f"{name}|0|{digest}"
        assert list(memo) == [key]
        # a later process trusts the memo (proved by a forged entry) ...
        forged = {key: [*memo[key], ["skyroute.stages.wind", []]]}
        assert "skyroute.stages.wind" in fresh(forged)
        # ... for that exact source only: another digest (an edit) is parsed again
        assert "skyroute.stages.wind" not in fresh({key.replace(digest, "0" * 64): forged[key]})
    finally:
        graph._module_imports.cache_clear()


def test_editing_a_module_deep_in_the_closure_changes_only_dependent_stages(monkeypatch):
    _load_registry()
    before = {name: st.code_version() for name, st in REGISTRY.items()}
    real = graph._module_source

    def edited(name):
        src = real(name)
        return src + b"\n# edited\n" if name == "skyroute.stages.energy" else src

    monkeypatch.setattr(graph, "_module_source", edited)
    after = {name: st.code_version() for name, st in REGISTRY.items()}
    changed = {n for n in before if before[n] != after[n]}
    assert "plan" in changed
    assert not changed & {"surface", "satellites", "wind", "clearance", "coverage", "traffic", "environment"}


def test_editing_a_moved_module_changes_its_stages(monkeypatch):
    _load_registry()
    before = {name: st.code_version() for name, st in REGISTRY.items()}
    real = graph._module_source
    for mod, want in (("skyroute.stages.traffic", {"traffic", "plan"}),
                      ("skyroute.stages.environment", {"environment"}),
                      ("skyroute.stages.cityjson", {"surface", "environment"})):
        monkeypatch.setattr(graph, "_module_source",
                            lambda name, mod=mod: real(name) + b"\n# edited\n" if name == mod else real(name))
        after = {name: st.code_version() for name, st in REGISTRY.items()}
        changed = {n for n in before if before[n] != after[n]}
        assert want <= changed, (mod, changed)
        assert not changed & {"satellites", "wind"}, (mod, changed)


def test_stable_hash_refuses_unknown_types_and_hashes_folders_by_content(tmp_path):
    from skyroute.pipeline.model import stable_hash

    class Opaque:
        pass

    with pytest.raises(TypeError, match="no canonical form for .*Opaque"):
        stable_hash({"x": Opaque()})
    d = tmp_path / "store.zarr"
    (d / "a").mkdir(parents=True)
    (d / "a" / "0.0").write_bytes(b"chunk")
    h1 = stable_hash(d)
    (d / "a" / "0.0").write_bytes(b"chunk2")  # same names, new content
    assert stable_hash(d) != h1
    (d / "a" / "0.0").write_bytes(b"chunk")
    assert stable_hash(d) == h1
    (d / "b").write_bytes(b"")
    assert stable_hash(d) != h1


def test_every_catalog_scenario_has_hashable_stage_settings():
    from skyroute.pipeline.model import stable_hash
    from skyroute.pipeline.settings import load_scenario, scenario_paths

    _load_registry()
    for name in scenario_paths():
        sc = load_scenario(name)
        for st in REGISTRY.values():
            if st.applies(sc):
                assert len(stable_hash(st.select(sc))) == 20, (name, st.name)


def test_editing_the_vehicle_yaml_changes_the_plan_key(tmp_path):
    import yaml

    from skyroute.pipeline.model import stable_hash
    from skyroute.pipeline.settings import load_scenario, parse_scenario
    from skyroute.stages.vehicle import load_vehicle

    _load_registry()
    sc = load_scenario("helsinki-medical")
    prof = load_vehicle(sc.vehicle).model_dump(mode="json")
    keys = []
    for capacity in (prof["battery_capacity_mah"], prof["battery_capacity_mah"] * 0.9):
        f = tmp_path / "vehicle.yaml"  # the same file, edited: only its content changes
        f.write_text(yaml.safe_dump({**prof, "battery_capacity_mah": capacity}))
        raw = yaml.safe_load(sc.source_path.read_text())
        raw["vehicle"] = str(f)
        sc2 = parse_scenario(raw, base=sc.source_path.parent)
        keys.append({n: stable_hash(st.select(sc2)) for n, st in REGISTRY.items() if st.applies(sc2)})
    changed = {n for n in keys[0] if keys[0][n] != keys[1][n]}
    assert changed == {"plan", "wind_bounds"}   # wind_bounds: the vehicle's A* energy bound


def test_a_damaged_chunk_is_dropped_and_recomputed(tmp_path, helsinki, caplog):
    import logging

    import numpy as np

    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.graph import run_pipeline

    cache = Cache(tmp_path / "cache")
    clean = run_pipeline(helsinki, cache=cache, targets=["clearance"])
    want = {n: clean[n].load() for n in ("surface", "clearance")}
    entry = cache.get("surface", clean.records[0].key)
    chunk = max((f for f in (entry.path / "data.zarr" / "surface").rglob("*") if f.is_file()),
                key=lambda f: f.stat().st_size)
    raw = bytearray(chunk.read_bytes())
    raw[len(raw) // 2] ^= 0xFF  # one byte flipped, same size: a silent overwrite
    chunk.write_bytes(bytes(raw))
    with caplog.at_level(logging.WARNING, logger="skyroute.cache"):
        again = run_pipeline(helsinki, cache=cache, targets=["clearance"])
    assert "damaged" in caplog.text and "was modified" in caplog.text
    hits = {r.name: r.cache_hit for r in again.records}
    assert hits["surface"] is False and hits["clearance"] is True  # same key: dependants reused
    for n, ds in want.items():
        for v in ds.data_vars:
            np.testing.assert_array_equal(again[n][v].values, ds[v].values)
    # a file removed from an entry is damage too
    entry = cache.get("clearance", again.records[-1].key)
    next(f for f in (entry.path / "data.zarr").rglob("*") if f.is_file() and f.name != "zarr.json").unlink()
    assert cache.get("clearance", again.records[-1].key) is None


def test_cache_prune_removes_least_recently_used_first(tmp_path):
    import os
    import time

    import xarray as xr
    from click.testing import CliRunner

    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.cli import main, parse_size

    assert parse_size("10G") == 10 << 30 and parse_size("1.5M") == int(1.5 * (1 << 20)) and parse_size("12") == 12
    cache = Cache(tmp_path / "c")
    for i, name in enumerate(("a", "b", "c")):
        ds = xr.Dataset({"v": ("x", np.random.default_rng(i).random(20000))})
        cache.write(name, f"k{i}", ds, {})
        os.utime(cache.path_for(name, f"k{i}") / "skyroute.json", ns=(i * 10**9, i * 10**9))
    time.sleep(0.01)
    assert cache.get("a", "k0") is not None  # a use: "a" becomes the most recent
    size = {e.stage: e.size_bytes for e in cache.entries()}
    r = CliRunner().invoke(main, ["cache", "prune", "--cache-dir", str(cache.root),
                                  "--max-size", str(size["a"] + size["c"])])
    assert r.exit_code == 0, r.output
    assert sorted(e.stage for e in cache.entries()) == ["a", "c"]  # b was the least recently used
    r = CliRunner().invoke(main, ["cache", "prune", "--cache-dir", str(cache.root), "--max-size", "lots"])
    assert r.exit_code == 2 and "is not a size" in r.output


def test_file_digests_persist_between_processes(tmp_path):
    import hashlib
    import json
    import os
    import subprocess
    import sys

    env = {**os.environ, "SKYROUTE_CACHE_DIR": str(tmp_path / "cache")}
    f = tmp_path / "big.bin"
    f.write_bytes(b"x" * 1000)
    code = ("import sys; from skyroute.pipeline import model; print(model.file_digest(sys.argv[1]));"
            "print(len(model._DIGESTS))")
    out = subprocess.run([sys.executable, "-c", code, str(f)], capture_output=True, text=True, check=True,
                         env=env)
    assert out.stdout.split()[0] == hashlib.sha256(b"x" * 1000).hexdigest()
    memo = (tmp_path / "cache" / "digests.json").read_text()
    assert str(f.resolve()) in memo
    # a second process reads the memo: no re-hash (proved by a memo entry that is not the real digest)
    table = json.loads(memo)
    table = {k: ("0" * 64 if k.startswith(str(f.resolve())) else v) for k, v in table.items()}
    (tmp_path / "cache" / "digests.json").write_text(json.dumps(table))
    out = subprocess.run([sys.executable, "-c", code, str(f)], capture_output=True, text=True, check=True,
                         env=env)
    assert out.stdout.split()[0] == "0" * 64
    f.write_bytes(b"y" * 1000)  # a new size/mtime: hashed again
    out = subprocess.run([sys.executable, "-c", code, str(f)], capture_output=True, text=True, check=True,
                         env=env)
    assert out.stdout.split()[0] == hashlib.sha256(b"y" * 1000).hexdigest()


def test_stages_never_import_pipeline():
    """Layering: skyroute.stages sits below skyroute.pipeline (errors, FrozenModel and the run
    control live in skyroute.stages.base / .control); imports inside functions count too."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "stages"
    upward = []
    for f in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(f.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            upward += [f"{f.relative_to(root.parent)}:{node.lineno} imports {n}" for n in names
                       if n == "skyroute.pipeline" or n.startswith("skyroute.pipeline.")]
    assert not upward, "\n".join(upward)


def test_planner_defaults_agree_everywhere():
    import inspect

    from skyroute.pipeline.settings import PlannerSettings
    from skyroute.stages.planning import grid_planner, step1, strategic

    assert PlannerSettings().name == "astar"
    assert PlannerSettings().step_cells == grid_planner.STEP_CELLS
    for fn in (strategic.plan_levels, step1.plan_step1, step1.step1_all_levels):
        assert inspect.signature(fn).parameters["planner"].default == "astar", fn.__name__
    for fn in (strategic.plan_levels, step1.plan_step1, grid_planner.make_lattice, grid_planner.plan_grid,
               grid_planner.shared_heuristic):
        assert inspect.signature(fn).parameters["step_cells"].default == grid_planner.STEP_CELLS, fn.__name__


def _all_keys(sc) -> dict[str, str]:
    """Every applicable stage's cache key, as the runner derives them (no stage computed)."""
    from skyroute.pipeline.graph import stage_key, stages_for

    keys: dict[str, str] = {}
    for st in stages_for(sc):
        keys[st.name] = stage_key(st, sc, [keys[d] for d in st.inputs]
                                  + [keys.get(d, "absent") for d in st.optional_inputs])
    return keys


@pytest.mark.parametrize(("edit", "expected"), [
    ("risk_tags", {"environment", "clearance", "plan"}),   # clearance takes the no-fly cells
    ("wind_file", {"wind", "wind_bounds", "plan"}),
    ("almanac", {"satellites", "coverage", "plan"}),
    ("buildings_file", {"surface", "environment", "wind", "wind_bounds", "clearance", "coverage", "traffic", "plan"}),
])
def test_editing_one_input_recomputes_exactly_its_dependants(tmp_path, edit, expected):
    """Each input kind, edited in place (same path, new content), changes the keys of exactly
    the stages that read it and of their dependants."""
    import shutil

    import yaml

    from skyroute.pipeline.settings import catalog_dir, load_scenario, parse_scenario

    sc0 = load_scenario("helsinki-medical")
    raw = yaml.safe_load(sc0.source_path.read_text())
    data = catalog_dir() / "data"
    copies = {"risk_tags": catalog_dir() / "risk_tags.yaml", "wind_file": data / "gfs_2011-01-15T12_wind.nc",
              "almanac": data / "yuma_2020-01-03.txt", "buildings_file": data / "helsinki_center.osm.pbf"}
    local = {k: tmp_path / p.name for k, p in copies.items()}
    for k, p in copies.items():
        shutil.copyfile(p, local[k])
    land = tmp_path / "landuse.osm.pbf"
    shutil.copyfile(data / "helsinki_center.osm.pbf", land)
    raw["data"].update({"risk_tags": str(local["risk_tags"]), "landuse": str(land)})
    raw["data"]["wind"]["path"] = str(local["wind_file"])
    raw["data"]["buildings"]["path"] = str(local["buildings_file"])
    raw["data"]["almanacs"] = [str(local["almanac"]), str(data / "alm_gal_ed259.txt")]
    before = _all_keys(parse_scenario(raw, base=sc0.source_path.parent))
    f = local[edit]
    f.write_bytes(f.read_bytes() + (b"\n# edited\n" if f.suffix in (".yaml", ".txt") else b"\0"))
    after = _all_keys(parse_scenario(raw, base=sc0.source_path.parent))
    assert {n for n in before if before[n] != after[n]} == expected
