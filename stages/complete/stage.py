"""`complete` stage: point-cloud completion of the radar map (RMap Sec. III-D, IV-B).

``model = uppointr`` (default): runs a trained UpPoinTr checkpoint over every radar patch of the sequence,
puts the predicted patches back in world coordinates, merges them and assembles the map at the voxel
resolution (the paper's Sec. V: the mean of the points in each voxel). ``model = voxel``: the
voxel U-Net (``voxel_net.py``) predicts the occupancy of every voxel of the radar map's lattice inside the
trajectory band, thresholded at the checkpoint's validation threshold; it needs the recorded trajectory
(``map_trajectory.parquet``: a map set's recorded one, or the one a log's radar map was built along).
``prefilter = band`` keeps only radar voxels inside the trajectory band (RMap's future work); ``auto``: on for
the voxel model (trained so), off for UpPoinTr. ``models`` runs further models beside the
configured one, each with its ``auto`` checkpoint, and writes their maps as ``completed_map_<model>.parquet``
(``auto``: every model on map sequences ``rmap_*``, only the configured one elsewhere); with a recorded trajectory
the stage also writes the band-filtered radar map (``radar_map_band.parquet``) for the evaluate stage's
pre-filtered input row. torch is imported only inside :meth:`CompleteStage.run`, so the pipeline imports without
the ``learn`` extra.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from pydantic import Field

from core.errors import UserError
from core.paths import PROJECT_ROOT
from core.stage import ParamGroup, Stage, StageContext, StageParams
from stages.complete.data import F64, read_patches, voxel_downsample
from stages.complete.voxel_grid import Band, in_band, trajectory_band

if TYPE_CHECKING:
    from sources.sequence import SequenceInfo

Model = Literal["uppointr", "voxel"]

#: trained on the simulator: the default for simulated sequences
DEFAULT_CHECKPOINT = "data/models/rmap_small.safetensors"
#: trained on the real ColoRadar maps (RMap's train scenes): the default for every other sequence kind
REAL_CHECKPOINT = "data/models/rmap_coloradar_small.safetensors"
#: the voxel model, trained on the real ColoRadar maps (RMap's train scenes): every sequence kind
VOXEL_CHECKPOINT = "data/models/rmap_voxel.safetensors"


#: the completion models, in the order the tables list them
MODELS: tuple[Model, ...] = ("uppointr", "voxel")
#: the band-filtered radar map (written when the sequence has a recorded trajectory)
BAND_FILE = "radar_map_band.parquet"


def model_file(model: str) -> str:
    """``completed_map_<model>.parquet``: a model's map when several ran."""
    return f"completed_map_{model}.parquet"


def default_checkpoint(kind: str, model: str = "uppointr") -> str:
    """The shipped checkpoint for a sequence kind and model: UpPoinTr simulator-trained for simulated
    sequences, else real-trained; the voxel model's real-trained one for every kind."""
    if model == "voxel":
        return VOXEL_CHECKPOINT
    return DEFAULT_CHECKPOINT if kind == "simulated" else REAL_CHECKPOINT


class PrefilterParams(ParamGroup):
    """The radar pre-filter of the map input."""

    mode: Literal["auto", "none", "band"] = Field("auto", description="band = keep radar voxels within band_radius "
                                                  "and band_z_below..band_z_above of the recorded trajectory; auto = "
                                                  "band for the voxel model, none for uppointr")
    band_radius: float = Field(7.0, gt=0, description="horizontal distance to the trajectory (m)")
    band_z_below: float = Field(-3.0, description="lowest height over the trajectory (m)")
    band_z_above: float = Field(4.5, description="highest height over the trajectory (m)")


class RuntimeParams(ParamGroup):
    """Where and how the network runs (the output does not depend on these, bf16 aside)."""

    device: Literal["cpu", "cuda", "auto"] = Field("cpu", description="where the network runs; auto = cuda "
                                                   "when torch sees a GPU")
    threads: int | None = Field(None, ge=1, le=256, description="torch CPU threads (None = torch's default)")
    batch_size: int = Field(8, ge=1, le=4096, description="uppointr: patches per forward pass")
    tile: int | None = Field(None, ge=8, le=4096,
                             description="voxel model: xy tile core (voxels, a multiple of 8); None = "
                             "one pass over the whole map up to 24 M voxels, else 256; the halo is the receptive "
                             "radius, so the output does not depend on it")
    bf16: bool = Field(False, description="voxel model: run the network under bfloat16 autocast (1.5x faster on a "
                       "CPU with bf16 support, Table III unchanged to the printed digit on the 18 test scenes; the "
                       "probabilities differ slightly, so the map may differ by a few voxels)")


class CompleteParams(StageParams):
    """Parameters of the `complete` stage."""

    model: Model = Field("uppointr", description="uppointr = the paper's patch network; voxel = the per-voxel 3D "
                         "U-Net on the map's lattice; its map is completed_map.parquet")
    models: list[Model] | Literal["auto"] = Field("auto", description="models run beside the configured one (each "
                                                  "with its auto checkpoint), their maps written as "
                                                  "completed_map_<model>.parquet for side-by-side tables; auto = "
                                                  "every model on map sequences (rmap_*), only `model` elsewhere")
    checkpoint: str = Field("auto", description="trained network (.safetensors or .pt); relative paths are "
                            "looked up from the working directory, then the project root; auto = "
                            f"{DEFAULT_CHECKPOINT} for simulated sequences, {REAL_CHECKPOINT} for real data "
                            f"(ColoRadar logs, map sequences); with model = voxel {VOXEL_CHECKPOINT}")
    seed: int = Field(0, description="seed of the input resampling (patches with more or fewer points than the "
                      "network's input size) and of torch")
    resolution: float | None = Field(None, ge=0.01, description="downsampling voxel size (m); None = the voxel "
                                     "stage's resolution (RMap: the map resolution, 0.15 m)")
    threshold: float | None = Field(None, gt=0, lt=1, description="voxel model: occupancy threshold of the "
                                    "completed map; None = the checkpoint's (chosen on its validation scenes)")
    prefilter: PrefilterParams = Field(default_factory=PrefilterParams, description="the radar pre-filter")
    runtime: RuntimeParams = Field(default_factory=RuntimeParams, description="where the network runs")


def resolve_checkpoint(path: str, kind: str = "simulated", model: str = "uppointr") -> Path:
    """A checkpoint path as given, else relative to the project root; ``auto`` by the sequence ``kind`` and
    the ``model``."""
    if path == "auto":
        path = default_checkpoint(kind, model)
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

    def input_stages(self, params: StageParams) -> tuple[str, ...]:
        assert isinstance(params, CompleteParams)
        # models = auto may add UpPoinTr (map sequences), which reads the patches
        wanted = [params.model, *(MODELS if params.models == "auto" else params.models)]
        return self.inputs if "uppointr" in wanted else ("voxel",)

    @staticmethod
    def models_to_run(kind: str, params: CompleteParams) -> list[Model]:
        """The configured model first, then the others of ``models`` (``auto``: all on map sequences)."""
        extra: list[Model] = (list(MODELS) if kind == "rmap" else []) if params.models == "auto" else params.models
        return [params.model, *(m for m in dict.fromkeys(extra) if m != params.model)]

    @staticmethod
    def model_checkpoint(params: CompleteParams, kind: str, model: str) -> Path:
        """``checkpoint`` for the configured model, the ``auto`` one for the others."""
        return resolve_checkpoint(params.checkpoint if model == params.model else "auto", kind, model)

    def key_material(self, seq: SequenceInfo, params: StageParams) -> dict[str, Any]:
        assert isinstance(params, CompleteParams)
        path = resolve_checkpoint(params.checkpoint, seq.kind, params.model)
        out: dict[str, Any] = {"checkpoint_sha256": file_sha256(path) if path.exists() else "missing"}
        others = self.models_to_run(seq.kind, params)[1:]
        if others:
            paths = {m: self.model_checkpoint(params, seq.kind, m) for m in others}
            out["model_checkpoints_sha256"] = {m: file_sha256(q) if q.exists() else "missing"
                                               for m, q in paths.items()}
        return out

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
        from stages.complete.infer import resolve_device

        p: CompleteParams = ctx.params
        if p.runtime.threads is not None:
            torch.set_num_threads(p.runtime.threads)
        device = resolve_device(p.runtime.device)
        models = self.models_to_run(ctx.seq.kind, p)
        # every model runs before anything is written: a failing one leaves no file behind
        runs: dict[Model, tuple[F64, dict[str, Any]]] = {}
        for m in models:
            ckpt = self.model_checkpoint(p, ctx.seq.kind, m)
            runs[m] = self._run_voxel(ctx, p, ckpt, device) if m == "voxel" else \
                self._run_uppointr(ctx, p, ckpt, device)
        band_map = self._band_radar(ctx, p)
        res = self.resolution(ctx)

        def write(pts: F64, counts: np.ndarray, name: str) -> None:
            write_artifact({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "count": counts.astype(np.int32)},
                           ctx.output(name), "completed_map")

        for m, (pts, stats) in runs.items():
            counts = stats.pop("_counts")
            if m == p.model:
                write(pts, counts, "completed_map.parquet")
                ctx.recording.static_points("world/complete", pts, colors=height_colors(pts[:, 2]), radii=res / 2)
                ctx.stats.update(stats)
            if len(runs) > 1:
                if m != p.model:
                    write(pts, counts, model_file(m))
                    ctx.recording.static_points(f"world/complete_{m}", pts, colors=height_colors(pts[:, 2]),
                                                radii=res / 2)
                ctx.stats.setdefault("models", {})[m] = {
                    k: stats[k] for k in ("checkpoint", "model_size", "n_parameters", "n_points", "model_seconds",
                                          "wall_seconds", "prefilter", "n_patches", "device") if k in stats}
                ctx.stats["models"][m]["file"] = "completed_map.parquet" if m == p.model else model_file(m)
        if band_map is not None:
            write(band_map, np.ones(len(band_map), np.int32), BAND_FILE)
            ctx.stats["n_radar_band"] = len(band_map)

    def _band_radar(self, ctx: StageContext, p: CompleteParams) -> F64 | None:
        """The radar map inside the trajectory band (the pre-filtered input); None without a trajectory."""
        if not (ctx.input_dirs["voxel"] / "map_trajectory.parquet").is_file():
            return None
        radar = self._cloud(ctx.input("voxel", "radar_map.parquet"), "radar_map")
        return trajectory_band(radar, self._trajectory(ctx), self.band(p))

    def _run_uppointr(self, ctx: StageContext, p: CompleteParams, ckpt: Path,
                      device: Any) -> tuple[F64, dict[str, Any]]:
        """UpPoinTr over every radar patch, merged and assembled at the voxel resolution (RMap Sec. III-D, V)."""
        from stages.complete.checkpoint import load_checkpoint
        from stages.complete.infer import complete_patches
        from stages.complete.voxel_checkpoint import checkpoint_kind

        if ckpt.is_file() and checkpoint_kind(ckpt) != "uppointr":
            raise UserError(f"{ckpt}: a {checkpoint_kind(ckpt)} checkpoint, not UpPoinTr; set complete.model = voxel "
                            "or give an UpPoinTr checkpoint")
        model, meta = load_checkpoint(ckpt, device)
        patches = read_patches(ctx.input("patches", "patches.parquet"), ctx.seq.name)
        if p.prefilter.mode == "band":
            traj = self._trajectory(ctx)
            band = self.band(p)
            patches = [q for q in (replace(q, radar=trajectory_band(q.radar, traj, band)) for q in patches)
                       if len(q.radar)]
        res = self.resolution(ctx)
        t0 = time.perf_counter()
        with ctx.progress(len(patches), "completing patches (UpPoinTr)") as advance:
            result = complete_patches(model, meta, patches, device, p.runtime.batch_size, p.seed, advance)
        wall = time.perf_counter() - t0
        merged = np.concatenate(result.points) if result.points else np.zeros((0, 3))
        down, counts = voxel_downsample(merged, res)
        if not patches:
            ctx.warn("the patches artifact holds no radar patches; the completed map is empty")
        return down, {
            "_counts": counts,
            "n_patches": len(patches),
            "n_points_predicted": len(merged),
            "n_points": len(down),
            "resolution": res,
            "device": str(device),
            "checkpoint": str(ckpt.relative_to(PROJECT_ROOT) if ckpt.is_relative_to(PROJECT_ROOT) else ckpt),
            "model_size": meta.train.get("config", {}).get("size", ""),
            "n_parameters": int(sum(q.numel() for q in model.parameters())),
            "norm_scale_m": meta.norm_scale,
            "model_seconds": result.model_seconds,
            "seconds_per_patch": result.seconds_per_patch,
            "wall_seconds": wall,
            "model": "uppointr",
            "prefilter": p.prefilter.mode if p.prefilter.mode != "auto" else "none",
        }

    @staticmethod
    def band(p: CompleteParams) -> Band:
        return Band(p.prefilter.band_radius, p.prefilter.band_z_below, p.prefilter.band_z_above)

    def _cloud(self, path: Path, schema: str) -> F64:
        from schemas import read_artifact

        t = read_artifact(path, schema, columns=["x", "y", "z"])
        return np.stack([t.column(c).to_numpy().astype(np.float64) for c in "xyz"], axis=1)

    def _trajectory(self, ctx: StageContext) -> F64:
        path = ctx.input_dirs["voxel"] / "map_trajectory.parquet"
        if not path.is_file():
            raise UserError(f"complete: {ctx.seq.name} has no recorded trajectory ({path} is missing; the voxel "
                            "model and the band pre-filter need it); rerun `pipeline run voxel --seq "
                            f"{ctx.seq.name} --force`, or set complete.model = uppointr and complete.prefilter.mode = "
                            "none and leave voxel out of complete.models")
        traj = self._cloud(path, "map_trajectory")
        if len(traj) == 0:
            raise UserError(f"{path}: the recorded trajectory is empty")
        return traj

    def _run_voxel(self, ctx: StageContext, p: CompleteParams, ckpt: Path,
                   device: Any) -> tuple[F64, dict[str, Any]]:
        """The voxel model over the whole map (tiled, equal to one pass), thresholded (RMap Sec. III-D's task
        posed per voxel)."""
        from stages.complete.voxel_checkpoint import load_voxel_checkpoint
        from stages.complete.voxel_grid import LatticeError, key_centres, lattice_keys
        from stages.complete.voxel_net import (
            auto_core,
            map_domain,
            n_parameters,
            predict_tiles,
            tile_origins,
        )

        model, meta = load_voxel_checkpoint(ckpt, str(device))
        if p.threshold is not None:  # the sequence kind's own decision threshold; the gate stays below it
            meta = replace(meta, threshold=p.threshold, union_gate=min(meta.union_gate, p.threshold))
        res = self.resolution(ctx)
        if abs(res - meta.resolution) > 1e-9:
            raise UserError(f"{ckpt}: trained for {meta.resolution:g} m voxels, the map is at {res:g} m; train a "
                            "voxel model at this resolution or set voxel.resolution")
        if p.runtime.tile is not None and p.runtime.tile % model.stride():
            raise UserError(f"complete.runtime.tile = {p.runtime.tile}: must be a multiple of {model.stride()}")
        radar_path = ctx.input("voxel", "radar_map.parquet")
        radar = self._cloud(radar_path, "radar_map")
        if len(radar) == 0:
            raise UserError(f"{radar_path}: the radar map has no voxels; nothing to complete")
        traj = self._trajectory(ctx)
        try:
            keys = lattice_keys(radar, res, "radar map")
            lidar_path = ctx.input_dirs["voxel"] / "lidar_map.parquet"
            if lidar_path.is_file():
                lattice_keys(self._cloud(lidar_path, "lidar_map"), res, "lidar map")
        except LatticeError as exc:
            raise UserError(f"{ctx.input_dirs['voxel']}: {exc}; the radar and lidar maps must be voxel centres "
                            "of one lattice") from exc
        prefilter = p.prefilter.mode in ("auto", "band")
        if prefilter:
            keep = in_band(radar, traj, self.band(p))
            keys = keys[keep]
            if len(keys) == 0:
                raise UserError(f"{radar_path}: no radar voxel within the pre-filter band of the trajectory "
                                f"({self.band(p)}); widen complete.prefilter.band_* or set "
                                "complete.prefilter.mode = none")
        t0 = time.perf_counter()
        dom = map_domain(traj, res, meta.band, model.stride())
        core = p.runtime.tile if p.runtime.tile is not None else auto_core(dom)
        with ctx.progress(len(tile_origins(dom, core)), "completing voxel tiles") as advance:
            pred = predict_tiles(model, keys, traj, res, meta.band, core=core, device=device, advance=advance,
                                 bf16=p.runtime.bf16)
        wall = time.perf_counter() - t0
        out = key_centres(meta.output_keys(pred, keys), res)
        return out, {
            "_counts": np.ones(len(out), np.int32),
            "model": "voxel",
            "prefilter": "band" if prefilter else "none",
            "n_radar_voxels": len(keys),
            "n_points": len(out),
            "resolution": res,
            "device": str(device),
            "bf16": p.runtime.bf16,
            "checkpoint": str(ckpt.relative_to(PROJECT_ROOT) if ckpt.is_relative_to(PROJECT_ROOT) else ckpt),
            "model_size": f"voxel U-Net {n_parameters(model):,} parameters",
            "n_parameters": n_parameters(model),
            "threshold": meta.threshold,
            "union_radar": meta.union_radar,
            "union_gate": meta.union_gate,
            "n_tiles": pred.n_tiles,
            "n_tiles_skipped": pred.n_skipped,
            "n_voxels_run": pred.n_voxels_run,
            "model_seconds": pred.model_seconds,
            "feature_seconds": pred.feature_seconds,
            "wall_seconds": wall,
        }


STAGE = CompleteStage()
