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
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import tomllib

import sources
from core.errors import UserError
from core.paths import data_dir
from core.stage import flatten_params
from sources import mapset, recorded
from sources.sequence import SequenceInfo

KINDS = tuple(sources.PROVIDES)


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
