"""The layers of docs/architecture.md hold: every import inside mpnode/ (at module level or inside
a function) points down the layers, no two modules import each other even indirectly, and
`import mpnode` stays light.  Test files share conftest fixtures and helper modules, never each other."""
import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: each package of mpnode and the packages it may import (docs/architecture.md)
LAYERS = {
    "base": set(),
    "engine": {"base"},
    "data": {"base"},
    "model": {"engine", "base"},
    "evaluation": {"model", "data", "engine", "base"},
    "training": {"evaluation", "model", "data", "engine", "base"},
    "runs": {"training", "evaluation", "model", "data", "engine", "base"},
    "plot": {"training", "evaluation", "base"},
    "control": {"model", "engine", "base"},
    "export": {"model", "data", "engine", "base"},
}


def module_name(path):
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_of(path):
    """Every mpnode module ``path`` imports, resolved to dotted names (relative imports too)."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            for alias in node.names:  # `from a import b` is module a.b when there is one
                out.add(f"{base}.{alias.name}" if module_exists(f"{base}.{alias.name}") else base)
        elif isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
    return {m for m in out if m.split(".")[0] == "mpnode"}


def module_exists(name):
    path = ROOT.joinpath(*name.split("."))
    return path.with_suffix(".py").exists() or (path / "__init__.py").exists()


def layer_of(module):
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


MODULES = {module_name(p): imports_of(p) for p in sorted((ROOT / "mpnode").rglob("*.py"))}


def test_every_package_has_its_layer():
    assert {layer_of(m) for m in MODULES} - {None} == set(LAYERS)


@pytest.mark.parametrize("module", sorted(m for m in MODULES if layer_of(m)))
def test_imports_point_down_the_layers(module):
    own = layer_of(module)
    for target in MODULES[module]:
        other = layer_of(target)
        if other is None:  # the package root: only its public names (errors, graph) are below everyone
            continue
        assert other == own or other in LAYERS[own], f"{module} imports {target} ({own} may import {LAYERS[own]})"


def test_no_import_cycle():
    """Depth-first search over the module graph (a package's __init__ counts as a module)."""
    state, stack = {}, []

    def visit(m):
        state[m] = "open"
        stack.append(m)
        for n in sorted(MODULES.get(m, ())):
            if state.get(n) == "open":
                cycle = stack[stack.index(n):] + [n]
                if not _parent_and_child(cycle):
                    raise AssertionError("import cycle: " + " -> ".join(cycle))
            elif n not in state:
                visit(n)
        stack.pop()
        state[m] = "done"

    for m in sorted(MODULES):
        if m not in state:
            visit(m)


def _parent_and_child(cycle):
    """A package's __init__ re-exporting a submodule that imports a sibling through the package is
    Python's own package mechanics, not a cycle between modules: a cycle of a package and its
    submodules only."""
    return all(a.startswith(cycle[0]) or cycle[0].startswith(a) for a in cycle)


def test_importing_mpnode_loads_numpy_only():
    code = ("import sys, mpnode; heavy = [m for m in ('h5py', 'scipy', 'numba', 'click', 'networkx', 'matplotlib') "
            "if m in sys.modules]; print(heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "[]", out.stdout


def test_no_function_is_longer_than_80_lines():
    """Functions short enough to read at once, in the library, the command line and the simulators."""
    long = []
    for folder in ("mpnode", "cli", "data_gen"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    if node.end_lineno - node.lineno + 1 > 80:
                        long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}")
    assert not long, long


def test_no_test_file_imports_another():
    """What tests share is a fixture of tests/conftest.py or a helper module (engine_helpers.py),
    never another test file or conftest itself: each test file reads on its own."""
    tests = ROOT / "tests"
    test_files = {p.stem for p in tests.glob("test_*.py")} | {"conftest"}
    found = []
    for path in sorted(tests.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [node.module] if isinstance(node, ast.ImportFrom) else \
                [a.name for a in node.names] if isinstance(node, ast.Import) else []
            found += [f"{path.name}:{node.lineno} imports {n}" for n in names if n in test_files]
    assert not found, found
