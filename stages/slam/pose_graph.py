"""`radar_graph`: a keyframe pose graph with radar-verified loop closures. Pure numpy + GTSAM.

The odometry (EKF-RIO) gives keyframes by distance and angle travelled and a relative-pose factor between
consecutive keyframes with its own increment covariance, propagated along the scans. Each keyframe holds the
radar endpoints of the scans nearest to it, accumulated along the odometry into the keyframe's frame (single TI
scans hold 30-100 points). Loop closures are proposed between keyframes that are close in the odometry's
estimate but far apart along the path, verified by registering the later one's local cloud against the earlier
pass with a wide yaw search (:mod:`registration`, a correlative scan matcher whose search gives the
covariance), and optimised with graduated non-convexity (Yang et al., RA-L 2020, the truncated quadratic) on
the closures, which drops a wrong one.
The odometry's heading drifts with the gyro bias its filter did not remove: each keyframe carries a yaw-rate bias
(a random walk, GTSAM variables beside the poses) that corrects the odometry factor's yaw over its interval, so a
closure corrects a drift that grows with time instead of bending the chain where the closure pulls. Every scan's
pose is its odometry pose moved by the correction of its two keyframes, interpolated on SE(2).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal, NamedTuple

import numpy as np
import numpy.typing as npt

from stages.slam.params import GraphParams
from stages.slam.registration import MatcherModel, match
from stages.slam.se2 import between, compose, wrap_angle

F64 = npt.NDArray[np.floating[Any]]
I64 = npt.NDArray[np.int64]

GTSAM_INSTALL = "pip install gtsam"


#: fewest endpoints in either local cloud of a loop candidate
MIN_LOOP_POINTS = 30
#: keyframes between loop searches of the same place
LOOP_EVERY = 2


def matcher_of(g: GraphParams) -> MatcherModel:
    """The registration's model with the graph's likelihood-field settings."""
    return MatcherModel(sigma=g.match_sigma, temperature=g.match_temperature)


@dataclass(frozen=True)
class Edge:
    """A factor between keyframes ``i`` and ``j``: relative pose ``z`` (pose of ``j`` in ``i``'s frame)."""

    kind: Literal["odometry", "loop"]
    i: int
    j: int
    z: F64  # (3,)
    cov: F64  # (3, 3) in j's body frame
    inliers: float = 1.0
    accepted: bool = True
    dt: float = 0.0  # s between the keyframes (odometry factors: the interval the yaw-rate bias acts over)


@dataclass
class GraphResult:
    """The optimised trajectory at every scan, the keyframes and the graph's edges."""

    poses: F64  # (T, 3) every scan
    keyframes: I64  # (K,) scan indices of the keyframes
    keyframe_poses: F64  # (K, 3) optimised
    keyframe_cov: F64  # (K, 3, 3) marginal covariances (body frame)
    edges: list[Edge]
    bias: F64 = field(default_factory=lambda: np.zeros(0))  # (K,) yaw-rate bias at each keyframe (rad/s)
    warnings: list[str] = field(default_factory=list)

    def count(self, kind: str, accepted: bool | None = None) -> int:
        return sum(e.kind == kind and (accepted is None or e.accepted == accepted) for e in self.edges)


# -- SE(2) on arrays ------------------------------------------------------------------------------------------------


def transform(pose: F64, points: F64) -> F64:
    """Points ``(N, 2)`` in ``pose``'s frame to the parent frame."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return points @ np.array([[c, s], [-s, c]]) + pose[:2]


def adjoint(d: F64) -> F64:
    """GTSAM's ``Pose2::AdjointMap`` of the pose ``d`` (tangent order x, y, yaw)."""
    c, s = np.cos(d[2]), np.sin(d[2])
    return np.array([[c, -s, d[1]], [s, c, -d[0]], [0.0, 0.0, 1.0]])


def propagate(increments: F64, cov: F64) -> tuple[F64, F64]:
    """Compose body-frame ``increments (n, 3)`` with covariances ``cov (n, 3, 3)`` (each in the body frame after
    its increment): the total and its covariance in the final body frame (``xi_n = Ad(d_n^-1) xi_n-1 + eta_n``)."""
    total: F64 = np.zeros(3)
    sigma: F64 = np.zeros((3, 3))
    for d, c in zip(increments, cov, strict=True):
        A = adjoint(between(d, np.zeros(3)))
        sigma = A @ sigma @ A.T + c
        total = compose(total, d)
    return total, sigma


def world_cov_to_body(pose: F64, cov: F64) -> F64:
    """A covariance of (x, y in the parent frame, yaw) to the body frame at ``pose``."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return R @ cov @ R.T


# -- keyframes -------------------------------------------------------------------------------------------------------


def select_keyframes(odometry: F64, distance: float, angle_deg: float) -> I64:
    """Scan indices of the keyframes: the first scan, then each scan past ``distance`` metres or ``angle_deg``
    degrees of odometry motion from the previous keyframe."""
    keys = [0]
    ang = np.radians(angle_deg)
    for i in range(1, len(odometry)):
        k = odometry[keys[-1]]
        if (np.hypot(*(odometry[i, :2] - k[:2])) >= distance
                or abs(wrap_angle(odometry[i, 2] - k[2])) >= ang):
            keys.append(i)
    return np.asarray(keys, dtype=np.int64)


def keyframe_clouds(odometry: F64, endpoints: Sequence[F64], keyframes: I64, resolution: float) -> list[F64]:
    """Each keyframe's cloud in its own frame: the endpoints of the scans nearer to it (by index) than to another
    keyframe, moved along the odometry, thinned to one point per ``resolution`` cell."""
    T = len(odometry)
    bounds = np.r_[0, (keyframes[1:] + keyframes[:-1] + 1) // 2, T]
    out = []
    for k, kf in enumerate(keyframes):
        parts = [transform(between(odometry[kf], odometry[s]), endpoints[s])
                 for s in range(bounds[k], bounds[k + 1]) if len(endpoints[s])]
        pts = np.concatenate(parts) if parts else np.zeros((0, 2))
        if len(pts):
            _, first = np.unique(np.round(pts / resolution).astype(np.int64), axis=0, return_index=True)
            pts = pts[np.sort(first)]
        out.append(pts)
    return out


def odometry_edges(odometry: F64, cov: F64, keyframes: I64, t_s: F64) -> list[Edge]:
    """Relative-pose factors between consecutive keyframes: the odometry's increments between them, their
    covariance propagated from the per-scan increment covariances ``cov (T, 3, 3)`` (row i: into scan i), and the
    interval ``dt`` from the scan times ``t_s`` (s)."""
    edges = []
    for k in range(1, len(keyframes)):
        a, b = int(keyframes[k - 1]), int(keyframes[k])
        inc = between(odometry[a:b], odometry[a + 1:b + 1])
        _, sigma = propagate(inc, cov[a + 1:b + 1])
        z = between(odometry[a], odometry[b])
        sigma = 0.5 * (sigma + sigma.T) + np.diag([1e-8, 1e-8, 1e-10])
        edges.append(Edge("odometry", k - 1, k, z, sigma, dt=float(t_s[b] - t_s[a])))
    return edges


# -- front end and loop closures -------------------------------------------------------------------------------------


def local_cloud(poses: F64, clouds: list[F64], centre: int, members: Sequence[int]) -> F64:
    """The clouds of keyframes ``members`` placed by ``poses`` and expressed in keyframe ``centre``'s frame."""
    parts = [transform(between(poses[centre], poses[i]), clouds[i]) for i in members if len(clouds[i])]
    return np.concatenate(parts) if parts else np.zeros((0, 2))


def travelled(keyframe_poses: F64) -> F64:
    """Cumulative path length at each keyframe (m)."""
    return np.r_[0.0, np.cumsum(np.hypot(*np.diff(keyframe_poses[:, :2], axis=0).T))]


def chain_prior(odometry: Sequence[Edge], j: int, k: int, bias_sigma0: float) -> F64:
    """The covariance of keyframe ``k``'s pose in keyframe ``j``'s frame (x, y in ``j``'s frame, yaw) that the
    odometry factors between them allow: their covariances composed on SE(2) (:func:`propagate`), plus a yaw-rate
    bias of prior std ``bias_sigma0`` acting over every factor's interval (the graph's own bias state), through
    the chain's Jacobian with respect to that bias."""
    chain = odometry[j:k]
    z = np.array([e.z for e in chain])
    dt = np.array([e.dt for e in chain])
    total, sigma = propagate(z, np.array([e.cov for e in chain]))
    eps = 1e-6
    biased = z.copy()
    biased[:, 2] += eps * dt
    shifted, _ = propagate(biased, np.zeros((len(z), 3, 3)))
    jac = (shifted - total) / eps
    jac[2] = wrap_angle(shifted[2] - total[2]) / eps
    c, s = np.cos(total[2]), np.sin(total[2])
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # k's body frame to j's frame
    out: F64 = R @ sigma @ R.T + bias_sigma0**2 * np.outer(jac, jac)
    return 0.5 * (out + out.T)


def pass_segment(poses: F64, s: F64, j: int, travelled_by: float, reach: float) -> range:
    """The keyframes of the pass through keyframe ``j``: the contiguous run around it along the path whose
    positions lie within ``reach`` (m) of ``j``'s and whose path length ``s`` is at most ``travelled_by``."""
    ok = (s <= travelled_by) & (np.hypot(*(poses[:, :2] - poses[j, :2]).T) <= reach)
    a, b = j, j
    while a > 0 and ok[a - 1]:
        a -= 1
    while b + 1 < len(poses) and ok[b + 1]:
        b += 1
    return range(a, b + 1)


def loop_closures(poses: F64, clouds: list[F64], model: GraphParams,
                  odometry: Sequence[Edge] | None = None) -> list[Edge]:
    """Closures proposed and verified on the odometry's keyframe poses: for every keyframe (at most one closure
    per ``loop_every`` keyframes), the nearest earlier keyframe within ``loop_radius`` that lies
    ``loop_min_travel`` or more back along the path; the local cloud around the keyframe (``local_keyframes``
    centred on it) is matched against the candidate's pass (:func:`pass_segment`: every keyframe of that pass
    within ``local_keyframes / 2 * keyframe_distance + max_range`` of it, so that the reference holds what the
    query can see, also when it comes back the other way), with a wide yaw search, the candidates ranked
    by their posterior under the odometry chain's prior between the two (:func:`chain_prior`; ``odometry``: the
    consecutive keyframes' factors, without them by the likelihood alone). One whose inlier share reaches
    ``loop_min_inliers`` is proposed; the optimiser may still reject it."""
    s = travelled(poses)
    out: list[Edge] = []
    half = max(1, model.local_keyframes // 2)
    reach = half * model.keyframe_distance + model.max_range
    matcher = matcher_of(model)
    last_closed = -(10**9)
    K = len(poses)
    for k in range(K):
        if k - last_closed < LOOP_EVERY:
            continue
        far = np.flatnonzero(s[k] - s[: k + 1] >= model.loop_min_travel)
        if not len(far):
            continue
        d = np.hypot(*(poses[far, :2] - poses[k, :2]).T)
        if d.min() > model.loop_radius:
            continue
        j = int(far[np.argmin(d)])
        ref = local_cloud(poses, clouds, j, pass_segment(poses, s, j, s[k] - model.loop_min_travel, reach))
        q = local_cloud(poses, clouds, k, range(max(0, k - half), min(K, k + half + 1)))
        if len(q) < MIN_LOOP_POINTS or len(ref) < MIN_LOOP_POINTS:
            continue
        prior = None if odometry is None else chain_prior(odometry, j, k, model.bias_sigma0)
        m = match(ref, q, between(poses[j], poses[k]), matcher, model.loop_radius, model.loop_search_yaw,
                  prior_cov=prior)
        if m.inliers < model.loop_min_inliers:
            continue
        out.append(Edge("loop", j, k, m.pose, world_cov_to_body(m.pose, m.cov), m.inliers))
        last_closed = k
    return out


#: PCM's test of two closures: the squared Mahalanobis norm of the cycle they close, below chi-square(3, 0.99)
PCM_CHI2 = 11.345


def pairwise_consistent(loops: Sequence[Edge], odometry: Sequence[Edge], poses: F64, bias_sigma0: float
                        ) -> npt.NDArray[np.bool_]:
    """PCM's consistency matrix (Mangelson et al., ICRA 2018): closures ``a`` (``i_a -> j_a``) and ``b`` agree when
    the cycle ``z_a, odometry j_a -> j_b, z_b^-1, odometry i_b -> i_a`` is the identity within
    :data:`PCM_CHI2` under the sum of the closures' covariances and the odometry chains' (:func:`chain_prior`,
    which holds the graph's yaw-rate-bias prior). Covariances are added in the frames they are given in: a
    first-order test, conservative where the frames differ little, as they do for closures a few metres apart."""
    n = len(loops)
    out = np.eye(n, dtype=bool)
    for a in range(n):
        for b in range(a + 1, n):
            A, B = loops[a], loops[b]
            cycle = compose(compose(compose(A.z, between(poses[A.j], poses[B.j])), between(B.z, np.zeros(3))),
                            between(poses[B.i], poses[A.i]))
            cycle[2] = wrap_angle(cycle[2])
            S = A.cov + B.cov + np.diag([1e-4, 1e-4, 1e-6])
            for x, y in ((A.j, B.j), (A.i, B.i)):
                if x != y:
                    S = S + chain_prior(odometry, min(x, y), max(x, y), bias_sigma0)
            out[a, b] = out[b, a] = float(cycle @ np.linalg.solve(S, cycle)) < PCM_CHI2
    return out


def largest_consistent_set(consistent: npt.NDArray[np.bool_]) -> list[int]:
    """The largest set of mutually consistent closures: a maximum clique of the consistency graph (networkx;
    ties go to the set whose members come first)."""
    import networkx as nx

    n = len(consistent)
    if n == 0:
        return []
    g = nx.Graph()
    g.add_nodes_from(range(n))
    g.add_edges_from((a, b) for a in range(n) for b in range(a + 1, n) if consistent[a, b])
    best = max(nx.find_cliques(g), key=lambda c: (len(c), [-i for i in sorted(c)]))
    return sorted(best)


# -- optimiser ------------------------------------------------------------------------------------------------------


def import_gtsam() -> Any:
    try:
        import gtsam
    except ImportError as exc:
        raise ImportError(f"radar_graph needs GTSAM: {GTSAM_INSTALL}") from exc
    return gtsam


def bias_key(k: int) -> int:
    """GTSAM key of keyframe ``k``'s yaw-rate bias (the poses are keys ``0 .. K-1``)."""
    gtsam = import_gtsam()
    return int(gtsam.symbol("b", k))


def odometry_bias_factor(e: Edge) -> Any:
    """The odometry factor between keyframes ``e.i`` and ``e.j`` with keyframe ``e.i``'s yaw-rate bias ``b``: the
    odometry measured the relative pose followed by a turn of ``b dt`` (its gyro's bias), so the error is
    ``Log(z^-1 (X_i^-1 X_j) R(b dt))`` with the factor's covariance. Jacobians by central differences on the
    tangent spaces (three variables, a cheap error)."""
    gtsam = import_gtsam()
    z = gtsam.Pose2(*e.z)
    dt, bkey = e.dt, bias_key(e.i)

    def error(xi: Any, xj: Any, b: float) -> F64:
        return np.asarray(gtsam.Pose2.Logmap(z.between(xi.between(xj).compose(gtsam.Pose2(0.0, 0.0, b * dt)))))

    def evaluate(_factor: Any, values: Any, jacobians: Any) -> F64:
        xi, xj, b = values.atPose2(e.i), values.atPose2(e.j), float(values.atVector(bkey)[0])
        if jacobians is not None:
            h = 1e-6
            ji, jj = np.zeros((3, 3)), np.zeros((3, 3))
            for d in range(3):
                v = np.zeros(3)
                v[d] = h
                ji[:, d] = (error(xi.retract(v), xj, b) - error(xi.retract(-v), xj, b)) / (2 * h)
                jj[:, d] = (error(xi, xj.retract(v), b) - error(xi, xj.retract(-v), b)) / (2 * h)
            jb = ((error(xi, xj, b + h) - error(xi, xj, b - h)) / (2 * h)).reshape(3, 1)
            jacobians[0], jacobians[1], jacobians[2] = ji, jj, jb
        return error(xi, xj, b)

    return gtsam.CustomFactor(gtsam.noiseModel.Gaussian.Covariance(e.cov), [e.i, e.j, bkey], evaluate)


def _between_factor(e: Edge, weight: float = 1.0) -> Any:
    """GTSAM's relative-pose factor of ``e`` (a loop closure, or an odometry edge without an interval), its
    covariance divided by ``weight`` (GNC's)."""
    gtsam = import_gtsam()
    return gtsam.BetweenFactorPose2(e.i, e.j, gtsam.Pose2(*e.z), gtsam.noiseModel.Gaussian.Covariance(e.cov / weight))


def gnc_weights(graph: Any, values: Any, loops: list[Edge], cbar2: float = 11.345, step: float = 1.4,
                max_iter: int = 100) -> tuple[Any, F64]:
    """Graduated non-convexity with the truncated quadratic (Yang et al., RA-L 2020) over the loop closures only,
    the factors of ``graph`` known inliers: the closures' weights (0: rejected, 1: kept) and the solution. A
    closure's whitened squared residual above ``cbar2`` (the 0.99 quantile of chi^2 with 3 dof) is an outlier at
    convergence. GTSAM's own GNC cannot copy the odometry's custom factors, hence this loop."""
    gtsam = import_gtsam()
    lm = gtsam.LevenbergMarquardtParams()
    full = gtsam.NonlinearFactorGraph(graph)
    for e in loops:
        full.add(_between_factor(e))
    values = gtsam.LevenbergMarquardtOptimizer(full, values, lm).optimize()
    r2 = np.array([2.0 * _between_factor(e).error(values) for e in loops])
    w = np.ones(len(loops))
    if r2.max() <= cbar2:
        return values, w
    mu = cbar2 / max(2.0 * r2.max() - cbar2, 1e-12)
    for _ in range(max_iter):
        weighted = gtsam.NonlinearFactorGraph(graph)
        for e, wi in zip(loops, w, strict=True):
            if wi > 1e-6:
                weighted.add(_between_factor(e, wi))
        values = gtsam.LevenbergMarquardtOptimizer(weighted, values, lm).optimize()
        r2 = np.array([2.0 * _between_factor(e).error(values) for e in loops])
        lo, hi = mu / (mu + 1.0) * cbar2, (mu + 1.0) / mu * cbar2
        w_new = np.where(r2 <= lo, 1.0, np.where(r2 >= hi, 0.0, np.sqrt(cbar2 * mu * (mu + 1.0) /
                                                                        np.maximum(r2, 1e-12)) - mu))
        settled = bool(np.all(np.abs(w_new - w) < 1e-6))
        w = np.clip(w_new, 0.0, 1.0)
        if settled and np.all((w < 1e-6) | (w > 1 - 1e-6)):
            break
        mu *= step
    return values, w


def optimise(initial: F64, edges: list[Edge], robust: Literal["gnc", "none"], bias_sigma0: float = 0.01,
             bias_walk: float = 1e-4) -> tuple[F64, F64, list[bool], F64]:
    """Batch optimisation of the keyframe poses (the first held by a tight prior) and their yaw-rate biases
    (prior ``bias_sigma0`` at the first, a random walk of ``bias_walk`` between consecutive keyframes over their
    odometry factor's ``dt``; an edge with ``dt = 0`` is a plain relative-pose factor): the poses, their marginal
    covariances, per edge whether the optimiser kept it (a loop closure whose GNC weight ends above one half;
    always the odometry) and the biases."""
    gtsam = import_gtsam()
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    K = len(initial)
    timed = any(e.kind != "loop" and e.dt > 0 for e in edges)  # without intervals there is no bias to estimate
    for k, p in enumerate(initial):
        values.insert(k, gtsam.Pose2(*p))
        if timed:
            values.insert(bias_key(k), np.zeros(1))
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*initial[0]),
                                     gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-4, 1e-4, 1e-5]))))
    if timed:
        graph.add(gtsam.PriorFactorVector(bias_key(0), np.zeros(1),
                                          gtsam.noiseModel.Isotropic.Sigma(1, bias_sigma0)))
    dts = np.zeros(K)
    for e in edges:
        if e.kind == "loop":
            continue
        if e.dt > 0:
            graph.add(odometry_bias_factor(e))
            if e.j == e.i + 1:
                dts[e.j] = e.dt
        else:
            graph.add(_between_factor(e))
    for k in range(1, K if timed else 0):
        walk = gtsam.noiseModel.Isotropic.Sigma(1, max(bias_walk * np.sqrt(dts[k]), 1e-7))
        graph.add(gtsam.BetweenFactorVector(bias_key(k - 1), bias_key(k), np.zeros(1), walk))
    loops = [e for e in edges if e.kind == "loop"]
    lm = gtsam.LevenbergMarquardtParams()
    lm.setRelativeErrorTol(1e-12)  # the final solve to convergence: a looser stop leaves GNC's last iterate
    lm.setAbsoluteErrorTol(1e-12)
    weights: F64 = np.ones(len(loops))
    if loops and robust == "gnc":
        result, weights = gnc_weights(graph, values, loops)
    elif loops:
        full = gtsam.NonlinearFactorGraph(graph)
        for e in loops:
            full.add(_between_factor(e))
        result = gtsam.LevenbergMarquardtOptimizer(full, values, lm).optimize()
    else:
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, lm).optimize()
    keep_loop = iter(bool(w > 0.5) for w in weights)
    kept = [next(keep_loop) if e.kind == "loop" else True for e in edges]
    clean = gtsam.NonlinearFactorGraph(graph)  # the solution and marginals without the rejected closures
    for e, k in zip(edges, kept, strict=True):
        if e.kind == "loop" and k:
            clean.add(_between_factor(e))
    if loops and robust == "gnc":
        # with every closure rejected the initial values (the odometry, zero bias) may already satisfy every
        # remaining factor: then they are the solution, exactly, not the optimiser's approximation of it
        exact = not any(w > 0.5 for w in weights) and clean.error(values) < 1e-12
        result = values if exact else gtsam.LevenbergMarquardtOptimizer(clean, result, lm).optimize()
    poses = np.array([[result.atPose2(k).x(), result.atPose2(k).y(), result.atPose2(k).theta()] for k in range(K)])
    bias = np.array([float(result.atVector(bias_key(k))[0]) if timed else 0.0 for k in range(K)])
    try:
        marg = gtsam.Marginals(clean, result)
        cov = np.stack([marg.marginalCovariance(k) for k in range(K)])
    except RuntimeError:  # an indeterminate system (should not happen with the priors and the odometry chain)
        cov = np.full((K, 3, 3), np.nan)
    return poses, cov, kept, bias


def interpolate(odometry: F64, keyframes: I64, keyframe_poses: F64) -> F64:
    """Every scan's pose: its odometry pose moved by the correction ``X_k O_k^-1`` of its keyframes, interpolated
    linearly (rotation and translation of the correction) between the two keyframes around it."""
    inv = between(odometry[keyframes], np.zeros((len(keyframes), 3)))
    corr = compose(keyframe_poses, inv)
    idx = np.arange(len(odometry))
    pos = np.interp(idx, keyframes, np.arange(len(keyframes)))
    lo = np.clip(np.floor(pos).astype(int), 0, len(keyframes) - 1)
    hi = np.clip(lo + 1, 0, len(keyframes) - 1)
    t = (pos - lo)[:, None]
    dyaw = wrap_angle(corr[hi, 2] - corr[lo, 2])
    c = np.column_stack([corr[lo, :2] * (1 - t) + corr[hi, :2] * t, wrap_angle(corr[lo, 2] + t[:, 0] * dyaw)])
    return compose(c, odometry)


class _Round(NamedTuple):
    """One round of loop proposals, consistency, and the robust optimisation."""

    poses: F64  # optimised keyframe poses
    cov: F64
    bias: F64
    edges: list[Edge]  # odometry and the consistent closures (accepted or not by GNC), then the inconsistent ones
    loops: list[Edge]  # every closure proposed
    inconsistent: list[Edge]
    accepted: set[tuple[int, int]]  # (i, j) of the closures kept


def _loop_round(current: F64, odometry_poses: F64, clouds: list[F64], odo: list[Edge], model: GraphParams) -> _Round:
    """Closures proposed around ``current`` (guesses and local clouds from it), PCM against the odometry chain
    (``odometry_poses``), then GNC from the odometry."""
    loops = loop_closures(current, clouds, model, odo)
    clique = set(largest_consistent_set(pairwise_consistent(loops, odo, odometry_poses, model.bias_sigma0)))
    inconsistent = [replace(e, accepted=False) for k, e in enumerate(loops) if k not in clique]
    edges = [*odo, *(e for k, e in enumerate(loops) if k in clique)]
    opt, kcov, kept, bias = optimise(odometry_poses, edges, "gnc", model.bias_sigma0, model.bias_walk)
    edges = [*(replace(e, accepted=k) for e, k in zip(edges, kept, strict=True)), *inconsistent]
    accepted = {(e.i, e.j) for e in edges if e.kind == "loop" and e.accepted}
    return _Round(opt, kcov, bias, edges, loops, inconsistent, accepted)


def optimise_graph(odometry: F64, cov: F64, t_s: F64, endpoints: Sequence[F64], model: GraphParams) -> GraphResult:
    """``radar_graph`` on arrays: ``odometry (T, 3)`` world <- base poses at the scans, ``cov (T, 3, 3)`` their
    increment covariances (row i: into scan i, body frame), ``t_s (T,)`` the scan times (s), ``endpoints`` each
    scan's radar endpoints in the body frame (2D). Raises ValueError for a log too short for two keyframes."""
    odometry = np.asarray(odometry, np.float64).reshape(-1, 3)
    if not len(endpoints) == len(odometry) == len(cov) == len(t_s):
        raise ValueError(f"radar_graph: {len(odometry)} odometry poses, {len(cov)} covariances, {len(t_s)} times and "
                         f"{len(endpoints)} scans must agree")
    import_gtsam()  # fail before the work when it is missing
    keyframes = select_keyframes(odometry, model.keyframe_distance, model.keyframe_angle)
    warnings: list[str] = []
    if len(keyframes) < 2:
        raise ValueError(f"radar_graph: the odometry moves less than slam.graph.keyframe_distance = "
                         f"{model.keyframe_distance} m and slam.graph.keyframe_angle = {model.keyframe_angle} deg "
                         "over the log: one keyframe, no graph")
    clouds = keyframe_clouds(odometry, endpoints, keyframes, matcher_of(model).resolution)
    odo = odometry_edges(odometry, cov, keyframes, np.asarray(t_s, np.float64))
    poses = odometry[keyframes]
    res = _loop_round(poses, poses, clouds, odo, model)
    for _ in range(model.loop_rounds - 1):  # each round proposes from the poses the one before optimised
        if not res.accepted:
            break
        nxt = _loop_round(res.poses, poses, clouds, odo, model)
        if not nxt.accepted:  # a later round that keeps nothing leaves the earlier solution
            break
        settled = nxt.accepted == res.accepted
        res = nxt
        if settled:
            break
    rejected = sum(e.kind == "loop" and not e.accepted for e in res.edges)
    if rejected:
        warnings.append(f"{len(res.inconsistent)} of {len(res.loops)} loop closures disagree with the largest "
                        f"mutually consistent set and the optimiser rejected {rejected - len(res.inconsistent)} "
                        "more; graph_edges.parquet lists them with accepted = false")
    return GraphResult(interpolate(odometry, keyframes, res.poses), keyframes, res.poses, res.cov, res.edges, res.bias,
                       warnings)
