"""TEMPORARY lead stub (replaced by the helper's exact module at merge)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class IntruderTracks:
    intruders: tuple

    @classmethod
    def from_intruders(cls, intruders):
        return cls(tuple(intruders))


@dataclass(frozen=True)
class Conflict:
    t_s: float
    index: int
    id: str
    distance_m: float
    t_cpa_s: float
    own_xyz_m: np.ndarray
    intruder_xyz_m: np.ndarray
    own_velocity_mps: np.ndarray
    intruder_velocity_mps: np.ndarray


def first_conflict(t_s, xyz_m, tracks, sep_m, t_from_s=-np.inf, dt_c_s=0.0):
    t_s = np.asarray(t_s, float)
    xyz_m = np.asarray(xyz_m, float)
    sep = np.broadcast_to(np.asarray(sep_m, float), (len(tracks.intruders),))
    tt = np.arange(max(t_s[0], t_from_s), t_s[-1], 0.02)
    if tt.size == 0:
        return None
    own = np.column_stack([np.interp(tt, t_s, xyz_m[:, k]) for k in range(3)])
    best = None
    for i, it in enumerate(tracks.intruders):
        live = (tt >= it.times_s[0]) & (tt <= it.times_s[-1])
        if not live.any():
            continue
        ip = np.column_stack([np.interp(tt, it.times_s, it.xyz_m[:, k]) for k in range(3)])
        d = np.linalg.norm(own - ip, axis=1)
        bad = live & (d < sep[i])
        if bad.any():
            j = int(np.argmax(bad))
            if best is None or tt[j] < best.t_s:
                k = int(np.argmin(np.where(live, d, np.inf)))
                vo = (own[min(j + 1, tt.size - 1)] - own[max(j - 1, 0)]) / (2 * 0.02)
                vi = (ip[min(j + 1, tt.size - 1)] - ip[max(j - 1, 0)]) / (2 * 0.02)
                best = Conflict(float(tt[j]), i, it.id, float(d[k]), float(tt[k]), own[j], ip[j], vo, vi)
    return best
