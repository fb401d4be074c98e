"""The time-conditioned Gaussian decoder, the Gaussian head, and the feature-lifting decoder.

Token order inside the decoder is [context features ; queries]. Every context token gets its frame's
time embedding; every query gets the target's. Only the query rows feed the head, so the last layer
may compute attention outputs and the MLP for those rows alone (`query_rows_only`): an exact saving.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from .attention import attention
from .config import C4GConfig

SH_C0 = 0.28209479177387814


class SinusoidalTimeEmbedding(nn.Module):
    """[cos(t f), sin(t f)] with f_i = exp(-ln(10000) i / (dim/2)); the frequencies are a buffer in the
    official checkpoint (`time_embedding.freqs`)."""

    def __init__(self, dim: int):
        super().__init__()
        half = dim // 2
        self.register_buffer("freqs", torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32) / half))

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        args = t[..., None] * self.freqs
        return torch.cat((args.cos(), args.sin()), dim=-1)


class DecoderAttention(nn.Module):
    """Self-attention with a bias-free fused qkv projection (`to_qkv`) and `to_out.0` (with bias)."""

    def __init__(self, dim: int, heads: int, head_dim: int):
        super().__init__()
        self.heads, self.head_dim = heads, head_dim
        inner = heads * head_dim
        self.norm = nn.LayerNorm(dim)
        self.to_qkv = nn.Linear(dim, 3 * inner, bias=False)
        self.to_out = nn.Sequential(nn.Linear(inner, dim))

    def forward(self, x: torch.Tensor, query_rows: int | None = None, qkv: torch.Tensor | None = None) -> torch.Tensor:
        """`qkv`, when given, is `to_qkv(norm(x))` computed another way (the precomputed form's first layer)."""
        if qkv is None:
            qkv = self.to_qkv(self.norm(x))
        q, k, v = qkv.chunk(3, dim=-1)
        if query_rows is not None:
            q = q[:, -query_rows:]
        return self.to_out(attention(q, k, v, self.heads, self.head_dim))


class FeedForward(nn.Module):
    """LayerNorm → Linear → GELU → Linear, named `net.{0,1,4}` as in the official checkpoint
    (indices 2 and 3 are the GELU and a dropout; 5 is another dropout)."""

    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.net = nn.Sequential(
            nn.LayerNorm(dim), nn.Linear(dim, hidden), nn.GELU(), nn.Dropout(0.0), nn.Linear(hidden, dim), nn.Dropout(0.0)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class GaussianDecoder(nn.Module):
    """`gmae_decoder`: pre-norm transformer layers [attention, feed-forward] and a final LayerNorm."""

    def __init__(self, cfg: C4GConfig):
        super().__init__()
        self.layers = nn.ModuleList(
            nn.ModuleList(
                [
                    DecoderAttention(cfg.decoder_dim, cfg.decoder_heads, cfg.decoder_head_dim),
                    FeedForward(cfg.decoder_dim, cfg.decoder_mlp),
                ]
            )
            for _ in range(cfg.decoder_depth)
        )
        self.norm = nn.LayerNorm(cfg.decoder_dim)

    def forward(self, x: torch.Tensor, query_rows: int | None = None, first_qkv: torch.Tensor | None = None) -> torch.Tensor:
        """x [B, L, D] → [B, L, D], or [B, query_rows, D] when `query_rows` is given. `first_qkv`, when
        given, is the first layer's qkv projection [B, L, 3 inner], computed by the caller
        (`c4g.precomputed`)."""
        last = len(self.layers) - 1
        for i, (attn, ff) in enumerate(self.layers):
            rows = query_rows if i == last else None
            qkv = first_qkv if i == 0 else None
            if rows is not None:
                x = x[:, -rows:] + attn(x, rows, qkv)
            else:
                x = x + attn(x, qkv=qkv)
            x = x + ff(x)
        return self.norm(x)


class FeatureDecoder(nn.Module):
    """Lifts 2D feature maps onto the Gaussians by reusing the Gaussian decoder's attention.

    A second token stream [context feature maps zero-padded to the decoder width ; learned queries]
    runs beside the Gaussian decoder. Each layer takes that layer's attention weights softmax(q k^T)
    from the Gaussian decoder and adds only its own value projection (`to_v`, no bias), output
    projection (`to_out.0`) and feed-forward. A final LayerNorm and a linear head give one feature
    vector per Gaussian. (C3G's design; C4G's repository has no feature decoder, so the names are ours.)
    """

    def __init__(self, cfg: C4GConfig):
        super().__init__()
        d, inner = cfg.decoder_dim, cfg.decoder_heads * cfg.decoder_head_dim
        self.layers = nn.ModuleList(
            nn.ModuleDict(
                {"to_v": nn.Linear(d, inner, bias=False), "to_out": nn.Sequential(nn.Linear(inner, d)), "ff": FeedForward(d, cfg.decoder_mlp)}
            )
            for _ in range(cfg.decoder_depth)
        )
        self.norm = nn.LayerNorm(d)
        self.head = nn.Linear(d, cfg.feature_dim)


def activate(raw: torch.Tensor, anchors: torch.Tensor) -> dict[str, torch.Tensor]:
    """Raw output of the Gaussian head (`gmae_to_gaussians`, Linear(D, 14) per query) [..., 14] →
    the reference's activated parameters (rotation in x, y, z, w order)."""
    scales_raw = raw[..., 4:7]
    # Softplus written as relu(x) + log(1 + exp(-|x|)): exact, and finite for any finite input
    # (ONNX's Softplus has no overflow guard).
    softplus = F.relu(scales_raw) + torch.log(1.0 + torch.exp(-scales_raw.abs()))
    rot = raw[..., 7:11]
    return {
        "means": raw[..., 0:3] + anchors,
        "opacities": torch.sigmoid(raw[..., 3]),
        "scales": 0.001 * softplus,
        "rotations_xyzw": rot / (rot.norm(dim=-1, keepdim=True) + 1e-8),
        "sh_dc": raw[..., 11:14],
    }


def to_canonical(p: dict[str, torch.Tensor]) -> torch.Tensor:
    """Activated parameters → the service's 14 channels: xyz, scale xyz, rotation wxyz, opacity, RGB."""
    rot = p["rotations_xyzw"]
    rgb = torch.clamp_min(SH_C0 * p["sh_dc"] + 0.5, 0.0)
    return torch.cat(
        (p["means"], p["scales"], rot[..., 3:4], rot[..., 0:3], p["opacities"][..., None], rgb), dim=-1
    )
