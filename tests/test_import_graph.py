"""The import graph of skyroute has no circles (issue 25): every ``import`` / ``from ... import``
of a ``skyroute.*`` module, at module level or inside a function (a lazy import is still a
dependency; an import under ``if TYPE_CHECKING:`` is for annotations only and is not), read from
the source with ``ast``; the strongly connected components of that graph
(Tarjan) must all be single modules.  A package's ``__init__`` counts as the package."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ROOTS = {"pipeline": REPO / "pipeline", "stages": REPO / "stages", "catalogs": REPO / "catalogs"}


def _modules() -> dict[str, Path]:
    out = {}
    for pkg, root in ROOTS.items():
        for f in root.rglob("*.py"):
            if "vendor" in f.parts or "__pycache__" in f.parts:
                continue
            rel = f.relative_to(root).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            out[".".join(["skyroute", pkg, *parts])] = f
    return out


def _resolve(name: str, mods: dict[str, Path]) -> str | None:
    while name and name not in mods:
        name = name.rpartition(".")[0]
    return name or None


def _runtime_nodes(tree: ast.AST):
    """Every node of ``tree`` outside ``if TYPE_CHECKING:`` blocks."""
    todo = [tree]
    while todo:
        node = todo.pop()
        yield node
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                todo.extend(child.orelse)
                continue
            todo.append(child)


def import_graph() -> dict[str, set[str]]:
    """module -> the skyroute modules it imports (anywhere in its source)."""
    mods = _modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for m, f in mods.items():
        is_pkg = f.name == "__init__.py"
        for node in _runtime_nodes(ast.parse(f.read_text(), str(f))):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    pkg = m if is_pkg else m.rpartition(".")[0]
                    for _ in range(node.level - 1):
                        pkg = pkg.rpartition(".")[0]
                    base = f"{pkg}.{base}" if base else pkg
                names = [f"{base}.{a.name}" for a in node.names] or [base]
            for n in names:
                if not n.startswith("skyroute."):
                    continue
                t = _resolve(n, mods)
                if t and t != m and not m.startswith(t + "."):   # a package's own modules importing it
                    graph[m].add(t)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on, stack, out = set(), [], []
    counter = [0]
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def test_the_cycle_finder_finds_a_known_cycle():
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert cycles(g) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_skyroute_import_graph_has_no_cycles():
    g = import_graph()
    assert len(g) > 100 and "skyroute.stages.planning.step1" in g["skyroute.stages.planning.strategic"]
    assert cycles(g) == []


def test_stages_never_import_pipeline():
    g = import_graph()
    bad = sorted((m, t) for m, ts in g.items() if m.startswith("skyroute.stages") for t in ts
                 if t.startswith("skyroute.pipeline"))
    assert bad == []


def test_planner_names_come_from_one_registry():
    """Issue 25: the CLI's --planner choices, the scenario validation, STEP I, compare and the
    vehicle-kind check all read stages/planning/registry.py."""
    from skyroute.pipeline import compare, settings
    from skyroute.pipeline.cli import main
    from skyroute.stages.planning import kinds, registry, step1

    plan_cmd = main.commands["plan"]
    opt = next(p for p in plan_cmd.params if p.name == "planner_name")   # validated with one error: line
    assert tuple(opt.metavar.split("|")) == registry.PLANNERS
    assert registry.planner_help() in opt.help
    assert registry.planner_help() in next(p for p in main.commands["compare"].params if p.name == "planners").help
    assert settings.PLANNERS is registry.PLANNERS and step1.PLANNERS is registry.PLANNERS
    assert compare.PLANNERS is registry.PLANNERS and kinds.FIXED_WING_PLANNERS is registry.FIXED_WING_PLANNERS
    assert set(registry.FIXED_WING_PLANNERS) | set(registry.ROTORCRAFT_PLANNERS) == set(registry.PLANNERS)
    for p in registry.REGISTRY.values():          # every solver named in the table exists
        mod, fn = p.solver.split(":")
        assert callable(getattr(__import__(mod, fromlist=[fn]), fn)), p.solver
    # the scenario validation refuses a name the registry does not have, naming the registry's
    with __import__("pytest").raises(Exception, match="known planners: " + ", ".join(registry.PLANNERS)):
        settings.parse_planner({"name": "warp-drive"})
