"""Navigation covariance analysis: numba kernel vs a plain-numpy filter loop (same model).

Run: python benchmarks/bench_navigation.py
"""

from __future__ import annotations

import time

import numpy as np

from skyroute.stages import navigation as N
from skyroute.stages.vehicle import load_vehicle


def numpy_filter(t, los, vis, imu, sigma):
    F, Qc = N.continuous_model(imu)
    phi, qd = N.discretise(F, Qc, float(t[1] - t[0]))
    P = np.diag([100.0] * 3 + [1.0] * 3 + [imu.accel_bias_sigma_mps2**2] * 3 + [9e4, 100.0])
    out = np.empty((len(t), 3))
    for i in range(len(t)):
        if i:
            P = phi @ P @ phi.T + qd
        rows = los[i][vis[i]]
        H = np.zeros((len(rows), N.NX))
        H[:, :3] = -rows
        H[:, 9] = 1.0
        S = H @ P @ H.T + sigma**2 * np.eye(len(rows))
        K = np.linalg.solve(S, H @ P).T
        P = P - K @ H @ P
        P = 0.5 * (P + P.T)
        out[i] = np.diag(P)[:3]
    return np.sqrt(out.sum(1))


def best(f, n=3):
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        r = f()
        ts.append(time.perf_counter() - t0)
    return min(ts), r


def main():
    imu = load_vehicle("dji-m300-rtk").imu
    rng = np.random.default_rng(0)
    nsat = 12
    N.navigation_error(np.arange(3.0), N.los_from_az_el(np.zeros((3, 1)), np.full((3, 1), 45.0)),
                       np.ones((3, 1), bool), imu)              # compile / load the numba cache
    print(f"{'epochs':>8} {'sats':>5} {'numba [s]':>10} {'numpy [s]':>10} {'speed-up':>9} {'max |dsigma| [m]':>17}")
    for m in (1_000, 10_000):
        t = np.arange(m, dtype=float)
        los = N.los_from_az_el(rng.uniform(0, 360, (m, nsat)), rng.uniform(10, 85, (m, nsat)))
        vis = rng.random((m, nsat)) < 0.8
        vis[:, :4] = True
        tk, ds = best(lambda t=t, los=los, vis=vis: N.navigation_error(t, los, vis, imu, 3.0))
        tn, ref = best(lambda t=t, los=los, vis=vis: numpy_filter(t, los, vis, imu, 3.0), n=1)
        diff = np.abs(ds.sigma_p_m.values - ref).max()
        print(f"{m:>8} {nsat:>5} {tk:>10.3f} {tn:>10.3f} {tn / tk:>9.1f} {diff:>17.2e}")


if __name__ == "__main__":
    main()
