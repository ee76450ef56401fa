"""The project's import graph: no cycles between modules or packages, no stage importing another, and layers.

Layers, bottom up: ``core`` (shared algorithms, errors, paths, the stage framework); ``schemas``, ``simulator``
and ``sources``; the stages (``stages.<name>``, each its own package); ``pipeline`` (orchestration).

Edges are every ``import`` the interpreter may execute (module level and inside functions); imports under
``if TYPE_CHECKING:`` are type-only and do not count. Stages are reached from ``pipeline/`` through the
stage registry (``pipeline.registry`` imports ``stages.<name>.stage`` by name), never by a static import.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("core", "pipeline", "stages", "schemas", "simulator", "sources", "experiments")
#: orchestration modules that may import one stage's package statically, with the reason (keep this short)
ALLOWED_PIPELINE_TO_STAGES = {
    # the `train` command trains the complete stage's networks (loaded when the command runs, torch with it)
    "pipeline.train": "stages.complete",
}


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for f in (ROOT / pkg).rglob("*.py"):
            name = ".".join(f.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
            out[name] = f
    return out


def _type_checking_lines(tree: ast.AST) -> set[int]:
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If):
            t = node.test
            name = t.id if isinstance(t, ast.Name) else t.attr if isinstance(t, ast.Attribute) else ""
            if name == "TYPE_CHECKING":
                for sub in node.body:
                    for n in ast.walk(sub):
                        if hasattr(n, "lineno"):
                            lines.add(n.lineno)
    return lines


def import_graph(types: bool = False) -> dict[str, set[str]]:
    """``{module: modules it imports at run time}`` over the project's packages; with ``types`` also the
    type-only imports (``if TYPE_CHECKING:``)."""
    mods = _modules()

    def resolve(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for mod, path in mods.items():
        tree = ast.parse(path.read_text(), str(path))
        skip = set() if types else _type_checking_lines(tree)
        deps: set[str] = set()
        for node in ast.walk(tree):
            if getattr(node, "lineno", None) in skip:
                continue
            if isinstance(node, ast.Import):
                deps |= {r for a in node.names if (r := resolve(a.name))}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                for a in node.names:
                    full = f"{node.module}.{a.name}"
                    r = full if full in mods else resolve(node.module)
                    if r:
                        deps.add(r)
        deps.discard(mod)
        graph[mod] = deps
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_graph_sees_known_edges() -> None:
    """The scanner finds module-level and function-level imports (so the checks below can fail)."""
    g = import_graph()
    assert "sources.mapset" in g["pipeline.sequences"]  # module level
    assert "simulator" in g["sources.simulated"]  # inside a function
    assert "sources.sequence" not in g["stages.slam.stage"]  # type-only import, ignored
    assert "sources.sequence" in import_graph(types=True)["stages.slam.stage"]  # unless asked for
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def package_of(module: str) -> str:
    """The package a module belongs to: ``stages.<name>`` for a stage, else the top-level package."""
    parts = module.split(".")
    return ".".join(parts[:2]) if parts[0] == "stages" and len(parts) > 1 else parts[0]


def package_graph(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """The module graph collapsed onto packages (self-edges dropped)."""
    out: dict[str, set[str]] = {}
    for mod, deps in graph.items():
        a = package_of(mod)
        out.setdefault(a, set()).update(b for d in deps if (b := package_of(d)) != a)
    return out


def test_no_import_cycles() -> None:
    found = cycles(import_graph(types=True))  # type-only imports close no circle either
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_orchestration_imports_no_stage_module() -> None:
    g = import_graph()
    bad = sorted((m, d) for m, deps in g.items() if m.startswith("pipeline") for d in deps
                 if d.startswith("stages") and not d.startswith(ALLOWED_PIPELINE_TO_STAGES.get(m, "\0")))
    assert not bad, f"pipeline/ imports stage modules (reach them through the stage registry): {bad}"


@pytest.mark.parametrize("layer", ["sources", "schemas", "simulator"])
def test_lower_layers_import_no_stage_and_no_registry(layer: str) -> None:
    """Sources, schemas and the simulator sit below the stages and the sequence registry."""
    g = import_graph()
    bad = sorted((m, d) for m, deps in g.items() if m.split(".")[0] == layer for d in deps
                 if d.startswith("stages") or d in ("pipeline.sequences", "pipeline.runner", "pipeline.registry",
                                                    "pipeline.cli", "pipeline.config", "core.stage"))
    assert not bad, bad


def test_package_graph_collapses_and_finds_cycles() -> None:
    """The package view merges modules (so the package checks below can fail)."""
    g = {"stages.a.x": {"stages.b.y"}, "stages.b.y": {"core.z"}, "core.z": set(), "pipeline.p": {"stages.a.x"}}
    assert package_graph(g) == {"stages.a": {"stages.b"}, "stages.b": {"core"}, "core": set(), "pipeline": {"stages.a"}}
    circle = {"stages.a.x": {"stages.b.y"}, "stages.b.y": {"stages.a.z"}}
    assert cycles(package_graph(circle)) == [["stages.a", "stages.b"]]


def test_no_package_cycles() -> None:
    found = cycles(package_graph(import_graph()))
    assert not found, "package cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_no_stage_imports_another_stage() -> None:
    """Code that several stages use lives in ``core``; a stage reaches another's results through artifacts."""
    bad = sorted((a, b) for a, deps in package_graph(import_graph()).items() if a.startswith("stages.")
                 for b in deps if b.startswith("stages.") and b != "stages")
    assert not bad, f"stage-to-stage imports (move the shared code to core/): {bad}"


def test_core_imports_nothing_above_it() -> None:
    """Not even for a type annotation."""
    g = import_graph(types=True)
    bad = sorted((m, d) for m, deps in g.items() if m.split(".")[0] == "core" for d in deps
                 if d.split(".")[0] != "core")
    assert not bad, bad


@pytest.mark.parametrize("layer", ["core", "schemas", "simulator", "sources", "stages"])
def test_nothing_below_pipeline_imports_it(layer: str) -> None:
    """``pipeline/`` is the orchestration on top; nothing below it imports it (stages are reached by name), not even
    for a type annotation."""
    g = import_graph(types=True)
    bad = sorted((m, d) for m, deps in g.items() if m.split(".")[0] == layer for d in deps
                 if d.split(".")[0] == "pipeline")
    assert not bad, bad


def test_product_imports_no_experiment() -> None:
    g = import_graph()
    bad = sorted((m, d) for m, deps in g.items() if m.split(".")[0] != "experiments" for d in deps
                 if d.split(".")[0] == "experiments")
    assert not bad, bad
