"""The decoder's precomputed form: the first layer's qkv projection of the context features, done
once per clip instead of once per target.

The first decoder layer computes qkv = W · LN(x) for every token x = F + e (a context token or a
query F, plus a time embedding e). LayerNorm is affine per token: with x̃ = x − mean(x),
LN(x) = γ ⊙ x̃ / σ(x) + β and σ(x)² = mean(x̃²) + eps. Since x̃ = F̃ + ẽ (F̃, ẽ: the token and the
embedding, each centred),

    W · LN(F + e) = [ (Wγ) F̃ + (Wγ) ẽ ] / σ + W β,          (Wγ) = W · diag(γ)
    σ² = var(F) + 2 F̃ · ẽ / d + var(e) + eps                 (every variance centred)

(Wγ) F̃ needs only the token. For a context token it depends on the clip's features alone: the
**context projection** [T, P, 3 inner], computed once per clip by `ContextProjection` (the package's
`context_projection.onnx`) and kept with the encoding. For a query it is a constant of the package.
Per target, what is left of the layer's projection is (Wγ) ẽ for each time embedding (one vector
per context frame and one for the target), one dot product F̃ · ẽ per token, and an element-wise
scale and shift: the layer-1 projection (2 · L · d · 3 inner FLOP a target) leaves the per-target
cost. The result equals the plain decoder's up to float rounding (`tests/model/test_precomputed.py`).

The variance is assembled from centred parts, never as E[x²] − mean², so that a token with a large
mean loses no precision; the centred query constants are computed in float64.
"""

from __future__ import annotations

import torch
from torch import nn

from .decoder import activate, to_canonical
from .network import C4G


def _first_layer(model: C4G):
    return model.gmae_decoder.layers[0][0]


def _weight_gamma(model: C4G) -> torch.Tensor:
    """(Wγ) = W · diag(γ) of the first layer, [3 inner, d], in float64."""
    attn = _first_layer(model)
    return attn.to_qkv.weight.detach().double() * attn.norm.weight.detach().double()


class ContextProjection(nn.Module):
    """features [T, P, d] → the context projection (Wγ) F̃ [T, P, 3 inner] (F̃: each token centred)."""

    def __init__(self, model: C4G):
        super().__init__()
        dtype = model.gaussian_tokens.dtype
        self.register_buffer("weight_gamma_t", _weight_gamma(model).T.contiguous().to(dtype))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        centred = features - features.mean(dim=-1, keepdim=True)
        return centred @ self.weight_gamma_t


class PrecomputedDecoder(nn.Module):
    """The Gaussian decoder fed the context projection instead of computing its first layer's qkv
    projection; every other layer is the model's own. The query constants are computed here, in
    float64, from the model's weights (which this module shares, not copies)."""

    def __init__(self, model: C4G):
        super().__init__()
        self.model = model
        attn = _first_layer(model)
        dtype = model.gaussian_tokens.dtype
        self.eps = float(attn.norm.eps)
        self.width = float(model.cfg.decoder_dim)
        with torch.no_grad():
            wg = _weight_gamma(model)
            queries = model.gaussian_tokens.detach().double()
            centred = queries - queries.mean(dim=-1, keepdim=True)
            self.register_buffer("weight_gamma_t", wg.T.contiguous().to(dtype))  # [d, 3 inner]
            self.register_buffer("weight_beta", (attn.to_qkv.weight.detach().double() @ attn.norm.bias.detach().double()).to(dtype))
            self.register_buffer("query_projection", (centred @ wg.T).to(dtype))  # [N, 3 inner]
            self.register_buffer("query_centred_t", centred.T.contiguous().to(dtype))  # [d, N]
            self.register_buffer("query_variance", centred.pow(2).mean(dim=-1).to(dtype))  # [N]

    def _normalised_projection(
        self, projection: torch.Tensor, variance: torch.Tensor, cross: torch.Tensor, centred_embedding: torch.Tensor
    ) -> torch.Tensor:
        """[(Wγ) F̃ + (Wγ) ẽ] / σ + W β for rows of tokens sharing one embedding: their projection
        (Wγ) F̃ [..., rows, 3 inner], variance [..., rows] and cross term F̃ · ẽ / d [..., rows], and
        the centred embedding ẽ [..., d]."""
        embedding_variance = centred_embedding.pow(2).mean(dim=-1, keepdim=True)
        inverse_sigma = torch.rsqrt(variance + 2.0 * cross + embedding_variance + self.eps)
        shift = (centred_embedding @ self.weight_gamma_t).unsqueeze(-2)
        return (projection + shift) * inverse_sigma.unsqueeze(-1) + self.weight_beta

    def first_qkv(
        self,
        features: torch.Tensor,
        context_projection: torch.Tensor,
        context_emb: torch.Tensor,
        target_emb: torch.Tensor,
        query_indices: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """The first layer's to_qkv(norm(tokens)) [B, T*P + N, 3 inner], token order as
        `C4G.time_conditioned_tokens`; with `query_indices` [Q], only those queries' rows
        (`c4g.model.query_subset`)."""
        t, p, _ = features.shape
        b = target_emb.shape[0]
        centred = features - features.mean(dim=-1, keepdim=True)  # [T, P, d]
        variance = centred.pow(2).mean(dim=-1)  # [T, P]
        context_emb = context_emb - context_emb.mean(dim=-1, keepdim=True)  # [B, T, d]
        # F̃ · ẽ per token, for every target: [T, P, d] @ [T, d, B] → [T, P, B] → [B, T, P].
        cross = (centred @ context_emb.permute(1, 2, 0)).permute(2, 0, 1) / self.width
        context = self._normalised_projection(context_projection[None], variance[None], cross, context_emb)
        target_emb = target_emb - target_emb.mean(dim=-1, keepdim=True)  # [B, d]
        projection, centred_t, query_variance = self.query_projection, self.query_centred_t, self.query_variance
        if query_indices is not None:
            projection, centred_t, query_variance = projection[query_indices], centred_t[:, query_indices], query_variance[query_indices]
        query_cross = (target_emb @ centred_t) / self.width  # [B, N]
        queries = self._normalised_projection(projection, query_variance, query_cross, target_emb)
        return torch.cat((context.reshape(b, t * p, -1), queries), dim=1)

    def decode_raw(
        self,
        features: torch.Tensor,
        context_projection: torch.Tensor,
        context_times: torch.Tensor,
        target_times: torch.Tensor,
        query_indices: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Raw head output [B, N, 14], as `C4G.decode_raw` (the last layer on the query rows only);
        with `query_indices` [Q], [B, Q, 14] of those queries alone (`c4g.model.query_subset`)."""
        m = self.model
        context_emb, target_emb = m.time_embeddings(context_times, target_times)
        x = m.tokens_with_embeddings(features, context_emb, target_emb)
        n = m.cfg.queries
        if query_indices is not None:
            # The query rows are the last N: keep the context rows and the chosen queries. The
            # count is traced from the input's shape, so an exported graph takes any subset.
            n = query_indices.shape[0]
            x = torch.cat((x[:, : -m.cfg.queries], x[:, -m.cfg.queries :][:, query_indices]), dim=1)
        qkv = self.first_qkv(features, context_projection, context_emb, target_emb, query_indices)
        x = m.gmae_decoder(x, query_rows=n, first_qkv=qkv)
        return m.gmae_to_gaussians(x[:, -n:])

    def decode_canonical(self, features, context_projection, context_times, target_times) -> torch.Tensor:
        """Gaussians [B, N, 14] in the service's canonical layout, as `C4G.decode_canonical`."""
        raw = self.decode_raw(features, context_projection, context_times, target_times)
        return to_canonical(activate(raw, self.model.anchor_positions.to(raw.dtype)))

