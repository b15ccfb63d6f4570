"""The scenario key reference (``catalogs/README.md``), generated from the settings models.

``python -m skyroute.pipeline.settings_reference > catalogs/README.md`` rewrites it; a test
checks that the shipped file equals the generated text, so the reference never drifts from
the models that validate the YAML.
"""

from __future__ import annotations

import types
import typing
from pathlib import Path
from typing import Any, get_args, get_origin

from pydantic import BaseModel
from pydantic_core import PydanticUndefined

from skyroute.pipeline.settings import Scenario

_UNITS = (("_mps2", "m/s^2"), ("_mps", "m/s"), ("_m2", "m^2"), ("_m", "m"), ("_deg", "deg"), ("_s", "s"),
          ("_min", "min"), ("_pct", "%"), ("_Wh", "Wh"), ("_mah", "mAh"), ("_kg", "kg"), ("_utc", "UTC"))

HEADER = """# Scenario keys

Every key a scenario YAML may hold (`catalogs/scenarios/*.yaml`, or your own file passed to any
command), with its type, unit and default. Unknown keys are an error. Paths are relative to the
YAML file. Heights are in the surface model's vertical datum; mission altitudes are above ground
level (AGL). This file is generated from the settings models
(`python -m skyroute.pipeline.settings_reference > catalogs/README.md`); a test keeps it in step.
"""


def _type_name(tp: Any) -> str:
    origin = get_origin(tp)
    if origin is typing.Annotated:
        return _type_name(get_args(tp)[0])
    if origin in (typing.Union, types.UnionType):
        return " | ".join(_type_name(a) for a in get_args(tp))
    if origin is typing.Literal:
        return " | ".join(repr(a) for a in get_args(tp))
    if origin in (tuple, list):
        args = get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"list of {_type_name(args[0])}"
        return f"[{', '.join(_type_name(a) for a in args)}]" if args else "list"
    if isinstance(tp, type):
        return {"NoneType": "null", "Path": "path", "datetime": "ISO 8601 time"}.get(tp.__name__, tp.__name__)
    return str(tp).replace("typing.", "")


def _unit(name: str) -> str:
    for suffix, unit in _UNITS:
        if name.endswith(suffix):
            return unit
    return ""


def _models(tp: Any) -> list[type[BaseModel]]:
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return [tp]
    return [m for a in get_args(tp) for m in _models(a)]


def scenario_keys(model: type[BaseModel] = Scenario, prefix: str = "") -> list[tuple[str, str, str, str, str]]:
    """``(key, type, unit, default, section doc)`` of every settable key, depth first."""
    rows = []
    for name, field in model.model_fields.items():
        if field.exclude:
            continue
        key = f"{prefix}{name}"
        subs = [m for m in _models(field.annotation) if m is not model]
        default = "required" if field.is_required() else (
            "" if field.default is PydanticUndefined else repr(field.default) if not isinstance(field.default, BaseModel)
            else "(section)")
        if isinstance(field.default, Path):
            default = str(field.default)
        tags = [_tag(sub) for sub in subs] if len(subs) > 1 else []
        doc = (f"a list of items told apart by their `kind`: {', '.join(str(t) for t in tags)}" if tags and all(tags)
               else _first_paragraph(subs[0]) if subs else "")
        rows.append((key, _type_name(field.annotation), _unit(name), default, doc))
        for sub in subs:
            tag = _tag(sub) if len(subs) > 1 else None
            if get_origin(field.annotation) in (tuple, list):
                if tag:
                    rows.append((f"{key}[kind={tag}]", sub.__name__, "", "", _first_paragraph(sub)))
                rows.extend(scenario_keys(sub, f"{key}[kind={tag}]." if tag else f"{key}[]."))
            else:
                rows.extend(scenario_keys(sub, key + "."))
    if prefix.endswith("].") and "[kind=" in prefix:  # a tagged union member: its kind first
        rows.sort(key=lambda r: r[0] != f"{prefix}kind")
    return rows


def _first_paragraph(model: type[BaseModel]) -> str:
    return (model.__doc__ or "").strip().split("\n\n")[0]


def _tag(model: type[BaseModel]) -> str | None:
    """The ``kind`` of a member of a tagged union (``Literal['wind']`` -> ``wind``)."""
    f = model.model_fields.get("kind")
    if f is None or get_origin(f.annotation) is not typing.Literal:
        return None
    return str(get_args(f.annotation)[0])


def reference_markdown() -> str:
    lines = [HEADER, "| key | type | unit | default |", "|---|---|---|---|"]
    notes = []
    for key, tp, unit, default, doc in scenario_keys():
        lines.append(f"| `{key}` | {tp.replace('|', '/')} | {unit} | {default.replace('|', '/')} |")
        if doc:
            notes.append(f"- `{key}`: {' '.join(doc.split())}")
    return "\n".join([*lines, "", "## Sections", "", *notes, ""])


if __name__ == "__main__":  # pragma: no cover
    print(reference_markdown(), end="")
