"""The time-conditioned Gaussian decoder (with its optional feature stream) and the Gaussian head.

Token order inside the decoder is [context features ; queries]. Every context token gets its frame's
time embedding; every query gets the target's. Only the query rows feed the head, so the last layer
may compute attention outputs and the MLP for those rows alone (`query_rows_only`): an exact saving.
Exported graphs also project the last layer's q for those rows alone, as a product of its own beside
k's and v's (`DecoderAttention.split_projection`): the same values, fewer FLOP, no slice copies.

The feature stream (feature lifting, `cfg.feature_dim` > 0) is the public C4G code's joint
two-stream decoder (`InstillAttention` / `InstillTransformer`): a second token sequence y of the
feature's own width F rides beside the Gaussian stream x. Each layer reuses x's attention weights
softmax(q k^T / sqrt(d)) and adds only y's value projection `to_anotherv` (F → inner, no bias,
applied to y without a norm), its output projection `to_yout` (inner → F), a residual, and y's own
pre-norm MLP (F → 2F → F, the layer's third module); a final `y_norm` closes the stream. y never
feeds back into x, so the Gaussians are those of the decoder without the stream, bit for bit.
"""

from __future__ import annotations

import contextlib
import math

import torch
import torch.nn.functional as F
from torch import nn

from .attention import attention
from .config import C4GConfig

SH_C0 = 0.28209479177387814
_SPLIT_EXPORT = True


@contextlib.contextmanager
def split_query_projection(enabled: bool = True):
    """Within this block, exported graphs split (or, disabled, keep whole) the last layer's qkv
    projection (`DecoderAttention.split_projection`); export splits it by default. For measuring
    the split against the graph without it (`c4g.bench.decoder`)."""
    global _SPLIT_EXPORT
    previous, _SPLIT_EXPORT = _SPLIT_EXPORT, enabled
    try:
        yield
    finally:
        _SPLIT_EXPORT = previous


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
    """Self-attention with a bias-free fused qkv projection (`to_qkv`) and `to_out.0` (with bias);
    with `feature_dim` > 0 also the feature stream's `to_anotherv` and `to_yout.0`."""

    def __init__(self, dim: int, heads: int, head_dim: int, feature_dim: int = 0):
        super().__init__()
        self.heads, self.head_dim = heads, head_dim
        inner = heads * head_dim
        self.norm = nn.LayerNorm(dim)
        self.to_qkv = nn.Linear(dim, 3 * inner, bias=False)
        self.to_out = nn.Sequential(nn.Linear(inner, dim))
        if feature_dim > 0:
            self.to_anotherv = nn.Linear(feature_dim, inner, bias=False)
            self.to_yout = nn.Sequential(nn.Linear(inner, feature_dim))

    def forward(self, x: torch.Tensor, query_rows: int | None = None, qkv: torch.Tensor | None = None) -> torch.Tensor:
        """`qkv`, when given, is `to_qkv(norm(x))` computed another way (the precomputed form's first layer)."""
        if qkv is None and query_rows is not None and _SPLIT_EXPORT and torch.onnx.is_in_onnx_export():
            q, k, v = self.split_projection(self.norm(x), query_rows)
        else:
            if qkv is None:
                qkv = self.to_qkv(self.norm(x))
            q, k, v = qkv.chunk(3, dim=-1)
            if query_rows is not None:
                q = q[:, -query_rows:]
        return self.to_out(attention(q, k, v, self.heads, self.head_dim))

    def split_projection(self, normed: torch.Tensor, query_rows: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """`to_qkv(normed).chunk(3)` with q for the last `query_rows` rows alone, as three products
        (what exported graphs compute, `forward` under export): the rows whose q is dropped are
        never projected, and no slice copies q, k and v out of one wide product. The same values
        as the fused projection's, up to float rounding."""
        weight = self.to_qkv.weight
        inner = weight.shape[0] // 3
        q = F.linear(normed[:, -query_rows:], weight[:inner])
        k = F.linear(normed, weight[inner : 2 * inner])
        v = F.linear(normed, weight[2 * inner :])
        return q, k, v

    def two_streams(self, x: torch.Tensor, y: torch.Tensor, query_rows: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The attention outputs of both streams: x's exactly as `forward`, and y's with the same
        weights softmax(q k^T) applied to `to_anotherv(y)`. Two attention calls rather than one on
        values concatenated per head: x's call is then the very one `forward` makes."""
        q, k, v = self.to_qkv(self.norm(x)).chunk(3, dim=-1)
        if query_rows is not None:
            q = q[:, -query_rows:]
        x_out = self.to_out(attention(q, k, v, self.heads, self.head_dim))
        y_out = self.to_yout(attention(q, k, self.to_anotherv(y), self.heads, self.head_dim))
        return x_out, y_out


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
    """`gmae_decoder`: pre-norm transformer layers [attention, feed-forward] and a final LayerNorm;
    with the feature stream, layers [attention, feed-forward, the feature stream's feed-forward]
    and `y_norm` (the public code's `InstillTransformer`, whose parameter names these are)."""

    def __init__(self, cfg: C4GConfig):
        super().__init__()
        f = cfg.feature_dim

        def layer() -> nn.ModuleList:
            modules = [DecoderAttention(cfg.decoder_dim, cfg.decoder_heads, cfg.decoder_head_dim, f), FeedForward(cfg.decoder_dim, cfg.decoder_mlp)]
            if f > 0:
                modules.append(FeedForward(f, 2 * f))
            return nn.ModuleList(modules)

        self.layers = nn.ModuleList(layer() for _ in range(cfg.decoder_depth))
        self.norm = nn.LayerNorm(cfg.decoder_dim)
        if f > 0:
            self.y_norm = nn.LayerNorm(f)

    def forward(self, x: torch.Tensor, query_rows: int | None = None, first_qkv: torch.Tensor | None = None) -> torch.Tensor:
        """x [B, L, D] → [B, L, D], or [B, query_rows, D] when `query_rows` is given. `first_qkv`, when
        given, is the first layer's qkv projection [B, L, 3 inner], computed by the caller
        (`c4g.model.precomputed`)."""
        last = len(self.layers) - 1
        for i, (attn, ff, *_) in enumerate(self.layers):
            rows = query_rows if i == last else None
            qkv = first_qkv if i == 0 else None
            if rows is not None:
                x = x[:, -rows:] + attn(x, rows, qkv)
            else:
                x = x + attn(x, qkv=qkv)
            x = x + ff(x)
        return self.norm(x)

    def two_streams(self, x: torch.Tensor, y: torch.Tensor, query_rows: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """x [B, L, D] and the feature stream y [B, L, F] → both after the last layer and their final
        norms ([B, query_rows, ·] when `query_rows` is given). x follows exactly the steps of `forward`."""
        last = len(self.layers) - 1
        for i, (attn, ff, ff_y) in enumerate(self.layers):
            rows = query_rows if i == last else None
            x_attn, y_attn = attn.two_streams(x, y, rows)
            if rows is not None:
                x, y = x[:, -rows:], y[:, -rows:]
            x = x + x_attn
            y = y + y_attn
            x = x + ff(x)
            y = y + ff_y(y)
        return self.norm(x), self.y_norm(y)


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
