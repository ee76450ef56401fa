"""Which way each weight moves the filter's heading, scan by scan, on the filter's own particles.

:mod:`likelihood_profile` scores scans against one map built along ground truth. In the filter every particle
scores a scan against a map built along its *own* path, and what the selection then does to the heading is a
shift of the cloud's weighted mean. This tool runs a filter and, at every scan, measures that shift for the
weight the filter uses and for *shadow* weights computed on the same particles, with maps built along the same
particle paths and resampled with them, that never enter the filter:

- ``grid``: the FastSLAM likelihood field (``fastslam_grid``'s weight, its own exponent);
- ``endpoints``: the Hilbert weight of the filter's map without the free samples' terms (``free_weight = 0``,
  the same map); the free samples' part is then the filter's weight minus it.

The *pull toward the truth* of a weight at scan k is ``-sign(ebar) (sum_i w_i e_i - ebar)``, where ``e_i`` is
particle i's heading error against ground truth, ``ebar`` their plain mean and ``w`` the weight's normalised
likelihoods over the particles (the scan's own factor, eq. 22, not the accumulated weights): the number of
degrees by which that scan's weight alone moves the cloud's mean heading towards the truth (negative: away).
Summed over a stretch of scans it says which weight steers the heading there, and where it goes wrong.

    python -m stages.slam.weight_pull RUN_DIR [--method rich_slam] [--seed 0] [--set n_particles=50 ...]
        [--windows 0,30,60,90] [--out table.md] [--npz record.npz]

RUN_DIR is a run folder with ``ingest/``, ``filter/`` and ``odometry/`` (``pipeline run odometry``), as for
:mod:`table3`. Numpy backend, global map, ``workers = 0`` (set for you).
"""

from __future__ import annotations

import argparse
import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from stages.slam.beam_sampling import BeamSamples
from stages.slam.rbpf import HilbertParticleMaps, wrap_angle
from stages.slam.rbpf import weigh_and_update as _weigh_and_update

F64 = npt.NDArray[np.floating[Any]]


def pull_toward_truth(yaw_error: npt.ArrayLike, log_likelihood: npt.ArrayLike) -> F64:
    """Per scan, the degrees by which a weight moves the cloud's mean heading towards the truth.

    ``yaw_error (T, Np)`` particle heading minus true heading (rad, any wrap), ``log_likelihood (T, Np)`` the
    weight's per-scan log-likelihoods. Returns ``(T,)`` in degrees: ``-sign(ebar) (sum_i w_i e_i - ebar)``
    with ``w = softmax(log_likelihood)`` and ``ebar`` the plain mean of the wrapped errors."""
    e = np.degrees(wrap_angle(np.asarray(yaw_error, dtype=np.float64)))
    ll = np.asarray(log_likelihood, dtype=np.float64)
    if e.shape != ll.shape or e.ndim != 2:
        raise ValueError(f"yaw_error {e.shape} and log_likelihood {ll.shape} must both be (scans, particles)")
    w = np.exp(ll - ll.max(axis=1, keepdims=True))
    w /= w.sum(axis=1, keepdims=True)
    ebar = e.mean(axis=1)
    return np.asarray(-np.sign(ebar) * (np.sum(w * e, axis=1) - ebar))


@dataclass
class ShadowedMaps:
    """``ParticleMaps`` that weigh and update ``main`` (the filter's maps, whose log-likelihood is returned) and,
    on the same poses, every map in ``shadows``, recording each one's per-scan log-likelihoods (``record``:
    name -> list of ``(Np,)``; ``"main"`` is the filter's). Resampling selects all of them alike."""

    main: Any
    shadows: dict[str, Any]
    record: dict[str, list[F64]] = field(default_factory=dict)

    def weigh_and_update(self, poses: F64, samples: BeamSamples) -> F64:
        ll = np.asarray(_weigh_and_update(self.main, poses, samples), dtype=np.float64)
        self.record.setdefault("main", []).append(ll.copy())
        for name, maps in self.shadows.items():
            s = np.asarray(_weigh_and_update(maps, poses, samples), dtype=np.float64)
            self.record.setdefault(name, []).append(s.copy())
        return ll

    def log_likelihood(self, poses: F64, samples: BeamSamples) -> F64:
        """Weights and update in one call (the filter always updates right after weighting)."""
        return self.weigh_and_update(poses, samples)

    def update(self, poses: F64, samples: BeamSamples) -> None:
        """Done in :meth:`log_likelihood`."""

    def map_of(self, k: int) -> tuple[F64, F64]:
        """Particle k's map of ``main`` (mean and covariance)."""
        theta, cov = self.main.map_of(k)
        return theta, cov

    def select(self, indices: npt.NDArray[np.int64]) -> None:
        self.main.select(indices)
        for maps in self.shadows.values():
            maps.select(indices)

    def close(self) -> None:
        for part in (self.main, *self.shadows.values()):
            close = getattr(part, "close", None)
            if close is not None:
                close()


def endpoint_shadow(maps: HilbertParticleMaps) -> HilbertParticleMaps:
    """A fresh copy of ``maps``' model that weighs endpoints only (``free_weight = 0``); its map is the same."""
    model = replace(maps.model, weighting=replace(maps.model.weighting, free_weight=0.0))
    return HilbertParticleMaps(maps.basis, len(maps.theta), model)


def window_table(t_s: F64, mean_error_deg: F64, pulls: dict[str, F64], edges: Sequence[float]) -> list[dict[str, Any]]:
    """Per window ``[a, b)`` of seconds: scans, the cloud's mean heading error and each weight's summed pull."""
    rows = []
    for a, b in itertools.pairwise(edges):
        m = (t_s >= a) & (t_s < b)
        rows.append({"from_s": a, "to_s": b, "scans": int(m.sum()),
                     "mean_error_deg": float(np.mean(mean_error_deg[m])) if m.any() else float("nan"),
                     **{name: float(np.sum(p[m])) for name, p in pulls.items()}})
    return rows


def markdown(rows: list[dict[str, Any]], names: Sequence[str]) -> str:
    head = "| seconds | scans | cloud's mean heading error (deg) | " + " | ".join(
        f"pull of {n} (deg)" for n in names) + " |"
    out = [head, "|" + "---|" * (3 + len(names))]
    for r in rows:
        out.append(f"| {r['from_s']:g}-{r['to_s']:g} | {r['scans']} | {r['mean_error_deg']:+.2f} | "
                   + " | ".join(f"{r[n]:+.2f}" for n in names) + " |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    from stages.slam import hilbert_map as hm
    from stages.slam.grid_map import GridParticleMaps, make_grid_spec
    from stages.slam.methods import domain_from_trajectory, run_method
    from stages.slam.stage import SlamParams
    from stages.slam.table3 import load_inputs, slam_overrides

    ap = argparse.ArgumentParser(prog="python -m stages.slam.weight_pull", description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("run", type=Path, help="run folder <runs>/<seq> with ingest/, filter/ and odometry/")
    ap.add_argument("--method", default="rich_slam", help="a Hilbert method (default rich_slam)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", dest="sets", action="append", default=[], help="slam parameter KEY=JSON")
    ap.add_argument("--windows", default="", help="window edges in seconds, e.g. 0,30,60,90 (default: thirds)")
    ap.add_argument("--out", type=Path, help="write the table as markdown here")
    ap.add_argument("--npz", type=Path, help="write the per-scan record (errors, log-likelihoods, pulls) here")
    a = ap.parse_args(argv)
    try:
        overrides: dict[str, Any] = {"workers": 0, **slam_overrides(a.sets)}
    except ValueError as exc:
        ap.error(str(exc))
    p = SlamParams(**overrides)
    t_ns, odo, samples, truth, motion = load_inputs(a.run, p)
    half, centre = domain_from_trajectory(odo[:, :2], p.domain_padding)
    basis = hm.make_basis(half, centre, p.n_basis, p.basis_kind)
    cfg = p.config()
    wrapped: list[ShadowedMaps] = []

    def shadow(maps: Any) -> Any:
        if not isinstance(maps, HilbertParticleMaps):
            raise SystemExit(f"weight_pull: {a.method} does not run on one in-process Hilbert map "
                             "(set slam.map = global, slam.backend = numpy, slam.grid_share = 0, slam.map_delay = 0)")
        grid = GridParticleMaps(make_grid_spec(basis.centre, basis.half_widths, cfg.grid_resolution),
                                len(maps.theta), cfg.grid, cfg.grid_likelihood_exponent)
        s = ShadowedMaps(maps, {"grid": grid, "endpoints": endpoint_shadow(maps)})
        wrapped.append(s)
        return s

    res = run_method(a.method, odo, samples, basis, cfg, a.seed, motion=motion, wrap_maps=shadow)
    rec = {k: np.stack(v) for k, v in wrapped[0].record.items()}
    particles = np.asarray(res.particles)
    tt, _, tyaw = truth
    true_yaw = np.interp(t_ns, tt, np.unwrap(tyaw))
    err = particles[:, :, 2] - true_yaw[:, None]
    pulls = {"the filter's weight": pull_toward_truth(err, rec["main"]),
             "its endpoints": pull_toward_truth(err, rec["endpoints"]),
             "its free samples": pull_toward_truth(err, rec["main"] - rec["endpoints"]),
             "the grid's likelihood field": pull_toward_truth(err, rec["grid"])}
    t_s = (t_ns - t_ns[0]) * 1e-9
    last = float(t_s[-1]) + 1e-6  # the last window holds the last scan
    edges = [float(x) for x in a.windows.split(",")] if a.windows else list(np.linspace(0.0, last, 4))
    edges[-1] = max(edges[-1], last)
    mean_err = np.degrees(wrap_angle(err)).mean(axis=1)
    rows = window_table(t_s, mean_err, pulls, edges)
    text = (f"{a.run.name}, {a.method}, seed {a.seed}, {cfg.n_particles} particles: pull toward the truth "
            f"(degrees of the cloud's mean heading, summed over the scans)\n\n" + markdown(rows, list(pulls)))
    print(text)
    if a.out:
        a.out.write_text(text + "\n")
    if a.npz:
        arrays: dict[str, Any] = {"t_s": t_s, "yaw_error": err, **{f"ll_{k}": v for k, v in rec.items()},
                                  **{f"pull_{k.replace(' ', '_')}": v for k, v in pulls.items()}}
        np.savez_compressed(a.npz, **arrays)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
