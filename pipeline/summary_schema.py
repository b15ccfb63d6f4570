"""The types of the ``summary.json`` values that ``skyroute report`` and ``skyroute diff`` read.

A summary is written by skyroute (strict JSON: non-finite numbers are ``null``), but it is a
text file a user may edit by hand.  :func:`check_summary` checks every value the two commands
read before they read it, so a wrong type (``"f_m": "NaN"``, ``"files": 5``, ``"plan": []``,
``"warnings": {}``, a list of levels holding a number ...) is one :class:`InputError` naming
the folder, the key (``plan.f_m``, ``fly.replannings[0].levels_tried[1]``) and the expected
type, instead of a traceback from deep inside the page or the table.

Only the keys listed in :data:`SUMMARY_SCHEMA` are checked, and only when present (each
command writes its own sections); keys it does not list are never read as typed values.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from skyroute.pipeline.errors import InputError

__all__ = ["SUMMARY_SCHEMA", "check_summary", "summary_problem"]


@dataclass(frozen=True)
class _T:
    """A leaf type: ``kinds`` among ``str``, ``int``, ``number``, ``bool``, ``null``."""

    kinds: tuple[str, ...]
    text: str


@dataclass(frozen=True)
class _List:
    """A JSON array whose items follow ``item`` (``length``: exactly that many items)."""

    item: Any
    length: int | None = None


STR = _T(("str",), "a string")
STR_N = _T(("str", "null"), "a string or null")
INT = _T(("int",), "an integer")
INT_N = _T(("int", "null"), "an integer or null")
NUM = _T(("number",), "a number")
NUM_N = _T(("number", "null"), "a number or null (skyroute writes a non-finite value as null, never \"NaN\")")
BOOL = _T(("bool",), "true or false")
SCALAR = _T(("str", "number", "bool", "null"), "a string, number, true/false or null")
LEVEL = _T(("str",), "a level name (a string such as \"1\" or \"landing\")")

_PLAN_NUMBERS = ("dop_threshold", "f_m", "C_l_m", "C_r_m", "C_d_m", "C_e_m", "length_m", "energy_Wh",
                 "flight_time_s", "clearance_radius_m")

# a dict spec lists keys; "*" applies to every key not listed
SUMMARY_SCHEMA: dict[str, Any] = {
    "schema_version": INT, "command": STR, "files": _List(STR), "warnings": _List(STR),
    "scenario": STR, "scenario_path": STR_N, "description": STR_N, "crs": STR_N, "seconds": NUM_N,
    "grid": {"nx": INT, "ny": INT, "resolution_m": NUM, "bounds": _List(NUM, 4)},
    "stages": _List({"name": STR, "key": STR_N, "cache_hit": BOOL, "seconds": NUM_N}),
    "plan": {"status": STR, "label": STR_N, **{k: NUM_N for k in _PLAN_NUMBERS}, "reasons": _List(STR),
             "provenance": {"planner": STR_N, "seed": INT_N, "weights": _List(NUM), "time_budget_s": NUM_N,
                            "max_tries": INT_N, "step_cells": INT_N, "budgets": {"*": SCALAR}, "vehicle": STR_N,
                            "vehicle_profile_hash": STR_N, "skyroute_version": STR_N}},
    "exports": {"files": _List(STR), "notes": _List(STR)},
    "fly": {"outcome": STR, "reason": STR_N, "n_replannings": INT, "chosen_levels": _List(LEVEL),
            "flight_time_s": NUM_N, "length_m": NUM_N, "energy_Wh": NUM_N, "t_rep_s": NUM_N, "tick_s": NUM_N,
            "seed": INT_N, "dop_threshold": NUM_N, "clearance": STR_N, "tactical_method": STR_N,
            "events": _List({"t_s": NUM_N, "kind": STR, "label": STR, "t_known_s": NUM_N, "t_coll_s": NUM_N,
                             "outcome": STR}),
            "replannings": _List({"replanning": INT, "event": STR, "t_event_s": NUM_N, "t_coll_s": NUM_N,
                                  "chosen_level": LEVEL, "levels_tried": _List(LEVEL),
                                  "levels_flyable": _List(LEVEL), "added_flight_time_s": NUM_N, "f_m": NUM_N}),
            "min_separation": _List({"id": STR, "kind": STR, "min_distance_m": NUM_N, "required_m": NUM_N,
                                     "clearance_m": NUM_N, "t_s": NUM_N}),
            "unavoidable_losses": _List({"intruder": SCALAR, "t_s": NUM_N, "predicted_margin_m": NUM_N,
                                         "predicted_min_m": NUM_N, "why": SCALAR})},
    "navsim": {"runs": INT_N, "epochs": INT_N, "seed": INT_N, "source": STR_N, "surface_uncertainty_m": NUM_N,
               "proposed_beats_weak": NUM_N, "nlos_used_share": NUM_N,
               "containment": {"*": {"*": NUM_N}}, "proposed": {"*": NUM_N}, "weak": {"*": NUM_N},
               "protection_level": {"method": STR_N, "budgets": {"*": NUM_N}, "*": SCALAR}},
    "fleet": {"counts": {}, "mean_delay_s": NUM_N, "throughput_plans_per_min": NUM_N,
              "conflicts_independent_check": SCALAR},
    "compare": {"planners": _List({"planner": STR_N})},
}


def _kind(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "bool"
    if isinstance(v, int):
        return "int"
    if isinstance(v, float):
        return "float"
    if isinstance(v, str):
        return "str"
    return "list" if isinstance(v, list) else "dict" if isinstance(v, dict) else type(v).__name__


def _shown(v: Any) -> str:
    k = _kind(v)
    what = {"null": "null", "bool": "a boolean", "int": "an integer", "float": "a number", "str": "a string",
            "list": "a list", "dict": "an object"}.get(k, k)
    if k in ("str", "int", "float", "bool"):
        text = repr(v) if k == "str" else str(v).lower() if k == "bool" else str(v)
        return f"{what} {text[:40]}"
    return what


def _leaf_ok(t: _T, v: Any) -> bool:
    k = _kind(v)
    return ((k == "str" and "str" in t.kinds) or (k == "null" and "null" in t.kinds)
            or (k == "bool" and "bool" in t.kinds) or (k == "int" and ("int" in t.kinds or "number" in t.kinds))
            or (k == "float" and "number" in t.kinds))


def _problem(spec: Any, v: Any, key: str) -> str | None:
    """``key: what it is, expected what`` for the first value of ``v`` that breaks ``spec``."""
    if isinstance(spec, _T):
        return None if _leaf_ok(spec, v) else f"{key} is {_shown(v)}, expected {spec.text}"
    if isinstance(spec, _List):
        if not isinstance(v, list):
            return f"{key} is {_shown(v)}, expected a list"
        if spec.length is not None and len(v) != spec.length:
            return f"{key} has {len(v)} items, expected {spec.length}"
        for i, x in enumerate(v):
            why = _problem(spec.item, x, f"{key}[{i}]")
            if why:
                return why
        return None
    if not isinstance(v, dict):
        return f"{key} is {_shown(v)}, expected an object"
    for k, x in v.items():
        sub = spec.get(k, spec.get("*"))
        if sub is None:
            continue
        why = _problem(sub, x, f"{key}.{k}" if key else str(k))
        if why:
            return why
    return None


def summary_problem(doc: Any) -> str | None:
    """The first value of the summary document ``doc`` whose type is not what
    :data:`SUMMARY_SCHEMA` says (``key is X, expected Y``), or None when every value fits."""
    if not isinstance(doc, dict):
        return f"the document is {_shown(doc)}, expected an object"
    return _problem(SUMMARY_SCHEMA, doc, "")


def check_summary(doc: Any, folder: Path | str, name: str = "folder") -> dict[str, Any]:
    """``doc`` (a parsed ``folder/summary.json``) when every value report and diff read has its
    type; :class:`InputError` otherwise: ``<name> <folder>: summary.json <key> is <value>,
    expected <type>; ...run the command that wrote it again``."""
    why = summary_problem(doc)
    if why:
        raise InputError(f"{name} {folder}: summary.json {why} (edited by hand?); run the command that wrote it "
                         "again")
    return doc
