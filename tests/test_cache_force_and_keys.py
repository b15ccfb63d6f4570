"""Cache entries and timings that mean one thing (issue 35, items 1, 4 and 5): a forced result
replaces its cache entry atomically (and the run folder's copy), cache keys depend on the
content of the data files and never on where they live, a warm ``compare`` says its compute
times are cached, and the wall clock of a command starts with its interpreter, not with the
process a shell exec'd it into."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from skyroute.pipeline.cache import Cache
from skyroute.pipeline.settings import catalog_dir, load_scenario

sys.path.insert(0, str(Path(__file__).parent))
from _dem import dem_scenario, write_dem_window  # noqa: E402

DATA = catalog_dir() / "data"


@pytest.fixture(autouse=True)
def _own_digest_memo(tmp_path, monkeypatch):
    """The digest memo (``<cache root>/digests.json``) of these tests in their own folder."""
    monkeypatch.setenv("SKYROUTE_CACHE_DIR", str(tmp_path / "cache"))


@pytest.fixture(scope="module")
def dem_src(tmp_path_factory) -> Path:
    """The DEM of the README's bring-your-own-DEM example."""
    return write_dem_window(tmp_path_factory.mktemp("dem") / "dem.tif")


def _scenario(folder: Path, dem_src: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copy(dem_src, folder / "dem.tif")
    shutil.copy(DATA / "yuma_2020-01-03.txt", folder / "yuma.txt")
    (folder / "s.yaml").write_text(dem_scenario())
    return folder / "s.yaml"


def _flip_one_byte(f: Path, pos: int) -> None:
    raw = bytearray(f.read_bytes())
    raw[pos] ^= 0x01
    f.write_bytes(bytes(raw))


# --------------------------------------------------------------------------- item 4: keys
def test_stage_keys_depend_on_the_data_content_not_on_where_they_live(tmp_path, dem_src):
    from skyroute.pipeline.graph import stage_keys

    a = _scenario(tmp_path / "a", dem_src)
    b = _scenario(tmp_path / "elsewhere" / "deeper" / "b", dem_src)     # the same bytes in another folder
    ka, kb = stage_keys(load_scenario(a)), stage_keys(load_scenario(b))
    assert set(ka) == {"surface", "satellites", "environment", "clearance", "coverage", "plan"}
    assert ka == kb
    # one byte changed in the almanac: the GNSS stages and the plan change, the maps do not
    _flip_one_byte(b.parent / "yuma.txt", 200)
    kb = stage_keys(load_scenario(b))
    assert {n for n in ka if ka[n] != kb[n]} == {"satellites", "coverage", "plan"}
    # one byte changed in the DEM (a pixel's last byte, past the header): every stage on the maps changes
    _flip_one_byte(b.parent / "dem.tif", (b.parent / "dem.tif").stat().st_size - 100)
    kc = stage_keys(load_scenario(b))
    assert {n for n in ka if kb[n] != kc[n]} == {"surface", "environment", "clearance", "coverage", "plan"}


@pytest.mark.parametrize("name", ["rotterdam-tactical", "helsinki-traffic"])
def test_a_copied_catalog_gets_the_shipped_scenarios_keys(tmp_path, name):
    """The issue's case: the same data files in site-packages and in a clone's catalogs/data
    (CityJSON, landing sites, OSM, wind NetCDF, two almanacs, the shipped risk tag table)."""
    from skyroute.pipeline.graph import stage_keys

    shutil.copytree(DATA, tmp_path / "catalogs" / "data")
    (tmp_path / "catalogs" / "scenarios").mkdir()
    copy = tmp_path / "catalogs" / "scenarios" / f"{name}.yaml"
    shutil.copy(catalog_dir() / "scenarios" / f"{name}.yaml", copy)
    shipped, copied = stage_keys(load_scenario(name)), stage_keys(load_scenario(copy))
    assert len(shipped) >= 8 and copied == shipped


def test_a_data_folder_is_keyed_by_its_content(tmp_path):
    from skyroute.pipeline.model import stable_hash

    for d in ("one/wind.zarr", "two/other.zarr"):
        (tmp_path / d / "u").mkdir(parents=True)
        (tmp_path / d / "zarr.json").write_text('{"zarr_format": 3}')
        (tmp_path / d / "u" / "c0").write_bytes(b"\x00\x01\x02")
    one, two = tmp_path / "one" / "wind.zarr", tmp_path / "two" / "other.zarr"
    assert stable_hash(one) == stable_hash(two)
    assert stable_hash(tmp_path / "one" / "zarr.json") != stable_hash(one)
    (two / "u" / "c0").write_bytes(b"\x00\x01\x03")
    assert stable_hash(one) != stable_hash(two)
    (two / "u" / "c0").write_bytes(b"\x00\x01\x02")
    assert stable_hash(one) == stable_hash(two)
    (two / "u" / "c0").rename(two / "u" / "c1")             # the store's own layout is content
    assert stable_hash(one) != stable_hash(two)


def test_a_file_is_keyed_by_its_bytes_and_format_suffix(tmp_path):
    from skyroute.pipeline.model import stable_hash

    (tmp_path / "x").mkdir()
    a, b, c = tmp_path / "a.json", tmp_path / "x" / "renamed.json", tmp_path / "x" / "same.osm"
    for p in (a, b, c):
        p.write_bytes(b'{"type": "CityJSON"}')
    assert stable_hash(a) == stable_hash(b)               # another folder, another name: the same key
    assert stable_hash(a) != stable_hash(c)               # readers choose the format by the suffix
    b.write_bytes(b'{"type": "CityJSON"} ')
    assert stable_hash(a) != stable_hash(b)               # one more byte: another key


# --------------------------------------------------------------------------- item 1: --force
def _ds(v: float, stamp: int) -> xr.Dataset:
    return xr.Dataset({"a": (("y", "x"), np.full((8, 8), v))}, attrs={"stamp": stamp}).chunk({"y": 4, "x": 4})


@pytest.mark.parametrize("swap", [True, False], ids=["exchange", "rename-aside"])
def test_a_forced_write_replaces_the_entry(tmp_path, monkeypatch, swap):
    import skyroute.pipeline.cache as cache_mod

    if not swap:           # a filesystem without renameat2(RENAME_EXCHANGE): old aside, new in
        monkeypatch.setattr(cache_mod, "_exchange", lambda a, b: False)
    cache = Cache(tmp_path / "c")
    first = cache.write("plan", "k0", _ds(1.0, 1), {})
    old_lazy = cache.open(first)                            # a reader holding the old entry lazily
    # a concurrent writer's result of the same key is kept (same key: same code, settings, inputs)
    cache.write("plan", "k0", _ds(2.0, 2), {})
    assert cache.attrs(cache.get("plan", "k0"))["stamp"] == 1
    # a forced result replaces it
    forced = cache.write("plan", "k0", _ds(3.0, 3), {}, replace=True)
    entry = cache.get("plan", "k0")
    assert entry is not None and entry.path == first.path == forced.path
    assert cache.attrs(entry)["stamp"] == 3
    np.testing.assert_array_equal(cache.open(entry)["a"].values, 3.0)
    assert entry.manifest["created_utc"] >= first.manifest["created_utc"]     # (1 s resolution)
    assert list(cache.tmp_dir.iterdir()) == []              # the old entry deleted, no temporary left
    # the old reader reads the entry's chunks by path: the new ones (never NaN, never an error)
    np.testing.assert_array_equal(old_lazy["a"].values, 3.0)


def test_a_reader_checking_an_entry_while_it_is_replaced_takes_the_new_one(tmp_path, monkeypatch):
    """A forced result swapped in while another reader re-hashes the old files: the files no
    longer match the manifest it read, which is no damage (no warning, the entry stays)."""
    import warnings

    import skyroute.pipeline.cache as cache_mod

    cache = Cache(tmp_path / "c")
    cache.write("plan", "k0", _ds(1.0, 1), {})
    real, swapped = cache_mod._damage, []

    def swap_then_check(store, files, verify=True):
        if not swapped:            # the reader has read the old manifest: a forced write lands now
            swapped.append(1)
            cache.write("plan", "k0", _ds(3.0, 3), {}, replace=True)
        return real(store, files, verify=verify)

    monkeypatch.setattr(cache_mod, "_damage", swap_then_check)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        entry = cache.get("plan", "k0")
    assert entry is not None and cache.attrs(entry)["stamp"] == 3
    np.testing.assert_array_equal(cache.open(entry)["a"].values, 3.0)


def test_run_force_keeps_the_new_result_in_the_cache_and_the_run_folder(tmp_path, dem_src, monkeypatch):
    """``skyroute run --force STAGE`` recomputes STAGE and keeps THAT result (the issue saw the
    first run's compute_time_s in the entry and in datasets/plan.zarr after ``--force plan``)."""
    from click.testing import CliRunner

    import skyroute.stages.almanac as almanac
    from skyroute.pipeline.cli import main

    calls = []
    real = almanac.sky_geometry

    def stamped(*args, **kw):                 # the result of every computation differs (like a timing)
        calls.append(1)
        ds = real(*args, **kw)
        ds.attrs["computation"] = len(calls)
        return ds

    monkeypatch.setattr(almanac, "sky_geometry", stamped)
    sc = _scenario(tmp_path / "s", dem_src)
    cache, out = tmp_path / "cache", tmp_path / "out"
    args = ["run", str(sc), "--stage", "satellites", "--no-report", "-q", "--out", str(out), "--cache-dir", str(cache)]
    for extra in ([], ["--force", "satellites"]):
        r = CliRunner().invoke(main, [*args, *extra])
        assert r.exit_code == 0, r.output
    assert len(calls) == 2                    # the forced run computed again
    (entry,) = [e for e in Cache(cache).entries() if e.stage == "satellites"]
    assert Cache(cache).attrs(entry)["computation"] == 2
    assert xr.open_zarr(out / "datasets" / "satellites.zarr", consolidated=False).attrs["computation"] == 2


# --------------------------------------------------------------------------- item 5: timings
def test_a_cached_compute_time_says_it_is_cached():
    from skyroute.pipeline.cli_compare import row_line
    from skyroute.pipeline.compare import COLUMNS, CompareRow

    v = {"f_m": 5344.2, "length_m": 1781.4, "energy_Wh": 52.25, "min_clearance_m": 3.5, "compute_s": 62.91}
    xyz = np.zeros((2, 3))
    cached = row_line(CompareRow("astar", {**v, "plan_cached": True}, xyz))
    fresh = row_line(CompareRow("astar", {**v, "plan_cached": False}, xyz))
    assert cached.endswith("compute 62.91 s (cached)")
    assert fresh.endswith("compute 62.91 s") and "cached" not in fresh
    assert "plan_cached" in COLUMNS and "compute_s" in COLUMNS


@pytest.mark.skipif(not sys.platform.startswith("linux") or shutil.which("bash") is None,
                    reason="a shell that execs its last command")
def test_the_wall_clock_starts_with_the_interpreter_not_the_shell(tmp_path):
    """``bash -c 'sleep S && skyroute ...'`` execs skyroute in the shell's own process, which
    started S seconds before the interpreter: the command's seconds must not count them."""
    code = ("import skyroute.pipeline.cli as c; c._command_started(); "
            "print(c.wall_s(), c._CPU0)")
    sleep_s = 1.5
    t0 = time.perf_counter()
    r = subprocess.run(["bash", "-c", f"sleep {sleep_s} && {sys.executable} -c '{code}'"],
                       capture_output=True, text=True, check=True, env={**os.environ})
    total_s = time.perf_counter() - t0
    wall, cpu0 = (float(v) for v in r.stdout.split())
    assert cpu0 <= wall < total_s - sleep_s + 0.05        # start-up counted, the shell's sleep not
