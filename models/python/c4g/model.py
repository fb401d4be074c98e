"""`C4G`: the whole model, with the official checkpoint's parameter names (minus its `encoder.` prefix).

encode: frames [T, 3, H, W] in [-1, 1] → features [T, P, C]
decode: features + normalised context times [B, T] + normalised target times [B] → Gaussians [B, N, ...]
decode_features: the same plus 2D feature maps [T, P, F] → per-Gaussian features [B, N, F]
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .aggregator import Aggregator
from .attention import attention
from .config import C4GConfig
from .decoder import FeatureDecoder, GaussianDecoder, SinusoidalTimeEmbedding, activate, to_canonical


class Backbone(nn.Module):
    """VGGT with every head removed: only `aggregator` remains (C4G predicts no cameras)."""

    def __init__(self, cfg: C4GConfig):
        super().__init__()
        self.aggregator = Aggregator(cfg)


class C4G(nn.Module):
    def __init__(self, cfg: C4GConfig):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        d = cfg.decoder_dim
        self.backbone = Backbone(cfg)
        self.gaussian_tokens = nn.Parameter(torch.zeros(cfg.queries, d))
        anchors = torch.zeros(cfg.queries, 3, dtype=torch.int64)
        anchors[:, 2] = 1
        self.register_buffer("anchor_positions", anchors)
        self.time_embedding = SinusoidalTimeEmbedding(cfg.time_dim)
        self.time_mlp = nn.Sequential(nn.Linear(cfg.time_dim, cfg.time_dim), nn.ReLU(), nn.Linear(cfg.time_dim, d), nn.ReLU())
        self.gmae_decoder = GaussianDecoder(cfg)
        self.gmae_to_gaussians = nn.Linear(d, 14)
        self.feature_decoder = FeatureDecoder(cfg) if cfg.feature_dim > 0 else None

    # -- encoder -----------------------------------------------------------------------------------
    def encode(self, frames: torch.Tensor, **precomputed) -> torch.Tensor:
        return self.backbone.aggregator(frames, **precomputed)

    # -- decoder -----------------------------------------------------------------------------------
    def time_embeddings(self, context_times: torch.Tensor, target_times: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The time MLP's embeddings of the context times [B, T, D] and of the target times [B, D]."""
        return self.time_mlp(self.time_embedding(context_times)), self.time_mlp(self.time_embedding(target_times))

    def time_conditioned_tokens(
        self, features: torch.Tensor, context_times: torch.Tensor, target_times: torch.Tensor
    ) -> torch.Tensor:
        """[context tokens + their frame's time embedding ; queries + the target's] → [B, T*P + N, D]."""
        return self.tokens_with_embeddings(features, *self.time_embeddings(context_times, target_times))

    def tokens_with_embeddings(self, features: torch.Tensor, context_emb: torch.Tensor, target_emb: torch.Tensor) -> torch.Tensor:
        """`time_conditioned_tokens` from the embeddings `time_embeddings` returns."""
        t, p, d = features.shape
        b = target_emb.shape[0]
        context = (features[None] + context_emb[:, :, None, :]).reshape(b, t * p, d)
        queries = self.gaussian_tokens[None] + target_emb[:, None, :]
        return torch.cat((context, queries), dim=1)

    def decode_raw(
        self, features: torch.Tensor, context_times: torch.Tensor, target_times: torch.Tensor, query_rows_only: bool = True
    ) -> torch.Tensor:
        """Raw head output [B, N, 14]. `query_rows_only=False` runs the last layer on every row, as the
        reference does (the result is the same; the export uses the cheaper form)."""
        n = self.cfg.queries
        x = self.time_conditioned_tokens(features, context_times, target_times)
        x = self.gmae_decoder(x, query_rows=n if query_rows_only else None)
        return self.gmae_to_gaussians(x[:, -n:])

    def decode(self, features, context_times, target_times, query_rows_only: bool = True) -> dict[str, torch.Tensor]:
        """Activated Gaussians in the reference's parameterisation (see `decoder.activate`)."""
        raw = self.decode_raw(features, context_times, target_times, query_rows_only)
        return activate(raw, self.anchor_positions.to(raw.dtype))

    def decode_canonical(self, features, context_times, target_times) -> torch.Tensor:
        """Gaussians [B, N, 14] in the service's canonical layout (docs/package.md)."""
        return to_canonical(self.decode(features, context_times, target_times))

    # -- feature lifting ---------------------------------------------------------------------------
    def decode_features(
        self, features: torch.Tensor, context_times: torch.Tensor, target_times: torch.Tensor, feature_maps: torch.Tensor
    ) -> torch.Tensor:
        """Per-Gaussian features [B, N, F] from 2D feature maps [T, P, F] (one vector per patch)."""
        if self.feature_decoder is None:
            raise ValueError("this model has no feature decoder (feature_dim = 0)")
        cfg, fd = self.cfg, self.feature_decoder
        n, d = cfg.queries, cfg.decoder_dim
        b = target_times.shape[0]
        x = self.time_conditioned_tokens(features, context_times, target_times)
        maps = F.pad(feature_maps, (0, d - feature_maps.shape[-1])).reshape(1, -1, d).expand(b, -1, -1)
        f = torch.cat((maps, self.gaussian_tokens[None].expand(b, -1, -1)), dim=1)
        last = len(self.gmae_decoder.layers) - 1
        heads, head_dim = cfg.decoder_heads, cfg.decoder_head_dim
        for i, ((attn, ff), fl) in enumerate(zip(self.gmae_decoder.layers, fd.layers)):
            keep = slice(-n, None) if i == last else slice(None)
            q, k, v = attn.to_qkv(attn.norm(x)).chunk(3, dim=-1)
            # One attention call for both streams: the same weights softmax(q k^T) apply to the
            # Gaussian values and the feature values, concatenated per head.
            values = torch.cat(
                (v.reshape(b, -1, heads, 1, head_dim), fl["to_v"](f).reshape(b, -1, heads, 1, head_dim)), dim=3
            ).reshape(b, -1, heads * 2 * head_dim)
            out = attention(q[:, keep], k, values, heads, head_dim).reshape(b, -1, heads, 2, head_dim)
            x = x[:, keep] + attn.to_out(out[:, :, :, 0].reshape(b, -1, heads * head_dim))
            x = x + ff(x)
            f = f[:, keep] + fl["to_out"](out[:, :, :, 1].reshape(b, -1, heads * head_dim))
            f = f + fl["ff"](f)
        return fd.head(fd.norm(f))
