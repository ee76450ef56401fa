"""`patches` stage: FPS patches of the radar and lidar maps (RMap Algorithm 1, Sec. III-B).

Reads the voxel stage's maps, runs ``fps_patches.make_patches`` and writes ``patches.parquet``: one row
per patch point with ``patch`` (int32), ``kind`` ('radar' / 'lidar'), world ``x, y, z``, the patch seed
``seed_x, seed_y, seed_z`` (the normalisation centre), ``scale`` (normalisation scale: network input
``(p - seed) / scale``, back to world ``q * scale + seed``), ``rank`` (neighbour rank, 0 = nearest) and
``padded`` (a resampled duplicate filling a patch when the map holds fewer than N points).
``patches.json`` beside it records the parameters, counts and the normalisation rule.
"""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
from pydantic import Field

from core.errors import UserError
from core.fps_patches import Patches, make_patches
from core.stage import ParamGroup, Stage, StageContext, StageParams
from schemas.io import read_artifact, write_artifact


class OutlierParams(ParamGroup):
    """Statistical outlier removal on the radar map before the patches (RMap Sec. III-B)."""

    neighbors: int = Field(20, ge=0, le=1000, description="k of the k-NN distances (0 = off)")
    std_ratio: float = Field(2.0, gt=0, description="drop radar points whose mean k-NN distance exceeds the map "
                             "mean by this many standard deviations")


class PatchesParams(StageParams):
    """Parameters of the `patches` stage (defaults: RMap Sec. III-B/C, test setting a = 4)."""

    a: float = Field(4.0, gt=0, description="seed multiplier: t = floor(a * n_R / N_R) seeds, at least 1 "
                     "(4 at test, 16 for training)")
    n_radar: int = Field(2048, ge=1, le=1_048_576, description="radar points per patch (N_R)")
    n_lidar: int = Field(8192, ge=1, le=4_194_304, description="lidar points per patch (N_L)")
    norm_scale: float = Field(0.0, ge=0, description="normalisation scale (m); 0 = per patch, the radar patch's "
                              "largest distance from its seed")
    seed: int = Field(0, description="seed of the FPS start point and of the padding draws")
    rerun_patches: int = Field(8, ge=0, le=10_000, description="patches logged to Rerun")
    outliers: OutlierParams = Field(default_factory=OutlierParams, description="outlier removal")


class PatchesStage(Stage):
    name = "patches"
    description = "FPS patches of the radar and lidar maps (RMap Algorithm 1)"
    inputs = ("voxel",)
    Params = PatchesParams
    version = "2"  # 2: t = floor(a * n_R / N_R) seeds (was ceil)
    outputs = ("patches.parquet", "patches.json")

    def run(self, ctx: StageContext) -> None:
        p: PatchesParams = ctx.params
        maps = {}
        for kind in ("radar", "lidar"):
            path = ctx.input("voxel", f"{kind}_map.parquet")
            tab = read_artifact(path, f"{kind}_map", columns=["x", "y", "z"])
            maps[kind] = np.stack([tab.column(c).to_numpy() for c in ("x", "y", "z")], axis=1).astype(np.float64)
            if len(maps[kind]) == 0 and kind == "lidar":
                ctx.warn("the lidar map is empty (no lidar or no ground truth in the log): radar patches only, "
                         "to complete; nothing to train or score them against")
            elif len(maps[kind]) == 0:
                raise UserError(f"{path}: the {kind} map is empty, no patches can be made; check the voxel stage's "
                                "inputs (`pipeline status`)")
        res = make_patches(maps["radar"], maps["lidar"], a=p.a, n_radar=p.n_radar, n_lidar=p.n_lidar,
                           outlier_neighbors=p.outliers.neighbors, outlier_std_ratio=p.outliers.std_ratio,
                           norm_scale=p.norm_scale, seed=p.seed)
        radar = maps["radar"][res.radar_inliers]
        t = len(res.seeds)
        parts = []
        for kind, pts, idx, pad in (("radar", radar, res.radar_idx, res.radar_padded),
                                    ("lidar", maps["lidar"], res.lidar_idx, res.lidar_padded)):
            k = idx.shape[1]
            xyz = pts[idx.reshape(-1)]
            patch = np.repeat(np.arange(t, dtype=np.int32), k)
            seeds = res.seeds[patch]
            parts.append(pa.table({
                "patch": pa.array(patch, pa.int32()),
                "kind": pa.array(np.full(len(patch), kind)),
                "x": pa.array(xyz[:, 0], pa.float64()), "y": pa.array(xyz[:, 1], pa.float64()),
                "z": pa.array(xyz[:, 2], pa.float64()),
                "seed_x": pa.array(seeds[:, 0], pa.float64()), "seed_y": pa.array(seeds[:, 1], pa.float64()),
                "seed_z": pa.array(seeds[:, 2], pa.float64()),
                "scale": pa.array(res.scale[patch], pa.float32()),
                "rank": pa.array(np.tile(np.arange(k, dtype=np.int32), t), pa.int32()),
                "padded": pa.array(pad.reshape(-1), pa.bool_()),
            }))
        table = pa.concat_tables(parts)
        write_artifact(table, ctx.output("patches.parquet"), "patches",
                       metadata={"normalisation": "(p - seed) / scale"})
        info = {
            "n_seeds": t, "a": p.a, "n_radar": p.n_radar, "n_lidar": p.n_lidar,
            "radar_map_points": len(maps["radar"]), "radar_points_after_outlier_removal": len(radar),
            "radar_outliers_removed": int((~res.radar_inliers).sum()), "lidar_map_points": len(maps["lidar"]),
            "radar_padded_rows": int(res.radar_padded.sum()), "lidar_padded_rows": int(res.lidar_padded.sum()),
            "normalisation": "centre = seed (first radar point of the patch); scale = "
                             + (f"{p.norm_scale} m (fixed)" if p.norm_scale > 0 else
                                "largest distance of the radar patch's points from the seed")
                             + "; normalised = (p - centre) / scale",
            "scale_min": float(res.scale.min()), "scale_max": float(res.scale.max()),
            "radar_coverage": _coverage(radar, res.radar_idx),
            "lidar_coverage": _coverage(maps["lidar"], res.lidar_idx),
        }
        ctx.output("patches.json").write_text(json.dumps(info, indent=2) + "\n")
        ctx.stats.update({k: v for k, v in info.items() if k != "normalisation"})
        self._log(ctx, p, radar, maps["lidar"], res)

    @staticmethod
    def _log(ctx: StageContext, p: PatchesParams, radar: np.ndarray, lidar: np.ndarray, res: Patches) -> None:
        n = min(p.rerun_patches, len(res.seeds))
        if n == 0:
            return
        palette = (np.array([[230, 25, 75], [60, 180, 75], [255, 225, 25], [0, 130, 200], [245, 130, 48],
                             [145, 30, 180], [70, 240, 240], [240, 50, 230], [210, 245, 60], [250, 190, 212]],
                            np.uint8))
        for entity, pts, idx in (("world/patches", lidar, res.lidar_idx), ("world/patches/radar", radar,
                                                                           res.radar_idx)):
            sel = idx[:n]
            colors = np.repeat(palette[np.arange(n) % len(palette)], sel.shape[1], axis=0)
            ctx.recording.static_points(entity, pts[sel.reshape(-1)], colors=colors, radii=0.04)
        ctx.recording.static_points("world/patches/seeds", res.seeds, colors=[255, 255, 255], radii=0.15)


def _coverage(points: np.ndarray, idx: np.ndarray) -> float:
    """Share of map points that fall in at least one patch."""
    if len(points) == 0:
        return float("nan")
    hit = np.zeros(len(points), bool)
    hit[idx.reshape(-1)] = True
    return float(hit.mean())


STAGE = PatchesStage()
