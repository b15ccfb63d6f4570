"""Frozen, typed settings models and the stable hash used for cache keys.

Every settings object in skyroute is a :class:`FrozenModel` (pydantic, ``frozen=True``,
``extra="forbid"``: an unknown option is an error, never silently ignored).  Stage cache keys
come from :func:`stable_hash` of the settings, which is independent of dict order and of the
Python process (no ``hash()``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict


class FrozenModel(BaseModel):
    """Base of all settings: immutable, strict about unknown keys."""

    model_config = ConfigDict(frozen=True, extra="forbid", validate_default=True)


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
        return {"__path__": str(obj), "sha256": file_digest(obj) if obj.is_file() else None}
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
    return repr(obj)


_DIGESTS: dict[tuple[str, int, int], str] = {}


def file_digest(path: str | Path) -> str:
    """SHA-256 of a file's content (memoised on path, size and mtime)."""
    p = Path(path)
    st = p.stat()
    key = (str(p.resolve()), st.st_size, st.st_mtime_ns)
    if key not in _DIGESTS:
        h = hashlib.sha256()
        with open(p, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        _DIGESTS[key] = h.hexdigest()
    return _DIGESTS[key]


def stable_hash(*parts: Any, length: int = 20) -> str:
    """Stable hex digest of ``parts`` (settings models, dicts, paths, arrays, scalars).

    Files named by :class:`pathlib.Path` contribute their content, so editing a data file
    changes every key that depends on it.
    """
    payload = json.dumps(_canonical(list(parts)), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(payload.encode()).hexdigest()[:length]
