"""The import graph of the installed code, read from the source (every import statement,
at module level or inside a function): no module imports itself through others."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("iscd", "drivers", "calibration")
MAPPED = {"drivers": "iscd.drivers", "calibration": "iscd.calibration"}
"""Folders installed under another name (pyproject's ``package-dir``)."""


def _module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[0] in MAPPED:
        parts[:1] = MAPPED[parts[0]].split(".")
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def import_graph(root: Path = ROOT, packages: tuple[str, ...] = PACKAGES) -> dict[str, set[str]]:
    """module -> the project's modules it imports (a name imported from a package that is
    itself a module counts as that module)."""
    files = {_module_name(p, root): p for pkg in packages for p in (root / pkg).rglob("*.py")}
    graph: dict[str, set[str]] = {m: set() for m in files}
    for mod, path in files.items():
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    pkg = mod.split(".") if is_pkg else mod.split(".")[:-1]
                    pkg = pkg[:len(pkg) - (node.level - 1)]
                    base = ".".join(pkg + ([base] if base else []))
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in files else base for a in node.names]
            for t in targets:
                while t and t not in files:
                    t = t.rpartition(".")[0]
                if t and t != mod:
                    graph[mod].add(t)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_finder_sees_a_cycle(tmp_path: Path) -> None:
    pkg = tmp_path / "iscd"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f():\n    from iscd.sub import b\n")
    (pkg / "sub" / "b.py").write_text("from ..a import f\n")
    (pkg / "c.py").write_text("import iscd.a\n")
    g = import_graph(tmp_path, ("iscd",))
    assert g["iscd.sub.b"] == {"iscd.a"} and g["iscd.a"] == {"iscd.sub.b"}
    assert cycles(g) == [["iscd.a", "iscd.sub.b"]]


KNOWN: list[list[str]] = []
"""Cycles still there, each with why; the list only shrinks."""


def test_no_import_cycles() -> None:
    g = import_graph()
    assert len(g) > 80  # the whole tree was read
    assert cycles(g) == KNOWN


DECODE = ("iscd.decode",)
RIG = ("iscd.rig",)
SERVICE = ("iscd.service",)
TOP = ("iscd.cli", "iscd.eval", "iscd.campaign")
CONTRACT: list[tuple[tuple[str, ...], tuple[str, ...], str]] = [
    (("iscd.core",), ("iscd.decode", "iscd.rig", "iscd.service", "iscd.outputs", "iscd.drivers",
                      "iscd.sim", "iscd.recording", "iscd.calibration", *TOP),
     "the core is below everything"),
    (DECODE, ("iscd.drivers", *RIG, "iscd.outputs", *SERVICE, *TOP),
     "decode reads frames handed to it: no cameras, rig, outputs, service or command line"),
    (("iscd.drivers",), (*DECODE, *RIG, "iscd.outputs", *SERVICE, *TOP, "iscd.calibration",
                         "iscd.recording"),
     "drivers talk to devices: they import only the core (and the simulator, which the mock rig renders with)"),
    (("iscd.sim",), (*DECODE, *RIG, "iscd.drivers", "iscd.outputs", *SERVICE, *TOP),
     "the simulator renders; it knows nothing of the receiver"),
    (RIG, (*DECODE, "iscd.outputs", *SERVICE, *TOP), "the rig moves frames from the cameras to the ring"),
    (("iscd.outputs",), ("iscd.drivers", *RIG, *SERVICE, *TOP), "outputs take records"),
    (("iscd.calibration",), (*DECODE, "iscd.outputs", *SERVICE, *TOP),
     "calibration is a tool over the rig model and the cameras"),
    (("iscd.eval",), ("iscd.campaign",), "the campaign runs the evaluation's code, not the other way round"),
    (("iscd.campaign",), ("iscd.drivers", *RIG, *SERVICE),
     "a campaign decodes recordings where they lie: no cameras, rig or daemon"),
]
"""(importers, what they must not import, why): the layers, one folder each."""

EXCEPTIONS: dict[tuple[str, str], str] = {}
"""Imports that break the contract, each with why; the list only shrinks."""


def _under(m: str, prefixes: tuple[str, ...]) -> bool:
    return any(m == p or m.startswith(p + ".") for p in prefixes)


def contract_breaks(graph: dict[str, set[str]]) -> list[str]:
    """Every import that breaks :data:`CONTRACT`, or imports the command line from below
    it, as 'importer -> imported: why'."""
    out = []
    for m in sorted(graph):
        for t in sorted(graph[m]):
            for src, bad, why in CONTRACT:
                if _under(m, src) and _under(t, bad) and (m, t) not in EXCEPTIONS:
                    out.append(f"{m} -> {t}: {why}")
            if _under(t, ("iscd.cli",)) and not _under(m, ("iscd.cli", "iscd.__main__")):
                out.append(f"{m} -> {t}: nothing imports the command line")
            if _under(t, ("iscd.cli.commands",)) and not _under(m, ("iscd.cli",)):
                out.append(f"{m} -> {t}: only the command line imports the commands")
    return out


def test_the_contract_catches_a_forbidden_import(tmp_path: Path) -> None:
    pkg = tmp_path / "iscd"
    for d in ("decode/comms", "service", "cli"):
        (pkg / d).mkdir(parents=True)
    for f in ("__init__.py", "decode/__init__.py", "decode/comms/__init__.py", "service/__init__.py",
              "service/daemon.py", "cli/__init__.py", "cli/main.py"):
        (pkg / f).write_text("")
    (pkg / "decode" / "comms" / "demod.py").write_text("import iscd.service.daemon\n")
    (pkg / "service" / "daemon.py").write_text("def f():\n    from iscd.cli.main import main\n")
    breaks = contract_breaks(import_graph(tmp_path, ("iscd",)))
    assert breaks == ["iscd.decode.comms.demod -> iscd.service.daemon: " + CONTRACT[1][2],
                      "iscd.service.daemon -> iscd.cli.main: nothing imports the command line"]


def test_the_layers_hold() -> None:
    assert contract_breaks(import_graph()) == []
