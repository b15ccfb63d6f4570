"""Damaged airspace files (issue 34, fuzz findings): every damage is ONE `error:` line naming the
file, the intent (and volume) and the field, with the fix, in every `skyroute airspace`
subcommand and when `skyroute fleet --airspace FILE` opens the file; never a traceback.

Each test builds a small valid airspace (two intents "good" and "bad", one volume each) and
damages it with SQL UPDATEs or flipped bytes, as benchmarks/fuzz_inputs.py does."""

from __future__ import annotations

import datetime as dt
import json
import math
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from skyroute.pipeline.cli import main
from skyroute.stages.airspace_store import MAX_ABS_TIME_S, AirspaceStore
from skyroute.stages.base import InputError

CRS, EPOCH = "EPSG:3067", "2020-01-03T10:00:00Z"
X0, Y0 = 385_000.0, 6_672_000.0


def _store(tmp_path: Path, *updates: tuple[str, object], name: str = "air.sqlite") -> Path:
    """A valid airspace file with intents "good" and "bad" (one volume each: 50-60 m, 0-30 s),
    then the SQL ``updates`` (statement, one parameter) applied."""
    import shapely

    from skyroute.stages.fleet import Volume4
    from skyroute.stages.intents import IntentVolume, intent_details

    path = tmp_path / name
    with AirspaceStore.create(path, CRS, EPOCH) as s:
        for k, ident in enumerate(("good", "bad")):
            v = [Volume4(shapely.box(X0 + 100 * k, Y0, X0 + 100 * k + 10, Y0 + 10), 50.0, 60.0, 0.0, 30.0)]
            iv = [IntentVolume(np.asarray(u.polygon.exterior.coords)[:-1], u.alt_lower_m, u.alt_upper_m,
                               u.t_start_s, u.t_end_s, 0.0) for u in v]
            s.accept(ident, intent_details(iv, CRS, EPOCH), v, priority=k, operator=f"op-{k}")
    c = sqlite3.connect(path)
    for stmt, value in updates:
        c.execute(stmt, (value,))
    c.commit()
    c.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    c.close()
    return path


def _cli(args, tmp_path: Path, monkeypatch) -> tuple[int, str, list[str]]:
    """``skyroute ARGS`` in ``tmp_path``: (exit code, output, error lines); never a traceback."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("SKYROUTE_CACHE_DIR", str(tmp_path / "cache"))
    res = CliRunner().invoke(main, [str(a) for a in args])
    assert "Traceback" not in res.output, res.output
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        raise res.exception
    return res.exit_code, res.output, [ln for ln in res.output.splitlines() if ln.startswith("error:")]


def _refused(args, tmp_path: Path, monkeypatch, *words: str) -> str:
    code, out, errors = _cli(args, tmp_path, monkeypatch)
    assert code == 2, out
    assert len(errors) == 1, out
    for w in words:
        assert w in errors[0], (w, out)
    return errors[0]


def _n_intents(path: Path) -> int:
    c = sqlite3.connect(path)
    try:
        return c.execute("SELECT COUNT(*) FROM intents").fetchone()[0]
    finally:
        c.close()


EVERY = [["ls", "{f}"], ["show", "{f}", "bad"], ["export", "{f}", "{o}"], ["check", "{f}"],
         ["check", "{f}", "--json"], ["rm", "{f}", "bad"]]
READS_INTENTS = EVERY[:5]          # rm reads no intent row (a damaged intent can be removed)
READS_VOLUMES = EVERY[3:5]         # check reads the volumes


def _id(v) -> str:
    """A test id: the subcommand (and --json), or the damaged value."""
    return "-".join(v[:1] + [a for a in v[2:] if a.startswith("--")]) if isinstance(v, list) else repr(v)[:10]


def _args(cmd, f: Path, tmp_path: Path) -> list[str]:
    return ["airspace", *[a.format(f=f, o=tmp_path / "exp") for a in cmd]]


# ---------------------------------------------------------------------------------- the meta table
def _geographic_wkt() -> str:
    from pyproj import CRS as PCRS

    return PCRS.from_epsg(4326).to_wkt()


# the fuzz findings' values in every subcommand, more values in two
META_CRS = [(v, c) for v in ("", "nan", "2") for c in EVERY] + [(v, c) for v in ("x" * 10000, b"\x00")
                                                              for c in (EVERY[0], EVERY[3])]


@pytest.mark.parametrize("value, cmd", META_CRS, ids=_id)
def test_meta_crs_damaged(tmp_path, monkeypatch, value, cmd):
    f = _store(tmp_path, ("UPDATE meta SET value = ? WHERE key = 'crs'", value))
    err = _refused(_args(cmd, f, tmp_path), tmp_path, monkeypatch, str(f), "meta table is damaged", "its crs",
                   "is not the WKT of a CRS", "restore the file from a copy")
    assert len(err) < 400                       # the value shown cut
    assert _n_intents(f) == 2                   # rm refused: nothing removed


def test_meta_crs_geographic_and_epoch_damaged(tmp_path, monkeypatch):
    f = _store(tmp_path, ("UPDATE meta SET value = ? WHERE key = 'crs'", _geographic_wkt()))
    _refused(["airspace", "check", f], tmp_path, monkeypatch, "its crs", "is not a projected (metric) CRS (WGS 84)")
    for i, bad in enumerate(("nan", "2100-13-45T99:00:00Z", "1700-01-01T00:00:00Z", "garbage")):
        f = _store(tmp_path, ("UPDATE meta SET value = ? WHERE key = 'epoch_utc'", bad), name=f"e{i}.sqlite")
        _refused(["airspace", "ls", f], tmp_path, monkeypatch, str(f), f"its epoch_utc {bad!r}",
                 "restore the file from a copy")
    with pytest.raises(InputError, match=r"its crs 'nan' is not the WKT of a CRS"):
        AirspaceStore.open(_store(tmp_path, ("UPDATE meta SET value = ? WHERE key = 'crs'", "nan"), name="n.sqlite"))


@pytest.mark.parametrize("key, value", [("crs", "nan"), ("crs", ""), ("epoch_utc", "nan")])
def test_fleet_refuses_a_damaged_meta_before_the_maps(tmp_path, monkeypatch, key, value):
    f = _store(tmp_path, (f"UPDATE meta SET value = ? WHERE key = '{key}'", value))
    _refused(["fleet", "helsinki-medical", "--missions", "1", "--seed", "1", "--airspace", f, "--out",
              tmp_path / "o"], tmp_path, monkeypatch, str(f), f"its {key} {value!r}", "restore the file from a copy")
    assert not (tmp_path / "cache" / "stages").exists(), "a stage ran before the refusal"


# ---------------------------------------------------------------------------------- volume numbers
VOLUME_DAMAGE = [("t_end_s", "abc"), ("alt_upper_m", b"\x00"), ("t_start_s", math.inf), ("alt_lower_m", -1e300),
                 ("t_end_s", 2.0**62), ("k", "x")]
VOLUME_CASES = [(*d, c) for d in VOLUME_DAMAGE[:2] for c in READS_VOLUMES] + [(*d, READS_VOLUMES[0])
                                                                             for d in VOLUME_DAMAGE[2:]]


@pytest.mark.parametrize("col, value, cmd", VOLUME_CASES, ids=_id)
def test_volume_numbers_damaged(tmp_path, monkeypatch, col, value, cmd):
    f = _store(tmp_path, (f"UPDATE volumes SET {col} = ? WHERE intent_id = 'bad'", value))
    where = "a volume's k" if col == "k" else f"volume 0: its {col}"
    _refused(_args(cmd, f, tmp_path), tmp_path, monkeypatch, str(f), "intent 'bad'", where, repr(value)[:8],
             "restore it from a copy", f"skyroute airspace rm {f} bad")


def test_damaged_volume_removed_then_the_check_passes(tmp_path, monkeypatch):
    f = _store(tmp_path, ("UPDATE volumes SET t_end_s = ? WHERE intent_id = 'bad'", "abc"))
    code, out, _ = _cli(["airspace", "ls", f], tmp_path, monkeypatch)     # ls reads no volume
    assert code == 0 and "2 intents, 2 volumes" in out, out
    code, out, _ = _cli(["airspace", "rm", f, "bad"], tmp_path, monkeypatch)
    assert code == 0 and "it holds 1" in out, out
    code, out, _ = _cli(["airspace", "check", f], tmp_path, monkeypatch)
    assert code == 0 and "1 intents, consistent" in out, out


# ---------------------------------------------------------------------------------- intent numbers
INTENT_DAMAGE = [("t_start_s", math.inf, "not a finite number within +-1e+09 s"),
                 ("t_start_s", 2**62, "not a finite number within +-1e+09 s"),
                 ("t_end_s", -math.inf, "not a finite number"),
                 ("n_volumes", math.inf, "not an integer in 1..2,147,483,647"),
                 ("n_volumes", 0, "not an integer in 1.."),
                 ("priority", math.inf, "not an integer in -2,147,483,648..2,147,483,647"),
                 ("priority", 2**40, "not an integer in -2,147,483,648.."),
                 ("priority", "abc", "not an integer"),
                 ("seq", b"\x01", "not an integer"),
                 ("operator", b"\x01", "is not a text")]


# the fuzz findings (times inf or 2^62, n_volumes / priority inf) in every subcommand reading the
# intents, the other damages in ls and show
INTENT_CASES = [(*d, c) for d in INTENT_DAMAGE[:2] + INTENT_DAMAGE[3:4] + INTENT_DAMAGE[5:6]
                for c in READS_INTENTS]
INTENT_CASES += [(*d, c) for d in INTENT_DAMAGE[2:3] + INTENT_DAMAGE[4:5] + INTENT_DAMAGE[6:]
                 for c in READS_INTENTS[:2]]


@pytest.mark.parametrize("col, value, words, cmd", INTENT_CASES, ids=_id)
def test_intent_numbers_damaged(tmp_path, monkeypatch, col, value, words, cmd):
    f = _store(tmp_path, (f"UPDATE intents SET {col} = ? WHERE id = 'bad'", value))
    _refused(_args(cmd, f, tmp_path), tmp_path, monkeypatch, str(f), f"intent 'bad': its {col}", words,
             "restore it from a copy", f"skyroute airspace rm {f} bad")
    assert not (tmp_path / "exp").exists()       # export refused before writing


def test_damaged_intent_removable_and_the_other_shown(tmp_path, monkeypatch):
    f = _store(tmp_path, ("UPDATE intents SET priority = ? WHERE id = 'bad'", math.inf))
    code, out, _ = _cli(["airspace", "show", f, "good"], tmp_path, monkeypatch)
    assert code == 0 and json.loads(out)["priority"] == 0, out
    code, out, _ = _cli(["airspace", "rm", f, "bad"], tmp_path, monkeypatch)
    assert code == 0 and "it holds 1" in out, out
    code, out, _ = _cli(["airspace", "check", f], tmp_path, monkeypatch)
    assert code == 0 and "1 intents, consistent" in out, out


def test_values_at_the_bounds_are_read(tmp_path, monkeypatch):
    """priority 2^31 - 1 and a time span ending MAX_ABS_TIME_S after the epoch are valid: ls
    shows them (the end time against datetime's own sum)."""
    f = _store(tmp_path, ("UPDATE intents SET priority = ? WHERE id = 'bad'", 2**31 - 1),
               ("UPDATE intents SET t_end_s = ? WHERE id = 'bad'", MAX_ABS_TIME_S))
    code, out, _ = _cli(["airspace", "ls", f, "--json"], tmp_path, monkeypatch)
    assert code == 0, out
    bad = {r["id"]: r for r in json.loads(out)["intents"]}["bad"]
    end = dt.datetime(2020, 1, 3, 10, tzinfo=dt.UTC) + dt.timedelta(seconds=1e9)
    assert bad["priority"] == 2**31 - 1
    assert bad["end_utc"] == end.strftime("%Y-%m-%dT%H:%M:%S.000Z") == "2051-09-11T11:46:40.000Z"
    code, out, _ = _cli(["airspace", "check", f], tmp_path, monkeypatch)   # valid numbers, but not its volumes'
    assert code == 1 and "problem: intent bad: its time span 0..1e+09 s differs from its volumes' 0..30 s" in out


def test_check_reports_unparsable_times_of_an_intent(tmp_path, monkeypatch):
    f = _store(tmp_path, ("UPDATE intents SET accepted_utc = ? WHERE id = 'bad'", "2100-13-45T99:00:00Z"),
               ("UPDATE intents SET departure_utc = ? WHERE id = 'good'", "nan"))
    code, out, errors = _cli(["airspace", "check", f], tmp_path, monkeypatch)
    assert code == 1 and not errors, out
    assert "problem: intent bad: its accepted_utc '2100-13-45T99:00:00Z' is not a UTC time" in out
    assert "problem: intent good: its departure_utc 'nan' is not a UTC time" in out


# ---------------------------------------------------------------------------------- flipped bytes
def _flip_schema(tmp_path: Path) -> Path:
    """The space after TABLE in volume_rtree's CREATE statement made 0xa0: SQLite's own error
    message is not UTF-8 (the fuzz case airspace:flip-bytes:3366979566)."""
    f = _store(tmp_path)
    b = bytearray(f.read_bytes())
    i = b.find(b"CREATE VIRTUAL TABLE volume_rtree")
    assert i > 0
    b[i + len("CREATE VIRTUAL TABLE")] = 0xA0
    f.write_bytes(bytes(b))
    return f


def _smash_intents_page(tmp_path: Path) -> Path:
    """The b-tree page header of the intents table overwritten: database disk image is malformed."""
    f = _store(tmp_path)
    c = sqlite3.connect(f)
    page = c.execute("PRAGMA page_size").fetchone()[0]
    root = c.execute("SELECT rootpage FROM sqlite_master WHERE name = 'intents'").fetchone()[0]
    c.close()
    b = bytearray(f.read_bytes())
    b[(root - 1) * page:(root - 1) * page + 12] = b"\xff" * 12
    f.write_bytes(bytes(b))
    return f


@pytest.mark.parametrize("cmd", EVERY, ids=_id)
def test_flipped_bytes_in_the_schema(tmp_path, monkeypatch, cmd):
    f = _flip_schema(tmp_path)
    _refused(_args(cmd, f, tmp_path), tmp_path, monkeypatch, str(f), "cannot be read as an airspace file",
             "UnicodeDecodeError", "restore it from a copy")


@pytest.mark.parametrize("cmd", [EVERY[0], EVERY[2], EVERY[3]], ids=_id)
def test_malformed_page(tmp_path, monkeypatch, cmd):
    f = _smash_intents_page(tmp_path)
    _refused(_args(cmd, f, tmp_path), tmp_path, monkeypatch, str(f), "damaged", "malformed",
             "restore it from a copy")


@pytest.mark.parametrize("cmd", READS_INTENTS[:2] + READS_INTENTS[4:], ids=_id)
def test_text_not_utf8(tmp_path, monkeypatch, cmd):
    f = _store(tmp_path)
    c = sqlite3.connect(f)
    c.execute("UPDATE intents SET operator = CAST(x'ff41' AS TEXT) WHERE id = 'bad'")
    c.commit()
    c.close()
    _refused(_args(cmd, f, tmp_path), tmp_path, monkeypatch, str(f), "is not valid UTF-8", "restore it from a copy")
