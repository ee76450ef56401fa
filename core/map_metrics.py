"""Map metrics of RMap Sec. IV-A on (N, 3) point clouds: Chamfer distances, F-score, D-Dist, per-axis CD.

``pred`` is the predicted / input map (radar map, completed map), ``gt`` the lidar map (RMap: the
``lidar_filtered`` map). Nearest neighbours come from ``scipy.spatial.cKDTree`` on float64 coordinates,
minimum over all neighbours (exact k = 1 queries). The conventions are those that reproduce the paper's
Table III on the authors' published maps (``shared/data/coloradar_maps/README.md``; checked to 0.0005 by
``tests/test_rmap_paper.py``):

- CD-l1 (PCN [20], PoinTr ``ChamferDistanceL1``): ``(mean_p min_g |p-g| + mean_g min_p |p-g|) / 2``;
- CD-l2 (eq. 1, [28], PoinTr ``ChamferDistanceL2``): ``mean_p min_g |p-g|^2 + mean_g min_p |p-g|^2``, a
  sum, not halved. Table III prints both in metres (m^2 for CD-l2) although the text says x1000; the x1000
  values are returned beside them (``*_x1000``);
- F-score at ``d`` (eq. 3-5, Tatarchenko et al. [30], the authors' Open3D computation): precision = share
  of ``pred`` with a ``gt`` point strictly nearer than ``d``, recall = share of ``gt`` with a ``pred`` point
  strictly nearer than ``d``, ``F = 2PR / (P + R)`` (0 when both are 0). This is the reported
  ``fscore_<d>``. On a 0.15 m voxel lattice with ``d = 0.15`` the face neighbours lie exactly on the
  threshold, so whether one counts is decided by the rounding of the stored float64 coordinates: the
  paper-compatible value is reproducible only on the coordinates exactly as published (float32 copies,
  recomputed centres or ``<=`` give 0.45x to 1.4x the published values);
- ``fscore_<d>_robust``: the same with the threshold lowered by ``ROBUST_TOL_FRACTION * d`` (0.1 % of the
  voxel, 0.15 mm at d = 0.15 m): on a lattice only coinciding voxels match ("predictions falling within
  the same voxel", Sec. IV-A), whatever the rounding; far below any real distance difference, so on
  continuous clouds (completed maps before downsampling) it equals the strict ``<`` value;
- D-Dist (eq. 6): for every ``gt`` point the distance to the nearest ``pred`` point; its percentiles
  50/75/90/95 with linear interpolation (numpy's default, ``method="linear"``). Table I pools these
  distances over the scenes of an environment (:func:`pooled_deviation_distribution`);
- per-axis CD (eq. 7, Table IV). Our reading of eq. 7: ``p_min`` / ``g_min`` are the 3D nearest
  neighbours (the same pairs as CD-l2), and each axis keeps only its squared coordinate difference,
  ``CD^x = mean_p (p^x - g_min(p)^x)^2 + mean_g (p_min(g)^x - g^x)^2``; hence ``CD^x + CD^y + CD^z = CD-l2``.
  (Table IV's input row, 0.267 + 0.223 + 0.576 = 1.066 against CD-l2 1.065, agrees with this reading;
  its RMap row, 0.278 against 0.279, too.);
- L/R ratio (Table I): number of lidar map points over radar map points; Table I averages the per-scene
  ratios over an environment's scenes.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

F64 = npt.NDArray[np.float64]
DDIST_PERCENTILES = (50.0, 75.0, 90.0, 95.0)
#: threshold reduction of the robust F-score, as a fraction of ``d`` (0.1 %: 0.15 mm at d = 0.15 m)
ROBUST_TOL_FRACTION = 1e-3


def _cloud(points: npt.ArrayLike, name: str) -> F64:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must be an (N, 3) array, got shape {arr.shape}")
    return arr


def nearest(query: npt.ArrayLike, ref: npt.ArrayLike) -> tuple[F64, npt.NDArray[np.int64]]:
    """For every query point: the distance to, and index of, its nearest reference point."""
    q, r = _cloud(query, "query"), _cloud(ref, "ref")
    if len(r) == 0:
        return np.full(len(q), np.inf), np.full(len(q), -1, np.int64)
    if len(q) == 0:
        return np.zeros(0), np.zeros(0, np.int64)
    d, i = cKDTree(r).query(q, k=1, workers=-1)
    return np.asarray(d, np.float64), np.asarray(i, np.int64)


class MapComparison:
    """Nearest neighbours of ``pred`` in ``gt`` and of ``gt`` in ``pred``, computed once for all metrics."""

    def __init__(self, pred: npt.ArrayLike, gt: npt.ArrayLike) -> None:
        self.pred = _cloud(pred, "pred")
        self.gt = _cloud(gt, "gt")
        self.d_pg, self.i_pg = nearest(self.pred, self.gt)  # pred -> nearest gt
        self.d_gp, self.i_gp = nearest(self.gt, self.pred)  # gt -> nearest pred

    @property
    def empty(self) -> bool:
        return len(self.pred) == 0 or len(self.gt) == 0

    def chamfer_l1(self) -> float:
        if self.empty:
            return float("nan")
        return float((self.d_pg.mean() + self.d_gp.mean()) / 2.0)

    def chamfer_l2(self) -> float:
        if self.empty:
            return float("nan")
        return float(np.mean(self.d_pg**2) + np.mean(self.d_gp**2))

    def fscore(self, d: float = 0.15, tie_tol: float = 0.0) -> tuple[float, float, float]:
        """(F-score, precision, recall) at distance ``d`` (eq. 3-5): strict ``dist < d - tie_tol`` (m).

        ``tie_tol = 0`` is the paper-compatible value; :meth:`fscore_robust` lowers the threshold.
        """
        if self.empty:
            return float("nan"), float("nan"), float("nan")
        thr = d - tie_tol
        p = float(np.mean(self.d_pg < thr))
        r = float(np.mean(self.d_gp < thr))
        f = 2 * p * r / (p + r) if p + r > 0 else 0.0
        return f, p, r

    def fscore_robust(self, d: float = 0.15, fraction: float = ROBUST_TOL_FRACTION) -> tuple[float, float, float]:
        """(F, P, R) with the threshold ``d * (1 - fraction)``: lattice ties at ``d`` never count."""
        return self.fscore(d, fraction * d)

    def deviation_distribution(self, percentiles: Sequence[float] = DDIST_PERCENTILES) -> F64:
        """Percentiles of the gt -> nearest pred distances (eq. 6)."""
        if self.empty:
            return np.full(len(percentiles), np.nan)
        return np.percentile(self.d_gp, list(percentiles), method="linear")

    def chamfer_per_axis(self) -> F64:
        """(CD^x, CD^y, CD^z) of eq. 7."""
        if self.empty:
            return np.full(3, np.nan)
        a = np.mean((self.pred - self.gt[self.i_pg]) ** 2, axis=0)
        b = np.mean((self.pred[self.i_gp] - self.gt) ** 2, axis=0)
        return np.asarray(a + b, np.float64)


def chamfer_l1(pred: npt.ArrayLike, gt: npt.ArrayLike) -> float:
    """CD-l1 (PoinTr ChamferDistanceL1): mean of both directions' mean nearest distances, halved."""
    return MapComparison(pred, gt).chamfer_l1()


def chamfer_l2(pred: npt.ArrayLike, gt: npt.ArrayLike) -> float:
    """CD-l2 (eq. 1, PoinTr ChamferDistanceL2): sum of both directions' mean squared nearest distances."""
    return MapComparison(pred, gt).chamfer_l2()


def fscore(pred: npt.ArrayLike, gt: npt.ArrayLike, d: float = 0.15, tie_tol: float = 0.0) -> float:
    """F-score at ``d`` (eq. 3-5), paper-compatible (strict ``<`` on float64) unless ``tie_tol`` > 0."""
    return MapComparison(pred, gt).fscore(d, tie_tol)[0]


def fscore_robust(pred: npt.ArrayLike, gt: npt.ArrayLike, d: float = 0.15,
                  fraction: float = ROBUST_TOL_FRACTION) -> float:
    """F-score at ``d * (1 - fraction)``: on a voxel lattice only coinciding voxels match."""
    return MapComparison(pred, gt).fscore_robust(d, fraction)[0]


def deviation_distribution(
    pred: npt.ArrayLike, gt: npt.ArrayLike, percentiles: Sequence[float] = DDIST_PERCENTILES
) -> F64:
    """D-Dist (eq. 6): percentiles of the distance from each gt point to its nearest pred point."""
    return MapComparison(pred, gt).deviation_distribution(percentiles)


def chamfer_per_axis(pred: npt.ArrayLike, gt: npt.ArrayLike) -> F64:
    """(CD^x, CD^y, CD^z) of eq. 7."""
    return MapComparison(pred, gt).chamfer_per_axis()


def pooled_deviation_distribution(
    distances: Sequence[npt.ArrayLike], percentiles: Sequence[float] = DDIST_PERCENTILES
) -> F64:
    """Table I's D-Dist of an environment: percentiles of the gt -> pred distances of all its scenes pooled."""
    parts = [np.asarray(d, np.float64).ravel() for d in distances]
    pooled = np.concatenate(parts) if parts else np.zeros(0)
    if len(pooled) == 0:
        return np.full(len(percentiles), np.nan)
    return np.percentile(pooled, list(percentiles), method="linear")


def lr_ratio(lidar: npt.ArrayLike | int, radar: npt.ArrayLike | int) -> float:
    """L/R ratio of Table I: lidar map points over radar map points (counts or clouds)."""
    n_l = lidar if isinstance(lidar, int) else len(np.asarray(lidar))
    n_r = radar if isinstance(radar, int) else len(np.asarray(radar))
    return float(n_l) / n_r if n_r else float("nan")


#: edges (m) of the bins of horizontal distance from the path; the last bin is everything beyond the last edge
PATH_BINS_M = (0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0)


def path_bin_names(edges: Sequence[float] = PATH_BINS_M) -> list[str]:
    """``0-1m``, ..., ``6-7m``, ``>7m``: the bins of :func:`recall_by_path_distance`."""
    return [f"{lo:g}-{hi:g}m" for lo, hi in itertools.pairwise(edges)] + [f">{edges[-1]:g}m"]


def recall_by_path_distance(cmp: MapComparison, path: npt.ArrayLike, d: float = 0.15,
                            edges: Sequence[float] = PATH_BINS_M) -> dict[str, float]:
    """Recall (the paper's strict ``dist < d``) of the ground-truth points binned by their horizontal distance
    to the nearest point of ``path (P, 2 or 3)``: ``recall_path_<bin>`` and the bin's point count
    ``n_gt_path_<bin>`` (for pooling over scenes); a bin without points has recall nan."""
    p = np.asarray(path, np.float64)
    if p.size == 0 or len(cmp.gt) == 0:
        return {}
    p = p.reshape(len(p), -1)[:, :2]
    dist, _ = cKDTree(p).query(cmp.gt[:, :2], k=1, workers=-1)
    hit = cmp.d_gp < d
    bins = np.digitize(dist, np.asarray(edges[1:]))  # 0 .. len(edges) - 1
    out: dict[str, float] = {}
    for b, name in enumerate(path_bin_names(edges)):
        m = bins == b
        out[f"recall_path_{name}"] = float(hit[m].mean()) if m.any() else float("nan")
        out[f"n_gt_path_{name}"] = float(m.sum())
    return out


def map_metrics(pred: npt.ArrayLike, gt: npt.ArrayLike, d: float = 0.15) -> dict[str, float]:
    """All map metrics under the report's metric names (``cd_l1``, ``cd_l2``, ``fscore_0.15``, ``ddist_p50``..)."""
    return comparison_metrics(MapComparison(pred, gt), d)


def comparison_metrics(cmp: MapComparison, d: float = 0.15) -> dict[str, float]:
    """:func:`map_metrics` of an existing :class:`MapComparison` (its nearest neighbours reused)."""
    f, p, r = cmp.fscore(d)
    fr, pr, rr = cmp.fscore_robust(d)
    cd1, cd2 = cmp.chamfer_l1(), cmp.chamfer_l2()
    out = {
        "cd_l1": cd1,
        "cd_l2": cd2,
        "cd_l1_x1000": cd1 * 1000.0,
        "cd_l2_x1000": cd2 * 1000.0,
        f"fscore_{d:g}": f,
        f"precision_{d:g}": p,
        f"recall_{d:g}": r,
        f"fscore_{d:g}_robust": fr,
        f"precision_{d:g}_robust": pr,
        f"recall_{d:g}_robust": rr,
    }
    for q, v in zip(DDIST_PERCENTILES, cmp.deviation_distribution(), strict=True):
        out[f"ddist_p{q:g}"] = float(v)
    for axis, v in zip("xyz", cmp.chamfer_per_axis(), strict=True):
        out[f"cd_{axis}"] = float(v)
    out["n_pred"] = float(len(cmp.pred))
    out["n_gt"] = float(len(cmp.gt))
    return out
