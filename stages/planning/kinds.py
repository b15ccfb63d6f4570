"""Which planners fit which vehicle kind (light: no compiled code, read at scenario load).

Rotorcraft (``kind: multirotor``) fly the seed 000 planners (``astar``, ``bitstar``, ...);
fixed-wing aircraft (``kind: fixed-wing``) the seed 002 lattice planners of
:mod:`skyroute.stages.planning.fixedwing`.  A planner that does not fit the vehicle is an
:class:`~skyroute.stages.base.InputError` naming the planners that do.
"""

from __future__ import annotations

from skyroute.stages.base import InputError
from skyroute.stages.planning.registry import FIXED_WING_PLANNERS, PLANNERS
from skyroute.stages.vehicle import FixedWingProfile, load_vehicle


def check_planner_vehicle(planner: str, vehicle, known: tuple[str, ...] = PLANNERS) -> None:
    """InputError when ``planner`` does not fit the kind of ``vehicle`` (a profile, catalog name
    or YAML path), naming the planners that do out of ``known`` (default: the
    :mod:`~skyroute.stages.planning.registry`)."""
    veh = load_vehicle(vehicle)
    if isinstance(veh, FixedWingProfile):
        if planner not in FIXED_WING_PLANNERS:
            raise InputError(f"planner {planner!r} plans for rotorcraft; vehicle {veh.name!r} is fixed-wing: use one "
                             f"of {', '.join(FIXED_WING_PLANNERS)}")
    elif planner in FIXED_WING_PLANNERS:
        rotor = [p for p in known if p not in FIXED_WING_PLANNERS]
        raise InputError(f"planner {planner!r} plans for fixed-wing aircraft; vehicle {veh.name!r} is a {veh.kind}: "
                         f"use one of {', '.join(rotor)}")


def planners_for(vehicle, known: tuple[str, ...] = PLANNERS) -> list[str]:
    """The planners of ``known`` that fit the kind of ``vehicle``, in order."""
    fixed = isinstance(load_vehicle(vehicle), FixedWingProfile)
    return [p for p in known if (p in FIXED_WING_PLANNERS) == fixed]


__all__ = ["FIXED_WING_PLANNERS", "check_planner_vehicle", "planners_for"]
