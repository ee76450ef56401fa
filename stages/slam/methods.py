"""The stage's filter methods on numpy inputs: odometry pass-through, FastSLAM with grids (the paper's FastSLAM-Radar
baseline), RICH-SLAM as the paper configures it and its two ablations of Table III.

Pure functions (no I/O): the stage reads artifacts, builds body-frame beam samples per scan and the
odometry poses, and calls :func:`run_method`. ``radar_graph`` is :mod:`pose_graph`'s.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from core import hilbert_map as hm
from stages.slam.backend import Backend, Device, resolve_device
from stages.slam.beam_sampling import BeamSamples, to_world
from stages.slam.grid_map import GridModel, GridParticleMaps, make_grid_spec
from stages.slam.parallel import ParallelHilbertMaps
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

Method = Literal["odometry", "radar_graph", "fastslam_grid", "rich_slam", "rich_slam_no_et", "rich_slam_mean_only"]
METHODS: tuple[Method, ...] = ("odometry", "radar_graph", "fastslam_grid", "rich_slam", "rich_slam_no_et",
                               "rich_slam_mean_only")
#: RICH-SLAM (Sec. IV) and its Table III ablations: without endpoint tolerance, and the mean-only weight of H-SLAM
HILBERT_METHODS = ("rich_slam", "rich_slam_no_et", "rich_slam_mean_only")
#: methods that are not particle filters (:mod:`pose_graph`; the slam stage runs them on their own inputs)
GRAPH_METHODS = ("radar_graph",)
#: the paper's endpoint tolerance radius r_e (m, Sec. IV-D2: "we set r_e = 0.25 m")
PAPER_ENDPOINT_TOLERANCE = 0.25
F64 = npt.NDArray[np.floating[Any]]


@dataclass(frozen=True)
class SlamConfig:
    """What the filter methods need, in metres and radians (defaults: the paper's, Table II and Sec. IV)."""

    n_particles: int = 200
    lengthscale_m: float = 2.0
    signal_variance: float = 16.0
    noise_variance: float = 0.36
    n_basis: int = 256
    basis_kind: hm.BasisKind = "tensor"
    endpoint_tolerance: float = PAPER_ENDPOINT_TOLERANCE
    et_ring_points: int = 8
    et_rings: int = 1
    et_variance: Literal["exact", "taylor"] = "taylor"
    #: the proposal: GMapping's motion model fitted to the odometry increment (eq. 21)
    noise: MotionNoise = field(default_factory=MotionNoise)
    resampling: Resampling = "systematic"
    resample_threshold: float = 0.5
    map_update: Literal["kalman", "laplace"] = "kalman"
    map_form: Literal["auto", "information", "covariance"] = "auto"
    laplace_iterations: int = 20
    dtype: Literal["float64", "float32"] = "float64"
    workers: int = 2
    #: array backend of the Hilbert methods' particle maps and filter loop, and its device
    backend: Backend = "numpy"
    device: Device = "auto"
    #: torch CPU threads (0: torch's default, one per core)
    torch_threads: int = 1
    grid: GridModel = field(default_factory=GridModel)
    grid_resolution: float = 0.1

    def map_model(self, method: str, form: Literal["information", "covariance"] = "information") -> MapModel:
        """The particle maps' parameter object of a Hilbert method (every backend takes it)."""
        return MapModel(self.lengthscale_m, self.signal_variance, self.noise_variance, self.weighting(method),
                        update=self.map_update, dtype=np.dtype(self.dtype), laplace_iterations=self.laplace_iterations,
                        form=form)

    def weighting(self, method: str) -> HilbertWeighting:
        """Eq. 28-29 for ``rich_slam``; r_e = 0 for ``rich_slam_no_et``; the mean only for ``rich_slam_mean_only``."""
        return HilbertWeighting(
            use_variance=method != "rich_slam_mean_only",
            endpoint_tolerance=0.0 if method == "rich_slam_no_et" else self.endpoint_tolerance,
            ring_points=self.et_ring_points,
            rings=self.et_rings,
            et_variance=self.et_variance,
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


def choose_form(cfg: SlamConfig, method: str, scans: Sequence[BeamSamples], M: int,
                info_efficiency: float = 0.75) -> Literal["information", "covariance"]:
    """``auto``: the form with the smaller modelled cost at the sequence's mean samples per scan.

    The information form's kernels (potrf, trsm on 256 x 256, one pass per scan) run at about
    ``info_efficiency`` of the rate of the covariance form's (symm, syrk, small products), measured
    side by side at 12, 61 and 180 samples per scan (N_p = 200, M = 256, 2 workers: 0.074 / 0.163 /
    0.334 s per scan against 0.054 / 0.162 / 0.666); the crossover is near 65 samples per scan.
    """
    if cfg.map_form != "auto":
        return cfg.map_form
    n = float(np.mean([s.n for s in scans])) if len(scans) else 0.0
    b = float(np.mean([len(s.endpoints) for s in scans])) if len(scans) else 0.0
    w = cfg.weighting(method)
    info = step_flops("information", n, b, M, w) / info_efficiency
    return "information" if info < step_flops("covariance", n, b, M, w) else "covariance"


def make_hilbert_maps(cfg: SlamConfig, basis: hm.HilbertBasis, method: str, n_particles: int,
                      form: Literal["information", "covariance"] = "information",
                      ) -> HilbertParticleMaps | ParallelHilbertMaps:
    """The particle maps of a Hilbert method: one global map over ``basis`` per particle, in ``workers``
    processes when ``workers > 0``."""
    factory: Callable[..., HilbertParticleMaps | ParallelHilbertMaps] = (
        partial(ParallelHilbertMaps, workers=cfg.workers) if cfg.workers > 0 else HilbertParticleMaps)
    return factory(basis, n_particles, cfg.map_model(method, form))


Observer = Callable[[int, RBPF, int], None]


def run_method(
    method: str,
    odometry: F64,
    scans: Sequence[BeamSamples],
    basis: hm.HilbertBasis,
    cfg: SlamConfig,
    seed: int,
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
    rng = np.random.default_rng(seed)
    form: Literal["information", "covariance"] = "information"
    maps: GridParticleMaps | HilbertParticleMaps | ParallelHilbertMaps | None = None
    if method == "fastslam_grid":
        spec = make_grid_spec(basis.centre, basis.half_widths, cfg.grid_resolution)
        maps = GridParticleMaps(spec, cfg.n_particles, cfg.grid)
    elif method in HILBERT_METHODS:
        form = choose_form(cfg, method, scans, basis.M)
        if cfg.backend == "numpy":
            maps = make_hilbert_maps(cfg, basis, method, cfg.n_particles, form)
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
        device = resolve_device(cfg.backend, cfg.device)[0]
        h = _run_torch(cfg, basis, method, form, device, odometry, scans, rng, keep_best, on_step)
    else:
        try:
            f = RBPF(maps, odometry[0], cfg.n_particles, cfg.noise, rng, cfg.resampling, cfg.resample_threshold)
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


def _run_torch(cfg: SlamConfig, basis: hm.HilbertBasis, method: str, form: Literal["information", "covariance"],
               device: str, odometry: F64, scans: Sequence[BeamSamples], rng: np.random.Generator,
               observer: Observer, on_step: Callable[[], None] | None) -> FilterHistory:
    """The Hilbert method's filter on the torch backend (imported only here: torch is optional)."""
    from stages.slam.torch_filter import TorchRBPF, cpu_threads
    from stages.slam.torch_maps import TorchHilbertMaps

    if cfg.map_update != "kalman":
        raise ValueError("the torch backend implements the Kalman map update; use backend = numpy for laplace")
    maps = TorchHilbertMaps(basis, cfg.n_particles, cfg.map_model(method, form), device=device)
    f = TorchRBPF(maps, odometry[0], cfg.n_particles, cfg.noise, rng, cfg.resampling, cfg.resample_threshold)
    with cpu_threads(cfg.torch_threads if device == "cpu" else 0):
        return f.run(odometry_increments(odometry), scans, observer=observer,  # type: ignore[arg-type]
                     on_step=on_step)


def map_along(
    poses: F64, scans: Sequence[BeamSamples], basis: hm.HilbertBasis, cfg: SlamConfig
) -> tuple[F64, F64]:
    """One Hilbert map built along fixed poses (mapping with known poses; used for non-Hilbert methods)."""
    theta, cov = hm.prior(basis, cfg.lengthscale_m, cfg.signal_variance)
    for pose, s in zip(poses, scans, strict=True):
        if s.n:
            phi = hm.features(basis, to_world(pose, s.points))
            theta, cov = hm.kalman_update(theta, cov, phi, s.labels, cfg.noise_variance, inplace=True)
    return theta, cov
