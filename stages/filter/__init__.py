"""The `filter` stage: Doppler ego-velocity and multi-frame radar point filtering (RICH-SLAM Sec. IV-B)."""
