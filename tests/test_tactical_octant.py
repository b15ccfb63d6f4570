"""Octant local collision avoidance (seed 004 III-D).

Oracles: octants of a path by dense sampling of the chord (not the plane-split), the seed's
counting claims on random lines, closest approaches by sampling the straight motions, and the
multi-UAV flights (the seed's two own UAVs plus an intruder, coplanar and not; BlueSky's
super conflict with 4 UAVs) by brute-force pairwise distances every 0.05 s."""

from __future__ import annotations

import math

import numpy as np
import pytest

from skyroute.stages.tactical.octant import (
    BACKWARD,
    FORWARD,
    avoid,
    body_frame,
    escape_direction,
    fly_fleet,
    octant_of,
    octants_crossed,
)


def _sampled_octants(q, d, radius, frame, coplanar):
    """Octants of 40001 samples of the future chord inside the ball (brute force)."""
    q = frame @ np.asarray(q, float)
    d = frame @ np.asarray(d, float)
    if coplanar:
        q[2] = d[2] = 0.0
    s = np.linspace(0.0, 4 * radius / max(np.linalg.norm(d), 1e-12), 40001)
    p = q[None] + s[:, None] * d[None]
    p = p[np.linalg.norm(p, axis=1) <= radius]
    if p.shape[0] == 0:
        return set()
    k = 1 + (p[:, 1] < 0) + 2 * (p[:, 0] >= 0) + 4 * ((p[:, 2] < 0) & (not coplanar))
    return set(k.tolist())


def test_octant_numbering_matches_the_seed_hemispheres():
    fr = body_frame((0.0, 1.0, 0.0))           # heading north: forward = +y, left = -x
    assert np.allclose(fr, [[0, 1, 0], [-1, 0, 0], [0, 0, 1]])
    assert octant_of((0.0, 5.0, 1.0), fr) in FORWARD and octant_of((0.0, -5.0, 1.0), fr) in BACKWARD
    assert octant_of((-1.0, 1.0, 1.0), fr) == 3 and octant_of((1.0, 1.0, 1.0), fr) == 4
    assert octant_of((-1.0, 1.0, -1.0), fr) == 7 and octant_of((1.0, -1.0, -1.0), fr) == 6
    for k in range(1, 9):                       # each escape direction lies in its own octant
        assert octant_of(escape_direction(k, fr), fr) == k
        assert octant_of(escape_direction(k, fr, max_elevation_deg=10.0), fr) == k
    for k in range(1, 5):
        e = escape_direction(k, fr, coplanar=True)
        assert abs(e[2]) < 1e-12 and octant_of(e + [0, 0, 1e-9], fr) == k


@pytest.mark.parametrize("coplanar", [False, True])
def test_octants_crossed_against_sampling_and_the_seed_counts(coplanar):
    rng = np.random.default_rng(11 + coplanar)
    fr = body_frame(rng.normal(size=3))
    n_max, fwd_free = 0, 0
    for _ in range(80):
        q = rng.normal(size=3) * 12.0
        d = rng.normal(size=3)
        got = set(octants_crossed(q, d, 10.0, fr, coplanar=coplanar))
        assert got == _sampled_octants(q, d, 10.0, fr, coplanar)
        n_max = max(n_max, len(got))
        # 3-D: one straight path never fills the forward hemisphere (the seed: |W| >= 1); in the
        # plane it may fill both forward quadrants, but leaves one quadrant vacant
        free = (1, 2, 3, 4) if coplanar else FORWARD
        fwd_free += any(k not in got for k in free)
    assert n_max <= (3 if coplanar else 4) and n_max >= 2 and fwd_free == 80
    assert octants_crossed((20.0, 0.0, 0.0), (0.0, 1.0, 0.0), 10.0, fr) == ()     # passes outside


def _min_margin(v_own, q, w, sep, horizon):
    t = np.linspace(0.0, horizon, 20001)
    return min(float(np.linalg.norm(qi[None] + t[:, None] * (wi - v_own)[None], axis=1).min()) - sep
               for qi, wi in zip(q, w, strict=True))


def test_head_on_intruder_escapes_into_a_forward_octant():
    own, v = np.zeros(3), np.array([2.0, 0.0, 0.0])
    q = np.array([[18.0, 0.3, 0.2]])
    w = np.array([[-2.0, 0.0, 0.0]])
    m = avoid(own, v, v, own + q, w, 5.0, speed_mps=2.0, periphery_m=20.0, horizon_s=10.0)
    assert m.kind == "octant" and m.octant in FORWARD
    assert set(m.occupied) == set(octants_crossed(q[0], w[0] - v, 20.0, body_frame(v)))
    assert _min_margin(m.velocity_mps, q, w, 5.0, 10.0) >= -1e-6
    assert _min_margin(v, q, w, 5.0, 10.0) < 0          # keeping the track would have lost it
    m2 = avoid(own, v, v, own + q, w, 5.0, speed_mps=2.0, periphery_m=20.0, horizon_s=10.0, coplanar=True)
    assert m2.kind == "octant" and m2.octant in (3, 4) and abs(m2.velocity_mps[2]) < 1e-12
    far = avoid(own, v, v, own + 5 * q, w, 5.0, speed_mps=2.0, periphery_m=20.0, horizon_s=10.0)
    assert far.kind == "track"                           # not sensed yet


def test_all_octants_occupied_uses_a_pocket_or_holds():
    # a hovering UAS, eight threats on the octant diagonals closing in on it: every octant is
    # occupied, holding loses separation; a pocket along an axis is clear of every diagonal
    diag = np.array([[sf, sl, su] for sf in (1, -1) for sl in (1, -1) for su in (1, -1)], float) / math.sqrt(3)
    q = 15.0 * diag
    w = -2.0 * diag
    m = avoid(np.zeros(3), np.zeros(3), np.zeros(3), q, w, 3.0, speed_mps=1.0, periphery_m=20.0, horizon_s=12.0)
    assert m.occupied == tuple(range(1, 9)) and m.kind == "pocket"
    assert _min_margin(np.zeros(3), q, w, 3.0, 12.0) < 0
    assert m.min_cpa_m >= 0 and _min_margin(m.velocity_mps, q, w, 3.0, 12.0) >= -1e-6
    assert abs(m.min_cpa_m - _min_margin(m.velocity_mps, q, w, 3.0, 12.0)) < 1e-3


def _brute_min_sep(res, sep_own, sep_intr):
    """Minimum over pairs of (distance - separation) every 0.05 s, each UAV until it arrives."""
    t = np.arange(0.0, res.t_s[-1], 0.05)
    n = res.xyz_m.shape[1]
    X = np.stack([np.column_stack([np.interp(t, res.t_s, res.xyz_m[:, i, k]) for k in range(3)]) for i in range(n)])
    live = np.array([t <= res.arrival_s[i] for i in range(n)])
    worst = math.inf
    for i in range(n):
        for j in range(i + 1, n):
            m = live[i] & live[j]
            if m.any():
                worst = min(worst, float(np.linalg.norm(X[i, m] - X[j, m], axis=1).min()) - sep_own)
        for j in range(res.intruder_xyz_m.shape[1]):
            Q = np.column_stack([np.interp(t, res.t_s, res.intruder_xyz_m[:, j, k]) for k in range(3)])
            worst = min(worst, float(np.linalg.norm(X[i, live[i]] - Q[live[i]], axis=1).min()) - sep_intr)
    return worst


@pytest.mark.parametrize("coplanar", [True, False])
def test_seed_two_own_uavs_and_an_intruder(coplanar):
    # seed IV-D: r_p = 2.5 m, speeds < 0.5 m/s; UAS-1 and UAS-2 head-on, the intruder crossing
    z2, zi, vz = (10.0, 10.0, 0.0) if coplanar else (12.0, 14.0, -0.1)
    S = np.array([[-12.0, 0.0, 10.0], [12.0, 0.5, z2]])
    G = np.array([[12.0, 0.0, 10.0], [-12.0, 0.5, z2]])
    res = fly_fleet(S, G, speed_mps=0.45, radius_m=0.5, margin_m=1.5, periphery_m=6.0, horizon_s=8.0, dt_s=0.1,
                    t_max_s=400.0, intruder_xyz=[[0.5, -12.0, zi]], intruder_vel_mps=[[0.0, 0.4, vz]],
                    intruder_radius_m=0.5, coplanar=coplanar)
    assert np.all(np.isfinite(res.arrival_s))
    assert _brute_min_sep(res, 2.5, 2.5) >= -1e-6
    assert res.kinds.get("octant", 0) > 0 and "best" not in res.kinds
    if coplanar:                                   # everything stays in the plane
        assert np.allclose(res.xyz_m[:, :, 2], 10.0)
    assert np.all(res.delay_s >= -0.1) and np.all(res.delay_s < 60.0)


def test_super_conflict_4_uavs():
    n, R = 4, 150.0
    ang = 2 * np.pi * np.arange(n) / n
    S = np.column_stack([R * np.cos(ang), R * np.sin(ang), np.full(n, 50.0)])
    G = S * [-1, -1, 1]
    res = fly_fleet(S, G, speed_mps=10.0, radius_m=1.0, margin_m=5.0, periphery_m=60.0, horizon_s=6.0,
                    dt_s=0.1, t_max_s=200.0, coplanar=True)
    assert np.all(np.isfinite(res.arrival_s)) and "best" not in res.kinds
    assert _brute_min_sep(res, 7.0, 7.0) >= -1e-6
    # without avoidance all four would meet at the centre
    assert res.kinds.get("octant", 0) > 0 and np.all(res.delay_s >= -0.1) and res.delay_s.max() > 0.5


@pytest.mark.parametrize(("n", "coplanar"), [(8, True), (16, False)])
def test_super_conflict_8_and_16_uavs(n, coplanar):
    """BlueSky's super conflict with 8 and 16 UAVs (issue 14): all arrive, zero losses of
    separation by the brute-force pairwise check, delays finite and reported (>= 0)."""
    R = 100.0
    ang = 2 * np.pi * np.arange(n) / n
    S = np.column_stack([R * np.cos(ang), R * np.sin(ang), np.full(n, 50.0)])
    G = S * [-1, -1, 1]
    res = fly_fleet(S, G, speed_mps=10.0, radius_m=1.0, margin_m=5.0, periphery_m=60.0, horizon_s=6.0,
                    dt_s=0.1, t_max_s=4 * R / 10.0 + 60.0, coplanar=coplanar)
    assert np.all(np.isfinite(res.arrival_s)) and "best" not in res.kinds
    assert _brute_min_sep(res, 7.0, 7.0) >= -1e-6
    assert res.delay_s.shape == (n,) and np.all(res.delay_s >= -0.1) and np.all(res.delay_s < 60.0)
    assert res.delay_s.max() > 0.5 and res.kinds.get("octant", 0) > 0


def test_tactical_method_is_checked():
    from click.testing import CliRunner

    from skyroute.pipeline.cli import main
    from skyroute.stages.base import InputError as BaseInputError
    from skyroute.stages.tactical.replay import TACTICAL_METHODS, FlyParams

    assert TACTICAL_METHODS == ("levels", "octant") and FlyParams().method == "levels"
    with pytest.raises(BaseInputError, match="levels, octant"):
        FlyParams(method="potential")
    res = CliRunner().invoke(main, ["fly", "helsinki-tactical", "--tactical", "potential"])
    assert res.exit_code == 2 and "levels" in res.output and "octant" in res.output
