"""A cache that verifies what it reads (issue 27): every file of an entry is re-hashed (BLAKE2b)
on every read, whatever its time says; a mismatch or an unreadable manifest is a warning and a
recompute, never a traceback, never trusted."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import xarray as xr

from skyroute.pipeline.cache import MANIFEST, Cache


def _entry(cache: Cache):
    ds = xr.Dataset({"clearance_m": (("y", "x"), np.random.default_rng(0).random((64, 64)))})
    return cache.write("clearance", "k0", ds, {"scenario": "t"}), ds


def _flip_keep_time(f, pos=None):
    st = f.stat()
    raw = bytearray(f.read_bytes())
    raw[len(raw) // 2 if pos is None else pos] ^= 0x01
    f.write_bytes(bytes(raw))
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))      # the file time restored
    assert f.stat().st_mtime_ns == st.st_mtime_ns and f.stat().st_size == st.st_size


def test_manifest_holds_blake2b_digests(tmp_path):
    from skyroute.pipeline.cache import blake2b_file

    cache = Cache(tmp_path)
    entry, _ = _entry(cache)
    files = entry.manifest["files"]
    assert files and all(row[2].startswith("blake2b:") for row in files.values())
    for rel, row in files.items():
        assert blake2b_file(entry.path / "data.zarr" / rel) == row[2]


@pytest.mark.parametrize("target", ["chunk", "zarr.json"])
def test_a_flipped_byte_with_its_time_restored_is_caught(tmp_path, target):
    cache = Cache(tmp_path)
    entry, ds = _entry(cache)
    store = entry.path / "data.zarr"
    if target == "chunk":
        f = max((p for p in (store / "clearance_m").rglob("*") if p.is_file() and p.name != "zarr.json"),
                key=lambda p: p.stat().st_size)
    else:
        f = store / "clearance_m" / "zarr.json"
    _flip_keep_time(f)
    with pytest.warns(RuntimeWarning, match="damaged.*does not match its checksum"):
        assert cache.get("clearance", "k0") is None
    assert not entry.path.exists()                         # removed: the stage recomputes
    again, _ = _entry(cache)                               # ... and the rewrite is trusted
    np.testing.assert_array_equal(cache.open(again)["clearance_m"].values, ds["clearance_m"].values)


@pytest.mark.parametrize("garbage", [bytes(range(256)), b"[1, 2]", b'{"key": "k0", "stage": "clearance", "files": 5}',
                                     b'{"key": "k0", "stage": "clearance", "files": {"../x": [1, 2, "blake2b:00"]}}',
                                     b'{"key": "k0", "stage": "clearance", "files": {"a": "b"}}'])
def test_garbage_in_the_manifest_is_a_warning_and_a_recompute(tmp_path, garbage):
    cache = Cache(tmp_path)
    entry, _ = _entry(cache)
    (entry.path / MANIFEST).write_bytes(garbage)
    with pytest.warns(RuntimeWarning, match="unreadable"):
        assert cache.get("clearance", "k0") is None
    assert cache.entries() == []
    _entry(cache)                                          # written again over the damaged entry
    assert cache.get("clearance", "k0") is not None


def test_entries_written_with_sha256_are_still_verified(tmp_path):
    """Entries of earlier versions (a bare SHA-256 per file) stay readable and verified."""
    from skyroute.pipeline.model import sha256_file

    cache = Cache(tmp_path)
    entry, _ = _entry(cache)
    mf = json.loads((entry.path / MANIFEST).read_text())
    for rel, row in mf["files"].items():
        row[2] = sha256_file(entry.path / "data.zarr" / rel)
    (entry.path / MANIFEST).write_text(json.dumps(mf))
    assert cache.get("clearance", "k0") is not None
    chunk = next(p for p in (entry.path / "data.zarr" / "clearance_m").rglob("*") if p.is_file() and p.name != "zarr.json")
    _flip_keep_time(chunk)
    with pytest.warns(RuntimeWarning, match="damaged"):
        assert cache.get("clearance", "k0") is None
