"""Single-fault solution-separation protection levels (ARAIM style), an alternative to the
k-sigma safety bubble of :mod:`skyroute.stages.navsim`.

References
----------
* WG-C Advanced RAIM Technical Subgroup, *ARAIM Airborne Algorithm Description Document*
  (ADD) v3.1, 2019 (EU-US Cooperation on Satellite Navigation), sections 2.4-2.5: all-in-view
  weighted least squares, fault-tolerant subsets, solution separation thresholds and the
  protection level equation.
* J. Blanch, T. Walter, P. Enge et al., "Baseline advanced RAIM user algorithm and possible
  improvements", IEEE Trans. Aerospace and Electronic Systems 51(1), 713-732, 2015.

Algorithm (one epoch, satellites ``i = 1..n`` in line of sight)
---------------------------------------------------------------
Geometry rows ``g_i = [-e_i, -n_i, -u_i, 1]`` (ENU unit line of sight receiver -> satellite,
clock last; the sign of the first three columns changes no sigma), weights
``W = diag(1 / sigma_i^2)`` [1/m^2] with ``sigma_i`` the pseudorange error sigma [m]:

* all in view: ``Q0 = (G^T W G)^-1``, ``S0 = Q0 G^T W``, ``sigma_0,q^2 = Q0[q, q]`` [m^2];
* subset ``k`` (satellite ``k`` removed, the single-fault hypothesis "satellite k is
  faulty"): ``W_k = W`` with ``w_k = 0``.  By Sherman-Morrison, with the leverage
  ``h_k = w_k g_k^T Q0 g_k`` and ``c_k = w_k / (1 - h_k)``:
  ``Q_k = Q0 + c_k (Q0 g_k)(Q0 g_k)^T`` and ``S_k - S0 = c_k (Q0 g_k)(g_k^T S0 - e_k^T)``;
* separation sigma ``sigma_ss,k,q^2 = [(S_k - S0) C_acc (S_k - S0)^T]_qq``; with
  ``C_acc = W^-1`` (one error model for integrity and continuity, below) this equals
  ``Q_k[q, q] - Q0[q, q] = w_k (Q0 g_k)_q^2 / (1 - h_k)``;
* thresholds ``T_k,q = K_fa,q sigma_ss,k,q`` with ``K_fa,q = Q^-1(P_FA,q / (2 n))``
  (``P_FA_HOR`` split over the two horizontal axes; ADD eq. for K_fa);
* protection level per axis ``q``: the ``PL`` solving
  ``2 Q((PL - b_0,q) / sigma_0,q) + sum_k p_sat Q((PL - T_k,q - b_k,q) / sigma_k,q)
  = P_HMI,q (1 - P_unmonitored / (P_HMI_VERT + P_HMI_HOR))`` (ADD PL equation; ``Q`` the
  standard normal tail; ``P_HMI,q = P_HMI_VERT`` vertically and ``P_HMI_HOR / 2`` per
  horizontal axis), found by bisection (the left side decreases in ``PL``) between the
  ADD-style bounds ``sigma_0 Q^-1(P / 2)`` and the largest single-term solution with
  ``P / (n + 1)`` each;  ``HPL = sqrt(PL_e^2 + PL_n^2)``, ``VPL = PL_u``;
* nominal biases ``b_0,q = sum_i |S0[q, i]| b_nom,i`` and ``b_k,q`` likewise with ``S_k``.

The PL bounds the error of the **snapshot** (epoch-wise) weighted least-squares position of
the line-of-sight satellites (the proposed filter's set), with the given integrity budget,
provided the solution separation test ``|x_k,q - x_0,q| <= T_k,q`` passes (else: alert, no
PL).  A Kalman filter that also integrates the IMU has a smaller error than the snapshot
solution (it averages over time), so the snapshot PL over-bounds the filter error: it is an
alternative bubble for the filter, conservative by construction, not a tight one.

Budgets (:class:`IntegrityBudget`; the choices and why)
-------------------------------------------------------
* ``p_hmi_hor = p_hmi_vert = 5e-8`` (total ``P_HMI = 1e-7``): the ADD's LPV-200 total
  integrity risk ``1e-7`` per exposure, applied per epoch as the ADD does (the exposure is
  the operation, errors being correlated over it), split **equally** between horizontal and
  vertical because a drone's obstacle clearance is both lateral (buildings) and vertical
  (terrain, roofs), unlike LPV-200 which puts 9.8e-8 on the vertical.  A "1e-7 per flight
  hour" requirement with independent 1 Hz snapshots would need ``1e-7 / 3600`` per epoch
  (pass it as ``IntegrityBudget(p_hmi_hor=..., ...)``).
* ``p_fa_hor = p_fa_vert = 2e-6`` (continuity, total ``4e-6`` as the ADD's LPV-200 false
  alert budget, split equally likewise).
* ``p_sat = 1e-5`` per satellite and epoch (ADD / GPS SPS performance standard ``R_sat``
  order); ``p_const = 0``: no constellation-wide fault mode for a single-constellation
  drone receiver (a GPS constellation fault, ~1e-8 in the ADD, is below the unmonitored
  threshold and is simply added to ``P_unmonitored`` if given).
* ``p_thres = 8e-8`` (ADD ``P_THRES``): the unmonitored probability (two or more satellites
  faulty at once, exact binomial tail, plus ``p_const``) must stay below it, else no PL.
* ``bias_nom_m = 0``: the navsim error model has zero-mean line-of-sight errors (NLOS
  satellites are excluded by the maps); the ADD's 0.75 m ``b_nom`` can be given.
* ``C_acc = C_int``: one pseudorange sigma for integrity and continuity (the navsim UERE;
  the ADD distinguishes URA from URE, which skyroute's error model does not).

The detector itself (separations ``x_k - x_0`` and thresholds on pseudorange residuals) is
:func:`separation_test`.

No PL (``+inf``): fewer than 5 satellites (with 4 every subset has 3 satellites and no
position: a fault cannot be detected, every satellite is critical), a geometry where a
subset is singular (``h_k -> 1``: that satellite's fault is unobservable), or an
unmonitored probability above ``p_thres`` / above ``P_HMI``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import scipy.special
import scipy.stats

from skyroute.stages.base import InputError

__all__ = ["IntegrityBudget", "axis_risk", "fa_multipliers", "pl_containment", "pl_series", "protection_levels_enu",
           "separation_sigmas", "separation_test", "solution_separation_pl"]

_LEVERAGE_MAX = 1.0 - 1e-9        # h_k above this: subset k is singular (satellite k critical)
_BISECTION_STEPS = 80


@dataclass(frozen=True)
class IntegrityBudget:
    """Integrity and continuity budgets of the protection level (module docstring: values and
    why).  Probabilities per epoch (per exposure)."""

    p_hmi_hor: float = 5e-8
    p_hmi_vert: float = 5e-8
    p_fa_hor: float = 2e-6
    p_fa_vert: float = 2e-6
    p_sat: float = 1e-5
    p_const: float = 0.0
    p_thres: float = 8e-8
    bias_nom_m: float = 0.0

    def __post_init__(self) -> None:
        for name in ("p_hmi_hor", "p_hmi_vert", "p_fa_hor", "p_fa_vert", "p_sat", "p_thres"):
            v = getattr(self, name)
            if not (np.isfinite(v) and 0.0 < v < 1.0):
                raise InputError(f"integrity budget {name} = {v} must be a probability in (0, 1)")
        if not 0.0 <= self.p_const < 1.0:
            raise InputError(f"integrity budget p_const = {self.p_const} must be in [0, 1)")
        if not (np.isfinite(self.bias_nom_m) and self.bias_nom_m >= 0):
            raise InputError(f"integrity budget bias_nom_m = {self.bias_nom_m} m must be >= 0")

    def as_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in dataclasses.asdict(self).items()}


def _qfunc(x):
    """Standard normal tail Q(x) = P(Z > x) (accurate far in the tail)."""
    return scipy.special.ndtr(-x)


def _qinv(p):
    """Inverse of Q: x with Q(x) = p (accurate for tiny p)."""
    return -scipy.special.ndtri(p)


def _rows(los_enu: np.ndarray) -> np.ndarray:
    return np.concatenate([-los_enu, np.ones(los_enu.shape[:-1] + (1,))], axis=-1)


def _subset_terms(G: np.ndarray, w: np.ndarray, w_acc: np.ndarray, bias_m: np.ndarray):
    """Batched (..., n, 4) rows, (..., n) weights [1/m^2] (0 = satellite unused), accuracy
    weights and nominal biases [m].  Returns sigma0 (..., 3), sigma_k (..., n, 3),
    sigma_ss (..., n, 3) [m], b0 (..., 3), bk (..., n, 3) [m], monitorable (..., n) bool
    (used and its subset solvable) and ok (...) bool (all-in-view solvable)."""
    N0 = np.einsum("...ia,...i,...ib->...ab", G, w, G)
    scale = np.maximum(np.trace(N0, axis1=-2, axis2=-1), 1e-300)[..., None, None]
    lam_min = np.linalg.eigvalsh(N0 / scale)[..., 0]
    ok = lam_min > 1e-10
    Q0 = np.linalg.inv(np.where(ok[..., None, None], N0, np.eye(4)))
    Qg = np.einsum("...ab,...ib->...ia", Q0, G)                                 # (..., n, 4)
    h = w * np.einsum("...ia,...ia->...i", G, Qg)                               # leverage
    used = w > 0
    mon = used & ok[..., None] & (h < _LEVERAGE_MAX)
    c = np.where(mon, w / np.where(mon, 1.0 - h, 1.0), 0.0)
    S0 = Qg * w[..., None]                                                      # (..., i, 4) = S0^T
    # r_k,i = (g_k^T S0 - e_k^T)_i ; S_k - S0 = c_k (Q0 g_k) r_k
    gS0 = np.einsum("...ka,...ia->...ki", G, S0)
    r = gS0 - np.eye(G.shape[-2])
    rvar = np.einsum("...ki,...i->...k", r * r, np.where(used, 1.0 / np.where(used, w_acc, 1.0), 0.0))
    qg3 = Qg[..., :3]
    var_ss = (c ** 2 * rvar)[..., None] * qg3 ** 2                             # (..., n, 3)
    q0d = np.diagonal(Q0, axis1=-2, axis2=-1)[..., :3]
    var_k = q0d[..., None, :] + c[..., None] * qg3 ** 2
    b0 = np.einsum("...ia,...i->...a", np.abs(S0[..., :3]), bias_m)
    if np.any(bias_m > 0):
        dS = (c[..., None, None] * qg3[..., :, :, None]) * r[..., :, None, :]     # (..., k, 3, i)
        bk = np.einsum("...kai,...i->...ka", np.abs(S0[..., None, :, :3].swapaxes(-1, -2) + dS), bias_m)
    else:
        bk = np.zeros(var_k.shape)
    return np.sqrt(q0d), np.sqrt(var_k), np.sqrt(var_ss), b0, bk, mon, ok


def separation_sigmas(G, sigma_i, sigma_acc_i=None) -> dict[str, np.ndarray]:
    """Sigmas of the single-fault solution separation for one epoch (module docstring).

    G : (n, 4) geometry rows ``[-e, -n, -u, 1]`` (any sign of the ENU part).
    sigma_i : (n,) pseudorange error sigmas [m] (integrity, ``C_int``).
    sigma_acc_i : (n,) sigmas [m] of ``C_acc`` for the separation (default ``sigma_i``).

    Returns ``sigma0_m`` (3,) all-in-view sigmas E, N, U [m]; ``sigma_k_m`` (n, 3) subset
    sigmas; ``sigma_ss_m`` (n, 3) separation sigmas [m] (NaN-free; rows of unmonitorable
    subsets are meaningless, see ``monitorable`` (n,) bool); ``solvable`` (bool).
    """
    G = np.asarray(G, float)
    s = np.asarray(sigma_i, float).reshape(-1)
    if G.ndim != 2 or G.shape[1] != 4 or s.shape != (G.shape[0],) or not (np.isfinite(G).all() and (s > 0).all()):
        raise InputError(f"G must be finite (n, 4) geometry rows and sigma_i (n,) sigmas > 0 [m]; "
                         f"got {G.shape}, {s.shape}")
    sa = s if sigma_acc_i is None else np.asarray(sigma_acc_i, float).reshape(-1)
    if sa.shape != s.shape or not (np.isfinite(sa).all() and (sa > 0).all()):
        raise InputError(f"sigma_acc_i must be (n={s.size},) finite sigmas > 0 [m]; got {sa.shape}")
    s0, sk, sss, _, _, mon, ok = _subset_terms(G, 1.0 / s**2, 1.0 / sa**2, np.zeros_like(s))
    return {"sigma0_m": s0, "sigma_k_m": sk, "sigma_ss_m": sss, "monitorable": mon, "solvable": bool(ok)}


def _p_unmonitored(n_used: np.ndarray, budget: IntegrityBudget) -> np.ndarray:
    """P(two or more of ``n_used`` satellites faulty) (exact binomial tail) + p_const."""
    return scipy.stats.binom.sf(1, n_used, budget.p_sat) + budget.p_const


def _solve_pl(p_target, sigma0, b0, p_k, T, sk, bk) -> np.ndarray:
    """PL (...) solving 2 Q((PL - b0)/sigma0) + sum_k p_k Q((PL - T_k - b_k)/s_k) = p_target
    by bisection; inputs broadcast over (...) and (..., n) for the subset terms."""
    n = p_k.shape[-1]
    lo = b0 + sigma0 * _qinv(p_target / 2.0)
    share = p_target[..., None] / ((n + 1) * np.where(p_k > 0, p_k, 1.0))
    xk = np.where(p_k > 0, T + bk + sk * _qinv(np.minimum(share, 0.5)), 0.0)
    hi = np.maximum(b0 + sigma0 * _qinv(p_target / (2.0 * (n + 1))), xk.max(-1, initial=0.0))
    hi = np.maximum(hi, lo)

    def risk(pl):
        return 2.0 * _qfunc((pl - b0) / sigma0) + np.sum(p_k * _qfunc((pl[..., None] - T - bk) / sk), axis=-1)

    for _ in range(_BISECTION_STEPS):
        mid = 0.5 * (lo + hi)
        above = risk(mid) > p_target                        # risk too high: PL must grow
        lo = np.where(above, mid, lo)
        hi = np.where(above, hi, mid)
    return hi


def _pl_batch(G, w, used, budget: IntegrityBudget) -> np.ndarray:
    """Per-axis PLs E, N, U [m] (..., 3) (+inf: no PL) for batched rows G (..., n, 4) and
    weights w (..., n) [1/m^2] of the satellites ``used`` (..., n)."""
    n_used = used.sum(-1)
    bias = np.where(used, budget.bias_nom_m, 0.0)
    s0, sk, sss, b0, bk, mon, ok = _subset_terms(G, np.where(used, w, 0.0), np.where(used, w, 0.0), bias)
    p_nm = _p_unmonitored(n_used, budget)
    avail = ok & (n_used >= 5) & (mon == used).all(-1) & (p_nm <= budget.p_thres)
    frac = 1.0 - p_nm / (budget.p_hmi_hor + budget.p_hmi_vert)
    avail &= frac > 0
    T = fa_multipliers(np.maximum(n_used, 1), budget)[..., None, :] * sss      # (..., n, 3)
    p_target = np.where(avail, frac, 1.0)[..., None] * axis_risk(budget)       # (..., 3)
    p_k = np.where(mon, budget.p_sat, 0.0)
    sk_safe = np.where(mon[..., None], sk, 1.0)
    pl = _solve_pl(p_target, np.where(avail[..., None], s0, 1.0), b0,
                   np.moveaxis(np.broadcast_to(p_k[..., None], sk.shape), -1, -2), np.moveaxis(T, -1, -2),
                   np.moveaxis(sk_safe, -1, -2), np.moveaxis(bk, -1, -2))
    return np.where(avail[..., None], pl, np.inf)


def fa_multipliers(n_modes, budget: IntegrityBudget) -> np.ndarray:
    """``K_fa`` (..., 3) for E, N, U with ``n_modes`` monitored fault modes (ADD:
    ``Q^-1(P_FA_HOR / (4 n))`` per horizontal axis, ``Q^-1(P_FA_VERT / (2 n))`` vertically;
    two-sided test, the horizontal false-alert budget split over two axes)."""
    n = np.asarray(n_modes, float)
    return np.stack([_qinv(budget.p_fa_hor / (4.0 * n))] * 2 + [_qinv(budget.p_fa_vert / (2.0 * n))], axis=-1)


def axis_risk(budget: IntegrityBudget) -> np.ndarray:
    """Integrity risk allocated per axis E, N, U (3,): ``P_HMI_HOR / 2`` per horizontal axis,
    ``P_HMI_VERT`` vertically (before the unmonitored-fault deduction)."""
    return np.array([budget.p_hmi_hor / 2.0, budget.p_hmi_hor / 2.0, budget.p_hmi_vert])


def _check_epoch(G, sigma_i) -> tuple[np.ndarray, np.ndarray]:
    G = np.asarray(G, float)
    s = np.asarray(sigma_i, float).reshape(-1)
    if G.ndim != 2 or G.shape[1] != 4 or s.shape != (G.shape[0],):
        raise InputError(f"G must be (n, 4) geometry rows and sigma_i (n,) [m]; got {G.shape}, {s.shape}")
    if not (np.isfinite(G).all() and np.isfinite(s).all() and (s > 0).all()):
        raise InputError("G must be finite and sigma_i finite and > 0 [m]")
    return G, s


def protection_levels_enu(G, sigma_i, budget: IntegrityBudget | None = None) -> np.ndarray:
    """Per-axis protection levels ``(PL_E, PL_N, PL_U)`` [m] of one epoch, each solving the
    ADD PL equation with its axis risk (:func:`axis_risk`); arguments and ``+inf`` as
    :func:`solution_separation_pl`."""
    budget = IntegrityBudget() if budget is None else budget
    G, s = _check_epoch(G, sigma_i)
    return _pl_batch(G, 1.0 / s**2, np.ones(s.size, bool), budget)


def solution_separation_pl(G, sigma_i, budget: IntegrityBudget | None = None) -> tuple[float, float]:
    """Single-fault solution-separation protection levels ``(HPL_m, VPL_m)`` [m] of one epoch
    (ARAIM ADD v3.1; Blanch et al. 2015; module docstring for the equations and budgets):
    ``HPL = sqrt(PL_E^2 + PL_N^2)``, ``VPL = PL_U`` (:func:`protection_levels_enu`).

    G : (n, 4) geometry rows ``[-e, -n, -u, 1]`` of the satellites used (ENU unit lines of
        sight receiver -> satellite, clock column last).
    sigma_i : (n,) pseudorange error sigmas [m] (``C_int = C_acc = diag(sigma_i^2)``).
    budget : :class:`IntegrityBudget` (default: the documented choices).

    ``+inf`` when no PL exists: fewer than 5 satellites (no fault detection possible), a
    critical satellite (a singular subset), or too large an unmonitored probability.
    """
    pl = protection_levels_enu(G, sigma_i, budget)
    return float(np.hypot(pl[0], pl[1])), float(pl[2])


def separation_test(G, sigma_i, dy_m, budget: IntegrityBudget | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The solution separation test of one epoch's geometry on pseudorange residuals.

    G : (n, 4) geometry rows; sigma_i : (n,) sigmas [m]; dy_m : (..., n) pseudorange
    residuals [m] (measured minus predicted at the linearisation point; any leading dims,
    e.g. Monte Carlo draws).  budget : :class:`IntegrityBudget` (the false-alert budget).

    Returns ``detected`` (...) bool (some ``|x_k,q - x_0,q| > T_k,q``), the separations
    ``x_k - x_0`` (..., n, 3) E, N, U [m] and the thresholds ``T_k,q`` (n, 3) [m]
    (``S_k - S_0 = c_k (Q0 g_k)(g_k^T S0 - e_k^T)``, module docstring).  Unmonitorable
    subsets (a critical satellite) get a separation of 0 and a threshold of +inf.
    """
    budget = IntegrityBudget() if budget is None else budget
    G, s = _check_epoch(G, sigma_i)
    dy = np.asarray(dy_m, float)
    if dy.shape[-1:] != (s.size,) or not np.isfinite(dy).all():
        raise InputError(f"dy_m must be finite residuals (..., n={s.size}) [m]; got {dy.shape}")
    w = 1.0 / s**2
    d = separation_sigmas(G, s)
    mon = d["monitorable"]
    N0 = G.T @ (w[:, None] * G)
    Qg = np.linalg.solve(N0, G.T).T if d["solvable"] else np.zeros_like(G)          # (n, 4) = Q0 g_k
    h = w * np.einsum("ia,ia->i", G, Qg)
    c = np.where(mon, w / np.where(mon, 1.0 - h, 1.0), 0.0)
    r = G @ (Qg * w[:, None]).T - np.eye(s.size)                                     # (k, i)
    sep = (c[:, None] * Qg[:, :3]) * (dy @ r.T)[..., None]                          # (..., k, 3)
    T = np.where(mon[:, None], fa_multipliers(max(int(mon.sum()), 1), budget) * d["sigma_ss_m"], np.inf)
    return (np.abs(sep) > T).any(axis=(-1, -2)), sep, T


def pl_series(los_enu, visible, sigma_uere_m, budget: IntegrityBudget | None = None, chunk: int = 512
              ) -> tuple[np.ndarray, np.ndarray]:
    """HPL and VPL (m,) [m] along a flight, from the snapshot least squares of the
    line-of-sight satellites at each epoch (the proposed filter's set).

    los_enu : (m, nsat, 3) unit lines of sight receiver -> satellite (ENU), as
        :func:`skyroute.stages.navsim.flight_geometry`.
    visible : (m, nsat) bool, the satellites used (in line of sight per the maps).
    sigma_uere_m : pseudorange sigma [m], scalar or (m, nsat).
    budget : :class:`IntegrityBudget`.  chunk : epochs per vectorised batch (memory).
    """
    budget = IntegrityBudget() if budget is None else budget
    los = np.asarray(los_enu, float)
    vis = np.asarray(visible, bool)
    if los.ndim != 3 or los.shape[2] != 3 or vis.shape != los.shape[:2]:
        raise InputError(f"los_enu must be (m, nsat, 3) and visible (m, nsat) bool; got {los.shape}, {vis.shape}")
    sig = np.broadcast_to(np.asarray(sigma_uere_m, float), vis.shape)
    if not (np.isfinite(sig[vis]).all() and (sig[vis] > 0).all()) or not np.isfinite(los[vis]).all():
        raise InputError("sigma_uere_m must be finite and > 0 [m] and los_enu finite for the visible satellites")
    los = np.where(vis[..., None], los, 0.0)
    w = np.where(vis, 1.0 / np.where(vis, sig, 1.0) ** 2, 0.0)
    m = vis.shape[0]
    hpl = np.empty(m)
    vpl = np.empty(m)
    for a in range(0, m, max(int(chunk), 1)):
        b = min(a + max(int(chunk), 1), m)
        pl = _pl_batch(_rows(los[a:b]), w[a:b], vis[a:b], budget)
        hpl[a:b], vpl[a:b] = np.hypot(pl[:, 0], pl[:, 1]), pl[:, 2]
    return hpl, vpl


def pl_containment(err_enu_m, hpl_m, vpl_m) -> dict[str, float]:
    """Containment of the PL bubble: share of (run, epoch) with ``|e_h| <= HPL`` and
    ``|e_u| <= VPL`` for errors ``err_enu_m`` (run, time, 3) [m] and PLs (time,) [m], over the
    epochs where a PL exists (finite); ``availability`` = share of epochs with a finite PL
    (both). NaN shares when no epoch has one."""
    e = np.asarray(err_enu_m, float)
    h = np.asarray(hpl_m, float).reshape(-1)
    v = np.asarray(vpl_m, float).reshape(-1)
    if e.ndim != 3 or e.shape[1:] != (h.size, 3) or v.shape != h.shape:
        raise InputError(f"err_enu_m must be (run, time, 3) and hpl_m, vpl_m (time,); got {e.shape}, {h.shape}, {v.shape}")
    av = np.isfinite(h) & np.isfinite(v)
    out = {"availability": float(np.mean(av)) if av.size else float("nan")}
    if not av.any():
        return out | {"containment_h": float("nan"), "containment_v": float("nan")}
    eh = np.hypot(e[:, av, 0], e[:, av, 1])
    ev = np.abs(e[:, av, 2])
    return out | {"containment_h": float(np.mean(eh <= h[av])), "containment_v": float(np.mean(ev <= v[av]))}
