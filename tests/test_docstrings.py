"""Numpydoc sections on the public functions of the numerical packages.

Covers ``iscd/decode`` (ranging, tracking, comms) and ``iscd/sim``: every public function (module level,
or a public method of a public class; no leading underscore) must have a docstring with a
``Parameters`` section naming each of its parameters (``self``/``cls`` aside; ``*args`` and
``**kwargs`` may be listed or left out) and a ``Returns`` (or ``Yields``) section unless it
returns None (no return annotation, or ``-> None``).

Skipped: numba kernels (decorated ``@njit``/``@jit``), properties, dunder methods and functions
with no parameters besides ``self``/``cls``. Read from the source with :mod:`ast`, so nothing is
imported.
"""

from __future__ import annotations

import ast
import inspect
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("iscd/decode/ranging", "iscd/decode/tracking", "iscd/decode/comms", "iscd/sim")

_NUMBA = {"njit", "jit", "vectorize", "guvectorize", "stencil", "cfunc"}
_SKIP_DECORATORS = _NUMBA | {"property", "cached_property", "setter", "deleter", "overload"}
_UNDERLINE = re.compile(r"^-{3,}$")
_ENTRY = re.compile(r"^(\*{0,2}[A-Za-z_][\w, *]*?)\s*(?::.*)?$")


def _decorator_name(node: ast.expr) -> str:
    if isinstance(node, ast.Call):
        node = node.func
    if isinstance(node, ast.Attribute):
        return node.attr
    return node.id if isinstance(node, ast.Name) else ""


def _public_functions(path: Path):
    """(qualified name, function node) of each public function of one module."""
    tree = ast.parse(path.read_text(), str(path))
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield node.name, node
        elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
            for item in node.body:
                if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    yield f"{node.name}.{item.name}", item


def _params(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> tuple[list[str], list[str]]:
    """(named parameters, star parameters as ``*args``/``**kwargs``), self/cls dropped."""
    a = fn.args
    named = [p.arg for p in a.posonlyargs + a.args + a.kwonlyargs]
    if named and named[0] in ("self", "cls"):
        named = named[1:]
    star = ([f"*{a.vararg.arg}"] if a.vararg else []) + ([f"**{a.kwarg.arg}"] if a.kwarg else [])
    return named, star


def _sections(doc: str) -> dict[str, list[str]]:
    """numpydoc section title -> its lines (the docstring dedented)."""
    lines = inspect.cleandoc(doc).splitlines()
    out: dict[str, list[str]] = {}
    current = None
    for i, line in enumerate(lines):
        if i + 1 < len(lines) and line.strip() and _UNDERLINE.match(lines[i + 1].strip()):
            current = line.strip()
            out[current] = []
        elif current is not None and not _UNDERLINE.match(line.strip()):
            out[current].append(line)
    return out


def _listed(section: list[str]) -> set[str]:
    """The names a Parameters section gives (entries at its own indent: ``a, b : type``)."""
    names: set[str] = set()
    for line in section:
        if not line.strip() or line[:1].isspace():
            continue
        m = _ENTRY.match(line.strip())
        if m:
            names.update(n.strip() for n in m.group(1).split(",") if n.strip())
    return names


def _returns_none(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    r = fn.returns
    return r is None or (isinstance(r, ast.Constant) and r.value in (None, "None"))


def _problems(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> list[str]:
    named, star = _params(fn)
    doc = ast.get_docstring(fn, clean=False)
    if not doc:
        return ["no docstring"]
    sections = _sections(doc)
    problems = []
    if "Parameters" not in sections:
        problems.append("no Parameters section")
    else:
        listed = _listed(sections["Parameters"])
        missing = [p for p in named if p not in listed]
        if missing:
            problems.append("Parameters lacks " + ", ".join(missing))
    if not _returns_none(fn) and not {"Returns", "Yields"} & sections.keys():
        problems.append("no Returns section")
    return problems


def _checked():
    """(where, function node) of every function the rule covers."""
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).glob("*.py")):
            rel = path.relative_to(ROOT)
            for qual, fn in _public_functions(path):
                name = fn.name
                if name.startswith("_") or qual.split(".")[0].startswith("_"):
                    continue
                if {_decorator_name(d) for d in fn.decorator_list} & _SKIP_DECORATORS:
                    continue
                named, star = _params(fn)
                if not named and not star:
                    continue
                yield f"{rel}:{fn.lineno} {qual}", fn


def test_the_rule_covers_functions():
    assert sum(1 for _ in _checked()) > 50


def test_public_numerical_functions_have_numpydoc_sections():
    offenders = [f"{where}: {'; '.join(p)}" for where, fn in _checked() if (p := _problems(fn))]
    assert not offenders, (
        f"{len(offenders)} public function(s) in {', '.join(PACKAGES)} lack numpydoc sections "
        "(Parameters naming every parameter; Returns unless -> None):\n  "
        + "\n  ".join(offenders))


def test_the_checker_reads_numpydoc():
    src = '''
def good(a, b, *, c=1) -> int:
    """Sum.

    Parameters
    ----------
    a, b : float
        Addends, px.
    c : int, optional
        Keyword-only.

    Returns
    -------
    int
    """

def bad(a, b) -> int:
    """Sum of ``a`` and ``b``, px."""
'''
    good, bad = ast.parse(src).body
    assert _problems(good) == []
    assert _problems(bad) == ["no Parameters section", "no Returns section"]
