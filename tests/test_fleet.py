"""First-come-first-served acceptance of 4-D volumes (stages/fleet.py), checked by brute force."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
import shapely.affinity

from skyroute.stages.base import InputError
from skyroute.stages.fleet import (
    Volume4,
    VolumeIndex,
    accept_fcfs,
    conflicts_naive,
    volumes_intersect,
    volumes_of_intent,
)


def _box(x0, y0, w=10.0, h=10.0, alt=(0.0, 10.0), t=(0.0, 60.0)):
    return Volume4(shapely.box(x0, y0, x0 + w, y0 + h), alt[0], alt[1], t[0], t[1])


def test_tiny_overlaps_at_1_cm():
    a = _box(0, 0)
    # outlines overlapping by a 1 cm strip (0.1 m^2): intersect; touching or 0.005 mm apart: not
    assert volumes_intersect(a, _box(9.99, 0))
    assert not volumes_intersect(a, _box(10.0, 0))
    assert not volumes_intersect(a, _box(9.999995, 0))        # 5e-5 m^2 < 1e-4 m^2
    # a 2 cm x 2 cm corner overlap
    assert volumes_intersect(a, _box(9.98, 9.98))             # 4e-4 m^2
    # altitude bands: touching no, 1 cm overlap yes
    assert not volumes_intersect(a, _box(5, 5, alt=(10.0, 20.0)))
    assert volumes_intersect(a, _box(5, 5, alt=(9.99, 20.0)))
    # time windows: touching no, 10 ms overlap yes
    assert not volumes_intersect(a, _box(5, 5, t=(60.0, 90.0)))
    assert volumes_intersect(a, _box(5, 5, t=(59.99, 90.0)))
    with pytest.raises(InputError):
        _box(0, 0, alt=(5.0, 5.0))


def _random_volumes(rng, n, extent=2000.0):
    out = []
    for _ in range(n):
        x, y = rng.uniform(0, extent, 2)
        ang = rng.uniform(0, np.pi)
        L, w = rng.uniform(20, 200), rng.uniform(4, 20)
        line = shapely.LineString([(x, y), (x + L * np.cos(ang), y + L * np.sin(ang))])
        lo = rng.uniform(0, 100)
        t0 = rng.uniform(0, 3600)
        out.append(Volume4(line.buffer(w, quad_segs=2), lo, lo + rng.uniform(5, 30), t0, t0 + rng.uniform(10, 120)))
    return out


def test_index_equals_pairwise_brute_force():
    rng = np.random.default_rng(5)
    acc = _random_volumes(rng, 1500)
    idx = VolumeIndex(rebuild_every=400)
    for k in range(0, len(acc), 100):            # indexed part + an unindexed tail
        idx.add(acc[k:k + 100], owner=k // 100)
    assert 0 < len(acc) - idx._n_tree < 400
    q = _random_volumes(rng, 200)
    got = idx.conflicts(q)
    want = conflicts_naive(q, acc)
    assert got == want and len(want) > 10


def test_fcfs_accepts_only_disjoint_intents():
    rng = np.random.default_rng(11)
    intents = [(f"m{i}", _random_volumes(rng, 4, extent=800.0)) for i in range(150)]
    dec, idx = accept_fcfs(intents)
    acc = [i for i, d in enumerate(dec) if d.accepted]
    assert 10 < len(acc) < 150
    # independent check: no two accepted intents intersect (every volume pair, shapely directly)
    for a in range(len(acc)):
        for b in range(a + 1, len(acc)):
            for va in intents[acc[a]][1]:
                for vb in intents[acc[b]][1]:
                    over = (va.alt_lower_m < vb.alt_upper_m and vb.alt_lower_m < va.alt_upper_m
                            and va.t_start_s < vb.t_end_s and vb.t_start_s < va.t_end_s)
                    assert not (over and va.polygon.intersection(vb.polygon).area > 1e-4)
    # every rejected one intersects an intent accepted before it, named in the decision
    for i, d in enumerate(dec):
        if not d.accepted:
            earlier = [j for j in acc if j < i and intents[j][0] in d.conflicts_with]
            assert earlier and conflicts_naive(intents[i][1], intents[earlier[0]][1])
            assert d.conflicts_with[0] in d.reason


def test_volumes_of_intent_round_trip():
    from skyroute.stages.intents import IntentVolume, intent_details

    crs = "EPSG:32635"
    ring = np.array([[385000.0, 6672000.0], [385050.0, 6672000.0], [385050.0, 6672030.0], [385000.0, 6672030.0]])
    doc = intent_details([IntentVolume(ring, 40.0, 60.0, 10.0, 70.0, 5.0)], crs, "2026-01-01T00:00:00Z")
    (v,) = volumes_of_intent(doc, crs, "2026-01-01T00:00:00Z")
    assert v.polygon.area == pytest.approx(1500.0, abs=1e-3)
    assert (v.alt_lower_m, v.alt_upper_m, v.t_start_s, v.t_end_s) == (40.0, 60.0, 10.0, 70.0)


def test_plan_intents_conflict_only_when_they_meet_in_time():
    """Two missions on the same route (intents of stages/intents.py): same departure ->
    rejected; departure after the first intent's last volume ends -> accepted; a route 40 m to
    the side (buffers ~4 m) -> accepted at the same time."""
    from skyroute.stages.fleet import volumes_of_plan
    from skyroute.stages.intents import plan_volumes
    from skyroute.stages.smoothing import KinematicLimits, corner_trajectory
    from skyroute.stages.vehicle import load_vehicle

    chain = np.array([[0.0, 0.0, 30.0], [300.0, 50.0, 50.0], [400.0, 300.0, 50.0]])
    traj = corner_trajectory(chain, np.full(2, 12.0), KinematicLimits.of(load_vehicle("dji-m300-rtk")))
    t_s = traj.sample_times(0.5)
    sigma = np.full(t_s.size, 0.5)

    def vols():
        return plan_volumes(traj, 0.0, t_s, sigma, lambda p: p[:, 2] + 20.0, vehicle_radius_m=2.0)

    first = volumes_of_plan(vols())
    end = max(v.t_end_s for v in first)
    later = volumes_of_plan(vols(), t_offset_s=end + 0.01)
    side = [Volume4(shapely.affinity.translate(v.polygon, 0.0, 40.0), v.alt_lower_m, v.alt_upper_m, v.t_start_s,
                    v.t_end_s) for v in first]
    dec, _ = accept_fcfs([("a", first), ("same", volumes_of_plan(vols())), ("later", later), ("side", side)])
    assert [d.accepted for d in dec] == [True, False, True, True]
    assert dec[1].conflicts_with == ("a",)


def test_site_pairs_without_the_matrix_equal_nonzero():
    """draw_missions' pairs (blocks of rows, no n x n matrix: a city has tens of thousands of
    sites) are np.nonzero's of the whole distance matrix, in the same order."""
    import numpy as np

    from skyroute.pipeline.fleet_missions import _Pairs

    rng = np.random.default_rng(5)
    for n, block in ((1, 256), (37, 4), (600, 256), (600, 7)):
        x, y = rng.uniform(0, 3000, n), rng.uniform(0, 3000, n)
        lab = rng.integers(1, 3, n)
        d = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :])
        ii, jj = np.nonzero((d >= 500.0) & (d <= 1500.0) & (lab[:, None] == lab[None, :]))
        _Pairs.BLOCK = block
        try:
            p = _Pairs(x, y, lab, 500.0, 1500.0)
        finally:
            _Pairs.BLOCK = 256
        assert p.size == ii.size
        for k in rng.integers(0, max(ii.size, 1), 50) if ii.size else []:
            assert p[int(k)] == (ii[k], jj[k])
        if ii.size:
            assert p[0] == (ii[0], jj[0]) and p[ii.size - 1] == (ii[-1], jj[-1])
