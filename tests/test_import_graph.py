"""The project's import graph: no cycles, and the orchestration layer imports no stage algorithm.

Edges are every ``import`` the interpreter may execute (module level and inside functions); imports under
``if TYPE_CHECKING:`` are type-only and do not count. Stages are reached from ``pipeline/`` through the
stage registry (``pipeline.registry`` imports ``stages.<name>.stage`` by name), never by a static import.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "stages", "schemas", "simulator", "sources")
#: static imports of stage modules from pipeline/ that are tolerated, with the reason (keep this short)
ALLOWED_PIPELINE_TO_STAGES = {
    # the `train` command's adapter lives in the complete stage's package (owned there); no algorithm module
    ("pipeline.cli", "stages.complete.train_cli"),
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


def import_graph() -> dict[str, set[str]]:
    """``{module: modules it imports at run time}`` over the project's packages."""
    mods = _modules()

    def resolve(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for mod, path in mods.items():
        tree = ast.parse(path.read_text(), str(path))
        skip = _type_checking_lines(tree)
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
    assert "pipeline.sequences" not in g["pipeline.stage"]  # type-only import, ignored
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycles() -> None:
    found = cycles(import_graph())
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_orchestration_imports_no_stage_module() -> None:
    g = import_graph()
    bad = sorted((m, d) for m, deps in g.items() if m.startswith("pipeline") for d in deps
                 if d.startswith("stages") and (m, d) not in ALLOWED_PIPELINE_TO_STAGES)
    assert not bad, f"pipeline/ imports stage modules (reach them through the stage registry): {bad}"


@pytest.mark.parametrize("layer", ["sources", "schemas", "simulator"])
def test_lower_layers_import_no_stage_and_no_registry(layer: str) -> None:
    """Sources, schemas and the simulator sit below the stages and the sequence registry."""
    g = import_graph()
    bad = sorted((m, d) for m, deps in g.items() if m.split(".")[0] == layer for d in deps
                 if d.startswith("stages") or d in ("pipeline.sequences", "pipeline.runner", "pipeline.registry",
                                                    "pipeline.cli", "pipeline.config", "pipeline.stage"))
    assert not bad, bad
