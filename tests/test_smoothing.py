"""Minimum-snap smoothing: interpolation, continuity, rest ends, and a direct KKT QP oracle."""

from __future__ import annotations

import numpy as np
import numpy.polynomial.polynomial as P
import pytest

from skyroute.pipeline.errors import InputError, PlanningError
from skyroute.stages.smoothing import insert_midpoints_where, min_snap, smooth_with_clearance


def _end_derivs(traj, k, r):
    """Derivative r of segment k at its start and at its end, from its own polynomial."""
    c = traj.coef[k]                                      # (8, 3)
    dc = P.polyder(c, r, axis=0) if r else c
    T = traj.segment_times_s[k]
    return P.polyval(0.0, dc), P.polyval(T, dc)


@pytest.fixture(scope="module")
def chain():
    rng = np.random.default_rng(3)
    w = np.cumsum(rng.uniform(-40, 40, (7, 3)), axis=0)
    t = rng.uniform(2.0, 9.0, 6)
    return w, t, min_snap(w, t)


def test_passes_through_waypoints(chain):
    w, t, traj = chain
    np.testing.assert_allclose(traj.sample(traj.knots_s), w, atol=1e-6)
    assert traj.duration_s == pytest.approx(t.sum())


def test_rest_at_both_ends(chain):
    _, _, traj = chain
    for r in (1, 2, 3):
        np.testing.assert_allclose(traj.derivative([0.0, traj.duration_s], r), 0.0, atol=1e-8)


def test_continuity_up_to_sixth_derivative(chain):
    _, _, traj = chain
    for k in range(len(traj.segment_times_s) - 1):
        for r in range(0, 7):
            left = _end_derivs(traj, k, r)[1]
            right = _end_derivs(traj, k + 1, r)[0]
            scale = 1.0 + np.abs(left).max()
            np.testing.assert_allclose(left, right, atol=1e-7 * scale, err_msg=f"joint {k} derivative {r}")
    # the 7th derivative is NOT continuous (the waypoint constraint acts there): the test can fail
    jumps = [np.abs(_end_derivs(traj, k, 7)[1] - _end_derivs(traj, k + 1, 7)[0]).max() for k in range(5)]
    assert max(jumps) > 1e-6


def test_public_derivatives_match_polynomial(chain):
    _, _, traj = chain
    tq = np.linspace(0.3, traj.duration_s - 0.3, 17)
    h = 1e-4
    fd_v = (traj.sample(tq + h) - traj.sample(tq - h)) / (2 * h)
    fd_a = (traj.velocity(tq + h) - traj.velocity(tq - h)) / (2 * h)
    np.testing.assert_allclose(traj.velocity(tq), fd_v, atol=1e-5)
    np.testing.assert_allclose(traj.acceleration(tq), fd_a, atol=1e-5)


def test_straight_chain_gives_straight_curve():
    u = np.array([3.0, -2.0, 1.0]) / np.sqrt(14)
    s = np.array([0.0, 7.0, 30.0, 31.0, 80.0])
    w = np.array([10.0, 20.0, 30.0]) + s[:, None] * u
    traj = min_snap(w, [1.0, 4.0, 0.5, 6.0])
    x = traj.sample(np.linspace(0, traj.duration_s, 501)) - w[0]
    off_line = x - (x @ u)[:, None] * u
    assert np.abs(off_line).max() < 1e-9


def _kkt_min_snap(w, t):
    """Direct equality-constrained QP in the raw coefficients, solved through its KKT system."""
    nseg = len(t)
    n = 8 * nseg
    Q = np.zeros((n, n))
    for k, T in enumerate(t):
        for i in range(8):
            for j in range(8):
                prod = P.polymul(P.polyder(np.eye(8)[i], 4), P.polyder(np.eye(8)[j], 4))
                Q[8 * k + i, 8 * k + j] = P.polyval(T, P.polyint(prod)) if prod.size else 0.0

    def row(k, r, tau):
        a = np.zeros(n)
        for i in range(8):
            d = P.polyder(np.eye(8)[i], r)
            a[8 * k + i] = P.polyval(tau, d) if d.size else 0.0
        return a

    rows, rhs = [], []
    for k, T in enumerate(t):
        rows += [row(k, 0, 0.0), row(k, 0, T)]
        rhs += [w[k], w[k + 1]]
    for k in range(nseg - 1):
        for r in (1, 2, 3):
            rows.append(row(k, r, t[k]) - row(k + 1, r, 0.0))
            rhs.append(np.zeros(3))
    for r in (1, 2, 3):
        rows += [row(0, r, 0.0), row(nseg - 1, r, t[-1])]
        rhs += [np.zeros(3), np.zeros(3)]
    A, b = np.array(rows), np.array(rhs)
    m = A.shape[0]
    K = np.block([[2 * Q, A.T], [A, np.zeros((m, m))]])
    sol = np.linalg.solve(K, np.vstack([np.zeros((n, 3)), b]))
    c = sol[:n]
    cost = float(np.einsum("ia,ij,ja->", c, Q, c))
    return c.reshape(nseg, 8, 3), cost


def test_closed_form_equals_kkt_qp():
    rng = np.random.default_rng(11)
    w = rng.uniform(-20, 20, (5, 3))
    t = rng.uniform(0.8, 2.5, 4)
    traj = min_snap(w, t)
    coef, cost = _kkt_min_snap(w, t)
    assert traj.snap_cost() == pytest.approx(cost, rel=1e-6)
    tq = np.linspace(0, t.sum(), 97)
    knots = np.concatenate([[0], np.cumsum(t)])
    k = np.clip(np.searchsorted(knots, tq, side="right") - 1, 0, 3)
    ref = np.array([P.polyval(tt - knots[kk], coef[kk]) for tt, kk in zip(tq, k, strict=True)])
    np.testing.assert_allclose(traj.sample(tq), ref, atol=1e-6)


def test_insert_midpoints_where():
    w = np.array([[0.0, 0, 0], [10, 0, 0], [10, 20, 0], [0, 20, 4]])
    t = np.array([1.0, 2.0, 4.0])
    nw, nt = insert_midpoints_where(w, t, [2, 0])
    np.testing.assert_allclose(nw, [[0, 0, 0], [5, 0, 0], [10, 0, 0], [10, 20, 0], [5, 20, 2], [0, 20, 4]])
    np.testing.assert_allclose(nt, [0.5, 0.5, 2.0, 2.0, 2.0])
    with pytest.raises(InputError, match="bad_segment_indices"):
        insert_midpoints_where(w, t, [3])


def _dist_to_chain(pts, w):
    d = np.full(len(pts), np.inf)
    for a, b in zip(w[:-1], w[1:], strict=True):
        ab = b - a
        s = np.clip(((pts - a) @ ab) / (ab @ ab), 0, 1)
        d = np.minimum(d, np.linalg.norm(pts - (a + s[:, None] * ab), axis=1))
    return d


def test_smooth_with_clearance_corridor():
    w = np.array([[0.0, 0, 30], [60, 0, 30], [60, 60, 40], [0, 60, 40]])
    t = np.array([6.0, 6.0, 6.0])

    def is_clear(p):
        return _dist_to_chain(p, w) <= 1.0                 # stay in a 1 m corridor

    raw = min_snap(w, t)
    pts, _ = raw.segment_samples(0.5)
    assert _dist_to_chain(pts, w).max() > 1.0             # plain min-snap cuts the corners
    calls = []
    traj = smooth_with_clearance(w, t, lambda p: calls.append(p.shape) or is_clear(p), max_iter=10)
    pts, _ = traj.segment_samples(0.25)
    assert _dist_to_chain(pts, w).max() <= 1.0 + 1e-3
    assert traj.duration_s == pytest.approx(18.0)
    assert len(traj.waypoints) > 4 and all(s[1] == 3 for s in calls)
    for p in w:                                            # original waypoints kept
        assert np.min(np.linalg.norm(traj.waypoints - p, axis=1)) < 1e-12
    with pytest.raises(PlanningError, match="still violates clearance"):
        smooth_with_clearance(w, t, is_clear, max_iter=0)


def test_bad_input():
    with pytest.raises(InputError, match="n-1 = 2"):
        min_snap(np.zeros((3, 3)), [1.0])
    with pytest.raises(InputError, match="> 0"):
        min_snap(np.zeros((3, 3)), [1.0, 0.0])
    with pytest.raises(InputError, match=r"shape \(n >= 2, 3\)"):
        min_snap(np.zeros((3, 2)), [1.0, 1.0])


# ------------------------------------------------------------------ corner trajectory (STEP III)
from skyroute.stages.smoothing import (  # noqa: E402
    KinematicLimits,
    _airspeed_cap,
    _cone_ok,
    corner_trajectory,
)

LIM = KinematicLimits(max_flight_path_angle_deg=15.0, max_airspeed_mps=23.0, max_climb_rate_mps=6.0,
                      max_descent_rate_mps=5.0, max_acceleration_mps2=3.0)
TAN15 = np.tan(np.radians(15.0))


def _dir(heading_deg, fpa_deg):
    h, a = np.radians(heading_deg), np.radians(fpa_deg)
    return np.array([np.cos(a) * np.cos(h), np.cos(a) * np.sin(h), np.sin(a)])


def _dense_limits_hold(traj, wind, lim=LIM, n=200001):
    """Brute-force check of every limit on a dense time grid, from the trajectory's own
    position samples (finite differences) and its analytic derivatives."""
    t = np.linspace(0.0, traj.duration_s, n)
    p = traj.sample(t)
    v = traj.velocity(t)
    a = traj.acceleration(t)
    # the analytic velocity is the derivative of the positions (central differences)
    fd = (p[2:] - p[:-2]) / (t[2:] - t[:-2])[:, None]
    assert np.max(np.linalg.norm(fd - v[1:-1], axis=1)) < 1e-3
    sp = np.linalg.norm(v, axis=1)
    moving = sp > 1e-9
    h = np.hypot(v[:, 0], v[:, 1])
    assert np.all(np.abs(v[moving, 2]) <= TAN15 * h[moving] + 1e-9)              # tangent angle
    assert np.all(v[:, 2] <= lim.max_climb_rate_mps + 1e-9)
    assert np.all(v[:, 2] >= -lim.max_descent_rate_mps - 1e-9)
    assert np.all(np.linalg.norm(a, axis=1) <= lim.max_acceleration_mps2 + 1e-9)
    assert np.all(np.linalg.norm(v - wind, axis=1) <= lim.max_airspeed_mps + 1e-9)
    # chords of a coarse sampling (every 0.5 s + boundaries): angle with horizontal >= 2 m
    ts = traj.sample_times(0.5)
    ps = traj.sample(ts)
    d = np.diff(ps, axis=0)
    hh = np.hypot(d[:, 0], d[:, 1])
    assert np.all(np.abs(d[:, 2]) <= TAN15 * hh + 1e-9)
    return t, p, v


def test_corner_trajectory_hairpin_climb_descend_within_every_limit():
    """A 138 deg hairpin where a 15 deg climb turns into a 15 deg descent (the w_l = 0 chains of
    issue 9): no tolerance anywhere; ends at rest on the chain's end points."""
    w = np.array([[0.0, 0.0, 50.0]])
    w = np.vstack([w, w[-1] + 80 * _dir(0, 15), ])
    w = np.vstack([w, w[-1] + 60 * _dir(138, -15), w[-1] + 60 * _dir(138, -15) + 90 * _dir(60, 0)])
    wind = np.array([4.0, -2.0, 0.0])
    traj = corner_trajectory(w, 10.0, LIM, winds=wind[None, :])
    t, p, v = _dense_limits_hold(traj, wind)
    np.testing.assert_allclose(p[0], w[0], atol=1e-9)
    np.testing.assert_allclose(p[-1], w[-1], atol=1e-6)
    assert np.linalg.norm(v[0]) == 0 and np.linalg.norm(v[-1]) < 1e-9
    # climb -> descent: the tangents' combinations pass through level flight, the arc is in the cone
    assert traj.corner_kind == ("arc", "arc")
    # every point lies on the chain or inside the triangle of a rounded corner: distance to the
    # chain's polyline is at most the cut-back of that corner (half the shorter leg)
    seg_d = []
    for a, b in zip(w[:-1], w[1:], strict=True):
        ab = b - a
        s = np.clip(((p - a) @ ab) / (ab @ ab), 0, 1)
        seg_d.append(np.linalg.norm(a + s[:, None] * ab - p, axis=1))
    assert np.min(seg_d, axis=0).max() <= 0.5 * 60 + 1e-9
    # climb -> climb through a hairpin: any rounding would be steeper than 15 deg, so it stops
    w2 = np.vstack([w[:2], w[1] + 60 * _dir(138, 14.9), w[1] + 60 * _dir(138, 14.9) + 50 * _dir(60, 0)])
    traj = corner_trajectory(w2, 10.0, LIM, winds=wind[None, :])
    assert traj.corner_kind[0] == "stop" and "flight-path angle" in traj.corner_reason[0]
    _dense_limits_hold(traj, wind)


def test_corner_trajectory_straight_leg_is_time_optimal_closed_form():
    """One level leg from rest to rest, cruise 10 m/s: T = L / v + v / a (trapezoid)."""
    w = np.array([[0.0, 0.0, 30.0], [500.0, 0.0, 30.0]])
    traj = corner_trajectory(w, 10.0, LIM)
    assert traj.duration_s == pytest.approx(500 / 10 + 10 / 3.0, rel=1e-12)
    # a leg too short to reach cruise: triangle, T = 2 sqrt(L / a)
    traj = corner_trajectory(np.array([[0.0, 0, 0], [12.0, 0, 0]]), 10.0, LIM)
    assert traj.duration_s == pytest.approx(2 * np.sqrt(12 / 3.0), rel=1e-12)
    # climbing at 14 deg: the vertical speed caps the cruise (6 / sin 14 deg = 24.8 > 23: airspeed)
    w = np.array([[0.0, 0, 0], [1000 * np.cos(np.radians(14)), 0, 1000 * np.sin(np.radians(14))]])
    traj = corner_trajectory(w, 30.0, LIM)
    assert np.max(np.linalg.norm(traj.velocity(np.linspace(0, traj.duration_s, 999)), axis=1)) == pytest.approx(23.0)
    traj = corner_trajectory(w, 30.0, LIM, winds=np.array([[5.0, 0, 0]]))     # tail wind: 6 m/s climb binds
    vz = traj.velocity(np.linspace(0, traj.duration_s, 999))[:, 2]
    assert vz.max() == pytest.approx(6.0)


def test_corner_trajectory_flat_turn_is_an_arc_at_the_lateral_limit():
    w = np.array([[0.0, 0, 40], [100.0, 0, 40], [100.0, 100.0, 40]])
    traj = corner_trajectory(w, 20.0, LIM)
    assert traj.corner_kind == ("arc",)
    R = 50.0 / np.tan(np.radians(45))                       # cut-back 50 m, 90 deg turn
    arc = traj.kind == 1
    assert traj.radius_m[arc][0] == pytest.approx(R)
    assert traj.v0[arc][0] == pytest.approx(np.sqrt(3.0 * R))  # v^2 / R = a_max
    _dense_limits_hold(traj, np.zeros(3))
    # no clearance under the corner: the vehicle stops there instead
    traj = corner_trajectory(w, 20.0, LIM, fillet_ok=lambda a, p, b: False)
    assert traj.corner_kind == ("stop",)
    assert np.linalg.norm(traj.velocity(traj.piece_t_s[1])) == 0.0
    _dense_limits_hold(traj, np.zeros(3))


def test_cone_test_against_dense_sampling():
    rng = np.random.default_rng(7)
    agree = 0
    for _ in range(400):
        u1 = _dir(rng.uniform(0, 360), rng.uniform(-15, 15))
        u2 = _dir(rng.uniform(0, 360), rng.uniform(-15, 15))
        s = np.linspace(0, 1, 20001)[:, None]
        c = (1 - s) * u1 + s * u2
        brute = np.all(np.abs(c[:, 2]) <= TAN15 * np.hypot(c[:, 0], c[:, 1]) + 1e-12)
        agree += brute == _cone_ok(u1, u2, TAN15)
    assert agree == 400


def test_airspeed_cap_against_bisection():
    rng = np.random.default_rng(11)
    for _ in range(200):
        u = _dir(rng.uniform(0, 360), rng.uniform(-15, 15))
        winds = rng.uniform(-8, 8, (4, 3))
        cap = _airspeed_cap(u, winds, 23.0)
        lo, hi = 0.0, 100.0
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if np.all(np.linalg.norm(mid * u - winds, axis=1) <= 23.0) else (lo, mid)
        assert cap == pytest.approx(lo, abs=1e-9)


def test_corner_trajectory_bad_input():
    with pytest.raises(InputError, match="waypoints"):
        corner_trajectory(np.zeros((1, 3)), 10.0, LIM)
    with pytest.raises(InputError, match="leg_speed_mps"):
        corner_trajectory(np.array([[0.0, 0, 0], [10.0, 0, 0]]), 0.0, LIM)
    with pytest.raises(PlanningError, match="wind exceeds the airspeed"):
        corner_trajectory(np.array([[0.0, 0, 0], [10.0, 0, 0]]), 10.0, LIM, winds=np.array([[-30.0, 0, 0]]))
