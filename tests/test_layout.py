"""The estimator's module layout: no import cycles, and the commands use public names only."""

from __future__ import annotations

import ast
from pathlib import Path

ESTIMATOR = Path(__file__).resolve().parents[1] / "estimator"


def _module(path: Path) -> str:
    name = ".".join(path.relative_to(ESTIMATOR.parent).with_suffix("").parts)
    return name.removesuffix(".__init__")


MODULES = {_module(p): p for p in ESTIMATOR.rglob("*.py")}


def _imports(path: Path, top_level: bool) -> list[tuple[str, str]]:
    """(module, name) of each `from estimator… import name`; top_level: only those run at
    import time (not inside functions or `if TYPE_CHECKING:`)."""
    found: list[tuple[str, str]] = []

    def visit(nodes: list[ast.stmt]) -> None:
        for node in nodes:
            if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
                continue
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("estimator"):
                found.extend((node.module or "", a.name) for a in node.names)
            elif isinstance(node, ast.Import):
                found.extend((a.name, "") for a in node.names if a.name.startswith("estimator"))
            elif not top_level or isinstance(node, ast.If | ast.Try):
                for field in ("body", "orelse", "finalbody", "handlers"):
                    children = getattr(node, field, [])
                    visit([c for c in children if isinstance(c, ast.stmt)])
                    for handler in children if field == "handlers" else []:
                        visit(handler.body)

    visit(ast.parse(path.read_text()).body)
    return found


def test_no_import_cycles_between_estimator_modules():
    graph: dict[str, set[str]] = {}
    for name, path in MODULES.items():
        targets = set()
        for module, imported in _imports(path, top_level=True):
            target = f"{module}.{imported}" if f"{module}.{imported}" in MODULES else module
            # a submodule reaching its siblings through its own package is no cycle
            if target in MODULES and target != name and not name.startswith(target + "."):
                targets.add(target)
        graph[name] = targets
    visiting: list[str] = []
    done: set[str] = set()

    def walk(name: str) -> None:
        if name in visiting:
            cycle = [*visiting[visiting.index(name) :], name]
            raise AssertionError("import cycle: " + " → ".join(cycle))
        if name in done:
            return
        visiting.append(name)
        for target in sorted(graph[name]):
            walk(target)
        visiting.pop()
        done.add(name)

    for name in sorted(graph):
        walk(name)


def test_modules_import_no_private_names_from_each_other():
    private = [
        f"{_module(path)} imports {module}.{name}"
        for path in MODULES.values()
        for module, name in _imports(path, top_level=False)
        if name.startswith("_") and module != _module(path)
    ]
    assert not private, "\n".join(private)
