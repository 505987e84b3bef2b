"""The import graph of the package: no module of ``pae`` imports itself back, directly or
through others (imports at module level and inside functions alike)."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"

Graph = dict[str, set[str]]
"""module -> the ``pae`` modules it imports."""


def module_name(path: Path) -> str:
    """The dotted name of the module in ``path`` (a package by its ``__init__.py``)."""
    parts = path.relative_to(SRC).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(path: Path, modules: set[str]) -> set[str]:
    """The modules of ``modules`` that the file at ``path`` imports anywhere in its code; in
    ``from pae.x import y`` the module ``pae.x.y`` when ``y`` is one, else ``pae.x``."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, *([base] if base else [])])
            submodules = {f"{base}.{alias.name}" for alias in node.names}
            found |= (submodules & modules) or {base}
    return (found & modules) - {name}


def import_graph() -> Graph:
    """Every module under ``src/pae`` -> the ``pae`` modules it imports."""
    paths = {module_name(path): path for path in sorted((SRC / "pae").rglob("*.py"))}
    return {name: imported_modules(path, set(paths)) for name, path in paths.items()}


def find_cycle(graph: Graph) -> list[str] | None:
    """One import cycle of ``graph`` as the modules along it, the first repeated at the end;
    None when there is none."""
    done: set[str] = set()

    def visit(module: str, path: list[str]) -> list[str] | None:
        if module in path:
            return [*path[path.index(module) :], module]
        if module in done:
            return None
        for imported in sorted(graph[module]):
            cycle = visit(imported, [*path, module])
            if cycle:
                return cycle
        done.add(module)
        return None

    for module in sorted(graph):
        cycle = visit(module, [])
        if cycle:
            return cycle
    return None


def find_cycles(graph: Graph) -> list[list[str]]:
    """Import cycles of ``graph`` until every one is broken: each found (find_cycle), then
    its closing import left out to look for the next."""
    remaining = {module: set(imported) for module, imported in graph.items()}
    cycles = []
    while cycle := find_cycle(remaining):
        cycles.append(cycle)
        remaining[cycle[-2]].discard(cycle[-1])
    return cycles


def reachable(graph: Graph, module: str) -> set[str]:
    """The modules ``module`` imports, directly or through others."""
    found: set[str] = set()
    todo = [module]
    while todo:
        for imported in graph[todo.pop()] - found:
            found.add(imported)
            todo.append(imported)
    return found


def test_the_graph_reads_the_forms_of_import() -> None:
    graph = import_graph()
    assert "pae.steps" in graph["pae.train"]  # from pae.steps import CHECKPOINTS, ...
    assert "pae.synthetic" in graph["pae.apps.synthesis"]  # imported inside a function


def test_cycles_are_found() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set()}
    assert find_cycle(graph) == ["a", "b", "c", "a"]
    assert find_cycle(graph | {"c": {"d"}}) is None
    assert find_cycles(graph | {"d": {"b"}}) == [["a", "b", "c", "a"], ["b", "c", "d", "b"]]


def test_no_module_imports_itself_back() -> None:
    cycles = find_cycles(import_graph())
    assert not cycles, "import cycles:\n" + "\n".join(" -> ".join(c) for c in cycles)


def test_steps_import_their_helpers_and_no_other_step() -> None:
    """A step's module (``pae.steps.<name>``) reaches no other step and not pae-eval's
    evaluations; the helpers of ``pae.runs`` and pae-eval's evaluations reach no step."""
    graph = import_graph()
    steps = {module for module in graph if module.startswith("pae.steps.")}
    assert "pae.steps.teacher" in steps
    for step in steps:
        found = reachable(graph, step) & (steps | {"pae.apps.checkpoint_evaluation"})
        assert not found, f"{step} imports {sorted(found)}"
    helpers = [m for m in graph if m.startswith("pae.runs")] + ["pae.apps.checkpoint_evaluation"]
    for helper in helpers:
        found = reachable(graph, helper) & steps
        assert not found, f"{helper} imports {sorted(found)}"


@pytest.mark.parametrize(
    ("omp", "numba_threads", "expected"),
    [("1", None, "1"), ("1", "2", "2"), (None, "1", "1")],
)
def test_numba_threads_follow_omp_num_threads(
    omp: str | None, numba_threads: str | None, expected: str
) -> None:
    """numba's pool takes OMP_NUM_THREADS when NUMBA_NUM_THREADS is not set (a larger pool
    leaves a worker spinning on the core torch needs); NUMBA_NUM_THREADS set wins."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS")}
    env |= {"OMP_NUM_THREADS": omp} if omp else {}
    env |= {"NUMBA_NUM_THREADS": numba_threads} if numba_threads else {}
    code = "import pae, numba; print(numba.config.NUMBA_NUM_THREADS)"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.stdout.strip() == expected, out.stderr


LAYERS = (
    ("pae.core",),
    ("pae.data", "pae.synthetic", "pae.report"),
    ("pae.models", "pae.scene_model"),
    ("pae.refine", "pae.relative", "pae.render_compare"),
    ("pae.lit", "pae.callbacks"),
    ("pae.runs", "pae.steps"),
    ("pae.apps", "pae.config"),
)
"""The packages of ``pae`` from the bottom up: shared maths and infrastructure, data, models
and the scene model, methods, Lightning wiring, steps, what the entry points run. A module
imports its own layer and those below; the entry points (``pae.train``, ``pae.evaluate``,
``pae.localize``, ``pae.data_cli``, ``pae.bench``) sit above every layer."""


def layer_of(module: str) -> int:
    """The layer of ``module`` (its index in ``LAYERS``; ``pae`` itself, which only names the
    config folder and the version, at the bottom; entry points: above all)."""
    if module == "pae":
        return 0
    for rank, packages in enumerate(LAYERS):
        if any(module == p or module.startswith(p + ".") for p in packages):
            return rank
    return len(LAYERS)


def test_no_package_imports_a_package_above_it() -> None:
    graph = import_graph()
    wrong = [
        f"{module} imports {imported}"
        for module, imports in graph.items()
        for imported in imports
        if layer_of(imported) > layer_of(module)
    ]
    assert not wrong, "\n".join(sorted(wrong))


def test_the_layers_are_found() -> None:
    assert layer_of("pae.core.geometry") == 0
    assert layer_of("pae.render_compare.refiner") == 3
    assert layer_of("pae.train") == len(LAYERS)
    assert layer_of("pae.database") == len(LAYERS)


def test_few_modules_at_the_top_and_none_too_long() -> None:
    top = [p for p in (SRC / "pae").glob("*.py")]
    assert len(top) <= 12, sorted(p.name for p in top)
    long = [str(p) for p in (SRC / "pae").rglob("*.py") if len(p.read_text().splitlines()) > 500]
    assert not long, long
    callbacks = (SRC / "pae" / "callbacks").glob("*.py")
    wide = [p.name for p in callbacks if len(p.read_text().splitlines()) > 150]
    assert not wide, f"callbacks are adapters of at most 150 lines: {wide}"
