"""Run every ``benchmarks/bench_*.py`` and print one table; results also go to ``benchmarks/results.json``.

Usage: ``python -m benchmarks [AREA ...] [--quick]``; naming areas reruns those and keeps the other
areas' last results in ``results.json``.
"""

from __future__ import annotations

import importlib
import json
import sys
from pathlib import Path

from rich.console import Console
from rich.table import Table

from benchmarks.common import Result


def main(argv: list[str]) -> int:
    quick = "--quick" in argv
    wanted = [a for a in argv if not a.startswith("--")]
    here = Path(__file__).parent
    modules = sorted(p.stem for p in here.glob("bench_*.py"))
    if wanted:
        modules = [m for m in modules if m.removeprefix("bench_") in wanted]
    console = Console()
    results: list[Result] = []
    for name in modules:
        console.print(f"[bold]{name}[/] ...")
        mod = importlib.import_module(f"benchmarks.{name}")
        results.extend(mod.run(quick=quick))
    table = Table(title="benchmarks", title_justify="left")
    for col in ("area", "name", "value", "unit", "reference", "ratio", "target", "note"):
        table.add_column(col)
    for r in results:
        table.add_row(r.area, r.name, f"{r.value:.4g}", r.unit, r.reference,
                      "" if r.ratio is None else f"{r.ratio:.3g}", r.target, r.note)
    console.print(table)
    out = here / "results.json"
    kept: list[dict[str, object]] = []
    if wanted and out.exists():  # a partial run replaces its own areas and keeps the others' last results
        areas = {r.area for r in results}
        kept = [r for r in json.loads(out.read_text()) if r.get("area") not in areas]
    out.write_text(json.dumps(kept + [r.as_dict() for r in results], indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
