"""Strategic deconfliction of many operators' intents: first-come-first-served acceptance.

Each mission's operational intent is a list of 4-D volumes (:class:`Volume4`: a polygon in a
metric map CRS, an altitude band [m] and a time window [s]).  Two volumes **intersect** when
their polygons share more than ``min_area_m2`` (default 1e-4 m^2, i.e. a 1 cm x 1 cm square:
ASTM F3548's 1 cm intersection precision, ``IntersectionMinimumPrecisionCm``) AND their
altitude bands overlap AND their time windows overlap (open intervals: bands or windows that
only touch do not overlap).  An intent is accepted when none of its volumes intersects an
accepted volume (:func:`accept_fcfs`).

:class:`VolumeIndex` holds the accepted volumes: an STRtree over their footprints' bounding boxes (shapely,
rebuilt when the not-yet-indexed tail grows past ``rebuild_every``; the tail is checked by
brute force meanwhile), numpy arrays of the altitude and time intervals, and the exact area
test only for the pairs that pass the box, altitude and time filters.
:func:`conflicts_naive` is the pairwise baseline (every accepted volume, no index).
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import shapely

from skyroute.stages.base import InputError

__all__ = ["MIN_AREA_M2", "FleetDecision", "Volume4", "VolumeIndex", "accept_fcfs", "conflicts_naive",
           "pairs_intersect", "volumes_intersect", "volumes_of_intent", "volumes_of_plan"]

MIN_AREA_M2 = 1e-4


@dataclass(frozen=True)
class Volume4:
    """A 4-D volume: ``polygon`` (shapely, map CRS [m]), altitudes ``alt_lower_m`` <
    ``alt_upper_m`` [m], times ``t_start_s`` < ``t_end_s`` [s] (any common epoch)."""

    polygon: shapely.Polygon
    alt_lower_m: float
    alt_upper_m: float
    t_start_s: float
    t_end_s: float

    def __post_init__(self):
        if not (self.alt_upper_m > self.alt_lower_m and self.t_end_s > self.t_start_s):
            raise InputError("a volume needs alt_upper_m > alt_lower_m and t_end_s > t_start_s")
        if not isinstance(self.polygon, shapely.Polygon) or self.polygon.is_empty:
            raise InputError("a volume's outline must be a non-empty shapely Polygon")


def volumes_of_intent(doc: dict, crs, start_time_utc) -> list[Volume4]:
    """The :class:`Volume4` list of an F3548 OperationalIntentDetails dict: vertices projected to
    the metric ``crs``, times in seconds after ``start_time_utc``."""
    import pandas as pd

    tr = _from_lonlat(crs if isinstance(crs, str) else str(crs.to_wkt()) if hasattr(crs, "to_wkt") else crs)
    t0 = pd.Timestamp(start_time_utc)
    t0 = t0.tz_localize("UTC") if t0.tzinfo is None else t0.tz_convert("UTC")
    out = []
    for v in doc["volumes"]:
        vx = v["volume"]["outline_polygon"]["vertices"]
        x, y = tr.transform([p["lng"] for p in vx], [p["lat"] for p in vx])
        out.append(Volume4(shapely.Polygon(np.column_stack([x, y])), float(v["volume"]["altitude_lower"]["value"]),
                           float(v["volume"]["altitude_upper"]["value"]),
                           (pd.Timestamp(v["time_start"]["value"]) - t0).total_seconds(),
                           (pd.Timestamp(v["time_end"]["value"]) - t0).total_seconds()))
    return out


@functools.lru_cache(maxsize=8)
def _from_lonlat(crs):
    from pyproj import Transformer

    return Transformer.from_crs(4326, crs, always_xy=True)


def volumes_of_plan(volumes: Sequence, t_offset_s: float = 0.0) -> list[Volume4]:
    """:class:`Volume4` s of :func:`skyroute.stages.intents.plan_volumes` output (map CRS,
    WGS 84 altitudes, mission times shifted by ``t_offset_s`` [s], e.g. a delayed departure)."""
    return [Volume4(shapely.Polygon(v.outline_xy_m), v.alt_lower_m, v.alt_upper_m, v.t_start_s + t_offset_s,
                    v.t_end_s + t_offset_s) for v in volumes]


def volumes_intersect(a: Volume4, b: Volume4, min_area_m2: float = MIN_AREA_M2) -> bool:
    """True when ``a`` and ``b`` overlap in altitude and time and their outlines share more
    than ``min_area_m2`` [m^2] (module docstring)."""
    if not (a.alt_lower_m < b.alt_upper_m and b.alt_lower_m < a.alt_upper_m):
        return False
    if not (a.t_start_s < b.t_end_s and b.t_start_s < a.t_end_s):
        return False
    return a.polygon.intersection(b.polygon).area > min_area_m2


def _arrays(vols: Sequence[Volume4]) -> tuple[np.ndarray, np.ndarray]:
    polys = np.array([v.polygon for v in vols], dtype=object)
    iv = np.array([[v.alt_lower_m, v.alt_upper_m, v.t_start_s, v.t_end_s] for v in vols], float).reshape(-1, 4)
    return polys, iv


def pairs_intersect(q: Sequence[Volume4], a: Sequence[Volume4], qidx, aidx,
                    min_area_m2: float = MIN_AREA_M2) -> np.ndarray:
    """Boolean mask over the candidate pairs ``(q[qidx[k]], a[aidx[k]])``: the exact 4-D test
    of :func:`volumes_intersect` (altitude and time overlap, then the outlines' shared area >
    ``min_area_m2`` [m^2]), vectorised.  The one exact test of the candidate pairs an index
    (the STRtree here, the R*Tree of :mod:`skyroute.stages.airspace_store`) proposes."""
    qidx, aidx = np.asarray(qidx, np.intp).ravel(), np.asarray(aidx, np.intp).ravel()
    if not len(q) or not len(a) or not qidx.size:
        return np.zeros(qidx.size, bool)
    qp, qi = _arrays(q)
    ap, ai = _arrays(a)
    return _exact(qp, qi, ap, ai, qidx, aidx, min_area_m2)


def _exact(qp, qi, ap, ai, qidx, aidx, min_area_m2) -> np.ndarray:
    """Mask of the candidate pairs (qidx, aidx) that intersect (intervals, then area)."""
    ok = ((qi[qidx, 0] < ai[aidx, 1]) & (ai[aidx, 0] < qi[qidx, 1])
          & (qi[qidx, 2] < ai[aidx, 3]) & (ai[aidx, 2] < qi[qidx, 3]))
    if ok.any():
        k = np.flatnonzero(ok)
        ok[k] = shapely.area(shapely.intersection(qp[qidx[k]], ap[aidx[k]])) > min_area_m2
    return ok


@dataclass
class VolumeIndex:
    """The accepted volumes (see the module docstring); ``owner[i]``: the intent id of volume i."""

    rebuild_every: int = 512
    min_area_m2: float = MIN_AREA_M2
    owner: list = field(default_factory=list)
    _polys: list = field(default_factory=list)
    _iv: list = field(default_factory=list)
    _tree: shapely.STRtree | None = None
    _n_tree: int = 0
    _ap: np.ndarray = field(default_factory=lambda: np.zeros(0, object))
    _ai: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))

    def __len__(self) -> int:
        return len(self._polys)

    def add(self, vols: Iterable[Volume4], owner) -> None:
        """Accept ``vols`` (no check) as belonging to intent ``owner``."""
        for v in vols:
            self._polys.append(v.polygon)
            self._iv.append((v.alt_lower_m, v.alt_upper_m, v.t_start_s, v.t_end_s))
            self.owner.append(owner)
        if len(self._polys) - self._n_tree >= self.rebuild_every:
            self._rebuild()

    def _rebuild(self) -> None:
        self._ap = np.array(self._polys, dtype=object)
        self._ai = np.array(self._iv, float).reshape(-1, 4)
        self._tree = shapely.STRtree(self._ap) if len(self._ap) else None
        self._n_tree = len(self._polys)

    def conflicts(self, vols: Sequence[Volume4]) -> list[tuple[int, int]]:
        """Pairs ``(i, j)``: candidate volume ``vols[i]`` intersects accepted volume ``j``."""
        if not vols or not self._polys:
            return []
        qp, qi = _arrays(vols)
        pairs: list[tuple[int, int]] = []
        if self._tree is not None:
            qidx, aidx = self._tree.query(qp)    # bounding boxes only: the intervals filter before GEOS
            ok = _exact(qp, qi, self._ap, self._ai, qidx, aidx, self.min_area_m2)
            pairs += list(zip(qidx[ok].tolist(), aidx[ok].tolist(), strict=True))
        n_tail = len(self._polys) - self._n_tree
        if n_tail:
            tp = np.array(self._polys[self._n_tree:], dtype=object)
            ti = np.array(self._iv[self._n_tree:], float).reshape(-1, 4)
            qidx, aidx = (a.ravel() for a in np.meshgrid(np.arange(len(vols)), np.arange(n_tail), indexing="ij"))
            ok = _exact(qp, qi, tp, ti, qidx, aidx, self.min_area_m2)
            pairs += [(int(i), int(j) + self._n_tree) for i, j in zip(qidx[ok], aidx[ok], strict=True)]
        return sorted(pairs)


def conflicts_naive(vols: Sequence[Volume4], accepted: Sequence[Volume4],
                    min_area_m2: float = MIN_AREA_M2) -> list[tuple[int, int]]:
    """The pairwise baseline of :meth:`VolumeIndex.conflicts`: :func:`volumes_intersect` on every pair."""
    return [(i, j) for i, a in enumerate(vols) for j, b in enumerate(accepted) if volumes_intersect(a, b, min_area_m2)]


@dataclass(frozen=True)
class FleetDecision:
    """Per intent, in arrival order: ``accepted`` and, when not, ``conflicts_with`` (ids of the
    accepted intents it intersects) and ``reason``."""

    intent_id: object
    accepted: bool
    conflicts_with: tuple = ()
    reason: str = ""


def accept_fcfs(intents: Sequence[tuple[object, Sequence[Volume4]]], index: VolumeIndex | None = None
                ) -> tuple[list[FleetDecision], VolumeIndex]:
    """First-come-first-served: each ``(intent_id, volumes)`` in order is accepted when none of
    its volumes intersects a volume accepted before it; returns the decisions and the index."""
    index = VolumeIndex() if index is None else index
    out = []
    for iid, vols in intents:
        if not len(vols):
            raise InputError(f"intent {iid!r} has no volume")
        pairs = index.conflicts(list(vols))
        if pairs:
            who = tuple(dict.fromkeys(index.owner[j] for _, j in pairs))
            out.append(FleetDecision(iid, False, who, f"its volumes intersect the accepted intent(s) "
                                     f"{', '.join(map(str, who))} ({len(pairs)} volume pair(s))"))
        else:
            index.add(vols, iid)
            out.append(FleetDecision(iid, True))
    return out, index
