"""`complete` stage: point-cloud completion of the radar map (RMap Sec. III-D, IV-B).

Runs a trained checkpoint over every radar patch of the sequence, puts the predicted patches back in world
coordinates, merges them and assembles the map at the voxel resolution: ``assembly = average`` (the
paper's Sec. V, the mean of the points in each voxel; the default) or ``snap`` (the voxel centres, on the
lattice of the radar and lidar maps). torch is imported
only inside :meth:`CompleteStage.run`, so the pipeline imports without the ``learn`` extra.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from pydantic import Field

from pipeline.paths import PROJECT_ROOT
from pipeline.stage import Stage, StageContext, StageParams
from stages.complete.data import Assembly, assemble_map, read_patches

if TYPE_CHECKING:
    from pipeline.sequences import SequenceInfo

#: trained on the simulator: the default for simulated sequences
DEFAULT_CHECKPOINT = "data/models/rmap_small.safetensors"
#: trained on the real ColoRadar maps (RMap's train scenes): the default for every other sequence kind
REAL_CHECKPOINT = "data/models/rmap_coloradar_small.safetensors"


def default_checkpoint(kind: str) -> str:
    """The shipped checkpoint for a sequence kind: simulator-trained for simulated sequences, else real-trained."""
    return DEFAULT_CHECKPOINT if kind == "simulated" else REAL_CHECKPOINT


class CompleteParams(StageParams):
    """Parameters of the `complete` stage."""

    checkpoint: str = Field("auto", description="trained network (.safetensors or .pt); relative paths are "
                            "looked up from the working directory, then the project root; auto = "
                            f"{DEFAULT_CHECKPOINT} for simulated sequences, {REAL_CHECKPOINT} for real data "
                            "(ColoRadar logs, map sequences)")
    device: Literal["cpu", "cuda", "auto"] = Field("cpu", description="where the network runs; auto = cuda "
                                                   "when torch sees a GPU")
    batch_size: int = Field(8, ge=1, description="patches per forward pass")
    seed: int = Field(0, description="seed of the input resampling (patches with more or fewer points than the "
                      "network's input size) and of torch")
    resolution: float | None = Field(None, gt=0, description="downsampling voxel size (m); None = the voxel "
                                     "stage's resolution (RMap: the map resolution, 0.15 m)")
    threads: int | None = Field(None, ge=1, description="torch CPU threads (None = torch's default)")
    assembly: Assembly = Field("average", description="how the merged predicted patches become the map, one "
                               "point per occupied voxel: average = the mean of its points (RMap Sec. V); snap = "
                               "its centre (k + 1/2) * resolution, on the lattice of the voxel maps")


def resolve_checkpoint(path: str, kind: str = "simulated") -> Path:
    """A checkpoint path as given, else relative to the project root; ``auto`` by the sequence ``kind``."""
    if path == "auto":
        path = default_checkpoint(kind)
    p = Path(path).expanduser()
    if p.is_absolute() or p.exists():
        return p
    return PROJECT_ROOT / p


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def height_colors(z: np.ndarray) -> np.ndarray:
    """RGB by height (blue low to red high) for the Rerun view."""
    if len(z) == 0:
        return np.zeros((0, 3), np.uint8)
    t = (z - np.percentile(z, 2)) / max(float(np.percentile(z, 98) - np.percentile(z, 2)), 1e-6)
    t = np.clip(t, 0.0, 1.0)
    return (np.stack([t, 1.0 - np.abs(2.0 * t - 1.0), 1.0 - t], axis=1) * 255).astype(np.uint8)


class CompleteStage(Stage):
    name = "complete"
    description = "point-cloud completion of the radar map (RMap Sec. III-D)"
    inputs = ("patches", "voxel")
    Params = CompleteParams
    version = "1"
    outputs = ("completed_map.parquet",)
    requires = ("torch", "safetensors")
    requires_extra = "learn"

    def key_material(self, seq: SequenceInfo, params: StageParams) -> dict[str, Any]:
        assert isinstance(params, CompleteParams)
        path = resolve_checkpoint(params.checkpoint, seq.kind)
        return {"checkpoint_sha256": file_sha256(path) if path.exists() else "missing"}

    def resolution(self, ctx: StageContext) -> float:
        p: CompleteParams = ctx.params
        if p.resolution is not None:
            return p.resolution
        manifest = ctx.input_dirs["voxel"] / "manifest.json"
        try:
            res = json.loads(manifest.read_text())["params"]["resolution"]
            return float(res)
        except (OSError, KeyError, TypeError, ValueError, json.JSONDecodeError):
            ctx.warn(f"{manifest}: no voxel resolution found; downsampling at 0.15 m (set complete.resolution)")
            return 0.15

    def run(self, ctx: StageContext) -> None:
        import torch

        from schemas import write_artifact
        from stages.complete.checkpoint import load_checkpoint
        from stages.complete.infer import complete_patches, resolve_device

        p: CompleteParams = ctx.params
        if p.threads is not None:
            torch.set_num_threads(p.threads)
        device = resolve_device(p.device)
        ckpt = resolve_checkpoint(p.checkpoint, ctx.seq.kind)
        model, meta = load_checkpoint(ckpt, device)
        patches = read_patches(ctx.input("patches", "patches.parquet"), ctx.seq.name)
        res = self.resolution(ctx)
        t0 = time.perf_counter()
        with ctx.progress(len(patches), "completing patches") as advance:
            result = complete_patches(model, meta, patches, device, p.batch_size, p.seed, advance)
        wall = time.perf_counter() - t0
        merged = np.concatenate(result.points) if result.points else np.zeros((0, 3))
        down, counts = assemble_map(merged, res, p.assembly)
        if not patches:
            ctx.warn("the patches artifact holds no radar patches; the completed map is empty")
        write_artifact({"x": down[:, 0], "y": down[:, 1], "z": down[:, 2], "count": counts.astype(np.int32)},
                       ctx.output("completed_map.parquet"), "completed_map")
        ctx.recording.static_points("world/complete", down, colors=height_colors(down[:, 2]), radii=res / 2)
        ctx.stats.update({
            "n_patches": len(patches),
            "n_points_predicted": len(merged),
            "n_points": len(down),
            "resolution": res,
            "assembly": p.assembly,
            "device": str(device),
            "checkpoint": str(ckpt.relative_to(PROJECT_ROOT) if ckpt.is_relative_to(PROJECT_ROOT) else ckpt),
            "model_size": meta.train.get("config", {}).get("size", ""),
            "norm_scale_m": meta.norm_scale,
            "model_seconds": result.model_seconds,
            "seconds_per_patch": result.seconds_per_patch,
            "wall_seconds": wall,
        })


STAGE = CompleteStage()
