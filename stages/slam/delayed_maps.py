"""Particle maps that weigh each scan against the map without its most recent scans (``slam.map_delay``).

A particle's map is built along its own path, so the scans it inserted in the last seconds agree with its
heading whether that heading is right or not: weighing the next scan against them rewards consistency with
the particle's own recent past, as scan matching does (``weight_pull``: on the drifting hallway the grid's
likelihood field, which the last metres of map dominate, pulls the cloud away from the truth where the loop
closes). With a delay of D scans, scan k is weighed against the map of scans ``<= k - D - 1`` and enters the
map at step ``k + D``, at the pose its particle had at step k (carried through resampling with the particle).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from stages.slam.beam_sampling import BeamSamples

F64 = npt.NDArray[np.floating[Any]]


@dataclass
class DelayedMaps:
    """``ParticleMaps`` over ``maps`` that insert every scan ``delay`` steps after weighing it."""

    maps: Any
    delay: int
    pending: deque[tuple[F64, BeamSamples]] = field(default_factory=deque)

    def __post_init__(self) -> None:
        if self.delay < 1:
            raise ValueError(f"slam.map_delay = {self.delay}: a delay is at least one scan (0 turns it off)")

    def log_likelihood(self, poses: F64, samples: BeamSamples) -> F64:
        """The scan's log-likelihood against the delayed map; then the scan ``delay`` steps back is inserted."""
        ll = np.asarray(self.maps.log_likelihood(poses, samples))
        self.pending.append((np.array(poses, dtype=np.float64, copy=True), samples))
        if len(self.pending) > self.delay:
            old_poses, old_samples = self.pending.popleft()
            self.maps.update(old_poses, old_samples)
        return ll

    def update(self, poses: F64, samples: BeamSamples) -> None:
        """Done in :meth:`log_likelihood` (a delayed insert)."""

    def select(self, indices: npt.NDArray[np.int64]) -> None:
        self.maps.select(indices)
        self.pending = deque((p[indices], s) for p, s in self.pending)

    def flush(self) -> None:
        """Insert every pending scan (the map then holds all scans, as without the delay)."""
        while self.pending:
            p, s = self.pending.popleft()
            self.maps.update(p, s)

    def map_of(self, k: int) -> tuple[F64, F64]:
        self.flush()
        theta, cov = self.maps.map_of(k)
        return theta, cov

    def close(self) -> None:
        close = getattr(self.maps, "close", None)
        if close is not None:
            close()
