"""The `plan` stage: A* plus continuous refinement on the Hilbert map (RICH-SLAM Sec. V-D)."""
