"""The exact 4-D intersection test (skyroute.stages.fleet: ``volumes_intersect`` and its
vectorised ``pairs_intersect``, the one test every index's candidates go through), property-tested
with hypothesis against geometry built so that the answer is known, and against an independent
reference (Sutherland-Hodgman clipping of convex polygons + shoelace area written here, plain
interval arithmetic): any overlap > 1 cm in space during an overlapping time window is a
conflict; touching (edge, vertex, altitude boundary, time boundary) or 1 cm apart is not."""

from __future__ import annotations

import math

import numpy as np
import shapely
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from skyroute.stages.fleet import MIN_AREA_M2, Volume4, pairs_intersect, volumes_intersect

SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
ORIGIN = (385_000.0, 6_672_000.0)      # UTM-sized coordinates: rounding at real magnitudes


@st.composite
def convex(draw, r_min=2.0, r_max=60.0):
    """A convex polygon (counter-clockwise vertices, (n, 2) [m]) on a circle of radius R around
    a point near ORIGIN: edges >= 0.5 m, every interior angle >= ~25 deg."""
    r = draw(st.floats(r_min, r_max))
    n = draw(st.integers(3, 8))
    gaps = np.array(draw(st.lists(st.floats(0.6, 2.4), min_size=n, max_size=n)))
    gaps = gaps / gaps.sum() * 2 * math.pi
    assume(gaps.min() >= 0.3 and gaps.max() <= 2.6)
    a0 = draw(st.floats(0, 2 * math.pi))
    ang = a0 + np.cumsum(np.r_[0.0, gaps[:-1]])
    cx = ORIGIN[0] + draw(st.floats(-500, 500))
    cy = ORIGIN[1] + draw(st.floats(-500, 500))
    return np.column_stack([cx + r * np.cos(ang), cy + r * np.sin(ang)])


band = st.tuples(st.floats(0, 200), st.floats(0.5, 80)).map(lambda t: (t[0], t[0] + t[1]))
window = st.tuples(st.floats(0, 7200), st.floats(1, 600)).map(lambda t: (t[0], t[0] + t[1]))


def vol(xy, alt, t) -> Volume4:
    return Volume4(shapely.Polygon(xy), alt[0], alt[1], t[0], t[1])


def both(a: Volume4, b: Volume4) -> bool:
    """volumes_intersect and pairs_intersect, which must agree, both ways round."""
    r = volumes_intersect(a, b)
    assert volumes_intersect(b, a) == r
    assert bool(pairs_intersect([a], [b], [0], [0])[0]) == r
    return r


def _edge_frame(xy: np.ndarray, k: int):
    """Edge k (vertex k to k+1) of a counter-clockwise polygon: its two ends and outward unit normal."""
    p, q = xy[k], xy[(k + 1) % len(xy)]
    d = (q - p) / np.linalg.norm(q - p)
    return p, q, np.array([d[1], -d[0]])


def _reflect(xy: np.ndarray, p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """xy reflected across the line through p with unit normal n."""
    return xy - 2.0 * ((xy - p) @ n)[:, None] * n[None, :]


# ------------------------------------------------------------------------------ edge contacts
@SETTINGS
@given(convex(), st.data(), band, window)
def test_edge_contact_touching_or_1cm_apart_is_no_conflict(xy, data, alt, t):
    k = data.draw(st.integers(0, len(xy) - 1))
    p, _, n = _edge_frame(xy, k)
    mirror = _reflect(xy, p, n)                           # the other side of edge k, sharing it
    gap = data.draw(st.sampled_from([0.0, 0.01, 0.0100001, 0.5]))
    a, b = vol(xy, alt, t), vol(mirror + gap * n, alt, t)
    assert shapely.Polygon(mirror + gap * n).distance(shapely.Polygon(xy)) < gap + 1e-6
    assert not both(a, b)


@SETTINGS
@given(convex(), st.data(), band, window)
def test_edge_overlap_deeper_than_1cm_is_a_conflict(xy, data, alt, t):
    k = data.draw(st.integers(0, len(xy) - 1))
    p, _, n = _edge_frame(xy, k)
    mirror = _reflect(xy, p, n)
    depth = data.draw(st.floats(0.0105, 1.0))
    b = vol(mirror - depth * n, alt, t)
    assert both(vol(xy, alt, t), b)


# ------------------------------------------------------------------------------ vertex contacts
@SETTINGS
@given(convex(), st.data(), band, window)
def test_vertex_contact_is_no_conflict_a_deep_one_is(xy, data, alt, t):
    k = data.draw(st.integers(0, len(xy) - 1))
    v = xy[k]
    opposite = 2.0 * v - xy                                 # point reflection through vertex k: meets A at v only
    out = v - xy.mean(axis=0)
    out /= np.linalg.norm(out)
    gap = data.draw(st.sampled_from([0.0, 0.01]))
    assert not both(vol(xy, alt, t), vol(opposite + gap * out, alt, t))
    # pushed 0.3 m into A along the outward direction: a real overlap (>= ~1e-2 m^2)
    deep = vol(opposite - 0.3 * out, alt, t)
    assert shapely.Polygon(xy).intersection(deep.polygon).area > MIN_AREA_M2
    assert both(vol(xy, alt, t), deep)


# ------------------------------------------------------------------------------ altitude / time boundaries
@SETTINGS
@given(convex(), band, window, st.floats(0.5, 50), st.sampled_from(["alt", "time"]))
def test_boundary_contact_in_altitude_or_time(xy, alt, t, extent, which):
    a = vol(xy, alt, t)

    def other(lo_shift: float) -> Volume4:
        if which == "alt":
            lo = alt[1] + lo_shift
            return vol(xy, (lo, lo + extent), t)
        lo = t[1] + lo_shift
        return vol(xy, alt, (lo, lo + extent))

    assert not both(a, other(0.0))        # the bands / windows only touch
    assert not both(a, other(0.01))       # 1 cm / 10 ms apart
    assert both(a, other(-0.0105))        # overlapping by more than 1 cm / 10 ms


@SETTINGS
@given(convex(), st.data(), band, window)
def test_spatial_overlap_needs_altitude_and_time_overlap(xy, data, alt, t):
    """A deep spatial overlap with the altitude bands touching, or the windows touching, is no
    conflict; a spatial touch with both overlapping is none either."""
    k = data.draw(st.integers(0, len(xy) - 1))
    p, _, n = _edge_frame(xy, k)
    mirror = _reflect(xy, p, n)
    a = vol(xy, alt, t)
    assert not both(a, vol(mirror - 0.5 * n, (alt[1], alt[1] + 10.0), t))
    assert not both(a, vol(mirror - 0.5 * n, alt, (t[0] - 30.0, t[0])))
    assert not both(a, vol(mirror, alt, t))


# ------------------------------------------------------------------------------ independent reference
def _clip(subject: np.ndarray, clipper: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman: the convex polygon ``subject`` clipped by the convex, counter-clockwise
    ``clipper`` (both (n, 2))."""
    out = subject
    m = len(clipper)
    for i in range(m):
        a, b = clipper[i], clipper[(i + 1) % m]
        if not len(out):
            break

        def inside(p, a=a, b=b):
            return (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]) >= 0

        def cut(p, q, a=a, b=b):
            d1 = (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])
            d2 = (b[0] - a[0]) * (q[1] - a[1]) - (b[1] - a[1]) * (q[0] - a[0])
            return p + (q - p) * (d1 / (d1 - d2))

        res = []
        for j in range(len(out)):
            p, q = out[j], out[(j + 1) % len(out)]
            if inside(q):
                if not inside(p):
                    res.append(cut(p, q))
                res.append(q)
            elif inside(p):
                res.append(cut(p, q))
        out = np.array(res).reshape(-1, 2)
    return out


def _area(xy: np.ndarray) -> float:
    if len(xy) < 3:
        return 0.0
    x, y = xy[:, 0] - xy[0, 0], xy[:, 1] - xy[0, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


@SETTINGS
@given(convex(r_max=30.0), convex(r_max=30.0), st.floats(-40, 40), st.floats(-40, 40), band, band, window, window)
def test_against_clipping_and_interval_arithmetic(p, q, dx, dy, alt_a, alt_b, t_a, t_b):
    """Random pairs near each other: the exact test equals (clipped area > 1e-4 m^2) and (the
    altitude overlap > 0) and (the time overlap > 0), computed here without shapely (pairs
    within 1e-9 of a threshold are skipped: there either answer is right)."""
    q = q - q.mean(axis=0) + p.mean(axis=0) + [dx, dy]
    area = _area(_clip(q, p))
    d_alt = min(alt_a[1], alt_b[1]) - max(alt_a[0], alt_b[0])
    d_t = min(t_a[1], t_b[1]) - max(t_a[0], t_b[0])
    assume(abs(area - MIN_AREA_M2) > 1e-6 and abs(d_alt) > 1e-9 and abs(d_t) > 1e-9)
    assert abs(shapely.Polygon(p).intersection(shapely.Polygon(q)).area - area) < 1e-6 * max(1.0, area)
    ref = area > MIN_AREA_M2 and d_alt > 0 and d_t > 0
    assert both(vol(p, alt_a, t_a), vol(q, alt_b, t_b)) == ref


def test_the_references_can_fail():
    """The clipping reference is not vacuous: a 2 x 2 m square and one shifted by 1 m share 2 m^2."""
    a = np.array([[0, 0], [2, 0], [2, 2], [0, 2]], float)
    assert _area(_clip(a + [1, 0], a)) == 2.0
    assert _area(_clip(a + [2.01, 0], a)) == 0.0
    assert both(vol(a, (0, 1), (0, 1)), vol(a + [1.0, 0.0], (0.5, 2), (0.5, 2)))
