"""`voxel` stage: radar and lidar OctoMap-style voxel maps (RMap Sec. III-A)."""

from __future__ import annotations

from pipeline.errors import UserError
from pipeline.stage import Stage, StageContext, StageParams


class VoxelParams(StageParams):
    """Parameters of the `voxel` stage."""


class VoxelStage(Stage):
    name = "voxel"
    description = "radar and lidar OctoMap-style voxel maps (RMap Sec. III-A)"
    inputs = ('ingest',)
    Params = VoxelParams
    outputs = ('radar_map.parquet', 'lidar_map.parquet')
    implemented = False

    def run(self, ctx: StageContext) -> None:
        raise UserError("stage 'voxel' is not implemented yet")


STAGE = VoxelStage()
