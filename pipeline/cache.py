"""Content-addressed zarr cache of stage outputs.

An entry is the folder ``<root>/stages/<stage>-<key>/`` holding ``data.zarr`` and the manifest
``skyroute.json``, where ``key`` is a stable hash of the stage
name, its code version, its settings and the keys of its inputs (see :mod:`skyroute.pipeline.graph`).

Integrity: the manifest lists every file of the zarr store with its size, modification time and
BLAKE2b digest (``blake2b:<hex>``; entries written before held a SHA-256).  :meth:`Cache.get`
re-hashes every file on every read, whatever its time says (a byte flipped with the file time
restored is caught): an entry with a missing, resized or altered file, or an unreadable manifest,
is damaged: it is removed with a warning and the stage recomputes.  Measured cost (helsinki-medical,
8 cached stages, 795 files, 5.3 MB): 8.6-9.0 ms per warm ``run_scenario(targets=["plan"])``
against 1.9-2.2 ms for sizes and times only, i.e. ~7 ms on a 0.14-0.22 s in-process warm run
(3-5 %) and 0.15 % of a warm ``skyroute plan`` command (4.8-5.3 s with its outputs).
Writes go to ``<root>/tmp/`` and are renamed into place only once the zarr store and its
manifest (``skyroute.json``) are complete; ``os.rename`` of a directory is atomic on one
filesystem, so a run killed at any moment leaves at worst an orphan under ``tmp/`` that no
later run reads (and :meth:`Cache.clean_tmp` removes).  An entry already in place is kept (a
concurrent writer of the same key won), except for a forced result (``run --force STAGE``),
which replaces it atomically (:meth:`Cache._replace`: the folders are swapped in one rename).

The root is, in order: the ``cache_dir`` argument (CLI ``--cache-dir``), ``$SKYROUTE_CACHE_DIR``,
``~/.cache/skyroute``.  For a dask.distributed cluster on several machines it must be a shared
filesystem path.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import logging
import os
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from skyroute.pipeline.errors import CacheError
from skyroute.pipeline.model import sha256_file

# xarray is imported where a dataset is opened or written: a warm run that reads none imports none
if TYPE_CHECKING:
    import xarray as xr

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


_HELD: dict[str, int] = {}    # cache root -> file descriptor of this process's shared lock
_CLEARING: set[str] = set()   # roots this process holds exclusively (clear / prune running)


def _lock_path(root: Path) -> Path:
    return root / ".lock"


def hold_shared(root: Path) -> None:
    """Hold a shared lock on the cache ``root`` for the rest of this process (or until
    :meth:`Cache.clear` / :meth:`Cache.prune` of this process lets it go): entries this process
    opened lazily are read until it ends, and ``skyroute cache clear`` in another process is
    refused meanwhile instead of pulling entries from under a running command."""
    key = str(root.resolve()) if root.exists() else str(root)
    if key in _HELD or key in _CLEARING:
        return
    try:
        import fcntl

        root.mkdir(parents=True, exist_ok=True)
        fd = os.open(_lock_path(root), os.O_RDWR | os.O_CREAT, 0o644)
        fcntl.flock(fd, fcntl.LOCK_SH)
        _HELD[key] = fd
    except (OSError, ImportError):
        pass    # a read-only cache, or no flock: nothing to protect it with


def _release(root: Path) -> None:
    key = str(root.resolve()) if root.exists() else str(root)
    fd = _HELD.pop(key, None)
    if fd is not None:
        os.close(fd)


class _Exclusive:
    """The exclusive lock of ``cache clear`` / ``prune``: refused (CacheError) while another
    process holds the cache."""

    def __init__(self, root: Path):
        self.root, self.fd = root, None

    def __enter__(self):
        _release(self.root)
        try:
            import fcntl
        except ImportError:
            return self
        try:
            self.fd = os.open(_lock_path(self.root), os.O_RDWR | os.O_CREAT, 0o644)
        except OSError:
            return self     # no lock file can be made (read-only): the removals will fail on their own
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(self.fd)
            self.fd = None
            raise CacheError(f"the cache {self.root} is in use by a running skyroute command or Python session: "
                             "removing entries now would pull them from under it; wait until it ends (or stop "
                             "it), then run this again") from None
        _CLEARING.add(str(self.root.resolve()))
        return self

    def __exit__(self, *exc):
        _CLEARING.discard(str(self.root.resolve()))
        if self.fd is not None:
            os.close(self.fd)


class Cache:
    """A cache directory; all methods are safe to call from several processes.  A process that
    reads or writes entries holds a shared lock on the root until it ends (:func:`hold_shared`),
    so :meth:`clear` and :meth:`prune` in another process wait for no one and are refused."""

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

    def check_writable(self) -> None:
        """CacheError (one line) when entries cannot be written here: before any stage computes,
        not after (a read-only cache is fine while every stage is cached)."""
        self._ensure()
        probe = self.tmp_dir / f".write-test-{os.getpid()}-{uuid.uuid4().hex[:6]}"
        try:
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as exc:
            raise CacheError(f"cannot write to the cache directory {self.root}: {exc.strerror or exc}; pass "
                             "--cache-dir or set SKYROUTE_CACHE_DIR to a writable folder") from None

    # -- read
    def get(self, stage: str, key: str, touch: bool = True, verify: bool = True,
            _again: bool = True) -> CacheEntry | None:
        """The complete entry for (stage, key), or None.  An entry is trusted only when its
        manifest exists and names the same key and its files are intact (``verify``: every
        file's digest is recomputed; False: sizes, and digests of files whose time changed, only);
        ``touch`` records the use (for :meth:`prune`).  Files that do not match a manifest that
        changed meanwhile (a forced result swapped in while they were checked) are checked
        again against the new manifest, never taken for damage."""
        p = self.path_for(stage, key)
        mf = p / MANIFEST
        if not mf.is_file():
            return None
        hold_shared(self.root)
        try:
            raw = mf.read_bytes()
            manifest = json.loads(raw.decode("utf-8"))
        except (OSError, UnicodeDecodeError, ValueError):
            raw, manifest = b"", None
        if not isinstance(manifest, dict):
            log.warning("cache entry %s has an unreadable manifest %s; removing it, the stage will be recomputed",
                        p.name, MANIFEST)
            _warn(f"cache entry {p.name}: unreadable manifest {MANIFEST}; recomputed")
            shutil.rmtree(p, ignore_errors=True)
            return None
        if manifest.get("key") != key or manifest.get("stage") != stage:
            return None
        damage = _damage(p / "data.zarr", manifest.get("files"), verify=verify)
        if damage and _again and _changed(mf, raw):     # replaced while checked (:meth:`_replace`)
            return self.get(stage, key, touch=touch, verify=verify, _again=False)
        if damage:
            _warn(f"cache entry {p.name} is damaged ({damage}); recomputed")
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
        """The entry's dataset, lazily (dask arrays; ``.rio`` registered)."""
        import rioxarray  # noqa: F401  (registers the .rio accessor)
        import xarray as xr

        try:
            ds = xr.open_zarr(entry.path / "data.zarr", chunks={} if chunks == "auto" else chunks, consolidated=False)
        except (FileNotFoundError, KeyError) as exc:    # zarr's GroupNotFoundError is a FileNotFoundError
            raise CacheError(f"cache entry {entry.path.name} was removed while this command ran ({exc}; "
                             "`skyroute cache clear` or `prune` elsewhere, or by hand): run the command again") from None
        for name, var in ds.variables.items():
            if isinstance(var.dtype, np.dtypes.StringDType):  # back to plain Python strings for users
                ds[name] = var.astype(object)
        return ds

    def attrs(self, entry: CacheEntry) -> dict[str, Any]:
        """The attributes of the entry's dataset, as :meth:`open` gives them (``ds.attrs``), read
        from the zarr group's metadata without opening the dataset (no xarray)."""
        try:
            meta = json.loads((entry.path / "data.zarr" / "zarr.json").read_bytes())   # zarr format 3
        except (OSError, ValueError):
            meta = None
        if not (isinstance(meta, dict) and isinstance(meta.get("attributes", {}), dict)):
            return dict(self.open(entry).attrs)          # another layout: as the opened dataset says
        return {k: v for k, v in meta.get("attributes", {}).items()
                if not k.lower().startswith("_nc")}       # as xarray's ZarrStore

    # -- checks passed (a check is a function of content-addressed entries: once passed, it
    # passes again on the same key, and its inputs need not be read)
    def passed(self, check: str, key: str) -> bool:
        """Whether the check ``check`` passed on ``key`` (:meth:`note_passed`)."""
        return (self.root / "checks" / f"{check}-{key}").is_file()

    def note_passed(self, check: str, key: str) -> None:
        """Record that the check ``check`` passed on ``key`` (a read-only cache records nothing)."""
        try:
            (self.root / "checks").mkdir(parents=True, exist_ok=True)
            (self.root / "checks" / f"{check}-{key}").touch()
        except OSError:
            pass

    # -- write
    def write(self, stage: str, key: str, ds: xr.Dataset, manifest: dict[str, Any],
              compute=None, replace: bool = False) -> CacheEntry:
        """Write ``ds`` atomically.  ``compute(delayed)`` runs the dask graph of the write
        (scheduler and progress bar are the caller's); default ``delayed.compute()``.

        When an intact entry for (stage, key) is already there (another process wrote it while
        this one computed) it is kept and the new result dropped (same key: same code, settings
        and inputs), unless ``replace`` (``run --force STAGE``): then the new result takes its
        place atomically (:meth:`_replace`)."""
        self._ensure()
        hold_shared(self.root)
        final = self.path_for(stage, key)
        tmp = self.tmp_dir / f"{stage}-{key}.{os.getpid()}.{uuid.uuid4().hex[:8]}"
        try:
            ds = prepare_for_zarr(ds)
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
                # the entry exists: a forced result replaces it; else it is a concurrent writer's
                # that won the race (kept), or a damaged one (get() removed it)
                if replace or self.get(stage, key) is None:
                    self._replace(tmp, stage, key)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)
        entry = self.get(stage, key, verify=False)   # the digests were computed from these files just now
        if entry is None:
            raise CacheError(f"cache entry {final} vanished right after it was written")
        return entry

    def _replace(self, new: Path, stage: str, key: str) -> None:
        """Put the complete entry folder ``new`` (under ``tmp/``) in the place of the entry
        (stage, key), ``final``.

        The two folders are swapped in one step (Linux ``renameat2(RENAME_EXCHANGE)``), so a
        reader finds the old entry or the new one at ``final``, never a missing or half one;
        where the filesystem cannot swap, the old entry is renamed aside into ``tmp/`` and the
        new one renamed in (a reader between the two renames finds no entry: a cache miss, it
        computes the stage).  The old entry is then deleted from ``tmp/``.

        A process that opened the old entry lazily (another command reading the same key) reads
        its chunks by path, i.e. from the new entry once it is in place: a result of the same
        key (same code, settings and inputs), so the same values for a deterministic stage (a
        result that depends on the machine's load is never cached); only a chunk read in the
        moment between the two renames of the fallback would be missing."""
        final = self.path_for(stage, key)
        aside = self.tmp_dir / f"{final.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.old"
        if _exchange(new, final):
            os.rename(new, aside)          # ``new`` now holds the old entry
        else:
            try:
                os.rename(final, aside)
            except FileNotFoundError:
                pass                       # removed meanwhile (clear, or a damaged entry)
            try:
                os.rename(new, final)
            except OSError:                # a concurrent writer put its entry in between: keep it
                if self.get(stage, key) is None:
                    raise
        shutil.rmtree(aside, ignore_errors=True)

    # -- maintenance
    def entries(self) -> list[CacheEntry]:
        out = []
        if self.stages_dir.is_dir():
            for p in sorted(self.stages_dir.iterdir()):
                stage, _, key = p.name.rpartition("-")
                e = self.get(stage, key, touch=False, verify=False)
                if e is not None:
                    out.append(e)
        return out

    def clear(self, stage: str | None = None) -> int:
        """Remove entries (of one stage, or all) and orphaned temporaries; returns how many.
        CacheError while another process holds the cache (:func:`hold_shared`)."""
        if not self.root.is_dir():
            return 0
        with _Exclusive(self.root):
            return self._clear(stage)

    def _clear(self, stage: str | None) -> int:
        n = 0
        for e in self.entries():
            if stage is None or e.stage == stage:
                shutil.rmtree(e.path, ignore_errors=True)
                n += 1
        if stage is None and self.stages_dir.is_dir():
            for p in self.stages_dir.iterdir():  # incomplete or foreign leftovers
                shutil.rmtree(p, ignore_errors=True)
        if stage is None:
            shutil.rmtree(self.root / "checks", ignore_errors=True)
            shutil.rmtree(self.root / "outputs", ignore_errors=True)   # derived outputs (output_memo)
        n += self.clean_tmp(all_=stage is None)
        return n

    def prune(self, max_size_bytes: int) -> list[CacheEntry]:
        """Remove least-recently-used entries until the cache holds at most ``max_size_bytes``
        (last use = the last :meth:`get` of the entry); returns the entries removed."""
        if max_size_bytes < 0:
            raise CacheError(f"--max-size must be >= 0, got {max_size_bytes} bytes")
        if not self.root.is_dir():
            return []
        with _Exclusive(self.root):
            return self._prune(max_size_bytes)

    def _prune(self, max_size_bytes: int) -> list[CacheEntry]:
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


def blake2b_file(path: str | Path) -> str:
    """``blake2b:<hex>``: BLAKE2b (32-byte digest) of a file's content, read in 1 MiB blocks."""
    h = hashlib.blake2b(digest_size=32)
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return "blake2b:" + h.hexdigest()


def _digest(path: Path, like: str) -> str:
    """The digest of ``path`` in the algorithm of ``like`` (``blake2b:...`` or a bare SHA-256)."""
    return blake2b_file(path) if like.startswith("blake2b:") else sha256_file(path)


def _file_table(store: Path) -> dict[str, list]:
    """``{relative path: [size, mtime_ns, blake2b digest]}`` of every file of a zarr store."""
    out = {}
    for f in sorted(store.rglob("*")):
        if f.is_file():
            st = f.stat()
            out[f.relative_to(store).as_posix()] = [st.st_size, st.st_mtime_ns, blake2b_file(f)]
    return out


def _damage(store: Path, files: Any, verify: bool = True) -> str:
    """Why the store differs from its file table ("" when intact; entries written before the
    table existed are taken as they are).  ``verify``: every file is re-hashed, whatever its
    time says; else only the files whose time changed."""
    if files is None:
        return ""
    if not isinstance(files, dict):
        return f"the file table of {MANIFEST} is unreadable"
    for rel, row in files.items():
        if not (isinstance(rel, str) and isinstance(row, list) and len(row) == 3
                and all(isinstance(v, int) for v in row[:2]) and isinstance(row[2], str)) or ".." in rel.split("/"):
            return f"the file table of {MANIFEST} is unreadable at {str(rel)[:60]!r}"
        size, mtime_ns, digest = row
        f = store / rel
        try:
            st = f.stat()
        except OSError:
            return f"{rel} is missing"
        if st.st_size != size:
            return f"{rel} has {st.st_size} bytes, {size} written"
        if (verify or st.st_mtime_ns != mtime_ns) and _digest(f, digest) != digest:
            return f"{rel} was modified (it does not match its checksum)"
    return ""


def _warn(text: str) -> None:
    """A damaged entry is a user-visible warning (one ``warning:`` line on the CLI)."""
    import warnings

    warnings.warn(text, RuntimeWarning, stacklevel=3)


def _changed(path: Path, raw: bytes) -> bool:
    """Whether the file ``path`` no longer holds the bytes ``raw``."""
    try:
        return path.read_bytes() != raw
    except OSError:
        return True


def _exchange(a: Path, b: Path) -> bool:
    """Swap the folders ``a`` and ``b`` atomically (Linux ``renameat2`` with
    ``RENAME_EXCHANGE``, glibc >= 2.28); False where the system or the filesystem cannot."""
    import ctypes
    import ctypes.util
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    at_fdcwd, rename_exchange = -100, 2
    return renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0


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


def prepare_for_zarr(ds: xr.Dataset) -> xr.Dataset:
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
