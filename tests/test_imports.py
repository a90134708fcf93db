"""The package's imports form no cycle: every ``roverswarm`` import of every module, also those
only for type checking and those inside functions, walked from the source."""

from __future__ import annotations

import ast
from pathlib import Path

import roverswarm

PACKAGE = Path(roverswarm.__file__).parent


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path, modules: set[str]) -> set[str]:
    """The package modules ``path`` imports: ``from A import B`` names module ``A.B`` if there
    is one, else ``A``."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.update(
                f"{node.module}.{alias.name}" if f"{node.module}.{alias.name}" in modules else node.module
                for alias in node.names
            )
    return {name for name in found if name in modules}


def import_graph() -> dict[str, set[str]]:
    paths = {module_name(p): p for p in PACKAGE.rglob("*.py")}
    return {name: imports(path, set(paths)) - {name} for name, path in paths.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle of ``graph`` as a list of modules (the first repeated at the end), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return path[path.index(nxt) :] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        state[node] = 2
        path.pop()
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def test_the_package_has_no_import_cycle():
    graph = import_graph()
    assert "roverswarm.learners.offpolicy" in graph and "roverswarm.algos.ppo" in graph["roverswarm.learners.onpolicy"]
    assert find_cycle(graph) is None, " -> ".join(find_cycle(graph))


def test_the_cycle_finder_finds_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_the_public_names_are_listed_importable_and_documented():
    """Every lazily loaded public name is in dir(roverswarm), help(roverswarm) and the module
    docstring's list, and imports."""
    import importlib
    import pydoc

    assert set(roverswarm.__all__) == set(roverswarm._EXPORTS)
    assert set(roverswarm.__all__) <= set(dir(roverswarm)) and "__version__" in dir(roverswarm)
    members = pydoc.render_doc(roverswarm, renderer=pydoc.plaintext).partition("\nCLASSES\n")[2]  # past the docstring
    for name in roverswarm.__all__:
        module = roverswarm._EXPORTS[name]
        assert f"``{name}`` (``{module}``)" in roverswarm.__doc__
        assert getattr(roverswarm, name) is getattr(importlib.import_module(module), name)
        assert any(shown in members for shown in (f"class {name}(", f"    {name}(", f"    {name} =")), name


def test_the_cli_and_the_jobs_start_without_scipy_or_matplotlib():
    """Every command, and every job a grid or sweep starts in a process of its own, imports the
    CLI or the job pool; scipy (the oracle's assignment, Table I's statistics) and matplotlib
    (figures, animations) load where they are used: together 1.7 s of the CLI's 4.2 s of
    imports (docs/performance.md), paid by each such process."""
    import subprocess
    import sys

    probe = (
        "import sys, roverswarm.cli, roverswarm.experiments.pool; "
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'scipy', 'matplotlib'}))"
    )
    loaded = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert loaded.stdout.strip() == "[]", loaded.stdout
