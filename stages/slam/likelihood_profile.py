"""How sharply a particle's map constrains its pose: scan log-likelihood profiles around the true pose.

A map is built along ground-truth poses from the scans before scan ``k``; scan ``k`` is then scored
at the true pose moved by body-frame offsets (forward, lateral, yaw). The profile of a weight
function tells what the filter's selection can correct: its peak should sit at zero offset and the
log-likelihood should fall by several units within the proposal's spread. Compared: the Hilbert-GP
weight with the variance (eq. 28, 30), without it (mean only), and the FastSLAM grid likelihood
field, each averaged over several test scans.

    python -m stages.slam.likelihood_profile [RUN_DIR ...] [--scans 8] [--out table.md]
        [--free-weight W ...] [--free-clearance C ...] [--ray-step R ...] [--endpoint-noise S2 ...] [--no-et]
        [--outlier E ...] [--refine] [--submaps]

``--free-weight`` / ``--free-clearance`` / ``--ray-step`` / ``--endpoint-noise`` add rows for the Hilbert
weight with the free samples' log terms weighted by W, with no free sample within C metres of the endpoint,
with a free sample every R metres along the beam (Table II: 1 m), or with a map whose endpoints (+1
samples) have the noise variance S2 instead of sigma_n^2 (issue 17's levers inside the paper's model).
``--outlier`` adds the Hilbert weight with outlier probability E (``slam.outlier``).
``--no-et`` adds the paper's weight without the endpoint tolerance (``rich_slam_no_et``, the ablation).
``--submaps`` adds the weight against local submaps (``submaps.py``) built along ground truth as the filter
builds them, with the paper's free-sample terms and without them. ``--refine`` adds the refinement table:
where Gauss-Newton on each objective of :mod:`pose_refinement` takes the test scans from the true pose and
from offsets of it, with a prior too wide to hold them (the map's own optimum; a good objective stays near
zero).

Without RUN_DIR it profiles the synthetic corridor (``synthetic.py``); a run folder needs ``ingest/``
and ``filter/`` (ground-truth poses at the radar scan times).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from stages.slam import hilbert_map as hm
from stages.slam.beam_sampling import BeamSamples, sample_beams, to_world
from stages.slam.grid_map import GridParticleMaps, likelihood_field_log_likelihood, make_grid_spec
from stages.slam.methods import SlamConfig, domain_from_trajectory
from stages.slam.pose_refinement import PoseRefinement, refine
from stages.slam.rbpf import (
    HilbertParticleMaps,
    HilbertWeighting,
    MapModel,
    compose,
    hilbert_log_likelihood,
    wrap_angle,
)

F64 = npt.NDArray[np.floating[Any]]
#: body-frame offsets profiled: metres forward / lateral, degrees of yaw
OFFSETS_M = np.round(np.arange(-1.0, 1.0001, 0.1), 3)
OFFSETS_DEG = np.round(np.arange(-10.0, 10.0001, 1.0), 3)


@dataclass
class Profile:
    """Mean log-likelihood (relative to the true pose) per offset along one axis."""

    model: str
    axis: str  # forward | lateral | yaw
    offsets: F64
    loglik: F64  # mean over test scans of loglik(offset) - loglik(0)

    @property
    def peak(self) -> float:
        return float(self.offsets[int(np.argmax(self.loglik))])

    def drop_at(self, d: float) -> float:
        """Mean fall of the log-likelihood at +-d from the true pose (positive = the true pose is preferred)."""
        i = [int(np.argmin(np.abs(self.offsets - s))) for s in (-d, d)]
        return float(-np.mean(self.loglik[i]))


def offset_poses(pose: F64, axis: str) -> tuple[F64, F64]:
    """The true pose moved by every profiled offset along ``axis`` (body frame)."""
    offs = OFFSETS_DEG if axis == "yaw" else OFFSETS_M
    delta = np.zeros((len(offs), 3))
    delta[:, {"forward": 0, "lateral": 1, "yaw": 2}[axis]] = np.radians(offs) if axis == "yaw" else offs
    return compose(np.repeat(pose[None, :], len(offs), 0), delta), offs


def hilbert_at(basis: hm.HilbertBasis, theta: F64, cov: F64, poses: F64, samples: BeamSamples,
               weighting: HilbertWeighting) -> F64:
    """The scan's Hilbert log-likelihood at each of ``poses`` against one map (``theta``, ``cov``)."""
    n = len(poses)
    return hilbert_log_likelihood(basis, np.repeat(theta[None], n, 0), np.repeat(cov[None], n, 0), poses, samples,
                                  weighting)


def submap_profiles(gt: F64, scans: Sequence[BeamSamples], test: Sequence[int], cfg: SlamConfig,
                    model: str = "hilbert_gp submaps") -> list[Profile]:
    """Profiles of the weight against local submaps (``cfg.submaps``, ``cfg.submap_lengthscale_m``): the
    submaps are built along ground truth as the filter builds them (opened and closed as it moves), and each
    test scan is scored against the submap the filter would weigh it against."""
    from stages.slam.submaps import Submap, SubmapParticleMaps

    assert cfg.submaps is not None
    w = cfg.weighting("rich_slam")
    mm = MapModel(cfg.submap_lengthscale_m, cfg.signal_variance, cfg.noise_variance, w, form="covariance")
    sub = SubmapParticleMaps.create(cfg.submaps, 1, mm, cfg.basis_kind)
    sums: dict[str, F64] = {}
    count = 0
    done = 0
    for k in sorted(test):
        for i in range(done, k):
            sub.weigh_and_update(gt[i : i + 1], scans[i])
        done = k
        target = sub.weighing(gt[k : k + 1])
        if scans[k].n == 0 or not isinstance(target, Submap):  # the profile's submaps are never kept
            continue
        count += 1
        maps = target.maps
        assert isinstance(maps, HilbertParticleMaps)  # in-process maps
        theta, cov = maps.map_of(0)
        for axis in ("forward", "lateral", "yaw"):
            poses, _ = offset_poses(gt[k], axis)
            n = len(poses)
            ll = hilbert_at(target.basis, theta, cov, poses, scans[k], w)
            sums[axis] = sums.get(axis, np.zeros(n)) + (ll - ll[n // 2])
    return [Profile(model, axis, OFFSETS_DEG if axis == "yaw" else OFFSETS_M, s / max(count, 1))
            for axis, s in sums.items()]


def profiles(gt: F64, scans: Sequence[BeamSamples], test: Sequence[int], cfg: SlamConfig,
             padding: float = 10.0,
             extra: dict[str, tuple[HilbertWeighting, Sequence[BeamSamples], float | None]] | None = None,
             ) -> list[Profile]:
    """Profiles of the Hilbert weight (with and without variance) and the grid likelihood field.

    ``gt (T, 3)`` are the true poses of ``scans``; every scan before a test scan builds the map (one
    map per model, grown incrementally), the test scan is only scored. ``extra``: more Hilbert rows, each
    a weighting, its own beam samples and its endpoints' noise variance (maps built from them; None: sigma_n^2).
    With ``cfg.submaps`` set, the rows of :func:`submap_profiles` are added (with ``cfg``'s free weight and, as
    a second row, without the free samples' terms).
    """
    half, centre = domain_from_trajectory(gt[:, :2], padding)
    basis = hm.make_basis(half, centre, cfg.n_basis, cfg.basis_kind)
    w = cfg.weighting("rich_slam")
    hil = HilbertParticleMaps(basis, 1, MapModel(cfg.lengthscale_m, cfg.signal_variance, cfg.noise_variance, w,
                                                 form="covariance"))
    grid = GridParticleMaps(make_grid_spec(centre, half, cfg.grid_resolution), 1, cfg.grid)
    models: dict[str, tuple[HilbertWeighting | None, Sequence[BeamSamples], HilbertParticleMaps | None]] = {
        "hilbert_gp (variance, ET)": (w, scans, hil),
        "hilbert_gp (mean only)": (cfg.weighting("rich_slam_mean_only"), scans, hil),
        "fastslam_grid": (None, scans, None)}
    for name, (wx, sx, s2e) in (extra or {}).items():
        mx: HilbertParticleMaps | None = hil if sx is scans and s2e is None else HilbertParticleMaps(
            basis, 1, MapModel(cfg.lengthscale_m, cfg.signal_variance, cfg.noise_variance, wx, form="covariance",
                               endpoint_noise_variance=s2e))
        models[name] = (wx, sx, mx)
    own = {id(m): (m, sx) for _, sx, m in models.values() if m is not None}
    sums: dict[tuple[str, str], F64] = {}
    done = 0
    for k in sorted(test):
        for i in range(done, k):
            for mx, sx in own.values():
                if sx[i].n:
                    mx.update(gt[i : i + 1], sx[i])
            if scans[i].n:
                grid.update(gt[i : i + 1], scans[i])
        done = k
        if scans[k].n == 0:
            continue
        posts = {key: mx.map_of(0) for key, (mx, _) in own.items()}
        for axis in ("forward", "lateral", "yaw"):
            poses, _ = offset_poses(gt[k], axis)
            n = len(poses)
            for name, (weighting, sx, mx) in models.items():
                if weighting is None or mx is None:
                    ll = likelihood_field_log_likelihood(np.repeat(grid.grids, n, axis=0), grid.spec,
                                                         to_world(poses, scans[k].endpoints), grid.model)
                else:
                    theta, cov = posts[id(mx)]
                    ll = hilbert_at(basis, theta, cov, poses, sx[k], weighting)
                zero = ll[n // 2]
                sums[(name, axis)] = sums.get((name, axis), np.zeros(n)) + (ll - zero)
    count = sum(1 for k in test if scans[k].n)
    out = [Profile(name, axis, OFFSETS_DEG if axis == "yaw" else OFFSETS_M, s / max(count, 1))
           for (name, axis), s in sums.items()]
    if cfg.submaps is not None:
        label = f"hilbert_gp submaps (l = {cfg.submap_lengthscale_m:g} m"
        out += submap_profiles(gt, scans, test, cfg, label + f", free weight {cfg.free_weight:g})")
        if cfg.free_weight != 0:
            out += submap_profiles(gt, scans, test, replace(cfg, free_weight=0.0), label + ", free weight 0)")
    return out


def refinement_bias(gt: F64, scans: Sequence[BeamSamples], test: Sequence[int], cfg: SlamConfig,
                    padding: float = 10.0, iterations: int = 8) -> list[str]:
    """Markdown rows: mean position / yaw error after Gauss-Newton from the true pose and from offsets.

    The map is built along ground truth from the scans before each test scan, the prior is 1 m / 0.3 rad
    (too wide to hold the start): where the refinement ends is where the objective peaks on that map.
    """
    half, centre = domain_from_trajectory(gt[:, :2], padding)
    basis = hm.make_basis(half, centre, cfg.n_basis, cfg.basis_kind)
    hil = HilbertParticleMaps(basis, 1, cfg.map_model("rich_slam", "covariance"))
    starts = {"true pose": (0.0, 0.0, 0.0), "lateral +-0.2 m": (0.0, 0.2, 0.0), "yaw +-3 deg": (0.0, 0.0, 3.0)}
    wide = np.array([1.0, 1.0, 0.09])
    errs: dict[tuple[str, str], list[F64]] = {}
    done = 0
    for k in sorted(test):
        for i in range(done, k):
            if scans[i].n:
                hil.update(gt[i : i + 1], scans[i])
        done = k
        if scans[k].n == 0:
            continue
        for label, (fx, ly, yaw) in starts.items():
            d = np.array([[fx, ly, np.radians(yaw)], [-fx, -ly, -np.radians(yaw)]])
            x0 = compose(np.repeat(gt[k : k + 1], 2, 0), d)
            for objective in ("logistic", "gaussian"):
                st = PoseRefinement(iterations, 0.25, 0.05, objective=objective,
                                    noise_variance=cfg.noise_variance)
                mode, _ = refine(basis, np.repeat(hil.theta, 2, 0), x0, wide, scans[k], st, cfg.likelihood_exponent)
                e = mode - gt[k]
                errs.setdefault((objective, label), []).append(
                    np.column_stack([np.hypot(e[:, 0], e[:, 1]), np.degrees(np.abs(wrap_angle(e[:, 2])))]))
    rows = []
    for (objective, label), v in errs.items():
        a = np.concatenate(v)
        rows.append(f"| {objective} | {label} | {a[:, 0].mean():.3f} | {a[:, 1].mean():.2f} |")
    return rows


def synthetic_case(n_scans: int = 300, seed: int = 1, free_clearance: float = 0.0, ray_step: float = 1.0,
                   ) -> tuple[F64, list[BeamSamples]]:
    """Ground truth and beam samples of the synthetic corridor (25 beams per scan)."""
    from stages.slam.synthetic import make_run

    run = make_run(n_scans, np.random.default_rng(seed))
    return run.groundtruth, [sample_beams(p, np.zeros(2), ray_step, 5.0, 0.0, free_clearance) for p in run.scans]


def run_folder_case(run_dir: Path, max_range: float = 5.0, ray_step: float = 1.0, free_clearance: float = 0.0,
                    ) -> tuple[F64, list[BeamSamples]]:
    """Ground-truth poses at the radar scan times and the filtered scans' beam samples of a run folder."""
    from stages.evaluate.world import gt_interpolator
    from stages.slam.stage import SlamParams, beam_samples_by_scan
    from stages.slam.unit_study import read_run_folder

    gt, calib, radar = read_run_folder(run_dir)
    interp = gt_interpolator(gt, int(0.5e9))
    scan = radar["scan"].to_numpy().astype(np.int64)
    t = radar["t_ns"].to_numpy().astype(np.int64)
    xyz = np.stack([radar[c].to_numpy().astype(np.float64) for c in ("x", "y", "z")], 1)
    ids, first = np.unique(scan, return_index=True)
    ok = interp.valid(t[first])
    ids, t_scan = ids[ok], t[first][ok]
    pos, rot = interp.at(t_scan)
    poses = np.column_stack([pos[:, :2], np.arctan2(rot[:, 1, 0], rot[:, 0, 0])])
    return poses, beam_samples_by_scan(scan, xyz, ids, calib, SlamParams(max_range=max_range, ray_step=ray_step,
                                                                             free_clearance=free_clearance))


def table(rows: Sequence[tuple[str, Profile]]) -> list[str]:
    lines = ["| data | weight | axis | peak offset | drop at +-0.2 m / 2 deg | drop at +-0.5 m / 5 deg |",
             "|---|---|---|---|---|---|"]
    for data, p in rows:
        unit, d1, d2 = ("deg", 2.0, 5.0) if p.axis == "yaw" else ("m", 0.2, 0.5)
        lines.append(f"| {data} | {p.model} | {p.axis} | {p.peak + 0.0:+.1f} {unit} | {p.drop_at(d1):.2f} | "
                     f"{p.drop_at(d2):.2f} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("runs", nargs="*", type=Path, help="run folders <runs>/<seq> with ingest/ and filter/")
    ap.add_argument("--scans", type=int, default=8, help="test scans per data set (evenly spaced in its second half)")
    ap.add_argument("--out", type=Path, help="write the table as markdown here")
    ap.add_argument("--free-weight", type=float, nargs="*", default=[], help="extra rows: free-sample weight W")
    ap.add_argument("--free-clearance", type=float, nargs="*", default=[], help="extra rows: free clearance C (m)")
    ap.add_argument("--ray-step", type=float, nargs="*", default=[], help="extra rows: a free sample every R m")
    ap.add_argument("--endpoint-noise", type=float, nargs="*", default=[],
                    help="extra rows: the endpoints' noise variance S2 in the map (free samples keep sigma_n^2)")
    ap.add_argument("--outlier", type=float, nargs="*", default=[],
                    help="extra rows: the Hilbert weight with outlier probability E (slam.outlier)")
    ap.add_argument("--no-et", action="store_true", help="extra row: the weight without the endpoint tolerance")
    ap.add_argument("--refine", action="store_true", help="also the refinement table (where Gauss-Newton ends)")
    ap.add_argument("--submaps", action="store_true", help="also the weight against local submaps (the slam "
                    "stage's submap defaults: slam.map = submaps)")
    a = ap.parse_args(argv)
    cfg = SlamConfig(workers=0)
    if a.submaps:
        from stages.slam.stage import SlamParams

        sub = SlamParams(map="submaps").config()
        cfg = replace(cfg, submaps=sub.submaps, submap_lengthscale_m=sub.submap_lengthscale_m)
    cases: list[tuple[str, Any]] = [
        (r.name, lambda c=0.0, step=1.0, r=r: run_folder_case(r, free_clearance=c, ray_step=step)) for r in a.runs]
    if not cases:
        cases = [("synthetic corridor", lambda c=0.0, step=1.0: synthetic_case(free_clearance=c, ray_step=step))]
    rows: list[tuple[str, Profile]] = []
    refine_rows: list[str] = []
    w = cfg.weighting("rich_slam")
    for name, load in cases:
        gt, scans = load()
        extra: dict[str, tuple[HilbertWeighting, Sequence[BeamSamples], float | None]] = {
            f"hilbert_gp (free weight {fw:g})": (replace(w, free_weight=fw), scans, None) for fw in a.free_weight}
        for c in a.free_clearance:
            extra[f"hilbert_gp (free clearance {c:g} m)"] = (w, load(c)[1], None)
        for step in a.ray_step:
            extra[f"hilbert_gp (ray step {step:g} m)"] = (w, load(step=step)[1], None)
        for s2e in a.endpoint_noise:
            extra[f"hilbert_gp (endpoint noise {s2e:g})"] = (w, scans, s2e)
        for e in a.outlier:
            extra[f"hilbert_gp (outlier {e:g})"] = (replace(w, outlier=e), scans, None)
        if a.no_et:
            extra["hilbert_gp (variance, no ET)"] = (cfg.weighting("rich_slam_no_et"), scans, None)
        test = np.linspace(len(scans) // 2, len(scans) - 1, a.scans).round().astype(int).tolist()
        new = [(name, p) for p in profiles(gt, scans, test, cfg, extra=extra)]
        rows += new
        print("\n".join(table(new)[2:]), flush=True)
        if a.refine:
            refine_rows += [f"| {name} " + r for r in refinement_bias(gt, scans, test, cfg)]
            print("\n".join(refine_rows[-6:]), flush=True)
    text = "\n".join(table(rows)) + "\n"
    if refine_rows:
        text += ("\n| data | objective | start | position error after [m] | yaw error after [deg] |\n"
                 "|---|---|---|---|---|\n" + "\n".join(refine_rows) + "\n")
    if a.out:
        a.out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
