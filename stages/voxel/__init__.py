"""The `voxel` stage: radar and lidar OctoMap-style voxel maps (RMap Sec. III-A)."""
