"""Detect-and-avoid style alerting of the tactical replay (issue 22 item 3).

Alert levels as RTCA DO-365B defines them for the DAA well-clear (Phase I, the thresholds of
NASA DAIDALUS' ``DO_365B_no_SUM`` configuration): a **preventive** alert when the aircraft are
predicted to enter the larger preventive volume within 55 s, **corrective** when a loss of
well clear is predicted within 55 s, a **warning** within 25 s.  DO-365's volumes are cylinders
(DTHR 0.66 nmi horizontally; ZTHR 450 ft, and 700 ft for the preventive alert) around manned
aircraft; skyroute's separation is the sphere ``S = r_p + r_i + d_c`` of the strategic and
tactical planners, so the volumes are scaled to it: loss of separation = closer than ``S``
(corrective, warning), preventive volume = closer than ``(700 / 450) S`` (the ratio of the two
ZTHR).  The times are DO-365's (the ASTM F3442 sUAS well clear keeps a spatial-only volume, as
here: no tau threshold).

Two predictions feed the levels:

* **intent-based** (the replay, at every conflict it finds): the ownship's current plan against
  the intruder's believed (declared) track: ``t_los`` = first time closer than S, ``t_pre`` = first
  time closer than 1.556 S, both from the moment the conflict is known;
* **state-based** (:func:`daa_series`, what a DAA display shows): straight-line extrapolation of
  both aircraft's current positions and velocities (flown trajectory, intruder truth), every
  ``step_s`` of the flight, for every intruder the ownship knows of.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["ALERT_LEVELS", "CORRECTIVE_S", "PREVENTIVE_FACTOR", "PREVENTIVE_S", "WARNING_S", "alert_of",
           "daa_series", "sphere_entry_time"]

PREVENTIVE_S = 55.0                 # [s] DO-365B alert 1 (preventive) alerting time
CORRECTIVE_S = 55.0                 # [s] alert 2 (corrective)
WARNING_S = 25.0                    # [s] alert 3 (warning)
PREVENTIVE_FACTOR = 700.0 / 450.0   # preventive / corrective ZTHR: the preventive volume's scale
ALERT_LEVELS = ("none", "preventive", "corrective", "warning")


def alert_of(t_los_s: float, t_pre_s: float = math.inf) -> str:
    """The alert level from the predicted time to loss of separation ``t_los_s`` [s] and the
    time to enter the preventive volume ``t_pre_s`` [s] (``inf``: never; 0: already inside)."""
    if t_los_s <= WARNING_S:
        return "warning"
    if t_los_s <= CORRECTIVE_S:
        return "corrective"
    if t_pre_s <= PREVENTIVE_S:
        return "preventive"
    return "none"


def sphere_entry_time(dp, dv, radius_m: float, lookahead_s: float = math.inf) -> float:
    """First time t in [0, lookahead] [s] with |dp + dv t| < radius (straight lines, closed
    form; 0 when already inside, inf when never)."""
    dp = np.asarray(dp, float)
    dv = np.asarray(dv, float)
    c = float(dp @ dp) - radius_m * radius_m
    if c < 0.0:
        return 0.0
    a = float(dv @ dv)
    b = float(dp @ dv)
    if a <= 0.0 or b >= 0.0:
        return math.inf
    disc = b * b - a * c
    if disc <= 0.0:
        return math.inf
    t = c / (-b + math.sqrt(disc))          # the smaller root, stable form
    return t if t <= lookahead_s else math.inf


def daa_series(log, step_s: float = 1.0) -> list[dict]:
    """State-based DAA picture of a :class:`~skyroute.stages.tactical.log.FlightLog`: one row per
    known intruder per ``step_s`` [s] while both fly (from when the ownship knows of it): ``t_s``,
    ``intruder``, ``range_m`` (centre to centre), ``required_m`` (S), ``t_los_s`` and
    ``t_preventive_s`` (straight-line predictions, inf: none within the alerting time) and
    ``alert`` (:func:`alert_of`).  Velocities are the flown trajectory's and the truth track's
    (central differences of the samples)."""
    t, p = log.flown()
    rows: list[dict] = []
    if t.size < 2:
        return rows
    v_own = np.gradient(p, t, axis=0)
    horizon = max(PREVENTIVE_S, CORRECTIVE_S)
    for it in log.intruders:
        ti = np.asarray(it.t_s, float)
        xi = np.asarray(it.xyz_m, float).reshape(-1, 3)
        if ti.size < 2:
            continue
        lo = max(float(t[0]), float(ti[0]), float(getattr(it, "known_from_s", 0.0)))
        hi = min(float(t[-1]), float(ti[-1]))
        if hi < lo:
            continue
        need = float(log.own_radius_m) + float(it.radius_m) + float(log.margin_m)
        ts = np.arange(math.ceil(lo / step_s) * step_s, hi + 1e-9, step_s)
        for tq in ts:
            po = np.array([np.interp(tq, t, p[:, k]) for k in range(3)])
            vo = np.array([np.interp(tq, t, v_own[:, k]) for k in range(3)])
            qi = np.array([np.interp(tq, ti, xi[:, k]) for k in range(3)])
            j = int(np.clip(np.searchsorted(ti, tq, side="right") - 1, 0, ti.size - 2))
            wi = (xi[j + 1] - xi[j]) / (ti[j + 1] - ti[j])
            dp, dv = qi - po, wi - vo
            t_los = sphere_entry_time(dp, dv, need, horizon)
            t_pre = sphere_entry_time(dp, dv, PREVENTIVE_FACTOR * need, horizon)
            rows.append({"t_s": float(tq), "intruder": str(it.id), "range_m": float(np.linalg.norm(dp)),
                         "required_m": need, "t_los_s": t_los, "t_preventive_s": t_pre,
                         "alert": alert_of(t_los, t_pre)})
    return rows
