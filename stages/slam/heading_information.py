"""How much heading a filter's scan weight holds: its Fisher information in yaw, scan by scan, along a path.

A map is built along ``poses`` (the odometry) from the scans before scan ``k``; scan ``k`` is scored at the pose
turned by ``-delta``, ``0`` and ``+delta``, and the curvature of the log-likelihood there,
``I_k = -(L(+delta) + L(-delta) - 2 L(0)) / delta^2`` (rad^-2, floored at 0), is the information one scan gives
the filter's selection about its heading. Its inverse square root is the heading spread one scan can resolve:
RICH-SLAM's Hilbert weight has 12-400 rad^-2 on the project's sequences (3-16 deg per scan), the grid's likelihood
field 400-4,700 (stages/slam/README.md, stop 47). The fused estimate widens its model of the filter's heading
error where this is low (:func:`heading_fusion.informed`).

Pure numpy on any :class:`rbpf.ParticleMaps` of three particles (the caller builds them: the method's own map
model), so every weight is measured the way its filter scores scans.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from stages.slam.beam_sampling import BeamSamples
from stages.slam.rbpf import ParticleMaps
from stages.slam.se2 import compose

F64 = npt.NDArray[np.floating[Any]]

#: the yaw step of the finite difference (rad): inside the weight's main lobe, above its numerical noise
DELTA = math.radians(2.0)


def yaw_information(maps: ParticleMaps, poses: npt.ArrayLike, scans: Sequence[BeamSamples],
                    delta: float = DELTA) -> F64:
    """Per-scan yaw Fisher information ``(T,)`` of ``maps``' weight along ``poses (T, 3)``; ``maps`` holds three
    particles and nothing yet (each is updated at the same pose). Scan 0 (no map before it) and empty scans: 0."""
    p = np.asarray(poses, np.float64).reshape(-1, 3)
    if len(p) != len(scans):
        raise ValueError(f"yaw_information: {len(p)} poses for {len(scans)} scans")
    if not delta > 0:
        raise ValueError(f"yaw_information: delta must be positive, got {delta}")
    turn = np.array([[0.0, 0.0, -delta], [0.0, 0.0, 0.0], [0.0, 0.0, delta]])
    out = np.zeros(len(p))
    for k, scan in enumerate(scans):
        if scan.n == 0:
            continue
        here = np.repeat(p[k][None], 3, axis=0)
        if k > 0:
            ll = np.asarray(maps.log_likelihood(compose(here, turn), scan), np.float64)
            out[k] = max(0.0, -(ll[0] + ll[2] - 2.0 * ll[1])) / delta ** 2
        maps.update(here, scan)
    return out
