"""Vehicle profiles: the rotorcraft constraints of seed 000 Table I plus the rotor/airframe
parameters that the energy model (seed 000 eq. 5-10, :mod:`skyroute.stages.energy`) needs.

Profiles live in the YAML catalog ``catalogs/vehicles/<name>.yaml`` (each value documented
there with its source: seed 000 Table I, the manufacturer's spec sheet, or ``assumed``).
:func:`load_vehicle` reads one by name or by path.

Derived quantities (properties of :class:`VehicleProfile`):

* ``r_p_m`` = d_m + K_m * dp_max, the collision-sphere radius [m] (seed 000 eq. 13);
* ``rotor.thrust_coefficient`` C_t (eq. 8), ``rotor.blade_drag_coefficient`` C_d,
  ``rotor.solidity`` sigma = 2 B_b / (pi AR_b) (text after eq. 9), ``rotor.blade_angle_rad``;
* ``battery_energy_j`` = capacity [mAh] * 3.6 * voltage [V] [J].

Hard kinematic limits (tolerance 0 in STEP III and in the validator): ``max_airspeed_mps``,
``max_flight_path_angle_deg``, ``max_climb_rate_mps`` / ``max_descent_rate_mps`` (vertical
speed [m/s], both positive) and ``max_acceleration_mps2`` (norm of the 3-D acceleration
[m/s^2]).  They are required: a profile without them does not load.

Fixed-wing aircraft (seed 002, Aiello et al.) are :class:`FixedWingProfile` (``kind: fixed-wing``
in the YAML): airframe, drag polar and limits; the drag polar ``D/L = A V^2 + B / V^2`` (seed 002
eq. 4-6), the Carson speed, stall speed and minimum turn radius are its properties.  The profile
is a discriminated union on ``kind`` (``multirotor``, the default, so older YAML still loads:
:class:`VehicleProfile`; ``fixed-wing``: :class:`FixedWingProfile`); :func:`load_vehicle`
returns the right type and every stage reads a vehicle through it.
"""

from __future__ import annotations

import math
from importlib.resources import files
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, ValidationError, model_validator

from skyroute.stages.base import DataError, FrozenModel, ScenarioError, UnknownNameError
from skyroute.stages.yaml_io import read_yaml_text

Pos = Annotated[float, Field(gt=0)]
NonNeg = Annotated[float, Field(ge=0)]

G0 = 9.80665  # standard gravity [m/s^2]
RHO_SL = 1.225  # ISA sea-level air density [kg/m^3]


class ImuSpec(FrozenModel):
    """Accelerometer figures used by the covariance analysis (:mod:`skyroute.stages.navigation`).

    ``accel_bias_instability_mg`` is the in-run bias stability [mg] (1 mg = 9.80665e-3 m/s^2),
    modelled as a first-order Gauss-Markov bias with steady-state sigma equal to it and
    correlation time ``accel_bias_correlation_time_s`` [s]; ``velocity_random_walk_mps_per_sqrt_h``
    [m/s/sqrt(h)] is the white accelerometer noise (process noise on velocity)."""

    accel_bias_instability_mg: Pos
    velocity_random_walk_mps_per_sqrt_h: Pos
    accel_bias_correlation_time_s: Pos = 3600.0

    @property
    def accel_bias_sigma_mps2(self) -> float:
        """In-run bias stability [m/s^2]."""
        return self.accel_bias_instability_mg * 1e-3 * G0

    @property
    def vrw_mps_per_sqrt_s(self) -> float:
        """Velocity random walk [m/s/sqrt(s)] (= sqrt of the accel white-noise PSD [m^2/s^3])."""
        return self.velocity_random_walk_mps_per_sqrt_h / 60.0


class AirframeSpec(FrozenModel):
    """Mass and body drag.  The drag area seen by the air flow depends on the attitude
    (seed 000: "drag vector, which depends on orientation"): with ``d`` the unit airspeed
    vector and ``t`` the thrust (body-up) axis,
    ``S = drag_area_side_m2 * sqrt(1 - (d.t)^2) + drag_area_top_m2 * |d.t|``  [m^2]
    (C_D * area, i.e. equivalent flat-plate areas; rotationally symmetric body)."""

    mass_kg: Pos
    payload_kg: NonNeg = 0.0
    drag_area_side_m2: NonNeg
    drag_area_top_m2: NonNeg

    @property
    def total_mass_kg(self) -> float:
        return self.mass_kg + self.payload_kg


class RotorSpec(FrozenModel):
    """Rotors and blades (seed 000 eq. 6-10; blade-element coefficients of eq. 8 and the
    blade drag coefficient as in Quan, *Introduction to Multicopter Design and Control*,
    Springer 2017, ch. 4, whose ``C_T`` for rpm becomes eq. 8 with Omega in rad/s)."""

    count: Annotated[int, Field(ge=1)]                 # N_b, number of rotors
    radius_m: Pos                                      # r_b = R_b
    blade_count: Annotated[int, Field(ge=1)]           # B_b
    pitch_m: Pos                                       # geometric propeller pitch H_p
    blade_aspect_ratio: Pos                            # AR_b = D_p / c_b
    zero_lift_angle_deg: float = 0.0                   # alpha_b
    downwash_factor: Pos = 0.85                        # epsilon
    correction_lambda: Pos = 0.75                      # lambda
    correction_zeta: Pos = 0.5                         # zeta
    lift_slope: Pos = 6.11                             # eta_0 (K_0), lift-curve slope [1/rad]
    oswald_factor: Pos = 0.83                          # e, for the blade induced drag
    zero_lift_drag_coefficient: Pos = 0.015            # C_fd
    induced_power_factor: Pos = 1.15                   # kappa (eq. 7)
    profile_advance_factor: NonNeg = 4.65              # K_v (eq. 9)

    @property
    def blade_angle_rad(self) -> float:
        """theta_b = atan(H_p / (pi D_p)) [rad], the pitch-helix angle at the tip (Quan 2017)."""
        return math.atan(self.pitch_m / (math.pi * 2.0 * self.radius_m))

    @property
    def solidity(self) -> float:
        """sigma = 2 B_b / (pi AR_b) (seed 000, after eq. 9)."""
        return 2.0 * self.blade_count / (math.pi * self.blade_aspect_ratio)

    @property
    def chord_m(self) -> float:
        """Mean blade chord D_p / AR_b [m] (informative)."""
        return 2.0 * self.radius_m / self.blade_aspect_ratio

    @property
    def thrust_coefficient(self) -> float:
        """C_t of eq. 8 (T = C_t rho pi R^4 Omega^2 per rotor)."""
        a = math.radians(self.zero_lift_angle_deg)
        ar = self.blade_aspect_ratio
        return (self.correction_lambda * self.correction_zeta**2 * self.blade_count * self.lift_slope
                * (self.downwash_factor * self.blade_angle_rad - a) / (math.pi * ar + self.lift_slope))

    @property
    def blade_drag_coefficient(self) -> float:
        """C_d = C_fd + pi AR K0^2 (eps theta - alpha0)^2 / (e (pi AR + K0)^2) (Quan 2017)."""
        a = math.radians(self.zero_lift_angle_deg)
        ar, k0 = self.blade_aspect_ratio, self.lift_slope
        return (self.zero_lift_drag_coefficient
                + math.pi * ar * k0**2 * (self.downwash_factor * self.blade_angle_rad - a) ** 2
                / (self.oswald_factor * (math.pi * ar + k0) ** 2))

    @property
    def disc_area_m2(self) -> float:
        """Total rotor disc area N_b pi R^2 [m^2]."""
        return self.count * math.pi * self.radius_m**2


class _SphereAndBattery:
    """The collision sphere and battery energy every vehicle kind derives the same way (its
    fields ``safety_distance_m``, ``safety_factor``, ``max_position_error_m``,
    ``battery_capacity_mah``, ``battery_voltage_v``)."""

    @property
    def r_p_m(self) -> float:
        """Collision-sphere radius r_p = d_m + K_m dp_max [m] (seed 000 eq. 13)."""
        return self.safety_distance_m + self.safety_factor * self.max_position_error_m

    @property
    def battery_energy_j(self) -> float:
        """Battery energy [J] = capacity [mAh] * 3.6 [C/mAh] * voltage [V]."""
        return self.battery_capacity_mah * 3.6 * self.battery_voltage_v


class VehicleProfile(_SphereAndBattery, FrozenModel):
    """A rotorcraft profile: constraints of seed 000 Table I plus energy-model parameters."""

    name: str
    kind: Literal["multirotor"] = "multirotor"
    description: str = ""
    references: tuple[str, ...] = ()
    # seed 000 Table I
    battery_capacity_mah: Pos                          # xi
    max_airspeed_mps: Pos                              # v_max
    max_wind_mps: Pos
    cruise_speed_mps: Pos                              # v_c
    max_flight_path_angle_deg: Annotated[float, Field(gt=0, le=90)]   # alpha
    max_position_error_m: Pos                          # dp_max
    safety_distance_m: NonNeg                          # d_m
    safety_factor: Annotated[float, Field(ge=1)] = 1.0  # K_m >= 1
    min_altitude_m: float = 0.0
    max_altitude_m: float
    imu: ImuSpec
    # hard kinematic limits of the smoothed trajectory (STEP III, :mod:`skyroute.stages.smoothing`)
    max_climb_rate_mps: Pos                            # vertical speed up [m/s]
    max_descent_rate_mps: Pos                          # vertical speed down [m/s] (a positive number)
    max_acceleration_mps2: Pos                         # |d^2 p / dt^2| [m/s^2], 3-D norm
    # not in Table I
    min_ground_speed_mps: NonNeg = 0.0                 # v_min of eq. 3
    battery_voltage_v: Pos
    airframe: AirframeSpec
    rotor: RotorSpec

    @model_validator(mode="after")
    def _check(self) -> VehicleProfile:
        if self.cruise_speed_mps > self.max_airspeed_mps:
            raise ValueError(f"cruise_speed_mps {self.cruise_speed_mps} exceeds max_airspeed_mps "
                             f"{self.max_airspeed_mps}")
        if self.min_ground_speed_mps >= self.cruise_speed_mps:
            raise ValueError("min_ground_speed_mps must be below cruise_speed_mps")
        if self.max_altitude_m <= self.min_altitude_m:
            raise ValueError("max_altitude_m must exceed min_altitude_m")
        return self

    @property
    def weight_n(self) -> float:
        """Take-off weight m g [N]."""
        return self.airframe.total_mass_kg * G0


# The drag polar of seed 002 eq. 4-6 and the speeds derived from it: plain arithmetic, the one
# home of each formula (the profile's properties call them; the compiled kernels of
# :mod:`skyroute.stages.fixedwing_energy` compile these same functions with numba).
def polar_a(rho_kgpm3: float, parasite_area_m2: float, weight_n: float) -> float:
    """A = rho f / (2 W) [s^2/m^2] (seed 002 eq. 5)."""
    return rho_kgpm3 * parasite_area_m2 / (2.0 * weight_n)


def polar_b(rho_kgpm3: float, weight_n: float, span_m: float, oswald: float) -> float:
    """B = 2 W / (rho b^2 pi e) [m^2/s^2] (seed 002 eq. 6)."""
    return 2.0 * weight_n / (rho_kgpm3 * span_m * span_m * math.pi * oswald)


def carson_speed(a: float, b: float) -> float:
    """V_opt = (B / A)^(1/4) [m/s], where D/L = A V^2 + B / V^2 is least."""
    return math.sqrt(math.sqrt(b / a))


def stall_speed(rho_kgpm3: float, weight_n: float, wing_area_m2: float, max_lift_coefficient: float) -> float:
    """V_s = sqrt(2 W / (rho S C_L,max)) [m/s] in level flight."""
    return math.sqrt(2.0 * weight_n / (rho_kgpm3 * wing_area_m2 * max_lift_coefficient))


def flown_airspeed(v_opt: float, v_stall: float, min_factor: float, v_max: float) -> float:
    """The flown airspeed [m/s]: the Carson speed, at least ``min_factor`` x stall, at most v_max."""
    return min(max(v_opt, min_factor * v_stall), v_max)


class FixedWingProfile(_SphereAndBattery, FrozenModel):
    """A fixed-wing aircraft (seed 002 section 3.2): airframe, drag polar and limits.

    Drag polar (seed 002 eq. 4-6, parabolic): ``D/L = A V^2 + B / V^2`` with
    ``A = rho f / (2 W)``, ``B = 2 W / (rho b^2 pi e)``, ``f = C_D0 S`` the parasite area [m^2],
    ``W = m g`` [N], ``b`` the span [m], ``e`` Oswald's efficiency.  ``A B = f / (b^2 pi e)``
    does not depend on the density, so ``(D/L)_opt = 2 sqrt(AB)`` is a constant of the
    airframe and the Carson speed ``V_opt = (B/A)^(1/4)`` scales as ``rho^(-1/2)``.
    The flown airspeed is :meth:`airspeed_mps` (the Carson speed, at least
    ``min_airspeed_factor`` x the stall speed, at most ``max_airspeed_mps``).
    Properties at sea level (ISA) take ``rho`` [kg/m^3] where it matters (``*_at`` methods).
    """

    name: str
    kind: Literal["fixed-wing"]
    description: str = ""
    references: tuple[str, ...] = ()
    mass_kg: Pos                                       # m (take-off)
    wing_area_m2: Pos                                  # S
    wing_span_m: Pos                                   # b
    zero_lift_drag_coefficient: Pos                    # C_D0
    oswald_factor: Annotated[float, Field(gt=0, le=1)]  # e
    max_lift_coefficient: Pos                          # C_L,max (stall)
    min_airspeed_factor: Annotated[float, Field(ge=1)] = 1.2   # flown airspeed >= factor x stall
    max_airspeed_mps: Pos
    max_wind_mps: Pos
    max_bank_deg: Annotated[float, Field(gt=0, lt=90)]         # sigma of seed 002 eq. 11
    max_climb_angle_deg: Annotated[float, Field(gt=0, lt=90)]
    max_descent_angle_deg: Annotated[float, Field(gt=0, lt=90)]
    battery_capacity_mah: Pos
    battery_voltage_v: Pos
    max_position_error_m: Pos                          # dp_max (navigation error bound)
    safety_distance_m: NonNeg
    safety_factor: Annotated[float, Field(ge=1)] = 1.0
    min_altitude_m: float = 0.0                        # AGL limits [m]
    max_altitude_m: float
    imu: ImuSpec

    @model_validator(mode="after")
    def _check(self) -> FixedWingProfile:
        if self.max_altitude_m <= self.min_altitude_m:
            raise ValueError("max_altitude_m must exceed min_altitude_m")
        return self

    # ---------------------------------------------------------------- airframe
    @property
    def weight_n(self) -> float:
        """W = m g [N]."""
        return self.mass_kg * G0

    @property
    def parasite_area_m2(self) -> float:
        """f = C_D0 S [m^2] (seed 002 eq. 5)."""
        return self.zero_lift_drag_coefficient * self.wing_area_m2

    @property
    def aspect_ratio(self) -> float:
        """b^2 / S [-]."""
        return self.wing_span_m**2 / self.wing_area_m2

    def polar_a_at(self, rho_kgpm3: float) -> float:
        """A = rho f / (2 W) [s^2/m^2] (seed 002 eq. 5)."""
        return polar_a(rho_kgpm3, self.parasite_area_m2, self.weight_n)

    def polar_b_at(self, rho_kgpm3: float) -> float:
        """B = 2 W / (rho b^2 pi e) [m^2/s^2] (seed 002 eq. 6)."""
        return polar_b(rho_kgpm3, self.weight_n, self.wing_span_m, self.oswald_factor)

    @property
    def A(self) -> float:
        """A at the ISA sea-level density [s^2/m^2]."""
        return self.polar_a_at(RHO_SL)

    @property
    def B(self) -> float:
        """B at the ISA sea-level density [m^2/s^2]."""
        return self.polar_b_at(RHO_SL)

    def carson_speed_at(self, rho_kgpm3: float) -> float:
        """V_opt = (B/A)^(1/4) [m/s] at density ``rho_kgpm3`` (seed 002, after eq. 10)."""
        return carson_speed(self.polar_a_at(rho_kgpm3), self.polar_b_at(rho_kgpm3))

    @property
    def carson_speed_mps(self) -> float:
        """V_opt at the ISA sea-level density [m/s]."""
        return self.carson_speed_at(RHO_SL)

    @property
    def min_drag_to_lift(self) -> float:
        """(D/L)_opt = 2 sqrt(AB) [-], independent of the density."""
        return 2.0 * math.sqrt(self.A * self.B)

    def stall_speed_at(self, rho_kgpm3: float) -> float:
        """V_s = sqrt(2 W / (rho S C_L,max)) [m/s] in level flight."""
        return stall_speed(rho_kgpm3, self.weight_n, self.wing_area_m2, self.max_lift_coefficient)

    @property
    def stall_speed_mps(self) -> float:
        """V_s at the ISA sea-level density [m/s]."""
        return self.stall_speed_at(RHO_SL)

    def airspeed_at(self, rho_kgpm3: float) -> float:
        """The flown airspeed [m/s]: ``min(max(V_opt, k V_s), max_airspeed_mps)``."""
        return flown_airspeed(self.carson_speed_at(rho_kgpm3), self.stall_speed_at(rho_kgpm3),
                              self.min_airspeed_factor, self.max_airspeed_mps)

    @property
    def cruise_speed_mps(self) -> float:
        """The flown airspeed in ISA sea-level air [m/s] (the cruise speed a ground station
        takes; the planners use :meth:`airspeed_at` the local density)."""
        return self.airspeed_at(RHO_SL)

    def turn_radius_at(self, airspeed_mps: float) -> float:
        """Minimum turn radius V^2 / (g tan(max bank)) [m] in still air."""
        return airspeed_mps**2 / (G0 * math.tan(math.radians(self.max_bank_deg)))

    @property
    def min_turn_radius_m(self) -> float:
        """Minimum still-air turn radius at the sea-level flown airspeed [m]."""
        return self.turn_radius_at(self.airspeed_at(RHO_SL))

    # ---------------------------------------------------------------- limits read by every stage
    @property
    def max_flight_path_angle_deg(self) -> float:
        """The larger of the climb and descent angle limits [deg]."""
        return max(self.max_climb_angle_deg, self.max_descent_angle_deg)


AnyVehicle = VehicleProfile | FixedWingProfile
VEHICLE_KINDS = {"multirotor": VehicleProfile, "fixed-wing": FixedWingProfile}


def vehicle_from_dict(raw: dict) -> AnyVehicle:
    """The profile of a mapping by its ``kind`` (default ``multirotor``); pydantic's
    ValidationError for invalid content, ValueError for an unknown kind."""
    kind = raw.get("kind", "multirotor")
    if not isinstance(kind, str) or kind not in VEHICLE_KINDS:
        raise ValueError(f"kind: unknown vehicle kind {kind!r}; known kinds: {', '.join(VEHICLE_KINDS)}")
    return VEHICLE_KINDS[kind].model_validate(raw)


def _catalog_dir():
    return files("skyroute.catalogs").joinpath("vehicles")


def known_vehicles() -> list[str]:
    """Names of the vehicles in the catalog (file stems)."""
    d = _catalog_dir()
    return sorted(p.name[:-5] for p in d.iterdir() if p.name.endswith(".yaml"))


_PARSED: dict[bytes, AnyVehicle] = {}   # YAML text -> profile (parsing takes ~10 ms; planners load per call)


def profile_hash(vehicle) -> str:
    """A hash of a vehicle profile's content (16 hex digits): BLAKE2b (8 bytes) of its sorted
    JSON (the plan request's ``vehicle_hash``; the ``wind_bounds`` stage's tiles carry it).

    Parameters
    ----------
    vehicle : VehicleProfile or FixedWingProfile

    Returns
    -------
    str
    """
    import hashlib
    import json

    doc = json.dumps(vehicle.model_dump(mode="json"), sort_keys=True, default=str)
    return hashlib.blake2b(doc.encode(), digest_size=8).hexdigest()


def load_vehicle(name_or_path: str | Path | AnyVehicle) -> AnyVehicle:
    """A :class:`VehicleProfile` (multirotor) or :class:`FixedWingProfile` by catalog name
    (``"dji-m300-rtk"``, ``"skywalker-x8"``) or YAML file path.

    Raises :class:`~skyroute.stages.base.UnknownNameError` for an unknown name,
    :class:`~skyroute.stages.base.DataError` for an unreadable file and
    :class:`~skyroute.stages.base.ScenarioError` (every problem listed) for invalid content.
    """
    if isinstance(name_or_path, VehicleProfile | FixedWingProfile):
        return name_or_path
    s = str(name_or_path)
    if isinstance(name_or_path, Path) or s.endswith((".yaml", ".yml")) or "/" in s:
        path = Path(s)
        try:
            found = path.is_file()
        except (OSError, ValueError):   # a name too long for the filesystem
            found = False
        if not found:
            raise DataError(f"vehicle file {path} not found; give a catalog name "
                            f"({', '.join(known_vehicles())}) or an existing YAML path")
        try:
            text = path.read_bytes()
        except OSError as exc:
            raise DataError(f"vehicle file {path} cannot be read: {exc.strerror or exc}") from None
        source = str(path)
    else:
        res = _catalog_dir().joinpath(f"{s}.yaml")
        if not res.is_file():
            raise UnknownNameError("vehicle", s, known_vehicles())
        text = res.read_bytes()
        source = f"vehicle {s}"
    hit = _PARSED.get(text)
    if hit is not None:     # the same file content parsed before: the same (frozen) profile
        return hit
    raw = read_yaml_text(text, source, "vehicle")   # one ScenarioError line: not UTF-8, not YAML, duplicate key...
    if not isinstance(raw, dict):
        raise DataError(f"{source}: expected a mapping of vehicle fields, got {type(raw).__name__}")
    kind = raw.get("kind", "multirotor")
    if not isinstance(kind, str) or kind not in VEHICLE_KINDS:
        raise ScenarioError(source, [f"kind: unknown vehicle kind {raw.get('kind')!r}; known kinds: "
                                     f"{', '.join(VEHICLE_KINDS)}"])
    try:
        veh = vehicle_from_dict(raw)
    except ValidationError as exc:
        problems = [f"{'.'.join(str(p) for p in e['loc']) or '(root)'}: {e['msg']}" if e["type"] != "number_field"
                    else f"{'.'.join(str(p) for p in (*e['loc'], e['ctx']['key']))}: {e['ctx']['why']}"
                    for e in exc.errors()]
        raise ScenarioError(source, problems) from exc
    if len(_PARSED) >= 64:
        _PARSED.clear()
    _PARSED[text] = veh
    return veh
