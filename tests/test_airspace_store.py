"""skyroute.stages.airspace_store: the SQLite airspace (WAL, R*Tree), its transactions, its
candidate query (property-tested: never misses a pair the all-pairs check finds) and its
consistency check (which must catch a damaged store)."""

from __future__ import annotations

import sqlite3
import tempfile
from pathlib import Path

import numpy as np
import pytest
import shapely
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from skyroute.stages.airspace_store import AirspaceConflictError, AirspaceStore
from skyroute.stages.base import InputError
from skyroute.stages.fleet import Volume4, accept_fcfs, conflicts_naive
from skyroute.stages.intents import IntentVolume, intent_details

CRS = "EPSG:3067"
EPOCH = "2020-01-03T10:00:00Z"
X0, Y0 = 385_000.0, 6_672_000.0


def box_vol(x, y, w, h, a0, a1, t0, t1) -> Volume4:
    return Volume4(shapely.box(X0 + x, Y0 + y, X0 + x + w, Y0 + y + h), a0, a1, t0, t1)


def doc_of(vols) -> dict:
    """The F3548 document of map volumes (intent_details: lat/lng, W84, RFC 3339)."""
    iv = [IntentVolume(np.asarray(v.polygon.exterior.coords)[:-1], v.alt_lower_m, v.alt_upper_m, v.t_start_s,
                       v.t_end_s, 0.0) for v in vols]
    return intent_details(iv, CRS, EPOCH)


@pytest.fixture
def store(tmp_path):
    with AirspaceStore.create(tmp_path / "a.sqlite", CRS, EPOCH) as s:
        yield s


def test_accept_list_reopen_and_wal(store, tmp_path):
    v1 = [box_vol(0, 0, 10, 10, 50, 60, 0, 30), box_vol(10, 0, 10, 10, 50, 60, 30, 60)]
    store.accept("a", doc_of(v1), v1, priority=1, operator="op-1", mission={"start": [1, 2]})
    v2 = [box_vol(0, 0, 10, 10, 60, 70, 0, 30), box_vol(10, 0, 10, 10, 60, 70, 30, 60)]   # touches a's band
    store.accept("b", doc_of(v2), v2)
    assert len(store) == 2 and store.n_volumes() == 4
    assert store.check() == []
    store.close()
    with AirspaceStore.open(tmp_path / "a.sqlite") as s:
        assert s._conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert [r.id for r in s.records()] == ["a", "b"]
        r = s.record("a")
        assert (r.priority, r.operator, r.mission, r.n_volumes) == (1, "op-1", {"start": [1, 2]}, 2)
        assert r.details["volumes"][0]["volume"]["altitude_lower"]["value"] == 50
        got = s.volumes(["a"])["a"]
        assert got[1].polygon.equals_exact(v1[1].polygon, 0.0) and got[1].t_end_s == 60
        assert s.decisions()["a"][0] == "accepted"
        with pytest.raises(InputError, match="no intent 'zz'"):
            s.record("zz")


def test_conflicting_accept_writes_nothing(store):
    v = [box_vol(0, 0, 10, 10, 50, 60, 0, 30)]
    store.accept("a", doc_of(v), v)
    w = [box_vol(5, 5, 10, 10, 55, 65, 20, 40)]
    with pytest.raises(AirspaceConflictError, match="a"):
        store.accept("b", doc_of(w), w)
    assert [r.id for r in store.records()] == ["a"] and store.n_volumes() == 1
    assert "b" not in store.decisions()
    # preemption: withdrawing "a" in the same transaction lets "b" in, and "a" is undecided again
    store.accept("b", doc_of(w), w, withdraw=["a"])
    assert [r.id for r in store.records()] == ["b"] and "a" not in store.decisions()
    assert store.check() == [] and store.self_conflicts() == []


def test_bad_files_are_one_clear_error(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        AirspaceStore.open(tmp_path / "nope.sqlite")
    (tmp_path / "t.txt").write_text("hello")
    with pytest.raises(InputError, match="not an SQLite database"):
        AirspaceStore.open(tmp_path / "t.txt")
    c = sqlite3.connect(tmp_path / "other.sqlite")
    c.execute("CREATE TABLE x (a)")
    c.commit()
    c.close()
    with pytest.raises(InputError, match="not a skyroute airspace"):
        AirspaceStore.open(tmp_path / "other.sqlite")
    with pytest.raises(InputError, match="projected"):
        AirspaceStore.create(tmp_path / "g.sqlite", "EPSG:4326", EPOCH)


def test_check_finds_damage(store):
    v = [box_vol(0, 0, 10, 10, 50, 60, 0, 30), box_vol(10, 0, 10, 10, 50, 60, 30, 60)]
    store.accept("a", doc_of(v), v)
    w = [box_vol(100, 0, 10, 10, 50, 60, 0, 30)]
    store.accept("b", doc_of(w), w)
    c = store._conn
    c.execute("DELETE FROM volumes WHERE intent_id = 'a' AND k = 1")            # a volume lost
    c.execute("UPDATE volume_rtree SET max_t = 10 WHERE vid = (SELECT vid FROM volumes WHERE intent_id = 'b')")
    probs = store.check()
    assert any("intent a: 1 volume rows" in p for p in probs)
    assert any("R*Tree box" in p for p in probs)
    # an outline moved by 1 m: the document no longer matches the stored volume
    c.execute("UPDATE volumes SET outline_wkb = ? WHERE intent_id = 'b'",
              (shapely.to_wkb(shapely.box(X0 + 101, Y0, X0 + 111, Y0 + 10)),))
    assert any("document outline differs" in p for p in store.check())


# ------------------------------------------------------------------------------ the candidate query
vol_st = st.builds(lambda x, y, w, h, a, da, t, dt: box_vol(x, y, w, h, a, a + da, t, t + dt),
                   st.floats(0, 200), st.floats(0, 200), st.floats(0.5, 60), st.floats(0.5, 60),
                   st.floats(0, 120), st.floats(0.5, 30), st.floats(0, 600), st.floats(1, 120))


def _rotated(v: Volume4, ang: float) -> Volume4:
    import shapely.affinity as aff

    return Volume4(aff.rotate(v.polygon, ang, origin="centroid"), v.alt_lower_m, v.alt_upper_m, v.t_start_s,
                   v.t_end_s)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.lists(vol_st, min_size=1, max_size=4), st.floats(0, 90)), min_size=1, max_size=25),
       st.lists(vol_st, min_size=1, max_size=8))
def test_rtree_candidates_never_miss_a_pair(intents, query):
    """First-come-first-served into the store (R*Tree + exact test) decides as accept_fcfs
    (STRtree) does; the candidates of any query hold every pair the all-pairs check finds,
    and the store's conflicts are exactly those pairs."""
    ints = [(f"i{k}", [_rotated(v, ang) for v in vs]) for k, (vs, ang) in enumerate(intents)]
    dec, _ = accept_fcfs(ints)
    with tempfile.TemporaryDirectory() as tmp, AirspaceStore.create(Path(tmp) / "s.sqlite", CRS, EPOCH) as s:
        for (iid, vs), d in zip(ints, dec, strict=True):
            try:
                s.accept(iid, doc_of(vs), vs)
                ok = True
            except AirspaceConflictError:
                ok = False
            assert ok == d.accepted
        acc = [(iid, vs) for (iid, vs), d in zip(ints, dec, strict=True) if d.accepted]
        flat = [(iid, v) for iid, vs in acc for v in vs]
        naive = conflicts_naive(query, [v for _, v in flat])
        qidx, vids = s.candidates(query)
        vid_of = {}
        for iid, _ in acc:
            for k, (vid,) in enumerate(s._conn.execute("SELECT vid FROM volumes WHERE intent_id = ? ORDER BY k",
                                                       (iid,))):
                vid_of[(iid, k)] = vid
        k_in = {}
        for iid, vs in acc:
            for k in range(len(vs)):
                k_in[len(k_in)] = vid_of[(iid, k)]
        cand = set(zip(qidx.tolist(), vids.tolist(), strict=True))
        for i, j in naive:
            assert (i, k_in[j]) in cand
        assert s.conflicts(query) == sorted({(i, flat[j][0]) for i, j in naive})
        assert s.self_conflicts() == []
