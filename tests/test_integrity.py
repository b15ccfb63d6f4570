"""Solution-separation protection levels (stages/integrity.py): subset separation sigmas against
a hand closed form and explicit numpy inverses, the PL equation plugged back, monotonicity,
no PL below 5 satellites, a fault-free Monte Carlo of the snapshot error against the budget
(binomial bounds), DOP cross-checks."""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest
from scipy.stats import binom, norm

from skyroute.stages import integrity as I
from skyroute.stages.base import InputError
from skyroute.stages.dop import dop_table
from skyroute.stages.navigation import los_from_az_el

AZ9 = np.array([0, 40, 80, 120, 160, 200, 240, 280, 320.0])
EL9 = np.array([20, 60, 35, 75, 25, 50, 30, 65, 45.0])


def _rows(az, el) -> np.ndarray:
    u = los_from_az_el(az, el)
    return np.c_[-u, np.ones(len(az))]


def _two_rings(n: int, el_a: float = 25.0, el_b: float = 65.0):
    """Ring A: n satellites at el_a, azimuths 360 j / n; ring B: n at el_b, offset by 180 / n."""
    j = np.arange(n)
    az = np.r_[360.0 * j / n, 360.0 * j / n + 180.0 / n]
    el = np.r_[np.full(n, el_a), np.full(n, el_b)]
    return az, el


def test_separation_closed_form_two_rings():
    """Two rings of n satellites, one sigma: hand closed form of sigma_0 and of the separation
    of satellite 0 of ring A (azimuth 0), and every subset against explicit inverses."""
    n, sig, ea, eb = 5, 3.0, 25.0, 65.0
    az, el = _two_rings(n, ea, eb)
    G = _rows(az, el)
    d = I.separation_sigmas(G, np.full(2 * n, sig))
    ca, cb, sa, sb = (math.cos(math.radians(ea)), math.cos(math.radians(eb)),
                      math.sin(math.radians(ea)), math.sin(math.radians(eb)))
    w = 1.0 / sig**2
    # all in view: horizontal block w n (ca^2 + cb^2) / 2 I; up/clock block w n [[sa^2+sb^2, sa+sb], [., 2]]
    s0_h = math.sqrt(2.0 / (w * n * (ca**2 + cb**2)))
    s0_u = math.sqrt(2.0 / (w * n * (sa - sb) ** 2))
    np.testing.assert_allclose(d["sigma0_m"], [s0_h, s0_h, s0_u], rtol=1e-12)
    # satellite 0 (az 0, ring A): leverage h = 2 ca^2 / (n (ca^2+cb^2)) + 1 / n
    h = 2 * ca**2 / (n * (ca**2 + cb**2)) + 1.0 / n
    ss_n = math.sqrt(4 * ca**2 / (w * n**2 * (ca**2 + cb**2) ** 2 * (1 - h)))
    ss_u = math.sqrt(1.0 / (w * n**2 * (sa - sb) ** 2 * (1 - h)))
    np.testing.assert_allclose(d["sigma_ss_m"][0], [0.0, ss_n, ss_u], rtol=1e-10, atol=1e-12)
    # symmetry: every satellite of a ring has the same horizontal and vertical separation
    hs = np.hypot(d["sigma_ss_m"][:, 0], d["sigma_ss_m"][:, 1])
    np.testing.assert_allclose(hs[:n], hs[0], rtol=1e-10)
    np.testing.assert_allclose(hs[n:], hs[n], rtol=1e-10)
    # independent numpy: S_k = (G_k^T W_k G_k)^-1 - (G^T W G)^-1 (position diagonal)
    Q0 = np.linalg.inv(w * G.T @ G)
    for k in range(2 * n):
        Gk = np.delete(G, k, axis=0)
        Qk = np.linalg.inv(w * Gk.T @ Gk)
        np.testing.assert_allclose(d["sigma_ss_m"][k] ** 2, np.diag(Qk - Q0)[:3], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(d["sigma_k_m"][k] ** 2, np.diag(Qk)[:3], rtol=1e-10)
    assert d["monitorable"].all() and d["solvable"]


def test_separation_general_c_acc_against_explicit_projection():
    """Unequal sigmas and C_acc != C_int: sigma_ss^2 = diag((S_k - S_0) C_acc (S_k - S_0)^T)."""
    G = _rows(AZ9, EL9)
    s_int = np.linspace(2.0, 5.0, 9)
    s_acc = 0.6 * s_int[::-1]
    d = I.separation_sigmas(G, s_int, s_acc)
    W = np.diag(1.0 / s_int**2)
    S0 = np.linalg.solve(G.T @ W @ G, G.T @ W)
    for k in range(9):
        Wk = W.copy()
        Wk[k, k] = 0.0
        Sk = np.linalg.solve(G.T @ Wk @ G, G.T @ Wk)
        D = Sk - S0
        np.testing.assert_allclose(d["sigma_ss_m"][k] ** 2, np.diag(D @ np.diag(s_acc**2) @ D.T)[:3], rtol=1e-9)


def _risk(pl, s0, sk, T, p_sat):
    return 2 * norm.sf(pl / s0) + np.sum(p_sat * norm.sf((pl - T) / sk))


@pytest.mark.parametrize("budget", [I.IntegrityBudget(), I.IntegrityBudget(p_hmi_hor=1e-9, p_hmi_vert=1e-6,
                                                                           p_fa_hor=1e-7, p_sat=3e-5)])
def test_pl_equation_plugged_back(budget):
    """The bisection PL satisfies the ADD PL equation to 1e-3 relative (independent scipy
    evaluation with the ADD K_fa and the unmonitored deduction)."""
    G = _rows(AZ9, EL9)
    sig = np.full(9, 3.0)
    pl = I.protection_levels_enu(G, sig, budget)
    assert np.isfinite(pl).all()
    d = I.separation_sigmas(G, sig)
    p_nm = 1.0 - (1 - budget.p_sat) ** 9 - 9 * budget.p_sat * (1 - budget.p_sat) ** 8
    frac = 1.0 - p_nm / (budget.p_hmi_hor + budget.p_hmi_vert)
    targets = [budget.p_hmi_hor / 2, budget.p_hmi_hor / 2, budget.p_hmi_vert]
    kfa = [norm.isf(budget.p_fa_hor / 36)] * 2 + [norm.isf(budget.p_fa_vert / 18)]
    for q in range(3):
        T = kfa[q] * d["sigma_ss_m"][:, q]
        r = _risk(pl[q], d["sigma0_m"][q], d["sigma_k_m"][:, q], T, budget.p_sat)
        assert abs(r / (frac * targets[q]) - 1.0) < 1e-3
        # and the PL is the smallest such value: 1 cm less is above the budget
        assert _risk(pl[q] - 0.01, d["sigma0_m"][q], d["sigma_k_m"][:, q], T, budget.p_sat) > frac * targets[q]
    hpl, vpl = I.solution_separation_pl(G, sig, budget)
    assert hpl == pytest.approx(math.hypot(pl[0], pl[1]), rel=1e-12) and vpl == pytest.approx(pl[2], rel=1e-12)


def test_nominal_bias_raises_pl():
    G = _rows(AZ9, EL9)
    h0, v0 = I.solution_separation_pl(G, np.full(9, 3.0))
    h1, v1 = I.solution_separation_pl(G, np.full(9, 3.0), I.IntegrityBudget(bias_nom_m=0.75))
    assert h0 < h1 < h0 + 2 * 9 * 0.75 and v0 < v1 < v0 + 2 * 9 * 0.75      # b <= sum |S| b_nom


def test_pl_monotone_in_sigma_and_satellites():
    G = _rows(AZ9, EL9)
    # sigma: PL is homogeneous of degree 1 in the sigmas (zero nominal bias) and increasing
    base = np.array(I.solution_separation_pl(G, np.full(9, 3.0)))
    np.testing.assert_allclose(I.solution_separation_pl(G, np.full(9, 6.0)), 2 * base, rtol=1e-9)
    prev = np.zeros(2)
    for s in (1.0, 2.0, 3.0, 5.0, 8.0):
        cur = np.array(I.solution_separation_pl(G, np.full(9, s)))
        assert (cur > prev).all()
        prev = cur
    one_worse = np.full(9, 3.0)
    one_worse[3] = 4.0
    assert (np.array(I.solution_separation_pl(G, one_worse)) > base).all()
    # satellites: symmetric additions (two rings of 3, 4, 5, 6, 8) lower both PLs
    hv = np.array([I.solution_separation_pl(_rows(*_two_rings(n)), np.full(2 * n, 3.0)) for n in (3, 4, 5, 6, 8)])
    assert (np.diff(hv, axis=0) < 0).all(), hv
    # one satellite at a time: the all-in-view sigma never grows (information); the PL may
    # (one more fault mode, a larger K_fa), so only sigma_0 is asserted monotone
    s0 = np.array([I.separation_sigmas(G[:n], np.full(n, 3.0))["sigma0_m"] for n in range(5, 10)])
    assert (np.diff(s0, axis=0) <= 1e-12).all()


def test_no_pl_below_five_satellites():
    """With 4 satellites every subset has 3 (no position): a fault cannot be detected, so no PL;
    a critical satellite (singular subset) likewise; 5 well-spread satellites give one."""
    G = _rows(AZ9, EL9)
    for n in (1, 3, 4):
        assert I.solution_separation_pl(G[:n], np.full(n, 3.0)) == (math.inf, math.inf)
    assert np.isfinite(I.solution_separation_pl(G[:5], np.full(5, 3.0))).all()
    # 5 satellites, 4 of them on one elevation ring + zenith: removing the zenith one leaves
    # up and clock inseparable (critical satellite) -> no PL
    crit = _rows(np.array([0, 90, 180, 270, 0.0]), np.array([30, 30, 30, 30, 90.0]))
    assert I.solution_separation_pl(crit, np.full(5, 3.0)) == (math.inf, math.inf)
    # unmonitored double faults above P_THRES (a large p_sat) -> no PL
    assert I.solution_separation_pl(G, np.full(9, 3.0), I.IntegrityBudget(p_sat=1e-3)) == (math.inf, math.inf)


@pytest.mark.parametrize("p_hmi", [2e-2, 1e-7])
def test_fault_free_monte_carlo_within_budget(p_hmi):
    """20000 fault-free snapshot WLS errors on a fixed geometry: the share above the PL is
    within the binomial bound of the budget; with a loose budget the vertical share also
    reaches its fault-free term 2 Q(VPL / sigma_0,U) (the PL is not grossly loose)."""
    n_draw = 20000
    G = _rows(AZ9, EL9)
    sig = np.linspace(2.0, 4.0, 9)
    budget = I.IntegrityBudget(p_hmi_hor=p_hmi, p_hmi_vert=p_hmi, p_thres=0.5)
    pl = I.protection_levels_enu(G, sig, budget)
    hpl = math.hypot(pl[0], pl[1])
    W = np.diag(1.0 / sig**2)
    S0 = np.linalg.solve(G.T @ W @ G, G.T @ W)
    rng = np.random.default_rng(12)
    err = (rng.standard_normal((n_draw, 9)) * sig) @ S0.T                  # (draw, 4) E, N, U, clock [m]
    out_h = int(np.sum(np.hypot(err[:, 0], err[:, 1]) > hpl))
    out_v = int(np.sum(np.abs(err[:, 2]) > pl[2]))
    assert out_h <= binom.ppf(1 - 1e-4, n_draw, p_hmi)
    assert out_v <= binom.ppf(1 - 1e-4, n_draw, p_hmi)
    if p_hmi > 1e-3:
        s0u = math.sqrt(np.linalg.inv(G.T @ W @ G)[2, 2])
        assert out_v >= binom.ppf(1e-4, n_draw, 2 * norm.sf(pl[2] / s0u))


def test_pl_series_matches_epochs_and_containment():
    rng = np.random.default_rng(3)
    m, nsat = 40, 9
    los = np.broadcast_to(los_from_az_el(AZ9, EL9), (m, nsat, 3)).copy()
    los[:, :, :2] *= 1.0 + 0.0 * rng.random((m, nsat, 1))
    vis = rng.random((m, nsat)) < 0.75
    vis[0] = False
    vis[0, :4] = True                                                        # 4 satellites: no PL
    hpl, vpl = I.pl_series(los, vis, 3.0, chunk=7)
    for i in range(m):
        ref = I.solution_separation_pl(_rows(AZ9[vis[i]], EL9[vis[i]]), np.full(vis[i].sum(), 3.0))
        np.testing.assert_allclose([hpl[i], vpl[i]], ref, rtol=1e-9)
    assert np.isinf(hpl[0]) and np.isinf(vpl[0])
    # containment: a hand-counted case
    h = np.array([10.0, 10.0, np.inf])
    v = np.array([5.0, 5.0, np.inf])
    e = np.zeros((2, 3, 3))
    e[0, 0] = [6.0, 8.0, 1.0]          # |e_h| = 10 <= 10 contained, |e_u| 1 <= 5
    e[1, 1] = [6.0, 8.1, 6.0]          # out horizontally and vertically
    c = I.pl_containment(e, h, v)
    assert c == {"availability": pytest.approx(2 / 3), "containment_h": 0.75, "containment_v": 0.75}
    with pytest.raises(InputError):
        I.pl_containment(e, h[:2], v)
    with pytest.raises(InputError):
        I.pl_series(los, vis[:, :3], 3.0)
    with pytest.raises(InputError):
        I.IntegrityBudget(p_sat=0.0)
    with pytest.raises(InputError):
        I.separation_sigmas(_rows(AZ9, EL9), np.full(9, 3.0), np.full(8, 3.0))
    with pytest.raises(InputError):
        I.solution_separation_pl(_rows(AZ9, EL9), np.full(9, -3.0))


def test_sigma0_matches_dop():
    """sigma_0 = sigma HDOP (horizontal, root-sum-square of E and N) and sigma VDOP, against
    skyroute's DOP kernel (a separate Cholesky implementation)."""
    G = _rows(AZ9, EL9)
    d = I.separation_sigmas(G, np.full(9, 3.0))
    _, _, hdop, vdop, _ = dop_table(AZ9, EL9)
    assert math.hypot(*d["sigma0_m"][:2]) == pytest.approx(3.0 * hdop, rel=1e-10)
    assert d["sigma0_m"][2] == pytest.approx(3.0 * vdop, rel=1e-10)


@pytest.mark.skipif(importlib.util.find_spec("gnss_lib_py") is None,
                    reason="gnss-lib-py is not installed (optional cross-check; not a dependency of skyroute)")
def test_sigma0_matches_gnss_lib_py_dop():
    from gnss_lib_py.navdata.navdata import NavData  # pragma: no cover
    from gnss_lib_py.utils.dop import calculate_dop  # pragma: no cover

    nav = NavData()
    nav["el_sv_deg"] = EL9
    nav["az_sv_deg"] = AZ9
    ref = calculate_dop(nav)
    d = I.separation_sigmas(_rows(AZ9, EL9), np.ones(9))
    assert math.hypot(*d["sigma0_m"][:2]) == pytest.approx(ref["HDOP"], rel=1e-9)
    assert d["sigma0_m"][2] == pytest.approx(ref["VDOP"], rel=1e-9)


def test_navsim_section_protection_level(tmp_path):
    """The navsim summary gains ``protection_level`` only when the Dataset has hpl_m/vpl_m;
    every other key is unchanged; its containment is recounted here from the errors."""
    from skyroute.pipeline.navsim import add_protection_levels
    from skyroute.stages.navsim import NavsimParams, simulate
    from skyroute.stages.navsim_outputs import navsim_section, write_navsim

    t = np.arange(0.0, 20.0, 0.5)
    xyz = np.stack([5.0 * t, np.zeros_like(t), np.full_like(t, 50.0)], axis=1)
    los = np.broadcast_to(los_from_az_el(AZ9, EL9), (t.size, 9, 3)).copy()
    recv = np.ones((t.size, 9), bool)
    vis = recv.copy()
    vis[t >= 15.0, :5] = False                                # 4 in line of sight: no PL there
    ds = simulate(t, xyz, los, vis, recv, params=NavsimParams(), runs=8, seed=2)
    before = navsim_section(ds, 1.0)
    assert "protection_level" not in before
    add_protection_levels(ds, los, vis, 3.0)
    after = navsim_section(ds, 1.0)
    pl = after.pop("protection_level")
    assert after == before
    hpl, vpl = I.pl_series(los, vis, 3.0)
    ok = np.isfinite(hpl)
    assert pl["availability"] == pytest.approx(ok.mean()) and 0 < ok.mean() < 1
    e = ds["err_proposed_m"].values[:, ok]
    assert pl["containment_h"] == pytest.approx(np.mean(np.hypot(e[..., 0], e[..., 1]) <= hpl[ok]))
    assert pl["containment_v"] == pytest.approx(np.mean(np.abs(e[..., 2]) <= vpl[ok]))
    assert pl["hpl_median_m"] == pytest.approx(np.median(hpl[ok]))
    assert pl["budgets"] == I.IntegrityBudget().as_dict()
    files = write_navsim(ds, tmp_path, 1.0)
    assert set(files) == {"navsim.csv", "navsim_errors.png", "navsim_bubble.png", "navsim_sats.png", "navsim_pl.png"}
    assert files["navsim_pl.png"].stat().st_size > 10_000


def _explicit_subsets(G, sig):
    """Independent numpy: S_0, S_k (explicit solves) and sigma_ss, sigma_k (n, 3) [m]."""
    W = np.diag(1.0 / sig**2)
    S0 = np.linalg.solve(G.T @ W @ G, G.T @ W)
    Sk, sss, sk = [], [], []
    for k in range(len(sig)):
        Wk = W.copy()
        Wk[k, k] = 0.0
        S = np.linalg.solve(G.T @ Wk @ G, G.T @ Wk)
        Sk.append(S)
        sss.append(np.sqrt(np.diag((S - S0) @ np.diag(sig**2) @ (S - S0).T))[:3])
        sk.append(np.sqrt(np.diag(S @ np.diag(sig**2) @ S.T))[:3])
    return S0, np.array(Sk), np.array(sss), np.array(sk)


def test_separation_test_false_alert_and_faulted_monte_carlo():
    """Detector on 20000 draws: fault-free, the alert rate stays within the false-alert budget
    (union over axes, binomial bound); with a bias on one satellite, the rate of undetected
    errors above the PL stays below the rigorous bound 2 Q((PL - T_k) / sigma_k) (undetected
    means |x_k - x_0| <= T_k, and x_k is fault-free), thresholds recomputed independently here."""
    n_draw = 20000
    G = _rows(AZ9, EL9)
    sig = np.full(9, 3.0)
    budget = I.IntegrityBudget(p_hmi_hor=1e-2, p_hmi_vert=1e-2, p_fa_hor=1e-2, p_fa_vert=1e-2, p_sat=1e-3,
                               p_thres=0.5)
    S0, Sk, sss, sk = _explicit_subsets(G, sig)
    kfa = np.array([norm.isf(budget.p_fa_hor / 36)] * 2 + [norm.isf(budget.p_fa_vert / 18)])
    T_ref = kfa * sss
    rng = np.random.default_rng(5)
    eps = rng.standard_normal((n_draw, 9)) * sig
    det, sep, T = I.separation_test(G, sig, eps, budget)
    np.testing.assert_allclose(T, T_ref, rtol=1e-9)
    np.testing.assert_allclose(sep[:7], np.einsum("kai,di->dka", (Sk - S0)[:, :3], eps[:7]), rtol=1e-9, atol=1e-9)
    assert det.sum() <= binom.ppf(1 - 1e-4, n_draw, budget.p_fa_hor + budget.p_fa_vert)
    pl = I.protection_levels_enu(G, sig, budget)
    k = 1                                                                     # the satellite at el 60 deg
    for bias in (5.0, 10.0, 20.0, 40.0):
        dy = eps.copy()
        dy[:, k] += bias
        det, _, _ = I.separation_test(G, sig, dy, budget)
        e0 = dy @ S0[:3].T
        for q in range(3):
            hmi = int(np.sum(~det & (np.abs(e0[:, q]) > pl[q])))
            bound = 2 * norm.sf((pl[q] - T_ref[k, q]) / sk[k, q])
            assert hmi <= binom.ppf(1 - 1e-4, n_draw, bound), (bias, q, hmi, bound)
    # a large fault is detected nearly always
    dy = eps.copy()
    dy[:, k] += 200.0
    assert I.separation_test(G, sig, dy, budget)[0].mean() > 0.99
