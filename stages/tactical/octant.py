"""Octant-based local collision avoidance (seed 004 section III-D) and its reciprocal use by
several own UAVs.

Frame and octants.  Around the UAS H the body frame has ``e_f`` its horizontal heading (the
direction of motion; the goal direction when H hovers), ``e_u`` the vertical and
``e_l = e_u x e_f`` (left).  A relative position ``(f, l, u)`` lies in octant
``1 + [l < 0] + 2 [f >= 0] + 4 [u < 0]``, so the forward hemisphere is
``F_h = {3, 4, 7, 8}`` and the backward one ``B_h = {1, 2, 5, 6}`` as in the seed's Fig. 12.
In a *coplanar* engagement (everything in H's horizontal plane) the up axis is dropped and the
neighbourhood is four quadrants, octants 1-4 (``F_h = {3, 4}``).

Threat path.  A threat (intruder, unknown intruder, or another own UAS) at relative position
``q`` with relative velocity ``d = v_I - v_H`` (the seed's eq. 7 line, in H's frame: H moves
too) is followed along its straight line inside the periphery ``P_r`` of radius
``periphery_m`` from now on; :func:`octants_crossed` splits that chord exactly at the frame's
planes (at most 4 octants, 3 quadrants when coplanar, as the seed notes).

Escape.  With the set of occupied octants ``O_c``, the vacant ones are ranked: forward
hemisphere first (the seed's preference, shortest escape), then by the distance between the
octant's centre point ``periphery_m * c_k`` and the threat chords (farther first).  The
escape velocity is the octant's centre direction at the UAS's speed; its vertical component
is limited to ``max_elevation_deg`` (still strictly inside the octant).  When no octant is
vacant (two or more threats from different octants), the neighbourhood is sectorised into
denser *pockets* (``n_azimuth`` x elevation rings, :func:`pocket_directions`), a pocket being
vacant when no threat chord passes within its angular half-width; H moves into the best
vacant pocket, preferably forward; else it holds its position.

Acceptance (what makes the manoeuvre safe, not only plausible).  Every candidate velocity
(tracking the goal, octant escapes, pockets, hold) is checked against every sensed threat
flying straight for ``horizon_s`` [s]: the closest point of approach over ``[0, horizon_s]``
must be at least the threat's separation ``sep_m``; the first accepted candidate in the
order *track > octant > pocket > hold* is flown.  If none is accepted, H flies the candidate
with the largest closest approach (kind ``"best"``: a loss of separation may follow and is
reported by the independent checks).

Separation threshold: ``sep_m = r_H + r_I + d_c`` (the radii of the two spheres plus the
traffic margin), the same as the tactical replay's.  Detection: a threat is sensed when its
range is at most ``periphery_m``; H reacts (leaves its track) only when a sensed threat's
straight path breaches the separation within ``horizon_s``.

Several own UAVs (:func:`fly_fleet`): each UAV runs the avoidance against the intruders and
the other UAVs.  **Priority rule**: the UAV with the lower index has priority; in each time
step the UAVs decide in priority order, each one seeing the *new* velocities of the UAVs of
higher priority and the current velocities of the others, so every pair is checked by its
lower-priority member against the final velocity of the higher-priority one (the higher one
also avoids the lower one's current motion: the avoidance is reciprocal, the priority only
breaks the symmetric deadlocks).  The motion is the seed's 3-DOF point model (velocity
changes at the steps of ``dt_s``); conflicts between steps are excluded by the closest-approach
test over a horizon longer than a step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from skyroute.stages.base import InputError

__all__ = ["BACKWARD", "FORWARD", "FleetResult", "Manoeuvre", "avoid", "body_frame", "escape_direction",
           "fly_fleet", "octant_of", "octants_crossed", "pocket_directions", "rank_octants"]

FORWARD = (3, 4, 7, 8)
BACKWARD = (1, 2, 5, 6)
_SIGNS = {k: (1.0 if (k - 1) & 2 else -1.0, -1.0 if (k - 1) & 1 else 1.0, -1.0 if (k - 1) & 4 else 1.0)
          for k in range(1, 9)}          # octant -> signs of (f, l, u) of its centre


def body_frame(heading_xyz, fallback_xyz=(1.0, 0.0, 0.0)) -> np.ndarray:
    """(3, 3) rows ``e_f, e_l, e_u``: ``e_f`` the horizontal direction of ``heading_xyz`` (of
    ``fallback_xyz`` when that is vertical or zero), ``e_u = (0, 0, 1)``, ``e_l = e_u x e_f``."""
    for h in (heading_xyz, fallback_xyz, (1.0, 0.0, 0.0)):
        f = np.array([float(h[0]), float(h[1]), 0.0])
        n = float(np.hypot(f[0], f[1]))
        if n > 1e-9:
            f /= n
            break
    u = np.array([0.0, 0.0, 1.0])
    return np.stack([f, np.cross(u, f), u])


def octant_of(rel_xyz, frame: np.ndarray) -> int:
    """Octant (1..8, seed numbering, module docstring) of a relative position [m]."""
    b = frame @ np.asarray(rel_xyz, float)
    return 1 + int(b[1] < 0) + 2 * int(b[0] >= 0) + 4 * int(b[2] < 0)


def _chord(q: np.ndarray, d: np.ndarray, radius: float) -> tuple[float, float] | None:
    """Parameters ``[s0, s1]`` (s >= 0: from now on) of ``q + s d`` inside the ball of
    ``radius`` around the origin, or None."""
    a = float(d @ d)
    if a < 1e-18:
        return (0.0, 0.0) if float(q @ q) <= radius * radius else None
    b = float(q @ d)
    c = float(q @ q) - radius * radius
    disc = b * b - a * c
    if disc < 0:
        return None
    sq = math.sqrt(disc)
    s0, s1 = (-b - sq) / a, (-b + sq) / a
    if s1 < 0:
        return None
    return max(s0, 0.0), s1


def octants_crossed(rel_xyz, rel_vel_mps, radius_m: float, frame: np.ndarray, *,
                    coplanar: bool = False) -> tuple[int, ...]:
    """Octants (quadrants 1-4 when ``coplanar``) the threat's straight relative path passes
    through inside the periphery of ``radius_m`` [m] from now on (the chord split exactly at
    the frame's planes); ``()`` when it does not enter the periphery."""
    q = frame @ np.asarray(rel_xyz, float)
    d = frame @ np.asarray(rel_vel_mps, float)
    if coplanar:
        q[2] = d[2] = 0.0
    ch = _chord(q, d, radius_m)
    if ch is None:
        return ()
    s0, s1 = ch
    cuts = [s0, s1]
    for k in range(2 if coplanar else 3):
        if abs(d[k]) > 1e-15:
            s = -q[k] / d[k]
            if s0 < s < s1:
                cuts.append(s)
    cuts.sort()
    out = set()
    if s1 - s0 <= 1e-12:
        cuts = [s0, s0]
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        m = q + 0.5 * (a + b) * d
        out.add(1 + int(m[1] < 0) + 2 * int(m[0] >= 0) + 4 * int(m[2] < 0 and not coplanar))
    return tuple(sorted(out))


def escape_direction(octant: int, frame: np.ndarray, *, coplanar: bool = False,
                     max_elevation_deg: float = 35.26) -> np.ndarray:
    """Unit world direction of the centre of ``octant`` (1..8; quadrant 1..4 when ``coplanar``:
    horizontal), its elevation limited to ``max_elevation_deg`` (> 0: strictly inside)."""
    sf, sl, su = _SIGNS[int(octant)]
    if coplanar:
        b = np.array([sf, sl, 0.0]) / math.sqrt(2.0)
    else:
        el = max(min(math.radians(max_elevation_deg), math.atan(1 / math.sqrt(2.0))), 1e-3)
        b = np.array([sf * math.cos(el) / math.sqrt(2.0), sl * math.cos(el) / math.sqrt(2.0), su * math.sin(el)])
    return frame.T @ b


def _seg_point_d(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    L2 = float(ab @ ab)
    s = 0.0 if L2 < 1e-18 else min(max(float((p - a) @ ab) / L2, 0.0), 1.0)
    return float(np.linalg.norm(a + s * ab - p))


def rank_octants(chords: list[tuple[np.ndarray, np.ndarray]], frame: np.ndarray, radius_m: float, *,
                 coplanar: bool = False) -> tuple[list[int], list[int]]:
    """``(vacant, occupied)``: the vacant octants ranked (forward hemisphere first, then
    farther from the threat chords ``(a, b)`` [m, relative, world frame] first) and the
    occupied ones, from the chords' octants."""
    occ: set[int] = set()
    for a, b in chords:
        occ |= set(_octs_of_segment(frame @ a, frame @ b, coplanar))
    allk = range(1, 5) if coplanar else range(1, 9)
    vac = [k for k in allk if k not in occ]

    def key(k):
        c = radius_m * escape_direction(k, frame, coplanar=coplanar)
        dmin = min((_seg_point_d(c, a, b) for a, b in chords), default=math.inf)
        return (0 if k in FORWARD else 1, -dmin, k)

    return sorted(vac, key=key), sorted(occ)


def _octs_of_segment(a: np.ndarray, b: np.ndarray, coplanar: bool) -> list[int]:
    """Octants of the body-frame segment a -> b (split at the planes)."""
    d = b - a
    if coplanar:
        a = a.copy()
        d = d.copy()
        a[2] = d[2] = 0.0
    cuts = [0.0, 1.0]
    for k in range(2 if coplanar else 3):
        if abs(d[k]) > 1e-15:
            s = -a[k] / d[k]
            if 0.0 < s < 1.0:
                cuts.append(s)
    cuts.sort()
    out = []
    for s0, s1 in zip(cuts[:-1], cuts[1:], strict=True):
        m = a + 0.5 * (s0 + s1) * d
        out.append(1 + int(m[1] < 0) + 2 * int(m[0] >= 0) + 4 * int(m[2] < 0 and not coplanar))
    return out


def pocket_directions(n_azimuth: int = 16, elevations_deg=(-30.0, 0.0, 30.0), *,
                      coplanar: bool = False) -> tuple[np.ndarray, float]:
    """Body-frame unit directions (k, 3) of the pockets (``n_azimuth`` per elevation ring;
    only the horizontal ring when ``coplanar``) and their angular half-width [rad]."""
    els = (0.0,) if coplanar else tuple(elevations_deg)
    az = 2 * math.pi * np.arange(n_azimuth) / n_azimuth
    dirs = [np.column_stack([np.cos(az) * math.cos(math.radians(e)), np.sin(az) * math.cos(math.radians(e)),
                             np.full(n_azimuth, math.sin(math.radians(e)))]) for e in els]
    return np.concatenate(dirs), math.pi / n_azimuth


# ------------------------------------------------------------------ one UAS, one step


@dataclass(frozen=True)
class Manoeuvre:
    """What H flies now: ``kind`` ``track`` (its desired velocity), ``octant`` (escape into
    ``octant``), ``pocket``, ``hold`` or ``best`` (nothing accepted: the largest closest
    approach); ``velocity_mps`` (3,); ``occupied`` octants of the breaching threats;
    ``min_cpa_m`` [m]: closest approach of that velocity to the sensed threats over the horizon
    minus their separation (>= 0 when accepted)."""

    kind: str
    velocity_mps: np.ndarray
    octant: int = 0
    occupied: tuple[int, ...] = ()
    min_cpa_m: float = math.inf


def _cpa_margin(vels: np.ndarray, q: np.ndarray, w: np.ndarray, sep: np.ndarray, horizon: float) -> np.ndarray:
    """(K,) min over threats of [closest distance over [0, horizon] - sep] for own velocities
    ``vels`` (K, 3); threats at relative positions ``q`` (M, 3) moving at ``w`` (M, 3)."""
    if q.shape[0] == 0:
        return np.full(vels.shape[0], math.inf)
    dv = w[None, :, :] - vels[:, None, :]                     # (K, M, 3) relative velocity
    a = np.einsum("kmi,kmi->km", dv, dv)
    b = np.einsum("mi,kmi->km", q, dv)
    tau = np.clip(np.where(a > 1e-18, -b / np.where(a > 1e-18, a, 1.0), 0.0), 0.0, horizon)
    rel = q[None] + tau[..., None] * dv
    return (np.linalg.norm(rel, axis=-1) - sep[None, :]).min(axis=1)


def avoid(own_xyz, own_vel_mps, desired_vel_mps, threat_xyz, threat_vel_mps, sep_m, *, speed_mps: float,
          periphery_m: float, horizon_s: float, coplanar: bool = False, max_elevation_deg: float = 35.26,
          n_pockets: int = 16) -> Manoeuvre:
    """One decision of the octant avoidance (module docstring) for H at ``own_xyz`` [m] moving
    at ``own_vel_mps``, wanting ``desired_vel_mps`` [m/s], against threats at ``threat_xyz``
    (M, 3) [m] with velocities ``threat_vel_mps`` (M, 3) [m/s] and separations ``sep_m``
    (scalar or (M,)) [m]; escapes are flown at ``speed_mps`` [m/s]."""
    if not (speed_mps > 0 and periphery_m > 0 and horizon_s > 0):
        raise InputError("speed_mps, periphery_m and horizon_s must be > 0 [m/s, m, s]")
    own = np.asarray(own_xyz, float)
    want = np.asarray(desired_vel_mps, float)
    tx = np.asarray(threat_xyz, float).reshape(-1, 3)
    tv = np.asarray(threat_vel_mps, float).reshape(-1, 3)
    sep = np.broadcast_to(np.asarray(sep_m, float), (tx.shape[0],))
    q = tx - own
    sensed = np.linalg.norm(q, axis=1) <= periphery_m
    q, w, s = q[sensed], tv[sensed], sep[sensed]
    track = _cpa_margin(want[None], q, w, s, horizon_s)[0]
    if track >= 0:
        return Manoeuvre("track", want, 0, (), track)
    frame = body_frame(own_vel_mps, want)
    # breaching threats: their straight relative paths over the horizon, clipped to the periphery
    vown = np.asarray(own_vel_mps, float)
    chords = []
    for qi, wi in zip(q, w, strict=True):
        ch = _chord(frame @ qi, frame @ (wi - vown), periphery_m)
        if ch is not None:
            d = wi - vown
            chords.append((qi + ch[0] * d, qi + min(ch[1], 1e6) * d))
    vac, occ = rank_octants(chords, frame, periphery_m, coplanar=coplanar)
    cands, kinds, octs = [], [], []
    for k in vac:
        cands.append(speed_mps * escape_direction(k, frame, coplanar=coplanar, max_elevation_deg=max_elevation_deg))
        kinds.append("octant")
        octs.append(k)
    dirs_b, half = pocket_directions(n_pockets, coplanar=coplanar)
    dirs = dirs_b @ frame                                      # body -> world
    if not coplanar and max_elevation_deg < 30.0:
        dirs = dirs[np.abs(dirs[:, 2]) <= math.sin(math.radians(max_elevation_deg)) + 1e-9]
    # vacant pockets (no chord within the angular half-width), forward ones first
    pv = []
    for dvec in dirs:
        c = periphery_m * dvec
        dmin = min((_seg_point_d(c, a, b) for a, b in chords), default=math.inf)
        vacant = dmin > periphery_m * math.sin(half)
        pv.append((0 if vacant else 1, 0 if float(dvec @ frame[0]) > 0 else 1, -dmin))
    for i in sorted(range(len(pv)), key=lambda i: pv[i]):
        cands.append(speed_mps * dirs[i])
        kinds.append("pocket")
        octs.append(octant_of(dirs[i], frame))
    cands.append(np.zeros(3))
    kinds.append("hold")
    octs.append(0)
    V = np.array(cands)
    m = _cpa_margin(V, q, w, s, horizon_s)
    ok = np.nonzero(m >= 0)[0]
    j = int(ok[0]) if ok.size else int(np.argmax(m))
    return Manoeuvre(kinds[j] if ok.size else "best", V[j], octs[j], tuple(occ), float(m[j]))


# ------------------------------------------------------------------ several own UAVs


@dataclass
class FleetResult:
    """Trajectories of :func:`fly_fleet`: ``t_s`` (n,) [s], ``xyz_m`` (n, N, 3) [m] (linear in
    time between samples), ``intruder_xyz_m`` (n, M, 3); ``arrival_s`` (N,) [s] (inf: not
    arrived); ``delay_s`` (N,) [s] arrival minus straight-line distance / speed; ``kinds``:
    counts of each manoeuvre kind over all steps."""

    t_s: np.ndarray
    xyz_m: np.ndarray
    intruder_xyz_m: np.ndarray
    arrival_s: np.ndarray
    delay_s: np.ndarray
    kinds: dict = field(default_factory=dict)


def fly_fleet(start_xyz, goal_xyz, *, speed_mps: float, radius_m, margin_m: float, periphery_m: float,
              horizon_s: float, dt_s: float = 0.1, t_max_s: float = 600.0, intruder_xyz=None,
              intruder_vel_mps=None, intruder_radius_m=1.0, coplanar: bool = False,
              max_elevation_deg: float = 35.26, goal_tol_m: float = 0.5) -> FleetResult:
    """Fly N own UAVs from ``start_xyz`` (N, 3) to ``goal_xyz`` (N, 3) [m] at ``speed_mps``
    with the octant avoidance and the priority rule (module docstring), among straight-flying
    intruders (M, 3) [m, m/s].  Separation of a pair: ``radius_i + radius_j + margin_m``.  A UAV
    within ``goal_tol_m`` [m] of its goal has arrived and leaves the airspace (it is no longer a
    threat); the intruders are non-cooperative (they keep their velocity)."""
    S = np.asarray(start_xyz, float).reshape(-1, 3)
    G = np.asarray(goal_xyz, float).reshape(-1, 3)
    n = S.shape[0]
    rad = np.broadcast_to(np.asarray(radius_m, float), (n,))
    ix = np.zeros((0, 3)) if intruder_xyz is None else np.asarray(intruder_xyz, float).reshape(-1, 3)
    iv = np.zeros_like(ix) if intruder_vel_mps is None else np.asarray(intruder_vel_mps, float).reshape(-1, 3)
    irad = np.broadcast_to(np.asarray(intruder_radius_m, float), (ix.shape[0],))
    if not (dt_s > 0 and horizon_s > dt_s):
        raise InputError(f"dt_s = {dt_s} s must be > 0 and horizon_s = {horizon_s} s longer than a step")
    pos = S.copy()
    vel = np.zeros_like(pos)
    arrived = np.full(n, math.inf)
    ts, xs, ixs = [0.0], [pos.copy()], [ix.copy()]
    kinds: dict[str, int] = {}
    t = 0.0
    while t < t_max_s - 1e-9 and not np.all(np.isfinite(arrived)):
        new = vel.copy()
        for i in range(n):
            if math.isfinite(arrived[i]):
                new[i] = 0.0
                continue
            to_goal = G[i] - pos[i]
            dist = float(np.linalg.norm(to_goal))
            want = to_goal / dist * min(speed_mps, dist / dt_s) if dist > 1e-12 else np.zeros(3)
            others = [j for j in range(n) if j != i and not math.isfinite(arrived[j])]
            tx = np.concatenate([pos[others], ix])
            tv = np.concatenate([np.array([new[j] if j < i else vel[j] for j in others]).reshape(-1, 3), iv])
            sep = np.concatenate([rad[i] + rad[others] + margin_m, rad[i] + irad + margin_m])
            m = avoid(pos[i], vel[i], want, tx, tv, sep, speed_mps=speed_mps, periphery_m=periphery_m,
                      horizon_s=horizon_s, coplanar=coplanar, max_elevation_deg=max_elevation_deg)
            kinds[m.kind] = kinds.get(m.kind, 0) + 1
            new[i] = m.velocity_mps
        vel = new
        pos = pos + vel * dt_s
        ix = ix + iv * dt_s
        t += dt_s
        done = (np.linalg.norm(G - pos, axis=1) <= goal_tol_m) & ~np.isfinite(arrived)
        arrived[done] = t
        ts.append(t)
        xs.append(pos.copy())
        ixs.append(ix.copy())
    straight = np.linalg.norm(G - S, axis=1) / speed_mps
    return FleetResult(np.array(ts), np.array(xs), np.array(ixs), arrived, arrived - straight, kinds)
