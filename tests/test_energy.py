"""Vehicle profiles and the segment energy model of seed 000 (eq. 2-13), checked by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from skyroute.pipeline.errors import DataError, InputError, ScenarioError, UnknownNameError
from skyroute.stages import energy as E
from skyroute.stages.vehicle import G0, VehicleProfile, known_vehicles, load_vehicle

RHO = 1.225


@pytest.fixture(scope="module")
def m300() -> VehicleProfile:
    return load_vehicle("dji-m300-rtk")


# ---------------------------------------------------------------- vehicle catalog

def test_m300_matches_table_1(m300):
    assert m300.battery_capacity_mah == 11870
    assert (m300.max_airspeed_mps, m300.max_wind_mps, m300.cruise_speed_mps) == (23, 15, 10)
    assert m300.max_flight_path_angle_deg == 15
    assert (m300.max_position_error_m, m300.safety_distance_m, m300.safety_factor) == (2, 3, 1)
    assert m300.imu.accel_bias_instability_mg == 0.20
    assert m300.imu.velocity_random_walk_mps_per_sqrt_h == 0.15
    assert (m300.min_altitude_m, m300.max_altitude_m) == (0, 80)
    assert m300.r_p_m == pytest.approx(3 + 1 * 2)                     # eq. 13
    assert m300.battery_energy_j == pytest.approx(11.870 * 52.8 * 3600)   # 627 Wh
    assert m300.imu.accel_bias_sigma_mps2 == pytest.approx(0.2e-3 * 9.80665)
    assert m300.imu.vrw_mps_per_sqrt_s == pytest.approx(0.15 / 60)
    assert "dji-m300-rtk" in known_vehicles()


def test_blade_coefficients_by_hand(m300):
    r = m300.rotor
    theta = math.atan(0.254 / (math.pi * 0.5334))                    # 2110 prop: 8.62 deg
    assert r.blade_angle_rad == pytest.approx(theta)
    ct = 0.75 * 0.5**2 * 2 * 6.11 * (0.85 * theta - 0) / (math.pi * 5 + 6.11)   # eq. 8
    assert r.thrust_coefficient == pytest.approx(ct) and ct == pytest.approx(0.01343, abs=1e-5)
    assert r.solidity == pytest.approx(2 * 2 / (math.pi * 5))
    cd = 0.015 + math.pi * 5 * 6.11**2 * (0.85 * theta) ** 2 / (0.83 * (math.pi * 5 + 6.11) ** 2)
    assert r.blade_drag_coefficient == pytest.approx(cd)


def test_unknown_vehicle():
    with pytest.raises(UnknownNameError, match="unknown vehicle 'dji-m9'.*dji-m300-rtk"):
        load_vehicle("dji-m9")


def test_vehicle_from_path_and_invalid(tmp_path, m300):
    import yaml

    good = tmp_path / "v.yaml"
    good.write_text(yaml.safe_dump(m300.model_dump(mode="json")))
    assert load_vehicle(good) == m300
    bad = m300.model_dump(mode="json")
    bad["cruise_speed_mps"] = -1
    bad["colour"] = "red"
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(bad))
    with pytest.raises(ScenarioError, match=r"(?s)2 problem.*cruise_speed_mps.*colour"):
        load_vehicle(p)
    with pytest.raises(DataError, match="not found"):
        load_vehicle(tmp_path / "missing.yaml")


# ---------------------------------------------------------------- hand-computed segment

def _trim(m300, v):
    """Scalar trim by hand: T t = W z + q S d, S = S_side sqrt(1-(d.t)^2) + S_top |d.t|."""
    W = m300.weight_n
    sp = math.sqrt(sum(c * c for c in v))
    d = [c / sp for c in v]
    q = 0.5 * RHO * sp * sp
    t = [0.0, 0.0, 1.0]
    for _ in range(200):
        c = abs(sum(a * b for a, b in zip(d, t, strict=True)))
        S = 0.10 * math.sqrt(1 - c * c) + 0.15 * c
        tv = [q * S * d[0], q * S * d[1], q * S * d[2] + W]
        T = math.sqrt(sum(x * x for x in tv))
        t = [x / T for x in tv]
    return T, S


def test_one_segment_by_hand(m300):
    # 100 m towards east, level, wind blowing towards west-north-west: w = (-4, 3, 0) m/s
    p0, p1, w = np.array([[0.0, 0, 30]]), np.array([[100.0, 0, 30]]), np.array([[-4.0, 3, 0]])
    # eq. 2: v_a = 10 e - w = (14, -3, 0), |v_a| = 14.32 < 23 and v_a(s) = 14 > 0 -> v_g = v_c
    tau = 100 / 10                                                      # eq. 4
    va = (14.0, -3.0, 0.0)
    T, S = _trim(m300, va)
    speed = math.hypot(14, 3)
    R, A = 0.2667, 4 * math.pi * 0.2667**2
    theta = math.atan(0.254 / (math.pi * 0.5334))
    ct = 0.75 * 0.25 * 2 * 6.11 * 0.85 * theta / (5 * math.pi + 6.11)
    cd = 0.015 + math.pi * 5 * 6.11**2 * (0.85 * theta) ** 2 / (0.83 * (5 * math.pi + 6.11) ** 2)
    sigma = 4 / (5 * math.pi)
    omega = math.sqrt(T / 4 / (RHO * math.pi * R**4 * ct))             # eq. 10
    p_ind = 1.15 * T**1.5 / math.sqrt(2 * RHO * A)                      # eq. 6-7 = momentum theory
    p_prof = 4 * RHO * math.pi * R**2 * (omega * R) ** 3 * sigma * cd / 8 * (1 + 4.65 * (14 / (omega * R)) ** 2)
    p_par = 0.5 * RHO * S * speed**3
    e_w = (p_ind + p_prof + p_par) * tau
    # no wind: airspeed 10 m/s along the segment
    T0, S0 = _trim(m300, (10.0, 0, 0))
    om0 = math.sqrt(T0 / 4 / (RHO * math.pi * R**4 * ct))
    p0w = (1.15 * T0**1.5 / math.sqrt(2 * RHO * A)
           + 4 * RHO * math.pi * R**2 * (om0 * R) ** 3 * sigma * cd / 8 * (1 + 4.65 * (10 / (om0 * R)) ** 2)
           + 0.5 * RHO * S0 * 10**3)
    e_0 = p0w * 10
    r = E.segment_energy(p0, p1, w, m300)
    assert r["time_s"][0] == pytest.approx(tau, abs=1e-9)
    assert r["energy_J"][0] == pytest.approx(e_w, rel=1e-9)
    assert r["energy_nowind_J"][0] == pytest.approx(e_0, rel=1e-9)
    assert r["airspeed_mps"][0] == pytest.approx(speed)
    assert E.energy_cost(p0, p1, w, m300)[0] == pytest.approx(e_w / e_0 * 100, rel=1e-9)  # eq. 12
    # magnitudes: ~1.1 kW with 14.3 m/s airspeed, ~0.96 kW at 10 m/s
    assert 900 < e_w / tau < 1400 and 800 < e_0 / 10 < 1100


def test_m_minus_and_m_plus_ground_speeds_by_hand(m300):
    p0, p1 = np.zeros((3, 3)), np.array([[0.0, 100, 0]] * 3)       # 100 m towards north
    wind = np.array([[0.0, -14, 0],      # head wind 14: |v_a| = 24 > 23 -> airspeed 0.8*23 = 18.4
                     [6.0, -13, 0],      # head 13 + cross 6: |v_a| = 23.8; g = -13 + sqrt(18.4^2 - 36)
                     [0.0, 12, 0]])      # tail wind 12 > v_c: m_+ -> g = 12, airspeed 0
    r = E.segment_energy(p0, p1, wind, m300)
    g = np.array([-14 + 18.4, -13 + math.sqrt(18.4**2 - 36), 12.0])
    np.testing.assert_allclose(r["ground_speed_mps"], g, rtol=1e-12)
    np.testing.assert_allclose(r["time_s"], 100 / g, rtol=1e-12)
    np.testing.assert_allclose(r["airspeed_mps"][:2], 18.4, rtol=1e-12)
    # m_+: hovering in the air mass: P = kappa W^1.5/sqrt(2 rho A) + sigma Cd/8 profile at mu = 0
    W, R = m300.weight_n, 0.2667
    om = math.sqrt(W / 4 / (RHO * math.pi * R**4 * m300.rotor.thrust_coefficient))
    p_h = (1.15 * W**1.5 / math.sqrt(2 * RHO * 4 * math.pi * R**2)
           + 4 * RHO * math.pi * R**2 * (om * R) ** 3 * m300.rotor.solidity * m300.rotor.blade_drag_coefficient / 8)
    assert r["energy_J"][2] == pytest.approx(p_h * 100 / 12, rel=1e-9)
    assert r["airspeed_mps"][2] == pytest.approx(0, abs=1e-12)


# ---------------------------------------------------------------- limits

def test_no_wind_ratio_is_one(m300):
    rng = np.random.default_rng(1)
    p0 = rng.uniform(-100, 100, (50, 3))
    p1 = p0 + rng.uniform(-80, 80, (50, 3))
    c = E.energy_cost(p0, p1, np.zeros((50, 3)), m300)
    np.testing.assert_allclose(c, np.linalg.norm(p1 - p0, axis=1), rtol=1e-12)


def test_tailwind_reduces_headwind_increases(m300):
    p0, p1 = np.zeros((1, 3)), np.array([[200.0, 0, 0]])
    e = [E.segment_energy(p0, p1, np.array([[u, 0, 0]]), m300)["energy_J"][0] for u in (-8, -4, 0, 4, 8)]
    assert all(a > b for a, b in zip(e, e[1:], strict=False))     # monotone in tail wind
    assert e[3] < e[2] * 0.95


def test_wind_limits_make_segment_unflyable(m300):
    p0, p1 = np.zeros((3, 3)), np.array([[100.0, 0, 0]] * 3)
    wind = np.array([[-15.0, 0, 0], [-16.0, 0, 0], [0.0, 19, 0]])   # at limit / above / cross > 18.4
    r = E.segment_energy(p0, p1, wind, m300)
    assert r["flyable"].tolist() == [True, False, False]
    assert np.isinf(r["energy_J"][1:]).all() and np.isinf(E.energy_cost(p0, p1, wind, m300)[1:]).all()
    # v_min: a vehicle with v_min = 4 m/s cannot hold 18.4 - 15 = 3.4 m/s against 15 m/s
    slow = m300.model_copy(update={"min_ground_speed_mps": 4.0})
    assert not E.segment_energy(p0[:1], p1[:1], wind[:1], slow)["flyable"][0]


def test_climb_costs_more_descent_half(m300):
    pw = E.rotor_power(np.zeros((3, 3)), np.zeros(3), np.array([2.0, 0.0, -2.0]), m300)
    W = m300.weight_n
    np.testing.assert_allclose(pw["climb_W"], [2 * W, 0, W], rtol=1e-12)     # m g v_z, half down
    assert pw["climb_W"][2] == pytest.approx(0.5 * pw["climb_W"][0])
    p0 = np.zeros((3, 3))
    p1 = np.array([[100.0, 0, 15], [100.0, 0, 0], [100.0, 0, -15]])
    r = E.segment_energy(p0, p1, np.zeros((3, 3)), m300)
    assert r["power_W"][0] > r["power_W"][2] > r["power_W"][1]
    # the climb term of a whole segment: E_climb - E_level(same airspeed) ~ m g dz
    vz = 10 * 15 / math.hypot(100, 15)
    pc = E.rotor_power(np.array([[10 * 100 / math.hypot(100, 15), 0, vz]] * 2), [10.0, 10.0], [vz, -vz], m300)
    assert (pc["total_W"][0] - pc["total_W"][1]) * r["time_s"][0] == pytest.approx(0.5 * W * 15, rel=1e-9)
    assert r["flight_path_angle_deg"][0] == pytest.approx(math.degrees(math.atan2(15, 100)))


def test_subsegments_sample_wind_callable(m300):
    p0, p1 = np.array([[0.0, 0, 10], [0.0, 0, 10]]), np.array([[100.0, 0, 10], [95.0, 0, 10]])
    uniform = E.segment_energy(p0, p1, lambda x: np.tile([3.0, -2.0, 0.0], (len(x), 1)), m300)
    arr = E.segment_energy(p0, p1, np.array([[3.0, -2, 0]] * 2), m300)
    for k in ("time_s", "energy_J", "energy_nowind_J"):
        np.testing.assert_allclose(uniform[k], arr[k], rtol=1e-12)
    # wind sampled at the START of each 10 m sub-segment: starts 0..40 calm, 50..90 tail 5 m/s
    step = E.segment_energy(p0[:1], p1[:1], lambda x: np.where(x[:, :1] >= 49.0, [[5.0, 0, 0]], [[0.0, 0, 0]]),
                            m300, subsegment_m=10.0)
    calm = E.segment_energy(p0[:1], p1[:1], np.zeros((1, 3)), m300)
    tail = E.segment_energy(p0[:1], p1[:1], np.array([[5.0, 0, 0]]), m300)
    assert step["energy_J"][0] == pytest.approx(0.5 * (calm["energy_J"][0] + tail["energy_J"][0]), rel=1e-12)
    assert step["time_s"][0] == pytest.approx(10.0)


def test_vectorised_matches_loop_and_dataset(m300):
    rng = np.random.default_rng(7)
    n = 40
    p0 = rng.uniform(0, 500, (n, 3))
    p1 = p0 + rng.normal(0, 60, (n, 3))
    w = rng.normal(0, 5, (n, 3))
    r = E.segment_energy(p0, p1, w, m300)
    for j in range(0, n, 7):
        rj = E.segment_energy(p0[j], p1[j], w[j], m300)
        for k in ("time_s", "energy_J", "energy_nowind_J"):
            assert rj[k][0] == pytest.approx(r[k][j], rel=1e-12)
    ds = E.segment_energy_dataset(p0, p1, w, m300)
    assert ds.sizes["segment"] == n and ds["energy_J"].attrs["units"] == "J"
    np.testing.assert_allclose(ds["energy_cost_m"].values, E.energy_cost(p0, p1, w, m300))


def test_zero_length_and_bad_input(m300):
    r = E.segment_energy(np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 3)), m300)
    assert r["time_s"][0] == 0 and r["energy_J"][0] == 0 and r["flyable"][0]
    assert E.energy_cost(np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 3)), m300)[0] == 0
    with pytest.raises(InputError, match=r"shape \(n, 3\)"):
        E.segment_energy(np.zeros((2, 2)), np.zeros((2, 2)), np.zeros((2, 3)), m300)
    with pytest.raises(InputError, match="wind_uvw must have shape"):
        E.segment_energy(np.zeros((2, 3)), np.ones((2, 3)), np.zeros((3, 3)), m300)
    with pytest.raises(InputError, match="NaN"):
        E.segment_energy(np.zeros((1, 3)), np.ones((1, 3)), np.full((1, 3), np.nan), m300)


def test_g0_consistent():
    assert G0 == 9.80665
