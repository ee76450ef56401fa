"""Particle maps split across worker processes sharing memory (the machine's cores, one BLAS thread each).

The per-particle BLAS-3 kernels of the information form (``particle_linalg``) are too small for a
multi-threaded BLAS to scale (threads spin and synchronise per 256 x 256 call, catastrophically when
the machine is shared), and scipy's BLAS wrappers hold the GIL, so Python threads do not help. Worker
processes do: each owns a contiguous block of particles whose maps live in shared memory, runs the
fused weight-and-update of a scan on it with a single-threaded BLAS, and returns the log-likelihoods.
The parent resamples by permuting the shared arrays (a copy, so duplicates never alias).
"""

from __future__ import annotations

import itertools
import multiprocessing as mp
import os
from dataclasses import dataclass, replace
from multiprocessing.connection import Connection
from multiprocessing.shared_memory import SharedMemory
from typing import Any

import numpy as np
import numpy.typing as npt

from core import hilbert_map as hm
from stages.slam.beam_sampling import BeamSamples
from stages.slam.particle_linalg import StackedCovariance, StackedInformation, select_rows
from stages.slam.rbpf import HilbertParticleMaps, MapModel

F64 = npt.NDArray[np.floating[Any]]
_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


@dataclass(frozen=True)
class _Spec:
    names: tuple[str, ...]  # shared blocks: theta, info, eta (information form) or theta, cov
    n_particles: int
    M: int
    dtype: str
    lo: int
    hi: int
    basis: hm.HilbertBasis
    model: MapModel


def _attach(name: str, shape: tuple[int, ...], dtype: str) -> tuple[SharedMemory, npt.NDArray[Any]]:
    shm = SharedMemory(name=name)
    return shm, np.ndarray(shape, dtype=np.dtype(dtype), buffer=shm.buf)


def _worker_main(conn: Connection, spec: _Spec) -> None:
    """Serve requests on particles ``[lo, hi)`` until ``None``: ``("step", poses, points, labels, beam, origin)``
    (the weights and the map update of a scan)."""
    Np, M = spec.n_particles, spec.M
    shapes = [(Np, M), (Np, M, M), (Np, M)]  # theta, info or cov, eta
    blocks = [_attach(name, shape, spec.dtype) for name, shape in zip(spec.names, shapes, strict=False)]
    arrays = tuple(b[1][spec.lo : spec.hi] for b in blocks)
    model = replace(spec.model, dtype=spec.dtype)
    maps = HilbertParticleMaps(spec.basis, spec.hi - spec.lo, model, arrays=arrays)
    try:
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):  # the parent is gone (killed): nothing to serve, leave quietly
                break
            if msg is None:
                break
            try:
                _kind, poses, points, labels, beam, origin = msg
                samples = BeamSamples(points, labels, beam, points[labels > 0], origin)
                reply: tuple[str, Any] = ("ok", maps.weigh_and_update(poses, samples))
            except Exception as exc:  # report, keep serving
                reply = ("error", f"{type(exc).__name__}: {exc}")
            try:
                conn.send(reply)
            except OSError:  # the parent is gone (killed) while this scan was weighed: leave quietly
                break
    finally:
        del arrays, maps
        for shm, _ in blocks:
            shm.close()


class ParallelHilbertMaps:
    """``ParticleMaps`` computed by ``workers`` processes on shared memory (either map form).

    ``log_likelihood`` runs the scan's weight and its map update in one round trip (RBPF always
    updates right after weighting, on the same poses); ``update`` is then a no-op.
    """

    def __init__(
        self,
        basis: hm.HilbertBasis,
        n_particles: int,
        model: MapModel,
        workers: int = 2,
    ) -> None:
        self.model = model
        dtype, form = model.dtype, model.form
        self.dtype = np.dtype(dtype)
        self.form = form
        M = basis.M
        self._shm: list[SharedMemory] = []
        self.theta = self._shared((n_particles, M))
        self.stack: StackedInformation | None = None
        self.cov: npt.NDArray[Any] | None = None
        self.cstack = StackedCovariance(np.ones(1), 0, self.dtype)
        if form == "information":
            self._stacks = [self.theta, self._shared((n_particles, M, M)), self._shared((n_particles, M))]
        else:
            self.cov = self._shared((n_particles, M, M))
            self._stacks = [self.theta, self.cov]
        self._prior(basis)
        workers = max(1, min(workers, n_particles))
        bounds = np.linspace(0, n_particles, workers + 1).round().astype(int)
        ctx = mp.get_context("spawn")
        self._conns: list[Connection] = []
        self._procs: list[Any] = []
        saved = {v: os.environ.get(v) for v in _THREAD_VARS}
        try:
            for v in _THREAD_VARS:
                os.environ[v] = "1"
            for lo, hi in itertools.pairwise(bounds):
                spec = _Spec(tuple(b.name for b in self._shm), n_particles, M, self.dtype.name, int(lo), int(hi),
                             basis, model)
                parent, child = ctx.Pipe()
                proc = ctx.Process(target=_worker_main, args=(child, spec), daemon=True)
                proc.start()
                child.close()
                self._conns.append(parent)
                self._procs.append(proc)
        except BaseException:
            self.close()
            raise
        finally:
            for v, old in saved.items():
                if old is None:
                    os.environ.pop(v, None)
                else:
                    os.environ[v] = old
        self._bounds = bounds

    def _prior(self, basis: hm.HilbertBasis) -> None:
        """Every particle's map to the prior on ``basis`` (in the shared arrays), and the parent's kernels."""
        m = self.model
        n_particles = len(self.theta)
        self.basis = basis
        self.theta[...] = 0
        if self.form == "information":
            _, info0, _ = hm.prior_information(basis, m.lengthscale, m.signal_variance)
            info, eta = self._stacks[1], self._stacks[2]
            info[...] = StackedInformation(np.diag(info0), 1, self.dtype).info[0]
            eta[...] = 0
            # kernels for the parent's queries of single maps
            self.stack = StackedInformation(np.diag(info0), n_particles, self.dtype, arrays=(info, eta))
        else:
            assert self.cov is not None
            _, cov0 = hm.prior(basis, m.lengthscale, m.signal_variance, dtype=self.dtype)
            self.cov[...] = cov0
            self.cstack = StackedCovariance(np.diag(cov0), n_particles, self.dtype, array=self.cov)

    def _round_trip(self, messages: list[Any]) -> list[Any]:
        for c, msg in zip(self._conns, messages, strict=True):
            c.send(msg)
        out = []
        for c in self._conns:
            status, value = c.recv()
            if status != "ok":
                raise RuntimeError(f"slam worker failed: {value}")
            out.append(value)
        return out

    def _shared(self, shape: tuple[int, ...]) -> npt.NDArray[Any]:
        size = int(np.prod(shape)) * self.dtype.itemsize
        shm = SharedMemory(create=True, size=max(size, 1))
        self._shm.append(shm)
        return np.ndarray(shape, dtype=self.dtype, buffer=shm.buf)

    def log_likelihood(self, poses: F64, samples: BeamSamples) -> F64:
        """The weights and, in the same round trip, the map update (see the class docstring)."""
        return self.weigh_and_update(poses, samples)

    def _scan_messages(self, kind: str, poses: F64, samples: BeamSamples) -> list[Any]:
        return [(kind, poses[lo:hi], samples.points, samples.labels, samples.beam, samples.origin)
                for lo, hi in itertools.pairwise(self._bounds)]

    def weigh_and_update(self, poses: F64, samples: BeamSamples) -> F64:
        if samples.n == 0:
            return np.zeros(len(poses))
        return np.concatenate(self._round_trip(self._scan_messages("step", poses, samples)))

    def update(self, poses: F64, samples: BeamSamples) -> None:
        """Done by the workers together with the weights."""

    def select(self, indices: npt.NDArray[np.int64]) -> None:
        """Resample the shared maps in place (only the rows that change are copied)."""
        for a in self._stacks:
            select_rows(a, indices)

    def map_of(self, k: int) -> tuple[F64, F64]:
        """Mean and covariance of particle k's map (float64)."""
        if self.stack is not None:
            theta, L = self.stack.posterior(k)
            return theta, hm.covariance_from_information(L)
        return self.theta[k].astype(np.float64), self.cstack.full(k)

    def close(self) -> None:
        for c in getattr(self, "_conns", []):
            try:
                c.send(None)
            except (BrokenPipeError, OSError):
                pass
        for p in getattr(self, "_procs", []):
            p.join(timeout=10)
            if p.is_alive():
                p.terminate()
        self._conns, self._procs = [], []
        # drop our views before releasing the blocks
        self.theta = np.zeros(0)
        self.cov = None
        self._stacks = []
        if self.stack is not None:
            self.stack.info, self.stack.eta = np.zeros((0, 0, 0)), np.zeros((0, 0))
        for shm in self._shm:
            shm.close()
            shm.unlink()
        self._shm = []

    def __enter__(self) -> ParallelHilbertMaps:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
