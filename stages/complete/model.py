"""UpPoinTr / AdaPoinTr-family completion network in pure PyTorch (RMap Sec. III-D).

Structure (AdaPoinTr [24] backbone, SeedFormer-style [25] upsampling as RMap's UpPoinTr):

1. Point proxies: a DGCNN grouper (kNN edge convolutions, FPS 2048 -> ``centers[0]`` -> ``centers[1]``)
   gives proxy centres and features; a positional MLP embeds the centres.
2. Geometry-aware transformer encoder: blocks of global self-attention fused (concatenation + linear)
   with a kNN graph attention over the proxy centres ("attn-graph"), then plain "attn" blocks.
3. Dynamic query generation: a global feature (max-pooled MLP) predicts ``n_query`` coarse points; with
   ``n_query / 2`` FPS points of the input they form candidates ranked by an MLP score, the top
   ``n_query`` become the coarse cloud P_c0 and, with the global feature, the decoder queries. RMap sets
   AdaPoinTr's 64 denoising queries to 0, so there are none here.
4. Geometry-aware decoder: self-attention + kNN graph attention among the queries, cross-attention +
   kNN graph attention from queries to proxies.
5. Head: ``"upsample"`` (UpPoinTr) runs upsample layers with factors ``up_factors`` ((1, 4, 4): 512 ->
   512 -> 2048 -> 8192); each layer refines the previous cloud with kNN vector attention over its points,
   splits every point's feature ``r`` ways and predicts child offsets (P_c,i, F_i from P_c,i-1, F_i-1).
   ``"fold"`` is AdaPoinTr's FoldingNet head: every coarse point is folded from a 2D grid into
   ``prod(up_factors)`` points in one step.

As in the reference implementation, the top candidates are picked with ``argsort``, so the ranking MLP
receives no gradient through the selection (scaling the queries by their score was tried and gave no
better fit on synthetic patches).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from stages.complete.ops import fps, fps_points, gather_points, knn


@dataclass(frozen=True)
class ModelConfig:
    """Sizes of the network; ``SIZES`` holds the paper's and a small CPU-trainable one."""

    n_input: int = 2048
    n_query: int = 512
    head: Literal["upsample", "fold"] = "upsample"
    up_factors: tuple[int, ...] = (1, 4, 4)
    centers: tuple[int, int] = (512, 256)
    grouper_k: int = 16
    embed_dim: int = 384
    encoder_depth: int = 6
    decoder_depth: int = 8
    num_heads: int = 6
    graph_k: int = 8
    graph_blocks: int = 1
    mlp_ratio: float = 2.0
    global_dim: int = 1024
    hidden_dim: int = 1024
    up_dim: int = 128
    up_k: int = 16

    @property
    def n_output(self) -> int:
        return self.n_query * math.prod(self.up_factors)

    def level_sizes(self) -> list[int]:
        """Number of points of every output level (the coarse cloud first)."""
        if self.head == "fold":
            return [self.n_query, self.n_output]
        sizes = [self.n_query]
        for r in self.up_factors:
            sizes.append(sizes[-1] * r)
        return sizes

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ModelConfig:
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown model config keys: {', '.join(sorted(unknown))}")
        vals = dict(d)
        for key in ("up_factors", "centers"):
            if key in vals:
                vals[key] = tuple(vals[key])
        return cls(**vals)


SIZES: dict[str, ModelConfig] = {
    # AdaPoinTr's PCN setting (384-d, 6 encoder / 8 decoder blocks, 1024-d global feature), RMap's 512 -> 8192
    "paper": ModelConfig(),
    # a narrow, shallow variant that trains on a 2-core CPU in minutes
    "small": ModelConfig(
        centers=(256, 128), embed_dim=96, encoder_depth=2, decoder_depth=2, num_heads=4, graph_k=8,
        mlp_ratio=2.0, global_dim=256, hidden_dim=256, up_dim=32, up_k=8,
    ),
}


def mlp(*dims: int, act: type[nn.Module] = nn.GELU) -> nn.Sequential:
    """Linear layers with an activation between them (none after the last)."""
    layers: list[nn.Module] = []
    for i in range(len(dims) - 1):
        layers.append(nn.Linear(dims[i], dims[i + 1]))
        if i < len(dims) - 2:
            layers.append(act())
    return nn.Sequential(*layers)


def edge_features(q_f: Tensor, v_f: Tensor, idx: Tensor) -> Tensor:
    """DGCNN edge features ``[f_j - f_i, f_i]`` of shape ``(B, Nq, k, 2C)`` for neighbours ``idx``."""
    nb = gather_points(v_f, idx)
    center = q_f.unsqueeze(2).expand_as(nb)
    return torch.cat([nb - center, center], dim=-1)


class EdgeConv(nn.Module):
    """Edge convolution with GroupNorm and max over the neighbours (the DGCNN grouper layer)."""

    def __init__(self, c_in: int, c_out: int, k: int) -> None:
        super().__init__()
        self.k = k
        self.lin = nn.Linear(2 * c_in, c_out, bias=False)
        self.norm = nn.GroupNorm(4, c_out)

    def forward(self, q_xyz: Tensor, q_f: Tensor, v_xyz: Tensor, v_f: Tensor) -> Tensor:
        idx = knn(q_xyz, v_xyz, min(self.k, v_xyz.shape[1]))
        h = self.lin(edge_features(q_f, v_f, idx))  # B Nq k C
        h = self.norm(h.permute(0, 3, 1, 2))  # B C Nq k
        return F.leaky_relu(h, 0.2).amax(-1).transpose(1, 2)


class DGCNNGrouper(nn.Module):
    """Point proxies: edge convolutions with two FPS downsamplings (AdaPoinTr's DGCNN_Grouper)."""

    num_features = 128

    def __init__(self, centers: tuple[int, int], k: int) -> None:
        super().__init__()
        self.centers = centers
        self.input_trans = nn.Linear(3, 8)
        self.layer1 = EdgeConv(8, 32, k)
        self.layer2 = EdgeConv(32, 64, k)
        self.layer3 = EdgeConv(64, 64, k)
        self.layer4 = EdgeConv(64, 128, k)

    def forward(self, xyz: Tensor) -> tuple[Tensor, Tensor]:
        f = self.input_trans(xyz)
        f = self.layer1(xyz, f, xyz, f)
        idx = fps(xyz, self.centers[0])
        q_xyz, q_f = gather_points(xyz, idx), gather_points(f, idx)
        f = self.layer2(q_xyz, q_f, xyz, f)
        xyz = q_xyz
        f = self.layer3(xyz, f, xyz, f)
        idx = fps(xyz, self.centers[1])
        q_xyz, q_f = gather_points(xyz, idx), gather_points(f, idx)
        f = self.layer4(q_xyz, q_f, xyz, f)
        return q_xyz, f


class Attention(nn.Module):
    """Multi-head attention of ``q`` over ``kv`` (self-attention when they are the same tensor)."""

    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"embed_dim {dim} is not divisible by num_heads {heads}")
        self.heads = heads
        self.q = nn.Linear(dim, dim, bias=False)
        self.kv = nn.Linear(dim, 2 * dim, bias=False)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor, kv: Tensor) -> Tensor:
        b, n, c = x.shape
        h = self.heads
        q = self.q(x).reshape(b, n, h, c // h).transpose(1, 2)
        k, v = self.kv(kv).reshape(b, kv.shape[1], 2, h, c // h).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(q, k, v)
        return self.proj(out.transpose(1, 2).reshape(b, n, c))


class GraphAttention(nn.Module):
    """AdaPoinTr's dynamic graph attention: an edge MLP over kNN neighbours, max-pooled."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.knn_map = nn.Sequential(nn.Linear(2 * dim, dim), nn.LeakyReLU(0.2))

    def forward(self, q: Tensor, v: Tensor, idx: Tensor) -> Tensor:
        return self.knn_map(edge_features(q, v, idx)).amax(2)


class FusedAttention(nn.Module):
    """Global attention, optionally fused with graph attention by concatenation and a linear map."""

    def __init__(self, dim: int, heads: int, graph: bool) -> None:
        super().__init__()
        self.attn = Attention(dim, heads)
        self.graph = GraphAttention(dim) if graph else None
        self.merge = nn.Linear(2 * dim, dim) if graph else None

    def forward(self, x: Tensor, kv: Tensor, idx: Tensor | None) -> Tensor:
        out = self.attn(x, kv)
        if self.graph is not None and self.merge is not None and idx is not None:
            out = self.merge(torch.cat([out, self.graph(x, kv, idx)], dim=-1))
        return out


class EncoderBlock(nn.Module):
    """Pre-norm transformer block with (graph-fused) self-attention."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float, graph: bool) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = FusedAttention(dim, heads, graph)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = mlp(dim, int(dim * mlp_ratio), dim)

    def forward(self, x: Tensor, idx: Tensor | None) -> Tensor:
        n = self.norm1(x)
        x = x + self.attn(n, n, idx)
        return x + self.mlp(self.norm2(x))


class DecoderBlock(nn.Module):
    """Self-attention among queries, then cross-attention to the proxies (both graph-fused when asked)."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float, graph: bool) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.self_attn = FusedAttention(dim, heads, graph)
        self.norm_q = nn.LayerNorm(dim)
        self.norm_v = nn.LayerNorm(dim)
        self.cross_attn = FusedAttention(dim, heads, graph)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = mlp(dim, int(dim * mlp_ratio), dim)

    def forward(self, q: Tensor, v: Tensor, self_idx: Tensor | None, cross_idx: Tensor | None) -> Tensor:
        n = self.norm1(q)
        q = q + self.self_attn(n, n, self_idx)
        q = q + self.cross_attn(self.norm_q(q), self.norm_v(v), cross_idx)
        return q + self.mlp(self.norm2(q))


class Fold(nn.Module):
    """FoldingNet head: a 2D grid of ``step * step`` points folded twice, conditioned on a feature."""

    def __init__(self, c_in: int, step: int, hidden: int = 256) -> None:
        super().__init__()
        self.step = step
        g = torch.linspace(-1.0, 1.0, step)
        grid = torch.stack(torch.meshgrid(g, g, indexing="ij"), dim=-1).reshape(-1, 2)
        self.register_buffer("grid", grid, persistent=False)
        self.fold1 = mlp(c_in + 2, hidden, hidden // 2, 3, act=nn.ReLU)
        self.fold2 = mlp(c_in + 3, hidden, hidden // 2, 3, act=nn.ReLU)

    def forward(self, f: Tensor) -> Tensor:
        """``f (B, M, C)`` -> offsets ``(B, M, step*step, 3)``."""
        b, m, c = f.shape
        s = self.step * self.step
        feat = f.unsqueeze(2).expand(b, m, s, c)
        grid = self.grid.to(f.dtype).expand(b, m, s, 2)  # type: ignore[operator]
        fd1 = self.fold1(torch.cat([grid, feat], dim=-1))
        return self.fold2(torch.cat([fd1, feat], dim=-1))


class VectorAttention(nn.Module):
    """kNN vector attention over points (Point Transformer / SeedFormer's upsample transformer)."""

    def __init__(self, dim: int, k: int) -> None:
        super().__init__()
        self.k = k
        self.qkv = nn.Linear(dim, 3 * dim, bias=False)
        self.pos = mlp(3, dim, dim)
        self.weight = mlp(dim, dim, dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, h: Tensor, xyz: Tensor) -> Tensor:
        q, k, v = self.qkv(h).chunk(3, dim=-1)
        idx = knn(xyz, xyz, min(self.k, xyz.shape[1]))
        pos = self.pos(xyz.unsqueeze(2) - gather_points(xyz, idx))  # B N k C
        w = self.weight(q.unsqueeze(2) - gather_points(k, idx) + pos).softmax(dim=2)
        return self.proj((w * (gather_points(v, idx) + pos)).sum(2))


class UpLayer(nn.Module):
    """One UpPoinTr upsample layer: (P_{i-1}, F_{i-1}) -> (P_i, F_i) with ``|P_i| = r |P_{i-1}|``."""

    def __init__(self, c_in: int, dim: int, global_dim: int, r: int, k: int) -> None:
        super().__init__()
        self.r = r
        self.point_feat = mlp(3, dim, dim)
        self.in_map = nn.Linear(c_in + dim + global_dim, dim)
        self.attn = VectorAttention(dim, k)
        self.split = nn.Linear(dim, dim * r)
        self.offset = mlp(dim, dim, 3)

    def forward(self, xyz: Tensor, f: Tensor, g: Tensor) -> tuple[Tensor, Tensor]:
        b, n, _ = xyz.shape
        h = self.in_map(torch.cat([f, self.point_feat(xyz), g.unsqueeze(1).expand(b, n, g.shape[-1])], -1))
        h = h + self.attn(h, xyz)
        child = self.split(F.gelu(h)).reshape(b, n * self.r, -1) + h.repeat_interleave(self.r, dim=1)
        return xyz.repeat_interleave(self.r, dim=1) + self.offset(F.gelu(child)), child


class UpPoinTr(nn.Module):
    """Radar patch ``(B, n_input, 3)`` -> list of clouds per level, coarse first, ``n_output`` points last."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        c = cfg.embed_dim
        if cfg.n_query % 2:
            raise ValueError("n_query must be even (half of the query candidates come from the input)")
        self.grouper = DGCNNGrouper(cfg.centers, cfg.grouper_k)
        self.pos_embed = mlp(3, 128, c)
        self.input_proj = mlp(DGCNNGrouper.num_features, 2 * c, c)
        self.encoder = nn.ModuleList(
            EncoderBlock(c, cfg.num_heads, cfg.mlp_ratio, i < cfg.graph_blocks) for i in range(cfg.encoder_depth)
        )
        self.increase_dim = mlp(c, cfg.hidden_dim, cfg.global_dim)
        self.coarse_pred = mlp(cfg.global_dim, cfg.hidden_dim, 3 * cfg.n_query)
        self.query_ranking = nn.Sequential(mlp(3, 256, 256, 1), nn.Sigmoid())
        self.mlp_query = mlp(cfg.global_dim + 3, cfg.hidden_dim, cfg.hidden_dim, c)
        self.decoder = nn.ModuleList(
            DecoderBlock(c, cfg.num_heads, cfg.mlp_ratio, i < cfg.graph_blocks) for i in range(cfg.decoder_depth)
        )
        self.increase_dim2 = mlp(c, cfg.hidden_dim, cfg.global_dim)
        self.reduce_map = nn.Linear(cfg.global_dim + c + 3, c)
        self.up_layers = nn.ModuleList()
        self.fold: Fold | None = None
        if cfg.head == "upsample":
            c_in = c
            for r in cfg.up_factors:
                self.up_layers.append(UpLayer(c_in, cfg.up_dim, cfg.global_dim, r, cfg.up_k))
                c_in = cfg.up_dim
        elif cfg.head == "fold":
            step = math.isqrt(math.prod(cfg.up_factors))
            if step * step != math.prod(cfg.up_factors):
                raise ValueError(f"fold head needs a square upsampling factor, got {math.prod(cfg.up_factors)}")
            self.fold = Fold(c, step, hidden=min(256, 2 * c))
        else:
            raise ValueError(f"unknown head {cfg.head!r} (upsample | fold)")
        self.apply(_init_weights)

    def encode(self, xyz: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Proxy centres ``(B, P, 3)``, encoded proxy features ``(B, P, C)`` and the global feature."""
        coor, f = self.grouper(xyz)
        x = self.input_proj(f) + self.pos_embed(coor)
        idx = knn(coor, coor, min(self.cfg.graph_k, coor.shape[1])) if self.cfg.graph_blocks else None
        for blk in self.encoder:
            x = blk(x, idx)
        return coor, x, self.increase_dim(x).amax(1)

    def queries(self, xyz: Tensor, g: Tensor) -> tuple[Tensor, Tensor]:
        """Dynamic queries: ranked candidates from the global feature and FPS of the input."""
        b = xyz.shape[0]
        learned = self.coarse_pred(g).reshape(b, self.cfg.n_query, 3)
        cand = torch.cat([learned, fps_points(xyz, self.cfg.n_query // 2)], dim=1)
        score = self.query_ranking(cand)  # B n 1
        top = score.squeeze(-1).argsort(dim=1, descending=True)[:, : self.cfg.n_query]
        coarse = gather_points(cand, top)
        q = self.mlp_query(torch.cat([g.unsqueeze(1).expand(b, coarse.shape[1], g.shape[-1]), coarse], -1))
        return coarse, q

    def forward(self, xyz: Tensor) -> list[Tensor]:
        coor, mem, g = self.encode(xyz)
        coarse, q = self.queries(xyz, g)
        k = self.cfg.graph_k
        self_idx = knn(coarse, coarse, min(k, coarse.shape[1])) if self.cfg.graph_blocks else None
        cross_idx = knn(coarse, coor, min(k, coor.shape[1])) if self.cfg.graph_blocks else None
        for blk in self.decoder:
            q = blk(q, mem, self_idx, cross_idx)
        b, m, _ = q.shape
        g2 = self.increase_dim2(q).amax(1)
        f = self.reduce_map(torch.cat([g2.unsqueeze(1).expand(b, m, g2.shape[-1]), q, coarse], -1))
        if self.fold is not None:
            fine = (coarse.unsqueeze(2) + self.fold(f)).reshape(b, -1, 3)
            return [coarse, fine]
        levels = [coarse]
        xyz_i = coarse
        for layer in self.up_layers:
            xyz_i, f = layer(xyz_i, f, g2)
            levels.append(xyz_i)
        return levels


def _init_weights(m: nn.Module) -> None:
    if isinstance(m, nn.Linear):
        nn.init.trunc_normal_(m.weight, std=0.02)
        if m.bias is not None:
            nn.init.zeros_(m.bias)
    elif isinstance(m, nn.LayerNorm):
        nn.init.ones_(m.weight)
        nn.init.zeros_(m.bias)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
