"""The stages of softplot.marks: each alone on a small render, and the package's structure.

Structure: no function of src/softplot/marks longer than MAX_LINES (except the ones listed with
a reason), no import circle between its modules, and no stage module importing the
orchestrator (detect.py).
"""

from __future__ import annotations

import ast
from pathlib import Path

import softplot.marks

MARKS = Path(softplot.marks.__file__).parent
MAX_LINES = 120
#: (module, function) -> why it is still longer than MAX_LINES
LONG_ALLOWED = {
    ("lsm.py", "lsm"): "the Gauss-Newton loop with its robust weights and tests: to be split "
                       "by its owner",
    ("measure.py", "measure"): "the fits, the scene refits and the acceptance: to be split "
                               "by its owner",
}


def _modules():
    return {p.stem: ast.parse(p.read_text(encoding="utf-8")) for p in sorted(MARKS.glob("*.py"))}


def test_no_function_longer_than_the_limit():
    long = {}
    for name, tree in _modules().items():
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_LINES:
                    long[(f"{name}.py", node.name)] = n
    unexpected = {k: v for k, v in long.items() if k not in LONG_ALLOWED}
    assert not unexpected, f"functions over {MAX_LINES} lines: {unexpected}"


def _imports(tree, names) -> set[str]:
    """The modules of softplot.marks a module imports (anywhere in it, functions included)."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            if node.module == "softplot.marks":
                out |= {a.name for a in node.names if a.name in names}
            elif node.module.startswith("softplot.marks."):
                out.add(node.module.split(".")[2])
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("softplot.marks."):
                    out.add(a.name.split(".")[2])
    return out


def _graph():
    mods = _modules()
    names = set(mods) - {"__init__"}
    return {m: _imports(t, names) - {m} for m, t in mods.items() if m != "__init__"}


def test_import_graph_has_no_circle():
    graph = _graph()
    assert {"common", "overview", "candidates", "lattice", "detect", "fiducial"} <= set(graph)
    state: dict = {}

    def visit(m, path):
        state[m] = 1
        for n in sorted(graph.get(m, ())):
            assert state.get(n) != 1, f"import circle: {' -> '.join(path + [m, n])}"
            if n not in state:
                visit(n, path + [m])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [])


def test_no_stage_imports_the_orchestrator():
    graph = _graph()
    users = sorted(m for m, deps in graph.items() if "detect" in deps)
    assert users == [], f"modules importing softplot.marks.detect: {users}"
    # the fiducial path reaches the shared helpers through common, not through detect
    assert "common" in graph["fiducial"] and "detect" not in graph["fiducial"]
