"""RMap's result tables side by side with the paper (Tables I, III, IV, VI), as markdown.

Pure functions over per-scene results (:class:`SceneResult`, collected from run folders by
:func:`stages.evaluate.rmap_results.collect_scene_results`); the paper's numbers come from
:mod:`core.rmap_paper`. Conventions (``shared/data/coloradar_maps/README.md``):

- a table's "Overall" CD-l1, CD-l2, F-score and CD^x/y/z are the mean of its scene rows (the paper's
  Overall rows are, to 0.0005); Overall D-Dist pools the ground-truth distances of all its scenes when
  every row carries them (``SceneResult.distances``), else it is the mean of the rows' percentiles, and
  the table says which (the paper's Overall D-Dist is not the mean of its rows; probably pooled);
- Table I: L/R is the mean of the per-scene ratios, D-Dist pooled over the environment's scenes;
- scenes whose ground truth was rebuilt from published patches are marked with a dagger.

Map ``method`` names are the artifacts': ``radar_map`` (the input), ``completed_map`` (ours), ``lidar_map``.
When the complete stage ran several models (``complete.models``) the evaluate stage also
writes ``completed_map_<model>`` (one per model, the configured one included) and ``radar_map_band`` (the
pre-filtered input); Tables III, IV and VI then have one row per map (:func:`table_iii_models`,
:func:`table_iv_models`, :func:`table_vi`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from core import rmap_paper as paper
from core.map_metrics import DDIST_PERCENTILES, pooled_deviation_distribution
from stages.evaluate.tables import fmt, markdown

F64 = npt.NDArray[np.float64]
INPUT, COMPLETED, LIDAR = "radar_map", "completed_map", "lidar_map"
BAND = "radar_map_band"
MODEL_PREFIX = "completed_map_"
#: row labels of the completion models (others: their name)
MODEL_LABELS = {"uppointr": "UpPoinTr", "voxel": "voxel U-Net"}
SCORE_KEYS = ("cd_l1", "cd_l2", "fscore_0.15")
DDIST_KEYS = paper.DDIST_KEYS
AXIS_KEYS = ("cd_l2", "cd_x", "cd_y", "cd_z")
REBUILT_MARK = "†"


@dataclass(frozen=True)
class SceneResult:
    """What one map sequence's run gives the tables.

    ``metrics[method][metric]``: the evaluate stage's map metrics (methods ``radar_map``,
    ``completed_map``); ``rebuilt``: ground truth rebuilt from published patches (index.json ``source``);
    ``a_test``, ``n_patches``, ``inference_s`` (network seconds over all patches), ``device``: from the
    patches and complete manifests; ``distances[method]``: ground-truth -> map nearest distances, for
    pooled D-Dist (optional).
    """

    scene: str
    metrics: Mapping[str, Mapping[str, float]]
    seq: str = ""
    rebuilt: bool = False
    a_test: float | None = None
    n_patches: int | None = None
    inference_s: float | None = None
    device: str = ""
    distances: Mapping[str, F64] = field(default_factory=dict)

    @property
    def environment(self) -> str:
        return paper.environment(self.scene)

    def get(self, method: str, metric: str) -> float:
        """A metric of one map, NaN when absent."""
        return float(self.metrics.get(method, {}).get(metric, float("nan")))


@dataclass(frozen=True)
class Table:
    """A built table: header, rows of cells, notes printed under it."""

    title: str
    headers: list[str]
    rows: list[list[str]]
    notes: list[str] = field(default_factory=list)

    def markdown(self) -> str:
        out = [f"### {self.title}", "", markdown(self.headers, self.rows)]
        if self.notes:
            out += [""] + [f"- {n}" for n in self.notes]
        return "\n".join(out) + "\n"


def scene_name(seq: str) -> str:
    """``rmap_arpg_lab_run0`` -> ``arpg_lab_run0``."""
    return seq.removeprefix("rmap_")


def ddist_cell(values: Sequence[float]) -> str:
    """``[p50, p75, p90, p95]``; '–' when none is known."""
    if all(v is None or not np.isfinite(v) for v in values):
        return "–"
    return "[" + ", ".join(fmt(float(v)) for v in values) + "]"


def overall(results: Sequence[SceneResult], method: str) -> tuple[dict[str, float], bool]:
    """Mean of the rows for CD/F/CD^x/y/z; D-Dist pooled when every row has distances (second value True)."""
    rows = [r for r in results if method in r.metrics]
    keys = (*SCORE_KEYS, "fscore_0.15_robust", "cd_x", "cd_y", "cd_z", *DDIST_KEYS)
    out = {k: float(np.mean([r.get(method, k) for r in rows])) if rows else float("nan") for k in keys}
    pooled = bool(rows) and all(method in r.distances for r in rows)
    if pooled:
        dd = pooled_deviation_distribution([r.distances[method] for r in rows], DDIST_PERCENTILES)
        out.update(dict(zip(DDIST_KEYS, map(float, dd), strict=True)))
    return out, pooled


def _scores(m: Mapping[str, float]) -> list[str]:
    return [fmt(m.get("cd_l1")), fmt(m.get("cd_l2")), fmt(m.get("fscore_0.15")),
            ddist_cell([m.get(k, float("nan")) for k in DDIST_KEYS])]


def _nan_scores() -> list[str]:
    return ["–"] * 4


def _label(r: SceneResult | None, scene: str) -> str:
    return scene + (f" {REBUILT_MARK}" if r is not None and r.rebuilt else "")


def _test_results(results: Iterable[SceneResult]) -> dict[str, SceneResult]:
    return {r.scene: r for r in results if r.scene in paper.TABLE_III}


def _coverage_note(have: Sequence[str], same_row: bool = False) -> list[str]:
    missing = [s for s in paper.TEST_SCENES if s not in have]
    if not missing:
        return []
    same = "; the row 'paper, same scenes' is the mean of the paper's rows for ours" if same_row else ""
    return [f"ours covers {len(have)} of the paper's {len(paper.TEST_SCENES)} test scenes (absent: "
            f"{', '.join(missing)}){same}."]


def _rebuilt_note(results: Iterable[SceneResult]) -> list[str]:
    rebuilt = [r.scene for r in results if r.rebuilt]
    if not rebuilt:
        return []
    return [f"{REBUILT_MARK} ground truth rebuilt as the union of the authors' published ground-truth patches "
            f"(no lidar_filtered map file published): {', '.join(rebuilt)}."]


def _ddist_note(pooled: bool) -> str:
    return ("Overall D-Dist: ground-truth distances pooled over the scenes." if pooled else
            "Overall D-Dist: mean of the rows' percentiles.") + (
            " The paper's Overall D-Dist is not the mean of its rows (input p95 1.181 against 1.109); it is "
            "probably pooled, which cannot be checked without its 3 absent scenes.")


def model_methods(results: Iterable[SceneResult]) -> list[str]:
    """The ``completed_map_<model>`` methods present, UpPoinTr and voxel first."""
    found = {m for r in results for m in r.metrics if m.startswith(MODEL_PREFIX)}
    order = [MODEL_PREFIX + m for m in MODEL_LABELS]
    return [m for m in order if m in found] + sorted(found - set(order))


def model_label(method: str) -> str:
    """``completed_map_voxel`` -> ``voxel U-Net``; the input maps by their role."""
    if method == INPUT:
        return "input"
    if method == BAND:
        return "pre-filtered input"
    name = method.removeprefix(MODEL_PREFIX)
    return MODEL_LABELS.get(name, name)


def map_rows(results: Sequence[SceneResult]) -> list[str]:
    """The maps of the per-model tables: input, pre-filtered input (when written), then every model."""
    return [INPUT, *([BAND] if any(BAND in r.metrics for r in results) else []), *model_methods(results)]


def _model_cells(m: Mapping[str, float], seconds: float | None = None) -> list[str]:
    return [fmt(m.get("cd_l1")), fmt(m.get("cd_l2")), fmt(m.get("fscore_0.15")), fmt(m.get("fscore_0.15_robust")),
            ddist_cell([m.get(k, float("nan")) for k in DDIST_KEYS]), fmt(seconds, 1) if seconds is not None else "–"]


def _paper_cells(s: paper.Scores | Mapping[str, float]) -> list[str]:
    m = s.metrics() if isinstance(s, paper.Scores) else s
    return [fmt(m.get("cd_l1")), fmt(m.get("cd_l2")), fmt(m.get("fscore_0.15")), "–",
            ddist_cell([m.get(k, float("nan")) for k in DDIST_KEYS]), "–"]


def _seconds(r: SceneResult, method: str) -> float | None:
    v = r.get(method, "model_seconds")
    return v if np.isfinite(v) else None


def table_iii_models(results: Iterable[SceneResult]) -> Table:
    """Table III with one row per map and scene (paper input, input, pre-filtered input, each model, paper
    RMap), then the Overall block (means; network seconds summed)."""
    res = _test_results(results)
    found = list(res.values())
    methods = map_rows(found)
    headers = ["scene", "map", "CD-l1", "CD-l2", "F", "F robust", "D-Dist", "network [s]"]
    rows = []
    for scene, prow in paper.TABLE_III.items():
        r = res.get(scene)
        if r is None:
            continue
        label = _label(r, scene)
        rows.append([label, "paper input", *_paper_cells(prow.input)])
        for m in methods:
            if m in r.metrics:
                rows.append([label, model_label(m), *_model_cells(r.metrics[m], _seconds(r, m))])
        rows.append([label, "paper RMap", *_paper_cells(prow.rmap)])
    rows.append(["**Overall**", "paper input", *_paper_cells(paper.TABLE_III_OVERALL.input)])
    pooled = True
    for m in methods:
        o, p_m = overall(found, m)
        pooled = pooled and p_m
        secs = [_seconds(r, m) for r in found if m in r.metrics]
        total = float(sum(s for s in secs if s is not None)) if secs and all(s is not None for s in secs) else None
        rows.append(["**Overall**", model_label(m), *_model_cells(o, total)])
    rows.append(["**Overall**", "paper RMap", *_paper_cells(paper.TABLE_III_OVERALL.rmap)])
    notes = _coverage_note(list(res), same_row=False)
    if len(res) < len(paper.TEST_SCENES):
        rows.append(["paper, same scenes", "paper input", *_paper_cells(_paper_mean([paper.TABLE_III[s].input
                                                                                     for s in res]))])
        rows.append(["paper, same scenes", "paper RMap", *_paper_cells(_paper_mean([paper.TABLE_III[s].rmap
                                                                                    for s in res]))])
        notes.append("'paper, same scenes': the mean of the paper's rows for the scenes we have.")
    counts = {m: sum(m in r.metrics for r in found) for m in methods}
    short = [f"{model_label(m)} {n}" for m, n in counts.items() if n < len(found)]
    if short:
        notes.append(f"maps present on fewer than all {len(found)} scenes (their Overall is over those): "
                     f"{', '.join(short)}.")
    notes += _rebuilt_note(found)
    notes.append(_ddist_note(pooled))
    notes.append("F: paper-exact (strict < 0.15 m in float64, the paper's convention); F robust: threshold 0.1 % "
                 "below 0.15 m, so lattice ties one voxel away never count. network [s]: the completion network's "
                 "seconds on this run's device (Overall: the total). Ground truth: lidar_filtered; CD-l1 in m, CD-l2 "
                 "in m². Paper erratum: outdoors_run4 input F printed 0.0123, read 0.123.")
    return Table("RMap Table III, one row per map: input, pre-filtered input and each completion model against the "
                 "lidar map", headers, rows, notes)


def table_iv_models(results: Iterable[SceneResult]) -> Table:
    """Table IV with one row per map: overall CD-l2 and per-axis CD (eq. 7), the paper's two rows around ours."""
    res = list(_test_results(results).values())
    headers = ["map", "CD-l2", "CD^x", "CD^y", "CD^z"]
    rows = [["paper input", *[fmt(paper.TABLE_IV["input"][k]) for k in AXIS_KEYS]]]
    for m in map_rows(res):
        o, _ = overall(res, m)
        rows.append([model_label(m), *[fmt(o.get(k)) for k in AXIS_KEYS]])
    rows.append(["paper RMap", *[fmt(paper.TABLE_IV["rmap"][k]) for k in AXIS_KEYS]])
    notes = _coverage_note([r.scene for r in res]) + _rebuilt_note(res)
    notes.append("m²; ours: mean over the test scenes of CD^x = mean_p (p^x - g_min(p)^x)² + "
                 "mean_g (p_min(g)^x - g^x)² with 3D nearest neighbours, so CD^x + CD^y + CD^z = CD-l2.")
    return Table("RMap Table IV, one row per map: Chamfer distance per axis", headers, rows, notes)


def table_iii(results: Iterable[SceneResult]) -> Table:
    """Table III side by side: paper input | ours input | paper RMap | ours completed, Overall row last."""
    res = _test_results(results)
    metric_heads = ["CD-l1", "CD-l2", "F", "D-Dist"]
    headers = ["scene", *[f"{g} {h}" for g in ("paper input", "ours input", "paper RMap", "ours completed")
                          for h in metric_heads]]
    rows = []
    for scene, prow in paper.TABLE_III.items():
        r = res.get(scene)
        ours_in = _scores(r.metrics[INPUT]) if r is not None and INPUT in r.metrics else _nan_scores()
        ours_c = _scores(r.metrics[COMPLETED]) if r is not None and COMPLETED in r.metrics else _nan_scores()
        rows.append([_label(r, scene), *_scores(prow.input.metrics()), *ours_in,
                     *_scores(prow.rmap.metrics()), *ours_c])
    found = list(res.values())
    o_in, pooled_in = overall(found, INPUT)
    o_c, pooled_c = overall(found, COMPLETED)
    rows.append(["**Overall**", *_scores(paper.TABLE_III_OVERALL.input.metrics()), *_scores(o_in),
                 *_scores(paper.TABLE_III_OVERALL.rmap.metrics()), *_scores(o_c)])
    notes = _coverage_note(list(res), same_row=True)
    if len(res) < len(paper.TEST_SCENES):
        same_in = _paper_mean([paper.TABLE_III[s].input for s in res])
        same_rm = _paper_mean([paper.TABLE_III[s].rmap for s in res])
        rows.append(["paper, same scenes", *_scores(same_in), *_nan_scores(), *_scores(same_rm), *_nan_scores()])
    n_in, n_c = (sum(m in r.metrics for r in found) for m in (INPUT, COMPLETED))
    if 0 < n_c < n_in:
        notes.append(f"ours completed Overall: the {n_c} scenes with a completed map (input: {n_in}).")
    notes += _rebuilt_note(found)
    notes.append(_ddist_note(pooled_in and (pooled_c or not any(COMPLETED in r.metrics for r in found))))
    robust = ", ".join(f"{name} {fmt(o['fscore_0.15_robust'])}" for name, o, method in
                       (("input", o_in, INPUT), ("completed", o_c, COMPLETED))
                       if any(method in r.metrics for r in found))
    if robust:
        notes.append(f"Robust F-score (threshold 0.1 % below 0.15 m: lattice ties never count), Overall: {robust}.")
    notes.append("Ground truth: lidar_filtered. CD-l1 in m, CD-l2 in m², F-score at 0.15 m (strict <, float64: "
                 "the paper's convention). Paper erratum: outdoors_run4 input F printed 0.0123, read 0.123.")
    return Table("RMap Table III: input radar map and completed map against the lidar map", headers, rows, notes)


def _paper_mean(rows: Sequence[paper.Scores]) -> dict[str, float]:
    ms = [r.metrics() for r in rows]
    return {k: float(np.mean([m[k] for m in ms])) if ms else float("nan") for k in paper.MAP_KEYS}


def table_iv(results: Iterable[SceneResult]) -> Table:
    """Table IV: overall CD-l2 and per-axis CD (eq. 7), input and completed maps, paper beside ours."""
    res = list(_test_results(results).values())
    headers = ["map", *[f"{w} {k}" for k in ("CD-l2", "CD^x", "CD^y", "CD^z") for w in ("paper", "ours")]]
    rows = []
    for label, method, prow in (("Input map", INPUT, paper.TABLE_IV["input"]),
                                ("RMap / ours completed", COMPLETED, paper.TABLE_IV["rmap"])):
        o, _ = overall(res, method)
        cells = []
        for k in AXIS_KEYS:
            cells += [fmt(prow[k]), fmt(o.get(k))]
        rows.append([label, *cells])
    notes = _coverage_note([r.scene for r in res]) + _rebuilt_note(res)
    notes.append("m²; ours: mean over the test scenes of CD^x = mean_p (p^x - g_min(p)^x)² + "
                 "mean_g (p_min(g)^x - g^x)² with 3D nearest neighbours, so CD^x + CD^y + CD^z = CD-l2.")
    return Table("RMap Table IV: Chamfer distance per axis", headers, rows, notes)


def table_vi(results: Iterable[SceneResult], a_values: Sequence[int] = (1, 2, 4, 8)) -> Table:
    """Table VI: per a_test the completed maps' overall scores, total patches and inference time, paper beside ours.

    ``results`` holds one :class:`SceneResult` per (scene, a_test) run; rows are ``a_values`` plus any
    other a_test found. Ours: mean over the test scenes of that a_test (their number is given), total
    patches, total network seconds and the device they ran on.
    """
    by_a: dict[float, list[SceneResult]] = {}
    for r in results:
        if r.a_test is not None and r.scene in paper.TABLE_III:
            by_a.setdefault(float(r.a_test), []).append(r)
    a_all = sorted({float(a) for a in a_values} | set(by_a))
    headers = ["a_test", "source", "scenes", "CD-l1", "CD-l2", "F", "D-Dist", "total patches",
               "inference [s]", "device", "parameters"]
    rows = []
    for a in a_all:
        prow = paper.TABLE_VI.get(int(a)) if float(a).is_integer() else None
        a_txt = fmt(a, 0) if float(a).is_integer() else fmt(a, 2)
        if prow is not None:
            rows.append([a_txt, "paper", "21", *_scores(prow.scores.metrics()), str(prow.patches),
                         fmt(prow.inference_s, 0), "RTX 6000", "–"])
        rs = by_a.get(a, [])
        models = model_methods(rs)
        if rs and models:  # one row per completion model (complete.models)
            devices = sorted({r.device for r in rs if r.device})
            for m in models:
                mrs = [r for r in rs if m in r.metrics]
                o, _ = overall(mrs, m)
                patches = [r.get(m, "n_patches") for r in mrs]
                secs = [r.get(m, "model_seconds") for r in mrs]
                params = {r.get(m, "n_parameters") for r in mrs}
                rows.append([a_txt, f"ours {model_label(m)}", str(len(mrs)), *_scores(o),
                             str(int(sum(patches))) if all(np.isfinite(patches)) else "–",
                             fmt(float(sum(secs)), 1) if all(np.isfinite(secs)) else "–", ", ".join(devices) or "–",
                             _param_cell(params)])
        elif rs:
            o, _ = overall(rs, COMPLETED)
            patches = [r.n_patches for r in rs if r.n_patches is not None]
            secs = [r.inference_s for r in rs if r.inference_s is not None]
            devices = sorted({r.device for r in rs if r.device})
            rows.append([a_txt, "ours", str(len(rs)), *_scores(o),
                         str(sum(patches)) if len(patches) == len(rs) else "–",
                         fmt(sum(secs), 1) if len(secs) == len(rs) else "–", ", ".join(devices) or "–",
                         _param_cell({r.get(COMPLETED, "n_parameters") for r in rs})])
        elif prow is not None:
            rows.append([a_txt, "ours", "0", *_nan_scores(), "–", "–", "–", "–"])
    notes = ["Paper: AdaPoinTr trained with a_train = 16, one patch at a time on an RTX 6000, 21 test scenes. "
             "Ours: the completed maps; patches t = floor(a n_R / N_R) per scene; inference = network seconds; "
             "parameters = the network's trainable parameter count. The voxel U-Net reads no patches (its row "
             "does not depend on a_test)."]
    unique = {r.scene: r for rs in by_a.values() for r in rs}
    notes += _rebuilt_note(unique.values())
    return Table("RMap Table VI: completion at several a_test", headers, rows, notes)


def _param_cell(values: Iterable[float]) -> str:
    known = sorted({int(v) for v in values if np.isfinite(v)})
    return ", ".join(f"{v:,}" for v in known) or "–"


def table_i(results: Iterable[SceneResult]) -> Table:
    """Table I: per environment the scene count, mean per-scene L/R and pooled D-Dist of the input radar map."""
    by_env: dict[str, list[SceneResult]] = {}
    for r in results:
        by_env.setdefault(r.environment, []).append(r)
    headers = ["environment", "paper scenes", "ours scenes", "paper L/R", "ours L/R", "paper D-Dist", "ours D-Dist"]
    rows = []
    envs = [*paper.TABLE_I, *sorted(set(by_env) - set(paper.TABLE_I))]
    pooled_all = True
    for env in envs:
        prow = paper.TABLE_I.get(env)
        rs = by_env.get(env, [])
        lr = float(np.mean([r.get(INPUT, "lr_ratio") for r in rs])) if rs else float("nan")
        if rs and all(INPUT in r.distances for r in rs):
            dd = list(pooled_deviation_distribution([r.distances[INPUT] for r in rs]))
        else:
            pooled_all = pooled_all and not rs
            dd = [float("nan")] * 4
        rows.append([env, str(prow.n_scenes) if prow else "–", str(len(rs)), fmt(prow.lr_ratio, 2) if prow else "–",
                     fmt(lr, 2), ddist_cell(prow.ddist) if prow else "–", ddist_cell(dd)])
    every = [r for rs in by_env.values() for r in rs]
    lr_all = float(np.mean([r.get(INPUT, "lr_ratio") for r in every])) if every else float("nan")
    dd_all = (list(pooled_deviation_distribution([r.distances[INPUT] for r in every]))
              if every and all(INPUT in r.distances for r in every) else [float("nan")] * 4)
    o = paper.TABLE_I_OVERALL
    rows.append(["**Overall**", str(o.n_scenes), str(len(every)), fmt(o.lr_ratio, 2), fmt(lr_all, 2),
                 ddist_cell(o.ddist), ddist_cell(dd_all)])
    notes = ["L/R: mean over the environment's scenes of n(lidar_filtered) / n(radar); D-Dist: ground-truth -> "
             "radar distances pooled over its scenes" + ("" if pooled_all else " (– where the maps were not read)")
             + ".", "Paper errata: outdoors has 10 scenes (printed 9); the arpg_lab and ec_hallways D-Dist rows "
             "look swapped."]
    notes += _rebuilt_note(r for rs in by_env.values() for r in rs)
    return Table("RMap Table I: lidar and radar maps per environment", headers, rows, notes)


def report(results: Sequence[SceneResult], sweep: Sequence[SceneResult] = (), figure: str | None = None) -> str:
    """Tables I, III, IV and (when ``sweep`` holds runs at several a_test) VI, as one markdown section.

    ``figure``: a relative path of the top-view image (:func:`stages.evaluate.rmap_results.plot_run_top_views`).
    """
    per_model = bool(model_methods(results))
    parts = ["## RMap on the ColoRadar map sets, side by side with the paper", "",
             table_i(results).markdown(),
             (table_iii_models(results) if per_model else table_iii(results)).markdown(),
             (table_iv_models(results) if per_model else table_iv(results)).markdown()]
    if sweep:
        parts.append(table_vi(sweep).markdown())
    if figure:
        parts.append(f"![top views of the input, completed and lidar maps]({figure})\n")
    return "\n".join(parts)
