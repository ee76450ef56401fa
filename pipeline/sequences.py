"""The sequence registry (``data/sequences.toml``) and where each sequence's data is found.

Kinds (the source layer in ``sources/`` does the locating and reading for each):
- ``simulated``: built-in worlds, generated on first use into the data cache by the simulator and then
  ingested through the same readers as real data (:mod:`sources.simulated`);
- ``coloradar``: a ColoRadar run looked up under ``$COLORADAR_ROOT`` (bag or extracted folder,
  :mod:`sources.recorded`);
- ``source``: an ad-hoc log given with ``--source``;
- ``rmap``: a published map set (the RMap authors' voxel maps of one scene) under ``$RMAP_ROOT`` or given
  with ``--source DIR`` (:mod:`sources.mapset`); it enters the DAG at the voxel stage's outputs.
"""

from __future__ import annotations

import fnmatch
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomllib

import sources
from core.errors import UserError
from core.paths import data_dir
from core.stage import flatten_params
from sources import mapset, recorded, simulated

KINDS = tuple(sources.PROVIDES)


@dataclass(frozen=True)
class SequenceInfo:
    name: str
    kind: str
    dataset: str = "coloradar"
    description: str = ""
    #: ColoRadar run name (``12_21_2020_ec_hallways_run0``)
    run: str | None = None
    #: simulated sequences
    world: str | None = None
    duration: float = 60.0
    seed: int = 0
    format: str = "bag"
    #: map sets: the scene (``arpg_lab_run0``), its environment and RMap split (``test`` / ``train``)
    scene: str | None = None
    environment: str = ""
    split: str = ""
    #: twins: a variant of the twin's sensor model, ``data/twins/<twin>.toml`` (``drift``); None: the defaults
    twin: str | None = None
    #: explicit source path (``--source``)
    source: Path | None = None
    params: dict[str, dict[str, Any]] = field(default_factory=dict)

    # -- what the source provides -----------------------------------------------------------------------
    @property
    def provides(self) -> frozenset[str]:
        """``{"log"}`` (sensor streams for ingest) or ``{"maps"}`` (voxel maps, the voxel stage's outputs)."""
        return sources.provides(self.kind)

    @property
    def kind_label(self) -> str:
        return sources.label(self.kind)

    # -- locating data ----------------------------------------------------------------------------------
    def expected_locations(self) -> list[Path]:
        """Where the data is looked for, in order."""
        if self.kind == "rmap":
            if self.source is not None:
                return [self.source]
            return mapset.locations(self.scene or self.name)
        if self.kind == "source":
            assert self.source is not None
            return [self.source]
        if self.kind == "simulated":
            return [self.simulated_path()]
        return recorded.coloradar_locations(self.run)

    def locate(self) -> Path | None:
        """The first existing data location, or None."""
        if self.kind == "rmap":
            root = self.map_root_or_none()
            return root
        return next((p for p in self.expected_locations() if p.exists()), None)

    def where(self) -> str:
        """Where the data is (or is expected), for listings."""
        found = self.locate()
        if found is not None and self.kind == "rmap":
            scene = self.scene or self.name
            layout = mapset.detect_layout(found, scene)
            return str(mapset.scene_files(found, scene, layout)["radar"]) if layout else str(found)
        if found is not None:
            return str(found)
        expected = self.expected_locations()
        if expected:
            return str(expected[0])
        if self.kind == "rmap":
            return f"${mapset.ROOT_VAR}/data/ply/{self.scene}_radar.ply or ${mapset.ROOT_VAR}/{self.scene}/"
        return f"${recorded.ROOT_VAR}/{self.run or ''}"

    def simulated_path(self) -> Path:
        return simulated.simulated_path(self.name, self.world, self.duration, self.seed, self.format, self.scene,
                                        self.twin)

    def map_root_or_none(self) -> Path | None:
        """The folder holding this map sequence's scene (either layout), or None."""
        scene = self.scene or self.name
        if self.source is not None:
            return self.source if mapset.detect_layout(self.source, scene) else None
        value = os.environ.get(mapset.ROOT_VAR)
        if not value:
            return None
        root = Path(value).expanduser()
        return root if root.is_dir() and mapset.detect_layout(root, scene) else None

    def map_root(self) -> Path:
        """The folder holding this map sequence's scene; a one-line error naming what to set otherwise."""
        scene = self.scene or self.name
        if self.source is not None:
            if mapset.detect_layout(self.source, scene) is None:
                raise UserError(f"--source {self.source}: no maps of scene '{scene}' in either layout")
            return self.source
        return mapset.root_for(scene)

    def resolve_source(self, generate: bool = True) -> Path:
        """Path of the sequence data, generating a simulated sequence on first use."""
        if self.kind == "rmap":
            return self.map_root()
        found = self.locate()
        if found is not None:
            return found
        if self.kind == "simulated" and generate:
            return simulated.generate(self)
        if self.kind == "coloradar":
            raise recorded.missing_log_error(self.name, self.run, self.expected_locations())
        raise UserError(f"sequence '{self.name}': source {self.expected_locations()[0]} does not exist")


def _registry_path() -> Path:
    return data_dir() / "sequences.toml"


def load_registry(path: Path | None = None) -> dict[str, SequenceInfo]:
    path = path or _registry_path()
    try:
        with path.open("rb") as f:
            doc = tomllib.load(f)
    except FileNotFoundError:
        raise UserError(f"{path}: sequence registry not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: invalid TOML ({exc})") from exc
    out = {}
    allowed = set(SequenceInfo.__dataclass_fields__) - {"name", "source"}
    for name, table in doc.items():
        unknown = set(table) - allowed
        if unknown:
            raise UserError(
                f"{path}: sequence '{name}' has unknown keys {sorted(unknown)} (allowed: {sorted(allowed)})"
            )
        kind = table.get("kind")
        if kind not in KINDS:
            raise UserError(f"{path}: sequence '{name}' has kind {kind!r}; use one of {', '.join(KINDS)}")
        if kind == "rmap" and not table.get("scene"):
            raise UserError(f"{path}: map sequence '{name}' needs scene = \"<scene>\" (e.g. arpg_lab_run0)")
        table["params"] = {stage: flatten_params(values) for stage, values in table.get("params", {}).items()}
        out[name] = SequenceInfo(name=name, **table)
    return out


def kind_defaults(kind: str, path: Path | None = None) -> dict[str, dict[str, Any]]:
    """Parameters every sequence of ``kind`` starts from (``data/kinds.toml``); the runner layers them above the
    workflow's and below the sequence's own ``params`` and ``--set``."""
    path = path or data_dir() / "kinds.toml"
    try:
        with path.open("rb") as f:
            table = tomllib.load(f)
    except FileNotFoundError:
        return {}
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: not valid TOML ({exc}); fix the file") from None
    return {stage: flatten_params(values) for stage, values in table.get(kind, {}).items()}


def get_sequence(name: str, registry: dict[str, SequenceInfo] | None = None) -> SequenceInfo:
    import difflib  # not pipeline.config.did_you_mean: config imports the stage contract, which names this module

    registry = registry if registry is not None else load_registry()
    if name not in registry:
        close = difflib.get_close_matches(name, list(registry), n=1, cutoff=0.5)
        hint = f"; did you mean '{close[0]}'?" if close else ""
        raise UserError(
            f"unknown sequence '{name}'{hint} (see `pipeline sequences`, "
            f"or pass --source PATH for unregistered data)"
        )
    return registry[name]


def seq_spec(values: Sequence[str] | None) -> str | None:
    """Repeated ``--seq`` options as one sequence spec (``a,b``); None when none was given."""
    return ",".join(values) if values else None


def expand_sequences(pattern: str, registry: dict[str, SequenceInfo] | None = None) -> list[SequenceInfo]:
    """Expand a comma-separated list of names and globs (``coloradar_*``) into registered sequences."""
    registry = registry if registry is not None else load_registry()
    out: list[SequenceInfo] = []
    for part in [p.strip() for p in pattern.split(",") if p.strip()]:
        if any(c in part for c in "*?["):
            matched = [registry[n] for n in registry if fnmatch.fnmatchcase(n, part)]
            if not matched:
                raise UserError(f"--seq '{part}' matches no registered sequence (see `pipeline sequences`)")
            out += matched
        else:
            out.append(get_sequence(part, registry))
    seen: set[str] = set()
    return [s for s in out if not (s.name in seen or seen.add(s.name))]  # type: ignore[func-returns-value]


def source_sequence(path: Path, name: str | None, dataset: str) -> SequenceInfo:
    """An unregistered sequence from ``--source PATH``: a log, or one scene of a map set (either layout)."""
    if not path.exists():
        raise UserError(f"--source {path}: no such file or folder")
    path = path.resolve()
    scenes = mapset.scenes_in(path) if path.is_dir() else []
    if scenes:
        wanted = name.removeprefix("rmap_") if name else None
        if wanted is not None and wanted in scenes:
            scene = wanted
        elif len(scenes) == 1:
            scene = scenes[0]
        else:
            raise UserError(f"--source {path}: holds {len(scenes)} map scenes ({', '.join(scenes[:4])}, ...); "
                            f"name one with --seq rmap_<scene>")
        return SequenceInfo(name=name or f"rmap_{scene}", kind="rmap", scene=scene, source=path)
    return SequenceInfo(name=name or recorded.log_stem(path), kind="source", dataset=dataset, source=path)


def source_fingerprint(path: Path) -> dict[str, Any]:
    """Cheap identity of a data source for cache keys (see :func:`sources.recorded.fingerprint`)."""
    return recorded.fingerprint(path)
