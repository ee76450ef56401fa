"""A registered or ad-hoc sequence: what it is (kind, world, scene, run) and where its data is found.

The record every stage receives; the registry that builds it from ``data/sequences.toml`` is
:mod:`pipeline.sequences`. Each kind's data is located and read by its module here (:mod:`sources.simulated`,
:mod:`sources.recorded`, :mod:`sources.mapset`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import sources
from core.errors import UserError
from sources import mapset, recorded, simulated


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
