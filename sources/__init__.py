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

from typing import Any

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

#: the completion model of real data: the voxel U-Net, trained on the real ColoRadar maps, is better than the
#: real-trained UpPoinTr on every Table III Overall metric of the 18 test scenes (docs/rmap.md); simulated
#: sequences keep the paper's UpPoinTr (the stage's own default; docs/radar_only.md, the twins)
_REAL_COMPLETION: dict[str, Any] = {"model": "voxel"}

#: parameters every sequence of a kind starts from (below the sequence's own ``params`` and ``--set``)
DEFAULT_PARAMS: dict[str, dict[str, dict[str, Any]]] = {
    # map sets enter at the voxel stage's outputs; only the map metrics can be computed
    "rmap": {"voxel": {"maps": "import"}, "evaluate": {"sections": ["rmap"]}, "complete": dict(_REAL_COMPLETION)},
    "coloradar": {"complete": dict(_REAL_COMPLETION)},
    "source": {"complete": dict(_REAL_COMPLETION)},
}


def provides(kind: str) -> frozenset[str]:
    """What data a sequence of ``kind`` provides (``log`` / ``maps``)."""
    return PROVIDES.get(kind, frozenset({"log"}))


def label(kind: str) -> str:
    return LABELS.get(kind, kind)
