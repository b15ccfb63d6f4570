"""ASTM F3548 operational intents of a plan (stages/intents.py)."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import shapely
from pyproj import Transformer

from skyroute.stages import intents
from skyroute.stages.base import InputError
from skyroute.stages.geoid import height_reference
from skyroute.stages.smoothing import KinematicLimits, corner_trajectory
from skyroute.stages.vehicle import load_vehicle

CRS = "EPSG:32635"   # UTM 35N (Helsinki)
START = "2026-06-01T10:00:00Z"
# a chain with a climb, two fillet corners and a descent [m]
CHAIN = np.array([[385000.0, 6672000.0, 30.0], [385400.0, 6672050.0, 60.0], [385500.0, 6672400.0, 60.0],
                  [385200.0, 6672700.0, 45.0]])
REF = height_reference("local ground (flat terrain, heights above ground level)", 35.0, "WGS 84 ellipsoid")


@pytest.fixture(scope="module")
def plan():
    veh = load_vehicle("dji-m300-rtk")
    traj = corner_trajectory(CHAIN, np.full(3, 12.0), KinematicLimits.of(veh))
    assert (np.asarray(traj.kind) == 1).any()   # arcs present
    t0 = 60.0
    t_s = t0 + traj.sample_times(0.5)
    sigma = 0.8 + 0.4 * np.sin(t_s / 17.0) ** 2
    to_ll = Transformer.from_crs(CRS, 4326, always_xy=True)

    def h_w84(p):
        lon, lat = to_ll.transform(p[:, 0], p[:, 1])
        return REF.ellipsoidal_m(lon, lat, p[:, 2])

    kw = dict(vehicle_radius_m=0.6, k_sigma=3.0, time_buffer_s=5.0, max_volume_s=15.0)
    vols = intents.plan_volumes(traj, t0, t_s, sigma, h_w84, **kw)
    doc = intents.intent_details(vols, CRS, START, priority=3)
    return traj, t0, t_s, sigma, h_w84, kw, vols, doc


def _dense(traj, t0, dt=0.01):
    tau = np.arange(0.0, traj.duration_s, dt)
    tau = np.append(tau, traj.duration_s)
    p = traj.sample(tau)
    lon, lat = Transformer.from_crs(CRS, 4326, always_xy=True).transform(p[:, 0], p[:, 1])
    h = REF.ellipsoidal_m(lon, lat, p[:, 2])
    t = pd.Timestamp(START) + pd.to_timedelta(t0 + tau, unit="s")
    return p, np.asarray(lon), np.asarray(lat), h, t


def test_volumes_contain_the_whole_trajectory(plan):
    traj, t0, *_, doc = plan
    _, lon, lat, h, t = _dense(traj, t0)
    assert intents.intent_conformance(doc, lon, lat, h, t) == 1.0
    # the time buffer: a vehicle 4.9 s late still conforms, 60 s late does not everywhere
    assert intents.intent_conformance(doc, lon, lat, h, t + pd.Timedelta(seconds=4.9)) == 1.0
    assert intents.intent_conformance(doc, lon, lat, h, t + pd.Timedelta(seconds=60)) < 0.9


def test_buffer_is_tight_on_straight_legs(plan):
    """A point beside a straight leg at the buffer + 0.3 m (horizontally, same time and
    height) is outside every volume valid then; at buffer - 0.3 m inside."""
    traj, t0, t_s, sigma, _, kw, vols, doc = plan
    line = np.flatnonzero(np.asarray(traj.kind) == 0)
    ph = line[np.argmax(np.diff(np.append(traj.phase_t0_s, traj.duration_s))[line])]
    tau = traj.phase_t0_s[ph] + 0.5 * (np.append(traj.phase_t0_s, traj.duration_s)[ph + 1] - traj.phase_t0_s[ph])
    p = traj.sample([tau])[0]
    v = traj.velocity([tau])[0]
    nrm = np.array([-v[1], v[0]]) / np.hypot(v[0], v[1])
    vol = next(x for x in vols if x.t_start_s + kw["time_buffer_s"] <= t0 + tau <= x.t_end_s - kw["time_buffer_s"])
    to_ll = Transformer.from_crs(CRS, 4326, always_xy=True)
    t = [pd.Timestamp(START) + pd.Timedelta(seconds=t0 + tau)]
    for side in (1, -1):
        for off, want in ((vol.buffer_m + 0.3, False), (vol.buffer_m - 0.3, True)):
            q = p[:2] + side * off * nrm
            lon, lat = to_ll.transform([q[0]], [q[1]])
            inside = intents.intent_conformance({"volumes": [v for v, x in zip(doc["volumes"], vols, strict=True)
                                                             if x is vol]}, lon, lat, REF.ellipsoidal_m(lon, lat, [p[2]]), t)
            assert inside == float(want), (side, off)
    # the horizontal buffer is k sigma + vehicle radius (+ 5 cm margin + 10 cm simplification) of the
    # bracketing samples
    s = intents._sigma_bracket(t_s, sigma, vol.t_start_s + 5.0, vol.t_end_s - 5.0)
    assert kw["k_sigma"] * s + kw["vehicle_radius_m"] <= vol.buffer_m <= kw["k_sigma"] * s + kw["vehicle_radius_m"] + 0.16


def test_round_trip_through_uas_standards(plan):
    *_, doc = plan
    oi = intents.parse_intent(json.loads(json.dumps(doc)))
    assert json.loads(json.dumps(oi)) == doc
    assert oi.priority == 3
    for v in oi.volumes:
        assert v.time_start.value.endswith("Z") and v.time_end.value.datetime > v.time_start.value.datetime
        assert v.volume.altitude_lower.reference == "W84" and v.volume.altitude_upper.value > v.volume.altitude_lower.value
    assert sum(len(v.volume.outline_polygon.vertices) for v in oi.volumes) <= intents.MAX_VERTICES
    # limits are enforced on foreign documents too
    bad = json.loads(json.dumps(doc))
    bad["volumes"][0]["time_end"] = dict(bad["volumes"][0]["time_start"])
    with pytest.raises(InputError, match="not after"):
        intents.parse_intent(bad)
    bad = json.loads(json.dumps(doc))
    bad["volumes"][0]["time_start"]["value"] = bad["volumes"][0]["time_start"]["value"][:-1] + "+00:00"
    with pytest.raises(InputError, match="ending in Z"):
        intents.parse_intent(bad)
    bad = json.loads(json.dumps(doc))
    vx = bad["volumes"][0]["volume"]["outline_polygon"]["vertices"]
    vx.append(dict(vx[0]))      # a closed ring: F3548 forbids the repeated closing vertex
    with pytest.raises(InputError, match="none repeated"):
        intents.parse_intent(bad)


def test_vertex_limit_merges_volumes(plan):
    traj, t0, t_s, sigma, h_w84, kw, vols, _ = plan
    few = intents.plan_volumes(traj, t0, t_s, sigma, h_w84, **kw, max_vertices=200)
    assert sum(v.outline_xy_m.shape[0] for v in few) <= 200 < sum(v.outline_xy_m.shape[0] for v in vols)
    doc = intents.intent_details(few, CRS, START)
    _, lon, lat, h, t = _dense(traj, t0, 0.05)
    assert intents.intent_conformance(doc, lon, lat, h, t) == 1.0


def test_zero_buffers_still_contain_the_arcs(plan):
    """k = 0, no vehicle radius: the chord margin alone keeps the fillet arcs inside (an
    independent dense sampling at 1 cm of arc length)."""
    traj, t0, t_s, sigma, h_w84, kw, _, _ = plan
    vols = intents.plan_volumes(traj, t0, t_s, sigma, h_w84, vehicle_radius_m=0.0, k_sigma=0.0, time_buffer_s=0.0,
                                spacing_m=5.0, margin_m=0.01, simplify_m=0.0)
    polys = [shapely.Polygon(v.outline_xy_m) for v in vols]
    p, *_ = _dense(traj, t0, 0.001)
    tau = np.append(np.arange(0.0, traj.duration_s, 0.001), traj.duration_s)
    ok = np.zeros(len(p), bool)
    for poly, v in zip(polys, vols, strict=True):
        m = (t0 + tau >= v.t_start_s) & (t0 + tau <= v.t_end_s)
        m[m] = shapely.contains_xy(poly.buffer(1e-6), p[m, 0], p[m, 1])
        ok |= m
    assert ok.all()


def test_volumes_are_small(plan):
    """As small as practical: the outlines' area is within 15 % of the exact neighbourhood of
    the path (each chunk's path buffered by its own radius, 64 segments per quarter circle)."""
    traj, t0, *_, kw, vols, _ = plan
    exact, ours = [], []
    for v in vols:
        tau = np.linspace(v.t_start_s + kw["time_buffer_s"] - t0, v.t_end_s - kw["time_buffer_s"] - t0, 400)
        exact.append(shapely.LineString(traj.sample(tau)[:, :2]).buffer(v.buffer_m, quad_segs=64))
        ours.append(shapely.Polygon(v.outline_xy_m))
    ratio = shapely.union_all(ours).area / shapely.union_all(exact).area
    assert 1.0 <= ratio < 1.15, ratio
    print(f"outline area / exact neighbourhood = {ratio:.4f}, {len(vols)} volumes, "
          f"{sum(v.outline_xy_m.shape[0] for v in vols)} vertices")


def test_bad_inputs():
    veh = load_vehicle("dji-m300-rtk")
    traj = corner_trajectory(CHAIN[:2], np.full(1, 10.0), KinematicLimits.of(veh))
    t_s = traj.sample_times(0.5)
    with pytest.raises(InputError, match="sigma_p"):
        intents.plan_volumes(traj, 0.0, t_s, np.full(t_s.size, np.nan), lambda p: p[:, 2], vehicle_radius_m=0.5)
    with pytest.raises(InputError, match="vehicle_radius_m"):
        intents.plan_volumes(traj, 0.0, t_s, np.ones(t_s.size), lambda p: p[:, 2], vehicle_radius_m=-1.0)


def test_altitude_bands_are_thin(plan):
    """Each band is the chunk's height range (<= max_dz_m = 10 m, the default) plus the buffer
    above and below (ellipsoidal offset is a constant here: local ground on the ellipsoid)."""
    traj, t0, t_s, sigma, _, kw, vols, _ = plan
    for v in vols:
        tau = np.linspace(v.t_start_s + 5.0 - t0, v.t_end_s - 5.0 - t0, 500)
        z = traj.sample(tau)[:, 2]
        assert np.ptp(z) <= 10.0 + 1e-6
        r_v = v.buffer_m - 0.05 - 0.1          # the margin and simplification are horizontal only
        assert v.alt_lower_m == pytest.approx(z.min() + 35.0 - r_v, abs=0.011)
        assert v.alt_upper_m == pytest.approx(z.max() + 35.0 + r_v, abs=0.011)
