"""Local Hilbert-GP submaps for RICH-SLAM's particles (issue 27, item 3).

The paper's particle map is one Hilbert-GP over the whole trajectory's envelope (Sec. III-C): with M basis
functions its shortest half-wavelength is ``2 L / sqrt(M)`` per axis, so the map, and with it the weight
of eq. 22-30, grows coarser as the world grows (about 7 m on a 59 m outdoor domain at M = 256, where the
prior at l = 2 m still holds detail down to about 2 m). Here every particle instead carries a few *submaps*:
square Hilbert-GP maps of half width ``half_width`` (each its own basis of eq. 6-7 with M functions, the same
for all particles), centred where the particles were when the submap was opened. Every scan is weighted
against the oldest open submap (the one with the most data) and inserted into all open ones; a submap
is closed when the robot leaves its *window* (the square in which every sample of a scan, up to
``reach`` from the robot, still lies inside the domain), and a new one is opened when the robot is
half a window away from every open one. So the map resolution depends on ``half_width`` and M only,
and the cost per scan is that of at most ``max_open`` maps of M functions, whatever the world's size.

What a submap cannot do is close a loop: a place seen again after its submap was closed is mapped anew.
Pure numpy, no I/O.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from stages.slam import hilbert_map as hm
from stages.slam.beam_sampling import BeamSamples
from stages.slam.rbpf import HilbertParticleMaps, MapModel, weigh_and_update

F64 = npt.NDArray[np.floating[Any]]


@dataclass(frozen=True)
class SubmapModel:
    """Geometry of the submaps; lengths in metres."""

    #: half width of each submap's square domain
    half_width: float = 9.0
    #: basis functions per submap (a perfect square for the tensor basis)
    n_basis: int = 256
    #: the furthest a scan's sample lies from the robot (the beam range plus the endpoint tolerance)
    reach: float = 5.25
    #: room left for the particles' spread about their mean position
    margin: float = 0.5
    #: open submaps at most (the oldest is closed first)
    max_open: int = 2

    @property
    def window(self) -> float:
        """Chebyshev distance from a submap's centre within which a scan lies wholly inside it."""
        return self.half_width - self.reach - self.margin

    def __post_init__(self) -> None:
        if self.window <= 0:
            raise ValueError(f"submap half width {self.half_width} m leaves no window for a robot whose samples "
                             f"reach {self.reach} m (plus {self.margin} m margin); make it larger than "
                             f"{self.reach + self.margin} m")
        if self.max_open < 1:
            raise ValueError(f"max_open must be >= 1, got {self.max_open}")


class SubmapMaps(Protocol):
    """What a submap's particle maps offer (:class:`HilbertParticleMaps`, ``parallel.ParallelHilbertMaps``)."""

    def weigh_and_update(self, poses: F64, samples: BeamSamples) -> F64: ...

    def insert(self, poses: F64, samples: BeamSamples) -> None: ...

    def select(self, indices: npt.NDArray[np.int64]) -> None: ...


@dataclass
class Submap:
    """One open submap: its basis, every particle's map over it, and how many scans it holds."""

    basis: hm.HilbertBasis
    maps: SubmapMaps
    scans: int = 0


#: the particle maps of a new submap on ``basis``, at the prior; ``spare`` are a closed submap's maps to reuse
#: (or None)
MapsFactory = Callable[[hm.HilbertBasis, "SubmapMaps | None"], SubmapMaps]


def in_process(n_particles: int, model: MapModel) -> MapsFactory:
    """New :class:`HilbertParticleMaps` for every submap."""
    return lambda basis, spare: HilbertParticleMaps(basis, n_particles, model)


@dataclass
class SubmapParticleMaps:
    """``ParticleMaps`` over local submaps (see the module docstring). ``factory(basis, spare)`` makes the
    particle maps of a new submap (prior maps, one per particle), reusing a closed submap's when it can."""

    geometry: SubmapModel
    factory: MapsFactory
    basis_kind: hm.BasisKind = "tensor"
    open: list[Submap] = field(default_factory=list)
    #: submaps opened so far (a diagnostic)
    opened: int = 0
    #: a closed submap's maps, kept for the next one (worker processes are not started anew)
    spare: list[SubmapMaps] = field(default_factory=list)

    @classmethod
    def create(cls, geometry: SubmapModel, n_particles: int, model: MapModel,
               basis_kind: hm.BasisKind = "tensor") -> SubmapParticleMaps:
        """Submaps whose particle maps live in this process."""
        return cls(geometry, in_process(n_particles, model), basis_kind)

    def _distance(self, s: Submap, centre: F64) -> float:
        return float(np.max(np.abs(centre - s.basis.centre)))

    def _close(self, s: Submap) -> None:
        """Keep a closed submap's maps for reuse when they can be reset (worker maps), else let them go."""
        if hasattr(s.maps, "reset") and not self.spare:
            self.spare.append(s.maps)
        elif hasattr(s.maps, "close"):
            s.maps.close()

    def _arrange(self, poses: F64) -> None:
        """Close the submaps the robot has left, open one where it is half a window from every open one."""
        g = self.geometry
        c = np.mean(np.asarray(poses, dtype=np.float64)[:, :2], axis=0)
        dist = [self._distance(s, c) for s in self.open]
        for s, d in zip(self.open, dist, strict=True):
            if d > g.window:
                self._close(s)
        self.open = [s for s, d in zip(self.open, dist, strict=True) if d <= g.window]
        if not any(d <= g.window / 2 for d in dist):
            if len(self.open) >= g.max_open:
                self._close(self.open.pop(0))
            basis = hm.make_basis([g.half_width, g.half_width], c, g.n_basis, self.basis_kind)
            spare = self.spare.pop() if self.spare else None
            self.open.append(Submap(basis, self.factory(basis, spare)))
            self.opened += 1

    def weighing(self, poses: F64) -> Submap | None:
        """The submaps arranged for a scan at ``poses``, and the one it is weighed against: the oldest open
        submap with data (None before the first scan)."""
        self._arrange(poses)
        return next((s for s in self.open if s.scans > 0), None)

    def weigh_and_update(self, poses: F64, samples: BeamSamples) -> F64:
        """eq. 22-30 against the oldest open submap with data, then eq. 15 into every open submap."""
        if samples.n == 0:
            return np.zeros(len(poses))
        target = self.weighing(poses)
        ll: F64 = np.zeros(len(poses))
        for s in self.open:
            if s is target:
                ll = s.maps.weigh_and_update(poses, samples)
            else:
                s.maps.insert(poses, samples)
            s.scans += 1
        return ll

    def log_likelihood(self, poses: F64, samples: BeamSamples) -> F64:
        """Weights and update in one call (the filter always updates right after weighting)."""
        return self.weigh_and_update(poses, samples)

    def update(self, poses: F64, samples: BeamSamples) -> None:
        """Done in :meth:`log_likelihood`."""

    def select(self, indices: npt.NDArray[np.int64]) -> None:
        for s in self.open:
            s.maps.select(indices)

    def close(self) -> None:
        """Release every submap's maps (worker processes, shared memory) that can be closed."""
        for m in [*(s.maps for s in self.open), *self.spare]:
            close = getattr(m, "close", None)
            if close is not None:
                close()
        self.open, self.spare = [], []


@dataclass
class HybridParticleMaps:
    """``ParticleMaps`` that weigh every scan against both the global map (``whole``: the paper's, which can
    close loops) and the local submaps (``local``: the detail the global basis cannot hold), each log-likelihood
    taken with ``share`` of the scan (``share`` on the submaps', ``1 - share`` on the global's), and update both."""

    whole: Any
    local: SubmapParticleMaps
    share: float = 0.5

    def weigh_and_update(self, poses: F64, samples: BeamSamples) -> F64:
        g = weigh_and_update(self.whole, poses, samples)
        s = self.local.weigh_and_update(poses, samples)
        return np.asarray((1.0 - self.share) * g + self.share * s)

    def log_likelihood(self, poses: F64, samples: BeamSamples) -> F64:
        """Weights and update in one call (the filter always updates right after weighting)."""
        return self.weigh_and_update(poses, samples)

    def update(self, poses: F64, samples: BeamSamples) -> None:
        """Done in :meth:`log_likelihood`."""

    def select(self, indices: npt.NDArray[np.int64]) -> None:
        self.whole.select(indices)
        self.local.select(indices)

    def close(self) -> None:
        close = getattr(self.whole, "close", None)
        if close is not None:
            close()
        self.local.close()
