"""Frozen, typed settings models and the stable hash used for cache keys.

Every settings object in skyroute is a :class:`FrozenModel` (pydantic, ``frozen=True``,
``extra="forbid"``: an unknown option is an error, never silently ignored).  Stage cache keys
come from :func:`stable_hash` of the settings, which is independent of dict order and of the
Python process (no ``hash()``).
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel

from skyroute.stages.base import FrozenModel  # noqa: F401  (re-exported: its home is stages.base)


def _canonical(obj: Any) -> Any:
    """Turn ``obj`` into plain JSON types in a canonical form."""
    if isinstance(obj, BaseModel):
        return {"__model__": type(obj).__name__, **_canonical(obj.model_dump(mode="python"))}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {"__dataclass__": type(obj).__name__,
                **{f.name: _canonical(getattr(obj, f.name)) for f in dataclasses.fields(obj)}}
    if isinstance(obj, dict):
        return {str(k): _canonical(v) for k, v in sorted(obj.items(), key=lambda kv: str(kv[0]))}
    if isinstance(obj, (list, tuple)):
        return [_canonical(v) for v in obj]
    if isinstance(obj, (set, frozenset)):
        return sorted(_canonical(v) for v in obj)
    if isinstance(obj, Path):
        return _path_canonical(obj)
    if isinstance(obj, np.ndarray):
        return {"__ndarray__": hashlib.sha256(np.ascontiguousarray(obj).tobytes()).hexdigest(),
                "dtype": str(obj.dtype), "shape": list(obj.shape)}
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return repr(f) if not math.isfinite(f) else f
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if hasattr(obj, "isoformat"):
        return obj.isoformat()
    if obj is None or isinstance(obj, (str, int, bool)):
        return obj
    if isinstance(obj, enum.Enum):
        return {"__enum__": type(obj).__name__, "value": _canonical(obj.value)}
    if isinstance(obj, bytes):
        return {"__bytes__": hashlib.sha256(obj).hexdigest()}
    if hasattr(obj, "to_wkt") and type(obj).__module__.startswith("pyproj"):
        return {"__crs__": obj.to_wkt()}
    # as pangeo-forge does: a type without a canonical form would hash by its repr, which may
    # hide its content (or change between processes): refuse it
    raise TypeError(f"stable_hash: no canonical form for {type(obj).__module__}.{type(obj).__qualname__}; "
                    "convert it to plain values (str, number, list, dict, Path, ndarray) in the settings")


def _path_canonical(p: Path) -> dict[str, Any]:
    """A data file or folder by its CONTENT, never by where it lives: a file is its size [bytes]
    and SHA-256 (memoised on path, size and mtime: :func:`file_digest`), a folder the digest of
    its files (:func:`dir_digest`: paths relative to it and contents), so the same bytes in
    site-packages or in a clone's ``catalogs/data`` give the same cache keys.  The last suffix
    (lower case) is kept: readers choose a format by it (``.json`` landuse is CityJSON, ``.grib``
    wind), so the same bytes under another suffix may be read as something else.  A path that is
    neither (nothing to read) is keyed by its text."""
    suffix = p.suffix.lower()
    if p.is_file():
        return {"__file__": suffix, "size": p.stat().st_size, "sha256": file_digest(p)}
    if p.is_dir():
        return {"__dir__": suffix, "sha256": dir_digest(p)}
    return {"__path__": str(p), "sha256": None}


_DIGESTS: dict[str, str] = {}
_DIGESTS_LOADED: list[Path] = []


def _digest_memo_path() -> Path:
    env = os.environ.get("SKYROUTE_CACHE_DIR")
    root = Path(env).expanduser() if env else Path.home() / ".cache" / "skyroute"
    return root / "digests.json"


def _load_digest_memo() -> None:
    path = _digest_memo_path()
    if _DIGESTS_LOADED and _DIGESTS_LOADED[-1] == path:
        return
    _DIGESTS_LOADED.append(path)
    try:
        memo = json.loads(path.read_text())
        if isinstance(memo, dict):
            _DIGESTS.update({k: v for k, v in memo.items() if isinstance(v, str)})
    except (OSError, ValueError):
        pass


def _save_digest_memo() -> None:
    path = _digest_memo_path()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(_DIGESTS))
        os.replace(tmp, path)  # atomic: a reader sees the old or the new memo, never half of one
    except OSError:
        pass  # a read-only cache folder only costs re-hashing


def sha256_file(path: str | Path) -> str:
    """SHA-256 of a file's content, read in 1 MiB blocks (no memo)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def file_digest(path: str | Path) -> str:
    """SHA-256 of a file's content, memoised on (path, size, mtime) in memory and in
    ``<cache root>/digests.json`` so big inputs are not re-read on every run."""
    p = Path(path)
    st = p.stat()
    key = f"{p.resolve()}|{st.st_size}|{st.st_mtime_ns}"
    _load_digest_memo()
    if key not in _DIGESTS:
        _DIGESTS[key] = sha256_file(p)
        _save_digest_memo()
    return _DIGESTS[key]


def dir_digest(path: str | Path) -> str:
    """SHA-256 over a folder's files (relative paths and contents, sorted; e.g. a zarr store)."""
    root = Path(path)
    h = hashlib.sha256()
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames.sort()
        for name in sorted(filenames):
            f = Path(dirpath) / name
            h.update(f.relative_to(root).as_posix().encode() + b"\0")
            h.update(file_digest(f).encode())
    return h.hexdigest()


def stable_hash(*parts: Any, length: int = 20) -> str:
    """Stable hex digest of ``parts`` (settings models, dicts, paths, arrays, scalars).

    Files and folders named by :class:`pathlib.Path` contribute their content (and never their
    location: :func:`_path_canonical`), so editing a data file changes every key that depends on
    it, and a copy of the same bytes elsewhere keeps them.  A type with no canonical form raises
    ``TypeError`` (never a ``repr`` that could hide its content).
    """
    payload = json.dumps(_canonical(list(parts)), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(payload.encode()).hexdigest()[:length]
