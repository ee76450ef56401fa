"""`complete` stage: point-cloud completion of the radar map (RMap Sec. III-D)."""

from __future__ import annotations

from pipeline.errors import UserError
from pipeline.stage import Stage, StageContext, StageParams


class CompleteParams(StageParams):
    """Parameters of the `complete` stage."""


class CompleteStage(Stage):
    name = "complete"
    description = "point-cloud completion of the radar map (RMap Sec. III-D)"
    inputs = ('patches',)
    Params = CompleteParams
    outputs = ('completed_map.parquet',)
    implemented = False

    def run(self, ctx: StageContext) -> None:
        raise UserError("stage 'complete' is not implemented yet")


STAGE = CompleteStage()
