"""`skyroute fleet` on helsinki-medical: every accepted intent checked against every other with
plain shapely code written here, trajectories checked for r + d_c separation by brute force,
determinism, the parallel driver's equality with the sequential one, fleet-file errors."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import shapely
from click.testing import CliRunner
from pyproj import Transformer

from skyroute.pipeline.cli import main
from skyroute.pipeline.settings import GroundReference, load_scenario
from skyroute.stages.vehicle import load_vehicle

GROUND: list[str] = []   # helsinki-medical has its own data.ground (issue 24): no flag needed
A = {"x": 385747.35, "y": 6672213.62, "alt_agl_m": 60}
B = {"x": 385969.55, "y": 6672495.29, "alt_agl_m": 60}
C = {"x": 385990.82, "y": 6672586.58, "alt_agl_m": 60}
D = {"x": 385497.54, "y": 6672661.04, "alt_agl_m": 60}
FLEET = {"missions": [
    {"id": "low", "operator": "op-a", "start": A, "goal": B, "departure": 0, "priority": 0},
    {"id": "high", "operator": "op-b", "start": A, "goal": B, "departure": 5, "priority": 1},
    {"id": "cross", "operator": "op-c", "start": C, "goal": D, "departure": 10},
    {"id": "back", "operator": "op-a", "start": B, "goal": A, "departure": "2020-01-03T10:00:20Z"},
]}


def _yaml(path: Path, doc: dict) -> Path:
    import yaml

    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("fleet-cache")


def _fleet(args, cache_dir):
    res = CliRunner().invoke(main, ["fleet", "helsinki-medical", *GROUND, "--cache-dir", str(cache_dir), "-q", *args])
    assert res.exit_code == 0, res.output
    return res


@pytest.fixture(scope="module")
def drawn(tmp_path_factory, cache_dir):
    out = tmp_path_factory.mktemp("drawn") / "o"
    _fleet(["--missions", "10", "--seed", "3", "--window-min", "10", "--out", str(out)], cache_dir)
    return out


@pytest.fixture(scope="module")
def small(tmp_path_factory, cache_dir):
    tmp = tmp_path_factory.mktemp("small")
    f = _yaml(tmp / "fleet.yaml", FLEET)
    _fleet(["--fleet", str(f), "--out", str(tmp / "a")], cache_dir)
    return tmp, f


def _rows(out: Path) -> list[dict]:
    with open(out / "fleet.csv") as f:
        return list(csv.DictReader(f))


def _decisions(out: Path) -> list[tuple]:
    return [tuple(v for k, v in r.items() if k != "compute_s") for r in _rows(out)]


# ----------------------------------------------------------------------------- independent checks
def _volumes(doc: dict, crs) -> list[tuple]:
    """(polygon [m], alt lo, alt hi [m], t0, t1 [ns]) of an intent, read with plain code."""
    tr = Transformer.from_crs(4326, crs, always_xy=True)
    out = []
    for v in doc["volumes"]:
        vx = v["volume"]["outline_polygon"]["vertices"]
        x, y = tr.transform([p["lng"] for p in vx], [p["lat"] for p in vx])
        out.append((shapely.Polygon(np.column_stack([x, y])), v["volume"]["altitude_lower"]["value"],
                    v["volume"]["altitude_upper"]["value"], pd.Timestamp(v["time_start"]["value"]).value,
                    pd.Timestamp(v["time_end"]["value"]).value))
    return out


def _intersect(u, v, min_area_m2=1e-4) -> bool:
    return (u[1] < v[2] and v[1] < u[2] and u[3] < v[4] and v[3] < u[4]
            and u[0].intersection(v[0]).area > min_area_m2)


def test_tiny_overlap_at_1_cm_precision():
    """InterUSS's 1 cm precision: 0.5 cm x 1 cm of shared area does not count, 2 cm x 1 cm does;
    the VolumeIndex used by the fleet agrees with the plain check above."""
    from skyroute.stages.fleet import Volume4, VolumeIndex

    base = shapely.box(0, 0, 10, 10)
    for dx, expect in ((0.005, False), (0.02, True)):
        other = shapely.box(10 - dx, 9.99, 20, 20)       # overlap dx x 0.01 m
        u, v = (base, 0.0, 10.0, 0, 10), (other, 5.0, 15.0, 5, 15)
        assert _intersect(u, v) is expect
        idx = VolumeIndex()
        idx.add([Volume4(base, 0.0, 10.0, 0.0, 10.0)], "a")
        assert bool(idx.conflicts([Volume4(other, 5.0, 15.0, 5.0, 15.0)])) is expect


def test_drawn_fleet_at_least_half_accepted(drawn):
    rows = _rows(drawn)
    assert len(rows) == 10
    ok = [r for r in rows if r["status"] in ("accepted", "delayed", "preempted-replanned")]
    assert len(ok) >= 5
    assert {p.stem for p in (drawn / "intents").glob("*.json")} == {r["mission"] for r in ok}
    for r in rows:
        if r["status"] == "delayed":
            assert float(r["delay_s"]) > 0
        if r["status"] == "rejected":
            assert r["reason"]
    doc = json.loads((drawn / "summary.json").read_text())
    assert doc["command"] == "fleet" and doc["schema_version"]
    assert all((drawn / f).is_file() for f in doc["files"])
    f = doc["fleet"]
    assert f["conflicts_independent_check"] == 0
    assert f["counts"]["accepted"] + f["counts"]["delayed"] + f["counts"]["preempted-replanned"] == len(ok)
    gj = json.loads((drawn / "fleet.geojson").read_text())
    assert len(gj["features"]) == len(ok) and gj["vertical_datum"]


def test_no_two_accepted_intents_intersect(drawn):
    from implicitdict import ImplicitDict
    from uas_standards.astm.f3548.v21.api import OperationalIntentDetails

    crs = load_scenario("helsinki-medical").grid.crs
    vols = {}
    for p in sorted((drawn / "intents").glob("*.json")):
        doc = json.loads(p.read_text())
        ImplicitDict.parse(doc, OperationalIntentDetails)
        vols[p.stem] = _volumes(doc, crs)
    ids = sorted(vols)
    pairs = 0
    for i, a in enumerate(ids):
        for b in ids[i + 1:]:
            for u in vols[a]:
                for v in vols[b]:
                    pairs += 1
                    assert not _intersect(u, v), (a, b)
    assert pairs > 1000


def test_trajectories_keep_separation_and_stay_in_their_intents(drawn):
    """Brute force at 0.05 s: every pair of tracks flying at the same instant is >= r_p + d_c
    apart; every track sample lies in a volume outline of its own intent during its window."""
    sc = load_scenario("helsinki-medical")
    need = load_vehicle(sc.vehicle).r_p_m + sc.traffic.margin_m
    tr = pd.read_csv(drawn / "tracks.csv")
    tracks = {m: g for m, g in tr.groupby("mission")}
    grid = {}
    for m, g in tracks.items():
        t = np.arange(np.ceil(g.t_s.min() / 0.05), np.floor(g.t_s.max() / 0.05) + 1) * 0.05
        grid[m] = (t, np.column_stack([np.interp(t, g.t_s, g[c]) for c in ("x_m", "y_m", "z_m")]))
    ids = sorted(grid)
    checked = 0
    for i, a in enumerate(ids):
        for b in ids[i + 1:]:
            ta, pa = grid[a]
            tb, pb = grid[b]
            common, ia, ib = np.intersect1d(np.round(ta / 0.05).astype(int), np.round(tb / 0.05).astype(int),
                                            return_indices=True)
            if common.size:
                checked += 1
                assert np.linalg.norm(pa[ia] - pb[ib], axis=1).min() >= need, (a, b)
    assert checked >= 1
    crs = sc.grid.crs
    t0 = pd.Timestamp(sc.mission.start_time_utc).value
    for m, g in tracks.items():
        vols = _volumes(json.loads((drawn / "intents" / f"{m}.json").read_text()), crs)
        t_ns = t0 + (g.t_s.to_numpy() * 1e9).astype(np.int64)
        inside = np.zeros(len(g), bool)
        for poly, _, _, a, b in vols:
            w = (t_ns >= a) & (t_ns <= b)
            inside[w] |= shapely.contains_xy(poly, g.x_m.to_numpy()[w], g.y_m.to_numpy()[w])
        assert inside.all(), m


def test_default_scenario_fleet_of_20_needs_no_flag(tmp_path, cache_dir):
    """`skyroute fleet helsinki-medical --missions 20 --seed 1` exits 0 with no extra flag: the
    scenario's own data.ground gives the intents their absolute heights (issue 24; the other
    city scenarios: tests/test_inspect.py)."""
    res = CliRunner().invoke(main, ["fleet", "helsinki-medical", "--missions", "20", "--seed", "1", "--out",
                                    str(tmp_path / "o"), "--cache-dir", str(cache_dir), "-q"])
    assert res.exit_code == 0, res.output
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert s["fleet"]["counts"]["accepted"] >= 1 and s["fleet"]["conflicts_independent_check"] == 0


def test_fleet_png(drawn):
    import matplotlib.image as mpimg

    img = mpimg.imread(drawn / "fleet.png")
    assert img.shape[1] > 1000 and img.std() > 0.05


def test_priority_preemption_and_determinism(small, cache_dir):
    tmp, f = small
    rows = {r["mission"]: r for r in _rows(tmp / "a")}
    assert rows["high"]["status"] == "accepted"
    assert rows["low"]["status"] in ("preempted-replanned", "rejected")
    assert rows["low"]["preempted_by"] == "high"
    if rows["low"]["status"] == "preempted-replanned":
        assert float(rows["low"]["delay_s"]) > 0
    assert rows["back"]["earliest_s"] == "20.0"
    _fleet(["--fleet", str(f), "--out", str(tmp / "b")], cache_dir)
    assert _decisions(tmp / "a") == _decisions(tmp / "b")
    for p in (tmp / "a" / "intents").glob("*.json"):
        assert p.read_text() == (tmp / "b" / "intents" / p.name).read_text()


def test_distributed_gives_the_sequential_result(small, cache_dir):
    """The speculative driver on a dask.distributed cluster (in-process workers here, to keep
    the test short; `--scheduler distributed` uses worker processes the same way) decides as
    the sequential run of the CLI."""
    from distributed import Client

    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.fleet import (
        FleetOptions,
        default_level,
        fleet_maps,
        load_fleet,
        run_fleet,
    )

    tmp, f = small
    sc = load_scenario("helsinki-medical")
    sc = sc.model_copy(update={"data": sc.data.model_copy(
        update={"ground": GroundReference(height_m=10.0, vertical_datum="EGM96 geoid")})})
    root = Cache(cache_dir).root
    maps = fleet_maps(sc, root)
    tasks = load_fleet(f, sc, sc.gnss.dop_thresholds)
    with Client(processes=False, n_workers=2, threads_per_worker=1, dashboard_address=None) as client:
        res = run_fleet(sc, tasks, cache_dir=root, options=FleetOptions(seed=0), default_dop=default_level(maps),
                        client=client)
    rows = {r["mission"]: r for r in _rows(tmp / "a")}
    assert [(o.task.id, o.status, o.delay_s) for o in res.outcomes] == \
        [(m, rows[m]["status"], float(rows[m]["delay_s"] or 0)) for m in rows]
    assert res.speculative["speculative_used"] + res.speculative["speculative_replanned"] >= 1


def test_distributed_speculation_on_a_dense_drawn_fleet(cache_dir):
    """A dense drawn fleet (30 missions in 4 min, most of them delayed or deconflicted): the
    speculative driver, whose kept attempts include RRT-deconflicted ones (still_valid through
    their free legs) and later departures, gives the sequential result plan for plan."""
    from distributed import Client

    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.fleet import (
        FleetOptions,
        default_level,
        draw_missions,
        fleet_maps,
        run_fleet,
    )

    sc = load_scenario("helsinki-medical")
    sc = sc.model_copy(update={"data": sc.data.model_copy(
        update={"ground": GroundReference(height_m=10.0, vertical_datum="EGM96 geoid")})})
    root = Cache(cache_dir).root
    maps = fleet_maps(sc, root)
    tasks = draw_missions(sc, maps, 30, 5, 240.0)
    opt = FleetOptions(seed=5)
    seq = run_fleet(sc, tasks, cache_dir=root, options=opt, default_dop=default_level(maps))
    with Client(processes=False, n_workers=2, threads_per_worker=1, dashboard_address=None) as client:
        par = run_fleet(sc, tasks, cache_dir=root, options=opt, default_dop=default_level(maps), client=client,
                        depth=3)
    assert [(o.task.id, o.status, o.delay_s, o.attempts) for o in seq.outcomes] == \
        [(o.task.id, o.status, o.delay_s, o.attempts) for o in par.outcomes]
    for a, b in zip(seq.outcomes, par.outcomes, strict=True):
        if a.attempt is not None:
            np.testing.assert_array_equal(a.attempt.xyz_m, b.attempt.xyz_m)
            assert a.attempt.doc == b.attempt.doc
    st = par.speculative
    assert sum(o.delay_s > 0 for o in seq.outcomes) >= 5
    assert st["speculative_used"] >= 5 and st["speculative_still_valid"] >= 1, st
    assert st["speculative_later_departures"] >= 1, st


@pytest.mark.parametrize("kw, match", [({"affinity": "goal"}, "affinity 'goal' must be"),
                                       ({"depth": -1}, "depth -1 must be an integer >= 0")])
def test_run_fleet_refuses_bad_driver_settings(kw, match):
    from skyroute.pipeline.errors import InputError
    from skyroute.pipeline.fleet import run_fleet

    with pytest.raises(InputError, match=match):
        run_fleet(load_scenario("helsinki-medical"), [], **kw)


@pytest.mark.parametrize("missions, lines", [
    ([{"id": "a", "start": A, "departure": 0}], 1),                                   # no goal
    ([{"id": "a", "start": A, "goal": B}, {"id": "a", "start": A, "goal": {"x": 1.0, "y": 2.0, "alt_agl_m": 5}}], 2),
])
def test_bad_fleet_file_exit_2_one_line_per_problem(tmp_path, missions, lines):
    f = _yaml(tmp_path / "bad.yaml", {"missions": missions})
    res = CliRunner().invoke(main, ["fleet", "helsinki-medical", "--fleet", str(f), "--out", str(tmp_path / "o"),
                                    "--cache-dir", str(tmp_path / "c")])
    assert res.exit_code == 2
    err = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(err) == lines and all(ln.startswith("error: ") for ln in err), res.output
    assert not (tmp_path / "c").exists()     # refused before any stage ran


def test_csv_fleet_file(tmp_path):
    from skyroute.pipeline.fleet import load_fleet

    p = tmp_path / "f.csv"
    p.write_text("id,operator,start_x,start_y,start_alt_agl_m,goal_lon,goal_lat,goal_alt_agl_m,departure,priority\n"
                 f"m1,op,{A['x']},{A['y']},60,24.9408349,60.1642173,50,2020-01-03T10:01:00Z,2\n")
    sc = load_scenario("helsinki-medical")
    (t,) = load_fleet(p, sc, sc.gnss.dop_thresholds)
    assert t.earliest_s == 60.0 and t.priority == 2 and t.goal_agl_m == 50
    gx, gy = sc.grid.from_lonlat(24.9408349, 60.1642173)
    assert abs(t.goal_xy[0] - float(gx)) < 1e-6 and abs(t.goal_xy[1] - float(gy)) < 1e-6


def test_volume_prisms_exact_against_sampling():
    """The STEP II prism test against 2001 samples per segment (grown outline, band, window)."""
    from skyroute.stages.fleet import Volume4
    from skyroute.stages.traffic import build_occupancy, volume_prisms

    rng = np.random.default_rng(1)
    vols = []
    for _ in range(30):
        c, z, t = rng.uniform(0, 100, 2), rng.uniform(0, 50), rng.uniform(0, 100)
        vols.append(Volume4(shapely.Point(c).buffer(rng.uniform(3, 10)), z, z + rng.uniform(2, 10), t,
                            t + rng.uniform(5, 30)))
    occ = build_occupancy([], 200.0, 1, 0.0, 0.0).with_volumes(volume_prisms(vols, grow_m=2.0, grow_z_m=1.0,
                                                                             grow_t_s=2.0))
    n = 600
    p0 = np.column_stack([rng.uniform(-10, 110, (n, 2)), rng.uniform(0, 60, n)])
    p1 = p0 + rng.normal(0, 15, (n, 3))
    t0 = rng.uniform(0, 120, n)
    t1 = t0 + rng.uniform(0, 10, n)
    got = occ.segment_conflicts(p0, t0, p1, t1)
    grown = [v.polygon.convex_hull.buffer(2.0 / np.cos(np.pi / 16), quad_segs=4).convex_hull for v in vols]
    s = np.linspace(0, 1, 2001)
    for i in range(n):
        q, tt = p0[i] + s[:, None] * (p1[i] - p0[i]), t0[i] + s * (t1[i] - t0[i])
        hit = False
        for v, g in zip(vols, grown, strict=True):
            m = ((q[:, 2] >= v.alt_lower_m - 1) & (q[:, 2] <= v.alt_upper_m + 1) & (tt >= v.t_start_s - 2)
                 & (tt <= v.t_end_s + 2))
            if m.any() and shapely.contains_xy(g, q[m, 0], q[m, 1]).any():
                hit = True
                break
        if hit:
            assert got[i], i
    assert 5 < got.sum() < n


def test_report_of_a_fleet_folder(drawn, tmp_path):
    """``skyroute report`` on a fleet folder: one self-contained page with the fleet figure and
    one table row per mission, statuses as in fleet.csv."""
    import re

    from skyroute.pipeline.report import build_report

    page = build_report(drawn, tmp_path / "report.html").read_text()
    assert "data:image/png;base64," in page and not re.search(r'src="(?!data:)', page)
    rows = _rows(drawn)
    table = page.split("<h2>Missions</h2>", 1)[1].split("</table>", 1)[0]
    assert table.count("<tr>") == len(rows) + 1
    for r in rows:      # a text column (left-aligned): <td class="text">
        assert re.search(rf'<td(?: class="[a-z]+")?>{re.escape(r["status"])}</td>', table), r["status"]


def test_nothing_accepted_exits_3_with_the_reason(tmp_path, cache_dir):
    """A fleet whose only mission cannot fly (its goal is inside a 70 m building) writes its
    outputs and exits 3 with the reason, like `plan` without a flyable candidate; STEP I fails
    whatever the departure, so the mission is not tried again at later departures."""
    f = _yaml(tmp_path / "walled.yaml", {"missions": [
        {"id": "walled", "operator": "op-a", "start": A, "goal": {"x": 385620.0, "y": 6671880.0, "alt_agl_m": 10},
         "departure": 0}]})
    res = CliRunner().invoke(main, ["fleet", "helsinki-medical", *GROUND, "--cache-dir", str(cache_dir), "-q",
                                    "--fleet", str(f), "--out", str(tmp_path / "o"), "--max-delay-min", "1"])
    assert res.exit_code == 3, res.output
    assert "no mission accepted:" in res.output and "inside obstacle clearance" in res.output
    (row,) = _rows(tmp_path / "o")
    assert row["status"] == "rejected" and "inside obstacle clearance" in row["reason"]
    assert row["attempts"] == "1" and "no plan at any departure" in row["reason"]


# ----------------------------------------------------------------------------- the airspace store (issue 26)
KILL_FLEET = {"missions": [
    {"id": "k1", "start": A, "goal": B, "departure": 0},
    {"id": "k2", "start": C, "goal": D, "departure": 5},
    {"id": "k3", "start": B, "goal": A, "departure": 10},
    {"id": "k4", "start": A, "goal": B, "departure": 15},
]}


def _air(args, code=0):
    res = CliRunner().invoke(main, ["airspace", *args])
    assert res.exit_code == code, res.output
    return res


@pytest.fixture(scope="module")
def airspace(tmp_path_factory, cache_dir):
    """The small fleet into a new airspace file, then the same missions under new ids into it:
    the second batch is planned against the first (delayed or re-routed, never intersecting)."""
    tmp = tmp_path_factory.mktemp("air")
    f = _yaml(tmp / "fleet.yaml", KILL_FLEET)
    g = _yaml(tmp / "again.yaml", {"missions": [{**m, "id": m["id"] + "b"} for m in KILL_FLEET["missions"]]})
    _fleet(["--fleet", str(f), "--out", str(tmp / "a"), "--airspace", str(tmp / "air.sqlite")], cache_dir)
    _fleet(["--fleet", str(g), "--out", str(tmp / "b"), "--airspace", str(tmp / "air.sqlite")], cache_dir)
    return tmp


def test_fleet_against_an_airspace(airspace):
    from skyroute.stages.airspace_store import AirspaceStore

    first = {r["mission"]: r for r in _rows(airspace / "a")}
    second = {r["mission"]: r for r in _rows(airspace / "b")}
    assert set(second) == {m + "b" for m in first}
    ok = ("accepted", "delayed", "preempted-replanned")
    # the same route at the same departure as an accepted intent of the first run cannot be
    # accepted undelayed with the same path: the first runs' intents were traffic
    assert any(second[m + "b"]["status"] != "accepted" or second[m + "b"]["length_m"] != first[m]["length_m"]
               for m in first if first[m]["status"] in ok)
    s = json.loads((airspace / "b" / "summary.json").read_text())["fleet"]["airspace"]
    assert s["intents_before"] == sum(r["status"] in ok for r in first.values()) > 0
    assert s["intents_after"] == s["intents_before"] + sum(r["status"] in ok for r in second.values())
    assert s["conflicts_with_the_airspace"] == 0
    with AirspaceStore.open(airspace / "air.sqlite") as st:
        assert len(st) == s["intents_after"]
        docs = {r.id: r.details for r in st.records(details=True)}
    # every pair of intents of both runs, by the plain shapely code of this file
    crs = load_scenario("helsinki-medical").grid.crs
    vols = {m: _volumes(d, crs) for m, d in docs.items()}
    ids = sorted(vols)
    for i, a in enumerate(ids):
        for b in ids[i + 1:]:
            assert not any(_intersect(u, v) for u in vols[a] for v in vols[b]), (a, b)
    assert "airspace.sqlite" not in json.loads((airspace / "b" / "summary.json").read_text())["files"]


def test_default_airspace_in_the_output_folder(drawn):
    """Without --airspace a run writes a new OUT/airspace.sqlite (listed in summary.json) holding
    exactly its accepted intents; `airspace check` passes on it."""
    doc = json.loads((drawn / "summary.json").read_text())
    assert "airspace.sqlite" in doc["files"]
    ok = {r["mission"] for r in _rows(drawn) if r["status"] != "rejected"}
    out = json.loads(_air(["ls", str(drawn / "airspace.sqlite"), "--json"]).output)
    assert {r["id"] for r in out["intents"]} == ok
    assert set(out["rejected_missions"]) == {r["mission"] for r in _rows(drawn) if r["status"] == "rejected"}
    _air(["check", str(drawn / "airspace.sqlite")])


def test_airspace_ls_show_export_check(airspace, tmp_path):
    f = str(airspace / "air.sqlite")
    out = _air(["ls", f]).output
    assert "k1 " in out and "k1b" in out and "Accepted" in out
    doc = json.loads(_air(["ls", f, "--json"]).output)
    ids = [r["id"] for r in doc["intents"]]
    shown = json.loads(_air(["show", f, ids[0]]).output)
    assert shown["state"] == "Accepted" and shown["details"]["volumes"] and shown["mission"]["scenario"]
    _air(["export", f, str(tmp_path / "x")])
    s = json.loads((tmp_path / "x" / "summary.json").read_text())
    assert s["command"] == "airspace export" and s["schema_version"] and s["warnings"] == []
    assert sorted(s["files"]) == sorted([f"{i}.json" for i in ids] + ["summary.json", ".skyroute-manifest.json"])
    from skyroute.stages.intents import parse_intent

    for i in ids:
        assert parse_intent(json.loads((tmp_path / "x" / f"{i}.json").read_text())).volumes
    chk = json.loads(_air(["check", f, "--json"]).output)
    assert chk["consistent"] and chk["conflicts"] == 0 and chk["intents"] == len(ids)


def test_airspace_check_finds_a_conflict_and_damage(airspace, tmp_path):
    """A copy of one intent under another id, written past the store's own check: `airspace
    check` exits 1 naming the pair; a volume row deleted: exit 1, inconsistent."""
    import shutil
    import sqlite3

    f = tmp_path / "bad.sqlite"
    shutil.copy(airspace / "air.sqlite", f)
    c = sqlite3.connect(f)
    c.execute("INSERT INTO intents SELECT 'dup', (SELECT MAX(seq) + 1 FROM intents), state, priority, operator, "
              "details, mission, departure_utc, t_start_s, t_end_s, accepted_utc, n_volumes FROM intents "
              "WHERE id = 'k1'")
    c.execute("INSERT INTO decisions SELECT 'dup', status, reason, mission_fields, decided_utc FROM decisions "
              "WHERE mission = 'k1'")
    rows = c.execute("SELECT k, outline_wkb, alt_lower_m, alt_upper_m, t_start_s, t_end_s FROM volumes "
                     "WHERE intent_id = 'k1'").fetchall()
    for r in rows:
        vid = c.execute("INSERT INTO volumes (intent_id, k, outline_wkb, alt_lower_m, alt_upper_m, t_start_s, "
                        "t_end_s) VALUES ('dup', ?, ?, ?, ?, ?, ?)", r).lastrowid
        b = shapely.from_wkb(r[1]).bounds
        c.execute("INSERT INTO volume_rtree VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                  (vid, b[0], b[2], b[1], b[3], r[2], r[3], r[4], r[5]))
    c.commit()
    res = _air(["check", str(f)], code=1)
    assert "conflict: dup x k1" in res.output and ", consistent," in res.output
    c.execute("DELETE FROM volumes WHERE intent_id = 'k2' AND k = 0")
    c.commit()
    c.close()
    res = _air(["check", str(f)], code=1)
    assert "INCONSISTENT" in res.output and "intent k2" in res.output


@pytest.mark.parametrize("args", [["airspace", "ls", "{f}"], ["airspace", "check", "{f}"],
                                  ["airspace", "show", "{f}", "x"], ["fleet", "helsinki-medical", "--missions", "1",
                                                                     "--airspace", "{f}", "--out", "{o}"]])
def test_bad_airspace_file_one_error_line_exit_2(tmp_path, args):
    f = tmp_path / "notes.txt"
    f.write_text("not a database")
    res = CliRunner().invoke(main, [a.format(f=f, o=tmp_path / "o") for a in args])
    assert res.exit_code == 2, res.output
    lines = [x for x in res.output.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "not an SQLite database" in lines[0]
    assert not (tmp_path / "o" / "fleet.csv").exists()


def test_airspace_folder_or_missing_file_one_error_line(tmp_path):
    for args, what in ((["airspace", "check", str(tmp_path)], "is a folder"),
                       (["airspace", "ls", str(tmp_path / "none.sqlite")], "does not exist")):
        res = CliRunner().invoke(main, args)
        assert res.exit_code == 2 and res.output.count("\n") == 1 and res.output.startswith("error: ")
        assert what in res.output


def test_unknown_intent_and_changed_mission(airspace, tmp_path, cache_dir):
    res = CliRunner().invoke(main, ["airspace", "show", str(airspace / "air.sqlite"), "nope"])
    assert res.exit_code == 2 and res.output.startswith("error: no intent 'nope'")
    moved = {"missions": [{**KILL_FLEET["missions"][0], "departure": 500}]}
    res = CliRunner().invoke(main, ["fleet", "helsinki-medical", "--cache-dir", str(cache_dir), "-q", "--fleet",
                                    str(_yaml(tmp_path / "m.yaml", moved)), "--airspace",
                                    str(airspace / "air.sqlite"), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "k1 already decided in the airspace" in res.output


def test_preemption_is_one_transaction_in_the_default_airspace(small):
    """The small fleet's preemption (high preempts low, low re-planned or rejected): its
    OUT/airspace.sqlite holds exactly the missions fleet.csv accepts, with their statuses, and
    `airspace check` passes."""
    tmp, _ = small
    rows = {r["mission"]: r for r in _rows(tmp / "a")}
    doc = json.loads(_air(["ls", str(tmp / "a" / "airspace.sqlite"), "--json"]).output)
    assert {r["id"]: r["status"] for r in doc["intents"]} == {m: r["status"] for m, r in rows.items()
                                                              if r["status"] != "rejected"}
    assert set(doc["rejected_missions"]) == {m for m, r in rows.items() if r["status"] == "rejected"}
    _air(["check", str(tmp / "a" / "airspace.sqlite")])


def test_intents_of_an_earlier_run_are_not_preempted(tmp_path, cache_dir):
    """A priority-1 mission on the route of a priority-0 intent accepted by an earlier run into
    the airspace is planned around it (delayed or re-routed): the stored intent stays."""
    low, high = FLEET["missions"][0], FLEET["missions"][1]
    air = str(tmp_path / "air.sqlite")
    _fleet(["--fleet", str(_yaml(tmp_path / "l.yaml", {"missions": [low]})), "--out", str(tmp_path / "l"),
            "--airspace", air], cache_dir)
    _fleet(["--fleet", str(_yaml(tmp_path / "h.yaml", {"missions": [high]})), "--out", str(tmp_path / "h"),
            "--airspace", air], cache_dir)
    (row,) = _rows(tmp_path / "h")
    assert row["status"] in ("accepted", "delayed") and not row["preempted_by"]
    doc = json.loads(_air(["ls", air, "--json"]).output)
    assert {r["id"] for r in doc["intents"]} == {"low", "high"}
    _air(["check", air])


def test_continue_the_default_airspace_of_a_folder(tmp_path, cache_dir):
    """`fleet --airspace OUT/airspace.sqlite --out OUT` (the folder's own file) keeps the file
    (summary.json lists it) and plans nothing twice."""
    f = _yaml(tmp_path / "f.yaml", {"missions": KILL_FLEET["missions"][:2]})
    out = tmp_path / "o"
    _fleet(["--fleet", str(f), "--out", str(out)], cache_dir)
    res = _fleet(["--fleet", str(f), "--out", str(out), "--airspace", str(out / "airspace.sqlite")], cache_dir)
    assert "2 mission(s) already decided" in res.output
    assert "airspace.sqlite" in json.loads((out / "summary.json").read_text())["files"]
    assert len(json.loads(_air(["ls", str(out / "airspace.sqlite"), "--json"]).output)["intents"]) == 2


def _child(args: list[str], pause_s: float) -> None:      # a forked `skyroute fleet --airspace` process
    import os
    import sys

    os.environ["SKYROUTE_TEST_ACCEPT_PAUSE_S"] = str(pause_s)
    fd = os.open(os.devnull, os.O_WRONLY)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    code = 1
    try:
        main(args, standalone_mode=False)
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    except BaseException:        # noqa: BLE001 - the exit code says it
        code = 1
    sys.stdout.flush()
    os._exit(code)


def test_sigkill_at_random_points_leaves_a_checked_store_that_continues(tmp_path, cache_dir):
    """`skyroute fleet --airspace FILE` in a child process SIGKILLed at a random moment, 20
    times (inside an accept's transaction about a third of the time: the child sleeps 0.15 s in
    each); after every kill `airspace check` passes (consistent, no conflict), and the next run
    continues the same file; a run that finishes must leave exactly the decisions of an
    uninterrupted run (then the file starts again empty).  The children are forked from this
    warm process (maps and compiled kernels loaded) to keep the 20 runs short."""
    import multiprocessing as mp
    import random
    import time

    from skyroute.stages.airspace_store import AirspaceStore

    f = _yaml(tmp_path / "fleet.yaml", KILL_FLEET)
    ref = tmp_path / "ref.sqlite"
    _fleet(["--fleet", str(f), "--out", str(tmp_path / "ref"), "--airspace", str(ref)], cache_dir)

    def decisions(p):
        with AirspaceStore.open(p) as s:
            dep = {r.id: r.departure_utc for r in s.records()}
            return {m: (d[0], dep.get(m)) for m, d in s.decisions().items()}

    want = decisions(ref)
    assert len(want) == 4
    store = tmp_path / "air.sqlite"
    args = ["fleet", "helsinki-medical", *GROUND, "--cache-dir", str(cache_dir), "-q", "--fleet", str(f), "--out",
            str(tmp_path / "o"), "--airspace", str(store)]
    rng = random.Random(26)
    ctx = mp.get_context("fork")
    t = time.perf_counter()                   # one whole run of a child: the span of the kill times
    p = ctx.Process(target=_child, args=(args, 0.15))
    p.start()
    p.join()
    t_full = time.perf_counter() - t
    assert p.exitcode == 0 and decisions(store) == want
    for q in tmp_path.glob("air.sqlite*"):
        q.unlink()
    kills = completed = partial = 0
    t0 = time.perf_counter()
    while kills < 20:
        p = ctx.Process(target=_child, args=(args, 0.15))
        p.start()
        p.join(rng.uniform(0.0, 0.7 * t_full))
        if p.exitcode is None:
            p.kill()                          # SIGKILL
            p.join()
        if p.exitcode == -9:                  # (the child may have finished between join and kill)
            kills += 1
            if store.exists():
                res = CliRunner().invoke(main, ["airspace", "check", str(store)])
                assert res.exit_code == 0, res.output
                got = decisions(store)
                assert all(want[m] == d for m, d in got.items()), (got, want)   # a prefix of the same decisions
                partial += 0 < len(got) < len(want)
        else:
            assert p.exitcode == 0
            assert decisions(store) == want   # continued to the uninterrupted run's result
            completed += 1
            for q in tmp_path.glob("air.sqlite*"):
                q.unlink()
    p = ctx.Process(target=_child, args=(args, 0.0))    # the last killed file continues to the end
    p.start()
    p.join()
    assert p.exitcode == 0 and decisions(store) == want
    print(f"{kills} kills ({partial} with some missions decided), {completed} runs completed, "
          f"{time.perf_counter() - t0:.1f} s")
    assert partial >= 3                       # the kills land while missions are being decided


def test_min_km_above_max_km_one_error_line(tmp_path):
    res = CliRunner().invoke(main, ["fleet", "helsinki-medical", "--missions", "3", "--min-km", "2", "--max-km", "1",
                                    "--out", str(tmp_path / "f")])
    assert res.exit_code == 2 and res.output.count("\n") == 1 and res.output.startswith("error: ")
    assert "--min-km 2 is above --max-km 1" in res.output
