"""Output folders that cannot destroy: a command writes into a fresh staging folder that is put
into place at the end, and only files skyroute itself wrote may ever be replaced or removed.

Every command that writes a folder (``run``, ``plan``, ``maps``, ``coverage``, ``fly``,
``navsim``, ``fleet``, ``compare``, ``airspace export``) gets its ``--out`` through
:func:`open_output_folder` (called by :func:`skyroute.pipeline.outputs.ensure_writable_dir`):

* **Before any work** the folder is checked: it must be new, empty, or a folder skyroute wrote
  (it holds a manifest, :data:`MANIFEST_NAME`); a file the command reads (the scenario, its
  data, an events or fleet file: :func:`skyroute.stages.base.inputs_read`) may not be a file
  skyroute wrote there, nor sit where the command writes (resolved paths and inodes compared).
* The command writes into :attr:`OutFolder.path`, a fresh hidden folder: beside ``--out`` when
  ``--out`` does not exist yet (then simply renamed into place at the end), inside it otherwise.
  An interrupted or failing command leaves ``--out`` as it was (:func:`discard_all`).
* At the end (:func:`commit_all`) each new file is moved into place.  A file already there is
  replaced only when the manifest of ``--out`` (or of a folder above it) lists it with the
  checksum it still has, and it is not an input of the command; nothing is written, replaced
  or removed through a symbolic link or outside ``--out``.  Files of the previous run of the
  same command that this run did not write are removed under the same rule.  Any other
  collision leaves ``--out`` unchanged and the new outputs in a visible folder beside them,
  named in the error.
* The manifest (``.skyroute-manifest.json``) lists every file written with its size and SHA-256
  (a zarr store: its file listing and sizes), and is written by skyroute only: a hand-written
  ``summary.json`` is never a licence to delete.
"""

from __future__ import annotations

import hashlib
import json
import os
import secrets
import shutil
import stat
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from skyroute.pipeline.errors import InputError
from skyroute.stages.base import inputs_read

__all__ = ["MANIFEST_NAME", "OutFolder", "add_to_manifest", "check_replaceable", "commit_all", "discard_all",
           "no_link_between", "open_output_folder", "owned_by_skyroute", "safe_member", "shown", "write_manifest",
           "write_single_file"]

MANIFEST_NAME = ".skyroute-manifest.json"
RETIRED_SUMMARY = ".summary.json.previous"   # the summary set aside while a commit moves the files
MANIFEST_SCHEMA = 1
STAGING_MARK = ".skyroute-staging"          # name part of every staging folder
TRASH_MARK = ".skyroute-trash"
UNPLACED_PREFIX = "skyroute-unplaced-"
ANCESTOR_LEVELS = 4                          # manifests this many folders above --out also vouch


# ------------------------------------------------------------------------------ records
def _sha256(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _store_digest(path: str) -> tuple[str, int, int] | None:
    """(digest of the relative names and sizes, file count, bytes) of a folder (a zarr store);
    None when it holds a symbolic link or anything but folders and regular files."""
    h = hashlib.sha256()
    n = size = 0
    for root, dirs, files in os.walk(path):
        dirs.sort()
        for name in dirs:
            if os.path.islink(os.path.join(root, name)):
                return None
        for name in sorted(files):
            p = os.path.join(root, name)
            st = os.lstat(p)
            if not stat.S_ISREG(st.st_mode):
                return None
            h.update(os.path.relpath(p, path).encode("utf-8", "surrogateescape") + b"\0")
            h.update(str(st.st_size).encode() + b"\0")
            n += 1
            size += st.st_size
    return h.hexdigest(), n, size


def record_of(path: str | Path) -> dict[str, Any] | None:
    """The manifest record of a file (``kind: file``: size, SHA-256), a symbolic link (``link``:
    its target) or a folder (``store``: listing digest); None for anything else."""
    p = os.fspath(path)
    try:
        st = os.lstat(p)
    except OSError:
        return None
    if stat.S_ISLNK(st.st_mode):
        return {"kind": "link", "target": os.readlink(p)}
    if stat.S_ISREG(st.st_mode):
        return {"kind": "file", "size": st.st_size, "sha256": _sha256(p), "mtime_ns": st.st_mtime_ns,
                "ino": st.st_ino}
    if stat.S_ISDIR(st.st_mode):
        d = _store_digest(p)
        if d is None:
            return None
        return {"kind": "store", "digest": d[0], "files": d[1], "size": d[2]}
    return None


def _matches(path: str, rec: Any) -> bool:
    """Whether ``path`` is still what ``rec`` recorded (the record of a manifest: untrusted)."""
    if not isinstance(rec, dict):
        return False
    try:
        st = os.lstat(path)
    except OSError:
        return False
    kind = rec.get("kind")
    if kind == "link":
        return stat.S_ISLNK(st.st_mode) and os.readlink(path) == rec.get("target")
    if kind == "file":
        if not stat.S_ISREG(st.st_mode) or st.st_size != rec.get("size"):
            return False
        if st.st_mtime_ns == rec.get("mtime_ns") and st.st_ino == rec.get("ino"):
            return True                      # unchanged since it was hashed (git's stat memo)
        return _sha256(path) == rec.get("sha256")
    if kind == "store":
        if not stat.S_ISDIR(st.st_mode):
            return False
        d = _store_digest(path)
        return d is not None and d[0] == rec.get("digest")
    return False


def _safe_rel(rel: Any) -> bool:
    if not isinstance(rel, str) or not rel or "\0" in rel or rel.startswith("/"):
        return False
    parts = rel.split("/")
    return all(p not in ("", ".", "..") for p in parts)


def read_manifest(folder: str | Path) -> dict[str, Any] | None:
    """The manifest of ``folder`` (``{"command", "entries": {rel: record}}``), or None when it
    has none (or a malformed one: then nothing of the folder is skyroute's)."""
    p = os.path.join(os.fspath(folder), MANIFEST_NAME)
    try:
        st = os.lstat(p)
        if not stat.S_ISREG(st.st_mode) or st.st_size > 64 << 20:
            return None
        with open(p, "rb") as f:
            doc = json.loads(f.read())
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get("schema") != MANIFEST_SCHEMA or not isinstance(doc.get("entries"), dict):
        return None
    entries = {k: v for k, v in doc["entries"].items() if _safe_rel(k) and isinstance(v, dict)}
    return {"command": str(doc.get("command", "")), "entries": entries}


def _write_json_atomic(path: str, doc: dict) -> None:
    tmp = f"{path}.{os.getpid()}.tmp"
    with open(tmp, "w") as f:
        json.dump(doc, f, indent=0, sort_keys=True)
    os.replace(tmp, path)


def write_manifest(folder: str | Path, command: str, entries: dict[str, dict]) -> None:
    """Write ``folder``'s manifest (atomically)."""
    _write_json_atomic(os.path.join(os.fspath(folder), MANIFEST_NAME),
                       {"schema": MANIFEST_SCHEMA, "written_by": "skyroute", "command": command,
                        "entries": entries})


def no_link_between(root: str, path: str) -> bool:
    """``path`` lies inside ``root`` and no folder between them is a symbolic link (or not a
    folder)."""
    rel = os.path.relpath(path, root)
    if rel.startswith("..") or os.path.isabs(rel):
        return False
    cur = root
    for part in rel.split(os.sep)[:-1]:
        cur = os.path.join(cur, part)
        try:
            st = os.lstat(cur)
        except OSError:
            return True                      # the rest does not exist yet
        if not stat.S_ISDIR(st.st_mode):
            return False
    return True


def owned_by_skyroute(path: str | Path, top: str | Path | None = None) -> bool:
    """Whether ``path`` is a file skyroute wrote and nobody changed since: a manifest in its
    folder or in a folder above it (up to :data:`ANCESTOR_LEVELS` above ``top``, default its
    own folder) lists it with the checksum it still has, and no folder on the way is a symbolic
    link."""
    p = os.path.abspath(os.fspath(path))
    folder = os.path.dirname(p)
    top_ = os.path.abspath(os.fspath(top)) if top is not None else folder
    rel_top = os.path.relpath(folder, top_)
    below = 0 if rel_top == "." or rel_top.startswith("..") else len(rel_top.split(os.sep))
    for _ in range(below + ANCESTOR_LEVELS + 1):
        m = read_manifest(folder)
        if m is not None:
            rec = m["entries"].get(os.path.relpath(p, folder).replace(os.sep, "/"))
            if rec is not None and no_link_between(folder, p) and _matches(p, rec):
                return True
        parent = os.path.dirname(folder)
        if parent == folder:
            return False
        folder = parent
    return False


def safe_member(root: str | Path, path: str | Path, magic: tuple[bytes, ...] = ()) -> bool:
    """``path`` is a regular file inside ``root`` reached through no symbolic link (``root``
    itself may be one) and, with ``magic``, starts with one of those byte strings."""
    r = os.path.realpath(os.fspath(root))
    p = os.path.join(r, os.path.relpath(os.path.abspath(os.fspath(path)), os.path.abspath(os.fspath(root))))
    if not no_link_between(r, p):
        return False
    try:
        st = os.lstat(p)
        if not stat.S_ISREG(st.st_mode):
            return False
        if magic:
            with open(p, "rb") as f:
                head = f.read(max(len(m) for m in magic))
            return any(head.startswith(m) for m in magic)
    except OSError:
        return False
    return True


# ------------------------------------------------------------------------------ the folder
def _input_ids() -> tuple[set[str], set[tuple[int, int]]]:
    paths = set(inputs_read())
    ids = set()
    for p in paths:
        try:
            st = os.stat(p)
            ids.add((st.st_dev, st.st_ino))
        except OSError:
            pass
    return paths, ids


def _is_input(path: str, paths: set[str], ids: set[tuple[int, int]]) -> bool:
    if os.path.realpath(path) in paths:
        return True
    try:
        st = os.lstat(path)
    except OSError:
        return False
    if stat.S_ISDIR(st.st_mode):
        return any(q == path or q.startswith(path.rstrip(os.sep) + os.sep) for q in paths)
    return (st.st_dev, st.st_ino) in ids


def _visible_entries(folder: str) -> list[str]:
    try:
        names = os.listdir(folder)
    except OSError:
        return []
    return sorted(n for n in names if n != MANIFEST_NAME and STAGING_MARK not in n and TRASH_MARK not in n)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


@dataclass
class OutFolder:
    """One command's output folder: ``final`` (``--out``, absolute), ``path`` (the staging
    folder the command writes into), ``command``, the previous run's manifest ``old`` (entries
    not yet verified) and the entries it keeps unchanged (:meth:`reuse`)."""

    final: Path
    path: Path
    command: str
    option: str = "--out"
    fresh: bool = True                       # --out did not exist: the staging folder is renamed into place
    old: dict[str, Any] = field(default_factory=dict)
    old_command: str = ""
    kept: dict[str, dict] = field(default_factory=dict)
    in_place: list[str] = field(default_factory=list)
    committed: bool = False

    # -------------------------------------------------------------- while the command writes
    def reuse(self, rel: str) -> bool:
        """Keep ``--out/rel`` as it is, if skyroute wrote it there and it is unchanged (a warm
        re-run reuses a figure or a store by its key instead of writing it again): True when
        kept (the caller then does not write it)."""
        rec = self.old.get(rel)
        p = os.path.join(self.final, rel)
        if rec is None or not no_link_between(str(self.final), p) or not _matches(p, rec):
            return False
        paths, ids = _input_ids()
        if _is_input(p, paths, ids):
            return False
        _link_into(p, os.path.join(self.path, rel))   # the staged folder is complete (report reads it)
        self.kept[rel] = rec
        return True

    def adopt_in_place(self, path: str | Path) -> str:
        """A file the command changed where it is in ``--out`` (the airspace file a fleet adds
        to): listed in the manifest with its new checksum, never moved, never stale; returns
        its path relative to ``--out``."""
        rel = os.path.relpath(os.path.abspath(os.fspath(path)), self.final).replace(os.sep, "/")
        if not _safe_rel(rel):
            raise ValueError(f"{path} is not inside {self.final}")
        self.in_place.append(rel)
        return rel

    def shown(self, p: str | Path) -> Path:
        """Where a file written into the staging folder will be once the command ends."""
        s = os.path.abspath(os.fspath(p))
        base = os.path.abspath(self.path)
        if s == base or s.startswith(base + os.sep):
            return Path(os.path.join(self.final, os.path.relpath(s, base))) if s != base else self.final
        return Path(p)

    # -------------------------------------------------------------- the end
    def _units(self) -> list[str]:
        """The staged files, links and zarr stores (relative, POSIX)."""
        out = []
        base = str(self.path)
        for root, dirs, files in os.walk(base):
            keep = []
            for d in sorted(dirs):
                full = os.path.join(root, d)
                if os.path.islink(full) or d.endswith(".zarr"):
                    out.append(os.path.relpath(full, base).replace(os.sep, "/"))
                else:
                    keep.append(d)
            dirs[:] = keep
            for f in sorted(files):
                rel = os.path.relpath(os.path.join(root, f), base).replace(os.sep, "/")
                if rel != MANIFEST_NAME:
                    out.append(rel)
        return out

    def _still_kept(self, u: str) -> bool:
        """A unit :meth:`reuse` kept and the command did not write again (its staged hard link
        is still the file of ``--out``)."""
        if u not in self.kept:
            return False
        src, dst = os.path.join(self.path, u), os.path.join(self.final, u)
        if self.kept[u].get("kind") == "store":
            return os.path.isdir(src) and os.path.isdir(dst)
        try:
            return os.lstat(src).st_ino == os.lstat(dst).st_ino
        except OSError:
            return False

    def _record(self, u: str) -> dict | None:
        """The record of a staged unit (a kept one, hard-linked, keeps its record)."""
        p = os.path.join(self.path, u)
        rec = self.kept.get(u)
        if rec is not None:
            if rec.get("kind") == "store" or (rec.get("kind") == "file" and _matches(p, rec)):
                return {**rec, "ino": os.lstat(p).st_ino, "mtime_ns": os.lstat(p).st_mtime_ns} \
                    if rec.get("kind") == "file" else rec
        return record_of(p)

    def commit(self) -> None:
        """Put the staged outputs into place (see the module docstring)."""
        if self.committed:
            return
        self.committed = True
        units = self._units()
        new = {u: r for u in units if (r := self._record(u)) is not None}
        final = str(self.final)
        for rel in self.in_place:            # changed where it is: its new record, never moved or stale
            if rel not in new and (r := record_of(os.path.join(final, rel))) is not None:
                new[rel] = r
        nested = _nested_manifests(new, self.kept)
        if self.fresh and not os.path.lexists(final):
            for folder, sub in nested.items():
                write_manifest(os.path.join(self.path, folder), self.command, sub)
            write_manifest(self.path, self.command, new)
            try:
                os.rename(self.path, final)
                return
            except OSError:
                pass                         # --out appeared meanwhile: place file by file
        paths, ids = _input_ids()
        conflicts: list[str] = []
        for u in units:
            dst = os.path.join(final, u)
            if not no_link_between(final, dst):
                conflicts.append(u)
            elif os.path.lexists(dst) and (_is_input(dst, paths, ids) or not (
                    u in self.old and _matches(dst, self.old[u]) or owned_by_skyroute(dst, final))):
                conflicts.append(u)
        if conflicts:
            self._unplaced(conflicts)
        stale = []
        if self.old_command == self.command:
            for rel, rec in self.old.items():
                if rel in new:
                    continue
                p = os.path.join(final, rel)
                if no_link_between(final, p) and _matches(p, rec) and not _is_input(p, paths, ids):
                    stale.append(rel)
        # 1. the summary is set aside: a folder caught half-way has none (report / diff refuse it)
        summary_path = os.path.join(final, "summary.json")
        retired = os.path.join(final, RETIRED_SUMMARY)
        if os.path.isfile(summary_path) and not os.path.islink(summary_path):
            os.replace(summary_path, retired)
        # 2. while files move, the manifest lists the old and the new ones (a killed commit
        # leaves nothing a later run cannot recognise as its own)
        write_manifest(final, self.command, {**self.old, **new})
        trash = os.path.join(final, f"{TRASH_MARK}-{os.getpid()}-{secrets.token_hex(4)}")

        def clear(p: str) -> None:
            if os.path.isdir(p) and not os.path.islink(p):
                os.makedirs(trash, exist_ok=True)
                os.rename(p, os.path.join(trash, secrets.token_hex(8)))
            elif os.path.lexists(p):
                os.unlink(p)

        # 3. the new files, summary.json last (a kept file or store stays where it is)
        moving = [u for u in units if not self._still_kept(u)]
        for u in [u for u in moving if u != "summary.json"] + [u for u in moving if u == "summary.json"]:
            src, dst = os.path.join(self.path, u), os.path.join(final, u)
            os.makedirs(os.path.dirname(dst), exist_ok=True)
            if os.path.lexists(dst) and (os.path.isdir(src) or (os.path.isdir(dst) and not os.path.islink(dst))):
                clear(dst)
            os.replace(src, dst)
        # 4. what the previous run of this command wrote and this one did not
        for rel in stale:
            p = os.path.join(final, rel)
            clear(p)
            _prune_empty(final, os.path.dirname(p))
        entries = dict(new)
        if self.old_command != self.command:   # a folder shared by two commands keeps the other's files
            for rel, rec in self.old.items():
                if rel not in entries and _matches(os.path.join(final, rel), rec):
                    entries[rel] = rec
        for folder, sub in nested.items():
            write_manifest(os.path.join(final, folder), self.command, sub)
        write_manifest(final, self.command, entries)
        if os.path.exists(summary_path) and os.path.lexists(retired):
            os.unlink(retired)
        shutil.rmtree(trash, ignore_errors=True)
        shutil.rmtree(self.path, ignore_errors=True)

    def _unplaced(self, conflicts: list[str]) -> None:
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        dest = os.path.join(self.final, f"{UNPLACED_PREFIX}{stamp}-{os.getpid()}")
        try:
            os.rename(self.path, dest)
        except OSError:
            dest = str(self.path)
        shown_ = ", ".join(conflicts[:5]) + (f" and {len(conflicts) - 5} more" if len(conflicts) > 5 else "")
        raise InputError(f"{self.option} {self.final} holds {shown_}, which skyroute did not write there (or "
                         "which changed since, or which this command reads): nothing in the folder was "
                         f"changed, and this run's outputs are in {dest}; move those files away or choose a "
                         f"new {self.option} folder")

    def discard(self) -> None:
        if not self.committed:
            self.committed = True
            shutil.rmtree(self.path, ignore_errors=True)


def _link_into(src: str, dst: str) -> None:
    """Hard-link the file or folder tree ``src`` to ``dst`` (a copy where links fail)."""
    os.makedirs(os.path.dirname(dst), exist_ok=True)
    if os.path.isdir(src) and not os.path.islink(src):
        for root, _dirs, files in os.walk(src):
            target = os.path.join(dst, os.path.relpath(root, src))
            os.makedirs(target, exist_ok=True)
            for f in files:
                _link_into(os.path.join(root, f), os.path.join(target, f))
        return
    try:
        os.link(src, dst, follow_symlinks=False)
    except OSError:
        shutil.copy2(src, dst, follow_symlinks=False)


def _nested_manifests(new: dict[str, dict], kept: dict[str, dict]) -> dict[str, dict[str, dict]]:
    """Manifests of the sub-folders that hold a summary.json of their own (``run``'s ``fly/``):
    a later command writing into that sub-folder finds its files listed there."""
    allrec = {**kept, **new}
    out: dict[str, dict[str, dict]] = {}
    for rel in allrec:
        if rel.endswith("/summary.json"):
            folder = rel.rsplit("/", 1)[0]
            out[folder] = {k[len(folder) + 1:]: v for k, v in allrec.items() if k.startswith(folder + "/")}
    return out


def _prune_empty(top: str, folder: str) -> None:
    while os.path.abspath(folder) != os.path.abspath(top):
        try:
            os.rmdir(folder)
        except OSError:
            return
        folder = os.path.dirname(folder)


def add_to_manifest(folder: str | Path, paths: Iterable[str | Path]) -> None:
    """List files skyroute just wrote into an existing folder (``skyroute report``'s page, the
    updated summary.json) in the folder's manifest, with their checksums."""
    folder = os.path.abspath(os.fspath(folder))
    man = read_manifest(folder)
    entries = dict(man["entries"]) if man is not None else {}
    for p in paths:
        full = os.path.abspath(os.fspath(p))
        rel = os.path.relpath(full, folder)
        if rel.startswith("..") or not no_link_between(folder, full):
            continue
        rec = record_of(full)
        if rec is not None:
            entries[rel.replace(os.sep, "/")] = rec
    write_manifest(folder, man["command"] if man is not None else "report", entries)


def check_replaceable(path: str | Path, option: str = "--out") -> None:
    """InputError unless ``path`` is absent or a file skyroute wrote there (unchanged), reached
    through no symbolic link, and not an input of the command: a single output file (the report
    page) never replaces a user's file."""
    p = os.path.abspath(os.fspath(path))
    if not os.path.lexists(p):
        return
    paths, ids = _input_ids()
    if os.path.islink(p) or not owned_by_skyroute(p) or _is_input(p, paths, ids):
        raise InputError(f"{option} {path}: a file skyroute did not write is there (or it changed since, or it is a "
                         "symbolic link): it is not replaced; move it away or choose another file name")


def write_single_file(path: str | Path, write, option: str = "--out") -> Path:
    """Write one output file (``write(tmp_path)`` fills a temporary sibling that keeps the
    suffix, then it is renamed into place, never written through a link) where
    :func:`check_replaceable` allows it, and list it in its folder's manifest."""
    p = Path(os.path.abspath(os.fspath(path)))
    check_replaceable(p, option)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f".{p.stem}.skyroute-{os.getpid()}-{secrets.token_hex(3)}.tmp{p.suffix}")
    try:
        write(tmp)
        os.replace(tmp, p)
    finally:
        if os.path.lexists(tmp):
            os.unlink(tmp)
    add_to_manifest(p.parent, [p])
    return p


# ------------------------------------------------------------------------------ the registry
_OPEN: list[OutFolder] = []


def open_output_folder(out_dir: str | Path, command: str, option: str = "--out") -> OutFolder:
    """Check ``out_dir`` before any work and open its staging folder (see the module docstring).
    Raises InputError (one line: what is wrong and the fix) for a folder skyroute may not write."""
    raw = os.fspath(out_dir)
    if any(ord(c) < 32 or c == "\x7f" for c in raw):
        raise InputError(f"{option} {raw!r}: a folder name with a control character (newline, tab...) is "
                         "refused; choose a plain name")
    final = Path(os.path.abspath(raw))
    if final.is_dir():
        final = Path(os.path.realpath(final))          # --out may itself be a link to a folder
    elif os.path.lexists(final):
        raise InputError(f"{option} {raw} is a file, not a folder; choose a folder name")
    for f in _OPEN:
        if f.final == final and not f.committed:
            return f
    paths, ids = _input_ids()
    fresh = not final.exists()
    old: dict[str, Any] = {}
    old_command = ""
    if not fresh:
        _sweep(final)
        man = read_manifest(final)
        entries = _visible_entries(str(final))
        if man is None and entries and not _vouched(final):
            listed = ", ".join(entries[:4]) + (" ..." if len(entries) > 4 else "")
            raise InputError(f"{option} {raw} is not empty ({listed}) and skyroute did not write it (it has no "
                             f"{MANIFEST_NAME}; a folder written by skyroute before 0.2 has none either): "
                             f"skyroute writes only into a new or empty folder, or one it wrote; choose another "
                             f"{option} (e.g. {os.path.join(raw, 'skyroute-out')})")
        if man is not None:
            old, old_command = man["entries"], man["command"]
        for rel in old:
            p = os.path.join(final, rel)
            if _is_input(p, paths, ids) and _matches(p, old[rel]):
                raise InputError(f"{option} {raw}: {rel} there is a file skyroute wrote that this command reads as "
                                 f"an input: the command would replace it; copy it out of {raw} (and point the "
                                 f"scenario at the copy) or choose another {option} folder")
        for q in sorted(paths):
            if q.startswith(str(final) + os.sep) and os.path.relpath(q, final).split(os.sep)[0] in _OUTPUT_NAMES:
                rel = os.path.relpath(q, final)
                raise InputError(f"{option} {raw}: {rel} is an input of this command, where skyroute writes its "
                                 f"outputs: it would be replaced; move it out of {raw} or choose another {option}")
        for name in _visible_entries(str(final)):
            p = os.path.join(final, name)
            if name not in _OUTPUT_NAMES:
                continue
            if os.path.islink(p) or (not os.path.isdir(p) and not (name in old and _matches(p, old[name]))
                                     and not owned_by_skyroute(p, final)):
                raise InputError(f"{option} {raw}: {name} there was not written by skyroute (or changed since), "
                                 f"and this command writes a {name}: move it away or choose another {option}")
        check_writable_dir(final, option)
        staging = final / f"{STAGING_MARK}-{os.getpid()}-{secrets.token_hex(4)}"
    else:
        if final.parent.is_dir():
            _sweep(final.parent, prefix=f".{final.name}{STAGING_MARK}-")
        staging = final.parent / f".{final.name}{STAGING_MARK}-{os.getpid()}-{secrets.token_hex(4)}"
    try:
        staging.parent.mkdir(parents=True, exist_ok=True)
        staging.mkdir()
    except OSError as exc:
        raise InputError(f"cannot write to {option} {raw}: {exc.strerror or exc}; choose a folder you can "
                         "write to") from None
    folder = OutFolder(final=final, path=staging, command=command, option=option, fresh=fresh, old=old,
                       old_command=old_command)
    _OPEN.append(folder)
    return folder


def check_writable_dir(out_dir: Path | str, option: str = "--out") -> Path:
    """Create ``out_dir`` and prove it writable (a probe file), nothing else."""
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        probe = out_dir / f".skyroute-write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise InputError(f"cannot write to {option} {out_dir}: {exc.strerror or exc}; choose a folder you "
                         "can write to") from None
    return out_dir


def _vouched(final: Path) -> bool:
    """A folder without a manifest whose every entry is vouched for by a manifest above it (the
    ``plan/`` folder a ``run`` wrote, written again by ``skyroute plan``)."""
    for root, dirs, files in os.walk(final):
        dirs[:] = [d for d in dirs if STAGING_MARK not in d and TRASH_MARK not in d]
        for name in files:
            if name == MANIFEST_NAME:
                continue
            if not owned_by_skyroute(os.path.join(root, name), final):
                return False
        for d in dirs:
            if os.path.islink(os.path.join(root, d)):
                return False
    return True


def _sweep(final: Path, prefix: str = "") -> None:
    """Remove the staging and trash folders that killed commands left in ``final`` (with
    ``prefix``: only those whose names start with it)."""
    try:
        names = os.listdir(final)
    except OSError:
        return
    for name in names:
        if STAGING_MARK not in name and TRASH_MARK not in name or not name.startswith(prefix):
            continue
        p = final / name
        try:
            pid = int(name.split("-")[-2])
        except (ValueError, IndexError):
            continue
        if p.is_dir() and not p.is_symlink() and not _pid_alive(pid):
            shutil.rmtree(p, ignore_errors=True)


def folder_of(path: str | Path) -> OutFolder | None:
    """The open output folder whose staging folder is ``path`` (or holds it)."""
    s = os.path.abspath(os.fspath(path))
    for f in reversed(_OPEN):
        base = os.path.abspath(f.path)
        if not f.committed and (s == base or s.startswith(base + os.sep)):
            return f
    return None


def shown(p: str | Path) -> Path:
    """``p`` as the user will find it once the command ends (a staged file's final place)."""
    f = folder_of(p)
    return f.shown(p) if f is not None else Path(p)


def commit_all() -> None:
    """Put every open output folder into place (the command succeeded, or ended with a result
    such as exit 3 "no flyable plan" after writing it)."""
    try:
        while _OPEN:
            f = _OPEN[0]
            f.commit()
            _OPEN.pop(0)
    finally:
        discard_all()


def discard_all() -> None:
    """Drop every open staging folder (the command failed or was interrupted: ``--out`` stays
    as it was)."""
    while _OPEN:
        _OPEN.pop().discard()


#: Top-level names skyroute commands write into --out: an input there is refused before any work.
_OUTPUT_NAMES = frozenset({
    "summary.json", "report.html", "surface.tif", "datasets", "figures", "plan", "fly", "maps.png",
    "candidates.csv", "waypoints.csv", "plan.geojson", "plan.kml", "plan.plan", "plan.gpkg", "plan.html",
    "intent.json", "top_view.png", "profile.png", "sigma_p.png", "bubble.png", "flown.csv", "flown.geojson",
    "intruders.geojson", "fly.html", "fleet.csv", "fleet.geojson", "tracks.csv", "fleet.png", "intents",
    "airspace.sqlite", "compare.csv", "compare.png", "navsim.csv", "coverage", "maps",
})


def scenario_inputs(sc) -> list[str]:
    """Every file a scenario names (its YAML, data files, almanacs, vehicle file...)."""
    keys = {"path", "landuse", "landing_sites", "nofly_zones", "risk_tags", "almanacs", "source_path", "zones"}
    out: list[str] = []

    def walk(node: Any, key: str = "") -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, str(k))
        elif isinstance(node, list | tuple):
            for v in node:
                walk(v, key)
        elif isinstance(node, str | Path) and key in keys and str(node):
            out.append(os.fspath(node))

    try:
        walk(sc.model_dump())
    except Exception:   # noqa: BLE001 - a model that cannot dump has no paths to protect here
        pass
    src = getattr(sc, "source_path", None)
    if src:
        out.append(os.fspath(src))
    return out


def note_scenario_inputs(sc) -> None:
    """Record the scenario's files as inputs of the running command."""
    from skyroute.stages.base import note_input

    for p in scenario_inputs(sc):
        note_input(p)
