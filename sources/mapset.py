"""Published map sets: the RMap authors' voxel maps of ColoRadar scenes (a source of kind ``rmap``).

Two layouts are read, both under ``$RMAP_ROOT`` or given with ``--source DIR``:

- ``authors``: a checkout of the authors' repository (arpg/RMap): ``data/ply/<scene>_{radar,lidar,
  lidar_filtered}.ply`` (ASCII PLY written by Open3D) and ``data/poses/<scene>.txt`` (thinned poses) and
  ``<scene>_all.txt`` (full trajectory), comma-separated x,y,z;
- ``folders``: one folder per scene, ``<scene>/{radar,lidar,lidar_filtered,poses,trajectory}.parquet``
  with float64 x, y, z (``../shared/data/coloradar_maps/``), an optional ``index.json`` beside the scene
  folders saying where each ``lidar_filtered`` came from (``map`` or rebuilt from published patches).

Ground truth is ``lidar_filtered``; ``lidar`` may be absent. Coordinates stay float64 as stored: the
paper-compatible F-score at d = 0.15 m decides neighbour ties on the stored values.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from core.errors import UserError
from sources.ply import read_ply_xyz

ROOT_VAR = "RMAP_ROOT"
F64 = npt.NDArray[np.float64]
Layout = Literal["authors", "folders"]

#: map files of a scene: name -> required
MAPS = {"radar": True, "lidar_filtered": True, "lidar": False}
POSES = {"poses": True, "trajectory": True}
_HINT = ("point RMAP_ROOT at a checkout of github.com/arpg/RMap (data/ply, data/poses) or at a folder of "
         "<scene>/{radar,lidar_filtered,poses,trajectory}.parquet, or use --source DIR")


@dataclass(frozen=True)
class MapSet:
    """One scene's maps and trajectories (world frame of the run, float64)."""

    scene: str
    layout: Layout
    root: Path
    radar: F64
    lidar_filtered: F64
    poses: F64
    trajectory: F64
    lidar: F64 | None = None
    #: where ``lidar_filtered`` came from: ``map`` (the authors' map file) or ``rebuilt`` (union of patches)
    lidar_filtered_source: str = "map"
    #: the index entry's text for the source (e.g. "union of 381 published gt patches")
    source_detail: str = ""
    environment: str = ""
    split: str = ""
    files: dict[str, Path] = field(default_factory=dict)


# -- index.json: the one reader ---------------------------------------------------------------------------------
#: the map set's index beside the scene folders (folders layout): scene -> split, environment, sources
INDEX_FILE = "index.json"


def read_index_file(path: Path) -> dict[str, dict[str, Any]]:
    """The scene -> entry mapping of a map set's ``index.json``, as stored.

    Every problem is a one-line :class:`UserError` naming the file: unreadable, not JSON, not an object of
    objects.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        why = " ".join(str(exc).split())
        raise UserError(f"{path}: unreadable map-set index ({why}); restore it from the map set") from exc
    if not isinstance(doc, dict):
        raise UserError(f"{path}: not a map-set index (a JSON object of scene -> split, environment, "
                        f"lidar_filtered; got {type(doc).__name__}); restore it from the map set")
    bad = [str(k) for k, v in doc.items() if not isinstance(v, dict)]
    if bad:
        raise UserError(f"{path}: scene {bad[0]!r} is not an object (split, environment, lidar_filtered); restore "
                        "the index from the map set")
    return doc


def lidar_filtered_source(entry: dict[str, Any]) -> str:
    """Where an index entry says the scene's ``lidar_filtered`` came from: ``map`` (the authors' map file,
    the default) or the entry's text for a stand-in (e.g. "union of 381 published gt patches")."""
    lf = entry.get("lidar_filtered", {})
    return str(lf.get("source", "map")) if isinstance(lf, dict) else "map"


def rebuilt_scenes(index: dict[str, dict[str, Any]]) -> set[str]:
    """Scenes of an index whose ``lidar_filtered`` was rebuilt (a source other than ``map``)."""
    return {s for s, v in index.items() if lidar_filtered_source(v) != "map"}


@dataclass(frozen=True)
class SceneInfo:
    name: str
    environment: str
    split: str
    #: how the ground-truth map was made ("map" or the stand-in rebuilt from published patches)
    gt_source: str


def read_index(root: str | Path) -> dict[str, SceneInfo]:
    """The scenes of a map set (``--maps``) that have radar and lidar_filtered files, by name (sorted).

    Unlike :func:`read_map_set`, which reads one scene, this needs the index and a split and environment
    for every scene in it (training and the Table III script choose scenes by them).
    """
    root = Path(root)
    index = root / INDEX_FILE
    if not root.is_dir():
        raise UserError(f"--maps {root}: not a folder; point it at a map set such as ../shared/data/coloradar_maps")
    if not index.is_file():
        raise UserError(f"--maps {root}: no {INDEX_FILE} (scene -> split and environment); is this a map set?")
    raw = read_index_file(index)
    out: dict[str, SceneInfo] = {}
    for name, v in sorted(raw.items()):
        if "split" not in v or "environment" not in v:
            raise UserError(f"{index}: scene {name!r} has no split or environment")
        if (root / name / "radar.parquet").is_file() and (root / name / "lidar_filtered.parquet").is_file():
            out[name] = SceneInfo(name, str(v["environment"]), str(v["split"]), lidar_filtered_source(v))
    if not out:
        raise UserError(f"--maps {root}: no scene with radar.parquet and lidar_filtered.parquet")
    return out


def scene_files(root: Path, scene: str, layout: Layout) -> dict[str, Path]:
    """Paths of every file of ``scene`` in ``layout`` (whether they exist or not)."""
    if layout == "authors":
        ply, poses = root / "data" / "ply", root / "data" / "poses"
        out = {k: ply / f"{scene}_{k}.ply" for k in MAPS}
        out["poses"] = poses / f"{scene}.txt"
        out["trajectory"] = poses / f"{scene}_all.txt"
        return out
    d = root if root.name == scene and (root / "radar.parquet").exists() else root / scene
    return {k: d / f"{k}.parquet" for k in (*MAPS, *POSES)}


def detect_layout(root: Path, scene: str) -> Layout | None:
    """The layout under which ``root`` holds ``scene``'s radar map, or None."""
    for layout in ("authors", "folders"):
        if scene_files(root, scene, layout)["radar"].is_file():
            return layout
    return None


def scenes_in(root: Path) -> list[str]:
    """Scenes found in ``root`` in either layout (a single scene folder counts as one)."""
    found: list[str] = []
    ply = root / "data" / "ply"
    if ply.is_dir():
        found += sorted(p.name.removesuffix("_radar.ply") for p in ply.glob("*_radar.ply"))
    if (root / "radar.parquet").is_file():
        found.append(root.name)
    elif root.is_dir():
        found += sorted(p.name for p in root.iterdir() if (p / "radar.parquet").is_file())
    return list(dict.fromkeys(found))


def locations(scene: str) -> list[Path]:
    """Where ``scene`` is looked for under ``$RMAP_ROOT`` (the radar map file of each layout)."""
    root = os.environ.get(ROOT_VAR)
    if not root:
        return []
    return [scene_files(Path(root), scene, lay)["radar"] for lay in ("authors", "folders")]


def root_for(scene: str) -> Path:
    """``$RMAP_ROOT`` checked: set, a folder, and holding ``scene`` in one of the layouts."""
    value = os.environ.get(ROOT_VAR)
    if not value:
        raise UserError(f"{ROOT_VAR} is not set (needed for map sequence 'rmap_{scene}'); {_HINT}")
    root = Path(value).expanduser()
    if not root.is_dir():
        raise UserError(f"{ROOT_VAR}={value}: no such folder; {_HINT}")
    if detect_layout(root, scene) is None:
        tried = " or ".join(str(p) for p in locations(scene))
        present = scenes_in(root)
        has = f" (it holds {len(present)} other scene(s), e.g. {', '.join(present[:3])})" if present else \
            " (it holds no scene in either layout)"
        raise UserError(f"{ROOT_VAR}={value}: no maps of scene '{scene}' (looked for {tried}){has}; {_HINT}")
    return root


def read_map_set(root: Path, scene: str) -> MapSet:
    """Read ``scene`` from ``root`` (either layout). Every problem is a one-line :class:`UserError`."""
    layout = detect_layout(root, scene)
    if layout is None:
        raise UserError(f"{root}: no maps of scene '{scene}' (looked for "
                        f"{scene_files(root, scene, 'authors')['radar']} and "
                        f"{scene_files(root, scene, 'folders')['radar']}); {_HINT}")
    files = scene_files(root, scene, layout)
    required = {**MAPS, **POSES}
    missing = [k for k, need in required.items() if need and not files[k].is_file()]
    if missing:
        names = ", ".join(str(files[k]) for k in missing)
        raise UserError(f"{names}: missing from scene '{scene}' ({layout} layout); copy the complete scene "
                        f"({', '.join(str(files[k].name) for k, n in required.items() if n)})")
    arrays: dict[str, F64 | None] = {}
    for k in MAPS:
        if not files[k].is_file():
            arrays[k] = None
            continue
        pts = _read_points(files[k], f"{k} map", layout)
        if len(pts) == 0:
            raise UserError(f"{files[k]}: the {k} map of scene '{scene}' is empty; download the file again")
        arrays[k] = pts
    for k in POSES:
        pts = _read_poses(files[k], layout) if layout == "authors" else _read_points(files[k], k, layout)
        if len(pts) == 0:
            raise UserError(f"{files[k]}: no {k} in scene '{scene}'; download the file again")
        arrays[k] = pts
    meta = _index_entry(root, scene, layout)
    lf = lidar_filtered_source(meta)
    radar, lidar_f, poses, traj = (arrays[k] for k in ("radar", "lidar_filtered", "poses", "trajectory"))
    assert radar is not None and lidar_f is not None and poses is not None and traj is not None
    return MapSet(scene=scene, layout=layout, root=root, radar=radar, lidar_filtered=lidar_f, poses=poses,
                  trajectory=traj, lidar=arrays["lidar"], lidar_filtered_source="map" if lf == "map" else "rebuilt",
                  source_detail=str(lf), environment=str(meta.get("environment", "")),
                  split=str(meta.get("split", "")), files={k: v for k, v in files.items() if v.is_file()})


def _read_points(path: Path, what: str, layout: Layout) -> F64:
    if layout == "authors":
        pts = read_ply_xyz(path, what)
    else:
        pts = _read_parquet_xyz(path, what)
    if not np.isfinite(pts).all():
        raise UserError(f"{path}: the {what} holds non-finite coordinates; download the file again")
    return pts


def _read_parquet_xyz(path: Path, what: str) -> F64:
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        table = pq.read_table(path)
    except (pa.ArrowInvalid, OSError) as exc:
        raise UserError(f"{path}: unreadable Parquet {what} ({exc}); the file is truncated or corrupt: copy it "
                        "again") from exc
    missing = [c for c in ("x", "y", "z") if c not in table.column_names]
    if missing:
        raise UserError(f"{path}: the {what} lacks column(s) {', '.join(missing)} (has: "
                        f"{', '.join(table.column_names) or 'none'}); expected float64 x, y, z")
    types = {c: table.schema.field(c).type for c in ("x", "y", "z")}
    if any(t != pa.float64() for t in types.values()):
        raise UserError(f"{path}: the {what}'s x, y, z must be float64 as published (got "
                        f"{', '.join(str(t) for t in types.values())}); lower precision changes the F-score")
    if any(table.column(c).null_count for c in ("x", "y", "z")):
        raise UserError(f"{path}: the {what} holds null coordinates")
    return np.stack([table.column(c).to_numpy() for c in ("x", "y", "z")], axis=1).astype(np.float64, copy=False)


def _read_poses(path: Path, layout: Layout) -> F64:
    """Comma-separated x,y,z per line (the authors' ``data/poses/*.txt``)."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: unreadable poses file ({exc})") from exc
    rows = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not rows:
        return np.zeros((0, 3))
    for i, ln in enumerate(text.splitlines(), 1):
        n = len(ln.split(",")) if ln.strip() and not ln.lstrip().startswith("#") else 3
        if n != 3:
            raise UserError(f"{path}: line {i} has {n} comma-separated columns, expected 3 (x,y,z); restore the "
                            "authors' file")
    try:
        out = np.array([[float(v) for v in ln.split(",")] for ln in rows], dtype=np.float64)
    except ValueError as exc:
        raise UserError(f"{path}: not numeric x,y,z ({exc}); restore the authors' file") from exc
    if not np.isfinite(out).all():
        raise UserError(f"{path}: non-finite pose coordinates; restore the authors' file")
    return out


def _index_entry(root: Path, scene: str, layout: Layout) -> dict[str, Any]:
    """The scene's entry of ``index.json`` (folders layout), or {} (no index, or the scene not in it)."""
    if layout != "folders":
        return {}
    path = scene_files(root, scene, layout)["radar"].parent.parent / INDEX_FILE
    if not path.is_file():
        return {}
    return read_index_file(path).get(scene, {})


def fingerprint(root: Path, scene: str) -> dict[str, Any]:
    """Cache-key identity of a scene's files: names, sizes, mtimes (not a content hash)."""
    layout = detect_layout(root, scene)
    if layout is None:
        return {"missing": str(root), "scene": scene}
    files = scene_files(root, scene, layout)
    out: dict[str, Any] = {"layout": layout, "scene": scene}
    for k, p in files.items():
        if p.is_file():
            st = p.stat()
            out[k] = f"{p}:{st.st_size}:{st.st_mtime_ns}"
    index = files["radar"].parent.parent / INDEX_FILE if layout == "folders" else None
    if index is not None and index.is_file():
        st = index.stat()
        out["index"] = f"{st.st_size}:{st.st_mtime_ns}"
    return out
