"""A persistent airspace: accepted ASTM F3548 operational intents and their 4-D volumes in SQLite.

One file per airspace (a city's airspace for a day, say).  SQLite in WAL mode
(``journal_mode=WAL``, ``synchronous=FULL``) holds:

* ``meta``: ``schema_version``, ``crs`` (WKT of the metric map CRS the volumes are stored in),
  ``epoch_utc`` (time 0 of the volumes' times [s]), ``created_utc``;
* ``intents``: one row per accepted operational intent: ``id``, ``seq`` (order of acceptance),
  ``state`` (F3548 ``OperationalIntentState``, ``Accepted``), ``priority`` (F3548, higher
  wins), ``operator``, ``details`` (the F3548 ``OperationalIntentDetails`` JSON, lat/lng and
  W84 altitudes), ``mission`` (the mission's fields as JSON: start, goal, earliest departure,
  vehicle, DOP level, scenario), ``departure_utc``, ``t_start_s`` / ``t_end_s`` (time span of its
  volumes [s after the epoch]), ``accepted_utc``, ``n_volumes``;
* ``volumes``: one row per 4-D volume of an intent: the outline polygon as WKB in the map CRS
  [m] (float64, exactly the polygon that was checked), ``alt_lower_m`` / ``alt_upper_m``
  (WGS 84 ellipsoidal [m]), ``t_start_s`` / ``t_end_s`` [s after the epoch];
* ``volume_rtree``: the SQLite R*Tree module over (x, y, altitude, time) boxes of the volumes,
  the space-time index (32-bit floats rounded outwards by SQLite, so a box always holds its
  volume);
* ``decisions``: the decision of every mission planned against the airspace (``accepted``,
  ``delayed``, ``preempted-replanned``, ``rejected`` with the reason) and its mission fields,
  so that a later run continues where an earlier one stopped.

Every change (:meth:`AirspaceStore.accept`, :meth:`AirspaceStore.withdraw`,
:meth:`AirspaceStore.record_decision`) is ONE transaction (``BEGIN IMMEDIATE``): a process
killed at any moment leaves either the whole change or none of it.  :meth:`AirspaceStore.accept`
re-checks the new volumes against the store inside its transaction, so two processes adding
to one airspace cannot both accept intersecting intents.

Conflicts: the R*Tree proposes the candidate volumes whose boxes overlap (closed intervals,
:meth:`AirspaceStore.candidates`); the exact test is :func:`skyroute.stages.fleet.pairs_intersect`
(its one home: altitude and time overlap as open intervals, outline area > 1e-4 m^2, F3548's
1 cm precision).  :meth:`AirspaceStore.check` tests the store's own consistency (the SQLite
integrity check, rows, index boxes, F3548 documents against the stored volumes).

A damaged file is read strictly: the meta ``crs`` must be the WKT of a projected CRS and
``epoch_utc`` a UTC time of the years 1900..2200; every row is checked where it is read
(:meth:`AirspaceStore._record`, :meth:`AirspaceStore._volume_numbers`): integers stored as
integers (``priority`` a 32-bit integer, ``seq`` and ``n_volumes`` >= 1, ``k`` >= 0), altitudes
finite within +-``MAX_ABS_ALT_M``, times finite within +-``MAX_ABS_TIME_S`` of the epoch, texts
valid UTF-8.  Anything else is ONE InputError naming the file, the intent (and volume) and the
field, with the fix (restore the file from a copy, or ``skyroute airspace rm FILE ID``).
"""

from __future__ import annotations

import datetime as dt
import json
import math
import os
import sqlite3
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import shapely

from skyroute.stages.base import InputError, SkyrouteError
from skyroute.stages.fleet import MIN_AREA_M2, Volume4, pairs_intersect

__all__ = ["MAX_ABS_ALT_M", "MAX_ABS_TIME_S", "SCHEMA_VERSION", "AirspaceConflictError", "AirspaceStore",
           "IntentRecord", "STATES"]

SCHEMA_VERSION = 1
STATES = ("Accepted", "Activated", "Nonconforming", "Contingent")   # F3548 OperationalIntentState
_PAUSE_ENV = "SKYROUTE_TEST_ACCEPT_PAUSE_S"   # test instrumentation: sleep inside accept's transaction
MAX_ABS_TIME_S = 1e9          # a stored time [s after the epoch] is within +-1e9 s (~31.7 years) of the epoch
MAX_ABS_ALT_M = 1e6           # a stored altitude [m] is within +-1000 km
_PRIORITY_RANGE = (-(2**31), 2**31 - 1)       # F3548 priority: a 32-bit integer (the fleet file's range)
_EPOCH_YEARS = (1900, 2200)   # epoch_utc +- MAX_ABS_TIME_S stays inside pandas' time range

_DDL = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS intents (
    id TEXT PRIMARY KEY,
    seq INTEGER NOT NULL UNIQUE,
    state TEXT NOT NULL,
    priority INTEGER NOT NULL,
    operator TEXT NOT NULL DEFAULT '',
    details TEXT NOT NULL,
    mission TEXT NOT NULL DEFAULT '{}',
    departure_utc TEXT NOT NULL DEFAULT '',
    t_start_s REAL NOT NULL,
    t_end_s REAL NOT NULL,
    accepted_utc TEXT NOT NULL,
    n_volumes INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS volumes (
    vid INTEGER PRIMARY KEY,
    intent_id TEXT NOT NULL REFERENCES intents(id) ON DELETE CASCADE,
    k INTEGER NOT NULL,
    outline_wkb BLOB NOT NULL,
    alt_lower_m REAL NOT NULL,
    alt_upper_m REAL NOT NULL,
    t_start_s REAL NOT NULL,
    t_end_s REAL NOT NULL,
    UNIQUE (intent_id, k)
);
CREATE INDEX IF NOT EXISTS volumes_intent ON volumes (intent_id);
CREATE VIRTUAL TABLE IF NOT EXISTS volume_rtree USING rtree(
    vid, min_x, max_x, min_y, max_y, min_alt, max_alt, min_t, max_t);
CREATE TABLE IF NOT EXISTS decisions (
    mission TEXT PRIMARY KEY,
    status TEXT NOT NULL,
    reason TEXT NOT NULL DEFAULT '',
    mission_fields TEXT NOT NULL DEFAULT '{}',
    decided_utc TEXT NOT NULL
);
"""


class AirspaceConflictError(SkyrouteError):
    """An intent given to :meth:`AirspaceStore.accept` intersects intents already in the store
    (``conflicts_with``: their ids)."""

    def __init__(self, intent_id, conflicts_with: Sequence[str]):
        self.conflicts_with = tuple(conflicts_with)
        super().__init__(f"intent {intent_id} intersects the accepted intent(s) {', '.join(self.conflicts_with)} "
                         "of the airspace (accepted meanwhile by another process?)")


@dataclass(frozen=True)
class IntentRecord:
    """One row of ``intents`` (``details``: the F3548 document, None unless asked for)."""

    id: str
    seq: int
    state: str
    priority: int
    operator: str
    n_volumes: int
    t_start_s: float
    t_end_s: float
    departure_utc: str
    accepted_utc: str
    mission: dict
    details: dict | None = None


def _now_utc() -> str:
    return dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def _utc(t) -> dt.datetime:
    import pandas as pd

    x = pd.Timestamp(t)
    x = x.tz_localize("UTC") if x.tzinfo is None else x.tz_convert("UTC")
    return x.to_pydatetime()


def _iso(text: str) -> dt.datetime:
    """An RFC 3339 UTC time (``...Z``) as an aware datetime (fast path; others via pandas)."""
    try:
        x = dt.datetime.fromisoformat(str(text).replace("Z", "+00:00"))
        return x if x.tzinfo is not None else x.replace(tzinfo=dt.UTC)
    except ValueError:
        return _utc(text)


def _shown(v, n: int = 40) -> str:
    """``repr(v)`` cut to ``n`` characters (a damaged value in a one-line error)."""
    r = repr(v)
    return r if len(r) <= n else r[:n] + "..."


def _stored_int(v, lo: int, hi: int) -> int | None:
    """A stored integer in ``lo..hi`` (an integral finite float too), else None (text, bytes,
    inf, out of range)."""
    if isinstance(v, float) and math.isfinite(v) and v.is_integer():
        v = int(v)
    if isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi:
        return v
    return None


def _stored_real(v, bound: float) -> float | None:
    """A stored finite number within +-``bound`` as a float, else None (text, bytes, NaN, inf,
    out of range)."""
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        x = float(v)
        if math.isfinite(x) and abs(x) <= bound:
            return x
    return None


def _strict_text(path: Path):
    """The connection's ``text_factory``: UTF-8, or the one-line error of a damaged file (bytes
    flipped in a stored text)."""
    def decode(b: bytes) -> str:
        try:
            return b.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise InputError(f"{path}: a text stored in the airspace file is not valid UTF-8 ({exc.reason} at "
                             f"byte {exc.start}); the file is damaged: restore it from a copy") from None
    return decode


def _box(v: Volume4) -> tuple[float, ...]:
    x0, y0, x1, y1 = v.polygon.bounds
    return (x0, x1, y0, y1, v.alt_lower_m, v.alt_upper_m, v.t_start_s, v.t_end_s)


class AirspaceStore:
    """An airspace file (see the module docstring).  Open with :meth:`open`, :meth:`create` or
    :meth:`open_or_create`; a context manager (closes the connection)."""

    def __init__(self, path: Path, conn: sqlite3.Connection):
        self.path = Path(path)
        self._conn = conn
        meta = dict(conn.execute("SELECT key, value FROM meta").fetchall())
        self.crs_wkt: str = meta.get("crs")
        self._crs = self._meta_crs(self.crs_wkt)
        self.epoch_utc: dt.datetime = self._meta_epoch(meta.get("epoch_utc"))
        self.schema_version = int(meta["schema_version"])

    def _meta_damaged(self, key: str, value, what: str) -> InputError:
        return InputError(f"{self.path}: the airspace's meta table is damaged: its {key} {_shown(value)} {what}; "
                          "restore the file from a copy")

    def _meta_crs(self, wkt):
        """The pyproj CRS of the meta ``crs`` (WKT of a projected CRS), else the one-line error."""
        from pyproj import CRS
        from pyproj.exceptions import CRSError

        try:
            c = CRS.from_wkt(wkt)
        except (CRSError, TypeError, ValueError) as exc:
            raise self._meta_damaged("crs", wkt, f"is not the WKT of a CRS ({str(exc)[:60]})") from None
        if not c.is_projected:
            raise self._meta_damaged("crs", wkt, f"is not a projected (metric) CRS ({c.name})")
        return c

    def _meta_epoch(self, text) -> dt.datetime:
        """The meta ``epoch_utc`` (a UTC time of the years 1900..2200), else the one-line error."""
        try:
            t = _utc(text) if isinstance(text, str) else None
        except (ValueError, TypeError, OverflowError) as exc:
            raise self._meta_damaged("epoch_utc", text, f"is not a UTC time ({str(exc)[:60]})") from None
        if not isinstance(t, dt.datetime) or not _EPOCH_YEARS[0] <= t.year <= _EPOCH_YEARS[1]:
            raise self._meta_damaged("epoch_utc", text, f"is not a UTC time of the years {_EPOCH_YEARS[0]}.."
                                     f"{_EPOCH_YEARS[1]}")
        return t

    # ------------------------------------------------------------------ opening
    @staticmethod
    def _connect(path: Path) -> sqlite3.Connection:
        conn = sqlite3.connect(str(path), timeout=30.0, isolation_level=None)   # explicit transactions
        conn.text_factory = _strict_text(Path(path))    # flipped bytes in a text: one error line
        conn.execute("PRAGMA journal_mode=WAL")
        conn.execute("PRAGMA synchronous=FULL")
        conn.execute("PRAGMA foreign_keys=ON")
        return conn

    @classmethod
    def open(cls, path: Path | str) -> AirspaceStore:
        """An existing airspace file; InputError (one line: what is wrong, how to fix it) when
        ``path`` is missing or is not a skyroute airspace of a known schema."""
        path = Path(path)
        if path.is_dir():
            raise InputError(f"{path} is a folder; give an airspace file (e.g. {path / 'airspace.sqlite'})")
        if not path.is_file():
            raise InputError(f"airspace file {path} does not exist; give the FILE written by "
                             "`skyroute fleet --airspace FILE` (or OUT/airspace.sqlite)")
        with open(path, "rb") as f:
            head = f.read(16)
        if head != b"SQLite format 3\x00":
            raise InputError(f"{path} is not an airspace file (not an SQLite database); give the FILE written by "
                             "`skyroute fleet --airspace FILE`")
        conn = None
        try:
            conn = cls._connect(path)
            names = {r[0] for r in conn.execute("SELECT name FROM sqlite_master")}
            need = {"meta", "intents", "volumes", "volume_rtree", "decisions"}
            if not need <= names:
                raise InputError(f"{path} is an SQLite database but not a skyroute airspace (missing table(s) "
                                 f"{', '.join(sorted(need - names))})")
            meta = dict(conn.execute("SELECT key, value FROM meta").fetchall())
            if str(meta.get("schema_version")) != str(SCHEMA_VERSION) or not {"crs", "epoch_utc"} <= set(meta):
                raise InputError(f"{path} has airspace schema version {_shown(meta.get('schema_version'))}; this "
                                 f"skyroute reads version {SCHEMA_VERSION}")
            return cls(path, conn)          # the meta crs and epoch_utc checked: one error line
        except (sqlite3.DatabaseError, UnicodeDecodeError) as exc:   # (SQLite's message of a damaged schema)
            if conn is not None:
                conn.close()
            raise InputError(f"{path} cannot be read as an airspace file ({type(exc).__name__}: {str(exc)[:120]}); "
                             "the file is damaged: restore it from a copy") from None
        except BaseException:
            if conn is not None:
                conn.close()
            raise

    @classmethod
    def create(cls, path: Path | str, crs, epoch_utc, *, replace: bool = False) -> AirspaceStore:
        """A new, empty airspace at ``path`` whose volumes are in the metric ``crs`` (anything
        pyproj reads) with times in seconds after ``epoch_utc``; ``replace``: replace an
        existing file, else InputError when it exists.  Written under a temporary name and
        renamed: a process killed meanwhile leaves no half-made file at ``path``."""
        from pyproj import CRS

        path = Path(path)
        if path.exists() and not replace:
            raise InputError(f"airspace file {path} exists already")
        c = CRS.from_user_input(crs)
        if not c.is_projected:
            raise InputError(f"an airspace needs a projected (metric) CRS, got {c.name}")
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        for suffix in ("", "-wal", "-shm", "-journal"):
            Path(str(tmp) + suffix).unlink(missing_ok=True)
        conn = cls._connect(tmp)
        conn.execute("BEGIN IMMEDIATE")
        for stmt in _DDL.split(";"):
            if stmt.strip():
                conn.execute(stmt)
        conn.executemany("INSERT INTO meta VALUES (?, ?)", [
            ("schema_version", str(SCHEMA_VERSION)), ("crs", c.to_wkt()),
            ("epoch_utc", _utc(epoch_utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")), ("created_utc", _now_utc())])
        conn.execute("COMMIT")
        conn.close()                       # checkpoints the WAL into the file (WAL mode stays set)
        for suffix in ("-wal", "-shm", "-journal"):
            Path(str(path) + suffix).unlink(missing_ok=True)
        os.replace(tmp, path)
        return cls(path, cls._connect(path))

    @classmethod
    def open_or_create(cls, path: Path | str, crs, epoch_utc) -> AirspaceStore:
        """:meth:`open` when ``path`` exists, else :meth:`create`."""
        return cls.open(path) if Path(path).exists() else cls.create(path, crs, epoch_utc)

    def close(self) -> None:
        self._conn.close()

    def __enter__(self) -> AirspaceStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ reading
    def __len__(self) -> int:
        return int(self._conn.execute("SELECT COUNT(*) FROM intents").fetchone()[0])

    def n_volumes(self) -> int:
        return int(self._conn.execute("SELECT COUNT(*) FROM volumes").fetchone()[0])

    def time_shift_s(self, start_time_utc) -> float:
        """Seconds [s] to add to mission times counted from ``start_time_utc`` to get store times."""
        return (_utc(start_time_utc) - self.epoch_utc).total_seconds()

    def same_crs(self, crs) -> bool:
        from pyproj import CRS

        return CRS.from_user_input(crs) == self._crs

    _COLS = "id, seq, state, priority, operator, n_volumes, t_start_s, t_end_s, departure_utc, accepted_utc, mission"

    def _damaged(self, intent_id, what: str) -> InputError:
        """The one-line error of an intent whose stored row cannot be read."""
        import shlex

        ident = str(intent_id)
        shown = repr(ident[:64]) + ("..." if len(ident) > 64 else "")
        rm = f"skyroute airspace rm {shlex.quote(str(self.path))} {shlex.quote(ident) if len(ident) <= 64 else 'ID'}"
        return InputError(f"{self.path}: intent {shown}: {what}; the file is damaged: restore it from a copy, or "
                          f"remove that intent (`{rm}`) and plan its mission again")

    def _json(self, intent_id, column: str, text, kind=dict):
        """``json.loads(text)`` of a stored column, or the one-line error naming the intent."""
        try:
            doc = json.loads(text)
        except (TypeError, ValueError, RecursionError) as exc:
            raise self._damaged(intent_id, f"its {column} is not valid JSON ({str(exc)[:80]})") from None
        if not isinstance(doc, kind):
            raise self._damaged(intent_id, f"its {column} is a JSON {type(doc).__name__}, not an object")
        return doc

    def _int(self, intent_id, where: str, field: str, v, lo: int, hi: int) -> int:
        x = _stored_int(v, lo, hi)
        if x is None:
            raise self._damaged(intent_id, f"{where}{field} {_shown(v)} is not an integer in {lo:,}..{hi:,}")
        return x

    def _real(self, intent_id, where: str, field: str, v, bound: float, unit: str) -> float:
        x = _stored_real(v, bound)
        if x is None:
            raise self._damaged(intent_id, f"{where}{field} {_shown(v)} is not a finite number within "
                                f"+-{bound:g} {unit}")
        return x

    def _volume_numbers(self, intent_id, k, a0, a1, t0, t1) -> tuple[int, float, float, float, float]:
        """``(k, alt_lower_m, alt_upper_m, t_start_s, t_end_s)`` of a stored volume row, checked
        (k an integer >= 0, altitudes [m] finite within +-MAX_ABS_ALT_M, times [s after the
        epoch] finite within +-MAX_ABS_TIME_S), else the one-line error naming the intent, the
        volume and the field."""
        k = self._int(intent_id, "a volume's ", "k", k, 0, 2**63 - 1)
        w = f"volume {k}: its "
        return (k, self._real(intent_id, w, "alt_lower_m", a0, MAX_ABS_ALT_M, "m"),
                self._real(intent_id, w, "alt_upper_m", a1, MAX_ABS_ALT_M, "m"),
                self._real(intent_id, w, "t_start_s", t0, MAX_ABS_TIME_S, "s of the epoch"),
                self._real(intent_id, w, "t_end_s", t1, MAX_ABS_TIME_S, "s of the epoch"))

    def _record(self, row, details=None) -> IntentRecord:
        """The IntentRecord of a stored ``intents`` row (columns ``_COLS`` [+ details]), every field
        checked (texts are texts; seq and n_volumes integers >= 1, priority a 32-bit integer,
        times [s after the epoch] finite within +-MAX_ABS_TIME_S; mission and details JSON
        objects), else the one-line error naming the intent and the field."""
        m = row[0]
        if not isinstance(m, str):
            raise self._damaged(m, f"its id is a {type(m).__name__}, not a text")
        for i, name in ((2, "state"), (4, "operator"), (8, "departure_utc"), (9, "accepted_utc")):
            if not isinstance(row[i], str):
                raise self._damaged(m, f"its {name} {_shown(row[i])} is not a text")
        seq = self._int(m, "its ", "seq", row[1], 1, 2**63 - 1)
        priority = self._int(m, "its ", "priority", row[3], *_PRIORITY_RANGE)
        n_vol = self._int(m, "its ", "n_volumes", row[5], 1, 2**31 - 1)
        t0 = self._real(m, "its ", "t_start_s", row[6], MAX_ABS_TIME_S, "s of the epoch")
        t1 = self._real(m, "its ", "t_end_s", row[7], MAX_ABS_TIME_S, "s of the epoch")
        return IntentRecord(m, seq, row[2], priority, row[4], n_vol, t0, t1, row[8], row[9],
                            self._json(m, "mission fields", row[10]),
                            None if details is None else self._json(m, "F3548 document (details)", details))

    def records(self, details: bool = False) -> list[IntentRecord]:
        """Every intent, in order of acceptance."""
        cols = self._COLS + (", details" if details else "")
        return [self._record(r[:11], r[11] if details else None)
                for r in self._conn.execute(f"SELECT {cols} FROM intents ORDER BY seq")]

    def record(self, intent_id: str) -> IntentRecord:
        """The intent ``intent_id`` with its F3548 document; InputError when it is not there."""
        r = self._conn.execute(f"SELECT {self._COLS}, details FROM intents WHERE id = ?", (intent_id,)).fetchone()
        if r is None:
            raise InputError(f"no intent {intent_id!r} in the airspace {self.path} (`skyroute airspace ls "
                             f"{self.path}` lists them)")
        return self._record(r[:11], r[11])

    def has(self, intent_id: str) -> bool:
        return self._conn.execute("SELECT 1 FROM intents WHERE id = ?", (intent_id,)).fetchone() is not None

    def decisions(self) -> dict[str, tuple[str, str, dict]]:
        """mission -> (status, reason, mission fields) of every decided mission."""
        out = {}
        for m, s, r, f in self._conn.execute("SELECT mission, status, reason, mission_fields FROM decisions"):
            for name, v in (("mission id", m), ("status", s), ("reason", r)):
                if not isinstance(v, str):
                    raise self._damaged(m, f"its decision's {name} {_shown(v)} is not a text")
            out[m] = (s, r, self._json(m, "decision's mission fields", f))
        return out

    def _vol(self, row, intent_id: str = "?", k: int | str = "?") -> Volume4:
        """A stored volume (WKB outline, altitudes [m], times [s]); the one-line error naming the
        intent and the volume when its outline is not a valid polygon's WKB."""
        try:
            poly = shapely.from_wkb(row[0])
        except (shapely.errors.GEOSException, TypeError, ValueError) as exc:
            raise self._damaged(intent_id, f"volume {k}: its outline is not valid WKB ({str(exc)[:80]})") from None
        if not isinstance(poly, shapely.Polygon) or poly.is_empty:
            raise self._damaged(intent_id, f"volume {k}: its outline is a {poly.geom_type}, not a polygon")
        _, a0, a1, t0, t1 = self._volume_numbers(intent_id, k, *row[1:5])
        return Volume4(poly, a0, a1, t0, t1)

    def volumes(self, ids: Iterable[str] | None = None, t_shift_s: float = 0.0) -> dict[str, list[Volume4]]:
        """intent id -> its volumes (store CRS; times [s after the epoch] minus ``t_shift_s``)."""
        q = "SELECT intent_id, outline_wkb, alt_lower_m, alt_upper_m, t_start_s, t_end_s, k FROM volumes"
        if ids is None:
            rows = self._conn.execute(q + " ORDER BY intent_id, k").fetchall()
        else:
            ids = list(ids)
            rows = []
            for i in range(0, len(ids), 500):
                part = ids[i:i + 500]
                rows += self._conn.execute(q + f" WHERE intent_id IN ({','.join('?' * len(part))}) "
                                           "ORDER BY intent_id, k", part).fetchall()
        out: dict[str, list[Volume4]] = {}
        for r in rows:
            v = self._vol(r[1:6], r[0], r[6])
            if t_shift_s:
                v = Volume4(v.polygon, v.alt_lower_m, v.alt_upper_m, v.t_start_s - t_shift_s, v.t_end_s - t_shift_s)
            out.setdefault(r[0], []).append(v)
        return out

    def ids_in_box(self, x0: float, y0: float, x1: float, y1: float, t0_s: float, t1_s: float) -> list[str]:
        """Intents with a volume whose index box meets the x/y box [m] and the time window [s
        after the epoch] (closed intervals; any altitude)."""
        return [r[0] for r in self._conn.execute(
            "SELECT DISTINCT v.intent_id FROM volume_rtree r JOIN volumes v ON v.vid = r.vid WHERE "
            "r.max_x >= ? AND r.min_x <= ? AND r.max_y >= ? AND r.min_y <= ? AND r.max_t >= ? AND r.min_t <= ?",
            (x0, x1, y0, y1, t0_s, t1_s))]

    def candidates(self, vols: Sequence[Volume4]) -> tuple[np.ndarray, np.ndarray]:
        """``(qidx, vid)``: the stored volumes (row ids) whose R*Tree boxes meet the box of
        ``vols[qidx]`` in x, y, altitude and time (closed intervals: a superset of the pairs that
        intersect)."""
        qi, vi = [], []
        cur = self._conn.cursor()
        for i, v in enumerate(vols):
            x0, x1, y0, y1, a0, a1, t0, t1 = _box(v)
            got = cur.execute("SELECT vid FROM volume_rtree WHERE max_x >= ? AND min_x <= ? AND max_y >= ? AND "
                              "min_y <= ? AND max_alt >= ? AND min_alt <= ? AND max_t >= ? AND min_t <= ?",
                              (x0, x1, y0, y1, a0, a1, t0, t1)).fetchall()
            qi += [i] * len(got)
            vi += [g[0] for g in got]
        return np.asarray(qi, np.intp), np.asarray(vi, np.int64)

    def _load_vids(self, vids: np.ndarray) -> dict[int, tuple[str, Volume4]]:
        out = {}
        u = np.unique(vids).tolist()
        for i in range(0, len(u), 500):
            part = u[i:i + 500]
            for r in self._conn.execute("SELECT vid, intent_id, outline_wkb, alt_lower_m, alt_upper_m, t_start_s, "
                                        f"t_end_s, k FROM volumes WHERE vid IN ({','.join('?' * len(part))})", part):
                out[int(r[0])] = (r[1], self._vol(r[2:7], r[1], r[7]))
        return out

    def conflicts(self, vols: Sequence[Volume4], *, exclude: Iterable[str] = (),
                  min_area_m2: float = MIN_AREA_M2) -> list[tuple[int, str]]:
        """``(i, intent id)`` pairs: ``vols[i]`` (store CRS and times) intersects a volume of that
        stored intent (R*Tree candidates, then :func:`~skyroute.stages.fleet.pairs_intersect`);
        intents in ``exclude`` are left out."""
        vols = list(vols)
        qidx, vids = self.candidates(vols)
        if not qidx.size:
            return []
        got = self._load_vids(vids)
        ex = set(exclude)
        keep = np.array([int(v) in got and got[int(v)][0] not in ex for v in vids], bool)   # (orphan boxes: check())
        qidx, vids = qidx[keep], vids[keep]
        if not qidx.size:
            return []
        order = {v: k for k, v in enumerate(got)}
        avols = [got[v][1] for v in got]
        ok = pairs_intersect(vols, avols, qidx, [order[int(v)] for v in vids], min_area_m2)
        return sorted({(int(i), got[int(v)][0]) for i, v in zip(qidx[ok], vids[ok], strict=True)})

    # ------------------------------------------------------------------ writing (one transaction each)
    def accept(self, intent_id: str, details: dict, vols: Sequence[Volume4], *, priority: int = 0,
               operator: str = "", mission: dict | None = None, departure_utc: str = "", state: str = "Accepted",
               withdraw: Iterable[str] = (), decision: tuple[str, str] | None = None,
               min_area_m2: float = MIN_AREA_M2) -> None:
        """Add the intent ``intent_id`` (F3548 ``details``, its volumes ``vols`` in the store CRS
        and times) in ONE transaction: the intents in ``withdraw`` (preempted) are removed
        first, the volumes are checked against the rest of the store (R*Tree + exact test;
        :class:`AirspaceConflictError` and nothing written when they intersect), then the
        intent, its volumes and their index boxes are written, with the mission's
        ``decision`` ((status, reason); default ``("accepted", "")``).  An intent of the same
        id already there is replaced."""
        vols = list(vols)
        if not vols:
            raise InputError(f"intent {intent_id!r} has no volume")
        if state not in STATES:
            raise InputError(f"state {state!r} is not an F3548 operational intent state ({', '.join(STATES)})")
        if len(details.get("volumes", ())) != len(vols):
            raise InputError(f"intent {intent_id!r}: {len(details.get('volumes', ()))} F3548 volumes but "
                             f"{len(vols)} map volumes")
        status, reason = decision or ("accepted", "")
        mission = dict(mission or {})
        c = self._conn
        c.execute("BEGIN IMMEDIATE")
        try:
            gone = [*withdraw, intent_id]
            for m in gone:
                self._delete(m)
            hit = self.conflicts(vols, min_area_m2=min_area_m2)
            if hit:
                raise AirspaceConflictError(intent_id, sorted({m for _, m in hit}))
            seq = int(c.execute("SELECT COALESCE(MAX(seq), 0) + 1 FROM intents").fetchone()[0])
            c.execute("INSERT INTO intents (id, seq, state, priority, operator, details, mission, departure_utc, "
                      "t_start_s, t_end_s, accepted_utc, n_volumes) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                      (intent_id, seq, state, int(priority), operator, json.dumps(details, allow_nan=False),
                       json.dumps(mission, allow_nan=False), departure_utc, min(v.t_start_s for v in vols),
                       max(v.t_end_s for v in vols), _now_utc(), len(vols)))
            pause = float(os.environ.get(_PAUSE_ENV, "0") or 0)
            for k, v in enumerate(vols):
                cur = c.execute("INSERT INTO volumes (intent_id, k, outline_wkb, alt_lower_m, alt_upper_m, t_start_s, "
                                "t_end_s) VALUES (?, ?, ?, ?, ?, ?, ?)",
                                (intent_id, k, shapely.to_wkb(v.polygon), v.alt_lower_m, v.alt_upper_m,
                                 v.t_start_s, v.t_end_s))
                c.execute("INSERT INTO volume_rtree VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)", (cur.lastrowid, *_box(v)))
                if pause and k == 0:
                    time.sleep(pause)    # test instrumentation: a SIGKILL lands inside the transaction
            c.execute("INSERT OR REPLACE INTO decisions VALUES (?, ?, ?, ?, ?)",
                      (intent_id, status, reason, json.dumps(mission, allow_nan=False), _now_utc()))
            for m in withdraw:           # a preempted mission is undecided again (re-planned next)
                c.execute("DELETE FROM decisions WHERE mission = ?", (m,))
            c.execute("COMMIT")
        except BaseException:
            c.execute("ROLLBACK")
            raise

    def _delete(self, intent_id: str) -> None:
        c = self._conn
        c.execute("DELETE FROM volume_rtree WHERE vid IN (SELECT vid FROM volumes WHERE intent_id = ?)", (intent_id,))
        c.execute("DELETE FROM volumes WHERE intent_id = ?", (intent_id,))
        c.execute("DELETE FROM intents WHERE id = ?", (intent_id,))

    def withdraw(self, ids: Iterable[str]) -> None:
        """Remove the intents ``ids`` (and their volumes and index boxes) in one transaction;
        their missions become undecided."""
        c = self._conn
        c.execute("BEGIN IMMEDIATE")
        try:
            for m in ids:
                self._delete(m)
                c.execute("DELETE FROM decisions WHERE mission = ?", (m,))
            c.execute("COMMIT")
        except BaseException:
            c.execute("ROLLBACK")
            raise

    def record_decision(self, mission: str, status: str, reason: str = "", fields: dict | None = None) -> None:
        """Record a decision without an intent (``rejected`` and its reason) in one transaction."""
        c = self._conn
        c.execute("BEGIN IMMEDIATE")
        try:
            c.execute("INSERT OR REPLACE INTO decisions VALUES (?, ?, ?, ?, ?)",
                      (mission, status, reason, json.dumps(fields or {}, allow_nan=False), _now_utc()))
            c.execute("COMMIT")
        except BaseException:
            c.execute("ROLLBACK")
            raise

    # ------------------------------------------------------------------ checks
    def check(self, tol_m: float = 1e-3) -> list[str]:
        """Problems of the store's consistency (empty when consistent): SQLite's integrity
        check; every intent has its ``n_volumes`` volumes (k = 0..n-1), each with an R*Tree box
        holding it, and no volume or box without an intent; an accepted decision for every
        intent; F3548 documents that parse, with the stored volumes' count, altitudes, times
        (the document's rounded outwards to the millisecond, by less than 1 ms + 1 us) and
        outlines (vertices within ``tol_m`` [m] of the stored polygon's, after projecting)."""
        from pyproj import Transformer

        c = self._conn
        out = [f"sqlite integrity: {r[0]}" for r in c.execute("PRAGMA integrity_check") if r[0] != "ok"]
        out += [f"R*Tree: {r[0]}" for r in c.execute("SELECT rtreecheck('volume_rtree')") if r[0] != "ok"]
        for (m,) in c.execute("SELECT DISTINCT intent_id FROM volumes WHERE intent_id NOT IN (SELECT id FROM intents)"):
            out.append(f"volumes of intent {m} which is not in the intents table")
        n_orphan = c.execute("SELECT COUNT(*) FROM volume_rtree WHERE vid NOT IN (SELECT vid FROM volumes)").fetchone()[0]
        if n_orphan:
            out.append(f"{n_orphan} R*Tree box(es) without a volume")
        dec = self.decisions()
        tr = Transformer.from_crs(4326, self._crs, always_xy=True)
        vols_rows: dict[str, list] = {}
        for r in c.execute("SELECT v.intent_id, v.k, v.outline_wkb, v.alt_lower_m, v.alt_upper_m, v.t_start_s, "
                           "v.t_end_s, b.min_x, b.max_x, b.min_y, b.max_y, b.min_alt, b.max_alt, b.min_t, b.max_t "
                           "FROM volumes v LEFT JOIN volume_rtree b ON b.vid = v.vid ORDER BY v.intent_id, v.k"):
            vols_rows.setdefault(r[0], []).append(r[1:])
        for rec in self.records(details=True):
            rows = []
            for r in vols_rows.get(rec.id, []):     # (k, wkb, a0, a1, t0, t1, box...): numbers checked
                k, a0, a1, t0, t1 = self._volume_numbers(rec.id, r[0], *r[2:6])
                rows.append((k, r[1], a0, a1, t0, t1, *r[6:]))
            if rec.state not in STATES:
                out.append(f"intent {rec.id}: state {rec.state!r} is not an F3548 state")
            if rec.id not in dec or dec[rec.id][0] == "rejected":
                out.append(f"intent {rec.id}: no accepted decision recorded")
            if [r[0] for r in rows] != list(range(rec.n_volumes)):
                out.append(f"intent {rec.id}: {len(rows)} volume rows, expected {rec.n_volumes} (k = 0..n-1)")
                continue
            span = (min(r[4] for r in rows), max(r[5] for r in rows))
            if (rec.t_start_s, rec.t_end_s) != span:
                out.append(f"intent {rec.id}: its time span {rec.t_start_s:.6g}..{rec.t_end_s:.6g} s differs from its "
                           f"volumes' {span[0]:.6g}..{span[1]:.6g} s")
            for name, text in (("departure_utc", rec.departure_utc), ("accepted_utc", rec.accepted_utc)):
                if text or name == "accepted_utc":
                    try:
                        ok = _iso(text).year > 0          # (NaT: its year is NaN)
                    except (ValueError, TypeError, OverflowError):
                        ok = False
                    if not ok:
                        out.append(f"intent {rec.id}: its {name} {_shown(text)} is not a UTC time")
            dvs = rec.details.get("volumes", []) if isinstance(rec.details, dict) else []
            if not isinstance(dvs, list):
                out.append(f"intent {rec.id}: its F3548 document's volumes are a {type(dvs).__name__}, not a list")
                continue
            if len(dvs) != rec.n_volumes:
                out.append(f"intent {rec.id}: its F3548 document has {len(dvs)} volumes, expected {rec.n_volumes}")
                continue
            try:                          # the document's outlines in the store CRS, one transform per intent
                verts = [dv["volume"]["outline_polygon"]["vertices"] for dv in dvs]
                lng = [float(q["lng"]) for vx in verts for q in vx]
                lat = [float(q["lat"]) for vx in verts for q in vx]
                xs, ys = tr.transform(lng, lat)
                cuts = np.cumsum([len(vx) for vx in verts])[:-1]
                doc_xy = np.split(np.column_stack([xs, ys]), cuts)
            except (KeyError, TypeError, ValueError) as exc:
                out.append(f"intent {rec.id}: F3548 document unreadable ({exc})")
                continue
            for r, dv, pts in zip(rows, dvs, doc_xy, strict=True):
                k, wkb, a0, a1, t0, t1 = r[:6]
                box = r[6:]
                try:
                    poly = shapely.from_wkb(wkb)
                except (shapely.errors.GEOSException, TypeError, ValueError):
                    out.append(f"intent {rec.id} volume {k}: unreadable outline (not valid WKB)")
                    continue
                if not isinstance(poly, shapely.Polygon):
                    out.append(f"intent {rec.id} volume {k}: its outline is a {poly.geom_type}, not a polygon")
                    continue
                if box[0] is None:
                    out.append(f"intent {rec.id} volume {k}: no R*Tree box")
                else:
                    bx0, by0, bx1, by1 = poly.bounds
                    if not (box[0] <= bx0 and bx1 <= box[1] and box[2] <= by0 and by1 <= box[3] and box[4] <= a0
                            and a1 <= box[5] and box[6] <= t0 and t1 <= box[7]):
                        out.append(f"intent {rec.id} volume {k}: its R*Tree box does not hold it")
                if not (a1 > a0 and t1 > t0 and poly.is_valid and not poly.is_empty):
                    out.append(f"intent {rec.id} volume {k}: empty or invalid volume")
                try:
                    da0 = float(dv["volume"]["altitude_lower"]["value"])
                    da1 = float(dv["volume"]["altitude_upper"]["value"])
                    dt0 = (_iso(dv["time_start"]["value"]) - self.epoch_utc).total_seconds()
                    dt1 = (_iso(dv["time_end"]["value"]) - self.epoch_utc).total_seconds()
                except (KeyError, TypeError, ValueError) as exc:
                    out.append(f"intent {rec.id} volume {k}: F3548 document unreadable ({exc})")
                    continue
                if (da0, da1) != (a0, a1):
                    out.append(f"intent {rec.id} volume {k}: document altitudes {da0}-{da1} m != stored {a0}-{a1} m")
                if not (-1e-6 <= t0 - dt0 < 1.001e-3 and -1e-6 <= dt1 - t1 < 1.001e-3):
                    out.append(f"intent {rec.id} volume {k}: document times do not round the stored ones outwards "
                               "to the millisecond")
                ring = np.asarray(poly.exterior.coords)[:-1]
                if pts.shape != ring.shape or not np.all(np.hypot(*(pts - ring).T) <= tol_m):
                    out.append(f"intent {rec.id} volume {k}: document outline differs from the stored one "
                               f"by more than {tol_m} m")
        return out

    def self_conflicts(self, min_area_m2: float = MIN_AREA_M2) -> list[tuple[str, str]]:
        """Pairs of stored intents whose volumes intersect, found through the R*Tree (the index
        path; :func:`skyroute.pipeline.fleet.independent_conflicts` is the all-pairs one)."""
        allv = self.volumes()
        bad = set()
        for m, vs in allv.items():
            for _, other in self.conflicts(vs, exclude=(m,), min_area_m2=min_area_m2):
                bad.add(tuple(sorted((m, other))))
        return sorted(bad)
