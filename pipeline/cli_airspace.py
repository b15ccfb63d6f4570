"""``skyroute airspace``: list, show, export and check an airspace file
(:mod:`skyroute.stages.airspace_store`, written by ``skyroute fleet --airspace FILE``)."""

from __future__ import annotations

import contextlib
import json
import sys
from pathlib import Path

import click

from skyroute.pipeline.outfolder import shown

FILE = click.Path(path_type=Path)   # checked by AirspaceStore.open: one `error:` line


@click.group("airspace")
def airspace_group() -> None:
    """An airspace file (SQLite: accepted ASTM F3548 operational intents, their 4-D volumes and
    an R*Tree space-time index) written by `skyroute fleet --airspace FILE`. A FILE that is not
    an airspace: one `error:` line, exit code 2."""


@contextlib.contextmanager
def _open(path: Path):
    """The airspace ``path`` open for one command; a damaged SQLite file found while reading it
    (SQLite's own error, a text that is not UTF-8) is one ``error:`` line (InputError) too: the
    store checks its rows where it reads them, this is the last guard."""
    import sqlite3

    from skyroute.stages.airspace_store import AirspaceStore
    from skyroute.stages.base import InputError

    s = AirspaceStore.open(path)
    try:
        yield s
    except (sqlite3.DatabaseError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: the airspace file is damaged ({type(exc).__name__}: {str(exc)[:120]}); "
                         "restore it from a copy") from None
    finally:
        s.close()


@airspace_group.command("ls")
@click.argument("file", type=FILE)
@click.option("--json", "as_json", is_flag=True, help="One JSON document on stdout instead of the table.")
def ls_command(file: Path, as_json: bool) -> None:
    """The intents of FILE in order of acceptance: id, state, priority, operator, volumes,
    departure and the time span of its volumes (UTC)."""
    import pandas as pd

    from skyroute.stages.intents import rfc3339

    with _open(file) as s:
        recs = s.records()
        epoch = pd.Timestamp(s.epoch_utc)
        dec = s.decisions()
        n_vol = s.n_volumes()
    rows = [{"id": r.id, "state": r.state, "priority": r.priority, "operator": r.operator, "volumes": r.n_volumes,
             "departure_utc": r.departure_utc, "status": dec.get(r.id, ("", "", {}))[0],
             "start_utc": rfc3339(epoch, r.t_start_s, "floor"), "end_utc": rfc3339(epoch, r.t_end_s, "ceil")}
            for r in recs]
    rejected = sorted(m for m, d in dec.items() if d[0] == "rejected")
    if as_json:
        click.echo(json.dumps({"file": str(file), "intents": rows, "volumes": n_vol, "rejected_missions": rejected},
                              indent=1))
        return
    click.echo(f"{file}: {len(rows)} intents, {n_vol} volumes, {len(rejected)} rejected mission(s); epoch "
               f"{epoch.isoformat()}")
    if rows:
        click.echo(f"{'id':16s} {'state':9s} {'prio':>4s} {'operator':10s} {'vols':>4s} {'status':19s} "
                   f"{'start_utc':25s} end_utc")
    for r in rows:
        click.echo(f"{r['id']:16s} {r['state']:9s} {r['priority']:4d} {r['operator']:10s} {r['volumes']:4d} "
                   f"{r['status']:19s} {r['start_utc']:25s} {r['end_utc']}")


@airspace_group.command("show")
@click.argument("file", type=FILE)
@click.argument("intent_id")
def show_command(file: Path, intent_id: str) -> None:
    """One intent of FILE as JSON: its record (state, priority, operator, mission fields,
    decision) and its F3548 OperationalIntentDetails under "details"."""
    with _open(file) as s:
        r = s.record(intent_id)
        dec = s.decisions().get(intent_id)
    doc = {"id": r.id, "state": r.state, "priority": r.priority, "operator": r.operator, "seq": r.seq,
           "departure_utc": r.departure_utc, "accepted_utc": r.accepted_utc, "volumes": r.n_volumes,
           "decision": None if dec is None else {"status": dec[0], "reason": dec[1]}, "mission": r.mission,
           "details": r.details}
    click.echo(json.dumps(doc, indent=1))


@airspace_group.command("export")
@click.argument("file", type=FILE)
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
def export_command(file: Path, out_dir: Path) -> None:
    """Write every intent of FILE as DIR/<id>.json (an F3548 OperationalIntentDetails document,
    checked against the uas_standards schema) and DIR/summary.json."""
    from skyroute.pipeline.fleet import check_mission_id
    from skyroute.pipeline.outputs import (
        ensure_writable_dir,
        previous_summary,
        remove_stale,
        write_summary,
    )
    from skyroute.stages.base import InputError
    from skyroute.stages.intents import parse_intent

    with _open(file) as s:
        recs = s.records(details=True)
        epoch = s.epoch_utc.isoformat()
        n_vol = s.n_volumes()
    for r in recs:              # each id names a file: never a path, before anything is written
        try:
            check_mission_id(r.id, "intent id")
        except ValueError as exc:
            raise InputError(f"{file}: {exc}; remove that intent (`skyroute airspace rm {file} ID`)") from None
    out = ensure_writable_dir(out_dir)
    files, warnings = [], []
    for r in recs:
        try:
            parse_intent(r.details)
        except Exception as exc:   # noqa: BLE001 - the schema's own message
            warnings.append(f"intent {r.id}: {exc}")
        p = out / f"{r.id}.json"
        p.write_text(json.dumps(r.details, indent=1))
        files.append(p.name)
    for w in warnings:
        click.echo(f"warning: {w}", err=True)
    remove_stale(out, previous_summary(out), files, "airspace export")
    write_summary(out, "airspace export", files, warnings, {"airspace": {
        "file": str(Path(file).resolve()), "intents": len(recs), "volumes": n_vol, "epoch_utc": epoch,
        "ids": [r.id for r in recs]}})
    click.echo(f"airspace export: {len(recs)} intents -> {shown(out)}")


@airspace_group.command("check")
@click.argument("file", type=FILE)
@click.option("--json", "as_json", is_flag=True, help="One JSON document on stdout.")
def check_command(file: Path, as_json: bool) -> None:
    """Re-check FILE: its consistency (SQLite integrity, rows, R*Tree boxes, every F3548
    document against its stored volumes) and its conflicts twice, by the independent all-pairs
    check of the F3548 documents (plain shapely code, no index) and through the R*Tree. Exit 0
    when consistent and conflict-free, 1 otherwise."""
    import time

    from skyroute.pipeline.fleet import independent_conflicts
    from skyroute.stages.fleet import volumes_of_intent

    with _open(file) as s:
        t = time.perf_counter()
        problems = s.check()
        t_cons = time.perf_counter() - t
        docs = {r.id: r.details for r in s.records(details=True)}
        bad = set()
        for m, d in docs.items():     # a document the all-pairs check cannot read: a problem (check found it)
            try:
                volumes_of_intent(d, s.crs_wkt, s.epoch_utc.isoformat())
            except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
                bad.add(m)
                problems.append(f"intent {m}: F3548 document unreadable by the all-pairs check "
                                f"({type(exc).__name__}: {str(exc)[:80]}); re-export it or remove it "
                                f"(`skyroute airspace rm {file} {m}`)")
        t = time.perf_counter()
        pairs = independent_conflicts({m: d for m, d in docs.items() if m not in bad}, s.crs_wkt,
                                      s.epoch_utc.isoformat())
        t_all = time.perf_counter() - t
        t = time.perf_counter()
        indexed = [p for p in s.self_conflicts() if not bad & set(p)]
        t_idx = time.perf_counter() - t
    if sorted(map(tuple, map(sorted, pairs))) != indexed:
        problems.append(f"the R*Tree check finds {len(indexed)} conflicting pair(s), the all-pairs check "
                        f"{len(pairs)}")
    ok = not problems and not pairs
    doc = {"file": str(file), "intents": len(docs), "consistent": not problems, "problems": problems,
           "conflicts": len(pairs), "conflicting_pairs": [list(p) for p in pairs],
           "seconds": {"consistency": round(t_cons, 3), "all_pairs": round(t_all, 3), "indexed": round(t_idx, 3)}}
    if as_json:
        click.echo(json.dumps(doc, indent=1))
    else:
        for p in problems:
            click.echo(f"problem: {p}")
        for a, b in pairs:
            click.echo(f"conflict: {a} x {b}")
        click.echo(f"airspace check: {len(docs)} intents, {'consistent' if not problems else 'INCONSISTENT'}, "
                   f"{len(pairs)} conflicting pair(s) (all-pairs {t_all:.2f} s, R*Tree {t_idx:.2f} s) -> "
                   f"{'ok' if ok else 'FAILED'}")
    sys.exit(0 if ok else 1)


@airspace_group.command("rm")
@click.argument("file", type=FILE)
@click.argument("intent_ids", nargs=-1, required=True)
def rm_command(file: Path, intent_ids: tuple[str, ...]) -> None:
    """Remove the intents INTENT_IDS of FILE (their volumes and index boxes, one transaction):
    their missions become undecided, so the next `skyroute fleet --airspace FILE` plans them
    again. Reads no intent document: a damaged intent can be removed too."""
    from skyroute.stages.base import InputError

    with _open(file) as s:
        missing = [m for m in intent_ids if not s.has(m)]
        if missing:
            raise InputError(f"no intent {missing[0][:64]!r} in the airspace {file} (`skyroute airspace ls {file}` "
                             "lists them)")
        s.withdraw(intent_ids)
        left = len(s)
    click.echo(f"airspace rm: {len(intent_ids)} intent(s) removed from {file}; it holds {left}")
