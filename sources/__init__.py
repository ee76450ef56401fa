"""Where a sequence's data comes from: one module per kind of source.

- :mod:`sources.recorded`: a recorded log (ROS1 bag, MCAP, extracted folder) under ``$COLORADAR_ROOT`` or
  given with ``--source``;
- :mod:`sources.simulated`: a built-in world, simulated on first use into the data cache;
- :mod:`sources.mapset`: a published map set (the RMap authors' voxel maps) under ``$RMAP_ROOT`` or given
  with ``--source``.

The sequence registry (:mod:`pipeline.sequences`) dispatches on the kind. Each kind *provides* data of
one sort: ``log`` (sensor streams for ingest) or ``maps`` (voxel maps that enter the DAG at the voxel
stage's outputs). Stages declare what they need (:attr:`core.stage.Stage.needs`); the runner skips
those whose needs the source does not provide. This package imports nothing from the orchestration
layer but :mod:`core.errors` and :mod:`core.paths`.
"""

from __future__ import annotations

#: sequence kinds and what their data provides
PROVIDES: dict[str, frozenset[str]] = {
    "simulated": frozenset({"log"}),
    "coloradar": frozenset({"log"}),
    "source": frozenset({"log"}),
    "rmap": frozenset({"maps"}),
}

#: how each kind is named in messages
LABELS: dict[str, str] = {
    "simulated": "simulated log",
    "coloradar": "recorded log",
    "source": "recorded log",
    "rmap": "published map set",
}

def provides(kind: str) -> frozenset[str]:
    """What data a sequence of ``kind`` provides (``log`` / ``maps``)."""
    return PROVIDES.get(kind, frozenset({"log"}))


def label(kind: str) -> str:
    return LABELS.get(kind, kind)
