"""The shared layer below the stages: errors and paths, the stage framework and its recordings, and the
algorithms more than one stage uses (SE(2)/SE(3) geometry, the Hilbert-GP map and its field, trajectory and map
metrics, farthest-point patches, the RMap paper's published tables). It imports nothing of the project above it.
"""
