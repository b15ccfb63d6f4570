"""Monte Carlo GNSS/INS navigation simulation with line-of-sight aware filtering (seed 003
section III and Figs. 11-13: the *proposed* filter versus the *weak solution*).

:mod:`skyroute.stages.navigation` predicts the filter covariance only; this module simulates
the errors as well: many runs of one flight, each with its own IMU noise, clock noise and
pseudorange errors, and two extended Kalman filters per run fed with the same measurements:

* **proposed** (seed 003): uses only the satellites in line of sight according to the maps
  (``visible``), with ``R_i = mu_los * sigma_UERE^2 * DOP_visible`` (seed 003 eq. 26: R is the
  local DOP times a diagonal of proportionality coefficients ``mu_i``; here ``mu_i`` is made
  dimensionless by ``sigma_UERE^2``);
* **weak** (seed 003 section IV-B): every received satellite, including hidden ones received
  by reflection (NLOS), with ``R_i = mu_i * sigma_UERE^2 * DOP_all`` (the DOP of every
  satellite above the mask) and the larger ``mu_i = mu_nlos_weak`` for the hidden satellites.

Filter and truth model
----------------------
One model, one home: the 11-state model ``[p, v, accelerometer bias, c dt, c dt']`` (ENU,
[m, m/s, m/s^2, m, m/s]) and its exact discretisation come from
:func:`skyroute.stages.navigation.continuous_model` / :func:`~skyroute.stages.navigation.discretise`
(IMU figures of the vehicle profile: velocity random walk, bias instability as a first-order
Gauss-Markov bias with its correlation time; two-state TCXO clock).  The truth uses the same
model: the IMU measures the true specific force plus the Gauss-Markov bias plus white noise,
and the receiver clock follows the two-state model.  The inertial mechanisation integrates
the measured specific force in both the truth and the filters, so the known input cancels
exactly in the error ``e = x_true - x_hat`` and the error obeys
``e_k+1 = Phi e_k + w_k`` with ``w_k ~ N(0, Qd)`` (the error-state / complementary filter form,
Brown & Hwang, Introduction to Random Signals and Applied Kalman Filtering, 4th ed., ch. 8-9;
Groves, Principles of GNSS, Inertial and Multisensor Integrated Navigation Systems, 2nd ed.
2013, ch. 14).  Hence the kernel simulates the errors; the true trajectory ``xyz_m`` fixes
the sky geometry (the caller's line-of-sight vectors and visibility along it) and is kept in
the output for reconstruction (``estimate = xyz_true_m - err``).  Both filters of a run start
from the same estimate, drawn from the prior ``P0`` (so the prior is consistent).

Pseudorange of satellite ``j`` at epoch ``i``:
``rho = |s_ij - p_true| + c dt + eps_ij`` with ``s_ij = p_true + D u_ij`` (``u_ij`` the unit
line of sight receiver -> satellite of the sky dataset at the true position, ``D =
sat_range_m``, ~20,200 km for GPS).  The EKF predicts ``|s_ij - p_hat| + c dt_hat`` (the
nonlinear range about its own estimate) and uses the Jacobian ``[-u_ij, 0, 0, 1, 0]``: the
plane-wave approximation.  Its error is the change of direction of a satellite ~2e7 m away
across the position error, ``|e_p| / D`` (2.5e-6 rad for 50 m), i.e. a range error
``|e_p|^2 / (2 D)`` ~ 6e-5 m, negligible against any UERE.  With that Jacobian the
covariance of a filter does not depend on its estimate: the **proposed** filter (fixed
visibility per the maps, deterministic R) has one covariance for all runs, computed once
(its gains are reused by every run); the **weak** filter's covariance depends on the run
because which hidden satellites are received is random (``nlos_reception_prob``), so it is
carried per run (only ``sigma`` is stored).

Error model (:class:`NavsimParams`)
----------------------------------
* satellites in line of sight: ``eps ~ N(0, sigma_uere_m^2)``, white at the GNSS rate
  (3.0 m: the single-frequency GPS SPS user range error budget, Kaplan & Hegarty, Understanding
  GPS/GNSS, 3rd ed. 2017; Misra & Enge, Global Positioning System, 2nd ed. 2006, as
  :data:`skyroute.stages.navigation.DEFAULT_UERE_M`);
* satellites above the mask but hidden by the surface (NLOS): for each *pass* (a maximal run
  of consecutive epochs in which the satellite is hidden) and each Monte Carlo run, the
  signal is received by reflection with probability ``nlos_reception_prob`` (else not at
  all: no plausible reflector), with a positive bias ``b`` constant over the pass plus white
  noise of sigma ``nlos_noise_factor * sigma_uere_m``.  An NLOS signal always travels a
  longer path, so its ranging error is positive (Groves 2013, ch. 9, multipath and NLOS
  reception: NLOS errors are positive and typically tens of metres in urban canyons,
  unbounded in principle); for a single reflection on a vertical wall facing the satellite
  at horizontal distance ``d`` the extra path is ``2 d cos(el)`` (Hsu, "Analysis and
  modeling GPS NLOS effect in highly urbanized area", GPS Solutions 22:7, 2018), e.g. 15 m
  for d = 10 m at el = 40 deg, the default mean.  Seed 003 makes the same point for a canyon
  (the reflected signal travels at least half its width).  The bias distribution is
  ``"exponential"`` (default: the maximum-entropy law of a positive quantity with a given
  mean) or ``"half-normal"``, with mean ``nlos_bias_mean_m``.
* GNSS updates at ``gnss_rate_hz`` (1 Hz); between them the filters only propagate, so
  the output has the sigma and error at every epoch of ``t_s`` (e.g. 10 Hz).
* DOP scaling (seed 003 eq. 26): ``R_i = mu_i * sigma_uere_m^2 * DOP`` when
  ``scale_r_by_dop``; a DOP that is +inf (fewer than 4 satellites: no fix) is replaced by
  ``dop_cap``.  The Kalman filter already carries the geometry in H, so the DOP factor is a
  deliberate inflation (the seed's "reactive" bubble): with DOP > 1 the proposed filter
  over-bounds white line-of-sight errors.  ``scale_r_by_dop=False`` with ``mu_los = 1``
  gives the filter whose assumptions match the truth (used by the consistency tests).

Outputs: :func:`simulate` returns an ``xarray.Dataset`` (dims ``run``, ``time``, ``axis``);
:func:`containment`, :func:`proposed_beats_weak`, :func:`error_cdf` and
:func:`gaussian_containment` summarise it (seed 003 Figs. 11-13, eq. 27 with
``sigma = sqrt(P_EE + P_NN + P_UU)``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numba
import numpy as np
import scipy.special
import xarray as xr

from skyroute.stages import navigation as nav
from skyroute.stages.base import InputError
from skyroute.stages.dop import dop_table
from skyroute.stages.sboa import bubble_radius_m
from skyroute.stages.vehicle import ImuSpec, VehicleProfile

GPS_RANGE_M = 2.02e7
BIAS_DISTRIBUTIONS = ("exponential", "half-normal")
FILTERS = ("proposed", "weak")


@dataclass(frozen=True)
class NavsimParams:
    """Error model and filter tuning of the navigation Monte Carlo (see the module docstring
    for the sources).

    sigma_uere_m : line-of-sight pseudorange error sigma [m] (3.0, SPS UERE budget).
    nlos_bias_mean_m : mean of the positive multipath bias of a received NLOS pass [m] (15.0).
    nlos_bias_distribution : ``"exponential"`` (default) or ``"half-normal"``.
    nlos_noise_factor : NLOS white-noise sigma / ``sigma_uere_m`` (2.0; reflected signals are
        weaker, so noisier).
    nlos_reception_prob : probability that a hidden satellite's pass is received by reflection
        at all (0.7; 0 = hidden satellites are never received).
    gnss_rate_hz : pseudorange update rate [Hz] (1.0).
    mu_los : seed 003 eq. 26 coefficient of line-of-sight satellites (both filters) (1.0).
    mu_nlos_weak : the weak filter's larger coefficient for hidden satellites (10.0; seed 003
        gives no value, only "higher"; 10 de-weights them to an effective sigma of ~9.5 m).
    scale_r_by_dop : multiply R by the local DOP (seed 003 eq. 26) (True).
    dop_cap : DOP used for R where it is +inf (fewer than 4 satellites) (10.0).
    sat_range_m : nominal receiver-satellite range for the nonlinear pseudorange [m] (2.02e7).
    initial_sigma : prior sigmas (position [m], velocity [m/s], clock bias [m], clock drift
        [m/s]), the accelerometer bias starting at its steady state (as navigation.py).
    clock_h0, clock_hm2 : Allan-variance coefficients of the receiver clock (TCXO, as
        navigation.py).
    """

    sigma_uere_m: float = nav.DEFAULT_UERE_M
    nlos_bias_mean_m: float = 15.0
    nlos_bias_distribution: str = "exponential"
    nlos_noise_factor: float = 2.0
    nlos_reception_prob: float = 0.7
    gnss_rate_hz: float = 1.0
    mu_los: float = 1.0
    mu_nlos_weak: float = 10.0
    scale_r_by_dop: bool = True
    dop_cap: float = 10.0
    sat_range_m: float = GPS_RANGE_M
    initial_sigma: tuple[float, float, float, float] = (10.0, 1.0, 300.0, 10.0)
    clock_h0: float = nav.TCXO_H0
    clock_hm2: float = nav.TCXO_HM2

    def __post_init__(self) -> None:
        positive = ("sigma_uere_m", "nlos_noise_factor", "gnss_rate_hz", "mu_los", "mu_nlos_weak",
                    "dop_cap", "sat_range_m", "clock_h0", "clock_hm2")
        for name in positive:
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"navsim parameter {name} = {v} must be a finite number > 0")
        if not (np.isfinite(self.nlos_bias_mean_m) and self.nlos_bias_mean_m >= 0):
            raise InputError(f"nlos_bias_mean_m = {self.nlos_bias_mean_m} m must be >= 0")
        if not 0.0 <= self.nlos_reception_prob <= 1.0:
            raise InputError(f"nlos_reception_prob = {self.nlos_reception_prob} must be in [0, 1]")
        if self.nlos_bias_distribution not in BIAS_DISTRIBUTIONS:
            raise InputError(f"nlos_bias_distribution {self.nlos_bias_distribution!r} unknown; "
                             f"use one of {BIAS_DISTRIBUTIONS}")
        if len(self.initial_sigma) != 4 or not all(np.isfinite(s) and s > 0 for s in self.initial_sigma):
            raise InputError("initial_sigma needs 4 positive values (position m, velocity m/s, clock m, clock m/s)")


# --------------------------------------------------------------------------------------------
# kernels
# --------------------------------------------------------------------------------------------

@numba.njit(cache=True, nogil=True)
def _gain_kernel(phis, qds, step_idx, los, used, r_var, do_update, p0, gains, ppos, sigma):
    """Deterministic covariance pass: gains (m, nsat, 11) of the sequential scalar updates of
    the used satellites, posterior position covariance ppos (m, 3, 3) and sigma (m,)."""
    m, nsat = used.shape
    n = p0.shape[0]
    P = p0.copy()
    tmp = np.empty((n, n))
    ph = np.empty(n)
    for i in range(m):
        if i > 0:
            nav.propagate_covariance(P, phis[step_idx[i]], qds[step_idx[i]], tmp)
        if do_update[i]:
            for j in range(nsat):
                if used[i, j]:
                    nav.scalar_update(P, los[i, j, 0], los[i, j, 1], los[i, j, 2], r_var[i, j], ph, gains[i, j])
        for a in range(3):
            for b in range(3):
                ppos[i, a, b] = P[a, b]
        sigma[i] = math.sqrt(P[0, 0] + P[1, 1] + P[2, 2])


@numba.njit(cache=True, nogil=True, inline="always")
def _residual(e, ue, un, uu, eps, rng_m):
    """z - h(x_hat) for the error e = x_true - x_hat: e_clock + eps + D - |D u + e_p|
    (written without cancellation)."""
    dx = rng_m * ue + e[0]
    dy = rng_m * un + e[1]
    dz = rng_m * uu + e[2]
    dist = math.sqrt(dx * dx + dy * dy + dz * dz)
    ee = e[0] * e[0] + e[1] * e[1] + e[2] * e[2]
    return e[9] + eps - (2.0 * rng_m * (ue * e[0] + un * e[1] + uu * e[2]) + ee) / (rng_m + dist)


@numba.njit(cache=True, nogil=True)
def _matvec(a, x, out):
    n = x.shape[0]
    for r in range(n):
        s = 0.0
        for k in range(n):
            s += a[r, k] * x[k]
        out[r] = s


@numba.njit(cache=True, nogil=True)
def _run(seed, phis, qds, qchols, step_idx, do_update, los, vis, recv, pass_id, rec_draw, bias_draw,
         sig_los, sig_nlos, rng_m, p0, p0chol, gains, r_weak, err_p, err_w, sig_w, n_nlos):
    """One Monte Carlo run: truth error draws and both filters (proposed with the shared
    gains, weak with its own covariance).  Writes this run's rows of the outputs."""
    np.random.seed(seed)
    m, nsat = vis.shape
    n = p0.shape[0]
    z = np.empty(n)
    w = np.empty(n)
    tmp = np.empty(n)
    ep = np.empty(n)
    P = p0.copy()
    ptmp = np.empty((n, n))
    ph = np.empty(n)
    kw = np.empty(n)
    for k in range(n):
        z[k] = np.random.standard_normal()
    _matvec(p0chol, z, ep)
    ew = ep.copy()
    for i in range(m):
        if i > 0:
            s_i = step_idx[i]
            for k in range(n):
                z[k] = np.random.standard_normal()
            _matvec(qchols[s_i], z, w)
            _matvec(phis[s_i], ep, tmp)
            for k in range(n):
                ep[k] = tmp[k] + w[k]
            _matvec(phis[s_i], ew, tmp)
            for k in range(n):
                ew[k] = tmp[k] + w[k]
            nav.propagate_covariance(P, phis[s_i], qds[s_i], ptmp)
        used_nlos = 0
        if do_update[i]:
            for j in range(nsat):
                if not recv[i, j]:
                    continue
                ue, un, uu = los[i, j, 0], los[i, j, 1], los[i, j, 2]
                if vis[i, j]:
                    eps = sig_los * np.random.standard_normal()
                    res = _residual(ep, ue, un, uu, eps, rng_m)
                    for k in range(n):
                        ep[k] -= gains[i, j, k] * res
                else:
                    pid = pass_id[i, j]
                    if not rec_draw[pid]:
                        continue
                    eps = bias_draw[pid] + sig_nlos * np.random.standard_normal()
                    used_nlos += 1
                res = _residual(ew, ue, un, uu, eps, rng_m)
                nav.scalar_update(P, ue, un, uu, r_weak[i, j], ph, kw)
                for k in range(n):
                    ew[k] -= kw[k] * res
        for a in range(3):
            err_p[i, a] = ep[a]
            err_w[i, a] = ew[a]
        sig_w[i] = math.sqrt(P[0, 0] + P[1, 1] + P[2, 2])
        n_nlos[i] = used_nlos


@numba.njit(cache=True, parallel=True)
def _mc_kernel(seeds, phis, qds, qchols, step_idx, do_update, los, vis, recv, pass_id, rec_draw,
               bias_draw, sig_los, sig_nlos, rng_m, p0, p0chol, gains, r_weak, err_p, err_w, sig_w,
               n_nlos):
    """All runs (prange).  Each run reseeds its thread's generator, so the numbers do not
    depend on the thread count or schedule."""
    for r in numba.prange(seeds.shape[0]):
        _run(seeds[r], phis, qds, qchols, step_idx, do_update, los, vis, recv, pass_id, rec_draw[r],
             bias_draw[r], sig_los, sig_nlos, rng_m, p0, p0chol, gains, r_weak, err_p[r], err_w[r],
             sig_w[r], n_nlos[r])


# --------------------------------------------------------------------------------------------
# numpy
# --------------------------------------------------------------------------------------------

def pdop_of(los_enu: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """PDOP (m,) of the satellites of ``mask`` (m, nsat) with unit lines of sight ``los_enu``
    (m, nsat, 3) ENU (seed 003 eq. 16 with unit UERE; +inf = fewer than 4 or singular),
    computed by :func:`skyroute.stages.dop.dop_table`."""
    los = np.asarray(los_enu, dtype=float)
    el = np.degrees(np.arcsin(np.clip(los[..., 2], -1.0, 1.0)))
    az = np.degrees(np.arctan2(los[..., 0], los[..., 1]))
    return dop_table(np.where(mask, az, np.nan), np.where(mask, el, np.nan))[..., 1]


def flight_geometry(problem, sky: xr.Dataset, surface_2d, t_s, xyz_m, start_time_utc,
                    cache: dict | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inputs of :func:`simulate` along a flight: ``(los_enu (m, nsat, 3), visible (m, nsat),
    received_ok (m, nsat))`` of the satellites of ``sky``
    (:func:`skyroute.stages.almanac.sky_geometry`) at samples ``xyz_m`` (m, 3) [m] in the map
    frame of ``problem.grid`` at mission times ``t_s`` [s] (UTC of time 0: ``start_time_utc``).
    Line of sight and occlusion by the surface heights ``surface_2d`` come from
    :func:`skyroute.stages.planning.step3.line_of_sight` (nearest sky epoch, exact visibility
    heights); ``received_ok`` is the sky's ``above_mask`` at the same epoch (above the
    elevation mask, visible or hidden).  ``cache``: as for ``line_of_sight``."""
    from skyroute.stages.sky_visibility import line_of_sight, sky_times_s

    if "above_mask" not in sky:
        raise InputError("sky dataset lacks 'above_mask': build it with skyroute.stages.almanac.sky_geometry")
    los, vis = line_of_sight(problem, sky, surface_2d, t_s, xyz_m, start_time_utc, cache=cache)
    ts = sky_times_s(sky, start_time_utc)
    t = np.asarray(t_s, dtype=float).reshape(-1)
    if ts.size > 1:                                   # nearest epoch, the rule of line_of_sight
        ep = np.clip(np.searchsorted(ts, t), 1, ts.size - 1)
        ep = np.where(np.abs(ts[ep - 1] - t) <= np.abs(ts[ep] - t), ep - 1, ep)
    else:
        ep = np.zeros(t.size, int)
    el = np.asarray(sky["el_deg"].transpose("time", "sat").values, float)
    az = np.asarray(sky["az_deg"].transpose("time", "sat").values, float)
    up = np.asarray(sky["above_mask"].transpose("time", "sat").values, bool)
    up = (up & np.isfinite(el) & (el > 0) & np.isfinite(az))[ep]
    return los, vis & up, up


def _pass_ids(hidden: np.ndarray) -> tuple[np.ndarray, int]:
    """Label each maximal run of consecutive hidden epochs of each satellite (-1 elsewhere)."""
    m, nsat = hidden.shape
    ids = np.full((m, nsat), -1, dtype=np.int64)
    offset = 0
    for j in range(nsat):
        h = hidden[:, j]
        starts = h & ~np.concatenate([[False], h[:-1]])
        lab = np.cumsum(starts) - 1 + offset
        ids[:, j] = np.where(h, lab, -1)
        offset += int(starts.sum())
    return ids, offset


def _draw_nlos(rng: np.random.Generator, params: NavsimParams, shape: tuple[int, ...]
               ) -> tuple[np.ndarray, np.ndarray]:
    """Per (run, NLOS pass): received by reflection (bool) and its positive bias [m] (mean
    ``nlos_bias_mean_m``; half-normal scale = mean * sqrt(pi / 2))."""
    received = rng.random(shape) < params.nlos_reception_prob
    if params.nlos_bias_distribution == "exponential":
        bias = rng.exponential(params.nlos_bias_mean_m, shape)
    else:
        bias = np.abs(rng.standard_normal(shape)) * params.nlos_bias_mean_m * math.sqrt(math.pi / 2)
    return received, bias


def _update_epochs(t: np.ndarray, rate_hz: float) -> np.ndarray:
    period = 1.0 / rate_hz
    do = np.zeros(t.size, bool)
    last = -np.inf
    for i in range(t.size):
        if t[i] - last >= period - 1e-9:
            do[i] = True
            last = t[i]
    return do


def _sqrtm_psd(a: np.ndarray) -> np.ndarray:
    """A factor L with L L^T = a for a symmetric positive semi-definite a."""
    lam, vec = np.linalg.eigh(0.5 * (a + a.T))
    return vec * np.sqrt(np.clip(lam, 0.0, None))


def _validate(t_s, xyz_m, los_enu, visible, received_ok, dop, dop_all):
    t = np.asarray(t_s, dtype=float).reshape(-1)
    m = t.size
    if m == 0:
        raise InputError("t_s is empty; give at least one epoch [s]")
    if not np.isfinite(t).all() or (np.diff(t) <= 0).any():
        raise InputError("t_s must be finite and strictly increasing [s]")
    xyz = np.asarray(xyz_m, dtype=float)
    if xyz.shape != (m, 3) or not np.isfinite(xyz).all():
        raise InputError(f"xyz_m must be a finite (m={m}, 3) true trajectory [m]; got shape {xyz.shape}")
    los = np.asarray(los_enu, dtype=float)
    if los.ndim != 3 or los.shape[0] != m or los.shape[2] != 3:
        raise InputError(f"los_enu must have shape (m={m}, nsat, 3); got {los.shape}")
    vis = np.asarray(visible)
    recv = np.asarray(received_ok)
    for name, a in (("visible", vis), ("received_ok", recv)):
        if a.shape != los.shape[:2] or a.dtype != bool:
            raise InputError(f"{name} must be a bool array of shape {los.shape[:2]}; got {a.dtype} {a.shape}")
    if (vis & ~recv).any():
        raise InputError("a satellite is visible but not above the mask (visible must imply received_ok); "
                         "pass visible & received_ok")
    norms = np.linalg.norm(np.where(recv[..., None], los, 0.0), axis=-1)
    if not np.isfinite(norms).all() or (np.abs(norms[recv] - 1.0) > 1e-6).any():
        raise InputError("los_enu of satellites above the mask must be finite unit vectors (receiver -> satellite, ENU)")
    out = []
    for name, d, mask in (("dop", dop, vis), ("dop_all", dop_all, recv)):
        if d is None:
            d = pdop_of(los, mask)
        d = np.asarray(d, dtype=float).reshape(-1)
        if d.shape != (m,) or np.isnan(d).any() or (d <= 0).any():
            raise InputError(f"{name} must be (m={m},) positive DOPs (+inf = no fix); got shape {d.shape}")
        out.append(d)
    return t, xyz, np.ascontiguousarray(los), np.ascontiguousarray(vis), np.ascontiguousarray(recv), out[0], out[1]


def simulate(t_s, xyz_m, los_enu, visible, received_ok, dop=None, params: NavsimParams | None = None,
             imu: ImuSpec | VehicleProfile | str | dict = "dji-m300-rtk", runs: int = 100, seed: int = 0,
             dop_all=None) -> xr.Dataset:
    """Monte Carlo of the proposed and weak GNSS/INS EKFs along one flight (module docstring).

    Parameters
    ----------
    t_s : (m,) epochs [s], strictly increasing (e.g. 10 Hz); GNSS updates at ``params.gnss_rate_hz``.
    xyz_m : (m, 3) true trajectory [m] in the map frame (~ENU).
    los_enu : (m, nsat, 3) unit line of sight receiver -> satellite (ENU) at the true position.
    visible : (m, nsat) bool, in line of sight per the maps (above the mask and not occluded).
    received_ok : (m, nsat) bool, above the elevation mask (visible or hidden by the surface).
    dop : (m,) local DOP of the visible satellites (proposed filter's R; default: their PDOP).
    params : :class:`NavsimParams` (default ``NavsimParams()``).
    imu : ImuSpec, VehicleProfile, vehicle name or dict of ImuSpec fields.
    runs : number of Monte Carlo runs (>= 1).
    seed : seed of all random draws (same seed, same numbers, any thread count).
    dop_all : (m,) DOP of every satellite above the mask (weak filter's R; default: their PDOP).

    Returns
    -------
    xarray.Dataset, dims ``run``, ``time``, ``axis`` (e, n, u), ``axis2``:
    ``err_proposed_m``, ``err_weak_m`` (run, time, axis) true minus estimated position [m];
    ``sigma_proposed_m`` (time) and ``sigma_weak_m`` (run, time) = sqrt(P_EE + P_NN + P_UU) [m];
    ``P_pos_proposed_m2`` (time, axis, axis2); ``n_visible``, ``n_received`` (time);
    ``n_nlos_used`` (run, time) hidden satellites the weak filter used (0 between updates);
    ``dop_visible``, ``dop_all``, ``updated`` (time); ``xyz_true_m`` (time, axis).
    """
    params = NavsimParams() if params is None else params
    if not isinstance(params, NavsimParams):
        raise InputError(f"params must be a NavsimParams, got {type(params).__name__}")
    runs = int(runs)
    if runs < 1:
        raise InputError(f"runs = {runs} must be >= 1")
    imu = nav.resolve_imu(imu)
    t, xyz, los, vis, recv, dop_v, dop_a = _validate(t_s, xyz_m, los_enu, visible, received_ok, dop, dop_all)
    m, nsat = vis.shape

    F, Qc = nav.continuous_model(imu, params.clock_h0, params.clock_hm2)
    steps = np.round(np.diff(t), 9)
    uniq, inv = np.unique(steps, return_inverse=True) if m > 1 else (np.zeros(0), np.zeros(0, np.int64))
    nu = max(uniq.size, 1)
    phis = np.tile(np.eye(nav.NX), (nu, 1, 1))
    qds = np.zeros((nu, nav.NX, nav.NX))
    for u, dt in enumerate(uniq):
        phis[u], qds[u] = nav.discretise(F, Qc, float(dt))
    qchols = np.stack([_sqrtm_psd(q) for q in qds])
    step_idx = np.concatenate([[0], inv]).astype(np.int64)
    do_update = _update_epochs(t, params.gnss_rate_hz)

    sp, sv, sc, sd = params.initial_sigma
    p0 = np.diag([sp**2] * 3 + [sv**2] * 3 + [imu.accel_bias_sigma_mps2**2] * 3 + [sc**2, sd**2])
    p0chol = np.sqrt(p0)

    def r_scale(d):
        return np.where(np.isfinite(d), d, params.dop_cap) if params.scale_r_by_dop else np.ones_like(d)

    var = params.sigma_uere_m**2
    r_prop = np.ascontiguousarray(np.broadcast_to((params.mu_los * var * r_scale(dop_v))[:, None], (m, nsat)))
    mu_w = np.where(vis, params.mu_los, params.mu_nlos_weak)
    r_weak = np.ascontiguousarray(mu_w * var * r_scale(dop_a)[:, None])

    gains = np.zeros((m, nsat, nav.NX))
    ppos = np.empty((m, 3, 3))
    sig_p = np.empty(m)
    _gain_kernel(phis, qds, step_idx, los, vis, r_prop, do_update, p0, gains, ppos, sig_p)

    pass_id, npass = _pass_ids(recv & ~vis)
    rng = np.random.default_rng(seed)
    seeds = rng.integers(0, 2**31 - 1, size=runs, dtype=np.int64)
    rec_draw, bias = _draw_nlos(rng, params, (runs, max(npass, 1)))

    err_p = np.empty((runs, m, 3))
    err_w = np.empty((runs, m, 3))
    sig_w = np.empty((runs, m))
    n_nlos = np.zeros((runs, m), np.int16)
    _mc_kernel(seeds, phis, qds, qchols, step_idx, do_update, los, vis, recv, pass_id, rec_draw, bias,
               params.sigma_uere_m, params.nlos_noise_factor * params.sigma_uere_m, params.sat_range_m,
               p0, p0chol, gains, r_weak, err_p, err_w, sig_w, n_nlos)

    axis = ["e", "n", "u"]
    coords = {"run": ("run", np.arange(runs)), "time": ("time", t, {"units": "s", "long_name": "epoch"}),
              "axis": ("axis", axis), "axis2": ("axis2", axis)}
    data = {
        "err_proposed_m": (("run", "time", "axis"), err_p,
                           {"units": "m", "long_name": "true minus estimated position, proposed filter"}),
        "err_weak_m": (("run", "time", "axis"), err_w,
                       {"units": "m", "long_name": "true minus estimated position, weak filter"}),
        "sigma_proposed_m": ("time", sig_p, {"units": "m", "long_name": "sqrt(tr P_pos), proposed filter"}),
        "sigma_weak_m": (("run", "time"), sig_w, {"units": "m", "long_name": "sqrt(tr P_pos), weak filter"}),
        "P_pos_proposed_m2": (("time", "axis", "axis2"), ppos,
                              {"units": "m2", "long_name": "position covariance, proposed filter"}),
        "n_visible": ("time", vis.sum(1).astype(np.int16), {"units": "1", "long_name": "satellites in line of sight"}),
        "n_received": ("time", recv.sum(1).astype(np.int16), {"units": "1", "long_name": "satellites above the mask"}),
        "n_nlos_used": (("run", "time"), n_nlos, {"units": "1", "long_name": "hidden satellites used by the weak filter"}),
        "dop_visible": ("time", dop_v, {"units": "1", "long_name": "DOP of the visible satellites (+inf = no fix)"}),
        "dop_all": ("time", dop_a, {"units": "1", "long_name": "DOP of the satellites above the mask"}),
        "updated": ("time", do_update, {"long_name": "GNSS update at this epoch"}),
        "xyz_true_m": (("time", "axis"), xyz, {"units": "m", "long_name": "true position (map frame)"}),
    }
    ds = xr.Dataset(data, coords=coords)
    attrs = {k: (list(v) if isinstance(v, tuple) else (int(v) if isinstance(v, bool) else v))
             for k, v in dataclasses.asdict(params).items()}
    ds.attrs.update(attrs)
    ds.attrs.update(method="Monte Carlo GNSS pseudorange / INS EKFs (seed 003 proposed and weak solutions)",
                    runs=runs, seed=int(seed), n_nlos_passes=npass,
                    accel_bias_instability_mg=imu.accel_bias_instability_mg,
                    velocity_random_walk_mps_per_sqrt_h=imu.velocity_random_walk_mps_per_sqrt_h,
                    accel_bias_correlation_time_s=imu.accel_bias_correlation_time_s)
    return ds


# --------------------------------------------------------------------------------------------
# summaries
# --------------------------------------------------------------------------------------------

def _norms(ds: xr.Dataset, updated_only: bool) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    sel = ds.updated.values if updated_only else np.ones(ds.sizes["time"], bool)
    out = {}
    for f in FILTERS:
        e = np.linalg.norm(ds[f"err_{f}_m"].values[:, sel], axis=-1)
        s = np.broadcast_to(ds[f"sigma_{f}_m"].values[..., sel], e.shape)
        out[f] = (e, s)
    return out


def containment(ds: xr.Dataset, k=(1, 2, 3), updated_only: bool = False) -> dict[str, dict[str, float]]:
    """Share over runs and epochs of ``|error| <= k sigma`` (seed 003 eq. 27 bubble radius
    ``k sqrt(tr P_pos)``) per filter: ``{"proposed": {"1sigma": f, ...}, "weak": {...}}``,
    fractions in [0, 1].  ``updated_only``: only epochs with a GNSS update."""
    res: dict[str, dict[str, float]] = {}
    for f, (e, s) in _norms(ds, updated_only).items():
        res[f] = {f"{kk:g}sigma": float(np.mean(e <= kk * s)) for kk in k}
    return res


def proposed_beats_weak(ds: xr.Dataset, updated_only: bool = False) -> float:
    """Share of (run, epoch) where the proposed 3-D error is smaller than the weak one (seed
    003 Fig. 13: 63 % of the time)."""
    n = _norms(ds, updated_only)
    return float(np.mean(n["proposed"][0] < n["weak"][0]))


def error_cdf(ds: xr.Dataset, errors_m=None, updated_only: bool = False) -> xr.Dataset:
    """Empirical CDF of the 3-D position error [m] over runs and epochs, per filter, on the
    grid ``errors_m`` (default: 200 points from 0 to the largest error).  Variables
    ``cdf_proposed``, ``cdf_weak`` on dim ``error_m``."""
    n = _norms(ds, updated_only)
    if errors_m is None:
        top = max(float(n[f][0].max()) for f in FILTERS)
        errors_m = np.linspace(0.0, top if top > 0 else 1.0, 200)
    grid = np.asarray(errors_m, dtype=float).reshape(-1)
    if grid.size == 0 or not np.isfinite(grid).all():
        raise InputError("errors_m must be a non-empty array of finite errors [m]")
    data = {}
    for f in FILTERS:
        srt = np.sort(n[f][0].ravel())
        data[f"cdf_{f}"] = ("error_m", np.searchsorted(srt, grid, side="right") / srt.size,
                            {"units": "1", "long_name": f"P(|error| <= x), {f} filter"})
    return xr.Dataset(data, coords={"error_m": ("error_m", grid, {"units": "m"})})


def gaussian_containment(cov_m2, k: float = 3.0, nodes: int = 48) -> np.ndarray:
    """``P(|e| <= k sqrt(tr C))`` for ``e ~ N(0, C)`` with ``C`` (..., 3, 3) [m^2]: the
    containment of a consistent filter's spherical bubble (seed 003 eq. 27).

    With ``C = V diag(lam) V^T``, ``e = V sqrt(lam) z``, ``z = r d`` with ``r^2 ~ chi2(3)``
    independent of the uniform direction ``d``, so
    ``P = E_d[ F_chi2(3)(k^2 tr C / sum_i lam_i d_i^2) ]``, a smooth integral over the sphere
    (one octant by symmetry) done by Gauss-Legendre quadrature in ``cos(theta)`` and ``phi``
    with ``nodes`` points each (error < 1e-9 for eigenvalue ratios up to 1e3).  Isotropic C
    gives ``chi2(3).cdf(3 k^2)`` (0.99999 for k = 3: the per-axis ``|e_i| <= 3 sigma_i`` is
    a different, looser bubble)."""
    c = np.asarray(cov_m2, dtype=float)
    if c.ndim < 2 or c.shape[-2:] != (3, 3):
        raise InputError(f"cov_m2 must be (..., 3, 3) [m^2], got {c.shape}")
    lam = np.clip(np.linalg.eigvalsh(0.5 * (c + np.swapaxes(c, -1, -2))), 0.0, None)
    tr = lam.sum(-1, keepdims=True)
    w = np.where(tr > 0, lam / np.where(tr > 0, tr, 1.0), 1.0 / 3.0)      # (..., 3), sums to 1
    x, wx = np.polynomial.legendre.leggauss(int(nodes))
    mu, wmu = 0.5 * (x + 1.0), 0.5 * wx                                  # cos(theta) in [0, 1]
    phi, wphi = 0.25 * np.pi * (x + 1.0), 0.5 * wx                      # phi in [0, pi/2], weights / (pi/2)
    st = np.sqrt(1.0 - mu**2)[:, None]
    d2 = np.stack([(st * np.cos(phi)) ** 2, (st * np.sin(phi)) ** 2,
                   np.broadcast_to(mu[:, None] ** 2, (mu.size, phi.size))], axis=-1)   # (n, n, 3)
    q = np.einsum("...k,ijk->...ij", w, d2)
    y = float(k) ** 2 / np.maximum(q, 1e-300)
    cdf = scipy.special.gammainc(1.5, 0.5 * y)                           # chi2(3) cdf
    return np.einsum("...ij,i,j->...", cdf, wmu, wphi)


__all__ = ["BIAS_DISTRIBUTIONS", "FILTERS", "GPS_RANGE_M", "NavsimParams", "bubble_radius_m", "containment", "error_cdf",
           "flight_geometry", "gaussian_containment", "pdop_of", "proposed_beats_weak", "simulate"]


