"""No import cycle among the project's modules, counting the imports inside functions; and the
tests split by what they need: ``tests/engine`` imports no application package, ``tests/apps``
holds the tests that do.

The graph is read from the source with ``ast``: every import a module can run — its module-level
statements and the bodies of its classes, functions and blocks — but not ``if TYPE_CHECKING:``
blocks (never run).  A lazy import inside a function is an edge too: a cycle through it is a
layering error, only deferred to the first call.  ``from pkg import name`` is an edge to the submodule ``pkg.name`` where that file
exists, else to ``pkg`` (its ``__init__``): a submodule taking a name from its own package's
``__init__``, which imports that submodule, is a cycle too.  Importing ``a.b.c`` also runs the
``__init__`` of ``a`` and ``a.b``: edges to those packages the importer is not itself inside.
"""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("shootlab", "manipulators", "mixtures", "studies", "benchmarks")
#: what the engine's tests may not use: the application packages and the folders of scripts
APPLICATIONS = ("manipulators", "mixtures", "studies", "examples", "benchmarks")


def project_modules(root: Path, packages) -> dict[str, Path]:
    """Dotted module name → file, for every .py file of the ``packages`` under ``root``."""
    modules = {}
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            modules[".".join(parts)] = path
    return modules


def _type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or \
        (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _runtime_imports(body: list[ast.stmt]):
    """The Import / ImportFrom statements run when a module with this body is imported."""
    for node in body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield from _runtime_imports(node.body)     # lazy, but an edge all the same
        elif isinstance(node, ast.If):
            if not _type_checking(node.test):
                yield from _runtime_imports(node.body)
            yield from _runtime_imports(node.orelse)
        elif isinstance(node, ast.ClassDef):
            yield from _runtime_imports(node.body)
        elif isinstance(node, ast.Try) or type(node).__name__ == "TryStar":
            for block in (node.body, node.orelse, node.finalbody, *(h.body for h in node.handlers)):
                yield from _runtime_imports(block)
        elif isinstance(node, (ast.With, ast.AsyncWith, ast.For, ast.AsyncFor, ast.While)):
            yield from _runtime_imports(node.body)
            yield from _runtime_imports(getattr(node, "orelse", []))


def import_graph(root: Path, packages=PACKAGES) -> dict[str, set[str]]:
    """module → the project modules it imports at import time (see the module docstring)."""
    modules = project_modules(root, packages)
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in _runtime_imports(ast.parse(path.read_text(encoding="utf-8"), str(path)).body):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                if node.level:
                    base = package.split(".")
                    base = base[:len(base) - (node.level - 1)]
                    base = ".".join(base + ([node.module] if node.module else []))
                else:
                    base = node.module
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
            for t in targets:
                # importing a.b.c runs the __init__ of a and a.b first: edges to those the importer
                # is not inside (then they are imported already)
                parts = t.split(".")
                above = {".".join(parts[:i]) for i in range(1, len(parts))}
                graph[name] |= {p for p in above if not name.startswith(p + ".")} | {t}
            graph[name] &= set(modules) - {name}
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle (a list of modules, the first repeated at the end) per strongly connected
    component of more than one module (Tarjan's algorithm, then a shortest way round)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                components.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    cycles = []
    for comp in components:
        inside, start = set(comp), comp[0]
        came = {start: None}
        frontier, found = [start], None
        while frontier and found is None:          # breadth first from start back to start
            nxt = []
            for v in frontier:
                for w in sorted(graph[v] & inside):
                    if w == start:
                        found = v
                        break
                    if w not in came:
                        came[w] = v
                        nxt.append(w)
                if found is not None:
                    break
            frontier = nxt
        path = [start]
        v = found
        while v is not None and v != start:
            path.append(v)
            v = came[v]
        cycles.append([start, *reversed(path[1:]), start])
    return cycles


def _describe(cycles: list[list[str]]) -> str:
    return "import cycle(s):\n" + "\n".join("  " + " -> ".join(c) for c in cycles)


def test_no_import_cycle():
    graph = import_graph(ROOT)
    assert len(graph) > 50 and graph["shootlab.bvp.solver"]      # the packages were read
    cycles = import_cycles(graph)
    assert not cycles, _describe(cycles)


def _write(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)


def test_a_cycle_is_found(tmp_path):
    _write(tmp_path, {
        "pkg/__init__.py": "from .a import f\n",
        "pkg/a.py": "from .b import g\n\ndef f():\n    return g()\n",
        "pkg/b.py": "import pkg.c\n",
        "pkg/c.py": "from pkg.a import f\n",
    })
    cycles = import_cycles(import_graph(tmp_path, ["pkg"]))
    assert cycles == [["pkg.a", "pkg.b", "pkg.c", "pkg.a"]], _describe(cycles)
    assert "pkg.a -> pkg.b -> pkg.c -> pkg.a" in _describe(cycles)


def test_a_name_from_the_own_package_init_is_a_cycle(tmp_path):
    _write(tmp_path, {
        "pkg/__init__.py": "from .a import f\nCONSTANT = 1\n",
        "pkg/a.py": "from . import CONSTANT\n\ndef f():\n    return CONSTANT\n",
    })
    assert import_cycles(import_graph(tmp_path, ["pkg"])) == [["pkg", "pkg.a", "pkg"]]


def test_lazy_imports_are_edges_and_type_checking_imports_are_not(tmp_path):
    _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/a.py": "from .b import g\n",
        "pkg/b.py": ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .a import f\n"
                     "def g():\n    from . import a\n    return a\n"),
        "pkg/sub/__init__.py": "",
        "pkg/sub/c.py": "from .. import a\nfrom ..b import g\nclass K:\n    from . import d\n",
        "pkg/sub/d.py": "",
    })
    graph = import_graph(tmp_path, ["pkg"])
    assert graph["pkg.a"] == {"pkg.b"} and graph["pkg.b"] == {"pkg.a"}         # the function's, not TYPE_CHECKING's
    assert graph["pkg.sub.c"] == {"pkg.a", "pkg.b", "pkg.sub.d"}      # relative, from a package, in a class body
    assert import_cycles(graph) == [["pkg.a", "pkg.b", "pkg.a"]]


def test_importing_a_submodule_runs_its_package_init(tmp_path):
    _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/a.py": "from pkg.sub.d import h\n",
        "pkg/sub/__init__.py": "from .c import k\n",
        "pkg/sub/c.py": "from ..a import f\n",
        "pkg/sub/d.py": "from . import c\n",
    })
    graph = import_graph(tmp_path, ["pkg"])
    assert graph["pkg.a"] == {"pkg.sub", "pkg.sub.d"} and graph["pkg.sub.d"] == {"pkg.sub.c"}
    assert import_cycles(graph) == [["pkg.a", "pkg.sub", "pkg.sub.c", "pkg.a"]]


# ----------------------------------------------------------------------------- engine and apps tests
def application_uses(path: Path) -> list[str]:
    """What a test file takes from the applications (:data:`APPLICATIONS`), as ``line N: what``:
    every import of one, wherever it stands (inside a function too), and every string that names
    one of them as a module or a path — ``"manipulators.msd:model"``, ``"examples/drive.py"``, or
    the component in ``ROOT / "examples" / "drive.py"`` (a file loaded by its path, or a module by
    ``importlib.import_module``).  A docstring that mentions an application is not a use."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            text = node.value
            first = text.replace("/", ".").replace(":", ".").split(".")[0]
            names = [text] if first in APPLICATIONS and " " not in text else []
        else:
            continue
        out += [(node.lineno, node.col_offset, n) for n in names if n.split(".")[0].split("/")[0] in APPLICATIONS]
    return [f"line {line}: {n}" for line, _, n in sorted(out)]


def test_engine_tests_use_no_application_and_apps_tests_do():
    """Every file of tests/engine runs with the engine alone; every file of tests/apps needs an
    application (else it belongs in tests/engine)."""
    engine = sorted((ROOT / "tests" / "engine").glob("test_*.py"))
    apps = sorted((ROOT / "tests" / "apps").glob("test_*.py"))
    assert len(engine) > 10 and len(apps) > 10
    used = {f.name: application_uses(f) for f in engine}
    assert not any(used.values()), {k: v for k, v in used.items() if v}
    unused = [f.name for f in apps if not application_uses(f)]
    assert not unused, f"tests/apps files that use no application (move them to tests/engine): {unused}"


def test_application_uses_finds_imports_paths_and_module_names(tmp_path):
    path = tmp_path / "test_x.py"
    path.write_text(
        '"""Tests of the examples of manipulators."""\n'
        "import importlib\nimport shootlab\nfrom manipulators.msd import model\n"
        "def test_a():\n    import mixtures\n    from studies import sweep\n"
        "    importlib.import_module('benchmarks.gpu')\n"
        "    return ROOT / 'examples' / 'drive.py', 'examples/tanks.py:model', 'manipulators.msd:model'\n"
        "def test_b():\n    return 'the examples', 'studies of it', shootlab.model\n")
    assert application_uses(path) == [
        "line 4: manipulators.msd", "line 6: mixtures", "line 7: studies", "line 8: benchmarks.gpu",
        "line 9: examples", "line 9: examples/tanks.py:model", "line 9: manipulators.msd:model"]
