"""`patches` stage: FPS patches of the radar and lidar maps (RMap Algorithm 1)."""

from __future__ import annotations

from pipeline.errors import UserError
from pipeline.stage import Stage, StageContext, StageParams


class PatchesParams(StageParams):
    """Parameters of the `patches` stage."""


class PatchesStage(Stage):
    name = "patches"
    description = "FPS patches of the radar and lidar maps (RMap Algorithm 1)"
    inputs = ('voxel',)
    Params = PatchesParams
    outputs = ('patches.parquet',)
    implemented = False

    def run(self, ctx: StageContext) -> None:
        raise UserError("stage 'patches' is not implemented yet")


STAGE = PatchesStage()
