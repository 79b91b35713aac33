"""The package's layers: imports run one way, counting the imports inside functions.

The graph is drawn from the source (every ``import`` and ``from ... import`` anywhere in a module, relative ones
resolved), so an import written inside a function to dodge a cycle at load time is counted as what it is.
"""

from __future__ import annotations

import ast
import collections
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "torchrod"

LAYERS = (
    ("values", "errors"),
    ("sensors",),
    ("rod",),
    ("loads",),
    ("shipped", "presets"),
    ("kernels",),
    ("model",),
    ("synthetic",),
    ("estimate",),
    ("learn",),
    ("io",),
    ("jig",),
    ("eval",),
    ("cli", "__main__"),
)
"""The layers, lowest first: a part may import its own layer's other parts only where the graph stays acyclic, and
any part of a lower layer. ``kernels`` imports nothing outside itself (they are compiled alone)."""

RANK = {part: rank for rank, parts in enumerate(LAYERS) for part in parts}


def _module_name(path: Path, package: Path = PACKAGE) -> str:
    parts = list(path.relative_to(package.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, package_root: Path = PACKAGE) -> set[str]:
    """The torchrod modules that ``path`` imports, anywhere in it (TYPE_CHECKING blocks and functions included)."""
    name = _module_name(path, package_root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if alias.name.split(".")[0] == "torchrod")
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] == "torchrod":
                found.add(target)
                # ``from torchrod import io`` imports the submodule
                where = package_root.parent / target.replace(".", "/")
                found.update(f"{target}.{a.name}" for a in node.names if (where / f"{a.name}.py").exists())
    return found


def _part(module: str) -> str | None:
    """The top-level part of the package a module belongs to (None for the package's own __init__)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


def package_graph() -> dict[str, dict[str, list[str]]]:
    """{part: {imported part: [module -> module, ...]}} over torchrod's top-level parts."""
    graph: dict[str, dict[str, list[str]]] = collections.defaultdict(lambda: collections.defaultdict(list))
    for path in sorted(PACKAGE.rglob("*.py")):
        module = _module_name(path)
        here = _part(module)
        for target in _imports(path):
            there = _part(target)
            if here is not None and there is not None and there != here:
                graph[here][there].append(f"{module} -> {target}")
    return graph


def test_every_part_of_the_package_has_a_layer():
    parts = {p.stem for p in PACKAGE.glob("*.py")} | {p.parent.name for p in PACKAGE.glob("*/*.py")}
    parts.discard("__init__")
    assert parts == set(RANK), f"without a layer: {sorted(parts - set(RANK))}; gone: {sorted(set(RANK) - parts)}"


def test_imports_run_one_way_down_the_layers():
    graph = package_graph()
    climbs = [
        f"{here} (layer {RANK[here]}) imports {there} (layer {RANK[there]}): {why[0]}"
        for here, targets in graph.items()
        for there, why in targets.items()
        if RANK[there] > RANK[here]
    ]
    assert not climbs, "\n".join(climbs)


def test_the_kernels_import_nothing_of_the_rest():
    graph = package_graph()
    assert not graph.get("kernels"), dict(graph["kernels"])


def test_the_package_graph_has_no_cycle():
    graph = {here: set(targets) for here, targets in package_graph().items()}
    state: dict[str, int] = {}

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                pytest.fail("import cycle: " + " -> ".join([*path[path.index(nxt) :], nxt]))
            if nxt not in state:
                visit(nxt, [*path, nxt])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])


def test_the_graph_sees_imports_inside_functions(tmp_path):
    """The drawing counts an import inside a function, relative or absolute, and a module imported by ``from
    package import module`` (else a hidden climb would pass)."""
    root = tmp_path / "torchrod"
    (root / "kernels").mkdir(parents=True)
    (root / "io").mkdir()
    (root / "io" / "stream.py").write_text("")
    probe = root / "kernels" / "probe.py"
    probe.write_text("def f():\n    from ..estimate.status import Status\n    import torchrod.learn\n"
                     "    from torchrod.io import stream\n")  # fmt: skip
    assert _imports(probe, root) == {"torchrod.estimate.status", "torchrod.learn", "torchrod.io", "torchrod.io.stream"}
