"""Content-addressed zarr cache of stage outputs.

An entry is the folder ``<root>/stages/<stage>-<key>/`` holding ``data.zarr`` and the manifest
``skyroute.json``, where ``key`` is a stable hash of the stage
name, its code version, its settings and the keys of its inputs (see :mod:`skyroute.pipeline.graph`).

Integrity: the manifest lists every file of the zarr store with its size, modification time and
SHA-256.  :meth:`Cache.get` checks sizes and modification times (a ``stat`` per file, no reading:
warm runs stay fast) and re-hashes only a file whose time changed (copied or overwritten); an
entry with a missing, resized or altered file is damaged: it is removed with a warning and the
stage recomputes.
Writes go to ``<root>/tmp/`` and are renamed into place only once the zarr store and its
manifest (``skyroute.json``) are complete; ``os.rename`` of a directory is atomic on one
filesystem, so a run killed at any moment leaves at worst an orphan under ``tmp/`` that no
later run reads (and :meth:`Cache.clean_tmp` removes).

The root is, in order: the ``cache_dir`` argument (CLI ``--cache-dir``), ``$SKYROUTE_CACHE_DIR``,
``~/.cache/skyroute``.  For a dask.distributed cluster on several machines it must be a shared
filesystem path.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from skyroute.pipeline.errors import CacheError
from skyroute.pipeline.model import sha256_file

log = logging.getLogger("skyroute.cache")
MANIFEST = "skyroute.json"


def default_cache_dir() -> Path:
    env = os.environ.get("SKYROUTE_CACHE_DIR")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "skyroute"


@dataclass(frozen=True)
class CacheEntry:
    stage: str
    key: str
    path: Path
    manifest: dict[str, Any]

    @property
    def size_bytes(self) -> int:
        return sum(f.stat().st_size for f in self.path.rglob("*") if f.is_file())


class Cache:
    """A cache directory; all methods are safe to call from several processes."""

    def __init__(self, root: str | Path | None = None):
        self.root = Path(root).expanduser() if root is not None else default_cache_dir()

    # -- layout
    @property
    def stages_dir(self) -> Path:
        return self.root / "stages"

    @property
    def tmp_dir(self) -> Path:
        return self.root / "tmp"

    def path_for(self, stage: str, key: str) -> Path:
        return self.stages_dir / f"{stage}-{key}"

    def _ensure(self) -> None:
        try:
            self.stages_dir.mkdir(parents=True, exist_ok=True)
            self.tmp_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise CacheError(f"cannot create cache directory {self.root}: {exc}; "
                             "pass --cache-dir or set SKYROUTE_CACHE_DIR to a writable folder") from exc

    # -- read
    def get(self, stage: str, key: str, touch: bool = True) -> CacheEntry | None:
        """The complete entry for (stage, key), or None.  An entry is trusted only when its
        manifest exists and names the same key and its files are intact; ``touch`` records the
        use (for :meth:`prune`)."""
        p = self.path_for(stage, key)
        mf = p / MANIFEST
        if not mf.is_file():
            return None
        try:
            manifest = json.loads(mf.read_text())
        except (OSError, json.JSONDecodeError):
            return None
        if manifest.get("key") != key or manifest.get("stage") != stage:
            return None
        damage = _damage(p / "data.zarr", manifest.get("files"))
        if damage:
            log.warning("cache entry %s is damaged (%s); removing it, the stage will be recomputed",
                        p.name, damage)
            shutil.rmtree(p, ignore_errors=True)
            return None
        if touch:
            try:
                os.utime(mf)  # last use, for least-recently-used pruning
            except OSError:
                pass
        return CacheEntry(stage, key, p, manifest)

    def open(self, entry: CacheEntry, chunks: Any = "auto") -> xr.Dataset:
        ds = xr.open_zarr(entry.path / "data.zarr", chunks={} if chunks == "auto" else chunks, consolidated=False)
        for name, var in ds.variables.items():
            if isinstance(var.dtype, np.dtypes.StringDType):  # back to plain Python strings for users
                ds[name] = var.astype(object)
        return ds

    # -- write
    def write(self, stage: str, key: str, ds: xr.Dataset, manifest: dict[str, Any],
              compute=None) -> CacheEntry:
        """Write ``ds`` atomically.  ``compute(delayed)`` runs the dask graph of the write
        (scheduler and progress bar are the caller's); default ``delayed.compute()``."""
        self._ensure()
        final = self.path_for(stage, key)
        tmp = self.tmp_dir / f"{stage}-{key}.{os.getpid()}.{uuid.uuid4().hex[:8]}"
        try:
            ds = _prepare_for_zarr(ds)
            tmp.mkdir(parents=True)
            delayed = ds.to_zarr(tmp / "data.zarr", mode="w", compute=False, consolidated=False)
            if compute is None:
                delayed.compute()
            else:
                compute(delayed)
            manifest = {**manifest, "stage": stage, "key": key,
                        "created_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
                        "files": _file_table(tmp / "data.zarr")}
            (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1, default=str))
            _fsync_dir(tmp)
            try:
                os.rename(tmp, final)
            except OSError:
                if self.get(stage, key) is None:  # not a concurrent writer that won the race
                    if final.exists():
                        shutil.rmtree(final, ignore_errors=True)
                    os.rename(tmp, final)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)
        entry = self.get(stage, key)
        if entry is None:
            raise CacheError(f"cache entry {final} vanished right after it was written")
        return entry

    # -- maintenance
    def entries(self) -> list[CacheEntry]:
        out = []
        if self.stages_dir.is_dir():
            for p in sorted(self.stages_dir.iterdir()):
                stage, _, key = p.name.rpartition("-")
                e = self.get(stage, key, touch=False)
                if e is not None:
                    out.append(e)
        return out

    def clear(self, stage: str | None = None) -> int:
        """Remove entries (of one stage, or all) and orphaned temporaries; returns how many."""
        n = 0
        for e in self.entries():
            if stage is None or e.stage == stage:
                shutil.rmtree(e.path, ignore_errors=True)
                n += 1
        if stage is None and self.stages_dir.is_dir():
            for p in self.stages_dir.iterdir():  # incomplete or foreign leftovers
                shutil.rmtree(p, ignore_errors=True)
        n += self.clean_tmp(all_=stage is None)
        return n

    def prune(self, max_size_bytes: int) -> list[CacheEntry]:
        """Remove least-recently-used entries until the cache holds at most ``max_size_bytes``
        (last use = the last :meth:`get` of the entry); returns the entries removed."""
        if max_size_bytes < 0:
            raise CacheError(f"--max-size must be >= 0, got {max_size_bytes} bytes")
        entries = sorted(self.entries(), key=lambda e: (e.path / MANIFEST).stat().st_mtime_ns)
        sizes = {e.path: e.size_bytes for e in entries}
        total = sum(sizes.values())
        removed = []
        for e in entries:
            if total <= max_size_bytes:
                break
            shutil.rmtree(e.path, ignore_errors=True)
            total -= sizes[e.path]
            removed.append(e)
        self.clean_tmp()
        return removed

    def clean_tmp(self, all_: bool = False) -> int:
        """Remove temporaries of processes that no longer run (or all of them)."""
        n = 0
        if not self.tmp_dir.is_dir():
            return 0
        for p in self.tmp_dir.iterdir():
            parts = p.name.split(".")
            pid = int(parts[1]) if len(parts) > 2 and parts[1].isdigit() else -1
            if all_ or not _pid_alive(pid):
                shutil.rmtree(p, ignore_errors=True)
                n += 1
        return n


def _file_table(store: Path) -> dict[str, list]:
    """``{relative path: [size, mtime_ns, sha256]}`` of every file of a zarr store."""
    out = {}
    for f in sorted(store.rglob("*")):
        if f.is_file():
            st = f.stat()
            out[f.relative_to(store).as_posix()] = [st.st_size, st.st_mtime_ns, sha256_file(f)]
    return out


def _damage(store: Path, files: dict[str, list] | None) -> str:
    """Why the store differs from its file table ("" when intact; entries written before the
    table existed are taken as they are)."""
    if files is None:
        return ""
    for rel, (size, mtime_ns, digest) in files.items():
        f = store / rel
        try:
            st = f.stat()
        except OSError:
            return f"{rel} is missing"
        if st.st_size != size:
            return f"{rel} has {st.st_size} bytes, {size} written"
        if st.st_mtime_ns != mtime_ns and sha256_file(f) != digest:
            return f"{rel} was modified"
    return ""


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:
        pass


def zarr_uniform_chunks(chunks: tuple[tuple[int, ...], ...]) -> tuple[tuple[int, ...], ...] | None:
    """Chunks that zarr can store for a dask array chunked ``chunks`` (one tuple of block sizes
    per dim), or None when ``chunks`` already are: zarr needs equal blocks along each dim, the
    last one possibly smaller.  Overlapped computations (:mod:`skyroute.stages.overlap`) merge
    too-small blocks into their neighbours, e.g. ``(1024, 526, 498, 1024, 28)``; such a dim
    gets blocks of its largest block size, ``(1024, 1024, 1024, 28)`` (never more cells per
    block than the largest block had, so memory per task does not grow)."""
    new, changed = [], False
    for c in chunks:
        c = tuple(int(v) for v in c)
        ok = len(c) <= 1 or (len(set(c[:-1])) == 1 and c[-1] <= c[0])
        if ok:
            new.append(c)
            continue
        size, total = max(c), sum(c)
        new.append((size,) * (total // size) + ((total % size,) if total % size else ()))
        changed = True
    return tuple(new) if changed else None


def _prepare_for_zarr(ds: xr.Dataset) -> xr.Dataset:
    """Drop encodings inherited from other stores, make string arrays zarr-friendly and
    rechunk dask arrays whose blocks zarr cannot store (:func:`zarr_uniform_chunks`): this is
    the one place every stage output passes through before ``to_zarr``."""
    ds = ds.copy()
    for name in list(ds.variables):
        var = ds.variables[name]
        var.encoding = {}
        if var.chunks is not None:
            uniform = zarr_uniform_chunks(var.chunks)
            if uniform is not None:
                var = var.chunk(dict(zip(var.dims, uniform, strict=True)))
                if name in ds.coords:
                    ds.coords[name] = var
                else:
                    ds[name] = var
        if var.dtype.kind in ("U", "O"):  # variable-length UTF-8 strings: a stable zarr v3 type
            ds[name] = var.copy(data=np.asarray(var.values).astype(np.dtypes.StringDType()))
    return ds
