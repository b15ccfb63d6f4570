"""GNSS/INS covariance analysis: DARE steady state, snapshot PDOP bound, inertial drift in an
outage, recovery, positive definiteness, and a plain-numpy Kalman filter oracle."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg

from skyroute.pipeline.errors import InputError
from skyroute.stages import navigation as N
from skyroute.stages.dop import dop
from skyroute.stages.vehicle import ImuSpec, load_vehicle

AZ = np.linspace(0.0, 330.0, 12)
EL = np.array([15, 25, 35, 45, 55, 65, 75, 20, 30, 40, 50, 60.0])
UERE = 3.0


@pytest.fixture(scope="module")
def imu() -> ImuSpec:
    return load_vehicle("dji-m300-rtk").imu


def _open_sky(m, nsat=12):
    los = np.broadcast_to(N.los_from_az_el(AZ[:nsat], EL[:nsat]), (m, nsat, 3)).copy()
    return np.arange(m, dtype=float), los, np.ones((m, nsat), bool)


def _h(los_rows):
    h = np.zeros((len(los_rows), N.NX))
    h[:, :3] = -los_rows
    h[:, 9] = 1.0
    return h


def test_first_epoch_is_snapshot_least_squares(imu):
    t, los, vis = _open_sky(3)
    ds = N.navigation_error(t, los, vis, imu, UERE, initial_sigma=(1e4, 1e3, 1e6, 1e3))
    pdop = dop(AZ, EL)["pdop"]                                  # independent DOP module (seed 003)
    assert 1.5 < pdop < 2.0
    assert ds.sigma_p_m.values[0] == pytest.approx(UERE * pdop, rel=1e-4)


def test_steady_state_equals_dare_and_beats_snapshot(imu):
    m = 6000
    t, los, vis = _open_sky(m)
    ds = N.navigation_error(t, los, vis, imu, UERE, return_covariance=True)
    F, Qc = N.continuous_model(imu)
    phi, qd = N.discretise(F, Qc, 1.0)
    H = _h(los[0])
    R = UERE**2 * np.eye(12)
    prior = scipy.linalg.solve_discrete_are(phi.T, H.T, qd, R)    # steady a priori covariance
    post = prior - prior @ H.T @ np.linalg.solve(H @ prior @ H.T + R, H @ prior)
    sig_ref = np.sqrt(np.trace(post[:3, :3]))
    assert ds.sigma_p_m.values[-1] == pytest.approx(sig_ref, rel=1e-4)
    np.testing.assert_allclose(ds.P.values[-1], post, rtol=1e-3, atol=1e-12)
    snapshot = UERE * dop(AZ, EL)["pdop"]
    assert ds.sigma_p_m.values[-1] <= snapshot                   # 1.12 m <= 4.9 m
    assert ds.sigma_h_m.values[-1] < ds.sigma_p_m.values[-1]
    np.testing.assert_allclose(ds.sigma_p_m**2, ds.sigma_h_m**2 + ds.sigma_v_m**2, rtol=1e-12)


@pytest.fixture(scope="module")
def outage(imu):
    m, t0, T = 3600, 3000, 60
    t, los, vis = _open_sky(m)
    vis_out = vis.copy()
    vis_out[t0 + 1:t0 + 1 + T] = False                          # no satellite from t0+1 .. t0+T
    vis_3 = vis.copy()
    vis_3[t0 + 1:t0 + 1 + T, 3:] = False                         # only 3 satellites
    full = N.navigation_error(t, los, vis_out, imu, UERE, return_covariance=True)
    three = N.navigation_error(t, los, vis_3, imu, UERE)
    ref = N.navigation_error(t, los, vis, imu, UERE)
    return t0, T, full, three, ref


def test_outage_grows_like_inertial_drift(outage, imu):
    t0, T, full, _, _ = outage
    P = full.P.values[t0]
    sig = full.sigma_p_m.values
    assert np.all(np.diff(sig[t0:t0 + T + 1]) > 0)              # grows through the outage
    # closed form per axis, constant bias + VRW, including the cross terms
    q = imu.vrw_mps_per_sqrt_s**2
    var = 0.0
    for a in range(3):
        p, v, b = a, 3 + a, 6 + a
        var += (P[p, p] + 2 * T * P[p, v] - T**2 * P[p, b] + T**2 * P[v, v] - T**3 * P[v, b]
                + T**4 / 4 * P[b, b] + q * T**3 / 3)
    assert sig[t0 + T] == pytest.approx(np.sqrt(var), rel=0.03)
    # order of magnitude: sigma_p0 (+) sigma_v0 T (+) 0.5 b T^2 (+) VRW sqrt(T^3/3), no correlations
    sb = np.sqrt(np.trace(P[6:9, 6:9]))
    rough = np.sqrt(np.trace(P[:3, :3]) + T**2 * np.trace(P[3:6, 3:6]) + (0.5 * sb * T**2) ** 2
                    + 3 * q * T**3 / 3)
    assert 0.5 < sig[t0 + T] / rough < 2.0                      # 4.49 m / 3.23 m = 1.39
    # with the in-run stability of Table I (0.2 mg per axis) as bias, 60 s -> 0.5 b T^2 = 3.5 m/axis
    b_spec = imu.accel_bias_sigma_mps2
    assert 0.5 * b_spec * T**2 == pytest.approx(3.53, abs=0.01)
    assert sig[t0 + T] < np.sqrt(3) * 0.5 * b_spec * T**2      # the bias was partly estimated


def test_three_satellites_partial_and_recovery(outage):
    t0, T, full, three, ref = outage
    s_full, s_3, s_ref = full.sigma_p_m.values, three.sigma_p_m.values, ref.sigma_p_m.values
    assert s_ref[t0 + T] < s_3[t0 + T] < s_full[t0 + T]        # 1.12 < 3.84 < 4.49 m
    assert int(three.n_visible[t0 + 5]) == 3 and int(full.n_visible[t0 + 5]) == 0
    # recovery: first fix after the outage brings it below the snapshot value, then back to normal
    assert s_full[t0 + T + 1] < UERE * dop(AZ, EL)["pdop"]
    assert s_full[t0 + T + 400] == pytest.approx(s_ref[t0 + T + 400], rel=0.05)


def test_covariance_symmetric_positive_definite(outage):
    _, _, full, _, _ = outage
    P = full.P.values
    assert np.array_equal(P, np.swapaxes(P, 1, 2))
    assert np.linalg.eigvalsh(P[::7]).min() > 0


def _numpy_kf(t, los, vis, imu, sigma, dt_s, p0):
    """Reference: batch (all satellites at once) Joseph-form update; Q_d by Gauss quadrature of
    int expm(F s) Qc expm(F s)^T ds (not Van Loan)."""
    F, Qc = N.continuous_model(imu)
    P = p0.copy()
    out, last, cache = [], -np.inf, {}
    x, wq = np.polynomial.legendre.leggauss(12)                  # Gauss-Legendre on [0, dt]
    for i in range(len(t)):
        if i:
            dt = t[i] - t[i - 1]
            if dt not in cache:
                qd = sum(0.5 * dt * wk * scipy.linalg.expm(F * s) @ Qc @ scipy.linalg.expm(F * s).T
                         for s, wk in zip(0.5 * dt * (x + 1), wq, strict=True))
                cache[dt] = (scipy.linalg.expm(F * dt), qd)
            phi, qd = cache[dt]
            P = phi @ P @ phi.T + qd
        if t[i] - last >= dt_s - 1e-9:
            last = t[i]
            rows = los[i][vis[i]]
            if len(rows):
                H = _h(rows)
                R = np.diag(sigma[i][vis[i]] ** 2)
                K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
                A = np.eye(N.NX) - K @ H
                P = A @ P @ A.T + K @ R @ K.T
        out.append(P.copy())
    return np.array(out)


def test_kernel_matches_numpy_filter(imu):
    rng = np.random.default_rng(5)
    m, ns = 60, 8
    t = np.cumsum(rng.choice([0.5, 1.0, 2.0], m))
    az, el = rng.uniform(0, 360, (m, ns)), rng.uniform(5, 85, (m, ns))
    los = N.los_from_az_el(az, el)
    vis = rng.random((m, ns)) < 0.6
    sigma = rng.uniform(1.0, 6.0, (m, ns))
    ds = N.navigation_error(t, los, vis, imu, sigma, dt_s=1.0, return_covariance=True,
                            initial_sigma=(10.0, 1.0, 300.0, 10.0))
    p0 = np.diag([100.0] * 3 + [1.0] * 3 + [imu.accel_bias_sigma_mps2**2] * 3 + [300.0**2, 100.0])
    ref = _numpy_kf(t, los, vis, imu, sigma, 1.0, p0)
    scale = np.sqrt(np.einsum("kii->ki", ref))
    np.testing.assert_allclose(ds.P.values / scale[:, :, None] / scale[:, None, :],
                               ref / scale[:, :, None] / scale[:, None, :], atol=1e-7)
    assert ds.updated.values.sum() < m                          # 0.5 s epochs only propagate


def test_bad_input(imu):
    t, los, vis = _open_sky(4)
    with pytest.raises(InputError, match="strictly increasing"):
        N.navigation_error(t[::-1], los, vis, imu)
    with pytest.raises(InputError, match="unit vectors"):
        N.navigation_error(t, los * 2, vis, imu)
    with pytest.raises(InputError, match="bool array"):
        N.navigation_error(t, los, vis.astype(int), imu)
    with pytest.raises(InputError, match=r"los_enu must have shape"):
        N.navigation_error(t, los[:, :, :2], vis, imu)
    with pytest.raises(InputError, match="gnss_sigma_m"):
        N.navigation_error(t, los, vis, imu, gnss_sigma_m=-1.0)
    ds = N.navigation_error(t, los, vis, {"accel_bias_instability_mg": 0.11,
                                          "velocity_random_walk_mps_per_sqrt_h": 0.06})
    assert ds.attrs["accel_bias_instability_mg"] == 0.11           # seed 001 Table 1 IMU


def _quadrature_qd(F, Qc, dt, n=40):
    """Q_d = int_0^dt expm(F s) Qc expm(F s)^T ds by Gauss-Legendre (no Van Loan block matrix)."""
    x, wq = np.polynomial.legendre.leggauss(n)
    out = np.zeros_like(F)
    for s, wk in zip(0.5 * dt * (x + 1), wq, strict=True):
        e = scipy.linalg.expm(F * s)
        out += 0.5 * dt * wk * e @ Qc @ e.T
    return out


@pytest.mark.parametrize("tau_s", [3600.0, 300.0, 20.0])
@pytest.mark.parametrize("dt", [1e-3, 0.0137, 0.5, 1.0, 3.7, 10.0])
def test_closed_form_discretisation_matches_van_loan(imu, tau_s, dt):
    """The closed-form phi / Q_d of the navigation model against the Van Loan block exponential
    (scipy expm) and against a Gauss-Legendre quadrature of its integral: equal to 1e-12
    relative on every entry (Van Loan leaves round-off of ~1e-16 of the matrix scale where
    the exact value is 0), exact zeros where the model has none."""
    spec = imu.model_copy(update={"accel_bias_correlation_time_s": tau_s})
    F, Qc = N.continuous_model(spec, clock_h0=3e-19, clock_hm2=5e-20)
    if dt / tau_s > 0.5:
        pytest.skip("beyond the closed form's range (Van Loan is used there)")
    assert N._model_scalars(F, Qc) is not None
    phi, qd = N.discretise(F, Qc, dt)
    phi_vl, qd_vl = N._van_loan(F, Qc, dt)
    for got, ref in ((phi, phi_vl), (qd, qd_vl)):
        nz = got != 0
        np.testing.assert_allclose(got[nz], ref[nz], rtol=1e-12, atol=0)   # every entry, however small
        assert np.all(np.abs(ref[~nz]) <= 1e-15 * np.abs(ref).max())      # exact zeros: Van Loan round-off
    np.testing.assert_allclose(phi, scipy.linalg.expm(F * dt), rtol=1e-13, atol=1e-15)
    ref = _quadrature_qd(F, Qc, dt)
    np.testing.assert_allclose(qd, ref, rtol=1e-11, atol=1e-14 * np.abs(ref).max())
    assert np.array_equal(qd, qd.T)
    # a per-axis entry that the quadrature resolves well: bias-driven position variance
    # ~ qb T^5 / 20 for T << tau
    qb = Qc[6, 6]
    if dt / tau_s < 1e-3:
        assert qd[0, 0] - Qc[3, 3] * dt**3 / 3 == pytest.approx(qb * dt**5 / 20, rel=1e-3)


def test_discretise_falls_back_to_van_loan(imu):
    """Matrices not of the navigation model's form, or steps beyond tau_b / 2, go through the
    Van Loan exponential."""
    F, Qc = N.continuous_model(imu)
    F2 = F.copy()
    F2[0, 1] = 2.0
    assert N._model_scalars(F2, Qc) is None
    for args in ((F2, Qc, 0.5), (F, Qc, 0.6 * imu.accel_bias_correlation_time_s)):
        phi, qd = N.discretise(*args)
        phi_vl, qd_vl = N._van_loan(*args)
        assert np.array_equal(phi, phi_vl) and np.array_equal(qd, qd_vl)
