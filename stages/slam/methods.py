"""The stage's filter methods on numpy inputs: odometry pass-through, FastSLAM with grids (the paper's FastSLAM-Radar
baseline), RICH-SLAM as the paper configures it and its two ablations of Table III.

Pure functions (no I/O): the stage reads artifacts, builds body-frame beam samples per scan and the
odometry poses, and calls :func:`run_method`. ``radar_graph`` is :mod:`pose_graph`'s.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from core import hilbert_map as hm
from stages.slam.backend import resolve_device
from stages.slam.beam_sampling import BeamSamples, to_world
from stages.slam.grid_map import GridModel, GridParticleMaps, make_grid_spec
from stages.slam.method_names import HILBERT_METHODS
from stages.slam.parallel import ParallelHilbertMaps
from stages.slam.params import MapParams, SlamParams
from stages.slam.rbpf import (
    RBPF,
    FilterHistory,
    HilbertParticleMaps,
    HilbertWeighting,
    MapModel,
    MotionNoise,
    Resampling,
    odometry_increments,
)

DOMAIN_PADDING = hm.DOMAIN_PADDING
#: the proposal: GMapping's motion model fitted to the odometry increment (eq. 21)
NOISE = MotionNoise()
RESAMPLING: Resampling = "systematic"
#: resample when N_eff < this * N_p (eq. 31)
RESAMPLE_THRESHOLD = 0.5
#: the discretised endpoint-tolerance disc (eq. 29): points on its ring, rings, and the variance term's form
ET_RING_POINTS, ET_RINGS = 8, 1
ET_VARIANCE: Literal["exact", "taylor"] = "taylor"
#: torch CPU threads of the torch backend (one is far faster on a shared machine)
TORCH_THREADS = 1
#: the grid baseline's inverse sensor model and likelihood field
GRID = GridModel()
F64 = npt.NDArray[np.floating[Any]]


def map_model(p: SlamParams, method: str, form: Literal["information", "covariance"] = "information") -> MapModel:
    """The particle maps' parameter object of a Hilbert method (every backend takes it)."""
    m = p.map
    return MapModel(m.lengthscale_m, m.signal_variance, m.noise_variance, weighting(p, method),
                    dtype=np.dtype(m.dtype), form=form)


def weighting(p: SlamParams, method: str) -> HilbertWeighting:
    """Eq. 28-29 for ``rich_slam``; r_e = 0 for ``rich_slam_no_et``; the mean only for ``rich_slam_mean_only``."""
    return HilbertWeighting(
        use_variance=method != "rich_slam_mean_only",
        endpoint_tolerance=0.0 if method == "rich_slam_no_et" else p.map.endpoint_tolerance,
        ring_points=ET_RING_POINTS,
        rings=ET_RINGS,
        et_variance=ET_VARIANCE,
    )


@dataclass
class MethodResult:
    """A method's trajectory (one pose per scan), filter diagnostics and, for Hilbert methods, the final maps."""

    method: str
    poses: F64  # (T, 3) the largest-weight particle per scan (Algorithm 1 line 9)
    n_eff: F64  # (T,)
    seconds: float
    resampled: int = 0
    particles: F64 | None = None  # (T, Np, 3)
    theta: F64 | None = None  # best particle's final map
    cov: F64 | None = None
    form: str = ""  # map form of the Hilbert methods
    device: str = "cpu"  # where the Hilbert methods' filter ran (``cpu`` or ``cuda``)


def domain_from_trajectory(xy: npt.ArrayLike, padding: float) -> tuple[F64, F64]:
    """Hilbert domain (half widths, centre) from a trajectory envelope plus a fixed padding."""
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    lo, hi = p.min(axis=0) - padding, p.max(axis=0) + padding
    return (hi - lo) / 2.0, (hi + lo) / 2.0


def step_flops(form: str, n: float, b: float, M: int, w: HilbertWeighting) -> float:
    """Dominant floating-point operations of one particle's weight and update (for the form choice)."""
    ring = w.ring_points * w.rings if (w.endpoint_tolerance > 0 and w.use_variance) else 0
    exact = w.et_variance == "exact"
    if form == "covariance":  # symm of samples and ring points (or Jacobians), S, W = R^-1 A, syrk downdate
        q = b * ring if exact else (2 * b if ring else 0)
        return 2 * (n + q) * M**2 + 4 * n * n * M + 7 * n**3 / 3 + n * M**2
    q = b * ring if exact else (2 * b if ring else 0)  # syrk, potrf, trsm of samples and ring points
    return n * M**2 + M**3 / 3 + (n + q) * M**2


def choose_form(p: SlamParams, method: str, scans: Sequence[BeamSamples], M: int,
                info_efficiency: float = 0.75) -> Literal["information", "covariance"]:
    """``auto``: the form with the smaller modelled cost at the sequence's mean samples per scan.

    The information form's kernels (potrf, trsm on 256 x 256, one pass per scan) run at about
    ``info_efficiency`` of the rate of the covariance form's (symm, syrk, small products), measured
    side by side at 12, 61 and 180 samples per scan (N_p = 200, M = 256, 2 workers: 0.074 / 0.163 /
    0.334 s per scan against 0.054 / 0.162 / 0.666); the crossover is near 65 samples per scan.
    """
    n = float(np.mean([s.n for s in scans])) if len(scans) else 0.0
    b = float(np.mean([len(s.endpoints) for s in scans])) if len(scans) else 0.0
    w = weighting(p, method)
    info = step_flops("information", n, b, M, w) / info_efficiency
    return "information" if info < step_flops("covariance", n, b, M, w) else "covariance"


def make_hilbert_maps(p: SlamParams, basis: hm.HilbertBasis, method: str, n_particles: int,
                      form: Literal["information", "covariance"] = "information",
                      ) -> HilbertParticleMaps | ParallelHilbertMaps:
    """The particle maps of a Hilbert method: one global map over ``basis`` per particle, in ``workers``
    processes when ``workers > 0``."""
    factory: Callable[..., HilbertParticleMaps | ParallelHilbertMaps] = (
        partial(ParallelHilbertMaps, workers=p.workers) if p.workers > 0 else HilbertParticleMaps)
    return factory(basis, n_particles, map_model(p, method, form))


Observer = Callable[[int, RBPF, int], None]


def run_method(
    method: str,
    odometry: F64,
    scans: Sequence[BeamSamples],
    basis: hm.HilbertBasis,
    p: SlamParams,
    observer: Observer | None = None,
    on_step: Callable[[], None] | None = None,
) -> MethodResult:
    """Run one filter method over the scans; ``odometry (T, 3)`` are world <- base poses at the scan times."""
    t0 = time.perf_counter()
    odometry = np.asarray(odometry, dtype=np.float64).reshape(-1, 3)
    if method == "odometry":
        if on_step is not None:
            for _ in range(len(odometry)):
                on_step()
        return MethodResult(method, odometry.copy(), np.ones(len(odometry)), time.perf_counter() - t0)
    rng = np.random.default_rng(p.seed)
    form: Literal["information", "covariance"] = "information"
    maps: GridParticleMaps | HilbertParticleMaps | ParallelHilbertMaps | None = None
    if method == "fastslam_grid":
        spec = make_grid_spec(basis.centre, basis.half_widths, p.grid.resolution)
        maps = GridParticleMaps(spec, p.n_particles, GRID)
    elif method in HILBERT_METHODS:
        form = choose_form(p, method, scans, basis.M)
        if p.backend == "numpy":
            maps = make_hilbert_maps(p, basis, method, p.n_particles, form)
    else:
        raise ValueError(f"unknown filter method {method!r}; one of odometry, fastslam_grid, "
                         f"{', '.join(HILBERT_METHODS)}")
    best_map: dict[str, F64] = {}

    def keep_best(i: int, f: Any, best: int) -> None:
        if i == len(odometry) - 1 and hasattr(f.maps, "map_of"):
            best_map["theta"], best_map["cov"] = f.maps.map_of(best)
        if observer is not None:
            observer(i, f, best)

    device = "cpu"
    if maps is None:
        device = resolve_device(p.backend, p.device)[0]
        h = _run_torch(p, basis, method, form, device, odometry, scans, rng, keep_best, on_step)
    else:
        try:
            f = RBPF(maps, odometry[0], p.n_particles, NOISE, rng, RESAMPLING, RESAMPLE_THRESHOLD)
            h = f.run(odometry_increments(odometry), scans, observer=keep_best, on_step=on_step)
        finally:
            close = getattr(maps, "close", None)
            if close is not None:
                close()
    return MethodResult(
        method, h.best_trajectory(), np.asarray(h.n_eff), time.perf_counter() - t0, int(np.sum(h.resampled)),
        np.asarray(h.particles), best_map.get("theta"), best_map.get("cov"),
        form if method in HILBERT_METHODS else "", device,
    )


def _run_torch(p: SlamParams, basis: hm.HilbertBasis, method: str, form: Literal["information", "covariance"],
               device: str, odometry: F64, scans: Sequence[BeamSamples], rng: np.random.Generator,
               observer: Observer, on_step: Callable[[], None] | None) -> FilterHistory:
    """The Hilbert method's filter on the torch backend (imported only here: torch is optional)."""
    from stages.slam.torch_filter import TorchRBPF, cpu_threads
    from stages.slam.torch_maps import TorchHilbertMaps

    maps = TorchHilbertMaps(basis, p.n_particles, map_model(p, method, form), device=device)
    f = TorchRBPF(maps, odometry[0], p.n_particles, NOISE, rng, RESAMPLING, RESAMPLE_THRESHOLD)
    with cpu_threads(TORCH_THREADS if device == "cpu" else 0):
        return f.run(odometry_increments(odometry), scans, observer=observer,  # type: ignore[arg-type]
                     on_step=on_step)


def map_along(
    poses: F64, scans: Sequence[BeamSamples], basis: hm.HilbertBasis, m: MapParams
) -> tuple[F64, F64]:
    """One Hilbert map built along fixed poses (mapping with known poses; used for non-Hilbert methods)."""
    theta, cov = hm.prior(basis, m.lengthscale_m, m.signal_variance)
    for pose, s in zip(poses, scans, strict=True):
        if s.n:
            phi = hm.features(basis, to_world(pose, s.points))
            theta, cov = hm.kalman_update(theta, cov, phi, s.labels, m.noise_variance, inplace=True)
    return theta, cov
