"""Voxel completion network (``complete.model = voxel``): a fully convolutional 3D U-Net in plain
torch ``conv3d`` that maps the radar map's lattice to a per-voxel occupancy logit of the lidar map.

No normalisation layer (no BatchNorm / GroupNorm), so a voxel's output depends only on the inputs within
:meth:`VoxelUNet.receptive_radius` of it and never on the tile it was computed in; :func:`predict_tiles` runs
a whole map in one pass, or as xy tiles with that radius as halo whose origins are multiples of
:meth:`VoxelUNet.stride` in lattice keys, which equals the one pass (``tests/test_voxel_net.py``).
The channels are :data:`stages.complete.voxel_grid.CHANNELS` (radar map and trajectory only).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import math
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch import nn

from stages.complete.voxel_grid import CHANNELS, F64, I64, Band, band_grid, trajectory_columns, voxel_features

MODEL_KIND = "voxel_unet"


@dataclass(frozen=True)
class VoxelNetConfig:
    """Widths per level (level i runs at stride 2^i), convolutions per level and the bottom's dilation."""

    in_channels: int = len(CHANNELS)
    widths: tuple[int, ...] = (8, 24, 48, 64)
    bottom_convs: int = 2
    bottom_dilation: int = 2

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["widths"] = list(self.widths)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> VoxelNetConfig:
        return cls(int(d["in_channels"]), tuple(int(w) for w in d["widths"]), int(d["bottom_convs"]),
                   int(d["bottom_dilation"]))


def _conv(cin: int, cout: int, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv3d(cin, cout, 3, padding=dilation, dilation=dilation), nn.ReLU(inplace=True))


class VoxelUNet(nn.Module):
    """3D U-Net: level 0 two 3^3 convs; each lower level a 2^3 stride-2 conv then 3^3 convs (the bottom
    ``bottom_convs`` dilated ones); the decoder a 2^3 stride-2 transposed conv, the skip concatenated, one
    3^3 conv; a 1^3 head. Input ``(B, C, X, Y, Z)`` with X, Y, Z multiples of :meth:`stride`."""

    def __init__(self, config: VoxelNetConfig | None = None) -> None:
        super().__init__()
        self.config = cfg = config or VoxelNetConfig()
        w = cfg.widths
        if len(w) < 2:
            raise ValueError("VoxelNetConfig.widths needs at least two levels")
        self.enc0 = nn.Sequential(_conv(cfg.in_channels, w[0]), _conv(w[0], w[0]))
        self.downs = nn.ModuleList()
        for i in range(1, len(w)):
            bottom = i == len(w) - 1
            convs = [_conv(w[i], w[i], cfg.bottom_dilation if bottom else 1)
                     for _ in range(cfg.bottom_convs if bottom else 1)]
            self.downs.append(nn.Sequential(nn.Conv3d(w[i - 1], w[i], 2, stride=2), nn.ReLU(inplace=True), *convs))
        self.ups = nn.ModuleList(
            nn.Sequential(nn.ConvTranspose3d(w[i + 1], w[i], 2, stride=2), nn.ReLU(inplace=True))
            for i in range(len(w) - 1))
        self.fuse = nn.ModuleList(_conv(2 * w[i], w[i]) for i in range(len(w) - 1))
        self.head = nn.Conv3d(w[0], 1, 1)

    def stride(self) -> int:
        """The input size must be a multiple of this (2^(levels-1)); tile origins too, in lattice keys."""
        return int(2 ** (len(self.config.widths) - 1))

    def receptive_radius(self) -> int:
        """An upper bound (voxels) of how far from a voxel an input can change its output."""
        cfg = self.config
        n = len(cfg.widths)
        r = 2  # level 0's two 3^3 convs
        for i in range(1, n):
            bottom = i == n - 1
            convs = cfg.bottom_convs if bottom else 1
            dil = cfg.bottom_dilation if bottom else 1
            r += 2 ** (i - 1) + convs * dil * 2 ** i  # the 2^3 stride-2 conv, then the 3^3 convs at stride 2^i
        for i in range(n - 1):
            r += 2 ** (i + 1) + 2 ** i  # transposed conv from level i+1, then the fusing 3^3 conv
        return r

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = [self.enc0(x)]
        h = skips[0]
        for down in self.downs:
            h = down(h)
            skips.append(h)
        for i in range(len(self.ups) - 1, -1, -1):
            h = self.fuse[i](torch.cat([self.ups[i](h), skips[i]], dim=1))
        out: torch.Tensor = self.head(h)[:, 0]
        return out


def n_parameters(model: nn.Module) -> int:
    return int(sum(p.numel() for p in model.parameters()))


@dataclass(frozen=True)
class Domain:
    """The lattice box a map's prediction covers: xy over the trajectory +- band radius, z over the
    trajectory's heights + the band's range; ``lo`` aligned to the model's stride."""

    lo: tuple[int, int, int]
    shape: tuple[int, int, int]


def map_domain(trajectory: F64, res: float, band: Band, stride: int) -> Domain:
    """:class:`Domain` of a map (lattice keys; every side a multiple of ``stride``)."""
    t = np.asarray(trajectory, np.float64)
    lo_m = np.array([t[:, 0].min() - band.radius, t[:, 1].min() - band.radius, t[:, 2].min() + band.z_below])
    hi_m = np.array([t[:, 0].max() + band.radius, t[:, 1].max() + band.radius, t[:, 2].max() + band.z_above])
    lo = np.floor(np.floor(lo_m / res) / stride) * stride
    hi = np.ceil((np.floor(hi_m / res) + 1) / stride) * stride
    lo_i = tuple(int(v) for v in lo)
    shape = tuple(int(v) for v in hi - lo)
    return Domain((lo_i[0], lo_i[1], lo_i[2]), (shape[0], shape[1], shape[2]))


@dataclass
class TilePrediction:
    """Occupancy probabilities of the band voxels of a map (lattice keys), and what it cost."""

    keys: I64
    probs: npt.NDArray[np.float32]
    n_tiles: int = 0
    n_skipped: int = 0
    n_voxels_run: int = 0
    model_seconds: float = 0.0
    feature_seconds: float = 0.0
    tiles: list[tuple[int, int]] = field(default_factory=list)


def tile_origins(domain: Domain, core: int) -> list[tuple[int, int]]:
    """xy key origins of the core tiles covering the domain (multiples of the stride by construction)."""
    xs = range(domain.lo[0], domain.lo[0] + domain.shape[0], core)
    ys = range(domain.lo[1], domain.lo[1] + domain.shape[1], core)
    return [(x, y) for x in xs for y in ys]


#: whole-map passes up to this many voxels (about 3-4 GB of activations at the default widths); tiles above
MAX_PASS_VOXELS = 24_000_000


def auto_core(domain: Domain, max_voxels: int = MAX_PASS_VOXELS, tile: int = 256) -> int:
    """One pass over the whole domain when it has at most ``max_voxels`` voxels, else ``tile``-voxel cores."""
    if int(np.prod(domain.shape)) <= max_voxels:
        return max(domain.shape[0], domain.shape[1])
    return tile


#: glibc's mallopt parameters and their defaults (``man mallopt``)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _GLIBC_DEFAULT = -1, -3, 128 * 1024
_reuse_depth = 0


@contextmanager
def reuse_freed_memory(limit: int = 2**31 - 1) -> Iterator[None]:
    """Inside: glibc keeps freed blocks of up to ``limit`` bytes for reuse instead of handing them back to the
    system, so that the network's large activations (hundreds of MB each, allocated anew by every layer) do
    not page-fault again and again; on leaving the outermost one, the thresholds go back to glibc's initial
    values and the freed memory is returned (``malloc_trim``). Nested uses keep the outer one's heap (held
    across the 18 test scenes: 4 scenes took 25 s instead of 34-36 s, 0.7 M page faults instead of 2.5-2.7 M).
    Values are unchanged. A no-op where the C library has no ``mallopt`` (not glibc)."""
    global _reuse_depth
    name = ctypes.util.find_library("c")
    libc = ctypes.CDLL(name) if name else None
    if libc is None or not hasattr(libc, "mallopt") or not hasattr(libc, "malloc_trim"):
        yield
        return
    if _reuse_depth == 0:
        libc.mallopt(_M_MMAP_THRESHOLD, ctypes.c_int(limit))
        libc.mallopt(_M_TRIM_THRESHOLD, ctypes.c_int(limit))
    _reuse_depth += 1
    try:
        yield
    finally:
        _reuse_depth -= 1
        if _reuse_depth == 0:
            libc.mallopt(_M_MMAP_THRESHOLD, ctypes.c_int(_GLIBC_DEFAULT))
            libc.mallopt(_M_TRIM_THRESHOLD, ctypes.c_int(_GLIBC_DEFAULT))
            libc.malloc_trim(ctypes.c_size_t(0))


@reuse_freed_memory()
@torch.inference_mode()
def predict_tiles(model: VoxelUNet, radar_keys: I64, trajectory: F64, res: float, band: Band,
                  core: int | None = None, halo: int | None = None, device: str | torch.device = "cpu",
                  advance: Callable[[int], None] | None = None, origins: Sequence[tuple[int, int]] | None = None,
                  bf16: bool = False) -> TilePrediction:
    """Occupancy probability of every band voxel of a map: one pass over the map's :class:`Domain` (zero
    padding at its faces), computed as xy tiles of ``core`` voxels (None: :func:`auto_core`), each with
    ``halo`` voxels of context cut at the domain's faces, and the whole z range of the domain.

    ``halo`` defaults to the receptive radius rounded up to the stride, and tile origins are multiples of the
    stride: the result then equals the single pass (``tests/test_voxel_net.py``). Tiles whose core holds no
    band voxel are skipped (their voxels are outside the pre-filter band and never output), and so are tiles
    with no radar voxel in core + halo (nothing to complete: no voxel output). ``origins`` restricts the run
    to some tiles (tests). ``bf16``: the network under bfloat16 autocast (1.7x faster on a CPU with AVX-512
    BF16; probabilities move by up to about 0.01, so the completed map can change by a few voxels).
    """
    s = model.stride()
    dom = map_domain(trajectory, res, band, s)
    core = core if core is not None else auto_core(dom)
    core = int(math.ceil(core / s) * s)
    halo = halo if halo is not None else int(math.ceil(model.receptive_radius() / s) * s)
    if halo % s:
        raise ValueError(f"tile halo {halo} must be a multiple of the model stride {s}")
    tiles = list(origins) if origins is not None else tile_origins(dom, core)
    keys_out: list[I64] = []
    probs_out: list[npt.NDArray[np.float32]] = []
    rk = np.asarray(radar_keys, np.int64)
    out = TilePrediction(np.zeros((0, 3), np.int64), np.zeros(0, np.float32))
    nz = dom.shape[2]
    z0 = dom.lo[2]
    hi = (dom.lo[0] + dom.shape[0], dom.lo[1] + dom.shape[1])
    for ox, oy in tiles:
        out.n_tiles += 1
        t0 = time.perf_counter()
        cshape = (min(core, hi[0] - ox), min(core, hi[1] - oy), nz)
        x0, y0 = max(ox - halo, dom.lo[0]), max(oy - halo, dom.lo[1])
        x1, y1 = min(ox + cshape[0] + halo, hi[0]), min(oy + cshape[1] + halo, hi[1])
        lo_in = np.array([x0, y0, z0])
        ishape = (x1 - x0, y1 - y0, nz)
        dist, tz = trajectory_columns(lo_in, ishape[:2], trajectory, res)  # once for the band and the features
        cx, cy = slice(ox - x0, ox - x0 + cshape[0]), slice(oy - y0, oy - y0 + cshape[1])
        inband = band_grid((ox, oy, z0), cshape, trajectory, res, band, (dist[cx, cy], tz[cx, cy]))
        near = rk[np.all((rk >= lo_in) & (rk < lo_in + np.asarray(ishape)), axis=1)] if len(rk) else rk
        if not inband.any() or len(near) == 0:
            out.n_skipped += 1
            if advance:
                advance(1)
            continue
        feats = voxel_features(near, trajectory, lo_in, ishape, res, (dist, tz))
        out.feature_seconds += time.perf_counter() - t0
        t1 = time.perf_counter()
        x = torch.from_numpy(feats)[None].to(device).contiguous(memory_format=torch.channels_last_3d)
        with torch.autocast(torch.device(device).type, dtype=torch.bfloat16, enabled=bf16):
            prob_t = torch.sigmoid(model(x))[0, cx, cy, :]
        prob = prob_t.float().cpu().numpy()
        del x, prob_t
        out.model_seconds += time.perf_counter() - t1
        out.n_voxels_run += int(np.prod(ishape))
        idx = np.argwhere(inband)
        keys_out.append(idx + np.array([ox, oy, z0]))
        probs_out.append(prob[inband])
        out.tiles.append((ox, oy))
        if advance:
            advance(1)
    if keys_out:
        out.keys = np.concatenate(keys_out).astype(np.int64)
        out.probs = np.concatenate(probs_out).astype(np.float32)
    return out


def dense_prediction(pred: TilePrediction, lo: Sequence[int], shape: Sequence[int]) -> npt.NDArray[np.float32]:
    """The probabilities of ``pred`` on a dense box (0 where nothing was predicted); for tests and figures."""
    grid = np.zeros(tuple(shape), np.float32)
    k = pred.keys - np.asarray(lo, np.int64)
    ok = np.all((k >= 0) & (k < np.asarray(shape)), axis=1)
    grid[k[ok, 0], k[ok, 1], k[ok, 2]] = pred.probs[ok]
    return grid


def probabilities_at(pred: TilePrediction, keys: I64) -> npt.NDArray[np.float32]:
    """The predicted probability of each of ``keys`` (0 where the prediction holds no such voxel)."""
    keys = np.asarray(keys, np.int64).reshape(-1, 3)
    out = np.zeros(len(keys), np.float32)
    if len(keys) == 0 or len(pred.keys) == 0:
        return out
    lo = np.minimum(pred.keys.min(axis=0), keys.min(axis=0))
    span = np.maximum(pred.keys.max(axis=0), keys.max(axis=0)) - lo + 1

    def flat(k: I64) -> I64:
        d = k - lo
        return np.asarray((d[:, 0] * span[1] + d[:, 1]) * span[2] + d[:, 2], np.int64)

    have = flat(pred.keys)
    order = np.argsort(have, kind="stable")
    want = flat(keys)
    i = np.clip(np.searchsorted(have, want, sorter=order), 0, len(have) - 1)
    hit = have[order[i]] == want
    out[hit] = pred.probs[order[i[hit]]]
    return out


def completed_keys(pred: TilePrediction, threshold: float, radar_keys: I64 | None = None,
                   radar_gate: float = 0.0) -> I64:
    """The completed map's voxel keys: band voxels with probability >= ``threshold``, plus the voxels of
    ``radar_keys`` (the pre-filtered radar map) when given (the union) whose own predicted probability is at
    least ``radar_gate`` (0: every radar voxel, the plain union), unique and sorted."""
    keys = pred.keys[pred.probs >= threshold]
    if radar_keys is not None and len(radar_keys):
        rk = np.asarray(radar_keys, np.int64)
        if radar_gate > 0:
            rk = rk[probabilities_at(pred, rk) >= radar_gate]
        keys = np.concatenate([keys, rk])
    if len(keys) == 0:
        return np.zeros((0, 3), np.int64)
    return np.unique(keys, axis=0)
