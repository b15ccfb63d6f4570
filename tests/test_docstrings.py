"""numpydoc sections of the public API a newcomer reads first (issue 25 item 6).

For each module below, every public function and class (the names in ``__all__``, or the
top-level names without a leading underscore where the module has no ``__all__``) that the
module itself defines has a docstring with numpydoc sections, pvlib's style:

* a function (or public method) that takes arguments besides ``self``/``cls`` has a
  ``Parameters`` section naming every argument, and one that returns something (a return
  annotation other than ``None``, or a ``return value`` statement) has a ``Returns`` section;
* a class has a ``Parameters`` or ``Attributes`` section; for a dataclass it names every field;
* a property has a docstring;
* no docstring line is longer than 120 characters.

The docstrings are read from the source with ``ast`` (not imported), so the test checks this
checkout whichever checkout of skyroute is installed.  Names imported from elsewhere (e.g.
``coverage.DOP_KINDS``) and constants are not checked here.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
MODULES = [
    "stages/grid.py",
    "stages/surface.py",
    "stages/occlusion.py",
    "stages/coverage.py",
    "stages/planning/strategic.py",
    "stages/planning/step1.py",
    "stages/planning/request.py",
]

_SECTION = r"^[ \t]*{name}[ \t]*\n[ \t]*-{{3,}}[ \t]*$"
_Def = ast.FunctionDef | ast.AsyncFunctionDef


def _section(doc: str, name: str) -> str | None:
    """The body of the numpydoc section ``name`` of ``doc`` (None if absent)."""
    m = re.search(_SECTION.format(name=name), doc, re.MULTILINE)
    if m is None:
        return None
    rest = doc[m.end():]
    nxt = re.search(r"^[ \t]*\w[\w ]*\n[ \t]*-{3,}[ \t]*$", rest, re.MULTILINE)
    return rest[:nxt.start()] if nxt else rest


def _documented(doc: str, *sections: str) -> set[str]:
    """Names listed in the given sections: ``name : type`` or ``a, b : type`` entries (the least
    indented lines of the section), ``*args`` / ``**kwargs`` without their stars."""
    out: set[str] = set()
    for s in sections:
        body = _section(doc, s)
        if not body:
            continue
        lines = [ln for ln in body.splitlines() if ln.strip()]
        indent = min(len(ln) - len(ln.lstrip()) for ln in lines)
        for ln in lines:
            if len(ln) - len(ln.lstrip()) == indent:
                head = ln.split(" : ", 1)[0].strip()
                out.update(n.strip().lstrip("*") for n in head.split(","))
    return out


def _arguments(fn: _Def) -> list[str]:
    a = fn.args
    names = [x.arg for x in (*a.posonlyargs, *a.args, *a.kwonlyargs)]
    names += [x.arg for x in (a.vararg, a.kwarg) if x is not None]
    return [n for n in names if n not in ("self", "cls")]


def _returns_value(fn: _Def) -> bool:
    if fn.returns is not None:
        return not (isinstance(fn.returns, ast.Constant) and fn.returns.value is None)
    stack = list(fn.body)
    while stack:
        node = stack.pop()
        if isinstance(node, ast.Return) and node.value is not None:
            return True
        if not isinstance(node, _Def | ast.ClassDef | ast.Lambda):
            stack.extend(ast.iter_child_nodes(node))
    return False


def _decorators(node: ast.AST) -> set[str]:
    out = set()
    for d in getattr(node, "decorator_list", []):
        d = d.func if isinstance(d, ast.Call) else d
        out.add(d.attr if isinstance(d, ast.Attribute) else getattr(d, "id", ""))
    return out


def _check_function(fn: _Def, where: str) -> list[str]:
    doc = ast.get_docstring(fn)
    if not doc:
        return [f"{where}: no docstring"]
    if "property" in _decorators(fn):
        return []
    problems = []
    args = _arguments(fn)
    if args:
        if _section(doc, "Parameters") is None:
            problems.append(f"{where}: takes {', '.join(args)} but has no Parameters section")
        else:
            missing = [a for a in args if a not in _documented(doc, "Parameters")]
            if missing:
                problems.append(f"{where}: Parameters does not name {', '.join(missing)}")
    if _returns_value(fn) and _section(doc, "Returns") is None:
        problems.append(f"{where}: returns a value but has no Returns section")
    return problems


def _fields(cls: ast.ClassDef) -> list[str]:
    """The fields of a dataclass (annotated names, ClassVar excluded)."""
    out = []
    for node in cls.body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            if "ClassVar" not in ast.unparse(node.annotation):
                out.append(node.target.id)
    return out


def _check_class(cls: ast.ClassDef, where: str) -> list[str]:
    doc = ast.get_docstring(cls)
    if not doc:
        return [f"{where}: no docstring"]
    problems = []
    if _section(doc, "Parameters") is None and _section(doc, "Attributes") is None:
        problems.append(f"{where}: no Parameters or Attributes section")
    elif "dataclass" in _decorators(cls):
        listed = _documented(doc, "Parameters", "Attributes")
        missing = [f for f in _fields(cls) if f not in listed]
        if missing:
            problems.append(f"{where}: Parameters/Attributes does not name {', '.join(missing)}")
    for node in cls.body:     # public methods; a dataclass's generated __init__ is not in the source
        if isinstance(node, _Def) and not node.name.startswith("_"):
            problems += _check_function(node, f"{where}.{node.name}")
    return problems


def _public_defs(tree: ast.Module) -> list[ast.AST]:
    public = None
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "__all__"
                                                for t in node.targets):
            public = set(ast.literal_eval(node.value))
    return [n for n in tree.body if isinstance(n, _Def | ast.ClassDef)
            and (n.name in public if public is not None else not n.name.startswith("_"))]


MAX_LINE = 120


def _long_lines(node: ast.AST, lines: list[str], where: str) -> list[str]:
    """Docstring source lines of ``node`` (and of its methods) longer than MAX_LINE."""
    out = []
    for n in ast.walk(node):
        body = getattr(n, "body", None)
        if isinstance(n, _Def | ast.ClassDef) and body and isinstance(body[0], ast.Expr) \
                and isinstance(body[0].value, ast.Constant) and isinstance(body[0].value.value, str):
            out += [f"{where}: docstring line {i} is {len(lines[i - 1])} > {MAX_LINE} characters"
                    for i in range(body[0].lineno, body[0].end_lineno + 1) if len(lines[i - 1]) > MAX_LINE]
    return out


def problems_of(source: str, module: str = "<module>") -> tuple[list[str], int]:
    """(problems, number of public definitions checked) of a module's source."""
    tree = ast.parse(source)
    lines = source.splitlines()
    defs = _public_defs(tree)
    problems: list[str] = []
    for node in defs:
        where = f"{module}:{node.name}"
        problems += _check_class(node, where) if isinstance(node, ast.ClassDef) else _check_function(node, where)
        problems += _long_lines(node, lines, where)
    return problems, len(defs)


@pytest.mark.parametrize("module", MODULES)
def test_public_docstrings_have_numpydoc_sections(module):
    problems, n = problems_of((REPO / module).read_text(encoding="utf-8"), module)
    assert n > 0, f"{module}: no public function or class found"
    assert not problems, "\n".join(problems)


BAD = '''
__all__ = ["f", "g", "h", "k", "C", "D"]


def f(x_m, y_m):
    """Sum [m].

    Parameters
    ----------
    x_m : float
        First [m].

    Returns
    -------
    float
    """
    return x_m + y_m


def g(x):
    """No sections."""
    return x


def h():
    return None


def k():
    """LONG"""


class C:
    """A class without sections."""

    def area(self, scale):
        """Area.

        Returns
        -------
        float
        """
        return scale


@dataclass
class D:
    """Fields.

    Attributes
    ----------
    a : int
        A.
    """

    a: int
    b: int
    K: ClassVar[int] = 1


def _private(x):
    return x
'''.replace("LONG", "x" * 120)   # a 130-character docstring line


def test_checker_finds_missing_sections():
    """The checker itself can fail: each defect of BAD is reported, nothing else."""
    problems, n = problems_of(BAD, "bad")
    assert n == 6
    assert sorted(problems) == sorted([
        "bad:f: Parameters does not name y_m",
        "bad:g: takes x but has no Parameters section",
        "bad:g: returns a value but has no Returns section",
        "bad:h: no docstring",
        "bad:k: docstring line 30 is 130 > 120 characters",
        "bad:C: no Parameters or Attributes section",
        "bad:C.area: takes scale but has no Parameters section",
        "bad:D: Parameters/Attributes does not name b",
    ])
