"""The torch backend of the RICH-SLAM particle maps and filter (CPU torch) against the numpy backend.

One 200-scan synthetic corridor run (the slam tests' world) is filtered once per map form by both
backends from the same seed; the tests compare the log weights scan by scan (float64: within 1e-9 of
their spread), the resampling decisions, the trajectories and the final maps. float32 is held to the
accuracy the numpy backend's float32 reaches on the same poses. No test needs a GPU.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from core import hilbert_map as hm  # noqa: E402
from core.errors import UserError  # noqa: E402
from stages.slam.backend import resolve_device  # noqa: E402
from stages.slam.beam_sampling import sample_beams  # noqa: E402
from stages.slam.rbpf import (  # noqa: E402
    RBPF,
    HilbertParticleMaps,
    HilbertWeighting,
    MapModel,
    MotionNoise,
    odometry_increments,
)
from stages.slam.synthetic import make_run  # noqa: E402
from stages.slam.torch_filter import TorchRBPF, cpu_threads  # noqa: E402
from stages.slam.torch_maps import TorchHilbertMaps  # noqa: E402

N_SCANS, N_P, M = 200, 12, 64
FORMS = ("information", "covariance")


@pytest.fixture(scope="module", autouse=True)
def _one_thread() -> Any:
    """One torch thread, as the stage runs it on a CPU (torch's default collapses on a shared machine)."""
    with cpu_threads(1):
        yield


@pytest.fixture(scope="module")
def corridor() -> dict[str, Any]:
    run = make_run(N_SCANS, np.random.default_rng(21), beams_per_scan=12)
    scans = [sample_beams(s, [0.0, 0.0], 1.0, 5.0) for s in run.scans]
    basis = hm.make_basis([14.0, 10.0], [0.0, 0.0], M)
    return {"run": run, "scans": scans, "basis": basis, "u": odometry_increments(run.odometry)}


def _filter(corridor: dict[str, Any], backend: str, form: str, **kw: Any) -> dict[str, Any]:
    """Run one backend over the corridor; log weights before resampling and the final maps."""
    b, w = corridor["basis"], HilbertWeighting(et_variance="taylor")
    rng = np.random.default_rng(0)
    maps: Any
    if backend == "numpy":
        maps = HilbertParticleMaps(b, N_P, MapModel(2.0, 16.0, 0.36, w, form=form))  # type: ignore[arg-type]
        f: Any = RBPF(maps, corridor["run"].odometry[0], N_P, MotionNoise(), rng)
    else:
        maps = TorchHilbertMaps(b, N_P, MapModel(2.0, 16.0, 0.36, w, form=form), **kw)  # type: ignore[arg-type]
        f = TorchRBPF(maps, corridor["run"].odometry[0], N_P, MotionNoise(), rng)
    logw: list[np.ndarray] = []

    def record(i: int, filt: Any, best: int) -> None:
        lw = filt.logw
        logw.append(lw.cpu().numpy() if isinstance(lw, torch.Tensor) else lw.copy())

    h = f.run(corridor["u"], corridor["scans"], observer=record)
    final = [maps.map_of(k) for k in (0, N_P - 1)]
    return {"history": h, "logw": np.asarray(logw), "maps": final}


@pytest.fixture(scope="module")
def runs(corridor: dict[str, Any]) -> dict[tuple[str, str], dict[str, Any]]:
    out = {}
    for form in FORMS:
        out[("numpy", form)] = _filter(corridor, "numpy", form)
        # the information form in blocks of a few particles, the covariance form in one block
        out[("torch", form)] = _filter(corridor, "torch", form,
                                       block_bytes=1 if form == "information" else None)
    return out


@pytest.mark.parametrize("form", FORMS)
def test_torch_filter_equals_numpy_filter_for_200_scans(runs: dict[tuple[str, str], Any], form: str) -> None:
    a, t = runs[("numpy", form)], runs[("torch", form)]
    ha, ht = a["history"], t["history"]
    assert len(ht.n_eff) == N_SCANS and sum(ha.resampled) >= 5  # the run exercises resampling
    # log weights scan by scan: within 1e-9 of the particles' spread
    spread = np.ptp(a["logw"], axis=1)
    assert np.all(spread[10:] > 0)
    err = np.max(np.abs(t["logw"] - a["logw"]), axis=1)
    assert np.all(err <= 1e-9 * np.maximum(spread, 1e-3)), float(np.max(err / np.maximum(spread, 1e-3)))
    assert ht.resampled == ha.resampled
    assert ht.best_index == ha.best_index
    np.testing.assert_allclose(ht.n_eff, ha.n_eff, rtol=1e-9)
    np.testing.assert_allclose(ht.best_trajectory(), ha.best_trajectory(), atol=1e-12)
    np.testing.assert_array_equal(np.asarray(ht.parents), np.asarray(ha.parents))
    np.testing.assert_allclose(np.asarray(ht.particles), np.asarray(ha.particles), atol=1e-12)
    for (th_a, cov_a), (th_t, cov_t) in zip(a["maps"], t["maps"], strict=True):
        np.testing.assert_allclose(th_t, th_a, atol=1e-8 * np.abs(th_a).max())
        np.testing.assert_allclose(cov_t, cov_a, atol=1e-9 * np.abs(cov_a).max())


def _float32_error(corridor: dict[str, Any], form: str, backend: str) -> float:
    """Largest |log-likelihood| difference of float32 maps to numpy float64 maps on the same poses, relative
    to the particles' spread (the measure of ``benchmarks/bench_slam.py``)."""
    b, w, scans = corridor["basis"], HilbertWeighting(et_variance="taylor"), corridor["scans"][:40]
    rng = np.random.default_rng(3)
    ref = HilbertParticleMaps(b, N_P, MapModel(2.0, 16.0, 0.36, w, form=form))  # type: ignore[arg-type]
    low: Any = (HilbertParticleMaps(b, N_P, MapModel(2.0, 16.0, 0.36, w, form=form, dtype=np.float32))  # type: ignore[arg-type]
                if backend == "numpy" else
                TorchHilbertMaps(b, N_P, MapModel(2.0, 16.0, 0.36, w, form=form, dtype="float32")))  # type: ignore[arg-type]
    worst = 0.0
    for i, s in enumerate(scans):
        poses = corridor["run"].groundtruth[i] + rng.normal(0, [0.05, 0.05, 0.01], (N_P, 3))
        ll = ref.weigh_and_update(poses, s)
        got = low.weigh_and_update(torch.as_tensor(poses) if backend == "torch" else poses, s)
        got = got.cpu().numpy() if isinstance(got, torch.Tensor) else got
        if s.n:  # spreads below 1e-3 log units decide nothing (e.g. prior maps)
            worst = max(worst, float(np.max(np.abs(got - ll)) / max(float(np.std(ll)), 1e-3)))
    return worst


@pytest.mark.parametrize("form", FORMS)
def test_torch_float32_is_as_accurate_as_numpy_float32(corridor: dict[str, Any], form: str) -> None:
    err_t = _float32_error(corridor, form, "torch")
    err_n = _float32_error(corridor, form, "numpy")
    # the benchmark reports 6.6e-4 .. 4.4e-3 of the spread for numpy float32 at M = 256
    assert err_t < 1e-2 and err_t <= 3 * err_n + 1e-4, (err_t, err_n)


def test_resampled_torch_maps_do_not_alias(corridor: dict[str, Any]) -> None:
    b, s = corridor["basis"], corridor["scans"][5]
    for form in FORMS:
        maps = TorchHilbertMaps(b, 3, MapModel(2.0, 16.0, 0.36, HilbertWeighting(), form=form))  # type: ignore[arg-type]
        poses = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.5], [0.0, 1.0, 1.0]], dtype=torch.float64)
        maps.weigh_and_update(poses, s)
        maps.select(torch.tensor([1, 1, 0]))
        np.testing.assert_array_equal(maps.map_of(0)[1], maps.map_of(1)[1])
        maps.weigh_and_update(torch.tensor([[2.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
                                           dtype=torch.float64), s)
        assert not np.allclose(maps.map_of(0)[1], maps.map_of(1)[1])


def test_device_choice_and_one_line_errors(monkeypatch: pytest.MonkeyPatch) -> None:
    assert resolve_device("numpy", "auto") == ("cpu", "")
    assert resolve_device("torch", "cpu") == ("cpu", "")
    with pytest.raises(UserError, match="needs slam"):
        resolve_device("numpy", "cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    device, note = resolve_device("torch", "auto")
    assert device == "cpu" and "auto" in note and "on the CPU" in note
    with pytest.raises(UserError, match="sees no CUDA device") as exc:
        resolve_device("torch", "cuda")
    assert "\n" not in str(exc.value)
    monkeypatch.setitem(sys.modules, "torch", None)  # torch not installed
    with pytest.raises(UserError, match="learn"):
        resolve_device("torch", "auto")


def test_stage_runs_the_torch_backend_and_logs_the_device(tmp_path: Path) -> None:
    from schemas.io import read_artifact
    from tests.test_slam_stage import _ctx, _run, _write_inputs

    dirs = _write_inputs(tmp_path / "in", 40)["dirs"]
    traj, stats = {}, {}
    for backend in ("numpy", "torch"):
        ctx = _ctx(tmp_path / backend, dirs, backend=backend, device="cpu" if backend == "torch" else "auto",
                   methods=["rich_slam"], n_particles=8, map={"n_basis": 64}, workers=0)
        _run(ctx)
        traj[backend] = read_artifact(tmp_path / backend / "trajectory.parquet", "trajectory")
        stats[backend] = ctx.stats
    assert stats["torch"]["backend"] == "torch" and stats["torch"]["device"] == "cpu"
    assert stats["torch"]["methods"]["rich_slam"]["device"] == "cpu"
    for c in ("x", "y", "yaw", "n_eff"):
        np.testing.assert_allclose(traj["torch"][c].to_numpy(), traj["numpy"][c].to_numpy(), atol=1e-9)
