"""The import graph read from the source (``ast``, imports inside functions included): the one-way
flow of DESIGN.md holds and no module waits for itself."""
from __future__ import annotations

import ast
import functools
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("service", "gestures", "clients")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: Path, modules: set[str]) -> set[str]:
    """Project modules imported anywhere in ``path`` (``from pkg import mod`` resolves to ``pkg.mod``)."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            targets = [f"{base}.{a.name}" for a in node.names] + [base]
        else:
            continue
        for target in targets:
            while target and target not in modules:
                target = target.rpartition(".")[0]
            if target and not (name == target or name.startswith(target + ".")):   # not its own packages
                out.add(target)
    return out


def read_graph() -> dict[str, set[str]]:
    files = [p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")]
    modules = {_module_name(p) for p in files}
    return {_module_name(p): _imports(p, modules) for p in files}


@functools.lru_cache(maxsize=1)
def import_graph() -> dict[str, set[str]]:
    """``read_graph`` in a fresh interpreter: CPython 3.11's AST conversion keeps a recursion counter
    that is not thread-safe, and other tests leave server threads behind (``SystemError: AST
    constructor recursion depth mismatch``)."""
    out = subprocess.run([sys.executable, __file__], capture_output=True, text=True, check=True).stdout
    return {module: set(targets) for module, targets in json.loads(out).items()}


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle as a list of modules, or None (depth-first search, three colours)."""
    colour: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        colour[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if colour.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if colour.get(nxt) is None and (found := visit(nxt)):
                return found
        colour[node] = 2
        stack.pop()
        return None

    for node in sorted(graph):
        if colour.get(node) is None and (found := visit(node)):
            return found
    return None


def test_the_graph_is_read_from_the_source():
    graph = import_graph()
    # known arrows, so a broken parser cannot pass the checks below by seeing no imports at all
    assert "service.model.quaternion" in graph["service.estimators.rigid.filters"]
    assert "service.estimators.base" in graph["service.estimators.chain"]
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]


def test_no_module_imports_itself_through_others():
    assert _cycle(import_graph()) is None


def test_the_estimators_do_not_stand_on_the_simulator():
    arrows = [(m, t) for m, targets in import_graph().items() if m.startswith("service.estimators")
              for t in targets if t.startswith("service.sim")]
    assert arrows == []


def test_the_model_and_the_protocol_are_the_ground_floor():
    for module, targets in import_graph().items():
        for floor in ("service.model", "service.protocol"):
            if module.startswith(floor):
                assert {t for t in targets if not t.startswith(floor)} == set(), module


if __name__ == "__main__":
    print(json.dumps({module: sorted(targets) for module, targets in read_graph().items()}))
