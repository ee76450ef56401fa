"""Published map sets as training and evaluation data for the completion network (RMap Sec. III-C, IV).

A map set is a folder laid out like ``shared/data/coloradar_maps``: ``<root>/<scene>/radar.parquet`` and
``<root>/<scene>/lidar_filtered.parquet`` (columns x, y, z, float64) and ``<root>/index.json`` giving each
scene's ``split`` (``test`` = RMap Table III, ``train`` = the rest) and ``environment``, read by
:func:`sources.mapset.read_index` (the one reader of ``index.json``). Ground truth is
``lidar_filtered`` (the shared README: it reproduces the paper's tables). :func:`read_scene` is the one
place that reads a scene, so that it can be swapped for the project's map-sequence source layer.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from core.errors import UserError
from sources.mapset import SceneInfo
from stages.complete.data import F64, Patch


def validation_scenes(scenes: dict[str, SceneInfo]) -> list[str]:
    """The validation part of the train scenes, fixed before training: in every environment the train
    scene with the highest run number (never a test scene)."""
    by_env: dict[str, list[tuple[int, str]]] = {}
    for s in scenes.values():
        if s.split == "train":
            run = s.name.rsplit("_run", 1)[-1]
            by_env.setdefault(s.environment, []).append((int(run) if run.isdigit() else -1, s.name))
    return sorted(max(v)[1] for v in by_env.values())


@dataclass(frozen=True)
class MapSplit:
    """Scenes for training, for validation (a part of RMap's train scenes) and RMap's test scenes."""

    train: list[str]
    val: list[str]
    test: list[str]


def map_split(scenes: dict[str, SceneInfo], val: Sequence[str] | None = None) -> MapSplit:
    """RMap's split with a validation part taken out of the train scenes (default :func:`validation_scenes`)."""
    val = list(val) if val is not None else validation_scenes(scenes)
    bad = [v for v in val if v not in scenes or scenes[v].split != "train"]
    if bad:
        raise UserError(f"validation scenes {bad}: not train scenes of the map set (test scenes are never used "
                        "for choices)")
    train = [s.name for s in scenes.values() if s.split == "train" and s.name not in val]
    test = [s.name for s in scenes.values() if s.split == "test"]
    return MapSplit(train, sorted(val), test)


def read_scene(root: str | Path, scene: str) -> tuple[F64, F64]:
    """(radar map, ground-truth lidar_filtered map) of one scene, float64 ``(N, 3)``, in either layout.

    The map-set reader of the sources layer (:func:`sources.mapset.read_map_set`): the values as stored, and
    every problem a one-line error naming the file.
    """
    from sources.mapset import read_map_set

    m = read_map_set(Path(root), scene)
    return m.radar, m.lidar_filtered


def scene_patches(radar: F64, lidar: F64, scene: str, a: float, seed: int = 0) -> list[Patch]:
    """Algorithm 1's patch pairs of one scene (the `patches` stage's defaults: 2048 radar, 8192 lidar points)."""
    from core.fps_patches import make_patches  # fpsample: only patch users need it (not the voxel model)

    res = make_patches(radar, lidar, a=a, seed=seed)
    rad = radar[res.radar_inliers]
    return [Patch(scene, i, res.seeds[i], rad[res.radar_idx[i]], lidar[res.lidar_idx[i]])
            for i in range(len(res.seeds))]
