"""RMap Table III on a published map set: input radar map and completed map of every scene against the
ground truth, beside the paper's values, with the Overall row (mean of the scene rows).

The completed map takes the `complete` stage's path: Algorithm 1's patches at ``a`` (a_test = 4), every
patch through the network, predictions merged and assembled at 0.15 m (the paper's Sec. V: the mean of the
points in each voxel). Run it as

    python -m experiments.rmap_uppointr_table --maps ../shared/data/coloradar_maps \
        --checkpoint data/models/rmap_coloradar_small.safetensors --out runs/table3.md
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from stages.complete.paper_table3 import KEYS, OVERALL, TABLE3, as_dict

LABELS = ("CD-l1", "CD-l2", "F@0.15", "D50", "D75", "D90", "D95")


def evaluate_scenes(root: str | Path, scenes: Sequence[str], checkpoint: str | Path, a: float = 4.0,
                    resolution: float = 0.15, device: str = "cpu", batch_size: int = 8, seed: int = 0,
                    advance: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """Per scene: the input and completed maps' metrics, patch count and network seconds per patch."""
    from sources.mapset import read_index
    from stages.complete.checkpoint import load_checkpoint
    from stages.complete.data import voxel_downsample
    from stages.complete.infer import resolve_device
    from stages.complete.map_eval import predict_map, score
    from stages.complete.maps import read_scene, scene_patches

    info = read_index(root)
    dev = resolve_device(device)
    model, meta = load_checkpoint(checkpoint, dev)
    rows = []
    for name in scenes:
        radar, gt = read_scene(root, name)
        patches = scene_patches(radar, gt, name, a, seed)
        t0 = time.perf_counter()
        merged, spp = predict_map(model, meta, patches, dev, batch_size, seed)
        row: dict[str, Any] = {"scene": name, "environment": info[name].environment,
                               "gt_source": info[name].gt_source, "n_patches": len(patches),
                               "seconds_per_patch": spp, "seconds": time.perf_counter() - t0,
                               "input": score(radar, gt)}
        row["completed"] = score(voxel_downsample(merged, resolution)[0], gt)
        rows.append(row)
        if advance is not None:
            advance(name)
    return rows


def overall(rows: Sequence[dict[str, Any]], which: str) -> dict[str, float]:
    """Table III's Overall row: the mean of the scene rows."""
    return {k: float(np.mean([r[which][k] for r in rows])) for k in KEYS}


def _fmt(d: dict[str, float]) -> str:
    return " | ".join(f"{d[k]:.3f}" for k in KEYS)


#: the second table's columns: both F-score forms (map_metrics: strict ``<`` and the robust form)
F_KEYS = ("cd_l1", "cd_l2", "fscore_0.15", "fscore_0.15_robust", "precision_0.15_robust", "recall_0.15_robust")
F_LABELS = ("CD-l1", "CD-l2", "F@0.15 exact", "F@0.15 robust", "P robust", "R robust")


def render(rows: Sequence[dict[str, Any]], checkpoint: str, a: float) -> str:
    """Markdown: per scene paper input | ours input | paper RMap | ours completed, then the Overall rows; then
    both F-score forms per scene and Overall."""
    head = " | ".join(LABELS)
    maps = [("ours completed", "completed")]
    out = [f"Table III on {len(rows)} scenes, checkpoint `{checkpoint}`, a_test = {a:g}, merged predictions "
           "averaged per 0.15 m voxel. `*` = ground truth rebuilt from the published patches.",
           "", f"| scene | map | {head} |", "| --- | --- |" + " --- |" * len(KEYS)]
    for r in rows:
        name = r["scene"] + ("*" if r["gt_source"] != "map" else "")
        paper = TABLE3.get(r["scene"])
        if paper:
            out.append(f"| {name} | paper input | {_fmt(as_dict(paper[0]))} |")
        out.append(f"| {name} | ours input | {_fmt(r['input'])} |")
        if paper:
            out.append(f"| {name} | paper RMap | {_fmt(as_dict(paper[1]))} |")
        for label, key in maps:
            out.append(f"| {name} | {label} | {_fmt(r[key])} |")
    in_paper = [r for r in rows if r["scene"] in TABLE3]
    if in_paper:
        same = [TABLE3[r["scene"]] for r in in_paper]
        p_in = dict(zip(KEYS, np.mean([s[0] for s in same], axis=0).tolist(), strict=True))
        p_rm = dict(zip(KEYS, np.mean([s[1] for s in same], axis=0).tolist(), strict=True))
        out.append(f"| Overall ({len(in_paper)} scenes) | paper input | {_fmt(p_in)} |")
        out.append(f"| Overall ({len(in_paper)} scenes) | paper RMap | {_fmt(p_rm)} |")
    out.append(f"| Overall ({len(rows)} scenes) | ours input | {_fmt(overall(rows, 'input'))} |")
    for label, key in maps:
        out.append(f"| Overall ({len(rows)} scenes) | {label} | {_fmt(overall(rows, key))} |")
    out.append(f"| Overall (paper, 21 scenes) | paper input | {_fmt(as_dict(OVERALL[0]))} |")
    out.append(f"| Overall (paper, 21 scenes) | paper RMap | {_fmt(as_dict(OVERALL[1]))} |")
    if rows and all(k in rows[0]["input"] for k in F_KEYS):
        out += ["", "Both F-score forms (paper-exact: strict `<` in float64; robust: threshold 0.15 m less 0.1 %, "
                "so lattice neighbours one voxel away never count), with the robust precision and recall:", "",
                f"| scene | map | {' | '.join(F_LABELS)} |", "| --- | --- |" + " --- |" * len(F_KEYS)]
        both = [("input", "input"), *maps]
        for r in rows:
            for label, key in both:
                out.append(f"| {r['scene']} | {label} | {' | '.join(f'{r[key][k]:.3f}' for k in F_KEYS)} |")
        for label, key in both:
            ov = {k: float(np.mean([r[key][k] for r in rows])) for k in F_KEYS}
            out.append(f"| Overall ({len(rows)} scenes) | {label} | {' | '.join(f'{ov[k]:.3f}' for k in F_KEYS)} |")
    n = sum(r["n_patches"] for r in rows)
    total = sum(r["seconds_per_patch"] * r["n_patches"] for r in rows)
    out += ["", f"{n} patches; network {total:.1f} s in all, {total / max(n, 1):.4f} s per patch (paper, Table "
            "VI: 56 s for 1262 patches at a_test = 4 on an RTX 6000, one patch at a time)."]
    return "\n".join(out) + "\n"


def main(
    maps: Annotated[Path, typer.Option("--maps", help="map set (index.json, <scene>/{radar,lidar_filtered}.parquet)")],
    checkpoint: Annotated[str, typer.Option("--checkpoint", help="completion checkpoint")],
    scenes: Annotated[str, typer.Option("--scenes", help="test (RMap Table III), val (the training run's "
                                        "validation scenes) or a,b,...")] = "test",
    a: Annotated[float, typer.Option("--a", help="patch seed multiplier (a_test)")] = 4.0,
    device: Annotated[str, typer.Option("--device", help="cpu, cuda or auto")] = "cpu",
    batch_size: Annotated[int, typer.Option("--batch-size", help="patches per forward pass (paper's timing: 1)")] = 8,
    threads: Annotated[int | None, typer.Option("--threads", help="torch CPU threads")] = None,
    out: Annotated[Path | None, typer.Option("--out", help="write the markdown here (and .json beside it)")] = None,
) -> None:
    """Table III (input vs completed, beside the paper) for the scenes of a map set."""
    import torch
    from rich.console import Console
    from rich.progress import Progress

    from sources.mapset import read_index
    from stages.complete.maps import validation_scenes

    if threads is not None:
        torch.set_num_threads(threads)
    info = read_index(maps)
    if scenes == "test":
        names = [n for n, s in info.items() if s.split == "test"]
    elif scenes == "val":
        names = validation_scenes(info)
    else:
        names = [s.strip() for s in scenes.split(",") if s.strip()]
        missing = [n for n in names if n not in info]
        if missing:
            raise typer.BadParameter(f"not in {maps}: {', '.join(missing)}", param_hint="--scenes")
    console = Console(stderr=True)
    with Progress(console=console, transient=True) as prog:
        task = prog.add_task("scenes", total=len(names))
        rows = evaluate_scenes(maps, names, checkpoint, a, device=device, batch_size=batch_size,
                               advance=lambda _n: prog.advance(task))
    text = render(rows, checkpoint, a)
    print(text)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        for path, body in ((out, text), (out.with_suffix(".json"), json.dumps(rows, indent=1) + "\n")):
            tmp = path.with_name(f".{path.name}.tmp")
            tmp.write_text(body)
            tmp.replace(path)


if __name__ == "__main__":
    typer.run(main)
