"""The stage's methods on numpy inputs: odometry pass-through, FastSLAM with grids, RICH-SLAM and ablations.

Pure functions (no I/O): the stage reads artifacts, builds body-frame beam samples per scan and the
odometry poses, and calls :func:`run_method`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any, Literal, NamedTuple

import numpy as np
import numpy.typing as npt

from stages.slam import hilbert_map as hm
from stages.slam.backend import Backend, Device, resolve_device
from stages.slam.beam_sampling import BeamSamples, to_world
from stages.slam.delayed_maps import DelayedMaps
from stages.slam.grid_map import GridModel, GridParticleMaps, make_grid_spec
from stages.slam.heading_fusion import HeadingFusion, fuse_heading, informed, recompose
from stages.slam.heading_information import yaw_information
from stages.slam.map_consistency import MapConsistency, consistent_scale, stacked_endpoints
from stages.slam.parallel import ParallelHilbertMaps, submap_factory
from stages.slam.pose_refinement import PoseRefinement
from stages.slam.rbpf import (
    RBPF,
    FilterHistory,
    HilbertParticleMaps,
    HilbertWeighting,
    MapModel,
    MotionNoise,
    Proposal,
    Resampling,
    WideMode,
    YawBias,
    odometry_increments,
)
from stages.slam.submaps import HybridParticleMaps, SubmapModel, SubmapParticleMaps

Method = Literal["odometry", "radar_graph", "fastslam_grid", "rich_slam", "rich_slam_no_et", "rich_slam_mean_only",
                 "rich_slam_refined", "rich_slam_paper"]
METHODS: tuple[Method, ...] = ("odometry", "radar_graph", "fastslam_grid", "rich_slam", "rich_slam_no_et",
                               "rich_slam_mean_only", "rich_slam_refined", "rich_slam_paper")
HILBERT_METHODS = ("rich_slam", "rich_slam_no_et", "rich_slam_mean_only", "rich_slam_refined", "rich_slam_paper")
#: methods that are not particle filters (:mod:`pose_graph`; the slam stage runs them on their own inputs)
GRAPH_METHODS = ("radar_graph",)
#: the paper's configuration (Sec. IV): the fixed GMapping-form proposal, no bias state, one global map
PAPER_METHODS = ("rich_slam_paper",)
#: the paper's endpoint tolerance radius r_e (m, Sec. IV-D2: "we set r_e = 0.25 m"), which ``rich_slam_paper`` keeps
PAPER_ENDPOINT_TOLERANCE = 0.25
#: how a filter's trajectory is read from its particles (``SlamConfig.estimate``)
Estimate = Literal["best_per_scan", "final_best_history", "weighted_mean", "smoothed", "fused"]
ESTIMATES: tuple[Estimate, ...] = ("best_per_scan", "final_best_history", "weighted_mean", "smoothed", "fused")
ProposalKind = Literal["odometry_covariance", "gmapping"]
#: methods whose particles are refined against their own maps before weighting (pose_refinement.py)
REFINED_METHODS = ("rich_slam_refined",)
F64 = npt.NDArray[np.floating[Any]]


@dataclass(frozen=True)
class SlamConfig:
    """Everything a method needs, in metres and radians."""

    n_particles: int = 200
    lengthscale_m: float = 2.0
    signal_variance: float = 16.0
    noise_variance: float = 0.36
    n_basis: int = 256
    basis_kind: hm.BasisKind = "tensor"
    endpoint_tolerance: float = 0.25
    et_ring_points: int = 8
    et_rings: int = 1
    et_variance: Literal["exact", "taylor"] = "taylor"
    likelihood_exponent: float = 1.0
    #: the grid filter's (fastslam_grid) exponent on its scan likelihood
    grid_likelihood_exponent: float = 1.0
    noise: MotionNoise = field(default_factory=MotionNoise)
    #: the filters' proposal: the odometry's own increment covariance (needs :class:`OdometryMotion`) or
    #: GMapping's fitted form (``noise``); ``rich_slam_paper`` always takes ``gmapping``. The pure default is
    #: the fitted form; the slam stage's default is ``odometry_covariance``.
    proposal: ProposalKind = "gmapping"
    #: factor on the odometry's increment covariance in the ``odometry_covariance`` proposal (1: as written)
    proposal_scale: float = 1.0
    #: a wide mode (GMapping's ``noise``) for a share of the particles beside the ``odometry_covariance`` proposal
    #: (None: off; never ``rich_slam_paper`` nor ``rich_slam_refined``)
    wide: WideMode | None = None
    #: each particle's yaw-rate bias state (None: none); ``rich_slam_paper`` never has one
    yaw_bias: YawBias | None = None
    resampling: Resampling = "systematic"
    resample_threshold: float = 0.5
    #: resampling keeps the weighted mean pose (:func:`rbpf.restore_mean`); ``rich_slam_paper`` never
    resample_keep_mean: bool = False
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
    #: the trajectory written: the largest-weight particle per scan (Algorithm 1 line 9), the final best
    #: particle's history, or the weighted mean pose per scan; ``rich_slam_paper`` always takes the first
    estimate: Estimate = "best_per_scan"
    #: the Laplace proposal of the refined method (``rich_slam_refined``); the others use eq. 21's
    refinement: PoseRefinement = field(default_factory=lambda: PoseRefinement(iterations=3))
    #: weight of the free samples' log terms against the endpoints' (1: the paper, eq. 23)
    free_weight: float = 1.0
    #: common support (:func:`rbpf.common_support_total`): only samples whose predictive variance is below this for
    #: every particle are scored (None: all, the paper; ``rich_slam_paper`` always)
    support_variance: float | None = None
    #: probability that a sample is not explained by the map (:attr:`rbpf.HilbertWeighting.outlier`; 0: the
    #: paper, ``rich_slam_paper`` always)
    outlier: float = 0.0
    #: sigma_n^2 of the endpoints' +1 labels in the map update (None: ``noise_variance`` for all, eq. 15)
    endpoint_noise_variance: float | None = None
    #: the Hilbert filters' particle maps: local submaps (:mod:`submaps`) or None, one global map over the
    #: trajectory's envelope (the paper; ``rich_slam_paper`` always)
    submaps: SubmapModel | None = None
    #: SE length scale of the submaps (m); the global map takes ``lengthscale_m``
    submap_lengthscale_m: float = 1.0
    #: with submaps: the share of each scan's log-likelihood taken against them; the rest against the global
    #: map, which is then kept too (1: submaps alone)
    submap_share: float = 1.0
    #: the share of each scan's log-likelihood that the Hilbert methods take from a FastSLAM occupancy grid that
    #: every particle carries beside its global Hilbert map (0: none, the paper; ``rich_slam_paper`` always)
    grid_share: float = 0.0
    #: weigh each scan against the map without its last ``map_delay`` scans (:mod:`delayed_maps`; 0: off)
    map_delay: int = 0
    #: the error models of the ``fused`` estimate (:mod:`heading_fusion`)
    fusion: HeadingFusion = field(default_factory=HeadingFusion)
    #: the scale of the fused correction chosen by the radar map's self-consistency (:mod:`map_consistency`)
    consistency: MapConsistency = field(default_factory=MapConsistency)
    #: the informed exponent (:func:`informed_exponent`): a Hilbert filter whose weight's median yaw information
    #: along the odometry is at least this (rad^-2, at ``likelihood_exponent``) runs with
    #: ``informed_likelihood_exponent`` instead (None: off; never ``rich_slam_paper`` nor ``rich_slam_refined``)
    informed_exponent_information: float | None = None
    informed_likelihood_exponent: float = 1.0

    def for_method(self, method: str) -> SlamConfig:
        """The configuration a method runs with: ``rich_slam_paper`` (:data:`PAPER_METHODS`) is the paper's
        whatever the settings (the GMapping proposal, no bias state, Algorithm 1's largest-weight particle,
        eq. 22 with exponent 1, r_e = 0.25 m, one global map); ``rich_slam_refined`` always has the global map,
        undelayed; every other method runs with this one."""
        if method in REFINED_METHODS:
            # the refinement works on one basis, the global map, and reads its means: no submaps, no delayed map
            return replace(self, submaps=None, map_delay=0, informed_exponent_information=None, wide=None)
        if method not in PAPER_METHODS:
            return self
        return replace(self, proposal="gmapping", yaw_bias=None, wide=None, estimate="best_per_scan",
                       likelihood_exponent=1.0, informed_exponent_information=None,
                       submaps=None, support_variance=None, resample_keep_mean=False, outlier=0.0,
                       grid_share=0.0, map_delay=0, endpoint_tolerance=PAPER_ENDPOINT_TOLERANCE)

    def map_model(self, method: str, form: Literal["information", "covariance"] = "information") -> MapModel:
        """The particle maps' parameter object of a Hilbert method (every backend takes it)."""
        return MapModel(self.lengthscale_m, self.signal_variance, self.noise_variance, self.weighting(method),
                        update=self.map_update, dtype=np.dtype(self.dtype), laplace_iterations=self.laplace_iterations,
                        form=form, endpoint_noise_variance=self.endpoint_noise_variance)

    def weighting(self, method: str) -> HilbertWeighting:
        return HilbertWeighting(
            use_variance=method != "rich_slam_mean_only",
            endpoint_tolerance=0.0 if method == "rich_slam_no_et" else self.endpoint_tolerance,
            ring_points=self.et_ring_points,
            rings=self.et_rings,
            et_variance=self.et_variance,
            exponent=self.likelihood_exponent,
            free_weight=self.free_weight,
            support_variance=self.support_variance,
            outlier=0.0 if method in PAPER_METHODS else self.outlier,
        )


@dataclass(frozen=True)
class OdometryMotion:
    """What the proposal takes from the odometry besides its poses: per-pose increment covariance
    ``cov (T, 3, 3)`` (body frame, into pose i; row 0 unused) and the intervals ``dt (T,)`` in seconds."""

    cov: F64
    dt: F64


def make_proposal(method: str, cfg: SlamConfig, motion: OdometryMotion | None, rng: np.random.Generator
                  ) -> Proposal:
    """The proposal of a filter method under ``cfg`` (``rich_slam_paper``'s: :meth:`SlamConfig.for_method`)."""
    cfg = cfg.for_method(method)
    kind, bias = cfg.proposal, cfg.yaw_bias
    if (kind == "odometry_covariance" or bias is not None) and motion is None:
        raise ValueError(f"{method}: proposal = {kind}{' with the yaw-rate bias state' if bias else ''} needs the "
                         f"odometry's increment covariance and scan intervals (OdometryMotion)")
    cov = motion.cov * cfg.proposal_scale if kind == "odometry_covariance" and motion is not None else None
    return Proposal(cfg.noise, cfg.n_particles, rng, cov=cov, dt=None if motion is None else motion.dt, bias=bias,
                    wide=cfg.wide if cov is not None else None)


@dataclass
class MethodResult:
    """A method's trajectory (one pose per scan), filter diagnostics and, for Hilbert methods, the final maps."""

    method: str
    poses: F64  # (T, 3)
    n_eff: F64  # (T,)
    seconds: float
    resampled: int = 0
    particles: F64 | None = None  # (T, Np, 3)
    theta: F64 | None = None  # best particle's final map
    cov: F64 | None = None
    form: str = ""  # map form of the Hilbert methods
    device: str = "cpu"  # where the Hilbert methods' filter ran (``cpu`` or ``cuda``)
    yaw_bias: F64 | None = None  # (T,) weighted mean of the particles' yaw-rate bias (bias state only)
    #: every estimate of the trajectory from the same run (``poses`` is the configured one's)
    estimates: dict[str, F64] = field(default_factory=dict)
    #: submaps the filter opened (``cfg.submaps``; 0 with the global map)
    submaps_opened: int = 0
    #: scans weighed against a closed submap (``submap_keep_closed``: loop closures)
    submap_revisits: int = 0
    #: scans where the fused estimate found the filter's heading jumping (:func:`heading_fusion.fuse_heading`)
    fusion_jumps: int = 0
    #: the fused estimate's model of the filter's heading error: its std (deg, :func:`heading_fusion.informed`) and
    #: the median per-scan yaw information of the method's weight along the odometry (rad^-2; None: not computed)
    fusion_filter_sigma_deg: float | None = None
    heading_information: float | None = None
    #: the exponent on the scan likelihood the filter ran with (Hilbert methods; :func:`informed_exponent`)
    likelihood_exponent: float | None = None
    #: the scale of the fusion's heading correction that the fused estimate applies (:func:`fused_estimate`)
    fusion_alpha: float | None = None
    #: the chosen scale's gain over the odometry in standard errors (``slam.fusion_alpha_guard`` on only)
    fusion_alpha_evidence: float | None = None
    #: (T,) the weight on the particles in the wide mode per scan (``cfg.wide`` only)
    wide_share: F64 | None = None


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
                      ) -> (HilbertParticleMaps | ParallelHilbertMaps | SubmapParticleMaps | HybridParticleMaps
                            | DelayedMaps):
    """The particle maps of a Hilbert method: one global map over ``basis``, local submaps when ``cfg.submaps`` is
    set, or both (``cfg.submap_share < 1``); each map in ``workers`` processes when ``workers > 0``."""
    factory: Callable[..., HilbertParticleMaps | ParallelHilbertMaps] = (
        partial(ParallelHilbertMaps, workers=cfg.workers) if cfg.workers > 0 else HilbertParticleMaps)
    if cfg.grid_share > 0 and method not in (*PAPER_METHODS, *REFINED_METHODS):
        if cfg.submaps is not None:
            raise ValueError("slam.grid_share takes the global Hilbert map: set slam.map = global")
        grid = GridParticleMaps(make_grid_spec(basis.centre, basis.half_widths, cfg.grid_resolution), n_particles,
                                cfg.grid, cfg.grid_likelihood_exponent)
        return HybridParticleMaps(factory(basis, n_particles, cfg.map_model(method, form)), grid, cfg.grid_share)
    if cfg.submaps is None:
        maps = factory(basis, n_particles, cfg.map_model(method, form))
        return DelayedMaps(maps, cfg.map_delay) if cfg.map_delay > 0 and method not in PAPER_METHODS else maps
    model = replace(cfg.map_model(method, form), lengthscale=cfg.submap_lengthscale_m)
    local = (SubmapParticleMaps(cfg.submaps, submap_factory(n_particles, model, cfg.workers), cfg.basis_kind,
                                weighting=model.weighting)
             if cfg.workers > 0 else SubmapParticleMaps.create(cfg.submaps, n_particles, model, cfg.basis_kind))
    if cfg.submap_share >= 1.0:
        return local
    return HybridParticleMaps(factory(basis, n_particles, cfg.map_model(method, form)), local, cfg.submap_share)


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
    motion: OdometryMotion | None = None,
    wrap_maps: Callable[[Any], Any] | None = None,
) -> MethodResult:
    """Run one method over the scans; ``odometry (T, 3)`` are world <- base poses at the scan times, ``motion``
    their increment covariance and intervals (needed by ``proposal = odometry_covariance`` and the bias state).
    ``wrap_maps``: applied to the particle maps before the filter starts (numpy backend; diagnostics such as
    :mod:`weight_pull` wrap them to record shadow weights)."""
    t0 = time.perf_counter()
    cfg = cfg.for_method(method)
    odometry = np.asarray(odometry, dtype=np.float64).reshape(-1, 3)
    if method == "odometry":
        if on_step is not None:
            for _ in range(len(odometry)):
                on_step()
        odo_poses = odometry.copy()
        return MethodResult(method, odo_poses, np.ones(len(odometry)), time.perf_counter() - t0,
                            estimates=dict.fromkeys(ESTIMATES, odo_poses))
    rng = np.random.default_rng(seed)
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; one of {', '.join(METHODS)}")
    if cfg.estimate == "fused" and motion is None:  # refused before the filter runs, not after
        raise ValueError(f"{method}: estimate = fused needs the odometry's increment covariance (odometry stage v4); "
                         "rerun `pipeline run odometry --force` or set slam.estimate = smoothed")
    cfg = informed_exponent(method, cfg, basis, odometry, scans)
    proposal = make_proposal(method, cfg, motion, rng)
    form: Literal["information", "covariance"] = "information"
    maps: (GridParticleMaps | HilbertParticleMaps | ParallelHilbertMaps | SubmapParticleMaps | HybridParticleMaps
           | DelayedMaps | None) = None
    if method == "fastslam_grid":
        spec = make_grid_spec(basis.centre, basis.half_widths, cfg.grid_resolution)
        maps = GridParticleMaps(spec, cfg.n_particles, cfg.grid, cfg.grid_likelihood_exponent)
    elif method in HILBERT_METHODS:
        form = choose_form(cfg, method, scans, cfg.submaps.n_basis if cfg.submaps else basis.M)
        if cfg.submaps is not None and cfg.backend != "numpy":
            raise ValueError(f"{method}: submaps run on the numpy backend only; set slam.map = global or "
                             "slam.backend = numpy")
        if cfg.backend == "numpy":
            maps = make_hilbert_maps(cfg, basis, method, cfg.n_particles, form)
    else:
        raise ValueError(f"unknown method {method!r}; one of {', '.join(METHODS)}")
    if wrap_maps is not None and maps is not None:
        maps = wrap_maps(maps)
    best_map: dict[str, F64] = {}

    def keep_best(i: int, f: Any, best: int) -> None:
        if i == len(odometry) - 1 and hasattr(f.maps, "map_of"):
            best_map["theta"], best_map["cov"] = f.maps.map_of(best)
        if observer is not None:
            observer(i, f, best)

    device = "cpu"
    if maps is None:
        device = resolve_device(cfg.backend, cfg.device)[0]
        h = _run_torch(cfg, basis, method, form, device, odometry, scans, rng, keep_best, on_step, proposal)
    else:
        try:
            refinement = cfg.refinement if method in REFINED_METHODS else None
            f = RBPF(maps, odometry[0], cfg.n_particles, cfg.noise, rng, cfg.resampling, cfg.resample_threshold,
                     refinement=refinement, basis=basis, exponent=cfg.likelihood_exponent, proposal=proposal,
                     keep_mean=cfg.resample_keep_mean)
            h = f.run(odometry_increments(odometry), scans, observer=keep_best, on_step=on_step)
        finally:
            close = getattr(maps, "close", None)
            if close is not None:
                close()
    estimates = {"best_per_scan": h.best_trajectory(), "final_best_history": h.final_best_history(),
                 "weighted_mean": h.mean_trajectory(), "smoothed": h.smoothed_trajectory()}
    fusion_jumps, alpha, evidence = 0, None, None
    fusion, information = cfg.fusion, None
    if motion is not None:
        fusion, information = informed_fusion(method, cfg, basis, odometry, scans)
        estimates["fused"], fusion_jumps, alpha, ev = fused_estimate(odometry, estimates["smoothed"], motion, fusion,
                                                                     scans, cfg.consistency)
        evidence = None if np.isnan(ev) else float(min(ev, 1e9))  # nan: no guard, or nothing searched; JSON-safe
    poses = estimates[cfg.estimate]
    sigma_deg, median_information = fusion_record(fusion, information) if motion is not None else (None, None)
    return MethodResult(
        method, poses, np.asarray(h.n_eff), time.perf_counter() - t0, int(np.sum(h.resampled)),
        np.asarray(h.particles), best_map.get("theta"), best_map.get("cov"),
        form if method in HILBERT_METHODS else "", device,
        np.asarray(h.yaw_bias) if proposal.bias is not None else None, estimates,
        *_submap_counts(maps), fusion_jumps, sigma_deg, median_information,
        likelihood_exponent=cfg.likelihood_exponent if method in HILBERT_METHODS else None, fusion_alpha=alpha,
        fusion_alpha_evidence=evidence, wide_share=np.asarray(h.wide_share) if proposal.wide is not None else None,
    )


def informed_exponent(method: str, cfg: SlamConfig, basis: hm.HilbertBasis, odometry: F64,
                      scans: Sequence[BeamSamples]) -> SlamConfig:
    """``cfg`` with eq. 22's exponent chosen by the weight's heading information (stop 49): a Hilbert filter
    whose weight's median yaw information along the odometry (:func:`weight_information`, at
    ``likelihood_exponent``) is at least ``informed_exponent_information`` runs with
    ``informed_likelihood_exponent``: a weight that holds the heading is tempered less. The switch is read
    once, before the filter, from the odometry and the scans alone; ``cfg`` itself where it is off."""
    cfg = cfg.for_method(method)
    if cfg.informed_exponent_information is None or method not in HILBERT_METHODS:
        return cfg
    information = weight_information(method, cfg, basis, odometry, scans)
    high = information.size > 0 and float(np.median(information)) >= cfg.informed_exponent_information
    return replace(cfg, informed_exponent_information=None,
                   likelihood_exponent=cfg.informed_likelihood_exponent if high else cfg.likelihood_exponent)


def fusion_record(model: HeadingFusion, information: F64 | None) -> tuple[float, float | None]:
    """What a fused row records of its model (:func:`informed_fusion`): the fusion's filter-error std (deg) and
    the weight's median heading information (rad^-2; None where none was computed). The filter run and
    ``table3 --from-kept`` both take it from here."""
    return float(np.degrees(model.filter_sigma)), None if information is None else float(np.median(information))


def weight_information(method: str, cfg: SlamConfig, basis: hm.HilbertBasis, odometry: F64,
                       scans: Sequence[BeamSamples]) -> F64:
    """Per-scan yaw information of ``method``'s own weight along the odometry
    (:func:`heading_information.yaw_information`, three particles of its map model in the form its filter would
    take, in process: 2-3 % of a 200-particle rich_slam run); the fused estimate's :func:`heading_fusion.informed`
    reads it."""
    cfg = replace(cfg.for_method(method), workers=0)
    maps: GridParticleMaps | HilbertParticleMaps | ParallelHilbertMaps | SubmapParticleMaps | HybridParticleMaps \
        | DelayedMaps
    if method == "fastslam_grid":
        maps = GridParticleMaps(make_grid_spec(basis.centre, basis.half_widths, cfg.grid_resolution), 3, cfg.grid,
                                cfg.grid_likelihood_exponent)
    elif method in HILBERT_METHODS:
        maps = make_hilbert_maps(cfg, basis, method, 3, choose_form(cfg, method, scans, basis.M))
    else:
        raise ValueError(f"weight_information: {method!r} has no scan weight")
    return yaw_information(maps, odometry, scans)


def informed_fusion(method: str, cfg: SlamConfig, basis: hm.HilbertBasis, odometry: F64,
                    scans: Sequence[BeamSamples]) -> tuple[HeadingFusion, F64 | None]:
    """``cfg.fusion`` widened by ``method``'s weight information along the odometry (:func:`weight_information`,
    :func:`heading_fusion.informed`), and that information; ``cfg.fusion`` and None when
    ``fusion.information_ref`` is 0. The filter run and ``table3 --from-kept`` both take the model from here."""
    if cfg.fusion.information_ref <= 0:
        return cfg.fusion, None
    information = weight_information(method, cfg, basis, odometry, scans)
    return informed(cfg.fusion, information), information


class FusedEstimate(NamedTuple):
    """:func:`fused_estimate`'s result."""

    poses: F64  # (T, 3) the fused trajectory
    jumps: int  # scans where the filter's heading jumped (``HeadingFusion.jump_gate``)
    alpha: float  # the scale of the fusion's correction applied
    evidence: float = float("nan")  # the best scale's gain in standard errors (``MapConsistency.guard`` on only)


def fused_estimate(odometry: F64, smoothed: F64, motion: OdometryMotion, model: HeadingFusion,
                   scans: Sequence[BeamSamples] = (), consistency: MapConsistency | None = None
                   ) -> FusedEstimate:
    """The ``fused`` estimate: the smoother's heading fused with the odometry's (:func:`heading_fusion.fuse_heading`,
    with the odometry's per-scan increment yaw variances), its correction of the odometry's heading scaled by the
    ``alpha`` that makes the scans' endpoints most consistent (:func:`map_consistency.consistent_scale`; 1 where
    ``consistency.alpha_max`` is 0 or no scans are given), the odometry's increments composed along it; the
    number of scans where the filter's heading jumped (``HeadingFusion.jump_gate``); ``alpha``; and, with the
    scale's guard on, its evidence (:class:`map_consistency.ScaleChoice`)."""
    t_s = np.cumsum(motion.dt)
    fused = fuse_heading(t_s, odometry[:, 2], smoothed[:, 2], motion.cov[:, 2, 2], model)
    alpha, evidence = 1.0, float("nan")
    if consistency is not None and consistency.alpha_max > 0 and len(scans):
        if len(scans) != len(odometry):
            raise ValueError(f"fused_estimate: {len(scans)} scans for {len(odometry)} odometry poses")
        points, scan = stacked_endpoints(scans)
        alpha, _, _, evidence = consistent_scale(odometry, fused.correction, points, scan, t_s, consistency)
    return FusedEstimate(recompose(odometry, alpha * fused.correction), fused.jumps, alpha, evidence)


def _submap_counts(maps: Any) -> tuple[int, int]:
    """Submaps opened and scans weighed against a closed one (0, 0 with the global map)."""
    local = maps.local if isinstance(maps, HybridParticleMaps) else maps
    return (local.opened, local.revisits) if isinstance(local, SubmapParticleMaps) else (0, 0)


def _run_torch(cfg: SlamConfig, basis: hm.HilbertBasis, method: str, form: Literal["information", "covariance"],
               device: str, odometry: F64, scans: Sequence[BeamSamples], rng: np.random.Generator,
               observer: Observer, on_step: Callable[[], None] | None, proposal: Proposal) -> FilterHistory:
    """The Hilbert method's filter on the torch backend (imported only here: torch is optional)."""
    from stages.slam.torch_filter import TorchRBPF, cpu_threads
    from stages.slam.torch_maps import TorchHilbertMaps

    if cfg.map_update != "kalman":
        raise ValueError("the torch backend implements the Kalman map update; use backend = numpy for laplace")
    if method in REFINED_METHODS:
        raise ValueError(f"{method} (pose refinement) runs on the numpy backend only; set slam.backend = numpy")
    if cfg.endpoint_noise_variance is not None:
        raise ValueError("endpoint_noise_variance runs on the numpy backend only; set slam.backend = numpy")
    maps = TorchHilbertMaps(basis, cfg.n_particles, cfg.map_model(method, form), device=device)
    f = TorchRBPF(maps, odometry[0], cfg.n_particles, cfg.noise, rng, cfg.resampling, cfg.resample_threshold,
                  proposal=proposal, keep_mean=cfg.resample_keep_mean)
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
            theta, cov = hm.kalman_update(theta, cov, phi, s.labels, hm.label_noise_variance(
                s.labels, cfg.noise_variance, cfg.endpoint_noise_variance), inplace=True)
    return theta, cov
