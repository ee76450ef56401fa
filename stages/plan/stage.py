"""`plan` stage: A* plus continuous refinement on the Hilbert map (RICH-SLAM Sec. V-D)."""

from __future__ import annotations

from pipeline.errors import UserError
from pipeline.stage import Stage, StageContext, StageParams


class PlanParams(StageParams):
    """Parameters of the `plan` stage."""


class PlanStage(Stage):
    name = "plan"
    description = "A* plus continuous refinement on the Hilbert map (RICH-SLAM Sec. V-D)"
    inputs = ('slam',)
    Params = PlanParams
    outputs = ('paths.parquet',)
    implemented = False

    def run(self, ctx: StageContext) -> None:
        raise UserError("stage 'plan' is not implemented yet")


STAGE = PlanStage()
