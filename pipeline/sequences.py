"""The sequence registry (``data/sequences.toml``) and where each sequence's data is found.

Kinds:
- ``simulated``: built-in worlds, generated on first use into the data cache by the simulator and then
  ingested through the same readers as real data;
- ``coloradar``: a ColoRadar run looked up under ``$COLORADAR_ROOT`` (bag or extracted folder);
- ``source``: an ad-hoc path given with ``--source``.
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomllib

from pipeline.errors import UserError
from pipeline.paths import cache_dir, data_dir


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
    #: explicit source path (``--source``)
    source: Path | None = None
    params: dict[str, dict[str, Any]] = field(default_factory=dict)

    # -- locating data ----------------------------------------------------------------------------------
    def expected_locations(self) -> list[Path]:
        """Where the data is looked for, in order."""
        if self.kind == "source":
            assert self.source is not None
            return [self.source]
        if self.kind == "simulated":
            return [self.simulated_path()]
        root = os.environ.get("COLORADAR_ROOT")
        if not root or self.run is None:
            return []
        short = self.run.split("_", 3)[-1] if self.run[:1].isdigit() else self.run
        base = Path(root)
        names = dict.fromkeys([self.run, short])
        out: list[Path] = []
        for n in names:
            out += [base / f"{n}.bag", base / n, base / "bags" / f"{n}.bag", base / f"{n}.mcap"]
        return out

    def locate(self) -> Path | None:
        """The first existing data location, or None."""
        return next((p for p in self.expected_locations() if p.exists()), None)

    def simulated_path(self) -> Path:
        spec = json.dumps(
            {"world": self.world, "duration": self.duration, "seed": self.seed, "format": self.format,
             **_simulator_fingerprint(self.world or self.name)},
            sort_keys=True,
        )
        digest = hashlib.sha256(spec.encode()).hexdigest()[:10]
        suffix = ".bag" if self.format == "bag" else ""
        return cache_dir() / "sequences" / f"{self.name}-{digest}" / f"{self.name}{suffix}"

    def resolve_source(self, generate: bool = True) -> Path:
        """Path of the sequence data, generating a simulated sequence on first use."""
        found = self.locate()
        if found is not None:
            return found
        if self.kind == "simulated" and generate:
            from simulator import generate_sequence

            return generate_sequence(self)
        if self.kind == "coloradar":
            if not os.environ.get("COLORADAR_ROOT"):
                raise UserError(
                    f"sequence '{self.name}' ({self.run}): COLORADAR_ROOT is not set; point it at the folder "
                    f"holding the ColoRadar bags or extracted runs, or use --source PATH"
                )
            tried = ", ".join(str(p) for p in self.expected_locations()[:2])
            raise UserError(f"sequence '{self.name}': no data found (looked for {tried}, ...); "
                            f"download {self.run} or use --source PATH")
        raise UserError(f"sequence '{self.name}': source {self.expected_locations()[0]} does not exist")


def _simulator_fingerprint(world: str) -> dict[str, str]:
    """Simulator code and world-file hashes, so a changed simulator or world regenerates the sequence."""
    try:
        from simulator import cache_fingerprint
    except ImportError:
        return {}
    return cache_fingerprint(world)


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
        out[name] = SequenceInfo(name=name, **table)
    return out


def get_sequence(name: str, registry: dict[str, SequenceInfo] | None = None) -> SequenceInfo:
    from pipeline.config import did_you_mean

    registry = registry if registry is not None else load_registry()
    if name not in registry:
        raise UserError(
            f"unknown sequence '{name}'{did_you_mean(name, registry)} (see `pipeline sequences`, "
            f"or pass --source PATH for unregistered data)"
        )
    return registry[name]


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
    """An unregistered sequence from ``--source PATH``."""
    if not path.exists():
        raise UserError(f"--source {path}: no such file or folder")
    stem = path.name.removesuffix(".bag").removesuffix(".mcap").removesuffix(".db3") or "source"
    return SequenceInfo(name=name or stem, kind="source", dataset=dataset, source=path.resolve())


def source_fingerprint(path: Path) -> dict[str, Any]:
    """Cheap identity of a data source for cache keys: path, sizes and mtimes (not a content hash)."""
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    h = hashlib.sha256()
    total = 0
    for f in files:
        st = f.stat()
        total += st.st_size
        h.update(f"{f.relative_to(path) if path.is_dir() else f.name}:{st.st_size}:{st.st_mtime_ns}".encode())
    return {"path": str(path), "bytes": total, "files": len(files), "digest": h.hexdigest()[:16]}
