"""Predicted navigation error along a trajectory: a GNSS/INS Kalman-filter covariance analysis
(seed 000 step III: "navigation error covariance is propagated ... exploiting GNSS pseudoranges
and inertial measurements in tightly coupled integration"; seed 001 footnote: only the
accelerometer figures enter this simplified propagation).

This is a **covariance analysis**: no measurements or trajectories are simulated.  The filter
is linear (the pseudorange Jacobian only needs the line-of-sight unit vectors of the visible
satellites, which the caller computes along the trajectory with the occlusion model), so the
covariance does not depend on the measured values and equals the one an EKF would carry.

Model (continuous time, ENU frame, 11 states)
---------------------------------------------
``x = [p (3) [m], v (3) [m/s], b (3) [m/s^2], c dt [m], c dt' [m/s]]``

* ``p' = v``; ``v' = -b + n_a``: the accelerometer is integrated in the navigation frame
  (attitude errors are not modelled, as in the seeds' simplified scheme), ``n_a`` white with
  PSD ``VRW^2`` [m^2/s^3] (velocity random walk [m/s/sqrt(h)] / 60);
* ``b' = -b / tau_b + n_b``: first-order Gauss-Markov accelerometer bias with steady-state
  sigma equal to the in-run bias stability [mg] and correlation time ``tau_b`` (PSD
  ``2 sigma_b^2 / tau_b``);
* receiver clock: ``(c dt)' = c dt' + n_f``, ``(c dt')' = n_g`` with the two-state clock model
  of Brown & Hwang (Introduction to Random Signals and Applied Kalman Filtering, 4th ed.,
  GPS receiver clock model):
  ``S_f = h0/2 c^2``, ``S_g = 2 pi^2 h_-2 c^2``; defaults for a TCXO ``h0 = 2e-19``,
  ``h_-2 = 2e-20`` (same source).

Discretisation is exact for each distinct epoch spacing (the Van Loan integrals, in closed
form for this model).  Pseudorange of a visible satellite: ``rho = |r_sat - p| + c dt + e``,
Jacobian row ``[-u, 0, 0, 1, 0]`` with ``u`` the unit line of sight receiver -> satellite
(ENU); ``e`` white with sigma ``gnss_sigma_m``.

UERE default: 3.0 m (1 sigma), a typical single-frequency GPS SPS user range error budget
(signal-in-space error < 1 m plus residual ionosphere after the broadcast model, troposphere,
multipath and receiver noise; the textbook budgets of Kaplan & Hegarty, Understanding GPS/GNSS,
3rd ed. 2017, and Misra & Enge, Global Positioning System, 2nd ed. 2006, are a few metres).
Give a per-satellite array to weight by elevation.

Limitation: the pseudorange errors are white, so with a static geometry the filter averages
them down (open sky steady state ~0.23 x UERE x PDOP at 1 Hz with the M300 IMU); real errors
(multipath, ionosphere) are correlated over minutes, so absolute values are optimistic while the
growth in occlusions and outages (what the planner compares) is driven by the IMU model.

Outputs (posterior covariance at each epoch, after that epoch's update):
``sigma_p_m = sqrt(P_EE + P_NN + P_UU)`` (3-D, the seeds' sigma_p), ``sigma_h_m =
sqrt(P_EE + P_NN)`` (horizontal), ``sigma_v_m = sqrt(P_UU)`` (vertical).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numba
import numpy as np
import scipy.linalg
import xarray as xr

from skyroute.stages.base import InputError
from skyroute.stages.vehicle import ImuSpec, VehicleProfile, load_vehicle

C_LIGHT = 299_792_458.0
DEFAULT_UERE_M = 3.0
TCXO_H0 = 2e-19
TCXO_HM2 = 2e-20
NX = 11
STATE_NAMES = ("p_e", "p_n", "p_u", "v_e", "v_n", "v_u", "b_e", "b_n", "b_u", "clock_bias", "clock_drift")


@dataclass(frozen=True)
class FilterState:
    """The navigation filter at one instant, to continue it (a tactical replan continues the
    filter the vehicle has, issue 22): posterior covariance ``P`` (11, 11) [SI units, state
    order :data:`STATE_NAMES`] at ``t_s`` [s], and ``t_update_s`` [s], the time of the last GNSS
    update at or before ``t_s`` (the update schedule continues from it)."""

    t_s: float
    P: np.ndarray
    t_update_s: float

    def __post_init__(self):
        P = np.asarray(self.P, float)
        if P.shape != (NX, NX) or not np.isfinite(P).all():
            raise InputError(f"FilterState.P must be a finite ({NX}, {NX}) covariance; got shape {P.shape}")
        if not (math.isfinite(self.t_s) and self.t_update_s <= self.t_s + 1e-9):
            raise InputError(f"FilterState: t_s = {self.t_s} must be finite and t_update_s = {self.t_update_s} "
                             "not later than it [s]")
        object.__setattr__(self, "P", P)

    @property
    def sigma_p_m(self) -> float:
        """3-D position sigma sqrt(P_EE + P_NN + P_UU) [m]."""
        return float(math.sqrt(self.P[0, 0] + self.P[1, 1] + self.P[2, 2]))


@dataclass(frozen=True)
class FilterTrack:
    """The filter along a flight: epochs ``t_s`` (m,) [s, increasing], posterior covariances
    ``P`` (m, 11, 11) and ``t_update_s`` (m,) [s] (last GNSS update at or before each epoch)."""

    t_s: np.ndarray
    P: np.ndarray
    t_update_s: np.ndarray

    def state_at(self, t_s: float) -> FilterState:
        """The state of the last epoch at or before ``t_s`` [s] (a run continued from it
        propagates to its own first epoch); InputError before the first epoch."""
        i = int(np.searchsorted(self.t_s, float(t_s) + 1e-9, side="right")) - 1
        if i < 0:
            raise InputError(f"the navigation filter track starts at t = {self.t_s[0]:.3f} s, after {t_s:.3f} s")
        return FilterState(float(self.t_s[i]), self.P[i], float(self.t_update_s[i]))

    @classmethod
    def from_dataset(cls, nav: xr.Dataset) -> FilterTrack:
        """From a :func:`navigation_error` result computed with ``return_covariance=True``."""
        if "P" not in nav or "t_update_s" not in nav:
            raise InputError("the navigation dataset has no covariance: compute it with return_covariance=True")
        return cls(np.asarray(nav["time"].values, float), np.asarray(nav["P"].values, float),
                   np.asarray(nav["t_update_s"].values, float))


def los_from_az_el(az_deg, el_deg) -> np.ndarray:
    """Unit line of sight receiver -> satellite in ENU (..., 3) from azimuth/elevation [deg]."""
    az, el = np.radians(np.asarray(az_deg, float)), np.radians(np.asarray(el_deg, float))
    return np.stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)], axis=-1)


def continuous_model(imu: ImuSpec, clock_h0: float = TCXO_H0, clock_hm2: float = TCXO_HM2
                     ) -> tuple[np.ndarray, np.ndarray]:
    """System matrix F (11,11) and white-noise spectral density matrix Qc (11,11)."""
    tau = imu.accel_bias_correlation_time_s
    F = np.zeros((NX, NX))
    Qc = np.zeros((NX, NX))
    for a in range(3):
        F[a, 3 + a] = 1.0
        F[3 + a, 6 + a] = -1.0
        F[6 + a, 6 + a] = -1.0 / tau
        Qc[3 + a, 3 + a] = imu.vrw_mps_per_sqrt_s**2
        Qc[6 + a, 6 + a] = 2.0 * imu.accel_bias_sigma_mps2**2 / tau
    F[9, 10] = 1.0
    Qc[9, 9] = clock_h0 / 2.0 * C_LIGHT**2
    Qc[10, 10] = 2.0 * np.pi**2 * clock_hm2 * C_LIGHT**2
    return F, Qc


def discretise(F: np.ndarray, Qc: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact transition matrix and process-noise covariance over ``dt_s`` (Van Loan 1978; for
    the model of :func:`continuous_model` with ``dt_s <= tau_b / 2`` the same integrals in
    closed form, :func:`_discretise_model`).  Results are memoised per (F, Qc, dt) (a bounded
    LRU: trajectories repeat their steps)."""
    F = np.ascontiguousarray(F, dtype=float)
    Qc = np.ascontiguousarray(Qc, dtype=float)
    phi, qd = _discretise_memo(F.tobytes(), Qc.tobytes(), F.shape[0], float(dt_s))
    return phi.copy(), qd.copy()


@functools.lru_cache(maxsize=4096)
def _discretise_memo(f_bytes: bytes, q_bytes: bytes, n: int, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    F = np.frombuffer(f_bytes).reshape(n, n)
    Qc = np.frombuffer(q_bytes).reshape(n, n)
    model = _model_scalars(F, Qc)
    if model is not None and 0.0 <= model[0] * dt_s <= 0.5:
        return _discretise_model(*model, dt_s)
    return _van_loan(F, Qc, dt_s)


def _van_loan(F: np.ndarray, Qc: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    n = F.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -F
    M[:n, n:] = Qc
    M[n:, n:] = F.T
    E = scipy.linalg.expm(M * dt_s)
    phi = E[n:, n:].T
    qd = phi @ E[:n, n:]
    return phi, 0.5 * (qd + qd.T)


def _model_scalars(F: np.ndarray, Qc: np.ndarray) -> tuple[float, float, float, float, float] | None:
    """``(1 / tau_b [1/s], S_v, S_b, S_f, S_g)`` when ``F``, ``Qc`` are exactly the matrices
    :func:`continuous_model` builds from them, else None."""
    if F.shape != (NX, NX) or Qc.shape != (NX, NX):
        return None
    a, qv, qb, qf, qg = -F[6, 6], Qc[3, 3], Qc[6, 6], Qc[9, 9], Qc[10, 10]
    if not (np.isfinite([a, qv, qb, qf, qg]).all() and a > 0):
        return None
    Ft = np.zeros((NX, NX))
    Qt = np.zeros((NX, NX))
    for i in range(3):
        Ft[i, 3 + i], Ft[3 + i, 6 + i], Ft[6 + i, 6 + i] = 1.0, -1.0, -a
        Qt[3 + i, 3 + i], Qt[6 + i, 6 + i] = qv, qb
    Ft[9, 10] = 1.0
    Qt[9, 9], Qt[10, 10] = qf, qg
    if not (np.array_equal(F, Ft) and np.array_equal(Qc, Qt)):
        return None
    return float(a), float(qv), float(qb), float(qf), float(qg)


_NTERMS = 24                                        # x^24 / 24! < 1e-31 for x <= 1/2
_FACT = np.array([math.factorial(k) for k in range(_NTERMS)], dtype=float)
_INV = 1.0 / np.arange(1, 2 * _NTERMS)


def _discretise_model(a: float, qv: float, qb: float, qf: float, qg: float, dt_s: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """``(phi, Q_d)`` over ``T = dt_s`` of :func:`continuous_model` (``a = 1 / tau_b``, PSDs
    ``qv`` velocity, ``qb`` bias, ``qf`` / ``qg`` clock), for ``a T <= 1/2``: the Van Loan
    integrals in closed form.  Per axis the bias column of ``phi(s)`` is ``g(s) = (g_p, g_v,
    e^{-a s})`` with ``g_v = -(1 - e^{-a s}) / a`` and ``g_p = int_0^s g_v``, each written as its
    (absolutely convergent, cancellation-free) power series in ``u = s / T``; ``Q_d = qv
    int (s, 1, 0)(s, 1, 0)^T ds + qb int g g^T ds`` (products of series, integrated term by
    term over ``[0, T]``); the clock is the two-state closed form (Brown & Hwang)."""
    T = float(dt_s)
    x = a * T
    pw = (-x) ** np.arange(_NTERMS)                 # (-x)^k
    ge = pw / _FACT                                 # e^{-a T u} = sum (-x)^k u^k / k!
    gv = np.zeros(_NTERMS)
    gv[1:] = -T * pw[:-1] / _FACT[1:]               # g_v(T u) = -T sum_{k>=1} (-x)^(k-1) u^k / k!
    gp = np.zeros(_NTERMS)
    gp[2:] = -T * T * pw[:-2] / _FACT[2:]           # g_p(T u) = -T^2 sum_{k>=2} (-x)^(k-2) u^k / k!
    g = (gp, gv, ge)
    qb_int = np.empty((3, 3))
    for i in range(3):
        for j in range(i, 3):                       # T int_0^1 g_i g_j du, smallest terms first
            qb_int[i, j] = qb_int[j, i] = T * float(np.sum((np.convolve(g[i], g[j]) * _INV)[::-1]))
    qv_int = np.array([[T**3 / 3.0, T**2 / 2.0, 0.0], [T**2 / 2.0, T, 0.0], [0.0, 0.0, 0.0]])
    blk = qv * qv_int + qb * qb_int
    col_b = (float(np.sum(gp[::-1])), float(np.sum(gv[::-1])), math.exp(-x))
    phi = np.zeros((NX, NX))
    qd = np.zeros((NX, NX))
    for ax in range(3):
        idx = (ax, 3 + ax, 6 + ax)
        phi[ax, ax] = phi[3 + ax, 3 + ax] = 1.0
        phi[ax, 3 + ax] = T
        for i in range(3):
            phi[idx[i], 6 + ax] = col_b[i]
            for j in range(3):
                qd[idx[i], idx[j]] = blk[i, j]
    phi[9, 9] = phi[10, 10] = 1.0
    phi[9, 10] = T
    qd[9, 9] = qf * T + qg * T**3 / 3.0
    qd[9, 10] = qd[10, 9] = qg * T**2 / 2.0
    qd[10, 10] = qg * T
    return phi, qd


@numba.njit(cache=True, nogil=True)
def propagate_covariance(P, phi, q, tmp):
    """P <- phi P phi^T + q, in place and symmetric (``tmp``: (n, n) scratch).  The one
    propagation of the filter covariance (this module's analysis and the Monte Carlo filters
    of :mod:`skyroute.stages.navsim`)."""
    n = P.shape[0]
    for r in range(n):                     # tmp = phi P
        for c in range(n):
            s = 0.0
            for k in range(n):
                s += phi[r, k] * P[k, c]
            tmp[r, c] = s
    for r in range(n):                     # P = tmp phi^T + Q
        for c in range(r, n):
            s = 0.0
            for k in range(n):
                s += tmp[r, k] * phi[c, k]
            s += q[r, c]
            P[r, c] = s
            P[c, r] = s


@numba.njit(cache=True, nogil=True)
def scalar_update(P, ue, un, uu, r_var, ph, gain):
    """Sequential scalar update of one pseudorange, h = [-u, 0, 0, 1 (clock), 0] with ``u``
    = (ue, un, uu) and variance ``r_var`` [m^2]: the Kalman gain into ``gain`` (n,) and
    P <- P - K h P in place (``ph``: (n,) scratch, P h^T on return)."""
    n = P.shape[0]
    for r in range(n):                     # ph = P h^T
        ph[r] = -P[r, 0] * ue - P[r, 1] * un - P[r, 2] * uu + P[r, 9]
    s = -ph[0] * ue - ph[1] * un - ph[2] * uu + ph[9] + r_var
    for r in range(n):
        gain[r] = ph[r] / s
    for r in range(n):
        for c in range(r, n):
            v = P[r, c] - gain[r] * ph[c]
            P[r, c] = v
            P[c, r] = v


@numba.njit(cache=True, nogil=True)
def _kf_kernel(phis, qds, step_idx, los, vis, r_var, do_update, p0, out):
    """Covariance recursion: propagate (epoch > 0), then sequential scalar pseudorange updates.
    out[i] = posterior covariance at epoch i."""
    m, nsat = vis.shape
    n = p0.shape[0]
    P = p0.copy()
    tmp = np.empty((n, n))
    ph = np.empty(n)
    gain = np.empty(n)
    for i in range(m):
        if i > 0:
            propagate_covariance(P, phis[step_idx[i]], qds[step_idx[i]], tmp)
        if do_update[i]:
            for j in range(nsat):
                if vis[i, j]:
                    scalar_update(P, los[i, j, 0], los[i, j, 1], los[i, j, 2], r_var[i, j], ph, gain)
        out[i] = P


def _as_imu(imu) -> ImuSpec:
    if isinstance(imu, ImuSpec):
        return imu
    if isinstance(imu, VehicleProfile):
        return imu.imu
    if isinstance(imu, dict):
        return ImuSpec.model_validate(imu)
    return load_vehicle(imu).imu


def resolve_imu(imu: ImuSpec | VehicleProfile | str | dict) -> ImuSpec:
    """The :class:`ImuSpec` of an ImuSpec, a VehicleProfile, a vehicle name or a dict of ImuSpec
    fields (the resolution :func:`navigation_error` applies to its ``imu`` argument)."""
    return _as_imu(imu)


def _validate(times_s, los_enu, visible, gnss_sigma_m):
    t = np.asarray(times_s, dtype=float).reshape(-1)
    los = np.asarray(los_enu, dtype=float)
    vis = np.asarray(visible)
    m = t.size
    if m == 0:
        raise InputError("times_s is empty; give at least one epoch [s]")
    if not np.isfinite(t).all() or (np.diff(t) <= 0).any():
        raise InputError("times_s must be finite and strictly increasing [s]")
    if los.ndim != 3 or los.shape[0] != m or los.shape[2] != 3:
        raise InputError(f"los_enu must have shape (m={m}, nsat, 3); got {los.shape}")
    if vis.shape != los.shape[:2] or vis.dtype != bool:
        raise InputError(f"visible must be a bool array of shape {los.shape[:2]}; got {vis.dtype} {vis.shape}")
    norms = np.linalg.norm(np.where(vis[..., None], los, 0.0), axis=-1)
    if (np.abs(norms[vis] - 1.0) > 1e-6).any() or not np.isfinite(norms).all():
        raise InputError("los_enu of visible satellites must be finite unit vectors (receiver -> satellite, ENU)")
    try:
        sig = np.broadcast_to(np.asarray(gnss_sigma_m, dtype=float), vis.shape)
    except ValueError as exc:
        raise InputError(f"gnss_sigma_m must be a scalar or broadcast to {vis.shape} [m]") from exc
    if not (np.isfinite(sig[vis]).all() and (sig[vis] > 0).all()):
        raise InputError("gnss_sigma_m must be finite and > 0 [m] for visible satellites")
    return t, np.ascontiguousarray(los), np.ascontiguousarray(vis), np.ascontiguousarray(sig**2)


def navigation_error(times_s, los_enu, visible, imu: ImuSpec | VehicleProfile | str | dict = "dji-m300-rtk",
                     gnss_sigma_m=DEFAULT_UERE_M, dt_s: float | None = None,
                     initial_sigma: tuple[float, float, float, float] = (10.0, 1.0, 300.0, 10.0),
                     clock_h0: float = TCXO_H0, clock_hm2: float = TCXO_HM2,
                     return_covariance: bool = False, initial_state: FilterState | None = None) -> xr.Dataset:
    """Predicted 1-sigma position error along a trajectory (covariance analysis, see module doc).

    Parameters
    ----------
    times_s : (m,) epochs [s], strictly increasing (any spacing).
    los_enu : (m, nsat, 3) unit line of sight receiver -> satellite in ENU at each epoch.
    visible : (m, nsat) bool, satellite in line of sight (above the mask, not occluded).
    imu : ImuSpec, a VehicleProfile, a vehicle name or a dict of ImuSpec fields.
    gnss_sigma_m : pseudorange (UERE) sigma [m], scalar or (m, nsat) array.
    dt_s : GNSS measurement period [s]; epochs closer than this to the last update are only
        propagated (default ``None``: update at every epoch).
    initial_sigma : prior sigmas (position [m], velocity [m/s], clock bias [m], clock drift [m/s]);
        the accelerometer bias starts at its steady-state sigma.
    return_covariance : also return the full covariance ``P`` (time, state, state2) and
        ``t_update_s`` (time) [s], the last update at or before each epoch
        (:meth:`FilterTrack.from_dataset`).
    initial_state : continue a filter (:class:`FilterState`) instead of starting from
        ``initial_sigma``: its covariance is propagated from ``initial_state.t_s`` to the first
        epoch (which may equal it), and the update schedule continues from
        ``initial_state.t_update_s``.

    Returns
    -------
    xarray.Dataset on dim ``time`` (coordinate ``times_s``): ``sigma_p_m`` (3-D),
    ``sigma_h_m`` (horizontal), ``sigma_v_m`` (vertical), ``sigma_bias_mps2`` (3-D accel bias),
    ``n_visible``, ``updated`` (a GNSS update happened at the epoch).
    """
    imu = _as_imu(imu)
    t, los, vis, r_var = _validate(times_s, los_enu, visible, gnss_sigma_m)
    if dt_s is not None and not dt_s > 0:
        raise InputError(f"dt_s must be > 0 [s] or None, got {dt_s}")
    if len(initial_sigma) != 4 or min(initial_sigma) <= 0:
        raise InputError("initial_sigma needs 4 positive values (position m, velocity m/s, clock m, clock m/s)")
    lead = 0                                   # a leading epoch at the initial state's time
    if initial_state is not None:
        dt0 = float(t[0]) - float(initial_state.t_s)
        if dt0 < -1e-9:
            raise InputError(f"the initial filter state (t = {initial_state.t_s:.3f} s) is later than the first epoch "
                             f"(t = {t[0]:.3f} s)")
        if dt0 > 1e-9:
            lead = 1
            t = np.concatenate([[float(initial_state.t_s)], t])
            los = np.concatenate([np.zeros((1,) + los.shape[1:]), los])
            vis = np.concatenate([np.zeros((1, vis.shape[1]), bool), vis])
            r_var = np.concatenate([np.ones((1, r_var.shape[1])), r_var])
    m = t.size
    F, Qc = continuous_model(imu, clock_h0, clock_hm2)
    steps = np.diff(t, prepend=t[0])
    keys = np.round(steps[1:], 9)
    uniq, inv = np.unique(keys, return_inverse=True) if m > 1 else (np.zeros(0), np.zeros(0, int))
    phis = np.empty((max(uniq.size, 1), NX, NX))
    qds = np.zeros_like(phis)
    phis[0] = np.eye(NX)
    for u, dt in enumerate(uniq):
        phis[u], qds[u] = discretise(F, Qc, float(dt))
    step_idx = np.concatenate([[0], inv]).astype(np.int64)
    last = -np.inf if initial_state is None else float(initial_state.t_update_s)
    do_update = np.zeros(m, bool)
    t_upd = np.empty(m)
    for i in range(m):
        if i < lead:
            pass                               # the initial state itself: already updated
        elif dt_s is None:
            do_update[i] = t[i] > last + 1e-9
        elif t[i] - last >= dt_s - 1e-9:
            do_update[i] = True
        if do_update[i]:
            last = t[i]
        t_upd[i] = last
    if initial_state is None:
        sp, sv, sc, sd = initial_sigma
        p0 = np.diag([sp**2] * 3 + [sv**2] * 3 + [imu.accel_bias_sigma_mps2**2] * 3 + [sc**2, sd**2])
    else:
        p0 = np.array(initial_state.P, float)
    out = np.empty((m, NX, NX))
    _kf_kernel(phis, qds, step_idx, los, vis, r_var, do_update, p0, out)
    if lead:
        t, los, vis, r_var, do_update, t_upd, out = (a[lead:] for a in (t, los, vis, r_var, do_update, t_upd, out))
    elif initial_state is not None and abs(float(initial_state.t_update_s) - float(t[0])) <= 1e-9:
        do_update = do_update.copy()
        do_update[0] = True          # the state is that epoch's posterior: its update happened before
    d = np.diagonal(out, axis1=1, axis2=2)
    coords = {"time": ("time", t, {"units": "s", "long_name": "epoch"})}
    data = {
        "sigma_p_m": ("time", np.sqrt(d[:, 0] + d[:, 1] + d[:, 2]),
                      {"units": "m", "long_name": "3-D position error sigma sqrt(tr P_pos)"}),
        "sigma_h_m": ("time", np.sqrt(d[:, 0] + d[:, 1]), {"units": "m", "long_name": "horizontal position error sigma"}),
        "sigma_v_m": ("time", np.sqrt(d[:, 2]), {"units": "m", "long_name": "vertical position error sigma"}),
        "sigma_bias_mps2": ("time", np.sqrt(d[:, 6] + d[:, 7] + d[:, 8]),
                            {"units": "m s-2", "long_name": "3-D accelerometer bias sigma"}),
        "n_visible": ("time", vis.sum(axis=1).astype(np.int32), {"units": "1", "long_name": "satellites in view"}),
        "updated": ("time", do_update, {"long_name": "GNSS update at this epoch"}),
    }
    if return_covariance:
        coords["state"] = ("state", list(STATE_NAMES))
        coords["state2"] = ("state2", list(STATE_NAMES))
        data["P"] = (("time", "state", "state2"), out, {"long_name": "posterior state covariance (SI units)"})
        data["t_update_s"] = ("time", t_upd, {"units": "s", "long_name": "last GNSS update at or before the epoch"})
    ds = xr.Dataset(data, coords=coords)
    ds.attrs.update(method="GNSS pseudorange / INS covariance analysis (no simulated measurements)",
                    gnss_sigma_m=float(np.mean(np.sqrt(r_var[vis]))) if vis.any() else float("nan"),
                    accel_bias_instability_mg=imu.accel_bias_instability_mg,
                    velocity_random_walk_mps_per_sqrt_h=imu.velocity_random_walk_mps_per_sqrt_h,
                    accel_bias_correlation_time_s=imu.accel_bias_correlation_time_s)
    return ds


__all__ = ["DEFAULT_UERE_M", "FilterState", "FilterTrack", "STATE_NAMES", "continuous_model", "discretise", "los_from_az_el", "propagate_covariance", "scalar_update",
           "navigation_error", "resolve_imu"]
