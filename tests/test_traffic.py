"""Traffic occupancy maps against brute force: dense sampling of the intruder paths (point
queries) and a numpy segment-to-path distance loop (segment queries)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from skyroute.pipeline.errors import InputError
from skyroute.stages.grid import Grid
from skyroute.stages.traffic import (
    Intruder,
    TrafficOccupancy,
    build_occupancy,
    intruders_from_records,
)

T_TOT, N_O, D_C, DT_C = 200.0, 10, 10.0, 10.0     # seed 000 case 2: dt = 20 s, dt_c = 10 s, d_c = 10 m
BAND = 0.01                                        # 1 cm tolerance band


def make_intruders(seed=1):
    rng = np.random.default_rng(seed)
    out = []
    for n in range(5):
        k = rng.integers(2, 8)
        t_start = rng.uniform(-30.0, 120.0)
        t = t_start + np.cumsum(np.r_[0.0, rng.uniform(5.0, 40.0, k - 1)])
        p = np.empty((k, 3))
        p[0] = [rng.uniform(0, 800), rng.uniform(0, 800), rng.uniform(30, 120)]
        for i in range(1, k):
            speed = rng.uniform(0.0 if i == 2 else 3.0, 15.0)          # one hover-ish leg
            head = rng.uniform(0, 2 * np.pi)
            climb = rng.uniform(-1.5, 1.5)
            dt = t[i] - t[i - 1]
            p[i] = p[i - 1] + dt * np.array([speed * np.cos(head), speed * np.sin(head), climb])
        out.append(Intruder(f"uav{n}", t, p, float(rng.uniform(1.0, 5.0))))
    return out


@pytest.fixture(scope="module")
def intruders():
    return make_intruders()


@pytest.fixture(scope="module")
def occ(intruders):
    return build_occupancy(intruders, T_TOT, N_O, D_C, DT_C)


def slice_window(k):
    dt = T_TOT / N_O
    return k * dt - DT_C, (k + 1) * dt + DT_C


def position(it, tau):
    return np.stack([np.interp(tau, it.times_s, it.xyz_m[:, j]) for j in range(3)], axis=-1)


@pytest.fixture(scope="module")
def dense_trees(intruders):
    """Per (slice, intruder): KD-tree of path samples every <= 1 cm (distance error <= 5 mm)."""
    trees = {}
    for k in range(N_O):
        a, b = slice_window(k)
        for n, it in enumerate(intruders):
            lo, hi = max(a, it.times_s[0]), min(b, it.times_s[-1])
            if lo > hi:
                continue
            v = np.linalg.norm(np.diff(it.xyz_m, axis=0), axis=1) / np.diff(it.times_s)
            dtau = 0.01 / max(v.max(), 1e-3)
            tau = np.union1d(np.arange(lo, hi, dtau), np.r_[lo, hi, it.times_s[(it.times_s > lo) & (it.times_s < hi)]])
            trees[(k, n)] = cKDTree(position(it, tau))
    return trees


def oracle_points(intruders, trees, x, y, z, t):
    """occupied? and 'inside the 1 cm band' from the dense samples."""
    k = np.minimum(np.floor(t / (T_TOT / N_O)).astype(int), N_O - 1)
    occupied = np.zeros(x.size, bool)
    near = np.zeros(x.size, bool)
    pts = np.stack([x, y, z], axis=1)
    for (kk, n), tree in trees.items():
        sel = np.nonzero(k == kk)[0]
        if sel.size == 0:
            continue
        d, _ = tree.query(pts[sel])
        R = intruders[n].radius_m + D_C
        occupied[sel] |= d <= R
        near[sel] |= np.abs(d - R) < BAND
    return occupied, near


def random_queries_near_paths(intruders, n, rng):
    """Points around the intruder paths (about half inside), at random times."""
    t = rng.uniform(0.0, T_TOT, n)
    which = rng.integers(0, len(intruders), n)
    base = np.empty((n, 3))
    for i, it in enumerate(intruders):
        sel = which == i
        tau = t[sel] + rng.uniform(-DT_C - 15.0, DT_C + 15.0, sel.sum())
        base[sel] = position(it, tau)
    direc = rng.normal(size=(n, 3))
    direc /= np.linalg.norm(direc, axis=1, keepdims=True)
    off = direc * rng.uniform(0.0, 25.0, (n, 1))
    return base + off, t


def test_point_queries_match_dense_sampling(intruders, occ, dense_trees):
    rng = np.random.default_rng(42)
    p, t = random_queries_near_paths(intruders, 12000, rng)
    # exact slice boundaries too
    t[:500] = rng.integers(0, N_O + 1, 500) * (T_TOT / N_O)
    got = occ.occupied(p[:, 0], p[:, 1], p[:, 2], t)
    exp, near = oracle_points(intruders, dense_trees, p[:, 0], p[:, 1], p[:, 2], t)
    away = ~near
    assert away.sum() > 11800
    assert 0.2 < exp.mean() < 0.8
    assert np.array_equal(got[away], exp[away]), f"{np.sum(got[away] != exp[away])} disagreements"


def seg_seg_distance(p, q, a, b):
    """Closest distance between segments p-q (n,3) and a-b (n,3): minimum of the interior
    critical point (if inside the unit square) and the four endpoint-to-segment distances."""
    def pt_seg(x, s0, s1):
        d = s1 - s0
        L2 = np.einsum("ij,ij->i", d, d)
        u = np.where(L2 > 0, np.einsum("ij,ij->i", x - s0, d) / np.where(L2 > 0, L2, 1), 0.0)
        u = np.clip(u, 0, 1)
        return np.linalg.norm(s0 + u[:, None] * d - x, axis=1)

    cands = [pt_seg(p, a, b), pt_seg(q, a, b), pt_seg(a, p, q), pt_seg(b, p, q)]
    d1, d2, r = q - p, b - a, p - a
    A = np.einsum("ij,ij->i", d1, d1)
    B = np.einsum("ij,ij->i", d1, d2)
    Cc = np.einsum("ij,ij->i", d2, d2)
    D = np.einsum("ij,ij->i", d1, r)
    E = np.einsum("ij,ij->i", d2, r)
    den = A * Cc - B * B
    ok = den > 1e-9 * np.maximum(A * Cc, 1e-300)
    s = np.where(ok, (B * E - Cc * D) / np.where(ok, den, 1), -1)
    u = np.where(ok, (A * E - B * D) / np.where(ok, den, 1), -1)
    inside = ok & (s >= 0) & (s <= 1) & (u >= 0) & (u <= 1)
    interior = np.linalg.norm(p + s[:, None] * d1 - (a + u[:, None] * d2), axis=1)
    cands.append(np.where(inside, interior, np.inf))
    return np.min(cands, axis=0)


def oracle_segments(intruders, p0, t0, p1, t1):
    """Per query: min over the slices it crosses of (distance to that slice's path pieces -
    reserved radius).  Path pieces rebuilt with np.interp at the window ends and waypoints."""
    dt = T_TOT / N_O
    ka = np.minimum(np.floor(t0 / dt).astype(int), N_O - 1)
    kb = np.minimum(np.floor(t1 / dt).astype(int), N_O - 1)
    best = np.full(len(p0), np.inf)
    dur = t1 - t0
    for k in range(N_O):
        q = np.nonzero((ka <= k) & (k <= kb))[0]
        if q.size == 0:
            continue
        pos = dur[q] > 0
        sa = np.where(pos, np.maximum((k * dt - t0[q]) / np.where(pos, dur[q], 1), 0.0), 0.0)
        sb = np.where(pos, np.minimum(((k + 1) * dt - t0[q]) / np.where(pos, dur[q], 1), 1.0), 1.0)
        qa = p0[q] + sa[:, None] * (p1[q] - p0[q])
        qb = p0[q] + sb[:, None] * (p1[q] - p0[q])
        a, b = slice_window(k)
        for it in intruders:
            lo, hi = max(a, it.times_s[0]), min(b, it.times_s[-1])
            if lo > hi:
                continue
            tau = np.union1d([lo, hi], it.times_s[(it.times_s > lo) & (it.times_s < hi)])
            path = position(it, tau)
            if len(path) == 1:
                path = np.vstack([path, path])
            for j in range(len(path) - 1):
                d = seg_seg_distance(qa, qb, np.broadcast_to(path[j], qa.shape), np.broadcast_to(path[j + 1], qa.shape))
                best[q] = np.minimum(best[q], d - (it.radius_m + D_C))
    return best


def test_segment_queries_match_numpy_oracle(intruders, occ):
    rng = np.random.default_rng(7)
    n = 10000
    p0, t0 = random_queries_near_paths(intruders, n, rng)
    dur = rng.uniform(0.0, 35.0, n)
    dur[:300] = 0.0                                           # instantaneous segments
    t0 = np.minimum(t0, T_TOT - dur)
    t1 = t0 + dur
    p1 = p0 + rng.normal(scale=20.0, size=(n, 3))
    p1[300:600] = p0[300:600]                                 # hovering
    got = occ.segment_conflicts(p0, t0, p1, t1)
    margin = oracle_segments(intruders, p0, t0, p1, t1)
    away = np.abs(margin) > BAND
    exp = margin <= 0
    assert away.sum() > 0.99 * n and 0.2 < exp.mean() < 0.9
    assert np.array_equal(got[away], exp[away]), f"{np.sum(got[away] != exp[away])} disagreements"
    # a single segment returns a bool, and hovering equals the point query over the slices
    i = 400
    assert occ.segment_conflicts(p0[i], t0[i], p1[i], t1[i]) == bool(got[i])


def test_seed_case_margins_and_slice_membership():
    # one intruder flying east at 10 m/s from x = 0 at t = 0, z = 50 m, radius 2 m
    it = Intruder("east", [0.0, 100.0], [[0, 0, 50], [1000, 0, 50]], 2.0)
    occ = build_occupancy([it], 100.0, 5, d_c_m=10.0, dt_c_s=10.0)   # dt = 20 s
    assert occ.dt_s == 20.0
    # slice 1 = [20, 40] s -> path during [10, 50] s: x in [100, 500], radius 12 m
    assert occ.occupied(100.0 - 11.9, 0, 50, 30.0) and not occ.occupied(100.0 - 12.1, 0, 50, 30.0)
    assert occ.occupied(500.0 + 11.9, 0, 50, 30.0) and not occ.occupied(500.0 + 12.1, 0, 50, 30.0)
    assert occ.occupied(300.0, 11.9, 50, 20.0) and not occ.occupied(300.0, 12.1, 50, 20.0)
    # t = 40 s belongs to slice 2 ([30, 70] s -> x in [300, 700])
    assert not occ.occupied(250.0, 0, 50, 40.0) and occ.occupied(250.0, 0, 50, 39.99)
    # segment across the path during slice 0 only, then away
    assert occ.segment_conflicts([50, -40, 50], 0.0, [50, 40, 50], 10.0)
    assert not occ.segment_conflicts([900, -40, 50], 0.0, [900, 40, 50], 10.0)
    # a segment that reaches x = 900 only in slice 4 ([80, 100] -> x in [700, 1000]) conflicts
    assert occ.segment_conflicts([900, -40, 50], 70.0, [900, 40, 50], 90.0)


def test_dense_slice_view_and_dataset_roundtrip(occ, intruders, tmp_path):
    g = Grid.from_bounds("EPSG:32633", -200, -200, 1000, 1000, 10.0)
    k, z = 4, 80.0
    view = occ.occupancy_slice(g, k, z)
    assert view.dims == ("y", "x") and view.dtype == bool and view.rio.crs.to_epsg() == 32633
    xx, yy = np.meshgrid(g.x, g.y)
    tk = (k + 0.5) * occ.dt_s
    assert np.array_equal(view.values, occ.occupied(xx, yy, z, tk))
    assert view.values.any()
    ds = occ.to_dataset()
    assert ds.sizes["capsule"] == occ.caps.shape[0] and ds.attrs["n_slices"] == N_O
    path = tmp_path / "traffic.zarr"
    ds.to_zarr(path, consolidated=False)
    import xarray as xr
    back = TrafficOccupancy.from_dataset(xr.open_zarr(path, consolidated=False).load())
    rng = np.random.default_rng(3)
    p, t = random_queries_near_paths(intruders, 3000, rng)
    assert np.array_equal(back.occupied(p[:, 0], p[:, 1], p[:, 2], t), occ.occupied(p[:, 0], p[:, 1], p[:, 2], t))
    assert back.intruder_ids == occ.intruder_ids


def test_records_and_bad_input():
    recs = [{"id": "a", "radius_m": 2.0, "waypoints": [[0, 0, 0, 50], [10, 100, 0, 50]]}]
    occ = build_occupancy(recs, 60.0, 3, 5.0, 0.0)
    assert occ.occupied(50.0, 6.9, 50.0, 5.0) and not occ.occupied(50.0, 7.1, 50.0, 5.0)
    assert not occ.occupied(50.0, 0.0, 50.0, 30.0)                 # intruder gone after 10 s
    bad = [{"id": "b", "waypoints": [[0, 0, 0, 0], [5, 1, 0, 0], [5, 2, 0, 0]]}]
    with pytest.raises(InputError, match=r"intruder 'b'.*waypoint 2 \(t = 5.0 s\)"):
        intruders_from_records(bad)
    with pytest.raises(InputError, match=r"intruder 'c'.*waypoint 1"):
        build_occupancy([{"id": "c", "waypoints": [[3, 0, 0, 0], [1, 1, 0, 0]]}], 60.0, 3, 5.0, 0.0)
    with pytest.raises(InputError, match="d_c"):
        build_occupancy(recs, 60.0, 3, -1.0, 0.0)
    with pytest.raises(InputError, match="dt_c"):
        build_occupancy(recs, 60.0, 3, 1.0, -0.5)
    with pytest.raises(InputError, match="N_o"):
        build_occupancy(recs, 60.0, 0, 1.0, 0.0)
    with pytest.raises(InputError, match="outside the occupancy maps"):
        occ.occupied(0, 0, 0, 61.0)
    with pytest.raises(InputError, match="before start time"):
        occ.segment_conflicts([0, 0, 0], 10.0, [1, 0, 0], 5.0)
    empty = build_occupancy([], 60.0, 3, 1.0, 0.0)
    assert not empty.occupied(0, 0, 0, 1.0) and not empty.segment_conflicts([0, 0, 0], 0.0, [9, 9, 9], 60.0)
