"""kNN, FPS and Chamfer of the completion network against brute-force numpy / scipy references."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from scipy.spatial.distance import cdist  # noqa: E402

from stages.complete import ops  # noqa: E402

BACKENDS = ["torch", "kdtree"]


def _clouds(seed: int, b: int = 2, n: int = 300, m: int = 200) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.normal(size=(b, n, 3)), rng.normal(size=(b, m, 3)) * 1.5 + 0.3


def _fps_reference(x: np.ndarray, n: int) -> list[int]:
    """Textbook FPS on one cloud: start at 0, then repeatedly the point farthest from the chosen set."""
    chosen = [0]
    d = cdist(x, x[[0]]).ravel()
    for _ in range(n - 1):
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, cdist(x, x[[i]]).ravel())
    return chosen


@pytest.mark.parametrize("backend", BACKENDS)
def test_knn_matches_brute_force(backend: str) -> None:
    q, r = _clouds(0)
    got = ops.knn(torch.from_numpy(q), torch.from_numpy(r), 7, backend=backend).numpy()
    for b in range(len(q)):
        ref = np.argsort(cdist(q[b], r[b]), axis=1, kind="stable")[:, :7]
        np.testing.assert_array_equal(got[b], ref)


def test_knn_torch_chunks_agree() -> None:
    q, r = _clouds(1, n=500)
    a = ops.knn(torch.from_numpy(q), torch.from_numpy(r), 5, backend="torch", chunk=64)
    b = ops.knn(torch.from_numpy(q), torch.from_numpy(r), 5, backend="torch", chunk=10_000)
    assert torch.equal(a, b)


@pytest.mark.parametrize("backend", BACKENDS)
def test_fps_matches_brute_force(backend: str) -> None:
    x, _ = _clouds(2, n=400)
    got = ops.fps(torch.from_numpy(x), 50, backend=backend).numpy()
    for b in range(len(x)):
        assert got[b].tolist() == _fps_reference(x[b], 50)


def test_fps_rejects_too_many() -> None:
    with pytest.raises(ValueError, match="cannot pick"):
        ops.fps(torch.zeros(1, 5, 3), 6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_chamfer_matches_brute_force(backend: str) -> None:
    p, g = _clouds(3)
    pt, gt = torch.from_numpy(p), torch.from_numpy(g)
    l2 = ops.chamfer_l2(pt, gt, backend=backend).numpy()
    l1 = ops.chamfer_l1(pt, gt, backend=backend).numpy()
    for b in range(len(p)):
        d = cdist(p[b], g[b])
        ref_l2 = (d.min(1) ** 2).mean() + (d.min(0) ** 2).mean()  # RMap eq. 1
        ref_l1 = 0.5 * (d.min(1).mean() + d.min(0).mean())
        assert l2[b] == pytest.approx(ref_l2, rel=1e-10)
        assert l1[b] == pytest.approx(ref_l1, rel=1e-8)


def test_chamfer_gradient_matches_dense_autograd() -> None:
    """The gather-based gradient equals autograd through the full distance matrix."""
    p, g = _clouds(4, n=120, m=90)
    pa = torch.from_numpy(p).requires_grad_(True)
    ga = torch.from_numpy(g).requires_grad_(True)
    ops.chamfer_l2(pa, ga).sum().backward()
    pb = torch.from_numpy(p).requires_grad_(True)
    gb = torch.from_numpy(g).requires_grad_(True)
    d = ((pb[:, :, None, :] - gb[:, None, :, :]) ** 2).sum(-1)
    (d.min(2).values.mean(1) + d.min(1).values.mean(1)).sum().backward()
    assert pa.grad is not None and pb.grad is not None and ga.grad is not None and gb.grad is not None
    torch.testing.assert_close(pa.grad, pb.grad)
    torch.testing.assert_close(ga.grad, gb.grad)


def test_chamfer_zero_for_identical_and_permuted() -> None:
    p, _ = _clouds(5)
    pt = torch.from_numpy(p)
    perm = torch.from_numpy(np.random.default_rng(0).permutation(p.shape[1]))
    assert torch.all(ops.chamfer_l2(pt, pt[:, perm]) == 0)


def test_gather_points() -> None:
    x = torch.arange(24.0).reshape(2, 4, 3)
    idx = torch.tensor([[[3, 0]], [[1, 1]]])
    out = ops.gather_points(x, idx)
    assert out.shape == (2, 1, 2, 3)
    torch.testing.assert_close(out[0, 0, 0], x[0, 3])
    torch.testing.assert_close(out[1, 0, 1], x[1, 1])
