"""Dynamic zone partitioning (seed 004 III-A): hand-worked intruder sets whose bit length r and
dense zones are derived in the comments, the prediction against closed forms, the obstacle
mask against a brute-force overlap test."""

from __future__ import annotations

import math

import numpy as np
import pytest

from skyroute.stages.base import InputError
from skyroute.stages.tactical.zones import (
    ZoneTracker,
    dense_mask,
    partition,
    predict_intruders,
    zone_bounds,
    zone_of,
)

WS = (0.0, 100.0, 0.0, 100.0)


def test_zone_bounds_follow_the_seed_fig7_example():
    # 01101 on [0, 32]^2: X bits 0,1,1 -> [0,16] -> [8,16] -> [12,16]; Y bits 1,0 -> [16,32] -> [16,24]
    assert zone_bounds("01101", (0, 32, 0, 32)) == (12.0, 16.0, 16.0, 24.0)
    assert zone_bounds("", WS) == WS
    # every point lies in the bounds of its own zone, for every r
    rng = np.random.default_rng(3)
    for xy in rng.uniform(0, 100, (50, 2)):
        for r in range(1, 8):
            x0, x1, y0, y1 = zone_bounds(zone_of(xy, r, WS), WS)
            assert x0 <= xy[0] <= x1 and y0 <= xy[1] <= y1
    with pytest.raises(InputError, match="0 and 1"):
        zone_bounds("012", WS)


def test_no_traffic_needs_one_bit():
    p = partition((10, 10), (90, 90), np.zeros((0, 3)), WS)
    assert p.ok and p.r == 1 and p.dense == () and list(p.counts) == [0, 0]


def test_two_intruders_in_the_east_half():
    # r = 1: zone '1' (x >= 50) holds both -> dense; own (10,10) and goal (20,90) in sparse '0'
    p = partition((10, 10), (20, 90), [(75, 75, 30), (80, 20, 40)], WS)
    assert p.ok and p.r == 1 and p.dense == ("1",) and list(p.counts) == [0, 2]
    (b,) = p.boxes
    assert (b.x_min_m, b.x_max_m, b.y_min_m, b.y_max_m) == (50.0, 100.0, 0.0, 100.0)


def test_own_zone_dense_until_r2():
    # r = 1: '0' holds own and both intruders -> own zone dense.  r = 2: 50 m squares; the pair is
    # in '01' (x < 50, y >= 50), own in '00', goal in '11', connection 00 - 10 - 11.
    p = partition((10, 10), (90, 90), [(10, 60), (20, 70)], WS)
    assert p.ok and p.r == 2 and p.dense == ("01",) and p.own_zone == "00" and p.goal_zone == "11"


def test_the_seed_sequence_own_dense_then_not_connected_then_ok():
    # pairs A (20,30),(22,40) and B (30,10),(40,20); own (10,10), goal (90,90)
    # r = 1, 2: own zone holds all four.  r = 3 (25 x 50 m): own zone [0,25]x[0,50] holds A.
    # r = 4 (25 m squares): own [0,25]^2 empty, but its two neighbours hold A and B: not connected.
    # r = 5 (12.5 x 25 m): A in [12.5,25]x[25,50] (dense, bits X 001 / Y 01 -> 00011), B split.
    A = [(20, 30), (22, 40)]
    B = [(30, 10), (40, 20)]
    p = partition((10, 10), (90, 90), A + B, WS)
    assert p.ok and p.r == 5 and p.dense == ("00011",)
    assert zone_bounds("00011", WS) == (12.5, 25.0, 25.0, 50.0)
    assert p.counts.sum() == 4 and p.counts[int("00011", 2)] == 2
    short = partition((10, 10), (90, 90), A + B, WS, r_max=4)
    assert not short.ok and "not connected" in short.reason and short.dense == ()


def test_goal_zone_condition_applies_only_near_the_goal():
    # own (10,10), goal (30,10), intruders (35,5), (45,20).  Near goal (threshold 50 m): r = 3, 4
    # put both intruders in the goal's zone; r = 5 (12.5 m columns) splits them: no dense zone.
    intr = [(35, 5), (45, 20)]
    near = partition((10, 10), (30, 10), intr, WS, goal_threshold_m=50.0)
    assert near.ok and near.r == 5 and near.dense == ()
    # far goal (threshold 10 m): r = 3, own zone [0,25]x[0,50] sparse and next to the (dense) goal
    # zone [25,50]x[0,50], which is left out of the definition
    far = partition((10, 10), (30, 10), intr, WS, goal_threshold_m=10.0)
    assert far.ok and far.r == 3 and far.dense == () and far.counts[int(far.goal_zone, 2)] == 2


def test_prediction_is_eq5_closed_form():
    p = np.array([[0.0, 0.0, 10.0], [5.0, -3.0, 20.0]])
    v = np.array([[2.0, 1.0, 0.0], [-1.0, 0.5, 0.2]])
    a = np.array([[0.1, 0.0, 0.0], [0.0, -0.2, 0.0]])
    T = 7.3
    pr = predict_intruders(p, v, T, a, dt_s=0.25, sigma_a_mps2=0.5)
    assert np.allclose(pr.xyz_m, p + v * T + 0.5 * a * T * T, atol=1e-9)
    assert np.allclose(pr.vel_mps, v + a * T, atol=1e-12)
    # white acceleration noise held per step: p_n = sum_k w_k dt^2 (n - k - 1/2)
    pr2 = predict_intruders(p, v, 8.0, dt_s=0.5, sigma_a_mps2=0.5)
    n, dt = 16, 0.5
    var = 0.25 * dt ** 4 * sum((m + 0.5) ** 2 for m in range(n))
    assert np.allclose(pr2.sigma_p_m, math.sqrt(var), rtol=1e-12)


def test_sigma_square_counts_an_intruder_in_every_zone_it_meets():
    # intruders at (48, 10) and (60, 10), own (90, 90), goal (70, 90).  k_sigma = 0: one per half
    # at r = 1, nothing dense.  With a +-3 m square the first also counts in '1' (x >= 50), own's
    # zone, which is then dense; r = 2: both in '10' (x >= 50, y < 50), own and goal in '11'.
    p0 = partition((90, 90), (70, 90), [(48, 10), (60, 10)], WS)
    assert p0.r == 1 and p0.dense == () and list(p0.counts) == [1, 1]
    p1 = partition((90, 90), (70, 90), [(48, 10), (60, 10)], WS, sigma_p_m=[1.0, 1.0], k_sigma=3.0)
    assert p1.r == 2 and p1.dense == ("10",) and list(p1.counts) == [1, 0, 2, 0]


def test_dense_mask_matches_brute_force_overlap():
    rng = np.random.default_rng(5)
    part = partition((10, 10), (90, 90), [(20, 30), (22, 40), (30, 10), (40, 20), (80, 60), (85, 62)], WS)
    assert part.ok and part.boxes
    res, x0, y1, shape = 3.0, -1.0, 101.5, (35, 35)
    m = dense_mask(part.boxes, x0, y1, res, shape)
    ref = np.zeros(shape, bool)
    for i in range(shape[0]):
        for j in range(shape[1]):
            cx0, cx1 = x0 + j * res, x0 + (j + 1) * res
            cy1, cy0 = y1 - i * res, y1 - (i + 1) * res
            ref[i, j] = any(cx0 <= b.x_max_m and cx1 >= b.x_min_m and cy0 <= b.y_max_m and cy1 >= b.y_min_m
                            for b in part.boxes)
    assert np.array_equal(m, ref)
    # points inside a box always fall in a masked cell
    for b in part.boxes:
        xs = rng.uniform(b.x_min_m, b.x_max_m, 200)
        ys = rng.uniform(b.y_min_m, b.y_max_m, 200)
        assert m[np.floor((y1 - ys) / res).astype(int), np.floor((xs - x0) / res).astype(int)].all()


def test_tracker_recomputes_only_when_the_definition_changes():
    tr = ZoneTracker(WS, period_s=10.0)
    xyz = np.array([[70.0, 20.0, 30.0], [80.0, 30.0, 30.0]])
    vel = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])      # the pair drifts north, staying in '1'
    p, ch = tr.update(0.0, (10, 10), (20, 90), xyz, vel)
    assert ch and p.dense == ("1",) and tr.recomputations == 1
    p, ch = tr.update(5.0, (10, 10), (20, 90), xyz, vel)          # inside the period: no prediction
    assert not ch and len(tr.history) == 1
    p, ch = tr.update(10.0, (10, 10), (20, 90), xyz + 10 * vel, vel)
    assert not ch and tr.recomputations == 1 and len(tr.history) == 2
    far = np.array([[70.0, 20.0, 30.0], [20.0, 30.0, 30.0]])    # now apart: no dense zone
    p, ch = tr.update(20.0, (10, 10), (20, 90), far, vel)
    assert ch and p.dense == () and tr.recomputations == 2
