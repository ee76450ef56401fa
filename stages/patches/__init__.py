"""The `patches` stage: FPS patches of the radar and lidar maps (RMap Algorithm 1)."""
