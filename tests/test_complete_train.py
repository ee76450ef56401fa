"""Training tooling: resume equals an uninterrupted run, the time limit stops with a state, map-set training
(--maps) with its validation split, bad --maps paths as one-line errors."""

from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pa = pytest.importorskip("pyarrow")
import pyarrow.parquet as pq  # noqa: E402
from rich.console import Console  # noqa: E402

from core.errors import UserError  # noqa: E402
from sources.mapset import read_index  # noqa: E402
from stages.complete.maps import map_split, validation_scenes  # noqa: E402
from stages.complete.model import SIZES, ModelConfig  # noqa: E402
from stages.complete.synthetic import make_patches, scene_surface  # noqa: E402
from stages.complete.train import Selection, TrainConfig, load_state, train  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TINY = ModelConfig(
    n_input=256, n_query=64, up_factors=(1, 2, 2), centers=(128, 64), grouper_k=8, embed_dim=32,
    encoder_depth=2, decoder_depth=2, num_heads=4, graph_k=4, global_dim=64, hidden_dim=64, up_dim=16, up_k=4,
)


@pytest.fixture(autouse=True)
def _tiny(monkeypatch: pytest.MonkeyPatch) -> object:
    monkeypatch.setitem(SIZES, "tiny", TINY)
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _cfg(**kw: object) -> TrainConfig:
    base = dict(size="tiny", epochs=3, batch_size=2, lr=2e-3, seed=0, patches_per_epoch=4)
    base.update(kw)
    return TrainConfig(**base)  # type: ignore[arg-type]


def test_resume_equals_uninterrupted(tmp_path: Path) -> None:
    tr = make_patches(6, seed=2, n_radar=256, n_lidar=256)
    va = make_patches(2, seed=3, n_radar=256, n_lidar=256)
    full = train(tr, va, _cfg(), torch.device("cpu"), state_path=tmp_path / "full.pt")
    part = train(tr, va, _cfg(epochs=2), torch.device("cpu"), state_path=tmp_path / "part.pt")
    assert len(part.history) == 2
    # the budget may grow on resume; the rest of the settings must match
    resumed = train(tr, va, _cfg(epochs=3), torch.device("cpu"), state_path=tmp_path / "part.pt", resume=True)
    assert [h["epoch"] for h in resumed.history] == [1, 2, 3]
    for a, b in zip(full.history, resumed.history, strict=True):
        assert a["train_loss"] == b["train_loss"] and a["val_cd_l2_m2"] == b["val_cd_l2_m2"]
    sa, sb = full.model.state_dict(), resumed.model.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert load_state(tmp_path / "part.pt")["history"][-1]["epoch"] == 3
    with pytest.raises(UserError, match="other settings"):
        train(tr, va, _cfg(lr=1e-3), torch.device("cpu"), state_path=tmp_path / "part.pt", resume=True)


def test_time_limit_stops_with_state_and_resumes(tmp_path: Path) -> None:
    tr = make_patches(4, seed=2, n_radar=256, n_lidar=256)
    state = tmp_path / "s.pt"
    res = train(tr, [], _cfg(epochs=5, time_limit_s=0.0), torch.device("cpu"), state_path=state)
    assert len(res.history) == 1 and res.meta.train["stopped_early"] is True
    assert len(load_state(state)["history"]) == 1
    more = train(tr, [], _cfg(epochs=5, time_limit_s=None), torch.device("cpu"), state_path=state, resume=True)
    assert len(more.history) == 5 and more.meta.train["stopped_early"] is False


def test_selection_returns_best_validation_epoch(tmp_path: Path) -> None:
    tr = make_patches(4, seed=2, n_radar=256, n_lidar=256)
    scores = iter([3.0, 1.0, 2.0])
    res = train(tr, [], _cfg(), torch.device("cpu"), validator=lambda m, s: {"x": next(scores)},
                select=Selection("val_x"))
    assert res.epoch == 2 and res.meta.train["selection"]["epoch"] == 2
    assert [h["val_x"] for h in res.history] == [3.0, 1.0, 2.0]


def test_bad_state_is_a_user_error(tmp_path: Path) -> None:
    (tmp_path / "s.pt").write_bytes(b"not a state")
    with pytest.raises(UserError, match="not a readable training state"):
        load_state(tmp_path / "s.pt")
    with pytest.raises(UserError, match="no training state"):
        load_state(tmp_path / "none.pt")


def _write_map_set(root: Path) -> None:
    """Three scenes in two environments, laid out like shared/data/coloradar_maps."""
    index = {}
    rng = np.random.default_rng(0)
    for name, env, split in (("lab_run0", "lab", "test"), ("lab_run1", "lab", "train"),
                             ("lab_run2", "lab", "train"), ("hall_run0", "hall", "test"),
                             ("hall_run1", "hall", "train")):
        lidar = scene_surface(rng, 6000, radius=3.0)
        radar = lidar[rng.choice(len(lidar), 1500, replace=False)] + rng.normal(0, 0.05, (1500, 3))
        (root / name).mkdir(parents=True)
        for kind, pts in (("radar", radar), ("lidar_filtered", lidar), ("poses", radar[:5]),
                          ("trajectory", radar[:20])):
            pq.write_table(pa.table({c: pts[:, j] for j, c in enumerate("xyz")}), root / name / f"{kind}.parquet")
        index[name] = {"environment": env, "split": split, "lidar_filtered": {"source": "map"}}
    (root / "index.json").write_text(json.dumps(index))


def test_map_split_keeps_test_scenes_out(tmp_path: Path) -> None:
    _write_map_set(tmp_path)
    scenes = read_index(tmp_path)
    assert validation_scenes(scenes) == ["hall_run1", "lab_run2"]
    sp = map_split(scenes)
    assert sp.train == ["lab_run1"] and sp.test == ["hall_run0", "lab_run0"]
    with pytest.raises(UserError, match="not train scenes"):
        map_split(scenes, ["lab_run0"])


def test_train_from_map_set(tmp_path: Path) -> None:
    from pipeline.config import load_workflow
    from pipeline.registry import load_stages
    from pipeline.train import TrainRequest, run_training
    from stages.complete.checkpoint import load_checkpoint

    maps = tmp_path / "maps"
    _write_map_set(maps)
    out = tmp_path / "m.safetensors"
    req = TrainRequest(seqs=None, test_seqs=None, runs_dir=tmp_path / "runs", registry=load_stages(),
                       workflow=load_workflow("default"), overrides={}, train_overrides={}, out=out,
                       train_kwargs=dict(size="tiny", epochs=2, batch_size=4, lr=2e-3, patches_per_epoch=4),
                       maps=maps, a_train=2.0, a_val=1.0, half=True)
    summary = run_training(req, Console(file=io.StringIO()))
    _, meta = load_checkpoint(out)
    rec = meta.train
    assert rec["train_scenes"] == ["lab_run1"] and rec["val_scenes"] == ["hall_run1", "lab_run2"]
    assert rec["test_scenes_not_used"] == ["hall_run0", "lab_run0"] and rec["a_train"] == 2.0
    assert rec["selection"]["key"] == "val_map_cd_l2" and summary["epochs"] == 2
    hist = json.loads((tmp_path / "m_history.json").read_text())["history"]
    assert all(np.isfinite(h["val_map_cd_l2"]) for h in hist)
    assert (tmp_path / "m_curve.png").exists() and (tmp_path / "m.safetensors.state.pt").exists()


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "pipeline", *args], capture_output=True, text=True, cwd=ROOT,
                          timeout=120)


def test_bad_maps_path_is_one_line_error(tmp_path: Path) -> None:
    r = _cli("train", "--maps", str(tmp_path / "nowhere"), "--out", str(tmp_path / "m.safetensors"))
    assert r.returncode == 2 and "nowhere: not a folder" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    with pytest.raises(UserError, match="no index"):
        read_index(tmp_path)
    (tmp_path / "index.json").write_text("{}")
    with pytest.raises(UserError, match="no scene with radar"):
        read_index(tmp_path)


def test_checkpoint_by_sequence_kind() -> None:
    from stages.complete.stage import DEFAULT_CHECKPOINT, REAL_CHECKPOINT, resolve_checkpoint

    assert resolve_checkpoint("auto", "simulated").resolve() == ROOT / DEFAULT_CHECKPOINT
    for kind in ("coloradar", "source", "rmap"):
        assert resolve_checkpoint("auto", kind).resolve() == ROOT / REAL_CHECKPOINT
    assert resolve_checkpoint(str(ROOT / "x.pt"), "simulated") == ROOT / "x.pt"


def test_shipped_real_checkpoint_loads() -> None:
    from stages.complete.checkpoint import load_checkpoint
    from stages.complete.stage import REAL_CHECKPOINT

    path = ROOT / REAL_CHECKPOINT
    if not path.exists():
        pytest.skip(f"{REAL_CHECKPOINT} not shipped")
    assert path.stat().st_size < 8 * 2**20
    _, meta = load_checkpoint(path)
    rec = meta.train
    assert meta.config.n_input == 2048 and meta.config.n_output == 8192
    # trained on train scenes only; the validation scenes are train scenes; no test scene was read
    assert rec["train_scenes"] and not set(rec["train_scenes"] + rec["val_scenes"]) & set(rec["test_scenes_not_used"])


def test_map_table_scores_input_and_completed(tmp_path: Path) -> None:
    from core.map_metrics import map_metrics
    from experiments.rmap_uppointr_table import evaluate_scenes, overall, render
    from stages.complete.checkpoint import CheckpointMeta, save_checkpoint
    from stages.complete.model import UpPoinTr

    maps = tmp_path / "maps"
    _write_map_set(maps)
    torch.manual_seed(0)
    ckpt = save_checkpoint(tmp_path / "t.safetensors", UpPoinTr(TINY), CheckpointMeta(TINY, 2.0, {}))
    rows = evaluate_scenes(maps, ["lab_run0"], ckpt, a=1.0)
    radar = pq.read_table(maps / "lab_run0" / "radar.parquet").to_pandas().to_numpy()
    gt = pq.read_table(maps / "lab_run0" / "lidar_filtered.parquet").to_pandas().to_numpy()
    assert rows[0]["input"]["cd_l2"] == pytest.approx(map_metrics(radar, gt)["cd_l2"])
    assert rows[0]["n_patches"] == 1 and rows[0]["completed"]["n_points"] > 0
    assert overall(rows, "completed")["cd_l1"] == rows[0]["completed"]["cd_l1"]
    text = render(rows, "t.safetensors", 1.0)
    assert "| lab_run0 | ours completed |" in text
    assert "Overall (paper, 21 scenes)" in text and "| Overall (1 scenes) | ours completed |" in text
    assert {"fscore_0.15_robust", "precision_0.15", "recall_0.15_robust"} <= set(rows[0]["completed"])
