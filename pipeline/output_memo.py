"""Derived outputs memoised by their keys: figures, GeoTIFFs, the plan files and pilot exports,
the flight replay's folder.

A run's outputs are pure functions of cached stages (their keys) and of the code that draws and
writes them (:func:`skyroute.pipeline.outputs.outputs_code_version`), so a command writing into
a NEW folder with every stage cached need not draw or replay anything again: each derived output
is stored once under ``<cache root>/outputs/<hash of its key>/`` and copied from there.

An entry holds ``data`` (the file, or a folder of files) and ``meta.json`` (the key, every file's
size and BLAKE2b digest, and the caller's small JSON ``meta``, e.g. summary sections).  It is
written under ``<cache root>/tmp/`` and renamed into place when complete (a killed command leaves
no entry); an entry whose files do not match their digests is removed and the output is made
again.  Copies, never links: a user editing an output in place cannot change the memo.
``skyroute cache clear`` removes the memo with the stage entries.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["OutputMemo", "computed_in_run", "memo_of"]

MEMO_DIR = "outputs"


def _digest(path: Path) -> str:
    from skyroute.pipeline.cache import blake2b_file

    return blake2b_file(path)


def _files(root: Path) -> dict[str, list]:
    """``{relative path: [size, digest]}`` of a file (``"."``) or of every file under a folder."""
    if root.is_file():
        return {".": [root.stat().st_size, _digest(root)]}
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_file() and not p.is_symlink():
            out[p.relative_to(root).as_posix()] = [p.stat().st_size, _digest(p)]
    return out


class OutputMemo:
    """The memo of derived outputs in the cache folder ``root``."""

    def __init__(self, root: str | Path):
        self.root = Path(root)

    def _entry(self, key: str) -> Path:
        from skyroute.pipeline.model import stable_hash

        return self.root / MEMO_DIR / stable_hash("output-memo", key, length=24)

    def fetch(self, key: str, dst: Path) -> dict[str, Any] | None:
        """Copy the output memoised under ``key`` to ``dst`` (a file, or a folder whose files are
        added to ``dst``); its ``meta``, or None when there is no intact entry."""
        entry = self._entry(key)
        try:
            doc = json.loads((entry / "meta.json").read_text())
        except (OSError, ValueError):
            return None
        data = entry / "data"
        if not isinstance(doc, dict) or doc.get("key") != key or _files(data) != doc.get("files"):
            shutil.rmtree(entry, ignore_errors=True)      # damaged or a hash collision: made again
            return None
        dst = Path(dst)
        dst.parent.mkdir(parents=True, exist_ok=True)
        if data.is_file():
            shutil.copyfile(data, dst)
        else:
            shutil.copytree(data, dst, dirs_exist_ok=True)
        try:
            os.utime(entry / "meta.json")                  # last use
        except OSError:
            pass
        return doc.get("meta") or {}

    def store(self, key: str, src: Path, meta: dict[str, Any] | None = None,
              only: list[str] | None = None) -> None:
        """Memoise the file or folder ``src`` (with ``only``: just those files of the folder,
        relative paths) under ``key``; a cache that cannot be written only costs the memo."""
        entry = self._entry(key)
        tmp = self.root / "tmp" / f"output-{os.getpid()}.{uuid.uuid4().hex[:8]}"
        try:
            tmp.mkdir(parents=True)
            src = Path(src)
            if src.is_file():
                shutil.copyfile(src, tmp / "data")
            else:
                (tmp / "data").mkdir()
                for rel in only if only is not None else [p.relative_to(src).as_posix() for p in src.rglob("*")
                                                          if p.is_file() and not p.is_symlink()]:
                    (tmp / "data" / rel).parent.mkdir(parents=True, exist_ok=True)
                    shutil.copyfile(src / rel, tmp / "data" / rel)
            (tmp / "meta.json").write_text(json.dumps({"key": key, "files": _files(tmp / "data"),
                                                       "meta": meta or {}}, allow_nan=False))
            entry.parent.mkdir(parents=True, exist_ok=True)
            try:
                os.rename(tmp, entry)
            except OSError:
                shutil.rmtree(entry, ignore_errors=True)   # an older or damaged entry of the key
                os.rename(tmp, entry)
        except (OSError, ValueError, TypeError):
            pass
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def make(self, key: str, dst: Path, make: Callable[[Path], Any], fresh: bool = False) -> bool:
        """``dst`` from the memo of ``key``, else made by ``make(dst)`` and memoised; True when
        it came from the memo.  ``fresh`` (a stage it derives from was computed in this run, e.g.
        ``--force``): made again whatever the memo holds, and the memo replaced."""
        if not fresh and self.fetch(key, dst) is not None:
            return True
        make(dst)
        if Path(dst).exists():
            self.store(key, Path(dst))
        return False


def computed_in_run(result, stages=None) -> bool:
    """Whether one of ``stages`` (default: all) of ``result`` was computed by this run rather
    than read from the cache (``--force``, or a new key): what derives from it is made again, never
    copied from the memo."""
    return any(not r.cache_hit for r in getattr(result, "records", ()) if stages is None or r.name in stages)


def memo_of(result) -> OutputMemo | None:
    """The output memo of the cache ``result``'s stages were read from (None when no stage of
    it is cached: nothing to key the outputs by)."""
    for rec in getattr(result, "records", ()):
        if rec.path:
            return OutputMemo(Path(rec.path).parent.parent)
    return None
