"""The cached stage graph: cache hits, selective recomputation, atomic writes, schedulers."""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from skyroute.pipeline import graph
from skyroute.pipeline.cache import Cache
from skyroute.pipeline.errors import UnknownNameError
from skyroute.pipeline.graph import REGISTRY, Stage, register, run_pipeline
from skyroute.pipeline.model import FrozenModel, stable_hash
from skyroute.pipeline.settings import load_scenario

HERE = Path(__file__).resolve().parent


def _load_slow():
    spec = importlib.util.spec_from_file_location("skyroute_test_slow_stage", HERE / "_slow_stage.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


class ScaleSettings(FrozenModel):
    factor: float = 2.0


SCALE = {"factor": 2.0}
CALLS: list[str] = []


def _scale_stage(surface: xr.Dataset, *, settings: ScaleSettings) -> xr.Dataset:
    CALLS.append("scaled")
    return xr.Dataset({"scaled": surface["surface"] * settings.factor})


@pytest.fixture
def scaled_stage():
    st = register(Stage("scaled", _scale_stage, lambda sc: ScaleSettings(factor=SCALE["factor"]), inputs=("surface",)))
    yield st
    REGISTRY.pop("scaled", None)
    REGISTRY.pop("slow", None)
    SCALE["factor"] = 2.0
    CALLS.clear()


def test_stable_hash_is_order_and_process_independent(tmp_path):
    assert stable_hash({"a": 1, "b": [1.0, 2]}) == stable_hash({"b": [1.0, 2], "a": 1})
    assert stable_hash({"a": 1}) != stable_hash({"a": 2})
    f = tmp_path / "f.txt"
    f.write_text("one")
    h1 = stable_hash(f)
    f.write_text("two")
    os.utime(f, ns=(time.time_ns(), time.time_ns() + 10**9))
    assert stable_hash(f) != h1  # file content is part of the key
    out = subprocess.run([sys.executable, "-c", "from skyroute.pipeline.model import stable_hash;"
                          "print(stable_hash({'b': [1.0, 2], 'a': 1}))"], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == stable_hash({"a": 1, "b": [1.0, 2]})


def test_rerun_reads_cache_and_change_recomputes_only_dependants(helsinki, cache, scaled_stage):
    r1 = run_pipeline(helsinki, cache=cache, targets=["scaled"])
    assert [(r.name, r.cache_hit) for r in r1.records] == [("surface", False), ("scaled", False)]
    r2 = run_pipeline(helsinki, cache=cache, targets=["scaled"])
    assert [(r.name, r.cache_hit) for r in r2.records] == [("surface", True), ("scaled", True)]
    assert CALLS == ["scaled"]
    xr.testing.assert_identical(r1["scaled"].load(), r2["scaled"].load())
    # a changed setting of the downstream stage recomputes it alone
    SCALE["factor"] = 3.0
    r3 = run_pipeline(helsinki, cache=cache, targets=["scaled"])
    assert [(r.name, r.cache_hit) for r in r3.records] == [("surface", True), ("scaled", False)]
    np.testing.assert_allclose(r3["scaled"]["scaled"].values, 1.5 * r1["scaled"]["scaled"].values)
    # a code change of the upstream stage recomputes it and its dependants
    REGISTRY["surface"] = Stage(**{**REGISTRY["surface"].__dict__, "version": "changed"})
    try:
        r4 = run_pipeline(helsinki, cache=cache, targets=["scaled"])
        assert [(r.name, r.cache_hit) for r in r4.records] == [("surface", False), ("scaled", False)]
    finally:
        REGISTRY.pop("surface")
        importlib.reload(importlib.import_module("skyroute.pipeline.stages_builtin"))
    assert len(cache.entries()) == 5


def test_sigkill_mid_write_leaves_nothing_trusted(tmp_path, helsinki):
    slow = _load_slow()
    cache_dir = tmp_path / "cache"
    script = tmp_path / "run_slow.py"
    script.write_text(textwrap.dedent(f"""
        import importlib.util, sys
        spec = importlib.util.spec_from_file_location("skyroute_test_slow_stage", {str(HERE / '_slow_stage.py')!r})
        mod = importlib.util.module_from_spec(spec); sys.modules[spec.name] = mod; spec.loader.exec_module(mod)
        mod.install()
        from skyroute.pipeline.cache import Cache
        from skyroute.pipeline.graph import run_pipeline
        from skyroute.pipeline.settings import load_scenario
        run_pipeline(load_scenario("helsinki-medical"), cache=Cache({str(cache_dir)!r}), targets=["slow"],
                     scheduler="synchronous")
    """))
    env = {**os.environ, "SKYROUTE_TEST_SLOW": "1"}
    proc = subprocess.Popen([sys.executable, str(script)], env=env)
    tmp_store = cache_dir / "tmp"
    deadline = time.time() + 120
    # wait until the slow stage is half written
    while time.time() < deadline:
        chunks = list(tmp_store.glob("slow-*/data.zarr/v/c/*")) if tmp_store.exists() else []
        if len(chunks) >= 5:
            break
        assert proc.poll() is None, "the writer finished before it could be killed"
        time.sleep(0.05)
    else:
        proc.kill()
        pytest.fail("the slow stage never started writing")
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    cache = Cache(cache_dir)
    assert [e.stage for e in cache.entries()] == ["surface"]  # completed before the kill
    assert list(tmp_store.iterdir())  # an orphan is left...
    assert not list((cache_dir / "stages").glob("slow-*"))  # ...but never under stages/
    # a later run ignores and removes the orphan, recomputes, and gets the right data
    slow.install()
    try:
        res = run_pipeline(helsinki, cache=cache, targets=["slow"])
    finally:
        REGISTRY.pop("slow", None)
    assert [(r.name, r.cache_hit) for r in res.records] == [("surface", True), ("slow", False)]
    np.testing.assert_array_equal(res["slow"]["v"].values, slow.expected())
    assert not list(tmp_store.iterdir())


def test_localcluster_two_workers_equals_threads(helsinki, tmp_path):
    # every stage of the default scenario, the (deterministic) plan included
    maps = ["coverage", "environment", "wind", "clearance", "traffic", "plan"]
    a = run_pipeline(helsinki, cache=Cache(tmp_path / "a"), scheduler="threads", targets=maps)
    b = run_pipeline(helsinki, cache=Cache(tmp_path / "b"), scheduler="distributed", workers=2, targets=maps)
    assert [r.name for r in a.records] == [r.name for r in b.records]
    for name in a.datasets:
        da_, db_ = a[name].load(), b[name].load()
        if name == "plan":  # wall-clock timings are the only thing allowed to differ
            da_, db_ = (d.drop_vars("compute_time_s").assign_attrs(compute_s=0.0) for d in (da_, db_))
        xr.testing.assert_identical(da_, db_)


def test_unknown_scheduler_and_stage(helsinki, cache):
    with pytest.raises(UnknownNameError, match="unknown scheduler 'gpu'; known schedulers: distributed"):
        run_pipeline(helsinki, cache=cache, scheduler="gpu")
    with pytest.raises(UnknownNameError, match="unknown stage 'nope'"):
        run_pipeline(helsinki, cache=cache, targets=["nope"])


def test_cache_clear(helsinki, cache):
    run_pipeline(helsinki, cache=cache, targets=["surface"])
    (cache.tmp_dir / "surface-x.999999999.abcd").mkdir(parents=True)
    assert len(cache.entries()) == 1
    assert cache.clear() == 2
    assert cache.entries() == [] and not list(cache.tmp_dir.iterdir())


def test_graph_module_exposes_registry():
    graph._load_registry()
    assert "surface" in REGISTRY


def test_prechecks_run_only_for_stages_that_compute(helsinki, cache, scaled_stage):
    """A stage read from the cache passed its precheck when it was computed: the runner knows
    every key before any stage runs and skips the precheck (it would read whole maps); so does
    a stage computed alone (every other stage cached: the precheck would save no work)."""
    def precheck(sc, datasets):
        assert "surface" in datasets
        CALLS.append("precheck")

    REGISTRY["scaled"] = Stage(**{**scaled_stage.__dict__, "precheck": precheck, "precheck_after": ("surface",)})
    run_pipeline(helsinki, cache=cache, targets=["scaled"])
    assert CALLS == ["precheck", "scaled"]
    r = run_pipeline(helsinki, cache=cache, targets=["scaled"])
    assert [x.cache_hit for x in r.records] == [True, True] and CALLS == ["precheck", "scaled"]
    # recomputed with every other stage cached: no work for the precheck to save, the stage checks itself
    run_pipeline(helsinki, cache=cache, targets=["scaled"], force=["scaled"])
    assert CALLS == ["precheck", "scaled", "scaled"]
    run_pipeline(helsinki, cache=cache, targets=["scaled"], force=["scaled", "surface"])
    assert CALLS == ["precheck", "scaled", "scaled", "precheck", "scaled"]


def _probe_code(*options: str) -> str:
    """A script running `skyroute run helsinki-medical [options] --out ARGV1 -q` in-process, then
    printing ``HEAVY`` and the compute-only modules it imported."""
    opts = "".join(f"{o!r}, " for o in options)
    return textwrap.dedent(f"""
        import sys
        from skyroute.pipeline.cli import main
        sys.argv = ["skyroute", "run", "helsinki-medical", {opts}"--out", sys.argv[1], "-q"]
        try:
            main()
        except SystemExit as exc:
            assert not exc.code, exc.code
        heavy = ("numba", "matplotlib", "ompl", "distributed", "xarray", "dask", "zarr", "pandas", "scipy",
                 "rasterio", "rioxarray", "shapely", "folium")
        print("HEAVY", *[m for m in heavy if m in sys.modules])
    """)


def test_warm_run_imports_no_compute_only_modules(tmp_path):
    """A warm `skyroute run` (every stage cached, outputs unchanged) imports neither numba nor
    matplotlib, ompl or dask.distributed: they load only where a stage computes or a figure is drawn."""
    code = _probe_code("--stage", "environment")
    env = {**os.environ, "SKYROUTE_CACHE_DIR": str(tmp_path / "cache")}
    report = tmp_path / "out" / "report.html"
    runs = []
    for _ in range(2):
        if report.exists():
            report.unlink()   # the warm run must rebuild it (from the PNG files already there)
        runs.append(subprocess.run([sys.executable, "-c", code, str(tmp_path / "out")], capture_output=True,
                                   text=True, env=env, timeout=600))
    for r in runs:
        assert r.returncode == 0, r.stderr
    cold, warm = (r.stdout.split("HEAVY")[1].split() for r in runs)
    assert {"numba", "matplotlib"} <= set(cold)   # the probe sees them when stages compute
    assert warm == [], warm
    # surface.png and maps.png (risk, landing, wind, no-fly) embedded by the warm run
    assert report.read_text().count('<img src="data:image/png;base64,') == 2


def test_warm_default_run_imports_no_compute_only_modules_and_reuses_its_outputs(tmp_path):
    """The whole default `skyroute run` (plan, pilot exports, map page, report), warm: no numba,
    matplotlib, ompl or dask.distributed (issue 25: reading a cached plan once looked up a
    distributed client), and no xarray, dask, zarr, pandas, scipy, rasterio, shapely or folium
    either (a warm run opens no dataset: keys, attributes and summary sections need none), and
    every output file is reused (the same modification times)."""
    code = _probe_code()
    env = {**os.environ, "SKYROUTE_CACHE_DIR": str(tmp_path / "cache")}
    out = tmp_path / "out"
    runs, mtimes, warns = [], [], []
    for _ in range(2):
        runs.append(subprocess.run([sys.executable, "-c", code, str(out)], capture_output=True, text=True, env=env,
                                   timeout=900))
        assert runs[-1].returncode == 0, runs[-1].stderr
        mtimes.append({p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file() and p.name not in
                       ("summary.json", "report.html", ".skyroute-manifest.json")})
        warns.append(json.loads((out / "summary.json").read_text())["warnings"])
        printed = [ln for ln in runs[-1].stderr.splitlines() if ln.startswith("warning: ")]
        assert len(printed) == len(set(printed)), printed     # each warning printed once
    warm = runs[1].stdout.split("HEAVY")[1].split()
    assert warm == [], warm
    assert mtimes[0] == mtimes[1]     # nothing rewritten but the summary, the report and the manifest listing them
    # the warnings of the stages (the almanac's unhealthy satellite) are the cold run's, on stderr too
    assert warns[0] == warns[1] and any("unhealthy satellites excluded" in w for w in warns[1]), warns
    assert any("unhealthy satellites excluded" in ln for ln in runs[1].stderr.splitlines())


def test_a_warm_run_opens_no_dataset_and_still_checks_a_changed_mission(tmp_path):
    """Issue 25: a cached stage's dataset is opened when first read, and its attributes come from
    the store's metadata (equal to the opened dataset's); the mission check is kept by the
    surface key, grid and mission points, so a warm run reads no map, and a mission moved into
    a building is still refused on the cached surface."""
    from skyroute.pipeline.errors import ScenarioError
    from skyroute.pipeline.runner import run_scenario

    cache = Cache(tmp_path / "c")
    sc = load_scenario("helsinki-medical")
    run_scenario(sc, cache=cache, targets=["surface"])
    warm = run_scenario(sc, cache=cache, targets=["surface"])
    assert warm.records[0].cache_hit and "surface" in warm.datasets and not warm.datasets.is_open("surface")
    attrs = warm.datasets.attrs("surface")
    assert attrs["skyroute_stage"] == "surface" and attrs == dict(warm["surface"].attrs)
    assert warm.datasets.is_open("surface")
    start = sc.mission.start.model_copy(update={"alt_agl_m": 10.0})
    bad = sc.model_copy(update={"mission": sc.mission.model_copy(update={"start": start})})
    with pytest.raises(ScenarioError, match="mission.start: altitude 10 m above ground is inside a building"):
        run_scenario(bad, cache=cache, targets=["surface"])


def test_output_keys_follow_the_output_code(monkeypatch):
    """Issue 25: a run's figures, GeoTIFFs and plan files are keyed like a stage, on the stage keys
    and the code that writes them (the output modules and every module they import), so an edit
    to that code rewrites them on the next warm run."""
    from skyroute.pipeline import outputs

    base = outputs.outputs_code_version()
    assert base == outputs.outputs_code_version()
    real = graph._module_source
    for edited in ("skyroute.pipeline.planmap", "skyroute.stages.figures"):   # an output module, one it imports
        monkeypatch.setattr(graph, "_module_source", lambda m, e=edited: real(m) + (b"\n# edit" if m == e else b""))
        assert outputs.outputs_code_version() != base, edited
