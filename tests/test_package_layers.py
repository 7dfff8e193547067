"""The package's layers: every import between its modules, lazy and type-checking ones included, goes to the same
or a lower layer, and no modules import each other in a cycle."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "sb3_spikeplastic"

#: the layers, lowest first; a module may import its own layer and those before it
LAYERS = ("envs", "snn", "sb3", "zoo", "study", "cli")
#: top-level modules and data packages -> their layer
TOP_LEVEL = {"envs": "envs", "hyperparams": "envs", "study_files": "envs", "cli": "cli", "__main__": "cli"}


def package_modules() -> dict[str, Path]:
    """Dotted module name -> file, ``envs/`` installed as ``sb3_spikeplastic.envs``."""
    files = {}
    for folder, prefix in ((ROOT / PACKAGE, (PACKAGE,)), (ROOT / "envs", (PACKAGE, "envs"))):
        for path in folder.rglob("*.py"):
            parts = prefix + path.relative_to(folder).with_suffix("").parts
            files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return files


def imports_of(name: str, path: Path, modules) -> set[str]:
    """The package's modules that ``name`` imports anywhere in its file."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([node.module] if node.module else []))
            else:
                base = node.module
            submodules = {f"{base}.{alias.name}" for alias in node.names} & set(modules)
            found.update(submodules)
            if len(submodules) < len(node.names):
                found.add(base)
    return {m for m in found if m in modules and m != name}


def layer_of(name: str) -> str:
    parts = name.split(".")
    if len(parts) == 1:
        return "root"
    return TOP_LEVEL.get(parts[1], parts[1])


@pytest.fixture(scope="module")
def graph():
    modules = package_modules()
    return {name: imports_of(name, path, modules) for name, path in modules.items()}


def test_every_module_is_in_a_layer(graph):
    unplaced = sorted(n for n in graph if layer_of(n) not in (*LAYERS, "root"))
    assert not unplaced, f"modules outside the layer folders {LAYERS}: {unplaced}"


def test_imports_go_down(graph):
    """The package root (its lazy public names reach every layer) counts as the top layer."""
    rank = {layer: i for i, layer in enumerate(LAYERS)} | {"root": len(LAYERS) - 1}
    upward = [
        f"{a} -> {b}"
        for a, targets in graph.items()
        for b in targets
        if layer_of(a) != "root" and rank[layer_of(b)] > rank[layer_of(a)]
    ]
    assert not upward, "imports from a lower layer into a higher one:\n" + "\n".join(sorted(upward))


def test_no_import_cycle(graph):
    """Tarjan's strongly connected components: every component has one module."""
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(node):
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in graph[node]:
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for node in graph:
        if node not in index:
            visit(node)
    assert not cycles, f"import cycles: {cycles}"


def test_the_checker_sees_lazy_imports(graph):
    """A function-level import counts: ``cli`` dispatches through one and imports the study layer lazily."""
    assert f"{PACKAGE}.study.declaration" in graph[f"{PACKAGE}.cli"]
    assert f"{PACKAGE}.sb3.activity" in graph[f"{PACKAGE}.sb3.ppo"]
