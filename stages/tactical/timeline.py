"""The ownship's plan as a timeline of exact trajectories, and the chain behind each of them.

A :class:`Segment` is one :class:`~skyroute.stages.smoothing.CornerTrajectory` (lines and
fillet arcs) whose time 0 is the mission time ``t0_s`` [s]; a :class:`Timeline` is the plan the
vehicle follows: segment ``k`` is active from ``starts_s[k]`` until the next start (a replan
cuts the timeline at the time it takes effect and appends its segment).

:func:`chain_of` recovers the polygonal chain (vertices and the legs' flown speeds) a
CornerTrajectory was built from, so the rest of a plan can be flown again with other speeds
(level 1) or continued from a point of it (levels 2, 3 and the landing).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from skyroute.stages.base import InputError
from skyroute.stages.smoothing import CornerTrajectory

__all__ = ["Segment", "Timeline", "along", "chain_of", "line_phase_at"]

_LINE = 0


@dataclass(frozen=True)
class Segment:
    """A trajectory flown from mission time ``t0_s`` [s]; ``part``: ``strategic``, ``L1``,
    ``L2``, ``L3``, ``landing``, ``escape``, ``resume`` ...; ``replanning``: the replanning that
    made it (None: the strategic plan).  ``nav``: the navigation filter along it
    (:class:`~skyroute.stages.navigation.FilterTrack`, so a replan continues the filter the
    vehicle has; None without GNSS data); ``then_chain`` (k, 3) [m] / ``then_speeds`` (k-1,)
    [m/s]: the rest of the mission after the segment's end (an escape ends in a hold; the
    mission continues from there), None when the segment itself ends the mission."""

    traj: CornerTrajectory
    t0_s: float
    part: str = "strategic"
    replanning: int | None = None
    nav: object | None = None
    then_chain: np.ndarray | None = None
    then_speeds: np.ndarray | None = None

    @property
    def t_end_s(self) -> float:
        return self.t0_s + float(self.traj.duration_s)

    def sample(self, t_s) -> np.ndarray:
        return self.traj.sample(np.asarray(t_s, float) - self.t0_s)

    def velocity(self, t_s) -> np.ndarray:
        return self.traj.velocity(np.asarray(t_s, float) - self.t0_s)

    def times(self, t_from_s: float, t_to_s: float, dt_s: float) -> np.ndarray:
        """Sample times [s] in ``[t_from_s, t_to_s]`` every ``dt_s`` plus every piece and
        phase boundary inside (chords then lie on one line or one arc)."""
        a, b = max(t_from_s, self.t0_s), min(t_to_s, self.t_end_s)
        if b < a:
            return np.zeros(0)
        n = max(int(math.ceil((b - a) / dt_s - 1e-9)), 1)
        reg = np.linspace(a, b, n + 1)
        kn = self.t0_s + np.concatenate([self.traj.piece_t_s, self.traj.phase_t0_s])
        kn = kn[(kn > a) & (kn < b)]
        t = np.unique(np.concatenate([reg, kn]))
        keep = np.r_[True, np.diff(t) > 1e-6]
        return t[keep]


@dataclass
class Timeline:
    """Segments in time order; segment ``k`` is followed from ``starts_s[k]``."""

    segments: list[Segment] = field(default_factory=list)
    starts_s: list[float] = field(default_factory=list)

    def add(self, seg: Segment, t_from_s: float) -> None:
        """Follow ``seg`` from ``t_from_s`` [s] (dropping what was planned after it)."""
        while self.starts_s and self.starts_s[-1] >= t_from_s - 1e-9:
            self.starts_s.pop()
            self.segments.pop()
        if self.segments and not (self.segments[-1].t0_s <= t_from_s):
            raise InputError("a timeline segment must start after the one it replaces")
        self.segments.append(seg)
        self.starts_s.append(float(t_from_s))

    @property
    def t_end_s(self) -> float:
        return self.segments[-1].t_end_s

    def active(self, t_s: float) -> int:
        k = int(np.searchsorted(np.asarray(self.starts_s), t_s, side="right")) - 1
        return max(k, 0)

    def sample(self, t_s: float) -> np.ndarray:
        return self.segments[self.active(t_s)].sample([t_s])[0]

    def velocity(self, t_s: float) -> np.ndarray:
        return self.segments[self.active(t_s)].velocity([t_s])[0]

    def pieces(self, t_from_s: float = -math.inf, t_to_s: float = math.inf):
        """``(segment, a, b)`` for each segment's active interval clipped to the window."""
        out = []
        for k, seg in enumerate(self.segments):
            a = self.starts_s[k]
            b = self.starts_s[k + 1] if k + 1 < len(self.segments) else seg.t_end_s
            a, b = max(a, t_from_s), min(b, t_to_s, seg.t_end_s)
            if b >= a:
                out.append((seg, a, b))
        return out

    def samples(self, t_from_s: float, dt_s: float, t_to_s: float = math.inf) -> tuple[np.ndarray, np.ndarray]:
        """``(t_s, xyz_m)`` of the plan from ``t_from_s`` (see :meth:`Segment.times`)."""
        ts, ps = [], []
        for seg, a, b in self.pieces(t_from_s, t_to_s):
            t = seg.times(a, b, dt_s)
            if ts and t.size and t[0] <= ts[-1][-1] + 1e-9:
                t = t[1:]
            if t.size:
                ts.append(t)
                ps.append(seg.sample(t))
        if not ts:
            return np.zeros(0), np.zeros((0, 3))
        return np.concatenate(ts), np.concatenate(ps)


def line_phase_at(traj: CornerTrajectory, tau_s: float) -> tuple[int, bool]:
    """``(phase index, is_line)`` at trajectory time ``tau_s`` [s]."""
    i = int(np.clip(np.searchsorted(traj.phase_t0_s, tau_s, side="right") - 1, 0, traj.phase_t0_s.size - 1))
    return i, bool(traj.kind[i] == _LINE)


def chain_of(traj: CornerTrajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The polygonal chain behind a CornerTrajectory.

    Returns ``(vertices (k, 3) [m], leg_speed_mps (k-1,), leg_of_phase (n_phases,))``:
    vertices are the start, every corner (an arc's corner is where its two tangent lines
    meet, ``A + R tan(theta / 2) e1``; a stop corner is the stop point) and the end; the leg
    speed is the highest speed flown on that leg's line phases (the plan's cruise there);
    ``leg_of_phase`` maps each phase to its leg (arcs: the leg they leave)."""
    n = traj.phase_t0_s.size
    verts = [traj.sample([0.0])[0]]
    speeds: list[float] = []
    leg_of = np.zeros(n, np.int64)
    cur_dir = None
    vmax = 0.0
    leg = 0
    for i in range(n):
        t0 = float(traj.phase_t0_s[i])
        t1 = float(traj.phase_t0_s[i + 1]) if i + 1 < n else float(traj.duration_s)
        if traj.kind[i] == _LINE:
            e1 = traj.e1[i]
            if cur_dir is not None and float(np.dot(cur_dir, e1)) < 1.0 - 1e-9:
                # a new leg after a stop corner (no arc between): the stop point is a vertex
                verts.append(traj.sample([t0])[0])
                speeds.append(vmax)
                vmax, leg = 0.0, leg + 1
            cur_dir = e1
            v0, a = float(traj.v0[i]), float(traj.a[i])
            vmax = max(vmax, v0, v0 + a * (t1 - t0))
            leg_of[i] = leg
        else:
            R = float(traj.radius_m[i])
            theta = float(traj.v0[i]) * (t1 - t0) / R
            verts.append(traj.origin[i] + R * math.tan(theta / 2.0) * traj.e1[i])
            speeds.append(max(vmax, float(traj.v0[i])))
            vmax, leg = float(traj.v0[i]), leg + 1
            leg_of[i] = leg
            # the next line's direction is the arc's end tangent
            cur_dir = math.cos(theta) * traj.e1[i] + math.sin(theta) * traj.e2[i]
    verts.append(traj.sample([traj.duration_s])[0])
    speeds.append(vmax)
    v = np.array(verts)
    s = np.maximum(np.array(speeds), 1e-3)
    ok = np.linalg.norm(np.diff(v, axis=0), axis=1) > 1e-6      # drop zero-length legs
    if not ok.all():
        new_of_leg = np.maximum(np.cumsum(ok) - 1, 0)
        v = np.concatenate([v[:1], v[1:][ok]])
        s = s[ok]
        leg_of = new_of_leg[np.minimum(leg_of, ok.size - 1)]
    return v, s, leg_of


def along(chain: np.ndarray, q: np.ndarray) -> float:
    """Arc length [m] along ``chain`` of the point of it nearest to ``q``."""
    a, b = chain[:-1], chain[1:]
    ab = b - a
    L2 = np.einsum("ij,ij->i", ab, ab)
    s = np.clip(np.einsum("ij,ij->i", q - a, ab) / np.where(L2 > 0, L2, 1.0), 0.0, 1.0)
    d = np.linalg.norm(a + s[:, None] * ab - q, axis=1)
    i = int(np.argmin(d))
    cum = np.concatenate([[0.0], np.cumsum(np.sqrt(L2))])
    return float(cum[i] + s[i] * math.sqrt(L2[i]))
