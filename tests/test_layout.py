"""The package's layout: no import cycle among its own modules, and ``tools/`` kept in rooms.

Every module under ``firmware_py/``, ``protocol/``, ``hil/`` and ``tools/`` is parsed with
``ast`` (nothing is imported) and every import of one of the package's own modules, relative
or absolute, at module level or inside a function, becomes an edge of the import graph. An
import of ``a.b.c`` from outside the package ``a.b`` also runs ``a.b``'s ``__init__`` first, so
it is an edge to that too (a registry in a package's ``__init__`` that imports a module which
imports the package back is a cycle at run time). Imports under ``if TYPE_CHECKING:`` are not
run and are left out. The graph must be acyclic: a cycle is reported as the list of its modules.
"""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: repository folder -> import name (pyproject.toml's [tool.setuptools.package-dir])
PACKAGES = {"firmware_py": "coiltrack.firmware", "protocol": "coiltrack.protocol", "hil": "coiltrack.hil",
            "tools": "coiltrack.tools"}
#: at most this many modules directly in tools/ (issue 32: the command line, the bench engine,
#: scenarios, outputs, inputs, analyses each in a subpackage)
TOOLS_TOP_MAX = 12


def _modules() -> dict[str, tuple[Path, bool]]:
    """import name -> (file, is a package's __init__)"""
    mods = {}
    for folder, name in PACKAGES.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = list(path.relative_to(ROOT / folder).with_suffix("").parts)
            is_pkg = parts[-1] == "__init__"
            mods[".".join([name] + (parts[:-1] if is_pkg else parts))] = (path, is_pkg)
    return mods


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST):
    """Every Import / ImportFrom node, except those under ``if TYPE_CHECKING:``."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            stack.extend(node.orelse)
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        stack.extend(ast.iter_child_nodes(node))


def _own(name: str, mods) -> str | None:
    """The deepest of the package's modules that ``name`` is or lies in."""
    while name and name not in mods:
        name = name.rpartition(".")[0]
    return name or None


def import_graph() -> dict[str, set[str]]:
    mods = _modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for mod, (path, is_pkg) in mods.items():
        here = mod if is_pkg else mod.rpartition(".")[0]
        for node in _imports(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                if node.level:
                    base = here.split(".")
                    base = base[:len(base) - (node.level - 1)]
                    assert base, f"{path}: relative import beyond the top"
                    src = ".".join(base + ([node.module] if node.module else []))
                else:
                    src = node.module or ""
                targets = [src] + [f"{src}.{a.name}" for a in node.names if f"{src}.{a.name}" in mods]
            for t in targets:
                own = _own(t, mods)
                if own is None:
                    continue
                # the target and every package on the way to it that ``mod`` is not inside of
                parts = own.split(".")
                for k in range(2, len(parts) + 1):
                    anc = ".".join(parts[:k])
                    if anc in mods and anc != mod and not mod.startswith(anc + "."):
                        graph[mod].add(anc)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, on, stack, out = {}, {}, set(), [], []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1 or v in graph[v]:
                    out.append(sorted(comp))
    return out


def test_the_checker_finds_a_cycle_and_a_self_import():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"a"}}) == [["a"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_graph_sees_relative_package_and_function_level_imports():
    g = import_graph()
    # tools.cli: ``from . import commands`` (a package) and ``from .inputs.infile import ...``
    assert {"coiltrack.tools.commands", "coiltrack.tools.inputs.infile", "coiltrack.tools.inputs"} <= g[
        "coiltrack.tools.cli"]
    # a family module imports its base within the package: no edge to the registry that lists it
    assert "coiltrack.tools.scenarios.base" in g["coiltrack.tools.scenarios.thesis"]
    assert "coiltrack.tools.scenarios" not in g["coiltrack.tools.scenarios.thesis"]
    # the registry lists every family
    assert "coiltrack.tools.scenarios.distortion" in g["coiltrack.tools.scenarios"]


def test_no_import_cycle():
    found = cycles(import_graph())
    assert not found, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in found)


def test_tools_top_holds_at_most_12_modules():
    top = sorted(p.name for p in (ROOT / "tools").glob("*.py"))
    assert len(top) <= TOOLS_TOP_MAX, f"{len(top)} modules directly in tools/: {top}"


def test_every_subpackage_is_in_pyproject():
    """A subpackage missing from [tool.setuptools] packages is left out of a wheel (an editable
    install still finds it, so nothing else would notice: ``protocol/conformance`` was)."""
    import tomllib

    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    pkgs = {".".join([name, *p.parent.relative_to(ROOT / folder).parts])
            for folder, name in PACKAGES.items() for p in (ROOT / folder).rglob("__init__.py")}
    assert pkgs - listed == set()
