"""Tactical separation checks against independent references: brute-force sampling of both
tracks at 1 ms (exact check), sampling of the intruder over the time-margin window (dt_c > 0),
hand-computed touching cases, and BlueSky's numpy formulation + dense sampling (pairwise)."""

from __future__ import annotations

import numpy as np
import pytest

from skyroute.stages.base import InputError
from skyroute.stages.tactical.conflict import (
    IntruderTracks,
    first_conflict,
    min_separation,
    pairwise_conflicts,
    pairwise_conflicts_numpy,
)
from skyroute.stages.traffic import Intruder

DT_BRUTE = 1e-3      # [s] brute-force sampling step
T_TOL = 1e-6         # [s] tolerance on the bracketing samples


def random_polyline(rng, n, t0, dt_range=(2.0, 8.0), speed=(3.0, 15.0), centre=(200.0, 200.0, 60.0)):
    t = t0 + np.cumsum(np.r_[0.0, rng.uniform(*dt_range, n - 1)])
    p = np.empty((n, 3))
    p[0] = np.asarray(centre) + rng.uniform(-80, 80, 3) * [1, 1, 0.2]
    for k in range(1, n):
        v = rng.uniform(*speed)
        h = rng.uniform(0, 2 * np.pi)
        # pull back towards the centre so that encounters happen
        pull = (np.asarray(centre) - p[k - 1]) * 0.05
        step = (t[k] - t[k - 1]) * np.array([v * np.cos(h), v * np.sin(h), rng.uniform(-1, 1)])
        p[k] = p[k - 1] + step + pull
    return t, p


def random_scene(seed, n_intruders=6):
    rng = np.random.default_rng(seed)
    t, p = random_polyline(rng, 15, 0.0)
    intr = []
    for i in range(n_intruders):
        k = int(rng.integers(1, 7))
        ti, pi = random_polyline(rng, k, rng.uniform(-20, 60))
        intr.append(Intruder(f"u{i}", ti, pi, float(rng.uniform(1, 3))))
    sep = rng.uniform(10.0, 40.0, n_intruders)
    return t, p, intr, sep


def interp(t, p, x):
    return np.stack([np.interp(x, t, p[:, d]) for d in range(3)], axis=-1)


def brute_first(t, p, intr, sep, t_from=-np.inf):
    """(t_prev, t_hit, index) of the first 1 ms sample closer than sep, or None."""
    best = None
    for i, it in enumerate(intr):
        lo = max(t[0], it.times_s[0], t_from)
        hi = min(t[-1], it.times_s[-1])
        if lo > hi:
            continue
        x = np.r_[np.arange(lo, hi, DT_BRUTE), hi]
        d = np.linalg.norm(interp(t, p, x) - interp(it.times_s, it.xyz_m, x), axis=1)
        k = np.nonzero(d < sep[i])[0]
        if k.size and (best is None or x[k[0]] < best[1]):
            best = (x[max(k[0] - 1, 0)] if k[0] > 0 else x[0], x[k[0]], i, x, d, k[0])
    return best


@pytest.mark.parametrize("seed", range(12))
def test_first_conflict_against_brute_force(seed):
    t, p, intr, sep = random_scene(seed)
    tracks = IntruderTracks.from_intruders(intr)
    for t_from in (-np.inf, 20.0):
        c = first_conflict(t, p, tracks, sep, t_from_s=t_from)
        b = brute_first(t, p, intr, sep, t_from)
        if b is None:
            # only an encounter shorter than the sampling step may escape the brute force
            assert c is None or sep[c.index] - c.distance_m < 1e-3
            continue
        t_prev, t_hit, i, x, d, k = b
        assert c is not None
        assert t_prev - T_TOL <= c.t_s <= t_hit + T_TOL
        if c.index != i:      # a tie within one sampling step
            assert abs(c.t_s - t_hit) <= DT_BRUTE + T_TOL
            continue
        assert c.id == intr[i].id
        np.testing.assert_allclose(c.own_xyz_m, interp(t, p, c.t_s), atol=1e-6)
        np.testing.assert_allclose(c.intruder_xyz_m, interp(intr[i].times_s, intr[i].xyz_m, c.t_s), atol=1e-6)
        assert abs(np.linalg.norm(c.own_xyz_m - c.intruder_xyz_m) - sep[i]) < 1e-6 or c.t_s == max(
            t[0], intr[i].times_s[0], t_from)
        # the encounter's minimum: sampled minimum over the run of samples inside
        run = d[k:]
        end = np.nonzero(run >= sep[i])[0]
        run = run[: end[0]] if end.size else run
        assert c.distance_m <= run.min() + 1e-9
        assert run.min() - c.distance_m < 0.05       # 1 ms x relative speed < 50 mm
        assert abs(np.linalg.norm(interp(t, p, c.t_cpa_s) - interp(intr[i].times_s, intr[i].xyz_m, c.t_cpa_s))
                   - c.distance_m) < 1e-6


def test_some_random_scenes_have_conflicts():
    """The random scenes above exercise both outcomes."""
    found = [first_conflict(*s[:2], IntruderTracks.from_intruders(s[2]), s[3]) is not None
             for s in map(random_scene, range(12))]
    assert 3 <= sum(found) <= 11


@pytest.mark.parametrize("seed", range(6))
def test_min_separation_against_brute_force(seed):
    t, p, intr, _ = random_scene(seed)
    m = min_separation(t, p, IntruderTracks.from_intruders(intr))
    for i, it in enumerate(intr):
        lo, hi = max(t[0], it.times_s[0]), min(t[-1], it.times_s[-1])
        if lo > hi:
            assert m[i] == np.inf
            continue
        x = np.r_[np.arange(lo, hi, DT_BRUTE), hi]
        d = np.linalg.norm(interp(t, p, x) - interp(it.times_s, it.xyz_m, x), axis=1).min()
        assert m[i] <= d + 1e-9 and d - m[i] < 0.05


def line_own():
    """Ownship along x at 10 m/s from x = 0 (t = 0) to x = 200 m (t = 20 s)."""
    return np.array([0.0, 10.0, 20.0]), np.array([[0.0, 0, 0], [100, 0, 0], [200, 0, 0]])


def test_touching_is_clear_and_grazing_is_a_conflict():
    t, p = line_own()
    tr = IntruderTracks.from_intruders([Intruder("hover", [0.0, 30.0], [[50, 8, 6], [50, 8, 6]])])
    assert first_conflict(t, p, tr, 10.0) is None                 # distance exactly 10 m at t = 5 s
    c = first_conflict(t, p, tr, 10.0 + 1e-6)
    assert c is not None and abs(c.t_s - 5.0) < 1e-3 and abs(c.distance_m - 10.0) < 1e-9
    assert abs(c.t_cpa_s - 5.0) < 1e-9
    np.testing.assert_allclose(c.own_velocity_mps, [10, 0, 0])
    np.testing.assert_allclose(c.intruder_velocity_mps, [0, 0, 0])
    assert min_separation(t, p, tr)[0] == 10.0


def test_crossing_closed_form():
    """Perpendicular crossing: relative motion (10, -5, 0) t + (-50, 25, 0): exact roots."""
    t, p = line_own()
    tr = IntruderTracks.from_intruders([Intruder("x", [0.0, 20.0], [[50, 25, 0], [50, -75, 0]], 1.0)])
    c = first_conflict(t, p, tr, 20.0)
    # |(-50 + 10 t, 25 - 5 t)|^2 = 400  ->  125 t^2 - 1250 t + 2725 = 0
    t1 = (1250 - np.sqrt(1250**2 - 4 * 125 * 2725)) / 250
    assert abs(c.t_s - t1) < 1e-9
    assert abs(c.t_cpa_s - 5.0) < 1e-9 and abs(c.distance_m) < 1e-9
    np.testing.assert_allclose(c.intruder_velocity_mps, [0, -5, 0])


def test_already_in_conflict_and_t_from():
    t, p = line_own()
    tr = IntruderTracks.from_intruders([Intruder("near", [0.0, 30.0], [[0, 5, 0], [300, 5, 0]])])
    c = first_conflict(t, p, tr, 10.0)
    assert c.t_s == 0.0 and abs(c.distance_m - 5.0) < 1e-12
    c = first_conflict(t, p, tr, 10.0, t_from_s=12.5)
    assert c.t_s == 12.5
    assert first_conflict(t, p, tr, 5.0) is None                   # constant 5 m: touching only


def test_intruder_existing_only_partly():
    t, p = line_own()
    # would sit on the ownship's path for the whole flight, but exists only on [12, 14] s
    tr = IntruderTracks.from_intruders([Intruder("late", [12.0, 14.0], [[120, 0, 0], [140, 0, 0]])])
    c = first_conflict(t, p, tr, 10.0)
    assert c.t_s == 12.0 and c.distance_m == 0.0
    assert first_conflict(t, p, tr, 10.0, t_from_s=14.0 + 1e-9) is None
    # a single waypoint exists at one instant only
    tr = IntruderTracks.from_intruders([Intruder("blip", [7.0], [[70, 3, 0]])])
    c = first_conflict(t, p, tr, 10.0)
    assert c.t_s == 7.0 and abs(c.distance_m - 3.0) < 1e-12
    assert first_conflict(t, p, tr, 2.0) is None
    # gone before the plan starts
    tr = IntruderTracks.from_intruders([Intruder("gone", [-10.0, -1.0], [[0, 0, 0], [0, 0, 0]])])
    assert first_conflict(t, p, tr, 10.0) is None and min_separation(t, p, tr)[0] == np.inf


def test_earliest_of_several_intruders():
    t, p = line_own()
    intr = [Intruder("b", [0.0, 30.0], [[150, 0, 0], [150, 0, 0]]),
            Intruder("a", [0.0, 30.0], [[80, 0, 0], [80, 0, 0]])]
    c = first_conflict(t, p, IntruderTracks.from_intruders(intr), np.array([5.0, 5.0]))
    assert c.id == "a" and abs(c.t_s - 7.5) < 1e-9


def brute_dtc_first(t, p, intr, sep, dtc, step=0.01):
    """First own sample time at which some intruder sample within [t - dtc, t + dtc] is closer."""
    x = np.arange(t[0], t[-1], step)
    P = interp(t, p, x)
    first = np.inf
    for i, it in enumerate(intr):
        tau = np.r_[np.arange(it.times_s[0], it.times_s[-1], step), it.times_s[-1]]
        Q = interp(it.times_s, it.xyz_m, tau)
        for a in range(0, x.size, 500):
            d = np.linalg.norm(P[a:a + 500, None, :] - Q[None, :, :], axis=2)
            ok = (np.abs(x[a:a + 500, None] - tau[None, :]) <= dtc) & (d < sep[i])
            hit = np.nonzero(ok.any(axis=1))[0]
            if hit.size:
                first = min(first, x[a + hit[0]])
                break
    return first


def test_time_margin_never_misses():
    hits = 0
    for seed in range(6):
        t, p, intr, sep = random_scene(100 + seed, n_intruders=5)
        t, p, sep = t[:6], p[:6], 2.0 * sep
        tracks = IntruderTracks.from_intruders(intr)
        for dtc in (0.5, 3.0):
            tb = brute_dtc_first(t, p, intr, sep, dtc)
            c = first_conflict(t, p, tracks, sep, dt_c_s=dtc)
            if np.isfinite(tb):
                hits += 1
                assert c is not None and c.t_s <= tb + 1e-9
                assert tb - c.t_s < 0.1       # the swept lower bound is not far off here
            exact = first_conflict(t, p, tracks, sep)
            if exact is not None:
                assert c is not None and c.t_s <= exact.t_s + 1e-9
                assert c.distance_m <= exact.distance_m + 1e-9
    assert hits >= 4         # not vacuous


def test_time_margin_tends_to_exact():
    t, p = line_own()
    tr = IntruderTracks.from_intruders([Intruder("x", [0.0, 20.0], [[50, 25, 0], [50, -75, 0]], 1.0)])
    exact = first_conflict(t, p, tr, 20.0)
    c = first_conflict(t, p, tr, 20.0, dt_c_s=1e-9)
    assert exact.t_s - 0.02 <= c.t_s <= exact.t_s
    # a static intruder: the window changes nothing, the estimate is within one leaf
    tr = IntruderTracks.from_intruders([Intruder("h", [0.0, 30.0], [[50, 8, 0], [50, 8, 0]])])
    exact = first_conflict(t, p, tr, 10.0)
    c = first_conflict(t, p, tr, 10.0, dt_c_s=5.0)
    assert exact.t_s - 0.051 <= c.t_s <= exact.t_s and abs(c.distance_m - 8.0) < 1e-9   # leaf 0.05 s
    # intruder 1 s ahead on the same line at the same speed, 10 m apart, existing from t = 0:
    # with a 2 s margin it may be at x = 10 m (tau = 0) while the ownship is at 10 t -> the
    # distance drops below 5 m at t = 0.5 s and reaches 0 at t = 1 s
    tr = IntruderTracks.from_intruders([Intruder("lead", [0.0, 20.0], [[10, 0, 0], [210, 0, 0]])])
    assert first_conflict(t, p, tr, 5.0) is None
    c = first_conflict(t, p, tr, 5.0, dt_c_s=2.0)
    assert 0.5 - 0.021 <= c.t_s <= 0.5 and c.distance_m == 0.0            # leaf 0.02 s
    assert abs(c.t_cpa_s - 1.0) <= 0.021


def test_input_errors():
    t, p = line_own()
    tr = IntruderTracks.from_intruders([Intruder("h", [0.0, 30.0], [[50, 8, 0], [50, 8, 0]])])
    with pytest.raises(InputError, match="increase strictly"):
        first_conflict([0.0, 10.0, 10.0], p, tr, 5.0)
    with pytest.raises(InputError, match=r"xyz_m \(n, 3\)"):
        first_conflict(t, p[:, :2], tr, 5.0)
    with pytest.raises(InputError, match="one per aircraft"):
        first_conflict(t, p, tr, [5.0, 6.0])
    with pytest.raises(InputError, match="dt_c_s"):
        first_conflict(t, p, tr, 5.0, dt_c_s=-1.0)
    with pytest.raises(InputError, match="IntruderTracks"):
        first_conflict(t, p, [Intruder("h", [0.0], [[0, 0, 0]])], 5.0)
    assert first_conflict(t, p, IntruderTracks.from_intruders([]), 5.0) is None


# ------------------------------------------------------------------ pairwise (state-based)


def random_picture(seed, n=400, size=3000.0):
    rng = np.random.default_rng(seed)
    x = np.c_[rng.uniform(0, size, (n, 2)), rng.uniform(30, 150, n)]
    v = np.c_[rng.normal(0, 12, (n, 2)), rng.normal(0, 1, n)]
    # edge cases: parallel pairs (same velocity), zero relative velocity in conflict, a
    # head-on pair, a pair already in conflict, a vertical-only crossing, an aircraft at rest
    v[1] = v[0]
    x[3], v[3] = x[2] + [20, 0, 0], v[2]
    x[5], v[4], v[5] = x[4] + [400, 0, 0], [10, 0, 0], [-10, 0, 0]
    x[7], v[7] = x[6] + [5, 5, 2], v[6] + [1, 0, 0]
    x[9], v[9] = x[8] + [0, 0, 60], v[8] + [0, 0, -3]
    v[10] = 0.0
    return x, v


def assert_same(a, b):
    assert len(a[0]) == len(b[0])
    for u, w in zip(a, b, strict=True):
        np.testing.assert_array_equal(u, w)


@pytest.mark.parametrize("seed", range(5))
def test_pairwise_fast_equals_numpy_baseline(seed):
    x, v = random_picture(seed)
    rng = np.random.default_rng(seed)
    for sep, vsep, look in ((50.0, None, 60.0), (rng.uniform(20, 80, len(x)), 15.0, 120.0), (30.0, 10.0, 5.0)):
        base = pairwise_conflicts_numpy(x, v, sep, look, vsep, block=97)
        fast = pairwise_conflicts(x, v, sep, look, vsep)
        assert_same(base, fast)
        assert len(base[0]) > 0
    pairs = set(zip(*pairwise_conflicts(x, v, 50.0, 60.0)[:2], strict=True))
    assert {(2, 3), (4, 5), (6, 7), (8, 9)} <= pairs


def test_pairwise_against_sampling():
    """Reported iff the cylinder (R horizontal, H vertical) is entered at some t in [0, T]."""
    x, v = random_picture(7, n=150, size=1500.0)
    R, H, T = 60.0, 20.0, 40.0
    i, j, tcpa, dcpa, tin = pairwise_conflicts(x, v, R, T, H)
    got = set(zip(i.tolist(), j.tolist(), strict=True))
    s = np.linspace(0, T, 4001)
    n = len(x)
    for a in range(n):
        rel = (x[a + 1:] - x[a])[:, None, :] + (v[a + 1:] - v[a])[:, None, :] * s[None, :, None]
        m = np.maximum(np.hypot(rel[..., 0], rel[..., 1]) / R, np.abs(rel[..., 2]) / H).min(axis=1)
        for k, mk in enumerate(m):
            if abs(mk - 1) < 0.01:
                continue
            assert ((a, a + 1 + k) in got) == (mk < 1), (a, a + 1 + k, mk)
    # t_cpa / d_cpa: horizontal closest approach of the relative motion
    moving = ((v[j, :2] - v[i, :2]) ** 2).sum(1) > 1e-6        # BlueSky limits |dv|^2 below
    assert 0 < moving.sum() < moving.size
    rx, rv = x[j, :2] - x[i, :2], v[j, :2] - v[i, :2]
    tc = -(rx * rv).sum(1)[moving] / (rv * rv).sum(1)[moving]
    np.testing.assert_allclose(tcpa[moving], tc, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(dcpa[moving], np.linalg.norm(rx[moving] + rv[moving] * tc[:, None], axis=1),
                               atol=1e-4)
    np.testing.assert_allclose(dcpa[~moving], np.linalg.norm(rx[~moving], axis=1), atol=1e-6)
    assert np.all(tin < T)


def test_pairwise_degenerate():
    x = np.array([[0.0, 0, 100], [30, 0, 100], [5000, 0, 100]])
    v = np.zeros((3, 3))
    assert_same(pairwise_conflicts_numpy(x, v, 50.0, 60.0), pairwise_conflicts(x, v, 50.0, 60.0))
    i, j, *_ = pairwise_conflicts(x, v, 50.0, 60.0)
    assert i.tolist() == [0] and j.tolist() == [1]
    for k in (0, 1):
        assert all(len(a) == 0 for a in pairwise_conflicts(x[:k], v[:k], 50.0, 60.0))
    with pytest.raises(InputError, match="lookahead_s"):
        pairwise_conflicts(x, v, 50.0, 0.0)
    with pytest.raises(InputError, match="same shape"):
        pairwise_conflicts(x, v[:2], 50.0, 10.0)


@pytest.mark.parametrize(("size", "look"), [(20000.0, 5.0), (500.0, 300.0)])     # grid / dense paths
def test_pairwise_near_zero_relative_velocity(size, look):
    """Pairs whose relative speed is below BlueSky's 1e-3 m/s limit, near the separation:
    the fast version keeps every pair the baseline's limited formula reports."""
    rng = np.random.default_rng(3)
    n = 300
    x = np.c_[rng.uniform(0, size, (n, 2)), rng.uniform(30, 60, n)]
    v = np.c_[rng.normal(0, 10, (n, 2)), rng.normal(0, 0.5, n)]
    for k in range(0, 60, 2):        # followers 49-51 m (R = 50 m) behind with tiny dv
        x[k + 1] = x[k] + [rng.uniform(49, 51), 0, rng.uniform(-5, 5)]
        v[k + 1] = v[k] + rng.normal(0, 3e-4, 3) * [1, 1, 0]
    base = pairwise_conflicts_numpy(x, v, 50.0, look, 15.0)
    fast = pairwise_conflicts(x, v, 50.0, look, 15.0)
    assert_same(base, fast)
    assert sum((a, a + 1) in set(zip(base[0].tolist(), base[1].tolist(), strict=True)) for a in range(0, 60, 2)) > 5


def test_intruder_tracks_validation():
    tr = IntruderTracks.from_intruders([Intruder("a", [0.0, 1.0], [[0, 0, 0], [1, 0, 0]]),
                                        {"id": "b", "waypoints": [[2.0, 0, 0, 0]], "radius_m": 1.5}])
    assert tr.ids == ("a", "b") and tr.offsets.tolist() == [0, 2, 3] and tr.radius_m.tolist() == [0.0, 1.5]
    with pytest.raises(InputError, match="increase strictly"):
        IntruderTracks([0.0, 0.0, 2.0], np.zeros((3, 3)), [0, 2, 3], [0.0, 0.0], ("a", "b"))
    with pytest.raises(InputError, match="offsets"):
        IntruderTracks([0.0, 1.0, 2.0], np.zeros((3, 3)), [0, 3, 3], [0.0, 0.0], ("a", "b"))
    with pytest.raises(InputError, match="from_intruders"):
        IntruderTracks([0.0, 1.0], np.zeros((2, 3)), [0, 2], [0.0, 0.0], ("a",))
