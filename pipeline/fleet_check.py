"""The fleet's independent checks: every pair of accepted intents by brute force
(:func:`independent_conflicts`) and the smallest separation of the flown tracks
(:func:`min_separation_m`)."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["independent_conflicts", "min_separation_m"]


# ---------------------------------------------------------------------------------- independent checks
def independent_conflicts(docs: dict[str, dict], crs, start_time_utc) -> list[tuple[str, str]]:
    """Pairs of missions whose intent documents intersect, by plain pairwise shapely code (every
    pair of volumes of two different intents: altitude overlap, time overlap and intersection
    area > 1e-4 m^2 in the metric ``crs``), independent of the VolumeIndex that accepted them."""
    from skyroute.stages.fleet import MIN_AREA_M2, volumes_of_intent

    vols = {m: volumes_of_intent(d, crs, start_time_utc) for m, d in docs.items()}
    ids = sorted(vols)
    span = {m: (min((u.t_start_s for u in vs), default=math.inf), max((u.t_end_s for u in vs), default=-math.inf))
            for m, vs in vols.items()}
    bad = []
    for i, a in enumerate(ids):
        for b in ids[i + 1:]:
            if not (span[a][0] < span[b][1] and span[b][0] < span[a][1]):
                continue       # no volume of a overlaps a volume of b in time
            hit = False
            for u in vols[a]:
                for v in vols[b]:
                    if (u.alt_lower_m < v.alt_upper_m and v.alt_lower_m < u.alt_upper_m and u.t_start_s < v.t_end_s
                            and v.t_start_s < u.t_end_s and u.polygon.intersection(v.polygon).area > MIN_AREA_M2):
                        hit = True
                        break
                if hit:
                    break
            if hit:
                bad.append((a, b))
    return bad


def min_separation_m(tracks: dict[str, tuple[np.ndarray, np.ndarray]]) -> tuple[float, tuple[str, str] | None]:
    """Smallest 3-D distance [m] between two tracks at the same time (each track: times [s],
    positions (n, 3) [m]; the other track linearly interpolated at one track's samples)."""
    ids = sorted(tracks)
    best, who = math.inf, None
    for i, a in enumerate(ids):
        ta, pa = tracks[a]
        for b in ids[i + 1:]:
            tb, pb = tracks[b]
            if ta[-1] < tb[0] or tb[-1] < ta[0]:
                continue
            m = (ta >= tb[0]) & (ta <= tb[-1])
            if not m.any():
                continue
            q = np.column_stack([np.interp(ta[m], tb, pb[:, k]) for k in range(3)])
            d = float(np.min(np.linalg.norm(pa[m] - q, axis=1)))
            if d < best:
                best, who = d, (a, b)
    return best, who
