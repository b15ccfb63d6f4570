"""Mutations of the shipped input files and of the CLI options (issue 27), shared by
tests/test_fuzz_inputs.py (a small sample under hypothesis) and benchmarks/fuzz_inputs.py
(thousands).

A case starts from the shipped files -- helsinki-medical.yaml (data paths made absolute), the
dji-m300-rtk vehicle, helsinki-tactical's events as an events file, a two-mission fleet file --
and applies one to three mutations drawn with a :class:`random.Random`: a value anywhere in the
tree replaced by a hostile one (``.inf``, ``.nan``, ``true``, ``""``, ``-1``, ``1e308``, a path,
a list, a mapping...), a key removed or added, or the file's text damaged (bytes flipped,
inserted, removed, the file cut, a line doubled).  Every command runs with ``--max-memory 1``:
a request that passes every check is refused by the memory estimate, before any stage runs, so
each case takes milliseconds and exercises the whole front door.  The outcome must be exit 0, 2
or 3, never an uncaught exception (a traceback).
"""

from __future__ import annotations

import copy
import json
import math
import random
import re
import time
from dataclasses import dataclass
from pathlib import Path

import yaml

HOSTILE = [math.inf, -math.inf, math.nan, True, False, None, "", " ", 0, -1, 1, 2**70, -(2**70), 1e308, -1e308,
           5e-324, 1e-12, "inf", "nan", "-1", "../../../tmp/x", "/", "G01", "EPSG:4326", "2100-01-01T00:00:00Z",
           [], {}, [1, 2], [True, False, True, True], {"a": 1}, "x" * 300, "\x00", "é", 3.5, 1e7, -1e-6]

TEXT_OPS = ("flip", "insert", "delete", "cut", "double-line", "tab")


def _paths(node, prefix=()):
    """Every key path of a parsed YAML tree (mappings and lists)."""
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, (*prefix, i))
    return out


def _get_parent(node, path):
    for k in path[:-1]:
        node = node[k]
    return node


def mutate_tree(raw, rnd: random.Random, n_ops: int):
    """``raw`` with ``n_ops`` random edits (replace, delete, add a key); returns (tree, log)."""
    raw = copy.deepcopy(raw)
    log = []
    for _ in range(n_ops):
        paths = _paths(raw)
        if not paths:
            break
        path = rnd.choice(paths)
        parent = _get_parent(raw, path)
        op = rnd.choice(("set", "set", "set", "delete", "add"))
        if op == "set":
            parent[path[-1]] = copy.deepcopy(rnd.choice(HOSTILE))
        elif op == "delete":
            if isinstance(parent, dict):
                del parent[path[-1]]
            else:
                parent.pop(path[-1])
        elif isinstance(parent, dict):
            parent[rnd.choice(["bogus", "name", "resolution_m", "id", "t_s", "kind"])] = copy.deepcopy(rnd.choice(HOSTILE))
        log.append(f"{op} {'.'.join(map(str, path))}")
    return raw, log


def mutate_text(data: bytes, rnd: random.Random, n_ops: int):
    """``data`` with ``n_ops`` byte-level edits; returns (bytes, log)."""
    b = bytearray(data)
    log = []
    for _ in range(n_ops):
        op = rnd.choice(TEXT_OPS)
        i = rnd.randrange(max(1, len(b)))
        if op == "flip" and b:
            b[i] ^= 1 << rnd.randrange(8)
        elif op == "insert":
            b[i:i] = bytes(rnd.randrange(256) for _ in range(rnd.randint(1, 4)))
        elif op == "delete":
            del b[i:i + rnd.randint(1, 8)]
        elif op == "cut":
            del b[i:]
        elif op == "double-line":
            lines = bytes(b).split(b"\n")
            k = rnd.randrange(len(lines))
            lines.insert(k, lines[k])
            b = bytearray(b"\n".join(lines))
        elif op == "tab":
            b[i:i] = b"\t"
        log.append(f"{op}@{i}")
    return bytes(b), log


@dataclass
class Base:
    """The shipped files, written under ``folder`` with absolute data paths."""

    folder: Path
    scenario: dict
    vehicle_text: str
    events: list
    fleet: dict

    @classmethod
    def make(cls, folder: Path) -> Base:
        from skyroute.pipeline.settings import catalog_dir, scenario_paths

        folder.mkdir(parents=True, exist_ok=True)
        paths = scenario_paths()
        data = str(paths["helsinki-medical"].parent.parent / "data") + "/"

        def raw(name):
            r = yaml.safe_load(paths[name].read_text())
            return json.loads(json.dumps(r, default=str).replace("../data/", data))

        sc = raw("helsinki-medical")
        events = raw("helsinki-tactical")["events"]
        fleet = {"missions": [
            {"id": "m1", "start": {"x": 385747.35, "y": 6672213.62, "alt_agl_m": 60},
             "goal": {"x": 385969.55, "y": 6672495.29, "alt_agl_m": 60}, "departure": 0, "priority": 1},
            {"id": "m2", "start": {"x": 385990.82, "y": 6672586.58, "alt_agl_m": 60},
             "goal": {"x": 385497.54, "y": 6672661.04, "alt_agl_m": 60}, "departure": 120}]}
        veh = (catalog_dir() / "vehicles" / "dji-m300-rtk.yaml").read_text()
        return cls(folder, sc, veh, events, fleet)


# command-line options with hostile values: (command, option, values)
CLI_OPTIONS = [
    ("plan", "--weights", ["1,1,1", "nan,1,1,1", "inf,0,0,0", "true,1,1,1", "", "-1,1,1,1", "1e400,1,1,1"]),
    ("plan", "--seed", ["-1", "2**40", "1e3", "nan", "18446744073709551616"]),
    ("plan", "--time-budget", ["nan", "inf", "-1", "0", "1e-300"]),
    ("plan", "--planner", ["", "bogus", "ASTAR", "../x"]),
    ("run", "--force", ["bogus", "", "plan,surface"]),
    ("run", "--stage", ["bogus", ""]),
    ("run", "--scheduler", ["bogus", "", "tcp://"]),
    ("fly", "--tick", ["nan", "inf", "-1", "0", "1e-7", "1e-300"]),
    ("fly", "--t-rep", ["nan", "-1", "0", "inf"]),
    ("fly", "--seed", ["-1", "nan"]),
    ("fly", "--tactical", ["bogus", ""]),
    ("navsim", "--runs", ["0", "-1", "1e9", "nan"]),
    ("navsim", "--seed", ["-1"]),
    ("fleet", "--window-min", ["nan", "inf", "-1", "0"]),
    ("fleet", "--max-delay-min", ["nan", "inf", "-1"]),
    ("fleet", "--delay-step-s", ["nan", "0", "inf"]),
    ("fleet", "--ground-m", ["nan", "inf", "1e30"]),
    ("fleet", "--seed", ["-1", "99999999999999999999"]),
    ("fleet", "--missions", ["0", "-1", "nan"]),
    ("plan", "--out", ["", " "]),
    ("plan", "--cache-dir", ["", " "]),
    ("plan", "--max-memory", ["", "lots", "-1", "0", "1e99T"]),
]

KINDS = ("scenario-tree", "scenario-text", "vehicle-tree", "vehicle-text", "events-tree", "events-text",
         "fleet-tree", "fleet-text", "option")


def build_case(base: Base, rnd: random.Random, kind: str | None = None, case_dir: Path | None = None):
    """One fuzz case: (argv, description).  Files go to ``case_dir`` (default base.folder/case)."""
    kind = kind or rnd.choice(KINDS)
    d = case_dir or base.folder / "case"
    d.mkdir(parents=True, exist_ok=True)
    n = rnd.randint(1, 3)
    sc_path, veh_path, ev_path, fl_path = d / "H.yaml", d / "veh.yaml", d / "events.yaml", d / "fleet.yaml"
    sc = copy.deepcopy(base.scenario)
    log: list[str] = []
    tail = ["--max-memory", "1", "--cache-dir", str(d / "cache"), "--out", str(d / "out")]
    if kind.startswith("vehicle"):
        if kind == "vehicle-tree":
            tree, log = mutate_tree(yaml.safe_load(base.vehicle_text), rnd, n)
            veh_path.write_text(yaml.safe_dump(tree))
        else:
            data, log = mutate_text(base.vehicle_text.encode(), rnd, n)
            veh_path.write_bytes(data)
        sc["vehicle"] = str(veh_path)
    if kind == "scenario-text":
        data, log = mutate_text(yaml.safe_dump(sc, sort_keys=False).encode(), rnd, n)
        sc_path.write_bytes(data)
    elif kind == "scenario-tree":
        tree, log = mutate_tree(sc, rnd, n)
        sc_path.write_text(yaml.safe_dump(tree, sort_keys=False))
    else:
        sc_path.write_text(yaml.safe_dump(sc, sort_keys=False))
    argv = ["plan", str(sc_path), *tail]
    if kind.startswith("events"):
        if kind == "events-tree":
            tree, log = mutate_tree({"events": base.events}, rnd, n)
            ev_path.write_text(yaml.safe_dump(tree))
        else:
            data, log = mutate_text(yaml.safe_dump(base.events).encode(), rnd, n)
            ev_path.write_bytes(data)
        argv = ["fly", str(sc_path), "--events", str(ev_path), *tail]
    elif kind.startswith("fleet"):
        if kind == "fleet-tree":
            tree, log = mutate_tree(base.fleet, rnd, n)
            fl_path.write_text(yaml.safe_dump(tree))
        else:
            data, log = mutate_text(yaml.safe_dump(base.fleet).encode(), rnd, n)
            fl_path.write_bytes(data)
        argv = ["fleet", str(sc_path), "--fleet", str(fl_path), *tail]
    elif kind == "option":
        cmd, opt, values = rnd.choice(CLI_OPTIONS)
        value = rnd.choice(values)
        rest = [a for a in tail]
        if opt in rest:                      # the option under test replaces the default one
            i = rest.index(opt)
            del rest[i:i + 2]
        extra = ["--missions", "2"] if cmd == "fleet" and opt != "--missions" else []
        scen = ["helsinki-tactical"] if cmd == "fly" else [str(sc_path)]
        argv = [cmd, *scen, opt, value, *extra, *rest]
        log = [f"{cmd} {opt} {value!r}"]
    return argv, f"{kind}: {'; '.join(log)}"


@dataclass
class Outcome:
    exit_code: int
    seconds: float
    error_lines: int
    traceback: str | None
    memory_refusal: bool = False

    @property
    def ok(self) -> bool:
        return self.exit_code in (0, 2, 3) and self.traceback is None


def run_case(argv) -> Outcome:
    """Run the CLI in-process; an uncaught exception is reported as its traceback; ``seconds``
    leaves out numba's compilations (:func:`skyroute.stages.control.compile_seconds`)."""
    import traceback

    from click.testing import CliRunner

    from skyroute.pipeline.cli import main
    from skyroute.stages.control import compile_seconds

    t0, c0 = time.perf_counter(), compile_seconds()
    res = CliRunner().invoke(main, argv)
    # bounded time is what a case costs a user whose kernels are compiled: a fresh machine's
    # first case of a kind compiles numba kernels (cached on disk after), which does not count
    dt = time.perf_counter() - t0 - (compile_seconds() - c0)
    tb = None
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        tb = "".join(traceback.format_exception(res.exception))
    errors = sum(1 for ln in res.output.splitlines() if ln.startswith("error:"))
    memory = "of memory" in res.output and "--max-memory" in res.output
    return Outcome(int(res.exit_code), dt, errors, tb, memory)


def short(tb: str | None) -> str:
    """The last line of a traceback (the exception), for counting distinct failures."""
    if not tb:
        return ""
    last = [ln for ln in tb.strip().splitlines() if ln.strip()][-1]
    return re.sub(r"0x[0-9a-f]+|\d+", "N", last)[:160]
