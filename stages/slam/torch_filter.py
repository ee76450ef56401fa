"""Algorithm 1 (RICH-SLAM Sec. IV-D) with the particles, weights and maps on a torch device.

The same filter as :class:`stages.slam.rbpf.RBPF`: propagation (eq. 21), weights in log space
(eq. 22-30), N_eff (eq. 31), resampling and the map update, as batched tensor operations. The random
draws come from the same seeded numpy generator, in the same order (``3 Np`` normals per scan, the
resampler's uniforms), and are uploaded, so a torch run follows the numpy run draw for draw. Per scan
one small tensor comes back (N_eff, the best particle, its pose, the Cholesky status); the particle
history stays on the device until :meth:`TorchRBPF.finish`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from stages.slam.beam_sampling import BeamSamples
from stages.slam.rbpf import FilterHistory, MotionNoise, Resampling, StepResult, run_steps
from stages.slam.torch_maps import TorchHilbertMaps

F64 = npt.NDArray[np.floating[Any]]


@contextmanager
def cpu_threads(n: int) -> Iterator[None]:
    """Run with ``n`` torch CPU threads (0: leave torch's setting), restored afterwards.

    On a shared machine torch's default of one thread per core collapses: the batched kernels of a
    small map are short and the threads wait for each other (measured 25-50x slower than one thread
    with the two cores busy; README, "torch backend").
    """
    old = torch.get_num_threads()
    if n > 0:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def wrap_angle_t(a: torch.Tensor) -> torch.Tensor:
    """Angles to (-pi, pi] (as :func:`rbpf.wrap_angle`)."""
    return -(torch.remainder(-a + torch.pi, 2 * torch.pi) - torch.pi)


def compose_t(x: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """``x (+) d`` for poses ``(Np, 3)`` and body-frame increments ``(Np, 3)``."""
    c, s = torch.cos(x[:, 2]), torch.sin(x[:, 2])
    return torch.stack([x[:, 0] + c * d[:, 0] - s * d[:, 1], x[:, 1] + s * d[:, 0] + c * d[:, 1],
                        wrap_angle_t(x[:, 2] + d[:, 2])], dim=1)


def resample_positions(kind: Resampling, n: int, rng: np.random.Generator) -> F64:
    """The resampler's sorted pointers in [0, 1), drawn exactly as :data:`rbpf.RESAMPLERS` draws them."""
    if kind == "systematic":
        return (rng.random() + np.arange(n)) / n
    if kind == "stratified":
        return (rng.random(n) + np.arange(n)) / n
    if kind == "multinomial":
        return np.sort(rng.random(n))
    raise ValueError(f"unknown resampling {kind!r}")


def search_t(w: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
    """Indices of the pointers in the cumulative weights (as ``rbpf._search``)."""
    c = torch.cumsum(w, dim=0)
    c = c / c[-1]
    c[-1] = 1.0
    return torch.clamp(torch.searchsorted(c, positions, right=True), max=len(w) - 1)


class TorchRBPF:
    """Algorithm 1 on a device: propagate, weight against the prior maps, update, select, resample."""

    def __init__(
        self,
        maps: TorchHilbertMaps,
        initial_pose: npt.ArrayLike,
        n_particles: int,
        noise: MotionNoise,
        rng: np.random.Generator,
        resampling: Resampling = "systematic",
        resample_threshold: float = 0.5,
    ) -> None:
        self.maps = maps
        self.device = maps.device
        p0 = torch.as_tensor(np.asarray(initial_pose, dtype=np.float64).reshape(1, 3), device=self.device)
        self.poses = p0.repeat(n_particles, 1)
        self.logw = torch.full((n_particles,), -float(np.log(n_particles)), dtype=torch.float64, device=self.device)
        self.noise = noise
        self.rng = rng
        self.resampling: Resampling = resampling
        self.resample_threshold = resample_threshold
        self.history = FilterHistory()
        self._parents = torch.arange(n_particles, device=self.device)
        self._particles: list[torch.Tensor] = []
        self._parent_log: list[torch.Tensor] = []
        self._tiny = float(np.finfo(np.float64).tiny)

    @property
    def n_particles(self) -> int:
        return int(self.poses.shape[0])

    def _propagate(self, u: npt.ArrayLike) -> None:
        """eq. 21 with the numpy filter's draws (:func:`rbpf.propagate`: the noise drawn on the host)."""
        u = np.asarray(u, dtype=np.float64).reshape(3)
        s_xy, s_yaw = self.noise.std(u)
        d = u + self.rng.standard_normal((self.n_particles, 3)) * np.array([s_xy, s_xy, s_yaw])
        self.poses = compose_t(self.poses, torch.as_tensor(d, device=self.device))

    def step(self, u: npt.ArrayLike, samples: BeamSamples, first: bool = False,
             observer: Callable[[TorchRBPF, int], None] | None = None) -> StepResult:
        """One iteration of Algorithm 1; ``observer(self, best)`` sees the maps before resampling."""
        if not first:
            self._propagate(u)
        logw = self.logw + self.maps.weigh_and_update(self.poses, samples)
        w = torch.exp(logw - logw.max())
        w = w / w.sum()
        self.logw = torch.log(torch.clamp_min(w, self._tiny))
        best_t = torch.argmax(w)
        n_eff_t = w.sum() ** 2 / torch.sum(w * w)
        stats = torch.cat([n_eff_t[None], best_t[None].to(torch.float64), self.poses[best_t],
                           self.maps.check()[None].to(torch.float64)]).cpu().numpy()  # the one sync per scan
        if stats[5] != 0:
            raise np.linalg.LinAlgError(f"a particle map's Cholesky factor failed ({int(stats[5])}); "
                                        "try dtype = float64")
        n_eff, best, pose = float(stats[0]), int(stats[1]), stats[2:5].copy()
        h = self.history
        h.best_pose.append(pose)
        h.best_index.append(best)
        h.n_eff.append(n_eff)
        self._particles.append(self.poses.clone())
        self._parent_log.append(self._parents)
        if observer is not None:
            observer(self, best)
        resampled = n_eff < self.resample_threshold * self.n_particles
        self._parents = torch.arange(self.n_particles, device=self.device)
        if resampled:
            pos = torch.as_tensor(resample_positions(self.resampling, self.n_particles, self.rng), device=self.device)
            idx = search_t(w, pos)
            self.poses = self.poses[idx]
            self.maps.select(idx)
            self.logw = torch.full_like(self.logw, -float(np.log(self.n_particles)))
            self._parents = idx
        h.resampled.append(resampled)
        return StepResult(best, pose, n_eff, resampled)

    def finish(self) -> FilterHistory:
        """Bring the particle history back to the host (``history.particles``, ``history.parents``)."""
        if self._particles:
            parts = torch.stack(self._particles).cpu().numpy()
            parents = torch.stack(self._parent_log).cpu().numpy().astype(np.int64)
            self.history.particles.extend(list(parts))
            self.history.parents.extend(list(parents))
            self._particles, self._parent_log = [], []
        return self.history

    def run(
        self,
        increments: npt.ArrayLike,
        scans: Sequence[BeamSamples],
        observer: Callable[[int, TorchRBPF, int], None] | None = None,
        on_step: Callable[[], None] | None = None,
    ) -> FilterHistory:
        """Run over all scans (as :meth:`RBPF.run`) and return the history on the host."""
        run_steps(self.step, increments, scans, observer, on_step)
        return self.finish()
