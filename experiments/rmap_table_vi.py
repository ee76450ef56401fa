"""RMap Table VI over several run folders, one per a_test: ``python -m experiments.rmap_table_vi DIR ...``.

``pipeline report`` reads one run store, so it shows Table VI for the a_test of that store only. Run the map
sequences once per a_test into their own store (``pipeline run all --seq 'rmap_*' --set patches.a=1
--runs-dir runs_a1``, ...) and pass the stores here: each store's map sequences become one (scene, a_test)
result each (:func:`rmap_results.collect_scene_results`: a_test from the patches manifest) and
:func:`rmap_tables.table_vi` puts them beside the paper's rows.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from core.errors import UserError
from stages.evaluate import rmap_tables as rt
from stages.evaluate.rmap_results import collect_scene_results


def results_of(runs_dirs: Sequence[Path]) -> list[rt.SceneResult]:
    """The map sequences' results of every run store; a one-line error for a store without any."""
    out: list[rt.SceneResult] = []
    for d in runs_dirs:
        res = collect_scene_results(Path(d))
        if not res:
            raise UserError(f"{d}: no evaluated map sequences (rmap_*); run `pipeline run all --seq 'rmap_*' "
                            f"--set patches.a=A --runs-dir {d}` first")
        out += res
    return out


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs_dirs", nargs="+", type=Path, help="run stores, one per a_test")
    ap.add_argument("--out", type=Path, help="also write the table as markdown")
    args = ap.parse_args(argv)
    try:
        results = results_of(args.runs_dirs)
    except UserError as exc:
        print(f"error: {exc}")
        return 2
    table = rt.table_vi(results)
    md = table.markdown()
    print(md)
    if args.out:
        tmp = args.out.with_suffix(args.out.suffix + ".tmp")
        tmp.write_text(md + "\n")
        tmp.replace(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
