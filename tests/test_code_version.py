"""Stage code versions come from the import closure of the stage function (AST, not a list)."""

from __future__ import annotations

from skyroute.pipeline import graph
from skyroute.pipeline.graph import REGISTRY, Stage, _load_registry, code_closure


def _traffic_like(*, settings):  # an import inside the body, as the built-in stages do
    from skyroute.stages.planning.strategic import intruders_for

    return intruders_for


def _select(sc):
    return None


def test_closure_follows_imports_inside_function_bodies():
    st = Stage("probe", _traffic_like, _select)
    _, mods = graph._function_imports(_traffic_like)
    assert "skyroute.stages.planning.strategic" in mods
    closure = code_closure(mods)
    # strategic imports these at module level or inside its functions
    for m in ("skyroute.stages.planning.problem", "skyroute.stages.planning.step3", "skyroute.stages.energy",
              "skyroute.stages.traffic", "skyroute.pipeline.errors"):
        assert m in closure, m
    assert all(m.startswith("skyroute.") for m in closure)
    assert st.code_version() == Stage("probe", _traffic_like, _select).code_version()


def test_built_in_stages_see_the_modules_the_hand_lists_missed():
    _load_registry()
    closure = {name: code_closure(set(st.code_modules) | graph._function_imports(st.func)[1])
               for name, st in REGISTRY.items()}
    assert {"skyroute.stages.surface", "skyroute.stages.grid"} <= closure["environment"]
    assert "skyroute.stages.planning.strategic" in closure["traffic"]
    assert "skyroute.stages.occlusion" in closure["coverage"]


def test_editing_a_module_deep_in_the_closure_changes_only_dependent_stages(monkeypatch):
    _load_registry()
    before = {name: st.code_version() for name, st in REGISTRY.items()}
    real = graph._module_source

    def edited(name):
        src = real(name)
        return src + b"\n# edited\n" if name == "skyroute.stages.energy" else src

    monkeypatch.setattr(graph, "_module_source", edited)
    after = {name: st.code_version() for name, st in REGISTRY.items()}
    changed = {n for n in before if before[n] != after[n]}
    assert "plan" in changed and "traffic" in changed
    assert not changed & {"surface", "satellites", "wind", "clearance", "coverage"}
