"""Discovery of the pipeline's stages (``stages/<name>/stage.py`` exporting ``STAGE``)."""

from __future__ import annotations

import importlib
from functools import cache

from core.errors import UserError
from core.stage import Stage, StageReport

#: The stages in dependency order.
STAGE_NAMES = ("ingest", "filter", "odometry", "slam", "voxel", "patches", "complete", "evaluate", "plan")


@cache
def load_stages() -> dict[str, Stage]:
    """Import every stage module and return ``{name: stage}`` in pipeline order."""
    out: dict[str, Stage] = {}
    for name in STAGE_NAMES:
        module = importlib.import_module(f"stages.{name}.stage")
        stage: Stage = module.STAGE
        if stage.name != name:
            raise RuntimeError(f"stages/{name}/stage.py exports a stage named {stage.name!r}")
        out[name] = stage
    return out


def stage_report(stage: str = "evaluate") -> StageReport:
    """The report hook of ``stage`` (:meth:`core.stage.Stage.report`): tables and figures over many runs."""
    rep = load_stages()[stage].report()
    if rep is None:
        raise UserError(f"stage '{stage}' has no report")
    return rep
