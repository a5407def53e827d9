"""The package's import graph: one way, no circles, no private names across modules.

Every ``import`` counts, deferred ones and those under ``TYPE_CHECKING`` included: a
deferred import hides a circle from Python, not from a reader following the code.
"""

from __future__ import annotations

import ast
from pathlib import Path

import fricjax

PACKAGE = Path(fricjax.__file__).parent


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


MODULES = _modules()


def _imports(module: str) -> list[tuple[str, str]]:
    """``(imported module, imported name or "")`` for every fricjax import of ``module``."""
    path = MODULES[module]
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found += [(a.name, "") for a in node.names if a.name in MODULES]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            for a in node.names:
                if f"{source}.{a.name}" in MODULES:
                    found.append((f"{source}.{a.name}", ""))
                elif source in MODULES:
                    found.append((source, a.name))
    return [(m, n) for m, n in found if m != module]


GRAPH = {m: sorted({dep for dep, _ in _imports(m)}) for m in MODULES}


def circles(graph: dict[str, list[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, []):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_circle_finder_finds_a_circle() -> None:
    graph = {"a": ["b"], "b": ["c"], "c": ["a"], "d": ["a"]}
    assert circles(graph) == [["a", "b", "c"]]
    assert circles({"a": ["b"], "b": []}) == []


def test_the_package_has_no_import_circle() -> None:
    assert len(GRAPH) > 50  # the walk saw the package
    assert circles(GRAPH) == []


def test_no_private_name_is_imported_from_another_module() -> None:
    private = [
        f"{m} imports {name} from {source}"
        for m in MODULES
        for source, name in _imports(m)
        if name.startswith("_")
    ]
    assert private == []


def test_the_model_layer_imports_nothing_above_it() -> None:
    # model → data → search → refine → diagnose → report → api → cli: a force law knows
    # nothing of recordings, searches or reports.
    above = ("fricjax.data", "fricjax.search", "fricjax.diagnose", "fricjax.report", "fricjax.io")
    above += ("fricjax.api", "fricjax.cli", "fricjax.config", "fricjax.problem")
    wrong = [
        f"{m} → {dep}"
        for m in MODULES
        if m.startswith("fricjax.model")
        for dep in GRAPH[m]
        if dep.startswith(above)
    ]
    assert wrong == []


def test_report_and_diagnose_do_not_reach_the_commands() -> None:
    wrong = [
        f"{m} → {dep}"
        for m in MODULES
        if m.startswith(("fricjax.diagnose", "fricjax.report", "fricjax.search", "fricjax.data"))
        for dep in GRAPH[m]
        if dep in ("fricjax.api", "fricjax.cli")
    ]
    assert wrong == []
