"""Traffic occupancy queries: bucket-indexed numba kernels vs a numpy loop over every capsule.

    python benchmarks/bench_traffic.py
"""

from __future__ import annotations

import time

import numpy as np

from skyroute.stages.traffic import Intruder, build_occupancy


def make_traffic(n_intruders: int, rng) -> list[Intruder]:
    out = []
    for n in range(n_intruders):
        k = 12
        t = rng.uniform(-60, 100) + np.cumsum(np.r_[0.0, rng.uniform(10, 60, k - 1)])
        p = np.cumsum(np.vstack([[rng.uniform(0, 5000), rng.uniform(0, 5000), rng.uniform(30, 150)],
                                 rng.normal(scale=[200, 200, 10], size=(k - 1, 3))]), axis=0)
        out.append(Intruder(f"u{n}", t, p, 2.0))
    return out


def numpy_points(occ, x, y, z, t):
    k = np.minimum(np.floor((t - occ.t0_s) / occ.dt_s).astype(int), occ.n_slices - 1)
    out = np.zeros(x.size, bool)
    p = np.stack([x, y, z], 1)
    for kk in range(occ.n_slices):
        q = np.nonzero(k == kk)[0]
        a, b = occ.slice_start[kk], occ.slice_start[kk + 1]
        if q.size == 0 or a == b:
            continue
        s0, s1, r = occ.caps[a:b, :3], occ.caps[a:b, 3:], occ.radius_m[a:b]
        d = s1 - s0
        L2 = np.maximum(np.einsum("ij,ij->i", d, d), 1e-300)
        w = p[q][:, None, :] - s0[None]
        u = np.clip(np.einsum("qci,ci->qc", w, d) / L2, 0, 1)
        dist2 = np.sum((w - u[..., None] * d[None]) ** 2, axis=2)
        out[q] = np.any(dist2 <= r[None] ** 2, axis=1)
    return out


def main() -> None:
    rng = np.random.default_rng(0)
    print(f"{'intruders':>9} {'capsules':>8} {'build [s]':>9} {'pts':>7} {'numpy [s]':>9} {'numba [s]':>9} "
          f"{'ratio':>6} {'segs':>6} {'seg numba [s]':>13} {'us/seg':>7}")
    for n_int in (10, 100, 400):
        intr = make_traffic(n_int, rng)
        t = time.perf_counter()
        occ = build_occupancy(intr, 600.0, 30, 10.0, 10.0)
        tbuild = time.perf_counter() - t
        occ.occupied(0.0, 0.0, 0.0, 0.0)
        occ.segment_conflicts([0, 0, 0], 0.0, [1, 1, 1], 1.0)  # compile
        n = 100_000
        x, y = rng.uniform(-500, 5500, n), rng.uniform(-500, 5500, n)
        z, tq = rng.uniform(0, 200, n), rng.uniform(0, 600, n)
        t = time.perf_counter()
        ref = numpy_points(occ, x, y, z, tq)
        tn = time.perf_counter() - t
        t = time.perf_counter()
        got = occ.occupied(x, y, z, tq)
        tk = time.perf_counter() - t
        assert np.array_equal(ref, got)
        ns = 20_000
        p0 = np.stack([x[:ns], y[:ns], z[:ns]], 1)
        p1 = p0 + rng.normal(scale=100, size=(ns, 3))
        t0 = np.minimum(tq[:ns], 560.0)
        t = time.perf_counter()
        occ.segment_conflicts(p0, t0, p1, t0 + 30.0)
        tsg = time.perf_counter() - t
        print(f"{n_int:>9d} {occ.caps.shape[0]:>8d} {tbuild:>9.3f} {n:>7d} {tn:>9.3f} {tk:>9.4f} {tn / tk:>6.0f} "
              f"{ns:>6d} {tsg:>13.4f} {1e6 * tsg / ns:>7.2f}")


if __name__ == "__main__":
    main()
