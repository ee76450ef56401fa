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

A closed submap is forgotten unless ``keep_closed`` is set: then it keeps every particle's posterior mean
(:class:`ClosedSubmap`; rows shared by the particles that descend from one parent, so resampling copies
nothing), and a scan is weighed against the *oldest* submap, open or closed, whose window holds the robot:
a place seen again is weighed against the map of the first visit, which is how a submap filter closes a
loop. Closed submaps weigh by their mean only (H-SLAM's mean-only weight, eq. 26 without eq. 28's variance):
a full posterior per particle would cost M^2 numbers per closed submap. Pure numpy, no I/O.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from stages.slam import hilbert_map as hm
from stages.slam.beam_sampling import BeamSamples
from stages.slam.particle_linalg import StackedInformation
from stages.slam.rbpf import HilbertParticleMaps, HilbertWeighting, MapModel, hilbert_log_likelihood, weigh_and_update

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
    #: keep closed submaps (their posterior means) and weigh a scan against the oldest one whose window holds
    #: the robot: loop closure; False forgets them (stop 34's submaps)
    keep_closed: bool = False

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
    #: its place in the order of opening (0 = the first submap)
    order: int = 0


@dataclass
class ClosedSubmap:
    """A closed submap's particle maps as posterior means: particle ``k``'s map is ``theta[rows[k]]``."""

    basis: hm.HilbertBasis
    theta: F64
    rows: npt.NDArray[np.int64]
    scans: int
    order: int

    def select(self, indices: npt.NDArray[np.int64]) -> None:
        """Survivors after resampling: only the row indices move; rows no particle holds any more are dropped."""
        kept, rows = np.unique(self.rows[indices], return_inverse=True)
        if len(kept) < len(self.theta):
            self.theta = self.theta[kept]
        self.rows = np.asarray(rows, dtype=np.int64).reshape(-1)

    def log_likelihood(self, poses: F64, samples: BeamSamples, weighting: HilbertWeighting) -> F64:
        """eq. 22-27 and 29 against every particle's mean map (mean-only: ``use_variance`` is ignored)."""
        mean_only = replace(weighting, use_variance=False)
        return hilbert_log_likelihood(self.basis, self.theta[self.rows], np.empty(0), poses, samples, mean_only)


def posterior_means(maps: Any) -> F64:
    """Every particle's current posterior mean ``(Np, M)`` (float64) of in-process or worker maps, either form.

    The information form's ``theta`` is the mean its last weighting used (before that scan's update), so the
    means are solved anew from ``(Y, eta)``; the covariance form's ``theta`` is current."""
    stack = getattr(maps, "stack", None)
    if stack is None and getattr(maps, "form", None) == "information" and hasattr(maps, "_stacks"):
        info, eta = maps._stacks[1], maps._stacks[2]  # worker maps: the shared (Y, eta)
        stack = StackedInformation(np.ones(info.shape[-1]), len(info), info.dtype, arrays=(info, eta))
    if stack is not None:
        return np.stack([stack.posterior(k)[0] for k in range(stack.n)])
    return np.array(maps.theta, dtype=np.float64)


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
    #: closed submaps kept for loop closure (``geometry.keep_closed``)
    closed: list[ClosedSubmap] = field(default_factory=list)
    #: how closed submaps weigh a scan (the open ones' weighting, mean-only)
    weighting: HilbertWeighting = field(default_factory=HilbertWeighting)
    #: scans weighed against a closed submap (a diagnostic)
    revisits: int = 0

    @classmethod
    def create(cls, geometry: SubmapModel, n_particles: int, model: MapModel,
               basis_kind: hm.BasisKind = "tensor") -> SubmapParticleMaps:
        """Submaps whose particle maps live in this process."""
        return cls(geometry, in_process(n_particles, model), basis_kind, weighting=model.weighting)

    def _distance(self, s: Submap, centre: F64) -> float:
        return float(np.max(np.abs(centre - s.basis.centre)))

    def _close(self, s: Submap) -> None:
        """Keep the closed submap's means (``keep_closed``), and its maps for reuse when they can be reset
        (worker maps), else let them go."""
        if self.geometry.keep_closed and s.scans > 0:
            theta = posterior_means(s.maps)
            self.closed.append(ClosedSubmap(s.basis, theta, np.arange(len(theta)), s.scans, s.order))
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
            self.open.append(Submap(basis, self.factory(basis, spare), order=self.opened))
            self.opened += 1

    def weighing(self, poses: F64) -> Submap | ClosedSubmap | None:
        """The submaps arranged for a scan at ``poses``, and the one it is weighed against: the oldest submap
        with data, open or (``keep_closed``) closed with the robot inside its window (None before the first
        scan)."""
        self._arrange(poses)
        target: Submap | ClosedSubmap | None = next((s for s in self.open if s.scans > 0), None)
        if self.closed:
            c = np.mean(np.asarray(poses, dtype=np.float64)[:, :2], axis=0)
            inside = [k for k in self.closed if float(np.max(np.abs(c - k.basis.centre))) <= self.geometry.window]
            old = min(inside, key=lambda k: k.order, default=None)
            if old is not None and (target is None or old.order < target.order):
                target = old
        return target

    def weigh_and_update(self, poses: F64, samples: BeamSamples) -> F64:
        """eq. 22-30 against the oldest submap with data (:meth:`weighing`), then eq. 15 into every open one."""
        if samples.n == 0:
            return np.zeros(len(poses))
        target = self.weighing(poses)
        ll: F64 = np.zeros(len(poses))
        if isinstance(target, ClosedSubmap):
            ll = target.log_likelihood(poses, samples, self.weighting)
            self.revisits += 1
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
        for k in self.closed:
            k.select(indices)

    def close(self) -> None:
        """Release every submap's maps (worker processes, shared memory) that can be closed."""
        for m in [*(s.maps for s in self.open), *self.spare]:
            close = getattr(m, "close", None)
            if close is not None:
                close()
        self.open, self.spare, self.closed = [], [], []


@dataclass
class HybridParticleMaps:
    """``ParticleMaps`` that weigh every scan against both the global map (``whole``: the paper's, which can
    close loops) and a second map of the same particles with the detail the global basis cannot hold
    (``local``: the local submaps, or the FastSLAM occupancy grid), each log-likelihood taken with ``share`` of
    the scan (``share`` on the second's, ``1 - share`` on the global's), and update both."""

    whole: Any
    local: Any
    share: float = 0.5

    def weigh_and_update(self, poses: F64, samples: BeamSamples) -> F64:
        g = weigh_and_update(self.whole, poses, samples)
        s = weigh_and_update(self.local, poses, samples)
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
        for part in (self.whole, self.local):
            close = getattr(part, "close", None)
            if close is not None:
                close()
