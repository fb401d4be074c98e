"""`C4G`: the whole model, with the official checkpoint's parameter names (minus its `encoder.` prefix).

encode: frames [T, 3, H, W] in [-1, 1] → features [T, P, C]
decode: features + normalised context times [B, T] + normalised target times [B] → Gaussians [B, N, ...]
decode_with_features: the same plus 2D feature maps [T, P, F] → Gaussians and per-Gaussian
features [B, N, F] (the feature stream, `cfg.feature_dim` > 0; see `decoder`)
"""

from __future__ import annotations

import re

import torch
from torch import nn

from .aggregator import Aggregator
from .config import C4GConfig
from .decoder import GaussianDecoder, SinusoidalTimeEmbedding, activate, to_canonical

# The feature stream's parameters (official-layout names, minus the `encoder.` prefix): inside the
# decoder's layers `to_anotherv`, `to_yout` and the third module (y's MLP), `y_norm`, and beside it
# the feature stream's query tokens and its head. Nothing else depends on them.
FEATURE_STREAM = re.compile(
    r"^(gmae_decoder\.layers\.\d+\.(0\.to_anotherv|0\.to_yout|2)\.|gmae_decoder\.y_norm\.|gaussian_tokens_feature$|feature_gmae_to_gaussians\.)"
)


def is_feature_stream(name: str) -> bool:
    """Whether the parameter `name` belongs to the feature stream."""
    return FEATURE_STREAM.match(name) is not None


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
        if cfg.feature_dim > 0:
            # The feature stream's query-position tokens (its learnable tokens at the feature's own
            # width) and the linear head from each query's final y to its Gaussian's feature, named as
            # in the public code (`gaussian_tokens_feature`, `feature_gmae_to_gaussians`).
            f = cfg.feature_dim
            self.gaussian_tokens_feature = nn.Parameter(torch.zeros(cfg.queries, f))
            self.feature_gmae_to_gaussians = nn.Linear(f, f)

    @property
    def has_feature_stream(self) -> bool:
        return self.cfg.feature_dim > 0

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
    def feature_tokens(self, feature_maps: torch.Tensor, batch: int) -> torch.Tensor:
        """The feature stream's input [B, T*P + N, F]: each context frame's 2D feature map, one F-wide
        vector per patch (in the order of the context tokens), then the feature query tokens. y gets
        no time embedding: time reaches it only through x's attention weights."""
        t, p, f = feature_maps.shape
        context = feature_maps.reshape(1, t * p, f).expand(batch, -1, -1)
        return torch.cat((context, self.gaussian_tokens_feature[None].expand(batch, -1, -1)), dim=1)

    def decode_raw_with_features(
        self, features, context_times, target_times, feature_maps, query_rows_only: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw head output [B, N, 14] (equal to `decode_raw`'s) and per-Gaussian features [B, N, F]."""
        if not self.has_feature_stream:
            raise ValueError("this model has no feature stream (feature_dim = 0)")
        n = self.cfg.queries
        # Checked in PyTorch only: an exported graph's shapes are the engine's contract to check.
        if not torch.jit.is_tracing() and feature_maps.shape != (*features.shape[:2], self.cfg.feature_dim):
            raise ValueError(f"feature maps {tuple(feature_maps.shape)} do not match features {tuple(features.shape)} at width {self.cfg.feature_dim}")
        x = self.time_conditioned_tokens(features, context_times, target_times)
        y = self.feature_tokens(feature_maps.to(x.dtype), x.shape[0])
        x, y = self.gmae_decoder.two_streams(x, y, query_rows=n if query_rows_only else None)
        return self.gmae_to_gaussians(x[:, -n:]), self.feature_gmae_to_gaussians(y[:, -n:])

    def decode_with_features(self, features, context_times, target_times, feature_maps) -> tuple[torch.Tensor, torch.Tensor]:
        """Gaussians [B, N, 14] in the canonical layout and the per-Gaussian features [B, N, F] lifted
        from `feature_maps` [T, P, F] (one F-wide vector per patch of each context frame)."""
        raw, lifted = self.decode_raw_with_features(features, context_times, target_times, feature_maps)
        return to_canonical(activate(raw, self.anchor_positions.to(raw.dtype))), lifted

    def decode_features(self, features, context_times, target_times, feature_maps) -> torch.Tensor:
        """Per-Gaussian features [B, N, F] alone (see `decode_with_features`)."""
        return self.decode_raw_with_features(features, context_times, target_times, feature_maps)[1]
