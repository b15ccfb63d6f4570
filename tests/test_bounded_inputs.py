"""Every resource bounded before the work (issue 34): fleet, navsim, fly, cluster and airspace
inputs.  Each reproduction of the issue is refused at the front door with one ``error:`` line
(exit 2) and no traceback, in well under a second or two; nothing here plans."""

from __future__ import annotations

import math
import os
import re
import socket
import sqlite3
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from skyroute.pipeline.cli import main
from skyroute.pipeline.errors import InputError
from skyroute.pipeline.settings import load_scenario

A = {"x": 385747.35, "y": 6672213.62, "alt_agl_m": 60}      # two points of helsinki-medical (test_fleet_cli)
B = {"x": 385969.55, "y": 6672495.29, "alt_agl_m": 60}


@pytest.fixture(scope="module")
def hm():
    return load_scenario("helsinki-medical")


def _cli(args, tmp_path: Path, monkeypatch):
    """``skyroute ARGS`` in ``tmp_path`` with its own cache: (exit code, output, error lines)."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("SKYROUTE_CACHE_DIR", str(tmp_path / "cache"))
    res = CliRunner().invoke(main, [str(a) for a in args])
    assert "Traceback" not in res.output, res.output
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        raise res.exception
    return res.exit_code, res.output, [ln for ln in res.output.splitlines() if ln.startswith("error:")]


def _refused(args, tmp_path, monkeypatch, *words, lines: int = 1) -> str:
    t0 = time.perf_counter()
    code, out, errors = _cli(args, tmp_path, monkeypatch)
    took = time.perf_counter() - t0
    assert code == 2, out
    assert len(errors) == lines, out
    for w in words:
        assert w in out, (w, out)
    assert not (tmp_path / "cache" / "stages").exists(), "a stage ran before the refusal"
    assert took < 10, f"refused only after {took:.1f} s"
    return out


def _fleet_file(tmp_path: Path, missions: list) -> Path:
    p = tmp_path / "fleet.yaml"
    p.write_text(yaml.safe_dump({"missions": missions}))
    return p


# ---------------------------------------------------------------------------------- 1. memory estimates
def test_navsim_runs_beyond_the_maximum(tmp_path, monkeypatch):
    from skyroute.pipeline.budget import MAX_NAVSIM_RUNS

    _refused(["navsim", "helsinki-medical", "--runs", "1000000"], tmp_path, monkeypatch, "--runs",
             f"1<=x<={MAX_NAVSIM_RUNS}")


def test_navsim_memory_refused_before_the_plan(tmp_path, monkeypatch):
    out = _refused(["navsim", "helsinki-medical", "--runs", "20000", "--max-memory", "2G"], tmp_path, monkeypatch,
                   "20,000 runs", "at least", "epochs", "--runs", "--max-memory (now 2.0 GiB)")
    assert "fit)" in out


def test_check_navsim_numbers(hm):
    from skyroute.pipeline import budget

    base = budget.scenario_footprint(hm).bytes
    need = budget.check_navsim(hm, 100, 1000, limit_bytes=1 << 40)
    assert need == pytest.approx(base + 100 * 1000 * 320)       # 320 B per run and epoch, by hand
    limit = int(base + 100 * 1000 * 320)
    assert budget.check_navsim(hm, 100, 1000, limit_bytes=limit + 1) <= limit + 1
    with pytest.raises(InputError, match=r"101 runs x 1,000 epochs.*\(99 fit\)"):
        budget.check_navsim(hm, 101, 1000, limit_bytes=limit - 320 * 1000)


def test_fleet_of_a_billion_missions_refused_at_once(tmp_path, monkeypatch):
    from skyroute.pipeline.fleet import MAX_FLEET_MISSIONS

    _refused(["fleet", "helsinki-medical", "--missions", "1000000000", "--seed", "1"], tmp_path, monkeypatch,
             "1,000,000,000", f"at most {MAX_FLEET_MISSIONS:,}", "--airspace")


def test_fleet_memory_refused_before_the_maps(tmp_path, monkeypatch):
    _refused(["fleet", "helsinki-medical", "--missions", "5000", "--max-memory", "1G"], tmp_path, monkeypatch,
             "a fleet of 5,000 missions", "512 KiB per mission", "--missions", "--max-memory (now 1.0 GiB)")


def test_check_fleet_numbers(hm):
    from skyroute.pipeline import budget

    maps = budget.scenario_footprint(hm).bytes
    assert budget.check_fleet(hm, 10, 1.5, limit_bytes=1 << 40) == pytest.approx(maps + 10 * (512 << 10))
    assert budget.check_fleet(hm, 10, 15.0, limit_bytes=1 << 40) == pytest.approx(maps + 10 * 10 * (512 << 10))
    limit = int(maps + 40 * (512 << 10))
    budget.check_fleet(hm, 40, 1.0, limit_bytes=limit)
    with pytest.raises(InputError, match=r"41 missions.*40 fit"):
        budget.check_fleet(hm, 41, 1.0, limit_bytes=limit)


def test_fleet_delay_attempts_bounded(tmp_path, monkeypatch):
    _refused(["fleet", "helsinki-medical", "--missions", "3", "--max-delay-min", "1e6"], tmp_path, monkeypatch,
             "1,000,001 departures", "--delay-step-s")


# ---------------------------------------------------------------------------------- 2. intruders
def _events_file(tmp_path: Path, n: int) -> Path:
    ev = [{"t_s": 5 + 0.001 * k, "kind": "intruder", "id": f"far-{k}", "radius_m": 2.0,
           "waypoints": [[5, 385300, 6672300, 100], [200, 385300, 6672310, 100]]} for k in range(n)]
    f = tmp_path / "ev.yaml"
    f.write_text(yaml.safe_dump({"events": ev}))
    return f


def test_fly_intruder_count_bounded(tmp_path, monkeypatch):
    from skyroute.pipeline.fly import MAX_INTRUDERS, check_intruders

    sc = load_scenario("helsinki-tactical")
    assert check_intruders(sc) == 4          # 2 traffic.intruders + 2 intruder events
    f = _events_file(tmp_path, MAX_INTRUDERS)
    _refused(["fly", "helsinki-tactical", "--events", f, "--out", tmp_path / "o"], tmp_path, monkeypatch,
             "504 intruder tracks", f"at most {MAX_INTRUDERS}", "intruder events 502")
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_fly_events_times_intruders_bounded(tmp_path, monkeypatch):
    from skyroute.pipeline.fly import MAX_EVENT_CHECKS

    f = _events_file(tmp_path, 250)           # 254 events (4 of the scenario) x 254 tracks = 64,516 checks
    _refused(["fly", "helsinki-tactical", "--events", f, "--out", tmp_path / "o"], tmp_path, monkeypatch,
             "254 events and 254 intruder tracks", "64,516 checks", f"at most {MAX_EVENT_CHECKS:,}")


# ---------------------------------------------------------------------------------- 3. endless reads
def test_fleet_from_dev_zero(tmp_path, monkeypatch):
    _refused(["fleet", "helsinki-medical", "--fleet", "/dev/zero"], tmp_path, monkeypatch, "/dev/zero", "device")


def test_fleet_csv_fifo_never_waits(tmp_path, monkeypatch):
    fifo = tmp_path / "f.csv"
    os.mkfifo(fifo)
    _refused(["fleet", "helsinki-medical", "--fleet", fifo], tmp_path, monkeypatch, "FIFO")


def test_yaml_reader_is_bounded(tmp_path, monkeypatch):
    from skyroute.stages import yaml_io
    from skyroute.stages.base import ScenarioError

    with pytest.raises(ScenarioError, match="/dev/zero is a device"):
        yaml_io.read_yaml_file("/dev/zero", "fleet")
    fifo = tmp_path / "s.yaml"
    os.mkfifo(fifo)
    with pytest.raises(ScenarioError, match="FIFO"):
        yaml_io.read_yaml_file(fifo, "scenario")
    big = tmp_path / "big.yaml"
    big.write_text("a: 1\n" + "# pad\n" * 200)
    monkeypatch.setattr(yaml_io, "MAX_BYTES", 100)
    with pytest.raises(ScenarioError, match="more than 100 bytes"):
        yaml_io.read_yaml_file(big, "scenario")


def test_navsim_trajectory_and_geojson_reads_are_bounded(tmp_path):
    from skyroute.pipeline.navsim import read_flown_csv
    from skyroute.stages.base import DataError
    from skyroute.stages.risk import read_geojson_lonlat

    with pytest.raises(InputError, match="/dev/zero is a device"):
        read_flown_csv(Path("/dev/zero"))
    with pytest.raises(InputError, match="--trajectory file not found"):
        read_flown_csv(tmp_path / "nope.csv")
    fifo = tmp_path / "zones.geojson"
    os.mkfifo(fifo)
    with pytest.raises(DataError, match="not found|FIFO"):     # not a regular file: never opened
        read_geojson_lonlat(fifo, "no-fly zones")
    ok = tmp_path / "ok.csv"
    ok.write_text("t_s,x_m,y_m,z_m\n0,1,2,3\n1,4,5,6\n")
    t, p = read_flown_csv(ok)
    assert t.tolist() == [0.0, 1.0] and p[1].tolist() == [4.0, 5.0, 6.0]


# ---------------------------------------------------------------------------------- 4. --scheduler addresses
class _Server:
    """A TCP server thread on 127.0.0.1 that sends ``greeting`` (None: never answers)."""

    def __init__(self, greeting: bytes | None):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(4)
        self.greeting, self.conns, self.stop = greeting, [], threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    @property
    def address(self) -> str:
        return f"tcp://127.0.0.1:{self.sock.getsockname()[1]}"

    def _run(self) -> None:
        self.sock.settimeout(0.2)
        while not self.stop.is_set():
            try:
                c, _ = self.sock.accept()
            except OSError:
                continue
            self.conns.append(c)
            if self.greeting is not None:
                c.sendall(self.greeting)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2)
        for c in self.conns:
            c.close()
        self.sock.close()


@pytest.fixture
def server(request):
    s = _Server(request.param)
    yield s
    s.close()


@pytest.mark.parametrize("server", [b"HTTP/1.1 400 Bad Request\r\n\r\n" * 4], indirect=True)
def test_scheduler_answering_garbage(server, tmp_path, monkeypatch):
    from skyroute.pipeline.graph import check_scheduler_address, scheduler_context

    with pytest.raises(InputError, match=r"is not a dask scheduler .*announce a message of .*dask scheduler"):
        check_scheduler_address(server.address)
    with pytest.raises(InputError, match="is not a dask scheduler"):
        with scheduler_context(server.address):
            pass
    _refused(["fleet", "helsinki-medical", "--missions", "2", "--scheduler", server.address], tmp_path, monkeypatch,
             "is not a dask scheduler", "drop --scheduler")


@pytest.mark.parametrize("server", [None], indirect=True)
def test_scheduler_never_answering_times_out(server):
    from skyroute.pipeline import graph

    assert graph.PROBE_TIMEOUT_S <= 10
    t0 = time.perf_counter()
    with pytest.raises(InputError, match=r"no dask handshake within 1 s"):
        graph.check_scheduler_address(server.address, timeout_s=1.0)
    assert time.perf_counter() - t0 < 3


def test_scheduler_address_closed_port_or_malformed():
    from skyroute.pipeline.graph import check_scheduler_address

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()                                   # nothing listens there now
    with pytest.raises(InputError, match="cannot connect to the dask scheduler"):
        check_scheduler_address(f"tcp://127.0.0.1:{port}")
    for bad in ("tcp://127.0.0.1", "tcp://127.0.0.1:99999", "tcp://:8786"):
        with pytest.raises(InputError, match="not a dask scheduler address"):
            check_scheduler_address(bad)


@pytest.mark.parametrize("server", [None], indirect=True)
def test_scheduler_handshake_accepted(server):
    """A greeting shaped like a dask scheduler's (length, frame header, msgpack keys) passes."""
    import struct

    from skyroute.pipeline.graph import check_scheduler_address

    body = struct.pack("QQ", 1, 42) + b"\x83\xabcompression\xc0\xa6python\x93\x03\x0b\x07\xafpickle-protocol\x05"
    server.greeting = struct.pack("Q", len(body)) + body
    check_scheduler_address(server.address)


# ---------------------------------------------------------------------------------- 5.-7. fleet file fields
def test_priority_beyond_sqlite_integers(tmp_path, monkeypatch, hm):
    from skyroute.pipeline.fleet import MAX_PRIORITY, FleetFileError, load_fleet

    f = _fleet_file(tmp_path, [{"id": "p", "start": A, "goal": B, "priority": 10**30}])
    with pytest.raises(FleetFileError, match=r"mission p: priority: .*1\.00e30 is outside .*2,147,483,647"):
        load_fleet(f, hm, hm.gnss.dop_thresholds)
    _refused(["fleet", "helsinki-medical", "--fleet", f], tmp_path, monkeypatch, "priority")
    ok = _fleet_file(tmp_path, [{"id": "p", "start": A, "goal": B, "priority": MAX_PRIORITY}])
    assert load_fleet(ok, hm, hm.gnss.dop_thresholds)[0].priority == 2**31 - 1


def test_mission_ids_are_safe_file_names():
    from skyroute.pipeline.fleet import MAX_ID_CHARS, check_mission_id

    for ok in ("m0001", "s1-m0001", "op_a.m-3", "x" * MAX_ID_CHARS):
        assert check_mission_id(ok) == ok
    for bad, why in [("", "empty"), ("x" * (MAX_ID_CHARS + 1), "longer than 64"), ("a/b", "'/'"),
                     ("a\x00b", "'\\x00'"), (".hidden", "starts with"), ("-rf", "starts with"), ("a b", "' '"),
                     ("..", "starts with"), ("mission\u00e9", "'\u00e9'")]:
        with pytest.raises(ValueError, match=re.escape(why)):
            check_mission_id(bad)


def test_long_mission_id_refused_before_any_work(tmp_path, monkeypatch, hm):
    f = _fleet_file(tmp_path, [{"id": "x" * 5000, "start": A, "goal": B}])
    out = _refused(["fleet", "helsinki-medical", "--fleet", f, "--out", tmp_path / "o"], tmp_path, monkeypatch,
                   "longer than 64 characters", "(5,000 characters)")
    assert len(out) < 600                       # shown truncated
    assert not (tmp_path / "o" / "airspace.sqlite").exists()


def test_missions_checked_before_the_maps(tmp_path, monkeypatch, hm):
    from skyroute.pipeline.fleet import FleetFileError, load_fleet

    far = {"x": A["x"], "y": A["y"] + 1.0, "alt_agl_m": 60}       # 1 m away: less than one 2 m cell
    missions = [{"id": "same", "start": A, "goal": A}, {"id": "near", "start": A, "goal": far},
                {"id": "fw", "start": A, "goal": B, "vehicle": "skywalker-x8"},
                {"id": "high", "start": A, "goal": {**B, "alt_agl_m": 500}},
                {"id": "fine", "start": A, "goal": B}]
    f = _fleet_file(tmp_path, missions)
    with pytest.raises(FleetFileError) as ei:
        load_fleet(f, hm, hm.gnss.dop_thresholds)
    probs = ei.value.problems
    assert len(probs) == 4, probs
    assert "mission same: start and goal are 0.00 m apart" in probs[0]
    assert "mission near: start and goal are 1.00 m apart" in probs[1]
    assert "mission fw: vehicle: 'skywalker-x8' is a fixed-wing vehicle" in probs[2] and "astar" in probs[2]
    assert "mission high: goal altitude 500 m AGL" in probs[3] and "max_altitude_agl_m" in probs[3]
    _refused(["fleet", "helsinki-medical", "--fleet", f], tmp_path, monkeypatch, "start and goal", lines=4)


def test_drawn_missions_of_a_fixed_wing_scenario(tmp_path, monkeypatch):
    _refused(["fleet", "san-gabriel-fixedwing-local", "--missions", "3"], tmp_path, monkeypatch,
             "fixed-wing vehicle", "astar", "skyroute plan")


def test_fleet_file_entries_not_mappings(tmp_path, monkeypatch):
    f = tmp_path / "fleet.yaml"
    f.write_text("missions: [oops, 3]\n")
    _refused(["fleet", "helsinki-medical", "--fleet", f], tmp_path, monkeypatch, "mission #1: expected a mapping",
             lines=2)


# ---------------------------------------------------------------------------------- 8. damaged airspace files
def _store(tmp_path: Path, name: str, damage: str | None, value) -> Path:
    import shapely

    from skyroute.stages.airspace_store import AirspaceStore
    from skyroute.stages.fleet import Volume4
    from skyroute.stages.intents import IntentVolume, intent_details

    crs, epoch, x0, y0 = "EPSG:3067", "2020-01-03T10:00:00Z", 385_000.0, 6_672_000.0
    path = tmp_path / name
    with AirspaceStore.create(path, crs, epoch) as s:
        for k, ident in enumerate(("good", "bad")):
            v = [Volume4(shapely.box(x0 + 100 * k, y0, x0 + 100 * k + 10, y0 + 10), 50.0, 60.0, 0.0, 30.0)]
            iv = [IntentVolume(np.asarray(u.polygon.exterior.coords)[:-1], u.alt_lower_m, u.alt_upper_m,
                               u.t_start_s, u.t_end_s, 0.0) for u in v]
            s.accept(ident, intent_details(iv, crs, epoch), v)
    if damage is not None:
        c = sqlite3.connect(path)
        c.execute(damage, (value,))
        c.commit()
        c.close()
    return path


_JSON_DAMAGE = [
    ("UPDATE intents SET details = ? WHERE id = 'bad'", "{not json", "F3548 document (details) is not valid JSON"),
    ("UPDATE intents SET mission = ? WHERE id = 'bad'", "[1, 2", "mission fields is not valid JSON"),
]
_WKB_DAMAGE = [
    ("UPDATE volumes SET outline_wkb = ? WHERE intent_id = 'bad'", b"\x01\x02\x03\x04\x05",
     "volume 0: its outline is not valid WKB"),
    ("UPDATE volumes SET outline_wkb = ? WHERE intent_id = 'bad'",
     bytes.fromhex("0101000000000000000000f03f0000000000000040"), "volume 0: its outline is a Point"),
]
# show and export read the documents; check reads the documents and the volumes
_CASES = [(*d, cmd) for d in _JSON_DAMAGE for cmd in (["check", "{f}"], ["show", "{f}", "bad"],
                                                      ["export", "{f}", "{o}"])]
_CASES += [(*_JSON_DAMAGE[1], ["ls", "{f}"])] + [(*d, ["check", "{f}"]) for d in _WKB_DAMAGE]   # ls: no documents


@pytest.mark.parametrize("damage, value, words, cmd", _CASES)
def test_damaged_airspace_one_error_line(tmp_path, monkeypatch, damage, value, words, cmd):
    f = _store(tmp_path, "air.sqlite", damage, value)
    args = ["airspace", *[a.format(f=f, o=tmp_path / "exp") for a in cmd]]
    _refused(args, tmp_path, monkeypatch, str(f), "intent 'bad'", words, "skyroute airspace rm")


def test_damaged_intent_removed_then_the_check_passes(tmp_path, monkeypatch):
    f = _store(tmp_path, "air.sqlite", "UPDATE intents SET details = ? WHERE id = 'bad'", "{not json")
    code, out, _ = _cli(["airspace", "rm", f, "bad"], tmp_path, monkeypatch)
    assert code == 0 and "1 intent(s) removed" in out and "it holds 1" in out
    code, out, _ = _cli(["airspace", "check", f], tmp_path, monkeypatch)
    assert code == 0 and "1 intents, consistent" in out, out
    _refused(["airspace", "rm", f, "nope"], tmp_path, monkeypatch, "no intent 'nope'")


def test_airspace_document_of_the_wrong_shape_is_a_problem(tmp_path, monkeypatch):
    f = _store(tmp_path, "air.sqlite", "UPDATE intents SET details = ? WHERE id = 'bad'", '{"volumes": 5}')
    code, out, errors = _cli(["airspace", "check", f], tmp_path, monkeypatch)
    assert code == 1 and not errors, out
    assert "problem: intent bad: its F3548 document's volumes are a int" in out
    assert "2 intents, INCONSISTENT" in out


def test_airspace_export_refuses_unsafe_ids(tmp_path, monkeypatch):
    f = _store(tmp_path, "air.sqlite", None, None)
    c = sqlite3.connect(f)
    for q in ("UPDATE intents SET id = '../../evil' WHERE id = 'bad'",
              "UPDATE volumes SET intent_id = '../../evil' WHERE intent_id = 'bad'",
              "UPDATE decisions SET mission = '../../evil' WHERE mission = 'bad'"):
        c.execute(q)
    c.commit()
    c.close()
    _refused(["airspace", "export", f, tmp_path / "exp"], tmp_path, monkeypatch, "intent id '../../evil' holds",
             "skyroute airspace rm")
    assert not (tmp_path / "evil.json").exists() and not (tmp_path.parent / "evil.json").exists()


def test_estimates_are_finite_for_sane_requests(hm):
    """The default requests pass: 20 drawn missions, navsim's 50 runs of a 10-minute flight."""
    from skyroute.pipeline import budget

    assert math.isfinite(budget.check_fleet(hm, 20, 1.5, limit_bytes=4 << 30))
    assert budget.check_navsim(hm, 50, 6001, limit_bytes=4 << 30) < 2 << 30
